//! Devices: the camera, the lamp and the operator, behind small traits.
//!
//! Every device reports what it actually did (the exposure the camera reads back, the lamp
//! state read back over the wire), never an echo of the request. Devices are opened by one
//! factory, [`open`], into boxed trait objects; the simulated lab goes down exactly the same
//! path as hardware (its lamp even through the real serial driver, over a pseudo-terminal),
//! so the capture engine has no test-only branches.

//! This root only declares the modules and re-exports their items (the paths stay
//! `glint_devices::open`, `glint_devices::Camera`, ...): every item lives in a module,
//! so that no module depends on the root that depends on it.

pub mod backends;
pub mod decode;
pub mod error;
pub mod lamp_protocol;
pub mod mock;
#[cfg(feature = "nokhwa")]
pub mod nokhwa_cam;
pub mod open;
pub mod opened;
pub mod operator;
pub mod rig;
pub mod serial_lamp;
pub mod traits;
#[cfg(feature = "v4l2")]
pub mod v4l2;
pub mod v4l2_rules;

pub use glint_format::image::{CameraInfo, ControlReading, Frame, LampState, Pixels};

pub use backends::{
    check_backends, BackendCheck, NOKHWA_BUILT, NOKHWA_MISSING, V4L2_BUILT, V4L2_MISSING,
};
pub use error::DeviceError;
pub use open::{lamp_off, not_drivable, open, LampOff};
pub use opened::Devices;
pub use operator::ConsoleOperator;
pub use traits::{BoardPose, Camera, Lamp, Operator, OperatorAction};
