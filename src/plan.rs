//! Capture plans: an experiment written down as data, a list of steps that never touch
//! hardware. A plan can be checked against a rig's limits and its duration and disk use
//! estimated with no devices at all (`glint capture --dry-run`).
//!
//! This module owns the plan's vocabulary, [`FrameKind`] included (what a `capture` step
//! keeps, and what a session's frame record says it shows). It sits below both modules that
//! use plans: the engine in [`crate::capture`] runs them, and [`crate::session`] records the
//! plan that ran in the manifest; it depends on neither (only on the rig and the devices'
//! operator actions). [`crate::capture`] re-exports everything here.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::devices::{BoardPose, OperatorAction};
use crate::rig::Rig;

/// The longest capture Glint starts: a day (a rig runs unattended; a plan longer than
/// that is a mistake in the rig file, e.g. exposures in ms where µs were meant).
pub const MAX_PLAN_SECONDS: f64 = 86_400.0;

/// What a frame shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FrameKind {
    /// The tile lit by the lamp (the exposure bracket).
    Tile,
    /// The lamp off: sensor offset and dark current at the same exposure.
    Dark,
    /// The chessboard grid with the tile removed, for calibration.
    Grid,
}

impl FrameKind {
    pub fn as_str(self) -> &'static str {
        match self {
            FrameKind::Tile => "tile",
            FrameKind::Dark => "dark",
            FrameKind::Grid => "grid",
        }
    }
}

/// One step of a plan.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "step", rename_all = "kebab-case")]
pub enum Step {
    /// Ask the lamp who it is (and so check that it answers).
    IdentifyLamp,
    LampOn {
        level: u16,
    },
    /// Let the lamp's output settle.
    WarmUp {
        ms: u64,
    },
    LampOff,
    /// Ask the operator to do something by hand.
    Operator {
        action: OperatorAction,
    },
    /// Set an exposure and wait until the frames show it.
    SetExposure {
        us: u32,
    },
    /// Keep `count` frames at the current exposure.
    Capture {
        kind: FrameKind,
        count: u32,
    },
}

impl std::fmt::Display for Step {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Step::IdentifyLamp => write!(f, "identify the lamp"),
            Step::LampOn { level } => write!(f, "lamp on at level {level}"),
            Step::WarmUp { ms } => write!(f, "lamp warm-up {}", human_duration(*ms as f64 * 1e-3)),
            Step::LampOff => write!(f, "lamp off"),
            Step::Operator { action } => write!(f, "operator: {action}"),
            Step::SetExposure { us } => write!(f, "exposure {us} µs"),
            Step::Capture { kind, count } => write!(
                f,
                "{count} {} frame{}",
                kind.as_str(),
                if *count == 1 { "" } else { "s" }
            ),
        }
    }
}

/// A capture plan.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Plan {
    pub steps: Vec<Step>,
}

/// What a plan may ask of the devices.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    pub min_exposure_us: u32,
    pub max_exposure_us: u32,
}

impl Limits {
    /// The camera limits a rig declares.
    pub fn from_rig(rig: &Rig) -> Self {
        Limits {
            min_exposure_us: rig.camera.min_exposure_us,
            max_exposure_us: rig.camera.max_exposure_us,
        }
    }
}

/// Time and disk a plan needs, estimated without devices.
#[derive(Debug, Clone, Serialize)]
pub struct Estimate {
    pub frames_kept: u32,
    /// Frames expected to be discarded while new exposures take effect.
    pub frames_settling: u32,
    pub seconds: f64,
    /// Uncompressed size of the kept frames' pixels (PNG is usually 40–70% of it).
    pub bytes_max: u64,
    /// Upper bound of the disk the session takes: the kept frames as PNGs stored
    /// uncompressed, with their framing and manifest entries. What the free disk is
    /// checked against.
    pub disk_bytes_max: u64,
}

/// Free disk where a session would be written.
#[derive(Debug, Clone, Serialize)]
pub struct Disk {
    /// The nearest existing folder on the way to the session (where it is measured),
    /// made absolute.
    pub path: PathBuf,
    /// Bytes an unprivileged user may still write there.
    pub free_bytes: u64,
}

