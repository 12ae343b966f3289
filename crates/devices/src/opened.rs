//! The devices of a rig, opened: what [`crate::open`] hands out.

use std::sync::{Arc, Mutex};

use glint_mock::{LampFirmware, LedgerEntry};

use crate::traits::{Camera, Lamp, Operator};

/// The devices of a rig, opened.
pub struct Devices {
    pub camera: Box<dyn Camera>,
    pub lamp: Box<dyn Lamp>,
    pub operator: Box<dyn Operator>,
    /// The simulated lab behind mock devices (its firmware, its truth), kept alive here.
    pub lab: Option<LabHandle>,
}

/// What stays of the simulated lab once its devices are handed out: the firmware (kept
/// running) and the truth, for tests.
pub struct LabHandle {
    /// The in-process firmware (none when the lamp is a serial one elsewhere).
    pub firmware: Option<LampFirmware>,
    /// Every frame the simulated sensor produced, with its true exposure.
    pub ledger: Arc<Mutex<Vec<LedgerEntry>>>,
}
