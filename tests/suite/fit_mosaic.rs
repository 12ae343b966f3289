//! A demosaicked camera: the fit reads the colour filter layout from the radiance's noise
//! and keeps each sample's own photosite channel, so a sharp highlight's n is not
//! smoothed by the interpolation. The scene is the simulated lab's rendering (its forward
//! model, not the fitter's) of a sharp Phong lobe (n 3000) at 640x480, put through an RGGB mosaic
//! with 0.3% noise per photosite and demosaicked bilinearly by this file's own code (each
//! missing channel the mean of its nearest photosites of that colour, as OpenCV's
//! `COLOR_Bayer*2RGB` does), with the true camera.

use glint::fit::geometry::Scene;
use glint::fit::model::Model;
use glint::fit::mosaic::{Mosaic, MosaicChoice};
use glint::fit::sample::{sample, RadianceImage, SampleOptions, Sampled};
use glint::fit::solve::{fit, Options, Sample};
use glint::hdr::merge::MASK_OK;
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};

use super::util::{load, set, small_table, tempdir};

const W: usize = 640;
const H: usize = 480;
const N: f64 = 3000.0;
/// Noise per photosite (relative sd).
const NOISE: f64 = 0.003;

/// The lab's noise-free radiance of a Phong tile of exponent `N` and the true scene.
fn render() -> (Vec<f32>, Scene) {
    let dir = tempdir();
    let mut t = small_table();
    set(&mut t, "camera.width", W as i64);
    set(&mut t, "camera.height", H as i64);
    set(&mut t, "mock.camera.fx", 750.0);
    set(&mut t, "mock.camera.fy", 750.0);
    set(&mut t, "mock.tile.model", "phong");
    set(&mut t, "mock.tile.n", N);
    set(
        &mut t,
        "mock.tile.ks",
        toml::Value::Array(vec![0.3.into(), 0.25.into(), 0.2.into()]),
    );
    super::util::truth(&load(dir.path(), &t))
}

/// The radiance through an RGGB mosaic (0.3% noise per photosite, seeded), demosaicked
/// bilinearly; the variance each value would get from a merge that knows nothing of the
/// mosaic (0.3% of the value, squared). On this scene n comes out −1.05% at −8.5 sd from
/// every channel, +0.27% at +1.3 sd from the photosites' own.
fn demosaicked(truth: &[f32]) -> (Vec<f32>, Vec<f32>) {
    let m = Mosaic::Rggb;
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(5);
    let mut raw = vec![0.0f64; W * H];
    for v in 0..H {
        for u in 0..W {
            let z: f64 = StandardNormal.sample(&mut rng);
            raw[v * W + u] = truth[3 * (v * W + u) + m.native(u, v)] as f64 * (1.0 + NOISE * z);
        }
    }
    let mut out = vec![0.0f32; 3 * W * H];
    for v in 0..H {
        for u in 0..W {
            let own = m.native(u, v);
            for c in 0..3 {
                let (mut s, mut k) = (0.0, 0);
                for dv in -1i64..=1 {
                    for du in -1i64..=1 {
                        let (x, y) = (u as i64 + du, v as i64 + dv);
                        if x < 0 || y < 0 || x >= W as i64 || y >= H as i64 {
                            continue;
                        }
                        let (x, y) = (x as usize, y as usize);
                        let keep = m.native(x, y) == c
                            && (own != c || (du, dv) == (0, 0))
                            && (c != 1 || du == 0 || dv == 0);
                        if keep {
                            s += raw[y * W + x];
                            k += 1;
                        }
                    }
                }
                out[3 * (v * W + u) + c] = (s / k as f64) as f32;
            }
        }
    }
    let var = out
        .iter()
        .map(|x| ((NOISE * *x as f64).powi(2) as f32).max(1e-30))
        .collect();
    (out, var)
}

