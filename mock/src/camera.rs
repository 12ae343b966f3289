//! The simulated camera: optics + sensor + the habits of real webcams.
//!
//! Frames are produced on demand with a simulated clock (a frame lasts the longer of its
//! exposure and the frame period). A new exposure takes effect `exposure_latency_frames`
//! frames after it is set, as on UVC webcams; the control read-back echoes the request, as
//! V4L2 does, so only frame metadata (when `reports_exposure`) or the image itself tells the
//! truth. Every frame the sensor produces, delivered or dropped, is written to a ledger with
//! its true exposure, so tests can check what the controller kept.

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};

use crate::config::{Faults, GridAlbedo, TrueTile};
use crate::lamp::LampPhysics;
use crate::optics::{render_radiance, PosedCamera, SceneGeometry, SceneKind, World};
use crate::sensor::Sensor;

/// Pixel data, RGB interleaved (or one sample a pixel from a mono sensor), rows top to bottom.
#[derive(Debug, Clone, PartialEq)]
pub enum SimPixels {
    U8(Vec<u8>),
    U16(Vec<u16>),
}

/// One delivered frame.
#[derive(Debug, Clone)]
pub struct SimFrame {
    pub width: u32,
    pub height: u32,
    pub pixels: SimPixels,
    /// Driver sequence number; gaps mean dropped frames.
    pub sequence: u64,
    /// Simulated device clock at the start of exposure, microseconds.
    pub timestamp_us: u64,
    /// The exposure the frame was taken with, if the camera reports it.
    pub reported_exposure_us: Option<u32>,
}

/// What the ledger knows about every frame the sensor produced.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LedgerEntry {
    pub sequence: u64,
    pub true_exposure_us: u32,
    pub lamp_output: f64,
    pub scene: SceneKind,
    pub delivered: bool,
}

/// Why a grab failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum GrabError {
    #[error("no frame arrived (the simulated camera stalled at frame {frame})")]
    Stalled { frame: u64 },
    #[error("the simulated camera was unplugged at frame {frame}")]
    Unplugged { frame: u64 },
}

/// The simulated camera.
pub struct SimCamera {
    pub(crate) width: u32,
    pub(crate) height: u32,
    pub(crate) bit_depth: u8,
    /// 3 (RGB sensor) or 1 (monochrome sensor).
    pub(crate) channels: u8,
    pub(crate) cam: PosedCamera,
    pub(crate) geometry: SceneGeometry,
    pub(crate) tile: TrueTile,
    pub(crate) albedo: GridAlbedo,
    pub(crate) intensity: f64,
    pub(crate) scene: Arc<Mutex<SceneKind>>,
    pub(crate) lamp: Arc<LampPhysics>,
    pub(crate) sensor: Sensor,
    pub(crate) faults: Faults,
    pub(crate) latency: u32,
    pub(crate) reports_exposure: bool,
    pub(crate) frame_period_us: f64,
    /// Wall-clock start, when frames are delivered in real time.
    pub(crate) realtime: Option<std::time::Instant>,
    pub(crate) ledger: Arc<Mutex<Vec<LedgerEntry>>>,
    radiance: HashMap<SceneKind, Arc<Vec<f32>>>,
    mono: HashMap<SceneKind, Arc<Vec<f32>>>,
    produced: u64,
    time_us: f64,
    exposure_us: u32,
    requested_us: u32,
    pending: VecDeque<(u64, u32)>,
}

