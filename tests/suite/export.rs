//! `glint export` end to end: a Blinn-Phong tile captured, merged, calibrated and fitted on
//! the simulated lab, exported to json, mitsuba and gltf, the files read back.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use serde_json::Value;

use super::fit_pipeline::pipeline;
use super::util::{copy_dir, err, glint, ok, tempdir};

/// One fitted session for every test here (made once: about half a minute).
fn session() -> &'static Path {
    static S: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    &S.get_or_init(|| {
        let dir = tempdir();
        pipeline(dir.path(), "blinn-phong", 120.0, 0.3, 11, [320, 240]);
        let s = dir.path().join("s");
        ok(&glint(&["fit", s.to_str().unwrap()]));
        (dir, s)
    })
    .1
}

fn fit_json(s: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(s.join("fit/fit.json")).unwrap()).unwrap()
}

fn stderr(o: &std::process::Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// The percentage after `label` in a line of stderr.
fn percent_after(text: &str, label: &str) -> f64 {
    let i = text
        .find(label)
        .unwrap_or_else(|| panic!("{label} in {text}"))
        + label.len();
    text[i..]
        .trim_start()
        .split('%')
        .next()
        .unwrap()
        .trim()
        .parse()
        .unwrap()
}

/// `glint export SESSION --to TO EXTRA... --out OUT`.
fn export(session: &Path, to: &str, out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec!["export", session.to_str().unwrap(), "--to", to];
    args.extend_from_slice(extra);
    args.extend_from_slice(&["--out", out.to_str().unwrap()]);
    glint(&args)
}

#[test]
fn export_json_carries_fit_json_parameters_and_says_relative() {
    let s = session();
    let out_dir = tempdir();
    let out = out_dir.path().join("m.json");
    let o = export(s, "json", &out, &[]);
    ok(&o);
    let v: Value = serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
    let f = fit_json(s);
    let chosen = f["chosen"].as_str().unwrap();
    let c = f["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["model"] == chosen)
        .unwrap();
    assert_eq!(v["model"], chosen);
    assert_eq!(v["units"], "relative");
    assert!(v["units_note"].as_str().unwrap().contains("RELATIVE"));
    assert!(v["formula"].as_str().unwrap().starts_with("f_r = kd"));
    for k in ["kd", "ks", "ks_over_kd"] {
        assert_eq!(v[k], c[k], "{k}");
    }
    assert_eq!(v["n"], c["n"]);
    // The covariance as fit.json has it: named parameters, its diagonal the sds.
    assert_eq!(v["covariance"]["parameters"], c["covariance"]["parameters"]);
    assert_eq!(v["covariance"]["matrix"], c["covariance"]["matrix"]);
    let names = v["covariance"]["parameters"].as_array().unwrap();
    assert_eq!(names.len(), 7);
    for (i, name) in names.iter().enumerate() {
        let name = name.as_str().unwrap();
        let var = v["covariance"]["matrix"][i][i].as_f64().unwrap();
        let sd = match name.split_once('_').unwrap() {
            ("ln", "n") => v["n"]["sd"].as_f64().unwrap() / v["n"]["value"].as_f64().unwrap(),
            (kind, ch) => v[kind]["rgb".find(ch).unwrap()]["sd"].as_f64().unwrap(),
        };
        assert!(
            (var.sqrt() / sd - 1.0).abs() < 1e-9,
            "{name}: {var} against sd {sd}"
        );
    }
    // A fit.json from before the covariance was written: said, not invented.
    let old = tempdir();
    let copy = old.path().join("s");
    copy_dir(s, &copy);
    let mut f = fit_json(&copy);
    for c in f["candidates"].as_array_mut().unwrap() {
        c.as_object_mut().unwrap().remove("covariance");
    }
    std::fs::write(copy.join("fit/fit.json"), serde_json::to_vec(&f).unwrap()).unwrap();
    let o = old.path().join("m.json");
    ok(&export(&copy, "json", &o, &[]));
    let before: Value = serde_json::from_slice(&std::fs::read(&o).unwrap()).unwrap();
    assert!(before["covariance"].is_null());
    assert!(before["covariance_note"]
        .as_str()
        .unwrap()
        .contains("no covariance"));
    assert_eq!(v["session"], s.display().to_string());

    // Another model by name, and an unknown one.
    ok(&export(
        s,
        "json",
        &out_dir.path().join("l.json"),
        &["--model", "lambert"],
    ));
    let v: Value =
        serde_json::from_slice(&std::fs::read(out_dir.path().join("l.json")).unwrap()).unwrap();
    assert_eq!(v["model"], "lambert");
    assert!(v["n"].is_null());
    let e = err(&glint(&[
        "export",
        s.to_str().unwrap(),
        "--to",
        "json",
        "--model",
        "ward",
    ]));
    assert!(
        e.contains("unknown model") && e.contains("blinn-phong"),
        "{e}"
    );
}

#[test]
fn export_mitsuba_fits_roughplastic_to_the_blinn_phong_tile() {
    let s = session();
    let d = tempdir();
    let out = d.path().join("tile.xml");
    // A relative session: refused without --albedo, in one line naming the fix.
    let e = err(&export(s, "mitsuba", &out, &[]));
    assert!(e.contains("relative") && e.contains("--albedo"), "{e}");
    assert!(!out.exists());
    let o = export(s, "mitsuba", &out, &["--albedo", "0.6"]);
    ok(&o);
    let err_text = stderr(&o);
    println!("{err_text}");
    let xml = std::fs::read_to_string(&out).unwrap();
    println!("{xml}");
    let doc = roxmltree::Document::parse(&xml).expect("well-formed XML");
    let bsdf = doc.root_element();
    assert_eq!(bsdf.tag_name().name(), "bsdf");
    assert_eq!(bsdf.attribute("type"), Some("roughplastic"));
    let value = |name: &str| {
        bsdf.children()
            .find(|n| n.attribute("name") == Some(name))
            .and_then(|n| n.attribute("value"))
            .unwrap_or_else(|| panic!("{name}"))
            .to_string()
    };
    let alpha: f64 = value("alpha").parse().unwrap();
    let diffuse: Vec<f64> = value("diffuse_reflectance")
        .split(',')
        .map(|x| x.trim().parse().unwrap())
        .collect();
    assert!(["beckmann", "ggx"].contains(&value("distribution").as_str()));
    // Walter's rule for n = 120 gives 0.128; the fit lands near it.
    assert!(alpha > 0.06 && alpha < 0.25, "{alpha}");
    // The albedo assumption is about the diffuse albedo: the brightest channel's is near
    // 0.6 (the roughplastic's interface takes a few percent).
    let max = diffuse.iter().copied().fold(0.0, f64::max);
    assert!(max > 0.45 && max <= 1.0, "{diffuse:?}");
    assert!(diffuse.iter().all(|d| *d > 0.1), "{diffuse:?}");
    assert!(xml.contains("ASSUMPTION") && xml.contains("albedo option 0.6"));
    // The conversion's error over the measured angles, in the file and on stderr.
    let rms = percent_after(&err_text, "measured angles:");
    println!("mitsuba conversion rms relative error {rms}%");
    assert!(rms < 5.0, "{rms}");
    assert!(xml.contains("rms relative error"));
}

#[test]
fn export_gltf_is_valid_json_with_a_fitted_material() {
    let s = session();
    let d = tempdir();
    let out = d.path().join("tile.gltf");
    let e = err(&export(s, "gltf", &out, &[]));
    assert!(e.contains("--albedo"), "{e}");
    let o = export(s, "gltf", &out, &["--albedo", "0.6"]);
    ok(&o);
    let err_text = stderr(&o);
    println!("{err_text}");
    let v: Value = serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
    assert_eq!(v["asset"]["version"], "2.0");
    let m = &v["materials"][0];
    let pbr = &m["pbrMetallicRoughness"];
    assert_eq!(pbr["metallicFactor"], 0.0);
    let base: Vec<f64> = pbr["baseColorFactor"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect();
    assert_eq!(base.len(), 4);
    assert!(base.iter().all(|b| (0.0..=1.0).contains(b)));
    let rough = pbr["roughnessFactor"].as_f64().unwrap();
    let alpha = v["extras"]["glint"]["conversion"]["ggx_alpha"]
        .as_f64()
        .unwrap();
    assert!((rough - alpha.sqrt()).abs() < 1e-5);
    assert!(alpha > 0.05 && alpha < 0.3, "{alpha}");
    // The mesh refers to the material, its buffer is a data URI of the stated length.
    assert_eq!(v["meshes"][0]["primitives"][0]["material"], 0);
    assert_eq!(v["buffers"][0]["byteLength"], 108);
    if m["extensions"]["KHR_materials_specular"].is_object() {
        assert!(v["extensionsUsed"]
            .as_array()
            .unwrap()
            .contains(&"KHR_materials_specular".into()));
    }
    assert_eq!(v["extras"]["glint"]["assumed_albedo"], 0.6);
    let rms = percent_after(&err_text, "measured angles:");
    println!("gltf conversion rms relative error {rms}%");
    assert!(rms < 5.0, "{rms}");
    let stored = v["extras"]["glint"]["conversion"]["rms_relative_error"]
        .as_f64()
        .unwrap();
    assert!((100.0 * stored - rms).abs() < 0.01);

    // Lambert to glTF: no lobe, exact.
    let out_l = d.path().join("lambert.gltf");
    ok(&export(
        s,
        "gltf",
        &out_l,
        &["--model", "lambert", "--albedo", "0.5"],
    ));
    let v: Value = serde_json::from_slice(&std::fs::read(&out_l).unwrap()).unwrap();
    let m = &v["materials"][0];
    assert_eq!(m["pbrMetallicRoughness"]["roughnessFactor"], 1.0);
    assert_eq!(
        m["extensions"]["KHR_materials_specular"]["specularFactor"],
        0.0
    );
    let base = m["pbrMetallicRoughness"]["baseColorFactor"]
        .as_array()
        .unwrap();
    let max = base[..3]
        .iter()
        .map(|x| x.as_f64().unwrap())
        .fold(0.0, f64::max);
    assert!((max - 0.5).abs() < 1e-6, "{max}");
    assert!(
        v["extras"]["glint"]["conversion"]["rms_relative_error"]
            .as_f64()
            .unwrap()
            < 1e-9
    );
}

#[test]
fn export_never_overwrites_without_force() {
    let s = session();
    let d = tempdir();
    let out = d.path().join("mine.json");
    std::fs::write(&out, b"the user's notes").unwrap();
    let args = |extra: &[&str]| {
        let mut a = vec!["export", s.to_str().unwrap(), "--to", "json", "--out"];
        a.push(out.to_str().unwrap());
        a.extend_from_slice(extra);
        a.iter().map(|x| x.to_string()).collect::<Vec<_>>()
    };
    let run = |a: Vec<String>| glint(&a.iter().map(|x| x.as_str()).collect::<Vec<_>>());
    let e = err(&run(args(&[])));
    assert!(e.contains("exists") && e.contains("--force"), "{e}");
    assert_eq!(std::fs::read(&out).unwrap(), b"the user's notes");
    // A link there is not followed either.
    let link = d.path().join("link.json");
    let target = d.path().join("target.json");
    std::os::unix::fs::symlink(&target, &link).unwrap();
    let e = err(&export(s, "json", &link, &[]));
    assert!(e.contains("exists"), "{e}");
    assert!(!target.exists());
    ok(&run(args(&["--force"])));
    let v: Value = serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
    assert_eq!(v["format"], "glint-material");
}

/// A session whose fit.json is tomorrow's: `units: absolute` and an `absolute` block per
/// candidate. The exports use the absolute values and need no --albedo.
#[test]
fn export_uses_absolute_units_where_fit_json_has_them() {
    let s = session();
    let d = tempdir();
    let a = d.path().join("abs");
    for sub in ["calib", "fit"] {
        std::fs::create_dir_all(a.join(sub)).unwrap();
    }
    std::fs::copy(s.join("manifest.json"), a.join("manifest.json")).unwrap();
    std::fs::copy(s.join("calib/camera.json"), a.join("calib/camera.json")).unwrap();
    std::fs::copy(s.join("fit/samples.csv"), a.join("fit/samples.csv")).unwrap();
    let mut f = fit_json(s);
    f["units"] = "absolute".into();
    // Absolute = relative times one factor chosen so the brightest albedo is 0.4.
    let chosen = f["chosen"].clone();
    let c = f["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["model"] == chosen)
        .unwrap()
        .clone();
    let kd_max = c["kd"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["value"].as_f64().unwrap())
        .fold(0.0, f64::max);
    let k = 0.4 / (std::f64::consts::PI * kd_max);
    let scaled = |ps: &Value, by: f64| {
        Value::Array(
            ps.as_array()
                .unwrap()
                .iter()
                .map(|p| {
                    serde_json::json!({
                        "value": p["value"].as_f64().unwrap() * by,
                        "sd": p["sd"].as_f64().unwrap() * by,
                        "ci95": [p["ci95"][0].as_f64().unwrap() * by, p["ci95"][1].as_f64().unwrap() * by],
                    })
                })
                .collect(),
        )
    };
    for cand in f["candidates"].as_array_mut().unwrap() {
        let abs = serde_json::json!({
            "kd_per_sr": scaled(&cand["kd"], k),
            "albedo": scaled(&cand["kd"], k * std::f64::consts::PI),
            "ks_per_sr": scaled(&cand["ks"], k),
        });
        cand["absolute"] = abs;
    }
    std::fs::write(
        a.join("fit/fit.json"),
        serde_json::to_vec_pretty(&f).unwrap(),
    )
    .unwrap();

    let out = d.path().join("abs.json");
    ok(&export(&a, "json", &out, &[]));
    let v: Value = serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
    assert_eq!(v["units"], "absolute");
    // Its covariance is in relative units and this file gives no reference factor.
    assert!(v["covariance"].is_null());
    assert!(v["covariance_note"].as_str().unwrap().contains("1/sr"));
    assert_eq!(v["kd"], scaled(&c["kd"], k));
    assert_eq!(v["relative"]["kd"], c["kd"]);

    let out = d.path().join("abs.xml");
    let o = export(&a, "mitsuba", &out, &[]);
    ok(&o);
    let xml = std::fs::read_to_string(&out).unwrap();
    assert!(!xml.contains("ASSUMPTION") && xml.contains("absolute"));
    // The same numbers as a relative export with the matching --albedo.
    let out2 = d.path().join("rel.xml");
    ok(&export(s, "mitsuba", &out2, &["--albedo", "0.4"]));
    let bsdf = |t: &str| t[t.find("<bsdf").unwrap()..].to_string();
    assert_eq!(bsdf(&xml), bsdf(&std::fs::read_to_string(&out2).unwrap()));
    let e = err(&glint(&[
        "export",
        a.to_str().unwrap(),
        "--to",
        "gltf",
        "--albedo",
        "0.5",
    ]));
    assert!(e.contains("absolute") && e.contains("--albedo"), "{e}");
}

#[test]
fn export_names_the_missing_fit_and_refuses_broken_files() {
    let d = tempdir();
    let s = session();
    let b = d.path().join("b");
    std::fs::create_dir_all(b.join("calib")).unwrap();
    std::fs::copy(s.join("manifest.json"), b.join("manifest.json")).unwrap();
    std::fs::copy(s.join("calib/camera.json"), b.join("calib/camera.json")).unwrap();
    let e = err(&glint(&["export", b.to_str().unwrap(), "--to", "json"]));
    assert!(e.contains("glint fit"), "{e}");
    std::fs::create_dir_all(b.join("fit")).unwrap();
    for junk in [
        &b"{"[..],
        b"[]",
        b"{\"format\": \"glint-fit\"}",
        b"\xff\xfe",
    ] {
        std::fs::write(b.join("fit/fit.json"), junk).unwrap();
        let e = err(&glint(&["export", b.to_str().unwrap(), "--to", "json"]));
        assert!(e.contains("fit.json"), "{e}");
    }
    // A good fit.json, samples.csv broken.
    std::fs::copy(s.join("fit/fit.json"), b.join("fit/fit.json")).unwrap();
    let e = err(&glint(&["export", b.to_str().unwrap(), "--to", "json"]));
    assert!(e.contains("samples.csv"), "{e}");
    let csv = std::fs::read_to_string(s.join("fit/samples.csv")).unwrap();
    let mut lines: Vec<String> = csv.lines().map(String::from).collect();
    lines[3] = lines[3].replacen(",", ",NaN,", 2);
    std::fs::write(b.join("fit/samples.csv"), lines.join("\n")).unwrap();
    let e = err(&glint(&["export", b.to_str().unwrap(), "--to", "json"]));
    assert!(e.contains("samples.csv") && e.contains("line"), "{e}");
    std::fs::write(b.join("fit/samples.csv"), "u,v\n1,2\n").unwrap();
    let e = err(&glint(&["export", b.to_str().unwrap(), "--to", "json"]));
    assert!(e.contains("no column"), "{e}");
    // --out into a folder that is not there.
    std::fs::copy(s.join("fit/samples.csv"), b.join("fit/samples.csv")).unwrap();
    let e = err(&export(&b, "json", &d.path().join("no/such/x.json"), &[]));
    assert!(e.contains("no such folder"), "{e}");
    // The default place: SESSION/export/<model>.json.
    let out = ok(&glint(&["export", b.to_str().unwrap(), "--to", "json"]));
    assert!(out.trim().ends_with("export/blinn-phong.json"), "{out}");
}
