//! Rig files: the shipped ones load; every kind of mistake is named with file, key and fix.

use std::path::Path;

use glint::rig::{self, RigError};

use super::util::{mock_table, root, set, small_table};

fn parse_err(t: &toml::Table) -> String {
    let text = toml::to_string(t).unwrap();
    rig::parse(&text, Path::new("bad.toml"))
        .unwrap_err()
        .to_string()
}

fn parse_text_err(text: &str) -> RigError {
    rig::parse(text, Path::new("bad.toml")).unwrap_err()
}

#[test]
fn shipped_rigs_load() {
    let m = rig::load(&root().join("rigs/mock.toml")).unwrap();
    assert_eq!(m.rig.bracket.exposures_us.len(), 7);
    let l = rig::load(&root().join("rigs/lab-example.toml")).unwrap();
    assert_eq!(l.rig.lamp.port.as_deref(), Some("/dev/ttyUSB0"));
}

#[test]
fn unknown_key_names_line_section_and_fix() {
    let text = std::fs::read_to_string(root().join("rigs/mock.toml"))
        .unwrap()
        .replace(
            "fps = 30.0\nframe_timeout_ms",
            "fsp = 30.0\nframe_timeout_ms",
        );
    let e = parse_text_err(&text).to_string();
    assert!(e.starts_with("bad.toml:"), "{e}");
    assert!(
        e.contains("unknown field `fsp`")
            && e.contains("in [camera]")
            && e.contains("fix its spelling"),
        "{e}"
    );
    let line: usize = e.split(':').nth(1).unwrap().parse().unwrap();
    assert_eq!(text.lines().nth(line - 1).unwrap().trim(), "fsp = 30.0");
}

#[test]
fn wrong_type_and_negative_exposure_are_syntax_errors_with_a_line() {
    let text = std::fs::read_to_string(root().join("rigs/mock.toml")).unwrap();
    let e = parse_text_err(&text.replace("width = 1280", "width = \"wide\"")).to_string();
    assert!(e.contains("bad.toml:") && e.contains("in [camera]"), "{e}");
    let e =
        parse_text_err(&text.replace("exposures_us = [125,", "exposures_us = [-125,")).to_string();
    assert!(e.contains("in [bracket]"), "{e}");
}

#[test]
fn semantic_problems_name_key_and_fix() {
    let cases: Vec<(&str, toml::Value, &str)> = vec![
        (
            "bracket.exposures_us",
            toml::Value::try_from(vec![125, 250, 250, 1000]).unwrap(),
            "must increase strictly: 250 µs follows 250 µs",
        ),
        (
            "bracket.exposures_us",
            toml::Value::try_from(vec![10, 250]).unwrap(),
            "outside the camera's range",
        ),
        (
            "bracket.exposures_us",
            toml::Value::try_from(Vec::<u32>::new()).unwrap(),
            "at least one exposure",
        ),
        (
            "geometry.lamp_position_mm",
            toml::Value::try_from(vec![100.0, 100.0, -20.0]).unwrap(),
            "must be above the grid",
        ),
        (
            "geometry.tile_outline_mm",
            toml::Value::try_from(vec![[50.0, 30.0], [450.0, 30.0], [450.0, 130.0]]).unwrap(),
            "off the grid",
        ),
        (
            "geometry.grid_inner_corners",
            toml::Value::try_from(vec![9, 7]).unwrap(),
            "origin is ambiguous",
        ),
        (
            "camera.bit_depth",
            toml::Value::Integer(12),
            "must be 8 or 16",
        ),
        ("lamp.level", toml::Value::Integer(1500), "0..1000"),
        (
            "mock.tile.n",
            toml::Value::Float(-3.0),
            "exponent must be positive",
        ),
        (
            "mock.camera.look_at_mm",
            toml::Value::try_from(vec![900.0, 60.0, 0.0]).unwrap(),
            "outside the simulated",
        ),
    ];
    for (key, value, expect) in cases {
        let mut t = mock_table();
        set(&mut t, key, value);
        let e = parse_err(&t);
        assert!(e.starts_with("bad.toml: "), "{key}: {e}");
        assert!(
            e.contains(
                key.split('.')
                    .take(2)
                    .collect::<Vec<_>>()
                    .join(".")
                    .as_str()
            ),
            "{key}: {e}"
        );
        assert!(e.contains(expect), "{key}: expected `{expect}` in: {e}");
    }
}

