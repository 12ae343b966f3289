//! The lamp firmware as a serial device: every line fault over a real pseudo-terminal,
//! byte for byte; `glint-mock lamp` as its own process (link, log, light file, signals);
//! and a camera lit through the light file by a lamp in another process.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use glint_mock::config::{Faults, LampConfig, LampPreset, MockConfig};
use glint_mock::lamp::{read_light_file, LightRecord};
use glint_mock::{light_file_for, Lab, LampFirmware, LampPhysics, SceneGeometry, SimPixels};
use serialport::TTYPort;

const LAUNCHER: &str = env!("CARGO_BIN_EXE_glint-mock");

fn firmware(preset: LampPreset, faults: Faults) -> (LampFirmware, Arc<LampPhysics>) {
    let physics = Arc::new(LampPhysics::new(Duration::ZERO));
    let cfg = LampConfig {
        preset,
        ..LampConfig::default()
    };
    let fw = LampFirmware::spawn(&cfg, &faults, Arc::clone(&physics), 9).unwrap();
    (fw, physics)
}

fn open(path: &str) -> TTYPort {
    serialport::new(path, 115_200)
        .timeout(Duration::from_millis(10))
        .open_native()
        .unwrap()
}

/// Everything that arrives until `n` bytes have, or `within` has passed.
fn read_n(port: &mut TTYPort, n: usize, within: Duration) -> Vec<u8> {
    let deadline = Instant::now() + within;
    let mut got = Vec::new();
    let mut buf = [0u8; 65536];
    while got.len() < n && Instant::now() < deadline {
        match port.read(&mut buf) {
            Ok(k) => got.extend_from_slice(&buf[..k]),
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
            Err(e) => panic!("{e}"),
        }
    }
    got
}

/// Exactly `want`, and nothing more for a while after it.
fn expect(port: &mut TTYPort, want: &[u8]) {
    let got = read_n(port, want.len(), Duration::from_secs(2));
    assert_eq!(
        String::from_utf8_lossy(&got),
        String::from_utf8_lossy(want),
        "bytes {got:?}"
    );
    expect_quiet(port, Duration::from_millis(60));
}

fn expect_quiet(port: &mut TTYPort, for_: Duration) {
    let extra = read_n(port, 1, for_);
    assert!(
        extra.is_empty(),
        "nothing more, got {:?}",
        String::from_utf8_lossy(&extra)
    );
}

/// Send `line` (with its LF) and expect exactly `reply`.
fn exchange(port: &mut TTYPort, line: &str, reply: &str) {
    port.write_all(format!("{line}\n").as_bytes()).unwrap();
    expect(port, reply.as_bytes());
}

#[test]
fn echo_comes_before_the_reply() {
    let (fw, _) = firmware(
        LampPreset::Glint,
        Faults {
            lamp_echo: true,
            ..Faults::default()
        },
    );
    let mut port = open(fw.port_path());
    exchange(&mut port, "ON", "ON\nOK\n");
    // As received, CR stripped: the echo ends in the reply terminator.
    port.write_all(b"STATE?\r\n").unwrap();
    expect(&mut port, b"STATE?\nON 1000\n");
}

#[test]
fn a_trailer_follows_every_reply_but_errors() {
    let (fw, _) = firmware(
        LampPreset::Glint,
        Faults {
            lamp_trailer: Some("OK".into()),
            ..Faults::default()
        },
    );
    let mut port = open(fw.port_path());
    exchange(&mut port, "*IDN?", "GLINT-MOCK-LAMP,1.0\nOK\n");
    exchange(&mut port, "ON", "OK\nOK\n");
    exchange(&mut port, "DANCE", "ERR 1 unknown command `DANCE`\n");
    exchange(
        &mut port,
        "LEVEL 2000",
        "ERR 2 level must be 0..1000, got 2000\n",
    );
}

#[test]
fn terminators_override_the_presets() {
    for (name, preset, want) in [
        ("cr", LampPreset::Glint, "OK\r"),
        ("crlf", LampPreset::Glint, "OK\r\n"),
        ("none", LampPreset::Glint, "OK"),
        ("lf", LampPreset::Lumencor, "E UNKNOWNCMD\n"),
    ] {
        let (fw, _) = firmware(
            preset,
            Faults {
                lamp_terminator: Some(name.into()),
                lamp_echo: name == "none",
                ..Faults::default()
            },
        );
        let mut port = open(fw.port_path());
        let echo = if name == "none" { "ON" } else { "" };
        exchange(&mut port, "ON", &format!("{echo}{want}"));
    }
}

