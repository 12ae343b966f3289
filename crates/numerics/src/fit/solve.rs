//! The fitter: no start values. For a fixed exponent n every model is linear in kd and ks,
//! so they are solved in closed form (non-negative least squares, each channel) and only n
//! is searched: a log-spaced scan, then golden-section refinement of ln n (variable
//! projection); then a joint Levenberg-Marquardt polish in (kd, ks, ln n) with the analytic
//! Jacobian, whose Jacobian gives the covariance.
//!
//! Samples are RGB, or monochrome ([`Options::channels`] = 1): then channel 0 holds the
//! radiance and the parameters are one kd, one ks and n. Channels 1 and 2 carry neither
//! data nor parameters (their weights are zero, their kd and ks held at 0, and neither
//! counts in the degrees of freedom): one reading is one value, never three.

#![allow(clippy::needless_range_loop)] // per-channel numerics read better with indices

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

use super::model::{diffuse, Geometry, Model, Reflectance};

/// One sample: its geometry, radiance per channel, and the radiance's variance (from the
/// HDR stage; weights are 1 / variance). A monochrome sample uses channel 0 only.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Sample {
    pub geometry: Geometry,
    pub radiance: [f64; 3],
    pub variance: [f64; 3],
    /// Channels that saturated: `radiance` is a lower bound there, and a model predicting
    /// at least that much fits it exactly.
    #[serde(default)]
    pub censored: [bool; 3],
}

impl Sample {
    /// A measured sample (nothing censored).
    pub fn new(geometry: Geometry, radiance: [f64; 3], variance: [f64; 3]) -> Self {
        Sample {
            geometry,
            radiance,
            variance,
            censored: [false; 3],
        }
    }
}

/// Start values for plain Levenberg-Marquardt (the paper's way): kd and ks (grey) and n.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Start {
    pub kd: f64,
    pub ks: f64,
    pub n: f64,
}

/// Search range and effort.
#[derive(Debug, Clone, Copy)]
pub struct Options {
    /// Exponents searched, n_min..n_max (log-spaced).
    pub n_min: f64,
    pub n_max: f64,
    /// Points of the coarse scan.
    pub scan: usize,
    /// The variances are the radiance's true variances (from the HDR stage): the
    /// covariance is (J^T J)^-1. Otherwise it is scaled by the residuals' variance.
    pub variances_known: bool,
    /// One ks for all three channels (dielectric highlights are white).
    pub grey_ks: bool,
    /// Channels of the samples: 3 (RGB), or 1 (a monochrome camera: channel 0 only).
    pub channels: usize,
    /// Huber loss with this threshold (in standard deviations) against surface flaws;
    /// None: least squares.
    pub huber: Option<f64>,
    /// Skip the search and run plain Levenberg-Marquardt from these start values (for
    /// comparison with the paper's method; the default needs none).
    pub start: Option<Start>,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            n_min: 1.0,
            n_max: 1.0e4,
            scan: 16,
            variances_known: true,
            grey_ks: false,
            channels: 3,
            huber: None,
            start: None,
        }
    }
}

/// Why the fit's polish stopped: the fit file's type (glint-format), so that `fit/fit.json`
/// carries it as the solver gives it.
pub use glint_format::stage::fit::Termination;

/// Most iterations of the polish.
pub const MAX_POLISH_ITERATIONS: usize = 100;

/// A fitted parameter.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    pub value: f64,
    /// Standard error.
    pub sd: f64,
}

impl Estimate {
    /// The 95% interval (normal approximation; for n it is computed on ln n).
    pub fn ci95(&self) -> [f64; 2] {
        [self.value - 1.96 * self.sd, self.value + 1.96 * self.sd]
    }
}

/// One model's fit (`M`: the built-in [`Model`]s, or any [`Reflectance`]).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ModelFit<M = Model> {
    pub model: M,
    pub kd: [Estimate; 3],
    /// Zero (and sd 0) for Lambert.
    pub ks: [Estimate; 3],
    /// The shared exponent (NaN for Lambert); `n_ci95` is its 95% interval from ln n.
    pub n: Estimate,
    pub n_ci95: [f64; 2],
    /// Weighted sum of squared residuals.
    pub chi2: f64,
    /// Residual degrees of freedom.
    pub dof: usize,
    /// Parameters of the model: kd per channel, and a lobe's ks (per channel, or one grey)
    /// and n; 3, 5 or 7 (RGB), 1 or 3 (monochrome).
    pub parameters: usize,
    /// Correlation of ks (strongest channel) with ln n (NaN for Lambert).
    pub ks_n_correlation: f64,
    /// The same from the fit's own covariance, before [`ModelFit::add_covariance`] adds
    /// the calibration's and the response's: whether the samples separate the lobe's
    /// height from its width (the uncertainty added later, little correlated, lowers the
    /// total's; a demosaicked Ward tile's GGX fit had −0.99 of its own and −0.76 in all).
    #[serde(default = "nan")]
    pub own_ks_n_correlation: f64,
    /// ks / kd per channel with its standard error (correlation included); NaN for Lambert,
    /// infinite where kd is 0 and ks is not.
    pub ratio: [Estimate; 3],
    /// 95% interval of ks / kd per channel by Fieller's theorem (the ratio of two
    /// correlated normal estimates): honest where kd is near or at 0, where it is open
    /// above (the upper end infinite).
    #[serde(default = "nan_pairs")]
    pub ratio_ci95: [[f64; 2]; 3],
    /// The fit's own 95% interval of ln n from the profile likelihood, as distances below
    /// and above the fitted ln n (None without a lobe). `n_ci95` widens it by the variance
    /// added later (calibration, response).
    #[serde(default)]
    pub n_profile95: Option<[f64; 2]>,
    /// ks / kd per channel along the profile of n: its least and largest value where chi2,
    /// minimised over kd and ks at each n, is within the 95% rise (at the ends of n's
    /// profile interval and at the optimum). Where n is loosely determined ks / kd moves
    /// with it along a curved valley that the covariance's straight line misses (a broad
    /// lobe whose height trades with its width); `ratio_ci95` spans this range too.
    #[serde(default)]
    pub ratio_trace95: Option<[[f64; 2]; 3]>,
    /// Variance of ln n added to the fit's own by [`ModelFit::add_covariance`].
    #[serde(default)]
    pub n_added_variance: f64,
    /// Covariance of (kd_r, kd_g, kd_b, ks_r, ks_g, ks_b, ln n); zero rows for parameters
    /// held (at a bound, or absent from the model).
    pub covariance: Vec<Vec<f64>>,
    /// Evaluations of the closed-form inner solve (scan and refinement).
    pub inner_evaluations: usize,
    /// Levenberg-Marquardt evaluations in the polish.
    pub polish_evaluations: usize,
    /// Why the polish stopped (the last polish, where a robust loss re-weights and
    /// polishes again): converged, or not (see [`Termination::was_successful`]).
    #[serde(default)]
    pub polish_termination: Termination,
    pub warnings: Vec<String>,
    /// Channels fitted: 3 (RGB) or 1 (monochrome: kd[0], ks[0] only; the others are 0
    /// with no uncertainty, and not parameters).
    #[serde(default = "three")]
    pub channels: usize,
}

