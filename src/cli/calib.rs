//! `glint calibrate` and `glint bench calib`.

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
    /// Intrinsics from an earlier calibration (its camera.json, e.g. from several photos
    /// with --images): they are held and only the pose is fitted.
    #[arg(long, value_name = "CAMERA_JSON")]
    intrinsics: Option<PathBuf>,
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
    let known = a.intrinsics.as_deref().map(run::load_known).transpose()?;
    let (file, written) = if let Some(s) = &a.session {
        eprintln!("calibrating from the grid photo of {} ...", s.display());
        let out = s.join("calib");
        (
            run::run_session_allowing(s, known.as_ref(), a.allow_incomplete)?,
            vec![out.join("camera.json"), out.join("corners.png")],
        )
    } else {
        let grid = parse_grid(a.grid.as_deref().context("--images needs --grid NxM")?)?;
        if let Some(s) = a.square_mm {
            if !(s.is_finite() && s > 0.0) {
                bail!("--square-mm must be positive, got {s}");
            }
        }
        eprintln!("calibrating from {} photo(s) ...", a.images.len());
        run::run_images(
            &a.images,
            GridSpec {
                inner_corners: grid,
                square_mm: a.square_mm,
            },
            &a.out,
            known.as_ref(),
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
        println!(
            "  {}: camera at ({:.2}, {:.2}, {:.2}) {}, distance {:.2}; RMS {:.4} px",
            v.name,
            v.camera_centre[0],
            v.camera_centre[1],
            v.camera_centre[2],
            f.length_unit,
            v.distance,
            v.rms_px
        );
    }
    let names: Vec<String> = written.iter().map(|p| p.display().to_string()).collect();
    println!("wrote {}", names.join(", "));
}

#[derive(Args)]
pub struct CalibBenchArgs {
    /// A photo of a 9x6 grid [default: ../shared/data/opencv_stereo_chessboard_9x6/images/left01.jpg].
    #[arg(long)]
    image: Option<PathBuf>,
    /// Inner corners.
    #[arg(long, default_value = "9x6")]
    grid: String,
    /// Timed repeats (the median is reported).
    #[arg(long, default_value_t = 50)]
    repeats: usize,
}

/// Detection + single-view calibration time on one core.
pub fn bench_calib(a: CalibBenchArgs) -> Result<ExitCode> {
    let path = a.image.unwrap_or_else(|| {
        PathBuf::from("../shared/data/opencv_stereo_chessboard_9x6/images/left01.jpg")
    });
    let img = image::open(&path).with_context(|| {
        format!(
            "{}: cannot open the photo (give one with --image)",
            path.display()
        )
    })?;
    let g = Gray::from_image(&img);
    let [nx, ny] = parse_grid(&a.grid)?;
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
        path.display(),
        g.width,
        g.height,
        a.repeats.max(1),
        d * 1e3,
        c * 1e3,
        (d + c) * 1e3
    );
    Ok(ExitCode::SUCCESS)
}
