//! Calibration: Tsai's start, Levenberg-Marquardt refinement on reprojection error, the
//! parameters chosen by BIC ("no more than the scene needs"), standard deviations from the
//! Jacobian at the optimum.

use levenberg_marquardt::{LeastSquaresProblem, LevenbergMarquardt};
use nalgebra::{storage::Owned, DMatrix, DVector, Dyn, Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use super::camera::{pixel_derivatives, rotation, Fit, Intrinsics, LensTerms, Pose};
use super::tsai::tsai;

/// One photo's corners: world points (grid frame, z = 0) and their pixels.
#[derive(Debug, Clone)]
pub struct ViewObs {
    pub name: String,
    pub world: Vec<[f64; 3]>,
    pub px: Vec<[f64; 2]>,
}

/// Errors of the calibration itself (detection has its own).
#[derive(Debug, thiserror::Error)]
pub enum CalibError {
    #[error("{0}: Tsai's method found no camera for this view (are the corners in order and not collinear?)")]
    NoStart(String),
    #[error("no views to calibrate")]
    NoViews,
}

/// A candidate model and how well it explains the corners.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Candidate {
    pub parameters: String,
    /// Intrinsic parameters fitted.
    pub count: usize,
    /// RMS reprojection error, pixels (root mean squared distance per corner).
    pub rms_px: f64,
    pub bic: f64,
}

/// A fitted parameter with its standard deviation.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Param {
    pub name: String,
    pub value: f64,
    /// Standard deviation: from the Jacobian at the optimum, sigma^2 (J^T J)^-1 with sigma
    /// from the residuals, plus what held parameters' uncertainty adds (a principal point
    /// held at the image centre: see `uncertainty_includes`); for the focal length,
    /// widened to the profile interval's larger half-width where that is wider.
    pub sd: f64,
    /// For the focal length, when its linearised sd exceeds 1%: the 68% profile-likelihood
    /// interval (each side searched out to a factor of 10).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub interval: Option<[f64; 2]>,
}

/// One view's result.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ViewResult {
    pub name: String,
    pub pose: Pose,
    /// Standard deviations of rvec (radians) and t (grid units).
    pub pose_sd: [f64; 6],
    /// Camera centre in the grid frame, -R^T t.
    pub camera_centre: [f64; 3],
    /// Its standard deviation per axis (zero in files written before it was added).
    #[serde(default)]
    pub camera_centre_sd: [f64; 3],
    /// Its covariance (grid units squared), from the pose's (zero in older files).
    #[serde(default)]
    pub camera_centre_covariance: [[f64; 3]; 3],
    /// Distance from the camera centre to the grid origin.
    pub distance: f64,
    pub rms_px: f64,
    /// Per corner: reprojected minus detected, pixels (row-major corner order).
    pub residuals: Vec<[f64; 2]>,
    /// Joint covariance of the fitted intrinsics (in the order of `parameters`) and this
    /// view's pose (rvec, t): what later stages need to carry the calibration's
    /// uncertainty into their own (empty in files written before it was added).
    #[serde(default)]
    pub covariance: Vec<Vec<f64>>,
    /// Where intrinsics were held at uncertain values ([`Calibration::held_fit`]): the
    /// joint covariance of every intrinsic of `held_fit` (fitted and held, in its order)
    /// and this view's pose. A held value's error moves the fitted pose with it (an error
    /// in the principal point turns the fitted camera to compensate); later stages draw
    /// the camera from this, not from `covariance` with the held values fixed, so the
    /// two errors come together as they do in the fit (absent: nothing was held).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub held_covariance: Vec<Vec<f64>>,
}

/// The calibration.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Calibration {
    pub width: usize,
    pub height: usize,
    pub intrinsics: Intrinsics,
    /// Which parameters were fitted (the rest held: principal point at the image centre,
    /// square pixels, absent distortion terms zero).
    pub fit: Fit,
    /// Fitted intrinsic parameters with standard deviations.
    pub parameters: Vec<Param>,
    /// Root mean squared reprojection distance per corner over all views, pixels (the
    /// definition of OpenCV's calibrateCamera).
    pub rms_px: f64,
    /// Standard deviation of one corner coordinate, estimated from the residuals.
    pub sigma_px: f64,
    pub views: Vec<ViewResult>,
    /// Every model tried, with its RMS and BIC; the chosen one has the lowest BIC.
    pub candidates: Vec<Candidate>,
    /// What the standard deviations and covariances include beyond the corners' noise:
    /// a principal point held at the image centre (its prior), or a lens held at a
    /// calibration with covariance (absent: the noise alone).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub uncertainty_includes: Option<String>,
    /// Where intrinsics were held at uncertain values (a lens profile, a principal point
    /// at the image centre): the fitted and held intrinsics together, the order of each
    /// view's `held_covariance`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held_fit: Option<Fit>,
    pub warnings: Vec<String>,
}

/// A Gaussian prior on the principal point: its offset from `centre` has standard
/// deviation `sd` px per axis. In a least-squares problem whose residuals are pixels with
/// noise sigma, it is two more residuals, (sigma / sd) (c - centre): `weight` = sigma / sd.
#[derive(Debug, Clone, Copy)]
struct PpPrior {
    centre: [f64; 2],
    sd: f64,
    weight: f64,
}

impl PpPrior {
    /// The principal point's columns among `fit`'s intrinsics, where `fit` frees it.
    fn columns(fit: &Fit) -> Option<[usize; 2]> {
        if !fit.principal_point {
            return None;
        }
        let nf = match (fit.focal, fit.aspect) {
            (false, _) => 0,
            (true, false) => 1,
            (true, true) => 2,
        };
        Some([nf, nf + 1])
    }
}

struct Lsq<'a> {
    views: &'a [ViewObs],
    fit: Fit,
    k: Intrinsics,
    poses: Vec<Pose>,
    x: DVector<f64>,
    /// Holds the focal length (the first parameter) at a value: one more residual,
    /// weight * (f - value), for the profile likelihood of f.
    anchor: Option<(f64, f64)>,
    /// The principal point's prior, where the fit frees it (two more residuals).
    prior: Option<(PpPrior, [usize; 2])>,
}

impl<'a> Lsq<'a> {
    fn new(
        views: &'a [ViewObs],
        fit: Fit,
        k: &Intrinsics,
        poses: &[Pose],
        anchor: Option<(f64, f64)>,
        prior: Option<PpPrior>,
    ) -> Self {
        let mut p = Lsq {
            views,
            fit,
            k: k.clone(),
            poses: poses.to_vec(),
            x: DVector::zeros(0),
            anchor,
            prior: prior.and_then(|q| PpPrior::columns(&fit).map(|c| (q, c))),
        };
        p.pack();
        p
    }