fn three() -> usize {
    3
}

fn nan() -> f64 {
    f64::NAN
}

fn nan_pairs() -> [[f64; 2]; 3] {
    [[f64::NAN; 2]; 3]
}

/// Delta chi-square of the 95% interval of one parameter (chi-square, 1 degree of freedom).
pub const DELTA_CHI2_95: f64 = 3.841_458_820_694_124;

/// Weighted sums of one channel for the 2x2 normal equations.
#[derive(Default, Clone, Copy)]
struct Sums {
    aa: f64,
    ab: f64,
    bb: f64,
    al: f64,
    bl: f64,
    ll: f64,
}

pub(crate) fn weights(s: &Sample) -> [f64; 3] {
    s.variance.map(|v| {
        if v.is_finite() && v > 0.0 {
            1.0 / v
        } else {
            0.0
        }
    })
}

/// Non-negative least squares for (kd, ks) from the sums: the solution and its cost.
fn nnls2(s: &Sums) -> ([f64; 2], f64) {
    let cost = |kd: f64, ks: f64| {
        s.ll - 2.0 * (kd * s.al + ks * s.bl)
            + kd * kd * s.aa
            + 2.0 * kd * ks * s.ab
            + ks * ks * s.bb
    };
    let det = s.aa * s.bb - s.ab * s.ab;
    if det > 1e-14 * s.aa * s.bb {
        let kd = (s.bb * s.al - s.ab * s.bl) / det;
        let ks = (s.aa * s.bl - s.ab * s.al) / det;
        if kd >= 0.0 && ks >= 0.0 {
            return ([kd, ks], cost(kd, ks));
        }
    }
    let mut best = ([0.0, 0.0], cost(0.0, 0.0));
    if s.aa > 0.0 {
        let kd = (s.al / s.aa).max(0.0);
        let c = cost(kd, 0.0);
        if c < best.1 {
            best = ([kd, 0.0], c);
        }
    }
    if s.bb > 0.0 {
        let ks = (s.bl / s.bb).max(0.0);
        let c = cost(0.0, ks);
        if c < best.1 {
            best = ([0.0, ks], c);
        }
    }
    best
}

/// Non-negative least squares for (kd_r, kd_g, kd_b, ks) with one ks for the three
/// channels: every face of the constraint set (each kd free or at 0, ks free or at 0) is
/// solved in closed form and the best feasible one kept.
fn grey_nnls(s: &[Sums; 3]) -> ([[f64; 2]; 3], f64) {
    let cost = |kd: [f64; 3], ks: f64| {
        (0..3)
            .map(|c| {
                let s = &s[c];
                s.ll - 2.0 * (kd[c] * s.al + ks * s.bl)
                    + kd[c] * kd[c] * s.aa
                    + 2.0 * kd[c] * ks * s.ab
                    + ks * ks * s.bb
            })
            .sum::<f64>()
    };
    // ks at 0: the channels separate.
    let kd0 = [0, 1, 2].map(|c| {
        if s[c].aa > 0.0 {
            (s[c].al / s[c].aa).max(0.0)
        } else {
            0.0
        }
    });
    let mut best = (kd0, 0.0, cost(kd0, 0.0));
    for free in 0..8u8 {
        let mut num = 0.0;
        let mut den = 0.0;
        for c in 0..3 {
            num += s[c].bl;
            den += s[c].bb;
            if free & (1 << c) != 0 && s[c].aa > 0.0 {
                num -= s[c].ab * s[c].al / s[c].aa;
                den -= s[c].ab * s[c].ab / s[c].aa;
            }
        }
        if den <= 0.0 {
            continue;
        }
        let ks = num / den;
        if ks < 0.0 {
            continue;
        }
        let mut kd = [0.0; 3];
        let mut ok = true;
        for c in 0..3 {
            if free & (1 << c) != 0 && s[c].aa > 0.0 {
                kd[c] = (s[c].al - s[c].ab * ks) / s[c].aa;
                ok &= kd[c] >= 0.0;
            }
        }
        if ok {
            let c = cost(kd, ks);
            if c < best.2 {
                best = (kd, ks, c);
            }
        }
    }
    let (kd, ks, c) = best;
    ([0, 1, 2].map(|i| [kd[i], ks]), c.max(0.0))
}

/// Per-sample quantities that do not depend on n, computed once per fit: for a power lobe
/// the inner solve then costs one exp per sample; other lobes are evaluated through their
/// [`Reflectance::specular`].
struct Prepared<'a> {
    /// A lobe that is not a power of a cosine, with the samples' geometry.
    general: Option<(&'a dyn Reflectance, Vec<Geometry>)>,
    /// Diffuse basis a.
    a: Vec<f64>,
    /// ln of the lobe's cosine (r.v or n.h); -inf where it is 0.
    ln_x: Vec<f64>,
    /// The lobe's factor: b = factor x^n (times n + 2 for the cosine lobe).
    factor: Vec<f64>,
    /// Weights in use (the Huber loss scales them down for outliers) and as given.
    w: Vec<[f64; 3]>,
    w0: Vec<[f64; 3]>,
    l: Vec<[f64; 3]>,
    cens: Vec<[bool; 3]>,
    /// Some value is censored: the profile over n then re-solves the linear parameters
    /// by the polish (the closed form leaves censored values out).
    any_censored: bool,
    /// Sum of w l^2 per channel over the measured (not censored) values.
    ll: [f64; 3],
    cosine_lobe: bool,
    /// ks shared by the channels: it lives in p[3].
    grey: bool,
}

