//! The lamp: its physics (light output with a warm-up ramp), the light link that lets a
//! camera in another process be lit by it, and its firmware, which speaks one of the
//! [`protocol`] presets on a pseudo-terminal exactly as a USB-serial lamp controller would.
//! Glint drives it through its real serial driver by opening the terminal's path, the same
//! way it opens `/dev/ttyUSB0`.
//!
//! The firmware is one thread with one event loop, as a single-threaded controller is: it
//! reads command lines (ending in LF; a trailing CR is stripped), handles them one at a
//! time in order, and answers each with exactly one reply line, which the line faults of
//! [`Faults`] then delay, split, lengthen, garble, echo or follow with a trailer. While a
//! reply waits to be sent, later commands wait in the queue.
//!
//! The pseudo-terminal tells the firmware whether a program has its port open: reads on
//! the master side fail with EIO while nobody has the other end open. The first read that
//! does not (data, or a timeout) after one that did is a program opening the port: a
//! CoolLED says hello then. What the firmware sends while nobody listens is lost, as on a
//! serial line, and what it had sent that nobody read is dropped when the port is closed,
//! so a program reopening the port (a daemon does) starts clean.
//!
//! The light link: a firmware given a light file publishes the lamp's physical state there
//! on every change, atomically (a temporary file in the same folder, renamed), as one line
//! `glint-mock light v1 fraction=<0..1> since_ns=<CLOCK_MONOTONIC ns when last switched on>
//! warmup_ms=<ms>`. [`LampPhysics::remote`] reads it: a camera in another process is lit
//! by the lamp without any other channel between them.

pub mod protocol;

use std::collections::VecDeque;
use std::io::Write;
use std::os::fd::{AsRawFd, RawFd};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};

use crate::config::{Faults, LampConfig, MAX_LAMP_DELAY_MS, MAX_OVERLONG_BYTES};
use crate::MockError;
use protocol::{Controller, Light};

/// CLOCK_MONOTONIC now, nanoseconds: the clock every process on the machine shares.
pub fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime fills the timespec it is given.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// The light file of a lamp whose port is linked at `link`: the link's path with `.light`
/// appended (`/tmp/glint-lab/ttyLAMP0` → `/tmp/glint-lab/ttyLAMP0.light`).
pub fn light_file_for(link: &Path) -> PathBuf {
    let mut s = link.as_os_str().to_os_string();
    s.push(".light");
    PathBuf::from(s)
}

/// The first words of a light file.
pub const LIGHT_MAGIC: &str = "glint-mock light v1";

/// The lamp's physical state as the light file carries it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LightRecord {
    /// Output at full warm-up, 0..=1; 0 when the lamp is off.
    pub fraction: f64,
    /// CLOCK_MONOTONIC (ns) when the lamp was last switched on.
    pub since_ns: u64,
    /// The warm-up: output ramps linearly from 0 to `fraction` over this long, ms.
    pub warmup_ms: u64,
}

impl LightRecord {
    /// The record's line (with its newline).
    pub fn line(&self) -> String {
        format!(
            "{LIGHT_MAGIC} fraction={} since_ns={} warmup_ms={}\n",
            self.fraction, self.since_ns, self.warmup_ms
        )
    }

    /// A record from a light file's text; `None` if it is not one (keys may come in any
    /// order; keys it does not know are ignored).
    pub fn parse(text: &str) -> Option<LightRecord> {
        let line = text.strip_suffix('\n').unwrap_or(text);
        let rest = line.strip_prefix(LIGHT_MAGIC)?.strip_prefix(' ')?;
        let (mut fraction, mut since_ns, mut warmup_ms) = (None, None, None);
        for kv in rest.split(' ') {
            let (k, v) = kv.split_once('=')?;
            match k {
                "fraction" => fraction = Some(v.parse::<f64>().ok()?),
                "since_ns" => since_ns = Some(v.parse::<u64>().ok()?),
                "warmup_ms" => warmup_ms = Some(v.parse::<u64>().ok()?),
                _ => {}
            }
        }
        let fraction = fraction.filter(|f| (0.0..=1.0).contains(f))?;
        Some(LightRecord {
            fraction,
            since_ns: since_ns?,
            warmup_ms: warmup_ms?,
        })
    }

