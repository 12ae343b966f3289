//! Validation renders, the report and `glint run`.

use std::path::Path;

use glint::fit::model::{Model, Reflectance};
use glint::fit::sample::TileMap;
use glint::validate::compare::predict_frame;
use glint::validate::render::{Board, Shading, Surface, View};

use super::util::{err, glint, load, ok, set, small_table, tempdir, true_scene};

const W: usize = 320;
const H: usize = 240;

fn rig_table(w: usize, h: usize) -> toml::Table {
    let mut t = small_table();
    let f = 1500.0 * w as f64 / 1280.0;
    set(&mut t, "camera.width", w as i64);
    set(&mut t, "camera.height", h as i64);
    set(&mut t, "mock.camera.fx", f);
    set(&mut t, "mock.camera.fy", f);
    t
}

/// Mean standardised residual and mean squared one of the frames against the renders,
/// over the pixels `keep` picks, readings inside the response's valid range only.
fn z_stats(
    dir: &Path,
    rendered: &[f32],
    r: &glint::hdr::response::Response,
    dark_per_us: f64,
    keep: &dyn Fn(usize) -> bool,
) -> (f64, f64, usize) {
    let m = glint::session::load(dir).unwrap();
    let (tiles, _) = glint::hdr::load_session(dir, &m).unwrap();
    let (mut s, mut s2, mut n) = (0.0, 0.0, 0usize);
    for (j, f) in tiles.frames.iter().enumerate() {
        let d = dark_per_us * f.exposure_us;
        let pred = predict_frame(rendered, r, f.exposure_us, [d; 3]);
        for k in (0..tiles.width * tiles.height).filter(|k| keep(*k)) {
            for c in 0..3 {
                let ch = &r.channels[c];
                let z = tiles.value(j, k, c) as f64;
                let zp = pred[3 * k + c] as f64;
                let valid = |v: f64| v >= ch.valid_min as f64 && v <= ch.valid_max as f64;
                if !(valid(z) && valid(zp)) {
                    continue;
                }
                let slope = r.slope(c, zp);
                let sd = (r.exposure_variance(c, zp) / (slope * slope)).sqrt();
                let e = (z - zp) / sd;
                s += e;
                s2 += e * e;
                n += 1;
            }
        }
    }
    (s / n as f64, s2 / n as f64, n)
}

#[test]
fn renders_with_the_true_scene_and_response_match_the_simulated_frames_to_the_noise() {
    // The renderer and the inverse response checked apart from the fitter: the tile and
    // the chessboard floor rendered with the simulator's true camera, reflectances, lamp
    // and sensor response must reproduce its frames to within their noise, exposure by
    // exposure; a 5% error in n must not.
    let dir = tempdir();
    let t = rig_table(W, H);
    super::util::record(dir.path(), &t).unwrap();
    let rig = load(dir.path(), &t).rig;
    let cfg = rig.mock.clone().unwrap();
    let response = super::hdr::true_response(&cfg.sensor);
    let cam = glint_mock::PosedCamera::new(&cfg.camera, W as u32, H as u32);
    let scene = true_scene(&cam, &rig, W, H);
    let view = View::new(
        &scene,
        Board {
            inner_corners: rig.geometry.grid_inner_corners,
            square_mm: rig.geometry.grid_square_mm,
        },
    );
    // The true response's exposure unit is radiance x µs, so radiance per second is the
    // simulator's radiance x 1e6; the lamp intensity is part of kd and ks.
    let scale = cfg.lamp.intensity * 1e6;
    assert_eq!(cfg.tile.model, glint_mock::Reflectance::BlinnPhong);
    let truth = Shading {
        model: Model::BlinnPhong,
        kd: cfg.tile.kd.map(|k| k * scale),
        ks: cfg.tile.ks.map(|k| k * scale),
        n: cfg.tile.n,
    };
    let a = |x: f64| [x * scale / std::f64::consts::PI; 3];
    let floor = [a(cfg.grid.dark), a(cfg.grid.light), a(cfg.grid.surround)];
    let rendered = view.render(&truth, &floor);
    let dark_per_us = cfg.sensor.dark_current_e_per_s * 1e-6 / cfg.sensor.electrons_per_radiance_us;
    let s = dir.path().join("s");
    let tile = TileMap::new(&scene, W, H, 1.0);
    let on_tile = |k: usize| tile.points[k].is_some();
    let on_floor = |k: usize| {
        matches!(view.surface(k), Surface::Square { .. } | Surface::Surround) && view.uniform(k)
    };
    let (mt, m2t, nt) = z_stats(&s, &rendered, &response, dark_per_us, &on_tile);
    let (mf, m2f, nf) = z_stats(&s, &rendered, &response, dark_per_us, &on_floor);
    println!("tile:  {nt} readings, mean z {mt:+.4}, mean z² {m2t:.4}");
    println!("floor: {nf} readings, mean z {mf:+.4}, mean z² {m2f:.4}");
    assert!(nt > 50_000 && nf > 50_000, "{nt} {nf}");
    assert!(
        mt.abs() < 0.05 && (0.9..1.1).contains(&m2t),
        "tile {mt} {m2t}"
    );
    assert!(
        mf.abs() < 0.05 && (0.9..1.1).contains(&m2f),
        "floor {mf} {m2f}"
    );
    // The comparison can fail: the tile with n 5% off.
    let off = view.render(
        &Shading {
            n: truth.n * 1.05,
            ..truth
        },
        &floor,
    );
    let (_, m2o, _) = z_stats(&s, &off, &response, dark_per_us, &on_tile);
    println!("tile with n 5% off: mean z² {m2o:.3}");
    assert!(m2o > 1.5, "{m2o}");
}

