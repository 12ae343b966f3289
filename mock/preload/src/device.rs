//! What the simulated device answers: the V4L2 ioctls of a UVC webcam, one open file at a
//! time.
//!
//! The device's state that outlives a file (format, frame interval, control values, who
//! streams) lives in the launcher, so that several programs, or several opens, see one
//! camera as they would see one driver; this side keeps what belongs to the open file (its
//! buffers, its queue, whether it streams) and knows the ABI. Every ioctl starts by reading
//! the device's state, which also tells a yanked camera (ENODEV) as the kernel does.

use std::collections::{HashMap, VecDeque};
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};

use libc::{c_int, c_void};

use crate::abi::*;
use crate::link::Link;

/// One control of the simulated camera, as uvcvideo describes it.
struct CtrlDef {
    id: u32,
    name: &'static str,
    type_: u32,
    min: i64,
    max: i64,
    step: u64,
    def: i64,
    /// The automatic control this one depends on, and its value that means "manual".
    master: Option<(u32, i64)>,
}

const fn ctrl(id: u32, name: &'static str, type_: u32, min: i64, max: i64, def: i64) -> CtrlDef {
    CtrlDef {
        id,
        name,
        type_,
        min,
        max,
        step: if type_ == CTRL_TYPE_CTRL_CLASS { 0 } else { 1 },
        def,
        master: None,
    }
}

const fn slave(mut c: CtrlDef, master: u32, manual: i64) -> CtrlDef {
    c.master = Some((master, manual));
    c
}

/// The controls, sorted by id (the order `V4L2_CTRL_FLAG_NEXT_CTRL` walks).
const CTRLS: &[CtrlDef] = &[
    ctrl(
        CID_USER_CLASS,
        "User Controls",
        CTRL_TYPE_CTRL_CLASS,
        0,
        0,
        0,
    ),
    ctrl(CID_BRIGHTNESS, "Brightness", CTRL_TYPE_INTEGER, -64, 64, 0),
    ctrl(CID_CONTRAST, "Contrast", CTRL_TYPE_INTEGER, 0, 100, 50),
    ctrl(
        CID_AUTO_WHITE_BALANCE,
        "White Balance, Automatic",
        CTRL_TYPE_BOOLEAN,
        0,
        1,
        1,
    ),
    ctrl(CID_AUTOGAIN, "Gain, Automatic", CTRL_TYPE_BOOLEAN, 0, 1, 1),
    slave(
        ctrl(CID_GAIN, "Gain", CTRL_TYPE_INTEGER, 0, 255, 0),
        CID_AUTOGAIN,
        0,
    ),
    slave(
        CtrlDef {
            step: 10,
            ..ctrl(
                CID_WHITE_BALANCE_TEMPERATURE,
                "White Balance Temperature",
                CTRL_TYPE_INTEGER,
                2800,
                6500,
                4600,
            )
        },
        CID_AUTO_WHITE_BALANCE,
        0,
    ),
    ctrl(
        CID_BACKLIGHT_COMPENSATION,
        "Backlight Compensation",
        CTRL_TYPE_INTEGER,
        0,
        2,
        1,
    ),
    ctrl(
        CID_CAMERA_CLASS,
        "Camera Controls",
        CTRL_TYPE_CTRL_CLASS,
        0,
        0,
        0,
    ),
    ctrl(CID_EXPOSURE_AUTO, "Auto Exposure", CTRL_TYPE_MENU, 0, 3, 3),
    slave(
        ctrl(
            CID_EXPOSURE_ABSOLUTE,
            "Exposure Time, Absolute",
            CTRL_TYPE_INTEGER,
            1,
            10_000,
            100,
        ),
        CID_EXPOSURE_AUTO,
        1,
    ),
    ctrl(
        CID_EXPOSURE_AUTO_PRIORITY,
        "Exposure, Dynamic Framerate",
        CTRL_TYPE_BOOLEAN,
        0,
        1,
        1,
    ),
];

/// The items of the exposure menu a UVC camera offers (0 and 2 are not: QUERYMENU EINVAL).
fn menu_item(id: u32, index: i64) -> Option<&'static str> {
    match (id, index) {
        (CID_EXPOSURE_AUTO, 1) => Some("Manual Mode"),
        (CID_EXPOSURE_AUTO, 3) => Some("Aperture Priority Mode"),
        _ => None,
    }
}

fn find_ctrl(id: u32) -> Option<&'static CtrlDef> {
    CTRLS.iter().find(|c| c.id == id)
}

