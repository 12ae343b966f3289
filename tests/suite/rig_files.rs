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
    let mut t = small_table();
    set(&mut t, "lamp.backend", "serial");
    let e = rig::parse(&toml::to_string(&t).unwrap(), Path::new("x.toml")).unwrap_err();
    let all = e.problems().join("\n");
    assert!(
        all.contains("lamp.port") && all.contains("backend = \"mock\" for both"),
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