    fn data_rows(&self) -> usize {
        2 * self.views.iter().map(|v| v.px.len()).sum::<usize>()
    }
    fn rows(&self) -> usize {
        self.data_rows() + self.anchor.is_some() as usize + 2 * self.prior.is_some() as usize
    }
    fn cols(&self) -> usize {
        self.fit.intrinsic_count() + 6 * self.views.len()
    }
    fn pack(&mut self) {
        let mut v = Vec::with_capacity(self.cols());
        self.k.pack(&self.fit, &mut v);
        for p in &self.poses {
            v.extend(p.rvec);
            v.extend(p.t);
        }
        self.x = DVector::from_vec(v);
    }
}

impl LeastSquaresProblem<f64, Dyn, Dyn> for Lsq<'_> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, x: &DVector<f64>) {
        self.x.copy_from(x);
        let s = x.as_slice();
        let n = self.k.unpack(&self.fit, s);
        for (i, p) in self.poses.iter_mut().enumerate() {
            let o = n + 6 * i;
            p.rvec = [s[o], s[o + 1], s[o + 2]];
            p.t = [s[o + 3], s[o + 4], s[o + 5]];
        }
    }

    fn params(&self) -> DVector<f64> {
        self.x.clone()
    }

    fn residuals(&self) -> Option<DVector<f64>> {
        let mut r = DVector::zeros(self.rows());
        let mut i = 0;
        let lens = Lens::new(&self.k);
        for (v, pose) in self.views.iter().zip(&self.poses) {
            let rm = rotation(pose.rvec);
            let t = Vector3::from(pose.t);
            for (w, p) in v.world.iter().zip(&v.px) {
                let xc = rm * Vector3::from(*w) + t;
                if xc.z.is_nan() || xc.z <= 0.0 {
                    return None;
                }
                let uv = lens.pixel(xc.x / xc.z, xc.y / xc.z).uv;
                r[i] = uv[0] - p[0];
                r[i + 1] = uv[1] - p[1];
                i += 2;
            }
        }
        if let Some((f, w)) = self.anchor {
            r[i] = w * (self.x[0] - f);
            i += 1;
        }
        if let Some((q, cols)) = self.prior {
            for (a, col) in cols.iter().enumerate() {
                r[i + a] = q.weight * (self.x[*col] - q.centre[a]);
            }
        }
        Some(r)
    }

    fn jacobian(&self) -> Option<DMatrix<f64>> {
        let fit = &self.fit;
        let k = &self.k;
        let ni = fit.intrinsic_count();
        let mut j = DMatrix::zeros(self.rows(), self.cols());
        let lens = Lens::new(k);
        let mut row = 0;
        for (vi, (v, pose)) in self.views.iter().zip(&self.poses).enumerate() {
            let rm = rotation(pose.rvec);
            let t = Vector3::from(pose.t);
            let rot = DRotate::new(&Vector3::from(pose.rvec), &rm);
            for w in &v.world {
                let pw = Vector3::from(*w);
                let xc = rm * pw + t;
                let (x, y) = (xc.x / xc.z, xc.y / xc.z);
                let q = lens.pixel(x, y);
                // The intrinsics, in `fit`'s order, and d(u, v)/d(Xc): camera::project's.
                let mut c = 0;
                let mut put = |d: [f64; 2]| {
                    j[(row, c)] = d[0];
                    j[(row + 1, c)] = d[1];
                    c += 1;
                };
                let terms = LensTerms {
                    x,
                    y,
                    z: xc.z,
                    xd: q.xd,
                    yd: q.yd,
                    r2: q.r2,
                    d: q.d,
                    dd: q.dd,
                    p: lens.p,
                };
                let duv = pixel_derivatives(k, fit, &terms, &mut put);
                let dr = rot.at(&pw);
                let o = ni + 6 * vi;
                for jj in 0..3 {
                    for (rr, duv) in duv.iter().enumerate() {
                        j[(row + rr, o + jj)] = (0..3).map(|c| duv[c] * dr[(c, jj)]).sum();
                        j[(row + rr, o + 3 + jj)] = duv[jj];
                    }
                }
                row += 2;
            }
        }
        if let Some((_, w)) = self.anchor {
            j[(row, 0)] = w;
            row += 1;
        }
        if let Some((q, cols)) = self.prior {
            for (a, col) in cols.iter().enumerate() {
                j[(row + a, *col)] = q.weight;
            }
        }
        Some(j)
    }
}

/// The lens of `camera::project`, its coefficients looked up once for all points.
struct Lens {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    k: [f64; 3],
    p: [f64; 2],
}

/// A distorted point: the pixel, the distorted normalised point, r², and the radial
/// factor and its derivative by r².
struct Distorted {
    uv: [f64; 2],
    xd: f64,
    yd: f64,
    r2: f64,
    d: f64,
    dd: f64,
}

impl Lens {
    fn new(k: &Intrinsics) -> Self {
        let kk = |i: usize| k.radial.get(i).copied().unwrap_or(0.0);
        Lens {
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            k: [kk(0), kk(1), kk(2)],
            p: k.tangential.unwrap_or([0.0; 2]),
        }
    }

    /// The pixel of normalised point (x, y) (the same sums as `camera::project`).
    #[inline]
    fn pixel(&self, x: f64, y: f64) -> Distorted {
        let r2 = x * x + y * y;
        let [k1, k2, k3] = self.k;
        let d = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let dd = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3);
        let [p1, p2] = self.p;
        let xd = x * d + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let yd = y * d + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        Distorted {
            uv: [self.fx * xd + self.cx, self.fy * yd + self.cy],
            xd,
            yd,
            r2,
            d,
            dd,
        }
    }
}

/// [v]x, the cross-product matrix.
fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// d(R(v) p)/dv (Gallego & Yezzi 2015, as in `camera::project`):
/// -R [p]x (v v^T + (R^T - I)[v]x) / |v|^2, with the factor in brackets worked out once
/// per view (the same sums, so the same values, as `camera::project`'s).
struct DRotate {
    r: Matrix3<f64>,
    m: Matrix3<f64>,
    n2: f64,
}

impl DRotate {
    fn new(v: &Vector3<f64>, r: &Matrix3<f64>) -> Self {
        let n2 = v.norm_squared();
        DRotate {
            r: *r,
            m: v * v.transpose() + (r.transpose() - Matrix3::identity()) * skew(v),
            n2,
        }
    }

    #[inline]
    fn at(&self, p: &Vector3<f64>) -> Matrix3<f64> {
        if self.n2 < 1e-20 {
            return -skew(p);
        }
        -self.r * skew(p) * self.m / self.n2
    }
}