    /// Output at CLOCK_MONOTONIC `now_ns`: fraction × min(1, (now − since) / warm-up).
    pub fn output_at(&self, now_ns: u64) -> f64 {
        if self.fraction == 0.0 {
            return 0.0;
        }
        if self.warmup_ms == 0 {
            return self.fraction;
        }
        let elapsed = now_ns.saturating_sub(self.since_ns) as f64;
        self.fraction * (elapsed / (self.warmup_ms as f64 * 1e6)).min(1.0)
    }
}

/// Write `record` to `path` atomically: a temporary file beside it, renamed over it.
pub fn write_light_file(path: &Path, record: &LightRecord) -> std::io::Result<()> {
    let name = path
        .file_name()
        .ok_or_else(|| std::io::Error::other("a light file needs a file name"))?;
    let mut tmp_name = std::ffi::OsString::from(".");
    tmp_name.push(name);
    tmp_name.push(format!(".{}.tmp", std::process::id()));
    let tmp = path.with_file_name(tmp_name);
    let written = std::fs::write(&tmp, record.line()).and_then(|_| std::fs::rename(&tmp, path));
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written
}

/// The record in the light file at `path`, if there is a well-formed one.
pub fn read_light_file(path: &Path) -> Option<LightRecord> {
    let mut text = String::new();
    let f = std::fs::File::open(path).ok()?;
    // A light file is one short line; read no more than a page of whatever is there.
    std::io::Read::read_to_string(&mut std::io::Read::take(f, 4096), &mut text).ok()?;
    LightRecord::parse(&text)
}

#[derive(Debug)]
struct LocalState {
    on: bool,
    fraction: f64,
    since_ns: u64,
    publish: Option<PathBuf>,
}

#[derive(Debug)]
enum Source {
    /// The lamp is in this process: the firmware switches it.
    Local {
        state: Mutex<LocalState>,
        warmup: Duration,
    },
    /// The lamp is another process's: its light file says what it does.
    Remote {
        path: PathBuf,
        cache: Mutex<Option<(Instant, Option<LightRecord>)>>,
    },
}

/// How often a remote lamp's light file is read at most.
const REMOTE_RECHECK: Duration = Duration::from_millis(2);

/// The lamp's light output, shared between the firmware (which switches it) and the
/// camera (which is lit by it); or, in remote mode, read from another process's firmware.
#[derive(Debug)]
pub struct LampPhysics {
    source: Source,
}

impl LampPhysics {
    /// A lamp in this process, off, at full level, taking `warmup` to reach full output.
    pub fn new(warmup: Duration) -> Self {
        LampPhysics {
            source: Source::Local {
                state: Mutex::new(LocalState {
                    on: false,
                    fraction: 1.0,
                    since_ns: 0,
                    publish: None,
                }),
                warmup,
            },
        }
    }

    /// The lamp of another process, whose firmware publishes at `light_file`. A missing or
    /// malformed file is a dark lamp.
    pub fn remote(light_file: &Path) -> Self {
        LampPhysics {
            source: Source::Remote {
                path: light_file.to_path_buf(),
                cache: Mutex::new(None),
            },
        }
    }

    /// The lamp's state now, as its light file carries it.
    pub fn record(&self) -> LightRecord {
        match &self.source {
            Source::Local { state, warmup } => {
                let s = state.lock().unwrap_or_else(|e| e.into_inner());
                local_record(&s, *warmup)
            }
            Source::Remote { path, cache } => {
                let mut c = cache.lock().unwrap_or_else(|e| e.into_inner());
                let now = Instant::now();
                let fresh = match *c {
                    Some((at, rec)) if now.duration_since(at) < REMOTE_RECHECK => rec,
                    _ => {
                        let rec = read_light_file(path);
                        *c = Some((now, rec));
                        rec
                    }
                };
                fresh.unwrap_or(LightRecord {
                    fraction: 0.0,
                    since_ns: 0,
                    warmup_ms: 0,
                })
            }
        }
    }

    /// Output as a fraction of full intensity, ramping linearly over the warm-up.
    pub fn output(&self) -> f64 {
        self.record().output_at(monotonic_ns())
    }

    /// Publish the lamp's state at `light_file` now and on every change (a local lamp; a
    /// remote one publishes nothing).
    pub fn publish_to(&self, light_file: &Path) -> std::io::Result<()> {
        if let Source::Local { state, warmup } = &self.source {
            let mut s = state.lock().unwrap_or_else(|e| e.into_inner());
            write_light_file(light_file, &local_record(&s, *warmup))?;
            s.publish = Some(light_file.to_path_buf());
        }
        Ok(())
    }