/// The control a query names: `id` itself, or with `NEXT_CTRL` the first after it.
fn query_target(raw: u32) -> Option<&'static CtrlDef> {
    let id = raw & CTRL_ID_MASK;
    if raw & CTRL_FLAG_NEXT_CTRL != 0 {
        CTRLS.iter().find(|c| c.id > id)
    } else if raw & CTRL_FLAG_NEXT_COMPOUND != 0 {
        None // no compound controls
    } else {
        find_ctrl(id)
    }
}

/// Formats, with their description and whether they are compressed.
fn describe(code: u32) -> (&'static str, u32) {
    match &code.to_le_bytes() {
        b"GREY" => ("8-bit Greyscale", 0),
        b"Y16 " => ("16-bit Greyscale", 0),
        b"Y10 " => ("10-bit Greyscale", 0),
        b"Y12 " => ("12-bit Greyscale", 0),
        b"YUYV" => ("YUYV 4:2:2", 0),
        b"RGB3" => ("24-bit RGB 8-8-8", 0),
        b"BGR3" => ("24-bit BGR 8-8-8", 0),
        b"MJPG" => ("Motion-JPEG", FMT_FLAG_COMPRESSED),
        _ => ("Unknown", 0),
    }
}

/// Fill a pixel format as uvcvideo does for `code` at `w` x `h`.
fn fill_pix(pix: &mut PixFormat, code: u32, w: u32, h: u32) {
    let bpp = match &code.to_le_bytes() {
        b"GREY" => 1,
        b"Y16 " | b"Y10 " | b"Y12 " | b"YUYV" => 2,
        b"RGB3" | b"BGR3" => 3,
        _ => 0,
    };
    let mjpg = code == fourcc(b"MJPG");
    *pix = PixFormat {
        width: w,
        height: h,
        pixelformat: code,
        field: FIELD_NONE,
        bytesperline: w.saturating_mul(bpp),
        // A compressed frame is at most two bytes a pixel (dwMaxVideoFrameBufferSize).
        sizeimage: w
            .saturating_mul(h)
            .saturating_mul(if mjpg { 2 } else { bpp }),
        colorspace: COLORSPACE_SRGB,
        priv_: PIX_FMT_PRIV_MAGIC,
        flags: 0,
        ycbcr_enc: YCBCR_ENC_601,
        quantization: if mjpg || code == fourcc(b"YUYV") {
            QUANTIZATION_LIM_RANGE
        } else {
            QUANTIZATION_FULL_RANGE
        },
        xfer_func: XFER_FUNC_SRGB,
    };
}

fn fourcc_of(name: &str) -> u32 {
    let mut c = [b' '; 4];
    for (d, s) in c.iter_mut().zip(name.bytes()) {
        *d = s;
    }
    fourcc(&c)
}

fn name_of(code: u32) -> String {
    String::from_utf8_lossy(&code.to_le_bytes())
        .trim_end()
        .to_string()
}

/// The device's state as the launcher reports it.
struct DevState {
    formats: Vec<u32>,
    sizes: Vec<(u32, u32)>,
    intervals: Vec<(u32, u32)>,
    fmt: u32,
    width: u32,
    height: u32,
    interval: (u32, u32),
    ctrls: HashMap<u32, i64>,
}

fn pair(s: &str, sep: char) -> Option<(u32, u32)> {
    let (a, b) = s.split_once(sep)?;
    Some((a.parse().ok()?, b.parse().ok()?))
}

impl DevState {
    fn parse(kv: &HashMap<String, String>) -> Result<DevState, i32> {
        let get = |k: &str| kv.get(k).map(String::as_str).ok_or(libc::EIO);
        let list = |k: &str, sep: char| -> Result<Vec<(u32, u32)>, i32> {
            get(k)?
                .split(',')
                .map(|s| pair(s, sep).ok_or(libc::EIO))
                .collect()
        };
        let ctrls = kv
            .iter()
            .filter_map(|(k, v)| {
                let id = u32::from_str_radix(k.strip_prefix("ctrl.")?, 16).ok()?;
                Some((id, v.parse().ok()?))
            })
            .collect();
        Ok(DevState {
            formats: get("formats")?.split(',').map(fourcc_of).collect(),
            sizes: list("sizes", 'x')?,
            intervals: list("intervals", '/')?,
            fmt: fourcc_of(get("fmt")?),
            width: get("width")?.parse().map_err(|_| libc::EIO)?,
            height: get("height")?.parse().map_err(|_| libc::EIO)?,
            interval: pair(get("interval")?, '/').ok_or(libc::EIO)?,
            ctrls,
        })
    }