#[test]
fn late_replies_come_late_and_later_commands_wait() {
    let (fw, _) = firmware(
        LampPreset::Glint,
        Faults {
            lamp_late_ms: 200,
            lamp_late_replies: vec![1],
            ..Faults::default()
        },
    );
    let mut port = open(fw.port_path());
    let sent = Instant::now();
    port.write_all(b"ON\nSTATE?\n").unwrap();
    let first = read_n(&mut port, 1, Duration::from_secs(2));
    let waited = sent.elapsed();
    assert!(
        waited >= Duration::from_millis(190) && waited < Duration::from_millis(600),
        "{waited:?}"
    );
    // The second, not late, follows as soon as the first is out.
    let mut rest = read_n(
        &mut port,
        "OK\nON 1000\n".len() - 1,
        Duration::from_millis(100),
    );
    let mut all = first;
    all.append(&mut rest);
    assert_eq!(String::from_utf8_lossy(&all), "OK\nON 1000\n");
    expect_quiet(&mut port, Duration::from_millis(60));
}

#[test]
fn every_reply_is_late_when_none_is_named() {
    let (fw, _) = firmware(
        LampPreset::Glint,
        Faults {
            lamp_late_ms: 120,
            ..Faults::default()
        },
    );
    let mut port = open(fw.port_path());
    for _ in 0..2 {
        let sent = Instant::now();
        port.write_all(b"STATE?\n").unwrap();
        expect_quiet(&mut port, Duration::from_millis(80));
        expect(&mut port, b"OFF\n");
        assert!(sent.elapsed() >= Duration::from_millis(115));
    }
}

#[test]
fn a_split_reply_comes_in_two_halves() {
    let (fw, _) = firmware(
        LampPreset::Lumencor,
        Faults {
            lamp_split_replies: vec![2],
            lamp_split_ms: 150,
            ..Faults::default()
        },
    );
    let mut port = open(fw.port_path());
    exchange(&mut port, "", "E UNKNOWNCMD\r\n");
    port.write_all(b"GET MODEL\n").unwrap();
    // "A MODEL Spectra III" is 19 bytes: 9, then 10 and the terminator.
    let first = read_n(&mut port, 9, Duration::from_secs(1));
    assert_eq!(String::from_utf8_lossy(&first), "A MODEL S");
    expect_quiet(&mut port, Duration::from_millis(100));
    expect(&mut port, b"pectra III\r\n");
}

#[test]
fn an_overlong_reply_is_printable_bytes_then_the_terminator() {
    let (fw, _) = firmware(
        LampPreset::Coolled,
        Faults {
            lamp_overlong_replies: vec![1],
            ..Faults::default()
        },
    );
    let mut port = open(fw.port_path());
    expect(
        &mut port,
        b"CoolLED precisExcite, Hello, pleased to meet you\r\n",
    );
    port.write_all(b"CSS?\n").unwrap();
    let got = read_n(&mut port, 100_002, Duration::from_secs(5));
    assert_eq!(got.len(), 100_002);
    assert!(got[..100_000].iter().all(|b| (0x21..0x7f).contains(b)));
    assert_eq!(&got[100_000..], b"\r\n");
    expect_quiet(&mut port, Duration::from_millis(60));
    exchange(&mut port, "CSS?", "CSSASF100BXF000CXF000\r\n");
}

#[test]
fn error_replies_are_the_presets_busy_and_do_nothing() {
    for (preset, on, busy) in [
        (LampPreset::Glint, "ON", "ERR 9 busy\n"),
        (LampPreset::Lumencor, "SET CH 0 1", "E BUSY\r\n"),
        (LampPreset::Coolled, "CSSASN100", "ERROR busy\r\n"),
    ] {
        let (fw, physics) = firmware(
            preset,
            Faults {
                lamp_error_replies: vec![1],
                lamp_trailer: Some("DONE".into()),
                ..Faults::default()
            },
        );
        let mut port = open(fw.port_path());
        if preset == LampPreset::Coolled {
            read_n(&mut port, 50, Duration::from_secs(1));
        }
        exchange(&mut port, on, busy);
        assert_eq!(physics.output(), 0.0, "{preset}: not executed");
        port.write_all(format!("{on}\n").as_bytes()).unwrap();
        read_n(&mut port, 1, Duration::from_secs(1));
        std::thread::sleep(Duration::from_millis(30));
        assert_eq!(physics.output(), 1.0, "{preset}: the retry is");
    }
}

