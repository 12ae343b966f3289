//! The Video4Linux2 camera backend (cargo feature `v4l2`), and what `glint devices` reads
//! from a V4L2 device.
//!
//! Opening a camera negotiates exactly what the rig names (pixel format, size, frame
//! interval) and refuses, with the device's own list, when the device does not offer it:
//! a driver's "nearest" format would silently change the measurement. Then every automatic
//! control is switched off ([`STANDARD_CONTROLS`]), the rig's `[camera.controls]` are set by
//! name, and every control is read back into [`CameraInfo::controls`] (the session manifest).
//!
//! The `v4l` crate (0.14) provides the device handle (`Device::with_path`, which opens with
//! `O_RDWR | O_NONBLOCK`), the capability query and the enumeration of formats, frame sizes
//! and frame intervals; everything else is a plain ioctl through `v4l::v4l2::ioctl` (which
//! issues `libc::syscall(SYS_ioctl, ..)`) on the structs of `v4l::v4l_sys`:
//! `VIDIOC_S_FMT`/`G_FMT` (the crate's `Format` has no `ycbcr_enc`), `VIDIOC_S_PARM`/`G_PARM`,
//! the controls (`VIDIOC_QUERYCTRL` with `V4L2_CTRL_FLAG_NEXT_CTRL`, `VIDIOC_QUERYMENU`,
//! `VIDIOC_G_CTRL`, `VIDIOC_S_CTRL`), and streaming: Glint keeps its own small mmap stream
//! (`VIDIOC_REQBUFS`, `QUERYBUF`, `mmap`, `QBUF`, `STREAMON`, `poll`, `DQBUF`, `STREAMOFF`,
//! `munmap`) rather than the crate's, whose buffer bookkeeping does not survive a timed-out
//! or interrupted dequeue and which panics on some errors when dropped.

use std::collections::BTreeMap;
use std::io;
use std::os::raw::c_void;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use v4l::capability::Flags as CapFlags;
use v4l::v4l2::{self as raw, vidioc};
use v4l::v4l_sys as sys;

use super::decode::{self, RawLayout, YcbcrParams};
use super::v4l2_rules::STANDARD_CONTROLS;
use super::v4l2_rules::{
    cid, control_name, exposure_units, park_exposure_us, EXPOSURE_MANUAL, EXPOSURE_UNIT_US,
};
use crate::error::DeviceError;
use crate::rig::{CameraSection, MissingControl, PixelFormat, Rig};
use crate::traits::Camera;
use glint_format::image::{CameraInfo, ControlReading, Frame};

// videodev2.h numbers used below.
const BUF_TYPE_VIDEO_CAPTURE: u32 = 1;
const MEMORY_MMAP: u32 = 1;
const FIELD_ANY: u32 = 0;
const BUF_FLAG_ERROR: u32 = 0x0000_0040;
const CAP_TIMEPERFRAME: u32 = 0x1000;
const CTRL_FLAG_DISABLED: u32 = 0x0001;
const CTRL_FLAG_READ_ONLY: u32 = 0x0004;
const CTRL_FLAG_INACTIVE: u32 = 0x0010;
const CTRL_FLAG_WRITE_ONLY: u32 = 0x0040;
const CTRL_FLAG_NEXT_CTRL: u32 = 0x8000_0000;
const CTRL_TYPE_INTEGER: u32 = 1;
const CTRL_TYPE_BOOLEAN: u32 = 2;
const CTRL_TYPE_MENU: u32 = 3;
const CTRL_TYPE_BUTTON: u32 = 4;
const CTRL_TYPE_INTEGER64: u32 = 5;
const CTRL_TYPE_CTRL_CLASS: u32 = 6;
const CTRL_TYPE_STRING: u32 = 7;
const CTRL_TYPE_BITMASK: u32 = 8;
const CTRL_TYPE_INTEGER_MENU: u32 = 9;
const CAP_VIDEO_CAPTURE: u32 = 0x0000_0001;
const CAP_STREAMING: u32 = 0x0400_0000;
const CAP_DEVICE_CAPS: u32 = 0x8000_0000;
const FMT_FLAG_COMPRESSED: u32 = 0x0001;
const FRMSIZE_TYPE_DISCRETE: u32 = 1;
const FRMSIZE_TYPE_CONTINUOUS: u32 = 2;
const FRMSIZE_TYPE_STEPWISE: u32 = 3;
const FRMIVAL_TYPE_DISCRETE: u32 = 1;
const FRMIVAL_TYPE_CONTINUOUS: u32 = 2;
const FRMIVAL_TYPE_STEPWISE: u32 = 3;

// Bounds on what a driver's enumerations may list: a driver (or an imitation of one) that
// answers every index would otherwise keep Glint asking forever.
const MAX_FORMATS: u32 = 64;
const MAX_SIZES: u32 = 512;
const MAX_INTERVALS: u32 = 128;
/// The most streaming buffers Glint maps (the rig asks for at most 32).
const MAX_BUFFERS: u32 = 64;

/// An open device node, closed on drop (the `v4l` crate's handle panics when `close`
/// fails, as it can for a device unplugged mid-stream, and on a path with a NUL byte).
struct Fd(i32);

impl Fd {
    /// Open `path` as V4L2 devices are opened: read-write, non-blocking.
    fn open(path: &Path) -> io::Result<Fd> {
        use std::os::unix::ffi::OsStrExt;
        let c = std::ffi::CString::new(path.as_os_str().as_bytes()).map_err(|_| {
            io::Error::new(io::ErrorKind::InvalidInput, "the path contains a NUL byte")
        })?;
        // SAFETY: a NUL-terminated path; the descriptor returned is owned by the `Fd`.
        let fd = unsafe {
            libc::open(
                c.as_ptr(),
                libc::O_RDWR | libc::O_NONBLOCK | libc::O_CLOEXEC,
            )
        };
        if fd < 0 {
            return Err(io::Error::last_os_error());
        }
        Ok(Fd(fd))
    }
}

impl Drop for Fd {
    fn drop(&mut self) {
        // SAFETY: the descriptor this `Fd` owns, not used after this.
        if unsafe { libc::close(self.0) } != 0 {
            tracing::debug!("closing a V4L2 device: {}", io::Error::last_os_error());
        }
    }
}

/// What VIDIOC_QUERYCAP says of a device node.
#[derive(Debug, Clone, PartialEq)]
struct Caps {
    driver: String,
    card: String,
    bus: String,
    /// The node's own capabilities (`device_caps` where the driver fills it: `capabilities`
    /// is the whole device's, which a UVC camera's metadata node shares with its capture node).
    bits: u32,
}

impl Caps {
    fn from_raw(c: &sys::v4l2_capability) -> Caps {
        Caps {
            driver: c_text(&c.driver),
            card: c_text(&c.card),
            bus: c_text(&c.bus_info),
            bits: if c.capabilities & CAP_DEVICE_CAPS != 0 {
                c.device_caps
            } else {
                c.capabilities
            },
        }
    }

    fn streaming_capture(&self) -> bool {
        self.bits & CAP_VIDEO_CAPTURE != 0 && self.bits & CAP_STREAMING != 0
    }

    fn flags_text(&self) -> String {
        format!("{:?}", CapFlags::from(self.bits))
    }
}

fn query_caps(fd: i32) -> io::Result<Caps> {
    let mut c: sys::v4l2_capability = zeroed();
    xioctl(fd, vidioc::VIDIOC_QUERYCAP, &mut c)?;
    Ok(Caps::from_raw(&c))
}

/// An ioctl on `fd` with `arg`, retried when a signal interrupts it.
fn xioctl<T>(fd: i32, request: vidioc::_IOC_TYPE, arg: &mut T) -> io::Result<()> {
    loop {
        // SAFETY: `arg` is the struct `request` is defined with (videodev2.h), valid and
        // exclusively borrowed for the duration of the call.
        match unsafe { raw::ioctl(fd, request, (arg as *mut T).cast::<c_void>()) } {
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            r => return r,
        }
    }
}

fn zeroed<T>() -> T {
    // SAFETY: only used for the plain-old-data structs of videodev2.h, for which all-zero
    // bytes are a valid (and the conventional initial) value.
    unsafe { std::mem::zeroed() }
}

fn c_text(bytes: &[u8]) -> String {
    let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
    String::from_utf8_lossy(&bytes[..end]).trim().to_string()
}

fn fourcc_u32(code: [u8; 4]) -> u32 {
    u32::from_le_bytes(code)
}

fn fourcc_text(code: [u8; 4]) -> String {
    String::from_utf8_lossy(&code).trim_end().to_string()
}

// ---------------------------------------------------------------------------------------
// Describing a device: formats and controls.