/// Public for the derivative tests: residuals and Jacobian of a problem at its start.
pub fn residuals_and_jacobian(
    views: &[ViewObs],
    fit: Fit,
    k: &Intrinsics,
    poses: &[Pose],
) -> (DVector<f64>, DMatrix<f64>, DVector<f64>) {
    let p = Lsq::new(views, fit, k, poses, None, None);
    (
        p.residuals().expect("points in front of the camera"),
        p.jacobian().unwrap(),
        p.x.clone(),
    )
}

/// Set a problem's parameters (for finite differences in the tests).
pub fn residuals_at(
    views: &[ViewObs],
    fit: Fit,
    k: &Intrinsics,
    poses: &[Pose],
    x: &DVector<f64>,
) -> DVector<f64> {
    let mut p = Lsq::new(views, fit, k, poses, None, None);
    p.set_params(x);
    p.residuals().expect("points in front of the camera")
}

struct Solved {
    k: Intrinsics,
    poses: Vec<Pose>,
    /// The corners' sum of squared residuals.
    ssr: f64,
    /// The principal point prior's share of the objective (0 without one).
    penalty: f64,
    /// The prior the solution was fitted under, if any.
    prior: Option<PpPrior>,
    m: usize,
    n: usize,
}

impl Solved {
    /// The corners' residual sd (SSR over the degrees of freedom).
    fn sigma(&self) -> f64 {
        (self.ssr / (self.m - self.n).max(1) as f64).sqrt()
    }
}

fn solve(
    views: &[ViewObs],
    fit: Fit,
    k: &Intrinsics,
    poses: &[Pose],
    prior: Option<PpPrior>,
) -> Option<Solved> {
    solve_anchored(views, fit, k, poses, None, prior)
}

fn solve_anchored(
    views: &[ViewObs],
    fit: Fit,
    k: &Intrinsics,
    poses: &[Pose],
    anchor: Option<(f64, f64)>,
    prior: Option<PpPrior>,
) -> Option<Solved> {
    let p = Lsq::new(views, fit, k, poses, anchor, prior);
    // Relative tolerances of 1e-10 (the crate defaults to 30 machine epsilons, which costs
    // iterations that change nothing measurable).
    let (mut p, report) = LevenbergMarquardt::new()
        .with_ftol(1e-10)
        .with_xtol(1e-10)
        .with_patience(200)
        .minimize(p);
    if !report.termination.was_successful() {
        return None;
    }
    p.anchor = None;
    let r = p.residuals()?;
    let m = p.data_rows();
    Some(Solved {
        m,
        n: p.cols(),
        ssr: r.rows(0, m).norm_squared(),
        penalty: r.rows(m, r.len() - m).norm_squared(),
        prior: None,
        k: p.k,
        poses: p.poses,
    })
}

