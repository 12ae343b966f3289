//! The noise model in exposure units, var(E) = shot x E + read, estimated from how the sample
//! pixels' readings scatter about their radiance.

use super::curve::{Noise, Response};
use super::samples::{median, Samples};
use crate::hdr::bracket::Bracket;

/// Estimate shot and read noise (exposure units) per channel from how the sample pixels'
/// readings scatter about their common radiance, after removing the quantisation part.
/// Pixels read in three exposures or more are used; where they are too few for a channel
/// (or show no noise beyond quantisation), pixels read in two are used too. A channel
/// that still has no noise takes the largest of the other channels' (a zero noise model
/// makes every later chi-square and interval meaningless: second family seed 14011, a
/// 16-bit camera with three exposures and most of its blue readings too dark in one of
/// them, merged blue with a relative sd of 1e-5 and the fit's chi-square came out 5e5).
/// Returns the channels that took another's noise.
pub(super) fn estimate_noise(r: &mut Response, b: &Bracket, samples: &[Samples]) -> Vec<usize> {
    let t: Vec<f64> = b.frames.iter().map(|f| f.exposure_us).collect();
    for (c, s) in samples.iter().enumerate() {
        for min_readings in [3, 2] {
            if let Some(n) = channel_noise(r, c, s, &t, min_readings) {
                r.channels[c].noise = n;
                break;
            }
        }
    }
    let mut lent = Vec::new();
    if let Some(fallback) = r
        .channels
        .iter()
        .map(|ch| ch.noise)
        .filter(has_noise)
        .reduce(|a, b| Noise {
            shot: a.shot.max(b.shot),
            read: a.read.max(b.read),
        })
    {
        for (c, ch) in r.channels.iter_mut().enumerate() {
            if c < samples.len() && !has_noise(&ch.noise) {
                ch.noise = fallback;
                lent.push(c);
            }
        }
    }
    lent
}

/// Whether a noise model has any noise.
fn has_noise(n: &Noise) -> bool {
    n.shot > 0.0 || n.read > 0.0
}

/// Channel c's noise from the pixels read in `min_readings` exposures or more: None where
/// there are too few, or they show no noise beyond quantisation.
fn channel_noise(
    r: &Response,
    c: usize,
    s: &Samples,
    t: &[f64],
    min_readings: usize,
) -> Option<Noise> {
    // Two passes: the first weighs readings by their quantisation alone, the second by
    // the first pass's whole noise model. Each deviation from the pixel's fitted
    // radiance is divided by sqrt(1 - h), h its leverage (its weight's share of the
    // fit): a reading that dominates the fit deviates little from it, and without the
    // correction the noise came out 30% too low (its readings pulled the median down).
    let mut noise: Option<Noise> = None;
    for _pass in 0..2 {
        let binned = noise_bins(r, c, s, t, noise, min_readings)?;
        let (shot, read) = fit_noise_robust(&binned);
        noise = Some(Noise { shot, read });
    }
    noise.filter(has_noise)
}

