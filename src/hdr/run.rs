//! The HDR stage on a session: `glint response SESSION` and `glint hdr SESSION`.
//!
//! The response belongs to the camera, so it is kept in a camera profile beside the rig
//! file (`<rig folder>/profiles/<camera>-<bits>bit.response.json`) and reused by every
//! later session of that camera. `glint hdr` takes, in order: a response file given with
//! `--response`, the camera's profile, or a response recovered from the session itself
//! (which then becomes the profile, if there is none yet). A profile is never replaced
//! unless asked (`glint response --replace-profile`).

use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;

use super::files;
use super::merge::{self, Merged};
use super::response::{self, RecoverOptions, Response};
use super::HdrError;
use crate::session::{self, Manifest};

/// Options of `glint hdr`.
#[derive(Debug, Clone, Default)]
pub struct HdrOptions {
    /// Use this response file.
    pub response_file: Option<PathBuf>,
    /// Recover the response from this session even if a profile exists.
    pub recover: bool,
    pub recover_options: RecoverOptions,
    /// Use this profile file instead of the one beside the rig.
    pub profile: Option<PathBuf>,
}

/// Progress of the stage.
#[derive(Debug, Clone)]
pub enum HdrEvent {
    /// Reading frames.
    Loading { frames: usize },
    /// Recovering the response.
    Recovering,
    /// Merging.
    Merging { frames: usize, megapixels: f64 },
    /// Writing files.
    Writing,
}

/// Where the response came from.
#[derive(Debug, Clone, Serialize)]
#[serde(rename_all = "kebab-case", tag = "kind", content = "path")]
pub enum ResponseSource {
    File(String),
    Profile(String),
    Recovered,
}

/// Summary of `glint hdr` (also `hdr/summary.json`).
#[derive(Debug, Clone, Serialize)]
pub struct HdrSummary {
    pub session: String,
    pub response: ResponseSource,
    pub model: String,
    /// The profile written (a newly recovered response), if any.
    pub profile_written: Option<String>,
    pub width: usize,
    pub height: usize,
    pub bit_depth: u8,
    pub exposures_us: Vec<f64>,
    pub dark_frames: usize,
    /// Samples (pixel x channel) with radiance, saturated in every frame, too dark in every frame.
    pub samples_measured: usize,
    pub samples_saturated: usize,
    pub samples_too_dark: usize,
    /// Range of measured radiance (exposure units per second).
    pub radiance_min: f64,
    pub radiance_max: f64,
    /// Median relative standard deviation of the measured radiance.
    pub median_relative_sd: f64,
    pub warnings: Vec<String>,
    pub files: Vec<String>,
    pub seconds: f64,
}

/// The camera profile file for a session: beside the rig file it was captured with.
pub fn profile_path(m: &Manifest) -> Option<PathBuf> {
    if m.rig_file.is_empty() {
        return None;
    }
    let camera = m.camera.as_ref()?;
    profile_path_for(Path::new(&m.rig_file), &camera.model, camera.bit_depth)
}

/// The profile of camera `model` at `bit_depth` for the rig file `rig`:
/// `<rig folder>/profiles/<model>-<bits>bit.response.json`.
pub fn profile_path_for(rig: &Path, model: &str, bit_depth: u8) -> Option<PathBuf> {
    let dir = rig
        .parent()
        .filter(|d| d.as_os_str().is_empty() || d.is_dir())?;
    let name: String = model
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '-'
            }
        })
        .collect();
    Some(
        dir.join("profiles")
            .join(format!("{name}-{bit_depth}bit.response.json")),
    )
}

/// Recover the response of a session's camera from its tile frames; written to the
/// session's `hdr/` (JSON, CSV, SVG).
pub fn recover_session(
    dir: &Path,
    opts: &RecoverOptions,
    on_event: &mut dyn FnMut(HdrEvent),
) -> Result<Response, HdrError> {
    let m = session::load(dir)?;
    on_event(HdrEvent::Loading {
        frames: m.frames.len(),
    });
    let (tiles, darks) = super::load_session(dir, &m)?;
    on_event(HdrEvent::Recovering);
    let r = recover_from(dir, &m, &tiles, &darks, opts)?;
    files::write_response(&dir.join("hdr"), &r)?;
    Ok(r)
}

/// Recover a response from a session's brackets, labelled with its camera and session.
fn recover_from(
    dir: &Path,
    m: &Manifest,
    tiles: &super::Bracket,
    darks: &super::Bracket,
    opts: &RecoverOptions,
) -> Result<Response, HdrError> {
    let mut r = response::recover(tiles, darks, opts)?;
    r.camera = m.camera.as_ref().map(|c| c.model.clone());
    r.recovered_from = dir.display().to_string();
    Ok(r)
}

/// Store a response as the camera's profile. Refuses to replace an existing profile
/// unless `replace`; returns whether it wrote.
pub fn store_profile(path: &Path, r: &Response, replace: bool) -> Result<bool, HdrError> {
    if path.exists() && !replace {
        return Ok(false);
    }
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent).map_err(|e| HdrError::File {
            path: parent.into(),
            reason: e.to_string(),
        })?;
    }
    files::save_response(path, r)?;
    Ok(true)
}

