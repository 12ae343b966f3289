//! The capture engine: the one owner of the devices, running plans step by step.
//!
//! Its key job is knowing which frames were really taken at the requested exposure.
//! Cameras apply a new exposure some frames late, or not at all, and their control
//! read-back only echoes the request. So after every change the engine watches the frames:
//! - where frames carry their exposure as metadata, it keeps the first frame that reports
//!   the requested value;
//! - otherwise it compares each frame's mean level with a frame taken just before the
//!   change: it waits for a jump in the expected direction, then for a frame that agrees
//!   with the one before it (the exposure has settled);
//! - where the image cannot show the change (lamp off, all black), it waits out the
//!   latency it measured earlier in the same capture, plus one frame.
//!
//! Every wait is bounded (`camera.settle_max_frames`); a camera that never shows the new
//! exposure is an error, as are dropped frames beyond `camera.max_dropped_frames`.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicI32, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

use serde::Serialize;

use crate::devices::{DeviceError, Devices, Frame, LampState, Pixels};
use crate::plan::{FrameKind, Plan, Step};
use crate::rig::Rig;
use crate::session::Verification;

/// A frame the plan keeps, with everything known about it.
#[derive(Debug, Clone)]
pub struct CapturedFrame {
    pub kind: FrameKind,
    pub frame: Frame,
    pub exposure_requested_us: u32,
    /// What the device reported: the frame's metadata where present, else the control.
    pub exposure_reported_us: u32,
    pub verified_by: Verification,
    /// The lamp's state, read back from the lamp before this group of frames.
    pub lamp: LampState,
    /// Host time the frame was received.
    pub received: SystemTime,
}

/// Progress of a running plan.
#[derive(Debug, Clone)]
pub enum Event {
    Started {
        steps: usize,
        frames: u32,
    },
    Step {
        index: usize,
        total: usize,
        description: String,
    },
    LampIdentity(String),
    Frame {
        kind: FrameKind,
        exposure_us: u32,
        kept: u32,
        total: u32,
    },
    Discarded {
        sequence: u64,
        reason: String,
    },
    Warning(String),
}

/// Why a [`Sink`] cannot take a frame (whatever its consumer's error is).
pub type SinkError = Box<dyn std::error::Error + Send + Sync>;

/// Where a running plan sends its frames and events.
pub trait Sink {
    fn event(&mut self, event: Event);
    /// Take a kept frame; an error stops the capture.
    fn frame(&mut self, frame: CapturedFrame) -> Result<(), SinkError>;
}

