//! `glint fit` end to end: files, the table and JSON, and its errors.

use super::fit_pipeline::pipeline;
use super::util::{err, glint, ok, record, small_table, tempdir};

#[test]
fn glint_fit_writes_samples_and_fit_and_reports_every_candidate() {
    let dir = tempdir();
    pipeline(dir.path(), "blinn-phong", 120.0, 0.3, 7, [320, 240]);
    let s = dir.path().join("s");
    let out = ok(&glint(&["fit", s.to_str().unwrap()]));
    assert!(out.contains("chosen: blinn-phong"), "{out}");
    for m in ["lambert", "phong", "blinn-phong", "cosine-lobe"] {
        assert!(out.contains(m), "{out}");
    }
    let csv = std::fs::read_to_string(s.join("fit/samples.csv")).unwrap();
    assert!(csv.starts_with("u,v,x_mm,y_mm"));
    assert!(csv.lines().count() > 50);
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(s.join("fit/fit.json")).unwrap()).unwrap();
    assert_eq!(v["format"], "glint-fit");
    assert_eq!(v["chosen"], "blinn-phong");
    let bp = v["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["model"] == "blinn-phong")
        .unwrap();
    let n = bp["n"]["value"].as_f64().unwrap();
    let ci = [
        bp["n"]["ci95"][0].as_f64().unwrap(),
        bp["n"]["ci95"][1].as_f64().unwrap(),
    ];
    println!("n {n} {ci:?}; propagated {}", v["solver"]["propagated"]);
    assert!((n / 120.0 - 1.0).abs() < 0.1 && ci[0] < n && n < ci[1]);
    assert!(bp["n_variance_share"]["calibration"].as_f64().unwrap() > 0.0);

    // One model, a user line, JSON on stdout.
    let out = ok(&glint(&[
        "fit",
        s.to_str().unwrap(),
        "--model",
        "phong",
        "--line",
        "100,120,220,120",
        "--json",
    ]));
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["candidates"].as_array().unwrap().len(), 1);
    assert_eq!(v["sampling"]["strategy"]["user-line"][0], 100.0);
}

#[test]
fn glint_fit_names_the_missing_stage() {
    let dir = tempdir();
    record(dir.path(), &small_table()).unwrap();
    let s = dir.path().join("s");
    let e = err(&glint(&["fit", s.to_str().unwrap()]));
    assert!(e.contains("glint calibrate"), "{e}");
    glint::calib::run::run_session(&s, None).unwrap();
    let e = err(&glint(&["fit", s.to_str().unwrap()]));
    assert!(e.contains("glint hdr"), "{e}");
    glint::hdr::run::run(&s, &Default::default(), &mut |_| {}).unwrap();
    let e = err(&glint(&["fit", s.to_str().unwrap(), "--line", "1,2,3"]));
    assert!(e.contains("u0,v0,u1,v1"), "{e}");
    let e = err(&glint(&["fit", s.to_str().unwrap(), "--line", "0,0,3,0"]));
    assert!(e.contains("does not cross the tile"), "{e}");
    let e = err(&glint(&[
        "fit",
        dir.path().join("nothing").to_str().unwrap(),
    ]));
    assert!(e.contains("manifest"), "{e}");
    // A corrupt radiance file.
    std::fs::write(s.join("hdr/radiance.exr"), b"junk").unwrap();
    let e = err(&glint(&["fit", s.to_str().unwrap()]));
    assert!(e.contains("radiance.exr"), "{e}");
    assert!(!s.join("fit/fit.json").exists());
}
