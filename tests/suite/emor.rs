//! The simulated sensor with a real camera response from the EMoR basis
//! (../shared/data/emor_camera_response_model; skipped with a message when absent).

use glint::capture;
use glint::devices;

use super::util::{load, record, root, set, small_table, tempdir};

#[test]
fn capture_with_an_emor_response_curve() {
    let emor = root().join("../shared/data/emor_camera_response_model/emor.txt");
    if !emor.exists() {
        eprintln!(
            "SKIPPED: {} is absent (it is shared test data, not part of the project)",
            emor.display()
        );
        return;
    }
    let dir = tempdir();
    let mut t = small_table();
    let mut response = toml::Table::new();
    response.insert("kind".into(), "emor".into());
    response.insert("file".into(), emor.to_str().unwrap().into());
    response.insert(
        "coefficients".into(),
        toml::Value::try_from(vec![0.4, -0.2, 0.1]).unwrap(),
    );
    set(&mut t, "mock.sensor.response", response);
    set(&mut t, "camera.bit_depth", 16);
    let rec = record(dir.path(), &t).unwrap();
    // Monotone response: the tile frames brighten with exposure.
    let means: Vec<f64> = rec
        .manifest
        .frames
        .iter()
        .filter(|f| f.kind == capture::FrameKind::Tile)
        .map(|f| {
            let v = image::open(dir.path().join("s").join(&f.file))
                .unwrap()
                .to_rgb16()
                .into_raw();
            v.iter().map(|x| *x as f64).sum::<f64>() / v.len() as f64
        })
        .collect();
    assert!(means.windows(2).all(|w| w[1] > w[0]), "{means:?}");
}

#[test]
fn a_missing_emor_file_is_named() {
    let dir = tempdir();
    let mut t = small_table();
    let mut response = toml::Table::new();
    response.insert("kind".into(), "emor".into());
    response.insert("file".into(), "no-such-emor.txt".into());
    response.insert(
        "coefficients".into(),
        toml::Value::try_from(Vec::<f64>::new()).unwrap(),
    );
    set(&mut t, "mock.sensor.response", response);
    let rig = load(dir.path(), &t);
    let e = devices::open(&rig).err().unwrap().to_string();
    assert!(
        e.contains("no-such-emor.txt") && e.contains("mock.sensor.response.file"),
        "{e}"
    );
}
