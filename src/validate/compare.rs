//! Rendered radiance back into pixel values and compared with the photographs.
//!
//! A rendering is turned into the frame the camera would have taken at exposure t by the
//! response: z = f(X t + D), f the inverse of the recovered curve ([`Response::value`]),
//! D the frame's dark level. The comparison is over the tile pixels only (those the
//! fitter may sample), reading by reading; a reading counts when both the photograph's
//! value and the prediction lie inside the response's valid range (saturated and too-dark
//! readings carry no number to compare). Reported per exposure and pooled:
//!
//! - RMSE in pixel values, beside the RMSE that noise alone would give (the response's
//!   noise model at the predicted value): a model that explains the tile reaches it;
//! - PSNR = 20 log10(max value / RMSE);
//! - SSIM (Wang et al. 2004: 11x11 Gaussian window, sigma 1.5, K1 = 0.01, K2 = 0.03, the
//!   value range as L), per channel, averaged over the tile pixels whose whole window
//!   holds counted readings;
//! - in HDR space: the relative radiance error sqrt(sum (X_model - X)^2 / sum X^2) over the
//!   measured tile pixels, and the mean squared standardised residual (about 1 when the
//!   model is within the noise).

use rayon::prelude::*;
use serde::Serialize;

use crate::hdr::response::Response;
use crate::hdr::Bracket;

/// The pixel values (fractional, before rounding) a camera with response `r` would show
/// for `radiance` at `exposure_us` with dark level `dark` (exposure units) per channel.
pub fn predict_frame(radiance: &[f32], r: &Response, exposure_us: f64, dark: [f64; 3]) -> Vec<f32> {
    let mut out = vec![f32::NAN; radiance.len()];
    predict_into(&mut out, radiance, r, exposure_us, dark, 0..radiance.len());
    out
}

/// [`predict_frame`] over the box (x0, y0, x1, y1) of an image `width` wide only (NaN
/// elsewhere, and everywhere for an empty box).
pub(crate) fn predict_box(
    radiance: &[f32],
    r: &Response,
    exposure_us: f64,
    dark: [f64; 3],
    bbox: [usize; 4],
    width: usize,
) -> Vec<f32> {
    let mut out = vec![f32::NAN; radiance.len()];
    let [x0, y0, x1, y1] = bbox;
    let nc = r.channels.len();
    for y in y0..=y1 {
        let row = nc * (y * width + x0)..nc * (y * width + x1 + 1);
        predict_into(&mut out, radiance, r, exposure_us, dark, row);
    }
    out
}

/// The predicted values of the samples `range` (RGB interleaved indices, or one sample a
/// pixel with a monochrome response) into `out`.
fn predict_into(
    out: &mut [f32],
    radiance: &[f32],
    r: &Response,
    exposure_us: f64,
    dark: [f64; 3],
    range: std::ops::Range<usize>,
) {
    let t = exposure_us * 1e-6;
    let nc = r.channels.len();
    for i in range {
        let c = i % nc;
        if radiance[i].is_finite() {
            out[i] = r.value(c, radiance[i] as f64 * t + dark[c]) as f32;
        }
    }
}

/// Figures for one exposure.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ExposureMetrics {
    pub exposure_us: f64,
    /// Readings compared (pixel x channel).
    pub readings: usize,
    pub rmse: f64,
    /// The RMSE the noise alone would give on the same readings.
    pub noise_rmse: f64,
    pub psnr_db: f64,
    /// Mean SSIM over the tile windows with every reading counted (NaN when none).
    pub ssim: f64,
    pub ssim_windows: usize,
}

/// Pixel-value figures over all exposures.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct PixelMetrics {
    pub readings: usize,
    pub rmse: f64,
    pub noise_rmse: f64,
    pub psnr_db: f64,
    pub ssim: f64,
    pub per_exposure: Vec<ExposureMetrics>,
}

/// HDR-space figures.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct RadianceMetrics {
    /// Measured tile samples compared (pixel x channel).
    pub samples: usize,
    /// sqrt(sum (model - measured)^2 / sum measured^2), all channels.
    pub relative_error: f64,
    /// The same per channel (R, G, B, or a monochrome camera's one).
    pub relative_error_rgb: Vec<f64>,
    /// Mean of (model - measured)^2 / variance.
    pub mean_z2: f64,
}

/// The tile region: pixels (y * width + x) to compare.
pub struct Region {
    pub width: usize,
    pub height: usize,
    pub inside: Vec<bool>,
    /// Bounding box (x0, y0, x1, y1), inclusive.
    pub bbox: [usize; 4],
}