    fn value(&self, c: &CtrlDef) -> i64 {
        self.ctrls.get(&c.id).copied().unwrap_or(c.def)
    }

    fn flags(&self, c: &CtrlDef) -> u32 {
        let mut flags = 0;
        if c.type_ == CTRL_TYPE_CTRL_CLASS {
            flags |= CTRL_FLAG_READ_ONLY | CTRL_FLAG_WRITE_ONLY;
        }
        if CTRLS
            .iter()
            .any(|s| s.master.is_some_and(|(m, _)| m == c.id))
        {
            flags |= CTRL_FLAG_UPDATE;
        }
        if let Some((m, manual)) = c.master {
            if find_ctrl(m).is_some_and(|mc| self.value(mc) != manual) {
                flags |= CTRL_FLAG_INACTIVE;
            }
        }
        flags
    }

    /// The supported size nearest `w` x `h`, by uvcvideo's measure.
    fn nearest_size(&self, w: u32, h: u32) -> Result<(u32, u32), i32> {
        let score = |&(fw, fh): &(u32, u32)| {
            let (w, h, fw, fh) = (w as u64, h as u64, fw as u64, fh as u64);
            let d = w.min(fw) * h.min(fh);
            w * h + fw * fh - 2 * d
        };
        self.sizes
            .iter()
            .copied()
            .min_by_key(score)
            .ok_or(libc::EIO)
    }

    fn nearest_interval(&self, num: u32, den: u32) -> Result<(u32, u32), i32> {
        let want = if den == 0 {
            0.0
        } else {
            num as f64 / den as f64
        };
        self.intervals
            .iter()
            .copied()
            .min_by(|a, b| {
                let da = (a.0 as f64 / a.1 as f64 - want).abs();
                let db = (b.0 as f64 / b.1 as f64 - want).abs();
                da.total_cmp(&db)
            })
            .ok_or(libc::EIO)
    }
}

/// A control value made valid as uvcvideo does: integers and booleans are rounded to the
/// step and clamped; a menu value out of range is ERANGE, a missing item EINVAL.
fn validate(c: &CtrlDef, v: i64) -> Result<i64, i32> {
    match c.type_ {
        CTRL_TYPE_MENU => {
            if v < c.min || v > c.max {
                Err(libc::ERANGE)
            } else if menu_item(c.id, v).is_none() {
                Err(libc::EINVAL)
            } else {
                Ok(v)
            }
        }
        CTRL_TYPE_CTRL_CLASS => Err(libc::EACCES),
        _ => {
            let step = c.step.max(1) as i64;
            let v = c.min + ((v.clamp(c.min, c.max) - c.min + step / 2) / step) * step;
            Ok(v.min(c.max))
        }
    }
}

/// This library's own mapping of a buffer's memfd: frames are read into it from the
/// socket, so the program's mapping of the same memfd sees them with no further copy.
struct Mapping {
    ptr: *mut u8,
    len: usize,
}

// SAFETY: a private mapping owned by one buffer, used under the open file's lock.
unsafe impl Send for Mapping {}

impl Mapping {
    fn new(fd: c_int, len: usize) -> Option<Mapping> {
        let p = crate::real_mmap(
            std::ptr::null_mut(),
            len,
            libc::PROT_READ | libc::PROT_WRITE,
            libc::MAP_SHARED,
            fd,
            0,
        );
        (p != libc::MAP_FAILED && !p.is_null()).then_some(Mapping {
            ptr: p as *mut u8,
            len,
        })
    }

    fn bytes(&mut self) -> &mut [u8] {
        // SAFETY: `len` bytes mapped read-write for as long as `self` lives.
        unsafe { std::slice::from_raw_parts_mut(self.ptr, self.len) }
    }
}

impl Drop for Mapping {
    fn drop(&mut self) {
        crate::real_munmap(self.ptr as *mut c_void, self.len);
    }
}

struct Buf {
    memfd: OwnedFd,
    map: Mapping,
    length: u32,
    offset: u32,
    queued: bool,
    done: Option<Buffer>,
}

/// One open file of the simulated device.
pub struct SimFile {
    link: Link,
    /// The placeholder file the application holds; its flags say whether it is non-blocking.
    real_fd: c_int,
    bufs: Vec<Buf>,
    queue: VecDeque<u32>,
    streaming: bool,
    claimed: bool,
    /// No buffer queued since REQBUFS or STREAMOFF: poll says POLLERR (vb2's
    /// `waiting_for_buffers` quirk for capture queues).
    waiting_for_buffers: bool,
}

