//! The calibration's shared types: its error, the file `calib/camera.json`, intrinsics
//! known from elsewhere and their check (read by [`super`] and by
//! [`crate::calib::export`]). A leaf: it names neither of them.

use std::path::PathBuf;

use crate::calib::camera::Intrinsics;
use crate::calib::detect::DetectError;
use crate::calib::solve::{CalibError, Calibration, LensCovariance};
use crate::session::SessionError;

pub use glint_format::stage::camera::{FORMAT, FORMAT_VERSION};

/// What can go wrong.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    #[error("{path}: {reason}")]
    File { path: PathBuf, reason: String },
    /// Not a `#[source]`: the message already holds the detector's, and an error chain
    /// printed in full would say it twice.
    #[error("{name}: {error}")]
    Detect { name: String, error: DetectError },
    #[error(transparent)]
    Calib(#[from] CalibError),
    #[error(transparent)]
    Session(#[from] SessionError),
    #[error("{0}")]
    Input(String),
}

pub use glint_format::stage::camera::{Detected, GridSpec};

/// The file `calib/camera.json` (glint-format's type, with the numerics' calibration).
pub type CameraFile = glint_format::stage::camera::CameraFile<Calibration>;

/// The grid's inner corners in grid coordinates (mm, or squares without a square size).
pub(crate) fn grid_world(g: &GridSpec) -> Vec<[f64; 3]> {
    let s = g.square_mm.unwrap_or(1.0);
    let [nx, ny] = g.inner_corners;
    (0..ny)
        .flat_map(|j| (0..nx).map(move |i| [i as f64 * s, j as f64 * s, 0.0]))
        .collect()
}

/// Intrinsics known from an earlier calibration (a `camera.json`), with its image size.
#[derive(Debug, Clone)]
pub struct Known {
    pub from: PathBuf,
    pub width: usize,
    pub height: usize,
    pub intrinsics: Intrinsics,
    /// The intrinsics' covariance where the file has one (carried into the pose's).
    pub covariance: Option<LensCovariance>,
}

pub(crate) const RADIAL_PROBLEM: &str =
    "calibration.intrinsics: at most 3 radial terms, each distortion term finite (|k| <= 1000)";

/// What makes intrinsics unusable for a `width` x `height` image (None when they are
/// fine): focal lengths positive (at most 1e7 px), the principal point near the image, at
/// most 3 radial terms, every distortion term finite (|k| <= 1000). The checks of
/// [`calibration_problem`], for a camera from elsewhere too (fit.json's refined one).
pub fn intrinsics_problem(k: &Intrinsics, width: usize, height: usize) -> Option<String> {
    for (name, f) in [("fx", k.fx), ("fy", k.fy)] {
        if !(f.is_finite() && f > 0.0 && f <= 1e7) {
            return Some(format!(
                "calibration.intrinsics.{name} = {f}: a focal length must be positive (pixels, at most 1e7)"
            ));
        }
    }
    let (w, h) = (width as f64, height as f64);
    if !(k.cx.is_finite() && k.cy.is_finite() && k.cx.abs() <= 10.0 * w && k.cy.abs() <= 10.0 * h) {
        return Some(format!(
            "calibration.intrinsics: principal point ({}, {}) is nowhere near the {width}x{height} image",
            k.cx, k.cy
        ));
    }
    if k.radial.len() > 3 || !k.distortion_in_bounds() {
        return Some(RADIAL_PROBLEM.into());
    }
    None
}
