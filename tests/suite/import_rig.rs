//! Photos from a camera Glint does not drive, with a processing rig: `glint import DIR
//! --times FILE --rig RIG [--grid PHOTO] [--dark PHOTO]` and then every stage (hdr,
//! calibrate, fit, validate, report) as on a captured session. The photos are the simulated
//! lab's, written out as a foreign camera would (16-bit TIFF; 8-bit JPEG with EXIF), so
//! the truth is known and the captured session's own results are the reference.

use std::path::Path;

use glint::capture::FrameKind;

use super::util::{err, glint, ok, record, set, small_table, tempdir};

/// A mock rig table at `size`, a Blinn-Phong tile of n = 120.
pub(super) fn table(size: [i64; 2], bits: i64, seed: i64) -> toml::Table {
    let mut t = small_table();
    let f = 1500.0 * size[0] as f64 / 1280.0;
    set(&mut t, "camera.width", size[0]);
    set(&mut t, "camera.height", size[1]);
    set(&mut t, "camera.bit_depth", bits);
    set(&mut t, "mock.camera.fx", f);
    set(&mut t, "mock.camera.fy", f);
    set(&mut t, "mock.seed", seed);
    set(&mut t, "mock.tile.model", "blinn-phong");
    set(&mut t, "mock.tile.n", 120.0);
    set(
        &mut t,
        "mock.tile.ks",
        toml::Value::Array(vec![0.3.into(); 3]),
    );
    t
}

/// A processing rig with `t`'s geometry: external camera and lamp, nothing else.
pub(super) fn processing_rig(path: &Path, t: &toml::Table) {
    let g = toml::to_string(&t["geometry"]).unwrap();
    std::fs::write(
        path,
        format!(
            "[rig]\nname = \"bench-dslr\"\n\n[camera]\nbackend = \"external\"\n\n[lamp]\nbackend = \"external\"\n\n[geometry]\n{g}"
        ),
    )
    .unwrap();
}

/// `glint import PHOTOS --times TIMES --rig RIG --out OUT`.
pub(super) fn import_with_rig(
    photos: &Path,
    times: &Path,
    rig: &Path,
    out: &Path,
) -> std::process::Output {
    glint(&[
        "import",
        s(photos),
        "--times",
        s(times),
        "--rig",
        s(rig),
        "--out",
        s(out),
    ])
}

pub(super) fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// hdr, calibrate, fit (JSON), validate, report on a session; the fit's JSON.
pub(super) fn chain(session: &Path) -> serde_json::Value {
    ok(&glint(&["hdr", s(session)]));
    ok(&glint(&["calibrate", s(session)]));
    let fit = ok(&glint(&["fit", s(session), "--json"]));
    ok(&glint(&["validate", s(session)]));
    ok(&glint(&["report", s(session)]));
    assert!(session.join("report/index.html").is_file());
    serde_json::from_str(&fit).unwrap()
}

