//! The simulated V4L2 camera as programs that are not Glint see it: `glint-mock v4l2`
//! runs a Python client doing raw ioctls, mmap and poll (tests/v4l2_probe.py), and
//! `v4l2-ctl` when it is installed, against a small rig (tests/sim-v4l2.toml, copied with
//! its paths in a temp folder). `glint-mock lab` runs the same with the lamp as a process of
//! its own.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const LAUNCHER: &str = env!("CARGO_BIN_EXE_glint-mock");
const BY_ID: &str = "v4l/by-id/usb-Glint_Simulated_Camera_0001-video-index0";

/// The preload library: next to the launcher, else built into its own target folder (the
/// running `cargo test` holds the lock of the usual one). None, with a message, if neither.
fn library() -> Option<PathBuf> {
    static LIB: std::sync::OnceLock<Option<PathBuf>> = std::sync::OnceLock::new();
    LIB.get_or_init(|| {
        let exe = Path::new(LAUNCHER);
        let dir = exe.parent().unwrap();
        let beside = dir.join("libglint_sim_v4l2.so");
        if beside.is_file() {
            return Some(beside);
        }
        let target = dir.parent().unwrap().join("glint-sim-preload");
        let release = dir.file_name().is_some_and(|n| n == "release");
        let mut cargo = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
        cargo
            .args(["build", "--quiet", "-p", "glint-sim-v4l2", "--target-dir"])
            .arg(&target)
            .current_dir(env!("CARGO_MANIFEST_DIR"));
        if release {
            cargo.arg("--release");
        }
        let built = target
            .join(if release { "release" } else { "debug" })
            .join("libglint_sim_v4l2.so");
        match cargo.status() {
            Ok(s) if s.success() && built.is_file() => Some(built),
            other => {
                eprintln!(
                    "SKIPPED: libglint_sim_v4l2.so is not beside {LAUNCHER} and could not be built ({other:?}); run `cargo build -p glint-sim-v4l2`"
                );
                None
            }
        }
    })
    .clone()
}

struct Lab {
    dir: tempfile::TempDir,
    rig: PathBuf,
}

impl Lab {
    /// The test rig with its device and lamp in a temp folder, `extra` appended to
    /// `[mock.faults]`, `format` as the pixel format.
    fn new(format: &str, faults: &str) -> Lab {
        let dir = tempfile::tempdir().unwrap();
        let text = std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/sim-v4l2.toml"),
        )
        .unwrap()
        .replace(
            "/tmp/glint-sim-test",
            dir.path().join("dev").to_str().unwrap(),
        )
        .replace(
            "pixel_format = \"YUYV\"",
            &format!("pixel_format = \"{format}\""),
        )
        .replace("[mock.faults]\n", &format!("[mock.faults]\n{faults}\n"));
        let rig = dir.path().join("rig.toml");
        std::fs::write(&rig, text).unwrap();
        Lab { dir, rig }
    }

    fn device(&self) -> PathBuf {
        self.dir.path().join("dev/video0")
    }

    fn by_id(&self) -> PathBuf {
        self.dir.path().join("dev").join(BY_ID)
    }

    fn run(&self, launcher_args: &[&str], cmd: &[&str]) -> Output {
        self.launch("v4l2", launcher_args, cmd)
    }

    /// `glint-mock SUB --rig RIG ARGS -- CMD`, with LAMP (the lamp's port) and PROBE (the
    /// V4L2 probe) in CMD's environment.
    fn launch(&self, sub: &str, launcher_args: &[&str], cmd: &[&str]) -> Output {
        Command::new(LAUNCHER)
            .args([sub, "--rig"])
            .arg(&self.rig)
            .args(launcher_args)
            .arg("--")
            .args(cmd)
            .env("GLINT_SIM_V4L2_LIB", library().unwrap())
            .env("LAMP", self.port())
            .env(
                "PROBE",
                Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/v4l2_probe.py"),
            )
            .output()
            .unwrap()
    }

    fn port(&self) -> PathBuf {
        self.dir.path().join("dev/ttyLAMP0")
    }

    /// Run the Python probe; its JSON lines.
    fn probe(&self, fourcc: &str, w: u32, h: u32, frames: u32, timeout_ms: u32) -> Vec<String> {
        self.probe_with(&["--fast"], fourcc, w, h, frames, timeout_ms)
    }

    /// [`Lab::probe`] with the launcher's arguments given.
    fn probe_with(
        &self,
        launcher_args: &[&str],
        fourcc: &str,
        w: u32,
        h: u32,
        frames: u32,
        timeout_ms: u32,
    ) -> Vec<String> {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/v4l2_probe.py");
        let by_id = self.by_id();
        let args = [
            "python3",
            script.to_str().unwrap(),
            by_id.to_str().unwrap(),
            fourcc,
            &w.to_string(),
            &h.to_string(),
            &frames.to_string(),
            &timeout_ms.to_string(),
        ];
        let out = self.run(launcher_args, &args);
        let stdout = String::from_utf8_lossy(&out.stdout).to_string();
        assert!(
            !stdout.contains("\"error\""),
            "probe failed: {stdout}\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
        stdout.lines().map(str::to_string).collect()
    }
}

