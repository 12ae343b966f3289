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

use serde::Serialize;

use crate::calib::run::{CameraFile, Known};
use crate::capture::{self, CapturedFrame, Event, FrameKind};
use crate::devices::Devices;
use crate::fit::run::{FitOptions, FitReport};
use crate::hdr::merge::{dark_levels, Merger};
use crate::hdr::run::{HdrEvent, HdrOptions, HdrSummary, ResponseSource};
use crate::hdr::{Bracket, BracketFrame, HdrError};
use crate::report::{ReportOptions, Written};
use crate::rig::LoadedRig;
use crate::validate::{ValidateEvent, ValidateOptions, ValidationReport};

/// The stages, in order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
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

/// Options of every stage.
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    pub hdr: HdrOptions,
    /// Hold the lens at an earlier calibration's intrinsics (fit the pose only).
    pub intrinsics: Option<Known>,
    pub fit: FitOptions,
    pub validate: ValidateOptions,
    pub report: ReportOptions,
}

/// What the capture gave.
#[derive(Debug, Clone, Serialize)]
pub struct CaptureSummary {
    pub frames: usize,
    pub discarded: u32,
    pub dropped: u64,
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
    pub fit: FitReport,
    pub validation: ValidationReport,
    pub report: Written,
}

/// Why a run stopped.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    #[error(transparent)]
    Capture(#[from] capture::RecordError),
    #[error("{} failed: {cause} (the session {} is kept with everything captured; once fixed, run `glint {} {}` and the stages after it)", .stage.name(), .session.display(), .stage.name(), .session.display())]
    Stage {
        stage: Stage,
        session: PathBuf,
        cause: String,
    },
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
        let mut tiles = Bracket::new(w, h, bits, self.tiles)?;
        let mut darks = Bracket::new(w, h, bits, self.darks)?;
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
type StageWork<'a> = dyn FnMut(&mut dyn FnMut(RunEvent)) -> Result<(), String> + 'a;

/// Run every stage on the rig's devices, writing the session at `out`.
pub fn run(
    rig: &LoadedRig,
    devices: Devices,
    out: &Path,
    stop: Arc<AtomicBool>,
    opts: &RunOptions,
    on_event: &mut dyn FnMut(RunEvent),
) -> Result<RunSummary, RunError> {
    let t0 = Instant::now();
    let mut stages = Vec::new();
    // The camera profile is the one beside this rig file (never where a manifest says).
    let mut opts = opts.clone();
    opts.hdr.rig = Some(rig.path.clone());
    let opts = &opts;
    // The response, if known, for merging while capturing.
    let info = devices.camera.info();
    let profile = crate::hdr::run::profile_path_for(&rig.path, &info.model, info.bit_depth);
    let mut streaming = crate::hdr::run::known_response(&opts.hdr, profile, info.bit_depth)
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
    let recorded = capture::record_with(
        rig,
        devices,
        out,
        stop,
        &mut |e| on_event(RunEvent::Capture(e)),
        &mut |f| {
            if let Some(s) = streaming.as_mut() {
                s.take(f);
            }
        },
    )?;
    let dir = recorded.dir.clone();
    stages.push((Stage::Capture, t.elapsed().as_secs_f64()));
    on_event(RunEvent::Done {
        stage: Stage::Capture,
        seconds: t.elapsed().as_secs_f64(),
    });
    if let Some(s) = streaming.as_ref().filter(|s| !s.tiles.is_empty()) {
        on_event(RunEvent::Streamed {
            frames: s.merger.frames(),
        });
    }
    let mut stage = |stage: Stage,
                     on_event: &mut dyn FnMut(RunEvent),
                     work: &mut StageWork|
     -> Result<(), RunError> {
        on_event(RunEvent::Stage(stage));
        let t = Instant::now();
        work(on_event).map_err(|cause| RunError::Stage {
            stage,
            session: dir.clone(),
            cause,
        })?;
        let seconds = t.elapsed().as_secs_f64();
        stages.push((stage, seconds));
        on_event(RunEvent::Done { stage, seconds });
        Ok(())
    };
    if let Some(e) = streaming.as_ref().and_then(|s| s.failed.as_ref()) {
        on_event(RunEvent::Capture(&Event::Warning(format!(
            "the merge during the capture stopped ({e}); merging after the capture instead"
        ))));
    }
    let streamed = streaming.as_ref().is_some_and(|s| s.failed.is_none());
    let mut streaming = streaming.filter(|s| s.failed.is_none());
    let mut hdr = None;
    stage(Stage::Hdr, on_event, &mut |ev| {
        let start = Instant::now();
        hdr = Some(match streaming.take() {
            Some(s) => s.finish(&dir, start).map_err(|e| e.to_string())?,
            None => {
                crate::hdr::run::run(&dir, &opts.hdr, &mut |e| ev(RunEvent::Hdr(e)))
                    .map_err(|e| e.to_string())?
                    .0
            }
        });
        Ok(())
    })?;
    let mut calibration = None;
    stage(Stage::Calibrate, on_event, &mut |_| {
        calibration = Some(
            crate::calib::run::run_session(&dir, opts.intrinsics.as_ref())
                .map_err(|e| e.to_string())?,
        );
        Ok(())
    })?;
    let mut fit = None;
    stage(Stage::Fit, on_event, &mut |_| {
        fit = Some(crate::fit::run::run(&dir, &opts.fit).map_err(|e| e.to_string())?);
        Ok(())
    })?;
    let mut validation = None;
    stage(Stage::Validate, on_event, &mut |ev| {
        validation = Some(
            crate::validate::run(&dir, &opts.validate, &mut |e| ev(RunEvent::Validate(e)))
                .map_err(|e| e.to_string())?,
        );
        Ok(())
    })?;
    let mut report = None;
    stage(Stage::Report, on_event, &mut |_| {
        report = Some(crate::report::write(&dir, &opts.report).map_err(|e| e.to_string())?);
        Ok(())
    })?;
    let done = "every stage ran";
    Ok(RunSummary {
        session: dir,
        streamed,
        stages,
        seconds: t0.elapsed().as_secs_f64(),
        capture: CaptureSummary {
            frames: recorded.manifest.frames.len(),
            discarded: recorded.summary.discarded,
            dropped: recorded.summary.dropped,
            latency_frames: recorded.summary.latency_frames,
        },
        hdr: hdr.expect(done),
        calibration: calibration.expect(done),
        fit: fit.expect(done),
        validation: validation.expect(done),
        report: report.expect(done),
    })
}
