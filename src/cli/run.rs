//! `glint validate`, `glint report` and `glint run`.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::Result;
use clap::Args;
use glint::fit::model::Reflectance;
use glint::pipeline::{Progress, Stage};
use glint::validate::{self, ValidateEvent, ValidateOptions, ValidationReport};

#[derive(Args)]
pub struct ValidateArgs {
    /// A fitted session (after glint fit); writes SESSION/validation/.
    #[arg(value_name = "SESSION")]
    session: PathBuf,
    /// The exposure the figures show, µs [default: the one that shows the most of the
    /// tile unsaturated].
    #[arg(long, value_name = "US")]
    exposure_us: Option<f64>,
    /// Work on a session that is not complete (`capturing`: killed, or `failed`), with a
    /// warning.
    #[arg(long)]
    allow_incomplete: bool,
    /// Print validation.json on stdout.
    #[arg(long)]
    json: bool,
}

pub fn cmd_validate(a: ValidateArgs) -> Result<ExitCode> {
    super::hdr::check_session(&a.session)?;
    let start = Instant::now();
    let mut show = |e: ValidateEvent| eprintln!("[{:6.2} s] {}", start.elapsed().as_secs_f64(), e);
    let r = validate::run(
        &a.session,
        &ValidateOptions {
            exposure_us: a.exposure_us,
            allow_incomplete: a.allow_incomplete,
        },
        &mut show,
    )?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        print_validation(&r);
        println!("wrote {}", r.files.join(", "));
    }
    for w in &r.warnings {
        eprintln!("warning: {w}");
    }
    Ok(ExitCode::SUCCESS)
}

/// The table of `glint validate`.
pub(crate) fn print_validation(r: &ValidationReport) {
    println!(
        "validation over {} tile pixels, every exposure; pixel values compared where photo and render are both in the response's valid range",
        r.tile_pixels
    );
    println!(
        "  {:<13} {:>9} {:>9} {:>9} {:>9} {:>7} {:>13} {:>9}",
        "model", "readings", "RMSE", "noise", "PSNR dB", "SSIM", "radiance err", "mean z²"
    );
    for m in &r.models {
        println!(
            "{} {:<13} {:>9} {:>9.3} {:>9.3} {:>9.2} {:>7.4} {:>12.2}% {:>9.2}",
            if m.chosen { "*" } else { " " },
            m.model.name(),
            m.pixels.readings,
            m.pixels.rmse,
            m.pixels.noise_rmse,
            m.pixels.psnr_db,
            m.pixels.ssim,
            100.0 * m.radiance.relative_error,
            m.radiance.mean_z2
        );
    }
}

#[derive(Args)]
pub struct ReportArgs {
    /// A session; writes SESSION/report/index.html with its figures beside it, from
    /// whatever stages have run (missing ones are named, with their command).
    #[arg(value_name = "SESSION")]
    session: PathBuf,
    /// The speed/accuracy chart of `glint bench fit` to include.
    #[arg(long, value_name = "SVG", default_value = "bench-fit/fit_bench.svg")]
    bench_chart: PathBuf,
    /// Report on a session that is not complete (`capturing`: killed, or `failed`); the
    /// page says so at the top.
    #[arg(long)]
    allow_incomplete: bool,
    /// Also print the results as JSON on stdout (for scripts): the files written, the
    /// stages missing, and each stage's key figures (null where it has not run): HDR
    /// summary, calibration (intrinsics, RMS, camera centre with sd, OpenCV's arrays), the
    /// chosen model's parameters with sds and intervals, validation figures per model.
    #[arg(long)]
    json: bool,
}

