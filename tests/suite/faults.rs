//! Every injected fault: a clear error, and a `failed` session holding every frame captured
//! before the fault, with valid checksums.

use glint::capture;
use glint::devices;
use glint::session::{self, State};

use super::util::{ledger, load, record, set, small_table, tempdir};

/// Capture with a fault set in `[mock.faults]`; returns (error text, frames kept, report).
fn capture_with(fault: &str, value: toml::Value) -> (String, usize, session::VerifyReport) {
    let dir = tempdir();
    let mut t = small_table();
    set(&mut t, &format!("mock.faults.{fault}"), value);
    let rig = load(dir.path(), &t);
    let out = dir.path().join("session");
    let devices = devices::open(&rig).unwrap();
    let err = capture::record(&rig, devices, &out, Default::default(), &mut |_| {})
        .err()
        .unwrap_or_else(|| panic!("{fault}: capture succeeded"));
    assert_eq!(err.session.as_deref(), Some(out.as_path()));
    let report = session::verify(&out).unwrap();
    let m = session::load(&out).unwrap();
    assert_eq!(m.state, State::Failed);
    assert_eq!(
        m.failure.as_deref(),
        Some(err.cause.as_str()),
        "the manifest records the reason"
    );
    assert!(report.intact(), "{fault}: {:?}", report.problems);
    assert_eq!(report.frames, err.frames);
    assert_eq!(
        std::fs::read_dir(out.join("frames")).unwrap().count(),
        err.frames,
        "no stray or partial files"
    );
    assert!(!err.to_string().contains('\n'), "one line: {err}");
    (err.to_string(), err.frames, report)
}

#[test]
fn dropped_frames() {
    let (e, frames, _) = capture_with("drop_frames", toml::Value::try_from(vec![9]).unwrap());
    assert!(
        e.contains("camera dropped 1 frame(s) (sequence 8 -> 10)")
            && e.contains("camera.max_dropped_frames = 0"),
        "{e}"
    );
    assert!(frames >= 1, "frames before the drop are kept: {frames}");
}

#[test]
fn dropped_frames_within_the_allowance_are_tolerated() {
    let dir = tempdir();
    let mut t = small_table();
    set(
        &mut t,
        "mock.faults.drop_frames",
        toml::Value::try_from(vec![9]).unwrap(),
    );
    set(&mut t, "camera.max_dropped_frames", 1);
    let rec = record(dir.path(), &t).unwrap();
    assert_eq!(rec.summary.dropped, 1);
    assert_eq!(rec.manifest.state, State::Complete);
}

#[test]
fn camera_stall() {
    let (e, frames, _) = capture_with("stall_at_frame", toml::Value::Integer(14));
    assert!(e.contains("camera stalled: no frame within 2000 ms"), "{e}");
    assert!(frames >= 2, "{frames}");
}

#[test]
fn ignored_exposure() {
    let (e, frames, _) = capture_with(
        "ignore_exposure_us",
        toml::Value::try_from(vec![1000]).unwrap(),
    );
    assert!(
        e.contains("camera did not apply exposure 1000 µs within 12 frames (frames report 500 µs)"),
        "{e}"
    );
    assert_eq!(frames, 3, "the 125, 250 and 500 µs frames are kept");
}

#[test]
fn lamp_stops_answering_mid_capture() {
    // Commands: *IDN?, LEVEL, ON, STATE? (verify), then STATE? before each group of frames.
    let (e, frames, _) = capture_with("lamp_silent_after", toml::Value::Integer(7));
    assert!(
        e.contains("did not answer `STATE?` (3 tries, 100 ms each)")
            && e.contains("reading the lamp state"),
        "{e}"
    );
    assert_eq!(frames, 3);
}

#[test]
fn lamp_garbles_every_try() {
    let (e, frames, _) = capture_with(
        "lamp_garble_replies",
        toml::Value::try_from(vec![6, 7, 8]).unwrap(),
    );
    // Replies 1-5: *IDN?, LEVEL, ON, STATE? (verify), STATE? before the 125 µs frame.
    assert!(e.contains("no usable reply to `STATE?` in 3 tries"), "{e}");
    assert_eq!(frames, 1);
}