/// Why a capture stopped.
#[derive(Debug, thiserror::Error)]
pub enum CaptureError {
    #[error("{context}: {source}")]
    Device {
        context: String,
        source: DeviceError,
    },
    #[error("camera did not apply exposure {requested_us} µs within {frames} frames ({seen}); remove it from bracket.exposures_us if the camera cannot take it, or raise camera.settle_max_frames")]
    ExposureNotApplied {
        requested_us: u32,
        frames: u32,
        seen: String,
    },
    #[error("camera set exposure {applied_us} µs when {requested_us} µs was asked; use exposures the camera supports (bracket.exposures_us)")]
    ExposureClamped { requested_us: u32, applied_us: u32 },
    #[error("camera changed exposure to {reported_us} µs while capturing at {requested_us} µs")]
    ExposureDrift { requested_us: u32, reported_us: u32 },
    #[error("camera dropped {dropped} frame(s) (sequence {from} -> {to}) during {context}, more than camera.max_dropped_frames = {max}; check the USB bandwidth and cable, or raise the limit")]
    DroppedFrames {
        dropped: u64,
        from: u64,
        to: u64,
        context: String,
        max: u32,
    },
    #[error("camera delivered a corrupt frame (sequence {sequence}: {got}, expected {expected}); check camera.width, camera.height, camera.bit_depth and the cable")]
    FrameShape {
        sequence: u64,
        got: String,
        expected: String,
    },
    #[error("interrupted by the user")]
    Interrupted,
    /// Stopped by a signal other than Ctrl-C (`SIGTERM`, `SIGHUP`).
    #[error("stopped by {signal}")]
    Signalled { signal: &'static str },
    /// Stopped for the reason given to [`Stop::stop_for`] (the daemon's abort).
    #[error("{0}")]
    Stopped(String),
    #[error("the {lamp} (level {level}) gave no light: {detail}; check the bulb, lamp.level and that the lamp really switches (lamp.commands)")]
    NoLight {
        lamp: String,
        level: u16,
        detail: String,
    },
    #[error("the bracket is saturated at every exposure ({pct:.0}% of the image at full scale even at {shortest_us} µs, {lamp} at level {level}); add shorter exposures to bracket.exposures_us or lower lamp.level")]
    BracketSaturated {
        lamp: String,
        level: u16,
        shortest_us: u32,
        pct: f64,
    },
    #[error("the light was still changing {waited_ms} ms after the lamp.warmup_ms = {warmup_ms} ms warm-up (the image level changed by {change_pct:.1}% between frames); check the lamp, or raise lamp.warmup_ms")]
    LightUnsteady {
        warmup_ms: u64,
        waited_ms: u64,
        change_pct: f64,
    },
    #[error("lamp reads back as {got} before {context}, expected {expected}")]
    LampState {
        context: String,
        expected: LampState,
        got: LampState,
    },
    #[error("{0}")]
    Sink(SinkError),
    #[error("the plan cannot run: {0}")]
    Plan(String),
}

/// The signal that asked the capture to stop, 0 for none (or for Ctrl-C, which reads as
/// [`CaptureError::Interrupted`]). Signals are process-wide, and so is this note.
static STOP_SIGNAL: AtomicI32 = AtomicI32::new(0);

/// Note that `signal` (a `libc::SIG*` number) asked every running capture to stop; the
/// caller also sets the capture's stop flag. Async-signal-safe (one atomic operation), so a
/// signal handler may call it. The first signal noted is the one reported.
pub fn note_stop_signal(signal: i32) {
    let _ = STOP_SIGNAL.compare_exchange(0, signal, Ordering::SeqCst, Ordering::SeqCst);
}

/// How one capture (and the run around it) is asked to stop, and why: the flag its engine
/// polls at each step and frame, and the reason the asker gave (the daemon: `aborted`,
/// `daemon stopped by SIGTERM`), which takes precedence over a noted signal. Clones share
/// both. A signal handler sets the flag alone (one atomic store: async-signal-safe),
/// through the `Arc<AtomicBool>` the stop was made from ([`Stop::from`], [`Stop::flag`]).
#[derive(Debug, Clone, Default)]
pub struct Stop {
    flag: Arc<AtomicBool>,
    reason: Arc<std::sync::Mutex<Option<String>>>,
}

impl From<Arc<AtomicBool>> for Stop {
    /// A stop whose flag is `flag` (set by a Ctrl-C handler, say), with no reason given.
    fn from(flag: Arc<AtomicBool>) -> Stop {
        Stop {
            flag,
            reason: Arc::default(),
        }
    }
}

impl Stop {
    /// The flag: set, the capture stops at its next step or frame.
    pub fn flag(&self) -> &Arc<AtomicBool> {
        &self.flag
    }

    /// Whether the stop was asked.
    pub fn is_set(&self) -> bool {
        self.flag.load(Ordering::SeqCst)
    }

    /// Stop for `reason`: the reason is noted before the flag is set, so the capture fails
    /// with exactly this reason. Not for signal handlers (it takes a lock).
    pub fn stop_for(&self, reason: &str) {
        *self.reason.lock().unwrap_or_else(|p| p.into_inner()) = Some(reason.to_string());
        self.flag.store(true, Ordering::SeqCst);
    }

