//! Work bounded by what a file says: `glint hdr` reads a session's
//! frames one at a time (its memory does not grow with the number of frames listed), and
//! a manifest listing more frames than its plan keeps, or a plan beyond a rig's bounds, is
//! refused with one line naming the limit and the count before anything is decoded.
//!
//! The sessions are the mock rig's (1280x960, 3.7 MB a frame decoded) with dark frames
//! appended as hard links to the session's own dark frames, as the issue made them.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use serde_json::{json, Value};

use super::util::{glint, ok, root};

/// Address space given to `glint hdr` (RLIMIT_AS). Measured on 2026-12-06 (`ulimit -v`)
/// on the session of [`hdr_memory_does_not_grow_with_the_dark_frames_listed`]: this build
/// merges it within 300 MB of address space (about 100 MB resident, as the plain session);
/// e6cdebf aborts at 1000 and at 1400 MB ("memory allocation ... failed"; 1.23 GB
/// resident when unlimited).
const BUDGET_MB: u64 = 600;

/// The mock rig's session, captured once (glint capture --rig rigs/mock.toml).
fn base() -> &'static Path {
    static BASE: OnceLock<PathBuf> = OnceLock::new();
    BASE.get_or_init(|| {
        let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("hdr-memory-base");
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(d.parent().unwrap()).unwrap();
        ok(&glint(&[
            "capture",
            "--rig",
            root().join("rigs/mock.toml").to_str().unwrap(),
            "--out",
            d.to_str().unwrap(),
        ]));
        d
    })
}

/// A copy of the base session (frames hard-linked) at `out` with `n` dark frames appended,
/// each a hard link to one of the session's dark frames. `planned`: spread over the
/// bracket's exposures, and the plan (and the embedded rig) keep that many dark frames at
/// each (within a rig's bounds); else all links of the first dark frame, the plan unchanged
/// (the session).
fn with_darks(out: &Path, n: usize, planned: bool) -> PathBuf {
    let base = base();
    let _ = std::fs::remove_dir_all(out);
    std::fs::create_dir_all(out.join("frames")).unwrap();
    let mut m: Value =
        serde_json::from_slice(&std::fs::read(base.join("manifest.json")).unwrap()).unwrap();
    let frames = m["frames"].as_array().unwrap().clone();
    for f in &frames {
        let file = f["file"].as_str().unwrap();
        std::fs::hard_link(base.join(file), out.join(file)).unwrap();
    }
    let darks: Vec<&Value> = frames.iter().filter(|f| f["kind"] == "dark").collect();
    let mut extra = Vec::new();
    for i in 0..n {
        let d = if planned {
            darks[i % darks.len()]
        } else {
            darks[0]
        };
        let mut r = d.clone();
        r["index"] = json!(frames.len() + i);
        let file = format!("frames/extra-{i:05}.png");
        r["file"] = json!(file);
        std::fs::hard_link(base.join(d["file"].as_str().unwrap()), out.join(&file)).unwrap();
        extra.push(r);
    }
    m["frames"].as_array_mut().unwrap().extend(extra);
    if planned {
        let per = 1 + n.div_ceil(darks.len());
        for s in m["plan"]["steps"].as_array_mut().unwrap() {
            if s["step"] == "capture" && s["kind"] == "dark" {
                s["count"] = json!(per);
            }
        }
        m["rig"]["bracket"]["dark_frames_per_exposure"] = json!(per);
    }
    std::fs::write(
        out.join("manifest.json"),
        serde_json::to_vec_pretty(&m).unwrap(),
    )
    .unwrap();
    out.to_path_buf()
}

/// Run glint under RLIMIT_AS = [`BUDGET_MB`]: (exited 0, stderr, peak RSS in MB as wait4
/// gives it, an upper bound).
fn glint_limited(args: &[&str]) -> (bool, String, f64) {
    super::util::glint_limited(args, BUDGET_MB)
}

fn error_line(stderr: &str) -> String {
    let lines: Vec<&str> = stderr.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(lines.len(), 1, "{stderr}");
    lines[0].to_string()
}

fn scratch(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("hdr-memory-{name}"))
}

