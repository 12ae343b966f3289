//! Rig files: what hardware a lab has and where everything stands.
//!
//! A rig file is TOML with the sections `[rig]`, `[camera]`, `[lamp]`, `[geometry]`,
//! `[bracket]` and, for the simulated lab, `[mock]`. Loading does two passes, so every
//! mistake is reported with the file, the key and the fix: serde rejects unknown keys and
//! wrong types (with the line), then [`Rig::problems`] checks what the types cannot
//! (exposures increasing and within the camera's limits, the lamp above the tile, the tile
//! on the grid, a chessboard whose orientation is unambiguous ...).
//!
//! Every value is finite and bounded (the `MAX_*` constants below, each named in the
//! error that refuses a value beyond it): NaN and ±inf are refused for every number,
//! fixed-size arrays (`lamp_position_mm`, `grid_inner_corners`, each outline corner) must
//! have exactly their length (serde alone drops extra entries silently), lamp commands are
//! one line without NUL, CR or LF, `rig.name` is a plain bounded file name. The same
//! check, [`Rig::problems`], is the one for a rig embedded in a session's manifest.
//!
//! Coordinates are the grid's (docs/design.md): millimetres, origin at an inner corner of the
//! chessboard, z up. Exposure times are microseconds.

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};

use glint_mock::MockConfig;
use serde::{Deserialize, Deserializer, Serialize};

use glint_format::fsx::{self, quote};

// The bounds every rig keeps. Each is far beyond what a lab uses and small enough that
// every stage's time, memory and disk stay bounded; the error refusing a value names it.

/// Largest image side, pixels (a 16384² 16-bit RGB frame is 1.6 GB).
pub const MAX_IMAGE_SIDE: u32 = 16_384;
/// Longest exposure, µs: 10 minutes.
pub const MAX_EXPOSURE_US: u32 = 600_000_000;
/// Most exposures in a bracket.
pub const MAX_EXPOSURES: usize = 64;
/// Frame rates a camera may declare, frames per second.
pub const MIN_FPS: f64 = 0.01;
pub const MAX_FPS: f64 = 1000.0;
/// Longest wait (lamp warm-up, frame timeout), ms: 1 hour.
pub const MAX_WAIT_MS: u64 = 3_600_000;
/// Longest wait for one reply of the lamp, ms: 1 minute.
pub const MAX_REPLY_TIMEOUT_MS: u64 = 60_000;
/// Most tries per lamp command.
pub const MAX_TRIES: u32 = 20;
/// Most frames to wait for a new exposure to show.
pub const MAX_SETTLE_FRAMES: u32 = 100;
/// Most dropped frames a capture may tolerate.
pub const MAX_DROPPED_FRAMES: u32 = 1000;
/// Most frames per exposure (tile or dark) and grid frames.
pub const MAX_FRAMES_PER_STEP: u32 = 100;
/// Most inner corners per side of the chessboard.
pub const MAX_GRID_CORNERS: u32 = 200;
/// Most corners of the tile's outline.
pub const MAX_OUTLINE_CORNERS: usize = 64;
/// Largest distance from the grid's origin, mm: 100 m.
pub const MAX_LENGTH_MM: f64 = 100_000.0;
/// Chessboard square sizes, mm.
pub const MIN_SQUARE_MM: f64 = 0.01;
pub const MAX_SQUARE_MM: f64 = 1000.0;
/// Serial speeds (Linux's termios goes up to 4 Mbaud).
pub const MIN_BAUD: u32 = 50;
pub const MAX_BAUD: u32 = 4_000_000;
/// Longest lamp command, bytes.
pub const MAX_COMMAND_BYTES: usize = 256;
/// Longest device path, bytes.
pub const MAX_PATH_BYTES: usize = 4096;
/// Longest rig name (it names session folders), characters.
pub const MAX_NAME_CHARS: usize = 64;
/// Longest rig description, characters.
pub const MAX_DESCRIPTION_CHARS: usize = 1000;

/// A loaded, validated rig.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Rig {
    pub rig: RigInfo,
    pub camera: CameraSection,
    pub lamp: LampSection,
    pub geometry: Geometry,
    /// Required for a camera Glint drives; a processing rig (`external` camera) may leave
    /// it out (`glint import` records the photos' exposures here).
    #[serde(default)]
    pub bracket: Bracket,
    /// A diffuse reflectance standard beside the tile, photographed in the tile's bracket:
    /// with it, kd and ks are reported in absolute terms (albedo, 1/sr); without, they stay
    /// relative (see [`ReferenceSection`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reference: Option<ReferenceSection>,
    /// Who performs the hands-on steps (placing and removing the tile): a person at the
    /// terminal (no section), or configured commands (an automated rig).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub operator: Option<OperatorSection>,
    /// The simulated lab's truth; required when a backend is `mock`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mock: Option<MockConfig>,
}

/// `[reference]`: a diffuse reflectance standard (a white standard of known reflectance,
/// e.g. 99%, or a calibrated grey card) lying on the grid beside the tile, placed and
/// removed with it, so that it is in every frame of the tile's bracket. Its radiance over
/// the lamp's irradiance there (both known from the geometry) gives the factor that the
/// lamp's intensity and the camera's gain put on every radiance, and so kd and ks in
/// absolute terms. Treated as Lambertian: its certificate's reflectance (the 0/45 or
/// hemispherical reflectance factor, per channel or one number) is taken as its albedo.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReferenceSection {
    /// Reflectance, 0..1: one number (a spectrally flat standard) or one per channel
    /// (R, G, B) from its certificate.
    pub reflectance: Channels,
    /// The certificate's standard uncertainty of the reflectance (absolute, e.g. 0.005),
    /// one number or one per channel.
    pub reflectance_sd: Channels,
    /// Its top face's outline in grid (x, y), mm, as a polygon.
    #[serde(deserialize_with = "each_exactly")]
    pub outline_mm: Vec<[f64; 2]>,
    /// Height of its top face above the grid, mm.
    pub thickness_mm: f64,
}

/// One number for every channel, or one per channel (R, G, B).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Channels {
    One(f64),
    Each([f64; 3]),
}

impl Channels {
    /// The value for channel `c` of a session with `channels` channels (a monochrome
    /// camera sees the mean of the three).
    pub fn get(&self, c: usize, channels: usize) -> f64 {
        match self {
            Channels::One(v) => *v,
            Channels::Each(v) if channels == 1 => (v[0] + v[1] + v[2]) / 3.0,
            Channels::Each(v) => v[c.min(2)],
        }
    }

