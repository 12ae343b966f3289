//! `glint calibrate`, `glint lens` and `glint bench calib`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{bail, Context, Result};
use clap::Args;
use glint::calib::run::{self, CameraFile, GridSpec};

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

pub(super) fn parse_grid(s: &str) -> Result<[usize; 2]> {
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
