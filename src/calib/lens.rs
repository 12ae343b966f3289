//! The camera's lens profile: its intrinsics with their covariance, recovered once from a
//! lens session (the board shown in several tilted poses, [`crate::plan::Plan::for_lens`])
//! and kept beside the rig like the camera's response profile, so that every later
//! session holds the lens and fits only the pose from its one grid photo.
//!
//! The file is `<rig folder>/profiles/<camera model>-<W>x<H>.lens.json`: a `camera.json`
//! of the lens session (format `glint-camera`, so `--intrinsics` reads it too) with a
//! `lens_profile` section saying where it came from and which checks it passed. The
//! resolution is in the name and in the file, and a session at another resolution is
//! refused by the loader. A profile is created new, never replaced unless asked.

use std::path::{Path, PathBuf};

use serde::Serialize;

use super::run::{CameraFile, Known, RunError};

/// Fewest views with a grid a lens profile is made from.
pub const MIN_VIEWS: usize = 4;
/// Smallest share of the lens plan's poses (views tried) the grid must be found in, half: a
/// plan that lost more has lost the tilts that pin the principal point and the focal
/// length (on a simulated 1280x960 camera with a long lens and its principal point 34 px
/// off, the board left the frame in 5 of 9 poses at 30 degrees; the 4 left passed every
/// other check, yet tilted about x one way only, and put the principal point 2.6 sd off
/// and the camera centre 0.40 mm).
pub const MIN_FOUND_SHARE: f64 = 0.5;
/// Largest RMS reprojection error of a lens profile, pixels.
pub const MAX_RMS_PX: f64 = 1.0;
/// Largest relative standard deviation of the focal length of a lens profile.
pub const MAX_F_REL_SD: f64 = 0.005;
/// Smallest spread of the board's normal among the views, degrees, about each of two
/// axes (rms angle from the mean normal): views all tilted the same way cannot separate
/// the focal length from the distance.
pub const MIN_TILT_SPREAD_DEG: f64 = 5.0;

/// The checks a lens calibration passed, stored in the profile.
#[derive(Debug, Clone, Serialize)]
pub struct LensChecks {
    pub views: usize,
    pub rms_px: f64,
    /// Relative standard deviation of the focal length (fx where fx and fy are apart).
    pub f_rel_sd: f64,
    /// Spread of the board's normal about the two axes it varies most about, degrees.
    pub tilt_spread_deg: [f64; 2],
}

/// The profile of camera `model` at `width` x `height` for the rig file `rig`:
/// `<rig folder>/profiles/<model>-<W>x<H>.lens.json` (the model's characters other than
/// letters, digits, `-` and `_` become `-`, at most 100 of them). None where the rig's
/// folder is not a folder.
pub fn profile_path(rig: &Path, model: &str, width: u32, height: u32) -> Option<PathBuf> {
    crate::rig::profile_file(rig, model, &format!("-{width}x{height}.lens.json"))
}

/// Why a calibration may not become the camera's lens profile ([`check`]), on one line.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NotAProfile {
    #[error("the grid was found in {views} view(s); a lens profile needs at least {MIN_VIEWS} (show the whole board in each pose: with glint lens, a smaller --tilt-deg, e.g. 20, keeps it in the frame)")]
    TooFewViews { views: usize },
    /// `border`: the poses skipped because the board showed only in part.
    #[error("the grid was found in {views} of {tried} poses; a lens profile needs at least {:.0}% of them ({})", 100.0 * MIN_FOUND_SHARE, found_advice(*.border))]
    TooFewFound {
        views: usize,
        tried: usize,
        border: usize,
    },
    #[error("the reprojection error is {rms_px:.3} px RMS; a lens profile needs at most {MAX_RMS_PX} px (a blurred or moving board?)")]
    Rms { rms_px: f64 },
    #[error("the calibration's covariance is not finite")]
    Covariance,
    #[error("the calibration fitted no focal length")]
    NoFocalLength,
    #[error("the focal length is {value:.1} ± {sd:.1} px ({:.2}%); a lens profile needs at most {:.1}% (tilt the board more, or show it in more poses)", 100.0 * .rel_sd, 100.0 * MAX_F_REL_SD)]
    FocalLength { value: f64, sd: f64, rel_sd: f64 },
    #[error("the board's tilt varies by {:.1}° and {:.1}° (rms) about the two axes; a lens profile needs at least {MIN_TILT_SPREAD_DEG}° about each (tilt the board about both of its axes)", .spread_deg[0], .spread_deg[1])]
    Tilt { spread_deg: [f64; 2] },
}

/// What to do when too few poses showed the grid, `border` of them because the board
/// showed only in part.
fn found_advice(border: usize) -> String {
    if border > 0 {
        format!(
            "{border} showed the board only in part; glint lens with a smaller --tilt-deg (30 by default; e.g. 20) keeps it in the frame"
        )
    } else {
        "see why each was skipped in camera.json's skipped list".into()
    }
}

