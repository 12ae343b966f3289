//! Fuzzing: property tests that mutate every kind of file and reply
//! Glint reads and check, on every case: no panic, every error one line of bounded length
//! (and no out-of-memory), nothing written outside the case's own session folder (but a
//! new camera profile, which must load, beside the rig file `hdr` is given with `--rig`), and the
//! rules of the issue that a mutation can break (a rig value accepted must be finite,
//! bounded and the value given; a frame outside the session fails `verify` and every
//! stage; the lamp is off at the end of every capture; a failed capture says `failed`).
//!
//! Targets: rig files (random edits, and a sweep of every key with every special value),
//! manifests (`verify`/`load`, and every stage), derived files (hdr/, calib/, fit/,
//! validation/ JSON, the camera profile; derived folders made links), frame PNGs (decode,
//! and the stages with the checksum updated), serial lamp replies (the driver alone, and
//! the lamp during a capture), the daemon's journal (torn at every byte of its last records,
//! every byte of two records flipped, lines of garbage, forged records; each replayed),
//! the daemon's `SESSION/events.jsonl` (forged, torn, garbage
//! lines, replayed to `glint follow` after a restart) and its replies and events as the
//! clients read them (a fake daemon on a socket of the test's own).
//!
//! Deterministic: proptest's ChaCha generator with a fixed seed, so CI sees the same cases
//! every run. `GLINT_FUZZ_CASES=N` sets the total number of random cases (default
//! [`DEFAULT_TOTAL`], shared out in fixed proportions, expensive targets getting fewer);
//! `GLINT_FUZZ_SEED=S` draws other cases.
//!
//! A case that runs stages runs in a child process (this test binary again, the ignored
//! test `fuzz_child`) under a 1 GiB address-space limit and a deadline, so a read of
//! `/dev/zero` or an endless loop is a finding, not a dead test run. One session is
//! captured and processed once per run (the template); each case works on a copy.
//!
//! Every case runs to the end and a target collects all distinct findings (a panic's
//! location, an error's shape, a write outside ...) with the smallest input that showed
//! each and the stages it was seen in, so one run lists everything to fix; the test fails
//! if there is any. A finding names its case (`[derived:17]`): see `fuzz_child` to re-run it.
//! Each target's summary also counts, per stage, the cases it succeeded in (how deep the
//! mutated inputs reach; an unmutated case passes every stage).

use std::collections::BTreeMap;
use std::io::{ErrorKind, Read, Write};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Mutex, OnceLock};
use std::time::{Duration, Instant};

use proptest::collection::vec;
use proptest::prelude::*;
use proptest::strategy::ValueTree;
use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};

use super::util::{copy_dir, record, root, small_table};

/// Cases across all targets when `GLINT_FUZZ_CASES` is not set.
pub const DEFAULT_TOTAL: usize = 3000;
/// Longest error message accepted (the path of the file, the key, a quoted value <= 100
/// characters, the fix).
const MAX_MESSAGE: usize = 600;
/// A stage that takes longer than this on a small session is a finding (bounded work).
const SLOW: Duration = Duration::from_secs(10);

// ---------------------------------------------------------------------------------------
// Runner: cases, seed, findings.

/// Shares of the total per target (cheap targets get many cases, stage runs few).
const SHARES: &[(&str, f64)] = &[
    ("rig", 0.60),
    ("serial", 0.08),
    ("capture", 0.01),
    ("png-decode", 0.16),
    ("manifest-load", 0.06),
    ("manifest-stages", 0.013),
    ("derived", 0.013),
    ("png-stages", 0.013),
    ("journal", 0.10),
    ("daemon-events", 0.04),
    ("daemon-replies", 0.1),
];

fn cases(target: &str) -> usize {
    let total = std::env::var("GLINT_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
        .unwrap_or(DEFAULT_TOTAL);
    let share = SHARES
        .iter()
        .find(|(t, _)| *t == target)
        .map(|(_, s)| *s)
        .expect("a known target");
    ((total as f64 * share).round() as usize).max(1)
}

fn runner(target: &str) -> TestRunner {
    let seed: u64 = std::env::var("GLINT_FUZZ_SEED")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(13);
    let mut bytes = [0u8; 32];
    bytes[..8].copy_from_slice(&seed.to_le_bytes());
    for (i, b) in target.bytes().enumerate() {
        bytes[8 + i % 24] ^= b;
    }
    let config = Config {
        cases: cases(target) as u32,
        rng_algorithm: RngAlgorithm::ChaCha,
        failure_persistence: None,
        ..Config::default()
    };
    TestRunner::new_with_rng(config, TestRng::from_seed(RngAlgorithm::ChaCha, &bytes))
}

/// Draw `n` values of `s` from the runner's generator.
fn draw<S: Strategy>(r: &mut TestRunner, s: &S) -> S::Value {
    s.new_tree(r).expect("strategy draws").current()
}

/// One distinct finding.
#[derive(Default)]
struct Entry {
    count: usize,
    /// The shortest input that showed it.
    input: String,
    detail: String,
    /// The stages (library calls) it was seen in.
    stages: std::collections::BTreeSet<String>,
}

/// Distinct findings of one target.
#[derive(Default)]
struct Findings {
    seen: BTreeMap<String, Entry>,
    /// Per stage, the cases it succeeded in (how deep the inputs reach).
    passed: BTreeMap<String, usize>,
}

impl Findings {
    fn add(&mut self, key: String, stage: &str, input: &str, detail: String) {
        let e = self.seen.entry(key).or_insert_with(|| Entry {
            input: input.to_string(),
            detail: detail.clone(),
            ..Default::default()
        });
        e.count += 1;
        e.stages.insert(stage.to_string());
        if input.len() < e.input.len() {
            e.input = input.to_string();
            e.detail = detail;
        }
    }

    fn merge(&mut self, other: Findings) {
        for (k, o) in other.seen {
            let e = self.seen.entry(k).or_insert_with(|| Entry {
                input: o.input.clone(),
                detail: o.detail.clone(),
                ..Default::default()
            });
            e.count += o.count;
            e.stages.extend(o.stages);
            if o.input.len() < e.input.len() {
                e.input = o.input;
                e.detail = o.detail;
            }
        }
        for (k, n) in other.passed {
            *self.passed.entry(k).or_default() += n;
        }
    }

    /// Check one stage's outcome.
    fn check<T>(&mut self, stage: &str, input: &str, out: Outcome<T>) -> Option<T> {
        match out {
            Outcome::Panic(p) => {
                self.add(
                    format!("panic at {}", p.location),
                    stage,
                    input,
                    format!(
                        "panicked: {} (first Glint frame: {})",
                        p.message, p.glint_frame
                    ),
                );
                None
            }
            Outcome::Err(e) => {
                let l = e.to_lowercase();
                if l.contains("out of memory") || l.contains("memory allocation") {
                    self.add(
                        format!(
                            "ran out of memory (an unbounded read; the child's limit is {} GiB)",
                            CHILD_MEMORY >> 30
                        ),
                        stage,
                        input,
                        format!("error: {}", show(&e)),
                    );
                }
                if let Some(what) = bad_message(&e) {
                    self.add(
                        format!("{what}: {}", shape(&e)),
                        stage,
                        input,
                        format!("error: {}", show(&e)),
                    );
                }
                None
            }
            Outcome::Ok(v) => {
                *self.passed.entry(stage.to_string()).or_default() += 1;
                Some(v)
            }
        }
    }

    /// One line per finding, for a child process to hand back.
    fn to_lines(&self) -> String {
        let clean = |s: &str| s.replace(['\t', '\n', '\r'], " ");
        let mut out = String::new();
        for (k, e) in &self.seen {
            let stages: Vec<&str> = e.stages.iter().map(String::as_str).collect();
            out.push_str(&format!(
                "finding\t{}\t{}\t{}\t{}\t{}\n",
                clean(k),
                e.count,
                clean(&e.input),
                clean(&e.detail),
                clean(&stages.join(","))
            ));
        }
        for (k, n) in &self.passed {
            out.push_str(&format!("passed\t{}\t{n}\n", clean(k)));
        }
        out
    }

    fn finish(self, target: &str, n: usize, start: Instant) {
        let passed: Vec<String> = self
            .passed
            .iter()
            .map(|(k, c)| format!("{k} {c}"))
            .collect();
        eprintln!(
            "fuzz {target}: {n} cases, {} distinct findings, {:.1} s; succeeded: {}",
            self.seen.len(),
            start.elapsed().as_secs_f64(),
            if passed.is_empty() {
                "none".to_string()
            } else {
                passed.join(", ")
            }
        );
        if self.seen.is_empty() {
            return;
        }
        let mut s = format!("fuzz {target}: {} distinct findings\n", self.seen.len());
        for (k, e) in &self.seen {
            let stages: Vec<&str> = e.stages.iter().map(String::as_str).collect();
            s.push_str(&format!(
                "- {k}\n    in: {}\n    cases: {}\n    input: {}\n    {}\n",
                stages.join(", "),
                e.count,
                e.input,
                e.detail
            ));
        }
        eprintln!("{s}");
        panic!("{s}");
    }
}

/// What is wrong with an error message, if anything.
fn bad_message(e: &str) -> Option<&'static str> {
    if e.contains('\n') || e.contains('\r') {
        Some("multi-line error")
    } else if e.chars().count() > MAX_MESSAGE {
        Some("overlong error")
    } else if e.trim().is_empty() {
        Some("empty error")
    } else {
        None
    }
}

/// An error's shape for grouping: the file's path left out, digits and runs of one
/// character folded, cut short.
fn shape(e: &str) -> String {
    let e = match e.find(": ") {
        Some(i) if e[..i].starts_with('/') => &e[i + 2..],
        _ => e,
    };
    let mut out = String::new();
    let mut chars = e.chars();
    while let Some(c) = chars.next() {
        match c {
            // A quoted value: its content left out.
            '"' | '`' => {
                out.push(c);
                out.push('…');
                for d in chars.by_ref() {
                    if d == c {
                        break;
                    }
                }
                out.push(c);
            }
            d if d.is_ascii_digit() => {
                if !out.ends_with('#') {
                    out.push('#');
                }
            }
            d if d.is_control() => out.push('~'),
            d => out.push(d),
        }
        if out.chars().count() >= 28 {
            break;
        }
    }
    out
}

/// An error for the findings list: one line, at most 300 characters.
fn show(e: &str) -> String {
    let s: String = e
        .chars()
        .take(300)
        .collect::<String>()
        .escape_debug()
        .to_string();
    if e.chars().count() > 300 {
        format!("{s}… ({} characters)", e.chars().count())
    } else {
        s
    }
}

// ---------------------------------------------------------------------------------------
// Panics: caught, with the location and the first frame in Glint's own code.

struct Panic {
    location: String,
    message: String,
    glint_frame: String,
}

enum Outcome<T> {
    Ok(T),
    Err(String),
    Panic(Panic),
}

thread_local! {
    static LAST_PANIC: std::cell::RefCell<Option<Panic>> = const { std::cell::RefCell::new(None) };
    static FUZZING: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}
static ACTIVE: AtomicUsize = AtomicUsize::new(0);
static STRAY: Mutex<Option<Panic>> = Mutex::new(None);

fn install_hook() {
    static ONCE: OnceLock<()> = OnceLock::new();
    ONCE.get_or_init(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            let fuzz_thread = FUZZING.with(|f| f.get());
            if !fuzz_thread {
                previous(info);
                if ACTIVE.load(Ordering::SeqCst) == 0 {
                    return;
                }
            }
            let message = info
                .payload()
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| info.payload().downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "(no message)".into());
            let location = info
                .location()
                .map(|l| format!("{}:{}", short_path(l.file()), l.line()))
                .unwrap_or_else(|| "?".into());
            let bt = std::backtrace::Backtrace::force_capture().to_string();
            let here = env!("CARGO_MANIFEST_DIR");
            let glint_frame = bt
                .lines()
                .map(str::trim)
                .filter_map(|l| l.strip_prefix("at "))
                .find(|l| {
                    (l.starts_with(&format!("{here}/src/")) || l.starts_with("./src/"))
                        || l.starts_with("src/")
                        || l.starts_with(&format!("{here}/mock/src/"))
                })
                .map(short_path)
                .unwrap_or_else(|| "none in the backtrace".into());
            let p = Panic {
                location,
                message: show(&message),
                glint_frame,
            };
            if fuzz_thread {
                LAST_PANIC.with(|l| *l.borrow_mut() = Some(p));
            } else {
                *STRAY.lock().unwrap_or_else(|e| e.into_inner()) = Some(p);
            }
        }));
    });
}

fn short_path(p: &str) -> String {
    let here = env!("CARGO_MANIFEST_DIR");
    let p = p
        .strip_prefix(here)
        .map(|s| s.trim_start_matches('/'))
        .unwrap_or(p);
    match p.find("/registry/src/") {
        Some(i) => {
            let rest = &p[i + "/registry/src/".len()..];
            rest.split_once('/').map_or(rest, |(_, r)| r).to_string()
        }
        None => p.to_string(),
    }
}

/// Run `f` catching panics; its error as text.
fn guarded<T, E: std::fmt::Display>(f: impl FnOnce() -> Result<T, E>) -> Outcome<T> {
    install_hook();
    FUZZING.with(|x| x.set(true));
    ACTIVE.fetch_add(1, Ordering::SeqCst);
    let r = catch_unwind(AssertUnwindSafe(f));
    ACTIVE.fetch_sub(1, Ordering::SeqCst);
    FUZZING.with(|x| x.set(false));
    match r {
        Ok(Ok(v)) => Outcome::Ok(v),
        Ok(Err(e)) => Outcome::Err(e.to_string()),
        Err(_) => {
            let p = LAST_PANIC
                .with(|l| l.borrow_mut().take())
                .or_else(|| STRAY.lock().unwrap_or_else(|e| e.into_inner()).take())
                .unwrap_or(Panic {
                    location: "?".into(),
                    message: "?".into(),
                    glint_frame: "?".into(),
                });
            Outcome::Panic(p)
        }
    }
}

// ---------------------------------------------------------------------------------------
// Documents: TOML and JSON as one tree, so one set of mutations serves both.

#[derive(Debug, Clone, PartialEq)]
enum Node {
    Null,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    Arr(Vec<Node>),
    Obj(Vec<(String, Node)>),
}

#[derive(Debug, Clone, PartialEq)]
enum Seg {
    Key(String),
    Idx(usize),
}

fn path_name(p: &[Seg]) -> String {
    let mut s = String::new();
    for seg in p {
        match seg {
            Seg::Key(k) => {
                if !s.is_empty() {
                    s.push('.');
                }
                s.push_str(k);
            }
            Seg::Idx(i) => s.push_str(&format!("[{i}]")),
        }
    }
    if s.is_empty() {
        "(the whole document)".into()
    } else {
        s
    }
}

impl Node {
    fn from_toml(v: &toml::Value) -> Node {
        match v {
            toml::Value::String(s) => Node::Str(s.clone()),
            toml::Value::Integer(i) => Node::Int(*i),
            toml::Value::Float(f) => Node::Float(*f),
            toml::Value::Boolean(b) => Node::Bool(*b),
            toml::Value::Datetime(d) => Node::Str(d.to_string()),
            toml::Value::Array(a) => Node::Arr(a.iter().map(Node::from_toml).collect()),
            toml::Value::Table(t) => Node::Obj(
                t.iter()
                    .map(|(k, v)| (k.clone(), Node::from_toml(v)))
                    .collect(),
            ),
        }
    }

    /// None for a null (TOML has none: the key is left out).
    fn to_toml(&self) -> Option<toml::Value> {
        Some(match self {
            Node::Null => return None,
            Node::Bool(b) => toml::Value::Boolean(*b),
            Node::Int(i) => toml::Value::Integer(*i),
            Node::Float(f) => toml::Value::Float(*f),
            Node::Str(s) => toml::Value::String(s.clone()),
            Node::Arr(a) => toml::Value::Array(a.iter().filter_map(Node::to_toml).collect()),
            Node::Obj(o) => toml::Value::Table(
                o.iter()
                    .filter_map(|(k, v)| v.to_toml().map(|v| (k.clone(), v)))
                    .collect(),
            ),
        })
    }

    fn toml_text(&self) -> String {
        match self.to_toml() {
            Some(toml::Value::Table(t)) => toml::to_string(&t).unwrap_or_default(),
            _ => String::new(),
        }
    }

    fn from_json(v: &serde_json::Value) -> Node {
        use serde_json::Value as V;
        match v {
            V::Null => Node::Null,
            V::Bool(b) => Node::Bool(*b),
            V::Number(n) => n
                .as_i64()
                .map(Node::Int)
                .unwrap_or_else(|| Node::Float(n.as_f64().unwrap_or(f64::NAN))),
            V::String(s) => Node::Str(s.clone()),
            V::Array(a) => Node::Arr(a.iter().map(Node::from_json).collect()),
            V::Object(o) => Node::Obj(
                o.iter()
                    .map(|(k, v)| (k.clone(), Node::from_json(v)))
                    .collect(),
            ),
        }
    }

