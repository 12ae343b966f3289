//! `glint capture`: the capture alone, its progress display, and the stop flag that
//! Ctrl-C, SIGTERM and SIGHUP set (a first signal stops, a second hurries, a third quits).

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
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
    let stop = stop_on_ctrl_c(&a.rig)?;
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

/// The flag a capture checks, set by Ctrl-C, SIGTERM or SIGHUP:
/// - the first signal stops the capture after the current frame: lamp off (read back),
///   session closed as `failed` naming the signal;
/// - a second stops it now: the same, with the last `OFF` and its read-back waited for at
///   most one reply each (no retries); a capture's lamp is never left on by it;
/// - a third quits at once, saying that the lamp may still be on and how to switch it off
///   (`glint lamp off --rig RIG`).
///
/// Outside a capture (before it, or in the stages after it: the lamp is off and the session
/// closed), a second signal quits at once. Installed once per process; later calls return
/// the same flag. `rig` is named in the third signal's message.
pub(crate) fn stop_on_ctrl_c(rig: &std::path::Path) -> Result<Arc<AtomicBool>> {
    static STOP: std::sync::OnceLock<Arc<AtomicBool>> = std::sync::OnceLock::new();
    /// Signals received so far.
    static COUNT: AtomicUsize = AtomicUsize::new(0);
    /// The third signal's message, written before the handler is installed (a handler may
    /// not format or allocate).
    static QUIT_MSG: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();

    extern "C" fn on_signal(signal: libc::c_int) {
        // Only async-signal-safe work here: atomics, write(2), _exit(2).
        let Some(flag) = STOP.get() else { return };
        let write = |msg: &[u8]| {
            // SAFETY: write(2) on stderr with a valid buffer is async-signal-safe.
            unsafe { libc::write(2, msg.as_ptr().cast(), msg.len()) };
        };
        // Noted before the flag is set, so the capture that sees the flag names the signal.
        glint::capture::note_stop_signal(signal);
        let n = COUNT.fetch_add(1, Ordering::SeqCst) + 1;
        let capturing = glint::capture::capture_active();
        if n >= 3 || (n == 2 && !capturing) {
            if capturing {
                write(QUIT_MSG.get().map_or(
                    b"\nquitting at once: the lamp may still be on\n".as_slice(),
                    |m| m.as_slice(),
                ));
            } else {
                write(b"\nquitting at once (no capture is running: the lamp is off)\n");
            }
            // SAFETY: _exit is async-signal-safe.
            unsafe { libc::_exit(128 + signal) };
        }
        if n == 2 {
            glint::capture::note_hurry();
            flag.store(true, Ordering::SeqCst);
            write(b"\nstopping now: lamp off (one try), session closed as failed; a third signal quits at once and may leave the lamp on\n");
            return;
        }
        flag.store(true, Ordering::SeqCst);
        let msg: &[u8] = match signal {
            libc::SIGTERM => b"\nSIGTERM: stopping after the current frame, lamp off (a second signal stops now)\n",
            libc::SIGHUP => b"\nSIGHUP: stopping after the current frame, lamp off (a second signal stops now)\n",
            _ => b"\nstopping after the current frame, lamp off (Ctrl-C again stops now, a third time quits at once)\n",
        };
        write(msg);
    }

    if let Some(flag) = STOP.get() {
        return Ok(Arc::clone(flag));
    }
    let _ = QUIT_MSG.set(
        format!(
            "\nquitting at once: the lamp may still be on (switch it off with `glint lamp off --rig {}`) and the session may still say `capturing`\n",
            rig.display()
        )
        .into_bytes(),
    );
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
