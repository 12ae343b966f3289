//! Devices: the camera, the lamp and the operator, behind small traits.
//!
//! Every device reports what it actually did (the exposure the camera reads back, the lamp
//! state read back over the wire), never an echo of the request. Devices are opened by one
//! factory, [`open`], into boxed trait objects; the simulated lab goes down exactly the same
//! path as hardware (its lamp even through the real serial driver, over a pseudo-terminal),
//! so the capture engine has no test-only branches.

pub mod decode;
pub mod lamp_protocol;
pub mod mock;
#[cfg(feature = "nokhwa")]
pub mod nokhwa_cam;
pub mod operator;
pub mod rig;
pub mod serial_lamp;
#[cfg(feature = "v4l2")]
pub mod v4l2;
pub mod v4l2_rules;

pub use glint_format::image::{CameraInfo, ControlReading, Frame, LampState, Pixels};

use std::time::Duration;

use crate::rig::{CameraBackend, LampBackend, LoadedRig, Rig};

/// Whether this Glint was built with the V4L2 camera backend (cargo feature `v4l2`).
pub const V4L2_BUILT: bool = cfg!(feature = "v4l2");

/// What a build without the V4L2 backend says about a V4L2 rig.
pub const V4L2_MISSING: &str = "this Glint was built without the V4L2 backend; rebuild with `cargo build --release --features v4l2` (needs libclang-dev)";

/// Whether this Glint was built with the nokhwa camera backend (cargo feature `nokhwa`).
pub const NOKHWA_BUILT: bool = cfg!(feature = "nokhwa");

/// What a build without the nokhwa backend says about a nokhwa rig.
pub const NOKHWA_MISSING: &str = "this Glint was built without the nokhwa backend; rebuild with `cargo build --release --features nokhwa` (on Linux it needs libclang-dev)";

/// What this build can say about opening a rig's devices before it opens them: problems
/// (the devices cannot be opened by this build at all) and warnings (they can, but not
/// exactly as the rig asks). `glint rig check` and the dry runs report both; [`open`]
/// refuses on the same problems.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct BackendCheck {
    pub problems: Vec<String>,
    pub warnings: Vec<String>,
}

/// Check that this build has the backends a rig names (see [`BackendCheck`]).
pub fn check_backends(rig: &Rig) -> BackendCheck {
    let mut c = BackendCheck::default();
    if rig.camera.backend == CameraBackend::V4l2 {
        if V4L2_BUILT {
            c.warnings = v4l2_rules::exposure_snap_warnings(rig);
        } else {
            c.problems
                .push(format!("camera.backend = \"v4l2\": {V4L2_MISSING}"));
        }
    }
    if rig.camera.backend == CameraBackend::Nokhwa {
        #[cfg(feature = "nokhwa")]
        {
            c.problems = nokhwa_cam::problems(rig);
            c.warnings = v4l2_rules::exposure_snap_warnings(rig);
        }
        #[cfg(not(feature = "nokhwa"))]
        c.problems
            .push(format!("camera.backend = \"nokhwa\": {NOKHWA_MISSING}"));
    }
    if let Ok(p) = rig.lamp.resolved_protocol() {
        let level = rig.lamp.level;
        let device = p.to_device(level);
        let back = p.from_device(device);
        if back != level {
            c.warnings.push(format!(
                "lamp.level = {level} is {device} on the lamp's {}..{} scale (protocol preset {}): it is set and reads back as {back}",
                p.level_range[0],
                p.level_range[1],
                p.preset.name()
            ));
        }
    }
    c
}

/// A camera that takes frames at a set exposure.
pub trait Camera: Send {
    fn info(&self) -> CameraInfo;
    /// Request an exposure; returns the control's value as read back from the device.
    /// The frames may take the new value only some frames later: see the capture engine.
    fn set_exposure(&mut self, us: u32) -> Result<u32, DeviceError>;
    /// The next frame, or [`DeviceError::CameraTimeout`] when none comes within `timeout`.
    fn grab(&mut self, timeout: Duration) -> Result<Frame, DeviceError>;
    /// The exposure control's step, µs: a request between steps is snapped to one (V4L2's
    /// `exposure_time_absolute` counts 100 µs units).
    fn exposure_step_us(&self) -> u32 {
        1
    }
}

