//! The fit through the whole simulated pipeline: capture on the mock rig, HDR merge,
//! calibration from the grid photo, sampling and fitting, against the mock's truth.

use std::path::Path;

use glint::fit::model::{Model, Reflectance};
use glint::fit::run::{run, FitOptions, FitReport};
use glint::fit::sample::Strategy;

use super::util::{record, set, small_table, tempdir};

/// Capture, merge and calibrate a mock tile; returns the session directory's parent.
pub fn pipeline(dir: &Path, model: &str, n: f64, ks: f64, seed: i64, size: [i64; 2]) {
    let mut t = small_table();
    let f = 1500.0 * size[0] as f64 / 1280.0;
    set(&mut t, "camera.width", size[0]);
    set(&mut t, "camera.height", size[1]);
    set(&mut t, "mock.camera.fx", f);
    set(&mut t, "mock.camera.fy", f);
    set(&mut t, "mock.seed", seed);
    set(&mut t, "mock.tile.model", model);
    set(&mut t, "mock.tile.n", n);
    set(
        &mut t,
        "mock.tile.ks",
        toml::Value::Array(vec![ks.into(); 3]),
    );
    record(dir, &t).unwrap();
    let s = dir.join("s");
    glint::hdr::run::run(&s, &Default::default(), &mut |_| {}).unwrap();
    glint::calib::run::run_session(&s, None).unwrap();
}

fn fit(dir: &Path, strategy: Strategy, count: usize, models: &[Model]) -> FitReport {
    let mut o = FitOptions::default();
    o.sample.strategy = strategy;
    o.sample.count = Some(count);
    o.models = models.to_vec();
    run(&dir.join("s"), &o).unwrap()
}

/// One fit's errors against the truth.
struct Outcome {
    n_error: f64,
    ratio_error: f64,
    n_covered: bool,
    ratio_covered: bool,
}

fn outcome(r: &FitReport, n: f64, ratio: f64, label: &str) -> Outcome {
    let c = &r.candidates[0];
    let o = Outcome {
        n_error: c.n.value / n - 1.0,
        ratio_error: c.ks_over_kd[1].value / ratio - 1.0,
        n_covered: c.n.ci95[0] <= n && n <= c.n.ci95[1],
        ratio_covered: c.ks_over_kd[1].ci95[0] <= ratio && ratio <= c.ks_over_kd[1].ci95[1],
    };
    println!(
        "{label} {:5} {:4} samples: n {:9.3} [{:9.3}, {:9.3}] ({:+.2}%) {}  ks/kd {:.4} ± {:.4} ({:+.2}%) {}  chi2/dof {:.2}",
        r.sampling.sampled.strategy.name(),
        r.sampling.sampled.used,
        c.n.value,
        c.n.ci95[0],
        c.n.ci95[1],
        100.0 * o.n_error,
        if o.n_covered { "in " } else { "OUT" },
        c.ks_over_kd[1].value,
        c.ks_over_kd[1].sd,
        100.0 * o.ratio_error,
        if o.ratio_covered { "in " } else { "OUT" },
        c.reduced_chi2
    );
    o
}

