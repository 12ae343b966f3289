//! `glint fit SESSION`: the session's radiance (hdr/), camera (calib/) and rig geometry
//! to samples, every candidate model's fit, the choice, and the files `fit/samples.csv`
//! and `fit/fit.json`.

use std::path::Path;
use std::time::Instant;

use serde::Serialize;

use super::choose::{choose, fitting_half, halves, Choice};
use super::geometry::Scene;
use super::model::{Model, Reflectance};
use super::sample::{sample, SampleOptions, Sampled};
use super::solve::{fit, measured_values, ModelFit, Options, Sample};
use crate::fsx::Within;
use crate::hdr::merge::MASK_OK;
use crate::session;
use glint_format::stage::{finite, fit as file};

pub use super::types::{FitError, Inputs, Param, SummaryError, FORMAT, FORMAT_VERSION};
use glint_format::stage::hdr::Summary as HdrSummary;

/// What to fit and how.
#[derive(Debug, Clone)]
pub struct FitOptions {
    /// Candidate models; the choice is among these.
    pub models: Vec<Model>,
    pub sample: SampleOptions,
    pub solver: Options,
    /// Draws of the camera (from the calibration's covariance) and of the response curve
    /// (from its coefficients' covariance) to carry their uncertainty into the fit's
    /// (0: the fit's own uncertainty only).
    pub draws: usize,
    /// Work on a session that is not complete (with a warning).
    pub allow_incomplete: bool,
    /// Where the grid photo leaves the pose weak (the calibration's share of n's variance
    /// above [`WEAK_POSE_SHARE`] and n's sd above [`WEAK_POSE_N_SD`]), refine the camera
    /// with the highlight ([`super::pose::refine`]) and fit everything again at the
    /// refined camera, drawing cameras from the uncertainty the joint problem leaves it,
    /// widened by the tension between the grid photo and the highlight where that is above
    /// 1 ([`super::pose::Refined::tension`]), and the response's curves as everywhere. On
    /// the scene family's weak poses from one photo the worst n error went from 6.2% to
    /// 2.6%; the joint problem's own intervals (no curve, no tension) covered only 65% of
    /// them, the grid photo's width 100% (too wide: the one-photo column's coverage was
    /// 98.3%).
    pub refine_weak_pose: bool,
}

impl Default for FitOptions {
    fn default() -> Self {
        FitOptions {
            models: Model::ALL.to_vec(),
            sample: SampleOptions::default(),
            solver: Options::default(),
            draws: 40,
            allow_incomplete: false,
            refine_weak_pose: true,
        }
    }
}

/// One candidate model as reported. kd, ks and ks / kd have one entry per channel: three
/// (R, G, B), or one for a monochrome camera ([`FitReport::channels`]).
#[derive(Debug, Clone, Serialize)]
pub struct Candidate {
    pub model: Model,
    pub kd: Vec<Param>,
    pub ks: Vec<Param>,
    /// ks / kd per channel (scale-free).
    pub ks_over_kd: Vec<Param>,
    /// The exponent; its interval is computed on ln n.
    pub n: Param,
    /// The microfacet model's roughness α = sqrt(2 / (n + 2)), from n and its interval
    /// (ggx only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub alpha: Option<Param>,
    /// Fitted on all samples.
    pub chi2: f64,
    pub dof: usize,
    pub reduced_chi2: f64,
    pub bic: f64,
    /// Fitted on half the samples, scored on the other half: mean squared standardised
    /// residual per value (about 1 when the model explains them to their noise).
    pub held_out: f64,
    pub parameters: usize,
    pub inner_evaluations: usize,
    pub polish_evaluations: usize,
    /// Why the final polish stopped (converged, or not and why).
    pub polish_termination: glint_numerics::fit::solve::Termination,
    pub ks_n_correlation: f64,
    /// Where the variance of ln n comes from: the fit's own noise, the calibration, the
    /// response curve (None when those were not carried in).
    pub n_variance_share: Option<UncertaintyShare>,
    /// kd and ks in absolute terms, where the rig has a reference standard.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub absolute: Option<super::reference::Absolute>,
    /// The fitted parameters' covariance: the fit's own and what the draws carried in
    /// (calibration, response curve).
    pub covariance: ParamCovariance,
    /// Whether the candidate explains the tile within its noise: held-out residuals at
    /// most [`EXPLAINS_HELD_OUT_RMS`] times the noise.
    pub explains: bool,
    /// Where the samples do not separate the lobe's height (ks) from its width (n): why
    /// (see [`mark_trade_offs`]).
    pub trade_off: Option<String>,
    pub warnings: Vec<String>,
    #[serde(skip)]
    pub fit: ModelFit,
}

/// A covariance of named parameters: kd and ks per channel in the fit's units (this
/// file's kd and ks: relative, before any reference standard), and ln n. A parameter held
/// at its bound has a zero row; a source the data do not bound, an infinite (null)
/// entry.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ParamCovariance {
    pub parameters: Vec<String>,
    pub matrix: Vec<Vec<f64>>,
}

impl ParamCovariance {
    /// The rows and columns of a fit's (kd_r, kd_g, kd_b, ks_r, ks_g, ks_b, ln n)
    /// covariance that its model and channels have.
    fn of(f: &ModelFit) -> Self {
        let names: &[&str] = if f.channels == 1 {
            &["y"]
        } else {
            &["r", "g", "b"]
        };
        let mut idx: Vec<(usize, String)> = names
            .iter()
            .enumerate()
            .map(|(c, n)| (c, format!("kd_{n}")))
            .collect();
        if f.model.has_lobe() {
            idx.extend(
                names
                    .iter()
                    .enumerate()
                    .map(|(c, n)| (3 + c, format!("ks_{n}"))),
            );
            idx.push((6, "ln_n".into()));
        }
        let at = |i: usize, j: usize| {
            f.covariance
                .get(i)
                .and_then(|r| r.get(j))
                .copied()
                .unwrap_or(f64::NAN)
        };
        ParamCovariance {
            matrix: idx
                .iter()
                .map(|(i, _)| idx.iter().map(|(j, _)| at(*i, *j)).collect())
                .collect(),
            parameters: idx.into_iter().map(|(_, n)| n).collect(),
        }
    }
}

impl Candidate {
    /// The held-out residuals' rms in units of their noise (the square root of
    /// `held_out`): about 1 where the model explains the tile, at most
    /// [`EXPLAINS_HELD_OUT_RMS`] where it counts as explaining it.
    pub fn held_out_rms(&self) -> f64 {
        self.held_out.sqrt()
    }

    /// Report a fit: `m` values were fitted; `held_out` is its score from the choice.
    pub fn new(f: ModelFit, held_out: f64, m: usize) -> Self {
        let nc = f.channels;
        Candidate {
            model: f.model,
            kd: f.kd[..nc].iter().map(Param::of).collect(),
            ks: f.ks[..nc].iter().map(Param::of).collect(),
            // Fieller's interval: honest where kd is near 0 (open above where it reaches 0).
            ks_over_kd: f.ratio[..nc]
                .iter()
                .zip(&f.ratio_ci95)
                .map(|(e, ci)| Param {
                    value: e.value,
                    sd: e.sd,
                    ci95: *ci,
                })
                .collect(),
            n: Param {
                value: f.n.value,
                sd: f.n.sd,
                ci95: f.n_ci95,
            },
            chi2: f.chi2,
            dof: f.dof,
            reduced_chi2: f.chi2 / f.dof.max(1) as f64,
            bic: f.bic(m),
            held_out,
            parameters: f.parameters,
            inner_evaluations: f.inner_evaluations,
            polish_evaluations: f.polish_evaluations,
            polish_termination: f.polish_termination,
            ks_n_correlation: f.ks_n_correlation,
            n_variance_share: None,
            alpha: None,
            absolute: None,
            covariance: ParamCovariance::of(&f),
            explains: held_out.is_finite() && held_out.sqrt() <= EXPLAINS_HELD_OUT_RMS,
            trade_off: None,
            warnings: f.warnings.clone(),
            fit: f,
        }
    }
}

/// The calibration's uncertainty carried into the fit by resampling: the camera
/// (intrinsics and pose) is drawn `draws` times from the calibration's covariance, every
/// sample's geometry recomputed for the drawn camera, and the model refitted; the spread
/// of the refitted parameters is added to the fit's own covariance. (A 0.05 mm error in
/// the camera centre moves n by about 1% on the mock rig: as much as the noise.) With
/// `about` the draws are `offset + root * w` in the calibration's whitened coordinates
/// ([`super::pose::Refined::draws`]): the refined camera, with the uncertainty the joint
/// problem of camera and highlight leaves it. Refitting the reflectance at each such camera
/// and adding the fit's own covariance at fixed camera gives the joint problem's marginal
/// covariance (the law of total variance), to which the response's draws then add the
/// curve's part the joint problem does not see.
#[allow(clippy::too_many_arguments)]
pub fn calibration_covariance(
    inputs: &Inputs,
    pixels: &[(usize, usize)],
    samples: &[Sample],
    model: Model,
    opts: &Options,
    draws: usize,
    seed: u64,
    about: Option<&super::pose::CameraDraws>,
) -> Option<Vec<Vec<f64>>> {
    use rand_distr::{Distribution, StandardNormal};
    let camera = super::pose::Camera::new(&inputs.calibration, &inputs.scene)?;
    if draws < 2 {
        return None;
    }
    let k = camera.dim();
    if about.is_some_and(|a| a.offset.len() != k || a.root.shape() != (k, k)) {
        return None;
    }
    refit_spread(model, opts, draws, seed, |rng| {
        let w = nalgebra::DVector::from_fn(k, |_, _| {
            Distribution::<f64>::sample(&StandardNormal, &mut *rng)
        });
        let z = match about {
            Some(a) => nalgebra::DVector::from_column_slice(&a.offset) + &a.root * w,
            None => w,
        };
        Some(super::pose::seen_by(
            &camera.scene(z.as_slice()),
            pixels,
            samples,
        ))
    })
}

