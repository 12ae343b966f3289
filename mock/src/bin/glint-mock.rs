//! `glint-mock`: the simulated lab as hardware other programs can use.
//!
//! `glint-mock v4l2 --rig RIG -- CMD ARGS...` builds the rig's simulated lab, makes the
//! rig's `camera.device` path a V4L2 camera inside CMD (through the preload library
//! `libglint_sim_v4l2.so`), links the rig's `lamp.port` path to the lab lamp's
//! pseudo-terminal, runs CMD, and removes what it made. `glint-mock scene place-tile` (or
//! `remove-tile`), run under it, has the lab's operator change the scene: a rig's
//! `[operator]` commands can name it.
//!
//! `glint-mock lamp --link PATH` runs the lamp firmware alone, as its own process: its
//! pseudo-terminal linked at PATH, its light published at PATH.light (see
//! `glint_mock::lamp`), until SIGTERM, SIGINT or SIGHUP.
//!
//! `glint-mock lab --rig RIG -- CMD ARGS...` is `v4l2` with the lab as separate processes:
//! the lamp runs as `glint-mock lamp` (a child process, whose pid CMD finds in
//! `GLINT_MOCK_LAMP_PID`: killing it unplugs the lamp) and the camera is lit through its
//! light file.

use std::ffi::OsString;
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::os::unix::process::{CommandExt, ExitStatusExt};
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

use clap::{Args, Parser, Subcommand};
use glint_mock::config::{Faults, LampPreset, MockConfig};
use glint_mock::encode::{EncodeOptions, Encoding};
use glint_mock::lamp::LIGHT_MAGIC;
use glint_mock::rigfile::RigFile;
use glint_mock::v4l2::{serve, ServeOptions, SimDevice};
use glint_mock::{light_file_for, Lab, LampFirmware, LampPhysics, SimCamera, SimOperator};

/// The environment variables the launcher sets for CMD.
const ENV_DEVICE: &str = "GLINT_SIM_V4L2_DEVICE";
const ENV_SOCKET: &str = "GLINT_SIM_V4L2_SOCKET";
const ENV_LIB: &str = "GLINT_SIM_V4L2_LIB";
/// `glint-mock lab`: the lamp process's pid, and its command log if one was asked for.
const ENV_LAMP_PID: &str = "GLINT_MOCK_LAMP_PID";
const ENV_LAMP_LOG: &str = "GLINT_MOCK_LAMP_LOG";
const LIB_NAME: &str = "libglint_sim_v4l2.so";
/// The stable name a udev rule would give the camera, beside the device.
pub const BY_ID: &str = "v4l/by-id/usb-Glint_Simulated_Camera_0001-video-index0";
/// What a placeholder file holds: how the launcher knows a stale one of its own.
const PLACEHOLDER: &str =
    "glint-mock: a simulated V4L2 device lives here while `glint-mock v4l2` runs\n";
/// How long `lab` waits for the lamp process to link its port.
const LAMP_START: Duration = Duration::from_secs(5);
/// How long `lab` gives the lamp process to end after SIGTERM before it kills it.
const LAMP_STOP: Duration = Duration::from_secs(2);

#[derive(Parser)]
#[command(
    name = "glint-mock",
    version,
    about = "Glint's simulated lab as hardware"
)]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

/// How the simulated camera is served (`v4l2` and `lab`).
#[derive(Args)]
struct CameraArgs {
    /// The rig file (camera.device is made a V4L2 camera; lamp.port the lamp's port).
    #[arg(long)]
    rig: PathBuf,
    /// Pixel format to start with (GREY, Y16, Y10, Y12, YUYV, RGB3, BGR3, MJPG);
    /// default: the rig's camera.pixel_format, else YUYV.
    #[arg(long)]
    format: Option<String>,
    /// Deliver frames as fast as they are made rather than at the camera's frame rate.
    #[arg(long)]
    fast: bool,
    /// Keep the Huffman tables (DHT) in MJPG frames (default: stripped, as UVC cameras do).
    #[arg(long)]
    mjpeg_keep_huffman: bool,
    /// For throughput benchmarks: after N frames of one state (exposure, scene, lamp),
    /// replay those N frames instead of making new ones, so the simulator keeps up with
    /// high frame rates on a small machine. Their noise repeats every N frames; a new
    /// state is made afresh (without the sensor's exposure latency once replaying).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=1000))]
    replay: Option<u32>,
}

/// Reply numbers, 1-based, comma-separated (`1,3`); empty: none.
#[derive(Debug, Clone)]
struct ReplyList(Vec<u32>);

fn reply_list(s: &str) -> Result<ReplyList, String> {
    if s.trim().is_empty() {
        return Ok(ReplyList(Vec::new()));
    }
    s.split(',')
        .map(|n| match n.trim().parse::<u32>() {
            Ok(v) if v >= 1 => Ok(v),
            _ => Err(format!(
                "`{}` is not a reply number (replies count from 1: e.g. 1,3)",
                n.trim()
            )),
        })
        .collect::<Result<Vec<_>, _>>()
        .map(ReplyList)
}

fn preset(s: &str) -> Result<LampPreset, String> {
    LampPreset::from_name(s).ok_or_else(|| {
        format!(
            "the simulated lamp speaks {}",
            LampPreset::ALL.map(LampPreset::name).join(", ")
        )
    })
}

