//! shoal in ROS 2's vocabulary (issue #20): CDR ([`cdr`]), the messages
//! ([`msgs`]), `rmw_zenoh`'s keys, tokens and attachments ([`rmw`]), and here
//! the mapping of shoal's messages onto ROS 2 topics and frames.
//!
//! **Frames.** shoal's body frames are forward-right-down (FRD, the marine
//! convention); ROS's `base_link` is forward-left-up (REP-103). Every pose is
//! turned by π about x on both sides (`T' = C·T·C`, `C = diag(1, −1, −1)`)
//! and its covariance by the same rotation on translation and rotation
//! blocks. shoal's covariance is over `(δt, δθ)` in the parent frame
//! (`geometry`'s convention), which is how ROS reads
//! `PoseWithCovariance.covariance`. Frame names follow REP-105's multi-robot
//! use: `auv<ID>/base_link`. The fleet map's poses are relative to the
//! reference vehicle, so their parent is `auv<ref>/base_link`.
//!
//! **Topics** (under [`Ros2Names::namespace`], `/shoal/<fleet>` with `-` → `_`):
//! `<ns>/auv<ID>/pose` (the fused pose of each localized vehicle), `/tf`,
//! `<ns>/observations/auv<O>/auv<T>` (each raw observation) and `/diagnostics`.

pub mod cdr;
pub mod msgs;
pub mod rmw;

use crate::geometry::{Cov6, Pose};
use crate::messages::{FleetMap, NodeStatus, Observation, VehicleId, VehicleState};
use msgs::{
    level, DiagnosticArray, DiagnosticStatus, Header, KeyValue, PoseWithCovarianceStamped,
    TfMessage, TransformStamped,
};
use nalgebra::{Isometry3, Matrix3, Matrix6, UnitQuaternion};

/// FLU from FRD (and back): a half turn about x.
fn frd_to_flu() -> Isometry3<f64> {
    Isometry3::from_parts(
        nalgebra::Translation3::identity(),
        UnitQuaternion::from_axis_angle(&nalgebra::Vector3::x_axis(), std::f64::consts::PI),
    )
}

/// `a_from_b` between two FRD body frames → the same between their FLU frames.
pub fn flu_pose(a_from_b: &Pose) -> Pose {
    let c = frd_to_flu();
    c * a_from_b * c.inverse()
}

/// The covariance of [`flu_pose`]'s result.
pub fn flu_covariance(cov: &Cov6) -> Cov6 {
    let r = Matrix3::from_diagonal(&nalgebra::Vector3::new(1.0, -1.0, -1.0));
    let mut j = Matrix6::zeros();
    j.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    j.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
    j * cov * j.transpose()
}

/// Topic and frame names of one fleet.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Ros2Names {
    /// `/shoal/<fleet>`, the fleet name's `-` written `_` (ROS names allow neither `-` nor `__`).
    pub namespace: String,
}

impl Ros2Names {
    pub fn new(fleet: &str) -> Self {
        let mut name: String = fleet
            .chars()
            .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
            .collect();
        while name.contains("__") {
            name = name.replace("__", "_");
        }
        let name = name.trim_matches('_');
        let name = if name.is_empty() || name.starts_with(|c: char| c.is_ascii_digit()) {
            format!("fleet_{name}")
        } else {
            name.to_string()
        };
        Self {
            namespace: format!("/shoal/{}", name.trim_end_matches('_')),
        }
    }

    pub fn base_link(v: VehicleId) -> String {
        format!("auv{v}/base_link")
    }
    pub fn pose_topic(&self, v: VehicleId) -> String {
        format!("{}/auv{v}/pose", self.namespace)
    }
    pub fn observation_topic(&self, observer: VehicleId, target: VehicleId) -> String {
        format!("{}/observations/auv{observer}/auv{target}", self.namespace)
    }
    pub const TF: &'static str = "/tf";
    pub const DIAGNOSTICS: &'static str = "/diagnostics";
}

