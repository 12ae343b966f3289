//! Capture plans: an experiment written down as data, a list of steps that never touch
//! hardware. A plan can be checked against a rig's limits and its duration and disk use
//! estimated with no devices at all (`glint capture --dry-run`); the engine runs it.

use serde::{Deserialize, Serialize};

use crate::devices::OperatorAction;
use crate::rig::Rig;

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
            Step::WarmUp { ms } => write!(f, "lamp warm-up {ms} ms"),
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
    /// Upper bound: uncompressed size of the kept frames (PNG is usually 40–70% of it).
    pub bytes_max: u64,
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

    /// Estimate duration and disk use for a rig's camera.
    pub fn estimate(&self, rig: &Rig) -> Estimate {
        let period_us = 1e6 / rig.camera.fps;
        let frame_s = |us: u32| (us as f64).max(period_us) * 1e-6;
        let mut e = Estimate {
            frames_kept: 0,
            frames_settling: 0,
            seconds: 0.0,
            bytes_max: 0,
        };
        let mut current = 0u32;
        let bytes_per_frame = rig.camera.width as u64
            * rig.camera.height as u64
            * 3
            * (rig.camera.bit_depth as u64 / 8);
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
                    e.bytes_max += *count as u64 * bytes_per_frame;
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
