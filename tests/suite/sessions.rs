//! Sessions: contents, lossless frames, checksums, never overwriting.

use glint::capture::{self, FrameKind};
use glint::devices::{self, Pixels};
use glint::session::{self, State};

use super::util::{load, record, set, small_table, tempdir};

#[test]
fn a_complete_session_holds_the_bracket_darks_and_grid() {
    let dir = tempdir();
    let rig = load(dir.path(), &small_table());
    let out = dir.path().join("s");
    let mut events = 0;
    let rec = capture::record(
        &rig,
        devices::open(&rig).unwrap(),
        &out,
        Default::default(),
        &mut |_| events += 1,
    )
    .unwrap();
    let m = session::load(&out).unwrap();
    assert_eq!(m, rec.manifest);
    assert_eq!(m.state, State::Complete);
    assert!(events > 30, "progress is reported");
    assert_eq!(m.lamp_identity.as_deref(), Some("GLINT-MOCK-LAMP,1.0"));
    assert_eq!(m.camera.as_ref().unwrap().width, 160);
    let of = |k| m.frames.iter().filter(|f| f.kind == k).collect::<Vec<_>>();
    let tile = of(FrameKind::Tile);
    assert_eq!(tile.len(), 7);
    let (lo, hi) = (
        tile[0].exposure_requested_us as f64,
        tile[6].exposure_requested_us as f64,
    );
    assert!((hi / lo).log2() >= 6.0);
    assert_eq!(of(FrameKind::Dark).len(), 7);
    assert_eq!(of(FrameKind::Grid).len(), 1);
    for f in &m.frames {
        assert_eq!(f.lamp.on, f.kind != FrameKind::Dark, "{}", f.file);
        let img = image::open(out.join(&f.file)).unwrap();
        assert_eq!((img.width(), img.height()), (160, 120));
    }
    assert!(m
        .frames
        .windows(2)
        .all(|w| w[0].sequence < w[1].sequence && w[0].timestamp <= w[1].timestamp));
    assert_eq!(
        std::fs::read_to_string(out.join("rig.toml")).unwrap(),
        rig.text
    );
    assert!(session::verify(&out).unwrap().intact());
    // Brighter with longer exposure (the physics arrived in the files).
    let mean = |f: &session::FrameRecord| {
        let v = image::open(out.join(&f.file)).unwrap().to_rgb8().into_raw();
        v.iter().map(|x| *x as f64).sum::<f64>() / v.len() as f64
    };
    assert!(tile.windows(2).all(|w| mean(w[1]) > mean(w[0])));
    assert!(mean(of(FrameKind::Dark)[0]) < 2.0);
}

#[test]
fn sixteen_bit_frames_round_trip_exactly() {
    let pixels: Vec<u16> = (0..4 * 3 * 3).map(|i| (i * 1811 % 65536) as u16).collect();
    let png = session::encode_png(4, 3, &Pixels::U16(pixels.clone())).unwrap();
    let back = image::load_from_memory(&png).unwrap();
    assert_eq!(back.color(), image::ColorType::Rgb16);
    assert_eq!(back.to_rgb16().into_raw(), pixels);

    let dir = tempdir();
    let mut t = small_table();
    set(&mut t, "camera.bit_depth", 16);
    let rec = record(dir.path(), &t).unwrap();
    let f = &rec.manifest.frames[3];
    let img = image::open(dir.path().join("s").join(&f.file)).unwrap();
    assert_eq!(img.color(), image::ColorType::Rgb16);
    assert!(
        img.to_rgb16().into_raw().iter().any(|v| *v > 255),
        "uses the 16-bit range"
    );
}

#[test]
fn verify_finds_altered_missing_and_stray_files() {
    let dir = tempdir();
    let out = dir.path().join("s");
    let rec = record(dir.path(), &small_table()).unwrap();
    let f0 = out.join(&rec.manifest.frames[0].file);
    let mut bytes = std::fs::read(&f0).unwrap();
    let last = bytes.len() - 20;
    bytes[last] ^= 1;
    std::fs::remove_file(&f0).unwrap();
    std::fs::write(&f0, bytes).unwrap();
    std::fs::remove_file(out.join(&rec.manifest.frames[1].file)).unwrap();
    std::fs::write(out.join("frames/.0099-tile.png.tmp-1"), b"partial").unwrap();
    let r = session::verify(&out).unwrap();
    assert_eq!(r.problems.len(), 2, "{:?}", r.problems);
    assert!(r.problems[0].contains("does not match the manifest"));
    assert!(r.problems[1].contains("No such file"));
    assert!(r.warnings.iter().any(|w| w.contains("interrupted write")));
}

#[test]
fn write_new_never_replaces_a_file() {
    let dir = tempdir();
    let p = dir.path().join("frame.png");
    session::write_new(&p, b"first").unwrap();
    let e = session::write_new(&p, b"second").unwrap_err().to_string();
    assert!(e.contains("placing"), "{e}");
    assert_eq!(std::fs::read(&p).unwrap(), b"first");
    assert_eq!(
        std::fs::read_dir(dir.path()).unwrap().count(),
        1,
        "no temporary file left behind"
    );
}

#[test]
fn plan_estimate_and_check() {
    let dir = tempdir();
    let rig = load(dir.path(), &small_table());
    let plan = capture::Plan::for_rig(&rig.rig);
    assert_eq!(plan.frames(), 15);
    let limits = capture::Limits {
        min_exposure_us: 50,
        max_exposure_us: 1_000_000,
    };
    assert!(plan.check(&limits).is_empty());
    let e = plan.estimate(&rig.rig);
    assert_eq!(e.frames_kept, 15);
    assert_eq!(e.bytes_max, 15 * 160 * 120 * 3);
    // 15 frames at >= 1/30 s, plus settling, plus no warm-up.
    assert!(e.seconds > 15.0 / 30.0 && e.seconds < 10.0, "{}", e.seconds);
    let narrow = capture::Limits {
        min_exposure_us: 200,
        max_exposure_us: 4000,
    };
    let p = plan.check(&narrow);
    assert!(
        p.iter()
            .any(|s| s.contains("exposure 125 µs): outside the camera's 200..4000 µs")),
        "{p:?}"
    );
    let mut bad = plan.clone();
    bad.steps.retain(|s| !matches!(s, capture::Step::LampOff));
    assert!(bad
        .check(&limits)
        .iter()
        .any(|s| s.contains("the lamp is on but dark frames need it off")));
}

#[test]
fn the_simulated_lab_is_deterministic_for_a_seed() {
    let sums = |seed: i64| {
        let dir = tempdir();
        let mut t = small_table();
        set(&mut t, "mock.seed", seed);
        let rec = record(dir.path(), &t).unwrap();
        rec.manifest
            .frames
            .iter()
            .map(|f| f.sha256.clone())
            .collect::<Vec<_>>()
    };
    let a = sums(5);
    assert_eq!(a, sums(5), "same seed, same frames, byte for byte");
    let b = sums(6);
    assert_eq!(a.len(), b.len());
    assert!(
        a.iter().zip(&b).all(|(x, y)| x != y),
        "another seed, other noise"
    );
}