    /// The reason given to [`Stop::stop_for`], if any.
    pub fn reason(&self) -> Option<String> {
        self.reason
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Why the stop was asked, in words: the reason given, else the signal noted (`stopped
    /// by SIGTERM`), else `interrupted by the user` (Ctrl-C). What a stage that is not
    /// started because of a stop reports.
    pub fn message(&self) -> String {
        self.error().to_string()
    }

    /// The error a set stop means: the reason given, else which signal, if one was noted.
    fn error(&self) -> CaptureError {
        if let Some(reason) = self.reason() {
            return CaptureError::Stopped(reason);
        }
        match STOP_SIGNAL.load(Ordering::SeqCst) {
            libc::SIGTERM => CaptureError::Signalled { signal: "SIGTERM" },
            libc::SIGHUP => CaptureError::Signalled { signal: "SIGHUP" },
            libc::SIGQUIT => CaptureError::Signalled { signal: "SIGQUIT" },
            _ => CaptureError::Interrupted,
        }
    }
}

/// A second signal asked to hurry the stop: the capture stops at once and its last `OFF`
/// waits at most one reply each for `OFF` and its read-back ([`crate::devices::Lamp::switch_off_quickly`]).
static HURRY: AtomicBool = AtomicBool::new(false);

/// Note that the stop is to be hurried (a second signal). Async-signal-safe (one atomic
/// store), so a signal handler may call it; the caller also sets the stop flag. The lamp is
/// still switched off and the session still closed: a hurried stop only waits less.
pub fn note_hurry() {
    HURRY.store(true, Ordering::SeqCst);
}

/// Whether [`note_hurry`] was called.
pub fn hurried() -> bool {
    HURRY.load(Ordering::SeqCst)
}

/// Captures in this process between their start and the closing of their session: while
/// one runs, the lamp may be on or the manifest still `capturing`.
static ACTIVE: AtomicUsize = AtomicUsize::new(0);

/// Whether a capture of this process is running (from before its devices are used until its
/// session is closed): a signal handler asks this to know whether quitting at once could
/// leave a lamp on or a session `capturing`. Async-signal-safe (one atomic load).
pub fn capture_active() -> bool {
    ACTIVE.load(Ordering::SeqCst) > 0
}

/// Marks a capture as running ([`capture_active`]) until dropped.
pub(crate) struct ActiveCapture(());

impl ActiveCapture {
    pub(crate) fn enter() -> Self {
        ACTIVE.fetch_add(1, Ordering::SeqCst);
        ActiveCapture(())
    }
}

impl Drop for ActiveCapture {
    fn drop(&mut self) {
        ACTIVE.fetch_sub(1, Ordering::SeqCst);
    }
}

/// The environment variable that names fault points at which the process raises signals
/// at itself, for tests: `POINT:SIG` entries separated by commas (`lamp-on:INT,lamp-on:INT`
/// raises SIGINT twice once the lamp reads back on). Each entry fires once, in order, at the
/// first time its point is reached. Points: `lamp-on` (the lamp read back on), `stopping`
/// (the capture has stopped and is about to switch the lamp off), `capture-done` (`glint
/// run`: the capture's session is closed, the later stages not yet started). Signals: INT,
/// TERM, HUP.
pub const FAULT_SIGNALS_ENV: &str = "GLINT_FAULT_SIGNALS";

/// Raise at this process the signals [`FAULT_SIGNALS_ENV`] names for `point`, if any (a
/// test's way to send a signal at an exact step, not at a time).
pub fn fault_point(point: &str) {
    static PLAN: std::sync::Mutex<Option<Vec<(String, i32)>>> = std::sync::Mutex::new(None);
    let mut plan = PLAN.lock().unwrap_or_else(|p| p.into_inner());
    let entries = plan.get_or_insert_with(|| {
        std::env::var(FAULT_SIGNALS_ENV)
            .unwrap_or_default()
            .split(',')
            .filter_map(|e| {
                let (p, sig) = e.trim().split_once(':')?;
                let sig = match sig.trim().trim_start_matches("SIG") {
                    "INT" => libc::SIGINT,
                    "TERM" => libc::SIGTERM,
                    "HUP" => libc::SIGHUP,
                    _ => return None,
                };
                Some((p.trim().to_string(), sig))
            })
            .collect()
    });
    while let Some(i) = entries.iter().position(|(p, _)| p == point) {
        let (_, sig) = entries.remove(i);
        tracing::debug!(point, signal = sig, "fault point: raising a signal");
        // SAFETY: raise(3) sends a signal to the calling thread; its handler (or default
        // action) runs as for any signal.
        unsafe { libc::raise(sig) };
    }
}

/// The least a lit tile raises the frame's mean level above the lamp-off (dark) frames at
/// the same exposure, as a fraction of full scale, at its best exposure. The mean is taken
/// over ~20,000-30,000 samples, so sensor noise moves it by well under 0.1% even at 10%
/// noise per pixel: 1% is far above noise, and a real lamp that cannot lift the image by 1%
/// of full scale at the longest exposure of the bracket leaves the HDR merge nothing to
/// work with either.
pub const MIN_LIGHT_ABOVE_DARK: f64 = 0.01;

/// A bracket whose every exposure has at least this fraction of samples at full scale is
/// saturated throughout.
const SATURATED_THROUGHOUT: f64 = 0.98;

/// Mean level and saturated fraction of the kept frames at one exposure.
#[derive(Debug, Clone, Copy, Default)]
struct Levels {
    mean_sum: f64,
    saturated_sum: f64,
    frames: u32,
}

impl Levels {
    fn add(&mut self, (mean, saturated): (f64, f64)) {
        self.mean_sum += mean;
        self.saturated_sum += saturated;
        self.frames += 1;
    }
    fn mean(&self) -> f64 {
        self.mean_sum / self.frames.max(1) as f64
    }
    fn saturated(&self) -> f64 {
        self.saturated_sum / self.frames.max(1) as f64
    }
}

/// Settings the engine takes from the rig.
#[derive(Debug, Clone)]
pub struct EngineConfig {
    pub frame_timeout: Duration,
    pub settle_max_frames: u32,
    pub max_dropped_frames: u32,
    pub width: u32,
    pub height: u32,
    pub bit_depth: u8,
    /// Samples a pixel: 3 (RGB) or 1 (monochrome).
    pub channels: u8,
}

impl EngineConfig {
    pub fn from_rig(rig: &Rig) -> Self {
        let c = &rig.camera;
        EngineConfig {
            frame_timeout: Duration::from_millis(c.frame_timeout_ms),
            settle_max_frames: c.settle_max_frames,
            max_dropped_frames: c.max_dropped_frames,
            width: c.width,
            height: c.height,
            bit_depth: c.bit_depth,
            channels: c.channels(),
        }
    }
}

/// How many frames were kept and discarded.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Summary {
    pub kept: u32,
    pub discarded: u32,
    pub dropped: u64,
    /// The largest exposure latency seen, in frames.
    pub latency_frames: Option<u32>,
}

struct Settled {
    us: u32,
    /// The exposure control's value as read back after setting it.
    control_us: u32,
    verified_by: Verification,
    /// Frames already grabbed at the new exposure, to be kept first.
    pending: Option<Frame>,
}

/// The engine: owns the devices while a plan runs.
pub struct Engine {
    pub devices: Devices,
    cfg: EngineConfig,
    last_sequence: Option<u64>,
    metadata: Option<bool>,
    lamp: LampState,
    current: Option<Settled>,
    summary: Summary,
    context: String,
    /// The lamp was switched since the last frame: that frame may straddle the switch.
    lamp_switched: bool,
    /// Set from outside (Ctrl-C, the daemon's abort) to stop the plan at the next step or
    /// frame, with why.
    stop: Stop,
    /// The lamp may be on: set when an `ON` (or `LEVEL`) is about to be sent, cleared only
    /// when the lamp reads back off. Whatever happens in between, the engine switches it off.
    lamp_may_be_on: bool,
    /// Why the lamp could not be switched off at the end (it may still be on).
    lamp_left_on: Option<String>,
    /// Levels of the tile and dark frames kept, by exposure (µs).
    tile_levels: BTreeMap<u32, Levels>,
    dark_levels: BTreeMap<u32, Levels>,
    /// The lamp as read back before the last tile frames.
    tile_lamp: LampState,
}

impl Engine {
    pub fn new(devices: Devices, cfg: EngineConfig) -> Self {
        Engine {
            devices,
            cfg,
            last_sequence: None,
            metadata: None,
            lamp: LampState::OFF,
            current: None,
            summary: Summary::default(),
            context: String::new(),
            lamp_switched: false,
            stop: Stop::default(),
            lamp_may_be_on: false,
            lamp_left_on: None,
            tile_levels: BTreeMap::new(),
            dark_levels: BTreeMap::new(),
            tile_lamp: LampState::OFF,
        }
    }

