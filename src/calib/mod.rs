//! Camera calibration from photos of the chessboard grid.

pub mod camera;
pub mod detect;
pub mod export;
pub mod lens;
pub mod run;
pub mod solve;
pub mod tsai;
