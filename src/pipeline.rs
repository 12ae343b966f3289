//! `glint run`: capture, HDR, calibration, fit, validation and report in one go, each
//! stage the same library call its own command makes, so that any stage can be re-run
//! alone on the finished session and give the same result.
//!
//! When the camera's response is already known (its profile beside the rig, or a file),
//! the HDR merge runs during the capture: every tile frame is folded into a streaming
//! [`Merger`] as soon as it is safely in the session, and once the dark frames are in,
//! each frame's dark level is taken out of the sums ([`Merger::subtract_dark`]), which
//! gives the batch merge's result (to float rounding). Without a profile (the first run
//! of a camera), the response is recovered from the session after the capture and stored
//! as the profile, and the merge runs then.
//!
//! A stage that fails stops the run with the session kept: everything captured and every
//! file the earlier stages wrote stay, and the error names the command that re-runs the
//! failed stage.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::calib::run::{CameraFile, Known};
use crate::capture::{self, CapturedFrame, Event, FrameKind, Stop};
use crate::devices::Devices;
use crate::fit::model::Reflectance;
use crate::fit::run::{FitOptions, FitReport};
use crate::hdr::merge::{dark_levels, Merger};
use crate::hdr::run::{HdrEvent, HdrOptions, HdrSummary, ResponseSource};
use crate::hdr::{Bracket, BracketFrame, HdrError};
use crate::report::{ReportOptions, Written};
use crate::rig::LoadedRig;
use crate::validate::{ValidateEvent, ValidateOptions, ValidationReport};

/// The stages, in order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Stage {
    Capture,
    Hdr,
    Calibrate,
    Fit,
    Validate,
    Report,
}

impl Stage {
    pub const ALL: [Stage; 6] = [
        Stage::Capture,
        Stage::Hdr,
        Stage::Calibrate,
        Stage::Fit,
        Stage::Validate,
        Stage::Report,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Stage::Capture => "capture",
            Stage::Hdr => "hdr",
            Stage::Calibrate => "calibrate",
            Stage::Fit => "fit",
            Stage::Validate => "validate",
            Stage::Report => "report",
        }
    }

    /// 1-based position.
    pub fn number(self) -> usize {
        Stage::ALL.iter().position(|s| *s == self).unwrap_or(0) + 1
    }
}

/// Progress of a run.
#[derive(Debug)]
pub enum RunEvent<'a> {
    /// A stage starts.
    Stage(Stage),
    /// A stage ended after `seconds`.
    Done {
        stage: Stage,
        seconds: f64,
    },
    Capture(&'a Event),
    /// A tile frame was folded into the streaming merge (count so far).
    Streamed {
        frames: usize,
    },
    Hdr(HdrEvent),
    Validate(ValidateEvent),
}

/// A run's progress as plain data: what `glint run` draws on the terminal and what the
/// daemon streams to its followers (one JSON object each, tagged by `event`), so a client
/// of the daemon draws exactly what `glint run` draws.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "event", rename_all = "kebab-case")]
pub enum Progress {
    /// A stage starts.
    Stage {
        stage: Stage,
    },
    /// A stage ended after `seconds`.
    StageDone {
        stage: Stage,
        seconds: f64,
    },
    /// The capture plan starts: its steps and the frames it keeps.
    Started {
        steps: usize,
        frames: u32,
    },
    /// A step of the capture plan starts.
    Step {
        index: usize,
        total: usize,
        description: String,
    },
    /// The lamp's reply to `*IDN?`.
    LampIdentity {
        identity: String,
    },
    /// A frame was kept (`kept` of `total`).
    Frame {
        kind: FrameKind,
        exposure_us: u32,
        kept: u32,
        total: u32,
    },
    /// A frame was taken and not kept (settling, a lamp switch).
    Discarded {
        sequence: u64,
        reason: String,
    },
    Warning {
        message: String,
    },
    /// Tile frames folded into the streaming merge during the capture.
    Streamed {
        frames: usize,
    },
    /// What the HDR stage is doing.
    Hdr {
        message: String,
    },
    /// What the validation is doing.
    Validate {
        message: String,
    },
}