fn python_available() -> bool {
    Command::new("python3")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success())
}

/// Skip (with the reason) when the library or python3 is missing.
macro_rules! need {
    () => {
        if library().is_none() {
            return;
        }
        if !python_available() {
            eprintln!("SKIPPED: python3 is not installed");
            return;
        }
    };
}

/// A number field of a JSON line.
fn num(line: &str, key: &str) -> i64 {
    let at = line
        .find(&format!("\"{key}\": "))
        .unwrap_or_else(|| panic!("no {key} in {line}"));
    line[at + key.len() + 4..]
        .chars()
        .take_while(|c| c.is_ascii_digit() || *c == '-')
        .collect::<String>()
        .parse()
        .unwrap()
}

fn events<'a>(lines: &'a [String], event: &str) -> Vec<&'a String> {
    let tag = format!("\"event\": \"{event}\"");
    lines.iter().filter(|l| l.contains(&tag)).collect()
}

const FLAG_ERROR: i64 = 0x40;
const FLAG_TIMESTAMP_MONOTONIC: i64 = 0x2000;

#[test]
fn a_raw_v4l2_client_streams_frames_through_the_by_id_link() {
    need!();
    let lab = Lab::new("YUYV", "");
    let lines = lab.probe("YUYV", 320, 240, 6, 2000);
    let cap = events(&lines, "cap")[0];
    assert!(cap.contains("\"driver\": \"glint-sim\""), "{cap}");
    assert!(
        cap.contains("\"card\": \"Glint Simulated Camera\""),
        "{cap}"
    );
    assert!(cap.contains("\"bus\": \"platform:glint-sim\""), "{cap}");
    assert_eq!(num(cap, "device_caps") & 0x0400_0001, 0x0400_0001);
    let fmt = events(&lines, "fmt")[0];
    assert_eq!(num(fmt, "bytesperline"), 640);
    assert_eq!(num(fmt, "sizeimage"), 320 * 240 * 2);
    assert_eq!(num(fmt, "colorspace"), 8); // SRGB
    assert_eq!(num(fmt, "ycbcr_enc"), 1); // 601
    assert_eq!(num(fmt, "quantization"), 2); // limited range
                                             // exposure_time_absolute is refused while auto_exposure is not manual, then taken.
    assert_eq!(num(events(&lines, "exposure_while_auto")[0], "errno"), 13);
    assert_eq!(num(events(&lines, "exposure")[0], "value"), 40);
    let frames = events(&lines, "frame");
    assert_eq!(frames.len(), 6);
    let mut last_ts = 0;
    for (i, f) in frames.iter().enumerate() {
        assert_eq!(num(f, "sequence"), i as i64, "{f}");
        assert_eq!(num(f, "bytesused"), 320 * 240 * 2);
        assert_eq!(num(f, "field"), 1);
        assert_eq!(
            num(f, "flags") & (FLAG_ERROR | FLAG_TIMESTAMP_MONOTONIC),
            FLAG_TIMESTAMP_MONOTONIC
        );
        let ts = num(f, "timestamp_us");
        assert!(ts > last_ts, "time stamps rise: {f}");
        last_ts = ts;
    }
    assert_eq!(events(&lines, "done").len(), 1);
    // The launcher removed what it made.
    assert!(!lab.device().exists());
    assert!(std::fs::symlink_metadata(lab.by_id()).is_err());
    assert!(std::fs::symlink_metadata(lab.dir.path().join("dev/ttyLAMP0")).is_err());
}