impl<'a> Prepared<'a> {
    /// The samples' channels beyond `channels` (a monochrome fit's 1 and 2) weigh nothing.
    fn new(model: &'a dyn Reflectance, samples: &[Sample], grey: bool, channels: usize) -> Self {
        let power: Option<Vec<_>> = samples
            .iter()
            .map(|s| model.power_lobe(&s.geometry))
            .collect();
        let mut p = Prepared {
            general: match (&power, model.has_lobe()) {
                (None, true) => Some((model, samples.iter().map(|s| s.geometry).collect())),
                _ => None,
            },
            a: Vec::with_capacity(samples.len()),
            ln_x: Vec::with_capacity(samples.len()),
            factor: Vec::with_capacity(samples.len()),
            w: Vec::with_capacity(samples.len()),
            w0: Vec::new(),
            l: Vec::with_capacity(samples.len()),
            cens: Vec::with_capacity(samples.len()),
            any_censored: false,
            ll: [0.0; 3],
            cosine_lobe: power
                .as_ref()
                .and_then(|v| v.first())
                .is_some_and(|l| l.n_plus_two),
            grey,
        };
        for (i, s) in samples.iter().enumerate() {
            p.a.push(diffuse(&s.geometry));
            let (x, f) = match (&power, model.has_lobe()) {
                (Some(v), true) => (v[i].x, v[i].factor),
                _ => (0.0, 0.0),
            };
            p.ln_x
                .push(if x > 0.0 { x.ln() } else { f64::NEG_INFINITY });
            p.factor.push(f);
            let mut w = weights(s);
            let mut l = s.radiance;
            let mut cens = s.censored;
            for c in channels..3 {
                (w[c], l[c], cens[c]) = (0.0, 0.0, false);
            }
            p.w.push(w);
            p.l.push(l);
            p.cens.push(cens);
        }
        p.w0 = p.w.clone();
        p.any_censored = p.cens.iter().flatten().any(|c| *c);
        p.sum_ll();
        p
    }

    fn sum_ll(&mut self) {
        self.ll = [0.0; 3];
        for i in 0..self.a.len() {
            for c in 0..3 {
                if !self.cens[i][c] {
                    self.ll[c] += self.w[i][c] * self.l[i][c] * self.l[i][c];
                }
            }
        }
    }

    /// Where ks of channel c lives in p.
    #[inline]
    fn ks_index(&self, c: usize) -> usize {
        if self.grey {
            3
        } else {
            3 + c
        }
    }

    /// Huber weights at p: each value's weight is scaled by min(1, k / |z|), z its
    /// standardised residual. Returns the largest change of a scale factor.
    fn reweight(&mut self, p: &[f64; 7], k: f64) -> f64 {
        let n = p[6].exp();
        let mut change = 0.0f64;
        for i in 0..self.a.len() {
            let (b, _) = self.lobe(i, n);
            for c in 0..3 {
                let w0 = self.w0[i][c];
                if w0 == 0.0 {
                    continue;
                }
                let r = p[c] * self.a[i] + p[self.ks_index(c)] * b - self.l[i][c];
                let z = (w0.sqrt() * r).abs();
                let q = if z <= k { 1.0 } else { k / z };
                change = change.max((q - self.w[i][c] / w0).abs());
                self.w[i][c] = w0 * q;
            }
        }
        self.sum_ll();
        change
    }

    /// The closed-form inner solve at exponent n: (kd, ks) per channel and the cost.
    fn inner(&self, n: f64) -> ([[f64; 2]; 3], f64) {
        let mut sums = [Sums::default(); 3];
        let lobe = if self.cosine_lobe { n + 2.0 } else { 1.0 };
        let general = self.general.is_some();
        for i in 0..self.a.len() {
            let a = self.a[i];
            let b = if general {
                self.lobe(i, n).0
            } else {
                self.factor[i] * lobe * (n * self.ln_x[i]).exp()
            };
            let (w, l) = (&self.w[i], &self.l[i]);
            for c in 0..3 {
                // Censored values take no part in the closed-form solve.
                let wc = if self.cens[i][c] { 0.0 } else { w[c] };
                let wa = wc * a;
                let wb = wc * b;
                let sc = &mut sums[c];
                sc.aa += wa * a;
                sc.ab += wa * b;
                sc.bb += wb * b;
                sc.al += wa * l[c];
                sc.bl += wb * l[c];
            }
        }
        for c in 0..3 {
            sums[c].ll = self.ll[c];
        }
        if self.grey {
            return grey_nnls(&sums);
        }
        let mut k = [[0.0; 2]; 3];
        let mut cost = 0.0;
        for c in 0..3 {
            let (kc, cc) = nnls2(&sums[c]);
            k[c] = kc;
            cost += cc;
        }
        (k, cost.max(0.0))
    }
}

/// What the polish ends with: the parameters, their cost (chi2), the cost evaluations
/// used, and why it stopped.
struct Polished {
    p: [f64; 7],
    cost: f64,
    evaluations: usize,
    termination: Termination,
}

