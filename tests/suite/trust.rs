//! The session folder is a trust boundary: a manifest cannot make Glint read
//! outside the session or write anywhere but into it; stages look at the session's state
//! and refuse inconsistent sessions with one line naming what to fix.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use serde_json::Value;

use super::util::{err, glint, ok, record, small_table, tempdir};

/// A complete session of the small mock rig in `dir/s` (rig file `dir/rig.toml`).
fn session(dir: &Path) -> PathBuf {
    record(dir, &small_table()).unwrap();
    dir.join("s")
}

/// Rewrite `s/manifest.json` through `edit` (as another tool, or an attacker, could).
fn edit_manifest(s: &Path, edit: impl FnOnce(&mut Value)) {
    let path = s.join("manifest.json");
    let mut v: Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    edit(&mut v);
    std::fs::write(&path, serde_json::to_vec_pretty(&v).unwrap()).unwrap();
}

fn sha(path: &Path) -> String {
    glint::session::sha256_hex(&std::fs::read(path).unwrap())
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Every stage on the session fails with one error line containing each of `want`, and
/// no stage panics.
fn every_stage_refuses(sess: &Path, want: &[&str]) {
    for stage in ["hdr", "calibrate", "fit", "validate", "report", "response"] {
        let out = glint(&[stage, s(sess)]);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!stderr.contains("panicked"), "{stage}: {stderr}");
        let e = err(&out);
        for w in want {
            assert!(e.contains(w), "{stage}: {e}\nshould contain: {w}");
        }
    }
}