/// The lamp's line faults (`[mock.faults] lamp_*`); each flag overrides the rig's.
#[derive(Args, Clone, Default)]
struct LampFaultArgs {
    /// Echo every command line before handling it (lamp_echo).
    #[arg(long)]
    echo: bool,
    /// A line sent after every reply that is not an error, e.g. OK (lamp_trailer).
    #[arg(long, value_name = "S")]
    trailer: Option<String>,
    /// The terminator of every line sent, overriding the preset's (lamp_terminator).
    #[arg(long, value_parser = ["lf", "cr", "crlf", "none"])]
    terminator: Option<String>,
    /// Late replies come this long after their command arrived (lamp_late_ms).
    #[arg(long, value_name = "MS")]
    late_ms: Option<u64>,
    /// The replies that are late, e.g. 1,3; none named: every reply (lamp_late_replies).
    #[arg(long, value_name = "LIST", value_parser = reply_list)]
    late_replies: Option<ReplyList>,
    /// Replies sent in two halves (lamp_split_replies).
    #[arg(long, value_name = "LIST", value_parser = reply_list)]
    split_replies: Option<ReplyList>,
    /// The pause between the halves of a split reply (lamp_split_ms).
    #[arg(long, value_name = "MS")]
    split_ms: Option<u64>,
    /// Replies replaced by a long run of printable bytes (lamp_overlong_replies).
    #[arg(long, value_name = "LIST", value_parser = reply_list)]
    overlong_replies: Option<ReplyList>,
    /// The length of an overlong reply (lamp_overlong_bytes).
    #[arg(long, value_name = "N")]
    overlong_bytes: Option<usize>,
    /// Replies that are the preset's busy error, their commands not executed
    /// (lamp_error_replies).
    #[arg(long, value_name = "LIST", value_parser = reply_list)]
    error_replies: Option<ReplyList>,
    /// Replies garbled on the wire (lamp_garble_replies).
    #[arg(long, value_name = "LIST", value_parser = reply_list)]
    garble_replies: Option<ReplyList>,
    /// The lamp answers N commands, then nothing (lamp_silent_after).
    #[arg(long, value_name = "N")]
    silent_after: Option<u32>,
}

impl LampFaultArgs {
    fn apply(&self, f: &mut Faults) {
        f.lamp_echo |= self.echo;
        let set = |dst: &mut Vec<u32>, src: &Option<ReplyList>| {
            if let Some(l) = src {
                dst.clone_from(&l.0);
            }
        };
        if let Some(t) = &self.trailer {
            f.lamp_trailer = Some(t.clone());
        }
        if let Some(t) = &self.terminator {
            f.lamp_terminator = Some(t.clone());
        }
        if let Some(v) = self.late_ms {
            f.lamp_late_ms = v;
        }
        set(&mut f.lamp_late_replies, &self.late_replies);
        set(&mut f.lamp_split_replies, &self.split_replies);
        if let Some(v) = self.split_ms {
            f.lamp_split_ms = v;
        }
        set(&mut f.lamp_overlong_replies, &self.overlong_replies);
        if let Some(v) = self.overlong_bytes {
            f.lamp_overlong_bytes = v;
        }
        set(&mut f.lamp_error_replies, &self.error_replies);
        set(&mut f.lamp_garble_replies, &self.garble_replies);
        if let Some(v) = self.silent_after {
            f.lamp_silent_after = Some(v);
        }
    }

    /// The same flags, for the command line of a `glint-mock lamp`.
    fn to_args(&self) -> Vec<OsString> {
        let mut a: Vec<OsString> = Vec::new();
        let mut put = |flag: &str, v: String| {
            a.push(flag.into());
            a.push(v.into());
        };
        let list = |l: &ReplyList| l.0.iter().map(u32::to_string).collect::<Vec<_>>().join(",");
        if let Some(t) = &self.trailer {
            put("--trailer", t.clone());
        }
        if let Some(t) = &self.terminator {
            put("--terminator", t.clone());
        }
        if let Some(v) = self.late_ms {
            put("--late-ms", v.to_string());
        }
        for (flag, l) in [
            ("--late-replies", &self.late_replies),
            ("--split-replies", &self.split_replies),
            ("--overlong-replies", &self.overlong_replies),
            ("--error-replies", &self.error_replies),
            ("--garble-replies", &self.garble_replies),
        ] {
            if let Some(l) = l {
                put(flag, list(l));
            }
        }
        if let Some(v) = self.split_ms {
            put("--split-ms", v.to_string());
        }
        if let Some(v) = self.overlong_bytes {
            put("--overlong-bytes", v.to_string());
        }
        if let Some(v) = self.silent_after {
            put("--silent-after", v.to_string());
        }
        if self.echo {
            a.push("--echo".into());
        }
        a
    }
}

/// The flag that sets a `[mock]` key, for messages.
fn flag_of(key: &str) -> Option<&'static str> {
    Some(match key {
        "lamp.identity" => "--identity",
        "lamp.warmup_ms" => "--warmup-ms",
        "lamp.command_log" => "--log",
        "faults.lamp_trailer" => "--trailer",
        "faults.lamp_terminator" => "--terminator",
        "faults.lamp_late_ms" => "--late-ms",
        "faults.lamp_late_replies" => "--late-replies",
        "faults.lamp_split_replies" => "--split-replies",
        "faults.lamp_split_ms" => "--split-ms",
        "faults.lamp_overlong_replies" => "--overlong-replies",
        "faults.lamp_overlong_bytes" => "--overlong-bytes",
        "faults.lamp_error_replies" => "--error-replies",
        "faults.lamp_garble_replies" => "--garble-replies",
        _ => return None,
    })
}