/// A control as the device describes it, with its current value.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ControlInfo {
    /// The name as `v4l2-ctl` prints it, and as `[camera.controls]` takes it.
    pub name: String,
    /// The driver's own name ("Exposure Time, Absolute").
    pub label: String,
    pub id: u32,
    /// `int`, `bool`, `menu`, `intmenu`, `button`, `int64`, `bitmask`, `string`, ...
    pub kind: &'static str,
    pub min: i64,
    pub max: i64,
    pub step: i64,
    pub default: i64,
    /// The current value (none for controls that cannot be read).
    pub value: Option<i64>,
    /// `read-only`, `inactive` (another control's setting makes it ineffective), ...
    pub flags: Vec<&'static str>,
    /// A menu's items: value and label.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub menu: Vec<(i64, String)>,
}

impl ControlInfo {
    fn readable(&self) -> bool {
        matches!(self.kind, "int" | "bool" | "menu" | "intmenu" | "bitmask")
            && !self.flags.contains(&"write-only")
    }

    fn read_only(&self) -> bool {
        self.flags.contains(&"read-only")
    }

    /// `min..max` (and step), or the menu, for messages.
    pub fn range_text(&self) -> String {
        match self.kind {
            "bool" => "0 or 1".into(),
            "menu" | "intmenu" => self
                .menu
                .iter()
                .map(|(v, l)| format!("{v} = {l}"))
                .collect::<Vec<_>>()
                .join(", "),
            _ if self.step > 1 => format!("{}..{} in steps of {}", self.min, self.max, self.step),
            _ => format!("{}..{}", self.min, self.max),
        }
    }
}

fn get_ctrl(fd: i32, id: u32) -> io::Result<i64> {
    let mut c: sys::v4l2_control = zeroed();
    c.id = id;
    xioctl(fd, vidioc::VIDIOC_G_CTRL, &mut c)?;
    Ok(c.value as i64)
}

fn set_ctrl(fd: i32, id: u32, value: i64) -> io::Result<()> {
    let mut c: sys::v4l2_control = zeroed();
    c.id = id;
    c.value = value.clamp(i32::MIN as i64, i32::MAX as i64) as i32;
    xioctl(fd, vidioc::VIDIOC_S_CTRL, &mut c)
}

/// The indices to ask VIDIOC_QUERYMENU for, of a menu the driver says spans `min..=max`:
/// none below 0, at most 256, none when min > max.
fn menu_indices(min: i32, max: i32) -> std::ops::RangeInclusive<i32> {
    let first = min.max(0);
    first..=max.min(first.saturating_add(255))
}

/// Every control of the device (control classes and disabled controls left out), with
/// menus and current values.
pub fn query_controls(fd: i32) -> io::Result<Vec<ControlInfo>> {
    let mut out = Vec::new();
    let mut id = CTRL_FLAG_NEXT_CTRL;
    // A bound against drivers (or imitations of them) that never end the list.
    for _ in 0..4096 {
        let mut q: sys::v4l2_queryctrl = zeroed();
        q.id = id;
        match xioctl(fd, vidioc::VIDIOC_QUERYCTRL, &mut q) {
            Ok(()) => {}
            // EINVAL ends the list; a device without controls may not know the ioctl.
            Err(e) if e.raw_os_error() == Some(libc::EINVAL) => break,
            Err(e) if out.is_empty() && e.raw_os_error() == Some(libc::ENOTTY) => break,
            Err(e) => return Err(e),
        }
        if q.id & !CTRL_FLAG_NEXT_CTRL <= id & !CTRL_FLAG_NEXT_CTRL && id != CTRL_FLAG_NEXT_CTRL {
            break;
        }
        id = q.id | CTRL_FLAG_NEXT_CTRL;
        if q.type_ == CTRL_TYPE_CTRL_CLASS || q.flags & CTRL_FLAG_DISABLED != 0 {
            continue;
        }
        let kind = match q.type_ {
            CTRL_TYPE_INTEGER => "int",
            CTRL_TYPE_BOOLEAN => "bool",
            CTRL_TYPE_MENU => "menu",
            CTRL_TYPE_BUTTON => "button",
            CTRL_TYPE_INTEGER64 => "int64",
            CTRL_TYPE_STRING => "string",
            CTRL_TYPE_BITMASK => "bitmask",
            CTRL_TYPE_INTEGER_MENU => "intmenu",
            _ => "other",
        };
        let mut flags = Vec::new();
        for (bit, name) in [
            (CTRL_FLAG_READ_ONLY, "read-only"),
            (CTRL_FLAG_INACTIVE, "inactive"),
            (CTRL_FLAG_WRITE_ONLY, "write-only"),
        ] {
            if q.flags & bit != 0 {
                flags.push(name);
            }
        }
        let label = c_text(&q.name);
        let mut c = ControlInfo {
            name: control_name(&label),
            label,
            id: q.id,
            kind,
            min: q.minimum as i64,
            max: q.maximum as i64,
            step: q.step as i64,
            default: q.default_value as i64,
            value: None,
            flags,
            menu: Vec::new(),
        };
        if matches!(q.type_, CTRL_TYPE_MENU | CTRL_TYPE_INTEGER_MENU) {
            for index in menu_indices(q.minimum, q.maximum) {
                let mut m: sys::v4l2_querymenu = zeroed();
                m.id = q.id;
                m.index = index as u32;
                // Drivers may leave gaps in a menu (EINVAL for an index): skip them.
                if xioctl(fd, vidioc::VIDIOC_QUERYMENU, &mut m).is_ok() {
                    // SAFETY: the driver filled the union member that matches the type.
                    let item = unsafe {
                        // Copied out: the struct is packed.
                        if q.type_ == CTRL_TYPE_MENU {
                            let name = m.__bindgen_anon_1.name;
                            c_text(&name)
                        } else {
                            let value = m.__bindgen_anon_1.value;
                            value.to_string()
                        }
                    };
                    c.menu.push((index as i64, item));
                }
            }
        }
        if c.readable() {
            c.value = get_ctrl(fd, c.id).ok();
        }
        out.push(c);
    }
    Ok(out)
}

/// A frame interval the device offers (seconds a frame: `num / den`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[serde(tag = "type", rename_all = "lowercase")]
pub enum IntervalInfo {
    Discrete {
        num: u32,
        den: u32,
    },
    Stepwise {
        min: (u32, u32),
        max: (u32, u32),
        step: (u32, u32),
    },
}

fn fps_of((num, den): (u32, u32)) -> f64 {
    if num == 0 {
        0.0
    } else {
        den as f64 / num as f64
    }
}

fn fps_text(fps: f64) -> String {
    let t = format!("{fps:.3}");
    t.trim_end_matches('0').trim_end_matches('.').to_string()
}

impl IntervalInfo {
    /// Whether the interval `1/fps` is offered (to 0.5 %).
    fn offers(&self, fps: f64) -> bool {
        let close = |f: f64| (f - fps).abs() <= 0.005 * fps;
        match *self {
            IntervalInfo::Discrete { num, den } => close(fps_of((num, den))),
            IntervalInfo::Stepwise { min, max, .. } => {
                // min is the shortest interval: the highest rate.
                fps <= fps_of(min) * 1.005 && fps >= fps_of(max) * 0.995
            }
        }
    }
}

impl std::fmt::Display for IntervalInfo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            IntervalInfo::Discrete { num, den } => write!(f, "{}", fps_text(fps_of((num, den)))),
            IntervalInfo::Stepwise { min, max, .. } => {
                write!(f, "{}..{}", fps_text(fps_of(max)), fps_text(fps_of(min)))
            }
        }
    }
}

/// A frame size the device offers for a format, with its frame intervals.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SizeInfo {
    pub width: u32,
    pub height: u32,
    /// For a range of sizes: the largest, and the steps (`width x height` is the smallest).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max: Option<(u32, u32)>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub step: Option<(u32, u32)>,
    pub intervals: Vec<IntervalInfo>,
}

impl SizeInfo {
    fn offers(&self, w: u32, h: u32) -> bool {
        match (self.max, self.step) {
            (Some((mw, mh)), Some((sw, sh))) => {
                let on = |v: u32, lo: u32, hi: u32, s: u32| {
                    v >= lo && v <= hi && (v - lo).is_multiple_of(s.max(1))
                };
                on(w, self.width, mw, sw) && on(h, self.height, mh, sh)
            }
            _ => (w, h) == (self.width, self.height),
        }
    }
}

/// A pixel format the device offers, with its sizes.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct FormatInfo {
    /// The four-character code (`YUYV`, `MJPG`, ...).
    pub fourcc: String,
    #[serde(skip)]
    pub code: [u8; 4],
    pub description: String,
    pub compressed: bool,
    /// Whether Glint reads it (camera.pixel_format).
    pub supported: bool,
    pub sizes: Vec<SizeInfo>,
}

