//! `fit/fit.json`, written by `glint fit` and read by `glint validate`, `glint report` and
//! `glint export` (their check of it against the session is the glint crate's
//! `fit::file`). The field order is the file's.

use serde::{Deserialize, Serialize};

/// The file's `format`.
pub const FORMAT: &str = "glint-fit";
/// The newest `format_version` this Glint writes and reads.
pub const FORMAT_VERSION: u32 = 1;

/// A parameter: value, standard deviation, 95% interval (any of them may be null in the
/// file: a NaN is written as null, an unbounded interval end too).
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq)]
pub struct Param {
    #[serde(default)]
    pub value: Option<f64>,
    #[serde(default)]
    pub sd: Option<f64>,
    #[serde(default)]
    pub ci95: [Option<f64>; 2],
}

impl Param {
    /// A parameter from its numbers (not finite ones written as null).
    pub fn of(value: f64, sd: f64, ci95: [f64; 2]) -> Self {
        use super::finite;
        Param {
            value: finite(value),
            sd: finite(sd),
            ci95: ci95.map(finite),
        }
    }

    /// The value, NaN where the file has none.
    pub fn v(&self) -> f64 {
        self.value.unwrap_or(f64::NAN)
    }
}

/// `fit/fit.json`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct FitFile {
    pub format: String,
    #[serde(default)]
    pub format_version: Option<u32>,
    #[serde(default)]
    pub created: String,
    #[serde(default)]
    pub session: String,
    /// Channels fitted: 3 (kd, ks and ks_over_kd list R, G, B) or 1 (a monochrome camera:
    /// one value each).
    pub channels: usize,
    /// True for a monochrome camera (`channels` 1).
    #[serde(default)]
    pub mono: bool,
    #[serde(default)]
    pub sampling: Sampling,
    #[serde(default)]
    pub solver: Solver,
    pub candidates: Vec<Candidate>,
    pub chosen: String,
    /// `absolute` (the rig's reference standard gave the factor that the lamp and the
    /// camera put on the radiance: each candidate's `absolute` holds kd and ks in 1/sr and
    /// the albedo) or `relative`; absent (older files): relative.
    #[serde(default)]
    pub units: Option<String>,
    /// What the reference standard gave, where the rig has one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reference: Option<Reference>,
    /// Held-out errors within this of the best count as equal.
    #[serde(default)]
    pub choice_tolerance: Option<f64>,
    #[serde(default)]
    pub warnings: Vec<String>,
    /// The camera refined with the highlight, where the grid photo left the pose weak.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera_refined: Option<CameraRefined>,
    /// Which candidates explain the tile within its noise, and what to do where none does
    /// (files written before 2026-12-07 have none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub verdict: Option<Verdict>,
    #[serde(default)]
    pub files: Vec<String>,
    #[serde(default)]
    pub seconds: Option<f64>,
}

/// Where the samples lie (the fit's `sampling.strategy`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Strategy {
    Line,
    Perpendicular,
    #[default]
    Cross,
    /// A line between two pixels (u0, v0, u1, v1).
    UserLine([f64; 4]),
    Rect,
    Random,
}

impl Strategy {
    /// The strategy's name; None for a user's line (its file entry is not one word).
    pub fn word(&self) -> Option<&'static str> {
        Some(match self {
            Strategy::Line => "line",
            Strategy::Perpendicular => "perpendicular",
            Strategy::Cross => "cross",
            Strategy::UserLine(_) => return None,
            Strategy::Rect => "rect",
            Strategy::Random => "random",
        })
    }
}

/// What became of saturated pixels.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Saturated {
    #[default]
    Exclude,
    Censor,
    Clip,
}

/// The highlight as found and as predicted.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct Highlight {
    /// Where the samples are centred (pixels).
    pub centre_px: [Option<f64>; 2],
    /// Peak of the radiance on the tile, or centre of the saturated patch.
    pub found_px: Option<[Option<f64>; 2]>,
    /// The mirror point the geometry predicts.
    pub predicted_px: [Option<f64>; 2],
    pub offset_px: Option<f64>,
    /// Tile pixels saturated in every exposure.
    pub saturated_pixels: usize,
    /// Of those, the ones at the highlight.
    pub saturated_at_highlight: usize,
    /// The predicted mirror point lies on the tile's usable pixels.
    pub mirror_on_tile: bool,
    /// The radiance peaks near the predicted mirror point.
    pub found_near_mirror: bool,
}