    /// JSON text; a non-finite float is written as the bare word (`NaN`, `1e999`), which
    /// is what another tool's writer might leave.
    fn json_text(&self, out: &mut String) {
        match self {
            Node::Null => out.push_str("null"),
            Node::Bool(b) => out.push_str(if *b { "true" } else { "false" }),
            Node::Int(i) => out.push_str(&i.to_string()),
            Node::Float(f) if f.is_nan() => out.push_str("NaN"),
            Node::Float(f) if f.is_infinite() => {
                out.push_str(if *f > 0.0 { "1e999" } else { "-1e999" })
            }
            Node::Float(f) => out.push_str(&format!("{f:?}")),
            Node::Str(s) => out.push_str(&serde_json::to_string(s).unwrap()),
            Node::Arr(a) => {
                out.push('[');
                for (i, v) in a.iter().enumerate() {
                    if i > 0 {
                        out.push(',');
                    }
                    v.json_text(out);
                }
                out.push(']');
            }
            Node::Obj(o) => {
                out.push_str("{\n");
                for (i, (k, v)) in o.iter().enumerate() {
                    if i > 0 {
                        out.push_str(",\n");
                    }
                    out.push_str(&serde_json::to_string(k).unwrap());
                    out.push(':');
                    v.json_text(out);
                }
                out.push_str("\n}");
            }
        }
    }

    fn json(&self) -> String {
        let mut s = String::new();
        self.json_text(&mut s);
        s
    }

    /// Every path (containers too), depth first.
    fn paths(&self, prefix: &mut Vec<Seg>, out: &mut Vec<Vec<Seg>>) {
        out.push(prefix.clone());
        match self {
            Node::Arr(a) => {
                for (i, v) in a.iter().enumerate() {
                    prefix.push(Seg::Idx(i));
                    v.paths(prefix, out);
                    prefix.pop();
                }
            }
            Node::Obj(o) => {
                for (k, v) in o {
                    prefix.push(Seg::Key(k.clone()));
                    v.paths(prefix, out);
                    prefix.pop();
                }
            }
            _ => {}
        }
    }

    fn get(&self, p: &[Seg]) -> Option<&Node> {
        let Some((first, rest)) = p.split_first() else {
            return Some(self);
        };
        match (self, first) {
            (Node::Arr(a), Seg::Idx(i)) => a.get(*i)?.get(rest),
            (Node::Obj(o), Seg::Key(k)) => o.iter().find(|(n, _)| n == k)?.1.get(rest),
            _ => None,
        }
    }

    fn get_mut(&mut self, p: &[Seg]) -> Option<&mut Node> {
        let Some((first, rest)) = p.split_first() else {
            return Some(self);
        };
        match (self, first) {
            (Node::Arr(a), Seg::Idx(i)) => a.get_mut(*i)?.get_mut(rest),
            (Node::Obj(o), Seg::Key(k)) => o.iter_mut().find(|(n, _)| n == k)?.1.get_mut(rest),
            _ => None,
        }
    }

    fn delete(&mut self, p: &[Seg]) {
        let Some((last, parent)) = p.split_last() else {
            return;
        };
        match (self.get_mut(parent), last) {
            (Some(Node::Arr(a)), Seg::Idx(i)) if *i < a.len() => {
                a.remove(*i);
            }
            (Some(Node::Obj(o)), Seg::Key(k)) => o.retain(|(n, _)| n != k),
            _ => {}
        }
    }

    fn set(&mut self, p: &[Seg], v: Node) {
        if let Some(n) = self.get_mut(p) {
            *n = v;
        }
    }

    fn leaves(&self, prefix: &mut Vec<Seg>, out: &mut Vec<(Vec<Seg>, Node)>) {
        match self {
            Node::Arr(a) if !a.is_empty() => {
                for (i, v) in a.iter().enumerate() {
                    prefix.push(Seg::Idx(i));
                    v.leaves(prefix, out);
                    prefix.pop();
                }
            }
            Node::Obj(o) if !o.is_empty() => {
                for (k, v) in o {
                    prefix.push(Seg::Key(k.clone()));
                    v.leaves(prefix, out);
                    prefix.pop();
                }
            }
            other => out.push((prefix.clone(), other.clone())),
        }
    }
}

// ---------------------------------------------------------------------------------------
// Mutations.

/// Values that break things: nulls, wrong types, zero, negative, huge, NaN and infinite
/// numbers, line breaks and NUL, escaping paths, long strings, long arrays.
fn special_values() -> Vec<Node> {
    let mut v = vec![Node::Null, Node::Bool(true)];
    v.extend(
        [
            0i64,
            -1,
            1,
            2,
            1001,
            16385,
            65536,
            2_147_483_648,
            4_294_967_296,
            i64::MAX,
            i64::MIN,
        ]
        .map(Node::Int),
    );
    v.extend(
        [
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            1e308,
            -1e308,
            1e-300,
            -0.0,
            -1.0,
            0.5,
            1e9,
        ]
        .map(Node::Float),
    );
    v.extend(
        [
            "",
            "NaN",
            "inf",
            "a\nb\rc",
            "a\0b",
            "/etc/passwd",
            "../x",
            "/dev/zero",
            "frames",
            "frames/../manifest.json",
            "é🙂",
            "mock",
        ]
        .map(|s| Node::Str(s.to_string())),
    );
    v.push(Node::Str("x".repeat(5000)));
    v.push(Node::Arr(vec![]));
    v.push(Node::Arr(vec![Node::Int(0); 1001]));
    v.push(Node::Obj(vec![]));
    v
}

/// A value put in place of another.
fn values() -> impl Strategy<Value = Node> {
    prop_oneof![
        8 => prop::sample::select(special_values()),
        1 => (1usize..20_000).prop_map(|n| Node::Str("x".repeat(n))),
        1 => vec(any::<u8>(), 0..40).prop_map(|b| Node::Str(String::from_utf8_lossy(&b).into())),
    ]
}

/// A structured edit, resolved on the document it is applied to (`pick` chooses the path
/// among those of area `area`).
#[derive(Debug, Clone)]
enum Edit {
    Set {
        area: u8,
        pick: u64,
        value: Node,
    },
    Scale {
        area: u8,
        pick: u64,
        factor: f64,
    },
    Delete {
        area: u8,
        pick: u64,
    },
    /// Append a copy of an array's last entry (or an unknown key to a table).
    Extra {
        area: u8,
        pick: u64,
    },
    /// Drop an array's last entry.
    Shorten {
        area: u8,
        pick: u64,
    },
    /// Give a number the value of another number in the document (a lamp at the tile's
    /// height, a width equal to an exposure ...).
    CopyFrom {
        area: u8,
        pick: u64,
        from: u64,
    },
}

/// An edit of the text once written.
#[derive(Debug, Clone)]
enum TextEdit {
    Flip { at: u64, xor: u8 },
    Truncate { at: u64 },
    Insert { at: u64, bytes: Vec<u8> },
}

fn edit() -> impl Strategy<Value = Edit> {
    let target = (any::<u8>(), any::<u64>());
    prop_oneof![
        4 => (target, values()).prop_map(|((area, pick), value)| Edit::Set { area, pick, value }),
        2 => (target, prop::sample::select(vec![-1.0, 0.0, 0.5, 2.0, 1e3, 1e6, 1e-6, 1e12]))
            .prop_map(|((area, pick), factor)| Edit::Scale { area, pick, factor }),
        1 => target.prop_map(|(area, pick)| Edit::Delete { area, pick }),
        1 => target.prop_map(|(area, pick)| Edit::Extra { area, pick }),
        1 => target.prop_map(|(area, pick)| Edit::Shorten { area, pick }),
        2 => (target, any::<u64>()).prop_map(|((area, pick), from)| Edit::CopyFrom { area, pick, from }),
    ]
}

fn text_edit() -> impl Strategy<Value = TextEdit> {
    prop_oneof![
        (any::<u64>(), 1u8..=255).prop_map(|(at, xor)| TextEdit::Flip { at, xor }),
        any::<u64>().prop_map(|at| TextEdit::Truncate { at }),
        (any::<u64>(), vec(any::<u8>(), 1..8))
            .prop_map(|(at, bytes)| TextEdit::Insert { at, bytes }),
    ]
}

/// Up to three structured edits, and sometimes text edits after them.
fn edits() -> impl Strategy<Value = (Vec<Edit>, Vec<TextEdit>)> {
    (
        vec(edit(), 1..=3),
        prop_oneof![3 => Just(vec![]), 1 => vec(text_edit(), 1..=2)],
    )
}

/// Apply `edits` to `doc`; `areas` are the path prefixes an edit's `area` chooses among
/// (an empty prefix: anywhere). Returns what was done, for the findings.
fn apply(doc: &mut Node, edits: &[Edit], areas: &[&str]) -> Vec<String> {
    let mut log = Vec::new();
    for e in edits {
        let (area, pick) = match e {
            Edit::Set { area, pick, .. }
            | Edit::Scale { area, pick, .. }
            | Edit::Delete { area, pick }
            | Edit::Extra { area, pick }
            | Edit::Shorten { area, pick }
            | Edit::CopyFrom { area, pick, .. } => (*area, *pick),
        };
        let prefix = areas[area as usize % areas.len()];
        let mut all = Vec::new();
        doc.paths(&mut Vec::new(), &mut all);
        let candidates: Vec<Vec<Seg>> = all
            .into_iter()
            .filter(|p| !p.is_empty())
            .filter(|p| prefix.is_empty() || matches!(&p[0], Seg::Key(k) if k == prefix))
            .collect();
        if candidates.is_empty() {
            continue;
        }
        let p = candidates[(pick % candidates.len() as u64) as usize].clone();
        let name = path_name(&p);
        match e {
            Edit::Set { value, .. } => {
                log.push(format!("set {name} = {}", brief(value)));
                doc.set(&p, value.clone());
            }
            Edit::Scale { factor, .. } => match doc.get(&p) {
                Some(Node::Int(i)) => {
                    let v = *i as f64 * factor;
                    let v = if v.fract() == 0.0 && v.abs() < 9e18 {
                        Node::Int(v as i64)
                    } else {
                        Node::Float(v)
                    };
                    log.push(format!("set {name} = {} (x{factor})", brief(&v)));
                    doc.set(&p, v);
                }
                Some(Node::Float(f)) => {
                    let v = Node::Float(f * factor);
                    log.push(format!("set {name} = {} (x{factor})", brief(&v)));
                    doc.set(&p, v);
                }
                _ => {}
            },
            Edit::Delete { .. } => {
                log.push(format!("delete {name}"));
                doc.delete(&p);
            }
            Edit::Extra { .. } => match doc.get_mut(&p) {
                Some(Node::Arr(a)) => {
                    let extra = a.last().cloned().unwrap_or(Node::Int(1));
                    log.push(format!("append {} to {name}", brief(&extra)));
                    a.push(extra);
                }
                Some(Node::Obj(o)) => {
                    log.push(format!("add unknown key {name}.extra = 1"));
                    o.push(("extra".into(), Node::Int(1)));
                }
                _ => {}
            },
            Edit::CopyFrom { from, .. } => {
                let mut leaves = Vec::new();
                doc.leaves(&mut Vec::new(), &mut leaves);
                let numbers: Vec<(Vec<Seg>, Node)> = leaves
                    .into_iter()
                    .filter(|(_, v)| matches!(v, Node::Int(_) | Node::Float(_)))
                    .collect();
                if matches!(doc.get(&p), Some(Node::Int(_) | Node::Float(_))) && !numbers.is_empty()
                {
                    let (q, v) = numbers[(from % numbers.len() as u64) as usize].clone();
                    log.push(format!(
                        "set {name} = {} (the value of {})",
                        brief(&v),
                        path_name(&q)
                    ));
                    doc.set(&p, v);
                }
            }
            Edit::Shorten { .. } => {
                if let Some(Node::Arr(a)) = doc.get_mut(&p) {
                    if a.pop().is_some() {
                        log.push(format!("drop the last entry of {name}"));
                    }
                }
            }
        }
    }
    log
}

fn apply_text(text: &mut Vec<u8>, edits: &[TextEdit]) -> Vec<String> {
    let mut log = Vec::new();
    for e in edits {
        let n = text.len() as u64;
        match e {
            TextEdit::Flip { at, xor } if n > 0 => {
                let i = (at % n) as usize;
                log.push(format!("byte {i} ^= {xor:#04x}"));
                text[i] ^= xor;
            }
            TextEdit::Truncate { at } => {
                let i = (at % (n + 1)) as usize;
                log.push(format!("truncate to {i} bytes"));
                text.truncate(i);
            }
            TextEdit::Insert { at, bytes } => {
                let i = (at % (n + 1)) as usize;
                log.push(format!("insert {bytes:?} at byte {i}"));
                text.splice(i..i, bytes.iter().copied());
            }
            _ => {}
        }
    }
    log
}

fn brief(v: &Node) -> String {
    match v {
        Node::Str(s) if s.chars().count() > 40 => format!(
            "a string of {} characters ({:?}…)",
            s.chars().count(),
            s.chars().take(8).collect::<String>()
        ),
        Node::Str(s) => format!("{s:?}"),
        Node::Arr(a) if a.len() > 8 => format!("an array of {} entries", a.len()),
        Node::Float(f) => format!("{f:?}"),
        other => {
            let mut s = String::new();
            other.json_text(&mut s);
            s.replace('\n', " ")
        }
    }
}

// ---------------------------------------------------------------------------------------
// Rig files.

/// The rigs the project ships, and the tests' small variant.
fn base_rigs() -> Vec<(String, Node)> {
    let mut out = Vec::new();
    let mut names: Vec<PathBuf> = std::fs::read_dir(root().join("rigs"))
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "toml"))
        .collect();
    names.sort();
    for p in names {
        let t: toml::Table = toml::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
        out.push((
            p.file_name().unwrap().to_string_lossy().into_owned(),
            Node::from_toml(&toml::Value::Table(t)),
        ));
    }
    out.push((
        "small_table()".into(),
        Node::from_toml(&toml::Value::Table(small_table())),
    ));
    out
}

/// Keys whose values the issue says must be bounded by what a real rig can reach.
const BOUNDED: &[&str] = &[
    "camera.width",
    "camera.height",
    "camera.fps",
    "camera.min_exposure_us",
    "camera.max_exposure_us",
    "camera.frame_timeout_ms",
    "camera.settle_max_frames",
    "lamp.warmup_ms",
    "lamp.reply_timeout_ms",
    "lamp.tries",
    "bracket.exposures_us",
    "bracket.grid_exposure_us",
    "bracket.frames_per_exposure",
    "bracket.dark_frames_per_exposure",
    "bracket.grid_frames",
    "geometry.grid_inner_corners",
];

fn absurd(v: &Node) -> bool {
    match v {
        Node::Int(i) => *i >= 2_147_483_648,
        Node::Float(f) => f.abs() >= 1e12,
        _ => false,
    }
}

/// Rig semantics checked when a mutated rig parses: every number finite, the bounded keys
/// bounded, command strings and the name single-line, and nothing silently dropped or
/// changed (each value given is the value parsed: no array cut short).
fn rig_accepted_checks(input: &Node, rig: &glint::rig::Rig, f: &mut Findings, desc: &str) {
    let Ok(parsed) = toml::Value::try_from(rig) else {
        f.add(
            "a parsed rig does not serialise back to TOML".into(),
            "rig::parse",
            desc,
            String::new(),
        );
        return;
    };
    let parsed = Node::from_toml(&parsed);
    let mut leaves = Vec::new();
    input.leaves(&mut Vec::new(), &mut leaves);
    for (p, v) in leaves {
        let name = path_name(&p);
        let key: String = name.split('[').next().unwrap_or("").to_string();
        if let Node::Float(x) = v {
            if !x.is_finite() {
                f.add(
                    format!("accepted a non-finite value at {key}"),
                    "rig::parse",
                    desc,
                    format!("{name} = {x} passed rig::parse"),
                );
            }
        }
        if BOUNDED.contains(&key.as_str()) && absurd(&v) {
            f.add(
                format!("accepted an unbounded value at {key}"),
                "rig::parse",
                desc,
                format!("{name} = {} passed rig::parse", brief(&v)),
            );
        }
        if let Node::Str(s) = &v {
            if (key.starts_with("lamp.commands.") || key == "rig.name")
                && (s.contains('\0') || s.contains('\n') || s.contains('\r'))
            {
                f.add(
                    format!("accepted a NUL or line break in {key}"),
                    "rig::parse",
                    desc,
                    format!("{name} = {s:?} passed rig::parse"),
                );
            }
        }
        let same = match (parsed.get(&p), &v) {
            // An empty table takes the defaults.
            (_, Node::Obj(o)) if o.is_empty() => true,
            (Some(Node::Float(a)), Node::Int(b)) => *a == *b as f64,
            (Some(Node::Float(a)), Node::Float(b)) => a == b || (a.is_nan() && b.is_nan()),
            (Some(a), b) => a == b,
            (None, Node::Arr(a)) => a.is_empty(),
            (None, _) => false,
        };
        if !same {
            f.add(
                format!("a value given is not the value parsed at {key}"),
                "rig::parse",
                desc,
                format!(
                    "{name} = {} was read as {}",
                    brief(&v),
                    parsed.get(&p).map_or("nothing".into(), brief)
                ),
            );
        }
    }
}