/// Binned (exposure, noise variance) of channel c's sample readings; readings weighed
/// by `noise` (or by quantisation alone when None). None when there are too few.
fn noise_bins(
    r: &Response,
    c: usize,
    s: &Samples,
    t: &[f64],
    noise: Option<Noise>,
    min_readings: usize,
) -> Option<Vec<(f64, f64)>> {
    let (lo, hi) = (r.channels[c].valid_min, r.channels[c].valid_max);
    // (E, |standardised deviation|, quantisation variance) per reading.
    let mut pts: Vec<(f64, f64, f64)> = Vec::new();
    for vals in &s.values {
        let obs: Vec<(f64, f64, f64)> = vals
            .iter()
            .enumerate()
            .filter(|(_, z)| (**z as u32) >= lo && (**z as u32) <= hi)
            .map(|(j, z)| {
                let e = r.exposure(c, *z as f64);
                let sl = r.slope(c, *z as f64);
                (e, t[j], sl * sl / 12.0)
            })
            .collect();
        if obs.len() < min_readings.max(2) {
            continue;
        }
        let var = |e: f64, q: f64| match noise {
            Some(n) => n.shot * e.max(0.0) + n.read + q,
            None => q,
        };
        // Radiance by weighted least squares through the origin: E_j = x t_j.
        let (mut num, mut den) = (0.0, 0.0);
        for (e, tj, q) in &obs {
            let w = 1.0 / (var(*e, *q) + 1e-12);
            num += w * e * tj;
            den += w * tj * tj;
        }
        let x = num / den;
        for (e, tj, q) in &obs {
            let w = 1.0 / (var(x * tj, *q) + 1e-12);
            let h = w * tj * tj / den;
            if h < 0.9 {
                pts.push((x * tj, (e - x * tj).abs() / (1.0 - h).sqrt(), *q));
            }
        }
    }
    // Bin by exposure; in each bin a robust variance (MAD, so that a few outliers or
    // moving pixels do not count) less the quantisation part; then the caller fits
    // var = shot E + read (both >= 0) robustly across the bins (see fit_noise_robust).
    if pts.len() < 20 {
        return None;
    }
    pts.sort_by(|a, b| a.0.total_cmp(&b.0));
    let nb = 16.min(pts.len() / 10).max(2);
    let per = pts.len() / nb;
    Some(
        pts.chunks(per)
            .filter_map(|ch| {
                let m = ch.len() as f64;
                let e = ch.iter().map(|p| p.0).sum::<f64>() / m;
                let mut d: Vec<f64> = ch.iter().map(|p| p.1).collect();
                // The mean square of the deviations within 4 robust sd (the MAD alone is
                // biased low when the quantisation step is as large as the noise, as at
                // the top of an 8-bit gamma curve).
                let cut = 4.0 * 1.4826 * median(&mut d);
                let kept: Vec<f64> = d.iter().copied().filter(|x| *x <= cut).collect();
                let ms = kept.iter().map(|x| x * x).sum::<f64>() / kept.len().max(1) as f64;
                let q = ch.iter().map(|p| p.2).sum::<f64>() / m;
                let v = (ms - q).max(0.0);
                (e > 0.0).then_some((e, v))
            })
            .collect(),
    )
}

/// Fit var = shot E + read (both >= 0) to binned (E, var) by least median of the log
/// ratio: every line through two bins, and every one-term model through one bin, is scored
/// by the median over the bins of |ln(var / model)|; the best wins. Bins where the curve
/// itself misfits (next to black or saturation, where a real camera's scatter can be ten
/// times its noise) are a minority and cannot pull the fit, as they do a least-squares fit.
fn fit_noise_robust(bins: &[(f64, f64)]) -> (f64, f64) {
    let mut cands: Vec<(f64, f64)> = Vec::new();
    for (i, a) in bins.iter().enumerate() {
        if a.0 > 0.0 {
            cands.push((a.1 / a.0, 0.0));
        }
        cands.push((0.0, a.1));
        for b in &bins[i + 1..] {
            if (b.0 - a.0).abs() > 0.0 {
                let shot = (b.1 - a.1) / (b.0 - a.0);
                let read = a.1 - shot * a.0;
                if shot >= 0.0 && read >= 0.0 {
                    cands.push((shot, read));
                }
            }
        }
    }
    let score = |(shot, read): (f64, f64)| {
        let mut d: Vec<f64> = bins
            .iter()
            .filter(|b| b.1 > 0.0)
            .map(|b| {
                let m = shot * b.0 + read;
                if m > 0.0 {
                    (b.1 / m).ln().abs()
                } else {
                    f64::INFINITY
                }
            })
            .collect();
        median(&mut d)
    };
    cands
        .into_iter()
        .filter(|c| c.0 + c.1 > 0.0)
        .map(|c| (score(c), c))
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, c)| c)
        .unwrap_or((0.0, 0.0))
}
