//! # glint-mock: the simulated lab
//!
//! A camera looking at a chessboard grid, a material tile that can be placed on it, a point
//! lamp behind a serial lamp controller: everything Glint drives, simulated with its own
//! forward model so that CI and dry runs go through the same code paths as a real rig.
//!
//! Its faces as hardware: the lamp firmware on a pseudo-terminal (speaking Glint's own
//! protocol, a Lumencor Spectra III's or a CoolLED pE-300's: see [`lamp`]), and the camera as
//! a V4L2 device that any Linux program can open, through the preload library
//! `glint-sim-v4l2` and the launcher `glint-mock v4l2 --rig RIG -- CMD` (see [`v4l2`] and the
//! binary's help).
//!
//! The lab also runs as separate processes: `glint-mock lamp --link PATH` is the lamp
//! firmware alone, publishing its light in a file beside its port ([`light_file_for`]), and
//! a camera built with [`Lab::camera_lit_by`] is lit through that file;
//! `glint-mock lab --rig RIG -- CMD` runs both so.
//!
//! The crate knows nothing of Glint's pipeline and never calls Glint's code: Glint adapts it
//! to its `Camera` and `Lamp` traits exactly as it adapts real hardware, and the lamp is only
//! reachable through a pseudo-terminal speaking the lamp protocol.
//!
//! ```no_run
//! use glint_mock::{Lab, MockConfig, SceneGeometry};
//! let geometry = SceneGeometry {
//!     lamp_position_mm: [100.0, 350.0, 300.0],
//!     tile_thickness_mm: 5.0,
//!     tile_outline_mm: vec![[50.0, 30.0], [150.0, 30.0], [150.0, 130.0], [50.0, 130.0]],
//!     grid_inner_corners: [9, 6],
//!     grid_square_mm: 25.0,
//!     reference: None,
//! };
//! let mut lab = Lab::new(&geometry, &MockConfig::default(), 640, 480, 8, std::path::Path::new(".")).unwrap();
//! println!("lamp controller on {}", lab.lamp.port_path());
//! let frame = lab.camera.grab().unwrap();
//! ```

pub mod camera;
pub mod config;
pub mod encode;
pub mod lamp;
pub mod optics;
pub mod rigfile;
pub mod sensor;
pub mod v4l2;

use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Duration;

pub use camera::{GrabError, LedgerEntry, SimCamera, SimFrame, SimPixels};
pub use config::{LampPreset, MockConfig, Reflectance, ResponseConfig};
pub use lamp::{light_file_for, LampFirmware, LampPhysics};
pub use optics::{BoardPose, PosedCamera, ReferenceTarget, SceneGeometry, SceneKind};

/// Errors setting up the lab.
#[derive(Debug, thiserror::Error)]
pub enum MockError {
    #[error("{0}")]
    Config(String),
    #[error("{0}")]
    Device(String),
}

/// The lab's operator: the hands that place the tile on the grid and take it away.
#[derive(Debug, Clone)]
pub struct SimOperator {
    scene: Arc<Mutex<SceneKind>>,
}

impl SimOperator {
    /// Put the tile on the grid.
    pub fn place_tile(&self) {
        *self.scene.lock().unwrap() = SceneKind::Tile;
    }
    /// Take the tile away so the whole grid is visible.
    pub fn remove_tile(&self) {
        *self.scene.lock().unwrap() = SceneKind::Grid;
    }
    /// Lift the board off the floor (the tile removed) and hold it in `pose`.
    pub fn show_board(&self, pose: BoardPose) {
        *self.scene.lock().unwrap() = SceneKind::Board(pose);
    }
    pub fn scene(&self) -> SceneKind {
        *self.scene.lock().unwrap()
    }
}

/// A complete simulated lab: camera, lamp firmware on a pseudo-terminal, and operator.
pub struct Lab {
    pub camera: SimCamera,
    pub lamp: LampFirmware,
    pub operator: SimOperator,
}

