//! The serial driver over a real pseudo-terminal against a device that misbehaves the way
//! real serial links do: overlong, unterminated, CR-only, split, late and echoed replies, a
//! late refusal, noise, and a port that vanishes. Each ends in the right state or in one
//! clear line naming the likely cause.
//!
//! The device here is a small scripted controller speaking docs/design.md's protocol on the
//! terminal's master side, so that each fault is exactly the one under test.

use std::io::{Read, Write};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use glint::devices::lamp_protocol::{LampCommands, LampProtocolSection, Protocol, Terminator};
use glint::devices::serial_lamp::{LampPolicy, SerialLamp};
use glint::devices::{DeviceError, Lamp, LampState};
use serialport::{SerialPort, TTYPort};

/// What the device does with its n-th command (1-based): the bytes to send, each after a
/// pause, in order.
type Script = Box<dyn FnMut(usize, &str, &str) -> Vec<(u64, Vec<u8>)> + Send>;

struct Device {
    path: String,
    commands: Arc<Mutex<Vec<String>>>,
    stop: Arc<std::sync::atomic::AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
    /// Dropping the master end "unplugs" the port.
    unplug: Arc<std::sync::atomic::AtomicBool>,
}

impl Drop for Device {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The correct reply of docs/design.md's protocol, with the device's state.
fn correct(state: &mut (bool, u16), cmd: &str) -> String {
    let parts: Vec<&str> = cmd.split_whitespace().collect();
    match parts.as_slice() {
        ["*IDN?"] => "ACME LAMP CONTROLLER,SN 4711,FW 2.3".into(),
        ["ON"] => {
            state.0 = true;
            "OK".into()
        }
        ["OFF"] => {
            state.0 = false;
            "OK".into()
        }
        ["LEVEL", v] => match v.parse::<u16>() {
            Ok(l) if l <= 1000 => {
                state.1 = l;
                "OK".into()
            }
            _ => "ERR 2 bad level".into(),
        },
        ["STATE?"] => {
            if state.0 {
                format!("ON {}", state.1)
            } else {
                "OFF".into()
            }
        }
        _ => format!("ERR 1 unknown command {cmd}"),
    }
}

/// Start a device whose replies `script` shapes: it gets the command number, the command
/// and the correct reply, and returns what to send.
fn device(mut script: Script) -> Device {
    let (mut master, slave) = TTYPort::pair().expect("a pseudo-terminal");
    let path = slave.name().expect("the terminal's path");
    drop(slave);
    master.set_timeout(Duration::from_millis(5)).unwrap();
    let commands = Arc::new(Mutex::new(Vec::new()));
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let unplug = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (c2, s2, u2) = (commands.clone(), stop.clone(), unplug.clone());
    let thread = std::thread::spawn(move || {
        let mut master = Some(master);
        let mut state = (false, 1000u16);
        let mut line = Vec::new();
        let mut n = 0usize;
        let mut buf = [0u8; 256];
        while !s2.load(std::sync::atomic::Ordering::SeqCst) {
            if u2.load(std::sync::atomic::Ordering::SeqCst) {
                master = None;
            }
            let Some(m) = master.as_mut() else {
                std::thread::sleep(Duration::from_millis(5));
                continue;
            };
            let k = match m.read(&mut buf) {
                Ok(k) => k,
                Err(_) => {
                    std::thread::sleep(Duration::from_millis(2));
                    continue;
                }
            };
            for &b in &buf[..k] {
                if b != b'\n' {
                    line.push(b);
                    continue;
                }
                let cmd = String::from_utf8_lossy(&line)
                    .trim_end_matches('\r')
                    .to_string();
                line.clear();
                n += 1;
                c2.lock().unwrap().push(cmd.clone());
                let reply = correct(&mut state, &cmd);
                for (pause, bytes) in script(n, &cmd, &reply) {
                    std::thread::sleep(Duration::from_millis(pause));
                    let _ = m.write_all(&bytes).and_then(|_| m.flush());
                }
            }
        }
    });
    Device {
        path,
        commands,
        stop,
        thread: Some(thread),
        unplug,
    }
}

/// Every reply as it should be, `\n`-terminated.
fn line(reply: &str) -> Vec<(u64, Vec<u8>)> {
    vec![(0, format!("{reply}\n").into_bytes())]
}

fn policy(timeout_ms: u64, section: LampProtocolSection) -> LampPolicy {
    LampPolicy {
        reply_timeout: Duration::from_millis(timeout_ms),
        tries: 3,
        protocol: Protocol::resolve(&section, &LampCommands::default()).unwrap(),
    }
}

fn open(d: &Device, p: LampPolicy) -> SerialLamp<Box<dyn SerialPort>> {
    SerialLamp::open(&d.path, 115_200, p).expect("the device's terminal opens")
}

const ON_700: LampState = LampState {
    on: true,
    level: 700,
};

/// Identify, switch on at 700, read back, switch off, read back: the whole protocol.
fn full_round(lamp: &mut SerialLamp<Box<dyn SerialPort>>) {
    assert_eq!(
        lamp.identify().unwrap(),
        "ACME LAMP CONTROLLER,SN 4711,FW 2.3"
    );
    assert_eq!(lamp.switch_on(700).unwrap(), ON_700);
    assert_eq!(lamp.state().unwrap(), ON_700);
    assert_eq!(lamp.switch_off().unwrap(), LampState::OFF);
    assert_eq!(lamp.state().unwrap(), LampState::OFF);
}

#[test]
fn a_100_kb_reply_is_read_whole_and_named_not_silence() {
    // Was: a 100 KB reply, read a byte a call, read as "did not answer".
    let d = device(Box::new(|n, _, r| {
        if n == 1 {
            let mut b = vec![b'A'; 100_000];
            b.push(b'\n');
            vec![(0, b)]
        } else {
            line(r)
        }
    }));
    let mut lamp = open(&d, policy(300, Default::default()));
    // The first try's 100 KB line is dropped as overlong; the retry's reply is taken.
    let t = Instant::now();
    full_round(&mut lamp);
    assert!(t.elapsed() < Duration::from_secs(3), "{:?}", t.elapsed());

    // Every reply 100 KB: one line naming its length and the terminator setting.
    let d = device(Box::new(|_, _, _| {
        let mut b = vec![b'A'; 100_000];
        b.push(b'\n');
        vec![(0, b)]
    }));
    let mut lamp = open(&d, policy(300, Default::default()));
    let e = lamp.identify().unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, DeviceError::LampGarbled { .. }), "{msg}");
    assert!(
        msg.contains("a line of 100000 bytes")
            && msg.contains("lamp.protocol.receive_terminator")
            && !msg.contains("did not answer")
            && msg.len() < 400,
        "{msg}"
    );
}

