//! V4L2 conventions that need no device and no bindings, so they are compiled (and tested)
//! in every build: control names as `v4l2-ctl` prints them, the standard controls Glint
//! sets, and how an exposure in µs lands on `exposure_time_absolute`'s 100 µs steps.
//!
//! The dry run uses these to warn about exposures the camera cannot take exactly, before
//! any device is opened; the backend ([`super::v4l2`]) uses the same functions once it
//! knows the control's range.

use crate::rig::{CameraBackend, Rig};

/// The unit of `exposure_time_absolute`, µs.
pub const EXPOSURE_UNIT_US: u32 = 100;

/// Control ids of videodev2.h / v4l2-controls.h (stable kernel ABI).
pub mod cid {
    const USER_BASE: u32 = 0x0098_0900;
    const CAMERA_BASE: u32 = 0x009a_0900;
    pub const AUTO_WHITE_BALANCE: u32 = USER_BASE + 12;
    pub const AUTOGAIN: u32 = USER_BASE + 18;
    pub const GAIN: u32 = USER_BASE + 19;
    pub const BACKLIGHT_COMPENSATION: u32 = USER_BASE + 28;
    /// Menu: 0 auto, 1 manual, 2 shutter priority, 3 aperture priority.
    pub const EXPOSURE_AUTO: u32 = CAMERA_BASE + 1;
    /// 100 µs units.
    pub const EXPOSURE_ABSOLUTE: u32 = CAMERA_BASE + 2;
    /// "Exposure, Dynamic Framerate" (older kernels: "Exposure, Auto Priority").
    pub const EXPOSURE_AUTO_PRIORITY: u32 = CAMERA_BASE + 3;
}

/// `exposure_auto`'s manual mode.
pub const EXPOSURE_MANUAL: i64 = 1;

/// The automatic controls Glint switches off before capturing, in order, with the value
/// that switches each off and its names (today's kernel name first; older kernels' after).
/// `exposure_time_absolute` is written again after `exposure_auto` (some cameras drop the
/// value on the switch). A camera without one of these is warned about, not refused.
pub const STANDARD_CONTROLS: [(u32, i64, &[&str]); 5] = [
    (
        cid::EXPOSURE_AUTO,
        EXPOSURE_MANUAL,
        &["auto_exposure", "exposure_auto"],
    ),
    (cid::AUTOGAIN, 0, &["gain_automatic", "autogain"]),
    (
        cid::AUTO_WHITE_BALANCE,
        0,
        &["white_balance_automatic", "white_balance_temperature_auto"],
    ),
    (cid::BACKLIGHT_COMPENSATION, 0, &["backlight_compensation"]),
    (
        cid::EXPOSURE_AUTO_PRIORITY,
        0,
        &["exposure_dynamic_framerate", "exposure_auto_priority"],
    ),
];

/// A control's name as `v4l2-ctl` prints it: the driver's name ("Exposure Time,
/// Absolute") lower-cased, every run of other characters one `_`, none at either end
/// (`exposure_time_absolute`).
pub fn control_name(driver_name: &str) -> String {
    let mut out = String::with_capacity(driver_name.len());
    let mut gap = false;
    for c in driver_name.chars() {
        if c.is_ascii_alphanumeric() {
            if gap && !out.is_empty() {
                out.push('_');
            }
            gap = false;
            out.push(c.to_ascii_lowercase());
        } else {
            gap = true;
        }
    }
    out
}

/// The control value (in 100 µs units) nearest `us` that `exposure_time_absolute` can
/// hold: `min + k·step`, within `min..=max` (ties round up).
pub fn exposure_units(us: u32, min: i64, max: i64, step: i64) -> i64 {
    let step = step.max(1);
    let min = min.max(0);
    // The largest reachable value: max itself may be off the step grid.
    let top = min + (max.max(min) - min) / step * step;
    let units = (us as i64 + EXPOSURE_UNIT_US as i64 / 2) / EXPOSURE_UNIT_US as i64;
    let k = (units - min + step / 2).div_euclid(step);
    (min + k * step).clamp(min, top)
}

/// The exposure (µs) the camera takes when asked for `us`, given
/// `exposure_time_absolute`'s `min`, `max` and `step` (in its 100 µs units).
pub fn snap_exposure_us(us: u32, min: i64, max: i64, step: i64) -> u32 {
    let units = exposure_units(us, min, max, step);
    (units.clamp(0, u32::MAX as i64 / EXPOSURE_UNIT_US as i64) as u32) * EXPOSURE_UNIT_US
}

