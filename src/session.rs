//! Session directories: the public, stable record of one capture (docs/session-format.md).
//!
//! ```text
//! SESSION/
//!   manifest.json   state, rig snapshot, software version, every frame with its checksum
//!   rig.toml        the rig file as it was read
//!   frames/*.png    lossless frames exactly as captured
//! ```
//!
//! Durability rules: every file is written under a temporary name, synced, and moved into
//! place; frames are linked into place with `link(2)`, which refuses to replace an existing
//! file, so a captured frame can never be overwritten. A frame enters the manifest only
//! after its file is on disk, and the manifest is rewritten (atomically) after every frame,
//! so a crash or a device fault leaves a session whose manifest lists exactly the frames
//! that are there, with valid checksums.
//!
//! The session owns its records: the manifest, each frame's [`FrameRecord`] with how its
//! exposure was confirmed ([`Verification`]), and [`NewFrame`], what a frame to write must
//! say about itself. It stores the capture plan ([`crate::plan`]) but knows nothing of the
//! engine that runs it: the capture module depends on this one, never the reverse, and
//! turns each frame its engine keeps into a [`NewFrame`].

use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{ExtendedColorType, ImageEncoder};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::devices::{CameraInfo, Frame, LampState, Pixels};
use crate::fsx;
use crate::plan::{FrameKind, Plan, Step};
use crate::rig::{LoadedRig, Rig};
pub use glint_format::image::channels_name;

/// Name of the format in `manifest.json`.
pub const FORMAT: &str = "glint-session";
/// Version of the format; bumped on any incompatible change.
pub const FORMAT_VERSION: u32 = 1;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum State {
    /// Capture running (or interrupted without a chance to say so).
    Capturing,
    Complete,
    /// Stopped by a fault; `failure` says why. Frames listed are intact.
    Failed,
}

impl State {
    /// The state as `manifest.json` spells it (serde's name).
    pub fn as_str(self) -> &'static str {
        match self {
            State::Capturing => "capturing",
            State::Complete => "complete",
            State::Failed => "failed",
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Software {
    pub name: String,
    pub version: String,
}

/// How a kept frame's exposure was confirmed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Verification {
    /// The frame's own metadata reported the requested exposure.
    Metadata,
    /// The image level jumped after the change and then held steady.
    ImageStatistics,
    /// The image could not show the change; the latency measured earlier was waited out.
    MeasuredLatency,
    /// Neither metadata, a visible change nor a measured latency: the full settle time was
    /// waited out (a warning is issued).
    SettleTimeout,
    /// Not captured by Glint: the exposure was given to `glint import` (a times file or the
    /// photo's EXIF data).
    Imported,
}

/// One kept frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameRecord {
    /// 0-based position in the session.
    pub index: u32,
    /// Path relative to the session directory.
    pub file: String,
    pub kind: FrameKind,
    pub exposure_requested_us: u32,
    pub exposure_reported_us: u32,
    /// The exposure to full precision, where it is not a whole number of µs (imported
    /// photos: 1/1024 s = 976.5625 µs).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub exposure_exact_us: Option<f64>,
    pub exposure_verified_by: Verification,
    /// Host time the frame arrived (RFC 3339, UTC).
    pub timestamp: String,
    /// Device clock at the start of exposure, µs, where the camera has one.
    pub device_timestamp_us: Option<u64>,
    /// The camera's frame sequence number.
    pub sequence: u64,
    pub lamp: LampState,
    pub width: u32,
    pub height: u32,
    pub bit_depth: u8,
    /// SHA-256 of the file's bytes, lowercase hex.
    pub sha256: String,
    /// An imported photo's aperture (EXIF FNumber), where it has one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub f_number: Option<f64>,
    /// An imported photo's ISO (EXIF PhotographicSensitivity), where it has one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub iso: Option<u32>,
}

/// A frame to write into a session ([`SessionWriter::add_frame`]): its pixels and what
/// is known about them. The capture makes one from every frame its engine keeps.
#[derive(Debug, Clone, Copy)]
pub struct NewFrame<'a> {
    pub kind: FrameKind,
    pub frame: &'a Frame,
    pub exposure_requested_us: u32,
    /// What the device reported: the frame's metadata where present, else the control.
    pub exposure_reported_us: u32,
    pub verified_by: Verification,
    /// The lamp's state, read back from the lamp before this group of frames.
    pub lamp: LampState,
    /// Host time the frame was received.
    pub received: SystemTime,
}

/// `manifest.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub format: String,
    pub format_version: u32,
    pub state: State,
    /// Why the capture failed (state `failed`).
    #[serde(default)]
    pub failure: Option<String>,
    pub software: Software,
    pub created: String,
    #[serde(default)]
    pub finished: Option<String>,
    /// The rig file's path as given when capturing (empty for imported sessions).
    #[serde(default)]
    pub rig_file: String,
    /// The rig as parsed (defaults filled in); absent for sessions made by `glint import`.
    #[serde(default)]
    pub rig: Option<Rig>,
    #[serde(default)]
    pub camera: Option<CameraInfo>,
    #[serde(default)]
    pub lamp_identity: Option<String>,
    /// The capture plan (empty for imported sessions).
    #[serde(default)]
    pub plan: Plan,
    /// Where the frames came from when the session was made by `glint import`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub imported_from: Option<String>,
    /// Set when a capture ends: `true` when the lamp read back off at the end (or was never
    /// switched on), `false` when switching it off failed and it may still be on. Absent
    /// while capturing and for imported sessions.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lamp_off_confirmed: Option<bool>,
    pub frames: Vec<FrameRecord>,
}

