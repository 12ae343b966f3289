//! The simulated camera lit by a lamp controller that is its own process (`glint-mock
//! lamp`), reached over a pseudo-terminal by its path exactly as `/dev/ttyUSB0` would be:
//! a serial lamp with the simulated camera, each protocol preset, and the controller's
//! process killed mid-capture (a USB adapter pulled out).

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use super::sim_lab::{glint, launcher, manifest, verify};
use super::util::{set, small_table, tempdir};

/// A `glint-mock lamp` process, killed when dropped.
pub struct LampProcess {
    pub child: Child,
    pub link: PathBuf,
    log: PathBuf,
}

impl Drop for LampProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl LampProcess {
    pub fn start(dir: &Path, preset: &str) -> LampProcess {
        let link = dir.join("dev/ttyLAMP0");
        let log = dir.join("lamp.log");
        let child = Command::new(launcher())
            .args(["lamp", "--link"])
            .arg(&link)
            .args(["--preset", preset, "--warmup-ms", "0", "--log"])
            .arg(&log)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("glint-mock lamp starts");
        let t = Instant::now();
        while std::fs::symlink_metadata(&link).is_err() {
            assert!(
                t.elapsed() < Duration::from_secs(10),
                "the lamp's link never appeared"
            );
            std::thread::sleep(Duration::from_millis(10));
        }
        LampProcess { child, link, log }
    }

    pub fn commands(&self) -> Vec<String> {
        std::fs::read_to_string(&self.log)
            .unwrap_or_default()
            .lines()
            .map(str::to_string)
            .collect()
    }
}

/// The small mock rig with its lamp on the serial port of `lamp`, speaking `preset`.
fn rig(dir: &Path, lamp: &LampProcess, preset: &str, size: (u32, u32)) -> PathBuf {
    let mut t = small_table();
    set(&mut t, "camera.width", size.0 as i64);
    set(&mut t, "camera.height", size.1 as i64);
    let f = 1500.0 * size.0 as f64 / 1280.0;
    set(&mut t, "mock.camera.fx", f);
    set(&mut t, "mock.camera.fy", f);
    set(&mut t, "lamp.backend", "serial");
    set(&mut t, "lamp.port", lamp.link.display().to_string());
    set(&mut t, "lamp.reply_timeout_ms", 300);
    set(&mut t, "lamp.level", 800);
    set(&mut t, "lamp.protocol.preset", preset);
    let path = dir.join("rig.toml");
    std::fs::write(&path, toml::to_string(&t).unwrap()).unwrap();
    path
}

/// The last two commands switch the lamp off and read it back, in the preset's words.
fn ends_off(preset: &str, commands: &[String]) {
    let (off, state) = match preset {
        "glint" => ("OFF", "STATE?"),
        "lumencor" => ("SET CH 0 0", "GET CHACT 0"),
        "coolled" => ("CSSAXF000", "CSS?"),
        _ => unreachable!(),
    };
    let n = commands.len();
    assert!(n >= 2, "{commands:?}");
    assert_eq!(
        [commands[n - 2].as_str(), commands[n - 1].as_str()],
        [off, state],
        "{commands:?}"
    );
}