const PAGE: u32 = 4096;

fn page_align(n: u32) -> Option<u32> {
    n.checked_next_multiple_of(PAGE)
}

/// The ioctl's argument as a `T`.
///
/// # Safety
/// `arg` must be null or point to a valid, writable `T`, as the caller of `ioctl` promised.
unsafe fn arg_mut<'a, T>(arg: *mut c_void) -> Result<&'a mut T, i32> {
    if arg.is_null() {
        return Err(libc::EFAULT);
    }
    Ok(&mut *(arg as *mut T))
}

fn kernel_version() -> u32 {
    // SAFETY: uname fills the struct it is given.
    let mut u: libc::utsname = unsafe { std::mem::zeroed() };
    if unsafe { libc::uname(&mut u) } != 0 {
        return 0;
    }
    let release: String = u
        .release
        .iter()
        .take_while(|c| **c != 0)
        .map(|c| *c as u8 as char)
        .collect();
    let mut parts = release
        .split(|c: char| !c.is_ascii_digit())
        .filter_map(|p| p.parse::<u32>().ok());
    let (a, b, c) = (
        parts.next().unwrap_or(0),
        parts.next().unwrap_or(0),
        parts.next().unwrap_or(0),
    );
    (a << 16) | (b.min(255) << 8) | c.min(255)
}

fn now_monotonic_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime fills the timespec it is given.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// What `poll` sees on a simulated device.
pub enum Readiness {
    /// Not streaming, or the device is gone (POLLERR, with POLLHUP when gone).
    Error {
        gone: bool,
    },
    Ready,
    NotYet,
}

impl SimFile {
    pub fn new(link: Link, real_fd: c_int) -> SimFile {
        SimFile {
            link,
            real_fd,
            bufs: Vec::new(),
            queue: VecDeque::new(),
            streaming: false,
            claimed: false,
            waiting_for_buffers: true,
        }
    }

    fn nonblocking(&self) -> bool {
        // SAFETY: F_GETFL on a descriptor the application holds open.
        let fl = unsafe { libc::fcntl(self.real_fd, libc::F_GETFL) };
        fl >= 0 && fl & libc::O_NONBLOCK != 0
    }

    fn state(&mut self) -> Result<DevState, i32> {
        DevState::parse(&self.link.state()?)
    }

    /// A buffer's mapping: the memfd holding buffer `offset`, if `len` fits it.
    pub fn mmap_target(&self, offset: i64, len: usize) -> Option<c_int> {
        self.bufs
            .iter()
            .find(|b| b.offset as i64 == offset && len <= b.map.len)
            .map(|b| b.memfd.as_raw_fd())
    }

    /// Poll readiness, waiting at most `timeout_ms` (-1: no limit) in the launcher.
    pub fn poll(&mut self, timeout_ms: i32) -> Readiness {
        if !self.streaming {
            return match self.link.call("STATE") {
                Err(libc::ENODEV) => Readiness::Error { gone: true },
                _ => Readiness::Error { gone: false },
            };
        }
        if self.waiting_for_buffers {
            return Readiness::Error { gone: false };
        }
        if self.queue.is_empty() {
            if timeout_ms != 0 {
                let ms = if timeout_ms < 0 {
                    50
                } else {
                    timeout_ms.min(50)
                };
                std::thread::sleep(std::time::Duration::from_millis(ms as u64));
            }
            return Readiness::NotYet;
        }
        match self.link.call(&format!("POLL {timeout_ms}")) {
            Ok(r) if r == "1" => Readiness::Ready,
            Ok(_) => Readiness::NotYet,
            Err(libc::ENODEV) => Readiness::Error { gone: true },
            Err(_) => Readiness::Error { gone: false },
        }
    }

