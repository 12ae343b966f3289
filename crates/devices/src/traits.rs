//! The device traits: a camera, a lamp and an operator, and the actions only hands can do.

use std::time::Duration;

use glint_format::image::{CameraInfo, Frame, LampState};

use crate::error::DeviceError;

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
