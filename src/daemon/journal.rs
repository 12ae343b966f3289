//! The queue and the history, kept on disk as a journal: `STATE_DIR/journal.jsonl`, one
//! JSON record a line, each appended and `fsync`ed before the daemon acts on it.
//!
//! Why a hand-written journal rather than an embedded store (redb, sled): the state is a
//! few hundred small records, the only operations are "append one" and "read all at
//! start", and a text journal can be read (and mended) by a person with a text editor.
//! At each start the daemon replays the journal and writes it anew as one `snapshot`
//! record (to a temporary file, synced, renamed into place, the folder synced), so it
//! never grows beyond the history it keeps.
//!
//! A crash can tear only the last line (appends are whole lines, synced one by one): a
//! last line without its newline is dropped with a warning. Any other line that does not
//! parse stops the daemon with its line number: the journal is the daemon's memory of
//! what ran, and guessing past damage could re-run a job or lose one.

use std::collections::BTreeMap;
use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use serde_json::Value;

use super::protocol::{Job, JobState};

/// Ended jobs the journal keeps (the oldest are dropped at start beyond this).
pub const HISTORY_KEPT: usize = 10_000;
/// Ended jobs whose summaries the journal keeps (the latest).
pub const SUMMARIES_KEPT: usize = 100;

/// One line of the journal.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "record", rename_all = "kebab-case")]
pub enum Record {
    /// The whole state (the first line after a start).
    Snapshot {
        next_id: u64,
        /// Queued jobs' ids in the order they run.
        queue: Vec<u64>,
        jobs: Vec<Job>,
    },
    Added {
        job: Box<Job>,
    },
    Removed {
        job: u64,
    },
    Moved {
        job: u64,
        to: usize,
    },
    /// A job starts: written before anything of it runs.
    Started {
        job: u64,
        at: String,
        #[serde(default)]
        session: Option<PathBuf>,
    },
    Ended {
        job: u64,
        state: JobState,
        at: String,
        #[serde(default)]
        error: Option<String>,
        #[serde(default)]
        summary: Option<Value>,
        #[serde(default)]
        summary_text: Option<String>,
    },
    /// A daemon started (pid) on this state.
    Opened {
        pid: u32,
        at: String,
    },
    /// The daemon stopped cleanly.
    Closed {
        at: String,
    },
}

/// The queue and the history, as replayed.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Book {
    pub jobs: BTreeMap<u64, Job>,
    /// Queued jobs in the order they run.
    pub queue: Vec<u64>,
    pub next_id: u64,
}

impl Book {
    /// Apply one record; an impossible one (a job that does not exist) is an error.
    pub fn apply(&mut self, r: &Record) -> Result<(), String> {
        match r {
            Record::Snapshot {
                next_id,
                queue,
                jobs,
            } => {
                self.jobs = jobs.iter().map(|j| (j.id, j.clone())).collect();
                self.queue = queue.clone();
                self.next_id = *next_id;
                for id in queue {
                    if self.jobs.get(id).map(|j| j.state) != Some(JobState::Queued) {
                        return Err(format!("the queue lists job {id}, which is not queued"));
                    }
                }
                let mut listed = queue.clone();
                listed.sort_unstable();
                listed.dedup();
                let queued = self
                    .jobs
                    .values()
                    .filter(|j| j.state == JobState::Queued)
                    .count();
                if listed.len() != queue.len() || queued != queue.len() {
                    return Err("the queue must list every queued job exactly once".to_string());
                }
                if self.jobs.keys().any(|&id| id >= self.next_id) {
                    return Err("a job's id is not below next_id".into());
                }
            }
            Record::Added { job } => {
                if self.jobs.contains_key(&job.id) || job.id < self.next_id {
                    return Err(format!("job {} added twice", job.id));
                }
                self.next_id = job.id + 1;
                if job.state == JobState::Queued {
                    self.queue.push(job.id);
                }
                self.jobs.insert(job.id, (**job).clone());
            }
            Record::Removed { job } => {
                self.take_queued(*job)?;
                self.jobs.remove(job);
            }
            Record::Moved { job, to } => {
                self.take_queued(*job)?;
                let to = (*to).min(self.queue.len());
                self.queue.insert(to, *job);
            }
            Record::Started { job, at, session } => {
                self.take_queued(*job)?;
                let j = self.job_mut(*job)?;
                j.state = JobState::Running;
                j.started = Some(at.clone());
                j.session = session.clone().or(j.session.take());
            }
            Record::Ended {
                job,
                state,
                at,
                error,
                summary,
                summary_text,
            } => {
                if !state.ended() {
                    return Err(format!("job {job} ended as {}", state.name()));
                }
                self.queue.retain(|q| q != job);
                let j = self.job_mut(*job)?;
                j.state = *state;
                j.ended = Some(at.clone());
                j.error = error.clone();
                j.summary = summary.clone();
                j.summary_text = summary_text.clone();
            }
            Record::Opened { .. } | Record::Closed { .. } => {}
        }
        Ok(())
    }