    /// Stop the plan (with [`CaptureError::Interrupted`], or the reason given to
    /// [`Stop::stop_for`]) once `stop` is set.
    pub fn with_stop(mut self, stop: impl Into<Stop>) -> Self {
        self.stop = stop.into();
        self
    }

    fn check_stop(&self) -> Result<(), CaptureError> {
        if self.stop.flag.load(Ordering::Relaxed) {
            return Err(self.stop.error());
        }
        Ok(())
    }

    /// Sleep for `d` in short slices, stopping at once when the stop flag is set.
    fn sleep(&self, d: Duration) -> Result<(), CaptureError> {
        let end = Instant::now() + d;
        loop {
            self.check_stop()?;
            let left = end.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(());
            }
            std::thread::sleep(left.min(Duration::from_millis(20)));
        }
    }

    /// Why the lamp could not be confirmed off when the last plan ended (`None`: it read
    /// back off, or was never switched on). When `Some`, the lamp may still be on.
    pub fn lamp_left_on(&self) -> Option<&str> {
        self.lamp_left_on.as_deref()
    }

    /// Switch the lamp off and note whether it read back off; when the stop is hurried (a
    /// second signal), with at most one reply waited for each of `OFF` and its read-back.
    fn switch_off(&mut self) -> Result<(), DeviceError> {
        let off = if hurried() {
            self.devices.lamp.switch_off_quickly()?
        } else {
            self.devices.lamp.switch_off()?
        };
        self.lamp = off;
        self.lamp_may_be_on = false;
        Ok(())
    }

    /// Run a plan, sending kept frames and progress to `sink`. The lamp is switched off at
    /// the end whenever it may be on (an `ON` or `LEVEL` was sent and no `OFF` was read back
    /// since), also when the plan fails, and also when switching it on failed half-way. If
    /// it does not read back off, [`Engine::lamp_left_on`] says why.
    pub fn run(&mut self, plan: &Plan, sink: &mut dyn Sink) -> Result<Summary, CaptureError> {
        self.lamp_left_on = None;
        self.tile_levels.clear();
        self.dark_levels.clear();
        let total = plan.frames();
        sink.event(Event::Started {
            steps: plan.steps.len(),
            frames: total,
        });
        let mut result = self.run_steps(plan, total, sink);
        if self.lamp_may_be_on {
            fault_point("stopping");
            match self.switch_off() {
                Ok(()) => tracing::info!("lamp switched off (read back off)"),
                Err(e) => {
                    let why = format!("switching it off failed: {e}");
                    sink.event(Event::Warning(format!(
                        "the {} may still be on: {why}",
                        self.devices.lamp.describe()
                    )));
                    self.lamp_left_on = Some(why);
                    if result.is_ok() {
                        result = Err(self.device("switching the lamp off at the end", e));
                    }
                }
            }
        }
        result.map(|_| self.summary.clone())
    }