    /// Light the lamp as a controller's state asks: switching it on starts the warm-up.
    pub(crate) fn set(&self, light: Light) {
        let Source::Local { state, warmup } = &self.source else {
            return;
        };
        let mut s = state.lock().unwrap_or_else(|e| e.into_inner());
        let before = (s.on, s.fraction, s.since_ns);
        if light.on && !s.on {
            s.since_ns = monotonic_ns();
        }
        s.on = light.on;
        if light.on {
            s.fraction = light.fraction.clamp(0.0, 1.0);
        }
        if (s.on, s.fraction, s.since_ns) != before {
            if let Some(p) = &s.publish {
                // A light file that cannot be written leaves the camera with the last
                // state; the lamp itself goes on.
                let _ = write_light_file(p, &local_record(&s, *warmup));
            }
        }
    }
}

fn local_record(s: &LocalState, warmup: Duration) -> LightRecord {
    LightRecord {
        fraction: if s.on { s.fraction } else { 0.0 },
        since_ns: s.since_ns,
        warmup_ms: warmup.as_millis().min(u64::MAX as u128) as u64,
    }
}

/// Bytes to put on the wire at a time.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Chunk {
    at: Instant,
    bytes: Vec<u8>,
    sent: usize,
}

impl Chunk {
    fn new(at: Instant, bytes: Vec<u8>) -> Chunk {
        Chunk { at, bytes, sent: 0 }
    }
}

/// Longest command line kept; the rest of a longer line is dropped (a controller's
/// receive buffer is small).
const MAX_LINE: usize = 4096;

/// The firmware's logic, apart from the terminal: the controller, the reply count and
/// the faults that act on each reply.
struct Firmware {
    controller: Controller,
    identity: String,
    faults: Faults,
    /// The terminator of every line sent.
    terminator: &'static str,
    /// Replies sent so far.
    answered: u32,
    garble: u64,
    physics: Arc<LampPhysics>,
}

impl Firmware {
    fn line(&self, text: &[u8]) -> Vec<u8> {
        let mut v = text.to_vec();
        v.extend_from_slice(self.terminator.as_bytes());
        v
    }

    fn greeting(&self) -> Option<Vec<u8>> {
        self.controller.greeting().map(|g| self.line(g.as_bytes()))
    }

    /// Handle one command line that arrived at `arrived`, taken up at `now`: what goes on
    /// the wire, and when. Order: echo (now); the reply (the preset's, or its error reply
    /// if the reply is to be an error, then made overlong, then garbled) at `now` or, if
    /// late, `lamp_late_ms` after the command arrived; split in two if it is to be; the
    /// trailer after a reply that is not an error.
    fn handle(&mut self, line: &str, arrived: Instant, now: Instant) -> Vec<Chunk> {
        let f = &self.faults;
        if f.lamp_silent_after.is_some_and(|s| self.answered >= s) {
            return Vec::new();
        }
        let mut out = Vec::new();
        if f.lamp_echo {
            out.push(Chunk::new(now, self.line(line.as_bytes())));
        }
        self.answered += 1;
        let n = self.answered;
        let reply = if f.lamp_error_replies.contains(&n) {
            self.controller.busy()
        } else {
            let r = self.controller.reply(&self.identity, line);
            self.physics.set(self.controller.light());
            r
        };
        let f = &self.faults;
        let mut text = reply.text.into_bytes();
        // Bounded as MockConfig::problems bounds them: spawn may be given any Faults.
        let delay = |ms: u64| Duration::from_millis(ms.min(MAX_LAMP_DELAY_MS));
        if f.lamp_overlong_replies.contains(&n) {
            text = (0..f.lamp_overlong_bytes.min(MAX_OVERLONG_BYTES))
                .map(|i| b'!' + (i % 94) as u8)
                .collect();
        }
        if f.lamp_garble_replies.contains(&n) {
            // Line noise: bytes flipped, non-ASCII garbage, same length.
            for b in text.iter_mut() {
                self.garble ^= self.garble << 13;
                self.garble ^= self.garble >> 7;
                self.garble ^= self.garble << 17;
                *b = 0x80 | (self.garble as u8 ^ *b);
            }
        }
        let late = f.lamp_late_ms > 0
            && (f.lamp_late_replies.is_empty() || f.lamp_late_replies.contains(&n));
        let at = if late {
            (arrived + delay(f.lamp_late_ms)).max(now)
        } else {
            now
        };
        let mut last = if f.lamp_split_replies.contains(&n) {
            let rest = text.split_off(text.len() / 2);
            out.push(Chunk::new(at, text));
            Chunk::new(at + delay(f.lamp_split_ms), self.line(&rest))
        } else {
            Chunk::new(at, self.line(&text))
        };
        if let Some(t) = f.lamp_trailer.as_ref().filter(|_| !reply.error) {
            last.bytes.extend(self.line(t.as_bytes()));
        }
        out.push(last);
        out
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
        LampFirmware::spawn_with(cfg, faults, physics, seed, None)
    }