impl Disk {
    /// The free space at `out`'s nearest existing ancestor (`out` itself if it exists;
    /// `.` for a relative path none of whose folders exist yet).
    pub fn at(out: &Path) -> std::io::Result<Disk> {
        let path = out
            .ancestors()
            .map(|p| {
                if p.as_os_str().is_empty() {
                    Path::new(".")
                } else {
                    p
                }
            })
            .find(|p| p.exists())
            .unwrap_or(Path::new("."));
        let path = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
        let c = std::ffi::CString::new(path.as_os_str().as_encoded_bytes())
            .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidInput, e))?;
        // SAFETY: `c` is a NUL-terminated path; `st` is plain old data the call fills.
        let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
        if unsafe { libc::statvfs(c.as_ptr(), &mut st) } != 0 {
            return Err(std::io::Error::last_os_error());
        }
        Ok(Disk {
            path,
            free_bytes: (st.f_bavail as u64).saturating_mul(st.f_frsize as u64),
        })
    }
}

/// A duration as people read it: `250 ms`, `2.4 s`, `45 s`, `3 min 20 s`, `1 h 5 min`,
/// `2 d 3 h`.
pub fn human_duration(seconds: f64) -> String {
    if !seconds.is_finite() {
        return format!("{seconds} s");
    }
    let s = seconds.max(0.0);
    if s < 1.0 && (s * 1000.0).round() < 1000.0 {
        return format!("{} ms", (s * 1000.0).round());
    }
    if s < 10.0 && (s * 10.0).round() < 100.0 {
        return format!("{:.1} s", s);
    }
    let total = s.round() as u64;
    let (m, sec) = (total / 60 % 60, total % 60);
    let pair = |a: u64, ua: &str, b: u64, ub: &str| {
        if b == 0 {
            format!("{a} {ua}")
        } else {
            format!("{a} {ua} {b} {ub}")
        }
    };
    if total < 60 {
        format!("{total} s")
    } else if total < 3600 {
        pair(m, "min", sec, "s")
    } else if total < 86_400 {
        // Round to the minute.
        let mins = (s / 60.0).round() as u64;
        if mins >= 24 * 60 {
            "1 d".into()
        } else {
            pair(mins / 60, "h", mins % 60, "min")
        }
    } else {
        let hours = (s / 3600.0).round() as u64;
        pair(hours / 24, "d", hours % 24, "h")
    }
}

/// A size as people read it: `850 kB`, `55.3 MB`, `1.2 GB`, `20.8 TB` (powers of 1000).
pub fn human_bytes(bytes: u64) -> String {
    let b = bytes as f64;
    match bytes {
        0..=999 => format!("{bytes} B"),
        1_000..=999_999 => format!("{:.0} kB", b / 1e3),
        1_000_000..=999_999_999 => format!("{:.1} MB", b / 1e6),
        1_000_000_000..=999_999_999_999 => format!("{:.1} GB", b / 1e9),
        _ => format!("{:.1} TB", b / 1e12),
    }
}

