//! The page's view model: everything the browser draws, computed here from
//! the wire messages by pure functions (so they are unit-tested), serialized
//! as one compact JSON snapshot per push.
//!
//! Coordinates are the fused map's: the reference vehicle's body frame, FRD
//! (x forward, y starboard, z down), metres. The top view shows x/y, the side
//! view x/z; the page only scales and flips them.

use nalgebra::{Matrix2, UnitQuaternion, Vector3};
use proto::config::Fleet;
use proto::geometry::{Cov6, Pose};
use proto::{
    EdgeReport, FleetMap, NodeStatus, RejectReason, SimTruth, VehicleEstimate, VehicleId,
    VehicleState,
};
use serde::Serialize;
use std::collections::BTreeMap;

/// Confidence region drawn around each estimate: 3 sigma, the same as the
/// ellipsoids of the Foxglove scene in the MCAP logs (`record/src/foxglove.rs`).
pub const ELLIPSE_SIGMAS: f64 = 3.0;

/// Estimates with a position sigma above this are drawn without an ellipse
/// (they are not localized in any useful sense; the ellipse would fill the view).
pub const MAX_DRAWN_SIGMA_M: f64 = 10.0;

/// A 2-D confidence ellipse: semi-axes (metres) and the major axis' angle
/// from the view's first axis towards its second (radians).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Ellipse {
    pub semi_major_m: f64,
    pub semi_minor_m: f64,
    pub angle_rad: f64,
}

/// The `sigmas`-sigma ellipse of a 2x2 position covariance block; `None` when
/// the block is not finite, not positive semi-definite, or wider than
/// [`MAX_DRAWN_SIGMA_M`].
pub fn ellipse_of(block: &Matrix2<f64>, sigmas: f64) -> Option<Ellipse> {
    if !block.iter().all(|x| x.is_finite()) {
        return None;
    }
    let (a, c) = (block[(0, 0)], block[(1, 1)]);
    let b = 0.5 * (block[(0, 1)] + block[(1, 0)]);
    // Closed-form eigenvalues of a symmetric 2x2 matrix.
    let mean = 0.5 * (a + c);
    let radius = (0.25 * (a - c) * (a - c) + b * b).sqrt();
    let (major, minor) = (mean + radius, mean - radius);
    if minor < -1e-12 || major > MAX_DRAWN_SIGMA_M * MAX_DRAWN_SIGMA_M {
        return None;
    }
    Some(Ellipse {
        semi_major_m: sigmas * major.max(0.0).sqrt(),
        semi_minor_m: sigmas * minor.max(0.0).sqrt(),
        angle_rad: 0.5 * (2.0 * b).atan2(a - c),
    })
}

/// The position block of a pose covariance restricted to axes `i`, `j`
/// (0 x, 1 y, 2 z). The covariance is over `(δt, δθ)` with `δt` in the
/// reference frame (`proto/src/geometry.rs`), so this block is directly the
/// uncertainty of the vehicle's position in the map.
pub fn position_block(cov: &Cov6, i: usize, j: usize) -> Matrix2<f64> {
    Matrix2::new(cov[(i, i)], cov[(i, j)], cov[(j, i)], cov[(j, j)])
}

/// Where a vehicle is in the map, as the page draws it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PlacedPose {
    pub position_m: [f64; 3],
    /// The body's x axis (bow direction) in the reference frame, unit length.
    pub forward: [f64; 3],
}

impl PlacedPose {
    pub fn of(reference_from_vehicle: &Pose) -> PlacedPose {
        let t = reference_from_vehicle.translation.vector;
        let f = reference_from_vehicle.rotation * Vector3::x();
        PlacedPose {
            position_m: [t.x, t.y, t.z],
            forward: [f.x, f.y, f.z],
        }
    }
}

/// Ground truth of every simulated vehicle relative to `reference` (the
/// fused map's gauge): `reference_from_vehicle = world_from_reference⁻¹ ·
/// world_from_vehicle`. Empty when the reference is not in the truth.
pub fn truth_relative_to(truth: &SimTruth, reference: VehicleId) -> BTreeMap<VehicleId, Pose> {
    let Some(world_from_reference) = truth
        .vehicles
        .iter()
        .find(|v| v.vehicle == reference)
        .map(|v| v.world_from_body)
    else {
        return BTreeMap::new();
    };
    let reference_from_world = world_from_reference.inverse();
    truth
        .vehicles
        .iter()
        .map(|v| (v.vehicle, reference_from_world * v.world_from_body))
        .collect()
}

