//! The camera refined with the tile itself.
//!
//! The highlight's position and shape on the tile depend on where the camera is: a 1 mm
//! error in the camera centre moves a fitted n by 13–18% (docs/design.md, "Where the errors
//! come from"), and a single grid photo leaves the centre uncertain by about that much along the line of
//! sight. The highlight is a second measurement of the same geometry. Here the camera (the
//! calibration's fitted intrinsics and the view's pose) and the reflectance are fitted
//! together: the tile's radiance residuals, weighted by their variances, plus the
//! calibration as a Gaussian prior (its covariance), minimised by Levenberg–Marquardt from
//! the calibrated camera and the ordinary fit. The prior is whitened (the camera is
//! x0 + L z with L L^T the calibration's covariance and z ~ N(0, I)), so the problem is
//! well scaled whatever the units of its parameters.
//!
//! The joint problem's (J^T J)^-1 holds both the noise and what remains of the camera's
//! uncertainty once the highlight has constrained it. `glint fit` draws cameras from that
//! remaining uncertainty ([`Refined::draws`]), widened where the grid photo and the
//! highlight disagree beyond what they state ([`Refined::tension`]), in place of the
//! camera drawn from the calibration alone.

use nalgebra::{DMatrix, DVector};

use super::geometry::Scene;
use super::model::{Model, Reflectance};
use super::solve::{ModelFit, Options, Sample};
use crate::calib::camera::{Intrinsics, Pose};
use crate::calib::solve::Calibration;

/// The camera and the fit after refinement.
#[derive(Debug, Clone)]
pub struct Refined {
    /// The fit at the refined camera, its covariance from the joint problem.
    pub fit: ModelFit,
    pub intrinsics: Intrinsics,
    pub pose: Pose,
    /// Camera centre before and after, grid mm.
    pub centre_before: [f64; 3],
    pub centre: [f64; 3],
    /// Standard deviation of the refined centre per axis, mm.
    pub centre_sd: [f64; 3],
    /// How far the refinement moved the camera from the calibration, in the calibration's
    /// own standard deviations (|z|; about sqrt(k) is typical for k camera parameters).
    pub prior_distance: f64,
    /// The tile's chi2 before and after.
    pub chi2_before: f64,
    pub chi2: f64,
    /// The samples' geometry at the refined camera.
    pub samples: Vec<Sample>,
    pub iterations: usize,
    /// How far the refinement moved the camera against how far it would move were the
    /// grid photo's and the highlight's uncertainties both right: |z|^2 / tr(I - C_z), C_z
    /// the joint problem's covariance of z (about 1 when they agree).
    pub tension: f64,
    /// Cameras about the refined one with the uncertainty the joint problem leaves it
    /// (widened by `tension` where that is above 1); the reflectance refitted at each
    /// carries it into the fit's intervals.
    pub draws: CameraDraws,
}

/// Where to draw cameras in the whitened coordinates of the calibration: `offset + root *
/// w`, w ~ N(0, I) (the calibration's own uncertainty is offset 0, root the identity).
#[derive(Debug, Clone)]
pub struct CameraDraws {
    /// The camera drawn about as an offset from the calibrated one in the calibration's
    /// standard deviations (the whitened coordinates z of the module's text).
    pub offset: Vec<f64>,
    /// A lower-triangular square root of the draws' covariance, in the same coordinates.
    pub root: DMatrix<f64>,
}

/// The parameters fitted besides the camera: kd per channel, ks per channel (or one grey
/// ks), ln n.
struct Layout {
    channels: usize,
    grey_ks: bool,
}

impl Layout {
    fn count(&self) -> usize {
        self.channels + if self.grey_ks { 1 } else { self.channels } + 1
    }

    fn pack(&self, f: &ModelFit) -> Vec<f64> {
        let mut v: Vec<f64> = (0..self.channels).map(|c| f.kd[c].value).collect();
        if self.grey_ks {
            v.push(f.ks[0].value);
        } else {
            v.extend((0..self.channels).map(|c| f.ks[c].value));
        }
        v.push(f.n.value.ln());
        v
    }

    /// kd, ks and n of channel c.
    fn at(&self, v: &[f64], c: usize) -> (f64, f64, f64) {
        let ks = if self.grey_ks {
            v[self.channels]
        } else {
            v[self.channels + c]
        };
        (v[c], ks, v[v.len() - 1].exp())
    }

