//! Debevec & Malik's free curve (1997): weighted least squares with a smoothness term and
//! the gauge g(mid) = 0, solved twice (hat weights, then outliers left out), checked
//! (determined by the data, not dominated by smoothing, monotonic, not ambiguous), and above
//! 8 bits solved on 256 bins of values.

use nalgebra::{DMatrix, DVector};

use crate::hdr::error::{CurveError, CurveProblem};

use super::checks::{isotonic, trim_by_bias};
use super::curve::{interp, rise_strictly, Channel, RecoverOptions};
use super::samples::{hat, median, Samples};

/// Result of a Debevec solve of one channel.
struct DebevecFit {
    g: Vec<f64>,
    sd: Vec<f64>,
    ln_e: Vec<f64>,
    /// Unweighted rms residual in ln E over readings with non-zero weight.
    rms: f64,
    /// Number of readings at each value (with non-zero weight).
    coverage: Vec<u32>,
}

/// Data weights per value for [`solve_debevec`]: Debevec's hat to start with, then the
/// inverse of the residuals' robust standard deviation at each value, and readings that
/// are outliers (moving objects, noise spikes) left out.
struct Weights {
    per_value: Vec<f64>,
    keep: Vec<Vec<bool>>,
    /// Variance of a reading's residual at each value (robust, from a previous fit), for
    /// the curve's standard deviations; `None`: one common variance.
    variance: Option<Vec<f64>>,
}

impl Weights {
    /// The readings in use: (sample i, frame j, value z, weight w), w > 0.
    fn readings<'a>(
        &'a self,
        s: &'a Samples,
    ) -> impl Iterator<Item = (usize, usize, usize, f64)> + 'a {
        s.values.iter().enumerate().flat_map(move |(i, vals)| {
            vals.iter().enumerate().filter_map(move |(j, &z)| {
                let w = self.per_value[z as usize];
                (w > 0.0 && self.keep[i][j]).then_some((i, j, z as usize, w))
            })
        })
    }

    fn hat(s: &Samples, max: u32) -> Self {
        Weights {
            per_value: (0..=max).map(|z| hat(z, max)).collect(),
            keep: s.values.iter().map(|v| vec![true; v.len()]).collect(),
            variance: None,
        }
    }

    /// From a fit's residuals: the residuals' robust (MAD) standard deviation sd(z) over
    /// bins of values; readings beyond 5 sd are dropped. The weights stay Debevec's hat:
    /// weights that depend on the observed value (like 1 / sd(z)) bias the curve towards
    /// where the samples are dense (measured: 5% instead of 1.6% on a linear sensor).
    fn from_residuals(s: &Samples, fit: &DebevecFit, ln_t: &[f64], max: u32) -> Self {
        let levels = max as usize + 1;
        let bin = (levels / 32).max(1);
        let nb = levels.div_ceil(bin);
        let mut res: Vec<Vec<f64>> = vec![Vec::new(); nb];
        for (i, vals) in s.values.iter().enumerate() {
            for (j, &z) in vals.iter().enumerate() {
                if z == 0 || z as u32 >= max {
                    continue;
                }
                let r = fit.g[z as usize] - fit.ln_e[i] - ln_t[j];
                res[z as usize / bin].push(r.abs());
            }
        }
        let mut all: Vec<f64> = res.iter().flatten().copied().collect();
        let global = 1.4826 * median(&mut all).max(1e-6);
        let sd_bin: Vec<f64> = res
            .iter_mut()
            .map(|r| {
                if r.len() >= 8 {
                    (1.4826 * median(r)).max(global * 0.05).max(1e-6)
                } else {
                    global
                }
            })
            .collect();
        let sd = |z: usize| sd_bin[z / bin];
        let per_value: Vec<f64> = (0..levels).map(|z| hat(z as u32, max)).collect();
        let keep = s
            .values
            .iter()
            .enumerate()
            .map(|(i, vals)| {
                vals.iter()
                    .enumerate()
                    .map(|(j, &z)| {
                        let z = z as usize;
                        per_value[z] > 0.0
                            && (fit.g[z] - fit.ln_e[i] - ln_t[j]).abs() <= 5.0 * sd(z)
                    })
                    .collect()
            })
            .collect();
        Weights {
            per_value,
            keep,
            variance: Some((0..levels).map(|z| sd(z) * sd(z)).collect()),
        }
    }
}

