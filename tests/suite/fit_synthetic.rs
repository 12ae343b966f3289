//! The paper's synthetic test, done without start values; derivatives against finite
//! differences. (The simulated truth here is written out in the test, not taken from the
//! fitter: a point lamp over a flat tile, docs/design.md's formulas.)

use glint::fit::model::{Geometry, Model, Reflectance};
use glint::fit::solve::{fit, polish_residuals_and_jacobian, Options, Sample};

const LAMP: [f64; 3] = [0.0, -150.0, 300.0];
const EYE: [f64; 3] = [0.0, 220.0, 380.0];

/// The truth's radiance, written out from docs/design.md (not from the fitter's model code).
fn truth(model: Model, p: [f64; 3], kd: [f64; 3], ks: [f64; 3], n: f64) -> [f64; 3] {
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let unit = |a: [f64; 3]| {
        let l = dot(a, a).sqrt();
        [a[0] / l, a[1] / l, a[2] / l]
    };
    let tl = sub(LAMP, p);
    let d2 = dot(tl, tl);
    let l = unit(tl);
    let v = unit(sub(EYE, p));
    let cos = l[2].max(0.0);
    let r = [-l[0], -l[1], l[2]];
    let rv = dot(r, v).max(0.0);
    let h = unit([l[0] + v[0], l[1] + v[1], l[2] + v[2]]);
    let nh = h[2].max(0.0);
    let mut out = [0.0; 3];
    for c in 0..3 {
        let fr_cos = match model {
            Model::Lambert => kd[c] * cos,
            Model::Phong => kd[c] * cos + ks[c] * rv.powf(n),
            Model::BlinnPhong => kd[c] * cos + ks[c] * nh.powf(n),
            Model::CosineLobe => {
                (kd[c] + ks[c] * (n + 2.0) / (2.0 * std::f64::consts::PI) * rv.powf(n)) * cos
            }
            Model::Ggx => kd[c] * cos + ks[c] * super::util::ggx_lobe(l, v, n),
        };
        out[c] = fr_cos / d2;
    }
    out
}

/// `count` samples along the plane of incidence, through the mirror point.
fn line(model: Model, count: usize, kd: [f64; 3], ks: [f64; 3], n: f64) -> Vec<Sample> {
    // The mirror point of the lamp seen from the eye on z = 0.
    let t = LAMP[2] / (LAMP[2] + EYE[2]);
    let y0 = LAMP[1] + t * (EYE[1] - LAMP[1]);
    (0..count)
        .map(|i| {
            let y = y0 - 120.0 + 240.0 * i as f64 / (count - 1) as f64;
            let p = [0.0, y, 0.0];
            Sample::new(
                Geometry::at(p, [0.0, 0.0, 1.0], LAMP, EYE),
                truth(model, p, kd, ks, n),
                [1.0; 3],
            )
        })
        .collect()
}

/// `count` samples across the plane of incidence, through the mirror point.
fn cross_line(model: Model, count: usize, kd: [f64; 3], ks: [f64; 3], n: f64) -> Vec<Sample> {
    let t = LAMP[2] / (LAMP[2] + EYE[2]);
    let y0 = LAMP[1] + t * (EYE[1] - LAMP[1]);
    (0..count)
        .map(|i| {
            let x = -120.0 + 240.0 * i as f64 / (count - 1) as f64;
            let p = [x, y0, 0.0];
            Sample::new(
                Geometry::at(p, [0.0, 0.0, 1.0], LAMP, EYE),
                truth(model, p, kd, ks, n),
                [1.0; 3],
            )
        })
        .collect()
}

