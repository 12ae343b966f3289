//! The V4L2 backend against the simulated camera at the V4L2 interface: `glint-mock v4l2`
//! runs Glint with the preload library that makes a path a V4L2 capture device, fed by the
//! simulated lab (its own physics), with the lamp on the lab firmware's pseudo-terminal and
//! the tile moved by the rig's `[operator]` commands. Every ioctl of the real backend runs.
//!
//! These need the launcher and the library built beside the test's `glint`:
//! `cargo build --workspace --features v4l2` (`.ci/run` does it first).

use std::path::Path;
use std::process::{Command, Output};

use super::sim_lab::{glint, launcher, manifest, sim_table, text, verify, write_rig};
use super::util::{set, tempdir};

/// Run `glint ARGS` inside the simulated lab of `rig` (frames as fast as the lab makes them).
fn under_lab(rig: &Path, args: &[&str]) -> Output {
    Command::new(launcher())
        .args(["v4l2", "--fast", "--rig"])
        .arg(rig)
        .arg("--")
        .arg(glint())
        .args(args)
        .output()
        .unwrap()
}

/// `glint capture --rig RIG --out SESSION` inside the simulated lab.
fn capture_under_lab(rig: &Path, session: &Path) -> Output {
    under_lab(
        rig,
        &[
            "capture",
            "--rig",
            rig.to_str().unwrap(),
            "--out",
            session.to_str().unwrap(),
        ],
    )
}

/// Capture with one `[mock.faults]` entry; the capture must fail on one line, the session
/// end `failed` and verify, with the frames before the fault kept.
fn faulty_capture(key: &str, value: toml::Value) -> (String, serde_json::Value) {
    let dir = tempdir();
    let mut t = sim_table(dir.path(), "sim-v4l2.toml", 160, 120);
    set(&mut t, "camera.frame_timeout_ms", 1000);
    set(&mut t, &format!("mock.faults.{key}"), value);
    let rig = write_rig(dir.path(), &t);
    let session = dir.path().join("s");
    let o = capture_under_lab(&rig, &session);
    assert!(!o.status.success(), "the capture should fail: {}", text(&o));
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    let m = manifest(&session);
    assert_eq!(m["state"], "failed", "{}", text(&o));
    assert!(
        m["frames"].as_array().unwrap().len() >= 2,
        "frames before the fault are kept: {m}"
    );
    verify(&session);
    (err, m)
}

#[test]
fn dropped_frame_is_a_sequence_gap() {
    let (e, m) = faulty_capture("drop_frames", toml::Value::try_from(vec![30]).unwrap());
    assert!(e.contains("camera dropped 1 frame(s)"), "{e}");
    assert!(m["failure"].as_str().unwrap().contains("dropped"), "{m}");
}

#[test]
fn buffer_flagged_erroneous_is_a_corrupt_frame() {
    let (e, _) = faulty_capture("corrupt_frames", toml::Value::try_from(vec![30]).unwrap());
    assert!(e.contains("corrupt"), "{e}");
}

#[test]
fn camera_that_stops_delivering_is_a_stall() {
    let (e, _) = faulty_capture("stall_at_frame", toml::Value::Integer(30));
    assert!(e.contains("camera stalled: no frame within 1000 ms"), "{e}");
}

#[test]
fn unplugged_camera_is_a_clear_error() {
    let (e, _) = faulty_capture("unplug_at_frame", toml::Value::Integer(30));
    assert!(e.contains("unplugged"), "{e}");
}

