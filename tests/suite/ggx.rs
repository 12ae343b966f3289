//! The microfacet candidate: GGX tiles rendered by the simulated lab
//! (its own Cook-Torrance code, Schlick's Fresnel with the tile's true F0), captured,
//! merged, calibrated and fitted with every candidate; the roughness α and F0 (absolute,
//! through the reference standard) recovered, and the microfacet model chosen on held-out
//! samples. That a Blinn-Phong tile is still called Blinn-Phong with GGX among the
//! candidates is `fit_pipeline::blinn_phong_tiles_from_n_5_to_1000_through_the_whole_pipeline`
//! and the scene family's model counts.

use std::path::Path;

use super::util::{glint, mock_table, ok, set, tempdir};

/// rigs/mock-reference.toml at 640x480 with a GGX tile.
fn ggx_rig(alpha: f64, f0: f64, kd: [f64; 3], bits: u32) -> toml::Table {
    let mut t: toml::Table = toml::from_str(
        &std::fs::read_to_string(super::util::root().join("rigs/mock-reference.toml")).unwrap(),
    )
    .unwrap();
    let base = mock_table();
    assert_eq!(t["geometry"], base["geometry"]);
    set(&mut t, "camera.width", 640);
    set(&mut t, "camera.height", 480);
    set(&mut t, "camera.bit_depth", bits);
    set(&mut t, "mock.camera.fx", 750.0);
    set(&mut t, "mock.camera.fy", 750.0);
    set(&mut t, "lamp.warmup_ms", 0);
    set(&mut t, "mock.lamp.warmup_ms", 0);
    set(&mut t, "mock.tile.model", "ggx");
    set(&mut t, "mock.tile.alpha", alpha);
    set(&mut t, "mock.tile.kd", kd.to_vec());
    set(&mut t, "mock.tile.ks", vec![f0; 3]);
    t
}