/// The joint polish in p = (kd[3], ks[3], ln n): Levenberg-Marquardt on the 7x7 normal
/// equations, accumulated sample by sample. Written here rather than with the
/// levenberg-marquardt crate (used for calibration): the crate factors the full
/// 3N x 7 Jacobian by QR every iteration, which took 40% of the fit's time at 800 samples,
/// while the normal equations of seven parameters cost almost nothing.
impl Prepared<'_> {
    /// The lobe's basis b and d b / d ln n at sample i.
    #[inline]
    fn lobe(&self, i: usize, n: f64) -> (f64, f64) {
        if let Some((m, g)) = &self.general {
            return m.specular(&g[i], n);
        }
        let xn = (n * self.ln_x[i]).exp();
        if xn == 0.0 {
            return (0.0, 0.0);
        }
        let f = self.factor[i];
        if self.cosine_lobe {
            // ((n + 2) x^n)' by ln n = n x^n + (n + 2) n x^n ln x.
            (
                f * (n + 2.0) * xn,
                f * n * xn * (1.0 + (n + 2.0) * self.ln_x[i]),
            )
        } else {
            (f * xn, f * n * xn * self.ln_x[i])
        }
    }

    /// Weighted residual of sample i, channel c, and its derivatives by the seven
    /// parameters (only kd_c, ks_c and ln n are non-zero).
    #[inline]
    fn residual(&self, i: usize, c: usize, p: &[f64; 7]) -> (f64, [f64; 3]) {
        let (b, db) = self.lobe(i, p[6].exp());
        let sw = self.w[i][c].sqrt();
        let a = self.a[i];
        let k = self.ks_index(c);
        let r = p[c] * a + p[k] * b - self.l[i][c];
        if self.cens[i][c] && r >= 0.0 {
            return (0.0, [0.0; 3]);
        }
        (sw * r, [sw * a, sw * b, sw * p[k] * db])
    }

    /// Cost, J^T J and J^T r over the free parameters.
    fn normal(&self, p: &[f64; 7], free: &[usize]) -> (f64, DMatrix<f64>, DVector<f64>) {
        let k = free.len();
        let mut full_jtj = [[0.0; 7]; 7];
        let mut full_jtr = [0.0; 7];
        let mut cost = 0.0;
        let lobe = p[3..6].iter().any(|v| *v != 0.0) || free.contains(&6);
        let n = p[6].exp();
        for i in 0..self.a.len() {
            let (b, db) = if lobe { self.lobe(i, n) } else { (0.0, 0.0) };
            let a = self.a[i];
            for c in 0..3 {
                let w = self.w[i][c];
                let k = self.ks_index(c);
                let r = p[c] * a + p[k] * b - self.l[i][c];
                // A censored value is fitted once the model reaches its bound.
                if self.cens[i][c] && r >= 0.0 {
                    continue;
                }
                cost += w * r * r;
                let d = [a, b, p[k] * db];
                let idx = [c, k, 6];
                for u in 0..3 {
                    full_jtr[idx[u]] += w * d[u] * r;
                    for v in 0..3 {
                        full_jtj[idx[u]][idx[v]] += w * d[u] * d[v];
                    }
                }
            }
        }
        let jtj = DMatrix::from_fn(k, k, |u, v| full_jtj[free[u]][free[v]]);
        let jtr = DVector::from_fn(k, |u, _| full_jtr[free[u]]);
        (cost, jtj, jtr)
    }

    /// Levenberg-Marquardt from p: the optimum, its cost, the number of cost evaluations
    /// and why it stopped.
    fn polish(&self, mut p: [f64; 7], free: &[usize]) -> Polished {
        let (mut cost, mut jtj, mut jtr) = self.normal(&p, free);
        let mut evals = 1;
        let mut lambda = 1e-3;
        let mut termination = Termination::LostPatience;
        for _ in 0..MAX_POLISH_ITERATIONS {
            let mut m = jtj.clone();
            for u in 0..free.len() {
                m[(u, u)] += lambda * jtj[(u, u)].max(1e-300);
            }
            let Some(ch) = m.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let step = ch.solve(&(-&jtr));
            let mut q = p;
            for (u, &f) in free.iter().enumerate() {
                q[f] += step[u];
            }
            // Stay at or above zero: a parameter pushed below is held at zero next round.
            for v in q.iter_mut().take(6) {
                *v = v.max(0.0);
            }
            let (c2, j2, r2) = self.normal(&q, free);
            evals += 1;
            if c2 <= cost {
                let done = cost - c2 <= 1e-15 * cost.max(1e-300)
                    || step.amax() <= 1e-12 * (1.0 + p.iter().fold(0.0f64, |a, v| a.max(v.abs())));
                p = q;
                cost = c2;
                jtj = j2;
                jtr = r2;
                lambda = (lambda / 10.0).max(1e-12);
                if done {
                    termination = Termination::Converged;
                    break;
                }
            } else {
                lambda *= 10.0;
                if lambda > 1e12 {
                    termination = Termination::NoImprovementPossible;
                    break;
                }
            }
        }
        Polished {
            p,
            cost,
            evaluations: evals,
            termination,
        }
    }
}

/// The profile likelihood of ln n: chi2 minimised over the linear parameters (kd, ks >= 0)
/// at each n. The fitter's closed-form inner solve is that minimum already, so the profile
/// costs one pass over the samples per n; it is what makes n's interval honest where a
/// linear parameter sits at its bound (kd = 0): there the curvature of chi2 with kd held
/// fixed sees only the lobe's shape, while the profile lets kd come off 0 as n moves.
impl Prepared<'_> {
    /// The profile at ln n. `linear`: the linear parameters, re-solved by the polish from
    /// the closed form's solution where values are censored.
    fn profile(&self, ln_n: f64, linear: &[usize]) -> f64 {
        let (k, cost) = self.inner(ln_n.exp());
        if !self.any_censored {
            return cost;
        }
        let mut p = [0.0; 7];
        for c in 0..3 {
            p[c] = k[c][0];
            p[3 + c] = k[c][1];
        }
        p[6] = ln_n;
        self.polish(p, linear).cost
    }

    /// Where the profile rises by `target` above `c0` on either side of `x0` (ln n),
    /// within `range` (ln n): [lo, hi]. A side that stays below the target up to the range's
    /// end ends there. `h0` is the first step (the curvature's half-width). Returns the
    /// interval and the profile evaluations used.
    fn profile_interval(
        &self,
        x0: f64,
        c0: f64,
        target: f64,
        range: [f64; 2],
        h0: f64,
        linear: &[usize],
    ) -> ([f64; 2], usize) {
        if !(x0.is_finite() && c0.is_finite() && target.is_finite() && target > 0.0) {
            // Nothing to step from: the interval is the searched range.
            return (range, 0);
        }
        let mut evals = 0;
        let root_target = target.sqrt();
        let mut g = |h: f64, s: f64| {
            evals += 1;
            (self.profile(x0 + s * h, linear) - c0).max(0.0).sqrt() - root_target
        };
        let mut ends = [x0; 2];
        for (k, s) in [-1.0, 1.0].into_iter().enumerate() {
            let room = if s < 0.0 {
                x0 - range[0]
            } else {
                range[1] - x0
            };
            if room.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
                continue;
            }
            // Step out, doubling, until the profile passes the target.
            let (mut a, mut ga) = (0.0, -root_target);
            let h_start = if h0.is_finite() && h0 > 0.0 { h0 } else { room };
            let mut h = h_start.clamp(1e-4f64.min(room), room);
            let mut above = None;
            loop {
                let gh = g(h, s);
                if gh.is_nan() {
                    // The profile cannot be evaluated there (a degenerate draw): this side
                    // is open to the searched range.
                    break;
                }
                if gh >= 0.0 {
                    above = Some((h, gh));
                    break;
                }
                (a, ga) = (h, gh);
                if h >= room {
                    break;
                }
                h = (2.0 * h).min(room);
            }
            let Some((mut b, mut gb)) = above else {
                ends[k] = x0 + s * room;
                continue;
            };
            // Illinois regula falsi on the signed root of the rise (about linear in ln n).
            let mut side = 0;
            for _ in 0..40 {
                if b - a <= 1e-4 * (1.0 + b) {
                    break;
                }
                // Bisection where regula falsi has no finite answer (an infinite rise: a
                // profile that cannot be evaluated beyond some n).
                let m = if gb - ga > 0.0 && ga.is_finite() && gb.is_finite() {
                    (a * gb - b * ga) / (gb - ga)
                } else {
                    0.5 * (a + b)
                };
                let m = m.clamp(a + 0.01 * (b - a), b - 0.01 * (b - a));
                let gm = g(m, s);
                if gm.is_nan() {
                    break;
                }
                if gm >= 0.0 {
                    (b, gb) = (m, gm);
                    if side == 1 {
                        ga *= 0.5;
                    }
                    side = 1;
                } else {
                    (a, ga) = (m, gm);
                    if side == -1 {
                        gb *= 0.5;
                    }
                    side = -1;
                }
            }
            ends[k] = x0 + s * 0.5 * (a + b);
        }
        (ends, evals)
    }
}

