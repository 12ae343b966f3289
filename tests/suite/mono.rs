//! Monochrome cameras through the whole chain: grey frames, a one-channel response and
//! radiance ("Y"), one kd and one ks with an honest uncertainty, validation and report.
//!
//! The simulated mono sensor sees the mean of the three bands' radiance, so on the mock
//! scene (kd = [0.35, 0.25, 0.18], ks = [0.3, 0.3, 0.3], n = 120) it measures a tile with
//! kd = 0.26, ks = 0.3, n = 120.

use std::path::Path;

use glint::fit::model::{Model, Reflectance};
use glint::fit::run::Candidate;
use glint::pipeline::RunSummary;
use serde_json::Value;

use super::util::{err, glint, load, ok, set, small_table, tempdir};

const W: usize = 320;
const H: usize = 240;
const N: f64 = 120.0;
const KD: [f64; 3] = [0.35, 0.25, 0.18];
const KS: [f64; 3] = [0.3, 0.3, 0.3];

fn mean(v: [f64; 3]) -> f64 {
    (v[0] + v[1] + v[2]) / 3.0
}

/// The mock rig at `W` x `H`, `bits` deep, monochrome with `format` (None: RGB); the
/// 16-bit sensor is a linear one.
fn rig_table(format: Option<&str>, bits: u8) -> toml::Table {
    let mut t = small_table();
    let f = 1500.0 * W as f64 / 1280.0;
    set(&mut t, "camera.width", W as i64);
    set(&mut t, "camera.height", H as i64);
    set(&mut t, "camera.bit_depth", bits as i64);
    set(&mut t, "mock.camera.fx", f);
    set(&mut t, "mock.camera.fy", f);
    if let Some(p) = format {
        set(&mut t, "camera.pixel_format", p);
    }
    if bits == 16 {
        // A linear 16-bit sensor (as scientific cameras are): Glint's model choice must
        // find it linear.
        let mut response = toml::Table::new();
        response.insert("kind".into(), "linear".into());
        set(&mut t, "mock.sensor.response", response);
    }
    t
}

/// `glint run` on the rig `t` (written into `dir`), into `dir/<name>`.
fn run(dir: &Path, t: &toml::Table, name: &str) -> RunSummary {
    let rig = load(dir, t);
    let devices = glint::devices::open(&rig).unwrap();
    let s = glint::pipeline::run(
        &rig,
        devices,
        &dir.join(name),
        Default::default(),
        &Default::default(),
        &mut |_| {},
    )
    .unwrap_or_else(|e| panic!("glint run failed: {e}"));
    if let Some(line) = glint::pipeline::truth_line(&rig, &s) {
        println!("{line}");
    }
    s
}

fn blinn(s: &RunSummary) -> &Candidate {
    s.fit
        .candidates
        .iter()
        .find(|c| c.model == Model::BlinnPhong)
        .expect("Blinn-Phong is a candidate")
}

