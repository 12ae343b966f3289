//! The HDR stage on a session: `glint response SESSION` and `glint hdr SESSION`.
//!
//! The response belongs to the camera, so it is kept in a camera profile beside the user's
//! rig file (`<rig folder>/profiles/<camera>-<bits>bit.response.json`, or
//! `<camera>-<bits>bit-mono.response.json` for a monochrome camera, the rig given with
//! `--rig`, or `glint run`'s) or in a file given with `--profile`, and reused by every
//! later session of that camera. Never where the session's manifest says its rig was: a
//! session is data, and data does not choose where Glint writes. `glint hdr` takes, in
//! order: a response file given with `--response`, the camera's profile, or a response
//! recovered from the session itself, which becomes the profile only if there is none yet,
//! the session is complete and it passes [`profile_quality`]. A profile is never replaced
//! unless asked (`glint response --replace-profile`, which refuses a session that fails
//! those checks).

use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;

use super::files;
use super::merge::{self, Merged};
use super::response::{self, RecoverOptions, Response};
use super::{Bracket, HdrError, SessionFrames};
use crate::session::{self, Manifest, State};

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
    /// The user's rig file: the camera profile is the one beside it.
    pub rig: Option<PathBuf>,
    /// Work on a session that is not complete (with a warning); no profile is stored.
    pub allow_incomplete: bool,
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

impl std::fmt::Display for HdrEvent {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            HdrEvent::Loading { frames } => write!(f, "reading and checking {frames} frames"),
            HdrEvent::Recovering => f.write_str("recovering the camera response"),
            HdrEvent::Merging { frames, megapixels } => {
                write!(f, "merging {frames} exposures of {megapixels:.1} MP")
            }
            HdrEvent::Writing => f.write_str("writing hdr/"),
        }
    }
}

/// Where the response came from.
#[derive(Debug, Clone, Serialize)]
#[serde(rename_all = "kebab-case", tag = "kind", content = "path")]
pub enum ResponseSource {
    File(String),
    Profile(String),
    Recovered,
}

/// Summary of `glint hdr`, in memory; `hdr/summary.json` is its [`HdrSummary::file`],
/// written through glint-format's type, the one every reader uses.
#[derive(Debug, Clone, Serialize)]
pub struct HdrSummary {
    pub session: String,
    /// The session's state (`complete` unless run with --allow-incomplete).
    pub state: State,
    pub response: ResponseSource,
    pub model: String,
    /// The profile written (a newly recovered response), if any.
    pub profile_written: Option<String>,
    pub width: usize,
    pub height: usize,
    pub bit_depth: u8,
    /// Channels of the frames and of radiance.exr: 3 (R, G, B) or 1 (Y, a monochrome
    /// camera).
    pub channels: usize,
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
    /// Things to know that are not a problem with the result (how to keep a profile).
    #[serde(default)]
    pub notes: Vec<String>,
    pub files: Vec<String>,
    pub seconds: f64,
}

impl ResponseSource {
    /// As `hdr/summary.json` holds it.
    pub fn file(&self) -> glint_format::stage::hdr::ResponseSource {
        let (kind, path) = match self {
            ResponseSource::File(p) => ("file", Some(p.clone())),
            ResponseSource::Profile(p) => ("profile", Some(p.clone())),
            ResponseSource::Recovered => ("recovered", None),
        };
        glint_format::stage::hdr::ResponseSource {
            kind: Some(kind.into()),
            path,
        }
    }
}

impl HdrSummary {
    /// `hdr/summary.json`: this summary as the file's type holds it.
    pub fn file(&self) -> glint_format::stage::hdr::Summary {
        let count = |n: usize| Some(n as u64);
        glint_format::stage::hdr::Summary {
            session: Some(self.session.clone()),
            state: Some(self.state.as_str().into()),
            response: self.response.file(),
            model: Some(self.model.clone()),
            profile_written: self.profile_written.clone(),
            width: count(self.width),
            height: count(self.height),
            bit_depth: Some(u64::from(self.bit_depth)),
            channels: count(self.channels),
            exposures_us: Some(self.exposures_us.iter().map(|e| Some(*e)).collect()),
            dark_frames: count(self.dark_frames),
            samples_measured: count(self.samples_measured),
            samples_saturated: count(self.samples_saturated),
            samples_too_dark: count(self.samples_too_dark),
            radiance_min: Some(self.radiance_min),
            radiance_max: Some(self.radiance_max),
            median_relative_sd: Some(self.median_relative_sd),
            warnings: self.warnings.clone(),
            notes: self.notes.clone(),
            files: self.files.clone(),
            seconds: Some(self.seconds),
        }
    }
}

