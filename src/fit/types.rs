//! The fit's shared types: its error, the file's format name, a reported parameter, and
//! the session's inputs (read by [`super::run`], [`super::reference`],
//! [`super::photometric`] and [`super::file`]). A leaf: it names no other module of the
//! fit's that names it.

use std::path::PathBuf;

use serde::Serialize;

use super::geometry::Scene;
use super::sample::{RadianceImage, SampleError};
use super::solve::Estimate;
use crate::calib::solve::Calibration;
use crate::session::{self, SessionError};

pub use glint_format::stage::fit::{FORMAT, FORMAT_VERSION};

#[derive(Debug, thiserror::Error)]
pub enum FitError {
    #[error("{path}: {reason}")]
    File { path: PathBuf, reason: String },
    #[error(transparent)]
    Session(#[from] SessionError),
    #[error(transparent)]
    Sample(#[from] SampleError),
    #[error(transparent)]
    Summary(#[from] SummaryError),
    #[error("{0}")]
    Input(String),
}

/// `hdr/summary.json` unusable (the messages name the file).
#[derive(Debug, thiserror::Error)]
pub enum SummaryError {
    #[error("{}: cannot read ({reason})", path.display())]
    Read { path: PathBuf, reason: String },
    #[error("{}: not JSON ({reason}); re-run glint hdr", path.display())]
    NotJson { path: PathBuf, reason: String },
    #[error("{}: exposures_us must list the bracket's exposures (positive µs); re-run glint hdr", path.display())]
    Exposures { path: PathBuf },
}

/// A parameter as reported: value, standard error, 95% interval. An unbounded end
/// (ks / kd where kd's interval reaches 0) is written as null.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Param {
    pub value: f64,
    pub sd: f64,
    pub ci95: [f64; 2],
}

impl Param {
    /// A parameter that is not negative (kd, ks): its normal interval cut at 0.
    pub(crate) fn of(e: &Estimate) -> Self {
        let [lo, hi] = e.ci95();
        Param {
            value: e.value,
            sd: e.sd,
            ci95: [lo.max(0.0), hi],
        }
    }

    /// As `fit/fit.json` holds it (not finite numbers as null).
    pub fn file(&self) -> glint_format::stage::fit::Param {
        glint_format::stage::fit::Param::of(self.value, self.sd, self.ci95)
    }
}

/// The session's inputs: scene and radiance.
pub struct Inputs {
    pub scene: Scene,
    pub width: usize,
    pub height: usize,
    /// Samples a pixel of `radiance`, `variance` and `mask`: 3 (RGB) or 1 (monochrome).
    pub channels: usize,
    pub radiance: Vec<f32>,
    pub variance: Vec<f32>,
    pub mask: Vec<u8>,
    /// Lower bound of a saturated value's radiance, per channel (infinite when unknown).
    pub saturation_level: [f64; 3],
    pub calibration: Calibration,
    /// The response the radiance was merged with (hdr/response.json), if there is one.
    pub response: Option<crate::hdr::response::Response>,
    /// The session's manifest (checked by [`session::open`]).
    pub manifest: session::Manifest,
    /// Warnings about the inputs (an incomplete session).
    pub warnings: Vec<String>,
    /// The rig's reference standard, if it has one.
    pub reference: Option<crate::rig::ReferenceSection>,
}

impl Inputs {
    pub fn image(&self) -> RadianceImage<'_> {
        RadianceImage {
            width: self.width,
            height: self.height,
            radiance: &self.radiance,
            variance: &self.variance,
            mask: &self.mask,
        }
    }
}
