//! The nokhwa camera backend (cargo feature `nokhwa`): a camera through the `nokhwa` crate,
//! for machines without Glint's own V4L2 backend in mind (macOS, Windows).
//!
//! nokhwa gives one API over V4L2, AVFoundation and Media Foundation, but less than Glint's
//! measurements need, so this backend is narrower than [`super::v4l2`]. What nokhwa 0.10.11
//! (with nokhwa-bindings-linux 0.1.4 and the v4l crate 0.14) allows, and what Glint does
//! about what it does not:
//!
//! - **Opening.** On Linux it opens a camera only by index, as `/dev/videoN`
//!   (`V4LCaptureDevice::new` takes `CameraIndex::as_index()`, and `v4l::Device::new(index)`
//!   opens `format!("/dev/video{}", index)`). `camera.device` is an index or a path; a path
//!   is opened as the `/dev/videoN` that is the same file (a `/dev/v4l/by-id` link resolves
//!   to one), and any other path is refused. The format is asked for exactly
//!   (`RequestedFormatType::Exact`) and nokhwa refuses what the driver changes; it takes only
//!   whole frames per second.
//! - **Formats.** Its `FrameFormat`s are MJPEG, YUYV, NV12, GRAY, RAWRGB and RAWBGR: no Y16,
//!   Y10 or Y12, and on Linux it asks V4L2 for GRAY as the code `GRAY`, which no driver has
//!   (V4L2's is `GREY`), so it cannot open a GREY camera there.
//! - **Exposure.** Its `KnownCameraControl::Exposure` is V4L2's user-class
//!   `V4L2_CID_EXPOSURE`, not the camera-class `exposure_time_absolute` UVC cameras have.
//!   Glint sets `exposure_time_absolute` (100 µs units), `auto_exposure` and the other
//!   automatics ([`STANDARD_CONTROLS`]) by their V4L2 ids (`KnownCameraControl::Other(id)`),
//!   and reads each back, so exposures are driven on Linux only: on macOS and Windows the
//!   controls have other ids and units, which Glint has not been exercised with, and the
//!   backend refuses there ([`problems`]).
//! - **Frames.** It returns the whole mmap buffer, without the driver's sequence number,
//!   `bytesused` or error flag, and its time stamp is a wall-clock estimate made from the
//!   driver's. Frames are numbered here as they arrive, so a dropped frame cannot be
//!   detected, nor a damaged one told from a good one ([`CameraInfo::notes`] says so); no
//!   device time stamp is recorded. Rows are taken as packed, and YUYV as BT.601 limited
//!   range (V4L2's default): nokhwa passes neither the stride nor the colorimetry. As with
//!   UVC, frames carry no exposure, and the capture verifies each exposure from the images.
//! - **Waiting.** Its `frame()` waits without limit (its stream polls with no timeout), and
//!   its `Camera` is not `Send`. The nokhwa camera therefore lives on a thread of its own
//!   that answers requests in order; a frame that does not come within the timeout is a
//!   [`DeviceError::CameraTimeout`] while that thread stays blocked, never a hang.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use nokhwa::utils::{
    CameraControl, CameraFormat, CameraIndex, ControlValueDescription, ControlValueSetter,
    FrameFormat, KnownCameraControl, KnownCameraControlFlag, RequestedFormat, RequestedFormatType,
    Resolution,
};
use nokhwa::NokhwaError;

use super::decode::{self, RawLayout, YcbcrParams};
use super::v4l2_rules::{
    cid, control_name, exposure_units, park_exposure_us, EXPOSURE_MANUAL, EXPOSURE_UNIT_US,
    STANDARD_CONTROLS,
};
use crate::error::DeviceError;
use crate::rig::{CameraBackend, MissingControl, PixelFormat, Rig};
use crate::traits::Camera;
use glint_format::image::{CameraInfo, ControlReading, Frame};

/// Whether this build drives exposures through nokhwa: by V4L2 control ids, on Linux.
const EXPOSURE_BY_V4L2_IDS: bool = cfg!(target_os = "linux");

/// Why a nokhwa camera cannot be driven off Linux.
const NOT_LINUX: &str = "camera.backend = \"nokhwa\" drives exposures only on Linux in this Glint (through V4L2 control ids); nokhwa's exposure controls on macOS (AVFoundation) and Windows (Media Foundation) have other ids and units and have not been exercised";

/// Why a GREY camera cannot be opened through nokhwa on Linux.
const GREY_ON_LINUX: &str = "camera.pixel_format = \"GREY\": nokhwa asks V4L2 for it as \"GRAY\", a code no driver has (V4L2's is \"GREY\"), so it cannot open a GREY camera; use camera.backend = \"v4l2\"";

/// How long opening may take (nokhwa lists every format, size and rate first).
const OPEN_TIMEOUT: Duration = Duration::from_secs(30);

/// How long setting a control may take.
const CONTROL_TIMEOUT: Duration = Duration::from_secs(5);