/// The profile of camera `model` at `bit_depth` with `channels` (3: RGB, 1: monochrome)
/// for the rig file `rig`: `<rig folder>/profiles/<model>-<bits>bit.response.json`, or
/// `<model>-<bits>bit-mono.response.json` for a monochrome camera, so that one camera's
/// RGB and monochrome modes never share a profile (the model's characters other than
/// letters, digits, `-` and `_` become `-`, at most 100 of them).
pub fn profile_path_for(rig: &Path, camera: &crate::devices::CameraInfo) -> Option<PathBuf> {
    let (bit_depth, channels) = (camera.bit_depth, camera.channels);
    // A colour camera's formats go through different processing in the camera (YUYV, RGB3,
    // MJPG), so each has its own response; the luma formats are told apart by depth.
    let model = match (&camera.pixel_format, channels) {
        (Some(f), 3) => format!("{}-{f}", camera.model),
        _ => camera.model.clone(),
    };
    crate::rig::profile_file(
        rig,
        &model,
        &format!(
            "-{bit_depth}bit{}.response.json",
            if channels == 1 { "-mono" } else { "" }
        ),
    )
}

/// Where a session's camera profile is: `profile` if given, else beside the user's rig
/// file `rig` (which must be a rig file, for the session's camera); None without either.
/// The manifest's `rig_file` is never used.
pub fn profile_place(
    profile: Option<&Path>,
    rig: Option<&Path>,
    m: &Manifest,
) -> Result<Option<PathBuf>, HdrError> {
    if let Some(p) = profile {
        return Ok(Some(p.into()));
    }
    let Some(rig) = rig else {
        return Ok(None);
    };
    let loaded = crate::rig::load(rig).map_err(|e| HdrError::Input(format!("--rig: {e}")))?;
    let Some(camera) = m.camera.as_ref() else {
        return Ok(None);
    };
    let c = &loaded.rig.camera;
    // A processing rig may leave its camera's depth to the photos (0).
    let any_depth = c.backend == crate::rig::CameraBackend::External && c.bit_depth == 0;
    if !any_depth && c.bit_depth != camera.bit_depth {
        return Err(HdrError::Input(format!(
            "--rig {}: its camera is {}-bit but the session's is {}-bit; give the rig file the session was captured with",
            rig.display(),
            c.bit_depth,
            camera.bit_depth
        )));
    }
    Ok(profile_path_for(rig, camera))
}

/// Why a recovered response may not become the camera's profile ([`profile_quality`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NotAProfile {
    #[error("the session is not complete (state {state})")]
    Incomplete { state: String },
    #[error("the bracket has {count} different exposure(s); a profile needs at least {PROFILE_MIN_EXPOSURES}")]
    FewExposures { count: usize },
    #[error("only {percent:.1}% of the {channel} readings are in the response's valid range {valid_min}..{valid_max} (the bracket is nearly all dark or all saturated)")]
    FewValid {
        channel: String,
        percent: f64,
        valid_min: u32,
        valid_max: u32,
    },
    #[error("only {useful} exposure(s) have {channel} readings in the response's valid range; a profile needs at least {PROFILE_MIN_EXPOSURES}")]
    FewUseful { useful: usize, channel: String },
}

/// Exposures a bracket needs before its response may become a camera profile.
pub const PROFILE_MIN_EXPOSURES: usize = 3;

