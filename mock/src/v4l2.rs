//! The simulated camera served to the V4L2 preload library (`glint-sim-v4l2`).
//!
//! The launcher (`glint-mock v4l2`) owns one [`SimCamera`] and answers, on a Unix socket,
//! the requests the preload library makes for the programs it is loaded into. The device's
//! lasting state lives here: format, frame size and interval, control values, which
//! connection holds buffers and streams, and whether the camera is gone. The library knows
//! the V4L2 ABI; this side knows the lab and its pixel formats.
//!
//! Protocol: ASCII request lines, one reply line each (`OK ...`, or `ERR <errno>`):
//!
//! | request | reply |
//! |---|---|
//! | `STATE` | `OK formats=YUYV,MJPG sizes=WxH,... intervals=N/D,... fmt=F width=W height=H interval=N/D ctrl.<hex id>=V ...` |
//! | `SET key=value ...` (`fmt`, `width`, `height`, `interval`, `ctrl.<hex id>`) | `OK` / `ERR 16` (buffers held elsewhere) / `ERR 22` |
//! | `CLAIM`, `RELEASE` (buffers) | `OK` / `ERR 16` |
//! | `STREAMON`, `STREAMOFF` | `OK` |
//! | `POLL <ms>` (-1: no limit) | `OK 1` (a frame is ready) / `OK 0` (timed out) |
//! | `DQBUF <0 or 1: non-blocking>` | `FRAME seq=S ts=NS error=0/1 bytes=N` then N bytes / `ERR 11` |
//! | `SCENE place-tile` / `SCENE remove-tile` | `OK` |
//! | `SCENE show-board TILT_X_DEG TILT_Y_DEG ROTATE_DEG LIFT_MM` (the board lifted and held in that pose: [`crate::BoardPose`]) | `OK` |
//!
//! Once the camera is unplugged (fault `unplug_at_frame`) every request but `SCENE` gets
//! `ERR 19` (ENODEV).
//!
//! Frames: the sensor makes a frame only while a client streams and has a buffer queued
//! (it idles otherwise, as the in-process camera does); a frame is ready when its time on
//! the wall clock has passed (a frame lasts the longer of its exposure and the frame
//! period, with the exposure latency of the lab's sensor), unless the launcher runs
//! `--fast`. The frame's time stamp is CLOCK_MONOTONIC at the start of its exposure.

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::camera::{GrabError, SimCamera, SimPixels};
use crate::encode::{self, EncodeOptions, Encoding};
use crate::lamp::monotonic_ns;
use crate::{SceneKind, SimOperator};

/// V4L2 control ids the simulated sensor acts on.
pub const CID_EXPOSURE_AUTO: u32 = 0x009a_0901;
pub const CID_EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;
/// `V4L2_EXPOSURE_MANUAL`.
pub const EXPOSURE_MANUAL: i64 = 1;
/// The exposure control's default, 100 µs units (the sensor starts at 10 ms).
pub const EXPOSURE_DEFAULT: i64 = 100;

/// How the launcher serves frames.
#[derive(Debug, Clone, Copy, Default)]
pub struct ServeOptions {
    /// Deliver frames as fast as they are made, not at the sensor's pace.
    pub fast: bool,
    /// Replay the last N frames of a state (exposure, scene, lamp) once N are made: for
    /// throughput benchmarks, where the sensor model itself is the bottleneck.
    pub replay: Option<usize>,
    pub encode: EncodeOptions,
}

struct Ready {
    at: Instant,
    sequence: u64,
    timestamp_ns: u64,
    error: bool,
    bytes: Vec<u8>,
}

/// The simulated device's lasting state.
pub struct SimDevice {
    camera: SimCamera,
    operator: SimOperator,
    opts: ServeOptions,
    formats: Vec<Encoding>,
    sizes: Vec<(u32, u32)>,
    intervals: Vec<(u32, u32)>,
    fmt: Encoding,
    size: (u32, u32),
    interval: (u32, u32),
    ctrls: BTreeMap<u32, i64>,
    owner: Option<u64>,
    streaming: Option<u64>,
    gone: bool,
    stalled: bool,
    pending: Option<Ready>,
    next_start: Instant,
    sequence_base: u64,
    /// `--replay`: the encoded frames of each state, and how many frames were replayed
    /// (added to the sensor's sequence numbers so they keep counting up).
    replay: std::collections::HashMap<ReplayKey, Vec<Vec<u8>>>,
    replayed: u64,
    last_sequence: u64,
}