#[test]
fn noise_free_lines_recover_every_model_without_start_values() {
    let kd = [0.35, 0.25, 0.18];
    let ks = [0.5, 0.45, 0.4];
    let opts = Options {
        variances_known: false,
        ..Options::default()
    };
    let mut worst: f64 = 0.0;
    for model in [Model::Phong, Model::BlinnPhong, Model::CosineLobe] {
        for n in [5.0, 40.0, 300.0, 1000.0] {
            for count in [100, 200, 400, 800] {
                let s = line(model, count, kd, ks, n);
                let f = fit(model, &s, &opts);
                let mut err: f64 = ((f.n.value - n) / n).abs();
                for c in 0..3 {
                    err = err.max(((f.kd[c].value - kd[c]) / kd[c]).abs());
                    err = err.max(((f.ks[c].value - ks[c]) / ks[c]).abs());
                }
                if count == 100 || count == 800 {
                    println!(
                        "{:12} n {n:6} {count:4} samples: worst relative error {err:.1e}; {} closed-form solves, {} LM evaluations",
                        model.name(),
                        f.inner_evaluations,
                        f.polish_evaluations
                    );
                }
                worst = worst.max(err);
                assert!(err < 1e-6, "{} n {n} {count}: {err}", model.name());
            }
        }
    }
    println!("worst relative error over all: {worst:.1e}");
    // Lambert: kd exactly.
    let s = line(Model::Lambert, 100, kd, [0.0; 3], 1.0);
    let f = fit(Model::Lambert, &s, &opts);
    for (e, t) in f.kd.iter().zip(kd) {
        assert!(((e.value - t) / t).abs() < 1e-9);
    }
}

#[test]
fn polish_jacobian_matches_finite_differences() {
    let kd = [0.35, 0.25, 0.18];
    let ks = [0.5, 0.45, 0.4];
    for model in [Model::Phong, Model::BlinnPhong, Model::CosineLobe] {
        let s = line(model, 50, kd, ks, 30.0);
        let p = [0.3, 0.2, 0.1, 0.6, 0.5, 0.4, 25f64.ln()];
        let (_, j) = polish_residuals_and_jacobian(&model, &s, p);
        for k in 0..7 {
            let h = 1e-6;
            let mut a = p;
            a[k] += h;
            let mut b = p;
            b[k] -= h;
            let fd = (polish_residuals_and_jacobian(&model, &s, a).0
                - polish_residuals_and_jacobian(&model, &s, b).0)
                / (2.0 * h);
            let err = (fd - j.column(k)).amax();
            let scale = j.column(k).amax().max(1e-12);
            assert!(
                err < 1e-6 * scale,
                "{} parameter {k}: {err} vs {scale}",
                model.name()
            );
        }
    }
}

#[test]
fn intervals_cover_the_truth_at_their_nominal_rate() {
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};
    let kd = [0.35, 0.25, 0.18];
    let ks = [0.5, 0.45, 0.4];
    let n = 60.0;
    let clean = line(Model::BlinnPhong, 300, kd, ks, n);
    let peak = clean.iter().map(|s| s.radiance[0]).fold(0.0f64, f64::max);
    let runs = 300;
    let (mut cover_n, mut cover_kd, mut cover_ks) = (0, 0, 0);
    for seed in 0..runs {
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed);
        let noisy: Vec<Sample> = clean
            .iter()
            .map(|s| {
                let mut o = *s;
                for c in 0..3 {
                    // 2% shot-like noise plus a floor, as the HDR stage reports it.
                    let var = (0.02 * s.radiance[c]).powi(2) + (1e-3 * peak).powi(2);
                    let z: f64 = StandardNormal.sample(&mut rng);
                    o.radiance[c] = s.radiance[c] + var.sqrt() * z;
                    o.variance[c] = var;
                }
                o
            })
            .collect();
        let f = fit(Model::BlinnPhong, &noisy, &Options::default());
        if f.n_ci95[0] <= n && n <= f.n_ci95[1] {
            cover_n += 1;
        }
        let [a, b] = f.kd[0].ci95();
        if a <= kd[0] && kd[0] <= b {
            cover_kd += 1;
        }
        let [a, b] = f.ks[0].ci95();
        if a <= ks[0] && ks[0] <= b {
            cover_ks += 1;
        }
    }
    let rate = |k: usize| k as f64 / runs as f64;
    println!(
        "95% intervals over {runs} seeds cover: n {:.3}, kd {:.3}, ks {:.3}",
        rate(cover_n),
        rate(cover_kd),
        rate(cover_ks)
    );
    // Binomial spread of 300 runs at 95%: sd 1.3%.
    for k in [cover_n, cover_kd, cover_ks] {
        assert!((0.91..=0.99).contains(&rate(k)), "{}", rate(k));
    }
}

