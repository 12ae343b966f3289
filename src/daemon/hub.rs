//! Event fan-out: every event gets the next sequence number, goes into its job's log (in
//! memory for recent jobs, and `SESSION/events.jsonl` once the session exists), and to
//! every follower.
//!
//! Publishing never waits: each follower has a bounded queue, and an event that does not
//! fit is dropped for that follower and counted. When its queue has drained, the
//! connection sends the follower a `resync` with a status snapshot and the number of
//! events it missed (see the server), so a stuck client never slows the capture and never
//! silently misses an outcome. A follower that attaches late gets its job's log from the
//! start, taken under the same lock that registers it, so it sees every event exactly once.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use serde_json::Value;
use tokio::sync::mpsc;

use super::protocol::event_line;

/// Events a follower's queue holds before it is counted as lagging.
pub const FOLLOWER_QUEUE: usize = 1024;
/// Jobs whose logs stay in memory (older ones are read back from `events.jsonl`).
const LOGS_KEPT: usize = 32;
/// The most events one job's in-memory log holds (a run has some hundreds).
const LOG_MAX_EVENTS: usize = 100_000;

/// One event line, shared by every follower it goes to.
pub type Line = Arc<str>;

/// A follower's end: its events and its count of events dropped for it.
pub struct Subscription {
    pub id: u64,
    /// The job's events so far (a job follower attaching late), to send first.
    pub backlog: Vec<Line>,
    pub rx: mpsc::Receiver<Line>,
    pub missed: Arc<AtomicU64>,
}

struct Follower {
    id: u64,
    /// Only this job's events; `None`: every event.
    job: Option<u64>,
    tx: mpsc::Sender<Line>,
    missed: Arc<AtomicU64>,
}

#[derive(Default)]
struct JobLog {
    lines: Vec<Line>,
    /// The session's `events.jsonl`, once the session exists.
    file: Option<File>,
    /// The session the job writes; `events.jsonl` is opened there once known.
    session: Option<PathBuf>,
    ended: bool,
}

#[derive(Default)]
struct Inner {
    seq: u64,
    next_follower: u64,
    followers: Vec<Follower>,
    logs: BTreeMap<u64, JobLog>,
}

impl Inner {
    /// Drop the oldest ended jobs' logs beyond [`LOGS_KEPT`] (a job that has not ended
    /// keeps its log: its followers wait for its events).
    fn make_room(&mut self) {
        while self.logs.len() >= LOGS_KEPT {
            let Some(oldest) = self.logs.iter().find(|(_, l)| l.ended).map(|(id, _)| *id) else {
                break;
            };
            self.logs.remove(&oldest);
        }
    }
}

/// The fan-out. Cheap to call from any thread; never blocks on a follower.
#[derive(Default)]
pub struct Hub {
    inner: Mutex<Inner>,
}

impl Hub {
    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The last sequence number given out.
    pub fn seq(&self) -> u64 {
        self.lock().seq
    }

    /// Publish an event (`fields` is an object with `event`); returns its sequence number.
    pub fn publish(&self, job: Option<u64>, fields: Value) -> u64 {
        // A job's last event: it ended, or was taken off the queue.
        let ended = matches!(
            fields.get("event").and_then(Value::as_str),
            Some("job-ended" | "job-removed")
        );
        let mut g = self.lock();
        g.seq += 1;
        let seq = g.seq;
        let line: Line = event_line(seq, job, fields).into();
        if let Some(j) = job {
            if !g.logs.contains_key(&j) {
                g.make_room();
            }
            let log = g.logs.entry(j).or_default();
            // The job's end is kept whatever the cap: a late follower must see it.
            if log.lines.len() < LOG_MAX_EVENTS || ended {
                log.lines.push(Arc::clone(&line));
            }
            log.write(&line);
            log.ended |= ended;
            if ended {
                log.file = None;
            }
        }
        g.followers.retain(|f| {
            if f.job.is_some() && f.job != job {
                return !f.tx.is_closed();
            }
            match f.tx.try_send(Arc::clone(&line)) {
                Ok(()) => true,
                Err(mpsc::error::TrySendError::Full(_)) => {
                    f.missed.fetch_add(1, Ordering::SeqCst);
                    true
                }
                Err(mpsc::error::TrySendError::Closed(_)) => false,
            }
        });
        seq
    }

    /// The session a job writes, so its events also go to `SESSION/events.jsonl` (the
    /// events so far are written at once). Call only once the session is the job's own
    /// (created by its capture, or the session it processes).
    pub fn set_session(&self, job: u64, dir: &Path) {
        let mut g = self.lock();
        let log = g.logs.entry(job).or_default();
        if log.session.is_some() {
            return;
        }
        log.session = Some(dir.to_path_buf());
        match open_events_file(dir) {
            Ok(f) => {
                log.file = Some(f);
                let lines = log.lines.clone();
                for l in &lines {
                    log.write(l);
                }
            }
            Err(e) => tracing::warn!("job {job}: not writing {}/events.jsonl: {e}", dir.display()),
        }
    }