/// Error of an estimate against ground truth: position (metres) and
/// rotation angle (radians) of `truth⁻¹ · estimate`'s rotation.
pub fn pose_error(estimate: &Pose, truth: &Pose) -> (f64, f64) {
    let dt = (estimate.translation.vector - truth.translation.vector).norm();
    let dr: UnitQuaternion<f64> = truth.rotation.inverse() * estimate.rotation;
    (dt, dr.angle())
}

/// One camera's health, from two successive status reports of its node.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CameraView {
    pub camera: u8,
    pub name: String,
    /// Frames per second over the interval between the two reports (the
    /// node's own figure for its last period when there is no earlier report).
    pub frame_rate_hz: f64,
    /// Detections per second over the interval between the two reports
    /// (`None` for the first report of a node).
    pub detection_rate_hz: Option<f64>,
    /// Detections per processed frame over that interval.
    pub detections_per_frame: Option<f64>,
    /// Restoration + detection + pose, mean per frame of the newest report
    /// period that had frames, milliseconds (`None`: no frame yet).
    pub latency_ms: Option<f64>,
    pub frames_dropped: u64,
    pub frames_invalid: u64,
}

/// Per-camera figures from the newest status `current` and, when there is
/// one, the node's previous report `previous` (rates are differences of the
/// counters over the reports' uptime difference; a restarted node, whose
/// counters went backwards, gets no rate until its next report).
pub fn camera_views(previous: Option<&NodeStatus>, current: &NodeStatus) -> Vec<CameraView> {
    current
        .cameras
        .iter()
        .map(|c| {
            let before = previous
                .filter(|p| p.uptime_s < current.uptime_s)
                .and_then(|p| p.cameras.iter().find(|pc| pc.camera == c.camera))
                .filter(|pc| pc.detections <= c.detections && pc.frames_in <= c.frames_in);
            let dt_s = previous.map_or(0.0, |p| current.uptime_s - p.uptime_s);
            let (fps, rate, per_frame) = match before {
                Some(pc) if dt_s > 0.0 => {
                    let det = (c.detections - pc.detections) as f64;
                    let frames = (c.frames_in - pc.frames_in) as f64;
                    (
                        frames / dt_s,
                        Some(det / dt_s),
                        (frames > 0.0).then_some(det / frames),
                    )
                }
                _ => (f64::from(c.frame_rate_hz), None, None),
            };
            CameraView {
                camera: c.camera,
                name: c.name.clone(),
                frame_rate_hz: fps,
                detection_rate_hz: rate,
                detections_per_frame: per_frame,
                latency_ms: None,
                frames_dropped: c.frames_dropped,
                frames_invalid: c.frames_invalid,
            }
        })
        .collect()
}

/// Status reports of a node over which camera rates are averaged: a node
/// reports every second, and at the demo's 0.5 frames per wall-clock
/// second a one-second figure flickers between 0 and 1.
pub const RATE_WINDOW_REPORTS: usize = 6;

/// A node's newest status reports (oldest first), and the newest's age.
#[derive(Debug, Clone, Default)]
pub struct NodeReports {
    pub window: std::collections::VecDeque<NodeStatus>,
    /// Seconds since the newest report arrived (wall clock of the station).
    pub age_s: f64,
}

impl NodeReports {
    pub fn push(&mut self, status: NodeStatus) {
        // A restarted node starts a new window (its counters start again).
        if self
            .window
            .back()
            .is_some_and(|last| status.uptime_s < last.uptime_s)
        {
            self.window.clear();
        }
        self.window.push_back(status);
        while self.window.len() > RATE_WINDOW_REPORTS {
            self.window.pop_front();
        }
        self.age_s = 0.0;
    }

    pub fn current(&self) -> Option<&NodeStatus> {
        self.window.back()
    }

    /// Per-camera figures over the window (see [`camera_views`]), with each
    /// camera's latency from the newest report whose period had frames (a
    /// period without frames reports 0 ms).
    pub fn camera_views(&self) -> Vec<CameraView> {
        let Some(current) = self.current() else {
            return Vec::new();
        };
        let mut views = camera_views(self.oldest(), current);
        for v in &mut views {
            v.latency_ms = self.window.iter().rev().find_map(|s| {
                s.cameras
                    .iter()
                    .find(|c| c.camera == v.camera)
                    .map(|c| f64::from(c.restore_ms + c.detect_ms + c.pose_ms))
                    .filter(|&ms| ms > 0.0)
            });
        }
        views
    }