/// What sampling found (the samples themselves are in `fit/samples.csv`).
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[serde(default)]
pub struct Sampling {
    pub strategy: Strategy,
    pub requested: usize,
    pub used: usize,
    pub highlight: Highlight,
    /// The lines' end points in pixels (u0, v0, u1, v1), for line strategies.
    pub lines_px: Vec<[Option<f64>; 4]>,
    pub tile_pixels: usize,
    pub left_out_saturated: usize,
    pub left_out_bloom: usize,
    pub left_out_no_radiance: usize,
    pub censored: usize,
    /// What became of saturated pixels.
    pub saturated: Saturated,
    /// A demosaicked camera's colour filter layout ("RGGB", "GRBG", "GBRG", "BGGR"), where
    /// each sample kept only its photosite's own channel.
    pub mosaic: Option<String>,
    /// Where the layout came from: "detected" (the radiance's noise), "given" (--mosaic),
    /// "none seen", "off" (--mosaic off) or "unreadable" (monochrome, or too little
    /// unmasked image).
    pub mosaic_source: String,
    /// The detection's contrast: about 1 without a mosaic, 1.5 and more with one.
    pub mosaic_contrast: Option<f64>,
    pub warnings: Vec<String>,
    /// Samples in the fitting half and the held-out half (alternate samples).
    pub fitting_half: usize,
    pub held_out_half: usize,
}

/// How the fit was solved.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[serde(default)]
pub struct Solver {
    pub method: String,
    pub n_range: [Option<f64>; 2],
    pub grey_ks: bool,
    pub huber: Option<f64>,
    pub variances: String,
    /// Uncertainties carried into every parameter's besides the fit's own.
    pub propagated: Vec<String>,
}

/// Why the fit's Levenberg-Marquardt polish stopped, as levenberg-marquardt's
/// `TerminationReason` says it of its solver: a report, not an error (whether a polish
/// that did not converge makes the fit unusable is the caller's call).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Termination {
    /// The cost stopped falling (by 1e-15 of itself) or the step became negligible (1e-12
    /// of the largest parameter).
    #[default]
    Converged,
    /// No step lowered the cost however much it was damped (the damping passed 1e12): the
    /// polish stands where no descent is left to find, at the limit of the arithmetic.
    NoImprovementPossible,
    /// 100 iterations (the fitter's `MAX_POLISH_ITERATIONS`) without converging.
    LostPatience,
}

impl Termination {
    /// Converged.
    pub fn was_successful(self) -> bool {
        self == Termination::Converged
    }

    /// As a word for a report: "converged", "no_improvement_possible", "lost_patience".
    pub fn as_str(self) -> &'static str {
        match self {
            Termination::Converged => "converged",
            Termination::NoImprovementPossible => "no_improvement_possible",
            Termination::LostPatience => "lost_patience",
        }
    }
}

/// One candidate model. kd, ks and ks / kd have one entry per channel.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Candidate {
    /// The model's name (`lambert`, `phong`, `blinn-phong`, `cosine-lobe`, `ggx`).
    pub model: String,
    pub kd: Vec<Param>,
    #[serde(default)]
    pub ks: Vec<Param>,
    /// ks / kd per channel (scale-free).
    #[serde(default)]
    pub ks_over_kd: Vec<Param>,
    /// The exponent; its interval is computed on ln n.
    pub n: Option<Param>,
    /// The microfacet model's roughness α (ggx only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alpha: Option<Param>,
    #[serde(default)]
    pub chi2: Option<f64>,
    #[serde(default)]
    pub dof: usize,
    #[serde(default)]
    pub reduced_chi2: Option<f64>,
    #[serde(default)]
    pub bic: Option<f64>,
    /// Mean squared standardised residual per held-out value.
    #[serde(default)]
    pub held_out: Option<f64>,
    #[serde(default)]
    pub parameters: usize,
    #[serde(default)]
    pub inner_evaluations: usize,
    #[serde(default)]
    pub polish_evaluations: usize,
    /// Why the final polish stopped (files written before it was recorded have none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub polish_termination: Option<Termination>,
    #[serde(default)]
    pub ks_n_correlation: Option<f64>,
    /// Where the variance of ln n comes from (null when only the fit's own was counted).
    #[serde(default)]
    pub n_variance_share: Option<UncertaintyShare>,
    /// kd and ks in absolute terms, where the rig has a reference standard.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub absolute: Option<Absolute>,
    /// The parameters' covariance (files written before 2026-12-04 have none).
    #[serde(default)]
    pub covariance: Option<Covariance>,
    /// Whether the candidate explains the tile within its noise: its held-out residuals at
    /// most `verdict.limit_rms` times the noise (absent in files written before 2026-12-07).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub explains: Option<bool>,
    /// Where the samples do not separate the lobe's height (ks) from its width (n): why,
    /// in words; n's and ks/kd's intervals then hold only as far as the model does.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub trade_off: Option<String>,
    #[serde(default)]
    pub warnings: Vec<String>,
}

