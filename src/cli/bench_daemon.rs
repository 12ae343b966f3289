//! `glint bench daemon`: what the daemon costs, measured in one sitting against a daemon
//! the bench starts itself.
//!
//! The daemon adds a socket, a journal and an event fan-out around the same pipeline that
//! `glint run` calls, and none of that should cost the capture anything. Three figures
//! check it: (a) how soon a job starts, and shows its first kept frame, after a client
//! sends `add` (the trigger latency an operator feels); (b) the wall time of a `capture`
//! job with no extra followers beside the same job with ten extra connections following
//! every event, as a ratio (publishing never waits for a follower, so the goal is within
//! 2%); (c) a `run` job's wall time through the daemon, `add` to `job-ended` as a client
//! sees it, beside `glint run` started as a subprocess, as a ratio (goal: within 5%).
//!
//! All times are taken by this process with a monotonic clock: the moment just before the
//! `add` line is written, and the moment each event is read off a connection that follows
//! every event for the whole sitting (the bench's watcher, so a "no followers" job still
//! has that one). Pairs are run in alternating order (A then B, then B then A) so that
//! drift of the machine cancels, and each figure is the median over the repeats, with the
//! smallest and largest beside it. A ratio's goal is judged by the 95% interval of the
//! mean over the pairs: met, not met, or inconclusive when the interval straddles it.
//! One untimed `run` of each kind goes first to warm the caches. Sessions are written to
//! fresh folders under the scratch folder and deleted once timed.
//!
//! Wall time is only as good as the machine is quiet, and a simulated capture's wall time
//! varies by about 10% from one job to the next even on a quiet machine, so a 2% goal
//! needs many repeats to be judged at all. So the bench also reads CPU time from `/proc`
//! around each timed job: the daemon's (what the followers cost it, a figure others' work
//! hardly moves), this process's (the followers' reading), and everybody else's as a share
//! of the machine, printed so that a busy sitting shows.

use std::collections::HashMap;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitCode, Stdio};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError};
use std::sync::{Arc, OnceLock};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::Args;
use glint::daemon::client::Client;
use glint::daemon::protocol::{JobKind, JobSpec};
use serde_json::{json, Value};

#[derive(Args)]
pub struct DaemonBenchArgs {
    /// The rig the daemon holds and `glint run` uses [default: rigs/mock.toml of the
    /// current folder, else of Glint's source tree].
    #[arg(long, value_name = "FILE")]
    rig: Option<PathBuf>,
    /// Timed repeats of each pair (the median is reported).
    #[arg(long, default_value_t = 3, value_name = "N")]
    repeats: usize,
    /// Extra connections following every event in the fan-out figure.
    #[arg(long, default_value_t = 10, value_name = "N")]
    followers: usize,
    /// Scratch folder (new or empty): the daemon's socket, state and log, and the sessions
    /// while they are timed [default: a temporary folder, removed at the end].
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Print the figures as JSON.
    #[arg(long)]
    json: bool,
}

/// The longest a single job may take before the bench gives up.
const JOB_LIMIT: Duration = Duration::from_secs(600);
/// Goals: (b) at most 2% slower with followers, (c) at most 5% slower through the daemon.
const FANOUT_GOAL: f64 = 0.02;
const RUN_GOAL: f64 = 0.05;

impl DaemonBenchArgs {
    /// The rig, once [`daemon_bench`] has resolved it (`--rig` or the default).
    fn rig(&self) -> &std::path::Path {
        self.rig.as_deref().unwrap_or(std::path::Path::new(""))
    }
}

