//! `glint calibrate`: a session's grid photo, or several photos of a grid, to
//! `calib/camera.json` and `calib/corners.png`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use super::camera::{project, rotation};
use super::detect::{detect, detect_linear, DetectError, Gray};
use super::solve::{calibrate, pose_with_lens, Calibration, LensCovariance, Options, ViewObs};
use crate::hdr::response::Response;
use crate::plan::FrameKind;
use crate::session;

pub mod types;
use types::RADIAL_PROBLEM;
pub use types::{
    intrinsics_problem, CameraFile, Detected, GridSpec, Known, RunError, FORMAT, FORMAT_VERSION,
};

/// A photo decoded within Glint's limits (its header is checked first: a small file
/// claiming a huge image is refused before anything is allocated).
fn decoded(path: &Path, bytes: &[u8]) -> Result<image::DynamicImage, RunError> {
    let (_, img) = crate::hdr::decode_image(bytes).map_err(|reason| RunError::File {
        path: path.into(),
        reason: reason.to_string(),
    })?;
    Ok(img)
}

/// The photo in linear light: each channel's value through the response `r` to relative
/// exposure (then luma, as [`crate::calib::gray_from_image`], for colour), scaled so that the full
/// scale is near 255. None where the photo's channels or depth are not the response's.
pub fn linear_grey(img: &image::DynamicImage, r: &Response) -> Option<Gray> {
    use image::DynamicImage as D;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let channels = r.channel_count();
    let max = r.max_value();
    let (values, ch): (Vec<u32>, usize) = match img {
        D::ImageLuma8(b) => (b.as_raw().iter().map(|&v| v as u32).collect(), 1),
        D::ImageLuma16(b) => (b.as_raw().iter().map(|&v| v as u32).collect(), 1),
        D::ImageRgb8(b) => (b.as_raw().iter().map(|&v| v as u32).collect(), 3),
        D::ImageRgb16(b) => (b.as_raw().iter().map(|&v| v as u32).collect(), 3),
        _ => return None,
    };
    let depth_max = match img {
        D::ImageLuma8(_) | D::ImageRgb8(_) => 255,
        _ => 65535,
    };
    if ch != channels || depth_max < max {
        return None;
    }
    // Per channel: a table from value to exposure (the curve evaluated once per value).
    let tables: Vec<Vec<f32>> = (0..ch)
        .map(|c| {
            (0..=max)
                .map(|z| r.exposure(c, z as f64).max(0.0) as f32)
                .collect()
        })
        .collect();
    let full: f64 = (0..ch).map(|c| tables[c][max as usize] as f64).sum::<f64>() / ch as f64;
    if !(full.is_finite() && full > 0.0) {
        return None;
    }
    let scale = (255.0 / full) as f32;
    let weights: &[f32] = if ch == 1 {
        &[1.0]
    } else {
        &[0.2126, 0.7152, 0.0722]
    };
    let data = values
        .chunks_exact(ch)
        .map(|px| {
            px.iter()
                .zip(weights)
                .enumerate()
                .map(|(c, (&z, &wt))| wt * tables[c][z.min(max) as usize])
                .sum::<f32>()
                * scale
        })
        .collect();
    Some(Gray::new(w, h, data))
}

/// Whether a pose is finite and bounded (|rvec| <= 100, |t| <= 1e9 mm per component).
pub fn pose_is_bounded(p: &crate::calib::camera::Pose) -> bool {
    p.rvec.iter().all(|x| x.is_finite() && x.abs() <= 100.0)
        && p.t.iter().all(|x| x.is_finite() && x.abs() <= 1e9)
}