/// The exposure (µs) a camera without per-frame exposure metadata is parked at before the
/// bracket: UVC frames carry no exposure, so the engine confirms each new exposure by the
/// change it makes in the image, and a first exposure equal to the parked one would show no
/// change to confirm. The longest of the bracket (or 4x the first) is two stops or more away.
pub fn park_exposure_us(rig: &Rig) -> u32 {
    let first_us = rig.bracket.exposures_us.first().copied().unwrap_or(10_000);
    let longest_us = rig
        .bracket
        .exposures_us
        .iter()
        .copied()
        .max()
        .unwrap_or(first_us);
    if longest_us >= first_us.saturating_mul(4) {
        longest_us
    } else {
        first_us.saturating_mul(4)
    }
}

/// Warnings for a V4L2 (or nokhwa) rig's exposures that are not whole 100 µs steps, naming what each
/// will snap to (the device's own range is not known before it is opened; it is applied
/// when the capture sets each exposure, and the manifest records what was read back).
pub fn exposure_snap_warnings(rig: &Rig) -> Vec<String> {
    // nokhwa on Linux sets the same control (see `super::nokhwa_cam`).
    if !matches!(
        rig.camera.backend,
        CameraBackend::V4l2 | CameraBackend::Nokhwa
    ) {
        return Vec::new();
    }
    let snap = |us: u32| snap_exposure_us(us, 1, i64::MAX / 2, 1);
    let mut out = Vec::new();
    for &us in &rig.bracket.exposures_us {
        if snap(us) != us {
            out.push(format!(
                "bracket.exposures_us: {us} µs is not a whole number of V4L2's 100 µs exposure_time_absolute steps; the camera will take {} µs",
                snap(us)
            ));
        }
    }
    let g = rig.bracket.grid_exposure_us;
    if snap(g) != g {
        out.push(format!(
            "bracket.grid_exposure_us: {g} µs is not a whole number of V4L2's 100 µs exposure_time_absolute steps; the camera will take {} µs",
            snap(g)
        ));
    }
    let mut seen = std::collections::BTreeMap::new();
    for &us in &rig.bracket.exposures_us {
        if let Some(other) = seen.insert(snap(us), us) {
            out.push(format!(
                "bracket.exposures_us: {other} µs and {us} µs both snap to {} µs, so the bracket repeats an exposure",
                snap(us)
            ));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn control_names_match_v4l2_ctl() {
        assert_eq!(
            control_name("Exposure Time, Absolute"),
            "exposure_time_absolute"
        );
        assert_eq!(
            control_name("White Balance, Automatic"),
            "white_balance_automatic"
        );
        assert_eq!(
            control_name("White Balance Temperature, Auto"),
            "white_balance_temperature_auto"
        );
        assert_eq!(
            control_name("Exposure, Dynamic Framerate"),
            "exposure_dynamic_framerate"
        );
        assert_eq!(control_name("  Gain (dB) "), "gain_db");
        assert_eq!(control_name("Power Line Frequency"), "power_line_frequency");
    }

    #[test]
    fn exposures_snap_to_100_us_steps_within_range() {
        // Whole steps stay.
        assert_eq!(snap_exposure_us(1000, 1, 5000, 1), 1000);
        // Nearest step, ties up.
        assert_eq!(snap_exposure_us(1249, 1, 5000, 1), 1200);
        assert_eq!(snap_exposure_us(1250, 1, 5000, 1), 1300);
        // Below the minimum and above the maximum: clamped.
        assert_eq!(snap_exposure_us(20, 3, 5000, 1), 300);
        assert_eq!(snap_exposure_us(0, 1, 5000, 1), 100);
        assert_eq!(snap_exposure_us(900_000, 1, 5000, 1), 500_000);
        // Coarser steps counted from the minimum: 3, 5, 7, ...
        assert_eq!(snap_exposure_us(600, 3, 5000, 2), 700);
        assert_eq!(snap_exposure_us(490, 3, 5000, 2), 500);
        // A maximum off the step grid: the largest reachable value below it.
        assert_eq!(snap_exposure_us(10_000, 3, 10, 2), 900);
        // A zero step (some drivers) behaves as 1.
        assert_eq!(snap_exposure_us(450, 1, 100, 0), 500);
        assert_eq!(exposure_units(1234, 1, 5000, 1), 12);
    }
}
