//! The serial lamp driver: the lamp protocol of DESIGN.md over any `Read + Write`.
//!
//! ASCII lines ending in `\n`; every command gets exactly one reply line. The driver waits a
//! bounded time for each reply, treats a reply that is not valid for the command as line
//! noise, drains whatever is left on the line and tries again (a bounded number of times),
//! and after every switching command reads the state back and checks it. It opens a serial
//! port only in [`SerialLamp::open`], so tests can drive it over a pseudo-terminal or a
//! byte script.

use std::io::{ErrorKind, Read, Write};
use std::time::{Duration, Instant};

use super::{DeviceError, Lamp, LampState};
use crate::rig::LampCommands;

/// Timing and retry policy.
#[derive(Debug, Clone)]
pub struct LampPolicy {
    pub reply_timeout: Duration,
    pub tries: u32,
    pub commands: LampCommands,
}

impl LampPolicy {
    /// The policy a rig's `[lamp]` section sets.
    pub fn from_rig(lamp: &crate::rig::LampSection) -> Self {
        LampPolicy {
            reply_timeout: Duration::from_millis(lamp.reply_timeout_ms),
            tries: lamp.tries,
            commands: lamp.commands.clone(),
        }
    }
}

/// A lamp controller on a serial line (or anything that reads and writes bytes).
pub struct SerialLamp<P> {
    port: P,
    name: String,
    policy: LampPolicy,
}

/// Longest reply line the driver keeps, bytes (replies of the protocol are a few bytes;
/// an identity a few dozen).
pub const MAX_LINE_BYTES: usize = 4096;

/// What [`SerialLamp::read_line`] got.
enum Reply {
    /// A line, without its terminator.
    Line(Vec<u8>),
    /// A line longer than [`MAX_LINE_BYTES`]: its first bytes.
    Overlong(Vec<u8>),
    /// Nothing complete before the deadline.
    Silent,
}

/// A printable reply for an error: at most [`crate::fsx::QUOTE_CHARS`] characters.
fn cut(line: &str) -> String {
    if line.chars().count() <= crate::fsx::QUOTE_CHARS {
        line.into()
    } else {
        let start: String = line.chars().take(crate::fsx::QUOTE_CHARS).collect();
        format!("{start}… ({} bytes)", line.len())
    }
}

/// The reply a command expects.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Expect {
    Identity,
    Ok,
    State,
}

impl SerialLamp<Box<dyn serialport::SerialPort>> {
    /// Open a serial port by path (`/dev/ttyUSB0`, or a pseudo-terminal's `/dev/pts/N`).
    pub fn open(path: &str, baud: u32, policy: LampPolicy) -> Result<Self, DeviceError> {
        let port = serialport::new(path, baud)
            // Short reads; the driver keeps its own per-reply deadline.
            .timeout(Duration::from_millis(10))
            .open()
            .map_err(|e| DeviceError::Open {
                what: format!("lamp port {path}"),
                reason: format!("{e}; check lamp.port and that no other program has it open"),
            })?;
        Ok(SerialLamp::new(port, format!("lamp on {path}"), policy))
    }
}

impl<P: Read + Write + Send> SerialLamp<P> {
    /// Drive a lamp over an already open byte stream.
    pub fn new(port: P, name: String, policy: LampPolicy) -> Self {
        SerialLamp { port, name, policy }
    }

    /// Send one command and return its reply line, with bounded retries.
    fn transact(&mut self, command: &str, expect: Expect) -> Result<String, DeviceError> {
        let mut last_garbled: Option<String> = None;
        for attempt in 1..=self.policy.tries {
            if attempt > 1 {
                self.drain();
                tracing::warn!(lamp = %self.name, command, attempt, "retrying lamp command");
            }
            self.port
                .write_all(format!("{command}\n").as_bytes())
                .and_then(|_| self.port.flush())
                .map_err(|source| DeviceError::Io {
                    op: format!("writing `{command}` to {}", self.name),
                    source,
                })?;
            match self.read_line()? {
                Reply::Silent => continue,
                Reply::Overlong(start) => {
                    last_garbled = Some(format!(
                        "{} (a line of more than {MAX_LINE_BYTES} bytes)",
                        crate::fsx::quote(&String::from_utf8_lossy(&start))
                    ))
                }
                Reply::Line(bytes) => match std::str::from_utf8(&bytes) {
                    Ok(line) if line.starts_with("ERR") && valid_ascii(line) => {
                        return Err(DeviceError::LampRefused {
                            lamp: self.name.clone(),
                            command: command.into(),
                            reply: cut(line),
                        })
                    }
                    Ok(line) if valid_reply(line, expect) => return Ok(line.to_string()),
                    _ => last_garbled = Some(crate::fsx::quote(&String::from_utf8_lossy(&bytes))),
                },
            }
        }
        Err(match last_garbled {
            Some(reply) => DeviceError::LampGarbled {
                lamp: self.name.clone(),
                command: command.into(),
                tries: self.policy.tries,
                reply,
            },
            None => DeviceError::LampSilent {
                lamp: self.name.clone(),
                command: command.into(),
                tries: self.policy.tries,
                timeout: self.policy.reply_timeout,
            },
        })
    }

