//! `glint calibrate` end to end: a mock capture's grid photo against the mock's truth, and
//! the --images mode's errors.

use super::util::{err, glint, ok, record, set, shared_data, small_table, tempdir};

/// A capture of the small mock rig at 640x480 (f 750 px) into `dir/s`; its path.
fn capture_640(dir: &std::path::Path) -> std::path::PathBuf {
    let mut t = small_table();
    set(&mut t, "camera.width", 640);
    set(&mut t, "camera.height", 480);
    set(&mut t, "mock.camera.fx", 750.0);
    set(&mut t, "mock.camera.fy", 750.0);
    record(dir, &t).unwrap();
    dir.join("s")
}

#[test]
fn a_captured_grid_photo_gives_the_mock_cameras_truth() {
    let dir = tempdir();
    let s = capture_640(dir.path());
    let out = ok(&glint(&["calibrate", s.to_str().unwrap(), "--json"]));
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert!(s.join("calib/camera.json").exists() && s.join("calib/corners.png").exists());
    let cal = &v["calibration"];
    let f = &cal["parameters"][0];
    let (fv, fsd) = (f["value"].as_f64().unwrap(), f["sd"].as_f64().unwrap());
    let c: Vec<f64> = cal["views"][0]["camera_centre"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect();
    // The mock's default camera stands at (100, -250, 380) mm.
    let truth = [100.0, -250.0, 380.0];
    let dc =
        ((c[0] - truth[0]).powi(2) + (c[1] - truth[1]).powi(2) + (c[2] - truth[2]).powi(2)).sqrt();
    let dist = (truth[0] * truth[0] + truth[1] * truth[1] + truth[2] * truth[2]).sqrt();
    println!(
        "model [{}], f {fv:.2} ± {fsd:.2} (true 750), centre {c:?} ({:.3}% of the distance off), rms {:.3} px",
        cal["candidates"].as_array().unwrap().len(),
        100.0 * dc / dist,
        cal["rms_px"].as_f64().unwrap()
    );
    assert_eq!(v["length_unit"], "mm");
    assert!((fv / 750.0 - 1.0).abs() < 0.005, "f {fv}");
    assert!((fv - 750.0).abs() < 4.0 * fsd, "f {fv} ± {fsd}");
    assert!(dc / dist < 0.005);

    // Intrinsics known from that calibration: the pose alone.
    let known = dir.path().join("known.json");
    std::fs::copy(s.join("calib/camera.json"), &known).unwrap();
    let out = ok(&glint(&[
        "calibrate",
        s.to_str().unwrap(),
        "--intrinsics",
        known.to_str().unwrap(),
        "--json",
    ]));
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["calibration"]["fit"]["focal"], false);
    assert_eq!(v["calibration"]["parameters"].as_array().unwrap().len(), 0);
    let c2 = &v["calibration"]["views"][0]["camera_centre"];
    assert!(
        (c2[2].as_f64().unwrap() - c[2]).abs() < 0.5,
        "{c2} vs {c:?}"
    );
}

#[test]
fn calibrate_refuses_bad_input_with_one_line() {
    let dir = tempdir();
    let junk = dir.path().join("junk.png");
    std::fs::write(&junk, b"not a png").unwrap();
    let e = err(&glint(&[
        "calibrate",
        "--images",
        junk.to_str().unwrap(),
        "--grid",
        "9x6",
        "--out",
        dir.path().join("c").to_str().unwrap(),
    ]));
    assert!(e.contains("corrupt"), "{e}");
    assert!(!dir.path().join("c").exists());
    let e = err(&glint(&[
        "calibrate",
        "--images",
        junk.to_str().unwrap(),
        "--grid",
        "8x6",
    ]));
    assert!(e.contains("ambiguous"), "{e}");
    let e = err(&glint(&[
        "calibrate",
        "--images",
        junk.to_str().unwrap(),
        "--grid",
        "nine",
    ]));
    assert!(e.contains("9x6"), "{e}");
    // A photo with no board.
    let grey = image::GrayImage::from_fn(320, 240, |x, y| {
        image::Luma([((x * 7 + y * 3) % 50) as u8 + 100])
    });
    let p = dir.path().join("plain.png");
    grey.save(&p).unwrap();
    let e = err(&glint(&[
        "calibrate",
        "--images",
        p.to_str().unwrap(),
        "--grid",
        "9x6",
        "--out",
        dir.path().join("c").to_str().unwrap(),
    ]));
    assert!(e.contains("no grid found"), "{e}");
    assert!(!dir.path().join("c").exists());
}