#[test]
fn glint_devices_lists_the_simulated_camera() {
    let dir = tempdir();
    let t = sim_table(dir.path(), "sim-v4l2.toml", 320, 240);
    let rig = write_rig(dir.path(), &t);
    let dev = dir.path().join("dev/video0");
    let o = under_lab(&rig, &["devices", dev.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    for want in [
        "Glint Simulated Camera",
        "YUYV",
        "RGB3",
        "MJPG",
        "320x240",
        "exposure_time_absolute",
        "auto_exposure",
        "gain",
    ] {
        assert!(out.contains(want), "`{want}` missing from:\n{out}");
    }
    let o = under_lab(&rig, &["devices", "--json", dev.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let _: serde_json::Value = serde_json::from_slice(&o.stdout)
        .unwrap_or_else(|e| panic!("not JSON ({e}): {}", text(&o)));
    // Through its stable name, as a rig should name a real camera.
    let by_id = dir
        .path()
        .join("dev/v4l/by-id/usb-Glint_Simulated_Camera_0001-video-index0");
    let o = under_lab(&rig, &["devices", by_id.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("Glint Simulated Camera"));
    // A monochrome camera offers the luma formats.
    let dir = tempdir();
    let t = sim_table(dir.path(), "sim-v4l2-mono.toml", 320, 240);
    let rig = write_rig(dir.path(), &t);
    let dev = dir.path().join("dev/video0");
    let o = under_lab(&rig, &["devices", dev.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    for want in ["GREY", "Y16", "Y10", "Y12"] {
        assert!(out.contains(want), "`{want}` missing from:\n{out}");
    }
}

/// A whole run through the V4L2 backend at 320x240 (CI also runs the shipped rigs at full
/// size): the tile's model and n come out, the manifest says what the device did.
fn run_small(file: &str) -> serde_json::Value {
    let dir = tempdir();
    let t = sim_table(dir.path(), file, 320, 240);
    let rig = write_rig(dir.path(), &t);
    let session = dir.path().join("s");
    let o = under_lab(
        &rig,
        &[
            "run",
            "--rig",
            rig.to_str().unwrap(),
            "--out",
            session.to_str().unwrap(),
            "--json",
        ],
    );
    assert!(o.status.success(), "{}", text(&o));
    let s: serde_json::Value = serde_json::from_slice(&o.stdout)
        .unwrap_or_else(|e| panic!("not JSON ({e}): {}", text(&o)));
    let chosen = s["fit"]["chosen"].as_str().unwrap();
    assert_eq!(chosen, "blinn-phong", "{s}");
    let n = s["fit"]["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["model"] == chosen)
        .unwrap()["n"]["value"]
        .as_f64()
        .unwrap();
    assert!((n / 120.0 - 1.0).abs() < 0.05, "n = {n}");
    let m = manifest(&session);
    assert_eq!(m["state"], "complete");
    assert_eq!(m["camera"]["backend"], "v4l2", "{}", m["camera"]);
    let controls = m["camera"]["controls"].as_array().unwrap();
    let value = |name: &str| {
        controls
            .iter()
            .find(|c| c["name"] == name)
            .unwrap_or_else(|| panic!("{name} not recorded: {controls:?}"))["value"]
            .as_i64()
            .unwrap()
    };
    // uvcvideo calls it `auto_exposure` (kernels before 5.x: `exposure_auto`).
    let auto = controls
        .iter()
        .find(|c| c["name"] == "auto_exposure" || c["name"] == "exposure_auto")
        .unwrap_or_else(|| panic!("auto exposure not recorded: {controls:?}"));
    assert_eq!(auto["value"], 1, "manual exposure: {auto}");
    assert!(value("exposure_time_absolute") >= 1);
    let how: std::collections::BTreeSet<&str> = m["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["exposure_verified_by"].as_str().unwrap())
        .collect();
    assert!(
        !how.contains("settle-timeout"),
        "every exposure verified: {how:?}"
    );
    verify(&session);
    m
}

#[test]
fn run_through_v4l2_yuyv_finds_the_tile() {
    let m = run_small("sim-v4l2.toml");
    assert_eq!(m["camera"]["pixel_format"], "YUYV");
    assert_eq!(m["camera"]["channels"], 3);
}

#[test]
fn run_through_v4l2_mono_y16_finds_the_tile() {
    let m = run_small("sim-v4l2-mono.toml");
    assert_eq!(m["camera"]["pixel_format"], "Y16");
    assert_eq!(m["camera"]["channels"], 1);
}

/// The manifest records what the device applied: an exposure off V4L2's 100 µs steps is
/// snapped (and recorded as applied), a control the rig names is set and read back, and a
/// control the camera lacks stops the capture before any frame, or is a warning when the
/// rig says so.
#[test]
fn the_manifest_records_what_the_device_applied() {
    let dir = tempdir();
    let mut t = sim_table(dir.path(), "sim-v4l2.toml", 160, 120);
    set(
        &mut t,
        "bracket.exposures_us",
        toml::Value::try_from(vec![100, 250, 400, 800, 1600, 3200, 6400]).unwrap(),
    );
    set(&mut t, "camera.controls.gain", 7);
    let rig = write_rig(dir.path(), &t);
    let session = dir.path().join("s");
    let o = capture_under_lab(&rig, &session);
    assert!(o.status.success(), "{}", text(&o));
    let m = manifest(&session);
    let frames = m["frames"].as_array().unwrap();
    let f = frames
        .iter()
        .find(|f| f["exposure_requested_us"] == 250)
        .unwrap_or_else(|| panic!("no frame at 250 µs: {m}"));
    let applied = f["exposure_reported_us"].as_u64().unwrap();
    assert!(applied == 200 || applied == 300, "{f}");
    let controls = m["camera"]["controls"].as_array().unwrap();
    let gain = controls.iter().find(|c| c["name"] == "gain").unwrap();
    assert_eq!(
        (gain["requested"].as_i64(), gain["value"].as_i64()),
        (Some(7), Some(7))
    );
    verify(&session);

    // A control the camera does not have.
    set(&mut t, "camera.controls.zoom_absolute", 3);
    let rig = write_rig(dir.path(), &t);
    let session = dir.path().join("s2");
    let o = capture_under_lab(&rig, &session);
    assert!(!o.status.success(), "{}", text(&o));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("zoom_absolute"), "{err}");
    set(&mut t, "camera.missing_control", "warn");
    let rig = write_rig(dir.path(), &t);
    let session = dir.path().join("s3");
    let o = capture_under_lab(&rig, &session);
    assert!(o.status.success(), "{}", text(&o));
    assert!(manifest(&session)["camera"]
        .to_string()
        .contains("zoom_absolute"));
}
