//! `glint calibrate`, `glint lens` and `glint bench calib`.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use glint::calib::detect::{detect, Gray};
use glint::calib::run::{self, CameraFile, GridSpec};
use glint::calib::solve::{calibrate, Options, ViewObs};

#[derive(Args)]
pub struct CalibrateArgs {
    /// A session whose grid photo to calibrate from (grid size and square size from its
    /// rig); writes SESSION/calib/camera.json and corners.png.
    #[arg(
        value_name = "SESSION",
        required_unless_present = "images",
        conflicts_with = "images"
    )]
    session: Option<PathBuf>,
    /// Photos of the grid instead of a session. Several photos share the intrinsics and get
    /// one pose each (calibrate the lens once; the rig's pose then comes from the photo
    /// taken in place). Photos where no grid is found are skipped with a warning.
    #[arg(long, num_args = 1.., value_name = "PHOTO")]
    images: Vec<PathBuf>,
    /// Inner corners of the grid, along x then y (a board of 10 x 7 squares has 9x6).
    #[arg(long, value_name = "NxM", requires = "images")]
    grid: Option<String>,
    /// Size of one square in mm (translations are then in mm; without it, in squares).
    #[arg(long, value_name = "MM", requires = "images")]
    square_mm: Option<f64>,
    /// Where to write camera.json and the pictures of the detected corners with --images:
    /// corners.png for one photo; for several, corners-01.png, corners-02.png, ... (the
    /// photo's place in the --images list), one per photo with a grid. DIR must be new or
    /// empty: Glint never replaces a file there.
    #[arg(long, value_name = "DIR", default_value = "calib", requires = "images")]
    out: PathBuf,
    /// The camera's response (a session's hdr/response.json, or its profile from beside the
    /// rig) for --images: the corners are then refined in linear light, which removes the
    /// tone curve's and the light's fall-off's bias (0.03-0.08 px on simulated boards).
    /// The photos must have the response's channels and bit depth.
    #[arg(long, value_name = "RESPONSE_JSON", requires = "images")]
    response: Option<PathBuf>,
    /// Intrinsics from an earlier calibration: its camera.json (e.g. from several photos
    /// with --images; its covariance is carried into the pose's), or an OpenCV FileStorage
    /// or ROS camera_info YAML (a name ending .yaml or .yml; held as exact). They are held
    /// and only the pose is fitted.
    #[arg(long, value_name = "CAMERA_JSON|YAML")]
    intrinsics: Option<PathBuf>,
    /// Hold the camera's lens profile from beside this rig file (made by `glint lens --rig
    /// RIG`), as `glint run` does: only the pose is fitted from the session's grid photo.
    /// Where the rig has no profile for the session's camera and size, the intrinsics are
    /// fitted from the photo, with a note.
    #[arg(
        long,
        value_name = "RIG",
        conflicts_with_all = ["images", "intrinsics"]
    )]
    rig: Option<PathBuf>,
    /// Work on a session that is not complete (`capturing`: killed, or `failed`), with a
    /// warning.
    #[arg(long, conflicts_with = "images")]
    allow_incomplete: bool,
    /// Print the calibration as JSON on stdout.
    #[arg(long)]
    json: bool,
}

fn parse_grid(s: &str) -> Result<[usize; 2]> {
    let (a, b) = s
        .split_once(['x', 'X'])
        .context("--grid must look like 9x6 (inner corners along x, then y)")?;
    let (a, b): (usize, usize) = (
        a.trim()
            .parse()
            .context("--grid: not a number before the x")?,
        b.trim()
            .parse()
            .context("--grid: not a number after the x")?,
    );
    if a < 2 || b < 2 {
        bail!("--grid needs at least 2x2 inner corners");
    }
    if (a + b) % 2 == 0 {
        bail!(
            "a {a}x{b} grid has {}x{} squares: its origin is ambiguous; use a board with an odd number of squares one way and an even number the other",
            a + 1,
            b + 1
        );
    }
    Ok([a, b])
}