/// `glint session verify` fails, printing a problem containing `want`.
fn verify_fails(sess: &Path, want: &str) {
    let out = glint(&["session", "verify", s(sess)]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(!out.status.success(), "verify passed:\n{text}");
    assert!(
        text.lines()
            .any(|l| l.starts_with("problem:") && l.contains(want)),
        "{text}\nshould name: {want}"
    );
}

#[test]
fn manifest_frame_at_etc_passwd_fails_verify_and_every_stage() {
    let dir = tempdir();
    let sess = session(dir.path());
    let target = Path::new("/etc/passwd");
    let sum = sha(target);
    edit_manifest(&sess, |m| {
        m["frames"][0]["file"] = "/etc/passwd".into();
        m["frames"][0]["sha256"] = sum.into();
    });
    verify_fails(&sess, "/etc/passwd");
    every_stage_refuses(&sess, &["/etc/passwd", "relative path inside the session"]);
    assert!(!sess.join("hdr").exists() && !sess.join("calib").exists());
}

#[test]
fn manifest_frame_at_dotdot_fails_verify_and_every_stage() {
    let dir = tempdir();
    let sess = session(dir.path());
    // A real frame moved out of the session, with its right checksum.
    let first = glint::session::load(&sess).unwrap().frames[0].file.clone();
    std::fs::copy(sess.join(&first), dir.path().join("x")).unwrap();
    edit_manifest(&sess, |m| m["frames"][0]["file"] = "../x".into());
    verify_fails(&sess, "../x");
    every_stage_refuses(&sess, &["`../x`", "relative path inside the session"]);
    assert!(!sess.join("hdr").exists());
}

#[test]
fn frame_through_a_symlink_leaving_the_session_is_refused() {
    let dir = tempdir();
    let sess = session(dir.path());
    let outside = dir.path().join("outside");
    std::fs::create_dir(&outside).unwrap();
    let first = glint::session::load(&sess).unwrap().frames[0].file.clone();
    std::fs::copy(sess.join(&first), outside.join("f.png")).unwrap();
    std::os::unix::fs::symlink(&outside, sess.join("elsewhere")).unwrap();
    edit_manifest(&sess, |m| m["frames"][0]["file"] = "elsewhere/f.png".into());
    verify_fails(&sess, "symbolic link");
    every_stage_refuses(&sess, &["elsewhere/f.png", "symbolic link"]);
}

#[test]
fn a_frame_that_is_a_link_to_a_file_outside_is_refused_by_every_stage() {
    // Was: a dark frame listed as `frames/link.png`, a link to a copy outside with its
    // checksum: the stages that do not read dark frames (calibrate, fit, report) went on.
    let dir = tempdir();
    let sess = session(dir.path());
    let m = glint::session::load(&sess).unwrap();
    let (k, dark) = m
        .frames
        .iter()
        .enumerate()
        .find(|(_, f)| f.kind == glint::capture::FrameKind::Dark)
        .map(|(k, f)| (k, f.file.clone()))
        .unwrap();
    let outside = dir.path().join("frame.png");
    std::fs::copy(sess.join(&dark), &outside).unwrap();
    std::os::unix::fs::symlink(&outside, sess.join("frames/link.png")).unwrap();
    let sum = sha(&outside);
    edit_manifest(&sess, |m| {
        m["frames"][k]["file"] = "frames/link.png".into();
        m["frames"][k]["sha256"] = sum.into();
    });
    verify_fails(&sess, "symbolic link");
    every_stage_refuses(&sess, &["frames/link.png", "is a symbolic link"]);
}

#[test]
fn dev_zero_as_a_frame_is_refused_quickly() {
    let dir = tempdir();
    let sess = session(dir.path());
    // Directly, and as a link inside the session.
    std::os::unix::fs::symlink("/dev/zero", sess.join("frames/zero.png")).unwrap();
    for file in ["/dev/zero", "frames/zero.png"] {
        edit_manifest(&sess, |m| m["frames"][0]["file"] = file.into());
        let t = Instant::now();
        verify_fails(&sess, file);
        let e = err(&glint(&["hdr", s(&sess)]));
        assert!(e.contains(file), "{e}");
        assert!(
            t.elapsed() < Duration::from_secs(20),
            "{file}: {:?}",
            t.elapsed()
        );
    }
    let e = err(&glint(&["hdr", s(&sess)]));
    assert!(e.contains("symbolic link"), "{e}");
}

#[test]
fn symlinked_hdr_gets_nothing_written_through_it() {
    let dir = tempdir();
    let sess = session(dir.path());
    let elsewhere = dir.path().join("elsewhere");
    std::fs::create_dir(&elsewhere).unwrap();
    std::os::unix::fs::symlink(&elsewhere, sess.join("hdr")).unwrap();
    let rig = dir.path().join("rig.toml");
    let e = err(&glint(&["hdr", s(&sess), "--rig", s(&rig)]));
    assert!(e.contains("symbolic link") && e.contains("hdr"), "{e}");
    let e = err(&glint(&["response", s(&sess)]));
    assert!(e.contains("symbolic link"), "{e}");
    // The same for calib/.
    std::os::unix::fs::symlink(&elsewhere, sess.join("calib")).unwrap();
    // (hdr/ is still a link too, which calibrate reads hdr/response.json through: it may
    // name either.)
    let e = err(&glint(&["calibrate", s(&sess)]));
    assert!(
        e.contains("symbolic link") && (e.contains("calib") || e.contains("`hdr`")),
        "{e}"
    );
    assert_eq!(
        std::fs::read_dir(&elsewhere).unwrap().count(),
        0,
        "nothing written through the links"
    );
    // `session verify` names the links.
    let out = ok(&glint(&["session", "verify", s(&sess)]));
    assert!(
        out.contains("hdr: a symbolic link") && out.contains("calib: a symbolic link"),
        "{out}"
    );
}

#[test]
fn hdr_on_a_session_whose_rig_file_points_elsewhere_writes_nothing_there() {
    let dir = tempdir();
    let sess = session(dir.path());
    let elsewhere = dir.path().join("elsewhere");
    std::fs::create_dir(&elsewhere).unwrap();
    std::fs::copy(dir.path().join("rig.toml"), elsewhere.join("rig.toml")).unwrap();
    edit_manifest(&sess, |m| {
        m["rig_file"] = elsewhere.join("rig.toml").to_str().unwrap().into()
    });
    let out = glint(&["hdr", s(&sess), "--json"]);
    let summary: Value = serde_json::from_str(&ok(&out)).unwrap();
    assert_eq!(summary["response"]["kind"], "recovered");
    assert!(summary["profile_written"].is_null());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("note:") && stderr.contains("--rig FILE"),
        "one note on how to keep a profile: {stderr}"
    );
    let out = ok(&glint(&["response", s(&sess), "--samples", "200"]));
    assert!(out.contains("No camera profile stored"), "{out}");
    let names: Vec<_> = std::fs::read_dir(&elsewhere)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(
        names,
        ["rig.toml"],
        "nothing written beside the manifest's rig_file"
    );
    assert!(!dir.path().join("profiles").exists());
}

