//! Stability where methods fail: a sweep over noise x true n x sampling strategy x start
//! values x saturated samples, on radiance rendered by the simulated lab (its own forward
//! model) with Gaussian noise added, and the true camera. A fit succeeds when n and ks/kd
//! are consistent with the truth (within 5% and 10%, or within 3 reported standard
//! deviations where the data allow no better) and its residuals are at the noise. Printed
//! as tables of success rates.

use glint::fit::geometry::Scene;
use glint::fit::model::Model;
use glint::fit::sample::{sample, RadianceImage, SampleOptions, Saturated, Strategy};
use glint::fit::solve::{fit, Options, Sample, Start};
use glint::hdr::merge::{MASK_OK, MASK_SATURATED};
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};

use super::util::{load, set, small_table, tempdir};

const W: usize = 640;
const H: usize = 480;
const KD: [f64; 3] = [0.35, 0.25, 0.18];
const KS: f64 = 0.3;

/// The lab's noise-free radiance of a Blinn-Phong tile with exponent n, and the true scene.
fn render(n: f64) -> (Vec<f32>, Scene) {
    let dir = tempdir();
    let mut t = small_table();
    set(&mut t, "camera.width", W as i64);
    set(&mut t, "camera.height", H as i64);
    set(&mut t, "mock.camera.fx", 750.0);
    set(&mut t, "mock.camera.fy", 750.0);
    set(&mut t, "mock.tile.n", n);
    set(
        &mut t,
        "mock.tile.kd",
        toml::Value::Array(KD.iter().map(|x| (*x).into()).collect()),
    );
    set(
        &mut t,
        "mock.tile.ks",
        toml::Value::Array(vec![KS.into(); 3]),
    );
    super::util::truth(&load(dir.path(), &t))
}

/// Noisy radiance with relative noise `sigma`; values above `clip` (a fraction of the
/// tile's peak) are saturated.
struct Noisy {
    radiance: Vec<f32>,
    variance: Vec<f32>,
    mask: Vec<u8>,
    level: f64,
}

fn noisy(truth: &[f32], sigma: f64, clip: Option<f64>, seed: u64) -> Noisy {
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed);
    let peak = truth.iter().fold(0.0f32, |a, b| a.max(*b)) as f64;
    let level = clip.map_or(f64::INFINITY, |c| c * peak);
    let mut out = Noisy {
        radiance: Vec::with_capacity(truth.len()),
        variance: Vec::with_capacity(truth.len()),
        mask: Vec::with_capacity(truth.len()),
        level,
    };
    for &l in truth {
        let l = l as f64;
        let z: f64 = StandardNormal.sample(&mut rng);
        if l > level {
            out.radiance.push(f32::NAN);
            out.variance.push(f32::NAN);
            out.mask.push(MASK_SATURATED);
        } else {
            out.radiance.push((l * (1.0 + sigma * z)) as f32);
            out.variance.push(((sigma * l).powi(2)).max(1e-30) as f32);
            out.mask.push(MASK_OK);
        }
    }
    out
}

#[derive(Clone, Copy, PartialEq)]
enum Method {
    /// Glint's: no start values.
    Default,
    /// Plain Levenberg-Marquardt from start values near the truth (n x 1.5, kd, ks x 1.3).
    PlainNear,
    /// Plain Levenberg-Marquardt from the start a user without a prior guess gives:
    /// kd = ks = the median radiance over the diffuse basis, n = 50.
    PlainPoor,
}

fn success(samples: &[Sample], method: Method, n_true: f64) -> bool {
    let mut opts = Options::default();
    match method {
        Method::Default => {}
        Method::PlainNear => {
            // Start values in the fit's units: kd relative to the lamp's (unknown) scale
            // taken from the default fit's kd, as a user's earlier measurement would be.
            let f = fit(Model::BlinnPhong, samples, &opts);
            let s = f.kd[1].value / KD[1];
            opts.start = Some(Start {
                kd: 1.3 * KD[1] * s,
                ks: 1.3 * KS * s,
                n: 1.5 * n_true,
            });
        }
        Method::PlainPoor => {
            let mut q: Vec<f64> = samples
                .iter()
                .map(|s| s.radiance[1] / Model::diffuse(&s.geometry))
                .collect();
            q.sort_by(|a, b| a.total_cmp(b));
            let m = q[q.len() / 2];
            opts.start = Some(Start {
                kd: m,
                ks: m,
                n: 50.0,
            });
        }
    }
    let f = fit(Model::BlinnPhong, samples, &opts);
    let r_true = KS / KD[1];
    // Consistent with the truth: within 5% (n) or 10% (ks/kd), or within 3 of the fit's
    // own standard deviations where the data cannot do better; and the fit explains the
    // data (a fit stuck away from the optimum leaves residuals far above the noise).
    let close =
        |v: f64, sd: f64, truth: f64, tol: f64| (v - truth).abs() < (tol * truth).max(3.0 * sd);
    close(f.n.value, f.n.sd, n_true, 0.05)
        && close(f.ratio[1].value, f.ratio[1].sd, r_true, 0.10)
        && f.chi2 / (f.dof.max(1) as f64) < 1.5
}