/// Refit `model` to `draws` perturbed copies of the samples (`make` draws one from the
/// seeded generator; None stops) and return the covariance of the refitted parameters.
fn refit_spread(
    model: Model,
    opts: &Options,
    draws: usize,
    seed: u64,
    mut make: impl FnMut(&mut rand_xoshiro::Xoshiro256PlusPlus) -> Option<Vec<Sample>>,
) -> Option<Vec<Vec<f64>>> {
    use rand::SeedableRng;
    if draws < 2 {
        return None;
    }
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed);
    let mut outs: Vec<[f64; 7]> = Vec::with_capacity(draws);
    for _ in 0..draws {
        let v = fit(model, &make(&mut rng)?, opts).values();
        // A draw the model cannot be fitted at (a camera so far off that the geometry
        // degenerates) says nothing about the spread; many of them say the source's
        // uncertainty is unbounded.
        if v.iter().all(|x| x.is_finite()) {
            outs.push(v);
        }
    }
    if 2 * outs.len() < draws.max(2) {
        return None;
    }
    let n = outs.len() as f64;
    let mean: Vec<f64> = (0..7)
        .map(|i| outs.iter().map(|o| o[i]).sum::<f64>() / n)
        .collect();
    Some(
        (0..7)
            .map(|i| {
                (0..7)
                    .map(|j| {
                        outs.iter()
                            .map(|o| (o[i] - mean[i]) * (o[j] - mean[j]))
                            .sum::<f64>()
                            / (n - 1.0)
                    })
                    .collect()
            })
            .collect(),
    )
}

/// The sampled pixels' readings in every frame of the bracket and of the dark frames,
/// with the response they were merged with: enough to merge them again with another
/// response.
pub struct Readings {
    pub response: crate::hdr::response::Response,
    pub tiles: crate::hdr::Bracket,
    pub darks: crate::hdr::Bracket,
    /// The pixels' merge prepared for curves drawn about `response` (None: the frames do
    /// not match it).
    pixel_merge: Option<crate::hdr::merge::PixelMerge>,
    /// The response's draws at the values `pixel_merge` needs (None: nothing to draw).
    draws: Option<crate::hdr::response::CurveDraws>,
    /// The response's alternative curves ([`crate::hdr::response::Alternative`]) as
    /// changes at the values `pixel_merge` needs.
    alternatives: Vec<Vec<Vec<f64>>>,
}

impl Readings {
    /// Read the session's frames at `pixels` (u, v); `response` is the one they were
    /// merged with.
    pub fn load(
        dir: &Path,
        pixels: &[(usize, usize)],
        response: crate::hdr::response::Response,
    ) -> Result<Self, FitError> {
        // The state was looked at by the stage that calls this.
        let m = session::open(dir, true)?;
        // Each frame is read, its readings at `pixels` kept and the rest dropped: the
        // memory is one frame's, whatever the number of frames listed.
        let input = |e: crate::hdr::HdrError| FitError::Input(e.to_string());
        let frames = crate::hdr::SessionFrames::new(dir, &m).map_err(input)?;
        let (w, nc) = (frames.width, frames.channels());
        let at: Vec<usize> = pixels.iter().map(|&(u, v)| v * w + u).collect();
        let pick = |list: &[&session::FrameRecord]| -> Result<crate::hdr::Bracket, FitError> {
            let picked = list
                .iter()
                .map(|r| Ok(frames.read(r).map_err(input)?.pick(&at, nc)))
                .collect::<Result<Vec<_>, FitError>>()?;
            Ok(crate::hdr::Bracket {
                width: pixels.len(),
                height: 1,
                bit_depth: frames.bit_depth,
                channels: nc,
                frames: picked,
            })
        };
        let (tiles, darks) = (pick(&frames.tiles)?, pick(&frames.darks)?);
        Ok(Readings::new(response, tiles, darks))
    }

    /// Readings of some pixels (`tiles` and `darks`: one row of them) merged with
    /// `response`.
    pub fn new(
        response: crate::hdr::response::Response,
        tiles: crate::hdr::Bracket,
        darks: crate::hdr::Bracket,
    ) -> Self {
        let pixel_merge = crate::hdr::merge::PixelMerge::new(&response, &tiles, &darks).ok();
        let draws = pixel_merge
            .as_ref()
            .and_then(|p| response.draws_for_bracket(p.values(), tiles.step()));
        let alternatives = pixel_merge
            .as_ref()
            .map(|p| {
                response
                    .alternatives
                    .iter()
                    .map(|a| a.delta_at(p.values()))
                    .collect()
            })
            .unwrap_or_default();
        Readings {
            response,
            tiles,
            darks,
            pixel_merge,
            draws,
            alternatives,
        }
    }

    /// Radiance and variance of the pixels merged with `r` (RGB interleaved, or one sample
    /// a pixel).
    pub fn merge(&self, r: &crate::hdr::response::Response) -> Option<crate::hdr::merge::Merged> {
        let dark = crate::hdr::merge::dark_levels(r, &self.tiles, &self.darks);
        crate::hdr::merge::merge(r, &self.tiles, &dark).ok()
    }

    /// The pixels merged with one curve drawn from the response's uncertainty (its
    /// coefficients' covariance and its misfit; see
    /// [`crate::hdr::response::Response::draws_at`]), evaluated only at the values the
    /// pixels read: microseconds at any bit depth. None where there is nothing to draw.
    pub fn merge_drawn(
        &self,
        normal: &mut dyn FnMut() -> f64,
    ) -> Option<crate::hdr::merge::Merged> {
        let delta = self.draws.as_ref()?.draw(normal);
        Some(self.pixel_merge.as_ref()?.merge(&delta))
    }

    /// The pixels merged with each of the response's alternative curves (the other models
    /// that fit the bracket nearly as well; none where there are none).
    pub fn merge_alternatives(&self) -> Vec<crate::hdr::merge::Merged> {
        let Some(p) = self.pixel_merge.as_ref() else {
            return Vec::new();
        };
        self.alternatives.iter().map(|d| p.merge(d)).collect()
    }
}

impl Readings {
    /// For each sampled value (pixel-major, channels interleaved): how many different
    /// exposures of the bracket read it within the response's valid range.
    pub fn exposures_read(&self) -> Vec<usize> {
        let b = &self.tiles;
        let nc = b.channels;
        let rc = self.response.channels.len();
        if rc == 0 {
            return Vec::new();
        }
        let mut times = Vec::new();
        (0..b.width * b.height * nc)
            .map(|k| {
                let (p, c) = (k / nc, k % nc);
                let ch = &self.response.channels[c.min(rc - 1)];
                times.clear();
                for (j, f) in b.frames.iter().enumerate() {
                    let z = b.value(j, p, c);
                    if z >= ch.valid_min && z <= ch.valid_max {
                        times.push(f.exposure_us);
                    }
                }
                times.sort_by(f64::total_cmp);
                times.dedup_by(|a, b| (*a / *b - 1.0).abs() < 1e-6);
                times.len()
            })
            .collect()
    }

    /// A warning where most sampled values are read at one exposure only: there the
    /// response curve's error at that value goes into the radiance unaveraged (readings at
    /// two or three exposures sit at different places on the curve, whose errors partly
    /// cancel), and a broad lobe turns a 0.1% slope across the tile into several percent
    /// of n (on the simulated lab: n +7.1% on a scene read at one exposure, +2.4% with two
    /// shorter exposures added).
    pub fn one_exposure_warning(&self) -> Option<String> {
        let read = self.exposures_read();
        let measured: Vec<usize> = read.into_iter().filter(|n| *n > 0).collect();
        if measured.is_empty() {
            return None;
        }
        let one = measured.iter().filter(|n| **n == 1).count();
        let share = one as f64 / measured.len() as f64;
        if share <= ONE_EXPOSURE_SHARE {
            return None;
        }
        let shortest = self
            .tiles
            .frames
            .iter()
            .map(|f| f.exposure_us)
            .fold(f64::INFINITY, f64::min);
        Some(format!(
            "{:.0}% of the sampled values are read at one exposure of the bracket only, so the response curve's error at those values goes into the radiance unaveraged (and, on a broad lobe, into n and ks/kd several times over); add exposures one and two stops shorter than the shortest ({} µs), so that the tile is read at two or three",
            100.0 * share,
            crate::hdr::merge::show_us(shortest)
        ))
    }
}

/// Share of the sampled values read at one exposure only above which the fit says so. The
/// values read once are the tile's brightest, the highlight that n rests on: a third of
/// them is enough to matter.
pub const ONE_EXPOSURE_SHARE: f64 = 1.0 / 3.0;

