//! The nokhwa backend from the outside, in every build: what the rig checks refuse for
//! `camera.backend = "nokhwa"` (formats nokhwa does not have, fractional frame rates, no
//! device), and what a build without the backend says about a nokhwa rig. The captures
//! through nokhwa are in `nokhwa_sim` (`--features nokhwa`).

use std::path::Path;

use glint::devices;
use glint::rig;

use super::util::{root, set, tempdir};

fn sim_nokhwa() -> toml::Table {
    toml::from_str(&std::fs::read_to_string(root().join("rigs/sim-nokhwa.toml")).unwrap()).unwrap()
}

/// Load `t`; the error's text, or "" when it loads.
fn load_err(dir: &Path, t: &toml::Table) -> String {
    let path = dir.join("rig.toml");
    std::fs::write(&path, toml::to_string(t).unwrap()).unwrap();
    rig::load(&path)
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default()
}

#[test]
fn rig_checks_refuse_what_nokhwa_cannot_take() {
    let dir = tempdir();
    assert_eq!(load_err(dir.path(), &sim_nokhwa()), "");
    for (key, value, want) in [
        (
            "camera.pixel_format",
            toml::Value::from("Y16"),
            "nokhwa has no Y16",
        ),
        (
            "camera.fps",
            toml::Value::from(29.97),
            "nokhwa sets whole frames per second, not 29.97",
        ),
        (
            "camera.device",
            toml::Value::from(""),
            "backend \"nokhwa\" needs a device",
        ),
    ] {
        let mut t = sim_nokhwa();
        set(&mut t, key, value);
        if key == "camera.pixel_format" {
            set(&mut t, "camera.bit_depth", 16);
        }
        let e = load_err(dir.path(), &t);
        assert!(e.contains(key) && e.contains(want), "{key}: {e}");
    }
    let mut t = sim_nokhwa();
    t["camera"].as_table_mut().unwrap().remove("pixel_format");
    let e = load_err(dir.path(), &t);
    assert!(e.contains("backend \"nokhwa\" needs a pixel format"), "{e}");
}

#[test]
fn backend_check_names_what_this_build_cannot_do() {
    let l = rig::load(&root().join("rigs/sim-nokhwa.toml")).unwrap();
    let c = devices::check_backends(&l.rig);
    if !devices::NOKHWA_BUILT {
        assert_eq!(
            c.problems,
            vec![format!(
                "camera.backend = \"nokhwa\": {}",
                devices::NOKHWA_MISSING
            )]
        );
        return;
    }
    if cfg!(target_os = "linux") {
        assert!(c.problems.is_empty(), "{c:?}");
        // On Linux nokhwa asks V4L2 for GREY as "GRAY".
        let dir = tempdir();
        let mut t = sim_nokhwa();
        set(&mut t, "camera.pixel_format", "GREY");
        let path = dir.path().join("grey.toml");
        std::fs::write(&path, toml::to_string(&t).unwrap()).unwrap();
        let l = rig::load(&path).unwrap();
        let c = devices::check_backends(&l.rig);
        assert_eq!(c.problems.len(), 1, "{c:?}");
        assert!(c.problems[0].contains("\"GRAY\""), "{c:?}");
    } else {
        assert!(c.problems[0].contains("only on Linux"), "{c:?}");
    }
}

#[cfg(not(feature = "nokhwa"))]
#[test]
fn a_build_without_the_backend_refuses_nokhwa_rigs() {
    let o = super::util::glint(&[
        "rig",
        "check",
        root().join("rigs/sim-nokhwa.toml").to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(out.contains(devices::NOKHWA_MISSING), "{out}");
    assert!(out.contains("--features nokhwa"), "{out}");
}
