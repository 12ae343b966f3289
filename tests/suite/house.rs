//! The house rules, checked on the source as it is: which crate may depend on what, no
//! circles between modules, no `Result<_, String>` in the library crates, no function over
//! 200 lines unless a comment says why it must be one (docs/design.md, "Architecture").
//!
//! Each rule reads files of this checkout (and `cargo metadata` for the crates' graph), so
//! it fails on the commit that breaks the rule, naming the place.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Command;

use regex::Regex;

/// The library crates: (crate name, source folder). The binary (`src/main.rs`, `src/cli/`)
/// is not a library: it may use anyhow and strings for its errors.
const LIBRARIES: [(&str, &str); 4] = [
    ("glint", "src"),
    ("glint_format", "crates/format/src"),
    ("glint_numerics", "crates/numerics/src"),
    ("glint_devices", "crates/devices/src"),
];

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Every `.rs` file under `dir` of the library (the binary's files left out).
fn library_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                if p.file_name().is_some_and(|n| n == "cli") && d == root().join("src") {
                    continue;
                }
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") && p != root().join("src/main.rs") {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

/// Source text with line comments and string literals emptied (line breaks kept), and the
/// unit tests (`#[cfg(test)] mod tests` to the end of the file) cut off.
fn code_of(text: &str) -> String {
    let comment = Regex::new(r"//[^\n]*").unwrap();
    let string = Regex::new(r#""(\\.|[^"\\])*""#).unwrap();
    // Character literals too, so that a '{' in one does not count as a brace.
    let character = Regex::new(r"'(\\.|[^'\\])'").unwrap();
    let s = comment.replace_all(text, "");
    let s = character.replace_all(&s, "' '");
    let s = string.replace_all(&s, |c: &regex::Captures| {
        "\n".repeat(c[0].matches('\n').count())
    });
    match s.find("#[cfg(test)]\nmod tests") {
        Some(i) => s[..i].to_string(),
        None => s.into_owned(),
    }
}

/// A file's module path inside its crate (`hdr::merge` for `src/hdr/merge.rs`).
fn module_of(src: &Path, file: &Path) -> Vec<String> {
    let rel = file.strip_prefix(src).unwrap().with_extension("");
    let mut m: Vec<String> = rel
        .components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect();
    if matches!(m.last().map(String::as_str), Some("mod" | "lib")) {
        m.pop();
    }
    m
}

/// The module graph of one crate: an edge from a module to every other module of the same
/// crate whose items its code names (`crate::a::b`, `super::x`, `child::y`, and the names in
/// a `use` group `crate::{a, b}`).
fn module_graph(src: &Path) -> BTreeMap<Vec<String>, BTreeSet<Vec<String>>> {
    let files = library_files(src);
    let modules: BTreeMap<Vec<String>, PathBuf> = files
        .iter()
        .map(|f| (module_of(src, f), f.clone()))
        .collect();
    let path = Regex::new(
        r"\b((?:crate|super|self|[a-z_][a-z0-9_]*)(?:::[A-Za-z_][A-Za-z0-9_]*)*)::(\{[^{}]*\}|[A-Za-z_][A-Za-z0-9_]*)",
    )
    .unwrap();
    let mut graph = BTreeMap::new();
    for (m, file) in &modules {
        let code = code_of(&std::fs::read_to_string(file).unwrap());
        let mut edges = BTreeSet::new();
        for c in path.captures_iter(&code) {
            let mut segs: Vec<&str> = c[1].split("::").collect();
            let tails: Vec<String> = if c[2].starts_with('{') {
                c[2][1..c[2].len() - 1]
                    .split(',')
                    .map(|t| t.trim().split("::").next().unwrap_or("").to_string())
                    .collect()
            } else {
                vec![c[2].to_string()]
            };
            let mut base: Vec<String> = match segs[0] {
                "crate" => {
                    segs.remove(0);
                    Vec::new()
                }
                "super" => {
                    let mut b = m.clone();
                    while segs.first() == Some(&"super") {
                        b.pop();
                        segs.remove(0);
                    }
                    b
                }
                "self" => {
                    segs.remove(0);
                    m.clone()
                }
                first => {
                    // A relative path starts at a child module of this one.
                    let mut child = m.clone();
                    child.push(first.to_string());
                    if !modules.contains_key(&child) {
                        continue;
                    }
                    m.clone()
                }
            };
            for s in segs {
                let mut next = base.clone();
                next.push(s.to_string());
                if modules.contains_key(&next) {
                    base = next;
                } else {
                    break;
                }
            }
            for t in &tails {
                let mut next = base.clone();
                next.push(t.clone());
                let target = if modules.contains_key(&next) {
                    next
                } else {
                    base.clone()
                };
                if &target != m && modules.contains_key(&target) {
                    edges.insert(target);
                }
            }
        }
        graph.insert(m.clone(), edges);
    }
    graph
}

/// The circles of a graph: its strongly connected components of more than one module.
fn circles(graph: &BTreeMap<Vec<String>, BTreeSet<Vec<String>>>) -> Vec<Vec<Vec<String>>> {
    // Kosaraju: finish order on the graph, then components on the reversed graph.
    fn visit<'a>(
        v: &'a Vec<String>,
        g: &'a BTreeMap<Vec<String>, BTreeSet<Vec<String>>>,
        seen: &mut BTreeSet<&'a Vec<String>>,
        out: &mut Vec<&'a Vec<String>>,
    ) {
        if !seen.insert(v) {
            return;
        }
        for w in &g[v] {
            visit(w, g, seen, out);
        }
        out.push(v);
    }
    let mut order = Vec::new();
    let mut seen = BTreeSet::new();
    for v in graph.keys() {
        visit(v, graph, &mut seen, &mut order);
    }
    let mut reversed: BTreeMap<Vec<String>, BTreeSet<Vec<String>>> =
        graph.keys().map(|k| (k.clone(), BTreeSet::new())).collect();
    for (a, bs) in graph {
        for b in bs {
            reversed.get_mut(b).unwrap().insert(a.clone());
        }
    }
    let mut seen = BTreeSet::new();
    let mut out = Vec::new();
    for v in order.into_iter().rev() {
        let mut comp = Vec::new();
        visit(v, &reversed, &mut seen, &mut comp);
        if comp.len() > 1 {
            out.push(comp.into_iter().cloned().collect());
        }
    }
    out
}

fn name(m: &[String]) -> String {
    if m.is_empty() {
        "(crate root)".into()
    } else {
        m.join("::")
    }
}

#[test]
fn no_module_is_in_a_circle() {
    let mut found = Vec::new();
    for (krate, dir) in LIBRARIES {
        let graph = module_graph(&root().join(dir));
        for c in circles(&graph) {
            let ties: Vec<String> = c
                .iter()
                .flat_map(|a| {
                    graph[a]
                        .iter()
                        .filter(|b| c.contains(b))
                        .map(move |b| format!("{} -> {}", name(a), name(b)))
                })
                .collect();
            found.push(format!("{krate}: {}", ties.join(", ")));
        }
    }
    assert!(found.is_empty(), "module circles:\n{}", found.join("\n"));
}

/// The circle finder finds a circle: two modules naming each other's items.
#[test]
fn the_circle_finder_sees_a_circle() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path();
    std::fs::write(src.join("lib.rs"), "pub mod a;\npub mod b;\npub mod c;\n").unwrap();
    std::fs::write(src.join("a.rs"), "use crate::b::B;\npub struct A;\n").unwrap();
    std::fs::write(src.join("b.rs"), "use crate::{a::A, c};\npub struct B;\n").unwrap();
    std::fs::write(src.join("c.rs"), "pub struct C(super::b::B);\n").unwrap();
    let graph = module_graph(src);
    let c = circles(&graph);
    // a -> b -> a and b -> c -> b: one circle of all three.
    assert_eq!(c.len(), 1, "{graph:?}");
    assert_eq!(c[0].len(), 3, "{c:?}");
}