#[test]
fn one_garbled_reply_is_survived_in_a_full_capture() {
    let dir = tempdir();
    let mut t = small_table();
    set(
        &mut t,
        "mock.faults.lamp_garble_replies",
        toml::Value::try_from(vec![2, 9]).unwrap(),
    );
    let rec = record(dir.path(), &t).unwrap();
    assert_eq!(rec.manifest.state, State::Complete);
    assert_eq!(rec.manifest.frames.len(), 15);
}

#[test]
fn a_session_folder_with_data_is_never_written_into() {
    let dir = tempdir();
    let rig = load(dir.path(), &small_table());
    let out = dir.path().join("existing");
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("precious.txt"), "data").unwrap();
    let e = capture::record(
        &rig,
        devices::open(&rig).unwrap(),
        &out,
        Default::default(),
        &mut |_| {},
    )
    .err()
    .unwrap();
    assert!(
        e.to_string().contains("already exists and is not empty"),
        "{e}"
    );
    assert!(e.session.is_none());
    assert_eq!(std::fs::read_dir(&out).unwrap().count(), 1);
    assert_eq!(
        std::fs::read_to_string(out.join("precious.txt")).unwrap(),
        "data"
    );
}

#[test]
fn corrupt_frame() {
    let (e, frames, _) = capture_with("corrupt_frames", toml::Value::try_from(vec![11]).unwrap());
    assert!(
        e.contains("camera delivered a corrupt frame (sequence 11: 160x120 8-bit RGB, 28800 samples, expected 160x120 8-bit RGB, 57600 samples)"),
        "{e}"
    );
    assert!(frames >= 2, "{frames}");
}