    /// The oldest report of the window, when there are at least two.
    pub fn oldest(&self) -> Option<&NodeStatus> {
        (self.window.len() >= 2).then(|| &self.window[0])
    }
}

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

/// Ground truth and a map are of the same instant when their stamps differ by
/// at most this (both come from the simulator's clock, so they are equal).
pub const TRUTH_MATCH_NS: u64 = 1_000_000;

/// The instant a map's estimates describe: its newest accepted observation's
/// capture stamp (the map's own stamp when it has none) — the same instant
/// `shoal demo` scores against (`src/demo.rs`, `pair_errors`).
pub fn valid_at_ns(map: &FleetMap) -> u64 {
    map.edges
        .iter()
        .filter(|e| e.rejected.is_none())
        .map(|e| e.stamp_ns)
        .max()
        .unwrap_or(map.stamp_ns)
}

/// The map to show and the ground truth to compare it with. Without truth
/// (a real trial) that is the newest map. In simulation the truth of a tick
/// arrives after its frames are rendered, so the newest map is often a
/// tick ahead of the newest truth: the newest map that *has* its truth is
/// shown instead (a lag of one rendering time), so that the error is not
/// inflated by the swarm's motion over a tick. A map is paired with the
/// truth of [`valid_at_ns`]. `maps` and `truths` are
/// oldest first.
pub fn pair_map_with_truth<'a, M>(
    maps: &'a [(FleetMap, M)],
    truths: &'a [SimTruth],
) -> (Option<&'a (FleetMap, M)>, Option<&'a SimTruth>) {
    let newest = maps.last();
    if truths.is_empty() {
        return (newest, None);
    }
    for m in maps.iter().rev() {
        let at = valid_at_ns(&m.0);
        if let Some(t) = nearest_truth(truths, at) {
            if t.stamp_ns.abs_diff(at) <= TRUTH_MATCH_NS {
                return (Some(m), Some(t));
            }
        }
    }
    // No map has its truth yet: the newest map, with the nearest truth.
    (
        newest,
        newest.and_then(|m| nearest_truth(truths, m.0.stamp_ns)),
    )
}