/// nokhwa's name for a pixel format, where it has one.
pub fn frame_format(pf: PixelFormat) -> Option<FrameFormat> {
    match pf {
        PixelFormat::YUYV => Some(FrameFormat::YUYV),
        PixelFormat::MJPG => Some(FrameFormat::MJPEG),
        PixelFormat::RGB3 => Some(FrameFormat::RAWRGB),
        PixelFormat::BGR3 => Some(FrameFormat::RAWBGR),
        PixelFormat::GREY => Some(FrameFormat::GRAY),
        PixelFormat::Y16 | PixelFormat::Y10 | PixelFormat::Y12 => None,
    }
}

/// The pixel format of a nokhwa frame format, where Glint reads it (not NV12).
pub fn pixel_format(ff: FrameFormat) -> Option<PixelFormat> {
    match ff {
        FrameFormat::YUYV => Some(PixelFormat::YUYV),
        FrameFormat::MJPEG => Some(PixelFormat::MJPG),
        FrameFormat::RAWRGB => Some(PixelFormat::RGB3),
        FrameFormat::RAWBGR => Some(PixelFormat::BGR3),
        FrameFormat::GRAY => Some(PixelFormat::GREY),
        FrameFormat::NV12 => None,
    }
}

/// The four-character code nokhwa asks V4L2 for, for a frame format (nokhwa-bindings-linux
/// 0.1.4, `frameformat_to_fourcc`).
pub fn v4l2_code_asked(ff: FrameFormat) -> [u8; 4] {
    *match ff {
        FrameFormat::MJPEG => b"MJPG",
        FrameFormat::YUYV => b"YUYV",
        FrameFormat::GRAY => b"GRAY",
        FrameFormat::RAWRGB => b"RGB3",
        FrameFormat::RAWBGR => b"BGR3",
        FrameFormat::NV12 => b"NV12",
    }
}

/// The V4L2 control id behind each of nokhwa's named controls on Linux
/// (nokhwa-bindings-linux's `known_camera_control_to_id`; videodev2.h numbers). nokhwa lists
/// a control with one of these ids under its name, every other under `Other(id)`.
const KNOWN_IDS: [(KnownCameraControl, u32); 15] = [
    (KnownCameraControl::Brightness, 0x0098_0900),
    (KnownCameraControl::Contrast, 0x0098_0901),
    (KnownCameraControl::Saturation, 0x0098_0902),
    (KnownCameraControl::Hue, 0x0098_0903),
    (KnownCameraControl::Gamma, 0x0098_0910),
    (KnownCameraControl::Exposure, 0x0098_0911),
    (KnownCameraControl::Gain, 0x0098_0913),
    (KnownCameraControl::WhiteBalance, 0x0098_091a),
    (KnownCameraControl::Sharpness, 0x0098_091b),
    (KnownCameraControl::BacklightComp, 0x0098_091c),
    (KnownCameraControl::Pan, 0x009a_0904),
    (KnownCameraControl::Tilt, 0x009a_0905),
    (KnownCameraControl::Focus, 0x009a_090b),
    (KnownCameraControl::Zoom, 0x009a_090e),
    (KnownCameraControl::Iris, 0x009a_0912),
];

/// How nokhwa names the V4L2 control `id`.
pub fn control_key(id: u32) -> KnownCameraControl {
    KNOWN_IDS
        .iter()
        .find(|(_, i)| *i == id)
        .map_or(KnownCameraControl::Other(id as u128), |(k, _)| *k)
}

/// The V4L2 id of a control as nokhwa names it.
pub fn control_id(key: KnownCameraControl) -> Option<u32> {
    match key {
        KnownCameraControl::Other(id) => u32::try_from(id).ok(),
        k => KNOWN_IDS.iter().find(|(n, _)| *n == k).map(|(_, i)| *i),
    }
}

/// What keeps this build from driving a rig's camera through nokhwa (nothing: empty).
/// `glint rig check` and the dry runs report them; [`NokhwaCamera::open`] refuses on them.
pub fn problems(rig: &Rig) -> Vec<String> {
    let mut out = Vec::new();
    if rig.camera.backend != CameraBackend::Nokhwa {
        return out;
    }
    if !EXPOSURE_BY_V4L2_IDS {
        out.push(NOT_LINUX.to_string());
    }
    if EXPOSURE_BY_V4L2_IDS && rig.camera.pixel_format == Some(PixelFormat::GREY) {
        out.push(GREY_ON_LINUX.to_string());
    }
    out
}

/// `/dev/videoN` → N.
fn dev_video_index(p: &Path) -> Option<u32> {
    if p.parent() != Some(Path::new("/dev")) {
        return None;
    }
    let n = p.file_name()?.to_str()?.strip_prefix("video")?;
    if n.is_empty() || !n.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    n.parse().ok()
}