/// The chosen model's n (value, 95% interval).
pub(super) fn chosen_n(fit: &serde_json::Value) -> (String, f64, [f64; 2]) {
    let chosen = fit["chosen"].as_str().unwrap().to_string();
    let c = fit["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["model"] == chosen.as_str())
        .unwrap();
    let n = &c["n"];
    (
        chosen,
        n["value"].as_f64().unwrap(),
        [
            n["ci95"][0].as_f64().unwrap(),
            n["ci95"][1].as_f64().unwrap(),
        ],
    )
}

/// A 16-bit TIFF bracket, dark and grid photos with a times file naming their kinds, a
/// processing rig: one `glint import` and the session runs every stage, to the same
/// result as the captured session it was written from.
#[test]
fn a_foreign_16_bit_tiff_session_runs_every_stage_with_a_processing_rig() {
    let dir = tempdir();
    let t = table([320, 240], 16, 7);
    let rec = record(dir.path(), &t).unwrap();
    let captured = dir.path().join("s");
    let photos = dir.path().join("tiff");
    std::fs::create_dir_all(&photos).unwrap();
    let mut times = String::from("# name  seconds  kind\n");
    for f in &rec.manifest.frames {
        let img = image::open(captured.join(&f.file)).unwrap();
        let name = format!("IMG_{:04}.tif", 100 + f.index);
        img.save(photos.join(&name)).unwrap();
        times.push_str(&format!(
            "{name} {} {}\n",
            f.exposure_us() * 1e-6,
            f.kind.as_str()
        ));
    }
    let tf = dir.path().join("times.txt");
    std::fs::write(&tf, times).unwrap();
    let rig = dir.path().join("processing.toml");
    processing_rig(&rig, &t);
    let check = ok(&glint(&["rig", "check", s(&rig)]));
    assert!(check.contains("processing rig"), "{check}");

    let out = dir.path().join("imported");
    let said = ok(&import_with_rig(&photos, &tf, &rig, &out));
    assert!(said.contains("glint calibrate"), "{said}");
    let m = glint::session::load(&out).unwrap();
    let kinds = |k: FrameKind| m.frames.iter().filter(|f| f.kind == k).count();
    let own = |k: FrameKind| rec.manifest.frames.iter().filter(|f| f.kind == k).count();
    for k in [FrameKind::Tile, FrameKind::Dark, FrameKind::Grid] {
        assert_eq!(kinds(k), own(k), "{k:?}");
    }
    let r = m.rig.as_ref().unwrap();
    assert_eq!(
        (r.camera.width, r.camera.height, r.camera.bit_depth),
        (320, 240, 16)
    );
    assert_eq!(r.bracket.exposures_us.len(), own(FrameKind::Tile));
    assert!(out.join("rig.toml").is_file());
    ok(&glint(&["session", "verify", s(&out)]));

    let imported = chain(&out);
    // The processing rig stores the camera's response profile beside it.
    ok(&glint(&["hdr", s(&out), "--rig", s(&rig)]));
    assert!(dir.path().join("profiles").is_dir());
    let reference = chain(&captured);
    let (mi, ni, ci) = chosen_n(&imported);
    let (mr, nr, _) = chosen_n(&reference);
    println!("imported: {mi} n {ni:.3} {ci:?}; captured: {mr} n {nr:.3}; truth blinn-phong 120");
    assert_eq!(mi, "blinn-phong");
    assert_eq!(mr, mi);
    // The same pixels and times: the same numbers.
    assert!((ni / nr - 1.0).abs() < 1e-6, "{ni} vs {nr}");
    assert!((ni / 120.0 - 1.0).abs() < 0.05, "{ni}");
    let cam: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("calib/camera.json")).unwrap())
            .unwrap();
    let cam_ref: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(captured.join("calib/camera.json")).unwrap())
            .unwrap();
    assert_eq!(cam["camera_matrix"], cam_ref["camera_matrix"]);
}

/// A JPEG whose EXIF says exposure `num/den` s, f-number `f` and ISO `iso`.
fn jpeg_with_exif(path: &Path, img: &image::RgbImage, t: (u32, u32), f: (u32, u32), iso: u32) {
    let mut jpeg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 95)
        .encode_image(img)
        .unwrap();
    let fields = [
        exif::Field {
            tag: exif::Tag::ExposureTime,
            ifd_num: exif::In::PRIMARY,
            value: exif::Value::Rational(vec![exif::Rational {
                num: t.0,
                denom: t.1,
            }]),
        },
        exif::Field {
            tag: exif::Tag::FNumber,
            ifd_num: exif::In::PRIMARY,
            value: exif::Value::Rational(vec![exif::Rational {
                num: f.0,
                denom: f.1,
            }]),
        },
        exif::Field {
            tag: exif::Tag::PhotographicSensitivity,
            ifd_num: exif::In::PRIMARY,
            value: exif::Value::Short(vec![iso as u16]),
        },
        exif::Field {
            tag: exif::Tag::Make,
            ifd_num: exif::In::PRIMARY,
            value: exif::Value::Ascii(vec![b"NIKON CORPORATION".to_vec()]),
        },
        exif::Field {
            tag: exif::Tag::Model,
            ifd_num: exif::In::PRIMARY,
            value: exif::Value::Ascii(vec![b"NIKON D850".to_vec()]),
        },
    ];
    let mut w = exif::experimental::Writer::new();
    for field in &fields {
        w.push_field(field);
    }
    let mut tiff = std::io::Cursor::new(Vec::new());
    w.write(&mut tiff, false).unwrap();
    let mut app1 = b"Exif\0\0".to_vec();
    app1.extend_from_slice(&tiff.into_inner());
    let len = (app1.len() + 2) as u16;
    let mut out = jpeg[..2].to_vec(); // SOI
    out.extend_from_slice(&[0xff, 0xe1]);
    out.extend_from_slice(&len.to_be_bytes());
    out.extend_from_slice(&app1);
    out.extend_from_slice(&jpeg[2..]);
    std::fs::write(path, out).unwrap();
}

