//! The serial lamp driver: a lamp protocol ([`super::lamp_protocol`]) over any
//! `Read + Write`, built for real serial links.
//!
//! Real links deliver replies late, split across reads, echoed, overlong, with CR, LF or
//! CRLF line ends, and with noise. The driver:
//!
//! - reads in chunks into its own buffer and cuts lines at the protocol's terminator (`auto`:
//!   CR, LF or CRLF, a CRLF split across reads included), keeping at most
//!   `max_line_bytes` of a line (the rest is counted and dropped);
//! - counts replies against the tries it sent: replies come in order, so a line that arrives
//!   while an earlier try's reply is still owed is that earlier reply. A late success is
//!   taken (the command is the same), a late refusal of an earlier try is skipped while the
//!   latest try may still succeed, and the replies still owed when a command succeeds are
//!   awaited and dropped before the next command, so the link never falls one reply behind;
//! - keeps a line begun before a timeout and completes it with the bytes after it (a reply
//!   split across the timeout is one reply, never glued onto the next), and drops whatever
//!   is left unclaimed before each new command (input flushed);
//! - skips the device's echo of a command and a trailer line (`OK` after each reply);
//! - after every switching command reads the state back (and the level, if the state reply
//!   does not carry it) and checks it, in the device's own units;
//! - names the likely cause when it gives up: silence (power, cable, port, baud), noise
//!   (baud), no line end (terminator), an overlong line (terminator), an unknown reply
//!   (protocol), a late device (timeout), or a port that vanished (unplugged).
//!
//! It opens a serial port only in [`SerialLamp::open`], so tests drive it over a
//! pseudo-terminal or a byte script.

use std::io::{ErrorKind, Read, Write};
use std::time::{Duration, Instant};

use super::lamp_protocol::{CommandKind, Protocol, Terminator};
use crate::error::DeviceError;
use crate::traits::Lamp;
use glint_format::image::LampState;

/// Timing, retry policy and protocol.
#[derive(Debug, Clone)]
pub struct LampPolicy {
    pub reply_timeout: Duration,
    pub tries: u32,
    pub protocol: Protocol,
}

impl LampPolicy {
    /// The policy a rig's `[lamp]` section sets.
    pub fn from_rig(lamp: &crate::rig::LampSection) -> Result<Self, DeviceError> {
        Ok(LampPolicy {
            reply_timeout: Duration::from_millis(lamp.reply_timeout_ms),
            tries: lamp.tries.max(1),
            protocol: lamp.resolved_protocol()?,
        })
    }

    /// Glint's own protocol (docs/design.md) with this timeout and number of tries.
    pub fn glint(reply_timeout: Duration, tries: u32) -> Self {
        LampPolicy {
            reply_timeout,
            tries: tries.max(1),
            protocol: Protocol::preset(super::lamp_protocol::LampPreset::Glint),
        }
    }
}

/// Longest reply line the driver keeps by default, bytes (replies of the protocols are a
/// few bytes; an identity a few dozen).
pub const MAX_LINE_BYTES: usize = 4096;

/// How many bytes of an overlong line are kept to quote it.
const QUOTED_START: usize = 64;

/// A printable reply for an error: at most [`glint_format::fsx::QUOTE_CHARS`] characters.
fn cut(line: &str) -> String {
    if line.chars().count() <= glint_format::fsx::QUOTE_CHARS {
        line.into()
    } else {
        let start: String = line.chars().take(glint_format::fsx::QUOTE_CHARS).collect();
        format!("{start}… ({} bytes)", line.len())
    }
}

fn quote_bytes(b: &[u8]) -> String {
    glint_format::fsx::quote(&String::from_utf8_lossy(b))
}

/// What the line reader got.
#[derive(Debug)]
enum Got {
    /// A line, without its terminator.
    Line(Vec<u8>),
    /// A line longer than the limit: its first bytes and its whole length.
    Overlong { start: Vec<u8>, len: usize },
    /// Nothing complete before the deadline.
    Timeout,
}

/// Cuts lines out of the bytes received.
#[derive(Debug)]
struct LineReader {
    buf: Vec<u8>,
    term: Terminator,
    max: usize,
    /// `auto`: the last line ended with CR, so an LF that comes next is its CRLF's end.
    swallow_lf: bool,
    /// Dropping an overlong line: its first bytes and its length so far.
    overlong: Option<(Vec<u8>, usize)>,
}

impl LineReader {
    fn new(term: Terminator, max: usize) -> Self {
        LineReader {
            buf: Vec::with_capacity(4096),
            term,
            max,
            swallow_lf: false,
            overlong: None,
        }
    }

