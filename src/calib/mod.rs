//! Camera calibration from photos of the chessboard grid.

pub mod export;
pub mod lens;
pub mod run;

// The numerical half (the camera model, detection, the solve) lives in `glint-numerics`.
pub use glint_numerics::calib::{camera, detect, solve, tsai};

/// Luma of an 8-bit or 16-bit RGB or grey image, on detection's scale (0..255).
pub fn gray_from_image(img: &image::DynamicImage) -> detect::Gray {
    let g = img.to_luma32f();
    let (w, h) = (g.width() as usize, g.height() as usize);
    detect::Gray::new(w, h, g.into_raw().into_iter().map(|v| v * 255.0).collect())
}
