//! HDR on plain data: brackets of frames ([`Bracket`]), camera response recovery
//! ([`response`]) and the variance-optimal merge ([`merge`]). No I/O: the stage that reads
//! sessions and writes files is the `glint` crate's `hdr` module.

mod bracket;
mod error;
pub mod merge;
pub mod response;

pub use bracket::{Bracket, BracketFrame, DarkMedian, MAX_EXPOSURE_US, MIN_EXPOSURE_US};
pub use error::{CurveError, CurveProblem, MergeError};