#[test]
fn a_reply_without_a_terminator_names_the_terminator_setting() {
    let d = device(Box::new(|_, _, r| vec![(0, r.as_bytes().to_vec())]));
    let mut lamp = open(&d, policy(150, Default::default()));
    let e = lamp.switch_off().unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, DeviceError::LampNoLineEnd { .. }), "{msg}");
    assert!(
        msg.contains("answered `OFF` without a line end (got `OK")
            && msg.contains("lamp.protocol.receive_terminator"),
        "{msg}"
    );
    assert!(!msg.contains('\n'), "one line");
}

#[test]
fn cr_only_replies_are_lines_and_a_wrong_terminator_is_named() {
    let cr = || {
        device(Box::new(|_, _, r: &str| {
            vec![(0, format!("{r}\r").into_bytes())]
        }))
    };
    let d = cr();
    let mut lamp = open(&d, policy(200, Default::default()));
    full_round(&mut lamp);
    // CRLF split between two writes is one line end, not an empty line.
    let d = device(Box::new(|_, _, r: &str| {
        vec![(0, format!("{r}\r").into_bytes()), (20, b"\n".to_vec())]
    }));
    let mut lamp = open(&d, policy(200, Default::default()));
    full_round(&mut lamp);
    // The rig insists on LF: the CR-only device is named as such.
    let d = cr();
    let section = LampProtocolSection {
        receive_terminator: Some(Terminator::Lf),
        ..Default::default()
    };
    let mut lamp = open(&d, policy(150, section));
    let msg = lamp.identify().unwrap_err().to_string();
    assert!(
        msg.contains("without a line end") && msg.contains("(now \"lf\")"),
        "{msg}"
    );
}

