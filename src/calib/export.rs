//! Camera files other tools read: OpenCV's FileStorage YAML (`calib/camera_opencv.yaml`,
//! as OpenCV's calibration sample writes it) and ROS's `camera_info` YAML
//! (`calib/camera_info.yaml`, as `camera_calibration_parsers` reads it); and either read
//! back as `--intrinsics`.
//!
//! Glint's camera model is OpenCV's (docs/design.md: Brown's radial k1, k2, k3 and tangential
//! p1, p2; pixel (0, 0) the centre of the top-left pixel), so the numbers carry over
//! unchanged: `camera_matrix` is [fx 0 cx; 0 fy cy; 0 0 1] and the distortion
//! coefficients are in OpenCV's order (k1, k2, p1, p2, k3), absent terms zero.
//!
//! The reader is hand-written for the subset these files use (top-level keys, a matrix's
//! `rows`, `cols` and `data: [ ... ]` over one or more lines): OpenCV writes a directive
//! (`%YAML:1.0` before OpenCV 4.x's end, `%YAML 1.2` since) and `!!opencv-matrix` tags that
//! general YAML crates refuse or need custom tag handling for, and the maintained ones pull
//! in far more than two matrices need.

use std::fmt::Write as _;

use super::camera::Intrinsics;
use super::run::types::{intrinsics_problem, CameraFile, Known, RunError};

/// The camera matrix [fx 0 cx; 0 fy cy; 0 0 1], rows.
pub fn camera_matrix(k: &Intrinsics) -> [[f64; 3]; 3] {
    [[k.fx, 0.0, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]]
}

/// The distortion coefficients in OpenCV's order: k1, k2, p1, p2, k3 (absent terms 0).
pub fn dist_coeffs(k: &Intrinsics) -> [f64; 5] {
    let r = |i: usize| k.radial.get(i).copied().unwrap_or(0.0);
    let [p1, p2] = k.tangential.unwrap_or([0.0, 0.0]);
    [r(0), r(1), p1, p2, r(2)]
}

/// A number as Rust writes it shortest (it reads back exactly; OpenCV's and ROS's readers
/// take it).
fn num(x: f64) -> String {
    if x.is_finite() {
        format!("{x:?}")
    } else {
        // Never written by a checked calibration; YAML's own spelling if it were.
        if x.is_nan() {
            ".nan".into()
        } else if x > 0.0 {
            ".inf".into()
        } else {
            "-.inf".into()
        }
    }
}

fn list(v: &[f64]) -> String {
    v.iter().map(|x| num(*x)).collect::<Vec<_>>().join(", ")
}

/// `calib/camera_opencv.yaml`: OpenCV's FileStorage YAML, with the keys of OpenCV's
/// calibration sample (`samples/cpp/calibration.cpp`): image size, `camera_matrix`,
/// `distortion_coefficients` (1 x 5), `avg_reprojection_error`, the board, and
/// `extrinsic_parameters` (one row per view: rvec, then t in the grid's unit: `length_unit`),
/// so that `cv2.projectPoints` reproduces Glint's projection of the grid's corners.
pub fn opencv_yaml(file: &CameraFile) -> String {
    let c = &file.calibration;
    let k = &c.intrinsics;
    let mut s = String::new();
    let _ = writeln!(s, "%YAML:1.0\n---");
    let _ = writeln!(s, "# Written by Glint {} ({}): OpenCV's camera model; extrinsic_parameters are rvec, t per view (X_cam = R X_grid + t, t in {}).",
        env!("CARGO_PKG_VERSION"), file.created, file.length_unit);
    let _ = writeln!(s, "image_width: {}", c.width);
    let _ = writeln!(s, "image_height: {}", c.height);
    let _ = writeln!(s, "board_width: {}", file.grid.inner_corners[0]);
    let _ = writeln!(s, "board_height: {}", file.grid.inner_corners[1]);
    let _ = writeln!(
        s,
        "square_size: {}",
        num(file.grid.square_mm.unwrap_or(1.0))
    );
    let _ = writeln!(s, "nr_of_frames: {}", c.views.len());
    let m = camera_matrix(k);
    matrix(&mut s, "camera_matrix", 3, 3, &m.concat());
    matrix(&mut s, "distortion_coefficients", 1, 5, &dist_coeffs(k));
    let _ = writeln!(s, "avg_reprojection_error: {}", num(c.rms_px));
    let ext: Vec<f64> = c
        .views
        .iter()
        .flat_map(|v| v.pose.rvec.into_iter().chain(v.pose.t))
        .collect();
    if !ext.is_empty() {
        matrix(&mut s, "extrinsic_parameters", c.views.len(), 6, &ext);
    }
    s
}