    fn run_steps(
        &mut self,
        plan: &Plan,
        total: u32,
        sink: &mut dyn Sink,
    ) -> Result<(), CaptureError> {
        let n = plan.steps.len();
        let last_capture = |k: FrameKind| {
            plan.steps
                .iter()
                .rposition(|s| matches!(s, Step::Capture { kind, .. } if *kind == k))
        };
        let (last_tile, last_dark) = (last_capture(FrameKind::Tile), last_capture(FrameKind::Dark));
        // The light is checked once the bracket and its dark frames are all in.
        let light_check_at = last_tile.map(|t| last_dark.map_or(t, |d| d.max(t)));
        for (i, step) in plan.steps.iter().enumerate() {
            self.check_stop()?;
            self.context = step.to_string();
            tracing::info!(step = i + 1, of = n, "{}", self.context);
            sink.event(Event::Step {
                index: i + 1,
                total: n,
                description: self.context.clone(),
            });
            match step {
                Step::IdentifyLamp => {
                    let id = self
                        .devices
                        .lamp
                        .identify()
                        .map_err(|e| self.device("identifying the lamp", e))?;
                    sink.event(Event::LampIdentity(id));
                }
                Step::LampOn { level } => {
                    // From the first byte sent, the lamp may be on, whatever the replies.
                    self.lamp_may_be_on = true;
                    self.lamp_switched = true;
                    self.forget_pending();
                    self.lamp = self
                        .devices
                        .lamp
                        .switch_on(*level)
                        .map_err(|e| self.device("switching the lamp on", e))?;
                    fault_point("lamp-on");
                }
                Step::LampOff => {
                    self.lamp_switched = true;
                    self.forget_pending();
                    self.switch_off()
                        .map_err(|e| self.device("switching the lamp off", e))?;
                }
                Step::WarmUp { ms } => {
                    self.sleep(Duration::from_millis(*ms))?;
                    self.wait_for_steady_light(*ms, sink)?;
                }
                Step::Operator { action } => {
                    self.devices
                        .operator
                        .perform(*action)
                        .map_err(|e| self.device("waiting for the operator", e))?;
                    // What the camera sees has changed: earlier image statistics mean nothing now.
                    self.forget_pending();
                }
                Step::SetExposure { us } => self.settle(*us, sink)?,
                Step::Capture { kind, count } => self.capture(*kind, *count, total, sink)?,
            }
            if Some(i) == last_tile {
                self.check_not_saturated()?;
            }
            if Some(i) == light_check_at {
                self.check_light()?;
            }
        }
        Ok(())
    }

    /// A bracket saturated at every exposure holds no radiance, only a lower bound.
    fn check_not_saturated(&self) -> Result<(), CaptureError> {
        let Some((&shortest_us, l)) = self.tile_levels.iter().next() else {
            return Ok(());
        };
        if self
            .tile_levels
            .values()
            .all(|l| l.saturated() >= SATURATED_THROUGHOUT)
        {
            return Err(CaptureError::BracketSaturated {
                lamp: self.devices.lamp.describe(),
                level: self.tile_lamp.level,
                shortest_us,
                pct: 100.0 * l.saturated(),
            });
        }
        Ok(())
    }

    /// No light, no success: at some exposure of the bracket the tile frames must be
    /// brighter than the dark frames at that exposure by [`MIN_LIGHT_ABOVE_DARK`]. Without
    /// dark frames (`bracket.dark_frames_per_exposure = 0`) only a bracket black at every
    /// exposure can be told apart.
    fn check_light(&self) -> Result<(), CaptureError> {
        if self.tile_levels.is_empty() {
            return Ok(());
        }
        let paired: Vec<(u32, f64)> = self
            .tile_levels
            .iter()
            .filter_map(|(us, t)| self.dark_levels.get(us).map(|d| (*us, t.mean() - d.mean())))
            .collect();
        let detail = if paired.is_empty() {
            let (us, m) = self
                .tile_levels
                .iter()
                .map(|(us, t)| (*us, t.mean()))
                .fold((0, f64::NEG_INFINITY), |a, b| if b.1 > a.1 { b } else { a });
            if m >= MIN_LIGHT_ABOVE_DARK {
                return Ok(());
            }
            format!(
                "the tile frames are black at every exposure (mean level at most {:.2}% of full scale, at {us} µs; no dark frames to compare with)",
                100.0 * m
            )
        } else {
            let (us, gain) =
                paired
                    .iter()
                    .copied()
                    .fold((0, f64::NEG_INFINITY), |a, b| if b.1 > a.1 { b } else { a });
            if gain >= MIN_LIGHT_ABOVE_DARK {
                tracing::info!(
                    exposure_us = us,
                    above_dark = gain,
                    "the lamp lifts the image above the dark frames"
                );
                return Ok(());
            }
            format!(
                "the tile frames are at most {:.2}% of full scale brighter than the lamp-off frames at the same exposure (at {us} µs; a lit tile shows at least {:.0}%)",
                100.0 * gain.max(0.0),
                100.0 * MIN_LIGHT_ABOVE_DARK
            )
        };
        Err(CaptureError::NoLight {
            lamp: self.devices.lamp.describe(),
            level: self.tile_lamp.level,
            detail,
        })
    }

