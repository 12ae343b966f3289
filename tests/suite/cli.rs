//! The command line, as a user runs it.

use std::process::Command;

use glint::capture::FrameKind;
use glint::session::{self, State};

use super::util::{load, root, set, small_table, tempdir};

fn glint(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_glint"))
        .args(args)
        .current_dir(root())
        .output()
        .unwrap()
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// The README's dry run: the shipped mock rig at full size, then `session verify`.
#[test]
fn capture_of_the_default_mock_rig_is_complete_and_verifies() {
    let dir = tempdir();
    let out = dir.path().join("session");
    let o = glint(&[
        "capture",
        "--rig",
        "rigs/mock.toml",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    assert!(
        text(&o.stdout).contains("complete: 7 tile, 7 dark, 1 grid frames"),
        "{}",
        text(&o.stdout)
    );
    let m = session::load(&out).unwrap();
    assert_eq!(m.state, State::Complete);
    let mut exposures: Vec<u32> = m
        .frames
        .iter()
        .filter(|f| f.kind == FrameKind::Tile)
        .map(|f| f.exposure_reported_us)
        .collect();
    exposures.dedup();
    assert!(exposures.len() >= 7);
    assert!((*exposures.last().unwrap() as f64 / exposures[0] as f64).log2() >= 6.0);
    assert!(
        m.frames.iter().any(|f| f.kind == FrameKind::Dark)
            && m.frames.iter().any(|f| f.kind == FrameKind::Grid)
    );
    let v = glint(&["session", "verify", out.to_str().unwrap()]);
    assert!(v.status.success());
    assert!(
        text(&v.stdout).contains("15 frames, state complete, all checksums match"),
        "{}",
        text(&v.stdout)
    );
}

#[test]
fn json_output_for_scripts() {
    let dir = tempdir();
    let rig = load(dir.path(), &small_table());
    let out = dir.path().join("s");
    let o = glint(&[
        "capture",
        "--rig",
        rig.path.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--json",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["state"], "complete");
    assert_eq!(j["frames"], 15);
    let v = glint(&["session", "verify", out.to_str().unwrap(), "--json"]);
    let j: serde_json::Value = serde_json::from_slice(&v.stdout).unwrap();
    assert_eq!(j["problems"].as_array().unwrap().len(), 0);
}

#[test]
fn a_fault_gives_one_line_a_nonzero_exit_and_a_failed_session() {
    let dir = tempdir();
    let mut t = small_table();
    set(&mut t, "mock.faults.stall_at_frame", 12);
    let rig = load(dir.path(), &t);
    let out = dir.path().join("s");
    let o = glint(&[
        "capture",
        "--rig",
        rig.path.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    let err = text(&o.stderr);
    let last: Vec<&str> = err.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(last.len(), 1, "{err}");
    assert!(
        last[0].contains("camera stalled")
            && last[0].contains("kept with")
            && last[0].contains("state failed"),
        "{}",
        last[0]
    );
    let v = glint(&["session", "verify", out.to_str().unwrap()]);
    assert!(
        v.status.success(),
        "a failed session is still intact: {}",
        text(&v.stdout)
    );
    assert!(text(&v.stdout).contains("state failed"));
}

#[test]
fn damaged_session_fails_verification() {
    let dir = tempdir();
    let rig = load(dir.path(), &small_table());
    let out = dir.path().join("s");
    assert!(glint(&[
        "capture",
        "--rig",
        rig.path.to_str().unwrap(),
        "--out",
        out.to_str().unwrap()
    ])
    .status
    .success());
    let m = session::load(&out).unwrap();
    std::fs::remove_file(out.join(&m.frames[4].file)).unwrap();
    let v = glint(&["session", "verify", out.to_str().unwrap()]);
    assert_eq!(v.status.code(), Some(1));
    assert!(text(&v.stdout).contains("DAMAGED"));
    let v = glint(&["session", "verify", dir.path().to_str().unwrap()]);
    assert!(
        text(&v.stderr).contains("has no manifest.json"),
        "{}",
        text(&v.stderr)
    );
}

#[test]
fn rig_check_lists_every_problem() {
    let o = glint(&["rig", "check", "rigs/mock.toml"]);
    assert!(o.status.success());
    assert!(text(&o.stdout).contains("ok (rig `mock`"));
    let dir = tempdir();
    let mut t = small_table();
    set(
        &mut t,
        "bracket.exposures_us",
        toml::Value::try_from(vec![500, 250]).unwrap(),
    );
    set(
        &mut t,
        "geometry.lamp_position_mm",
        toml::Value::try_from(vec![0.0, 0.0, 1.0]).unwrap(),
    );
    let path = dir.path().join("bad.toml");
    std::fs::write(&path, toml::to_string(&t).unwrap()).unwrap();
    let o = glint(&["rig", "check", path.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1));
    let out = text(&o.stdout);
    assert_eq!(out.lines().count(), 2, "{out}");
    assert!(
        out.contains("bad.toml: bracket.exposures_us: must increase strictly"),
        "{out}"
    );
    assert!(
        out.contains("bad.toml: geometry.lamp_position_mm: the lamp (z = 1 mm) must be above"),
        "{out}"
    );
}

#[test]
fn dry_run_plans_without_devices() {
    let o = glint(&["capture", "--rig", "rigs/lab-example.toml", "--dry-run"]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let s = text(&o.stdout);
    assert!(
        s.contains("Keeps 36 frames") && s.contains("operator: remove the tile"),
        "{s}"
    );
    let o = glint(&["capture", "--rig", "rigs/mock.toml", "--dry-run", "--json"]);
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["estimate"]["frames_kept"], 15);
}

#[test]
fn unsupported_hardware_is_named() {
    let o = glint(&[
        "capture",
        "--rig",
        "rigs/lab-example.toml",
        "--out",
        "/nonexistent/never",
    ]);
    assert_eq!(o.status.code(), Some(1));
    let e = text(&o.stderr);
    assert!(
        e.contains("camera.backend = \"v4l2\" (/dev/video0) is not built into this Glint yet"),
        "{e}"
    );
    assert!(!std::path::Path::new("/nonexistent/never").exists());
}
