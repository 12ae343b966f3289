//! `glint import`: a folder of bracketed photos from any camera -> a Glint session.
//!
//! Exposure times come from a times file (one line per photo: `<file name> <seconds>`, the
//! time as a decimal `0.004` or a fraction `1/250`; `#` starts a comment) or, where a photo
//! carries EXIF data, from its ExposureTime tag. Every time is checked: positive, within
//! 1 µs .. 1 hour, no two photos sharing one.
//!
//! The work is bounded whatever the photos are: every file read is size-capped and must be
//! a regular file ([`crate::fsx`]); each photo's header is read and checked (size, bit
//! depth, at most [`crate::hdr::MAX_SIDE`] a side and [`crate::hdr::MAX_PIXELS`]) before
//! any photo is decoded; photos are then decoded one at a time, checked, written as a
//! lossless PNG frame and dropped, keeping only a sparse sample of their pixels.
//!
//! Those samples check that brightness rises with exposure time: a photo exposed longer
//! than the one before it in the bracket but clearly darker is refused (times written in
//! 1/s, `1000` for 1/1000 s, reverse the bracket).
//!
//! Nothing is written unless every photo is good: the session is built in a temporary
//! folder beside `out` and renamed into place at the end (`out` must not exist, or be an
//! empty folder). Its frames are all of kind `tile`.

use std::collections::HashSet;
use std::fs;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

use crate::devices::{CameraInfo, LampState, Pixels};
use crate::fsx::{self, quote};
use crate::hdr::{decode, probe_image, ImageInfo};
use crate::plan::{FrameKind, Plan};
use crate::session::{
    self, encode_png, sha256_hex, write_new, FrameRecord, Manifest, Software, State, Verification,
};

/// Shortest exposure time an import takes, seconds (1 µs).
pub const MIN_EXPOSURE_S: f64 = 1e-6;
/// Longest exposure time an import takes, seconds (1 hour).
pub const MAX_EXPOSURE_S: f64 = 3600.0;

/// What can go wrong; every message names the file (and line) to fix.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error("{0}")]
    Input(String),
    #[error(transparent)]
    Session(#[from] session::SessionError),
}

fn input(msg: String) -> ImportError {
    ImportError::Input(msg)
}

/// A photo's path for a message: on one line, and when longer than ~100 characters its
/// end (the file name) is kept.
fn shown(p: &Path) -> String {
    let s = short(&p.display().to_string());
    let n = s.chars().count();
    if n <= fsx::QUOTE_CHARS {
        return s;
    }
    let full = p
        .display()
        .to_string()
        .replace(|c: char| c.is_control(), "?");
    let tail: String = full
        .chars()
        .skip(full.chars().count().saturating_sub(fsx::QUOTE_CHARS - 1))
        .collect();
    format!("…{tail}")
}

/// A name for a message: [`quote`]d (one line, at most ~100 characters), without the
/// backticks.
fn short(s: &str) -> String {
    let q = quote(s);
    q[1..q.len() - 1].to_string()
}

/// Parse an exposure time in seconds: `0.004`, `4e-3` or `1/250`.
pub fn parse_time(s: &str) -> Option<f64> {
    let v = match s.split_once('/') {
        Some((a, b)) => a.trim().parse::<f64>().ok()? / b.trim().parse::<f64>().ok()?,
        None => s.trim().parse::<f64>().ok()?,
    };
    Some(v)
}

/// Check an exposure time of `name` (`written` as the user wrote it), for an error
/// starting with `at`: finite, positive, within [`MIN_EXPOSURE_S`] .. [`MAX_EXPOSURE_S`].
pub fn check_time(at: &str, name: &str, t: f64, written: &str) -> Result<(), ImportError> {
    let (name, written) = (quote(name), quote(written));
    if t.is_nan() || (t.is_infinite() && t > 0.0) {
        return Err(input(format!(
            "{at}: the exposure time of {name} is {written}, not a number of seconds; write seconds as a decimal (0.004) or a fraction (1/250)"
        )));
    }
    if t <= 0.0 {
        return Err(input(format!(
            "{at}: the exposure time of {name} is {written}; it must be positive"
        )));
    }
    if !(MIN_EXPOSURE_S..=MAX_EXPOSURE_S).contains(&t) {
        let hint = if t > MAX_EXPOSURE_S {
            "; if the times are in 1/s (`1000` for 1/1000 s), write them as fractions (`1/1000`)"
        } else {
            ""
        };
        return Err(input(format!(
            "{at}: the exposure time of {name} is {written} = {t:e} s, outside the 1 µs .. 1 hour (0.000001 .. 3600 s) an exposure can be{hint}"
        )));
    }
    Ok(())
}