    fn values(&self) -> Vec<f64> {
        match self {
            Channels::One(v) => vec![*v],
            Channels::Each(v) => v.to_vec(),
        }
    }
}

/// `[operator]`: commands that do what a person would, for an automated rig (a robot arm,
/// a turntable, the simulated lab's `glint-mock scene`). Each is a program and its
/// arguments, run without a shell; it must exit 0 once the scene is ready.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OperatorSection {
    /// Put the tile on the grid at its outline.
    pub place_tile: Vec<String>,
    /// Take the tile off so the whole grid shows.
    pub remove_tile: Vec<String>,
    /// Hold the chessboard in a pose, for `glint lens` (optional): the pose is appended as
    /// `--pose K --tilt-x-deg A --tilt-y-deg B --rotate-deg C --lift-mm H`; e.g.
    /// ["glint-mock", "scene", "show-board"]. Without it a person is asked.
    #[serde(default)]
    pub show_board: Vec<String>,
    /// Give up on a command after this long.
    #[serde(default = "default_operator_timeout_ms")]
    pub timeout_ms: u64,
}

fn default_operator_timeout_ms() -> u64 {
    60_000
}

/// What a camera delivers, by its V4L2 name (`v4l2-ctl --list-formats` spells them so).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum PixelFormat {
    /// 8-bit luma (a monochrome camera).
    GREY,
    /// 16-bit luma, little-endian (a monochrome camera).
    Y16,
    /// 10-bit luma in 16-bit little-endian words.
    Y10,
    /// 12-bit luma in 16-bit little-endian words.
    Y12,
    /// Packed 4:2:2 Y'CbCr: full-resolution luma, chroma shared by pixel pairs.
    YUYV,
    /// 8-bit R'G'B'.
    RGB3,
    /// 8-bit B'G'R'.
    BGR3,
    /// Motion JPEG: lossy and processed in the camera; refused unless `allow_lossy`.
    MJPG,
}

impl PixelFormat {
    pub const ALL: [PixelFormat; 8] = [
        PixelFormat::GREY,
        PixelFormat::Y16,
        PixelFormat::Y10,
        PixelFormat::Y12,
        PixelFormat::YUYV,
        PixelFormat::RGB3,
        PixelFormat::BGR3,
        PixelFormat::MJPG,
    ];
    /// The V4L2 four-character code.
    pub fn fourcc(self) -> [u8; 4] {
        *match self {
            PixelFormat::GREY => b"GREY",
            PixelFormat::Y16 => b"Y16 ",
            PixelFormat::Y10 => b"Y10 ",
            PixelFormat::Y12 => b"Y12 ",
            PixelFormat::YUYV => b"YUYV",
            PixelFormat::RGB3 => b"RGB3",
            PixelFormat::BGR3 => b"BGR3",
            PixelFormat::MJPG => b"MJPG",
        }
    }
    /// The format of a four-character code, if Glint reads it.
    pub fn from_fourcc(code: [u8; 4]) -> Option<PixelFormat> {
        PixelFormat::ALL.into_iter().find(|f| f.fourcc() == code)
    }
    pub fn name(self) -> &'static str {
        match self {
            PixelFormat::GREY => "GREY",
            PixelFormat::Y16 => "Y16",
            PixelFormat::Y10 => "Y10",
            PixelFormat::Y12 => "Y12",
            PixelFormat::YUYV => "YUYV",
            PixelFormat::RGB3 => "RGB3",
            PixelFormat::BGR3 => "BGR3",
            PixelFormat::MJPG => "MJPG",
        }
    }
    /// Samples a pixel once decoded: 1 for the luma formats, 3 for the colour ones.
    pub fn channels(self) -> u8 {
        match self {
            PixelFormat::GREY | PixelFormat::Y16 | PixelFormat::Y10 | PixelFormat::Y12 => 1,
            _ => 3,
        }
    }
    /// Bits a sample once decoded (Y10 and Y12 are scaled to 16 bits: value << 6 or << 4).
    pub fn bit_depth(self) -> u8 {
        match self {
            PixelFormat::Y16 | PixelFormat::Y10 | PixelFormat::Y12 => 16,
            _ => 8,
        }
    }
    /// Lossy, camera-processed formats (not fit for measurement by default).
    pub fn lossy(self) -> bool {
        self == PixelFormat::MJPG
    }
}

impl std::fmt::Display for PixelFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// What to do when the camera lacks a control the rig names.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MissingControl {
    /// Refuse to capture.
    #[default]
    Error,
    /// Warn and go on.
    Warn,
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
    /// A camera through the nokhwa crate (cargo feature `nokhwa`; `device`: its index, or
    /// on Linux its /dev/videoN path).
    Nokhwa,
    /// A camera Glint does not drive (a DSLR tethered with gphoto2, a machine-vision camera
    /// with its vendor's tool): a processing rig, for `glint import`. Its size and bit depth
    /// are optional (checked against the photos where given); nothing only capture uses is
    /// required.
    External,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSection {
    pub backend: CameraBackend,
    /// Device path for `v4l2`; for `nokhwa`, the camera's index or (Linux) /dev/videoN path.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub device: Option<String>,
    /// Required for a camera Glint drives; optional (0: the photos') for `external`.
    #[serde(default)]
    pub width: u32,
    #[serde(default)]
    pub height: u32,
    /// 8 or 16 bits per channel.
    #[serde(default = "default_bit_depth")]
    pub bit_depth: u8,
    /// The shortest and longest exposure the camera can take, µs (required for a camera
    /// Glint drives).
    #[serde(default)]
    pub min_exposure_us: u32,
    #[serde(default)]
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
    /// What the camera delivers (V4L2 four-character code name). `v4l2` needs one; the
    /// simulated camera takes GREY or Y16 for a monochrome sensor, none for RGB.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pixel_format: Option<PixelFormat>,
    /// Accept a lossy, camera-processed format (MJPG) for measurement; the session is
    /// flagged as lossy.
    #[serde(default)]
    pub allow_lossy: bool,
    /// Device controls to set before capturing (V4L2 names as `glint devices` lists them,
    /// e.g. `gain = 0`); each is read back and recorded.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub controls: BTreeMap<String, i64>,
    /// A control in `controls` the device lacks: `"error"` (refuse) or `"warn"`.
    #[serde(default)]
    pub missing_control: MissingControl,
    /// Driver buffers to stream with (V4L2 mmap).
    #[serde(default = "default_buffers")]
    pub buffers: u32,
}

