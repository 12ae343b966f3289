//! Calibration on the real chessboard photos in ../shared/data (OpenCV's reference there).

use std::path::PathBuf;

use glint::calib::detect::{detect, Gray};

use super::util::root;

fn data() -> Option<PathBuf> {
    let d = root().join("../shared/data/opencv_stereo_chessboard_9x6");
    if !d.exists() {
        eprintln!(
            "SKIPPED: {} is absent (shared test data, not part of the project)",
            d.display()
        );
        return None;
    }
    Some(d)
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
    Gray::from_image(&image::open(path).unwrap())
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
