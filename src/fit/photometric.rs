//! Known geometry beyond a flat tile: photometric data sets, where every pixel has a known
//! normal and every photo a known light direction and intensity (DiLiGenT's layout:
//! `images/NNN.png`, `light_directions.txt`, `light_intensities.txt`, `mask.png` and the
//! normals in `Normal_gt.mat`). The same fitter takes them: each pixel
//! of each photo is one sample, with the view direction (0, 0, 1) (a distant camera, as
//! DiLiGenT assumes) and the photo divided by its light's intensity.

use std::path::{Path, PathBuf};

use serde::Serialize;

use super::choose::choose;
use super::model::{Geometry, Model};
use super::run::{Candidate, FitError};
use super::solve::{measured_values, ModelFit, Options, Sample};

/// One photo.
pub struct Photo {
    /// The number in its file name (1-based line of the light files).
    pub index: usize,
    pub name: String,
    pub light: [f64; 3],
    pub intensity: [f64; 3],
    /// RGB interleaved, 16-bit.
    pub pixels: Vec<u16>,
}

/// A photometric data set.
pub struct PhotometricSet {
    pub dir: PathBuf,
    pub width: usize,
    pub height: usize,
    pub mask: Vec<bool>,
    /// Unit normal per pixel (x right, y up, z towards the camera).
    pub normals: Vec<[f64; 3]>,
    pub photos: Vec<Photo>,
    pub max_value: u16,
}

fn bad(path: &Path, reason: impl std::fmt::Display) -> FitError {
    FitError::File {
        path: path.into(),
        reason: reason.to_string(),
    }
}

/// Most photos a data set may have (DiLiGenT has 96).
pub const MAX_PHOTOS: usize = 10_000;
/// Most pixel values (photos x pixels x 3) loaded at once: 2^30 (2 GiB of 16-bit values;
/// DiLiGenT's 96 photos of 612x512 are 90 million).
pub const MAX_VALUES: u64 = 1 << 30;

/// Rows of three finite numbers (`what` says what they are, for the error).
fn read_rows(path: &Path, what: &str) -> Result<Vec<[f64; 3]>, FitError> {
    let text = crate::fsx::read_text_capped(path, crate::fsx::MAX_TEXT_BYTES)
        .map_err(|e| bad(path, format!("cannot read ({e})")))?;
    text.lines()
        .filter(|l| !l.trim().is_empty())
        .enumerate()
        .map(|(i, l)| {
            let not_three = || {
                bad(
                    path,
                    format!(
                        "line {}: {} is not three numbers ({what})",
                        i + 1,
                        crate::fsx::quote(l.trim())
                    ),
                )
            };
            let v: Vec<f64> = l
                .split_whitespace()
                .map(|x| x.parse::<f64>())
                .collect::<Result<_, _>>()
                .map_err(|_| not_three())?;
            if v.len() != 3 {
                return Err(not_three());
            }
            if !v.iter().all(|x| x.is_finite()) {
                return Err(bad(
                    path,
                    format!("line {}: {what} must be finite numbers", i + 1),
                ));
            }
            Ok([v[0], v[1], v[2]])
        })
        .collect()
}

/// Read and decode an image within Glint's limits.
fn read_image(path: &Path) -> Result<image::DynamicImage, FitError> {
    let bytes = crate::fsx::read_capped(path, crate::fsx::MAX_IMAGE_BYTES)
        .map_err(|e| bad(path, format!("cannot read ({e})")))?;
    crate::hdr::decode_image(&bytes)
        .map(|(_, img)| img)
        .map_err(|e| bad(path, e))
}

/// Normals from DiLiGenT's `Normal_gt.mat` (MATLAB v5, a height x width x 3 double array).
fn read_normals(dir: &Path, width: usize, height: usize) -> Result<Vec<[f64; 3]>, FitError> {
    let mat = dir.join("Normal_gt.mat");
    let n = width * height;
    if mat.exists() {
        // Three doubles a pixel and the file's headers: a larger file is not these normals.
        let cap = 24 * n as u64 + (1 << 20);
        let bytes = crate::fsx::read_capped(&mat, cap)
            .map_err(|e| bad(&mat, format!("cannot read ({e})")))?;
        let m = matfile::MatFile::parse(std::io::Cursor::new(bytes))
            .map_err(|e| bad(&mat, format!("not a readable MATLAB file ({e:?})")))?;
        let a = m
            .arrays()
            .iter()
            .find(|a| a.size() == &vec![height, width, 3])
            .ok_or_else(|| {
                bad(
                    &mat,
                    format!("has no {height} x {width} x 3 array of normals"),
                )
            })?;
        let matfile::NumericData::Double { real, .. } = a.data() else {
            return Err(bad(&mat, "the normals are not doubles"));
        };
        if real.len() != 3 * n {
            return Err(bad(
                &mat,
                format!(
                    "the normals array holds {} values, not {}",
                    real.len(),
                    3 * n
                ),
            ));
        }
        // MATLAB stores column-major: element (r, c, k) at r + height (c + width k).
        Ok((0..n)
            .map(|i| {
                let (r, c) = (i / width, i % width);
                [0, 1, 2].map(|k| real[r + height * (c + width * k)])
            })
            .collect())
    } else {
        Err(FitError::Input(format!(
            "{}: no normals (DiLiGenT's Normal_gt.mat)",
            dir.display()
        )))
    }
}

