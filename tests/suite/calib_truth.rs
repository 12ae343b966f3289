//! Single-view calibration that tells the truth: on simulated scenes whose principal point
//! is off the image centre (drawn from the prior Glint assumes), the camera centre and the
//! focal length must lie within their stated intervals at about the nominal rate.

use glint::calib::detect::detect;
use glint::calib::solve::{calibrate, Options, ViewObs, PRINCIPAL_POINT_PRIOR};
use glint_mock::config::TrueCamera;
use rand::{RngExt, SeedableRng};
use rand_distr::{Distribution, StandardNormal};
use rand_xoshiro::Xoshiro256PlusPlus;

use super::calib_sim::{geometry, photo, world_points};

/// One random scene: camera position and tilt, focal length, principal point offset
/// (normal, sd = Glint's prior), distortion; seeded.
pub fn scene(seed: u64, w: u32, h: u32) -> TrueCamera {
    let mut r = Xoshiro256PlusPlus::seed_from_u64(seed);
    let side = w.max(h) as f64;
    let mut n = || -> f64 { StandardNormal.sample(&mut r) };
    let (ox, oy) = (n(), n());
    let mut r = Xoshiro256PlusPlus::seed_from_u64(seed ^ 0x5eed);
    let f = side * r.random_range(1.0..1.6);
    let back = r.random_range(220.0..320.0);
    let up = r.random_range(330.0..420.0);
    let cx = (w as f64 - 1.0) / 2.0 + ox * PRINCIPAL_POINT_PRIOR * side;
    let cy = (h as f64 - 1.0) / 2.0 + oy * PRINCIPAL_POINT_PRIOR * side;
    TrueCamera {
        fx: f,
        fy: f,
        cx: Some(cx),
        cy: Some(cy),
        k1: r.random_range(-0.12..0.02),
        k2: r.random_range(-0.02..0.04),
        position_mm: [r.random_range(40.0..120.0), -back, up],
        look_at_mm: [r.random_range(70.0..90.0), r.random_range(40.0..60.0), 0.0],
        roll_deg: r.random_range(-10.0..10.0),
    }
}

/// Per scene: |C - C_true| / sd per axis, and (f - f_true) / sd.
fn z_scores(seeds: std::ops::Range<u64>, w: u32, h: u32) -> Vec<([f64; 3], f64, f64, f64)> {
    let g = geometry(9, 6);
    let mut out = Vec::new();
    for seed in seeds {
        let truth_cam = scene(seed, w, h);
        let (img, truth) = photo(&truth_cam, w, h, &g, 2.0, 1000 + seed);
        let grid = match detect(&img, 9, 6) {
            Ok(g) => g,
            Err(e) => panic!("seed {seed}: {e}"),
        };
        let v = ViewObs {
            name: format!("seed {seed}"),
            world: world_points(9, 6),
            px: grid.corners,
        };
        let cal = calibrate(&[v], w as usize, h as usize, Options::for_views(1)).unwrap();
        let view = &cal.views[0];
        let c_true = truth.cam.centre;
        let z = [0, 1, 2].map(|i| (view.camera_centre[i] - c_true[i]) / view.camera_centre_sd[i]);
        let err = (0..3)
            .map(|i| (view.camera_centre[i] - c_true[i]).powi(2))
            .sum::<f64>()
            .sqrt();
        let f = &cal.parameters[0];
        let zf = (f.value - truth_cam.fx) / f.sd;
        println!(
            "seed {seed}: [{}] pp off ({:+.1}, {:+.1}) px; C off {err:.2} mm, sd ({:.2}, {:.2}, {:.2}), z ({:+.2}, {:+.2}, {:+.2}); f {:.1} ± {:.1} (true {:.1}, {:+.2}%, z {zf:+.2})",
            cal.fit.describe(),
            truth_cam.cx.unwrap() - (w as f64 - 1.0) / 2.0,
            truth_cam.cy.unwrap() - (h as f64 - 1.0) / 2.0,
            view.camera_centre_sd[0],
            view.camera_centre_sd[1],
            view.camera_centre_sd[2],
            z[0],
            z[1],
            z[2],
            f.value,
            f.sd,
            truth_cam.fx,
            100.0 * (f.value / truth_cam.fx - 1.0),
        );
        out.push((z, zf, err, 100.0 * (f.value / truth_cam.fx - 1.0)));
    }
    out
}

fn report(z: &[([f64; 3], f64, f64, f64)]) -> (f64, f64, f64, f64) {
    let n = z.len() as f64;
    let within = |k: f64| {
        z.iter()
            .map(|(c, _, _, _)| c.iter().filter(|x| x.abs() < k).count())
            .sum::<usize>() as f64
            / (3.0 * n)
    };
    let f95 = z.iter().filter(|(_, f, _, _)| f.abs() < 1.96).count() as f64 / n;
    let (c68, c95) = (within(1.0), within(1.96));
    let worst = z.iter().map(|x| x.2).fold(0.0, f64::max);
    let worst_f = z.iter().map(|x| x.3.abs()).fold(0.0, f64::max);
    println!(
        "{} scenes: camera centre within 1 sd {:.0}% (68% nominal), within 1.96 sd {:.0}% (95%); f within 1.96 sd {:.0}%; worst centre error {worst:.2} mm, worst f error {worst_f:.2}%",
        z.len(),
        100.0 * c68,
        100.0 * c95,
        100.0 * f95
    );
    (c68, c95, f95, worst_f)
}

/// 24 scenes at 640x480 with the principal point off centre: the intervals cover the
/// truth at about their nominal rate (per axis of the camera centre, and f).
#[test]
fn single_view_intervals_cover_the_truth_at_their_nominal_rate() {
    let z = z_scores(0..24, 640, 480);
    let (c68, c95, f95, worst_f) = report(&z);
    // At least the nominal rate (measured: 93% within 1 sd, all within 1.96, with a freed
    // principal point fitted under its prior; worst centre error 14.4 mm, worst f 2.9%).
    assert!(c68 >= 0.6, "within 1 sd: {c68}");
    assert!(c95 >= 0.9, "within 1.96 sd: {c95}");
    assert!(f95 >= 0.9, "f within 1.96 sd: {f95}");
    // A freed principal point stays near its prior instead of wandering along the valley
    // one view leaves it in (5.4% with a free fit).
    assert!(worst_f < 4.0, "worst f error {worst_f}%");
}

/// The same over 100 scenes (run by hand: cargo test -- --ignored single_view_sweep).
#[test]
#[ignore]
fn single_view_sweep() {
    let z = z_scores(100..200, 640, 480);
    let (c68, c95, _, _) = report(&z);
    assert!(c68 >= 0.6 && c95 >= 0.9);
}
