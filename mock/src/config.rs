//! The `[mock]` section of a rig file: the simulated lab's ground truth.
//!
//! These types are owned by the simulator, not by Glint: Glint's rig loader embeds them
//! as they are, so the truth the simulator renders is written in exactly one place.
//! Every field has a default, so `[mock]` with nothing in it is a working lab.

use serde::{Deserialize, Serialize};

/// Everything the simulated lab needs beyond the rig's shared geometry.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MockConfig {
    /// Seed for every random number the lab draws (sensor noise, garbled bytes).
    pub seed: u64,
    /// The true camera: intrinsics, distortion and where it stands.
    pub camera: TrueCamera,
    /// The true reflectance of the tile.
    pub tile: TrueTile,
    /// Albedos of the grid floor.
    pub grid: GridAlbedo,
    /// The sensor: response, noise, quantisation, latency.
    pub sensor: SensorConfig,
    /// The lamp firmware.
    pub lamp: LampConfig,
    /// Faults to inject.
    pub faults: Faults,
    /// The reflectance standard's true albedo, where the rig has a `[reference]`
    /// (default: its certificate's value).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reference: Option<TrueReference>,
}

/// `[mock.reference]`: what the reference standard really reflects (its certificate may
/// say otherwise, within its stated uncertainty or not).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrueReference {
    /// Albedo per channel (R, G, B).
    #[serde(deserialize_with = "exactly")]
    pub albedo: [f64; 3],
}

impl Default for MockConfig {
    fn default() -> Self {
        MockConfig {
            seed: 1,
            camera: TrueCamera::default(),
            tile: TrueTile::default(),
            grid: GridAlbedo::default(),
            sensor: SensorConfig::default(),
            lamp: LampConfig::default(),
            faults: Faults::default(),
            reference: None,
        }
    }
}

/// The camera's true parameters (docs/design.md camera model).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrueCamera {
    /// Focal lengths in pixels at the rig's resolution.
    pub fx: f64,
    pub fy: f64,
    /// Principal point in pixels; `None` means the image centre.
    pub cx: Option<f64>,
    pub cy: Option<f64>,
    /// Radial distortion, d = 1 + k1 r^2 + k2 r^4.
    pub k1: f64,
    pub k2: f64,
    /// Camera centre in grid coordinates (mm).
    #[serde(deserialize_with = "exactly")]
    pub position_mm: [f64; 3],
    /// The grid point the optical axis passes through (mm).
    #[serde(deserialize_with = "exactly")]
    pub look_at_mm: [f64; 3],
    /// Rotation about the optical axis, degrees.
    pub roll_deg: f64,
}

impl Default for TrueCamera {
    fn default() -> Self {
        TrueCamera {
            fx: 1500.0,
            fy: 1500.0,
            cx: None,
            cy: None,
            k1: -0.08,
            k2: 0.02,
            position_mm: [100.0, -250.0, 380.0],
            look_at_mm: [100.0, 60.0, 0.0],
            roll_deg: 0.0,
        }
    }
}

/// Reflectance models the lab can render (formulas of docs/design.md).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Reflectance {
    Lambert,
    Phong,
    BlinnPhong,
    CosineLobe,
    /// Cook-Torrance: GGX distribution of roughness `alpha`, Smith's separable shadowing,
    /// Schlick's Fresnel with `ks` as F0 per channel (`n` unused).
    Ggx,
}

/// The tile's true reflectance: per-channel kd and ks, shared exponent n.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrueTile {
    pub model: Reflectance,
    #[serde(deserialize_with = "exactly")]
    pub kd: [f64; 3],
    #[serde(deserialize_with = "exactly")]
    pub ks: [f64; 3],
    pub n: f64,
    /// The GGX tile's roughness (model `ggx` only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub alpha: Option<f64>,
}

