//! The `glint` command line: a thin layer mapping sub-commands onto library calls.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::SystemTime;

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use glint::capture::{self, Event, Limits, Plan};
use glint::{devices, rig, session};
use indicatif::{ProgressBar, ProgressStyle};

mod bench;
mod bench_fit;
mod bench_hdr;
mod cli_calib;
mod cli_fit;
mod cli_hdr;
mod cli_run;

/// Glint measures how a material tile reflects light: it drives a camera and a lamp
/// through exposure brackets, records self-describing sessions, and turns them into
/// HDR radiance, a calibrated camera, fitted reflectance models with uncertainties, and a
/// validated report.
#[derive(Parser)]
#[command(
    name = "glint",
    version,
    propagate_version = true,
    after_help = "Start with the simulated lab, which needs no hardware:\n\n  glint run --rig rigs/mock.toml                 # capture, HDR, calibration, fit, validation, report\n  glint capture --rig rigs/mock.toml --dry-run   # the plan, time and disk use\n  glint session verify sessions/<the folder it printed>\n\nEvery stage is a command of its own (capture, hdr, calibrate, fit, validate, report), to re-run on a session.\n\nDescribe your own rig by copying rigs/lab-example.toml; check it with `glint rig check FILE`."
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
    Capture(CaptureArgs),
    /// Turn a folder of bracketed photos from any camera into a session.
    Import(cli_hdr::ImportArgs),
    /// Recover the camera's response curve from a session's bracket and store it as the
    /// camera's profile (reused by every later `glint hdr` of that camera).
    Response(cli_hdr::ResponseArgs),
    /// Merge a session's bracket into radiance: hdr/radiance.exr, variance.exr, mask.png.
    ///
    /// Uses the camera's stored response (profile), or recovers one from the session.
    Hdr(cli_hdr::HdrArgs),
    /// Calibrate the camera from a photo of the chessboard grid (a session's grid frame,
    /// or --images): intrinsics, distortion and pose with standard deviations, in
    /// calib/camera.json, and calib/corners.png (detected corners green, reprojected red,
    /// residuals in yellow drawn 50x).
    ///
    /// Tsai's method gives the start (no start values needed); Levenberg-Marquardt refines
    /// it; the lens model (principal point, aspect, radial and tangential terms) is the one
    /// with the lowest BIC.
    Calibrate(cli_calib::CalibrateArgs),
    /// Fit reflectance models to a session's radiance (after glint hdr and glint
    /// calibrate): samples through the highlight, every candidate model with standard
    /// errors and 95% intervals, and the simplest model that explains the tile.
    ///
    /// No start values are needed: for each exponent n, kd and ks are solved in closed
    /// form; n is searched over 1..10000, then all parameters are polished together.
    Fit(cli_fit::FitArgs),
    /// Fit the models to a photometric data set with known normals and lights (DiLiGenT's
    /// layout): fit on alternate photos, predict the others, report each model's error.
    FitPhotometric(cli_fit::FitPhotometricArgs),
    /// Validate the fit (after glint fit): render the scene with every fitted model, map
    /// the radiance back to pixel values through the camera's response and compare with
    /// the photographs: RMSE beside the noise, PSNR, SSIM, relative radiance error;
    /// validation/validation.json and figures (photo beside renders, difference maps,
    /// the radiance profile through the highlight).
    Validate(cli_run::ValidateArgs),
    /// Write the session's report: report/index.html with its figures beside it (the
    /// capture, HDR, calibration, fit with uncertainties, validation).
    Report(cli_run::ReportArgs),
    /// Everything in one command: capture, HDR, calibration, fit, validation, report.
    ///
    /// The HDR merge runs during the capture when the camera's response is known (its
    /// profile from an earlier run); otherwise it is recovered after the capture and stored.
    /// Every stage can be re-run alone on the session afterwards (glint hdr, calibrate,
    /// fit, validate, report).
    Run(cli_run::RunArgs),
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

