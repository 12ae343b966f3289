//! The daemon's async shell: the socket, the connections, the scheduler, signals.
//!
//! tokio serves the socket and fans events out; jobs run on blocking threads
//! ([`Runner::execute`] in `spawn_blocking`). One lock ([`Core`]) holds the queue, the
//! history, the journal and the running job; every change is appended to the journal
//! (synced) under that lock before the daemon acts on it or tells a client. The hub (events)
//! has its own lock and never takes the core's.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime};

use serde_json::{json, Value};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::unix::OwnedWriteHalf;
use tokio::net::{UnixListener, UnixStream};
use tokio::sync::{mpsc, Notify};

use super::hub::{Hub, Line, Subscription};
use super::journal::{Book, Journal, JournalError, Record, Refused};
use super::paths;
use super::protocol::{self, Job, JobKind, JobState, Request, MAX_REQUEST, PROTOCOL_VERSION};
use super::runner::{close_interrupted_session, AnswerError, OperatorMode, Outcome, Runner};
use crate::capture::Stop;
use crate::session::timestamp;

/// Clients served at once; more are told so and closed.
pub const MAX_CONNECTIONS: usize = 64;
/// Jobs the queue holds at most.
pub const MAX_QUEUED: usize = 1000;
/// Ended jobs `jobs` lists (the latest; the journal keeps more).
pub const JOBS_LISTED: usize = 500;
/// A write to a client that takes longer than this drops the client.
const WRITE_TIMEOUT: Duration = Duration::from_secs(30);
/// How long a refused client is given to read why and close.
const REFUSE_LINGER: Duration = Duration::from_secs(2);

/// How to run the daemon (`glint daemon`'s flags).
#[derive(Debug, Clone)]
pub struct Options {
    pub rig: PathBuf,
    pub socket: Option<PathBuf>,
    pub state_dir: Option<PathBuf>,
    pub sessions_dir: Option<PathBuf>,
    pub group: Option<String>,
    pub operator: OperatorMode,
    pub operator_timeout: Duration,
    /// How often idle devices are checked (the lamp asked its state).
    pub health_interval: Duration,
}

struct RunningJob {
    id: u64,
    stop: Stop,
}

