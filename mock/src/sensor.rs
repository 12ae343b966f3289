//! The sensor: radiance x exposure -> electrons -> noise -> clipping -> response -> digital value.
//!
//! Speed matters here (a frame is 1.2 M pixels x 3 channels at 1280x960), so the response
//! curve is a lookup table with linear interpolation and the noise uses a table of standard
//! normal deviates indexed by a seeded xoshiro generator (four 16-bit indices per 64-bit
//! draw). The table holds 65 536 exact quantiles of N(0, 1), so the noise is Gaussian to
//! within the table's resolution and identical for a seed on every machine.

use rand::{Rng, SeedableRng};

use rand_distr::{Distribution, StandardNormal};
use rand_xoshiro::Xoshiro256PlusPlus;
use std::path::Path;

use crate::config::{ResponseConfig, SensorConfig};
use crate::MockError;

/// Samples in the response lookup table.
const LUT: usize = 4096;

/// A response curve, normalised exposure in [0, 1] -> normalised value in [0, 1].
#[derive(Debug, Clone)]
pub struct Response {
    table: Vec<f32>,
}

impl Response {
    /// Build the configured curve; EMoR files are found relative to `base`.
    pub fn new(cfg: &ResponseConfig, base: &Path) -> Result<Self, MockError> {
        let f: Box<dyn Fn(f64) -> f64> = match cfg {
            ResponseConfig::Linear => Box::new(|x| x),
            ResponseConfig::Gamma { gamma } => {
                let g = *gamma;
                Box::new(move |x: f64| x.powf(1.0 / g))
            }
            ResponseConfig::Emor { file, coefficients } => {
                let path = base.join(file);
                let curve = emor_curve(&path, coefficients)?;
                Box::new(move |x: f64| {
                    let p = x * (curve.len() - 1) as f64;
                    let i = (p.floor() as usize).min(curve.len() - 2);
                    let t = p - i as f64;
                    curve[i] * (1.0 - t) + curve[i + 1] * t
                })
            }
        };
        let table: Vec<f32> = (0..=LUT)
            .map(|i| f(i as f64 / LUT as f64).clamp(0.0, 1.0) as f32)
            .collect();
        if table.windows(2).any(|w| w[1] < w[0]) {
            return Err(MockError::Config(
                "mock.sensor.response is not monotonic; choose EMoR coefficients closer to 0"
                    .into(),
            ));
        }
        Ok(Response { table })
    }

    /// The curve at normalised exposure `x` (clamped to [0, 1]).
    #[inline]
    pub fn eval(&self, x: f32) -> f32 {
        let p = x.clamp(0.0, 1.0) * LUT as f32;
        let i = (p as usize).min(LUT - 1);
        let t = p - i as f32;
        self.table[i] + t * (self.table[i + 1] - self.table[i])
    }
}

/// Read `emor.txt` (blocks `E`, `f0`, `h(1)`..`h(25)` of 1024 numbers) and combine.
fn emor_curve(path: &Path, coefficients: &[f64]) -> Result<Vec<f64>, MockError> {
    let text = std::fs::read_to_string(path).map_err(|e| {
        MockError::Config(format!(
            "cannot read the EMoR file {} ({e}); set mock.sensor.response.file to emor.txt",
            path.display()
        ))
    })?;
    let mut blocks: Vec<Vec<f64>> = Vec::new();
    for line in text.lines() {
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        if line.contains('=') {
            blocks.push(Vec::with_capacity(1024));
            continue;
        }
        let block = blocks.last_mut().ok_or_else(|| {
            MockError::Config(format!(
                "{} does not start with a block header",
                path.display()
            ))
        })?;
        for tok in line.split_whitespace() {
            block.push(tok.parse().map_err(|_| {
                MockError::Config(format!("{}: `{tok}` is not a number", path.display()))
            })?);
        }
    }
    if blocks.len() < 2 + coefficients.len() || blocks.iter().any(|b| b.len() != 1024) {
        return Err(MockError::Config(format!(
            "{} is not an EMoR file (expected blocks E, f0, h(1).. of 1024 numbers)",
            path.display()
        )));
    }
    let mut f = blocks[1].clone();
    for (k, c) in coefficients.iter().enumerate() {
        for (fi, hi) in f.iter_mut().zip(&blocks[2 + k]) {
            *fi += c * hi;
        }
    }
    Ok(f)
}

/// Standard normal deviates: 65 536 quantiles, used by index.
struct NormalTable(Vec<f32>);

impl NormalTable {
    fn new() -> Self {
        // Exact quantiles at (i + 0.5) / N would need an inverse CDF; a large seeded
        // sample, sorted, is as good for noise and needs no special functions.
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(0x5eed_ab1e);
        let mut v: Vec<f32> = (0..65536)
            .map(|_| {
                let z: f64 = StandardNormal.sample(&mut rng);
                z as f32
            })
            .collect();
        v.sort_by(|a, b| a.partial_cmp(b).unwrap());
        // Remove the sample mean so the noise is unbiased.
        let mean = v.iter().map(|x| *x as f64).sum::<f64>() / v.len() as f64;
        v.iter_mut().for_each(|x| *x -= mean as f32);
        NormalTable(v)
    }
}