pub fn cmd_calibrate(a: CalibrateArgs) -> Result<ExitCode> {
    let mut known = a.intrinsics.as_deref().map(run::load_known).transpose()?;
    if let (Some(rig), Some(s)) = (&a.rig, &a.session) {
        known = glint::pipeline::lens_profile_for(rig, s).map_err(anyhow::Error::msg)?;
        match &known {
            Some(k) => eprintln!(
                "holding the lens profile {} (only the pose is fitted)",
                k.from.display()
            ),
            None => eprintln!(
                "note: no lens profile for this session's camera beside {}; the intrinsics are fitted from the grid photo (glint lens --rig {} makes one)",
                rig.display(),
                rig.display()
            ),
        }
    }
    let (file, written) = if let Some(s) = &a.session {
        eprintln!("calibrating from the grid photo of {} ...", s.display());
        let out = s.join("calib");
        (
            run::run_session_allowing(s, known.as_ref(), a.allow_incomplete)?,
            vec![
                out.join("camera.json"),
                out.join(run::OPENCV_YAML),
                out.join(run::ROS_YAML),
                out.join("corners.png"),
            ],
        )
    } else {
        let grid = parse_grid(a.grid.as_deref().context("--images needs --grid NxM")?)?;
        if let Some(s) = a.square_mm {
            if !(s.is_finite() && s > 0.0) {
                bail!("--square-mm must be positive, got {s}");
            }
        }
        let response = match &a.response {
            Some(p) => Some(
                glint::hdr::files::load_response(p)
                    .map_err(|e| anyhow::anyhow!("--response {e}"))?,
            ),
            None => None,
        };
        let from = a.response.as_ref().map(|p| p.display().to_string());
        eprintln!("calibrating from {} photo(s) ...", a.images.len());
        run::run_images(
            &a.images,
            GridSpec {
                inner_corners: grid,
                square_mm: a.square_mm,
            },
            &a.out,
            known.as_ref(),
            response.as_ref().zip(from.as_deref()),
        )?
    };
    for w in &file.calibration.warnings {
        eprintln!("warning: {w}");
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&file)?);
    } else {
        print_summary(&file, &written);
    }
    Ok(ExitCode::SUCCESS)
}

#[derive(Args)]
pub struct LensArgs {
    /// The rig file (TOML); the lens profile is stored beside it, in profiles/.
    #[arg(long, value_name = "FILE")]
    rig: PathBuf,
    /// Where to write the lens session; must not exist or be empty.
    /// [default: sessions/<rig name>-lens-<UTC time>]
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// How many poses (5..9): head-on, tilted about x and y each way, then about both
    /// axes at once.
    #[arg(long, default_value_t = 9, value_name = "N")]
    poses: usize,
    /// The tilt of the single-axis poses, degrees (10..45); the diagonal poses tilt 0.8
    /// of it about each axis.
    #[arg(long, default_value_t = 30.0, value_name = "DEG")]
    tilt_deg: f64,
    /// List the poses and the plan, estimate time and disk, open no device.
    #[arg(long)]
    dry_run: bool,
    /// Replace the camera's existing lens profile (it is kept otherwise).
    #[arg(long)]
    replace_profile: bool,
    /// Print the outcome as JSON on stdout.
    #[arg(long)]
    json: bool,
}

