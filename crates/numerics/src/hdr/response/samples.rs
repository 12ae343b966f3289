//! The sample pixels a curve is recovered from, chosen deliberately, and the weights and
//! robust statistics every fit uses on them.

use crate::hdr::bracket::Bracket;

/// Debevec's hat weight on 0..=max.
pub(super) fn hat(z: u32, max: u32) -> f64 {
    let z = z as f64;
    let max = max as f64;
    let mid = 0.5 * max;
    if z <= mid {
        z
    } else {
        max - z
    }
}

/// The sample pixels of one channel: for each sample its value in every frame.
#[derive(Debug, Clone)]
pub struct Samples {
    /// Pixel index (y * width + x) of each sample.
    pub pixels: Vec<usize>,
    /// values[i][j]: sample i in frame j.
    pub values: Vec<Vec<u16>>,
}

/// Choose sample pixels deliberately (not at random): candidates on a regular grid away
/// from the image border, in flat neighbourhoods (so a slight shift or blur between frames
/// does not matter), never saturated or black in every frame, and stratified so that their
/// values cover the whole range in every frame. Readings from `sat` (the channel's
/// [`Bracket::clip_levels`]) up are saturated: they are handed on as the format's top, so
/// that every fit sees them as such. So is a reading next to one (its 3x3 neighbourhood in
/// the same frame and channel): a demosaicked camera interpolates each channel from the
/// neighbouring photosites, so beside a clipped one it reads too low, neither clipped nor
/// measured, and a few thousand such readings at the top of the longest frames bend a
/// polynomial curve by tens of percent (a second scene family's Bayer cameras:
/// docs/results/accuracy.md). Deterministic.
pub fn select_samples(b: &Bracket, c: usize, n: usize, sat: u32) -> Samples {
    let (w, h) = (b.width, b.height);
    let max = b.max_value();
    let margin = ((w.min(h) as f64 * 0.03) as usize).max(2);
    let nf = b.frames.len();
    // A grid of about 40 000 candidates.
    let area = (w - 2 * margin).max(1) * (h - 2 * margin).max(1);
    let stride = ((area as f64 / 40_000.0).sqrt().floor() as usize).max(1);
    let mid_frame = nf / 2;
    // A reading at or beside a clipped one counts as clipped (see above); `margin` >= 2
    // keeps the neighbourhood inside the image.
    // Only a reading of at least a quarter of the clip can be one: interpolated from at most
    // four photosites, one of them clipped, it reads at least that.
    let read = |j: usize, p: usize| -> u32 {
        let v = b.value(j, p, c);
        let near = [
            p - w - 1,
            p - w,
            p - w + 1,
            p - 1,
            p + 1,
            p + w - 1,
            p + w,
            p + w + 1,
        ];
        let clipped = v >= sat || (4 * v >= sat && near.iter().any(|q| b.value(j, *q, c) >= sat));
        if clipped {
            sat.max(max)
        } else {
            v
        }
    };
    struct Cand {
        p: usize,
        flat: u32,
        /// Its readings in every frame ([`read`]'s: clipped ones at the top).
        vals: Vec<u32>,
    }
    let mut cands: Vec<Cand> = Vec::new();
    let mut y = margin;
    while y + margin < h {
        let mut x = margin;
        while x + margin < w {
            let p = y * w + x;
            let vals: Vec<u32> = (0..nf).map(|j| read(j, p)).collect();
            let informative = vals.iter().filter(|v| **v > 0 && **v < sat).count() >= 2;
            // Values must not fall as exposure grows (moving objects, noise spikes).
            let monotone = vals.windows(2).all(|v| v[1] + (max / 32).max(2) >= v[0]);
            if informative && monotone {
                let v0 = b.value(mid_frame, p, c) as i64;
                let flat = [p - 1, p + 1, p - w, p + w]
                    .iter()
                    .map(|q| (b.value(mid_frame, *q, c) as i64 - v0).unsigned_abs())
                    .max()
                    .unwrap_or(0) as u32;
                cands.push(Cand { p, flat, vals });
            }
            x += stride;
        }
        y += stride;
    }
    // Flattest first; ties broken by a fixed scramble of position (spreads over the image).
    let scramble = |p: usize| (p as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15) >> 32;
    cands.sort_by_key(|c| (c.flat, scramble(c.p)));
    // Strata: (frame, value bin).
    let bins = 32usize;
    let mut strata: Vec<Vec<usize>> = vec![Vec::new(); nf * bins];
    for (k, cand) in cands.iter().enumerate() {
        for (j, &v) in cand.vals.iter().enumerate() {
            if v > 0 && v < sat {
                let bin = (v as usize * bins / (max as usize + 1)).min(bins - 1);
                strata[j * bins + bin].push(k);
            }
        }
    }
    let mut taken = vec![false; cands.len()];
    let mut chosen = Vec::new();
    let mut cursor = vec![0usize; strata.len()];
    while chosen.len() < n {
        let mut progress = false;
        for (s, list) in strata.iter().enumerate() {
            while cursor[s] < list.len() && taken[list[cursor[s]]] {
                cursor[s] += 1;
            }
            if cursor[s] < list.len() {
                let k = list[cursor[s]];
                taken[k] = true;
                chosen.push(k);
                progress = true;
                if chosen.len() == n {
                    break;
                }
            }
        }
        if !progress {
            break;
        }
    }
    chosen.sort_unstable_by_key(|k| cands[*k].p);
    let values = chosen
        .iter()
        .map(|k| {
            cands[*k]
                .vals
                .iter()
                .map(|&v| if v >= sat { max as u16 } else { v as u16 })
                .collect()
        })
        .collect();
    Samples {
        pixels: chosen.iter().map(|k| cands[*k].p).collect(),
        values,
    }
}

/// Most sample pixels per channel Debevec's dense solve is given.
pub const MAX_DEBEVEC_SAMPLES: usize = 1500;

/// Default number of samples: enough equations for the 256 unknowns several times over
/// (Debevec: N (P - 1) > 255), at least 300, at most 600.
pub fn default_samples(exposures: usize) -> usize {
    let p = exposures.max(2) - 1;
    (16 * 256 / p).clamp(300, 600)
}

/// Median (reorders the slice); 0 for an empty one.
pub fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let k = v.len() / 2;
    *v.select_nth_unstable_by(k, |a, b| a.total_cmp(b)).1
}