/// The HDR response's uncertainty carried into the fit: curves drawn from the response's
/// uncertainty (a polynomial's coefficient covariance, and every curve's misfit to its data
/// beyond their noise), the sampled pixels merged again with each, the model refitted, the
/// spread of the refits; and the response's alternatives (other models' curves that fit the
/// bracket nearly as well, [`crate::hdr::response::Alternative`]): the model refitted with
/// each, and with k of them the chosen curve and each alternative taken as equally likely
/// right, the expected square of the change, sum of d d' / (k + 1), each change counted
/// only by what the draws do not already explain (`beyond_draws`). None where there is
/// nothing to draw and no alternative (a linear or Debevec curve that fits its data, and no
/// other model near it).
pub fn response_covariance(
    readings: &Readings,
    samples: &[Sample],
    model: Model,
    opts: &Options,
    draws: usize,
    seed: u64,
) -> Option<Vec<Vec<f64>>> {
    use rand_distr::{Distribution, StandardNormal};
    let spread = refit_spread(model, opts, draws, seed ^ 0x9e37_79b9, |rng| {
        let m = readings.merge_drawn(&mut || StandardNormal.sample(&mut *rng))?;
        Some(remerged(samples, &m))
    });
    let other = alternatives_covariance(readings, samples, model, opts, spread.as_ref());
    match (spread, other) {
        (Some(mut a), Some(b)) => {
            for (ra, rb) in a.iter_mut().zip(&b) {
                for (x, y) in ra.iter_mut().zip(rb) {
                    *x += y;
                }
            }
            Some(a)
        }
        (a, b) => a.or(b),
    }
}

/// The response's alternatives' part of [`response_covariance`]: None without any, or
/// where the model cannot be fitted to the samples as they are. Each change counts only
/// by what exceeds the chosen curve's own draws (`spread`, see [`beyond_draws`]): two
/// curves that both follow a well-determined bracket differ by their noise, which the
/// draws already hold.
fn alternatives_covariance(
    readings: &Readings,
    samples: &[Sample],
    model: Model,
    opts: &Options,
    spread: Option<&Vec<Vec<f64>>>,
) -> Option<Vec<Vec<f64>>> {
    let merged = readings.merge_alternatives();
    if merged.is_empty() {
        return None;
    }
    let base = fit(model, samples, opts).values();
    if !base.iter().all(|x| x.is_finite()) {
        return None;
    }
    let changes: Vec<[f64; 7]> = merged
        .iter()
        .map(|m| fit(model, &remerged(samples, m), opts).values())
        .filter(|v| v.iter().all(|x| x.is_finite()))
        .map(|v| {
            let d: [f64; 7] = std::array::from_fn(|i| v[i] - base[i]);
            let f = spread.map_or(1.0, |s| beyond_draws(&d, s)).sqrt();
            d.map(|x| f * x)
        })
        .collect();
    if changes.is_empty() {
        return None;
    }
    let w = 1.0 / (merged.len() + 1) as f64;
    Some(
        (0..7)
            .map(|i| {
                (0..7)
                    .map(|j| w * changes.iter().map(|d| d[i] * d[j]).sum::<f64>())
                    .collect()
            })
            .collect(),
    )
}

/// The share of a change `d` between two curves' fits that the chosen curve's draws
/// (covariance `spread`) do not already explain: with m = d' spread^-1 d (over the
/// directions the draws move, in their correlation's units) and r those directions, the
/// difference of two curves that differ only by such noise has m about 2 r; the share is
/// max(0, 1 - 2 r / m) (a positive-part shrinkage, as James and Stein's).
fn beyond_draws(d: &[f64; 7], spread: &[Vec<f64>]) -> f64 {
    let sd: Vec<f64> = (0..7)
        .map(|i| spread.get(i).and_then(|r| r.get(i)).copied().unwrap_or(0.0))
        .map(|v| {
            if v.is_finite() && v > 0.0 {
                v.sqrt()
            } else {
                0.0
            }
        })
        .collect();
    let idx: Vec<usize> = (0..7)
        .filter(|i| sd[*i] > 0.0 && d[*i].is_finite())
        .collect();
    let k = idx.len();
    if k == 0 {
        return 1.0;
    }
    let corr = nalgebra::DMatrix::from_fn(k, k, |a, b| {
        let (i, j) = (idx[a], idx[b]);
        spread[i][j] / (sd[i] * sd[j])
    });
    if !corr.iter().all(|x| x.is_finite()) {
        return 1.0;
    }
    let eig = nalgebra::SymmetricEigen::new(corr);
    let top = eig.eigenvalues.iter().copied().fold(0.0, f64::max);
    let (mut m, mut r) = (0.0, 0usize);
    for (a, l) in eig.eigenvalues.iter().enumerate() {
        if *l > 1e-9 * top {
            let proj: f64 = (0..k)
                .map(|b| eig.eigenvectors[(b, a)] * d[idx[b]] / sd[idx[b]])
                .sum();
            m += proj * proj / l;
            r += 1;
        }
    }
    if r == 0 || m <= 0.0 {
        return if r == 0 { 1.0 } else { 0.0 };
    }
    (1.0 - 2.0 * r as f64 / m).max(0.0)
}

/// `samples` with the radiance and variance of `m` (merged again at the same pixels, in
/// order) wherever it measured them.
fn remerged(samples: &[Sample], m: &crate::hdr::merge::Merged) -> Vec<Sample> {
    let nc = m.channels;
    samples
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let mut s = *s;
            for c in 0..nc {
                let k = nc * i + c;
                // (A channel the sample holds no value of, as a demosaicked camera's
                // interpolated ones, stays out.)
                if !s.censored[c] && s.variance[c].is_finite() && m.mask.get(k) == Some(&MASK_OK) {
                    s.radiance[c] = m.radiance[k] as f64;
                    s.variance[c] = m.variance[k] as f64;
                }
            }
            s
        })
        .collect()
}

/// Shares of a parameter's variance by source.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct UncertaintyShare {
    pub fit: f64,
    pub calibration: Option<f64>,
    pub response: Option<f64>,
}

/// The file `fit/fit.json`.
#[derive(Debug, Clone, Serialize)]
pub struct FitReport {
    pub format: String,
    pub format_version: u32,
    pub created: String,
    pub session: String,
    /// Channels fitted: 3 (kd, ks and ks_over_kd list R, G, B) or 1 (a monochrome camera:
    /// one value each).
    pub channels: usize,
    /// True for a monochrome camera (`channels` 1).
    pub mono: bool,
    pub sampling: Sampling,
    pub solver: SolverReport,
    pub candidates: Vec<Candidate>,
    pub chosen: Model,
    /// `absolute` (the rig's reference standard gave the factor that the lamp and the
    /// camera put on the radiance: each candidate's `absolute` holds kd and ks in 1/sr and
    /// the albedo) or `relative` (kd and ks carry that unknown factor; n and ks/kd are
    /// absolute either way).
    pub units: String,
    /// What the reference standard gave, where the rig has one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reference: Option<super::reference::ReferenceReport>,
    /// Held-out errors within this of the best count as equal.
    pub choice_tolerance: f64,
    pub warnings: Vec<String>,
    /// The camera refined with the highlight, where the pose was weak (see
    /// [`FitOptions::refine_weak_pose`]); the samples' geometry and every candidate are then
    /// at this camera, and `glint validate` renders with it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub camera_refined: Option<CameraRefined>,
    /// Which candidates explain the tile within its noise, and the remedies where none does.
    pub verdict: Verdict,
    pub files: Vec<String>,
    pub seconds: f64,
}

/// A candidate explains the tile when its held-out residuals are at most this many times
/// the noise (root mean squared standardised residual over the held-out samples). Not 1:
/// the noise model itself is known only to a few tens of percent on a real camera (the
/// response's slope, demosaicking, the lens's blur): on the second scene family's held-out
/// seeds the true model's misfit is within this in 75% of fits (median 1.4), on the
/// simulated lab's about 1.0 (docs/fitting.md, "Which candidates explain the tile").
pub const EXPLAINS_HELD_OUT_RMS: f64 = 2.0;

/// Which candidates explain the tile within its noise ([`EXPLAINS_HELD_OUT_RMS`]).
#[derive(Debug, Clone, Serialize)]
pub struct Verdict {
    pub explained_by: Vec<Model>,
    /// The candidate with the smallest held-out misfit, and that misfit in multiples of
    /// the noise.
    pub best: Model,
    pub best_held_out_rms: f64,
    /// Where none explains the tile: what would (named from what the fit found).
    pub remedies: Vec<String>,
}

/// A lobe's height and width trade off where the lobe keeps more than
/// [`BROAD_LOBE_FLOOR`] of its peak over every sample, or ks and n correlate beyond
/// this (in the fit's own covariance or with the calibration and response carried in).
pub const TRADE_OFF_CORRELATION: f64 = 0.97;

#[derive(Debug, Clone, Serialize)]
pub struct Sampling {
    /// What sampling found (the samples themselves go to samples.csv).
    #[serde(flatten)]
    pub sampled: Sampled,
    /// Samples in the fitting half and the held-out half (alternate samples).
    pub fitting_half: usize,
    pub held_out_half: usize,
}

#[derive(Debug, Clone, Serialize)]
pub struct SolverReport {
    pub method: String,
    pub n_range: [f64; 2],
    pub grey_ks: bool,
    pub huber: Option<f64>,
    pub variances: String,
    /// Uncertainties carried into every parameter's besides the fit's own.
    pub propagated: Vec<String>,
}

impl FitReport {
    /// The file `fit/fit.json` this report is written as.
    pub fn file(&self) -> file::FitFile {
        file::FitFile {
            format: self.format.clone(),
            format_version: Some(self.format_version),
            created: self.created.clone(),
            session: self.session.clone(),
            channels: self.channels,
            mono: self.mono,
            sampling: self.sampling.file(),
            solver: self.solver.file(),
            candidates: self.candidates.iter().map(Candidate::file).collect(),
            chosen: self.chosen.name().into(),
            units: Some(self.units.clone()),
            reference: self.reference.as_ref().map(|r| r.file()),
            choice_tolerance: finite(self.choice_tolerance),
            warnings: self.warnings.clone(),
            camera_refined: self.camera_refined.as_ref().map(CameraRefined::file),
            verdict: Some(self.verdict.file()),
            files: self.files.clone(),
            seconds: finite(self.seconds),
        }
    }
}