/// A folder of EXIF-carrying JPEGs (as a DSLR tethered with gphoto2 writes them; the
/// times exact fractions of a second), the grid and dark photos given by flag and no times
/// file: the session runs every stage and finds the tile's model. A bracket whose ISO
/// changes is imported with a warning naming the photos.
#[test]
fn an_exif_jpeg_set_with_grid_and_dark_flags_runs_every_stage() {
    let dir = tempdir();
    let mut t = table([320, 240], 8, 11);
    // Exposures a camera offers: powers of two of a second.
    let ex: Vec<i64> = (0..7).map(|k| 1_000_000 / 8192 * (1 << k)).collect();
    set(
        &mut t,
        "bracket.exposures_us",
        toml::Value::Array(ex.iter().map(|&e| e.into()).collect()),
    );
    let rec = record(dir.path(), &t).unwrap();
    let captured = dir.path().join("s");
    let photos = dir.path().join("DCIM");
    std::fs::create_dir_all(&photos).unwrap();
    let (mut grid, mut dark) = (Vec::new(), Vec::new());
    for f in &rec.manifest.frames {
        let img = image::open(captured.join(&f.file)).unwrap().to_rgb8();
        let name = format!("DSC_{:04}.JPG", 200 + f.index);
        // The time as the camera writes it: 1/N s.
        let den = (1e6 / f.exposure_us()).round() as u32;
        assert!((1e6 / den as f64 / f.exposure_us() - 1.0).abs() < 0.01);
        jpeg_with_exif(&photos.join(&name), &img, (1, den), (56, 10), 100);
        match f.kind {
            FrameKind::Grid => grid.push(name),
            FrameKind::Dark => dark.push(name),
            FrameKind::Tile => {}
        }
    }
    let rig = dir.path().join("processing.toml");
    processing_rig(&rig, &t);
    let out = dir.path().join("imported");
    let args_for = |out: &Path| {
        let mut args = vec![
            "import".to_string(),
            s(&photos).into(),
            "--rig".into(),
            s(&rig).into(),
            "--out".into(),
            s(out).into(),
        ];
        for g in &grid {
            args.extend(["--grid".into(), g.clone()]);
        }
        for d in &dark {
            args.extend(["--dark".into(), photos.join(d).to_str().unwrap().into()]);
        }
        args
    };
    let args = args_for(&out);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let o = glint(&args);
    let said = ok(&o);
    assert!(said.contains("With 1 grid and 7 dark"), "{said}");
    assert!(String::from_utf8_lossy(&o.stderr).trim().is_empty());
    let m = glint::session::load(&out).unwrap();
    assert!(m
        .frames
        .iter()
        .all(|f| f.f_number == Some(5.6) && f.iso == Some(100)));
    // The camera named from EXIF: its profiles are that camera's.
    assert_eq!(
        m.camera.as_ref().unwrap().model,
        "NIKON CORPORATION NIKON D850"
    );
    let fit = chain(&out);
    let (model, n, ci) = chosen_n(&fit);
    println!("JPEG import: {model} n {n:.2} {ci:?} (truth blinn-phong 120)");
    assert_eq!(model, "blinn-phong");
    assert!((n / 120.0 - 1.0).abs() < 0.15, "{n}");

    // One photo at another ISO: imported, with a warning that names it.
    let tile = rec
        .manifest
        .frames
        .iter()
        .find(|f| f.kind == FrameKind::Tile && f.index == 3)
        .unwrap();
    let img = image::open(captured.join(&tile.file)).unwrap().to_rgb8();
    let den = (1e6 / tile.exposure_us()).round() as u32;
    jpeg_with_exif(&photos.join("DSC_0203.JPG"), &img, (1, den), (56, 10), 400);
    let again = dir.path().join("again");
    let args = args_for(&again);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let o = glint(&args);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{e}");
    assert!(
        e.contains("warning: the ISO (EXIF PhotographicSensitivity) changes within the bracket")
            && e.contains("ISO 400"),
        "{e}"
    );
}

