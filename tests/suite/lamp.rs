//! The real serial driver against the simulated lamp firmware on a pseudo-terminal.

use std::sync::Arc;
use std::time::{Duration, Instant};

use glint::devices::serial_lamp::{LampPolicy, SerialLamp};
use glint::devices::{DeviceError, Lamp, LampState};
use glint_mock::config::{Faults, LampConfig};
use glint_mock::{LampFirmware, LampPhysics};

fn firmware(faults: Faults) -> (LampFirmware, Arc<LampPhysics>) {
    let physics = Arc::new(LampPhysics::new(Duration::ZERO));
    let fw = LampFirmware::spawn(&LampConfig::default(), &faults, Arc::clone(&physics), 9).unwrap();
    (fw, physics)
}

fn open(fw: &LampFirmware, timeout_ms: u64) -> SerialLamp<Box<dyn serialport::SerialPort>> {
    let policy = LampPolicy::glint(Duration::from_millis(timeout_ms), 3);
    SerialLamp::open(fw.port_path(), 115_200, policy).unwrap()
}

#[test]
fn switches_the_lamp_and_reads_it_back_over_a_pty() {
    let (fw, physics) = firmware(Faults::default());
    assert!(
        fw.port_path().starts_with("/dev/pts/"),
        "{}",
        fw.port_path()
    );
    let mut lamp = open(&fw, 300);
    assert_eq!(lamp.identify().unwrap(), "GLINT-MOCK-LAMP,1.0");
    assert_eq!(
        lamp.switch_on(700).unwrap(),
        LampState {
            on: true,
            level: 700
        }
    );
    assert!(
        (physics.output() - 0.7).abs() < 1e-12,
        "the light really is on"
    );
    assert_eq!(
        lamp.state().unwrap(),
        LampState {
            on: true,
            level: 700
        }
    );
    assert_eq!(
        lamp.switch_off().unwrap(),
        LampState {
            on: false,
            level: 0
        }
    );
    assert_eq!(physics.output(), 0.0);
    assert_eq!(
        fw.commands(),
        [
            "*IDN?",
            "LEVEL 700",
            "ON",
            "STATE?",
            "STATE?",
            "OFF",
            "STATE?"
        ]
    );
}

#[test]
fn survives_a_garbled_reply() {
    // The 2nd reply (to `LEVEL 500`) arrives as line noise; the driver retries it.
    let (fw, _) = firmware(Faults {
        lamp_garble_replies: vec![2],
        ..Faults::default()
    });
    let mut lamp = open(&fw, 200);
    lamp.identify().unwrap();
    assert_eq!(
        lamp.switch_on(500).unwrap(),
        LampState {
            on: true,
            level: 500
        }
    );
    assert_eq!(
        fw.commands(),
        ["*IDN?", "LEVEL 500", "LEVEL 500", "ON", "STATE?"]
    );
}

#[test]
fn gives_up_on_persistent_garbage_with_a_clear_error() {
    let (fw, _) = firmware(Faults {
        lamp_garble_replies: vec![1, 2, 3],
        ..Faults::default()
    });
    let mut lamp = open(&fw, 200);
    let e = lamp.identify().unwrap_err();
    assert!(
        matches!(e, DeviceError::LampGarbled { tries: 3, .. }),
        "{e}"
    );
    let msg = e.to_string();
    assert!(
        msg.contains("no usable reply to `*IDN?` in 3 tries")
            && msg.contains("check lamp.baud (noise"),
        "{msg}"
    );
}

#[test]
fn a_silent_lamp_fails_after_bounded_retries() {
    let (fw, _) = firmware(Faults {
        lamp_silent_after: Some(1),
        ..Faults::default()
    });
    let mut lamp = open(&fw, 150);
    lamp.identify().unwrap();
    let t = Instant::now();
    let e = lamp.switch_on(1000).unwrap_err();
    let waited = t.elapsed();
    assert!(matches!(e, DeviceError::LampSilent { tries: 3, .. }), "{e}");
    assert_eq!(
        e.to_string(),
        format!("lamp on {} did not answer `LEVEL 1000` (3 tries, 150 ms each); check that it is powered and connected to lamp.port, lamp.baud, and lamp.reply_timeout_ms for a slow device", fw.port_path())
    );
    assert!(
        waited >= Duration::from_millis(450) && waited < Duration::from_millis(1500),
        "{waited:?}"
    );
    assert_eq!(
        fw.commands().iter().filter(|c| *c == "LEVEL 1000").count(),
        3,
        "exactly `tries` attempts"
    );
}

