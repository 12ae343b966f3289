//! A channel whose bracket shows it in two exposures only up to some value, where another
//! channel's shows it higher: its curve continued there with the other channel's shape.
//!
//! A bright, nearly uniform tile on a dark table, bracketed from where its brightest
//! channel reads near full scale: one step longer that channel clips everywhere on the
//! tile, so its readings above the background's appear in the shortest exposure only, and
//! no pair of readings says what the curve is between the background's top and the tile.
//! Without a curve there the tile has no radiance in that channel and nothing can be
//! fitted (six scenes in a hundred of the second scene family: a green or blue channel
//! known only to mid-scale, the other two to the top). Cameras apply one tone curve to
//! every channel after their white balance, z = f(k_c E), so ln E(z) differs between
//! channels by a constant: where two channels' curves agree in shape over the values both
//! are measured at, the one measured higher gives the other its shape above. The shapes'
//! disagreement where both are measured (at least [`SHAPE_FLOOR`]) is kept as the
//! channel's misfit, which its curve draws carry into every interval.

use super::curve::{channel_name, rise_strictly, Channel, LN_EXPOSURE_LIMIT};
use super::samples::Samples;

/// Smallest shape allowance (rms, ln E) kept for a continued channel: over a short overlap
/// two channels may agree better than they do above it.
pub(super) const SHAPE_FLOOR: f64 = 0.01;

/// Largest disagreement in shape (rms, ln E, over the values both channels are measured
/// at) for which one channel's shape is lent to another: beyond it the channels do not
/// share a tone curve, and the values stay without radiance.
const SHAPE_LIMIT: f64 = 0.05;

/// One channel continued with another's shape (the warning names which).
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Borrowed {
    pub channel: usize,
    /// The channel's own curve ends here (the top of the values it is read at in two
    /// exposures); above, up to the new `valid_max`, the shape is `from`'s.
    pub own_top: u32,
    /// The shapes' rms disagreement over the values both are measured at (ln E).
    pub disagreement: f64,
}

/// The highest value a sample reads unclipped, among samples with two or more readings
/// between black and the top (only those tie the curve down there); None for none.
pub(super) fn observed_top(s: &Samples, max: u32) -> Option<u32> {
    s.values
        .iter()
        .filter(|v| v.iter().filter(|z| **z > 0 && (**z as u32) < max).count() >= 2)
        .flat_map(|v| v.iter().map(|z| *z as u32).filter(|z| *z > 0 && *z < max))
        .max()
}

/// Continue every table channel whose curve ends well below another's with that channel's
/// shape (the one that agrees best over the two stops below the channel's own top, within
/// [`SHAPE_LIMIT`]), and
/// say so in `warnings`. `tops[c]` is [`observed_top`] of channel `c`'s samples. Linear
/// curves are left as they are (their formula holds over every value).
pub(super) fn borrow_shapes(
    channels: &mut [Channel],
    tops: &[Option<u32>],
    max: u32,
    warnings: &mut Vec<String>,
) -> Vec<Borrowed> {
    let levels = max as usize + 1;
    let table = |ch: &Channel| ch.ln_exposure.len() == levels;
    let mut out: Vec<Borrowed> = Vec::new();
    // Passes until nothing changes: a channel may lend a shape it borrowed itself (green
    // known to mid-scale, red to near the top, blue to the top), the disagreements added
    // in quadrature.
    for _ in 0..channels.len() {
        let mut changed = false;
        // Highest first: a channel lends the most once it has been continued itself.
        let mut order: Vec<usize> = (0..channels.len()).collect();
        order.sort_by_key(|c| std::cmp::Reverse(channels[*c].valid_max));
        for c in order {
            if !table(&channels[c]) || out.iter().any(|b| b.channel == c) {
                continue;
            }
            let Some(obs) = tops.get(c).copied().flatten() else {
                continue;
            };
            let ch = &channels[c];
            let top = ch.valid_max.min(obs);
            if top <= ch.valid_min {
                continue;
            }
            // The sibling that agrees best in shape where both are measured, among those
            // whose curve reaches a sixteenth of the range higher.
            let lent = |s: usize| {
                out.iter()
                    .find(|b| b.channel == s)
                    .map_or(0.0, |b| b.disagreement)
            };
            let best = channels
                .iter()
                .enumerate()
                .filter(|(s, sib)| {
                    *s != c && table(sib) && sib.valid_max as usize >= top as usize + levels / 16
                })
                .filter_map(|(s, sib)| {
                    // The two stops below the channel's own top (where both are known):
                    // the shape next to where the borrowed one takes over, and clear of
                    // the dark end, where read noise bends every curve its own way.
                    let b = top.min(sib.valid_max);
                    let a = ch.valid_min.max(sib.valid_min).max(b / 4);
                    if (b as usize) < a as usize + (levels / 64).max(8) {
                        return None;
                    }
                    let (m, offset) = shape_disagreement(ch, sib, a, b);
                    (m <= SHAPE_LIMIT).then(|| (s, m, m.hypot(lent(s)), offset, a))
                })
                .min_by(|x, y| x.2.total_cmp(&y.2));
            let Some((s, m, total, offset, a)) = best else {
                continue;
            };
            let sib = channels[s].clone();
            let dst = &mut channels[c];
            let t = top as usize;
            // Above the top, the sibling's curve with the offset the two stops below give
            // (a curve's own last values, at the edge of its data, are its least sure);
            // over those two stops, a blend from the channel's own curve to that one,
            // linear in ln z, so that the curve stays continuous.
            let lent_curve = |z: usize| sib.ln_exposure[z] + offset;
            let (la, lt) = ((a.max(1) as f64).ln(), (t as f64).ln());
            for z in a as usize..=t {
                let w = if lt > la {
                    ((z as f64).ln() - la) / (lt - la)
                } else {
                    1.0
                };
                dst.ln_exposure[z] = (1.0 - w) * dst.ln_exposure[z] + w * lent_curve(z);
            }
            for z in t + 1..levels {
                dst.ln_exposure[z] = lent_curve(z).clamp(-LN_EXPOSURE_LIMIT, LN_EXPOSURE_LIMIT);
            }
            // Where the blend dipped (by far less than the curve's uncertainty), it rises
            // by the least step again: every reader requires a rising curve.
            rise_strictly(
                &mut dst.ln_exposure[a as usize..=(sib.valid_max as usize).min(levels - 1)],
            );
            if dst.ln_exposure_sd.len() == levels && sib.ln_exposure_sd.len() == levels {
                dst.ln_exposure_sd[t + 1..].copy_from_slice(&sib.ln_exposure_sd[t + 1..]);
            }
            dst.valid_max = sib.valid_max;
            let n = channels.len();
            let why = if obs <= top {
                "no sample pixel reads above it in two exposures"
            } else {
                "the bracket does not determine its curve above it"
            };
            warnings.push(format!(
                "channel {}: its curve is known up to {top} ({why}), so above it the curve takes channel {}'s shape, up to {} (the two agree within {:.2}% rms over the two stops below {top}; radiance there rests on the channels sharing one tone curve); add an exposure one stop shorter than the shortest to measure it",
                channel_name(n, c),
                channel_name(n, s),
                sib.valid_max,
                100.0 * m
            ));
            out.push(Borrowed {
                channel: c,
                own_top: top,
                disagreement: total,
            });
            changed = true;
        }
        if !changed {
            break;
        }
    }
    out
}

