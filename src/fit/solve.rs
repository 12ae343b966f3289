//! The fitter: no start values. For a fixed exponent n every model is linear in kd and ks,
//! so they are solved in closed form (non-negative least squares, each channel) and only n
//! is searched: a log-spaced scan, then golden-section refinement of ln n (variable
//! projection); then a joint Levenberg-Marquardt polish in (kd, ks, ln n) with the analytic
//! Jacobian, whose Jacobian gives the covariance.

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

use super::model::{Geometry, Model};

/// One sample: its geometry, radiance per channel, and the radiance's variance (from the
/// HDR stage; weights are 1 / variance).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Sample {
    pub geometry: Geometry,
    pub radiance: [f64; 3],
    pub variance: [f64; 3],
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
}

impl Default for Options {
    fn default() -> Self {
        Options {
            n_min: 1.0,
            n_max: 1.0e4,
            scan: 16,
            variances_known: true,
        }
    }
}

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

/// One model's fit.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ModelFit {
    pub model: Model,
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
    /// Evaluations of the closed-form inner solve (scan and refinement).
    pub inner_evaluations: usize,
    /// Levenberg-Marquardt evaluations in the polish.
    pub polish_evaluations: usize,
    pub warnings: Vec<String>,
}

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

fn weights(s: &Sample) -> [f64; 3] {
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

/// Per-sample quantities that do not depend on n, computed once per fit: the inner solve
/// then costs one exp per sample.
struct Prepared {
    /// Diffuse basis a.
    a: Vec<f64>,
    /// ln of the lobe's cosine (r.v or n.h); -inf where it is 0.
    ln_x: Vec<f64>,
    /// The lobe's factor: b = factor x^n (times n + 2 for the cosine lobe).
    factor: Vec<f64>,
    w: Vec<[f64; 3]>,
    l: Vec<[f64; 3]>,
    /// Sum of w l^2 per channel.
    ll: [f64; 3],
    cosine_lobe: bool,
}

impl Prepared {
    fn new(model: Model, samples: &[Sample]) -> Self {
        let mut p = Prepared {
            a: Vec::with_capacity(samples.len()),
            ln_x: Vec::with_capacity(samples.len()),
            factor: Vec::with_capacity(samples.len()),
            w: Vec::with_capacity(samples.len()),
            l: Vec::with_capacity(samples.len()),
            ll: [0.0; 3],
            cosine_lobe: model == Model::CosineLobe,
        };
        for s in samples {
            let g = &s.geometry;
            p.a.push(Model::diffuse(g));
            let (x, f) = match model {
                Model::Lambert => (0.0, 0.0),
                Model::Phong => (g.r_dot_v, 1.0 / g.d2),
                Model::BlinnPhong => (g.n_dot_h, 1.0 / g.d2),
                Model::CosineLobe => (g.r_dot_v, g.cos_l / (g.d2 * 2.0 * std::f64::consts::PI)),
            };
            p.ln_x
                .push(if x > 0.0 { x.ln() } else { f64::NEG_INFINITY });
            p.factor.push(f);
            let w = weights(s);
            for (ll, (w, l)) in p.ll.iter_mut().zip(w.iter().zip(&s.radiance)) {
                *ll += w * l * l;
            }
            p.w.push(w);
            p.l.push(s.radiance);
        }
        p
    }

    /// The closed-form inner solve at exponent n: (kd, ks) per channel and the cost.
    fn inner(&self, n: f64) -> ([[f64; 2]; 3], f64) {
        let mut sums = [Sums::default(); 3];
        let lobe = if self.cosine_lobe { n + 2.0 } else { 1.0 };
        for i in 0..self.a.len() {
            let a = self.a[i];
            let b = self.factor[i] * lobe * (n * self.ln_x[i]).exp();
            let (w, l) = (&self.w[i], &self.l[i]);
            for c in 0..3 {
                let wa = w[c] * a;
                let wb = w[c] * b;
                let sc = &mut sums[c];
                sc.aa += wa * a;
                sc.ab += wa * b;
                sc.bb += wb * b;
                sc.al += wa * l[c];
                sc.bl += wb * l[c];
            }
        }
        let mut k = [[0.0; 2]; 3];
        let mut cost = 0.0;
        for c in 0..3 {
            sums[c].ll = self.ll[c];
            let (kc, cc) = nnls2(&sums[c]);
            k[c] = kc;
            cost += cc;
        }
        (k, cost.max(0.0))
    }
}

/// The joint polish in p = (kd[3], ks[3], ln n): Levenberg-Marquardt on the 7x7 normal
/// equations, accumulated sample by sample. Written here rather than with the
/// levenberg-marquardt crate (used for calibration): the crate factors the full
/// 3N x 7 Jacobian by QR every iteration, which took 40% of the fit's time at 800 samples,
/// while the normal equations of seven parameters cost almost nothing.
impl Prepared {
    /// The lobe's basis b and d b / d ln n at sample i.
    #[inline]
    fn lobe(&self, i: usize, n: f64) -> (f64, f64) {
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
        (
            sw * (p[c] * a + p[3 + c] * b - self.l[i][c]),
            [sw * a, sw * b, sw * p[3 + c] * db],
        )
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
                let r = p[c] * a + p[3 + c] * b - self.l[i][c];
                cost += w * r * r;
                let d = [a, b, p[3 + c] * db];
                let idx = [c, 3 + c, 6];
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

    /// Levenberg-Marquardt from p; returns the optimum, its cost, J^T J there, and the
    /// number of cost evaluations.
    fn polish(&self, mut p: [f64; 7], free: &[usize]) -> ([f64; 7], f64, DMatrix<f64>, usize) {
        let (mut cost, mut jtj, mut jtr) = self.normal(&p, free);
        let mut evals = 1;
        let mut lambda = 1e-3;
        for _ in 0..100 {
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
                    break;
                }
            } else {
                lambda *= 10.0;
                if lambda > 1e12 {
                    break;
                }
            }
        }
        (p, cost, jtj, evals)
    }
}

