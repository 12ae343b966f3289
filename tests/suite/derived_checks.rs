//! No silent nonsense from a session: every stage checks what it reads,
//! once, in the reader every stage shares: the HDR files say what they hold (a swap is
//! caught), a response's curve must rise, fit.json is refused by validate, report and
//! export alike, export opens the manifest as every stage does, `session verify` refuses
//! an absurd exact exposure, and a camera's profiles and `--intrinsics` files get the rules
//! of the session's own files.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use serde_json::Value;

use super::util::{copy_dir, err, glint, ok, record, small_table, tempdir};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A complete small mock session, merged (its profile stored beside the rig), calibrated
/// and fitted, made once: `(rig.toml, session)` in a folder kept for the tests' run.
fn fitted() -> &'static (PathBuf, PathBuf) {
    static S: OnceLock<(tempfile::TempDir, (PathBuf, PathBuf))> = OnceLock::new();
    &S.get_or_init(|| {
        let dir = tempdir();
        record(dir.path(), &small_table()).unwrap();
        let (rig, sess) = (dir.path().join("rig.toml"), dir.path().join("s"));
        ok(&glint(&["hdr", s(&sess), "--rig", s(&rig)]));
        ok(&glint(&["calibrate", s(&sess)]));
        ok(&glint(&["fit", s(&sess)]));
        (dir, (rig, sess))
    })
    .1
}

/// A copy of the fitted session (and its rig with its profiles) in `dir`: (rig, session).
fn copy(dir: &Path) -> (PathBuf, PathBuf) {
    copy_dir(fitted().0.parent().unwrap(), dir);
    (dir.join("rig.toml"), dir.join("s"))
}

fn read_json(p: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap()
}

fn write_json(p: &Path, v: &Value) {
    std::fs::write(p, serde_json::to_vec_pretty(v).unwrap()).unwrap();
}

/// The single error line of a failed stage, checked to contain each of `want` and no
/// panic.
fn refused(out: &std::process::Output, want: &[&str]) -> String {
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    let e = err(out);
    for w in want {
        assert!(e.contains(w), "{e}\nshould contain: {w}");
    }
    e
}

#[test]
fn swapped_radiance_and_variance_are_refused_naming_the_header() {
    let d = tempdir();
    let (_, sess) = copy(d.path());
    let hdr = sess.join("hdr");
    std::fs::rename(hdr.join("radiance.exr"), hdr.join("x.exr")).unwrap();
    std::fs::rename(hdr.join("variance.exr"), hdr.join("radiance.exr")).unwrap();
    std::fs::rename(hdr.join("x.exr"), hdr.join("variance.exr")).unwrap();
    // Was: fit chose Lambert without a word (exit 0).
    for stage in ["fit", "validate"] {
        let e = refused(
            &glint(&[stage, s(&sess)]),
            &["hdr/radiance.exr", "glint_quantity", "re-run glint hdr"],
        );
        assert!(e.contains("variance of radiance"), "{stage}: {e}");
    }
    // The variance copied over the radiance: only radiance.exr is wrong.
    std::fs::copy(hdr.join("radiance.exr"), hdr.join("variance.exr")).unwrap();
    refused(
        &glint(&["fit", s(&sess)]),
        &["hdr/radiance.exr", "glint_quantity"],
    );
}