    /// Where the first line ends: (index of its terminator, terminator length).
    fn find_end(&self) -> Option<(usize, usize)> {
        match self.term {
            Terminator::Auto => self
                .buf
                .iter()
                .position(|b| *b == b'\r' || *b == b'\n')
                .map(|i| (i, 1)),
            Terminator::Lf => self.buf.iter().position(|b| *b == b'\n').map(|i| (i, 1)),
            Terminator::Cr => self.buf.iter().position(|b| *b == b'\r').map(|i| (i, 1)),
            Terminator::Crlf => self
                .buf
                .windows(2)
                .position(|w| w == b"\r\n")
                .map(|i| (i, 2)),
        }
    }

    /// Keep memory bounded while no line ends: a line past the limit is counted, not kept
    /// (a last CR, which may begin a CRLF, stays).
    fn bound(&mut self) {
        if self.buf.len() <= self.max || self.find_end().is_some() {
            return;
        }
        let keep = usize::from(self.buf.last() == Some(&b'\r'));
        let drop = self.buf.len() - keep;
        let entry = self
            .overlong
            .get_or_insert_with(|| (self.buf[..QUOTED_START.min(drop)].to_vec(), 0));
        entry.1 += drop;
        self.buf.drain(..drop);
    }

    /// One complete line from what has been received, if there is one. Blank lines are
    /// skipped (no protocol replies with one; they are the CR or LF of another line end).
    fn take(&mut self) -> Option<Got> {
        loop {
            if self.swallow_lf && !self.buf.is_empty() {
                if self.buf[0] == b'\n' {
                    self.buf.remove(0);
                }
                self.swallow_lf = false;
            }
            let Some((i, tlen)) = self.find_end() else {
                self.bound();
                return None;
            };
            let ended_by_cr = self.buf[i] == b'\r' && tlen == 1;
            let mut line: Vec<u8> = self.buf.drain(..i + tlen).collect();
            line.truncate(i);
            if self.term == Terminator::Auto && ended_by_cr {
                self.swallow_lf = true;
            }
            if self.term == Terminator::Lf && line.last() == Some(&b'\r') {
                line.pop();
            }
            if let Some((start, len)) = self.overlong.take() {
                return Some(Got::Overlong {
                    start,
                    len: len + line.len(),
                });
            }
            if line.len() > self.max {
                return Some(Got::Overlong {
                    start: line[..QUOTED_START.min(line.len())].to_vec(),
                    len: line.len(),
                });
            }
            if line.is_empty() {
                continue;
            }
            return Some(Got::Line(line));
        }
    }

    /// A line begun and not ended: its first bytes and its length.
    fn partial(&self) -> Option<(Vec<u8>, usize)> {
        if let Some((start, len)) = &self.overlong {
            return Some((start.clone(), len + self.buf.len()));
        }
        let b: Vec<u8> = self
            .buf
            .iter()
            .copied()
            .filter(|b| *b != b'\r' && *b != b'\n')
            .collect();
        let len = b.len();
        (len > 0).then(|| (b.into_iter().take(QUOTED_START).collect(), len))
    }

    fn clear(&mut self) {
        self.buf.clear();
        self.overlong = None;
        self.swallow_lf = false;
    }
}

/// The reply a command expects.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Expect {
    Identity,
    Success,
    State,
    Level,
}

/// Why a command got no reply it could use.
#[derive(Debug)]
enum Unusable {
    /// Printable text that matches no reply of the protocol.
    Unknown(String),
    /// Bytes that are not printable ASCII.
    Noise(Vec<u8>),
    /// A line longer than the limit.
    Overlong { start: Vec<u8>, len: usize },
}

/// A level the device can have.
fn in_range(text: &str, [lo, hi]: [u32; 2]) -> bool {
    text.parse::<u32>().is_ok_and(|l| (lo..=hi).contains(&l))
}

/// Is this error the port going away (a USB adapter unplugged, a pty whose other end
/// closed) rather than a passing fault?
fn is_gone(e: &std::io::Error) -> bool {
    matches!(
        e.kind(),
        ErrorKind::BrokenPipe
            | ErrorKind::NotConnected
            | ErrorKind::UnexpectedEof
            | ErrorKind::ConnectionReset
            | ErrorKind::ConnectionAborted
            | ErrorKind::NotFound
    ) || matches!(
        e.raw_os_error(),
        Some(libc::EIO) | Some(libc::ENXIO) | Some(libc::ENODEV) | Some(libc::EBADF)
    )
}