/// A state of the simulated lab whose frames look alike but for noise.
type ReplayKey = (u32, SceneKind, u32, Encoding, (u32, u32));

/// A frame rate as a frame interval `num/den`, reduced.
fn interval_of(fps: f64) -> (u32, u32) {
    let (mut n, mut d) = (1000u64, (fps * 1000.0).round().max(1.0) as u64);
    let g = gcd(n, d);
    n /= g;
    d /= g;
    (n as u32, d as u32)
}

fn gcd(a: u64, b: u64) -> u64 {
    if b == 0 {
        a
    } else {
        gcd(b, a % b)
    }
}

/// This thread's CPU time (for the timing log, `GLINT_MOCK_TIMING`).
fn thread_cpu() -> Duration {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime fills the timespec it is given.
    unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    Duration::new(ts.tv_sec as u64, ts.tv_nsec as u32)
}

/// CLOCK_MONOTONIC at `t`.
fn monotonic_at(t: Instant) -> u64 {
    let now = Instant::now();
    let mono = monotonic_ns();
    if t >= now {
        mono + (t - now).as_nanos() as u64
    } else {
        mono.saturating_sub((now - t).as_nanos() as u64)
    }
}

impl SimDevice {
    /// The device for `camera`, sending `format` at first (it must suit the camera's
    /// sensor: a luma format for a mono sensor, a colour one for RGB).
    pub fn new(
        camera: SimCamera,
        operator: SimOperator,
        format: Encoding,
        fps: f64,
        opts: ServeOptions,
    ) -> SimDevice {
        let (w, h) = (camera.width(), camera.height());
        let formats: Vec<Encoding> = Encoding::ALL
            .into_iter()
            .filter(|e| e.channels() == camera.channels())
            .collect();
        let mut sizes = vec![(w, h)];
        for s in [(640, 480), (320, 240), (160, 120)] {
            if s.0 < w && s.1 < h && !sizes.contains(&s) {
                sizes.push(s);
            }
        }
        let native = interval_of(fps);
        let mut intervals = vec![native];
        if fps >= 2.0 {
            intervals.push(interval_of(fps / 2.0));
        }
        let mut camera = camera;
        camera.set_fps(fps);
        SimDevice {
            camera,
            operator,
            opts,
            formats,
            sizes,
            intervals,
            fmt: format,
            size: (w, h),
            interval: native,
            ctrls: BTreeMap::new(),
            owner: None,
            streaming: None,
            gone: false,
            stalled: false,
            pending: None,
            next_start: Instant::now(),
            sequence_base: 0,
            replay: Default::default(),
            replayed: 0,
            last_sequence: 0,
        }
    }

    fn ctrl(&self, id: u32, default: i64) -> i64 {
        self.ctrls.get(&id).copied().unwrap_or(default)
    }

    fn state_line(&self) -> String {
        let list = |v: &[(u32, u32)], sep: char| {
            v.iter()
                .map(|(a, b)| format!("{a}{sep}{b}"))
                .collect::<Vec<_>>()
                .join(",")
        };
        let mut s = format!(
            "OK formats={} sizes={} intervals={} fmt={} width={} height={} interval={}/{}",
            self.formats
                .iter()
                .map(|f| f.name())
                .collect::<Vec<_>>()
                .join(","),
            list(&self.sizes, 'x'),
            list(&self.intervals, '/'),
            self.fmt.name(),
            self.size.0,
            self.size.1,
            self.interval.0,
            self.interval.1
        );
        for (id, v) in &self.ctrls {
            s.push_str(&format!(" ctrl.{id:x}={v}"));
        }
        s
    }

