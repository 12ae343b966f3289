//! The `glint` command line: argument parsing and dispatch; each command group lives in a
//! module of its own here (capture, hdr, calib, fit, run, checks, benchmarks).

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod bench;
mod bench_calib;
mod bench_daemon;
mod bench_fit;
mod bench_hdr;
#[cfg(feature = "v4l2")]
mod bench_v4l2;
mod calib;
mod capture;
mod checks;
mod daemon;
mod devices;
mod export;
mod fit;
mod hdr;
mod lamp;
mod run;

/// Glint measures how a material tile reflects light: it drives a camera and a lamp
/// through exposure brackets, records self-describing sessions, and turns them into
/// HDR radiance, a calibrated camera, fitted reflectance models with uncertainties, and a
/// validated report.
#[derive(Parser)]
#[command(
    name = "glint",
    version,
    propagate_version = true,
    after_help = "Start with the simulated lab, which needs no hardware:\n\n  glint run --rig rigs/mock.toml                 # capture, HDR, calibration, fit, validation, report\n  glint capture --rig rigs/mock.toml --dry-run   # the plan, time and disk use\n  glint session verify sessions/<the folder it printed>\n\nEvery stage is a command of its own (capture, hdr, calibrate, fit, validate, report), to re-run on a session.\n\nA rig left running: `glint daemon --rig FILE` holds it; `glint trigger run` queues a run and follows it (`glint jobs`, `glint follow JOB`, `glint abort`).\n\nDescribe your own rig by copying rigs/lab-example.toml; check it with `glint rig check FILE`."
)]
struct Cli {
    /// Log more (-v: info, -vv: debug, -vvv: trace); logs go to stderr.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Capture a session: lamp on, the exposure bracket, dark frames, the grid photo.
    ///
    /// The tile must be on the grid when the capture starts; you will be asked to remove
    /// it before the grid photo (the simulated lab does this itself).
    ///
    /// Ctrl-C, SIGTERM or SIGHUP stops after the current frame: lamp off (read back),
    /// session closed as `failed` naming the signal. A second signal stops now: the same,
    /// waiting at most one reply each for the lamp's OFF and its read-back. A third quits at
    /// once and says the lamp may still be on (`glint lamp off --rig FILE` switches it off).
    Capture(capture::CaptureArgs),
    /// Turn a folder of bracketed photos from any camera into a session.
    Import(hdr::ImportArgs),
    /// Recover the camera's response curve from a session's bracket and store it as the
    /// camera's profile (reused by every later `glint hdr` of that camera).
    Response(hdr::ResponseArgs),
    /// Merge a session's bracket into radiance: hdr/radiance.exr, variance.exr, mask.png.
    ///
    /// Uses the camera's stored response (profile), or recovers one from the session.
    Hdr(hdr::HdrArgs),
    /// Calibrate the camera from a photo of the chessboard grid (a session's grid frame,
    /// or --images): intrinsics, distortion and pose with standard deviations, in
    /// calib/camera.json (and, for OpenCV and ROS, calib/camera_opencv.yaml and
    /// calib/camera_info.yaml), and calib/corners.png (detected corners green,
    /// reprojected red, residuals in yellow drawn 50x).
    ///
    /// Tsai's method gives the start (no start values needed); Levenberg-Marquardt refines
    /// it; the lens model (principal point, aspect, radial and tangential terms) is the one
    /// with the lowest BIC.
    Calibrate(calib::CalibrateArgs),
    /// Calibrate the camera's lens once and keep it as the camera's lens profile beside the
    /// rig: the operator (a person, the rig's operator.show_board command, or the simulated
    /// lab) shows the board in several tilted poses, one grid photo each; the intrinsics
    /// with their covariance come from all of them together. Later `glint run`s hold this
    /// lens and fit only the pose from their grid photo.
    ///
    /// `--dry-run` lists the poses and the plan. The profile
    /// (profiles/<camera>-<W>x<H>.lens.json) is written only from a complete session that
    /// passes its checks (at least 4 views, RMS at most 1 px, f sd at most 0.5%, tilt varied
    /// about two axes), and an existing one is kept unless --replace-profile.
    Lens(calib::LensArgs),
    /// Fit reflectance models to a session's radiance (after glint hdr and glint
    /// calibrate): samples through the highlight, every candidate model with standard
    /// errors and 95% intervals, and the simplest model that explains the tile.
    ///
    /// No start values are needed: for each exponent n, kd and ks are solved in closed
    /// form; n is searched over 1..10000, then all parameters are polished together.
    Fit(fit::FitArgs),
    /// Fit the models to a photometric data set with known normals and lights (DiLiGenT's
    /// layout): fit on alternate photos, predict the others, report each model's error.
    FitPhotometric(fit::FitPhotometricArgs),
    /// Validate the fit (after glint fit): render the scene with every fitted model, map
    /// the radiance back to pixel values through the camera's response and compare with
    /// the photographs: RMSE beside the noise, PSNR, SSIM, relative radiance error;
    /// validation/validation.json and figures (photo beside renders, difference maps,
    /// the radiance profile through the highlight).
    Validate(run::ValidateArgs),
    /// Write the session's report: report/index.html with its figures beside it (the
    /// capture, HDR, calibration, fit with uncertainties, validation).
    Report(run::ReportArgs),
    /// Export a fitted model (glint fit) as a material other tools load: a Mitsuba 3
    /// `<bsdf>`, a glTF 2.0 material, or a plain JSON record (docs/export.md).
    ///
    /// Mitsuba's roughplastic and glTF's material are fitted to the model over the angles
    /// the tile was measured at, and the conversion's error is written and printed. A
    /// session in relative units needs --albedo for mitsuba and gltf.
    Export(export::ExportArgs),
    /// Everything in one command: capture, HDR, calibration, fit, validation, report.
    ///
    /// The HDR merge runs during the capture when the camera's response is known (its
    /// profile from an earlier run); otherwise it is recovered after the capture and stored.
    /// Every stage can be re-run alone on the session afterwards (glint hdr, calibrate,
    /// fit, validate, report).
    ///
    /// Signals during the capture act as for `glint capture` (a first stops after the frame,
    /// a second stops now, both with the lamp off and the session closed; a third quits at
    /// once); after the capture a signal stops the run before its next stage, naming the
    /// signal, and a second quits at once.
    Run(run::RunArgs),
    /// Run the daemon that holds the rig (`glint daemon --rig FILE`), or ask a running one
    /// for its status (`glint daemon status`) or to stop (`glint daemon stop`).
    ///
    /// The daemon opens the rig's devices once and keeps them (lamp off between jobs),
    /// takes jobs from `glint trigger` (or any client of its socket: see
    /// docs/daemon-protocol.md), runs them one at a time, and streams their progress. It
    /// runs in the foreground (systemd-friendly: docs/glint.service); SIGTERM or Ctrl-C
    /// aborts the running job cleanly (lamp off) and exits 0.
    Daemon(daemon::DaemonArgs),
    /// Queue a job on the daemon (run, capture, or process SESSION) and follow it to the end
    /// with `glint run`'s display and summary; exits non-zero if the job fails.
    Trigger(daemon::TriggerArgs),
    /// The daemon's queue and history (job, state, session, error).
    Jobs(daemon::JobsArgs),
    /// Follow a job of the daemon from its start to its end (answering its operator
    /// requests from this terminal).
    Follow(daemon::FollowArgs),
    /// Abort the daemon's running job: at its next frame, lamp off, session `failed: aborted`.
    Abort(daemon::AbortArgs),
    /// The daemon's queue: start, stop, remove or move jobs.
    #[command(subcommand)]
    Queue(daemon::QueueCommand),
    /// The cameras and serial ports of this machine, described so you can write a rig's
    /// [camera] and [lamp] sections from them.
    ///
    /// For each V4L2 camera (every /dev/video* node, or the PATHs given): its driver, card
    /// and bus, its stable name under /dev/v4l/by-id (use it for camera.device: /dev/videoN
    /// numbers change between plug-ins), every pixel format with its frame sizes and frame
    /// rates (camera.pixel_format, width, height, fps), every control with its type, range,
    /// default and current value and menu items (the names [camera.controls] takes, as
    /// v4l2-ctl prints them), and a suggested [camera] section: the best lossless format at
    /// the largest size, and the exposure limits of exposure_time_absolute (100 µs units).
    /// A UVC camera has more than one node; only the capture node is described in full.
    ///
    /// Then the serial ports (lamp.port), with their USB identity and stable names under
    /// /dev/serial/by-id.
    ///
    /// A Glint built without the V4L2 backend lists serial ports only; build it with
    /// `cargo build --release --features v4l2` (needs libclang-dev).
    ///
    /// Exit status 1 when a PATH given is not a camera or serial port Glint can open (it is
    /// still described, with the reason).
    #[command(after_help = "Examples:
  glint devices                                   # every camera and serial port
  glint devices /dev/video0                       # one camera
  glint devices /dev/v4l/by-id/usb-046d_HD_Pro_Webcam_C920-video-index0 --json")]
    Devices(devices::DevicesArgs),
    /// The rig's lamp alone: `glint lamp off --rig FILE` switches it off and reads it back
    /// (after a crash, or from a service's ExecStopPost).
    #[command(subcommand)]
    Lamp(lamp::LampCommand),
    /// Rig files: check one.
    #[command(subcommand)]
    Rig(RigCommand),
    /// Session directories: verify one.
    #[command(subcommand)]
    Session(SessionCommand),
    /// Benchmarks.
    #[command(subcommand)]
    Bench(BenchCommand),
}