pub fn cmd_report(a: ReportArgs) -> Result<ExitCode> {
    super::hdr::check_session(&a.session)?;
    let w = glint::report::write(
        &a.session,
        &glint::report::ReportOptions {
            bench_chart: Some(a.bench_chart),
            allow_incomplete: a.allow_incomplete,
        },
    )?;
    for w in &w.warnings {
        eprintln!("warning: {w}");
    }
    for m in &w.missing {
        eprintln!(
            "note: no {m} results yet (glint {m} {})",
            a.session.display()
        );
    }
    if a.json {
        let results = glint::report::results(&a.session)?;
        println!(
            "{}",
            serde_json::json!({
                "report": w.index, "files": w.files, "missing": w.missing,
                "warnings": w.warnings, "results": results,
            })
        );
    } else {
        println!("wrote {} ({} files)", w.index.display(), w.files.len());
    }
    Ok(ExitCode::SUCCESS)
}

#[derive(Args)]
pub struct RunArgs {
    /// The rig file (TOML); rigs/mock.toml runs the simulated lab.
    #[arg(long, value_name = "FILE")]
    rig: PathBuf,
    /// Where to write the session; must not exist or be empty.
    /// [default: sessions/<rig name>-<UTC time>]
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Hold the lens at an earlier calibration (a camera.json, or an OpenCV or ROS camera
    /// YAML); only the pose is fitted.
    /// Without it the camera's lens profile beside the rig (from `glint lens`) is held
    /// where there is one, and the run says so.
    #[arg(long, value_name = "CAMERA_JSON|YAML")]
    intrinsics: Option<PathBuf>,
    /// Ignore the camera's lens profile: fit the intrinsics from the one grid photo (their
    /// uncertainty, and the pose's, then allow for the principal point's offset).
    #[arg(long, conflicts_with = "intrinsics")]
    no_lens_profile: bool,
    /// Samples for the fit [default: 400 per 640 pixels of the image's longer side, at
    /// least 400: 800 at 1280x960] (see glint fit --help).
    #[arg(long, value_name = "N")]
    samples: Option<usize>,
    /// Where the fit's samples lie (see glint fit --help): the default cross through the
    /// highlight tells the paper's models apart; a broad lobe (n below about 20, GGX α
    /// above 0.3) is better measured over the tile's area, e.g. `--strategy rect
    /// --samples 2000`.
    #[arg(long, value_enum, default_value = "cross")]
    strategy: super::fit::StrategyArg,
    /// The speed/accuracy chart of `glint bench fit` to put in the report, where it exists.
    #[arg(long, value_name = "SVG", default_value = "bench-fit/fit_bench.svg")]
    bench_chart: PathBuf,
    /// Check the capture's plan and estimate its time and disk use, without opening any
    /// device (as `glint capture --dry-run`).
    #[arg(long)]
    dry_run: bool,
    /// Print the whole run's summary as JSON on stdout (progress stays on stderr).
    #[arg(long)]
    json: bool,
}

/// One progress display for every stage: a bar over the capture's frames and the five
/// later stages on a terminal, plain time-stamped lines otherwise.
pub(crate) struct RunProgress {
    bar: Option<indicatif::ProgressBar>,
    start: Instant,
    frames: u64,
    stage: Stage,
}

impl RunProgress {
    pub(crate) fn new(frames: u32) -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            // The capture's frames, then one step per later stage.
            let b = indicatif::ProgressBar::new(frames as u64 + Stage::ALL.len() as u64 - 1);
            b.set_style(
                indicatif::ProgressStyle::with_template(
                    "{spinner} {elapsed:>3} [{bar:30}] {prefix} {msg}",
                )
                .expect("valid template")
                .progress_chars("=> "),
            );
            b.enable_steady_tick(std::time::Duration::from_millis(120));
            b
        });
        RunProgress {
            bar,
            start: Instant::now(),
            frames: frames as u64,
            stage: Stage::Capture,
        }
    }

    fn line(&self, msg: &str) {
        match &self.bar {
            Some(b) => b.set_message(msg.to_string()),
            None => eprintln!(
                "[{:6.2} s] [{}/{} {}] {msg}",
                self.start.elapsed().as_secs_f64(),
                self.stage.number(),
                Stage::ALL.len(),
                self.stage.name()
            ),
        }
    }

    /// Draw one event: the same for `glint run` and for a daemon's job followed by
    /// `glint trigger` or `glint follow`.
    pub(crate) fn show(&mut self, e: &Progress) {
        match e {
            Progress::Stage { stage } => {
                self.stage = *stage;
                if let Some(b) = &self.bar {
                    b.set_prefix(format!(
                        "[{}/{} {}]",
                        stage.number(),
                        Stage::ALL.len(),
                        stage.name()
                    ));
                    b.set_message("");
                } else {
                    self.line("starting");
                }
            }
            Progress::StageDone { stage, seconds } => {
                if let Some(b) = &self.bar {
                    let done = self.frames + stage.number() as u64 - 1;
                    b.set_position(done);
                } else {
                    self.line(&format!("done in {seconds:.2} s"));
                }
            }
            Progress::Started { frames, .. } => {
                self.frames = *frames as u64;
                if let Some(b) = &self.bar {
                    b.set_length(*frames as u64 + Stage::ALL.len() as u64 - 1);
                }
            }
            Progress::Step { description, .. } => self.line(description),
            Progress::Frame {
                kind,
                exposure_us,
                kept,
                total,
            } => match &self.bar {
                Some(b) => b.set_position(*kept as u64),
                None => self.line(&format!(
                    "kept {} frame at {exposure_us} µs ({kept}/{total})",
                    kind.as_str()
                )),
            },
            Progress::Warning { message } => match &self.bar {
                Some(b) => b.println(format!("warning: {message}")),
                None => eprintln!("warning: {message}"),
            },
            Progress::Streamed { frames } => {
                self.line(&format!("{frames} tile frames merged during the capture"))
            }
            Progress::Hdr { message } | Progress::Validate { message } => self.line(message),
            Progress::LampIdentity { .. } | Progress::Discarded { .. } => {}
        }
    }

    /// A line of its own above the bar (or on stderr).
    pub(crate) fn println(&self, msg: &str) {
        match &self.bar {
            Some(b) => b.println(msg),
            None => eprintln!("{msg}"),
        }
    }

    pub(crate) fn finish(&self) {
        if let Some(b) = &self.bar {
            b.finish_and_clear();
        }
    }
}