/// Rms of ln E(z) of `a` less `b`'s, less its mean, over `lo..=hi` (at most about 512
/// values, evenly spaced): how far the two curves differ in shape there; and the mean
/// (the offset between them there).
fn shape_disagreement(a: &Channel, b: &Channel, lo: u32, hi: u32) -> (f64, f64) {
    let stride = ((hi - lo) as usize / 512).max(1);
    let d: Vec<f64> = (lo as usize..=hi as usize)
        .step_by(stride)
        .map(|z| a.ln_exposure[z] - b.ln_exposure[z])
        .collect();
    let mean = d.iter().sum::<f64>() / d.len() as f64;
    let rms = (d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / d.len() as f64).sqrt();
    (rms, mean)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A table channel of a 12-bit-like format (`max` 4095) with the curve `f` (ln E of z),
    /// valid over `lo..=hi`.
    fn channel(f: impl Fn(f64) -> f64, lo: u32, hi: u32, max: u32) -> Channel {
        let g: Vec<f64> = (0..=max).map(|z| f((z as f64).max(0.5))).collect();
        let sd = vec![0.001; max as usize + 1];
        Channel::table(g, sd, Vec::new(), (lo as usize, hi as usize), 0.01, 100)
    }

    #[test]
    fn a_channel_known_to_mid_scale_takes_the_shape_of_one_known_to_the_top() {
        let max = 4095;
        // One tone curve (gamma 2.2 with a shoulder) after white-balance gains: ln E of
        // each channel differs by a constant.
        let curve = |z: f64| 2.2 * (z / 4095.0).ln() + 0.3 * (z / 4095.0).powi(3);
        let mut chs = vec![
            channel(|z| curve(z) - 0.2, 100, 4000, max),
            // Green's own curve ends at mid-scale, and above is a smoothing prior's guess.
            channel(|z| curve(z).min(curve(2048.0)) + 1e-6 * z, 100, 2048, max),
            channel(|z| curve(z) + 0.4, 100, 4000, max),
        ];
        let mut warnings = Vec::new();
        let tops = [Some(4000), Some(1500), Some(4000)];
        let b = borrow_shapes(&mut chs, &tops, max, &mut warnings);
        assert_eq!(b.len(), 1, "{b:?}");
        assert_eq!((b[0].channel, b[0].own_top), (1, 1500));
        assert!(b[0].disagreement < 1e-3, "{b:?}");
        assert_eq!(chs[1].valid_max, 4000);
        // Above its own top green follows the true curve (up to its constant).
        for z in [1600usize, 2500, 3500, 4000] {
            let want = curve(z as f64) - curve(1500.0) + chs[1].ln_exposure[1500];
            assert!((chs[1].ln_exposure[z] - want).abs() < 1e-3, "value {z}");
        }
        assert!(warnings[0].contains("channel G") && warnings[0].contains("one stop shorter"));
        // Red and blue were left alone.
        assert_eq!(chs[0].valid_max, 4000);
        assert_eq!(chs[2].valid_max, 4000);
    }

    #[test]
    fn channels_of_different_shapes_lend_nothing() {
        let max = 4095;
        let mut chs = vec![
            channel(|z| 2.2 * (z / 4095.0).ln(), 100, 4000, max),
            channel(|z| 1.0 * (z / 4095.0).ln(), 100, 2048, max),
        ];
        let mut warnings = Vec::new();
        let b = borrow_shapes(&mut chs, &[Some(4000), Some(2048)], max, &mut warnings);
        assert!(b.is_empty(), "{b:?}");
        assert_eq!(chs[1].valid_max, 2048);
        assert!(warnings.is_empty());
    }

    #[test]
    fn the_observed_top_counts_only_samples_read_in_two_exposures() {
        let s = Samples {
            pixels: vec![0, 1, 2],
            values: vec![
                vec![100, 400, 4095],
                vec![3000, 4095, 4095],
                vec![0, 900, 2000],
            ],
        };
        assert_eq!(observed_top(&s, 4095), Some(2000));
    }
}