/// Whether a response recovered from a session may become the camera's profile, which
/// every later session of the camera is merged with: the session complete, at least
/// [`PROFILE_MIN_EXPOSURES`] different exposures, and in every channel at least that many
/// exposures where at least 1% of the readings are in the response's valid range, with
/// at least 10% of all readings valid (a bracket all dark or all saturated says nothing
/// about the curve). The error says why not.
pub fn profile_quality(m: &Manifest, tiles: &Bracket, r: &Response) -> Result<(), NotAProfile> {
    if m.state != State::Complete {
        return Err(NotAProfile::Incomplete {
            state: serde_json::to_value(m.state)
                .ok()
                .and_then(|v| v.as_str().map(String::from))
                .unwrap_or_default(),
        });
    }
    let mut times: Vec<f64> = tiles.frames.iter().map(|f| f.exposure_us).collect();
    times.sort_by(|a, b| a.total_cmp(b));
    times.dedup_by(|a, b| (*a / *b - 1.0).abs() < 1e-6);
    if times.len() < PROFILE_MIN_EXPOSURES {
        return Err(NotAProfile::FewExposures { count: times.len() });
    }
    let n = tiles.width * tiles.height;
    let step = (n / 200_000).max(1);
    for (c, ch) in r.channels.iter().enumerate().take(3) {
        let mut useful = 0;
        let (mut valid, mut total) = (0usize, 0usize);
        for j in 0..tiles.frames.len() {
            let (mut v, mut t) = (0usize, 0usize);
            for p in (0..n).step_by(step) {
                let z = tiles.value(j, p, c);
                t += 1;
                if z >= ch.valid_min && z <= ch.valid_max {
                    v += 1;
                }
            }
            if v * 100 >= t && v > 0 {
                useful += 1;
            }
            valid += v;
            total += t;
        }
        let name = r.channel_name(c);
        if valid * 10 < total {
            return Err(NotAProfile::FewValid {
                channel: name.to_string(),
                percent: 100.0 * valid as f64 / total.max(1) as f64,
                valid_min: ch.valid_min,
                valid_max: ch.valid_max,
            });
        }
        if useful < PROFILE_MIN_EXPOSURES {
            return Err(NotAProfile::FewUseful {
                useful,
                channel: name.to_string(),
            });
        }
    }
    Ok(())
}

/// Recover a response from a session's brackets, labelled with its camera and session.
fn recover_from(
    dir: &Path,
    m: &Manifest,
    tiles: &super::Bracket,
    darks: &[super::DarkMedian],
    opts: &RecoverOptions,
) -> Result<Response, HdrError> {
    let mut r = response::recover_with(tiles, darks, opts)?;
    r.camera = m.camera.as_ref().map(|c| c.model.clone());
    r.recovered_from = dir.display().to_string();
    Ok(r)
}

/// Store a response as the camera's profile. Refuses to replace an existing profile
/// unless `replace`; returns whether it wrote.
pub fn store_profile(path: &Path, r: &Response, replace: bool) -> Result<bool, HdrError> {
    if path.symlink_metadata().is_ok() && !replace {
        return Ok(false);
    }
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        // A real folder (created if missing), never a link: nothing is written through one.
        crate::fsx::ensure_dir(parent).map_err(|e| HdrError::File {
            path: parent.into(),
            reason: e.to_string(),
        })?;
    }
    files::save_response(path, r)?;
    Ok(true)
}

/// Options of `glint response`.
#[derive(Debug, Clone, Default)]
pub struct ResponseOptions {
    pub recover_options: RecoverOptions,
    /// Store the profile in this file.
    pub profile: Option<PathBuf>,
    /// The user's rig file: the profile is the one beside it.
    pub rig: Option<PathBuf>,
    /// Replace an existing profile (the session must pass [`profile_quality`]).
    pub replace_profile: bool,
    pub allow_incomplete: bool,
}

/// What became of the camera profile in `glint response`.
#[derive(Debug, Clone, Serialize)]
#[serde(rename_all = "kebab-case", tag = "kind", content = "detail")]
pub enum ProfileStored {
    /// Written (new, or replaced as asked).
    Written(PathBuf),
    /// A profile exists and was kept.
    Kept(PathBuf),
    /// Not stored: the session fails the profile checks (why).
    Refused { path: PathBuf, why: String },
    /// No --rig and no --profile: nowhere to store one.
    Nowhere,
}

/// `glint response SESSION`: the session's response, written to its `hdr/`
/// (JSON, CSV, SVG), and stored as the camera's profile where [`profile_place`] says,
/// if the session passes [`profile_quality`].
pub fn response(
    dir: &Path,
    opts: &ResponseOptions,
    on_event: &mut dyn FnMut(HdrEvent),
) -> Result<(Response, ProfileStored, Vec<String>), HdrError> {
    let m = session::open(dir, opts.allow_incomplete)?;
    session::check_out_dir(&dir.join("hdr"))?;
    let warnings: Vec<String> = session::incomplete_warning(&m).into_iter().collect();
    let place = profile_place(opts.profile.as_deref(), opts.rig.as_deref(), &m)?;
    on_event(HdrEvent::Loading {
        frames: m.frames.len(),
    });
    let frames = SessionFrames::new(dir, &m)?;
    let tiles = frames.tiles()?;
    let darks = frames.dark_medians()?;
    on_event(HdrEvent::Recovering);
    let r = recover_from(dir, &m, &tiles, &darks, &opts.recover_options)?;
    let quality = profile_quality(&m, &tiles, &r);
    if let (true, Err(why)) = (opts.replace_profile, &quality) {
        return Err(HdrError::Input(format!(
            "--replace-profile: the response of {} cannot become the camera's profile: {why}; nothing was written",
            dir.display()
        )));
    }
    files::write_response(&dir.join("hdr"), &r, tiles.step())?;
    let stored = match (place, quality) {
        (None, _) => ProfileStored::Nowhere,
        (Some(path), Err(why)) => ProfileStored::Refused {
            path,
            why: why.to_string(),
        },
        (Some(path), Ok(())) => {
            if store_profile(&path, &r, opts.replace_profile)? {
                ProfileStored::Written(path)
            } else {
                ProfileStored::Kept(path)
            }
        }
    };
    Ok((r, stored, warnings))
}