    /// [`LampFirmware::spawn`], publishing the lamp's light at `light_file` if given (see
    /// [`LampPhysics::remote`]): it is written before this returns.
    pub fn spawn_with(
        cfg: &LampConfig,
        faults: &Faults,
        physics: Arc<LampPhysics>,
        seed: u64,
        light_file: Option<&Path>,
    ) -> Result<Self, MockError> {
        let (master, slave) = TTYPort::pair()
            .map_err(|e| MockError::Device(format!("cannot create a pseudo-terminal: {e}")))?;
        let path = slave
            .name()
            .ok_or_else(|| MockError::Device("the pseudo-terminal has no path".into()))?;
        // Release our end of the terminal: the controller opens it by path, exclusively,
        // as it would a USB serial adapter. The master keeps the terminal alive.
        drop(slave);
        let fd = master.as_raw_fd();
        // SAFETY: fcntl on a descriptor `master` owns.
        let nonblocking = unsafe {
            let flags = libc::fcntl(fd, libc::F_GETFL);
            flags >= 0 && libc::fcntl(fd, libc::F_SETFL, flags | libc::O_NONBLOCK) == 0
        };
        if !nonblocking {
            return Err(MockError::Device(format!(
                "pseudo-terminal: {}",
                std::io::Error::last_os_error()
            )));
        }
        if let Some(light) = light_file {
            physics.publish_to(light).map_err(|e| {
                MockError::Device(format!(
                    "cannot write the light file {}: {e}",
                    light.display()
                ))
            })?;
        }
        let log = match &cfg.command_log {
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
        let terminator = faults
            .lamp_terminator_bytes()
            .unwrap_or(cfg.preset.terminator());
        let firmware = Firmware {
            controller: Controller::new(cfg.preset),
            identity: cfg.identity.clone(),
            faults: faults.clone(),
            terminator,
            answered: 0,
            garble: seed | 1,
            physics,
        };
        let stop = Arc::new(AtomicBool::new(false));
        let commands = Arc::new(Mutex::new(Vec::new()));
        let wire = Wire {
            // Watched from before anybody can open the port, so no open goes unseen.
            opens: Opens::watch(&path),
            master,
            slave: path.clone(),
            stop: Arc::clone(&stop),
            commands: Arc::clone(&commands),
            log,
        };
        let thread = std::thread::Builder::new()
            .name("mock-lamp-firmware".into())
            .spawn(move || wire.run(firmware))
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
        self.commands
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
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

/// The firmware's end of the terminal.
struct Wire {
    opens: Option<Opens>,
    master: TTYPort,
    slave: String,
    stop: Arc<AtomicBool>,
    commands: Arc<Mutex<Vec<String>>>,
    log: Option<std::fs::File>,
}

/// The longest the firmware sleeps before it looks at the terminal and its stop flag again.
const TICK: Duration = Duration::from_millis(20);

/// Who has the port open, counted from inotify's open and close events on the terminal's
/// device node. The master's EIO alone misses a close and a reopen that come between two
/// of its reads (a daemon reopening at once); the events do not.
struct Opens {
    fd: std::os::fd::OwnedFd,
    /// Open files on the terminal's other end.
    count: u32,
    /// Events of the firmware's own opens (see [`Wire::drop_unread`]), not to be counted.
    skip_open: u32,
    skip_close: u32,
}

impl Opens {
    /// Watch `path`; `None` where inotify is not to be had (the EIO rule serves then).
    fn watch(path: &str) -> Option<Opens> {
        use std::os::fd::FromRawFd;
        let c = std::ffi::CString::new(path).ok()?;
        // SAFETY: inotify_init1 returns a new descriptor, owned from here on.
        let fd = unsafe { libc::inotify_init1(libc::IN_NONBLOCK | libc::IN_CLOEXEC) };
        if fd < 0 {
            return None;
        }
        // SAFETY: fd is a new descriptor nothing else owns.
        let fd = unsafe { std::os::fd::OwnedFd::from_raw_fd(fd) };
        let mask = libc::IN_OPEN | libc::IN_CLOSE_WRITE | libc::IN_CLOSE_NOWRITE;
        // SAFETY: a watch on a NUL-terminated path.
        if unsafe { libc::inotify_add_watch(fd.as_raw_fd(), c.as_ptr(), mask) } < 0 {
            return None;
        }
        Some(Opens {
            fd,
            count: 0,
            skip_open: 0,
            skip_close: 0,
        })
    }

    /// Read the events that came: each time the port went from closed to open (`true`)
    /// or from open to closed (`false`), in order.
    fn changes(&mut self) -> Vec<bool> {
        let mut out = Vec::new();
        let mut buf = [0u8; 4096];
        loop {
            // SAFETY: reading into a live buffer from a descriptor `self` owns.
            let n = unsafe { libc::read(self.fd.as_raw_fd(), buf.as_mut_ptr().cast(), buf.len()) };
            if n <= 0 {
                return out;
            }
            let header = std::mem::size_of::<libc::inotify_event>();
            let mut at = 0usize;
            while at + header <= n as usize {
                // SAFETY: the kernel wrote whole events; read_unaligned copes with any
                // alignment of the buffer.
                let ev: libc::inotify_event =
                    unsafe { std::ptr::read_unaligned(buf[at..].as_ptr().cast()) };
                at += header + ev.len as usize;
                if ev.mask & libc::IN_OPEN != 0 {
                    if self.skip_open > 0 {
                        self.skip_open -= 1;
                    } else {
                        self.count += 1;
                        if self.count == 1 {
                            out.push(true);
                        }
                    }
                }
                if ev.mask & (libc::IN_CLOSE_WRITE | libc::IN_CLOSE_NOWRITE) != 0 {
                    if self.skip_close > 0 {
                        self.skip_close -= 1;
                    } else if self.count > 0 {
                        self.count -= 1;
                        if self.count == 0 {
                            out.push(false);
                        }
                    }
                }
            }
        }
    }
}

/// The state of the line: whether a program has the port open, and what waits to be
/// handled and sent.
struct Line {
    connected: bool,
    /// The command line being received.
    partial: Vec<u8>,
    queue: VecDeque<(Instant, String)>,
    outbox: VecDeque<Chunk>,
}

impl Wire {
    fn fd(&self) -> RawFd {
        self.master.as_raw_fd()
    }

    fn run(mut self, mut fw: Firmware) {
        let mut opens = self.opens.take();
        let mut l = Line {
            connected: false,
            partial: Vec::new(),
            queue: VecDeque::new(),
            outbox: VecDeque::new(),
        };
        let mut buf = [0u8; 4096];
        while !self.stop.load(Ordering::Relaxed) {
            let now = Instant::now();
            if l.outbox.is_empty() {
                if let Some((arrived, cmd)) = l.queue.pop_front() {
                    l.outbox.extend(fw.handle(&cmd, arrived, now));
                }
            }
            let blocked = self.send_due(&mut l, now);
            if l.outbox.is_empty() && !l.queue.is_empty() {
                continue;
            }
            let mut wait = TICK;
            if let (false, Some(c)) = (blocked, l.outbox.front()) {
                wait = wait.min(c.at.saturating_duration_since(now));
            }
            let mut pfds = [
                libc::pollfd {
                    fd: self.fd(),
                    events: libc::POLLIN | if blocked { libc::POLLOUT } else { 0 },
                    revents: 0,
                },
                libc::pollfd {
                    fd: opens.as_ref().map_or(-1, |o| o.fd.as_raw_fd()),
                    events: libc::POLLIN,
                    revents: 0,
                },
            ];
            let ms = wait.as_micros().div_ceil(1000) as libc::c_int;
            // SAFETY: polling two pollfds that live across the call (a negative fd is
            // ignored).
            let ready = unsafe { libc::poll(pfds.as_mut_ptr(), 2, ms) };
            if ready < 0 {
                continue; // EINTR
            }
            if let Some(o) = opens.as_mut() {
                for open in o.changes() {
                    if open {
                        self.connect(&fw, &mut l);
                    } else if self.disconnect(&mut l, now) {
                        // The firmware's own open and close of the port: not a program's.
                        o.skip_open += 1;
                        o.skip_close += 1;
                    }
                }
            }
            let by_eio = opens.is_none();
            let master = pfds[0].revents;
            if ready == 0 || master & (libc::POLLIN | libc::POLLHUP | libc::POLLERR) == 0 {
                // Quiet, and no hang-up: somebody has the port open.
                if by_eio && ready == 0 && !l.connected {
                    self.connect(&fw, &mut l);
                }
                continue;
            }
            if by_eio && master & libc::POLLHUP != 0 && l.connected {
                // Closed (and perhaps open again already: the read says).
                let _ = self.disconnect(&mut l, now);
            }
            // SAFETY: reading into a live buffer from a descriptor `master` owns.
            let n = unsafe { libc::read(self.fd(), buf.as_mut_ptr().cast(), buf.len()) };
            let err = (n < 0).then(|| std::io::Error::last_os_error().raw_os_error());
            if n == 0 || err == Some(Some(libc::EINTR)) {
                continue;
            }
            if n < 0 && err != Some(Some(libc::EAGAIN)) {
                // EIO: nobody has the port open (yet, or any more).
                if by_eio && l.connected {
                    let _ = self.disconnect(&mut l, now);
                }
                // A hung-up terminal polls ready at once: look again a little later.
                std::thread::sleep(Duration::from_millis(5));
                continue;
            }
            if !l.connected && (by_eio || n > 0) {
                // (Data is a program on the other end, whatever the events said.)
                if let Some(o) = opens.as_mut() {
                    o.count = o.count.max(1);
                }
                self.connect(&fw, &mut l);
            }
            if n > 0 {
                self.receive(&mut l, &buf[..n as usize]);
            }
        }
    }

    /// Send what is due, as far as the terminal takes it; `true` if it takes no more now.
    fn send_due(&self, l: &mut Line, now: Instant) -> bool {
        while let Some(c) = l.outbox.front_mut() {
            if c.at > now {
                return false;
            }
            if !l.connected || c.sent >= c.bytes.len() {
                // Nobody listens: bytes on an unplugged line are lost.
                l.outbox.pop_front();
                continue;
            }
            let rest = &c.bytes[c.sent..];
            // SAFETY: writing from a live buffer to a descriptor `master` owns.
            let n = unsafe { libc::write(self.fd(), rest.as_ptr().cast(), rest.len()) };
            if n >= 0 {
                c.sent += n as usize;
                continue;
            }
            match std::io::Error::last_os_error().raw_os_error() {
                Some(libc::EINTR) => {}
                Some(libc::EAGAIN) => return true,
                _ => {
                    l.outbox.pop_front();
                }
            }
        }
        false
    }

    /// A program opened the port: the controller greets it, if it does.
    fn connect(&self, fw: &Firmware, l: &mut Line) {
        l.connected = true;
        if let Some(g) = fw.greeting() {
            l.outbox.push_front(Chunk::new(Instant::now(), g));
        }
    }

    /// The port was closed: what was due is lost, and what was sent and not read dropped.
    /// `true` if the firmware opened the port for that (see [`Wire::drop_unread`]).
    fn disconnect(&self, l: &mut Line, now: Instant) -> bool {
        l.connected = false;
        l.outbox.retain(|c| c.at > now && c.sent == 0);
        self.drop_unread()
    }

    /// Bytes came: complete command lines join the queue.
    fn receive(&mut self, l: &mut Line, bytes: &[u8]) {
        let arrived = Instant::now();
        for &b in bytes {
            if b == b'\n' {
                let mut raw = std::mem::take(&mut l.partial);
                if raw.last() == Some(&b'\r') {
                    raw.pop();
                }
                let cmd = String::from_utf8_lossy(&raw).into_owned();
                self.received(&cmd);
                l.queue.push_back((arrived, cmd));
            } else if l.partial.len() < MAX_LINE {
                l.partial.push(b);
            }
        }
    }

    /// A command line came: keep it, and log it.
    fn received(&mut self, cmd: &str) {
        self.commands
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(cmd.to_string());
        if let Some(f) = self.log.as_mut() {
            // The log is for observers; a failing log never stops the lamp.
            let _ = writeln!(f, "{cmd}").and_then(|_| f.flush());
        }
    }

    /// Drop what was sent to the port and not read, as a serial line loses what comes
    /// while nobody listens (best effort: the terminal's other end is opened for a moment
    /// to flush it).
    /// `true` if it opened the port.
    fn drop_unread(&self) -> bool {
        let Ok(path) = std::ffi::CString::new(self.slave.as_str()) else {
            return false;
        };
        // SAFETY: open, tcflush and close of a descriptor this function owns.
        unsafe {
            let fd = libc::open(
                path.as_ptr(),
                libc::O_RDWR | libc::O_NOCTTY | libc::O_NONBLOCK,
            );
            if fd < 0 {
                return false;
            }
            libc::tcflush(fd, libc::TCIFLUSH);
            libc::close(fd);
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::LampPreset;

    fn firmware(preset: LampPreset, faults: Faults) -> Firmware {
        Firmware {
            controller: Controller::new(preset),
            identity: "ID".into(),
            terminator: faults
                .lamp_terminator_bytes()
                .unwrap_or(preset.terminator()),
            faults,
            answered: 0,
            garble: 7,
            physics: Arc::new(LampPhysics::new(Duration::ZERO)),
        }
    }

    /// (ms after `t0`, bytes) of each chunk.
    fn wire(chunks: Vec<Chunk>, t0: Instant) -> Vec<(u128, String)> {
        chunks
            .into_iter()
            .map(|c| {
                (
                    (c.at - t0).as_millis(),
                    String::from_utf8_lossy(&c.bytes).into_owned(),
                )
            })
            .collect()
    }

    #[test]
    fn replies_and_terminators_of_each_preset() {
        let t0 = Instant::now();
        let mut g = firmware(LampPreset::Glint, Faults::default());
        assert_eq!(wire(g.handle("ON", t0, t0), t0), [(0, "OK\n".into())]);
        assert!((g.physics.output() - 1.0).abs() < 1e-12, "switched on");
        let mut l = firmware(LampPreset::Lumencor, Faults::default());
        assert_eq!(
            wire(l.handle("", t0, t0), t0),
            [(0, "E UNKNOWNCMD\r\n".into())]
        );
        let mut c = firmware(LampPreset::Coolled, Faults::default());
        assert_eq!(
            c.greeting().unwrap(),
            b"CoolLED precisExcite, Hello, pleased to meet you\r\n"
        );
        assert_eq!(
            wire(c.handle("CSSASN050", t0, t0), t0),
            [(0, "CSSASN050BXF000CXF000\r\n".into())]
        );
        assert!((c.physics.output() - 0.5).abs() < 1e-12);
    }

    #[test]
    fn a_late_error_from_a_first_try_with_echo_and_trailer() {
        let t0 = Instant::now();
        let mut fw = firmware(
            LampPreset::Glint,
            Faults {
                lamp_echo: true,
                lamp_trailer: Some("OK".into()),
                lamp_terminator: Some("crlf".into()),
                lamp_late_ms: 300,
                lamp_late_replies: vec![1],
                lamp_error_replies: vec![1],
                ..Faults::default()
            },
        );
        // Taken up 100 ms after it arrived: the echo goes now, the reply 300 ms after arrival.
        let now = t0 + Duration::from_millis(100);
        assert_eq!(
            wire(fw.handle("ON", t0, now), t0),
            [(100, "ON\r\n".into()), (300, "ERR 9 busy\r\n".into())]
        );
        assert_eq!(fw.physics.output(), 0.0, "a busy lamp did not execute ON");
        assert_eq!(
            wire(fw.handle("ON", now, now), t0),
            [(100, "ON\r\n".into()), (100, "OK\r\nOK\r\n".into())]
        );
        assert_eq!(fw.physics.output(), 1.0);
    }

    #[test]
    fn split_overlong_garbled_and_silent() {
        let t0 = Instant::now();
        let mut fw = firmware(
            LampPreset::Glint,
            Faults {
                lamp_split_replies: vec![1, 3],
                lamp_split_ms: 50,
                lamp_overlong_replies: vec![2, 3],
                lamp_overlong_bytes: 10,
                lamp_garble_replies: vec![4],
                lamp_silent_after: Some(4),
                lamp_terminator: Some("none".into()),
                ..Faults::default()
            },
        );
        assert_eq!(
            wire(fw.handle("STATE?", t0, t0), t0),
            [(0, "O".into()), (50, "FF".into())]
        );
        assert_eq!(
            wire(fw.handle("STATE?", t0, t0), t0),
            [(0, "!\"#$%&'()*".into())]
        );
        assert_eq!(
            wire(fw.handle("STATE?", t0, t0), t0),
            [(0, "!\"#$%".into()), (50, "&'()*".into())]
        );
        let garbled = fw.handle("STATE?", t0, t0);
        assert_eq!(garbled.len(), 1);
        assert_eq!(garbled[0].bytes.len(), 3);
        assert!(garbled[0].bytes.iter().all(|b| *b >= 0x80));
        assert!(fw.handle("ON", t0, t0).is_empty(), "silent after 4 replies");
        assert_eq!(fw.physics.output(), 0.0, "and a silent lamp does nothing");
    }

    #[test]
    fn faults_beyond_the_bounds_do_not_panic() {
        // LampFirmware::spawn takes Faults as they come (Lab::new checks them first).
        let t0 = Instant::now();
        let mut fw = firmware(
            LampPreset::Glint,
            Faults {
                lamp_late_ms: u64::MAX,
                lamp_split_replies: vec![1],
                lamp_split_ms: u64::MAX,
                ..Faults::default()
            },
        );
        let c = fw.handle("ON", t0, t0);
        assert_eq!((c[0].at - t0).as_millis(), MAX_LAMP_DELAY_MS as u128);
        assert_eq!((c[1].at - t0).as_millis(), 2 * MAX_LAMP_DELAY_MS as u128);
    }

    #[test]
    fn every_reply_late_when_no_list() {
        let t0 = Instant::now();
        let mut fw = firmware(
            LampPreset::Lumencor,
            Faults {
                lamp_late_ms: 40,
                ..Faults::default()
            },
        );
        for _ in 0..3 {
            let c = fw.handle("GET MODEL", t0, t0);
            assert_eq!((c[0].at - t0).as_millis(), 40);
        }
    }

    #[test]
    fn light_records_round_trip_and_refuse_garbage() {
        let r = LightRecord {
            fraction: 0.7,
            since_ns: 123_456_789,
            warmup_ms: 250,
        };
        assert_eq!(
            r.line(),
            "glint-mock light v1 fraction=0.7 since_ns=123456789 warmup_ms=250\n"
        );
        assert_eq!(LightRecord::parse(&r.line()), Some(r));
        assert_eq!(
            LightRecord::parse(
                "glint-mock light v1 warmup_ms=250 since_ns=123456789 fraction=0.7 pid=4"
            ),
            Some(r)
        );
        for bad in [
            "",
            "glint-mock light v1",
            "glint-mock light v2 fraction=0.7 since_ns=1 warmup_ms=2",
            "glint-mock light v1 fraction=1.5 since_ns=1 warmup_ms=2",
            "glint-mock light v1 fraction=NaN since_ns=1 warmup_ms=2",
            "glint-mock light v1 fraction=-0.1 since_ns=1 warmup_ms=2",
            "glint-mock light v1 fraction=0.5 since_ns=-1 warmup_ms=2",
            "glint-mock light v1 fraction=0.5 warmup_ms=2",
            "glint-mock light v1 fraction=0.5  since_ns=1 warmup_ms=2",
            "glint-mock light v1 fraction since_ns=1 warmup_ms=2",
        ] {
            assert_eq!(LightRecord::parse(bad), None, "{bad}");
        }
        // Ramps over the warm-up, and holds.
        assert_eq!(r.output_at(123_456_789), 0.0);
        assert!((r.output_at(123_456_789 + 125_000_000) - 0.35).abs() < 1e-9);
        assert!((r.output_at(u64::MAX) - 0.7).abs() < 1e-12);
        assert_eq!(r.output_at(0), 0.0, "before it was switched on");
    }

    #[test]
    fn remote_physics_follows_a_local_lamp_through_its_light_file() {
        let dir = tempfile::tempdir().unwrap();
        let light = light_file_for(&dir.path().join("ttyLAMP0"));
        assert_eq!(light, dir.path().join("ttyLAMP0.light"));
        let remote = LampPhysics::remote(&light);
        assert_eq!(remote.output(), 0.0, "no file: dark");
        let local = LampPhysics::new(Duration::ZERO);
        local.publish_to(&light).unwrap();
        local.set(Light {
            on: true,
            fraction: 0.25,
        });
        std::thread::sleep(REMOTE_RECHECK);
        assert!((remote.output() - 0.25).abs() < 1e-12);
        local.set(Light {
            on: false,
            fraction: 0.0,
        });
        std::thread::sleep(REMOTE_RECHECK);
        assert_eq!(remote.output(), 0.0);
        std::fs::write(&light, "rubbish").unwrap();
        std::thread::sleep(REMOTE_RECHECK);
        assert_eq!(remote.output(), 0.0);
        // Only the light file is left behind: no temporary files.
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(names.len(), 1);
    }

    #[test]
    fn warmup_ramps() {
        let p = LampPhysics::new(Duration::from_millis(400));
        p.set(Light {
            on: true,
            fraction: 1.0,
        });
        let early = p.output();
        std::thread::sleep(Duration::from_millis(450));
        assert!(early < 0.5, "{early}");
        assert_eq!(p.output(), 1.0);
    }
}