/// A sink that asks the engine to stop after `after` kept frames.
struct StopAfter {
    after: usize,
    kept: usize,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

impl capture::Sink for StopAfter {
    fn event(&mut self, _: capture::Event) {}
    fn frame(&mut self, _: capture::CapturedFrame) -> Result<(), capture::SinkError> {
        self.kept += 1;
        if self.kept == self.after {
            self.stop.store(true, std::sync::atomic::Ordering::SeqCst);
        }
        Ok(())
    }
}

/// Run the rig's whole plan on `engine`, keeping every frame, and return the error it ends with.
fn run_to_error(engine: &mut capture::Engine, rig: &glint::rig::LoadedRig) -> String {
    let mut sink = StopAfter {
        after: usize::MAX,
        kept: 0,
        stop: Default::default(),
    };
    engine
        .run(&capture::Plan::for_rig(&rig.rig), &mut sink)
        .unwrap_err()
        .to_string()
}

#[test]
fn interrupting_stops_at_the_next_frame_and_switches_the_lamp_off() {
    let dir = tempdir();
    let rig = load(dir.path(), &small_table());
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let mut engine = capture::Engine::new(
        devices::open(&rig).unwrap(),
        capture::EngineConfig::from_rig(&rig.rig),
    )
    .with_stop(stop.clone());
    let mut sink = StopAfter {
        after: 3,
        kept: 0,
        stop,
    };
    let e = engine
        .run(&capture::Plan::for_rig(&rig.rig), &mut sink)
        .unwrap_err();
    assert!(matches!(e, capture::CaptureError::Interrupted), "{e}");
    assert_eq!(sink.kept, 3);
    let commands = engine
        .devices
        .lab
        .as_ref()
        .unwrap()
        .firmware
        .as_ref()
        .unwrap()
        .commands();
    assert_eq!(
        &commands[commands.len() - 2..],
        ["OFF", "STATE?"],
        "the lamp is switched off and checked: {commands:?}"
    );
}

#[test]
fn an_interrupted_session_is_closed_as_failed() {
    let dir = tempdir();
    let rig = load(dir.path(), &small_table());
    let out = dir.path().join("s");
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let flag = stop.clone();
    let e = capture::record(&rig, devices::open(&rig).unwrap(), &out, stop, &mut |ev| {
        if let capture::Event::Frame { kept: 4, .. } = ev {
            flag.store(true, std::sync::atomic::Ordering::SeqCst);
        }
    })
    .err()
    .unwrap();
    assert!(
        e.to_string()
            .starts_with("interrupted by the user (session"),
        "{e}"
    );
    let m = session::load(&out).unwrap();
    assert_eq!(m.state, State::Failed);
    assert!(m.frames.len() >= 4);
    assert!(session::verify(&out).unwrap().intact());
}

/// A rig whose lamp really needs `lamp_ms` to warm up while the rig allows none, with the
/// camera on real time so the warm-up shows in the frames.
fn slow_lamp(lamp_ms: i64) -> toml::Table {
    let mut t = small_table();
    set(&mut t, "lamp.warmup_ms", 0);
    set(&mut t, "mock.lamp.warmup_ms", lamp_ms);
    set(&mut t, "mock.sensor.realtime", true);
    t
}

#[test]
fn a_lamp_slower_than_its_warmup_is_waited_for_and_named() {
    let dir = tempdir();
    let rig = load(dir.path(), &slow_lamp(300));
    let mut warnings = Vec::new();
    let rec = capture::record(
        &rig,
        devices::open(&rig).unwrap(),
        &dir.path().join("s"),
        Default::default(),
        &mut |e| {
            if let capture::Event::Warning(w) = e {
                warnings.push(w.clone());
            }
        },
    )
    .unwrap();
    // Ground truth: every lit frame kept was taken at full lamp output.
    let ledger = ledger(&rec);
    for f in rec
        .manifest
        .frames
        .iter()
        .filter(|f| f.kind != capture::FrameKind::Dark)
    {
        let e = ledger.iter().find(|e| e.sequence == f.sequence).unwrap();
        assert_eq!(
            e.lamp_output, 1.0,
            "{} was taken while the lamp warmed up",
            f.file
        );
    }
    assert!(
        warnings
            .iter()
            .any(|w| w.contains("longer than lamp.warmup_ms = 0 ms to settle")),
        "{warnings:?}"
    );
    assert!(
        ledger
            .iter()
            .any(|e| e.lamp_output > 0.0 && e.lamp_output < 1.0),
        "the ramp was seen"
    );
}

#[test]
fn a_lamp_still_warming_after_the_extra_wait_is_an_error() {
    // The bulb needs 3 s; the rig allows none, and the engine waits at most 1 s more. Its
    // level still rises ~1% a frame then. (Drifts below 0.5% a frame are not detected.)
    let dir = tempdir();
    let e = record(dir.path(), &slow_lamp(3000)).err().unwrap();
    assert!(
        e.to_string().starts_with("the light was still changing"),
        "{e}"
    );
    assert!(e.to_string().contains("raise lamp.warmup_ms"), "{e}");
    assert_eq!(e.frames, 0);
}

/// Every file below `dir` whose name marks it as a temporary (`.tmp-`).
fn temp_files(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if e.file_type().unwrap().is_dir() {
                todo.push(p);
            } else if e.file_name().to_string_lossy().contains(".tmp-") {
                out.push(p);
            }
        }
    }
    out
}

#[test]
fn lamp_level_zero_ends_failed_naming_the_lamp() {
    // Was: a dead bulb (or level 0) gave a `complete` session of black tile frames.
    let dir = tempdir();
    let mut t = small_table();
    set(&mut t, "lamp.level", 0);
    let rig = load(dir.path(), &t);
    let out = dir.path().join("s");
    let e = capture::record(
        &rig,
        devices::open(&rig).unwrap(),
        &out,
        Default::default(),
        &mut |_| {},
    )
    .err()
    .expect("a capture without light must not succeed");
    let text = e.to_string();
    assert!(
        e.cause.starts_with("the lamp on /dev/pts/") && e.cause.contains("(level 0) gave no light"),
        "{text}"
    );
    assert!(
        e.cause.contains("brighter than the lamp-off frames") && e.cause.contains("lamp.level"),
        "{text}"
    );
    assert!(!text.contains('\n'), "one line: {text}");
    let m = session::load(&out).unwrap();
    assert_eq!(m.state, State::Failed);
    assert_eq!(m.failure.as_deref(), Some(e.cause.as_str()));
    assert_eq!(m.lamp_off_confirmed, Some(true), "the lamp read back off");
    // The check runs once the bracket and its dark frames are in: 7 tile + 7 dark frames,
    // kept intact; the grid is never asked for.
    assert_eq!(m.frames.len(), 14);
    assert!(session::verify(&out).unwrap().intact());
}