/// The normal (not dev, not build) dependencies of every package of the workspace, by
/// package name, transitively, as `cargo metadata` resolves them with default features.
fn dependency_closure() -> BTreeMap<String, BTreeSet<String>> {
    let out = Command::new(env!("CARGO"))
        .args(["metadata", "--format-version", "1"])
        .current_dir(root())
        .output()
        .expect("running cargo metadata");
    assert!(
        out.status.success(),
        "cargo metadata: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let names: BTreeMap<&str, &str> = v["packages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| (p["id"].as_str().unwrap(), p["name"].as_str().unwrap()))
        .collect();
    let mut direct: BTreeMap<&str, Vec<&str>> = BTreeMap::new();
    for n in v["resolve"]["nodes"].as_array().unwrap() {
        let deps = n["deps"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|d| {
                d["dep_kinds"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|k| k["kind"].is_null())
            })
            .map(|d| d["pkg"].as_str().unwrap())
            .collect();
        direct.insert(n["id"].as_str().unwrap(), deps);
    }
    let mut closure = BTreeMap::new();
    for id in direct.keys() {
        let mut seen = BTreeSet::new();
        let mut stack = direct[id].clone();
        while let Some(d) = stack.pop() {
            if seen.insert(names[d].to_string()) {
                stack.extend(direct.get(d).into_iter().flatten());
            }
        }
        closure.insert(names[id].to_string(), seen);
    }
    closure
}