/// What a processing rig and the import's new flags refuse, each in one line naming the
/// fix, with nothing written.
#[test]
fn processing_rigs_and_grid_photos_are_refused_where_they_cannot_work() {
    let dir = tempdir();
    let t = table([160, 120], 8, 3);
    let rec = record(dir.path(), &t).unwrap();
    let captured = dir.path().join("s");
    let photos = dir.path().join("p");
    std::fs::create_dir_all(&photos).unwrap();
    let mut times = String::new();
    for f in &rec.manifest.frames {
        let name = format!("{:02}.png", f.index);
        std::fs::copy(captured.join(&f.file), photos.join(&name)).unwrap();
        times.push_str(&format!(
            "{name} {} {}\n",
            f.exposure_us() * 1e-6,
            f.kind.as_str()
        ));
    }
    let tf = dir.path().join("times.txt");
    std::fs::write(&tf, &times).unwrap();
    let rig = dir.path().join("processing.toml");
    processing_rig(&rig, &t);
    let out = dir.path().join("out");
    let fails = |args: &[&str], want: &str| {
        let e = err(&glint(args));
        assert!(e.contains(want), "{e}\nshould contain: {want}");
        assert_eq!(e.trim().lines().count(), 1, "{e}");
        assert!(!out.exists(), "nothing is written");
    };
    let (p, tfs, rigs, outs) = (s(&photos), s(&tf), s(&rig), s(&out));
    // A grid photo without a rig: nothing to place it in.
    fails(
        &["import", p, "--times", tfs, "--out", outs],
        "give the rig too (--rig RIG",
    );
    // A rig whose camera is not the photos'.
    let wrong = dir.path().join("wrong.toml");
    std::fs::write(
        &wrong,
        std::fs::read_to_string(&rig).unwrap().replace(
            "backend = \"external\"\n\n[lamp]",
            "backend = \"external\"\nwidth = 640\nheight = 480\n\n[lamp]",
        ),
    )
    .unwrap();
    fails(
        &[
            "import",
            p,
            "--times",
            tfs,
            "--rig",
            s(&wrong),
            "--out",
            outs,
        ],
        "has a 640x480 camera but the photos are 160x120",
    );
    // A kind the times file does not know, and one that contradicts a flag.
    let tf2 = dir.path().join("times2.txt");
    std::fs::write(&tf2, times.replace(" grid", " chessboard")).unwrap();
    fails(
        &[
            "import",
            p,
            "--times",
            s(&tf2),
            "--rig",
            rigs,
            "--out",
            outs,
        ],
        "is not a kind of photo; write tile",
    );
    let grid_name = rec
        .manifest
        .frames
        .iter()
        .find(|f| f.kind == FrameKind::Grid)
        .map(|f| format!("{:02}.png", f.index))
        .unwrap();
    fails(
        &[
            "import", p, "--times", tfs, "--rig", rigs, "--dark", &grid_name, "--out", outs,
        ],
        "is given as a dark photo but the times file lists it as grid",
    );
    // A grid photo of another size.
    image::RgbImage::new(80, 60)
        .save(photos.join("small.png"))
        .unwrap();
    let tf3 = dir.path().join("times3.txt");
    let mut t3: String = times
        .lines()
        .filter(|l| !l.ends_with(" grid"))
        .map(|l| format!("{l}\n"))
        .collect();
    t3.push_str("small.png 1/250 grid\n");
    std::fs::write(&tf3, t3).unwrap();
    fails(
        &[
            "import",
            p,
            "--times",
            s(&tf3),
            "--rig",
            rigs,
            "--out",
            outs,
        ],
        "must have one size",
    );
    // A grid photo given by flag, outside the folder and without EXIF: where its time goes.
    let outside = dir.path().join("board.png");
    std::fs::copy(photos.join(&grid_name), &outside).unwrap();
    let no_grid: String = times
        .lines()
        .filter(|l| !l.ends_with(" grid"))
        .map(|l| format!("{l}\n"))
        .collect();
    std::fs::write(&tf3, no_grid).unwrap();
    fails(
        &[
            "import",
            p,
            "--times",
            s(&tf3),
            "--rig",
            rigs,
            "--grid",
            s(&outside),
            "--out",
            outs,
        ],
        "no EXIF exposure time; put it in",
    );
    // A processing rig cannot capture, not even in a dry run or a lens plan.
    for args in [
        vec!["capture", "--rig", rigs, "--out", outs],
        vec!["capture", "--rig", rigs, "--dry-run"],
        vec!["lens", "--rig", rigs, "--dry-run"],
        vec!["run", "--rig", rigs, "--out", outs],
    ] {
        let e = err(&glint(&args));
        assert!(
            e.contains("Glint does not drive this camera"),
            "{args:?}: {e}"
        );
        assert_eq!(e.trim().lines().count(), 1, "{e}");
    }
    // Its exposure range may be left out, but not given reversed.
    let reversed = dir.path().join("reversed.toml");
    std::fs::write(
        &reversed,
        std::fs::read_to_string(&rig).unwrap().replace(
            "backend = \"external\"\n\n[lamp]",
            "backend = \"external\"\nmin_exposure_us = 100\n\n[lamp]",
        ),
    )
    .unwrap();
    let o = glint(&["rig", "check", s(&reversed)]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stdout).contains("camera.min_exposure_us"));
    // One photo given as both grid and dark.
    fails(
        &[
            "import", p, "--rig", rigs, "--grid", &grid_name, "--dark", &grid_name, "--out", outs,
        ],
        "given both as a grid photo and as a dark photo",
    );
    // The rig the photos were captured with (not a processing rig), without a grid photo:
    // imported, its own grid exposure kept.
    let no_grid: String = times
        .lines()
        .filter(|l| !l.ends_with(" grid"))
        .map(|l| format!("{l}\n"))
        .collect();
    std::fs::write(&tf3, no_grid).unwrap();
    let own = dir.path().join("rig.toml");
    ok(&glint(&[
        "import",
        p,
        "--times",
        s(&tf3),
        "--rig",
        s(&own),
        "--out",
        outs,
    ]));
    let m = glint::session::load(&out).unwrap();
    assert_eq!(
        m.rig.unwrap().bracket.grid_exposure_us,
        rec.manifest.rig.as_ref().unwrap().bracket.grid_exposure_us
    );
    // A rig for a camera Glint drives still needs what capture uses.
    let v4l2 = dir.path().join("v4l2.toml");
    std::fs::write(
        &v4l2,
        std::fs::read_to_string(&rig).unwrap().replacen(
            "backend = \"external\"",
            "backend = \"v4l2\"\ndevice = \"/dev/video0\"\npixel_format = \"YUYV\"",
            1,
        ),
    )
    .unwrap();
    let o = glint(&["rig", "check", s(&v4l2)]);
    assert!(!o.status.success());
    let said = String::from_utf8_lossy(&o.stdout);
    for key in [
        "camera.width: missing",
        "camera.min_exposure_us: missing",
        "bracket: missing",
    ] {
        assert!(said.contains(key), "{said}");
    }
}

