//! Capture: the engine that runs plans on the devices, and [`record`], which runs a plan
//! on its own thread and streams the frames into a session as they arrive.
//!
//! Capture depends on the session, never the reverse: the plans it runs are data of their
//! own ([`crate::plan`]), the frame records it writes belong to [`crate::session`], and
//! each kept [`CapturedFrame`] is handed to the session writer as a [`NewFrame`]. The
//! plan's types and [`Verification`] are re-exported here, so `capture::Plan`,
//! `capture::FrameKind` and the like keep working.
//!
//! The engine thread and the session writer are joined by a bounded channel: frames are
//! handed out while the capture runs (later stages, such as a streaming HDR merge, can
//! consume the same stream), PNG encoding overlaps the next exposure, and if the writer
//! fails the channel closes and the engine stops at its next frame.

mod engine;

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::mpsc::{sync_channel, Receiver, SyncSender};
use std::sync::Arc;

pub use crate::plan::{
    human_bytes, human_duration, Disk, Estimate, FrameKind, Limits, Plan, Step, MAX_PLAN_SECONDS,
};
pub use crate::session::Verification;
pub use engine::{
    capture_active, fault_point, hurried, mean_level, note_hurry, note_stop_signal, CaptureError,
    CapturedFrame, Engine, EngineConfig, Event, Sink, SinkError, Stop, Summary, FAULT_SIGNALS_ENV,
    MIN_LIGHT_ABOVE_DARK,
};

use crate::devices::Devices;
use crate::rig::LoadedRig;
use crate::session::{Manifest, NewFrame, SessionWriter};

/// A message from a running capture.
#[derive(Debug)]
pub enum Message {
    Event(Event),
    Frame(Box<CapturedFrame>),
}

/// What the session writes of a kept frame.
impl<'a> From<&'a CapturedFrame> for NewFrame<'a> {
    fn from(c: &'a CapturedFrame) -> Self {
        NewFrame {
            kind: c.kind,
            frame: &c.frame,
            exposure_requested_us: c.exposure_requested_us,
            exposure_reported_us: c.exposure_reported_us,
            verified_by: c.verified_by,
            lamp: c.lamp,
            received: c.received,
        }
    }
}

struct ChannelSink(SyncSender<Message>);

impl Sink for ChannelSink {
    fn event(&mut self, event: Event) {
        let _ = self.0.send(Message::Event(event));
    }
    fn frame(&mut self, frame: CapturedFrame) -> Result<(), SinkError> {
        self.0
            .send(Message::Frame(Box::new(frame)))
            .map_err(|_| ConsumerStopped.into())
    }
}

/// The frame consumer of a capture on its own thread has gone (its own error says why).
#[derive(Debug, thiserror::Error)]
#[error("the frame consumer stopped (see the error before this one)")]
struct ConsumerStopped;

/// Why a capture failed, before the session records it.
#[derive(Debug, thiserror::Error)]
enum Failure {
    #[error("writing the session: {0}")]
    Write(crate::session::SessionError),
    #[error(transparent)]
    Capture(CaptureError),
}

/// A capture running on its own thread.
pub struct Running {
    pub messages: Receiver<Message>,
    handle: std::thread::JoinHandle<(Engine, Result<Summary, CaptureError>)>,
}

impl Running {
    /// Wait for the engine; returns it (with its devices) and the outcome.
    pub fn join(self) -> (Engine, Result<Summary, CaptureError>) {
        drop(self.messages);
        self.handle.join().expect("capture engine thread panicked")
    }
}

/// Run `plan` on `engine` in a thread of its own; frames and events arrive on `messages`.
pub fn spawn(mut engine: Engine, plan: Plan) -> Running {
    let (tx, rx) = sync_channel(4);
    let handle = std::thread::Builder::new()
        .name("capture-engine".into())
        .spawn(move || {
            let mut sink = ChannelSink(tx);
            let result = engine.run(&plan, &mut sink);
            (engine, result)
        })
        .expect("spawning the capture thread");
    Running {
        messages: rx,
        handle,
    }
}