fn pose_message(
    stamp_ns: u64,
    frame: String,
    a_from_b: &Pose,
    cov: &Cov6,
) -> PoseWithCovarianceStamped {
    let p = flu_pose(a_from_b);
    let c = flu_covariance(cov);
    let q = p.rotation.quaternion();
    PoseWithCovarianceStamped {
        header: Header::new(stamp_ns, frame),
        position: [p.translation.x, p.translation.y, p.translation.z],
        orientation: [q.i, q.j, q.k, q.w],
        // nalgebra is column-major; ROS's array is row-major.
        covariance: std::array::from_fn(|k| c[(k / 6, k % 6)]),
    }
}

/// Vehicles with a pose worth publishing: localized now or carried by odometry.
fn localized(state: VehicleState) -> bool {
    matches!(state, VehicleState::Live | VehicleState::Predicted)
}

/// The fused map's poses, one per localized vehicle (the reference's is the identity).
pub fn map_poses(map: &FleetMap, names: &Ros2Names) -> Vec<(String, PoseWithCovarianceStamped)> {
    let parent = Ros2Names::base_link(map.reference);
    map.vehicles
        .iter()
        .filter(|v| localized(v.state) || v.vehicle == map.reference)
        .map(|v| {
            (
                names.pose_topic(v.vehicle),
                pose_message(
                    map.stamp_ns,
                    parent.clone(),
                    &v.reference_from_vehicle,
                    &v.covariance,
                ),
            )
        })
        .collect()
}

/// The fused map as transforms `auv<ref>/base_link` → `auv<ID>/base_link`.
pub fn map_tf(map: &FleetMap) -> TfMessage {
    let parent = Ros2Names::base_link(map.reference);
    TfMessage {
        transforms: map
            .vehicles
            .iter()
            .filter(|v| localized(v.state) && v.vehicle != map.reference)
            .map(|v| {
                let p = flu_pose(&v.reference_from_vehicle);
                let q = p.rotation.quaternion();
                TransformStamped {
                    header: Header::new(map.stamp_ns, parent.clone()),
                    child_frame_id: Ros2Names::base_link(v.vehicle),
                    translation: [p.translation.x, p.translation.y, p.translation.z],
                    rotation: [q.i, q.j, q.k, q.w],
                }
            })
            .collect(),
    }
}

/// One raw observation, in its observer's `base_link`; `None` for a marker
/// the fleet file does not know (no target vehicle to name the topic by).
pub fn observation_pose(
    obs: &Observation,
    names: &Ros2Names,
) -> Option<(String, PoseWithCovarianceStamped)> {
    let target = obs.target_vehicle?;
    Some((
        names.observation_topic(obs.observer, target),
        pose_message(
            obs.stamp_ns,
            Ros2Names::base_link(obs.observer),
            &obs.observer_from_target,
            &obs.covariance,
        ),
    ))
}

fn kv(key: impl Into<String>, value: impl ToString) -> KeyValue {
    KeyValue {
        key: key.into(),
        value: value.to_string(),
    }
}

/// A node's health report as one `DiagnosticStatus` per node: WARN when a
/// camera delivered no frames in the last period or rejected frames, the
/// counters as key/values.
pub fn node_diagnostics(status: &NodeStatus) -> DiagnosticArray {
    let v = status.vehicle;
    let mut values = vec![
        kv("uptime_s", format!("{:.1}", status.uptime_s)),
        kv("observations_sent", status.observations_sent),
        kv("messages_rejected", status.messages_rejected),
    ];
    match &status.clock {
        Some(c) => values.extend([
            kv("clock.synchronised", c.synchronised),
            kv("clock.offset_ns", c.offset_ns),
            kv("clock.est_error_ns", c.est_error_ns),
            kv("clock.max_error_ns", c.max_error_ns),
        ]),
        None => values.push(kv("clock.synchronised", "unknown")),
    }
    let mut problems = Vec::new();
    for c in &status.cameras {
        let p = format!("camera{}.", c.camera);
        values.extend([
            kv(format!("{p}name"), &c.name),
            kv(format!("{p}frames_in"), c.frames_in),
            kv(format!("{p}frames_dropped"), c.frames_dropped),
            kv(format!("{p}frames_invalid"), c.frames_invalid),
            kv(format!("{p}detections"), c.detections),
            kv(
                format!("{p}frame_rate_hz"),
                format!("{:.2}", c.frame_rate_hz),
            ),
            kv(format!("{p}restore_ms"), format!("{:.2}", c.restore_ms)),
            kv(format!("{p}detect_ms"), format!("{:.2}", c.detect_ms)),
            kv(format!("{p}pose_ms"), format!("{:.2}", c.pose_ms)),
            kv(format!("{p}stamp_source"), c.stamp_source.name()),
            kv(format!("{p}frames_missed"), c.frames_missed),
            kv(format!("{p}reconnects"), c.reconnects),
        ]);
        if c.frame_rate_hz <= 0.0 {
            problems.push(format!("camera {} ({}) has no frames", c.camera, c.name));
        }
        if c.frames_invalid > 0 {
            problems.push(format!(
                "camera {} rejected {} frames",
                c.camera, c.frames_invalid
            ));
        }
    }
    let (lvl, message) = if problems.is_empty() {
        (level::OK, "running".to_string())
    } else {
        (level::WARN, problems.join("; "))
    };
    DiagnosticArray {
        header: Header::new(status.stamp_ns, ""),
        status: vec![DiagnosticStatus {
            level: lvl,
            name: format!("shoal node auv{v}"),
            message,
            hardware_id: format!("auv{v}"),
            values,
        }],
    }
}

