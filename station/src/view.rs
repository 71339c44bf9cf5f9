//! The page's view model: everything the browser draws, computed here from
//! the wire messages by pure functions (so they are unit-tested), serialized
//! as one compact JSON snapshot per push.
//!
//! Coordinates are the fused map's: the reference vehicle's body frame, FRD
//! (x forward, y starboard, z down), metres. The top view shows x/y, the side
//! view x/z; the page only scales and flips them.

#[cfg(test)]
mod fixtures;
mod geometry;
mod pairing;
mod rates;

pub use geometry::{
    ellipse_of, pose_error, position_block, truth_relative_to, Ellipse, PlacedPose, ELLIPSE_SIGMAS,
    MAX_DRAWN_SIGMA_M,
};
pub use pairing::{nearest_truth, pair_map_with_truth, valid_at_ns, TRUTH_MATCH_NS};
pub use rates::{camera_views, CameraView, NodeReports, RATE_WINDOW_REPORTS};

use proto::config::Fleet;
use proto::{
    EdgeReport, FleetMap, RejectReason, SimTruth, VehicleEstimate, VehicleId, VehicleState,
};
use serde::Serialize;
use std::collections::BTreeMap;

/// Everything the page shows about one vehicle.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct VehicleView {
    pub id: VehicleId,
    pub name: String,
    pub hull_length_m: f64,
    pub hull_diameter_m: f64,
    pub is_reference: bool,
    /// `live`, `stale`, `unobserved` (from the map) or `absent` (not in the map).
    pub state: &'static str,
    /// Its node's liveliness token (`None`: never seen either way).
    pub alive: Option<bool>,
    /// Fused pose, when the map localizes it.
    pub estimate: Option<PlacedPose>,
    pub ellipse_top: Option<Ellipse>,
    pub ellipse_side: Option<Ellipse>,
    /// 1-sigma position uncertainty along x, y, z (metres).
    pub sigma_m: Option<[f64; 3]>,
    /// Map time minus the newest observation involving it (seconds).
    pub last_seen_age_s: Option<f64>,
    /// Ground truth in the map's reference frame (simulation only).
    pub truth: Option<PlacedPose>,
    pub error_mm: Option<f64>,
    pub error_deg: Option<f64>,
    pub cameras: Vec<CameraView>,
    /// Seconds since its node's last status report.
    pub status_age_s: Option<f64>,
    pub observations_sent: Option<u64>,
    pub messages_rejected: Option<u64>,
}

/// Edges of the last map with the same observer, target, camera and verdict, merged.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EdgeView {
    pub observer: VehicleId,
    pub target: Option<VehicleId>,
    pub camera: u8,
    pub marker: u32,
    /// `accepted` or the rejection reason (`ChiSquare`, `FlippedHypothesis`, …).
    pub verdict: String,
    pub count: usize,
    /// Largest finite chi-square of the merged edges (`None`: not computed).
    pub max_chi2: Option<f64>,
}

/// The name the page colours an edge by.
pub fn verdict_name(rejected: &Option<RejectReason>) -> String {
    match rejected {
        None => "accepted".into(),
        Some(r) => format!("{r:?}"),
    }
}

/// Merge a map's edges by (observer, target, camera, marker, verdict).
pub fn edge_views(edges: &[EdgeReport]) -> Vec<EdgeView> {
    let mut merged: BTreeMap<(VehicleId, Option<VehicleId>, u8, u32, String), EdgeView> =
        BTreeMap::new();
    for e in edges {
        let verdict = verdict_name(&e.rejected);
        let key = (
            e.observer,
            e.target_vehicle,
            e.camera,
            e.target_marker,
            verdict.clone(),
        );
        let chi2 = e.chi2.is_finite().then_some(e.chi2);
        let v = merged.entry(key).or_insert(EdgeView {
            observer: e.observer,
            target: e.target_vehicle,
            camera: e.camera,
            marker: e.target_marker,
            verdict,
            count: 0,
            max_chi2: None,
        });
        v.count += 1;
        v.max_chi2 = match (v.max_chi2, chi2) {
            (Some(a), Some(b)) => Some(a.max(b)),
            (a, b) => a.or(b),
        };
    }
    merged.into_values().collect()
}