#[test]
fn model_choice_picks_the_true_model() {
    use glint::fit::choose::choose;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};
    let kd = [0.35, 0.25, 0.18];
    let ks = [0.5, 0.45, 0.4];
    let mut report = Vec::new();
    for truth_model in Model::ALL {
        let ks_t = if truth_model.has_lobe() { ks } else { [0.0; 3] };
        // A cross: the line in the plane of incidence alone cannot tell Phong from
        // Blinn-Phong (there the angle between r and v is exactly twice that between n
        // and h, so the lobes agree to second order); across it the Blinn-Phong lobe is
        // wider.
        let mut clean = line(truth_model, 200, kd, ks_t, 40.0);
        clean.extend(cross_line(truth_model, 200, kd, ks_t, 40.0));
        let peak = clean.iter().map(|s| s.radiance[0]).fold(0.0f64, f64::max);
        let runs = 40;
        let mut right = 0;
        for seed in 0..runs {
            let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(1000 + seed);
            let noisy: Vec<Sample> = clean
                .iter()
                .map(|s| {
                    let mut o = *s;
                    for c in 0..3 {
                        let var = (0.02 * s.radiance[c]).powi(2) + (1e-3 * peak).powi(2);
                        let z: f64 = StandardNormal.sample(&mut rng);
                        o.radiance[c] = s.radiance[c] + var.sqrt() * z;
                        o.variance[c] = var;
                    }
                    o
                })
                .collect();
            // Alternate samples: fit on one half, hold out the other.
            let train: Vec<Sample> = noisy.iter().step_by(2).copied().collect();
            let test: Vec<Sample> = noisy.iter().skip(1).step_by(2).copied().collect();
            let ch = choose(&Model::ALL, &train, &test, &Options::default());
            if ch.chosen == truth_model {
                right += 1;
            }
        }
        report.push((truth_model.name(), right as f64 / runs as f64));
    }
    println!("true model chosen: {report:?}");
    for (name, rate) in report {
        assert!(rate >= 0.95, "{name}: {rate}");
    }
}

#[test]
fn grey_ks_recovers_a_white_highlight_with_five_parameters() {
    // Dielectric: the highlight has the lamp's colour, one ks for the three channels.
    let kd = [0.35, 0.25, 0.18];
    let ks = [0.4; 3];
    let opts = Options {
        variances_known: false,
        grey_ks: true,
        ..Options::default()
    };
    for model in [Model::Phong, Model::BlinnPhong, Model::CosineLobe] {
        let s = line(model, 200, kd, ks, 60.0);
        let f = fit(model, &s, &opts);
        let mut err: f64 = (f.n.value / 60.0 - 1.0).abs();
        for c in 0..3 {
            err = err
                .max((f.kd[c].value / kd[c] - 1.0).abs())
                .max((f.ks[c].value / ks[c] - 1.0).abs());
        }
        println!("{}: grey ks, worst relative error {err:.1e}", model.name());
        assert!(err < 1e-6, "{}: {err}", model.name());
        assert_eq!(f.dof, 3 * 200 - 5);
        assert_eq!(f.ks[0].value, f.ks[2].value);
        assert!(f.ks[0].sd > 0.0 && f.ks[0].sd == f.ks[1].sd);
    }
    // Coloured highlight (a metal): the grey fit cannot explain it, the free one can.
    let s = line(Model::BlinnPhong, 200, kd, [0.6, 0.4, 0.2], 60.0);
    let grey = fit(Model::BlinnPhong, &s, &opts);
    let free = fit(
        Model::BlinnPhong,
        &s,
        &Options {
            variances_known: false,
            ..Options::default()
        },
    );
    assert!(
        free.chi2 < 1e-12 * grey.chi2,
        "{} vs {}",
        free.chi2,
        grey.chi2
    );
}