/// A monochrome camera's photos (grey 16-bit TIFF) stay one channel: the session is a
/// monochrome one (as captured with `pixel_format = "Y16"`), its processing rig's camera
/// made grey from the photos, and every stage runs to the same numbers as the captured
/// session. Grey and colour photos together are refused.
#[test]
fn grey_photos_import_as_a_monochrome_session() {
    let dir = tempdir();
    let mut t = table([320, 240], 16, 5);
    set(&mut t, "camera.pixel_format", "Y16");
    let rec = record(dir.path(), &t).unwrap();
    let captured = dir.path().join("s");
    let photos = dir.path().join("mono");
    std::fs::create_dir_all(&photos).unwrap();
    let mut times = String::new();
    for f in &rec.manifest.frames {
        let img = image::open(captured.join(&f.file)).unwrap();
        assert!(matches!(img, image::DynamicImage::ImageLuma16(_)));
        let name = format!("m{:02}.tif", f.index);
        img.save(photos.join(&name)).unwrap();
        times.push_str(&format!(
            "{name} {} {}\n",
            f.exposure_us() * 1e-6,
            f.kind.as_str()
        ));
    }
    let tf = dir.path().join("times.txt");
    std::fs::write(&tf, &times).unwrap();
    let rig = dir.path().join("processing.toml");
    processing_rig(&rig, &t);
    let out = dir.path().join("imported");
    ok(&import_with_rig(&photos, &tf, &rig, &out));
    let m = glint::session::load(&out).unwrap();
    assert_eq!(m.channels(), 1);
    assert_eq!(
        m.rig.as_ref().unwrap().camera.pixel_format,
        Some(glint::rig::PixelFormat::Y16)
    );
    let imported = chain(&out);
    let reference = chain(&captured);
    let (mi, ni, _) = chosen_n(&imported);
    let (mr, nr, _) = chosen_n(&reference);
    println!("mono import: {mi} n {ni:.3}; captured: {mr} n {nr:.3}");
    assert_eq!((mi.as_str(), mr.as_str()), ("blinn-phong", "blinn-phong"));
    assert!((ni / nr - 1.0).abs() < 1e-6, "{ni} vs {nr}");

    // One colour photo among grey ones.
    let first = times.lines().next().unwrap().split(' ').next().unwrap();
    image::open(photos.join(first))
        .unwrap()
        .to_rgb16()
        .save(photos.join(first))
        .unwrap();
    let e = err(&glint(&[
        "import",
        s(&photos),
        "--times",
        s(&tf),
        "--rig",
        s(&rig),
        "--out",
        s(&dir.path().join("mixed")),
    ]));
    assert!(e.contains("is grey but") || e.contains("is colour"), "{e}");
}