/// The response `glint hdr` takes for a session without recovering one: a file given with
/// `--response`, else the camera's profile (`opts.profile`, else `profile`: the one beside
/// the rig), unless `opts.recover`. None: recover one. The response must be for the
/// session's `bit_depth` and `channels` (a monochrome camera's response has one channel).
pub fn known_response(
    opts: &HdrOptions,
    profile: Option<PathBuf>,
    bit_depth: u8,
    channels: usize,
) -> Result<Option<(Response, ResponseSource)>, HdrError> {
    let check_channels = |r: &Response, p: &Path| {
        if r.channels.len() == channels {
            return Ok(());
        }
        Err(HdrError::Input(format!(
            "the response {} is for frames of {} but the session's have {}; recover one with glint response",
            p.display(),
            session::channels_name(r.channels.len() as u8),
            session::channels_name(channels as u8)
        )))
    };
    if let Some(f) = &opts.response_file {
        let r = files::load_response(f)?;
        check_channels(&r, f)?;
        return Ok(Some((r, ResponseSource::File(f.display().to_string()))));
    }
    // The file given with --profile is the user's; the one beside the rig is
    // `profiles/NAME`, read through no link below the rig's folder.
    let profile = match (&opts.profile, profile) {
        (Some(p), _) => Some((p.clone(), crate::fsx::Within::file(p))),
        (None, Some(p)) => Some((p.clone(), crate::fsx::Within::last(&p, 2))),
        (None, None) => None,
    };
    let Some((p, file)) = profile
        .as_ref()
        .filter(|(_, file)| file.is_there() && !opts.recover)
    else {
        return Ok(None);
    };
    let r = files::load_response(file)?;
    if r.bit_depth != bit_depth {
        return Err(HdrError::Input(format!(
            "the camera profile {} is for {}-bit frames but the session's are {bit_depth}-bit; recover one with glint response",
            p.display(),
            r.bit_depth,
        )));
    }
    check_channels(&r, p)?;
    Ok(Some((r, ResponseSource::Profile(p.display().to_string()))))
}

/// The note `glint hdr` gives when it recovered a response with nowhere to keep it.
pub const NO_PROFILE_NOTE: &str = "the response was recovered from this session alone and not stored: pass --rig FILE (the rig file you capture with; its camera profile is kept in FILE's folder, profiles/) or --profile FILE to store it and merge later sessions with it";

