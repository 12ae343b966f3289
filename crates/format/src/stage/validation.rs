//! `validation/validation.json`, written by `glint validate` and read by `glint report`.
//! The field order is the file's.

use serde::{Deserialize, Serialize};

/// The file's `format`.
pub const FORMAT: &str = "glint-validation";
/// The newest `format_version` this Glint writes.
pub const FORMAT_VERSION: u32 = 1;

/// `validation/validation.json`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ValidationFile {
    pub format: String,
    #[serde(default)]
    pub format_version: Option<u32>,
    #[serde(default)]
    pub created: String,
    #[serde(default)]
    pub session: String,
    /// Channels compared: 3 (R, G, B) or 1 (a monochrome camera).
    #[serde(default)]
    pub channels: usize,
    #[serde(default)]
    pub chosen: String,
    /// Tile pixels compared.
    #[serde(default)]
    pub tile_pixels: usize,
    /// The exposure the figures show, µs.
    #[serde(default)]
    pub figure_exposure_us: Option<f64>,
    /// The floor's albedos measured from the radiance (dark squares, light squares,
    /// surround; per channel).
    #[serde(default)]
    pub floor_albedo: Vec<Vec<Option<f64>>>,
    pub models: Vec<ModelValidation>,
    #[serde(default)]
    pub warnings: Vec<String>,
    #[serde(default)]
    pub files: Vec<String>,
    #[serde(default)]
    pub seconds: Option<f64>,
}

impl ValidationFile {
    /// The chosen model's validation, if the file marks one.
    pub fn chosen(&self) -> Option<&ModelValidation> {
        self.models.iter().find(|m| m.chosen)
    }
}

/// One model's validation.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ModelValidation {
    pub model: String,
    #[serde(default)]
    pub chosen: bool,
    /// Per channel: R, G, B, or a monochrome camera's one.
    #[serde(default)]
    pub kd: Vec<Option<f64>>,
    #[serde(default)]
    pub ks: Vec<Option<f64>>,
    #[serde(default)]
    pub n: Option<f64>,
    /// Against the photographs, in pixel values.
    #[serde(default)]
    pub pixels: PixelMetrics,
    /// Against the merged radiance.
    #[serde(default)]
    pub radiance: RadianceMetrics,
}

/// Pixel-value figures over all exposures.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[serde(default)]
pub struct PixelMetrics {
    pub readings: usize,
    pub rmse: Option<f64>,
    pub noise_rmse: Option<f64>,
    pub psnr_db: Option<f64>,
    pub ssim: Option<f64>,
    pub per_exposure: Vec<ExposureMetrics>,
}

/// Pixel-value figures at one exposure.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[serde(default)]
pub struct ExposureMetrics {
    pub exposure_us: Option<f64>,
    /// Readings compared (pixel x channel).
    pub readings: usize,
    pub rmse: Option<f64>,
    /// The RMSE the noise alone would give on the same readings.
    pub noise_rmse: Option<f64>,
    pub psnr_db: Option<f64>,
    pub ssim: Option<f64>,
    pub ssim_windows: usize,
}

/// HDR-space figures.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[serde(default)]
pub struct RadianceMetrics {
    /// Measured tile samples compared (pixel x channel).
    pub samples: usize,
    /// sqrt(sum (model - measured)^2 / sum measured^2), all channels.
    pub relative_error: Option<f64>,
    /// The same per channel.
    pub relative_error_rgb: Vec<Option<f64>>,
    /// Mean of (model - measured)^2 / variance.
    pub mean_z2: Option<f64>,
}