/// The response `glint hdr` takes for a session without recovering one: a file given with
/// `--response`, else the camera's profile (`opts.profile`, else `profile`: the one beside
/// the rig), unless `opts.recover`. None: recover one.
pub fn known_response(
    opts: &HdrOptions,
    profile: Option<PathBuf>,
    bit_depth: u8,
) -> Result<Option<(Response, ResponseSource)>, HdrError> {
    if let Some(f) = &opts.response_file {
        return Ok(Some((
            files::load_response(f)?,
            ResponseSource::File(f.display().to_string()),
        )));
    }
    let profile = opts.profile.clone().or(profile);
    let Some(p) = profile.as_ref().filter(|p| p.exists() && !opts.recover) else {
        return Ok(None);
    };
    let r = files::load_response(p)?;
    if r.bit_depth != bit_depth {
        return Err(HdrError::Input(format!(
            "the camera profile {} is for {}-bit frames but the session's are {bit_depth}-bit; recover one with glint response",
            p.display(),
            r.bit_depth,
        )));
    }
    Ok(Some((r, ResponseSource::Profile(p.display().to_string()))))
}

/// `glint hdr SESSION`: response (file, profile or recovered), merge, files.
pub fn run(
    dir: &Path,
    opts: &HdrOptions,
    on_event: &mut dyn FnMut(HdrEvent),
) -> Result<(HdrSummary, Merged), HdrError> {
    let start = Instant::now();
    let m = session::load(dir)?;
    on_event(HdrEvent::Loading {
        frames: m.frames.len(),
    });
    let (tiles, darks) = super::load_session(dir, &m)?;
    let mut profile_written = None;
    let (r, source) = match known_response(opts, profile_path(&m), tiles.bit_depth)? {
        Some(known) => known,
        None => {
            on_event(HdrEvent::Recovering);
            let r = recover_from(dir, &m, &tiles, &darks, &opts.recover_options)?;
            if let Some(p) = opts.profile.clone().or_else(|| profile_path(&m)) {
                if store_profile(&p, &r, false)? {
                    profile_written = Some(p.display().to_string());
                }
            }
            (r, ResponseSource::Recovered)
        }
    };
    on_event(HdrEvent::Merging {
        frames: tiles.frames.len(),
        megapixels: (tiles.width * tiles.height) as f64 * 1e-6,
    });
    let dark = merge::dark_levels(&r, &tiles, &darks);
    let merged = merge::merge(&r, &tiles, &dark)?;
    on_event(HdrEvent::Writing);
    let summary = write_outputs(
        dir,
        &r,
        source,
        profile_written,
        &tiles,
        darks.frames.len(),
        &merged,
        start,
    )?;
    Ok((summary, merged))
}

/// Write a merge's files (`hdr/`) and its summary; `tiles` gives the bracket's size and
/// exposures (its frames are not read again).
#[allow(clippy::too_many_arguments)]
pub fn write_outputs(
    dir: &Path,
    r: &Response,
    source: ResponseSource,
    profile_written: Option<String>,
    tiles: &super::Bracket,
    dark_frames: usize,
    merged: &Merged,
    start: Instant,
) -> Result<HdrSummary, HdrError> {
    let out = dir.join("hdr");
    files::write_merged(&out, merged)?;
    files::write_response(&out, r)?;
    let [ok, sat, too_dark] = merged.counts();
    let mut lo = f64::INFINITY;
    let mut hi = f64::NEG_INFINITY;
    let mut rel: Vec<f32> = Vec::with_capacity(ok);
    for (x, v) in merged.radiance.iter().zip(&merged.variance) {
        if x.is_finite() {
            lo = lo.min(*x as f64);
            hi = hi.max(*x as f64);
            if *x > 0.0 {
                rel.push(v.sqrt() / x);
            }
        }
    }
    let median = if rel.is_empty() {
        f64::NAN
    } else {
        let k = rel.len() / 2;
        *rel.select_nth_unstable_by(k, |a, b| a.total_cmp(b)).1 as f64
    };
    let mut warnings = r.warnings.clone();
    if sat > 0 {
        warnings.push(format!(
            "{sat} samples ({:.2}%) are saturated even in the shortest exposure ({} µs): they have no radiance (mask.png); add a shorter exposure to measure them",
            100.0 * sat as f64 / merged.mask.len() as f64,
            tiles.frames[0].exposure_us
        ));
    }
    let summary = HdrSummary {
        session: dir.display().to_string(),
        response: source,
        model: r.model.as_str().into(),
        profile_written,
        width: tiles.width,
        height: tiles.height,
        bit_depth: tiles.bit_depth,
        exposures_us: tiles.frames.iter().map(|f| f.exposure_us).collect(),
        dark_frames,
        samples_measured: ok,
        samples_saturated: sat,
        samples_too_dark: too_dark,
        radiance_min: if lo.is_finite() { lo } else { f64::NAN },
        radiance_max: if hi.is_finite() { hi } else { f64::NAN },
        median_relative_sd: median,
        warnings,
        files: [
            "radiance.exr",
            "variance.exr",
            "mask.png",
            "response.json",
            "response.csv",
            "response.svg",
            "summary.json",
        ]
        .iter()
        .map(|f| format!("hdr/{f}"))
        .collect(),
        seconds: start.elapsed().as_secs_f64(),
    };
    let json = serde_json::to_vec_pretty(&summary).expect("summary serialises");
    session::write_replace(&out.join("summary.json"), &json)?;
    Ok(summary)
}