/// One answer of VIDIOC_ENUM_FRAMEINTERVALS (none for a type videodev2.h does not define).
fn interval_from(e: &sys::v4l2_frmivalenum) -> Option<IntervalInfo> {
    // SAFETY: the union member read is the one `type_` names.
    unsafe {
        match e.type_ {
            FRMIVAL_TYPE_DISCRETE => {
                let f = e.__bindgen_anon_1.discrete;
                Some(IntervalInfo::Discrete {
                    num: f.numerator,
                    den: f.denominator,
                })
            }
            FRMIVAL_TYPE_CONTINUOUS | FRMIVAL_TYPE_STEPWISE => {
                let s = e.__bindgen_anon_1.stepwise;
                let frac = |f: sys::v4l2_fract| (f.numerator, f.denominator);
                Some(IntervalInfo::Stepwise {
                    min: frac(s.min),
                    max: frac(s.max),
                    step: frac(s.step),
                })
            }
            _ => None,
        }
    }
}

/// One answer of VIDIOC_ENUM_FRAMESIZES, without its intervals (none for an unknown type).
fn size_from(e: &sys::v4l2_frmsizeenum) -> Option<SizeInfo> {
    // SAFETY: the union member read is the one `type_` names.
    unsafe {
        match e.type_ {
            FRMSIZE_TYPE_DISCRETE => {
                let z = e.__bindgen_anon_1.discrete;
                Some(SizeInfo {
                    width: z.width,
                    height: z.height,
                    max: None,
                    step: None,
                    intervals: Vec::new(),
                })
            }
            FRMSIZE_TYPE_CONTINUOUS | FRMSIZE_TYPE_STEPWISE => {
                let z = e.__bindgen_anon_1.stepwise;
                Some(SizeInfo {
                    width: z.min_width,
                    height: z.min_height,
                    max: Some((z.max_width, z.max_height)),
                    step: Some((z.step_width.max(1), z.step_height.max(1))),
                    intervals: Vec::new(),
                })
            }
            _ => None,
        }
    }
}

/// One answer of VIDIOC_ENUM_FMT, without its sizes.
fn format_from(d: &sys::v4l2_fmtdesc) -> FormatInfo {
    let code = d.pixelformat.to_le_bytes();
    FormatInfo {
        fourcc: fourcc_text(code),
        code,
        description: c_text(&d.description),
        compressed: d.flags & FMT_FLAG_COMPRESSED != 0,
        supported: PixelFormat::from_fourcc(code).is_some(),
        sizes: Vec::new(),
    }
}

/// Ask `ask(index)` for entries 0, 1, ... until the driver answers EINVAL (the end of the
/// list), at most `cap` of them: more is a driver that does not end its list (an error of
/// kind `InvalidData`).
fn enumerate<T>(
    what: &str,
    cap: u32,
    mut ask: impl FnMut(u32) -> io::Result<T>,
) -> io::Result<Vec<T>> {
    let mut out = Vec::new();
    for index in 0..=cap {
        match ask(index) {
            Ok(_) if index == cap => {
                return Err(io::Error::new(
                    io::ErrorKind::InvalidData,
                    format!("the driver lists more than {cap} {what}; it does not end the list"),
                ))
            }
            Ok(v) => out.push(v),
            Err(e) if e.raw_os_error() == Some(libc::EINVAL) => break,
            // A device that does not know the enumeration lists nothing.
            Err(e) if index == 0 && e.raw_os_error() == Some(libc::ENOTTY) => break,
            Err(e) => return Err(e),
        }
    }
    Ok(out)
}

fn intervals(fd: i32, code: [u8; 4], w: u32, h: u32) -> io::Result<Vec<IntervalInfo>> {
    let all = enumerate(
        "frame intervals (VIDIOC_ENUM_FRAMEINTERVALS)",
        MAX_INTERVALS,
        |index| {
            let mut e: sys::v4l2_frmivalenum = zeroed();
            e.index = index;
            e.pixel_format = fourcc_u32(code);
            e.width = w;
            e.height = h;
            xioctl(fd, vidioc::VIDIOC_ENUM_FRAMEINTERVALS, &mut e)?;
            Ok(interval_from(&e))
        },
    )?;
    Ok(all.into_iter().flatten().collect())
}

/// The capture formats of a device, each with its sizes and frame intervals.
fn list_formats(fd: i32) -> io::Result<Vec<FormatInfo>> {
    let mut formats = enumerate("pixel formats (VIDIOC_ENUM_FMT)", MAX_FORMATS, |index| {
        let mut d: sys::v4l2_fmtdesc = zeroed();
        d.index = index;
        d.type_ = BUF_TYPE_VIDEO_CAPTURE;
        xioctl(fd, vidioc::VIDIOC_ENUM_FMT, &mut d)?;
        Ok(format_from(&d))
    })?;
    for f in &mut formats {
        let sizes = match enumerate("frame sizes (VIDIOC_ENUM_FRAMESIZES)", MAX_SIZES, |index| {
            let mut e: sys::v4l2_frmsizeenum = zeroed();
            e.index = index;
            e.pixel_format = fourcc_u32(f.code);
            xioctl(fd, vidioc::VIDIOC_ENUM_FRAMESIZES, &mut e)?;
            Ok(size_from(&e))
        }) {
            Ok(z) => z,
            Err(e) if e.kind() == io::ErrorKind::InvalidData => {
                return Err(io::Error::other(format!("the sizes of {}: {e}", f.fourcc)))
            }
            // A driver that cannot list a format's sizes: the format is shown without them
            // (and opening it relies on VIDIOC_S_FMT's answer).
            Err(_) => Vec::new(),
        };
        for mut z in sizes.into_iter().flatten() {
            // A range's rates are listed for its largest size.
            let (w, h) = z.max.unwrap_or((z.width, z.height));
            // A driver that cannot list the rates of a size still offers the size.
            z.intervals = match intervals(fd, f.code, w, h) {
                Err(e) if e.kind() == io::ErrorKind::InvalidData => {
                    return Err(io::Error::other(format!(
                        "the rates of {} {w}x{h}: {e}",
                        f.fourcc
                    )))
                }
                r => r.unwrap_or_default(),
            };
            f.sizes.push(z);
        }
    }
    Ok(formats)
}

/// The formats as lines of text, indented by `indent`: a format a line, then its sizes
/// with their frame rates.
pub fn formats_text(formats: &[FormatInfo], indent: &str) -> String {
    let mut s = String::new();
    for f in formats {
        s += &format!(
            "{indent}{:<5} {}{}{}\n",
            f.fourcc,
            f.description,
            if f.compressed { " (compressed)" } else { "" },
            if f.supported {
                ""
            } else {
                " [Glint does not read this format]"
            }
        );
        for z in &f.sizes {
            let size = match (z.max, z.step) {
                (Some((mw, mh)), Some((sw, sh))) => format!(
                    "{}x{} to {mw}x{mh} in steps of {sw}x{sh}",
                    z.width, z.height
                ),
                _ => format!("{}x{}", z.width, z.height),
            };
            let rates: Vec<String> = z.intervals.iter().map(|i| i.to_string()).collect();
            s += &format!(
                "{indent}      {size:<12} {}\n",
                if rates.is_empty() {
                    "(frame rates not listed)".to_string()
                } else {
                    format!("{} fps", rates.join(", "))
                }
            );
        }
    }
    s
}

