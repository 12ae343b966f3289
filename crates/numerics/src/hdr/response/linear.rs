//! The linear curve: E = (z - black) x gain, the black level from the dark frames or the
//! bracket itself.

use super::curve::{channel_name, Channel, Noise};
use super::samples::{hat, Samples};
use crate::hdr::bracket::{Bracket, DarkMedian};
use crate::hdr::error::CurveError;

/// Linear model for one channel: black level from the dark frames (the intercept of their
/// medians against exposure time; one dark exposure: its median) or, without dark frames, from the bracket itself (one common intercept of the
/// samples' lines of value against exposure time). Returns the channel and the BIC of the
/// fit in the same weighted ln E residuals as the Debevec fit (so they can be compared).
pub(super) fn fit_linear(
    s: &Samples,
    b: &Bracket,
    darks: &[DarkMedian],
    c: usize,
    max: u32,
) -> Result<Channel, CurveError> {
    let t: Vec<f64> = b.frames.iter().map(|f| f.exposure_us).collect();
    let usable = |z: u16| z > 0 && (z as u32) < max;
    // Dark frames at several exposures: the black level is the intercept of their medians
    // against exposure time. Dark current adds charge in proportion to the time, as
    // radiance does (the merge takes it out with the dark frames); taken as black level, the
    // shortest dark frame's 25 e of dark current bent a linear sensor's curve enough that
    // BIC preferred a polynomial.
    let dark_t: Vec<f64> = darks.iter().map(|f| f.exposure_us).collect();
    let spread = dark_t.iter().cloned().fold(f64::NEG_INFINITY, f64::max)
        > 1.5 * dark_t.iter().cloned().fold(f64::INFINITY, f64::min);
    let black = if spread {
        let m: Vec<f64> = darks.iter().map(|d| d.median[c]).collect();
        let n = m.len() as f64;
        let (mt, mm) = (dark_t.iter().sum::<f64>() / n, m.iter().sum::<f64>() / n);
        let stt: f64 = dark_t.iter().map(|t| (t - mt).powi(2)).sum();
        let stm: f64 = dark_t
            .iter()
            .zip(&m)
            .map(|(t, v)| (t - mt) * (v - mm))
            .sum();
        (mm - stm / stt * mt).max(0.0)
    } else if let Some(d) = darks
        .iter()
        .min_by(|a, bb| a.exposure_us.total_cmp(&bb.exposure_us))
    {
        // Median over the shortest dark frame.
        d.median[c]
    } else {
        let (mut uv, mut vv) = (0.0, 0.0);
        for vals in &s.values {
            let idx: Vec<usize> = (0..vals.len()).filter(|j| usable(vals[*j])).collect();
            if idx.len() < 2 {
                continue;
            }
            let t2: f64 = idx.iter().map(|j| t[*j] * t[*j]).sum();
            let zt: f64 = idx.iter().map(|j| vals[*j] as f64 * t[*j]).sum();
            let st: f64 = idx.iter().map(|j| t[*j]).sum();
            for j in &idx {
                let u = vals[*j] as f64 - t[*j] * zt / t2;
                let v = 1.0 - t[*j] * st / t2;
                uv += u * v;
                vv += v * v;
            }
        }
        if vv > 0.0 {
            (uv / vv).max(0.0)
        } else {
            0.0
        }
    };
    let gain = 1.0 / (max as f64 - black).max(1.0);
    // Residuals in ln E with hat weights, as in the Debevec fit.
    let mut rss = 0.0;
    let mut rows = 0;
    for vals in &s.values {
        let obs: Vec<(f64, f64, f64)> = vals
            .iter()
            .enumerate()
            .filter(|(_, z)| usable(**z) && **z as f64 > black + 0.5)
            .map(|(j, z)| {
                (
                    ((*z as f64 - black) * gain).ln() - t[j].ln(),
                    hat(*z as u32, max),
                    0.0,
                )
            })
            .collect();
        let sw: f64 = obs.iter().map(|o| o.1 * o.1).sum();
        if obs.len() < 2 || sw == 0.0 {
            continue;
        }
        let mean = obs.iter().map(|o| o.1 * o.1 * o.0).sum::<f64>() / sw;
        for o in &obs {
            let r = o.0 - mean;
            rss += r * r;
            rows += 1;
        }
    }
    if rows == 0 {
        return Err(CurveError::NothingAboveBlack {
            channel: channel_name(b.channels, c).to_string(),
            black,
        });
    }
    let valid_min = (black.floor() as u32 + 1).max(1);
    Ok(Channel {
        ln_exposure: Vec::new(),
        coefficients: Vec::new(),
        coefficient_covariance: Vec::new(),
        ln_exposure_sd: Vec::new(),
        black,
        gain,
        valid_min,
        valid_max: max - 1,
        noise: Noise {
            shot: 0.0,
            read: 0.0,
        },
        rms_residual: (rss / rows as f64).sqrt(),
        misfit_sd: 0.0,
        samples: s.values.len(),
    })
}
