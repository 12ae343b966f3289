//! The slice of the V4L2 ABI the simulated device answers, written by hand from
//! `<linux/videodev2.h>` for 64-bit Linux (x86_64, aarch64; little-endian, LP64).
//!
//! Hand-written rather than generated (bindgen needs libclang): every struct carries a
//! compile-time size check against the kernel's `sizeof`, checked with gcc on the header.

#![allow(dead_code)]

/// `_IOC(dir, type, nr, size)` of `<asm-generic/ioctl.h>`.
const fn ioc(dir: u32, ty: u8, nr: u8, size: usize) -> u32 {
    (dir << 30) | ((size as u32) << 16) | ((ty as u32) << 8) | nr as u32
}
const fn ior<T>(nr: u8) -> u32 {
    ioc(2, b'V', nr, std::mem::size_of::<T>())
}
const fn iow<T>(nr: u8) -> u32 {
    ioc(1, b'V', nr, std::mem::size_of::<T>())
}
const fn iowr<T>(nr: u8) -> u32 {
    ioc(3, b'V', nr, std::mem::size_of::<T>())
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct Capability {
    pub driver: [u8; 16],
    pub card: [u8; 32],
    pub bus_info: [u8; 32],
    pub version: u32,
    pub capabilities: u32,
    pub device_caps: u32,
    pub reserved: [u32; 3],
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct PixFormat {
    pub width: u32,
    pub height: u32,
    pub pixelformat: u32,
    pub field: u32,
    pub bytesperline: u32,
    pub sizeimage: u32,
    pub colorspace: u32,
    pub priv_: u32,
    pub flags: u32,
    pub ycbcr_enc: u32,
    pub quantization: u32,
    pub xfer_func: u32,
}

/// `struct v4l2_format`: the union is 200 bytes, 8-aligned (it holds pointers).
#[repr(C)]
pub struct Format {
    pub type_: u32,
    pub pad: u32,
    pub fmt: [u64; 25],
}

impl Format {
    pub fn pix(&mut self) -> &mut PixFormat {
        // SAFETY: the union starts with `struct v4l2_pix_format` (48 bytes of the 200).
        unsafe { &mut *(self.fmt.as_mut_ptr() as *mut PixFormat) }
    }
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct Timeval {
    pub tv_sec: i64,
    pub tv_usec: i64,
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct Timecode {
    pub type_: u32,
    pub flags: u32,
    pub frames: u8,
    pub seconds: u8,
    pub minutes: u8,
    pub hours: u8,
    pub userbits: [u8; 4],
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct Buffer {
    pub index: u32,
    pub type_: u32,
    pub bytesused: u32,
    pub flags: u32,
    pub field: u32,
    pub pad0: u32,
    pub timestamp: Timeval,
    pub timecode: Timecode,
    pub sequence: u32,
    pub memory: u32,
    /// The union `m`: `offset` (u32, the low half on little-endian), `userptr`, `planes`, `fd`.
    pub m: u64,
    pub length: u32,
    pub reserved2: u32,
    pub request_fd: i32,
    pub pad1: u32,
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct RequestBuffers {
    pub count: u32,
    pub type_: u32,
    pub memory: u32,
    pub capabilities: u32,
    /// `__u8 flags; __u8 reserved[3];`
    pub flags_reserved: u32,
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct QueryCtrl {
    pub id: u32,
    pub type_: u32,
    pub name: [u8; 32],
    pub minimum: i32,
    pub maximum: i32,
    pub step: i32,
    pub default_value: i32,
    pub flags: u32,
    pub reserved: [u32; 2],
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct QueryExtCtrl {
    pub id: u32,
    pub type_: u32,
    pub name: [u8; 32],
    pub minimum: i64,
    pub maximum: i64,
    pub step: u64,
    pub default_value: i64,
    pub flags: u32,
    pub elem_size: u32,
    pub elems: u32,
    pub nr_of_dims: u32,
    pub dims: [u32; 4],
    pub reserved: [u32; 32],
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct Control {
    pub id: u32,
    pub value: i32,
}

/// `struct v4l2_ext_control` is `__attribute__ ((packed))`; the union is 8 bytes
/// (`value`, `value64`, or a pointer for string and compound controls).
#[repr(C, packed)]
#[derive(Clone, Copy)]
pub struct ExtControl {
    pub id: u32,
    pub size: u32,
    pub reserved2: u32,
    pub value64: i64,
}

#[repr(C)]
pub struct ExtControls {
    /// `ctrl_class` or `which`.
    pub which: u32,
    pub count: u32,
    pub error_idx: u32,
    pub request_fd: i32,
    pub reserved: u32,
    pub pad: u32,
    pub controls: *mut ExtControl,
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct FmtDesc {
    pub index: u32,
    pub type_: u32,
    pub flags: u32,
    pub description: [u8; 32],
    pub pixelformat: u32,
    pub mbus_code: u32,
    pub reserved: [u32; 3],
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct FrmSizeEnum {
    pub index: u32,
    pub pixel_format: u32,
    pub type_: u32,
    /// `discrete {width, height}` or `stepwise {6 × u32}`.
    pub size: [u32; 6],
    pub reserved: [u32; 2],
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct Fract {
    pub numerator: u32,
    pub denominator: u32,
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct FrmIvalEnum {
    pub index: u32,
    pub pixel_format: u32,
    pub width: u32,
    pub height: u32,
    pub type_: u32,
    /// `discrete` (one fraction) or `stepwise {min, max, step}`.
    pub interval: [Fract; 3],
    pub reserved: [u32; 2],
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct CaptureParm {
    pub capability: u32,
    pub capturemode: u32,
    pub timeperframe: Fract,
    pub extendedmode: u32,
    pub readbuffers: u32,
    pub reserved: [u32; 4],
}

#[repr(C)]
pub struct StreamParm {
    pub type_: u32,
    /// The union `parm` (`v4l2_captureparm` first), 200 bytes.
    pub parm: [u32; 50],
}

impl StreamParm {
    pub fn capture(&mut self) -> &mut CaptureParm {
        // SAFETY: the union starts with `struct v4l2_captureparm` (40 of its 200 bytes), 4-aligned.
        unsafe { &mut *(self.parm.as_mut_ptr() as *mut CaptureParm) }
    }
}

/// `struct v4l2_querymenu` is packed; the union is `name[32]` or `__s64 value`.
#[repr(C, packed)]
#[derive(Clone, Copy)]
pub struct QueryMenu {
    pub id: u32,
    pub index: u32,
    pub name: [u8; 32],
    pub reserved: u32,
}

#[repr(C)]
#[derive(Clone, Copy)]
pub struct Input {
    pub index: u32,
    pub name: [u8; 32],
    pub type_: u32,
    pub audioset: u32,
    pub tuner: u32,
    pub std: u64,
    pub status: u32,
    pub capabilities: u32,
    pub reserved: [u32; 3],
}

// Sizes as gcc reports them for <linux/videodev2.h> on x86_64 (the same on aarch64).
const _: () = {
    use std::mem::size_of;
    assert!(size_of::<Capability>() == 104);
    assert!(size_of::<PixFormat>() == 48);
    assert!(size_of::<Format>() == 208);
    assert!(size_of::<Timecode>() == 16);
    assert!(size_of::<Buffer>() == 88);
    assert!(std::mem::offset_of!(Buffer, timestamp) == 24);
    assert!(std::mem::offset_of!(Buffer, sequence) == 56);
    assert!(std::mem::offset_of!(Buffer, m) == 64);
    assert!(std::mem::offset_of!(Buffer, length) == 72);
    assert!(size_of::<RequestBuffers>() == 20);
    assert!(size_of::<QueryCtrl>() == 68);
    assert!(size_of::<QueryExtCtrl>() == 232);
    assert!(std::mem::offset_of!(QueryExtCtrl, minimum) == 40);
    assert!(std::mem::offset_of!(QueryExtCtrl, elem_size) == 76);
    assert!(size_of::<Control>() == 8);
    assert!(size_of::<ExtControl>() == 20);
    assert!(size_of::<ExtControls>() == 32);
    assert!(std::mem::offset_of!(ExtControls, controls) == 24);
    assert!(size_of::<FmtDesc>() == 64);
    assert!(size_of::<FrmSizeEnum>() == 44);
    assert!(size_of::<FrmIvalEnum>() == 52);
    assert!(size_of::<StreamParm>() == 204);
    assert!(size_of::<CaptureParm>() == 40);
    assert!(size_of::<QueryMenu>() == 44);
    assert!(size_of::<Input>() == 80);
    assert!(std::mem::offset_of!(Input, std) == 48);
};

pub const VIDIOC_QUERYCAP: u32 = ior::<Capability>(0);
pub const VIDIOC_ENUM_FMT: u32 = iowr::<FmtDesc>(2);
pub const VIDIOC_G_FMT: u32 = iowr::<Format>(4);
pub const VIDIOC_S_FMT: u32 = iowr::<Format>(5);
pub const VIDIOC_REQBUFS: u32 = iowr::<RequestBuffers>(8);
pub const VIDIOC_QUERYBUF: u32 = iowr::<Buffer>(9);
pub const VIDIOC_QBUF: u32 = iowr::<Buffer>(15);
pub const VIDIOC_DQBUF: u32 = iowr::<Buffer>(17);
pub const VIDIOC_STREAMON: u32 = iow::<i32>(18);
pub const VIDIOC_STREAMOFF: u32 = iow::<i32>(19);
pub const VIDIOC_G_PARM: u32 = iowr::<StreamParm>(21);
pub const VIDIOC_S_PARM: u32 = iowr::<StreamParm>(22);
pub const VIDIOC_ENUMINPUT: u32 = iowr::<Input>(26);
pub const VIDIOC_G_CTRL: u32 = iowr::<Control>(27);
pub const VIDIOC_S_CTRL: u32 = iowr::<Control>(28);
pub const VIDIOC_QUERYCTRL: u32 = iowr::<QueryCtrl>(36);
pub const VIDIOC_QUERYMENU: u32 = iowr::<QueryMenu>(37);
pub const VIDIOC_G_INPUT: u32 = ior::<i32>(38);
pub const VIDIOC_S_INPUT: u32 = iowr::<i32>(39);
pub const VIDIOC_TRY_FMT: u32 = iowr::<Format>(64);
pub const VIDIOC_G_PRIORITY: u32 = ior::<u32>(67);
pub const VIDIOC_S_PRIORITY: u32 = iow::<u32>(68);
pub const VIDIOC_G_EXT_CTRLS: u32 = iowr::<ExtControls>(71);
pub const VIDIOC_S_EXT_CTRLS: u32 = iowr::<ExtControls>(72);
pub const VIDIOC_TRY_EXT_CTRLS: u32 = iowr::<ExtControls>(73);
pub const VIDIOC_ENUM_FRAMESIZES: u32 = iowr::<FrmSizeEnum>(74);
pub const VIDIOC_ENUM_FRAMEINTERVALS: u32 = iowr::<FrmIvalEnum>(75);
pub const VIDIOC_QUERY_EXT_CTRL: u32 = iowr::<QueryExtCtrl>(103);

// The numbers gcc computes from the header.
const _: () = {
    assert!(VIDIOC_QUERYCAP == 0x8068_5600);
    assert!(VIDIOC_S_FMT == 0xc0d0_5605);
    assert!(VIDIOC_REQBUFS == 0xc014_5608);
    assert!(VIDIOC_DQBUF == 0xc058_5611);
    assert!(VIDIOC_STREAMON == 0x4004_5612);
    assert!(VIDIOC_S_PARM == 0xc0cc_5616);
    assert!(VIDIOC_QUERYMENU == 0xc02c_5625);
    assert!(VIDIOC_G_EXT_CTRLS == 0xc020_5647);
    assert!(VIDIOC_ENUM_FRAMEINTERVALS == 0xc034_564b);
    assert!(VIDIOC_QUERY_EXT_CTRL == 0xc0e8_5667);
    assert!(VIDIOC_ENUMINPUT == 0xc050_561a);
};

pub const BUF_TYPE_VIDEO_CAPTURE: u32 = 1;
pub const MEMORY_MMAP: u32 = 1;
pub const FIELD_NONE: u32 = 1;

pub const CAP_VIDEO_CAPTURE: u32 = 0x0000_0001;
pub const CAP_EXT_PIX_FORMAT: u32 = 0x0020_0000;
pub const CAP_STREAMING: u32 = 0x0400_0000;
pub const CAP_DEVICE_CAPS: u32 = 0x8000_0000;
pub const CAP_TIMEPERFRAME: u32 = 0x1000;

pub const BUF_FLAG_MAPPED: u32 = 0x1;
pub const BUF_FLAG_QUEUED: u32 = 0x2;
pub const BUF_FLAG_DONE: u32 = 0x4;
pub const BUF_FLAG_ERROR: u32 = 0x40;
pub const BUF_FLAG_TIMESTAMP_MONOTONIC: u32 = 0x2000;
pub const BUF_FLAG_TSTAMP_SRC_SOE: u32 = 0x1_0000;
pub const BUF_CAP_SUPPORTS_MMAP: u32 = 0x1;

pub const FMT_FLAG_COMPRESSED: u32 = 0x1;
pub const FRMSIZE_TYPE_DISCRETE: u32 = 1;
pub const FRMIVAL_TYPE_DISCRETE: u32 = 1;
pub const PIX_FMT_PRIV_MAGIC: u32 = 0xfeed_cafe;

pub const COLORSPACE_SRGB: u32 = 8;
pub const YCBCR_ENC_601: u32 = 1;
pub const QUANTIZATION_FULL_RANGE: u32 = 1;
pub const QUANTIZATION_LIM_RANGE: u32 = 2;
pub const XFER_FUNC_SRGB: u32 = 2;

pub const INPUT_TYPE_CAMERA: u32 = 2;
pub const PRIORITY_DEFAULT: u32 = 2;

pub const CTRL_TYPE_INTEGER: u32 = 1;
pub const CTRL_TYPE_BOOLEAN: u32 = 2;
pub const CTRL_TYPE_MENU: u32 = 3;
pub const CTRL_TYPE_CTRL_CLASS: u32 = 6;

pub const CTRL_FLAG_READ_ONLY: u32 = 0x4;
pub const CTRL_FLAG_UPDATE: u32 = 0x8;
pub const CTRL_FLAG_INACTIVE: u32 = 0x10;
pub const CTRL_FLAG_WRITE_ONLY: u32 = 0x40;
pub const CTRL_FLAG_NEXT_CTRL: u32 = 0x8000_0000;
pub const CTRL_FLAG_NEXT_COMPOUND: u32 = 0x4000_0000;
pub const CTRL_ID_MASK: u32 = 0x0fff_ffff;
pub const CTRL_WHICH_CUR_VAL: u32 = 0;
pub const CTRL_WHICH_DEF_VAL: u32 = 0x0f00_0000;
pub const CTRL_WHICH_REQUEST_VAL: u32 = 0x0f01_0000;

pub const CID_USER_CLASS: u32 = 0x0098_0001;
pub const CID_BRIGHTNESS: u32 = 0x0098_0900;
pub const CID_CONTRAST: u32 = 0x0098_0901;
pub const CID_AUTO_WHITE_BALANCE: u32 = 0x0098_090c;
pub const CID_AUTOGAIN: u32 = 0x0098_0912;
pub const CID_GAIN: u32 = 0x0098_0913;
pub const CID_WHITE_BALANCE_TEMPERATURE: u32 = 0x0098_091a;
pub const CID_BACKLIGHT_COMPENSATION: u32 = 0x0098_091c;
pub const CID_CAMERA_CLASS: u32 = 0x009a_0001;
pub const CID_EXPOSURE_AUTO: u32 = 0x009a_0901;
pub const CID_EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;
pub const CID_EXPOSURE_AUTO_PRIORITY: u32 = 0x009a_0903;

/// A four-character code as V4L2 packs it (`v4l2_fourcc`).
pub const fn fourcc(c: &[u8; 4]) -> u32 {
    u32::from_le_bytes(*c)
}

/// Copy `s` into a NUL-terminated fixed-size C string field.
pub fn put_str(dst: &mut [u8], s: &str) {
    dst.fill(0);
    let n = s.len().min(dst.len() - 1);
    dst[..n].copy_from_slice(&s.as_bytes()[..n]);
}

/// `V4L2_CID_MAX_CTRLS`: the most controls one extended-controls call may name.
pub const CID_MAX_CTRLS: u32 = 1024;