/// What `glint devices` shows of one V4L2 device.
#[derive(Debug, Clone, serde::Serialize)]
pub struct DeviceReport {
    pub path: PathBuf,
    /// Its stable names under /dev/v4l/by-id (filled in by the caller).
    pub by_id: Vec<PathBuf>,
    pub driver: String,
    pub card: String,
    pub bus: String,
    /// Whether it captures video by streaming (the node a camera is opened by).
    pub capture: bool,
    pub capabilities: String,
    pub formats: Vec<FormatInfo>,
    pub controls: Vec<ControlInfo>,
    /// Why it could not be read, where it could not.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// Read what a device is and offers; problems are reported in [`DeviceReport::error`].
pub fn describe(path: &Path) -> DeviceReport {
    let mut r = DeviceReport {
        path: path.to_path_buf(),
        by_id: Vec::new(),
        driver: String::new(),
        card: String::new(),
        bus: String::new(),
        capture: false,
        capabilities: String::new(),
        formats: Vec::new(),
        controls: Vec::new(),
        error: None,
    };
    let fd = match Fd::open(path) {
        Ok(d) => d,
        Err(e) => {
            r.error = Some(open_hint(path, &e));
            return r;
        }
    };
    match query_caps(fd.0) {
        Ok(c) => {
            r.capture = c.streaming_capture();
            r.capabilities = c.flags_text();
            r.driver = c.driver;
            r.card = c.card;
            r.bus = c.bus;
        }
        Err(e) => {
            r.error = Some(not_v4l2(path, &e));
            return r;
        }
    }
    let mut problems = Vec::new();
    if r.capture {
        match list_formats(fd.0) {
            Ok(f) => r.formats = f,
            Err(e) => problems.push(format!("listing its formats: {e}")),
        }
    }
    match query_controls(fd.0) {
        Ok(c) => r.controls = c,
        Err(e) => problems.push(format!("listing its controls: {e}")),
    }
    if !problems.is_empty() {
        r.error = Some(problems.join("; "));
    }
    r
}

/// What `path` is, when it is not a device node ("a directory", "a regular file", ...).
fn not_a_device(path: &Path) -> Option<&'static str> {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(path.as_os_str().as_bytes()).ok()?;
    let mut st: libc::stat = zeroed_stat();
    // SAFETY: a NUL-terminated path and a stat to fill. (libc's `stat`, not `statx`, so a
    // simulated device is seen as the device it plays.)
    if unsafe { libc::stat(c.as_ptr(), &mut st) } != 0 {
        return None;
    }
    match st.st_mode & libc::S_IFMT {
        libc::S_IFCHR => None,
        libc::S_IFDIR => Some("a directory"),
        libc::S_IFREG => Some("a regular file"),
        libc::S_IFIFO => Some("a named pipe"),
        libc::S_IFSOCK => Some("a socket"),
        libc::S_IFBLK => Some("a block device"),
        _ => Some("not a character device"),
    }
}

fn zeroed_stat() -> libc::stat {
    // SAFETY: `stat` is plain old data; all-zero bytes are a valid value.
    unsafe { std::mem::zeroed() }
}

/// Why a node that opened is not a V4L2 device (its VIDIOC_QUERYCAP failed with `e`).
fn not_v4l2(path: &Path, e: &io::Error) -> String {
    match not_a_device(path) {
        Some(what) => format!("not a V4L2 device: {what}; a camera is a /dev/video node (`glint devices` lists them)"),
        None => format!("not a V4L2 device (VIDIOC_QUERYCAP: {e}); a camera is a /dev/video node (`glint devices` lists them)"),
    }
}

fn open_hint(path: &Path, e: &io::Error) -> String {
    if let Some(what) = not_a_device(path) {
        return format!(
            "not a V4L2 device: {what}; a camera is a /dev/video node (`glint devices` lists them)"
        );
    }
    match e.raw_os_error() {
        Some(libc::ENOENT) => format!("{e}: no such device; `glint devices` lists the cameras present"),
        Some(libc::EACCES) | Some(libc::EPERM) => format!(
            "{e}: add your user to the group that owns the device (usually `video`: sudo usermod -aG video $USER, then log in again)"
        ),
        Some(libc::EBUSY) => format!("{e}: another program has the camera open"),
        _ => e.to_string(),
    }
}

// ---------------------------------------------------------------------------------------
// Streaming.

struct Mapping {
    ptr: *mut u8,
    len: usize,
}

/// The driver's buffers, mapped into this process (V4L2 memory-mapped streaming I/O).
struct MmapStream {
    fd: i32,
    bufs: Vec<Mapping>,
    /// Which buffers the driver holds (queued, not yet dequeued): a buffer is queued at
    /// most once, and read only while Glint holds it.
    queued: Vec<bool>,
    streaming: bool,
}

// SAFETY: the mappings belong to this stream alone and are only read through `&self` /
// `&mut self`; nothing else in the process holds the pointers.
unsafe impl Send for MmapStream {}

/// What the driver reported that cannot be: the reason of a [`DeviceError::CorruptFrame`]
/// or of a refused open.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
enum DriverFault {
    #[error("the driver says it filled {used} bytes of a {len}-byte buffer")]
    Overfilled { used: usize, len: usize },
    #[error("the driver's stride ({stride} bytes a row) is shorter than a row ({row} bytes)")]
    ShortStride { stride: u32, row: usize },
    #[error(
        "the driver's stride ({stride} bytes a row) makes a {rows}-row frame of {bytes} bytes"
    )]
    HugeFrame { stride: u32, rows: u32, bytes: u64 },
}

/// A buffer taken from the driver.
struct Dequeued {
    index: usize,
    /// The bytes the driver says it filled, checked against the buffer's length.
    bytesused: Result<usize, DriverFault>,
    flags: u32,
    sequence: u32,
    timestamp_us: Option<u64>,
}

enum StreamError {
    Timeout,
    Io(&'static str, io::Error),
}

impl MmapStream {
    fn buffer(index: u32) -> sys::v4l2_buffer {
        let mut b: sys::v4l2_buffer = zeroed();
        b.index = index;
        b.type_ = BUF_TYPE_VIDEO_CAPTURE;
        b.memory = MEMORY_MMAP;
        b
    }

    /// Ask the driver for `count` buffers and map them; each must hold `frame_bytes` (the
    /// fewest bytes a frame of the negotiated format takes).
    fn new(fd: i32, count: u32, frame_bytes: usize) -> io::Result<MmapStream> {
        let mut req: sys::v4l2_requestbuffers = zeroed();
        req.count = count;
        req.type_ = BUF_TYPE_VIDEO_CAPTURE;
        req.memory = MEMORY_MMAP;
        xioctl(fd, vidioc::VIDIOC_REQBUFS, &mut req)?;
        // From here on, Drop gives the buffers back, whatever fails.
        let mut s = MmapStream {
            fd,
            bufs: Vec::new(),
            queued: Vec::new(),
            streaming: false,
        };
        check_buffer_count(count, req.count)?;
        for index in 0..req.count {
            let mut b = Self::buffer(index);
            xioctl(fd, vidioc::VIDIOC_QUERYBUF, &mut b)?;
            // SAFETY: `offset` is the union member of an MMAP buffer.
            let offset = unsafe { b.m.offset };
            let len = check_buffer_length(index, b.length, frame_bytes)?;
            // SAFETY: mapping the region the driver names for this buffer; the offset is
            // the driver's cookie for it.
            let ptr = unsafe {
                raw::mmap(
                    std::ptr::null_mut(),
                    len,
                    libc::PROT_READ | libc::PROT_WRITE,
                    libc::MAP_SHARED,
                    fd,
                    offset as libc::off_t,
                )
            }
            .map_err(|e| {
                io::Error::new(
                    e.kind(),
                    format!("mapping buffer {index} of {len} bytes (mmap): {e}"),
                )
            })?;
            s.bufs.push(Mapping {
                ptr: ptr.cast(),
                len,
            });
            s.queued.push(false);
        }
        Ok(s)
    }

    fn queue(&mut self, index: usize) -> io::Result<()> {
        match self.queued.get(index) {
            None => {
                return Err(io::Error::other(format!(
                    "buffer {index} is not one of the {} mapped",
                    self.bufs.len()
                )))
            }
            // Already the driver's: queueing it twice would be refused (or worse).
            Some(true) => return Ok(()),
            Some(false) => {}
        }
        let mut b = Self::buffer(index as u32);
        xioctl(self.fd, vidioc::VIDIOC_QBUF, &mut b)?;
        self.queued[index] = true;
        Ok(())
    }

    fn start(&mut self) -> io::Result<()> {
        for i in 0..self.bufs.len() {
            self.queue(i)?;
        }
        let mut t = BUF_TYPE_VIDEO_CAPTURE as libc::c_int;
        xioctl(self.fd, vidioc::VIDIOC_STREAMON, &mut t)?;
        self.streaming = true;
        Ok(())
    }

