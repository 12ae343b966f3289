//! Even and uneven exposure steps: where every exposure of a bracket is the one
//! before times the same ratio r, a response curve that differs from the true one by a
//! wiggle repeating every factor r of exposure explains the bracket exactly as well (each
//! pixel's readings all move by the wiggle's value at its radiance, which the pixel's
//! unknown radiance absorbs): the bracket cannot see it, and the recovered curve keeps
//! whatever such wiggle the noise and the model's shape give it. Steps of two ratios whose
//! logarithms are not in a simple proportion (0.8 and 1.3 stops: x1.74, x2.46) leave no
//! wiggle invisible. Whether that matters was measured here, on the mock's EMoR curves
//! (drawn from seeded generators) against the true curve: it does not (below).

use glint::hdr::response::{self, RecoverOptions, Response};
use glint_mock::config::ResponseConfig;

use super::hdr_depth::{emor_file, random_emor};
use super::hdr_sim::{bracket, scene, sensor};

const W: usize = 320;
const H: usize = 240;

/// Seven exposures from 125 µs, the steps (in stops) taken in turn.
fn steps(stops: &[f64]) -> Vec<f64> {
    let mut t = vec![125.0];
    for i in 0..6 {
        let last = t[t.len() - 1];
        t.push(last * 2f64.powf(stops[i % stops.len()]));
    }
    t
}

/// The normalised exposure at which the true curve reads `y` (0..1), by bisection.
fn inverse(truth: &glint_mock::sensor::Response, y: f64) -> f64 {
    let (mut lo, mut hi) = (0.0f64, 1.0f64);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if (truth.eval(mid as f32) as f64) < y {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// The recovered curve's error of shape against the truth: rms over the values from 1/32
/// of full scale to the top of the valid range (every channel) of ln E recovered minus ln
/// E true, its mean removed (radiance is relative).
fn shape_error(r: &Response, cfg: &ResponseConfig) -> f64 {
    let truth = glint_mock::sensor::Response::new(cfg, std::path::Path::new("/")).unwrap();
    let max = r.max_value() as f64;
    let mut d = Vec::new();
    for (c, ch) in r.channels.iter().enumerate() {
        let lo = ch.valid_min.max(r.max_value() / 32);
        let stride = ((ch.valid_max - lo) / 400).max(1);
        for z in (lo..=ch.valid_max).step_by(stride as usize) {
            let e = r.exposure(c, z as f64);
            let x = inverse(&truth, z as f64 / max);
            if e > 0.0 && x > 0.0 {
                d.push(e.ln() - x.ln());
            }
        }
    }
    let mean = d.iter().sum::<f64>() / d.len() as f64;
    (d.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / d.len() as f64).sqrt()
}

/// The sweep: seven exposures stepping by each pattern (stops, in turn), eight EMoR curves
/// at 8 and 16 bit, the recovered curve's shape error and the merge's median error (run by
/// hand: `cargo test --release --test tests exposure_steps_sweep -- --ignored --nocapture`).
/// Measured 2026-12-04: every pattern within noise of every other (shape 0.18-0.20% at 8
/// bit, 0.16-0.18% at 16; merge 0.54-0.56% / 0.52-0.54%): the invisible wiggle is not
/// what limits the recovered curves, whose degree-10 polynomial in ln z cannot follow a
/// wiggle one stop long anyway, so the README's advice stays one stop apart.
#[test]
#[ignore]
fn exposure_steps_sweep() {
    let Some(file) = emor_file() else {
        return;
    };
    for pat in [
        vec![1.0],
        vec![0.8],
        vec![1.05],
        vec![0.8, 1.3],
        vec![1.3, 0.8],
        vec![0.7, 1.4],
    ] {
        let t = steps(&pat);
        let (mut s8, mut s16, mut h8, mut h16) = (0.0, 0.0, 0.0, 0.0);
        for k in 0..8u64 {
            let cfg = random_emor(&file, 500 + k);
            for bits in [8u8, 16] {
                let seed = 900 + 10 * k + bits as u64;
                let s = sensor(cfg.clone(), 4.0);
                let rad = scene(W, H, 0.3, 150.0);
                let b = bracket(&s, &rad, W, H, bits, &t, seed);
                let d = bracket(&s, &vec![0.0f32; rad.len()], W, H, bits, &t, seed + 1);
                let r = response::recover(&b, &d, &RecoverOptions::default()).unwrap();
                let m =
                    glint::hdr::merge::merge(&r, &b, &glint::hdr::merge::dark_levels(&r, &b, &d))
                        .unwrap();
                let e = super::hdr_depth::median_error(&m, &rad);
                let sh = shape_error(&r, &cfg);
                if bits == 8 {
                    s8 += sh;
                    h8 += e
                } else {
                    s16 += sh;
                    h16 += e
                }
            }
        }
        println!(
            "{pat:?}: shape 8 {:.3}% 16 {:.3}%  hdr 8 {:.3}% 16 {:.3}%",
            12.5 * s8,
            12.5 * s16,
            12.5 * h8,
            12.5 * h16
        );
    }
}