impl Sampling {
    /// As `fit/fit.json` holds it.
    fn file(&self) -> file::Sampling {
        use super::sample::{Saturated, Strategy};
        let s = &self.sampled;
        let h = &s.highlight;
        let pair = |p: [f64; 2]| p.map(finite);
        file::Sampling {
            strategy: match s.strategy {
                Strategy::Line => file::Strategy::Line,
                Strategy::Perpendicular => file::Strategy::Perpendicular,
                Strategy::Cross => file::Strategy::Cross,
                Strategy::UserLine(l) => file::Strategy::UserLine(l),
                Strategy::Rect => file::Strategy::Rect,
                Strategy::Random => file::Strategy::Random,
            },
            requested: s.requested,
            used: s.used,
            highlight: file::Highlight {
                centre_px: pair(h.centre_px),
                found_px: h.found_px.map(pair),
                predicted_px: pair(h.predicted_px),
                offset_px: finite(h.offset_px),
                saturated_pixels: h.saturated_pixels,
                saturated_at_highlight: h.saturated_at_highlight,
                mirror_on_tile: h.mirror_on_tile,
                found_near_mirror: h.found_near_mirror,
            },
            lines_px: s.lines_px.iter().map(|l| l.map(finite)).collect(),
            tile_pixels: s.tile_pixels,
            left_out_saturated: s.left_out_saturated,
            left_out_bloom: s.left_out_bloom,
            left_out_no_radiance: s.left_out_no_radiance,
            censored: s.censored,
            saturated: match s.saturated {
                Saturated::Exclude => file::Saturated::Exclude,
                Saturated::Censor => file::Saturated::Censor,
                Saturated::Clip => file::Saturated::Clip,
            },
            mosaic: s.mosaic.map(|m| m.name().to_string()),
            mosaic_source: s.mosaic_source.into(),
            mosaic_contrast: s.mosaic_detection.and_then(|d| finite(d.contrast)),
            warnings: s.warnings.clone(),
            fitting_half: self.fitting_half,
            held_out_half: self.held_out_half,
        }
    }
}

impl SolverReport {
    /// As `fit/fit.json` holds it.
    fn file(&self) -> file::Solver {
        file::Solver {
            method: self.method.clone(),
            n_range: self.n_range.map(finite),
            grey_ks: self.grey_ks,
            huber: self.huber.and_then(finite),
            variances: self.variances.clone(),
            propagated: self.propagated.clone(),
        }
    }
}

impl Candidate {
    /// As `fit/fit.json` holds it.
    pub fn file(&self) -> file::Candidate {
        let list = |p: &[Param]| p.iter().map(Param::file).collect();
        file::Candidate {
            model: self.model.name().into(),
            kd: list(&self.kd),
            ks: list(&self.ks),
            ks_over_kd: list(&self.ks_over_kd),
            n: Some(self.n.file()),
            alpha: self.alpha.as_ref().map(Param::file),
            chi2: finite(self.chi2),
            dof: self.dof,
            reduced_chi2: finite(self.reduced_chi2),
            bic: finite(self.bic),
            held_out: finite(self.held_out),
            parameters: self.parameters,
            inner_evaluations: self.inner_evaluations,
            polish_evaluations: self.polish_evaluations,
            polish_termination: Some(self.polish_termination),
            ks_n_correlation: finite(self.ks_n_correlation),
            n_variance_share: self.n_variance_share.map(|s| file::UncertaintyShare {
                fit: finite(s.fit),
                calibration: s.calibration.and_then(finite),
                response: s.response.and_then(finite),
            }),
            absolute: self.absolute.as_ref().map(|a| a.file()),
            covariance: Some(file::Covariance {
                parameters: self.covariance.parameters.clone(),
                matrix: self
                    .covariance
                    .matrix
                    .iter()
                    .map(|r| r.iter().map(|x| finite(*x)).collect())
                    .collect(),
            }),
            explains: Some(self.explains),
            trade_off: self.trade_off.clone(),
            warnings: self.warnings.clone(),
        }
    }
}

impl Verdict {
    /// As `fit/fit.json` holds it.
    fn file(&self) -> file::Verdict {
        file::Verdict {
            explained_by: self
                .explained_by
                .iter()
                .map(|m| m.name().to_string())
                .collect(),
            none_explains: self.explained_by.is_empty(),
            best: self.best.name().into(),
            best_held_out_rms: finite(self.best_held_out_rms),
            limit_rms: EXPLAINS_HELD_OUT_RMS,
            remedies: self.remedies.clone(),
        }
    }
}

impl CameraRefined {
    /// As `fit/fit.json` holds it.
    fn file(&self) -> file::CameraRefined {
        file::CameraRefined {
            intrinsics: (&self.intrinsics).into(),
            rvec: self.rvec,
            t: self.t,
            centre_mm: self.centre_mm,
            centre_before_mm: self.centre_before_mm.map(finite),
            moved_mm: finite(self.moved_mm),
            moved_sd: finite(self.moved_sd),
            chi2_before: finite(self.chi2_before),
            chi2: finite(self.chi2),
            n_before: finite(self.n_before),
            n_after: finite(self.n_after),
            tension: finite(self.tension),
        }
    }
}

fn file_err(path: &Path, reason: impl std::fmt::Display) -> FitError {
    FitError::File {
        path: path.into(),
        reason: reason.to_string(),
    }
}

/// Load what the fit needs from a session: its rig, calib/camera.json and hdr/. The
/// session must be complete.
pub fn load_inputs(dir: &Path) -> Result<Inputs, FitError> {
    load_inputs_allowing(dir, false)
}

/// Whether a derived file is there at all (a link on the way counts: reading it is then
/// refused).
fn present(file: &Within) -> bool {
    file.is_there()
}

/// [`load_inputs`], on a session that is not complete too if `allow_incomplete` (with a
/// warning in [`Inputs::warnings`]). Every derived file is read size-capped, as a regular
/// file, and checked: a file that is there but unusable is an error naming it, never
/// taken as missing.
pub fn load_inputs_allowing(dir: &Path, allow_incomplete: bool) -> Result<Inputs, FitError> {
    let m = session::open(dir, allow_incomplete)?;
    session::check_out_dir(&dir.join("fit"))?;
    let warnings: Vec<String> = session::incomplete_warning(&m).into_iter().collect();
    let rig = m.rig.as_ref().ok_or_else(|| {
        FitError::Input(format!(
            "{}: the session has no rig (an imported session), so the lamp and tile positions are unknown; capture with a rig file",
            dir.display()
        ))
    })?;
    let g = &rig.geometry;
    let cam_file = Within::new(dir, "calib/camera.json");
    let cam_path = cam_file.path();
    if !present(&cam_file) {
        return Err(file_err(
            &cam_path,
            format!(
                "missing: calibrate first (glint calibrate {})",
                dir.display()
            ),
        ));
    }
    let (v, cal) = crate::calib::run::load_camera_file(&cam_file).map_err(|e| match e {
        crate::calib::run::RunError::File { path, reason } => FitError::File { path, reason },
        other => FitError::Input(other.to_string()),
    })?;
    let view = cal
        .views
        .first()
        .ok_or_else(|| file_err(&cam_path, "has no view (pose); re-run glint calibrate"))?;
    if v.length_unit != "mm" {
        return Err(file_err(
            &cam_path,
            "its lengths are not in mm (calibrated without the square size), so it cannot be placed in the rig",
        ));
    }
    let hdr = dir.join("hdr");
    let rad_file = Within::new(dir, "hdr/radiance.exr");
    let rad_path = rad_file.path();
    if !present(&rad_file) {
        return Err(file_err(
            &rad_path,
            format!(
                "missing: merge the bracket first (glint hdr {})",
                dir.display()
            ),
        ));
    }
    let (w, h, radiance) =
        crate::hdr::files::read_exr(&rad_file).map_err(|e| FitError::Input(e.to_string()))?;
    let var_file = Within::new(dir, "hdr/variance.exr");
    let (w2, h2, variance) =
        crate::hdr::files::read_exr(&var_file).map_err(|e| FitError::Input(e.to_string()))?;
    // The radiance's channels must be the session's (a monochrome camera's are one, Y).
    let channels = m.channels() as usize;
    let got = |data: &[f32], w: usize, h: usize| data.len() / (w * h).max(1);
    if got(&radiance, w, h) != channels || got(&variance, w2, h2) != channels {
        return Err(FitError::Input(format!(
            "{}: the radiance has {} but the session's frames have {}; re-run glint hdr",
            hdr.display(),
            session::channels_name(got(&radiance, w, h) as u8),
            session::channels_name(channels as u8)
        )));
    }
    // One sample a pixel for a monochrome session (grey), else three (RGB).
    let mask = crate::hdr::files::read_mask(Within::new(dir, "hdr/mask.png"), w, h, channels)
        .map_err(|e| FitError::Input(e.to_string()))?;
    if (w2, h2) != (w, h) {
        return Err(FitError::Input(format!(
            "{}: radiance, variance and mask differ in size; re-run glint hdr",
            hdr.display()
        )));
    }
    if (cal.width, cal.height) != (w, h) {
        return Err(FitError::Input(format!(
            "the calibration is for {}x{} images but the radiance is {w}x{h}: calibrate this camera at this resolution",
            cal.width, cal.height
        )));
    }
    let resp_file = Within::new(dir, "hdr/response.json");
    let resp_path = resp_file.path();
    let response = if present(&resp_file) {
        Some(
            crate::hdr::files::load_response(&resp_file)
                .map_err(|e| FitError::Input(e.to_string()))?,
        )
    } else {
        None
    };
    if let Some(r) = &response {
        if r.channels.len() != channels {
            return Err(file_err(
                &resp_path,
                format!(
                    "is for frames of {} but the session's have {}; re-run glint hdr",
                    session::channels_name(r.channels.len() as u8),
                    session::channels_name(channels as u8)
                ),
            ));
        }
    }
    let saturation_level = match &response {
        Some(r) => saturation_level(dir, r)?,
        None => None,
    }
    .unwrap_or([f64::INFINITY; 3]);
    let pose = view.pose;
    let scene = Scene::new(
        cal.intrinsics.clone(),
        pose,
        g.lamp_position_mm,
        g.tile_thickness_mm,
        g.tile_outline_mm.clone(),
        [w, h],
    );
    Ok(Inputs {
        scene,
        width: w,
        height: h,
        channels,
        radiance,
        variance,
        mask,
        saturation_level,
        calibration: cal,
        response,
        warnings,
        reference: rig.reference.clone(),
        manifest: m,
    })
}