#[test]
fn ambiguous_board_is_refused() {
    let mut t = mock_table();
    set(
        &mut t,
        "geometry.grid_inner_corners",
        toml::Value::try_from(vec![9, 7]).unwrap(),
    );
    assert!(parse_err(&t).contains("looks the same turned half round"));
}

#[test]
fn backends_must_agree_and_serial_needs_a_port() {
    // An empty level command sends the level with `on`, which must then carry it.
    let mut t = small_table();
    set(&mut t, "lamp.commands.level", "");
    let (code, lines) = rig_check(&t);
    assert_eq!(code, Some(1));
    assert!(
        lines
            .iter()
            .any(|l| l.starts_with("bad.toml: lamp.commands.on: ")
                && l.contains("must contain `{level}`")),
        "{lines:?}"
    );
    // The simulated camera may be lit by a serial lamp (glint-mock lamp); a serial lamp
    // needs its port.
    let mut t = small_table();
    set(&mut t, "lamp.backend", "serial");
    set(&mut t, "lamp.tries", 0);
    let e = rig::parse(&toml::to_string(&t).unwrap(), Path::new("x.toml")).unwrap_err();
    let all = e.problems().join("\n");
    assert!(
        all.contains("lamp.port") && !all.contains("lamp.backend"),
        "{all}"
    );
    assert!(
        e.to_string()
            .contains("more; `glint rig check` lists them all"),
        "{e}"
    );
}