pub fn daemon_bench(mut a: DaemonBenchArgs) -> Result<ExitCode> {
    if a.repeats == 0 {
        bail!("--repeats must be at least 1");
    }
    let exe = std::env::current_exe().context("finding this glint executable")?;
    let cwd = std::env::current_dir().context("reading the working directory")?;
    let given = super::bench::mock_rig(a.rig.as_deref())?;
    let rig =
        std::fs::canonicalize(&given).with_context(|| format!("the rig {}", given.display()))?;
    a.rig = Some(given);
    glint::rig::load(&rig)?;

    // The scratch folder: a temporary one, or --out (new or empty).
    let temp;
    let scratch = match &a.out {
        Some(d) => {
            let d = cwd.join(d);
            if std::fs::read_dir(&d).is_ok_and(|mut r| r.next().is_some()) {
                bail!("{} is not empty; give a new or empty --out", d.display());
            }
            std::fs::create_dir_all(&d).with_context(|| format!("creating {}", d.display()))?;
            d
        }
        None => {
            temp = tempfile::Builder::new()
                .prefix("glint-bench-daemon-")
                .tempdir()
                .context("creating a temporary folder")?;
            temp.path().to_path_buf()
        }
    };
    let sessions = scratch.join("sessions");
    std::fs::create_dir_all(&sessions)?;
    // What `glint run` puts in its report by default, given to the daemon's jobs too.
    let bench_chart = Some(cwd.join("bench-fit/fit_bench.svg")).filter(|p| p.is_file());

    let load_before = load_average();
    let daemon = DaemonChild::start(&exe, &rig, &scratch)?;
    let socket = daemon.socket.clone();
    let mut bench = Bench {
        daemon_pid: daemon.pid(),
        control: Client::connect(&socket)?,
        watcher: Watcher::start(&socket)?,
        socket,
        sessions,
        exe,
        rig: rig.clone(),
        bench_chart,
        count: 0,
    };

    eprintln!("warming up: one run through the daemon, one glint run");
    bench.daemon_job(JobKind::Run, 0)?;
    bench.cli_run()?;

    let mut r = Results::default();
    for i in 0..a.repeats {
        let n = i + 1;
        let flip = i % 2 == 1;
        // (a) and (b): a capture job without and with extra followers.
        for with in [flip, !flip] {
            let t = bench.daemon_job(JobKind::Capture, if with { a.followers } else { 0 })?;
            eprintln!(
                "repeat {n}/{}: capture, {:>2} extra followers: {:.3} s (start {:.1} ms, first frame {:.1} ms; others used {:.0}% of the machine)",
                a.repeats,
                if with { a.followers } else { 0 },
                t.wall,
                t.started * 1e3,
                t.first_frame * 1e3,
                t.cpu.others * 100.0
            );
            r.events_per_capture = t.events;
            r.follower_shortfall += t.follower_shortfall;
            r.resyncs += t.resyncs;
            r.others.push(t.cpu.others);
            if with {
                r.capture_with.push(t.wall);
                r.started_with.push(t.started);
                r.first_frame_with.push(t.first_frame);
                r.capture_cpu_with.push(t.cpu.daemon_s);
                r.followers_cpu.push(t.cpu.ours_s);
            } else {
                r.capture_without.push(t.wall);
                r.started.push(t.started);
                r.first_frame.push(t.first_frame);
                r.capture_cpu_without.push(t.cpu.daemon_s);
            }
        }
        r.fanout_ratio
            .push(r.capture_with[i] / r.capture_without[i]);
        // (c): a run through the daemon and a glint run subprocess.
        for through_daemon in [!flip, flip] {
            if through_daemon {
                let t = bench.daemon_job(JobKind::Run, 0)?;
                eprintln!(
                    "repeat {n}/{}: run through the daemon: {:.3} s (others used {:.0}% of the machine)",
                    a.repeats,
                    t.wall,
                    t.cpu.others * 100.0
                );
                r.run_daemon.push(t.wall);
                r.run_daemon_cpu.push(t.cpu.daemon_s);
                r.others.push(t.cpu.others);
            } else {
                let (wall, cpu) = bench.cli_run()?;
                eprintln!(
                    "repeat {n}/{}: glint run subprocess:   {wall:.3} s (others used {:.0}% of the machine)",
                    a.repeats,
                    cpu.others * 100.0
                );
                r.run_cli.push(wall);
                r.run_cli_cpu.push(cpu.ours_s);
                r.others.push(cpu.others);
            }
        }
        r.run_ratio.push(r.run_daemon[i] / r.run_cli[i]);
    }
    drop(bench);
    let status = daemon.stop()?;
    // The publishing side of the fan-out, in-process, where nothing else varies.
    r.publish_s = [
        publish_cost(0, PUBLISH_EVENTS),
        publish_cost(a.followers, PUBLISH_EVENTS),
    ];

    let mut machine = Machine::this();
    machine.load = [load_before, load_average()];
    let command = format!(
        "glint bench daemon --rig {} --repeats {}{}",
        a.rig().display(),
        a.repeats,
        if a.followers == 10 {
            String::new()
        } else {
            format!(" --followers {}", a.followers)
        }
    );
    if a.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&r.json(&machine, &a, &command, &status))?
        );
    } else {
        r.print(&machine, &a, &status);
    }
    Ok(ExitCode::SUCCESS)
}

