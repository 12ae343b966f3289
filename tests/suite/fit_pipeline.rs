//! The fit through the whole simulated pipeline: capture on the mock rig, HDR merge,
//! calibration from the grid photo, sampling and fitting, against the mock's truth.

use std::path::Path;

use glint::fit::model::Model;
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
    set(&mut t, "mock.tile.ks", toml::Value::Array(vec![ks.into(); 3]));
    record(dir, &t).unwrap();
    let s = dir.join("s");
    glint::hdr::run::run(&s, &Default::default(), &mut |_| {}).unwrap();
    glint::calib::run::run_session(&s, None).unwrap();
}

fn fit(dir: &Path, strategy: Strategy, count: usize, models: &[Model]) -> FitReport {
    let mut o = FitOptions::default();
    o.sample.strategy = strategy;
    o.sample.count = count;
    o.models = models.to_vec();
    run(&dir.join("s"), &o).unwrap().0
}

#[test]
fn blinn_phong_tiles_from_n_5_to_1000_through_the_whole_pipeline() {
    let ns = [5.0, 30.0, 120.0, 400.0, 1000.0];
    let (mut worst_n, mut worst_r) = (0.0f64, 0.0f64);
    let (mut cover, mut total) = (0, 0);
    for &n in &ns {
        for seed in 0..2 {
            let dir = tempdir();
            pipeline(dir.path(), "blinn-phong", n, 0.3, seed, [640, 480]);
            for (strategy, count) in [(Strategy::Line, 400), (Strategy::Rect, 2000)] {
                let r = fit(dir.path(), strategy, count, &[Model::BlinnPhong]);
                let c = &r.candidates[0];
                let ratio = 0.3 / 0.25;
                let en = c.n.value / n - 1.0;
                let er = c.ks_over_kd[1].value / ratio - 1.0;
                let inside_n = c.n.ci95[0] <= n && n <= c.n.ci95[1];
                let inside_r = c.ks_over_kd[1].ci95[0] <= ratio && ratio <= c.ks_over_kd[1].ci95[1];
                println!(
                    "n {n:6} seed {seed} {:5} {:4} samples: n {:9.3} [{:9.3}, {:9.3}] ({:+.2}%) {}  ks/kd {:.4} ± {:.4} ({:+.2}%) {}  chi2/dof {:.2}",
                    strategy.name(),
                    r.sampling.sampled.used,
                    c.n.value,
                    c.n.ci95[0],
                    c.n.ci95[1],
                    100.0 * en,
                    if inside_n { "in " } else { "OUT" },
                    c.ks_over_kd[1].value,
                    c.ks_over_kd[1].sd,
                    100.0 * er,
                    if inside_r { "in " } else { "OUT" },
                    c.reduced_chi2
                );
                worst_n = worst_n.max(en.abs());
                worst_r = worst_r.max(er.abs());
                cover += inside_n as usize + inside_r as usize;
                total += 2;
            }
        }
    }
    println!("worst n {:.2}%, worst ks/kd {:.2}%, coverage {cover}/{total}", 100.0 * worst_n, 100.0 * worst_r);
}

/// Diagnostic: the merged radiance on the tile against the mock's true radiance, by level.
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
        set(&mut t, "mock.tile.ks", toml::Value::Array(vec![0.3.into(); 3]));
        t
    });
    let r = &rig.rig;
    let cfg = r.mock.clone().unwrap();
    let mut lab = glint_mock::Lab::new(&r.scene_geometry(), &cfg, 640, 480, 8, &rig.base_dir()).unwrap();
    let truth = lab.camera.radiance(glint_mock::SceneKind::Tile);
    let inputs = glint::fit::run::load_inputs(&dir.path().join("s")).unwrap();
    let resp = glint::hdr::files::load_response(&dir.path().join("s/hdr/response.json")).unwrap();
    for ch in &resp.channels {
        println!("noise {:?} (true shot {:.3e}: exposure 1 = value 128)", ch.noise, 1.0 / (20000.0 * (128.0f64 / 255.0).powf(2.2)));
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
                rows.push((c, inputs.radiance[k] as f64, inputs.variance[k] as f64, truth[k] as f64));
            }
        }
    }
    for c in 0..3 {
        let v: Vec<_> = rows.iter().filter(|r| r.0 == c).collect();
        let s = v.iter().map(|r| r.1 * r.3 / r.2).sum::<f64>() / v.iter().map(|r| r.3 * r.3 / r.2).sum::<f64>();
        let mut by: Vec<(f64, f64, f64)> = v.iter().map(|r| (r.1, (r.1 - s * r.3) / r.2.sqrt(), r.1 / (s * r.3) - 1.0)).collect();
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