#[test]
fn missing_file_is_a_clear_error() {
    let e = rig::load(Path::new("no/such/rig.toml"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("cannot read rig file no/such/rig.toml"), "{e}");
}

/// `glint rig check` on the table `t`: (exit code, stdout lines).
fn rig_check(t: &toml::Table) -> (Option<i32>, Vec<String>) {
    let dir = super::util::tempdir();
    let path = dir.path().join("bad.toml");
    std::fs::write(&path, toml::to_string(t).unwrap()).unwrap();
    let o = super::util::glint(&["rig", "check", path.to_str().unwrap()]);
    let out = String::from_utf8_lossy(&o.stdout);
    // Every problem is an error line: `error: FILE: key: message`.
    if !o.status.success() {
        for l in out.lines() {
            assert!(l.starts_with("error: "), "{l}");
        }
    }
    (
        o.status.code(),
        out.lines()
            .map(|l| {
                l.trim_start_matches("error: ")
                    .replace(path.to_str().unwrap(), "bad.toml")
            })
            .collect(),
    )
}

/// The one line `glint rig check` prints for a rig with one mistake, after checking it
/// failed.
fn one_problem(t: &toml::Table) -> String {
    let (code, lines) = rig_check(t);
    assert_eq!(code, Some(1), "{lines:?}");
    assert_eq!(lines.len(), 1, "{lines:?}");
    lines[0].clone()
}

#[test]
fn fps_inf_is_refused_by_rig_check_naming_the_key() {
    // It passed, the capture said complete and the manifest stored `null` for fps, so no
    // later command could read the session.
    let mut t = small_table();
    set(&mut t, "camera.fps", f64::INFINITY);
    let e = one_problem(&t);
    assert!(e.starts_with("bad.toml: camera.fps: "), "{e}");
    assert!(e.contains("finite") && e.contains("inf"), "{e}");
}

#[test]
fn a_huge_or_tiny_number_is_shown_short_not_in_309_digits() {
    // `{}` prints 1e308 as 309 digits: the error named the key but buried it.
    for (key, v, shown) in [
        ("camera.fps", 1e308, "1e308"),
        ("geometry.tile_thickness_mm", -1e308, "-1e308"),
        ("mock.tile.n", 1e300, "1e300"),
        ("mock.sensor.read_noise_e", -1e-300, "-1e-300"),
    ] {
        let mut t = small_table();
        set(&mut t, key, v);
        let e = one_problem(&t);
        assert!(e.contains(key) && e.contains(shown), "{key}: {e}");
        assert!(e.len() < 200, "{key}: {e}");
    }
}

#[test]
fn fps_nan_is_refused_by_rig_check_naming_the_key() {
    let mut t = small_table();
    set(&mut t, "camera.fps", f64::NAN);
    let e = one_problem(&t);
    assert!(e.starts_with("bad.toml: camera.fps: "), "{e}");
    assert!(e.contains("finite") && e.contains("NaN"), "{e}");
}

#[test]
fn width_2147483648_is_refused_by_rig_check_naming_the_key_and_bound() {
    let mut t = small_table();
    set(&mut t, "camera.width", 2_147_483_648i64);
    let e = one_problem(&t);
    assert!(
        e.starts_with("bad.toml: camera.width: must be at most 16384 pixels (got 2147483648)"),
        "{e}"
    );
    // Beyond u32 it is a type error, still naming the key.
    set(&mut t, "camera.width", 5_000_000_000i64);
    let e = one_problem(&t);
    assert!(
        e.contains("camera.width") && e.contains("(in [camera])"),
        "{e}"
    );
}

#[test]
fn every_float_of_a_rig_refuses_nan_and_inf_naming_the_key() {
    use toml::Value;
    let f = Value::Float;
    let arr = |v: Vec<Value>| Value::Array(v);
    let cases = |x: f64| -> Vec<(&'static str, &'static str, Value)> {
        vec![
            ("camera.fps", "camera.fps", f(x)),
            (
                "geometry.tile_thickness_mm",
                "geometry.tile_thickness_mm",
                f(x),
            ),
            ("geometry.grid_square_mm", "geometry.grid_square_mm", f(x)),
            (
                "geometry.lamp_position_mm",
                "geometry.lamp_position_mm",
                arr(vec![f(100.0), f(x), f(300.0)]),
            ),
            (
                "geometry.tile_outline_mm",
                "geometry.tile_outline_mm",
                arr(vec![
                    arr(vec![f(50.0), f(30.0)]),
                    arr(vec![f(x), f(30.0)]),
                    arr(vec![f(150.0), f(130.0)]),
                ]),
            ),
            ("mock.camera.fx", "mock.camera.fx", f(x)),
            ("mock.camera.fy", "mock.camera.fy", f(x)),
            ("mock.camera.cx", "mock.camera.cx", f(x)),
            ("mock.camera.cy", "mock.camera.cy", f(x)),
            ("mock.camera.k1", "mock.camera.k1", f(x)),
            ("mock.camera.k2", "mock.camera.k2", f(x)),
            ("mock.camera.roll_deg", "mock.camera.roll_deg", f(x)),
            (
                "mock.camera.position_mm",
                "mock.camera.position_mm",
                arr(vec![f(100.0), f(-250.0), f(x)]),
            ),
            (
                "mock.camera.look_at_mm",
                "mock.camera.look_at_mm",
                arr(vec![f(x), f(60.0), f(0.0)]),
            ),
            (
                "mock.tile.kd",
                "mock.tile.kd",
                arr(vec![f(0.3), f(x), f(0.2)]),
            ),
            (
                "mock.tile.ks",
                "mock.tile.ks",
                arr(vec![f(x), f(0.3), f(0.3)]),
            ),
            ("mock.tile.n", "mock.tile.n", f(x)),
            ("mock.grid.light", "mock.grid.light", f(x)),
            ("mock.grid.dark", "mock.grid.dark", f(x)),
            ("mock.grid.surround", "mock.grid.surround", f(x)),
            (
                "mock.sensor.response.gamma",
                "mock.sensor.response.gamma",
                f(x),
            ),
            (
                "mock.sensor.electrons_per_radiance_us",
                "mock.sensor.electrons_per_radiance_us",
                f(x),
            ),
            ("mock.sensor.full_well_e", "mock.sensor.full_well_e", f(x)),
            ("mock.sensor.read_noise_e", "mock.sensor.read_noise_e", f(x)),
            (
                "mock.sensor.dark_current_e_per_s",
                "mock.sensor.dark_current_e_per_s",
                f(x),
            ),
            ("mock.sensor.blooming", "mock.sensor.blooming", f(x)),
            ("mock.sensor.fps", "mock.sensor.fps", f(x)),
            ("mock.lamp.intensity", "mock.lamp.intensity", f(x)),
        ]
    };
    for x in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        for (key, named, value) in cases(x) {
            let mut t = small_table();
            set(&mut t, key, value);
            let e = rig::parse(&toml::to_string(&t).unwrap(), Path::new("bad.toml"))
                .expect_err(&format!("{key} = {x} was accepted"));
            let problems = e.problems();
            assert!(
                problems
                    .iter()
                    .any(|p| p.starts_with(&format!("{named}: "))),
                "{key} = {x}: {problems:?}"
            );
        }
    }
    // The EMoR response's coefficients too.
    let mut t = small_table();
    let mut emor = toml::Table::new();
    emor.insert("kind".into(), "emor".into());
    emor.insert("file".into(), "emor.txt".into());
    emor.insert("coefficients".into(), arr(vec![f(0.1), f(f64::NAN)]));
    set(&mut t, "mock.sensor.response", Value::Table(emor));
    let e = rig::parse(&toml::to_string(&t).unwrap(), Path::new("bad.toml")).unwrap_err();
    assert!(
        e.to_string()
            .contains("mock.sensor.response.coefficients: each must be a finite number"),
        "{e}"
    );
}

