//! The lamp: its physics (light output with a warm-up ramp) and its firmware, which
//! speaks the protocol of DESIGN.md on a pseudo-terminal exactly as a USB-serial lamp
//! controller would. Glint drives it through its real serial driver by opening the
//! terminal's path, the same way it opens `/dev/ttyUSB0`.

use std::io::{ErrorKind, Read, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};

use crate::config::{Faults, LampConfig};
use crate::MockError;

#[derive(Debug)]
struct PhysState {
    on: bool,
    level: u16,
    on_since: Instant,
}

/// The lamp's light output, shared between the firmware (which switches it) and the
/// camera (which is lit by it).
#[derive(Debug)]
pub struct LampPhysics {
    state: Mutex<PhysState>,
    warmup: Duration,
}

impl LampPhysics {
    pub fn new(warmup: Duration) -> Self {
        LampPhysics {
            state: Mutex::new(PhysState {
                on: false,
                level: 1000,
                on_since: Instant::now(),
            }),
            warmup,
        }
    }

    /// Output as a fraction of full intensity: level/1000, ramping linearly over the warm-up.
    pub fn output(&self) -> f64 {
        let s = self.state.lock().unwrap();
        if !s.on {
            return 0.0;
        }
        let ramp = if self.warmup.is_zero() {
            1.0
        } else {
            (s.on_since.elapsed().as_secs_f64() / self.warmup.as_secs_f64()).min(1.0)
        };
        s.level as f64 / 1000.0 * ramp
    }

    fn switch(&self, on: bool) {
        let mut s = self.state.lock().unwrap();
        if on && !s.on {
            s.on_since = Instant::now();
        }
        s.on = on;
    }

    fn set_level(&self, level: u16) {
        self.state.lock().unwrap().level = level;
    }

    fn state_line(&self) -> String {
        let s = self.state.lock().unwrap();
        if s.on {
            format!("ON {}", s.level)
        } else {
            "OFF".to_string()
        }
    }
}

/// The firmware's reply to one command line (without the newline).
fn reply(physics: &LampPhysics, identity: &str, line: &str) -> String {
    let mut parts = line.split_whitespace();
    match (parts.next(), parts.next(), parts.next()) {
        (Some("*IDN?"), None, _) => identity.to_string(),
        (Some("ON"), None, _) => {
            physics.switch(true);
            "OK".into()
        }
        (Some("OFF"), None, _) => {
            physics.switch(false);
            "OK".into()
        }
        (Some("STATE?"), None, _) => physics.state_line(),
        (Some("LEVEL"), Some(v), None) => match v.parse::<u16>() {
            Ok(l) if l <= 1000 => {
                physics.set_level(l);
                "OK".into()
            }
            _ => format!("ERR 2 level must be 0..1000, got {v}"),
        },
        _ => format!("ERR 1 unknown command `{line}`"),
    }
}

/// A running lamp firmware on a pseudo-terminal. Dropping it stops the firmware.
pub struct LampFirmware {
    path: String,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
    commands: Arc<Mutex<Vec<String>>>,
}