#[test]
fn lamp_level_zero_without_dark_frames_is_refused_as_a_black_bracket() {
    // With no dark frames to compare with, a bracket black at every exposure is the sign.
    let dir = tempdir();
    let mut t = small_table();
    set(&mut t, "lamp.level", 0);
    set(&mut t, "bracket.dark_frames_per_exposure", 0);
    let e = record(dir.path(), &t).err().unwrap();
    assert!(
        e.cause
            .contains("(level 0) gave no light: the tile frames are black at every exposure"),
        "{e}"
    );
    assert_eq!(e.frames, 7);
}

#[test]
fn a_dim_but_real_lamp_passes_the_light_check() {
    // 3% of full output: dim, but the bracket's long exposures show it.
    let dir = tempdir();
    let mut t = small_table();
    set(&mut t, "lamp.level", 30);
    let rec = record(dir.path(), &t).unwrap();
    assert_eq!(rec.manifest.state, State::Complete);
}

#[test]
fn a_bracket_saturated_at_every_exposure_is_refused() {
    let dir = tempdir();
    let mut t = small_table();
    set(&mut t, "mock.lamp.intensity", 1.0e12);
    let e = record(dir.path(), &t).err().unwrap();
    assert!(
        e.cause
            .starts_with("the bracket is saturated at every exposure")
            && e.cause.contains("even at 125 µs")
            && e.cause.contains("lamp on /dev/pts/")
            && e.cause.contains("bracket.exposures_us"),
        "{e}"
    );
    let m = session::load(&dir.path().join("s")).unwrap();
    assert_eq!(m.state, State::Failed);
    assert_eq!(
        m.frames.len(),
        7,
        "the tile frames, checked before the darks"
    );
}

#[test]
fn garbled_on_read_back_still_sends_off() {
    // Was: ON acknowledged, its STATE? read-back garbled on every try: the engine never knew
    // the lamp was on, sent no OFF and said nothing.
    // Replies: 1 *IDN?, 2 LEVEL, 3 ON, 4-6 STATE? (the read-back, every try garbled).
    let dir = tempdir();
    let mut t = small_table();
    set(
        &mut t,
        "mock.faults.lamp_garble_replies",
        toml::Value::try_from(vec![4, 5, 6]).unwrap(),
    );
    let rig = load(dir.path(), &t);
    let mut engine = capture::Engine::new(
        devices::open(&rig).unwrap(),
        capture::EngineConfig::from_rig(&rig.rig),
    );
    let e = run_to_error(&mut engine, &rig);
    assert!(
        e.contains("switching the lamp on") && e.contains("no usable reply to `STATE?`"),
        "{e}"
    );
    let commands = engine
        .devices
        .lab
        .as_ref()
        .unwrap()
        .firmware
        .as_ref()
        .unwrap()
        .commands();
    assert_eq!(
        commands,
        [
            "*IDN?",
            "LEVEL 1000",
            "ON",
            "STATE?",
            "STATE?",
            "STATE?",
            "OFF",
            "STATE?"
        ],
        "OFF is sent and read back"
    );
    assert_eq!(engine.lamp_left_on(), None, "the lamp read back off");
    // Through a session: failed, with the lamp recorded as off.
    let (e, frames, _) = capture_with(
        "lamp_garble_replies",
        toml::Value::try_from(vec![4, 5, 6]).unwrap(),
    );
    assert!(e.contains("no usable reply to `STATE?`"), "{e}");
    assert!(!e.contains("may still be on"), "{e}");
    assert_eq!(frames, 0);
}