#[test]
fn every_value_has_an_upper_bound_named_in_the_error() {
    use toml::Value;
    let int = Value::Integer;
    let many = |n: i64| Value::try_from((1..=n).map(|i| i * 100).collect::<Vec<_>>()).unwrap();
    let outline = Value::try_from(
        (0..65)
            .map(|i| {
                let a = i as f64 / 65.0 * std::f64::consts::TAU;
                [100.0 + 40.0 * a.cos(), 80.0 + 40.0 * a.sin()]
            })
            .collect::<Vec<_>>(),
    )
    .unwrap();
    let cases: Vec<(&str, Value, &str)> = vec![
        ("camera.width", int(16_385), "at most 16384 pixels"),
        ("camera.height", int(20_000), "at most 16384 pixels"),
        (
            "camera.max_exposure_us",
            int(600_000_001),
            "at most 600000000 µs",
        ),
        (
            "camera.fps",
            Value::Float(1e4),
            "at most 1000 frames per second",
        ),
        (
            "camera.fps",
            Value::Float(1e-300),
            "at least 0.01 frames per second",
        ),
        (
            "camera.frame_timeout_ms",
            int(3_600_001),
            "at most 3600000 ms",
        ),
        ("camera.settle_max_frames", int(101), "at most 100 frames"),
        (
            "camera.max_dropped_frames",
            int(1001),
            "at most 1000 frames",
        ),
        ("lamp.baud", int(4_000_001), "at most 4000000 baud"),
        ("lamp.warmup_ms", int(3_600_001), "at most 3600000 ms"),
        ("lamp.reply_timeout_ms", int(60_001), "at most 60000 ms"),
        ("lamp.tries", int(21), "at most 20"),
        (
            "bracket.frames_per_exposure",
            int(101),
            "at most 100 frames",
        ),
        (
            "bracket.dark_frames_per_exposure",
            int(101),
            "at most 100 frames",
        ),
        ("bracket.grid_frames", int(101), "at most 100 frames"),
        ("bracket.exposures_us", many(65), "at most 64"),
        ("geometry.tile_outline_mm", outline, "at most 64"),
        (
            "geometry.lamp_position_mm",
            Value::try_from(vec![100.0, 350.0, 1e6]).unwrap(),
            "within ±100000",
        ),
        (
            "geometry.grid_square_mm",
            Value::Float(1001.0),
            "at most 1000 mm",
        ),
        (
            "geometry.tile_thickness_mm",
            Value::Float(2e5),
            "at most 100000 mm",
        ),
        (
            "mock.camera.fx",
            Value::Float(2e6),
            "at most 1000000 pixels",
        ),
        ("mock.camera.k1", Value::Float(-11.0), "at least -10"),
        ("mock.tile.n", Value::Float(1e6), "at most 100000"),
        (
            "mock.sensor.full_well_e",
            Value::Float(1e10),
            "at most 1000000000",
        ),
        (
            "mock.sensor.exposure_latency_frames",
            int(1001),
            "at most 1000",
        ),
        ("mock.lamp.warmup_ms", int(3_600_001), "at most 3600000 ms"),
        (
            "mock.lamp.intensity",
            Value::Float(1e16),
            "at most 1000000000000000",
        ),
    ];
    for (key, value, expect) in cases {
        let mut t = small_table();
        set(&mut t, key, value);
        let e = rig::parse(&toml::to_string(&t).unwrap(), Path::new("bad.toml")).expect_err(key);
        let problems = e.problems();
        assert!(
            problems
                .iter()
                .any(|p| p.starts_with(&format!("{key}: ")) && p.contains(expect)),
            "{key}: expected `{expect}` in {problems:?}"
        );
    }
}

