//! Which camera backends this build has, and what it can say about opening a rig's devices
//! before it opens them ([`check_backends`]).

#[cfg(feature = "nokhwa")]
use crate::nokhwa_cam;
use crate::rig::{CameraBackend, Rig};
use crate::v4l2_rules;

/// Whether this Glint was built with the V4L2 camera backend (cargo feature `v4l2`).
pub const V4L2_BUILT: bool = cfg!(feature = "v4l2");

/// What a build without the V4L2 backend says about a V4L2 rig.
pub const V4L2_MISSING: &str = "this Glint was built without the V4L2 backend; rebuild with `cargo build --release --features v4l2` (needs libclang-dev)";

/// Whether this Glint was built with the nokhwa camera backend (cargo feature `nokhwa`).
pub const NOKHWA_BUILT: bool = cfg!(feature = "nokhwa");

/// What a build without the nokhwa backend says about a nokhwa rig.
pub const NOKHWA_MISSING: &str = "this Glint was built without the nokhwa backend; rebuild with `cargo build --release --features nokhwa` (on Linux it needs libclang-dev)";

/// What this build can say about opening a rig's devices before it opens them: problems
/// (the devices cannot be opened by this build at all) and warnings (they can, but not
/// exactly as the rig asks). `glint rig check` and the dry runs report both; [`open`]
/// refuses on the same problems.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct BackendCheck {
    pub problems: Vec<String>,
    pub warnings: Vec<String>,
}

/// Check that this build has the backends a rig names (see [`BackendCheck`]).
pub fn check_backends(rig: &Rig) -> BackendCheck {
    let mut c = BackendCheck::default();
    if rig.camera.backend == CameraBackend::V4l2 {
        if V4L2_BUILT {
            c.warnings = v4l2_rules::exposure_snap_warnings(rig);
        } else {
            c.problems
                .push(format!("camera.backend = \"v4l2\": {V4L2_MISSING}"));
        }
    }
    if rig.camera.backend == CameraBackend::Nokhwa {
        #[cfg(feature = "nokhwa")]
        {
            c.problems = nokhwa_cam::problems(rig);
            c.warnings = v4l2_rules::exposure_snap_warnings(rig);
        }
        #[cfg(not(feature = "nokhwa"))]
        c.problems
            .push(format!("camera.backend = \"nokhwa\": {NOKHWA_MISSING}"));
    }
    if let Ok(p) = rig.lamp.resolved_protocol() {
        let level = rig.lamp.level;
        let device = p.to_device(level);
        let back = p.from_device(device);
        if back != level {
            c.warnings.push(format!(
                "lamp.level = {level} is {device} on the lamp's {}..{} scale (protocol preset {}): it is set and reads back as {back}",
                p.level_range[0],
                p.level_range[1],
                p.preset.name()
            ));
        }
    }
    c
}
