//! A curve's uncertainty drawn as curves: the polynomial's coefficients, the misfit beyond
//! the noise as a smooth random curve, and the part a bracket cannot see (periodic in ln z
//! with the bracket's step).

use nalgebra::{DMatrix, DVector};

use super::basis::{chebyshev, fine_readings, poly_basis, MAX_DEGREE};
use super::curve::{Model, Response};

impl Response {
    /// A curve drawn from this one's uncertainty, as a whole table ([`Response::draws_at`]
    /// every value): table curves (polynomial, Debevec) only, `normal` giving standard normal
    /// deviates. None for a linear curve, or where there is nothing to draw.
    pub fn draw(&self, normal: &mut dyn FnMut() -> f64) -> Option<Response> {
        if self.model == Model::Linear {
            return None;
        }
        let all: Vec<u32> = (0..=self.max_value()).collect();
        let draws = self.draws_at(&vec![all; self.channels.len()])?;
        let d = draws.draw(normal);
        let mut out = self.clone();
        for (ch, d) in out.channels.iter_mut().zip(d) {
            for (g, d) in ch.ln_exposure.iter_mut().zip(d) {
                *g += d;
            }
        }
        Some(out)
    }

    /// Curves drawn from this one's uncertainty, evaluated only at `values[c]` for channel
    /// `c` (a merge of a few pixels needs no table of 65 536 values). Two independent parts:
    /// a polynomial curve's coefficients, normal with their covariance; and every curve's
    /// misfit ([`Channel::misfit_sd`]), a random smooth curve (Chebyshev in ln z over the
    /// valid values, of degree 10 up to 12 bits, 16 above) whose variance, averaged over the
    /// valid values, is the misfit's square. None where neither part is there (a linear or
    /// Debevec curve that fits its data, or a file written before either was stored).
    pub fn draws_at(&self, values: &[Vec<u32>]) -> Option<CurveDraws> {
        self.draws_for_bracket(values, None)
    }

    /// [`Response::draws_at`] for the frames of a bracket whose exposures step by
    /// `step` in ln (the median ratio of neighbouring exposures). The curve's misfit gets a
    /// third part then: a random curve periodic in ln z with that period (a sine and a
    /// cosine, each of sd `misfit_sd`, so its rms is the misfit's). Such a curve is what a
    /// bracket cannot see: every reading and the one a step brighter move by the same
    /// amount, so the residuals, and with them the misfit, stay as they were; yet across a
    /// tile it bends the merged radiance by up to twice its amplitude between pixels a
    /// half-step apart, which is what a broad lobe's n and ks/kd are made of. Its size is
    /// not in the data: the visible misfit's is taken for it, times the step in stops where
    /// that is more than one ([`period_scale`]; on the simulated family
    /// 8-bit EMoR curves missed by 0.2-0.9% near the ends where the misfit read 0.2%, and
    /// broad lobes' ks/kd moved by up to 44%, beyond 5 sd without this part).
    pub fn draws_for_bracket(&self, values: &[Vec<u32>], step: Option<f64>) -> Option<CurveDraws> {
        let max = self.max_value();
        let mut parts = Vec::with_capacity(self.channels.len());
        for (ch, vals) in self.channels.iter().zip(values) {
            let mut p = Vec::new();
            let k = ch.coefficients.len();
            if self.model == Model::Polynomial && k > 0 && ch.coefficient_covariance.len() == k {
                let cov = DMatrix::from_fn(k, k, |i, j| {
                    ch.coefficient_covariance[i].get(j).copied().unwrap_or(0.0)
                });
                if cov.iter().all(|x| x.is_finite()) {
                    let basis = vals
                        .iter()
                        .map(|z| {
                            let mut phi = [0.0; MAX_DEGREE];
                            poly_basis(*z as f64, k, max, &mut phi);
                            phi
                        })
                        .collect();
                    p.push((sqrt_psd(cov), basis));
                }
            }
            if ch.misfit_sd > 0.0 && ch.misfit_sd.is_finite() && ch.valid_max > ch.valid_min + 1 {
                let (lo, hi) = (
                    (ch.valid_min.max(1) as f64).ln(),
                    (ch.valid_max as f64).ln(),
                );
                let m = misfit_degree(max);
                let psi = |z: f64| {
                    let mut out = [0.0; MAX_DEGREE];
                    let u = (2.0 * (z.max(0.5).ln() - lo) / (hi - lo) - 1.0).clamp(-1.0, 1.0);
                    chebyshev(u, m, &mut out);
                    out
                };
                // Normalise: the mean over the valid values (even in ln z) of psi' G psi is 1.
                const N: usize = 256;
                let mut gram = DMatrix::<f64>::zeros(m, m);
                for i in 0..N {
                    let z = (lo + (i as f64 + 0.5) / N as f64 * (hi - lo)).exp();
                    let r = psi(z);
                    for a in 0..m {
                        for b in 0..m {
                            gram[(a, b)] += r[a] * r[b] / N as f64;
                        }
                    }
                }
                if let Some(inv) = gram.try_inverse() {
                    let cov = inv * (ch.misfit_sd.powi(2) / m as f64);
                    let basis = vals.iter().map(|z| psi(*z as f64)).collect();
                    p.push((sqrt_psd(cov), basis));
                }
                if let Some(step) = step.filter(|s| s.is_finite() && *s > 0.05) {
                    let w = std::f64::consts::TAU / step;
                    let basis = vals
                        .iter()
                        .map(|z| {
                            let mut out = [0.0; MAX_DEGREE];
                            let x = w * (*z as f64).max(0.5).ln();
                            out[0] = x.sin();
                            out[1] = x.cos();
                            out
                        })
                        .collect();
                    let amplitude = ch.misfit_sd * period_scale(step);
                    p.push((DMatrix::from_diagonal_element(2, 2, amplitude), basis));
                }
            }
            parts.push(p);
        }
        if parts.iter().all(|p| p.is_empty()) {
            return None;
        }
        Some(CurveDraws { parts })
    }
}

