//! Adapters from the simulated lab (`glint-mock`) to the device traits.
//!
//! The camera adapter is thin; the lamp is not adapted at all: the lab's firmware listens on
//! a pseudo-terminal and Glint opens that terminal with the same [`SerialLamp::open`] it
//! uses for `/dev/ttyUSB0`. With `lamp.backend = "serial"` the simulated camera is lit by
//! whatever lamp firmware runs at `lamp.port` in another process (`glint-mock lamp`), whose
//! light reaches the camera through the lab's own light link, not through Glint.

use std::time::Duration;

use glint_mock::{GrabError, Lab, SimCamera, SimOperator, SimPixels};

use glint_format::image::{CameraInfo, Frame, Pixels};

use crate::error::DeviceError;
use crate::opened::Devices;
pub use crate::opened::LabHandle;
use crate::rig::{LoadedRig, Rig};
use crate::serial_lamp::{LampPolicy, SerialLamp};
use crate::traits::{Camera, Operator, OperatorAction};

/// The simulated lab itself, for the benchmark commands that time its parts directly.
pub use glint_mock as sim;

/// The simulated camera as a [`Camera`].
pub struct MockCamera(pub SimCamera);

impl Camera for MockCamera {
    fn info(&self) -> CameraInfo {
        CameraInfo {
            backend: Some("mock".into()),
            pixel_format: (self.0.channels() == 1).then(|| {
                if self.0.bit_depth() == 8 {
                    "GREY"
                } else {
                    "Y16"
                }
                .into()
            }),
            ..CameraInfo::basic(
                "glint-mock simulated camera",
                self.0.width(),
                self.0.height(),
                self.0.bit_depth(),
                self.0.channels(),
            )
        }
    }

    fn set_exposure(&mut self, us: u32) -> Result<u32, DeviceError> {
        Ok(self.0.set_exposure(us))
    }

    fn grab(&mut self, timeout: Duration) -> Result<Frame, DeviceError> {
        // A stalled simulated camera reports the timeout at once rather than idling for it.
        let f = self.0.grab().map_err(|e| match e {
            GrabError::Stalled { .. } => DeviceError::CameraTimeout { after: timeout },
            GrabError::Unplugged { .. } => DeviceError::Unplugged {
                device: "the simulated camera".into(),
            },
        })?;
        Ok(Frame {
            width: f.width,
            height: f.height,
            bit_depth: self.0.bit_depth(),
            channels: self.0.channels(),
            pixels: match f.pixels {
                SimPixels::U8(v) => Pixels::U8(v),
                SimPixels::U16(v) => Pixels::U16(v),
            },
            sequence: f.sequence,
            device_timestamp_us: Some(f.timestamp_us),
            exposure_us: f.reported_exposure_us,
        })
    }
}

/// The lab's operator as an [`Operator`].
pub struct MockOperator(pub SimOperator);

impl Operator for MockOperator {
    fn perform(&mut self, action: OperatorAction) -> Result<(), DeviceError> {
        match action {
            OperatorAction::PlaceTile => self.0.place_tile(),
            OperatorAction::RemoveTile => self.0.remove_tile(),
            OperatorAction::ShowBoard(p) => self.0.show_board(glint_mock::BoardPose::new(
                p.tilt_x_deg as f64,
                p.tilt_y_deg as f64,
                p.rotate_deg as f64,
                p.lift_mm as f64,
            )),
        }
        Ok(())
    }
}