/// A lamp that can be switched and read back.
pub trait Lamp: Send {
    /// Where the lamp is, for messages (e.g. `serial lamp on /dev/ttyUSB0`).
    fn describe(&self) -> String;
    fn identify(&mut self) -> Result<String, DeviceError>;
    /// Switch on at `level` and return the state read back.
    fn switch_on(&mut self, level: u16) -> Result<LampState, DeviceError>;
    /// Switch off and return the state read back.
    fn switch_off(&mut self) -> Result<LampState, DeviceError>;
    /// [`Lamp::switch_off`] in a hurry (a second signal): the same commands, waiting at
    /// most one reply timeout each for `OFF` and its read-back instead of every retry.
    fn switch_off_quickly(&mut self) -> Result<LampState, DeviceError> {
        self.switch_off()
    }
    fn state(&mut self) -> Result<LampState, DeviceError>;
}

/// Things only hands can do.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum OperatorAction {
    /// Put the tile on the grid at its outline.
    PlaceTile,
    /// Take the tile off so the whole grid shows.
    RemoveTile,
    /// Take the tile off and hold the chessboard in a pose (the lens calibration).
    ShowBoard(BoardPose),
}

/// A pose of the chessboard for the lens calibration: lifted off the floor and turned
/// about its own centre, first `tilt_x_deg` about the grid's x axis, then `tilt_y_deg`
/// about y, then `rotate_deg` about z (right-handed, grid frame), its centre `lift_mm`
/// above the floor. The calibration finds the pose itself: these only need to be
/// roughly right, and whole degrees and millimetres are enough.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub struct BoardPose {
    /// The pose's number in the plan, from 1.
    pub index: u32,
    pub tilt_x_deg: i32,
    pub tilt_y_deg: i32,
    pub rotate_deg: i32,
    pub lift_mm: u32,
}

impl std::fmt::Display for BoardPose {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "pose {}: tilted {}° about x, {}° about y, turned {}° about z, its centre {} mm above the floor",
            self.index, self.tilt_x_deg, self.tilt_y_deg, self.rotate_deg, self.lift_mm
        )
    }
}

impl std::fmt::Display for OperatorAction {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            OperatorAction::PlaceTile => f.write_str("place the tile on the grid at its outline"),
            OperatorAction::RemoveTile => {
                f.write_str("remove the tile so the whole grid is visible")
            }
            OperatorAction::ShowBoard(p) => write!(
                f,
                "remove the tile and hold the chessboard in {p} (in full view of the camera)"
            ),
        }
    }
}

/// Whoever performs [`OperatorAction`]s: a person at a terminal, or the simulated lab.
pub trait Operator: Send {
    fn perform(&mut self, action: OperatorAction) -> Result<(), DeviceError>;
}

/// A person at the terminal: asked on stderr, answers with Enter.
pub struct ConsoleOperator;

impl Operator for ConsoleOperator {
    fn perform(&mut self, action: OperatorAction) -> Result<(), DeviceError> {
        use std::io::{BufRead, IsTerminal, Write};
        if !std::io::stdin().is_terminal() {
            return Err(DeviceError::Operator(format!(
                "the capture needs someone to {action}, but standard input is not a terminal; run `glint capture` from a terminal"
            )));
        }
        eprint!("Please {action}, then press Enter (Ctrl-C aborts): ");
        let _ = std::io::stderr().flush();
        let mut line = String::new();
        std::io::stdin()
            .lock()
            .read_line(&mut line)
            .map_err(|e| DeviceError::Operator(format!("could not read the answer: {e}")))?;
        Ok(())
    }
}