#[test]
fn a_late_err_from_a_first_try() {
    let (fw, physics) = firmware(
        LampPreset::Glint,
        Faults {
            lamp_error_replies: vec![1],
            lamp_late_ms: 150,
            lamp_late_replies: vec![1],
            ..Faults::default()
        },
    );
    let mut port = open(fw.port_path());
    port.write_all(b"ON\n").unwrap();
    expect_quiet(&mut port, Duration::from_millis(100));
    expect(&mut port, b"ERR 9 busy\n");
    assert_eq!(physics.output(), 0.0);
    exchange(&mut port, "ON", "OK\n");
    assert_eq!(physics.output(), 1.0);
    assert_eq!(fw.commands(), ["ON", "ON"]);
}

#[test]
fn garbled_replies_are_seeded_noise_of_the_same_length() {
    let run = || {
        let (fw, _) = firmware(
            LampPreset::Glint,
            Faults {
                lamp_garble_replies: vec![2],
                ..Faults::default()
            },
        );
        let mut port = open(fw.port_path());
        exchange(&mut port, "ON", "OK\n");
        port.write_all(b"STATE?\n").unwrap();
        let got = read_n(&mut port, 8, Duration::from_secs(1));
        expect_quiet(&mut port, Duration::from_millis(60));
        got
    };
    let a = run();
    assert_eq!(a.len(), "ON 1000\n".len());
    assert!(a[..7].iter().all(|b| *b >= 0x80), "{a:?}");
    assert_eq!(a[7], b'\n');
    assert_eq!(run(), a, "the same seed garbles the same way");
}

#[test]
fn a_silent_lamp_answers_n_commands_then_nothing() {
    let (fw, _) = firmware(
        LampPreset::Glint,
        Faults {
            lamp_silent_after: Some(1),
            lamp_echo: true,
            ..Faults::default()
        },
    );
    let mut port = open(fw.port_path());
    exchange(&mut port, "ON", "ON\nOK\n");
    port.write_all(b"STATE?\n").unwrap();
    expect_quiet(&mut port, Duration::from_millis(200));
    assert_eq!(fw.commands(), ["ON", "STATE?"], "it still hears them");
}

#[test]
fn blank_lines_and_crs() {
    let (fw, _) = firmware(LampPreset::Glint, Faults::default());
    let mut port = open(fw.port_path());
    port.write_all(b"\r\n\nSTATE?\r\r\n").unwrap();
    // One trailing CR is stripped; glint's words are split at any whitespace.
    expect(
        &mut port,
        b"ERR 1 unknown command ``\nERR 1 unknown command ``\nOFF\n",
    );
    assert_eq!(fw.commands(), ["", "", "STATE?\r"]);
}

#[test]
fn lumencor_power_up_quirk_over_the_wire() {
    let (fw, physics) = firmware(LampPreset::Lumencor, Faults::default());
    let mut port = open(fw.port_path());
    exchange(&mut port, "GET MODEL", "E UNKNOWNCMD\r\n");
    exchange(&mut port, "GET MODEL", "A MODEL Spectra III\r\n");
    exchange(&mut port, "SET CHINT 0 400", "A CHINT 0 400\r\n");
    exchange(&mut port, "SET CH 0 1", "A CH 0 1\r\n");
    assert!((physics.output() - 0.4).abs() < 1e-12);
    // A reopened port is not a power-up.
    drop(port);
    let mut port = open(fw.port_path());
    exchange(&mut port, "GET CHACT 0", "A CHACT 0 1\r\n");
}