/// The ggx candidate of a fit.json.
fn ggx(fit: &serde_json::Value) -> &serde_json::Value {
    fit["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["model"] == "ggx")
        .unwrap()
}

fn run(dir: &Path, t: &toml::Table) -> serde_json::Value {
    let rig = dir.join("rig.toml");
    std::fs::write(&rig, toml::to_string(t).unwrap()).unwrap();
    let s = dir.join("s");
    let s = s.to_str().unwrap();
    ok(&glint(&["run", "--rig", rig.to_str().unwrap(), "--out", s]));
    // A broad lobe needs the tile's area, not a cross through its peak.
    serde_json::from_str(&ok(&glint(&[
        "fit",
        s,
        "--strategy",
        "rect",
        "--samples",
        "2000",
        "--json",
    ])))
    .unwrap()
}

/// One GGX fit judged against its truth: a line for the log, and whether ggx was chosen
/// with α within 3% and F0 within 5%, each 95% interval covering its truth.
fn judge(fit: &serde_json::Value, alpha: f64, f0: f64, what: &str) -> (String, bool) {
    let c = ggx(fit);
    let get = |p: &serde_json::Value| {
        (
            p["value"].as_f64().unwrap(),
            p["ci95"][0].as_f64().unwrap(),
            p["ci95"][1].as_f64().unwrap(),
        )
    };
    let (av, alo, ahi) = get(&c["alpha"]);
    let (fv, flo, fhi) = get(&c["absolute"]["f0"][1]);
    let line = format!(
        "{what}: chose {} from {} samples, α {av:.4} [{alo:.4}, {ahi:.4}] ({:+.2}%), F0 {fv:.4} [{flo:.4}, {fhi:.4}] ({:+.2}%)",
        fit["chosen"],
        fit["sampling"]["used"],
        100.0 * (av / alpha - 1.0),
        100.0 * (fv / f0 - 1.0)
    );
    let good = fit["chosen"] == "ggx"
        && (av / alpha - 1.0).abs() <= 0.03
        && (fv / f0 - 1.0).abs() <= 0.05
        && (alo..=ahi).contains(&alpha)
        && (flo..=fhi).contains(&f0);
    (line, good)
}

/// Print every case's line and fail naming the cases that missed.
fn all_good(cases: &[(String, bool)]) {
    let seen: Vec<&String> = cases.iter().map(|c| &c.0).collect();
    let failures: Vec<&String> = cases.iter().filter(|c| !c.1).map(|c| &c.0).collect();
    println!("{seen:#?}");
    assert!(failures.is_empty(), "{failures:#?}\nall: {seen:#?}");
}

/// α from 0.05 to 0.3 on bright and dark tiles, 8 and 16 bit: α within 3% and F0 within
/// 5% of the truth, each 95% interval covering it, and ggx chosen.
#[test]
fn ggx_tiles_give_their_roughness_and_f0_and_are_chosen() {
    let mut cases = Vec::new();
    for (alpha, f0, kd, bits) in [
        (0.05, 0.04, [0.2, 0.15, 0.1], 8),
        (0.12, 0.06, [0.05, 0.05, 0.04], 16),
        (0.25, 0.045, [0.15, 0.12, 0.1], 8),
        (0.3, 0.05, [0.2, 0.15, 0.1], 16),
    ] {
        let dir = tempdir();
        let fit = run(dir.path(), &ggx_rig(alpha, f0, kd, bits));
        cases.push(judge(
            &fit,
            alpha,
            f0,
            &format!("α {alpha} F0 {f0} {bits}-bit"),
        ));
    }
    all_good(&cases);
}

/// Without a reference standard the microfacet model's ks is F0 times the unknown factor:
/// α is still reported, F0 is not, and fit.json says the units are relative.
#[test]
fn without_a_reference_ggx_gives_alpha_but_no_f0() {
    let mut t = ggx_rig(0.1, 0.05, [0.2, 0.15, 0.1], 8);
    t.remove("reference");
    t["mock"].as_table_mut().unwrap().remove("reference");
    let dir = tempdir();
    let fit = run(dir.path(), &t);
    assert_eq!(fit["units"], "relative");
    let c = ggx(&fit);
    let a = c["alpha"]["value"].as_f64().unwrap();
    assert!((a / 0.1 - 1.0).abs() < 0.03, "{a}");
    assert!(c.get("absolute").is_none());
}

/// A broad lobe (α = 0.5) needs the angles it spreads over. At the rig's geometry the tile
/// spans half-angles of 0-9°, where α = 0.5 is known only to ±11% and F0 to ±60% (one sd;
/// Blinn-Phong explains the data as well and is chosen). With the lamp near and low over
/// the tile's far edge ([100, 120, 80]) and the camera nearer ([100, -120, 260]) the tile
/// spans 0-34°, and over its area (rect, about 10 000 samples) α comes within 3%, F0
/// within 5%, and GGX is chosen, on a bright tile and a dark one.
#[test]
fn a_broad_ggx_lobe_is_measured_where_the_lamp_is_near() {
    let mut cases = Vec::new();
    for kd in [[0.2, 0.15, 0.1], [0.05, 0.05, 0.04]] {
        let (alpha, f0) = (0.5, 0.05);
        let mut t = ggx_rig(alpha, f0, kd, 8);
        set(
            &mut t,
            "geometry.lamp_position_mm",
            vec![100.0, 120.0, 80.0],
        );
        set(
            &mut t,
            "mock.camera.position_mm",
            vec![100.0, -120.0, 260.0],
        );
        let dir = tempdir();
        let fit = run(dir.path(), &t);
        cases.push(judge(&fit, alpha, f0, &format!("kd {kd:?}")));
    }
    all_good(&cases);
}

/// The fitter shapes Schlick's growth for F0 = 0.04: a tile of F0 0.12 is warned of (its
/// α and F0 carry a bias the intervals leave out), one of 0.05 is not.
#[test]
fn an_f0_far_from_the_fresnel_shape_is_warned_of() {
    for (f0, warned) in [(0.12, true), (0.05, false)] {
        let dir = tempdir();
        let fit = run(dir.path(), &ggx_rig(0.1, f0, [0.2, 0.15, 0.1], 8));
        let w = ggx(&fit)["warnings"].to_string();
        assert_eq!(w.contains("F0 comes out"), warned, "F0 {f0}: {w}");
    }
}
