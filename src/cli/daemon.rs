//! The daemon and its clients: `glint daemon`, `glint trigger`, `glint jobs`, `glint
//! follow`, `glint abort`, `glint queue`, `glint daemon status|stop`.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use glint::daemon::client::{
    Aborting, Added, Client, JobEnded, Jobs, QueueOrder, QueueRunning, Status,
};
use glint::daemon::protocol::{Job, JobKind, JobSpec, JobState};
use glint::daemon::{paths, OperatorMode};
use glint::fsx::{printable, printable_json, printable_lines};
use glint::pipeline::Progress;
use serde_json::{json, Value};

use super::run::RunProgress;

/// `glint daemon`: run it, or ask it for its status or to stop.
#[derive(Args)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct DaemonArgs {
    #[command(subcommand)]
    command: Option<DaemonCommand>,
    /// The rig file (TOML) whose devices the daemon holds.
    #[arg(long, value_name = "FILE", required = true)]
    rig: Option<PathBuf>,
    /// The socket clients connect to [default: /run/glint/glint.sock for root, else
    /// $XDG_RUNTIME_DIR/glint/glint.sock, else /tmp/glint-UID/glint.sock].
    #[arg(long, value_name = "PATH")]
    socket: Option<PathBuf>,
    /// Where the queue and history are kept [default: /var/lib/glint for root, else
    /// $XDG_STATE_HOME/glint, else ~/.local/state/glint].
    #[arg(long, value_name = "DIR")]
    state_dir: Option<PathBuf>,
    /// Where jobs without --out write their sessions [default: STATE_DIR/sessions].
    #[arg(long, value_name = "DIR")]
    sessions: Option<PathBuf>,
    /// Let this group's members use the daemon too (socket mode 0660 in a 0750 folder).
    #[arg(long, value_name = "NAME")]
    group: Option<String>,
    /// Who performs operator actions (remove the tile for the grid photo): `auto` lets the
    /// simulated lab do it on a mock rig and asks a person through a client on a real one;
    /// `clients` always asks through a client.
    #[arg(long, value_enum, default_value = "auto")]
    operator: OperatorMode,
    /// How long a job waits for an operator before it fails, seconds (a job may set its
    /// own with `glint trigger --operator-timeout`).
    #[arg(long, value_name = "S", default_value_t = 600.0)]
    operator_timeout: f64,
    /// How often the idle devices are checked (the lamp asked its state; one found on is
    /// switched off), seconds.
    #[arg(long, value_name = "S", default_value_t = 30.0)]
    health_interval: f64,
}

#[derive(Subcommand)]
enum DaemonCommand {
    /// The daemon's devices and their health, the queue and the running job.
    Status(SocketArgs),
    /// Abort the running job (lamp off, session failed), and stop the daemon.
    Stop(SocketArgs),
}

#[derive(Args, Clone)]
pub struct SocketArgs {
    /// The daemon's socket [default: $GLINT_SOCKET, else the daemon's default].
    #[arg(long, value_name = "PATH")]
    socket: Option<PathBuf>,
    /// Print JSON on stdout.
    #[arg(long)]
    json: bool,
}

impl SocketArgs {
    fn connect(&self) -> Result<Client> {
        let socket = self.socket.clone().unwrap_or_else(paths::client_socket);
        Ok(Client::connect(&socket)?)
    }
}