/// A record the book refuses, or the journal cannot take.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error(transparent)]
    Refused(#[from] Refused),
    #[error(transparent)]
    Journal(#[from] JournalError),
}

/// A job's paths that the daemon refuses ([`check_job_paths`]).
#[derive(Debug, thiserror::Error)]
pub enum PathError {
    #[error("{} exists and is not a folder; choose another --out", .0.display())]
    OutNotAFolder(PathBuf),
    #[error("{} already exists and is not empty; choose another --out (Glint never writes into existing data)", .0.display())]
    OutNotEmpty(PathBuf),
    #[error("{} has no manifest.json: not a session", .0.display())]
    NotASession(PathBuf),
    #[error("intrinsics: {}", crate::fsx::short_message(&.0.to_string()))]
    Intrinsics(crate::calib::run::RunError),
}

/// Why the daemon refuses a request (the `error` of its reply).
#[derive(Debug, thiserror::Error)]
pub enum Refusal {
    #[error(transparent)]
    Request(#[from] protocol::RequestError),
    #[error("this daemon speaks protocol {PROTOCOL_VERSION}, the client {client}; use a glint of the daemon's version ({})", crate::VERSION)]
    Version { client: u32 },
    #[error("say hello first: {{\"id\": 1, \"cmd\": \"hello\", \"version\": {PROTOCOL_VERSION}}}")]
    NoHello,
    #[error("job {job} is not running (job {running} is){hint}")]
    OtherRunning {
        job: u64,
        running: u64,
        hint: &'static str,
    },
    #[error("job {job} is not running{hint}")]
    NotRunning { job: u64, hint: &'static str },
    #[error("no job is running")]
    NoneRunning,
    #[error("the daemon is stopping")]
    Stopping,
    #[error("there is no job {0} (see `glint jobs`)")]
    NoSuchJobSeeJobs(u64),
    #[error("job {0}'s events cannot be followed")]
    Unfollowable(u64),
    #[error("{0}")]
    BadJob(String),
    #[error(transparent)]
    Paths(#[from] PathError),
    #[error("checking the job's paths: {0}")]
    PathCheck(tokio::task::JoinError),
    #[error("the daemon is stopping; no new jobs")]
    StoppingNoNewJobs,
    #[error("the queue holds {MAX_QUEUED} jobs already; wait for some to run, or remove some")]
    QueueFull,
    #[error("there is no job {0}")]
    NoSuchJob(u64),
    #[error("job {job} is {state}, not queued")]
    NotQueued { job: u64, state: &'static str },
    #[error(transparent)]
    Record(#[from] RecordError),
    #[error(transparent)]
    Operator(#[from] AnswerError),
}

/// The state behind the core lock.
struct Core {
    book: Book,
    journal: Journal,
    running: Option<RunningJob>,
    queue_running: bool,
    /// Why the daemon stopped the queue itself (the journal could not be written), until
    /// `queue-start` or `queue-stop`.
    stopped_by: Option<String>,
    shutting_down: bool,
}

impl Core {
    /// Append a record to the journal, then apply it (and write the journal anew as one
    /// snapshot once it has grown long).
    fn record(&mut self, r: Record) -> Result<(), RecordError> {
        // Only what the book accepts goes on disk: a refused record never reaches the journal.
        self.book.check(&r)?;
        self.journal.append(&r)?;
        self.book.apply(&r)?;
        if self.journal.wants_compaction() {
            self.book.prune();
            if let Err(e) = self.journal.compact(&self.book) {
                tracing::error!("compacting the journal: {e}; the queue is stopped");
                self.queue_running = false;
                self.stopped_by = Some(format!("compacting the journal: {e}"));
            }
        }
        Ok(())
    }
}

struct Info {
    socket: PathBuf,
    state_dir: PathBuf,
    started: String,
    /// What the start found in the journal (`status`'s `journal`).
    journal: Value,
}

struct Daemon {
    core: Mutex<Core>,
    hub: Arc<Hub>,
    runner: Arc<Runner>,
    info: Info,
    group: Option<u32>,
    /// Wakes the scheduler.
    wake: Notify,
    /// The daemon has stopped its last job and may exit.
    finished: Notify,
    connections: AtomicUsize,
    health_interval: Duration,
}

impl Daemon {
    fn core(&self) -> std::sync::MutexGuard<'_, Core> {
        self.core.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn status(&self) -> Value {
        let c = self.core();
        let running = c
            .running
            .as_ref()
            .and_then(|r| c.book.jobs.get(&r.id))
            .cloned();
        json!({
            "daemon": {
                "version": crate::VERSION,
                "protocol": PROTOCOL_VERSION,
                "pid": std::process::id(),
                "socket": self.info.socket,
                "state_dir": self.info.state_dir,
                "sessions": self.runner.sessions_dir,
                "rig": self.runner.rig.path,
                "rig_name": self.runner.rig.rig.rig.name,
                "started": self.info.started,
                "followers": self.hub.followers(),
                "seq": self.hub.seq(),
            },
            "queue": {
                "running": c.queue_running,
                "stopped_by": c.stopped_by,
                "queued": c.book.queue.len(),
                "shutting_down": c.shutting_down,
            },
            "journal": self.info.journal,
            "devices": self.runner.health(),
            "running": running,
            "operator": self.runner.desk.waiting(),
        })
    }

    /// The queue and the latest [`JOBS_LISTED`] ended jobs, without their summaries (a
    /// job's summary comes with its `job-ended` event: `follow` it).
    fn jobs(&self) -> Value {
        let c = self.core();
        let brief = |j: &Job| {
            let mut j = j.clone();
            j.summary = None;
            j.summary_text = None;
            j
        };
        let queue: Vec<Job> = c
            .book
            .queue
            .iter()
            .filter_map(|id| c.book.jobs.get(id))
            .map(brief)
            .collect();
        let ended: Vec<&Job> = c.book.jobs.values().filter(|j| j.state.ended()).collect();
        let omitted = ended.len().saturating_sub(JOBS_LISTED);
        let history: Vec<Job> = ended[omitted..].iter().map(|j| brief(j)).collect();
        json!({
            "queue_running": c.queue_running,
            "running": c.book.running().map(brief),
            "queue": queue,
            "history": history,
            "history_omitted": omitted,
        })
    }

    /// Ask the running job to stop for `reason` (lamp off, session failed with it).
    fn abort_running(c: &Core, desk: &super::runner::Desk, reason: &str) -> Option<u64> {
        let r = c.running.as_ref()?;
        r.stop.stop_for(reason);
        desk.wake();
        Some(r.id)
    }

    /// Stop: abort the running job for `reason`, start nothing more, then exit.
    fn begin_shutdown(&self, reason: &str) {
        let mut c = self.core();
        if c.shutting_down {
            return;
        }
        c.shutting_down = true;
        let aborted = Self::abort_running(&c, &self.runner.desk, reason);
        drop(c);
        tracing::warn!(
            "{reason}: {}",
            match aborted {
                Some(id) => format!("aborting job {id} (lamp off), then exiting"),
                None => "exiting".into(),
            }
        );
        self.hub.publish(
            None,
            json!({"event": "daemon-stopping", "reason": reason, "aborting": aborted}),
        );
        self.wake.notify_one();
    }
}

/// Why the daemon cannot start (or stopped on an error).
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error(transparent)]
    Rig(#[from] crate::rig::RigError),
    #[error("{}: {why}", .rig.display())]
    NotDrivable { rig: PathBuf, why: String },
    #[error("resolving {}", .path.display())]
    Resolve {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("the socket path {} is longer than a Unix socket address holds (about 100 bytes); give a shorter --socket", .socket.display())]
    SocketTooLong { socket: PathBuf },
    #[error("--socket {}: no folder", .socket.display())]
    NoSocketFolder { socket: PathBuf },
    #[error("creating the state folder {}", .path.display())]
    StateDir {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(transparent)]
    Paths(#[from] paths::PathsError),
    #[error(transparent)]
    Journal(#[from] JournalError),
    #[error(transparent)]
    Record(#[from] RecordError),
    #[error("listening on {}", .socket.display())]
    Listen {
        socket: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("giving {} to the group", .socket.display())]
    SocketGroup {
        socket: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("setting the mode of {}", .socket.display())]
    SocketMode {
        socket: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("starting the async runtime")]
    Runtime(#[source] std::io::Error),
    #[error(transparent)]
    Io(#[from] std::io::Error),
}

/// What the daemon's start has made ready before it reads its journal: the rig, the
/// folders, and the locks it holds while it runs.
struct Start {
    rig: crate::rig::LoadedRig,
    /// Whether the lamp read back off at the start.
    lamp_off_confirmed: bool,
    socket: PathBuf,
    state_dir: PathBuf,
    sessions_dir: PathBuf,
    gid: Option<u32>,
    /// The socket's and the state folder's locks, held until the daemon exits.
    _locks: (std::fs::File, std::fs::File),
}

/// Run the daemon in the foreground until SIGTERM, SIGINT, SIGHUP or `shutdown`.
pub fn serve(opts: Options) -> Result<(), ServeError> {
    let start = prepare(&opts)?;
    let (core, journal_found) = open_core(&start)?;
    let hub = Arc::new(Hub::default());
    for id in &core.book.queue {
        hub.open_log(*id, Vec::new());
    }
    let Start {
        rig,
        socket,
        state_dir,
        sessions_dir,
        gid,
        _locks,
        ..
    } = start;
    let runner = Arc::new(Runner::new(
        rig,
        sessions_dir.clone(),
        opts.operator,
        opts.operator_timeout,
        Arc::clone(&hub),
    ));
    // The devices, opened once, the lamp switched off (a crash may have left it on). A
    // device that fails here is reported in `status` and retried by the next job.
    if let Err(e) = runner.open_devices() {
        tracing::error!("{e}; the daemon starts anyway and retries at the next job");
    }

    paths::remove_stale_socket(&socket)?;
    let listener = bind(&socket, gid)?;
    let daemon = Arc::new(Daemon {
        core: Mutex::new(core),
        hub,
        runner,
        info: Info {
            socket: socket.clone(),
            state_dir: state_dir.clone(),
            started: timestamp(SystemTime::now()),
            journal: journal_found,
        },
        group: gid,
        wake: Notify::new(),
        finished: Notify::new(),
        connections: AtomicUsize::new(0),
        health_interval: opts.health_interval,
    });
    print_ready(&daemon, &sessions_dir);

    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("glint-daemon")
        .enable_all()
        .build()
        .map_err(ServeError::Runtime)?;
    let result = rt.block_on(main_loop(Arc::clone(&daemon), listener));
    // No lamp burns after the daemon, whatever its last job did.
    if let Err(e) = daemon.runner.lamp_off_at_exit() {
        tracing::error!("at exit: {e}");
    }
    let _ = std::fs::remove_file(&socket);
    rt.shutdown_timeout(Duration::from_secs(1));
    result
}

/// The start up to the journal: the rig (refused where Glint cannot drive it), the lamp
/// switched off, the socket's and state's folders made, and their locks taken.
fn prepare(opts: &Options) -> Result<Start, ServeError> {
    let mut rig = crate::rig::load(&opts.rig)?;
    if let Some(why) = crate::devices::not_drivable(&rig.rig) {
        return Err(ServeError::NotDrivable {
            rig: opts.rig.clone(),
            why,
        });
    }
    rig.path = std::fs::canonicalize(&rig.path).map_err(|source| ServeError::Resolve {
        path: rig.path.clone(),
        source,
    })?;
    // The lamp off first, before anything else may stop this start (a damaged journal, an
    // unwritable state folder): a lamp a killed daemon left on goes dark even if this one
    // then refuses to start. Only the lamp is opened; a port another program holds (a
    // running daemon or capture) is refused by the port's lock and left alone.
    let lamp_off_confirmed = match crate::devices::lamp_off(&rig) {
        Ok(off) => {
            tracing::info!("lamp off at the start: {off:?}");
            true
        }
        Err(e) => {
            tracing::warn!("switching the lamp off at the start: {e}; it may still be on");
            false
        }
    };
    let absolute = |p: PathBuf| {
        std::path::absolute(&p).map_err(|source| ServeError::Resolve { path: p, source })
    };
    let socket = absolute(opts.socket.clone().unwrap_or_else(paths::default_socket))?;
    let state_dir = absolute(
        opts.state_dir
            .clone()
            .unwrap_or_else(paths::default_state_dir),
    )?;
    let sessions_dir = absolute(
        opts.sessions_dir
            .clone()
            .unwrap_or_else(|| state_dir.join("sessions")),
    )?;
    if socket.as_os_str().len() > 100 {
        return Err(ServeError::SocketTooLong { socket });
    }
    let gid = opts.group.as_deref().map(paths::group_id).transpose()?;
    let socket_dir = socket.parent().ok_or_else(|| ServeError::NoSocketFolder {
        socket: socket.clone(),
    })?;
    paths::socket_dir(socket_dir, gid)?;
    {
        use std::os::unix::fs::DirBuilderExt;
        std::fs::DirBuilder::new()
            .recursive(true)
            .mode(0o700)
            .create(&state_dir)
            .map_err(|source| ServeError::StateDir {
                path: state_dir.clone(),
                source,
            })?;
    }
    let mut lock_name = socket.clone().into_os_string();
    lock_name.push(".lock");
    let socket_lock = paths::lock(
        Path::new(&lock_name),
        &format!("the socket {}", socket.display()),
    )?;
    let state_lock = paths::lock(
        &state_dir.join("daemon.lock"),
        &format!("the state folder {}", state_dir.display()),
    )?;
    Ok(Start {
        rig,
        lamp_off_confirmed,
        socket,
        state_dir,
        sessions_dir,
        gid,
        _locks: (socket_lock, state_lock),
    })
}

/// The queue and the history from the journal: replayed (damage set aside, the queue then
/// stopped), the job a dead daemon was running closed as interrupted with its session,
/// stale sessions closed, and this daemon's start journaled. Also what the start found in
/// the journal, for `status`.
fn open_core(start: &Start) -> Result<(Core, Value), ServeError> {
    let (state_dir, sessions_dir) = (&start.state_dir, &start.sessions_dir);
    let lamp_off_confirmed = start.lamp_off_confirmed;
    let (journal, replayed) = match Journal::open(state_dir) {
        Ok(opened) => opened,
        Err(e) => {
            // No job can be named from an unreadable journal; its sessions still can be.
            close_stale_sessions(sessions_dir, lamp_off_confirmed);
            return Err(e.into());
        }
    };
    for n in &replayed.notes {
        tracing::warn!("{n}");
    }
    let journal_found = json!({
        "path": state_dir.join("journal.jsonl"),
        "damaged_lines": replayed.damaged_count,
        "damaged": replayed.damaged,
        "set_aside": replayed.set_aside,
    });
    let mut core = Core {
        book: replayed.book,
        journal,
        running: None,
        queue_running: true,
        stopped_by: None,
        shutting_down: false,
    };
    if let Some(side) = &replayed.set_aside {
        // Replayed past damage: nothing starts until someone has looked.
        core.queue_running = false;
        tracing::warn!(
            "the journal had {} damaged line(s), set aside (kept in {}); the rest was replayed and the queue waits for `glint queue start`",
            replayed.damaged_count,
            side.display()
        );
    }
    let interrupted = close_interrupted(&mut core, lamp_off_confirmed)?;
    // Any other session a killed capture left `capturing` in the sessions folder.
    close_stale_sessions(sessions_dir, lamp_off_confirmed);
    // After a crash, or with jobs waiting from before, nothing starts until told.
    if !core.book.queue.is_empty() {
        core.queue_running = false;
        tracing::warn!(
            "{} job(s) queued from before wait; `glint queue start` runs them",
            core.book.queue.len()
        );
    }
    if !replayed.clean && interrupted == 0 {
        tracing::warn!(
            "the last daemon on {} did not stop cleanly",
            state_dir.display()
        );
    }
    core.record(Record::Opened {
        pid: std::process::id(),
        at: timestamp(SystemTime::now()),
    })?;
    Ok((core, journal_found))
}

/// Mark interrupted the job the last daemon was running when it died, its session closed;
/// how many there were.
fn close_interrupted(core: &mut Core, lamp_off_confirmed: bool) -> Result<usize, ServeError> {
    let interrupted: Vec<Job> = core
        .book
        .jobs
        .values()
        .filter(|j| j.state == JobState::Running)
        .cloned()
        .collect();
    for j in &interrupted {
        let why = "daemon stopped (killed or crashed while this job ran; found at the next start)";
        let closed = match (&j.session, j.spec.kind) {
            (Some(dir), JobKind::Run | JobKind::Capture) if dir.join("manifest.json").exists() => {
                close_interrupted_session(dir, why, lamp_off_confirmed)
                    .unwrap_or_else(|e| format!("its session could not be closed: {e}"))
            }
            (Some(dir), _) => format!("session {} left as it is", dir.display()),
            (None, _) => "no session".into(),
        };
        tracing::warn!(
            "job {} was running when the last daemon died: marked interrupted; {closed}",
            j.id
        );
        core.record(Record::Ended {
            job: j.id,
            state: JobState::Interrupted,
            at: timestamp(SystemTime::now()),
            error: Some(format!("{why}; {closed}")),
            summary: None,
            summary_text: None,
        })?;
    }
    Ok(interrupted.len())
}

/// What the daemon says on its standard output once it is ready.
fn print_ready(daemon: &Daemon, sessions_dir: &Path) {
    let c = daemon.core();
    let (socket, state_dir) = (&daemon.info.socket, &daemon.info.state_dir);
    println!(
        "glint daemon {} (pid {}): rig {} ({})",
        crate::VERSION,
        std::process::id(),
        daemon.runner.rig.rig.rig.name,
        daemon.runner.rig.path.display()
    );
    println!("  socket   {}", socket.display());
    println!("  state    {}", state_dir.display());
    println!("  sessions {}", sessions_dir.display());
    let health = daemon.runner.health();
    println!(
        "  devices  {} ({})",
        health.state,
        health.last_error.unwrap_or_else(|| "lamp off".into())
    );
    println!(
        "  queue    {} ({} queued, {} in the history)",
        if c.queue_running {
            "running"
        } else {
            "stopped: `glint queue start` runs it"
        },
        c.book.queue.len(),
        c.book.jobs.len().saturating_sub(c.book.queue.len())
    );
    println!(
        "ready: `glint trigger run --socket {}` queues a run",
        socket.display()
    );
    drop(c);
    use std::io::Write;
    let _ = std::io::stdout().flush();
}

/// Close as `failed` every session of the sessions folder still `capturing` (its capture
/// was killed with the daemon), recording whether the lamp was read back off at this start.
fn close_stale_sessions(sessions_dir: &Path, lamp_off_confirmed: bool) {
    let why =
        "daemon stopped (killed or crashed while capturing this session; found at the next start)";
    for (_, line) in super::runner::close_capturing_sessions(sessions_dir, why, lamp_off_confirmed)
    {
        tracing::warn!("{line}");
    }
}

/// Bind the socket owner-only (group-only with `--group`): created under a umask that
/// lets nobody else in, then given its mode explicitly.
fn bind(socket: &Path, gid: Option<u32>) -> Result<std::os::unix::net::UnixListener, ServeError> {
    use std::os::unix::fs::PermissionsExt;
    // SAFETY: umask only swaps the process's file-creation mask; no thread creates files
    // while the daemon starts.
    let old = unsafe { libc::umask(0o177) };
    let bound = std::os::unix::net::UnixListener::bind(socket);
    // SAFETY: as above, restoring the previous mask.
    unsafe { libc::umask(old) };
    let listener = bound.map_err(|source| ServeError::Listen {
        socket: socket.into(),
        source,
    })?;
    if let Some(g) = gid {
        std::os::unix::fs::chown(socket, None, Some(g)).map_err(|source| {
            ServeError::SocketGroup {
                socket: socket.into(),
                source,
            }
        })?;
    }
    let mode = if gid.is_some() { 0o660 } else { 0o600 };
    std::fs::set_permissions(socket, std::fs::Permissions::from_mode(mode)).map_err(|source| {
        ServeError::SocketMode {
            socket: socket.into(),
            source,
        }
    })?;
    listener.set_nonblocking(true)?;
    Ok(listener)
}

async fn main_loop(
    d: Arc<Daemon>,
    listener: std::os::unix::net::UnixListener,
) -> Result<(), ServeError> {
    let listener = UnixListener::from_std(listener)?;
    let _ = sd_notify::notify(&[sd_notify::NotifyState::Ready]);
    tokio::spawn(scheduler(Arc::clone(&d)));
    tokio::spawn(health(Arc::clone(&d), d.health_interval));
    tokio::spawn(signals(Arc::clone(&d)));
    loop {
        tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => {
                    tokio::spawn(connection(Arc::clone(&d), stream));
                }
                Err(e) => {
                    tracing::warn!("accepting a client: {e}");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            },
            _ = d.finished.notified() => break,
        }
    }
    let _ = sd_notify::notify(&[sd_notify::NotifyState::Stopping]);
    // Let the writers send the last events (the aborted job's end) before the runtime stops.
    tokio::time::sleep(Duration::from_millis(200)).await;
    Ok(())
}

/// Check the devices every `every` while no job runs, so that `status` tells their health
/// between jobs too.
async fn health(d: Arc<Daemon>, every: Duration) {
    loop {
        tokio::time::sleep(every).await;
        let idle = {
            let c = d.core();
            c.running.is_none() && !c.shutting_down
        };
        if idle {
            let runner = Arc::clone(&d.runner);
            let _ = tokio::task::spawn_blocking(move || runner.probe()).await;
        }
    }
}

async fn signals(d: Arc<Daemon>) {
    use tokio::signal::unix::{signal, SignalKind};
    let (Ok(mut term), Ok(mut int), Ok(mut hup)) = (
        signal(SignalKind::terminate()),
        signal(SignalKind::interrupt()),
        signal(SignalKind::hangup()),
    ) else {
        tracing::error!("cannot handle signals; stop the daemon with `glint daemon stop`");
        return;
    };
    loop {
        let name = tokio::select! {
            _ = term.recv() => "SIGTERM",
            _ = int.recv() => "SIGINT",
            _ = hup.recv() => "SIGHUP",
        };
        d.begin_shutdown(&format!("daemon stopped by {name}"));
    }
}

/// Start queued jobs one at a time, while the queue runs; end the daemon once it is
/// stopping and no job runs.
async fn scheduler(d: Arc<Daemon>) {
    loop {
        let next = {
            let mut c = d.core();
            if c.running.is_some() {
                None
            } else if c.shutting_down {
                if let Err(e) = c.journal.append(&Record::Closed {
                    at: timestamp(SystemTime::now()),
                }) {
                    tracing::error!("{e}");
                }
                d.finished.notify_one();
                return;
            } else if let (true, Some(&id)) = (c.queue_running, c.book.queue.first()) {
                start_job(&d, &mut c, id)
            } else {
                None
            }
        };
        if let Some(started) = next {
            launch(&d, started);
        }
        d.wake.notified().await;
    }
}

/// Run a job [`start_job`] marked running, on a blocking thread.
fn launch(d: &Arc<Daemon>, (job, session, stop): Started) {
    d.hub.publish(
        Some(job.id),
        json!({"event": "job-started", "kind": job.spec.kind, "session": session}),
    );
    let runner = Arc::clone(&d.runner);
    let id = job.id;
    let handle =
        tokio::task::spawn_blocking(move || runner.execute(&job, session.as_deref(), stop));
    let d2 = Arc::clone(d);
    tokio::spawn(async move {
        let outcome = handle.await.unwrap_or_else(|e| Outcome {
            state: JobState::Failed,
            error: Some(format!("internal error: the job's thread failed ({e})")),
            summary: None,
            summary_text: None,
        });
        finish_job(&d2, id, outcome);
    });
}

type Started = (Job, Option<PathBuf>, Stop);

/// Mark job `id` running (journaled first); `None` when the journal cannot be written
/// (the queue is then stopped: nothing runs that the journal does not know of).
fn start_job(d: &Daemon, c: &mut Core, id: u64) -> Option<Started> {
    let job = c.book.jobs.get(&id)?.clone();
    let session = d.runner.session_for(&job);
    if let Err(e) = c.record(Record::Started {
        job: id,
        at: timestamp(SystemTime::now()),
        session: session.clone(),
    }) {
        tracing::error!("cannot start job {id}: {e}; the queue is stopped");
        c.queue_running = false;
        c.stopped_by = Some(format!("cannot start job {id}: {e}"));
        return None;
    }
    let stop = Stop::default();
    c.running = Some(RunningJob {
        id,
        stop: stop.clone(),
    });
    let job = c.book.jobs.get(&id)?.clone();
    Some((job, session, stop))
}

fn finish_job(d: &Daemon, id: u64, o: Outcome) {
    let session = {
        let mut c = d.core();
        if let Err(e) = c.record(Record::Ended {
            job: id,
            state: o.state,
            at: timestamp(SystemTime::now()),
            error: o.error.clone(),
            summary: o.summary.clone(),
            summary_text: o.summary_text.clone(),
        }) {
            // The journal cannot say it: the book still must (the job is not running), and
            // nothing more starts that the journal would not know of.
            tracing::error!("job {id}: {e}; the queue is stopped");
            if let Some(j) = c.book.jobs.get_mut(&id) {
                j.state = o.state;
                j.error = o.error.clone();
            }
            c.queue_running = false;
            c.stopped_by = Some(format!("job {id}'s end could not be journaled: {e}"));
        }
        c.running = None;
        c.book.jobs.get(&id).and_then(|j| j.session.clone())
    };
    match &o.error {
        Some(e) => tracing::warn!("job {id} {}: {e}", o.state.name()),
        None => tracing::info!("job {id} complete"),
    }
    d.hub.publish(
        Some(id),
        json!({
            "event": "job-ended", "state": o.state, "session": session, "error": o.error,
            "summary": o.summary, "summary_text": o.summary_text,
        }),
    );
    d.wake.notify_one();
}

/// What the reader hands the writer of a connection.
enum Out {
    Line(String),
    /// Start following (the reply is written first, then the backlog, then live events).
    Follow {
        reply: String,
        sub: Subscription,
        job: Option<u64>,
        /// Send heartbeats while following (the client asked).
        heartbeat: bool,
    },
    Unfollow(String),
}

async fn connection(d: Arc<Daemon>, stream: UnixStream) {
    let cred = stream.peer_cred();
    let (uid, gid, pid) = match &cred {
        Ok(c) => (c.uid(), c.gid(), c.pid()),
        Err(e) => {
            tracing::warn!("refused a client whose credentials cannot be read: {e}");
            return;
        }
    };
    let (rd, wr) = stream.into_split();
    if !paths::peer_allowed(uid, gid, pid, d.group) {
        tracing::warn!(
            "refused a client of uid {uid} (gid {gid}, pid {}): only the daemon's user{} may use it",
            pid.map_or("?".into(), |p| p.to_string()),
            if d.group.is_some() { " and group" } else { "" }
        );
        let msg = protocol::error(
            &Value::Null,
            &format!("permission denied: uid {uid} may not use this daemon"),
        );
        refuse(rd, wr, &msg).await;
        return;
    }
    if d.connections.fetch_add(1, Ordering::SeqCst) >= MAX_CONNECTIONS {
        d.connections.fetch_sub(1, Ordering::SeqCst);
        let msg = protocol::error(
            &Value::Null,
            &format!(
                "too many clients: the daemon serves {MAX_CONNECTIONS} at once; try again later"
            ),
        );
        refuse(rd, wr, &msg).await;
        return;
    }
    let by = format!(
        "uid {uid}, pid {}",
        pid.map_or("?".into(), |p| p.to_string())
    );
    // Small: a reply is short, but a follow of an old job carries its replayed events.
    let (tx, rx) = mpsc::channel::<Out>(4);
    let writer = tokio::spawn(writer(Arc::clone(&d), wr, rx));
    let mut reader = BufReader::new(rd);
    let mut hello = false;
    loop {
        let line = match read_line(&mut reader, MAX_REQUEST).await {
            Ok(Some(l)) => l,
            Ok(None) | Err(_) => break,
        };
        let out = match line {
            Err(len) => Out::Line(protocol::error(
                &Value::Null,
                &format!("a request line of {len}+ bytes is longer than {MAX_REQUEST}; ignored"),
            )),
            Ok(bytes) => match std::str::from_utf8(&bytes) {
                Err(_) => Out::Line(protocol::error(&Value::Null, "a request line is not UTF-8")),
                Ok(text) if text.trim().is_empty() => continue,
                Ok(text) => {
                    let incoming = protocol::parse_request(text);
                    handle(&d, &mut hello, &by, incoming).await
                }
            },
        };
        if tx.send(out).await.is_err() {
            break;
        }
    }
    drop(tx);
    let _ = writer.await;
    d.connections.fetch_sub(1, Ordering::SeqCst);
}

/// Tell a refused client why in one line, then close: the write side first, and the
/// client's own lines (its `hello`) read and dropped until it closes too, at most
/// [`REFUSE_LINGER`]; closing with them unread would reset the connection, and the client
/// would see a broken pipe instead of the reason.
async fn refuse(rd: tokio::net::unix::OwnedReadHalf, mut wr: OwnedWriteHalf, msg: &str) {
    use tokio::io::AsyncReadExt;
    let write = async {
        wr.write_all(msg.as_bytes()).await?;
        wr.write_all(b"\n").await?;
        wr.shutdown().await
    };
    if tokio::time::timeout(REFUSE_LINGER, write).await.is_err() {
        return;
    }
    let mut rd = rd.take(MAX_REQUEST as u64);
    let _ = tokio::time::timeout(
        REFUSE_LINGER,
        tokio::io::copy(&mut rd, &mut tokio::io::sink()),
    )
    .await;
}

/// Read one line of at most `max` bytes. `Ok(None)`: the end of the stream; `Err(n)` in
/// the line: a line longer than `max` (its first `n` bytes counted), skipped to its end.
async fn read_line(
    r: &mut BufReader<tokio::net::unix::OwnedReadHalf>,
    max: usize,
) -> std::io::Result<Option<Result<Vec<u8>, usize>>> {
    let mut buf = Vec::new();
    let mut skipped: Option<usize> = None;
    loop {
        let avail = r.fill_buf().await?;
        if avail.is_empty() {
            return Ok(match skipped {
                Some(n) => Some(Err(n)),
                None if buf.is_empty() => None,
                None => Some(Ok(buf)),
            });
        }
        let (chunk, end) = match avail.iter().position(|b| *b == b'\n') {
            Some(i) => (&avail[..i], Some(i + 1)),
            None => (avail, None),
        };
        match skipped.as_mut() {
            Some(n) => *n += chunk.len(),
            None if buf.len() + chunk.len() > max => skipped = Some(buf.len() + chunk.len()),
            None => buf.extend_from_slice(chunk),
        }
        if skipped.is_some() {
            buf = Vec::new();
        }
        let used = end.unwrap_or(avail.len());
        r.consume(used);
        if end.is_some() {
            return Ok(Some(match skipped {
                Some(n) => Err(n),
                None => Ok(buf),
            }));
        }
    }
}

async fn write_line(w: &mut OwnedWriteHalf, line: &str) -> std::io::Result<()> {
    let write = async {
        w.write_all(line.as_bytes()).await?;
        w.write_all(b"\n").await
    };
    match tokio::time::timeout(WRITE_TIMEOUT, write).await {
        Ok(r) => r,
        Err(_) => Err(std::io::Error::new(
            std::io::ErrorKind::TimedOut,
            "the client reads nothing",
        )),
    }
}

/// The last event of a job: it ended, or was taken off the queue.
fn is_job_end(line: &str) -> bool {
    line.contains("\"event\":\"job-ended\"") || line.contains("\"event\":\"job-removed\"")
}

/// Write replies and followed events to one client; a lagging follower gets a `resync`
/// once its queue has drained.
async fn writer(d: Arc<Daemon>, mut wr: OwnedWriteHalf, mut rx: mpsc::Receiver<Out>) {
    let mut follow: Option<(Subscription, Option<u64>)> = None;
    let mut beating = false;
    // A follower hears the daemon at least this often (see `protocol::HEARTBEAT`).
    let mut beat = tokio::time::interval_at(
        tokio::time::Instant::now() + protocol::HEARTBEAT,
        protocol::HEARTBEAT,
    );
    beat.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let result: std::io::Result<()> = async {
        loop {
            let following = follow.is_some() && beating;
            let next_event = async {
                match follow.as_mut() {
                    Some((s, _)) => s.rx.recv().await,
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                biased;
                m = rx.recv() => match m {
                    None => break,
                    Some(Out::Line(l)) => write_line(&mut wr, &l).await?,
                    Some(Out::Unfollow(reply)) => {
                        if let Some((s, _)) = follow.take() {
                            d.hub.unfollow(s.id);
                        }
                        write_line(&mut wr, &reply).await?;
                    }
                    Some(Out::Follow { reply, mut sub, job, heartbeat }) => {
                        beating = heartbeat;
                        if let Some((s, _)) = follow.take() {
                            d.hub.unfollow(s.id);
                        }
                        write_line(&mut wr, &reply).await?;
                        let backlog = std::mem::take(&mut sub.backlog);
                        let mut ended = false;
                        for l in &backlog {
                            write_line(&mut wr, l).await?;
                            ended |= job.is_some() && is_job_end(l);
                        }
                        if ended {
                            d.hub.unfollow(sub.id);
                        } else {
                            follow = Some((sub, job));
                        }
                    }
                },
                e = next_event => match e {
                    Some(l) => {
                        if is_job_end(&l) {
                            // A follower that missed events hears so before the job's end.
                            if let Some((s, job)) = follow.as_ref() {
                                let missed = s.missed.swap(0, Ordering::SeqCst);
                                if missed > 0 {
                                    write_line(&mut wr, &resync(&d, missed, *job)).await?;
                                }
                            }
                        }
                        write_line(&mut wr, &l).await?;
                        if follow.as_ref().is_some_and(|(_, j)| j.is_some()) && is_job_end(&l) {
                            if let Some((s, _)) = follow.take() {
                                d.hub.unfollow(s.id);
                            }
                        }
                    }
                    None => {
                        // A job follow whose events stop without the job's end: say where
                        // things stand, which ends it.
                        if let Some((s, Some(j))) = follow.take() {
                            d.hub.unfollow(s.id);
                            write_line(&mut wr, &resync(&d, s.missed.swap(0, Ordering::SeqCst), Some(j))).await?;
                        }
                    }
                },
                _ = beat.tick(), if following => {
                    write_line(&mut wr, &heartbeat(&d)).await?;
                }
            }
            // A follower that fell behind: once drained, say what it missed and where
            // things stand.
            if let Some((s, job)) = follow.as_ref() {
                if s.rx.is_empty() && s.missed.load(Ordering::SeqCst) > 0 {
                    let missed = s.missed.swap(0, Ordering::SeqCst);
                    let line = resync(&d, missed, *job);
                    write_line(&mut wr, &line).await?;
                    if job.is_some() && job_view_ended(&line) {
                        if let Some((s, _)) = follow.take() {
                            d.hub.unfollow(s.id);
                        }
                    }
                }
            }
        }
        Ok(())
    }
    .await;
    if let Some((s, _)) = follow.take() {
        d.hub.unfollow(s.id);
    }
    if let Err(e) = result {
        tracing::debug!("a client went away: {e}");
    }
}

/// The `heartbeat` a follower gets every [`protocol::HEARTBEAT`]: no sequence number of its
/// own (`seq` is the last one given out), only proof that the daemon is there.
fn heartbeat(d: &Daemon) -> String {
    json!({"event": "heartbeat", "seq": d.hub.seq()}).to_string()
}

/// The `resync` a follower gets after missing `missed` events: where things stand now.
fn resync(d: &Daemon, missed: u64, job: Option<u64>) -> String {
    let job_view = job.and_then(|j| d.core().book.jobs.get(&j).cloned());
    json!({
        "event": "resync", "seq": d.hub.seq(), "missed": missed,
        "status": d.status(), "job": job_view,
    })
    .to_string()
}

/// A resync line whose followed job has ended, or no longer exists (removed): its events
/// end there.
fn job_view_ended(line: &str) -> bool {
    serde_json::from_str::<Value>(line)
        .ok()
        .and_then(|v| {
            let job = v.get("job")?;
            if job.is_null() {
                return Some(true);
            }
            let state: JobState = serde_json::from_value(job.get("state")?.clone()).ok()?;
            Some(state.ended())
        })
        .unwrap_or(false)
}

async fn handle(d: &Arc<Daemon>, hello: &mut bool, by: &str, incoming: protocol::Incoming) -> Out {
    let id = incoming.id;
    let reply = |r: Result<Value, Refusal>| {
        Out::Line(match r {
            Ok(v) => protocol::ok(&id, v),
            Err(e) => protocol::error(&id, &e.to_string()),
        })
    };
    let request = match incoming.request {
        Ok(r) => r,
        Err(e) => return reply(Err(e.into())),
    };
    if let Request::Hello { version, .. } = &request {
        if *version != PROTOCOL_VERSION {
            return reply(Err(Refusal::Version { client: *version }));
        }
        *hello = true;
        return reply(Ok(json!({
            "protocol": PROTOCOL_VERSION,
            "daemon": crate::VERSION,
            "pid": std::process::id(),
            "rig": d.runner.rig.rig.rig.name,
            "heartbeat_s": protocol::HEARTBEAT.as_secs_f64(),
        })));
    }
    if !*hello {
        return reply(Err(Refusal::NoHello));
    }
    match request {
        Request::Hello { .. } => unreachable!("answered above"),
        Request::Status => reply(Ok(d.status())),
        Request::Jobs => reply(Ok(d.jobs())),
        Request::Add { job } => reply(add(d, job, by).await),
        Request::Remove { job } => reply(change_queue(d, job, None)),
        Request::Move { job, to } => reply(change_queue(d, job, Some(to))),
        Request::Abort { job } => {
            let c = d.core();
            let running = c.running.as_ref().map(|r| r.id);
            reply(match (job, running) {
                (Some(j), Some(r)) if j != r => Err(Refusal::OtherRunning {
                    job: j,
                    running: r,
                    hint: queued_hint(&c, j),
                }),
                (Some(j), None) => Err(Refusal::NotRunning {
                    job: j,
                    hint: queued_hint(&c, j),
                }),
                (None, None) => Err(Refusal::NoneRunning),
                _ => {
                    let id = Daemon::abort_running(&c, &d.runner.desk, "aborted");
                    drop(c);
                    if let Some(id) = id {
                        tracing::warn!("job {id} aborted by {by}");
                    }
                    Ok(json!({ "aborting": id }))
                }
            })
        }
        Request::QueueStart | Request::QueueStop => {
            let run = matches!(request, Request::QueueStart);
            let (running, stopped_by, started) = {
                let mut c = d.core();
                if c.shutting_down && run {
                    return reply(Err(Refusal::Stopping));
                }
                c.queue_running = run;
                c.stopped_by = None;
                // The next job is started here, not by the scheduler later, so the reply
                // says what the queue is: one the journal cannot record stops it at once.
                let started = match (run, &c.running, c.book.queue.first().copied()) {
                    (true, None, Some(next)) => start_job(d, &mut c, next),
                    _ => None,
                };
                (c.queue_running, c.stopped_by.clone(), started)
            };
            d.hub
                .publish(None, json!({"event": "queue", "running": running}));
            if let Some(started) = started {
                launch(d, started);
            }
            d.wake.notify_one();
            let mut r = json!({ "queue_running": running });
            if let Some(why) = stopped_by {
                r["stopped_by"] = why.into();
            }
            reply(Ok(r))
        }
        Request::Follow {
            job: None,
            heartbeat,
        } => {
            let sub = d.hub.follow_all();
            Out::Follow {
                reply: protocol::ok(
                    &id,
                    json!({ "following": "all", "from_seq": d.hub.seq() + 1 }),
                ),
                sub,
                job: None,
                heartbeat,
            }
        }
        Request::Follow {
            job: Some(j),
            heartbeat,
        } => {
            let following = protocol::ok(&id, json!({ "following": j }));
            if let Some(sub) = d.hub.follow_job(j) {
                return Out::Follow {
                    reply: following,
                    sub,
                    job: Some(j),
                    heartbeat,
                };
            }
            // Not in memory: the events the job's session keeps, then its end as the
            // journal knows it (a job of an earlier daemon run).
            let job = d.core().book.jobs.get(&j).cloned();
            let Some(job) = job else {
                return reply(Err(Refusal::NoSuchJobSeeJobs(j)));
            };
            // The session's file is history only (anyone who can write the session can
            // write it): its outcome lines are dropped, and the outcome is the journal's.
            let mut lines = match job.session.clone() {
                Some(dir) => tokio::task::spawn_blocking(move || {
                    super::hub::read_events_file(&dir, j).unwrap_or_default()
                })
                .await
                .unwrap_or_default(),
                None => Vec::new(),
            };
            lines.retain(|l| super::hub::is_history(l));
            if !job.state.ended() {
                // Queued (or running) and not in memory: wait for its events.
                d.hub.open_log(j, lines);
                return match d.hub.follow_job(j) {
                    Some(sub) => Out::Follow {
                        reply: following,
                        sub,
                        job: Some(j),
                        heartbeat,
                    },
                    None => reply(Err(Refusal::Unfollowable(j))),
                };
            }
            // The job's end as the journal knows it: the journal is the truth.
            lines.push(
                protocol::event_line(
                    d.hub.seq(),
                    Some(j),
                    json!({
                        "event": "job-ended", "state": job.state, "session": job.session,
                        "error": job.error, "summary": job.summary,
                        "summary_text": job.summary_text, "replayed": true,
                    }),
                )
                .into(),
            );
            let (tx, rx) = mpsc::channel::<Line>(1);
            drop(tx);
            Out::Follow {
                reply: following,
                sub: Subscription {
                    id: 0,
                    backlog: lines,
                    rx,
                    missed: Default::default(),
                },
                job: Some(j),
                heartbeat,
            }
        }
        Request::Unfollow => Out::Unfollow(protocol::ok(&id, json!({ "following": null }))),
        Request::OperatorDone { job } => reply(
            d.runner
                .desk
                .answer(job)
                .map(|_| json!({ "answered": job }))
                .map_err(Refusal::from),
        ),
        Request::Shutdown => {
            tracing::warn!("stop asked by {by}");
            d.begin_shutdown("daemon stopped by `glint daemon stop`");
            reply(Ok(json!({ "stopping": true })))
        }
    }
}

fn queued_hint(c: &Core, j: u64) -> &'static str {
    match c.book.jobs.get(&j).map(|x| x.state) {
        Some(JobState::Queued) => " (it is queued: `glint queue remove` takes it off the queue)",
        Some(_) => " (it has ended)",
        None => " (there is no such job)",
    }
}

/// The checks of a job's paths that touch the filesystem (run on a blocking thread: a
/// hung mount must not stall the socket).
fn check_job_paths(spec: &protocol::JobSpec) -> Result<(), PathError> {
    if let Some(out) = &spec.out {
        if out.exists() && !out.is_dir() {
            return Err(PathError::OutNotAFolder(out.clone()));
        }
        if std::fs::read_dir(out).is_ok_and(|mut r| r.next().is_some()) {
            return Err(PathError::OutNotEmpty(out.clone()));
        }
    }
    if let Some(s) = &spec.session {
        if !s.join("manifest.json").is_file() {
            return Err(PathError::NotASession(s.clone()));
        }
    }
    // The job's files are read as the job will read them (a regular file, capped, that
    // parses), so a bad one is refused now, not after a whole capture.
    if let Some(p) = &spec.intrinsics {
        crate::calib::run::load_known(p).map_err(PathError::Intrinsics)?;
    }
    Ok(())
}

async fn add(d: &Daemon, spec: protocol::JobSpec, by: &str) -> Result<Value, Refusal> {
    if let Some(p) = spec.problems().into_iter().next() {
        return Err(Refusal::BadJob(p));
    }
    let checked = spec.clone();
    tokio::task::spawn_blocking(move || check_job_paths(&checked))
        .await
        .map_err(Refusal::PathCheck)??;
    let mut c = d.core();
    if c.shutting_down {
        return Err(Refusal::StoppingNoNewJobs);
    }
    if c.book.queue.len() >= MAX_QUEUED {
        return Err(Refusal::QueueFull);
    }
    let job = Job::queued(
        c.book.next_id,
        spec,
        Some(by.to_string()),
        timestamp(SystemTime::now()),
    );
    c.record(Record::Added {
        job: Box::new(job.clone()),
    })?;
    let position = c.book.queue.len().saturating_sub(1);
    let queue_running = c.queue_running;
    // Published under the core lock, so it comes before the job's start.
    d.hub.publish(
        Some(job.id),
        json!({"event": "job-added", "kind": job.spec.kind, "position": position}),
    );
    drop(c);
    d.wake.notify_one();
    Ok(json!({ "job": job.id, "position": position, "queue_running": queue_running }))
}

fn change_queue(d: &Daemon, id: u64, to: Option<usize>) -> Result<Value, Refusal> {
    let mut c = d.core();
    match c.book.jobs.get(&id).map(|j| j.state) {
        None => return Err(Refusal::NoSuchJob(id)),
        Some(JobState::Queued) => {}
        Some(s) => {
            return Err(Refusal::NotQueued {
                job: id,
                state: s.name(),
            })
        }
    }
    let r = match to {
        None => Record::Removed { job: id },
        Some(to) => Record::Moved { job: id, to },
    };
    c.record(r)?;
    let queue = c.book.queue.clone();
    d.hub.publish(
        Some(id),
        match to {
            None => json!({"event": "job-removed"}),
            Some(_) => json!({"event": "job-moved", "queue": queue}),
        },
    );
    drop(c);
    d.wake.notify_one();
    Ok(json!({ "queue": queue }))
}