/// What went wrong with a session directory.
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    #[error("{path} already exists and is not empty; choose another --out (Glint never writes into existing data)")]
    Exists { path: PathBuf },
    #[error("{op} {path}: {source}")]
    Io {
        op: &'static str,
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: not a Glint session manifest: {reason}")]
    BadManifest { path: PathBuf, reason: String },
    #[error("encoding frame {index} as PNG: {source}")]
    Encode {
        index: u32,
        source: image::ImageError,
    },
    #[error("cannot start the session in {}: {step}: {source}; nothing was left there", .dir.display())]
    Start {
        dir: PathBuf,
        step: String,
        source: Box<SessionError>,
    },
    /// The manifest contradicts itself, the rig or the session folder.
    #[error("{path}: {first}{more}", more = more_problems(*.more))]
    Invalid {
        path: PathBuf,
        first: String,
        more: usize,
    },
    /// An output folder that is a symbolic link or not a folder (the message names it).
    #[error("{0}")]
    UnsafeOutput(String),
    /// The capture did not finish (`capturing`) or failed.
    #[error("the session {} is {what}, not complete; its results would rest on an unfinished capture: re-capture, or pass --allow-incomplete to use its {frames} frames anyway", .dir.display())]
    Incomplete {
        dir: PathBuf,
        /// "`capturing` (the capture was killed or is still running)", "`failed` (...)".
        what: String,
        frames: usize,
    },
}

fn more_problems(n: usize) -> String {
    match n {
        0 => String::new(),
        n => format!(" (and {n} more; `glint session verify` lists them all)"),
    }
}

fn io<'a>(op: &'static str, path: &'a Path) -> impl FnOnce(std::io::Error) -> SessionError + 'a {
    move |source| SessionError::Io {
        op,
        path: path.to_path_buf(),
        source,
    }
}

/// A frame's bytes, read and checked: its path inside the session ([`fsx::inside`]), a
/// regular file of at most [`fsx::MAX_IMAGE_BYTES`], the manifest's checksum, and a PNG
/// whose header says the size and bit depth the manifest lists, with the session's
/// `channels` (3: RGB, 1: grey; [`Manifest::channels`]), checked before anything is
/// decoded. The error is the path and what is wrong with it, for the caller's own error
/// type.
pub fn read_verified(
    dir: &Path,
    f: &FrameRecord,
    channels: u8,
) -> Result<Vec<u8>, (PathBuf, String)> {
    let path = fsx::inside(dir, &f.file).map_err(|e| (dir.join("manifest.json"), e.to_string()))?;
    let bytes = fsx::Within::new(dir, &f.file)
        .read(fsx::MAX_IMAGE_BYTES)
        .map_err(|e| {
            (
                path.clone(),
                format!("cannot read a frame listed in the manifest ({e})"),
            )
        })?;
    if sha256_hex(&bytes) != f.sha256 {
        return Err((
            path,
            "the file's checksum does not match the manifest; the frame was altered (glint session verify)".into(),
        ));
    }
    check_png_header(&bytes, f, channels).map_err(|e| (path, e.to_string()))?;
    Ok(bytes)
}

/// The size, bit depth and colour type a PNG's header (IHDR) declares.
pub fn png_header(bytes: &[u8]) -> Option<(u32, u32, u8, u8)> {
    const SIG: &[u8] = b"\x89PNG\r\n\x1a\n";
    if bytes.len() < 33 || &bytes[..8] != SIG || &bytes[12..16] != b"IHDR" {
        return None;
    }
    let be = |i: usize| u32::from_be_bytes([bytes[i], bytes[i + 1], bytes[i + 2], bytes[i + 3]]);
    Some((be(16), be(20), bytes[24], bytes[25]))
}

/// A frame file's PNG header against its manifest entry: the session format's frames are
/// PNGs of the listed size and bit depth, RGB (3 channels) or, from a monochrome camera,
/// grey (1 channel).
fn check_png_header(bytes: &[u8], f: &FrameRecord, channels: u8) -> Result<(), PngProblem> {
    let Some((w, h, bits, colour)) = png_header(bytes) else {
        return Err(PngProblem::NotPng);
    };
    if (w, h, bits) != (f.width, f.height, f.bit_depth) {
        return Err(PngProblem::Size {
            found: (w, h, bits),
            listed: (f.width, f.height, f.bit_depth),
        });
    }
    // PNG colour types: 0 grey, 2 RGB.
    let (want, expected) = match channels {
        1 => (
            0,
            "this session's frames are grey (1 channel: a monochrome camera)",
        ),
        _ => (2, "a session's frames are RGB (3 channels)"),
    };
    if colour != want {
        let what = match colour {
            0 => "1 channel (grey)",
            2 => "3 channels (RGB)",
            3 => "a palette",
            4 => "2 channels (grey and alpha)",
            6 => "4 channels (RGBA)",
            _ => "an unknown colour type",
        };
        return Err(PngProblem::Colour { what, expected });
    }
    Ok(())
}

/// What is wrong with a frame file's PNG header ([`check_png_header`]), after its name.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PngProblem {
    #[error("is not a PNG file (a session's frames are PNG)")]
    NotPng,
    /// Width, height and bits of the file, and as the manifest lists them.
    #[error("is a {}x{} {}-bit image but the manifest lists it as {}x{} {}-bit; the frame or the manifest was altered", .found.0, .found.1, .found.2, .listed.0, .listed.1, .listed.2)]
    Size {
        found: (u32, u32, u8),
        listed: (u32, u32, u8),
    },
    #[error("has {what}, but {expected}")]
    Colour {
        what: &'static str,
        expected: &'static str,
    },
}

/// RFC 3339 UTC with microseconds.
pub fn timestamp(t: SystemTime) -> String {
    humantime::format_rfc3339_micros(t).to_string()
}

/// Write `bytes` to a new file `path`, never replacing an existing one: temporary file,
/// fsync, `link` into place (fails if `path` exists), fsync the directory. On any error
/// the temporary file is removed.
pub fn write_new(path: &Path, bytes: &[u8]) -> Result<(), SessionError> {
    let tmp = temp_name(path);
    write_synced(&tmp, bytes)?;
    let linked = fs::hard_link(&tmp, path);
    let _ = fs::remove_file(&tmp);
    linked.map_err(io("placing", path))?;
    sync_dir(path)
}