impl Default for TrueTile {
    fn default() -> Self {
        TrueTile {
            model: Reflectance::BlinnPhong,
            kd: [0.35, 0.25, 0.18],
            ks: [0.5, 0.5, 0.5],
            n: 120.0,
            alpha: None,
        }
    }
}

/// Lambertian albedos of the floor the tile rests on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GridAlbedo {
    pub light: f64,
    pub dark: f64,
    /// Beyond the printed board.
    pub surround: f64,
}

impl Default for GridAlbedo {
    fn default() -> Self {
        GridAlbedo {
            light: 0.8,
            dark: 0.06,
            surround: 0.4,
        }
    }
}

/// The camera's response curve: normalised exposure in [0, 1] -> normalised value in [0, 1].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, tag = "kind", rename_all = "kebab-case")]
pub enum ResponseConfig {
    /// value = x.
    Linear,
    /// value = x^(1/gamma).
    Gamma { gamma: f64 },
    /// Grossberg & Nayar's EMoR: f0 + sum c_k h_k, read from `emor.txt`
    /// (a path relative to the rig file's folder, or absolute).
    Emor {
        file: String,
        coefficients: Vec<f64>,
    },
}

/// Sensor model: electrons, noise, quantisation, latency.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SensorConfig {
    pub response: ResponseConfig,
    /// Electrons per unit scene radiance per microsecond of exposure at full lamp output.
    pub electrons_per_radiance_us: f64,
    /// Charge at saturation.
    pub full_well_e: f64,
    /// Read noise, electrons rms.
    pub read_noise_e: f64,
    /// Dark current, electrons per second.
    pub dark_current_e_per_s: f64,
    /// Simulate shot and read noise (false: a noise-free sensor, for tests of what
    /// quantisation alone does).
    pub noise: bool,
    /// Fraction of charge above the full well that spills into the four neighbours.
    pub blooming: f64,
    /// A new exposure takes effect this many frames after it is set (UVC webcams: 1 to 3).
    pub exposure_latency_frames: u32,
    /// Whether each frame carries the exposure it was really taken with (as metadata).
    pub reports_exposure: bool,
    /// Frame rate when exposures are shorter than a frame period.
    pub fps: f64,
    /// Deliver frames in real time (a frame takes its exposure or frame period on the wall
    /// clock, as on hardware), so the lamp's warm-up, which runs on the wall clock, shows in
    /// the frames. Off by default: frames come as fast as they are computed.
    pub realtime: bool,
}

impl Default for SensorConfig {
    fn default() -> Self {
        SensorConfig {
            response: ResponseConfig::Gamma { gamma: 2.2 },
            electrons_per_radiance_us: 0.05,
            full_well_e: 20000.0,
            read_noise_e: 4.0,
            dark_current_e_per_s: 20.0,
            noise: true,
            blooming: 0.0,
            exposure_latency_frames: 2,
            reports_exposure: true,
            fps: 30.0,
            realtime: false,
        }
    }
}

/// Lamp firmware.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LampConfig {
    /// Radiant intensity at level 1000 (arbitrary units; sets the scene's brightness).
    pub intensity: f64,
    /// Time the lamp takes to reach full output after `ON` (linear ramp), milliseconds.
    pub warmup_ms: u64,
    /// What `*IDN?` answers.
    pub identity: String,
    /// A file the firmware appends every command line it receives to (one a line), as a
    /// lamp controller's own log would show them: how a test that runs Glint as another
    /// process sees what reached the lamp. Relative paths are relative to Glint's working
    /// folder.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub command_log: Option<String>,
    /// The protocol the firmware speaks (`glint`, `lumencor` or `coolled`).
    pub preset: LampPreset,
}

impl Default for LampConfig {
    fn default() -> Self {
        LampConfig {
            intensity: 1.0e6,
            warmup_ms: 200,
            identity: "GLINT-MOCK-LAMP,1.0".to_string(),
            command_log: None,
            preset: LampPreset::Glint,
        }
    }
}