#[test]
fn an_unacknowledged_off_is_recorded_and_the_error_says_the_lamp_may_be_on() {
    // The lamp goes silent mid-capture: the OFF after the failure is not acknowledged.
    let dir = tempdir();
    let mut t = small_table();
    set(&mut t, "mock.faults.lamp_silent_after", 7);
    let e = record(dir.path(), &t).err().unwrap();
    assert!(
        e.cause.contains("reading the lamp state")
            && e.cause.contains("; the lamp on /dev/pts/")
            && e.cause.contains("may still be on: switching it off failed")
            && e.cause.contains("did not answer `OFF`"),
        "{e}"
    );
    let m = session::load(&dir.path().join("s")).unwrap();
    assert_eq!(m.state, State::Failed);
    assert_eq!(m.lamp_off_confirmed, Some(false));
    assert_eq!(m.failure.as_deref(), Some(e.cause.as_str()));
}

#[test]
fn a_complete_capture_records_the_lamp_off() {
    let dir = tempdir();
    let rec = record(dir.path(), &small_table()).unwrap();
    assert_eq!(rec.manifest.lamp_off_confirmed, Some(true));
    let m = session::load(&dir.path().join("s")).unwrap();
    assert_eq!(m.lamp_off_confirmed, Some(true));
    assert!(
        temp_files(&dir.path().join("s")).is_empty(),
        "the reserve is gone"
    );
}

#[test]
fn interrupting_a_long_warm_up_acts_at_once() {
    // Was: the warm-up was one sleep; Ctrl-C took effect only when it ended.
    let dir = tempdir();
    let mut t = small_table();
    set(&mut t, "lamp.warmup_ms", 5000);
    let rig = load(dir.path(), &t);
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let flag = stop.clone();
    let start = std::time::Instant::now();
    let out = dir.path().join("s");
    let setter = std::thread::spawn(move || {
        std::thread::sleep(std::time::Duration::from_millis(300));
        flag.store(true, std::sync::atomic::Ordering::SeqCst);
    });
    let e = capture::record(&rig, devices::open(&rig).unwrap(), &out, stop, &mut |_| {})
        .err()
        .unwrap();
    setter.join().unwrap();
    let took = start.elapsed();
    assert!(e.cause == "interrupted by the user", "{e}");
    assert!(
        took < std::time::Duration::from_millis(1500),
        "stopped {took:?} after the start, 5 s warm-up"
    );
    let m = session::load(&out).unwrap();
    assert_eq!(m.state, State::Failed);
    assert_eq!(m.lamp_off_confirmed, Some(true));
}

/// A tmpfs of `size` mounted on a fresh folder, unmounted when dropped; `None` (with a
/// SKIPPED line) where this machine does not let us mount one.
struct Tmpfs {
    dir: tempfile::TempDir,
}

impl Tmpfs {
    fn mount(size: &str) -> Option<Tmpfs> {
        let dir = tempdir();
        let status = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(dir.path())
            .stderr(std::process::Stdio::piped())
            .output();
        match status {
            Ok(o) if o.status.success() => Some(Tmpfs { dir }),
            Ok(o) => {
                eprintln!(
                    "SKIPPED: cannot mount a {size} tmpfs (needs root): {}",
                    String::from_utf8_lossy(&o.stderr).trim()
                );
                None
            }
            Err(e) => {
                eprintln!("SKIPPED: cannot run mount: {e}");
                None
            }
        }
    }
    fn path(&self) -> &std::path::Path {
        self.dir.path()
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount")
            .arg(self.dir.path())
            .status();
    }
}

