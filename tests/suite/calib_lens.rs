//! The lens belongs to the camera: the lens plan on the simulated lab (the lab's operator
//! holds the board in each pose, its own renderer draws it) gives the camera's lens
//! profile; a later session's in-place grid photo then gives the pose alone, holding that
//! lens. Checked against the lab's truth on scenes not tuned on: camera position and
//! tilt, focal length, principal point offset and distortion vary with the seed.

use std::path::Path;

use glint::calib::{lens, run};
use glint::capture::{FrameKind, Plan, Step};
use glint::devices::OperatorAction;
use rand::{RngExt, SeedableRng};
use rand_xoshiro::Xoshiro256PlusPlus;

use super::util::{load, set, small_table, tempdir};

/// A 640x480 mock rig whose true camera is drawn from `seed`.
fn rig_table(seed: u64) -> (toml::Table, [f64; 3], f64) {
    let mut r = Xoshiro256PlusPlus::seed_from_u64(seed);
    let mut t = small_table();
    set(&mut t, "camera.width", 640);
    set(&mut t, "camera.height", 480);
    let f = r.random_range(680.0..820.0);
    set(&mut t, "mock.camera.fx", f);
    set(&mut t, "mock.camera.fy", f);
    set(
        &mut t,
        "mock.camera.cx",
        319.5 + r.random_range(-16.0..16.0),
    );
    set(
        &mut t,
        "mock.camera.cy",
        239.5 + r.random_range(-12.0..12.0),
    );
    set(&mut t, "mock.camera.k1", r.random_range(-0.12..0.0));
    set(&mut t, "mock.camera.k2", r.random_range(0.0..0.04));
    // About 450 mm from the board's centre, looking down at 35..45 degrees.
    let pos = [
        r.random_range(70.0..130.0),
        r.random_range(-300.0..-230.0),
        r.random_range(340.0..400.0),
    ];
    set(
        &mut t,
        "mock.camera.position_mm",
        toml::Value::Array(pos.iter().map(|x| toml::Value::Float(*x)).collect()),
    );
    set(
        &mut t,
        "mock.camera.look_at_mm",
        toml::Value::Array(
            [r.random_range(90.0..110.0), r.random_range(50.0..75.0), 0.0]
                .iter()
                .map(|x| toml::Value::Float(*x))
                .collect(),
        ),
    );
    set(&mut t, "mock.camera.roll_deg", r.random_range(-5.0..5.0));
    set(&mut t, "mock.seed", seed as i64);
    set(&mut t, "bracket.grid_frames", 2);
    (t, pos, f)
}

/// The grid photo alone, as a session's plan takes it (tile removed, lamp on).
fn grid_plan(rig: &glint::rig::Rig) -> Plan {
    Plan {
        steps: vec![
            Step::IdentifyLamp,
            Step::Operator {
                action: OperatorAction::RemoveTile,
            },
            Step::LampOn {
                level: rig.lamp.level,
            },
            Step::SetExposure {
                us: rig.bracket.grid_exposure_us,
            },
            Step::Capture {
                kind: FrameKind::Grid,
                count: rig.bracket.grid_frames,
            },
            Step::LampOff,
        ],
    }
}

struct Outcome {
    centre_error_mm: f64,
    z: f64,
    f_error: f64,
    single_view_error_mm: f64,
    /// The lens plan's tilt the profile was made at (30, or 20 where the check refused 30).
    tilt_deg: f64,
}