impl SimCamera {
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn assemble(
        width: u32,
        height: u32,
        bit_depth: u8,
        cam: PosedCamera,
        geometry: SceneGeometry,
        tile: TrueTile,
        albedo: GridAlbedo,
        intensity: f64,
        scene: Arc<Mutex<SceneKind>>,
        lamp: Arc<LampPhysics>,
        sensor: Sensor,
        faults: Faults,
        latency: u32,
        reports_exposure: bool,
        fps: f64,
    ) -> Self {
        SimCamera {
            width,
            height,
            bit_depth,
            channels: 3,
            cam,
            geometry,
            tile,
            albedo,
            intensity,
            scene,
            lamp,
            sensor,
            faults,
            latency,
            reports_exposure,
            frame_period_us: 1e6 / fps,
            realtime: None,
            ledger: Arc::new(Mutex::new(Vec::new())),
            radiance: HashMap::new(),
            mono: HashMap::new(),
            produced: 0,
            time_us: 0.0,
            exposure_us: 10_000,
            requested_us: 10_000,
            pending: VecDeque::new(),
        }
    }

    pub fn width(&self) -> u32 {
        self.width
    }
    pub fn height(&self) -> u32 {
        self.height
    }
    pub fn bit_depth(&self) -> u8 {
        self.bit_depth
    }
    /// Samples a pixel: 3 (RGB interleaved) or 1 (monochrome).
    pub fn channels(&self) -> u8 {
        self.channels
    }

    /// The true camera (for tests and later calibration checks).
    pub fn true_camera(&self) -> &PosedCamera {
        &self.cam
    }

    /// Every frame produced so far, with its true exposure.
    pub fn ledger(&self) -> Arc<Mutex<Vec<LedgerEntry>>> {
        Arc::clone(&self.ledger)
    }

    /// Request an exposure. Returns the control's value as read back, which, as with
    /// V4L2, is the request, whether or not (or when) the sensor applies it.
    pub fn set_exposure(&mut self, us: u32) -> u32 {
        self.requested_us = us;
        if !self.faults.ignore_exposure_us.contains(&us) {
            self.pending
                .push_back((self.produced + self.latency as u64, us));
        }
        self.requested_us
    }

    /// The simulated device clock, µs: the end of the last frame produced (frames,
    /// dropped ones included, follow one another without gaps while frames are asked for).
    pub fn clock_us(&self) -> f64 {
        self.time_us
    }

    /// Frames produced so far, dropped ones included (the next frame's number).
    pub fn produced(&self) -> u64 {
        self.produced
    }

    /// Change the frame rate (frames last the longer of their exposure and 1/fps).
    pub fn set_fps(&mut self, fps: f64) {
        if fps.is_finite() && fps > 0.0 {
            self.frame_period_us = 1e6 / fps;
        }
    }

    /// The exposure control's current value.
    pub fn exposure_control(&self) -> u32 {
        self.requested_us
    }

    /// The radiance image of a scene, rendered on first use.
    pub fn radiance(&mut self, kind: SceneKind) -> Arc<Vec<f32>> {
        if let Some(r) = self.radiance.get(&kind) {
            return Arc::clone(r);
        }
        let world = World {
            geometry: &self.geometry,
            tile: &self.tile,
            albedo: &self.albedo,
            intensity: self.intensity,
            kind,
        };
        let r = Arc::new(render_radiance(&self.cam, &world, self.width, self.height));
        self.radiance.insert(kind, Arc::clone(&r));
        r
    }

    /// The radiance the sensor's pixels see: the scene's RGB radiance, or for a monochrome
    /// sensor its mean over the three channels (a panchromatic sensor whose spectral
    /// response is flat over the simulated world's three bands; so a mono camera sees a
    /// tile of kd = mean(kd), ks = mean(ks), the same n).
    fn sensor_radiance(&mut self, kind: SceneKind) -> Arc<Vec<f32>> {
        if self.channels == 3 {
            return self.radiance(kind);
        }
        if let Some(r) = self.mono.get(&kind) {
            return Arc::clone(r);
        }
        let rgb = self.radiance(kind);
        let r = Arc::new(
            rgb.chunks_exact(3)
                .map(|p| (p[0] + p[1] + p[2]) / 3.0)
                .collect::<Vec<f32>>(),
        );
        self.mono.insert(kind, Arc::clone(&r));
        r
    }