/// The 95% interval of r = ks / kd by Fieller's theorem from the estimates and their
/// (co)variances: the r for which ks - r kd is within 1.96 of its standard error of 0.
/// Bounded when kd is clearly above 0; open above ([lo, inf]) when kd's interval reaches 0.
/// The ratio is not negative, so the interval is cut at 0.
pub fn fieller_ratio_ci95(kd: f64, ks: f64, var_kd: f64, var_ks: f64, cov: f64) -> [f64; 2] {
    let t2 = 1.96f64 * 1.96;
    let a = kd * kd - t2 * var_kd;
    let b = kd * ks - t2 * cov;
    let c = ks * ks - t2 * var_ks;
    let disc = b * b - a * c;
    if !(a.is_finite() && b.is_finite() && c.is_finite()) {
        return [f64::NAN; 2];
    }
    if a > 0.0 {
        if disc < 0.0 {
            // Cannot happen for a positive semi-definite covariance; the point itself.
            let r = ks / kd;
            return [r.max(0.0), r.max(0.0)];
        }
        let q = disc.sqrt();
        return [((b - q) / a).max(0.0), ((b + q) / a).max(0.0)];
    }
    // kd's interval reaches 0: the set is outside the roots (or everything), cut at 0.
    if disc <= 0.0 || a == 0.0 {
        let lo = if a == 0.0 && b > 0.0 {
            (c / (2.0 * b)).max(0.0)
        } else {
            0.0
        };
        return [lo, f64::INFINITY];
    }
    let q = disc.sqrt();
    let (r1, r2) = ((b + q) / a, (b - q) / a);
    let (r1, r2) = (r1.min(r2), r1.max(r2));
    if r1 < 0.0 {
        [r2.max(0.0), f64::INFINITY]
    } else {
        [0.0, f64::INFINITY]
    }
}

/// Public for the derivative test: the weighted residuals and their Jacobian (3N x 7) at
/// p = (kd, ks, ln n), from the same per-sample derivatives the fit accumulates.
pub fn polish_residuals_and_jacobian(
    model: &dyn Reflectance,
    samples: &[Sample],
    p: [f64; 7],
) -> (DVector<f64>, DMatrix<f64>) {
    let prep = Prepared::new(model, samples, false, 3);
    let m = 3 * samples.len();
    let mut r = DVector::zeros(m);
    let mut j = DMatrix::zeros(m, 7);
    for i in 0..samples.len() {
        for c in 0..3 {
            let (res, d) = prep.residual(i, c, &p);
            r[3 * i + c] = res;
            j[(3 * i + c, c)] = d[0];
            j[(3 * i + c, 3 + c)] = d[1];
            j[(3 * i + c, 6)] = d[2];
        }
    }
    (r, j)
}

/// The variable-projection search for ln n: a log-spaced scan, then golden-section
/// refinement to 1% in n. Returns p = (kd, ks, ln n) and the inner solves used.
fn search(
    prep: &Prepared,
    model: &dyn Reflectance,
    opts: &Options,
    warnings: &mut Vec<String>,
) -> ([f64; 7], usize) {
    let mut evals = 0;
    let (k, ln_n) = if model.has_lobe() {
        let (l0, l1) = (opts.n_min.ln(), opts.n_max.ln());
        let m = opts.scan.max(3);
        let t = |i: usize| l0 + (l1 - l0) * i as f64 / (m - 1) as f64;
        let costs: Vec<f64> = (0..m)
            .map(|i| {
                evals += 1;
                prep.inner(t(i).exp()).1
            })
            .collect();
        let best = (0..m)
            .min_by(|&a, &b| costs[a].total_cmp(&costs[b]))
            .unwrap();
        // Golden-section search on the bracket around it.
        let (mut a, mut b) = (t(best.saturating_sub(1)), t((best + 1).min(m - 1)));
        let g = (5f64.sqrt() - 1.0) / 2.0;
        let mut x1 = b - g * (b - a);
        let mut x2 = a + g * (b - a);
        let mut f1 = prep.inner(x1.exp()).1;
        let mut f2 = prep.inner(x2.exp()).1;
        evals += 2;
        // To 1% in n: the polish converges from there in a few steps.
        while b - a > 1e-2 {
            if f1 < f2 {
                b = x2;
                x2 = x1;
                f2 = f1;
                x1 = b - g * (b - a);
                f1 = prep.inner(x1.exp()).1;
            } else {
                a = x1;
                x1 = x2;
                f1 = f2;
                x2 = a + g * (b - a);
                f2 = prep.inner(x2.exp()).1;
            }
            evals += 1;
        }
        let ln_n = 0.5 * (a + b);
        if best == 0 || best == m - 1 {
            warnings.push(format!(
                "the exponent sits at the end of the range searched ({}..{}): the highlight may be missing from the samples, or the surface is flatter or sharper than the range",
                opts.n_min, opts.n_max
            ));
        }
        (prep.inner(ln_n.exp()).0, ln_n)
    } else {
        evals += 1;
        // Lambert: ks = 0; the inner solve with b = 0 gives kd.
        (prep.inner(1.0).0, 0.0)
    };
    let mut full = [0.0; 7];
    for c in 0..3 {
        full[c] = k[c][0];
        full[3 + c] = if model.has_lobe() { k[c][1] } else { 0.0 };
    }
    full[6] = ln_n;
    (full, evals)
}