/// A textured scene's relative radiance at (x, y), 0.02 .. 1: a gradient with a
/// deterministic speckle (a hash of the position), so that a JPEG of it has a long
/// entropy-coded scan and every pixel its own value.
fn radiance(x: u32, y: u32, w: u32, h: u32) -> f64 {
    let mut k = (x as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15)
        ^ (y as u64).wrapping_mul(0xc2b2_ae3d_27d4_eb4f);
    k ^= k >> 29;
    k = k.wrapping_mul(0xbf58_476d_1ce4_e5b9);
    k ^= k >> 32;
    let speckle = (k % 1000) as f64 / 1000.0;
    0.02 + 0.6 * (x as f64 / w as f64) * (0.5 + 0.5 * y as f64 / h as f64) + 0.3 * speckle
}

/// The scene photographed at `scale` (times its radiance), values clipped at full scale,
/// written as `path` in the format its extension names: `bits` 8 or 16, `grey` one channel.
fn scene_photo(path: &Path, scale: f64, bits: u8, grey: bool) {
    let (w, h) = (160, 120);
    let v = |x, y| (radiance(x, y, w, h) * scale).min(1.0);
    match (bits, grey) {
        (8, false) => image::RgbImage::from_fn(w, h, |x, y| {
            let a = (v(x, y) * 255.0).round() as u8;
            image::Rgb([a, a.saturating_sub(10), a / 2 + 20])
        })
        .save(path),
        (8, true) => {
            image::GrayImage::from_fn(w, h, |x, y| image::Luma([(v(x, y) * 255.0).round() as u8]))
                .save(path)
        }
        (_, false) => image::ImageBuffer::<image::Rgb<u16>, Vec<u16>>::from_fn(w, h, |x, y| {
            let a = (v(x, y) * 65535.0).round() as u16;
            image::Rgb([a, a / 2, a.saturating_sub(900)])
        })
        .save(path),
        (_, true) => image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(w, h, |x, y| {
            image::Luma([(v(x, y) * 65535.0).round() as u16])
        })
        .save(path),
    }
    .unwrap();
}

