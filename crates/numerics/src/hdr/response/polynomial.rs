//! The polynomial curve: ln E a polynomial (Chebyshev basis) in ln z, each sample's ln
//! radiance eliminated, the degree chosen by BIC, the dark end and outliers left out.

use nalgebra::{DMatrix, DVector};

use crate::hdr::error::{CurveError, CurveProblem};

use super::basis::{max_degree, poly_basis, poly_range, MAX_DEGREE};
use super::checks::trim_by_bias;
use super::curve::Channel;
use super::samples::{median, Samples};

/// The polynomial fit's weight on a reading at value `z`: Debevec's hat below the middle
/// (where read noise makes a reading's ln E less certain as the value falls), flat above
/// it up to `POLY_TAPER` of the full scale from the top, and falling to zero over that last
/// stretch (where a reading may be clipped). Debevec's hat all the way (squared: 25 at 0.98
/// of full scale against 16 000 in the middle) left a curve's top to the polynomial's whim,
/// and that is where a highlight's flanks are read: degree 10 in ln z, fitted under the hat
/// to 40 noise-free EMoR curves (Grossberg & Nayar's basis, coefficients drawn as the
/// simulated family draws them), missed them by 0.37% (median; 1.2% worst) between 0.93
/// and 0.96 of full scale and 0.6% (2.0%) at 0.97-0.98; under this weight by 0.05% (0.17%)
/// and 0.12% (0.8%), the middle unchanged (0.26%). Flat below the middle too, the fit
/// followed the dark readings' noise (gamma 2.2 with 20 e read noise: valid only from 52).
fn poly_weight(z: u32, max: u32) -> f64 {
    let (z, max) = (z as f64, max as f64);
    let mid = 0.5 * max;
    z.min(mid).min((max - z) * mid / (POLY_TAPER * max))
}

/// See [`poly_weight`].
const POLY_TAPER: f64 = 0.05;

/// Polynomial response for one channel: ln E = sum a_k T_k(u(z)), u linear in ln z. A
/// gamma curve is degree 1; real curves need a few more. With each sample's ln radiance
/// eliminated (readings centred per sample), the least-squares problem has only `k`
/// unknowns. The degree is chosen by BIC, with residuals scaled by their spread at each
/// value; outliers (beyond 5 robust sd) are dropped before the final fit. Few parameters
/// and no smoothing: the ripple that equal exposure ratios leave in a free curve cannot
/// appear.
/// The polynomial fit's least-squares problem for one channel: its sample pixels, the
/// weight of a reading at each value (zero outside [`poly_range`]) and the basis there.
struct PolyFit<'a> {
    s: &'a Samples,
    ln_t: &'a [f64],
    levels: usize,
    hatw: Vec<f64>,
    phi: Vec<[f64; MAX_DEGREE]>,
}

/// Which readings a fit uses: `keep[i][j]` for sample i in frame j.
type Keep = Vec<Vec<bool>>;

/// Residuals of a curve per reading (sample i, frame j); None for a reading not used.
type Residuals = Vec<Vec<Option<f64>>>;

#[allow(clippy::needless_range_loop)] // index-heavy numerics read better with indices
impl<'a> PolyFit<'a> {
    fn new(s: &'a Samples, ln_t: &'a [f64], max: u32) -> Self {
        let levels = max as usize + 1;
        let (floor, ceiling) = poly_range(max);
        let hatw: Vec<f64> = (0..levels)
            .map(|z| {
                if (z as u32) < floor || (z as u32) > ceiling {
                    0.0
                } else {
                    poly_weight(z as u32, max)
                }
            })
            .collect();
        let mut phi = vec![[0.0f64; MAX_DEGREE]; levels];
        for (z, p) in phi.iter_mut().enumerate() {
            poly_basis(z as f64, MAX_DEGREE, max, p);
        }
        PolyFit {
            s,
            ln_t,
            levels,
            hatw,
            phi,
        }
    }

