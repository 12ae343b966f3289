//! `glint fit` end to end: files, the table and JSON, and its errors.

use super::fit_pipeline::pipeline;
use super::util::{err, glint, ok, record, shared_data, small_table, tempdir};

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
    // Every angle the models take is in the file, and they agree: with h = (l + v) / |l + v|,
    // v.h = sqrt((1 + l.v) / 2) and n.h = (n.l + n.v) / (2 v.h).
    let head: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    let at = |name: &str| head.iter().position(|h| *h == name).unwrap();
    let (cl, cv, nh, vh) = (at("cos_l"), at("cos_v"), at("n_dot_h"), at("v_dot_h"));
    for line in csv.lines().skip(1) {
        let f: Vec<f64> = line
            .split(',')
            .map(|x| x.parse().unwrap_or(f64::NAN))
            .collect();
        assert!(
            (f[nh] - (f[cl] + f[cv]) / (2.0 * f[vh])).abs() < 1e-6,
            "{line}"
        );
        assert!(
            f[vh] > 0.0 && f[vh] <= 1.0 && f[cv] > 0.0 && f[cv] <= 1.0,
            "{line}"
        );
    }
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

/// `fit-photometric --out FILE` never replaces a file, and never follows a link there
/// (today a dangling link passed the exists check and std::fs::write created its target).
#[test]
fn fit_photometric_out_never_replaces_a_file_or_follows_a_link() {
    let Some(data) = shared_data("diligent_ballPNG_subset") else {
        return;
    };
    let dir = tempdir();
    let run = |out: &std::path::Path| {
        glint(&[
            "fit-photometric",
            data.to_str().unwrap(),
            "--model",
            "lambert",
            "--stride",
            "16",
            "--out",
            out.to_str().unwrap(),
        ])
    };
    let mine = dir.path().join("mine.json");
    std::fs::write(&mine, b"the user's notes").unwrap();
    let e = err(&run(&mine));
    assert!(e.contains("exists"), "{e}");
    assert_eq!(std::fs::read(&mine).unwrap(), b"the user's notes");
    let link = dir.path().join("link.json");
    let target = dir.path().join("target.json");
    std::os::unix::fs::symlink(&target, &link).unwrap();
    let e = err(&run(&link));
    assert!(e.contains("exists"), "{e}");
    assert!(!target.exists(), "nothing written through the link");
    let new = dir.path().join("new.json");
    ok(&run(&new));
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&new).unwrap()).unwrap();
    assert_eq!(v["format"], "glint-fit-photometric");
}

/// A photometric data set is files Glint reads: a photo numbered 000 (today a panic on
/// `index - 1`), a zero or NaN light, a line of a megabyte, and a decompression bomb as
/// mask.png are each one line naming the file.
#[test]
fn fit_photometric_refuses_hostile_data_sets_with_one_line() {
    let set = |dirs: &str, ints: &str, photo: &str| {
        let d = tempdir();
        std::fs::create_dir(d.path().join("images")).unwrap();
        image::ImageBuffer::<image::Rgb<u16>, Vec<u16>>::from_pixel(8, 8, image::Rgb([1000; 3]))
            .save(d.path().join("images").join(photo))
            .unwrap();
        image::GrayImage::from_pixel(8, 8, image::Luma([255]))
            .save(d.path().join("mask.png"))
            .unwrap();
        std::fs::write(d.path().join("light_directions.txt"), dirs).unwrap();
        std::fs::write(d.path().join("light_intensities.txt"), ints).unwrap();
        d
    };
    let run = |d: &tempfile::TempDir| err(&glint(&["fit-photometric", d.path().to_str().unwrap()]));
    let d = set("0 0 1\n", "1 1 1\n", "000.png");
    let e = run(&d);
    assert!(
        e.contains("000.png") && e.contains("numbered from 001"),
        "{e}"
    );
    let d = set("0 0 1\n", "1 0 1\n", "001.png");
    let e = run(&d);
    assert!(
        e.contains("light_intensities.txt") && e.contains("line 1"),
        "{e}"
    );
    let d = set("0 NaN 1\n", "1 1 1\n", "001.png");
    let e = run(&d);
    assert!(
        e.contains("light_directions.txt") && e.contains("finite"),
        "{e}"
    );
    let d = set("0 0 0\n", "1 1 1\n", "001.png");
    let e = run(&d);
    assert!(e.contains("light direction is zero"), "{e}");
    let d = set(
        &format!("0 0 {}\n", "9".repeat(1 << 20)),
        "1 1 1\n",
        "001.png",
    );
    let e = run(&d);
    assert!(e.len() < 400 && e.contains("light_directions.txt"), "{e}");
    // mask.png claiming 20000x20000 (a PNG header and no pixels).
    let d = set("0 0 1\n", "1 1 1\n", "001.png");
    let mut png = b"\x89PNG\r\n\x1a\n\0\0\0\x0dIHDR".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&20000u32.to_be_bytes());
    ihdr.extend_from_slice(&20000u32.to_be_bytes());
    ihdr.extend_from_slice(&[8, 0, 0, 0, 0]);
    png.extend_from_slice(&ihdr);
    let mut crc_in = b"IHDR".to_vec();
    crc_in.extend_from_slice(&ihdr);
    png.extend_from_slice(&crc32(&crc_in).to_be_bytes());
    for kind in [b"IDAT", b"IEND"] {
        png.extend_from_slice(&[0; 4]);
        png.extend_from_slice(kind);
        png.extend_from_slice(&crc32(kind).to_be_bytes());
    }
    std::fs::write(d.path().join("mask.png"), &png).unwrap();
    let e = run(&d);
    assert!(e.contains("mask.png") && e.contains("20000x20000"), "{e}");
}

fn crc32(data: &[u8]) -> u32 {
    let mut c = !0u32;
    for b in data {
        c ^= *b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}
