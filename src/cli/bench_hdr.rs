//! `glint bench hdr`: merge throughput at 12 MP against a memory-bandwidth baseline
//! measured in the same run (one pass per frame that only adds the frame into a float
//! image, on all cores, the same chunking as the merge).

use std::process::ExitCode;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use glint::devices::Pixels;
use glint::hdr::merge::{self, Merger};
use glint::hdr::response::{Channel, Model, Noise, Response, FORMAT, FORMAT_VERSION};
use glint::hdr::{Bracket, BracketFrame};
use rayon::prelude::*;

#[derive(Args)]
pub struct HdrBenchArgs {
    /// Image size, WIDTHxHEIGHT (default 12 MP).
    #[arg(long, default_value = "4000x3000")]
    size: String,
    /// Exposures in the bracket.
    #[arg(long, default_value_t = 7)]
    exposures: usize,
    /// Timed repeats of each method (the median is reported).
    #[arg(long, default_value_t = 5)]
    repeats: usize,
    /// Print the figures as JSON.
    #[arg(long)]
    json: bool,
}

/// A gamma-2.2 camera response (the merge's cost does not depend on the curve).
fn gamma_response() -> Response {
    let ch = Channel {
        ln_exposure: (0..256)
            .map(|z| ((z as f64).max(0.5) / 255.0).powf(2.2).ln())
            .collect(),
        ln_exposure_sd: Vec::new(),
        coefficients: Vec::new(),
        coefficient_covariance: Vec::new(),
        black: 0.0,
        gain: 0.0,
        valid_min: 3,
        valid_max: 250,
        noise: Noise {
            shot: 1e-4,
            read: 1e-8,
        },
        rms_residual: 0.0,
        misfit_sd: 0.0,
        samples: 0,
    };
    Response {
        format: FORMAT.into(),
        format_version: FORMAT_VERSION,
        model: Model::Debevec,
        bit_depth: 8,
        camera: None,
        recovered_from: "bench".into(),
        lambda: 0.0,
        choice: None,
        channels: vec![ch.clone(), ch.clone(), ch],
        alternatives: Vec::new(),
        warnings: Vec::new(),
    }
}

/// Frames of a scene with a 16-stop range and noise-like texture (a hash per pixel).
fn frames(w: usize, h: usize, n: usize) -> Vec<BracketFrame> {
    (0..n)
        .map(|j| {
            let t = 125.0 * 2f64.powi(j as i32);
            let mut px = vec![0u8; w * h * 3];
            px.par_chunks_mut(w * 3).enumerate().for_each(|(y, row)| {
                for (k, v) in row.iter_mut().enumerate() {
                    let x = k / 3;
                    let h =
                        ((x as u64 * 0x9e37_79b9 + y as u64 * 0x85eb_ca6b + k as u64) >> 7) & 0xff;
                    let rad =
                        2f64.powf(16.0 * x as f64 / w as f64 - 12.0) * (1.0 + h as f64 / 2048.0);
                    let e = (rad * t * 1e-3).min(1.0);
                    *v = (e.powf(1.0 / 2.2) * 255.0 + 0.5) as u8;
                }
            });
            BracketFrame {
                name: format!("{t} µs"),
                exposure_us: t,
                pixels: Pixels::U8(px),
            }
        })
        .collect()
}