    /// Solve for degree k with the readings `keep` (None: all with hat weight > 0): the
    /// coefficients and the inverse of the normal matrix.
    fn solve(&self, k: usize, keep: Option<&Keep>) -> Option<(Vec<f64>, DMatrix<f64>)> {
        let (s, ln_t, hatw, phi) = (self.s, self.ln_t, &self.hatw, &self.phi);
        let mut m = DMatrix::<f64>::zeros(k, k);
        let mut rhs = DVector::<f64>::zeros(k);
        for (i, vals) in s.values.iter().enumerate() {
            let use_it = |j: usize| {
                let w = hatw[vals[j] as usize];
                w > 0.0 && keep.is_none_or(|kp| kp[i][j])
            };
            let mut sw = 0.0;
            let mut mphi = [0.0; MAX_DEGREE];
            let mut ml = 0.0;
            for j in 0..vals.len() {
                if use_it(j) {
                    let w2 = hatw[vals[j] as usize].powi(2);
                    sw += w2;
                    for a in 0..k {
                        mphi[a] += w2 * phi[vals[j] as usize][a];
                    }
                    ml += w2 * ln_t[j];
                }
            }
            if sw == 0.0 {
                continue;
            }
            for a in 0..k {
                mphi[a] /= sw;
            }
            ml /= sw;
            for j in 0..vals.len() {
                if use_it(j) {
                    let z = vals[j] as usize;
                    let w2 = hatw[z].powi(2);
                    let l = ln_t[j] - ml;
                    for a in 0..k {
                        let pa = phi[z][a] - mphi[a];
                        rhs[a] += w2 * pa * l;
                        for bb in 0..k {
                            m[(a, bb)] += w2 * pa * (phi[z][bb] - mphi[bb]);
                        }
                    }
                }
            }
        }
        let chol = m.clone().cholesky()?;
        let a = chol.solve(&rhs);
        Some((a.iter().copied().collect(), chol.inverse()))
    }

    /// The curve of coefficients `a` at every value.
    fn table(&self, a: &[f64]) -> Vec<f64> {
        let (levels, phi) = (self.levels, &self.phi);
        (0..levels)
            .map(|z| (0..a.len()).map(|j| a[j] * phi[z][j]).sum())
            .collect()
    }

    /// Residuals of a curve: per reading (sample i, frame j) with the sample's ln radiance
    /// at its weighted mean.
    fn residuals(&self, g: &[f64], keep: Option<&Keep>) -> Residuals {
        let (s, ln_t, hatw) = (self.s, self.ln_t, &self.hatw);
        s.values
            .iter()
            .enumerate()
            .map(|(i, vals)| {
                let use_it =
                    |j: usize| hatw[vals[j] as usize] > 0.0 && keep.is_none_or(|kp| kp[i][j]);
                let (mut sw, mut se) = (0.0, 0.0);
                for j in 0..vals.len() {
                    if use_it(j) {
                        let w2 = hatw[vals[j] as usize].powi(2);
                        sw += w2;
                        se += w2 * (g[vals[j] as usize] - ln_t[j]);
                    }
                }
                let e = if sw > 0.0 { se / sw } else { 0.0 };
                (0..vals.len())
                    .map(|j| use_it(j).then(|| g[vals[j] as usize] - ln_t[j] - e))
                    .collect()
            })
            .collect()
    }
}

/// Robust spread of a fit's residuals by value, in bins of 1/32 of the range: the scale
/// for BIC and for outliers.
struct Spread {
    bin: usize,
    /// Readings in each bin.
    counts: Vec<usize>,
    sd_bin: Vec<f64>,
}

impl Spread {
    fn of(s: &Samples, r: &Residuals, levels: usize) -> Self {
        let bin = (levels / 32).max(1);
        let mut by_bin: Vec<Vec<f64>> = vec![Vec::new(); levels.div_ceil(bin)];
        for (vals, rs) in s.values.iter().zip(r) {
            for (z, r) in vals.iter().zip(rs) {
                if let Some(r) = r {
                    by_bin[*z as usize / bin].push(r.abs());
                }
            }
        }
        let mut all: Vec<f64> = by_bin.iter().flatten().copied().collect();
        let global = (1.4826 * median(&mut all)).max(1e-6);
        let sd_bin: Vec<f64> = by_bin
            .iter_mut()
            .map(|v| {
                if v.len() >= 8 {
                    (1.4826 * median(v)).max(0.05 * global).max(1e-6)
                } else {
                    global
                }
            })
            .collect();
        Spread {
            bin,
            counts: by_bin.iter().map(Vec::len).collect(),
            sd_bin,
        }
    }

    fn sd(&self, z: u16) -> f64 {
        self.sd_bin[z as usize / self.bin]
    }
}

