//! Calibration on the real chessboard photos in ../shared/data (OpenCV's reference there).

use std::path::PathBuf;

use glint::calib::detect::{detect, Gray};
use glint::calib::solve::{calibrate, Options, ViewObs};

use super::util::shared_data;

fn data() -> Option<PathBuf> {
    shared_data("opencv_stereo_chessboard_9x6")
}

fn reference(d: &std::path::Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(d.join("reference.json")).unwrap()).unwrap()
}

fn points(v: &serde_json::Value) -> Vec<[f64; 2]> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|p| [p[0].as_f64().unwrap(), p[1].as_f64().unwrap()])
        .collect()
}

fn gray(path: &std::path::Path) -> Gray {
    glint::calib::gray_from_image(&image::open(path).unwrap())
}

#[test]
fn corners_match_opencv_on_the_real_photos() {
    let Some(d) = data() else { return };
    let r = reference(&d);
    let mut medians = Vec::new();
    for side in ["left", "right"] {
        for im in r["images"][side].as_array().unwrap() {
            let f = im["file"].as_str().unwrap();
            if !im["found"].as_bool().unwrap() {
                continue;
            }
            let cv = points(&im["corners"]);
            let g = detect(&gray(&d.join("images").join(f)), 9, 6)
                .unwrap_or_else(|e| panic!("{f}: {e}"));
            // Match the order: each of ours to OpenCV's nearest.
            let mut dd: Vec<f64> = g
                .corners
                .iter()
                .map(|p| {
                    cv.iter()
                        .map(|q| (p[0] - q[0]).hypot(p[1] - q[1]))
                        .fold(f64::INFINITY, f64::min)
                })
                .collect();
            dd.sort_by(|a, b| a.total_cmp(b));
            let med = dd[dd.len() / 2];
            println!(
                "{f}: median {med:.4} px, max {:.4} px (window {})",
                dd[dd.len() - 1],
                g.window
            );
            medians.push(med);
        }
    }
    medians.sort_by(|a, b| a.total_cmp(b));
    let all = medians[medians.len() / 2];
    println!(
        "median over photos {all:.4}, worst photo {:.4}",
        medians[medians.len() - 1]
    );
    assert!(medians[medians.len() - 1] < 0.1);
}

fn view(d: &std::path::Path, f: &str) -> ViewObs {
    let g = detect(&gray(&d.join("images").join(f)), 9, 6).unwrap();
    let world: Vec<[f64; 3]> = (0..6)
        .flat_map(|j| (0..9).map(move |i| [i as f64, j as f64, 0.0]))
        .collect();
    let used: Vec<usize> = (0..54)
        .filter(|k| !g.filled.contains(k) && !g.doubtful.contains(k))
        .collect();
    if !g.doubtful.is_empty() {
        println!("{f}: {} doubtful corners left out", g.doubtful.len());
    }
    ViewObs {
        name: f.into(),
        world: used.iter().map(|&k| world[k]).collect(),
        px: used.iter().map(|&k| g.corners[k]).collect(),
    }
}

/// Every model tried, then the chosen one's parameters.
fn print_calibration(c: &glint::calib::solve::Calibration) {
    for cand in &c.candidates {
        println!(
            "{:30} rms {:.4} bic {:.1}",
            cand.parameters, cand.rms_px, cand.bic
        );
    }
    for p in &c.parameters {
        println!("{} = {:.5} ± {:.5}", p.name, p.value, p.sd);
    }
}

#[test]
fn thirteen_left_photos_give_opencvs_intrinsics() {
    let Some(d) = data() else { return };
    let r = reference(&d);
    let cv = &r["calibrations"]["left_all_default"];
    let files: Vec<String> = cv["images_used"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap().to_string())
        .collect();
    let views: Vec<ViewObs> = files.iter().map(|f| view(&d, f)).collect();
    let c = calibrate(&views, 640, 480, Options::for_views(views.len())).unwrap();
    print_calibration(&c);
    let k = &c.intrinsics;
    let m = &cv["camera_matrix"];
    let (fx, cx, cy) = (
        m[0][0].as_f64().unwrap(),
        m[0][2].as_f64().unwrap(),
        m[1][2].as_f64().unwrap(),
    );
    let rms_cv = cv["rms"].as_f64().unwrap();
    println!(
        "Glint: fx {:.2} cx {:.2} cy {:.2} rms {:.4}; OpenCV: fx {fx:.2} cx {cx:.2} cy {cy:.2} rms {rms_cv:.4}",
        k.fx, k.cx, k.cy, c.rms_px
    );
    assert!((k.fx / fx - 1.0).abs() < 0.01);
    assert!((k.cx / cx - 1.0).abs() < 0.01);
    assert!((k.cy / cy - 1.0).abs() < 0.01);
    // Same definition as OpenCV's (root mean squared distance per corner).
    assert!(c.rms_px <= rms_cv, "{} vs {rms_cv}", c.rms_px);
}

#[test]
fn single_view_of_left01() {
    let Some(d) = data() else { return };
    let r = reference(&d);
    let cv = &r["calibrations"]["left01_single_fixpp_zerotangent_fixk3"];
    let v = view(&d, "left01.jpg");
    let c = calibrate(&[v], 640, 480, Options::for_views(1)).unwrap();
    print_calibration(&c);
    let fx_cv = cv["camera_matrix"][0][0].as_f64().unwrap();
    let f = &c.parameters[0];
    println!(
        "left01 alone: Glint [{}] f {:.2} ± {:.2}, rms {:.4}; OpenCV (pp fixed, fx, fy, k1, k2) fx {fx_cv:.2} fy {:.2}, k {}, rms {}",
        c.fit.describe(),
        f.value,
        f.sd,
        c.rms_px,
        cv["camera_matrix"][1][1].as_f64().unwrap(),
        cv["dist_coeffs_k1_k2_p1_p2_k3"],
        cv["rms"]
    );
    assert!(c.warnings.is_empty(), "{:?}", c.warnings);
    // One view: agreement within the view's own uncertainty.
    assert!(
        (f.value - fx_cv).abs() < 3.0 * f.sd,
        "{} ± {} vs {fx_cv}",
        f.value,
        f.sd
    );
}