/// What makes a calibration unusable (None when it is fine): the image size within
/// 1..=16384 a side, focal lengths positive, the principal point near the image, at most
/// 3 radial terms, every number finite and bounded, standard deviations not negative, and
/// each view's covariance (where present) square over the fitted intrinsics and the pose,
/// with no negative variance. The rules of every camera file Glint reads: a session's
/// `calib/camera.json`, a lens profile beside the rig, `--intrinsics`.
pub fn calibration_problem(c: &Calibration) -> Option<String> {
    let max = crate::session::MAX_SIDE as usize;
    if c.width == 0 || c.height == 0 || c.width > max || c.height > max {
        return Some(format!(
            "calibration: {}x{} is not an image size (1..{max} per side)",
            c.width, c.height
        ));
    }
    if let Some(p) = intrinsics_problem(&c.intrinsics, c.width, c.height) {
        return Some(p);
    }
    if c.fit.radial > 3 {
        return Some(RADIAL_PROBLEM.into());
    }
    if let Some(p) = c
        .parameters
        .iter()
        .find(|p| !(p.sd.is_finite() && p.sd >= 0.0))
    {
        return Some(format!(
            "calibration.parameters: {}'s sd = {} must be finite and not negative",
            crate::fsx::quote(&p.name),
            p.sd
        ));
    }
    let n = c.fit.intrinsic_count() + 6;
    for (i, v) in c.views.iter().enumerate() {
        let sd_ok = |x: &f64| x.is_finite() && *x >= 0.0;
        if !(v.pose_sd.iter().all(sd_ok) && v.camera_centre_sd.iter().all(sd_ok)) {
            return Some(format!(
                "calibration.views[{i}]: pose_sd and camera_centre_sd must be finite and not negative"
            ));
        }
        if v.covariance
            .iter()
            .enumerate()
            .any(|(j, r)| r.get(j).is_some_and(|x| *x < 0.0))
        {
            return Some(format!(
                "calibration.views[{i}].covariance: a variance (its diagonal) is negative"
            ));
        }
        if !pose_is_bounded(&v.pose) {
            return Some(format!(
                "calibration.views[{i}].pose: rvec and t must be finite and bounded"
            ));
        }
        if !(v.covariance.is_empty()
            || v.covariance.len() == n
                && v.covariance
                    .iter()
                    .all(|r| r.len() == n && r.iter().all(|x| x.is_finite())))
        {
            return Some(format!(
                "calibration.views[{i}].covariance: must be empty or {n}x{n} finite values (the fitted intrinsics and the pose)"
            ));
        }
    }
    None
}

/// Read and check a `camera.json` (size-capped, a regular file): its format, a positive
/// square size (or none), a usable calibration ([`calibration_problem`]). Returns the file
/// (its one type, [`CameraFile`]) and its calibration; errors name the file and what to
/// fix.
pub fn load_camera_file(
    file: impl Into<crate::fsx::Within>,
) -> Result<(CameraFile, Calibration), RunError> {
    let file = file.into();
    let path = &file.path();
    let bad = |reason: String| RunError::File {
        path: path.into(),
        reason,
    };
    let text = file
        .read_text(crate::fsx::MAX_TEXT_BYTES)
        .map_err(|e| bad(format!("cannot read ({e})")))?;
    let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| {
        bad(format!(
            "not JSON ({}); re-run glint calibrate",
            crate::fsx::json_error(&e)
        ))
    })?;
    if v["format"] != FORMAT {
        return Err(bad(format!(
            "not a {FORMAT} file (written by glint calibrate)"
        )));
    }
    let sq = &v["grid"]["square_mm"];
    if !sq.is_null()
        && !sq
            .as_f64()
            .is_some_and(|s| s.is_finite() && s > 0.0 && s <= 1e4)
    {
        return Err(bad(format!(
            "grid.square_mm = {}: the square size must be positive (mm, at most 10000); re-run glint calibrate",
            crate::fsx::quote(&sq.to_string())
        )));
    }
    // The format and the square size first, read as they are, for the messages above.
    let c: CameraFile = serde_json::from_value(v).map_err(|e| {
        bad(format!(
            "not a glint-camera file ({}); re-run glint calibrate",
            crate::fsx::json_error(&e)
        ))
    })?;
    if let Some(p) = calibration_problem(&c.calibration) {
        return Err(bad(format!("{p}; re-run glint calibrate")));
    }
    let cal = c.calibration.clone();
    Ok((c, cal))
}

