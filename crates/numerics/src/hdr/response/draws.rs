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
    /// `step` in ln (the median ratio of neighbouring exposures). A table curve's draws get
    /// a third part then: a random curve periodic in ln E (the curve's own output) with that
    /// period, a sine and a cosine, each of sd [`BEND_SHARE`] times the curve's [`bend`] over
    /// the values read. Such a curve is what a bracket cannot see: every reading and the
    /// one a step brighter move by the same amount, so the residuals, and with them the
    /// misfit, stay as they were; yet across a tile it bends the merged radiance by up to
    /// twice its amplitude between pixels a half-step apart, which is what a broad lobe's n
    /// and ks/kd are made of. Its size is not in the data; what sets it is how far the
    /// camera's curve departs from the one shape every fit finds exactly, a power law (a
    /// straight line in ln E against ln z), within one step: a gamma or linear curve has no
    /// such error, a bent tone curve an error that grows with its bend and with the step
    /// (docs/results/accuracy.md, seventh round).
    pub fn draws_for_bracket(&self, values: &[Vec<u32>], step: Option<f64>) -> Option<CurveDraws> {
        let max = self.max_value();
        let mut parts = Vec::with_capacity(self.channels.len());
        for (c, (ch, vals)) in self.channels.iter().zip(values).enumerate() {
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
            }
            if let Some(step) = step.filter(|s| s.is_finite() && *s > 0.05) {
                let amplitude = BEND_SHARE * bend(self, c, vals, step);
                if amplitude > 0.0 && amplitude.is_finite() {
                    let w = std::f64::consts::TAU / step;
                    let basis = vals
                        .iter()
                        .map(|z| {
                            let mut out = [0.0; MAX_DEGREE];
                            let e = self.exposure(c, (*z as f64).max(0.5));
                            let x = if e > 0.0 && e.is_finite() {
                                w * e.ln()
                            } else {
                                0.0
                            };
                            out[0] = x.sin();
                            out[1] = x.cos();
                            out
                        })
                        .collect();
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

/// The unseen periodic curve's sd (each of its sine and cosine) as a share of the curve's
/// [`bend`] over the values read. Measured on the second scene family's seeds 13000-13099
/// (a tuning set): the merged radiance's systematic error on the tile, rms, was 0.15-0.25
/// of the bend at the median and 0.6-0.8 of it at the 90th percentile, alike for brackets
/// a stop and two stops apart (where the visible misfit had put it at 0.5 to 2 times the
/// misfit, with a tail to 20 times). Half the bend took 13011's n from -13 to -4 sd and the
/// four other 2-stop scenes beyond 3 sd within it; seeds 14000-14099 were then held out
/// (docs/results/accuracy.md, seventh round).
pub const BEND_SHARE: f64 = 0.5;

/// How far channel `c`'s curve departs from a power law within one bracket step (`step`,
/// ln) about the values `vals` it reads: for each value, the curve over the ln E within
/// half a step of the value's (33 points even in ln E) is fitted with a straight line in
/// ln z and the rms residual taken; then the rms over the values (at most 64, by quantile,
/// so the values read most count most). Zero for a linear curve, a gamma curve, or one the
/// values do not reach. A power law is the shape every curve model and every bracket
/// recovers exactly (a straight line in ln E against ln z moves each reading and the one a
/// step brighter alike only if it is one); what a camera's curve bends within one step is
/// what its recovered curve can have wrong where the bracket does not see it.
pub fn bend(r: &Response, c: usize, vals: &[u32], step: f64) -> f64 {
    let Some(ch) = r.channels.get(c) else {
        return 0.0;
    };
    if r.model == Model::Linear || !(step.is_finite() && step > 0.0) {
        return 0.0;
    }
    let g = &ch.ln_exposure;
    let lo = ch.valid_min.max(1) as usize;
    // The inverse response below reads the table up to valid_max.
    let hi = ch.valid_max as usize;
    if hi >= g.len() || hi < lo + 2 || !g[lo..=hi].iter().all(|x| x.is_finite()) {
        return 0.0;
    }
    let mut read: Vec<usize> = vals
        .iter()
        .map(|z| *z as usize)
        .filter(|z| (lo..=hi).contains(z))
        .collect();
    if read.is_empty() {
        return 0.0;
    }
    read.sort_unstable();
    let take = read.len().min(BEND_VALUES);
    // The value where the curve reaches y, within the values the curve is known at (the
    // inverse response, [`Response::value`]), and the curve there.
    let at = |y: f64| -> (f64, f64) {
        let y = y.clamp(g[lo], g[hi]);
        (r.value(c, y.exp()), y)
    };
    let (mut sum, mut n) = (0.0, 0usize);
    for i in 0..take {
        let y0 = g[read[i * read.len() / take]];
        let pts: Vec<(f64, f64)> = (0..BEND_POINTS)
            .map(|k| {
                let (z, y) = at(y0 + step * (k as f64 / (BEND_POINTS - 1) as f64 - 0.5));
                (z.max(0.5).ln(), y)
            })
            .collect();
        let kf = pts.len() as f64;
        let (mx, my) = (
            pts.iter().map(|p| p.0).sum::<f64>() / kf,
            pts.iter().map(|p| p.1).sum::<f64>() / kf,
        );
        let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
        if sxx <= 1e-12 {
            continue;
        }
        let slope = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum::<f64>() / sxx;
        sum += pts
            .iter()
            .map(|p| (p.1 - my - slope * (p.0 - mx)).powi(2))
            .sum::<f64>()
            / kf;
        n += 1;
    }
    if n == 0 {
        0.0
    } else {
        (sum / n as f64).sqrt()
    }
}

/// Values [`bend`] averages over (by quantile of those read).
const BEND_VALUES: usize = 64;

/// Points of the curve [`bend`] fits a line to within each step.
const BEND_POINTS: usize = 33;

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::hdr::response::curve::{Channel, Noise};
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    /// A 12-bit Debevec-style table response, one channel, ln E = `f(ln (z / 16))` (so
    /// that its values read as an 8-bit camera's, finely).
    fn table(f: impl Fn(f64) -> f64) -> Response {
        let g: Vec<f64> = (0..4096u32)
            .map(|z| f((z.max(1) as f64 / 16.0).ln()))
            .collect();
        Response {
            format: "glint-response".into(),
            format_version: 1,
            model: Model::Debevec,
            bit_depth: 12,
            camera: None,
            recovered_from: String::new(),
            lambda: 0.0,
            choice: None,
            channels: vec![Channel {
                noise: Noise {
                    shot: 0.0,
                    read: 0.0,
                },
                ..Channel::table(g, Vec::new(), Vec::new(), (64, 4000), 0.0, 100)
            }],
            alternatives: Vec::new(),
            warnings: Vec::new(),
        }
    }

    /// A bent curve: a power law with a bump of 0.3 in ln E about value 60.
    fn bent(x: f64) -> f64 {
        2.2 * x + 0.3 * (-(x - 60f64.ln()).powi(2) / 0.18).exp()
    }

    #[test]
    fn a_power_law_has_no_bend_and_a_bent_curve_more_the_longer_the_step() {
        let vals: Vec<u32> = (320..3200).step_by(16).collect();
        let two_stops = 4f64.ln();
        let gamma = table(|x| 2.2 * x);
        let r = table(bent);
        let (one, two) = (bend(&r, 0, &vals, 2f64.ln()), bend(&r, 0, &vals, two_stops));
        assert!(one > 1e-3, "bend over a stop {one}");
        assert!(
            two > 1.5 * one,
            "bend over two stops {two} against one {one}"
        );
        // A power law's only bend is the table's interpolation between values.
        assert!(bend(&gamma, 0, &vals, two_stops) < 0.02 * two);
        // Values the curve is not known at, or a linear curve: nothing.
        assert_eq!(bend(&r, 0, &[1, 2, 4095], two_stops), 0.0);
        let mut linear = r.clone();
        linear.model = Model::Linear;
        assert_eq!(bend(&linear, 0, &vals, two_stops), 0.0);
    }

    #[test]
    fn the_unseen_curve_is_periodic_in_ln_e_with_the_brackets_step() {
        // No misfit and no coefficients: the draws are the periodic part alone. Readings
        // a step apart in ln E (one at each exposure of the same radiance) move alike, and
        // readings half a step apart move opposite ways.
        let r = table(bent);
        let step = 4f64.ln();
        let g = &r.channels[0].ln_exposure;
        let find = |y: f64| {
            (1..4096u32)
                .min_by(|a, b| {
                    (g[*a as usize] - y)
                        .abs()
                        .total_cmp(&(g[*b as usize] - y).abs())
                })
                .unwrap()
        };
        let z0 = 640u32;
        let (z1, zh) = (find(g[640] + step), find(g[640] + step / 2.0));
        let off = |z: u32| g[z as usize] - g[640];
        assert!((off(z1) - step).abs() < 0.005 && (off(zh) - step / 2.0).abs() < 0.005);
        let draws = r
            .draws_for_bracket(&[vec![z0, z1, zh]], Some(step))
            .expect("a bent curve has an unseen part");
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(12345);
        let mut normal = || -> f64 { StandardNormal.sample(&mut rng) };
        let sd = draws.sd()[0][0];
        assert!(sd > 0.0);
        for _ in 0..20 {
            let d = &draws.draw(&mut normal)[0];
            let tol = 0.1 * sd;
            assert!(
                (d[0] - d[1]).abs() < tol,
                "a step apart: {} vs {}",
                d[0],
                d[1]
            );
            assert!(
                (d[0] + d[2]).abs() < tol,
                "half a step apart: {} vs {}",
                d[0],
                d[2]
            );
        }
    }
}
