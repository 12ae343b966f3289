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
pub fn predict_box(
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
///
/// Only the tile's bounding box is worked on: the predicted values are computed for the
/// tile pixels alone (nothing else is compared), into buffers the size of the box.
pub fn pixel_metrics(
    rendered: &[f32],
    region: &Region,
    r: &Response,
    tiles: &Bracket,
    dark: &[[f64; 3]],
) -> PixelMetrics {
    let max = r.max_value() as f64;
    let per: Vec<ExposureMetrics> = tiles
        .frames
        .par_iter()
        .enumerate()
        .map(|(j, f)| {
            let b = BoxReadings::new(rendered, region, r, tiles, j, f.exposure_us, dark[j]);
            let (ssim, windows) = b.ssim(max);
            let m = b.readings;
            let rmse = (b.sse / m.max(1) as f64).sqrt();
            ExposureMetrics {
                exposure_us: f.exposure_us,
                readings: m,
                rmse: if m > 0 { rmse } else { f64::NAN },
                noise_rmse: if m > 0 {
                    (b.noise / m as f64).sqrt()
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

/// One exposure's photograph and prediction over the region's bounding box (samples
/// `nc * (y * bw + x) + c`, box coordinates): the readings compared, and their sums.
struct BoxReadings {
    bw: usize,
    bh: usize,
    nc: usize,
    /// Whether box pixel y * bw + x is a tile pixel.
    inside: Vec<bool>,
    obs: Vec<f32>,
    pred: Vec<f32>,
    counted: Vec<bool>,
    readings: usize,
    sse: f64,
    noise: f64,
}

impl BoxReadings {
    #[allow(clippy::too_many_arguments)]
    fn new(
        rendered: &[f32],
        region: &Region,
        r: &Response,
        tiles: &Bracket,
        j: usize,
        exposure_us: f64,
        dark: [f64; 3],
    ) -> Self {
        let nc = r.channels.len();
        let [x0, y0, x1, y1] = region.bbox;
        let (bw, bh) = if x1 < x0 || y1 < y0 {
            (0, 0)
        } else {
            (x1 - x0 + 1, y1 - y0 + 1)
        };
        let t = exposure_us * 1e-6;
        let mut b = BoxReadings {
            bw,
            bh,
            nc,
            inside: vec![false; bw * bh],
            obs: vec![0.0; bw * bh * nc],
            pred: vec![f32::NAN; bw * bh * nc],
            counted: vec![false; bw * bh * nc],
            readings: 0,
            sse: 0.0,
            noise: 0.0,
        };
        // Row-major over the tile pixels, channels innermost: the sums are added in the
        // same order as over the whole frame.
        for y in 0..bh {
            for x in 0..bw {
                let k = (y0 + y) * region.width + x0 + x;
                if !region.inside[k] {
                    continue;
                }
                let i = y * bw + x;
                b.inside[i] = true;
                for c in 0..nc {
                    let ch = &r.channels[c];
                    let z = tiles.value(j, k, c) as f64;
                    let x_rad = rendered[nc * k + c];
                    let zp = if x_rad.is_finite() {
                        r.value(c, x_rad as f64 * t + dark[c]) as f32
                    } else {
                        f32::NAN
                    };
                    b.obs[nc * i + c] = z as f32;
                    b.pred[nc * i + c] = zp;
                    let zp = zp as f64;
                    let valid = |v: f64| v >= ch.valid_min as f64 && v <= ch.valid_max as f64;
                    if !(zp.is_finite() && valid(z) && valid(zp)) {
                        continue;
                    }
                    b.counted[nc * i + c] = true;
                    b.sse += (z - zp).powi(2);
                    let s = r.slope(c, zp);
                    b.noise += r.exposure_variance(c, zp) / (s * s).max(1e-300);
                    b.readings += 1;
                }
            }
        }
        b
    }

    /// Mean SSIM of the photograph against the prediction and the windows scored.
    fn ssim(&self, range: f64) -> (f64, usize) {
        ssim_box(
            &self.obs,
            &self.pred,
            &self.counted,
            &self.inside,
            [self.bw, self.bh, self.nc],
            range,
        )
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
    // The box's samples, then the same computation as pixel_metrics'.
    let mut inside = Vec::with_capacity(bw * bh);
    let (mut ba, mut bb, mut bc) = (
        Vec::with_capacity(bw * bh * nc),
        Vec::with_capacity(bw * bh * nc),
        Vec::with_capacity(bw * bh * nc),
    );
    for y in y0..=y1 {
        let row = y * region.width + x0..y * region.width + x1 + 1;
        inside.extend_from_slice(&region.inside[row.clone()]);
        let row = nc * row.start..nc * row.end;
        ba.extend_from_slice(&a[row.clone()]);
        bb.extend_from_slice(&b[row.clone()]);
        bc.extend_from_slice(&counted[row]);
    }
    ssim_box(&ba, &bb, &bc, &inside, [bw, bh, nc], range)
}

/// [`ssim`] on a box's own samples: `a`, `b`, `counted` hold `nc * (y * bw + x) + c`,
/// `inside` whether box pixel y * bw + x is in the region; `size` is [bw, bh, nc].
///
/// Per channel the five maps (a, b, a², b², ab; counted readings only) are blurred
/// with the separable window, rows then columns, one row of output at a time, and the
/// SSIM is scored at the pixels whose window holds only counted readings. Each blurred
/// value is the sum of the same products, added in the same order, as a direct
/// convolution's: the result does not depend on the loop order.
fn ssim_box(
    a: &[f32],
    b: &[f32],
    counted: &[bool],
    inside: &[bool],
    size: [usize; 3],
    range: f64,
) -> (f64, usize) {
    let [bw, bh, nc] = size;
    if bw < 11 || bh < 11 {
        return (f64::NAN, 0);
    }
    let g = gauss();
    let c1 = (0.01 * range).powi(2);
    let c2 = (0.03 * range).powi(2);
    let (mut sum, mut count) = (0.0, 0usize);
    let n = bw * bh;
    // The five maps, then their row blurs (columns 5..bw - 5), as [map][pixel].
    let mut maps = vec![0.0f64; 5 * n];
    let mut rows = vec![0.0f64; 5 * n];
    let mut bad = vec![0u32; (bw + 1) * (bh + 1)];
    let mut out = vec![0.0f64; 5 * bw];
    for c in 0..nc {
        maps.fill(0.0);
        for i in 0..n {
            if counted[nc * i + c] {
                let (p, q) = (a[nc * i + c] as f64, b[nc * i + c] as f64);
                maps[i] = p;
                maps[n + i] = q;
                maps[2 * n + i] = p * p;
                maps[3 * n + i] = q * q;
                maps[4 * n + i] = p * q;
            }
        }
        // Rows: out[x] = sum_i g[i] m[x + i - 5], for x in 5..bw - 5.
        rows.fill(0.0);
        for (m, h) in maps.chunks_exact(bw).zip(rows.chunks_exact_mut(bw)) {
            let h = &mut h[5..bw - 5];
            for (i, gi) in g.iter().enumerate() {
                h.iter_mut()
                    .zip(&m[i..i + bw - 10])
                    .for_each(|(o, v)| *o += gi * v);
            }
        }
        // Windows with every reading counted: a box count of uncounted readings.
        for y in 0..bh {
            for x in 0..bw {
                bad[(y + 1) * (bw + 1) + x + 1] =
                    bad[y * (bw + 1) + x + 1] + bad[(y + 1) * (bw + 1) + x] - bad[y * (bw + 1) + x]
                        + u32::from(!counted[nc * (y * bw + x) + c]);
            }
        }
        let window_bad = |x: usize, y: usize| {
            let (xa, ya, xb, yb) = (x - 5, y - 5, x + 6, y + 6);
            bad[yb * (bw + 1) + xb] + bad[ya * (bw + 1) + xa]
                - bad[ya * (bw + 1) + xb]
                - bad[yb * (bw + 1) + xa]
        };
        for y in 5..bh - 5 {
            if (5..bw - 5).all(|x| !inside[y * bw + x] || window_bad(x, y) != 0) {
                continue;
            }
            // Columns, for this output row: out[k][x] = sum_i g[i] rows[k][(y + i - 5), x].
            out.fill(0.0);
            for (k, o) in out.chunks_exact_mut(bw).enumerate() {
                let o = &mut o[5..bw - 5];
                for (i, gi) in g.iter().enumerate() {
                    let src = &rows[k * n + (y + i - 5) * bw..][5..bw - 5];
                    o.iter_mut().zip(src).for_each(|(o, v)| *o += gi * v);
                }
            }
            for x in 5..bw - 5 {
                if window_bad(x, y) != 0 || !inside[y * bw + x] {
                    continue;
                }
                let (ma, mb) = (out[x], out[bw + x]);
                let va = out[2 * bw + x] - ma * ma;
                let vb = out[3 * bw + x] - mb * mb;
                let cov = out[4 * bw + x] - ma * mb;
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The SSIM as first written: every map blurred over the whole box by a direct
    /// convolution, then scored.
    fn ssim_direct(
        a: &[f32],
        b: &[f32],
        counted: &[bool],
        region: &Region,
        range: f64,
    ) -> (f64, usize) {
        let nc = a.len() / (region.width * region.height);
        let [x0, y0, x1, y1] = region.bbox;
        let (bw, bh) = (x1 - x0 + 1, y1 - y0 + 1);
        let w = region.width;
        let g = gauss();
        let (c1, c2) = ((0.01 * range).powi(2), (0.03 * range).powi(2));
        let (mut sum, mut count) = (0.0, 0usize);
        for c in 0..nc {
            let at = |x: usize, y: usize| nc * ((y0 + y) * w + x0 + x) + c;
            let map = |f: &dyn Fn(f64, f64) -> f64| -> Vec<f64> {
                let mut m = vec![0.0; bw * bh];
                for y in 0..bh {
                    for x in 0..bw {
                        if counted[at(x, y)] {
                            m[y * bw + x] = f(a[at(x, y)] as f64, b[at(x, y)] as f64);
                        }
                    }
                }
                m
            };
            let blur_at = |m: &[f64], x: usize, y: usize| -> f64 {
                (0..11)
                    .map(|j| {
                        g[j] * (0..11)
                            .map(|i| g[i] * m[(y + j - 5) * bw + x + i - 5])
                            .sum::<f64>()
                    })
                    .sum()
            };
            let maps = [
                map(&|p, _| p),
                map(&|_, q| q),
                map(&|p, _| p * p),
                map(&|_, q| q * q),
                map(&|p, q| p * q),
            ];
            for y in 5..bh.saturating_sub(5) {
                for x in 5..bw.saturating_sub(5) {
                    let all =
                        (y - 5..=y + 5).all(|yy| (x - 5..=x + 5).all(|xx| counted[at(xx, yy)]));
                    if !all || !region.inside[(y0 + y) * w + x0 + x] {
                        continue;
                    }
                    let v = maps.each_ref().map(|m| blur_at(m, x, y));
                    let (ma, mb) = (v[0], v[1]);
                    let (va, vb, cov) = (v[2] - ma * ma, v[3] - mb * mb, v[4] - ma * mb);
                    sum += ((2.0 * ma * mb + c1) * (2.0 * cov + c2))
                        / ((ma * ma + mb * mb + c1) * (va + vb + c2));
                    count += 1;
                }
            }
        }
        (sum / count as f64, count)
    }

    #[test]
    fn ssim_equals_the_direct_convolution() {
        // A disc of tile in a 60 x 50 frame, RGB, with uncounted readings scattered.
        let (w, h, nc) = (60, 50, 3);
        let inside: Vec<bool> = (0..w * h)
            .map(|k| {
                let (x, y) = ((k % w) as f64 - 31.0, (k / w) as f64 - 24.0);
                x * x + y * y < 20.0 * 20.0
            })
            .collect();
        let region = Region::new(w, h, inside);
        let mut s = 12345u64;
        let mut rnd = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 33) as f64 / (1u64 << 31) as f64
        };
        let n = w * h * nc;
        let a: Vec<f32> = (0..n)
            .map(|i| (100.0 + 80.0 * ((i / 7) as f64).sin()).round() as f32)
            .collect();
        let b: Vec<f32> = a.iter().map(|v| v + (4.0 * rnd() - 2.0) as f32).collect();
        let counted: Vec<bool> = (0..n)
            .map(|i| region.inside[i / nc] && rnd() > 0.002)
            .collect();
        let fast = ssim(&a, &b, &counted, &region, 255.0);
        let direct = ssim_direct(&a, &b, &counted, &region, 255.0);
        assert!(fast.1 > 100, "{fast:?}");
        assert_eq!(fast.1, direct.1);
        assert!((fast.0 - direct.0).abs() < 1e-12, "{fast:?} vs {direct:?}");
    }
}