fn lens_then_pose(dir: &Path, seed: u64, poses: usize) -> Outcome {
    let (t, truth, f_true) = rig_table(seed);
    let loaded = load(dir, &t);
    let r = &loaded.rig;
    // 1. The lens plan, run by the engine on the simulated lab; where the board left the
    // frame in more than half of the poses, again at 20 degrees, as the check tells the
    // operator to.
    let mut tilts = [30.0, 20.0].into_iter().peekable();
    let (info, file, checks, lens_dir, tilt_deg) = loop {
        let tilt = tilts.next().expect("a tilt to try");
        let lens_dir = dir.join(format!("lens-{tilt}"));
        let plan = Plan::for_lens(r, &glint::plan::lens_poses(r, tilt, poses));
        let devices = glint::devices::open(&loaded).unwrap();
        let rec = glint::capture::record_plan(
            &loaded,
            plan,
            devices,
            &lens_dir,
            Default::default(),
            &mut |_| {},
            &mut |_| {},
        )
        .map_err(|(e, _)| e)
        .unwrap();
        let info = rec.devices.camera.info();
        let file = run::run_session(&rec.dir, None).unwrap();
        for w in &file.skipped {
            println!("seed {seed} at {tilt} degrees: skipped {w}");
        }
        match lens::check(&file) {
            Ok(checks) => break (info, file, checks, rec.dir, tilt),
            Err(e) if tilts.peek().is_some() && e.to_string().contains("smaller --tilt-deg") => {
                println!("seed {seed}: at {tilt} degrees: {e}");
            }
            Err(e) => panic!("seed {seed}: {e}"),
        }
    };
    let path = lens::profile_path(&loaded.path, &info.model, info.width, info.height).unwrap();
    let stored = lens::store(&path, &file, &checks, &lens_dir, &info.model, false).unwrap();
    assert!(matches!(stored, lens::Stored::Written { .. }));
    // Never replaced unless asked.
    assert!(matches!(
        lens::store(&path, &file, &checks, &lens_dir, &info.model, false).unwrap(),
        lens::Stored::Kept { .. }
    ));
    let f = &file.calibration.parameters[0];
    let f_error = f.value / f_true - 1.0;

    // 2. A later session: the in-place grid photo, its pose with the profile's lens.
    let devices = glint::devices::open(&loaded).unwrap();
    let rec = glint::capture::record_plan(
        &loaded,
        grid_plan(r),
        devices,
        &dir.join("session"),
        Default::default(),
        &mut |_| {},
        &mut |_| {},
    )
    .map_err(|(e, _)| e)
    .unwrap();
    let known = lens::load(&loaded.path, &info.model, info.width, info.height)
        .unwrap()
        .expect("the profile just written");
    let posed = run::run_session(&rec.dir, Some(&known)).unwrap();
    let v = &posed.calibration.views[0];
    let d: Vec<f64> = (0..3).map(|i| v.camera_centre[i] - truth[i]).collect();
    let err = d.iter().map(|x| x * x).sum::<f64>().sqrt();
    let z = (0..3)
        .map(|i| (d[i] / v.camera_centre_sd[i]).abs())
        .fold(0.0, f64::max);
    // `glint calibrate SESSION --rig RIG` holds the same profile and gives the same pose.
    std::fs::remove_dir_all(rec.dir.join("calib")).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_glint"))
        .arg("calibrate")
        .arg(&rec.dir)
        .arg("--rig")
        .arg(&loaded.path)
        .arg("--json")
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "glint calibrate --rig: {said}");
    assert!(said.contains("holding the lens profile"), "{said}");
    let cli: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(cli["calibration"]["fit"]["focal"], false, "{cli}");
    let cc = &cli["calibration"]["views"][0]["camera_centre"];
    for i in 0..3 {
        let x = cc[i].as_f64().unwrap();
        assert!(
            (x - v.camera_centre[i]).abs() < 1e-9,
            "glint calibrate --rig: centre {cc} against {:?}",
            v.camera_centre
        );
    }
    // The same photo calibrated alone (the intrinsics fitted from it), for comparison.
    std::fs::remove_dir_all(rec.dir.join("calib")).unwrap();
    let single = run::run_session(&rec.dir, None).unwrap();
    let s = &single.calibration.views[0];
    let single_err = (0..3)
        .map(|i| (s.camera_centre[i] - truth[i]).powi(2))
        .sum::<f64>()
        .sqrt();
    println!(
        "seed {seed}: lens [{}] f {:.2} ± {:.2} (true {f_true:.2}, {:+.3}%), RMS {:.3} px, tilt spread {:.1}°/{:.1}°; pose with the profile: centre off {err:.3} mm (sd {:.3}, {:.3}, {:.3}; worst |z| {z:.2}); from the photo alone: {single_err:.3} mm",
        file.calibration.fit.describe(),
        f.value,
        f.sd,
        100.0 * f_error,
        file.calibration.rms_px,
        checks.tilt_spread_deg[0],
        checks.tilt_spread_deg[1],
        v.camera_centre_sd[0],
        v.camera_centre_sd[1],
        v.camera_centre_sd[2],
    );
    Outcome {
        centre_error_mm: err,
        z,
        f_error,
        single_view_error_mm: single_err,
        tilt_deg,
    }
}

/// Lens plan on the mock → lens profile → a capture's grid photo → its pose holding the
/// profile's lens: the camera centre within 0.3 mm of the truth and within 3 sd, on
/// three scenes.
#[test]
fn a_lens_profile_gives_the_pose_from_the_grid_photo_within_a_third_of_a_millimetre() {
    let mut worst: f64 = 0.0;
    let mut tilts = Vec::new();
    for seed in [11, 12, 13] {
        let d = tempdir();
        let o = lens_then_pose(d.path(), seed, 9);
        tilts.push(o.tilt_deg);
        assert!(
            o.centre_error_mm < 0.3,
            "seed {seed}: camera centre {:.3} mm off",
            o.centre_error_mm
        );
        assert!(o.z < 3.0, "seed {seed}: {:.2} sd off", o.z);
        assert!(
            o.f_error.abs() < 0.005,
            "seed {seed}: f {:.3}%",
            100.0 * o.f_error
        );
        worst = worst.max(o.centre_error_mm);
        let _ = o.single_view_error_mm;
    }
    // The check on half of the poses both refuses (seeds 11 and 13 lose 5 of 9 poses at
    // 30 degrees: the board leaves the frame, or its far rows go dark) and lets a plan
    // through (seed 12).
    assert_eq!(
        tilts,
        [20.0, 30.0, 20.0],
        "the tilts the profiles were made at"
    );
    println!("worst camera-centre error with the lens profile: {worst:.3} mm");
}

/// More scenes (run by hand: cargo test -- --ignored lens_profile_sweep).
#[test]
#[ignore]
fn lens_profile_sweep() {
    let (mut worst, mut worst_single, mut worst_f) = (0.0f64, 0.0f64, 0.0f64);
    let mut within3 = 0;
    let seeds = 20..32;
    let n = seeds.clone().count();
    for seed in seeds {
        let d = tempdir();
        let o = lens_then_pose(d.path(), seed, 9);
        worst = worst.max(o.centre_error_mm);
        worst_single = worst_single.max(o.single_view_error_mm);
        worst_f = worst_f.max(o.f_error.abs());
        within3 += (o.z < 3.0) as usize;
    }
    println!(
        "{n} scenes: camera centre with the lens profile worst {worst:.3} mm ({within3} of {n} within 3 sd on every axis); from the photo alone worst {worst_single:.3} mm; f worst {:.3}%",
        100.0 * worst_f
    );
    assert!(worst < 0.3 && within3 == n);
}
