//! Helpers: small, fast variants of the mock rig, written to a fresh temporary directory.

use std::path::{Path, PathBuf};

use glint::rig::{self, LoadedRig};

pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// rigs/mock.toml as a table.
pub fn mock_table() -> toml::Table {
    toml::from_str(&std::fs::read_to_string(root().join("rigs/mock.toml")).unwrap()).unwrap()
}

/// Set a dotted key (creating tables on the way).
pub fn set(t: &mut toml::Table, key: &str, v: impl Into<toml::Value>) {
    let mut parts: Vec<&str> = key.split('.').collect();
    let last = parts.pop().unwrap();
    let mut cur = t;
    for p in parts {
        cur = cur
            .entry(p.to_string())
            .or_insert_with(|| toml::Value::Table(toml::Table::new()))
            .as_table_mut()
            .unwrap();
    }
    cur.insert(last.to_string(), v.into());
}

/// The mock rig at 160x120 with no lamp warm-up: the same scene, fast.
pub fn small_table() -> toml::Table {
    let mut t = mock_table();
    set(&mut t, "camera.width", 160);
    set(&mut t, "camera.height", 120);
    set(&mut t, "mock.camera.fx", 187.5);
    set(&mut t, "mock.camera.fy", 187.5);
    set(&mut t, "lamp.warmup_ms", 0);
    set(&mut t, "lamp.reply_timeout_ms", 100);
    set(&mut t, "mock.lamp.warmup_ms", 0);
    t
}

/// Write a rig table into `dir` and load it.
pub fn load(dir: &Path, t: &toml::Table) -> LoadedRig {
    let path = dir.join("rig.toml");
    std::fs::write(&path, toml::to_string(t).unwrap()).unwrap();
    rig::load(&path).unwrap_or_else(|e| panic!("test rig does not load: {e}"))
}

pub fn tempdir() -> tempfile::TempDir {
    tempfile::tempdir().unwrap()
}

/// Write the rig `t` into `dir` and capture it into `dir/s` with no progress callback.
pub fn record(
    dir: &Path,
    t: &toml::Table,
) -> Result<glint::capture::Recorded, glint::capture::RecordError> {
    let rig = load(dir, t);
    let devices = glint::devices::open(&rig).unwrap();
    glint::capture::record(
        &rig,
        devices,
        &dir.join("s"),
        Default::default(),
        &mut |_| {},
    )
}

/// The simulator's ground truth: every frame its sensor produced.
pub fn ledger(rec: &glint::capture::Recorded) -> Vec<glint_mock::LedgerEntry> {
    rec.devices
        .lab
        .as_ref()
        .expect("a mock rig")
        .ledger
        .lock()
        .unwrap()
        .clone()
}

/// Run the glint binary.
pub fn glint(args: &[&str]) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_glint"))
        .args(args)
        .output()
        .expect("glint runs")
}