/// Fit one model to the samples.
pub fn fit<M: Reflectance + Copy>(model: M, samples: &[Sample], opts: &Options) -> ModelFit<M> {
    let nc = opts.channels.clamp(1, 3);
    let mut prep = Prepared::new(&model, samples, opts.grey_ks && model.has_lobe(), nc);
    let grey = prep.grey;
    let mut warnings = Vec::new();
    let (full, evals) = match opts.start {
        Some(st) => (given_start(st, model.has_lobe(), nc), 0),
        None => search(&prep, &model, opts, &mut warnings),
    };
    let params = model_parameters(model.has_lobe(), grey, nc);
    // Those the polish moves: parameters at the non-negativity bound stay there.
    let free: Vec<usize> = params
        .iter()
        .copied()
        .filter(|&i| i == 6 || full[i] > 0.0 || opts.start.is_some())
        .collect();
    let polished = prep.polish(full, &free);
    let (mut values, mut chi2, mut polish_evaluations) =
        (polished.p, polished.cost, polished.evaluations);
    let mut polish_termination = polished.termination;
    if let Some(k) = opts.huber {
        for _ in 0..30 {
            let change = prep.reweight(&values, k);
            let polished = prep.polish(values, &free);
            (values, chi2, polish_evaluations) = (
                polished.p,
                polished.cost,
                polish_evaluations + polished.evaluations,
            );
            polish_termination = polished.termination;
            if change < 1e-3 {
                break;
            }
        }
    }
    if grey && nc == 3 {
        values[4] = values[3];
        values[5] = values[3];
    }
    // Values measured (a demosaicked camera's samples hold one channel each).
    let dof = measured_in(samples, nc).saturating_sub(free.len());
    // The covariance is taken over every parameter of the model, those at their bound
    // included: held out of it, a kd at 0 would take its trade-off with ks and n along,
    // and their intervals would shrink (n's to a tenth on a tile whose kd fits to 0).
    let free = &params;
    // With variances from the HDR stage the covariance is (J^T J)^-1, widened by the
    // reduced chi2 where the residuals exceed their noise (a noise model that is a little
    // low, or flaws no model explains; the Birge ratio). Without variances, the residuals
    // give the scale.
    let reduced = chi2 / dof.max(1) as f64;
    let scale = if opts.variances_known {
        reduced.max(1.0)
    } else {
        reduced
    };
    let mut covariance = prep.covariance(&values, free, scale, nc);
    let mut n_profile95 = None;
    let mut ratio_trace95 = None;
    let mut profile_evaluations = 0;
    if model.has_lobe() {
        let profiled = prep.profile_n(&values, &params, chi2, scale, opts, &mut covariance);
        (n_profile95, ratio_trace95, profile_evaluations) = (
            Some(profiled.half),
            Some(profiled.trace),
            profiled.evaluations,
        );
    }
    let d = Derived::new(
        &model,
        &values,
        &covariance,
        nc,
        n_profile95,
        ratio_trace95,
        0.0,
    );
    let (n, n_ci95, ks_n_correlation) = (d.n, d.n_ci95, d.ks_n_correlation);
    let sd = |i: usize| covariance[i][i].max(0.0).sqrt();
    if model.has_lobe() && ks_n_correlation.abs() > 0.97 && sd(6) <= 0.5 {
        warnings.push(format!(
            "ks and n are strongly correlated ({ks_n_correlation:.3}): the samples do not separate the lobe's height from its width, so a higher, sharper lobe fits as well as a lower, broader one"
        ));
    }
    if model.has_lobe() && sd(6) > 0.5 {
        warnings.push(format!(
            "the exponent is not determined by these samples (n = {:.3} with a 95% range {:.3}..{:.3}): is the highlight in view?",
            n.value, n_ci95[0], n_ci95[1]
        ));
    }
    ModelFit {
        model,
        kd: d.kd,
        ks: d.ks,
        n,
        n_ci95,
        chi2,
        dof,
        parameters: match (model.has_lobe(), grey) {
            (false, _) => nc,
            (true, true) => nc + 2,
            (true, false) => 2 * nc + 1,
        },
        ks_n_correlation,
        own_ks_n_correlation: ks_n_correlation,
        ratio: d.ratio,
        ratio_ci95: d.ratio_ci95,
        n_profile95,
        ratio_trace95,
        n_added_variance: 0.0,
        covariance,
        inner_evaluations: evals + profile_evaluations,
        polish_evaluations,
        polish_termination,
        warnings,
        channels: nc,
    }
}

/// The start values given in `opts.start` as a parameter vector (kd, ks, ln n): none of a
/// lobe for a model without one, none for channels beyond `nc`.
fn given_start(st: Start, has_lobe: bool, nc: usize) -> [f64; 7] {
    let mut p = [
        st.kd,
        st.kd,
        st.kd,
        st.ks,
        st.ks,
        st.ks,
        st.n.max(1e-300).ln(),
    ];
    if !has_lobe {
        p[3..].fill(0.0);
    }
    for c in nc..3 {
        (p[c], p[3 + c]) = (0.0, 0.0);
    }
    p
}

/// The model's parameters: Lambert has no lobe; a grey ks lives in p[3]; a monochrome
/// fit has no kd, ks for channels 1 and 2.
fn model_parameters(has_lobe: bool, grey: bool, nc: usize) -> Vec<usize> {
    (0..7)
        .filter(|&i| {
            if i >= 3 && !has_lobe || grey && (i == 4 || i == 5) {
                return false;
            }
            !(i < 6 && i % 3 >= nc)
        })
        .collect()
}

/// n's interval from the profile likelihood.
struct Profiled {
    /// The 95% interval of ln n, as distances below and above the fitted value.
    half: [f64; 2],
    /// ks / kd per channel along the profile: least and largest.
    trace: [[f64; 2]; 3],
    /// Profile evaluations used.
    evaluations: usize,
}