/// The lens plan's default poses: head-on; tilted by `tilt_deg` about x (towards the
/// camera's side, -y) and about y each way; by 0.8 `tilt_deg` about both axes at once
/// (about 1.1 `tilt_deg` in all); and by half of `tilt_deg` away from the camera's side,
/// alone and with 0.8 `tilt_deg` about y; each turned a little about z. Tilts away from a
/// camera that looks down at about 40° are halved: 30° away would show the board at 70°,
/// too foreshortened for its far rows. The focal
/// length is best determined by tilts near 45 degrees (Zhang 2000; Sturm & Maybank 1999),
/// but at 45 degrees the far rows of a board foreshorten to half their width and a
/// lamp-lit board darkens on the side turned from the lamp: 30 degrees keeps every corner
/// sharp and bright while still separating focal length from distance. `count` takes the
/// first poses of that list (5 at least, 9 at most).
pub fn lens_poses(rig: &Rig, tilt_deg: f64, count: usize) -> Vec<BoardPose> {
    let t = tilt_deg;
    let d = 0.8 * tilt_deg;
    let h = 0.5 * tilt_deg;
    let list: [(f64, f64, f64); 9] = [
        (0.0, 0.0, 0.0),
        (t, 0.0, 5.0),
        (0.0, t, 5.0),
        (0.0, -t, -5.0),
        (d, d, 10.0),
        (d, -d, -10.0),
        (-h, 0.0, -5.0),
        (-h, d, 10.0),
        (-h, -d, -10.0),
    ];
    let g = &rig.geometry;
    let sq = g.grid_square_mm;
    // The plate: one square and a half-square margin beyond the outer inner corners.
    let half = [
        (g.grid_inner_corners[0] as f64 + 2.0) * sq / 2.0,
        (g.grid_inner_corners[1] as f64 + 2.0) * sq / 2.0,
    ];
    list.iter()
        .take(count.clamp(5, 9))
        .enumerate()
        .map(|(i, &(tx, ty, rz))| {
            // Lifted so that the plate's lowest corner clears the floor by 5 mm.
            let (a, b) = (tx.to_radians(), ty.to_radians());
            let drop = [[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]
                .iter()
                .map(|[sx, sy]| {
                    let (x, y) = (sx * half[0], sy * half[1]);
                    // z of Rz Ry Rx (x, y, 0): Rx gives z = y sin a, Ry mixes in x, Rz keeps z.
                    -x * b.sin() + y * a.sin() * b.cos()
                })
                .fold(0.0f64, |m, z| m.max(-z));
            BoardPose {
                index: i as u32 + 1,
                tilt_x_deg: tx.round() as i32,
                tilt_y_deg: ty.round() as i32,
                rotate_deg: rz as i32,
                lift_mm: if tx == 0.0 && ty == 0.0 {
                    0
                } else {
                    (drop + 5.0).ceil() as u32
                },
            }
        })
        .collect()
}

/// A lens pose's exposure: the grid exposure scaled by how much less (or more) of the
/// lamp's light falls on the tilted board than on the flat one, at the board's centre
/// (within 1/4..4 of the grid exposure and the camera's limits).
pub fn lens_exposure_us(rig: &Rig, p: &BoardPose) -> u32 {
    let g = &rig.geometry;
    let c = [
        (g.grid_inner_corners[0] as f64 - 1.0) / 2.0 * g.grid_square_mm,
        (g.grid_inner_corners[1] as f64 - 1.0) / 2.0 * g.grid_square_mm,
    ];
    let lamp = g.lamp_position_mm;
    let (a, b, r) = (
        (p.tilt_x_deg as f64).to_radians(),
        (p.tilt_y_deg as f64).to_radians(),
        (p.rotate_deg as f64).to_radians(),
    );
    // n = Rz Ry Rx z.
    let n0 = [b.sin() * a.cos(), -a.sin(), b.cos() * a.cos()];
    let n = [
        r.cos() * n0[0] - r.sin() * n0[1],
        r.sin() * n0[0] + r.cos() * n0[1],
        n0[2],
    ];
    let irradiance = |z: f64, n: [f64; 3]| {
        let l = [lamp[0] - c[0], lamp[1] - c[1], lamp[2] - z];
        let d2 = l[0] * l[0] + l[1] * l[1] + l[2] * l[2];
        (l[0] * n[0] + l[1] * n[1] + l[2] * n[2]).max(0.0) / d2.powf(1.5)
    };
    let flat = irradiance(0.0, [0.0, 0.0, 1.0]);
    let tilted = irradiance(p.lift_mm as f64, n);
    let scale = if tilted > 0.0 && flat > 0.0 {
        (flat / tilted).clamp(0.25, 4.0)
    } else {
        4.0
    };
    let us = rig.bracket.grid_exposure_us as f64 * scale;
    (us.round() as u32).clamp(rig.camera.min_exposure_us, rig.camera.max_exposure_us)
}

/// Frames an exposure change is assumed to cost in estimates (UVC latency + confirmation).
const SETTLE_FRAMES_ESTIMATE: u32 = 4;

impl Plan {
    /// The standard plan for a rig: lamp on and warm-up; the bracket (tile frames at each
    /// exposure, shortest first); lamp off and dark frames at each exposure (longest first,
    /// so the first needs no change); the tile removed, lamp on, the grid photo; lamp off.
    /// The tile is expected on the grid when the capture starts.
    pub fn for_rig(rig: &Rig) -> Plan {
        let b = &rig.bracket;
        let level = rig.lamp.level;
        let warm = rig.lamp.warmup_ms;
        let mut steps = vec![
            Step::IdentifyLamp,
            Step::LampOn { level },
            Step::WarmUp { ms: warm },
        ];
        for &us in &b.exposures_us {
            steps.push(Step::SetExposure { us });
            steps.push(Step::Capture {
                kind: FrameKind::Tile,
                count: b.frames_per_exposure,
            });
        }
        steps.push(Step::LampOff);
        if b.dark_frames_per_exposure > 0 {
            for &us in b.exposures_us.iter().rev() {
                steps.push(Step::SetExposure { us });
                steps.push(Step::Capture {
                    kind: FrameKind::Dark,
                    count: b.dark_frames_per_exposure,
                });
            }
        }
        steps.push(Step::Operator {
            action: OperatorAction::RemoveTile,
        });
        steps.push(Step::LampOn { level });
        steps.push(Step::WarmUp { ms: warm });
        steps.push(Step::SetExposure {
            us: b.grid_exposure_us,
        });
        steps.push(Step::Capture {
            kind: FrameKind::Grid,
            count: b.grid_frames,
        });
        steps.push(Step::LampOff);
        Plan { steps }
    }

    /// The lens calibration plan: the tile removed, the lamp on; for each pose the operator
    /// holds the board in it and the grid frames are taken (the exposure scaled so that
    /// the tilted board is about as bright as the flat grid photo: by the cosine of the
    /// lamp's light on it); lamp off; the board laid flat with the tile on it again, so
    /// the rig is ready for a capture. A session of this plan is a *lens session*: its grid
    /// frames are one view per pose ([`Plan::grid_groups`]).
    pub fn for_lens(rig: &Rig, poses: &[BoardPose]) -> Plan {
        let b = &rig.bracket;
        let level = rig.lamp.level;
        let mut steps = vec![
            Step::IdentifyLamp,
            Step::LampOn { level },
            Step::WarmUp {
                ms: rig.lamp.warmup_ms,
            },
        ];
        for p in poses {
            steps.push(Step::Operator {
                action: OperatorAction::ShowBoard(*p),
            });
            steps.push(Step::SetExposure {
                us: lens_exposure_us(rig, p),
            });
            steps.push(Step::Capture {
                kind: FrameKind::Grid,
                count: b.grid_frames.max(1),
            });
        }
        steps.push(Step::LampOff);
        steps.push(Step::Operator {
            action: OperatorAction::PlaceTile,
        });
        Plan { steps }
    }

    /// The board poses of a lens plan, in order (empty for any other plan).
    pub fn board_poses(&self) -> Vec<BoardPose> {
        self.steps
            .iter()
            .filter_map(|s| match s {
                Step::Operator {
                    action: OperatorAction::ShowBoard(p),
                } => Some(*p),
                _ => None,
            })
            .collect()
    }

    /// How a session's grid frames group into views: for each grid capture step, the
    /// board pose shown before it (None: the board flat on the floor) and its frame count,
    /// in the order the frames were taken.
    pub fn grid_groups(&self) -> Vec<(Option<BoardPose>, u32)> {
        let mut pose = None;
        let mut out = Vec::new();
        for s in &self.steps {
            match s {
                Step::Operator {
                    action: OperatorAction::ShowBoard(p),
                } => pose = Some(*p),
                Step::Operator { .. } => pose = None,
                Step::Capture {
                    kind: FrameKind::Grid,
                    count,
                } => out.push((pose, *count)),
                _ => {}
            }
        }
        out
    }

    /// Frames the plan keeps.
    pub fn frames(&self) -> u32 {
        self.steps
            .iter()
            .map(|s| {
                if let Step::Capture { count, .. } = s {
                    *count
                } else {
                    0
                }
            })
            .sum()
    }

    /// Problems running this plan on devices with these limits (empty when fine).
    pub fn check(&self, limits: &Limits) -> Vec<String> {
        let mut out = Vec::new();
        let mut exposure_set = false;
        let mut lamp_on = false;
        for (i, s) in self.steps.iter().enumerate() {
            let n = i + 1;
            match s {
                Step::SetExposure { us } => {
                    if *us < limits.min_exposure_us || *us > limits.max_exposure_us {
                        out.push(format!(
                            "step {n} ({s}): outside the camera's {}..{} µs",
                            limits.min_exposure_us, limits.max_exposure_us
                        ));
                    }
                    exposure_set = true;
                }
                Step::Capture { kind, count } => {
                    if !exposure_set {
                        out.push(format!("step {n} ({s}): no exposure set before it"));
                    }
                    if *count == 0 {
                        out.push(format!("step {n} ({s}): captures nothing"));
                    }
                    let needs_light = *kind != FrameKind::Dark;
                    if needs_light != lamp_on {
                        out.push(format!(
                            "step {n} ({s}): the lamp is {} but {} frames need it {}",
                            if lamp_on { "on" } else { "off" },
                            kind.as_str(),
                            if needs_light { "on" } else { "off" }
                        ));
                    }
                }
                Step::LampOn { level } => {
                    if *level > 1000 {
                        out.push(format!("step {n} ({s}): level must be 0..1000"));
                    }
                    lamp_on = true;
                }
                Step::LampOff => lamp_on = false,
                Step::IdentifyLamp | Step::WarmUp { .. } | Step::Operator { .. } => {}
            }
        }
        if self.frames() == 0 {
            out.push("the plan keeps no frames".into());
        }
        out
    }

    /// Problems with what the plan needs of the machine for a rig whose session would be
    /// written at `out`: more than [`MAX_PLAN_SECONDS`], or more disk than is free there
    /// (its upper bound, [`Estimate::disk_bytes_max`], against [`Disk::at`]). Empty when
    /// fine.
    pub fn check_resources(&self, rig: &Rig, out: &Path) -> Vec<String> {
        let est = self.estimate(rig);
        let mut out_problems = Vec::new();
        if est.seconds.is_nan() || est.seconds > MAX_PLAN_SECONDS {
            out_problems.push(format!(
                "the plan would take about {}, more than a day; shorten it (fewer or shorter exposures in bracket.exposures_us, fewer bracket.frames_per_exposure or dark frames, a shorter lamp.warmup_ms)",
                human_duration(est.seconds)
            ));
        }
        match Disk::at(out) {
            Ok(d) if d.free_bytes < est.disk_bytes_max => out_problems.push(format!(
                "the session needs up to {} on disk ({} frames of {}x{} at {} bits, stored uncompressed at worst) but {} has {} free; free space there or write the session elsewhere (--out)",
                human_bytes(est.disk_bytes_max),
                est.frames_kept,
                rig.camera.width,
                rig.camera.height,
                rig.camera.bit_depth,
                d.path.display(),
                human_bytes(d.free_bytes)
            )),
            Ok(_) => {}
            Err(e) => out_problems.push(format!(
                "cannot tell how much disk is free where the session would be written ({}): {e}",
                out.display()
            )),
        }
        out_problems
    }

    /// Estimate duration and disk use for a rig's camera.
    pub fn estimate(&self, rig: &Rig) -> Estimate {
        let period_us = 1e6 / rig.camera.fps;
        let frame_s = |us: u32| (us as f64).max(period_us) * 1e-6;
        let mut e = Estimate {
            frames_kept: 0,
            frames_settling: 0,
            seconds: 0.0,
            bytes_max: 0,
            disk_bytes_max: 0,
        };
        let mut current = 0u32;
        let c = &rig.camera;
        // Samples a pixel: 3 (RGB), or 1 for a monochrome camera.
        let pixels = c.width as u64
            * c.height as u64
            * c.channels() as u64
            * (c.bit_depth as u64).div_ceil(8);
        // PNG adds a filter byte per row; a stored (uncompressed) zlib block carries 5
        // bytes per 64 KiB; PNG chunks and the frame's manifest entry stay under 4 KiB.
        let png = pixels + c.height as u64;
        let disk_per_frame = png + png.div_ceil(65_535) * 5 + 4096;
        for s in &self.steps {
            match s {
                Step::SetExposure { us } => {
                    if *us != current {
                        e.frames_settling += SETTLE_FRAMES_ESTIMATE;
                        e.seconds += SETTLE_FRAMES_ESTIMATE as f64 * frame_s(*us);
                    }
                    current = *us;
                }
                Step::Capture { count, .. } => {
                    e.frames_kept += count;
                    e.seconds += *count as f64 * frame_s(current);
                    e.bytes_max += *count as u64 * pixels;
                    e.disk_bytes_max += *count as u64 * disk_per_frame;
                }
                Step::WarmUp { ms } => {
                    // The engine then checks on two frames that the light has settled.
                    e.frames_settling += 2;
                    e.seconds += *ms as f64 * 1e-3 + 2.0 * frame_s(current);
                }
                _ => {}
            }
        }
        e
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_read_as_people_say_them() {
        for (s, want) in [
            (0.0, "0 ms"),
            (0.25, "250 ms"),
            (0.9996, "1.0 s"),
            (2.44, "2.4 s"),
            (9.96, "10 s"),
            (45.2, "45 s"),
            (59.6, "1 min"),
            (200.0, "3 min 20 s"),
            (3599.6, "1 h"),
            (3900.0, "1 h 5 min"),
            (86_399.0, "1 d"),
            (95_700.0, "1 d 3 h"),
            (3.0 * 86_400.0, "3 d"),
        ] {
            assert_eq!(human_duration(s), want, "{s} s");
        }
    }

    #[test]
    fn sizes_read_as_people_say_them() {
        assert_eq!(human_bytes(12), "12 B");
        assert_eq!(human_bytes(850_000), "850 kB");
        assert_eq!(human_bytes(55_350_000), "55.4 MB");
        assert_eq!(human_bytes(2_400_000_000_000), "2.4 TB");
    }

    #[test]
    fn free_disk_is_measured_at_the_nearest_existing_folder() {
        let d = tempfile::tempdir().unwrap();
        let disk = Disk::at(&d.path().join("not/yet/there")).unwrap();
        assert_eq!(disk.path, d.path().canonicalize().unwrap());
        assert!(disk.free_bytes > 0);
        assert_eq!(
            Disk::at(Path::new("no-such-folder-glint/x")).unwrap().path,
            std::env::current_dir().unwrap()
        );
    }
}
