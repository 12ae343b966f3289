//! Opening a rig's devices ([`open`]), or its lamp alone to switch it off ([`lamp_off`]).

#[cfg(not(feature = "nokhwa"))]
use crate::backends::NOKHWA_MISSING;
#[cfg(not(feature = "v4l2"))]
use crate::backends::V4L2_MISSING;
use crate::error::DeviceError;
use crate::mock;
#[cfg(feature = "nokhwa")]
use crate::nokhwa_cam;
use crate::opened::Devices;
#[cfg(any(feature = "v4l2", feature = "nokhwa"))]
use crate::operator;
use crate::rig::{CameraBackend, LampBackend, LoadedRig, Rig};
use crate::serial_lamp;
#[cfg(any(feature = "v4l2", feature = "nokhwa"))]
use crate::traits::Camera;
use crate::traits::Lamp;
#[cfg(feature = "v4l2")]
use crate::v4l2;

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