#[test]
fn coolled_greets_every_program_that_opens_its_port() {
    let (fw, physics) = firmware(LampPreset::Coolled, Faults::default());
    let hello = b"CoolLED precisExcite, Hello, pleased to meet you\r\n";
    for round in 0..3 {
        let mut port = open(fw.port_path());
        expect(&mut port, hello);
        exchange(&mut port, "CSSASN050", "CSSASN050BXF000CXF000\r\n");
        assert!((physics.output() - 0.5).abs() < 1e-12, "round {round}");
        // Left unread when the port closes: dropped, as on a serial line (once the
        // firmware has seen the close: a program reopening at once may still read it).
        port.write_all(b"CSS?\n").unwrap();
        std::thread::sleep(Duration::from_millis(30));
        drop(port);
        std::thread::sleep(Duration::from_millis(30));
    }
    // Opened with std::fs and raw termios, as any program may.
    let mut f = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(fw.port_path())
        .unwrap();
    raw(&f);
    let mut got = vec![0u8; hello.len()];
    f.read_exact(&mut got).unwrap();
    assert_eq!(got, hello);
    f.write_all(b"CSS?\n").unwrap();
    let mut got = vec![0u8; 23];
    f.read_exact(&mut got).unwrap();
    assert_eq!(got, b"CSSASN050BXF000CXF000\r\n");
}

fn raw(f: &std::fs::File) {
    use std::os::fd::AsRawFd;
    // SAFETY: termios of a descriptor `f` owns.
    unsafe {
        let mut t: libc::termios = std::mem::zeroed();
        assert_eq!(libc::tcgetattr(f.as_raw_fd(), &mut t), 0);
        libc::cfmakeraw(&mut t);
        assert_eq!(libc::tcsetattr(f.as_raw_fd(), libc::TCSANOW, &t), 0);
    }
}

/// A `glint-mock lamp` process; killed if a test fails before it ends it.
struct LampProcess {
    child: Child,
    link: PathBuf,
}

impl LampProcess {
    fn start(link: &Path, args: &[&str]) -> LampProcess {
        let child = Command::new(LAUNCHER)
            .arg("lamp")
            .arg("--link")
            .arg(link)
            .args(args)
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let mut p = LampProcess {
            child,
            link: link.to_path_buf(),
        };
        let deadline = Instant::now() + Duration::from_secs(5);
        while std::fs::read_link(link).is_err() {
            if let Some(status) = p.child.try_wait().unwrap() {
                let mut err = String::new();
                p.child
                    .stderr
                    .take()
                    .unwrap()
                    .read_to_string(&mut err)
                    .unwrap();
                panic!("the lamp ended ({status}): {err}");
            }
            assert!(Instant::now() < deadline, "the lamp did not link {link:?}");
            std::thread::sleep(Duration::from_millis(10));
        }
        p
    }

    fn port(&self) -> TTYPort {
        open(self.link.to_str().unwrap())
    }

    /// SIGTERM, and its exit code and stderr.
    fn terminate(mut self) -> (Option<i32>, String) {
        // SAFETY: signalling a child this test started and has not reaped.
        unsafe { libc::kill(self.child.id() as i32, libc::SIGTERM) };
        let status = self.child.wait().unwrap();
        let mut err = String::new();
        self.child
            .stderr
            .take()
            .unwrap()
            .read_to_string(&mut err)
            .unwrap();
        (status.code(), err)
    }
}

impl Drop for LampProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Until the light file says `fraction` (the firmware publishes after its reply).
fn light_becomes(light: &Path, fraction: f64) -> LightRecord {
    let deadline = Instant::now() + Duration::from_secs(2);
    loop {
        if let Some(r) = read_light_file(light) {
            if r.fraction == fraction {
                return r;
            }
        }
        assert!(
            Instant::now() < deadline,
            "{light:?}: {:?}",
            std::fs::read_to_string(light)
        );
        std::thread::sleep(Duration::from_millis(5));
    }
}