/// A lamp controller on a serial line (or anything that reads and writes bytes).
pub struct SerialLamp<P> {
    port: P,
    name: String,
    policy: LampPolicy,
    reader: LineReader,
    /// Reply lines still to come for earlier tries of the last command.
    owed: usize,
    /// Echoes still to come of the last command's tries (`echo = true`), which come
    /// before the replies owed and are not replies.
    echoes_owed: usize,
    /// The last command and the reply it expected, to know its echo among the replies owed.
    last_command: String,
    last_expect: Expect,
    /// When the last command's last try was sent.
    last_sent: Option<Instant>,
    /// When the last reply taken arrived, and the timeout of its command: replies still
    /// owed are awaited for two timeouts after the later of this and `last_sent`.
    last_reply: Option<(Instant, Duration)>,
    /// When the last command ended (for `command_gap_ms`).
    last_done: Option<Instant>,
    warned_echo: bool,
    warned_late: bool,
    /// Nothing waits past this (a hurried switch-off): no reply, no retry.
    hurry_deadline: Option<Instant>,
}

impl SerialLamp<Box<dyn serialport::SerialPort>> {
    /// Open a serial port by path (`/dev/ttyUSB0`, `/dev/serial/by-id/...`, or a
    /// pseudo-terminal) and do what the protocol asks on connection (drain a greeting, send
    /// a blank line).
    pub fn open(path: &str, baud: u32, policy: LampPolicy) -> Result<Self, DeviceError> {
        let port = serialport::new(path, baud)
            // Short reads; the driver keeps its own per-reply deadline.
            .timeout(Duration::from_millis(10))
            .open()
            .map_err(|e| DeviceError::Open {
                what: format!("lamp port {path}"),
                reason: format!(
                    "{e}; check lamp.port (a /dev/serial/by-id/ name stays the same across replugs), that the controller is plugged in, and that no other program has the port open"
                ),
            })?;
        let mut lamp = SerialLamp::new(port, format!("lamp on {path}"), policy);
        lamp.connect()?;
        Ok(lamp)
    }
}

impl<P: Read + Write + Send> SerialLamp<P> {
    /// Drive a lamp over an already open byte stream (nothing is sent until asked; see
    /// [`SerialLamp::connect`]).
    pub fn new(port: P, name: String, policy: LampPolicy) -> Self {
        let reader = LineReader::new(
            policy.protocol.receive_terminator,
            policy.protocol.max_line_bytes,
        );
        SerialLamp {
            port,
            name,
            policy,
            reader,
            owed: 0,
            echoes_owed: 0,
            last_command: String::new(),
            last_expect: Expect::Success,
            last_sent: None,
            last_reply: None,
            last_done: None,
            warned_echo: false,
            warned_late: false,
            hurry_deadline: None,
        }
    }

    /// What the protocol asks on connection: drain a greeting until the line is quiet,
    /// and send a blank line whose reply is dropped.
    pub fn connect(&mut self) -> Result<(), DeviceError> {
        if let Some(quiet) = self.policy.protocol.drain {
            // Until the line has been quiet for `quiet`, at most five times that long.
            let end = Instant::now() + quiet * 5;
            let mut quiet_until = Instant::now() + quiet;
            let mut drained = 0usize;
            while Instant::now() < quiet_until.min(end) {
                let n = self.read_some()?;
                // Discarded as it comes: a chatty device cannot grow the buffer.
                self.reader.clear();
                if n > 0 {
                    drained += n;
                    quiet_until = Instant::now() + quiet;
                }
            }
            if drained > 0 {
                tracing::debug!(lamp = %self.name, bytes = drained, "drained the lamp's greeting");
            }
            self.reader.clear();
        }
        if self.policy.protocol.blank_line {
            self.send_line("")?;
            let deadline = Instant::now() + self.policy.reply_timeout;
            // Its reply (often an error) is dropped; a device that says nothing is fine too,
            // but a reply still to come is owed, awaited and dropped before the first command.
            if let Got::Timeout = self.next_line(deadline)? {
                self.owed = 1;
                self.echoes_owed = 0;
                self.last_command.clear();
                self.last_reply = self.last_sent.map(|s| (s, self.policy.reply_timeout));
            }
            self.last_done = Some(Instant::now());
        }
        self.flush_input()?;
        Ok(())
    }