/// The sensor of one camera: turns irradiance into digital values.
pub struct Sensor {
    cfg: SensorConfig,
    normal: NormalTable,
    rng: Xoshiro256PlusPlus,
    /// Digital value for each bin of collected charge (bins of at most half an electron,
    /// finer than charge itself is quantised, so the table loses nothing).
    dn: Vec<u16>,
    electrons_per_bin: f32,
    scratch: Vec<f32>,
}

/// Largest electrons -> value table.
const MAX_BINS: usize = 1 << 18;

impl Sensor {
    pub fn new(
        cfg: &SensorConfig,
        bit_depth: u8,
        seed: u64,
        base: &Path,
    ) -> Result<Self, MockError> {
        if bit_depth != 8 && bit_depth != 16 {
            return Err(MockError::Config(format!(
                "bit depth {bit_depth} is not simulated; use 8 or 16"
            )));
        }
        let response = Response::new(&cfg.response, base)?;
        let max_dn = ((1u32 << bit_depth) - 1) as f32;
        let bins = ((cfg.full_well_e * 2.0).ceil() as usize).clamp(1024, MAX_BINS);
        let electrons_per_bin = (cfg.full_well_e / bins as f64) as f32;
        // Each bin's value at its centre; the last entry is saturation.
        let dn = (0..=bins)
            .map(|i| {
                let x = ((i as f32 + 0.5) / bins as f32).min(1.0);
                (response.eval(x) * max_dn + 0.5) as u16
            })
            .collect();
        Ok(Sensor {
            cfg: cfg.clone(),
            normal: NormalTable::new(),
            rng: Xoshiro256PlusPlus::seed_from_u64(seed),
            dn,
            electrons_per_bin,
            scratch: Vec::new(),
        })
    }

    /// Expose: `radiance` (`channels` samples a pixel at full lamp output, rows of `width`
    /// pixels) x `lamp` (0..1) for `exposure_us`, written as digital values into `out`.
    #[allow(clippy::too_many_arguments)]
    pub fn expose<T: Sample>(
        &mut self,
        radiance: &[f32],
        width: usize,
        channels: usize,
        lamp: f64,
        exposure_us: f64,
        out: &mut [T],
    ) {
        assert_eq!(radiance.len(), out.len());
        let gain = (self.cfg.electrons_per_radiance_us * lamp * exposure_us) as f32;
        let dark = (self.cfg.dark_current_e_per_s * exposure_us * 1e-6) as f32;
        let read2 = (self.cfg.read_noise_e * self.cfg.read_noise_e) as f32;
        let noise = self.cfg.noise;
        let full = self.cfg.full_well_e as f32;
        let bloom = self.cfg.blooming as f32;
        let inv_bin = 1.0 / self.electrons_per_bin;
        let dn = &self.dn;
        let last = (dn.len() - 1) as f32;
        let value = |e: f32| T::from_dn(dn[(e * inv_bin).clamp(0.0, last) as usize]);
        if noise && bloom == 0.0 {
            // The common case, straight into the output.
            noisy_electrons(
                &mut self.rng,
                &self.normal.0,
                radiance,
                gain,
                dark,
                read2,
                out,
                value,
            );
        } else {
            // Charge first (noisy or not), then blooming, then digital values.
            let mut scratch = std::mem::take(&mut self.scratch);
            if noise {
                scratch.resize(radiance.len(), 0.0);
                noisy_electrons(
                    &mut self.rng,
                    &self.normal.0,
                    radiance,
                    gain,
                    dark,
                    read2,
                    &mut scratch,
                    |e| e.max(0.0),
                );
            } else {
                scratch.clear();
                scratch.extend(radiance.iter().map(|l| (l * gain + dark).max(0.0)));
            }
            if bloom != 0.0 {
                bloom_spill(&mut scratch, width * channels, channels, full, bloom);
            }
            for (o, e) in out.iter_mut().zip(&scratch) {
                *o = value(*e);
            }
            self.scratch = scratch;
        }
    }
}

/// Mean electrons plus shot and read noise, mapped by `f` into `out`.
#[allow(clippy::too_many_arguments)]
#[inline]
fn noisy_electrons<T, F: Fn(f32) -> T>(
    rng: &mut Xoshiro256PlusPlus,
    table: &[f32],
    radiance: &[f32],
    gain: f32,
    dark: f32,
    read2: f32,
    out: &mut [T],
    f: F,
) {
    let table: &[f32; 65536] = table.try_into().expect("normal table has 65536 entries");
    // In blocks: the deviates are gathered first, then the arithmetic runs over plain
    // arrays, where it vectorises (the same IEEE operations, so the same values).
    const BLOCK: usize = 64;
    let mut z = [0f32; BLOCK];
    let mut e = [0f32; BLOCK];
    for (rad, out) in radiance.chunks(BLOCK).zip(out.chunks_mut(BLOCK)) {
        let m = rad.len();
        for z4 in z[..m].chunks_mut(4) {
            let r = rng.next_u64();
            for (j, zj) in z4.iter_mut().enumerate() {
                *zj = table[((r >> (16 * j)) & 0xffff) as usize];
            }
        }
        for ((ei, l), zi) in e[..m].iter_mut().zip(rad).zip(&z[..m]) {
            let mean = l * gain + dark;
            *ei = mean + zi * (mean + read2).sqrt();
        }
        for (o, ei) in out.iter_mut().zip(&e[..m]) {
            *o = f(*ei);
        }
    }
}