#[test]
fn opening_a_missing_port_names_it() {
    let policy = LampPolicy::glint(Duration::from_millis(100), 1);
    let e = SerialLamp::open("/dev/glint-no-such-port", 9600, policy)
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("cannot open lamp port /dev/glint-no-such-port") && e.contains("lamp.port"),
        "{e}"
    );
}

/// Run `glint capture` on the small mock rig with a 5 s warm-up and the lamp firmware
/// logging every command it receives; once the lamp is on, send `signal`. Returns the
/// output, the time from the signal to the exit, the session's manifest and the firmware's
/// command log.
fn signal_mid_capture(
    signal: libc::c_int,
) -> (
    std::process::Output,
    Duration,
    glint::session::Manifest,
    Vec<String>,
) {
    use super::util::{load, set, small_table, tempdir};
    let dir = tempdir();
    let log = dir.path().join("lamp.log");
    let mut t = small_table();
    set(&mut t, "lamp.warmup_ms", 5000);
    set(&mut t, "mock.lamp.command_log", log.display().to_string());
    let rig = load(dir.path(), &t);
    let out = dir.path().join("s");
    let child = std::process::Command::new(env!("CARGO_BIN_EXE_glint"))
        .args(["capture", "--rig"])
        .arg(&rig.path)
        .arg("--out")
        .arg(&out)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let read_log = || {
        std::fs::read_to_string(&log)
            .unwrap_or_default()
            .lines()
            .map(str::to_string)
            .collect::<Vec<_>>()
    };
    let started = Instant::now();
    while !read_log().iter().any(|c| c == "ON") {
        assert!(
            started.elapsed() < Duration::from_secs(30),
            "the lamp was never switched on: {:?}",
            read_log()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    // In the warm-up now (it lasts 5 s): the signal must act at once.
    std::thread::sleep(Duration::from_millis(200));
    let sent = Instant::now();
    // SAFETY: kill(2) on our own child's pid.
    assert_eq!(unsafe { libc::kill(child.id() as libc::pid_t, signal) }, 0);
    let output = child.wait_with_output().unwrap();
    let took = sent.elapsed();
    let m = glint::session::load(&out).unwrap();
    (output, took, m, read_log())
}

fn assert_stopped_cleanly(signal: libc::c_int, reason: &str) {
    let (output, took, m, log) = signal_mid_capture(signal);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "{stderr}");
    assert!(
        took < Duration::from_millis(2000),
        "exited {took:?} after the signal, during a 5 s warm-up"
    );
    assert_eq!(m.state, glint::session::State::Failed);
    assert_eq!(m.failure.as_deref(), Some(reason));
    // What the lamp's own firmware received: ON, then OFF and its read-back at the end.
    let on = log.iter().position(|c| c == "ON").unwrap();
    assert_eq!(
        &log[on + 1..],
        ["STATE?", "OFF", "STATE?"],
        "switched on, read back, switched off, read back: {log:?}"
    );
    // ... and the driver saw it read back off.
    assert_eq!(m.lamp_off_confirmed, Some(true));
    let errors: Vec<&str> = stderr.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(errors.len(), 1, "{stderr}");
    assert!(
        errors[0].starts_with(&format!("error: {reason} (session ")),
        "{stderr}"
    );
}

#[test]
fn sigterm_mid_capture_sends_off_and_leaves_failed() {
    // Was: SIGTERM killed glint at once, the lamp stayed on, the manifest said `capturing`.
    assert_stopped_cleanly(libc::SIGTERM, "stopped by SIGTERM");
}

#[test]
fn sighup_mid_capture_sends_off_and_leaves_failed() {
    assert_stopped_cleanly(libc::SIGHUP, "stopped by SIGHUP");
}

#[test]
fn ctrl_c_during_a_long_warm_up_acts_at_once() {
    assert_stopped_cleanly(libc::SIGINT, "interrupted by the user");
}