/// The camera index nokhwa is to open for `camera.device`, and how to name the camera in
/// messages: an index (`"0"`), or on Linux a path that is a `/dev/videoN` (through links,
/// or as the same file under another name).
fn camera_index(device: &str) -> Result<(u32, String), NokhwaFault> {
    let device = device.trim();
    if !device.is_empty() && device.bytes().all(|b| b.is_ascii_digit()) {
        let n: u32 = device.parse().map_err(|_| NokhwaFault::IndexRange {
            device: device.to_string(),
        })?;
        let shown = if cfg!(target_os = "linux") {
            format!("/dev/video{n}")
        } else {
            format!("index {n}")
        };
        return Ok((n, shown));
    }
    if !cfg!(target_os = "linux") {
        return Err(NokhwaFault::ByIndexOnly {
            device: device.to_string(),
        });
    }
    same_dev_video(Path::new(device))
}

#[cfg(target_os = "linux")]
fn same_dev_video(path: &Path) -> Result<(u32, String), NokhwaFault> {
    use std::os::unix::fs::MetadataExt;
    let refuse = || NokhwaFault::NotDevVideo {
        path: path.to_path_buf(),
    };
    let meta = std::fs::metadata(path).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => NokhwaFault::NoSuchDevice {
            path: path.to_path_buf(),
        },
        _ => NokhwaFault::Stat {
            path: path.to_path_buf(),
            source: e,
        },
    })?;
    let shown = |n: u32| {
        if path == Path::new(&format!("/dev/video{n}")) {
            path.display().to_string()
        } else {
            format!("{} (/dev/video{n})", path.display())
        }
    };
    if let Some(n) = std::fs::canonicalize(path)
        .ok()
        .and_then(|p| dev_video_index(&p))
    {
        return Ok((n, shown(n)));
    }
    // Another name for a /dev/videoN node: the same file, or the same character device.
    let same = |m: &std::fs::Metadata| {
        (m.dev(), m.ino()) == (meta.dev(), meta.ino())
            || (m.file_type().is_char_device()
                && meta.file_type().is_char_device()
                && m.rdev() == meta.rdev())
    };
    use std::os::unix::fs::FileTypeExt;
    let entries = std::fs::read_dir("/dev").map_err(NokhwaFault::ListDev)?;
    let mut found: Vec<u32> = entries
        .flatten()
        .filter_map(|e| {
            let p = e.path();
            let n = dev_video_index(&p)?;
            std::fs::metadata(&p).ok().filter(same).map(|_| n)
        })
        .collect();
    found.sort_unstable();
    found.first().map(|&n| (n, shown(n))).ok_or_else(refuse)
}

#[cfg(not(target_os = "linux"))]
fn same_dev_video(path: &Path) -> Result<(u32, String), NokhwaFault> {
    Err(NokhwaFault::ByIndexOnly {
        device: path.display().to_string(),
    })
}