    /// The next filled buffer, waiting at most `timeout`.
    fn dequeue(&mut self, timeout: Duration) -> Result<Dequeued, StreamError> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let ms = left.as_micros().div_ceil(1000).min(i32::MAX as u128) as i32;
            let mut pfd = libc::pollfd {
                fd: self.fd,
                events: libc::POLLIN,
                revents: 0,
            };
            // SAFETY: one valid pollfd.
            let n = unsafe { libc::poll(&mut pfd, 1, ms) };
            if n < 0 {
                let e = io::Error::last_os_error();
                if e.kind() == io::ErrorKind::Interrupted {
                    continue;
                }
                return Err(StreamError::Io("waiting for a frame (poll)", e));
            }
            if n == 0 {
                return Err(StreamError::Timeout);
            }
            let mut b = Self::buffer(0);
            match xioctl(self.fd, vidioc::VIDIOC_DQBUF, &mut b) {
                Ok(()) => {
                    let index = b.index as usize;
                    if !self.queued.get(index).copied().unwrap_or(false) {
                        return Err(StreamError::Io(
                            "taking a frame from the driver (VIDIOC_DQBUF)",
                            io::Error::other(format!(
                                "the driver returned buffer {index}, which it was not given ({} buffers, {} queued)",
                                self.bufs.len(),
                                self.queued.iter().filter(|&&q| q).count()
                            )),
                        ));
                    }
                    self.queued[index] = false;
                    let len = self.bufs[index].len;
                    return Ok(Dequeued {
                        index,
                        bytesused: check_bytesused(b.bytesused, len),
                        flags: b.flags,
                        sequence: b.sequence,
                        // time_t and suseconds_t are 32 bits wide on some targets.
                        #[allow(clippy::unnecessary_cast)]
                        timestamp_us: timestamp_us(
                            b.timestamp.tv_sec as i64,
                            b.timestamp.tv_usec as i64,
                        ),
                    });
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    if pfd.revents & (libc::POLLERR | libc::POLLHUP | libc::POLLNVAL) != 0 {
                        return Err(StreamError::Io(
                            "waiting for a frame (poll)",
                            io::Error::other("the device signals an error and has no frame"),
                        ));
                    }
                    if left.is_zero() {
                        return Err(StreamError::Timeout);
                    }
                }
                Err(e) => {
                    return Err(StreamError::Io(
                        "taking a frame from the driver (VIDIOC_DQBUF)",
                        e,
                    ))
                }
            }
        }
    }

    /// The first `bytesused` bytes of a buffer Glint holds (empty for one it does not).
    fn data(&self, index: usize, bytesused: usize) -> &[u8] {
        match (self.bufs.get(index), self.queued.get(index)) {
            // SAFETY: the mapping is `len` bytes long and lives as long as `self`; the
            // buffer is dequeued, so the driver does not write it until it is queued again,
            // which needs `&mut self`.
            (Some(m), Some(false)) => unsafe {
                std::slice::from_raw_parts(m.ptr, bytesused.min(m.len))
            },
            _ => &[],
        }
    }
}

impl Drop for MmapStream {
    fn drop(&mut self) {
        if self.streaming {
            let mut t = BUF_TYPE_VIDEO_CAPTURE as libc::c_int;
            if let Err(e) = xioctl(self.fd, vidioc::VIDIOC_STREAMOFF, &mut t) {
                tracing::debug!("VIDIOC_STREAMOFF: {e}");
            }
        }
        for m in self.bufs.drain(..) {
            // SAFETY: unmapping a mapping made in `new`, not used after this.
            if let Err(e) = unsafe { raw::munmap(m.ptr.cast(), m.len) } {
                tracing::debug!("munmap of a V4L2 buffer: {e}");
            }
        }
        let mut req: sys::v4l2_requestbuffers = zeroed();
        req.type_ = BUF_TYPE_VIDEO_CAPTURE;
        req.memory = MEMORY_MMAP;
        if let Err(e) = xioctl(self.fd, vidioc::VIDIOC_REQBUFS, &mut req) {
            tracing::debug!("VIDIOC_REQBUFS 0: {e}");
        }
    }
}

/// The buffers the driver granted (`granted`) for the `asked` of the rig: at least 2 to
/// stream, and not so many that mapping them is a driver's mistake.
fn check_buffer_count(asked: u32, granted: u32) -> io::Result<()> {
    if granted < 2 {
        return Err(io::Error::other(format!(
            "the driver granted {granted} buffer(s) of the {asked} asked for; streaming needs at least 2"
        )));
    }
    if granted > MAX_BUFFERS.max(asked) {
        return Err(io::Error::other(format!(
            "the driver granted {granted} buffers of the {asked} asked for (VIDIOC_REQBUFS); more than {} is a driver fault",
            MAX_BUFFERS.max(asked)
        )));
    }
    Ok(())
}

/// A buffer's length as VIDIOC_QUERYBUF gives it: it must hold a frame (`frame_bytes`).
fn check_buffer_length(index: u32, length: u32, frame_bytes: usize) -> io::Result<usize> {
    let len = length as usize;
    if len == 0 || len < frame_bytes {
        return Err(io::Error::other(format!(
            "the driver's buffer {index} is {len} bytes (VIDIOC_QUERYBUF), a frame of the format set needs {frame_bytes}"
        )));
    }
    Ok(len)
}

/// The bytes a dequeued buffer holds: more than the buffer's length is a driver fault.
fn check_bytesused(bytesused: u32, len: usize) -> Result<usize, DriverFault> {
    let used = bytesused as usize;
    if used > len {
        return Err(DriverFault::Overfilled { used, len });
    }
    Ok(used)
}

/// A buffer's timestamp in µs (none for zero, negative or out-of-range values).
fn timestamp_us(sec: i64, usec: i64) -> Option<u64> {
    let us = sec.checked_mul(1_000_000)?.checked_add(usec)?;
    (us > 0).then_some(us as u64)
}

// ---------------------------------------------------------------------------------------
// The camera.

/// `exposure_time_absolute`'s range, in its 100 µs units.
#[derive(Debug, Clone, Copy)]
struct ExposureRange {
    min: i64,
    max: i64,
    step: i64,
}

/// A V4L2 camera, set up for measurement and streaming.
pub struct V4l2Camera {
    // Dropped before the device: streaming off and buffers released while the fd is open.
    stream: MmapStream,
    device: Fd,
    path: String,
    layout: RawLayout,
    exposure: ExposureRange,
    info: CameraInfo,
    /// Thread CPU time the last frame's decoding took (for `glint bench v4l2`).
    last_decode_cpu: Duration,
}

/// CPU time this thread has used so far.
pub fn thread_cpu_time() -> Duration {
    let mut t = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: a valid timespec to fill; CLOCK_THREAD_CPUTIME_ID exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t) };
    Duration::new(
        t.tv_sec.max(0) as u64,
        t.tv_nsec.clamp(0, 999_999_999) as u32,
    )
}

fn open_err(path: &str, reason: impl Into<String>) -> DeviceError {
    DeviceError::Open {
        what: format!("camera {path}"),
        reason: reason.into(),
    }
}

/// What [`negotiate_format`] agreed with the driver: the frames' layout, the frame interval
/// to ask for (`num/den` s), and the formats the camera offers (for messages).
type Negotiated = (RawLayout, Option<(u32, u32)>, Vec<FormatInfo>);

/// What [`set_controls`] found and did: the camera's controls, its exposure range, and the
/// value asked of each control set (by id).
type ControlsSet = (Vec<ControlInfo>, ExposureRange, BTreeMap<u32, i64>);

/// Set the rig's pixel format and size, exactly (or a refusal with what the camera offers),
/// and read it back: the layout of its frames, and the frame interval to ask for.
fn negotiate_format(
    fd: i32,
    caps: &Caps,
    c: &CameraSection,
    pf: PixelFormat,
    shown: &str,
) -> Result<Negotiated, DeviceError> {
    // Format, size, frame interval: exactly as the rig says, or a refusal with the list.
    let formats =
        list_formats(fd).map_err(|e| open_err(shown, format!("listing its formats: {e}")))?;
    let offered = || format!("it offers:\n{}", formats_text(&formats, "    "));
    let Some(fmt) = formats.iter().find(|f| f.code == pf.fourcc()) else {
        return Err(open_err(
            shown,
            format!(
                "{} does not deliver pixel format {pf}; {}",
                caps.card,
                offered()
            ),
        ));
    };
    let (w, h) = (c.width, c.height);
    let size = fmt.sizes.iter().find(|z| z.offers(w, h));
    if size.is_none() && !fmt.sizes.is_empty() {
        return Err(open_err(
            shown,
            format!(
                "{} does not deliver {pf} at {w}x{h}; {}",
                caps.card,
                offered()
            ),
        ));
    }
    let interval = match size.map(|z| &z.intervals) {
        Some(ivs) if !ivs.is_empty() => match ivs.iter().find(|i| i.offers(c.fps)) {
            Some(IntervalInfo::Discrete { num, den }) => Some((*num, *den)),
            Some(IntervalInfo::Stepwise { .. }) => Some(fraction_of_fps(c.fps)),
            None => {
                return Err(open_err(
                    shown,
                    format!(
                        "{} does not deliver {pf} {w}x{h} at {} fps (camera.fps); {}",
                        caps.card,
                        fps_text(c.fps),
                        offered()
                    ),
                ))
            }
        },
        _ => Some(fraction_of_fps(c.fps)),
    };

    let mut f: sys::v4l2_format = zeroed();
    f.type_ = BUF_TYPE_VIDEO_CAPTURE;
    let mut want: sys::v4l2_pix_format = zeroed();
    want.width = w;
    want.height = h;
    want.pixelformat = fourcc_u32(pf.fourcc());
    want.field = FIELD_ANY;
    // `pix` is the union member of a single-planar capture format.
    f.fmt.pix = want;
    xioctl(fd, vidioc::VIDIOC_S_FMT, &mut f).map_err(|e| {
        open_err(
            shown,
            format!("setting the format {pf} {w}x{h} (VIDIOC_S_FMT): {e}"),
        )
    })?;
    let mut f: sys::v4l2_format = zeroed();
    f.type_ = BUF_TYPE_VIDEO_CAPTURE;
    xioctl(fd, vidioc::VIDIOC_G_FMT, &mut f).map_err(|e| {
        open_err(
            shown,
            format!("reading the format back (VIDIOC_G_FMT): {e}"),
        )
    })?;
    // SAFETY: as above.
    let pix = unsafe { f.fmt.pix };
    let got = pix.pixelformat.to_le_bytes();
    if (got, pix.width, pix.height) != (pf.fourcc(), w, h) {
        return Err(open_err(
            shown,
            format!(
                "asked for {pf} {w}x{h}, the driver set {} {}x{}; {}",
                fourcc_text(got),
                pix.width,
                pix.height,
                offered()
            ),
        ));
    }
    // SAFETY: `ycbcr_enc` is the member for Y'CbCr formats (hsv_enc shares its bytes).
    let ycbcr_enc = unsafe { pix.__bindgen_anon_1.ycbcr_enc };
    let mut layout = RawLayout::packed(pf, w, h);
    if pf != PixelFormat::MJPG {
        layout.bytes_per_line = stride_of(pix.bytesperline, &layout)
            .map_err(|e| open_err(shown, format!("{e} (VIDIOC_G_FMT for {pf} {w}x{h})")))?;
    }
    layout.ycbcr = YcbcrParams::from_v4l2(pix.colorspace, ycbcr_enc, pix.quantization);
    Ok((layout, interval, formats))
}