    /// The index in the 7-vector (kd r g b, ks r g b, ln n) of each parameter: a grey ks
    /// stands for all three channels' ks.
    fn slots(&self, i: usize) -> Vec<usize> {
        let nc = self.channels;
        if i < nc {
            vec![i]
        } else if i == self.count() - 1 {
            vec![6]
        } else if self.grey_ks {
            (0..nc).map(|c| 3 + c).collect()
        } else {
            vec![3 + (i - nc)]
        }
    }
}

/// The camera as a whitened vector around the calibration: x = x0 + L z, L L^T the
/// calibration's covariance (of its intrinsics and the first view's pose), so z ~ N(0, I)
/// draws a camera as uncertain as the calibration says. Where intrinsics were held at
/// uncertain values (a lens profile, a principal point at the image centre), they are
/// drawn too, jointly with the pose ([`crate::calib::solve::ViewResult::held_covariance`]):
/// a held principal point's error comes with the turn of the camera that compensates it,
/// and drawing that turn alone would move every pixel's ray on the tile, which the real
/// error does not.
pub struct Camera<'a> {
    cal: &'a Calibration,
    base: &'a Scene,
    /// The intrinsics x holds (the calibration's fitted ones, or fitted and held).
    fit: crate::calib::camera::Fit,
    x0: DVector<f64>,
    root: DMatrix<f64>,
    intrinsic_count: usize,
}

impl<'a> Camera<'a> {
    /// None where the calibration has no usable covariance.
    pub fn new(cal: &'a Calibration, base: &'a Scene) -> Option<Self> {
        let view = cal.views.first()?;
        let (fit, covariance) = match cal.held_fit {
            Some(h) if !view.held_covariance.is_empty() => (h, &view.held_covariance),
            _ => (cal.fit, &view.covariance),
        };
        let k = covariance.len();
        let ni = k.checked_sub(6)?;
        if covariance.iter().any(|r| r.len() != k) {
            return None;
        }
        let cov = DMatrix::from_fn(k, k, |i, j| covariance[i][j]);
        if !cov.iter().all(|x| x.is_finite()) {
            return None;
        }
        // A square root that tolerates a singular covariance (directions of zero variance
        // are held).
        let eig = nalgebra::SymmetricEigen::new(cov);
        let root =
            &eig.eigenvectors * DMatrix::from_diagonal(&eig.eigenvalues.map(|l| l.max(0.0).sqrt()));
        let mut x0 = Vec::new();
        cal.intrinsics.pack(&fit, &mut x0);
        if x0.len() != ni {
            return None;
        }
        x0.extend_from_slice(&view.pose.rvec);
        x0.extend_from_slice(&view.pose.t);
        Some(Camera {
            cal,
            base,
            fit,
            x0: DVector::from_vec(x0),
            root,
            intrinsic_count: ni,
        })
    }

    pub fn dim(&self) -> usize {
        self.x0.len()
    }

    fn at(&self, z: &[f64]) -> (Intrinsics, Pose) {
        let x = &self.x0 + &self.root * DVector::from_column_slice(z);
        let ni = self.intrinsic_count;
        let mut intr = self.cal.intrinsics.clone();
        intr.unpack(&self.fit, &x.as_slice()[..ni]);
        let pose = Pose {
            rvec: [x[ni], x[ni + 1], x[ni + 2]],
            t: [x[ni + 3], x[ni + 4], x[ni + 5]],
        };
        (intr, pose)
    }

    /// The lamp and tile seen by the camera at z.
    pub fn scene(&self, z: &[f64]) -> Scene {
        let (i, p) = self.at(z);
        self.base.with_camera(i, p)
    }
}

