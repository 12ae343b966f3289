//! # glint-numerics
//!
//! Glint's numerical stages on plain data: no devices, no session files, no async. Each
//! takes arrays and returns numbers with their uncertainties; the `glint` crate reads
//! sessions, calls these, and writes the results.
//! - [`hdr`]: camera response recovery and the variance-optimal merge of a bracket;
//! - [`calib`]: chessboard detection, the camera model and its calibration with
//!   uncertainties;
//! - [`fit`]: reflectance models, sampling the tile, the fit with no start values, the pose
//!   refined from the highlight, the model choice;
//! - [`validate`]: rendering the fitted models and comparing them with the photographs.

pub mod calib {
    //! Camera calibration from photos of the chessboard grid: the numerical half.
    pub mod camera;
    pub mod detect;
    pub mod solve;
    pub mod tsai;
}

pub mod fit {
    //! Reflectance fitting (paper sections 3.3, 3.4, 4): models and a fitter that needs no
    //! start values.
    pub mod choose;
    pub mod geometry;
    pub mod model;
    pub mod mosaic;
    pub mod pose;
    pub mod sample;
    pub mod solve;
}

pub mod hdr;

pub mod validate {
    //! Validation (paper section 4): renders of fitted models and their comparison with
    //! the photographs.
    pub mod compare;
    pub mod render;
}
