//! The documentation as a newcomer meets it: a README short enough to read in five minutes
//! whose commands table lists every command `glint --help` shows, links in the README and
//! `docs/` that lead to a file and a heading of this checkout, and no text that points
//! outside the project (a design file or data folder a clone does not have, or the numbers of
//! a tracker users cannot see).
//!
//! The checks on the whole project read the files git tracks (`git ls-files`) and skip
//! binary files; they list every offending line as `file:line: text`, so one run names all
//! there is to fix.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use regex::Regex;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The README's limit: a newcomer reads it in five minutes.
const README_MAX_LINES: usize = 300;

#[test]
fn the_readme_is_at_most_300_lines() {
    let lines = read(&root().join("README.md")).lines().count();
    assert!(
        lines <= README_MAX_LINES,
        "README.md has {lines} lines, more than {README_MAX_LINES}: move the detail into docs/"
    );
}

/// The names a clap help text lists under `Commands:` (one per line, indented by two spaces).
fn listed_commands(help: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut inside = false;
    for line in help.lines() {
        if line.trim_end() == "Commands:" {
            inside = true;
            continue;
        }
        if !inside {
            continue;
        }
        if line.trim().is_empty() || !line.starts_with("  ") {
            break;
        }
        if line.starts_with("   ") {
            continue; // a wrapped description
        }
        if let Some(name) = line.split_whitespace().next() {
            out.push(name.to_string());
        }
    }
    out
}