#[test]
fn replay_repeats_the_frames_of_a_state_with_the_sequence_counting_on() {
    need!();
    let lab = Lab::new("YUYV", "");
    let lines = lab.probe_with(&["--fast", "--replay", "3"], "YUYV", 320, 240, 12, 2000);
    let frames = events(&lines, "frame");
    assert_eq!(frames.len(), 12);
    let seqs: Vec<i64> = frames.iter().map(|f| num(f, "sequence")).collect();
    assert_eq!(seqs, (0..12).collect::<Vec<i64>>(), "no gap, no repeat");
    let crc: Vec<i64> = frames.iter().map(|f| num(f, "crc")).collect();
    // Once three frames of the (steady) state are made they come round again, in turn.
    let tail = &crc[6..];
    assert_eq!(tail[0..3], tail[3..6], "{crc:?}");
    assert!(
        tail[0] != tail[1] && tail[1] != tail[2],
        "noise differs within the cycle: {crc:?}"
    );
    let ts: Vec<i64> = frames.iter().map(|f| num(f, "timestamp_us")).collect();
    assert!(
        ts.windows(2).all(|w| w[1] > w[0]),
        "time stamps rise: {ts:?}"
    );
}

#[test]
fn dropped_and_corrupt_frames_show_as_a_driver_shows_them() {
    need!();
    let lab = Lab::new("YUYV", "drop_frames = [2]\ncorrupt_frames = [3]");
    let lines = lab.probe("YUYV", 320, 240, 4, 2000);
    let frames = events(&lines, "frame");
    let seqs: Vec<i64> = frames.iter().map(|f| num(f, "sequence")).collect();
    assert_eq!(
        seqs,
        [0, 1, 3, 4],
        "a dropped frame is a gap in the sequence"
    );
    let corrupt = frames[2];
    assert_eq!(num(corrupt, "flags") & FLAG_ERROR, FLAG_ERROR, "{corrupt}");
    assert!(num(corrupt, "bytesused") < 320 * 240 * 2);
    assert_eq!(num(frames[3], "flags") & FLAG_ERROR, 0);
}

#[test]
fn a_stalled_camera_times_out_and_nonblocking_dqbuf_says_eagain() {
    need!();
    let lab = Lab::new("YUYV", "stall_at_frame = 2");
    let lines = lab.probe("YUYV", 320, 240, 5, 300);
    assert_eq!(events(&lines, "frame").len(), 2);
    let timeout = events(&lines, "timeout");
    assert_eq!(timeout.len(), 1, "{lines:?}");
    assert_eq!(num(timeout[0], "dqbuf_errno"), 11);
}

#[test]
fn an_unplugged_camera_answers_enodev_and_pollerr_pollhup() {
    need!();
    let lab = Lab::new("YUYV", "unplug_at_frame = 2");
    let lines = lab.probe("YUYV", 320, 240, 5, 2000);
    assert_eq!(events(&lines, "frame").len(), 2);
    let gone = events(&lines, "gone");
    assert_eq!(gone.len(), 1, "{lines:?}");
    assert_eq!(num(gone[0], "revents") & 0x18, 0x18, "POLLERR | POLLHUP");
    assert_eq!(num(gone[0], "dqbuf_errno"), 19);
    assert_eq!(num(events(&lines, "after_gone")[0], "querycap_errno"), 19);
}

#[test]
fn a_mono_rig_sends_luma_formats() {
    need!();
    let lab = Lab::new("Y16", "");
    let lines = lab.probe("Y16", 160, 120, 2, 2000);
    let fmt = events(&lines, "fmt")[0];
    assert!(fmt.contains("\"fourcc\": \"Y16 \""), "{fmt}");
    assert_eq!(num(fmt, "width"), 160);
    assert_eq!(num(fmt, "bytesperline"), 320);
    assert_eq!(num(fmt, "quantization"), 1); // full range
    let frames = events(&lines, "frame");
    assert_eq!(frames.len(), 2);
    assert_eq!(num(frames[0], "bytesused"), 160 * 120 * 2);
}