/// The baseline's work: add every frame into `acc`, on all cores, in the merge's chunks.
fn sum_frames(acc: &mut [f32], b: &Bracket) {
    for f in &b.frames {
        let Pixels::U8(px) = &f.pixels else {
            unreachable!("the bench makes 8-bit frames")
        };
        acc.par_chunks_mut(3 * 4096)
            .zip(px.par_chunks(3 * 4096))
            .for_each(|(a, p)| a.iter_mut().zip(p).for_each(|(a, p)| *a += *p as f32));
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

pub fn hdr(a: HdrBenchArgs) -> Result<ExitCode> {
    let (w, h) = a
        .size
        .split_once('x')
        .and_then(|(w, h)| Some((w.parse::<usize>().ok()?, h.parse::<usize>().ok()?)))
        .context("--size must look like 4000x3000")?;
    if a.exposures < 2 || a.repeats == 0 {
        bail!("--exposures must be at least 2 and --repeats at least 1");
    }
    let mp = (w * h) as f64 * 1e-6;
    eprintln!("making {} frames of {w}x{h} ...", a.exposures);
    let b = Bracket::new(w, h, 8, frames(w, h, a.exposures))?;
    let r = gamma_response();
    let dark = vec![[0.0; 3]; a.exposures];
    let threads = rayon::current_num_threads();

    // Baseline: add every frame into a new float image, frame by frame, on all cores. Like
    // the merges it makes its output from scratch (allocation included).
    let mut base = Vec::new();
    for _ in 0..a.repeats {
        let t0 = Instant::now();
        let mut acc = vec![0.0f32; w * h * 3];
        sum_frames(&mut acc, &b);
        base.push(t0.elapsed().as_secs_f64());
        std::hint::black_box(&acc);
    }
    // Memory traffic alone, with the output already in place (no page faults).
    let mut warm = Vec::new();
    let mut acc = vec![0.0f32; w * h * 3];
    for _ in 0..a.repeats {
        acc.par_iter_mut().for_each(|v| *v = 0.0);
        let t0 = Instant::now();
        sum_frames(&mut acc, &b);
        warm.push(t0.elapsed().as_secs_f64());
        std::hint::black_box(&acc);
    }
    drop(acc);

    let mut batch = Vec::new();
    for _ in 0..a.repeats {
        let t0 = Instant::now();
        let m = merge::merge(&r, &b, &dark)?;
        batch.push(t0.elapsed().as_secs_f64());
        std::hint::black_box(&m);
    }
    // Into buffers reused from the previous repeat (no page faults).
    let mut reuse = Vec::new();
    let mut out = merge::merge(&r, &b, &dark)?;
    for _ in 0..a.repeats {
        let t0 = Instant::now();
        merge::merge_into(&r, &b, &dark, &mut out)?;
        reuse.push(t0.elapsed().as_secs_f64());
        std::hint::black_box(&out);
    }
    drop(out);
    let mut stream = Vec::new();
    for _ in 0..a.repeats {
        let t0 = Instant::now();
        let mut s = Merger::new(r.clone(), w, h);
        for f in &b.frames {
            s.fold(f, [0.0; 3])?;
        }
        let m = s.finish();
        stream.push(t0.elapsed().as_secs_f64());
        std::hint::black_box(&m);
    }
    // Streaming into a merger reused from an earlier bracket.
    let mut sreuse = Vec::new();
    let mut s = Merger::new(r.clone(), w, h);
    for f in &b.frames {
        s.fold(f, [0.0; 3])?;
    }
    for _ in 0..a.repeats {
        s.reset();
        let t0 = Instant::now();
        for f in &b.frames {
            s.fold(f, [0.0; 3])?;
        }
        sreuse.push(t0.elapsed().as_secs_f64());
    }
    drop(s);
    let tsr = median(sreuse);
    let (tb, tm, ts, tw, tr) = (
        median(base),
        median(batch),
        median(stream),
        median(warm),
        median(reuse),
    );
    if a.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "width": w, "height": h, "exposures": a.exposures, "threads": threads,
                "baseline_sum_s": tb, "baseline_sum_preallocated_s": tw, "merge_batch_s": tm, "merge_streaming_s": ts,
                "baseline_mp_per_s": mp / tb, "merge_batch_mp_per_s": mp / tm,
                "merge_streaming_mp_per_s": mp / ts,
                "streaming_fold_reused_s": tsr, "streaming_fold_reused_mp_per_s": mp / tsr,
                "merge_reused_buffers_s": tr, "merge_reused_buffers_mp_per_s": mp / tr,
                "baseline_preallocated_mp_per_s": mp / tw,
            }))?
        );
    } else {
        println!(
            "HDR merge of {} exposures at {w}x{h} ({mp:.1} MP), {threads} threads, median of {}:",
            a.exposures, a.repeats
        );
        println!(
            "  baseline (sum the frames into a float image): {:7.1} ms  {:7.1} MP/s",
            tb * 1e3,
            mp / tb
        );
        println!(
            "  baseline into a float image already in memory: {:7.1} ms  {:7.1} MP/s",
            tw * 1e3,
            mp / tw
        );
        println!(
            "  merge, all frames at hand:                   {:7.1} ms  {:7.1} MP/s  ({:.2}x the baseline)",
            tm * 1e3,
            mp / tm,
            tb / tm
        );
        println!(
            "  merge into reused buffers:                   {:7.1} ms  {:7.1} MP/s  ({:.2}x the in-memory baseline)",
            tr * 1e3,
            mp / tr,
            tw / tr
        );
        println!(
            "  merge, streaming (frame by frame):           {:7.1} ms  {:7.1} MP/s  ({:.2}x the baseline)",
            ts * 1e3,
            mp / ts,
            tb / ts
        );
        println!(
            "  streaming folds into a reused merger:        {:7.1} ms  {:7.1} MP/s  ({:.2}x the in-memory baseline)",
            tsr * 1e3,
            mp / tsr,
            tw / tsr
        );
    }
    Ok(ExitCode::SUCCESS)
}