/// Residuals of the joint problem at (z, theta): the tile's standardised radiance
/// residuals, then z itself (the prior). None where a sampled pixel no longer sees the tile
/// plane.
fn residuals(
    cam: &Camera,
    layout: &Layout,
    model: Model,
    pixels: &[(usize, usize)],
    samples: &[Sample],
    z: &[f64],
    theta: &[f64],
) -> Option<Vec<f64>> {
    let scene = cam.scene(z);
    let mut r = Vec::with_capacity(samples.len() * layout.channels + z.len());
    for (&(u, v), s) in pixels.iter().zip(samples) {
        let g = scene.geometry_at(u as f64, v as f64)?;
        for c in 0..layout.channels {
            let var = s.variance[c];
            if s.censored[c] || !(var.is_finite() && var > 0.0) {
                continue;
            }
            let (kd, ks, n) = layout.at(theta, c);
            let pred = model.radiance(&g, kd, ks, n);
            r.push((s.radiance[c] - pred) / var.sqrt());
        }
    }
    r.extend_from_slice(z);
    Some(r)
}

/// Fit the camera and `start`'s model together (see the module's text). `pixels` are the
/// samples' pixels (u, v) and `samples` their values at the calibrated camera `base`.
/// None where the model has no lobe (a matte tile says nothing about the camera's
/// position), the calibration has no usable covariance, or the problem does not converge.
pub fn refine(
    base: &Scene,
    cal: &Calibration,
    pixels: &[(usize, usize)],
    samples: &[Sample],
    start: &ModelFit,
    opts: &Options,
) -> Option<Refined> {
    refine_with(base, cal, pixels, samples, start, opts, 1.0)
}

/// [`refine`] with the calibration's standard deviations multiplied by `prior_scale` (a
/// weaker prior where the calibration's own are known to be too small).
pub fn refine_with(
    base: &Scene,
    cal: &Calibration,
    pixels: &[(usize, usize)],
    samples: &[Sample],
    start: &ModelFit,
    opts: &Options,
    prior_scale: f64,
) -> Option<Refined> {
    let model = start.model;
    if !model.has_lobe() || pixels.len() != samples.len() {
        return None;
    }
    let mut cam = Camera::new(cal, base)?;
    cam.root *= prior_scale;
    let layout = Layout {
        channels: opts.channels.clamp(1, 3),
        grey_ks: opts.grey_ks,
    };
    let k = cam.dim();
    let p = layout.count();
    let mut x: Vec<f64> = vec![0.0; k];
    x.extend(layout.pack(start));
    let eval = |x: &[f64]| residuals(&cam, &layout, model, pixels, samples, &x[..k], &x[k..]);
    let cost = |r: &[f64]| r.iter().map(|v| v * v).sum::<f64>();
    let mut r = eval(&x)?;
    let prior_len = k;
    let chi2_of = |r: &[f64]| cost(&r[..r.len() - prior_len]);
    let chi2_before = chi2_of(&r);
    let mut c = cost(&r);
    let mut lambda = 1e-3;
    let mut iterations = 0;
    let mut jac = jacobian(&eval, &x, &r, k)?;
    for _ in 0..50 {
        iterations += 1;
        let jt = jac.transpose();
        let a = &jt * &jac;
        let g = &jt * DVector::from_column_slice(&r);
        let mut improved = false;
        for _ in 0..12 {
            let mut m = a.clone();
            for i in 0..k + p {
                m[(i, i)] += lambda * a[(i, i)].max(1e-12);
            }
            let Some(step) = m.cholesky().map(|ch| ch.solve(&(-&g))) else {
                lambda *= 10.0;
                continue;
            };
            let xn: Vec<f64> = x.iter().zip(step.iter()).map(|(a, b)| a + b).collect();
            match eval(&xn) {
                Some(rn) if cost(&rn) < c => {
                    let rel = (c - cost(&rn)) / c.max(1e-300);
                    x = xn;
                    r = rn;
                    c = cost(&r);
                    lambda = (lambda / 10.0).max(1e-12);
                    improved = true;
                    if rel < 1e-10 {
                        lambda = -1.0; // converged
                    }
                    break;
                }
                _ => lambda *= 10.0,
            }
        }
        if !improved || lambda < 0.0 {
            break;
        }
        jac = jacobian(&eval, &x, &r, k)?;
    }
    jac = jacobian(&eval, &x, &r, k)?;
    let cov = (jac.transpose() * &jac).try_inverse()?;
    if !cov.iter().all(|v| v.is_finite()) {
        return None;
    }

    // The fit at the refined camera, with the joint covariance of its parameters.
    let theta = &x[k..];
    let mut fit = start.clone();
    for ch in 0..layout.channels {
        let (kd, ks, n) = layout.at(theta, ch);
        fit.kd[ch].value = kd;
        fit.ks[ch].value = ks;
        fit.n.value = n;
    }
    let mut c7 = vec![vec![0.0; 7]; 7];
    for i in 0..p {
        for j in 0..p {
            for &a in &layout.slots(i) {
                for &b in &layout.slots(j) {
                    c7[a][b] = cov[(k + i, k + j)];
                }
            }
        }
    }
    for row in fit.covariance.iter_mut() {
        for v in row.iter_mut() {
            *v = 0.0;
        }
    }
    // The joint problem's curvature is the interval now: the unrefined fit's profile of n
    // was taken at the other camera.
    fit.n_profile95 = None;
    fit.ratio_trace95 = None;
    fit.n_added_variance = 0.0;
    fit.add_covariance(&c7);
    fit.chi2 = chi2_of(&r);

    // The refined camera and its centre's uncertainty (by the delta method on z).
    let (intrinsics, pose) = cam.at(&x[..k]);
    let scene = base.with_camera(intrinsics.clone(), pose);
    let centre = scene.centre;
    let mut jc = DMatrix::zeros(3, k);
    for i in 0..k {
        let mut zp = x[..k].to_vec();
        zp[i] += 1e-4;
        let cp = cam.scene(&zp).centre;
        for a in 0..3 {
            jc[(a, i)] = (cp[a] - centre[a]) / 1e-4;
        }
    }
    let cz = cov.view((0, 0), (k, k)).into_owned();
    // The grid photo and the highlight as two measurements of one camera: were both
    // uncertainties right, the refined camera would sit |z|^2 ~ tr(I - C_z) from the
    // calibrated one (C_z the joint covariance of z, the prior N(0, I)). Further off, they
    // disagree beyond what they state, and the camera's remaining covariance is widened by
    // the ratio (the Birge ratio, as the Particle Data Group scales an inconsistent
    // average); never narrowed.
    let z_norm = x[..k].iter().map(|v| v * v).sum::<f64>().sqrt();
    let tension = z_norm * z_norm / (k as f64 - cz.trace()).max(1e-9);
    let posterior_root = cz.clone().cholesky()?.l() * prior_scale * tension.max(1.0).sqrt();
    let cc = &jc * cz * jc.transpose();
    let refined_samples = seen_by(&scene, pixels, samples);
    Some(Refined {
        fit,
        intrinsics,
        pose,
        centre_before: base.centre,
        centre,
        centre_sd: [cc[(0, 0)].sqrt(), cc[(1, 1)].sqrt(), cc[(2, 2)].sqrt()],
        prior_distance: z_norm,
        chi2_before,
        chi2: chi2_of(&r),
        samples: refined_samples,
        iterations,
        tension,
        draws: CameraDraws {
            offset: x[..k].iter().map(|v| v * prior_scale).collect(),
            root: posterior_root,
        },
    })
}