#[derive(Args)]
struct CaptureArgs {
    /// The rig file (TOML) describing camera, lamp, geometry and bracket.
    #[arg(long, value_name = "FILE")]
    rig: PathBuf,
    /// Where to write the session; must not exist or be empty.
    /// [default: sessions/<rig name>-<UTC time>]
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Check the plan and estimate time and disk use, without opening any device.
    #[arg(long)]
    dry_run: bool,
    /// Print a JSON summary on stdout (progress stays on stderr).
    #[arg(long)]
    json: bool,
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
    Calib(cli_calib::CalibBenchArgs),
    /// Speed against accuracy of the fit: sample count (50..2000) x strategy (line, cross,
    /// rect, random) on a simulated tile, every candidate model timed on one core; writes
    /// bench-fit/fit_bench.csv and fit_bench.svg.
    Fit(bench_fit::FitBenchArgs),
}

fn main() -> ExitCode {
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
        Command::Capture(a) => cmd_capture(a),
        Command::Import(a) => cli_hdr::cmd_import(a),
        Command::Response(a) => cli_hdr::cmd_response(a),
        Command::Hdr(a) => cli_hdr::cmd_hdr(a),
        Command::Calibrate(a) => cli_calib::cmd_calibrate(a),
        Command::Fit(a) => cli_fit::cmd_fit(a),
        Command::FitPhotometric(a) => cli_fit::cmd_fit_photometric(a),
        Command::Validate(a) => cli_run::cmd_validate(a),
        Command::Report(a) => cli_run::cmd_report(a),
        Command::Run(a) => cli_run::cmd_run(a),
        Command::Rig(RigCommand::Check { file, json }) => cmd_rig_check(&file, json),
        Command::Session(SessionCommand::Verify { dir, json }) => cmd_session_verify(&dir, json),
        Command::Bench(BenchCommand::Capture(a)) => bench::capture(a),
        Command::Bench(BenchCommand::Hdr(a)) => bench_hdr::hdr(a),
        Command::Bench(BenchCommand::Calib(a)) => cli_calib::bench_calib(a),
        Command::Bench(BenchCommand::Fit(a)) => bench_fit::fit_bench(a),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

pub(crate) fn default_out(name: &str) -> PathBuf {
    let t = humantime::format_rfc3339_seconds(SystemTime::now()).to_string();
    let stamp: String = t.chars().filter(|c| c.is_ascii_alphanumeric()).collect();
    Path::new("sessions").join(format!("{name}-{stamp}"))
}

fn cmd_capture(a: CaptureArgs) -> Result<ExitCode> {
    let loaded = rig::load(&a.rig)?;
    let r = &loaded.rig;
    let plan = Plan::for_rig(r);
    let out = a.out.unwrap_or_else(|| default_out(&r.rig.name));
    if a.dry_run {
        let mut problems = plan.check(&Limits::from_rig(r));
        problems.extend(plan.check_resources(r, &out));
        let est = plan.estimate(r);
        let disk = capture::Disk::at(&out).ok();
        if a.json {
            println!(
                "{}",
                serde_json::json!({
                    "rig": loaded.path, "plan": plan, "problems": problems, "estimate": est,
                    "duration": capture::human_duration(est.seconds), "out": out, "disk": disk,
                })
            );
        } else {
            println!("Plan for rig `{}` ({}):", r.rig.name, loaded.path.display());
            for (i, s) in plan.steps.iter().enumerate() {
                println!("  {:>2}. {s}", i + 1);
            }
            println!(
                "Keeps {} frames (about {} more discarded while exposures settle); about {}; at most {} on disk{}.",
                est.frames_kept,
                est.frames_settling,
                capture::human_duration(est.seconds),
                capture::human_bytes(est.disk_bytes_max),
                disk.map(|d| format!(
                    " ({} free at {})",
                    capture::human_bytes(d.free_bytes),
                    d.path.display()
                ))
                .unwrap_or_default()
            );
            for p in &problems {
                println!("problem: {p}");
            }
        }
        return Ok(if problems.is_empty() {
            ExitCode::SUCCESS
        } else {
            ExitCode::FAILURE
        });
    }
    // Refused here too, before any device is opened.
    if let Some(p) = plan.check_resources(r, &out).into_iter().next() {
        bail!("the capture plan cannot run: {p}");
    }
    let devices = devices::open(&loaded).context("opening the rig's devices")?;
    let stop = stop_on_ctrl_c()?;
    let mut progress = Progress::new(plan.frames());
    let recorded = capture::record(&loaded, devices, &out, stop, &mut |e| progress.show(e));
    progress.finish();
    let rec = recorded?;
    let m = &rec.manifest;
    if a.json {
        println!(
            "{}",
            serde_json::json!({
                "session": rec.dir, "state": m.state, "frames": m.frames.len(),
                "discarded": rec.summary.discarded, "dropped": rec.summary.dropped,
                "latency_frames": rec.summary.latency_frames,
            })
        );
    } else {
        let count = |k| m.frames.iter().filter(|f| f.kind == k).count();
        println!(
            "Session {} complete: {} tile, {} dark, {} grid frames ({} discarded while settling; exposure latency {} frames).",
            rec.dir.display(),
            count(capture::FrameKind::Tile),
            count(capture::FrameKind::Dark),
            count(capture::FrameKind::Grid),
            rec.summary.discarded,
            rec.summary.latency_frames.map_or("unknown".into(), |k| k.to_string()),
        );
        println!("Check it with: glint session verify {}", rec.dir.display());
    }
    Ok(ExitCode::SUCCESS)
}

/// The flag a capture checks: the first Ctrl-C, SIGTERM or SIGHUP sets it (the capture
/// stops cleanly: lamp off, session closed as failed, naming the signal); a second one exits
/// at once. Installed once per process; later calls return the same flag.
pub(crate) fn stop_on_ctrl_c() -> Result<Arc<AtomicBool>> {
    static STOP: std::sync::OnceLock<Arc<AtomicBool>> = std::sync::OnceLock::new();

    extern "C" fn on_signal(signal: libc::c_int) {
        // Only async-signal-safe work here: atomics, write(2), _exit(2).
        let Some(flag) = STOP.get() else { return };
        // Noted before the flag is set, so the capture that sees the flag names the signal.
        glint::capture::note_stop_signal(signal);
        if flag.swap(true, Ordering::SeqCst) {
            // SAFETY: _exit is async-signal-safe.
            unsafe { libc::_exit(128 + signal) };
        }
        let msg: &[u8] = match signal {
            libc::SIGTERM => b"\nSIGTERM: stopping after the current frame, lamp off\n",
            libc::SIGHUP => b"\nSIGHUP: stopping after the current frame, lamp off\n",
            _ => b"\nstopping after the current frame (Ctrl-C again to quit at once)\n",
        };
        // SAFETY: write(2) on stderr with a valid buffer is async-signal-safe.
        unsafe { libc::write(2, msg.as_ptr().cast(), msg.len()) };
    }

    if let Some(flag) = STOP.get() {
        return Ok(Arc::clone(flag));
    }
    let stop = Arc::clone(STOP.get_or_init(|| Arc::new(AtomicBool::new(false))));
    for signal in [libc::SIGINT, libc::SIGTERM, libc::SIGHUP] {
        // SAFETY: a zeroed sigaction is valid; the handler only does async-signal-safe work.
        let installed = unsafe {
            let mut action: libc::sigaction = std::mem::zeroed();
            action.sa_sigaction = on_signal as extern "C" fn(libc::c_int) as libc::sighandler_t;
            action.sa_flags = libc::SA_RESTART;
            libc::sigemptyset(&mut action.sa_mask);
            libc::sigaction(signal, &action, std::ptr::null_mut())
        };
        if installed != 0 {
            return Err(std::io::Error::last_os_error())
                .with_context(|| format!("installing the handler for signal {signal}"));
        }
    }
    Ok(stop)
}

/// Progress on stderr: a bar on a terminal, plain lines otherwise.
struct Progress {
    bar: Option<ProgressBar>,
}

impl Progress {
    fn new(frames: u32) -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            let b = ProgressBar::new(frames as u64);
            b.set_style(
                ProgressStyle::with_template("{spinner} [{bar:30}] {pos}/{len} frames  {msg}")
                    .expect("valid template")
                    .progress_chars("=> "),
            );
            b
        });
        Progress { bar }
    }

    fn show(&mut self, e: &Event) {
        match (&self.bar, e) {
            (Some(b), Event::Step { description, .. }) => b.set_message(description.clone()),
            (Some(b), Event::Frame { kept, .. }) => b.set_position(*kept as u64),
            (Some(b), Event::Warning(w)) => b.println(format!("warning: {w}")),
            (Some(_), _) => {}
            (
                None,
                Event::Step {
                    index,
                    total,
                    description,
                },
            ) => eprintln!("[{index:>2}/{total}] {description}"),
            (None, Event::LampIdentity(id)) => eprintln!("        lamp: {id}"),
            (
                None,
                Event::Frame {
                    kind,
                    exposure_us,
                    kept,
                    total,
                },
            ) => {
                eprintln!(
                    "        kept {} frame at {exposure_us} µs ({kept}/{total})",
                    kind.as_str()
                )
            }
            (None, Event::Warning(w)) => eprintln!("warning: {w}"),
            (None, _) => {}
        }
    }

    fn finish(&self) {
        if let Some(b) = &self.bar {
            b.finish_and_clear();
        }
    }
}

