//! `glint bench v4l2`: how fast a rig's V4L2 camera streams into Glint, and what each frame
//! costs the CPU (decoding its pixel format, then encoding the PNG the session stores).
//!
//! The work is split the way a capture splits it (src/capture/, [`session::SessionWriter`]):
//! one thread grabs and decodes (the capture engine's, in `Camera::grab`), another encodes
//! each frame as a PNG and writes it (the session writer's), joined by a bounded channel of
//! the capture's capacity. So the frames per second sustained are the pipeline's, and the
//! grab thread waits for the writer only when the writer falls behind.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::mpsc::sync_channel;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use glint::devices::v4l2::{thread_cpu_time, V4l2Camera};
use glint::devices::{Camera, Frame};
use glint::{rig, session};

/// Frames the channel between the two threads holds, as in `capture::spawn`.
const CHANNEL_FRAMES: usize = 4;

/// Frames grabbed before counting, while the stream starts.
const WARMUP_FRAMES: u32 = 5;

/// Below this share of the rig's frame rate, the pipeline did not keep up.
const KEPT_UP_SHARE: f64 = 0.97;

#[derive(Args)]
pub struct V4l2BenchArgs {
    /// The rig whose camera (camera.backend = "v4l2") is streamed; its lamp is not used.
    #[arg(long, value_name = "FILE")]
    rig: PathBuf,
    /// Frames to stream (after 5 that are not counted, while the stream starts).
    #[arg(long, default_value_t = 120)]
    frames: u32,
    /// Where the PNGs are written (in a temporary folder, removed at the end); the
    /// system's temporary directory by default. Name a folder on the disk sessions go to
    /// for the figures a capture will see.
    #[arg(long, value_name = "DIR")]
    dir: Option<PathBuf>,
    /// Print the figures as JSON.
    #[arg(long)]
    json: bool,
}

/// The writer thread's totals.
#[derive(Default)]
struct Written {
    frames: u32,
    png_cpu: Duration,
    /// Writing (temporary file, fsync, link) and hashing, as the session does.
    write_cpu: Duration,
    write_wall: Duration,
    thread_cpu: Duration,
    bytes: usize,
    /// When the last frame was on disk.
    done: Option<Instant>,
}

/// CPU time (user + system) the whole process has used so far.
fn process_cpu_time() -> Duration {
    // SAFETY: a zeroed rusage is a valid buffer for getrusage to fill.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: RUSAGE_SELF and a valid pointer.
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let tv = |t: libc::timeval| {
        Duration::from_secs(t.tv_sec.max(0) as u64) + Duration::from_micros(t.tv_usec.max(0) as u64)
    };
    tv(u.ru_utime) + tv(u.ru_stime)
}