/// Of `truths` (any order), the one whose stamp is nearest `stamp_ns`.
pub fn nearest_truth<'a>(
    truths: impl IntoIterator<Item = &'a SimTruth>,
    stamp_ns: u64,
) -> Option<&'a SimTruth> {
    truths
        .into_iter()
        .min_by_key(|t| t.stamp_ns.abs_diff(stamp_ns))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Matrix6, Rotation2, Vector3};
    use proto::{CameraStatus, VehicleTruth};

    const PAPER: &str = include_str!("../../configs/fleets/paper.toml");

    fn paper() -> Fleet {
        Fleet::parse(PAPER, std::path::Path::new("configs/fleets/paper.toml")).unwrap()
    }

    fn pose(xyz: [f64; 3], yaw_rad: f64) -> Pose {
        Isometry3::new(Vector3::from(xyz), Vector3::z() * yaw_rad)
    }

    #[test]
    fn ellipse_of_diagonal_block_is_axis_aligned_three_sigma() {
        let e = ellipse_of(&Matrix2::new(0.04, 0.0, 0.0, 0.01), 3.0).unwrap();
        assert!((e.semi_major_m - 0.6).abs() < 1e-12, "{e:?}");
        assert!((e.semi_minor_m - 0.3).abs() < 1e-12, "{e:?}");
        assert!(e.angle_rad.abs() < 1e-12, "{e:?}");
        // Larger along the second axis: major axis at 90°.
        let e = ellipse_of(&Matrix2::new(0.01, 0.0, 0.0, 0.04), 1.0).unwrap();
        assert!((e.semi_major_m - 0.2).abs() < 1e-12);
        assert!(
            (e.angle_rad.abs() - std::f64::consts::FRAC_PI_2).abs() < 1e-12,
            "{e:?}"
        );
    }

    #[test]
    fn ellipse_of_rotated_block_recovers_angle_and_axes() {
        let r = Rotation2::new(30f64.to_radians()).into_inner();
        let block = r * Matrix2::new(9e-4, 0.0, 0.0, 1e-4) * r.transpose();
        let e = ellipse_of(&block, 3.0).unwrap();
        assert!((e.semi_major_m - 0.09).abs() < 1e-9, "{e:?}");
        assert!((e.semi_minor_m - 0.03).abs() < 1e-9, "{e:?}");
        assert!((e.angle_rad.to_degrees() - 30.0).abs() < 1e-6, "{e:?}");
    }

    #[test]
    fn ellipse_of_refuses_nan_indefinite_and_huge_blocks() {
        assert!(ellipse_of(&Matrix2::new(f64::NAN, 0.0, 0.0, 1.0), 3.0).is_none());
        assert!(ellipse_of(&Matrix2::new(1e-2, 0.0, 0.0, -1e-2), 3.0).is_none());
        assert!(ellipse_of(&Matrix2::new(200.0, 0.0, 0.0, 1.0), 3.0).is_none());
        // The reference vehicle's zero covariance is a point, not an error.
        let e = ellipse_of(&Matrix2::zeros(), 3.0).unwrap();
        assert_eq!((e.semi_major_m, e.semi_minor_m), (0.0, 0.0));
    }

    #[test]
    fn position_block_picks_the_side_view_axes() {
        let mut cov = Matrix6::zeros();
        cov[(0, 0)] = 1.0;
        cov[(0, 2)] = 0.5;
        cov[(2, 0)] = 0.5;
        cov[(2, 2)] = 2.0;
        cov[(1, 1)] = 7.0;
        assert_eq!(position_block(&cov, 0, 2), Matrix2::new(1.0, 0.5, 0.5, 2.0));
        assert_eq!(position_block(&cov, 0, 1), Matrix2::new(1.0, 0.0, 0.0, 7.0));
    }

    fn truth_of(poses: &[(VehicleId, Pose)], stamp_ns: u64) -> SimTruth {
        SimTruth {
            stamp_ns,
            tick: stamp_ns / 1_000_000_000,
            water_c_per_m: 0.5,
            vehicles: poses
                .iter()
                .map(|&(vehicle, world_from_body)| VehicleTruth {
                    vehicle,
                    world_from_body,
                    velocity_body: [0.0; 3],
                })
                .collect(),
            visible: vec![],
        }
    }

    #[test]
    fn truth_is_expressed_in_the_reference_body_frame() {
        // Reference heading east (yaw 90° in NED); vehicle 15 three metres east of it.
        let half_pi = std::f64::consts::FRAC_PI_2;
        let t = truth_of(
            &[
                (10, pose([1.0, 2.0, 0.0], half_pi)),
                (15, pose([1.0, 5.0, 0.5], half_pi)),
            ],
            0,
        );
        let rel = truth_relative_to(&t, 10);
        let p15 = rel[&15].translation.vector;
        assert!((p15 - Vector3::new(3.0, 0.0, 0.5)).norm() < 1e-12, "{p15}");
        assert!(rel[&10].translation.vector.norm() < 1e-12);
        assert!(truth_relative_to(&t, 99).is_empty());
    }

    #[test]
    fn pose_error_measures_position_and_angle() {
        let truth = pose([3.0, 0.0, 0.0], 0.0);
        let est = pose([3.0, 0.004, 0.003], 2f64.to_radians());
        let (dt, dr) = pose_error(&est, &truth);
        assert!((dt - 0.005).abs() < 1e-12, "{dt}");
        assert!((dr.to_degrees() - 2.0).abs() < 1e-9, "{dr}");
    }

    fn status(uptime_s: f64, frames_in: u64, detections: u64) -> NodeStatus {
        NodeStatus {
            vehicle: 15,
            stamp_ns: 0,
            uptime_s,
            cameras: vec![CameraStatus {
                camera: 3,
                name: "port".into(),
                frames_in,
                detections,
                frame_rate_hz: 2.0,
                restore_ms: 10.0,
                detect_ms: 20.0,
                pose_ms: 1.5,
                ..Default::default()
            }],
            observations_sent: detections,
            messages_rejected: 0,
        }
    }

    #[test]
    fn camera_rates_come_from_successive_reports() {
        let first = camera_views(None, &status(10.0, 20, 10));
        assert_eq!(first[0].detection_rate_hz, None);
        let v = camera_views(Some(&status(10.0, 20, 10)), &status(12.0, 24, 14));
        assert!((v[0].frame_rate_hz - 2.0).abs() < 1e-12, "{v:?}");
        assert!(
            (v[0].detection_rate_hz.unwrap() - 2.0).abs() < 1e-12,
            "{v:?}"
        );
        assert!(
            (v[0].detections_per_frame.unwrap() - 1.0).abs() < 1e-12,
            "{v:?}"
        );
        // A restarted node (counters and uptime went back) gets no rate.
        let v = camera_views(Some(&status(30.0, 60, 50)), &status(1.0, 2, 1));
        assert_eq!(v[0].detection_rate_hz, None);
    }

    fn edge(
        observer: VehicleId,
        target: VehicleId,
        rejected: Option<RejectReason>,
        chi2: f64,
    ) -> EdgeReport {
        EdgeReport {
            observer,
            camera: 4,
            target_marker: target,
            target_vehicle: Some(target),
            stamp_ns: 1,
            frame_seq: 1,
            rejected,
            chi2,
        }
    }

    #[test]
    fn rates_average_over_a_window_of_reports_and_restart_with_the_node() {
        let mut r = NodeReports::default();
        for k in 0..10u64 {
            // One frame every other second: per-report figures flicker, the window does not.
            r.push(status(k as f64, k / 2, k / 2));
        }
        assert_eq!(r.window.len(), RATE_WINDOW_REPORTS);
        let v = camera_views(r.oldest(), r.current().unwrap());
        assert!((v[0].frame_rate_hz - 0.4).abs() < 1e-12, "{v:?}");
        // Latency from the newest report with frames, not a frameless period's 0.
        let mut idle = status(10.0, 5, 5);
        idle.cameras[0].restore_ms = 0.0;
        idle.cameras[0].detect_ms = 0.0;
        idle.cameras[0].pose_ms = 0.0;
        r.push(idle);
        assert_eq!(r.camera_views()[0].latency_ms, Some(31.5));
        r.push(status(0.5, 0, 0));
        assert_eq!(r.window.len(), 1, "a restarted node starts a new window");
        assert!(r.oldest().is_none());
    }

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

    #[test]
    fn map_shown_is_the_newest_with_its_own_truth() {
        let maps: Vec<(FleetMap, ())> = [1, 2, 2, 3]
            .iter()
            .enumerate()
            .map(|(i, &s)| {
                let mut m = FleetMap {
                    fleet: "paper".into(),
                    producer: "central".into(),
                    seq: i as u64,
                    stamp_ns: s * 1_000_000_000,
                    reference: 10,
                    vehicles: vec![],
                    edges: vec![],
                    solve_time_us: 0,
                };
                m.seq = i as u64;
                (m, ())
            })
            .collect();
        let truths: Vec<SimTruth> = [1, 2].map(|s| truth_of(&[], s * 1_000_000_000)).into();
        // Map 3 (stamp 3 s) has no truth yet: the newest map of 2 s (seq 2) is shown.
        let (m, t) = pair_map_with_truth(&maps, &truths);
        assert_eq!((m.unwrap().0.seq, t.unwrap().stamp_ns), (2, 2_000_000_000));
        // Without truth at all, the newest map.
        let (m, t) = pair_map_with_truth(&maps, &[]);
        assert_eq!((m.unwrap().0.seq, t), (3, None));
        // A map stamped 3 s whose newest accepted observation is of 2 s is valid at 2 s.
        let mut late = maps[3].clone();
        late.0.edges = vec![
            edge(10, 15, None, 1.0),
            edge(10, 17, Some(RejectReason::Stale), 1.0),
        ];
        late.0.edges[0].stamp_ns = 2_000_000_000;
        late.0.edges[1].stamp_ns = 3_000_000_000;
        assert_eq!(valid_at_ns(&late.0), 2_000_000_000);
        let with_late = [maps[0].clone(), late];
        let (m, t) = pair_map_with_truth(&with_late, &truths);
        assert_eq!((m.unwrap().0.seq, t.unwrap().stamp_ns), (3, 2_000_000_000));
        // Truth only from long ago: newest map, nearest truth.
        let old = [truth_of(&[], 0)];
        let (m, t) = pair_map_with_truth(&maps[3..], &old);
        assert_eq!((m.unwrap().0.seq, t.unwrap().stamp_ns), (3, 0));
    }

    #[test]
    fn nearest_truth_matches_the_map_stamp() {
        let ts: Vec<SimTruth> = [1, 2, 3, 4]
            .map(|s| truth_of(&[], s * 1_000_000_000))
            .into();
        assert_eq!(
            nearest_truth(&ts, 2_400_000_000).unwrap().stamp_ns,
            2_000_000_000
        );
        assert_eq!(
            nearest_truth(&ts, 9_000_000_000).unwrap().stamp_ns,
            4_000_000_000
        );
        assert!(nearest_truth(&[], 0).is_none());
    }
}
