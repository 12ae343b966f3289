//! `glint capture`: the capture alone, its progress display, and the stop flag that
//! Ctrl-C, SIGTERM and SIGHUP set.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use clap::Args;
use glint::capture::{self, Event, Limits, Plan};
use glint::{devices, rig};
use indicatif::{ProgressBar, ProgressStyle};

use super::default_out;

#[derive(Args)]
pub struct CaptureArgs {
    /// The rig file (TOML) describing camera, lamp, geometry and bracket.
    #[arg(long, value_name = "FILE")]
    pub rig: PathBuf,
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

pub fn cmd_capture(a: CaptureArgs) -> Result<ExitCode> {
    let loaded = super::load_capture_rig(&a.rig)?;
    let r = &loaded.rig;
    let plan = Plan::for_rig(r);
    let out = a.out.unwrap_or_else(|| default_out(&r.rig.name));
    if a.dry_run {
        return dry_run(&loaded, &plan, &out, a.json);
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
    if a.json {
        println!("{}", rec.summary_json());
    } else {
        println!("{}", rec.summary_text());
        println!("Check it with: glint session verify {}", rec.dir.display());
    }
    Ok(ExitCode::SUCCESS)
}

/// The dry run of `glint capture` and `glint run`: the plan, its time and disk use, and
/// every problem found without opening a device (the plan against the rig's limits, the
/// resources, and whether this build has the rig's backends).
pub(crate) fn dry_run(
    loaded: &rig::LoadedRig,
    plan: &Plan,
    out: &std::path::Path,
    json: bool,
) -> Result<ExitCode> {
    let r = &loaded.rig;
    let backends = devices::check_backends(r);
    let mut problems = backends.problems.clone();
    problems.extend(plan.check(&Limits::from_rig(r)));
    problems.extend(plan.check_resources(r, out));
    let warnings = backends.warnings;
    let est = plan.estimate(r);
    let disk = capture::Disk::at(out).ok();
    if json {
        println!(
            "{}",
            serde_json::json!({
                "rig": loaded.path, "plan": plan, "problems": problems, "warnings": warnings,
                "estimate": est, "duration": capture::human_duration(est.seconds), "out": out,
                "disk": disk,
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
        for w in &warnings {
            println!("warning: {w}");
        }
        for p in &problems {
            println!("problem: {p}");
        }
    }
    Ok(if problems.is_empty() {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
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