/// The samples at pixels `pixels` with their geometry as `scene`'s camera sees it (a pixel
/// that no longer sees the tile plane keeps its old geometry).
pub fn seen_by(scene: &Scene, pixels: &[(usize, usize)], samples: &[Sample]) -> Vec<Sample> {
    pixels
        .iter()
        .zip(samples)
        .map(|(&(u, v), s)| {
            let mut s = *s;
            if let Some(g) = scene.geometry_at(u as f64, v as f64) {
                s.geometry = g;
            }
            s
        })
        .collect()
}

/// Forward-difference Jacobian of the residuals; camera coordinates (whitened: one unit is
/// one standard deviation) get a fixed step, reflectance parameters a relative one.
fn jacobian(
    eval: &dyn Fn(&[f64]) -> Option<Vec<f64>>,
    x: &[f64],
    r: &[f64],
    k: usize,
) -> Option<DMatrix<f64>> {
    let mut j = DMatrix::zeros(r.len(), x.len());
    for i in 0..x.len() {
        let h = if i < k {
            1e-4
        } else {
            1e-6 * x[i].abs().max(1e-3)
        };
        let mut xp = x.to_vec();
        xp[i] += h;
        let rp = eval(&xp)?;
        if rp.len() != r.len() {
            return None;
        }
        for (row, (a, b)) in rp.iter().zip(r).enumerate() {
            j[(row, i)] = (a - b) / h;
        }
    }
    Some(j)
}