#[test]
fn the_numerics_and_format_crates_stay_plain() {
    let closure = dependency_closure();
    let forbidden = [
        "tokio",
        "serialport",
        "v4l",
        "nokhwa",
        "image",
        "exr",
        "plotters",
        "clap",
        "glint-mock",
        "glint-devices",
    ];
    for krate in ["glint-format", "glint-numerics"] {
        let deps = &closure[krate];
        let bad: Vec<&&str> = forbidden.iter().filter(|f| deps.contains(**f)).collect();
        assert!(bad.is_empty(), "{krate} depends on {bad:?}");
    }
    // And they are the bottom of the house: format depends on no Glint crate, numerics on
    // format alone.
    assert!(!closure["glint-format"]
        .iter()
        .any(|d| d.starts_with("glint")));
    let glint: Vec<&String> = closure["glint-numerics"]
        .iter()
        .filter(|d| d.starts_with("glint"))
        .collect();
    assert_eq!(glint, ["glint-format"]);
}

#[test]
fn only_the_devices_crate_depends_on_the_simulator() {
    let text = |p: &str| std::fs::read_to_string(root().join(p)).unwrap();
    let section = |toml: &str, name: &str| -> String {
        let v: toml::Table = toml.parse().unwrap();
        v.get(name)
            .and_then(|t| t.as_table())
            .map(|t| t.keys().cloned().collect::<Vec<_>>().join(" "))
            .unwrap_or_default()
    };
    for manifest in [
        "Cargo.toml",
        "crates/format/Cargo.toml",
        "crates/numerics/Cargo.toml",
    ] {
        let deps = section(&text(manifest), "dependencies");
        assert!(
            !deps.split(' ').any(|d| d == "glint-mock"),
            "{manifest} names glint-mock among its [dependencies]"
        );
    }
    let devices = section(&text("crates/devices/Cargo.toml"), "dependencies");
    assert!(devices.split(' ').any(|d| d == "glint-mock"));
}

#[test]
fn the_library_crates_return_no_string_errors() {
    let pattern = Regex::new(r"Result<[^;{]*,\s*String\s*>").unwrap();
    let mut found = Vec::new();
    for (_, dir) in LIBRARIES {
        for f in library_files(&root().join(dir)) {
            let code = code_of(&std::fs::read_to_string(&f).unwrap());
            for (i, line) in code.lines().enumerate() {
                if pattern.is_match(line) {
                    found.push(format!(
                        "{}:{}: {}",
                        f.strip_prefix(root()).unwrap().display(),
                        i + 1,
                        line.trim()
                    ));
                }
            }
        }
    }
    assert!(
        found.is_empty(),
        "{} `Result<_, String>` in the library crates (a thiserror enum of the domain carries the context instead):\n{}",
        found.len(),
        found.join("\n")
    );
}

/// A function's lines, from its `fn` line to its closing brace, for every function of a
/// file's code (comments and strings emptied, so braces in them do not count).
fn functions(code: &str) -> Vec<(String, usize, usize)> {
    let head = Regex::new(r"(?m)^[ \t]*(?:pub(?:\([^)]*\))?\s+)?(?:const\s+)?(?:async\s+)?(?:unsafe\s+)?fn\s+([A-Za-z_][A-Za-z0-9_]*)").unwrap();
    let mut out = Vec::new();
    for c in head.captures_iter(code) {
        let start = c.get(0).unwrap().start();
        let rest = &code[start..];
        let (Some(open), semi) = (rest.find('{'), rest.find(';')) else {
            continue;
        };
        if semi.is_some_and(|s| s < open) {
            continue; // a declaration without a body (a trait's)
        }
        let mut depth = 0usize;
        let mut end = None;
        for (i, ch) in rest[open..].char_indices() {
            match ch {
                '{' => depth += 1,
                '}' => {
                    depth -= 1;
                    if depth == 0 {
                        end = Some(open + i);
                        break;
                    }
                }
                _ => {}
            }
        }
        let Some(end) = end else { continue };
        let first = code[..start].matches('\n').count() + 1;
        let last = first + rest[..end].matches('\n').count();
        out.push((c[1].to_string(), first, last - first + 1));
    }
    out
}

#[test]
fn no_function_is_over_200_lines_without_a_reason() {
    let mut found = Vec::new();
    for (_, dir) in LIBRARIES {
        for f in library_files(&root().join(dir)) {
            let text = std::fs::read_to_string(&f).unwrap();
            let raw: Vec<&str> = text.lines().collect();
            for (name, line, len) in functions(&code_of(&text)) {
                // The reason: a comment just above the function saying why it is one
                // ("Long by design: ...").
                let above = raw[line.saturating_sub(12)..line - 1].join("\n");
                if len > 200 && !above.contains("Long by design:") {
                    found.push(format!(
                        "{}:{line}: fn {name} has {len} lines",
                        f.strip_prefix(root()).unwrap().display()
                    ));
                }
            }
        }
    }
    assert!(
        found.is_empty(),
        "functions over 200 lines (split them by job, or say above why one must be long with a comment \"Long by design: ...\"):\n{}",
        found.join("\n")
    );
}