/// Replace `path` atomically (temporary file, fsync, rename, fsync the directory). On any
/// error the temporary file is removed and `path` is as it was.
pub fn write_replace(path: &Path, bytes: &[u8]) -> Result<(), SessionError> {
    let tmp = temp_name(path);
    write_synced(&tmp, bytes)?;
    if let Err(e) = fs::rename(&tmp, path) {
        let _ = fs::remove_file(&tmp);
        return Err(io("renaming into place", path)(e));
    }
    sync_dir(path)
}

fn temp_name(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!(".{name}.tmp-{}", std::process::id()))
}

/// Create `path` (it must not exist), write and sync it; if writing or syncing fails (a
/// full disk), the half-written file is removed again.
fn write_synced(path: &Path, bytes: &[u8]) -> Result<(), SessionError> {
    create_filled(path, "writing", |f| f.write_all(bytes))
}

/// Create `path` new, fill it with `fill` (`op` names it in errors) and sync it; on any
/// error after creating it, the file is removed again.
fn create_filled(
    path: &Path,
    op: &'static str,
    fill: impl FnOnce(&mut File) -> std::io::Result<()>,
) -> Result<(), SessionError> {
    let mut f = File::options()
        .write(true)
        .create_new(true)
        .open(path)
        .map_err(io("creating", path))?;
    let done = fill(&mut f)
        .map_err(io(op, path))
        .and_then(|_| f.sync_all().map_err(io("syncing", path)));
    if done.is_err() {
        drop(f);
        let _ = fs::remove_file(path);
    }
    done
}

fn sync_dir(path: &Path) -> Result<(), SessionError> {
    let dir = path.parent().unwrap_or(Path::new("."));
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(io("syncing directory", dir))
}

/// Allocate `len` bytes to a new file `path` (really allocated, not a sparse hole), synced;
/// removed again on any error.
fn write_reserve(path: &Path, len: u64) -> Result<(), SessionError> {
    use std::os::fd::AsRawFd;
    create_filled(path, "allocating", |f| {
        // SAFETY: the descriptor is open for writing for the duration of the call.
        let r = unsafe { libc::posix_fallocate(f.as_raw_fd(), 0, len as libc::off_t) };
        match r {
            0 => Ok(()),
            libc::ENOSPC | libc::EFBIG | libc::EDQUOT => Err(std::io::Error::from_raw_os_error(r)),
            // No fallocate here: write the bytes (not zeros, which some file systems compress).
            _ => f.write_all(&vec![0xa5; len as usize]),
        }
    })
}

/// Encode pixels losslessly as PNG (8- or 16-bit): RGB interleaved, or one sample a pixel
/// (a monochrome camera's, width x height samples) as a grey PNG (L8, L16).
pub fn encode_png(width: u32, height: u32, pixels: &Pixels) -> Result<Vec<u8>, image::ImageError> {
    let mut buf = Vec::with_capacity(pixels.len());
    let enc = PngEncoder::new_with_quality(&mut buf, CompressionType::Fast, FilterType::Sub);
    let grey = pixels.len() as u64 == width as u64 * height as u64;
    match pixels {
        Pixels::U8(v) => {
            let t = if grey {
                ExtendedColorType::L8
            } else {
                ExtendedColorType::Rgb8
            };
            enc.write_image(v, width, height, t)
        }
        Pixels::U16(v) => {
            let bytes: Vec<u8> = v.iter().flat_map(|x| x.to_ne_bytes()).collect();
            let t = if grey {
                ExtendedColorType::L16
            } else {
                ExtendedColorType::Rgb16
            };
            enc.write_image(&bytes, width, height, t)
        }
    }?;
    Ok(buf)
}

/// SHA-256 as lowercase hex.
pub fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// A new session's folder name: `NAME-<UTC time>` (e.g. `mock-20261202T004226Z`), as
/// `glint capture`, `glint run` and the daemon name sessions they are not given a folder for.
pub fn folder_name(name: &str) -> String {
    let t = humantime::format_rfc3339_seconds(SystemTime::now()).to_string();
    let stamp: String = t.chars().filter(|c| c.is_ascii_alphanumeric()).collect();
    format!("{name}-{stamp}")
}

/// Writes a session while a capture runs.
///
/// A full disk must not leave a manifest that still says `capturing`: rewriting the
/// manifest needs room for a new copy of it. So the writer keeps a reserve file in the
/// session, `.glint-reserve.tmp-PID`, allocated at the start and big enough for the
/// largest manifest the plan can produce; [`SessionWriter::finish`] removes it just before
/// the last manifest is written, so that one always fits. (Freeing the failed temporary
/// file alone is not enough when the manifest itself is what no longer fits, and rewriting
/// the manifest in place would leave a torn one after a crash.) A killed capture leaves the
/// reserve behind, named like every other leftover temporary file.
pub struct SessionWriter {
    dir: PathBuf,
    manifest: Manifest,
    reserve: Option<PathBuf>,
}

/// Bytes one frame's record adds to the manifest, at most (a record is ~550 bytes).
const RESERVE_PER_FRAME: u64 = 1024;
/// Room for the failure reason and the closing fields.
const RESERVE_SLACK: u64 = 32 * 1024;

impl SessionWriter {
    /// Start a new session in `dir`, which must not exist or be empty. If the session
    /// cannot be started (not even the first manifest fits), everything written is removed
    /// again, and `dir` too when this call created it.
    pub fn create(
        dir: &Path,
        rig: &LoadedRig,
        plan: &Plan,
        camera: CameraInfo,
    ) -> Result<Self, SessionError> {
        let existed = dir.exists();
        if existed {
            let empty = fs::read_dir(dir)
                .map_err(io("reading", dir))?
                .next()
                .is_none();
            if !empty {
                return Err(SessionError::Exists { path: dir.into() });
            }
        }
        let manifest = Manifest {
            format: FORMAT.into(),
            format_version: FORMAT_VERSION,
            state: State::Capturing,
            failure: None,
            software: Software {
                name: "glint".into(),
                version: crate::VERSION.into(),
            },
            created: timestamp(SystemTime::now()),
            finished: None,
            rig_file: rig.path.display().to_string(),
            rig: Some(rig.rig.clone()),
            camera: Some(camera),
            lamp_identity: None,
            plan: plan.clone(),
            imported_from: None,
            lamp_off_confirmed: None,
            frames: Vec::new(),
        };
        let mut w = SessionWriter {
            dir: dir.into(),
            manifest,
            reserve: None,
        };
        let started = w.start(rig, plan);
        if let Err((step, e)) = started {
            w.remove_partial(existed);
            return Err(SessionError::Start {
                dir: dir.into(),
                step,
                source: Box::new(e),
            });
        }
        Ok(w)
    }