#[test]
fn blinn_phong_tiles_from_n_5_to_1000_through_the_whole_pipeline() {
    // Ten seeds at each exponent; 640x480 frames (the default rig's scene at half size).
    // The line pair (cross, the default) and a rectangle of 2000 samples.
    let ns = [5.0, 30.0, 120.0, 400.0, 1000.0];
    let ratio = 0.3 / 0.25;
    let mut all = Vec::new();
    for &n in &ns {
        for seed in 0..10 {
            let dir = tempdir();
            pipeline(dir.path(), "blinn-phong", n, 0.3, seed, [640, 480]);
            for (strategy, count) in [(Strategy::Cross, 400), (Strategy::Rect, 2000)] {
                let r = fit(dir.path(), strategy, count, &[Model::BlinnPhong]);
                let label = format!("n {n:6} seed {seed}");
                all.push((n, strategy, outcome(&r, n, ratio, &label)));
            }
        }
    }
    for strategy in [Strategy::Cross, Strategy::Rect] {
        for &n in &ns {
            let v: Vec<&Outcome> = all
                .iter()
                .filter(|a| a.0 == n && a.1 == strategy)
                .map(|a| &a.2)
                .collect();
            let worst_n = v.iter().map(|o| o.n_error.abs()).fold(0.0, f64::max);
            let worst_r = v.iter().map(|o| o.ratio_error.abs()).fold(0.0, f64::max);
            let cn = v.iter().filter(|o| o.n_covered).count();
            let cr = v.iter().filter(|o| o.ratio_covered).count();
            println!(
                "{:5} n {n:6}: worst n error {:.2}%, worst ks/kd error {:.2}%, 95% intervals cover n {cn}/{}, ks/kd {cr}/{}",
                strategy.name(),
                100.0 * worst_n,
                100.0 * worst_r,
                v.len(),
                v.len()
            );
        }
    }
    let covered: usize = all
        .iter()
        .map(|a| a.2.n_covered as usize + a.2.ratio_covered as usize)
        .sum();
    println!("coverage over all: {covered}/{}", 2 * all.len());
    // Measured (README, "Fitting"): with a rectangle of 2000 samples n is within 1.3% at
    // every exponent and ks/kd within 1.9% from n = 30 on (3.2% at n = 5, where its
    // standard deviation is 1.4% at this image size); the line pair (about 220 pixels) is
    // within 1.5% from n = 120, and noise-limited below (12% in ks/kd at n = 5).
    for (n, strategy, o) in &all {
        let (tol_n, tol_r) = match (strategy, *n) {
            (Strategy::Rect, n) if n >= 30.0 => (0.015, 0.025),
            (Strategy::Rect, _) => (0.02, 0.05),
            (_, n) if n >= 120.0 => (0.02, 0.025),
            (_, n) if n >= 30.0 => (0.03, 0.08),
            _ => (0.1, 0.2),
        };
        assert!(
            o.n_error.abs() < tol_n && o.ratio_error.abs() < tol_r,
            "n {n} {}: n off by {:.2}%, ks/kd by {:.2}%",
            strategy.name(),
            100.0 * o.n_error,
            100.0 * o.ratio_error
        );
    }
    assert!(
        covered as f64 >= 0.9 * (2 * all.len()) as f64,
        "95% intervals cover the truth in only {covered} of {}",
        2 * all.len()
    );
}

/// Diagnostic (run by hand: `cargo test --release diagnose_hdr -- --ignored --nocapture`,
/// with GLINT_TRUE_RESPONSE=1 to merge with the sensor's true response instead of the
/// recovered one): the merged radiance on the tile against the mock's true radiance, by
/// level: the bias (after one scale per channel) and the mean squared standardised error.
/// Measured: recovered response, bias within ±0.12% by level and z^2 1.07-1.27 (the noise
/// estimate is low); true response, bias within ±0.08% and z^2 0.98-1.01.
#[test]
#[ignore]
fn diagnose_hdr_on_the_tile() {
    let dir = tempdir();
    pipeline(dir.path(), "blinn-phong", 120.0, 0.3, 0, [640, 480]);
    let rig = super::util::load(dir.path(), &{
        let mut t = small_table();
        set(&mut t, "camera.width", 640);
        set(&mut t, "camera.height", 480);
        set(&mut t, "mock.camera.fx", 750.0);
        set(&mut t, "mock.camera.fy", 750.0);
        set(&mut t, "mock.seed", 0);
        set(&mut t, "mock.tile.n", 120.0);
        set(
            &mut t,
            "mock.tile.ks",
            toml::Value::Array(vec![0.3.into(); 3]),
        );
        t
    });
    let r = &rig.rig;
    let cfg = r.mock.clone().unwrap();
    let mut lab =
        glint_mock::Lab::new(&r.scene_geometry(), &cfg, 640, 480, 8, &rig.base_dir()).unwrap();
    let truth = lab.camera.radiance(glint_mock::SceneKind::Tile);
    if std::env::var("GLINT_TRUE_RESPONSE").is_ok() {
        // Merge again with the sensor's true response: what is left is the merge's own.
        let r = super::hdr::true_response(&cfg.sensor);
        let f = dir.path().join("true.json");
        glint::hdr::files::save_response(&f, &r).unwrap();
        let o = glint::hdr::run::HdrOptions {
            response_file: Some(f),
            ..Default::default()
        };
        glint::hdr::run::run(&dir.path().join("s"), &o, &mut |_| {}).unwrap();
    }
    let inputs = glint::fit::run::load_inputs(&dir.path().join("s")).unwrap();
    let resp = glint::hdr::files::load_response(&dir.path().join("s/hdr/response.json")).unwrap();
    for ch in &resp.channels {
        println!(
            "noise {:?} (true shot {:.3e}: exposure 1 = value 128)",
            ch.noise,
            1.0 / (20000.0 * (128.0f64 / 255.0).powf(2.2))
        );
    }
    let tile = glint::fit::sample::TileMap::new(&inputs.scene, 640, 480, 1.0);
    let mut rows = Vec::new();
    for i in 0..640 * 480 {
        if tile.points[i].is_none() {
            continue;
        }
        for c in 0..3 {
            let k = 3 * i + c;
            if inputs.mask[k] == 0 {
                rows.push((
                    c,
                    inputs.radiance[k] as f64,
                    inputs.variance[k] as f64,
                    truth[k] as f64,
                ));
            }
        }
    }
    for c in 0..3 {
        let v: Vec<_> = rows.iter().filter(|r| r.0 == c).collect();
        let s = v.iter().map(|r| r.1 * r.3 / r.2).sum::<f64>()
            / v.iter().map(|r| r.3 * r.3 / r.2).sum::<f64>();
        let mut by: Vec<(f64, f64, f64)> = v
            .iter()
            .map(|r| (r.1, (r.1 - s * r.3) / r.2.sqrt(), r.1 / (s * r.3) - 1.0))
            .collect();
        by.sort_by(|a, b| a.0.total_cmp(&b.0));
        let z2 = by.iter().map(|x| x.1 * x.1).sum::<f64>() / by.len() as f64;
        println!("channel {c}: {} px, mean z^2 {z2:.3}", by.len());
        for q in by.chunks(by.len() / 8 + 1) {
            let m = q.len() as f64;
            println!(
                "   L {:8.2}..{:8.2}: bias {:+.4}%  z^2 {:.3}",
                q[0].0,
                q[q.len() - 1].0,
                100.0 * q.iter().map(|x| x.2).sum::<f64>() / m,
                q.iter().map(|x| x.1 * x.1).sum::<f64>() / m
            );
        }
    }
}