/// `glint run` on the rig `t` (written into `dir`), into `dir/<name>`.
fn run(dir: &Path, t: &toml::Table, name: &str) -> glint::pipeline::RunSummary {
    let rig = load(dir, t);
    let devices = glint::devices::open(&rig).unwrap();
    glint::pipeline::run(
        &rig,
        devices,
        &dir.join(name),
        Default::default(),
        &Default::default(),
        &mut |_| {},
    )
    .unwrap_or_else(|e| panic!("glint run failed: {e}"))
}

fn rel(a: f64, b: f64) -> f64 {
    if a == b {
        0.0
    } else {
        (a - b).abs() / a.abs().max(b.abs())
    }
}

#[test]
fn glint_run_then_every_stage_alone_gives_the_same_result() {
    let dir = tempdir();
    let t = rig_table(W, H);
    // First run of this camera: no profile yet, so the response is recovered after the
    // capture and stored; the second run merges during the capture.
    let first = run(dir.path(), &t, "first");
    assert!(!first.streamed);
    assert!(dir.path().join("profiles").is_dir());
    let second = run(dir.path(), &t, "second");
    assert!(
        second.streamed,
        "the profile was known: the merge runs during capture"
    );
    for s in [&first, &second] {
        assert_eq!(
            s.fit.chosen,
            Model::BlinnPhong,
            "the simulated tile is Blinn-Phong"
        );
        let c = s.validation.chosen();
        println!(
            "{}: n {:.2}, PSNR {:.2} dB, RMSE {:.3} (noise {:.3}), {:.1} s",
            s.session.display(),
            s.fit
                .candidates
                .iter()
                .find(|c| c.model == Model::BlinnPhong)
                .unwrap()
                .n
                .value,
            c.pixels.psnr_db,
            c.pixels.rmse,
            c.pixels.noise_rmse,
            s.seconds
        );
        assert!(c.pixels.rmse < 1.3 * c.pixels.noise_rmse);
    }
    let s = &second.session;
    // HDR alone (the batch merge, with the same profile) against the streamed merge.
    let read = |f: &str| {
        glint::hdr::files::read_exr(&s.join("hdr").join(f))
            .unwrap()
            .2
    };
    let (rad, var) = (read("radiance.exr"), read("variance.exr"));
    let mask = std::fs::read(s.join("hdr/mask.png")).unwrap();
    let opts = glint::hdr::run::HdrOptions {
        rig: Some(dir.path().join("rig.toml")),
        ..Default::default()
    };
    let (hdr, _) = glint::hdr::run::run(s, &opts, &mut |_| {}).unwrap();
    assert!(matches!(
        hdr.response,
        glint::hdr::run::ResponseSource::Profile(_)
    ));
    let (rad2, var2) = (read("radiance.exr"), read("variance.exr"));
    assert_eq!(mask, std::fs::read(s.join("hdr/mask.png")).unwrap());
    let worst = |a: &[f32], b: &[f32]| {
        a.iter()
            .zip(b)
            .filter(|(x, _)| x.is_finite())
            .map(|(x, y)| rel(*x as f64, *y as f64))
            .fold(0.0, f64::max)
    };
    let (wr, wv) = (worst(&rad, &rad2), worst(&var, &var2));
    println!("hdr re-run: radiance within {wr:.1e}, variance within {wv:.1e}");
    assert!(wr < 1e-5 && wv < 1e-5);
    // Calibration alone: the same camera.
    let cal = glint::calib::run::run_session(s, None).unwrap();
    for (a, b) in cal
        .calibration
        .parameters
        .iter()
        .zip(&second.calibration.calibration.parameters)
    {
        assert_eq!(a.name, b.name);
        assert!(
            rel(a.value, b.value) < 1e-9 && rel(a.sd, b.sd) < 1e-6,
            "{a:?} {b:?}"
        );
    }
    // Fit alone.
    let fit = glint::fit::run::run(s, &Default::default()).unwrap();
    assert_eq!(fit.chosen, second.fit.chosen);
    for (a, b) in fit.candidates.iter().zip(&second.fit.candidates) {
        assert_eq!(a.model, b.model);
        if a.model.has_lobe() {
            assert!(rel(a.n.value, b.n.value) < 1e-4, "{} n", a.model.name());
            assert!(rel(a.n.sd, b.n.sd) < 1e-3, "{} n sd", a.model.name());
        }
        for c in 0..3 {
            assert!(
                rel(a.kd[c].value, b.kd[c].value) < 1e-4,
                "{} kd",
                a.model.name()
            );
        }
    }
    // Validation alone.
    let v = glint::validate::run(s, &Default::default(), &mut |_| {}).unwrap();
    for (a, b) in v.models.iter().zip(&second.validation.models) {
        assert_eq!((a.model, a.chosen), (b.model, b.chosen));
        assert!(rel(a.pixels.rmse, b.pixels.rmse) < 1e-3);
        assert!(rel(a.radiance.relative_error, b.radiance.relative_error) < 1e-3);
        assert!((a.pixels.readings as f64 / b.pixels.readings as f64 - 1.0).abs() < 1e-3);
    }
    // Report alone: the same files.
    let r = glint::report::write(s, &Default::default()).unwrap();
    assert_eq!(r.files, second.report.files);
    assert!(r.missing.is_empty());
}

