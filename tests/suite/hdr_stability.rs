//! Stability of response recovery: sweeps over lambda, sample count, exposure count and
//! noise around a default case. Every run either gives a curve within 3% of the truth with
//! no warning, or says what is wrong (a warning or an error): never a silently wrong curve.

use glint::hdr::response::{self, ModelChoice, RecoverOptions};
use glint::hdr::Bracket;
use glint_mock::config::ResponseConfig;

use super::hdr::curve_error;
use super::hdr_sim::{bracket, scene, sensor, times};

const W: usize = 160;
const H: usize = 96;

struct Case {
    what: String,
    model: ModelChoice,
    lambda: f64,
    samples: Option<usize>,
    exposures: usize,
    read_noise: f64,
}

fn case(model: ModelChoice, what: String) -> Case {
    Case {
        what,
        model,
        lambda: 10.0,
        samples: None,
        exposures: 7,
        read_noise: 4.0,
    }
}

/// Run the cases; print each outcome; return the silently wrong ones.
fn run(cases: &[Case]) -> Vec<String> {
    let rad = scene(W, H, 0.05, 150.0);
    let mut silent = Vec::new();
    for c in cases {
        let cfg = sensor(ResponseConfig::Gamma { gamma: 2.2 }, c.read_noise);
        // Exposures a stop apart, centred on the default bracket's middle.
        let first = 1000.0 / 2f64.powf((c.exposures as f64 - 1.0) / 2.0);
        let b = bracket(&cfg, &rad, W, H, 8, &times(first, c.exposures, 1.0), 3);
        let opts = RecoverOptions {
            model: c.model,
            lambda: c.lambda,
            samples: c.samples,
            ..Default::default()
        };
        let outcome = match response::recover(&b, &Bracket::empty(W, H, 8), &opts) {
            Err(e) => format!("error: {e}"),
            Ok(r) => {
                let err = (0..3)
                    .map(|k| {
                        let ch = &r.channels[k];
                        let (lo, hi) = (ch.valid_min.max(32), ch.valid_max.min(232));
                        if hi <= lo {
                            return 0.0;
                        }
                        curve_error(&r, &cfg, k, lo, hi).0
                    })
                    .fold(0.0f64, f64::max);
                if r.warnings.is_empty() {
                    if err > 0.03 {
                        silent.push(format!("{}: error {:.1}%", c.what, 100.0 * err));
                    }
                    format!("ok, error {:.2}%", 100.0 * err)
                } else {
                    format!("error {:.2}%, warned: {}", 100.0 * err, r.warnings[0])
                }
            }
        };
        println!("{:?} {:18} {outcome}", c.model, c.what);
    }
    silent
}

/// The sweep: lambda (where it applies), samples, exposures 2..9, read noise.
fn sweep(model: ModelChoice, lambdas: &[f64]) -> Vec<Case> {
    let mut cases = Vec::new();
    for &l in lambdas {
        cases.push(Case {
            lambda: l,
            ..case(model, format!("lambda {l}"))
        });
    }
    for s in [5, 20, 60, 150, 600] {
        cases.push(Case {
            samples: Some(s),
            ..case(model, format!("{s} samples"))
        });
    }
    for n in 2..=9 {
        cases.push(Case {
            exposures: n,
            ..case(model, format!("{n} exposures"))
        });
    }
    for r in [1.0, 30.0, 150.0, 600.0] {
        cases.push(Case {
            read_noise: r,
            ..case(model, format!("read noise {r} e"))
        });
    }
    cases
}

#[test]
fn debevec_recovery_fails_loudly_never_silently() {
    let cases = sweep(
        ModelChoice::Debevec,
        &[0.0, 0.1, 1.0, 10.0, 100.0, 1000.0, 1e5],
    );
    let silent = run(&cases);
    assert!(silent.is_empty(), "silently wrong: {silent:#?}");
}

#[test]
fn polynomial_recovery_fails_loudly_never_silently() {
    let silent = run(&sweep(ModelChoice::Polynomial, &[]));
    assert!(silent.is_empty(), "silently wrong: {silent:#?}");
}