    /// One line without its terminator, [`Reply::Silent`] when the deadline passes first,
    /// or [`Reply::Overlong`] for a line longer than [`MAX_LINE_BYTES`] (its first bytes;
    /// the rest is read and dropped up to its end or the deadline), so a device sending
    /// bytes without end cannot grow memory.
    fn read_line(&mut self) -> Result<Reply, DeviceError> {
        let deadline = Instant::now() + self.policy.reply_timeout;
        let mut line = Vec::new();
        let mut overlong = false;
        let mut byte = [0u8; 1];
        while Instant::now() < deadline {
            match self.port.read(&mut byte) {
                Ok(0) => std::thread::sleep(Duration::from_millis(2)),
                Ok(_) if byte[0] == b'\n' => {
                    if overlong {
                        return Ok(Reply::Overlong(line));
                    }
                    if line.last() == Some(&b'\r') {
                        line.pop();
                    }
                    return Ok(Reply::Line(line));
                }
                Ok(_) if line.len() >= MAX_LINE_BYTES => overlong = true,
                Ok(_) => line.push(byte[0]),
                Err(e)
                    if matches!(
                        e.kind(),
                        ErrorKind::TimedOut | ErrorKind::WouldBlock | ErrorKind::Interrupted
                    ) => {}
                Err(source) => {
                    return Err(DeviceError::Io {
                        op: format!("reading from {}", self.name),
                        source,
                    })
                }
            }
        }
        Ok(if overlong {
            Reply::Overlong(line)
        } else {
            Reply::Silent
        })
    }

    /// Discard anything still arriving (a late reply to an earlier try).
    fn drain(&mut self) {
        let deadline = Instant::now() + Duration::from_millis(30);
        let mut buf = [0u8; 256];
        while Instant::now() < deadline {
            match self.port.read(&mut buf) {
                Ok(n) if n > 0 => continue,
                _ => std::thread::sleep(Duration::from_millis(2)),
            }
        }
    }

    fn parse_state(line: &str) -> LampState {
        match line.split_whitespace().collect::<Vec<_>>().as_slice() {
            ["ON", level] => LampState {
                on: true,
                level: level.parse().unwrap_or(0),
            },
            _ => LampState::OFF,
        }
    }

    fn verify(&mut self, command: &str, expected: LampState) -> Result<LampState, DeviceError> {
        let got = self.state()?;
        if got != expected {
            return Err(DeviceError::LampState {
                lamp: self.name.clone(),
                command: command.into(),
                expected,
                got,
            });
        }
        Ok(got)
    }
}

fn valid_ascii(line: &str) -> bool {
    !line.is_empty() && line.bytes().all(|b| (0x20..0x7f).contains(&b))
}

fn valid_reply(line: &str, expect: Expect) -> bool {
    if !valid_ascii(line) {
        return false;
    }
    match expect {
        Expect::Identity => true,
        Expect::Ok => line == "OK",
        Expect::State => {
            line == "OFF"
                || line
                    .strip_prefix("ON ")
                    .and_then(|l| l.parse::<u16>().ok())
                    .is_some_and(|l| l <= 1000)
        }
    }
}

impl<P: Read + Write + Send> Lamp for SerialLamp<P> {
    fn describe(&self) -> String {
        self.name.clone()
    }

    fn identify(&mut self) -> Result<String, DeviceError> {
        let cmd = self.policy.commands.identify.clone();
        self.transact(&cmd, Expect::Identity)
    }

    fn switch_on(&mut self, level: u16) -> Result<LampState, DeviceError> {
        let level_cmd = self
            .policy
            .commands
            .level
            .replace("{level}", &level.to_string());
        self.transact(&level_cmd, Expect::Ok)?;
        let on = self.policy.commands.on.clone();
        self.transact(&on, Expect::Ok)?;
        self.verify(&on, LampState { on: true, level })
    }

    fn switch_off(&mut self) -> Result<LampState, DeviceError> {
        let off = self.policy.commands.off.clone();
        self.transact(&off, Expect::Ok)?;
        self.verify(&off, LampState::OFF)
    }