#[test]
fn the_lamp_process_serves_logs_lights_and_cleans_up() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("dev/lab/ttyLAMP0");
    let log = dir.path().join("lamp.log");
    let lamp = LampProcess::start(
        &link,
        &[
            "--log",
            log.to_str().unwrap(),
            "--warmup-ms",
            "0",
            "--identity",
            "ACME,7",
        ],
    );
    assert!(std::fs::read_link(&link).unwrap().starts_with("/dev/pts/"));
    let light = light_file_for(&link);
    assert_eq!(light, dir.path().join("dev/lab/ttyLAMP0.light"));
    assert_eq!(light_becomes(&light, 0.0).warmup_ms, 0);
    let mut port = lamp.port();
    exchange(&mut port, "*IDN?", "ACME,7\n");
    exchange(&mut port, "LEVEL 500", "OK\n");
    let before = glint_mock::lamp::monotonic_ns();
    exchange(&mut port, "ON", "OK\n");
    let on = light_becomes(&light, 0.5);
    assert!(on.since_ns >= before, "switched on after {before}: {on:?}");
    exchange(&mut port, "STATE?", "ON 500\n");
    exchange(&mut port, "OFF", "OK\n");
    light_becomes(&light, 0.0);
    drop(port);
    assert_eq!(
        std::fs::read_to_string(&log).unwrap(),
        "*IDN?\nLEVEL 500\nON\nSTATE?\nOFF\n"
    );
    let (code, err) = lamp.terminate();
    assert_eq!(code, Some(0), "{err}");
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(
        err.contains("a glint lamp controller on /dev/pts/") && err.contains("ttyLAMP0"),
        "{err}"
    );
    assert!(std::fs::symlink_metadata(&link).is_err(), "link removed");
    assert!(!light.exists(), "light file removed");
    assert!(
        !dir.path().join("dev").exists(),
        "the folders it made removed"
    );
    assert!(log.exists(), "the log stays");
}

const RIG: &str = r#"
[camera]
width = 64
height = 48
[lamp]
port = "unused"
[lamp.protocol]
preset = "lumencor"
reply_timeout_ms = 500
[geometry]
lamp_position_mm = [100.0, 350.0, 300.0]
tile_thickness_mm = 5.0
tile_outline_mm = [[50.0, 30.0], [150.0, 30.0], [150.0, 130.0], [50.0, 130.0]]
grid_inner_corners = [9, 6]
grid_square_mm = 25.0
[mock.lamp]
preset = "coolled"
warmup_ms = 0
[mock.faults]
lamp_echo = true
lamp_trailer = "OK"
"#;

#[test]
fn the_lamp_process_takes_the_rigs_settings_and_flags_override_them() {
    let dir = tempfile::tempdir().unwrap();
    let rig = dir.path().join("rig.toml");
    std::fs::write(&rig, RIG).unwrap();
    let link = dir.path().join("ttyA");
    // [lamp.protocol] preset over [mock.lamp] preset; the rig's faults.
    let lamp = LampProcess::start(&link, &["--rig", rig.to_str().unwrap()]);
    let mut port = lamp.port();
    exchange(&mut port, "", "\r\nE UNKNOWNCMD\r\n");
    exchange(
        &mut port,
        "GET MODEL",
        "GET MODEL\r\nA MODEL Spectra III\r\nOK\r\n",
    );
    drop(port);
    assert_eq!(lamp.terminate().0, Some(0));
    // Flags override the rig.
    let lamp = LampProcess::start(
        &link,
        &[
            "--rig",
            rig.to_str().unwrap(),
            "--preset",
            "coolled",
            "--trailer",
            "K",
            "--terminator",
            "lf",
        ],
    );
    let mut port = lamp.port();
    expect(
        &mut port,
        b"CoolLED precisExcite, Hello, pleased to meet you\n",
    );
    exchange(&mut port, "CSS?", "CSS?\nCSSASF100BXF000CXF000\nK\n");
    drop(port);
    assert_eq!(lamp.terminate().0, Some(0));
}

#[test]
fn the_lamp_process_refuses_bad_flags_and_paths_in_one_line() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("mine");
    std::fs::write(&file, "mine").unwrap();
    let bad_rig = dir.path().join("bad.toml");
    std::fs::write(
        &bad_rig,
        RIG.replace("preset = \"lumencor\"", "preset = \"philips\""),
    )
    .unwrap();
    let link = dir.path().join("ttyB");
    for (args, says) in [
        (
            vec!["--link", file.to_str().unwrap()],
            "is not a stale glint-mock lamp link; refusing to replace it",
        ),
        (
            vec!["--link", link.to_str().unwrap(), "--late-replies", "0,2"],
            "`0` is not a reply number",
        ),
        (
            vec!["--link", link.to_str().unwrap(), "--late-replies", "2"],
            "mock.faults.lamp_late_replies (--late-replies): names late replies but faults.lamp_late_ms is 0",
        ),
        (
            vec!["--link", link.to_str().unwrap(), "--preset", "philips"],
            "the simulated lamp speaks glint, lumencor, coolled",
        ),
        (
            vec!["--link", link.to_str().unwrap(), "--rig", bad_rig.to_str().unwrap()],
            "[lamp.protocol] preset = \"philips\" is not simulated",
        ),
        (
            vec!["--link", link.to_str().unwrap(), "--terminator", "lfcr"],
            "invalid value 'lfcr' for '--terminator",
        ),
        (
            vec!["--link", file.join("x").to_str().unwrap()],
            "cannot create",
        ),
        (vec!["--lnk", "x"], "unexpected argument '--lnk' found"),
        (
            vec![],
            "the following required arguments were not provided: --link <PATH>",
        ),
    ] {
        let out = Command::new(LAUNCHER)
            .arg("lamp")
            .args(&args)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(says), "{args:?}: {err}");
        assert_eq!(err.lines().count(), 1, "{err}");
    }
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "mine");
    assert!(std::fs::symlink_metadata(&link).is_err());
}

