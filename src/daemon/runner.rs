//! Running one job on a blocking thread: the rig's devices (kept from job to job, reopened
//! after a failure), the operator desk (hands asked through clients), and the pipeline
//! calls the CLI makes. Everything here is synchronous; the server calls [`Runner::execute`]
//! from `spawn_blocking`.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant, SystemTime};

use serde::Serialize;
use serde_json::{json, Value};

use super::hub::Hub;
use super::protocol::{Job, JobKind, JobState};
use crate::capture::{self, Event, Stop};
use crate::devices::{self, DeviceError, Devices, Operator, OperatorAction};
use crate::pipeline::{self, Progress, RunEvent, RunOptions};
use crate::rig::{CameraBackend, LoadedRig};
use crate::session;

/// An operator's answer that matches nothing waiting ([`Desk::answer`]).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum AnswerError {
    #[error("job {job} asks nothing of the operator (job {waiting} does)")]
    OtherJob { job: u64, waiting: u64 },
    #[error("job {job} asks nothing of the operator now")]
    Nothing { job: u64 },
}

/// The rig's devices that cannot be opened, or whose lamp may still be on.
#[derive(Debug, thiserror::Error)]
pub enum DevicesError {
    #[error("opening the rig's devices: {0}")]
    Open(DeviceError),
    #[error("the {lamp} did not confirm OFF after opening: {source}")]
    NotOffAfterOpening { lamp: String, source: DeviceError },
    #[error("the {lamp} may still be on: {source}")]
    MayBeOn { lamp: String, source: DeviceError },
    #[error("the idle lamp was on and did not switch off: {0}")]
    IdleLampOn(DeviceError),
    #[error("idle check: {0}")]
    IdleCheck(DeviceError),
    #[error("{devices}; the lamp alone: {lamp}; it may still be on")]
    LampAlone {
        devices: Box<DevicesError>,
        lamp: DeviceError,
    },
}