    /// A failed read or write: the port gone (each later command tries again, and fails
    /// at once while it stays gone), or another I/O error.
    fn io_error(&mut self, op: &str, source: std::io::Error) -> DeviceError {
        if is_gone(&source) {
            DeviceError::LampGone {
                lamp: self.name.clone(),
                reason: format!("{op}: {source}"),
            }
        } else {
            DeviceError::Io {
                op: format!("{op} ({})", self.name),
                source,
            }
        }
    }

    /// Read what has arrived into the line reader: the number of bytes (0 when the
    /// port's short read timed out).
    fn read_some(&mut self) -> Result<usize, DeviceError> {
        let mut chunk = [0u8; 4096];
        match self.port.read(&mut chunk) {
            Ok(0) => {
                std::thread::sleep(Duration::from_millis(2));
                Ok(0)
            }
            Ok(n) => {
                self.reader.buf.extend_from_slice(&chunk[..n]);
                // Bound memory even before lines are cut.
                if self.reader.buf.len() > self.reader.max + chunk.len() {
                    self.reader.bound();
                }
                Ok(n)
            }
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::TimedOut | ErrorKind::WouldBlock | ErrorKind::Interrupted
                ) =>
            {
                Ok(0)
            }
            Err(e) => Err(self.io_error("reading", e)),
        }
    }

    /// The next line, or [`Got::Timeout`] at `deadline`.
    fn next_line(&mut self, deadline: Instant) -> Result<Got, DeviceError> {
        let deadline = self.hurry_deadline.map_or(deadline, |h| h.min(deadline));
        loop {
            if let Some(g) = self.reader.take() {
                return Ok(g);
            }
            if Instant::now() >= deadline {
                return Ok(Got::Timeout);
            }
            self.read_some()?;
        }
    }

    /// Drop whatever has arrived and is not claimed.
    fn flush_input(&mut self) -> Result<(), DeviceError> {
        // At most a few reads: a device that never stops sending cannot hold us here.
        for _ in 0..64 {
            if self.read_some()? == 0 {
                break;
            }
        }
        self.reader.clear();
        Ok(())
    }

    fn send_line(&mut self, command: &str) -> Result<(), DeviceError> {
        let mut bytes = command.as_bytes().to_vec();
        bytes.extend_from_slice(self.policy.protocol.send_terminator.bytes());
        let written = self.port.write_all(&bytes).and_then(|_| self.port.flush());
        if let Err(e) = written {
            let op = format!("writing `{command}`");
            return Err(self.io_error(&op, e));
        }
        self.last_sent = Some(Instant::now());
        Ok(())
    }

    /// Before a new command: wait for the replies earlier tries still owe (and drop them),
    /// drop anything else unclaimed, and keep the pause the protocol asks between commands.
    fn before_command(&mut self) -> Result<(), DeviceError> {
        if self.owed > 0 {
            let (arrived, timeout) = self
                .last_reply
                .unwrap_or((Instant::now(), self.policy.reply_timeout));
            let since = self.last_sent.map_or(arrived, |s| s.max(arrived));
            let deadline = since + timeout * 2;
            while self.owed > 0 {
                match self.next_line(deadline)? {
                    Got::Timeout => break,
                    Got::Line(l) => {
                        if self.policy.protocol.trailer.as_deref().map(str::as_bytes)
                            == Some(l.as_slice())
                        {
                            continue;
                        }
                        if l == self.last_command.as_bytes() {
                            // The echo of a later try, as `exchange` tells it from a reply.
                            if self.echoes_owed > 0 {
                                self.echoes_owed -= 1;
                                continue;
                            }
                            let text = String::from_utf8_lossy(&l);
                            if self.last_expect == Expect::Identity
                                || !self.matches(self.last_expect, &text)
                            {
                                continue;
                            }
                        }
                        tracing::debug!(lamp = %self.name, reply = %quote_bytes(&l), "dropped a late reply to an earlier try");
                        self.owed -= 1;
                    }
                    Got::Overlong { .. } => self.owed -= 1,
                }
            }
            self.owed = 0;
        }
        self.echoes_owed = 0;
        self.flush_input()?;
        if let Some(done) = self.last_done {
            let gap = self.policy.protocol.command_gap;
            let since = done.elapsed();
            if since < gap {
                std::thread::sleep(gap - since);
            }
        }
        Ok(())
    }

    fn matches(&self, expect: Expect, line: &str) -> bool {
        let p = &self.policy.protocol;
        match expect {
            Expect::Identity => p.identity.is_match(line),
            Expect::Success => p.success.is_match(line),
            Expect::State => {
                p.state_off.is_match(line)
                    || p.state_on.captures(line).is_some_and(|c| {
                        c.name("level")
                            .is_none_or(|m| in_range(m.as_str(), p.level_range))
                    })
            }
            Expect::Level => p
                .level_reply
                .as_ref()
                .and_then(|r| r.captures(line))
                .and_then(|c| c.name("level"))
                .is_some_and(|m| in_range(m.as_str(), p.level_range)),
        }
    }

    /// Send one command and return its reply line, with bounded retries.
    fn transact(
        &mut self,
        kind: CommandKind,
        command: &str,
        expect: Expect,
    ) -> Result<String, DeviceError> {
        self.before_command()?;
        let result = self.exchange(kind, command, expect);
        self.last_done = Some(Instant::now());
        result
    }

    fn exchange(
        &mut self,
        kind: CommandKind,
        command: &str,
        expect: Expect,
    ) -> Result<String, DeviceError> {
        let timeout = self
            .policy
            .protocol
            .timeout(kind, self.policy.reply_timeout);
        let tries = self.policy.tries;
        let echo = self.policy.protocol.echo;
        let trailer = self.policy.protocol.trailer.clone();
        let mut sent: Vec<Instant> = Vec::new();
        let mut seen = 0usize;
        let mut echoes_due = 0usize;
        let mut early_refusal: Option<String> = None;
        let mut unusable: Option<Unusable> = None;
        self.last_command = command.to_string();
        self.last_expect = expect;
        for attempt in 1..=tries {
            if attempt > 1 && self.hurry_deadline.is_some_and(|h| Instant::now() >= h) {
                break;
            }
            if attempt > 1 {
                tracing::warn!(lamp = %self.name, command, attempt, "retrying lamp command");
            }
            self.send_line(command)?;
            sent.push(Instant::now());
            if echo {
                echoes_due += 1;
            }
            let deadline = Instant::now() + timeout;
            loop {
                let (bytes, arrived) = match self.next_line(deadline)? {
                    Got::Timeout => break,
                    Got::Overlong { start, len } => {
                        seen += 1;
                        unusable = Some(Unusable::Overlong { start, len });
                        if seen < sent.len() {
                            continue;
                        }
                        break;
                    }
                    Got::Line(l) => (l, Instant::now()),
                };
                let printable = bytes.iter().all(|b| (0x20..0x7f).contains(b));
                let text = String::from_utf8_lossy(&bytes).into_owned();
                if printable && text == command {
                    // The device's echo of the command, unless it is a reply that may
                    // equal the command (a status line such as CoolLED's).
                    if echoes_due > 0 {
                        echoes_due -= 1;
                        continue;
                    }
                    if expect == Expect::Identity || !self.matches(expect, &text) {
                        if !self.warned_echo {
                            self.warned_echo = true;
                            tracing::warn!(lamp = %self.name, command, "the lamp echoes commands; set lamp.protocol.echo = true");
                        }
                        continue;
                    }
                }
                if printable
                    && trailer.as_deref() == Some(text.as_str())
                    && !self.matches(expect, &text)
                {
                    continue;
                }
                seen += 1;
                let latest = seen >= sent.len();
                // A refusal is a refusal even when the expected pattern would take it too
                // (the glint preset's identity is any line).
                let refused = printable && self.policy.protocol.error.is_match(&text);
                if printable && !refused && self.matches(expect, &text) {
                    // Replies come in order: this one answers try `seen`.
                    let try_sent = sent[seen.min(sent.len()) - 1];
                    let took = arrived.saturating_duration_since(try_sent);
                    if !latest && took > timeout && !self.warned_late {
                        self.warned_late = true;
                        tracing::warn!(
                            lamp = %self.name,
                            command,
                            "the lamp answered {} ms after the command, later than its {} ms timeout; raise lamp.reply_timeout_ms",
                            took.as_millis(),
                            timeout.as_millis()
                        );
                    }
                    self.owed = sent.len() - seen;
                    self.echoes_owed = echoes_due;
                    self.last_reply = Some((arrived, timeout));
                    return Ok(text);
                }
                if refused {
                    if !latest {
                        // A late refusal of an earlier try: the latest may still succeed.
                        early_refusal = Some(text);
                        continue;
                    }
                    self.owed = 0;
                    return Err(DeviceError::LampRefused {
                        lamp: self.name.clone(),
                        command: command.into(),
                        reply: cut(&text),
                    });
                }
                unusable = Some(if printable {
                    Unusable::Unknown(text)
                } else {
                    Unusable::Noise(bytes)
                });
                if !latest {
                    continue;
                }
                break;
            }
        }
        // Replies still owed (a line begun is one of them) are dropped before the next
        // command.
        self.owed = sent.len().saturating_sub(seen);
        self.echoes_owed = echoes_due;
        self.last_reply = Some((Instant::now(), timeout));
        let partial = self.reader.partial();
        Err(self.unanswered(command, timeout, unusable, partial, early_refusal))
    }

    /// The error for a command that got no usable reply in all its tries.
    fn unanswered(
        &self,
        command: &str,
        timeout: Duration,
        unusable: Option<Unusable>,
        partial: Option<(Vec<u8>, usize)>,
        early_refusal: Option<String>,
    ) -> DeviceError {
        let p = &self.policy.protocol;
        let tries = self.policy.tries;
        let garbled = |reply: String, hint: String| DeviceError::LampGarbled {
            lamp: self.name.clone(),
            command: command.into(),
            tries,
            detail: format!("last {reply}; {hint}"),
        };
        let baud_hint =
            "check lamp.baud (noise is what a wrong baud rate looks like) and the cable"
                .to_string();
        match (unusable, partial) {
            (Some(Unusable::Overlong { start, len }), _) => garbled(
                format!(
                    "a line of {len} bytes beginning {}",
                    quote_bytes(&start[..start.len().min(32)])
                ),
                format!(
                    "longer than lamp.protocol.max_line_bytes = {}: check lamp.protocol.receive_terminator (now {}) and lamp.baud",
                    p.max_line_bytes,
                    p.receive_terminator.name()
                ),
            ),
            (Some(Unusable::Noise(bytes)), _) => garbled(quote_bytes(&bytes), baud_hint),
            (Some(Unusable::Unknown(text)), _) => garbled(
                glint_format::fsx::quote(&text),
                format!(
                    "it matches none of the replies lamp.protocol expects (preset \"{}\"): check lamp.protocol.preset and lamp.protocol.replies",
                    p.preset.name()
                ),
            ),
            (None, Some((bytes, len))) => {
                let printable = bytes.iter().all(|b| (0x20..0x7f).contains(b));
                let shown = &bytes[..bytes.len().min(32)];
                let got = if len > shown.len() {
                    format!("{}… ({len} bytes)", quote_bytes(shown).trim_end_matches('…'))
                } else {
                    quote_bytes(shown)
                };
                if printable {
                    DeviceError::LampNoLineEnd {
                        lamp: self.name.clone(),
                        command: command.into(),
                        got,
                        terminator: p.receive_terminator.name(),
                    }
                } else {
                    garbled(got, baud_hint)
                }
            }
            (None, None) => match early_refusal {
                Some(reply) => DeviceError::LampRefused {
                    lamp: self.name.clone(),
                    command: command.into(),
                    reply: cut(&reply),
                },
                None => DeviceError::LampSilent {
                    lamp: self.name.clone(),
                    command: command.into(),
                    tries,
                    timeout,
                },
            },
        }
    }

    /// The state read back: on or off, and the level in the device's units.
    fn read_state(&mut self) -> Result<(bool, u32), DeviceError> {
        let cmd = self.policy.protocol.state.clone();
        let line = self.transact(CommandKind::State, &cmd, Expect::State)?;
        let p = &self.policy.protocol;
        if p.state_off.is_match(&line) {
            return Ok((false, 0));
        }
        let captured = p
            .state_on
            .captures(&line)
            .and_then(|c| c.name("level"))
            .map(|m| m.as_str().to_string());
        let level_text = match captured {
            Some(l) => l,
            None => match p.level_query.clone() {
                Some(q) => {
                    let reply = self.transact(CommandKind::LevelQuery, &q, Expect::Level)?;
                    self.policy
                        .protocol
                        .level_reply
                        .as_ref()
                        .and_then(|r| r.captures(&reply))
                        .and_then(|c| c.name("level"))
                        .map(|m| m.as_str().to_string())
                        .unwrap_or_default()
                }
                None => String::new(),
            },
        };
        let level = level_text.parse::<u32>().map_err(|_| DeviceError::LampGarbled {
            lamp: self.name.clone(),
            command: cmd.clone(),
            tries: 1,
            detail: format!(
                "{} carries no level; check lamp.protocol.replies.state_on (capture `(?P<level>\\d+)`) or lamp.commands.level_query",
                glint_format::fsx::quote(&line)
            ),
        })?;
        Ok((true, level))
    }

    fn verify(
        &mut self,
        command: &str,
        on: bool,
        device_level: u32,
    ) -> Result<LampState, DeviceError> {
        let (got_on, got_level) = self.read_state()?;
        if got_on != on || (on && got_level != device_level) {
            return Err(DeviceError::LampState {
                lamp: self.name.clone(),
                command: command.into(),
                expected: self.as_state(on, device_level),
                got: self.as_state(got_on, got_level),
            });
        }
        Ok(self.as_state(on, device_level))
    }

    /// A state read in the device's units, in Glint's (an off lamp has level 0).
    fn as_state(&self, on: bool, device_level: u32) -> LampState {
        if on {
            LampState {
                on: true,
                level: self.policy.protocol.from_device(device_level),
            }
        } else {
            LampState::OFF
        }
    }
}

