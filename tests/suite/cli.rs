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
    // A build without the V4L2 backend plans the capture but cannot run it (tests/suite/v4l2.rs).
    assert_eq!(
        o.status.success(),
        glint::devices::V4L2_BUILT,
        "{}",
        text(&o.stderr)
    );
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
    if glint::devices::V4L2_BUILT {
        // No camera at /dev/video0 on a test machine, or no lamp: refused all the same.
        assert!(e.contains("opening the rig's devices"), "{e}");
    } else {
        assert!(
            e.contains("camera.backend = \"v4l2\" (/dev/video0): this Glint was built without the V4L2 backend; rebuild with `cargo build --release --features v4l2` (needs libclang-dev)"),
            "{e}"
        );
    }
    assert!(!std::path::Path::new("/nonexistent/never").exists());
}

/// The small mock rig with a bracket of 5- and 10-minute exposures, 100 frames each: a
/// plan of about 1 d 3 h.
fn day_long_table() -> toml::Table {
    let mut t = small_table();
    set(&mut t, "camera.max_exposure_us", 600_000_000);
    set(&mut t, "camera.frame_timeout_ms", 700_000);
    set(
        &mut t,
        "bracket.exposures_us",
        toml::Value::try_from(vec![300_000_000, 600_000_000]).unwrap(),
    );
    set(&mut t, "bracket.frames_per_exposure", 100);
    t
}

#[test]
fn day_long_plan_is_refused_by_the_dry_run() {
    let dir = tempdir();
    let rig = load(dir.path(), &day_long_table());
    let o = glint(&["capture", "--rig", rig.path.to_str().unwrap(), "--dry-run"]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o.stdout));
    let s = text(&o.stdout);
    assert!(s.contains("about 1 d 3 h;"), "{s}");
    let problems: Vec<&str> = s.lines().filter(|l| l.starts_with("problem:")).collect();
    assert_eq!(problems.len(), 1, "{s}");
    assert!(
        problems[0].contains("would take about 1 d 3 h, more than a day")
            && problems[0].contains("bracket.exposures_us"),
        "{s}"
    );
}