/// Read the intrinsics of a `camera.json` (checked as [`load_camera_file`] does), or of
/// an OpenCV FileStorage or ROS camera_info YAML (a name ending `.yaml` or `.yml`; see
/// [`super::export::read_intrinsics_yaml`]: no covariance, the lens is held as exact).
pub fn load_known(file: impl Into<crate::fsx::Within>) -> Result<Known, RunError> {
    let file = file.into();
    let path = &file.path();
    let yaml = path
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("yaml") || e.eq_ignore_ascii_case("yml"));
    if yaml {
        return super::export::read_intrinsics_yaml(&file);
    }
    let (_, cal) = load_camera_file(&file)?;
    let n = cal.fit.intrinsic_count();
    let covariance = cal
        .views
        .first()
        .filter(|v| n > 0 && v.covariance.len() >= n)
        .map(|v| LensCovariance {
            fit: cal.fit,
            covariance: nalgebra::DMatrix::from_fn(n, n, |i, j| v.covariance[i][j]),
        });
    Ok(Known {
        from: path.into(),
        width: cal.width,
        height: cal.height,
        intrinsics: cal.intrinsics,
        covariance,
    })
}

/// Calibrate a session from its grid photo(s) (several frames of the grid are averaged);
/// with `known` intrinsics only the pose is fitted.
pub fn run_session(dir: &Path, known: Option<&Known>) -> Result<CameraFile, RunError> {
    run_session_allowing(dir, known, false)
}

/// The response the grid photos are linearised with: `given` (a camera profile, with
/// where it is from), else the session's own `hdr/response.json` where HDR has run, else
/// none (the corners are then refined on the photo's values as they are).
fn session_response(
    dir: &Path,
    given: Option<(&Response, &str)>,
) -> Result<Option<(Response, String)>, RunError> {
    if let Some((r, from)) = given {
        return Ok(Some((r.clone(), from.to_string())));
    }
    let file = crate::fsx::Within::new(dir, "hdr/response.json");
    let p = file.path();
    if !file.is_there() {
        return Ok(None);
    }
    let r = crate::hdr::files::load_response(&file).map_err(|e| RunError::File {
        path: p.clone(),
        reason: format!(
            "{}; run glint hdr again (the grid photo is linearised with it)",
            match e {
                crate::hdr::HdrError::File { reason, .. } => reason,
                other => other.to_string(),
            }
        ),
    })?;
    Ok(Some((r, "hdr/response.json".into())))
}

/// [`run_session`], on a session that is not complete too if `allow_incomplete` (with a
/// warning in the calibration's warnings).
pub fn run_session_allowing(
    dir: &Path,
    known: Option<&Known>,
    allow_incomplete: bool,
) -> Result<CameraFile, RunError> {
    run_session_with(dir, known, allow_incomplete, None)
}