impl Prepared<'_> {
    /// The covariance of (kd, ks, ln n) over the parameters `free` at `values`, (J^T J)^-1
    /// times `scale`, as the full 7x7 matrix (a grey ks is one parameter, shown in all
    /// three channels; zero rows for parameters not in `free`).
    fn covariance(
        &self,
        values: &[f64; 7],
        free: &[usize],
        scale: f64,
        nc: usize,
    ) -> Vec<Vec<f64>> {
        let grey = self.grey;
        let jtj = self.normal(values, free).1;
        // Invert J^T J scaled to unit diagonal: kd multiplies a basis of order 1/D^2 while
        // ln n is of order one, so the raw matrix spans many decades and a floor on its
        // singular values relative to the largest would cut the kd directions.
        let k = free.len();
        let dscale = DVector::from_iterator(
            k,
            (0..k).map(|u| {
                let d = jtj[(u, u)];
                if d > 0.0 {
                    1.0 / d.sqrt()
                } else {
                    1.0
                }
            }),
        );
        let scaled = DMatrix::from_fn(k, k, |u, v| jtj[(u, v)] * dscale[u] * dscale[v]);
        let svd = scaled.svd(true, true);
        let smax = svd.singular_values.max();
        let cov = match (&svd.u, &svd.v_t) {
            (Some(u), Some(vt)) => {
                let inv = DVector::from_iterator(
                    k,
                    svd.singular_values
                        .iter()
                        .map(|v| 1.0 / v.max(smax * 1e-14)),
                );
                let c = vt.transpose() * DMatrix::from_diagonal(&inv) * u.transpose() * scale;
                DMatrix::from_fn(k, k, |u, v| c[(u, v)] * dscale[u] * dscale[v])
            }
            _ => DMatrix::from_element(k, k, f64::INFINITY),
        };
        // The full 7x7 covariance (a grey ks is one parameter, shown in all three channels).
        let slot = |i: usize| {
            if i < 6 && i % 3 >= nc {
                return None;
            }
            let i = if grey && (i == 4 || i == 5) { 3 } else { i };
            free.iter().position(|&f| f == i)
        };
        (0..7)
            .map(|i| {
                (0..7)
                    .map(|j| match (slot(i), slot(j)) {
                        (Some(a), Some(b)) => cov[(a, b)],
                        _ => 0.0,
                    })
                    .collect()
            })
            .collect()
    }

    /// n's interval from the profile likelihood: where chi2, minimised over the linear
    /// parameters (kd, ks >= 0) at each n, rises by 3.84 (times the Birge ratio `scale`);
    /// ks / kd along it; and `covariance` widened where the profile is wider than the
    /// curvature says.
    fn profile_n(
        &self,
        values: &[f64; 7],
        params: &[usize],
        chi2: f64,
        scale: f64,
        opts: &Options,
        covariance: &mut [Vec<f64>],
    ) -> Profiled {
        let nc = opts.channels.clamp(1, 3);
        let prep = self;
        let x0 = values[6];
        let linear: Vec<usize> = params.iter().copied().filter(|&i| i != 6).collect();
        let c0 = chi2.min(prep.profile(x0, &linear));
        let sd_curv = covariance[6][6].max(0.0).sqrt();
        let range = [opts.n_min.ln().min(x0), opts.n_max.ln().max(x0)];
        let ([lo, hi], e) = prep.profile_interval(
            x0,
            c0,
            DELTA_CHI2_95 * scale,
            range,
            1.96 * sd_curv,
            &linear,
        );
        let half = [x0 - lo, hi - x0];
        // ks / kd at the profile's ends (the closed form at those n: the linear parameters
        // that minimise chi2 there) and at the optimum.
        let at_ends = [lo, hi].map(|x| prep.inner(x.exp()).0);
        let mut trace = [[f64::NAN; 2]; 3];
        for (c, t) in trace.iter_mut().enumerate().take(nc) {
            let r0 = values[3 + c] / values[c];
            let rs = at_ends.map(|k| k[c][1] / k[c][0]);
            *t = [r0, rs[0], rs[1]]
                .iter()
                .filter(|r| !r.is_nan())
                .fold([f64::INFINITY, f64::NEG_INFINITY], |[a, b], &r| {
                    [a.min(r), b.max(r)]
                });
        }
        // ln n's standard deviation: the wider side of the profile interval over 1.96,
        // where that exceeds the curvature's. The other parameters move with ln n along
        // their regression on it (b_i = cov(i, n) / var(n)), so widening var(n) by f^2
        // adds (f^2 - 1) var(n) b b^T to the whole covariance: ks, whose height trades with
        // the lobe's width, widens with n, not only n.
        let sd_prof = half[0].max(half[1]) / 1.96;
        if sd_curv > 0.0 && sd_prof > sd_curv && sd_prof.is_finite() {
            let f2 = (sd_prof / sd_curv).powi(2);
            let v = covariance[6][6];
            let col: Vec<f64> = (0..7).map(|i| covariance[i][6]).collect();
            for i in 0..7 {
                for j in 0..7 {
                    covariance[i][j] += (f2 - 1.0) * col[i] * col[j] / v;
                }
            }
        }
        Profiled {
            half,
            trace,
            evaluations: e + 1,
        }
    }
}

/// Estimates derived from the parameter vector p = (kd, ks, ln n) and its covariance.
struct Derived {
    kd: [Estimate; 3],
    ks: [Estimate; 3],
    n: Estimate,
    n_ci95: [f64; 2],
    ratio: [Estimate; 3],
    ratio_ci95: [[f64; 2]; 3],
    ks_n_correlation: f64,
}

impl Derived {
    /// `profile`: the fit's own 95% interval of ln n (distances below and above), widened
    /// in quadrature by `added` (variance of ln n from other sources); without it the
    /// interval is the normal one on ln n. `trace`: ks / kd's range along that profile
    /// ([`ModelFit::ratio_trace95`]); its interval and sd span it.
    fn new(
        model: &dyn Reflectance,
        values: &[f64; 7],
        cov: &[Vec<f64>],
        channels: usize,
        profile: Option<[f64; 2]>,
        trace: Option<[[f64; 2]; 3]>,
        added: f64,
    ) -> Self {
        let sd = |i: usize| cov[i][i].max(0.0).sqrt();
        let est = |i: usize| Estimate {
            value: values[i],
            sd: sd(i),
        };
        let nan = Estimate {
            value: f64::NAN,
            sd: f64::NAN,
        };
        let lobe = model.has_lobe();
        let (n, n_ci95) = if lobe {
            let (ln, s) = (values[6], sd(6));
            let [below, above] = match profile {
                Some(h) => h.map(|h| (h * h + 1.96 * 1.96 * added.max(0.0)).sqrt()),
                None => [1.96 * s; 2],
            };
            (
                Estimate {
                    value: ln.exp(),
                    sd: ln.exp() * s,
                },
                [(ln - below).exp(), (ln + above).exp()],
            )
        } else {
            (nan, [f64::NAN; 2])
        };
        // Correlation of ks (the strongest channel's) with ln n: near 1 when the samples
        // miss the highlight's peak (clipped, or off the line).
        let ks_n_correlation = if lobe {
            let c = 3
                + (0..channels)
                    .max_by(|&a, &b| values[3 + a].total_cmp(&values[3 + b]))
                    .unwrap();
            let den = (cov[c][c] * cov[6][6]).sqrt();
            if den > 0.0 {
                cov[c][6] / den
            } else {
                f64::NAN
            }
        } else {
            f64::NAN
        };
        // ks / kd by the delta method, correlation included; infinite where kd is 0.
        let ratio = [0, 1, 2].map(|c| {
            if !lobe || c >= channels || values[c] <= 0.0 && values[3 + c] <= 0.0 {
                return nan;
            }
            if values[c] <= 0.0 {
                return Estimate {
                    value: f64::INFINITY,
                    sd: f64::INFINITY,
                };
            }
            let (kd, ks) = (values[c], values[3 + c]);
            let r = ks / kd;
            // d r / d kd = -r / kd, d r / d ks = 1 / kd.
            let var = (r * r * cov[c][c] + cov[3 + c][3 + c] - 2.0 * r * cov[c][3 + c]) / (kd * kd);
            Estimate {
                value: r,
                sd: var.max(0.0).sqrt(),
            }
        });
        // Its interval by Fieller's theorem: open above where kd's interval reaches 0.
        let ratio_ci95 = [0, 1, 2].map(|c| {
            if !lobe || c >= channels || values[c] <= 0.0 && values[3 + c] <= 0.0 {
                return [f64::NAN; 2];
            }
            let f = fieller_ratio_ci95(
                values[c],
                values[3 + c],
                cov[c][c],
                cov[3 + c][3 + c],
                cov[c][3 + c],
            );
            match trace.map(|t| t[c]) {
                Some([lo, hi]) if lo <= hi => [f[0].min(lo), f[1].max(hi)],
                _ => f,
            }
        });
        // The ratio's sd spans its interval (Fieller's and the trace's): the interval's wider
        // side over 1.96. Where kd is small against its error the ratio's distribution is
        // skewed (a long tail above), and the delta method's sd, which sees only the slope
        // at the estimate, claimed more than the interval did: on a broad lobe (n 18, the
        // lobe's share varying 2% over the tile) ks / kd 1.31 +- 0.46 with the interval
        // 0.72..2.82 and the truth at 3.34 (-4.5 "sd", outside the interval by 0.7 of its
        // upper half).
        let mut ratio = ratio;
        for c in 0..channels.min(3) {
            let [lo, hi] = ratio_ci95[c];
            let r = &mut ratio[c];
            if lo <= hi && r.value.is_finite() {
                let wide = (r.value - lo).max(hi - r.value) / 1.96;
                if wide > r.sd {
                    r.sd = wide;
                }
            }
        }
        Derived {
            kd: [est(0), est(1), est(2)],
            ks: [est(3), est(4), est(5)],
            n,
            n_ci95,
            ratio,
            ratio_ci95,
            ks_n_correlation,
        }
    }
}

