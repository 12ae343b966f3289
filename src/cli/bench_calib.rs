//! `glint bench calib`: chessboard detection and calibration timed on one photo (OpenCV's
//! left01.jpg from the shared test data where it is present; a synthetic board otherwise).

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use glint::calib::detect::{detect, Gray};
use glint::calib::solve::{calibrate, Options, ViewObs};

use super::calib::parse_grid;

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
/// where the reference photo is absent (the shared test data is not part of a clone).
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
                "note: no {} (the shared test data is not part of a clone): timing a synthetic photo of a {nx}x{ny} board instead (give a photo with --image)",
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
