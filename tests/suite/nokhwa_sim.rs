//! The nokhwa backend against the simulated camera at the V4L2 interface: `glint-mock v4l2`
//! makes a path a V4L2 capture device (its preload library, fed by the simulated lab), and
//! tests/with-dev-video.sh gives Glint a private /dev in which /dev/video0 is that path,
//! since nokhwa opens V4L2 cameras only as /dev/videoN. Every ioctl nokhwa (and the v4l
//! crate under it) issues goes to the simulated device.
//!
//! These need the launcher and the library built beside the test's `glint`
//! (`cargo build --workspace --features nokhwa`; `.ci/run` does it first), and root or
//! unprivileged user namespaces for the private /dev.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use super::sim_lab::{glint, launcher, manifest, text, verify, write_rig};
use super::util::{root, set, tempdir};

/// rigs/sim-nokhwa.toml at `width` x `height`, its devices in `dir/dev`, no warm-ups.
fn sim_table(dir: &Path, width: u32, height: u32) -> toml::Table {
    super::sim_lab::sim_table(dir, "sim-nokhwa.toml", width, height)
}

/// Run `glint ARGS` inside the simulated lab of `rig` (in `dir`), with /dev/video0 the
/// simulated camera when `dev_video` (frames as fast as the lab makes them).
fn under_lab(dir: &Path, rig: &Path, dev_video: bool, args: &[&str]) -> Output {
    let mut c = Command::new(launcher());
    c.args(["v4l2", "--fast", "--rig"]).arg(rig).arg("--");
    if dev_video {
        c.arg(root().join("tests/with-dev-video.sh"))
            .arg(dir.join("dev/video0"))
            .arg("0");
    }
    c.arg(glint()).args(args).output().unwrap()
}

/// `glint capture` of `t` through nokhwa: its output and the session folder.
fn capture(dir: &Path, t: &toml::Table) -> (Output, PathBuf) {
    let rig = write_rig(dir, t);
    let session = dir.join("s");
    let o = under_lab(
        dir,
        &rig,
        true,
        &[
            "capture",
            "--rig",
            rig.to_str().unwrap(),
            "--out",
            session.to_str().unwrap(),
        ],
    );
    (o, session)
}

/// The nokhwa backend's demonstration: a whole `glint run` through nokhwa at 320x240 (CI also
/// runs the shipped rig at full size): the tile's model and n come out, and the manifest
/// says nokhwa drove the camera, with the controls read back.
#[test]
fn run_through_nokhwa_finds_the_tile() {
    let dir = tempdir();
    let t = sim_table(dir.path(), 320, 240);
    let rig = write_rig(dir.path(), &t);
    let session = dir.path().join("s");
    let o = under_lab(
        dir.path(),
        &rig,
        true,
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
    eprintln!("through nokhwa at 320x240: {chosen}, n = {n:.2} (truth 120)");
    assert!((n / 120.0 - 1.0).abs() < 0.05, "n = {n}");
    let m = manifest(&session);
    assert_eq!(m["state"], "complete");
    let cam = &m["camera"];
    assert_eq!(cam["backend"], "nokhwa", "{cam}");
    assert_eq!(cam["pixel_format"], "YUYV");
    assert!(
        cam["device"].as_str().unwrap().ends_with("(/dev/video0)"),
        "{cam}"
    );
    let controls = cam["controls"].as_array().unwrap();
    let value = |name: &str| {
        controls
            .iter()
            .find(|c| c["name"] == name)
            .unwrap_or_else(|| panic!("{name} not recorded: {controls:?}"))["value"]
            .as_i64()
            .unwrap()
    };
    assert_eq!(value("auto_exposure"), 1, "manual exposure");
    assert_eq!(value("gain_automatic"), 0);
    assert!(value("exposure_time_absolute") >= 1);
    assert!(
        cam["notes"]
            .to_string()
            .contains("dropped frame cannot be detected"),
        "{cam}"
    );
    let frames = m["frames"].as_array().unwrap();
    let how: std::collections::BTreeSet<&str> = frames
        .iter()
        .map(|f| f["exposure_verified_by"].as_str().unwrap())
        .collect();
    assert!(
        !how.contains("settle-timeout"),
        "every exposure verified from the images: {how:?}"
    );
    assert!(frames.iter().all(|f| f["device_timestamp_us"].is_null()));
    verify(&session);
}

/// A camera that stops delivering is a stall after the frame timeout, not a hang: nokhwa's
/// own wait has no limit, and is left blocked on its thread.
#[test]
fn camera_that_stops_delivering_is_a_stall_not_a_hang() {
    let dir = tempdir();
    let mut t = sim_table(dir.path(), 160, 120);
    set(&mut t, "camera.frame_timeout_ms", 1000);
    set(&mut t, "mock.faults.stall_at_frame", 30);
    let start = std::time::Instant::now();
    let (o, session) = capture(dir.path(), &t);
    assert!(!o.status.success(), "the capture should fail: {}", text(&o));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("camera stalled: no frame within 1000 ms"),
        "{err}"
    );
    assert!(start.elapsed().as_secs() < 60, "{:?}", start.elapsed());
    let m = manifest(&session);
    assert_eq!(m["state"], "failed");
    verify(&session);
}

#[test]
fn unplugged_camera_is_a_clear_error() {
    let dir = tempdir();
    let mut t = sim_table(dir.path(), 160, 120);
    set(&mut t, "camera.frame_timeout_ms", 1000);
    set(&mut t, "mock.faults.unplug_at_frame", 30);
    let (o, session) = capture(dir.path(), &t);
    assert!(!o.status.success(), "the capture should fail: {}", text(&o));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("unplugged"), "{err}");
    assert_eq!(manifest(&session)["state"], "failed");
    verify(&session);
}

/// What nokhwa does not allow, pinned: a frame the camera drops leaves no gap in the
/// numbering (nokhwa passes no sequence numbers), so the capture goes on where the V4L2
/// backend stops (`v4l2_sim::dropped_frame_is_a_sequence_gap`).
#[test]
fn a_dropped_frame_goes_unseen_through_nokhwa() {
    let dir = tempdir();
    let mut t = sim_table(dir.path(), 160, 120);
    set(
        &mut t,
        "mock.faults.drop_frames",
        toml::Value::try_from(vec![30]).unwrap(),
    );
    let (o, session) = capture(dir.path(), &t);
    assert!(o.status.success(), "{}", text(&o));
    assert!(!String::from_utf8_lossy(&o.stderr).contains("dropped"));
    let m = manifest(&session);
    let seq: Vec<u64> = m["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["sequence"].as_u64().unwrap())
        .collect();
    assert!(seq.windows(2).all(|w| w[0] < w[1]), "{seq:?}");
    verify(&session);
}

/// The rig's device as a path that is no /dev/videoN (no private /dev): refused on one line
/// that says what nokhwa needs.
#[test]
fn a_path_that_is_no_dev_video_is_refused() {
    let dir = tempdir();
    let t = sim_table(dir.path(), 160, 120);
    let rig = write_rig(dir.path(), &t);
    let session = dir.path().join("s");
    let o = under_lab(
        dir.path(),
        &rig,
        false,
        &[
            "capture",
            "--rig",
            rig.to_str().unwrap(),
            "--out",
            session.to_str().unwrap(),
        ],
    );
    assert!(!o.status.success(), "{}", text(&o));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("nokhwa opens V4L2 cameras only as /dev/videoN"),
        "{err}"
    );
}