#[test]
fn censored_samples_recover_a_clipped_highlight_and_clipped_values_do_not() {
    // The highlight's top is clipped at 70% of the peak (a saturated sensor). Kept as
    // lower bounds (censored) the fit recovers the truth; left out too; kept as if they
    // were measurements (the paper's failure) it does not.
    let kd = [0.35, 0.25, 0.18];
    let ks = [0.5, 0.45, 0.4];
    let n = 80.0;
    let clean = line(Model::BlinnPhong, 300, kd, ks, n);
    let peak = clean.iter().map(|s| s.radiance[0]).fold(0.0f64, f64::max);
    let level = 0.7 * peak;
    let clip = |censor: bool| -> Vec<Sample> {
        clean
            .iter()
            .map(|s| {
                let mut s = *s;
                for c in 0..3 {
                    if s.radiance[c] > level {
                        s.radiance[c] = level;
                        s.censored[c] = censor;
                    }
                }
                s
            })
            .collect()
    };
    let opts = Options {
        variances_known: false,
        ..Options::default()
    };
    let err = |f: &glint::fit::solve::ModelFit| {
        (f.n.value / n - 1.0)
            .abs()
            .max((f.ratio[0].value / (ks[0] / kd[0]) - 1.0).abs())
    };
    let censored = clip(true);
    assert!(censored.iter().any(|s| s.censored.contains(&true)));
    let f_cens = fit(Model::BlinnPhong, &censored, &opts);
    let left_out: Vec<Sample> = clean
        .iter()
        .filter(|s| s.radiance.iter().all(|x| *x <= level))
        .copied()
        .collect();
    let f_out = fit(Model::BlinnPhong, &left_out, &opts);
    let f_kept = fit(Model::BlinnPhong, &clip(false), &opts);
    println!(
        "clipped at 70%: censored {:.1e}, left out {:.1e}, kept as measured {:.1e} (worst relative error of n, ks/kd)",
        err(&f_cens),
        err(&f_out),
        err(&f_kept)
    );
    assert!(err(&f_cens) < 1e-6 && err(&f_out) < 1e-6);
    assert!(err(&f_kept) > 0.05);
    // Every censored value is predicted at or above its bound.
    for s in &censored {
        for c in 0..3 {
            if s.censored[c] {
                let p = Model::BlinnPhong.radiance(
                    &s.geometry,
                    f_cens.kd[c].value,
                    f_cens.ks[c].value,
                    f_cens.n.value,
                );
                assert!(p >= level * (1.0 - 1e-9));
            }
        }
    }
    // The censored residuals' derivatives: zero where the bound is met, the measured
    // ones elsewhere; against finite differences.
    let p = [0.3, 0.2, 0.1, 0.4, 0.4, 0.3, 70f64.ln()];
    let (_, j) = polish_residuals_and_jacobian(&Model::BlinnPhong, &censored, p);
    for k in 0..7 {
        let h = 1e-7;
        let (mut a, mut b) = (p, p);
        a[k] += h;
        b[k] -= h;
        let fd = (polish_residuals_and_jacobian(&Model::BlinnPhong, &censored, a).0
            - polish_residuals_and_jacobian(&Model::BlinnPhong, &censored, b).0)
            / (2.0 * h);
        let e = (fd - j.column(k)).amax();
        assert!(
            e < 1e-5 * j.column(k).amax().max(1e-12),
            "parameter {k}: {e}"
        );
    }
}

#[test]
fn huber_loss_resists_surface_flaws() {
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};
    // 1% noise and a flaw: 6% of the samples (a scratch across the line) 40% too bright.
    let kd = [0.35, 0.25, 0.18];
    let ks = [0.5, 0.45, 0.4];
    let n = 60.0;
    let clean = line(Model::BlinnPhong, 400, kd, ks, n);
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(3);
    let flawed: Vec<Sample> = clean
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let mut s = *s;
            for c in 0..3 {
                let sd = 0.01 * s.radiance[c];
                let z: f64 = StandardNormal.sample(&mut rng);
                let flaw = if (150..174).contains(&i) { 1.4 } else { 1.0 };
                s.radiance[c] = s.radiance[c] * flaw + sd * z;
                s.variance[c] = sd * sd;
            }
            s
        })
        .collect();
    let ls = fit(Model::BlinnPhong, &flawed, &Options::default());
    let hub = fit(
        Model::BlinnPhong,
        &flawed,
        &Options {
            huber: Some(2.0),
            ..Options::default()
        },
    );
    let e = |f: &glint::fit::solve::ModelFit| (f.n.value / n - 1.0).abs();
    println!(
        "flawed line: n error least squares {:.2}%, Huber {:.2}%",
        100.0 * e(&ls),
        100.0 * e(&hub)
    );
    assert!(e(&hub) < 0.02 && e(&ls) > 2.0 * e(&hub));
}

/// A model from outside the crate, through the trait alone: a Gaussian lobe in the
/// half-vector angle, b(n) = exp(-n theta_h^2) / D^2 (not a power of a cosine, so the
/// fitter evaluates it through `specular`).
#[derive(Debug, Clone, Copy)]
struct GaussianLobe;