    /// The files of a new session: the folders, rig.toml, the first manifest, the reserve.
    fn start(&mut self, rig: &LoadedRig, plan: &Plan) -> Result<(), (String, SessionError)> {
        let dir = self.dir.clone();
        let step = |s: &str| {
            let s = s.to_string();
            move |e| (s, e)
        };
        fs::create_dir_all(dir.join("frames"))
            .map_err(io("creating", &dir))
            .map_err(step("creating the session folder"))?;
        write_new(&dir.join("rig.toml"), rig.text.as_bytes()).map_err(step("writing rig.toml"))?;
        self.save()
            .map_err(step("the first manifest does not fit"))?;
        let first = self.manifest_json().len() as u64;
        let len = (first + plan.frames() as u64 * RESERVE_PER_FRAME + RESERVE_SLACK)
            .next_multiple_of(4096);
        let reserve = dir.join(format!("{RESERVE_PREFIX}{}", std::process::id()));
        write_reserve(&reserve, len).map_err(step(&format!(
            "reserving {} KB for the last manifest",
            len / 1024
        )))?;
        self.reserve = Some(reserve);
        Ok(())
    }

    /// Undo a session that could not be started: remove what this writer wrote, and the
    /// folder when it was created here (`remove_dir` refuses a folder that holds anything
    /// else, so nothing but Glint's own partial files is ever removed).
    fn remove_partial(&mut self, existed: bool) {
        if let Some(r) = self.reserve.take() {
            let _ = fs::remove_file(r);
        }
        let _ = fs::remove_file(self.dir.join("manifest.json"));
        let _ = fs::remove_file(self.dir.join("rig.toml"));
        let _ = fs::remove_dir(self.dir.join("frames"));
        if !existed {
            let _ = fs::remove_dir(&self.dir);
        }
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    fn manifest_json(&self) -> Vec<u8> {
        manifest_bytes(&self.manifest)
    }

    fn save(&self) -> Result<(), SessionError> {
        write_replace(&self.dir.join("manifest.json"), &self.manifest_json())
    }

    /// Record the lamp's reply to `*IDN?`.
    pub fn set_lamp_identity(&mut self, identity: String) -> Result<(), SessionError> {
        self.manifest.lamp_identity = Some(identity);
        self.save()
    }

    /// Note whether the lamp read back off at the end; written by [`SessionWriter::finish`].
    pub fn set_lamp_off_confirmed(&mut self, confirmed: bool) {
        self.manifest.lamp_off_confirmed = Some(confirmed);
    }

    /// Write a frame, then list it in the manifest. Takes a [`NewFrame`], or anything that
    /// converts into one (a `&capture::CapturedFrame` does).
    pub fn add_frame<'a>(
        &mut self,
        frame: impl Into<NewFrame<'a>>,
    ) -> Result<&FrameRecord, SessionError> {
        let c = frame.into();
        let index = self.manifest.frames.len() as u32;
        let f = c.frame;
        let png = encode_png(f.width, f.height, &f.pixels)
            .map_err(|source| SessionError::Encode { index, source })?;
        let file = format!(
            "frames/{index:04}-{}-{}us.png",
            c.kind.as_str(),
            c.exposure_requested_us
        );
        write_new(&self.dir.join(&file), &png)?;
        self.manifest.frames.push(FrameRecord {
            index,
            file,
            kind: c.kind,
            exposure_requested_us: c.exposure_requested_us,
            exposure_reported_us: c.exposure_reported_us,
            exposure_exact_us: None,
            exposure_verified_by: c.verified_by,
            timestamp: timestamp(c.received),
            device_timestamp_us: f.device_timestamp_us,
            sequence: f.sequence,
            lamp: c.lamp,
            width: f.width,
            height: f.height,
            bit_depth: f.bit_depth,
            sha256: sha256_hex(&png),
            f_number: None,
            iso: None,
        });
        // The frame is on disk: if the manifest cannot list it now, the last manifest
        // (written from the reserve) will.
        self.save()?;
        Ok(self.manifest.frames.last().unwrap())
    }

    /// Close the session as complete, or as failed with the reason. The reserve is freed
    /// first, so this last manifest fits even on a full disk.
    pub fn finish(mut self, failure: Option<String>) -> Result<Manifest, SessionError> {
        close(&mut self.manifest, failure);
        if let Some(r) = self.reserve.take() {
            let _ = fs::remove_file(&r);
        }
        self.save()?;
        Ok(self.manifest)
    }
}

/// `manifest.json`'s bytes.
fn manifest_bytes(m: &Manifest) -> Vec<u8> {
    serde_json::to_vec_pretty(m).expect("manifest serialises")
}

/// The start of the disk reserve's name (then the capturing process's pid): a session
/// that has one is being captured, or its capture died.
pub const RESERVE_PREFIX: &str = ".glint-reserve.tmp-";

/// A manifest's closing fields: complete, or failed with the reason.
fn close(m: &mut Manifest, failure: Option<String>) {
    m.state = if failure.is_some() {
        State::Failed
    } else {
        State::Complete
    };
    m.failure = failure;
    m.finished = Some(timestamp(SystemTime::now()));
}