/// Load a data set in DiLiGenT's layout.
pub fn load(dir: &Path) -> Result<PhotometricSet, FitError> {
    let images = dir.join("images");
    let mut files: Vec<(usize, PathBuf)> = std::fs::read_dir(&images)
        .map_err(|e| {
            bad(
                &images,
                format!("cannot list ({e}); expected images/NNN.png"),
            )
        })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter_map(|p| {
            let stem = p.file_stem()?.to_str()?.parse::<usize>().ok()?;
            (p.extension()? == "png").then_some((stem, p))
        })
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(bad(&images, "no NNN.png photos"));
    }
    if let Some((_, p)) = files.iter().find(|(i, _)| *i == 0) {
        return Err(bad(
            p,
            "photos are numbered from 001 (line NNN of the light files)",
        ));
    }
    if files.len() > MAX_PHOTOS {
        return Err(bad(
            &images,
            format!(
                "holds {} photos; Glint fits at most {MAX_PHOTOS}",
                files.len()
            ),
        ));
    }
    let dirs_path = dir.join("light_directions.txt");
    let ints_path = dir.join("light_intensities.txt");
    let dirs = read_rows(&dirs_path, "a light direction")?;
    let ints = read_rows(&ints_path, "a light's RGB intensity")?;
    if let Some(i) = dirs
        .iter()
        .position(|d| (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() < 1e-9)
    {
        return Err(bad(
            &dirs_path,
            format!("line {}: the light direction is zero", i + 1),
        ));
    }
    if let Some(i) = ints.iter().position(|v| v.iter().any(|x| *x <= 0.0)) {
        return Err(bad(
            &ints_path,
            format!(
                "line {}: a light's intensity must be positive in every channel (the photo is divided by it)",
                i + 1
            ),
        ));
    }
    let mask_path = dir.join("mask.png");
    let mask_img = read_image(&mask_path)?.to_luma8();
    let (width, height) = (mask_img.width() as usize, mask_img.height() as usize);
    let values = files.len() as u64 * (width * height * 3) as u64;
    if values > MAX_VALUES {
        return Err(bad(
            &images,
            format!(
                "{} photos of {width}x{height} are {values} values; Glint loads at most {MAX_VALUES} (use fewer or smaller photos)",
                files.len()
            ),
        ));
    }
    let mask: Vec<bool> = mask_img.into_raw().into_iter().map(|v| v > 127).collect();
    let normals = read_normals(dir, width, height)?;
    if let Some(i) = (0..width * height).find(|&i| {
        let v = normals[i];
        mask[i]
            && !(v.iter().all(|x| x.is_finite()) && v.iter().map(|x| x * x).sum::<f64>() > 1e-12)
    }) {
        return Err(bad(
            &dir.join("Normal_gt.mat"),
            format!(
                "the normal at pixel ({}, {}), inside the mask, is not a finite non-zero vector",
                i % width,
                i / width
            ),
        ));
    }
    let mut photos = Vec::new();
    for (index, path) in files {
        let light = *dirs.get(index - 1).ok_or_else(|| {
            bad(
                &dir.join("light_directions.txt"),
                format!("has no line {index} for {}", path.display()),
            )
        })?;
        let intensity = *ints.get(index - 1).ok_or_else(|| {
            bad(
                &dir.join("light_intensities.txt"),
                format!("has no line {index} for {}", path.display()),
            )
        })?;
        // The size from the header first: a photo of another size is never decoded.
        let bytes = crate::fsx::read_capped(&path, crate::fsx::MAX_IMAGE_BYTES)
            .map_err(|e| bad(&path, format!("cannot read ({e})")))?;
        let info = crate::hdr::probe_image(&bytes).map_err(|e| bad(&path, e))?;
        if (info.width as usize, info.height as usize) != (width, height) {
            return Err(bad(&path, format!("is not {width}x{height} like mask.png")));
        }
        let (_, img) = crate::hdr::decode_image(&bytes).map_err(|e| bad(&path, e))?;
        drop(bytes);
        photos.push(Photo {
            index,
            name: path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            light,
            intensity,
            pixels: img.into_rgb16().into_raw(),
        });
    }
    Ok(PhotometricSet {
        dir: dir.into(),
        width,
        height,
        mask,
        normals,
        photos,
        max_value: u16::MAX,
    })
}