/// Read and check `hdr/summary.json` (size-capped, a regular file): JSON with
/// `exposures_us`, a list of positive finite times; the file's one type
/// ([`glint_format::stage::hdr::Summary`]). Errors name the file.
pub fn load_hdr_summary(file: &Within) -> Result<HdrSummary, SummaryError> {
    let path = file.path();
    let text = file
        .read(crate::fsx::MAX_TEXT_BYTES)
        .map_err(|e| SummaryError::Read {
            path: path.clone(),
            reason: e.to_string(),
        })?;
    let s: HdrSummary = serde_json::from_slice(&text).map_err(|e| SummaryError::NotJson {
        path: path.clone(),
        reason: crate::fsx::json_error(&e),
    })?;
    let ok = s.exposures_us.as_ref().is_some_and(|a| {
        !a.is_empty()
            && a.iter().all(|x| {
                x.is_some_and(|t| t.is_finite() && t > 0.0 && t <= session::MAX_EXPOSURE_US)
            })
    });
    if !ok {
        return Err(SummaryError::Exposures { path });
    }
    Ok(s)
}

/// The least radiance a value saturated in every exposure can stand for: the top of the
/// response's valid range in the shortest exposure (None without hdr/summary.json).
fn saturation_level(
    dir: &Path,
    r: &crate::hdr::response::Response,
) -> Result<Option<[f64; 3]>, FitError> {
    let file = Within::new(dir, "hdr/summary.json");
    if !present(&file) {
        return Ok(None);
    }
    let s = load_hdr_summary(&file)?;
    let t = s
        .exposures_us
        .iter()
        .flatten()
        .flatten()
        .fold(f64::INFINITY, |a, b| a.min(*b));
    if !t.is_finite() {
        return Ok(None);
    }
    // A monochrome response's one level; the unused channels' never matter.
    Ok(Some([0, 1, 2].map(|c| {
        if c < r.channels.len() {
            r.exposure(c, r.channels[c].valid_max as f64) / (t * 1e-6)
        } else {
            f64::INFINITY
        }
    })))
}

/// Every candidate fitted on all samples, with the held-out scores of the choice.
pub fn fit_candidates(
    models: &[Model],
    samples: &[Sample],
    opts: &Options,
) -> (Vec<Candidate>, Choice) {
    let (train, test) = halves(samples);
    let choice = choose(models, &train, &test, opts);
    let m = measured_values(samples);
    let candidates = choice
        .candidates
        .iter()
        .map(|sc| Candidate::new(fit(sc.fit.model, samples, opts), sc.held_out, m))
        .collect();
    (candidates, choice)
}

/// How much of its peak the fitted lobe keeps at the sample where it is weakest (the lobe's
/// shape alone: the lamp's falloff divided out), among samples the lobe reaches at all.
/// Near 1: the lobe is broader than the sampled region, so its width (n) and height (ks)
/// trade off against kd. NaN without a lobe.
pub fn lobe_floor(f: &ModelFit, samples: &[Sample]) -> f64 {
    lobe_floor_at(f, samples, f.n.value)
}

/// [`lobe_floor`] of the model's lobe at exponent `n` (the fit's own, or an end of its
/// interval).
fn lobe_floor_at(f: &ModelFit, samples: &[Sample], n: f64) -> f64 {
    if !f.model.has_lobe() || samples.is_empty() || !(n.is_finite() && n > 0.0) {
        return f64::NAN;
    }
    let shape: Vec<f64> = samples
        .iter()
        .map(|s| f.model.specular(&s.geometry, n).0 * s.geometry.d2)
        .collect();
    let peak = shape.iter().fold(0.0f64, |a, b| a.max(*b));
    if peak.is_nan() || peak <= 0.0 {
        return f64::NAN;
    }
    shape.iter().fold(1.0f64, |a, b| a.min(b / peak))
}

/// A lobe that keeps more than this share of its peak over every sample is broader than
/// the sampled region. On the mock tile with the default cross, a Blinn-Phong lobe keeps
/// 95% at n = 5 (n's interval ±12%, ks/kd trading off with kd), 73% at n = 30 and 31% at
/// n = 120 (both well determined).
pub const BROAD_LOBE_FLOOR: f64 = 0.8;

/// The calibration's share of ln n's variance above which the pose is said to dominate.
pub const WEAK_POSE_SHARE: f64 = 0.5;

/// n's relative standard deviation below which a pose that dominates it is not worth a
/// warning: its 95% interval is within about 2%, the accuracy a lens profile gives (the
/// pose dominates there too, but harmlessly).
pub const WEAK_POSE_N_SD: f64 = 0.01;

/// The report's warnings: what sampling found, the chosen model's own (its fit's), and
/// the causes of a weak fit, each named only where its evidence is in the data: a clipped
/// highlight (saturated pixels at the peak), samples that pass the highlight's centre by
/// more than a few pixels (they miss the peak), a lobe broader than the samples, a
/// highlight off the tile (from sampling), a tile with no highlight (Lambert chosen), a
/// pose that dominates n's uncertainty, and a ks-n trade-off with none of those.
/// Saturation is blamed only where something saturated.
pub fn report_warnings(
    sampled: &Sampled,
    samples: &[Sample],
    chosen: Option<&Candidate>,
    lens_held: bool,
) -> Vec<String> {
    report_warnings_pose(sampled, samples, chosen, None, lens_held)
}

/// [`report_warnings`], the weak-pose warning judged on `pose_from` where given (the
/// chosen candidate at the calibrated camera, before the highlight refined it).
fn report_warnings_pose(
    sampled: &Sampled,
    samples: &[Sample],
    chosen: Option<&Candidate>,
    pose_from: Option<&Candidate>,
    lens_held: bool,
) -> Vec<String> {
    let mut warnings: Vec<String> = sampled.warnings.clone();
    let h = &sampled.highlight;
    let mut cause = false;
    if h.saturated_at_highlight > 0 {
        cause = true;
        let fate = match sampled.saturated {
            super::sample::Saturated::Exclude => "left out",
            super::sample::Saturated::Censor => "kept as censored values",
            super::sample::Saturated::Clip => "kept as if measured (biased)",
        };
        warnings.push(format!(
            "the highlight is clipped: {} tile pixels at its peak are saturated in every exposure ({fate}), so the samples lack the peak and ks and n trade off (a higher, sharper lobe fits as well as a lower, broader one); add a shorter exposure to the bracket{}",
            h.saturated_at_highlight,
            if sampled.saturated == super::sample::Saturated::Exclude {
                ", or keep them as censored values (--saturated censor)"
            } else {
                ""
            }
        ));
    }
    if !h.mirror_on_tile {
        // Sampling's warning says it.
        cause = true;
    }
    let Some(c) = chosen else {
        return warnings;
    };
    for w in &c.warnings {
        warnings.push(format!("{}: {w}", c.model.name()));
    }
    let lobe = c.model.has_lobe();
    if !lobe && h.mirror_on_tile && !h.found_near_mirror && h.saturated_at_highlight == 0 {
        cause = true;
        warnings.push(format!(
            "no highlight: the radiance does not peak at the mirror point and the chosen model, {}, has no lobe; the tile looks matte",
            c.model.name()
        ));
    }
    // Samples that pass the highlight's centre by more than a few pixels see only its flank.
    let near_px = (0.05 * (sampled.tile_pixels as f64).sqrt()).max(3.0);
    let nearest = sampled
        .samples
        .iter()
        .map(|p| (p.u as f64 - h.centre_px[0]).hypot(p.v as f64 - h.centre_px[1]))
        .fold(f64::INFINITY, f64::min);
    // (A clipped peak has no samples for its own reason, named above.)
    let missed = lobe && h.mirror_on_tile && h.saturated_at_highlight == 0 && nearest > near_px;
    if missed {
        cause = true;
        warnings.push(format!(
            "the samples miss the peak: the nearest passes {nearest:.0} px from the highlight's centre ({:.0}, {:.0}) px, so they see only its flank and ks and n trade off; sample through the highlight (the default cross does)",
            h.centre_px[0], h.centre_px[1]
        ));
    }
    let floor = lobe_floor(&c.fit, samples);
    if lobe && !missed && floor > BROAD_LOBE_FLOOR {
        cause = true;
        warnings.push(format!(
            "the lobe is broader than the sampled region: at the samples' edge it is still {:.0}% of its peak (n = {:.3}), so n, ks and kd trade off (n's 95% interval {:.3}..{:.3}); sample more of the tile (--strategy rect) or frame more of it",
            100.0 * floor,
            c.n.value,
            c.n.ci95[0],
            c.n.ci95[1]
        ));
    }
    let pc = pose_from.unwrap_or(c);
    if let Some(share) = pc.n_variance_share.and_then(|s| s.calibration) {
        let rel = pc.n.sd / pc.n.value;
        if weak_pose(pc) {
            let fix = if lens_held {
                "the lens is held, so the grid photo alone is weak: frame the grid larger in the image, seen less obliquely, or use a higher resolution"
            } else {
                "calibrate with the grid filling more of the image, seen less obliquely, or hold the lens with a lens profile (glint lens --rig RIG), so that the grid photo fits only the pose"
            };
            warnings.push(format!(
                "the calibration dominates n's uncertainty{} ({:.0}% of its variance, n ± {:.1}%): the camera's pose is weakly determined; {fix}",
                if pose_from.is_some() {
                    " at the grid photo's camera"
                } else {
                    ""
                },
                100.0 * share,
                100.0 * rel
            ));
        }
    }
    if lobe && c.ks_n_correlation.abs() > 0.97 && !cause {
        warnings.push(format!(
            "ks and n trade off (correlation {:.3}) although nothing saturated at the highlight, it is on the tile, sampled through, and the lobe narrower than the samples: more samples at the peak (--strategy rect) or less noise would separate them",
            c.ks_n_correlation
        ));
    }
    warnings
}