impl<P: Read + Write + Send> Lamp for SerialLamp<P> {
    fn describe(&self) -> String {
        self.name.clone()
    }

    fn identify(&mut self) -> Result<String, DeviceError> {
        let cmd = self.policy.protocol.identify.clone();
        self.transact(CommandKind::Identify, &cmd, Expect::Identity)
    }

    fn switch_on(&mut self, level: u16) -> Result<LampState, DeviceError> {
        let p = &self.policy.protocol;
        let device_level = p.to_device(level);
        let level_cmd = p.level.as_ref().map(|c| p.with_level(c, device_level));
        let on = p.with_level(&p.on, device_level);
        if let Some(level_cmd) = level_cmd {
            self.transact(CommandKind::Level, &level_cmd, Expect::Success)?;
        }
        self.transact(CommandKind::On, &on, Expect::Success)?;
        self.verify(&on, true, device_level)
    }

    fn switch_off(&mut self) -> Result<LampState, DeviceError> {
        let p = &self.policy.protocol;
        let off = p.with_level(&p.off, 0);
        self.transact(CommandKind::Off, &off, Expect::Success)?;
        self.verify(&off, false, 0)
    }

    fn switch_off_quickly(&mut self) -> Result<LampState, DeviceError> {
        // One reply each for OFF and the read-back (with the pause between commands).
        let p = &self.policy.protocol;
        let bound = p.timeout(CommandKind::Off, self.policy.reply_timeout)
            + p.timeout(CommandKind::State, self.policy.reply_timeout)
            + p.command_gap * 2
            + Duration::from_millis(50);
        self.hurry_deadline = Some(Instant::now() + bound);
        let off = self.switch_off();
        self.hurry_deadline = None;
        off
    }