fn json(path: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

/// A mono run and an RGB run of the same scene at `bits`: the mono one recovers the mean
/// of the bands, its files are one channel throughout, and its n is no more certain than
/// the RGB run's (one third of the values: nothing counted three times).
fn mono_against_rgb(format: &str, bits: u8) {
    let dir = tempdir();
    let mono = run(dir.path(), &rig_table(Some(format), bits), "mono");
    let rgb_dir = tempdir();
    let rgb = run(rgb_dir.path(), &rig_table(None, bits), "rgb");
    let (m, r) = (blinn(&mono), blinn(&rgb));
    let kd_rgb_mean = (r.kd[0].value + r.kd[1].value + r.kd[2].value) / 3.0;
    println!(
        "{format} {bits}-bit mono: chosen {}, n {:.2} ± {:.2} [{:.2}, {:.2}], kd {:.5} ± {:.5}, ks {:.5} ± {:.5}, ks/kd {:.4} ± {:.4}, {} samples, dof {}",
        mono.fit.chosen.name(),
        m.n.value,
        m.n.sd,
        m.n.ci95[0],
        m.n.ci95[1],
        m.kd[0].value,
        m.kd[0].sd,
        m.ks[0].value,
        m.ks[0].sd,
        m.ks_over_kd[0].value,
        m.ks_over_kd[0].sd,
        mono.fit.sampling.sampled.used,
        m.dof
    );
    println!(
        "{format} {bits}-bit RGB:  chosen {}, n {:.2} ± {:.2} [{:.2}, {:.2}], kd {:.5} {:.5} {:.5} (mean {:.5}), ks/kd (G) {:.4} ± {:.4}, {} samples, dof {}",
        rgb.fit.chosen.name(),
        r.n.value,
        r.n.sd,
        r.n.ci95[0],
        r.n.ci95[1],
        r.kd[0].value,
        r.kd[1].value,
        r.kd[2].value,
        kd_rgb_mean,
        r.ks_over_kd[1].value,
        r.ks_over_kd[1].sd,
        rgb.fit.sampling.sampled.used,
        r.dof
    );
    // One channel: one kd, one ks, n; parameters 3 and the degrees of freedom of one
    // value a sample.
    assert_eq!(mono.fit.channels, 1);
    assert!(mono.fit.mono);
    assert_eq!((m.kd.len(), m.ks.len(), m.ks_over_kd.len()), (1, 1, 1));
    assert_eq!(m.parameters, 3);
    assert_eq!(m.dof, mono.fit.sampling.sampled.used - 3);
    assert_eq!(mono.fit.chosen, Model::BlinnPhong);
    // The truth a mono camera sees: the same n, ks/kd = mean(ks) / mean(kd).
    assert!((m.n.value / N - 1.0).abs() < 0.05, "n {}", m.n.value);
    let ratio = mean(KS) / mean(KD);
    assert!(
        (m.ks_over_kd[0].value / ratio - 1.0).abs() < 0.05,
        "ks/kd {} against {ratio}",
        m.ks_over_kd[0].value
    );
    // kd in the radiance's units: the mean of the bands the RGB camera measured.
    assert!(
        (m.kd[0].value / kd_rgb_mean - 1.0).abs() < 0.04,
        "mono kd {} against the RGB run's mean {kd_rgb_mean}",
        m.kd[0].value
    );
    // Honest uncertainty: the interval covers the truth, and a third of the values does
    // not make n more certain than the RGB run's.
    assert!(m.n.ci95[0] <= N && N <= m.n.ci95[1], "{:?}", m.n.ci95);
    assert!(m.n.sd > 0.0 && m.n.sd >= r.n.sd, "{} < {}", m.n.sd, r.n.sd);

    // The files: grey PNG frames of the camera's depth, a one-channel response (its own
    // profile), "Y" radiance, and fit.json listing one value with "channels": 1.
    let s = &mono.session;
    let man = glint::session::load(s).unwrap();
    assert_eq!(man.channels(), 1);
    for f in &man.frames {
        let png = std::fs::read(s.join(&f.file)).unwrap();
        let (_, _, depth, colour) = glint::session::png_header(&png).unwrap();
        assert_eq!((depth, colour), (bits, 0), "{} is not grey", f.file);
    }
    let resp = glint::hdr::files::load_response(&s.join("hdr/response.json")).unwrap();
    assert_eq!(resp.channels.len(), 1);
    let profile = dir
        .path()
        .join(format!("profiles/mock-camera-{bits}bit-mono.response.json"));
    let profiles: Vec<_> = std::fs::read_dir(dir.path().join("profiles"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(
        profiles.iter().all(|p| p.ends_with("-mono.response.json")),
        "{profiles:?} ({})",
        profile.display()
    );
    let (w, h, rad) = glint::hdr::files::read_exr(&s.join("hdr/radiance.exr")).unwrap();
    assert_eq!((w, h, rad.len()), (W, H, W * H));
    assert_eq!(json(&s.join("hdr/summary.json"))["channels"], 1);
    let fit = json(&s.join("fit/fit.json"));
    assert_eq!(
        (fit["channels"].as_u64(), fit["mono"].as_bool()),
        (Some(1), Some(true))
    );
    for c in fit["candidates"].as_array().unwrap() {
        assert_eq!(c["kd"].as_array().unwrap().len(), 1);
        assert_eq!(c["ks"].as_array().unwrap().len(), 1);
    }
    let csv = std::fs::read_to_string(s.join("fit/samples.csv")).unwrap();
    assert!(csv.lines().next().unwrap().contains("radiance_y"));
    // Validation compared one channel; the report says mono.
    let v = mono.validation.chosen();
    assert_eq!(mono.validation.channels, 1);
    assert_eq!(v.kd.len(), 1);
    assert_eq!(v.radiance.relative_error_rgb.len(), 1);
    println!(
        "{format} validation: PSNR {:.2} dB, RMSE {:.3} (noise {:.3}), {} readings",
        v.pixels.psnr_db, v.pixels.rmse, v.pixels.noise_rmse, v.pixels.readings
    );
    assert!(v.pixels.rmse < 1.5 * v.pixels.noise_rmse);
    let html = std::fs::read_to_string(s.join("report/index.html")).unwrap();
    assert!(html.contains("-bit, mono"), "the camera line says mono");
    assert!(html.contains("kd (mono)"));
    let text = mono.text(None);
    assert!(text.contains("kd (mono)"), "{text}");
}

#[test]
fn a_grey_8bit_run_recovers_the_mean_of_the_bands_with_an_honest_uncertainty() {
    mono_against_rgb("GREY", 8);
}

#[test]
fn a_y16_run_recovers_the_mean_of_the_bands_with_an_honest_uncertainty() {
    mono_against_rgb("Y16", 16);
}

/// A small mono capture in `dir/s`.
fn mono_session(dir: &Path) -> std::path::PathBuf {
    let mut t = small_table();
    set(&mut t, "camera.pixel_format", "GREY");
    super::util::record(dir, &t).unwrap_or_else(|e| panic!("capture: {e}"));
    dir.join("s")
}

#[test]
fn a_mono_session_verifies_and_its_channels_must_match_the_rig() {
    let dir = tempdir();
    let s = mono_session(dir.path());
    let path = s.to_str().unwrap();
    let text = ok(&glint(&["session", "verify", path]));
    println!("{text}");
    let man = glint::session::load(&s).unwrap();
    assert_eq!(man.camera.as_ref().unwrap().channels, 1);
    let f = &man.frames[0];
    let png = std::fs::read(s.join(&f.file)).unwrap();
    assert_eq!(glint::session::png_header(&png).unwrap(), (160, 120, 8, 0));
    // An RGB frame in a mono session is refused (its checksum made to fit).
    let sess_manifest = s.join("manifest.json");
    let original = std::fs::read(&sess_manifest).unwrap();
    let frame = s.join(&f.file);
    let kept = std::fs::read(&frame).unwrap();
    image::RgbImage::new(160, 120).save(&frame).unwrap();
    let sum = glint::session::sha256_hex(&std::fs::read(&frame).unwrap());
    let mut m: Value = serde_json::from_slice(&original).unwrap();
    m["frames"][0]["sha256"] = sum.into();
    std::fs::write(&sess_manifest, serde_json::to_vec(&m).unwrap()).unwrap();
    let out = glint(&["session", "verify", path]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(!out.status.success());
    assert!(
        text.contains("has 3 channels (RGB), but this session's frames are grey"),
        "{text}"
    );
    let e = err(&glint(&["hdr", path]));
    assert!(e.contains("grey"), "{e}");
    // The camera's report must match the embedded rig's pixel format.
    std::fs::write(&frame, kept).unwrap();
    let mut m: Value = serde_json::from_slice(&original).unwrap();
    m["camera"]["channels"] = 3.into();
    std::fs::write(&sess_manifest, serde_json::to_vec(&m).unwrap()).unwrap();
    let out = glint(&["session", "verify", path]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(!out.status.success());
    assert!(
        text.contains("3 channels (RGB) does not match the embedded rig's camera (1 channel (monochrome), pixel_format GREY)"),
        "{text}"
    );
    std::fs::write(&sess_manifest, original).unwrap();
    ok(&glint(&["session", "verify", path]));
}

#[test]
fn a_response_of_the_other_kind_is_refused_for_a_mono_session() {
    let dir = tempdir();
    let s = mono_session(dir.path());
    let path = s.to_str().unwrap();
    // The session's own (one-channel) response merges it.
    ok(&glint(&["hdr", path]));
    let resp = s.join("hdr/response.json");
    let mut r: Value = json(&resp);
    assert_eq!(r["channels"].as_array().unwrap().len(), 1);
    // An RGB response (three channels) for this mono session is refused, naming both.
    let ch = r["channels"][0].clone();
    r["channels"] = Value::Array(vec![ch.clone(), ch.clone(), ch]);
    // (Its alternative curves, one channel each, would be refused first.)
    r.as_object_mut().unwrap().remove("alternatives");
    let rgb = dir.path().join("rgb.response.json");
    std::fs::write(&rgb, serde_json::to_vec(&r).unwrap()).unwrap();
    let e = err(&glint(&["hdr", path, "--response", rgb.to_str().unwrap()]));
    assert!(
        e.contains("3 channels (RGB)") && e.contains("1 channel (monochrome)"),
        "{e}"
    );
}
