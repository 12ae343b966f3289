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
//! **Each line carries its checksum.** A record is written as its JSON object with one
//! more member at its end, `,"crc":"XXXXXXXX"}`: the CRC-32 (IEEE, as zlib and PNG),
//! eight lower-case hex digits, of the line's bytes with that member taken out (the
//! record's JSON as it was serialised, ending in `}`). So a byte flipped in place that
//! still parses is caught. Journals written before checksums (whose first line has no
//! `crc`) are read as they are (a checksum present is still checked); in a journal whose
//! first line carries one, every line must. To mend a journal by hand, delete every line's
//! `,"crc":"…"` (the start writes it anew with checksums).
//!
//! **A write that fails leaves the journal as it was.** An append that fails (a full disk:
//! ENOSPC, after part of the line may have reached the file) cuts the file back to its
//! last whole record before the error is returned, so a later append never lands on a torn
//! line; if even that fails, the journal refuses every later record until the daemon is
//! restarted (whose replay sets the torn line aside).
//!
//! **A damaged line is set aside, never fatal.** At start a line that is torn (the daemon
//! killed while writing it), not a record, not UTF-8, fails its checksum, or that the
//! book refuses (a job that does not exist, one added twice, an `ended` as `running`, an
//! id beyond [`MAX_ID`], a snapshot after the first line) is skipped and the rest replayed. The journal as it was read is
//! kept beside it, `journal.jsonl.damaged-<UTC time>` (a new name each time, never one
//! overwritten), the damaged lines are logged with their numbers and why, `daemon status`
//! shows them (`journal`), and the queue starts stopped. Only a journal that cannot be
//! read at all (unreadable, or larger than [`crate::fsx::MAX_TEXT_BYTES`]) stops the start.
//!
//! What replaying past a damaged line means for safety: a record refused leaves the book
//! as it was (records are checked before they change anything). A job whose `started`
//! survived but whose `ended` is lost stays `running`, and the start closes it as
//! `interrupted` (its session `failed`), as after a crash: it never runs again. A job
//! whose `started` line is itself damaged (but still names the job) and that no later
//! record ended is also taken as having started: it may have run, so it is closed as
//! `interrupted` rather than re-run. Ids named in damaged lines are never given out again
//! (`next_id` moves past them). Jobs still queued stay queued, and wait for `glint queue
//! start`.
//!
//! **Fault injection (tests).** `GLINT_FAULT=journal-enospc:N` (also `N-M`, or `N-` for
//! every append from the N-th on; appends counted from 1 since the daemon opened the
//! journal; other comma-separated entries are ignored here) makes those appends write
//! half their line, then fail with ENOSPC, exactly as a full disk does.

use std::collections::BTreeMap;
use std::fs::{File, OpenOptions};
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};
use serde_json::Value;

use super::protocol::{Job, JobState};

/// Ended jobs the journal keeps (the oldest are dropped at start beyond this).
pub const HISTORY_KEPT: usize = 10_000;
/// Ended jobs whose summaries the journal keeps (the latest).
pub const SUMMARIES_KEPT: usize = 100;
/// Job ids stay below this (2^53: exact as a JSON number in any language); a record with
/// a larger one is damage.
pub const MAX_ID: u64 = 1 << 53;

/// Why the book refuses a record (see [`Book::check`]).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Refused {
    #[error("job {0} is not queued")]
    NotQueued(u64),
    #[error("job {0} does not exist")]
    NoSuchJob(u64),
    #[error("next_id {0} is beyond {MAX_ID}")]
    NextIdBeyond(u64),
    #[error("a job is listed twice")]
    ListedTwice,
    #[error("a job's id is not below next_id")]
    IdNotBelowNextId,
    #[error("the queue lists job {0}, which is not queued")]
    QueueListsUnqueued(u64),
    #[error("the queue must list every queued job exactly once")]
    QueueNotExact,
    #[error("job {0} has an id beyond {MAX_ID}")]
    IdBeyond(u64),
    #[error("job {0} added twice")]
    AddedTwice(u64),
    #[error("job {job} ended as {state}")]
    EndedAs { job: u64, state: &'static str },
}