/// [`run_session_allowing`], the grid photos linearised with `response` (a camera
/// profile, and where it is from) where given ([`session_response`]).
pub fn run_session_with(
    dir: &Path,
    known: Option<&Known>,
    allow_incomplete: bool,
    response: Option<(&Response, &str)>,
) -> Result<CameraFile, RunError> {
    let start = Instant::now();
    let m = session::open(dir, allow_incomplete)?;
    let response = session_response(dir, response)?;
    session::check_out_dir(&dir.join("calib"))?;
    let rig = m.rig.as_ref().ok_or_else(|| {
        RunError::Input(format!(
            "{}: the session has no rig (an imported session); use glint calibrate --images PHOTO --grid NxM",
            dir.display()
        ))
    })?;
    let g = &rig.geometry;
    let spec = GridSpec {
        inner_corners: [
            g.grid_inner_corners[0] as usize,
            g.grid_inner_corners[1] as usize,
        ],
        square_mm: Some(g.grid_square_mm),
    };
    // One view per board pose of a lens session (its plan shows the board in poses);
    // otherwise every grid frame is of the one view, averaged.
    let grids: Vec<&session::FrameRecord> = m
        .frames
        .iter()
        .filter(|f| f.kind == FrameKind::Grid)
        .collect();
    let groups = m.plan.grid_groups();
    let lens_session = groups.iter().any(|(p, _)| p.is_some());
    let mut views: Vec<(String, Vec<&session::FrameRecord>)> = Vec::new();
    if lens_session {
        let mut rest = grids.as_slice();
        for (pose, count) in &groups {
            let take = (*count as usize).min(rest.len());
            if take == 0 {
                break;
            }
            let name = match pose {
                Some(p) => format!("board pose {}", p.index),
                None => "grid".into(),
            };
            views.push((name, rest[..take].to_vec()));
            rest = &rest[take..];
        }
        if !rest.is_empty() {
            views.push(("grid (frames beyond the plan)".into(), rest.to_vec()));
        }
    } else if !grids.is_empty() {
        views.push(("grid".into(), grids));
    }
    if views.is_empty() {
        return Err(RunError::Input(format!(
            "{}: the session has no grid frame; capture one (the bracket's grid_frames) or use glint calibrate --images",
            dir.display()
        )));
    }
    let mut imgs = Vec::new();
    let mut linears = Vec::new();
    // Linear light for every frame, or for none.
    let mut all_linear = response.is_some();
    for (name, frames) in &views {
        let mut sum: Option<Gray> = None;
        let mut lin_sum: Option<Gray> = None;
        for f in frames {
            let path = dir.join(&f.file);
            let bytes = session::read_verified(dir, f, m.channels())
                .map_err(|(path, reason)| RunError::File { path, reason })?;
            let img = decoded(&path, &bytes)?;
            let g = crate::calib::gray_from_image(&img);
            if all_linear {
                match response.as_ref().and_then(|(r, _)| linear_grey(&img, r)) {
                    Some(l) => match &mut lin_sum {
                        None => lin_sum = Some(l),
                        Some(s) if (s.width, s.height) == (l.width, l.height) => {
                            s.data.iter_mut().zip(&l.data).for_each(|(a, b)| *a += b)
                        }
                        Some(_) => all_linear = false,
                    },
                    None => all_linear = false,
                }
            }
            if (g.width as u64, g.height as u64) != (f.width as u64, f.height as u64) {
                return Err(RunError::File {
                    path,
                    reason: format!(
                        "decodes as {}x{} but the manifest lists {}x{}; the frame or the manifest was altered",
                        g.width, g.height, f.width, f.height
                    ),
                });
            }
            match &mut sum {
                None => sum = Some(g),
                Some(s) => {
                    if (s.width, s.height) != (g.width, g.height) {
                        return Err(RunError::Input(format!(
                            "{}: grid frames differ in size",
                            f.file
                        )));
                    }
                    s.data.iter_mut().zip(&g.data).for_each(|(a, b)| *a += b);
                }
            }
        }
        let n = frames.len();
        let mut img = sum.expect("each view has a frame");
        img.data.iter_mut().for_each(|v| *v /= n as f32);
        let name = format!(
            "{name} ({n} frame{} averaged)",
            if n == 1 { "" } else { "s" }
        );
        imgs.push((name, img));
        linears.push(lin_sum);
    }
    let out = dir.join("calib");
    session::out_dir(&out)?;
    let refined = refined_on(match &response {
        Some((_, from)) if all_linear => RefinedOn::Linear(from),
        Some((_, from)) => RefinedOn::Values(format!(
            "the response {from} does not fit the grid frames' channels or depth"
        )),
        None => RefinedOn::Values(
            "no response known: HDR has not run and no camera profile was given".into(),
        ),
    });
    let lin: Vec<Option<&Gray>> = if all_linear {
        linears.iter().map(|l| l.as_ref()).collect()
    } else {
        vec![None; imgs.len()]
    };
    let mut file = solve_images(&imgs, &lin, spec, start, known, refined)?;
    if let Some(w) = session::incomplete_warning(&m) {
        file.calibration.warnings.insert(0, w);
    }
    // The picture of each view whose grid was found, in the order of the views.
    let shown: Vec<&Gray> = imgs
        .iter()
        .filter(|(name, _)| file.detections.iter().any(|d| &d.name == name))
        .map(|(_, g)| g)
        .collect();
    write(&out, &file, &shown)?;
    Ok(file)
}