/// Parse a mutated rig (`doc`, written as `text`, edited as text or not) and check it.
fn check_rig(doc: &Node, text: &str, text_edited: bool, desc: &str, f: &mut Findings) {
    let path = Path::new("/lab/rigs/bench.toml");
    match guarded(|| Ok::<_, String>(glint::rig::parse(text, path))) {
        Outcome::Ok(Ok(rig)) => {
            *f.passed.entry("rig::parse".into()).or_default() += 1;
            if !text_edited {
                // What TOML holds of the edits (a null leaves the key out).
                let given = doc
                    .to_toml()
                    .map(|v| Node::from_toml(&v))
                    .unwrap_or(Node::Null);
                rig_accepted_checks(&given, &rig, f, desc);
            }
        }
        // The error and each problem `glint rig check` lists: one line each.
        Outcome::Ok(Err(e)) => {
            f.check::<()>("rig::parse", desc, Outcome::Err(e.to_string()));
            let listed = match &e {
                glint::rig::RigError::Invalid { .. } => e.problems(),
                _ => vec![],
            };
            for p in listed {
                f.check::<()>("rig check (a listed problem)", desc, Outcome::Err(p));
            }
        }
        Outcome::Err(_) => unreachable!("parse's result is returned whole"),
        Outcome::Panic(p) => {
            f.check::<()>("rig::parse", desc, Outcome::Panic(p));
        }
    }
}

#[test]
fn fuzz_rig_files_every_key_with_every_special_value() {
    // Not random: each shipped rig with each of its keys (and array entries) set to each
    // special value, deleted, or given an extra entry: one edit at a time.
    let start = Instant::now();
    let mut f = Findings::default();
    let mut n = 0;
    for (base_name, base) in base_rigs() {
        let mut paths = Vec::new();
        base.paths(&mut Vec::new(), &mut paths);
        for p in paths.iter().filter(|p| !p.is_empty()) {
            let name = path_name(p);
            let mut edits: Vec<(String, Node)> = special_values()
                .into_iter()
                .map(|v| {
                    let mut d = base.clone();
                    let what = format!("set {name} = {}", brief(&v));
                    d.set(p, v);
                    (what, d)
                })
                .collect();
            let mut d = base.clone();
            d.delete(p);
            edits.push((format!("delete {name}"), d));
            if let Some(Node::Arr(a)) = base.get(p) {
                let mut d = base.clone();
                if let Some(Node::Arr(b)) = d.get_mut(p) {
                    b.push(a.last().cloned().unwrap_or(Node::Int(1)));
                }
                edits.push((format!("append an entry to {name}"), d));
            }
            for (what, doc) in edits {
                n += 1;
                check_rig(
                    &doc,
                    &doc.toml_text(),
                    false,
                    &format!("{base_name}: {what}"),
                    &mut f,
                );
            }
        }
    }
    f.finish("rig sweep", n, start);
}

#[test]
fn fuzz_rig_files_parse_without_panic_and_fail_on_one_line() {
    let start = Instant::now();
    let bases = base_rigs();
    let mut r = runner("rig");
    let n = cases("rig");
    let strategy = (0..bases.len(), edits());
    let mut f = Findings::default();
    for _ in 0..n {
        let (b, (es, ts)) = draw(&mut r, &strategy);
        let (base_name, base) = &bases[b];
        let mut doc = base.clone();
        let mut log = apply(
            &mut doc,
            &es,
            &["", "camera", "lamp", "geometry", "bracket", "mock"],
        );
        let mut text = doc.toml_text().into_bytes();
        log.extend(apply_text(&mut text, &ts));
        let text = String::from_utf8_lossy(&text).into_owned();
        let desc = format!("{base_name}: {}", log.join("; "));
        check_rig(&doc, &text, !ts.is_empty(), &desc, &mut f);
    }
    f.finish("rig", n, start);
}

// ---------------------------------------------------------------------------------------
// A session, captured once per test run, with every stage's results.

struct Template {
    /// Holds rig.toml and the session s/ (with hdr/, calib/, fit/, validation/, report/).
    dir: PathBuf,
    /// The camera profile the first `glint hdr` stored.
    profile: PathBuf,
}

/// Set in a child process: the parent's template folder.
const TEMPLATE_ENV: &str = "GLINT_FUZZ_TEMPLATE";
/// Set in a child process: `target:case`.
const CHILD_ENV: &str = "GLINT_FUZZ_CHILD";
/// Set in a child process: the folder its cases go in.
const SCRATCH_ENV: &str = "GLINT_FUZZ_SCRATCH";
/// Set in a child process: where it writes its findings.
const OUT_ENV: &str = "GLINT_FUZZ_OUT";
/// A child's address space: a read that never ends fails here, not on the machine.
const CHILD_MEMORY: u64 = 1 << 30;
/// A child case that runs longer than this is a finding (a 160x120 session's stages all
/// take about a second).
const CHILD_DEADLINE: Duration = Duration::from_secs(20);

static TEMPLATE: OnceLock<Template> = OnceLock::new();

extern "C" fn remove_template() {
    if std::env::var_os(TEMPLATE_ENV).is_none() {
        if let Some(t) = TEMPLATE.get() {
            let _ = std::fs::remove_dir_all(&t.dir);
        }
    }
}

fn fit_options() -> glint::fit::run::FitOptions {
    glint::fit::run::FitOptions {
        draws: 2,
        ..Default::default()
    }
}

fn template() -> &'static Template {
    TEMPLATE.get_or_init(|| {
        // A child uses its parent's template; GLINT_FUZZ_TEMPLATE=DIR set by hand builds
        // one there and keeps it (to re-run one case: see `fuzz_child`).
        let given = std::env::var_os(TEMPLATE_ENV).map(PathBuf::from);
        if let Some(dir) = given
            .as_ref()
            .filter(|d| d.join("s/manifest.json").exists())
        {
            let profile = std::fs::read_dir(dir.join("profiles"))
                .unwrap()
                .flatten()
                .next()
                .unwrap()
                .path();
            return Template {
                dir: dir.clone(),
                profile,
            };
        }
        let dir = match given {
            Some(d) => {
                std::fs::create_dir_all(&d).unwrap();
                d
            }
            None => {
                let d = tempfile::Builder::new()
                    .prefix("glint-fuzz-template-")
                    .tempdir()
                    .unwrap()
                    .keep();
                // SAFETY: registers a plain function to run at exit; it only removes a
                // folder.
                unsafe {
                    libc::atexit(remove_template);
                }
                d
            }
        };
        let t = Instant::now();
        record(&dir, &small_table()).expect("the small mock rig captures");
        let s = dir.join("s");
        // A profile is stored only beside a rig file given explicitly (`--rig`).
        let (hdr, _) = glint::hdr::run::run(
            &s,
            &glint::hdr::run::HdrOptions {
                rig: Some(dir.join("rig.toml")),
                ..Default::default()
            },
            &mut |_| {},
        )
        .unwrap();
        glint::calib::run::run_session(&s, None).unwrap();
        glint::fit::run::run(&s, &fit_options()).unwrap();
        glint::validate::run(&s, &Default::default(), &mut |_| {}).unwrap();
        glint::report::write(&s, &Default::default()).unwrap();
        eprintln!(
            "fuzz: template session captured and processed in {:.1} s",
            t.elapsed().as_secs_f64()
        );
        Template {
            profile: PathBuf::from(hdr.profile_written.expect("the first hdr stores a profile")),
            dir,
        }
    })
}

/// Every entry under `dir` (not following links) with its content hash, leaving out
/// `skip` (the session folder, where writing is allowed).
fn snapshot(dir: &Path, skip: &Path) -> BTreeMap<PathBuf, String> {
    fn walk(d: &Path, skip: &Path, out: &mut BTreeMap<PathBuf, String>) {
        let Ok(rd) = std::fs::read_dir(d) else {
            return;
        };
        for e in rd.flatten() {
            let p = e.path();
            if p == skip {
                continue;
            }
            let Ok(m) = std::fs::symlink_metadata(&p) else {
                continue;
            };
            if m.is_dir() {
                out.insert(p.clone(), "dir".into());
                walk(&p, skip, out);
            } else if m.file_type().is_symlink() {
                out.insert(p.clone(), format!("link {:?}", std::fs::read_link(&p).ok()));
            } else {
                let bytes = std::fs::read(&p).unwrap_or_default();
                out.insert(p.clone(), glint::session::sha256_hex(&bytes));
            }
        }
    }
    let mut out = BTreeMap::new();
    walk(dir, skip, &mut out);
    out
}

/// Places a bad manifest could make Glint write to (profiles beside a `rig_file` of
/// `/etc/passwd`, `../x`, a relative name): none may appear. (The harness never puts such
/// a `rig_file` in a manifest; this is the safety net.)
fn stray_places() -> Vec<PathBuf> {
    let cwd = std::env::current_dir().unwrap();
    let mut v = vec![
        PathBuf::from("/etc/profiles"),
        PathBuf::from("/dev/profiles"),
        PathBuf::from("/profiles"),
        cwd.join("profiles"),
    ];
    if let Some(p) = cwd.parent() {
        v.push(p.join("profiles"));
    }
    v
}

/// One case's folder: `s/` (the session copy), `rig/rig.toml` (the rig file its manifest
/// names; with the camera profile when `with_profile`), `canary/` (a user's file and a
/// copy of a frame, for paths that escape).
struct Case {
    _tmp: tempfile::TempDir,
    root: PathBuf,
    s: PathBuf,
    manifest: Node,
    /// Everything outside s/ as it was at the last check.
    before: std::cell::RefCell<BTreeMap<PathBuf, String>>,
}

impl Case {
    fn new(with_profile: bool) -> Case {
        let t = template();
        // In a child, inside the folder its parent removes (a child killed at its
        // deadline leaves nothing behind).
        let mut b = tempfile::Builder::new();
        b.prefix("glint-fuzz-");
        let tmp = match std::env::var_os(SCRATCH_ENV) {
            Some(d) => b.tempdir_in(d),
            None => b.tempdir(),
        }
        .unwrap();
        let root = tmp.path().to_path_buf();
        let s = root.join("s");
        copy_dir(&t.dir.join("s"), &s);
        std::fs::create_dir_all(root.join("rig")).unwrap();
        std::fs::copy(t.dir.join("rig.toml"), root.join("rig/rig.toml")).unwrap();
        if with_profile {
            std::fs::create_dir_all(root.join("rig/profiles")).unwrap();
            std::fs::copy(
                &t.profile,
                root.join("rig/profiles")
                    .join(t.profile.file_name().unwrap()),
            )
            .unwrap();
        }
        std::fs::create_dir_all(root.join("canary")).unwrap();
        std::fs::write(root.join("canary/keep.txt"), "the user's own file\n").unwrap();
        let text = std::fs::read(s.join("manifest.json")).unwrap();
        let mut manifest = Node::from_json(&serde_json::from_slice(&text).unwrap());
        manifest.set(
            &[Seg::Key("rig_file".into())],
            Node::Str(root.join("rig/rig.toml").display().to_string()),
        );
        let first = match manifest.get(&[
            Seg::Key("frames".into()),
            Seg::Idx(0),
            Seg::Key("file".into()),
        ]) {
            Some(Node::Str(f)) => f.clone(),
            _ => unreachable!("a captured manifest lists frames"),
        };
        std::fs::copy(s.join(&first), root.join("canary/frame.png")).unwrap();
        std::fs::write(s.join("manifest.json"), manifest.json()).unwrap();
        let before = std::cell::RefCell::new(snapshot(&root, &s));
        Case {
            _tmp: tmp,
            root,
            s,
            manifest,
            before,
        }
    }

    /// Take the state outside s/ as the baseline (after the case's own set-up).
    fn rebase(&self) {
        *self.before.borrow_mut() = snapshot(&self.root, &self.s);
    }

    fn write_manifest(&self, text: &[u8]) {
        std::fs::write(self.s.join("manifest.json"), text).unwrap();
    }

    /// Findings for writes outside the session since the last check.
    fn check_outside(&self, f: &mut Findings, stage: &str, desc: &str) {
        let mut after = snapshot(&self.root, &self.s);
        let before = self.before.replace(after.clone());
        // `glint hdr --rig rig/rig.toml` may store a new camera profile beside the rig
        // (never replace one): it must be a response file that loads.
        if stage == "hdr::run::run" {
            let profiles = self.root.join("rig/profiles");
            let new_profiles: Vec<PathBuf> = after
                .keys()
                .filter(|k| !before.contains_key(*k))
                .filter(|k| {
                    k.parent() == Some(profiles.as_path())
                        && k.to_string_lossy().ends_with(".response.json")
                        && after
                            .get(*k)
                            .is_some_and(|v| v != "dir" && !v.starts_with("link "))
                })
                .cloned()
                .collect();
            for p in &new_profiles {
                if let Err(e) = glint::hdr::files::load_response(p) {
                    f.add(
                        "stored a camera profile that does not load".into(),
                        stage,
                        desc,
                        format!("{}: {}", p.display(), show(&e.to_string())),
                    );
                }
                after.remove(p);
            }
            if !before.contains_key(&profiles) && !new_profiles.is_empty() {
                after.remove(&profiles);
            }
        }
        if after != before {
            let rel = |k: &Path| {
                k.strip_prefix(&self.root)
                    .unwrap_or(k)
                    .display()
                    .to_string()
            };
            let changed: Vec<String> = after
                .iter()
                .filter(|(k, v)| before.get(*k) != Some(v))
                .map(|(k, _)| rel(k))
                .chain(
                    before
                        .keys()
                        .filter(|k| !after.contains_key(*k))
                        .map(|k| format!("{} (removed)", rel(k))),
                )
                .collect();
            let first = changed.first().cloned().unwrap_or_default();
            let place: String = first.split('/').take(2).collect::<Vec<_>>().join("/");
            f.add(
                format!("wrote outside the session ({place})"),
                stage,
                desc,
                format!("changed outside s/: {}", changed.join(", ")),
            );
        }
        for p in stray_places() {
            if p.exists() {
                f.add(
                    format!("wrote outside the session ({})", p.display()),
                    stage,
                    desc,
                    format!("{} appeared", p.display()),
                );
            }
        }
    }
}

type StageFn = fn(&Path) -> Result<(), String>;

fn st_verify(s: &Path) -> Result<(), String> {
    glint::session::verify(s)
        .map(|_| ())
        .map_err(|e| e.to_string())
}
fn st_load(s: &Path) -> Result<(), String> {
    glint::session::load(s)
        .map(|_| ())
        .map_err(|e| e.to_string())
}
/// The case's own rig file (`rig/rig.toml` beside `s/`), which `glint hdr --rig` is
/// given: the camera profile is read, or stored, beside it.
fn case_rig(s: &Path) -> PathBuf {
    s.parent().unwrap_or(s).join("rig/rig.toml")
}
fn st_hdr(s: &Path) -> Result<(), String> {
    let opts = glint::hdr::run::HdrOptions {
        rig: Some(case_rig(s)),
        ..Default::default()
    };
    glint::hdr::run::run(s, &opts, &mut |_| {})
        .map(|_| ())
        .map_err(|e| e.to_string())
}
fn st_calib(s: &Path) -> Result<(), String> {
    glint::calib::run::run_session(s, None)
        .map(|_| ())
        .map_err(|e| e.to_string())
}
fn st_fit(s: &Path) -> Result<(), String> {
    glint::fit::run::run(s, &fit_options())
        .map(|_| ())
        .map_err(|e| e.to_string())
}
fn st_validate(s: &Path) -> Result<(), String> {
    glint::validate::run(s, &Default::default(), &mut |_| {})
        .map(|_| ())
        .map_err(|e| e.to_string())
}
fn st_report(s: &Path) -> Result<(), String> {
    glint::report::write(s, &Default::default())
        .map(|_| ())
        .map_err(|e| e.to_string())
}

const STAGES: &[(&str, StageFn)] = &[
    ("session::verify", st_verify),
    ("session::load", st_load),
    ("hdr::run::run", st_hdr),
    ("calib::run::run_session", st_calib),
    ("fit::run::run", st_fit),
    ("validate::run", st_validate),
    ("report::write", st_report),
];

// ---------------------------------------------------------------------------------------
// Child processes: a case that reads `/dev/zero` to the end, or loops, must not take the
// test binary (or the machine) with it. Each stage case runs in this test binary started
// again (the ignored test `fuzz_child`), under an address-space limit and a deadline.

static CHILD_OUT: Mutex<Option<std::fs::File>> = Mutex::new(None);

/// Tell the parent what the child is doing (the input, the stage it starts).
fn note(kind: &str, text: &str) {
    if let Some(f) = CHILD_OUT.lock().unwrap_or_else(|e| e.into_inner()).as_mut() {
        let _ = writeln!(f, "{kind}\t{}", text.replace(['\t', '\n', '\r'], " "));
        let _ = f.flush();
    }
}

/// Run `stages` on the case's session, each guarded, timed and checked for writes
/// outside; returns the names of those that succeeded.
fn run_stages(c: &Case, stages: &[(&str, StageFn)], f: &mut Findings, desc: &str) -> Vec<String> {
    let mut ok = Vec::new();
    for (name, stage) in stages {
        note("stage", name);
        let t = Instant::now();
        let out = guarded(|| stage(&c.s));
        if let Outcome::Err(e) = &out {
            // For whoever re-runs the case by hand (the parent reads no such line).
            note("refused", &format!("{name}: {e}"));
        }
        if t.elapsed() > SLOW {
            f.add(
                format!("slow ({} s or more on a 160x120 session)", SLOW.as_secs()),
                name,
                desc,
                format!("took {:.1} s", t.elapsed().as_secs_f64()),
            );
        }
        if f.check(name, desc, out).is_some() {
            ok.push(name.to_string());
        }
        c.check_outside(f, name, desc);
    }
    ok
}