/// Values with a usable variance (those a fit weighs): the m of BIC's k ln m.
pub fn measured_values(samples: &[Sample]) -> usize {
    measured_in(samples, 3)
}

/// Values with a weight among the first `channels` of each sample.
fn measured_in(samples: &[Sample], channels: usize) -> usize {
    samples
        .iter()
        .map(|s| weights(s)[..channels].iter().filter(|w| **w > 0.0).count())
        .sum()
}

impl<M: Reflectance> ModelFit<M> {
    /// The fitted model's radiance for channel c at a sample's geometry.
    pub fn predict(&self, g: &Geometry, c: usize) -> f64 {
        self.model
            .radiance(g, self.kd[c].value, self.ks[c].value, self.n.value)
    }

    /// BIC on `m` fitted values: chi2 + k ln m.
    pub fn bic(&self, m: usize) -> f64 {
        self.chi2 + self.parameters as f64 * (m.max(1) as f64).ln()
    }

    /// The parameter vector (kd, ks, ln n).
    pub fn values(&self) -> [f64; 7] {
        let ln_n = if self.model.has_lobe() {
            self.n.value.ln()
        } else {
            0.0
        };
        [
            self.kd[0].value,
            self.kd[1].value,
            self.kd[2].value,
            self.ks[0].value,
            self.ks[1].value,
            self.ks[2].value,
            ln_n,
        ]
    }

    /// Carry ks / kd's range ([`ModelFit::ratio_trace95`]) on to n's interval as other
    /// sources widened it ([`ModelFit::add_covariance`]): the model refitted to `samples`
    /// with n held at each end of that interval, and ks / kd there joins the range. A broad
    /// lobe's height trades with its width whatever moved n (the response's draws moving n
    /// by 14% moved ks / kd by 74% on a 1280x960 scene, −4.8 sd without this, −2.8 sd with
    /// it). Two more fits; nothing where n's interval is the fit's own.
    pub fn follow_n_interval(&mut self, samples: &[Sample], opts: &Options)
    where
        M: Copy,
    {
        if !self.model.has_lobe() || self.n_added_variance <= 0.0 {
            return;
        }
        let Some(mut trace) = self.ratio_trace95 else {
            return;
        };
        for x in self.n_ci95 {
            if !(x.is_finite() && x > 0.0) {
                continue;
            }
            let x = x.clamp(opts.n_min, opts.n_max);
            let held = fit(
                self.model,
                samples,
                &Options {
                    n_min: x * (1.0 - 1e-4),
                    n_max: x * (1.0 + 1e-4),
                    ..*opts
                },
            );
            for (c, t) in trace.iter_mut().enumerate().take(self.channels.min(3)) {
                let r = held.ks[c].value / held.kd[c].value;
                if !r.is_nan() {
                    *t = [t[0].min(r), t[1].max(r)];
                }
            }
        }
        self.ratio_trace95 = Some(trace);
        self.derive();
    }

    /// Recompute every standard error and interval from the covariance, the profile and
    /// the trace.
    fn derive(&mut self) {
        let d = Derived::new(
            &self.model,
            &self.values(),
            &self.covariance,
            self.channels,
            self.n_profile95,
            self.ratio_trace95,
            self.n_added_variance,
        );
        self.kd = d.kd;
        self.ks = d.ks;
        self.n = d.n;
        self.n_ci95 = d.n_ci95;
        self.ratio = d.ratio;
        self.ratio_ci95 = d.ratio_ci95;
        self.ks_n_correlation = d.ks_n_correlation;
    }

    /// Add a covariance from another source (the calibration's, by resampling) to the
    /// fit's own, and recompute every standard error and interval.
    pub fn add_covariance(&mut self, extra: &[Vec<f64>]) {
        for i in 0..7 {
            for j in 0..7 {
                self.covariance[i][j] += extra[i][j];
            }
        }
        self.n_added_variance += extra[6][6].max(0.0);
        self.derive();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::model::{Geometry, Model, Reflectance};

    /// The polish says why it stopped: on samples a Phong lobe explains exactly, it
    /// converges.
    #[test]
    fn the_polish_says_why_it_stopped() {
        let samples: Vec<Sample> = (0..60)
            .map(|i| {
                let t = i as f64 / 59.0;
                let g = Geometry {
                    cos_l: 0.6 + 0.3 * t,
                    r_dot_v: 0.9 + 0.1 * t,
                    n_dot_h: 0.97 + 0.03 * t,
                    d2: 1.0,
                    cos_v: 0.8,
                    v_dot_h: 0.9,
                };
                let l = Model::Phong.radiance(&g, 0.3, 0.5, 40.0);
                Sample::new(g, [l; 3], [1e-4 * l * l; 3])
            })
            .collect();
        let f = fit(Model::Phong, &samples, &Options::default());
        assert_eq!(f.polish_termination, Termination::Converged);
        assert!(f.polish_termination.was_successful());
        assert!((f.n.value / 40.0 - 1.0).abs() < 1e-3, "{}", f.n.value);
    }
}