/// Mark every candidate with a lobe whose height and width the samples do not separate:
/// the lobe keeps more than [`BROAD_LOBE_FLOOR`] of its peak over every sample (it is
/// broader than the sampled region), or ks and n correlate beyond
/// [`TRADE_OFF_CORRELATION`]. One rule for every model, so that each interval says so
/// where it holds (the chosen model's warnings also name the cause).
pub fn mark_trade_offs(candidates: &mut [Candidate], samples: &[Sample]) {
    for c in candidates.iter_mut().filter(|c| c.model.has_lobe()) {
        let floor = lobe_floor(&c.fit, samples);
        // The broadest lobe n's interval allows: where it keeps more than
        // BROAD_LOBE_FLOOR of its peak over every sample, kd and ks are told apart there
        // only by a few percent of shape across the tile, which any error of the radiance's
        // shape (the response's, the pixel's footprint, the lamp's emission) overturns.
        let low_floor = lobe_floor_at(&c.fit, samples, c.n.ci95[0]);
        if low_floor > BROAD_LOBE_FLOOR {
            open_ratio_above(c);
        }
        // The samples' own evidence (the fit's covariance before the calibration's and
        // the response's are added) or the total, whichever correlates more.
        let r = if c.fit.own_ks_n_correlation.abs() >= c.ks_n_correlation.abs() {
            c.fit.own_ks_n_correlation
        } else {
            c.ks_n_correlation
        };
        c.trade_off = if floor > BROAD_LOBE_FLOOR {
            Some(format!(
                "the lobe keeps {:.0}% of its peak over every sample (broader than the sampled region), so its height (ks) and width (n) trade off (correlation {r:.3})",
                100.0 * floor
            ))
        } else if low_floor > BROAD_LOBE_FLOOR {
            Some(format!(
                "at the low end of n's interval ({:.3}) the lobe keeps {:.0}% of its peak over every sample (broader than the sampled region), so its height (ks) and width (n) trade off with kd, and ks/kd is open above (correlation {r:.3})",
                c.n.ci95[0],
                100.0 * low_floor
            ))
        } else if r.abs() > TRADE_OFF_CORRELATION {
            Some(format!(
                "ks and n correlate ({r:.3}): the samples do not separate the lobe's height from its width"
            ))
        } else {
            None
        };
    }
}

/// ks / kd's interval open above (no sd) in every channel: where n's interval reaches a
/// lobe broader than the sampled region, the samples do not bound how much of the tile's
/// radiance the lobe holds rather than kd. On a second-family scene (a cosine lobe, n 12.8,
/// the samples' r.v over 0.991..1) n's interval was 11.8..367 and ks / kd 0..0.53 against
/// the truth's 1.24: refitted at the true n to the true radiance, the same samples gave 0.40,
/// the lobe varying 10% over them.
fn open_ratio_above(c: &mut Candidate) {
    for r in c.ks_over_kd.iter_mut() {
        if r.value.is_nan() {
            continue;
        }
        r.ci95[1] = f64::INFINITY;
        r.sd = f64::INFINITY;
    }
}

/// Which candidates explain the tile within its noise; where none does, the remedies the
/// fit's findings point to (`warnings`: what sampling and the fit said).
pub fn verdict(candidates: &[Candidate], sampled: &Sampled, warnings: &[String]) -> Verdict {
    let explained_by: Vec<Model> = candidates
        .iter()
        .filter(|c| c.explains)
        .map(|c| c.model)
        .collect();
    let best = candidates
        .iter()
        .filter(|c| c.held_out.is_finite())
        .min_by(|a, b| a.held_out.total_cmp(&b.held_out));
    let (best, best_held_out_rms) = match best {
        Some(c) => (c.model, c.held_out_rms()),
        None => (
            candidates.first().map_or(Model::Lambert, |c| c.model),
            f64::NAN,
        ),
    };
    let mut remedies = Vec::new();
    if explained_by.is_empty() {
        let said = |s: &str| warnings.iter().any(|w| w.contains(s));
        if said("read at one exposure") || sampled.highlight.saturated_at_highlight > 0 {
            remedies.push("a longer bracket: exposures shorter than the shortest, so that the highlight is read unclipped at two or three".into());
        }
        if sampled.strategy != super::sample::Strategy::Rect {
            remedies.push("rect sampling (glint fit --strategy rect): samples over the whole tile see more of the lobe's flanks".into());
        }
        remedies.push("more lamp positions: one lamp gives each pixel one pair of directions, and several see the lobe over more half-angles, where the candidates differ".into());
        remedies.push("where fit/samples.csv shows a few outliers (dust, a scratch), a robust fit: glint fit --huber 1.345".into());
    }
    Verdict {
        explained_by,
        best,
        best_held_out_rms,
        remedies,
    }
}

impl Verdict {
    /// The first screen's line: which candidates explain the tile, or that none does and
    /// what to do.
    pub fn line(&self, candidates: &[Candidate]) -> String {
        let rms = |m: Model| {
            candidates
                .iter()
                .find(|c| c.model == m)
                .map_or(f64::NAN, Candidate::held_out_rms)
        };
        if self.explained_by.is_empty() {
            format!(
                "no candidate explains the tile within its noise: the best, {}, leaves held-out residuals {:.1} times the noise (limit {EXPLAINS_HELD_OUT_RMS}); the tile's reflectance is outside the candidates, light other than the lamp's reaches it, or the noise is underestimated; try {}",
                self.best.name(),
                self.best_held_out_rms,
                self.remedies.join("; or ")
            )
        } else {
            let not: Vec<String> = candidates
                .iter()
                .filter(|c| !c.explains)
                .map(|c| format!("{} {:.1}x", c.model.name(), c.held_out_rms()))
                .collect();
            format!(
                "explain the tile within its noise (held-out residuals at most {EXPLAINS_HELD_OUT_RMS} times it): {}{}",
                self.explained_by
                    .iter()
                    .map(|m| format!("{} {:.2}x", m.name(), rms(*m)))
                    .collect::<Vec<_>>()
                    .join(", "),
                if not.is_empty() {
                    format!("; not: {}", not.join(", "))
                } else {
                    String::new()
                }
            )
        }
    }
}

/// What the fit of every candidate gives, with the calibration's and the response's
/// uncertainty carried in.
struct Fitted {
    candidates: Vec<Candidate>,
    choice: Choice,
    propagated: Vec<String>,
    /// Why the camera's uncertainty is in no interval, where it is not.
    undetermined_camera: Option<UndeterminedCamera>,
}