impl PhotometricSet {
    /// Samples of the photos `which` (indices into `photos`): every `stride`-th masked
    /// pixel each way, saturated pixels (and `bloom` pixels around them) left out.
    /// Variances are shot-noise-like (proportional to the value, plus one unit); their
    /// scale is estimated from the residuals.
    pub fn samples(&self, which: &[usize], stride: usize, bloom: usize) -> (Vec<Sample>, usize) {
        let (w, h) = (self.width, self.height);
        let mut out = Vec::new();
        let mut left_out = 0;
        for &k in which {
            let p = &self.photos[k];
            let sat: Vec<bool> = (0..w * h)
                .map(|i| p.pixels[3 * i..3 * i + 3].contains(&self.max_value))
                .collect();
            let near_sat = |i: usize| {
                let (x, y) = ((i % w) as i64, (i / w) as i64);
                let b = bloom as i64;
                (y - b..=y + b).any(|yy| {
                    (x - b..=x + b).any(|xx| {
                        xx >= 0
                            && yy >= 0
                            && (xx as usize) < w
                            && (yy as usize) < h
                            && sat[yy as usize * w + xx as usize]
                    })
                })
            };
            for y in (0..h).step_by(stride.max(1)) {
                for x in (0..w).step_by(stride.max(1)) {
                    let i = y * w + x;
                    if !self.mask[i] {
                        continue;
                    }
                    if near_sat(i) {
                        left_out += 1;
                        continue;
                    }
                    let g = Geometry::from_vectors(p.light, [0.0, 0.0, 1.0], self.normals[i], 1.0);
                    let mut radiance = [0.0; 3];
                    let mut variance = [0.0; 3];
                    for c in 0..3 {
                        let v = p.pixels[3 * i + c] as f64;
                        radiance[c] = v / p.intensity[c];
                        variance[c] = (v + 1.0) / (p.intensity[c] * p.intensity[c]);
                    }
                    out.push(Sample::new(g, radiance, variance));
                }
            }
        }
        (out, left_out)
    }
}

/// One model's result on the photometric set.
#[derive(Debug, Clone, Serialize)]
pub struct PhotoCandidate {
    #[serde(flatten)]
    pub candidate: Candidate,
    /// sqrt(sum (predicted - measured)^2 / sum measured^2) over every value of the fitting
    /// photos and of the held-out photos.
    pub relative_error_fit: f64,
    pub relative_error_held_out: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct PhotoReport {
    pub format: String,
    pub data_set: String,
    pub fit_photos: Vec<String>,
    pub held_out_photos: Vec<String>,
    pub stride: usize,
    pub fit_samples: usize,
    pub held_out_samples: usize,
    pub left_out_saturated: usize,
    pub candidates: Vec<PhotoCandidate>,
    pub chosen: Model,
    pub seconds: f64,
}

fn relative_error(f: &ModelFit, s: &[Sample]) -> f64 {
    let (mut num, mut den) = (0.0, 0.0);
    for x in s {
        for ch in 0..3 {
            let p = f.predict(&x.geometry, ch);
            num += (p - x.radiance[ch]).powi(2);
            den += x.radiance[ch].powi(2);
        }
    }
    (num / den.max(1e-300)).sqrt()
}

/// Fit on alternate photos (the 1st, 3rd, ... of those present), predict the others.
pub fn fit_set(set: &PhotometricSet, models: &[Model], stride: usize) -> PhotoReport {
    let start = std::time::Instant::now();
    let fit_idx: Vec<usize> = (0..set.photos.len()).step_by(2).collect();
    let test_idx: Vec<usize> = (1..set.photos.len()).step_by(2).collect();
    let (train, l1) = set.samples(&fit_idx, stride, 2);
    let (test, l2) = set.samples(&test_idx, stride, 2);
    let opts = Options {
        variances_known: false,
        ..Options::default()
    };
    let choice = choose(models, &train, &test, &opts);
    let m = measured_values(&train);
    let chosen = choice.chosen;
    let candidates = choice
        .candidates
        .into_iter()
        .map(|sc| {
            let c = Candidate::new(sc.fit, sc.held_out, m);
            PhotoCandidate {
                relative_error_fit: relative_error(&c.fit, &train),
                relative_error_held_out: relative_error(&c.fit, &test),
                candidate: c,
            }
        })
        .collect();
    let names = |idx: &[usize]| idx.iter().map(|&k| set.photos[k].name.clone()).collect();
    PhotoReport {
        format: "glint-fit-photometric".into(),
        data_set: set.dir.display().to_string(),
        fit_photos: names(&fit_idx),
        held_out_photos: names(&test_idx),
        stride,
        fit_samples: train.len(),
        held_out_samples: test.len(),
        left_out_saturated: l1 + l2,
        candidates,
        chosen,
        seconds: start.elapsed().as_secs_f64(),
    }
}