fn solve_debevec(
    s: &Samples,
    ln_t: &[f64],
    max: u32,
    lambda: f64,
    wts: &Weights,
    with_sd: bool,
) -> Result<DebevecFit, CurveProblem> {
    let levels = max as usize + 1;
    let ns = s.values.len();
    let n = levels + ns;
    let mut m = DMatrix::<f64>::zeros(n, n);
    let mut rhs = DVector::<f64>::zeros(n);
    let mut coverage = vec![0u32; levels];
    let mut rows = 0usize;
    for (i, j, z, w) in wts.readings(s) {
        let ei = levels + i;
        coverage[z] += 1;
        rows += 1;
        let w2 = w * w;
        m[(z, z)] += w2;
        m[(ei, ei)] += w2;
        m[(z, ei)] -= w2;
        m[(ei, z)] -= w2;
        rhs[z] += w2 * ln_t[j];
        rhs[ei] -= w2 * ln_t[j];
    }
    for z in 1..levels - 1 {
        let w = lambda * hat(z as u32, max);
        let idx = [z - 1, z, z + 1];
        let co = [1.0, -2.0, 1.0];
        for a in 0..3 {
            for b in 0..3 {
                m[(idx[a], idx[b])] += w * w * co[a] * co[b];
            }
        }
    }
    // Gauge: g(mid) = 0, as a hard constraint (the unknown is eliminated), so that the
    // standard deviations below are relative to it.
    let mid = levels / 2;
    for k in 0..n {
        m[(mid, k)] = 0.0;
        m[(k, mid)] = 0.0;
    }
    m[(mid, mid)] = 1.0;
    rhs[mid] = 0.0;
    // A sample with no usable reading would leave its unknown free; such samples are not
    // selected, but guard anyway with a tiny ridge.
    for i in 0..ns {
        if m[(levels + i, levels + i)] == 0.0 {
            m[(levels + i, levels + i)] = 1.0;
        }
    }
    let chol = m.clone().cholesky().ok_or(CurveProblem::Singular)?;
    let x = chol.solve(&rhs);
    let g: Vec<f64> = x.iter().take(levels).copied().collect();
    let ln_e: Vec<f64> = x.iter().skip(levels).copied().collect();
    let mut rss_w = 0.0;
    let mut rss = 0.0;
    for (i, j, z, w) in wts.readings(s) {
        let r = g[z] - ln_e[i] - ln_t[j];
        rss_w += w * w * r * r;
        rss += r * r;
    }
    let rms = (rss / rows.max(1) as f64).sqrt();
    let sd = if with_sd {
        // Covariance of the curve (relative to the gauge): the sandwich
        // M^-1 (sum w^2 var(z) a a^T) M^-1 with the readings' variance at their value, or
        // sigma^2 M^-1 with one common variance.
        let mut e = DMatrix::<f64>::zeros(n, levels);
        for z in 0..levels {
            e[(z, z)] = 1.0;
        }
        let inv = chol.solve(&e);
        let var: Vec<f64> = match &wts.variance {
            Some(v) => (0..levels)
                .map(|z| {
                    if z == mid {
                        return 0.0;
                    }
                    wts.readings(s)
                        .map(|(i, _, zz, w)| {
                            let gz = if zz == mid { 0.0 } else { inv[(zz, z)] };
                            let d = gz - inv[(levels + i, z)];
                            w * w * v[zz] * d * d
                        })
                        .sum()
                })
                .collect(),
            None => {
                let dof = rows.saturating_sub(levels + ns).max(1);
                let sigma2 = rss_w / dof as f64;
                (0..levels)
                    .map(|z| if z == mid { 0.0 } else { sigma2 * inv[(z, z)] })
                    .collect()
            }
        };
        var.iter().map(|v| v.max(0.0).sqrt()).collect()
    } else {
        Vec::new()
    };
    Ok(DebevecFit {
        g,
        sd,
        ln_e,
        rms,
        coverage,
    })
}