#[derive(Subcommand)]
enum RigCommand {
    /// Validate a rig file and list every problem with its key and fix.
    Check {
        #[arg(value_name = "FILE")]
        file: PathBuf,
        /// Print the result as JSON.
        #[arg(long)]
        json: bool,
    },
}

#[derive(Subcommand)]
enum SessionCommand {
    /// Check a session: every frame present with a matching SHA-256, nothing unlisted.
    /// Exits non-zero when a file is missing or altered.
    Verify {
        #[arg(value_name = "DIR")]
        dir: PathBuf,
        /// Print the report as JSON.
        #[arg(long)]
        json: bool,
    },
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Simulated frames per second at 1280x960 (one core) and the wall time of a full
    /// `glint capture` of a rig (default rigs/mock.toml).
    Capture(bench::CaptureBenchArgs),
    /// HDR merge throughput (output megapixels/s) for a 12 MP, 7-exposure bracket, beside a
    /// memory-bandwidth baseline measured in the same run.
    Hdr(bench_hdr::HdrBenchArgs),
    /// Chessboard detection + single-view calibration time for one photo, one thread.
    Calib(bench_calib::CalibBenchArgs),
    /// Speed against accuracy of the fit: sample count (50..2000) x strategy (line, cross,
    /// rect, random) on a simulated tile, every candidate model timed on one core; writes
    /// bench-fit/fit_bench.csv and fit_bench.svg.
    Fit(bench_fit::FitBenchArgs),
    /// The daemon's overhead, in one sitting against a daemon it starts: trigger latency
    /// of a capture job, capture wall time with and without 10 extra followers, and a run
    /// through the daemon beside a `glint run` subprocess.
    Daemon(bench_daemon::DaemonBenchArgs),
    /// A rig's V4L2 camera streaming into Glint: frames/s sustained, dropped frames, and
    /// CPU per frame for decoding its pixel format and for encoding the session's PNG.
    #[cfg(feature = "v4l2")]
    V4l2(bench_v4l2::V4l2BenchArgs),
}