    /// Produce the next frame, or fail as the configured faults say.
    pub fn grab(&mut self) -> Result<SimFrame, GrabError> {
        loop {
            let n = self.produced;
            if self.faults.unplug_at_frame.is_some_and(|u| n >= u) {
                return Err(GrabError::Unplugged { frame: n });
            }
            if self.faults.stall_at_frame.is_some_and(|s| n >= s) {
                return Err(GrabError::Stalled { frame: n });
            }
            while self.pending.front().is_some_and(|(at, _)| *at <= n) {
                self.exposure_us = self.pending.pop_front().unwrap().1;
            }
            let scene = *self.scene.lock().unwrap();
            let lamp = self.lamp.output();
            let exposure = self.exposure_us;
            let duration_us = (exposure as f64).max(self.frame_period_us);
            if let Some(start) = self.realtime {
                // The sensor idles while nobody asks for frames; then a frame takes its time.
                self.time_us = self.time_us.max(start.elapsed().as_secs_f64() * 1e6);
                std::thread::sleep(std::time::Duration::from_micros(duration_us as u64));
            }
            let timestamp_us = self.time_us as u64;
            self.time_us += duration_us;
            self.produced += 1;
            let delivered = !self.faults.drop_frames.contains(&n);
            self.ledger.lock().unwrap().push(LedgerEntry {
                sequence: n,
                true_exposure_us: exposure,
                lamp_output: lamp,
                scene,
                delivered,
            });
            if !delivered {
                continue;
            }
            let radiance = self.sensor_radiance(scene);
            let w = self.width as usize;
            let ch = self.channels as usize;
            // A corrupt transfer delivers only half the bytes.
            let keep = if self.faults.corrupt_frames.contains(&n) {
                radiance.len() / 2
            } else {
                radiance.len()
            };
            let pixels = if self.bit_depth == 8 {
                let mut out = vec![0u8; radiance.len()];
                self.sensor
                    .expose(&radiance, w, ch, lamp, exposure as f64, &mut out);
                out.truncate(keep);
                SimPixels::U8(out)
            } else {
                let mut out = vec![0u16; radiance.len()];
                self.sensor
                    .expose(&radiance, w, ch, lamp, exposure as f64, &mut out);
                out.truncate(keep);
                SimPixels::U16(out)
            };
            return Ok(SimFrame {
                width: self.width,
                height: self.height,
                pixels,
                sequence: n,
                timestamp_us,
                reported_exposure_us: self.reports_exposure.then_some(exposure),
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::config::MockConfig;
    use crate::{GrabError, Lab, SceneGeometry};

    fn geometry() -> SceneGeometry {
        SceneGeometry {
            lamp_position_mm: [100.0, 350.0, 300.0],
            tile_thickness_mm: 5.0,
            tile_outline_mm: vec![[50.0, 30.0], [150.0, 30.0], [150.0, 130.0], [50.0, 130.0]],
            grid_inner_corners: [9, 6],
            grid_square_mm: 25.0,
            reference: None,
        }
    }

    #[test]
    fn an_unplugged_camera_delivers_nothing_more() {
        let mut cfg = MockConfig::default();
        cfg.faults.unplug_at_frame = Some(2);
        cfg.faults.drop_frames = vec![1];
        let mut lab = Lab::new(&geometry(), &cfg, 32, 24, 8, std::path::Path::new(".")).unwrap();
        assert_eq!(lab.camera.grab().unwrap().sequence, 0);
        assert_eq!(
            lab.camera.grab().unwrap_err(),
            GrabError::Unplugged { frame: 2 }
        );
        assert_eq!(
            lab.camera.grab().unwrap_err(),
            GrabError::Unplugged { frame: 2 }
        );
    }

    #[test]
    fn a_stall_before_the_unplug_is_refused() {
        let mut cfg = MockConfig::default();
        cfg.faults.unplug_at_frame = Some(5);
        cfg.faults.stall_at_frame = Some(3);
        let problems = cfg.problems();
        assert!(
            problems.iter().any(|(k, _)| k == "faults.unplug_at_frame"),
            "{problems:?}"
        );
    }
}