/// `glint import DIR --times FILE --out OUT` of photos `names` at `times` (seconds, as
/// written in the times file).
fn import_times(dir: &Path, photos: &Path, lines: &[(String, &str)]) -> std::process::Output {
    let tf = dir.join("times.txt");
    let text: String = lines.iter().map(|(n, t)| format!("{n} {t}\n")).collect();
    std::fs::write(&tf, text).unwrap();
    glint(&[
        "import",
        s(photos),
        "--times",
        s(&tf),
        "--out",
        s(&dir.join("out")),
    ])
}

/// A photo cut to half its length is refused in every format `glint import` reads, naming
/// it, with nothing written. Before, a JPEG so cut imported with exit 0 (the image crate
/// runs its JPEG decoder leniently: the missing rows decode grey, 128) and `glint hdr`
/// merged it.
#[test]
fn a_photo_cut_to_half_its_length_is_refused_in_every_format() {
    for (ext, bits, grey) in [
        ("jpg", 8, false),
        ("jpg", 8, true),
        ("png", 8, false),
        ("png", 16, false),
        ("tif", 8, false),
        ("tif", 16, false),
        ("tif", 16, true),
    ] {
        let dir = tempdir();
        let photos = dir.path().join("photos");
        std::fs::create_dir_all(&photos).unwrap();
        let mut lines = Vec::new();
        for (i, t) in ["1/250", "1/125", "1/60"].into_iter().enumerate() {
            let name = format!("p{i}.{ext}");
            scene_photo(&photos.join(&name), 0.5 * 2f64.powi(i as i32), bits, grey);
            lines.push((name, t));
        }
        let cut = photos.join(format!("p1.{ext}"));
        let bytes = std::fs::read(&cut).unwrap();
        let half = &bytes[..bytes.len() / 2];
        if ext == "jpg" {
            // The lenient decoder takes it, and fills the rows it lacks with grey.
            let img = image::load_from_memory(half).expect("the image crate decodes it");
            assert_eq!(img.to_luma8().get_pixel(80, 119).0, [128], "{bits} {grey}");
        }
        assert!(
            glint::hdr::decode(half, "p1").is_err(),
            "{ext} {bits} {grey}"
        );
        std::fs::write(&cut, half).unwrap();
        let o = import_times(dir.path(), &photos, &lines);
        let e = err(&o);
        println!("{ext} {bits}-bit{}: {e}", if grey { " grey" } else { "" });
        assert!(
            e.contains(&format!("p1.{ext}")) && e.contains("cannot decode"),
            "{ext} {bits} {grey}: {e}"
        );
        if ext == "jpg" {
            assert!(e.contains("cut short (truncated)"), "{e}");
        }
        assert!(!dir.path().join("out").exists(), "nothing is written");
    }
}