/// Why nokhwa could not find, set up or drive the camera: the reason of a
/// [`DeviceError::Open`], or of a [`DeviceError::Io`] once the camera is open.
#[derive(Debug, thiserror::Error)]
enum NokhwaFault {
    #[error("camera index {device} is out of range")]
    IndexRange { device: String },
    #[error("{device}: nokhwa opens cameras by index here; give camera.device as a number (device = \"0\")")]
    ByIndexOnly { device: String },
    #[error("nokhwa opens V4L2 cameras only as /dev/videoN, by index, and {} is none of them; give camera.device as the camera's index (device = \"0\") or /dev/videoN path, or use camera.backend = \"v4l2\", which opens any path", .path.display())]
    NotDevVideo { path: std::path::PathBuf },
    #[error("{}: no such device; `glint devices` lists the cameras present", .path.display())]
    NoSuchDevice { path: std::path::PathBuf },
    #[error("{}: {source}", .path.display())]
    Stat {
        path: std::path::PathBuf,
        source: std::io::Error,
    },
    #[error("listing /dev: {0}")]
    ListDev(std::io::Error),
    /// What nokhwa said, on one line.
    #[error("{detail}")]
    Nokhwa { detail: String },
    /// A step of the set-up that failed, and why.
    #[error("{doing}: {source}")]
    Doing {
        doing: String,
        source: Box<NokhwaFault>,
    },
    #[error("nokhwa could not open it as {format}: {source}")]
    OpenAs {
        format: String,
        source: Box<NokhwaFault>,
    },
    #[error("asked for {asked}, nokhwa set {got}")]
    FormatSet { asked: String, got: String },
    #[error("{card} has no exposure_time_absolute control (V4L2 id {id:#x}) that nokhwa can read, so Glint cannot set its exposures; its controls are: {controls}")]
    NoExposureControl {
        card: String,
        id: u32,
        controls: String,
    },
    #[error("nokhwa describes exposure_time_absolute as {description}, not a range")]
    NotARange { description: String },
    #[error("{missing}; set missing_control = \"warn\" to go on without it")]
    MissingControl { missing: String },
    #[error("control `{name}` (camera.controls) is read-only")]
    ReadOnly { name: String },
    #[error("control `{name}` = {value} (camera.controls) is outside its range: {lo}..{hi}")]
    OutOfRange {
        name: String,
        value: i64,
        lo: i64,
        hi: i64,
    },
    #[error("{} reads back {} = {} after being switched to manual exposure ({}); it cannot be used for measurement", .card, .name, .value, EXPOSURE_MANUAL)]
    NotManual {
        card: String,
        name: String,
        value: i64,
    },
    #[error("{control} is not a number")]
    NotANumber { control: String },
    #[error("nokhwa panicked while {what}: {msg}")]
    Panicked { what: &'static str, msg: String },
}

impl NokhwaFault {
    /// This fault as the reason `doing` failed.
    fn doing(self, doing: impl Into<String>) -> NokhwaFault {
        NokhwaFault::Doing {
            doing: doing.into(),
            source: Box::new(self),
        }
    }
}

/// What the camera thread is asked to do.
enum Request {
    /// Set `exposure_time_absolute` to this many units and read it back.
    Exposure(i64),
    /// The next frame's bytes.
    Grab,
}

/// The camera thread's answers, in the order of the requests.
enum Reply {
    Exposure(Result<i64, NokhwaFault>),
    Frame(Result<Vec<u8>, NokhwaFault>),
}

/// What the camera thread needs to set the camera up.
struct Setup {
    index: u32,
    format: CameraFormat,
    controls: std::collections::BTreeMap<String, i64>,
    missing_control: MissingControl,
    park_us: u32,
}

/// What setting the camera up found.
struct Opened {
    card: String,
    driver: String,
    bus: String,
    exposure: ExposureRange,
    readings: Vec<ControlReading>,
    notes: Vec<String>,
}

/// `exposure_time_absolute`'s range, in its 100 µs units.
#[derive(Debug, Clone, Copy)]
struct ExposureRange {
    min: i64,
    max: i64,
    step: i64,
}

/// A camera through nokhwa, set up for measurement and streaming on its own thread.
pub struct NokhwaCamera {
    requests: Option<mpsc::Sender<Request>>,
    replies: mpsc::Receiver<Reply>,
    /// Replies the camera thread still owes (a request whose wait ran out is answered late).
    owed: usize,
    thread: Option<std::thread::JoinHandle<()>>,
    shown: String,
    layout: RawLayout,
    exposure: ExposureRange,
    info: CameraInfo,
    /// The number the next frame nokhwa delivers gets (nokhwa passes no sequence numbers).
    next_sequence: u64,
}

fn open_err(shown: &str, reason: impl ToString) -> DeviceError {
    DeviceError::Open {
        what: format!("camera {shown} (nokhwa)"),
        reason: reason.to_string(),
    }
}

/// A control's value as nokhwa describes it, where it is a number or a switch.
fn value_of(d: &ControlValueDescription) -> Option<i64> {
    match d {
        ControlValueDescription::Integer { value, .. }
        | ControlValueDescription::IntegerRange { value, .. } => Some(*value),
        ControlValueDescription::Boolean { value, .. } => Some(*value as i64),
        _ => None,
    }
}

/// `min`, `max` and `step` of a numeric control (a switch is 0..1).
fn range_of(d: &ControlValueDescription) -> Option<(i64, i64, i64)> {
    match d {
        ControlValueDescription::IntegerRange { min, max, step, .. } => Some((*min, *max, *step)),
        ControlValueDescription::Boolean { .. } => Some((0, 1, 1)),
        _ => None,
    }
}

/// One line for a nokhwa error.
fn one_line(e: &NokhwaError) -> NokhwaFault {
    NokhwaFault::Nokhwa {
        detail: e.to_string().replace('\n', "; "),
    }
}

/// Set a control to `value` the way nokhwa takes its kind (a switch as a boolean). nokhwa
/// reads the control back and calls a value other than the one asked for "Rejected"; that
/// is not an error here: the caller reads back what was applied.
fn set_control(cam: &mut nokhwa::Camera, c: &CameraControl, value: i64) -> Result<(), NokhwaFault> {
    let setter = match c.description() {
        ControlValueDescription::Boolean { .. } => ControlValueSetter::Boolean(value != 0),
        _ => ControlValueSetter::Integer(value),
    };
    match cam.set_camera_control(c.control(), setter) {
        Ok(()) => Ok(()),
        Err(NokhwaError::SetPropertyError { error, .. }) if error == "Rejected" => Ok(()),
        Err(e) => Err(one_line(&e)),
    }
}

fn read_control(cam: &nokhwa::Camera, key: KnownCameraControl) -> Result<i64, NokhwaFault> {
    let c = cam.camera_control(key).map_err(|e| one_line(&e))?;
    value_of(c.description()).ok_or_else(|| NokhwaFault::NotANumber {
        control: c.name().to_string(),
    })
}

fn names(controls: &[CameraControl]) -> String {
    controls
        .iter()
        .map(|c| control_name(c.name()))
        .collect::<Vec<_>>()
        .join(", ")
}

/// Open the camera through nokhwa and set it up for measurement (on the camera thread).
/// Returns the camera, what was found, and its `exposure_time_absolute` control.
fn set_up(s: &Setup) -> Result<(nokhwa::Camera, Opened, CameraControl), NokhwaFault> {
    let wanted = [s.format.format()];
    let mut cam = nokhwa::Camera::new(
        CameraIndex::Index(s.index),
        RequestedFormat::with_formats(RequestedFormatType::Exact(s.format), &wanted),
    )
    .map_err(|e| NokhwaFault::OpenAs {
        format: s.format.to_string(),
        source: Box::new(one_line(&e)),
    })?;
    let got = cam.camera_format();
    if got != s.format {
        return Err(NokhwaFault::FormatSet {
            asked: s.format.to_string(),
            got: got.to_string(),
        });
    }
    let ni = cam.info().clone();
    let card = ni.human_name();
    let mut notes = vec![
        "nokhwa passes no frame sequence numbers: frames are numbered as they arrive, so a dropped frame cannot be detected".to_string(),
        "nokhwa passes neither the driver's error flag nor the bytes it filled: a damaged frame cannot be told from a good one".to_string(),
        "nokhwa passes no device time stamps (only a wall-clock estimate): none are recorded".to_string(),
    ];
    if s.format.format() == FrameFormat::YUYV {
        notes.push(format!(
            "YUYV decoded as {} (V4L2's default): nokhwa does not pass the driver's colorimetry",
            YcbcrParams::default()
        ));
    }
    let note = |notes: &mut Vec<String>, msg: String| {
        tracing::warn!("{msg}");
        notes.push(msg);
    };

    let controls = cam
        .camera_controls()
        .map_err(|e| one_line(&e).doing("listing its controls"))?;
    let by_id = |id: u32| controls.iter().find(|c| c.control() == control_key(id));
    let Some(exp) = by_id(cid::EXPOSURE_ABSOLUTE) else {
        return Err(NokhwaFault::NoExposureControl {
            card,
            id: cid::EXPOSURE_ABSOLUTE,
            controls: names(&controls),
        });
    };
    let Some((min, max, step)) = range_of(exp.description()) else {
        return Err(NokhwaFault::NotARange {
            description: format!("{:?}", exp.description()),
        });
    };
    let exposure = ExposureRange {
        min,
        max,
        step: step.max(1),
    };
    let exp_control = exp.clone();
    let park_units = exposure_units(s.park_us, exposure.min, exposure.max, exposure.step);
    let mut requested: std::collections::BTreeMap<u32, i64> = Default::default();
    for (id, value, known) in STANDARD_CONTROLS {
        let Some(c) = by_id(id) else {
            note(
                &mut notes,
                format!(
                    "{card} has no {} control that nokhwa can read; it was left as it is",
                    known.join(" / ")
                ),
            );
            continue;
        };
        match set_control(&mut cam, c, value) {
            Ok(()) => {
                requested.insert(id, value);
            }
            Err(e) if id == cid::EXPOSURE_AUTO => {
                return Err(e.doing(format!(
                    "could not switch {card} to manual exposure ({} = {EXPOSURE_MANUAL})",
                    control_name(c.name())
                )))
            }
            Err(e) => note(
                &mut notes,
                format!("could not set {} to {value}: {e}", control_name(c.name())),
            ),
        }
        if id == cid::EXPOSURE_AUTO {
            // Some cameras drop the exposure when switching to manual: write it again.
            set_control(&mut cam, exp, park_units)
                .map_err(|e| e.doing(format!("setting exposure_time_absolute to {park_units}")))?;
            requested.insert(cid::EXPOSURE_ABSOLUTE, park_units);
        }
    }
    for (name, &value) in &s.controls {
        let Some(c) = controls.iter().find(|c| &control_name(c.name()) == name) else {
            let msg = format!(
                "{card} has no control `{name}` (camera.controls) that nokhwa can read; its controls are: {}",
                names(&controls)
            );
            match s.missing_control {
                MissingControl::Error => return Err(NokhwaFault::MissingControl { missing: msg }),
                MissingControl::Warn => {
                    note(&mut notes, msg);
                    continue;
                }
            }
        };
        if c.flag().contains(&KnownCameraControlFlag::ReadOnly) {
            return Err(NokhwaFault::ReadOnly { name: name.clone() });
        }
        if let Some((lo, hi, _)) = range_of(c.description()) {
            if value < lo || value > hi {
                return Err(NokhwaFault::OutOfRange {
                    name: name.clone(),
                    value,
                    lo,
                    hi,
                });
            }
        }
        set_control(&mut cam, c, value).map_err(|e| {
            e.doing(format!(
                "setting control `{name}` to {value} (camera.controls)"
            ))
        })?;
        if let Some(id) = control_id(c.control()) {
            requested.insert(id, value);
        }
    }

    // Read everything back.
    let controls = cam
        .camera_controls()
        .map_err(|e| one_line(&e).doing("reading its controls back"))?;
    let mut readings = Vec::new();
    for c in &controls {
        let Some(value) = value_of(c.description()) else {
            continue;
        };
        let name = control_name(c.name());
        let asked = control_id(c.control()).and_then(|id| requested.get(&id).copied());
        if control_id(c.control()) == Some(cid::EXPOSURE_AUTO) && value != EXPOSURE_MANUAL {
            return Err(NokhwaFault::NotManual { card, name, value });
        }
        if let Some(a) = asked.filter(|&a| a != value) {
            note(
                &mut notes,
                format!("{name} was set to {a} but reads back {value}"),
            );
        }
        readings.push(ControlReading {
            name,
            value,
            requested: asked,
        });
    }
    cam.open_stream()
        .map_err(|e| one_line(&e).doing("starting to stream"))?;
    Ok((
        cam,
        Opened {
            card,
            driver: ni.description().to_string(),
            bus: ni.misc(),
            exposure,
            readings,
            notes,
        },
        exp_control,
    ))
}

/// A panic in nokhwa (or the crates under it) as an error message.
fn guarded<T>(
    what: &'static str,
    f: impl FnOnce() -> Result<T, NokhwaFault>,
) -> Result<T, NokhwaFault> {
    catch_unwind(AssertUnwindSafe(f)).unwrap_or_else(|p| {
        let msg = p
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| p.downcast_ref::<String>().cloned())
            .unwrap_or_default();
        Err(NokhwaFault::Panicked { what, msg })
    })
}

