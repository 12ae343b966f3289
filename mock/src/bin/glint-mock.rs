//! `glint-mock`: the simulated lab as hardware other programs can use.
//!
//! `glint-mock v4l2 --rig RIG -- CMD ARGS...` builds the rig's simulated lab, makes the
//! rig's `camera.device` path a V4L2 camera inside CMD (through the preload library
//! `libglint_sim_v4l2.so`), links the rig's `lamp.port` path to the lab lamp's
//! pseudo-terminal, runs CMD, and removes what it made. `glint-mock scene place-tile` (or
//! `remove-tile`), run under it, has the lab's operator change the scene: a rig's
//! `[operator]` commands can name it.

use std::ffi::OsString;
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::os::unix::process::ExitStatusExt;
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};
use std::sync::atomic::{AtomicI32, Ordering};

use clap::{Parser, Subcommand, ValueEnum};
use glint_mock::encode::{EncodeOptions, Encoding};
use glint_mock::rigfile::RigFile;
use glint_mock::v4l2::{serve, ServeOptions, SimDevice};
use glint_mock::Lab;

/// The environment variables the launcher sets for CMD.
const ENV_DEVICE: &str = "GLINT_SIM_V4L2_DEVICE";
const ENV_SOCKET: &str = "GLINT_SIM_V4L2_SOCKET";
const ENV_LIB: &str = "GLINT_SIM_V4L2_LIB";
const LIB_NAME: &str = "libglint_sim_v4l2.so";
/// The stable name a udev rule would give the camera, beside the device.
pub const BY_ID: &str = "v4l/by-id/usb-Glint_Simulated_Camera_0001-video-index0";
/// What a placeholder file holds: how the launcher knows a stale one of its own.
const PLACEHOLDER: &str =
    "glint-mock: a simulated V4L2 device lives here while `glint-mock v4l2` runs\n";

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

#[derive(Subcommand)]
enum Cmd {
    /// Run CMD with the rig's camera as a simulated V4L2 device and its lamp on a pty.
    V4l2 {
        /// The rig file (camera.device is made a V4L2 camera; lamp.port, if any, the lamp).
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
        /// The program to run, and its arguments.
        #[arg(last = true, required = true)]
        cmd: Vec<OsString>,
    },
    /// Change the scene of the running launcher (from a program it runs).
    Scene {
        #[arg(value_enum)]
        action: SceneAction,
    },
}

#[derive(Clone, Copy, ValueEnum)]
enum SceneAction {
    PlaceTile,
    RemoveTile,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Cmd::V4l2 {
            rig,
            format,
            fast,
            mjpeg_keep_huffman,
            replay,
            cmd,
        } => run_v4l2(
            &rig,
            format.as_deref(),
            fast,
            mjpeg_keep_huffman,
            replay,
            &cmd,
        ),
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
        format!("no glint-mock launcher is running here ({ENV_SOCKET} is not set; run this under `glint-mock v4l2 --rig RIG -- ...`)")
    })?;
    let word = match action {
        SceneAction::PlaceTile => "place-tile",
        SceneAction::RemoveTile => "remove-tile",
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

fn run_v4l2(
    rig_path: &Path,
    format: Option<&str>,
    fast: bool,
    keep_huffman: bool,
    replay: Option<u32>,
    cmd: &[OsString],
) -> Result<u8, String> {
    let rig = RigFile::load(rig_path).map_err(|e| e.to_string())?;
    let device = rig.camera.device.clone().ok_or_else(|| {
        format!(
            "{}: [camera] has no device; name the path to make a V4L2 camera (e.g. device = \"/tmp/glint/video0\")",
            rig_path.display()
        )
    })?;
    let fmt_name = format
        .map(str::to_string)
        .or_else(|| rig.camera.pixel_format.clone())
        .unwrap_or_else(|| "YUYV".into());
    let encoding = Encoding::from_name(&fmt_name).ok_or_else(|| {
        format!("pixel format {fmt_name} is not simulated; use one of GREY, Y16, Y10, Y12, YUYV, RGB3, BGR3, MJPG")
    })?;
    let library = find_library()?;

    let mut cfg = rig.mock.clone().unwrap_or_default();
    // The launcher paces frames itself (see glint_mock::v4l2), at the camera's rate.
    cfg.sensor.realtime = false;
    cfg.sensor.fps = rig.camera.fps;
    let lab = Lab::new_with(
        &rig.scene_geometry(),
        &cfg,
        rig.camera.width,
        rig.camera.height,
        rig.camera.bit_depth,
        encoding.channels(),
        &rig.base,
    )
    .map_err(|e| format!("{}: {e}", rig_path.display()))?;
    let Lab {
        camera,
        lamp,
        operator,
    } = lab;

    // From here on a SIGINT/SIGTERM must not kill the launcher before it cleans up.
    install_signal_forwarding();
    let mut made = Made::default();
    // The camera: a placeholder file, and its stable name beside it.
    let device = absolute(Path::new(&device));
    if let Some(parent) = device.parent() {
        made.dir(parent)?;
    }
    claim(&device, "device placeholder", is_placeholder)?;
    // create_new: never replace a file that appeared since `claim` looked.
    std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&device)
        .and_then(|mut f| f.write_all(PLACEHOLDER.as_bytes()))
        .map_err(|e| format!("cannot create {}: {e}", device.display()))?;
    made.files.push(device.clone());
    let by_id = device.parent().unwrap_or(Path::new("/")).join(BY_ID);
    made.dir(by_id.parent().unwrap())?;
    claim(&by_id, "by-id link", |p| {
        std::fs::read_link(p).is_ok_and(|t| t == device)
    })?;
    std::os::unix::fs::symlink(&device, &by_id)
        .map_err(|e| format!("cannot create {}: {e}", by_id.display()))?;
    made.files.push(by_id);
    // The lamp: its port path links to the firmware's pseudo-terminal.
    if let Some(port) = &rig.lamp.port {
        let port = absolute(Path::new(port));
        if let Some(parent) = port.parent() {
            made.dir(parent)?;
        }
        claim(&port, "lamp link", |p| {
            std::fs::read_link(p).is_ok_and(|t| t.starts_with("/dev/pts/"))
        })?;
        std::os::unix::fs::symlink(lamp.port_path(), &port)
            .map_err(|e| format!("cannot create {}: {e}", port.display()))?;
        made.files.push(port);
    }
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
        encoding,
        rig.camera.fps,
        ServeOptions {
            fast,
            replay: replay.map(|n| n as usize),
            encode: EncodeOptions {
                keep_huffman,
                ..Default::default()
            },
        },
    );
    let _server = serve(listener, sim);

    let mut preload = library.into_os_string();
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
        .env(ENV_DEVICE, &device)
        .env(ENV_SOCKET, &socket)
        .env("PATH", path)
        .spawn()
        .map_err(|e| format!("cannot run {}: {e}", cmd[0].to_string_lossy()))?;
    CHILD.store(child.id() as i32, Ordering::SeqCst);
    let early = PENDING.swap(0, Ordering::SeqCst);
    if early != 0 {
        // SAFETY: signalling the child just started.
        unsafe { libc::kill(child.id() as i32, early) };
    }
    let status = child
        .wait()
        .map_err(|e| format!("waiting for {}: {e}", cmd[0].to_string_lossy()))?;
    made.clean();
    drop(lamp);
    Ok(match (status.code(), status.signal()) {
        (Some(c), _) => c.clamp(0, 255) as u8,
        (None, Some(s)) => (128 + s).clamp(0, 255) as u8,
        _ => 1,
    })
}