    /// Whether [`Book::apply`] would accept `r`, without applying it (the daemon checks a
    /// record before it goes on disk).
    pub fn check(&self, r: &Record) -> Result<(), String> {
        let queued = |id: &u64| {
            if self.queue.contains(id) {
                Ok(())
            } else {
                Err(format!("job {id} is not queued"))
            }
        };
        match r {
            Record::Added { job } => {
                if self.jobs.contains_key(&job.id) || job.id < self.next_id {
                    return Err(format!("job {} added twice", job.id));
                }
                Ok(())
            }
            Record::Removed { job } | Record::Moved { job, .. } | Record::Started { job, .. } => {
                queued(job)
            }
            Record::Ended { job, state, .. } => {
                if !state.ended() {
                    return Err(format!("job {job} ended as {}", state.name()));
                }
                if !self.jobs.contains_key(job) {
                    return Err(format!("job {job} does not exist"));
                }
                Ok(())
            }
            Record::Snapshot { .. } | Record::Opened { .. } | Record::Closed { .. } => Ok(()),
        }
    }

    /// Forget the summaries of all but the latest [`SUMMARIES_KEPT`] ended jobs (memory).
    pub fn prune(&mut self) {
        let ended: Vec<u64> = self
            .jobs
            .values()
            .filter(|j| j.state.ended() && j.summary.is_some())
            .map(|j| j.id)
            .collect();
        for id in &ended[..ended.len().saturating_sub(SUMMARIES_KEPT)] {
            if let Some(j) = self.jobs.get_mut(id) {
                j.summary = None;
                j.summary_text = None;
            }
        }
    }

    fn job_mut(&mut self, id: u64) -> Result<&mut Job, String> {
        self.jobs
            .get_mut(&id)
            .ok_or_else(|| format!("job {id} does not exist"))
    }

    fn take_queued(&mut self, id: u64) -> Result<(), String> {
        let at = self
            .queue
            .iter()
            .position(|q| *q == id)
            .ok_or_else(|| format!("job {id} is not queued"))?;
        self.queue.remove(at);
        Ok(())
    }

    /// The job now running, if any.
    pub fn running(&self) -> Option<&Job> {
        self.jobs.values().find(|j| j.state == JobState::Running)
    }

    /// The state as one record, dropping the oldest ended jobs beyond [`HISTORY_KEPT`],
    /// and the summaries of all but the latest [`SUMMARIES_KEPT`] (a run's is some tens of
    /// kilobytes; each job's session keeps its own in `events.jsonl`).
    pub fn snapshot(&self) -> Record {
        let ended: Vec<u64> = self
            .jobs
            .values()
            .filter(|j| j.state.ended())
            .map(|j| j.id)
            .collect();
        let drop = ended.len().saturating_sub(HISTORY_KEPT);
        let dropped: std::collections::HashSet<u64> = ended.into_iter().take(drop).collect();
        let ended_kept = self.jobs.values().filter(|j| j.state.ended()).count() - drop;
        let mut ended_seen = 0;
        Record::Snapshot {
            next_id: self.next_id,
            queue: self.queue.clone(),
            jobs: self
                .jobs
                .values()
                .filter(|j| !dropped.contains(&j.id))
                .map(|j| {
                    let mut j = j.clone();
                    if j.state.ended() {
                        ended_seen += 1;
                        if ended_kept - ended_seen >= SUMMARIES_KEPT {
                            j.summary = None;
                            j.summary_text = None;
                        }
                    }
                    j
                })
                .collect(),
        }
    }
}

/// What replaying a journal found.
#[derive(Debug)]
pub struct Replayed {
    pub book: Book,
    /// Whether the last daemon on this state stopped cleanly (or there was none).
    pub clean: bool,
    /// Things to log (a torn last line).
    pub notes: Vec<String>,
}