#[test]
fn a_reply_split_across_the_timeout_is_one_reply_and_the_next_is_in_step() {
    // Was: the identity read as two replies joined, and later reads one behind.
    let d = device(Box::new(|n, _, r: &str| {
        if n == 1 {
            let (a, b) = r.split_at(r.len() / 2);
            vec![
                (0, a.as_bytes().to_vec()),
                (220, format!("{b}\n").into_bytes()),
            ]
        } else {
            line(r)
        }
    }));
    let mut lamp = open(&d, policy(150, Default::default()));
    full_round(&mut lamp);
    let commands = d.commands.lock().unwrap().clone();
    assert_eq!(commands[0], "*IDN?");
}

#[test]
fn replies_late_by_1_2_times_the_timeout_never_put_the_link_one_behind() {
    // Every reply 1.2x the timeout late. Was: every later state read one behind.
    let d = device(Box::new(|_, _, r: &str| {
        vec![(240, format!("{r}\n").into_bytes())]
    }));
    let mut lamp = open(&d, policy(200, Default::default()));
    full_round(&mut lamp);
    // Once more, switching between levels: each read is of its own command.
    for level in [300u16, 900, 450] {
        assert_eq!(
            lamp.switch_on(level).unwrap(),
            LampState { on: true, level }
        );
        assert_eq!(lamp.state().unwrap(), LampState { on: true, level });
    }
    assert_eq!(lamp.switch_off().unwrap(), LampState::OFF);
}

#[test]
fn a_late_refusal_of_a_first_try_does_not_abort_the_retry() {
    // The first `LEVEL` is heard wrong and refused, late; the retry is done. Was: the late
    // `ERR` taken as the reply to the retry, and the capture aborted.
    let d = device(Box::new(|n, cmd: &str, r: &str| {
        if n == 2 && cmd.starts_with("LEVEL") {
            vec![(260, b"ERR 7 checksum\n".to_vec())]
        } else {
            line(r)
        }
    }));
    let mut lamp = open(&d, policy(200, Default::default()));
    full_round(&mut lamp);
    let commands = d.commands.lock().unwrap().clone();
    assert_eq!(
        commands.iter().filter(|c| *c == "LEVEL 700").count(),
        2,
        "{commands:?}"
    );
    // A refusal of the latest try is a refusal, at once.
    let d = device(Box::new(|_, cmd: &str, r: &str| {
        if cmd.starts_with("LEVEL") {
            line("ERR 2 level out of range")
        } else {
            line(r)
        }
    }));
    let mut lamp = open(&d, policy(200, Default::default()));
    let t = Instant::now();
    let msg = lamp.switch_on(700).unwrap_err().to_string();
    assert!(msg.contains("refused `LEVEL 700`: ERR 2"), "{msg}");
    // At once: well before the three tries of 200 ms a retry would take (margin for load).
    assert!(
        t.elapsed() < Duration::from_millis(450),
        "{:?}",
        t.elapsed()
    );
}

#[test]
fn an_echoing_device_is_understood_with_or_without_echo_set() {
    // Was: the identity recorded as `*IDN?`.
    let echoing = || {
        device(Box::new(|_, cmd: &str, r: &str| {
            vec![(0, format!("{cmd}\r\n{r}\r\n").into_bytes())]
        }))
    };
    let d = echoing();
    let mut lamp = open(&d, policy(200, Default::default()));
    full_round(&mut lamp);
    let d = echoing();
    let section = LampProtocolSection {
        echo: Some(true),
        ..Default::default()
    };
    let mut lamp = open(&d, policy(200, section));
    full_round(&mut lamp);
    // A trailer line after each reply is skipped too.
    let d = device(Box::new(|_, _, r: &str| {
        vec![(0, format!("{r}\nDONE\n").into_bytes())]
    }));
    let section = LampProtocolSection {
        trailer: Some("DONE".into()),
        ..Default::default()
    };
    let mut lamp = open(&d, policy(200, section));
    full_round(&mut lamp);
}