/// The readings the final fits use: those of the richest fit (residuals `r_max`) within 5
/// robust sd of it, above the dark end.
// The dark end: readings whose scatter in ln E exceeds 10% are left out. There read
// noise, dark current and the clipping of negative charge at zero bias them, and a
// global polynomial bent to follow them ripples across the whole range: on the
// simulated gamma-2.2 camera, degree 10 and a -0.35%..+0.7% ripple with the values
// below 16, degree 1 and 0.001% without (which moved a broad lobe's fitted ks/kd by
// 5-10%). A linear sensor's readings are precise much lower, and keep their values
// down to 4 or so: a fixed cut at 16 left them too short a range and a 6% ripple.
// The cut never rises above an eighth of the range (a noisy channel, like the
// Memorial bracket's blue, keeps its middle).
fn kept_readings(s: &Samples, r_max: &Residuals, spread: &Spread, levels: usize, max: u32) -> Keep {
    let (floor, _) = poly_range(max);
    let (bin, sd_bin) = (spread.bin, &spread.sd_bin);
    let sd = |z: u16| spread.sd(z);
    let mid_bin = (levels / 2) / bin;
    let mut low_bin = mid_bin;
    while low_bin > 0 && spread.counts[low_bin - 1] >= 8 && sd_bin[low_bin - 1] <= 0.1 {
        low_bin -= 1;
    }
    let low = ((low_bin * bin) as u32).clamp(floor, max.div_ceil(8));
    s.values
        .iter()
        .zip(r_max)
        .map(|(vals, rs)| {
            vals.iter()
                .zip(rs)
                .map(|(z, r)| (*z as u32) >= low && r.is_some_and(|r| r.abs() <= 5.0 * sd(*z)))
                .collect()
        })
        .collect()
}

/// Degree by BIC on the kept readings, residuals in units of their spread: the degree, its
/// coefficients and the inverse of its normal matrix (None: singular at every degree).
fn choose_degree(
    fit: &PolyFit,
    keep: &Keep,
    spread: &Spread,
    top_degree: usize,
) -> Option<(usize, Vec<f64>, DMatrix<f64>)> {
    let s = fit.s;
    let sd = |z: u16| spread.sd(z);
    let n_obs: usize = keep.iter().flatten().filter(|k| **k).count();
    let mut best: Option<(usize, f64, Vec<f64>, DMatrix<f64>)> = None;
    for k in 1..=top_degree {
        let Some((a, inv)) = fit.solve(k, Some(keep)) else {
            continue;
        };
        let g = fit.table(&a);
        // A curve that does not increase over a third of the values around the middle is
        // no response (valid_range refuses it): a degree that bends so is passed over for
        // one that does not, rather than the whole model failing on it. (Seen on 2-stop
        // brackets of three exposures, where BIC's best degree fell between two values in
        // the middle and the camera was then merged as linear, 13% off.)
        if !increases_around_middle(&g) {
            continue;
        }
        let r = fit.residuals(&g, Some(keep));
        let chi2: f64 = s
            .values
            .iter()
            .zip(&r)
            .flat_map(|(vals, rs)| vals.iter().zip(rs))
            .filter_map(|(z, r)| r.map(|r| (r / sd(*z)).powi(2)))
            .sum();
        let bic = chi2 + k as f64 * (n_obs.max(1) as f64).ln();
        if best.as_ref().is_none_or(|b| bic < b.1) {
            best = Some((k, bic, a, inv));
        }
    }
    best.map(|(k, _, a, inv)| (k, a, inv))
}

/// The values around the middle over which `g` increases, in one run, within
/// `bottom..=top`.
fn increasing_run(g: &[f64], bottom: usize, top: usize) -> (usize, usize) {
    let mid = g.len() / 2;
    let (mut lo, mut hi) = (mid, mid);
    while lo > bottom && g[lo - 1] < g[lo] {
        lo -= 1;
    }
    while hi < top && g[hi + 1] > g[hi] {
        hi += 1;
    }
    (lo, hi)
}

/// Whether `g` increases over at least a third of its values around the middle: the first
/// test of [`valid_range`], over every value the curve may be valid for (1..=levels - 2)
/// rather than the readings' own range.
fn increases_around_middle(g: &[f64]) -> bool {
    let (lo, hi) = increasing_run(g, 1, g.len() - 2);
    hi - lo >= g.len() / 3
}

/// The fitted curve's standard deviation at every value, sigma^2 phi^T (Phi^T W Phi)^-1 phi
/// with sigma^2 from the weighted residuals, and the sums the channel keeps.
struct CurveSd {
    sigma2: f64,
    sd_g: Vec<f64>,
    /// Readings used at each value.
    coverage: Vec<u32>,
    rss: f64,
    wsum: f64,
}