/// Seven copies of one photo at seven exposure times are refused, naming the first two
/// photos that do not differ; before, they imported and merged. So is a bracket of small
/// steps (each under half a stop, too close to compare one by one) whose ends do not
/// differ. The same scene photographed as the times say imports, and so does a bracket of
/// black photos (nothing to tell from).
#[test]
fn copies_of_one_photo_at_seven_times_are_refused_naming_two() {
    let times = [
        "0.001", "0.002", "0.004", "0.008", "0.016", "0.032", "0.064",
    ];
    for (ext, bits) in [("png", 8), ("jpg", 8), ("tif", 16)] {
        let dir = tempdir();
        let photos = dir.path().join("photos");
        std::fs::create_dir_all(&photos).unwrap();
        scene_photo(&photos.join(format!("p0.{ext}")), 0.6, bits, false);
        let mut lines = vec![(format!("p0.{ext}"), times[0])];
        for (i, t) in times.iter().enumerate().skip(1) {
            let name = format!("p{i}.{ext}");
            std::fs::copy(photos.join(format!("p0.{ext}")), photos.join(&name)).unwrap();
            lines.push((name, *t));
        }
        let e = err(&import_times(dir.path(), &photos, &lines));
        println!("{e}");
        assert!(
            e.contains(&format!(
                "p1.{ext} (0.002 s) is no brighter than p0.{ext} (0.001 s)"
            )) && e.contains("do not change with their exposure times"),
            "{e}"
        );
        assert!(!dir.path().join("out").exists(), "nothing is written");
    }
    // Small steps: 7% longer each (a tenth of a stop), 1.5x from end to end.
    let dir = tempdir();
    let photos = dir.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    scene_photo(&photos.join("p0.png"), 0.6, 8, false);
    let small: Vec<String> = (0..7)
        .map(|i| format!("{:.6}", 0.01 * 1.07f64.powi(i)))
        .collect();
    let mut lines = vec![("p0.png".to_string(), small[0].as_str())];
    for (i, t) in small.iter().enumerate().skip(1) {
        let name = format!("p{i}.png");
        std::fs::copy(photos.join("p0.png"), photos.join(&name)).unwrap();
        lines.push((name, t.as_str()));
    }
    let e = err(&import_times(dir.path(), &photos, &lines));
    assert!(
        e.contains("p6.png (0.015007 s) is no brighter than p0.png (0.01 s)"),
        "{e}"
    );
    // The scene as the times say: values in proportion to the time (clipped).
    let dir = tempdir();
    let photos = dir.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    let mut lines = Vec::new();
    for (i, t) in times.iter().enumerate() {
        let name = format!("p{i}.jpg");
        scene_photo(&photos.join(&name), 0.05 * 2f64.powi(i as i32), 8, false);
        lines.push((name, *t));
    }
    ok(&import_times(dir.path(), &photos, &lines));
    // Black photos: nothing compared, nothing refused.
    let dir = tempdir();
    let photos = dir.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    let mut lines = Vec::new();
    for (i, t) in times.iter().enumerate() {
        let name = format!("p{i}.png");
        image::RgbImage::new(32, 24)
            .save(photos.join(&name))
            .unwrap();
        lines.push((name, *t));
    }
    ok(&import_times(dir.path(), &photos, &lines));
}

/// A folder whose photos would make a session every stage refuses (more than 100 dark photos
/// at one time: the bound a manifest without a plan is held to) is refused at import, naming
/// the count and the limit, with nothing written. Before, the import succeeded and `glint
/// hdr` then refused the session.
#[test]
fn an_import_beyond_the_bounds_a_manifest_is_held_to_is_refused() {
    let dir = tempdir();
    let photos = dir.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    let times = ["0.001", "0.002", "0.004"];
    let mut lines = Vec::new();
    for (i, t) in times.iter().enumerate() {
        let name = format!("p{i}.png");
        scene_photo(&photos.join(&name), 0.1 * 2f64.powi(i as i32), 8, false);
        lines.push((name, *t));
    }
    image::RgbImage::new(160, 120)
        .save(photos.join("d0.png"))
        .unwrap();
    for i in 1..=100 {
        std::fs::hard_link(photos.join("d0.png"), photos.join(format!("d{i}.png"))).unwrap();
    }
    let tf = dir.path().join("times.txt");
    let mut text: String = lines.iter().map(|(n, t)| format!("{n} {t}\n")).collect();
    for i in 0..=100 {
        text.push_str(&format!("d{i}.png 0.004 dark\n"));
    }
    std::fs::write(&tf, text).unwrap();
    let out = glint(&[
        "import",
        s(&photos),
        "--times",
        s(&tf),
        "--out",
        s(&dir.path().join("out")),
    ]);
    let e = err(&out);
    assert!(
        e.contains("101 dark frames at 4000 µs") && e.contains("at most 100"),
        "{e}"
    );
    assert!(!dir.path().join("out").exists(), "nothing is written");
}
