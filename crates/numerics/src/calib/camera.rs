//! The camera model of docs/design.md: X_cam = R X + t; x = X/Z, y = Y/Z;
//! d = 1 + k1 r^2 + k2 r^4 (+ k3 r^6 where the data call for it), and, only where the data
//! call for it, tangential terms (p1, p2, Brown's model, as OpenCV's);
//! u = fx (d x + tangential) + cx, v = fy (d y + tangential) + cy. Pixel (0, 0) is the
//! centre of the top-left pixel.
//!
//! Projection returns its derivatives too (analytic; checked against finite differences
//! in the tests).

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

/// Largest distortion coefficient (|k1|..|k3|, |p1|, |p2|) a camera file may hold, and a
/// calibration may free: a term beyond it is one the photos do not determine (a single
/// grid photo covering little of the image once gave k3 = 3186 ± 618).
pub const MAX_DISTORTION: f64 = 1e3;

/// Intrinsics.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// k1, k2, k3 (as many as fitted; absent terms are zero).
    pub radial: Vec<f64>,
    /// p1, p2, when fitted.
    pub tangential: Option<[f64; 2]>,
}

impl Intrinsics {
    /// Every distortion term finite and within [`MAX_DISTORTION`].
    pub fn distortion_in_bounds(&self) -> bool {
        self.radial
            .iter()
            .chain(self.tangential.iter().flatten())
            .all(|x| x.is_finite() && x.abs() <= MAX_DISTORTION)
    }
}

/// The intrinsics as the stage files hold them (field for field the same).
impl From<&glint_format::stage::fit::Intrinsics> for Intrinsics {
    fn from(k: &glint_format::stage::fit::Intrinsics) -> Self {
        Intrinsics {
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            radial: k.radial.clone(),
            tangential: k.tangential,
        }
    }
}

impl From<&Intrinsics> for glint_format::stage::fit::Intrinsics {
    fn from(k: &Intrinsics) -> Self {
        glint_format::stage::fit::Intrinsics {
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            radial: k.radial.clone(),
            tangential: k.tangential,
        }
    }
}

/// A camera pose: X_cam = R(rvec) X_world + t, rvec a rotation vector (axis times angle).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub rvec: [f64; 3],
    pub t: [f64; 3],
}

/// Which parameters a fit frees.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Fit {
    /// The focal length (false only when the intrinsics are known and held).
    pub focal: bool,
    /// fx and fy separately (otherwise square pixels, fx = fy).
    pub aspect: bool,
    /// The principal point (otherwise the image centre).
    pub principal_point: bool,
    /// Number of radial terms, 0..=3.
    pub radial: usize,
    /// p1, p2.
    pub tangential: bool,
}

impl Fit {
    /// Number of intrinsic parameters.
    pub fn intrinsic_count(&self) -> usize {
        self.focal as usize * (1 + self.aspect as usize)
            + 2 * self.principal_point as usize
            + self.radial
            + 2 * self.tangential as usize
    }

    /// Names of the intrinsic parameters, in order.
    pub fn names(&self) -> Vec<String> {
        let mut n = Vec::new();
        if !self.focal {
        } else if self.aspect {
            n.extend(["fx".to_string(), "fy".to_string()]);
        } else {
            n.push("f".into());
        }
        if self.principal_point {
            n.extend(["cx".to_string(), "cy".to_string()]);
        }
        for k in 0..self.radial {
            n.push(format!("k{}", k + 1));
        }
        if self.tangential {
            n.extend(["p1".to_string(), "p2".to_string()]);
        }
        n
    }

    /// A short description, e.g. "f, k1, k2".
    pub fn describe(&self) -> String {
        if self.intrinsic_count() == 0 {
            return "pose only (intrinsics held)".into();
        }
        self.names().join(", ")
    }

    /// The simplest model: square pixels, centred principal point, no distortion.
    pub fn simplest() -> Self {
        Fit {
            focal: true,
            aspect: false,
            principal_point: false,
            radial: 0,
            tangential: false,
        }
    }

    /// Nothing intrinsic: the pose alone.
    pub fn pose_only() -> Self {
        Fit {
            focal: false,
            aspect: false,
            principal_point: false,
            radial: 0,
            tangential: false,
        }
    }
}

impl Intrinsics {
    /// The fitted parameters as a vector, in `fit`'s order.
    pub fn pack(&self, fit: &Fit, out: &mut Vec<f64>) {
        if !fit.focal {
        } else if fit.aspect {
            out.extend([self.fx, self.fy]);
        } else {
            out.push(0.5 * (self.fx + self.fy));
        }
        if fit.principal_point {
            out.extend([self.cx, self.cy]);
        }
        for k in 0..fit.radial {
            out.push(self.radial.get(k).copied().unwrap_or(0.0));
        }
        if fit.tangential {
            out.extend(self.tangential.unwrap_or([0.0; 2]));
        }
    }