#[test]
fn a_stale_link_of_a_killed_lamp_is_replaced() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ttyC");
    std::os::unix::fs::symlink("/dev/pts/999", &link).unwrap();
    std::fs::write(
        light_file_for(&link),
        "glint-mock light v1 fraction=1 since_ns=0 warmup_ms=0\n",
    )
    .unwrap();
    let lamp = LampProcess::start(&link, &[]);
    let deadline = Instant::now() + Duration::from_secs(5);
    while !std::fs::read_link(&link).is_ok_and(|t| t != Path::new("/dev/pts/999")) {
        assert!(Instant::now() < deadline, "the stale link stayed");
        std::thread::sleep(Duration::from_millis(10));
    }
    let mut port = lamp.port();
    exchange(&mut port, "STATE?", "OFF\n");
    drop(port);
    assert_eq!(light_becomes(&light_file_for(&link), 0.0).since_ns, 0);
    assert_eq!(lamp.terminate().0, Some(0));
}

fn mean(p: &SimPixels) -> f64 {
    match p {
        SimPixels::U8(v) => v.iter().map(|x| *x as f64).sum::<f64>() / v.len() as f64,
        SimPixels::U16(v) => v.iter().map(|x| *x as f64).sum::<f64>() / v.len() as f64,
    }
}

#[test]
fn a_camera_is_lit_by_a_lamp_in_another_process() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ttyLAMP0");
    let lamp = LampProcess::start(&link, &["--warmup-ms", "0", "--preset", "coolled"]);
    let geometry = SceneGeometry {
        lamp_position_mm: [100.0, 350.0, 300.0],
        tile_thickness_mm: 5.0,
        tile_outline_mm: vec![[50.0, 30.0], [150.0, 30.0], [150.0, 130.0], [50.0, 130.0]],
        grid_inner_corners: [9, 6],
        grid_square_mm: 25.0,
        reference: None,
    };
    let mut cfg = MockConfig::default();
    cfg.camera.fx = 100.0;
    cfg.camera.fy = 100.0;
    let (mut camera, _operator) = Lab::camera_lit_by(
        &geometry,
        &cfg,
        80,
        60,
        8,
        3,
        Path::new("."),
        &light_file_for(&link),
    )
    .unwrap();
    let mut brightness = || {
        // Past the sensor's exposure latency.
        (0..3)
            .map(|_| camera.grab().unwrap())
            .last()
            .map(|f| mean(&f.pixels))
            .unwrap()
    };
    let dark = brightness();
    let mut port = lamp.port();
    read_n(&mut port, 50, Duration::from_secs(1));
    exchange(&mut port, "CSSASN100", "CSSASN100BXF000CXF000\r\n");
    light_becomes(&light_file_for(&link), 1.0);
    std::thread::sleep(Duration::from_millis(5));
    let lit = brightness();
    assert!(lit > dark + 10.0, "lit {lit}, dark {dark}");
    exchange(&mut port, "CSSASF100", "CSSASF100BXF000CXF000\r\n");
    light_becomes(&light_file_for(&link), 0.0);
    std::thread::sleep(Duration::from_millis(5));
    assert!(brightness() < dark + 2.0);
    // The lamp's process ends: its light goes out with it.
    drop(port);
    assert_eq!(lamp.terminate().0, Some(0));
    std::thread::sleep(Duration::from_millis(5));
    assert!(brightness() < dark + 2.0);
}