/// Ask for the rig's frame interval: a driver that sets another rate is refused, one that
/// cannot set it is noted (the camera runs at its own rate).
fn set_frame_rate(
    fd: i32,
    interval: Option<(u32, u32)>,
    asked_fps: f64,
    offered: &dyn Fn() -> String,
    shown: &str,
    notes: &mut Vec<String>,
) -> Result<(), DeviceError> {
    if let Some((num, den)) = interval {
        let mut p: sys::v4l2_streamparm = zeroed();
        p.type_ = BUF_TYPE_VIDEO_CAPTURE;
        let mut cap: sys::v4l2_captureparm = zeroed();
        cap.timeperframe.numerator = num;
        cap.timeperframe.denominator = den;
        // `capture` is the union member for capture streams.
        p.parm.capture = cap;
        match xioctl(fd, vidioc::VIDIOC_S_PARM, &mut p) {
            Ok(()) => {
                let mut p: sys::v4l2_streamparm = zeroed();
                p.type_ = BUF_TYPE_VIDEO_CAPTURE;
                if xioctl(fd, vidioc::VIDIOC_G_PARM, &mut p).is_ok() {
                    // SAFETY: `capture` is the union member for capture streams.
                    let cap = unsafe { p.parm.capture };
                    let t = cap.timeperframe;
                    let fps = fps_of((t.numerator, t.denominator));
                    if cap.capability & CAP_TIMEPERFRAME != 0
                        && (fps - asked_fps).abs() > 0.005 * asked_fps
                    {
                        return Err(open_err(
                            shown,
                            format!(
                                "asked for {} fps, the driver set {} fps; {}",
                                fps_text(asked_fps),
                                fps_text(fps),
                                offered()
                            ),
                        ));
                    }
                }
            }
            Err(e) => notes.push(format!(
                "the frame rate could not be set to {} fps (VIDIOC_S_PARM: {e}); the camera runs at its own rate",
                fps_text(asked_fps)
            )),
        }
    }
    Ok(())
}

/// Switch the camera's automatic controls off ([`STANDARD_CONTROLS`], the exposure parked
/// away from the bracket's first) and set `[camera.controls]`: the camera's controls, its
/// exposure range and the values asked for.
fn set_controls(
    fd: i32,
    rig: &Rig,
    caps: &Caps,
    shown: &str,
    notes: &mut Vec<String>,
) -> Result<ControlsSet, DeviceError> {
    let c = &rig.camera;
    let controls =
        query_controls(fd).map_err(|e| open_err(shown, format!("listing its controls: {e}")))?;
    let by_id = |id: u32| controls.iter().find(|k| k.id == id);
    let Some(exp) = by_id(cid::EXPOSURE_ABSOLUTE) else {
        return Err(open_err(
            shown,
            format!(
                "{} has no exposure_time_absolute control, so Glint cannot set its exposures; its controls are: {}",
                caps.card,
                control_names(&controls)
            ),
        ));
    };
    let exposure = ExposureRange {
        min: exp.min,
        max: exp.max,
        step: exp.step.max(1),
    };
    // Park the exposure away from the bracket's first (see `park_exposure_us`).
    let park_us = park_exposure_us(rig);
    let first_units = exposure_units(park_us, exposure.min, exposure.max, exposure.step);
    let mut requested: BTreeMap<u32, i64> = BTreeMap::new();
    let note = |notes: &mut Vec<String>, msg: String| {
        tracing::warn!("{msg}");
        notes.push(msg);
    };
    for (id, value, names) in STANDARD_CONTROLS {
        let Some(k) = by_id(id) else {
            note(
                notes,
                format!(
                    "{} has no {} control; it was left as it is",
                    caps.card,
                    names.join(" / ")
                ),
            );
            continue;
        };
        match set_ctrl(fd, id, value) {
            Ok(()) => {
                requested.insert(id, value);
            }
            Err(e) if id == cid::EXPOSURE_AUTO => {
                return Err(open_err(
                    shown,
                    format!(
                        "could not switch {} to manual exposure ({} = {EXPOSURE_MANUAL}: {e}); its menu: {}",
                        caps.card,
                        k.name,
                        k.range_text()
                    ),
                ))
            }
            Err(e) => note(
                notes,
                format!("could not set {} to {value}: {e}", k.name),
            ),
        }
        if id == cid::EXPOSURE_AUTO {
            // Some cameras drop the exposure when switching to manual: write it again.
            set_ctrl(fd, cid::EXPOSURE_ABSOLUTE, first_units).map_err(|e| {
                open_err(
                    shown,
                    format!("setting exposure_time_absolute to {first_units}: {e}"),
                )
            })?;
            requested.insert(cid::EXPOSURE_ABSOLUTE, first_units);
        }
    }
    for (name, &value) in &c.controls {
        let Some(k) = controls.iter().find(|k| &k.name == name) else {
            let msg = format!(
                "{} has no control `{name}` (camera.controls); its controls are: {}",
                caps.card,
                control_names(&controls)
            );
            match c.missing_control {
                MissingControl::Error => {
                    return Err(open_err(
                        shown,
                        format!("{msg}; set missing_control = \"warn\" to go on without it"),
                    ))
                }
                MissingControl::Warn => {
                    note(notes, msg);
                    continue;
                }
            }
        };
        if k.read_only() {
            return Err(open_err(
                shown,
                format!("control `{name}` (camera.controls) is read-only"),
            ));
        }
        let in_menu = k.menu.is_empty() || k.menu.iter().any(|(v, _)| *v == value);
        if value < k.min || value > k.max || !in_menu {
            return Err(open_err(
                shown,
                format!(
                    "control `{name}` = {value} (camera.controls) is outside its range: {}",
                    k.range_text()
                ),
            ));
        }
        set_ctrl(fd, k.id, value).map_err(|e| {
            open_err(
                shown,
                format!("setting control `{name}` to {value} (camera.controls): {e}"),
            )
        })?;
        requested.insert(k.id, value);
    }

    Ok((controls, exposure, requested))
}

/// Every readable control read back: a camera that is not in manual exposure is refused;
/// a value other than the one asked for is noted.
fn read_back(
    fd: i32,
    caps: &Caps,
    controls: &[ControlInfo],
    requested: &BTreeMap<u32, i64>,
    shown: &str,
    notes: &mut Vec<String>,
) -> Result<Vec<ControlReading>, DeviceError> {
    let note = |notes: &mut Vec<String>, msg: String| {
        tracing::warn!("{msg}");
        notes.push(msg);
    };
    let mut readings = Vec::new();
    for k in controls.iter().filter(|k| k.readable()) {
        let Ok(value) = get_ctrl(fd, k.id) else {
            continue;
        };
        let asked = requested.get(&k.id).copied();
        if k.id == cid::EXPOSURE_AUTO && value != EXPOSURE_MANUAL {
            return Err(open_err(
                shown,
                format!("{} reads back {} = {value} after being switched to manual exposure ({EXPOSURE_MANUAL}); it cannot be used for measurement", caps.card, k.name),
            ));
        }
        if let Some(a) = asked.filter(|&a| a != value) {
            note(
                notes,
                format!("{} was set to {a} but reads back {value}", k.name),
            );
        }
        readings.push(ControlReading {
            name: k.name.clone(),
            value,
            requested: asked,
        });
    }

    Ok(readings)
}