/// Its stdout, after checking it succeeded.
pub fn ok(out: &std::process::Output) -> String {
    assert!(
        out.status.success(),
        "glint failed: {}\n{}",
        String::from_utf8_lossy(&out.stderr),
        String::from_utf8_lossy(&out.stdout)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// The single `error:` line of a failed run.
pub fn err(out: &std::process::Output) -> String {
    assert!(!out.status.success(), "expected a failure");
    let e = String::from_utf8_lossy(&out.stderr);
    let lines: Vec<&str> = e.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(lines.len(), 1, "{e}");
    lines[0].to_string()
}

/// A folder of ../shared/data, or None (and a SKIPPED line) where it is absent: a user's
/// fresh clone has no shared test data.
pub fn shared_data(name: &str) -> Option<PathBuf> {
    let d = root().join("../shared/data").join(name);
    if !d.exists() {
        eprintln!(
            "SKIPPED: {} is absent (shared test data, not part of the project)",
            d.display()
        );
        return None;
    }
    Some(d)
}

/// The simulator's true camera (`cam`) as a Glint scene of the rig's tile and lamp, for
/// images of `w` x `h`: to test stages apart from the calibration.
pub fn true_scene(
    cam: &glint_mock::PosedCamera,
    rig: &glint::rig::Rig,
    w: usize,
    h: usize,
) -> glint::fit::geometry::Scene {
    use glint::calib::camera::{rotation_vector, Intrinsics, Pose};
    let (rm, t) = cam.extrinsics();
    let m = nalgebra::Matrix3::from_fn(|i, j| rm[i][j]);
    glint::fit::geometry::Scene::new(
        Intrinsics {
            fx: cam.fx,
            fy: cam.fy,
            cx: cam.cx,
            cy: cam.cy,
            radial: vec![cam.k1, cam.k2],
            tangential: None,
        },
        Pose {
            rvec: rotation_vector(&m),
            t,
        },
        rig.geometry.lamp_position_mm,
        rig.geometry.tile_thickness_mm,
        rig.geometry.tile_outline_mm.clone(),
        [w, h],
    )
}

/// The simulated lab of a loaded mock rig at the rig's image size and depth, on its own: for
/// the simulator's true radiance and camera, with nothing captured.
pub fn lab(rig: &LoadedRig) -> glint_mock::Lab {
    let r = &rig.rig;
    glint_mock::Lab::new(
        &r.scene_geometry(),
        r.mock.as_ref().expect("a mock rig"),
        r.camera.width,
        r.camera.height,
        r.camera.bit_depth,
        &rig.base_dir(),
    )
    .unwrap()
}

/// The simulator's true radiance of the tile on the grid (RGB interleaved) and its true
/// camera as a Glint scene.
pub fn truth(rig: &LoadedRig) -> (Vec<f32>, glint::fit::geometry::Scene) {
    let mut lab = lab(rig);
    let r = &rig.rig;
    let rad = lab.camera.radiance(glint_mock::SceneKind::Tile).to_vec();
    let scene = true_scene(
        lab.camera.true_camera(),
        r,
        r.camera.width as usize,
        r.camera.height as usize,
    );
    (rad, scene)
}

/// The microfacet model's lobe, f_r's lobe times n.l for ks = 1, written out here (not
/// the fitter's code): GGX D, Smith's separable G1 G1 and Schlick's growth shaped with F0
/// = 0.04 (as `glint::fit::model::ggx` defines the model), for unit light and view
/// vectors over the normal z, at the roughness of exponent n (α = sqrt(2 / (n + 2))).
pub fn ggx_lobe(l: [f64; 3], v: [f64; 3], n: f64) -> f64 {
    let (cl, cv) = (l[2], v[2]);
    if cl <= 0.0 || cv <= 0.0 {
        return 0.0;
    }
    let a2 = 2.0 / (n + 2.0);
    let h = [l[0] + v[0], l[1] + v[1], l[2] + v[2]];
    let hn = (h[0] * h[0] + h[1] * h[1] + h[2] * h[2]).sqrt();
    let nh = h[2] / hn;
    let vh = (v[0] * h[0] + v[1] * h[1] + v[2] * h[2]) / hn;
    let den = nh * nh * (a2 - 1.0) + 1.0;
    let d = a2 / (std::f64::consts::PI * den * den);
    let g1 = |x: f64| 2.0 * x / (x + (a2 + (1.0 - a2) * x * x).sqrt());
    let f = 1.0 + (1.0 / 0.04 - 1.0) * (1.0 - vh).max(0.0).powi(5);
    d * g1(cl) * g1(cv) * f / (4.0 * cv)
}

/// A copy of a folder tree (regular files and folders; links left out).
pub fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let t = e.file_type().unwrap();
        if t.is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else if t.is_file() {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

/// Run glint with at most `budget_mb` of address space (RLIMIT_AS, as `ulimit -v` sets it:
/// an allocation beyond it fails and aborts the process), returning (success, stderr, peak
/// resident memory in MB). The peak is wait4's ru_maxrss, which on Linux also counts the
/// test process's own peak when the child was spawned (the address space it was forked
/// from), so it is an upper bound; the limit is what the test holds the child to.
// The child is reaped by wait4 (which gives its rusage), not by Child::wait.
#[allow(clippy::zombie_processes)]
pub fn glint_limited(args: &[&str], budget_mb: u64) -> (bool, String, f64) {
    use std::io::Read;
    use std::os::unix::process::CommandExt;
    use std::process::{Command, Stdio};
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_glint"));
    cmd.args(args).stdout(Stdio::null()).stderr(Stdio::piped());
    // SAFETY: setrlimit is async-signal-safe; nothing else runs between fork and exec.
    unsafe {
        cmd.pre_exec(move || {
            let lim = libc::rlimit {
                rlim_cur: budget_mb << 20,
                rlim_max: budget_mb << 20,
            };
            if libc::setrlimit(libc::RLIMIT_AS, &lim) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let mut child = cmd.spawn().unwrap();
    let mut stderr = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut stderr)
        .unwrap();
    let pid = child.id() as libc::pid_t;
    let mut status = 0;
    // SAFETY: plain out-parameters; the child is ours and not yet reaped.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    let r = unsafe { libc::wait4(pid, &mut status, 0, &mut ru) };
    assert_eq!(r, pid, "wait4");
    let success = libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 0;
    // ru_maxrss is in KiB on Linux.
    (success, stderr, ru.ru_maxrss as f64 / 1024.0)
}