fn default_buffers() -> u32 {
    4
}

impl CameraSection {
    /// Samples a pixel of this camera's frames: 1 (monochrome) or 3 (RGB).
    pub fn channels(&self) -> u8 {
        self.pixel_format.map_or(3, PixelFormat::channels)
    }
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
    /// A lamp Glint does not switch (a processing rig, for `glint import`): only its
    /// position (`geometry.lamp_position_mm`) matters.
    External,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LampSection {
    pub backend: LampBackend,
    /// Serial device, e.g. `/dev/ttyUSB0`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub port: Option<String>,
    /// Baud rate; default: the protocol preset's (115200; 57600 for coolled).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub baud: Option<u32>,
    /// Output level while capturing, 0..1000.
    #[serde(default = "default_level")]
    pub level: u16,
    /// Wait this long after switching on before capturing (required for a lamp Glint
    /// switches).
    #[serde(default)]
    pub warmup_ms: u64,
    /// Wait this long for each reply line.
    #[serde(default = "default_reply_timeout_ms")]
    pub reply_timeout_ms: u64,
    /// Tries per command before giving up (at least 1).
    #[serde(default = "default_tries")]
    pub tries: u32,
    /// How the lamp controller talks: a preset and what differs from it.
    #[serde(default)]
    pub protocol: LampProtocolSection,
    /// The command strings of the lamp's protocol, for lamps that spell them differently
    /// (each overrides the preset's).
    #[serde(default)]
    pub commands: LampCommands,
}

impl LampSection {
    /// The baud rate: `baud`, else the protocol preset's.
    pub fn baud(&self) -> u32 {
        self.baud.unwrap_or_else(|| self.protocol.preset.baud())
    }