#[test]
fn the_report_is_self_contained() {
    let dir = tempdir();
    let s = run(dir.path(), &rig_table(W, H), "s");
    let html = std::fs::read_to_string(&s.report.index).unwrap();
    let refs = glint::report::references(&html);
    let report = s.session.join("report");
    for f in [
        "compare.png",
        "difference.png",
        "profile.svg",
        "response.svg",
        "corners.png",
        "brdf.svg",
        "rig.svg",
    ] {
        assert!(refs.iter().any(|r| r == f), "the report shows {f}");
    }
    // The sketch's mirror point is on the tile, and the response plot has its band.
    let sketch = std::fs::read_to_string(report.join("rig.svg")).unwrap();
    assert!(sketch.contains("mirror point") && !sketch.contains("off the tile"));
    let plot = std::fs::read_to_string(report.join("response.svg")).unwrap();
    assert!(plot.contains("95% band"));
    for r in &refs {
        assert!(
            !r.starts_with('/') && !r.contains(".."),
            "{r} stays inside report/"
        );
        assert!(
            report.join(r).is_file(),
            "report/{r} is referenced but missing"
        );
    }
    for f in &s.report.files {
        assert!(report.join(f).is_file());
    }
    for needle in [
        "Chosen model: blinn-phong",
        "PSNR",
        "Calibration",
        "HDR merge",
        "Capture",
    ] {
        assert!(html.contains(needle), "{needle}");
    }
    // Moved elsewhere, the folder still holds everything it shows.
    let moved = dir.path().join("moved");
    std::fs::rename(&report, &moved).unwrap();
    for r in &refs {
        assert!(moved.join(r).is_file());
    }
}

#[test]
fn glint_run_on_the_command_line_ends_with_the_summary() {
    let dir = tempdir();
    let t = rig_table(W, H);
    load(dir.path(), &t);
    let rig = dir.path().join("rig.toml");
    let out = dir.path().join("s");
    let o = glint(&[
        "run",
        "--rig",
        rig.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let text = ok(&o);
    println!("{text}");
    assert!(text.contains("Chosen model: blinn-phong"), "{text}");
    assert!(text.contains("Validation: PSNR"));
    assert!(text.contains(&format!(
        "Report: {}",
        out.join("report/index.html").display()
    )));
    // The stages alone on the finished session, from the command line.
    for stage in ["validate", "report"] {
        ok(&glint(&[stage, out.to_str().unwrap()]));
    }
    // A stage that cannot run says which one came first.
    let bare = dir.path().join("bare");
    std::fs::create_dir_all(&bare).unwrap();
    super::util::record(&bare, &t).unwrap_or_else(|_| panic!());
    let e = err(&glint(&["validate", bare.join("s").to_str().unwrap()]));
    assert!(e.contains("glint fit"), "{e}");
    // The output folder is never overwritten.
    let e = err(&glint(&[
        "run",
        "--rig",
        rig.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]));
    println!("{e}");
}