/// Fit every candidate to `samples` (at `pixels`) and carry in the calibration's
/// uncertainty (the camera drawn from the calibration, or, given `camera_draws`, about a
/// refined camera with what uncertainty the highlight left it: see
/// [`calibration_covariance`]) and the
/// response's (`readings` merged again with drawn curves).
fn fit_with_draws(
    inputs: &Inputs,
    readings: Option<&Readings>,
    pixels: &[(usize, usize)],
    samples: &[Sample],
    opts: &FitOptions,
    camera_draws: Option<&super::pose::CameraDraws>,
) -> Fitted {
    let (mut candidates, choice) = fit_candidates(&opts.models, samples, &opts.solver);
    let mut propagated = Vec::new();
    let mut undetermined_camera = None;
    if opts.draws > 0 {
        let mut no_response = false;
        let mut undetermined = false;
        for c in candidates.iter_mut() {
            let cal = calibration_covariance(
                inputs,
                pixels,
                samples,
                c.model,
                &opts.solver,
                opts.draws,
                opts.sample.seed,
                camera_draws,
            );
            undetermined |= cal.is_none() && c.model.has_lobe();
            let resp = readings.and_then(|r| {
                response_covariance(
                    r,
                    samples,
                    c.model,
                    &opts.solver,
                    opts.draws,
                    opts.sample.seed,
                )
            });
            no_response |= resp.is_none();
            let mut f = c.fit.clone();
            let own = f.covariance[6][6];
            let mut shares = [None, None];
            for (k, extra) in [cal, resp].into_iter().enumerate() {
                if let Some(extra) = extra {
                    f.add_covariance(&extra);
                    shares[k] = Some(extra[6][6]);
                }
            }
            f.follow_n_interval(samples, &opts.solver);
            let total = f.covariance[6][6];
            // A source whose variance is unbounded (a camera the grid photo does not
            // determine) is all of it.
            let ratio = |x: f64| {
                if x.is_infinite() {
                    1.0
                } else if total.is_infinite() {
                    0.0
                } else {
                    x / total
                }
            };
            let share = |x: Option<f64>| x.filter(|_| f.model.has_lobe() && total > 0.0).map(ratio);
            let n_share = UncertaintyShare {
                fit: if f.model.has_lobe() && total > 0.0 {
                    ratio(own)
                } else {
                    f64::NAN
                },
                calibration: share(shares[0]),
                response: share(shares[1]),
            };
            *c = Candidate::new(f, c.held_out, measured_values(samples));
            c.n_variance_share = Some(n_share);
        }
        undetermined_camera = undetermined.then(|| UndeterminedCamera::of(inputs));
        if let Some(u) = undetermined_camera {
            propagated.push(u.propagated().into());
        } else if camera_draws.is_some() {
            propagated.push(format!(
                "calibration as the highlight refined it ({} draws of the camera about the refined one, from the joint fit's covariance widened by the tension)",
                opts.draws
            ));
        } else {
            propagated.push(format!("calibration ({} draws of the camera)", opts.draws));
        }
        if no_response {
            propagated.push("not the response curve's (it has neither a stored covariance nor a misfit beyond its noise: a curve that fits its data, or one recovered before Glint stored them)".into());
        } else {
            let others: Vec<&str> = readings
                .map(|r| {
                    r.response
                        .alternatives
                        .iter()
                        .map(|a| a.model.as_str())
                        .collect()
                })
                .unwrap_or_default();
            let also = if others.is_empty() {
                String::new()
            } else {
                format!(
                    "; and refitted with the other curves that fit the bracket nearly as well ({}), what they disagree on added",
                    others.join(", ")
                )
            };
            propagated.push(format!(
                "response curve ({} draws, the sampled pixels merged again{also})",
                opts.draws
            ));
        }
    }
    Fitted {
        candidates,
        choice,
        propagated,
        undetermined_camera,
    }
}

/// The camera refined with the highlight where the grid photo left the pose weak
/// ([`FitOptions::refine_weak_pose`]).
#[derive(Debug, Clone, Serialize)]
pub struct CameraRefined {
    /// The refined camera: intrinsics, and the view's pose (grid to camera: Rodrigues
    /// vector, translation in mm).
    pub intrinsics: crate::calib::camera::Intrinsics,
    pub rvec: [f64; 3],
    pub t: [f64; 3],
    /// Camera centre after and before, grid mm, and how far it moved (mm, and in the
    /// calibration's own standard deviations).
    pub centre_mm: [f64; 3],
    pub centre_before_mm: [f64; 3],
    pub moved_mm: f64,
    pub moved_sd: f64,
    /// The tile's chi2 at the calibrated and at the refined camera (with the model fitted
    /// at each).
    pub chi2_before: f64,
    pub chi2: f64,
    /// The chosen model's n at the calibrated camera and at the refined one.
    pub n_before: f64,
    pub n_after: f64,
    /// How far the camera moved against how far the grid photo's and the highlight's
    /// stated uncertainties expect (about 1 when they agree; above 1, the camera's
    /// remaining covariance is widened by it).
    pub tension: f64,
}

/// Whether the calibration dominates a candidate's n (the weak-pose warning's test; a NaN
/// sd counts as large).
fn weak_pose(c: &Candidate) -> bool {
    let Some(share) = c.n_variance_share.and_then(|s| s.calibration) else {
        return false;
    };
    let rel = c.n.sd / c.n.value;
    c.model.has_lobe() && share > WEAK_POSE_SHARE && (rel.is_nan() || rel > WEAK_POSE_N_SD)
}

/// A fit again at the camera refined with the highlight.
struct Refit {
    fitted: Fitted,
    samples: Vec<Sample>,
    camera: CameraRefined,
    /// The chosen candidate at the calibrated camera.
    before: Candidate,
}

/// Where the grid photo leaves the pose weak (see [`FitOptions::refine_weak_pose`]): the
/// camera refined with the highlight and every candidate fitted again there; None where
/// the pose is not weak or the refinement does not lower the tile's chi2.
fn refit_at_refined_camera(
    inputs: &Inputs,
    readings: Option<&Readings>,
    pixels: &[(usize, usize)],
    samples: &[Sample],
    fitted: &Fitted,
    opts: &FitOptions,
) -> Option<Refit> {
    if !(opts.refine_weak_pose && opts.draws > 0) {
        return None;
    }
    let c = fitted
        .candidates
        .iter()
        .find(|c| c.model == fitted.choice.chosen)
        .filter(|c| weak_pose(c))?;
    let r = super::pose::refine(
        &inputs.scene,
        &inputs.calibration,
        pixels,
        samples,
        &c.fit,
        &opts.solver,
    )
    .filter(|r| r.samples.len() == samples.len() && r.chi2 < r.chi2_before)?;
    let again = fit_with_draws(inputs, readings, pixels, &r.samples, opts, Some(&r.draws));
    let n_after = again
        .candidates
        .iter()
        .find(|c| c.model == again.choice.chosen)
        .map_or(f64::NAN, |c| c.n.value);
    let camera = CameraRefined {
        intrinsics: r.intrinsics.clone(),
        rvec: r.pose.rvec,
        t: r.pose.t,
        centre_mm: r.centre,
        centre_before_mm: r.centre_before,
        moved_mm: (nalgebra::Vector3::from(r.centre) - nalgebra::Vector3::from(r.centre_before))
            .norm(),
        moved_sd: r.prior_distance,
        chi2_before: r.chi2_before,
        chi2: r.chi2,
        n_before: c.n.value,
        n_after,
        tension: r.tension,
    };
    Some(Refit {
        fitted: again,
        samples: r.samples.clone(),
        camera,
        before: c.clone(),
    })
}

/// The candidates' derived values: the microfacet model's α from n, every candidate's
/// absolute values where a reference standard gave the factor, and the microfacet model's
/// warning where F0 is far from the shape its Fresnel term assumes.
fn finish_candidates(
    candidates: &mut [Candidate],
    reference: Option<&super::reference::ReferenceReport>,
) {
    for c in candidates.iter_mut().filter(|c| c.model == Model::Ggx) {
        use super::model::ggx::alpha;
        let n = &c.n;
        c.alpha = Some(Param {
            value: alpha(n.value),
            sd: alpha(n.value) / (2.0 * (n.value + 2.0)) * n.sd,
            ci95: [alpha(n.ci95[1]), alpha(n.ci95[0])],
        });
    }
    if let Some(r) = reference {
        for c in candidates.iter_mut() {
            c.absolute = Some(super::reference::absolute(&c.kd, &c.ks, c.model, r));
        }
    }
    // The microfacet model shapes Schlick's growth with F0 = F0_SHAPE; a tile far from it
    // keeps a bias its intervals leave out (README, "A broad lobe needs the angles").
    for c in candidates.iter_mut().filter(|c| c.model == Model::Ggx) {
        use super::model::ggx::F0_SHAPE;
        let f0 = c.absolute.as_ref().and_then(|a| {
            let v: Vec<f64> =
                a.f0.iter()
                    .map(|p| p.value)
                    .filter(|v| v.is_finite())
                    .collect();
            (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
        });
        if let Some(f0) = f0.filter(|f| !(0.5 * F0_SHAPE..=2.0 * F0_SHAPE).contains(f)) {
            c.warnings.push(format!(
                "F0 comes out {f0:.3}, but the model shapes Fresnel's growth towards grazing angles for F0 = {F0_SHAPE} (a dielectric): this far from it α and F0 carry a bias their intervals leave out (noise-free, at F0 0.10: F0 about -13%, α -3%)"
            ));
        }
    }
}

/// Why the camera's uncertainty could not be carried into the intervals: a calibration
/// without a bounded covariance, or a model that cannot be refitted at most of the cameras
/// drawn from one (second family seed 14044: a camera 0.15 mm from the truth, a fit whose
/// held-out residuals were 15 000 times the noise, and a warning that blamed the
/// calibration).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum UndeterminedCamera {
    NoCovariance,
    RefitsFail,
}

impl UndeterminedCamera {
    /// The cause, for a fit whose calibration covariance came out None: whether the
    /// calibration gives the camera a bounded covariance to draw from
    /// ([`super::pose::Camera::new`]).
    fn of(inputs: &Inputs) -> Self {
        if super::pose::Camera::new(&inputs.calibration, &inputs.scene).is_some() {
            UndeterminedCamera::RefitsFail
        } else {
            UndeterminedCamera::NoCovariance
        }
    }

    /// What `solver.propagated` says instead of the calibration's draws.
    fn propagated(self) -> &'static str {
        match self {
            UndeterminedCamera::NoCovariance => {
                "not the calibration's (its covariance is missing or unbounded)"
            }
            UndeterminedCamera::RefitsFail => {
                "not the calibration's (the model could not be refitted at most of the cameras drawn from it)"
            }
        }
    }

    /// The fit's warning.
    fn warning(self) -> &'static str {
        match self {
            UndeterminedCamera::NoCovariance => {
                "the calibration does not determine the camera (its covariance is missing or unbounded), so no interval here includes the camera's uncertainty: treat n and ks/kd as unknown; hold the lens with a lens profile (glint lens --rig RIG) so that the grid photo fits only the pose"
            }
            UndeterminedCamera::RefitsFail => {
                "the model could not be refitted at most of the cameras drawn from the calibration's uncertainty (the fit fails there, not the calibration: see whether any candidate explains the tile), so no interval here includes the camera's uncertainty: treat n and ks/kd as unknown"
            }
        }
    }
}