/// The session as if the capture had been killed after `keep` tile frames: state
/// `capturing`, no end time, the later frames' files gone from the manifest.
fn kill_after(sess: &Path, keep: usize) {
    edit_manifest(sess, |m| {
        m["state"] = "capturing".into();
        m["finished"] = Value::Null;
        m["frames"].as_array_mut().unwrap().truncate(keep);
    });
}

#[test]
fn hdr_on_a_killed_session_refuses_without_allow_incomplete_and_stores_no_profile() {
    let dir = tempdir();
    let sess = session(dir.path());
    kill_after(&sess, 2);
    let rig = dir.path().join("rig.toml");
    let e = err(&glint(&["hdr", s(&sess), "--rig", s(&rig)]));
    assert!(
        e.contains("`capturing`") && e.contains("--allow-incomplete"),
        "{e}"
    );
    assert!(!dir.path().join("profiles").exists(), "no profile stored");
    assert!(!sess.join("hdr").exists(), "nothing written");
    every_stage_refuses(&sess, &["`capturing`", "--allow-incomplete"]);
    // A failed capture is refused in the same way, with its reason.
    edit_manifest(&sess, |m| {
        m["state"] = "failed".into();
        m["failure"] = "lamp did not answer".into();
    });
    let e = err(&glint(&["hdr", s(&sess), "--rig", s(&rig)]));
    assert!(
        e.contains("`failed`") && e.contains("lamp did not answer"),
        "{e}"
    );
}

#[test]
fn a_killed_session_with_allow_incomplete_proceeds_with_a_warning_and_stores_no_profile() {
    let dir = tempdir();
    let sess = session(dir.path());
    kill_after(&sess, 5);
    let rig = dir.path().join("rig.toml");
    let out = glint(&[
        "hdr",
        s(&sess),
        "--rig",
        s(&rig),
        "--allow-incomplete",
        "--json",
    ]);
    let summary: Value = serde_json::from_str(&ok(&out)).unwrap();
    assert_eq!(summary["state"], "capturing");
    assert_eq!(summary["exposures_us"].as_array().unwrap().len(), 5);
    assert!(summary["profile_written"].is_null());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("warning: the session is `capturing`"),
        "{stderr}"
    );
    assert!(
        stderr.contains("not stored as the camera profile"),
        "{stderr}"
    );
    assert!(!dir.path().join("profiles").exists(), "no profile stored");
    // --replace-profile is refused for it, writing nothing.
    let e = err(&glint(&[
        "response",
        s(&sess),
        "--rig",
        s(&rig),
        "--allow-incomplete",
        "--replace-profile",
    ]));
    assert!(e.contains("not complete"), "{e}");
    assert!(!dir.path().join("profiles").exists());
    // The report shows the state at the top.
    ok(&glint(&["report", s(&sess), "--allow-incomplete"]));
    let html = std::fs::read_to_string(sess.join("report/index.html")).unwrap();
    let banner = html.find("Incomplete session: state capturing").unwrap();
    assert!(banner < html.find("<h2>").unwrap(), "before every section");
}

#[test]
fn a_profile_is_not_stored_from_a_bracket_of_two_exposures() {
    let dir = tempdir();
    let mut t = small_table();
    super::util::set(
        &mut t,
        "bracket.exposures_us",
        toml::Value::try_from(vec![1000, 4000]).unwrap(),
    );
    record(dir.path(), &t).unwrap();
    let sess = dir.path().join("s");
    let rig = dir.path().join("rig.toml");
    let out = glint(&["hdr", s(&sess), "--rig", s(&rig), "--json"]);
    let summary: Value = serde_json::from_str(&ok(&out)).unwrap();
    assert!(summary["profile_written"].is_null());
    assert!(
        summary["warnings"][0]
            .as_str()
            .unwrap()
            .contains("2 different exposure(s); a profile needs at least 3"),
        "{summary}"
    );
    assert!(!dir.path().join("profiles").exists());
    let e = err(&glint(&[
        "response",
        s(&sess),
        "--rig",
        s(&rig),
        "--replace-profile",
    ]));
    assert!(e.contains("needs at least 3"), "{e}");
}