/// Public for the derivative test: the weighted residuals and their Jacobian (3N x 7) at
/// p = (kd, ks, ln n), from the same per-sample derivatives the fit accumulates.
pub fn polish_residuals_and_jacobian(
    model: Model,
    samples: &[Sample],
    p: [f64; 7],
) -> (DVector<f64>, DMatrix<f64>) {
    let prep = Prepared::new(model, samples);
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

/// Fit one model to the samples.
pub fn fit(model: Model, samples: &[Sample], opts: &Options) -> ModelFit {
    let prep = Prepared::new(model, samples);
    let inner = |_: Model, _: &[Sample], n: f64| prep.inner(n);
    // Lambert has no lobe: its ln n is held at 0 and never used.
    let mut evals = 0;
    let mut warnings = Vec::new();
    let (k, ln_n) = if model.has_lobe() {
        // Coarse scan of ln n.
        let (l0, l1) = (opts.n_min.ln(), opts.n_max.ln());
        let m = opts.scan.max(3);
        let t = |i: usize| l0 + (l1 - l0) * i as f64 / (m - 1) as f64;
        let costs: Vec<f64> = (0..m)
            .map(|i| {
                evals += 1;
                inner(model, samples, t(i).exp()).1
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
        let mut f1 = inner(model, samples, x1.exp()).1;
        let mut f2 = inner(model, samples, x2.exp()).1;
        evals += 2;
        // To 1% in n: the polish converges from there in a few steps.
        while b - a > 1e-2 {
            if f1 < f2 {
                b = x2;
                x2 = x1;
                f2 = f1;
                x1 = b - g * (b - a);
                f1 = inner(model, samples, x1.exp()).1;
            } else {
                a = x1;
                x1 = x2;
                f1 = f2;
                x2 = a + g * (b - a);
                f2 = inner(model, samples, x2.exp()).1;
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
        (inner(model, samples, ln_n.exp()).0, ln_n)
    } else {
        evals += 1;
        // Lambert: ks = 0; the inner solve with b = 0 gives kd.
        (inner(model, samples, 1.0).0, f64::NAN)
    };
    let mut full = [0.0; 7];
    for c in 0..3 {
        full[c] = k[c][0];
        full[3 + c] = if model.has_lobe() { k[c][1] } else { 0.0 };
    }
    full[6] = if model.has_lobe() { ln_n } else { 0.0 };
    // Parameters at the non-negativity bound stay there; Lambert has no lobe.
    let free: Vec<usize> = (0..7)
        .filter(|&i| {
            if i >= 3 && !model.has_lobe() {
                return false;
            }
            i == 6 || full[i] > 0.0
        })
        .collect();
    let (values, chi2, jtj, polish_evaluations) = prep.polish(full, &free);
    let dof = (3 * samples.len()).saturating_sub(free.len());
    let scale = if opts.variances_known {
        1.0
    } else {
        chi2 / dof.max(1) as f64
    };
    let svd = jtj.svd(true, true);
    let smax = svd.singular_values.max();
    let cov = match (&svd.u, &svd.v_t) {
        (Some(u), Some(vt)) => {
            let inv = DVector::from_iterator(
                free.len(),
                svd.singular_values
                    .iter()
                    .map(|v| 1.0 / v.max(smax * 1e-14)),
            );
            vt.transpose() * DMatrix::from_diagonal(&inv) * u.transpose() * scale
        }
        _ => DMatrix::from_element(free.len(), free.len(), f64::INFINITY),
    };
    let sd = |i: usize| {
        free.iter()
            .position(|&f| f == i)
            .map_or(0.0, |k| cov[(k, k)].max(0.0).sqrt())
    };
    let est = |i: usize| Estimate {
        value: values[i],
        sd: sd(i),
    };
    let (n, n_ci95) = if model.has_lobe() {
        let ln = values[6];
        let s = sd(6);
        (
            Estimate {
                value: ln.exp(),
                sd: ln.exp() * s,
            },
            [(ln - 1.96 * s).exp(), (ln + 1.96 * s).exp()],
        )
    } else {
        (
            Estimate {
                value: f64::NAN,
                sd: f64::NAN,
            },
            [f64::NAN; 2],
        )
    };
    if model.has_lobe() && sd(6) > 0.5 {
        warnings.push(format!(
            "the exponent is not determined by these samples (n = {:.3} with a 95% range {:.3}..{:.3}): is the highlight in view?",
            n.value, n_ci95[0], n_ci95[1]
        ));
    }
    ModelFit {
        model,
        kd: [est(0), est(1), est(2)],
        ks: [est(3), est(4), est(5)],
        n,
        n_ci95,
        chi2,
        dof,
        inner_evaluations: evals,
        polish_evaluations,
        warnings,
    }
}
