//! Hand-made inputs for the unit tests of the solve's steps.

use super::frames::{Frame, TrackKey};
use crate::consistency::Candidate;
use crate::window::{Admission, Stored};
use proto::config::Fleet;
use proto::geometry::{Cov6, Pose};
use proto::{CodeSet, ImageQuality, Observation, PoseHypothesis, VehicleId};

/// One second, ns.
pub const S: u64 = 1_000_000_000;

/// Admission limits of the tests: a 2 s window, 0.25 s of clock skew, σ ≤ 5.
pub const LIMITS: Admission = Admission {
    window_ns: 2 * S,
    link_window_ns: 8 * S,
    max_clock_skew_ns: S / 4,
    max_std: 5.0,
    max_per_observer: crate::DEFAULT_MAX_WINDOW_PER_OBSERVER,
};

/// `configs/fleets/paper.toml`: vehicles 10, 15 and 17.
pub fn paper_fleet() -> Fleet {
    Fleet::load(
        &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/fleets/paper.toml"),
    )
    .expect("paper fleet loads")
}

/// Covariance of every hand-made observation: σ = 1 cm and 0.57° per axis.
pub const COV: f64 = 1e-4;

/// An observation of `marker` by `observer`'s `camera` at `stamp_ns`, no alternative.
pub fn observation(
    observer: VehicleId,
    camera: u8,
    marker: u32,
    stamp_ns: u64,
    observer_from_target: Pose,
) -> Observation {
    Observation {
        observer,
        camera,
        codes: CodeSet::Shoal,
        target_marker: marker,
        target_vehicle: None,
        stamp_ns,
        frame_seq: stamp_ns / 100_000_000,
        observer_from_target,
        covariance: Cov6::identity() * COV,
        reprojection_rms_px: 0.5,
        alternative: None,
        corner_count: 12,
        corners_px: Vec::new(),
        quality: ImageQuality::default(),
        predicted: false,
    }
}

/// `obs` with a planar-flip alternative `alt`.
pub fn with_alternative(mut obs: Observation, alt: Pose) -> Observation {
    obs.alternative = Some(PoseHypothesis {
        observer_from_target: alt,
        covariance: obs.covariance,
        reprojection_rms_px: 0.6,
    });
    obs
}

pub fn stored(obs: Observation, target: VehicleId) -> Stored {
    Stored {
        obs,
        target,
        linked: false,
    }
}

/// Frame `index` of `observer`'s camera 0 seeing `target`'s marker `target`
/// at `stamp_ns`: primary `pose`, optional alternative `alt`.
pub fn frame(
    index: usize,
    observer: VehicleId,
    target: VehicleId,
    stamp_ns: u64,
    pose: Pose,
    alt: Option<Pose>,
) -> Frame {
    let cov = Cov6::identity() * COV;
    Frame {
        observer,
        target,
        stamp_ns,
        track: TrackKey {
            observer,
            camera: 0,
            codes: CodeSet::Shoal.name(),
            marker: target,
        },
        hyps: [
            Candidate::new(index, 0, pose, cov),
            alt.and_then(|a| Candidate::new(index, 1, a, cov)),
        ],
        inflation: [0.0; 2],
    }
}