#[derive(Args)]
struct LampArgs {
    /// Where to link the lamp's port (a pseudo-terminal); its light file is PATH.light.
    #[arg(long, value_name = "PATH")]
    link: PathBuf,
    /// Take the lamp's settings from this rig's [mock] section (warm-up, identity, faults,
    /// preset) and its [lamp.protocol] preset; the flags below override them.
    #[arg(long)]
    rig: Option<PathBuf>,
    /// The protocol the firmware speaks.
    #[arg(long, value_parser = preset, value_name = "glint|lumencor|coolled")]
    preset: Option<LampPreset>,
    /// Append every command line received to FILE (created if missing).
    #[arg(long, value_name = "FILE")]
    log: Option<PathBuf>,
    /// What `*IDN?` answers (glint preset).
    #[arg(long, value_name = "S")]
    identity: Option<String>,
    /// The lamp's warm-up after it is switched on, ms.
    #[arg(long, value_name = "N")]
    warmup_ms: Option<u64>,
    #[command(flatten)]
    faults: LampFaultArgs,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run CMD with the rig's camera as a simulated V4L2 device and its lamp on a pty.
    V4l2 {
        #[command(flatten)]
        camera: CameraArgs,
        /// The program to run, and its arguments.
        #[arg(last = true, required = true)]
        cmd: Vec<OsString>,
    },
    /// Run the lamp firmware as its own process, its port linked at --link, until
    /// SIGTERM, SIGINT or SIGHUP.
    Lamp(LampArgs),
    /// Run CMD with the lab as separate processes: the rig's lamp as `glint-mock lamp` at
    /// lamp.port, its camera as a simulated V4L2 device lit by that lamp.
    Lab {
        #[command(flatten)]
        camera: CameraArgs,
        /// The protocol the lamp speaks (default: the rig's [lamp.protocol] preset, else
        /// its [mock.lamp] preset, else glint).
        #[arg(long, value_parser = preset, value_name = "glint|lumencor|coolled")]
        preset: Option<LampPreset>,
        /// Append every command line the lamp receives to FILE (CMD finds it in
        /// GLINT_MOCK_LAMP_LOG).
        #[arg(long, value_name = "FILE")]
        lamp_log: Option<PathBuf>,
        #[command(flatten)]
        faults: LampFaultArgs,
        /// The program to run, and its arguments.
        #[arg(last = true, required = true)]
        cmd: Vec<OsString>,
    },
    /// Change the scene of the running launcher (from a program it runs).
    Scene {
        #[command(subcommand)]
        action: SceneAction,
    },
}

#[derive(Clone, Copy, Subcommand)]
enum SceneAction {
    /// Put the tile on the grid at its outline.
    PlaceTile,
    /// Take the tile off so the whole grid shows.
    RemoveTile,
    /// Take the tile off, lift the chessboard off the floor and hold it in a pose: turned
    /// about its centre by TILT_X about the grid's x axis, then TILT_Y about y, then ROTATE
    /// about z, its centre lifted by LIFT (for the lens calibration).
    ShowBoard {
        #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
        tilt_x_deg: f64,
        #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
        tilt_y_deg: f64,
        #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
        rotate_deg: f64,
        #[arg(long, default_value_t = 0.0)]
        lift_mm: f64,
        /// The pose's number in the plan (for the log; the pose is what the flags say).
        #[arg(long)]
        pose: Option<u32>,
    },
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) if e.use_stderr() => {
            // One line, as every error of the launcher: clap's first paragraph.
            let text = e.render().to_string();
            let said: Vec<&str> = text
                .lines()
                .map(str::trim)
                .take_while(|l| !l.is_empty() && !l.starts_with("Usage:"))
                .collect();
            let said = said.join(" ");
            eprintln!(
                "glint-mock: {} (see glint-mock help)",
                said.strip_prefix("error: ").unwrap_or(&said)
            );
            return ExitCode::from(2);
        }
        Err(e) => e.exit(),
    };
    let result = match cli.command {
        Cmd::V4l2 { camera, cmd } => run_v4l2(&camera, &cmd),
        Cmd::Lamp(args) => run_lamp(&args),
        Cmd::Lab {
            camera,
            preset,
            lamp_log,
            faults,
            cmd,
        } => run_lab(&camera, preset, lamp_log.as_deref(), &faults, &cmd),
        Cmd::Scene { action } => scene(action).map(|_| 0),
    };
    match result {
        Ok(code) => ExitCode::from(code),
        Err(e) => {
            eprintln!("glint-mock: {e}");
            ExitCode::from(2)
        }
    }
}