/// The camera thread: set the camera up, say how that went, then answer requests in order
/// until the handle is dropped.
fn camera_thread(
    setup: Setup,
    opened: mpsc::Sender<Result<Opened, NokhwaFault>>,
    requests: mpsc::Receiver<Request>,
    replies: mpsc::Sender<Reply>,
) {
    let (mut cam, exp) = match guarded("opening the camera", || set_up(&setup)) {
        Ok((cam, o, exp)) => {
            if opened.send(Ok(o)).is_err() {
                return;
            }
            (cam, exp)
        }
        Err(e) => {
            let _ = opened.send(Err(e));
            return;
        }
    };
    for r in requests {
        let reply = match r {
            Request::Exposure(units) => Reply::Exposure(guarded("setting the exposure", || {
                set_control(&mut cam, &exp, units)?;
                read_control(&cam, exp.control())
            })),
            Request::Grab => Reply::Frame(guarded("reading a frame", || {
                cam.frame_raw()
                    .map(|b| b.into_owned())
                    .map_err(|e| one_line(&e))
            })),
        };
        if replies.send(reply).is_err() {
            break;
        }
    }
    // Dropping the camera stops its stream.
    let _ = guarded("closing the camera", || {
        drop(cam);
        Ok(())
    });
}

/// Why a request got no answer.
enum NoAnswer {
    TimedOut,
    /// The camera thread is gone (it ended after a panic in nokhwa's drop, say).
    Gone,
}

