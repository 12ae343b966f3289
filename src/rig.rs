//! Rig files: what hardware a lab has and where everything stands.
//!
//! A rig file is TOML with the sections `[rig]`, `[camera]`, `[lamp]`, `[geometry]`,
//! `[bracket]` and, for the simulated lab, `[mock]`. Loading does two passes, so every
//! mistake is reported with the file, the key and the fix: serde rejects unknown keys and
//! wrong types (with the line), then [`Rig::problems`] checks what the types cannot
//! (exposures increasing and within the camera's limits, the lamp above the tile, the tile
//! on the grid, a chessboard whose orientation is unambiguous ...).
//!
//! Coordinates are the grid's (DESIGN.md): millimetres, origin at an inner corner of the
//! chessboard, z up. Exposure times are microseconds.

use std::fmt;
use std::path::{Path, PathBuf};

use glint_mock::MockConfig;
use serde::{Deserialize, Serialize};

/// A loaded, validated rig.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Rig {
    pub rig: RigInfo,
    pub camera: CameraSection,
    pub lamp: LampSection,
    pub geometry: Geometry,
    pub bracket: Bracket,
    /// The simulated lab's truth; required when a backend is `mock`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mock: Option<MockConfig>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RigInfo {
    /// Short name, used in session folder names.
    pub name: String,
    #[serde(default)]
    pub description: String,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CameraBackend {
    /// The simulated camera of `glint-mock`.
    Mock,
    /// A Video4Linux2 camera (`device`, e.g. `/dev/video0`).
    V4l2,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSection {
    pub backend: CameraBackend,
    /// Device path for `v4l2`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub device: Option<String>,
    pub width: u32,
    pub height: u32,
    /// 8 or 16 bits per channel.
    #[serde(default = "default_bit_depth")]
    pub bit_depth: u8,
    /// The shortest and longest exposure the camera can take, µs.
    pub min_exposure_us: u32,
    pub max_exposure_us: u32,
    /// Frames per second when exposures are short (for planning).
    #[serde(default = "default_fps")]
    pub fps: f64,
    /// Give up on a frame after this long.
    #[serde(default = "default_frame_timeout_ms")]
    pub frame_timeout_ms: u64,
    /// Give up on a new exposure that has not shown up in the frames after this many frames.
    #[serde(default = "default_settle_max_frames")]
    pub settle_max_frames: u32,
    /// Abort a capture after more dropped frames than this.
    #[serde(default)]
    pub max_dropped_frames: u32,
}

fn default_bit_depth() -> u8 {
    8
}
fn default_fps() -> f64 {
    30.0
}
fn default_frame_timeout_ms() -> u64 {
    2000
}
fn default_settle_max_frames() -> u32 {
    12
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LampBackend {
    /// The simulated lamp firmware, reached over a pseudo-terminal with the serial driver.
    Mock,
    /// A lamp controller on a serial port (`port`).
    Serial,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LampSection {
    pub backend: LampBackend,
    /// Serial device, e.g. `/dev/ttyUSB0`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub port: Option<String>,
    #[serde(default = "default_baud")]
    pub baud: u32,
    /// Output level while capturing, 0..1000.
    #[serde(default = "default_level")]
    pub level: u16,
    /// Wait this long after switching on before capturing.
    pub warmup_ms: u64,
    /// Wait this long for each reply line.
    #[serde(default = "default_reply_timeout_ms")]
    pub reply_timeout_ms: u64,
    /// Tries per command before giving up (at least 1).
    #[serde(default = "default_tries")]
    pub tries: u32,
    /// The command strings of the lamp's protocol, for lamps that spell them differently.
    #[serde(default)]
    pub commands: LampCommands,
}

fn default_baud() -> u32 {
    115_200
}
fn default_level() -> u16 {
    1000
}
fn default_reply_timeout_ms() -> u64 {
    500
}
fn default_tries() -> u32 {
    3
}

/// Command strings (DESIGN.md lamp protocol); `{level}` is replaced by the level.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LampCommands {
    pub identify: String,
    pub on: String,
    pub off: String,
    pub level: String,
    pub state: String,
}

impl Default for LampCommands {
    fn default() -> Self {
        LampCommands {
            identify: "*IDN?".into(),
            on: "ON".into(),
            off: "OFF".into(),
            level: "LEVEL {level}".into(),
            state: "STATE?".into(),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Geometry {
    /// The lamp's centre in grid coordinates, mm.
    pub lamp_position_mm: [f64; 3],
    /// The tile's top face is the plane z = tile_thickness_mm.
    pub tile_thickness_mm: f64,
    /// The tile's outline in grid (x, y), mm, as a polygon.
    pub tile_outline_mm: Vec<[f64; 2]>,
    /// Inner corners of the chessboard along x and along y.
    pub grid_inner_corners: [u32; 2],
    pub grid_square_mm: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Bracket {
    /// Exposure times, shortest first, µs.
    pub exposures_us: Vec<u32>,
    #[serde(default = "one")]
    pub frames_per_exposure: u32,
    /// Dark frames (lamp off) at each exposure of the bracket.
    #[serde(default = "one")]
    pub dark_frames_per_exposure: u32,
    /// Exposure of the grid photo (tile removed, lamp on), µs.
    pub grid_exposure_us: u32,
    #[serde(default = "one")]
    pub grid_frames: u32,
}

fn one() -> u32 {
    1
}

/// One thing wrong with a rig file.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Problem {
    /// Dotted key, e.g. `bracket.exposures_us`.
    pub key: String,
    /// What is wrong and how to fix it.
    pub message: String,
}

impl fmt::Display for Problem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.key, self.message)
    }
}

/// Why a rig file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum RigError {
    #[error("cannot read rig file {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}:{line}:{column}: {message}")]
    Syntax {
        path: PathBuf,
        line: usize,
        column: usize,
        message: String,
    },
    #[error("{path}: {first}{more}", first = problems[0], more = more_problems(problems.len()))]
    Invalid {
        path: PathBuf,
        problems: Vec<Problem>,
    },
}

fn more_problems(n: usize) -> String {
    match n {
        1 => String::new(),
        n => format!(" (and {} more; `glint rig check` lists them all)", n - 1),
    }
}

impl RigError {
    /// Every problem, for `glint rig check`.
    pub fn problems(&self) -> Vec<String> {
        match self {
            RigError::Invalid { problems, .. } => problems.iter().map(|p| p.to_string()).collect(),
            other => vec![other.to_string()],
        }
    }
}

/// A rig together with where it came from.
#[derive(Debug, Clone)]
pub struct LoadedRig {
    pub rig: Rig,
    /// The file it was read from.
    pub path: PathBuf,
    /// Its text, as read (stored in sessions beside the parsed snapshot).
    pub text: String,
}

impl LoadedRig {
    /// The folder relative paths in the rig are relative to.
    pub fn base_dir(&self) -> PathBuf {
        self.path
            .parent()
            .map(Path::to_path_buf)
            .unwrap_or_default()
    }
}

/// Read, parse and validate a rig file.
pub fn load(path: &Path) -> Result<LoadedRig, RigError> {
    let text = std::fs::read_to_string(path).map_err(|source| RigError::Read {
        path: path.into(),
        source,
    })?;
    let rig = parse(&text, path)?;
    Ok(LoadedRig {
        rig,
        path: path.into(),
        text,
    })
}

/// Parse and validate rig text; `path` is used in messages.
pub fn parse(text: &str, path: &Path) -> Result<Rig, RigError> {
    let rig: Rig = toml::from_str(text).map_err(|e| {
        let (line, column) = e.span().map(|s| line_col(text, s.start)).unwrap_or((1, 1));
        let section = enclosing_table(text, line)
            .map(|t| format!(" in [{t}]"))
            .unwrap_or_default();
        let mut message = e.message().trim().to_string();
        if message.starts_with("unknown field") {
            message.push_str("; remove it or fix its spelling");
        }
        RigError::Syntax {
            path: path.into(),
            line,
            column,
            message: format!("{message}{section}"),
        }
    })?;
    let problems = rig.problems();
    if problems.is_empty() {
        Ok(rig)
    } else {
        Err(RigError::Invalid {
            path: path.into(),
            problems,
        })
    }
}

fn line_col(text: &str, offset: usize) -> (usize, usize) {
    let before = &text[..offset.min(text.len())];
    let line = before.matches('\n').count() + 1;
    let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
    (line, column)
}

fn enclosing_table(text: &str, line: usize) -> Option<String> {
    text.lines()
        .take(line)
        .filter_map(|l| {
            let l = l.trim();
            (l.starts_with('[') && l.ends_with(']'))
                .then(|| l.trim_matches(['[', ']']).trim().to_string())
        })
        .last()
}

impl Rig {
    /// Everything wrong with the rig that its types cannot express.
    pub fn problems(&self) -> Vec<Problem> {
        let mut out = Vec::new();
        let mut bad = |key: &str, message: String| {
            out.push(Problem {
                key: key.into(),
                message,
            })
        };

        if self.rig.name.trim().is_empty()
            || !self
                .rig
                .name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
        {
            bad("rig.name", format!("`{}` must be non-empty letters, digits, `-`, `_` or `.` (it names session folders)", self.rig.name));
        }

        // Camera.
        let c = &self.camera;
        if c.width < 16 || c.height < 16 {
            bad(
                "camera.width",
                format!(
                    "{}x{} is too small; give the camera's resolution in pixels",
                    c.width, c.height
                ),
            );
        }
        if c.bit_depth != 8 && c.bit_depth != 16 {
            bad(
                "camera.bit_depth",
                format!("must be 8 or 16 (got {})", c.bit_depth),
            );
        }
        if c.min_exposure_us == 0 || c.min_exposure_us > c.max_exposure_us {
            bad(
                "camera.min_exposure_us",
                format!(
                    "must be positive and at most camera.max_exposure_us (got {}..{})",
                    c.min_exposure_us, c.max_exposure_us
                ),
            );
        }
        if !positive(c.fps) {
            bad("camera.fps", format!("must be positive (got {})", c.fps));
        }
        if c.frame_timeout_ms == 0 {
            bad("camera.frame_timeout_ms", "must be positive".into());
        }
        if c.settle_max_frames == 0 {
            bad("camera.settle_max_frames", "must be at least 1".into());
        }
        if c.backend == CameraBackend::V4l2 && c.device.as_deref().unwrap_or("").is_empty() {
            bad(
                "camera.device",
                "backend \"v4l2\" needs a device path, e.g. device = \"/dev/video0\"".into(),
            );
        }

        // Lamp.
        let l = &self.lamp;
        if l.backend == LampBackend::Serial && l.port.as_deref().unwrap_or("").is_empty() {
            bad(
                "lamp.port",
                "backend \"serial\" needs a port, e.g. port = \"/dev/ttyUSB0\"".into(),
            );
        }
        if l.level > 1000 {
            bad("lamp.level", format!("must be 0..1000 (got {})", l.level));
        }
        if l.tries == 0 {
            bad("lamp.tries", "must be at least 1".into());
        }
        if l.reply_timeout_ms == 0 {
            bad("lamp.reply_timeout_ms", "must be positive".into());
        }
        if !l.commands.level.contains("{level}") {
            bad(
                "lamp.commands.level",
                format!("`{}` must contain `{{level}}`", l.commands.level),
            );
        }
        let mock_camera = c.backend == CameraBackend::Mock;
        if mock_camera != (l.backend == LampBackend::Mock) {
            bad(
                "lamp.backend",
                "the simulated camera is lit only by the simulated lamp: use backend = \"mock\" for both camera and lamp, or for neither".into(),
            );
        }

        // Geometry.
        let g = &self.geometry;
        let [nx, ny] = g.grid_inner_corners;
        if nx < 2 || ny < 2 {
            bad(
                "geometry.grid_inner_corners",
                format!("needs at least 2x2 inner corners (got {nx}x{ny})"),
            );
        } else if (nx % 2 == 0) == (ny % 2 == 0) {
            bad(
                "geometry.grid_inner_corners",
                format!(
                    "{nx}x{ny} inner corners make a {}x{} board that looks the same turned half round, so its origin is ambiguous; use a board with an odd number of squares one way and an even number the other (e.g. 9x6 inner corners)",
                    nx + 1,
                    ny + 1
                ),
            );
        }
        if !positive(g.grid_square_mm) {
            bad(
                "geometry.grid_square_mm",
                format!("must be positive (got {})", g.grid_square_mm),
            );
        }
        if !non_negative(g.tile_thickness_mm) {
            bad(
                "geometry.tile_thickness_mm",
                format!("must not be negative (got {})", g.tile_thickness_mm),
            );
        }
        if g.lamp_position_mm[2] <= g.tile_thickness_mm.max(0.0) {
            bad(
                "geometry.lamp_position_mm",
                format!(
                    "the lamp (z = {} mm) must be above the grid and the tile top (z = {} mm); z is measured up from the grid",
                    g.lamp_position_mm[2], g.tile_thickness_mm
                ),
            );
        }
        let poly = &g.tile_outline_mm;
        if poly.len() < 3 {
            bad(
                "geometry.tile_outline_mm",
                format!("needs at least 3 corners (got {})", poly.len()),
            );
        } else {
            let area = poly
                .iter()
                .zip(poly.iter().cycle().skip(1))
                .map(|(a, b)| a[0] * b[1] - b[0] * a[1])
                .sum::<f64>()
                / 2.0;
            if area.abs() < 1.0 {
                bad(
                    "geometry.tile_outline_mm",
                    "the outline encloses no area; list the corners in order around the tile"
                        .into(),
                );
            }
            let s = g.grid_square_mm;
            let (x0, x1, y0, y1) = (-s, nx as f64 * s, -s, ny as f64 * s);
            if let Some(p) = poly
                .iter()
                .find(|p| !(p[0] >= x0 && p[0] <= x1 && p[1] >= y0 && p[1] <= y1))
            {
                bad(
                    "geometry.tile_outline_mm",
                    format!(
                        "corner ({}, {}) is off the grid, which spans x {x0}..{x1} mm and y {y0}..{y1} mm; measure the outline from the grid's origin corner",
                        p[0], p[1]
                    ),
                );
            }
        }

        // Bracket.
        let b = &self.bracket;
        if b.exposures_us.is_empty() {
            bad(
                "bracket.exposures_us",
                "list at least one exposure, shortest first, in µs".into(),
            );
        }
        if let Some(i) = b.exposures_us.windows(2).position(|w| w[1] <= w[0]) {
            bad(
                "bracket.exposures_us",
                format!(
                    "must increase strictly: {} µs follows {} µs (entry {}); list exposures shortest first without repeats",
                    b.exposures_us[i + 1],
                    b.exposures_us[i],
                    i + 2
                ),
            );
        }
        for (key, e) in b
            .exposures_us
            .iter()
            .map(|e| ("bracket.exposures_us", *e))
            .chain([("bracket.grid_exposure_us", b.grid_exposure_us)])
        {
            if e < c.min_exposure_us || e > c.max_exposure_us {
                bad(
                    key,
                    format!(
                        "{e} µs is outside the camera's range {}..{} µs (camera.min_exposure_us, camera.max_exposure_us)",
                        c.min_exposure_us, c.max_exposure_us
                    ),
                );
                break;
            }
        }
        if b.frames_per_exposure == 0 {
            bad("bracket.frames_per_exposure", "must be at least 1".into());
        }
        if b.grid_frames == 0 {
            bad(
                "bracket.grid_frames",
                "must be at least 1 (the grid photo calibrates the camera)".into(),
            );
        }

        // The simulated lab.
        match (&self.mock, mock_camera || l.backend == LampBackend::Mock) {
            (None, true) => bad(
                "mock",
                "backend \"mock\" needs a [mock] section (it may be empty to use the defaults)"
                    .into(),
            ),
            (Some(m), _) => {
                let mock_problems = m.problems();
                let mock_ok = mock_problems.is_empty();
                for (key, message) in mock_problems {
                    bad(&format!("mock.{key}"), message);
                }
                if mock_ok && mock_camera && nx >= 2 && ny >= 2 {
                    let cam = glint_mock::PosedCamera::new(&m.camera, c.width, c.height);
                    let s = g.grid_square_mm;
                    for p in [
                        [0.0, 0.0],
                        [(nx - 1) as f64 * s, 0.0],
                        [0.0, (ny - 1) as f64 * s],
                        [(nx - 1) as f64 * s, (ny - 1) as f64 * s],
                    ] {
                        let inside = cam.project([p[0], p[1], 0.0]).is_some_and(|q| {
                            q[0] >= 0.0
                                && q[1] >= 0.0
                                && q[0] <= (c.width - 1) as f64
                                && q[1] <= (c.height - 1) as f64
                        });
                        if !inside {
                            bad(
                                "mock.camera",
                                format!(
                                    "the grid corner ({}, {}) mm is outside the simulated {}x{} image; move or turn the camera (position_mm, look_at_mm) or shorten fx/fy",
                                    p[0], p[1], c.width, c.height
                                ),
                            );
                            break;
                        }
                    }
                }
            }
            (None, false) => {}
        }
        out
    }

    /// The geometry in the simulated lab's terms.
    pub fn scene_geometry(&self) -> glint_mock::SceneGeometry {
        let g = &self.geometry;
        glint_mock::SceneGeometry {
            lamp_position_mm: g.lamp_position_mm,
            tile_thickness_mm: g.tile_thickness_mm,
            tile_outline_mm: g.tile_outline_mm.clone(),
            grid_inner_corners: g.grid_inner_corners,
            grid_square_mm: g.grid_square_mm,
        }
    }
}

/// `x > 0`, false for NaN.
fn positive(x: f64) -> bool {
    x > 0.0
}

/// `x >= 0`, false for NaN.
fn non_negative(x: f64) -> bool {
    x >= 0.0
}
