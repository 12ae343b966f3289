//! # glint-format
//!
//! The bottom of Glint's house: plain data every other crate shares, with no devices, no
//! numerics and no async.
//! - [`image`]: pixels and frames as a camera delivers them ([`image::Pixels`],
//!   [`image::Frame`]), what a camera is ([`image::CameraInfo`]), the lamp's state read back;
//! - [`fsx`]: reading and writing where Glint does not control the files (caps, no links,
//!   atomic replacement);
//! - [`stage`]: one type per stage file (`fit/fit.json`, `validation/validation.json`),
//!   used by its writer and every reader.

pub mod fsx;
pub mod image;
pub mod stage;