impl V4l2Camera {
    /// Open the rig's camera (`camera.device`: a /dev/video node or a /dev/v4l/by-id link),
    /// negotiate its format, switch its automatic controls off, set `[camera.controls]`,
    /// read every control back, and start streaming.
    pub fn open(rig: &Rig) -> Result<V4l2Camera, DeviceError> {
        let c = &rig.camera;
        let path = c.device.clone().unwrap_or_default();
        let shown = match std::fs::canonicalize(&path) {
            Ok(real) if real != Path::new(&path) => format!("{path} ({})", real.display()),
            _ => path.clone(),
        };
        let Some(pf) = c.pixel_format else {
            return Err(open_err(
                &shown,
                "camera.pixel_format is not set; `glint devices` lists what the camera offers",
            ));
        };
        if pf.lossy() && !c.allow_lossy {
            return Err(open_err(
                &shown,
                format!("{pf} is lossy and processed in the camera; set camera.allow_lossy = true to accept it, or choose YUYV, GREY or Y16"),
            ));
        }
        let device = Fd::open(Path::new(&path))
            .map_err(|e| open_err(&shown, open_hint(Path::new(&path), &e)))?;
        let fd = device.0;
        let caps = query_caps(fd).map_err(|e| open_err(&shown, not_v4l2(Path::new(&path), &e)))?;
        if !caps.streaming_capture() {
            return Err(open_err(
                &shown,
                format!(
                    "{} ({}) is not a streaming video capture node (capabilities {:?}); a UVC camera has several /dev/video nodes and only one captures: `glint devices` shows which",
                    caps.card,
                    caps.driver,
                    caps.flags_text()
                ),
            ));
        }

        // Format, size, frame interval: exactly as the rig says, or a refusal with the list.
        let (layout, interval, formats) = negotiate_format(fd, &caps, c, pf, &shown)?;
        let (w, h) = (c.width, c.height);
        let offered = || format!("it offers:\n{}", formats_text(&formats, "    "));
        let mut notes = Vec::new();
        set_frame_rate(fd, interval, c.fps, &offered, &shown, &mut notes)?;
        let (controls, exposure, requested) = set_controls(fd, rig, &caps, &shown, &mut notes)?;
        let readings = read_back(fd, &caps, &controls, &requested, &shown, &mut notes)?;

        let mut stream = MmapStream::new(fd, c.buffers, layout.min_bytes()).map_err(|e| {
            open_err(
                &shown,
                format!("setting up {} streaming buffers: {e}", c.buffers),
            )
        })?;
        stream
            .start()
            .map_err(|e| open_err(&shown, format!("starting to stream (VIDIOC_STREAMON): {e}")))?;

        let info = CameraInfo {
            backend: Some("v4l2".into()),
            device: Some(format!(
                "{} / {} / {} at {shown}",
                caps.driver, caps.card, caps.bus
            )),
            pixel_format: Some(pf.name().to_string()),
            ycbcr_encoding: (pf == PixelFormat::YUYV).then(|| layout.ycbcr.to_string()),
            lossy: pf.lossy(),
            controls: readings,
            notes,
            ..CameraInfo::basic(caps.card.clone(), w, h, pf.bit_depth(), pf.channels())
        };
        tracing::info!(
            "opened {shown}: {} {pf} {w}x{h}, exposure_time_absolute {}..{} step {}",
            caps.card,
            exposure.min,
            exposure.max,
            exposure.step
        );
        Ok(V4l2Camera {
            stream,
            device,
            path: shown,
            layout,
            exposure,
            info,
            last_decode_cpu: Duration::ZERO,
        })
    }

    /// The thread CPU time the last [`Camera::grab`] spent decoding its frame.
    pub fn last_decode_cpu(&self) -> Duration {
        self.last_decode_cpu
    }

    /// An error of a stream operation: a vanished device (ENODEV, EIO, ENXIO) is
    /// [`DeviceError::Unplugged`].
    fn stream_err(&self, op: &str, e: io::Error) -> DeviceError {
        match e.raw_os_error() {
            Some(libc::ENODEV) | Some(libc::EIO) | Some(libc::ENXIO) => DeviceError::Unplugged {
                device: format!("camera {}", self.path),
            },
            _ => DeviceError::Io {
                op: format!("{op} on camera {}", self.path),
                source: e,
            },
        }
    }

    /// An error of a control: only ENODEV means the device is gone (UVC cameras answer EIO
    /// for controls they refuse).
    fn control_err(&self, op: String, e: io::Error) -> DeviceError {
        match e.raw_os_error() {
            Some(libc::ENODEV) => DeviceError::Unplugged {
                device: format!("camera {}", self.path),
            },
            _ => DeviceError::Io {
                op: format!("{op} on camera {}", self.path),
                source: e,
            },
        }
    }
}

/// The stride (bytes a row) to read frames with, from the driver's `bytesperline`: 0 (some
/// drivers) means packed rows; a stride shorter than a row, or one that makes a frame
/// larger than 4 GiB, is a driver fault.
fn stride_of(bytesperline: u32, packed: &RawLayout) -> Result<u32, DriverFault> {
    let row = packed.row_bytes();
    if bytesperline == 0 {
        return Ok(packed.bytes_per_line);
    }
    if (bytesperline as usize) < row {
        return Err(DriverFault::ShortStride {
            stride: bytesperline,
            row,
        });
    }
    let frame = (packed.height as u64).saturating_mul(bytesperline as u64);
    if frame > u32::MAX as u64 {
        return Err(DriverFault::HugeFrame {
            stride: bytesperline,
            rows: packed.height,
            bytes: frame,
        });
    }
    Ok(bytesperline)
}

/// `1/fps` as a fraction (to a thousandth of a frame per second).
fn fraction_of_fps(fps: f64) -> (u32, u32) {
    let den = (fps * 1000.0).round().max(1.0) as u32;
    let (mut a, mut b) = (1000u32, den);
    while b != 0 {
        (a, b) = (b, a % b);
    }
    (1000 / a, den / a)
}

fn control_names(controls: &[ControlInfo]) -> String {
    controls
        .iter()
        .map(|k| k.name.as_str())
        .collect::<Vec<_>>()
        .join(", ")
}

impl Camera for V4l2Camera {
    fn info(&self) -> CameraInfo {
        self.info.clone()
    }

    fn set_exposure(&mut self, us: u32) -> Result<u32, DeviceError> {
        let fd = self.device.0;
        let e = self.exposure;
        let units = exposure_units(us, e.min, e.max, e.step);
        set_ctrl(fd, cid::EXPOSURE_ABSOLUTE, units).map_err(|err| {
            self.control_err(
                format!(
                    "setting exposure_time_absolute to {units} ({} µs)",
                    units * EXPOSURE_UNIT_US as i64
                ),
                err,
            )
        })?;
        let back = get_ctrl(fd, cid::EXPOSURE_ABSOLUTE)
            .map_err(|err| self.control_err("reading exposure_time_absolute back".into(), err))?;
        Ok((back.clamp(0, (u32::MAX / EXPOSURE_UNIT_US) as i64) as u32) * EXPOSURE_UNIT_US)
    }

    fn exposure_step_us(&self) -> u32 {
        (self.exposure.step.clamp(1, 1_000_000) as u32) * EXPOSURE_UNIT_US
    }