impl From<&Event> for Progress {
    fn from(e: &Event) -> Self {
        match e {
            Event::Started { steps, frames } => Progress::Started {
                steps: *steps,
                frames: *frames,
            },
            Event::Step {
                index,
                total,
                description,
            } => Progress::Step {
                index: *index,
                total: *total,
                description: description.clone(),
            },
            Event::LampIdentity(id) => Progress::LampIdentity {
                identity: id.clone(),
            },
            Event::Frame {
                kind,
                exposure_us,
                kept,
                total,
            } => Progress::Frame {
                kind: *kind,
                exposure_us: *exposure_us,
                kept: *kept,
                total: *total,
            },
            Event::Discarded { sequence, reason } => Progress::Discarded {
                sequence: *sequence,
                reason: reason.clone(),
            },
            Event::Warning(w) => Progress::Warning { message: w.clone() },
        }
    }
}

impl From<&RunEvent<'_>> for Progress {
    fn from(e: &RunEvent) -> Self {
        match e {
            RunEvent::Stage(stage) => Progress::Stage { stage: *stage },
            RunEvent::Done { stage, seconds } => Progress::StageDone {
                stage: *stage,
                seconds: *seconds,
            },
            RunEvent::Capture(e) => Progress::from(*e),
            RunEvent::Streamed { frames } => Progress::Streamed { frames: *frames },
            RunEvent::Hdr(HdrEvent::Recovering) => Progress::Hdr {
                message: "no camera profile yet: recovering the response from this session".into(),
            },
            RunEvent::Hdr(e) => Progress::Hdr {
                message: e.to_string(),
            },
            RunEvent::Validate(e) => Progress::Validate {
                message: e.to_string(),
            },
        }
    }
}

/// Options of every stage.
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    pub hdr: HdrOptions,
    /// Hold the lens at an earlier calibration's intrinsics (fit the pose only). Without
    /// it the camera's lens profile beside the rig is held, where there is one.
    pub intrinsics: Option<Known>,
    /// Do not use the camera's lens profile: fit the intrinsics from the grid photo.
    pub no_lens_profile: bool,
    pub fit: FitOptions,
    pub validate: ValidateOptions,
    pub report: ReportOptions,
}

/// What the capture gave.
#[derive(Debug, Clone, Serialize)]
pub struct CaptureSummary {
    pub frames: usize,
    /// Frames taken and not kept; `None` where the stages ran on a session captured
    /// earlier (a daemon's `process` job), which does not record them.
    pub discarded: Option<u32>,
    /// Frames the camera dropped; `None` as for `discarded`.
    pub dropped: Option<u64>,
    pub latency_frames: Option<u32>,
}

/// A finished run.
#[derive(Debug, Clone, Serialize)]
pub struct RunSummary {
    pub session: PathBuf,
    /// Whether the HDR merge ran during the capture (the response was known).
    pub streamed: bool,
    /// Seconds per stage.
    pub stages: Vec<(Stage, f64)>,
    pub seconds: f64,
    pub capture: CaptureSummary,
    pub hdr: HdrSummary,
    pub calibration: CameraFile,
    /// The lens held in the calibration (the pose alone fitted): the lens profile's or
    /// `--intrinsics`' file; None where the intrinsics were fitted from the grid photo.
    pub lens: Option<PathBuf>,
    pub fit: FitReport,
    pub validation: ValidationReport,
    pub report: Written,
}

/// Why a run stopped.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    #[error(transparent)]
    Capture(#[from] capture::RecordError),
    #[error("{} failed: {source} (the session {} is kept with everything captured; once fixed, run `glint {} {}` and the stages after it)", .stage.name(), .session.display(), .stage.name(), .session.display())]
    Stage {
        stage: Stage,
        session: PathBuf,
        source: Box<StageError>,
    },
}