pub fn main() -> ExitCode {
    let cli = Cli::parse();
    let level = match cli.verbose {
        0 => "warn",
        1 => "info",
        2 => "debug",
        _ => "trace",
    };
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| level.into()),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .with_target(false)
        .init();
    let result = match cli.command {
        Command::Capture(a) => capture::cmd_capture(a),
        Command::Import(a) => hdr::cmd_import(a),
        Command::Response(a) => hdr::cmd_response(a),
        Command::Hdr(a) => hdr::cmd_hdr(a),
        Command::Calibrate(a) => calib::cmd_calibrate(a),
        Command::Lens(a) => calib::cmd_lens(a),
        Command::Fit(a) => fit::cmd_fit(a),
        Command::FitPhotometric(a) => fit::cmd_fit_photometric(a),
        Command::Validate(a) => run::cmd_validate(a),
        Command::Report(a) => run::cmd_report(a),
        Command::Export(a) => export::cmd_export(a),
        Command::Run(a) => run::cmd_run(a),
        Command::Daemon(a) => daemon::cmd_daemon(a),
        Command::Trigger(a) => daemon::cmd_trigger(a),
        Command::Jobs(a) => daemon::cmd_jobs(a),
        Command::Follow(a) => daemon::cmd_follow(a),
        Command::Abort(a) => daemon::cmd_abort(a),
        Command::Queue(q) => daemon::cmd_queue(q),
        Command::Devices(a) => devices::cmd_devices(a),
        Command::Lamp(c) => lamp::cmd_lamp(c),
        Command::Rig(RigCommand::Check { file, json }) => checks::cmd_rig_check(&file, json),
        Command::Session(SessionCommand::Verify { dir, json }) => {
            checks::cmd_session_verify(&dir, json)
        }
        Command::Bench(BenchCommand::Capture(a)) => bench::capture(a),
        Command::Bench(BenchCommand::Hdr(a)) => bench_hdr::hdr(a),
        Command::Bench(BenchCommand::Calib(a)) => bench_calib::bench_calib(a),
        Command::Bench(BenchCommand::Fit(a)) => bench_fit::fit_bench(a),
        Command::Bench(BenchCommand::Daemon(a)) => bench_daemon::daemon_bench(a),
        #[cfg(feature = "v4l2")]
        Command::Bench(BenchCommand::V4l2(a)) => bench_v4l2::v4l2(a),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {}", error_line(&e));
            ExitCode::FAILURE
        }
    }
}

/// An error and its causes on one line, as `{:#}` joins them (`message: cause: cause`),
/// except that a cause whose text the line already holds is left out. Many errors name
/// their cause in their own message (`cannot read rig file X: No such file or directory`)
/// and also give it as their `source()`, so that a library caller can reach it; printing
/// the whole chain repeated it ("…(os error 2): No such file or directory (os error 2)").
/// This is the one place the binary prints an error, so the rule holds for every command.
pub(crate) fn error_line(e: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if line.contains(&text) {
            continue;
        }
        if !line.is_empty() {
            line.push_str(": ");
        }
        line.push_str(&text);
    }
    line
}

/// Load a rig to capture with: refused, naming the file, where Glint cannot drive it (a
/// processing rig, [`glint::devices::not_drivable`]), before any plan is made.
pub(crate) fn load_capture_rig(path: &Path) -> anyhow::Result<glint::rig::LoadedRig> {
    let loaded = glint::rig::load(path)?;
    if let Some(why) = glint::devices::not_drivable(&loaded.rig) {
        anyhow::bail!("{}: {why}", path.display());
    }
    Ok(loaded)
}

pub(crate) fn default_out(name: &str) -> PathBuf {
    Path::new("sessions").join(glint::session::folder_name(name))
}