fn matrix(s: &mut String, name: &str, rows: usize, cols: usize, data: &[f64]) {
    let _ = writeln!(
        s,
        "{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n   data: [ {} ]",
        list(data)
    );
}

/// `calib/camera_info.yaml`: ROS's camera_info YAML (the `camera_calibration_parsers`
/// format: `plumb_bob` distortion, identity rectification, and the projection matrix
/// [K | 0], i.e. a rectified image with the same camera matrix).
pub fn ros_camera_info_yaml(file: &CameraFile, camera_name: &str) -> String {
    let c = &file.calibration;
    let k = &c.intrinsics;
    let m = camera_matrix(k);
    let p = [
        k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0,
    ];
    let block = |name: &str, rows: usize, cols: usize, data: &[f64]| {
        format!(
            "{name}:\n  rows: {rows}\n  cols: {cols}\n  data: [{}]\n",
            list(data)
        )
    };
    let mut s = String::new();
    let _ = writeln!(s, "image_width: {}", c.width);
    let _ = writeln!(s, "image_height: {}", c.height);
    let _ = writeln!(s, "camera_name: {}", yaml_plain(camera_name));
    s += &block("camera_matrix", 3, 3, &m.concat());
    let _ = writeln!(s, "distortion_model: plumb_bob");
    s += &block("distortion_coefficients", 1, 5, &dist_coeffs(k));
    s += &block(
        "rectification_matrix",
        3,
        3,
        &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
    );
    s += &block("projection_matrix", 3, 4, &p);
    s
}

/// A camera name as a YAML plain scalar: ROS names are [A-Za-z0-9_]; anything else
/// becomes `_`.
fn yaml_plain(name: &str) -> String {
    let n: String = name
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect();
    if n.is_empty() {
        "camera".into()
    } else {
        n
    }
}

/// Intrinsics from an OpenCV FileStorage YAML or a ROS camera_info YAML: the image size
/// (`image_width`, `image_height`), `camera_matrix` (3 x 3, zero skew) and
/// `distortion_coefficients` (4, 5, 8, 12 or 14 values in OpenCV's order; the terms
/// beyond k3 must be 0: Glint's model has no rational or thin-prism terms). No covariance:
/// the lens is held as exact.
pub fn read_intrinsics_yaml(file: impl Into<crate::fsx::Within>) -> Result<Known, RunError> {
    let file = file.into();
    let path = &file.path();
    let bad = |reason: String| RunError::File {
        path: path.into(),
        reason,
    };
    let text = file
        .read_text(crate::fsx::MAX_TEXT_BYTES)
        .map_err(|e| bad(format!("cannot read ({e})")))?;
    parse_intrinsics_yaml(&text)
        .map(|(width, height, intrinsics)| Known {
            from: path.into(),
            width,
            height,
            intrinsics,
            covariance: None,
        })
        .map_err(|e| bad(e.0))
}

/// What is wrong with a camera YAML, in words that name the key (one line). It reads as
/// the text it holds (`e.contains("no skew")`).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct YamlError(pub String);

impl std::ops::Deref for YamlError {
    type Target = str;
    fn deref(&self) -> &str {
        &self.0
    }
}

impl From<&str> for YamlError {
    fn from(s: &str) -> Self {
        YamlError(s.into())
    }
}

impl From<String> for YamlError {
    fn from(s: String) -> Self {
        YamlError(s)
    }
}