    /// Answer one ioctl; `Err(errno)` on failure.
    ///
    /// # Safety
    /// `arg` must be what the caller of `ioctl` passed for `req`.
    pub unsafe fn ioctl(&mut self, req: u32, arg: *mut c_void) -> Result<(), i32> {
        let st = self.state()?;
        match req {
            VIDIOC_QUERYCAP => {
                let cap = arg_mut::<Capability>(arg)?;
                *cap = std::mem::zeroed();
                put_str(&mut cap.driver, "glint-sim");
                put_str(&mut cap.card, "Glint Simulated Camera");
                put_str(&mut cap.bus_info, "platform:glint-sim");
                cap.version = kernel_version();
                cap.device_caps = CAP_VIDEO_CAPTURE | CAP_STREAMING | CAP_EXT_PIX_FORMAT;
                cap.capabilities = cap.device_caps | CAP_DEVICE_CAPS;
                Ok(())
            }
            VIDIOC_ENUM_FMT => {
                let d = arg_mut::<FmtDesc>(arg)?;
                if d.type_ != BUF_TYPE_VIDEO_CAPTURE {
                    return Err(libc::EINVAL);
                }
                let code = *st.formats.get(d.index as usize).ok_or(libc::EINVAL)?;
                let (desc, flags) = describe(code);
                d.flags = flags;
                put_str(&mut d.description, desc);
                d.pixelformat = code;
                d.mbus_code = 0;
                d.reserved = [0; 3];
                Ok(())
            }
            VIDIOC_G_FMT => {
                let f = arg_mut::<Format>(arg)?;
                if f.type_ != BUF_TYPE_VIDEO_CAPTURE {
                    return Err(libc::EINVAL);
                }
                f.fmt = [0; 25];
                fill_pix(f.pix(), st.fmt, st.width, st.height);
                Ok(())
            }
            VIDIOC_S_FMT | VIDIOC_TRY_FMT => {
                let f = arg_mut::<Format>(arg)?;
                if f.type_ != BUF_TYPE_VIDEO_CAPTURE {
                    return Err(libc::EINVAL);
                }
                let want = *f.pix();
                let code = if st.formats.contains(&want.pixelformat) {
                    want.pixelformat
                } else {
                    *st.formats.first().ok_or(libc::EIO)?
                };
                let (w, h) = st.nearest_size(want.width, want.height)?;
                f.fmt = [0; 25];
                fill_pix(f.pix(), code, w, h);
                if req == VIDIOC_S_FMT {
                    if !self.bufs.is_empty() || self.streaming {
                        return Err(libc::EBUSY);
                    }
                    self.link
                        .call(&format!("SET fmt={} width={w} height={h}", name_of(code)))?;
                }
                Ok(())
            }
            VIDIOC_ENUM_FRAMESIZES => {
                let s = arg_mut::<FrmSizeEnum>(arg)?;
                if !st.formats.contains(&s.pixel_format) {
                    return Err(libc::EINVAL);
                }
                let (w, h) = *st.sizes.get(s.index as usize).ok_or(libc::EINVAL)?;
                s.type_ = FRMSIZE_TYPE_DISCRETE;
                s.size = [w, h, 0, 0, 0, 0];
                s.reserved = [0; 2];
                Ok(())
            }
            VIDIOC_ENUM_FRAMEINTERVALS => {
                let i = arg_mut::<FrmIvalEnum>(arg)?;
                if !st.formats.contains(&i.pixel_format) || !st.sizes.contains(&(i.width, i.height))
                {
                    return Err(libc::EINVAL);
                }
                let (n, d) = *st.intervals.get(i.index as usize).ok_or(libc::EINVAL)?;
                i.type_ = FRMIVAL_TYPE_DISCRETE;
                i.interval = [Fract {
                    numerator: n,
                    denominator: d,
                }; 3];
                i.interval[1] = Fract {
                    numerator: 0,
                    denominator: 0,
                };
                i.interval[2] = i.interval[1];
                i.reserved = [0; 2];
                Ok(())
            }
            VIDIOC_G_PARM | VIDIOC_S_PARM => {
                let p = arg_mut::<StreamParm>(arg)?;
                if p.type_ != BUF_TYPE_VIDEO_CAPTURE {
                    return Err(libc::EINVAL);
                }
                let (mut n, mut d) = st.interval;
                if req == VIDIOC_S_PARM {
                    if self.streaming {
                        return Err(libc::EBUSY);
                    }
                    let t = p.capture().timeperframe;
                    (n, d) = st.nearest_interval(t.numerator, t.denominator)?;
                    self.link.call(&format!("SET interval={n}/{d}"))?;
                }
                p.parm = [0; 50];
                let c = p.capture();
                c.capability = CAP_TIMEPERFRAME;
                c.timeperframe = Fract {
                    numerator: n,
                    denominator: d,
                };
                Ok(())
            }
            VIDIOC_ENUMINPUT => {
                let i = arg_mut::<Input>(arg)?;
                if i.index != 0 {
                    return Err(libc::EINVAL);
                }
                *i = Input {
                    index: 0,
                    type_: INPUT_TYPE_CAMERA,
                    ..std::mem::zeroed()
                };
                put_str(&mut i.name, "Camera 1");
                Ok(())
            }
            VIDIOC_G_INPUT => {
                *arg_mut::<i32>(arg)? = 0;
                Ok(())
            }
            VIDIOC_S_INPUT => match *arg_mut::<i32>(arg)? {
                0 => Ok(()),
                _ => Err(libc::EINVAL),
            },
            VIDIOC_G_PRIORITY => {
                *arg_mut::<u32>(arg)? = PRIORITY_DEFAULT;
                Ok(())
            }
            VIDIOC_S_PRIORITY => match *arg_mut::<u32>(arg)? {
                0..=3 => Ok(()),
                _ => Err(libc::EINVAL),
            },
            VIDIOC_QUERYCTRL => {
                let q = arg_mut::<QueryCtrl>(arg)?;
                let c = query_target(q.id).ok_or(libc::EINVAL)?;
                *q = QueryCtrl {
                    id: c.id,
                    type_: c.type_,
                    name: [0; 32],
                    minimum: c.min as i32,
                    maximum: c.max as i32,
                    step: c.step as i32,
                    default_value: c.def as i32,
                    flags: st.flags(c),
                    reserved: [0; 2],
                };
                put_str(&mut q.name, c.name);
                Ok(())
            }
            VIDIOC_QUERY_EXT_CTRL => {
                let q = arg_mut::<QueryExtCtrl>(arg)?;
                let c = query_target(q.id).ok_or(libc::EINVAL)?;
                *q = QueryExtCtrl {
                    id: c.id,
                    type_: c.type_,
                    minimum: c.min,
                    maximum: c.max,
                    step: c.step,
                    default_value: c.def,
                    flags: st.flags(c),
                    elem_size: if c.type_ == CTRL_TYPE_CTRL_CLASS {
                        0
                    } else {
                        4
                    },
                    elems: 1,
                    ..std::mem::zeroed()
                };
                put_str(&mut q.name, c.name);
                Ok(())
            }
            VIDIOC_QUERYMENU => {
                let m = arg_mut::<QueryMenu>(arg)?;
                let (id, index) = (m.id, m.index);
                let c = find_ctrl(id).ok_or(libc::EINVAL)?;
                if c.type_ != CTRL_TYPE_MENU {
                    return Err(libc::EINVAL);
                }
                let name = menu_item(id, index as i64).ok_or(libc::EINVAL)?;
                put_str(&mut m.name, name);
                m.reserved = 0;
                Ok(())
            }
            VIDIOC_G_CTRL => {
                let c = arg_mut::<Control>(arg)?;
                let def = find_ctrl(c.id).ok_or(libc::EINVAL)?;
                if def.type_ == CTRL_TYPE_CTRL_CLASS {
                    return Err(libc::EACCES);
                }
                c.value = st.value(def) as i32;
                Ok(())
            }
            VIDIOC_S_CTRL => {
                let c = arg_mut::<Control>(arg)?;
                let mut one = [(c.id, c.value as i64)];
                self.set_controls(&st, &mut one, true).map_err(|(_, e)| e)?;
                c.value = one[0].1 as i32;
                Ok(())
            }
            VIDIOC_G_EXT_CTRLS | VIDIOC_S_EXT_CTRLS | VIDIOC_TRY_EXT_CTRLS => {
                let cs = arg_mut::<ExtControls>(arg)?;
                let which = cs.which;
                if which == CTRL_WHICH_REQUEST_VAL {
                    return Err(libc::EINVAL);
                }
                if cs.count == 0 {
                    return Ok(());
                }
                if cs.count > CID_MAX_CTRLS {
                    return Err(libc::EINVAL);
                }
                if cs.controls.is_null() {
                    return Err(libc::EFAULT);
                }
                let items = std::slice::from_raw_parts_mut(cs.controls, cs.count as usize);
                if req == VIDIOC_G_EXT_CTRLS {
                    for (i, item) in items.iter_mut().enumerate() {
                        let id = item.id;
                        let Some(def) = find_ctrl(id) else {
                            cs.error_idx = i as u32;
                            return Err(libc::EINVAL);
                        };
                        if def.type_ == CTRL_TYPE_CTRL_CLASS {
                            cs.error_idx = i as u32;
                            return Err(libc::EACCES);
                        }
                        let v = if which == CTRL_WHICH_DEF_VAL {
                            def.def
                        } else {
                            st.value(def)
                        };
                        item.value64 = (v as i32) as u32 as i64;
                    }
                    return Ok(());
                }
                if which == CTRL_WHICH_DEF_VAL {
                    return Err(libc::EINVAL);
                }
                let mut vals: Vec<(u32, i64)> = items
                    .iter()
                    .map(|c| {
                        let v = c.value64;
                        (c.id, (v as u32 as i32) as i64)
                    })
                    .collect();
                match self.set_controls(&st, &mut vals, req == VIDIOC_S_EXT_CTRLS) {
                    Ok(()) => {
                        for (item, (_, v)) in items.iter_mut().zip(vals) {
                            item.value64 = (v as i32) as u32 as i64;
                        }
                        Ok(())
                    }
                    Err((i, e)) => {
                        cs.error_idx = i as u32;
                        Err(e)
                    }
                }
            }
            VIDIOC_REQBUFS => {
                let r = arg_mut::<RequestBuffers>(arg)?;
                if r.type_ != BUF_TYPE_VIDEO_CAPTURE || r.memory != MEMORY_MMAP {
                    return Err(libc::EINVAL);
                }
                if self.streaming {
                    return Err(libc::EBUSY);
                }
                self.bufs.clear();
                self.queue.clear();
                self.waiting_for_buffers = true;
                r.capabilities = BUF_CAP_SUPPORTS_MMAP;
                r.flags_reserved = 0;
                if r.count == 0 {
                    if self.claimed {
                        self.link.call("RELEASE")?;
                        self.claimed = false;
                    }
                    return Ok(());
                }
                if !self.claimed {
                    self.link.call("CLAIM")?;
                    self.claimed = true;
                }
                let mut pix = std::mem::zeroed();
                fill_pix(&mut pix, st.fmt, st.width, st.height);
                let count = r.count.clamp(1, 32);
                let mut offset = 0u32;
                for _ in 0..count {
                    let fd =
                        libc::memfd_create(c"glint-sim-v4l2-buffer".as_ptr(), libc::MFD_CLOEXEC);
                    if fd < 0 {
                        self.bufs.clear();
                        return Err(libc::ENOMEM);
                    }
                    let memfd = OwnedFd::from_raw_fd(fd);
                    // Offsets are 32 bits: a frame too large for them cannot be served.
                    let Some((len, next)) = page_align(pix.sizeimage)
                        .filter(|l| *l > 0)
                        .and_then(|l| Some((l, offset.checked_add(l)?)))
                    else {
                        self.bufs.clear();
                        return Err(libc::ENOMEM);
                    };
                    if libc::ftruncate(fd, len as libc::off_t) != 0 {
                        self.bufs.clear();
                        return Err(libc::ENOMEM);
                    }
                    let Some(map) = Mapping::new(fd, len as usize) else {
                        self.bufs.clear();
                        return Err(libc::ENOMEM);
                    };
                    self.bufs.push(Buf {
                        memfd,
                        map,
                        length: pix.sizeimage,
                        offset,
                        queued: false,
                        done: None,
                    });
                    offset = next;
                }
                r.count = count;
                Ok(())
            }
            VIDIOC_QUERYBUF | VIDIOC_QBUF => {
                let b = arg_mut::<Buffer>(arg)?;
                if b.type_ != BUF_TYPE_VIDEO_CAPTURE {
                    return Err(libc::EINVAL);
                }
                let index = b.index;
                let buf = self.bufs.get_mut(index as usize).ok_or(libc::EINVAL)?;
                if req == VIDIOC_QBUF {
                    if b.memory != MEMORY_MMAP || buf.queued {
                        return Err(libc::EINVAL);
                    }
                    buf.queued = true;
                    buf.done = None;
                    self.queue.push_back(index);
                    self.waiting_for_buffers = false;
                }
                let (queued, length, offset) = (buf.queued, buf.length, buf.offset);
                *b = match buf.done {
                    Some(done) => done,
                    None => Buffer {
                        index,
                        type_: BUF_TYPE_VIDEO_CAPTURE,
                        field: FIELD_NONE,
                        memory: MEMORY_MMAP,
                        ..std::mem::zeroed()
                    },
                };
                b.flags = (b.flags & !BUF_FLAG_QUEUED)
                    | BUF_FLAG_MAPPED
                    | BUF_FLAG_TIMESTAMP_MONOTONIC
                    | BUF_FLAG_TSTAMP_SRC_SOE
                    | if queued { BUF_FLAG_QUEUED } else { 0 };
                b.m = offset as u64;
                b.length = length;
                Ok(())
            }
            VIDIOC_DQBUF => {
                let b = arg_mut::<Buffer>(arg)?;
                if b.type_ != BUF_TYPE_VIDEO_CAPTURE || b.memory != MEMORY_MMAP {
                    return Err(libc::EINVAL);
                }
                if !self.streaming {
                    return Err(libc::EINVAL);
                }
                let nonblock = self.nonblocking();
                let Some(&index) = self.queue.front() else {
                    // A real driver would wait for ever on an empty queue.
                    return Err(if nonblock { libc::EAGAIN } else { libc::EINVAL });
                };
                let buf = self.bufs.get_mut(index as usize).ok_or(libc::EIO)?;
                let length = (buf.length as usize).min(buf.map.len);
                let frame = self.link.dqbuf(nonblock, &mut buf.map.bytes()[..length])?;
                self.queue.pop_front();
                let used = frame.used;
                // DONE is cleared once a buffer is dequeued.
                let mut flags =
                    BUF_FLAG_MAPPED | BUF_FLAG_TIMESTAMP_MONOTONIC | BUF_FLAG_TSTAMP_SRC_SOE;
                if frame.error {
                    flags |= BUF_FLAG_ERROR;
                }
                let ts = if frame.timestamp_ns == 0 {
                    now_monotonic_ns()
                } else {
                    frame.timestamp_ns
                };
                let out = Buffer {
                    index,
                    type_: BUF_TYPE_VIDEO_CAPTURE,
                    bytesused: used as u32,
                    flags,
                    field: FIELD_NONE,
                    timestamp: Timeval {
                        tv_sec: (ts / 1_000_000_000) as i64,
                        tv_usec: (ts % 1_000_000_000 / 1000) as i64,
                    },
                    sequence: frame.sequence,
                    memory: MEMORY_MMAP,
                    m: buf.offset as u64,
                    length: buf.length,
                    ..std::mem::zeroed()
                };
                buf.queued = false;
                buf.done = Some(out);
                *b = out;
                Ok(())
            }
            VIDIOC_STREAMON | VIDIOC_STREAMOFF => {
                if *arg_mut::<u32>(arg)? != BUF_TYPE_VIDEO_CAPTURE {
                    return Err(libc::EINVAL);
                }
                if req == VIDIOC_STREAMON {
                    if self.bufs.is_empty() {
                        return Err(libc::EINVAL);
                    }
                    if !self.streaming {
                        self.link.call("STREAMON")?;
                        self.streaming = true;
                    }
                } else {
                    if self.streaming {
                        self.link.call("STREAMOFF")?;
                    }
                    self.streaming = false;
                    self.queue.clear();
                    self.waiting_for_buffers = true;
                    for b in &mut self.bufs {
                        b.queued = false;
                        b.done = None;
                    }
                }
                Ok(())
            }
            _ => Err(libc::ENOTTY),
        }
    }

