//! A channel the bracket shows in two exposures only up to mid-scale: a bright green tile on
//! a dim table, bracketed from where its green reads near full scale, so that one stop
//! longer green clips everywhere on it. The mock's sensor (one gamma curve for every
//! channel, as cameras apply) gives the truth; the recovered green curve must take the
//! shape of a channel the bracket shows to the top, and the tile's green radiance must
//! agree with the table's to within 1% (the scale between the two is what a borrowed
//! shape could get wrong).

use glint::hdr::merge::{self, MASK_OK};
use glint::hdr::response::{self, ModelChoice, RecoverOptions};
use glint_mock::config::ResponseConfig;

use super::hdr_depth::{emor_file, random_emor};
use super::hdr_sim::{bracket, sensor, times};

const W: usize = 240;
const H: usize = 160;

/// Is pixel (x, y) on the tile (the middle third of the image)?
fn on_tile(x: usize, y: usize) -> bool {
    (W / 3..2 * W / 3).contains(&x) && (H / 3..2 * H / 3).contains(&y)
}

/// Radiance: a table whose magenta-ish light (green a quarter of red and blue) grows
/// across the image, and a green tile whose green reads 85-93% of full scale at 125 µs.
fn scene() -> Vec<f32> {
    let mut r = Vec::with_capacity(W * H * 3);
    for y in 0..H {
        for x in 0..W {
            let fx = x as f64 / (W - 1) as f64;
            let fy = y as f64 / (H - 1) as f64;
            let rgb = if on_tile(x, y) {
                // Gamma 2.2: value 0.85..0.93 at 125 µs is 0.70..0.85 of the full well.
                let g = 20000.0 / 125.0 * (0.70 + 0.15 * fx) * (1.0 - 0.02 * fy);
                [0.3 * g, g, 0.3 * g]
            } else {
                let base = 2.0 * 20f64.powf(fx) * (1.0 + 0.2 * fy);
                [base, 0.25 * base, base]
            };
            r.extend(rgb.iter().map(|v| *v as f32));
        }
    }
    r
}

/// The tile's green against the table's (median relative error after the table's scale),
/// and the recovered green channel's valid top and misfit, for one curve.
fn tile_against_table(curve: ResponseConfig) -> Result<(f64, u32, f64), String> {
    let rad = scene();
    let cfg = sensor(curve, 5.0);
    let t = times(125.0, 3, 1.0);
    let b = bracket(&cfg, &rad, W, H, 16, &t, 7);
    let d = bracket(&cfg, &vec![0.0f32; rad.len()], W, H, 16, &t, 8);
    let opts = RecoverOptions {
        model: ModelChoice::Auto,
        ..Default::default()
    };
    let r = response::recover(&b, &d, &opts).map_err(|e| e.to_string())?;
    let g = &r.channels[1];
    let said = r
        .warnings
        .iter()
        .find(|w| w.starts_with("channel G: its curve is known up to"));
    if !said.is_some_and(|w| w.contains("shape") && w.contains("one stop shorter")) {
        return Err(format!(
            "no word of green's borrowed shape: {:?}",
            r.warnings
        ));
    }
    let m = merge::merge(&r, &b, &merge::dark_levels(&r, &b, &d)).map_err(|e| e.to_string())?;
    // Green relative to its truth, on the table (own curve) and on the tile (borrowed).
    let ratios = |tile: bool| {
        let mut q: Vec<f64> = (0..W * H)
            .filter(|p| on_tile(p % W, p / W) == tile && m.mask[3 * p + 1] == MASK_OK)
            .map(|p| m.radiance[3 * p + 1] as f64 / rad[3 * p + 1] as f64)
            .collect();
        q.sort_by(|a, b| a.total_cmp(b));
        q
    };
    let (table, tile) = (ratios(false), ratios(true));
    let on_tile_px = W * H / 9;
    if (tile.len() as f64) < 0.95 * on_tile_px as f64 {
        return Err(format!(
            "green has radiance at {} of the tile's {on_tile_px} pixels",
            tile.len()
        ));
    }
    let scale = table[table.len() / 2];
    let mut err: Vec<f64> = tile.iter().map(|x| (x / scale - 1.0).abs()).collect();
    err.sort_by(|a, b| a.total_cmp(b));
    Ok((err[err.len() / 2], g.valid_max, g.misfit_sd))
}

#[test]
fn a_channel_known_to_mid_scale_takes_anothers_shape_and_the_tile_keeps_its_radiance() {
    let mut curves = vec![(
        "gamma 2.2".to_string(),
        ResponseConfig::Gamma { gamma: 2.2 },
    )];
    // EMoR curves bend near the top, where a straight continuation misses.
    if let Some(f) = emor_file() {
        for seed in [11, 23, 37] {
            curves.push((format!("EMoR seed {seed}"), random_emor(&f, seed)));
        }
    }
    let mut failures = Vec::new();
    for (name, curve) in curves {
        match tile_against_table(curve) {
            Ok((median, top, misfit)) => {
                eprintln!(
                    "{name}: green valid to {top}, misfit {misfit:.4}; the tile's green against the table's: median {:.3}%",
                    100.0 * median
                );
                if median > 0.01 || (top as f64) < 0.95 * 65535.0 || misfit < 0.01 {
                    failures.push(format!(
                        "{name}: tile {:.2}% off, green valid to {top}, misfit {misfit:.4}",
                        100.0 * median
                    ));
                }
            }
            Err(e) => failures.push(format!("{name}: {e}")),
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}