#[test]
fn hdr_files_without_the_attribute_are_still_read() {
    // Files written before the header was checked (or by another tool) carry no
    // glint_quantity: they are read as their names say.
    let d = tempdir();
    let (w, h, data) = (4, 3, vec![1.0f32; 36]);
    for name in ["radiance.exr", "variance.exr"] {
        let bytes = glint::hdr::files::encode_exr(w, h, &data, &[]).unwrap();
        std::fs::write(d.path().join(name), bytes).unwrap();
        let (rw, rh, px) = glint::hdr::files::read_exr(&d.path().join(name)).unwrap();
        assert_eq!((rw, rh, px.len()), (4, 3, 36));
    }
    // A wrong tag is refused whatever else the file holds.
    let bytes =
        glint::hdr::files::encode_exr(w, h, &data, &[("glint_quantity", "radiance".to_string())])
            .unwrap();
    std::fs::write(d.path().join("variance.exr"), bytes).unwrap();
    let e = glint::hdr::files::read_exr(&d.path().join("variance.exr"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("glint_quantity") && e.contains("`radiance`"),
        "{e}"
    );
}

/// Reverse every channel's ln_exposure in a response file.
fn reverse_response(p: &Path) {
    let mut v = read_json(p);
    for ch in v["channels"].as_array_mut().unwrap() {
        ch["ln_exposure"].as_array_mut().unwrap().reverse();
    }
    write_json(p, &v);
}

#[test]
fn a_reversed_response_is_refused_by_validate_and_fit() {
    let d = tempdir();
    let (_, sess) = copy(d.path());
    reverse_response(&sess.join("hdr/response.json"));
    // Was: validate printed "readings 0 ... PSNR NaN" and exited 0.
    for stage in ["validate", "fit", "calibrate"] {
        refused(
            &glint(&[stage, s(&sess)]),
            &["hdr/response.json", "ln_exposure must increase"],
        );
    }
}

#[test]
fn a_response_profile_beside_the_rig_and_a_response_file_get_the_same_rules() {
    let d = tempdir();
    let (rig, sess) = copy(d.path());
    let profiles: Vec<PathBuf> = std::fs::read_dir(d.path().join("profiles"))
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| s(p).ends_with(".response.json"))
        .collect();
    assert_eq!(profiles.len(), 1, "{profiles:?}");
    reverse_response(&profiles[0]);
    refused(
        &glint(&["hdr", s(&sess), "--rig", s(&rig)]),
        &[".response.json", "ln_exposure must increase"],
    );
    refused(
        &glint(&["hdr", s(&sess), "--response", s(&profiles[0])]),
        &[".response.json", "ln_exposure must increase"],
    );
}

#[test]
fn an_intrinsics_file_with_a_negative_variance_is_refused_as_camera_json_is() {
    let d = tempdir();
    let (_, sess) = copy(d.path());
    let mut v = read_json(&sess.join("calib/camera.json"));
    let cov = &mut v["calibration"]["views"][0]["covariance"];
    assert!(cov.as_array().is_some_and(|c| !c.is_empty()), "{cov}");
    cov[0][0] = Value::from(-1.0);
    let file = d.path().join("lens.json");
    write_json(&file, &v);
    refused(
        &glint(&["calibrate", s(&sess), "--intrinsics", s(&file)]),
        &["lens.json", "covariance", "negative"],
    );
    // The session's own calib/camera.json, the same.
    write_json(&sess.join("calib/camera.json"), &v);
    refused(
        &glint(&["fit", s(&sess)]),
        &["calib/camera.json", "covariance", "negative"],
    );
}

/// Edit the session's fit.json and check validate, report and export refuse it, naming
/// fit.json and each of `want`.
fn fit_json_refused(sess: &Path, edit: impl FnOnce(&mut Value), want: &[&str]) {
    let p = sess.join("fit/fit.json");
    let good = std::fs::read(&p).unwrap();
    let mut v: Value = serde_json::from_slice(&good).unwrap();
    edit(&mut v);
    write_json(&p, &v);
    for args in [
        vec!["validate", s(sess)],
        vec!["report", s(sess)],
        vec!["report", s(sess), "--json"],
        vec!["export", s(sess), "--to", "json"],
    ] {
        let e = refused(&glint(&args), want);
        assert!(
            e.contains("fit/fit.json") && e.contains("re-run glint fit"),
            "{args:?}: {e}"
        );
    }
    std::fs::write(&p, good).unwrap();
}