/// Whether a calibration may become the camera's lens profile: enough views, a small
/// reprojection error, the board's tilt varied about two axes, every covariance finite and
/// the focal length's standard deviation small. The checks, or why not (one line).
pub fn check(file: &CameraFile) -> Result<LensChecks, NotAProfile> {
    let cal = &file.calibration;
    let views = cal.views.len();
    if views < MIN_VIEWS {
        return Err(NotAProfile::TooFewViews { views });
    }
    let tried = views + file.skipped.len();
    if (views as f64) < MIN_FOUND_SHARE * tried as f64 {
        let border = file
            .skipped
            .iter()
            .filter(|s| s.contains(super::detect::AT_BORDER))
            .count();
        return Err(NotAProfile::TooFewFound {
            views,
            tried,
            border,
        });
    }
    if !(cal.rms_px.is_finite() && cal.rms_px <= MAX_RMS_PX) {
        return Err(NotAProfile::Rms { rms_px: cal.rms_px });
    }
    if cal
        .views
        .iter()
        .any(|v| v.covariance.iter().flatten().any(|x| !x.is_finite()))
    {
        return Err(NotAProfile::Covariance);
    }
    let f = cal
        .parameters
        .first()
        .filter(|p| p.name == "f" || p.name == "fx")
        .ok_or(NotAProfile::NoFocalLength)?;
    let f_rel_sd = f.sd / f.value;
    if !(f_rel_sd.is_finite() && f_rel_sd <= MAX_F_REL_SD) {
        return Err(NotAProfile::FocalLength {
            value: f.value,
            sd: f.sd,
            rel_sd: f_rel_sd,
        });
    }
    let spread = tilt_spread_deg(file);
    if spread[1] < MIN_TILT_SPREAD_DEG {
        return Err(NotAProfile::Tilt { spread_deg: spread });
    }
    Ok(LensChecks {
        views,
        rms_px: cal.rms_px,
        f_rel_sd,
        tilt_spread_deg: spread,
    })
}

/// The rms angle of the board's normals (in the camera's frame) from their mean, about
/// the two axes it varies most about, degrees (larger first).
pub fn tilt_spread_deg(file: &CameraFile) -> [f64; 2] {
    let normals: Vec<nalgebra::Vector3<f64>> = file
        .rotations
        .iter()
        .map(|r| nalgebra::Vector3::new(r[0][2], r[1][2], r[2][2]))
        .collect();
    if normals.len() < 2 {
        return [0.0; 2];
    }
    let n = normals.len() as f64;
    let mean = normals.iter().sum::<nalgebra::Vector3<f64>>() / n;
    let mut m = nalgebra::Matrix3::zeros();
    for v in &normals {
        let d = v - mean;
        m += d * d.transpose() / n;
    }
    let mut ev: Vec<f64> = m.symmetric_eigenvalues().iter().copied().collect();
    ev.sort_by(|a, b| b.total_cmp(a));
    [ev[0], ev[1]].map(|l| l.max(0.0).sqrt().min(1.0).asin().to_degrees())
}

/// What became of the profile.
#[derive(Debug, Clone, Serialize)]
#[serde(tag = "outcome", rename_all = "kebab-case")]
pub enum Stored {
    Written {
        path: PathBuf,
    },
    /// One exists and was kept (no `--replace-profile`).
    Kept {
        path: PathBuf,
    },
}

/// Store a lens session's calibration as the camera's lens profile at `path`: created
/// new (an existing profile is kept unless `replace`; a link is never followed).
pub fn store(
    path: &Path,
    file: &CameraFile,
    checks: &LensChecks,
    session: &Path,
    camera: &str,
    replace: bool,
) -> Result<Stored, RunError> {
    let exists = path.symlink_metadata().is_ok();
    if exists && !replace {
        return Ok(Stored::Kept { path: path.into() });
    }
    let bad = |reason: String| RunError::File {
        path: path.into(),
        reason,
    };
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        crate::fsx::ensure_dir(parent).map_err(|e| bad(format!("cannot make its folder ({e})")))?;
    }
    let mut v = serde_json::to_value(file).expect("the calibration serialises");
    v["lens_profile"] = serde_json::json!({
        "camera": camera,
        "width": file.calibration.width,
        "height": file.calibration.height,
        "from_session": session.display().to_string(),
        "checks": checks,
    });
    let bytes = serde_json::to_vec_pretty(&v).expect("JSON serialises");
    if exists {
        // Asked to replace: written beside it and renamed over it (atomic).
        crate::session::write_replace(path, &bytes)?;
    } else {
        crate::fsx::create_new(path, &bytes).map_err(|e| {
            bad(if e.kind() == std::io::ErrorKind::AlreadyExists {
                "appeared while calibrating; it is kept (use --replace-profile to replace it)"
                    .into()
            } else {
                format!("cannot write ({e})")
            })
        })?;
    }
    Ok(Stored::Written { path: path.into() })
}

/// The camera's lens profile for a rig file and camera, if there is one: None where there
/// is no profile file; an error where there is one that cannot be used (it names the
/// file and what to do).
pub fn load(rig: &Path, model: &str, width: u32, height: u32) -> Result<Option<Known>, RunError> {
    let Some(path) = profile_path(rig, model, width, height) else {
        return Ok(None);
    };
    // The profile is `profiles/NAME` beside the rig: read through no link below the rig's
    // folder, as a session's files are below the session's.
    let file = crate::fsx::Within::last(&path, 2);
    if !file.is_there() {
        return Ok(None);
    }
    let k = super::run::load_known(&file).map_err(|e| {
        RunError::Input(format!(
            "{e} (the camera's lens profile: re-run glint lens --rig {} --replace-profile, or pass --no-lens-profile)",
            rig.display()
        ))
    })?;
    if (k.width, k.height) != (width as usize, height as usize) {
        return Err(RunError::Input(format!(
            "{}: a lens profile for {}x{} but the camera delivers {width}x{height}; re-run glint lens --rig {} --replace-profile",
            path.display(),
            k.width,
            k.height,
            rig.display()
        )));
    }
    Ok(Some(k))
}