/// What went wrong with a device.
#[derive(Debug, thiserror::Error)]
pub enum DeviceError {
    #[error("camera stalled: no frame within {} ms; check the cable and that no other program holds the camera", .after.as_millis())]
    CameraTimeout { after: Duration },
    #[error("{lamp} did not answer `{command}` ({tries} tries, {} ms each); check that it is powered and connected to lamp.port, lamp.baud, and lamp.reply_timeout_ms for a slow device", .timeout.as_millis())]
    LampSilent {
        lamp: String,
        command: String,
        tries: u32,
        timeout: Duration,
    },
    /// `detail`: the last reply and the likely cause.
    #[error("{lamp} gave no usable reply to `{command}` in {tries} tries: {detail}")]
    LampGarbled {
        lamp: String,
        command: String,
        tries: u32,
        detail: String,
    },
    #[error("{lamp} answered `{command}` without a line end (got {got}); set lamp.protocol.receive_terminator (now \"{terminator}\") to the line end it sends")]
    LampNoLineEnd {
        lamp: String,
        command: String,
        got: String,
        terminator: &'static str,
    },
    #[error("{lamp} is gone ({reason}): the USB-serial adapter was unplugged or the controller lost power; the lamp's state is unknown: check it, plug it back in and start again")]
    LampGone { lamp: String, reason: String },
    #[error("{lamp} refused `{command}`: {reply}")]
    LampRefused {
        lamp: String,
        command: String,
        reply: String,
    },
    #[error("{lamp} reads back as {got} after `{command}`, expected {expected}; the lamp may be faulty or in local mode")]
    LampState {
        lamp: String,
        command: String,
        expected: LampState,
        got: LampState,
    },
    #[error("{device} is gone (unplugged or its driver was unloaded); plug the camera back in and start again")]
    Unplugged { device: String },
    #[error("the camera flagged frame {sequence} as corrupt ({reason}); check the cable and USB bandwidth")]
    CorruptFrame { sequence: u64, reason: String },
    #[error("cannot open {what}: {reason}")]
    Open { what: String, reason: String },
    #[error("{op}: {source}")]
    Io { op: String, source: std::io::Error },
    #[error("{0}")]
    Operator(String),
    #[error("{0}")]
    Unsupported(String),
}

/// The devices of a rig, opened.
pub struct Devices {
    pub camera: Box<dyn Camera>,
    pub lamp: Box<dyn Lamp>,
    pub operator: Box<dyn Operator>,
    /// The simulated lab behind mock devices (its firmware, its truth), kept alive here.
    pub lab: Option<mock::LabHandle>,
}

/// Why Glint cannot capture with `rig` at all, before any plan is made: a processing
/// rig's camera or lamp (`backend = "external"`) is not Glint's to drive. None otherwise.
pub fn not_drivable(rig: &Rig) -> Option<String> {
    if rig.camera.backend == CameraBackend::External {
        Some("camera.backend = \"external\": Glint does not drive this camera (a processing rig); import its photos with glint import DIR --times FILE --rig RIG [--grid PHOTO] [--dark PHOTO]".into())
    } else if rig.lamp.backend == LampBackend::External {
        Some("lamp.backend = \"external\": Glint cannot switch this lamp, and captures only with a lamp it switches (lamp.backend = \"serial\" or \"mock\"); a processing rig's photos come in with glint import".into())
    } else {
        None
    }
}