/// `glint hdr SESSION`: response (file, profile or recovered), merge, files.
pub fn run(
    dir: &Path,
    opts: &HdrOptions,
    on_event: &mut dyn FnMut(HdrEvent),
) -> Result<(HdrSummary, Merged), HdrError> {
    let start = Instant::now();
    let m = session::open(dir, opts.allow_incomplete)?;
    session::check_out_dir(&dir.join("hdr"))?;
    let mut warnings: Vec<String> = session::incomplete_warning(&m).into_iter().collect();
    let mut notes = Vec::new();
    let place = profile_place(opts.profile.as_deref(), opts.rig.as_deref(), &m)?;
    on_event(HdrEvent::Loading {
        frames: m.frames.len(),
    });
    // Frames are read one at a time: the memory is the merge's sums and one frame (all
    // tile frames only while a response is recovered from them), whatever the number of
    // frames listed.
    let frames = SessionFrames::new(dir, &m)?;
    let times = frames.times();
    let mut profile_written = None;
    let mut tiles = None;
    let (r, source) =
        match known_response(opts, place.clone(), frames.bit_depth, frames.channels())? {
            Some(known) => known,
            None => {
                let all = frames.tiles()?;
                let darks = frames.dark_medians()?;
                on_event(HdrEvent::Recovering);
                let r = recover_from(dir, &m, &all, &darks, &opts.recover_options)?;
                match &place {
                    None => notes.push(NO_PROFILE_NOTE.into()),
                    Some(p) => match profile_quality(&m, &all, &r) {
                        Err(why) => warnings.push(format!(
                            "the recovered response was not stored as the camera profile {}: {why}",
                            p.display()
                        )),
                        Ok(()) => {
                            if store_profile(p, &r, false)? {
                                profile_written = Some(p.display().to_string());
                            }
                        }
                    },
                }
                if let Some(w) = alternatives_warning(&r, &all, &frames)? {
                    warnings.push(w);
                }
                tiles = Some(all);
                (r, ResponseSource::Recovered)
            }
        };
    merge::check_response(&r, &times)?;
    on_event(HdrEvent::Merging {
        frames: times.frames.len(),
        megapixels: (times.width * times.height) as f64 * 1e-6,
    });
    let mut dark = merge::DarkLevels::default();
    for f in &frames.darks {
        let d = frames.read(f)?;
        dark.add(&r, d.exposure_us, &d.pixels);
    }
    let mut merger = merge::Merger::new(r, times.width, times.height);
    match tiles {
        Some(all) => {
            for f in all.frames {
                let level = dark.for_exposure(f.exposure_us);
                merger.fold(&f, level)?;
            }
        }
        None => {
            for f in &frames.tiles {
                let f = frames.read(f)?;
                merger.fold(&f, dark.for_exposure(f.exposure_us))?;
            }
        }
    }
    let r = merger.response().clone();
    let merged = merger.finish();
    check_finite(&merged)?;
    on_event(HdrEvent::Writing);
    let summary = write_outputs(
        dir,
        &r,
        source,
        profile_written,
        &times,
        dark.frames(),
        &merged,
        Extra {
            state: m.state,
            warnings,
            notes,
        },
        start,
    )?;
    Ok((summary, merged))
}

/// Above this median relative difference between the radiance merged with the chosen curve
/// and with an alternative that fits the bracket nearly as well, `glint hdr` says the
/// bracket does not determine the curve (the merge's accuracy goal is 1%).
pub const AMBIGUOUS_MERGE: f64 = 0.01;

/// Pixels (at most) on which the chosen curve's and the alternatives' merges are compared.
const AMBIGUITY_PIXELS: usize = 20_000;

/// Where the response was recovered from this bracket and another model's curve fits it
/// nearly as well ([`response::Alternative`]): the image's pixels (a spread subset) merged
/// with each, and a warning where the two radiances differ by more than
/// [`AMBIGUOUS_MERGE`] (the median over the pixels of |ratio / its median - 1|, per
/// channel: one scale per channel, which no relative result sees). The bracket cannot tell
/// the curves apart, so that difference is an error of the merge's shape the merge's own
/// variance does not hold.
pub fn alternatives_warning(
    r: &Response,
    all: &Bracket,
    frames: &SessionFrames,
) -> Result<Option<String>, HdrError> {
    if r.alternatives.is_empty() {
        return Ok(None);
    }
    let n = all.width * all.height;
    let nc = all.channels;
    let stride = n.div_ceil(AMBIGUITY_PIXELS).max(1);
    let picked: Vec<usize> = (0..n).step_by(stride).collect();
    let sub = |frames: Vec<super::BracketFrame>| Bracket {
        width: picked.len(),
        height: 1,
        bit_depth: all.bit_depth,
        channels: nc,
        frames,
    };
    let tiles = sub(all.frames.iter().map(|f| f.pick(&picked, nc)).collect());
    let darks = sub(frames
        .darks
        .iter()
        .map(|f| frames.read(f).map(|d| d.pick(&picked, nc)))
        .collect::<Result<_, _>>()?);
    let Ok(p) = merge::PixelMerge::new(r, &tiles, &darks) else {
        return Ok(None);
    };
    let zero: Vec<Vec<f64>> = p.values().iter().map(|v| vec![0.0; v.len()]).collect();
    let chosen = p.merge(&zero);
    let mut worst: Option<(f64, usize, &str)> = None;
    for a in &r.alternatives {
        let other = p.merge(&a.delta_at(p.values()));
        for c in 0..nc {
            let mut ratios: Vec<f64> = (c..chosen.radiance.len())
                .step_by(nc)
                .filter(|&k| chosen.mask[k] == merge::MASK_OK && other.mask[k] == merge::MASK_OK)
                .map(|k| other.radiance[k] as f64 / chosen.radiance[k] as f64)
                .filter(|x| x.is_finite() && *x > 0.0)
                .collect();
            if ratios.is_empty() {
                continue;
            }
            let scale = response::median(&mut ratios);
            let mut dev: Vec<f64> = ratios.iter().map(|x| (x / scale - 1.0).abs()).collect();
            let d = response::median(&mut dev);
            tracing::info!(
                "the {} curve merges channel {c} {:.2}% differently from the {} one",
                a.model.as_str(),
                100.0 * d,
                r.model.as_str()
            );
            if worst.is_none_or(|w| d > w.0) {
                worst = Some((d, c, a.model.as_str()));
            }
        }
    }
    Ok(worst.filter(|w| w.0 > AMBIGUOUS_MERGE).map(|(d, c, model)| {
        let channel = if nc == 1 {
            String::new()
        } else {
            format!(" in channel {}", ["R", "G", "B"][c.min(2)])
        };
        format!(
            "the bracket does not determine the response curve: the {model} curve fits it nearly as well as the {} one and merges the image {:.1}% differently{channel} (median over the pixels, one scale per channel), an error of the radiance's shape the variance does not hold; capture exposures one stop apart, or merge with a camera profile from a denser bracket (--profile FILE)",
            r.model.as_str(),
            100.0 * d
        )
    }))
}

