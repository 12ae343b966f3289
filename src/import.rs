//! `glint import`: a folder of bracketed photos from any camera -> a Glint session.
//!
//! Exposure times come from a times file (one line per photo: `<file name> <seconds>
//! [tile|dark|grid]`, the time as a decimal `0.004` or a fraction `1/250`, the kind `tile`
//! unless named; `#` starts a comment) or, where a photo carries EXIF data, from its
//! ExposureTime tag. Every time is checked: positive, within 1 µs .. 1 hour, no two tile
//! photos sharing one. EXIF aperture (FNumber) and ISO are recorded with each frame, and a
//! change of either within the bracket is warned about (the merge assumes only the time
//! changes).
//!
//! With a rig (`--rig`, usually a processing rig: `camera.backend = "external"`) the session
//! holds its geometry and grid, and `glint calibrate`, `fit`, `validate` and `report` run on
//! it as on a captured one; grid photos (`--grid`, or kind `grid`) calibrate the camera, dark
//! photos (`--dark`, or kind `dark`; the lens capped, at the tile photos' exposures) give the
//! black level. Without a rig only `glint hdr` applies.
//!
//! The work is bounded whatever the photos are: every file read is size-capped and must be
//! a regular file ([`crate::fsx`]); each photo's header is read and checked (size, bit
//! depth, at most [`crate::hdr::MAX_SIDE`] a side and [`crate::hdr::MAX_PIXELS`]) before
//! any photo is decoded; photos are then decoded one at a time, checked, written as a
//! lossless PNG frame and dropped, keeping only a sparse sample of their pixels.
//!
//! Those samples check that brightness rises with exposure time: a photo exposed longer
//! than the one before it in the bracket but clearly darker is refused (times written in
//! 1/s, `1000` for 1/1000 s, reverse the bracket); so is one exposed half a stop or more
//! longer ([`MIN_RATIO`]) whose mean level, over the pixels black or saturated in neither,
//! does not rise ([`no_brighter`]: copies of one photo, or a camera in an automatic mode
//! that undid each change of time): compared with the photo before it, it must rise at
//! all (at the dark end of a real bracket, as Debevec's memorial church, neighbours a stop
//! apart differ by well under 1% in mean level), and across the whole bracket, the longest
//! against the shortest, by [`MIN_RISE`].
//!
//! A photo is decoded whole or refused: a file cut short (a JPEG truncated to half its
//! length decodes leniently with its lower rows grey) is refused by the decoder
//! ([`crate::hdr::decode_image`]).
//!
//! Nothing is written unless every photo is good: the session is built in a temporary
//! folder beside `out` and renamed into place at the end (`out` must not exist, or be an
//! empty folder).

use std::collections::HashSet;
use std::fs;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