#[test]
fn extra_array_entries_are_refused_not_cut() {
    // serde filled fixed-size arrays from the first entries and dropped the rest.
    let cases: Vec<(&str, toml::Value, &str)> = vec![
        (
            "geometry.lamp_position_mm",
            toml::Value::try_from(vec![100.0, 350.0, 300.0, 4.0]).unwrap(),
            "has 4 entries; give exactly 3",
        ),
        (
            "geometry.grid_inner_corners",
            toml::Value::try_from(vec![9, 6, 1]).unwrap(),
            "has 3 entries; give exactly 2",
        ),
        (
            "geometry.tile_outline_mm",
            toml::Value::try_from(vec![
                vec![50.0, 30.0],
                vec![150.0, 30.0, 7.0],
                vec![150.0, 130.0],
            ])
            .unwrap(),
            "entry 2 has 3 numbers; give each as exactly 2",
        ),
        (
            "mock.camera.position_mm",
            toml::Value::try_from(vec![100.0, -250.0, 380.0, 1.0]).unwrap(),
            "has 4 entries; give exactly 3",
        ),
        (
            "mock.camera.look_at_mm",
            toml::Value::try_from(vec![100.0, 60.0]).unwrap(),
            "has 2 entries; give exactly 3",
        ),
        (
            "mock.tile.kd",
            toml::Value::try_from(vec![0.3, 0.2, 0.1, 0.5]).unwrap(),
            "has 4 entries; give exactly 3",
        ),
        (
            "mock.tile.ks",
            toml::Value::try_from(vec![0.3, 0.2, 0.1, 0.5]).unwrap(),
            "has 4 entries; give exactly 3",
        ),
        // Passed before: the device's range read from its first two entries.
        (
            "lamp.protocol.level_range",
            toml::Value::try_from(vec![0, 1000, 5]).unwrap(),
            "has 3 entries; give exactly 2",
        ),
        (
            "lamp.protocol.level_range",
            toml::Value::try_from(vec![1000]).unwrap(),
            "has 1 entries; give exactly 2",
        ),
    ];
    for (key, value, expect) in cases {
        let mut t = small_table();
        set(&mut t, key, value);
        let e = one_problem(&t);
        assert!(e.starts_with("bad.toml:"), "{key}: {e}");
        assert!(e.contains(&format!(": {key}: {expect}")), "{key}: {e}");
    }
}