fn scene(action: SceneAction) -> Result<(), String> {
    let socket = std::env::var(ENV_SOCKET).map_err(|_| {
        format!("no glint-mock launcher is running here ({ENV_SOCKET} is not set; run this under `glint-mock v4l2 --rig RIG -- ...` or `glint-mock lab --rig RIG -- ...`)")
    })?;
    let word = match action {
        SceneAction::PlaceTile => "place-tile".to_string(),
        SceneAction::RemoveTile => "remove-tile".to_string(),
        SceneAction::ShowBoard {
            tilt_x_deg,
            tilt_y_deg,
            rotate_deg,
            lift_mm,
            ..
        } => {
            for (name, v, max) in [
                ("--tilt-x-deg", tilt_x_deg, 89.0),
                ("--tilt-y-deg", tilt_y_deg, 89.0),
                ("--rotate-deg", rotate_deg, 360.0),
                ("--lift-mm", lift_mm, 1e4),
            ] {
                if !(v.is_finite() && v.abs() <= max) {
                    return Err(format!("{name} {v}: must be within ±{max}"));
                }
            }
            format!("show-board {tilt_x_deg} {tilt_y_deg} {rotate_deg} {lift_mm}")
        }
    };
    let mut s = UnixStream::connect(&socket)
        .map_err(|e| format!("no glint-mock launcher answers on {socket}: {e}"))?;
    writeln!(s, "SCENE {word}").map_err(|e| format!("{socket}: {e}"))?;
    let mut reply = String::new();
    BufReader::new(&s)
        .read_line(&mut reply)
        .map_err(|e| format!("{socket}: {e}"))?;
    match reply.trim() {
        "OK" => Ok(()),
        other => Err(format!("the launcher refused `{word}`: {other}")),
    }
}

/// What the launcher made on disk, removed when it ends.
#[derive(Default)]
struct Made {
    files: Vec<PathBuf>,
    dirs: Vec<PathBuf>,
}

impl Made {
    /// Create `dir` and its missing ancestors, remembering them.
    fn dir(&mut self, dir: &Path) -> Result<(), String> {
        let mut missing = Vec::new();
        let mut d = Some(dir);
        while let Some(p) = d {
            if p.as_os_str().is_empty() || p.exists() {
                break;
            }
            missing.push(p.to_path_buf());
            d = p.parent();
        }
        std::fs::create_dir_all(dir)
            .map_err(|e| format!("cannot create {}: {e}", dir.display()))?;
        // Outermost first: `clean` removes them in the reverse order of their making.
        self.dirs.extend(missing.into_iter().rev());
        Ok(())
    }

    fn clean(&mut self) {
        for f in self.files.drain(..).rev() {
            let _ = std::fs::remove_file(&f);
        }
        for d in self.dirs.drain(..).rev() {
            let _ = std::fs::remove_dir(&d);
        }
    }
}

impl Drop for Made {
    fn drop(&mut self) {
        self.clean();
    }
}

/// Make `path` free for the launcher's own file, or refuse: only a stale thing of the
/// launcher's own (`stale` says which) is removed; anything else is the user's.
fn claim(path: &Path, what: &str, stale: impl Fn(&Path) -> bool) -> Result<(), String> {
    if std::fs::symlink_metadata(path).is_err() {
        return Ok(());
    }
    if stale(path) {
        return std::fs::remove_file(path)
            .map_err(|e| format!("cannot remove the stale {} {}: {e}", what, path.display()));
    }
    Err(format!(
        "{} exists and is not a stale glint-mock {what}; refusing to replace it (move it away or point the rig elsewhere)",
        path.display()
    ))
}

fn is_placeholder(p: &Path) -> bool {
    std::fs::symlink_metadata(p).is_ok_and(|m| m.is_file())
        && std::fs::read(p).is_ok_and(|c| c == PLACEHOLDER.as_bytes())
}

fn absolute(p: &Path) -> PathBuf {
    if p.is_absolute() {
        p.to_path_buf()
    } else {
        std::env::current_dir().unwrap_or_default().join(p)
    }
}

fn find_library() -> Result<PathBuf, String> {
    if let Some(p) = std::env::var_os(ENV_LIB) {
        let p = PathBuf::from(p);
        return if p.is_file() {
            Ok(absolute(&p))
        } else {
            Err(format!("{ENV_LIB}={} is not a file", p.display()))
        };
    }
    let exe = std::env::current_exe().map_err(|e| format!("cannot locate glint-mock: {e}"))?;
    let dir = exe.parent().unwrap_or(Path::new("."));
    for candidate in [dir.join(LIB_NAME), dir.join("..").join(LIB_NAME)] {
        if candidate.is_file() {
            return Ok(candidate);
        }
    }
    Err(format!(
        "cannot find {LIB_NAME} next to {} (build it with `cargo build -p glint-sim-v4l2`, or set {ENV_LIB})",
        exe.display()
    ))
}

static CHILD: AtomicI32 = AtomicI32::new(0);
/// A signal that came before CMD was running, forwarded once it runs.
static PENDING: AtomicI32 = AtomicI32::new(0);

extern "C" fn forward_signal(sig: libc::c_int, info: *mut libc::siginfo_t, _: *mut libc::c_void) {
    // SIGINT from the terminal (si_code SI_KERNEL) reaches CMD already: it is in the same
    // process group. One sent to the launcher alone (kill: si_code <= 0) is forwarded, as
    // SIGTERM and SIGHUP are; the launcher cleans up when CMD has ended.
    // SAFETY: the kernel's siginfo for this signal.
    let from_tty = sig == libc::SIGINT && !info.is_null() && unsafe { (*info).si_code } > 0;
    if from_tty {
        return;
    }
    let pid = CHILD.load(Ordering::SeqCst);
    if pid > 0 {
        // SAFETY: kill is async-signal-safe.
        unsafe { libc::kill(pid, sig) };
    } else {
        PENDING.store(sig, Ordering::SeqCst);
    }
}