/// Close a session whose capture died without closing it (its process was killed): one
/// still `capturing` becomes `failed` with `why` (every frame it lists stays; frames on disk
/// it does not list are left for [`verify`] to name), and the dead capture's disk reserve
/// is removed. `lamp_off_confirmed` is recorded when given: whether the closer read the
/// lamp back off (a daemon at its restart), as a capture records it at its end.
/// `Ok(None)`: the session was not `capturing` and is left as it is (its state is
/// returned).
pub fn close_abandoned(
    dir: &Path,
    why: &str,
    lamp_off_confirmed: Option<bool>,
) -> Result<Option<State>, SessionError> {
    let mut m = load(dir)?;
    if m.state != State::Capturing {
        return Ok(Some(m.state));
    }
    if let Ok(entries) = fs::read_dir(dir) {
        for e in entries.flatten().take(10_000) {
            let reserve = e.file_name().to_string_lossy().starts_with(RESERVE_PREFIX);
            if reserve && e.file_type().is_ok_and(|t| t.is_file()) {
                let _ = fs::remove_file(e.path());
            }
        }
    }
    close(&mut m, Some(why.to_string()));
    if lamp_off_confirmed.is_some() {
        m.lamp_off_confirmed = lamp_off_confirmed;
    }
    write_replace(&dir.join("manifest.json"), &manifest_bytes(&m))?;
    Ok(None)
}

impl Manifest {
    /// Samples a pixel of the session's frames: 1 for a monochrome camera, 3 for RGB. The
    /// camera's report where there is one (older sessions' reports say 3), else the
    /// embedded rig's camera, else 3 (an imported session).
    pub fn channels(&self) -> u8 {
        match (&self.camera, &self.rig) {
            (Some(c), _) => c.channels,
            (None, Some(r)) => r.camera.channels(),
            (None, None) => 3,
        }
    }
}

impl FrameRecord {
    /// The exposure the frame was taken with, µs (the camera's report, or the exact time
    /// an import was given).
    pub fn exposure_us(&self) -> f64 {
        self.exposure_exact_us
            .unwrap_or(self.exposure_reported_us as f64)
    }
}

/// Make sure a derived folder of a session (`hdr/`, `calib/`, ...) is a real folder,
/// creating it if missing ([`fsx::ensure_dir`]): never a symbolic link, so nothing is
/// written through one.
pub fn out_dir(path: &Path) -> Result<(), SessionError> {
    fsx::ensure_dir(path).map_err(|e| {
        if e.kind() == std::io::ErrorKind::InvalidData {
            SessionError::UnsafeOutput(e.to_string())
        } else {
            SessionError::Io {
                op: "creating",
                path: path.into(),
                source: e,
            }
        }
    })
}

/// Refuse a derived folder that exists but is not a real folder (a link), without creating
/// it: for a stage to check before it does any work.
pub fn check_out_dir(path: &Path) -> Result<(), SessionError> {
    match fs::symlink_metadata(path) {
        Ok(m) if !m.is_dir() => out_dir(path),
        _ => Ok(()),
    }
}

/// Longest side of a frame Glint accepts, pixels.
pub const MAX_SIDE: u32 = 16384;
/// Longest exposure Glint accepts in a manifest, µs (one hour).
pub const MAX_EXPOSURE_US: f64 = 3.6e9;
/// Shortest exposure Glint accepts in a manifest, µs (as `glint import` takes).
pub const MIN_EXPOSURE_US: f64 = 1.0;

/// Read a session's manifest (size-capped, a regular file) and check its format; the
/// contents are checked by [`problems`] ([`open`] does both).
pub fn load(dir: &Path) -> Result<Manifest, SessionError> {
    let path = dir.join("manifest.json");
    let text = fsx::read_capped(&path, fsx::MAX_TEXT_BYTES).map_err(io("reading", &path))?;
    let m: Manifest = serde_json::from_slice(&text).map_err(|e| SessionError::BadManifest {
        path: path.clone(),
        reason: fsx::json_error(&e),
    })?;
    if m.format != FORMAT {
        return Err(SessionError::BadManifest {
            path,
            reason: format!("format is {}, not `{FORMAT}`", fsx::quote(&m.format)),
        });
    }
    if m.format_version > FORMAT_VERSION {
        return Err(SessionError::BadManifest {
            path,
            reason: format!(
                "format version {} is newer than this Glint reads ({FORMAT_VERSION}); update Glint",
                m.format_version
            ),
        });
    }
    Ok(m)
}

/// Open a session for a stage: [`load`], then every check of [`problems`] (the first is
/// the error), then its state: a session that is not `complete` is refused unless
/// `allow_incomplete` (the stage then adds [`incomplete_warning`] to its warnings).
pub fn open(dir: &Path, allow_incomplete: bool) -> Result<Manifest, SessionError> {
    let m = load(dir)?;
    if m.state != State::Complete && !allow_incomplete {
        return Err(SessionError::Incomplete {
            dir: dir.into(),
            what: describe_state(&m),
            frames: m.frames.len(),
        });
    }
    let p = problems(dir, &m);
    if let Some(first) = p.first() {
        return Err(SessionError::Invalid {
            path: dir.join("manifest.json"),
            first: first.clone(),
            more: p.len() - 1,
        });
    }
    Ok(m)
}

/// The state of a session that is not complete, in words.
fn describe_state(m: &Manifest) -> String {
    match m.state {
        State::Capturing => "`capturing` (the capture was killed or is still running)".to_string(),
        State::Failed => format!(
            "`failed` ({})",
            fsx::quote(m.failure.as_deref().unwrap_or("no reason recorded"))
        ),
        State::Complete => "`complete`".into(),
    }
}

/// The warning a stage gives when it works on a session that is not complete
/// (`--allow-incomplete`); None for a complete one.
pub fn incomplete_warning(m: &Manifest) -> Option<String> {
    (m.state != State::Complete).then(|| {
        format!(
            "the session is {}: these results come from an unfinished capture of {} frames (--allow-incomplete)",
            describe_state(m),
            m.frames.len()
        )
    })
}

