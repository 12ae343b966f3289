//! Camera calibration from photos of the chessboard grid.

pub mod detect;