fn install_signal_forwarding() {
    for sig in [libc::SIGINT, libc::SIGTERM, libc::SIGHUP] {
        // SAFETY: a handler that only reads atomics and calls kill.
        unsafe {
            let mut sa: libc::sigaction = std::mem::zeroed();
            sa.sa_sigaction = forward_signal as *const () as libc::sighandler_t;
            sa.sa_flags = libc::SA_SIGINFO | libc::SA_RESTART;
            libc::sigemptyset(&mut sa.sa_mask);
            libc::sigaction(sig, &sa, std::ptr::null_mut());
        }
    }
}

fn is_pts_link(p: &Path) -> bool {
    std::fs::read_link(p).is_ok_and(|t| t.starts_with("/dev/pts/"))
}

fn is_light_file(p: &Path) -> bool {
    std::fs::symlink_metadata(p).is_ok_and(|m| m.is_file())
        && std::fs::File::open(p).is_ok_and(|f| {
            let mut head = Vec::new();
            std::io::Read::read_to_end(
                &mut std::io::Read::take(f, LIGHT_MAGIC.len() as u64),
                &mut head,
            )
            .is_ok()
                && head == LIGHT_MAGIC.as_bytes()
        })
}

/// CMD's exit status as the launcher's: its code, or 128 + the signal that ended it.
fn exit_code(status: ExitStatus) -> u8 {
    match (status.code(), status.signal()) {
        (Some(c), _) => c.clamp(0, 255) as u8,
        (None, Some(s)) => (128 + s).clamp(0, 255) as u8,
        _ => 1,
    }
}

/// What the launchers (`v4l2`, `lab`) take from the rig before anything runs.
struct Launch {
    rig: RigFile,
    rig_path: PathBuf,
    /// The camera's device path, absolute.
    device: PathBuf,
    encoding: Encoding,
    library: PathBuf,
    opts: ServeOptions,
}

impl Launch {
    fn new(args: &CameraArgs) -> Result<Launch, String> {
        let rig_path = &args.rig;
        let rig = RigFile::load(rig_path).map_err(|e| e.to_string())?;
        let device = rig.camera.device.clone().ok_or_else(|| {
            format!(
                "{}: [camera] has no device; name the path to make a V4L2 camera (e.g. device = \"/tmp/glint/video0\")",
                rig_path.display()
            )
        })?;
        let fmt_name = args
            .format
            .clone()
            .or_else(|| rig.camera.pixel_format.clone())
            .unwrap_or_else(|| "YUYV".into());
        let encoding = Encoding::from_name(&fmt_name).ok_or_else(|| {
            format!("pixel format {fmt_name} is not simulated; use one of GREY, Y16, Y10, Y12, YUYV, RGB3, BGR3, MJPG")
        })?;
        let library = find_library()?;
        Ok(Launch {
            rig,
            rig_path: absolute(rig_path),
            device: absolute(Path::new(&device)),
            encoding,
            library,
            opts: ServeOptions {
                fast: args.fast,
                replay: args.replay.map(|n| n as usize),
                encode: EncodeOptions {
                    keep_huffman: args.mjpeg_keep_huffman,
                    ..Default::default()
                },
            },
        })
    }

    /// The lab's settings for the camera: the launcher paces frames itself (see
    /// glint_mock::v4l2), at the camera's rate.
    fn camera_config(&self) -> MockConfig {
        let mut cfg = self.rig.mock.clone().unwrap_or_default();
        cfg.sensor.realtime = false;
        cfg.sensor.fps = self.rig.camera.fps;
        cfg
    }

    /// The preset the rig's lamp speaks (see [`RigFile::lamp_preset`]).
    fn lamp_preset(&self) -> Result<LampPreset, String> {
        self.rig
            .lamp_preset()
            .map_err(|e| format!("{}: {e}", self.rig_path.display()))
    }

    /// The rig's lamp port, absolute.
    fn port(&self) -> Option<PathBuf> {
        self.rig
            .lamp
            .port
            .as_deref()
            .map(|p| absolute(Path::new(p)))
    }

    /// Make the device (a placeholder file and its by-id link), serve `camera` on a
    /// socket, run CMD with the environment the preload library needs (and `env`), and
    /// wait for it.
    fn serve_and_run(
        &self,
        made: &mut Made,
        camera: SimCamera,
        operator: SimOperator,
        env: &[(&str, OsString)],
        cmd: &[OsString],
    ) -> Result<ExitStatus, String> {
        let device = &self.device;
        // The camera: a placeholder file, and its stable name beside it.
        if let Some(parent) = device.parent() {
            made.dir(parent)?;
        }
        claim(device, "device placeholder", is_placeholder)?;
        // create_new: never replace a file that appeared since `claim` looked.
        std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(device)
            .and_then(|mut f| f.write_all(PLACEHOLDER.as_bytes()))
            .map_err(|e| format!("cannot create {}: {e}", device.display()))?;
        made.files.push(device.clone());
        let by_id = device.parent().unwrap_or(Path::new("/")).join(BY_ID);
        made.dir(by_id.parent().unwrap_or(Path::new("/")))?;
        claim(&by_id, "by-id link", |p| {
            std::fs::read_link(p).is_ok_and(|t| t == *device)
        })?;
        std::os::unix::fs::symlink(device, &by_id)
            .map_err(|e| format!("cannot create {}: {e}", by_id.display()))?;
        made.files.push(by_id);
        // The socket, in a private folder.
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.subsec_nanos())
            .unwrap_or(0);
        let sock_dir =
            std::env::temp_dir().join(format!("glint-mock-{}-{nanos:08x}", std::process::id()));
        std::fs::create_dir(&sock_dir)
            .map_err(|e| format!("cannot create {}: {e}", sock_dir.display()))?;
        made.dirs.push(sock_dir.clone());
        let socket = sock_dir.join("camera.sock");
        let listener = UnixListener::bind(&socket)
            .map_err(|e| format!("cannot listen on {}: {e}", socket.display()))?;
        made.files.push(socket.clone());
        let sim = SimDevice::new(
            camera,
            operator,
            self.encoding,
            self.rig.camera.fps,
            self.opts,
        );
        let _server = serve(listener, sim);