/// The protocols the simulated lamp firmware speaks (see [`crate::lamp::protocol`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LampPreset {
    /// Glint's own line protocol (docs/design.md): `*IDN?`, `LEVEL n`, `ON`, `OFF`, `STATE?`.
    #[default]
    Glint,
    /// A Lumencor Spectra III in standard mode, one channel (WHITE).
    Lumencor,
    /// A CoolLED pE-300: channels A, B, C; the lamp is channel A.
    Coolled,
}

impl LampPreset {
    pub const ALL: [LampPreset; 3] = [LampPreset::Glint, LampPreset::Lumencor, LampPreset::Coolled];

    /// The name in rig files and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            LampPreset::Glint => "glint",
            LampPreset::Lumencor => "lumencor",
            LampPreset::Coolled => "coolled",
        }
    }

    /// The preset called `name`, if the lamp speaks it.
    pub fn from_name(name: &str) -> Option<LampPreset> {
        LampPreset::ALL.into_iter().find(|p| p.name() == name)
    }

    /// The line terminator of the preset's replies.
    pub fn terminator(self) -> &'static str {
        match self {
            LampPreset::Glint => "\n",
            LampPreset::Lumencor | LampPreset::Coolled => "\r\n",
        }
    }
}

impl std::fmt::Display for LampPreset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Faults switched on from the rig file. Frame numbers count every frame the sensor
/// produces, from 0, including dropped ones. Reply numbers of the lamp (`lamp_*_replies`)
/// count, from 1, the reply lines the firmware sends: echoed commands, trailers and the
/// greeting are not replies.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Faults {
    /// These frames are never delivered (the sequence number jumps over them).
    pub drop_frames: Vec<u64>,
    /// These frames arrive truncated (half their bytes), as from a broken transfer.
    pub corrupt_frames: Vec<u64>,
    /// From this frame on the camera delivers nothing (every grab times out).
    pub stall_at_frame: Option<u64>,
    /// At this frame the camera is unplugged: it delivers nothing more and every later
    /// request fails as with a yanked USB camera (V4L2: ENODEV).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub unplug_at_frame: Option<u64>,
    /// Exposures (µs) the camera accepts but silently does not apply.
    pub ignore_exposure_us: Vec<u32>,
    /// The lamp answers this many commands, then never again.
    pub lamp_silent_after: Option<u32>,
    /// These replies (1-based count of replies sent) are garbled on the wire.
    pub lamp_garble_replies: Vec<u32>,
    /// The lamp echoes every command line it receives (without its terminator, then the
    /// reply terminator) before it handles it.
    pub lamp_echo: bool,
    /// A line the lamp sends after every reply that is not an error (e.g. `OK`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lamp_trailer: Option<String>,
    /// The terminator of every line the lamp sends, overriding its preset's: `lf`, `cr`,
    /// `crlf` or `none` (none: no terminator at all).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lamp_terminator: Option<String>,
    /// Late replies come this long after their command arrived, ms (0: none is late).
    pub lamp_late_ms: u64,
    /// The replies that are late; empty (with `lamp_late_ms` > 0): every reply.
    pub lamp_late_replies: Vec<u32>,
    /// These replies are sent in two pieces: the first half of their bytes, then the rest
    /// (with the terminator) `lamp_split_ms` later.
    pub lamp_split_replies: Vec<u32>,
    /// The pause between the two pieces of a split reply, ms.
    pub lamp_split_ms: u64,
    /// These replies are replaced by `lamp_overlong_bytes` printable ASCII bytes (no
    /// terminator among them), then the terminator.
    pub lamp_overlong_replies: Vec<u32>,
    pub lamp_overlong_bytes: usize,
    /// These replies are the preset's error reply (`ERR 9 busy`, `E BUSY`, `ERROR busy`) and
    /// their commands are not executed.
    pub lamp_error_replies: Vec<u32>,
}