#[test]
fn grid_of_1001x1000_corners_is_refused_naming_the_bound() {
    // It ran calibration for minutes.
    let mut t = small_table();
    set(
        &mut t,
        "geometry.grid_inner_corners",
        toml::Value::try_from(vec![1001, 1000]).unwrap(),
    );
    let e = one_problem(&t);
    assert!(
        e.starts_with(
            "bad.toml: geometry.grid_inner_corners: 1001x1000 inner corners: at most 200 a side"
        ),
        "{e}"
    );
}

#[test]
fn nul_or_newline_in_a_lamp_command_is_refused() {
    for (key, cmd, expect) in [
        ("lamp.commands.on", "ON\0", "has a NUL byte"),
        ("lamp.commands.off", "OFF\nON", "has a line break"),
        ("lamp.commands.state", "STATE?\r", "has a line break"),
        (
            "lamp.commands.identify",
            "*IDN?\u{1b}",
            "control character U+001B",
        ),
        ("lamp.commands.identify", "", "is empty"),
        ("lamp.commands.identify", &"X".repeat(300), "at most 256"),
    ] {
        let mut t = small_table();
        set(&mut t, key, cmd);
        let (code, lines) = rig_check(&t);
        assert_eq!(code, Some(1), "{key}");
        assert!(
            lines
                .iter()
                .any(|l| l.starts_with(&format!("bad.toml: {key}: ")) && l.contains(expect)),
            "{key}: {lines:?}"
        );
        // The message stays on one line however the command is spelt.
        assert!(lines.iter().all(|l| !l.contains('\0') && !l.contains('\r')));
    }
    let mut t = small_table();
    set(&mut t, "mock.lamp.identity", "GLINT\nOK");
    let (_, lines) = rig_check(&t);
    assert!(
        lines.iter().any(|l| l.contains("mock.lamp.identity")),
        "{lines:?}"
    );
}

#[test]
fn rig_name_dot_dot_or_too_long_is_refused() {
    for (name, expect) in [
        ("..", "must not start with `.`"),
        (".", "must not start with `.`"),
        (".hidden", "must not start with `.`"),
        ("a/b", "letters, digits"),
    ] {
        let mut t = small_table();
        set(&mut t, "rig.name", name);
        let e = one_problem(&t);
        assert!(
            e.starts_with("bad.toml: rig.name: ") && e.contains(expect),
            "{name}: {e}"
        );
    }
    let mut t = small_table();
    set(&mut t, "rig.name", "n".repeat(65));
    assert!(one_problem(&t).contains("at most 64"));
    set(&mut t, "rig.name", "n".repeat(64));
    assert_eq!(rig_check(&t).0, Some(0));
}

#[test]
fn device_paths_with_nul_or_too_long_are_refused() {
    let mut t = toml::from_str::<toml::Table>(
        &std::fs::read_to_string(root().join("rigs/lab-example.toml")).unwrap(),
    )
    .unwrap();
    set(&mut t, "camera.device", "/dev/video0\0x");
    set(&mut t, "lamp.port", format!("/dev/{}", "t".repeat(5000)));
    let (code, lines) = rig_check(&t);
    assert_eq!(code, Some(1));
    assert!(
        lines
            .iter()
            .any(|l| l.contains("camera.device") && l.contains("NUL")),
        "{lines:?}"
    );
    assert!(
        lines
            .iter()
            .any(|l| l.contains("lamp.port") && l.contains("4096 bytes")),
        "{lines:?}"
    );
    assert!(lines.iter().all(|l| l.chars().count() < 400), "{lines:?}");
}

