//! Reflectance fitting (paper sections 3.3, 3.4, 4): models and a fitter that needs no
//! start values.

pub mod file;
pub mod photometric;
pub mod reference;
pub mod run;
pub mod types;

// The numerical half (models, sampling, the solve, the pose) lives in `glint-numerics`.
pub use glint_numerics::fit::{choose, geometry, model, mosaic, pose, sample, solve};
