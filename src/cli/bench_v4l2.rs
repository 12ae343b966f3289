//! `glint bench v4l2`: how fast a rig's V4L2 camera streams into Glint, and what each frame
//! costs the CPU (decoding its pixel format, then encoding the PNG the session stores).

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::Args;
use glint::devices::v4l2::{thread_cpu_time, V4l2Camera};
use glint::devices::Camera;
use glint::{rig, session};

#[derive(Args)]
pub struct V4l2BenchArgs {
    /// The rig whose camera (camera.backend = "v4l2") is streamed; its lamp is not used.
    #[arg(long, value_name = "FILE")]
    rig: PathBuf,
    /// Frames to stream (after 5 that are not counted, while the stream starts).
    #[arg(long, default_value_t = 120)]
    frames: u32,
    /// Print the figures as JSON.
    #[arg(long)]
    json: bool,
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
    let mut cam = V4l2Camera::open(r).context("opening the rig's camera")?;
    let exposure = r.bracket.exposures_us.first().copied().unwrap_or(10_000);
    let applied = cam.set_exposure(exposure)?;
    let timeout = Duration::from_millis(r.camera.frame_timeout_ms);
    for _ in 0..5 {
        cam.grab(timeout)?;
    }
    let (mut decode, mut png, mut bytes) = (Duration::ZERO, Duration::ZERO, 0usize);
    let (mut dropped, mut last) = (0u64, None::<u64>);
    let t = Instant::now();
    for _ in 0..a.frames {
        let f = cam.grab(timeout)?;
        decode += cam.last_decode_cpu();
        if let Some(l) = last {
            dropped += f.sequence.saturating_sub(l + 1);
        }
        last = Some(f.sequence);
        let c = thread_cpu_time();
        let encoded = session::encode_png(f.width, f.height, &f.pixels)
            .map_err(|e| anyhow::anyhow!("encoding a PNG: {e}"))?;
        png += thread_cpu_time().saturating_sub(c);
        bytes += encoded.len();
    }
    let wall = t.elapsed().as_secs_f64();
    let n = a.frames as f64;
    let info = cam.info();
    let fps = n / wall;
    let decode_ms = decode.as_secs_f64() * 1e3 / n;
    let png_ms = png.as_secs_f64() * 1e3 / n;
    if a.json {
        println!(
            "{}",
            serde_json::json!({
                "camera": info.model, "device": info.device, "pixel_format": info.pixel_format,
                "size": format!("{}x{}", info.width, info.height), "exposure_us": applied,
                "rig_fps": r.camera.fps, "frames": a.frames, "wall_s": wall,
                "frames_per_s": fps, "dropped": dropped,
                "decode_cpu_ms_per_frame": decode_ms, "png_cpu_ms_per_frame": png_ms,
                "png_bytes_per_frame": bytes as f64 / n,
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
        println!(
            "{} frames in {wall:.2} s: {fps:.1} frames/s sustained, {dropped} dropped",
            a.frames
        );
        println!(
            "CPU per frame (this thread): decode {decode_ms:.2} ms, PNG encode {png_ms:.2} ms ({:.0} kB)",
            bytes as f64 / n / 1e3
        );
        if decode_ms + png_ms > 1e3 / r.camera.fps {
            println!(
                "note: decoding and encoding take longer than a frame interval ({:.1} ms): a capture keeps up only because it keeps a few frames per exposure",
                1e3 / r.camera.fps
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}
