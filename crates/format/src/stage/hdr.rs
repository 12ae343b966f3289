//! `hdr/summary.json`, the radiance summary, written by `glint hdr` and read by `glint fit`
//! and `glint report`. The field order is the file's.
//!
//! Read leniently, as the stages after the merge always read it: a field that is missing
//! or of another kind is `None` (or empty), so a file from an older Glint still gives
//! its report; the one field the fit needs, `exposures_us`, is checked by the fit.

use serde::{Deserialize, Serialize};

use super::lenient;

/// Where the response came from: `{"kind": "file"|"profile", "path": ...}` or
/// `{"kind": "recovered"}`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ResponseSource {
    #[serde(default, deserialize_with = "lenient::text")]
    pub kind: Option<String>,
    #[serde(
        default,
        deserialize_with = "lenient::text",
        skip_serializing_if = "Option::is_none"
    )]
    pub path: Option<String>,
}

/// `hdr/summary.json`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    #[serde(default, deserialize_with = "lenient::text")]
    pub session: Option<String>,
    /// The session's state (`complete` unless merged with --allow-incomplete).
    #[serde(default, deserialize_with = "lenient::text")]
    pub state: Option<String>,
    #[serde(default, deserialize_with = "lenient::response")]
    pub response: ResponseSource,
    #[serde(default, deserialize_with = "lenient::text")]
    pub model: Option<String>,
    /// The profile written (a newly recovered response), if any.
    #[serde(default, deserialize_with = "lenient::text")]
    pub profile_written: Option<String>,
    #[serde(default, deserialize_with = "lenient::count")]
    pub width: Option<u64>,
    #[serde(default, deserialize_with = "lenient::count")]
    pub height: Option<u64>,
    #[serde(default, deserialize_with = "lenient::count")]
    pub bit_depth: Option<u64>,
    /// Channels of the frames and of radiance.exr: 3 (R, G, B) or 1.
    #[serde(default, deserialize_with = "lenient::count")]
    pub channels: Option<u64>,
    /// The bracket's exposures, µs (an entry that is not a number: None).
    #[serde(default, deserialize_with = "lenient::nums")]
    pub exposures_us: Option<Vec<Option<f64>>>,
    #[serde(default, deserialize_with = "lenient::count")]
    pub dark_frames: Option<u64>,
    /// Samples (pixel x channel) with radiance, saturated in every frame, too dark in
    /// every frame.
    #[serde(default, deserialize_with = "lenient::count")]
    pub samples_measured: Option<u64>,
    #[serde(default, deserialize_with = "lenient::count")]
    pub samples_saturated: Option<u64>,
    #[serde(default, deserialize_with = "lenient::count")]
    pub samples_too_dark: Option<u64>,
    /// Range of measured radiance (exposure units per second).
    #[serde(default, deserialize_with = "lenient::num")]
    pub radiance_min: Option<f64>,
    #[serde(default, deserialize_with = "lenient::num")]
    pub radiance_max: Option<f64>,
    /// Median relative standard deviation of the measured radiance.
    #[serde(default, deserialize_with = "lenient::num")]
    pub median_relative_sd: Option<f64>,
    #[serde(default, deserialize_with = "lenient::texts")]
    pub warnings: Vec<String>,
    #[serde(default, deserialize_with = "lenient::texts")]
    pub notes: Vec<String>,
    #[serde(default, deserialize_with = "lenient::texts")]
    pub files: Vec<String>,
    #[serde(default, deserialize_with = "lenient::num")]
    pub seconds: Option<f64>,
}