    /// A frame grabbed while settling shows the scene and light of then; after the lamp or
    /// the scene changes it must not be kept.
    fn forget_pending(&mut self) {
        if let Some(c) = self.current.as_mut() {
            c.pending = None;
        }
    }

    fn device(&self, what: &str, source: DeviceError) -> CaptureError {
        CaptureError::Device {
            context: format!("{what} (step: {})", self.context),
            source,
        }
    }

    /// The next frame, checked for shape and dropped frames; after a lamp switch, the
    /// first frame is discarded.
    fn grab(&mut self, sink: &mut dyn Sink) -> Result<Frame, CaptureError> {
        if std::mem::take(&mut self.lamp_switched) {
            let f = self.grab_checked(sink)?;
            self.discard(&f, "may straddle the lamp switching", sink);
        }
        self.grab_checked(sink)
    }

    fn grab_checked(&mut self, sink: &mut dyn Sink) -> Result<Frame, CaptureError> {
        self.check_stop()?;
        let f = self
            .devices
            .camera
            .grab(self.cfg.frame_timeout)
            .map_err(|e| {
                self.device(
                    &format!(
                        "waiting for frame {}",
                        self.summary.kept + self.summary.discarded + 1
                    ),
                    e,
                )
            })?;
        let (w, h, d, c) = (
            self.cfg.width,
            self.cfg.height,
            self.cfg.bit_depth,
            self.cfg.channels,
        );
        let samples = w as usize * h as usize * c as usize;
        let kind = |c: u8| if c == 1 { "mono" } else { "RGB" };
        if (f.width, f.height, f.bit_depth, f.channels, f.pixels.len()) != (w, h, d, c, samples) {
            return Err(CaptureError::FrameShape {
                sequence: f.sequence,
                got: format!(
                    "{}x{} {}-bit {}, {} samples",
                    f.width,
                    f.height,
                    f.bit_depth,
                    kind(f.channels),
                    f.pixels.len()
                ),
                expected: format!("{w}x{h} {d}-bit {}, {samples} samples", kind(c)),
            });
        }
        if let Some(last) = self.last_sequence {
            if f.sequence > last + 1 {
                let gap = f.sequence - last - 1;
                self.summary.dropped += gap;
                sink.event(Event::Warning(format!(
                    "camera dropped {gap} frame(s) before sequence {}",
                    f.sequence
                )));
                if self.summary.dropped > self.cfg.max_dropped_frames as u64 {
                    return Err(CaptureError::DroppedFrames {
                        dropped: self.summary.dropped,
                        from: last,
                        to: f.sequence,
                        context: self.context.clone(),
                        max: self.cfg.max_dropped_frames,
                    });
                }
            }
        }
        self.last_sequence = Some(f.sequence);
        if self.metadata.is_none() {
            self.metadata = Some(f.exposure_us.is_some());
        }
        Ok(f)
    }

    fn discard(&mut self, f: &Frame, reason: &str, sink: &mut dyn Sink) {
        tracing::debug!(sequence = f.sequence, reason, "discarded frame");
        self.summary.discarded += 1;
        sink.event(Event::Discarded {
            sequence: f.sequence,
            reason: reason.into(),
        });
    }

    /// After a warm-up, make sure the light has really settled: two frames in a row must
    /// agree in level (0.2% of full scale plus 0.5%). A lamp that is slower than
    /// `lamp.warmup_ms` is waited for (with a warning) up to the warm-up time again, at least
    /// a second; one that never settles is an error. Frames that cannot show the light (too
    /// dark or saturated at the current exposure) end the check.
    fn wait_for_steady_light(
        &mut self,
        warmup_ms: u64,
        sink: &mut dyn Sink,
    ) -> Result<(), CaptureError> {
        let started = std::time::Instant::now();
        let limit = Duration::from_millis(warmup_ms.max(1000));
        let mut previous: Option<f64> = None;
        let mut unsteady = 0;
        loop {
            let f = self.grab(sink)?;
            let m = mean_level(&f);
            self.discard(&f, "checking that the light has settled", sink);
            if !shows_level_changes(m) {
                tracing::debug!(
                    level = m,
                    "the image cannot show whether the light has settled"
                );
                return Ok(());
            }
            if let Some(p) = previous {
                let change = m - p;
                if change.abs() <= 0.002 + 0.005 * p {
                    if unsteady > 1 {
                        sink.event(Event::Warning(format!(
                            "the light took {} ms longer than lamp.warmup_ms = {warmup_ms} ms to settle; raise lamp.warmup_ms",
                            started.elapsed().as_millis()
                        )));
                    }
                    return Ok(());
                }
                if started.elapsed() > limit {
                    return Err(CaptureError::LightUnsteady {
                        warmup_ms,
                        waited_ms: started.elapsed().as_millis() as u64,
                        change_pct: 100.0 * change / p,
                    });
                }
            }
            unsteady += 1;
            previous = Some(m);
        }
    }