/// The map's identity and timing.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MapInfo {
    pub producer: String,
    pub seq: u64,
    pub stamp_s: f64,
    pub solve_ms: f64,
    /// Seconds since the station received it (wall clock).
    pub age_s: f64,
    pub edges_accepted: usize,
    pub edges_rejected: usize,
}

/// The whole page state at one instant.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SwarmView {
    /// Increments with every snapshot the station publishes.
    pub update: u64,
    pub fleet: String,
    pub reference: VehicleId,
    pub ellipse_sigmas: f64,
    pub map: Option<MapInfo>,
    /// Simulation time of the ground truth shown (`None`: no simulator).
    pub truth_stamp_s: Option<f64>,
    pub vehicles: Vec<VehicleView>,
    pub edges: Vec<EdgeView>,
    /// Edges of the last map per verdict, for the legend.
    pub verdicts: BTreeMap<String, usize>,
    /// Messages the station could not decode (wrong version, corrupt…).
    pub messages_rejected: u64,
}

/// What the station knows at one instant.
#[derive(Debug, Clone, Copy)]
pub struct ViewInputs<'a> {
    pub fleet: &'a Fleet,
    pub map: Option<(&'a FleetMap, f64)>,
    /// Ground truth nearest in time to the map (or the newest, without a map).
    pub truth: Option<&'a SimTruth>,
    pub nodes: &'a BTreeMap<VehicleId, NodeReports>,
    pub alive: &'a BTreeMap<VehicleId, bool>,
    pub messages_rejected: u64,
}

fn state_name(s: VehicleState) -> &'static str {
    match s {
        VehicleState::Live => "live",
        VehicleState::Stale => "stale",
        VehicleState::Unobserved => "unobserved",
        VehicleState::Predicted => "predicted",
    }
}