/// The fit's verdict: which candidates explain the tile within its noise.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct Verdict {
    /// The candidates whose held-out residuals are within `limit_rms` times the noise.
    pub explained_by: Vec<String>,
    /// True where none is.
    pub none_explains: bool,
    /// The candidate with the smallest held-out misfit, and that misfit as a multiple of
    /// the noise (root mean squared standardised residual on the held-out samples).
    pub best: String,
    pub best_held_out_rms: Option<f64>,
    /// The held-out misfit, in multiples of the noise, up to which a candidate explains
    /// the tile.
    pub limit_rms: f64,
    /// What would let a candidate explain the tile (or tell them apart), where none does.
    #[serde(default)]
    pub remedies: Vec<String>,
}

/// Shares of a parameter's variance by source.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct UncertaintyShare {
    pub fit: Option<f64>,
    pub calibration: Option<f64>,
    pub response: Option<f64>,
}

/// A candidate's parameters in absolute terms.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct Absolute {
    /// kd in 1/sr, per channel.
    #[serde(default)]
    pub kd_per_sr: Vec<Param>,
    /// The diffuse albedo, pi kd, per channel.
    #[serde(default)]
    pub albedo: Vec<Param>,
    /// ks in 1/sr, per channel (empty for a model without a lobe and for ggx).
    #[serde(default)]
    pub ks_per_sr: Vec<Param>,
    /// The microfacet model's F0, per channel (ggx only).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub f0: Vec<Param>,
}

/// A covariance of named parameters: kd and ks per channel in the fit's relative units,
/// and ln n. Entries not finite (a source the data did not bound) are null.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Covariance {
    pub parameters: Vec<String>,
    pub matrix: Vec<Vec<Option<f64>>>,
}

/// What the reference standard gave.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Reference {
    /// The certificate's reflectance and its standard uncertainty, per channel.
    #[serde(default)]
    pub reflectance: Vec<Option<f64>>,
    #[serde(default)]
    pub reflectance_sd: Vec<Option<f64>>,
    /// Pixels that see only the standard.
    #[serde(default)]
    pub pixels: usize,
    /// Of those, set aside as outliers.
    #[serde(default)]
    pub outliers: usize,
    /// The factor lamp intensity x camera gain per channel (radiance per unit BRDF).
    pub factor: Vec<Param>,
    /// The factor's relative standard deviation by source, per channel.
    #[serde(default)]
    pub factor_relative_sd: Vec<FactorSd>,
}

/// Sources of the reference factor's relative uncertainty.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct FactorSd {
    pub pixels: Option<f64>,
    pub certificate: Option<f64>,
    pub response: Option<f64>,
    pub total: Option<f64>,
}

/// The intrinsics of a camera as the files hold them.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// k1, k2, k3 (as many as fitted; absent terms are zero).
    pub radial: Vec<f64>,
    /// p1, p2, when fitted.
    pub tangential: Option<[f64; 2]>,
}

/// The camera refined with the highlight where the grid photo left the pose weak.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct CameraRefined {
    /// The refined camera: intrinsics, and the view's pose (grid to camera: Rodrigues
    /// vector, translation in mm).
    pub intrinsics: Intrinsics,
    pub rvec: [f64; 3],
    pub t: [f64; 3],
    /// Camera centre after and before, grid mm, and how far it moved.
    pub centre_mm: [f64; 3],
    #[serde(default)]
    pub centre_before_mm: [Option<f64>; 3],
    #[serde(default)]
    pub moved_mm: Option<f64>,
    #[serde(default)]
    pub moved_sd: Option<f64>,
    /// The tile's chi2 at the calibrated and at the refined camera.
    #[serde(default)]
    pub chi2_before: Option<f64>,
    #[serde(default)]
    pub chi2: Option<f64>,
    /// The chosen model's n at the calibrated camera and at the refined one.
    #[serde(default)]
    pub n_before: Option<f64>,
    #[serde(default)]
    pub n_after: Option<f64>,
    /// How far the camera moved against how far the stated uncertainties expect.
    #[serde(default)]
    pub tension: Option<f64>,
}