#[test]
fn model_choice_finds_the_true_model_through_the_whole_pipeline() {
    // Each model in turn as the tile's truth, ten seeds each, the default sampling (the
    // line pair through the highlight); every candidate fitted, the simplest whose
    // held-out error is within the noise of the best chosen.
    let cases = [
        ("lambert", Model::Lambert, 120.0, 0.0),
        ("phong", Model::Phong, 40.0, 0.3),
        ("blinn-phong", Model::BlinnPhong, 120.0, 0.3),
        ("cosine-lobe", Model::CosineLobe, 40.0, 0.05),
    ];
    let mut right = 0;
    let mut total = 0;
    for (name, truth, n, ks) in cases {
        let mut line = format!("{name:12}:");
        for seed in 0..10 {
            let dir = tempdir();
            pipeline(dir.path(), name, n, ks, 100 + seed, [640, 480]);
            let o = FitOptions {
                draws: 0,
                ..FitOptions::default()
            };
            let r = run(&dir.path().join("s"), &o).unwrap();
            line.push_str(&format!(" {}", r.chosen.name()));
            right += (r.chosen == truth) as usize;
            total += 1;
        }
        println!("{line}");
    }
    println!("true model chosen in {right} of {total} runs");
    assert!(right as f64 >= 0.95 * total as f64, "{right} of {total}");
}

/// The broadest lobe at the mock rig's own size (1280x960) with 8000 samples: run by hand
/// (`cargo test --release full_size_broad_lobe -- --ignored --nocapture`; about a minute).
#[test]
#[ignore]
fn full_size_broad_lobe() {
    let (mut worst_n, mut worst_r, mut covered) = (0.0f64, 0.0f64, 0);
    for seed in 0..10 {
        let dir = tempdir();
        pipeline(dir.path(), "blinn-phong", 5.0, 0.3, seed, [1280, 960]);
        let r = fit(dir.path(), Strategy::Rect, 8000, &[Model::BlinnPhong]);
        let o = outcome(&r, 5.0, 1.2, &format!("1280x960 n 5 seed {seed}"));
        worst_n = worst_n.max(o.n_error.abs());
        worst_r = worst_r.max(o.ratio_error.abs());
        covered += o.n_covered as usize + o.ratio_covered as usize;
    }
    println!(
        "1280x960, n = 5, rect 8000: worst n error {:.2}%, worst ks/kd error {:.2}%, intervals cover {covered}/20",
        100.0 * worst_n,
        100.0 * worst_r
    );
}
