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
use v4l::frameinterval::FrameIntervalEnum;
use v4l::framesize::FrameSizeEnum;
use v4l::v4l2::{self as raw, vidioc};
use v4l::v4l_sys as sys;
use v4l::video::Capture;
use v4l::{Device, FourCC};

use super::decode::{self, RawLayout, YcbcrParams};
use super::serial_lamp::{LampPolicy, SerialLamp};
use super::v4l2_rules::STANDARD_CONTROLS;
use super::v4l2_rules::{cid, control_name, exposure_units, EXPOSURE_MANUAL, EXPOSURE_UNIT_US};
use super::{Camera, CameraInfo, ControlReading, DeviceError, Devices, Frame};
use crate::rig::{LoadedRig, MissingControl, PixelFormat, Rig};

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
            for index in q.minimum.max(0)..=q.maximum.min(q.minimum.max(0) + 255) {
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

fn intervals(dev: &Device, code: [u8; 4], w: u32, h: u32) -> Vec<IntervalInfo> {
    let frac = |f: v4l::Fraction| (f.numerator, f.denominator);
    dev.enum_frameintervals(FourCC::new(&code), w, h)
        .unwrap_or_default()
        .into_iter()
        .map(|i| match i.interval {
            FrameIntervalEnum::Discrete(f) => IntervalInfo::Discrete {
                num: f.numerator,
                den: f.denominator,
            },
            FrameIntervalEnum::Stepwise(s) => IntervalInfo::Stepwise {
                min: frac(s.min),
                max: frac(s.max),
                step: frac(s.step),
            },
        })
        .collect()
}

/// The capture formats of a device, each with its sizes and frame intervals.
pub fn list_formats(dev: &Device) -> io::Result<Vec<FormatInfo>> {
    let mut out = Vec::new();
    for d in dev.enum_formats()? {
        let code = d.fourcc.repr;
        let mut sizes = Vec::new();
        for s in dev.enum_framesizes(d.fourcc).unwrap_or_default() {
            sizes.push(match s.size {
                FrameSizeEnum::Discrete(z) => SizeInfo {
                    width: z.width,
                    height: z.height,
                    max: None,
                    step: None,
                    intervals: intervals(dev, code, z.width, z.height),
                },
                FrameSizeEnum::Stepwise(z) => SizeInfo {
                    width: z.min_width,
                    height: z.min_height,
                    max: Some((z.max_width, z.max_height)),
                    step: Some((z.step_width, z.step_height)),
                    intervals: intervals(dev, code, z.max_width, z.max_height),
                },
            });
        }
        out.push(FormatInfo {
            fourcc: fourcc_text(code),
            code,
            description: d.description.clone(),
            compressed: d
                .flags
                .contains(v4l::format::description::Flags::COMPRESSED),
            supported: PixelFormat::from_fourcc(code).is_some(),
            sizes,
        });
    }
    Ok(out)
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
    let dev = match Device::with_path(path) {
        Ok(d) => d,
        Err(e) => {
            r.error = Some(open_hint(&e));
            return r;
        }
    };
    match dev.query_caps() {
        Ok(c) => {
            r.driver = c.driver;
            r.card = c.card;
            r.bus = c.bus;
            r.capture = c.capabilities.contains(CapFlags::VIDEO_CAPTURE)
                && c.capabilities.contains(CapFlags::STREAMING);
            r.capabilities = format!("{:?}", c.capabilities);
        }
        Err(e) => {
            r.error = Some(format!("not a V4L2 device (VIDIOC_QUERYCAP: {e})"));
            return r;
        }
    }
    if r.capture {
        match list_formats(&dev) {
            Ok(f) => r.formats = f,
            Err(e) => r.error = Some(format!("listing its formats: {e}")),
        }
    }
    match query_controls(dev.handle().fd()) {
        Ok(c) => r.controls = c,
        Err(e) => r.error = Some(format!("listing its controls: {e}")),
    }
    r
}

fn open_hint(e: &io::Error) -> String {
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
    streaming: bool,
}

// SAFETY: the mappings belong to this stream alone and are only read through `&self` /
// `&mut self`; nothing else in the process holds the pointers.
unsafe impl Send for MmapStream {}

/// A buffer taken from the driver.
struct Dequeued {
    index: usize,
    bytesused: usize,
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

    /// Ask the driver for `count` buffers and map them.
    fn new(fd: i32, count: u32) -> io::Result<MmapStream> {
        let mut req: sys::v4l2_requestbuffers = zeroed();
        req.count = count;
        req.type_ = BUF_TYPE_VIDEO_CAPTURE;
        req.memory = MEMORY_MMAP;
        xioctl(fd, vidioc::VIDIOC_REQBUFS, &mut req)?;
        // From here on, Drop gives the buffers back, whatever fails.
        let mut s = MmapStream {
            fd,
            bufs: Vec::new(),
            streaming: false,
        };
        for index in 0..req.count {
            let mut b = Self::buffer(index);
            xioctl(fd, vidioc::VIDIOC_QUERYBUF, &mut b)?;
            // SAFETY: mapping the region the driver names for this buffer; the offset is
            // the driver's cookie for it.
            let ptr = unsafe {
                raw::mmap(
                    std::ptr::null_mut(),
                    b.length as usize,
                    libc::PROT_READ | libc::PROT_WRITE,
                    libc::MAP_SHARED,
                    fd,
                    b.m.offset as libc::off_t,
                )
            }?;
            s.bufs.push(Mapping {
                ptr: ptr.cast(),
                len: b.length as usize,
            });
        }
        if s.bufs.len() < 2 {
            return Err(io::Error::other(format!(
                "the driver granted {} buffer(s) of the {count} asked for; streaming needs at least 2",
                s.bufs.len()
            )));
        }
        Ok(s)
    }

    fn queue(&mut self, index: usize) -> io::Result<()> {
        let mut b = Self::buffer(index as u32);
        xioctl(self.fd, vidioc::VIDIOC_QBUF, &mut b)
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
                    let Some(m) = self.bufs.get(index) else {
                        return Err(StreamError::Io(
                            "taking a frame from the driver (VIDIOC_DQBUF)",
                            io::Error::other(format!(
                                "the driver returned buffer {index}, which it never gave out"
                            )),
                        ));
                    };
                    // time_t and suseconds_t are 32 bits wide on some targets.
                    #[allow(clippy::unnecessary_cast)]
                    let us = b.timestamp.tv_sec as i64 * 1_000_000 + b.timestamp.tv_usec as i64;
                    return Ok(Dequeued {
                        index,
                        bytesused: (b.bytesused as usize).min(m.len),
                        flags: b.flags,
                        sequence: b.sequence,
                        timestamp_us: (us > 0).then_some(us as u64),
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

    fn data(&self, index: usize, bytesused: usize) -> &[u8] {
        let m = &self.bufs[index];
        // SAFETY: the mapping is `len` bytes long and lives as long as `self`; the driver does
        // not write a buffer until it is queued again, which needs `&mut self`.
        unsafe { std::slice::from_raw_parts(m.ptr, bytesused.min(m.len)) }
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
    device: Device,
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
        let device = Device::with_path(&path).map_err(|e| open_err(&shown, open_hint(&e)))?;
        let fd = device.handle().fd();
        let caps = device
            .query_caps()
            .map_err(|e| open_err(&shown, format!("not a V4L2 device (VIDIOC_QUERYCAP: {e})")))?;
        if !caps.capabilities.contains(CapFlags::VIDEO_CAPTURE)
            || !caps.capabilities.contains(CapFlags::STREAMING)
        {
            return Err(open_err(
                &shown,
                format!(
                    "{} ({}) is not a streaming video capture node (capabilities {:?}); a UVC camera has several /dev/video nodes and only one captures: `glint devices` shows which",
                    caps.card, caps.driver, caps.capabilities
                ),
            ));
        }

        // Format, size, frame interval: exactly as the rig says, or a refusal with the list.
        let formats = list_formats(&device)
            .map_err(|e| open_err(&shown, format!("listing its formats: {e}")))?;
        let offered = || format!("it offers:\n{}", formats_text(&formats, "    "));
        let Some(fmt) = formats.iter().find(|f| f.code == pf.fourcc()) else {
            return Err(open_err(
                &shown,
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
                &shown,
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
                        &shown,
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
                &shown,
                format!("setting the format {pf} {w}x{h} (VIDIOC_S_FMT): {e}"),
            )
        })?;
        let mut f: sys::v4l2_format = zeroed();
        f.type_ = BUF_TYPE_VIDEO_CAPTURE;
        xioctl(fd, vidioc::VIDIOC_G_FMT, &mut f).map_err(|e| {
            open_err(
                &shown,
                format!("reading the format back (VIDIOC_G_FMT): {e}"),
            )
        })?;
        // SAFETY: as above.
        let pix = unsafe { f.fmt.pix };
        let got = pix.pixelformat.to_le_bytes();
        if (got, pix.width, pix.height) != (pf.fourcc(), w, h) {
            return Err(open_err(
                &shown,
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
        if pix.bytesperline as usize >= layout.row_bytes() && pf != PixelFormat::MJPG {
            layout.bytes_per_line = pix.bytesperline;
        }
        layout.ycbcr = YcbcrParams::from_v4l2(pix.colorspace, ycbcr_enc, pix.quantization);
        let mut notes = Vec::new();

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
                        // SAFETY: as above.
                        let cap = unsafe { p.parm.capture };
                        let t = cap.timeperframe;
                        let fps = fps_of((t.numerator, t.denominator));
                        if cap.capability & CAP_TIMEPERFRAME != 0
                            && (fps - c.fps).abs() > 0.005 * c.fps
                        {
                            return Err(open_err(
                                &shown,
                                format!(
                                    "asked for {} fps, the driver set {} fps; {}",
                                    fps_text(c.fps),
                                    fps_text(fps),
                                    offered()
                                ),
                            ));
                        }
                    }
                }
                Err(e) => notes.push(format!(
                    "the frame rate could not be set to {} fps (VIDIOC_S_PARM: {e}); the camera runs at its own rate",
                    fps_text(c.fps)
                )),
            }
        }

        // Controls.
        let controls = query_controls(fd)
            .map_err(|e| open_err(&shown, format!("listing its controls: {e}")))?;
        let by_id = |id: u32| controls.iter().find(|k| k.id == id);
        let Some(exp) = by_id(cid::EXPOSURE_ABSOLUTE) else {
            return Err(open_err(
                &shown,
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
        // Park the exposure away from the bracket's first: UVC frames carry no exposure, so
        // the engine confirms each new exposure by the change it makes in the image, and a
        // first exposure equal to the parked one would show no change to confirm. The
        // longest of the bracket (or 4x the first) is two stops or more away.
        let first_us = rig.bracket.exposures_us.first().copied().unwrap_or(10_000);
        let longest_us = rig
            .bracket
            .exposures_us
            .iter()
            .copied()
            .max()
            .unwrap_or(first_us);
        let park_us = if longest_us >= first_us.saturating_mul(4) {
            longest_us
        } else {
            first_us.saturating_mul(4)
        };
        let first_units = exposure_units(park_us, exposure.min, exposure.max, exposure.step);
        let mut requested: BTreeMap<u32, i64> = BTreeMap::new();
        let note = |notes: &mut Vec<String>, msg: String| {
            tracing::warn!("{msg}");
            notes.push(msg);
        };
        for (id, value, names) in STANDARD_CONTROLS {
            let Some(k) = by_id(id) else {
                note(
                    &mut notes,
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
                        &shown,
                        format!(
                            "could not switch {} to manual exposure ({} = {EXPOSURE_MANUAL}: {e}); its menu: {}",
                            caps.card,
                            k.name,
                            k.range_text()
                        ),
                    ))
                }
                Err(e) => note(
                    &mut notes,
                    format!("could not set {} to {value}: {e}", k.name),
                ),
            }
            if id == cid::EXPOSURE_AUTO {
                // Some cameras drop the exposure when switching to manual: write it again.
                set_ctrl(fd, cid::EXPOSURE_ABSOLUTE, first_units).map_err(|e| {
                    open_err(
                        &shown,
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
                            &shown,
                            format!("{msg}; set missing_control = \"warn\" to go on without it"),
                        ))
                    }
                    MissingControl::Warn => {
                        note(&mut notes, msg);
                        continue;
                    }
                }
            };
            if k.read_only() {
                return Err(open_err(
                    &shown,
                    format!("control `{name}` (camera.controls) is read-only"),
                ));
            }
            let in_menu = k.menu.is_empty() || k.menu.iter().any(|(v, _)| *v == value);
            if value < k.min || value > k.max || !in_menu {
                return Err(open_err(
                    &shown,
                    format!(
                        "control `{name}` = {value} (camera.controls) is outside its range: {}",
                        k.range_text()
                    ),
                ));
            }
            set_ctrl(fd, k.id, value).map_err(|e| {
                open_err(
                    &shown,
                    format!("setting control `{name}` to {value} (camera.controls): {e}"),
                )
            })?;
            requested.insert(k.id, value);
        }

        // Read everything back.
        let mut readings = Vec::new();
        for k in controls.iter().filter(|k| k.readable()) {
            let Ok(value) = get_ctrl(fd, k.id) else {
                continue;
            };
            let asked = requested.get(&k.id).copied();
            if k.id == cid::EXPOSURE_AUTO && value != EXPOSURE_MANUAL {
                return Err(open_err(
                    &shown,
                    format!("{} reads back {} = {value} after being switched to manual exposure ({EXPOSURE_MANUAL}); it cannot be used for measurement", caps.card, k.name),
                ));
            }
            if let Some(a) = asked.filter(|&a| a != value) {
                note(
                    &mut notes,
                    format!("{} was set to {a} but reads back {value}", k.name),
                );
            }
            readings.push(ControlReading {
                name: k.name.clone(),
                value,
                requested: asked,
            });
        }

        let mut stream = MmapStream::new(fd, c.buffers).map_err(|e| {
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
        let fd = self.device.handle().fd();
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
        let pixels = if b.flags & BUF_FLAG_ERROR != 0 {
            Err(DeviceError::CorruptFrame {
                sequence,
                reason: "the driver flagged the buffer as damaged (V4L2_BUF_FLAG_ERROR)".into(),
            })
        } else {
            let t = thread_cpu_time();
            let p = decode::decode(
                &self.layout,
                self.stream.data(b.index, b.bytesused),
                sequence,
            );
            self.last_decode_cpu = thread_cpu_time().saturating_sub(t);
            p
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

/// The devices of a rig with a V4L2 camera and a serial lamp.
pub fn open_devices(rig: &LoadedRig) -> Result<Devices, DeviceError> {
    let r = &rig.rig;
    let camera = V4l2Camera::open(r)?;
    let port = r.lamp.port.as_deref().unwrap_or_default();
    let lamp = SerialLamp::open(port, r.lamp.baud, LampPolicy::from_rig(&r.lamp))?;
    Ok(Devices {
        camera: Box::new(camera),
        lamp: Box::new(lamp),
        operator: super::operator::for_rig(&rig.rig),
        lab: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

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
