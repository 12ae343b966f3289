//! HDR: response recovery and merge against simulated truth, the real Memorial bracket,
//! stability, bad input.

use glint::hdr::response::{self, ModelChoice, RecoverOptions, Response};
use glint::hdr::Bracket;
use glint_mock::config::ResponseConfig;

use super::hdr_sim::{bracket, scene, sensor, times, true_ln_exposure};

const W: usize = 240;
const H: usize = 160;

/// Largest |recovered - true| of ln E over values `lo..=hi`, after removing the best offset
/// (the unavoidable scale).
fn curve_error(
    r: &Response,
    cfg: &glint_mock::config::SensorConfig,
    c: usize,
    lo: u32,
    hi: u32,
) -> (f64, u32) {
    let d: Vec<(u32, f64)> = (lo..=hi)
        .map(|z| {
            (
                z,
                r.exposure(c, z as f64).ln() - true_ln_exposure(cfg, r.bit_depth, z as f64),
            )
        })
        .collect();
    let mut v: Vec<f64> = d.iter().map(|x| x.1).collect();
    v.sort_by(|a, b| a.total_cmp(b));
    let off = 0.5 * (v[0] + v[v.len() - 1]);
    d.iter()
        .map(|(z, x)| ((x - off).abs(), *z))
        .max_by(|a, b| a.0.total_cmp(&b.0))
        .unwrap()
}

fn empty(b: &Bracket) -> Bracket {
    Bracket::empty(b.width, b.height, b.bit_depth)
}

#[test]
fn explore() {
    let rad = scene(W, H, 0.05, 150.0);
    for (name, resp) in [
        ("gamma2.2", ResponseConfig::Gamma { gamma: 2.2 }),
        ("linear", ResponseConfig::Linear),
    ] {
        for noise in [false, true] {
            let mut cfg = sensor(resp.clone(), 4.0);
            cfg.noise = noise;
            let b = bracket(&cfg, &rad, W, H, 8, &times(125.0, 7, 1.0), 1);
            let opts = RecoverOptions {
                model: ModelChoice::Debevec,
                ..Default::default()
            };
            match response::recover(&b, &empty(&b), &opts) {
                Ok(r) => {
                    for c in 0..3 {
                        let ch = &r.channels[c];
                        let e =
                            curve_error(&r, &cfg, c, ch.valid_min.max(16), ch.valid_max.min(240));
                        println!(
                            "{name} noise {noise} c{c} valid {}..{} err {:.4} at {}  warn {:?}",
                            ch.valid_min, ch.valid_max, e.0, e.1, r.warnings
                        );
                    }
                }
                Err(e) => println!("{name} noise {noise}: {e}"),
            }
        }
    }
}

#[test]
fn explore2() {
    let rad = scene(W, H, 0.05, 150.0);
    for resp in [ResponseConfig::Linear, ResponseConfig::Gamma { gamma: 2.2 }] {
        let cfg = sensor(resp, 4.0);
        let b = bracket(&cfg, &rad, W, H, 8, &times(125.0, 7, 1.0), 1);
        for lambda in [3.0, 10.0, 30.0, 100.0] {
            for samples in [300, 600] {
                let opts = RecoverOptions {
                    model: ModelChoice::Debevec,
                    lambda,
                    samples: Some(samples),
                    ..Default::default()
                };
                let r = match response::recover(&b, &empty(&b), &opts) {
                    Ok(r) => r,
                    Err(e) => {
                        println!("{e}");
                        continue;
                    }
                };
                let c = 0;
                let d: Vec<String> = (8..=248)
                    .step_by(16)
                    .map(|z| {
                        format!(
                            "{z}:{:+.3}",
                            r.exposure(c, z as f64).ln()
                                - true_ln_exposure(&cfg, 8, z as f64)
                                - (r.exposure(c, 128.0).ln() - true_ln_exposure(&cfg, 8, 128.0))
                        )
                    })
                    .collect();
                println!(
                    "lambda {lambda} n {samples}: {} {:?}",
                    d.join(" "),
                    r.warnings
                );
            }
        }
    }
}
