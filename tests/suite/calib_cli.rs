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

/// The board's squares given for its inner corners (10x7 for a 9x6 board): the error says
/// which count the grid size is, once (the detector's message was printed twice, as the
/// error and as its cause).
#[test]
fn squares_given_for_inner_corners_get_the_hint_once() {
    let dir = tempdir();
    let s = capture_640(dir.path());
    let grid = std::fs::read_dir(s.join("frames"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.to_string_lossy().contains("-grid-"))
        .unwrap();
    let e = err(&glint(&[
        "calibrate",
        "--images",
        grid.to_str().unwrap(),
        "--grid",
        "10x7",
        "--out",
        dir.path().join("c").to_str().unwrap(),
    ]));
    assert!(
        e.contains("inner corners, not squares: a board of 10x7 squares has 9x6 inner corners"),
        "{e}"
    );
    assert_eq!(e.matches("found").count(), 1, "{e}");
    assert_eq!(e.trim().lines().count(), 1, "{e}");
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
            "camera_info.yaml",
            "camera_opencv.yaml",
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

/// `calib/` holds the camera for OpenCV and ROS too: the same numbers as camera.json (its
/// `camera_matrix` and `dist_coeffs` arrays too), in OpenCV's order, with the views'
/// extrinsics; projected by OpenCV's model written out here (not Glint's code), the YAML's
/// camera puts the corners where Glint's own projection does; and read back as
/// `--intrinsics` it is held exactly (only the pose is fitted, and lands where it was).
#[test]
fn calib_writes_opencv_and_ros_camera_files_that_read_back() {
    let dir = tempdir();
    let s = capture_640(dir.path());
    ok(&glint(&["calibrate", s.to_str().unwrap()]));
    let cam: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(s.join("calib/camera.json")).unwrap())
            .unwrap();
    let k = &cam["calibration"]["intrinsics"];
    let f = |v: &serde_json::Value| v.as_f64().unwrap();
    let m: Vec<f64> = cam["camera_matrix"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|r| r.as_array().unwrap().iter().map(f))
        .collect();
    assert_eq!(
        m,
        [
            f(&k["fx"]),
            0.0,
            f(&k["cx"]),
            0.0,
            f(&k["fy"]),
            f(&k["cy"]),
            0.0,
            0.0,
            1.0
        ]
    );
    let d: Vec<f64> = cam["dist_coeffs"]
        .as_array()
        .unwrap()
        .iter()
        .map(f)
        .collect();
    let radial: Vec<f64> = k["radial"].as_array().unwrap().iter().map(f).collect();
    assert_eq!(d[0], radial.first().copied().unwrap_or(0.0));
    assert_eq!(d[1], radial.get(1).copied().unwrap_or(0.0));
    assert_eq!(d[4], radial.get(2).copied().unwrap_or(0.0));

    let yaml = std::fs::read_to_string(s.join("calib/camera_opencv.yaml")).unwrap();
    let (w, h, ky) = glint::calib::export::parse_intrinsics_yaml(&yaml).unwrap();
    assert_eq!((w, h), (640, 480));
    assert_eq!([ky.fx, ky.fy, ky.cx, ky.cy], [m[0], m[4], m[2], m[5]]);
    let ros = std::fs::read_to_string(s.join("calib/camera_info.yaml")).unwrap();
    assert!(ros.contains("distortion_model: plumb_bob"), "{ros}");
    let (_, _, kr) = glint::calib::export::parse_intrinsics_yaml(&ros).unwrap();
    assert_eq!(kr, ky);

    // OpenCV's projection (cv::projectPoints with k1, k2, p1, p2, k3), from the YAML's
    // numbers alone: extrinsic_parameters' first row is the view's rvec and t.
    let ext = yaml_matrix(&yaml, "extrinsic_parameters");
    let dist = yaml_matrix(&yaml, "distortion_coefficients");
    let cm = yaml_matrix(&yaml, "camera_matrix");
    assert_eq!(ext.len(), 6);
    let (r, t) = ([ext[0], ext[1], ext[2]], [ext[3], ext[4], ext[5]]);
    let rot = rodrigues(r);
    let grid = &cam["grid"];
    let nx = grid["inner_corners"][0].as_u64().unwrap() as usize;
    let sq = f(&grid["square_mm"]);
    let det = &cam["detections"][0];
    let skip: Vec<u64> = det["placed"]
        .as_array()
        .unwrap()
        .iter()
        .chain(det["doubtful"].as_array().unwrap())
        .map(|x| x.as_u64().unwrap())
        .collect();
    let residuals = cam["calibration"]["views"][0]["residuals"]
        .as_array()
        .unwrap();
    let mut used = 0;
    let mut worst: f64 = 0.0;
    for (i, c) in det["corners"].as_array().unwrap().iter().enumerate() {
        if skip.contains(&(i as u64)) {
            continue;
        }
        let x = [(i % nx) as f64 * sq, (i / nx) as f64 * sq, 0.0];
        let xc: Vec<f64> = (0..3)
            .map(|a| rot[a][0] * x[0] + rot[a][1] * x[1] + rot[a][2] * x[2] + t[a])
            .collect();
        let (u, v) = (xc[0] / xc[2], xc[1] / xc[2]);
        let r2 = u * u + v * v;
        let rad = 1.0 + dist[0] * r2 + dist[1] * r2 * r2 + dist[4] * r2 * r2 * r2;
        let xd = u * rad + 2.0 * dist[2] * u * v + dist[3] * (r2 + 2.0 * u * u);
        let yd = v * rad + dist[2] * (r2 + 2.0 * v * v) + 2.0 * dist[3] * u * v;
        let p = [cm[0] * xd + cm[2], cm[4] * yd + cm[5]];
        // Glint's own projection: the detected corner plus its residual.
        let res = &residuals[used];
        let g = [f(&c[0]) + f(&res[0]), f(&c[1]) + f(&res[1])];
        worst = worst.max((p[0] - g[0]).hypot(p[1] - g[1]));
        used += 1;
    }
    println!(
        "{used} corners; OpenCV's model from the YAML vs Glint's projection: worst {worst:.2e} px"
    );
    assert_eq!(used, residuals.len());
    assert!(worst < 1e-6, "{worst}");

    // Read back as --intrinsics: held, only the pose fitted, the centre where it was.
    let before = cam["calibration"]["views"][0]["camera_centre"].clone();
    let out = ok(&glint(&[
        "calibrate",
        s.to_str().unwrap(),
        "--intrinsics",
        s.join("calib/camera_opencv.yaml").to_str().unwrap(),
        "--json",
    ]));
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    let cal = &v["calibration"];
    assert_eq!(cal["fit"]["focal"], false, "{}", cal["fit"]);
    assert_eq!(f(&cal["intrinsics"]["fx"]), m[0]);
    let after = &cal["views"][0]["camera_centre"];
    let moved = (0..3)
        .map(|i| (f(&after[i]) - f(&before[i])).powi(2))
        .sum::<f64>()
        .sqrt();
    println!("camera centre moved {moved:.2e} mm with the lens held from the YAML");
    assert!(moved < 1e-3, "{moved}");
}

/// A top-level matrix's data in an OpenCV YAML (the test's own reading).
fn yaml_matrix(yaml: &str, key: &str) -> Vec<f64> {
    let start = yaml.find(&format!("{key}:")).unwrap();
    let rest = &yaml[start..];
    let open = rest.find('[').unwrap();
    let close = rest.find(']').unwrap();
    rest[open + 1..close]
        .split(',')
        .map(|x| x.trim().parse::<f64>().unwrap())
        .collect()
}

/// Rodrigues' formula: the rotation matrix of a rotation vector.
fn rodrigues(r: [f64; 3]) -> [[f64; 3]; 3] {
    let th = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
    if th < 1e-300 {
        return [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    }
    let k = [r[0] / th, r[1] / th, r[2] / th];
    let (s, c) = th.sin_cos();
    let mut m = [[0.0; 3]; 3];
    let kx = [[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]];
    for i in 0..3 {
        for j in 0..3 {
            let kk: f64 = (0..3).map(|l| kx[i][l] * kx[l][j]).sum();
            m[i][j] = if i == j { 1.0 } else { 0.0 } + s * kx[i][j] + (1.0 - c) * kk;
        }
    }
    m
}

/// A camera YAML from anywhere: random edits of one that reads (characters replaced,
/// inserted, lines cut) never panic, and every error is one line naming what is wrong.
#[test]
fn camera_yaml_edits_never_panic_and_errors_are_one_line() {
    use proptest::prelude::*;
    use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};
    let good = "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 750.5, 0., 319.5, 0., 750.5, 239.5,\n       0., 0., 1. ]\ndistortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ -0.1, 0.01, 0., 0., 0. ]\n";
    assert!(glint::calib::export::parse_intrinsics_yaml(good).is_ok());
    let alphabet: Vec<char> = "[]:,.-e0123456789 \n\tabcdrows:data\u{e9}\u{1f600}#'\"!"
        .chars()
        .collect();
    let edits = proptest::collection::vec((0usize..400, 0usize..alphabet.len(), 0u8..3), 1..8);
    let mut runner = TestRunner::new_with_rng(
        Config {
            cases: 2000,
            failure_persistence: None,
            ..Config::default()
        },
        TestRng::from_seed(RngAlgorithm::ChaCha, &[7; 32]),
    );
    let (ok, refused) = (std::cell::Cell::new(0), std::cell::Cell::new(0));
    runner
        .run(&edits, |edits| {
            let mut s: Vec<char> = good.chars().collect();
            for (at, c, kind) in edits {
                let at = at % (s.len() + 1);
                match kind {
                    0 if at < s.len() => s[at] = alphabet[c],
                    1 => s.insert(at, alphabet[c]),
                    _ => {
                        let end = (at + c).min(s.len());
                        s.drain(at.min(end)..end);
                    }
                }
            }
            let text: String = s.into_iter().collect();
            match glint::calib::export::parse_intrinsics_yaml(&text) {
                Ok(_) => ok.set(ok.get() + 1),
                Err(e) => {
                    refused.set(refused.get() + 1);
                    prop_assert!(!e.contains('\n') && e.len() < 400 && !e.is_empty(), "{e:?}");
                }
            }
            Ok(())
        })
        .unwrap();
    let (ok, refused) = (ok.get(), refused.get());
    println!("2000 edited YAMLs: {ok} read, {refused} refused with one line");
    assert!(ok > 0 && refused > 0);
}

/// `glint report --json` prints the results for scripts: null for a stage not run yet
/// (and it is listed as missing), the stage's figures once it has.
#[test]
fn report_json_gives_each_stages_figures_or_null() {
    let dir = tempdir();
    let s = capture_640(dir.path());
    let out = ok(&glint(&["report", s.to_str().unwrap(), "--json"]));
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert!(v["results"]["calibration"].is_null(), "{v}");
    assert!(v["results"]["fit"].is_null());
    let missing: Vec<&str> = v["missing"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m.as_str().unwrap())
        .collect();
    assert!(
        missing.contains(&"calibrate") || missing.contains(&"calibration"),
        "{missing:?}"
    );
    ok(&glint(&["calibrate", s.to_str().unwrap()]));
    let out = ok(&glint(&["report", s.to_str().unwrap(), "--json"]));
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    let c = &v["results"]["calibration"];
    let centre: Vec<f64> = c["camera_centre"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect();
    // The mock's default camera stands at (100, -250, 380) mm.
    assert!((centre[2] - 380.0).abs() < 10.0, "{centre:?}");
    assert_eq!(c["camera_matrix"][2][2], 1.0);
    assert!(v["report"].as_str().unwrap().ends_with("index.html"));
}

/// `glint bench calib` on a fresh clone (no shared test data, so no left01.jpg): it times a
/// synthetic photo of the board instead, and says so; the board is found.
#[test]
fn bench_calib_without_the_photo_times_a_synthetic_board() {
    let dir = tempdir();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_glint"))
        .args(["bench", "calib", "--repeats", "1"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    let stdout = ok(&out);
    assert!(
        stderr.contains("synthetic photo of a 9x6 board"),
        "{stderr}"
    );
    assert!(
        stdout.starts_with("a synthetic board (640x480)"),
        "{stdout}"
    );
}
