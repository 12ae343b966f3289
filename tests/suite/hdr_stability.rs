//! Stability of response recovery: a sweep over lambda, sample count, exposure count and
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
    lambda: f64,
    samples: Option<usize>,
    exposures: usize,
    read_noise: f64,
}

#[test]
fn recovery_fails_loudly_never_silently() {
    let mut cases = Vec::new();
    let base = |what: String| Case {
        what,
        lambda: 10.0,
        samples: None,
        exposures: 7,
        read_noise: 4.0,
    };
    for l in [0.0, 0.1, 1.0, 10.0, 100.0, 1000.0, 1e5] {
        cases.push(Case {
            lambda: l,
            ..base(format!("lambda {l}"))
        });
    }
    for s in [5, 20, 60, 150, 600] {
        cases.push(Case {
            samples: Some(s),
            ..base(format!("{s} samples"))
        });
    }
    for n in 2..=9 {
        cases.push(Case {
            exposures: n,
            ..base(format!("{n} exposures"))
        });
    }
    for r in [1.0, 30.0, 150.0, 600.0] {
        cases.push(Case {
            read_noise: r,
            ..base(format!("read noise {r} e"))
        });
    }
    let rad = scene(W, H, 0.05, 150.0);
    let mut silent_failures = Vec::new();
    for case in &cases {
        let cfg = sensor(ResponseConfig::Gamma { gamma: 2.2 }, case.read_noise);
        // Exposures a stop apart, centred on the default bracket's middle.
        let first = 1000.0 / 2f64.powf((case.exposures as f64 - 1.0) / 2.0);
        let b = bracket(&cfg, &rad, W, H, 8, &times(first, case.exposures, 1.0), 3);
        let opts = RecoverOptions {
            model: ModelChoice::Debevec,
            lambda: case.lambda,
            samples: case.samples,
            ..Default::default()
        };
        let outcome = match response::recover(&b, &Bracket::empty(W, H, 8), &opts) {
            Err(e) => format!("error: {e}"),
            Ok(r) => {
                let err = (0..3)
                    .map(|c| {
                        let ch = &r.channels[c];
                        let lo = ch.valid_min.max(32);
                        let hi = ch.valid_max.min(232);
                        if hi <= lo {
                            return 0.0;
                        }
                        curve_error(&r, &cfg, c, lo, hi).0
                    })
                    .fold(0.0f64, f64::max);
                if r.warnings.is_empty() {
                    if err > 0.03 {
                        silent_failures.push(format!("{}: error {:.1}%", case.what, 100.0 * err));
                    }
                    format!("ok, error {:.2}%", 100.0 * err)
                } else {
                    format!("error {:.2}%, warned: {}", 100.0 * err, r.warnings[0])
                }
            }
        };
        println!("{:18} {outcome}", case.what);
    }
    assert!(
        silent_failures.is_empty(),
        "silently wrong: {silent_failures:#?}"
    );
}

#[test]
fn polynomial_recovery_fails_loudly_never_silently() {
    let rad = scene(W, H, 0.05, 150.0);
    let mut silent = Vec::new();
    let cases: Vec<(String, usize, Option<usize>, f64)> = (2..=9)
        .map(|n| (format!("{n} exposures"), n, None, 4.0))
        .chain([5, 20, 60].map(|s| (format!("{s} samples"), 7, Some(s), 4.0)))
        .chain([150.0, 600.0].map(|r| (format!("read noise {r} e"), 7, None, r)))
        .collect();
    for (what, n, samples, read) in cases {
        let cfg = sensor(ResponseConfig::Gamma { gamma: 2.2 }, read);
        let first = 1000.0 / 2f64.powf((n as f64 - 1.0) / 2.0);
        let b = bracket(&cfg, &rad, W, H, 8, &times(first, n, 1.0), 3);
        let opts = RecoverOptions {
            model: ModelChoice::Polynomial,
            samples,
            ..Default::default()
        };
        let outcome = match response::recover(&b, &Bracket::empty(W, H, 8), &opts) {
            Err(e) => format!("error: {e}"),
            Ok(r) => {
                let err = (0..3)
                    .map(|c| {
                        let ch = &r.channels[c];
                        curve_error(&r, &cfg, c, ch.valid_min.max(32), ch.valid_max.min(232)).0
                    })
                    .fold(0.0f64, f64::max);
                if r.warnings.is_empty() && err > 0.03 {
                    silent.push(format!("{what}: {:.1}%", 100.0 * err));
                }
                format!("error {:.2}%, warnings {:?}", 100.0 * err, r.warnings)
            }
        };
        println!("polynomial, {what:16} {outcome}");
    }
    assert!(silent.is_empty(), "silently wrong: {silent:#?}");
}