/// Profile likelihood of the focal length: the range of f over which the best fit with f
/// held is within one unit of chi-square (sigma^2 from the optimum) of the optimum, i.e.
/// a 68% interval that follows the curved valley of a nearly degenerate view (where the
/// linearised standard deviation, taken at a point far along the valley, is too small).
/// Each side is searched out to a factor of 10.
fn profile_f(
    views: &[ViewObs],
    fit: Fit,
    best: &Solved,
    prior: Option<PpPrior>,
    sigma2: f64,
    sd: f64,
) -> [f64; 2] {
    let f0 = best.k.fx;
    let excess = |f: f64| -> f64 {
        let mut k = best.k.clone();
        k.fx = f;
        k.fy = f * best.k.fy / best.k.fx;
        // Along the valley the distance grows with f (the board keeps its size).
        let poses: Vec<Pose> = best
            .poses
            .iter()
            .map(|p| Pose {
                rvec: p.rvec,
                t: [p.t[0] * f / f0, p.t[1] * f / f0, p.t[2] * f / f0],
            })
            .collect();
        let w = 1e6 / f0;
        // The prior's weight at this sigma (its share is part of the objective profiled).
        let prior = prior.map(|q| PpPrior {
            weight: sigma2.sqrt() / q.sd,
            ..q
        });
        let base = best.ssr + prior.map_or(0.0, |q| best_penalty(best, &q));
        solve_anchored(views, fit, &k, &poses, Some((f, w)), prior)
            .map_or(f64::INFINITY, |s| (s.ssr + s.penalty - base) / sigma2)
    };
    let mut out = [f0; 2];
    let max = 10f64.ln();
    for (side, o) in [-1.0, 1.0].iter().zip(out.iter_mut()) {
        let mut lo = 0.0;
        let mut hi = (sd / f0).clamp(1e-6, max);
        while excess(f0 * (side * hi).exp()) < 1.0 {
            lo = hi;
            hi *= 2.0;
            if hi >= max {
                hi = max;
                break;
            }
        }
        if hi >= max && excess(f0 * (side * hi).exp()) < 1.0 {
            *o = f0 * (side * hi).exp();
            continue;
        }
        for _ in 0..12 {
            let mid = 0.5 * (lo + hi);
            if excess(f0 * (side * mid).exp()) < 1.0 {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        *o = f0 * (side * 0.5 * (lo + hi)).exp();
    }
    out
}

/// [`solve`] from `start`, with the prior's weight made consistent with the fit's own noise:
/// the noise estimated before a needed term was freed is inflated by that term's misfit,
/// and a prior weighed by it would be too tight. Re-solved (at most three times) until the
/// residuals' sigma moves by less than 5%.
fn solve_with_prior(
    views: &[ViewObs],
    fit: Fit,
    start: &Solved,
    prior: Option<PpPrior>,
) -> Option<Solved> {
    let mut q = prior.filter(|_| fit.principal_point);
    let mut r = solve(views, fit, &start.k, &start.poses, q)?;
    for _ in 0..3 {
        let Some(p) = q else { break };
        let sigma = r.sigma();
        if (sigma / p.sd / p.weight - 1.0).abs() < 0.05 {
            break;
        }
        q = Some(PpPrior {
            weight: sigma / p.sd,
            ..p
        });
        r = solve(views, fit, &r.k, &r.poses, q)?;
    }
    r.prior = q;
    Some(r)
}

/// The prior's share of the objective at a solution's principal point.
fn best_penalty(s: &Solved, q: &PpPrior) -> f64 {
    let d = [s.k.cx - q.centre[0], s.k.cy - q.centre[1]];
    q.weight * q.weight * (d[0] * d[0] + d[1] * d[1])
}

fn bic(s: &Solved) -> f64 {
    let m = s.m as f64;
    m * (s.ssr / m).max(1e-300).ln() + s.n as f64 * m.ln()
}

/// Which extra parameters a search may free.
#[derive(Debug, Clone, Copy)]
pub struct Options {
    /// Try fx != fy (several views only, by default).
    pub aspect: bool,
    /// Try a free principal point.
    pub principal_point: bool,
    /// Most radial terms to try.
    pub max_radial: usize,
    /// Try tangential terms.
    pub tangential: bool,
    /// Where the principal point is held at the image centre (not freed by BIC), the
    /// standard deviation of its true offset, as a fraction of the image's longer side:
    /// the covariance of the fitted parameters is widened by what that offset would move
    /// them (0: not widened).
    pub principal_point_prior: f64,
}

/// The principal point's offset from the image centre that single-view intervals allow
/// for, one standard deviation per axis, as a fraction of the image's longer side. Lenses
/// are rarely centred on their sensor to better than a few percent (OpenCV's left01..13
/// camera: 3.5% and 1.1% off); 3% puts such an offset near one standard deviation.
pub const PRINCIPAL_POINT_PRIOR: f64 = 0.03;

impl Options {
    /// The default search for `views` photos.
    pub fn for_views(n: usize) -> Self {
        Options {
            aspect: n > 1,
            principal_point: true,
            max_radial: 3,
            // One view cannot tell decentring distortion from a shifted principal point
            // and a turned camera: freeing both gave wrong cameras with small sds.
            tangential: n > 1,
            principal_point_prior: PRINCIPAL_POINT_PRIOR,
        }
    }
}

/// The pose of each view with the intrinsics known (from an earlier calibration of the
/// same camera at the same resolution); they are held, not refitted.
pub fn pose_with(
    views: &[ViewObs],
    width: usize,
    height: usize,
    k: &Intrinsics,
) -> Result<Calibration, CalibError> {
    pose_with_lens(views, width, height, k, None)
}

/// The intrinsics' uncertainty, for a pose fitted with them held: which parameters were
/// fitted when they were calibrated, and their covariance (in [`Fit::names`] order).
#[derive(Debug, Clone)]
pub struct LensCovariance {
    pub fit: Fit,
    pub covariance: DMatrix<f64>,
}

/// [`pose_with`], with the held intrinsics' covariance carried into the pose's: the pose's
/// covariance is widened by what the intrinsics' errors would move it (first order).
pub fn pose_with_lens(
    views: &[ViewObs],
    width: usize,
    height: usize,
    k: &Intrinsics,
    lens: Option<&LensCovariance>,
) -> Result<Calibration, CalibError> {
    if views.is_empty() {
        return Err(CalibError::NoViews);
    }
    let c = [k.cx, k.cy];
    let mut poses = Vec::new();
    for v in views {
        // Tsai on undistorted-enough pixels: the start only needs to be near.
        let (f, mut p) =
            tsai(&v.world, &v.px, c, k.fx).ok_or_else(|| CalibError::NoStart(v.name.clone()))?;
        let s = k.fx / f;
        p.t = [p.t[0] * s, p.t[1] * s, p.t[2] * s];
        poses.push(p);
    }
    let fit = Fit::pose_only();
    let best = solve(views, fit, k, &poses, None)
        .ok_or_else(|| CalibError::NoStart(views[0].name.clone()))?;
    let npts: usize = views.iter().map(|v| v.px.len()).sum();
    let candidates = vec![Candidate {
        parameters: fit.describe(),
        count: 0,
        rms_px: (best.ssr / npts as f64).sqrt(),
        bic: bic(&best),
    }];
    let held = lens
        .filter(|l| {
            let n = l.fit.intrinsic_count();
            n > 0 && l.covariance.shape() == (n, n) && l.covariance.iter().all(|x| x.is_finite())
        })
        .map(|l| Held {
            fit: l.fit,
            columns: (0..l.fit.intrinsic_count()).collect(),
            covariance: l.covariance.clone(),
        });
    let carried = held.is_some();
    let mut cal = finish(views, width, height, fit, best, candidates, held, None);
    if !carried {
        cal.warnings.push("the intrinsics were held at a given calibration without a covariance; the pose's standard deviations do not include their uncertainty".into());
    }
    Ok(cal)
}

/// Calibrate from one or more views of the grid (images `width` x `height`).
pub fn calibrate(
    views: &[ViewObs],
    width: usize,
    height: usize,
    opts: Options,
) -> Result<Calibration, CalibError> {
    if views.is_empty() {
        return Err(CalibError::NoViews);
    }
    let c = [(width as f64 - 1.0) / 2.0, (height as f64 - 1.0) / 2.0];
    let mut fs = Vec::new();
    let mut poses = Vec::new();
    for v in views {
        let (f, p) = tsai(&v.world, &v.px, c, width.max(height) as f64)
            .ok_or_else(|| CalibError::NoStart(v.name.clone()))?;
        fs.push(f);
        poses.push(p);
    }
    let mut sorted = fs.clone();
    sorted.sort_by(|a, b| a.total_cmp(b));
    let f0 = sorted[sorted.len() / 2];
    // Each view's distance scaled to the common focal length.
    for (p, f) in poses.iter_mut().zip(&fs) {
        let s = f0 / f;
        p.t = [p.t[0] * s, p.t[1] * s, p.t[2] * s];
    }
    let k0 = Intrinsics {
        fx: f0,
        fy: f0,
        cx: c[0],
        cy: c[1],
        radial: Vec::new(),
        tangential: None,
    };
    let mut fit = Fit::simplest();
    let npts: usize = views.iter().map(|v| v.px.len()).sum();
    let rms = |s: &Solved| (s.ssr / npts as f64).sqrt();
    let mut best = solve(views, fit, &k0, &poses, None)
        .ok_or_else(|| CalibError::NoStart(views[0].name.clone()))?;
    // One photo cannot fix the principal point and the focal length together (a plane's
    // homography gives two constraints on the intrinsics): a free principal point wanders
    // along that valley to wherever the corners' noise sends it, dragging f and the
    // camera's distance with it (tens of pixels and millimetres). So from one photo a freed
    // principal point is fitted under the same prior the held one is widened by: its
    // offset from the image centre within `principal_point_prior` of the longer side. The
    // prior's weight is the corners' noise over its sd, the noise taken from the free fit.
    let pp_sd = opts.principal_point_prior * width.max(height) as f64;
    let mut prior: Option<PpPrior> = None;
    let mut candidates = vec![Candidate {
        parameters: fit.describe(),
        count: fit.intrinsic_count(),
        rms_px: rms(&best),
        bic: bic(&best),
    }];
    // Forward selection: free the group that lowers BIC most, until none does.
    loop {
        let mut steps = Vec::new();
        if fit.radial < opts.max_radial {
            steps.push(Fit {
                radial: fit.radial + 1,
                ..fit
            });
        }
        if opts.principal_point && !fit.principal_point {
            steps.push(Fit {
                principal_point: true,
                ..fit
            });
        }
        if opts.aspect && !fit.aspect {
            steps.push(Fit {
                aspect: true,
                ..fit
            });
        }
        if opts.tangential && !fit.tangential {
            steps.push(Fit {
                tangential: true,
                ..fit
            });
        }
        let mut next: Option<(Fit, Solved)> = None;
        for s in steps {
            let mut q = prior;
            let mut free = None;
            if s.principal_point && q.is_none() && views.len() == 1 && pp_sd > 0.0 {
                // The free fit first: its SSR is the least any fit of this model reaches,
                // so where its BIC does not win, the fit under the prior cannot either, and
                // the free fit stands as the candidate tried (what `candidates` lists).
                let f = solve(views, s, &best.k, &best.poses, None);
                let to_beat = next.as_ref().map_or(bic(&best), |n| bic(&n.1));
                // The noise the prior's weight starts from (the fit under the prior then
                // sets it from its own): the free fit's where that wins BIC. Where the
                // free fit lost its way along the valley (it did not converge), which is
                // what the prior is there for, the fit under it is still tried, from the
                // present fit's noise. Before 2026-12-04 such a photo kept the principal
                // point at the centre untried: 15 of 300 simulated scenes, among them
                // most of the weak poses (scene 148: the principal point 13 px off,
                // corners 0.16 px rms against 0.02 px of noise, the centre 12 mm off, 3.2
                // sd along an axis the covariance put at 0.2 mm).
                let noise = match &f {
                    Some(f) if bic(f) < to_beat => Some(f.sigma()),
                    None => Some(best.sigma()),
                    Some(_) => None,
                };
                match noise {
                    Some(sigma) => {
                        q = Some(PpPrior {
                            centre: c,
                            sd: pp_sd,
                            weight: sigma / pp_sd,
                        })
                    }
                    None => free = Some(f),
                }
            }
            let solved = match free {
                Some(f) => f,
                None => solve_with_prior(views, s, &best, q),
            };
            // A term the photos cannot determine runs off to coefficients no camera file
            // holds (|k| beyond MAX_DISTORTION): not a candidate.
            if let Some(r) = solved.filter(|r| r.k.distortion_in_bounds()) {
                candidates.push(Candidate {
                    parameters: s.describe(),
                    count: s.intrinsic_count(),
                    rms_px: rms(&r),
                    bic: bic(&r),
                });
                if bic(&r) < next.as_ref().map_or(bic(&best), |n| bic(&n.1)) {
                    next = Some((s, r));
                }
            }
        }
        match next {
            Some((f, r)) => {
                fit = f;
                prior = r.prior;
                best = r;
            }
            None => break,
        }
    }
    // The principal point held at the image centre: its possible offset widens the
    // covariance of what was fitted.
    let held = (!fit.principal_point && opts.principal_point_prior > 0.0).then(|| {
        let sd = opts.principal_point_prior * width.max(height) as f64;
        let nf = if fit.aspect { 2 } else { 1 };
        Held {
            fit: Fit {
                principal_point: true,
                ..fit
            },
            columns: vec![nf, nf + 1],
            covariance: DMatrix::from_diagonal_element(2, 2, sd * sd),
        }
    });
    Ok(finish(
        views, width, height, fit, best, candidates, held, prior,
    ))
}

/// Parameters held at a value that is itself uncertain: the fit's covariance is widened
/// by G S G^T, G = d(fitted)/d(held) = -(J^T J)^-1 J^T J_h at the optimum, S the held
/// parameters' covariance (the estimator's error when the held values are off by a draw
/// from S, to first order).
struct Held {
    /// A fit that frees the held parameters too (for their Jacobian columns).
    fit: Fit,
    /// The held parameters' columns among `fit`'s intrinsics.
    columns: Vec<usize>,
    covariance: DMatrix<f64>,
}

/// The inverse of a symmetric positive semi-definite matrix by its eigendecomposition,
/// eigenvalues floored at `floor` of the largest (an undetermined direction gets a huge
/// variance, never a negative one).
fn sym_inverse(a: &DMatrix<f64>, floor: f64) -> DMatrix<f64> {
    let a = (a + a.transpose()) * 0.5;
    let eig = nalgebra::SymmetricEigen::new(a);
    let lmax = eig.eigenvalues.iter().fold(0.0f64, |m, &l| m.max(l.abs()));
    if !(lmax > 0.0 && lmax.is_finite()) {
        return DMatrix::from_element(eig.eigenvalues.len(), eig.eigenvalues.len(), f64::INFINITY);
    }
    let inv = eig.eigenvalues.map(|l| 1.0 / l.max(lmax * floor));
    &eig.eigenvectors * DMatrix::from_diagonal(&inv) * eig.eigenvectors.transpose()
}

/// Covariance of a camera centre C = -R(rvec)^T t from the covariance of (rvec, t)
/// (first order; the Jacobian by central differences).
pub fn centre_covariance(pose: &Pose, cov: &DMatrix<f64>) -> [[f64; 3]; 3] {
    let centre = |x: &[f64; 6]| {
        let r = super::camera::rotation([x[0], x[1], x[2]]);
        -(r.transpose() * nalgebra::Vector3::new(x[3], x[4], x[5]))
    };
    let x0 = [
        pose.rvec[0],
        pose.rvec[1],
        pose.rvec[2],
        pose.t[0],
        pose.t[1],
        pose.t[2],
    ];
    let mut j = DMatrix::zeros(3, 6);
    for k in 0..6 {
        let h = if k < 3 {
            1e-6
        } else {
            1e-4 * (1.0 + x0[k].abs())
        };
        let (mut a, mut b) = (x0, x0);
        a[k] += h;
        b[k] -= h;
        let d = (centre(&a) - centre(&b)) / (2.0 * h);
        for r in 0..3 {
            j[(r, k)] = d[r];
        }
    }
    let c = &j * cov * j.transpose();
    let mut out = [[0.0; 3]; 3];
    for (r, row) in out.iter_mut().enumerate() {
        for (k, x) in row.iter_mut().enumerate() {
            *x = c[(r, k)];
        }
    }
    out
}

#[allow(clippy::too_many_arguments)]
fn finish(
    views: &[ViewObs],
    width: usize,
    height: usize,
    fit: Fit,
    s: Solved,
    candidates: Vec<Candidate>,
    held: Option<Held>,
    prior: Option<PpPrior>,
) -> Calibration {
    let (r, j, _) = residuals_and_jacobian(views, fit, &s.k, &s.poses);
    let dof = (s.m as f64 - s.n as f64).max(1.0);
    let sigma2 = s.ssr / dof;
    // A principal point fitted under a prior: the prior's two rows (weight sigma / sd)
    // join the Jacobian, so the covariance is the posterior's.
    let prior = prior.and_then(|q| PpPrior::columns(&fit).map(|c| (q, c)));
    let j = match prior {
        Some((q, cols)) => {
            let mut a = j.clone().resize_vertically(j.nrows() + 2, 0.0);
            for (k, col) in cols.iter().enumerate() {
                a[(j.nrows() + k, *col)] = sigma2.sqrt() / q.sd;
            }
            a
        }
        None => j,
    };
    let mut cov = covariance_of(&j, s.n, sigma2);
    let mut includes = None;
    let mut joint: Option<HeldJoint> = None;
    if let Some(h) = &held {
        if let Some((widened, held_joint, held_includes)) =
            marginalise_held(views, h, &s, &j, sigma2, fit, width.max(height))
        {
            joint = held_joint;
            cov = widened;
            includes = Some(held_includes);
        }
    }
    let sd = |i: usize| cov[(i, i)].max(0.0).sqrt();
    // The focal length's profile where the linearised sd exceeds 1%.
    let f_interval = (fit.focal && sd(0) > 0.01 * s.k.fx)
        .then(|| profile_f(views, fit, &s, prior.map(|p| p.0), sigma2, sd(0)));
    if let Some((q, _)) = prior {
        includes = Some(format!(
            "the principal point fitted under a prior: its offset from the image centre taken as {:.1} px sd per axis ({:.0}% of the longer side), as one photo cannot fix it and the focal length together",
            q.sd,
            100.0 * q.sd / width.max(height) as f64
        ));
    }
    let names = fit.names();
    let mut vals = Vec::new();
    s.k.pack(&fit, &mut vals);
    let parameters: Vec<Param> = names
        .iter()
        .zip(&vals)
        .enumerate()
        .map(|(i, (n, v))| Param {
            name: n.clone(),
            value: *v,
            sd: sd(i),
            interval: None,
        })
        .collect();
    let mut parameters = parameters;
    if let Some([lo, hi]) = f_interval {
        let p = &mut parameters[0];
        p.interval = Some([lo, hi]);
        p.sd = p.sd.max(p.value - lo).max(hi - p.value);
    }
    let ni = fit.intrinsic_count();
    let out_views = view_results(views, &s, &r, &cov, joint.as_ref(), ni);
    let npts: usize = views.iter().map(|v| v.px.len()).sum();
    let mut warnings = Vec::new();
    if let Some(f) = parameters
        .first()
        .filter(|_| fit.focal)
        .filter(|f| f.sd > 0.01 * f.value)
    {
        let range = f
            .interval
            .map(|[a, b]| format!(", 68% range {a:.0}..{b:.0} px"))
            .unwrap_or_default();
        warnings.push(format!(
            "the focal length is poorly determined ({:.0} ± {:.0} px, {:.1}%{range}): focal length and distance trade off when the board is seen nearly head-on; tilt the board 30-45 degrees towards the camera, or calibrate the intrinsics from several photos (glint calibrate --images ...)",
            f.value,
            f.sd,
            100.0 * f.sd / f.value
        ));
    }
    Calibration {
        width,
        height,
        intrinsics: s.k,
        fit,
        parameters,
        rms_px: (s.ssr / npts as f64).sqrt(),
        sigma_px: sigma2.sqrt(),
        views: out_views,
        candidates,
        uncertainty_includes: includes,
        held_fit: joint.map(|j| j.fit),
        warnings,
    }
}

/// Covariance sigma^2 (J^T J)^-1 of the `params` parameters whose Jacobian is `j`.
fn covariance_of(j: &DMatrix<f64>, params: usize, sigma2: f64) -> DMatrix<f64> {
    // Covariance sigma^2 (J^T J)^-1 from the SVD of J itself with its columns scaled to
    // unit length: J^T J spans many decades (focal length in pixels, rotations in radians),
    // and the SVD of J^T J itself gave covariances with negative variances (its left and
    // right singular vectors part ways in the small directions). With J D = U S V^T,
    // (J^T J)^-1 = D V S^-2 V^T D: positive semi-definite by construction. Singular values
    // are floored at 1e-7 of the largest, so an undetermined direction gets a huge variance,
    // never zero.
    let scale = DVector::from_iterator(
        params,
        (0..params).map(|c| {
            let n = j.column(c).norm();
            if n > 0.0 && n.is_finite() {
                1.0 / n
            } else {
                1.0
            }
        }),
    );
    let mut js = j.clone();
    for c in 0..params {
        js.column_mut(c).scale_mut(scale[c]);
    }
    let svd = js.svd(false, true);
    let smax = svd.singular_values.max();
    match &svd.v_t {
        Some(vt) if smax.is_finite() && smax > 0.0 => {
            let inv = DVector::from_iterator(
                svd.singular_values.len(),
                svd.singular_values
                    .iter()
                    .map(|v| 1.0 / v.max(smax * 1e-7).powi(2)),
            );
            let v = vt.transpose();
            let d = DMatrix::from_diagonal(&scale);
            &d * &v * DMatrix::from_diagonal(&inv) * v.transpose() * &d * sigma2
        }
        _ => DMatrix::from_element(params, params, f64::INFINITY),
    }
}

/// The held parameters `h` marginalised into the fitted ones' covariance (`j` their
/// Jacobian, `sigma2` the residuals' variance): the widened covariance, the joint blocks
/// with the held parameters where finite, and the words for what the uncertainty
/// includes. None where the widened covariance is not finite. `side`: the image's longer
/// side, px.
fn marginalise_held(
    views: &[ViewObs],
    h: &Held,
    s: &Solved,
    j: &DMatrix<f64>,
    sigma2: f64,
    fit: Fit,
    side: usize,
) -> Option<(DMatrix<f64>, Option<HeldJoint>, String)> {
    // The held parameters c, with prior covariance S, marginalised at first order:
    // cov = sigma^2 [J^T J - B (C + sigma^2 S^-1)^-1 B^T]^-1, B = J^T J_c, C = J_c^T J_c
    // (the fitted block of the joint covariance of a fit with c free and S as its
    // prior), so the data's own hold on c counts as well as the prior.
    let (_, jx, _) = residuals_and_jacobian(views, h.fit, &s.k, &s.poses);
    let jh = DMatrix::from_fn(j.nrows(), h.columns.len(), |r, c| jx[(r, h.columns[c])]);
    let b = j.transpose() * &jh;
    let c = jh.transpose() * &jh;
    let s_inv = sym_inverse(&h.covariance, 1e-12);
    let inner = sym_inverse(&(c + s_inv * sigma2), 1e-14);
    let m = j.transpose() * j - &b * &inner * b.transpose();
    let widened = sym_inverse(&m, 1e-14) * sigma2;
    if !widened.iter().all(|x| x.is_finite()) {
        return None;
    }
    // The rest of the joint posterior's inverse, block by block: with
    // D = C + sigma^2 S^-1, cov(fitted, held) = -W B D^-1 and
    // cov(held, held) = sigma^2 D^-1 + D^-1 B^T W B D^-1, W the widened covariance.
    let cross = -(&widened * &b * &inner);
    let hh = &inner * sigma2 + &inner * b.transpose() * &widened * &b * &inner;
    let joint = cross
        .iter()
        .chain(hh.iter())
        .all(|x| x.is_finite())
        .then(|| HeldJoint {
            fit: h.fit,
            columns: h.columns.clone(),
            cross,
            hh,
        });
    let includes = if fit.focal {
        format!(
            "the principal point held at the image centre, its offset taken as {:.1} px sd per axis ({:.0}% of the longer side)",
            h.covariance[(0, 0)].sqrt(),
            100.0 * h.covariance[(0, 0)].sqrt() / side as f64
        )
    } else {
        format!("the held intrinsics' covariance ({})", h.fit.describe())
    };
    Some((widened, joint, includes))
}

/// Each view's result: its pose with its sd and covariance (with the intrinsics' `ni`
/// parameters, and with the held ones where `joint` is given), its camera centre and
/// the residuals `r` of its corners.
fn view_results(
    views: &[ViewObs],
    s: &Solved,
    r: &DVector<f64>,
    cov: &DMatrix<f64>,
    joint: Option<&HeldJoint>,
    ni: usize,
) -> Vec<ViewResult> {
    let sd = |i: usize| cov[(i, i)].max(0.0).sqrt();
    let mut out_views = Vec::new();
    let mut off = 0;
    for (vi, (v, pose)) in views.iter().zip(&s.poses).enumerate() {
        let n = v.px.len();
        let res: Vec<[f64; 2]> = (0..n)
            .map(|k| [r[off + 2 * k], r[off + 2 * k + 1]])
            .collect();
        off += 2 * n;
        let rm = super::camera::rotation(pose.rvec);
        let c = -(rm.transpose() * nalgebra::Vector3::from(pose.t));
        let mut psd = [0.0; 6];
        for (k, x) in psd.iter_mut().enumerate() {
            *x = sd(ni + 6 * vi + k);
        }
        let idx: Vec<usize> = (0..ni).chain(ni + 6 * vi..ni + 6 * vi + 6).collect();
        let covariance = idx
            .iter()
            .map(|&a| idx.iter().map(|&b| cov[(a, b)]).collect())
            .collect();
        let held_covariance = joint.map(|j| j.view(cov, ni, vi)).unwrap_or_default();
        let pose_cov = DMatrix::from_fn(6, 6, |a, b| cov[(ni + 6 * vi + a, ni + 6 * vi + b)]);
        let centre_cov = centre_covariance(pose, &pose_cov);
        out_views.push(ViewResult {
            name: v.name.clone(),
            pose: *pose,
            pose_sd: psd,
            camera_centre: [c.x, c.y, c.z],
            camera_centre_sd: [0, 1, 2].map(|i| centre_cov[i][i].max(0.0).sqrt()),
            camera_centre_covariance: centre_cov,
            distance: c.norm(),
            rms_px: (res.iter().map(|e| e[0] * e[0] + e[1] * e[1]).sum::<f64>() / n as f64).sqrt(),
            residuals: res,
            covariance,
            held_covariance,
        });
    }
    out_views
}

/// The held parameters' joint covariance blocks with the fitted ones.
struct HeldJoint {
    /// The fitted and held intrinsics together.
    fit: Fit,
    /// The held parameters' columns among `fit`'s intrinsics (the others are the fitted
    /// intrinsics, in order).
    columns: Vec<usize>,
    /// cov(fitted, held).
    cross: DMatrix<f64>,
    /// cov(held, held).
    hh: DMatrix<f64>,
}

impl HeldJoint {
    /// View `vi`'s joint covariance of every intrinsic of `fit` and its pose, given the
    /// fitted parameters' covariance `cov` (`ni` intrinsics, then 6 per view).
    fn view(&self, cov: &DMatrix<f64>, ni: usize, vi: usize) -> Vec<Vec<f64>> {
        let (held_fit, columns, cross, hh) = (&self.fit, &self.columns, &self.cross, &self.hh);
        #[derive(Clone, Copy)]
        enum Src {
            Fitted(usize),
            Held(usize),
        }
        let mut fitted = 0;
        let mut idx: Vec<Src> = (0..held_fit.intrinsic_count())
            .map(|a| match columns.iter().position(|&c| c == a) {
                Some(q) => Src::Held(q),
                None => {
                    fitted += 1;
                    Src::Fitted(fitted - 1)
                }
            })
            .collect();
        if fitted != ni {
            return Vec::new();
        }
        idx.extend((0..6).map(|k| Src::Fitted(ni + 6 * vi + k)));
        let at = |a: Src, b: Src| match (a, b) {
            (Src::Fitted(i), Src::Fitted(j)) => cov[(i, j)],
            (Src::Fitted(i), Src::Held(q)) => cross[(i, q)],
            (Src::Held(q), Src::Fitted(j)) => cross[(j, q)],
            (Src::Held(p), Src::Held(q)) => hh[(p, q)],
        };
        idx.iter()
            .map(|&a| idx.iter().map(|&b| at(a, b)).collect())
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::super::camera::project;
    use super::*;

    /// With the lens held at a profile that is itself uncertain, the fitted pose turns and
    /// moves to make up for the profile's error, so the camera maps the board's plane
    /// nearly right even where the board is not (beside it, where a tile lies). The joint
    /// covariance of the held intrinsics and the pose (`held_covariance`) says how far off
    /// that mapping is: over seeded trials (profile error drawn from its covariance, corner
    /// noise), the projection error of a point beside the board has mean squared
    /// Mahalanobis distance 2 (chi-square, 2 degrees of freedom). The pose's covariance
    /// alone, with the intrinsics taken as exact, overstates it many times over (it was
    /// what the fit's camera draws used, and n's intervals covered 98.7% instead of 95%).
    #[test]
    fn the_held_lens_and_the_pose_are_drawn_together() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal, StandardNormal};
        let truth = Intrinsics {
            fx: 800.0,
            fy: 800.0,
            cx: 330.0,
            cy: 236.0,
            radial: vec![-0.1],
            tangential: None,
        };
        let lens_fit = Fit {
            principal_point: true,
            radial: 1,
            ..Fit::simplest()
        };
        // The profile's covariance (f, cx, cy, k1): a few lens-session views' worth.
        let sds = [0.6, 0.35, 0.35, 0.001];
        let s_cov = DMatrix::from_fn(4, 4, |i, j| if i == j { sds[i] * sds[i] } else { 0.0 });
        let lens = LensCovariance {
            fit: lens_fit,
            covariance: s_cov,
        };
        let world: Vec<[f64; 3]> = (0..6)
            .flat_map(|j| (0..9).map(move |i| [i as f64, j as f64, 0.0]))
            .collect();
        let pose = Pose {
            rvec: [0.35, -0.2, 0.05],
            t: [-4.0, -2.5, 16.0],
        };
        // Beside the board, in its plane and in view.
        let beside = [11.0, 2.5, 0.0];
        let noise = Normal::new(0.0, 0.05).unwrap();
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(17);
        let (mut joint_d2, mut pose_d2) = (0.0, 0.0);
        let trials = 200;
        for _ in 0..trials {
            let mut k = truth.clone();
            let d: Vec<f64> = sds
                .iter()
                .map(|sd| {
                    let z: f64 = StandardNormal.sample(&mut rng);
                    sd * z
                })
                .collect();
            k.fx += d[0];
            k.fy += d[0];
            k.cx += d[1];
            k.cy += d[2];
            k.radial[0] += d[3];
            let px = world
                .iter()
                .map(|w| {
                    let q = project(&truth, &pose, *w, None).uv;
                    [q[0] + noise.sample(&mut rng), q[1] + noise.sample(&mut rng)]
                })
                .collect();
            let views = [ViewObs {
                name: "grid".into(),
                world: world.clone(),
                px,
            }];
            let cal = pose_with_lens(&views, 640, 480, &k, Some(&lens)).unwrap();
            assert_eq!(cal.held_fit, Some(lens_fit));
            let v = &cal.views[0];
            // The joint covariance's pose block is the pose's covariance.
            for a in 0..6 {
                for b in 0..6 {
                    let (x, y) = (v.held_covariance[4 + a][4 + b], v.covariance[a][b]);
                    assert!((x - y).abs() <= 1e-9 * (x.abs() + y.abs()) + 1e-300);
                }
            }
            let est = project(&k, &v.pose, beside, Some(&lens_fit));
            let tru = project(&truth, &pose, beside, None).uv;
            let e = nalgebra::Vector2::new(est.uv[0] - tru[0], est.uv[1] - tru[1]);
            let jac = DMatrix::from_fn(2, 10, |r, c| {
                if c < 4 {
                    est.d_intrinsics[c][r]
                } else {
                    est.d_pose[c - 4][r]
                }
            });
            let cov = DMatrix::from_fn(10, 10, |a, b| v.held_covariance[a][b]);
            let cov_pose = DMatrix::from_fn(10, 10, |a, b| {
                if a >= 4 && b >= 4 {
                    v.covariance[a - 4][b - 4]
                } else {
                    0.0
                }
            });
            let d2 = |c: &DMatrix<f64>| {
                let m = &jac * c * jac.transpose();
                let m = nalgebra::Matrix2::new(m[(0, 0)], m[(0, 1)], m[(1, 0)], m[(1, 1)]);
                (e.transpose() * m.try_inverse().unwrap() * e)[0]
            };
            joint_d2 += d2(&cov) / trials as f64;
            pose_d2 += d2(&cov_pose) / trials as f64;
        }
        eprintln!("mean squared distance: joint {joint_d2:.3}, the pose alone {pose_d2:.3}");
        // The mean of 200 chi-square(2) values: 2, sd 0.14.
        assert!(
            (1.5..2.6).contains(&joint_d2),
            "joint draws: mean squared distance {joint_d2:.2}, want 2"
        );
        assert!(
            pose_d2 < 0.5 * joint_d2,
            "the pose alone: mean squared distance {pose_d2:.2}, joint {joint_d2:.2}"
        );
    }

    /// The problem's residuals and Jacobian are camera::project's, view by view, to the
    /// last bit (ill-determined fits, a head-on view, follow different paths otherwise).
    #[test]
    fn residuals_and_jacobian_are_projects() {
        let world: Vec<[f64; 3]> = (0..6)
            .flat_map(|j| (0..9).map(move |i| [i as f64, j as f64, 0.1 * (i * j) as f64]))
            .collect();
        let k = Intrinsics {
            fx: 540.0,
            fy: 530.0,
            cx: 330.0,
            cy: 235.0,
            radial: vec![-0.29, 0.1, -0.02],
            tangential: Some([1e-3, -4e-4]),
        };
        let poses = [
            Pose {
                rvec: [0.3, -0.4, 0.1],
                t: [-4.0, -2.0, 15.0],
            },
            Pose {
                rvec: [0.0, 0.0, 0.0],
                t: [-3.0, -3.0, 12.0],
            },
            Pose {
                rvec: [-0.05, 0.6, 2.9],
                t: [3.0, 1.0, 18.0],
            },
        ];
        let views: Vec<ViewObs> = poses
            .iter()
            .enumerate()
            .map(|(n, p)| ViewObs {
                name: format!("v{n}"),
                world: world.clone(),
                px: world
                    .iter()
                    .map(|w| {
                        let q = project(&k, p, *w, None).uv;
                        [q[0] + 0.3, q[1] - 0.2]
                    })
                    .collect(),
            })
            .collect();
        let fits = [
            Fit::simplest(),
            Fit {
                aspect: true,
                principal_point: true,
                radial: 3,
                tangential: true,
                ..Fit::simplest()
            },
            Fit::pose_only(),
        ];
        for fit in fits {
            let (r, j, _) = residuals_and_jacobian(&views, fit, &k, &poses);
            let ni = fit.intrinsic_count();
            let mut row = 0;
            for (vi, (v, pose)) in views.iter().zip(&poses).enumerate() {
                for (w, p) in v.world.iter().zip(&v.px) {
                    let q = project(&k, pose, *w, Some(&fit));
                    for a in 0..2 {
                        assert_eq!(r[row + a], q.uv[a] - p[a]);
                        for (c, d) in q.d_intrinsics.iter().enumerate() {
                            assert_eq!(j[(row + a, c)], d[a], "{fit:?} intrinsic {c}");
                        }
                        for (c, d) in q.d_pose.iter().enumerate() {
                            assert_eq!(
                                j[(row + a, ni + 6 * vi + c)],
                                d[a],
                                "{fit:?} view {vi} pose {c}"
                            );
                        }
                    }
                    row += 2;
                }
            }
        }
    }
}