impl LampFirmware {
    /// Start the firmware on a new pseudo-terminal.
    pub fn spawn(
        cfg: &LampConfig,
        faults: &Faults,
        physics: Arc<LampPhysics>,
        seed: u64,
    ) -> Result<Self, MockError> {
        let (mut master, slave) = TTYPort::pair()
            .map_err(|e| MockError::Device(format!("cannot create a pseudo-terminal: {e}")))?;
        let path = slave
            .name()
            .ok_or_else(|| MockError::Device("the pseudo-terminal has no path".into()))?;
        // Release our end of the terminal: the controller opens it by path, exclusively,
        // as it would a USB serial adapter. The master keeps the terminal alive.
        drop(slave);
        master
            .set_timeout(Duration::from_millis(20))
            .map_err(|e| MockError::Device(format!("pseudo-terminal: {e}")))?;
        let stop = Arc::new(AtomicBool::new(false));
        let commands = Arc::new(Mutex::new(Vec::new()));
        let (stop2, commands2) = (Arc::clone(&stop), Arc::clone(&commands));
        let identity = cfg.identity.clone();
        let faults = faults.clone();
        let mut log = match &cfg.command_log {
            Some(path) => Some(
                std::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(path)
                    .map_err(|e| {
                        MockError::Device(format!("cannot open mock.lamp.command_log {path}: {e}"))
                    })?,
            ),
            None => None,
        };
        let thread = std::thread::Builder::new()
            .name("mock-lamp-firmware".into())
            .spawn(move || {
                let mut buf = Vec::new();
                let mut byte = [0u8; 256];
                let mut answered = 0u32;
                let mut garble = seed | 1;
                while !stop2.load(Ordering::Relaxed) {
                    let n = match master.read(&mut byte) {
                        Ok(0) => continue,
                        Ok(n) => n,
                        Err(e)
                            if matches!(
                                e.kind(),
                                ErrorKind::TimedOut
                                    | ErrorKind::WouldBlock
                                    | ErrorKind::Interrupted
                            ) =>
                        {
                            continue
                        }
                        // EIO: nobody has the terminal open (yet, or any more).
                        Err(_) => {
                            std::thread::sleep(Duration::from_millis(5));
                            continue;
                        }
                    };
                    buf.extend_from_slice(&byte[..n]);
                    while let Some(pos) = buf.iter().position(|b| *b == b'\n') {
                        let raw: Vec<u8> = buf.drain(..=pos).collect();
                        let line = String::from_utf8_lossy(&raw)
                            .trim_end_matches(['\n', '\r'])
                            .trim()
                            .to_string();
                        commands2.lock().unwrap().push(line.clone());
                        if let Some(f) = log.as_mut() {
                            // The log is for observers; a failing log never stops the lamp.
                            let _ = writeln!(f, "{line}").and_then(|_| f.flush());
                        }
                        if faults.lamp_silent_after.is_some_and(|s| answered >= s) {
                            continue;
                        }
                        let mut out = reply(&physics, &identity, &line).into_bytes();
                        answered += 1;
                        if faults.lamp_garble_replies.contains(&answered) {
                            // Line noise: bytes flipped, non-ASCII garbage, same length.
                            for b in out.iter_mut() {
                                garble ^= garble << 13;
                                garble ^= garble >> 7;
                                garble ^= garble << 17;
                                *b = 0x80 | (garble as u8 ^ *b);
                            }
                        }
                        out.push(b'\n');
                        if master.write_all(&out).and_then(|_| master.flush()).is_err() {
                            return;
                        }
                    }
                }
            })
            .map_err(|e| MockError::Device(format!("cannot start the lamp firmware: {e}")))?;
        Ok(LampFirmware {
            path,
            stop,
            thread: Some(thread),
            commands,
        })
    }

    /// The terminal's path, e.g. `/dev/pts/3`: open it as a serial port.
    pub fn port_path(&self) -> &str {
        &self.path
    }

    /// Every command line the firmware has received, in order.
    pub fn commands(&self) -> Vec<String> {
        self.commands.lock().unwrap().clone()
    }
}

impl Drop for LampFirmware {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn protocol_replies() {
        let p = LampPhysics::new(Duration::ZERO);
        assert_eq!(reply(&p, "ID", "*IDN?"), "ID");
        assert_eq!(reply(&p, "ID", "STATE?"), "OFF");
        assert_eq!(reply(&p, "ID", "LEVEL 500"), "OK");
        assert_eq!(reply(&p, "ID", "ON"), "OK");
        assert_eq!(reply(&p, "ID", "STATE?"), "ON 500");
        assert!((p.output() - 0.5).abs() < 1e-12);
        assert!(reply(&p, "ID", "LEVEL 1001").starts_with("ERR 2"));
        assert!(reply(&p, "ID", "DANCE").starts_with("ERR 1"));
        assert_eq!(reply(&p, "ID", "OFF"), "OK");
        assert_eq!(p.output(), 0.0);
    }

    #[test]
    fn warmup_ramps() {
        let p = LampPhysics::new(Duration::from_millis(400));
        p.switch(true);
        let early = p.output();
        std::thread::sleep(Duration::from_millis(450));
        assert!(early < 0.5, "{early}");
        assert_eq!(p.output(), 1.0);
    }
}