pub(super) fn debevec_channel(
    s: &Samples,
    ln_t: &[f64],
    max: u32,
    opts: &RecoverOptions,
    name: &str,
    warnings: &mut Vec<String>,
) -> Result<Channel, CurveError> {
    let nf = ln_t.len();
    let levels = max as usize + 1;
    let ns = s.values.len();
    let equations = s
        .values
        .iter()
        .map(|v| {
            v.iter()
                .filter(|z| hat(**z as u32, max) > 0.0)
                .count()
                .saturating_sub(1)
        })
        .sum::<usize>();
    let refuse = |problem| CurveError::Channel {
        channel: name.to_string(),
        problem,
    };
    if equations < levels / 2 {
        return Err(refuse(CurveProblem::TooFewEquations {
            samples: ns,
            exposures: nf,
            equations,
            levels,
        }));
    }
    // Two passes: hat weights; then outliers (beyond 5 robust sd at their value) left out,
    // and the curve's standard deviations from the residuals' spread at each value.
    let wts0 = Weights::hat(s, max);
    // Lambda as in OpenCV (70 samples x 16 exposures), scaled with the number of readings
    // so that data and smoothness keep the same balance whatever the sample count.
    let lambda = opts.lambda * ((ns * nf) as f64 / (70.0 * 16.0)).sqrt();
    let first = solve_debevec(s, ln_t, max, lambda, &wts0, false).map_err(refuse)?;
    let wts = Weights::from_residuals(s, &first, ln_t, max);
    let fit = solve_debevec(s, ln_t, max, lambda, &wts, true).map_err(refuse)?;
    // The values the data determine: observed, and with a small standard deviation,
    // contiguous around the gauge value.
    let mid = levels / 2;
    let good = |z: usize| fit.sd[z] <= opts.max_sd && z > 0 && z < levels - 1;
    let observed_lo = fit.coverage.iter().position(|c| *c > 0).unwrap_or(mid);
    let observed_hi = fit.coverage.iter().rposition(|c| *c > 0).unwrap_or(mid);
    if !good(mid) {
        return Err(refuse(CurveProblem::UndeterminedAtMid { sd: fit.sd[mid] }));
    }
    let mut lo = mid;
    while lo > observed_lo && good(lo - 1) {
        lo -= 1;
    }
    let mut hi = mid;
    while hi < observed_hi && good(hi + 1) {
        hi += 1;
    }
    // Smoothing check: without smoothing, g(z) would sit at the mean of its readings; the
    // mean residual at a value is how far smoothing pulls the curve off its data there.
    // Near the ends of the range (where a curve bends hardest) such values are cut off;
    // elsewhere they are reported.
    let residuals = wts
        .readings(s)
        .map(|(i, j, z, _)| (z, fit.g[z] - fit.ln_e[i] - ln_t[j]));
    let worst;
    (lo, hi, worst) = trim_by_bias(residuals, levels, lo, hi);
    if let Some((z, m)) = worst {
        warnings.push(format!(
            "channel {name}: smoothing pulls the curve {:.1}% off its data at value {z}; lower --lambda",
            100.0 * m.abs()
        ));
    }
    // The very ends: a curve that flattens or turns back next to saturation or black
    // (clipped readings) is cut there.
    let edge = levels / 16;
    while let Some(z) = (hi.saturating_sub(edge).max(lo)..hi)
        .rev()
        .find(|z| fit.g[z + 1] <= fit.g[*z])
    {
        hi = z;
    }
    while let Some(z) = (lo..(lo + edge).min(hi)).find(|z| fit.g[z + 1] <= fit.g[*z]) {
        lo = z + 1;
    }
    // Inside: a dip within the curve's own uncertainty is smoothed out (isotonic
    // regression); a larger one means the data do not determine the curve.
    let mut g = fit.g.clone();
    let mut dips = 0;
    for z in lo..hi {
        if g[z + 1] <= g[z] {
            let drop = g[z] - g[z + 1];
            let sd = fit.sd[z].max(fit.sd[z + 1]);
            if drop > 3.0 * sd {
                return Err(refuse(CurveProblem::Falls {
                    z,
                    next: z + 1,
                    at: g[z],
                    then: g[z + 1],
                }));
            }
            dips += 1;
        }
    }
    if dips > 0 {
        isotonic(&mut g[lo..=hi]);
        rise_strictly(&mut g[lo..=hi]);
        warnings.push(format!(
            "channel {name}: the curve dipped (within its uncertainty) at {dips} values; made monotonic"
        ));
    }
    let span = hi - lo;
    if span < levels / 3 {
        return Err(refuse(CurveProblem::Narrow { lo, hi }));
    }
    // Ambiguity check: where the exposures are far apart (and their ratios equal), the data
    // fix the curve only up to a ripple that repeats with the exposure ratio (Grossberg &
    // Nayar 2003); only the smoothness term removes it. If the curve moves when lambda is
    // tripled or divided by three, the data do not pin it down.
    let mut moved: f64 = 0.0;
    for k in [3.0, 1.0 / 3.0] {
        if let Ok(alt) = solve_debevec(s, ln_t, max, lambda * k, &wts, false) {
            // Over the well-exposed part (the curve's steep dark end always moves).
            let d: Vec<f64> = (lo.max(levels / 8)..=hi)
                .map(|z| alt.g[z] - fit.g[z])
                .collect();
            let (mn, mx) = d.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, x| {
                (a.0.min(*x), a.1.max(*x))
            });
            moved = moved.max(0.5 * (mx - mn));
        }
    }
    if moved > 0.015 {
        warnings.push(format!(
            "channel {name}: the curve changes by {:.1}% when lambda is tripled or divided by three: the exposures do not pin it down (too few, too far apart, or all the same ratio apart); add exposures between them",
            100.0 * moved
        ));
    }
    if lo > observed_lo + levels / 16 || hi + levels / 16 < observed_hi {
        warnings.push(format!(
            "channel {name}: the curve is well determined only for values {lo}..{hi} (observed {observed_lo}..{observed_hi}); other values are treated as too dark or saturated"
        ));
    }
    Ok(Channel::table(g, fit.sd, Vec::new(), (lo, hi), fit.rms, ns))
}

