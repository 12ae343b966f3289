//! `calib/camera.json`, written by `glint calibrate` and read by `glint fit`,
//! `glint validate`, `glint report` and `glint export`. The calibration itself is the
//! numerics' type (`C`: glint-numerics' `Calibration`), so that this crate stays below
//! the numerics; every other field is here. The field order is the file's.

use serde::{Deserialize, Serialize};

/// The file's `format`.
pub const FORMAT: &str = "glint-camera";
/// The newest `format_version` this Glint writes.
pub const FORMAT_VERSION: u32 = 1;

/// The grid: inner corners and square size.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct GridSpec {
    pub inner_corners: [usize; 2],
    /// Square size in mm; `None`: lengths are in squares.
    pub square_mm: Option<f64>,
}

/// One photo's detection.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Detected {
    pub name: String,
    /// Detected corners, pixels, row-major (corner (i, j) at j * nx + i).
    pub corners: Vec<[f64; 2]>,
    /// Corners not found but placed between their neighbours (under a shadow's edge or
    /// glare): approximate, and left out of the fit. The view's residuals are for the
    /// other corners, in order.
    pub placed: Vec<usize>,
    /// Corners found whose position is doubtful (they move when image edges that miss
    /// them are down-weighted: a shadow's edge, glare, the board's rim nearby): left out
    /// of the fit.
    pub doubtful: Vec<usize>,
    pub spacing_px: f64,
}

/// The file `calib/camera.json`, its calibration of type `C`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraFile<C> {
    pub format: String,
    #[serde(default)]
    pub format_version: u32,
    #[serde(default)]
    pub created: String,
    #[serde(default)]
    pub grid: GridSpec,
    /// Length unit of translations and camera centres.
    #[serde(default)]
    pub length_unit: String,
    /// The convention, for readers of the file.
    #[serde(default)]
    pub conventions: String,
    pub calibration: C,
    /// The intrinsics as OpenCV's arrays (the numbers of `calibration.intrinsics`): the
    /// camera matrix [fx 0 cx; 0 fy cy; 0 0 1] and the distortion coefficients in OpenCV's
    /// order, k1, k2, p1, p2, k3 (terms not fitted are 0). `calib/camera_opencv.yaml` and
    /// `calib/camera_info.yaml` hold them for OpenCV and ROS.
    #[serde(default)]
    pub camera_matrix: [[f64; 3]; 3],
    #[serde(default)]
    pub dist_coeffs: [f64; 5],
    /// Rotation matrices of the views (rows; X_cam = R X + t).
    #[serde(default)]
    pub rotations: Vec<[[f64; 3]; 3]>,
    #[serde(default)]
    pub detections: Vec<Detected>,
    /// Photos that were given but in which no grid was found.
    #[serde(default)]
    pub skipped: Vec<String>,
    /// What the corners were refined on: the photo in linear light through the camera's
    /// response (and which), or the photo's values as they are.
    #[serde(default)]
    pub corners_refined_on: String,
    #[serde(default)]
    pub seconds: f64,
}