impl Default for Faults {
    fn default() -> Self {
        Faults {
            drop_frames: Vec::new(),
            corrupt_frames: Vec::new(),
            stall_at_frame: None,
            unplug_at_frame: None,
            ignore_exposure_us: Vec::new(),
            lamp_silent_after: None,
            lamp_garble_replies: Vec::new(),
            lamp_echo: false,
            lamp_trailer: None,
            lamp_terminator: None,
            lamp_late_ms: 0,
            lamp_late_replies: Vec::new(),
            lamp_split_replies: Vec::new(),
            lamp_split_ms: 0,
            lamp_overlong_replies: Vec::new(),
            lamp_overlong_bytes: DEFAULT_OVERLONG_BYTES,
            lamp_error_replies: Vec::new(),
        }
    }
}

/// The default length of an overlong lamp reply, bytes.
pub const DEFAULT_OVERLONG_BYTES: usize = 100_000;

/// The terminators `lamp_terminator` names, with their bytes.
pub const LAMP_TERMINATORS: [(&str, &str); 4] =
    [("lf", "\n"), ("cr", "\r"), ("crlf", "\r\n"), ("none", "")];

impl Faults {
    /// The terminator named by `lamp_terminator`, if it names one.
    pub fn lamp_terminator_bytes(&self) -> Option<&'static str> {
        let name = self.lamp_terminator.as_deref()?;
        LAMP_TERMINATORS
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, t)| *t)
    }
}

/// Bounds of the simulated lab's values: each far beyond a real scene, small enough that
/// the simulation stays finite (and each named in the error that refuses a value beyond it).
pub const MAX_LENGTH_MM: f64 = 100_000.0;
/// Focal lengths and principal points, pixels.
pub const MAX_PIXELS: f64 = 1.0e6;
/// |k1|, |k2|.
pub const MAX_DISTORTION: f64 = 10.0;
/// kd, ks.
pub const MAX_REFLECTANCE: f64 = 100.0;
/// The tile's exponent n.
pub const MAX_EXPONENT: f64 = 1.0e5;
/// Electron counts and rates (full well, read noise, dark current, electrons per unit).
pub const MAX_ELECTRONS: f64 = 1.0e9;
/// The lamp's intensity.
pub const MAX_INTENSITY: f64 = 1.0e15;
/// Frame rates, frames per second.
pub const MIN_FPS: f64 = 0.01;
pub const MAX_FPS: f64 = 1000.0;
/// Lamp warm-up, ms: 1 hour.
pub const MAX_WARMUP_MS: u64 = 3_600_000;
/// Exposure latency, frames.
pub const MAX_LATENCY_FRAMES: u32 = 1000;
/// Entries of each fault list.
pub const MAX_FAULTS: usize = 10_000;
/// Longest text (the lamp's identity, a file name), bytes.
pub const MAX_TEXT_BYTES: usize = 4096;
/// The lamp's late replies and the pause in split ones, ms: 10 minutes.
pub const MAX_LAMP_DELAY_MS: u64 = 600_000;
/// An overlong lamp reply, bytes: 16 MiB.
pub const MAX_OVERLONG_BYTES: usize = 16 << 20;

