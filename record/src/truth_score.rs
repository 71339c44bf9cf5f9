//! Re-fused maps scored against the log's own ground truth (`SimTruth`, in
//! logs of simulated trials): how far each Live vehicle is from where the
//! simulator put it, whether a map put one on a planar-flip twin, and whether
//! the reported covariance owns up to the error (NEES).
//!
//! A map is scored against the truth of its newest accepted observation's
//! capture (the freshest information it holds), as the demo scores its
//! pairs. A log holds a tick's truth after that tick's frames' observations
//! (the simulator publishes it once the frames are rendered), so a map waits
//! for a truth at or after that capture before it is scored. A log without
//! that tick's truth (a message lost on the way) leaves the map unscored
//! and counted: the nearest other tick's truth is where
//! the vehicles were up to a tick earlier or later, and scoring against it
//! reads their motion as error.

use proto::geometry::difference;
use proto::{FleetMap, SimTruth, VehicleState};
use std::collections::VecDeque;

/// A Live vehicle this far off in rotation is on a planar-flip twin, degrees.
pub const FLIP_ERROR_DEG: f64 = 10.0;
/// Truth messages kept to match maps with (a few seconds of ticks).
const TRUTHS_KEPT: usize = 256;
/// A truth this close to a map's capture is that capture's (the simulator
/// stamps a tick's frames and its truth alike).
pub const SAME_INSTANT_NS: u64 = 1_000_000;

/// The re-fused maps against the log's ground truth.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct TruthScore {
    pub maps_scored: u64,
    /// Maps whose capture's truth is not in the log (not scored).
    pub maps_without_truth: u64,
    /// Maps with a Live vehicle more than [`FLIP_ERROR_DEG`] off.
    pub maps_flipped: u64,
    /// Live non-reference vehicle estimates scored.
    pub estimates_scored: u64,
    pub mean_position_error_m: f64,
    pub max_position_error_m: f64,
    /// Mean of `eᵀΣ⁻¹e` (6 DoF: 6 when the covariance is the error's own).
    pub mean_nees: f64,
}

#[derive(Debug, Default)]
pub(crate) struct TruthAcc {
    truths: VecDeque<SimTruth>,
    /// Maps waiting for the truth of their newest capture.
    pending: VecDeque<(u64, FleetMap)>,
    score: TruthScore,
    position_sum: f64,
    nees_sum: f64,
    nees_n: u64,
}

impl TruthAcc {
    pub fn add_truth(&mut self, t: SimTruth) {
        if self.truths.len() == TRUTHS_KEPT {
            self.truths.pop_front();
        }
        let newest = t.stamp_ns;
        self.truths.push_back(t);
        while self.pending.front().is_some_and(|(at, _)| *at <= newest) {
            if let Some((at, map)) = self.pending.pop_front() {
                self.score(at, &map);
            }
        }
    }

    pub fn add_map(&mut self, map: &FleetMap) {
        let valid_at = map.valid_at_ns();
        let known = self.truths.back().is_some_and(|t| t.stamp_ns >= valid_at);
        if known {
            self.score(valid_at, map);
        } else {
            if self.pending.len() == TRUTHS_KEPT {
                if let Some((at, old)) = self.pending.pop_front() {
                    self.score(at, &old);
                }
            }
            self.pending.push_back((valid_at, map.clone()));
        }
    }

    fn score(&mut self, valid_at: u64, map: &FleetMap) {
        let Some(truth) = self
            .truths
            .iter()
            .min_by_key(|t| t.stamp_ns.abs_diff(valid_at))
        else {
            return;
        };
        if truth.stamp_ns.abs_diff(valid_at) > SAME_INSTANT_NS {
            self.score.maps_without_truth += 1;
            return;
        }
        let pose = |v| {
            truth
                .vehicles
                .iter()
                .find(|t| t.vehicle == v)
                .map(|t| t.world_from_body)
        };
        let Some(world_from_ref) = pose(map.reference) else {
            return;
        };
        self.score.maps_scored += 1;
        let mut flipped = false;
        for v in map
            .vehicles
            .iter()
            .filter(|v| v.state == VehicleState::Live && v.vehicle != map.reference)
        {
            let Some(w) = pose(v.vehicle) else { continue };
            let e = difference(&v.reference_from_vehicle, &(world_from_ref.inverse() * w));
            let position = e.fixed_rows::<3>(0).norm();
            flipped |= e.fixed_rows::<3>(3).norm().to_degrees() > FLIP_ERROR_DEG;
            self.score.estimates_scored += 1;
            self.position_sum += position;
            self.score.max_position_error_m = self.score.max_position_error_m.max(position);
            if let Some(info) = v.covariance.try_inverse() {
                self.nees_sum += (e.transpose() * info * e)[0];
                self.nees_n += 1;
            }
        }
        self.score.maps_flipped += u64::from(flipped);
    }