/// Build the simulated lab of a rig and open its devices.
pub fn open(rig: &LoadedRig) -> Result<Devices, DeviceError> {
    let r = &rig.rig;
    if r.lamp.backend == crate::rig::LampBackend::Serial {
        return open_lit_by_serial(rig);
    }
    let mut cfg = r.mock.clone().unwrap_or_default();
    // The in-process firmware speaks the protocol preset the rig's lamp speaks.
    cfg.lamp.preset = glint_mock::config::LampPreset::from_name(r.lamp.protocol.preset.name())
        .unwrap_or_default();
    let lab = Lab::new_with(
        &r.scene_geometry(),
        &cfg,
        r.camera.width,
        r.camera.height,
        r.camera.bit_depth,
        r.camera.channels(),
        &rig.base_dir(),
    )
    .map_err(|e| DeviceError::Open {
        what: "the simulated lab".into(),
        reason: e.to_string(),
    })?;
    let Lab {
        camera,
        lamp: firmware,
        operator,
    } = lab;
    let lamp = SerialLamp::open(
        firmware.port_path(),
        r.lamp.baud(),
        LampPolicy::from_rig(&r.lamp)?,
    )?;
    let ledger = camera.ledger();
    Ok(Devices {
        camera: Box::new(MockCamera(camera)),
        lamp: Box::new(lamp),
        operator: Box::new(MockOperator(operator)),
        lab: Some(LabHandle {
            firmware: Some(firmware),
            ledger,
        }),
    })
}

/// The simulated camera with the rig's serial lamp: the lamp is opened as any serial lamp
/// is, and the camera sees the light of the `glint-mock lamp` firmware at that port (none,
/// with a warning, if the port is not one).
fn open_lit_by_serial(rig: &LoadedRig) -> Result<Devices, DeviceError> {
    let r = &rig.rig;
    let port = r.lamp.port.clone().unwrap_or_default();
    let light = glint_mock::lamp::light_file_for(std::path::Path::new(&port));
    if !light.exists() {
        tracing::warn!(
            "{port} is not a glint-mock lamp ({} does not exist): the simulated camera stays dark whatever the lamp does",
            light.display()
        );
    }
    let cfg = r.mock.clone().unwrap_or_default();
    let (camera, operator) = Lab::camera_lit_by(
        &r.scene_geometry(),
        &cfg,
        r.camera.width,
        r.camera.height,
        r.camera.bit_depth,
        r.camera.channels(),
        &rig.base_dir(),
        &light,
    )
    .map_err(|e| DeviceError::Open {
        what: "the simulated camera".into(),
        reason: e.to_string(),
    })?;
    let lamp = SerialLamp::open(&port, r.lamp.baud(), LampPolicy::from_rig(&r.lamp)?)?;
    let ledger = camera.ledger();
    Ok(Devices {
        camera: Box::new(MockCamera(camera)),
        lamp: Box::new(lamp),
        operator: Box::new(MockOperator(operator)),
        lab: Some(LabHandle {
            firmware: None,
            ledger,
        }),
    })
}

/// The simulated tile as the rig's camera sees it: the truth a run on a simulated rig is
/// scored against. For a monochrome camera (which sees the mean of the three bands'
/// radiance) kd = mean(kd), ks = mean(ks).
#[derive(Debug, Clone, PartialEq)]
pub struct SimulatedTile {
    /// The model's name as the rig's `[mock.tile] model` spells it (`blinn-phong`, ...).
    pub model: String,
    /// Whether the model has a specular lobe (every model but `lambert`).
    pub lobe: bool,
    /// The microfacet roughness α of a `ggx` tile; `None` for the other models.
    pub ggx_alpha: Option<f64>,
    /// The exponent n (unused by a `ggx` tile: see [`SimulatedTile::ggx_alpha`]).
    pub n: f64,
    pub kd: Vec<f64>,
    pub ks: Vec<f64>,
}

/// The rig's simulated tile (`[mock.tile]`) as its camera sees it; `None` for a real rig.
pub fn simulated_tile(rig: &Rig) -> Option<SimulatedTile> {
    let t = &rig.mock.as_ref()?.tile;
    let model = serde_json::to_value(t.model).ok()?;
    let (kd, ks) = if rig.camera.channels() == 1 {
        let mean = |v: [f64; 3]| (v[0] + v[1] + v[2]) / 3.0;
        (vec![mean(t.kd)], vec![mean(t.ks)])
    } else {
        (t.kd.to_vec(), t.ks.to_vec())
    };
    Some(SimulatedTile {
        model: model.as_str().unwrap_or("?").to_string(),
        lobe: t.model != glint_mock::Reflectance::Lambert,
        ggx_alpha: match t.model {
            glint_mock::Reflectance::Ggx => t.alpha,
            _ => None,
        },
        n: t.n,
        kd,
        ks,
    })
}