/// [`read_intrinsics_yaml`] on the file's text: (width, height, intrinsics) or what is
/// wrong, in words that name the key.
pub fn parse_intrinsics_yaml(text: &str) -> Result<(usize, usize, Intrinsics), YamlError> {
    const ADVICE: &str = "an OpenCV FileStorage YAML (camera_matrix, distortion_coefficients, image_width, image_height) or a ROS camera_info YAML";
    let size = |key: &str| -> Result<usize, YamlError> {
        let v = scalar(text, key).ok_or_else(|| format!("no {key}: not {ADVICE}"))?;
        v.parse::<usize>()
            .ok()
            .filter(|n| (1..=100_000).contains(n))
            .ok_or_else(|| {
                YamlError(format!(
                    "{key}: {v:?} is not an image size in pixels (1..100000)"
                ))
            })
    };
    let width = size("image_width")?;
    let height = size("image_height")?;
    let m = matrix_data(text, "camera_matrix")
        .map_err(|e| YamlError(format!("camera_matrix: {e}")))?
        .ok_or_else(|| format!("no camera_matrix: not {ADVICE}"))?;
    if m.len() != 9 {
        return Err(YamlError(format!(
            "camera_matrix has {} values; it must be 3 x 3",
            m.len()
        )));
    }
    if m[1] != 0.0 || m[3] != 0.0 || m[6] != 0.0 || m[7] != 0.0 || m[8] != 1.0 {
        return Err(YamlError(format!(
            "camera_matrix [{}] is not [fx 0 cx; 0 fy cy; 0 0 1] (Glint's model has no skew)",
            list(&m)
        )));
    }
    let d = matrix_data(text, "distortion_coefficients")
        .map_err(|e| YamlError(format!("distortion_coefficients: {e}")))?
        .unwrap_or_default();
    if !matches!(d.len(), 0 | 4 | 5 | 8 | 12 | 14) {
        return Err(YamlError(format!(
            "distortion_coefficients has {} values; OpenCV's are 4, 5, 8, 12 or 14 (k1, k2, p1, p2[, k3, ...])",
            d.len()
        )));
    }
    if let Some(i) = d.iter().skip(5).position(|x| *x != 0.0) {
        return Err(YamlError(format!(
            "distortion_coefficients[{}] = {}: Glint's camera model has k1, k2, p1, p2, k3 only (the rational and thin-prism terms must be 0)",
            i + 5,
            d[i + 5]
        )));
    }
    let at = |i: usize| d.get(i).copied().unwrap_or(0.0);
    let mut radial = vec![at(0), at(1), at(4)];
    while radial.last() == Some(&0.0) {
        radial.pop();
    }
    let tangential = (at(2) != 0.0 || at(3) != 0.0).then_some([at(2), at(3)]);
    let k = Intrinsics {
        fx: m[0],
        fy: m[4],
        cx: m[2],
        cy: m[5],
        radial,
        tangential,
    };
    if let Some(p) = intrinsics_problem(&k, width, height) {
        return Err(YamlError(p));
    }
    Ok((width, height, k))
}

/// The line of top-level `key:` (not indented), and the lines after it.
fn top_level<'a>(text: &'a str, key: &str) -> Option<(&'a str, std::str::Lines<'a>)> {
    let mut lines = text.lines();
    while let Some(l) = lines.next() {
        if let Some(rest) = l.strip_prefix(key) {
            if let Some(rest) = rest.trim_start().strip_prefix(':') {
                return Some((rest, lines));
            }
        }
    }
    None
}

/// A top-level scalar's text (comments and quotes removed).
fn scalar<'a>(text: &'a str, key: &str) -> Option<&'a str> {
    let (rest, _) = top_level(text, key)?;
    let v = rest.split('#').next().unwrap_or("").trim();
    Some(v.trim_matches(|c| c == '"' || c == '\''))
}

/// A top-level matrix's `data` (None where the key is absent): the block's indented
/// lines, `data: [ ... ]` over one or more lines.
fn matrix_data(text: &str, key: &str) -> Result<Option<Vec<f64>>, YamlError> {
    let Some((rest, lines)) = top_level(text, key) else {
        return Ok(None);
    };
    let mut body = String::from(rest);
    for l in lines {
        if !l.starts_with([' ', '\t']) && !l.trim().is_empty() {
            break;
        }
        body.push('\n');
        body.push_str(l);
    }
    let Some(start) = body.find("data:") else {
        return Err("no data: [ ... ] under it".into());
    };
    let after = &body[start + 5..];
    let open = after.find('[').ok_or("data is not a [ ... ] list")?;
    let close = after[open..]
        .find(']')
        .ok_or("data's [ ... ] list is not closed")?;
    let inner = &after[open + 1..open + close];
    let mut out = Vec::new();
    for (i, item) in inner.split(',').enumerate() {
        let t = item.trim();
        if t.is_empty() && inner.trim().is_empty() {
            break;
        }
        let x = t
            .parse::<f64>()
            .ok()
            .filter(|x| x.is_finite())
            .ok_or_else(|| format!("data[{i}] = {t:?} is not a finite number"))?;
        out.push(x);
        if out.len() > 64 {
            return Err("more than 64 values".into());
        }
    }
    // rows x cols, where given, must be the count.
    let dim = |name: &str| {
        body.lines()
            .filter_map(|l| l.trim().strip_prefix(name))
            .filter_map(|r| r.trim_start().strip_prefix(':'))
            .find_map(|v| v.trim().parse::<usize>().ok())
    };
    if let (Some(r), Some(c)) = (dim("rows"), dim("cols")) {
        if r.checked_mul(c) != Some(out.len()) {
            return Err(YamlError(format!(
                "rows {r} x cols {c} but {} values in data",
                out.len()
            )));
        }
    }
    Ok(Some(out))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// As OpenCV 5.1's `cv2.FileStorage` writes it (numbers over lines, `0.` and `1.`).
    const OPENCV: &str = "%YAML 1.2
---
image_width: 640
image_height: 480
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 657.46697944293521, 0., 319.5, 0., 655.12345678899999, 239.25,
       0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ -0.1234567, 0.02, 0.001, -0.00050000000000000001, 0. ]