    fn set(&mut self, conn: u64, args: &str) -> Result<(), i32> {
        let mut fmt = self.fmt;
        let (mut w, mut h) = self.size;
        let mut interval = self.interval;
        let mut ctrls = Vec::new();
        for kv in args.split_whitespace() {
            let (k, v) = kv.split_once('=').ok_or(libc::EINVAL)?;
            let num = |v: &str| v.parse::<u32>().map_err(|_| libc::EINVAL);
            match k {
                "fmt" => {
                    fmt = Encoding::from_name(v)
                        .filter(|f| self.formats.contains(f))
                        .ok_or(libc::EINVAL)?
                }
                "width" => w = num(v)?,
                "height" => h = num(v)?,
                "interval" => {
                    let (a, b) = v.split_once('/').ok_or(libc::EINVAL)?;
                    interval = (num(a)?, num(b)?);
                }
                _ => {
                    let id = k
                        .strip_prefix("ctrl.")
                        .and_then(|id| u32::from_str_radix(id, 16).ok())
                        .ok_or(libc::EINVAL)?;
                    ctrls.push((id, v.parse::<i64>().map_err(|_| libc::EINVAL)?));
                }
            }
        }
        if !self.sizes.contains(&(w, h)) || !self.intervals.contains(&interval) {
            return Err(libc::EINVAL);
        }
        let changes_stream = fmt != self.fmt || (w, h) != self.size || interval != self.interval;
        if changes_stream && self.owner.is_some_and(|o| o != conn) {
            return Err(libc::EBUSY);
        }
        self.fmt = fmt;
        self.size = (w, h);
        if interval != self.interval {
            self.interval = interval;
            self.camera
                .set_fps(interval.1 as f64 / interval.0.max(1) as f64);
        }
        for (id, v) in ctrls {
            self.ctrls.insert(id, v);
            let manual = self.ctrl(CID_EXPOSURE_AUTO, 3) == EXPOSURE_MANUAL;
            // The sensor takes the exposure control in manual mode; in the automatic modes
            // the simulated camera holds the exposure it has.
            if manual && (id == CID_EXPOSURE_ABSOLUTE || id == CID_EXPOSURE_AUTO) {
                let units = self.ctrl(CID_EXPOSURE_ABSOLUTE, EXPOSURE_DEFAULT);
                self.camera.set_exposure((units.max(1) * 100) as u32);
            }
        }
        Ok(())
    }

    /// Make the next frame if a client streams and none is waiting.
    fn produce(&mut self) {
        if self.pending.is_some() || self.gone || self.stalled || self.streaming.is_none() {
            return;
        }
        let key: ReplayKey = (
            self.camera.exposure_control(),
            *self.camera.scene.lock().unwrap_or_else(|e| e.into_inner()),
            (self.camera.lamp.output() * 1000.0).round() as u32,
            self.fmt,
            self.size,
        );
        if let Some(n) = self.opts.replay {
            if let Some(frames) = self.replay.get(&key).filter(|f| f.len() >= n) {
                let bytes = frames[(self.replayed as usize) % n].clone();
                let period =
                    Duration::from_micros((key.0 as f64).max(self.camera.frame_period_us) as u64);
                let now = Instant::now();
                let at = if self.opts.fast {
                    now
                } else {
                    (self.next_start + period).max(now)
                };
                self.next_start = at;
                self.replayed += 1;
                self.last_sequence += 1;
                self.pending = Some(Ready {
                    at,
                    sequence: self.last_sequence,
                    timestamp_ns: monotonic_at(at.checked_sub(period).unwrap_or(at)),
                    error: false,
                    bytes,
                });
                return;
            }
        }
        let before = self.camera.clock_us();
        // The sensor starts when asked (it idles while no buffer waits), or when its last
        // frame ended; making the frame's pixels overlaps its exposure, so a frame is ready
        // at its end or when its pixels are made, whichever is later.
        let asked = Instant::now();
        let t0 = thread_cpu();
        match self.camera.grab() {
            Ok(frame) => {
                let after = self.camera.clock_us();
                let now = Instant::now();
                let start = self.next_start.max(asked);
                let end = start + Duration::from_micros((after - before).max(0.0) as u64);
                let at = if self.opts.fast { now } else { end.max(now) };
                self.next_start = if self.opts.fast { at } else { end };
                // The frame's own exposure began this long before it was done.
                let own =
                    Duration::from_micros((after - frame.timestamp_us as f64).max(0.0) as u64);
                let exposure_start = at.checked_sub(own).unwrap_or(start);
                let (w, h, ch) = (frame.width, frame.height, self.camera.channels());
                let full = w as usize * h as usize * ch as usize;
                let mut pixels = frame.pixels;
                let short = match &mut pixels {
                    SimPixels::U8(v) => {
                        let s = v.len() < full;
                        v.resize(full, 0);
                        s
                    }
                    SimPixels::U16(v) => {
                        let s = v.len() < full;
                        v.resize(full, 0);
                        s
                    }
                };
                let t1 = thread_cpu();
                let pixels = if (w, h) == self.size {
                    pixels
                } else {
                    encode::resample(&pixels, w, h, ch, self.size.0, self.size.1)
                };
                let t2 = thread_cpu();
                let mut bytes = encode::encode(
                    &pixels,
                    self.size.0,
                    self.size.1,
                    ch,
                    self.fmt,
                    self.opts.encode,
                );
                if std::env::var_os("GLINT_MOCK_TIMING").is_some() {
                    let t3 = thread_cpu();
                    eprintln!(
                        "timing (thread cpu) grab={:?} resample={:?} encode={:?}",
                        t1 - t0,
                        t2 - t1,
                        t3 - t2
                    );
                }
                if short {
                    // A broken transfer: the driver flags the buffer and gives what came.
                    bytes.truncate(bytes.len() / 2);
                }
                let sequence = frame.sequence - self.sequence_base + self.replayed;
                self.last_sequence = sequence;
                if let Some(n) = self.opts.replay {
                    let frames = self.replay.entry(key).or_default();
                    if frames.len() < n && !short {
                        frames.push(bytes.clone());
                    }
                }
                self.pending = Some(Ready {
                    at,
                    sequence,
                    timestamp_ns: monotonic_at(exposure_start),
                    error: short,
                    bytes,
                });
            }
            Err(GrabError::Stalled { .. }) => self.stalled = true,
            Err(GrabError::Unplugged { .. }) => self.gone = true,
        }
    }
}

