//! Tsai's coplanar calibration (Tsai 1987), used as the start for the refinement: the
//! principal point at the image centre, square pixels, no distortion. Needs no start
//! values: the radial alignment constraint gives R and (tx, ty) by linear least squares,
//! then f and tz follow from a second linear solve.

use nalgebra::{DMatrix, DVector, Matrix3};

use super::camera::{rotation_vector, Pose};

/// f (pixels) and the pose, from world points on z = 0 and their pixels, with the
/// principal point at `c`. None when the view gives no solution (fewer than 5 points,
/// or points that are collinear).
///
/// When the view cannot separate f from the distance (the board seen head-on: the second
/// solve is singular), f is taken as `f_guess` and the distance follows from the board's
/// size in the image; the refinement and its uncertainties then tell how little the view
/// says about f.
pub fn tsai(world: &[[f64; 3]], px: &[[f64; 2]], c: [f64; 2], f_guess: f64) -> Option<(f64, Pose)> {
    let n = world.len();
    if n < 5 {
        return None;
    }
    // Step 1: (r1, r2, tx, r4, r5) / ty.
    let mut a = DMatrix::zeros(n, 5);
    let mut b = DVector::zeros(n);
    for (k, (w, p)) in world.iter().zip(px).enumerate() {
        let (xd, yd) = (p[0] - c[0], p[1] - c[1]);
        a.set_row(
            k,
            &nalgebra::RowDVector::from_row_slice(&[
                yd * w[0],
                yd * w[1],
                yd,
                -xd * w[0],
                -xd * w[1],
            ]),
        );
        b[k] = xd;
    }
    let s = a.svd(true, true).solve(&b, 1e-12).ok()?;
    let (r1p, r2p, txp, r4p, r5p) = (s[0], s[1], s[2], s[3], s[4]);
    // Step 2: ty^2.
    let sr = r1p * r1p + r2p * r2p + r4p * r4p + r5p * r5p;
    let det = r1p * r5p - r4p * r2p;
    let ty2 = if det.abs() > 1e-12 {
        (sr - (sr * sr - 4.0 * det * det).max(0.0).sqrt()) / (2.0 * det * det)
    } else {
        // One row or column of C is zero: ty^2 = 1 / (sum of squares of the other pair).
        let pairs = [
            r1p * r1p + r2p * r2p,
            r4p * r4p + r5p * r5p,
            r1p * r1p + r4p * r4p,
            r2p * r2p + r5p * r5p,
        ];
        1.0 / pairs.iter().cloned().fold(0.0, f64::max)
    };
    if !(ty2.is_finite() && ty2 > 0.0) {
        return None;
    }
    // Step 3: the sign of ty, from the point farthest from the centre.
    let far = (0..n)
        .max_by(|&i, &j| {
            let d = |k: usize| (px[k][0] - c[0]).hypot(px[k][1] - c[1]);
            d(i).total_cmp(&d(j))
        })
        .unwrap();
    let mut ty = ty2.sqrt();
    let (xd, yd) = (px[far][0] - c[0], px[far][1] - c[1]);
    let xc = r1p * ty * world[far][0] + r2p * ty * world[far][1] + txp * ty;
    let yc = r4p * ty * world[far][0] + r5p * ty * world[far][1] + ty;
    if xc.signum() != xd.signum() || yc.signum() != yd.signum() {
        ty = -ty;
    }
    // Step 4: R.
    let (r1, r2, tx, r4, r5) = (r1p * ty, r2p * ty, txp * ty, r4p * ty, r5p * ty);
    let mut r3 = (1.0 - r1 * r1 - r2 * r2).max(0.0).sqrt();
    let mut r6 = -(r1 * r4 + r2 * r5).signum() * (1.0 - r4 * r4 - r5 * r5).max(0.0).sqrt();
    let solve_f = |r3: f64, r6: f64| {
        let row1 = nalgebra::Vector3::new(r1, r2, r3);
        let row2 = nalgebra::Vector3::new(r4, r5, r6);
        let row3 = row1.cross(&row2);
        // Step 5: f and tz from y_c f - Y tz = Y w and x_c f - X tz = X w.
        let mut a = DMatrix::zeros(2 * n, 2);
        let mut b = DVector::zeros(2 * n);
        for (k, (w, p)) in world.iter().zip(px).enumerate() {
            let (xd, yd) = (p[0] - c[0], p[1] - c[1]);
            let xc = r1 * w[0] + r2 * w[1] + tx;
            let yc = r4 * w[0] + r5 * w[1] + ty;
            let ww = row3.x * w[0] + row3.y * w[1];
            a[(2 * k, 0)] = xc;
            a[(2 * k, 1)] = -xd;
            b[2 * k] = xd * ww;
            a[(2 * k + 1, 0)] = yc;
            a[(2 * k + 1, 1)] = -yd;
            b[2 * k + 1] = yd * ww;
        }
        // Columns scaled to unit length, so the conditioning compares like with like.
        let n0 = a.column(0).norm().max(1e-300);
        let n1 = a.column(1).norm().max(1e-300);
        let mut an = a.clone();
        an.column_mut(0).scale_mut(1.0 / n0);
        an.column_mut(1).scale_mut(1.0 / n1);
        let svd = an.svd(true, true);
        let sv = &svd.singular_values;
        if sv.min() < 1e-3 * sv.max() {
            // Head-on: f and tz inseparable. tz from the board's size in the image.
            let mut ratio: Vec<f64> = world
                .iter()
                .zip(px)
                .filter_map(|(w, p)| {
                    let (xd, yd) = (p[0] - c[0], p[1] - c[1]);
                    let xc = r1 * w[0] + r2 * w[1] + tx;
                    let yc = r4 * w[0] + r5 * w[1] + ty;
                    let den = xd.abs() + yd.abs();
                    (den > 1.0).then(|| (xc.abs() + yc.abs()) / den)
                })
                .collect();
            if ratio.is_empty() {
                return None;
            }
            ratio.sort_by(|a, b| a.total_cmp(b));
            let tz = f_guess * ratio[ratio.len() / 2];
            return Some((f_guess, tz, row1, row2, row3));
        }
        let s = svd.solve(&b, 1e-12).ok()?;
        Some((s[0] / n0, s[1] / n1, row1, row2, row3))
    };
    let (mut f, mut tz, mut row1, mut row2, mut row3) = solve_f(r3, r6)?;
    if f < 0.0 {
        r3 = -r3;
        r6 = -r6;
        (f, tz, row1, row2, row3) = solve_f(r3, r6)?;
    }
    if !(f.is_finite() && f > 0.0 && tz > 0.0) {
        return None;
    }
    let m = Matrix3::from_rows(&[row1.transpose(), row2.transpose(), row3.transpose()]);
    // Nearest rotation.
    let svd = m.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let mut rot = u * vt;
    if rot.determinant() < 0.0 {
        let mut u2 = u;
        u2.column_mut(2).neg_mut();
        rot = u2 * vt;
    }
    Some((
        f,
        Pose {
            rvec: rotation_vector(&rot),
            t: [tx, ty, tz],
        },
    ))
}