impl NokhwaCamera {
    /// Open the rig's camera (`camera.device`: an index, or on Linux a /dev/videoN path)
    /// through nokhwa in exactly the rig's format, switch its automatic controls off, set
    /// `[camera.controls]`, read every control back, and start streaming.
    pub fn open(rig: &Rig) -> Result<NokhwaCamera, DeviceError> {
        let c = &rig.camera;
        let device = c.device.clone().unwrap_or_default();
        let (index, shown) = camera_index(&device).map_err(|e| open_err(&device, e))?;
        if let Some(p) = problems(rig).into_iter().next() {
            return Err(open_err(&shown, p));
        }
        let Some(pf) = c.pixel_format else {
            return Err(open_err(&shown, "camera.pixel_format is not set"));
        };
        if pf.lossy() && !c.allow_lossy {
            return Err(open_err(
                &shown,
                format!("{pf} is lossy and processed in the camera; set camera.allow_lossy = true to accept it, or choose YUYV"),
            ));
        }
        let Some(ff) = frame_format(pf) else {
            return Err(open_err(&shown, format!("nokhwa has no {pf}")));
        };
        if c.fps.fract() != 0.0 || !(1.0..=1000.0).contains(&c.fps) {
            return Err(open_err(
                &shown,
                format!("nokhwa sets whole frames per second, not {}", c.fps),
            ));
        }
        let setup = Setup {
            index,
            format: CameraFormat::new(Resolution::new(c.width, c.height), ff, c.fps as u32),
            controls: c.controls.clone(),
            missing_control: c.missing_control,
            park_us: park_exposure_us(rig),
        };
        let (opened_tx, opened_rx) = mpsc::channel();
        let (req_tx, req_rx) = mpsc::channel();
        let (rep_tx, rep_rx) = mpsc::channel();
        let thread = std::thread::Builder::new()
            .name("nokhwa-camera".into())
            .spawn(move || camera_thread(setup, opened_tx, req_rx, rep_tx))
            .map_err(|e| open_err(&shown, format!("starting its thread: {e}")))?;
        let o = match opened_rx.recv_timeout(OPEN_TIMEOUT) {
            Ok(Ok(o)) => o,
            Ok(Err(e)) => return Err(open_err(&shown, e)),
            Err(mpsc::RecvTimeoutError::Timeout) => {
                return Err(open_err(
                    &shown,
                    format!(
                        "nokhwa did not finish opening it within {} s",
                        OPEN_TIMEOUT.as_secs()
                    ),
                ))
            }
            Err(mpsc::RecvTimeoutError::Disconnected) => {
                return Err(open_err(&shown, "nokhwa's camera thread ended"))
            }
        };
        let (w, h) = (c.width, c.height);
        let layout = RawLayout::packed(pf, w, h);
        tracing::info!(
            "opened {shown} through nokhwa: {} {pf} {w}x{h}, exposure_time_absolute {}..{} step {}",
            o.card,
            o.exposure.min,
            o.exposure.max,
            o.exposure.step
        );
        let info = CameraInfo {
            backend: Some("nokhwa".into()),
            device: Some(format!("{} / {} / {} at {shown}", o.driver, o.card, o.bus)),
            pixel_format: Some(pf.name().to_string()),
            ycbcr_encoding: (pf == PixelFormat::YUYV).then(|| layout.ycbcr.to_string()),
            lossy: pf.lossy(),
            controls: o.readings,
            notes: o.notes,
            ..CameraInfo::basic(o.card.clone(), w, h, pf.bit_depth(), pf.channels())
        };
        Ok(NokhwaCamera {
            requests: Some(req_tx),
            replies: rep_rx,
            owed: 0,
            thread: Some(thread),
            shown,
            layout,
            exposure: o.exposure,
            info,
            next_sequence: 0,
        })
    }