#[test]
fn lamp_in_the_tile_plane_in_an_embedded_rig_is_a_clear_error_not_a_panic() {
    let dir = tempdir();
    let sess = session(dir.path());
    glint::hdr::run::run(&sess, &Default::default(), &mut |_| {}).unwrap();
    glint::calib::run::run_session(&sess, None).unwrap();
    edit_manifest(&sess, |m| {
        let z = m["rig"]["geometry"]["tile_thickness_mm"].clone();
        m["rig"]["geometry"]["lamp_position_mm"][2] = z;
    });
    let out = glint(&["fit", s(&sess)]);
    assert!(!String::from_utf8_lossy(&out.stderr).contains("panicked"));
    let e = err(&out);
    assert!(
        e.contains("manifest.json") && e.contains("geometry.lamp_position_mm"),
        "{e}"
    );
    verify_fails(&sess, "geometry.lamp_position_mm");
}

#[test]
fn a_frame_listed_twice_is_refused() {
    let dir = tempdir();
    let sess = session(dir.path());
    edit_manifest(&sess, |m| {
        let f0 = m["frames"][0].clone();
        m["frames"][1]["file"] = f0["file"].clone();
        m["frames"][1]["sha256"] = f0["sha256"].clone();
    });
    verify_fails(&sess, "listed twice");
    every_stage_refuses(&sess, &["frame 1", "listed twice"]);
}

#[test]
fn two_tile_frames_labelled_with_one_exposure_are_refused() {
    let dir = tempdir();
    let sess = session(dir.path());
    edit_manifest(&sess, |m| {
        for k in ["exposure_requested_us", "exposure_reported_us"] {
            m["frames"][1][k] = m["frames"][0][k].clone();
        }
    });
    let e = err(&glint(&["hdr", s(&sess)]));
    assert!(e.contains("2 tile frames are labelled with"), "{e}");
    verify_fails(&sess, "labelled with");
}

/// Writes a picture to a path.
type WriteImage = Box<dyn Fn(&Path)>;

#[test]
fn a_frame_whose_size_depth_or_channels_differ_from_the_manifest_is_refused() {
    let dir = tempdir();
    let sess = session(dir.path());
    let file = glint::session::load(&sess).unwrap().frames[0].file.clone();
    let path = sess.join(&file);
    let cases: [(&str, WriteImage); 3] = [
        (
            "is a 16x16 8-bit image but the manifest lists it as 160x120 8-bit",
            Box::new(|p| image::RgbImage::new(16, 16).save(p).unwrap()),
        ),
        (
            "is a 160x120 16-bit image",
            Box::new(|p| {
                image::ImageBuffer::<image::Rgb<u16>, Vec<u16>>::new(160, 120)
                    .save(p)
                    .unwrap()
            }),
        ),
        (
            "has 1 channel (grey), but a session's frames are RGB",
            Box::new(|p| image::GrayImage::new(160, 120).save(p).unwrap()),
        ),
    ];
    for (want, write) in cases {
        std::fs::remove_file(&path).unwrap();
        write(&path);
        // The checksum fits: only the contents disagree with the manifest.
        let sum = sha(&path);
        edit_manifest(&sess, |m| m["frames"][0]["sha256"] = sum.into());
        let e = err(&glint(&["hdr", s(&sess)]));
        assert!(
            e.contains(want) && e.contains(&file),
            "{e}\nshould contain: {want}"
        );
        verify_fails(&sess, want);
    }
    assert!(!sess.join("hdr").exists());
}