fn is_sha256_hex(s: &str) -> bool {
    s.len() == 64
        && s.bytes()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

/// Everything inconsistent in a session's manifest, each naming the frame or key and what
/// to fix: the embedded rig (as `glint rig check` would), the camera, and every frame's
/// path (relative, inside the session, through no symbolic link and not one, listed
/// once), index,
/// size, bit depth, exposure and checksum, and tile frames labelled with one exposure
/// beyond what the plan keeps. Frame files are not read here ([`read_verified`] and
/// [`verify`] do).
pub fn problems(dir: &Path, m: &Manifest) -> Vec<String> {
    let mut out = Vec::new();
    if let Some(rig) = &m.rig {
        for p in rig.problems() {
            out.push(format!(
                "the embedded rig: {}: {} (the session's rig is not a valid rig)",
                p.key, p.message
            ));
        }
    }
    // The frames' shape: the camera's as reported, which the rig's must match.
    let mut shape = None;
    if let Some(c) = &m.camera {
        if c.width == 0 || c.height == 0 || c.width > MAX_SIDE || c.height > MAX_SIDE {
            out.push(format!(
                "camera: {}x{} is not a usable image size (1..{MAX_SIDE} per side)",
                c.width, c.height
            ));
        }
        if c.bit_depth != 8 && c.bit_depth != 16 {
            out.push(format!(
                "camera.bit_depth: must be 8 or 16 (got {})",
                c.bit_depth
            ));
        }
        if c.model.chars().count() > 200 || c.model.chars().any(|ch| ch.is_control()) {
            out.push(format!(
                "camera.model: {} is not a camera name (at most 200 characters on one line)",
                fsx::quote(&c.model)
            ));
        }
        if c.channels != 1 && c.channels != 3 {
            out.push(format!(
                "camera.channels: must be 1 (monochrome) or 3 (RGB) (got {})",
                c.channels
            ));
        }
        shape = Some((c.width, c.height, c.bit_depth));
    }
    if let (Some(c), Some(rig)) = (&m.camera, &m.rig) {
        let rc = rig.camera.channels();
        if c.channels != rc {
            out.push(format!(
                "camera: {} does not match the embedded rig's camera ({}, pixel_format {})",
                channels_name(c.channels),
                channels_name(rc),
                rig.camera
                    .pixel_format
                    .map_or("none: RGB".to_string(), |f| f.name().to_string())
            ));
        }
    }
    if let Some(rig) = &m.rig {
        let rc = &rig.camera;
        let r = (rc.width, rc.height, rc.bit_depth);
        match shape {
            Some(s) if s != r => out.push(format!(
                "camera: {}x{} {}-bit does not match the embedded rig's camera ({}x{} {}-bit)",
                s.0, s.1, s.2, r.0, r.1, r.2
            )),
            _ => shape = Some(r),
        }
    }
    let mut seen: std::collections::HashMap<PathBuf, usize> = Default::default();
    for (i, f) in m.frames.iter().enumerate() {
        let name = fsx::quote(&f.file);
        let mut bad = |what: String| out.push(format!("frame {i} ({name}): {what}"));
        if f.index as usize != i {
            bad(format!(
                "is listed with index {}; frames are listed in order from 0",
                f.index
            ));
        }
        match fsx::inside(dir, &f.file) {
            Ok(p) => {
                if p.symlink_metadata()
                    .is_ok_and(|m| m.file_type().is_symlink())
                {
                    bad("is a symbolic link; a session's frames must be files inside it".into());
                }
                if let Some(j) = seen.insert(p, i) {
                    bad(format!(
                        "the same file as frame {j}: a frame is listed twice"
                    ));
                }
            }
            Err(e) => bad(e.to_string()),
        }
        if f.width == 0 || f.height == 0 || f.width > MAX_SIDE || f.height > MAX_SIDE {
            bad(format!(
                "{}x{} is not a usable frame size (1..{MAX_SIDE} per side)",
                f.width, f.height
            ));
        }
        if f.bit_depth != 8 && f.bit_depth != 16 {
            bad(format!("bit_depth must be 8 or 16 (got {})", f.bit_depth));
        }
        if let Some((w, h, b)) = shape {
            if (f.width, f.height, f.bit_depth) != (w, h, b) {
                bad(format!(
                    "is listed as {}x{} {}-bit but the camera's frames are {w}x{h} {b}-bit",
                    f.width, f.height, f.bit_depth
                ));
            }
        }
        for (key, v) in [
            ("exposure_requested_us", f.exposure_requested_us as f64),
            ("exposure_reported_us", f.exposure_reported_us as f64),
        ]
        .into_iter()
        .chain(f.exposure_exact_us.map(|x| ("exposure_exact_us", x)))
        {
            if !(v.is_finite() && v > 0.0 && v <= MAX_EXPOSURE_US) {
                // 1e300 as `1e300`, not its 301 digits.
                let shown = if v.is_finite() && v != 0.0 && !(1e-3..1e12).contains(&v.abs()) {
                    format!("{v:e}")
                } else {
                    format!("{v}")
                };
                bad(format!(
                    "{key} = {shown} µs: must be positive and at most {MAX_EXPOSURE_US} µs (one hour)"
                ));
            }
        }
        // The exact time is the reported one to full precision (an imported photo's
        // 1/1024 s = 976.5625 µs beside 977): at least 1 µs, as import takes, and within
        // half a µs of exposure_reported_us.
        if let Some(x) = f.exposure_exact_us.filter(|x| x.is_finite() && *x > 0.0) {
            let reported = f.exposure_reported_us as f64;
            if x < MIN_EXPOSURE_US || (x - reported).abs() > 0.5 {
                let shown = if (1e-3..1e12).contains(&x) {
                    format!("{x}")
                } else {
                    format!("{x:e}")
                };
                bad(format!(
                    "exposure_exact_us = {shown} µs: must be at least {MIN_EXPOSURE_US} µs and within 0.5 µs of exposure_reported_us ({reported} µs); correct it or remove the key"
                ));
            }
        }
        if !is_sha256_hex(&f.sha256) {
            bad(format!(
                "sha256 {} is not a SHA-256 (64 lowercase hex digits)",
                fsx::quote(&f.sha256)
            ));
        }
    }
    out.extend(exposure_problems(m));
    out.extend(count_problems(m));
    out
}

/// The plan's bounds, as a rig's: every capture step keeps at most
/// [`crate::rig::MAX_FRAMES_PER_STEP`] frames, and so does the plan of tile or of dark
/// frames at one exposure; a plan has at most [`crate::rig::MAX_EXPOSURES`] capture steps
/// of each kind (a rig's plan has one per exposure); and dark and grid frames, like tile frames, no more labelled with one
/// exposure than the plan keeps there (a session without a plan, as imported ones: at most
/// [`crate::rig::MAX_FRAMES_PER_STEP`] of a kind at one exposure and
/// [`crate::rig::MAX_EXPOSURES`] exposures of a kind). So the frames a stage reads are
/// bounded by what a rig may ask for, whatever the manifest lists; each problem names the
/// limit and the count.
pub fn count_problems(m: &Manifest) -> Vec<String> {
    use crate::rig::{MAX_EXPOSURES, MAX_FRAMES_PER_STEP};
    use std::collections::BTreeMap;
    let mut out = Vec::new();
    let mut steps: BTreeMap<&'static str, usize> = BTreeMap::new();
    let mut planned: BTreeMap<(&'static str, u32), u64> = BTreeMap::new();
    let mut current = None;
    for (i, s) in m.plan.steps.iter().enumerate() {
        match s {
            Step::SetExposure { us } => current = Some(*us),
            Step::Capture { kind, count } => {
                if *count > MAX_FRAMES_PER_STEP {
                    out.push(format!(
                        "plan step {} ({s}): keeps {count} frames, more than the {MAX_FRAMES_PER_STEP} a capture step may keep (a rig's frames_per_exposure, dark_frames_per_exposure and grid_frames are at most {MAX_FRAMES_PER_STEP})",
                        i + 1
                    ));
                }
                *steps.entry(kind.as_str()).or_default() += 1;
                if let Some(us) = current {
                    *planned.entry((kind.as_str(), us)).or_default() += *count as u64;
                }
            }
            _ => {}
        }
    }
    for ((kind, us), n) in &planned {
        if *kind != FrameKind::Grid.as_str() && *n > MAX_FRAMES_PER_STEP as u64 {
            out.push(format!(
                "the plan keeps {n} {kind} frames at {us} µs, more than the {MAX_FRAMES_PER_STEP} a rig may keep of a kind at one exposure (bracket.frames_per_exposure, bracket.dark_frames_per_exposure)"
            ));
        }
    }
    for (kind, n) in &steps {
        if *n > MAX_EXPOSURES {
            out.push(format!(
                "the plan has {n} capture steps of {kind} frames, more than the {MAX_EXPOSURES} a plan may have (a rig's bracket has at most {MAX_EXPOSURES} exposures)"
            ));
        }
    }
    let mut got: BTreeMap<(&'static str, u32), u64> = BTreeMap::new();
    for f in m.frames.iter().filter(|f| f.kind != FrameKind::Tile) {
        *got.entry((f.kind.as_str(), f.exposure_requested_us))
            .or_default() += 1;
    }
    if m.plan.steps.is_empty() {
        let mut kinds: BTreeMap<&'static str, usize> = BTreeMap::new();
        for ((kind, us), n) in &got {
            *kinds.entry(kind).or_default() += 1;
            if *n > MAX_FRAMES_PER_STEP as u64 {
                out.push(format!(
                    "{n} {kind} frames at {us} µs: a session without a capture plan may have at most {MAX_FRAMES_PER_STEP} of a kind at one exposure"
                ));
            }
        }
        let mut tiles: Vec<u32> = m
            .frames
            .iter()
            .filter(|f| f.kind == FrameKind::Tile)
            .map(|f| f.exposure_requested_us)
            .collect();
        tiles.sort_unstable();
        tiles.dedup();
        kinds.insert(FrameKind::Tile.as_str(), tiles.len());
        for (kind, n) in &kinds {
            if *n > MAX_EXPOSURES {
                out.push(format!(
                    "{kind} frames at {n} exposures: a session without a capture plan may have at most {MAX_EXPOSURES} (a rig's bracket has at most {MAX_EXPOSURES} exposures)"
                ));
            }
        }
        return out;
    }
    for ((kind, us), n) in &got {
        match planned.get(&(*kind, *us)) {
            None => out.push(format!(
                "{n} {kind} frame(s) at {us} µs, an exposure at which the capture plan keeps no {kind} frames"
            )),
            Some(k) if n > k => out.push(format!(
                "{n} {kind} frames are labelled with {us} µs but the plan keeps {k} at that exposure; a manifest may not list more frames than its plan keeps"
            )),
            _ => {}
        }
    }
    out
}

/// Tile frames labelled with one exposure: at most as many as the plan keeps at that
/// exposure (one each for a session without a plan, as imported ones), and for a complete
/// session exactly that many.
fn exposure_problems(m: &Manifest) -> Vec<String> {
    use std::collections::BTreeMap;
    let mut out = Vec::new();
    let tiles: Vec<&FrameRecord> = m
        .frames
        .iter()
        .filter(|f| f.kind == FrameKind::Tile)
        .collect();
    // The plan: tile frames per requested exposure.
    let mut planned: BTreeMap<u32, u64> = BTreeMap::new();
    let mut current = None;
    for s in &m.plan.steps {
        match s {
            Step::SetExposure { us } => current = Some(*us),
            Step::Capture {
                kind: FrameKind::Tile,
                count,
            } => {
                if let Some(us) = current {
                    *planned.entry(us).or_default() += *count as u64;
                }
            }
            _ => {}
        }
    }
    if !planned.is_empty() {
        let mut got: BTreeMap<u32, u64> = BTreeMap::new();
        for f in &tiles {
            *got.entry(f.exposure_requested_us).or_default() += 1;
        }
        for (us, n) in &got {
            match planned.get(us) {
                None => out.push(format!(
                    "{n} tile frame(s) at {us} µs, an exposure the capture plan does not have"
                )),
                Some(k) if n > k => out.push(format!(
                    "{n} tile frames are labelled with {us} µs but the plan keeps {k} at that exposure; two frames cannot have been taken as one"
                )),
                Some(k) if n < k && m.state == State::Complete => out.push(format!(
                    "{n} tile frame(s) at {us} µs but the plan of this complete session keeps {k}"
                )),
                _ => {}
            }
        }
        if m.state == State::Complete {
            for (us, k) in &planned {
                if !got.contains_key(us) {
                    out.push(format!(
                        "no tile frame at {us} µs, though the plan of this complete session keeps {k}"
                    ));
                }
            }
        }
    }
    // The exposure the merge uses: at most `k` readings per requested exposure behind it.
    let mut by_time: Vec<(f64, u32)> = tiles
        .iter()
        .map(|f| (f.exposure_us(), f.exposure_requested_us))
        .collect();
    by_time.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut i = 0;
    while i < by_time.len() {
        let t = by_time[i].0;
        let mut j = i;
        while j < by_time.len() && by_time[j].0 == t {
            j += 1;
        }
        let mut requested: Vec<u32> = by_time[i..j].iter().map(|x| x.1).collect();
        requested.sort_unstable();
        requested.dedup();
        let allowed: u64 = if planned.is_empty() {
            1
        } else {
            requested
                .iter()
                .map(|r| planned.get(r).copied().unwrap_or(1))
                .sum()
        };
        if (j - i) as u64 > allowed {
            out.push(format!(
                "{} tile frames are labelled with the exposure {t} µs, where {allowed} {} expected; a bracket's frames each have their own exposure",
                j - i,
                if allowed == 1 { "is" } else { "are" }
            ));
        }
        i = j;
    }
    out
}

/// The outcome of [`verify`].
#[derive(Debug, Clone, Serialize)]
pub struct VerifyReport {
    pub state: State,
    pub failure: Option<String>,
    pub frames: usize,
    /// Integrity problems: an inconsistent manifest, missing or unreadable files, checksum
    /// mismatches. Empty when intact.
    pub problems: Vec<String>,
    /// Things worth knowing that do not break integrity: leftovers of interrupted writes,
    /// unlisted frames, symbolic links, an unfinished state.
    pub warnings: Vec<String>,
}

impl VerifyReport {
    pub fn intact(&self) -> bool {
        self.problems.is_empty()
    }
}

/// Check a session: the manifest consistent ([`problems`]), every listed frame present
/// (a regular file inside the session, size-capped) with its checksum and the header the
/// manifest lists, and leftovers anywhere in the session (temporary files, unlisted
/// frames, symbolic links).
pub fn verify(dir: &Path) -> Result<VerifyReport, SessionError> {
    let m = load(dir)?;
    let mut problems = problems(dir, &m);
    let mut warnings = Vec::new();
    let mut listed = std::collections::HashSet::new();
    for f in &m.frames {
        let Ok(path) = fsx::inside(dir, &f.file) else {
            continue; // reported by problems()
        };
        listed.insert(path.clone());
        match fsx::Within::new(dir, &f.file).read(fsx::MAX_IMAGE_BYTES) {
            Ok(bytes) => {
                let sum = sha256_hex(&bytes);
                if sum != f.sha256 {
                    problems.push(format!(
                        "{}: checksum {sum} does not match the manifest's {}",
                        fsx::quote(&f.file),
                        fsx::quote(&f.sha256)
                    ));
                } else if let Err(e) = check_png_header(&bytes, f, m.channels()) {
                    problems.push(format!("{}: {e}", fsx::quote(&f.file)));
                }
            }
            Err(e) => problems.push(format!("{}: {e}", fsx::quote(&f.file))),
        }
    }
    leftovers(dir, dir, 0, &listed, &mut warnings);
    match m.state {
        State::Capturing => warnings.push(
            "state is `capturing`: the capture is running or was killed before it could finish"
                .into(),
        ),
        State::Failed => warnings.push(format!(
            "capture failed: {}",
            fsx::short_message(m.failure.as_deref().unwrap_or("no reason recorded"))
        )),
        State::Complete => {}
    }
    Ok(VerifyReport {
        state: m.state,
        failure: m.failure,
        frames: m.frames.len(),
        problems,
        warnings,
    })
}

/// Leftovers under `at` (a folder of the session `dir`), depth-first in name order,
/// following no symbolic link: temporary files of interrupted writes anywhere, files in
/// `frames/` the manifest does not list, and symbolic links (Glint follows none).
fn leftovers(
    dir: &Path,
    at: &Path,
    depth: usize,
    listed: &std::collections::HashSet<PathBuf>,
    warnings: &mut Vec<String>,
) {
    const MAX_NOTES: usize = 1000;
    let Ok(entries) = fs::read_dir(at) else {
        return;
    };
    let mut entries: Vec<_> = entries.flatten().take(100_000).collect();
    entries.sort_by_key(|e| e.file_name());
    for e in entries {
        if warnings.len() >= MAX_NOTES {
            return;
        }
        let path = e.path();
        let rel = path
            .strip_prefix(dir)
            .unwrap_or(&path)
            .to_string_lossy()
            .replace(|c: char| c.is_control(), "?");
        let name = e.file_name().to_string_lossy().into_owned();
        let Ok(meta) = fs::symlink_metadata(&path) else {
            continue;
        };
        let temp = name.contains(".tmp-")
            || name.starts_with(".report.new-")
            || name.starts_with(".report.old-");
        if meta.file_type().is_symlink() {
            warnings.push(format!(
                "{rel}: a symbolic link; Glint neither reads nor writes through links in a session (remove it)"
            ));
        } else if temp {
            warnings.push(format!(
                "{rel}: left over from an interrupted write (not part of the session)"
            ));
        } else if meta.is_dir() {
            if depth < 8 {
                leftovers(dir, &path, depth + 1, listed, warnings);
            }
        } else if rel.starts_with("frames/") && !listed.contains(&path) {
            warnings.push(format!("{rel}: not listed in the manifest"));
        }
    }
}