type Shared = Arc<Mutex<SimDevice>>;

fn lock(d: &Shared) -> std::sync::MutexGuard<'_, SimDevice> {
    d.lock().unwrap_or_else(|e| e.into_inner())
}

/// Serve `device` on `listener` until the process ends (a thread a connection).
pub fn serve(listener: UnixListener, device: SimDevice) -> std::thread::JoinHandle<()> {
    let device: Shared = Arc::new(Mutex::new(device));
    std::thread::spawn(move || {
        static NEXT: AtomicU64 = AtomicU64::new(1);
        for stream in listener.incoming() {
            let Ok(stream) = stream else { continue };
            let device = Arc::clone(&device);
            let id = NEXT.fetch_add(1, Ordering::Relaxed);
            std::thread::spawn(move || {
                let _ = connection(stream, &device, id);
                let mut d = lock(&device);
                if d.owner == Some(id) {
                    d.owner = None;
                }
                if d.streaming == Some(id) {
                    d.streaming = None;
                    d.pending = None;
                }
            });
        }
    })
}

/// What a request waits for.
enum Wait {
    Poll(Option<Instant>),
    Frame { nonblock: bool },
}

fn connection(stream: UnixStream, device: &Shared, id: u64) -> std::io::Result<()> {
    let mut out = stream.try_clone()?;
    let reader = BufReader::new(stream);
    for line in reader.lines() {
        let line = line?;
        let (cmd, args) = line.split_once(' ').unwrap_or((line.as_str(), ""));
        let reply: Result<String, i32> = {
            let mut d = lock(device);
            if cmd == "SCENE" {
                match args.trim() {
                    "place-tile" => {
                        d.operator.place_tile();
                        Ok("OK".into())
                    }
                    "remove-tile" => {
                        d.operator.remove_tile();
                        Ok("OK".into())
                    }
                    a if a.starts_with("show-board") => {
                        // show-board TILT_X_DEG TILT_Y_DEG ROTATE_DEG LIFT_MM
                        let v: Vec<f64> = a
                            .split_whitespace()
                            .skip(1)
                            .filter_map(|x| x.parse().ok())
                            .filter(|x: &f64| x.is_finite() && x.abs() <= 1e4)
                            .collect();
                        if v.len() == 4 && a.split_whitespace().count() == 5 {
                            d.operator
                                .show_board(crate::BoardPose::new(v[0], v[1], v[2], v[3]));
                            Ok("OK".into())
                        } else {
                            Err(libc::EINVAL)
                        }
                    }
                    _ => Err(libc::EINVAL),
                }
            } else if d.gone {
                Err(libc::ENODEV)
            } else {
                match cmd {
                    "STATE" => Ok(d.state_line()),
                    "SET" => d.set(id, args).map(|_| "OK".into()),
                    "CLAIM" => match d.owner {
                        Some(o) if o != id => Err(libc::EBUSY),
                        _ => {
                            d.owner = Some(id);
                            Ok("OK".into())
                        }
                    },
                    "RELEASE" => {
                        if d.owner == Some(id) {
                            d.owner = None;
                        }
                        Ok("OK".into())
                    }
                    "STREAMON" => {
                        if d.owner != Some(id) {
                            Err(libc::EBUSY)
                        } else {
                            d.streaming = Some(id);
                            d.pending = None;
                            d.sequence_base = d.camera.produced();
                            d.next_start = Instant::now();
                            Ok("OK".into())
                        }
                    }
                    "STREAMOFF" => {
                        if d.streaming == Some(id) {
                            d.streaming = None;
                            d.pending = None;
                        }
                        Ok("OK".into())
                    }
                    "POLL" | "DQBUF" => Ok(String::new()),
                    _ => Err(libc::EINVAL),
                }
            }
        };
        let wait = match (cmd, &reply) {
            ("POLL", Ok(_)) => {
                let ms: i64 = args.trim().parse().unwrap_or(0);
                Wait::Poll((ms >= 0).then(|| Instant::now() + Duration::from_millis(ms as u64)))
            }
            ("DQBUF", Ok(_)) => Wait::Frame {
                nonblock: args.trim() == "1",
            },
            _ => {
                match reply {
                    Ok(s) => writeln!(out, "{s}")?,
                    Err(e) => writeln!(out, "ERR {e}")?,
                }
                continue;
            }
        };
        match wait_for_frame(device, id, wait) {
            Err(e) => writeln!(out, "ERR {e}")?,
            Ok(None) => writeln!(out, "OK 0")?,
            Ok(Some(None)) => writeln!(out, "OK 1")?,
            Ok(Some(Some(f))) => {
                writeln!(
                    out,
                    "FRAME seq={} ts={} error={} bytes={}",
                    f.sequence,
                    f.timestamp_ns,
                    f.error as u8,
                    f.bytes.len()
                )?;
                out.write_all(&f.bytes)?;
            }
        }
    }
    Ok(())
}