use crate::devices::{CameraInfo, LampState, Pixels};
use crate::fsx::{self, quote};
use crate::hdr::{probe_image, ImageInfo};
use crate::plan::{FrameKind, Plan};
use crate::rig::{CameraBackend, LoadedRig};
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
    /// A photo that does not decode (its name and the reason).
    #[error(transparent)]
    Decode(#[from] crate::hdr::HdrError),
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

/// A photo's kind from a times file's third column.
fn parse_kind(s: &str) -> Option<FrameKind> {
    [FrameKind::Tile, FrameKind::Dark, FrameKind::Grid]
        .into_iter()
        .find(|k| k.as_str().eq_ignore_ascii_case(s))
}

/// Parse a times file into (file name, seconds) in file order (every kind).
pub fn parse_times(path: &Path, text: &str) -> Result<Vec<(String, f64)>, ImportError> {
    Ok(parse_times_with_kinds(path, text)?
        .into_iter()
        .map(|(n, t, _)| (n, t))
        .collect())
}

/// Parse a times file into (file name, seconds, kind) in file order: `<file name>
/// <seconds> [tile|dark|grid]`.
pub fn parse_times_with_kinds(
    path: &Path,
    text: &str,
) -> Result<Vec<(String, f64, FrameKind)>, ImportError> {
    let mut out: Vec<(String, f64, FrameKind)> = Vec::new();
    let mut names = HashSet::new();
    for (i, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let at = format!("{}:{}", path.display(), i + 1);
        let mut parts = line.split_whitespace();
        let (Some(name), Some(time), kind, None) =
            (parts.next(), parts.next(), parts.next(), parts.next())
        else {
            return Err(input(format!(
                "{at}: expected `<file name> <exposure time in seconds> [tile|dark|grid]`, got {}",
                quote(line)
            )));
        };
        let kind = match kind {
            None => FrameKind::Tile,
            Some(k) => parse_kind(k).ok_or_else(|| {
                input(format!(
                    "{at}: {} is not a kind of photo; write tile (the bracket, the default), dark (lens capped) or grid (the chessboard, tile removed)",
                    quote(k)
                ))
            })?,
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
        out.push((name.to_string(), t, kind));
    }
    if out.is_empty() {
        return Err(input(format!(
            "{}: no photos listed; write one line per photo: `<file name> <seconds>`",
            path.display()
        )));
    }
    Ok(out)
}

/// What a photo's EXIF data says, where it has them: ExposureTime (s), FNumber, ISO
/// (PhotographicSensitivity) and the camera (`Make Model`, one line of at most 100
/// characters of text; an imported session's camera is named by it, so that its response
/// and lens profiles are that camera's). The EXIF block is parsed once a photo.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PhotoExif {
    pub exposure_s: Option<f64>,
    pub f_number: Option<f64>,
    pub iso: Option<u32>,
    pub camera: Option<String>,
}

/// [`PhotoExif`] of a photo's bytes (all None where it has no EXIF block).
pub fn photo_exif(bytes: &[u8]) -> PhotoExif {
    let mut cur = std::io::Cursor::new(bytes);
    let Ok(ex) = exif::Reader::new().read_from_container(&mut cur) else {
        return PhotoExif::default();
    };
    let rational = |tag| {
        ex.get_field(tag, exif::In::PRIMARY)
            .and_then(|f| match &f.value {
                exif::Value::Rational(v) if !v.is_empty() => Some(v[0].to_f64()),
                _ => None,
            })
    };
    let text = |tag| {
        ex.get_field(tag, exif::In::PRIMARY)
            .and_then(|f| match &f.value {
                exif::Value::Ascii(v) => v
                    .first()
                    .map(|b| String::from_utf8_lossy(b).trim().to_string()),
                _ => None,
            })
    };
    let make = text(exif::Tag::Make).unwrap_or_default();
    let model = text(exif::Tag::Model).unwrap_or_default();
    // Many cameras repeat the make in the model ("Canon" / "Canon EOS 5D").
    let name = if model.starts_with(&make) {
        model
    } else {
        format!("{make} {model}")
    };
    let name: String = name
        .chars()
        .map(|c| if c.is_control() { ' ' } else { c })
        .take(100)
        .collect();
    let name = name.trim().to_string();
    PhotoExif {
        exposure_s: rational(exif::Tag::ExposureTime),
        f_number: rational(exif::Tag::FNumber).filter(|f| f.is_finite() && *f > 0.0 && *f < 1e4),
        iso: ex
            .get_field(exif::Tag::PhotographicSensitivity, exif::In::PRIMARY)
            .and_then(|f| f.value.get_uint(0))
            .filter(|v| *v > 0),
        camera: (!name.is_empty()).then_some(name),
    }
}

/// What `glint import` is given besides the folder.
#[derive(Debug, Clone, Default)]
pub struct ImportOptions {
    /// The times file (`<file name> <seconds> [tile|dark|grid]` per line); else EXIF.
    pub times: Option<PathBuf>,
    /// The rig whose geometry and grid the session holds (a processing rig, or the rig of
    /// the bench the photos were taken on).
    pub rig: Option<LoadedRig>,
    /// Grid photos (the chessboard, tile removed): paths as given, or names in the folder.
    pub grid: Vec<PathBuf>,
    /// Dark photos (lens capped) at the tile photos' exposures.
    pub dark: Vec<PathBuf>,
}

/// The result of an import.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ImportReport {
    pub session: PathBuf,
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    pub bit_depth: u8,
    /// (file, seconds) of the tile photos, shortest first.
    pub exposures_s: Vec<(String, f64)>,
    /// Grid and dark photos imported.
    pub grid: usize,
    pub dark: usize,
    /// The rig the session holds, if one was given.
    pub rig: Option<PathBuf>,
    /// What the user should know (aperture or ISO changing within the bracket, a dark
    /// photo at no tile photo's exposure).
    pub warnings: Vec<String>,
}

/// Samples kept of each photo for the brightness check: at most this many pixels, on a
/// regular grid (the same grid in every photo of a bracket).
pub const CHECK_PIXELS: usize = 1 << 16;