#[test]
fn day_long_plan_is_refused_by_capture_before_opening_devices() {
    let dir = tempdir();
    let rig = load(dir.path(), &day_long_table());
    let out = dir.path().join("s");
    let o = glint(&[
        "capture",
        "--rig",
        rig.path.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let e = super::util::err(&o);
    assert!(
        e.contains("the capture plan cannot run") && e.contains("more than a day"),
        "{e}"
    );
    assert!(!out.exists(), "nothing is written for a refused plan");
    // `glint run` refuses it the same way, before it opens a device.
    let e = super::util::err(&glint(&[
        "run",
        "--rig",
        rig.path.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]));
    assert!(
        e.contains("the capture plan cannot run") && e.contains("more than a day"),
        "{e}"
    );
    assert!(!out.exists(), "nothing is written for a refused plan");
    // The library's capture refuses it too, before the session is created.
    let devices = glint::devices::open(&rig).unwrap();
    let r = glint::capture::record(&rig, devices, &out, Default::default(), &mut |_| {});
    let e = r.err().expect("refused").to_string();
    assert!(e.contains("more than a day"), "{e}");
    assert!(!out.exists());
}

/// Free bytes at `p` by statvfs.
fn free_bytes(p: &std::path::Path) -> u64 {
    let c = std::ffi::CString::new(p.as_os_str().as_encoded_bytes()).unwrap();
    let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
    assert_eq!(unsafe { libc::statvfs(c.as_ptr(), &mut st) }, 0);
    st.f_bavail as u64 * st.f_frsize as u64
}

#[test]
fn plan_bigger_than_the_free_disk_is_refused_by_the_dry_run() {
    // 16384x16384 16-bit RGB frames (1.6 GB each), 100 per exposure and 100 dark: 2.4 TB.
    let dir = tempdir();
    let mut t = small_table();
    set(&mut t, "camera.width", 16384);
    set(&mut t, "camera.height", 16384);
    set(&mut t, "camera.bit_depth", 16);
    set(&mut t, "bracket.frames_per_exposure", 100);
    set(&mut t, "bracket.dark_frames_per_exposure", 100);
    set(&mut t, "bracket.grid_frames", 100);
    let rig = load(dir.path(), &t);
    let need = 1500u64 * 16384 * 16384 * 6;
    let free = free_bytes(dir.path());
    if free >= need {
        eprintln!(
            "SKIPPED: {} has {free} bytes free, more than the {need} this plan needs",
            dir.path().display()
        );
        return;
    }
    let out = dir.path().join("s");
    let o = glint(&[
        "capture",
        "--rig",
        rig.path.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--dry-run",
    ]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o.stdout));
    let s = text(&o.stdout);
    let problems: Vec<&str> = s.lines().filter(|l| l.starts_with("problem:")).collect();
    assert_eq!(problems.len(), 1, "{s}");
    let p = problems[0];
    assert!(
        p.contains("the session needs up to 2.4 TB on disk")
            && p.contains("1500 frames of 16384x16384 at 16 bits")
            && p.contains(&format!(
                "but {} has",
                dir.path().canonicalize().unwrap().display()
            ))
            && p.contains("free"),
        "{p}"
    );
    assert!(!out.exists());
    // The same plan written where there is room passes: the free disk is what decides.
    let mut t2 = t.clone();
    set(&mut t2, "camera.width", 160);
    set(&mut t2, "camera.height", 120);
    let rig = load(dir.path(), &t2);
    let o = glint(&[
        "capture",
        "--rig",
        rig.path.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--dry-run",
        "--json",
    ]);
    assert!(o.status.success(), "{}", text(&o.stdout));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(
        j["disk"]["path"],
        dir.path().canonicalize().unwrap().to_str().unwrap()
    );
    assert!(j["disk"]["free_bytes"].as_u64().unwrap() > 0);
}

#[test]
fn dry_run_prints_times_as_people_read_them() {
    let dir = tempdir();
    let mut t = small_table();
    set(&mut t, "lamp.warmup_ms", 200_000);
    let rig = load(dir.path(), &t);
    let o = glint(&["capture", "--rig", rig.path.to_str().unwrap(), "--dry-run"]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let s = text(&o.stdout);
    assert!(s.contains("lamp warm-up 3 min 20 s"), "{s}");
    // Two warm-ups of 200 s and about 2.4 s of frames.
    assert!(s.contains("; about 6 min 42 s;"), "{s}");
    let o = glint(&["capture", "--rig", "rigs/mock.toml", "--dry-run"]);
    let s = text(&o.stdout);
    assert!(
        s.contains("lamp warm-up 250 ms") && s.contains("; about 3.0 s;"),
        "{s}"
    );
}

/// A tmpfs of `mb` MB mounted on a fresh folder, unmounted when dropped; None (and a
/// SKIPPED line) where mounting is not allowed.
struct Tmpfs {
    dir: tempfile::TempDir,
}

impl Tmpfs {
    fn mount(mb: u32) -> Option<Tmpfs> {
        let dir = tempdir();
        let o = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={mb}m"), "tmpfs"])
            .arg(dir.path())
            .output();
        match o {
            Ok(o) if o.status.success() => Some(Tmpfs { dir }),
            Ok(o) => {
                eprintln!(
                    "SKIPPED: cannot mount a tmpfs here ({})",
                    text(&o.stderr).trim()
                );
                None
            }
            Err(e) => {
                eprintln!("SKIPPED: cannot run mount ({e})");
                None
            }
        }
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(self.dir.path()).status();
    }
}

#[test]
fn plan_bigger_than_a_12_mb_tmpfs_is_refused_before_capturing() {
    let Some(fs) = Tmpfs::mount(12) else { return };
    let out = fs.dir.path().join("session");
    // The shipped mock rig keeps 15 frames of 1280x960: up to 55.4 MB.
    let o = glint(&[
        "capture",
        "--rig",
        "rigs/mock.toml",
        "--out",
        out.to_str().unwrap(),
        "--dry-run",
    ]);
    assert_eq!(o.status.code(), Some(1));
    let s = text(&o.stdout);
    assert!(
        s.contains("problem: the session needs up to 55.4 MB on disk")
            && s.contains("has 12.6 MB free"),
        "{s}"
    );
    let o = glint(&[
        "capture",
        "--rig",
        "rigs/mock.toml",
        "--out",
        out.to_str().unwrap(),
    ]);
    let e = super::util::err(&o);
    assert!(
        e.contains("the capture plan cannot run: the session needs up to 55.4 MB"),
        "{e}"
    );
    assert_eq!(
        std::fs::read_dir(fs.dir.path()).unwrap().count(),
        0,
        "nothing is written"
    );
}

/// No part of an error line says the same thing twice: its `: `-separated parts are
/// all different (before, a missing rig printed "…: No such file or directory (os error
/// 2): No such file or directory (os error 2)": a message that names its cause, printed
/// with that cause again from its error chain).
fn said_once(e: &str) {
    let parts: Vec<&str> = e.split(": ").filter(|p| p.len() > 8).collect();
    for (i, p) in parts.iter().enumerate() {
        assert!(!parts[..i].contains(p), "`{p}` twice in: {e}");
    }
}

/// A cause is printed once, whatever the command: a missing rig, a folder given as a rig
/// (with every command that takes one), a missing session.
#[test]
fn an_error_names_its_cause_once() {
    let dir = tempdir();
    let folder = dir.path().to_str().unwrap();
    let missing = dir.path().join("no-such-rig.toml");
    let missing = missing.to_str().unwrap();
    let out = dir.path().join("s");
    let out = out.to_str().unwrap();
    for (rig, cause) in [
        (missing, "No such file or directory"),
        (folder, "is not a regular file"),
    ] {
        for args in [
            vec!["run", "--rig", rig, "--out", out],
            vec!["capture", "--rig", rig, "--dry-run"],
            vec!["lens", "--rig", rig, "--dry-run"],
            vec!["daemon", "--rig", rig],
            vec!["bench", "fit", "--rig", rig],
            vec!["bench", "capture", "--rig", rig],
            vec!["import", folder, "--rig", rig, "--out", out],
        ] {
            let e = super::util::err(&glint(&args));
            assert_eq!(e.matches(cause).count(), 1, "{args:?}: {e}");
            said_once(&e);
        }
    }
    for args in [
        vec!["hdr", missing],
        vec!["calibrate", missing],
        vec!["fit", missing],
        vec!["report", folder],
        vec!["session", "verify", missing],
    ] {
        let o = glint(&args);
        assert!(!o.status.success(), "{args:?}");
        for line in text(&o.stderr).lines().chain(text(&o.stdout).lines()) {
            said_once(line);
        }
    }
}

/// `glint bench fit` from outside the repository: the default rig is the source tree's
/// rigs/mock.toml (before: "cannot read rig file rigs/mock.toml: No such file …" twice),
/// and a --rig that is not there is named once.
#[test]
fn bench_fit_runs_from_outside_the_repository() {
    let dir = tempdir();
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_glint"))
        .args([
            "bench",
            "fit",
            "--sessions",
            "1",
            "--repeats",
            "1",
            "--seeds",
            "1",
            "--out",
            "b",
        ])
        .current_dir(dir.path())
        .output()
        .unwrap();
    let e = text(&o.stderr);
    assert!(o.status.success(), "{e}");
    let rig = root().join("rigs/mock.toml");
    assert!(
        e.contains(&format!("the simulated tile of {}", rig.display())),
        "{e}"
    );
    assert!(dir.path().join("b/fit_bench.csv").is_file());
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_glint"))
        .args(["bench", "fit", "--rig", "rigs/mock.toml"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    let e = super::util::err(&o);
    assert!(
        e.contains("cannot read rig file rigs/mock.toml: No such file or directory"),
        "{e}"
    );
    said_once(&e);
}