impl Reflectance for GaussianLobe {
    fn name(&self) -> &'static str {
        "gaussian-lobe"
    }
    fn has_lobe(&self) -> bool {
        true
    }
    fn specular(&self, g: &Geometry, n: f64) -> (f64, f64) {
        let th = g.n_dot_h.clamp(-1.0, 1.0).acos();
        let b = (-n * th * th).exp() / g.d2;
        (b, -n * th * th * b)
    }
}

#[test]
fn a_model_added_through_the_trait_is_fitted_and_chosen_like_the_built_in_ones() {
    let kd = [0.35, 0.25, 0.18];
    let ks = [0.5, 0.45, 0.4];
    let n = 300.0;
    // The truth, written out: the Gaussian lobe's radiance on a cross of samples.
    let gauss_truth = |s: &Sample| -> [f64; 3] {
        let g = &s.geometry;
        let th = g.n_dot_h.acos();
        [0, 1, 2].map(|c| (kd[c] * g.cos_l + ks[c] * (-n * th * th).exp()) / g.d2)
    };
    let mut samples = line(Model::Lambert, 200, kd, [0.0; 3], 1.0);
    samples.extend(cross_line(Model::Lambert, 200, kd, [0.0; 3], 1.0));
    for s in samples.iter_mut() {
        s.radiance = gauss_truth(s);
    }
    let opts = Options {
        variances_known: false,
        ..Options::default()
    };
    let f = fit(GaussianLobe, &samples, &opts);
    let err = (f.n.value / n - 1.0)
        .abs()
        .max((f.ks[0].value / ks[0] - 1.0).abs())
        .max((f.kd[2].value / kd[2] - 1.0).abs());
    println!(
        "gaussian lobe through the trait: worst relative error {err:.1e} ({} closed-form solves, {} LM evaluations)",
        f.inner_evaluations, f.polish_evaluations
    );
    assert!(err < 1e-6, "{err}");
    // Its derivative by ln n against finite differences, through the polish's Jacobian.
    let p = [0.3, 0.2, 0.1, 0.4, 0.4, 0.3, 250f64.ln()];
    let (_, j) = polish_residuals_and_jacobian(&GaussianLobe, &samples, p);
    let h = 1e-6;
    let (mut a, mut b) = (p, p);
    a[6] += h;
    b[6] -= h;
    let fd = (polish_residuals_and_jacobian(&GaussianLobe, &samples, a).0
        - polish_residuals_and_jacobian(&GaussianLobe, &samples, b).0)
        / (2.0 * h);
    assert!((fd - j.column(6)).amax() < 1e-6 * j.column(6).amax());
    // Chosen among the built-ins on its own data, and not on Blinn-Phong's (0.5% noise).
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(11);
    let mut noisy = |v: &[Sample]| -> Vec<Sample> {
        v.iter()
            .map(|s| {
                let mut s = *s;
                for c in 0..3 {
                    let sd = 0.005 * s.radiance[c];
                    let z: f64 = StandardNormal.sample(&mut rng);
                    s.radiance[c] += sd * z;
                    s.variance[c] = sd * sd;
                }
                s
            })
            .collect()
    };
    let opts = Options::default();
    let samples = noisy(&samples);
    let train: Vec<Sample> = samples.iter().step_by(2).copied().collect();
    let test: Vec<Sample> = samples.iter().skip(1).step_by(2).copied().collect();
    let models: [&dyn Reflectance; 3] = [&Model::Lambert, &Model::BlinnPhong, &GaussianLobe];
    let c = glint::fit::choose::choose(&models, &train, &test, &opts);
    assert_eq!(c.chosen.name(), "gaussian-lobe");
    let mut bp = line(Model::BlinnPhong, 200, kd, ks, 120.0);
    bp.extend(cross_line(Model::BlinnPhong, 200, kd, ks, 120.0));
    let bp = noisy(&bp);
    let train: Vec<Sample> = bp.iter().step_by(2).copied().collect();
    let test: Vec<Sample> = bp.iter().skip(1).step_by(2).copied().collect();
    let c = glint::fit::choose::choose(&models, &train, &test, &opts);
    assert_eq!(c.chosen.name(), "blinn-phong");
}