/// A sparse sample of a photo's values (`channels` samples a pixel: 3 for RGB, 1 for
/// grey), on a regular grid of at most [`CHECK_PIXELS`] pixels.
pub fn sample_values(width: usize, height: usize, channels: usize, pixels: &Pixels) -> Vec<u16> {
    let step = ((width * height) as f64 / CHECK_PIXELS as f64)
        .sqrt()
        .ceil()
        .max(1.0) as usize;
    let mut out = Vec::new();
    for y in (0..height).step_by(step) {
        for x in (0..width).step_by(step) {
            let i = channels * (y * width + x);
            for c in 0..channels {
                out.push(match pixels {
                    Pixels::U8(v) => v.get(i + c).map_or(0, |v| *v as u16),
                    Pixels::U16(v) => v.get(i + c).copied().unwrap_or(0),
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

/// Exposure ratio from which a longer photo must be brighter: half a stop (√2). Closer
/// times may differ by less than the noise.
pub const MIN_RATIO: f64 = std::f64::consts::SQRT_2;
/// How much brighter, at least: the mean level rises by 2% (half a stop more light raises
/// a linear sensor's values by 41%, a JPEG's gamma-encoded ones by about 17%).
pub const MIN_RISE: f64 = 0.02;

/// The mean levels of the same pixels of two photos, over those that can show a change:
/// the pixels black (within 2% of full scale of 0) in both or saturated (within 2% of
/// full scale) in both are left out, as in [`clearly_darker`]. (mean of `shorter`, mean of
/// `longer`, pixels compared); None when fewer than 16 are left (nothing to tell).
pub fn mean_levels(shorter: &[u16], longer: &[u16], max_value: u32) -> Option<(f64, f64, usize)> {
    let margin = (max_value / 50).max(1) as i64;
    let (lo, hi) = (margin, max_value as i64 - margin);
    let (mut n, mut sa, mut sb) = (0usize, 0.0f64, 0.0f64);
    for (&a, &b) in shorter.iter().zip(longer) {
        let (a, b) = (a as i64, b as i64);
        if (a <= lo && b <= lo) || (a >= hi && b >= hi) {
            continue;
        }
        n += 1;
        sa += a as f64;
        sb += b as f64;
    }
    (n >= 16).then(|| (sa / n as f64, sb / n as f64, n))
}

/// Does a photo exposed `ratio` times longer than another ([`MIN_RATIO`] at least) fail
/// to be brighter? Its mean level over the pixels that can show a change
/// ([`mean_levels`]) must exceed the other's by `min_rise` (0: at all; [`MIN_RISE`] across
/// a whole bracket); when it does not, the
/// photos do not change with their exposure times (copies of one photo, or a camera left
/// in an automatic mode that undid each change of time) and (mean of `shorter`, mean of
/// `longer`, pixels compared) is returned.
pub fn no_brighter(
    shorter: &[u16],
    longer: &[u16],
    ratio: f64,
    max_value: u32,
    min_rise: f64,
) -> Option<(f64, f64, usize)> {
    if ratio.is_nan() || ratio < MIN_RATIO {
        return None;
    }
    let (a, b, n) = mean_levels(shorter, longer, max_value)?;
    (b <= a * (1.0 + min_rise)).then_some((a, b, n))
}

/// A photo once its header is read.
struct Listed {
    name: String,
    path: PathBuf,
    seconds: f64,
    kind: FrameKind,
    info: ImageInfo,
    /// One channel (grey) rather than colour.
    grey: bool,
    f_number: Option<f64>,
    iso: Option<u32>,
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

/// Is the photo grey (one channel, with or without alpha)? From its header.
fn is_grey(bytes: &[u8]) -> bool {
    use image::ImageDecoder;
    // A DNG's mosaic is colour (its first image, a thumbnail, says nothing about it).
    if crate::hdr::dng::is_dng(bytes) {
        return false;
    }
    image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .ok()
        .and_then(|r| r.into_decoder().ok())
        .is_some_and(|d| {
            matches!(
                d.color_type(),
                image::ColorType::L8
                    | image::ColorType::La8
                    | image::ColorType::L16
                    | image::ColorType::La16
            )
        })
}

/// An exposure in seconds as the whole µs a frame record and a rig's bracket hold (at
/// least 1).
fn whole_us(seconds: f64) -> u32 {
    (seconds * 1e6).round().clamp(1.0, u32::MAX as f64) as u32
}

/// A photo given on the command line (`--grid`, `--dark`): the path as given, or a name in
/// the photos' folder.
fn resolve_given(dir: &Path, p: &Path, flag: &str) -> Result<PathBuf, ImportError> {
    if p.exists() {
        return Ok(p.to_path_buf());
    }
    let inside = dir.join(p);
    if p.is_relative() && inside.exists() {
        return Ok(inside);
    }
    Err(input(format!(
        "{flag} {}: no such photo (neither that path nor {})",
        shown(p),
        shown(&inside)
    )))
}

/// A photo as listed: its name, path, time (from the times file; none: from its EXIF) and
/// kind.
type Entry = (String, PathBuf, Option<f64>, FrameKind);

/// The photos to import: those the times file lists (else the folder's photos), with the
/// photos given by flag (`--grid`, `--dark`) of their kinds.
fn list_photos(dir: &Path, opts: &ImportOptions) -> Result<Vec<Entry>, ImportError> {
    let times = opts.times.as_deref();
    // The photos given by flag, with their kinds (their times: the times file, else EXIF).
    let mut given: Vec<(PathBuf, FrameKind)> = Vec::new();
    for (list, flag, kind) in [
        (&opts.grid, "--grid", FrameKind::Grid),
        (&opts.dark, "--dark", FrameKind::Dark),
    ] {
        for p in list {
            given.push((resolve_given(dir, p, flag)?, kind));
        }
    }
    let canon = |p: &Path| fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
    let given_canon: Vec<(PathBuf, FrameKind)> =
        given.iter().map(|(p, k)| (canon(p), *k)).collect();
    for (i, (c, k)) in given_canon.iter().enumerate() {
        if let Some((_, k2)) = given_canon[..i].iter().find(|(c2, k2)| c2 == c && k2 != k) {
            return Err(input(format!(
                "{} is given both as a {} photo and as a {} photo (--grid and --dark); give it one kind",
                shown(&given[i].0),
                k2.as_str(),
                k.as_str()
            )));
        }
    }
    // The photos and their times.
    let mut listed: Vec<Entry> = match times {
        Some(tf) => {
            let text = fsx::read_text_capped(tf, fsx::MAX_TEXT_BYTES)
                .map_err(|e| input(format!("cannot read the times file {} ({e})", tf.display())))?;
            let mut v = Vec::new();
            for (n, t, k) in parse_times_with_kinds(tf, &text)? {
                let path = fsx::inside(dir, &n).map_err(|e| {
                    input(format!(
                        "{}: the photo {e}; list photos inside {}",
                        tf.display(),
                        dir.display()
                    ))
                })?;
                v.push((n, path, Some(t), k));
            }
            v
        }
        None => {
            let mut names: Vec<String> = fs::read_dir(dir)
                .map_err(|e| input(format!("cannot list {} ({e})", dir.display())))?
                .flatten()
                .filter(|e| e.path().is_file())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|n| {
                    let l = n.to_ascii_lowercase();
                    [".png", ".jpg", ".jpeg", ".tif", ".tiff", ".dng"]
                        .iter()
                        .any(|x| l.ends_with(x))
                })
                .collect();
            names.sort();
            if names.is_empty() {
                return Err(input(format!(
                    "{} holds no PNG, JPEG, TIFF or DNG photos",
                    dir.display()
                )));
            }
            names
                .into_iter()
                .map(|n| {
                    let path = dir.join(&n);
                    (n, path, None, FrameKind::Tile)
                })
                .collect()
        }
    };
    // A photo given by flag and also listed (or found in the folder) is that entry, of the
    // flag's kind; one the times file gives another kind is a contradiction.
    for ((p, kind), (c, _)) in given.iter().zip(&given_canon) {
        match listed.iter_mut().find(|e| canon(&e.1) == *c) {
            Some(e) => {
                if times.is_some() && e.3 != FrameKind::Tile && e.3 != *kind {
                    return Err(input(format!(
                        "{} is given as a {} photo but the times file lists it as {}; give it one kind",
                        shown(p),
                        kind.as_str(),
                        e.3.as_str()
                    )));
                }
                e.3 = *kind;
            }
            None => {
                let name = p
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_else(|| p.display().to_string());
                listed.push((name, p.clone(), None, *kind));
            }
        }
    }
    let has_rig = opts.rig.is_some();
    if !has_rig && listed.iter().any(|e| e.3 == FrameKind::Grid) {
        return Err(input(
            "a grid photo calibrates the camera in the rig's grid coordinates: give the rig too (--rig RIG; a processing rig, camera.backend = \"external\", holds just the geometry and grid)".into(),
        ));
    }
    Ok(listed)
}

/// Where the exposure times came from, for messages.
fn where_times(times: Option<&Path>) -> String {
    match times {
        Some(tf) => format!("the times file {}", tf.display()),
        None => "the photos' EXIF exposure times".into(),
    }
}

/// Two exposure times that are one (photos of one time are repeats, averaged).
fn same_time(a: f64, b: f64) -> bool {
    (b / a - 1.0).abs() < 1e-9
}

/// Every photo's header and time, one file at a time, all of one size and depth; and the
/// camera's model (the first photo's EXIF that names one).
fn read_headers(
    dir: &Path,
    listed: &[Entry],
    from_times: bool,
) -> Result<(Vec<Listed>, Option<String>), ImportError> {
    // First every photo's header and time, one file at a time: a bad photo (wrong size,
    // too large, not an image) is found before anything is decoded.
    let mut photos: Vec<Listed> = Vec::new();
    let mut camera_model: Option<String> = None;
    for (name, path, t, kind) in listed {
        let bytes = read_photo(path, dir, from_times)?;
        let exif = photo_exif(&bytes);
        let seconds = match t {
            Some(t) => *t,
            None => {
                let s = exif.exposure_s.ok_or_else(|| {
                    let how = if *kind == FrameKind::Tile {
                        "give the times with --times FILE (`<file name> <seconds>` per line)"
                            .to_string()
                    } else {
                        format!(
                            "put it in {} and list it in a times file with its kind (`{} 1/60 {}`)",
                            dir.display(),
                            short(name),
                            kind.as_str()
                        )
                    };
                    input(format!("{}: no EXIF exposure time; {how}", shown(path)))
                })?;
                check_time(
                    &format!("{} (EXIF ExposureTime)", shown(path)),
                    name,
                    s,
                    &s.to_string(),
                )?;
                s
            }
        };
        let info = probe_image(&bytes).map_err(|e| input(format!("{}: {e}", shown(path))))?;
        let grey = is_grey(&bytes);
        if camera_model.is_none() {
            camera_model = exif.camera;
        }
        if let Some(first) = photos.first() {
            if (info.width, info.height) != (first.info.width, first.info.height) {
                return Err(input(format!(
                    "{} is {}x{} but {} is {}x{}; all photos of a session (bracket, grid and dark) must have one size",
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
                    "{} is {}-bit but {} is {}-bit; all photos of a session (bracket, grid and dark) must have one bit depth",
                    short(name),
                    info.bit_depth,
                    short(&first.name),
                    first.info.bit_depth
                )));
            }
        }
        photos.push(Listed {
            name: name.clone(),
            path: path.clone(),
            seconds,
            kind: *kind,
            info,
            grey,
            f_number: exif.f_number,
            iso: exif.iso,
        });
    }
    Ok((photos, camera_model))
}

/// Sort the photos (tile photos first, shortest first, then darks, then grids) and check
/// they make a bracket: all grey (a monochrome camera's, returned true) or all colour, and
/// tile photos at two times at least.
fn sort_and_check(photos: &mut [Listed], times: Option<&Path>) -> Result<bool, ImportError> {
    // A monochrome camera's photos are grey, and stay one channel (as a monochrome camera's
    // captured session); grey and colour photos do not mix.
    let mono = photos.iter().all(|p| p.grey);
    if !mono {
        if let (Some(g), Some(c)) = (
            photos.iter().find(|p| p.grey),
            photos.iter().find(|p| !p.grey),
        ) {
            return Err(input(format!(
                "{} is grey but {} is colour; all photos of a session come from one camera (convert them alike)",
                short(&g.name),
                short(&c.name)
            )));
        }
    }
    // Tile photos first (shortest first), then darks, then grids; each kind in time order.
    let rank = |k: FrameKind| match k {
        FrameKind::Tile => 0,
        FrameKind::Dark => 1,
        FrameKind::Grid => 2,
    };
    photos.sort_by(|a, b| {
        rank(a.kind)
            .cmp(&rank(b.kind))
            .then(a.seconds.total_cmp(&b.seconds))
    });
    let tiles: Vec<&Listed> = photos
        .iter()
        .filter(|p| p.kind == FrameKind::Tile)
        .collect();
    // Several photos at one time are averaged (as a capture's frames_per_exposure); a
    // bracket needs two times at least.
    let distinct = 1 + tiles
        .windows(2)
        .filter(|w| !same_time(w[0].seconds, w[1].seconds))
        .count();
    if tiles.len() < 2 || distinct < 2 {
        let what = match tiles.first() {
            Some(p) if tiles.len() >= 2 => format!(
                "all {} tile photos have the exposure time {} s",
                tiles.len(),
                p.seconds
            ),
            _ => format!("found {} tile photo(s)", tiles.len()),
        };
        return Err(input(format!(
            "a bracket needs tile photos at 2 exposure times at least, about one stop apart: {what}; check {}",
            where_times(times)
        )));
    }
    Ok(mono)
}

/// What the user should know of the bracket: aperture or ISO changing within it, a dark
/// photo at no tile photo's exposure.
fn bracket_warnings(photos: &[Listed], tiles: &[&Listed]) -> Vec<String> {
    let mut warnings = Vec::new();
    // The merge takes only the time to change: a bracket whose aperture or ISO changes
    // scales some photos' radiance by a factor it does not know.
    for (what, vals) in [
        (
            "aperture (EXIF FNumber)",
            tiles
                .iter()
                .filter_map(|p| p.f_number.map(|f| (p, format!("f/{f}"))))
                .collect::<Vec<_>>(),
        ),
        (
            "ISO (EXIF PhotographicSensitivity)",
            tiles
                .iter()
                .filter_map(|p| p.iso.map(|v| (p, format!("ISO {v}"))))
                .collect::<Vec<_>>(),
        ),
    ] {
        if let Some((a, b)) = vals
            .iter()
            .zip(vals.iter().skip(1))
            .find(|(a, b)| a.1 != b.1)
        {
            warnings.push(format!(
                "the {what} changes within the bracket ({} {}, {} {}): the merge takes only the exposure time to change, so the radiance is off by their ratio; shoot the bracket at one aperture and ISO (manual mode)",
                short(&a.0.name),
                a.1,
                short(&b.0.name),
                b.1
            ));
        }
    }
    for d in photos.iter().filter(|p| p.kind == FrameKind::Dark) {
        // Matched as the merge matches them (crate::hdr::merge::dark_levels: within 1%).
        if !tiles
            .iter()
            .any(|t| (d.seconds / t.seconds - 1.0).abs() < 0.01)
        {
            warnings.push(format!(
                "dark photo {} ({} s) is at no tile photo's exposure, so it is not used: a dark photo is subtracted from the tile photos of its exposure",
                short(&d.name),
                d.seconds
            ));
        }
    }
    warnings
}

/// The rig given, checked against the photos and made to describe them (its camera, its
/// bracket as imported).
fn rig_for_photos<'o>(
    opts: &'o ImportOptions,
    photos: &[Listed],
    tiles: &[&Listed],
    first: ImageInfo,
    mono: bool,
) -> Result<Option<(&'o LoadedRig, crate::rig::Rig)>, ImportError> {
    let channels: u8 = if mono { 1 } else { 3 };
    // The rig, checked against the photos and made to describe them.
    Ok(match &opts.rig {
        None => None,
        Some(l) => {
            let mut r = l.rig.clone();
            let c = &r.camera;
            let external = c.backend == CameraBackend::External;
            if !(external && c.width == 0) && (c.width, c.height) != (first.width, first.height) {
                return Err(input(format!(
                    "the rig {} has a {}x{} camera but the photos are {}x{}; give the rig of the camera that took them (or leave camera.width and height out of a processing rig)",
                    l.path.display(),
                    c.width,
                    c.height,
                    first.width,
                    first.height
                )));
            }
            if !(external && c.bit_depth == 0) && c.bit_depth != first.bit_depth {
                return Err(input(format!(
                    "the rig {} has a {}-bit camera but the photos are {}-bit; give the rig of the camera that took them (or leave camera.bit_depth out of a processing rig)",
                    l.path.display(),
                    c.bit_depth,
                    first.bit_depth
                )));
            }
            if !external && r.camera.channels() != channels {
                return Err(input(format!(
                    "the rig {} has a {} camera but the photos are {}; give the rig of the camera that took them, or a processing rig",
                    l.path.display(),
                    if r.camera.channels() == 1 { "monochrome" } else { "colour" },
                    if mono { "grey" } else { "colour" }
                )));
            }
            // A processing rig's camera is what the photos say it is.
            r.camera.pixel_format = match (mono, first.bit_depth) {
                (false, _) if external => None,
                (true, 8) => Some(crate::rig::PixelFormat::GREY),
                (true, _) => Some(crate::rig::PixelFormat::Y16),
                (false, _) => r.camera.pixel_format,
            };
            r.camera.width = first.width;
            r.camera.height = first.height;
            r.camera.bit_depth = first.bit_depth;
            // The bracket as imported: the tile photos' exposures (µs, whole), the grid's.
            let mut us: Vec<u32> = tiles.iter().map(|p| whole_us(p.seconds)).collect();
            us.dedup();
            let per = |k: FrameKind| photos.iter().filter(|p| p.kind == k).count() as u32;
            r.bracket.exposures_us = us;
            r.bracket.frames_per_exposure = r
                .bracket
                .exposures_us
                .iter()
                .map(|&e| tiles.iter().filter(|p| whole_us(p.seconds) == e).count() as u32)
                .max()
                .unwrap_or(1)
                .min(crate::rig::MAX_FRAMES_PER_STEP);
            r.bracket.dark_frames_per_exposure = per(FrameKind::Dark)
                .div_ceil(r.bracket.exposures_us.len() as u32)
                .clamp(1, crate::rig::MAX_FRAMES_PER_STEP);
            r.bracket.grid_frames = per(FrameKind::Grid).clamp(1, crate::rig::MAX_FRAMES_PER_STEP);
            // The grid photo's exposure (without one, the rig's own stays).
            if let Some(p) = photos.iter().find(|p| p.kind == FrameKind::Grid) {
                r.bracket.grid_exposure_us = whole_us(p.seconds);
            }
            if external {
                // Glint set no exposure: the camera's range is the photos'.
                r.camera.min_exposure_us = 0;
                r.camera.max_exposure_us = 0;
            }
            let problems = r.problems();
            if let Some(p) = problems.first() {
                return Err(input(format!(
                    "the rig {} does not fit these photos: {}: {}",
                    l.path.display(),
                    p.key,
                    p.message
                )));
            }
            Some((l, r))
        }
    })
}

/// The temporary folder beside `out` (in `out`'s parent, returned too) that the session
/// is built in, with its `frames` folder.
fn staging_beside(out: &Path) -> Result<(PathBuf, tempfile::TempDir), ImportError> {
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
    Ok((parent, staging))
}

/// Decode each photo (one at a time), check the bracket brightens with its times, and
/// write it as a frame into `staging`: the frames' records.
fn write_frames(
    dir: &Path,
    photos: &[Listed],
    channels: u8,
    max_value: u32,
    times: Option<&Path>,
    staging: &Path,
    now: &str,
) -> Result<Vec<FrameRecord>, ImportError> {
    let from_times = times.is_some();
    let mut frames = Vec::new();
    // The samples of the first tile photo (the shortest time), of the first photo of the
    // last shorter time and of the first photo of the current time.
    let mut shortest: Option<(usize, Vec<u16>)> = None;
    let mut previous: Option<(usize, Vec<u16>)> = None;
    let mut current: Option<(usize, Vec<u16>)> = None;
    // A photo exposed half a stop or more longer than the one before it in the bracket
    // that is no brighter than it: the photos do not change with their times.
    let unchanged_error = |q: &Listed, p: &Listed, before: &[u16], values: &[u16], rise: f64| {
        let (a, b, n) = no_brighter(before, values, p.seconds / q.seconds, max_value, rise)?;
        let expected = if rise > 0.0 {
            format!("at least {:.0}% more is expected", 100.0 * rise)
        } else {
            "some rise is expected".to_string()
        };
        Some(input(format!(
            "{} ({} s) is no brighter than {} ({} s) although exposed {:.1}x longer (mean level {b:.1} against {a:.1} over the {n} sampled pixel values black or saturated in neither; {expected}): the photos do not change with their exposure times; a bracket is one scene photographed at several times with the aperture and ISO fixed (manual mode), so check the photos and {}",
            short(&p.name),
            p.seconds,
            short(&q.name),
            q.seconds,
            p.seconds / q.seconds,
            where_times(times)
        )))
    };
    for (i, p) in photos.iter().enumerate() {
        // One photo decoded at a time; its pixels are dropped at the end of the loop.
        let bytes = read_photo(&p.path, dir, from_times)?;
        let shown = shown(&p.path);
        let (width, height, bits, pixels) =
            crate::hdr::decode_as(&bytes, &shown, channels as usize)?;
        drop(bytes);
        if (width as u32, height as u32, bits) != (p.info.width, p.info.height, p.info.bit_depth) {
            return Err(input(format!(
                "{shown}: changed while being imported (now {width}x{height} {bits}-bit); import again"
            )));
        }
        if p.kind == FrameKind::Tile {
            let values = sample_values(width, height, channels as usize, &pixels);
            // Compared with the first photo of the last shorter time (photos of one time
            // are repeats, averaged).
            if current
                .as_ref()
                .is_some_and(|(j, _)| !same_time(photos[*j].seconds, p.seconds))
            {
                previous = current.take();
            }
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
                        where_times(times)
                    )));
                }
                if let Some(e) = unchanged_error(q, p, before, &values, 0.0) {
                    return Err(e);
                }
            }
            if shortest.is_none() {
                shortest = Some((i, values.clone()));
            }
            if current.is_none() {
                current = Some((i, values));
            }
        }
        let png = encode_png(width as u32, height as u32, &pixels)
            .map_err(|e| input(format!("{shown}: {e}")))?;
        drop(pixels);
        let us = p.seconds * 1e6;
        let rounded = whole_us(p.seconds);
        let file = format!("frames/{i:04}-{}-{}.png", p.kind.as_str(), stem_of(&p.name));
        write_new(&staging.join(&file), &png)?;
        frames.push(FrameRecord {
            index: i as u32,
            file,
            kind: p.kind,
            exposure_requested_us: rounded,
            exposure_reported_us: rounded,
            exposure_exact_us: (us != rounded as f64).then_some(us),
            exposure_verified_by: Verification::Imported,
            timestamp: now.to_string(),
            device_timestamp_us: None,
            sequence: i as u64,
            // Unknown: Glint did not switch it (recorded as off, as for every import).
            lamp: LampState::OFF,
            width: width as u32,
            height: height as u32,
            bit_depth: bits,
            sha256: sha256_hex(&png),
            f_number: p.f_number,
            iso: p.iso,
        });
    }
    // And across the whole bracket (steps of less than half a stop are not compared one
    // by one): the first photo of the longest time against the shortest.
    if let (Some((j, first)), Some((k, last))) = (&shortest, &current) {
        if let Some(e) = unchanged_error(&photos[*j], &photos[*k], first, last, MIN_RISE) {
            return Err(e);
        }
    }
    Ok(frames)
}