pub fn cmd_daemon(a: DaemonArgs) -> Result<ExitCode> {
    match a.command {
        Some(DaemonCommand::Status(s)) => status(&s),
        Some(DaemonCommand::Stop(s)) => {
            let mut c = s.connect()?;
            #[derive(serde::Deserialize)]
            struct Stopping {
                #[allow(dead_code)]
                stopping: bool,
            }
            let r = c.request(json!({"cmd": "shutdown"}))?;
            typed::<Stopping>("shutdown", &r)?;
            if s.json {
                println!("{}", printable_json(&r.to_string()));
            } else {
                println!("the daemon is stopping (a running job is aborted, lamp off)");
            }
            Ok(ExitCode::SUCCESS)
        }
        None => {
            let Some(rig) = a.rig else {
                bail!("glint daemon needs --rig FILE");
            };
            if !(a.operator_timeout.is_finite() && a.operator_timeout > 0.0) {
                bail!(
                    "--operator-timeout must be a positive number of seconds (got {})",
                    a.operator_timeout
                );
            }
            if !(a.health_interval.is_finite() && a.health_interval >= 0.1) {
                bail!(
                    "--health-interval must be at least 0.1 s (got {})",
                    a.health_interval
                );
            }
            glint::daemon::serve(glint::daemon::Options {
                rig,
                socket: a.socket,
                state_dir: a.state_dir,
                sessions_dir: a.sessions,
                group: a.group,
                operator: a.operator,
                operator_timeout: Duration::from_secs_f64(a.operator_timeout.min(7.0 * 86400.0)),
                health_interval: Duration::from_secs_f64(a.health_interval.min(86400.0)),
            })?;
            Ok(ExitCode::SUCCESS)
        }
    }
}