#[test]
fn the_simulated_camera_lit_by_a_lamp_process_finds_the_tile() {
    let dir = tempdir();
    let lamp = LampProcess::start(dir.path(), "lumencor");
    let rig = rig(dir.path(), &lamp, "lumencor", (320, 240));
    let out = Command::new(glint())
        .args(["run", "--json", "--rig"])
        .arg(&rig)
        .arg("--out")
        .arg(dir.path().join("s"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let j: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let fit = &j["fit"];
    assert_eq!(fit["chosen"], "blinn-phong", "{fit}");
    let chosen = fit["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["model"] == "blinn-phong")
        .unwrap();
    let n = chosen["n"]["value"].as_f64().unwrap();
    assert!((n / 120.0 - 1.0).abs() < 0.05, "n = {n}");
    let commands = lamp.commands();
    // The preset's connection step (a blank line), identify, level 800 of 1000, on.
    assert_eq!(commands[0], "", "{commands:?}");
    assert!(commands.contains(&"GET MODEL".to_string()), "{commands:?}");
    assert!(
        commands.contains(&"SET CHINT 0 800".to_string()),
        "{commands:?}"
    );
    ends_off("lumencor", &commands);
    let manifest = manifest(&dir.path().join("s"));
    assert_eq!(manifest["state"], "complete");
    assert!(
        manifest.to_string().contains("A MODEL Spectra III"),
        "the lamp's identity is recorded"
    );
}

#[test]
fn every_preset_captures_and_ends_with_the_lamp_off() {
    for preset in ["glint", "coolled"] {
        let dir = tempdir();
        let lamp = LampProcess::start(dir.path(), preset);
        let rig = rig(dir.path(), &lamp, preset, (160, 120));
        let out = Command::new(glint())
            .args(["capture", "--rig"])
            .arg(&rig)
            .arg("--out")
            .arg(dir.path().join("s"))
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{preset}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let commands = lamp.commands();
        ends_off(preset, &commands);
        if preset == "coolled" {
            // 800 of 1000 is 80% in the device's percent, with the switch-on.
            assert!(commands.contains(&"CSSASN080".to_string()), "{commands:?}");
        }
    }
}

#[test]
fn killing_the_lamp_process_mid_capture_leaves_a_failed_session_that_verifies() {
    let dir = tempdir();
    let mut lamp = LampProcess::start(dir.path(), "glint");
    let rig_path = rig(dir.path(), &lamp, "glint", (160, 120));
    // Frames take real time, so the capture lasts long enough to pull the plug in it.
    let mut t: toml::Table = toml::from_str(&std::fs::read_to_string(&rig_path).unwrap()).unwrap();
    set(&mut t, "mock.sensor.realtime", true);
    std::fs::write(&rig_path, toml::to_string(&t).unwrap()).unwrap();
    let session = dir.path().join("s");
    let capture = Command::new(glint())
        .args(["capture", "--rig"])
        .arg(&rig_path)
        .arg("--out")
        .arg(&session)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Once the lamp is on and its state has been read before a few frame groups, the
    // controller's process dies (its pty closes: an unplugged USB adapter).
    let t0 = Instant::now();
    loop {
        let c = lamp.commands();
        let on = c.iter().position(|l| l == "ON");
        if on.is_some_and(|i| c.len() >= i + 4) {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(30), "{c:?}");
        std::thread::sleep(Duration::from_millis(2));
    }
    lamp.child.kill().unwrap();
    lamp.child.wait().unwrap();
    let out = capture.wait_with_output().unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    let errors: Vec<&str> = stderr.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(errors.len(), 1, "{stderr}");
    assert!(
        errors[0].contains("is gone") && errors[0].contains("may still be on"),
        "{}",
        errors[0]
    );
    let manifest = manifest(&session);
    assert_eq!(manifest["state"], "failed", "{manifest}");
    // Nobody could confirm the lamp off: its state is recorded as unknown.
    assert_eq!(manifest["lamp_off_confirmed"], false, "{manifest}");
    verify(&session);
}

/// Whether the lamp of `lamp` is dark, as its light file (what the simulated camera sees)
/// says.
pub fn is_dark(lamp: &LampProcess) -> bool {
    let light = glint_mock::lamp::light_file_for(&lamp.link);
    let rec = glint_mock::lamp::read_light_file(&light)
        .unwrap_or_else(|| panic!("{} holds no light record", light.display()));
    rec.fraction == 0.0
}

/// `glint run` on the serial-lamp rig, the process raising at itself the signals
/// `faults` names at their steps (GLINT_FAULT_SIGNALS: deterministic, not timed).
fn run_signalled(
    faults: &str,
) -> (
    std::process::Output,
    PathBuf,
    LampProcess,
    tempfile::TempDir,
) {
    let dir = tempdir();
    let lamp = LampProcess::start(dir.path(), "glint");
    let rig = rig(dir.path(), &lamp, "glint", (160, 120));
    let session = dir.path().join("s");
    let out = Command::new(glint())
        .args(["run", "--rig"])
        .arg(&rig)
        .arg("--out")
        .arg(&session)
        .env(glint::capture::FAULT_SIGNALS_ENV, faults)
        .stdin(Stdio::null())
        .output()
        .unwrap();
    (out, session, lamp, dir)
}

/// A second signal (at once, or while the capture is already stopping) hurries the stop
/// but never skips the lamp's OFF or the manifest: exit 1 (not 130), session `failed`
/// naming the first signal, the lamp read back off, its light dark.
#[test]
fn a_second_signal_still_switches_the_lamp_off_and_closes_the_session() {
    // Was: the second signal _exit()ed: status 130, manifest `capturing`, lamp lit.
    for (faults, reason) in [
        ("lamp-on:INT,lamp-on:INT", "interrupted by the user"),
        ("lamp-on:TERM,lamp-on:TERM", "stopped by SIGTERM"),
        ("lamp-on:HUP,lamp-on:INT", "stopped by SIGHUP"),
        ("lamp-on:INT,stopping:INT", "interrupted by the user"),
        ("lamp-on:TERM,stopping:HUP", "stopped by SIGTERM"),
    ] {
        let (out, session, lamp, _dir) = run_signalled(faults);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{faults}: {stderr}");
        assert!(stderr.contains("stopping now"), "{faults}: {stderr}");
        let errors: Vec<&str> = stderr.lines().filter(|l| l.starts_with("error:")).collect();
        assert_eq!(errors.len(), 1, "{faults}: {stderr}");
        assert!(
            errors[0].starts_with(&format!("error: {reason} (session ")),
            "{faults}: {stderr}"
        );
        let m = manifest(&session);
        assert_eq!(m["state"], "failed", "{faults}: {m}");
        assert_eq!(m["failure"], reason, "{faults}: {m}");
        assert_eq!(m["lamp_off_confirmed"], true, "{faults}: {m}");
        ends_off("glint", &lamp.commands());
        assert!(is_dark(&lamp), "{faults}: the lamp's light file is lit");
        verify(&session);
    }
}

/// A third signal quits at once and says so, naming the command that switches the lamp
/// off; that command then does.
#[test]
fn a_third_signal_quits_at_once_saying_the_lamp_may_be_on_and_glint_lamp_off_switches_it_off() {
    let (out, session, lamp, dir) = run_signalled("lamp-on:INT,lamp-on:INT,lamp-on:INT");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(130), "{stderr}");
    assert!(
        stderr.contains("the lamp may still be on") && stderr.contains("glint lamp off --rig"),
        "{stderr}"
    );
    assert_eq!(manifest(&session)["state"], "capturing");
    assert!(
        !is_dark(&lamp),
        "quitting at once leaves the lamp as it was"
    );
    let off = Command::new(glint())
        .args(["lamp", "off", "--rig"])
        .arg(dir.path().join("rig.toml"))
        .output()
        .unwrap();
    assert!(
        off.status.success(),
        "{}",
        String::from_utf8_lossy(&off.stderr)
    );
    assert!(
        String::from_utf8_lossy(&off.stdout).contains("is off (read back)"),
        "{}",
        String::from_utf8_lossy(&off.stdout)
    );
    ends_off("glint", &lamp.commands());
    assert!(is_dark(&lamp), "glint lamp off left the light file lit");
}

/// A SIGTERM after the capture (before the HDR stage) is named as SIGTERM, not as the user.
#[test]
fn sigterm_after_the_capture_is_named_not_blamed_on_the_user() {
    let (out, session, lamp, _dir) = run_signalled("capture-done:TERM");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    let errors: Vec<&str> = stderr.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(errors.len(), 1, "{stderr}");
    assert!(
        errors[0].starts_with("error: hdr failed: stopped by SIGTERM"),
        "{stderr}"
    );
    assert!(!stderr.contains("interrupted by the user"), "{stderr}");
    assert_eq!(manifest(&session)["state"], "complete");
    assert!(is_dark(&lamp), "the lamp's light file is lit");
}

/// `glint lamp off` on a port that is not there: one line naming the port, exit 1.
#[test]
fn glint_lamp_off_on_a_missing_port_fails_in_one_line() {
    let dir = tempdir();
    let mut t = small_table();
    set(&mut t, "lamp.backend", "serial");
    set(
        &mut t,
        "lamp.port",
        dir.path().join("ttyNONE").display().to_string(),
    );
    let rig = dir.path().join("rig.toml");
    std::fs::write(&rig, toml::to_string(&t).unwrap()).unwrap();
    let out = Command::new(glint())
        .args(["lamp", "off", "--rig"])
        .arg(&rig)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    assert!(
        stderr.contains("ttyNONE") && stderr.contains("may still be on"),
        "{stderr}"
    );
    // The help teaches when to use it.
    let help = Command::new(glint())
        .args(["lamp", "off", "--help"])
        .output()
        .unwrap();
    let help = String::from_utf8_lossy(&help.stdout);
    assert!(
        help.contains("ExecStopPost") && help.contains("kill -9"),
        "{help}"
    );
}