/// Why a job failed (its `error`, shortened).
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    #[error(transparent)]
    Intrinsics(crate::calib::run::RunError),
    #[error("the job has no session")]
    NoSession,
    #[error(transparent)]
    Run(#[from] pipeline::RunError),
    #[error(transparent)]
    Summary(#[from] serde_json::Error),
    #[error("the capture plan cannot run: {0}")]
    Plan(String),
    #[error(transparent)]
    Devices(#[from] DevicesError),
    #[error("the rig's devices are not open")]
    NotOpen,
    #[error("the tile is off the grid since the last job's grid photo: {0}")]
    TileOff(DeviceError),
    #[error(transparent)]
    Capture(#[from] capture::RecordError),
}

/// Who performs operator actions.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum OperatorMode {
    /// The rig's own hands: the simulated lab for a mock rig, the `[operator]` commands
    /// where the rig has them, a person through a client otherwise.
    Auto,
    /// Always a person through a client (`glint trigger` or `glint follow` at the rig);
    /// for a mock rig the simulated lab then does what the person confirmed.
    Clients,
}

/// What the daemon knows of its devices, for `status`.
#[derive(Debug, Clone, Serialize)]
pub struct Health {
    pub camera: String,
    pub lamp: String,
    /// `ok` (open, last use fine), `closed` (reopened at the next job), `failed` (the last
    /// open or job failed on a device; reopened at the next job).
    pub state: &'static str,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_error: Option<String>,
    pub since: String,
}

/// The outcome of a job.
pub struct Outcome {
    pub state: JobState,
    pub error: Option<String>,
    pub summary: Option<Value>,
    pub summary_text: Option<String>,
}

/// An operator request waiting for an answer.
#[derive(Debug, Clone, Serialize)]
pub struct Waiting {
    pub job: u64,
    pub action: OperatorAction,
    pub message: String,
    pub timeout_s: f64,
    pub since: String,
}

#[derive(Default)]
struct DeskState {
    job: Option<u64>,
    timeout: Duration,
    stop: Option<Stop>,
    waiting: Option<Waiting>,
    answered: bool,
    /// The last job's grid photo took the tile off: the next capture needs it back.
    tile_off: bool,
}

/// Where operator requests wait for an answer from a client.
#[derive(Default)]
pub struct Desk {
    state: Mutex<DeskState>,
    cv: Condvar,
}

impl Desk {
    fn lock(&self) -> std::sync::MutexGuard<'_, DeskState> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The request waiting now, if any.
    pub fn waiting(&self) -> Option<Waiting> {
        self.lock().waiting.clone()
    }

    /// A client says the operator did what `job` asked. `Err` when nothing of that job
    /// waits.
    pub fn answer(&self, job: u64) -> Result<(), AnswerError> {
        let mut s = self.lock();
        match &s.waiting {
            Some(w) if w.job == job => {
                s.answered = true;
                self.cv.notify_all();
                Ok(())
            }
            Some(w) => Err(AnswerError::OtherJob {
                job,
                waiting: w.job,
            }),
            None => Err(AnswerError::Nothing { job }),
        }
    }

    /// Wake a waiting request so it sees its job's stop flag.
    pub fn wake(&self) {
        self.cv.notify_all();
    }
}

/// The operator the daemon puts in its devices: asks through clients (or lets the
/// simulated lab act), and keeps track of whether the tile is on the grid.
struct DeskOperator {
    inner: Box<dyn Operator>,
    /// The rig has hands of its own (the simulated lab, or `[operator]` commands): `inner`
    /// performs the actions; otherwise `inner` is a console nobody watches.
    simulated: bool,
    /// Who `inner` is, for the `operator-done` event.
    by: &'static str,
    mode: OperatorMode,
    desk: Arc<Desk>,
    hub: Arc<Hub>,
}

impl Operator for DeskOperator {
    fn perform(&mut self, action: OperatorAction) -> Result<(), DeviceError> {
        let job = self.desk.lock().job;
        if self.simulated && self.mode == OperatorMode::Auto {
            self.inner.perform(action)?;
            self.hub.publish(
                job,
                json!({"event": "operator-done", "action": action, "message": action.to_string(), "by": self.by}),
            );
        } else {
            self.ask(job, action)?;
            if self.simulated {
                // The rig's own hands do what the person confirmed.
                self.inner.perform(action)?;
            }
        }
        // Showing the board in a pose takes the tile out of view as removing it does.
        self.desk.lock().tile_off = matches!(
            action,
            OperatorAction::RemoveTile | OperatorAction::ShowBoard(_)
        );
        Ok(())
    }
}

impl DeskOperator {
    fn ask(&mut self, job: Option<u64>, action: OperatorAction) -> Result<(), DeviceError> {
        let desk = Arc::clone(&self.desk);
        let mut s = desk.lock();
        let timeout = s.timeout;
        let stop = s.stop.clone();
        let Some(job) = job.or(s.job) else {
            return Err(DeviceError::Operator(format!(
                "the rig needs someone to {action}, outside any job"
            )));
        };
        let waiting = Waiting {
            job,
            action,
            message: action.to_string(),
            timeout_s: timeout.as_secs_f64(),
            since: session::timestamp(SystemTime::now()),
        };
        s.waiting = Some(waiting.clone());
        s.answered = false;
        drop(s);
        self.hub.publish(
            Some(job),
            json!({"event": "operator", "action": action, "message": waiting.message, "timeout_s": waiting.timeout_s}),
        );
        tracing::warn!(
            "job {job} waits for the operator to {action} (at most {:.0} s; answer with glint trigger or glint follow {job})",
            timeout.as_secs_f64()
        );
        let end = Instant::now() + timeout;
        let mut s = desk.lock();
        let outcome = loop {
            if s.answered {
                break Ok(());
            }
            if let Some(stop) = stop.as_ref().filter(|f| f.is_set()) {
                break Err(DeviceError::Operator(
                    stop.reason().unwrap_or_else(|| "aborted".into()),
                ));
            }
            let left = end.saturating_duration_since(Instant::now());
            if left.is_zero() {
                break Err(DeviceError::Operator(format!(
                    "nobody answered the request to {action} within {} s; answer it at the rig with `glint follow {job}` (or `glint trigger`), or raise the job's operator timeout",
                    fmt_secs(timeout)
                )));
            }
            s = desk
                .cv
                .wait_timeout(s, left.min(Duration::from_millis(200)))
                .map(|(g, _)| g)
                .unwrap_or_else(|p| p.into_inner().0);
        };
        s.waiting = None;
        s.answered = false;
        drop(s);
        if outcome.is_ok() {
            self.hub.publish(
                Some(job),
                json!({"event": "operator-done", "action": action, "message": action.to_string(), "by": "a client"}),
            );
        }
        outcome
    }
}

fn fmt_secs(d: Duration) -> String {
    let s = d.as_secs_f64();
    if s.fract() == 0.0 {
        format!("{s:.0}")
    } else {
        format!("{s:.1}")
    }
}

/// A placeholder while the real operator is moved into the desk's wrapper.
struct Nobody;
impl Operator for Nobody {
    fn perform(&mut self, action: OperatorAction) -> Result<(), DeviceError> {
        Err(DeviceError::Operator(format!("nobody to {action}")))
    }
}

/// Runs jobs on the rig.
pub struct Runner {
    pub rig: LoadedRig,
    /// Where jobs without `out` write their sessions.
    pub sessions_dir: PathBuf,
    pub operator_mode: OperatorMode,
    pub operator_timeout: Duration,
    pub desk: Arc<Desk>,
    hub: Arc<Hub>,
    devices: Mutex<Option<Devices>>,
    health: Mutex<Health>,
    /// Held while a job runs: the idle check never touches devices a job uses.
    busy: Mutex<()>,
}

impl Runner {
    pub fn new(
        rig: LoadedRig,
        sessions_dir: PathBuf,
        operator_mode: OperatorMode,
        operator_timeout: Duration,
        hub: Arc<Hub>,
    ) -> Self {
        let r = &rig.rig;
        let health = Health {
            camera: format!(
                "{:?} camera{} {}x{} {}-bit",
                r.camera.backend,
                r.camera
                    .device
                    .as_deref()
                    .map(|d| format!(" at {d}"))
                    .unwrap_or_default(),
                r.camera.width,
                r.camera.height,
                r.camera.bit_depth
            )
            .to_lowercase(),
            lamp: format!("{:?} lamp", r.lamp.backend).to_lowercase(),
            state: "closed",
            last_error: None,
            since: session::timestamp(SystemTime::now()),
        };
        Runner {
            rig,
            sessions_dir,
            operator_mode,
            operator_timeout,
            desk: Arc::new(Desk::default()),
            hub,
            devices: Mutex::new(None),
            health: Mutex::new(health),
            busy: Mutex::new(()),
        }
    }

    pub fn health(&self) -> Health {
        self.health
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    fn set_health(&self, state: &'static str, error: Option<String>) {
        let mut h = self.health.lock().unwrap_or_else(|p| p.into_inner());
        if h.state != state || h.last_error != error {
            h.since = session::timestamp(SystemTime::now());
        }
        h.state = state;
        h.last_error = error;
    }

    /// Open the rig's devices (if they are not open) and switch the lamp off: at the
    /// daemon's start (a crash may have left it on) and before each job after a failure.
    pub fn open_devices(&self) -> Result<(), DevicesError> {
        let mut slot = self.devices.lock().unwrap_or_else(|p| p.into_inner());
        if slot.is_some() {
            return Ok(());
        }
        let opened = devices::open(&self.rig).map_err(DevicesError::Open);
        let mut d = match opened {
            Ok(d) => d,
            Err(e) => {
                self.set_health("failed", Some(e.to_string()));
                return Err(e);
            }
        };
        if let Err(e) = d.lamp.switch_off() {
            let e = DevicesError::NotOffAfterOpening {
                lamp: d.lamp.describe(),
                source: e,
            };
            self.set_health("failed", Some(e.to_string()));
            return Err(e);
        }
        {
            let mut h = self.health.lock().unwrap_or_else(|p| p.into_inner());
            let info = d.camera.info();
            h.camera = format!(
                "{} {}x{} {}-bit",
                info.model, info.width, info.height, info.bit_depth
            );
            h.lamp = d.lamp.describe();
        }
        let inner = std::mem::replace(&mut d.operator, Box::new(Nobody));
        d.operator = Box::new(DeskOperator {
            inner,
            simulated: self.rig.rig.camera.backend == CameraBackend::Mock
                || self.rig.rig.operator.is_some(),
            by: if self.rig.rig.camera.backend == CameraBackend::Mock {
                "the simulated lab"
            } else {
                "the rig's [operator] commands"
            },
            mode: self.operator_mode,
            desk: Arc::clone(&self.desk),
            hub: Arc::clone(&self.hub),
        });
        *slot = Some(d);
        self.set_health("ok", None);
        Ok(())
    }

    /// Check idle devices: ask the lamp its state (a lamp found on while no job runs is
    /// switched off). A lamp that does not answer closes the devices, and `status` says
    /// why; closed devices are reopened (lamp off), so `status` also shows a device that
    /// has come back. Never while a job runs.
    pub fn probe(&self) {
        let Ok(_idle) = self.busy.try_lock() else {
            return; // a job runs
        };
        let closed = self
            .devices
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .is_none();
        if closed {
            if let Err(e) = self.open_devices() {
                tracing::warn!("idle check: {e}");
            }
            return;
        }
        let mut slot = self.devices.lock().unwrap_or_else(|p| p.into_inner());
        let Some(d) = slot.as_mut() else { return };
        let found = match d.lamp.state() {
            Ok(s) if s.on => {
                tracing::warn!(
                    "the {} was {s} with no job running; switching it off",
                    d.lamp.describe()
                );
                d.lamp
                    .switch_off()
                    .map(|_| ())
                    .map_err(DevicesError::IdleLampOn)
            }
            Ok(_) => Ok(()),
            Err(e) => Err(DevicesError::IdleCheck(e)),
        };
        match found {
            Ok(()) => {
                drop(slot);
                self.set_health("ok", None);
            }
            Err(e) => {
                tracing::error!("{e}; the devices are closed and reopened at the next job");
                *slot = None;
                drop(slot);
                self.set_health("failed", Some(e.to_string()));
            }
        }
    }

    /// At the daemon's exit: switch the lamp off (the devices are open) or open them to do
    /// so (a failed job closed them), so that no lamp burns after the daemon. `Err` says
    /// the lamp may still be on.
    pub fn lamp_off_at_exit(&self) -> Result<(), DevicesError> {
        let open = self
            .devices
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .is_some();
        if !open {
            // Opening switches the lamp off and confirms it; where the devices cannot be
            // opened (a camera gone), the lamp alone is.
            return self.open_devices().or_else(|e| {
                devices::lamp_off(&self.rig)
                    .map(|_| ())
                    .map_err(|lamp| DevicesError::LampAlone {
                        devices: Box::new(e),
                        lamp,
                    })
            });
        }
        let mut slot = self.devices.lock().unwrap_or_else(|p| p.into_inner());
        match slot.as_mut() {
            Some(d) => d
                .lamp
                .switch_off()
                .map(|_| ())
                .map_err(|e| DevicesError::MayBeOn {
                    lamp: d.lamp.describe(),
                    source: e,
                }),
            None => Ok(()),
        }
    }

    /// Close the devices (a failed job: they are reopened for the next one).
    fn close_devices(&self, why: String) {
        let mut slot = self.devices.lock().unwrap_or_else(|p| p.into_inner());
        *slot = None;
        self.set_health("failed", Some(why));
    }

    /// The session a job writes: its `out`, or a new folder in the sessions folder.
    pub fn session_for(&self, job: &Job) -> Option<PathBuf> {
        match job.spec.kind {
            JobKind::Process => job.spec.session.clone(),
            JobKind::Run | JobKind::Capture => Some(job.spec.out.clone().unwrap_or_else(|| {
                let name = session::folder_name(&self.rig.rig.rig.name);
                self.sessions_dir.join(format!("{name}-job{}", job.id))
            })),
        }
    }

    /// Run a job to its end. `stop` aborts it (the reason noted with
    /// [`Stop::stop_for`]).
    pub fn execute(&self, job: &Job, session: Option<&Path>, stop: Stop) -> Outcome {
        let _busy = self.busy.lock().unwrap_or_else(|p| p.into_inner());
        {
            let mut s = self.desk.lock();
            s.job = Some(job.id);
            s.stop = Some(stop.clone());
            s.timeout = job
                .spec
                .operator_timeout_s
                .map(Duration::from_secs_f64)
                .unwrap_or(self.operator_timeout);
        }
        let result = self.execute_inner(job, session, &stop);
        self.desk.lock().job = None;
        match result {
            Ok((summary, text)) => Outcome {
                state: JobState::Complete,
                error: None,
                summary: Some(summary),
                summary_text: Some(text),
            },
            Err(e) => Outcome {
                state: if stop.is_set() {
                    JobState::Aborted
                } else {
                    JobState::Failed
                },
                error: Some(crate::fsx::short_message(&e.to_string())),
                summary: None,
                summary_text: None,
            },
        }
    }

    fn options(&self, job: &Job) -> Result<RunOptions, JobError> {
        let s = &job.spec;
        let mut opts = RunOptions {
            intrinsics: s
                .intrinsics
                .as_deref()
                .map(crate::calib::run::load_known)
                .transpose()
                .map_err(JobError::Intrinsics)?,
            ..Default::default()
        };
        opts.fit.sample.count = s.samples;
        if let Some(st) = s.strategy {
            opts.fit.sample.strategy = st;
        }
        opts.report.bench_chart = s.bench_chart.clone();
        opts.hdr.allow_incomplete = s.allow_incomplete;
        opts.fit.allow_incomplete = s.allow_incomplete;
        opts.validate.allow_incomplete = s.allow_incomplete;
        opts.report.allow_incomplete = s.allow_incomplete;
        Ok(opts)
    }

    fn execute_inner(
        &self,
        job: &Job,
        session: Option<&Path>,
        stop: &Stop,
    ) -> Result<(Value, String), JobError> {
        let opts = self.options(job)?;
        let session = session.ok_or(JobError::NoSession)?;
        let hub = &self.hub;
        let id = job.id;
        let mut on_event = |e: RunEvent| {
            if let RunEvent::Capture(Event::Started { .. }) = e {
                // The capture has created the session: it is this job's own.
                hub.set_session(id, session);
            }
            publish_progress(hub, id, &Progress::from(&e));
        };
        if job.spec.kind == JobKind::Process {
            hub.set_session(id, session);
            let s = pipeline::process(&self.rig, session, stop.clone(), &opts, &mut on_event)?;
            let text = s.text(pipeline::truth_line(&self.rig, &s).as_deref());
            return Ok((serde_json::to_value(&s)?, text));
        }
        if let Some(p) = capture::Plan::for_rig(&self.rig.rig)
            .check_resources(&self.rig.rig, session)
            .into_iter()
            .next()
        {
            return Err(JobError::Plan(p));
        }
        self.open_devices()?;
        let mut devices = self
            .devices
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .take()
            .ok_or(JobError::NotOpen)?;
        // The last job's grid photo took the tile off the grid: it goes back first.
        if self.desk.lock().tile_off {
            if let Err(e) = devices.operator.perform(OperatorAction::PlaceTile) {
                *self.devices.lock().unwrap_or_else(|p| p.into_inner()) = Some(devices);
                return Err(JobError::TileOff(e));
            }
        }
        let (devices, result) = match job.spec.kind {
            JobKind::Run => {
                let (d, r) = pipeline::run_returning(
                    &self.rig,
                    devices,
                    session,
                    stop.clone(),
                    &opts,
                    &mut on_event,
                );
                let r = r.map_err(JobError::from).and_then(|s| {
                    let text = s.text(pipeline::truth_line(&self.rig, &s).as_deref());
                    Ok((serde_json::to_value(&s)?, text))
                });
                (d, r)
            }
            _ => {
                let r = capture::record_returning(
                    &self.rig,
                    devices,
                    session,
                    stop.clone(),
                    &mut |e| on_event(RunEvent::Capture(e)),
                    &mut |_| {},
                );
                match r {
                    Ok(rec) => {
                        let done = (rec.summary_json(), rec.summary_text());
                        (Some(rec.devices), Ok(done))
                    }
                    Err((e, d)) => (Some(d), Err(e.into())),
                }
            }
        };
        match (&result, devices) {
            (Ok(_), Some(d)) => {
                *self.devices.lock().unwrap_or_else(|p| p.into_inner()) = Some(d);
                self.set_health("ok", None);
            }
            (Err(_), Some(mut d)) if stop.is_set() => {
                // Aborted: the capture switched the lamp off; confirm it, and keep the
                // devices only if it reads back off.
                match d.lamp.switch_off() {
                    Ok(_) => *self.devices.lock().unwrap_or_else(|p| p.into_inner()) = Some(d),
                    Err(e) => {
                        drop(d);
                        self.close_devices(format!(
                            "the lamp may still be on: switching it off after the abort failed: {e}"
                        ));
                    }
                }
            }
            (Err(e), d) => {
                // A failure: whatever failed, the devices are closed and reopened (and the
                // lamp switched off again) before the next job.
                drop(d);
                self.close_devices(e.to_string());
            }
            (Ok(_), None) => self.close_devices("the capture lost the devices".into()),
        }
        result
    }
}

/// Publish a progress event of a job.
pub fn publish_progress(hub: &Hub, job: u64, p: &Progress) {
    match serde_json::to_value(p) {
        Ok(v) => {
            hub.publish(Some(job), v);
        }
        Err(e) => tracing::warn!("job {job}: an event could not be encoded: {e}"),
    }
}

/// Close the session of a job the daemon was running when it died
/// ([`session::close_abandoned`]), recording whether the lamp was read back off at this
/// start (`lamp_off_confirmed`); a line for the log.
pub fn close_interrupted_session(
    dir: &Path,
    why: &str,
    lamp_off_confirmed: bool,
) -> Result<String, session::SessionError> {
    match session::close_abandoned(dir, why, Some(lamp_off_confirmed))? {
        None => Ok(format!(
            "session {} closed as failed (lamp {})",
            dir.display(),
            if lamp_off_confirmed {
                "read back off"
            } else {
                "not confirmed off"
            }
        )),
        Some(state) => Ok(format!(
            "session {} left as it is (state {})",
            dir.display(),
            serde_json::to_value(state)
                .ok()
                .and_then(|v| v.as_str().map(str::to_string))
                .unwrap_or_default()
        )),
    }
}

/// Sessions in the daemon's sessions folder still `capturing` (a capture killed with its
/// daemon), closed as `failed` with `why` and `lamp_off_confirmed`, whatever the journal
/// holds: the journal may be unreadable, or may not name them. A session whose capture is
/// alive (its disk reserve names a running process other than this one) is left alone, as
/// are links and anything that is not a session. Returns the folders closed, with a line
/// each for the log.
pub fn close_capturing_sessions(
    sessions_dir: &Path,
    why: &str,
    lamp_off_confirmed: bool,
) -> Vec<(PathBuf, String)> {
    let Ok(entries) = std::fs::read_dir(sessions_dir) else {
        return Vec::new();
    };
    let mut closed = Vec::new();
    for e in entries.flatten().take(100_000) {
        // A link is never followed (it may lead anywhere); only real folders are sessions.
        if !e.file_type().is_ok_and(|t| t.is_dir()) {
            continue;
        }
        let dir = e.path();
        let is_capturing = session::load(&dir)
            .map(|m| m.state == session::State::Capturing)
            .unwrap_or(false);
        if !is_capturing {
            continue;
        }
        if let Some(pid) = live_capturer(&dir) {
            tracing::warn!(
                "session {} says capturing and process {pid} still writes it: left alone",
                dir.display()
            );
            continue;
        }
        let line = close_interrupted_session(&dir, why, lamp_off_confirmed)
            .unwrap_or_else(|e| format!("session {} could not be closed: {e}", dir.display()));
        closed.push((dir, line));
    }
    closed
}

/// The running process (not this one) whose disk reserve is in the session `dir`, if any:
/// a capture still writing it.
fn live_capturer(dir: &Path) -> Option<u32> {
    let me = std::process::id();
    std::fs::read_dir(dir)
        .ok()?
        .flatten()
        .take(10_000)
        .filter_map(|e| {
            let name = e.file_name();
            let pid = name
                .to_str()?
                .strip_prefix(session::RESERVE_PREFIX)?
                .parse::<u32>()
                .ok()?;
            Some(pid)
        })
        .find(|&pid| {
            pid != me
                && i32::try_from(pid).is_ok_and(|p| {
                    // SAFETY: kill(2) with signal 0 only checks that the process exists.
                    let r = unsafe { libc::kill(p, 0) };
                    r == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
                })
        })
}