    /// The score, or `None` when the log had no truth to score against.
    pub fn finish(mut self) -> Option<TruthScore> {
        for (at, map) in std::mem::take(&mut self.pending) {
            self.score(at, &map);
        }
        if self.score.maps_scored == 0 && self.score.maps_without_truth == 0 {
            return None;
        }
        let n = self.score.estimates_scored.max(1) as f64;
        self.score.mean_position_error_m = self.position_sum / n;
        self.score.mean_nees = if self.nees_n > 0 {
            self.nees_sum / self.nees_n as f64
        } else {
            f64::NAN
        };
        Some(self.score)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proto::geometry::{pose_from_xyz_rpy, Cov6, Pose};
    use proto::{EdgeReport, VehicleEstimate, VehicleTruth};

    const S: u64 = 1_000_000_000;

    fn truth(stamp_ns: u64, x15: f64) -> SimTruth {
        let v = |vehicle, world_from_body| VehicleTruth {
            vehicle,
            world_from_body,
            velocity_body: [0.0; 3],
        };
        SimTruth {
            stamp_ns,
            tick: stamp_ns / S,
            water_c_per_m: 0.5,
            vehicles: vec![
                v(10, Pose::identity()),
                v(15, pose_from_xyz_rpy([x15, 2.0, 0.0], [0.0; 3])),
            ],
            visible: vec![],
        }
    }

    /// A map at `stamp_ns` whose newest accepted observation was captured then, putting 15 at `pose`.
    fn map(stamp_ns: u64, pose: Pose) -> FleetMap {
        let estimate = |vehicle, reference_from_vehicle| VehicleEstimate {
            vehicle,
            state: VehicleState::Live,
            reference_from_vehicle,
            covariance: Cov6::identity() * 1e-4,
            last_seen_ns: stamp_ns,
        };
        FleetMap {
            fleet: "paper".into(),
            producer: "central".into(),
            seq: 1,
            stamp_ns,
            reference: 10,
            vehicles: vec![estimate(10, Pose::identity()), estimate(15, pose)],
            edges: vec![EdgeReport {
                observer: 10,
                camera: 0,
                target_marker: 15,
                target_vehicle: Some(15),
                stamp_ns,
                frame_seq: 0,
                rejected: None,
                chi2: 0.0,
            }],
            solve_time_us: 0,
        }
    }

    #[test]
    fn a_map_waits_for_its_captures_truth_and_a_twin_counts_as_flipped() {
        let mut acc = TruthAcc::default();
        acc.add_truth(truth(0, 0.0));
        // 15 moved 0.5 m by t = 1 s; the map of t = 1 s comes before that truth.
        let at_1 = pose_from_xyz_rpy([0.5, 2.0, 0.0], [0.0; 3]);
        acc.add_map(&map(S, at_1));
        acc.add_truth(truth(S, 0.5));
        // A map on a twin 40° off, scored at once (its truth is known).
        acc.add_map(&map(S, at_1 * pose_from_xyz_rpy([0.0; 3], [0.0, 0.7, 0.0])));
        let s = acc.finish().expect("scored");
        assert_eq!(
            (s.maps_scored, s.maps_flipped, s.estimates_scored),
            (2, 1, 2)
        );
        assert!(s.max_position_error_m < 1e-9, "{s:?}");
        // A tick whose truth the log lost: its map is counted, not scored
        // against the next tick's truth (0.5 m away by then).
        let mut lost = TruthAcc::default();
        lost.add_truth(truth(0, 0.0));
        lost.add_map(&map(S, at_1));
        lost.add_truth(truth(2 * S, 1.0));
        lost.add_map(&map(2 * S, pose_from_xyz_rpy([1.0, 2.0, 0.0], [0.0; 3])));
        let s = lost.finish().expect("one map scored");
        assert_eq!((s.maps_scored, s.maps_without_truth), (1, 1), "{s:?}");
        assert!(s.max_position_error_m < 1e-9, "{s:?}");
        // Without a truth, nothing is scored.
        let mut none = TruthAcc::default();
        none.add_map(&map(S, at_1));
        assert_eq!(none.finish(), None);
    }
}