/// Replay a journal's text.
pub fn replay(path: &Path, text: &str) -> Result<Replayed, String> {
    let mut book = Book {
        next_id: 1,
        ..Book::default()
    };
    let mut clean = true;
    let mut notes = Vec::new();
    let torn_tail = !text.is_empty() && !text.ends_with('\n');
    let lines: Vec<&str> = text.split_terminator('\n').collect();
    for (i, line) in lines.iter().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let last = i + 1 == lines.len();
        let record: Record = match serde_json::from_str(line) {
            Ok(r) => r,
            Err(_) if last && torn_tail => {
                notes.push(format!(
                    "{}: dropped a torn last line (the daemon was killed while writing it)",
                    path.display()
                ));
                break;
            }
            Err(e) => {
                return Err(format!(
                    "{} line {}: not a journal record: {}; move the file away to start with an empty queue and history",
                    path.display(),
                    i + 1,
                    crate::fsx::json_error(&e)
                ))
            }
        };
        match &record {
            Record::Opened { .. } => clean = false,
            Record::Closed { .. } => clean = true,
            _ => {}
        }
        book.apply(&record).map_err(|e| {
            format!(
                "{} line {}: {e}; move the file away to start with an empty queue and history",
                path.display(),
                i + 1
            )
        })?;
    }
    Ok(Replayed { book, clean, notes })
}

/// The journal file, open for appending.
pub struct Journal {
    path: PathBuf,
    file: File,
    /// Its size, bytes.
    bytes: u64,
    /// Written anew past this size.
    threshold: u64,
    /// A compaction failed half-way: nothing more is written (every change is refused).
    broken: Option<String>,
}

impl Journal {
    /// Read the journal in `state_dir` (a missing one is empty), replay it, and write it
    /// anew as one snapshot.
    pub fn open(state_dir: &Path) -> Result<(Journal, Replayed), String> {
        let path = state_dir.join("journal.jsonl");
        let text = match crate::fsx::read_text_capped(&path, crate::fsx::MAX_TEXT_BYTES) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => String::new(),
            Err(e) => return Err(format!("reading {}: {e}", path.display())),
        };
        let replayed = replay(&path, &text)?;
        let (file, bytes) = write_snapshot(&path, &replayed.book)?;
        let mut replayed = replayed;
        replayed.book.prune();
        Ok((
            Journal {
                path,
                file,
                bytes,
                threshold: COMPACT_BYTES.max(2 * bytes),
                broken: None,
            },
            replayed,
        ))
    }

    /// Append one record and sync it to disk; past [`COMPACT_BYTES`], write the journal
    /// anew as one snapshot of `book` (with the record applied).
    pub fn append(&mut self, r: &Record) -> Result<(), String> {
        if let Some(e) = &self.broken {
            return Err(format!("the journal cannot be written since: {e}"));
        }
        let mut line = serde_json::to_vec(r).map_err(|e| e.to_string())?;
        line.push(b'\n');
        self.file
            .write_all(&line)
            .and_then(|_| self.file.sync_data())
            .map_err(|e| format!("writing {}: {e}", self.path.display()))?;
        self.bytes += line.len() as u64;
        Ok(())
    }

    /// Whether the journal has grown enough to be written anew ([`Journal::compact`]).
    pub fn wants_compaction(&self) -> bool {
        self.bytes > self.threshold
    }

    /// Write the journal anew as one snapshot of `book` (which must be what it replays to).
    /// A failure leaves the journal refusing every later record (the file on disk may no
    /// longer be the one open here): the daemon then starts nothing more.
    pub fn compact(&mut self, book: &Book) -> Result<(), String> {
        match write_snapshot(&self.path, book) {
            Ok((file, bytes)) => {
                self.file = file;
                self.bytes = bytes;
                self.threshold = COMPACT_BYTES.max(2 * bytes);
                Ok(())
            }
            Err(e) => {
                self.broken = Some(e.clone());
                Err(e)
            }
        }
    }
}

/// A journal this long (bytes) is written anew as a snapshot while the daemon runs, so it
/// stays far below what [`Journal::open`] reads ([`crate::fsx::MAX_TEXT_BYTES`]).
pub const COMPACT_BYTES: u64 = 8 << 20;