    /// Ask the camera thread and wait up to `timeout` for its answer. Late answers to
    /// earlier requests come first and are passed over; a frame among them counts as
    /// delivered (and so shows as a gap in the numbering).
    fn call(&mut self, r: Request, timeout: Duration) -> Result<Reply, NoAnswer> {
        let Some(tx) = &self.requests else {
            return Err(NoAnswer::Gone);
        };
        tx.send(r).map_err(|_| NoAnswer::Gone)?;
        self.owed += 1;
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.replies.recv_timeout(left) {
                Ok(reply) => {
                    self.owed -= 1;
                    if self.owed == 0 {
                        return Ok(reply);
                    }
                    if let Reply::Frame(Ok(_)) = reply {
                        self.next_sequence += 1;
                    }
                }
                Err(mpsc::RecvTimeoutError::Timeout) => return Err(NoAnswer::TimedOut),
                Err(mpsc::RecvTimeoutError::Disconnected) => return Err(NoAnswer::Gone),
            }
        }
    }

    fn gone(&self) -> DeviceError {
        DeviceError::Io {
            op: format!("talking to camera {} through nokhwa", self.shown),
            source: std::io::Error::other("nokhwa's camera thread ended"),
        }
    }

    /// An error nokhwa reported: a vanished device (ENODEV, EIO, ENXIO in its message, the
    /// only form nokhwa passes them on in) is [`DeviceError::Unplugged`].
    fn device_err(&self, op: &str, fault: NokhwaFault) -> DeviceError {
        let msg = fault.to_string();
        if ["(os error 19)", "(os error 5)", "(os error 6)"]
            .iter()
            .any(|e| msg.contains(e))
        {
            return DeviceError::Unplugged {
                device: format!("camera {}", self.shown),
            };
        }
        DeviceError::Io {
            op: format!("{op} on camera {} (nokhwa)", self.shown),
            source: std::io::Error::other(msg),
        }
    }
}

impl Drop for NokhwaCamera {
    fn drop(&mut self) {
        // Closing the request channel ends the camera thread, which closes the camera; a
        // thread still blocked in nokhwa's wait for a frame is left to the process's end.
        self.requests = None;
        if let Some(t) = self.thread.take() {
            if self.owed == 0 {
                let _ = t.join();
            }
        }
    }
}

impl Camera for NokhwaCamera {
    fn info(&self) -> CameraInfo {
        self.info.clone()
    }