/// Open the devices a rig names.
pub fn open(rig: &LoadedRig) -> Result<Devices, DeviceError> {
    let r = &rig.rig;
    match (r.camera.backend, r.lamp.backend) {
        (CameraBackend::External, _) | (_, LampBackend::External) => Err(
            DeviceError::Unsupported(not_drivable(r).unwrap_or_default()),
        ),
        (CameraBackend::Mock, LampBackend::Mock) => mock::open(rig),
        #[cfg(not(feature = "v4l2"))]
        (CameraBackend::V4l2, _) => Err(DeviceError::Unsupported(format!(
            "camera.backend = \"v4l2\" ({}): {V4L2_MISSING}",
            r.camera.device.as_deref().unwrap_or("?")
        ))),
        #[cfg(feature = "v4l2")]
        (CameraBackend::V4l2, LampBackend::Mock) => Err(DeviceError::Unsupported(
            "a V4L2 camera cannot be lit by the simulated lamp (lamp.backend = \"mock\"), which lights only the simulated scene; give the rig its serial lamp (lamp.backend = \"serial\", port = \"/dev/ttyUSB0\"), or use rigs/mock.toml for the whole simulated lab".into(),
        )),
        #[cfg(feature = "v4l2")]
        (CameraBackend::V4l2, LampBackend::Serial) => {
            with_serial_lamp(rig, Box::new(v4l2::V4l2Camera::open(r)?))
        }
        #[cfg(not(feature = "nokhwa"))]
        (CameraBackend::Nokhwa, _) => Err(DeviceError::Unsupported(format!(
            "camera.backend = \"nokhwa\" ({}): {NOKHWA_MISSING}",
            r.camera.device.as_deref().unwrap_or("?")
        ))),
        #[cfg(feature = "nokhwa")]
        (CameraBackend::Nokhwa, LampBackend::Mock) => Err(DeviceError::Unsupported(
            "a nokhwa camera cannot be lit by the simulated lamp (lamp.backend = \"mock\"), which lights only the simulated scene; give the rig its serial lamp (lamp.backend = \"serial\")".into(),
        )),
        #[cfg(feature = "nokhwa")]
        (CameraBackend::Nokhwa, LampBackend::Serial) => {
            with_serial_lamp(rig, Box::new(nokhwa_cam::NokhwaCamera::open(r)?))
        }
        (CameraBackend::Mock, LampBackend::Serial) => mock::open(rig),
    }
}

/// What [`lamp_off`] did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LampOff {
    /// The lamp was sent its `OFF` and read back off (`lamp` says which, e.g. `lamp on
    /// /dev/ttyUSB0`).
    ReadBackOff { lamp: String },
    /// The rig's lamp is the simulated lab's, which lives inside a running Glint and goes
    /// dark with it: nothing outside a Glint process can be on.
    Simulated,
}

/// Switch a rig's lamp off and read it back, opening only the lamp (never the camera, so a
/// camera that is gone or busy does not keep the lamp on): for `glint lamp off`, a
/// service's `ExecStopPost`, and the daemon's first act at its start, before it reads its
/// journal. A lamp port another program holds (a capture or daemon using the lamp) is
/// refused by the port's lock, so this never switches off a lamp in use.
pub fn lamp_off(rig: &LoadedRig) -> Result<LampOff, DeviceError> {
    let r = &rig.rig;
    match r.lamp.backend {
        LampBackend::Mock => Ok(LampOff::Simulated),
        LampBackend::External => Err(DeviceError::Unsupported(
            "lamp.backend = \"external\": Glint cannot switch this lamp (a processing rig); switch it off at the lamp".into(),
        )),
        LampBackend::Serial => {
            let port = r.lamp.port.as_deref().unwrap_or_default();
            let mut lamp = serial_lamp::SerialLamp::open(
                port,
                r.lamp.baud(),
                serial_lamp::LampPolicy::from_rig(&r.lamp)?,
            )?;
            lamp.switch_off()?;
            Ok(LampOff::ReadBackOff {
                lamp: lamp.describe(),
            })
        }
    }
}

/// The devices of a rig whose camera is `camera` and whose lamp is on a serial port.
#[cfg(any(feature = "v4l2", feature = "nokhwa"))]
fn with_serial_lamp(rig: &LoadedRig, camera: Box<dyn Camera>) -> Result<Devices, DeviceError> {
    let r = &rig.rig;
    let port = r.lamp.port.as_deref().unwrap_or_default();
    let lamp = serial_lamp::SerialLamp::open(
        port,
        r.lamp.baud(),
        serial_lamp::LampPolicy::from_rig(&r.lamp)?,
    )?;
    Ok(Devices {
        camera,
        lamp: Box::new(lamp),
        operator: operator::for_rig(r),
        lab: None,
    })
}