#[test]
fn the_launcher_passes_the_exit_status_and_sets_the_environment() {
    if library().is_none() {
        return;
    }
    let lab = Lab::new("YUYV", "");
    let out = lab.run(
        &[],
        &[
            "sh",
            "-c",
            "test -e \"$GLINT_SIM_V4L2_DEVICE\" && test -S \"$GLINT_SIM_V4L2_SOCKET\" && glint-mock scene remove-tile && glint-mock scene place-tile && exit 7",
        ],
    );
    assert_eq!(
        out.status.code(),
        Some(7),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn the_launcher_never_replaces_a_users_file() {
    if library().is_none() {
        return;
    }
    let lab = Lab::new("YUYV", "");
    std::fs::create_dir_all(lab.device().parent().unwrap()).unwrap();
    std::fs::write(lab.device(), "mine").unwrap();
    let out = lab.run(&[], &["true"]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("refusing to replace"), "{err}");
    assert_eq!(err.lines().count(), 1, "{err}");
    assert_eq!(std::fs::read_to_string(lab.device()).unwrap(), "mine");
}

#[test]
fn scene_without_a_launcher_says_so() {
    let out = Command::new(LAUNCHER)
        .args(["scene", "place-tile"])
        .env_remove("GLINT_SIM_V4L2_SOCKET")
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no glint-mock launcher"), "{err}");
}

#[test]
fn v4l2_ctl_sees_a_camera_and_streams_from_it() {
    if library().is_none() {
        return;
    }
    if Command::new("v4l2-ctl").arg("--version").output().is_err() {
        eprintln!("SKIPPED: v4l2-ctl is not installed (apt-get install v4l-utils)");
        return;
    }
    let lab = Lab::new("YUYV", "");
    let dev = lab.by_id();
    let script = format!(
        "v4l2-ctl -d {d} --all && v4l2-ctl -d {d} --list-formats-ext --list-ctrls-menus && v4l2-ctl -d {d} -c auto_exposure=1,exposure_time_absolute=20 && v4l2-ctl -d {d} -C exposure_time_absolute && v4l2-ctl -d {d} --stream-mmap --stream-count=5",
        d = dev.display()
    );
    let out = lab.run(&["--fast"], &["sh", "-c", &script]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        text.contains("Card type        : Glint Simulated Camera"),
        "{text}"
    );
    assert!(text.contains("'YUYV' (YUYV 4:2:2)"), "{text}");
    assert!(
        text.contains("exposure_time_absolute 0x009a0902 (int)"),
        "{text}"
    );
    assert!(text.contains("3: Aperture Priority Mode"), "{text}");
    assert!(text.contains("exposure_time_absolute: 20"), "{text}");
}

/// `glint-mock lab`: the lamp is a process of its own at the rig's lamp.port.
#[test]
fn lab_runs_cmd_with_the_lamp_as_its_own_process() {
    if library().is_none() {
        return;
    }
    let lab = Lab::new("YUYV", "");
    let log = lab.dir.path().join("lamp.log");
    let pid_file = lab.dir.path().join("lamp.pid");
    let script = format!(
        "test -L \"$LAMP\" && test -f \"$LAMP.light\" && test -e \"$GLINT_SIM_V4L2_DEVICE\" \
         && test -S \"$GLINT_SIM_V4L2_SOCKET\" && kill -0 \"$GLINT_MOCK_LAMP_PID\" \
         && test \"$GLINT_MOCK_LAMP_LOG\" = {log} && echo \"$GLINT_MOCK_LAMP_PID\" > {pid} \
         && printf 'ON\\n' > \"$LAMP\" \
         && for i in 1 2 3 4 5 6 7 8 9 10; do grep -q 'fraction=1 ' \"$LAMP.light\" && break; sleep 0.05; done \
         && grep -q 'fraction=1 ' \"$LAMP.light\" \
         && glint-mock scene remove-tile && glint-mock scene place-tile && exit 7",
        log = log.display(),
        pid = pid_file.display()
    );
    let out = lab.launch(
        "lab",
        &["--lamp-log", log.to_str().unwrap(), "--echo"],
        &["sh", "-c", &script],
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(7), "{err}");
    assert!(
        err.contains("glint-mock lamp: a glint lamp controller on /dev/pts/"),
        "{err}"
    );
    assert_eq!(std::fs::read_to_string(&log).unwrap(), "ON\n");
    // After it: the lamp has ended, its link and light are gone, and so is the camera.
    let pid: i32 = std::fs::read_to_string(&pid_file)
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    // SAFETY: signal 0 only asks whether the process exists.
    assert_ne!(unsafe { libc::kill(pid, 0) }, 0, "the lamp ended");
    assert!(std::fs::symlink_metadata(lab.port()).is_err());
    assert!(!lab.dir.path().join("dev/ttyLAMP0.light").exists());
    assert!(!lab.device().exists());
    assert!(
        !lab.dir.path().join("dev").exists(),
        "the folders made removed"
    );
}

#[test]
fn lab_lights_the_camera_with_the_lamp_process() {
    need!();
    let lab = Lab::new("YUYV", "");
    let script = format!(
        "python3 \"$PROBE\" {dev} YUYV 320 240 2 2000 && printf 'ON\\n' > \"$LAMP\" \
         && sleep 0.4 && python3 \"$PROBE\" {dev} YUYV 320 240 2 2000",
        dev = lab.by_id().display()
    );
    let out = lab.launch("lab", &["--fast"], &["sh", "-c", &script]);
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(
        out.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let lines: Vec<String> = text.lines().map(str::to_string).collect();
    let means: Vec<i64> = events(&lines, "frame")
        .iter()
        .map(|f| num(f, "mean"))
        .collect();
    assert_eq!(means.len(), 4, "{text}");
    assert!(
        means[2] > means[1] + 5 && means[3] > means[1] + 5,
        "brighter once the lamp is on: {means:?}"
    );
}

#[test]
fn killing_the_lamp_process_unplugs_the_lamp() {
    if library().is_none() {
        return;
    }
    let lab = Lab::new("YUYV", "");
    let script = "printf 'ON\\n' > \"$LAMP\" && kill -9 \"$GLINT_MOCK_LAMP_PID\" && sleep 0.3 \
                  && test ! -e \"$LAMP.light\" && test ! -L \"$LAMP\" && exit 5";
    let out = lab.launch("lab", &[], &["sh", "-c", script]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(5), "{err}");
    assert!(err.contains("ended (signal: 9"), "{err}");
}

#[test]
fn lab_says_what_is_wrong_in_one_line() {
    if library().is_none() {
        return;
    }
    // No lamp port.
    let lab = Lab::new("YUYV", "");
    let text = std::fs::read_to_string(&lab.rig).unwrap();
    let no_port: String = text
        .lines()
        .filter(|l| !l.starts_with("port ="))
        .map(|l| format!("{l}\n"))
        .collect();
    std::fs::write(&lab.rig, no_port).unwrap();
    let out = lab.launch("lab", &[], &["true"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("[lamp] has no port"), "{err}");
    assert_eq!(err.lines().count(), 1, "{err}");
    // A lamp that cannot start: its log cannot be opened.
    let lab = Lab::new("YUYV", "");
    let out = lab.launch(
        "lab",
        &["--lamp-log", lab.dir.path().to_str().unwrap()],
        &["true"],
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    let last = err.lines().last().unwrap();
    assert!(
        last.starts_with("glint-mock: the lamp process ended (exit status: 2) before it linked")
            && last.contains("cannot open mock.lamp.command_log"),
        "{err}"
    );
    assert!(std::fs::symlink_metadata(lab.port()).is_err());
    assert!(!lab.device().exists());
    // A preset the lamp does not speak.
    let lab = Lab::new("YUYV", "");
    let text = std::fs::read_to_string(&lab.rig).unwrap();
    std::fs::write(
        &lab.rig,
        text.replace(
            "[geometry]",
            "[lamp.protocol]\npreset = \"philips\"\n\n[geometry]",
        ),
    )
    .unwrap();
    let out = lab.launch("lab", &[], &["true"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("is not simulated") && err.contains("--preset"),
        "{err}"
    );
    assert_eq!(
        lab.launch("lab", &["--preset", "coolled"], &["true"])
            .status
            .code(),
        Some(0)
    );
}

#[test]
fn v4l2_lamp_speaks_the_rigs_preset() {
    if library().is_none() {
        return;
    }
    let lab = Lab::new("YUYV", "");
    let text = std::fs::read_to_string(&lab.rig).unwrap();
    std::fs::write(
        &lab.rig,
        text.replace(
            "[geometry]",
            "[lamp.protocol]\npreset = \"coolled\"\n\n[geometry]",
        ),
    )
    .unwrap();
    let script = "exec 3<>\"$LAMP\" && stty raw -echo <&3 && printf 'CSS?\\n' >&3 && sleep 0.2 \
                  && dd bs=4096 count=1 <&3 2>/dev/null | grep -q '^CSSASF100BXF000CXF000' && exit 4";
    let out = lab.run(&[], &["sh", "-c", script]);
    assert_eq!(
        out.status.code(),
        Some(4),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