/// The fit's warnings: the inputs', an albedo above 1, a camera the calibration does not
/// determine, the pose's and the highlight's, one exposure, a refined camera.
#[allow(clippy::too_many_arguments)]
fn run_warnings(
    inputs: &Inputs,
    sampled: &Sampled,
    samples: &[Sample],
    candidates: &[Candidate],
    chosen: Model,
    weak_before: Option<&Candidate>,
    undetermined_camera: Option<UndeterminedCamera>,
    one_exposure: Option<String>,
    camera_refined: Option<&CameraRefined>,
) -> Vec<String> {
    let mut warnings = inputs.warnings.clone();
    // A passive surface reflects at most what falls on it.
    if let Some(a) = candidates
        .iter()
        .find(|c| c.model == chosen)
        .and_then(|c| c.absolute.as_ref())
    {
        if let Some((c, p)) = a.albedo.iter().enumerate().find(|(_, p)| p.ci95[0] > 1.0) {
            warnings.push(format!(
                "the diffuse albedo comes out {:.3} (channel {}), above 1, which no passive surface reflects: check reference.reflectance against the standard's certificate, and that the lamp lights the standard as it does the tile (no shadow, no stray light on the tile)",
                p.value,
                crate::hdr::response::channel_name(inputs.channels, c)
            ));
        }
    }
    if let Some(u) = undetermined_camera {
        warnings.push(u.warning().into());
    }
    warnings.extend(report_warnings_pose(
        sampled,
        samples,
        candidates.iter().find(|c| c.model == chosen),
        weak_before,
        !inputs.calibration.fit.focal,
    ));
    warnings.extend(one_exposure);
    if let Some(c) = camera_refined {
        warnings.push(format!(
            "the camera was refined with the highlight, the grid photo alone leaving the pose weak: its centre moved {:.2} mm ({:.1} of the calibration's standard deviations) and n went from {:.4} to {:.4}; the intervals carry the camera's uncertainty the highlight leaves{} (glint fit --keep-camera does not refine; a lens profile makes the pose strong)",
            c.moved_mm,
            c.moved_sd,
            c.n_before,
            c.n_after,
            if c.tension > 1.0 {
                format!(
                    ", widened {:.1}x because the highlight and the grid photo disagree by more than their uncertainties allow (tension {:.1})",
                    c.tension.sqrt(),
                    c.tension
                )
            } else {
                String::new()
            }
        ));
    }
    warnings
}

impl SolverReport {
    /// How the solver was set, and the uncertainties carried in.
    fn of(solver: &Options, propagated: Vec<String>) -> Self {
        SolverReport {
            method: if solver.start.is_some() {
                "levenberg-marquardt from the given start values".into()
            } else {
                "variable projection (closed-form kd, ks; log scan and golden search of n), then Levenberg-Marquardt".into()
            },
            n_range: [solver.n_min, solver.n_max],
            grey_ks: solver.grey_ks,
            huber: solver.huber,
            propagated,
            variances: if solver.variances_known {
                "from the HDR stage".into()
            } else {
                "estimated from the residuals".into()
            },
        }
    }
}

/// `glint fit SESSION`.
/// The report holds the samples too (`report.sampling.sampled.samples`).
pub fn run(dir: &Path, opts: &FitOptions) -> Result<FitReport, FitError> {
    let start = Instant::now();
    let inputs = load_inputs_allowing(dir, opts.allow_incomplete)?;
    // Absolute units from the reference standard, where the rig has one (measured first:
    // a standard the photos do not show stops the fit before its work).
    let reference = match &inputs.reference {
        Some(r) => Some(super::reference::measure(&inputs, r)?),
        None => None,
    };
    let mut sopts = opts.sample.clone();
    sopts.saturation_level = inputs.saturation_level;
    let mut sampled = sample(&inputs.scene, &inputs.image(), &sopts)?;
    let mut samples: Vec<Sample> = sampled.samples.iter().map(|s| s.sample).collect();
    // A monochrome session's samples hold one channel: one kd, one ks and n.
    let mut opts = opts.clone();
    opts.solver.channels = inputs.channels;
    let opts = &opts;
    let pixels: Vec<(usize, usize)> = sampled.samples.iter().map(|s| (s.u, s.v)).collect();
    let readings = if opts.draws > 0 {
        inputs
            .response
            .clone()
            .and_then(|r| Readings::load(dir, &pixels, r).ok())
    } else {
        None
    };
    let one_exposure = readings.as_ref().and_then(Readings::one_exposure_warning);
    let mut fitted = fit_with_draws(&inputs, readings.as_ref(), &pixels, &samples, opts, None);
    // A weak pose (the grid photo leaves n's uncertainty mostly the camera's): the camera
    // refined with the highlight, and everything fitted again there (see `refine_weak_pose`).
    let mut camera_refined = None;
    // The chosen candidate at the calibrated camera, where the camera was refined: the
    // weak-pose warning speaks of the grid photo.
    let mut weak_before: Option<Candidate> = None;
    if let Some(r) =
        refit_at_refined_camera(&inputs, readings.as_ref(), &pixels, &samples, &fitted, opts)
    {
        for (p, x) in sampled.samples.iter_mut().zip(&r.samples) {
            p.sample = *x;
        }
        samples = r.samples;
        fitted = r.fitted;
        camera_refined = Some(r.camera);
        weak_before = Some(r.before);
    }
    let Fitted {
        mut candidates,
        choice,
        propagated,
        undetermined_camera,
    } = fitted;
    finish_candidates(&mut candidates, reference.as_ref());
    mark_trade_offs(&mut candidates, &samples);
    let mut warnings = run_warnings(
        &inputs,
        &sampled,
        &samples,
        &candidates,
        choice.chosen,
        weak_before.as_ref(),
        undetermined_camera,
        one_exposure,
        camera_refined.as_ref(),
    );
    let verdict = verdict(&candidates, &sampled, &warnings);
    if verdict.explained_by.is_empty() {
        warnings.push(verdict.line(&candidates));
    }
    let out = dir.join("fit");
    session::out_dir(&out)?;
    let chosen = candidates
        .iter()
        .find(|c| c.model == choice.chosen)
        .map(|c| &c.fit);
    session::write_replace(
        &out.join("samples.csv"),
        samples_csv_channels(&sampled, chosen, inputs.channels).as_bytes(),
    )?;
    let fitting = fitting_half(&samples).iter().filter(|h| **h).count();
    let report = FitReport {
        format: FORMAT.into(),
        format_version: FORMAT_VERSION,
        created: session::timestamp(std::time::SystemTime::now()),
        session: dir.display().to_string(),
        channels: inputs.channels,
        mono: inputs.channels == 1,
        sampling: Sampling {
            sampled,
            fitting_half: fitting,
            held_out_half: samples.len() - fitting,
        },
        solver: SolverReport::of(&opts.solver, propagated),
        candidates,
        chosen: choice.chosen,
        units: if reference.is_some() {
            "absolute"
        } else {
            "relative"
        }
        .into(),
        reference,
        choice_tolerance: choice.tolerance,
        warnings,
        camera_refined,
        verdict,
        files: vec!["fit/samples.csv".into(), "fit/fit.json".into()],
        seconds: start.elapsed().as_secs_f64(),
    };
    let json = serde_json::to_vec_pretty(&report.file()).expect("report serialises");
    session::write_replace(&out.join("fit.json"), &json)?;
    Ok(report)
}

/// The samples as CSV: pixel, tile point, geometry, radiance and variance, and the chosen
/// model's prediction.
pub fn samples_csv(s: &Sampled, chosen: Option<&ModelFit>) -> String {
    samples_csv_channels(s, chosen, 3)
}

/// [`samples_csv`] for samples of `channels` (3: R, G, B columns; 1: a monochrome
/// camera's, with Y columns: radiance_y, variance_y, censored_y, predicted_y).
pub fn samples_csv_channels(s: &Sampled, chosen: Option<&ModelFit>, channels: usize) -> String {
    let names: &[&str] = if channels == 1 {
        &["y"]
    } else {
        &["r", "g", "b"]
    };
    let mut out = String::from(
        "u,v,x_mm,y_mm,along_mm,half,cos_l,r_dot_v,n_dot_h,cos_v,v_dot_h,lamp_distance_mm",
    );
    for column in ["radiance", "variance", "censored", "predicted"] {
        for n in names {
            out.push_str(&format!(",{column}_{n}"));
        }
    }
    out.push('\n');
    let half = fitting_half(&s.samples.iter().map(|p| p.sample).collect::<Vec<_>>());
    for (p, fitting) in s.samples.iter().zip(half) {
        let g = &p.sample.geometry;
        out.push_str(&format!(
            "{},{},{:.4},{:.4},{:.4},{},{:.9},{:.9},{:.9},{:.9},{:.9},{:.4}",
            p.u,
            p.v,
            p.point[0],
            p.point[1],
            p.along_mm,
            if fitting { "fit" } else { "held-out" },
            g.cos_l,
            g.r_dot_v,
            g.n_dot_h,
            g.cos_v,
            g.v_dot_h,
            g.d2.sqrt(),
        ));
        let c = 0..names.len();
        c.clone()
            .for_each(|c| out.push_str(&format!(",{:.6e}", p.sample.radiance[c])));
        c.clone()
            .for_each(|c| out.push_str(&format!(",{:.6e}", p.sample.variance[c])));
        c.clone()
            .for_each(|c| out.push_str(&format!(",{}", p.sample.censored[c] as u8)));
        c.for_each(|c| {
            let pred = chosen.map_or(f64::NAN, |f| f.predict(g, c));
            out.push_str(&format!(",{pred:.6e}"))
        });
        out.push('\n');
    }
    out
}