pub fn cmd_run(a: RunArgs) -> Result<ExitCode> {
    use anyhow::{bail, Context};
    let loaded = super::load_capture_rig(&a.rig)?;
    let r = &loaded.rig;
    if let Some(p) = a
        .samples
        .and_then(|k| glint::fit::sample::count_problem(k, None))
    {
        bail!("--samples {p}");
    }
    let plan = glint::capture::Plan::for_rig(r);
    let out = a.out.unwrap_or_else(|| super::default_out(&r.rig.name));
    if a.dry_run {
        return super::capture::dry_run(&loaded, &plan, &out, a.json);
    }
    let mut opts = glint::pipeline::RunOptions {
        intrinsics: a
            .intrinsics
            .as_deref()
            .map(glint::calib::run::load_known)
            .transpose()?,
        no_lens_profile: a.no_lens_profile,
        ..Default::default()
    };
    opts.fit.sample.count = a.samples;
    opts.fit.sample.strategy = a.strategy.strategy();
    opts.report.bench_chart = Some(a.bench_chart);
    // A plan longer than a day or bigger than the free disk is refused before any device opens.
    if let Some(p) = plan.check_resources(r, &out).into_iter().next() {
        bail!("the capture plan cannot run: {p}");
    }
    let devices = glint::devices::open(&loaded).context("opening the rig's devices")?;
    let stop = super::capture::stop_on_ctrl_c(&a.rig)?;
    let mut progress = RunProgress::new(plan.frames());
    let result = glint::pipeline::run(&loaded, devices, &out, stop, &opts, &mut |e| {
        progress.show(&Progress::from(&e))
    });
    progress.finish();
    let s = result?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&s)?);
    } else {
        // The simulated lab knows the truth: say whether the run found it.
        let truth = glint::pipeline::truth_line(&loaded, &s);
        println!("{}", s.text(truth.as_deref()));
    }
    Ok(ExitCode::SUCCESS)
}