/// The fused map's vehicles as diagnostics: OK when localized, WARN when
/// only carried by odometry, STALE when gone or not connected.
pub fn map_diagnostics(map: &FleetMap) -> DiagnosticArray {
    DiagnosticArray {
        header: Header::new(map.stamp_ns, ""),
        status: map
            .vehicles
            .iter()
            .map(|v| {
                let (lvl, message) = match v.state {
                    VehicleState::Live => (level::OK, "localized"),
                    VehicleState::Predicted => (level::WARN, "carried by odometry"),
                    VehicleState::Stale => (level::STALE, "stale"),
                    VehicleState::Unobserved => (level::STALE, "not connected to the reference"),
                };
                DiagnosticStatus {
                    level: lvl,
                    name: format!("shoal fusion auv{}", v.vehicle),
                    message: message.into(),
                    hardware_id: format!("auv{}", v.vehicle),
                    values: vec![
                        kv("reference", format!("auv{}", map.reference)),
                        kv("last_seen_ns", v.last_seen_ns),
                        kv("map_seq", map.seq),
                    ],
                }
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, Vector3};

    #[test]
    fn frd_poses_turn_into_flu() {
        // 2 m ahead, 1 m to starboard (FRD +y), 0.5 m deeper (FRD +z), yawed
        // 90° to starboard (about FRD +z, down).
        let frd = Pose::from_parts(
            Translation3::new(2.0, 1.0, 0.5),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2),
        );
        let flu = flu_pose(&frd);
        // FLU: ahead +x, port +y, up +z: starboard is −y, deeper is −z.
        assert!((flu.translation.vector - Vector3::new(2.0, -1.0, -0.5)).norm() < 1e-12);
        // A turn to starboard is negative about FLU's +z (up).
        let (_, _, yaw) = flu.rotation.euler_angles();
        assert!((yaw + std::f64::consts::FRAC_PI_2).abs() < 1e-12, "{yaw}");
        let mut cov = Cov6::identity();
        cov[(0, 1)] = 0.3;
        cov[(1, 0)] = 0.3;
        cov[(3, 5)] = 0.2;
        cov[(5, 3)] = 0.2;
        let c = flu_covariance(&cov);
        assert_eq!(c[(0, 1)], -0.3);
        assert_eq!(c[(3, 5)], -0.2);
        assert_eq!(c[(1, 1)], 1.0);
    }

    #[test]
    fn fleet_names_become_ros_names() {
        assert_eq!(Ros2Names::new("demo").namespace, "/shoal/demo");
        assert_eq!(
            Ros2Names::new("sea-trial-2").namespace,
            "/shoal/sea_trial_2"
        );
        assert_eq!(Ros2Names::new("3rd").namespace, "/shoal/fleet_3rd");
        assert_eq!(Ros2Names::new("a--b").namespace, "/shoal/a_b");
        for fleet in ["demo", "sea-trial-2", "3rd", "a--b", "_x_", "-"] {
            let n = Ros2Names::new(fleet);
            for topic in [n.pose_topic(10), n.observation_topic(10, 17)] {
                assert!(rmw::valid_topic(&topic), "{fleet}: {topic}");
            }
        }
    }
}