#[test]
fn frame_timeout_shorter_than_an_exposure_is_refused() {
    let mut t = small_table();
    set(&mut t, "camera.frame_timeout_ms", 8);
    let e = one_problem(&t);
    assert!(
        e.contains("camera.frame_timeout_ms") && e.contains("longest exposure (8000 µs)"),
        "{e}"
    );
}

#[test]
fn rig_file_that_is_a_device_is_refused_not_read_forever() {
    let e = rig::load(Path::new("/dev/zero")).unwrap_err().to_string();
    assert!(
        e.contains("cannot read rig file /dev/zero") && e.contains("not a regular file"),
        "{e}"
    );
}

#[test]
fn every_shipped_rig_passes_rig_check() {
    let mut n = 0;
    for entry in std::fs::read_dir(root().join("rigs")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().and_then(|e| e.to_str()) != Some("toml") {
            continue;
        }
        let o = super::util::glint(&["rig", "check", path.to_str().unwrap()]);
        let out = String::from_utf8_lossy(&o.stdout);
        // A V4L2 (or nokhwa) rig is valid, but a build without the backend says it cannot
        // drive it.
        let missing = match rig::load(&path).unwrap().rig.camera.backend {
            rig::CameraBackend::V4l2 if !glint::devices::V4L2_BUILT => {
                Some(glint::devices::V4L2_MISSING)
            }
            rig::CameraBackend::Nokhwa if !glint::devices::NOKHWA_BUILT => {
                Some(glint::devices::NOKHWA_MISSING)
            }
            _ => None,
        };
        if let Some(missing) = missing {
            assert_eq!(o.status.code(), Some(1), "{}: {out}", path.display());
            assert!(out.contains(missing), "{}: {out}", path.display());
        } else {
            assert!(o.status.success(), "{}: {out}", path.display());
        }
        n += 1;
    }
    assert!(n >= 3, "found {n} rig files");
}

#[test]
fn a_long_wrong_value_is_quoted_short_on_one_line() {
    let text = std::fs::read_to_string(root().join("rigs/mock.toml")).unwrap();
    let long = format!("{}\\n{}", "A".repeat(5000), "B".repeat(5000));
    let e =
        parse_text_err(&text.replace("width = 1280", &format!("width = \"{long}\""))).to_string();
    assert!(!e.contains('\n') && e.chars().count() < 300, "{e}");
    assert!(
        e.contains("camera.width: invalid type: string") && e.contains('…'),
        "{e}"
    );
    let e = parse_text_err(&text.replace("[rig]", &format!("[rig]\n{} = 1", "k".repeat(5000))))
        .to_string();
    assert!(
        e.chars().count() < 300 && e.contains("unknown field"),
        "{e}"
    );
}

#[test]
fn a_table_given_as_an_empty_list_is_refused_not_read_as_defaults() {
    // Was: `mock.camera = []` (or `lamp.commands = []`, `mock = []`) parsed as a section of
    // defaults, and a list of numbers as a section filled by position.
    let mock = std::fs::read_to_string(root().join("rigs/mock.toml")).unwrap();
    let cases: Vec<(String, &str)> = vec![
        (
            mock.replacen("[lamp]", "[lamp]\ncommands = []", 1),
            "lamp.commands",
        ),
        (
            mock.replacen("[mock]\n", "[mock]\ngrid = []\n", 1),
            "mock.grid",
        ),
    ];
    for (text, key) in cases {
        let e = parse_text_err(&text).to_string();
        assert!(
            e.contains(&format!(
                "{key}: must be a table, not a list: a [{key}] section"
            )),
            "{key}: {e}"
        );
    }
    let mut t = mock_table();
    set(&mut t, "mock", toml::Value::Array(vec![]));
    let e = parse_err(&t);
    assert!(e.contains("mock: must be a table, not a list"), "{e}");
    // An empty section is the defaults, as before.
    let text = mock.replacen("[mock]\n", "[mock]\ngrid = {}\n", 1);
    assert!(rig::parse(&text, Path::new("ok.toml")).is_ok());
}