/// `glint ARGS --help`'s text.
fn help_of(args: &[String]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_glint"))
        .args(args)
        .arg("--help")
        .output()
        .expect("glint runs");
    assert!(
        out.status.success(),
        "glint {} --help failed: {}",
        args.join(" "),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Every command and subcommand of the built binary, as word paths (`["queue", "move"]`):
/// what `glint --help` lists, then what each of those lists, to any depth. Clap's own
/// `help` subcommand is kept at the top (`glint help`) and left out below it.
fn every_command() -> Vec<Vec<String>> {
    let mut out = Vec::new();
    let mut todo: Vec<Vec<String>> = vec![Vec::new()];
    while let Some(path) = todo.pop() {
        for name in listed_commands(&help_of(&path)) {
            if name == "help" && !path.is_empty() {
                continue;
            }
            let mut p = path.clone();
            p.push(name.clone());
            out.push(p.clone());
            if name != "help" {
                todo.push(p);
            }
        }
    }
    out.sort();
    out
}

/// The first cell of a Markdown table row (a `\|` inside it is a pipe of its text).
fn first_cell(row: &str) -> String {
    let body = row.trim().trim_start_matches('|');
    let mut cell = String::new();
    let mut chars = body.chars().peekable();
    while let Some(c) = chars.next() {
        match c {
            '\\' if chars.peek() == Some(&'|') => {
                cell.push('|');
                chars.next();
            }
            '|' => break,
            _ => cell.push(c),
        }
    }
    cell
}

/// The command lines the README's commands table names: every code span starting with
/// `glint ` in a first cell of a table row of its `## Commands` section, split into words
/// (`glint trigger run|capture` gives `["glint", "trigger", "run|capture"]`).
fn readme_table_commands(readme: &str) -> Vec<Vec<String>> {
    let span = Regex::new(r"`([^`]*)`").unwrap();
    let mut out = Vec::new();
    let mut inside = false;
    for line in readme.lines() {
        if line.starts_with("## ") {
            inside = line.trim() == "## Commands";
            continue;
        }
        if !inside || !line.trim_start().starts_with('|') {
            continue;
        }
        for c in span.captures_iter(&first_cell(line)) {
            let words: Vec<String> = c[1].split_whitespace().map(str::to_string).collect();
            if words.first().is_some_and(|w| w == "glint") {
                out.push(words);
            }
        }
    }
    out
}

/// Whether a table entry's words name a command path: `glint` then, word by word, the
/// path's names (a word may offer alternatives, `start|stop`).
fn names(entry: &[String], path: &[String]) -> bool {
    entry.len() > path.len()
        && path
            .iter()
            .zip(&entry[1..])
            .all(|(name, word)| word.split('|').any(|alt| alt == name))
}

#[test]
fn the_readme_commands_table_lists_every_command_of_glint_help() {
    let commands = every_command();
    assert!(
        commands.len() > 20,
        "glint --help lists too few commands to be read right: {commands:?}"
    );
    let table = readme_table_commands(&read(&root().join("README.md")));
    let missing: Vec<String> = commands
        .iter()
        .filter(|path| !table.iter().any(|entry| names(entry, path)))
        .map(|path| format!("glint {}", path.join(" ")))
        .collect();
    assert!(
        missing.is_empty(),
        "README.md's commands table (the first column of the table under \"## Commands\") does not name:\n{}",
        missing.join("\n")
    );
}

/// A text's lines with fenced code blocks blanked (line numbers kept).
fn prose_lines(text: &str) -> Vec<String> {
    let mut fence = false;
    text.lines()
        .map(|line| {
            if line.trim_start().starts_with("```") {
                fence = !fence;
                return String::new();
            }
            if fence {
                String::new()
            } else {
                line.to_string()
            }
        })
        .collect()
}

/// GitHub's anchor for a heading: lower case, every character but letters, digits, `_`, `-`
/// and spaces dropped, spaces as `-`.
fn slug(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter(|c| c.is_alphanumeric() || *c == '_' || *c == '-' || *c == ' ')
        .map(|c| if c == ' ' { '-' } else { c })
        .collect()
}

/// The anchors of a Markdown file's headings (a repeated heading gets `-1`, `-2`, ...).
fn anchors(text: &str) -> Vec<String> {
    let heading = Regex::new(r"^#{1,6}\s+(.*?)\s*#*\s*$").unwrap();
    let mut seen: BTreeMap<String, usize> = BTreeMap::new();
    let mut out = Vec::new();
    for line in prose_lines(text) {
        if let Some(c) = heading.captures(&line) {
            let s = slug(&c[1]);
            let n = seen.entry(s.clone()).or_insert(0);
            out.push(if *n == 0 {
                s.clone()
            } else {
                format!("{s}-{n}")
            });
            *n += 1;
        }
    }
    out
}

/// The Markdown files whose links are checked: README.md, CHANGELOG.md and every `.md`
/// under docs/.
fn markdown_files() -> Vec<PathBuf> {
    let mut out = vec![root().join("README.md")];
    if root().join("CHANGELOG.md").exists() {
        out.push(root().join("CHANGELOG.md"));
    }
    let mut stack = vec![root().join("docs")];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "md") {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

fn relative(p: &Path) -> String {
    p.strip_prefix(root()).unwrap_or(p).display().to_string()
}

#[test]
fn every_relative_link_of_the_readme_and_docs_leads_to_a_file_and_heading() {
    let link = Regex::new(r#"\]\(([^)\s]+)(?:\s+"[^"]*")?\)"#).unwrap();
    let code = Regex::new(r"`[^`]*`").unwrap();
    let scheme = Regex::new(r"^[A-Za-z][A-Za-z0-9+.-]*:").unwrap();
    let project = root().canonicalize().unwrap();
    let mut found = Vec::new();
    for file in markdown_files() {
        let text = read(&file);
        for (i, line) in prose_lines(&text).iter().enumerate() {
            let line = code.replace_all(line, "");
            for c in link.captures_iter(&line) {
                let target = &c[1];
                if scheme.is_match(target) {
                    continue;
                }
                let (path, anchor) = match target.split_once('#') {
                    Some((p, a)) => (p, Some(a)),
                    None => (target, None),
                };
                let at = format!("{}:{}: {target}", relative(&file), i + 1);
                let dest = if path.is_empty() {
                    file.clone()
                } else {
                    file.parent().unwrap().join(path)
                };
                let Ok(dest) = dest.canonicalize() else {
                    found.push(format!("{at}: no such file"));
                    continue;
                };
                if !dest.starts_with(&project) {
                    found.push(format!("{at}: outside the project"));
                    continue;
                }
                if let Some(a) = anchor {
                    let is_md = dest.extension().is_some_and(|x| x == "md");
                    if is_md && !anchors(&read(&dest)).iter().any(|h| h == a) {
                        found.push(format!(
                            "{at}: no heading with that anchor in {}",
                            relative(&dest)
                        ));
                    }
                }
            }
        }
    }
    assert!(
        found.is_empty(),
        "{} broken links:\n{}",
        found.len(),
        found.join("\n")
    );
}

/// The project's text files as git tracks them: (path relative to the root, text). None
/// where git or the checkout is not there (a packaged crate).
fn project_texts() -> Option<Vec<(String, String)>> {
    let out = Command::new("git")
        .args(["ls-files", "-z"])
        .current_dir(root())
        .output()
        .ok()?;
    if !out.status.success() {
        return None;
    }
    let mut texts = Vec::new();
    for name in out.stdout.split(|b| *b == 0).filter(|n| !n.is_empty()) {
        let name = String::from_utf8_lossy(name).into_owned();
        let Ok(bytes) = std::fs::read(root().join(&name)) else {
            continue; // deleted in the work tree
        };
        if bytes[..bytes.len().min(8000)].contains(&0) {
            continue; // binary
        }
        let Ok(text) = String::from_utf8(bytes) else {
            continue; // binary
        };
        texts.push((name, text));
    }
    Some(texts)
}

/// The project's lines that `bad` says are wrong, as `file:line: text`.
fn offending_lines(bad: impl Fn(&str, &str) -> bool) -> Option<Vec<String>> {
    let mut found = Vec::new();
    for (name, text) in project_texts()? {
        for (i, line) in text.lines().enumerate() {
            if bad(&name, line) {
                found.push(format!("{name}:{}: {}", i + 1, line.trim()));
            }
        }
    }
    Some(found)
}

#[test]
fn nothing_in_the_project_points_outside_it() {
    // Spelled in pieces, so that this file does not name what it looks for.
    let design = ["DESIGN", ".md"].concat();
    let shared = ["..", "/shared"].concat();
    let data = [shared.as_str(), "/data"].concat();
    let Some(found) = offending_lines(|name, line| {
        if line.contains(&design) {
            return true;
        }
        if !line.contains(&shared) {
            return false;
        }
        // Tests, benchmarks (the scripts, and the `glint bench` commands' modules) and CI
        // may read the shared data where it is there, and skip where it is not.
        let may_read = name.starts_with("tests/")
            || name.starts_with("benches/")
            || name.starts_with("src/cli/bench")
            || name == ".ci/run";
        !(may_read && line.contains(&data))
    }) else {
        eprintln!("SKIPPED: not a git checkout; the project's files cannot be listed");
        return;
    };
    assert!(
        found.is_empty(),
        "{} lines name {design} (cite docs/design.md and its section instead) or {shared} (not part of a clone; only tests, benchmarks and .ci/run may read {data}):\n{}",
        found.len(),
        found.join("\n")
    );
}

#[test]
fn the_project_names_no_tracker_numbers() {
    let number = Regex::new(r"(?i)\bissues?\s+#?[0-9]+").unwrap();
    let Some(found) = offending_lines(|_, line| number.is_match(line)) else {
        eprintln!("SKIPPED: not a git checkout; the project's files cannot be listed");
        return;
    };
    assert!(
        found.is_empty(),
        "{} lines name an issue by its number, which users cannot look up: say what the thing is instead:\n{}",
        found.len(),
        found.join("\n")
    );
}

/// The link checker's anchors follow GitHub's rules.
#[test]
fn anchors_are_githubs() {
    assert_eq!(
        slug("Fail safe: what Glint refuses and why"),
        "fail-safe-what-glint-refuses-and-why"
    );
    assert_eq!(
        slug("The response file (`glint-response`, version 1)"),
        "the-response-file-glint-response-version-1"
    );
    assert_eq!(slug("## fit/".trim_start_matches("## ")), "fit");
    assert_eq!(
        anchors("# A\n```\n# not a heading\n```\n## A\n"),
        ["a", "a-1"]
    );
}

/// The table reader sees escaped pipes and alternatives.
#[test]
fn the_commands_table_reader_reads_alternatives() {
    let readme = "## Commands\n\n| command | what |\n| --- | --- |\n| `glint queue start\\|stop`, `glint export SESSION` | x \\| y |\n\n## Next\n| `glint other` | |\n";
    let table = readme_table_commands(readme);
    assert_eq!(table.len(), 2, "{table:?}");
    let p = |s: &str| s.split(' ').map(str::to_string).collect::<Vec<_>>();
    assert!(table.iter().any(|e| names(e, &p("queue stop"))));
    assert!(table.iter().any(|e| names(e, &p("export"))));
    assert!(!table.iter().any(|e| names(e, &p("other"))));
    assert!(!table.iter().any(|e| names(e, &p("queue move"))));
}