    /// Keep a log for a job that has not ended though it has no events yet in this daemon
    /// (queued before a restart), so that it can be followed; `events` are its earlier
    /// events (from its session's `events.jsonl`), if any.
    pub fn open_log(&self, job: u64, events: Vec<Line>) {
        let mut g = self.lock();
        if !g.logs.contains_key(&job) {
            g.make_room();
            g.logs.entry(job).or_default().lines = events;
        }
    }

    /// Follow every event from now on.
    pub fn follow_all(&self) -> Subscription {
        let mut g = self.lock();
        Self::register(&mut g, None, Vec::new())
    }

    /// Follow a job: its events so far (`None` if they are no longer in memory: read
    /// `events.jsonl`), and live ones unless it has ended.
    pub fn follow_job(&self, job: u64) -> Option<Subscription> {
        let mut g = self.lock();
        let (backlog, ended) = {
            let log = g.logs.get(&job)?;
            (log.lines.clone(), log.ended)
        };
        let mut s = Self::register(&mut g, Some(job), backlog);
        if ended {
            // Nothing more will come: an empty, closed queue.
            g.followers.retain(|f| f.id != s.id);
            s.rx.close();
        }
        Some(s)
    }

    fn register(g: &mut Inner, job: Option<u64>, backlog: Vec<Line>) -> Subscription {
        let (tx, rx) = mpsc::channel(FOLLOWER_QUEUE);
        g.next_follower += 1;
        let id = g.next_follower;
        let missed = Arc::new(AtomicU64::new(0));
        g.followers.push(Follower {
            id,
            job,
            tx,
            missed: Arc::clone(&missed),
        });
        Subscription {
            id,
            backlog,
            rx,
            missed,
        }
    }

    /// Stop sending to a follower.
    pub fn unfollow(&self, id: u64) {
        self.lock().followers.retain(|f| f.id != id);
    }

    /// How many followers are attached (for `status`).
    pub fn followers(&self) -> usize {
        self.lock().followers.len()
    }
}

impl JobLog {
    fn write(&mut self, line: &str) {
        if let Some(f) = self.file.as_mut() {
            let mut bytes = Vec::with_capacity(line.len() + 1);
            bytes.extend_from_slice(line.as_bytes());
            bytes.push(b'\n');
            if let Err(e) = f.write_all(&bytes) {
                tracing::warn!("writing events.jsonl: {e}; no more events written there");
                self.file = None;
            }
        }
    }
}

/// Open `DIR/events.jsonl` for appending: a regular file or a new one, never through a
/// link, never a FIFO or device (opened without blocking, then checked).
fn open_events_file(dir: &Path) -> std::io::Result<File> {
    use std::os::unix::fs::OpenOptionsExt;
    let f = std::fs::OpenOptions::new()
        .append(true)
        .create(true)
        .mode(0o644)
        .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK)
        .open(dir.join("events.jsonl"))?;
    if !f.metadata()?.is_file() {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            "events.jsonl is not a regular file",
        ));
    }
    Ok(f)
}

/// Whether a line read back from a session's `events.jsonl` may be replayed to a follower
/// as history: a JSON object whose `event` is a progress event, never one that says how
/// the job ended or asks something of the client (`job-ended`, `job-removed`, `resync`,
/// `operator`, `operator-done`, `heartbeat`, `daemon-stopping`): the file is in the
/// session, which others may write, and a job's outcome is the journal's alone.
pub fn is_history(line: &str) -> bool {
    let Ok(Value::Object(m)) = serde_json::from_str::<Value>(line) else {
        return false;
    };
    match m.get("event").and_then(Value::as_str) {
        Some(e) => !matches!(
            e,
            "job-ended"
                | "job-removed"
                | "resync"
                | "operator"
                | "operator-done"
                | "heartbeat"
                | "daemon-stopping"
        ),
        None => false,
    }
}

/// The most of an `events.jsonl` a follow replays, bytes (a run's events are ~100 kB).
pub const REPLAY_MAX_BYTES: u64 = 8 << 20;

/// A finished job's events read back from its session's `events.jsonl` (at most
/// [`REPLAY_MAX_BYTES`], a regular file, lines of at most `MAX_LINE`), for a follower of a
/// job whose log is no longer in memory.
pub fn read_events_file(dir: &Path, job: u64) -> std::io::Result<Vec<Line>> {
    let text = crate::fsx::read_text_capped(&dir.join("events.jsonl"), REPLAY_MAX_BYTES)?;
    Ok(text
        .lines()
        .filter(|l| l.len() <= super::protocol::MAX_LINE)
        .filter(|l| {
            serde_json::from_str::<Value>(l)
                .ok()
                .and_then(|v| v.get("job").and_then(Value::as_u64))
                == Some(job)
        })
        .map(Line::from)
        .collect())
}