#[test]
fn noise_is_named_as_a_baud_rate_problem() {
    // What a device at another baud rate sends: bytes of no meaning, with and without
    // line ends (seeded).
    let mut x = 0x9e37_79b9_7f4a_7c15u64;
    let d = device(Box::new(move |n, _, _| {
        let mut b = Vec::new();
        for _ in 0..24 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            b.push(0x80 | (x as u8));
        }
        if n % 2 == 0 {
            b.push(b'\n');
        }
        vec![(0, b)]
    }));
    let mut lamp = open(&d, policy(150, Default::default()));
    for _ in 0..2 {
        let msg = lamp.state().unwrap_err().to_string();
        assert!(
            msg.contains("lamp.baud (noise is what a wrong baud rate looks like)"),
            "{msg}"
        );
        assert!(!msg.chars().any(|c| c.is_control()), "{msg}");
    }
    // Printable replies that the protocol does not know name the protocol.
    let d = device(Box::new(|_, _, _| line("HELLO")));
    let mut lamp = open(&d, policy(150, Default::default()));
    let msg = lamp.state().unwrap_err().to_string();
    assert!(
        msg.contains("last `HELLO`") && msg.contains("lamp.protocol.preset"),
        "{msg}"
    );
}

#[test]
fn a_port_that_vanishes_is_named_gone_at_once() {
    let d = device(Box::new(|_, _, r| line(r)));
    let mut lamp = open(&d, policy(300, Default::default()));
    assert_eq!(lamp.switch_on(700).unwrap(), ON_700);
    d.unplug.store(true, std::sync::atomic::Ordering::SeqCst);
    std::thread::sleep(Duration::from_millis(50));
    let t = Instant::now();
    let e = lamp.state().unwrap_err();
    assert!(matches!(e, DeviceError::LampGone { .. }), "{e}");
    let msg = e.to_string();
    assert!(
        msg.contains("is gone") && msg.contains("state is unknown"),
        "{msg}"
    );
    // And stays gone without waiting out timeouts (3 tries of 300 ms each, twice, would be
    // 1.8 s; the margin is for a loaded machine).
    assert!(lamp.switch_off().is_err());
    assert!(
        t.elapsed() < Duration::from_millis(800),
        "{:?}",
        t.elapsed()
    );
}

#[test]
fn a_late_echoing_device_never_puts_the_link_one_behind() {
    // The device echoes each command at once and replies 150 ms later (timeout 100 ms), one
    // command at a time: the retry's echo comes after the first try's reply. Was: that echo
    // counted as the retry's owed reply, so the retry's own reply was taken by the next
    // command and the state read failed one behind.
    let d = device(Box::new(|_, cmd: &str, r: &str| {
        vec![
            (0, format!("{cmd}\r\n").into_bytes()),
            (150, format!("{r}\r\n").into_bytes()),
        ]
    }));
    let section = LampProtocolSection {
        echo: Some(true),
        ..Default::default()
    };
    let mut lamp = open(&d, policy(100, section));
    assert_eq!(lamp.switch_on(700).unwrap(), ON_700);
    assert_eq!(lamp.state().unwrap(), ON_700);
}

#[test]
fn a_late_reply_to_the_blank_line_on_connection_is_not_the_first_commands() {
    // The device answers the blank line sent on connection (a freshly powered engine's
    // first command fails) with a refusal, after the timeout. Was: that refusal taken as
    // the reply to the first command, and identify failed with `refused`.
    let d = device(Box::new(|n, _, r: &str| {
        if n == 1 {
            vec![(150, b"ERR 1 unknown command\n".to_vec())]
        } else {
            line(r)
        }
    }));
    let section = LampProtocolSection {
        on_connect: glint::devices::lamp_protocol::OnConnectSection {
            drain_ms: None,
            blank_line: Some(true),
        },
        ..Default::default()
    };
    let mut lamp = open(&d, policy(100, section));
    full_round(&mut lamp);
    let commands = d.commands.lock().unwrap().clone();
    assert_eq!(commands[..2], ["", "*IDN?"], "{commands:?}");
}