/// Check that `out` may receive the files of `calibrate --images`: absent, or an empty
/// real folder (never a link), so that no file of the user's is ever replaced.
fn check_out(out: &Path) -> Result<(), RunError> {
    let refuse = |why: &str| {
        Err(RunError::Input(format!(
            "{} {why}; give --out a new or empty folder (Glint never replaces files it did not write)",
            out.display()
        )))
    };
    match std::fs::symlink_metadata(out) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(RunError::File {
            path: out.into(),
            reason: e.to_string(),
        }),
        Ok(m) if m.file_type().is_symlink() => refuse("is a symbolic link"),
        Ok(m) if !m.is_dir() => refuse("is a file, not a folder"),
        Ok(_) => match std::fs::read_dir(out).map(|mut d| d.next().is_none()) {
            Ok(true) => Ok(()),
            Ok(false) => refuse("is not empty"),
            Err(e) => Err(RunError::File {
                path: out.into(),
                reason: e.to_string(),
            }),
        },
    }
}

/// The picture files of `calibrate --images`: `corners.png` for one photo; for several,
/// `corners-NN.png`, NN the photo's place in the list (from 01), one per photo with a grid.
pub fn picture_name(photos: usize, index: usize) -> String {
    if photos == 1 {
        "corners.png".into()
    } else {
        let width = photos.to_string().len().max(2);
        format!("corners-{:0width$}.png", index + 1)
    }
}

/// A photo file, read and decoded within Glint's limits ([`decoded`]).
fn read_image(p: &Path) -> Result<image::DynamicImage, RunError> {
    let bytes =
        crate::fsx::read_capped(p, crate::fsx::MAX_IMAGE_BYTES).map_err(|e| RunError::File {
            path: p.into(),
            reason: format!("cannot read ({e})"),
        })?;
    decoded(p, &bytes)
}

/// What the corners were refined on: linear light through the response from where it
/// says, or the photo's values and why not.
enum RefinedOn<'a> {
    Linear(&'a str),
    Values(String),
}

/// What `camera.json`'s `corners_refined_on` says.
fn refined_on(on: RefinedOn) -> String {
    match on {
        RefinedOn::Linear(from) => format!("linear light (the response {from})"),
        RefinedOn::Values(why_not) => format!("the photo's values ({why_not})"),
    }
}

fn create_new(path: &Path, bytes: &[u8]) -> Result<(), RunError> {
    crate::fsx::create_new(path, bytes).map_err(|e| RunError::File {
        path: path.into(),
        reason: if e.kind() == std::io::ErrorKind::AlreadyExists {
            "appeared while calibrating; Glint does not replace it (choose another --out)".into()
        } else {
            format!("cannot write ({e})")
        },
    })
}

/// Calibrate from photos; the intrinsics are shared, each photo has its pose. `out` must
/// be absent or an empty folder; every file is created new there: `camera.json` and a
/// picture per photo with a grid ([`picture_name`]). Photos are decoded one at a time
/// (and again, one at a time, for the pictures). Returns the calibration and the files
/// written. With `response` (the camera's response and where it came from) the corners are
/// refined in linear light ([`detect_linear`]); every photo must then have the response's
/// channels and depth.
pub fn run_images(
    paths: &[PathBuf],
    spec: GridSpec,
    out: &Path,
    known: Option<&Known>,
    response: Option<(&Response, &str)>,
) -> Result<(CameraFile, Vec<PathBuf>), RunError> {
    let start = Instant::now();
    check_out(out)?;
    let mut found = Vec::new();
    let mut size: Option<(usize, usize, String)> = None;
    for p in paths {
        let img = read_image(p)?;
        let g = crate::calib::gray_from_image(&img);
        let linear = match response {
            None => None,
            Some((r, from)) => Some(linear_grey(&img, r).ok_or_else(|| RunError::File {
                path: p.into(),
                reason: format!(
                    "its channels or bit depth are not those of the response {from} ({} channel(s), values up to {}); give the response of the camera that took the photos, or leave --response out",
                    r.channel_count(),
                    r.max_value()
                ),
            })?),
        };
        let name = p.display().to_string();
        match &size {
            None => size = Some((g.width, g.height, name.clone())),
            Some((w, h, first)) if (g.width, g.height) != (*w, *h) => {
                return Err(RunError::Input(format!(
                    "{name} is {}x{} but {first} is {w}x{h}; photos calibrated together must come from one camera at one resolution",
                    g.width, g.height
                )));
            }
            Some(_) => {}
        }
        let r = detect_view(&name, &g, linear.as_ref(), spec);
        found.push((name, r));
    }
    let Some((w, h, _)) = size else {
        return Err(RunError::Input(
            "no photos given (--images PHOTO ...)".into(),
        ));
    };
    let detected: Vec<usize> = found
        .iter()
        .enumerate()
        .filter(|(_, (_, r))| r.is_ok())
        .map(|(i, _)| i)
        .collect();
    let refined = refined_on(match response {
        Some((_, from)) => RefinedOn::Linear(from),
        None => RefinedOn::Values("no --response given".into()),
    });
    let file = solve_views(found, (w, h), spec, start, known, refined)?;
    crate::fsx::ensure_dir(out).map_err(|e| RunError::File {
        path: out.into(),
        reason: e.to_string(),
    })?;
    let mut written = Vec::new();
    let json = serde_json::to_vec_pretty(&file).expect("the calibration serialises");
    let path = out.join("camera.json");
    create_new(&path, &json)?;
    written.push(path);
    for (name, text) in others(&file) {
        let path = out.join(name);
        create_new(&path, text.as_bytes())?;
        written.push(path);
    }
    for (k, &i) in detected.iter().enumerate() {
        let g = crate::calib::gray_from_image(&read_image(&paths[i])?);
        let path = out.join(picture_name(paths.len(), i));
        create_new(&path, &picture_png(&file, k, &g, &path)?)?;
        written.push(path);
    }
    Ok((file, written))
}