        let mut preload = self.library.clone().into_os_string();
        if let Some(old) = std::env::var_os("LD_PRELOAD").filter(|o| !o.is_empty()) {
            preload.push(":");
            preload.push(old);
        }
        let mut path = OsString::new();
        if let Some(dir) = std::env::current_exe()
            .ok()
            .and_then(|e| e.parent().map(Path::to_path_buf))
        {
            path.push(dir);
            path.push(":");
        }
        path.push(std::env::var_os("PATH").unwrap_or_default());
        let mut child = Command::new(&cmd[0])
            .args(&cmd[1..])
            .env("LD_PRELOAD", preload)
            .env(ENV_DEVICE, device)
            .env(ENV_SOCKET, &socket)
            .env("PATH", path)
            .envs(env.iter().map(|(k, v)| (k, v)))
            .spawn()
            .map_err(|e| format!("cannot run {}: {e}", cmd[0].to_string_lossy()))?;
        CHILD.store(child.id() as i32, Ordering::SeqCst);
        let early = PENDING.swap(0, Ordering::SeqCst);
        if early != 0 {
            // SAFETY: signalling the child just started.
            unsafe { libc::kill(child.id() as i32, early) };
        }
        child
            .wait()
            .map_err(|e| format!("waiting for {}: {e}", cmd[0].to_string_lossy()))
    }
}

fn run_v4l2(args: &CameraArgs, cmd: &[OsString]) -> Result<u8, String> {
    let launch = Launch::new(args)?;
    let rig = &launch.rig;
    let mut cfg = launch.camera_config();
    // The lamp firmware in this process speaks the rig's preset.
    cfg.lamp.preset = launch.lamp_preset()?;
    let lab = Lab::new_with(
        &rig.scene_geometry(),
        &cfg,
        rig.camera.width,
        rig.camera.height,
        rig.camera.bit_depth,
        launch.encoding.channels(),
        &rig.base,
    )
    .map_err(|e| format!("{}: {e}", launch.rig_path.display()))?;
    let Lab {
        camera,
        lamp,
        operator,
    } = lab;

    // From here on a SIGINT/SIGTERM must not kill the launcher before it cleans up.
    install_signal_forwarding();
    let mut made = Made::default();
    // The lamp: its port path links to the firmware's pseudo-terminal.
    if let Some(port) = launch.port() {
        if let Some(parent) = port.parent() {
            made.dir(parent)?;
        }
        claim(&port, "lamp link", is_pts_link)?;
        std::os::unix::fs::symlink(lamp.port_path(), &port)
            .map_err(|e| format!("cannot create {}: {e}", port.display()))?;
        made.files.push(port);
    }
    let status = launch.serve_and_run(&mut made, camera, operator, &[], cmd)?;
    made.clean();
    drop(lamp);
    Ok(exit_code(status))
}

fn run_lab(
    args: &CameraArgs,
    preset: Option<LampPreset>,
    lamp_log: Option<&Path>,
    faults: &LampFaultArgs,
    cmd: &[OsString],
) -> Result<u8, String> {
    let launch = Launch::new(args)?;
    let rig = &launch.rig;
    let port = launch.port().ok_or_else(|| {
        format!(
            "{}: [lamp] has no port; name the path to link the simulated lamp's port at (e.g. port = \"/tmp/glint/ttyLAMP0\")",
            launch.rig_path.display()
        )
    })?;
    if preset.is_none() {
        // The lamp process would refuse it: say so before anything starts.
        launch
            .lamp_preset()
            .map_err(|e| format!("{e} (or say which with --preset)"))?;
    }
    let cfg = launch.camera_config();
    let (camera, operator) = Lab::camera_lit_by(
        &rig.scene_geometry(),
        &cfg,
        rig.camera.width,
        rig.camera.height,
        rig.camera.bit_depth,
        launch.encoding.channels(),
        &rig.base,
        &light_file_for(&port),
    )
    .map_err(|e| format!("{}: {e}", launch.rig_path.display()))?;

    install_signal_forwarding();
    // A link left by a lamp that did not end cleanly goes first: the lamp's link appearing
    // is how the launcher knows it is ready.
    claim(&port, "lamp link", is_pts_link)?;
    let log = lamp_log.map(absolute);
    let mut lamp_args: Vec<OsString> = vec![
        "lamp".into(),
        "--rig".into(),
        launch.rig_path.clone().into(),
        "--link".into(),
        port.clone().into(),
    ];
    if let Some(p) = preset {
        lamp_args.extend(["--preset".into(), p.name().into()]);
    }
    if let Some(l) = &log {
        lamp_args.extend(["--log".into(), l.clone().into()]);
    }
    lamp_args.extend(faults.to_args());
    let mut lamp = LampProcess::start(&lamp_args, &port)?;

    let mut env = vec![(ENV_LAMP_PID, OsString::from(lamp.pid.to_string()))];
    if let Some(l) = &log {
        env.push((ENV_LAMP_LOG, l.clone().into_os_string()));
    }
    let mut made = Made::default();
    let status = launch.serve_and_run(&mut made, camera, operator, &env, cmd);
    // The camera's files go first: the lamp removes the folders it made once empty.
    made.clean();
    lamp.stop();
    Ok(exit_code(status?))
}

