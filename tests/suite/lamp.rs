//! The real serial driver against the simulated lamp firmware on a pseudo-terminal.

use std::sync::Arc;
use std::time::{Duration, Instant};

use glint::devices::serial_lamp::{LampPolicy, SerialLamp};
use glint::devices::{DeviceError, Lamp, LampState};
use glint::glint_mock::config::{Faults, LampConfig};
use glint::glint_mock::{LampFirmware, LampPhysics};
use glint::rig::LampCommands;

fn firmware(faults: Faults) -> (LampFirmware, Arc<LampPhysics>) {
    let physics = Arc::new(LampPhysics::new(Duration::ZERO));
    let fw = LampFirmware::spawn(&LampConfig::default(), &faults, Arc::clone(&physics), 9).unwrap();
    (fw, physics)
}

fn open(fw: &LampFirmware, timeout_ms: u64) -> SerialLamp<Box<dyn serialport::SerialPort>> {
    let policy = LampPolicy {
        reply_timeout: Duration::from_millis(timeout_ms),
        tries: 3,
        commands: LampCommands::default(),
    };
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
        msg.contains("garbled replies to `*IDN?` (3 tries") && msg.contains("check the baud rate"),
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
        format!("lamp on {} did not answer `LEVEL 1000` (3 tries, 150 ms each); check its power and cable", fw.port_path())
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
    let policy = LampPolicy {
        reply_timeout: Duration::from_millis(100),
        tries: 1,
        commands: LampCommands::default(),
    };
    let e = SerialLamp::open("/dev/glint-no-such-port", 9600, policy)
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("cannot open lamp port /dev/glint-no-such-port") && e.contains("lamp.port"),
        "{e}"
    );
}