/// A merge whose measured samples are all finite: the frames' tables keep them so
/// ([`merge::Merger::fold`] refuses a frame that would not), so this is a last look, an
/// error naming the first pixel that is not, never a result.
fn check_finite(m: &Merged) -> Result<(), HdrError> {
    let bad = m
        .radiance
        .iter()
        .zip(&m.variance)
        .zip(&m.mask)
        .position(|((x, v), k)| *k == merge::MASK_OK && !(x.is_finite() && v.is_finite()));
    match bad {
        None => Ok(()),
        Some(k) => {
            let p = k / m.channels.max(1);
            Err(HdrError::Input(format!(
                "the merge gives a non-finite radiance at pixel ({}, {}), channel {}; check the frames' exposure times and the response",
                p % m.width.max(1),
                p / m.width.max(1),
                k % m.channels.max(1)
            )))
        }
    }
}

/// What a merge's summary says besides the merge: the session's state, warnings and notes
/// from before the merge.
#[derive(Debug, Clone)]
pub struct Extra {
    pub state: State,
    pub warnings: Vec<String>,
    pub notes: Vec<String>,
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
    extra: Extra,
    start: Instant,
) -> Result<HdrSummary, HdrError> {
    let out = dir.join("hdr");
    files::write_merged(&out, merged)?;
    files::write_response(&out, r, tiles.step())?;
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
    let mut warnings = extra.warnings;
    warnings.extend(r.warnings.iter().cloned());
    if sat > 0 {
        warnings.push(format!(
            "{sat} samples ({:.2}%) are saturated, or read above where the response curve is known, even in the shortest exposure ({} µs): they have no radiance (mask.png); add a shorter exposure to measure them (the response's valid range ends at {}; a recovered curve is known only where the bracket shows a value in two exposures)",
            100.0 * sat as f64 / merged.mask.len() as f64,
            tiles.frames[0].exposure_us,
            (0..r.channels.len())
                .map(|c| format!(
                    "{} {}",
                    r.channel_name(c),
                    r.channels[c].valid_max
                ))
                .collect::<Vec<_>>()
                .join(", ")
        ));
    }
    let summary = HdrSummary {
        session: dir.display().to_string(),
        state: extra.state,
        response: source,
        model: r.model.as_str().into(),
        profile_written,
        width: tiles.width,
        height: tiles.height,
        bit_depth: tiles.bit_depth,
        channels: merged.channels,
        exposures_us: tiles.frames.iter().map(|f| f.exposure_us).collect(),
        dark_frames,
        samples_measured: ok,
        samples_saturated: sat,
        samples_too_dark: too_dark,
        radiance_min: if lo.is_finite() { lo } else { f64::NAN },
        radiance_max: if hi.is_finite() { hi } else { f64::NAN },
        median_relative_sd: median,
        warnings,
        notes: extra.notes,
        files: [
            "radiance.exr",
            "variance.exr",
            "radiance.hdr",
            "preview.png",
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
    let json = serde_json::to_vec_pretty(&summary.file()).expect("summary serialises");
    session::write_replace(&out.join("summary.json"), &json)?;
    Ok(summary)
}