/// `calibrate --images PHOTO --out DIR` into a folder holding a user's `corners.png`
/// (today replaced without a word) is refused and the file is unchanged; a new folder
/// gets `camera.json` and `corners.png`, each created new; a second run into it is
/// refused too. A symbolic link as DIR is refused.
#[test]
fn calibrate_images_refuses_a_non_empty_out_and_keeps_the_users_corners_png() {
    let Some(data) = shared_data("opencv_stereo_chessboard_9x6") else {
        return;
    };
    let photo = data.join("images/left01.jpg");
    let dir = tempdir();
    let out = dir.path().join("mine");
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("corners.png"), b"the user's own picture").unwrap();
    let run = |out: &std::path::Path| {
        glint(&[
            "calibrate",
            "--images",
            photo.to_str().unwrap(),
            "--grid",
            "9x6",
            "--out",
            out.to_str().unwrap(),
        ])
    };
    let e = err(&run(&out));
    assert!(e.contains("is not empty") && e.contains("mine"), "{e}");
    assert_eq!(
        std::fs::read(out.join("corners.png")).unwrap(),
        b"the user's own picture"
    );
    assert_eq!(std::fs::read_dir(&out).unwrap().count(), 1);
    // A new folder: both files, then no second run into it.
    let fresh = dir.path().join("fresh");
    let stdout = ok(&run(&fresh));
    assert!(stdout.contains("corners.png"), "{stdout}");
    let picture = std::fs::read(fresh.join("corners.png")).unwrap();
    image::load_from_memory(&picture).unwrap();
    assert!(fresh.join("camera.json").exists());
    let e = err(&run(&fresh));
    assert!(e.contains("is not empty"), "{e}");
    assert_eq!(std::fs::read(fresh.join("corners.png")).unwrap(), picture);
    // A link as the folder.
    let link = dir.path().join("link");
    std::os::unix::fs::symlink(dir.path().join("elsewhere"), &link).unwrap();
    let e = err(&run(&link));
    assert!(e.contains("symbolic link"), "{e}");
    assert!(!dir.path().join("elsewhere").exists());
}

/// Several `--images` (today one `corners.png` showing only the first view) give one
/// picture per photo with a grid, `corners-NN.png` after the photo's place in the list.
#[test]
fn calibrate_several_images_writes_one_corners_png_per_view() {
    let Some(data) = shared_data("opencv_stereo_chessboard_9x6") else {
        return;
    };
    let photos: Vec<String> = ["left01.jpg", "left02.jpg", "left03.jpg"]
        .iter()
        .map(|f| data.join("images").join(f).display().to_string())
        .collect();
    let dir = tempdir();
    let out = dir.path().join("c");
    let mut args = vec!["calibrate", "--images"];
    args.extend(photos.iter().map(|s| s.as_str()));
    args.extend(["--grid", "9x6", "--out", out.to_str().unwrap()]);
    ok(&glint(&args));
    let mut names: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(
        names,
        [
            "camera.json",
            "corners-01.png",
            "corners-02.png",
            "corners-03.png"
        ]
    );
    // Each picture is its own photo's.
    let a = std::fs::read(out.join("corners-01.png")).unwrap();
    let b = std::fs::read(out.join("corners-02.png")).unwrap();
    assert_ne!(a, b);
}

/// `calibrate --images PHOTO --response RESPONSE_JSON` refines the corners in linear light,
/// exactly as the session's own calibration does once HDR has run (the same corners), and
/// leaves a smaller residual than the photo's values on the mock's gamma 2.2 camera; a
/// photo whose channels are not the response's is refused with one line and nothing
/// written.
#[test]
fn calibrate_images_with_a_response_refines_in_linear_light_as_the_session_does() {
    let dir = tempdir();
    let s = capture_640(dir.path());
    glint::hdr::run::run(&s, &Default::default(), &mut |_| {}).unwrap();
    let session: serde_json::Value =
        serde_json::from_str(&ok(&glint(&["calibrate", s.to_str().unwrap(), "--json"]))).unwrap();
    let grid = std::fs::read_dir(s.join("frames"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.to_string_lossy().contains("-grid-"))
        .expect("the capture has a grid photo");
    let response = s.join("hdr/response.json");
    let images = |out: &str, with: bool| {
        let out = dir.path().join(out);
        let mut args = vec![
            "calibrate",
            "--images",
            grid.to_str().unwrap(),
            "--grid",
            "9x6",
            "--square-mm",
            "25",
            "--json",
            "--out",
            out.to_str().unwrap(),
        ];
        if with {
            args.extend(["--response", response.to_str().unwrap()]);
        }
        let v: serde_json::Value = serde_json::from_str(&ok(&glint(&args))).unwrap();
        v
    };
    let lin = images("lin", true);
    let plain = images("plain", false);
    assert!(
        lin["corners_refined_on"]
            .as_str()
            .unwrap()
            .starts_with("linear light"),
        "{}",
        lin["corners_refined_on"]
    );
    assert!(plain["corners_refined_on"]
        .as_str()
        .unwrap()
        .starts_with("the photo's values"));
    let corners = |v: &serde_json::Value| -> Vec<f64> {
        v["detections"][0]["corners"]
            .as_array()
            .unwrap()
            .iter()
            .flat_map(|p| p.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()))
            .collect()
    };
    let (a, b) = (corners(&lin), corners(&session));
    assert_eq!(a.len(), b.len());
    let most = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max);
    assert!(most < 1e-6, "the session's corners differ by {most} px");
    let rms = |v: &serde_json::Value| v["calibration"]["rms_px"].as_f64().unwrap();
    println!(
        "rms: linear light {:.4} px, photo's values {:.4} px",
        rms(&lin),
        rms(&plain)
    );
    assert!(rms(&lin) < 0.9 * rms(&plain));
    // A grey copy of the colour photo does not fit the colour camera's response.
    let grey = dir.path().join("grey.png");
    image::open(&grid).unwrap().to_luma8().save(&grey).unwrap();
    let out = dir.path().join("refused");
    let e = err(&glint(&[
        "calibrate",
        "--images",
        grey.to_str().unwrap(),
        "--grid",
        "9x6",
        "--response",
        response.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]));
    assert!(e.contains("channels or bit depth"), "{e}");
    assert!(!out.exists());
}
