//! Exposure latency: a new exposure reaches the frames k frames late. Whatever k, and
//! whether or not frames report their exposure, every kept frame must have been taken at
//! the requested exposure, as the simulator's ledger (its ground truth) records.

use std::collections::HashMap;

use glint::capture::{FrameKind, Verification};
use glint_mock::SceneKind;

use super::util::{ledger, record, set, small_table, tempdir};

fn check(latency: u32, metadata: bool) {
    let dir = tempdir();
    let mut t = small_table();
    set(
        &mut t,
        "mock.sensor.exposure_latency_frames",
        latency as i64,
    );
    set(&mut t, "mock.sensor.reports_exposure", metadata);
    let rec = record(dir.path(), &t)
        .unwrap_or_else(|e| panic!("latency {latency}, metadata {metadata}: {e}"));
    let ledger = ledger(&rec);
    let truth: HashMap<u64, _> = ledger.iter().map(|e| (e.sequence, *e)).collect();
    assert_eq!(rec.manifest.frames.len(), 15);
    for f in &rec.manifest.frames {
        let e = truth[&f.sequence];
        let what = format!(
            "latency {latency}, metadata {metadata}, frame {} ({})",
            f.index, f.file
        );
        assert!(e.delivered, "{what}");
        assert_eq!(
            e.true_exposure_us, f.exposure_requested_us,
            "{what}: kept a frame at the wrong exposure"
        );
        assert_eq!(f.exposure_reported_us, f.exposure_requested_us, "{what}");
        match f.kind {
            FrameKind::Dark => assert_eq!(e.lamp_output, 0.0, "{what}: a dark frame was lit"),
            _ => assert_eq!(e.lamp_output, 1.0, "{what}: lamp not at full output"),
        }
        assert_eq!(
            e.scene == SceneKind::Grid,
            f.kind == FrameKind::Grid,
            "{what}: wrong scene"
        );
        if metadata {
            assert_eq!(f.exposure_verified_by, Verification::Metadata, "{what}");
        } else {
            assert!(
                matches!(
                    f.exposure_verified_by,
                    Verification::ImageStatistics | Verification::MeasuredLatency
                ),
                "{what}: {:?}",
                f.exposure_verified_by
            );
        }
    }
    // The test can fail: frames at the old exposure were delivered and had to be skipped.
    let kept: std::collections::HashSet<u64> =
        rec.manifest.frames.iter().map(|f| f.sequence).collect();
    let skipped_wrong = ledger
        .iter()
        .filter(|e| e.delivered && !kept.contains(&e.sequence))
        .count();
    assert!(skipped_wrong > 0);
    if metadata {
        assert_eq!(
            rec.summary.latency_frames,
            Some(latency),
            "latency measured from metadata"
        );
    } else if latency > 0 {
        assert_eq!(
            rec.summary.latency_frames,
            Some(latency),
            "latency measured from the image"
        );
    }
}

#[test]
fn latency_0_to_3_with_frame_metadata() {
    for k in [0, 1, 2, 3] {
        check(k, true);
    }
}

#[test]
fn latency_0_to_3_from_image_statistics_alone() {
    for k in [0, 1, 2, 3] {
        check(k, false);
    }
}

#[test]
fn a_long_latency_beyond_the_settle_limit_is_an_error() {
    let dir = tempdir();
    let mut t = small_table();
    set(&mut t, "mock.sensor.exposure_latency_frames", 8);
    set(&mut t, "camera.settle_max_frames", 5);
    let e = record(dir.path(), &t).err().unwrap();
    assert!(
        e.to_string()
            .contains("did not apply exposure 125 µs within 5 frames"),
        "{e}"
    );
}