/// Build the snapshot number `update`.
pub fn build_view(inputs: &ViewInputs<'_>, update: u64) -> SwarmView {
    let fleet = inputs.fleet;
    let reference = inputs
        .map
        .map_or(fleet.reference_vehicle, |(m, _)| m.reference);
    let truth = inputs
        .truth
        .map(|t| truth_relative_to(t, reference))
        .unwrap_or_default();
    let estimates: BTreeMap<VehicleId, &VehicleEstimate> = inputs
        .map
        .map(|(m, _)| m.vehicles.iter().map(|v| (v.vehicle, v)).collect())
        .unwrap_or_default();
    let vehicles = fleet
        .vehicles
        .iter()
        .map(|spec| {
            let est = estimates.get(&spec.id).copied();
            let localized =
                est.filter(|e| e.vehicle == reference || e.state != VehicleState::Unobserved);
            let truth_pose = truth.get(&spec.id);
            let error = match (localized, truth_pose) {
                (Some(e), Some(t)) => Some(pose_error(&e.reference_from_vehicle, t)),
                _ => None,
            };
            let node = inputs.nodes.get(&spec.id);
            let status = node.and_then(|n| n.current());
            VehicleView {
                id: spec.id,
                name: spec.name.clone(),
                hull_length_m: spec.hull.length_m,
                hull_diameter_m: spec.hull.diameter_m,
                is_reference: spec.id == reference,
                state: est.map_or("absent", |e| state_name(e.state)),
                alive: inputs.alive.get(&spec.id).copied(),
                estimate: localized.map(|e| PlacedPose::of(&e.reference_from_vehicle)),
                ellipse_top: localized
                    .and_then(|e| ellipse_of(&position_block(&e.covariance, 0, 1), ELLIPSE_SIGMAS)),
                ellipse_side: localized
                    .and_then(|e| ellipse_of(&position_block(&e.covariance, 0, 2), ELLIPSE_SIGMAS)),
                sigma_m: localized.map(|e| [0, 1, 2].map(|i| e.covariance[(i, i)].max(0.0).sqrt())),
                last_seen_age_s: match (est, inputs.map) {
                    (Some(e), Some((m, _))) if e.last_seen_ns > 0 => {
                        Some(m.stamp_ns.saturating_sub(e.last_seen_ns) as f64 * 1e-9)
                    }
                    _ => None,
                },
                truth: truth_pose.map(PlacedPose::of),
                error_mm: error.map(|(dt, _)| dt * 1e3),
                error_deg: error.map(|(_, dr)| dr.to_degrees()),
                cameras: node.map(NodeReports::camera_views).unwrap_or_default(),
                status_age_s: status.and(node.map(|n| n.age_s)),
                observations_sent: status.map(|s| s.observations_sent),
                messages_rejected: status.map(|s| s.messages_rejected),
            }
        })
        .collect();
    let (edges, verdicts, map) = match inputs.map {
        Some((m, age_s)) => {
            let mut verdicts = BTreeMap::new();
            for e in &m.edges {
                *verdicts.entry(verdict_name(&e.rejected)).or_insert(0) += 1;
            }
            let accepted = m.edges.iter().filter(|e| e.rejected.is_none()).count();
            (
                edge_views(&m.edges),
                verdicts,
                Some(MapInfo {
                    producer: m.producer.clone(),
                    seq: m.seq,
                    stamp_s: m.stamp_ns as f64 * 1e-9,
                    solve_ms: m.solve_time_us as f64 * 1e-3,
                    age_s,
                    edges_accepted: accepted,
                    edges_rejected: m.edges.len() - accepted,
                }),
            )
        }
        None => (Vec::new(), BTreeMap::new(), None),
    };
    SwarmView {
        update,
        fleet: fleet.name.clone(),
        reference,
        ellipse_sigmas: ELLIPSE_SIGMAS,
        map,
        truth_stamp_s: inputs.truth.map(|t| t.stamp_ns as f64 * 1e-9),
        vehicles,
        edges,
        verdicts,
        messages_rejected: inputs.messages_rejected,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::view::fixtures::{edge, paper, pose, status, truth_of};
    use nalgebra::Matrix6;
    use proto::geometry::Pose;

    #[test]
    fn edges_merge_by_pair_and_verdict() {
        let edges = [
            edge(10, 15, None, 1.0),
            edge(10, 15, None, f64::NAN),
            edge(10, 15, Some(RejectReason::FlippedHypothesis), 40.0),
            edge(15, 17, Some(RejectReason::ChiSquare), 30.0),
            edge(15, 17, Some(RejectReason::ChiSquare), 90.0),
        ];
        let v = edge_views(&edges);
        assert_eq!(v.len(), 3, "{v:?}");
        let acc = v.iter().find(|e| e.verdict == "accepted").unwrap();
        assert_eq!((acc.count, acc.max_chi2), (2, Some(1.0)));
        let chi = v.iter().find(|e| e.verdict == "ChiSquare").unwrap();
        assert_eq!(
            (chi.observer, chi.target, chi.count, chi.max_chi2),
            (15, Some(17), 2, Some(90.0))
        );
        assert!(v.iter().any(|e| e.verdict == "FlippedHypothesis"));
    }

    fn estimate(
        vehicle: VehicleId,
        state: VehicleState,
        p: Pose,
        sigma_m: f64,
        last_seen_ns: u64,
    ) -> VehicleEstimate {
        VehicleEstimate {
            vehicle,
            state,
            reference_from_vehicle: p,
            covariance: Matrix6::identity() * sigma_m * sigma_m,
            last_seen_ns,
        }
    }

    #[test]
    fn view_shows_every_fleet_vehicle_with_error_against_truth() {
        let fleet = paper();
        let map = FleetMap {
            fleet: "paper".into(),
            producer: "central".into(),
            seq: 41,
            stamp_ns: 12_000_000_000,
            reference: 10,
            vehicles: vec![
                estimate(
                    10,
                    VehicleState::Live,
                    Pose::identity(),
                    0.0,
                    12_000_000_000,
                ),
                estimate(
                    15,
                    VehicleState::Live,
                    pose([0.0, 1.76, 0.0], 0.0),
                    0.01,
                    11_500_000_000,
                ),
                estimate(17, VehicleState::Unobserved, Pose::identity(), 100.0, 0),
            ],
            edges: vec![
                edge(10, 15, None, 1.0),
                edge(10, 15, Some(RejectReason::FlippedHypothesis), 50.0),
            ],
            solve_time_us: 2500,
        };
        let truth = truth_of(
            &[
                (10, pose([5.0, 0.0, 2.0], 0.0)),
                (15, pose([5.0, 1.75, 2.0], 0.0)),
                (17, pose([5.0, 3.5, 2.0], 0.0)),
            ],
            12_000_000_000,
        );
        let mut nodes = BTreeMap::new();
        let mut reports = NodeReports::default();
        reports.push(status(1.0, 2, 1));
        reports.push(status(2.0, 4, 3));
        reports.age_s = 0.4;
        nodes.insert(15, reports);
        let alive = BTreeMap::from([(10, true), (15, true), (17, false)]);
        let view = build_view(
            &ViewInputs {
                fleet: &fleet,
                map: Some((&map, 0.1)),
                truth: Some(&truth),
                nodes: &nodes,
                alive: &alive,
                messages_rejected: 0,
            },
            5,
        );
        assert_eq!(
            view.vehicles.iter().map(|v| v.id).collect::<Vec<_>>(),
            [10, 15, 17]
        );
        let v15 = &view.vehicles[1];
        assert_eq!(v15.state, "live");
        assert!((v15.error_mm.unwrap() - 10.0).abs() < 1e-6, "{v15:?}");
        assert!((v15.last_seen_age_s.unwrap() - 0.5).abs() < 1e-9);
        let e = v15.ellipse_top.unwrap();
        assert!((e.semi_major_m - 0.03).abs() < 1e-12);
        assert_eq!(v15.cameras[0].detection_rate_hz, Some(2.0));
        assert_eq!(v15.status_age_s, Some(0.4));
        let v17 = &view.vehicles[2];
        assert_eq!((v17.state, v17.alive), ("unobserved", Some(false)));
        assert!(v17.estimate.is_none() && v17.error_mm.is_none() && v17.ellipse_top.is_none());
        assert!(
            v17.truth.is_some(),
            "the ghost is drawn even when the estimate is missing"
        );
        assert!(view.vehicles[0].is_reference);
        assert_eq!(view.verdicts["FlippedHypothesis"], 1);
        let info = view.map.as_ref().unwrap();
        assert_eq!(
            (info.seq, info.edges_accepted, info.edges_rejected),
            (41, 1, 1)
        );
        let json = serde_json::to_string(&view).unwrap();
        assert!(json.contains("\"update\":5"), "{json}");
        assert!(!json.contains('\n'), "one SSE data line");
    }

    #[test]
    fn view_without_a_map_lists_the_fleet_as_absent() {
        let fleet = paper();
        let view = build_view(
            &ViewInputs {
                fleet: &fleet,
                map: None,
                truth: None,
                nodes: &BTreeMap::new(),
                alive: &BTreeMap::new(),
                messages_rejected: 3,
            },
            1,
        );
        assert_eq!(view.vehicles.len(), 3);
        assert!(view
            .vehicles
            .iter()
            .all(|v| v.state == "absent" && v.estimate.is_none()));
        assert!(view.map.is_none() && view.edges.is_empty());
        assert_eq!(view.messages_rejected, 3);
    }
}
