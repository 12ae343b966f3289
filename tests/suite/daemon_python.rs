//! The Python client in docs/daemon-protocol.md, run as written against a daemon on the
//! small mock rig: the page's example is a working client of the protocol.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

use super::daemon::{small_rig, Daemon};

/// The line that opens the client's block in the page.
const FENCE: &str = "```python glint-client";

/// The longest the client may take (a debug build's run on the small rig takes about a
/// minute, most of it the HDR stage).
const CLIENT_LIMIT: Duration = Duration::from_secs(900);

fn doc_path() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/daemon-protocol.md")
}

/// The code of the page's one `python glint-client` block.
fn python_block() -> String {
    let path = doc_path();
    let doc = std::fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("reading {}: {e}", path.display()));
    let opening: Vec<usize> = doc
        .lines()
        .enumerate()
        .filter(|(_, l)| l.trim_end() == FENCE)
        .map(|(i, _)| i)
        .collect();
    assert_eq!(
        opening.len(),
        1,
        "{} must have exactly one block opening with the line {FENCE}",
        path.display()
    );
    let mut code = String::new();
    for line in doc.lines().skip(opening[0] + 1) {
        if line.trim_end() == "```" {
            assert!(!code.trim().is_empty(), "the {FENCE} block is empty");
            return code;
        }
        code.push_str(line);
        code.push('\n');
    }
    panic!("the {FENCE} block in {} is not closed", path.display());
}

fn have_python3() -> bool {
    Command::new("python3")
        .arg("--version")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// Run `cmd` to its end (killed after `limit`): its status, stdout and stderr.
fn run_limited(cmd: &mut Command, limit: Duration) -> (Option<ExitStatus>, String, String) {
    let mut child = cmd
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawning python3");
    let drain = |mut r: Box<dyn Read + Send>| {
        std::thread::spawn(move || {
            let mut s = String::new();
            let _ = r.read_to_string(&mut s);
            s
        })
    };
    let out = drain(Box::new(child.stdout.take().unwrap()));
    let err = drain(Box::new(child.stderr.take().unwrap()));
    let t0 = Instant::now();
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break Some(st);
        }
        if t0.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    (status, out.join().unwrap(), err.join().unwrap())
}

#[test]
fn python_client_from_the_doc_queues_a_job_and_reads_its_events() {
    if !have_python3() {
        println!("SKIPPED: python3 not found");
        return;
    }
    let code = python_block();
    let mut d = Daemon::new(&small_rig());
    d.start();
    let script = d.dir.path().join("glint-client.py");
    std::fs::write(&script, &code).unwrap();
    let out = d.dir.path().join("python-session");
    assert!(!out.exists());

    let (status, stdout, stderr) = run_limited(
        Command::new("python3")
            .arg(&script)
            .arg(&d.socket)
            .arg(&out),
        CLIENT_LIMIT,
    );
    println!("{stdout}");
    let context = || {
        format!(
            "python3 glint-client.py: {status:?}\n--- stdout\n{stdout}\n--- stderr\n{stderr}\n--- daemon log\n{}",
            d.log()
        )
    };
    let status =
        status.unwrap_or_else(|| panic!("the client ran over {CLIENT_LIMIT:?}: {}", context()));
    assert!(status.success(), "the client failed: {}", context());

    // "SEQ EVENT [STATE]" per line, seq increasing.
    let mut seqs = Vec::new();
    let mut events = Vec::new();
    for line in stdout.lines().filter(|l| !l.trim().is_empty()) {
        let mut words = line.split_whitespace();
        let seq: u64 = words
            .next()
            .and_then(|w| w.parse().ok())
            .unwrap_or_else(|| panic!("a line without a sequence number: {line:?}\n{}", context()));
        let event = words
            .next()
            .unwrap_or_else(|| panic!("a line without an event: {line:?}\n{}", context()));
        seqs.push(seq);
        events.push((event.to_string(), words.next().map(str::to_string)));
    }
    assert!(
        !seqs.is_empty(),
        "the client printed no events: {}",
        context()
    );
    assert!(
        seqs.windows(2).all(|w| w[0] < w[1]),
        "the sequence numbers do not increase: {seqs:?}"
    );
    let has = |name: &str| events.iter().any(|(e, _)| e == name);
    for name in ["job-added", "job-started", "frame", "job-ended"] {
        assert!(has(name), "no {name} event: {}", context());
    }
    assert!(
        !has("resync"),
        "a lone local client fell behind: {}",
        context()
    );
    assert_eq!(
        events.last().unwrap(),
        &("job-ended".to_string(), Some("complete".to_string())),
        "the last event is not the job ending complete: {}",
        context()
    );

    // The session the job wrote, where the client asked.
    let manifest: Value = serde_json::from_str(
        &std::fs::read_to_string(out.join("manifest.json"))
            .unwrap_or_else(|e| panic!("{}/manifest.json: {e}\n{}", out.display(), context())),
    )
    .unwrap();
    assert_eq!(manifest["state"], "complete", "{manifest}");

    // The session keeps the same events the client was sent.
    let kept: Vec<u64> = std::fs::read_to_string(out.join("events.jsonl"))
        .unwrap()
        .lines()
        .map(|l| {
            serde_json::from_str::<Value>(l).unwrap()["seq"]
                .as_u64()
                .unwrap()
        })
        .collect();
    assert_eq!(
        kept, seqs,
        "events.jsonl and the events the client printed differ"
    );

    // The daemon agrees.
    let jobs = d.jobs();
    let history = jobs["history"].as_array().unwrap();
    assert_eq!(history.len(), 1, "{jobs}");
    assert_eq!(history[0]["state"], "complete");
    assert_eq!(history[0]["session"], out.to_str().unwrap());
}

#[test]
fn python_client_in_the_doc_is_at_most_30_lines() {
    let code = python_block();
    let lines: Vec<&str> = code
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .collect();
    assert!(
        lines.len() <= 30,
        "the Python client has {} lines of code (at most 30):\n{}",
        lines.len(),
        lines.join("\n")
    );
    // It is the client the page describes: the socket from argv[1], hello first.
    assert!(code.contains("sys.argv[1]"), "{code}");
    assert!(code.contains("\"hello\""), "{code}");
}