    fn state(&mut self) -> Result<LampState, DeviceError> {
        let (on, level) = self.read_state()?;
        Ok(self.as_state(on, level))
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
        /// Each read returns all that is pending (as a pty does), not one byte.
        whole: bool,
    }

    impl Read for Script {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            if self.pending.is_empty() {
                return Err(ErrorKind::TimedOut.into());
            }
            let n = if self.whole {
                self.pending.len().min(buf.len())
            } else {
                1
            };
            for (b, p) in buf.iter_mut().zip(self.pending.drain(..n)) {
                *b = p;
            }
            Ok(n)
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
        let policy = LampPolicy::glint(Duration::from_millis(30), 3);
        SerialLamp::new(
            Script {
                replies: replies.into(),
                pending: VecDeque::new(),
                written: vec![],
                whole: false,
            },
            "test lamp".into(),
            policy,
        )
    }

    fn lamp_with(
        section: super::super::lamp_protocol::LampProtocolSection,
        replies: Vec<Option<&'static [u8]>>,
    ) -> SerialLamp<Script> {
        let policy = LampPolicy {
            reply_timeout: Duration::from_millis(30),
            tries: 3,
            protocol: Protocol::resolve(&section, &Default::default()).unwrap(),
        };
        SerialLamp::new(
            Script {
                replies: replies.into(),
                pending: VecDeque::new(),
                written: vec![],
                whole: true,
            },
            "test lamp".into(),
            policy,
        )
    }