fn samples_of(
    scene: &Scene,
    img: &Noisy,
    strategy: Strategy,
    count: usize,
    sat: Saturated,
    seed: u64,
) -> Vec<Sample> {
    let ri = RadianceImage {
        width: W,
        height: H,
        radiance: &img.radiance,
        variance: &img.variance,
        mask: &img.mask,
    };
    let so = SampleOptions {
        strategy,
        count: Some(count),
        saturated: sat,
        saturation_level: [img.level; 3],
        bloom_margin_px: 0,
        seed,
        ..SampleOptions::default()
    };
    sample(scene, &ri, &so)
        .map(|s| s.samples.iter().map(|p| p.sample).collect())
        .unwrap_or_default()
}

#[test]
fn stability_sweep_shows_where_the_paper_method_fails_and_the_default_does_not() {
    let ns = [5.0, 30.0, 120.0, 500.0, 2000.0, 8000.0];
    let seeds = 8u64;
    let renders: Vec<(Vec<f32>, Scene)> = ns.iter().map(|&n| render(n)).collect();
    let pct = |k: usize, t: usize| 100.0 * k as f64 / t as f64;
    let header = |title: &str| {
        println!("\n{title}");
        print!("{:32}", "");
        for n in ns {
            print!(" n={n:<6}");
        }
        println!();
    };
    // Success rate of `f` at each n over noise levels x seeds.
    let rate = |strategy: Strategy,
                count: usize,
                clip: Option<f64>,
                sat: Saturated,
                method: Method,
                noises: &[f64]|
     -> Vec<f64> {
        ns.iter()
            .zip(&renders)
            .map(|(&n, (truth, scene))| {
                let mut ok = 0;
                let mut total = 0;
                for &sigma in noises {
                    for seed in 0..seeds {
                        let img = noisy(truth, sigma, clip, seed * 7919 + (n as u64));
                        let s = samples_of(scene, &img, strategy, count, sat, seed + 1);
                        if s.len() >= 10 && success(&s, method, n) {
                            ok += 1;
                        }
                        total += 1;
                    }
                }
                pct(ok, total)
            })
            .collect()
    };
    let row = |label: &str, v: &[f64]| {
        print!("{label:32}");
        for x in v {
            print!(" {x:6.0}% ");
        }
        println!();
    };
    let noises = [0.003, 0.01, 0.03];

    header("Start values (cross, 400 samples; noise 0.3%, 1%, 3%): success rate");
    let default_cross = rate(
        Strategy::Cross,
        400,
        None,
        Saturated::Exclude,
        Method::Default,
        &noises,
    );
    let near = rate(
        Strategy::Cross,
        400,
        None,
        Saturated::Exclude,
        Method::PlainNear,
        &noises,
    );
    let poor = rate(
        Strategy::Cross,
        400,
        None,
        Saturated::Exclude,
        Method::PlainPoor,
        &noises,
    );
    row("default (no start values)", &default_cross);
    row("plain LM, start near the truth", &near);
    row("plain LM, start n = 50", &poor);

    header("Sampling (noise 1%): success rate");
    let mut by_strategy = Vec::new();
    for (name, st, count) in [
        ("line, 200", Strategy::Line, 200),
        ("cross, 200", Strategy::Cross, 200),
        ("rect, 200", Strategy::Rect, 200),
        ("random, 200", Strategy::Random, 200),
        ("random, 100", Strategy::Random, 100),
        ("random, 50", Strategy::Random, 50),
    ] {
        let d = rate(
            st,
            count,
            None,
            Saturated::Exclude,
            Method::Default,
            &[0.01],
        );
        let p = rate(
            st,
            count,
            None,
            Saturated::Exclude,
            Method::PlainPoor,
            &[0.01],
        );
        row(&format!("{name}: default"), &d);
        row(&format!("{name}: plain LM, n = 50"), &p);
        by_strategy.push((name, d, p));
    }

    header("Saturated samples (the highlight's top 15% clipped; cross, 400; noise 1%)");
    let clip = Some(0.85);
    let excl = rate(
        Strategy::Cross,
        400,
        clip,
        Saturated::Exclude,
        Method::Default,
        &[0.01],
    );
    let cens = rate(
        Strategy::Cross,
        400,
        clip,
        Saturated::Censor,
        Method::Default,
        &[0.01],
    );
    let kept = rate(
        Strategy::Cross,
        400,
        clip,
        Saturated::Clip,
        Method::Default,
        &[0.01],
    );
    row("left out (default)", &excl);
    row("kept as censored", &cens);
    row("kept as measured (the paper's)", &kept);

    // The default method succeeds at every exponent, with or without saturation.
    for (k, &n) in ns.iter().enumerate() {
        assert!(
            default_cross[k] >= 90.0,
            "default at n = {n}: {}%",
            default_cross[k]
        );
        assert!(
            excl[k] >= 85.0,
            "saturated left out at n = {n}: {}%",
            excl[k]
        );
    }
    for (name, d, _) in &by_strategy {
        assert!(d.iter().all(|x| *x >= 85.0), "{name}, default: {d:?}");
    }
    // Plain LM from a poor start fails somewhere in the range; so does plain LM on a
    // few random samples (few land on a sharp highlight); the saturated samples kept as
    // measured fail at most exponents.
    assert!(
        poor.iter().any(|x| *x < 50.0),
        "plain LM never failed: {poor:?}"
    );
    let random_plain: Vec<f64> = by_strategy[4..].iter().flat_map(|r| r.2.clone()).collect();
    assert!(
        random_plain.iter().any(|x| *x < 90.0),
        "random, plain LM: {random_plain:?}"
    );
    assert!(
        kept.iter().filter(|x| **x < 50.0).count() >= 3,
        "clipped samples: {kept:?}"
    );
}