    fn set_exposure(&mut self, us: u32) -> Result<u32, DeviceError> {
        let e = self.exposure;
        let units = exposure_units(us, e.min, e.max, e.step);
        let op = format!(
            "setting exposure_time_absolute to {units} ({} µs)",
            units * EXPOSURE_UNIT_US as i64
        );
        match self.call(Request::Exposure(units), CONTROL_TIMEOUT) {
            Ok(Reply::Exposure(Ok(back))) => {
                Ok((back.clamp(0, (u32::MAX / EXPOSURE_UNIT_US) as i64) as u32) * EXPOSURE_UNIT_US)
            }
            Ok(Reply::Exposure(Err(msg))) => Err(self.device_err(&op, msg)),
            Ok(Reply::Frame(_)) => Err(self.gone()),
            Err(NoAnswer::TimedOut) => Err(DeviceError::CameraTimeout {
                after: CONTROL_TIMEOUT,
            }),
            Err(NoAnswer::Gone) => Err(self.gone()),
        }
    }

    fn exposure_step_us(&self) -> u32 {
        (self.exposure.step.clamp(1, 1_000_000) as u32) * EXPOSURE_UNIT_US
    }

    fn grab(&mut self, timeout: Duration) -> Result<Frame, DeviceError> {
        let bytes = match self.call(Request::Grab, timeout) {
            Ok(Reply::Frame(Ok(b))) => b,
            Ok(Reply::Frame(Err(msg))) => return Err(self.device_err("reading a frame", msg)),
            Ok(Reply::Exposure(_)) | Err(NoAnswer::Gone) => return Err(self.gone()),
            Err(NoAnswer::TimedOut) => return Err(DeviceError::CameraTimeout { after: timeout }),
        };
        let sequence = self.next_sequence;
        self.next_sequence += 1;
        let l = &self.layout;
        Ok(Frame {
            width: l.width,
            height: l.height,
            bit_depth: l.format.bit_depth(),
            channels: l.format.channels(),
            pixels: decode::decode(l, &bytes, sequence)?,
            sequence,
            device_timestamp_us: None,
            exposure_us: None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pixel_formats_map_to_nokhwas_names_and_back() {
        for pf in PixelFormat::ALL {
            match frame_format(pf) {
                Some(ff) => assert_eq!(pixel_format(ff), Some(pf), "{pf}"),
                None => assert!(
                    matches!(pf, PixelFormat::Y16 | PixelFormat::Y10 | PixelFormat::Y12),
                    "{pf}"
                ),
            }
        }
        assert_eq!(pixel_format(FrameFormat::NV12), None);
        // The codes nokhwa asks V4L2 for are V4L2's own, except GREY's.
        for pf in [
            PixelFormat::YUYV,
            PixelFormat::MJPG,
            PixelFormat::RGB3,
            PixelFormat::BGR3,
        ] {
            assert_eq!(v4l2_code_asked(frame_format(pf).unwrap()), pf.fourcc());
        }
        assert_eq!(v4l2_code_asked(FrameFormat::GRAY), *b"GRAY");
        assert_ne!(PixelFormat::GREY.fourcc(), *b"GRAY");
    }

    #[test]
    fn control_ids_map_to_nokhwas_keys_and_back() {
        // nokhwa's Exposure is the user-class exposure, not exposure_time_absolute.
        assert_eq!(control_key(0x0098_0911), KnownCameraControl::Exposure);
        assert_eq!(
            control_key(cid::EXPOSURE_ABSOLUTE),
            KnownCameraControl::Other(cid::EXPOSURE_ABSOLUTE as u128)
        );
        assert_eq!(control_key(cid::GAIN), KnownCameraControl::Gain);
        assert_eq!(
            control_key(cid::BACKLIGHT_COMPENSATION),
            KnownCameraControl::BacklightComp
        );
        for (id, _, _) in STANDARD_CONTROLS {
            assert_eq!(control_id(control_key(id)), Some(id));
        }
        for (k, id) in KNOWN_IDS {
            assert_eq!((control_key(id), control_id(k)), (k, Some(id)));
        }
        assert_eq!(control_id(KnownCameraControl::Other(1 << 40)), None);
    }

    #[test]
    fn devices_are_indices_or_dev_video_paths() {
        assert_eq!(dev_video_index(Path::new("/dev/video0")), Some(0));
        assert_eq!(dev_video_index(Path::new("/dev/video12")), Some(12));
        for p in [
            "/dev/video",
            "/dev/videox",
            "/tmp/video0",
            "/dev/v4l/video0",
        ] {
            assert_eq!(dev_video_index(Path::new(p)), None, "{p}");
        }
        let (n, _) = camera_index("3").unwrap();
        assert_eq!(n, 3);
        assert!(camera_index("99999999999").is_err());
        if cfg!(target_os = "linux") {
            assert_eq!(camera_index(" 0 ").unwrap().1, "/dev/video0");
            let e = camera_index("/nonexistent/glint-camera")
                .unwrap_err()
                .to_string();
            assert!(e.contains("no such device"), "{e}");
            // A path that exists but is no /dev/videoN.
            let e = camera_index("/").unwrap_err().to_string();
            assert!(e.contains("only as /dev/videoN"), "{e}");
        }
    }
}
