//! `glint bench capture`: how fast the simulated lab makes frames, and how long a whole
//! capture of a rig takes. Figures go in the README with the machine they ran on.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Args;
use glint::capture;
use glint::devices::mock::sim::Lab;
use glint::devices::serial_lamp::{LampPolicy, SerialLamp};
use glint::devices::{self, Lamp};

#[derive(Args)]
pub struct CaptureBenchArgs {
    /// The rig whose simulated lab and capture are timed (it must use the mock backends)
    /// [default: rigs/mock.toml of the current folder, else of Glint's source tree].
    #[arg(long, value_name = "FILE")]
    rig: Option<PathBuf>,
    /// Frames to time for the frame rate.
    #[arg(long, default_value_t = 60)]
    frames: u32,
    /// Image size for the frame rate, WIDTHxHEIGHT.
    #[arg(long, default_value = "1280x960")]
    size: String,
    /// Full captures to time (the median is reported).
    #[arg(long, default_value_t = 3)]
    runs: u32,
    /// Print the figures as JSON.
    #[arg(long)]
    json: bool,
}

/// The simulated lab's rig, as `--rig` of a benchmark names it when not given.
const MOCK_RIG: &str = "rigs/mock.toml";

/// The rig a benchmark of the simulated lab runs: the one given with `--rig`, else
/// `rigs/mock.toml` of the current folder, else that of the source tree this glint was
/// built from (so that `glint bench ...` works from any folder on the machine that built
/// it); else an error saying what is missing and how to give it.
pub(crate) fn mock_rig(given: Option<&Path>) -> Result<PathBuf> {
    if let Some(p) = given {
        return Ok(p.to_path_buf());
    }
    let source = Path::new(env!("CARGO_MANIFEST_DIR")).join(MOCK_RIG);
    find_mock_rig(Path::new(MOCK_RIG), &source)
}

/// `here` (a path relative to the current folder) if it is a file, else `source`, else the
/// error naming both.
fn find_mock_rig(here: &Path, source: &Path) -> Result<PathBuf> {
    if let Some(p) = [here, source].into_iter().find(|p| p.is_file()) {
        return Ok(p.to_path_buf());
    }
    let cwd = std::env::current_dir()
        .map(|d| d.join(here).display().to_string())
        .unwrap_or_else(|_| here.display().to_string());
    anyhow::bail!(
        "no --rig given, and the default rig {} is neither in the current folder ({cwd}) nor in the source tree this glint was built from ({}); run it from Glint's repository, or give a rig with mock backends with --rig FILE (Glint's rigs/mock.toml)",
        here.display(),
        source.display()
    )
}

pub fn capture(a: CaptureBenchArgs) -> Result<ExitCode> {
    let rig = mock_rig(a.rig.as_deref())?;
    let loaded = super::load_capture_rig(&rig)?;
    let r = &loaded.rig;
    let (w, h) = a
        .size
        .split_once('x')
        .and_then(|(w, h)| Some((w.parse::<u32>().ok()?, h.parse::<u32>().ok()?)))
        .context("--size must look like 1280x960")?;
    let mut cfg = r
        .mock
        .clone()
        .context("the rig has no [mock] section; bench a mock rig")?;
    // Keep the view when the size changes: focal lengths scale with the width.
    let scale = w as f64 / r.camera.width as f64;
    cfg.camera.fx *= scale;
    cfg.camera.fy *= scale;
    cfg.faults = Default::default();
    cfg.sensor.exposure_latency_frames = 0;

    // Frame rate of the simulator on this thread (one core), lamp on at full output.
    let mut lab = Lab::new(
        &r.scene_geometry(),
        &cfg,
        w,
        h,
        r.camera.bit_depth,
        &loaded.base_dir(),
    )?;
    let mut lamp = SerialLamp::open(
        lab.lamp.port_path(),
        r.lamp.baud(),
        LampPolicy::from_rig(&r.lamp)?,
    )?;
    lamp.switch_on(1000)?;
    std::thread::sleep(Duration::from_millis(cfg.lamp.warmup_ms));
    let t = Instant::now();
    lab.camera
        .radiance(glint::devices::mock::sim::SceneKind::Tile);
    let render_s = t.elapsed().as_secs_f64();
    let exposures = &r.bracket.exposures_us;
    let t = Instant::now();
    for i in 0..a.frames {
        lab.camera
            .set_exposure(exposures[i as usize % exposures.len()]);
        lab.camera.grab().map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    let fps = a.frames as f64 / t.elapsed().as_secs_f64();
    drop(lab);

    // Wall time of whole captures into a scratch folder.
    let mut walls = Vec::new();
    let mut frames = 0;
    for run in 0..a.runs.max(1) {
        let out = std::env::temp_dir().join(format!("glint-bench-{}-{run}", std::process::id()));
        let t = Instant::now();
        let devices = devices::open(&loaded)?;
        let rec = capture::record(&loaded, devices, &out, Default::default(), &mut |_| {})?;
        walls.push(t.elapsed().as_secs_f64());
        frames = rec.manifest.frames.len();
        std::fs::remove_dir_all(&out).with_context(|| format!("removing {}", out.display()))?;
    }
    walls.sort_by(|a, b| a.partial_cmp(b).unwrap());
    let wall = walls[walls.len() / 2];
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .map(|l| l.split(':').nth(1).unwrap_or("").trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    if a.json {
        println!(
            "{}",
            serde_json::json!({
                "size": format!("{w}x{h}"), "bit_depth": r.camera.bit_depth,
                "scene_render_s": render_s, "frames_per_s_one_core": fps,
                "capture_rig": rig, "capture_wall_s_median": wall, "capture_wall_s": walls,
                "frames_kept": frames, "cpu": cpu,
            })
        );
    } else {
        println!(
            "machine: {cpu}, {} cores",
            std::thread::available_parallelism().map_or(0, |n| n.get())
        );
        println!(
            "simulated frames at {w}x{h} {}-bit, one core: {fps:.1} frames/s (goal >= 30)",
            r.camera.bit_depth
        );
        println!("scene render (once per scene): {:.0} ms", render_s * 1e3);
        println!(
            "glint capture --rig {}: {:.2} s wall (median of {}; {} frames kept)",
            rig.display(),
            wall,
            walls.len(),
            frames
        );
    }
    Ok(ExitCode::SUCCESS)
}
