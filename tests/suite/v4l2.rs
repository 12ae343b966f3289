//! The V4L2 backend from the outside: what a build without it says about a V4L2 rig, the
//! exposure-step warnings of the dry run, and (with `--features v4l2`) captures through
//! `glint-mock v4l2`, which makes a path behave as a V4L2 camera.

use std::process::Command;

use glint::devices::{self, v4l2_rules};
use glint::rig;

use super::util::root;

fn glint(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_glint"))
        .args(args)
        .current_dir(root())
        .output()
        .expect("glint runs")
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// rigs/lab-example.toml with its bracket's 300 µs exposure at 250 µs (off the 100 µs grid)
/// and the grid photo at 12_345 µs, in `dir`.
fn off_grid_rig(dir: &std::path::Path) -> std::path::PathBuf {
    let text = std::fs::read_to_string(root().join("rigs/lab-example.toml")).unwrap();
    let mut t: toml::Table = toml::from_str(&text).unwrap();
    super::util::set(
        &mut t,
        "bracket.exposures_us",
        toml::Value::Array(
            [100, 250, 1000, 3000, 10000, 30000, 100000]
                .into_iter()
                .map(toml::Value::from)
                .collect(),
        ),
    );
    super::util::set(&mut t, "bracket.grid_exposure_us", 12_345);
    let p = dir.join("off-grid.toml");
    std::fs::write(&p, toml::to_string(&t).unwrap()).unwrap();
    p
}

#[test]
fn exposures_off_the_100_us_grid_are_named_with_what_they_snap_to() {
    let dir = tempfile::tempdir().unwrap();
    let l = rig::load(&off_grid_rig(dir.path())).unwrap();
    let w = v4l2_rules::exposure_snap_warnings(&l.rig);
    assert_eq!(w.len(), 2, "{w:?}");
    assert!(
        w[0].contains("250 µs") && w[0].contains("will take 300 µs"),
        "{w:?}"
    );
    assert!(w[1].contains("grid_exposure_us: 12345 µs") && w[1].contains("will take 12300 µs"));
    // The simulated camera has no such steps.
    let mock = rig::load(&root().join("rigs/mock.toml")).unwrap();
    assert!(v4l2_rules::exposure_snap_warnings(&mock.rig).is_empty());
    assert_eq!(devices::check_backends(&mock.rig), Default::default());
}

#[cfg(not(feature = "v4l2"))]
const MISSING: &str = "this Glint was built without the V4L2 backend; rebuild with `cargo build --release --features v4l2` (needs libclang-dev)";

#[cfg(not(feature = "v4l2"))]
#[test]
fn a_build_without_the_backend_refuses_v4l2_rigs_in_rig_check_and_dry_runs() {
    let o = glint(&["rig", "check", "rigs/lab-example.toml"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(text(&o.stdout).contains(MISSING), "{}", text(&o.stdout));
    let o = glint(&["rig", "check", "rigs/lab-example.toml", "--json"]);
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["ok"], false);
    assert!(j["problems"][0].as_str().unwrap().contains(MISSING));
    for cmd in ["capture", "run"] {
        let o = glint(&[cmd, "--rig", "rigs/lab-example.toml", "--dry-run"]);
        assert_eq!(o.status.code(), Some(1), "{cmd}");
        let s = text(&o.stdout);
        assert!(s.contains("Plan for rig `lab-bench-1`"), "{cmd}: {s}");
        assert!(
            s.contains(&format!("problem: camera.backend = \"v4l2\": {MISSING}")),
            "{cmd}: {s}"
        );
    }
    // The mock rig is unaffected.
    let o = glint(&["rig", "check", "rigs/mock.toml"]);
    assert!(o.status.success(), "{}", text(&o.stdout));
    // `glint devices` lists serial ports and says how to get cameras.
    let o = glint(&["devices"]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    assert!(text(&o.stdout).contains(&format!("Cameras (V4L2): not listed: {MISSING}")));
    let o = glint(&["devices", "--json"]);
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["v4l2_built"], false);
    assert!(j["serial_ports"].is_array());
}

#[cfg(feature = "v4l2")]
#[test]
fn the_dry_run_warns_about_exposures_off_the_100_us_grid() {
    let dir = tempfile::tempdir().unwrap();
    let rig = off_grid_rig(dir.path());
    let rig = rig.to_str().unwrap();
    let o = glint(&["capture", "--rig", rig, "--dry-run"]);
    assert!(o.status.success(), "{}", text(&o.stdout));
    let s = text(&o.stdout);
    assert!(
        s.contains("warning: bracket.exposures_us: 250 µs is not a whole number of V4L2's 100 µs exposure_time_absolute steps; the camera will take 300 µs"),
        "{s}"
    );
    let o = glint(&["rig", "check", rig, "--json"]);
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["ok"], true);
    assert_eq!(j["warnings"].as_array().unwrap().len(), 2);
}

#[cfg(feature = "v4l2")]
#[test]
fn devices_describes_a_missing_path_and_exits_1() {
    let o = glint(&["devices", "/dev/video-glint-test-none", "--json"]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["v4l2_built"], true);
    assert!(j["cameras"][0]["error"]
        .as_str()
        .unwrap()
        .contains("no such device"));
}