/// What one daemon job looked like from this client, seconds from the `add`.
struct JobTimes {
    started: f64,
    first_frame: f64,
    wall: f64,
    /// The job's events the watcher read.
    events: u64,
    /// Events the extra followers together read fewer than the watcher.
    follower_shortfall: u64,
    /// `resync` lines (a connection fell behind) the watcher and followers saw.
    resyncs: u64,
    /// CPU used from the `add` to the job's end.
    cpu: CpuUse,
}

/// Everything the bench needs during the sitting.
struct Bench {
    socket: PathBuf,
    daemon_pid: u32,
    /// The connection that sends `add`.
    control: Client,
    watcher: Watcher,
    sessions: PathBuf,
    exe: PathBuf,
    rig: PathBuf,
    bench_chart: Option<PathBuf>,
    /// Sessions written so far (their folders are numbered).
    count: usize,
}

impl Bench {
    /// A fresh session folder (it must not exist).
    fn new_out(&mut self, what: &str) -> PathBuf {
        self.count += 1;
        self.sessions.join(format!("{:03}-{what}", self.count))
    }

    /// Queue a job on the daemon with `followers` extra connections following every
    /// event, and time it to its end.
    fn daemon_job(&mut self, kind: JobKind, followers: usize) -> Result<JobTimes> {
        let out = self.new_out(&format!("{}-daemon-f{followers}", kind.name()));
        let mut spec = JobSpec::new(kind);
        spec.out = Some(out.clone());
        if kind == JobKind::Run {
            spec.bench_chart = self.bench_chart.clone();
        }
        // The followers are attached (their `follow` answered) before the job is added.
        let target = Arc::new(OnceLock::new());
        let extra = (0..followers)
            .map(|_| Follower::attach(&self.socket, Arc::clone(&target)))
            .collect::<Result<Vec<_>>>()?;

        let before = CpuMark::take(self.daemon_pid);
        let t0 = Instant::now();
        let added = self.control.request(json!({"cmd": "add", "job": spec}))?;
        let id = added["job"]
            .as_u64()
            .context("the daemon's reply to `add` has no job id")?;
        let _ = target.set(id);
        let seen = self.watcher.wait_job(id)?;
        let cpu = CpuMark::take(self.daemon_pid).since(&before);

        let mut shortfall = 0;
        let mut resyncs = seen.resyncs;
        for f in extra {
            let got = f.join()?;
            shortfall += seen.events.saturating_sub(got.events);
            resyncs += got.resyncs;
        }
        if seen.state != "complete" {
            bail!(
                "job {id} ({}) ended {}: {}",
                kind.name(),
                seen.state,
                seen.error
            );
        }
        let since = |t: Option<Instant>, what: &str| -> Result<f64> {
            Ok(t.with_context(|| format!("job {id} sent no {what} event"))?
                .duration_since(t0)
                .as_secs_f64())
        };
        let times = JobTimes {
            started: since(seen.started, "job-started")?,
            first_frame: since(seen.first_frame, "frame")?,
            wall: seen.ended.duration_since(t0).as_secs_f64(),
            events: seen.events,
            follower_shortfall: shortfall,
            resyncs,
            cpu,
        };
        remove(&out)?;
        Ok(times)
    }

    /// `glint run --rig RIG --out DIR` as a subprocess: its wall time, spawn to exit, and
    /// the CPU used meanwhile (the subprocess's is `ours_s`).
    fn cli_run(&mut self) -> Result<(f64, CpuUse)> {
        let out = self.new_out("run-cli");
        let log_path = self.sessions.join("glint-run.log");
        let log = File::options()
            .create(true)
            .append(true)
            .open(&log_path)
            .with_context(|| format!("opening {}", log_path.display()))?;
        let before = CpuMark::take(self.daemon_pid);
        let t0 = Instant::now();
        let status = Command::new(&self.exe)
            .arg("run")
            .arg("--rig")
            .arg(&self.rig)
            .arg("--out")
            .arg(&out)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(log)
            .status()
            .context("starting glint run")?;
        let wall = t0.elapsed().as_secs_f64();
        let cpu = CpuMark::take(self.daemon_pid).since(&before);
        if !status.success() {
            bail!(
                "glint run exited with {status}; its output is in {}",
                log_path.display()
            );
        }
        remove(&out)?;
        Ok((wall, cpu))
    }
}

fn remove(dir: &Path) -> Result<()> {
    std::fs::remove_dir_all(dir).with_context(|| format!("removing {}", dir.display()))
}