/// A finished capture.
pub struct Recorded {
    pub dir: PathBuf,
    pub manifest: Manifest,
    pub summary: Summary,
    /// The devices, returned (tests read the simulated lab's truth from them).
    pub devices: Devices,
}

impl Recorded {
    /// What `glint capture --json` prints (and a daemon's `capture` job reports).
    pub fn summary_json(&self) -> serde_json::Value {
        let m = &self.manifest;
        serde_json::json!({
            "session": self.dir, "state": m.state, "frames": m.frames.len(),
            "discarded": self.summary.discarded, "dropped": self.summary.dropped,
            "latency_frames": self.summary.latency_frames,
        })
    }

    /// The line `glint capture` prints at the end.
    pub fn summary_text(&self) -> String {
        let count = |k| self.manifest.frames.iter().filter(|f| f.kind == k).count();
        format!(
            "Session {} complete: {} tile, {} dark, {} grid frames ({} discarded while settling; exposure latency {} frames).",
            self.dir.display(),
            count(FrameKind::Tile),
            count(FrameKind::Dark),
            count(FrameKind::Grid),
            self.summary.discarded,
            self.summary
                .latency_frames
                .map_or("unknown".into(), |k| k.to_string()),
        )
    }
}

/// A capture that stopped on a fault. The session, if it was created, is on disk in state
/// `failed` with every frame captured before the fault (unless `manifest_updated` is false:
/// then even the reserve could not hold the last manifest, and it still says `capturing`).
#[derive(Debug, thiserror::Error)]
#[error("{cause}{}", .session.as_ref().map(|d| if *.manifest_updated {
    format!(" (session {} kept with {} frame(s), state failed)", d.display(), .frames)
} else {
    format!(" (session {} kept with {} frame(s); its manifest could not be updated and still says capturing)", d.display(), .frames)
}).unwrap_or_default())]
pub struct RecordError {
    pub cause: String,
    pub session: Option<PathBuf>,
    pub frames: usize,
    /// Whether the manifest on disk records the failure.
    pub manifest_updated: bool,
}

/// Check a rig's plan, then capture it into a new session at `out`, reporting progress to
/// `on_event`.
///
/// Setting `stop` (e.g. from a Ctrl-C handler) ends the capture at the next step or frame,
/// with the lamp switched off and the session closed as `failed: interrupted by the user`
/// (or `stopped by SIGTERM` when [`note_stop_signal`] noted a signal); after
/// [`note_hurry`], the same with the last `OFF` bounded to one reply each.
pub fn record(
    rig: &LoadedRig,
    devices: Devices,
    out: &Path,
    stop: Arc<AtomicBool>,
    on_event: &mut dyn FnMut(&Event),
) -> Result<Recorded, RecordError> {
    record_with(rig, devices, out, stop, on_event, &mut |_| {})
}

/// [`record`], handing every kept frame to `on_frame` once it is safely in the session
/// (a streaming HDR merge folds the frames in while the capture runs).
pub fn record_with(
    rig: &LoadedRig,
    devices: Devices,
    out: &Path,
    stop: Arc<AtomicBool>,
    on_event: &mut dyn FnMut(&Event),
    on_frame: &mut dyn FnMut(&CapturedFrame),
) -> Result<Recorded, RecordError> {
    record_returning(rig, devices, out, stop.into(), on_event, on_frame).map_err(|(e, _)| e)
}

/// [`record_with`] that hands the devices back also when the capture fails (a daemon keeps
/// them for the next job), with the lamp switched off as after every capture.
// Returned once per capture, never on a hot path: the error's size does not matter.
#[allow(clippy::result_large_err)]
pub fn record_returning(
    rig: &LoadedRig,
    devices: Devices,
    out: &Path,
    stop: Stop,
    on_event: &mut dyn FnMut(&Event),
    on_frame: &mut dyn FnMut(&CapturedFrame),
) -> Result<Recorded, (RecordError, Devices)> {
    record_stoppable(
        rig,
        Plan::for_rig(&rig.rig),
        devices,
        out,
        stop,
        on_event,
        on_frame,
    )
}