impl Region {
    pub fn new(width: usize, height: usize, inside: Vec<bool>) -> Self {
        let (mut x0, mut y0, mut x1, mut y1) = (width, height, 0, 0);
        for (k, _) in inside.iter().enumerate().filter(|(_, b)| **b) {
            let (x, y) = (k % width, k / width);
            x0 = x0.min(x);
            y0 = y0.min(y);
            x1 = x1.max(x);
            y1 = y1.max(y);
        }
        Region {
            width,
            height,
            inside,
            bbox: [x0, y0, x1, y1],
        }
    }

    pub fn count(&self) -> usize {
        self.inside.iter().filter(|b| **b).count()
    }
}

fn psnr(max: f64, rmse: f64) -> f64 {
    20.0 * (max / rmse).log10()
}

/// Compare a rendering (radiance) with a bracket's photographs over `region`.
pub fn pixel_metrics(
    rendered: &[f32],
    region: &Region,
    r: &Response,
    tiles: &Bracket,
    dark: &[[f64; 3]],
) -> PixelMetrics {
    let max = r.max_value() as f64;
    let nc = r.channels.len();
    let per: Vec<ExposureMetrics> = tiles
        .frames
        .par_iter()
        .enumerate()
        .map(|(j, f)| {
            let pred = predict_box(
                rendered,
                r,
                f.exposure_us,
                dark[j],
                region.bbox,
                region.width,
            );
            let n = region.width * region.height;
            let mut counted = vec![false; n * nc];
            let mut obs = vec![0f32; n * nc];
            let (mut sse, mut noise, mut m) = (0.0, 0.0, 0usize);
            for k in (0..n).filter(|k| region.inside[*k]) {
                for c in 0..nc {
                    let ch = &r.channels[c];
                    let z = tiles.value(j, k, c) as f64;
                    let zp = pred[nc * k + c] as f64;
                    obs[nc * k + c] = z as f32;
                    let valid = |v: f64| v >= ch.valid_min as f64 && v <= ch.valid_max as f64;
                    if !(zp.is_finite() && valid(z) && valid(zp)) {
                        continue;
                    }
                    counted[nc * k + c] = true;
                    sse += (z - zp).powi(2);
                    let s = r.slope(c, zp);
                    noise += r.exposure_variance(c, zp) / (s * s).max(1e-300);
                    m += 1;
                }
            }
            let rmse = (sse / m.max(1) as f64).sqrt();
            let (ssim, windows) = ssim(&obs, &pred, &counted, region, max);
            ExposureMetrics {
                exposure_us: f.exposure_us,
                readings: m,
                rmse: if m > 0 { rmse } else { f64::NAN },
                noise_rmse: if m > 0 {
                    (noise / m as f64).sqrt()
                } else {
                    f64::NAN
                },
                psnr_db: if m > 0 { psnr(max, rmse) } else { f64::NAN },
                ssim,
                ssim_windows: windows,
            }
        })
        .collect();
    let m: usize = per.iter().map(|e| e.readings).sum();
    let pooled = |f: fn(&ExposureMetrics) -> f64| -> f64 {
        (per.iter()
            .filter(|e| e.readings > 0)
            .map(|e| f(e).powi(2) * e.readings as f64)
            .sum::<f64>()
            / m.max(1) as f64)
            .sqrt()
    };
    let rmse = pooled(|e| e.rmse);
    let windows: usize = per.iter().map(|e| e.ssim_windows).sum();
    PixelMetrics {
        readings: m,
        rmse,
        noise_rmse: pooled(|e| e.noise_rmse),
        psnr_db: psnr(max, rmse),
        ssim: if windows > 0 {
            per.iter()
                .filter(|e| e.ssim_windows > 0)
                .map(|e| e.ssim * e.ssim_windows as f64)
                .sum::<f64>()
                / windows as f64
        } else {
            f64::NAN
        },
        per_exposure: per,
    }
}

/// Compare a rendering with the merged radiance over `region`.
pub fn radiance_metrics(
    rendered: &[f32],
    region: &Region,
    radiance: &[f32],
    variance: &[f32],
    mask: &[u8],
) -> RadianceMetrics {
    let nc = radiance.len() / region.inside.len().max(1);
    let mut num = [0.0; 3];
    let mut den = [0.0; 3];
    let (mut z2, mut m) = (0.0, 0usize);
    for k in (0..region.inside.len()).filter(|k| region.inside[*k]) {
        for c in 0..nc {
            let i = nc * k + c;
            if mask[i] != crate::hdr::merge::MASK_OK || !radiance[i].is_finite() {
                continue;
            }
            let (x, p, v) = (radiance[i] as f64, rendered[i] as f64, variance[i] as f64);
            num[c] += (p - x).powi(2);
            den[c] += x * x;
            if v > 0.0 {
                z2 += (p - x).powi(2) / v;
            }
            m += 1;
        }
    }
    RadianceMetrics {
        samples: m,
        relative_error: (num.iter().sum::<f64>() / den.iter().sum::<f64>()).sqrt(),
        relative_error_rgb: (0..nc).map(|c| (num[c] / den[c]).sqrt()).collect(),
        mean_z2: z2 / m.max(1) as f64,
    }
}