/// Parse a times file into (file name, seconds) in file order.
pub fn parse_times(path: &Path, text: &str) -> Result<Vec<(String, f64)>, ImportError> {
    let mut out: Vec<(String, f64)> = Vec::new();
    let mut names = HashSet::new();
    for (i, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let at = format!("{}:{}", path.display(), i + 1);
        let mut parts = line.split_whitespace();
        let (Some(name), Some(time), None) = (parts.next(), parts.next(), parts.next()) else {
            return Err(input(format!(
                "{at}: expected `<file name> <exposure time in seconds>`, got {}",
                quote(line)
            )));
        };
        let t = parse_time(time).ok_or_else(|| {
            input(format!(
                "{at}: {} is not a time; write seconds as a decimal (0.004) or a fraction (1/250)",
                quote(time)
            ))
        })?;
        check_time(&at, name, t, time)?;
        if !names.insert(name.to_string()) {
            return Err(input(format!("{at}: {} is listed twice", short(name))));
        }
        out.push((name.to_string(), t));
    }
    if out.is_empty() {
        return Err(input(format!(
            "{}: no photos listed; write one line per photo: `<file name> <seconds>`",
            path.display()
        )));
    }
    Ok(out)
}

/// EXIF ExposureTime in seconds, where the file has one.
pub fn exif_exposure(bytes: &[u8]) -> Option<f64> {
    let mut cur = std::io::Cursor::new(bytes);
    let ex = exif::Reader::new().read_from_container(&mut cur).ok()?;
    let f = ex.get_field(exif::Tag::ExposureTime, exif::In::PRIMARY)?;
    match &f.value {
        exif::Value::Rational(v) if !v.is_empty() => Some(v[0].to_f64()),
        _ => None,
    }
}

/// The result of an import.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ImportReport {
    pub session: PathBuf,
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    pub bit_depth: u8,
    /// (file, seconds), shortest first.
    pub exposures_s: Vec<(String, f64)>,
}

/// Samples kept of each photo for the brightness check: at most this many pixels, on a
/// regular grid (the same grid in every photo of a bracket).
pub const CHECK_PIXELS: usize = 1 << 16;

/// A sparse sample of a photo's values (RGB, on a regular grid of at most
/// [`CHECK_PIXELS`] pixels).
pub fn sample_values(width: usize, height: usize, pixels: &Pixels) -> Vec<u16> {
    let step = ((width * height) as f64 / CHECK_PIXELS as f64)
        .sqrt()
        .ceil()
        .max(1.0) as usize;
    let mut out = Vec::new();
    for y in (0..height).step_by(step) {
        for x in (0..width).step_by(step) {
            let i = 3 * (y * width + x);
            for c in 0..3 {
                out.push(match pixels {
                    Pixels::U8(v) => v[i + c] as u16,
                    Pixels::U16(v) => v[i + c],
                });
            }
        }
    }
    out
}

/// Is a photo `longer` (exposed longer) clearly darker than `shorter`? Compares the same
/// pixels of both, leaving out those black in both or saturated in both (they carry no
/// information about the order) and counting a pixel darker or brighter only beyond 2% of
/// full scale (noise). Returns the fraction of compared pixels that are darker, when most
/// are and at least four times as many are darker as brighter; None otherwise (including
/// when too few pixels can be compared to tell).
pub fn clearly_darker(shorter: &[u16], longer: &[u16], max_value: u32) -> Option<f64> {
    let margin = (max_value / 50).max(1) as i64;
    let (lo, hi) = (margin, max_value as i64 - margin);
    let (mut n, mut darker, mut brighter) = (0usize, 0usize, 0usize);
    for (&a, &b) in shorter.iter().zip(longer) {
        let (a, b) = (a as i64, b as i64);
        if (a <= lo && b <= lo) || (a >= hi && b >= hi) {
            continue;
        }
        n += 1;
        if b < a - margin {
            darker += 1;
        } else if b > a + margin {
            brighter += 1;
        }
    }
    (n >= 16 && 2 * darker > n && darker > 4 * brighter).then(|| darker as f64 / n as f64)
}