#[test]
fn junk_camera_json_is_refused_naming_the_file() {
    let dir = tempdir();
    let sess = session(dir.path());
    glint::hdr::run::run(&sess, &Default::default(), &mut |_| {}).unwrap();
    glint::calib::run::run_session(&sess, None).unwrap();
    let cam = sess.join("calib/camera.json");
    let good: Value = serde_json::from_slice(&std::fs::read(&cam).unwrap()).unwrap();
    std::fs::write(&cam, b"{\"format\": \"glint-camera\", ").unwrap();
    for stage in ["fit", "report"] {
        let e = err(&glint(&[stage, s(&sess)]));
        assert!(
            e.contains("calib/camera.json") && e.contains("not JSON") && e.contains("EOF"),
            "{stage}: {e}"
        );
    }
    // Values that parse but cannot be: a negative square size, a negative focal length.
    let mut v = good.clone();
    v["grid"]["square_mm"] = (-5.0).into();
    std::fs::write(&cam, serde_json::to_vec(&v).unwrap()).unwrap();
    let e = err(&glint(&["fit", s(&sess)]));
    assert!(
        e.contains("camera.json") && e.contains("square size must be positive"),
        "{e}"
    );
    let mut v = good.clone();
    v["calibration"]["intrinsics"]["fx"] = (-300.0).into();
    std::fs::write(&cam, serde_json::to_vec(&v).unwrap()).unwrap();
    let e = err(&glint(&["fit", s(&sess)]));
    assert!(
        e.contains("fx = -300") && e.contains("focal length must be positive"),
        "{e}"
    );
    let e = err(&glint(&["calibrate", s(&sess), "--intrinsics", s(&cam)]));
    assert!(e.contains("focal length must be positive"), "{e}");
    assert!(!sess.join("fit").exists());
}

#[test]
fn junk_derived_json_is_named_with_its_parse_error_not_taken_as_missing() {
    let dir = tempdir();
    let sess = session(dir.path());
    glint::hdr::run::run(&sess, &Default::default(), &mut |_| {}).unwrap();
    glint::calib::run::run_session(&sess, None).unwrap();
    for (file, stage) in [
        ("hdr/response.json", "fit"),
        ("hdr/summary.json", "fit"),
        ("hdr/summary.json", "report"),
    ] {
        let p = sess.join(file);
        let good = std::fs::read(&p).unwrap();
        std::fs::write(&p, b"{\"format\": ").unwrap();
        let e = err(&glint(&[stage, s(&sess)]));
        assert!(e.contains(file) && e.contains("EOF"), "{stage} {file}: {e}");
        std::fs::write(&p, good).unwrap();
    }
    // fit.json and validation.json: junk is named, not "not validated yet".
    std::fs::create_dir_all(sess.join("fit")).unwrap();
    std::fs::write(sess.join("fit/fit.json"), b"{\"chosen\": ").unwrap();
    for stage in ["validate", "report"] {
        let e = err(&glint(&[stage, s(&sess)]));
        assert!(
            e.contains("fit/fit.json") && e.contains("EOF"),
            "{stage}: {e}"
        );
    }
    std::fs::remove_file(sess.join("fit/fit.json")).unwrap();
    std::fs::create_dir_all(sess.join("validation")).unwrap();
    std::fs::write(sess.join("validation/validation.json"), b"nonsense").unwrap();
    let e = err(&glint(&["report", s(&sess)]));
    assert!(
        e.contains("validation/validation.json") && e.contains("not JSON"),
        "{e}"
    );
}

#[test]
fn verify_reports_leftovers_anywhere_in_the_session() {
    let dir = tempdir();
    let sess = session(dir.path());
    std::fs::create_dir_all(sess.join("hdr")).unwrap();
    std::fs::write(sess.join("hdr/.radiance.exr.tmp-4242"), b"half").unwrap();
    std::fs::create_dir_all(sess.join(".report.new-77")).unwrap();
    std::fs::write(sess.join("frames/extra.png"), b"stray").unwrap();
    let out = ok(&glint(&["session", "verify", s(&sess)]));
    for want in [
        "hdr/.radiance.exr.tmp-4242: left over from an interrupted write",
        ".report.new-77: left over from an interrupted write",
        "frames/extra.png: not listed in the manifest",
    ] {
        assert!(out.contains(want), "{out}\nshould contain: {want}");
    }
}

#[test]
fn verify_lists_a_frame_name_or_failure_with_line_breaks_on_one_line() {
    // Was: a frame file `a\nb\rc` that is not there was listed as
    // "a<LF>b<CR>c: No such file or directory", over three lines.
    let dir = tempdir();
    let sess = session(dir.path());
    edit_manifest(&sess, |m| {
        m["frames"][0]["file"] = "a\nb\rc".into();
        m["state"] = "failed".into();
        m["failure"] = format!("the lamp\nsaid {}", "x".repeat(5000)).into();
    });
    let rep = glint::session::verify(&sess).unwrap();
    assert!(
        rep.problems.iter().any(|p| p.contains("`a\\nb\\rc`")),
        "{:?}",
        rep.problems
    );
    for p in rep.problems.iter().chain(&rep.warnings) {
        assert!(
            !p.contains(['\n', '\r']) && p.chars().count() < 600,
            "{p:?}"
        );
    }
    assert!(rep
        .warnings
        .iter()
        .any(|w| w.starts_with("capture failed: the lamp said x")));
}