    /// The lamp's protocol, resolved (the rig's checks have refused a broken one, so this
    /// fails only for a rig that was not checked).
    pub fn resolved_protocol(
        &self,
    ) -> Result<crate::lamp_protocol::Protocol, crate::error::DeviceError> {
        crate::lamp_protocol::Protocol::resolve(&self.protocol, &self.commands)
            .map_err(|p| crate::error::DeviceError::Unsupported(format!("{}: {}", p[0].0, p[0].1)))
    }
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

pub use crate::lamp_protocol::{LampCommands, LampProtocolSection};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Geometry {
    /// The lamp's centre in grid coordinates, mm.
    #[serde(deserialize_with = "exactly")]
    pub lamp_position_mm: [f64; 3],
    /// The tile's top face is the plane z = tile_thickness_mm.
    pub tile_thickness_mm: f64,
    /// The tile's outline in grid (x, y), mm, as a polygon.
    #[serde(deserialize_with = "each_exactly")]
    pub tile_outline_mm: Vec<[f64; 2]>,
    /// Inner corners of the chessboard along x and along y.
    #[serde(deserialize_with = "exactly")]
    pub grid_inner_corners: [u32; 2],
    pub grid_square_mm: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Bracket {
    /// Exposure times, shortest first, µs.
    #[serde(default)]
    pub exposures_us: Vec<u32>,
    #[serde(default = "one")]
    pub frames_per_exposure: u32,
    /// Dark frames (lamp off) at each exposure of the bracket.
    #[serde(default = "one")]
    pub dark_frames_per_exposure: u32,
    /// Exposure of the grid photo (tile removed, lamp on), µs.
    #[serde(default)]
    pub grid_exposure_us: u32,
    #[serde(default = "one")]
    pub grid_frames: u32,
}

fn one() -> u32 {
    1
}

impl Default for Bracket {
    /// No bracket: a processing rig's (the photos bring their own exposures).
    fn default() -> Self {
        Bracket {
            exposures_us: Vec::new(),
            frames_per_exposure: 1,
            dark_frames_per_exposure: 1,
            grid_exposure_us: 0,
            grid_frames: 1,
        }
    }
}

/// A fixed-size array that must have exactly `N` entries: serde alone fills the array
/// from the first `N` and drops the rest without a word. Every fixed-size array of the rig
/// file goes through this (or [`exactly_opt`]).
pub(crate) fn exactly<'de, D, T, const N: usize>(d: D) -> Result<[T; N], D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    let v = Vec::<T>::deserialize(d)?;
    let len = v.len();
    v.try_into()
        .map_err(|_| serde::de::Error::custom(format!("has {len} entries; give exactly {N}")))
}

/// [`exactly`] for an optional key (`#[serde(default, deserialize_with = "...")]`).
pub(crate) fn exactly_opt<'de, D, T, const N: usize>(d: D) -> Result<Option<[T; N]>, D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    exactly(d).map(Some)
}

/// A list of fixed-size arrays, each with exactly `N` entries.
fn each_exactly<'de, D, T, const N: usize>(d: D) -> Result<Vec<[T; N]>, D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    Vec::<Vec<T>>::deserialize(d)?
        .into_iter()
        .enumerate()
        .map(|(i, v)| {
            let len = v.len();
            v.try_into().map_err(|_| {
                serde::de::Error::custom(format!(
                    "entry {} has {len} numbers; give each as exactly {N}",
                    i + 1
                ))
            })
        })
        .collect()
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
///
/// The file may be reached through a symbolic link (it is the user's own), but must be a
/// regular file of at most [`fsx::MAX_TEXT_BYTES`].
pub fn load(path: &Path) -> Result<LoadedRig, RigError> {
    let text = std::fs::canonicalize(path)
        .and_then(|real| fsx::read_text_capped(&real, fsx::MAX_TEXT_BYTES))
        .map_err(|source| RigError::Read {
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
        let section_name = enclosing_table(text, line);
        let section = section_name
            .as_ref()
            .map(|t| format!(" (in [{}])", one_line(t)))
            .unwrap_or_default();
        let mut message = fsx::short_message(e.message());
        if message.starts_with("unknown field") {
            message.push_str("; remove it or fix its spelling");
        }
        if let Some(key) = dotted_key(&e).filter(|k| Some(k) != section_name.as_ref()) {
            message = format!("{key}: {message}");
        }
        RigError::Syntax {
            path: path.into(),
            line,
            column,
            message: format!("{message}{section}"),
        }
    })?;
    let mut rig = rig;
    // The file as a plain table (it parsed as a rig, so it parses as a table), for what
    // the rig's types cannot tell: which keys were written, and as what.
    let given = text.parse::<toml::Table>().unwrap_or_default();
    let mut problems = tables_given_as_arrays(&given, &rig);
    problems.extend(missing_for_capture(&given, &mut rig));
    if problems.is_empty() {
        problems = rig.problems();
    }
    if problems.is_empty() {
        Ok(rig)
    } else {
        Err(RigError::Invalid {
            path: path.into(),
            problems,
        })
    }
}

/// The keys only capture uses are optional in the file (a processing rig, with an
/// `external` camera and lamp, has no use for them) but required for a camera or lamp Glint
/// drives: each one missing there is a problem, worded as serde would have. An external
/// camera without `bit_depth` takes the photos' (0 here).
fn missing_for_capture(given: &toml::Table, rig: &mut Rig) -> Vec<Problem> {
    let has = |section: &str, key: &str| {
        given
            .get(section)
            .and_then(|t| t.as_table())
            .is_some_and(|t| t.contains_key(key))
    };
    let mut out = Vec::new();
    let mut missing = |key: &str, what: &str| {
        out.push(Problem {
            key: key.into(),
            message: format!("missing; {what}"),
        })
    };
    if rig.camera.backend == CameraBackend::External {
        if !has("camera", "bit_depth") {
            rig.camera.bit_depth = 0;
        }
    } else {
        for (k, what) in [
            ("width", "give the camera's resolution in pixels"),
            ("height", "give the camera's resolution in pixels"),
            (
                "min_exposure_us",
                "give the shortest exposure the camera takes, µs",
            ),
            (
                "max_exposure_us",
                "give the longest exposure the camera takes, µs",
            ),
        ] {
            if !has("camera", k) {
                missing(&format!("camera.{k}"), what);
            }
        }
        if !given.contains_key("bracket") {
            missing(
                "bracket",
                "a camera Glint drives needs a [bracket] (exposures_us, grid_exposure_us); only a processing rig (camera.backend = \"external\") may leave it out",
            );
        } else {
            for (k, what) in [
                ("exposures_us", "list the exposures, shortest first, in µs"),
                ("grid_exposure_us", "give the grid photo's exposure, µs"),
            ] {
                if !has("bracket", k) {
                    missing(&format!("bracket.{k}"), what);
                }
            }
        }
    }
    if rig.lamp.backend != LampBackend::External && !has("lamp", "warmup_ms") {
        missing(
            "lamp.warmup_ms",
            "give the time the lamp needs to stabilise after switching on, ms (0 for an LED)",
        );
    }
    out
}

/// Sections given as arrays (`mock.camera = []`): serde reads a struct from a list of its
/// fields in order, so `[]` would silently be a section of defaults, and a list of values
/// a section filled by position. Every key that the parsed rig has as a table must be a
/// table in the file too.
fn tables_given_as_arrays(given: &toml::Table, rig: &Rig) -> Vec<Problem> {
    fn walk(given: &toml::Table, parsed: &toml::Table, prefix: &str, out: &mut Vec<Problem>) {
        for (k, p) in parsed {
            let key = if prefix.is_empty() {
                k.clone()
            } else {
                format!("{prefix}.{k}")
            };
            match (given.get(k), p) {
                (Some(toml::Value::Table(g)), toml::Value::Table(p)) => walk(g, p, &key, out),
                (Some(g), toml::Value::Table(_)) if !g.is_table() => out.push(Problem {
                    message: format!(
                        "must be a table, not {}: a [{key}] section (empty for the defaults)",
                        match g.type_str() {
                            "array" => "a list".to_string(),
                            "integer" => "an integer".to_string(),
                            t => format!("a {t}"),
                        }
                    ),
                    key,
                }),
                _ => {}
            }
        }
    }
    let Ok(toml::Value::Table(parsed)) = toml::Value::try_from(rig) else {
        return Vec::new();
    };
    let mut out = Vec::new();
    walk(given, &parsed, "", &mut out);
    out
}

/// A header's name for a message: control characters as spaces, at most
/// [`fsx::QUOTE_CHARS`] characters (the header line is copied from the file as it is).
fn one_line(name: &str) -> String {
    let mut out: String = name
        .chars()
        .map(|c| if c.is_control() { ' ' } else { c })
        .take(fsx::QUOTE_CHARS)
        .collect();
    if name.chars().count() > fsx::QUOTE_CHARS {
        out.push('…');
    }
    out
}

/// The dotted key a deserialisation error is about (`geometry.lamp_position_mm`), if the
/// error knows it: toml keeps the keys private but prints them when it has no input.
fn dotted_key(e: &toml::de::Error) -> Option<String> {
    let mut bare = e.clone();
    bare.set_input(None);
    bare.to_string()
        .lines()
        .find_map(|l| l.strip_prefix("in `")?.strip_suffix('`').map(String::from))
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
    /// Everything wrong with the rig that its types cannot express: every number finite and
    /// within the bounds above, every string one bounded line, and the parts consistent
    /// with each other. The one check for a rig, whether read from a rig file or from a
    /// session's manifest.
    pub fn problems(&self) -> Vec<Problem> {
        let mut ck = Checks::default();
        self.check_info(&mut ck);
        self.check_camera(&mut ck);
        self.check_lamp(&mut ck);
        self.check_operator(&mut ck);
        let geometry_ok = self.check_geometry(&mut ck);
        self.check_bracket(&mut ck);
        if geometry_ok {
            self.check_reference(&mut ck);
        }
        self.check_mock(&mut ck, geometry_ok);
        ck.out
    }

    fn check_info(&self, ck: &mut Checks) {
        let name = &self.rig.name;
        if name.trim().is_empty()
            || !name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
        {
            ck.bad("rig.name", format!("{} must be non-empty letters, digits, `-`, `_` or `.` (it names session folders)", quote(name)));
        } else if name.starts_with('.') {
            ck.bad(
                "rig.name",
                format!(
                    "{} must not start with `.` (it names session folders: `.` and `..` are not folders of their own, and a leading dot hides them)",
                    quote(name)
                ),
            );
        } else if name.len() > MAX_NAME_CHARS {
            ck.bad(
                "rig.name",
                format!(
                    "is {} characters; at most {MAX_NAME_CHARS} (it names session folders)",
                    name.len()
                ),
            );
        }
        let d = &self.rig.description;
        if d.chars().count() > MAX_DESCRIPTION_CHARS || d.contains('\0') {
            ck.bad(
                "rig.description",
                format!("must be at most {MAX_DESCRIPTION_CHARS} characters of text, without NUL"),
            );
        }
    }

    fn check_camera(&self, ck: &mut Checks) {
        let c = &self.camera;
        let external = c.backend == CameraBackend::External;
        // An external camera's size may be left out (0x0: the photos'), but not half given.
        let size_left_out = external && c.width == 0 && c.height == 0;
        if !size_left_out && (c.width < 16 || c.height < 16) {
            ck.bad(
                "camera.width",
                format!(
                    "{}x{} is too small; give the camera's resolution in pixels",
                    c.width, c.height
                ),
            );
        }
        for (key, v) in [("camera.width", c.width), ("camera.height", c.height)] {
            if v > MAX_IMAGE_SIDE {
                ck.bad(
                    key,
                    format!(
                        "must be at most {MAX_IMAGE_SIDE} pixels (got {v}); give the camera's resolution in pixels"
                    ),
                );
            }
        }
        if c.bit_depth != 8 && c.bit_depth != 16 && !(external && c.bit_depth == 0) {
            ck.bad(
                "camera.bit_depth",
                format!("must be 8 or 16 (got {})", c.bit_depth),
            );
        }
        // An external camera's exposures are the photos' (Glint sets none): its range may be
        // left out, but where given it must make sense.
        let range_left_out = external && c.min_exposure_us == 0 && c.max_exposure_us == 0;
        if !range_left_out && (c.min_exposure_us == 0 || c.min_exposure_us > c.max_exposure_us) {
            ck.bad(
                "camera.min_exposure_us",
                format!(
                    "must be positive and at most camera.max_exposure_us (got {}..{})",
                    c.min_exposure_us, c.max_exposure_us
                ),
            );
        }
        ck.count(
            "camera.max_exposure_us",
            c.max_exposure_us.into(),
            0,
            MAX_EXPOSURE_US.into(),
            " µs (10 min)",
        );
        ck.number("camera.fps", c.fps, MIN_FPS, MAX_FPS, " frames per second");
        if ck.count(
            "camera.frame_timeout_ms",
            c.frame_timeout_ms,
            1,
            MAX_WAIT_MS,
            " ms (1 h)",
        ) {
            let longest = self
                .bracket
                .exposures_us
                .iter()
                .copied()
                .chain([self.bracket.grid_exposure_us])
                .max()
                .unwrap_or(0);
            // Only a camera Glint drives waits for frames: an external one's photos come
            // in however long their exposures were (a lab's 3 s exposure, imported).
            if !external && c.frame_timeout_ms.saturating_mul(1000) <= longest as u64 {
                ck.bad(
                    "camera.frame_timeout_ms",
                    format!(
                        "{} ms is no longer than the longest exposure ({longest} µs), so every frame at it would time out; make it longer",
                        c.frame_timeout_ms
                    ),
                );
            }
        }
        if c.settle_max_frames == 0 {
            ck.bad("camera.settle_max_frames", "must be at least 1");
        } else {
            ck.count(
                "camera.settle_max_frames",
                c.settle_max_frames.into(),
                1,
                MAX_SETTLE_FRAMES.into(),
                " frames",
            );
        }
        ck.count(
            "camera.max_dropped_frames",
            c.max_dropped_frames.into(),
            0,
            MAX_DROPPED_FRAMES.into(),
            " frames",
        );
        if let Some(d) = &c.device {
            ck.path("camera.device", d);
        }
        match (c.backend, c.pixel_format) {
            (CameraBackend::V4l2, None) => ck.bad(
                "camera.pixel_format",
                "backend \"v4l2\" needs a pixel format: one of GREY, Y16, Y10, Y12 (monochrome), YUYV, RGB3, BGR3, MJPG; `glint devices` lists what the camera offers",
            ),
            (CameraBackend::Nokhwa, None) => ck.bad(
                "camera.pixel_format",
                "backend \"nokhwa\" needs a pixel format: one of YUYV, RGB3, BGR3, MJPG (nokhwa has no Y16, Y10 or Y12, and on Linux cannot open GREY)",
            ),
            (CameraBackend::Nokhwa, Some(f)) if matches!(f, PixelFormat::Y16 | PixelFormat::Y10 | PixelFormat::Y12) => ck.bad(
                "camera.pixel_format",
                format!("nokhwa has no {f} (its formats are MJPEG, YUYV, NV12, GRAY, RAWRGB, RAWBGR); use camera.backend = \"v4l2\" for {f}"),
            ),
            (CameraBackend::Mock, Some(f)) if f.channels() != 1 || f == PixelFormat::Y10 || f == PixelFormat::Y12 => ck.bad(
                "camera.pixel_format",
                format!("the simulated camera delivers RGB (no pixel_format), GREY or Y16, not {f}"),
            ),
            _ => {}
        }
        if let Some(f) = c.pixel_format {
            if f.bit_depth() != c.bit_depth {
                ck.bad(
                    "camera.bit_depth",
                    format!(
                        "pixel format {f} delivers {}-bit samples; set bit_depth = {}",
                        f.bit_depth(),
                        f.bit_depth()
                    ),
                );
            }
            if f.lossy() && !c.allow_lossy {
                ck.bad(
                    "camera.pixel_format",
                    format!("{f} is lossy and processed in the camera, so its values are not measurements; choose YUYV, GREY or Y16, or set allow_lossy = true to accept it (the session is flagged)"),
                );
            }
        }
        if c.backend == CameraBackend::Mock && !c.controls.is_empty() {
            ck.bad(
                "camera.controls",
                "the simulated camera has no controls to set; remove [camera.controls]",
            );
        }
        ck.count("camera.buffers", c.buffers.into(), 2, 32, " buffers");
        for name in c.controls.keys() {
            if name.is_empty()
                || name.len() > 64
                || !name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_')
            {
                ck.bad(
                    "camera.controls",
                    format!("{} is not a control name; use the names `glint devices` lists (letters, digits, _)", quote(name)),
                );
            }
        }
        if c.backend == CameraBackend::V4l2 && c.device.as_deref().unwrap_or("").is_empty() {
            ck.bad(
                "camera.device",
                "backend \"v4l2\" needs a device path, e.g. device = \"/dev/video0\"",
            );
        }
        if c.backend == CameraBackend::Nokhwa {
            if c.device.as_deref().unwrap_or("").trim().is_empty() {
                ck.bad(
                    "camera.device",
                    "backend \"nokhwa\" needs a device: the camera's index (device = \"0\") or, on Linux, its /dev/videoN path",
                );
            }
            if c.fps.fract() != 0.0 {
                ck.bad(
                    "camera.fps",
                    format!("nokhwa sets whole frames per second, not {}; use a whole number, or camera.backend = \"v4l2\"", c.fps),
                );
            }
        }
    }

    fn check_operator(&self, ck: &mut Checks) {
        let Some(o) = &self.operator else { return };
        for (key, cmd) in [
            ("operator.place_tile", &o.place_tile),
            ("operator.remove_tile", &o.remove_tile),
            ("operator.show_board", &o.show_board),
        ] {
            if key == "operator.show_board" && cmd.is_empty() {
                continue;
            }
            if cmd.first().is_none_or(|p| p.trim().is_empty()) {
                ck.bad(
                    key,
                    "must name a program and its arguments, e.g. [\"glint-mock\", \"scene\", \"place-tile\"]",
                );
            } else if cmd.len() > 64 || cmd.iter().any(|a| a.len() > 4096 || a.contains('\0')) {
                ck.bad(
                    key,
                    "at most 64 arguments of at most 4096 bytes, without NUL",
                );
            }
        }
        ck.count(
            "operator.timeout_ms",
            o.timeout_ms,
            1,
            MAX_WAIT_MS,
            " ms (1 h)",
        );
    }

    fn check_lamp(&self, ck: &mut Checks) {
        let l = &self.lamp;
        if let Some(p) = &l.port {
            ck.path("lamp.port", p);
        }
        if l.backend == LampBackend::Serial && l.port.as_deref().unwrap_or("").is_empty() {
            ck.bad(
                "lamp.port",
                "backend \"serial\" needs a port, e.g. port = \"/dev/ttyUSB0\"",
            );
        }
        ck.count(
            "lamp.baud",
            l.baud().into(),
            MIN_BAUD.into(),
            MAX_BAUD.into(),
            " baud",
        );
        if l.level > 1000 {
            ck.bad("lamp.level", format!("must be 0..1000 (got {})", l.level));
        }
        ck.count("lamp.warmup_ms", l.warmup_ms, 0, MAX_WAIT_MS, " ms (1 h)");
        if l.reply_timeout_ms == 0 {
            ck.bad("lamp.reply_timeout_ms", "must be positive");
        } else {
            ck.count(
                "lamp.reply_timeout_ms",
                l.reply_timeout_ms,
                1,
                MAX_REPLY_TIMEOUT_MS,
                " ms (1 min)",
            );
        }
        if l.tries == 0 {
            ck.bad("lamp.tries", "must be at least 1");
        } else {
            ck.count("lamp.tries", l.tries.into(), 1, MAX_TRIES.into(), "");
        }
        match crate::lamp_protocol::Protocol::resolve(&l.protocol, &l.commands) {
            Ok(p) => {
                for (key, s) in p.commands() {
                    ck.command(key, s);
                }
            }
            Err(problems) => {
                for (key, msg) in problems {
                    ck.bad(&key, msg);
                }
            }
        }
        // The simulated lamp lights only the simulated scene; the simulated camera may be lit
        // by a serial lamp (`glint-mock lamp`'s light reaches it).
        if self.camera.backend != CameraBackend::Mock && l.backend == LampBackend::Mock {
            ck.bad(
                "lamp.backend",
                "the simulated lamp (\"mock\") lights only the simulated camera's scene: give a real camera a serial lamp (backend = \"serial\", port = \"/dev/ttyUSB0\")",
            );
        }
    }

    /// True when the geometry has no problem (so the simulated camera can be checked
    /// against it).
    fn check_geometry(&self, ck: &mut Checks) -> bool {
        let before = ck.out.len();
        let g = &self.geometry;
        let [nx, ny] = g.grid_inner_corners;
        if nx < 2 || ny < 2 {
            ck.bad(
                "geometry.grid_inner_corners",
                format!("needs at least 2x2 inner corners (got {nx}x{ny})"),
            );
        } else if nx > MAX_GRID_CORNERS || ny > MAX_GRID_CORNERS {
            ck.bad(
                "geometry.grid_inner_corners",
                format!(
                    "{nx}x{ny} inner corners: at most {MAX_GRID_CORNERS} a side (calibration boards have a few dozen; the detection and the pose refinement grow with the corner count, and a 1001x1000 grid takes minutes)"
                ),
            );
        } else if (nx % 2 == 0) == (ny % 2 == 0) {
            ck.bad(
                "geometry.grid_inner_corners",
                format!(
                    "{nx}x{ny} inner corners make a {}x{} board that looks the same turned half round, so its origin is ambiguous; use a board with an odd number of squares one way and an even number the other (e.g. 9x6 inner corners)",
                    nx + 1,
                    ny + 1
                ),
            );
        }
        let square_ok = ck.number(
            "geometry.grid_square_mm",
            g.grid_square_mm,
            MIN_SQUARE_MM,
            MAX_SQUARE_MM,
            " mm",
        );
        let thickness_ok = if g.tile_thickness_mm < 0.0 {
            ck.bad(
                "geometry.tile_thickness_mm",
                format!(
                    "must not be negative (got {})",
                    glint_mock::config::show_number(g.tile_thickness_mm)
                ),
            );
            false
        } else {
            ck.number(
                "geometry.tile_thickness_mm",
                g.tile_thickness_mm,
                0.0,
                MAX_LENGTH_MM,
                " mm (100 m)",
            )
        };
        let mut lamp_ok = true;
        for (axis, v) in ["x", "y", "z"].iter().zip(g.lamp_position_mm) {
            if !v.is_finite() || v.abs() > MAX_LENGTH_MM {
                ck.bad(
                    "geometry.lamp_position_mm",
                    format!(
                        "{axis} = {v} mm: each coordinate must be a finite number of mm within ±{MAX_LENGTH_MM} (100 m) of the grid's origin"
                    ),
                );
                lamp_ok = false;
                break;
            }
        }
        if lamp_ok && thickness_ok && g.lamp_position_mm[2] <= g.tile_thickness_mm.max(0.0) {
            ck.bad(
                "geometry.lamp_position_mm",
                format!(
                    "the lamp (z = {} mm) must be above the grid and the tile top (z = {} mm); z is measured up from the grid",
                    g.lamp_position_mm[2], g.tile_thickness_mm
                ),
            );
        }
        let poly = &g.tile_outline_mm;
        if poly.len() < 3 {
            ck.bad(
                "geometry.tile_outline_mm",
                format!("needs at least 3 corners (got {})", poly.len()),
            );
        } else if poly.len() > MAX_OUTLINE_CORNERS {
            ck.bad(
                "geometry.tile_outline_mm",
                format!(
                    "has {} corners; at most {MAX_OUTLINE_CORNERS} (a tile's outline is a simple polygon)",
                    poly.len()
                ),
            );
        } else if let Some((i, p)) = poly
            .iter()
            .enumerate()
            .find(|(_, p)| !(p[0].is_finite() && p[1].is_finite()))
        {
            ck.bad(
                "geometry.tile_outline_mm",
                format!(
                    "corner {} ({}, {}) must be finite numbers of mm",
                    i + 1,
                    p[0],
                    p[1]
                ),
            );
        } else {
            let area = polygon_area(poly);
            if area.is_nan() || area.abs() < 1.0 {
                ck.bad(
                    "geometry.tile_outline_mm",
                    "the outline encloses no area; list the corners in order around the tile",
                );
            }
            if square_ok && nx >= 2 && ny >= 2 {
                let s = g.grid_square_mm;
                let (x0, x1, y0, y1) = (-s, nx as f64 * s, -s, ny as f64 * s);
                if let Some(p) = poly
                    .iter()
                    .find(|p| !(p[0] >= x0 && p[0] <= x1 && p[1] >= y0 && p[1] <= y1))
                {
                    ck.bad(
                        "geometry.tile_outline_mm",
                        format!(
                            "corner ({}, {}) is off the grid, which spans x {x0}..{x1} mm and y {y0}..{y1} mm; measure the outline from the grid's origin corner",
                            p[0], p[1]
                        ),
                    );
                }
            }
        }
        ck.out.len() == before
    }

    fn check_reference(&self, ck: &mut Checks) {
        let Some(r) = &self.reference else {
            return;
        };
        for (key, v, lo, hi) in [
            ("reference.reflectance", &r.reflectance, 0.01, 1.0),
            ("reference.reflectance_sd", &r.reflectance_sd, 0.0, 0.2),
        ] {
            if let Some(x) = v.values().into_iter().find(|x| !(*x >= lo && *x <= hi)) {
                ck.bad(
                    key,
                    format!(
                        "{} is outside {lo}..{hi}; give the certificate's value as a fraction (0.99 for 99%)",
                        glint_mock::config::show_number(x)
                    ),
                );
            }
        }
        let g = &self.geometry;
        if !(r.thickness_mm >= 0.0 && r.thickness_mm < g.lamp_position_mm[2]) {
            ck.bad(
                "reference.thickness_mm",
                format!(
                    "{} mm: the top face's height above the grid, from 0 up to below the lamp (z = {} mm)",
                    glint_mock::config::show_number(r.thickness_mm),
                    g.lamp_position_mm[2]
                ),
            );
        }
        let poly = &r.outline_mm;
        if poly.len() < 3 || poly.len() > MAX_OUTLINE_CORNERS {
            ck.bad(
                "reference.outline_mm",
                format!(
                    "has {} corners; give 3 to {MAX_OUTLINE_CORNERS}, in order around the reference's top face",
                    poly.len()
                ),
            );
            return;
        }
        if poly
            .iter()
            .any(|p| !(p[0].abs() <= MAX_LENGTH_MM && p[1].abs() <= MAX_LENGTH_MM))
        {
            ck.bad(
                "reference.outline_mm",
                format!("corners must be finite numbers of mm within ±{MAX_LENGTH_MM} of the grid's origin"),
            );
            return;
        }
        let area = polygon_area(poly);
        if area.abs() < 25.0 {
            ck.bad(
                "reference.outline_mm",
                format!(
                    "encloses {:.1} mm²; the reference needs at least 5x5 mm (and a few hundred pixels in the photos); list the corners in order around it",
                    area.abs()
                ),
            );
            return;
        }
        // The two must not overlap: a corner of either inside the other, or crossing edges.
        let tile = &g.tile_outline_mm;
        let overlap = poly.iter().any(|p| inside_polygon(tile, p[0], p[1]))
            || tile.iter().any(|p| inside_polygon(poly, p[0], p[1]))
            || edges_cross(poly, tile);
        if overlap {
            ck.bad(
                "reference.outline_mm",
                "overlaps geometry.tile_outline_mm; the reference lies beside the tile, not on it",
            );
        }
    }

    fn check_bracket(&self, ck: &mut Checks) {
        let c = &self.camera;
        let b = &self.bracket;
        let external = c.backend == CameraBackend::External;
        // A processing rig may have no bracket: the photos bring their exposures.
        if b.exposures_us.is_empty() && !external {
            ck.bad(
                "bracket.exposures_us",
                "list at least one exposure, shortest first, in µs",
            );
        } else if b.exposures_us.len() > MAX_EXPOSURES {
            ck.bad(
                "bracket.exposures_us",
                format!(
                    "lists {} exposures; at most {MAX_EXPOSURES} (a bracket one stop apart spans a camera's whole range in about 20)",
                    b.exposures_us.len()
                ),
            );
        }
        if let Some(i) = b.exposures_us.windows(2).position(|w| w[1] <= w[0]) {
            ck.bad(
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
            .filter(|_| !external)
        {
            if e < c.min_exposure_us || e > c.max_exposure_us {
                ck.bad(
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
            ck.bad("bracket.frames_per_exposure", "must be at least 1");
        }
        if b.grid_frames == 0 {
            ck.bad(
                "bracket.grid_frames",
                "must be at least 1 (the grid photo calibrates the camera)",
            );
        }
        for (key, v) in [
            ("bracket.frames_per_exposure", b.frames_per_exposure),
            (
                "bracket.dark_frames_per_exposure",
                b.dark_frames_per_exposure,
            ),
            ("bracket.grid_frames", b.grid_frames),
        ] {
            if v > MAX_FRAMES_PER_STEP {
                ck.bad(
                    key,
                    format!(
                        "must be at most {MAX_FRAMES_PER_STEP} frames (got {v}); averaging 100 frames already cuts the noise tenfold"
                    ),
                );
            }
        }
    }

    fn check_mock(&self, ck: &mut Checks, geometry_ok: bool) {
        let c = &self.camera;
        let g = &self.geometry;
        let mock_camera = c.backend == CameraBackend::Mock;
        match (
            &self.mock,
            mock_camera || self.lamp.backend == LampBackend::Mock,
        ) {
            (None, true) => ck.bad(
                "mock",
                "backend \"mock\" needs a [mock] section (it may be empty to use the defaults)",
            ),
            (Some(m), _) => {
                if m.reference.is_some() && self.reference.is_none() {
                    ck.bad(
                        "mock.reference",
                        "gives the true albedo of a reference standard, but the rig has no [reference] section saying where it lies",
                    );
                }
                let mock_problems = m.problems();
                let mock_ok = mock_problems.is_empty();
                for (key, message) in mock_problems {
                    ck.bad(&format!("mock.{key}"), message);
                }
                let size_ok = (16..=MAX_IMAGE_SIDE).contains(&c.width)
                    && (16..=MAX_IMAGE_SIDE).contains(&c.height);
                if mock_ok && mock_camera && geometry_ok && size_ok {
                    let [nx, ny] = g.grid_inner_corners;
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
                            ck.bad(
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
            reference: self
                .reference
                .as_ref()
                .map(|r| glint_mock::ReferenceTarget {
                    outline_mm: r.outline_mm.clone(),
                    thickness_mm: r.thickness_mm,
                    albedo: self
                        .mock
                        .as_ref()
                        .and_then(|m| m.reference.as_ref())
                        .map(|t| t.albedo)
                        .unwrap_or([0, 1, 2].map(|c| r.reflectance.get(c, 3))),
                }),
        }
    }
}

/// The signed area of a polygon (shoelace formula), mm².
fn polygon_area(poly: &[[f64; 2]]) -> f64 {
    poly.iter()
        .zip(poly.iter().cycle().skip(1))
        .map(|(a, b)| a[0] * b[1] - b[0] * a[1])
        .sum::<f64>()
        / 2.0
}

/// Whether (x, y) is inside the polygon (even-odd rule).
pub fn inside_polygon(poly: &[[f64; 2]], x: f64, y: f64) -> bool {
    let mut inside = false;
    let n = poly.len();
    for i in 0..n {
        let (a, b) = (poly[i], poly[(i + n - 1) % n]);
        if (a[1] > y) != (b[1] > y) && x < (b[0] - a[0]) * (y - a[1]) / (b[1] - a[1]) + a[0] {
            inside = !inside;
        }
    }
    inside
}

/// Whether an edge of one polygon properly crosses an edge of the other.
fn edges_cross(p: &[[f64; 2]], q: &[[f64; 2]]) -> bool {
    let side = |a: [f64; 2], b: [f64; 2], c: [f64; 2]| {
        (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    };
    let edges = |v: &[[f64; 2]]| {
        (0..v.len())
            .map(|i| (v[i], v[(i + 1) % v.len()]))
            .collect::<Vec<_>>()
    };
    edges(p).iter().any(|&(a, b)| {
        edges(q).iter().any(|&(c, d)| {
            side(a, b, c) * side(a, b, d) < 0.0 && side(c, d, a) * side(c, d, b) < 0.0
        })
    })
}

/// Problems collected by [`Rig::problems`].
#[derive(Default)]
struct Checks {
    out: Vec<Problem>,
}

impl Checks {
    fn bad(&mut self, key: &str, message: impl Into<String>) {
        self.out.push(Problem {
            key: key.into(),
            message: message.into(),
        });
    }

    /// A finite number in `lo..=hi` (`unit` follows the bound in the message).
    fn number(&mut self, key: &str, v: f64, lo: f64, hi: f64, unit: &str) -> bool {
        match glint_mock::config::out_of_range(v, lo, hi, unit) {
            Some(why) => {
                self.bad(key, why);
                false
            }
            None => true,
        }
    }

    /// A whole number in `lo..=hi`.
    fn count(&mut self, key: &str, v: u64, lo: u64, hi: u64, unit: &str) -> bool {
        let why = if v < lo {
            format!("must be at least {lo}{unit} (got {v})")
        } else if v > hi {
            format!("must be at most {hi}{unit} (got {v})")
        } else {
            return true;
        };
        self.bad(key, why);
        false
    }

    /// A device path: at most [`MAX_PATH_BYTES`], no NUL.
    fn path(&mut self, key: &str, s: &str) {
        if s.len() > MAX_PATH_BYTES || s.contains('\0') {
            self.bad(
                key,
                format!(
                    "{} is not a usable path: at most {MAX_PATH_BYTES} bytes, without NUL",
                    quote(s)
                ),
            );
        }
    }

    /// A lamp command: one non-empty line of at most [`MAX_COMMAND_BYTES`], no control
    /// characters (the driver ends each command with `\n` itself).
    fn command(&mut self, key: &str, s: &str) {
        let why = if s.is_empty() {
            "is empty; give the command the lamp expects".to_string()
        } else if s.len() > MAX_COMMAND_BYTES {
            format!(
                "is {} bytes; at most {MAX_COMMAND_BYTES} (one protocol line)",
                s.len()
            )
        } else if s.contains('\0') {
            format!("{} has a NUL byte; remove it", quote(s))
        } else if s.contains(['\r', '\n']) {
            format!(
                "{} has a line break (CR or LF); remove it: the driver ends every command with a newline itself",
                quote(s)
            )
        } else if let Some(c) = s.chars().find(|c| c.is_control()) {
            format!(
                "{} has the control character U+{:04X}; a command is one line of text",
                quote(s),
                c as u32
            )
        } else {
            return;
        };
        self.bad(key, why);
    }
}

/// A camera's profile file beside the rig file `rig`: `<rig folder>/profiles/<model><suffix>`,
/// the model's characters other than letters, digits, `-` and `_` made `-` (at most 100 of
/// them), so that no model name can leave the folder. None where the rig's folder is not a
/// folder. The response profile (`hdr::run::profile_path_for`) and the lens profile
/// (`calib::lens::profile_path`) are both named here.
pub fn profile_file(rig: &Path, model: &str, suffix: &str) -> Option<PathBuf> {
    let dir = rig
        .parent()
        .filter(|d| d.as_os_str().is_empty() || d.is_dir())?;
    let name: String = model
        .chars()
        .take(100)
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '-'
            }
        })
        .collect();
    Some(dir.join("profiles").join(format!("{name}{suffix}")))
}