    #[test]
    fn a_line_over_a_short_max_line_bytes_is_named_not_a_panic() {
        // Was: with max_line_bytes below 64, a reply line longer than the limit but
        // shorter than 64 bytes, read in one chunk, panicked slicing its first 64 bytes.
        let section = super::super::lamp_protocol::LampProtocolSection {
            max_line_bytes: Some(16),
            ..Default::default()
        };
        let r: &[u8] = b"ACME LAMP CONTROLLER SN 4711\n";
        let mut l = lamp_with(section, vec![Some(r), Some(r), Some(r)]);
        let e = l.identify().unwrap_err().to_string();
        assert!(
            e.contains("a line of 28 bytes beginning `ACME LAMP CONTROLLER SN 4711`")
                && e.contains("max_line_bytes = 16"),
            "{e}"
        );
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
            e.contains("no usable reply to `STATE?` in 3 tries") && e.contains("lamp.protocol"),
            "{e}"
        );
    }

    #[test]
    fn reports_a_refusal_and_a_wrong_state() {
        let mut l = lamp(vec![Some(b"ERR 2 level out of range\n")]);
        assert!(l
            .switch_on(1000)
            .unwrap_err()
            .to_string()
            .contains("refused `LEVEL 1000`: ERR 2"));
        let mut l = lamp(vec![Some(b"OK\n"), Some(b"OK\n"), Some(b"OFF\n")]);
        let e = l.switch_on(1000).unwrap_err().to_string();
        assert!(
            e.contains("reads back as off after `ON`, expected on at level 1000"),
            "{e}"
        );
    }

    #[test]
    fn a_refusal_of_identify_is_a_refusal_not_the_identity() {
        // Was: the glint preset's identity pattern (any line) was tried before the error
        // pattern, so `ERR 1 unknown command` was recorded as the lamp's identity.
        let mut l = lamp(vec![Some(b"ERR 1 unknown command\n")]);
        let e = l.identify().unwrap_err();
        assert!(matches!(e, DeviceError::LampRefused { .. }), "{e:?}");
        assert!(e.to_string().contains("refused `*IDN?`: ERR 1"), "{e}");
        // A late refusal of a first try still gives way to the retry's identity.
        let mut l = lamp(vec![None, Some(b"ERR 7 checksum\nACME LAMP\n")]);
        assert_eq!(l.identify().unwrap(), "ACME LAMP");
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
        assert!(e.contains("no usable reply to `OFF`"), "{e}");
        assert!(
            e.contains("a line of 5841 bytes")
                && e.contains("max_line_bytes = 4096")
                && e.chars().count() < 400,
            "{e}"
        );
        // Control characters of a garbled line are escaped, on one line.
        let mut l = lamp(vec![
            Some(b"O\x1bK\x07\n"),
            Some(b"O\x1bK\n"),
            Some(b"\x1bOK\x08\r\n"),
        ]);
        let e = l.switch_off().unwrap_err().to_string();
        assert!(!e.chars().any(|c| c.is_control()), "{e}");
        assert!(e.contains("lamp.baud"), "{e}");
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

    /// A device that sends `reads` chunks of short lines, then nothing.
    struct Chatter {
        reads: usize,
    }
    impl Read for Chatter {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            if self.reads == 0 {
                return Err(ErrorKind::TimedOut.into());
            }
            self.reads -= 1;
            for (i, b) in buf.iter_mut().enumerate() {
                *b = if i % 2 == 0 { b'A' } else { b'\n' };
            }
            Ok(buf.len())
        }
    }
    impl Write for Chatter {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            Ok(buf.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn a_greeting_drained_on_connection_is_not_kept() {
        // Was: the drain kept every byte it read until the line went quiet (up to 5 x
        // drain_ms, 300 s): lines are not bounded like one overlong line, so a chatty
        // device grew the buffer without bound.
        let section = super::super::lamp_protocol::LampProtocolSection {
            on_connect: super::super::lamp_protocol::OnConnectSection {
                drain_ms: Some(1),
                blank_line: None,
            },
            ..Default::default()
        };
        let policy = LampPolicy {
            reply_timeout: Duration::from_millis(30),
            tries: 1,
            protocol: Protocol::resolve(&section, &Default::default()).unwrap(),
        };
        let mut l = SerialLamp::new(Chatter { reads: 256 }, "chatty lamp".into(), policy);
        l.connect().unwrap();
        assert!(
            l.reader.buf.capacity() <= MAX_LINE_BYTES + 2 * 4096,
            "{}",
            l.reader.buf.capacity()
        );
    }

    #[test]
    fn a_device_spewing_bytes_keeps_at_most_one_bounded_line() {
        let policy = LampPolicy::glint(Duration::from_millis(50), 1);
        let mut l = SerialLamp::new(Spew, "spewing lamp".into(), policy);
        let deadline = Instant::now() + Duration::from_millis(50);
        assert!(matches!(l.next_line(deadline).unwrap(), Got::Timeout));
        assert!(
            l.reader.buf.len() <= 2 * MAX_LINE_BYTES + 4096,
            "{}",
            l.reader.buf.len()
        );
        let e = l.state().unwrap_err().to_string();
        assert!(e.contains("without a line end") && e.len() < 400, "{e}");
    }
}
