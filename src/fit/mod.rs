//! Reflectance fitting (paper sections 3.3, 3.4, 4): models and a fitter that needs no
//! start values.

pub mod choose;
pub mod file;
pub mod geometry;
pub mod model;
pub mod photometric;
pub mod pose;
pub mod reference;
pub mod run;
pub mod sample;
pub mod solve;