#[test]
fn a_syntax_error_names_its_section_on_one_line_without_control_characters() {
    // Was: the ` (in [section])` suffix copied the raw header line, CR and control bytes
    // included.
    let text = "[rig]\nname = \"x\"\n[F\u{1b}]\r\u{18}lamp.commands]\nfoo bar\n";
    let e = parse_text_err(text).to_string();
    assert!(e.contains("(in [F"), "{e}");
    assert!(!e.chars().any(|c| c.is_control()), "{e:?}");
    let long = format!("[{}]\nfoo bar\n", "s".repeat(5000));
    let e = parse_text_err(&long).to_string();
    assert!(e.chars().count() < 400, "{e}");
}

#[test]
fn the_guides_lamp_protocol_example_is_a_valid_rig_section() {
    // The guide's "Use it with a real lamp" shows every key of [lamp.protocol]; it must check.
    let readme = std::fs::read_to_string(super::util::root().join("docs/guide.md")).unwrap();
    let section = readme
        .split("## Use it with a real lamp")
        .nth(1)
        .expect("the guide has the section");
    let block = section
        .split("```toml\n")
        .nth(1)
        .and_then(|b| b.split("```").next())
        .expect("a toml block");
    let mut t = small_table();
    set(&mut t, "lamp.backend", "serial");
    set(&mut t, "lamp.port", "/dev/ttyUSB0");
    let mut text = toml::to_string(&t).unwrap();
    let lamp: toml::Table = toml::from_str(&format!("[lamp]\n{block}")).unwrap();
    // Merge the example's [lamp.protocol] and [lamp.commands] into the rig.
    let mut full: toml::Table = toml::from_str(&text).unwrap();
    let l = full["lamp"].as_table_mut().unwrap();
    for (k, v) in lamp["lamp"].as_table().unwrap() {
        l.insert(k.clone(), v.clone());
    }
    text = toml::to_string(&full).unwrap();
    let rig = rig::parse(&text, Path::new("readme.toml"))
        .unwrap_or_else(|e| panic!("{}", e.problems().join("\n")));
    let p = rig.lamp.resolved_protocol().unwrap();
    assert_eq!(p.preset.name(), "lumencor");
    assert_eq!(p.trailer.as_deref(), Some("OK"));
    assert_eq!(
        p.timeout(
            glint::devices::lamp_protocol::CommandKind::On,
            std::time::Duration::from_millis(1)
        ),
        std::time::Duration::from_millis(2000)
    );
}

/// A frame timeout no longer than the longest exposure is refused for a camera Glint drives
/// (every frame at that exposure would time out), not for an external one, whose photos
/// Glint never waits for: a lab's own tool that wrote a session with 3.3 s exposures had it
/// refused by `glint hdr` (found by the second scene family, seed 7013).
#[test]
fn a_frame_timeout_shorter_than_an_exposure_is_refused_only_where_glint_takes_the_frames() {
    let mut t = mock_table();
    set(
        &mut t,
        "bracket.exposures_us",
        toml::Value::Array(vec![815_000i64.into(), 3_262_753i64.into()]),
    );
    set(&mut t, "camera.max_exposure_us", 4_000_000i64);
    let e = parse_err(&t);
    assert!(
        e.contains("camera.frame_timeout_ms") && e.contains("no longer than the longest exposure"),
        "{e}"
    );
    let g = toml::to_string(&t["geometry"]).unwrap();
    let b = toml::to_string(&t["bracket"]).unwrap();
    let text = format!(
        "[rig]\nname = \"lab-import\"\n\n[camera]\nbackend = \"external\"\n\n[lamp]\nbackend = \"external\"\n\n[geometry]\n{g}\n[bracket]\n{b}"
    );
    if let Err(e) = rig::parse(&text, Path::new("lab-import.toml")) {
        panic!("an external camera's 3.3 s exposure refused: {e}");
    }
}