    /// Set from a vector in `fit`'s order (the principal point stays where it is when not
    /// fitted); returns the number of values read.
    pub fn unpack(&mut self, fit: &Fit, v: &[f64]) -> usize {
        let mut i = 0;
        if !fit.focal {
        } else if fit.aspect {
            self.fx = v[0];
            self.fy = v[1];
            i = 2;
        } else {
            self.fx = v[0];
            self.fy = v[0];
            i += 1;
        }
        if fit.principal_point {
            self.cx = v[i];
            self.cy = v[i + 1];
            i += 2;
        }
        // Terms not fitted keep their values (known intrinsics held in a pose-only fit).
        if self.radial.len() < fit.radial {
            self.radial.resize(fit.radial, 0.0);
        }
        self.radial[..fit.radial].copy_from_slice(&v[i..i + fit.radial]);
        i += fit.radial;
        if fit.tangential {
            self.tangential = Some([v[i], v[i + 1]]);
            i += 2;
        }
        i
    }
}

impl Intrinsics {
    /// The normalised, undistorted image point (x, y) = (X/Z, Y/Z) seen at pixel (u, v):
    /// the inverse of the distortion, by Newton's method on the 2x2 distortion map
    /// (fixed-point iteration stalls for strong barrel distortion at the image corners).
    /// None where it does not converge (outside the lens model's valid field).
    pub fn undistort(&self, u: f64, v: f64) -> Option<[f64; 2]> {
        let xd = (u - self.cx) / self.fx;
        let yd = (v - self.cy) / self.fy;
        let kk = |i: usize| self.radial.get(i).copied().unwrap_or(0.0);
        let (k1, k2, k3) = (kk(0), kk(1), kk(2));
        let [p1, p2] = self.tangential.unwrap_or([0.0; 2]);
        let (mut x, mut y) = (xd, yd);
        for _ in 0..50 {
            let r2 = x * x + y * y;
            let d = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            let dd = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3);
            let fx = x * d + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd;
            let fy = y * d + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd;
            let a11 = d + 2.0 * x * x * dd + 2.0 * p1 * y + 6.0 * p2 * x;
            let a12 = 2.0 * x * y * dd + 2.0 * p1 * x + 2.0 * p2 * y;
            let a22 = d + 2.0 * y * y * dd + 6.0 * p1 * y + 2.0 * p2 * x;
            let det = a11 * a22 - a12 * a12;
            if det.abs() < 1e-12 {
                return None;
            }
            let dx = (a22 * fx - a12 * fy) / det;
            let dy = (a11 * fy - a12 * fx) / det;
            x -= dx;
            y -= dy;
            if dx.abs().max(dy.abs()) < 1e-14 {
                return Some([x, y]);
            }
        }
        None
    }
}

/// [v]x, the cross-product matrix.
fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// Rotation matrix of a rotation vector (Rodrigues).
pub fn rotation(r: [f64; 3]) -> Matrix3<f64> {
    let v = Vector3::from(r);
    nalgebra::Rotation3::new(v).into_inner()
}

/// Rotation vector of a rotation matrix (orthonormalised first).
pub fn rotation_vector(m: &Matrix3<f64>) -> [f64; 3] {
    let r = nalgebra::Rotation3::from_matrix(m);
    let v = r.scaled_axis();
    [v.x, v.y, v.z]
}

/// d(R(v) p)/dv (Gallego & Yezzi 2015): -R [p]x (v v^T + (R^T - I)[v]x) / |v|^2.
fn d_rotate(v: &Vector3<f64>, r: &Matrix3<f64>, p: &Vector3<f64>) -> Matrix3<f64> {
    let n2 = v.norm_squared();
    if n2 < 1e-20 {
        return -skew(p);
    }
    -r * skew(p) * (v * v.transpose() + (r.transpose() - Matrix3::identity()) * skew(v)) / n2
}

/// A pixel and its derivatives by the intrinsic parameters (in `fit`'s order) and by the
/// pose (rvec, t).
pub struct Projection {
    pub uv: [f64; 2],
    pub d_intrinsics: Vec<[f64; 2]>,
    pub d_pose: [[f64; 2]; 6],
    /// Depth of the point in front of the camera.
    pub depth: f64,
}

/// A point's lens terms at its normalised coordinates (x, y) = (X/Z, Y/Z): the distorted
/// (xd, yd), r^2, the radial factor d and its derivative by r^2, dd, the tangential p.
pub struct LensTerms {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub xd: f64,
    pub yd: f64,
    pub r2: f64,
    pub d: f64,
    pub dd: f64,
    pub p: [f64; 2],
}