impl MockConfig {
    /// Problems with the configuration, each as (key below `mock.`, what is wrong and how to fix it).
    pub fn problems(&self) -> Vec<(String, String)> {
        let mut ck = Checks::default();
        let c = &self.camera;
        for (key, v) in [("camera.fx", c.fx), ("camera.fy", c.fy)] {
            if v.is_finite() && v <= 0.0 {
                ck.bad(
                    key,
                    format!(
                        "focal lengths must be positive pixels (got fx={}, fy={})",
                        c.fx, c.fy
                    ),
                );
            } else {
                ck.number(key, v, 1.0, MAX_PIXELS, " pixels");
            }
        }
        for (key, v) in [("camera.cx", c.cx), ("camera.cy", c.cy)] {
            if let Some(v) = v {
                ck.number(key, v, -MAX_PIXELS, MAX_PIXELS, " pixels");
            }
        }
        ck.number("camera.k1", c.k1, -MAX_DISTORTION, MAX_DISTORTION, "");
        ck.number("camera.k2", c.k2, -MAX_DISTORTION, MAX_DISTORTION, "");
        ck.number("camera.roll_deg", c.roll_deg, -360.0, 360.0, " degrees");
        let position_ok = ck.point("camera.position_mm", &c.position_mm);
        let look_ok = ck.point("camera.look_at_mm", &c.look_at_mm);
        if position_ok && c.position_mm[2] <= 0.0 {
            ck.bad(
                "camera.position_mm",
                "the camera must be above the grid (z > 0 mm)",
            );
        }
        if position_ok && look_ok {
            let dir = [
                c.look_at_mm[0] - c.position_mm[0],
                c.look_at_mm[1] - c.position_mm[1],
                c.look_at_mm[2] - c.position_mm[2],
            ];
            let len = (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]).sqrt();
            if len == 0.0 {
                ck.bad("camera.look_at_mm", "must differ from camera.position_mm");
            } else if (dir[0] * dir[0] + dir[1] * dir[1]).sqrt() < 1e-6 * len {
                ck.bad(
                    "camera.look_at_mm",
                    "the camera looks straight down; tilt it slightly (move look_at_mm in x or y) so its roll is defined",
                );
            }
        }
        let t = &self.tile;
        for (key, v) in [("tile.kd", &t.kd), ("tile.ks", &t.ks)] {
            if let Some(x) = v.iter().find(|x| !x.is_finite()) {
                ck.bad(key, format!("each must be a finite number (got {x})"));
            } else if v.iter().any(|x| *x < 0.0) {
                ck.bad(key, "kd and ks must be non-negative");
            } else if let Some(x) = v.iter().find(|x| **x > MAX_REFLECTANCE) {
                ck.bad(
                    key,
                    format!("each must be at most {MAX_REFLECTANCE} (got {x})"),
                );
            }
        }
        match (t.model, t.alpha) {
            (Reflectance::Ggx, None) => ck.bad(
                "tile.alpha",
                "model \"ggx\" needs its roughness alpha (0.01..1); ks is its F0 per channel",
            ),
            (Reflectance::Ggx, Some(a)) => {
                ck.number("tile.alpha", a, 0.01, 1.0, "");
                for x in t.ks {
                    ck.number("tile.ks", x, 0.0, 1.0, " (F0 of the ggx tile)");
                }
            }
            (_, Some(_)) => ck.bad(
                "tile.alpha",
                "is the ggx tile's roughness; use n for the other models",
            ),
            (_, None) => {}
        }
        if t.n.is_finite() && t.n <= 0.0 {
            ck.bad(
                "tile.n",
                format!("the exponent must be positive (got {})", show_number(t.n)),
            );
        } else {
            ck.number("tile.n", t.n, 0.0, MAX_EXPONENT, "");
        }
        let g = &self.grid;
        for (key, v) in [
            ("grid.light", g.light),
            ("grid.dark", g.dark),
            ("grid.surround", g.surround),
        ] {
            ck.number(key, v, 0.0, 1.0, " (an albedo)");
        }
        if let Some(r) = &self.reference {
            for v in r.albedo {
                ck.number("reference.albedo", v, 0.0, 1.0, " (an albedo)");
            }
        }
        let s = &self.sensor;
        match &s.response {
            ResponseConfig::Gamma { gamma } => {
                if ck.positive("sensor.response.gamma", *gamma, 10.0, "") {
                    ck.number("sensor.response.gamma", *gamma, 0.1, 10.0, "");
                }
            }
            ResponseConfig::Emor { coefficients, .. } if coefficients.len() > 25 => ck.bad(
                "sensor.response.coefficients",
                "EMoR has 25 basis curves at most",
            ),
            ResponseConfig::Emor { file, coefficients } => {
                if file.len() > MAX_TEXT_BYTES || file.contains('\0') {
                    ck.bad(
                        "sensor.response.file",
                        format!("must be a path of at most {MAX_TEXT_BYTES} bytes, without NUL"),
                    );
                }
                if let Some(x) = coefficients
                    .iter()
                    .find(|x| !(x.is_finite() && x.abs() <= 100.0))
                {
                    ck.bad(
                        "sensor.response.coefficients",
                        format!("each must be a finite number within ±100 (got {x})"),
                    );
                }
            }
            ResponseConfig::Linear => {}
        }
        for (key, v) in [
            (
                "sensor.electrons_per_radiance_us",
                s.electrons_per_radiance_us,
            ),
            ("sensor.full_well_e", s.full_well_e),
        ] {
            ck.positive(key, v, MAX_ELECTRONS, " electrons");
        }
        if ck.positive("sensor.fps", s.fps, MAX_FPS, " frames per second") {
            ck.number("sensor.fps", s.fps, MIN_FPS, MAX_FPS, " frames per second");
        }
        ck.positive("lamp.intensity", self.lamp.intensity, MAX_INTENSITY, "");
        for (key, v) in [
            ("sensor.read_noise_e", s.read_noise_e),
            ("sensor.dark_current_e_per_s", s.dark_current_e_per_s),
        ] {
            if v < 0.0 {
                ck.bad(
                    key,
                    format!("must not be negative (got {})", show_number(v)),
                );
            } else {
                ck.number(key, v, 0.0, MAX_ELECTRONS, " electrons");
            }
        }
        if !(0.0..=1.0).contains(&s.blooming) {
            ck.bad(
                "sensor.blooming",
                format!("is a fraction in [0, 1] (got {})", show_number(s.blooming)),
            );
        }
        if s.exposure_latency_frames > MAX_LATENCY_FRAMES {
            ck.bad(
                "sensor.exposure_latency_frames",
                format!(
                    "must be at most {MAX_LATENCY_FRAMES} frames (got {})",
                    s.exposure_latency_frames
                ),
            );
        }
        let l = &self.lamp;
        if l.warmup_ms > MAX_WARMUP_MS {
            ck.bad(
                "lamp.warmup_ms",
                format!(
                    "must be at most {MAX_WARMUP_MS} ms (1 h) (got {})",
                    l.warmup_ms
                ),
            );
        }
        if l.identity.len() > MAX_TEXT_BYTES || l.identity.chars().any(char::is_control) {
            ck.bad(
                "lamp.identity",
                format!("must be one line of at most {MAX_TEXT_BYTES} bytes, without NUL, CR, LF or other control characters (it is sent as a reply line)"),
            );
        }
        if let Some(log) = &l.command_log {
            if log.is_empty() || log.len() > MAX_TEXT_BYTES || log.contains('\0') {
                ck.bad(
                    "lamp.command_log",
                    format!("must be a path of 1 to {MAX_TEXT_BYTES} bytes, without NUL"),
                );
            }
        }
        let f = &self.faults;
        if let (Some(unplug), Some(stall)) = (f.unplug_at_frame, f.stall_at_frame) {
            if stall <= unplug {
                ck.bad(
                    "faults.unplug_at_frame",
                    format!("the camera stalls at frame {stall}, before it is unplugged at frame {unplug}; keep one of the two (or unplug it first)"),
                );
            }
        }
        for (key, n) in [
            ("faults.drop_frames", f.drop_frames.len()),
            ("faults.corrupt_frames", f.corrupt_frames.len()),
            ("faults.ignore_exposure_us", f.ignore_exposure_us.len()),
        ] {
            if n > MAX_FAULTS {
                ck.bad(key, format!("lists {n} entries; at most {MAX_FAULTS}"));
            }
        }
        for (key, list) in [
            ("faults.lamp_garble_replies", &f.lamp_garble_replies),
            ("faults.lamp_late_replies", &f.lamp_late_replies),
            ("faults.lamp_split_replies", &f.lamp_split_replies),
            ("faults.lamp_overlong_replies", &f.lamp_overlong_replies),
            ("faults.lamp_error_replies", &f.lamp_error_replies),
        ] {
            if list.len() > MAX_FAULTS {
                ck.bad(
                    key,
                    format!("lists {} entries; at most {MAX_FAULTS}", list.len()),
                );
            } else if list.contains(&0) {
                ck.bad(
                    key,
                    "replies are counted from 1 (the first reply the lamp sends is 1); 0 is none",
                );
            }
        }
        for (key, v) in [
            ("faults.lamp_late_ms", f.lamp_late_ms),
            ("faults.lamp_split_ms", f.lamp_split_ms),
        ] {
            if v > MAX_LAMP_DELAY_MS {
                ck.bad(
                    key,
                    format!("must be at most {MAX_LAMP_DELAY_MS} ms (10 min) (got {v})"),
                );
            }
        }
        if f.lamp_late_ms == 0 && !f.lamp_late_replies.is_empty() {
            ck.bad(
                "faults.lamp_late_replies",
                "names late replies but faults.lamp_late_ms is 0; say how late they are",
            );
        }
        if !(1..=MAX_OVERLONG_BYTES).contains(&f.lamp_overlong_bytes) {
            ck.bad(
                "faults.lamp_overlong_bytes",
                format!(
                    "must be 1 to {MAX_OVERLONG_BYTES} bytes (got {})",
                    f.lamp_overlong_bytes
                ),
            );
        }
        if let Some(t) = &f.lamp_trailer {
            if t.len() > MAX_TEXT_BYTES || t.chars().any(char::is_control) {
                ck.bad(
                    "faults.lamp_trailer",
                    format!("must be one line of at most {MAX_TEXT_BYTES} bytes, without control characters (it is sent as a line)"),
                );
            }
        }
        if let Some(t) = &f.lamp_terminator {
            if f.lamp_terminator_bytes().is_none() {
                ck.bad(
                    "faults.lamp_terminator",
                    format!(
                        "is one of lf, cr, crlf, none (got {:?})",
                        t.chars().take(40).collect::<String>()
                    ),
                );
            }
        }
        ck.out
    }
}