pub fn v4l2(a: V4l2BenchArgs) -> Result<ExitCode> {
    let loaded = rig::load(&a.rig)?;
    let r = &loaded.rig;
    if r.camera.backend != rig::CameraBackend::V4l2 {
        bail!(
            "{} has no V4L2 camera (camera.backend = \"v4l2\")",
            a.rig.display()
        );
    }
    if a.frames == 0 {
        bail!("--frames must be at least 1");
    }
    let mut tmp = tempfile::Builder::new();
    tmp.prefix("glint-bench-v4l2-");
    let out = match &a.dir {
        Some(d) => tmp.tempdir_in(d),
        None => tmp.tempdir(),
    }
    .context("making a temporary folder for the PNGs")?;
    let mut cam = V4l2Camera::open(r).context("opening the rig's camera")?;
    let exposure = r.bracket.exposures_us.first().copied().unwrap_or(10_000);
    let applied = cam.set_exposure(exposure)?;
    let timeout = Duration::from_millis(r.camera.frame_timeout_ms);
    for _ in 0..WARMUP_FRAMES {
        cam.grab(timeout)?;
    }

    // The session writer's half: PNG encoding, then the file, synced, and its hash.
    let (tx, rx) = sync_channel::<Frame>(CHANNEL_FRAMES);
    let dir = out.path().to_path_buf();
    let writer = std::thread::Builder::new()
        .name("bench-writer".into())
        .spawn(move || -> Result<Written> {
            let mut w = Written::default();
            let start = thread_cpu_time();
            for f in rx {
                let c0 = thread_cpu_time();
                let png = session::encode_png(f.width, f.height, &f.pixels)
                    .map_err(|e| anyhow!("encoding a PNG: {e}"))?;
                let c1 = thread_cpu_time();
                let t = Instant::now();
                session::write_new(&dir.join(format!("{:04}.png", w.frames)), &png)?;
                std::hint::black_box(session::sha256_hex(&png));
                w.write_wall += t.elapsed();
                w.write_cpu += thread_cpu_time().saturating_sub(c1);
                w.png_cpu += c1.saturating_sub(c0);
                w.bytes += png.len();
                w.frames += 1;
                w.done = Some(Instant::now());
            }
            w.thread_cpu = thread_cpu_time().saturating_sub(start);
            Ok(w)
        })
        .context("starting the writer thread")?;

    // The capture engine's half: grab (and decode) each frame, hand it on.
    let (mut decode, mut blocked) = (Duration::ZERO, Duration::ZERO);
    let (mut dropped, mut last) = (0u64, None::<u64>);
    let mut stamps = (None::<u64>, None::<u64>);
    let mut sent = 0u32;
    let process0 = process_cpu_time();
    let grab_cpu0 = thread_cpu_time();
    let t = Instant::now();
    let mut grab_err = None;
    for _ in 0..a.frames {
        let f = match cam.grab(timeout) {
            Ok(f) => f,
            Err(e) => {
                grab_err = Some(e);
                break;
            }
        };
        decode += cam.last_decode_cpu();
        if let Some(l) = last {
            dropped += f.sequence.saturating_sub(l + 1);
        }
        last = Some(f.sequence);
        if let Some(ts) = f.device_timestamp_us {
            stamps.0.get_or_insert(ts);
            stamps.1 = Some(ts);
        }
        let s = Instant::now();
        if tx.send(f).is_err() {
            break; // the writer failed: its error is below
        }
        blocked += s.elapsed();
        sent += 1;
    }
    let grab_cpu = thread_cpu_time().saturating_sub(grab_cpu0);
    drop(tx);
    let w = writer
        .join()
        .map_err(|_| anyhow!("the writer thread panicked"))??;
    if let Some(e) = grab_err {
        return Err(e).context(format!("grabbing frame {} of {}", sent + 1, a.frames));
    }
    let done = w.done.unwrap_or_else(Instant::now);
    let wall = done.saturating_duration_since(t).as_secs_f64();
    let process_cpu = process_cpu_time().saturating_sub(process0);
    drop(out); // removes the PNGs

    let n = a.frames as f64;
    let ms = |d: Duration| d.as_secs_f64() * 1e3 / n;
    let info = cam.info();
    let fps = n / wall;
    let device_fps = match stamps {
        (Some(a0), Some(a1)) if a1 > a0 && n > 1.0 => Some((n - 1.0) * 1e6 / (a1 - a0) as f64),
        _ => None,
    };
    let kept_up = dropped == 0 && fps >= KEPT_UP_SHARE * r.camera.fps;
    let (decode_ms, png_ms) = (ms(decode), ms(w.png_cpu));
    let (grab_ms, writer_ms) = (ms(grab_cpu), ms(w.thread_cpu));
    let (write_ms, write_wall_ms) = (ms(w.write_cpu), ms(w.write_wall));
    let interval_ms = 1e3 / r.camera.fps;
    if a.json {
        println!(
            "{}",
            serde_json::json!({
                "camera": info.model, "device": info.device, "pixel_format": info.pixel_format,
                "size": format!("{}x{}", info.width, info.height), "exposure_us": applied,
                "rig_fps": r.camera.fps, "frames": a.frames, "wall_s": wall,
                "frames_per_s": fps, "dropped": dropped, "kept_up": kept_up,
                "device_fps": device_fps,
                "decode_cpu_ms_per_frame": decode_ms, "png_cpu_ms_per_frame": png_ms,
                "png_bytes_per_frame": w.bytes as f64 / n,
                "write_cpu_ms_per_frame": write_ms, "write_wall_ms_per_frame": write_wall_ms,
                "grab_thread_cpu_ms_per_frame": grab_ms,
                "writer_thread_cpu_ms_per_frame": writer_ms,
                "process_cpu_ms_per_frame": ms(process_cpu),
                "grab_waited_for_writer_s": blocked.as_secs_f64(),
                "channel_frames": CHANNEL_FRAMES,
            })
        );
    } else {
        println!(
            "{} ({}): {} {}x{} at {} fps asked, exposure {applied} µs",
            info.model,
            info.device.as_deref().unwrap_or("?"),
            info.pixel_format.as_deref().unwrap_or("?"),
            info.width,
            info.height,
            r.camera.fps
        );
        let device = device_fps
            .map(|f| format!(" (device time stamps: {f:.1} frames/s)"))
            .unwrap_or_default();
        println!(
            "{} frames decoded and written in {wall:.2} s: {fps:.1} frames/s sustained{device}, {dropped} dropped: {}",
            a.frames,
            if kept_up {
                "kept up with the camera"
            } else {
                "did NOT keep up with the camera"
            }
        );
        println!(
            "grab thread, CPU per frame: {grab_ms:.2} ms, of which decode {decode_ms:.2} ms; waited {:.2} s in all for the writer",
            blocked.as_secs_f64()
        );
        println!(
            "writer thread, CPU per frame: {writer_ms:.2} ms: PNG encode {png_ms:.2} ms ({:.0} kB), write + fsync + SHA-256 {write_ms:.2} ms CPU, {write_wall_ms:.2} ms wall",
            w.bytes as f64 / n / 1e3
        );
        println!(
            "process CPU per frame: {:.2} ms (frame interval {interval_ms:.1} ms)",
            ms(process_cpu)
        );
        if grab_ms.max(writer_ms) > interval_ms {
            println!(
                "note: a thread needs more CPU per frame than the frame interval: a capture keeps up only because it keeps a few frames per exposure"
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}