    /// Set an exposure and wait until the frames show it.
    fn settle(&mut self, us: u32, sink: &mut dyn Sink) -> Result<(), CaptureError> {
        if self.current.as_ref().is_some_and(|c| c.us == us) {
            return Ok(());
        }
        let previous = self.current.take().map(|c| c.us);
        // A reference frame at the old exposure, unless frames report their exposure.
        let reference = if self.metadata == Some(true) {
            None
        } else {
            let f = self.grab(sink)?;
            let m = mean_level(&f);
            self.discard(&f, "reference before an exposure change", sink);
            if self.metadata == Some(true) {
                None
            } else {
                Some(m)
            }
        };
        let applied = self
            .devices
            .camera
            .set_exposure(us)
            .map_err(|e| self.device("setting the exposure", e))?;
        if !same_exposure(applied, us) {
            // Snapped to the control's step (within half a step): the frames are taken at
            // the applied exposure, which the session records and the merge uses.
            let step = self.devices.camera.exposure_step_us().max(1);
            if step > 1 && applied.abs_diff(us) <= step / 2 {
                sink.event(Event::Warning(format!(
                    "exposure {us} µs is not on the camera's {step} µs steps: {applied} µs applied (and recorded); choose exposures on its steps to avoid this"
                )));
            } else {
                return Err(CaptureError::ExposureClamped {
                    requested_us: us,
                    applied_us: applied,
                });
            }
        }
        // Which way the image should move; unknown for the first change of a capture.
        let brighter = previous.map(|p| us > p);
        let informative = reference.is_some_and(shows_level_changes);
        let mut changed_at: Option<(u32, f64)> = None;
        let mut seen = String::from("image level unchanged");
        for i in 1..=self.cfg.settle_max_frames {
            let f = self.grab(sink)?;
            let verdict = match (f.exposure_us, reference) {
                (Some(r), _) => {
                    seen = format!("frames report {r} µs");
                    (same_exposure(r, us) || same_exposure(r, applied))
                        .then_some(Verification::Metadata)
                }
                (None, Some(m_ref)) => {
                    let m = mean_level(&f);
                    match changed_at {
                        None => {
                            let jump = m - m_ref;
                            let threshold = 0.002 + 0.02 * m_ref;
                            let moved = match brighter {
                                Some(true) => jump > threshold,
                                Some(false) => -jump > threshold,
                                None => jump.abs() > threshold,
                            };
                            if moved {
                                changed_at = Some((i, m));
                            }
                            None
                        }
                        Some((_, m_prev)) => {
                            if (m - m_prev).abs() <= 0.002 + 0.01 * m_prev {
                                Some(Verification::ImageStatistics)
                            } else {
                                changed_at = changed_at.map(|(k, _)| (k, m));
                                None
                            }
                        }
                    }
                }
                (None, None) => unreachable!("a reference is taken when frames carry no exposure"),
            };
            let verdict = verdict.or_else(|| {
                // The image cannot show the change: wait out the measured latency.
                let k = self.summary.latency_frames?;
                (!informative && f.exposure_us.is_none() && i > k + 1)
                    .then_some(Verification::MeasuredLatency)
            });
            if let Some(v) = verdict {
                let latency = match v {
                    Verification::Metadata => Some(i - 1),
                    Verification::ImageStatistics => changed_at.map(|(k, _)| k - 1),
                    _ => None,
                };
                if let Some(l) = latency {
                    self.summary.latency_frames =
                        Some(self.summary.latency_frames.map_or(l, |k| k.max(l)));
                }
                tracing::info!(exposure_us = us, frames = i, verified_by = ?v, "exposure settled");
                self.current = Some(Settled {
                    us,
                    control_us: applied,
                    verified_by: v,
                    pending: Some(f),
                });
                return Ok(());
            }
            self.discard(&f, &format!("waiting for exposure {us} µs"), sink);
        }
        // Without metadata, a change can be invisible: the image is black or saturated, or
        // (first change of a capture) the camera was already at this exposure. Every latency
        // up to the limit has now passed, so the frames are at the new exposure unless the
        // camera ignores it, which nothing visible can tell apart.
        let unknowable = self.metadata == Some(false)
            && ((!informative && self.summary.latency_frames.is_none())
                || (informative && previous.is_none()));
        if unknowable {
            sink.event(Event::Warning(format!(
                "exposure {us} µs could not be confirmed (frames carry no exposure and the image did not change); waited {} frames",
                self.cfg.settle_max_frames
            )));
            self.current = Some(Settled {
                us,
                control_us: applied,
                verified_by: Verification::SettleTimeout,
                pending: None,
            });
            return Ok(());
        }
        Err(CaptureError::ExposureNotApplied {
            requested_us: us,
            frames: self.cfg.settle_max_frames,
            seen,
        })
    }