/// Run case `i` of `target` in a child process; its findings, or a finding for its death
/// or its running past `limit`.
fn in_child(f: &mut Findings, target: &str, i: usize, limit: Duration) {
    let t = template();
    let out = tempfile::NamedTempFile::new().unwrap();
    let scratch = tempfile::tempdir().unwrap();
    let mut child = std::process::Command::new(std::env::current_exe().unwrap())
        .args([
            "--exact",
            "suite::fuzz::fuzz_child",
            "--ignored",
            "--nocapture",
            "--test-threads",
            "1",
        ])
        .env(CHILD_ENV, format!("{target}:{i}"))
        .env(OUT_ENV, out.path())
        .env(SCRATCH_ENV, scratch.path())
        .env(TEMPLATE_ENV, &t.dir)
        .env("RUST_BACKTRACE", "1")
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("the test binary starts again");
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break Some(s);
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    let text = std::fs::read_to_string(out.path()).unwrap_or_default();
    let mut input = format!("{target} case {i}");
    let mut stage = "setting up the case".to_string();
    let mut done = false;
    let mut got = Findings::default();
    for line in text.lines() {
        let parts: Vec<&str> = line.split('\t').collect();
        match parts.as_slice() {
            ["input", d] => input = format!("{d} [{target}:{i}]"),
            ["stage", s] => stage = s.to_string(),
            ["done"] => done = true,
            ["passed", stage, n] => {
                *got.passed.entry(stage.to_string()).or_default() += n.parse().unwrap_or(0)
            }
            ["finding", key, count, inp, detail, stages] => {
                let count: usize = count.parse().unwrap_or(1);
                for s in stages.split(',') {
                    got.add(key.to_string(), s, inp, detail.to_string());
                }
                if let Some(e) = got.seen.get_mut(*key) {
                    e.count = e.count.max(count);
                }
            }
            _ => {}
        }
    }
    f.merge(got);
    match status {
        None => f.add(
            format!(
                "did not finish within {} s (unbounded work)",
                limit.as_secs()
            ),
            &stage,
            &input,
            String::new(),
        ),
        Some(s) if !done => f.add(
            format!(
                "the process died ({s}): out of memory under the {} GiB limit, or an abort",
                CHILD_MEMORY >> 30
            ),
            &stage,
            &input,
            String::new(),
        ),
        Some(_) => {}
    }
}

/// Cases of a target run in children, one after another.
fn run_in_children(target: &str, limit: Duration) {
    let start = Instant::now();
    let n = cases(target);
    let mut f = Findings::default();
    for i in 0..n {
        in_child(&mut f, target, i, limit);
    }
    f.finish(target, n, start);
}

/// One case in this process: what the fuzz tests start for each case. To re-run a case
/// that a finding names (`[derived:17]`):
/// `GLINT_FUZZ_TEMPLATE=/tmp/glint-fuzz-t GLINT_FUZZ_CHILD=derived:17
/// GLINT_FUZZ_OUT=/dev/stdout cargo test --test tests fuzz_child -- --ignored --exact
/// suite::fuzz::fuzz_child` (the template is built in the first run and kept).
#[test]
#[ignore = "runs only as the fuzz tests' child process (GLINT_FUZZ_CHILD)"]
fn fuzz_child() {
    let Ok(spec) = std::env::var(CHILD_ENV) else {
        return;
    };
    let lim = libc::rlimit {
        rlim_cur: CHILD_MEMORY,
        rlim_max: CHILD_MEMORY,
    };
    // SAFETY: setrlimit with a valid struct; it only lowers this process's limit.
    unsafe {
        libc::setrlimit(libc::RLIMIT_AS, &lim);
    }
    let out = std::env::var(OUT_ENV).unwrap();
    *CHILD_OUT.lock().unwrap() = Some(std::fs::File::create(out).unwrap());
    let (target, i) = spec.split_once(':').unwrap();
    let i: usize = i.parse().unwrap();
    let mut f = Findings::default();
    match target {
        "manifest-load" => manifest_load_case(i, &mut f),
        "manifest-stages" => manifest_stages_case(i, &mut f),
        "derived" => derived_case(i, &mut f),
        "png-stages" => png_stages_case(i, &mut f),
        "trust" => trust_case(i, &mut f),
        other => panic!("unknown fuzz target {other}"),
    }
    let lines = f.to_lines();
    let mut g = CHILD_OUT.lock().unwrap();
    let file = g.as_mut().unwrap();
    file.write_all(lines.as_bytes()).unwrap();
    file.write_all(b"done\n").unwrap();
    file.flush().unwrap();
}

/// Case `i` of a target: the runner's `i + 1`-th draw.
fn nth_case<S: Strategy>(target: &str, i: usize, s: &S) -> S::Value {
    let mut r = runner(target);
    for _ in 0..i {
        draw(&mut r, s);
    }
    draw(&mut r, s)
}

// ---------------------------------------------------------------------------------------
// Manifests.

/// A manifest-specific change of a frame: where its file points, duplicates, exposures.
#[derive(Debug, Clone)]
enum FrameEdit {
    /// Point frame k elsewhere (0 /etc/passwd, 1 ../canary/frame.png, 2 /dev/zero,
    /// 3 an absolute path outside, 4 a link in frames/ to outside, 5 frames/ itself a
    /// link to a folder outside), with that file's checksum.
    Escape { k: u64, to: u8 },
    /// List frame k twice.
    Duplicate { k: u64 },
    /// Give frame k the exposure of frame k + 1.
    SameExposure { k: u64 },
}

fn frame_edit() -> impl Strategy<Value = FrameEdit> {
    prop_oneof![
        (any::<u64>(), 0u8..6).prop_map(|(k, to)| FrameEdit::Escape { k, to }),
        any::<u64>().prop_map(|k| FrameEdit::Duplicate { k }),
        any::<u64>().prop_map(|k| FrameEdit::SameExposure { k }),
    ]
}

/// Apply a frame edit; returns its description and whether the frame now points outside.
fn apply_frame_edit(c: &Case, m: &mut Node, e: &FrameEdit) -> (String, bool) {
    let Some(Node::Arr(frames)) = m.get_mut(&[Seg::Key("frames".into())]) else {
        return (String::new(), false);
    };
    if frames.is_empty() {
        return (String::new(), false);
    }
    let n = frames.len() as u64;
    let file_of = |f: &Node| match f.get(&[Seg::Key("file".into())]) {
        Some(Node::Str(s)) => s.clone(),
        _ => String::new(),
    };
    match e {
        FrameEdit::Escape { k, to } => {
            let k = (k % n) as usize;
            let outside = c.root.join("canary/frame.png");
            let (path, real): (String, Option<PathBuf>) = match to {
                0 => ("/etc/passwd".into(), Some("/etc/passwd".into())),
                1 => ("../canary/frame.png".into(), Some(outside.clone())),
                2 => ("/dev/zero".into(), None),
                3 => (outside.display().to_string(), Some(outside.clone())),
                4 => {
                    let _ = std::os::unix::fs::symlink(&outside, c.s.join("frames/link.png"));
                    ("frames/link.png".into(), Some(outside.clone()))
                }
                _ => {
                    let moved = c.root.join("canary/frames");
                    let _ = std::fs::rename(c.s.join("frames"), &moved);
                    let _ = std::os::unix::fs::symlink(&moved, c.s.join("frames"));
                    (file_of(&frames[k]), None)
                }
            };
            frames[k].set(&[Seg::Key("file".into())], Node::Str(path.clone()));
            if let Some(real) = real {
                if let Ok(bytes) = std::fs::read(&real) {
                    frames[k].set(
                        &[Seg::Key("sha256".into())],
                        Node::Str(glint::session::sha256_hex(&bytes)),
                    );
                }
            }
            let how = match to {
                2 => "",
                4 => " (a link to canary/frame.png), with its checksum",
                5 => " (frames/ a link to canary/frames)",
                _ => ", with its checksum",
            };
            (format!("frames[{k}].file = {path:?}{how}"), true)
        }
        FrameEdit::Duplicate { k } => {
            let k = (k % n) as usize;
            let dup = frames[k].clone();
            frames.push(dup);
            (format!("frames[{k}] listed twice"), false)
        }
        FrameEdit::SameExposure { k } => {
            let k = (k % n) as usize;
            let j = (k + 1) % n as usize;
            for key in ["exposure_requested_us", "exposure_reported_us"] {
                if let Some(v) = frames[j].get(&[Seg::Key(key.into())]).cloned() {
                    frames[k].set(&[Seg::Key(key.into())], v);
                }
            }
            (
                format!(
                    "frames[{k}] ({}) given the exposure of frames[{j}]",
                    file_of(&frames[k])
                ),
                false,
            )
        }
    }
}

/// Areas of a manifest that edits aim at (frames and the rig snapshot most). `rig_file`
/// is left alone: a `rig_file` of `/etc/x` would have Glint (run as root here) create
/// `/etc/profiles`; the write to where `rig_file` says is checked with the case's own
/// rig folder instead.
const MANIFEST_AREAS: &[&str] = &[
    "frames", "frames", "rig", "rig", "plan", "camera", "state", "",
];

/// Rig snapshots a stage must refuse (or survive): geometry and sizes that a rig file
/// check would catch, stored in a manifest that no check has seen.
const RIG_EDITS: &[&str] = &[
    "the lamp in the tile plane (lamp z = tile_thickness_mm)",
    "the lamp on the tile (at its first corner, z = tile_thickness_mm)",
    "the lamp below the grid (z = -300)",
    "a 1001x1000 grid (geometry.grid_inner_corners)",
    "a negative square (geometry.grid_square_mm = -25)",
    "a tile outline of one point repeated",
    "the tile above the camera (tile_thickness_mm = 1e6)",
    "camera.width = 320, twice the frames' width",
    "every exposure the same (bracket.exposures_us = [1000, 1000, ...])",
    "no rig (rig = null, as an imported session)",
];

fn apply_rig_edit(m: &mut Node, k: usize) -> String {
    let key = |s: &str| -> Vec<Seg> { s.split('.').map(|k| Seg::Key(k.into())).collect() };
    let num = |m: &Node, p: &str| match m.get(&key(p)) {
        Some(Node::Float(f)) => *f,
        Some(Node::Int(i)) => *i as f64,
        _ => 0.0,
    };
    let lamp = |i: usize| {
        let mut p = key("rig.geometry.lamp_position_mm");
        p.push(Seg::Idx(i));
        p
    };
    let t = num(m, "rig.geometry.tile_thickness_mm");
    match k {
        0 => m.set(&lamp(2), Node::Float(t)),
        1 => {
            let c = match m.get(&key("rig.geometry.tile_outline_mm")) {
                Some(Node::Arr(a)) => a.first().cloned(),
                _ => None,
            };
            if let Some(Node::Arr(xy)) = c {
                for (i, v) in xy.into_iter().take(2).enumerate() {
                    m.set(&lamp(i), v);
                }
            }
            m.set(&lamp(2), Node::Float(t));
        }
        2 => m.set(&lamp(2), Node::Float(-300.0)),
        3 => m.set(
            &key("rig.geometry.grid_inner_corners"),
            Node::Arr(vec![Node::Int(1001), Node::Int(1000)]),
        ),
        4 => m.set(&key("rig.geometry.grid_square_mm"), Node::Float(-25.0)),
        5 => {
            if let Some(Node::Arr(a)) = m.get_mut(&key("rig.geometry.tile_outline_mm")) {
                let first = a[0].clone();
                a.iter_mut().for_each(|c| *c = first.clone());
            }
        }
        6 => m.set(&key("rig.geometry.tile_thickness_mm"), Node::Float(1e6)),
        7 => m.set(&key("rig.camera.width"), Node::Int(320)),
        8 => {
            if let Some(Node::Arr(a)) = m.get_mut(&key("rig.bracket.exposures_us")) {
                a.iter_mut().for_each(|e| *e = Node::Int(1000));
            }
        }
        _ => m.set(&key("rig"), Node::Null),
    }
    RIG_EDITS[k].to_string()
}

type ManifestCase = (
    Vec<Edit>,
    Vec<TextEdit>,
    Option<FrameEdit>,
    Option<usize>,
    bool,
);

fn manifest_case_strategy() -> impl Strategy<Value = ManifestCase> {
    (
        edits(),
        prop_oneof![2 => Just(None), 1 => frame_edit().prop_map(Some)],
        prop_oneof![2 => Just(None), 1 => (0..RIG_EDITS.len()).prop_map(Some)],
        any::<bool>(),
    )
        .prop_map(|((e, t), fe, re, p)| {
            // With a rig edit, at most one other edit, so the rig edit is what is tested.
            let e = if re.is_some() {
                e.into_iter().take(1).collect()
            } else {
                e
            };
            (e, t, fe, re, p)
        })
}

/// Build one mutated manifest in a fresh case; returns the case, the description and
/// whether a frame points outside the session.
fn manifest_case((e, t, fe, re, with_profile): &ManifestCase) -> (Case, String, bool) {
    let c = Case::new(*with_profile);
    let mut m = c.manifest.clone();
    let mut log = Vec::new();
    let mut escapes = false;
    if let Some(k) = re {
        log.push(apply_rig_edit(&mut m, *k));
    }
    if let Some(fe) = fe {
        let (d, esc) = apply_frame_edit(&c, &mut m, fe);
        log.push(d);
        escapes = esc;
    }
    // Never a rig_file outside the case (see MANIFEST_AREAS).
    let rig_file = m.get(&[Seg::Key("rig_file".into())]).cloned();
    log.extend(apply(&mut m, e, MANIFEST_AREAS));
    if m.get(&[Seg::Key("rig_file".into())]) != rig_file.as_ref() {
        if let Some(v) = rig_file {
            m.set(&[Seg::Key("rig_file".into())], v);
        }
    }
    let mut text = m.json().into_bytes();
    log.extend(apply_text(&mut text, t));
    c.write_manifest(&text);
    c.rebase();
    let desc = format!(
        "manifest: {}{}",
        log.join("; "),
        if *with_profile {
            ""
        } else {
            " (no camera profile beside the rig yet)"
        }
    );
    note("input", &desc);
    (c, desc, escapes)
}

/// `session verify`'s report: each problem and warning one line (the CLI lists them), and
/// a frame outside the session is a problem.
fn check_verify(c: &Case, escapes: bool, f: &mut Findings, desc: &str) -> bool {
    let Outcome::Ok(rep) = guarded(|| glint::session::verify(&c.s)) else {
        return false;
    };
    for p in rep.problems.iter().chain(&rep.warnings) {
        f.check::<()>(
            "session::verify (a listed problem)",
            desc,
            Outcome::Err(p.clone()),
        );
    }
    if escapes && rep.intact() {
        f.add(
            "succeeds with a frame outside the session".into(),
            "session::verify",
            desc,
            "verify reports the session intact".into(),
        );
    }
    rep.intact()
}

fn manifest_load_case(i: usize, f: &mut Findings) {
    let case = nth_case("manifest-load", i, &manifest_case_strategy());
    let (c, desc, escapes) = manifest_case(&case);
    run_stages(&c, &STAGES[..2], f, &desc);
    check_verify(&c, escapes, f, &desc);
}

fn manifest_stages_case(i: usize, f: &mut Findings) {
    let case = nth_case("manifest-stages", i, &manifest_case_strategy());
    let (c, desc, escapes) = manifest_case(&case);
    // verify first (it reads every frame), then every stage.
    check_verify(&c, escapes, f, &desc);
    // A rig snapshot that `glint rig check` would refuse (item 2).
    let refused = glint::session::load(&c.s)
        .ok()
        .and_then(|m| m.rig)
        .and_then(|r| catch_unwind(AssertUnwindSafe(|| r.problems())).ok())
        .and_then(|p| p.into_iter().next());
    let ok = run_stages(&c, STAGES, f, &desc);
    if let Some(problem) = refused {
        for s in ok
            .iter()
            .filter(|s| !matches!(s.as_str(), "session::load" | "session::verify"))
        {
            f.add(
                "uses a rig snapshot that rig validation refuses".into(),
                s,
                &desc,
                format!("the manifest's rig: {}", show(&problem.to_string())),
            );
        }
    }
    if escapes {
        for s in ok
            .iter()
            .filter(|s| !matches!(s.as_str(), "session::load" | "session::verify"))
        {
            f.add(
                "succeeds with a frame outside the session".into(),
                s,
                &desc,
                String::new(),
            );
        }
    }
}

#[test]
fn fuzz_manifests_verify_and_load_without_panic() {
    run_in_children("manifest-load", CHILD_DEADLINE);
}

#[test]
fn fuzz_manifests_through_every_stage() {
    run_in_children("manifest-stages", CHILD_DEADLINE);
}

// ---------------------------------------------------------------------------------------
// Derived files.