/// The pixel's derivatives by the intrinsics, in `fit`'s order (each given to `put`), and
/// by the point in the camera's frame (returned, 2 x 3). One place for both
/// [`project`] and the calibration's Jacobian, so that they agree to the last bit.
#[inline]
pub fn pixel_derivatives(
    k: &Intrinsics,
    fit: &Fit,
    t: &LensTerms,
    put: &mut impl FnMut([f64; 2]),
) -> [[f64; 3]; 2] {
    let LensTerms {
        x,
        y,
        z,
        xd,
        yd,
        r2,
        d,
        dd,
        p: [p1, p2],
    } = *t;
    if !fit.focal {
    } else if fit.aspect {
        put([xd, 0.0]);
        put([0.0, yd]);
    } else {
        put([xd, yd]);
    }
    if fit.principal_point {
        put([1.0, 0.0]);
        put([0.0, 1.0]);
    }
    let mut rn = r2;
    for _ in 0..fit.radial {
        put([k.fx * x * rn, k.fy * y * rn]);
        rn *= r2;
    }
    if fit.tangential {
        put([k.fx * 2.0 * x * y, k.fy * (r2 + 2.0 * y * y)]);
        put([k.fx * (r2 + 2.0 * x * x), k.fy * 2.0 * x * y]);
    }
    // d(xd, yd)/d(x, y)
    let a11 = d + 2.0 * x * x * dd + 2.0 * p1 * y + 6.0 * p2 * x;
    let a12 = 2.0 * x * y * dd + 2.0 * p1 * x + 2.0 * p2 * y;
    let a21 = a12;
    let a22 = d + 2.0 * y * y * dd + 6.0 * p1 * y + 2.0 * p2 * x;
    // d(x, y)/d(Xc)
    let iz = 1.0 / z;
    let dx = [iz, 0.0, -x * iz];
    let dy = [0.0, iz, -y * iz];
    // d(u, v)/d(Xc), 2 x 3
    let mut duv = [[0.0; 3]; 2];
    for c in 0..3 {
        duv[0][c] = k.fx * (a11 * dx[c] + a12 * dy[c]);
        duv[1][c] = k.fy * (a21 * dx[c] + a22 * dy[c]);
    }
    duv
}

/// Project world point `p` (with derivatives when `fit` is given).
pub fn project(k: &Intrinsics, pose: &Pose, p: [f64; 3], fit: Option<&Fit>) -> Projection {
    let v = Vector3::from(pose.rvec);
    let r = rotation(pose.rvec);
    let pw = Vector3::from(p);
    let xc = r * pw + Vector3::from(pose.t);
    let (x, y) = (xc.x / xc.z, xc.y / xc.z);
    let r2 = x * x + y * y;
    let kk = |i: usize| k.radial.get(i).copied().unwrap_or(0.0);
    let (k1, k2, k3) = (kk(0), kk(1), kk(2));
    let d = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
    let dd = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3);
    let [p1, p2] = k.tangential.unwrap_or([0.0; 2]);
    let xd = x * d + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
    let yd = y * d + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
    let uv = [k.fx * xd + k.cx, k.fy * yd + k.cy];
    let Some(fit) = fit else {
        return Projection {
            uv,
            d_intrinsics: Vec::new(),
            d_pose: [[0.0; 2]; 6],
            depth: xc.z,
        };
    };
    let mut di = Vec::with_capacity(fit.intrinsic_count());
    let lens = LensTerms {
        x,
        y,
        z: xc.z,
        xd,
        yd,
        r2,
        d,
        dd,
        p: [p1, p2],
    };
    let duv = pixel_derivatives(k, fit, &lens, &mut |g| di.push(g));
    let dr = d_rotate(&v, &r, &pw);
    let mut dp = [[0.0; 2]; 6];
    for j in 0..3 {
        for row in 0..2 {
            dp[j][row] = (0..3).map(|c| duv[row][c] * dr[(c, j)]).sum();
            dp[3 + j][row] = duv[row][j];
        }
    }
    Projection {
        uv,
        d_intrinsics: di,
        d_pose: dp,
        depth: xc.z,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distortion_beyond_the_files_bound_is_out_of_bounds() {
        let mut k = Intrinsics {
            fx: 1000.0,
            fy: 1000.0,
            cx: 320.0,
            cy: 240.0,
            radial: vec![-0.3, 0.1],
            tangential: Some([1e-3, -1e-3]),
        };
        assert!(k.distortion_in_bounds());
        k.radial.push(3185.7);
        assert!(!k.distortion_in_bounds());
        k.radial[2] = f64::NAN;
        assert!(!k.distortion_in_bounds());
        k.radial.pop();
        k.tangential = Some([0.0, -2e3]);
        assert!(!k.distortion_in_bounds());
    }
}
