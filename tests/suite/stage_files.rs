//! One type per stage file (glint-format's `stage`): every stage file the mock pipeline
//! writes (hdr/summary.json, hdr/response.json, calib/camera.json, fit/fit.json, validation/validation.json)
//! is read back through its type and written again byte for byte (a round trip of every
//! field: a field the type lacked, or named otherwise, would be lost or added); the
//! writers' in-memory reports give the same bytes through the type; and a fit file with
//! every optional part (a reference standard, absolute values, a refined camera, the
//! microfacet model's α and F0) survives the same round trip.

use std::path::Path;

use glint::calib::run::CameraFile;
use glint_format::stage::fit::{
    Absolute, CameraRefined, Candidate, Covariance, FactorSd, FitFile, Intrinsics, Param,
    Reference, Termination, UncertaintyShare, Verdict,
};
use glint_format::stage::hdr::Summary;
use glint_format::stage::validation::ValidationFile;
use serde::de::DeserializeOwned;
use serde::Serialize;

use super::util::{record, small_table, tempdir};

/// The file at `path` read through `T` and written again as the stages write it.
fn round_trip<T: DeserializeOwned + Serialize>(path: &Path) -> (T, Vec<u8>, Vec<u8>) {
    let bytes = std::fs::read(path).unwrap();
    let typed: T = serde_json::from_slice(&bytes)
        .unwrap_or_else(|e| panic!("{} does not read through its type: {e}", path.display()));
    let again = serde_json::to_vec_pretty(&typed).unwrap();
    (typed, bytes, again)
}

fn assert_same(path: &Path, bytes: &[u8], again: &[u8]) {
    assert!(
        bytes == again,
        "{}: the round trip through its type changed it:\n--- file\n{}\n--- again\n{}",
        path.display(),
        String::from_utf8_lossy(bytes),
        String::from_utf8_lossy(again)
    );
}

#[test]
fn every_stage_file_reads_back_through_its_type_and_writes_the_same_bytes() {
    let dir = tempdir();
    record(dir.path(), &small_table()).unwrap();
    let s = dir.path().join("s");
    let (hdr, _) = glint::hdr::run::run(&s, &Default::default(), &mut |_| {}).unwrap();
    let camera = glint::calib::run::run_session(&s, None).unwrap();
    let fit = glint::fit::run::run(
        &s,
        &glint::fit::run::FitOptions {
            draws: 2,
            ..Default::default()
        },
    )
    .unwrap();
    let validation = glint::validate::run(&s, &Default::default(), &mut |_| {}).unwrap();

    let p = s.join("hdr/summary.json");
    let (summary, bytes, again) = round_trip::<Summary>(&p);
    assert_same(&p, &bytes, &again);
    assert!(summary.exposures_us.is_some_and(|e| !e.is_empty()));
    assert_eq!(
        serde_json::to_vec_pretty(&hdr.file()).unwrap(),
        bytes,
        "summary.json is the merge's summary"
    );

    // The response's one type is the numerics' curve (`Response`): the fit, calibration,
    // validation and profiles all read it through `hdr::files::load_response`.
    let p = s.join("hdr/response.json");
    let (response, bytes, again) = round_trip::<glint::hdr::response::Response>(&p);
    assert_same(&p, &bytes, &again);
    let loaded =
        glint::hdr::files::load_response(glint::fsx::Within::new(&s, "hdr/response.json")).unwrap();
    assert_eq!(loaded, response, "the reader gives what the file holds");

    let p = s.join("calib/camera.json");
    let (cam, bytes, again) = round_trip::<CameraFile>(&p);
    assert_same(&p, &bytes, &again);
    assert_eq!(
        serde_json::to_vec_pretty(&cam).unwrap(),
        serde_json::to_vec_pretty(&camera).unwrap(),
        "camera.json is the calibration's file"
    );

    let p = s.join("fit/fit.json");
    let (f, bytes, again) = round_trip::<FitFile>(&p);
    assert_same(&p, &bytes, &again);
    assert_eq!(f, fit.file(), "fit.json is the report's file");
    assert_eq!(f.chosen, glint::fit::model::Reflectance::name(&fit.chosen));

    let p = s.join("validation/validation.json");
    let (v, bytes, again) = round_trip::<ValidationFile>(&p);
    assert_same(&p, &bytes, &again);
    assert_eq!(v, validation.file(), "validation.json is the report's file");
    assert_eq!(
        v.chosen().map(|m| m.model.as_str()),
        Some(f.chosen.as_str())
    );

    // And the report reads them all.
    glint::report::write(&s, &Default::default()).unwrap();
}

fn param(x: f64) -> Param {
    Param::of(x, 0.1 * x, [0.9 * x, f64::INFINITY])
}