/// Spread charge above the full well into the four neighbours (one pass).
fn bloom_spill(e: &mut [f32], row: usize, channels: usize, full: f32, fraction: f32) {
    let n = e.len();
    let excess: Vec<(usize, f32)> = e
        .iter()
        .enumerate()
        .filter(|(_, v)| **v > full)
        .map(|(i, v)| (i, (*v - full) * fraction * 0.25))
        .collect();
    for (i, x) in excess {
        for j in [
            i.wrapping_sub(channels),
            i + channels,
            i.wrapping_sub(row),
            i + row,
        ] {
            if j < n {
                e[j] += x;
            }
        }
    }
}

/// A digital sample type.
pub trait Sample: Copy + Default + Send + 'static {
    fn from_dn(v: u16) -> Self;
}
impl Sample for u8 {
    #[inline]
    fn from_dn(v: u16) -> Self {
        v as u8
    }
}
impl Sample for u16 {
    #[inline]
    fn from_dn(v: u16) -> Self {
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn linear(read_noise: f64) -> SensorConfig {
        SensorConfig {
            response: ResponseConfig::Linear,
            electrons_per_radiance_us: 1.0,
            full_well_e: 60000.0,
            read_noise_e: read_noise,
            dark_current_e_per_s: 0.0,
            ..SensorConfig::default()
        }
    }

    #[test]
    fn mean_and_variance_follow_shot_and_read_noise() {
        // 16-bit linear sensor: DN = e * 65535 / 60000. Mean 10000 e, read noise 20 e.
        let mut s = Sensor::new(&linear(20.0), 16, 7, Path::new(".")).unwrap();
        let rad = vec![10.0f32; 300_000];
        let mut out = vec![0u16; rad.len()];
        s.expose(&rad, 100, 3, 1.0, 1000.0, &mut out);
        let k = 65535.0 / 60000.0;
        let e: Vec<f64> = out.iter().map(|v| *v as f64 / k).collect();
        let mean = e.iter().sum::<f64>() / e.len() as f64;
        let var = e.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / e.len() as f64;
        assert!((mean - 10000.0).abs() < 1.0, "mean {mean}");
        let expect = 10000.0 + 400.0 + 1.0 / (12.0 * k * k);
        assert!((var / expect - 1.0).abs() < 0.02, "var {var} vs {expect}");
    }

    #[test]
    fn saturates_at_full_well_and_is_seeded() {
        let mut a = Sensor::new(&linear(5.0), 8, 3, Path::new(".")).unwrap();
        let mut b = Sensor::new(&linear(5.0), 8, 3, Path::new(".")).unwrap();
        let rad = vec![1000.0f32; 1200];
        let (mut oa, mut ob) = (vec![0u8; 1200], vec![0u8; 1200]);
        a.expose(&rad, 20, 3, 1.0, 1000.0, &mut oa);
        b.expose(&rad, 20, 3, 1.0, 1000.0, &mut ob);
        assert!(oa.iter().all(|v| *v == 255));
        let rad = vec![20.0f32; 1200];
        a.expose(&rad, 20, 3, 1.0, 1000.0, &mut oa);
        b.expose(&rad, 20, 3, 1.0, 1000.0, &mut ob);
        assert_eq!(oa, ob);
    }

    #[test]
    fn gamma_response_is_monotonic_and_spans_the_range() {
        let r = Response::new(&ResponseConfig::Gamma { gamma: 2.2 }, Path::new(".")).unwrap();
        assert_eq!(r.eval(0.0), 0.0);
        assert!((r.eval(1.0) - 1.0).abs() < 1e-6);
        assert!((r.eval(0.18) - 0.18f32.powf(1.0 / 2.2)).abs() < 2e-3);
        let mut last = -1.0;
        for i in 0..=1000 {
            let v = r.eval(i as f32 / 1000.0);
            assert!(v >= last);
            last = v;
        }
    }

    #[test]
    fn blooming_spills_into_neighbours() {
        let mut cfg = linear(0.0);
        cfg.blooming = 1.0;
        let mut s = Sensor::new(&cfg, 16, 1, Path::new(".")).unwrap();
        // 5x5 image (15 samples a row), one very bright pixel in the middle.
        let mut rad = vec![1.0f32; 75];
        for c in 0..3 {
            rad[(2 * 5 + 2) * 3 + c] = 600.0;
        }
        let mut out = vec![0u16; 75];
        s.expose(&rad, 5, 3, 1.0, 1000.0, &mut out);
        let px = |x: usize, y: usize| out[(y * 5 + x) * 3];
        assert_eq!(px(2, 2), 65535);
        assert_eq!(px(1, 2), 65535, "the excess spills left");
        assert!(px(0, 0) < 2000, "far pixels are untouched");
    }
}