/// Values a bin of the free Debevec curve spans: 1 for 8-bit frames, (max + 1) / 256 above.
pub(super) fn debevec_bin(max: u32) -> usize {
    ((max as usize + 1) / 256).max(1)
}

/// Debevec & Malik's free curve above 8 bits. A table of 65 536 values is not determined by
/// a bracket, so the readings go into 256 bins of values (bin = z / 256, 16-bit) and the free
/// curve is solved on the bins exactly as for 8-bit frames, with the same checks; every value
/// then gets the curve interpolated between the centres of its bins. Within a bin readings
/// differ by up to 256 values, which the solve sees as noise: large at the dark end, where a
/// smooth model explains the readings better and BIC says so.
pub(super) fn debevec_binned(
    s: &Samples,
    ln_t: &[f64],
    max: u32,
    opts: &RecoverOptions,
    name: &str,
    warnings: &mut Vec<String>,
) -> Result<Channel, CurveError> {
    let bin = debevec_bin(max);
    let binned = Samples {
        pixels: s.pixels.clone(),
        values: s
            .values
            .iter()
            .map(|v| v.iter().map(|z| (*z as usize / bin) as u16).collect())
            .collect(),
    };
    let mut w8 = Vec::new();
    let ch = debevec_channel(&binned, ln_t, 255, opts, name, &mut w8).map_err(|e| {
        CurveError::Binned {
            bin,
            source: Box::new(e),
        }
    })?;
    warnings.extend(
        w8.into_iter()
            .map(|w| format!("{w} (values in 256 bins of {bin})")),
    );
    let at = |t: &[f64], z: usize| interp(t, (z as f64 + 0.5) / bin as f64 - 0.5);
    let levels = max as usize + 1;
    let g: Vec<f64> = (0..levels).map(|z| at(&ch.ln_exposure, z)).collect();
    let sd: Vec<f64> = (0..levels).map(|z| at(&ch.ln_exposure_sd, z)).collect();
    let lo = ch.valid_min as usize * bin + bin / 2;
    let hi = (ch.valid_max as usize * bin + bin / 2).min(levels - 2);
    Ok(Channel::table(
        g,
        sd,
        Vec::new(),
        (lo, hi),
        ch.rms_residual,
        ch.samples,
    ))
}