    fn grab(&mut self, timeout: Duration) -> Result<Frame, DeviceError> {
        let b = match self.stream.dequeue(timeout) {
            Ok(b) => b,
            Err(StreamError::Timeout) => return Err(DeviceError::CameraTimeout { after: timeout }),
            Err(StreamError::Io(op, e)) => return Err(self.stream_err(op, e)),
        };
        let sequence = b.sequence as u64;
        let pixels = match b.bytesused {
            _ if b.flags & BUF_FLAG_ERROR != 0 => Err(DeviceError::CorruptFrame {
                sequence,
                reason: "the driver flagged the buffer as damaged (V4L2_BUF_FLAG_ERROR)".into(),
            }),
            Err(fault) => Err(DeviceError::CorruptFrame {
                sequence,
                reason: fault.to_string(),
            }),
            Ok(used) => {
                let t = thread_cpu_time();
                let p = decode::decode(&self.layout, self.stream.data(b.index, used), sequence);
                self.last_decode_cpu = thread_cpu_time().saturating_sub(t);
                p
            }
        };
        // The buffer goes back to the driver whatever became of its contents.
        if let Err(e) = self.stream.queue(b.index) {
            return Err(self.stream_err("giving a buffer back to the driver (VIDIOC_QBUF)", e));
        }
        Ok(Frame {
            width: self.layout.width,
            height: self.layout.height,
            bit_depth: self.layout.format.bit_depth(),
            channels: self.layout.format.channels(),
            pixels: pixels?,
            sequence,
            device_timestamp_us: b.timestamp_us,
            exposure_us: None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn driver_strings_without_nul_or_utf8_are_read_safely() {
        let mut c: sys::v4l2_capability = zeroed();
        c.driver = [b'x'; 16]; // no NUL at all
        c.card[..4].copy_from_slice(&[b'C', 0xff, 0xfe, 0]);
        c.card[5..9].copy_from_slice(&[0xc3, 0x28, 0xa0, 0xa1]); // garbage after the NUL
        c.bus_info = [0xff; 32];
        c.capabilities = CAP_DEVICE_CAPS | CAP_VIDEO_CAPTURE | CAP_STREAMING;
        c.device_caps = 0x0080_0000 | CAP_STREAMING; // a metadata node
        let k = Caps::from_raw(&c);
        assert_eq!(k.driver, "x".repeat(16));
        assert!(k.card.starts_with('C'));
        assert!(
            !k.streaming_capture(),
            "device_caps, not the whole device's, decide"
        );
        c.capabilities = CAP_VIDEO_CAPTURE | CAP_STREAMING; // an old driver: no device_caps
        assert!(Caps::from_raw(&c).streaming_capture());
        let mut d: sys::v4l2_fmtdesc = zeroed();
        d.description = [0x80; 32];
        d.pixelformat = u32::from_le_bytes(*b"YUYV");
        d.flags = FMT_FLAG_COMPRESSED;
        let f = format_from(&d);
        assert_eq!(
            (f.fourcc.as_str(), f.compressed, f.supported),
            ("YUYV", true, true)
        );
        d.pixelformat = u32::from_le_bytes([0xff, 0, 0xfe, 1]);
        assert!(!format_from(&d).supported);
    }

    #[test]
    fn unknown_or_degenerate_sizes_and_intervals_do_not_panic() {
        let mut e: sys::v4l2_frmsizeenum = zeroed();
        e.type_ = 99;
        assert!(size_from(&e).is_none());
        e.type_ = FRMSIZE_TYPE_STEPWISE;
        // Writing a union's member is safe; size_from reads it back.
        e.__bindgen_anon_1.stepwise.min_width = 640;
        e.__bindgen_anon_1.stepwise.max_width = 16; // min > max
        e.__bindgen_anon_1.stepwise.min_height = 16;
        e.__bindgen_anon_1.stepwise.max_height = u32::MAX;
        let z = size_from(&e).unwrap();
        assert_eq!(z.step, Some((1, 1)), "a zero step is read as 1");
        assert!(!z.offers(320, 240) && !z.offers(640, 16));
        let mut i: sys::v4l2_frmivalenum = zeroed();
        i.type_ = 7;
        assert!(interval_from(&i).is_none());
        i.type_ = FRMIVAL_TYPE_DISCRETE; // 0/0
        let d = interval_from(&i).unwrap();
        assert_eq!(d.to_string(), "0");
        assert!(!d.offers(30.0));
        i.type_ = FRMIVAL_TYPE_CONTINUOUS;
        let s = interval_from(&i).unwrap();
        assert!(!s.offers(30.0));
        assert!(formats_text(
            &[FormatInfo {
                fourcc: "????".into(),
                code: [0; 4],
                description: String::new(),
                compressed: false,
                supported: false,
                sizes: vec![z],
            }],
            ""
        )
        .contains("640x16 to 16x4294967295"));
    }

    #[test]
    fn enumerations_end_at_einval_and_are_capped() {
        let einval = || io::Error::from_raw_os_error(libc::EINVAL);
        let three = enumerate("things", 8, |i| if i < 3 { Ok(i) } else { Err(einval()) });
        assert_eq!(three.unwrap(), vec![0, 1, 2]);
        let exactly = enumerate("things", 3, |i| if i < 3 { Ok(i) } else { Err(einval()) });
        assert_eq!(exactly.unwrap().len(), 3);
        let forever = enumerate("things (VIDIOC_ENUM_FMT)", 8, Ok).unwrap_err();
        assert_eq!(forever.kind(), io::ErrorKind::InvalidData);
        assert!(
            forever.to_string().contains("more than 8 things"),
            "{forever}"
        );
        let none = enumerate("things", 8, |_| -> io::Result<u32> {
            Err(io::Error::from_raw_os_error(libc::ENOTTY))
        });
        assert!(none.unwrap().is_empty());
        let gone = enumerate("things", 8, |i| {
            if i < 2 {
                Ok(i)
            } else {
                Err(io::Error::from_raw_os_error(libc::ENODEV))
            }
        });
        assert!(gone.is_err());
    }

    #[test]
    fn menus_of_any_claimed_range_are_bounded() {
        assert_eq!(menu_indices(0, 3), 0..=3);
        assert!(menu_indices(5, 2).is_empty());
        assert_eq!(menu_indices(-10, 1), 0..=1);
        assert_eq!(menu_indices(0, i32::MAX).count(), 256);
        assert_eq!(menu_indices(i32::MAX - 1, i32::MAX).count(), 2);
        assert_eq!(menu_indices(i32::MAX, i32::MAX).count(), 1);
    }

    #[test]
    fn streaming_replies_are_checked() {
        assert!(check_buffer_count(4, 4).is_ok());
        assert!(check_buffer_count(4, 1).is_err());
        assert!(check_buffer_count(4, 0).is_err());
        assert!(check_buffer_count(4, 64).is_ok());
        assert!(check_buffer_count(4, u32::MAX).is_err());
        assert_eq!(check_buffer_length(0, 1000, 800).unwrap(), 1000);
        assert!(check_buffer_length(0, 0, 0).is_err());
        let short = check_buffer_length(1, 100, 153_600).unwrap_err();
        assert!(
            short.to_string().contains("buffer 1 is 100 bytes"),
            "{short}"
        );
        assert_eq!(check_bytesused(10, 10), Ok(10));
        assert!(check_bytesused(u32::MAX, 10)
            .unwrap_err()
            .to_string()
            .contains("filled 4294967295 bytes of a 10-byte buffer"));
        assert_eq!(timestamp_us(1, 5), Some(1_000_005));
        assert_eq!(timestamp_us(0, 0), None);
        assert_eq!(timestamp_us(-5, 0), None);
        assert_eq!(timestamp_us(i64::MAX, 0), None);
        assert_eq!(timestamp_us(i64::MAX / 1_000_000, i64::MAX), None);
    }

    #[test]
    fn strides_from_the_driver_are_checked() {
        let packed = RawLayout::packed(PixelFormat::YUYV, 320, 240);
        assert_eq!(stride_of(0, &packed), Ok(640));
        assert_eq!(stride_of(640, &packed), Ok(640));
        assert_eq!(stride_of(704, &packed), Ok(704));
        assert!(stride_of(639, &packed)
            .unwrap_err()
            .to_string()
            .contains("shorter than a row"));
        assert!(stride_of(u32::MAX, &packed).is_err());
        let mut l = packed;
        l.bytes_per_line = stride_of(u32::MAX / 240, &packed).unwrap();
        assert!(l.min_bytes() <= u32::MAX as usize);
    }

    #[test]
    fn fps_fractions_are_reduced() {
        assert_eq!(fraction_of_fps(30.0), (1, 30));
        assert_eq!(fraction_of_fps(7.5), (2, 15));
        assert_eq!(fraction_of_fps(29.97), (100, 2997));
    }

    #[test]
    fn sizes_and_intervals_match_what_the_rig_asks() {
        let z = SizeInfo {
            width: 16,
            height: 16,
            max: Some((4096, 2160)),
            step: Some((16, 8)),
            intervals: vec![],
        };
        assert!(z.offers(1920, 1080));
        assert!(!z.offers(1921, 1080));
        let i = IntervalInfo::Discrete { num: 1, den: 30 };
        assert!(i.offers(30.0) && !i.offers(25.0));
        let s = IntervalInfo::Stepwise {
            min: (1, 60),
            max: (1, 1),
            step: (1, 1),
        };
        assert!(s.offers(25.0) && !s.offers(120.0));
        assert_eq!(i.to_string(), "30");
        assert_eq!(
            IntervalInfo::Discrete { num: 2, den: 15 }.to_string(),
            "7.5"
        );
    }
}