#[test]
fn a_full_disk_leaves_a_failed_manifest_and_no_temp_file() {
    // Was: the disk filled, the error said so, and the manifest still said `capturing`
    // (rewriting it needed space) with a half-written frame's temporary file left behind.
    // The plan fits the 12 MB (a plan that does not is refused before it starts); the disk
    // fills during the capture, as when another program takes the space: after the second
    // frame a filler file takes every free byte.
    let Some(fs) = Tmpfs::mount("12m") else {
        return;
    };
    let dir = tempdir();
    let mut t = small_table();
    set(&mut t, "camera.bit_depth", 16);
    set(&mut t, "bracket.frames_per_exposure", 2);
    let rig = load(dir.path(), &t);
    let out = fs.path().join("s");
    let mut kept = 0;
    let e = capture::record_with(
        &rig,
        devices::open(&rig).unwrap(),
        &out,
        Default::default(),
        &mut |_| {},
        &mut |_| {
            kept += 1;
            if kept == 2 {
                use std::io::Write;
                let mut filler = std::fs::File::create(fs.path().join("filler")).unwrap();
                for chunk in [65536usize, 4096, 1] {
                    while filler.write_all(&vec![1u8; chunk]).is_ok() {}
                }
            }
        },
    )
    .err()
    .expect("the disk fills after the second frame");
    assert!(
        e.cause.starts_with("writing the session") && e.cause.contains("No space left on device"),
        "{e}"
    );
    assert!(e.manifest_updated, "{e}");
    assert!(e.to_string().ends_with("state failed)"), "{e}");
    let m = session::load(&out).unwrap();
    assert_eq!(m.state, State::Failed, "the manifest tells the truth");
    assert_eq!(m.failure.as_deref(), Some(e.cause.as_str()));
    assert_eq!(m.lamp_off_confirmed, Some(true));
    assert_eq!(temp_files(&out), Vec::<std::path::PathBuf>::new());
    let report = session::verify(&out).unwrap();
    assert!(report.intact(), "{:?}", report.problems);
    assert!(report.frames >= 2, "{}", report.frames);
    assert_eq!(report.frames, e.frames);
    assert_eq!(
        std::fs::read_dir(out.join("frames")).unwrap().count(),
        report.frames,
        "every frame on disk is listed"
    );
}

#[test]
fn a_session_whose_first_manifest_does_not_fit_leaves_nothing() {
    // Room for rig.toml only: the first manifest cannot be written. (Through
    // `capture::record` such a disk is refused before anything is written, the plan being
    // bigger than the free disk; here the session is started directly, as when the disk
    // fills between that check and the start.)
    let dir = tempdir();
    let rig = load(dir.path(), &small_table());
    let pages = rig.text.len().div_ceil(4096);
    let Some(fs) = Tmpfs::mount(&format!("{}k", pages * 4)) else {
        return;
    };
    let plan = capture::Plan::for_rig(&rig.rig);
    let camera = devices::CameraInfo::basic("test", 160, 120, 8, 3);
    for existing in [false, true] {
        let out = fs.path().join("s");
        if existing {
            std::fs::create_dir(&out).unwrap();
        }
        let e = session::SessionWriter::create(&out, &rig, &plan, camera.clone())
            .err()
            .unwrap();
        let text = e.to_string();
        assert!(
            text.starts_with(&format!("cannot start the session in {}", out.display()))
                && text.contains("the first manifest does not fit")
                && text.contains("No space left on device")
                && text.ends_with("nothing was left there"),
            "{text}"
        );
        if existing {
            assert_eq!(std::fs::read_dir(&out).unwrap().count(), 0, "left empty");
            std::fs::remove_dir(&out).unwrap();
        } else {
            assert!(!out.exists(), "the folder Glint made is gone");
        }
        assert_eq!(std::fs::read_dir(fs.path()).unwrap().count(), 0);
    }
}