/// How much larger than the visible misfit the unseen periodic curve is drawn, for a
/// bracket stepping by `step` (ln): the step in stops, at least 1. The visible misfit is the
/// curve's structure as the bracket sees it, a stop or so at a time; a curve error whose
/// slope is that large reaches an amplitude proportional to its period, and the unseen
/// curve's period is the step. On the second scene family, brackets of three exposures two
/// stops apart held every one of the errors beyond 3 sd that the response dominated (seeds
/// 10000-10099 and 12000-12099, docs/results/accuracy.md) with the misfit's own amplitude.
fn period_scale(step: f64) -> f64 {
    (step / std::f64::consts::LN_2).max(1.0)
}

/// Degree of the smooth random curve that carries a curve's misfit into its draws: 16 on
/// frames of more than 12 bits, the cap of their polynomial curves ([`max_degree`]), and 10
/// up to 12 bits (where the cap is 10 to 14 by the bracket's step; the 8-bit families'
/// intervals were measured with draws of degree 10 under both caps). A broad lobe's tile
/// spans a fifth of a stop or so, and what moves its n and ks/kd is the curve's slope there:
/// the recovered EMoR curves' errors wiggle at about the curve's degree (e.g. +0.2%, -0.3%
/// at 0.9 and 0.95 of full scale); degree 4 drew slopes too gentle, and degree 10 on 16-bit
/// curves (fitted to degree 13-15) left the 1280x960 scene family's n = 18.6 tile's ks/kd at
/// -3.2 sd once 800 samples took the noise down (docs/results/accuracy.md).
fn misfit_degree(max: u32) -> usize {
    if fine_readings(max) {
        MAX_DEGREE
    } else {
        10
    }
}

/// A square root R (R R' = C) of a symmetric positive semi-definite matrix, tolerating a
/// singular one.
fn sqrt_psd(c: DMatrix<f64>) -> DMatrix<f64> {
    let eig = nalgebra::SymmetricEigen::new(c);
    &eig.eigenvectors * DMatrix::from_diagonal(&eig.eigenvalues.map(|l| l.max(0.0).sqrt()))
}

/// Curves drawn from a response's uncertainty at chosen values ([`Response::draws_at`]).
#[derive(Debug, Clone)]
pub struct CurveDraws {
    /// Per channel, per independent part: a square root of its covariance and its basis
    /// functions at each value.
    parts: Vec<Vec<DrawPart>>,
}

/// One independent part of a curve's draws: a square root of its covariance, and its
/// basis functions at each value.
type DrawPart = (DMatrix<f64>, Vec<[f64; MAX_DEGREE]>);

impl CurveDraws {
    /// The standard deviation of the draws' change of ln E at each value, per channel
    /// (every part's variance at the value, summed: the parts are independent).
    pub fn sd(&self) -> Vec<Vec<f64>> {
        self.parts
            .iter()
            .map(|parts| {
                let n = parts.first().map(|p| p.1.len()).unwrap_or(0);
                (0..n)
                    .map(|i| {
                        parts
                            .iter()
                            .map(|(root, basis)| {
                                let phi = &basis[i];
                                // |R' phi|^2 = phi' R R' phi = phi' C phi.
                                (0..root.ncols())
                                    .map(|j| {
                                        let t: f64 =
                                            (0..root.nrows()).map(|k| root[(k, j)] * phi[k]).sum();
                                        t * t
                                    })
                                    .sum::<f64>()
                            })
                            .sum::<f64>()
                            .sqrt()
                    })
                    .collect()
            })
            .collect()
    }

    /// One draw: per channel, the change of ln E at each of its values (`normal` gives
    /// standard normal deviates, taken channel by channel, part by part).
    pub fn draw(&self, normal: &mut dyn FnMut() -> f64) -> Vec<Vec<f64>> {
        self.parts
            .iter()
            .map(|parts| {
                let n = parts.first().map(|p| p.1.len()).unwrap_or(0);
                let mut out = vec![0.0; n];
                for (root, basis) in parts {
                    let k = root.nrows();
                    let z = DVector::from_fn(k, |_, _| normal());
                    let d = root * z;
                    for (o, phi) in out.iter_mut().zip(basis) {
                        *o += (0..k).map(|j| d[j] * phi[j]).sum::<f64>();
                    }
                }
                out
            })
            .collect()
    }
}