/// What is wrong with a number that must be finite and in `lo..=hi` (`unit` follows the
/// bound), or `None`: the one wording of a bound for the simulated lab's checks and Glint's
/// rig checks alike.
pub fn out_of_range(v: f64, lo: f64, hi: f64, unit: &str) -> Option<String> {
    let got = show_number(v);
    if !v.is_finite() {
        Some(format!("must be a finite number (got {got})"))
    } else if v < lo {
        Some(format!("must be at least {lo}{unit} (got {got})"))
    } else if v > hi {
        Some(format!("must be at most {hi}{unit} (got {got})"))
    } else {
        None
    }
}

/// A number for a message: as written where people write it so, else in exponent form
/// (`1e308`, not 309 digits).
pub fn show_number(v: f64) -> String {
    if v == 0.0 || !v.is_finite() || (1e-4..1e12).contains(&v.abs()) {
        format!("{v}")
    } else {
        format!("{v:e}")
    }
}

/// Problems collected by [`MockConfig::problems`].
#[derive(Default)]
struct Checks {
    out: Vec<(String, String)>,
}

impl Checks {
    fn bad(&mut self, key: &str, message: impl Into<String>) {
        self.out.push((key.to_string(), message.into()));
    }

    /// A finite number in `lo..=hi` (`unit` follows the bound in the message).
    fn number(&mut self, key: &str, v: f64, lo: f64, hi: f64, unit: &str) -> bool {
        match out_of_range(v, lo, hi, unit) {
            Some(why) => {
                self.bad(key, why);
                false
            }
            None => true,
        }
    }