    fn capture(
        &mut self,
        kind: FrameKind,
        count: u32,
        total: u32,
        sink: &mut dyn Sink,
    ) -> Result<(), CaptureError> {
        let lamp = self
            .devices
            .lamp
            .state()
            .map_err(|e| self.device("reading the lamp state", e))?;
        let want_on = kind != FrameKind::Dark;
        if lamp.on != want_on || (want_on && lamp != self.lamp) {
            let expected = if want_on { self.lamp } else { LampState::OFF };
            return Err(CaptureError::LampState {
                context: self.context.clone(),
                expected,
                got: lamp,
            });
        }
        let (us, control, verified_by) = match &self.current {
            Some(c) => (c.us, c.control_us, c.verified_by),
            None => {
                return Err(CaptureError::Plan(format!(
                    "{}: no exposure set",
                    self.context
                )))
            }
        };
        for _ in 0..count {
            let f = match self.current.as_mut().and_then(|c| c.pending.take()) {
                Some(f) => f,
                None => self.grab(sink)?,
            };
            if let Some(r) = f.exposure_us {
                if !same_exposure(r, us) {
                    return Err(CaptureError::ExposureDrift {
                        requested_us: us,
                        reported_us: r,
                    });
                }
            }
            self.summary.kept += 1;
            match kind {
                FrameKind::Tile => {
                    self.tile_lamp = lamp;
                    self.tile_levels.entry(us).or_default().add(level_stats(&f));
                }
                FrameKind::Dark => self.dark_levels.entry(us).or_default().add(level_stats(&f)),
                FrameKind::Grid => {}
            }
            let captured = CapturedFrame {
                kind,
                exposure_requested_us: us,
                exposure_reported_us: f.exposure_us.unwrap_or(control),
                verified_by,
                lamp,
                received: SystemTime::now(),
                frame: f,
            };
            sink.frame(captured).map_err(CaptureError::Sink)?;
            sink.event(Event::Frame {
                kind,
                exposure_us: us,
                kept: self.summary.kept,
                total,
            });
        }
        Ok(())
    }
}

/// Whether an image of mean level `m` (0..1) can show a change of exposure or light: not
/// (nearly) black, not (nearly) saturated.
fn shows_level_changes(m: f64) -> bool {
    (0.02..=0.98).contains(&m)
}

/// Whether a reported exposure is the requested one, allowing for the camera's rounding
/// (1 µs or 1%, whichever is more).
fn same_exposure(reported: u32, requested: u32) -> bool {
    reported.abs_diff(requested) <= 1.max(requested / 100)
}

/// Mean level of a frame in [0, 1] and the fraction of samples at full scale (within 1%),
/// from the same sparse grid of samples as [`mean_level`].
fn level_stats(f: &Frame) -> (f64, f64) {
    let n = f.pixels.len();
    let step = (n / 30_000).max(1) | 1; // odd stride: visits all three channels
    let (sum, saturated, count, max) = match &f.pixels {
        Pixels::U8(v) => stats_of(v.iter().step_by(step).map(|x| *x as u32), 255),
        Pixels::U16(v) => stats_of(
            v.iter().step_by(step).map(|x| *x as u32),
            (1u32 << f.bit_depth.min(16)) - 1,
        ),
    };
    if count == 0 {
        return (0.0, 0.0);
    }
    (
        sum / (count as f64 * max as f64),
        saturated as f64 / count as f64,
    )
}

fn stats_of(values: impl Iterator<Item = u32>, max: u32) -> (f64, u64, u64, u32) {
    let full = max - max / 100;
    let (mut sum, mut saturated, mut count) = (0.0, 0u64, 0u64);
    for x in values {
        sum += x as f64;
        saturated += (x >= full) as u64;
        count += 1;
    }
    (sum, saturated, count, max.max(1))
}

/// Mean level of a frame in [0, 1], from a sparse grid of samples (0 for an empty frame).
pub fn mean_level(f: &Frame) -> f64 {
    level_stats(f).0
}