fn fitted(scene: &Scene, rad: &[f32], var: &[f32], mosaic: MosaicChoice) -> (Sampled, f64, f64) {
    let mask = vec![MASK_OK; rad.len()];
    let img = RadianceImage {
        width: W,
        height: H,
        radiance: rad,
        variance: var,
        mask: &mask,
    };
    let so = SampleOptions {
        mosaic,
        ..SampleOptions::default()
    };
    let sampled = sample(scene, &img, &so).unwrap();
    let samples: Vec<Sample> = sampled.samples.iter().map(|p| p.sample).collect();
    let f = fit(Model::Phong, &samples, &Options::default());
    (sampled, f.n.value, f.n.sd)
}

#[test]
fn a_demosaicked_sharp_highlight_is_fitted_from_each_photosites_own_channel() {
    let (truth, scene) = render();
    let (rad, var) = demosaicked(&truth);
    // Every channel of every pixel: the interpolation smooths the highlight.
    let (off, n_off, sd_off) = fitted(&scene, &rad, &var, MosaicChoice::Off);
    // The layout read from the noise: the photosites' own values only.
    let (auto, n_auto, sd_auto) = fitted(&scene, &rad, &var, MosaicChoice::Auto);
    let z = |n: f64, sd: f64| (n - N) / sd;
    println!(
        "n off {n_off:.1} ± {sd_off:.1} ({:+.1} sd, {:+.2}%), auto {n_auto:.1} ± {sd_auto:.1} ({:+.1} sd, {:+.2}%); {:?}",
        z(n_off, sd_off),
        100.0 * (n_off / N - 1.0),
        z(n_auto, sd_auto),
        100.0 * (n_auto / N - 1.0),
        auto.mosaic_detection
    );
    assert_eq!(off.mosaic, None);
    assert_eq!(off.mosaic_source, "off");
    assert_eq!(
        auto.mosaic,
        Some(Mosaic::Rggb),
        "{:?}",
        auto.mosaic_detection
    );
    assert_eq!(auto.mosaic_source, "detected");
    // Each sample holds its photosite's channel and no other.
    for p in &auto.samples {
        let own = Mosaic::Rggb.native(p.u, p.v);
        for c in 0..3 {
            assert_eq!(p.sample.variance[c].is_finite(), c == own, "{p:?}");
        }
    }
    // The interpolation biases n beyond its interval; the photosites' own values do not.
    assert!(z(n_off, sd_off).abs() > 3.0, "n {n_off} ± {sd_off}");
    assert!(z(n_auto, sd_auto).abs() < 3.0, "n {n_auto} ± {sd_auto}");
    // The model choice, its halves holding every colour: Phong.
    let samples: Vec<Sample> = auto.samples.iter().map(|p| p.sample).collect();
    let (_, choice) = glint::fit::run::fit_candidates(&Model::ALL, &samples, &Options::default());
    assert_eq!(choice.chosen, Model::Phong);
    // The layout given by the user is the one read.
    let (given, n_given, _) = fitted(&scene, &rad, &var, MosaicChoice::Given(Mosaic::Rggb));
    assert_eq!(given.mosaic_source, "given");
    assert_eq!(n_given, n_auto);
}

#[test]
fn the_simulated_labs_camera_shows_no_mosaic() {
    // Every channel of every pixel measured (0.3% noise each): nothing is dropped.
    let (truth, scene) = render();
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(6);
    let rad: Vec<f32> = truth
        .iter()
        .map(|x| {
            let z: f64 = StandardNormal.sample(&mut rng);
            (*x as f64 * (1.0 + NOISE * z)) as f32
        })
        .collect();
    let var: Vec<f32> = rad
        .iter()
        .map(|x| ((NOISE * *x as f64).powi(2) as f32).max(1e-30))
        .collect();
    let (s, _, _) = fitted(&scene, &rad, &var, MosaicChoice::Auto);
    assert_eq!(s.mosaic, None, "{:?}", s.mosaic_detection);
    assert_eq!(s.mosaic_source, "none seen");
    let d = s.mosaic_detection.unwrap();
    assert!((0.8..1.25).contains(&d.contrast), "{d:?}");
    assert!(s
        .samples
        .iter()
        .all(|p| p.sample.variance.iter().all(|v| v.is_finite())));
}
