//! Helpers for tests that run Glint inside the simulated lab launched as hardware
//! (`glint-mock v4l2`, `glint-mock lamp`): the binaries, the simulated rigs at a test's size,
//! and the checks of a session.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

#[cfg(any(feature = "v4l2", feature = "nokhwa"))]
use super::util::{root, set};

pub fn glint() -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_glint"))
}

/// `glint-mock`, built into the same target folder as `glint`.
pub fn launcher() -> PathBuf {
    let p = glint().parent().unwrap().join("glint-mock");
    assert!(
        p.exists(),
        "{} is missing: build the workspace first (cargo build --workspace, with the features under test)",
        p.display()
    );
    p
}

/// rigs/FILE (a simulated camera rig) at `width` x `height`, its devices in `dir/dev`, no
/// warm-ups.
#[cfg(any(feature = "v4l2", feature = "nokhwa"))]
pub fn sim_table(dir: &Path, file: &str, width: u32, height: u32) -> toml::Table {
    let mut t: toml::Table =
        toml::from_str(&std::fs::read_to_string(root().join("rigs").join(file)).unwrap()).unwrap();
    let dev = dir.join("dev");
    set(
        &mut t,
        "camera.device",
        dev.join("video0").display().to_string(),
    );
    set(
        &mut t,
        "lamp.port",
        dev.join("ttyLAMP0").display().to_string(),
    );
    set(&mut t, "camera.width", width as i64);
    set(&mut t, "camera.height", height as i64);
    let f = 1500.0 * width as f64 / 1280.0;
    set(&mut t, "mock.camera.fx", f);
    set(&mut t, "mock.camera.fy", f);
    set(&mut t, "lamp.warmup_ms", 0);
    set(&mut t, "lamp.reply_timeout_ms", 200);
    set(&mut t, "mock.lamp.warmup_ms", 0);
    t
}

#[cfg(any(feature = "v4l2", feature = "nokhwa"))]
pub fn write_rig(dir: &Path, t: &toml::Table) -> PathBuf {
    let path = dir.join("rig.toml");
    std::fs::write(&path, toml::to_string(t).unwrap()).unwrap();
    path
}

pub fn text(o: &Output) -> String {
    format!(
        "status {:?}\nstdout:\n{}\nstderr:\n{}",
        o.status,
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

pub fn manifest(session: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(session.join("manifest.json")).unwrap()).unwrap()
}

pub fn verify(session: &Path) {
    let o = Command::new(glint())
        .args(["session", "verify"])
        .arg(session)
        .output()
        .unwrap();
    assert!(o.status.success(), "session does not verify: {}", text(&o));
}