fn status(s: &SocketArgs) -> Result<ExitCode> {
    let mut c = s.connect()?;
    let raw = c.request(json!({"cmd": "status"}))?;
    let st: Status = typed("status", &raw)?;
    if s.json {
        println!("{}", printable_json(&serde_json::to_string_pretty(&raw)?));
        return Ok(ExitCode::SUCCESS);
    }
    let d = &st.daemon;
    println!(
        "glint daemon {} (pid {}), rig `{}` ({}), up since {}",
        printable(&d.version),
        d.pid,
        printable(&d.rig_name),
        printable(&d.rig.to_string_lossy()),
        printable(&d.started)
    );
    let dev = &st.devices;
    println!(
        "devices: {} ({}; {}) since {}{}",
        printable(&dev.state),
        printable(&dev.camera),
        printable(&dev.lamp),
        printable(&dev.since),
        dev.last_error
            .as_deref()
            .map(|e| format!("\n  last error: {}", printable(e)))
            .unwrap_or_default()
    );
    let q = &st.queue;
    println!(
        "queue: {}, {} queued{}",
        if q.running {
            "running"
        } else {
            "stopped (`glint queue start` runs it)"
        },
        q.queued,
        if q.shutting_down {
            "; the daemon is stopping"
        } else {
            ""
        }
    );
    match &st.running {
        Some(j) => println!(
            "running: job {} ({}) since {}, session {}",
            j.id,
            j.spec.kind.name(),
            printable(j.started.as_deref().unwrap_or("?")),
            j.session
                .as_deref()
                .map_or("?".into(), |p| printable(&p.to_string_lossy()).into_owned())
        ),
        None => println!("running: nothing"),
    }
    if let Some(w) = &st.operator {
        println!(
            "waiting for the operator: job {} asks to {} (since {}; `glint follow {}` answers)",
            w.job,
            printable(&w.message),
            printable(&w.since),
            w.job,
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// A reply's `result` as the struct a command prints from: a reply of another shape is an
/// error (exit 1), never printed as `null`.
fn typed<T: serde::de::DeserializeOwned>(cmd: &str, v: &Value) -> Result<T> {
    serde_json::from_value(v.clone()).map_err(|e| {
        glint::daemon::client::ClientError::Mistyped {
            cmd: cmd.into(),
            reason: glint::fsx::short_message(&e.to_string()),
        }
        .into()
    })
}

/// `glint trigger`: queue a job on the daemon and follow it.
#[derive(Args)]
pub struct TriggerArgs {
    #[command(subcommand)]
    job: TriggerJob,
}

#[derive(Subcommand)]
enum TriggerJob {
    /// Capture, HDR, calibration, fit, validation, report: what `glint run` does.
    Run(TriggerRunArgs),
    /// The capture alone, as `glint capture`.
    Capture(TriggerRunArgs),
    /// The stages after the capture (HDR to report) on an existing session.
    Process(TriggerProcessArgs),
}

#[derive(Args)]
struct FollowOpts {
    #[command(flatten)]
    socket: SocketArgs,
    /// Queue the job, print its id, and return at once.
    #[arg(long)]
    detach: bool,
    /// Fail the job when nobody answers an operator request within this many seconds
    /// [default: the daemon's --operator-timeout].
    #[arg(long, value_name = "S")]
    operator_timeout: Option<f64>,
}

#[derive(Args)]
struct TriggerRunArgs {
    /// Where to write the session; must not exist or be empty [default: the daemon's
    /// sessions folder].
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Hold the lens at an earlier calibration (a camera.json, or an OpenCV or ROS camera
    /// YAML); only the pose is fitted.
    #[arg(long, value_name = "CAMERA_JSON|YAML")]
    intrinsics: Option<PathBuf>,
    /// Samples for the fit [default: 400 per 640 pixels of the image's longer side, at
    /// least 400: 800 at 1280x960] (see glint fit --help).
    #[arg(long, value_name = "N")]
    samples: Option<usize>,
    /// Where the fit's samples lie (see glint fit --help; a broad lobe wants rect).
    #[arg(long, value_enum, default_value = "cross")]
    strategy: super::fit::StrategyArg,
    /// The speed/accuracy chart of `glint bench fit` to put in the report, where it exists.
    #[arg(long, value_name = "SVG")]
    bench_chart: Option<PathBuf>,
    #[command(flatten)]
    follow: FollowOpts,
}

#[derive(Args)]
struct TriggerProcessArgs {
    /// The session (captured earlier).
    #[arg(value_name = "SESSION")]
    session: PathBuf,
    /// Hold the lens at an earlier calibration (a camera.json, or an OpenCV or ROS camera
    /// YAML); only the pose is fitted.
    #[arg(long, value_name = "CAMERA_JSON|YAML")]
    intrinsics: Option<PathBuf>,
    /// Samples for the fit [default: 400 per 640 pixels of the image's longer side, at
    /// least 400: 800 at 1280x960] (see glint fit --help).
    #[arg(long, value_name = "N")]
    samples: Option<usize>,
    /// Where the fit's samples lie (see glint fit --help; a broad lobe wants rect).
    #[arg(long, value_enum, default_value = "cross")]
    strategy: super::fit::StrategyArg,
    /// Work on a session that is not complete, with a warning.
    #[arg(long)]
    allow_incomplete: bool,
    #[command(flatten)]
    follow: FollowOpts,
}

/// A path made absolute against this client's working directory (the daemon has its own).
fn absolute(p: Option<PathBuf>) -> Result<Option<PathBuf>> {
    p.map(|p| std::path::absolute(&p).with_context(|| format!("resolving {}", p.display())))
        .transpose()
}

pub fn cmd_trigger(a: TriggerArgs) -> Result<ExitCode> {
    let (spec, follow) = match a.job {
        TriggerJob::Run(r) => (run_spec(JobKind::Run, &r)?, r.follow),
        TriggerJob::Capture(r) => (run_spec(JobKind::Capture, &r)?, r.follow),
        TriggerJob::Process(p) => {
            let mut s = JobSpec::new(JobKind::Process);
            s.session = absolute(Some(p.session))?;
            s.intrinsics = absolute(p.intrinsics)?;
            s.samples = p.samples;
            s.strategy = Some(p.strategy.strategy());
            s.allow_incomplete = p.allow_incomplete;
            s.operator_timeout_s = p.follow.operator_timeout;
            (s, p.follow)
        }
    };
    let socket = follow
        .socket
        .socket
        .clone()
        .unwrap_or_else(paths::client_socket);
    let mut c = Client::connect(&socket)?;
    let raw = c.request(json!({"cmd": "add", "job": spec}))?;
    let added: Added = typed("add", &raw)?;
    let id = added.job;
    let queue_running = added.queue_running;
    if follow.detach {
        if follow.socket.json {
            println!("{}", printable_json(&raw.to_string()));
        } else {
            println!(
                "queued job {id} (position {}); follow it with `glint follow {id}`",
                added.position
            );
        }
        if !queue_running {
            eprintln!("note: the daemon's queue is stopped; `glint queue start` runs it");
        }
        return Ok(ExitCode::SUCCESS);
    }
    eprintln!("queued job {id} on the daemon at {}", socket.display());
    if !queue_running {
        eprintln!("note: the daemon's queue is stopped; the job waits until `glint queue start`");
    }
    follow_job(c, &socket, id, follow.socket.json, false)
}

fn run_spec(kind: JobKind, r: &TriggerRunArgs) -> Result<JobSpec> {
    let mut s = JobSpec::new(kind);
    s.out = absolute(r.out.clone())?;
    s.intrinsics = absolute(r.intrinsics.clone())?;
    s.bench_chart = absolute(r.bench_chart.clone())?;
    s.samples = r.samples;
    s.strategy = Some(r.strategy.strategy());
    s.operator_timeout_s = r.follow.operator_timeout;
    Ok(s)
}

/// `glint follow JOB`.
#[derive(Args)]
pub struct FollowArgs {
    /// The job (see `glint jobs`).
    #[arg(value_name = "JOB")]
    job: u64,
    #[command(flatten)]
    socket: SocketArgs,
    /// Print the job's events as they come, one JSON line each (with --json).
    #[arg(long, requires = "json")]
    events: bool,
}

pub fn cmd_follow(a: FollowArgs) -> Result<ExitCode> {
    let socket = a.socket.socket.clone().unwrap_or_else(paths::client_socket);
    let c = Client::connect(&socket)?;
    follow_job(c, &socket, a.job, a.socket.json, a.events)
}

/// Follow a job to its end with `glint run`'s display, answering operator requests from
/// standard input; print its summary; exit non-zero unless it completed.
fn follow_job(
    mut c: Client,
    socket: &Path,
    id: u64,
    json: bool,
    raw_events: bool,
) -> Result<ExitCode> {
    c.request(json!({"cmd": "follow", "job": id}))?;
    let mut progress = RunProgress::new(0);
    let waiting: Arc<Mutex<Option<u64>>> = Arc::new(Mutex::new(None));
    let mut answerer = None;
    let end: JobEnded = loop {
        let e = match c.next_event() {
            Ok(e) => e,
            Err(err) => {
                progress.finish();
                bail!("{err}; job {id} may still be running (`glint jobs` shows it once the daemon is back)");
            }
        };
        // Only this job's events (and a resync, which names the job it is about): an
        // event of another job says nothing of this one.
        let kind = e["event"].as_str().unwrap_or("");
        if kind != "resync" && e["job"].as_u64() != Some(id) {
            continue;
        }
        if raw_events {
            println!("{}", printable_json(&e.to_string()));
        }
        match kind {
            "job-ended" => {
                progress.finish();
                break typed::<JobEnded>("follow (its job-ended event)", &e)?;
            }
            "job-removed" => {
                progress.finish();
                eprintln!("error: job {id} was taken off the queue (`glint queue remove`)");
                return Ok(ExitCode::FAILURE);
            }
            "resync" => {
                progress.println(&format!(
                    "(this client fell behind and missed {} events)",
                    e["missed"]
                        .as_u64()
                        .map_or("some".into(), |n| n.to_string())
                ));
                if e["job"].is_null() {
                    progress.finish();
                    eprintln!("error: job {id} no longer exists (taken off the queue)");
                    return Ok(ExitCode::FAILURE);
                }
                if let Ok(job) = serde_json::from_value::<Job>(e["job"].clone()) {
                    if job.id != id {
                        continue;
                    }
                    if job.state.ended() {
                        progress.finish();
                        break JobEnded {
                            job: job.id,
                            state: job.state,
                            session: job.session,
                            error: job.error,
                            summary: job.summary,
                            summary_text: job.summary_text,
                        };
                    }
                }
            }
            "job-started" => progress.println(&format!(
                "job {id} started: {} into {}",
                printable(e["kind"].as_str().unwrap_or("?")),
                printable(e["session"].as_str().unwrap_or("?"))
            )),
            "operator" => {
                let msg = e["message"].as_str().unwrap_or("act on the rig");
                progress.println(&format!(
                    "The rig needs you: please {}, then press Enter here (the job waits {} s).",
                    printable(msg),
                    e["timeout_s"]
                        .as_f64()
                        .map_or("?".into(), |t| t.to_string())
                ));
                *waiting.lock().unwrap_or_else(|p| p.into_inner()) = Some(id);
                if answerer.is_none() {
                    answerer = Some(spawn_answerer(socket.to_path_buf(), Arc::clone(&waiting)));
                }
            }
            "operator-done" => {
                *waiting.lock().unwrap_or_else(|p| p.into_inner()) = None;
                progress.println(&format!(
                    "operator: {} (by {})",
                    printable(e["message"].as_str().unwrap_or("?")),
                    printable(e["by"].as_str().unwrap_or("?"))
                ));
            }
            _ => {
                if let Ok(p) = serde_json::from_value::<Progress>(e.clone()) {
                    progress.show(&printable_progress(p));
                }
            }
        }
    };
    if end.state == JobState::Complete {
        if raw_events {
            // The events were the output.
        } else if json {
            println!(
                "{}",
                printable_json(&serde_json::to_string_pretty(&end.summary)?)
            );
        } else {
            println!(
                "{}",
                printable_lines(end.summary_text.as_deref().unwrap_or(""))
            );
        }
        return Ok(ExitCode::SUCCESS);
    }
    eprintln!(
        "error: job {id} {}: {}",
        end.state.name(),
        printable(end.error.as_deref().unwrap_or("no reason given"))
    );
    if let Some(s) = &end.session {
        eprintln!("session: {}", printable(&s.to_string_lossy()));
    }
    Ok(ExitCode::FAILURE)
}

/// A progress event from the daemon with its text made printable.
fn printable_progress(p: Progress) -> Progress {
    let clean = |s: String| printable(&s).into_owned();
    match p {
        Progress::Step {
            index,
            total,
            description,
        } => Progress::Step {
            index,
            total,
            description: clean(description),
        },
        Progress::LampIdentity { identity } => Progress::LampIdentity {
            identity: clean(identity),
        },
        Progress::Discarded { sequence, reason } => Progress::Discarded {
            sequence,
            reason: clean(reason),
        },
        Progress::Warning { message } => Progress::Warning {
            message: clean(message),
        },
        Progress::Hdr { message } => Progress::Hdr {
            message: clean(message),
        },
        Progress::Validate { message } => Progress::Validate {
            message: clean(message),
        },
        other => other,
    }
}

/// Reads standard input; each line answers the operator request waiting then (through a
/// connection of its own, so the events keep coming meanwhile).
fn spawn_answerer(
    socket: PathBuf,
    waiting: Arc<Mutex<Option<u64>>>,
) -> std::thread::JoinHandle<()> {
    std::thread::spawn(move || {
        let stdin = std::io::stdin();
        let mut line = String::new();
        loop {
            line.clear();
            match stdin.read_line(&mut line) {
                Ok(0) | Err(_) => {
                    if !std::io::stdin().is_terminal() {
                        eprintln!(
                            "(standard input ended: this client cannot answer operator requests)"
                        );
                    }
                    return;
                }
                Ok(_) => {}
            }
            let job = waiting.lock().unwrap_or_else(|p| p.into_inner()).take();
            let Some(job) = job else { continue };
            let sent = Client::connect(&socket)
                .and_then(|mut c| c.request(json!({"cmd": "operator-done", "job": job})));
            if let Err(e) = sent {
                eprintln!("warning: could not answer the operator request: {e}");
            }
        }
    })
}

/// `glint jobs`.
#[derive(Args)]
pub struct JobsArgs {
    #[command(flatten)]
    socket: SocketArgs,
}

pub fn cmd_jobs(a: JobsArgs) -> Result<ExitCode> {
    let mut c = a.socket.connect()?;
    let raw = c.request(json!({"cmd": "jobs"}))?;
    let j: Jobs = typed("jobs", &raw)?;
    if a.socket.json {
        println!("{}", printable_json(&serde_json::to_string_pretty(&raw)?));
        return Ok(ExitCode::SUCCESS);
    }
    let line = |j: &Job| {
        format!(
            "{:>5}  {:<11} {:<8} {}{}",
            j.id,
            j.state.name(),
            j.spec.kind.name(),
            j.session
                .as_deref()
                .or(j.spec.session.as_deref())
                .or(j.spec.out.as_deref())
                .map_or("-".into(), |p| printable(&p.to_string_lossy()).into_owned()),
            j.error
                .as_deref()
                .map(|e| format!("\n       {}", printable(e)))
                .unwrap_or_default()
        )
    };
    println!("{:>5}  {:<11} {:<8} session", "job", "state", "kind");
    for job in &j.history {
        println!("{}", line(job));
    }
    if let Some(r) = &j.running {
        println!("{}", line(r));
    }
    for job in &j.queue {
        println!("{}", line(job));
    }
    println!(
        "queue: {}",
        if j.queue_running {
            "running"
        } else {
            "stopped (`glint queue start` runs it)"
        }
    );
    Ok(ExitCode::SUCCESS)
}

/// `glint abort [JOB]`.
#[derive(Args)]
pub struct AbortArgs {
    /// Abort only if this job is the one running.
    #[arg(value_name = "JOB")]
    job: Option<u64>,
    #[command(flatten)]
    socket: SocketArgs,
}

pub fn cmd_abort(a: AbortArgs) -> Result<ExitCode> {
    let mut c = a.socket.connect()?;
    let r = c.request(json!({"cmd": "abort", "job": a.job}))?;
    let aborting: Aborting = typed("abort", &r)?;
    if a.socket.json {
        println!("{}", printable_json(&r.to_string()));
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "aborting job {} at its next frame (lamp off, session failed: aborted)",
        aborting.aborting
    );
    Ok(ExitCode::SUCCESS)
}

/// `glint queue ...`.
#[derive(Subcommand)]
pub enum QueueCommand {
    /// Run queued jobs, one at a time in order (needed after the daemon restarts with jobs
    /// waiting, so that no lamp switches on by surprise).
    Start(SocketArgs),
    /// Start no new job once the running one ends.
    Stop(SocketArgs),
    /// Take a queued job off the queue.
    Remove {
        #[arg(value_name = "JOB")]
        job: u64,
        #[command(flatten)]
        socket: SocketArgs,
    },
    /// Move a queued job to a position (0: next).
    Move {
        #[arg(value_name = "JOB")]
        job: u64,
        #[arg(value_name = "POSITION")]
        to: usize,
        #[command(flatten)]
        socket: SocketArgs,
    },
}

pub fn cmd_queue(q: QueueCommand) -> Result<ExitCode> {
    let (socket, request, order) = match q {
        QueueCommand::Start(s) => (s, json!({"cmd": "queue-start"}), false),
        QueueCommand::Stop(s) => (s, json!({"cmd": "queue-stop"}), false),
        QueueCommand::Remove { job, socket } => {
            (socket, json!({"cmd": "remove", "job": job}), true)
        }
        QueueCommand::Move { job, to, socket } => {
            (socket, json!({"cmd": "move", "job": job, "to": to}), true)
        }
    };
    let cmd = request["cmd"].as_str().unwrap_or("queue").to_string();
    let mut c = socket.connect()?;
    let r = c.request(request)?;
    if !socket.json {
        if let Some(why) = r["stopped_by"].as_str() {
            // Asked to run, the daemon stopped it at once (its journal cannot be written).
            eprintln!("glint: queue stopped: {}", printable(why));
            return Ok(ExitCode::FAILURE);
        }
    }
    let text = if order {
        let q: QueueOrder = typed(&cmd, &r)?;
        format!(
            "queue: [{}]",
            q.queue
                .iter()
                .map(u64::to_string)
                .collect::<Vec<_>>()
                .join(", ")
        )
    } else {
        let q: QueueRunning = typed(&cmd, &r)?;
        format!(
            "queue {}",
            if q.queue_running {
                "running"
            } else {
                "stopped"
            }
        )
    };
    if socket.json {
        println!("{}", printable_json(&r.to_string()));
    } else {
        println!("{text}");
    }
    Ok(ExitCode::SUCCESS)
}