/// Write `book` as the journal at `path`: one snapshot line in a temporary file, synced,
/// renamed into place, the folder synced; the new file opened for appending, and its size.
fn write_snapshot(path: &Path, book: &Book) -> Result<(File, u64), String> {
    use std::os::unix::fs::OpenOptionsExt;
    let mut snapshot =
        serde_json::to_vec(&book.snapshot()).map_err(|e| format!("writing the journal: {e}"))?;
    snapshot.push(b'\n');
    let dir = path.parent().unwrap_or(Path::new("."));
    let tmp = dir.join(format!("journal.jsonl.tmp-{}", std::process::id()));
    // One left by a daemon of the same pid that died while compacting.
    let _ = std::fs::remove_file(&tmp);
    let written = (|| -> std::io::Result<()> {
        let mut f = OpenOptions::new()
            .write(true)
            .create_new(true)
            .mode(0o600)
            .custom_flags(libc::O_NOFOLLOW)
            .open(&tmp)?;
        f.write_all(&snapshot)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)?;
        File::open(dir)?.sync_all()
    })();
    if let Err(e) = written {
        let _ = std::fs::remove_file(&tmp);
        return Err(format!("writing {}: {e}", path.display()));
    }
    let file = OpenOptions::new()
        .append(true)
        .open(path)
        .map_err(|e| format!("opening {}: {e}", path.display()))?;
    Ok((file, snapshot.len() as u64))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::daemon::protocol::{JobKind, JobSpec};

    fn job(id: u64) -> Job {
        Job::queued(id, JobSpec::new(JobKind::Run), None, "t".into())
    }

    #[test]
    fn replay_follows_the_queue_and_drops_only_a_torn_last_line() {
        let recs = [
            Record::Opened {
                pid: 1,
                at: "t".into(),
            },
            Record::Added {
                job: Box::new(job(1)),
            },
            Record::Added {
                job: Box::new(job(2)),
            },
            Record::Added {
                job: Box::new(job(3)),
            },
            Record::Moved { job: 3, to: 0 },
            Record::Removed { job: 2 },
            Record::Started {
                job: 3,
                at: "t".into(),
                session: Some("/s".into()),
            },
        ];
        let mut text: String = recs
            .iter()
            .map(|r| serde_json::to_string(r).unwrap() + "\n")
            .collect();
        let r = replay(Path::new("j"), &text).unwrap();
        assert_eq!(r.book.queue, vec![1]);
        assert_eq!(r.book.running().map(|j| j.id), Some(3));
        assert!(!r.clean, "opened and never closed");
        assert_eq!(r.book.next_id, 4);
        text.push_str("{\"record\":\"ended\",\"jo");
        let torn = replay(Path::new("j"), &text).unwrap();
        assert_eq!(torn.book, r.book);
        assert_eq!(torn.notes.len(), 1);
        let bad = text.replace("\"moved\"", "\"mooved\"");
        assert!(replay(Path::new("j"), &bad).unwrap_err().contains("line 5"));
        // A snapshot replays to the same book.
        let snap = serde_json::to_string(&r.book.snapshot()).unwrap() + "\n";
        assert_eq!(replay(Path::new("j"), &snap).unwrap().book, r.book);
    }

    #[test]
    fn impossible_records_are_refused() {
        let mut b = Book::default();
        assert!(b.apply(&Record::Removed { job: 9 }).is_err());
        b.apply(&Record::Added {
            job: Box::new(job(1)),
        })
        .unwrap();
        assert!(b
            .apply(&Record::Added {
                job: Box::new(job(1))
            })
            .is_err());
        assert!(b
            .apply(&Record::Ended {
                job: 1,
                state: JobState::Running,
                at: "t".into(),
                error: None,
                summary: None,
                summary_text: None
            })
            .is_err());
    }

    #[test]
    fn a_snapshot_keeps_the_latest_summaries_and_compaction_replays_to_the_same_book() {
        let dir = tempfile::tempdir().unwrap();
        let (mut journal, replayed) = Journal::open(dir.path()).unwrap();
        let mut book = replayed.book;
        for id in 1..=(SUMMARIES_KEPT as u64 + 20) {
            for r in [
                Record::Added {
                    job: Box::new(job(id)),
                },
                Record::Started {
                    job: id,
                    at: "t".into(),
                    session: None,
                },
                Record::Ended {
                    job: id,
                    state: JobState::Complete,
                    at: "t".into(),
                    error: None,
                    summary: Some(serde_json::json!({ "n": id })),
                    summary_text: Some(format!("job {id}")),
                },
            ] {
                journal.append(&r).unwrap();
                book.apply(&r).unwrap();
            }
        }
        // Replayed as appended (the book in memory keeps the latest summaries only).
        let (_, again) = Journal::open(dir.path()).unwrap();
        let mut pruned = book.clone();
        pruned.prune();
        assert_eq!(again.book, pruned);
        assert_ne!(pruned, book);
        // Written anew: one line, the oldest 20 summaries dropped, the rest as they were.
        journal.compact(&book).unwrap();
        let text = std::fs::read_to_string(dir.path().join("journal.jsonl")).unwrap();
        assert_eq!(text.lines().count(), 1);
        let (_, compacted) = Journal::open(dir.path()).unwrap();
        let with_summary: Vec<u64> = compacted
            .book
            .jobs
            .values()
            .filter(|j| j.summary.is_some())
            .map(|j| j.id)
            .collect();
        assert_eq!(with_summary, (21..=120).collect::<Vec<u64>>());
        assert_eq!(compacted.book.jobs.len(), 120);
        assert_eq!(compacted.book.next_id, 121);
    }
}