/// A derived file, and the stages that read it (`PROFILE`: the camera profile beside the
/// rig, which `glint hdr` reads).
const DERIVED: &[(&str, &[&str])] = &[
    (
        "hdr/response.json",
        &[
            "fit::run::run",
            "validate::run",
            "hdr --response",
            "files::load_response",
        ],
    ),
    ("hdr/summary.json", &["fit::run::run", "report::write"]),
    (
        "calib/camera.json",
        &[
            "fit::run::run",
            "validate::run",
            "calib::run::load_known",
            "calib --intrinsics",
        ],
    ),
    ("fit/fit.json", &["validate::run", "report::write"]),
    ("validation/validation.json", &["report::write"]),
    ("PROFILE", &["hdr::run::run"]),
];

/// Derived folders that may be replaced by a link to a folder outside, and the stage
/// that writes there.
const DERIVED_DIRS: &[(&str, &str)] = &[
    ("hdr", "hdr::run::run"),
    ("calib", "calib::run::run_session"),
    ("fit", "fit::run::run"),
    ("validation", "validate::run"),
    ("report", "report::write"),
];

fn stage_by_name(name: &str, s: &Path, file: &Path) -> Result<(), String> {
    let e = |x: &dyn std::fmt::Display| x.to_string();
    match name {
        "hdr --response" => glint::hdr::run::run(
            s,
            &glint::hdr::run::HdrOptions {
                response_file: Some(file.into()),
                rig: Some(case_rig(s)),
                ..Default::default()
            },
            &mut |_| {},
        )
        .map(|_| ())
        .map_err(|x| e(&x)),
        "files::load_response" => glint::hdr::files::load_response(file)
            .map(|_| ())
            .map_err(|x| e(&x)),
        "calib::run::load_known" => glint::calib::run::load_known(file)
            .map(|_| ())
            .map_err(|x| e(&x)),
        "calib --intrinsics" => {
            let k = glint::calib::run::load_known(file).map_err(|x| e(&x))?;
            glint::calib::run::run_session(s, Some(&k))
                .map(|_| ())
                .map_err(|x| e(&x))
        }
        other => STAGES
            .iter()
            .find(|(n, _)| *n == other)
            .map(|(_, st)| st(s))
            .unwrap_or_else(|| panic!("unknown stage {other}")),
    }
}

type DerivedCase = (usize, (Vec<Edit>, Vec<TextEdit>), Option<usize>);

fn derived_strategy() -> impl Strategy<Value = DerivedCase> {
    (
        0..DERIVED.len(),
        edits(),
        prop_oneof![4 => Just(None), 1 => (0..DERIVED_DIRS.len()).prop_map(Some)],
    )
}

fn derived_case(i: usize, f: &mut Findings) {
    let (which, (e, t), link) = nth_case("derived", i, &derived_strategy());
    let (file, readers) = DERIVED[which];
    let c = Case::new(true);
    let path = if file == "PROFILE" {
        c.root
            .join("rig/profiles")
            .join(template().profile.file_name().unwrap())
    } else {
        c.s.join(file)
    };
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    let mut doc = Node::from_json(&v);
    let mut log = apply(&mut doc, &e, &[""]);
    let mut text = doc.json().into_bytes();
    log.extend(apply_text(&mut text, &t));
    std::fs::write(&path, &text).unwrap();
    let mut stages: Vec<&str> = readers.to_vec();
    if let Some(d) = link {
        let (dir, writer) = DERIVED_DIRS[d];
        let out = c.root.join("canary").join(dir);
        let _ = std::fs::rename(c.s.join(dir), &out);
        let _ = std::os::unix::fs::symlink(&out, c.s.join(dir));
        log.push(format!("{dir}/ a link to a folder outside the session"));
        stages.push(writer);
    }
    c.rebase();
    let name = if file == "PROFILE" {
        "the camera profile (rig/profiles/)"
    } else {
        file
    };
    let desc = format!("{name}: {}", log.join("; "));
    note("input", &desc);
    for stage in stages {
        note("stage", stage);
        let t0 = Instant::now();
        let out = guarded(|| stage_by_name(stage, &c.s, &path));
        if t0.elapsed() > SLOW {
            f.add(
                format!("slow ({} s or more on a 160x120 session)", SLOW.as_secs()),
                stage,
                &desc,
                format!("took {:.1} s", t0.elapsed().as_secs_f64()),
            );
        }
        f.check(stage, &desc, out);
        c.check_outside(f, stage, &desc);
    }
}

#[test]
fn fuzz_derived_files_read_by_later_stages() {
    run_in_children("derived", CHILD_DEADLINE);
}

// ---------------------------------------------------------------------------------------
// Derived files as a trust boundary: every file a later stage reads in
// hdr/, calib/, fit/ and validation/ replaced by a mutated copy or by a link, and each
// derived folder by a link to a folder outside, through every stage that reads them.
// Not random: every file with every change, so the counts are the same in every run.

/// A derived file and the stages that read it: with the file (or its folder) a symbolic
/// link, each of these must fail, on one line naming the link.
const TRUST_FILES: &[(&str, &[&str])] = &[
    ("hdr/radiance.exr", &["validate::run", "fit::run::run"]),
    ("hdr/variance.exr", &["validate::run", "fit::run::run"]),
    ("hdr/mask.png", &["validate::run", "fit::run::run"]),
    (
        "hdr/response.json",
        &["validate::run", "fit::run::run", "calib::run::run_session"],
    ),
    (
        "hdr/summary.json",
        &["report::write", "validate::run", "fit::run::run"],
    ),
    ("hdr/response.svg", &["report::write"]),
    (
        "calib/camera.json",
        &["report::write", "validate::run", "fit::run::run"],
    ),
    ("calib/corners.png", &["report::write"]),
    (
        "fit/fit.json",
        &["report::write", "export::load", "validate::run"],
    ),
    ("fit/samples.csv", &["export::load"]),
    ("validation/validation.json", &["report::write"]),
    ("validation/compare.png", &["report::write"]),
];

/// Each derived folder and the stage that writes it (which must refuse a link there and
/// write nothing through it).
const TRUST_DIRS: &[(&str, &str)] = &[
    ("hdr", "hdr::run::run"),
    ("calib", "calib::run::run_session"),
    ("fit", "fit::run::run"),
    ("validation", "validate::run"),
];

/// The stages of the family, readers before the writers that would replace what they
/// read: report, export, validate, fit, calibrate (and hdr, for a linked hdr/).
const TRUST_ORDER: &[&str] = &[
    "report::write",
    "export::load",
    "validate::run",
    "fit::run::run",
    "calib::run::run_session",
];

/// What a case does to a derived file (or folder).
#[derive(Debug, Clone, Copy, PartialEq)]
enum Change {
    /// Cut to half its length.
    Truncated,
    /// Every 97th byte flipped (xor 0x5a).
    Flipped,
    /// Emptied.
    Emptied,
    /// Grown (sparse) to 3 GiB: beyond every cap.
    Huge,
    /// Moved outside the session, a symbolic link to it left in its place.
    FileLink,
    /// Moved outside the session, a hard link to it left in its place (accepted: a hard
    /// link is a regular file, checked like any other; the copy outside must not change).
    HardLink,
    /// The whole folder moved outside the session, a symbolic link to it in its place.
    DirLink,
}

const FILE_CHANGES: &[Change] = &[
    Change::Truncated,
    Change::Flipped,
    Change::Emptied,
    Change::Huge,
    Change::FileLink,
    Change::HardLink,
];

/// Every case of the family: (file or folder, change).
fn trust_cases() -> Vec<(&'static str, Change)> {
    let mut v = Vec::new();
    for (file, _) in TRUST_FILES {
        for c in FILE_CHANGES {
            v.push((*file, *c));
        }
    }
    for (dir, _) in TRUST_DIRS {
        v.push((*dir, Change::DirLink));
    }
    v
}

fn st_export(s: &Path) -> Result<(), String> {
    glint::export::load(s, None)
        .map(|_| ())
        .map_err(|e| e.to_string())
}

fn trust_stage(name: &str, s: &Path) -> Result<(), String> {
    match name {
        "export::load" => st_export(s),
        other => STAGES
            .iter()
            .find(|(n, _)| *n == other)
            .map(|(_, st)| st(s))
            .unwrap_or_else(|| panic!("unknown stage {other}")),
    }
}

fn trust_case(i: usize, f: &mut Findings) {
    let (what, change) = trust_cases()[i];
    let c = Case::new(true);
    let place = c.s.join(what);
    let outside = c.root.join("canary").join(what.replace('/', "-"));
    let desc = format!("{what}: {change:?}");
    note("input", &desc);
    match change {
        Change::Truncated => {
            let b = std::fs::read(&place).unwrap();
            std::fs::write(&place, &b[..b.len() / 2]).unwrap();
        }
        Change::Flipped => {
            let mut b = std::fs::read(&place).unwrap();
            for k in (0..b.len()).step_by(97) {
                b[k] ^= 0x5a;
            }
            std::fs::write(&place, &b).unwrap();
        }
        Change::Emptied => std::fs::write(&place, b"").unwrap(),
        Change::Huge => std::fs::OpenOptions::new()
            .write(true)
            .open(&place)
            .unwrap()
            .set_len(3 << 30)
            .unwrap(),
        Change::FileLink => {
            std::fs::rename(&place, &outside).unwrap();
            std::os::unix::fs::symlink(&outside, &place).unwrap();
        }
        Change::HardLink => {
            std::fs::rename(&place, &outside).unwrap();
            std::fs::hard_link(&outside, &place).unwrap();
        }
        Change::DirLink => {
            std::fs::rename(&place, &outside).unwrap();
            std::os::unix::fs::symlink(&outside, &place).unwrap();
        }
    }
    c.rebase();
    // The stages that must refuse: those reading the linked file, or any file of the
    // linked folder, and the folder's writer.
    let must_refuse: Vec<&str> = match change {
        Change::FileLink => TRUST_FILES
            .iter()
            .find(|(p, _)| *p == what)
            .map(|(_, r)| r.to_vec())
            .unwrap_or_default(),
        Change::DirLink => {
            let mut v: Vec<&str> = TRUST_FILES
                .iter()
                .filter(|(p, _)| p.starts_with(&format!("{what}/")))
                .flat_map(|(_, r)| r.iter().copied())
                .collect();
            v.extend(
                TRUST_DIRS
                    .iter()
                    .filter(|(d, _)| *d == what)
                    .map(|(_, w)| *w),
            );
            v
        }
        _ => Vec::new(),
    };
    let mut order: Vec<&str> = TRUST_ORDER.to_vec();
    if what == "hdr" {
        order.push("hdr::run::run");
    }
    for stage in order {
        note("stage", stage);
        let t0 = Instant::now();
        let out = guarded(|| trust_stage(stage, &c.s));
        if t0.elapsed() > SLOW {
            f.add(
                format!("slow ({} s or more on a 160x120 session)", SLOW.as_secs()),
                stage,
                &desc,
                format!("took {:.1} s", t0.elapsed().as_secs_f64()),
            );
        }
        if must_refuse.contains(&stage) {
            match &out {
                Outcome::Err(e) if e.contains("symbolic link") => {}
                Outcome::Err(e) => f.add(
                    "a link refused without naming it".into(),
                    stage,
                    &desc,
                    format!("error: {}", show(e)),
                ),
                Outcome::Ok(_) => f.add(
                    "read through a symbolic link (succeeded)".into(),
                    stage,
                    &desc,
                    String::new(),
                ),
                Outcome::Panic(_) => {}
            }
        }
        f.check(stage, &desc, out);
        c.check_outside(f, stage, &desc);
    }
}

#[test]
fn fuzz_derived_folders_mutated_and_linked_through_every_stage() {
    let start = Instant::now();
    let cases = trust_cases();
    let mut f = Findings::default();
    for i in 0..cases.len() {
        in_child(&mut f, "trust", i, CHILD_DEADLINE);
    }
    let links = cases
        .iter()
        .filter(|(_, c)| matches!(c, Change::FileLink | Change::DirLink))
        .count();
    eprintln!(
        "fuzz trust: {} cases ({} files x {} changes, {} folders linked; {links} with a symbolic link, each refused by every stage that reads it)",
        cases.len(),
        TRUST_FILES.len(),
        FILE_CHANGES.len(),
        TRUST_DIRS.len()
    );
    f.finish("trust", cases.len(), start);
}

// ---------------------------------------------------------------------------------------
// PNG frames.

#[derive(Debug, Clone)]
enum PngEdit {
    /// Set an IHDR field: 0 width, 1 height, 2 bit depth, 3 colour type, 4 compression,
    /// 5 filter, 6 interlace.
    Ihdr {
        field: u8,
        value: u32,
    },
    /// Set the length field of chunk k.
    ChunkLength {
        k: u64,
        value: u32,
    },
    Truncate {
        at: u64,
    },
    Flip {
        at: u64,
        xor: u8,
    },
    Append {
        bytes: Vec<u8>,
    },
}

fn png_edit() -> impl Strategy<Value = PngEdit> {
    let big = prop::sample::select(vec![
        0u32,
        1,
        2,
        3,
        4,
        6,
        8,
        16,
        17,
        255,
        16384,
        65535,
        1 << 20,
        0x7fff_ffff,
        0x8000_0000,
        u32::MAX,
    ]);
    prop_oneof![
        3 => (0u8..7, big.clone()).prop_map(|(field, value)| PngEdit::Ihdr { field, value }),
        1 => (any::<u64>(), big).prop_map(|(k, value)| PngEdit::ChunkLength { k, value }),
        1 => any::<u64>().prop_map(|at| PngEdit::Truncate { at }),
        2 => (any::<u64>(), 1u8..=255).prop_map(|(at, xor)| PngEdit::Flip { at, xor }),
        1 => vec(any::<u8>(), 1..64).prop_map(|bytes| PngEdit::Append { bytes }),
    ]
}

/// Chunk offsets (start of the length field) of a PNG.
fn chunks(png: &[u8]) -> Vec<usize> {
    let mut out = Vec::new();
    let mut at = 8;
    while at + 12 <= png.len() {
        out.push(at);
        let len = u32::from_be_bytes(png[at..at + 4].try_into().unwrap()) as usize;
        at = match at.checked_add(12 + len) {
            Some(a) => a,
            None => break,
        };
    }
    out
}

/// Recompute the CRC of every chunk that lies within the file, so a decoder gets past it.
fn fix_crcs(png: &mut [u8]) {
    for at in chunks(png) {
        let len = u32::from_be_bytes(png[at..at + 4].try_into().unwrap()) as usize;
        let end = at + 8 + len;
        if end + 4 > png.len() {
            break;
        }
        let crc = crc32(&png[at + 4..end]);
        png[end..end + 4].copy_from_slice(&crc.to_be_bytes());
    }
}