    fn state(&mut self) -> Result<LampState, DeviceError> {
        let cmd = self.policy.commands.state.clone();
        let line = self.transact(&cmd, Expect::State)?;
        Ok(Self::parse_state(&line))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::VecDeque;

    /// A scripted lamp: each written line pops the next canned reply (or silence).
    struct Script {
        replies: VecDeque<Option<&'static [u8]>>,
        pending: VecDeque<u8>,
        written: Vec<u8>,
    }

    impl Read for Script {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            match self.pending.pop_front() {
                Some(b) => {
                    buf[0] = b;
                    Ok(1)
                }
                None => Err(ErrorKind::TimedOut.into()),
            }
        }
    }
    impl Write for Script {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            self.written.extend_from_slice(buf);
            if buf.ends_with(b"\n") {
                if let Some(Some(r)) = self.replies.pop_front() {
                    self.pending.extend(r.iter().copied());
                }
            }
            Ok(buf.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    fn lamp(replies: Vec<Option<&'static [u8]>>) -> SerialLamp<Script> {
        let policy = LampPolicy {
            reply_timeout: Duration::from_millis(30),
            tries: 3,
            commands: LampCommands::default(),
        };
        SerialLamp::new(
            Script {
                replies: replies.into(),
                pending: VecDeque::new(),
                written: vec![],
            },
            "test lamp".into(),
            policy,
        )
    }

    #[test]
    fn switches_on_and_verifies() {
        let mut l = lamp(vec![Some(b"OK\n"), Some(b"OK\r\n"), Some(b"ON 700\n")]);
        assert_eq!(
            l.switch_on(700).unwrap(),
            LampState {
                on: true,
                level: 700
            }
        );
        assert_eq!(
            String::from_utf8(l.port.written.clone()).unwrap(),
            "LEVEL 700\nON\nSTATE?\n"
        );
    }

    #[test]
    fn retries_after_garbage_and_silence() {
        let mut l = lamp(vec![Some(b"\xff\xfe\n"), None, Some(b"OFF\n")]);
        assert_eq!(l.state().unwrap(), LampState::OFF);
    }

    #[test]
    fn gives_up_after_bounded_tries() {
        let mut l = lamp(vec![None, None, None, Some(b"OFF\n")]);
        let e = l.state().unwrap_err().to_string();
        assert!(
            e.contains("did not answer `STATE?` (3 tries, 30 ms each)"),
            "{e}"
        );
        let mut l = lamp(vec![
            Some(b"O\x01K\n"),
            Some(b"garbage\n"),
            Some(b"ON 99999\n"),
        ]);
        let e = l.state().unwrap_err().to_string();
        assert!(
            e.contains("garbled replies to `STATE?`") && e.contains("lamp.baud"),
            "{e}"
        );
    }

    #[test]
    fn reports_a_refusal_and_a_wrong_state() {
        let mut l = lamp(vec![Some(b"ERR 2 level out of range\n")]);
        assert!(l
            .switch_on(5000)
            .unwrap_err()
            .to_string()
            .contains("refused `LEVEL 5000`: ERR 2"));
        let mut l = lamp(vec![Some(b"OK\n"), Some(b"OK\n"), Some(b"OFF\n")]);
        let e = l.switch_on(1000).unwrap_err().to_string();
        assert!(
            e.contains("reads back as off after `ON`, expected on at level 1000"),
            "{e}"
        );
    }

    fn leaked(v: Vec<u8>) -> &'static [u8] {
        Vec::leak(v)
    }

    #[test]
    fn a_refusal_with_a_huge_reply_is_quoted_short() {
        // Was: `LampRefused` quoted an 18,804-byte reply whole.
        let mut reply = b"ERR".to_vec();
        reply.extend(std::iter::repeat_n(b'E', 3000));
        reply.push(b'\n');
        let mut l = lamp(vec![Some(leaked(reply))]);
        let e = l.switch_off().unwrap_err().to_string();
        assert!(
            e.contains("refused `OFF`: ERREEE") && e.contains("(3003 bytes)"),
            "{e}"
        );
        assert!(e.chars().count() < 200, "{e}");
    }

    #[test]
    fn a_garbled_overlong_reply_is_quoted_short_and_not_kept_whole() {
        // Was: `LampGarbled` quoted a 5,841-byte line whole, and read_line kept any length.
        let mut reply = vec![b'A'; 5841];
        reply.push(b'\n');
        let r = leaked(reply);
        let mut l = lamp(vec![Some(r), Some(r), Some(r)]);
        let e = l.switch_off().unwrap_err().to_string();
        assert!(e.contains("garbled replies to `OFF`"), "{e}");
        assert!(
            e.contains("more than 4096 bytes") && e.chars().count() < 300,
            "{e}"
        );
        // Control characters of a garbled line are escaped, on one line.
        let mut l = lamp(vec![
            Some(b"O\rK\x1b\n"),
            Some(b"O\rK\n"),
            Some(b"\rOK\r\n"),
        ]);
        let e = l.switch_off().unwrap_err().to_string();
        assert!(!e.contains('\r') && e.contains("\\r"), "{e}");
    }

    /// A device that sends the same byte for ever.
    struct Spew;
    impl Read for Spew {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            buf.fill(b'A');
            Ok(buf.len())
        }
    }
    impl Write for Spew {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            Ok(buf.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn a_device_spewing_bytes_keeps_at_most_one_bounded_line() {
        let policy = LampPolicy {
            reply_timeout: Duration::from_millis(50),
            tries: 1,
            commands: LampCommands::default(),
        };
        let mut l = SerialLamp::new(Spew, "spewing lamp".into(), policy);
        match l.read_line().unwrap() {
            Reply::Overlong(start) => assert_eq!(start.len(), MAX_LINE_BYTES),
            _ => panic!("an endless line is overlong"),
        }
        let e = l.state().unwrap_err().to_string();
        assert!(
            e.contains("garbled replies to `STATE?`") && e.len() < 300,
            "{e}"
        );
    }
}