extrinsic_parameters: !!opencv-matrix
   rows: 2
   cols: 6
   dt: d
   data: [ 0.10000000000000001, 0.20000000000000001, 0.29999999999999999,
       10., 20., 400.5, 0.10000000000000001, 0.20000000000000001,
       0.29999999999999999, 10., 20., 400.5 ]
avg_reprojection_error: 0.123
";

    #[test]
    fn reads_what_opencv_writes() {
        let (w, h, k) = parse_intrinsics_yaml(OPENCV).unwrap();
        assert_eq!((w, h), (640, 480));
        assert_eq!(k.fx, 657.466_979_442_935_2);
        assert_eq!(k.fy, 655.123456789);
        assert_eq!((k.cx, k.cy), (319.5, 239.25));
        assert_eq!(k.radial, vec![-0.1234567, 0.02]);
        assert_eq!(k.tangential, Some([0.001, -0.0005]));
    }

    #[test]
    fn refuses_what_glint_cannot_model_with_the_key_named() {
        let skew = OPENCV.replace(
            "657.46697944293521, 0., 319.5",
            "657.46697944293521, 0.5, 319.5",
        );
        assert!(parse_intrinsics_yaml(&skew)
            .unwrap_err()
            .contains("no skew"));
        let rational = OPENCV.replace(
            "cols: 5\n   dt: d\n   data: [ -0.1234567, 0.02, 0.001, -0.00050000000000000001, 0. ]",
            "cols: 8\n   dt: d\n   data: [ -0.1234567, 0.02, 0.001, -0.0005, 0., 0.3, 0., 0. ]",
        );
        let e = parse_intrinsics_yaml(&rational).unwrap_err();
        assert!(e.contains("distortion_coefficients[5] = 0.3"), "{e}");
        let open = OPENCV.replace("0., 0., 1. ]", "0., 0., 1.");
        assert!(parse_intrinsics_yaml(&open)
            .unwrap_err()
            .contains("not closed"));
        let junk = OPENCV.replace("319.5", "x");
        let e = parse_intrinsics_yaml(&junk).unwrap_err();
        assert!(e.starts_with("camera_matrix: data[2] = \"x\""), "{e}");
        assert!(parse_intrinsics_yaml("{}")
            .unwrap_err()
            .contains("no image_width"));
        let huge = OPENCV.replace("image_width: 640", "image_width: 99999999999999999999999");
        assert!(parse_intrinsics_yaml(&huge)
            .unwrap_err()
            .starts_with("image_width:"));
    }

    #[test]
    fn the_coefficients_are_in_opencvs_order() {
        let k = Intrinsics {
            fx: 800.0,
            fy: 801.0,
            cx: 320.0,
            cy: 240.0,
            radial: vec![-0.1, 0.01, 0.001],
            tangential: Some([0.0002, -0.0003]),
        };
        assert_eq!(dist_coeffs(&k), [-0.1, 0.01, 0.0002, -0.0003, 0.001]);
        let k2 = Intrinsics {
            radial: vec![-0.1],
            tangential: None,
            ..k.clone()
        };
        assert_eq!(dist_coeffs(&k2), [-0.1, 0.0, 0.0, 0.0, 0.0]);
        assert_eq!(
            camera_matrix(&k),
            [[800.0, 0.0, 320.0], [0.0, 801.0, 240.0], [0.0, 0.0, 1.0]]
        );
    }
}