impl CurveSd {
    #[allow(clippy::needless_range_loop)] // index-heavy numerics read better with indices
    fn of(fit: &PolyFit, r: &Residuals, k: usize, inv: &DMatrix<f64>) -> Self {
        let (s, hatw, phi, levels) = (fit.s, &fit.hatw, &fit.phi, fit.levels);
        let (mut rss_w, mut rows, mut rss, mut wsum) = (0.0, 0usize, 0.0, 0.0);
        let mut coverage = vec![0u32; levels];
        for (vals, rs) in s.values.iter().zip(r) {
            for (z, r) in vals.iter().zip(rs) {
                if let Some(r) = r {
                    let w2 = hatw[*z as usize].powi(2);
                    rss_w += w2 * r * r;
                    rss += w2 * r * r;
                    wsum += w2;
                    rows += 1;
                    coverage[*z as usize] += 1;
                }
            }
        }
        let sigma2 = rss_w / (rows.saturating_sub(k + s.values.len())).max(1) as f64;
        let sd_g: Vec<f64> = (0..levels)
            .map(|z| {
                let p = &phi[z][..k];
                let mut v = 0.0;
                for i in 0..k {
                    for j in 0..k {
                        v += p[i] * inv[(i, j)] * p[j];
                    }
                }
                (sigma2 * v.max(0.0)).sqrt()
            })
            .collect();
        CurveSd {
            sigma2,
            sd_g,
            coverage,
            rss,
            wsum,
        }
    }
}

/// The values the curve `g` is valid for: observed, increasing, contiguous around the
/// middle, less the ends where it misses its data; warnings for a curve that misses or is
/// uncertain inside them, or is valid for too short a range. Returns the fitted range and
/// the valid one: where the fitted range reaches the samples' top, the curve continues
/// (straight in ln z, [`extend_outside`]) to the format's top and is valid there too,
/// with a warning. Sampling leaves out readings beside clipped pixels (a demosaicked
/// camera's are wrong there) and readings seen at one exposure only, so the samples'
/// top can end well below the clip (a 2-stop bracket of an 8-bit camera: 188 of 255)
/// while a bright tile is read above it at its shortest exposure; without the
/// continuation it would have no radiance at all.
fn valid_range(
    g: &[f64],
    sd: &CurveSd,
    s: &Samples,
    r: &Residuals,
    levels: usize,
    name: &str,
    warnings: &mut Vec<String>,
) -> Result<(usize, usize, usize), CurveError> {
    let coverage = &sd.coverage;
    // Valid: observed, increasing, contiguous around the middle.
    let mid = levels / 2;
    let lo_obs = coverage.iter().position(|c| *c > 0).unwrap_or(mid).max(1);
    let hi_obs = coverage
        .iter()
        .rposition(|c| *c > 0)
        .unwrap_or(mid)
        .min(levels - 2);
    let (mut lo, mut hi) = increasing_run(g, lo_obs, hi_obs);
    if hi - lo < levels / 3 {
        return Err(CurveError::Channel {
            channel: name.to_string(),
            problem: CurveProblem::NotIncreasing { lo, hi },
        });
    }
    // Misfit: the mean residual at a value is how far the curve misses its data there.
    // Near the ends of the range such values are cut off; elsewhere they are reported.
    let residuals = s.values.iter().zip(r).flat_map(|(vals, rs)| {
        vals.iter()
            .zip(rs)
            .filter_map(|(z, r)| r.map(|r| (*z as usize, r)))
    });
    let worst;
    (lo, hi, worst) = trim_by_bias(residuals, levels, lo, hi);
    if let Some((z, m)) = worst.filter(|(_, m)| m.abs() > 0.02) {
        warnings.push(format!(
            "channel {name}: the polynomial curve misses its data by {:.1}% at value {z}; try --model debevec",
            100.0 * m.abs()
        ));
    }
    // Uncertainty: where the data leave the curve unsure by more than 1.5% in the
    // well-exposed range (values 32..224 of 255).
    if let Some((z, sd)) = (lo.max(levels / 8)..=hi.min(levels * 7 / 8))
        .map(|z| (z, sd.sd_g[z]))
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .filter(|(_, sd)| *sd > 0.015)
    {
        warnings.push(format!(
            "channel {name}: the curve is uncertain by {:.1}% (one standard deviation) at value {z}; add exposures or sample pixels, or reduce the noise",
            100.0 * sd
        ));
    }
    let top = if hi == hi_obs && hi < levels - 2 {
        if hi < levels * 15 / 16 {
            warnings.push(format!(
                "channel {name}: no sample pixel reads above {hi} in two exposures (beside clipped pixels, or in the shortest only), so the curve is continued straight in ln z from there up: radiance read there is extrapolated; add an exposure one stop shorter than the shortest"
            ));
        }
        levels - 2
    } else {
        hi
    };
    if lo > levels / 8 || top < levels * 27 / 32 {
        warnings.push(format!(
            "channel {name}: the polynomial curve is usable only for values {lo}..{top} (observed {lo_obs}..{hi_obs}); other values are treated as too dark or saturated"
        ));
    }
    Ok((lo, hi, top))
}