/// A photo once its header is read.
struct Listed {
    name: String,
    path: PathBuf,
    seconds: f64,
    info: ImageInfo,
}

fn read_photo(path: &Path, dir: &Path, from_times: bool) -> Result<Vec<u8>, ImportError> {
    fsx::read_capped(path, fsx::MAX_IMAGE_BYTES).map_err(|e| {
        let hint = if from_times && e.kind() == std::io::ErrorKind::NotFound {
            format!(
                "; the times file lists a photo that is not in {}",
                dir.display()
            )
        } else {
            String::new()
        };
        input(format!("{}: cannot read ({e}){hint}", shown(path)))
    })
}

/// The part of a photo's name kept in its frame's file name: letters, digits, `-` and
/// `_` (others become `_`), at most 64 characters.
fn stem_of(name: &str) -> String {
    name.rsplit_once('.')
        .map(|(s, _)| s)
        .unwrap_or(name)
        .chars()
        .take(64)
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// Check that `out` can receive a session: absent, or an empty real folder.
fn check_out(out: &Path) -> Result<(), ImportError> {
    match fs::symlink_metadata(out) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(input(format!("cannot read {} ({e})", out.display()))),
        Ok(m) if m.is_dir() => {
            let empty = fs::read_dir(out)
                .map_err(|e| input(format!("cannot read {} ({e})", out.display())))?
                .next()
                .is_none();
            if empty {
                Ok(())
            } else {
                Err(session::SessionError::Exists { path: out.into() }.into())
            }
        }
        Ok(m) if m.file_type().is_symlink() => Err(input(format!(
            "{} is a symbolic link; give --out a new folder (Glint writes sessions only into real folders)",
            out.display()
        ))),
        Ok(_) => Err(session::SessionError::Exists { path: out.into() }.into()),
    }
}