/// `glint lens`: the lens calibration plan on the rig (the operator shows the board in
/// each pose), the multi-view calibration of that lens session, its checks, and the
/// camera's lens profile beside the rig.
pub fn cmd_lens(a: LensArgs) -> Result<ExitCode> {
    use glint::calib::lens;
    let loaded = super::load_capture_rig(&a.rig)?;
    let r = &loaded.rig;
    if !(5..=9).contains(&a.poses) {
        bail!("--poses must be 5..9 (got {})", a.poses);
    }
    if !(a.tilt_deg.is_finite() && (10.0..=45.0).contains(&a.tilt_deg)) {
        bail!("--tilt-deg must be 10..45 degrees (got {})", a.tilt_deg);
    }
    let poses = glint::plan::lens_poses(r, a.tilt_deg, a.poses);
    let plan = glint::capture::Plan::for_lens(r, &poses);
    let out = a
        .out
        .unwrap_or_else(|| super::default_out(&format!("{}-lens", r.rig.name)));
    if a.dry_run {
        if !a.json {
            println!(
                "Lens calibration: {} poses of the {}x{} board (the operator holds it; a rig's operator.show_board command, or a person, is asked):",
                poses.len(),
                r.geometry.grid_inner_corners[0],
                r.geometry.grid_inner_corners[1]
            );
            for p in &poses {
                println!("  {p}");
            }
        }
        return super::capture::dry_run(&loaded, &plan, &out, a.json);
    }
    if let Some(p) = plan
        .check(&glint::capture::Limits::from_rig(r))
        .into_iter()
        .chain(plan.check_resources(r, &out))
        .next()
    {
        bail!("the lens plan cannot run: {p}");
    }
    let devices = glint::devices::open(&loaded).context("opening the rig's devices")?;
    let info = devices.camera.info();
    let profile = lens::profile_path(&loaded.path, &info.model, info.width, info.height)
        .with_context(|| {
            format!(
                "{}: the rig's folder is not a folder; the lens profile goes beside the rig",
                loaded.path.display()
            )
        })?;
    if profile.symlink_metadata().is_ok() && !a.replace_profile {
        eprintln!(
            "note: the camera has a lens profile ({}); it will be kept (--replace-profile replaces it)",
            profile.display()
        );
    }
    let stop = super::capture::stop_on_ctrl_c(&a.rig)?;
    let total = plan.frames();
    let recorded = glint::capture::record_plan(
        &loaded,
        plan,
        devices,
        &out,
        stop,
        &mut |e| {
            if let glint::capture::Event::Step { description, .. } = e {
                if description.starts_with("operator") {
                    eprintln!("{description}");
                }
            }
        },
        &mut |_| {},
    )
    .map_err(|(e, _)| e)?;
    eprintln!(
        "captured {} grid frames in {} poses into {}; calibrating ...",
        total,
        poses.len(),
        recorded.dir.display()
    );
    // The grid photos in linear light where the camera's response is known (its profile
    // beside the rig, stored by the first `glint run`): corners without the tone curve's
    // bias.
    let response = glint::hdr::run::known_response(
        &glint::hdr::run::HdrOptions::default(),
        glint::hdr::run::profile_path_for(&loaded.path, &info),
        info.bit_depth,
        info.channels as usize,
    )
    .context("reading the camera's response profile")?;
    if response.is_none() {
        eprintln!(
            "note: the camera has no response profile yet: the corners are refined on the photos' values (run glint run once first for corners in linear light)"
        );
    }
    let from = match &response {
        Some((_, glint::hdr::run::ResponseSource::Profile(p)))
        | Some((_, glint::hdr::run::ResponseSource::File(p))) => p.clone(),
        _ => String::new(),
    };
    let file = run::run_session_with(
        &recorded.dir,
        None,
        false,
        response.as_ref().map(|(r, _)| (r, from.as_str())),
    )?;
    for w in &file.calibration.warnings {
        eprintln!("warning: {w}");
    }
    let checks = lens::check(&file).map_err(|why| {
        anyhow::anyhow!(
            "the lens session {} does not pass the lens profile's checks: {why}; no profile was stored",
            recorded.dir.display()
        )
    })?;
    let stored = lens::store(
        &profile,
        &file,
        &checks,
        &recorded.dir,
        &info.model,
        a.replace_profile,
    )?;
    if a.json {
        println!(
            "{}",
            serde_json::json!({
                "session": recorded.dir, "profile": stored, "checks": checks,
                "calibration": file.calibration,
            })
        );
    } else {
        print_summary(&file, &[recorded.dir.join("calib").join("camera.json")]);
        println!(
            "checks: {} views, RMS {:.3} px, f sd {:.3}%, tilt spread {:.1}° and {:.1}°",
            checks.views,
            checks.rms_px,
            100.0 * checks.f_rel_sd,
            checks.tilt_spread_deg[0],
            checks.tilt_spread_deg[1]
        );
        match stored {
            lens::Stored::Written { path } => println!(
                "lens profile written: {} (glint run --rig {} now holds this lens and fits only the pose)",
                path.display(),
                loaded.path.display()
            ),
            lens::Stored::Kept { path } => println!(
                "lens profile kept: {} exists (--replace-profile replaces it)",
                path.display()
            ),
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn print_summary(f: &CameraFile, written: &[PathBuf]) {
    let c = &f.calibration;
    println!(
        "{} view(s), {}x{} px; model: {} (principal point {}, {} pixels)",
        c.views.len(),
        c.width,
        c.height,
        if c.fit.intrinsic_count() == 0 {
            c.fit.describe()
        } else {
            format!("{}, chosen by BIC", c.fit.describe())
        },
        if c.fit.principal_point {
            "fitted"
        } else {
            "at the image centre"
        },
        if c.fit.aspect { "fx != fy" } else { "square" }
    );
    for p in &c.parameters {
        println!("  {:3} = {:>12.6} ± {:.6}", p.name, p.value, p.sd);
    }
    println!(
        "  RMS reprojection error {:.4} px per corner (sd of one coordinate {:.4} px)",
        c.rms_px, c.sigma_px
    );
    for v in &c.views {
        let [x, y, z] = v.camera_centre;
        let [sx, sy, sz] = v.camera_centre_sd;
        println!(
            "  {}: camera centre ({x:.2} ± {sx:.2}, {y:.2} ± {sy:.2}, {z:.2} ± {sz:.2}) {}, distance {:.2}; RMS {:.4} px",
            v.name,
            f.length_unit,
            v.distance,
            v.rms_px
        );
    }
    if let Some(u) = &c.uncertainty_includes {
        println!("  the standard deviations include {u}");
    }
    let names: Vec<String> = written.iter().map(|p| p.display().to_string()).collect();
    println!("wrote {}", names.join(", "));
}

#[derive(Args)]
pub struct CalibBenchArgs {
    /// A photo of a 9x6 grid [default: ../shared/data/opencv_stereo_chessboard_9x6/images/left01.jpg;
    /// where that is absent, a synthetic 640x480 photo of a board of --grid's size].
    #[arg(long)]
    image: Option<PathBuf>,
    /// Inner corners.
    #[arg(long, default_value = "9x6")]
    grid: String,
    /// Timed repeats (the median is reported).
    #[arg(long, default_value_t = 50)]
    repeats: usize,
}

/// A synthetic photo of a board of `nx` x `ny` inner corners, 640x480 like OpenCV's
/// left01.jpg: the board seen obliquely (a homography), white margin, grey surround,
/// 4x4 supersampled edges and a little deterministic noise. For `glint bench calib`
/// where the reference photo is absent (a fresh clone has no ../shared).
fn synthetic_board(nx: usize, ny: usize) -> Gray {
    let (w, h) = (640usize, 480usize);
    // Board corners (in squares: the outer squares' edges, -1..nx and -1..ny) to image.
    let src = [
        [-1.0, -1.0],
        [nx as f64, -1.0],
        [nx as f64, ny as f64],
        [-1.0, ny as f64],
    ];
    let dst = [
        [150.0, 95.0],
        [505.0, 120.0],
        [470.0, 385.0],
        [125.0, 350.0],
    ];
    // H maps board to image: solve the 8 unknowns of [h0 h1 h2; h3 h4 h5; h6 h7 1].
    let mut a = nalgebra::SMatrix::<f64, 8, 8>::zeros();
    let mut b = nalgebra::SVector::<f64, 8>::zeros();
    for (k, ([x, y], [u, v])) in src.iter().zip(&dst).enumerate() {
        let r = 2 * k;
        a.row_mut(r)
            .copy_from_slice(&[*x, *y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y]);
        a.row_mut(r + 1)
            .copy_from_slice(&[0.0, 0.0, 0.0, *x, *y, 1.0, -v * x, -v * y]);
        b[r] = *u;
        b[r + 1] = *v;
    }
    let hv = a.lu().solve(&b).unwrap_or_default();
    let hm = nalgebra::Matrix3::new(hv[0], hv[1], hv[2], hv[3], hv[4], hv[5], hv[6], hv[7], 1.0);
    let inv = hm.try_inverse().unwrap_or_else(nalgebra::Matrix3::identity);
    let margin = 0.4;
    let shade = |x: f64, y: f64| -> f32 {
        let p = inv * nalgebra::Vector3::new(x, y, 1.0);
        let (bx, by) = (p[0] / p[2], p[1] / p[2]);
        let inside = |lo: f64, hi: f64, v: f64| v >= lo && v < hi;
        if inside(-1.0, nx as f64, bx) && inside(-1.0, ny as f64, by) {
            // Square (0, 0), beyond inner corner (0, 0) in +x and +y, is dark.
            if (bx.floor() as i64 + by.floor() as i64).rem_euclid(2) == 0 {
                30.0
            } else {
                225.0
            }
        } else if inside(-1.0 - margin, nx as f64 + margin, bx)
            && inside(-1.0 - margin, ny as f64 + margin, by)
        {
            225.0
        } else {
            110.0
        }
    };
    let mut data = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            let mut sum = 0.0;
            for sy in 0..4 {
                for sx in 0..4 {
                    sum += shade(
                        x as f64 + (sx as f64 + 0.5) / 4.0 - 0.5,
                        y as f64 + (sy as f64 + 0.5) / 4.0 - 0.5,
                    );
                }
            }
            let noise = ((x * 7919 + y * 104_729) % 7) as f32 - 3.0;
            data.push((sum / 16.0 + noise).clamp(0.0, 255.0));
        }
    }
    Gray::new(w, h, data)
}

/// Detection + single-view calibration time on one core.
pub fn bench_calib(a: CalibBenchArgs) -> Result<ExitCode> {
    let [nx, ny] = parse_grid(&a.grid)?;
    let default = PathBuf::from("../shared/data/opencv_stereo_chessboard_9x6/images/left01.jpg");
    let (g, path) = match a
        .image
        .or_else(|| default.exists().then(|| default.clone()))
    {
        Some(path) => {
            let img = image::open(&path)
                .with_context(|| format!("{}: cannot open the photo", path.display()))?;
            (
                glint::calib::gray_from_image(&img),
                path.display().to_string(),
            )
        }
        None => {
            eprintln!(
                "note: no {} (a fresh clone has no ../shared): timing a synthetic photo of a {nx}x{ny} board instead (give a photo with --image)",
                default.display()
            );
            (synthetic_board(nx, ny), "a synthetic board".to_string())
        }
    };
    let world: Vec<[f64; 3]> = (0..ny)
        .flat_map(|j| (0..nx).map(move |i| [i as f64, j as f64, 0.0]))
        .collect();
    let (mut td, mut tc) = (Vec::new(), Vec::new());
    for _ in 0..a.repeats.max(1) {
        let t0 = Instant::now();
        let grid = detect(&g, nx, ny)?;
        let t1 = Instant::now();
        let v = ViewObs {
            name: "bench".into(),
            world: world.clone(),
            px: grid.corners,
        };
        let c = calibrate(&[v], g.width, g.height, Options::for_views(1))?;
        let t2 = Instant::now();
        std::hint::black_box(c);
        td.push((t1 - t0).as_secs_f64());
        tc.push((t2 - t1).as_secs_f64());
    }
    let med = |mut v: Vec<f64>| {
        v.sort_by(|a, b| a.total_cmp(b));
        v[v.len() / 2]
    };
    let (d, c) = (med(td), med(tc));
    println!(
        "{} ({}x{}), one thread, median of {}: detection {:.2} ms + single-view calibration {:.2} ms = {:.2} ms",
        path,
        g.width,
        g.height,
        a.repeats.max(1),
        d * 1e3,
        c * 1e3,
        (d + c) * 1e3
    );
    Ok(ExitCode::SUCCESS)
}