/// Continue a curve outside its valid range `lo..=hi` as a straight line in ln z.
#[allow(clippy::needless_range_loop)] // index-heavy numerics read better with indices
fn extend_outside(g: &mut [f64], lo: usize, hi: usize, levels: usize) {
    // Outside the valid range a high-degree polynomial runs wild: continue the curve as a
    // straight line in ln z from each end instead (the values there carry no radiance,
    // but the table stays monotonic for plots and the inverse response).
    let lnz = |z: usize| (z as f64).max(0.5).ln();
    let s_lo = (g[lo + 1] - g[lo]) / (lnz(lo + 1) - lnz(lo));
    for z in 0..lo {
        g[z] = g[lo] + s_lo * (lnz(z) - lnz(lo));
    }
    let s_hi = (g[hi] - g[hi - 1]) / (lnz(hi) - lnz(hi - 1));
    for z in hi + 1..levels {
        g[z] = g[hi] + s_hi * (lnz(z) - lnz(hi));
    }
}

/// Polynomial response for one channel: ln E = sum a_k T_k(u(z)), u linear in ln z. A
/// gamma curve is degree 1; real curves need a few more. With each sample's ln radiance
/// eliminated (readings centred per sample), the least-squares problem has only `k`
/// unknowns. The degree is chosen by BIC, with residuals scaled by their spread at each
/// value; outliers (beyond 5 robust sd) are dropped before the final fit. Few parameters
/// and no smoothing: the ripple that equal exposure ratios leave in a free curve cannot
/// appear.
pub(super) fn fit_polynomial(
    s: &Samples,
    ln_t: &[f64],
    step: Option<f64>,
    max: u32,
    name: &str,
    warnings: &mut Vec<String>,
) -> Result<Channel, CurveError> {
    let refuse = |problem| CurveError::Channel {
        channel: name.to_string(),
        problem,
    };
    let levels = max as usize + 1;
    // Readings in the lowest 1/64 of the range are never fitted; those above, up to where
    // the readings' scatter in ln E falls below 10%, are left out after the first pass (see
    // [`kept_readings`]).
    let fit = PolyFit::new(s, ln_t, max);
    // Robust spread of the residuals by value (bins of 1/32 of the range), from the
    // richest model: the scale for BIC and for outliers.
    let top_degree = max_degree(max, step);
    let (a_max, _) = (1..=top_degree)
        .rev()
        .find_map(|k| fit.solve(k, None))
        .ok_or_else(|| refuse(CurveProblem::PolynomialSingular))?;
    let r_max = fit.residuals(&fit.table(&a_max), None);
    let spread = Spread::of(s, &r_max, levels);
    let keep = kept_readings(s, &r_max, &spread, levels, max);
    let (k, a, inv) = choose_degree(&fit, &keep, &spread, top_degree)
        .ok_or_else(|| refuse(CurveProblem::PolynomialSingular))?;
    let mut g = fit.table(&a);
    // Standard deviation of g(z): sigma^2 phi^T (Phi^T W Phi)^-1 phi, sigma^2 from the
    // weighted residuals.
    let r = fit.residuals(&g, Some(&keep));
    let sd = CurveSd::of(&fit, &r, k, &inv);
    let (lo, hi, top) = valid_range(&g, &sd, s, &r, levels, name, warnings)?;
    extend_outside(&mut g, lo, hi, levels);
    let rms = (sd.rss / sd.wsum.max(1e-300)).sqrt();
    let sigma2 = sd.sigma2;
    let mut ch = Channel::table(g, sd.sd_g, a, (lo, top), rms, s.values.len());
    ch.coefficient_covariance = (0..k)
        .map(|i| (0..k).map(|j| sigma2 * inv[(i, j)]).collect())
        .collect();
    Ok(ch)
}