/// Every file below `dir` (not following links) with its bytes' checksum.
fn contents(dir: &Path) -> Vec<(PathBuf, String)> {
    let mut v: Vec<(PathBuf, String)> = std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .map(|e| (e.path(), sha(&e.path())))
        .collect();
    v.sort();
    v
}

/// A processed session (hdr, calibration, fit, validation) of the small mock rig.
fn processed(dir: &Path) -> PathBuf {
    let sess = session(dir);
    glint::hdr::run::run(&sess, &Default::default(), &mut |_| {}).unwrap();
    glint::calib::run::run_session(&sess, None).unwrap();
    let fit = glint::fit::run::FitOptions {
        draws: 2,
        ..Default::default()
    };
    glint::fit::run::run(&sess, &fit).unwrap();
    glint::validate::run(&sess, &Default::default(), &mut |_| {}).unwrap();
    sess
}

/// A derived folder moved out of the session and a link left in its
/// place (`mv S/hdr X; ln -s X S/hdr`) is read by no stage: every stage that reads a file
/// of it (fit, calibrate, validate, report, export) fails on one line naming the link and
/// what to do, and nothing is written through it. Before, fit, calibrate and validate
/// read X/* and exited 0, report followed linked calib/, fit/ and validation/, export a
/// linked fit/.
#[test]
fn a_derived_folder_linked_outside_the_session_is_read_by_no_stage() {
    let dir = tempdir();
    let sess = processed(dir.path());
    let exported = dir.path().join("exported.json");
    for (folder, readers) in [
        ("hdr", &["fit", "calibrate", "validate", "report"][..]),
        ("calib", &["fit", "validate", "report", "export"][..]),
        ("fit", &["validate", "report", "export"][..]),
        ("validation", &["report"][..]),
    ] {
        let away = dir.path().join(format!("away-{folder}"));
        std::fs::rename(sess.join(folder), &away).unwrap();
        std::os::unix::fs::symlink(&away, sess.join(folder)).unwrap();
        let before = contents(&away);
        for stage in readers {
            let mut args = vec![*stage, s(&sess)];
            if *stage == "export" {
                args.extend(["--to", "json", "--out", s(&exported)]);
            }
            let e = err(&glint(&args));
            assert!(
                e.contains(&format!("`{folder}` is a symbolic link"))
                    && e.contains("put the folder itself in its place"),
                "{stage} with {folder}/ a link: {e}"
            );
        }
        assert_eq!(
            contents(&away),
            before,
            "{folder}: nothing written through the link"
        );
        std::fs::remove_file(sess.join(folder)).unwrap();
        std::fs::rename(&away, sess.join(folder)).unwrap();
    }
    // One file a link (to a copy outside): refused by name, as frames are.
    let away = dir.path().join("fit.json");
    std::fs::rename(sess.join("fit/fit.json"), &away).unwrap();
    std::os::unix::fs::symlink(&away, sess.join("fit/fit.json")).unwrap();
    for stage in ["validate", "report"] {
        let e = err(&glint(&[stage, s(&sess)]));
        assert!(
            e.contains("fit/fit.json") && e.contains("is a symbolic link"),
            "{stage}: {e}"
        );
    }
}

/// The camera profile beside the rig (`profiles/NAME`) is read through no link either: a
/// linked `profiles/` folder is refused by `glint hdr --rig`, naming it.
#[test]
fn a_linked_profiles_folder_beside_the_rig_is_refused() {
    let dir = tempdir();
    let sess = session(dir.path());
    let rig = dir.path().join("rig.toml");
    ok(&glint(&["hdr", s(&sess), "--rig", s(&rig)]));
    let away = dir.path().join("away-profiles");
    std::fs::rename(dir.path().join("profiles"), &away).unwrap();
    std::os::unix::fs::symlink(&away, dir.path().join("profiles")).unwrap();
    let e = err(&glint(&["hdr", s(&sess), "--rig", s(&rig)]));
    assert!(e.contains("`profiles` is a symbolic link"), "{e}");
}
