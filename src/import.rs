//! `glint import`: a folder of bracketed photos from any camera -> a Glint session.
//!
//! Exposure times come from a times file (one line per photo: `<file name> <seconds>`, the
//! time as a decimal `0.004` or a fraction `1/250`; `#` starts a comment) or, where a photo
//! carries EXIF data, from its ExposureTime tag. Everything is checked before anything is
//! written: every photo decodes, all have one size and bit depth, every time is positive
//! and no two photos share a time. Only then is the session created (in a new or empty
//! folder); its frames are lossless PNG copies of the decoded photos, all of kind `tile`.

use std::collections::HashSet;
use std::fs;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

use crate::capture::{FrameKind, Plan, Verification};
use crate::devices::{CameraInfo, LampState, Pixels};
use crate::hdr::decode;
use crate::session::{
    self, encode_png, sha256_hex, write_new, FrameRecord, Manifest, Software, State,
};

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

/// Parse an exposure time in seconds: `0.004`, `4e-3` or `1/250`.
pub fn parse_time(s: &str) -> Option<f64> {
    let v = match s.split_once('/') {
        Some((a, b)) => a.trim().parse::<f64>().ok()? / b.trim().parse::<f64>().ok()?,
        None => s.trim().parse::<f64>().ok()?,
    };
    Some(v)
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
                "{at}: expected `<file name> <exposure time in seconds>`, got `{line}`"
            )));
        };
        let t = parse_time(time).ok_or_else(|| {
            input(format!(
                "{at}: `{time}` is not a time; write seconds as a decimal (0.004) or a fraction (1/250)"
            ))
        })?;
        if !(t.is_finite() && t > 0.0) {
            return Err(input(format!(
                "{at}: the exposure time of {name} is {time}; it must be positive"
            )));
        }
        if !names.insert(name.to_string()) {
            return Err(input(format!("{at}: {name} is listed twice")));
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

/// Import the photos of `dir` into a new session at `out`.
pub fn import(dir: &Path, times: Option<&Path>, out: &Path) -> Result<ImportReport, ImportError> {
    if !dir.is_dir() {
        return Err(input(format!(
            "{} is not a folder of photos",
            dir.display()
        )));
    }
    // The photos and their times.
    let listed: Vec<(String, Option<f64>)> = match times {
        Some(tf) => {
            let text = fs::read_to_string(tf)
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
    // Decode everything first: nothing is written unless all photos are good.
    struct Photo {
        name: String,
        seconds: f64,
        width: usize,
        height: usize,
        bits: u8,
        pixels: Pixels,
    }
    let mut photos: Vec<Photo> = Vec::new();
    for (name, t) in &listed {
        let path = dir.join(name);
        let bytes = fs::read(&path).map_err(|e| {
            input(format!(
                "{}: cannot read ({e}); the times file lists a photo that is not in {}",
                path.display(),
                dir.display()
            ))
        })?;
        let seconds = match t {
            Some(t) => *t,
            None => exif_exposure(&bytes).ok_or_else(|| {
                input(format!(
                    "{}: no EXIF exposure time; give the times with --times FILE (`<file name> <seconds>` per line)",
                    path.display()
                ))
            })?,
        };
        if !(seconds.is_finite() && seconds > 0.0) {
            return Err(input(format!(
                "{}: exposure time {seconds} s is not positive",
                path.display()
            )));
        }
        let (width, height, bits, pixels) =
            decode(&bytes, &path.display().to_string()).map_err(|e| input(e.to_string()))?;
        if let Some(first) = photos.first() {
            if (width, height) != (first.width, first.height) {
                return Err(input(format!(
                    "{name} is {width}x{height} but {} is {}x{}; all photos of a bracket must have one size",
                    first.name, first.width, first.height
                )));
            }
            if bits != first.bits {
                return Err(input(format!(
                    "{name} is {bits}-bit but {} is {}-bit; all photos of a bracket must have one bit depth",
                    first.name, first.bits
                )));
            }
        }
        photos.push(Photo {
            name: name.clone(),
            seconds,
            width,
            height,
            bits,
            pixels,
        });
    }
    photos.sort_by(|a, b| a.seconds.total_cmp(&b.seconds));
    for w in photos.windows(2) {
        if (w[1].seconds / w[0].seconds - 1.0).abs() < 1e-9 {
            return Err(input(format!(
                "{} and {} have the same exposure time ({} s); a bracket needs distinct times",
                w[0].name, w[1].name, w[0].seconds
            )));
        }
    }
    if photos.len() < 2 {
        return Err(input(format!(
            "a bracket needs at least 2 photos, found {}",
            photos.len()
        )));
    }
    // Encode before creating anything.
    let mut encoded = Vec::new();
    for p in &photos {
        let png = encode_png(p.width as u32, p.height as u32, &p.pixels)
            .map_err(|e| input(format!("{}: {e}", p.name)))?;
        encoded.push(png);
    }
    // Write.
    if out.exists() {
        let empty = fs::read_dir(out)
            .map_err(|e| input(format!("cannot read {} ({e})", out.display())))?
            .next()
            .is_none();
        if !empty {
            return Err(session::SessionError::Exists { path: out.into() }.into());
        }
    }
    fs::create_dir_all(out.join("frames"))
        .map_err(|e| input(format!("cannot create {} ({e})", out.display())))?;
    let now = session::timestamp(SystemTime::now());
    let first = &photos[0];
    let mut frames = Vec::new();
    for (i, (p, png)) in photos.iter().zip(&encoded).enumerate() {
        let us = p.seconds * 1e6;
        let rounded = us.round().clamp(1.0, u32::MAX as f64) as u32;
        let stem: String = p
            .name
            .rsplit_once('.')
            .map(|(s, _)| s)
            .unwrap_or(&p.name)
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                    c
                } else {
                    '_'
                }
            })
            .collect();
        let file = format!("frames/{i:04}-tile-{stem}.png");
        write_new(&out.join(&file), png)?;
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
            width: p.width as u32,
            height: p.height as u32,
            bit_depth: p.bits,
            sha256: sha256_hex(png),
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
        camera: Some(CameraInfo {
            model: "imported".into(),
            width: first.width as u32,
            height: first.height as u32,
            bit_depth: first.bits,
        }),
        lamp_identity: None,
        plan: Plan::default(),
        imported_from: Some(dir.display().to_string()),
        lamp_off_confirmed: None,
        frames,
    };
    let json = serde_json::to_vec_pretty(&manifest).expect("manifest serialises");
    write_new(&out.join("manifest.json"), &json)?;
    Ok(ImportReport {
        session: out.into(),
        frames: photos.len(),
        width: first.width as u32,
        height: first.height as u32,
        bit_depth: first.bits,
        exposures_s: photos.iter().map(|p| (p.name.clone(), p.seconds)).collect(),
    })
}