#[test]
fn the_last_manifest_fits_on_a_disk_filled_to_the_last_byte() {
    // The failed frame frees nothing here (the disk is full before its first byte): only
    // the session's reserve makes room for the manifest that says `failed`.
    let Some(fs) = Tmpfs::mount("2m") else { return };
    let dir = tempdir();
    let rig = load(dir.path(), &small_table());
    let out = fs.path().join("s");
    let camera = devices::CameraInfo::basic("test", 160, 120, 8, 3);
    let plan = capture::Plan::for_rig(&rig.rig);
    let mut writer = session::SessionWriter::create(&out, &rig, &plan, camera).unwrap();
    // Fill the disk: 64 KB writes, then single pages, until nothing more fits.
    {
        use std::io::Write;
        let mut filler = std::fs::File::create(fs.path().join("filler")).unwrap();
        for chunk in [65536usize, 4096, 1] {
            while filler.write_all(&vec![1u8; chunk]).is_ok() {}
        }
    }
    let frame = capture::CapturedFrame {
        kind: capture::FrameKind::Tile,
        frame: devices::Frame {
            width: 160,
            height: 120,
            bit_depth: 8,
            channels: 3,
            pixels: devices::Pixels::U8((0..160 * 120 * 3).map(|i| (i * 7 % 251) as u8).collect()),
            sequence: 3,
            device_timestamp_us: None,
            exposure_us: Some(125),
        },
        exposure_requested_us: 125,
        exposure_reported_us: 125,
        verified_by: capture::Verification::Metadata,
        lamp: devices::LampState {
            on: true,
            level: 1000,
        },
        received: std::time::SystemTime::now(),
    };
    let e = writer
        .add_frame(&frame)
        .expect_err("the disk is full")
        .to_string();
    assert!(e.contains("No space left on device"), "{e}");
    assert_eq!(
        temp_files(&out).len(),
        1,
        "only the reserve: {:?}",
        temp_files(&out)
    );
    let m = writer
        .finish(Some(format!("writing the session: {e}")))
        .unwrap();
    assert_eq!(m.state, State::Failed);
    let on_disk = session::load(&out).unwrap();
    assert_eq!(on_disk.state, State::Failed);
    assert!(on_disk.failure.unwrap().contains("No space left on device"));
    assert!(temp_files(&out).is_empty(), "{:?}", temp_files(&out));
    assert!(session::verify(&out).unwrap().intact());
}

/// A lamp firmware that answers correctly, except that reading the reply to `ON` fails
/// with an I/O error; it records every command.
struct BreaksOnOn {
    line: Vec<u8>,
    pending: std::collections::VecDeque<u8>,
    on: bool,
    broken: bool,
    commands: std::sync::Arc<std::sync::Mutex<Vec<String>>>,
}

impl std::io::Read for BreaksOnOn {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        if std::mem::take(&mut self.broken) {
            return Err(std::io::Error::new(
                std::io::ErrorKind::BrokenPipe,
                "the port went away",
            ));
        }
        match self.pending.pop_front() {
            Some(b) => {
                buf[0] = b;
                Ok(1)
            }
            None => Err(std::io::ErrorKind::TimedOut.into()),
        }
    }
}

impl std::io::Write for BreaksOnOn {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        for &b in buf {
            if b != b'\n' {
                self.line.push(b);
                continue;
            }
            let cmd = String::from_utf8_lossy(&std::mem::take(&mut self.line)).into_owned();
            let reply = match cmd.as_str() {
                "ON" => {
                    self.on = true;
                    self.broken = true;
                    String::new()
                }
                "OFF" => {
                    self.on = false;
                    "OK".into()
                }
                "STATE?" if self.on => "ON 1000".into(),
                "STATE?" => "OFF".into(),
                "*IDN?" => "TEST-LAMP,1.0".into(),
                _ => "OK".into(),
            };
            if !reply.is_empty() {
                self.pending.extend(format!("{reply}\n").bytes());
            }
            self.commands.lock().unwrap().push(cmd);
        }
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

#[test]
fn an_io_error_in_reply_to_on_still_sends_off() {
    // ON was written; reading its reply failed. The lamp may be on: OFF must follow.
    let dir = tempdir();
    let rig = load(dir.path(), &small_table());
    let commands = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let mut devs = devices::open(&rig).unwrap();
    devs.lamp = Box::new(devices::serial_lamp::SerialLamp::new(
        BreaksOnOn {
            line: Vec::new(),
            pending: Default::default(),
            on: false,
            broken: false,
            commands: commands.clone(),
        },
        "test lamp".into(),
        devices::serial_lamp::LampPolicy::glint(std::time::Duration::from_millis(20), 2),
    ));
    let mut engine = capture::Engine::new(devs, capture::EngineConfig::from_rig(&rig.rig));
    let e = run_to_error(&mut engine, &rig);
    assert!(
        e.contains("switching the lamp on") && e.contains("the port went away"),
        "{e}"
    );
    let commands = commands.lock().unwrap().clone();
    let on = commands
        .iter()
        .position(|c| c == "ON")
        .expect("ON was sent");
    assert_eq!(
        &commands[on + 1..],
        ["OFF", "STATE?"],
        "OFF is sent and read back: {commands:?}"
    );
    assert_eq!(engine.lamp_left_on(), None, "the lamp read back off");
}