#[test]
fn absurd_fit_json_is_refused_by_validate_report_and_export_alike() {
    let d = tempdir();
    let (_, sess) = copy(d.path());
    let chosen = read_json(&sess.join("fit/fit.json"))["chosen"]
        .as_str()
        .unwrap()
        .to_string();
    let lobe = |v: &mut Value| -> usize {
        v["candidates"]
            .as_array()
            .unwrap()
            .iter()
            .position(|c| c["model"] != "lambert")
            .unwrap()
    };
    // Was: each passed validate and report (export refused some).
    fit_json_refused(
        &sess,
        |v| v["candidates"][0]["kd"][0]["value"] = Value::from(-1e8),
        &["candidates[0]", "kd[0]", "value"],
    );
    fit_json_refused(&sess, |v| v["format"] = "x".into(), &["format", "`x`"]);
    fit_json_refused(
        &sess,
        |v| v["channels"] = Value::from(1),
        &["channels", "3 channels (RGB)"],
    );
    fit_json_refused(
        &sess,
        |v| {
            let i = lobe(v);
            v["candidates"][i]["n"]["ci95"] = serde_json::json!([500.0, 10.0]);
        },
        &["n", "ci95", "inverted"],
    );
    fit_json_refused(
        &sess,
        |v| v["candidates"][0]["kd"][1]["sd"] = Value::from(-0.5),
        &["kd[1]", "sd", "negative"],
    );
    fit_json_refused(
        &sess,
        |v| {
            let c = v["candidates"][0].clone();
            v["candidates"].as_array_mut().unwrap().push(c);
        },
        &["model", "listed twice"],
    );
    fit_json_refused(
        &sess,
        |v| {
            let i = lobe(v);
            v["candidates"][i]["covariance"]["matrix"][0][0] = Value::from(-1.0);
        },
        &["covariance", "negative"],
    );
    fit_json_refused(
        &sess,
        |v| v["chosen"] = "ward".into(),
        &["chosen", "`ward`"],
    );
    // The file as written passes every stage.
    ok(&glint(&["export", s(&sess), "--to", "json"]));
    assert!(!chosen.is_empty());
}

fn edit_manifest(sess: &Path, edit: impl FnOnce(&mut Value)) {
    let p = sess.join("manifest.json");
    let mut v = read_json(&p);
    edit(&mut v);
    write_json(&p, &v);
}

#[test]
fn export_opens_the_manifest_as_every_stage_does() {
    let d = tempdir();
    let (_, sess) = copy(d.path());
    // Was: export ignored the manifest's state.
    edit_manifest(&sess, |v| v["state"] = "capturing".into());
    refused(
        &glint(&["export", s(&sess), "--to", "json"]),
        &["capturing", "--allow-incomplete"],
    );
    let out = glint(&["export", s(&sess), "--to", "json", "--allow-incomplete"]);
    ok(&out);
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("warning: the session is `capturing`"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // And its frame rules: a frame listed twice.
    edit_manifest(&sess, |v| {
        v["state"] = "complete".into();
        let f = v["frames"][1]["file"].clone();
        v["frames"][2]["file"] = f;
    });
    refused(
        &glint(&["export", s(&sess), "--to", "json", "--force"]),
        &["manifest.json", "listed twice"],
    );
}

#[test]
fn verify_refuses_an_absurd_exact_exposure() {
    let d = tempdir();
    let (_, sess) = copy(d.path());
    let verify = |sess: &Path| glint(&["session", "verify", s(sess)]);
    for bad in [1e-300, 0.5, 1e9] {
        edit_manifest(&sess, |v| {
            v["frames"][0]["exposure_exact_us"] = Value::from(bad);
        });
        // Was: 1e-300 passed `session verify`.
        let out = verify(&sess);
        let text = String::from_utf8_lossy(&out.stdout);
        assert!(!out.status.success(), "{bad}: verify passed:\n{text}");
        assert!(
            text.lines().any(|l| l.starts_with("problem:")
                && l.contains("frame 0")
                && l.contains("exposure_exact_us")),
            "{bad}: {text}"
        );
        refused(&glint(&["hdr", s(&sess)]), &["exposure_exact_us"]);
    }
    // The reported time to full precision (within half a µs) is fine.
    edit_manifest(&sess, |v| {
        let r = v["frames"][0]["exposure_reported_us"].as_f64().unwrap();
        v["frames"][0]["exposure_exact_us"] = Value::from(r + 0.25);
    });
    let out = verify(&sess);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
}