/// Import the photos of `dir` into a new session at `out`.
pub fn import(dir: &Path, opts: &ImportOptions, out: &Path) -> Result<ImportReport, ImportError> {
    if !dir.is_dir() {
        return Err(input(format!(
            "{} is not a folder of photos",
            dir.display()
        )));
    }
    check_out(out)?;
    let times = opts.times.as_deref();
    let listed = list_photos(dir, opts)?;
    // First every photo's header and time, one file at a time: a bad photo (wrong size,
    // too large, not an image) is found before anything is decoded.
    let (mut photos, camera_model) = read_headers(dir, &listed, times.is_some())?;
    let mono = sort_and_check(&mut photos, times)?;
    let channels: u8 = if mono { 1 } else { 3 };
    let tiles: Vec<&Listed> = photos
        .iter()
        .filter(|p| p.kind == FrameKind::Tile)
        .collect();
    let warnings = bracket_warnings(&photos, &tiles);
    let first = photos[0].info;
    let max_value = (1u32 << first.bit_depth) - 1;
    let rig = rig_for_photos(opts, &photos, &tiles, first, mono)?;

    // Then the session, built in a temporary folder beside `out` and renamed into place
    // once complete: nothing appears at `out` unless every photo is good, and a failure
    // leaves nothing behind (the folder is removed when `staging` is dropped).
    let (parent, staging) = staging_beside(out)?;
    let now = session::timestamp(SystemTime::now());
    let frames = write_frames(
        dir,
        &photos,
        channels,
        max_value,
        times,
        staging.path(),
        &now,
    )?;
    if let Some((l, _)) = &rig {
        write_new(&staging.path().join("rig.toml"), l.text.as_bytes())?;
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
        rig_file: rig
            .as_ref()
            .map(|(l, _)| l.path.display().to_string())
            .unwrap_or_default(),
        rig: rig.as_ref().map(|(_, r)| r.clone()),
        camera: Some(CameraInfo::basic(
            camera_model.as_deref().unwrap_or("imported"),
            first.width,
            first.height,
            first.bit_depth,
            channels,
        )),
        lamp_identity: None,
        plan: Plan::default(),
        imported_from: Some(dir.display().to_string()),
        lamp_off_confirmed: None,
        frames,
    };
    // The bounds every stage holds a manifest to (frames of a kind at one time, exposures):
    // a session they would refuse is not made.
    if let Some(p) = session::count_problems(&manifest).into_iter().next() {
        return Err(input(format!(
            "{p}; import fewer photos (nothing was written)"
        )));
    }
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
    let count = |k: FrameKind| photos.iter().filter(|p| p.kind == k).count();
    Ok(ImportReport {
        session: out.into(),
        frames: photos.len(),
        width: first.width,
        height: first.height,
        bit_depth: first.bit_depth,
        exposures_s: tiles.iter().map(|p| (p.name.clone(), p.seconds)).collect(),
        grid: count(FrameKind::Grid),
        dark: count(FrameKind::Dark),
        rig: rig.as_ref().map(|(l, _)| l.path.clone()),
        warnings,
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
    fn times_file_kinds_default_to_tile_and_unknown_ones_name_the_line() {
        let t = parse_times_with_kinds(
            Path::new("t.txt"),
            "a.png 1/250\nb.png 1/60 DARK # capped\nc.png 0.01 grid\n",
        )
        .unwrap();
        let kinds: Vec<FrameKind> = t.iter().map(|x| x.2).collect();
        assert_eq!(kinds, [FrameKind::Tile, FrameKind::Dark, FrameKind::Grid]);
        let e = parse_times_with_kinds(Path::new("t.txt"), "a.png 1/250\nb.png 1/60 board\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("t.txt:2: `board` is not a kind of photo"),
            "{e}"
        );
        let e = parse_times_with_kinds(Path::new("t.txt"), "a.png 1/250 tile extra\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("t.txt:1: expected `<file name> <exposure time"),
            "{e}"
        );
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

    #[test]
    fn a_longer_photo_must_be_brighter_where_it_is_clipped_in_neither() {
        let ramp: Vec<u16> = (0..3000).map(|i| (i % 256) as u16).collect();
        // The same photo twice: refused from half a stop apart, not closer.
        let (a, b, n) = no_brighter(&ramp, &ramp, 2.0, 255, 0.0).unwrap();
        assert_eq!(a, b);
        assert!(n > 2500, "{n}");
        assert_eq!(no_brighter(&ramp, &ramp, 1.3, 255, MIN_RISE), None);
        // Twice as long, linear and clipped, or through a gamma of 2.2: brighter.
        let double: Vec<u16> = ramp.iter().map(|v| (v * 2).min(255)).collect();
        assert_eq!(no_brighter(&ramp, &double, 2.0, 255, MIN_RISE), None);
        let gamma: Vec<u16> = ramp
            .iter()
            .map(|&v| (255.0 * (v as f64 / 255.0 * 2f64.sqrt()).min(1.0).powf(1.0 / 2.2)) as u16)
            .collect();
        assert_eq!(no_brighter(&ramp, &gamma, 2f64.sqrt(), 255, MIN_RISE), None);
        // 1% brighter is within what repeats of one exposure differ by: refused across a
        // whole bracket, not between neighbours (the dark end of a real bracket).
        let same: Vec<u16> = ramp.iter().map(|v| v + (v % 100 == 0) as u16).collect();
        assert!(no_brighter(&ramp, &same, 4.0, 255, MIN_RISE).is_some());
        assert_eq!(no_brighter(&ramp, &same, 2.0, 255, 0.0), None);
        // Black or saturated in both: nothing to tell.
        assert_eq!(
            no_brighter(&[255; 300], &[255; 300], 8.0, 255, MIN_RISE),
            None
        );
        assert_eq!(no_brighter(&[0; 300], &[1; 300], 8.0, 255, MIN_RISE), None);
    }
}
