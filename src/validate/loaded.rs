//! What the renders need from a session, loaded once: shared by the stage
//! ([`super::load`]) and its figures ([`super::figures`]). A leaf: it names neither.

use glint_numerics::validate::compare::Region;
use glint_numerics::validate::render::{FloorAlbedo, View};

use crate::fit::types::Inputs;
use crate::hdr::Bracket;

/// What the renders need from a session, loaded once.
pub struct Loaded {
    pub inputs: Inputs,
    pub tiles: Bracket,
    pub dark: Vec<[f64; 3]>,
    pub response: crate::hdr::response::Response,
    pub view: View,
    pub region: Region,
    pub floor: FloorAlbedo,
}