/// 301 dark frames more than the mock plan's 7, which a plan keeping 44 at each exposure
/// allows: `glint hdr` merges them within 600 MB of address space (e6cdebf held every frame
/// decoded, 1.23 GB resident, and aborted under this limit), and the radiance is the plain
/// session's (the added dark frames are copies of its own: the same dark levels).
#[test]
fn hdr_memory_does_not_grow_with_the_dark_frames_listed() {
    let s = with_darks(&scratch("planned"), 301, true);
    let (success, stderr, peak) = glint_limited(&["hdr", s.to_str().unwrap()]);
    println!("glint hdr, 308 dark frames, within {BUDGET_MB} MB: peak RSS <= {peak:.0} MB");
    assert!(success, "{stderr}");
    let summary: Value =
        serde_json::from_slice(&std::fs::read(s.join("hdr/summary.json")).unwrap()).unwrap();
    assert_eq!(summary["dark_frames"], 308);
    // The plain session, merged the same way.
    let plain = scratch("plain");
    let _ = std::fs::remove_dir_all(&plain);
    super::util::copy_dir(base(), &plain);
    let (success, stderr, _) = glint_limited(&["hdr", plain.to_str().unwrap()]);
    assert!(success, "{stderr}");
    let read = |d: &Path| {
        glint::hdr::files::read_exr(&d.join("hdr/radiance.exr"))
            .unwrap_or_else(|e| panic!("{e}"))
            .2
    };
    let (a, b) = (read(&s), read(&plain));
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert!(
            (x.is_nan() && y.is_nan()) || (x - y).abs() <= 1e-5 * y.abs().max(1e-6),
            "{x} against {y}"
        );
    }
}

/// The session: 300 links of one dark frame appended to a manifest whose plan keeps
/// one dark frame at each exposure. Refused before any frame is decoded (so within the
/// memory limit), one line naming the count and the plan's; so are plans beyond a rig's
/// bounds: a capture step of 101 frames, and 101 dark frames planned at one exposure.
#[test]
fn hdr_refuses_more_frames_than_the_plan_keeps() {
    let s = with_darks(&scratch("hostile"), 300, false);
    let (success, stderr, peak) = glint_limited(&["hdr", s.to_str().unwrap()]);
    println!("glint hdr refusing 301 dark frames: peak RSS <= {peak:.0} MB");
    assert!(!success);
    let e = error_line(&stderr);
    assert!(
        e.contains("301 dark frames are labelled with 8000 µs but the plan keeps 1"),
        "{e}"
    );
    assert!(!s.join("hdr/radiance.exr").exists());

    // A plan whose step keeps more than a rig may.
    let s = with_darks(&scratch("step"), 0, false);
    let path = s.join("manifest.json");
    let mut m: Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    for st in m["plan"]["steps"].as_array_mut().unwrap() {
        if st["step"] == "capture" && st["kind"] == "dark" {
            st["count"] = json!(101);
        }
    }
    std::fs::write(&path, serde_json::to_vec(&m).unwrap()).unwrap();
    let e = error_line(&String::from_utf8_lossy(
        &glint(&["hdr", s.to_str().unwrap()]).stderr,
    ));
    assert!(
        e.contains("keeps 101 frames, more than the 100 a capture step may keep"),
        "{e}"
    );

    // Two steps of 100 dark frames at one exposure: 200 planned there.
    let mut m: Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    let steps = m["plan"]["steps"].as_array_mut().unwrap();
    for st in steps.iter_mut() {
        if st["step"] == "capture" && st["kind"] == "dark" {
            st["count"] = json!(100);
        }
    }
    let i = steps
        .iter()
        .position(|st| st["step"] == "capture" && st["kind"] == "dark")
        .unwrap();
    let again = steps[i].clone();
    steps.insert(i + 1, again);
    std::fs::write(&path, serde_json::to_vec(&m).unwrap()).unwrap();
    let e = error_line(&String::from_utf8_lossy(
        &glint(&["hdr", s.to_str().unwrap()]).stderr,
    ));
    assert!(
        e.contains("the plan keeps 200 dark frames at 8000 µs, more than the 100"),
        "{e}"
    );
}

/// The merge as `glint hdr` now runs it (frames read one at a time, folded into running
/// sums, dark frames folded into levels) gives the merge of e6cdebf (every frame loaded,
/// then [`glint::hdr::merge::merge`]) to the bit: radiance, variance and mask.
#[test]
fn the_merge_read_frame_by_frame_is_the_batch_merge_to_the_bit() {
    use glint::hdr::{files, load_session, merge, run};
    let dir = super::util::tempdir();
    super::util::record(dir.path(), &super::util::small_table()).unwrap();
    let s = dir.path().join("s");
    run::run(&s, &Default::default(), &mut |_| {}).unwrap();
    let file = dir.path().join("response.json");
    std::fs::copy(s.join("hdr/response.json"), &file).unwrap();
    let opts = run::HdrOptions {
        response_file: Some(file.clone()),
        ..Default::default()
    };
    let (summary, streamed) = run::run(&s, &opts, &mut |_| {}).unwrap();
    assert_eq!(summary.dark_frames, 7);
    let r = files::load_response(&file).unwrap();
    let m = glint::session::open(&s, false).unwrap();
    let (tiles, darks) = load_session(&s, &m).unwrap();
    let batch = merge::merge(&r, &tiles, &merge::dark_levels(&r, &tiles, &darks)).unwrap();
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&streamed.radiance), bits(&batch.radiance));
    assert_eq!(bits(&streamed.variance), bits(&batch.variance));
    assert_eq!(streamed.mask, batch.mask);
    assert!(batch.counts()[0] > 0);
}
