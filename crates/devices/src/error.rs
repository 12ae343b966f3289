//! What went wrong with a device.

use std::time::Duration;

use glint_format::image::LampState;

/// What went wrong with a device.
#[derive(Debug, thiserror::Error)]
pub enum DeviceError {
    #[error("camera stalled: no frame within {} ms; check the cable and that no other program holds the camera", .after.as_millis())]
    CameraTimeout { after: Duration },
    #[error("{lamp} did not answer `{command}` ({tries} tries, {} ms each); check that it is powered and connected to lamp.port, lamp.baud, and lamp.reply_timeout_ms for a slow device", .timeout.as_millis())]
    LampSilent {
        lamp: String,
        command: String,
        tries: u32,
        timeout: Duration,
    },
    /// `detail`: the last reply and the likely cause.
    #[error("{lamp} gave no usable reply to `{command}` in {tries} tries: {detail}")]
    LampGarbled {
        lamp: String,
        command: String,
        tries: u32,
        detail: String,
    },
    #[error("{lamp} answered `{command}` without a line end (got {got}); set lamp.protocol.receive_terminator (now \"{terminator}\") to the line end it sends")]
    LampNoLineEnd {
        lamp: String,
        command: String,
        got: String,
        terminator: &'static str,
    },
    #[error("{lamp} is gone ({reason}): the USB-serial adapter was unplugged or the controller lost power; the lamp's state is unknown: check it, plug it back in and start again")]
    LampGone { lamp: String, reason: String },
    #[error("{lamp} refused `{command}`: {reply}")]
    LampRefused {
        lamp: String,
        command: String,
        reply: String,
    },
    #[error("{lamp} reads back as {got} after `{command}`, expected {expected}; the lamp may be faulty or in local mode")]
    LampState {
        lamp: String,
        command: String,
        expected: LampState,
        got: LampState,
    },
    #[error("{device} is gone (unplugged or its driver was unloaded); plug the camera back in and start again")]
    Unplugged { device: String },
    #[error("the camera flagged frame {sequence} as corrupt ({reason}); check the cable and USB bandwidth")]
    CorruptFrame { sequence: u64, reason: String },
    #[error("cannot open {what}: {reason}")]
    Open { what: String, reason: String },
    #[error("{op}: {source}")]
    Io { op: String, source: std::io::Error },
    #[error("{0}")]
    Operator(String),
    #[error("{0}")]
    Unsupported(String),
}