/// Import the photos of `dir` into a new session at `out`.
pub fn import(dir: &Path, times: Option<&Path>, out: &Path) -> Result<ImportReport, ImportError> {
    if !dir.is_dir() {
        return Err(input(format!(
            "{} is not a folder of photos",
            dir.display()
        )));
    }
    check_out(out)?;
    // The photos and their times.
    let listed: Vec<(String, Option<f64>)> = match times {
        Some(tf) => {
            let text = fsx::read_text_capped(tf, fsx::MAX_TEXT_BYTES)
                .map_err(|e| input(format!("cannot read the times file {} ({e})", tf.display())))?;
            parse_times(tf, &text)?
                .into_iter()
                .map(|(n, t)| (n, Some(t)))
                .collect()
        }
        None => {
            let mut names: Vec<String> = fs::read_dir(dir)
                .map_err(|e| input(format!("cannot list {} ({e})", dir.display())))?
                .flatten()
                .filter(|e| e.path().is_file())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|n| {
                    let l = n.to_ascii_lowercase();
                    [".png", ".jpg", ".jpeg", ".tif", ".tiff"]
                        .iter()
                        .any(|x| l.ends_with(x))
                })
                .collect();
            names.sort();
            if names.is_empty() {
                return Err(input(format!(
                    "{} holds no PNG, JPEG or TIFF photos",
                    dir.display()
                )));
            }
            names.into_iter().map(|n| (n, None)).collect()
        }
    };
    let from_times = times.is_some();
    let where_times = || match times {
        Some(tf) => format!("the times file {}", tf.display()),
        None => "the photos' EXIF exposure times".into(),
    };
    // First every photo's header and time, one file at a time: a bad photo (wrong size,
    // too large, not an image) is found before anything is decoded.
    let mut photos: Vec<Listed> = Vec::new();
    for (name, t) in &listed {
        let path = fsx::inside(dir, name).map_err(|e| {
            input(format!(
                "{}: the photo {e}; list photos inside {}",
                times.unwrap_or(dir).display(),
                dir.display()
            ))
        })?;
        let bytes = read_photo(&path, dir, from_times)?;
        let seconds = match t {
            Some(t) => *t,
            None => {
                let s = exif_exposure(&bytes).ok_or_else(|| {
                    input(format!(
                        "{}: no EXIF exposure time; give the times with --times FILE (`<file name> <seconds>` per line)",
                        shown(&path)
                    ))
                })?;
                check_time(
                    &format!("{} (EXIF ExposureTime)", shown(&path)),
                    name,
                    s,
                    &s.to_string(),
                )?;
                s
            }
        };
        let info = probe_image(&bytes).map_err(|e| input(format!("{}: {e}", shown(&path))))?;
        if let Some(first) = photos.first() {
            if (info.width, info.height) != (first.info.width, first.info.height) {
                return Err(input(format!(
                    "{} is {}x{} but {} is {}x{}; all photos of a bracket must have one size",
                    short(name),
                    info.width,
                    info.height,
                    short(&first.name),
                    first.info.width,
                    first.info.height
                )));
            }
            if info.bit_depth != first.info.bit_depth {
                return Err(input(format!(
                    "{} is {}-bit but {} is {}-bit; all photos of a bracket must have one bit depth",
                    short(name),
                    info.bit_depth,
                    short(&first.name),
                    first.info.bit_depth
                )));
            }
        }
        photos.push(Listed {
            name: name.clone(),
            path,
            seconds,
            info,
        });
    }
    photos.sort_by(|a, b| a.seconds.total_cmp(&b.seconds));
    for w in photos.windows(2) {
        if (w[1].seconds / w[0].seconds - 1.0).abs() < 1e-9 {
            return Err(input(format!(
                "{} and {} have the same exposure time ({} s); a bracket needs distinct times",
                short(&w[0].name),
                short(&w[1].name),
                w[0].seconds
            )));
        }
    }
    if photos.len() < 2 {
        return Err(input(format!(
            "a bracket needs at least 2 photos, found {}",
            photos.len()
        )));
    }
    let first = photos[0].info;
    let max_value = (1u32 << first.bit_depth) - 1;

    // Then the session, built in a temporary folder beside `out` and renamed into place
    // once complete: nothing appears at `out` unless every photo is good, and a failure
    // leaves nothing behind (the folder is removed when `staging` is dropped).
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    fsx::ensure_dir(&parent)
        .map_err(|e| input(format!("cannot create {} ({e})", parent.display())))?;
    let out_name = out
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "session".into());
    let staging = tempfile::Builder::new()
        .prefix(&format!(".{}.import-", stem_of(&out_name)))
        .tempdir_in(&parent)
        .map_err(|e| {
            input(format!(
                "cannot create a folder in {} ({e})",
                parent.display()
            ))
        })?;
    let frames_dir = staging.path().join("frames");
    fs::create_dir(&frames_dir)
        .map_err(|e| input(format!("cannot create {} ({e})", frames_dir.display())))?;
    let now = session::timestamp(SystemTime::now());
    let mut frames = Vec::new();
    let mut previous: Option<(usize, Vec<u16>)> = None;
    for (i, p) in photos.iter().enumerate() {
        // One photo decoded at a time; its pixels are dropped at the end of the loop.
        let bytes = read_photo(&p.path, dir, from_times)?;
        let shown = shown(&p.path);
        let (width, height, bits, pixels) =
            decode(&bytes, &shown).map_err(|e| input(e.to_string()))?;
        drop(bytes);
        if (width as u32, height as u32, bits) != (p.info.width, p.info.height, p.info.bit_depth) {
            return Err(input(format!(
                "{shown}: changed while being imported (now {width}x{height} {bits}-bit); import again"
            )));
        }
        let values = sample_values(width, height, &pixels);
        if let Some((j, before)) = &previous {
            let q = &photos[*j];
            if let Some(f) = clearly_darker(before, &values, max_value) {
                return Err(input(format!(
                    "{} ({} s) is darker than {} ({} s) in {:.0}% of the pixels compared, although exposed longer: the times are wrong or not in seconds (1/1000 s written as `1000` is in 1/s: write `1/1000`); check {}",
                    short(&p.name),
                    p.seconds,
                    short(&q.name),
                    q.seconds,
                    100.0 * f,
                    where_times()
                )));
            }
        }
        previous = Some((i, values));
        let png = encode_png(width as u32, height as u32, &pixels)
            .map_err(|e| input(format!("{shown}: {e}")))?;
        drop(pixels);
        let us = p.seconds * 1e6;
        let rounded = us.round().clamp(1.0, u32::MAX as f64) as u32;
        let file = format!("frames/{i:04}-tile-{}.png", stem_of(&p.name));
        write_new(&staging.path().join(&file), &png)?;
        frames.push(FrameRecord {
            index: i as u32,
            file,
            kind: FrameKind::Tile,
            exposure_requested_us: rounded,
            exposure_reported_us: rounded,
            exposure_exact_us: (us != rounded as f64).then_some(us),
            exposure_verified_by: Verification::Imported,
            timestamp: now.clone(),
            device_timestamp_us: None,
            sequence: i as u64,
            lamp: LampState::OFF,
            width: width as u32,
            height: height as u32,
            bit_depth: bits,
            sha256: sha256_hex(&png),
        });
    }
    let manifest = Manifest {
        format: session::FORMAT.into(),
        format_version: session::FORMAT_VERSION,
        state: State::Complete,
        failure: None,
        software: Software {
            name: "glint".into(),
            version: crate::VERSION.into(),
        },
        created: now.clone(),
        finished: Some(now),
        rig_file: String::new(),
        rig: None,
        camera: Some(CameraInfo::basic(
            "imported",
            first.width,
            first.height,
            first.bit_depth,
            3,
        )),
        lamp_identity: None,
        plan: Plan::default(),
        imported_from: Some(dir.display().to_string()),
        lamp_off_confirmed: None,
        frames,
    };
    let json = serde_json::to_vec_pretty(&manifest).expect("manifest serialises");
    write_new(&staging.path().join("manifest.json"), &json)?;
    // Into place: `out` is absent or still an empty folder (rename replaces only an empty
    // one; if something appeared there meanwhile, the rename fails and nothing is lost).
    check_out(out)?;
    fs::rename(staging.path(), out).map_err(|e| {
        input(format!(
            "cannot move the new session into place at {} ({e}); nothing was written there",
            out.display()
        ))
    })?;
    let _ = staging.keep();
    if let Ok(d) = fs::File::open(&parent) {
        let _ = d.sync_all();
    }
    Ok(ImportReport {
        session: out.into(),
        frames: photos.len(),
        width: first.width,
        height: first.height,
        bit_depth: first.bit_depth,
        exposures_s: photos.iter().map(|p| (p.name.clone(), p.seconds)).collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn absurd_times_are_refused_with_the_range() {
        for (t, want) in [
            ("1e-300", "outside the 1 µs .. 1 hour"),
            ("1e300", "outside the 1 µs .. 1 hour"),
            ("4000", "write them as fractions (`1/1000`)"),
            ("1/0", "not a number of seconds"),
            ("0/0", "not a number of seconds"),
            ("0", "must be positive"),
            ("-1/0", "must be positive"),
        ] {
            let e = parse_times(Path::new("t.txt"), &format!("a.png {t}\n"))
                .unwrap_err()
                .to_string();
            assert!(e.contains(want), "{t}: {e}");
            assert!(e.starts_with("t.txt:1: "), "{e}");
        }
        assert!(parse_times(Path::new("t.txt"), "a.png 0.000001\nb.png 3600\n").is_ok());
    }

    #[test]
    fn a_long_times_file_line_is_quoted_short_on_one_line() {
        let long = "x".repeat(1 << 20);
        for text in [
            format!("{long}\n"),
            format!("a.png {long}\n"),
            format!("{long} 1/2\n{long} 1/4\n"),
        ] {
            let e = parse_times(Path::new("t.txt"), &text)
                .unwrap_err()
                .to_string();
            assert!(e.len() < 400, "{} bytes", e.len());
            assert!(!e.contains('\n'));
        }
    }

    #[test]
    fn brightness_order_tolerates_noise_and_clipping_but_not_a_reversed_bracket() {
        let ramp: Vec<u16> = (0..3000).map(|i| (i % 256) as u16).collect();
        // Twice as long: values double (clipped at 255).
        let double: Vec<u16> = ramp.iter().map(|v| (v * 2).min(255)).collect();
        assert_eq!(clearly_darker(&ramp, &double, 255), None);
        assert!(clearly_darker(&double, &ramp, 255).unwrap() > 0.9);
        // Nearly the same exposure, with noise of a few levels either way.
        let noisy: Vec<u16> = ramp
            .iter()
            .enumerate()
            .map(|(i, v)| (*v as i32 + (i as i32 % 7) - 3).clamp(0, 255) as u16)
            .collect();
        assert_eq!(clearly_darker(&ramp, &noisy, 255), None);
        assert_eq!(clearly_darker(&noisy, &ramp, 255), None);
        // Saturated (or black) in both: nothing to compare.
        assert_eq!(clearly_darker(&[255; 300], &[254; 300], 255), None);
        assert_eq!(clearly_darker(&[3; 300], &[0; 300], 255), None);
    }
}