/// A fit file with every optional part present.
fn full_fit() -> FitFile {
    let ps = |x: f64| vec![param(x), param(2.0 * x), param(3.0 * x)];
    let candidate = |model: &str| Candidate {
        model: model.into(),
        kd: ps(0.1),
        ks: ps(0.2),
        ks_over_kd: ps(2.0),
        n: Some(param(120.0)),
        alpha: (model == "ggx").then(|| param(0.13)),
        chi2: Some(101.5),
        dof: 97,
        reduced_chi2: Some(1.046),
        bic: Some(-12.25),
        held_out: Some(1.01),
        parameters: 7,
        inner_evaluations: 40,
        polish_evaluations: 12,
        polish_termination: Some(Termination::LostPatience),
        ks_n_correlation: None,
        n_variance_share: Some(UncertaintyShare {
            fit: Some(0.5),
            calibration: Some(0.25),
            response: None,
        }),
        absolute: Some(Absolute {
            kd_per_sr: ps(0.03),
            albedo: ps(0.1),
            ks_per_sr: ps(0.06),
            f0: if model == "ggx" { ps(0.04) } else { vec![] },
        }),
        covariance: Some(Covariance {
            parameters: vec!["kd_r".into(), "ln_n".into()],
            matrix: vec![vec![Some(1e-4), None], vec![None, Some(2.5e-3)]],
        }),
        explains: Some(model == "ggx"),
        trade_off: (model == "ggx").then(|| "ks and n correlate (0.990)".into()),
        warnings: vec!["a warning".into()],
    };
    let mut f: FitFile = serde_json::from_value(serde_json::json!({
        "format": "glint-fit", "channels": 3, "candidates": [], "chosen": "ggx",
    }))
    .unwrap();
    f.format_version = Some(1);
    f.sampling.strategy = glint_format::stage::fit::Strategy::UserLine([1.0, 2.0, 3.0, 4.0]);
    f.sampling.highlight.found_px = Some([Some(1.5), None]);
    f.sampling.lines_px = vec![[Some(1.0), Some(2.0), Some(3.0), Some(4.0)]];
    f.solver.huber = Some(1.345);
    f.candidates = vec![candidate("lambert"), candidate("ggx")];
    f.units = Some("absolute".into());
    f.reference = Some(Reference {
        reflectance: vec![Some(0.99); 3],
        reflectance_sd: vec![Some(0.01); 3],
        pixels: 400,
        outliers: 2,
        factor: ps(1e5),
        factor_relative_sd: vec![
            FactorSd {
                pixels: Some(0.001),
                certificate: Some(0.01),
                response: Some(0.002),
                total: Some(0.0103),
            };
            3
        ],
    });
    f.choice_tolerance = Some(0.02);
    f.camera_refined = Some(CameraRefined {
        intrinsics: Intrinsics {
            fx: 1500.0,
            fy: 1500.0,
            cx: 640.0,
            cy: 480.0,
            radial: vec![-0.1, 0.01],
            tangential: Some([0.001, -0.002]),
        },
        rvec: [0.1, 0.2, 0.3],
        t: [-10.0, 20.0, 500.0],
        centre_mm: [1.0, 2.0, 3.0],
        centre_before_mm: [Some(1.1), Some(2.1), Some(3.1)],
        moved_mm: Some(0.17),
        moved_sd: Some(1.2),
        chi2_before: Some(130.0),
        chi2: Some(101.5),
        n_before: Some(118.0),
        n_after: Some(120.0),
        tension: Some(1.4),
    });
    f.verdict = Some(Verdict {
        explained_by: vec!["ggx".into()],
        none_explains: false,
        best: "ggx".into(),
        best_held_out_rms: Some(1.01),
        limit_rms: 2.0,
        remedies: vec!["more lamp positions".into()],
    });
    f.files = vec!["fit/samples.csv".into(), "fit/fit.json".into()];
    f.seconds = Some(0.25);
    f
}

#[test]
fn a_fit_file_with_every_optional_part_survives_a_round_trip() {
    let f = full_fit();
    let bytes = serde_json::to_vec_pretty(&f).unwrap();
    let back: FitFile = serde_json::from_slice(&bytes).unwrap();
    assert_eq!(back, f);
    assert_eq!(serde_json::to_vec_pretty(&back).unwrap(), bytes);
    // Not finite numbers are written as null and read back as absent.
    let text = String::from_utf8(bytes).unwrap();
    assert!(text.contains("\"user-line\""), "{text}");
    assert_eq!(back.candidates[0].kd[0].ci95[1], None);
    // And the glint crate's check passes it (a file every reader takes).
    use glint::fit::file::Check as _;
    assert_eq!(back.check(&glint::fit::file::Facts { channels: 3 }), None);
}