/// Why a line of the journal is not a record the book accepts (a damaged line).
#[derive(Debug, thiserror::Error)]
pub enum LineError {
    #[error("its checksum does not match (changed after it was written)")]
    Checksum,
    #[error("no checksum, in a journal whose lines carry one")]
    NoChecksum,
    #[error("not UTF-8 text (byte {byte} of the line)")]
    NotUtf8 { byte: usize },
    #[error("not a journal record: {}", crate::fsx::json_error(.0))]
    NotARecord(serde_json::Error),
    #[error("a snapshot after the journal's first line")]
    LateSnapshot,
    #[error(transparent)]
    Refused(#[from] Refused),
}

/// A journal that cannot be read or written. Cheap to clone (the journal keeps the error
/// that broke it, to refuse every later record with it).
#[derive(Debug, Clone, thiserror::Error)]
pub enum JournalError {
    #[error("{0}")]
    Encode(Arc<serde_json::Error>),
    #[error("reading {}: {source}", path.display())]
    Read {
        path: PathBuf,
        source: Arc<io::Error>,
    },
    #[error("writing {}: {source}", path.display())]
    Write {
        path: PathBuf,
        source: Arc<io::Error>,
    },
    #[error("opening {}: {source}", path.display())]
    Open {
        path: PathBuf,
        source: Arc<io::Error>,
    },
    #[error("writing the journal: {0}")]
    Snapshot(Box<JournalError>),
    #[error("keeping the damaged journal {} aside as {}: {source}", path.display(), side.display())]
    KeepAside {
        path: PathBuf,
        side: PathBuf,
        source: Arc<io::Error>,
    },
    #[error("keeping the damaged journal {} aside: 1000 names taken", path.display())]
    NamesTaken { path: PathBuf },
    #[error("{write}, and cutting it back to its last whole record failed: {cut}")]
    CutBack {
        write: Box<JournalError>,
        cut: Arc<io::Error>,
    },
    #[error("the journal cannot be written since: {0}")]
    Broken(Box<JournalError>),
}

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
    /// Apply one record; an impossible one (a job that does not exist) is an error, and
    /// leaves the book as it was (every record is checked before it changes anything).
    pub fn apply(&mut self, r: &Record) -> Result<(), Refused> {
        self.check(r)?;
        match r {
            Record::Snapshot {
                next_id,
                queue,
                jobs,
            } => {
                self.jobs = jobs.iter().map(|j| (j.id, j.clone())).collect();
                self.queue = queue.clone();
                self.next_id = *next_id;
            }
            Record::Added { job } => {
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
    /// record before it goes on disk, and replay before it changes the book).
    pub fn check(&self, r: &Record) -> Result<(), Refused> {
        let queued = |id: &u64| {
            if self.queue.contains(id) && self.jobs.contains_key(id) {
                Ok(())
            } else {
                Err(Refused::NotQueued(*id))
            }
        };
        match r {
            Record::Snapshot {
                next_id,
                queue,
                jobs,
            } => {
                if *next_id > MAX_ID {
                    return Err(Refused::NextIdBeyond(*next_id));
                }
                let mut ids: Vec<u64> = jobs.iter().map(|j| j.id).collect();
                ids.sort_unstable();
                ids.dedup();
                if ids.len() != jobs.len() {
                    return Err(Refused::ListedTwice);
                }
                if ids.last().is_some_and(|&id| id >= *next_id) {
                    return Err(Refused::IdNotBelowNextId);
                }
                let states: std::collections::HashMap<u64, JobState> =
                    jobs.iter().map(|j| (j.id, j.state)).collect();
                for id in queue {
                    if states.get(id) != Some(&JobState::Queued) {
                        return Err(Refused::QueueListsUnqueued(*id));
                    }
                }
                let mut listed = queue.clone();
                listed.sort_unstable();
                listed.dedup();
                let queued = jobs.iter().filter(|j| j.state == JobState::Queued).count();
                if listed.len() != queue.len() || queued != queue.len() {
                    return Err(Refused::QueueNotExact);
                }
                Ok(())
            }
            Record::Added { job } => {
                if job.id >= MAX_ID {
                    return Err(Refused::IdBeyond(job.id));
                }
                if self.jobs.contains_key(&job.id) || job.id < self.next_id {
                    return Err(Refused::AddedTwice(job.id));
                }
                Ok(())
            }
            Record::Removed { job } | Record::Moved { job, .. } | Record::Started { job, .. } => {
                queued(job)
            }
            Record::Ended { job, state, .. } => {
                if !state.ended() {
                    return Err(Refused::EndedAs {
                        job: *job,
                        state: state.name(),
                    });
                }
                if !self.jobs.contains_key(job) {
                    return Err(Refused::NoSuchJob(*job));
                }
                Ok(())
            }
            Record::Opened { .. } | Record::Closed { .. } => Ok(()),
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

    fn job_mut(&mut self, id: u64) -> Result<&mut Job, Refused> {
        self.jobs.get_mut(&id).ok_or(Refused::NoSuchJob(id))
    }

    fn take_queued(&mut self, id: u64) -> Result<(), Refused> {
        let at = self
            .queue
            .iter()
            .position(|q| *q == id)
            .ok_or(Refused::NotQueued(id))?;
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
    /// Things to log (the damaged lines, the jobs taken as started).
    pub notes: Vec<String>,
    /// The lines set aside, numbered from 1 (the first [`DAMAGED_LISTED`]).
    pub damaged: Vec<Damaged>,
    /// How many lines were set aside in all.
    pub damaged_count: usize,
    /// Where the journal as it was read was kept, when a line was set aside.
    pub set_aside: Option<PathBuf>,
}

/// A line of the journal set aside at start.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Damaged {
    /// Its number, from 1.
    pub line: usize,
    /// Why it was set aside.
    pub why: String,
}

/// Damaged lines listed (in the log, in `status`); the rest are counted.
pub const DAMAGED_LISTED: usize = 20;

/// `,"crc":"XXXXXXXX"}`: the member each line ends with.
const CRC_HEAD: &[u8] = b",\"crc\":\"";
const CRC_TAIL_LEN: usize = CRC_HEAD.len() + 8 + 2;

/// A record as one journal line: its JSON with its checksum member, and `\n`.
pub fn encode(r: &Record) -> Result<Vec<u8>, JournalError> {
    let mut line = serde_json::to_vec(r).map_err(|e| JournalError::Encode(Arc::new(e)))?;
    let crc = crc32fast::hash(&line);
    line.pop(); // the closing brace
    line.extend_from_slice(CRC_HEAD);
    line.extend_from_slice(format!("{crc:08x}\"}}\n").as_bytes());
    Ok(line)
}

/// Whether `line` ends with a checksum member: then the record's JSON (the member taken
/// out) and whether the checksum matches it.
fn split_crc(line: &[u8]) -> Option<(Vec<u8>, bool)> {
    let n = line.len();
    if n < CRC_TAIL_LEN + 1
        || &line[n - CRC_TAIL_LEN..n - 10] != CRC_HEAD
        || &line[n - 2..] != b"\"}"
    {
        return None;
    }
    let mut body = line[..n - CRC_TAIL_LEN].to_vec();
    body.push(b'}');
    let stated = std::str::from_utf8(&line[n - 10..n - 2])
        .ok()
        .filter(|h| {
            h.bytes()
                .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
        })
        .and_then(|h| u32::from_str_radix(h, 16).ok());
    let ok = stated == Some(crc32fast::hash(&body));
    Some((body, ok))
}

/// One line as a record, or why it is not one. `checked`: the journal's lines carry
/// checksums, so this one must.
fn parse_line(line: &[u8], checked: bool) -> Result<Record, LineError> {
    let body = match split_crc(line) {
        Some((_, false)) => return Err(LineError::Checksum),
        Some((body, true)) => body,
        None if checked => return Err(LineError::NoChecksum),
        None => line.to_vec(),
    };
    let text = std::str::from_utf8(&body).map_err(|e| LineError::NotUtf8 {
        byte: e.valid_up_to() + 1,
    })?;
    serde_json::from_str(text).map_err(LineError::NotARecord)
}

/// What a damaged line still says, read leniently (any JSON object): whether it is a
/// `started` record and for which job (with its time), and the largest job id it names.
fn salvage(line: &[u8]) -> (Option<(u64, Option<String>)>, Option<u64>) {
    let body = split_crc(line)
        .map(|(b, _)| b)
        .unwrap_or_else(|| line.to_vec());
    let Ok(v) = serde_json::from_slice::<Value>(&body) else {
        return (None, None);
    };
    let job = v["job"].as_u64().or_else(|| v["job"]["id"].as_u64());
    let started = match (v["record"].as_str(), v["job"].as_u64()) {
        (Some("started"), Some(id)) => Some((id, v["at"].as_str().map(str::to_string))),
        _ => None,
    };
    (started, job.filter(|&id| id < MAX_ID))
}

/// Replay a journal's bytes: every line that is a record the book accepts, in order;
/// the others are listed in [`Replayed::damaged`] and skipped (see the module doc).
pub fn replay(path: &Path, text: impl AsRef<[u8]>) -> Replayed {
    let text = text.as_ref();
    let mut book = Book {
        next_id: 1,
        ..Book::default()
    };
    let mut clean = true;
    let mut notes = Vec::new();
    let mut damaged = Vec::new();
    let mut damaged_count = 0;
    let mut lines: Vec<&[u8]> = text.split(|&b| b == b'\n').collect();
    let torn_tail = lines.last().is_some_and(|l| !l.is_empty());
    if !torn_tail {
        lines.pop();
    }
    // Written with checksums (every line carries one) if its first line carries one.
    let checked = lines
        .iter()
        .find(|l| !l.iter().all(u8::is_ascii_whitespace))
        .is_some_and(|l| split_crc(l).is_some());
    let mut started_in_damage: Vec<(u64, Option<String>)> = Vec::new();
    let mut named_in_damage: Option<u64> = None;
    let mut first = true;
    for (i, line) in lines.iter().enumerate() {
        if line.iter().all(u8::is_ascii_whitespace) {
            continue;
        }
        let last = i + 1 == lines.len();
        let applied = parse_line(line, checked).and_then(|record| {
            // A snapshot is only ever written as a journal's first line.
            if matches!(record, Record::Snapshot { .. }) && !first {
                return Err(LineError::LateSnapshot);
            }
            book.apply(&record)?;
            Ok(record)
        });
        first = false;
        let why = match applied {
            Ok(record) => {
                match record {
                    Record::Opened { .. } => clean = false,
                    Record::Closed { .. } => clean = true,
                    _ => {}
                }
                continue;
            }
            Err(_) if last && torn_tail => {
                "torn: it has no end of line (the daemon stopped while writing it)".to_string()
            }
            Err(e) => e.to_string(),
        };
        let (started, named) = salvage(line);
        started_in_damage.extend(started);
        named_in_damage = named_in_damage.max(named);
        damaged_count += 1;
        if damaged.len() < DAMAGED_LISTED {
            damaged.push(Damaged { line: i + 1, why });
        }
    }
    // Ids named by damaged lines are never given out again.
    if let Some(id) = named_in_damage {
        book.next_id = book.next_id.max(id + 1);
    }
    // A job whose `started` is damaged and that nothing later ended may have run: taken
    // as started (the daemon closes it as interrupted), never run again.
    for (id, at) in started_in_damage {
        if book.queue.contains(&id) {
            let started = Record::Started {
                job: id,
                at: at.unwrap_or_else(|| "unknown (a damaged journal line)".into()),
                session: None,
            };
            if book.apply(&started).is_ok() {
                notes.push(format!(
                    "{}: job {id}'s `started` line is damaged: taken as started (it may have run), to be closed as interrupted, not run again",
                    path.display()
                ));
            }
        }
    }
    for d in &damaged {
        notes.push(format!(
            "{} line {}: {}; set aside",
            path.display(),
            d.line,
            d.why
        ));
    }
    if damaged_count > damaged.len() {
        notes.push(format!(
            "{}: {} more damaged lines set aside",
            path.display(),
            damaged_count - damaged.len()
        ));
    }
    Replayed {
        book,
        clean,
        notes,
        damaged,
        damaged_count,
        set_aside: None,
    }
}

/// Appends that fail (the fault point `journal-enospc`, see the module doc): numbered
/// from 1 since the journal was opened, `from..=to`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Fault {
    pub from: u64,
    pub to: u64,
}

impl Fault {
    /// The `journal-enospc` entry of a `GLINT_FAULT` value, if any (others are ignored).
    pub fn parse(spec: &str) -> Option<Fault> {
        spec.split(',').find_map(|entry| {
            let range = entry.trim().strip_prefix("journal-enospc:")?;
            let (from, to) = match range.split_once('-') {
                Some((a, "")) => (a.parse().ok()?, u64::MAX),
                Some((a, b)) => (a.parse().ok()?, b.parse().ok()?),
                None => {
                    let n = range.parse().ok()?;
                    (n, n)
                }
            };
            Some(Fault { from, to })
        })
    }

    fn hits(&self, n: u64) -> bool {
        (self.from..=self.to).contains(&n)
    }
}

/// The journal file, open for appending.
pub struct Journal {
    path: PathBuf,
    file: File,
    /// Its size, bytes: the end of its last whole record.
    bytes: u64,
    /// Written anew past this size.
    threshold: u64,
    /// The journal could not be put back as it was after a failed write, or a compaction
    /// failed half-way: nothing more is written (every change is refused).
    broken: Option<JournalError>,
    /// Appends since it was opened.
    appends: u64,
    /// Appends made to fail (tests: `GLINT_FAULT`).
    fault: Option<Fault>,
}

impl Journal {
    /// Read the journal in `state_dir` (a missing one is empty), replay it, set a damaged
    /// one aside (kept as it was read, beside it), and write it anew as one snapshot.
    pub fn open(state_dir: &Path) -> Result<(Journal, Replayed), JournalError> {
        let path = state_dir.join("journal.jsonl");
        let bytes = match crate::fsx::read_capped(&path, crate::fsx::MAX_TEXT_BYTES) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
            Err(e) => {
                return Err(JournalError::Read {
                    path,
                    source: Arc::new(e),
                })
            }
        };
        let mut replayed = replay(&path, &bytes);
        if replayed.damaged_count > 0 {
            let side = keep_aside(&path, &bytes)?;
            replayed.notes.push(format!(
                "the journal as it was read is kept in {}",
                side.display()
            ));
            replayed.set_aside = Some(side);
        }
        let (file, written) = write_snapshot(&path, &replayed.book)?;
        replayed.book.prune();
        let fault = std::env::var("GLINT_FAULT")
            .ok()
            .and_then(|v| Fault::parse(&v));
        Ok((
            Journal {
                path,
                file,
                bytes: written,
                threshold: COMPACT_BYTES.max(2 * written),
                broken: None,
                appends: 0,
                fault,
            },
            replayed,
        ))
    }

    /// Make appends fail as on a full disk (tests; see [`Fault`]).
    pub fn set_fault(&mut self, fault: Option<Fault>) {
        self.fault = fault;
    }

    /// Append one record and sync it to disk. A write that fails is undone (the file cut
    /// back to its last whole record) before the error is returned.
    pub fn append(&mut self, r: &Record) -> Result<(), JournalError> {
        if let Some(e) = &self.broken {
            return Err(JournalError::Broken(Box::new(e.clone())));
        }
        let line = encode(r)?;
        self.appends += 1;
        let written = match self.fault {
            Some(f) if f.hits(self.appends) => self
                .file
                .write_all(&line[..line.len() / 2])
                .and_then(|_| Err(std::io::Error::from_raw_os_error(libc::ENOSPC))),
            _ => self.file.write_all(&line),
        }
        .and_then(|_| self.file.sync_data());
        if let Err(e) = written {
            let e = JournalError::Write {
                path: self.path.clone(),
                source: Arc::new(e),
            };
            // Cut back to the last whole record, so the next append starts a line of its own.
            if let Err(cut) = self
                .file
                .set_len(self.bytes)
                .and_then(|_| self.file.sync_data())
            {
                self.broken = Some(JournalError::CutBack {
                    write: Box::new(e.clone()),
                    cut: Arc::new(cut),
                });
            }
            return Err(e);
        }
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
    pub fn compact(&mut self, book: &Book) -> Result<(), JournalError> {
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

/// Keep `bytes` (a damaged journal as read) beside `path` under a new name,
/// `journal.jsonl.damaged-<UTC time>` (`-2`, `-3`… added if taken), synced; its path.
fn keep_aside(path: &Path, bytes: &[u8]) -> Result<PathBuf, JournalError> {
    use std::os::unix::fs::OpenOptionsExt;
    let dir = path.parent().unwrap_or(Path::new("."));
    let stamp: String = crate::session::timestamp(std::time::SystemTime::now())
        .chars()
        .filter(|c| c.is_ascii_alphanumeric() || *c == '.')
        .collect();
    let name = path.file_name().unwrap_or_default().to_string_lossy();
    let fail = |e: std::io::Error, side: &Path| JournalError::KeepAside {
        path: path.to_path_buf(),
        side: side.to_path_buf(),
        source: Arc::new(e),
    };
    for k in 1..=1000 {
        let side = dir.join(match k {
            1 => format!("{name}.damaged-{stamp}"),
            _ => format!("{name}.damaged-{stamp}-{k}"),
        });
        let opened = OpenOptions::new()
            .write(true)
            .create_new(true)
            .mode(0o600)
            .custom_flags(libc::O_NOFOLLOW)
            .open(&side);
        let mut f = match opened {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(fail(e, &side)),
        };
        let written = f
            .write_all(bytes)
            .and_then(|_| f.sync_all())
            .and_then(|_| File::open(dir)?.sync_all());
        if let Err(e) = written {
            let _ = std::fs::remove_file(&side);
            return Err(fail(e, &side));
        }
        return Ok(side);
    }
    Err(JournalError::NamesTaken {
        path: path.to_path_buf(),
    })
}

/// A journal this long (bytes) is written anew as a snapshot while the daemon runs, so it
/// stays far below what [`Journal::open`] reads ([`crate::fsx::MAX_TEXT_BYTES`]).
pub const COMPACT_BYTES: u64 = 8 << 20;

/// Write `book` as the journal at `path`: one snapshot line in a temporary file, synced,
/// renamed into place, the folder synced; the new file opened for appending, and its size.
fn write_snapshot(path: &Path, book: &Book) -> Result<(File, u64), JournalError> {
    use std::os::unix::fs::OpenOptionsExt;
    let snapshot = encode(&book.snapshot()).map_err(|e| JournalError::Snapshot(Box::new(e)))?;
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
        return Err(JournalError::Write {
            path: path.to_path_buf(),
            source: Arc::new(e),
        });
    }
    let file = OpenOptions::new()
        .append(true)
        .open(path)
        .map_err(|e| JournalError::Open {
            path: path.to_path_buf(),
            source: Arc::new(e),
        })?;
    Ok((file, snapshot.len() as u64))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::daemon::protocol::{JobKind, JobSpec};

    fn job(id: u64) -> Job {
        Job::queued(id, JobSpec::new(JobKind::Run), None, "t".into())
    }

    fn lines(recs: &[Record]) -> String {
        recs.iter()
            .map(|r| String::from_utf8(encode(r).unwrap()).unwrap())
            .collect()
    }

    fn added(id: u64) -> Record {
        Record::Added {
            job: Box::new(job(id)),
        }
    }

    fn started(id: u64) -> Record {
        Record::Started {
            job: id,
            at: "t".into(),
            session: Some("/s".into()),
        }
    }

    fn ended(id: u64) -> Record {
        Record::Ended {
            job: id,
            state: JobState::Complete,
            at: "t".into(),
            error: None,
            summary: None,
            summary_text: None,
        }
    }

    #[test]
    fn replay_follows_the_queue_and_sets_aside_a_torn_last_line() {
        let recs = [
            Record::Opened {
                pid: 1,
                at: "t".into(),
            },
            added(1),
            added(2),
            added(3),
            Record::Moved { job: 3, to: 0 },
            Record::Removed { job: 2 },
            started(3),
        ];
        let mut text = lines(&recs);
        let r = replay(Path::new("j"), &text);
        assert_eq!(r.damaged_count, 0, "{:?}", r.notes);
        assert_eq!(r.book.queue, vec![1]);
        assert_eq!(r.book.running().map(|j| j.id), Some(3));
        assert!(!r.clean, "opened and never closed");
        assert_eq!(r.book.next_id, 4);
        text.push_str("{\"record\":\"ended\",\"jo");
        let torn = replay(Path::new("j"), &text);
        assert_eq!(torn.book, r.book);
        assert_eq!(torn.damaged_count, 1);
        assert!(
            torn.damaged[0].why.starts_with("torn"),
            "{:?}",
            torn.damaged
        );
        // A line of garbage in the middle: set aside, the rest replayed.
        let bad = text.replace("\"moved\"", "\"mooved\"");
        let b = replay(Path::new("j"), &bad);
        assert_eq!(b.damaged.iter().map(|d| d.line).collect::<Vec<_>>(), [5, 8]);
        assert_eq!(b.book.queue, vec![1], "job 3 started all the same");
        // A snapshot replays to the same book.
        let snap = lines(&[r.book.snapshot()]);
        assert_eq!(replay(Path::new("j"), &snap).book, r.book);
    }

    #[test]
    fn a_journal_without_checksums_is_read_and_a_checksummed_one_catches_a_flipped_byte() {
        let recs = [added(1), added(2), added(3), Record::Removed { job: 2 }];
        // Written before checksums: plain JSON lines.
        let old: String = recs
            .iter()
            .map(|r| serde_json::to_string(r).unwrap() + "\n")
            .collect();
        let o = replay(Path::new("j"), &old);
        assert_eq!((o.damaged_count, o.book.queue.clone()), (0, vec![1, 3]));
        // The same with checksums (the line docs/daemon-protocol.md shows).
        assert_eq!(
            encode(&Record::Removed { job: 5 }).unwrap(),
            b"{\"record\":\"removed\",\"job\":5,\"crc\":\"594d41f7\"}\n"
        );
        let new = lines(&recs);
        assert!(new.lines().all(|l| l.contains(",\"crc\":\"")), "{new}");
        assert_eq!(replay(Path::new("j"), &new).book, o.book);
        // "removed" of job 2 made job 3's: still a record the book accepts, caught by its
        // checksum; the rest replayed.
        let flipped = new.replacen("\"removed\",\"job\":2", "\"removed\",\"job\":3", 1);
        assert_ne!(flipped, new);
        let f = replay(Path::new("j"), &flipped);
        assert_eq!(f.damaged_count, 1);
        assert!(f.damaged[0].why.contains("checksum"), "{:?}", f.damaged);
        assert_eq!(f.book.queue, vec![1, 2, 3]);
        // A line without its checksum in a checksummed journal is damage too.
        let mixed =
            new.clone() + &serde_json::to_string(&Record::Removed { job: 1 }).unwrap() + "\n";
        let m = replay(Path::new("j"), &mixed);
        assert_eq!(m.damaged_count, 1);
        assert_eq!(m.book.queue, vec![1, 3]);
    }

    #[test]
    fn a_job_whose_ended_is_lost_stays_running_and_one_whose_started_is_damaged_is_not_queued() {
        // Ended lost (torn): job 1 stays running, for the start to close as interrupted.
        let text = lines(&[added(1), added(2), started(1)]);
        let torn = text.clone() + &String::from_utf8(encode(&ended(1)).unwrap()).unwrap()[..20];
        let r = replay(Path::new("j"), &torn);
        assert_eq!(r.book.running().map(|j| j.id), Some(1));
        assert_eq!(r.book.queue, vec![2]);
        // Started damaged in place (a flipped byte in its time) and no ended: taken as
        // started (it may have run), never left queued to run again.
        let flipped = text.replacen("\"at\":\"t\",\"session\"", "\"at\":\"u\",\"session\"", 1);
        let f = replay(Path::new("j"), &flipped);
        assert_eq!(f.damaged_count, 1, "{:?}", f.notes);
        assert_eq!(f.book.running().map(|j| j.id), Some(1));
        assert_eq!(f.book.queue, vec![2]);
        assert!(f.notes.iter().any(|n| n.contains("taken as started")));
        // An added line lost: its id is never given out again.
        let lost = lines(&[added(1), added(2)]).replacen("\"id\":2", "\"id\":9", 1);
        let l = replay(Path::new("j"), &lost);
        assert_eq!((l.damaged_count, l.book.next_id), (1, 10));
    }

    #[test]
    fn a_write_that_fails_half_way_leaves_the_journal_as_it_was() {
        let dir = tempfile::tempdir().unwrap();
        let (mut journal, replayed) = Journal::open(dir.path()).unwrap();
        let mut book = replayed.book;
        // The 3rd append writes half its line, then fails with ENOSPC (a full disk).
        journal.set_fault(Some(Fault { from: 3, to: 3 }));
        for id in 1..=5 {
            let r = added(id);
            match journal.append(&r) {
                Ok(()) => book.apply(&r).unwrap(),
                Err(e) => {
                    assert_eq!(id, 3);
                    assert!(e.to_string().contains("No space left on device"), "{e}");
                }
            }
        }
        let text = std::fs::read_to_string(dir.path().join("journal.jsonl")).unwrap();
        assert!(text.ends_with('\n'));
        let (_, again) = Journal::open(dir.path()).unwrap();
        assert_eq!(again.damaged_count, 0, "{:?}", again.notes);
        assert!(again.set_aside.is_none());
        assert_eq!(again.book.queue, vec![1, 2, 4, 5]);
        assert_eq!(again.book, book);
    }

    #[test]
    fn a_damaged_journal_is_kept_aside_under_a_new_name_each_start() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("journal.jsonl");
        let text = lines(&[added(1), added(2)]) + "garbage\n";
        let mut sides = Vec::new();
        for _ in 0..2 {
            std::fs::write(&path, &text).unwrap();
            let (_, r) = Journal::open(dir.path()).unwrap();
            assert_eq!(r.damaged_count, 1);
            assert_eq!(r.book.queue, vec![1, 2]);
            let side = r.set_aside.unwrap();
            assert_eq!(std::fs::read_to_string(&side).unwrap(), text);
            sides.push(side);
        }
        assert_ne!(sides[0], sides[1]);
        // Written anew: whole, with checksums, nothing to set aside.
        let (_, r) = Journal::open(dir.path()).unwrap();
        assert_eq!((r.damaged_count, r.book.queue), (0, vec![1, 2]));
    }

    #[test]
    fn the_fault_point_is_parsed_from_its_entry() {
        assert_eq!(
            Fault::parse("lamp-x:1,journal-enospc:29"),
            Some(Fault { from: 29, to: 29 })
        );
        assert_eq!(
            Fault::parse("journal-enospc:2-"),
            Some(Fault {
                from: 2,
                to: u64::MAX
            })
        );
        assert_eq!(
            Fault::parse("journal-enospc:2-4"),
            Some(Fault { from: 2, to: 4 })
        );
        assert_eq!(Fault::parse("journal-enospc:x"), None);
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
