//! The polynomial curve's basis: Chebyshev polynomials in ln z over the fitted range, and the
//! highest degree a channel's readings and a bracket's step allow.

/// Highest polynomial degree tried (on frames of more than 12 bits; see
/// [`max_degree`]).
pub const MAX_DEGREE: usize = 16;

/// Whether a channel whose values run to `max` reads finely enough (more than 12 bits) for
/// curves of [`MAX_DEGREE`] ([`max_degree`], [`misfit_degree`]).
pub(super) fn fine_readings(max: u32) -> bool {
    max as usize + 1 > 4096
}

/// Highest degree tried for a channel whose values run to `max`, from a bracket whose
/// exposures step by `step` in ln. Finer readings carry a curve of more detail: on 16-bit EMoR curves
/// degree 10 left -0.3%..-0.7% between 0.9 and 0.98 of full scale, and a broad lobe's n
/// moved 8.6% with it; degree 16 (BIC takes 13-15) leaves 0.1%. (Degree 24 on 16 bit
/// rippled by 1%: the cap is a cap.)
///
/// Up to 12 bits the bracket's step sets it. A curve error periodic in ln z with the
/// step's period moves every reading and the one a step brighter alike, so the readings
/// cannot pin it down, and a polynomial that can bend that finely lets the readings' noise
/// and quantisation into it. Degree k over the fitted range (a width L in ln z) bends with
/// a period of about 2L/k in the middle; the cap keeps that above 0.8 steps: 10 to 14 (14
/// for steps of a stop or less, 10 at 1.5 stops). Measured: with 5 exposures 1.5 stops
/// apart and 20 e read noise, degree 14 rippled by 1.2-1.4% on gamma 1.6 and EMoR curves
/// where 10 stays within 0.2% (`recovered_responses_are_within_one_percent_of_the_truth`);
/// with 7 exposures a stop apart the cap of 10 held BIC back in 165 of 252 channels of the
/// scene family's 8-bit EMoR scenes at 640x480, and what the polynomial could not follow
/// was the same from curve to curve (+0.06% at 0.6 and 0.9 of full scale, -0.13% at 0.98,
/// in 75-80% of them): n leaned high, +0.52% on average from the curve alone (+0.38 of its
/// sd), the one estimate in 72 beyond 3 sd at 1280x960 in seeds 50-99. Under 14 BIC takes
/// 12-14 in 180 of 252 and the lean halves (+0.26%, +0.21 sd).
///
/// Steps wider than 1.5 stops (a lab's 2-stop brackets) lower the cap below 10, at every
/// bit depth: the same rule, floored at 6. Measured on the second scene family
/// (benches/family2, seeds 1000-1099): with 2-stop steps degree 10 on 8 bits and 16 on 16
/// bits let a ripple of the step's period into the curve (+-4% in ln E on an 8-bit EMoR
/// curve, and the radiance 2-15% off on 16-bit ones, linear cameras included), in 39 of
/// 57 such scenes over 1%.
pub(super) fn max_degree(max: u32, step: Option<f64>) -> usize {
    let (lo, hi) = poly_range(max);
    let width = (hi.max(2) as f64 / lo.max(1) as f64).ln();
    let step = step.filter(|s| s.is_finite() && *s > 0.0);
    let by_step = |s: f64| (2.5 * width / s).floor() as usize;
    // Wider than 1.5 stops: the step's own cap, at least 6.
    if let Some(s) = step.filter(|s| *s > 1.5 * std::f64::consts::LN_2 * 1.01) {
        let top = if fine_readings(max) { MAX_DEGREE } else { 14 };
        return by_step(s).clamp(6, top);
    }
    if fine_readings(max) {
        return MAX_DEGREE;
    }
    match step {
        Some(s) => by_step(s).clamp(10, 14),
        None => 10,
    }
}

/// Chebyshev polynomials T_1..T_k at u.
pub(super) fn chebyshev(u: f64, k: usize, out: &mut [f64]) {
    let (mut t0, mut t1) = (1.0, u);
    for (j, o) in out.iter_mut().enumerate().take(k) {
        if j == 0 {
            *o = t1;
        } else {
            let t2 = 2.0 * u * t1 - t0;
            t0 = t1;
            t1 = t2;
            *o = t1;
        }
    }
}

/// The values the polynomial curve may be fitted to (see [`fit_polynomial`], which may
/// raise the bottom further): above the lowest 1/64 of the range.
pub(super) fn poly_range(max: u32) -> (u32, u32) {
    (max.div_ceil(64), max - 1)
}

/// The polynomial response's basis at value z: T_k(u(z)) - T_k(u(mid)), u running from -1
/// to 1 over the fitted range linearly in ln z (so the gauge g(mid) = 0 holds for any
/// coefficients, and the fitted values span the Chebyshev polynomials' whole domain).
pub(super) fn poly_basis(z: f64, k: usize, max: u32, out: &mut [f64]) {
    let (lo, hi) = poly_range(max);
    let top = (hi as f64).ln();
    let bottom = (lo as f64).ln();
    let u = |z: f64| 2.0 * (z.max(0.5).ln() - bottom) / (top - bottom) - 1.0;
    let mut at_mid = [0.0; MAX_DEGREE];
    chebyshev(u(max.div_ceil(2) as f64), k, &mut at_mid);
    chebyshev(u(z), k, out);
    for j in 0..k {
        out[j] -= at_mid[j];
    }
}