fn crc32(bytes: &[u8]) -> u32 {
    let mut c = 0xffff_ffffu32;
    for b in bytes {
        c ^= *b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xedb8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

fn apply_png(png: &mut Vec<u8>, edits: &[PngEdit], fix: bool) -> Vec<String> {
    let mut log = Vec::new();
    for e in edits {
        match e {
            PngEdit::Ihdr { field, value } if png.len() >= 33 => {
                let (name, at, size) = [
                    ("width", 16, 4),
                    ("height", 20, 4),
                    ("bit depth", 24, 1),
                    ("colour type", 25, 1),
                    ("compression", 26, 1),
                    ("filter", 27, 1),
                    ("interlace", 28, 1),
                ][*field as usize % 7];
                let v = if size == 1 { value & 0xff } else { *value };
                if size == 4 {
                    png[at..at + 4].copy_from_slice(&v.to_be_bytes());
                } else {
                    png[at] = v as u8;
                }
                log.push(format!("IHDR {name} = {v}"));
            }
            PngEdit::ChunkLength { k, value } => {
                let c = chunks(png);
                if !c.is_empty() {
                    let i = (k % c.len() as u64) as usize;
                    let at = c[i];
                    let ty = String::from_utf8_lossy(&png[at + 4..at + 8]).into_owned();
                    png[at..at + 4].copy_from_slice(&value.to_be_bytes());
                    log.push(format!("chunk {i} ({ty}) length = {value}"));
                }
            }
            PngEdit::Truncate { at } => {
                let i = (at % (png.len() as u64 + 1)) as usize;
                png.truncate(i);
                log.push(format!("truncate to {i} bytes"));
            }
            PngEdit::Flip { at, xor } if !png.is_empty() => {
                let i = (at % png.len() as u64) as usize;
                png[i] ^= xor;
                log.push(format!("byte {i} ^= {xor:#04x}"));
            }
            PngEdit::Append { bytes } => {
                png.extend_from_slice(bytes);
                log.push(format!("append {} bytes", bytes.len()));
            }
            _ => {}
        }
    }
    if fix {
        fix_crcs(png);
        log.push("CRCs fixed".into());
    }
    log
}

fn template_frame(kind: &str) -> (String, Vec<u8>) {
    let t = template();
    let m = glint::session::load(&t.dir.join("s")).unwrap();
    let f = m
        .frames
        .iter()
        .find(|f| f.kind.as_str() == kind)
        .expect("a frame of that kind");
    (
        f.file.clone(),
        std::fs::read(t.dir.join("s").join(&f.file)).unwrap(),
    )
}

#[test]
fn fuzz_png_decode_of_mutated_frames() {
    let start = Instant::now();
    let mut r = runner("png-decode");
    let n = cases("png-decode");
    let (_, tile) = template_frame("tile");
    let (_, grid) = template_frame("grid");
    let strategy = (any::<bool>(), vec(png_edit(), 1..=3), any::<bool>());
    let mut f = Findings::default();
    for _ in 0..n {
        let (g, edits, fix) = draw(&mut r, &strategy);
        let mut png = if g { grid.clone() } else { tile.clone() };
        let log = apply_png(&mut png, &edits, fix);
        let desc = format!(
            "{} frame: {}",
            if g { "grid" } else { "tile" },
            log.join("; ")
        );
        let t0 = Instant::now();
        f.check(
            "hdr::decode",
            &desc,
            guarded(|| glint::hdr::decode(&png, "frames/x.png").map(|_| ())),
        );
        if t0.elapsed() > Duration::from_secs(5) {
            f.add(
                "slow (5 s or more for one 160x120 frame)".into(),
                "hdr::decode",
                &desc,
                format!("{:.1} s", t0.elapsed().as_secs_f64()),
            );
        }
    }
    f.finish("png-decode", n, start);
}

type PngCase = (&'static str, Vec<PngEdit>, bool);

fn png_strategy() -> impl Strategy<Value = PngCase> {
    (
        prop::sample::select(vec!["tile", "dark", "grid"]),
        vec(png_edit(), 1..=3),
        any::<bool>(),
    )
}

fn png_stages_case(i: usize, f: &mut Findings) {
    let (kind, edits, fix) = nth_case("png-stages", i, &png_strategy());
    let (file, mut png) = template_frame(kind);
    let log = apply_png(&mut png, &edits, fix);
    let desc = format!(
        "{file}: {} (the manifest's checksum updated)",
        log.join("; ")
    );
    note("input", &desc);
    let c = Case::new(true);
    std::fs::write(c.s.join(&file), &png).unwrap();
    let mut m = c.manifest.clone();
    if let Some(Node::Arr(frames)) = m.get_mut(&[Seg::Key("frames".into())]) {
        for fr in frames.iter_mut() {
            if fr.get(&[Seg::Key("file".into())]) == Some(&Node::Str(file.clone())) {
                fr.set(
                    &[Seg::Key("sha256".into())],
                    Node::Str(glint::session::sha256_hex(&png)),
                );
            }
        }
    }
    c.write_manifest(m.json().as_bytes());
    c.rebase();
    let stages: Vec<(&str, StageFn)> = STAGES
        .iter()
        .copied()
        .filter(|(n, _)| {
            matches!(*n, "session::verify" | "hdr::run::run" | "validate::run")
                || (kind == "grid" && *n == "calib::run::run_session")
        })
        .collect();
    let ok = run_stages(&c, &stages, f, &desc);
    // A frame whose size or depth differs from the manifest's must be refused by every
    // stage that reads it: grid frames calibration, tile and dark frames hdr and
    // validation (which do not read grid frames).
    let reads = |s: &str| match kind {
        "grid" => s == "calib::run::run_session",
        _ => matches!(s, "hdr::run::run" | "validate::run"),
    };
    if let Ok((w, h, bits, _)) = glint::hdr::decode(&png, &file) {
        if (w, h, bits) != (160, 120, 8) {
            for s in ok.iter().filter(|s| reads(s)) {
                f.add(
                    "accepts a frame whose size or depth differs from the manifest".into(),
                    s,
                    &desc,
                    format!("decoded {w}x{h} {bits}-bit, the manifest says 160x120 8-bit"),
                );
            }
        }
    }
}

#[test]
fn fuzz_png_frames_through_the_stages() {
    run_in_children("png-stages", CHILD_DEADLINE);
}

// ---------------------------------------------------------------------------------------
// Serial replies.

/// One scripted reply to a written line.
#[derive(Debug, Clone)]
enum Reply {
    Bytes(Vec<u8>),
    Silence,
    /// Bytes that never stop (no newline).
    Endless(u8),
    /// The port fails.
    IoError,
}

fn reply() -> impl Strategy<Value = Reply> {
    let canned = prop::sample::select(vec![
        &b"OK\n"[..],
        b"OK\r\n",
        b"OFF\n",
        b"ON 1000\n",
        b"ON 700\n",
        b"ON 99999\n",
        b"ON -1\n",
        b"ON\n",
        b"GLINT-MOCK-LAMP,1.0\n",
        b"ERR 2 level out of range\n",
        b"\n",
        b"\r\n",
        b"\r",
        b"OK",
        b"O",
        b"\xff\xfe\n",
        b"OK\0\n",
        b"OK\nOK\n",
        b"ERR\n",
    ])
    .prop_map(|b| Reply::Bytes(b.to_vec()));
    prop_oneof![
        6 => canned,
        2 => vec(any::<u8>(), 0..64).prop_map(Reply::Bytes),
        1 => (1usize..20_000, any::<bool>()).prop_map(|(n, nl)| {
            let mut v = vec![b'E'; n];
            v[..3.min(n)].copy_from_slice(&b"ERR"[..3.min(n)]);
            if nl { v.push(b'\n'); }
            Reply::Bytes(v)
        }),
        1 => (1usize..20_000).prop_map(|n| { let mut v = vec![b'A'; n]; v.push(b'\n'); Reply::Bytes(v) }),
        2 => Just(Reply::Silence),
        1 => any::<u8>().prop_map(|b| Reply::Endless(if b == b'\n' { b'x' } else { b })),
        1 => Just(Reply::IoError),
    ]
}

/// A scripted port: each line written takes the next reply; reads wait 1 ms when nothing
/// is pending (like a serial port's short timeout).
struct Port {
    replies: std::collections::VecDeque<Reply>,
    pending: std::collections::VecDeque<u8>,
    endless: Option<u8>,
    broken: bool,
}

impl Read for Port {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        if self.broken {
            return Err(std::io::Error::new(
                ErrorKind::BrokenPipe,
                "the port went away",
            ));
        }
        if let Some(b) = self.pending.pop_front() {
            buf[0] = b;
            return Ok(1);
        }
        if let Some(b) = self.endless {
            buf[0] = b;
            return Ok(1);
        }
        std::thread::sleep(Duration::from_millis(1));
        Err(ErrorKind::TimedOut.into())
    }
}

impl Write for Port {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        if buf.ends_with(b"\n") {
            match self.replies.pop_front() {
                Some(Reply::Bytes(b)) => self.pending.extend(b),
                Some(Reply::Endless(b)) => self.endless = Some(b),
                Some(Reply::IoError) => self.broken = true,
                Some(Reply::Silence) | None => {}
            }
        }
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

#[derive(Debug, Clone, Copy)]
enum LampOp {
    Identify,
    On(u16),
    Off,
    State,
}

impl LampOp {
    /// Commands (transactions) the op sends at most.
    fn transactions(self) -> u32 {
        match self {
            LampOp::On(_) => 3,
            LampOp::Off => 2,
            _ => 1,
        }
    }
}

#[test]
fn fuzz_serial_lamp_replies() {
    let start = Instant::now();
    let mut r = runner("serial");
    let n = cases("serial");
    let op = prop_oneof![
        Just(LampOp::Identify),
        prop::sample::select(vec![0u16, 1, 700, 1000, 1001, u16::MAX]).prop_map(LampOp::On),
        Just(LampOp::Off),
        Just(LampOp::State),
    ];
    let strategy = (vec(op, 1..=3), vec(reply(), 0..12), 1u32..=3, 2u64..=8);
    let all: Vec<SerialCase> = (0..n).map(|_| draw(&mut r, &strategy)).collect();
    // The cases mostly wait (reply deadlines): four at a time.
    let mut f = Findings::default();
    std::thread::scope(|scope| {
        let workers: Vec<_> = all
            .chunks(n.div_ceil(4))
            .map(|chunk| {
                scope.spawn(move || {
                    let mut f = Findings::default();
                    for c in chunk {
                        serial_case(c, &mut f);
                    }
                    f
                })
            })
            .collect();
        for w in workers {
            f.merge(w.join().expect("a serial fuzz worker"));
        }
    });
    f.finish("serial", n, start);
}

type SerialCase = (Vec<LampOp>, Vec<Reply>, u32, u64);

fn serial_case((ops, replies, tries, timeout_ms): &SerialCase, f: &mut Findings) {
    use glint::devices::Lamp;
    let (tries, timeout_ms) = (*tries, *timeout_ms);
    let desc = format!(
        "ops {ops:?}, tries {tries}, timeout {timeout_ms} ms, replies {:?}",
        replies
            .iter()
            .map(|r| match r {
                Reply::Bytes(b) if b.len() > 24 =>
                    format!("{} bytes {:?}…", b.len(), String::from_utf8_lossy(&b[..8])),
                Reply::Bytes(b) => format!("{:?}", String::from_utf8_lossy(b)),
                other => format!("{other:?}"),
            })
            .collect::<Vec<_>>()
    );
    let policy =
        glint::devices::serial_lamp::LampPolicy::glint(Duration::from_millis(timeout_ms), tries);
    let port = Port {
        replies: replies.clone().into(),
        pending: Default::default(),
        endless: None,
        broken: false,
    };
    let mut lamp = glint::devices::serial_lamp::SerialLamp::new(port, "fuzz lamp".into(), policy);
    // Each try: a reply deadline; after a command that used retries or failed, up to two
    // deadlines more for the replies still owed.
    let budget: u32 = ops.iter().map(|o| o.transactions()).sum::<u32>() * (tries + 2);
    let limit = Duration::from_millis(budget as u64 * (timeout_ms + 40) + 250);
    let t0 = Instant::now();
    for op in ops {
        let out = guarded(|| match op {
            LampOp::Identify => lamp.identify().map(|_| ()),
            LampOp::On(l) => lamp.switch_on(*l).map(|_| ()),
            LampOp::Off => lamp.switch_off().map(|_| ()),
            LampOp::State => lamp.state().map(|_| ()),
        });
        let name = format!("SerialLamp {op:?}");
        let name = name.split('(').next().unwrap_or_default();
        f.check(name, &desc, out);
    }
    if t0.elapsed() > limit {
        f.add(
            "took longer than its tries and timeouts allow".into(),
            "SerialLamp",
            &desc,
            format!(
                "{:.0} ms, limit {} ms",
                t0.elapsed().as_secs_f64() * 1e3,
                limit.as_millis()
            ),
        );
    }
}

// ---------------------------------------------------------------------------------------
// The lamp during a capture: a firmware that answers every command correctly except where
// a fault is scripted (a garbled, silent, endless or failing reply to command k). Whatever
// happens, the lamp is off at the end (an OFF follows the last ON) and a failed capture
// leaves its manifest `failed`. The firmware switches the simulated lab's lamp as it is
// told, so the camera sees light and a capture without a fault that matters completes.

struct Firmware {
    /// The simulated lab's own lamp, switched as this firmware is.
    light: Box<dyn glint::devices::Lamp>,
    on: bool,
    level: u16,
    /// Commands received so far.
    n: usize,
    faults: BTreeMap<usize, Reply>,
    line: Vec<u8>,
    written: std::sync::Arc<Mutex<Vec<String>>>,
    pending: std::collections::VecDeque<u8>,
    endless: Option<u8>,
    broken: bool,
}

impl Read for Firmware {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        if self.broken {
            self.broken = false;
            return Err(std::io::Error::new(
                ErrorKind::BrokenPipe,
                "the port went away",
            ));
        }
        if let Some(b) = self.pending.pop_front() {
            buf[0] = b;
            return Ok(1);
        }
        if let Some(b) = self.endless {
            buf[0] = b;
            return Ok(1);
        }
        std::thread::sleep(Duration::from_millis(1));
        Err(ErrorKind::TimedOut.into())
    }
}

impl Write for Firmware {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        for &b in buf {
            if b != b'\n' {
                self.line.push(b);
                continue;
            }
            let cmd = String::from_utf8_lossy(&std::mem::take(&mut self.line)).into_owned();
            self.endless = None;
            let reply = match cmd.as_str() {
                "*IDN?" => "FUZZ-LAMP,1.0".to_string(),
                "ON" => {
                    self.on = true;
                    let _ = self.light.switch_on(self.level);
                    "OK".into()
                }
                "OFF" => {
                    self.on = false;
                    let _ = self.light.switch_off();
                    "OK".into()
                }
                "STATE?" if self.on => format!("ON {}", self.level),
                "STATE?" => "OFF".into(),
                c if c.starts_with("LEVEL ") => match c[6..].parse() {
                    Ok(l) => {
                        self.level = l;
                        "OK".into()
                    }
                    Err(_) => "ERR 2 bad level".into(),
                },
                _ => "ERR 1 unknown command".into(),
            };
            self.written.lock().unwrap().push(cmd);
            match self.faults.get(&self.n) {
                Some(Reply::Bytes(b)) => self.pending.extend(b.iter().copied()),
                Some(Reply::Endless(b)) => self.endless = Some(*b),
                Some(Reply::IoError) => self.broken = true,
                Some(Reply::Silence) => {}
                None => self.pending.extend(format!("{reply}\n").bytes()),
            }
            self.n += 1;
        }
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

#[test]
fn fuzz_lamp_replies_during_a_capture() {
    let start = Instant::now();
    let mut r = runner("capture");
    let n = cases("capture");
    let strategy = (
        vec((0usize..40, reply()), 1..=3),
        1u32..=3,
        prop::sample::select(vec![0u16, 1, 1000]),
    );
    let mut f = Findings::default();
    for _ in 0..n {
        let (faults, tries, level) = draw(&mut r, &strategy);
        let faults: BTreeMap<usize, Reply> = faults.into_iter().collect();
        let desc = format!(
            "lamp.tries {tries}, lamp.level {level}, faults {:?}",
            faults
                .iter()
                .map(|(k, r)| match r {
                    Reply::Bytes(b) if b.len() > 24 => format!(
                        "reply {k}: {} bytes {:?}…",
                        b.len(),
                        String::from_utf8_lossy(&b[..8])
                    ),
                    Reply::Bytes(b) => format!("reply {k}: {:?}", String::from_utf8_lossy(b)),
                    other => format!("reply {k}: {other:?}"),
                })
                .collect::<Vec<_>>()
        );
        let dir = super::util::tempdir();
        let mut t = small_table();
        super::util::set(&mut t, "lamp.tries", tries as i64);
        super::util::set(&mut t, "lamp.level", level as i64);
        let rig = super::util::load(dir.path(), &t);
        let written = std::sync::Arc::new(Mutex::new(Vec::new()));
        let glint::devices::Devices {
            camera,
            lamp: light,
            operator,
            lab,
        } = glint::devices::open(&rig).unwrap();
        let firmware = Firmware {
            light,
            on: false,
            level: 0,
            n: 0,
            faults,
            line: Vec::new(),
            written: written.clone(),
            pending: Default::default(),
            endless: None,
            broken: false,
        };
        let policy =
            glint::devices::serial_lamp::LampPolicy::glint(Duration::from_millis(5), tries);
        let devices = glint::devices::Devices {
            camera,
            lamp: Box::new(glint::devices::serial_lamp::SerialLamp::new(
                firmware,
                "fuzz lamp".into(),
                policy,
            )),
            operator,
            lab,
        };
        let out = dir.path().join("s");
        let t0 = Instant::now();
        let res = guarded(|| {
            glint::capture::record(&rig, devices, &out, Default::default(), &mut |_| {}).map(|_| ())
        });
        let failed = matches!(res, Outcome::Err(_));
        if let Outcome::Err(e) = &res {
            if let Ok(v) = std::fs::read(out.join("manifest.json")) {
                let state = serde_json::from_slice::<serde_json::Value>(&v)
                    .ok()
                    .and_then(|m| m["state"].as_str().map(String::from))
                    .unwrap_or_default();
                if state != "failed" {
                    f.add(
                        format!("a failed capture leaves the manifest `{state}`"),
                        "capture::record",
                        &desc,
                        format!("error: {}", show(e)),
                    );
                }
            }
        }
        if let Outcome::Ok(()) = &res {
            // A capture that succeeds is whole.
            match glint::session::verify(&out) {
                Ok(rep) if rep.intact() => {}
                Ok(rep) => f.add(
                    "a capture that succeeded is not intact".into(),
                    "capture::record",
                    &desc,
                    rep.problems.join("; "),
                ),
                Err(e) => f.add(
                    "a capture that succeeded is not intact".into(),
                    "capture::record",
                    &desc,
                    show(&e.to_string()),
                ),
            }
        }
        f.check("capture::record", &desc, res);
        let cmds = written.lock().unwrap().clone();
        let last_on = cmds.iter().rposition(|c| c == "ON");
        let last_off = cmds.iter().rposition(|c| c == "OFF");
        if let Some(on) = last_on {
            if last_off.is_none_or(|off| off < on) {
                f.add(
                    "the lamp is left on: no OFF after the last ON".into(),
                    "capture::record",
                    &desc,
                    format!(
                        "capture {}; commands: {}",
                        if failed { "failed" } else { "succeeded" },
                        cmds.join(" | ")
                    ),
                );
            }
        }
        if t0.elapsed() > SLOW {
            f.add(
                format!("slow ({} s or more for a 160x120 capture)", SLOW.as_secs()),
                "capture::record",
                &desc,
                format!("{:.1} s", t0.elapsed().as_secs_f64()),
            );
        }
    }
    f.finish("capture", n, start);
}

// ---------------------------------------------------------------------------------------
// The daemon's journal: torn, flipped, garbage, forged; each replayed.

mod journal_fuzz {
    use super::*;
    use glint::daemon::journal::{self as jr, Book, Record};
    use glint::daemon::protocol::{Job, JobKind, JobSpec, JobState};

    fn job(id: u64) -> Job {
        Job::queued(
            id,
            JobSpec::new(JobKind::Capture),
            Some("uid 1000, pid 1".into()),
            "2026-12-06T00:00:00.000000Z".into(),
        )
    }
    fn added(id: u64) -> Record {
        Record::Added {
            job: Box::new(job(id)),
        }
    }
    fn started(id: u64) -> Record {
        Record::Started {
            job: id,
            at: "2026-12-06T00:00:01.000000Z".into(),
            session: Some(format!("/data/s{id}").into()),
        }
    }
    fn ended(id: u64, state: JobState) -> Record {
        Record::Ended {
            job: id,
            state,
            at: "2026-12-06T00:00:02.000000Z".into(),
            error: None,
            summary: Some(serde_json::json!({"frames": id})),
            summary_text: Some(format!("job {id}")),
        }
    }

    /// A journal as a daemon leaves it: a snapshot (jobs 1 and 2 ended, 3 queued), then a
    /// daemon's records, killed while job 6 runs. Replayed: 4 and 7 queued, 6 running.
    fn base() -> Vec<Record> {
        let mut b = Book {
            next_id: 1,
            ..Book::default()
        };
        for r in [
            added(1),
            added(2),
            added(3),
            started(1),
            ended(1, JobState::Complete),
            started(2),
            ended(2, JobState::Failed),
        ] {
            b.apply(&r).unwrap();
        }
        vec![
            b.snapshot(),
            Record::Opened {
                pid: 7,
                at: "t".into(),
            },
            added(4),
            added(5),
            added(6),
            Record::Moved { job: 6, to: 0 },
            Record::Removed { job: 5 },
            started(3),
            ended(3, JobState::Complete),
            added(7),
            started(6),
        ]
    }

    fn line(r: &Record, checked: bool) -> Vec<u8> {
        if checked {
            jr::encode(r).unwrap()
        } else {
            let mut l = serde_json::to_vec(r).unwrap();
            l.push(b'\n');
            l
        }
    }

    /// A JSON object as a line with a valid checksum (a forger who knows the format).
    fn forged(json: &str) -> Vec<u8> {
        let crc = crc32(json.as_bytes());
        let mut l = json.as_bytes()[..json.len() - 1].to_vec();
        l.extend_from_slice(format!(",\"crc\":\"{crc:08x}\"}}\n").as_bytes());
        l
    }

    /// The job ids a line names (read leniently).
    fn named(line: &[u8]) -> Vec<u64> {
        let text = String::from_utf8_lossy(line);
        let v: serde_json::Value = match serde_json::from_str(text.trim_end()) {
            Ok(v) => v,
            Err(_) => return Vec::new(),
        };
        let mut ids: Vec<u64> = [v["job"].as_u64(), v["job"]["id"].as_u64()]
            .into_iter()
            .flatten()
            .collect();
        if let Some(jobs) = v["jobs"].as_array() {
            ids.extend(jobs.iter().filter_map(|j| j["id"].as_u64()));
        }
        ids
    }

    /// The jobs a record taken as real can shadow: all ids up to the largest it names.
    fn shadowed(line: &[u8]) -> Vec<u64> {
        let max = named(line).into_iter().max().unwrap_or(0);
        (1..=7).filter(|&j| j <= max).collect()
    }

    struct Case {
        desc: String,
        text: Vec<u8>,
        /// The book exactly as it must replay, when known.
        exact: Option<Book>,
        /// Lines that must be set aside, when known.
        damaged: Option<usize>,
        /// Jobs a changed line names (they may be lost, started or ended).
        touched: Vec<u64>,
    }

    fn queued(b: &Book) -> Vec<u64> {
        b.queue.clone()
    }

    /// Replay one case; check what must hold.
    fn check(c: &Case, original: &Book, open: bool, f: &mut Findings) {
        let out = guarded(|| Ok::<_, String>(jr::replay(Path::new("journal.jsonl"), &c.text)));
        let Some(r) = f.check("journal::replay", &c.desc, out) else {
            return;
        };
        let bad = |f: &mut Findings, what: &str, detail: String| {
            f.add(what.to_string(), "journal::replay", &c.desc, detail)
        };
        if let Some(exact) = &c.exact {
            if &r.book != exact {
                bad(
                    f,
                    "replayed to another book than the whole records give",
                    format!("queue {:?}, expected {:?}", r.book.queue, exact.queue),
                );
            }
        }
        if let Some(n) = c.damaged {
            if r.damaged_count != n {
                bad(
                    f,
                    "set aside another number of lines",
                    format!(
                        "{} set aside, expected {n}: {:?}",
                        r.damaged_count, r.damaged
                    ),
                );
            }
        }
        // Queued jobs kept: each queued before and named by no changed line still is.
        for id in queued(original) {
            if !c.touched.contains(&id) && !r.book.queue.contains(&id) {
                bad(
                    f,
                    "a queued job was lost",
                    format!("job {id}; queue {:?}", r.book.queue),
                );
            }
        }
        // Never re-run: a job that started or ended is never queued again.
        for (id, j) in &original.jobs {
            if j.state != JobState::Queued && !c.touched.contains(id) && r.book.queue.contains(id) {
                bad(
                    f,
                    "a job that ran is queued again",
                    format!("job {id} was {}", j.state.name()),
                );
            }
        }
        if r.book.next_id < original.next_id
            && !c
                .touched
                .iter()
                .any(|&id| id.saturating_add(1) >= original.next_id)
        {
            bad(
                f,
                "next_id went back (an id would be given out again)",
                format!("{} < {}", r.book.next_id, original.next_id),
            );
        }
        // What the daemon writes at start reads back whole, to the same book.
        let snap = jr::encode(&r.book.snapshot()).unwrap();
        let again = jr::replay(Path::new("journal.jsonl"), &snap);
        if again.damaged_count != 0 || again.book != r.book {
            bad(
                f,
                "the snapshot written at start does not replay to the same book",
                format!("{:?}", again.notes),
            );
        }
        if r.notes
            .iter()
            .any(|n| n.contains('\n') || n.len() > MAX_MESSAGE)
        {
            bad(f, "a note is not one short line", format!("{:?}", r.notes));
        }
        if open {
            // Through the daemon's open: never refused, the damaged journal kept aside.
            let dir = super::super::util::tempdir();
            std::fs::write(dir.path().join("journal.jsonl"), &c.text).unwrap();
            let out = guarded(|| jr::Journal::open(dir.path()).map(|(_, r)| r));
            match out {
                Outcome::Ok(o) => {
                    let kept = o
                        .set_aside
                        .as_ref()
                        .and_then(|p| std::fs::read(p).ok())
                        .is_some_and(|t| t == c.text);
                    if (o.damaged_count > 0) != kept {
                        bad(
                            f,
                            "the damaged journal is not kept aside as it was read",
                            format!("{:?}", o.set_aside),
                        );
                    }
                    match jr::Journal::open(dir.path()) {
                        Ok((_, o2)) if o2.damaged_count == 0 && o2.book.queue == o.book.queue => {}
                        Ok((_, o2)) => bad(
                            f,
                            "the journal written at start is damaged at the next",
                            format!("{:?}", o2.notes),
                        ),
                        Err(e) => bad(f, "the journal written at start is refused", e.to_string()),
                    }
                }
                Outcome::Err(e) => f.add(
                    "Journal::open refused a readable journal".into(),
                    "journal::open",
                    &c.desc,
                    show(&e),
                ),
                Outcome::Panic(p) => f.add(
                    format!("panic at {}", p.location),
                    "journal::open",
                    &c.desc,
                    p.message,
                ),
            }
        }
    }

    fn garbage() -> impl Strategy<Value = Vec<u8>> {
        prop_oneof![
            vec(any::<u8>(), 1..200).prop_map(|mut v| {
                v.retain(|b| *b != b'\n');
                v.push(b'x');
                v
            }),
            "[ -~]{1,120}".prop_map(String::into_bytes),
            Just(b"{}".to_vec()),
            Just(b"[]".to_vec()),
            Just(b"null".to_vec()),
            Just(b"{\"record\":\"added\"}".to_vec()),
            Just(b"{\"record\":\"snapshot\",\"next_id\":1,\"queue\":[],\"jobs\":[]}".to_vec()),
            Just(b"{\"record\":\"removed\",\"job\":4,\"crc\":\"00000000\"}".to_vec()),
            Just(vec![b'['; 5000]),
            Just(vec![b'a'; 100_000]),
            Just(vec![0xff, 0xfe, b'{', 0xc3]),
        ]
    }

    /// A forged record (valid JSON, for the checksum a valid one or none): ids that do not
    /// exist, an `ended` before its `started`, duplicate ids, huge numbers.
    fn forgery() -> impl Strategy<Value = String> {
        let id = prop_oneof![
            Just("0"),
            Just("1"),
            Just("3"),
            Just("4"),
            Just("6"),
            Just("7"),
            Just("99"),
            Just("9007199254740991"),
            Just("9007199254740992"),
            Just("18446744073709551615"),
            Just("18446744073709551616"),
            Just("-1"),
            Just("1e300"),
            Just("4.5"),
            Just("null"),
            Just("\"4\""),
        ];
        let state = prop_oneof![
            Just("queued"),
            Just("running"),
            Just("complete"),
            Just("interrupted"),
            Just("bogus")
        ];
        (0..9usize, id, state, id_to()).prop_map(|(k, id, state, to)| {
            let job = format!(
                "{{\"id\":{id},\"spec\":{{\"kind\":\"capture\"}},\"state\":\"{state}\",\"queued\":\"t\"}}"
            );
            match k {
                0 => format!("{{\"record\":\"added\",\"job\":{job}}}"),
                1 => format!("{{\"record\":\"removed\",\"job\":{id}}}"),
                2 => format!("{{\"record\":\"moved\",\"job\":{id},\"to\":{to}}}"),
                3 => format!("{{\"record\":\"started\",\"job\":{id},\"at\":\"t\"}}"),
                4 => format!(
                    "{{\"record\":\"ended\",\"job\":{id},\"state\":\"{state}\",\"at\":\"t\"}}"
                ),
                5 => format!(
                    "{{\"record\":\"snapshot\",\"next_id\":{id},\"queue\":[{id}],\"jobs\":[{job}]}}"
                ),
                6 => format!("{{\"record\":\"opened\",\"pid\":{id},\"at\":\"t\"}}"),
                7 => "{\"record\":\"closed\",\"at\":\"t\"}".to_string(),
                _ => format!("{{\"record\":\"added\",\"job\":{job},\"extra\":[1,2]}}"),
            }
        })
    }

    fn id_to() -> impl Strategy<Value = String> {
        prop_oneof![
            Just("0".to_string()),
            Just("1".to_string()),
            Just("18446744073709551615".to_string()),
            Just("-3".to_string())
        ]
    }

    #[derive(Debug, Clone)]
    enum Mutation {
        Garbage(usize, Vec<u8>),
        Forged(usize, String, bool),
        Flip(usize, u8),
    }

    fn mutation() -> impl Strategy<Value = Mutation> {
        prop_oneof![
            (0..20usize, garbage()).prop_map(|(at, g)| Mutation::Garbage(at, g)),
            (0..20usize, forgery(), any::<bool>())
                .prop_map(|(at, j, sum)| Mutation::Forged(at, j, sum)),
            (any::<usize>(), 1..=255u8).prop_map(|(at, x)| Mutation::Flip(at, x)),
        ]
    }

    #[test]
    fn fuzz_journal_torn_flipped_garbage_and_forged_lines_are_replayed_never_refused() {
        let start = Instant::now();
        let mut f = Findings::default();
        let mut n = 0;
        let recs = base();
        for checked in [true, false] {
            let lines: Vec<Vec<u8>> = recs.iter().map(|r| line(r, checked)).collect();
            let text: Vec<u8> = lines.concat();
            let original = jr::replay(Path::new("j"), &text);
            assert_eq!(original.damaged_count, 0, "{:?}", original.notes);
            assert_eq!(original.book.queue, vec![4, 7]);
            let original = original.book;
            let form = if checked {
                "checksummed"
            } else {
                "old (no checksums)"
            };
            // Torn at every byte of its last three records (a crash while writing).
            let first_torn = lines[..lines.len() - 3].concat().len();
            for k in first_torn..text.len() {
                // A cut just before an end of line leaves that line whole.
                let mid = k > 0 && text[k - 1] != b'\n' && text[k] != b'\n';
                let before =
                    text[..k].iter().filter(|b| **b == b'\n').count() + (text[k] == b'\n') as usize;
                let whole = jr::replay(Path::new("j"), lines[..before].concat()).book;
                let c = Case {
                    desc: format!("{form} journal torn at byte {k}"),
                    text: text[..k].to_vec(),
                    exact: Some(whole),
                    damaged: Some(mid as usize),
                    touched: (4..=7).collect(),
                };
                check(&c, &original, n % 16 == 0, &mut f);
                n += 1;
                // The old failure: later records appended onto the torn line.
                if mid {
                    let mut t = text[..k].to_vec();
                    t.extend(lines[lines.len() - 2..].concat());
                    let c = Case {
                        desc: format!("{form} journal torn at byte {k}, then appended to"),
                        text: t,
                        exact: None,
                        damaged: None,
                        touched: (3..=7).collect(),
                    };
                    check(&c, &original, false, &mut f);
                    n += 1;
                }
            }
            if checked {
                // Every byte of two records flipped (a bit, and to another character): the
                // checksum catches each.
                for which in [2, lines.len() - 1] {
                    let at = lines[..which].concat().len();
                    for i in 0..lines[which].len() - 1 {
                        for x in [0x01u8, 0x20] {
                            let mut t = text.clone();
                            t[at + i] ^= x;
                            if t[at + i] == b'\n' {
                                continue;
                            }
                            let mut touched = named(&lines[which]);
                            touched.extend(named(&t[at..at + lines[which].len()]));
                            let mut exact_lines = lines.clone();
                            exact_lines.remove(which);
                            let c = Case {
                                desc: format!("line {} byte {i} xor {x:#04x}", which + 1),
                                text: t,
                                exact: (which == 2)
                                    .then(|| jr::replay(Path::new("j"), exact_lines.concat()).book),
                                damaged: Some(1),
                                touched,
                            };
                            check(&c, &original, n % 16 == 0, &mut f);
                            n += 1;
                        }
                    }
                }
            }
            // Random lines of garbage, forged records and flipped bytes, one to four a case.
            let mut r = runner("journal");
            let each = cases("journal");
            for k in 0..each {
                let ms = draw(&mut r, &vec(mutation(), 1..=4));
                let mut ls = lines.clone();
                let mut touched = Vec::new();
                let mut only_garbage = true;
                let mut garbage_lines = 0;
                let mut desc = Vec::new();
                for m in &ms {
                    match m {
                        Mutation::Garbage(at, g) => {
                            let mut l = g.clone();
                            l.push(b'\n');
                            garbage_lines += !l.iter().all(u8::is_ascii_whitespace) as usize;
                            let at = (*at).clamp(1, ls.len());
                            desc.push(format!("garbage at line {}: {}", at + 1, brief_bytes(g)));
                            ls.insert(at, l);
                        }
                        Mutation::Forged(at, json, sum) => {
                            only_garbage = false;
                            let l = if *sum {
                                forged(json)
                            } else {
                                format!("{json}\n").into_bytes()
                            };
                            touched.extend(named(&l));
                            if *sum || !checked {
                                // A forged record the journal cannot tell from a real one:
                                // an `added` takes its id, and a later job of that id or
                                // below is refused as added twice.
                                touched.extend(shadowed(&l));
                            }
                            let at = (*at).clamp(1, ls.len());
                            desc.push(format!(
                                "forged at line {}{}: {json}",
                                at + 1,
                                if *sum { " with its checksum" } else { "" }
                            ));
                            ls.insert(at, l);
                        }
                        Mutation::Flip(at, x) => {
                            only_garbage = false;
                            let total: usize = ls.iter().map(Vec::len).sum();
                            let mut at = at % total;
                            for i in 0..ls.len() {
                                if at < ls[i].len() {
                                    touched.extend(named(&ls[i]));
                                    if at + 1 == ls[i].len() {
                                        // Its end of line: joined to the next.
                                        touched.extend(
                                            ls.get(i + 1).map(|l| named(l)).unwrap_or_default(),
                                        );
                                    }
                                    ls[i][at] ^= x;
                                    touched.extend(named(&ls[i]));
                                    if !checked {
                                        // Without checksums a flip may go unseen.
                                        touched.extend(shadowed(&ls[i]));
                                    }
                                    desc.push(format!(
                                        "byte {at} of line {} flipped ^{x:#04x}",
                                        i + 1
                                    ));
                                    break;
                                }
                                at -= ls[i].len();
                            }
                        }
                    }
                }
                let c = Case {
                    desc: format!("{form} [journal:{k}] {}", desc.join("; ")),
                    text: ls.concat(),
                    exact: only_garbage.then(|| original.clone()),
                    damaged: only_garbage.then_some(garbage_lines),
                    touched,
                };
                check(&c, &original, k % 8 == 0, &mut f);
                n += 1;
            }
        }
        f.finish("journal", n, start);
    }

    fn brief_bytes(b: &[u8]) -> String {
        let s = String::from_utf8_lossy(&b[..b.len().min(60)]).to_string();
        format!(
            "{s:?}{}",
            if b.len() > 60 {
                format!(" ({} bytes)", b.len())
            } else {
                String::new()
            }
        )
    }
}
use serde_json::{json, Value};

// ---------------------------------------------------------------------------------------
// The daemon: a session's events file and the daemon's replies are
// input like any file. Oracles: never a panic, never a raw control character on the
// terminal, never exit 0 on an outcome the journal does not hold, a client never hangs.

/// What is wrong with one client run, if anything: a panic, a raw control character, a
/// run longer than `limit`.
fn client_run_problem(o: &std::process::Output, took: Duration, limit: Duration) -> Option<String> {
    let err = String::from_utf8_lossy(&o.stderr);
    if o.status.code() == Some(101) || err.contains("panicked") {
        return Some(format!("a panic: {}", show(&err)));
    }
    if o.status.code().is_none() {
        return Some(format!("killed by a signal: {:?}", o.status));
    }
    if let Some(bad) = super::daemon::raw_controls(o) {
        return Some(format!("a raw control character: {}", show(&bad)));
    }
    if took > limit {
        return Some(format!("took {took:?}"));
    }
    None
}

/// One piece of a forged `events.jsonl` for job `id`.
fn forged_event_piece(r: &mut TestRunner, id: u64, real: &[String]) -> (String, Vec<u8>) {
    let evil = [
        "FAKE",
        "FAKE\u{1b}[2J\u{1b}]0;t\u{7}",
        "FAKE\r\nsession: /etc",
        "FAKE\u{9b}31m\u{202e}",
    ];
    let e = evil[draw(r, &(0..evil.len()))];
    // History may be printed (escaped); only an outcome's text must never be.
    let hist = e.replace("FAKE", "HIST");
    let job: Value = match draw(r, &(0..6usize)) {
        0 => json!(id + 1),
        1 => json!("x"),
        2 => Value::Null,
        _ => json!(id),
    };
    let state = [
        "complete", "failed", "aborted", "queued", "running", "nonsense",
    ][draw(r, &(0..6usize))];
    let line = |v: Value| v.to_string().into_bytes();
    match draw(r, &(0..11usize)) {
        0 | 1 => (
            format!("job-ended {state} job {job}"),
            line(
                json!({"seq": 9999, "event": "job-ended", "job": job, "state": state,
                        "summary_text": e, "summary": {"fake": e}, "error": e, "session": e}),
            ),
        ),
        2 => (
            "resync complete".into(),
            line(
                json!({"seq": 1, "event": "resync", "job": {"id": id, "state": "complete",
                        "spec": {"kind": "run"}, "queued": "x", "summary_text": e}, "missed": 1}),
            ),
        ),
        3 => (
            "operator".into(),
            line(json!({"seq": 2, "event": "operator", "job": job, "message": e, "timeout_s": 1})),
        ),
        4 => (
            "job-removed".into(),
            line(json!({"seq": 3, "event": "job-removed", "job": job})),
        ),
        5 => {
            // A torn line: a real one cut short.
            let l = real[draw(r, &(0..real.len()))].as_bytes();
            let cut = draw(r, &(0..l.len().max(1)));
            ("torn".into(), l[..cut].to_vec())
        }
        6 => ("garbage".into(), draw(r, &vec(any::<u8>(), 0..200))),
        7 => (
            "nested end".into(),
            line(
                json!({"seq": 4, "event": "warning", "job": id, "message": hist,
                        "x": {"event": "job-ended", "state": "complete"}}),
            ),
        ),
        8 => (
            "progress with escapes".into(),
            line(
                json!({"seq": 5, "event": (["step", "warning", "job-started", "hdr"][draw(r, &(0..4usize))]),
                        "job": id, "index": 0, "total": 1, "description": hist, "message": hist,
                        "session": hist, "kind": hist}),
            ),
        ),
        9 => (
            "not an object".into(),
            ["[1,2]", "17", "\"job-ended\"", "null", "{}"][draw(r, &(0..5usize))]
                .as_bytes()
                .to_vec(),
        ),
        _ => (
            "heartbeat".into(),
            line(json!({"seq": 6, "event": "heartbeat", "job": id})),
        ),
    }
}

#[test]
fn fuzz_daemon_events_files_never_change_the_journals_outcome() {
    let n = cases("daemon-events");
    let start = Instant::now();
    let mut r = runner("daemon-events");
    let mut f = Findings::default();
    let (d, id, session) = super::daemon::interrupted_job();
    let events = session.join("events.jsonl");
    let original = std::fs::read_to_string(&events).unwrap();
    let real: Vec<String> = original.lines().map(str::to_string).collect();
    for i in 0..n {
        let mut lines: Vec<Vec<u8>> = real.iter().map(|l| l.as_bytes().to_vec()).collect();
        let mut desc = Vec::new();
        if draw(&mut r, &(0..3usize)) == 0 {
            lines.clear();
            desc.push("no history".to_string());
        }
        for _ in 0..draw(&mut r, &(1..5usize)) {
            let (what, piece) = forged_event_piece(&mut r, id, &real);
            let at = draw(&mut r, &(0..lines.len() + 1));
            lines.insert(at, piece);
            desc.push(format!("{what} at line {}", at + 1));
        }
        let mut bytes = lines.join(&b'\n');
        if draw(&mut r, &(0..2usize)) == 0 {
            bytes.push(b'\n');
        }
        let _ = std::fs::remove_file(&events);
        match draw(&mut r, &(0..40usize)) {
            0 => {
                std::os::unix::fs::symlink("/dev/zero", &events).unwrap();
                desc = vec!["a link to /dev/zero".into()];
            }
            1 => {
                std::os::unix::fs::symlink("/etc/passwd", &events).unwrap();
                desc = vec!["a link to /etc/passwd".into()];
            }
            _ => std::fs::write(&events, &bytes).unwrap(),
        }
        let desc = format!("[daemon-events:{i}] {}", desc.join(", "));
        let args: &[&str] = match i % 3 {
            0 => &["follow"],
            1 => &["follow", "--json"],
            _ => &["follow", "--json", "--events"],
        };
        let id_s = id.to_string();
        let mut full = args.to_vec();
        full.insert(1, &id_s);
        let t0 = Instant::now();
        let o = d.glint(&full);
        let took = t0.elapsed();
        let all = format!(
            "{}{}",
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr)
        );
        let mut problem = client_run_problem(&o, took, Duration::from_secs(10));
        if problem.is_none() && o.status.success() {
            problem = Some("exit 0 on a job the journal says interrupted".into());
        }
        if problem.is_none() && all.contains("FAKE") && args.len() < 3 {
            problem = Some(format!("a forged text printed: {}", show(&all)));
        }
        if problem.is_none() && !all.contains("interrupted") {
            problem = Some(format!("the journal's outcome not printed: {}", show(&all)));
        }
        match problem {
            Some(p) => f.add(p.clone(), &args.join(" "), &desc, show(&all)),
            None => *f.passed.entry(args.join(" ")).or_default() += 1,
        }
    }
    std::fs::write(&events, original).unwrap();
    f.finish("daemon-events", n, start);
}

/// A value that breaks a reply's field: wrong type, absurd, or text with escapes.
fn bad_reply_value(r: &mut TestRunner) -> Value {
    let v = [
        Value::Null,
        json!("x"),
        json!(-1),
        json!(1e308),
        json!(true),
        json!({}),
        json!([]),
        json!("\u{1b}[2J\u{1b}]0;pwned\u{7}\nforged line"),
        json!(u64::MAX),
        json!("a".repeat(5000)),
    ];
    v[draw(r, &(0..v.len()))].clone()
}

/// Every (path, value) leaf of a JSON value.
fn leaves(v: &Value, path: Vec<String>, out: &mut Vec<Vec<String>>) {
    match v {
        Value::Object(m) => {
            for (k, x) in m {
                let mut p = path.clone();
                p.push(k.clone());
                out.push(p.clone());
                leaves(x, p, out);
            }
        }
        Value::Array(a) => {
            for (i, x) in a.iter().enumerate() {
                let mut p = path.clone();
                p.push(i.to_string());
                out.push(p.clone());
                leaves(x, p, out);
            }
        }
        _ => {}
    }
}

/// `v` with the value at `path` replaced (`Some`) or removed (`None`).
fn set_path(v: &mut Value, path: &[String], to: Option<Value>) {
    let (last, head) = path.split_last().unwrap();
    let mut at = v;
    for k in head {
        at = match at {
            Value::Object(m) => m.get_mut(k).unwrap(),
            Value::Array(a) => &mut a[k.parse::<usize>().unwrap()],
            _ => return,
        };
    }
    match (at, to) {
        (Value::Object(m), Some(x)) => {
            m.insert(last.clone(), x);
        }
        (Value::Object(m), None) => {
            m.remove(last);
        }
        (Value::Array(a), Some(x)) => a[last.parse::<usize>().unwrap()] = x,
        (Value::Array(a), None) => {
            a.remove(last.parse::<usize>().unwrap());
        }
        _ => {}
    }
}

/// Mutate one line of the fake daemon's script: a field changed or removed, or the line
/// torn, or replaced by garbage. The line, and what was done.
fn mutate_line(r: &mut TestRunner, line: &Value) -> (String, String) {
    match draw(r, &(0..10usize)) {
        0 => {
            let s = line.to_string();
            let cut = draw(r, &(0..s.len()));
            (s[..cut].to_string(), format!("torn at {cut}"))
        }
        1 => {
            let g: Vec<u8> = draw(r, &vec(any::<u8>(), 0..100));
            (
                String::from_utf8_lossy(&g).replace('\n', " "),
                "garbage".into(),
            )
        }
        _ => {
            let mut v = line.clone();
            let mut ps = Vec::new();
            leaves(&v, Vec::new(), &mut ps);
            if ps.is_empty() {
                return (v.to_string(), "unchanged".into());
            }
            let p = ps[draw(r, &(0..ps.len()))].clone();
            let remove = draw(r, &(0..4usize)) == 0;
            let to = (!remove).then(|| bad_reply_value(r));
            let what = match &to {
                Some(x) => format!("{} = {}", p.join("."), brief_json(x)),
                None => format!("{} removed", p.join(".")),
            };
            set_path(&mut v, &p, to);
            (v.to_string(), what)
        }
    }
}

fn brief_json(v: &Value) -> String {
    let s = v.to_string();
    if s.len() > 40 {
        format!("{}…", &s[..40])
    } else {
        s
    }
}

#[test]
fn fuzz_daemon_replies_and_events_read_by_the_clients() {
    use super::daemon::{fake_hello, FakeDaemon};
    let n = cases("daemon-replies");
    let start = Instant::now();
    let mut r = runner("daemon-replies");
    let mut f = Findings::default();
    // The fake daemon answers from the current case's script: per command, the lines to
    // send (the reply's id filled in).
    type Script = BTreeMap<String, Vec<String>>;
    let script: std::sync::Arc<Mutex<Script>> = Default::default();
    let s2 = std::sync::Arc::clone(&script);
    let fake = FakeDaemon::start(move |req| {
        let cmd = req["cmd"].as_str().unwrap_or("").to_string();
        let lines = s2.lock().unwrap().get(&cmd).cloned();
        match lines {
            Some(ls) => ls
                .into_iter()
                .map(|l| l.replace("\"ID\"", &req["id"].to_string()))
                .collect(),
            None => vec!["#hang".into()],
        }
    });
    let job = json!({"id": 9, "spec": {"kind": "run", "out": "/o"}, "state": "failed",
                     "queued": "t", "session": "/s", "error": "e"});
    let ok = |result: Value| json!({"id": "ID", "ok": true, "result": result});
    let status = json!({
        "daemon": {"version": "0.1.0", "pid": 1, "rig_name": "r", "rig": "/r.toml", "started": "t"},
        "devices": {"state": "ok", "camera": "c", "lamp": "l", "since": "t", "last_error": "e"},
        "queue": {"running": true, "queued": 0, "shutting_down": false},
        "running": job, "operator": {"job": 9, "message": "m", "since": "t"},
    });
    let commands: Vec<(&[&str], &str, Vec<Value>)> = vec![
        (&["daemon", "status"], "status", vec![ok(status)]),
        (
            &["jobs"],
            "jobs",
            vec![ok(json!({"queue_running": true, "running": job,
            "queue": [job], "history": [job], "history_omitted": 0}))],
        ),
        (
            &["queue", "start"],
            "queue-start",
            vec![ok(json!({"queue_running": true}))],
        ),
        (
            &["queue", "remove", "1"],
            "remove",
            vec![ok(json!({"queue": [2, 3]}))],
        ),
        (
            &["trigger", "run", "--detach"],
            "add",
            vec![ok(json!({"job": 9, "position": 0, "queue_running": true}))],
        ),
        (&["abort"], "abort", vec![ok(json!({"aborting": 9}))]),
        (
            &["follow", "9"],
            "follow",
            vec![
                ok(json!({"following": 9})),
                json!({"seq": 1, "event": "job-started", "job": 9, "kind": "run", "session": "/s"}),
                json!({"seq": 2, "event": "step", "job": 9, "index": 0, "total": 3, "description": "d"}),
                json!({"seq": 3, "event": "heartbeat"}),
                json!({"seq": 4, "event": "job-ended", "job": 8, "state": "complete", "summary_text": "OTHER"}),
                json!({"seq": 5, "event": "warning", "job": 9, "message": "w"}),
                json!({"seq": 6, "event": "job-ended", "job": 9, "state": "complete", "summary_text": "S", "summary": {}}),
            ],
        ),
    ];
    for i in 0..n {
        let (args, cmd, lines) = &commands[i % commands.len()];
        let mut hello =
            serde_json::from_str::<Value>(&fake_hello(&json!({"id": "ID"}), 0.1)).unwrap();
        let mut sent: Vec<String> = lines.iter().map(Value::to_string).collect();
        let mut desc = Vec::new();
        // Mutate the hello now and then, else 1-3 lines of the command's script.
        if draw(&mut r, &(0..8usize)) == 0 {
            let (l, what) = mutate_line(&mut r, &hello);
            desc.push(format!("hello: {what}"));
            hello = serde_json::from_str(&l).unwrap_or(Value::Null);
            if hello.is_null() {
                hello = json!(l);
            }
        } else {
            for _ in 0..draw(&mut r, &(1..4usize)) {
                let k = draw(&mut r, &(0..lines.len()));
                let (l, what) = mutate_line(&mut r, &lines[k]);
                desc.push(format!("line {k}: {what}"));
                sent[k] = l;
            }
        }
        match draw(&mut r, &(0..4usize)) {
            0 => {
                sent.push("#close".into());
                desc.push("then closed".into());
            }
            1 => {
                let cut = draw(&mut r, &(0..sent.len()));
                sent.truncate(cut.max(1));
                sent.push("#hang".into());
                desc.push(format!("silent after line {}", cut.max(1)));
            }
            _ => {}
        }
        let hello_line = match &hello {
            Value::String(s) => s.clone(),
            v => v.to_string(),
        };
        {
            let mut s = script.lock().unwrap();
            s.clear();
            s.insert("hello".into(), vec![hello_line]);
            s.insert(cmd.to_string(), sent.clone());
        }
        let desc = format!(
            "[daemon-replies:{i}] {} {}",
            args.join(" "),
            desc.join(", ")
        );
        let (o, took) = fake.glint(args, 1.0);
        let err = String::from_utf8_lossy(&o.stderr).to_string();
        let mut problem = client_run_problem(&o, took, Duration::from_secs(10));
        // A follow ends 0 only on a well-formed `job-ended` of its own job, `complete`.
        if problem.is_none() && *cmd == "follow" && o.status.success() {
            let real_end = sent.iter().take_while(|l| !l.starts_with('#')).any(|l| {
                serde_json::from_str::<Value>(l).is_ok_and(|v| {
                    v["event"] == "job-ended"
                        && v["job"] == 9
                        && serde_json::from_value::<glint::daemon::client::JobEnded>(v.clone())
                            .is_ok_and(|e| e.state == glint::daemon::protocol::JobState::Complete)
                })
            });
            if !real_end {
                problem = Some("follow exit 0 without its job's complete end".into());
            }
        }
        if problem.is_none()
            && *cmd != "follow"
            && !o.status.success()
            && err.trim().lines().count() != 1
        {
            problem = Some(format!("an error of {} lines", err.trim().lines().count()));
        }
        if problem.is_none()
            && o.status.success()
            && String::from_utf8_lossy(&o.stdout).contains("null")
            && *cmd != "follow"
        {
            problem = Some(format!(
                "printed null: {}",
                show(&String::from_utf8_lossy(&o.stdout))
            ));
        }
        match problem {
            Some(p) => f.add(
                p,
                cmd,
                &desc,
                show(&format!("{err} | {}", String::from_utf8_lossy(&o.stdout))),
            ),
            None => *f.passed.entry(cmd.to_string()).or_default() += 1,
        }
    }
    f.finish("daemon-replies", n, start);
}
