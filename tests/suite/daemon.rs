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
        }
    }

    /// Start it and wait until its socket answers.
    pub fn start(&mut self) -> &mut Self {
        let child = Command::new(env!("CARGO_BIN_EXE_glint"))
            .args(["daemon", "--rig"])
            .arg(&self.rig)
            .arg("--socket")
            .arg(&self.socket)
            .arg("--state-dir")
            .arg(&self.state)
            .args(&self.flags)
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
    pub fn events_until(&mut self, stop: impl Fn(&Value) -> bool) -> Vec<Value> {
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