    /// A finite number in `(0, hi]`.
    fn positive(&mut self, key: &str, v: f64, hi: f64, unit: &str) -> bool {
        if v.is_finite() && v <= 0.0 {
            self.bad(key, format!("must be positive (got {})", show_number(v)));
            return false;
        }
        self.number(key, v, 0.0, hi, unit)
    }

    /// A point in grid coordinates: finite, within [`MAX_LENGTH_MM`] of the origin.
    fn point(&mut self, key: &str, p: &[f64; 3]) -> bool {
        if let Some((axis, v)) = ["x", "y", "z"]
            .iter()
            .zip(p)
            .find(|(_, v)| !(v.is_finite() && v.abs() <= MAX_LENGTH_MM))
        {
            self.bad(
                key,
                format!(
                    "{axis} = {v} mm: each coordinate must be a finite number of mm within ±{MAX_LENGTH_MM} (100 m) of the grid's origin"
                ),
            );
            return false;
        }
        true
    }
}

/// A fixed-size array that must have exactly `N` entries: serde alone fills the array
/// from the first `N` and drops the rest without a word.
fn exactly<'de, D, T, const N: usize>(d: D) -> Result<[T; N], D::Error>
where
    D: serde::Deserializer<'de>,
    T: Deserialize<'de>,
{
    let v = Vec::<T>::deserialize(d)?;
    let len = v.len();
    v.try_into()
        .map_err(|_| serde::de::Error::custom(format!("has {len} entries; give exactly {N}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn keys(cfg: &MockConfig) -> Vec<String> {
        cfg.problems().into_iter().map(|(k, _)| k).collect()
    }

    #[test]
    fn lamp_settings_read_from_toml() {
        let cfg: MockConfig = toml::from_str(
            r#"
            [lamp]
            preset = "coolled"
            [faults]
            lamp_echo = true
            lamp_trailer = "OK"
            lamp_terminator = "cr"
            lamp_late_ms = 300
            lamp_late_replies = [1]
            lamp_split_replies = [2]
            lamp_split_ms = 40
            lamp_overlong_replies = [3]
            lamp_error_replies = [1]
            "#,
        )
        .unwrap();
        assert_eq!(cfg.lamp.preset, LampPreset::Coolled);
        assert!(cfg.faults.lamp_echo);
        assert_eq!(cfg.faults.lamp_terminator_bytes(), Some("\r"));
        assert_eq!(cfg.faults.lamp_overlong_bytes, DEFAULT_OVERLONG_BYTES);
        assert_eq!(keys(&cfg), Vec::<String>::new());
        let defaults: MockConfig = toml::from_str("").unwrap();
        assert_eq!(defaults.lamp.preset, LampPreset::Glint);
        assert_eq!(defaults, MockConfig::default());
        let e = toml::from_str::<MockConfig>("[lamp]\npreset = \"philips\"").unwrap_err();
        assert!(e.to_string().contains("glint"), "{e}");
    }

    #[test]
    fn lamp_faults_out_of_bounds_are_named() {
        let mut cfg = MockConfig::default();
        cfg.faults.lamp_terminator = Some("lfcr".into());
        cfg.faults.lamp_trailer = Some("O\nK".into());
        cfg.faults.lamp_late_ms = MAX_LAMP_DELAY_MS + 1;
        cfg.faults.lamp_split_ms = MAX_LAMP_DELAY_MS + 1;
        cfg.faults.lamp_error_replies = vec![0];
        cfg.faults.lamp_overlong_bytes = 0;
        cfg.faults.lamp_split_replies = vec![1; MAX_FAULTS + 1];
        assert_eq!(
            keys(&cfg),
            [
                "faults.lamp_split_replies",
                "faults.lamp_error_replies",
                "faults.lamp_late_ms",
                "faults.lamp_split_ms",
                "faults.lamp_overlong_bytes",
                "faults.lamp_trailer",
                "faults.lamp_terminator",
            ]
        );
        let mut cfg = MockConfig::default();
        cfg.faults.lamp_late_replies = vec![2];
        assert_eq!(keys(&cfg), ["faults.lamp_late_replies"]);
    }
}