fn cmd_rig_check(file: &Path, json: bool) -> Result<ExitCode> {
    match rig::load(file) {
        Ok(l) => {
            if json {
                println!(
                    "{}",
                    serde_json::json!({ "file": file, "ok": true, "problems": [] })
                );
            } else {
                let r = &l.rig;
                println!(
                    "{}: ok (rig `{}`: {:?} camera {}x{} {}-bit, {:?} lamp, {} exposures {}..{} µs)",
                    file.display(),
                    r.rig.name,
                    r.camera.backend,
                    r.camera.width,
                    r.camera.height,
                    r.camera.bit_depth,
                    r.lamp.backend,
                    r.bracket.exposures_us.len(),
                    r.bracket.exposures_us.first().unwrap_or(&0),
                    r.bracket.exposures_us.last().unwrap_or(&0)
                );
            }
            Ok(ExitCode::SUCCESS)
        }
        Err(e) => {
            let problems = e.problems();
            if json {
                println!(
                    "{}",
                    serde_json::json!({ "file": file, "ok": false, "problems": problems })
                );
            } else if let rig::RigError::Invalid { path, .. } = &e {
                for p in &problems {
                    println!("{}: {p}", path.display());
                }
            } else {
                println!("{e}");
            }
            Ok(ExitCode::FAILURE)
        }
    }
}

fn cmd_session_verify(dir: &Path, json: bool) -> Result<ExitCode> {
    if !dir.join("manifest.json").exists() {
        bail!(
            "{} has no manifest.json; give the session directory that `glint capture` printed",
            dir.display()
        );
    }
    let report = session::verify(dir)?;
    if json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        for p in &report.problems {
            println!("problem: {p}");
        }
        for w in &report.warnings {
            println!("note: {w}");
        }
        println!(
            "{}: {} frames, state {}, {}",
            dir.display(),
            report.frames,
            serde_json::to_value(report.state)?.as_str().unwrap_or("?"),
            if report.intact() {
                "all checksums match"
            } else {
                "DAMAGED"
            }
        );
    }
    Ok(if report.intact() {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}
