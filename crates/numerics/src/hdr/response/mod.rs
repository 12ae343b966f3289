//! Camera response curves: recovery from a bracket, noise model, inverse response.
//!
//! A response maps a pixel value z to the relative *exposure* E (radiance x time) that
//! produced it, per channel. Three models, fitted at every bit depth and scored on the
//! same readings (a 16-bit camera may apply a tone curve as well as an 8-bit one), the
//! simplest whose shape fits as well as any chosen:
//! - **Polynomial**: ln E a polynomial (Chebyshev basis) in ln z, degree by BIC.
//! - **Debevec & Malik** (1997): g(z) = ln E(z) as a free table of 256 values (above 8 bits,
//!   on 256 bins of values), recovered by weighted least squares with a smoothness term and
//!   the gauge g(128) = 0. Glint chooses its sample pixels deliberately (see
//!   [`select_samples`]) and checks the result (monotonic, determined by the data, not
//!   dominated by smoothing).
//! - **Linear**: E = (z - black) x gain, the black level from dark frames where there are
//!   any; a linear curve whose residuals show structure is reported as not linear.
//!
//! Each channel also carries a noise model in exposure units,
//! var(E) = shot x E + read + quantisation(z), estimated from the bracket itself, which the
//! merge uses for variance-optimal weights and per-pixel variances; and its misfit beyond
//! that noise, which [`Response::draws_at`] draws with the curve's own uncertainty.
//!
//! One file a job: [`curve`] the types, [`draws`] their uncertainty as curves, [`samples`]
//! the sample pixels, one file per model ([`debevec`], [`polynomial`] with its [`basis`],
//! [`linear`]), [`checks`] and [`score`] that judge a fitted curve, [`noise`] the noise
//! model, [`recover`] that runs them all and chooses, [`borrow`] that continues a channel known
//! only to mid-scale with another's shape, and [`alternatives`] the other models' curves
//! that fit nearly as well.

pub mod alternatives;
mod basis;
mod borrow;
mod checks;
mod curve;
mod debevec;
mod draws;
mod linear;
mod noise;
mod polynomial;
mod recover;
mod samples;
mod score;

pub use basis::MAX_DEGREE;
pub use curve::{
    channel_name, Alternative, Channel, ChoiceReport, Model, ModelChoice, Noise, RecoverOptions,
    Response, CHANNELS, FORMAT, FORMAT_VERSION, LN_EXPOSURE_LIMIT,
};
pub use draws::CurveDraws;
pub use recover::{recover, recover_with};
pub use samples::{default_samples, median, select_samples, Samples, MAX_DEBEVEC_SAMPLES};