/// `glint-mock lamp` run by `lab`, as a child process in its own process group (a
/// terminal's Ctrl-C reaches CMD, and the launcher ends the lamp after CMD).
struct LampProcess {
    pid: i32,
    /// Set once the process has ended (before it is reaped, so its pid is never reused
    /// while the launcher may still signal it).
    ended: Arc<Mutex<bool>>,
    stopping: Arc<AtomicBool>,
    done: mpsc::Receiver<ExitStatus>,
    status: Option<ExitStatus>,
}

impl LampProcess {
    fn start(args: &[OsString], link: &Path) -> Result<LampProcess, String> {
        let exe = std::env::current_exe().map_err(|e| format!("cannot locate glint-mock: {e}"))?;
        let mut command = Command::new(&exe);
        command
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .process_group(0);
        // SAFETY: prctl is async-signal-safe; the lamp ends with the launcher, however the
        // launcher ends.
        unsafe {
            command.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
                Ok(())
            });
        }
        let mut child = command
            .spawn()
            .map_err(|e| format!("cannot start the lamp ({}): {e}", exe.display()))?;
        let pid = child.id() as i32;
        // Its stderr: passed on, and kept for the message if it dies.
        let said = Arc::new(Mutex::new(String::new()));
        let mut listener = None;
        if let Some(err) = child.stderr.take() {
            let said = Arc::clone(&said);
            listener = Some(std::thread::spawn(move || {
                for line in BufReader::new(err).lines() {
                    let Ok(line) = line else { break };
                    eprintln!("{line}");
                    let mut s = said.lock().unwrap_or_else(|e| e.into_inner());
                    if s.len() < 4096 {
                        if !s.is_empty() {
                            s.push_str("; ");
                        }
                        s.push_str(line.trim());
                    }
                }
            }));
        }
        let ended = Arc::new(Mutex::new(false));
        let stopping = Arc::new(AtomicBool::new(false));
        let (tx, done) = mpsc::channel();
        {
            let (ended, stopping) = (Arc::clone(&ended), Arc::clone(&stopping));
            let link = link.to_path_buf();
            std::thread::spawn(move || {
                // SAFETY: waitid with WNOWAIT leaves the child to be reaped by `wait`.
                unsafe {
                    let mut info: libc::siginfo_t = std::mem::zeroed();
                    while libc::waitid(
                        libc::P_PID,
                        pid as libc::id_t,
                        &mut info,
                        libc::WEXITED | libc::WNOWAIT,
                    ) != 0
                        && std::io::Error::last_os_error().raw_os_error() == Some(libc::EINTR)
                    {
                    }
                }
                *ended.lock().unwrap_or_else(|e| e.into_inner()) = true;
                let Ok(status) = child.wait() else { return };
                // A lamp that was killed leaves its link and light behind: an unplugged
                // lamp has neither.
                let light = light_file_for(&link);
                if is_pts_link(&link) {
                    let _ = std::fs::remove_file(&link);
                }
                if is_light_file(&light) {
                    let _ = std::fs::remove_file(&light);
                }
                if !stopping.load(Ordering::SeqCst) {
                    eprintln!(
                        "glint-mock: the lamp (pid {pid}) ended ({status}) while CMD ran: its port and its light are gone"
                    );
                }
                let _ = tx.send(status);
            });
        }
        let mut lamp = LampProcess {
            pid,
            ended,
            stopping,
            done,
            status: None,
        };
        let deadline = Instant::now() + LAMP_START;
        loop {
            if is_pts_link(link) {
                return Ok(lamp);
            }
            if let Ok(status) = lamp.done.try_recv() {
                lamp.stopping.store(true, Ordering::SeqCst);
                lamp.status = Some(status);
                // All it said, to its end.
                if let Some(l) = listener.take() {
                    let _ = l.join();
                }
                let said = said.lock().unwrap_or_else(|e| e.into_inner()).clone();
                return Err(format!(
                    "the lamp process ended ({status}) before it linked {}: {}",
                    link.display(),
                    if said.is_empty() {
                        "it said nothing"
                    } else {
                        &said
                    }
                ));
            }
            if Instant::now() >= deadline {
                lamp.stop();
                let said = said.lock().unwrap_or_else(|e| e.into_inner()).clone();
                return Err(format!(
                    "the lamp process did not link {} within {} s{}",
                    link.display(),
                    LAMP_START.as_secs(),
                    if said.is_empty() {
                        String::new()
                    } else {
                        format!(": {said}")
                    }
                ));
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    fn signal(&self, sig: libc::c_int) {
        let ended = self.ended.lock().unwrap_or_else(|e| e.into_inner());
        if !*ended {
            // SAFETY: the process has not been reaped (`ended` is set before it is, and
            // held here), so the pid is still the lamp's.
            unsafe { libc::kill(self.pid, sig) };
        }
    }

    /// End the lamp: SIGTERM, then SIGKILL if it has not ended after [`LAMP_STOP`].
    fn stop(&mut self) {
        if self.status.is_some() {
            return;
        }
        self.stopping.store(true, Ordering::SeqCst);
        self.signal(libc::SIGTERM);
        let status = match self.done.recv_timeout(LAMP_STOP) {
            Ok(s) => Some(s),
            Err(_) => {
                self.signal(libc::SIGKILL);
                self.done.recv_timeout(LAMP_STOP).ok()
            }
        };
        self.status = status;
    }
}

impl Drop for LampProcess {
    fn drop(&mut self) {
        self.stop();
    }
}

/// SIGINT, SIGTERM and SIGHUP, blocked in this thread (and the threads it starts) so that
/// [`wait_for_signal`] takes them.
fn block_signals() -> libc::sigset_t {
    // SAFETY: building a signal set and masking it in this thread.
    unsafe {
        let mut set: libc::sigset_t = std::mem::zeroed();
        libc::sigemptyset(&mut set);
        for sig in [libc::SIGINT, libc::SIGTERM, libc::SIGHUP] {
            libc::sigaddset(&mut set, sig);
        }
        libc::pthread_sigmask(libc::SIG_BLOCK, &set, std::ptr::null_mut());
        set
    }
}

fn wait_for_signal(set: &libc::sigset_t) -> libc::c_int {
    let mut sig: libc::c_int = 0;
    // SAFETY: sigwait on a set blocked in every thread of the process.
    while unsafe { libc::sigwait(set, &mut sig) } != 0 {}
    sig
}

/// The settings of `glint-mock lamp`: the rig's, then the flags.
fn lamp_config(args: &LampArgs) -> Result<MockConfig, String> {
    let mut cfg = match &args.rig {
        Some(path) => {
            let rig = RigFile::load(path).map_err(|e| e.to_string())?;
            let mut cfg = rig.mock.clone().unwrap_or_default();
            match (rig.lamp_preset(), args.preset) {
                (Ok(p), _) => cfg.lamp.preset = p,
                (Err(_), Some(_)) => {}
                (Err(e), None) => return Err(format!("{}: {e}", path.display())),
            }
            cfg
        }
        None => MockConfig::default(),
    };
    if let Some(p) = args.preset {
        cfg.lamp.preset = p;
    }
    if let Some(log) = &args.log {
        let log = absolute(log);
        cfg.lamp.command_log = Some(
            log.to_str()
                .ok_or_else(|| format!("--log {}: the path is not UTF-8", log.display()))?
                .to_string(),
        );
    }
    if let Some(id) = &args.identity {
        cfg.lamp.identity = id.clone();
    }
    if let Some(ms) = args.warmup_ms {
        cfg.lamp.warmup_ms = ms;
    }
    args.faults.apply(&mut cfg.faults);
    if let Some((key, msg)) = cfg.problems().into_iter().next() {
        let flag = flag_of(&key).map_or(String::new(), |f| format!(" ({f})"));
        return Err(format!("mock.{key}{flag}: {msg}"));
    }
    Ok(cfg)
}

fn run_lamp(args: &LampArgs) -> Result<u8, String> {
    let cfg = lamp_config(args)?;
    let link = absolute(&args.link);
    if link.file_name().is_none() {
        return Err(format!(
            "--link {}: name a file to link the lamp's port at (e.g. /tmp/glint/ttyLAMP0)",
            args.link.display()
        ));
    }
    let light = light_file_for(&link);
    // Before any thread starts: the signals that end the lamp wait for `wait_for_signal`.
    let signals = block_signals();
    let mut made = Made::default();
    if let Some(parent) = link.parent() {
        made.dir(parent)?;
    }
    claim(&link, "lamp link", is_pts_link)?;
    claim(&light, "light file", is_light_file)?;
    made.files.push(light.clone());
    let physics = Arc::new(LampPhysics::new(Duration::from_millis(cfg.lamp.warmup_ms)));
    let firmware =
        LampFirmware::spawn_with(&cfg.lamp, &cfg.faults, physics, cfg.seed, Some(&light))
            .map_err(|e| e.to_string())?;
    // The link appears last: a program waiting for it finds the lamp ready.
    std::os::unix::fs::symlink(firmware.port_path(), &link)
        .map_err(|e| format!("cannot create {}: {e}", link.display()))?;
    made.files.push(link.clone());
    eprintln!(
        "glint-mock lamp: a {} lamp controller on {}, linked at {} (its light at {}); pid {}",
        cfg.lamp.preset,
        firmware.port_path(),
        link.display(),
        light.display(),
        std::process::id()
    );
    wait_for_signal(&signals);
    // Unlink first (no program opens the port any more), then stop the firmware (it
    // publishes no more light), then remove the light and the folders.
    let _ = std::fs::remove_file(&link);
    drop(firmware);
    made.clean();
    Ok(0)
}