/// 1-D Gaussian weights of the SSIM window.
fn gauss() -> [f64; 11] {
    let mut g = [0.0; 11];
    for (i, w) in g.iter_mut().enumerate() {
        let x = i as f64 - 5.0;
        *w = (-x * x / (2.0 * 1.5 * 1.5)).exp();
    }
    let s: f64 = g.iter().sum();
    g.map(|w| w / s)
}

/// Mean SSIM of `a` against `b` (RGB interleaved, or one sample a pixel), per channel,
/// over the pixels of the region whose 11x11 window holds only counted readings; and the
/// number of such windows.
pub fn ssim(a: &[f32], b: &[f32], counted: &[bool], region: &Region, range: f64) -> (f64, usize) {
    let nc = a.len() / (region.width * region.height).max(1);
    let [x0, y0, x1, y1] = region.bbox;
    if x1 < x0 || y1 < y0 {
        return (f64::NAN, 0);
    }
    let (bw, bh) = (x1 - x0 + 1, y1 - y0 + 1);
    let w = region.width;
    let g = gauss();
    let c1 = (0.01 * range).powi(2);
    let c2 = (0.03 * range).powi(2);
    let (mut sum, mut count) = (0.0, 0usize);
    for c in 0..nc {
        // Blur the five maps over the box, counted readings only (others weigh 0, and
        // windows that hold one are not scored).
        let at = |x: usize, y: usize| nc * ((y0 + y) * w + x0 + x) + c;
        let ok = |x: usize, y: usize| counted[at(x, y)];
        let maps = |f: &dyn Fn(f64, f64) -> f64| -> Vec<f64> {
            let mut m = vec![0.0; bw * bh];
            for y in 0..bh {
                for x in 0..bw {
                    if ok(x, y) {
                        m[y * bw + x] = f(a[at(x, y)] as f64, b[at(x, y)] as f64);
                    }
                }
            }
            m
        };
        let blur = |m: &[f64]| -> Vec<f64> {
            let mut h = vec![0.0; bw * bh];
            for y in 0..bh {
                for x in 5..bw.saturating_sub(5) {
                    h[y * bw + x] = (0..11).map(|i| g[i] * m[y * bw + x + i - 5]).sum();
                }
            }
            let mut out = vec![0.0; bw * bh];
            for y in 5..bh.saturating_sub(5) {
                for x in 0..bw {
                    out[y * bw + x] = (0..11).map(|i| g[i] * h[(y + i - 5) * bw + x]).sum();
                }
            }
            out
        };
        // Windows with every reading counted: a box count of uncounted readings.
        let mut bad = vec![0u32; (bw + 1) * (bh + 1)];
        for y in 0..bh {
            for x in 0..bw {
                bad[(y + 1) * (bw + 1) + x + 1] =
                    bad[y * (bw + 1) + x + 1] + bad[(y + 1) * (bw + 1) + x] - bad[y * (bw + 1) + x]
                        + u32::from(!ok(x, y));
            }
        }
        let window_bad = |x: usize, y: usize| {
            let (xa, ya, xb, yb) = (x - 5, y - 5, x + 6, y + 6);
            bad[yb * (bw + 1) + xb] + bad[ya * (bw + 1) + xa]
                - bad[ya * (bw + 1) + xb]
                - bad[yb * (bw + 1) + xa]
        };
        let mu_a = blur(&maps(&|p, _| p));
        let mu_b = blur(&maps(&|_, q| q));
        let aa = blur(&maps(&|p, _| p * p));
        let bb = blur(&maps(&|_, q| q * q));
        let ab = blur(&maps(&|p, q| p * q));
        for y in 5..bh.saturating_sub(5) {
            for x in 5..bw.saturating_sub(5) {
                if window_bad(x, y) != 0 || !region.inside[(y0 + y) * w + x0 + x] {
                    continue;
                }
                let i = y * bw + x;
                let (ma, mb) = (mu_a[i], mu_b[i]);
                let va = aa[i] - ma * ma;
                let vb = bb[i] - mb * mb;
                let cov = ab[i] - ma * mb;
                sum += ((2.0 * ma * mb + c1) * (2.0 * cov + c2))
                    / ((ma * ma + mb * mb + c1) * (va + vb + c2));
                count += 1;
            }
        }
    }
    if count == 0 {
        (f64::NAN, 0)
    } else {
        (sum / count as f64, count)
    }
}