/// The daemon this bench runs, as a child process; stopped with SIGTERM when dropped.
struct DaemonChild {
    child: Option<Child>,
    socket: PathBuf,
    log: PathBuf,
}

impl DaemonChild {
    /// Start `glint daemon` on the rig with its socket and state in `scratch`, and wait
    /// until the socket answers.
    fn start(exe: &Path, rig: &Path, scratch: &Path) -> Result<DaemonChild> {
        let socket = scratch.join("s/glint.sock");
        if socket.as_os_str().len() > 100 {
            bail!(
                "the socket path {} is too long for a Unix socket; give a shorter --out",
                socket.display()
            );
        }
        let log = scratch.join("daemon.log");
        let out = File::create(&log).with_context(|| format!("creating {}", log.display()))?;
        let child = Command::new(exe)
            .arg("daemon")
            .arg("--rig")
            .arg(rig)
            .arg("--socket")
            .arg(&socket)
            .arg("--state-dir")
            .arg(scratch.join("state"))
            .stdin(Stdio::null())
            .stdout(out.try_clone()?)
            .stderr(out)
            .spawn()
            .context("starting glint daemon")?;
        let mut d = DaemonChild {
            child: Some(child),
            socket,
            log,
        };
        let t0 = Instant::now();
        loop {
            if Client::connect(&d.socket).is_ok() {
                return Ok(d);
            }
            if let Some(st) = d.child.as_mut().and_then(|c| c.try_wait().ok().flatten()) {
                d.child = None;
                bail!("the daemon exited with {st}:\n{}", d.log_text());
            }
            if t0.elapsed() > Duration::from_secs(30) {
                bail!("the daemon did not answer within 30 s:\n{}", d.log_text());
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    fn pid(&self) -> u32 {
        self.child.as_ref().map_or(0, Child::id)
    }

    fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// SIGTERM, then wait for the exit (SIGKILL after 30 s); how it exited.
    fn stop(mut self) -> Result<String> {
        let Some(mut child) = self.child.take() else {
            bail!("the daemon is not running");
        };
        // SAFETY: kill(2) on the pid of our own child, which has not been reaped yet.
        unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGTERM) };
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(30) {
            if let Some(st) = child.try_wait()? {
                return Ok(st.to_string());
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        child.kill()?;
        let st = child.wait()?;
        Ok(format!(
            "{st} (SIGKILL: it did not exit within 30 s of SIGTERM)"
        ))
    }
}

impl Drop for DaemonChild {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            // SAFETY: as in `stop`.
            unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGTERM) };
            let t0 = Instant::now();
            while t0.elapsed() < Duration::from_secs(30) {
                if let Ok(Some(_)) = child.try_wait() {
                    return;
                }
                std::thread::sleep(Duration::from_millis(20));
            }
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// An event and the moment it was read.
type Stamped = (Instant, Value);

/// One connection following every event for the whole sitting, read on a thread that
/// stamps each event as it arrives.
struct Watcher {
    rx: Receiver<Stamped>,
    _thread: JoinHandle<()>,
}

/// A job as the watcher saw it.
struct Seen {
    started: Option<Instant>,
    first_frame: Option<Instant>,
    ended: Instant,
    state: String,
    error: String,
    events: u64,
    resyncs: u64,
}

impl Watcher {
    fn start(socket: &Path) -> Result<Watcher> {
        let mut c = Client::connect(socket)?;
        c.request(json!({"cmd": "follow"}))?;
        let (tx, rx) = mpsc::channel();
        let thread = std::thread::spawn(move || {
            while let Ok(e) = c.next_event() {
                if tx.send((Instant::now(), e)).is_err() {
                    break;
                }
            }
        });
        Ok(Watcher {
            rx,
            _thread: thread,
        })
    }

    /// Read events until job `id` ends.
    fn wait_job(&self, id: u64) -> Result<Seen> {
        let limit = Instant::now() + JOB_LIMIT;
        let (mut started, mut first_frame) = (None, None);
        let (mut events, mut resyncs) = (0, 0);
        loop {
            let left = limit.saturating_duration_since(Instant::now());
            let (t, e) = match self.rx.recv_timeout(left) {
                Ok(x) => x,
                Err(RecvTimeoutError::Timeout) => {
                    bail!("job {id} did not end within {} s", JOB_LIMIT.as_secs())
                }
                Err(RecvTimeoutError::Disconnected) => {
                    bail!("lost the daemon while job {id} ran (see its log)")
                }
            };
            let kind = e["event"].as_str().unwrap_or("");
            if kind == "resync" {
                resyncs += 1;
            }
            if e["job"].as_u64() != Some(id) {
                continue;
            }
            events += 1;
            match kind {
                "job-started" => started = started.or(Some(t)),
                "frame" => first_frame = first_frame.or(Some(t)),
                "job-ended" => {
                    return Ok(Seen {
                        started,
                        first_frame,
                        ended: t,
                        state: e["state"].as_str().unwrap_or("?").to_string(),
                        error: e["error"].as_str().unwrap_or("no reason given").to_string(),
                        events,
                        resyncs,
                    })
                }
                _ => {}
            }
        }
    }
}

/// An extra connection following every event on a thread of its own, reading (and
/// parsing) each one until the target job ends.
struct Follower(JoinHandle<Result<Followed>>);

struct Followed {
    /// The target job's events it read.
    events: u64,
    resyncs: u64,
}

impl Follower {
    /// Connect and follow every event (attached once this returns); the job to wait for
    /// is set in `target` once it is known.
    fn attach(socket: &Path, target: Arc<OnceLock<u64>>) -> Result<Follower> {
        let mut c = Client::connect(socket)?;
        c.request(json!({"cmd": "follow"}))?;
        Ok(Follower(std::thread::spawn(move || {
            let mut per_job: HashMap<u64, u64> = HashMap::new();
            let mut resyncs = 0;
            loop {
                let e = c.next_event()?;
                if e["event"] == "resync" {
                    resyncs += 1;
                }
                let Some(job) = e["job"].as_u64() else {
                    continue;
                };
                *per_job.entry(job).or_default() += 1;
                if e["event"] == "job-ended" && target.get() == Some(&job) {
                    return Ok(Followed {
                        events: per_job[&job],
                        resyncs,
                    });
                }
            }
        })))
    }

    fn join(self) -> Result<Followed> {
        self.0
            .join()
            .map_err(|_| anyhow::anyhow!("a follower thread panicked"))?
    }
}

/// CPU time at a moment, in clock ticks: the whole machine's busy time, the daemon's, and
/// this process's with its reaped children (the `glint run` subprocesses). Wall time on a
/// shared machine is only as good as the machine is quiet; this tells how quiet it was,
/// and CPU time per job is a figure others' work hardly moves.
struct CpuMark {
    at: Instant,
    machine: u64,
    daemon: u64,
    ours: u64,
}

/// CPU used between two marks.
#[derive(Clone, Copy)]
struct CpuUse {
    /// By the daemon, seconds.
    daemon_s: f64,
    /// By this process (its watcher and followers) and the subprocesses it waited for.
    ours_s: f64,
    /// By everything else, as a share of all the machine's cores over the interval.
    others: f64,
}

impl CpuMark {
    fn take(daemon_pid: u32) -> CpuMark {
        let machine = std::fs::read_to_string("/proc/stat")
            .ok()
            .and_then(|s| {
                let line = s.lines().next()?.strip_prefix("cpu ")?.to_string();
                // user nice system idle iowait irq softirq steal: all but idle and iowait.
                let v: Vec<u64> = line
                    .split_whitespace()
                    .filter_map(|x| x.parse().ok())
                    .collect();
                Some(v.iter().take(8).sum::<u64>() - v.get(3)? - v.get(4)?)
            })
            .unwrap_or(0);
        let proc_ticks = |path: &str, children: bool| -> u64 {
            std::fs::read_to_string(path)
                .ok()
                .and_then(|s| {
                    // Fields after the command name (which may hold spaces), from `state`:
                    // utime and stime are the 12th and 13th, cutime and cstime the next two.
                    let rest = &s[s.rfind(')')? + 1..];
                    let f: Vec<u64> = rest
                        .split_whitespace()
                        .skip(11)
                        .take(4)
                        .filter_map(|x| x.parse().ok())
                        .collect();
                    Some(f.iter().take(if children { 4 } else { 2 }).sum())
                })
                .unwrap_or(0)
        };
        CpuMark {
            at: Instant::now(),
            machine,
            daemon: proc_ticks(&format!("/proc/{daemon_pid}/stat"), false),
            ours: proc_ticks("/proc/self/stat", true),
        }
    }

    fn since(&self, before: &CpuMark) -> CpuUse {
        // SAFETY: sysconf has no preconditions.
        let hz = match unsafe { libc::sysconf(libc::_SC_CLK_TCK) } {
            n if n > 0 => n as f64,
            _ => 100.0,
        };
        let cores = std::fs::read_to_string("/proc/stat")
            .map(|s| {
                s.lines()
                    .filter(|l| l.starts_with("cpu") && !l.starts_with("cpu "))
                    .count()
            })
            .unwrap_or(1)
            .max(1);
        let daemon = self.daemon.saturating_sub(before.daemon);
        let ours = self.ours.saturating_sub(before.ours);
        let others = self
            .machine
            .saturating_sub(before.machine)
            .saturating_sub(daemon + ours);
        let wall = self.at.duration_since(before.at).as_secs_f64();
        CpuUse {
            daemon_s: daemon as f64 / hz,
            ours_s: ours as f64 / hz,
            others: if wall > 0.0 {
                (others as f64 / hz / (wall * cores as f64)).min(1.0)
            } else {
                0.0
            },
        }
    }
}

/// The CPU and its cores, and how busy the machine was.
struct Machine {
    cpu: String,
    cores: usize,
    /// The 1-minute load average before and after the sitting (others' work on the
    /// machine shows here, and in the spread of the figures).
    load: [Option<f64>; 2],
}

/// The 1-minute load average.
fn load_average() -> Option<f64> {
    std::fs::read_to_string("/proc/loadavg")
        .ok()?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

impl Machine {
    fn this() -> Machine {
        let cpu = std::fs::read_to_string("/proc/cpuinfo")
            .ok()
            .and_then(|s| {
                s.lines()
                    .find(|l| l.starts_with("model name"))
                    .and_then(|l| l.split_once(':'))
                    .map(|(_, v)| v.trim().to_string())
            })
            .unwrap_or_else(|| "unknown CPU".into());
        Machine {
            cpu,
            cores: std::thread::available_parallelism().map_or(0, |n| n.get()),
            load: [None, None],
        }
    }
}

/// Events published for the in-process figure of the fan-out.
const PUBLISH_EVENTS: usize = 20_000;

/// What [`glint::daemon::hub::Hub::publish`] costs the capture thread per event, seconds:
/// with `followers` followers of every event, each draining its queue on a thread of its
/// own (as the daemon's connection writers do), over `events` events shaped like a kept
/// frame's. The capture thread publishes every event itself and never waits for a
/// follower, so this is what the followers can cost it directly; the writers' own work runs
/// on other threads (its CPU is the daemon-CPU figure of the sitting).
fn publish_cost(followers: usize, events: usize) -> f64 {
    let hub = glint::daemon::hub::Hub::default();
    let drains: Vec<JoinHandle<u64>> = (0..followers)
        .map(|_| {
            let mut sub = hub.follow_all();
            std::thread::spawn(move || {
                let mut n = 0;
                while sub.rx.blocking_recv().is_some() {
                    n += 1;
                }
                n
            })
        })
        .collect();
    let fields =
        json!({"event": "frame", "kind": "tile", "exposure_us": 4000, "kept": 7, "total": 15});
    let t = Instant::now();
    for _ in 0..events {
        hub.publish(Some(1), fields.clone());
    }
    let per_event = t.elapsed().as_secs_f64() / events as f64;
    drop(hub);
    for d in drains {
        let _ = d.join();
    }
    per_event
}

/// Every figure of the sitting, one entry per repeat.
#[derive(Default)]
struct Results {
    /// (a) `add` to `job-started`, and to the first kept frame, no extra followers, s.
    started: Vec<f64>,
    first_frame: Vec<f64>,
    /// The same with the extra followers attached.
    started_with: Vec<f64>,
    first_frame_with: Vec<f64>,
    /// (b) capture jobs, `add` to `job-ended`, s, and with/without per repeat.
    capture_without: Vec<f64>,
    capture_with: Vec<f64>,
    fanout_ratio: Vec<f64>,
    /// The daemon's CPU per capture job without and with the followers, and the
    /// followers' own (this process's), s.
    capture_cpu_without: Vec<f64>,
    capture_cpu_with: Vec<f64>,
    followers_cpu: Vec<f64>,
    events_per_capture: u64,
    follower_shortfall: u64,
    resyncs: u64,
    /// (c) run jobs through the daemon, `glint run` subprocesses, s, and daemon/CLI.
    run_daemon: Vec<f64>,
    run_cli: Vec<f64>,
    run_ratio: Vec<f64>,
    /// CPU of a run: the daemon's for its job, the subprocess's for `glint run`, s.
    run_daemon_cpu: Vec<f64>,
    run_cli_cpu: Vec<f64>,
    /// Others' share of the machine during each timed job.
    others: Vec<f64>,
    /// `Hub::publish` per event with no follower and with the extra followers, s.
    publish_s: [f64; 2],
}

impl Results {
    /// The publishing cost the followers add to one capture, as a share of its wall time.
    fn publish_share(&self) -> f64 {
        let extra = (self.publish_s[1] - self.publish_s[0]).max(0.0);
        extra * self.events_per_capture as f64 / stats(&self.capture_without).0
    }
}

/// The mean of the paired ratios and the half-width of its 95% interval (Student's t
/// over the pairs; infinite with one pair).
fn interval(ratios: &[f64]) -> (f64, f64) {
    /// Two-sided 95% quantiles of Student's t for 1 to 30 degrees of freedom.
    const T95: [f64; 30] = [
        12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160,
        2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056,
        2.052, 2.048, 2.045, 2.042,
    ];
    let n = ratios.len();
    let mean = ratios.iter().sum::<f64>() / n as f64;
    if n < 2 {
        return (mean, f64::INFINITY);
    }
    let var = ratios.iter().map(|r| (r - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    let t = T95
        .get(n - 2)
        .copied()
        .unwrap_or(if n <= 60 { 2.0 } else { 1.96 });
    (mean, t * (var / n as f64).sqrt())
}

/// Whether the ratios meet `ratio <= 1 + goal`, by the 95% interval of their mean: met
/// when all of it is within the goal, not met when none of it is, and otherwise the
/// machine's noise is wider than the goal for this many repeats.
fn verdict(ratios: &[f64], goal: f64) -> &'static str {
    let (mean, half) = interval(ratios);
    if mean + half <= 1.0 + goal {
        "met"
    } else if mean - half > 1.0 + goal {
        "NOT met"
    } else {
        "inconclusive (noise wider than the goal: more --repeats, or a quieter machine)"
    }
}

/// `interval` as JSON (`null` half-width with one pair).
fn interval_json(ratios: &[f64]) -> Value {
    let (mean, half) = interval(ratios);
    json!({ "mean": mean, "half_width": half.is_finite().then_some(half) })
}

/// Median, smallest, largest.
fn stats(v: &[f64]) -> (f64, f64, f64) {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let n = s.len();
    let median = if n % 2 == 1 {
        s[n / 2]
    } else {
        (s[n / 2 - 1] + s[n / 2]) / 2.0
    };
    (median, s[0], s[n - 1])
}

impl Results {
    fn print(&self, m: &Machine, a: &DaemonBenchArgs, daemon_exit: &str) {
        println!(
            "glint bench daemon: rig {}, {} repeats in alternating order (median, min-max)",
            a.rig().display(),
            a.repeats
        );
        let load = |l: Option<f64>| l.map_or("?".into(), |l| format!("{l:.2}"));
        println!(
            "machine: {}, {} cores; load average {} before, {} after",
            m.cpu,
            m.cores,
            load(m.load[0]),
            load(m.load[1])
        );
        let ms = |label: &str, v: &[f64]| {
            let (med, lo, hi) = stats(v);
            println!(
                "  {label:<46} {:>9.1} ms  ({:.1}-{:.1})",
                med * 1e3,
                lo * 1e3,
                hi * 1e3
            );
        };
        let s = |label: &str, v: &[f64]| {
            let (med, lo, hi) = stats(v);
            println!("  {label:<46} {med:>9.3} s   ({lo:.3}-{hi:.3})");
        };
        let ratio = |label: &str, v: &[f64], goal: f64| {
            let (med, lo, hi) = stats(v);
            let (mean, half) = interval(v);
            println!("  {label:<46} {med:>9.3}     ({lo:.3}-{hi:.3})");
            println!(
                "  {:<46} {mean:>9.3} +- {half:.3} (95%); goal <= {:.2}: {}",
                "  mean of the pairs",
                1.0 + goal,
                verdict(v, goal)
            );
        };
        println!("(a) trigger latency of a capture job");
        ms("add -> job-started", &self.started);
        ms("add -> first kept frame", &self.first_frame);
        println!(
            "(b) event fan-out: capture job wall (add -> job-ended), {} events",
            self.events_per_capture
        );
        s("no extra followers", &self.capture_without);
        s(
            &format!("{} extra followers", a.followers),
            &self.capture_with,
        );
        ratio("ratio with / without", &self.fanout_ratio, FANOUT_GOAL);
        s(
            "daemon CPU per job, no extra followers",
            &self.capture_cpu_without,
        );
        s(
            &format!("daemon CPU per job, {} extra followers", a.followers),
            &self.capture_cpu_with,
        );
        s("the followers' own CPU (this process)", &self.followers_cpu);
        println!(
            "  {:<46} {:>9.2} us / {:.2} us per event (in-process, {PUBLISH_EVENTS} events)",
            format!("publishing: no follower / {}", a.followers),
            self.publish_s[0] * 1e6,
            self.publish_s[1] * 1e6
        );
        println!(
            "  {:<46} {:>9.4} %  of a capture's wall time; goal <= {:.0}%: {}",
            "the followers' cost on the capture thread",
            100.0 * self.publish_share(),
            100.0 * FANOUT_GOAL,
            if self.publish_share() <= FANOUT_GOAL {
                "met"
            } else {
                "NOT met"
            }
        );
        println!(
            "  every follower read every event: {}",
            if self.follower_shortfall == 0 && self.resyncs == 0 {
                "yes".to_string()
            } else {
                format!(
                    "NO ({} events short, {} resyncs)",
                    self.follower_shortfall, self.resyncs
                )
            }
        );
        println!("(c) run wall time");
        s("through the daemon (add -> job-ended)", &self.run_daemon);
        s("glint run subprocess (spawn -> exit)", &self.run_cli);
        ratio("ratio daemon / subprocess", &self.run_ratio, RUN_GOAL);
        s("CPU: the daemon's for the job", &self.run_daemon_cpu);
        s("CPU: the glint run subprocess's", &self.run_cli_cpu);
        let (med, _, hi) = stats(&self.others);
        println!(
            "others' use of the machine during the timed jobs: median {:.0}%, at most {:.0}% ({} of {} jobs above 10%)",
            med * 100.0,
            hi * 100.0,
            self.others.iter().filter(|&&x| x > 0.1).count(),
            self.others.len()
        );
        println!("daemon stopped by SIGTERM: {daemon_exit}");
    }

    fn json(&self, m: &Machine, a: &DaemonBenchArgs, command: &str, daemon_exit: &str) -> Value {
        let fig = |v: &[f64]| {
            let (median, min, max) = stats(v);
            json!({ "median": median, "min": min, "max": max, "each": v })
        };
        json!({
            "command": command,
            "cpu": m.cpu,
            "cores": m.cores,
            "load_average_1min": { "before": m.load[0], "after": m.load[1] },
            "rig": a.rig(),
            "repeats": a.repeats,
            "followers": a.followers,
            "trigger": {
                "add_to_started_s": fig(&self.started),
                "add_to_first_frame_s": fig(&self.first_frame),
                "with_followers": {
                    "add_to_started_s": fig(&self.started_with),
                    "add_to_first_frame_s": fig(&self.first_frame_with),
                },
            },
            "fanout": {
                "capture_without_s": fig(&self.capture_without),
                "capture_with_s": fig(&self.capture_with),
                "ratio": fig(&self.fanout_ratio),
                "goal_ratio_max": 1.0 + FANOUT_GOAL,
                "ratio_mean_ci95": interval_json(&self.fanout_ratio),
                "verdict": verdict(&self.fanout_ratio, FANOUT_GOAL),
                "daemon_cpu_without_s": fig(&self.capture_cpu_without),
                "daemon_cpu_with_s": fig(&self.capture_cpu_with),
                "followers_cpu_s": fig(&self.followers_cpu),
                "events_per_capture": self.events_per_capture,
                "publish_s_per_event": { "no_follower": self.publish_s[0], "followers": self.publish_s[1] },
                "publish_share_of_capture": self.publish_share(),
                "follower_events_short": self.follower_shortfall,
                "resyncs": self.resyncs,
            },
            "run": {
                "daemon_s": fig(&self.run_daemon),
                "cli_s": fig(&self.run_cli),
                "ratio": fig(&self.run_ratio),
                "goal_ratio_max": 1.0 + RUN_GOAL,
                "ratio_mean_ci95": interval_json(&self.run_ratio),
                "verdict": verdict(&self.run_ratio, RUN_GOAL),
                "daemon_cpu_s": fig(&self.run_daemon_cpu),
                "cli_cpu_s": fig(&self.run_cli_cpu),
            },
            "others_machine_share": fig(&self.others),
            "daemon_exit": daemon_exit,
        })
    }
}
