//! The daemon: `glint daemon` run as a process, driven by `glint trigger`/`jobs`/`abort`
//! and by raw protocol lines, killed and restarted.

use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use serde_json::{json, Value};

use super::util;

/// A `glint daemon` child process on a rig of its own, in a temporary folder.
pub struct Daemon {
    pub dir: tempfile::TempDir,
    pub socket: PathBuf,
    pub state: PathBuf,
    pub rig: PathBuf,
    pub child: Option<Child>,
    /// Extra flags for `glint daemon`.
    pub flags: Vec<String>,
    /// Environment variables of the next start (a fault point, say).
    pub env: Vec<(String, String)>,
}

impl Daemon {
    /// A daemon on the rig `t` (written to DIR/rig.toml), not yet started.
    pub fn new(t: &toml::Table) -> Daemon {
        let dir = util::tempdir();
        let rig = dir.path().join("rig.toml");
        std::fs::write(&rig, toml::to_string(t).unwrap()).unwrap();
        Daemon {
            socket: dir.path().join("run/glint.sock"),
            state: dir.path().join("state"),
            rig,
            dir,
            child: None,
            flags: Vec::new(),
            env: Vec::new(),
        }
    }

    /// `glint daemon` on this rig and socket, with the state folder `state`.
    pub fn command(&self, state: &Path) -> Command {
        let mut c = Command::new(env!("CARGO_BIN_EXE_glint"));
        c.args(["daemon", "--rig"])
            .arg(&self.rig)
            .arg("--socket")
            .arg(&self.socket)
            .arg("--state-dir")
            .arg(state)
            .args(&self.flags)
            .envs(self.env.iter().map(|(k, v)| (k, v)));
        c
    }