    /// Validate, and when `apply` store, control values, as uvcvideo does for
    /// S_EXT_CTRLS/TRY_EXT_CTRLS: values are made valid in place; a control whose automatic
    /// master is not in manual mode (taking a master set in the same request into account)
    /// refuses a write with EACCES. On failure: (index, errno).
    fn set_controls(
        &mut self,
        st: &DevState,
        vals: &mut [(u32, i64)],
        apply: bool,
    ) -> Result<(), (usize, i32)> {
        for i in 0..vals.len() {
            let (id, v) = vals[i];
            let def = find_ctrl(id).ok_or((i, libc::EINVAL))?;
            vals[i].1 = validate(def, v).map_err(|e| (i, e))?;
            if let (true, Some((master, manual))) = (apply, def.master) {
                let master_value = match vals.iter().rev().find(|(m, _)| *m == master) {
                    Some((_, mv)) => *mv,
                    None => find_ctrl(master).map_or(0, |m| st.value(m)),
                };
                if master_value != manual {
                    return Err((i, libc::EACCES));
                }
            }
        }
        if apply {
            let set: Vec<String> = vals
                .iter()
                .map(|(id, v)| format!("ctrl.{id:x}={v}"))
                .collect();
            self.link
                .call(&format!("SET {}", set.join(" ")))
                .map_err(|e| (vals.len(), e))?;
        }
        Ok(())
    }
}