/// Why a stage after the capture stopped.
#[derive(Debug, thiserror::Error)]
pub enum StageError {
    /// The run was stopped (the reason noted, else the signal by its name).
    #[error("{0}")]
    Stopped(String),
    #[error(transparent)]
    Session(#[from] crate::session::SessionError),
    #[error(transparent)]
    Hdr(#[from] HdrError),
    /// Calibration, and an unusable lens profile.
    #[error(transparent)]
    Calibrate(#[from] crate::calib::run::RunError),
    #[error(transparent)]
    Fit(#[from] crate::fit::run::FitError),
    #[error(transparent)]
    Validate(#[from] crate::validate::ValidateError),
    #[error(transparent)]
    Report(#[from] crate::report::ReportError),
}

/// The streaming merge's state during the capture.
struct Streaming {
    merger: Merger,
    source: ResponseSource,
    tiles: Vec<BracketFrame>,
    darks: Vec<BracketFrame>,
    /// The first fold that failed (the merge then runs after the capture instead).
    failed: Option<String>,
}

impl Streaming {
    fn take(&mut self, f: &CapturedFrame) {
        let frame = BracketFrame {
            name: format!(
                "{} frame {} at {} µs",
                f.kind.as_str(),
                f.frame.sequence,
                f.exposure_reported_us
            ),
            exposure_us: f.exposure_reported_us as f64,
            pixels: f.frame.pixels.clone(),
        };
        match f.kind {
            FrameKind::Tile => {
                if self.failed.is_none() {
                    if let Err(e) = self.merger.fold(&frame, [0.0; 3]) {
                        self.failed = Some(e.to_string());
                    }
                }
                self.tiles.push(frame);
            }
            FrameKind::Dark => self.darks.push(frame),
            FrameKind::Grid => {}
        }
    }

    /// Take the dark levels out and write `hdr/` as `glint hdr` does.
    fn finish(self, dir: &Path, start: Instant) -> Result<HdrSummary, HdrError> {
        let (w, h) = (self.merger.width(), self.merger.height());
        let bits = self.merger.response().bit_depth;
        let c = self.merger.response().channels.len();
        let mut tiles = Bracket::new_with(w, h, bits, c, self.tiles)?;
        let mut darks = Bracket::new_with(w, h, bits, c, self.darks)?;
        tiles.sort();
        darks.sort();
        tiles.check_exposures()?;
        let dark = dark_levels(self.merger.response(), &tiles, &darks);
        let mut merger = self.merger;
        for (f, d) in tiles.frames.iter().zip(&dark) {
            merger.subtract_dark(f, *d)?;
        }
        let response = merger.response().clone();
        let merged = merger.finish();
        crate::hdr::run::write_outputs(
            dir,
            &response,
            self.source,
            None,
            &tiles,
            darks.frames.len(),
            &merged,
            crate::hdr::run::Extra {
                state: crate::session::State::Complete,
                warnings: Vec::new(),
                notes: Vec::new(),
            },
            start,
        )
    }
}

/// A stage's work: given the progress callback, run, or say why not.
type StageWork<'a> = dyn FnMut(&mut dyn FnMut(RunEvent)) -> Result<(), StageError> + 'a;

/// Run every stage on the rig's devices, writing the session at `out`.
pub fn run(
    rig: &LoadedRig,
    devices: Devices,
    out: &Path,
    stop: Arc<AtomicBool>,
    opts: &RunOptions,
    on_event: &mut dyn FnMut(RunEvent),
) -> Result<RunSummary, RunError> {
    run_returning(rig, devices, out, stop.into(), opts, on_event).1
}

/// [`run`] that hands the devices back whatever the outcome (`None` only if the capture
/// thread lost them): the daemon keeps its devices from one job to the next.
///
/// Setting `stop` ends the capture at its next frame (lamp off, session `failed`), or the
/// run at the next stage after the capture.
pub fn run_returning(
    rig: &LoadedRig,
    devices: Devices,
    out: &Path,
    stop: Stop,
    opts: &RunOptions,
    on_event: &mut dyn FnMut(RunEvent),
) -> (Option<Devices>, Result<RunSummary, RunError>) {
    let t0 = Instant::now();
    // The camera profile is the one beside this rig file (never where a manifest says).
    let mut opts = opts.clone();
    opts.hdr.rig = Some(rig.path.clone());
    let opts = &opts;
    // The response, if known, for merging while capturing.
    let info = devices.camera.info();
    let profile = crate::hdr::run::profile_path_for(&rig.path, &info);
    let mut streaming =
        crate::hdr::run::known_response(&opts.hdr, profile, info.bit_depth, info.channels as usize)
            .ok()
            .flatten()
            .map(|(r, source)| Streaming {
                merger: Merger::new(r, info.width as usize, info.height as usize),
                source,
                tiles: Vec::new(),
                darks: Vec::new(),
                failed: None,
            });

    on_event(RunEvent::Stage(Stage::Capture));
    let t = Instant::now();
    let recorded = capture::record_returning(
        rig,
        devices,
        out,
        stop.clone(),
        &mut |e| on_event(RunEvent::Capture(e)),
        &mut |f| {
            if let Some(s) = streaming.as_mut() {
                s.take(f);
            }
        },
    );
    let recorded = match recorded {
        Ok(r) => r,
        Err((e, devices)) => return (Some(devices), Err(e.into())),
    };
    let capture_seconds = t.elapsed().as_secs_f64();
    capture::fault_point("capture-done");
    on_event(RunEvent::Done {
        stage: Stage::Capture,
        seconds: capture_seconds,
    });
    if let Some(s) = streaming.as_ref().filter(|s| !s.tiles.is_empty()) {
        on_event(RunEvent::Streamed {
            frames: s.merger.frames(),
        });
    }
    if let Some(e) = streaming.as_ref().and_then(|s| s.failed.as_ref()) {
        on_event(RunEvent::Capture(&Event::Warning(format!(
            "the merge during the capture stopped ({e}); merging after the capture instead"
        ))));
    }
    let streaming = streaming.filter(|s| s.failed.is_none());
    let capture = CaptureSummary {
        frames: recorded.manifest.frames.len(),
        discarded: Some(recorded.summary.discarded),
        dropped: Some(recorded.summary.dropped),
        latency_frames: recorded.summary.latency_frames,
    };
    let result = after_capture(
        recorded.dir,
        capture,
        vec![(Stage::Capture, capture_seconds)],
        streaming,
        &stop,
        opts,
        t0,
        on_event,
    );
    (Some(recorded.devices), result)
}

/// The camera's lens profile beside `rig` for the camera of the session at `dir`, if there
/// is one (an unusable one is an error that says how to fix it).
pub fn lens_profile_for(rig: &Path, dir: &Path) -> Result<Option<Known>, StageError> {
    let m = crate::session::open(dir, true)?;
    let Some(c) = m.camera.as_ref() else {
        return Ok(None);
    };
    Ok(crate::calib::lens::load(rig, &c.model, c.width, c.height)?)
}

/// The stages after the capture (HDR, calibration, fit, validation, report) on a session
/// that is already captured: the daemon's `process` job. The camera profile is the one
/// beside `rig` (the daemon's rig file), as for [`run`]. Setting `stop` ends the run at the
/// next stage.
pub fn process(
    rig: &LoadedRig,
    dir: &Path,
    stop: Stop,
    opts: &RunOptions,
    on_event: &mut dyn FnMut(RunEvent),
) -> Result<RunSummary, RunError> {
    let t0 = Instant::now();
    let mut opts = opts.clone();
    opts.hdr.rig = Some(rig.path.clone());
    let m = crate::session::open(dir, opts.hdr.allow_incomplete).map_err(|e| RunError::Stage {
        stage: Stage::Hdr,
        session: dir.to_path_buf(),
        source: Box::new(e.into()),
    })?;
    // What the capture discarded and dropped is not recorded in a session: unknown here.
    let capture = CaptureSummary {
        frames: m.frames.len(),
        discarded: None,
        dropped: None,
        latency_frames: None,
    };
    after_capture(
        dir.to_path_buf(),
        capture,
        Vec::new(),
        None,
        &stop,
        &opts,
        t0,
        on_event,
    )
}

/// HDR (from the streaming merge where it ran), calibration, fit, validation and report.
#[allow(clippy::too_many_arguments)]
fn after_capture(
    dir: PathBuf,
    capture: CaptureSummary,
    mut stages: Vec<(Stage, f64)>,
    streaming: Option<Streaming>,
    stop: &Stop,
    opts: &RunOptions,
    t0: Instant,
    on_event: &mut dyn FnMut(RunEvent),
) -> Result<RunSummary, RunError> {
    let mut stage = |stage: Stage,
                     on_event: &mut dyn FnMut(RunEvent),
                     work: &mut StageWork|
     -> Result<(), RunError> {
        let failed = |source: StageError| RunError::Stage {
            stage,
            session: dir.clone(),
            source: Box::new(source),
        };
        if stop.is_set() {
            // The reason noted, else the signal by its name (a SIGTERM is not the user).
            return Err(failed(StageError::Stopped(stop.message())));
        }
        on_event(RunEvent::Stage(stage));
        let t = Instant::now();
        work(on_event).map_err(failed)?;
        let seconds = t.elapsed().as_secs_f64();
        stages.push((stage, seconds));
        on_event(RunEvent::Done { stage, seconds });
        Ok(())
    };
    let streamed = streaming.is_some();
    let mut streaming = streaming;
    let mut hdr = None;
    stage(Stage::Hdr, on_event, &mut |ev| {
        let start = Instant::now();
        hdr = Some(match streaming.take() {
            Some(s) => s.finish(&dir, start)?,
            None => crate::hdr::run::run(&dir, &opts.hdr, &mut |e| ev(RunEvent::Hdr(e)))?.0,
        });
        Ok(())
    })?;
    let mut calibration = None;
    let mut lens = None;
    stage(Stage::Calibrate, on_event, &mut |_| {
        let known = match (&opts.intrinsics, &opts.hdr.rig) {
            (Some(k), _) => Some(k.clone()),
            (None, Some(rig)) if !opts.no_lens_profile => lens_profile_for(rig, &dir)?,
            _ => None,
        };
        lens = known.as_ref().map(|k| k.from.clone());
        calibration = Some(crate::calib::run::run_session(&dir, known.as_ref())?);
        Ok(())
    })?;
    let mut fit = None;
    stage(Stage::Fit, on_event, &mut |_| {
        fit = Some(crate::fit::run::run(&dir, &opts.fit)?);
        Ok(())
    })?;
    let mut validation = None;
    stage(Stage::Validate, on_event, &mut |ev| {
        validation = Some(crate::validate::run(&dir, &opts.validate, &mut |e| {
            ev(RunEvent::Validate(e))
        })?);
        Ok(())
    })?;
    let mut report = None;
    stage(Stage::Report, on_event, &mut |_| {
        report = Some(crate::report::write(&dir, &opts.report)?);
        Ok(())
    })?;
    let done = "every stage ran";
    Ok(RunSummary {
        session: dir,
        streamed,
        stages,
        seconds: t0.elapsed().as_secs_f64(),
        capture,
        hdr: hdr.expect(done),
        calibration: calibration.expect(done),
        lens,
        fit: fit.expect(done),
        validation: validation.expect(done),
        report: report.expect(done),
    })
}

impl RunSummary {
    /// The first screen's lines on which candidates explain the tile within its noise
    /// (the fit's held-out misfit, the renders' RMSE against noise) and which models'
    /// lobe height and width trade off.
    fn verdict_text(&self) -> String {
        use std::fmt::Write;
        let s = self;
        let f = &s.fit;
        let mut o = String::new();
        // Which candidates explain the tile within its noise (the fit's held-out misfit),
        // with the validation's RMSE against noise beside it; where none does, the fit's
        // warning below says so with the remedies.
        let explained: Vec<String> = f
            .verdict
            .explained_by
            .iter()
            .map(|m| {
                let held = f
                    .candidates
                    .iter()
                    .find(|c| c.model == *m)
                    .map_or(f64::NAN, |c| c.held_out_rms());
                match s.validation.models.iter().find(|v| v.model == *m) {
                    Some(v) => format!(
                        "{} (held-out {:.2}x noise; renders RMSE {:.3} against {:.3})",
                        m.name(),
                        held,
                        v.pixels.rmse,
                        v.pixels.noise_rmse
                    ),
                    None => format!("{} (held-out {:.2}x noise)", m.name(), held),
                }
            })
            .collect();
        if explained.is_empty() {
            let _ = writeln!(
                o,
                "Explains the tile within its noise: none of the candidates (the best, {}, leaves {:.1}x the noise held out; see the warning below).",
                f.verdict.best.name(),
                f.verdict.best_held_out_rms
            );
        } else {
            let _ = writeln!(
                o,
                "Explains the tile within its noise: {}.",
                explained.join(", ")
            );
        }
        let traded: Vec<&str> = f
            .candidates
            .iter()
            .filter(|c| c.trade_off.is_some())
            .map(|c| c.model.name())
            .collect();
        if !traded.is_empty() {
            let _ = writeln!(
                o,
                "ks and n trade off (height against width of the lobe) in: {}; their n and ks/kd intervals hold only along that ridge.",
                traded.join(", ")
            );
        }
        o
    }

    /// The one-screen summary at the end of `glint run` (and of `glint trigger run`), with
    /// `truth` (see [`truth_line`]) where the rig is simulated.
    pub fn text(&self, truth: Option<&str>) -> String {
        use std::fmt::Write;
        let s = self;
        let mut o = String::new();
        let f = &s.fit;
        let _ = writeln!(
            o,
            "Session {}: {} frames; HDR merged {}.",
            s.session.display(),
            s.capture.frames,
            if s.streamed {
                "during the capture (the camera's profile was known)"
            } else if s
                .stages
                .first()
                .is_some_and(|(st, _)| *st == Stage::Capture)
            {
                "after the capture (response recovered and stored as the camera's profile)"
            } else {
                "from the session's frames"
            }
        );
        let cal = &s.calibration.calibration;
        match &s.lens {
            Some(l) => {
                let _ = writeln!(
                    o,
                    "Calibration: the lens held at {} (pose fitted, {:.3} px RMS reprojection error).",
                    l.display(),
                    cal.rms_px
                );
            }
            None => {
                let _ = writeln!(
                    o,
                    "Calibration: {} ({:.3} px RMS reprojection error).",
                    cal.parameters
                        .iter()
                        .take(3)
                        .map(|p| format!("{} = {}", p.name, pm(p.value, p.sd)))
                        .collect::<Vec<_>>()
                        .join(", "),
                    cal.rms_px
                );
            }
        }
        if let Some(v) = cal.views.first() {
            let [x, y, z] = v.camera_centre;
            let [sx, sy, sz] = v.camera_centre_sd;
            let _ = writeln!(
                o,
                "Camera centre (grid mm): x {}, y {}, z {}.",
                pm(x, sx),
                pm(y, sy),
                pm(z, sz)
            );
        }
        if let Some(c) = f.candidates.iter().find(|c| c.model == f.chosen) {
            let _ = writeln!(o, "Chosen model: {}", c.model.name());
            let rgb = |p: &[crate::fit::run::Param]| {
                p.iter()
                    .map(|x| pm(x.value, x.sd))
                    .collect::<Vec<_>>()
                    .join(", ")
            };
            // A monochrome camera's one channel; of RGB, G for the ratio.
            let (names, g) = if f.mono {
                ("(mono)   ", 0)
            } else {
                ("(R, G, B)", 1)
            };
            let _ = writeln!(o, "  kd {names}  {}", rgb(&c.kd));
            if c.model.has_lobe() {
                let _ = writeln!(o, "  ks {names}  {}", rgb(&c.ks));
                let _ = writeln!(
                    o,
                    "  n             {:.2} (95%: {:.2} to {:.2})",
                    c.n.value, c.n.ci95[0], c.n.ci95[1]
                );
                if let Some(a) = &c.alpha {
                    let _ = writeln!(
                        o,
                        "  α (roughness) {:.4} (95%: {:.4} to {:.4})",
                        a.value, a.ci95[0], a.ci95[1]
                    );
                }
                let _ = writeln!(
                    o,
                    "  ks/kd {}     {}",
                    if f.mono { "(Y)" } else { "(G)" },
                    pm(c.ks_over_kd[g].value, c.ks_over_kd[g].sd)
                );
            }
            match (&c.absolute, &f.reference) {
                (Some(a), Some(r)) => {
                    let _ = writeln!(o, "  albedo {names} {}", rgb(&a.albedo));
                    if !a.ks_per_sr.is_empty() {
                        let _ = writeln!(o, "  ks {names} 1/sr {}", rgb(&a.ks_per_sr));
                    }
                    if !a.f0.is_empty() {
                        let _ = writeln!(o, "  F0 {names}  {}", rgb(&a.f0));
                    }
                    let _ = writeln!(
                        o,
                        "  (absolute, from the reference standard of reflectance {} in {} pixels; kd, ks above in the radiance's relative units)",
                        r.reflectance
                            .iter()
                            .map(|x| format!("{x}"))
                            .collect::<Vec<_>>()
                            .join(", "),
                        r.pixels
                    );
                }
                _ => {
                    let _ = writeln!(
                        o,
                        "  (kd, ks in the radiance's relative units, the rig having no [reference] standard; ratios and n absolute)"
                    );
                }
            }
        }
        o.push_str(&s.verdict_text());
        let v = s.validation.chosen();
        let _ = writeln!(
            o,
            "Validation: PSNR {:.2} dB, RMSE {:.3} against {:.3} from noise alone (pixel values, {} readings); radiance error {:.2}%; SSIM {:.4}.",
            v.pixels.psnr_db,
            v.pixels.rmse,
            v.pixels.noise_rmse,
            v.pixels.readings,
            100.0 * v.radiance.relative_error,
            v.pixels.ssim
        );
        let _ = writeln!(
            o,
            "Other models (PSNR): {}.",
            s.validation
                .models
                .iter()
                .filter(|m| !m.chosen)
                .map(|m| format!("{} {:.2} dB", m.model.name(), m.pixels.psnr_db))
                .collect::<Vec<_>>()
                .join(", ")
        );
        if let Some(t) = truth {
            let _ = writeln!(o, "{t}");
        }
        for w in f.warnings.iter().chain(&s.validation.warnings) {
            let _ = writeln!(o, "warning: {w}");
        }
        let _ = writeln!(
            o,
            "Stages: {}; total {:.1} s.",
            s.stages
                .iter()
                .map(|(st, t)| format!("{} {:.2} s", st.name(), t))
                .collect::<Vec<_>>()
                .join(", "),
            s.seconds
        );
        let _ = write!(o, "Report: {}", s.report.index.display());
        o
    }
}

/// The simulated tile's (kd, ks, n) as the rig's camera sees them: the rig's
/// `[mock.tile]` for an RGB camera; for a monochrome one (which sees the mean of the three
/// bands' radiance) kd = mean(kd), ks = mean(ks), the same n. `None` for a real rig.
pub fn seen_truth(rig: &crate::rig::Rig) -> Option<(Vec<f64>, Vec<f64>, f64)> {
    let t = crate::devices::mock::simulated_tile(rig)?;
    Some((t.kd, t.ks, truth_exponent(t.ggx_alpha, t.n)))
}

/// The exponent a simulated tile has on the fitter's scale: a microfacet tile's roughness
/// converted, else its own n.
fn truth_exponent(ggx_alpha: Option<f64>, n: f64) -> f64 {
    match ggx_alpha {
        Some(a) => crate::fit::model::ggx::exponent(a),
        None => n,
    }
}

/// Where the rig is simulated, whether the run found the simulated tile's model (the rig's
/// `[mock.tile]`, read through the simulated lab's adapter), in one line; `None` for a real
/// rig. For a monochrome camera the truth is what it sees: kd = mean(kd), ks = mean(ks),
/// the same n ([`seen_truth`]).
pub fn truth_line(rig: &LoadedRig, s: &RunSummary) -> Option<String> {
    let t = crate::devices::mock::simulated_tile(&rig.rig)?;
    let n = truth_exponent(t.ggx_alpha, t.n);
    let (kd, ks) = (&t.kd, &t.ks);
    let name = t.model.clone();
    let lobe = t.lobe;
    let mono = kd.len() == 1;
    Some(format!(
        "Simulated truth (the rig's [mock.tile]{}): {name}{}; the chosen model {}.",
        if mono {
            ", seen by a mono camera: the mean of the three bands"
        } else {
            ""
        },
        if lobe && mono {
            format!(
                ", kd = {:.4}, ks = {:.4}, n = {}, ks/kd (Y) = {:.4}",
                kd[0],
                ks[0],
                n,
                ks[0] / kd[0]
            )
        } else if let Some(a) = t.ggx_alpha {
            format!(", α = {a} (n = {n:.2}), F0 (G) = {:.4}", ks[1])
        } else if lobe {
            format!(", n = {}, ks/kd (G) = {:.4}", n, ks[1] / kd[1])
        } else if mono {
            format!(", kd = {:.4}", kd[0])
        } else {
            String::new()
        },
        if name == s.fit.chosen.name() {
            "matches"
        } else {
            "does NOT match"
        }
    ))
}

/// value ± sd as text, with a common power of ten where needed.
fn pm(value: f64, sd: f64) -> String {
    match crate::report::value_sd(value, sd) {
        (t, Some(e)) => format!("{t}e{e}"),
        (t, None) => t,
    }
}
