//! Simulated brackets with known truth, made with the mock's sensor (its own forward model).

use std::path::Path;

use glint::devices::Pixels;
use glint::hdr::{Bracket, BracketFrame};
use glint_mock::config::{ResponseConfig, SensorConfig};
use glint_mock::sensor::{Response as MockResponse, Sensor};

/// A test scene: radiance (electrons per µs at full lamp) over a wide dynamic range.
/// Columns sweep log-uniformly from `lo` to `hi`; rows hold a gentle second gradient and the
/// three channels differ by fixed factors. Smooth, so every pixel is locally flat. A block
/// at the top left is far too bright (saturated in every frame) and one at the bottom right
/// far too dark (black in every frame).
pub fn scene(w: usize, h: usize, lo: f64, hi: f64) -> Vec<f32> {
    let mut r = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            let fx = x as f64 / (w - 1) as f64;
            let fy = y as f64 / (h - 1) as f64;
            let base = if x < BLOCK && y < BLOCK {
                1.0e5
            } else if x >= w - BLOCK && y >= h - BLOCK {
                1.0e-5
            } else {
                lo * (hi / lo).powf(fx) * (1.0 + 0.25 * fy)
            };
            for k in [1.0, 0.8, 0.6] {
                r.push((base * k) as f32);
            }
        }
    }
    r
}

/// Side of the saturated and the dark block.
pub const BLOCK: usize = 12;

/// A sensor configuration: response, read noise (electrons; 0 and `shot = false` for a
/// noise-free sensor).
pub fn sensor(response: ResponseConfig, read_noise_e: f64) -> SensorConfig {
    SensorConfig {
        response,
        electrons_per_radiance_us: 1.0,
        full_well_e: 20000.0,
        read_noise_e,
        dark_current_e_per_s: 0.0,
        blooming: 0.0,
        ..SensorConfig::default()
    }
}

/// Expose `radiance` at every time of `times_us`.
pub fn bracket(
    cfg: &SensorConfig,
    radiance: &[f32],
    w: usize,
    h: usize,
    bits: u8,
    times_us: &[f64],
    seed: u64,
) -> Bracket {
    let mut s = Sensor::new(cfg, bits, seed, Path::new("/")).unwrap();
    let frames = times_us
        .iter()
        .map(|t| {
            let pixels = if bits == 8 {
                let mut out = vec![0u8; radiance.len()];
                s.expose(radiance, w, 3, 1.0, *t, &mut out);
                Pixels::U8(out)
            } else {
                let mut out = vec![0u16; radiance.len()];
                s.expose(radiance, w, 3, 1.0, *t, &mut out);
                Pixels::U16(out)
            };
            BracketFrame {
                name: format!("{t} µs"),
                exposure_us: *t,
                pixels,
            }
        })
        .collect();
    Bracket::new(w, h, bits, frames).unwrap()
}

/// The true ln exposure (electrons, as radiance x µs) for value `z` of a `bits` sensor with
/// this response: the inverse of the mock's curve at z / max, by bisection.
pub fn true_ln_exposure(cfg: &SensorConfig, bits: u8, z: f64) -> f64 {
    let r = MockResponse::new(&cfg.response, Path::new("/")).unwrap();
    let max = ((1u32 << bits) - 1) as f64;
    let target = (z / max) as f32;
    let (mut a, mut b) = (0.0f32, 1.0f32);
    for _ in 0..60 {
        let m = 0.5 * (a + b);
        if r.eval(m) < target {
            a = m;
        } else {
            b = m;
        }
    }
    ((0.5 * (a + b)) as f64 * cfg.full_well_e / cfg.electrons_per_radiance_us).ln()
}

/// `n` exposures spaced `stops` apart, starting at `first_us`.
pub fn times(first_us: f64, n: usize, stops: f64) -> Vec<f64> {
    (0..n)
        .map(|i| first_us * 2f64.powf(stops * i as f64))
        .collect()
}