/// [`record_returning`] with a plan of the caller's (the lens plan, [`Plan::for_lens`]).
#[allow(clippy::result_large_err)]
pub fn record_plan(
    rig: &LoadedRig,
    plan: Plan,
    devices: Devices,
    out: &Path,
    stop: Arc<AtomicBool>,
    on_event: &mut dyn FnMut(&Event),
    on_frame: &mut dyn FnMut(&CapturedFrame),
) -> Result<Recorded, (RecordError, Devices)> {
    record_stoppable(rig, plan, devices, out, stop.into(), on_event, on_frame)
}

/// [`record_plan`] stopped by a [`Stop`] (which may carry why).
#[allow(clippy::result_large_err)]
fn record_stoppable(
    rig: &LoadedRig,
    plan: Plan,
    devices: Devices,
    out: &Path,
    stop: Stop,
    on_event: &mut dyn FnMut(&Event),
    on_frame: &mut dyn FnMut(&CapturedFrame),
) -> Result<Recorded, (RecordError, Devices)> {
    let fail = |cause: String| RecordError {
        cause,
        session: None,
        frames: 0,
        manifest_updated: false,
    };
    if let Some(p) = (plan.check(&Limits::from_rig(&rig.rig)).into_iter())
        .chain(plan.check_resources(&rig.rig, out))
        .next()
    {
        return Err((fail(format!("the capture plan cannot run: {p}")), devices));
    }
    // From here until the session is closed, quitting at once could leave the lamp on
    // or the manifest `capturing`: a signal handler asks [`capture_active`].
    let _active = engine::ActiveCapture::enter();
    // The session is written before any device is touched: if it cannot be, nothing runs.
    let mut writer = match SessionWriter::create(out, rig, &plan, devices.camera.info()) {
        Ok(w) => w,
        Err(e) => return Err((fail(e.to_string()), devices)),
    };
    let engine = Engine::new(devices, EngineConfig::from_rig(&rig.rig)).with_stop(stop);
    let running = spawn(engine, plan);
    let mut write_error: Option<crate::session::SessionError> = None;
    for msg in running.messages.iter() {
        let written = match msg {
            Message::Event(e) => {
                on_event(&e);
                match e {
                    Event::LampIdentity(id) => writer.set_lamp_identity(id),
                    _ => Ok(()),
                }
            }
            Message::Frame(f) => writer.add_frame(NewFrame::from(&*f)).map(|_| on_frame(&f)),
        };
        if let Err(err) = written {
            write_error = Some(err);
            break;
        }
    }
    let (engine, result) = running.join();
    let dir = writer.dir().to_path_buf();
    let frames = writer.manifest().frames.len();
    let failed = |cause: String, manifest_updated: bool| RecordError {
        cause,
        session: Some(dir.clone()),
        frames,
        manifest_updated,
    };
    let left_on = engine.lamp_left_on().map(str::to_string);
    writer.set_lamp_off_confirmed(left_on.is_none());
    let outcome = match write_error {
        Some(w) => Err(Failure::Write(w)),
        None => result.map_err(Failure::Capture),
    };
    // The engine reports any failure to switch the lamp off as a failure of the capture.
    // The session records the failure in words (its manifest's `failure`).
    let outcome = match (outcome, left_on) {
        (Ok(summary), _) => Ok(summary),
        (Err(cause), Some(why)) => Err(format!(
            "{cause}; the {} may still be on: {why}",
            engine.devices.lamp.describe()
        )),
        (Err(cause), None) => Err(cause.to_string()),
    };
    let devices = engine.devices;
    match outcome {
        Ok(summary) => match writer.finish(None) {
            Ok(manifest) => Ok(Recorded {
                dir,
                manifest,
                summary,
                devices,
            }),
            Err(e) => Err((failed(format!("closing the session: {e}"), false), devices)),
        },
        Err(cause) => match writer.finish(Some(cause.clone())) {
            Ok(_) => Err((failed(cause, true), devices)),
            Err(e) => Err((
                failed(
                    format!("{cause}; recording the failure failed too: {e}"),
                    false,
                ),
                devices,
            )),
        },
    }
}