/// The camera files for other tools beside `camera.json` (see [`super::export`]): name
/// and text.
fn others(file: &CameraFile) -> [(&'static str, String); 2] {
    [
        (OPENCV_YAML, super::export::opencv_yaml(file)),
        (
            ROS_YAML,
            super::export::ros_camera_info_yaml(file, "glint_camera"),
        ),
    ]
}

/// OpenCV's FileStorage YAML of the calibration, in `calib/`.
pub const OPENCV_YAML: &str = "camera_opencv.yaml";
/// ROS's camera_info YAML of the calibration, in `calib/`.
pub const ROS_YAML: &str = "camera_info.yaml";

/// One photo's detection: its view for the fit and what was found, or why not.
type Found = Result<(ViewObs, Detected), DetectError>;

/// Detect the grid in one photo: its view for the fit and its detection, or why it
/// cannot be one (no grid, or too few corners found for a reliable pose).
fn detect_view(
    name: &str,
    img: &Gray,
    linear: Option<&Gray>,
    spec: GridSpec,
) -> Result<(ViewObs, Detected), DetectError> {
    let [nx, ny] = spec.inner_corners;
    let g = match linear {
        Some(l) => detect_linear(img, l, nx, ny)?,
        None => detect(img, nx, ny)?,
    };
    let used: Vec<usize> = (0..g.corners.len())
        .filter(|k| !g.filled.contains(k) && !g.doubtful.contains(k))
        .collect();
    if used.len() < 8 || 2 * used.len() < g.corners.len() {
        return Err(DetectError::Partial {
            found: used.len(),
            expected: g.corners.len(),
            grid: spec.inner_corners,
            touches_border: false,
        });
    }
    let world = types::grid_world(&spec);
    Ok((
        ViewObs {
            name: name.to_string(),
            world: used.iter().map(|&k| world[k]).collect(),
            px: used.iter().map(|&k| g.corners[k]).collect(),
        },
        Detected {
            name: name.to_string(),
            corners: g.corners,
            placed: g.filled,
            doubtful: g.doubtful,
            spacing_px: g.spacing_px,
        },
    ))
}

/// Detect and solve photos held in memory (a session's averaged grid photo), each with
/// its linear-light copy where there is one (`linear`, one entry per photo).
fn solve_images(
    imgs: &[(String, Gray)],
    linear: &[Option<&Gray>],
    spec: GridSpec,
    start: Instant,
    known: Option<&Known>,
    refined_on: String,
) -> Result<CameraFile, RunError> {
    let size = imgs
        .first()
        .map(|(_, g)| (g.width, g.height))
        .unwrap_or((0, 0));
    let found = imgs
        .iter()
        .zip(linear)
        .map(|((n, g), l)| (n.clone(), detect_view(n, g, *l, spec)))
        .collect();
    solve_views(found, size, spec, start, known, refined_on)
}

/// Solve the views found (photos of `size`); with one photo its detection error is the
/// error, with several a photo without a usable grid is skipped with a warning.
fn solve_views(
    found: Vec<(String, Found)>,
    size: (usize, usize),
    spec: GridSpec,
    start: Instant,
    known: Option<&Known>,
    corners_refined_on: String,
) -> Result<CameraFile, RunError> {
    let single = found.len() == 1;
    let mut skipped = Vec::new();
    let mut views = Vec::new();
    let mut detections = Vec::new();
    let mut first_error = None;
    for (name, r) in found {
        match r {
            Ok((v, d)) => {
                views.push(v);
                detections.push(d);
            }
            Err(e) => {
                if single {
                    return Err(RunError::Detect { name, error: e });
                }
                skipped.push(format!("{name}: {e}"));
                first_error.get_or_insert((name, e));
            }
        }
    }
    let Some(_) = views.first() else {
        return Err(match first_error {
            Some((name, error)) => RunError::Detect { name, error },
            None => RunError::Input("no photos to calibrate from".into()),
        });
    };
    let (w, h) = size;
    let mut cal = match known {
        Some(k) => {
            if (k.width, k.height) != (w, h) {
                return Err(RunError::Input(format!(
                    "{} is a calibration at {}x{} but the photos are {w}x{h}; calibrate the intrinsics at this resolution",
                    k.from.display(),
                    k.width,
                    k.height
                )));
            }
            pose_with_lens(&views, w, h, &k.intrinsics, k.covariance.as_ref())?
        }
        None => calibrate(&views, w, h, Options::for_views(views.len()))?,
    };
    for s in &skipped {
        cal.warnings.push(format!("skipped {s}"));
    }
    let rotations = cal
        .views
        .iter()
        .map(|v| {
            let r = rotation(v.pose.rvec);
            [
                [r[(0, 0)], r[(0, 1)], r[(0, 2)]],
                [r[(1, 0)], r[(1, 1)], r[(1, 2)]],
                [r[(2, 0)], r[(2, 1)], r[(2, 2)]],
            ]
        })
        .collect();
    Ok(CameraFile {
        format: FORMAT.into(),
        format_version: FORMAT_VERSION,
        created: session::timestamp(std::time::SystemTime::now()),
        grid: spec,
        length_unit: if spec.square_mm.is_some() { "mm" } else { "grid squares" }.into(),
        conventions: "X_cam = R X_grid + t (R from rvec, a rotation vector); x = X/Z, y = Y/Z; r2 = x^2 + y^2; d = 1 + k1 r2 + k2 r2^2 + k3 r2^3; u = fx (d x + 2 p1 x y + p2 (r2 + 2 x^2)) + cx, v = fy (d y + p1 (r2 + 2 y^2) + 2 p2 x y) + cy; pixel (0, 0) is the centre of the top-left pixel; the grid origin is the inner corner whose +x,+y square is dark, x along the first count of inner corners, z towards the camera".into(),
        camera_matrix: super::export::camera_matrix(&cal.intrinsics),
        dist_coeffs: super::export::dist_coeffs(&cal.intrinsics),
        calibration: cal,
        rotations,
        detections,
        skipped,
        corners_refined_on,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// The session's `calib/`: derived results, replaced atomically when the stage is re-run:
/// `camera.json` and a picture per view (`corners.png`, or `corners-NN.png` for a lens
/// session's several views).
fn write(out: &Path, file: &CameraFile, imgs: &[&Gray]) -> Result<(), RunError> {
    let json = serde_json::to_vec_pretty(file).expect("the calibration serialises");
    session::write_replace(&out.join("camera.json"), &json)?;
    for (name, text) in others(file) {
        session::write_replace(&out.join(name), text.as_bytes())?;
    }
    for (k, img) in imgs.iter().enumerate() {
        let path = out.join(picture_name(imgs.len(), k));
        let bytes = picture_png(file, k, img, &path)?;
        session::write_replace(&path, &bytes)?;
    }
    Ok(())
}

/// [`picture_of`] view `k` as PNG bytes (`path`: for the error).
fn picture_png(file: &CameraFile, k: usize, img: &Gray, path: &Path) -> Result<Vec<u8>, RunError> {
    let png = picture_of(file, k, img);
    let mut bytes = Vec::new();
    png.write_to(
        &mut std::io::Cursor::new(&mut bytes),
        image::ImageFormat::Png,
    )
    .map_err(|e| RunError::File {
        path: path.into(),
        reason: e.to_string(),
    })?;
    Ok(bytes)
}

/// Residuals are drawn this many times their length.
pub const RESIDUAL_SCALE: f64 = 50.0;

/// The first view's photo with its detected corners (green crosses), the reprojected
/// corners (red circles), each residual drawn enlarged (yellow, x50), and the grid's
/// origin (circled) with its x axis (cyan) and y axis (magenta); corners placed rather
/// than found, or doubtful, are circled in orange (not used in the fit).
pub fn picture(file: &CameraFile, img: &Gray) -> image::RgbImage {
    picture_of(file, 0, img)
}

/// [`picture`] for view `k` (its photo `img`).
pub fn picture_of(file: &CameraFile, k: usize, img: &Gray) -> image::RgbImage {
    let (w, h) = (img.width as u32, img.height as u32);
    let mut out = image::RgbImage::from_fn(w, h, |x, y| {
        let v = (img.data[(y * w + x) as usize] * 0.7).clamp(0.0, 255.0) as u8;
        image::Rgb([v, v, v])
    });
    let cal = &file.calibration;
    let (Some(det), Some(view)) = (file.detections.get(k), cal.views.get(k)) else {
        return out;
    };
    let world = types::grid_world(&file.grid);
    // The grid's axes from the origin: x in cyan, y in magenta.
    let [nx, ny] = file.grid.inner_corners;
    let o = det.corners[0];
    for (end, col) in [
        (det.corners[nx - 1], [0, 220, 255]),
        (det.corners[(ny - 1) * nx], [255, 0, 220]),
    ] {
        for d in [-1.0, 0.0, 1.0] {
            line(&mut out, [o[0] + d, o[1]], [end[0] + d, end[1]], col);
            line(&mut out, [o[0], o[1] + d], [end[0], end[1] + d], col);
        }
    }
    circle(&mut out, o, 7.0, [0, 220, 255]);
    for (k, (p, wp)) in det.corners.iter().zip(&world).enumerate() {
        if det.placed.contains(&k) || det.doubtful.contains(&k) {
            circle(&mut out, *p, 5.0, [255, 140, 0]);
            continue;
        }
        let q = project(&cal.intrinsics, &view.pose, *wp, None).uv;
        let end = [
            p[0] + RESIDUAL_SCALE * (q[0] - p[0]),
            p[1] + RESIDUAL_SCALE * (q[1] - p[1]),
        ];
        line(&mut out, *p, end, [255, 220, 0]);
        line(
            &mut out,
            [p[0] - 4.0, p[1]],
            [p[0] + 4.0, p[1]],
            [0, 230, 0],
        );
        line(
            &mut out,
            [p[0], p[1] - 4.0],
            [p[0], p[1] + 4.0],
            [0, 230, 0],
        );
        circle(&mut out, q, 3.0, [255, 40, 40]);
    }
    out
}

fn put(img: &mut image::RgbImage, x: f64, y: f64, c: [u8; 3]) {
    let (xi, yi) = (x.round(), y.round());
    if xi >= 0.0 && yi >= 0.0 && (xi as u32) < img.width() && (yi as u32) < img.height() {
        img.put_pixel(xi as u32, yi as u32, image::Rgb(c));
    }
}

fn line(img: &mut image::RgbImage, a: [f64; 2], b: [f64; 2], c: [u8; 3]) {
    let n = ((b[0] - a[0]).abs().max((b[1] - a[1]).abs()).ceil() as usize).clamp(1, 100_000);
    for k in 0..=n {
        let t = k as f64 / n as f64;
        put(img, a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t, c);
    }
}

fn circle(img: &mut image::RgbImage, p: [f64; 2], r: f64, c: [u8; 3]) {
    for k in 0..32 {
        let a = k as f64 * std::f64::consts::TAU / 32.0;
        put(img, p[0] + r * a.cos(), p[1] + r * a.sin(), c);
    }
}
