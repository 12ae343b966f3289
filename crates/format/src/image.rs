//! Image types: pixels and frames as a camera delivers them, what a camera is, and the
//! lamp's state as read back. Plain data, shared by the devices that make them and the
//! stages that read them.

/// Pixel data, rows top to bottom: RGB interleaved, or one sample a pixel from a
/// monochrome camera ([`Frame::channels`]).
#[derive(Debug, Clone, PartialEq)]
pub enum Pixels {
    U8(Vec<u8>),
    U16(Vec<u16>),
}

impl Pixels {
    pub fn len(&self) -> usize {
        match self {
            Pixels::U8(v) => v.len(),
            Pixels::U16(v) => v.len(),
        }
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// A frame as the camera delivered it.
#[derive(Debug, Clone)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub bit_depth: u8,
    /// Samples a pixel: 3 (RGB interleaved) or 1 (monochrome).
    pub channels: u8,
    pub pixels: Pixels,
    /// Driver sequence number; a gap means frames were dropped.
    pub sequence: u64,
    /// Device clock at the start of exposure, µs, where the device has one.
    pub device_timestamp_us: Option<u64>,
    /// The exposure this frame was taken with, where the device reports it per frame.
    pub exposure_us: Option<u32>,
}

/// What a camera is.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct CameraInfo {
    pub model: String,
    pub width: u32,
    pub height: u32,
    pub bit_depth: u8,
    /// Samples a pixel: 3 (RGB) or 1 (monochrome). Sessions from before monochrome
    /// cameras are RGB.
    #[serde(default = "three")]
    pub channels: u8,
    /// The backend that drove it (`mock`, `v4l2`, `nokhwa`); absent in older sessions.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub backend: Option<String>,
    /// Driver, card and bus, as the device names them (V4L2).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub device: Option<String>,
    /// The pixel format frames arrived in (V4L2 four-character code name).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pixel_format: Option<String>,
    /// How Y'CbCr frames (YUYV) were converted to RGB: matrix and range, as the device
    /// reported them (e.g. `BT.601 limited range`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ycbcr_encoding: Option<String>,
    /// The frames were lossy and processed in the camera (MJPG): not measurements.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub lossy: bool,
    /// Every control as read back from the device once set up for capture.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub controls: Vec<ControlReading>,
    /// What did not go as the rig asked when the camera was set up (a standard control
    /// the camera lacks, a named control skipped under `missing_control = "warn"`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
}

fn three() -> u8 {
    3
}

impl CameraInfo {
    /// A camera known only by name and frame shape.
    pub fn basic(
        model: impl Into<String>,
        width: u32,
        height: u32,
        bit_depth: u8,
        channels: u8,
    ) -> Self {
        CameraInfo {
            model: model.into(),
            width,
            height,
            bit_depth,
            channels,
            backend: None,
            device: None,
            pixel_format: None,
            ycbcr_encoding: None,
            lossy: false,
            controls: Vec::new(),
            notes: Vec::new(),
        }
    }
}

/// A device control as read back.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ControlReading {
    /// The control's name as `glint devices` lists it (e.g. `exposure_time_absolute`).
    pub name: String,
    /// Its value read back from the device.
    pub value: i64,
    /// The value Glint asked for, where it set the control.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub requested: Option<i64>,
}

/// The lamp's state as read back from it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct LampState {
    pub on: bool,
    /// Output level 0..1000 (meaningful when on).
    pub level: u16,
}

impl LampState {
    /// The lamp switched off (the level of an off lamp is 0).
    pub const OFF: LampState = LampState {
        on: false,
        level: 0,
    };
}

impl std::fmt::Display for LampState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.on {
            write!(f, "on at level {}", self.level)
        } else {
            write!(f, "off")
        }
    }
}

/// "1 channel (monochrome)" or "3 channels (RGB)".
pub fn channels_name(c: u8) -> String {
    match c {
        1 => "1 channel (monochrome)".into(),
        3 => "3 channels (RGB)".into(),
        n => format!("{n} channels"),
    }
}