    /// Start it and wait until its socket answers.
    pub fn start(&mut self) -> &mut Self {
        let child = self
            .command(&self.state)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::from(
                std::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(self.dir.path().join("daemon.log"))
                    .unwrap(),
            ))
            .spawn()
            .expect("spawning glint daemon");
        self.child = Some(child);
        let t0 = Instant::now();
        while UnixStream::connect(&self.socket).is_err() {
            if let Some(st) = self.child.as_mut().unwrap().try_wait().unwrap() {
                panic!("the daemon exited with {st}: {}", self.log());
            }
            assert!(
                t0.elapsed() < Duration::from_secs(30),
                "the daemon did not listen within 30 s: {}",
                self.log()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        self
    }

    pub fn log(&self) -> String {
        std::fs::read_to_string(self.dir.path().join("daemon.log")).unwrap_or_default()
    }

    pub fn pid(&self) -> i32 {
        self.child.as_ref().unwrap().id() as i32
    }

    pub fn signal(&self, sig: i32) {
        // SAFETY: kill(2) on our own child's pid.
        unsafe { libc::kill(self.pid(), sig) };
    }

    /// Wait for the daemon to exit (at most `limit`); its exit status.
    pub fn wait(&mut self, limit: Duration) -> std::process::ExitStatus {
        let t0 = Instant::now();
        loop {
            if let Some(st) = self.child.as_mut().unwrap().try_wait().unwrap() {
                self.child = None;
                return st;
            }
            assert!(
                t0.elapsed() < limit,
                "the daemon did not exit within {limit:?}: {}",
                self.log()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Run `glint ARGS --socket S`.
    pub fn glint(&self, args: &[&str]) -> Output {
        Command::new(env!("CARGO_BIN_EXE_glint"))
            .args(args)
            .arg("--socket")
            .arg(&self.socket)
            .stdin(Stdio::null())
            .output()
            .unwrap()
    }

    /// `glint jobs --json`.
    pub fn jobs(&self) -> Value {
        let o = self.glint(&["jobs", "--json"]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        serde_json::from_slice(&o.stdout).unwrap()
    }

    /// A raw protocol connection, past hello.
    pub fn connect(&self) -> Conn {
        let mut c = Conn::open(&self.socket);
        let r = c.request(json!({"cmd": "hello", "version": 1}));
        assert_eq!(r["ok"], true, "{r}");
        c
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// A raw connection speaking JSON lines.
pub struct Conn {
    pub writer: UnixStream,
    pub reader: BufReader<UnixStream>,
    next: u64,
}

impl Conn {
    pub fn open(socket: &Path) -> Conn {
        let s = UnixStream::connect(socket).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
        Conn {
            reader: BufReader::new(s.try_clone().unwrap()),
            writer: s,
            next: 1,
        }
    }

    pub fn send_raw(&mut self, bytes: &[u8]) {
        self.writer.write_all(bytes).unwrap();
    }

    /// The next line, parsed.
    pub fn line(&mut self) -> Value {
        let mut l = String::new();
        let n = self.reader.read_line(&mut l).unwrap();
        assert!(n > 0, "the daemon closed the connection");
        serde_json::from_str(&l).unwrap_or_else(|e| panic!("{e}: {l}"))
    }

    /// Send a request and return its reply (events before it are skipped).
    pub fn request(&mut self, mut r: Value) -> Value {
        let id = self.next;
        self.next += 1;
        r["id"] = id.into();
        self.send_raw(format!("{r}\n").as_bytes());
        loop {
            let v = self.line();
            if v.get("event").is_none() && v["id"] == id {
                return v;
            }
        }
    }

    /// Events until (and with) the first for which `stop` holds.
    pub fn events_until(&mut self, mut stop: impl FnMut(&Value) -> bool) -> Vec<Value> {
        let mut out = Vec::new();
        loop {
            let v = self.line();
            if v.get("event").is_none() {
                continue;
            }
            let done = stop(&v);
            out.push(v);
            if done {
                return out;
            }
        }
    }
}

/// The small fast mock rig.
pub fn small_rig() -> toml::Table {
    util::small_table()
}

/// `glint ARGS` with `GLINT_SOCKET` unset, its output.
fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_glint"))
        .args(args)
        .env_remove("GLINT_SOCKET")
        .stdin(Stdio::null())
        .output()
        .unwrap()
}

fn text(o: &Output) -> String {
    format!(
        "status {}\nstdout: {}\nstderr: {}",
        o.status,
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

fn is_job_event(v: &Value, job: u64) -> bool {
    v["job"] == job
}

fn ended(job: u64) -> impl Fn(&Value) -> bool {
    move |v: &Value| v["job"] == job && v["event"] == "job-ended"
}

/// The keys of a JSON object, sorted.
fn keys(v: &Value) -> Vec<String> {
    let mut k: Vec<String> = v.as_object().unwrap().keys().cloned().collect();
    k.sort();
    k
}

#[test]
fn trigger_run_prints_the_run_summary_and_every_follower_sees_the_same_events() {
    let mut d = Daemon::new(&small_rig());
    d.start();
    // A follower of every event, attached before the job exists.
    let mut live = d.connect();
    assert_eq!(live.request(json!({"cmd": "follow"}))["ok"], true);
    let out = d.dir.path().join("session");
    let o = d.glint(&["trigger", "run", "--json", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let summary: Value = serde_json::from_slice(&o.stdout).unwrap();
    // The same summary as `glint run --json` on the same rig.
    let reference = run(&[
        "run",
        "--json",
        "--rig",
        d.rig.to_str().unwrap(),
        "--out",
        d.dir.path().join("reference").to_str().unwrap(),
    ]);
    assert!(reference.status.success(), "{}", text(&reference));
    let reference: Value = serde_json::from_slice(&reference.stdout).unwrap();
    assert_eq!(keys(&summary), keys(&reference));
    assert_eq!(summary["fit"]["chosen"], "blinn-phong");
    assert_eq!(summary["fit"]["chosen"], reference["fit"]["chosen"]);
    let n = summary["fit"]["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["model"] == "blinn-phong")
        .map(|c| c["n"]["value"].as_f64().unwrap())
        .unwrap();
    assert!((n - 120.0).abs() < 0.1 * 120.0, "n = {n}");
    assert!(summary["validation"]["models"].as_array().unwrap().len() >= 2);
    assert_eq!(summary["session"], out.to_str().unwrap());
    // The live follower's events of job 1, and a late follower's replay, are identical.
    let seen: Vec<Value> = live
        .events_until(ended(1))
        .into_iter()
        .filter(|v| is_job_event(v, 1))
        .collect();
    let mut late = d.connect();
    assert_eq!(late.request(json!({"cmd": "follow", "job": 1}))["ok"], true);
    let replayed = late.events_until(ended(1));
    assert_eq!(seen, replayed);
    assert!(seen.len() > 20, "{} events", seen.len());
    let seqs: Vec<u64> = seen.iter().map(|v| v["seq"].as_u64().unwrap()).collect();
    assert!(seqs.windows(2).all(|w| w[0] < w[1]), "{seqs:?}");
    assert_eq!(seen.first().unwrap()["event"], "job-added");
    assert!(seen.iter().any(|v| v["event"] == "frame"));
    assert_eq!(seen.last().unwrap()["state"], "complete");
    // The session keeps them too.
    let file = std::fs::read_to_string(out.join("events.jsonl")).unwrap();
    let from_file: Vec<Value> = file
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(from_file, seen);
    // ... and the session verifies with the file in it.
    let v = run(&["session", "verify", out.to_str().unwrap()]);
    assert!(v.status.success(), "{}", text(&v));
    // A process job runs the stages again on that session and finds the same.
    let o = d.glint(&["trigger", "process", out.to_str().unwrap(), "--json"]);
    assert!(o.status.success(), "{}", text(&o));
    let again: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(again["fit"]["chosen"], summary["fit"]["chosen"]);
    assert_eq!(again["capture"]["frames"], summary["capture"]["frames"]);
    assert!(
        again["capture"]["dropped"].is_null(),
        "{}",
        again["capture"]
    );
    assert_eq!(
        again["stages"].as_array().unwrap().len(),
        5,
        "hdr to report: {}",
        again["stages"]
    );
}

#[test]
fn the_socket_is_owner_only_and_another_uid_is_refused() {
    use std::os::unix::fs::{MetadataExt, PermissionsExt};
    let mut d = Daemon::new(&small_rig());
    d.start();
    let sock = std::fs::symlink_metadata(&d.socket).unwrap();
    let dir = std::fs::symlink_metadata(d.socket.parent().unwrap()).unwrap();
    // SAFETY: geteuid cannot fail.
    let me = unsafe { libc::geteuid() };
    assert_eq!(sock.permissions().mode() & 0o777, 0o600);
    assert_eq!(dir.permissions().mode() & 0o777, 0o700);
    assert_eq!((sock.uid(), dir.uid()), (me, me));
    if me != 0 || Command::new("setpriv").arg("--help").output().is_err() {
        println!("SKIPPED: another uid needs root and setpriv");
        return;
    }
    let as_nobody = |caps: bool| {
        let mut c = Command::new("setpriv");
        c.args(["--reuid=65534", "--regid=65534", "--clear-groups"]);
        if caps {
            // Past the folder's permissions, so that the daemon's own check answers.
            c.args(["--inh-caps=+dac_override", "--ambient-caps=+dac_override"]);
        }
        c.arg(env!("CARGO_BIN_EXE_glint"))
            .args(["jobs", "--socket"])
            .arg(&d.socket)
            .output()
            .unwrap()
    };
    let o = as_nobody(false);
    assert!(!o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("Permission denied"), "{}", text(&o));
    let o = as_nobody(true);
    assert!(!o.status.success(), "{}", text(&o));
    assert!(
        text(&o).contains("permission denied: uid 65534 may not use this daemon"),
        "{}",
        text(&o)
    );
    assert!(
        d.log().contains("refused a client of uid 65534"),
        "{}",
        d.log()
    );
    // The daemon's user still gets in.
    assert!(d.glint(&["daemon", "status"]).status.success());
}

#[test]
fn a_second_daemon_for_the_same_socket_refuses_and_a_stale_socket_is_cleaned_up() {
    let mut d = Daemon::new(&small_rig());
    d.start();
    let o = d
        .command(&d.dir.path().join("other-state"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(
        text(&o).contains("another glint daemon already serves the socket"),
        "{}",
        text(&o)
    );
    // Killed, it leaves its socket behind; the next daemon removes it and serves.
    d.signal(libc::SIGKILL);
    d.wait(Duration::from_secs(10));
    assert!(d.socket.exists());
    d.start();
    assert!(d.log().contains("stale socket"), "{}", d.log());
    assert!(d.glint(&["daemon", "status"]).status.success());
}

/// The small rig, slowed to real time at `fps` with a lamp command log at `log`.
fn slow_rig(fps: f64, log: &Path) -> toml::Table {
    let mut t = small_rig();
    util::set(&mut t, "mock.sensor.realtime", true);
    util::set(&mut t, "mock.sensor.fps", fps);
    util::set(&mut t, "camera.fps", fps);
    util::set(&mut t, "mock.lamp.command_log", log.to_str().unwrap());
    t
}

/// Queue a job without following it; its id.
fn queue(d: &Daemon, kind: &str) -> u64 {
    let o = d.glint(&["trigger", kind, "--detach", "--json"]);
    assert!(o.status.success(), "{}", text(&o));
    let v: Value = serde_json::from_slice(&o.stdout).unwrap();
    v["job"].as_u64().unwrap()
}

fn job(jobs: &Value, id: u64) -> Value {
    for list in ["history", "queue"] {
        if let Some(j) = jobs[list]
            .as_array()
            .unwrap()
            .iter()
            .find(|j| j["id"] == id)
        {
            return j.clone();
        }
    }
    if jobs["running"]["id"] == id {
        return jobs["running"].clone();
    }
    panic!("no job {id} in {jobs}")
}

fn manifest(dir: &str) -> Value {
    serde_json::from_str(&std::fs::read_to_string(Path::new(dir).join("manifest.json")).unwrap())
        .unwrap()
}

#[test]
fn kill_9_mid_capture_then_restart_marks_the_job_interrupted_and_starts_nothing() {
    let dir = util::tempdir();
    let mut d = Daemon::new(&slow_rig(15.0, &dir.path().join("lamp.log")));
    d.start();
    let mut watch = d.connect();
    watch.request(json!({"cmd": "follow"}));
    let first = queue(&d, "capture");
    let second = queue(&d, "run");
    // Some frames in, then the daemon dies.
    let mut frames = 0;
    watch.events_until(|v| {
        frames += (v["event"] == "frame" && v["job"] == first) as u32;
        frames >= 3
    });
    d.signal(libc::SIGKILL);
    d.wait(Duration::from_secs(10));
    d.start();
    let jobs = d.jobs();
    let j1 = job(&jobs, first);
    assert_eq!(j1["state"], "interrupted", "{jobs}");
    assert!(
        j1["error"].as_str().unwrap().contains("daemon stopped"),
        "{j1}"
    );
    let session = j1["session"].as_str().unwrap();
    let m = manifest(session);
    assert_eq!(m["state"], "failed");
    assert!(
        m["failure"].as_str().unwrap().starts_with("daemon stopped"),
        "{m}"
    );
    assert!(m["frames"].as_array().unwrap().len() >= 3);
    let v = run(&["session", "verify", session]);
    assert!(v.status.success(), "{}", text(&v));
    // The queued job stays queued and does not start by itself.
    assert_eq!(jobs["queue_running"], false);
    assert_eq!(job(&jobs, second)["state"], "queued");
    std::thread::sleep(Duration::from_millis(1500));
    assert_eq!(job(&d.jobs(), second)["state"], "queued");
    assert!(
        d.log().contains("`glint queue start` runs them"),
        "{}",
        d.log()
    );
    // The restarted daemon switched the lamp off when it opened the rig.
    let log = std::fs::read_to_string(dir.path().join("lamp.log")).unwrap();
    assert!(log.lines().any(|l| l.starts_with("OFF")), "{log}");
    // Following the interrupted job replays what it did and ends with its outcome.
    let o = d.glint(&["follow", &first.to_string()]);
    assert!(!o.status.success());
    assert!(
        text(&o).contains(&format!("job {first} interrupted: daemon stopped")),
        "{}",
        text(&o)
    );
    // A follower of the queued job waits for it; told to, the daemon runs the queue.
    let follower = Command::new(env!("CARGO_BIN_EXE_glint"))
        .args(["follow", &second.to_string(), "--json", "--socket"])
        .arg(&d.socket)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(300));
    assert!(d.glint(&["queue", "start"]).status.success());
    let o = follower.wait_with_output().unwrap();
    assert!(o.status.success(), "{}", text(&o));
    let summary: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(summary["fit"]["chosen"], "blinn-phong");
    assert_eq!(job(&d.jobs(), second)["state"], "complete");
}

/// The lamp firmware's log: the commands it received, in order.
fn lamp_commands(log: &Path) -> Vec<String> {
    std::fs::read_to_string(log)
        .unwrap()
        .lines()
        .map(|l| l.split_whitespace().next().unwrap_or("").to_string())
        .collect()
}

/// A daemon on a real-time rig with a lamp log, a follower of every event, and a capture
/// job that has kept its first frame.
fn capture_under_way() -> (Daemon, Conn, u64, PathBuf) {
    let mut d = Daemon::new(&small_rig());
    let log = d.dir.path().join("lamp.log");
    std::fs::write(&d.rig, toml::to_string(&slow_rig(15.0, &log)).unwrap()).unwrap();
    d.start();
    let mut watch = d.connect();
    watch.request(json!({"cmd": "follow"}));
    let id = queue(&d, "capture");
    watch.events_until(|v| v["event"] == "frame" && v["job"] == id);
    (d, watch, id, log)
}

#[test]
fn sigterm_mid_capture_switches_the_lamp_off_fails_the_session_and_exits_0() {
    let (mut d, _watch, id, log) = capture_under_way();
    d.signal(libc::SIGTERM);
    let status = d.wait(Duration::from_secs(20));
    assert!(status.success(), "exit {status}: {}", d.log());
    let cmds = lamp_commands(&log);
    let on = cmds
        .iter()
        .rposition(|c| c == "ON")
        .expect("the lamp was switched on");
    assert!(cmds[on..].iter().any(|c| c == "OFF"), "{cmds:?}");
    d.start();
    let j = job(&d.jobs(), id);
    assert_eq!(j["state"], "aborted", "{j}");
    let m = manifest(j["session"].as_str().unwrap());
    assert_eq!(m["state"], "failed");
    assert_eq!(m["failure"], "daemon stopped by SIGTERM");
    assert_eq!(m["lamp_off_confirmed"], true);
    let v = run(&["session", "verify", j["session"].as_str().unwrap()]);
    assert!(v.status.success(), "{}", text(&v));
}

#[test]
fn abort_from_a_second_client_switches_the_lamp_off_and_the_daemon_carries_on() {
    let (d, mut watch, id, log) = capture_under_way();
    let o = d.glint(&["abort"]);
    assert!(o.status.success(), "{}", text(&o));
    let end = watch.events_until(ended(id)).pop().unwrap();
    assert_eq!(end["state"], "aborted", "{end}");
    // The one-line error: the reason, then where the session is.
    assert!(
        end["error"].as_str().unwrap().starts_with("aborted ("),
        "{end}"
    );
    let cmds = lamp_commands(&log);
    let on = cmds.iter().rposition(|c| c == "ON").unwrap();
    assert!(cmds[on..].iter().any(|c| c == "OFF"), "{cmds:?}");
    let m = manifest(end["session"].as_str().unwrap());
    assert_eq!(
        (m["state"].as_str(), m["failure"].as_str()),
        (Some("failed"), Some("aborted"))
    );
    // Still up, devices fine, and the next job runs.
    let st = d.glint(&["daemon", "status", "--json"]);
    let st: Value = serde_json::from_slice(&st.stdout).unwrap();
    assert_eq!(st["devices"]["state"], "ok", "{st}");
    let next = queue(&d, "capture");
    let end = watch.events_until(ended(next)).pop().unwrap();
    assert_eq!(end["state"], "complete", "{end}");
    // Following the aborted job exits non-zero with its one-line error.
    let o = d.glint(&["follow", &id.to_string()]);
    assert!(!o.status.success());
    assert!(
        text(&o).contains(&format!("job {id} aborted: aborted")),
        "{}",
        text(&o)
    );
}

/// Resident memory of a process, kB.
fn rss_kb(pid: i32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap()
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next()?.parse().ok())
        .unwrap()
}

#[test]
fn ten_thousand_malformed_lines_and_a_10_mb_line_get_errors_and_the_daemon_carries_on() {
    use rand::{RngExt, SeedableRng};
    let mut d = Daemon::new(&small_rig());
    d.start();
    let before = rss_kb(d.pid());
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(14);
    let templates = [
        r#"{"cmd":"status"}"#,
        r#"{"id":1,"cmd":"add","job":{"kind":"run","samples":5}}"#,
        r#"{"id":"x","cmd":"add","job":{"kind":"process"}}"#,
        r#"{"id":2,"cmd":"follow","job":99999}"#,
        r#"{"id":3,"cmd":"move","job":-1,"to":1e400}"#,
        r#"{"id":4,"cmd":"remove","job":"1"}"#,
        r#"{"id":[1],"cmd":"jobs"}"#,
        r#"{"id":5,"cmd":"hello","version":999}"#,
        r#"{"id":6,"cmd":"operator-done","job":1}"#,
        r#"{"id":7,"cmd":"abort","job":3}"#,
        r#"{"id":8,"cmd":"add","job":{"kind":"run","out":"relative/path"}}"#,
        r#"{"id":9,"cmd":"nonsense"}"#,
        r#"[1,2,3]"#,
        r#""cmd""#,
        r#"{"cmd":{"nested":[[[[[[[[[[]]]]]]]]]]}}"#,
    ];
    let mut lines: Vec<Vec<u8>> = Vec::new();
    let mut i = 0;
    while lines.len() < 10_000 {
        i += 1;
        let line: Vec<u8> = match i % 4 {
            0 => (0..rng.random_range(1..200))
                .map(|_| rng.random::<u8>())
                .filter(|b| *b != b'\n')
                .collect(),
            1 => {
                let mut t = templates[rng.random_range(0..templates.len())]
                    .as_bytes()
                    .to_vec();
                // Cut or flip a byte here and there.
                if rng.random_bool(0.5) && !t.is_empty() {
                    let at = rng.random_range(0..t.len());
                    t.truncate(at);
                }
                if rng.random_bool(0.3) && !t.is_empty() {
                    let at = rng.random_range(0..t.len());
                    t[at] = rng.random_range(32..127);
                }
                t
            }
            2 => templates[rng.random_range(0..templates.len())]
                .as_bytes()
                .to_vec(),
            _ => format!(
                "{{\"id\":{},\"cmd\":\"{}\"}}",
                rng.random::<u32>(),
                "x".repeat(rng.random_range(0..50))
            )
            .into_bytes(),
        };
        if !line.iter().all(u8::is_ascii_whitespace) {
            lines.push(line);
        }
    }
    let mut c = d.connect();
    // Replies are read on a thread of their own, so neither side's buffer fills.
    let reader = c.reader.get_ref().try_clone().unwrap();
    let count = std::thread::spawn(move || {
        let mut r = BufReader::new(reader);
        let (mut ok, mut errors, mut l) = (0u64, 0u64, String::new());
        loop {
            l.clear();
            if r.read_line(&mut l).unwrap_or(0) == 0 {
                return (ok, errors);
            }
            let v: Value = serde_json::from_str(&l).expect("every reply is JSON");
            if v.get("event").is_some() {
                continue;
            }
            match v["ok"].as_bool() {
                Some(true) => ok += 1,
                Some(false) => errors += 1,
                None => panic!("a reply without ok: {l}"),
            }
        }
    });
    for l in &lines {
        c.send_raw(l);
        c.send_raw(b"\n");
    }
    // A 10 MB line, in pieces.
    let chunk = vec![b'a'; 1 << 20];
    for _ in 0..10 {
        c.send_raw(&chunk);
    }
    c.send_raw(b"\n");
    c.writer.shutdown(std::net::Shutdown::Write).unwrap();
    let (ok, errors) = count.join().unwrap();
    assert_eq!(
        (ok + errors) as usize,
        lines.len() + 1,
        "every line gets exactly one reply"
    );
    assert!(errors > 5000, "{ok} ok, {errors} errors");
    // Still answering, and memory did not grow with what it was sent.
    let mut fresh = d.connect();
    let st = fresh.request(json!({"cmd": "status"}));
    assert_eq!(st["ok"], true, "{st}");
    let after = rss_kb(d.pid());
    println!(
        "{} lines: {ok} ok, {errors} errors; the daemon's resident memory {before} kB before, {after} kB after",
        lines.len() + 1
    );
    assert!(
        after < before + 30_000,
        "resident memory grew from {before} kB to {after} kB"
    );
    assert!(!d.log().contains("panicked"), "{}", d.log());
    // Jobs queued by the fuzz, if any, are real jobs: clear them.
    let _ = fresh.request(json!({"cmd": "queue-stop"}));
}

#[test]
fn a_job_waiting_for_an_operator_with_nobody_attached_fails_after_its_timeout() {
    let dir = util::tempdir();
    let log = dir.path().join("lamp.log");
    let mut d = Daemon::new(&slow_rig(60.0, &log));
    d.flags = vec!["--operator".into(), "clients".into()];
    d.start();
    let mut watch = d.connect();
    watch.request(json!({"cmd": "follow"}));
    let o = d.glint(&[
        "trigger",
        "run",
        "--detach",
        "--json",
        "--operator-timeout",
        "2",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let id = serde_json::from_slice::<Value>(&o.stdout).unwrap()["job"]
        .as_u64()
        .unwrap();
    let asked = watch
        .events_until(|v| v["event"] == "operator")
        .pop()
        .unwrap();
    let t0 = Instant::now();
    assert_eq!(asked["action"], "remove-tile");
    // It waits visibly.
    let st: Value =
        serde_json::from_slice(&d.glint(&["daemon", "status", "--json"]).stdout).unwrap();
    assert_eq!(st["operator"]["job"], id, "{st}");
    let end = watch.events_until(ended(id)).pop().unwrap();
    let waited = t0.elapsed();
    assert_eq!(end["state"], "failed", "{end}");
    assert!(
        end["error"].as_str().unwrap().contains("nobody answered"),
        "{end}"
    );
    assert!(
        waited > Duration::from_millis(1500) && waited < Duration::from_secs(10),
        "{waited:?}"
    );
    let m = manifest(end["session"].as_str().unwrap());
    assert_eq!(m["state"], "failed");
    assert_eq!(m["lamp_off_confirmed"], true);
    // Someone at the rig answers: the next job completes.
    let mut trigger = Command::new(env!("CARGO_BIN_EXE_glint"))
        .args(["trigger", "capture", "--socket"])
        .arg(&d.socket)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // The failed job never took the tile off: the new one asks only for the grid photo.
    let mut answers = trigger.stdin.take().unwrap();
    answers.write_all(b"\n").unwrap();
    let done = watch
        .events_until(|v| v["event"] == "operator-done")
        .pop()
        .unwrap();
    assert_eq!(done["action"], "remove-tile", "{done}");
    assert_eq!(done["by"], "a client", "{done}");
    drop(answers);
    let o = trigger.wait_with_output().unwrap();
    assert!(o.status.success(), "{}", text(&o));
    assert!(
        String::from_utf8_lossy(&o.stdout).contains("complete"),
        "{}",
        text(&o)
    );
}

#[test]
fn a_stalled_camera_fails_the_job_the_daemon_stays_up_and_reopens_the_devices() {
    let mut t = small_rig();
    util::set(&mut t, "mock.faults.stall_at_frame", 12);
    let mut d = Daemon::new(&t);
    d.start();
    let mut watch = d.connect();
    watch.request(json!({"cmd": "follow"}));
    let first = queue(&d, "capture");
    let end = watch.events_until(ended(first)).pop().unwrap();
    assert_eq!(end["state"], "failed", "{end}");
    let error = end["error"].as_str().unwrap();
    assert!(error.contains("camera stalled: no frame within"), "{error}");
    assert!(!error.contains('\n'), "one line: {error}");
    let st: Value =
        serde_json::from_slice(&d.glint(&["daemon", "status", "--json"]).stdout).unwrap();
    assert_eq!(st["devices"]["state"], "failed", "{st}");
    assert!(
        st["devices"]["last_error"]
            .as_str()
            .unwrap()
            .contains("camera stalled"),
        "{st}"
    );
    // The next job reopens the devices (a fresh simulated camera, which stalls again at
    // its own frame 12), rather than finding them gone.
    let second = queue(&d, "capture");
    let end = watch.events_until(ended(second)).pop().unwrap();
    assert!(
        end["error"].as_str().unwrap().contains("camera stalled"),
        "{end}"
    );
    let m = manifest(end["session"].as_str().unwrap());
    assert_eq!(m["state"], "failed");
    // A client that loses the daemon says so in one line.
    let follower = Command::new(env!("CARGO_BIN_EXE_glint"))
        .args(["follow", "999", "--socket"])
        .arg(&d.socket)
        .output()
        .unwrap();
    assert!(
        text(&follower).contains("there is no job 999"),
        "{}",
        text(&follower)
    );
    let watcher = Command::new(env!("CARGO_BIN_EXE_glint"))
        .args(["trigger", "run", "--operator-timeout", "30", "--socket"])
        .arg(&d.socket)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    watch.events_until(|v| v["event"] == "job-started");
    d.signal(libc::SIGKILL);
    let o = watcher.wait_with_output().unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    let last = err.lines().last().unwrap_or("");
    assert!(last.starts_with("error: lost the glint daemon at"), "{err}");
}

#[test]
fn a_stuck_follower_never_holds_the_capture_and_gets_a_resync_when_it_reads_again() {
    let mut t = small_rig();
    // Many frames: some thousands of events, more than a stuck follower's queue holds.
    util::set(&mut t, "bracket.frames_per_exposure", 40);
    util::set(&mut t, "bracket.dark_frames_per_exposure", 40);
    let mut d = Daemon::new(&t);
    d.start();
    // A follower of everything that reads nothing.
    let mut stuck = d.connect();
    assert_eq!(stuck.request(json!({"cmd": "follow"}))["ok"], true);
    let mut watch = d.connect();
    watch.request(json!({"cmd": "follow"}));
    let jobs: Vec<u64> = (0..4).map(|_| queue(&d, "capture")).collect();
    let mut events = 0;
    for id in &jobs {
        let seen = watch.events_until(ended(*id));
        events += seen.len();
        assert_eq!(
            seen.last().unwrap()["state"],
            "complete",
            "{:?}",
            seen.last()
        );
    }
    assert!(events > 2500, "{events} events");
    // The stuck one now reads: what fitted in its queue and the socket, then a resync
    // saying how many it missed and where things stand.
    let mut missed = None;
    for _ in 0..events + 10 {
        let v = stuck.line();
        if v["event"] == "resync" {
            missed = v["missed"].as_u64();
            assert_eq!(v["status"]["queue"]["queued"], 0, "{v}");
            assert!(v["status"]["running"].is_null(), "{v}");
            break;
        }
    }
    let missed = missed.expect("a resync");
    assert!(
        missed > 0 && (missed as usize) < events,
        "{missed} of {events}"
    );
    // And it follows on as usual.
    let id = queue(&d, "capture");
    let rest = stuck.events_until(ended(id));
    assert_eq!(rest.last().unwrap()["state"], "complete");
}

#[test]
fn a_lamp_that_stops_answering_between_jobs_shows_in_status() {
    let mut t = small_rig();
    // Opening sends OFF and STATE?; the first idle check's STATE? is answered, then nothing.
    util::set(&mut t, "mock.faults.lamp_silent_after", 3);
    let mut d = Daemon::new(&t);
    d.flags = vec!["--health-interval".into(), "0.3".into()];
    d.start();
    let t0 = Instant::now();
    let status = loop {
        let o = d.glint(&["daemon", "status", "--json"]);
        let st: Value = serde_json::from_slice(&o.stdout).unwrap();
        if st["devices"]["state"] == "failed" {
            break st;
        }
        assert!(t0.elapsed() < Duration::from_secs(20), "{st}");
        std::thread::sleep(Duration::from_millis(100));
    };
    let e = status["devices"]["last_error"].as_str().unwrap();
    assert!(e.starts_with("idle check:"), "{e}");
    assert!(e.contains("did not answer `STATE?`"), "{e}");
    assert!(d
        .log()
        .contains("the devices are closed and reopened at the next job"));
}

#[test]
fn queued_jobs_can_be_moved_and_removed_and_a_stopped_queue_starts_nothing() {
    let mut d = Daemon::new(&small_rig());
    d.start();
    assert!(d.glint(&["queue", "stop"]).status.success());
    let ids: Vec<u64> = (0..3).map(|_| queue(&d, "capture")).collect();
    let o = d.glint(&["queue", "move", &ids[2].to_string(), "0"]);
    assert!(o.status.success(), "{}", text(&o));
    let o = d.glint(&["queue", "remove", &ids[1].to_string()]);
    assert!(o.status.success(), "{}", text(&o));
    let jobs = d.jobs();
    let order: Vec<u64> = jobs["queue"]
        .as_array()
        .unwrap()
        .iter()
        .map(|j| j["id"].as_u64().unwrap())
        .collect();
    assert_eq!(order, vec![ids[2], ids[0]]);
    assert!(jobs["running"].is_null() && jobs["history"].as_array().unwrap().is_empty());
    // The removed job's follower is told so; removing it again, or a running one, is refused.
    let o = d.glint(&["follow", &ids[1].to_string()]);
    assert!(!o.status.success());
    assert!(text(&o).contains("taken off the queue"), "{}", text(&o));
    let o = d.glint(&["queue", "remove", &ids[1].to_string()]);
    assert!(
        text(&o).contains(&format!("there is no job {}", ids[1])),
        "{}",
        text(&o)
    );
    let o = d.glint(&["abort"]);
    assert!(text(&o).contains("no job is running"), "{}", text(&o));
    // Started, it runs them in the new order.
    assert!(d.glint(&["queue", "start"]).status.success());
    let o = d.glint(&["follow", &ids[0].to_string()]);
    assert!(o.status.success(), "{}", text(&o));
    let jobs = d.jobs();
    let started = |id: u64| job(&jobs, id)["started"].as_str().unwrap().to_string();
    assert!(started(ids[2]) < started(ids[0]));
}

#[test]
fn a_lamp_unplugged_mid_job_fails_it_and_the_next_job_reopens_the_port() {
    // The lamp controller is its own process on a pty (a USB-serial adapter); it dies in
    // the middle of a capture, comes back at the same path, and the next job uses it.
    let lampdir = util::tempdir();
    let mut lamp = super::lamp_process::LampProcess::start(lampdir.path(), "glint");
    let mut t = small_rig();
    util::set(&mut t, "mock.sensor.realtime", true);
    util::set(&mut t, "lamp.backend", "serial");
    util::set(&mut t, "lamp.port", lamp.link.display().to_string());
    util::set(&mut t, "lamp.reply_timeout_ms", 200);
    let mut d = Daemon::new(&t);
    d.start();
    let mut watch = d.connect();
    watch.request(json!({"cmd": "follow"}));
    let first = queue(&d, "capture");
    let t0 = std::time::Instant::now();
    loop {
        let c = lamp.commands();
        if c.iter()
            .position(|l| l == "ON")
            .is_some_and(|i| c.len() >= i + 4)
        {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(60), "{c:?}");
        std::thread::sleep(Duration::from_millis(2));
    }
    lamp.child.kill().unwrap();
    lamp.child.wait().unwrap();
    let end = watch.events_until(ended(first)).pop().unwrap();
    assert_eq!(end["state"], "failed", "{end}");
    let error = end["error"].as_str().unwrap();
    assert!(error.contains("is gone"), "{error}");
    assert!(!error.contains('\n'), "one line: {error}");
    assert_eq!(
        manifest(end["session"].as_str().unwrap())["state"],
        "failed"
    );
    // Plugged back in (the same path): the next job opens the port again and completes.
    drop(lamp);
    let lamp = super::lamp_process::LampProcess::start(lampdir.path(), "glint");
    let second = queue(&d, "capture");
    let end = watch.events_until(ended(second)).pop().unwrap();
    assert_eq!(end["state"], "complete", "{end}");
    let c = lamp.commands();
    assert!(c.iter().any(|l| l == "ON"), "{c:?}");
    assert_eq!(&c[c.len() - 2..], ["OFF", "STATE?"], "{c:?}");
}

/// A daemon killed mid-capture with a serial lamp lit, its journal then damaged (a line of
/// garbage, or not readable at all): the next start switches the lamp off before it reads
/// the journal, and closes the session left `capturing` as `failed`, recording that the
/// lamp read back off, whether it then starts or refuses to.
#[test]
fn a_restart_on_a_damaged_journal_still_switches_the_lamp_off_and_closes_the_session() {
    use super::lamp_process::{is_dark, LampProcess};
    // Was: "line N: not a journal record…", exit 1, the lamp lit, the session `capturing`.
    for damage in ["garbage", "unreadable"] {
        let lampdir = util::tempdir();
        let lamp = LampProcess::start(lampdir.path(), "glint");
        let mut t = small_rig();
        util::set(&mut t, "mock.sensor.realtime", true);
        util::set(&mut t, "lamp.backend", "serial");
        util::set(&mut t, "lamp.port", lamp.link.display().to_string());
        util::set(&mut t, "lamp.reply_timeout_ms", 200);
        let mut d = Daemon::new(&t);
        d.start();
        let mut watch = d.connect();
        watch.request(json!({"cmd": "follow"}));
        let first = queue(&d, "capture");
        let mut frames = 0;
        watch.events_until(|v| {
            frames += (v["event"] == "frame" && v["job"] == first) as u32;
            frames >= 3
        });
        d.signal(libc::SIGKILL);
        d.wait(Duration::from_secs(10));
        assert!(
            !is_dark(&lamp),
            "{damage}: the lamp was lit when the daemon died"
        );
        let journal = d.state.join("journal.jsonl");
        match damage {
            "garbage" => {
                let mut f = std::fs::OpenOptions::new()
                    .append(true)
                    .open(&journal)
                    .unwrap();
                f.write_all(b"{\"record\":\"added\",\"job\":{\"id\":29,\"s\nnot a record\n")
                    .unwrap();
            }
            _ => {
                std::fs::remove_file(&journal).unwrap();
                std::fs::create_dir(&journal).unwrap();
            }
        }
        let mut child = d
            .command(&d.state)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        // It either refuses to start (exits) or starts (listens): either way, after that
        // the lamp is dark and the session closed.
        let t0 = Instant::now();
        let exited = loop {
            if let Some(st) = child.try_wait().unwrap() {
                break Some(st);
            }
            if UnixStream::connect(&d.socket).is_ok() {
                break None;
            }
            assert!(t0.elapsed() < Duration::from_secs(30), "{damage}: neither");
            std::thread::sleep(Duration::from_millis(20));
        };
        if exited.is_none() {
            let _ = child.kill();
        }
        let out = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        if let Some(st) = exited {
            assert!(!st.success(), "{damage}: {stderr}");
            let errors: Vec<&str> = stderr.lines().filter(|l| l.starts_with("error:")).collect();
            assert_eq!(errors.len(), 1, "{damage}: {stderr}");
        }
        assert!(
            is_dark(&lamp),
            "{damage}: the lamp's light file is lit: {stderr}"
        );
        let c = lamp.commands();
        assert_eq!(&c[c.len() - 2..], ["OFF", "STATE?"], "{damage}: {c:?}");
        let sessions: Vec<PathBuf> = std::fs::read_dir(d.state.join("sessions"))
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        assert_eq!(sessions.len(), 1, "{sessions:?}");
        let m = manifest(sessions[0].to_str().unwrap());
        assert_eq!(m["state"], "failed", "{damage}: {m}");
        assert!(
            m["failure"].as_str().unwrap().starts_with("daemon stopped"),
            "{damage}: {m}"
        );
        assert_eq!(m["lamp_off_confirmed"], true, "{damage}: {m}");
        let v = run(&["session", "verify", sessions[0].to_str().unwrap()]);
        assert!(v.status.success(), "{damage}: {}", text(&v));
    }
}

// ---------------------------------------------------------------------------------------
// The journal on a full disk, and damaged.

/// Start `d` with `GLINT_FAULT` set to `fault` (a named fault point, see
/// `src/daemon/journal.rs`) and wait until its socket answers.
fn start_with_fault(d: &mut Daemon, fault: &str) {
    d.env = vec![("GLINT_FAULT".into(), fault.into())];
    d.start();
    d.env.clear();
}

fn add_capture(c: &mut Conn) -> Value {
    c.request(json!({"cmd": "add", "job": {"kind": "capture"}}))
}

fn queued_ids(jobs: &Value) -> Vec<u64> {
    jobs["queue"]
        .as_array()
        .unwrap()
        .iter()
        .map(|j| j["id"].as_u64().unwrap())
        .collect()
}

#[test]
fn the_29th_add_failing_with_enospc_leaves_the_journal_whole_and_every_other_job_is_kept() {
    let mut d = Daemon::new(&small_rig());
    // Append 1 is the daemon's `opened`; append 30 is the 29th add: it writes half its
    // line, then fails with ENOSPC, as on the issue's full tmpfs.
    start_with_fault(&mut d, "journal-enospc:30");
    let mut c = d.connect();
    assert_eq!(c.request(json!({"cmd": "queue-stop"}))["ok"], true);
    let mut ids = Vec::new();
    for n in 1..=35 {
        let r = add_capture(&mut c);
        if n == 29 {
            assert_eq!(r["ok"], false, "{r}");
            let e = r["error"].as_str().unwrap();
            assert!(e.contains("No space left on device"), "{e}");
        } else {
            assert_eq!(r["ok"], true, "add {n}: {r}");
            ids.push(r["result"]["job"].as_u64().unwrap());
        }
    }
    assert_eq!(ids.len(), 34);
    // No torn line: every line of the journal is whole.
    let text = std::fs::read_to_string(d.state.join("journal.jsonl")).unwrap();
    assert!(text.ends_with('\n'));
    for l in text.lines() {
        serde_json::from_str::<Value>(l).unwrap_or_else(|e| panic!("{e}: {l}"));
    }
    // Killed, and started again: every job that was added is there, nothing set aside.
    d.signal(libc::SIGKILL);
    d.wait(Duration::from_secs(10));
    d.start();
    let jobs = d.jobs();
    assert_eq!(queued_ids(&jobs), ids, "{jobs}");
    let st = d.connect().request(json!({"cmd": "status"}));
    assert_eq!(st["result"]["journal"]["damaged_lines"], 0, "{st}");
    assert!(st["result"]["journal"]["set_aside"].is_null(), "{st}");
}

#[test]
fn queue_start_on_a_full_disk_answers_that_the_queue_is_stopped() {
    let mut d = Daemon::new(&small_rig());
    // `opened` and two adds are written; every append after them fails (the disk fills).
    start_with_fault(&mut d, "journal-enospc:4-");
    let mut c = d.connect();
    assert_eq!(c.request(json!({"cmd": "queue-stop"}))["ok"], true);
    for _ in 0..2 {
        assert_eq!(add_capture(&mut c)["ok"], true);
    }
    // The job cannot be journaled as started: the queue stops at once, and the reply says so.
    let r = c.request(json!({"cmd": "queue-start"}));
    assert_eq!(r["ok"], true, "{r}");
    assert_eq!(r["result"]["queue_running"], false, "{r}");
    let why = r["result"]["stopped_by"].as_str().unwrap();
    assert!(
        why.contains("cannot start job 1") && why.contains("No space left on device"),
        "{why}"
    );
    let st = c.request(json!({"cmd": "status"}));
    assert_eq!(st["result"]["queue"]["running"], false, "{st}");
    assert_eq!(st["result"]["running"], Value::Null, "{st}");
    // The command line says it too, with exit 1.
    let o = d.glint(&["queue", "start"]);
    assert!(!o.status.success(), "{}", text(&o));
    assert!(
        text(&o).contains("queue stopped: cannot start job 1"),
        "{}",
        text(&o)
    );
    let jobs = d.jobs();
    assert_eq!(queued_ids(&jobs), vec![1, 2], "{jobs}");
}

#[test]
fn a_damaged_journal_is_set_aside_reported_and_the_rest_replayed() {
    use glint::daemon::journal::{encode, Record};
    use glint::daemon::protocol::{Job, JobKind, JobSpec, JobState};
    let mut d = Daemon::new(&small_rig());
    std::fs::create_dir_all(&d.state).unwrap();
    let job = |id| Record::Added {
        job: Box::new(Job::queued(
            id,
            JobSpec::new(JobKind::Capture),
            None,
            "2026-12-06T00:00:00Z".into(),
        )),
    };
    let line = |r: &Record| String::from_utf8(encode(r).unwrap()).unwrap();
    // Jobs 1-4 added; job 1 started and its `ended` torn (the disk filled); a line of
    // garbage; job 3's line damaged in place (a byte changed, still JSON); a torn last line.
    let mut text = String::new();
    for id in 1..=4 {
        text += &line(&job(id));
    }
    text += &line(&Record::Started {
        job: 1,
        at: "2026-12-06T00:00:01Z".into(),
        session: None,
    });
    let ended = line(&Record::Ended {
        job: 1,
        state: JobState::Complete,
        at: "2026-12-06T00:00:02Z".into(),
        error: None,
        summary: None,
        summary_text: None,
    });
    text += &ended[..ended.len() / 2];
    text += "\n\u{1b}[31mnot a record\n";
    text = text.replacen("\"id\":3,", "\"id\":8,", 1);
    text += "{\"record\":\"added\",\"job\":{\"id\":5,\"s";
    std::fs::write(d.state.join("journal.jsonl"), &text).unwrap();
    d.start();
    let jobs = d.jobs();
    // Jobs 2 and 4 kept queued; job 1 started and never ended: interrupted, not re-run;
    // the queue waits to be started.
    assert_eq!(queued_ids(&jobs), vec![2, 4], "{jobs}");
    assert_eq!(job_state(&jobs, 1), "interrupted", "{jobs}");
    assert_eq!(jobs["queue_running"], false, "{jobs}");
    let st = d.connect().request(json!({"cmd": "status"}));
    let j = &st["result"]["journal"];
    assert_eq!(j["damaged_lines"], 4, "{st}");
    let lines: Vec<u64> = j["damaged"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| d["line"].as_u64().unwrap())
        .collect();
    assert_eq!(lines, vec![3, 6, 7, 8], "{st}");
    // The journal as it was read is kept, under a name of its own.
    let side = PathBuf::from(j["set_aside"].as_str().unwrap());
    assert_eq!(std::fs::read_to_string(&side).unwrap(), text);
    assert!(d.log().contains("set aside"), "{}", d.log());
    // Ids named in damaged lines are not given out again.
    let r = add_capture(&mut d.connect());
    assert_eq!(r["result"]["job"], 9, "{r}");
    // Restarted twice more: nothing more set aside, the earlier side file untouched.
    for _ in 0..2 {
        d.signal(libc::SIGTERM);
        d.wait(Duration::from_secs(10));
        d.start();
        let st = d.connect().request(json!({"cmd": "status"}));
        assert_eq!(st["result"]["journal"]["damaged_lines"], 0, "{st}");
    }
    assert_eq!(std::fs::read_to_string(&side).unwrap(), text);
    assert_eq!(queued_ids(&d.jobs()), vec![2, 4, 9]);
}

fn job_state(jobs: &Value, id: u64) -> String {
    job(jobs, id)["state"].as_str().unwrap().to_string()
}

// ---------------------------------------------------------------------------------------
// The journal is the truth; what is printed is clean; clients never hang.

/// A fake daemon: a Unix socket this test listens on, answering each request line with
/// what `script` returns for it. A returned `#sleep MS` pauses, `#hang` stops answering
/// (the connection stays open, its lines read and ignored), `#close` closes it.
pub struct FakeDaemon {
    /// Holds the socket's folder.
    pub _dir: tempfile::TempDir,
    pub socket: PathBuf,
}

impl FakeDaemon {
    pub fn start(script: impl Fn(&Value) -> Vec<String> + Send + Sync + 'static) -> FakeDaemon {
        let dir = util::tempdir();
        let socket = dir.path().join("fake.sock");
        let listener = std::os::unix::net::UnixListener::bind(&socket).unwrap();
        let script = std::sync::Arc::new(script);
        std::thread::spawn(move || {
            for stream in listener.incoming() {
                let Ok(stream) = stream else { return };
                let script = std::sync::Arc::clone(&script);
                std::thread::spawn(move || {
                    let mut w = stream.try_clone().unwrap();
                    let mut r = BufReader::new(stream);
                    let mut hung = false;
                    loop {
                        let mut l = String::new();
                        match r.read_line(&mut l) {
                            Ok(0) | Err(_) => return,
                            Ok(_) => {}
                        }
                        if hung {
                            continue;
                        }
                        let req: Value = serde_json::from_str(&l).unwrap_or(Value::Null);
                        for out in script(&req) {
                            if let Some(ms) = out.strip_prefix("#sleep ") {
                                std::thread::sleep(Duration::from_millis(ms.parse().unwrap()));
                            } else if out == "#hang" {
                                hung = true;
                                break;
                            } else if out == "#close"
                                || w.write_all(format!("{out}\n").as_bytes()).is_err()
                            {
                                return;
                            }
                        }
                    }
                });
            }
        });
        FakeDaemon { _dir: dir, socket }
    }

    /// `glint ARGS --socket S` with `GLINT_REPLY_TIMEOUT` = `timeout_s`; its output and
    /// how long it took.
    pub fn glint(&self, args: &[&str], timeout_s: f64) -> (Output, Duration) {
        let t0 = Instant::now();
        let o = Command::new(env!("CARGO_BIN_EXE_glint"))
            .args(args)
            .arg("--socket")
            .arg(&self.socket)
            .env("GLINT_REPLY_TIMEOUT", timeout_s.to_string())
            .stdin(Stdio::null())
            .output()
            .unwrap();
        (o, t0.elapsed())
    }
}

/// The reply a fake daemon gives to `hello` (heartbeats every `heartbeat_s`).
pub fn fake_hello(req: &Value, heartbeat_s: f64) -> String {
    json!({"id": req["id"], "ok": true, "result": {
        "protocol": 1, "daemon": "0.1.0", "pid": 4242, "rig": "fake", "heartbeat_s": heartbeat_s,
    }})
    .to_string()
}

/// The reply `{"id": ID, "ok": true, "result": RESULT}`.
pub fn fake_ok(req: &Value, result: Value) -> String {
    json!({"id": req["id"], "ok": true, "result": result}).to_string()
}

/// Raw bytes a terminal would act on (escape, bell, carriage return, C1 controls), if any.
pub fn raw_controls(o: &Output) -> Option<String> {
    for (name, bytes) in [("stdout", &o.stdout), ("stderr", &o.stderr)] {
        let s = String::from_utf8_lossy(bytes);
        if let Some(c) = s
            .chars()
            .find(|c| c.is_control() && *c != '\n' || ('\u{202a}'..='\u{202e}').contains(c))
        {
            return Some(format!("{name} has {c:?}: {s:?}"));
        }
    }
    None
}

#[test]
fn a_daemon_that_never_answers_hangs_no_client() {
    let fake = FakeDaemon::start(|_| vec!["#hang".into()]);
    for args in [
        &["jobs"][..],
        &["daemon", "status"],
        &["queue", "remove", "1"],
        &["queue", "start"],
        &["abort"],
        &["trigger", "run", "--detach"],
        &["trigger", "run"],
        &["follow", "9"],
    ] {
        let (o, took) = fake.glint(args, 0.5);
        assert!(!o.status.success(), "{args:?}: {}", text(&o));
        assert!(took < Duration::from_secs(10), "{args:?} took {took:?}");
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(e.contains("did not answer within 0.5 s"), "{args:?}: {e}");
        assert_eq!(e.trim().lines().count(), 1, "{args:?}: {e}");
    }
}

/// A fake daemon that answers `follow` and then sends `events` (lines, or `#` directives).
fn fake_follow(heartbeat_s: f64, events: Vec<String>) -> FakeDaemon {
    FakeDaemon::start(move |req| match req["cmd"].as_str() {
        Some("hello") => vec![fake_hello(req, heartbeat_s)],
        Some("follow") => {
            let mut v = vec![fake_ok(req, json!({"following": req["job"]}))];
            v.extend(events.iter().cloned());
            v
        }
        _ => vec!["#hang".into()],
    })
}

fn ended_line(job: u64, state: &str, extra: Value) -> String {
    let mut v = json!({"seq": 50, "event": "job-ended", "job": job, "state": state});
    for (k, x) in extra.as_object().unwrap() {
        v[k] = x.clone();
    }
    v.to_string()
}

#[test]
fn follow_lives_on_heartbeats_through_a_long_step_and_ends_when_they_stop() {
    // 2 s of heartbeats only (every 0.1 s; the client gives up after 3 x 0.2 s + 0.5 s of
    // silence), then the job's end.
    let mut events = Vec::new();
    for _ in 0..20 {
        events.push("#sleep 100".to_string());
        events.push(json!({"event": "heartbeat", "seq": 3}).to_string());
    }
    events.push(ended_line(9, "complete", json!({"summary_text": "DONE"})));
    let fake = fake_follow(0.2, events);
    let (o, took) = fake.glint(&["follow", "9"], 5.0);
    assert!(o.status.success(), "{}", text(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("DONE"));
    assert!(took >= Duration::from_secs(2), "{took:?}");
    // A daemon that falls silent (no event, no heartbeat) ends the follow, non-zero.
    let fake = fake_follow(0.2, vec!["#hang".into()]);
    let (o, took) = fake.glint(&["follow", "9"], 5.0);
    assert!(!o.status.success(), "{}", text(&o));
    assert!(took < Duration::from_secs(4), "{took:?}");
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("an event or its heartbeat"), "{e}");
}

#[test]
fn the_end_of_another_job_does_not_end_a_follow() {
    let fake = fake_follow(
        0.2,
        vec![
            ended_line(8, "complete", json!({"summary_text": "OTHER"})),
            "#hang".into(),
        ],
    );
    let (o, _) = fake.glint(&["follow", "9"], 5.0);
    assert!(!o.status.success(), "{}", text(&o));
    assert!(
        !String::from_utf8_lossy(&o.stdout).contains("OTHER"),
        "{}",
        text(&o)
    );
    let fake = fake_follow(
        0.2,
        vec![
            ended_line(8, "complete", json!({"summary_text": "OTHER"})),
            ended_line(9, "failed", json!({"error": "the lamp broke"})),
        ],
    );
    let (o, _) = fake.glint(&["follow", "9"], 5.0);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(
        text(&o).contains("job 9 failed: the lamp broke"),
        "{}",
        text(&o)
    );
}

#[test]
fn mistyped_replies_are_errors_never_printed_nulls() {
    let cases: Vec<(&[&str], Value)> = vec![
        (&["daemon", "status"], json!({"pid": "x"})),
        (
            &["daemon", "status"],
            json!({"daemon": {"version": 1, "pid": "x"}}),
        ),
        (&["jobs"], json!({"queue_running": "yes"})),
        (
            &["jobs"],
            json!({"queue_running": true, "queue": [{"id": "x"}], "history": []}),
        ),
        (&["trigger", "run", "--detach"], json!({"job": "x"})),
        (&["queue", "start"], json!({"queue_running": null})),
        (&["queue", "remove", "3"], json!({"queue": "all"})),
        (&["abort"], json!(null)),
        (&["daemon", "stop"], json!([])),
    ];
    for (args, result) in cases {
        let r = result.clone();
        let fake = FakeDaemon::start(move |req| match req["cmd"].as_str() {
            Some("hello") => vec![fake_hello(req, 5.0)],
            _ => vec![fake_ok(req, r.clone())],
        });
        let (o, _) = fake.glint(args, 5.0);
        assert_eq!(o.status.code(), Some(1), "{args:?} {result}: {}", text(&o));
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(
            e.contains("is not what this glint"),
            "{args:?} {result}: {e}"
        );
        assert!(o.stdout.is_empty(), "{args:?} {result}: {}", text(&o));
    }
    // A hello without its fields: every command refuses the daemon.
    let fake = FakeDaemon::start(|req| vec![fake_ok(req, json!({"ok": true, "pid": "x"}))]);
    let (o, _) = fake.glint(&["daemon", "status"], 5.0);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(text(&o).contains("reply to `hello`"), "{}", text(&o));
    assert!(!text(&o).contains("null"), "{}", text(&o));
}

#[test]
fn escape_codes_and_newlines_from_the_daemon_never_reach_the_terminal_raw() {
    let evil = "\u{1b}[31mred\u{1b}]0;title\u{7}\r\nforged: line\u{9b}2J\u{202e}";
    let job = json!({
        "id": 9, "spec": {"kind": "run", "out": format!("/o{evil}")}, "state": "failed",
        "queued": evil, "session": format!("/s{evil}"), "error": evil,
    });
    let status = json!({
        "daemon": {"version": evil, "pid": 1, "rig_name": evil, "rig": evil, "started": evil},
        "devices": {"state": evil, "camera": evil, "lamp": evil, "since": evil, "last_error": evil},
        "queue": {"running": true, "queued": 0, "shutting_down": false},
        "running": job, "operator": {"job": 9, "message": evil, "since": evil},
    });
    let jobs = json!({"queue_running": true, "running": job, "queue": [job], "history": [job]});
    let fake = FakeDaemon::start(move |req| {
        match req["cmd"].as_str() {
        Some("hello") => vec![fake_hello(req, 5.0)],
        Some("status") => vec![fake_ok(req, status.clone())],
        Some("jobs") => vec![fake_ok(req, jobs.clone())],
        Some("follow") => vec![
            fake_ok(req, json!({"following": 9})),
            json!({"seq": 1, "event": "job-started", "job": 9, "kind": evil, "session": evil})
                .to_string(),
            json!({"seq": 2, "event": "step", "job": 9, "index": 0, "total": 1, "description": evil})
                .to_string(),
            json!({"seq": 3, "event": "warning", "job": 9, "message": evil}).to_string(),
            json!({"seq": 4, "event": "operator", "job": 9, "message": evil, "timeout_s": 1})
                .to_string(),
            ended_line(9, "failed", json!({"error": evil, "session": evil})),
        ],
        Some("queue-start") => vec![json!({"id": req["id"], "ok": false, "error": evil}).to_string()],
        _ => vec!["#hang".into()],
    }
    });
    for args in [
        &["daemon", "status"][..],
        &["jobs"],
        &["follow", "9"],
        &["queue", "start"],
    ] {
        let (o, _) = fake.glint(args, 5.0);
        if let Some(bad) = raw_controls(&o) {
            panic!("{args:?}: {bad}");
        }
        let all = text(&o);
        assert!(
            !all.lines().any(|l| l.starts_with("forged")),
            "{args:?}: a forged line: {all}"
        );
        assert!(all.contains("\\u{1b}[31mred"), "{args:?}: {all}");
    }
}

#[test]
fn the_65th_client_is_told_too_many_clients_in_one_line() {
    let mut d = Daemon::new(&small_rig());
    d.start();
    let held: Vec<Conn> = (0..64).map(|_| d.connect()).collect();
    for _ in 0..3 {
        let o = d.glint(&["jobs"]);
        assert_eq!(o.status.code(), Some(1), "{}", text(&o));
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(e.contains("too many clients"), "{e}");
        assert_eq!(e.trim().lines().count(), 1, "{e}");
        assert!(!e.contains("roken pipe") && !e.contains("reset"), "{e}");
    }
    drop(held);
    std::thread::sleep(Duration::from_millis(300));
    assert!(d.glint(&["jobs"]).status.success());
}

#[test]
fn a_job_whose_intrinsics_are_not_a_lens_file_is_refused_when_added() {
    let mut d = Daemon::new(&small_rig());
    d.start();
    let dir = util::tempdir();
    let fifo = dir.path().join("fifo.json");
    let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
    // SAFETY: mkfifo on a path in our own temporary folder.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
    let junk = dir.path().join("junk.json");
    std::fs::write(&junk, "{\"fx\": 1}").unwrap();
    for (file, says) in [
        ("/dev/zero", "device"),
        ("/etc/passwd", "not JSON"),
        (fifo.to_str().unwrap(), "FIFO"),
        (junk.to_str().unwrap(), "junk.json"),
        ("/nonexistent/camera.json", "camera.json"),
    ] {
        let t0 = Instant::now();
        let o = d.glint(&["trigger", "run", "--detach", "--intrinsics", file]);
        assert_eq!(o.status.code(), Some(1), "{file}: {}", text(&o));
        assert!(t0.elapsed() < Duration::from_secs(10));
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(e.contains("intrinsics") && e.contains(says), "{file}: {e}");
        assert_eq!(e.trim().lines().count(), 1, "{file}: {e}");
    }
    let jobs = d.jobs();
    assert!(jobs["queue"].as_array().unwrap().is_empty(), "{jobs}");
    assert!(jobs["history"].as_array().unwrap().is_empty(), "{jobs}");
}

/// A daemon whose capture job was killed (-9) after its first frame and which was then
/// started again: the job is `interrupted` in the journal. The daemon, the job, and its
/// session.
pub fn interrupted_job() -> (Daemon, u64, PathBuf) {
    let (mut d, _watch, id, _log) = capture_under_way();
    d.signal(libc::SIGKILL);
    d.wait(Duration::from_secs(10));
    d.start();
    let j = job(&d.jobs(), id);
    assert_eq!(j["state"], "interrupted", "{j}");
    let session = PathBuf::from(j["session"].as_str().unwrap());
    assert!(session.join("events.jsonl").is_file());
    (d, id, session)
}

#[test]
fn a_forged_events_file_cannot_change_a_jobs_outcome_after_a_restart() {
    let (d, id, session) = interrupted_job();
    let events = session.join("events.jsonl");
    let mut f = std::fs::OpenOptions::new()
        .append(true)
        .open(&events)
        .unwrap();
    writeln!(
        f,
        "{}",
        json!({"seq": 9999, "event": "job-ended", "job": id, "state": "complete",
               "summary_text": "FAKE\u{1b}[2J", "summary": {"fake": true}})
    )
    .unwrap();
    drop(f);
    let o = d.glint(&["follow", &id.to_string()]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(!text(&o).contains("FAKE"), "{}", text(&o));
    assert!(
        text(&o).contains(&format!("job {id} interrupted: daemon stopped")),
        "{}",
        text(&o)
    );
    let o = d.glint(&["follow", &id.to_string(), "--json"]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(!text(&o).contains("fake"), "{}", text(&o));
    // The raw events: the file's history, then the journal's end, once.
    let o = d.glint(&["follow", &id.to_string(), "--json", "--events"]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    let ends: Vec<Value> = String::from_utf8_lossy(&o.stdout)
        .lines()
        .map(|l| serde_json::from_str::<Value>(l).unwrap())
        .filter(|v| v["event"] == "job-ended")
        .collect();
    assert_eq!(ends.len(), 1, "{}", text(&o));
    assert_eq!(ends[0]["state"], "interrupted");
    assert_eq!(ends[0]["replayed"], true);
}
