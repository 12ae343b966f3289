//! # Glint
//!
//! Glint measures how a flat material tile reflects light, after Schirmacher et al.,
//! "Image-Based BRDF Reconstruction" (1999): it drives a camera and a lamp through exposure
//! brackets, writes self-describing session directories, merges HDR radiance, calibrates the
//! camera from a chessboard grid, fits reflectance models and validates them by rendering.
//!
//! This crate is the library; the `glint` binary is a thin command line over it.
//! Module map:
//! - [`rig`]: rig files (TOML), validated with errors that name the file, key and fix;
//! - [`devices`]: camera, lamp and operator traits, the serial lamp driver, the mock adapters;
//! - [`plan`]: capture plans (data), checked and estimated without devices;
//! - [`session`]: the session directory format, its frame records, atomic writes,
//!   verification;
//! - [`capture`]: the one engine that runs plans on the devices, recording into a session;
//! - [`fsx`]: reading and writing where Glint does not control the files (caps, no links);
//! - [`hdr`]: camera response recovery, the variance-optimal merge, EXR output;
//! - [`import`]: a folder of bracketed photos from any camera -> a session;
//! - [`calib`]: chessboard detection and camera calibration with uncertainties;
//! - [`fit`]: reflectance models fitted with no start values, and the model choice;
//! - [`validate`]: renders of the fitted models compared with the photographs;
//! - [`report`]: the session's self-contained HTML report; [`sketch`]: its drawing of the
//!   rig's geometry;
//! - [`pipeline`]: `glint run`, every stage in one go;
//! - [`daemon`]: `glint daemon`, the rig held by a service that queues jobs and streams events.

pub mod calib;
pub mod capture;
pub mod daemon;
pub mod export;
pub mod fit;
pub mod hdr;
pub mod import;
pub mod pipeline;
pub mod plan;
pub mod report;
pub mod session;
pub mod sketch;
pub mod validate;

// The crates beneath, under the paths they had when they were modules of this one.
pub use glint_devices::{self as devices, rig};
pub use glint_format::fsx;

/// Glint's version, recorded in every session.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");