impl Lab {
    /// Build the lab for a `width` x `height` RGB camera of `bit_depth` bits (8 or 16).
    /// `base` is the folder that relative paths in `cfg` (an EMoR file) are relative to.
    pub fn new(
        geometry: &SceneGeometry,
        cfg: &MockConfig,
        width: u32,
        height: u32,
        bit_depth: u8,
        base: &Path,
    ) -> Result<Lab, MockError> {
        Lab::new_with(geometry, cfg, width, height, bit_depth, 3, base)
    }

    /// [`Lab::new`] for a camera of `channels` samples a pixel: 3 (RGB) or 1 (a monochrome
    /// sensor, which sees the mean of the three bands).
    pub fn new_with(
        geometry: &SceneGeometry,
        cfg: &MockConfig,
        width: u32,
        height: u32,
        bit_depth: u8,
        channels: u8,
        base: &Path,
    ) -> Result<Lab, MockError> {
        let physics = Arc::new(LampPhysics::new(Duration::from_millis(cfg.lamp.warmup_ms)));
        let (camera, operator) = assemble(
            geometry,
            cfg,
            width,
            height,
            bit_depth,
            channels,
            base,
            Arc::clone(&physics),
        )?;
        let lamp = LampFirmware::spawn(&cfg.lamp, &cfg.faults, physics, cfg.seed)?;
        Ok(Lab {
            camera,
            lamp,
            operator,
        })
    }

    /// The simulated camera and operator of [`Lab::new_with`], lit by the lamp whose
    /// firmware (in another process: `glint-mock lamp`) publishes its light at `light_file`
    /// (see [`light_file_for`]). No lamp firmware runs in this process; while the light
    /// file is missing or malformed the lamp is dark.
    #[allow(clippy::too_many_arguments)]
    pub fn camera_lit_by(
        geometry: &SceneGeometry,
        cfg: &MockConfig,
        width: u32,
        height: u32,
        bit_depth: u8,
        channels: u8,
        base: &Path,
        light_file: &Path,
    ) -> Result<(SimCamera, SimOperator), MockError> {
        let physics = Arc::new(LampPhysics::remote(light_file));
        assemble(
            geometry, cfg, width, height, bit_depth, channels, base, physics,
        )
    }
}

/// The camera and operator of a lab whose lamp is `physics`.
#[allow(clippy::too_many_arguments)]
fn assemble(
    geometry: &SceneGeometry,
    cfg: &MockConfig,
    width: u32,
    height: u32,
    bit_depth: u8,
    channels: u8,
    base: &Path,
    physics: Arc<LampPhysics>,
) -> Result<(SimCamera, SimOperator), MockError> {
    if channels != 1 && channels != 3 {
        return Err(MockError::Config(format!(
            "a camera of {channels} channels is not simulated; use 1 (mono) or 3 (RGB)"
        )));
    }
    if let Some((key, msg)) = cfg.problems().into_iter().next() {
        return Err(MockError::Config(format!("mock.{key}: {msg}")));
    }
    let scene = Arc::new(Mutex::new(SceneKind::Tile));
    let sensor = sensor::Sensor::new(&cfg.sensor, bit_depth, cfg.seed, base)?;
    let mut camera = SimCamera::assemble(
        width,
        height,
        bit_depth,
        PosedCamera::new(&cfg.camera, width, height),
        geometry.clone(),
        cfg.tile.clone(),
        cfg.grid.clone(),
        cfg.lamp.intensity,
        Arc::clone(&scene),
        physics,
        sensor,
        cfg.faults.clone(),
        cfg.sensor.exposure_latency_frames,
        cfg.sensor.reports_exposure,
        cfg.sensor.fps,
    );
    camera.channels = channels;
    camera.realtime = cfg.sensor.realtime.then(std::time::Instant::now);
    Ok((camera, SimOperator { scene }))
}