/// Wait for the next frame to be ready: `Ok(None)` timed out, `Ok(Some(None))` ready
/// (poll), `Ok(Some(Some(frame)))` taken (DQBUF).
#[allow(clippy::type_complexity)]
fn wait_for_frame(device: &Shared, id: u64, wait: Wait) -> Result<Option<Option<Ready>>, i32> {
    loop {
        let until = {
            let mut d = lock(device);
            if d.gone {
                return Err(libc::ENODEV);
            }
            if d.streaming != Some(id) {
                return match wait {
                    Wait::Poll(_) => Ok(None),
                    Wait::Frame { .. } => Err(libc::EINVAL),
                };
            }
            d.produce();
            if d.gone {
                return Err(libc::ENODEV);
            }
            let now = Instant::now();
            match &d.pending {
                Some(r) if r.at <= now => {
                    return Ok(Some(match wait {
                        Wait::Poll(_) => None,
                        Wait::Frame { .. } => d.pending.take(),
                    }));
                }
                Some(r) => Some(r.at),
                None => None, // stalled: nothing will come
            }
        };
        let deadline = match wait {
            Wait::Frame { nonblock: true } => return Err(libc::EAGAIN),
            Wait::Frame { nonblock: false } => None,
            Wait::Poll(d) => d,
        };
        let now = Instant::now();
        if deadline.is_some_and(|d| d <= now) {
            return Ok(None);
        }
        // Sleep until the frame is due or the deadline, at most 50 ms at a time (so an
        // unplug or a STREAMOFF elsewhere is seen).
        let mut wake = now + Duration::from_millis(50);
        if let Some(u) = until {
            wake = wake.min(u);
        }
        if let Some(d) = deadline {
            wake = wake.min(d);
        }
        std::thread::sleep(wake.saturating_duration_since(now));
    }
}
