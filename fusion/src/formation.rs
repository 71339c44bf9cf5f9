//! An example formation-keeping controller that steers vehicles using only
//! the fused map: each follower holds a slot (a position in the reference
//! vehicle's body frame) and the reference's heading.
//!
//! Proportional control in the follower's own body frame, plus the
//! formation's cruise speed as feed-forward:
//!
//! ```text
//! e_ref  = slot − ref_from_v.t              position error, reference frame
//! v_cmd  = cruise·x̂ + k_p · (v_from_ref.R · e_ref)    clamped to max_speed
//! r_cmd  = −k_yaw · yaw(ref_from_v)                    clamped to max_yaw_rate
//! ```
//!
//! Vehicles that are stale, unobserved or whose estimate is older than
//! `max_age_s` get no command (the simulator keeps their last one, a real
//! vehicle its own safe behaviour).

use crate::MapView;
use nalgebra::Vector3;
use proto::config::Fleet;
use proto::geometry::rpy_of;
use proto::{VehicleCommand, VehicleId, VehicleState};
use std::collections::BTreeMap;

#[derive(Debug, Clone, PartialEq)]
pub struct FormationController {
    pub reference: VehicleId,
    /// Desired position of each follower in the reference's body frame (m).
    pub slots: BTreeMap<VehicleId, Vector3<f64>>,
    /// Forward speed of the formation (m/s).
    pub cruise_m_s: f64,
    pub k_position: f64,
    pub k_yaw: f64,
    pub max_speed_m_s: f64,
    pub max_yaw_rate: f64,
    pub max_age_s: f64,
}

impl FormationController {
    /// Line abreast: followers to starboard of the reference, `spacing_m` apart, in fleet order.
    pub fn line_abreast(fleet: &Fleet, spacing_m: f64, cruise_m_s: f64) -> FormationController {
        let mut slots = BTreeMap::new();
        let mut k = 1.0;
        for v in &fleet.vehicles {
            if v.id != fleet.reference_vehicle {
                slots.insert(v.id, Vector3::new(0.0, k * spacing_m, 0.0));
                k += 1.0;
            }
        }
        FormationController {
            reference: fleet.reference_vehicle,
            slots,
            cruise_m_s,
            k_position: 0.4,
            k_yaw: 0.5,
            max_speed_m_s: 1.0,
            max_yaw_rate: 0.3,
            max_age_s: 2.0,
        }
    }

    /// Commands for every follower the map localizes freshly enough.
    pub fn commands(&self, view: &MapView) -> Vec<VehicleCommand> {
        let stamp_ns = view.map().stamp_ns;
        let mut out = Vec::new();
        for (&v, slot) in &self.slots {
            let Some(rel) = view.relative(self.reference, v) else {
                continue;
            };
            // A vehicle carried forward by odometry is current, however long unseen.
            let predicted = rel.predicted;
            let fresh = predicted || rel.age_ns as f64 * 1e-9 <= self.max_age_s;
            let live = predicted
                || view
                    .vehicle(v)
                    .is_some_and(|e| e.state == VehicleState::Live);
            if !fresh || !live {
                continue;
            }
            let ref_from_v = rel.a_from_b.pose;
            let err_ref = slot - ref_from_v.translation.vector;
            let err_body = ref_from_v.rotation.inverse() * err_ref;
            let mut vel = Vector3::new(self.cruise_m_s, 0.0, 0.0) + err_body * self.k_position;
            let n = vel.norm();
            if n > self.max_speed_m_s {
                vel *= self.max_speed_m_s / n;
            }
            let yaw = rpy_of(&ref_from_v)[2];
            let yaw_rate = (-self.k_yaw * yaw).clamp(-self.max_yaw_rate, self.max_yaw_rate);
            out.push(VehicleCommand {
                vehicle: v,
                stamp_ns,
                velocity_body: [vel.x, vel.y, vel.z],
                yaw_rate,
            });
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proto::geometry::{pose_from_xyz_rpy, Cov6};
    use proto::{FleetMap, VehicleEstimate};

    fn map_with(v_pose: proto::Pose) -> FleetMap {
        let est = |vehicle, pose| VehicleEstimate {
            vehicle,
            state: VehicleState::Live,
            reference_from_vehicle: pose,
            covariance: Cov6::identity() * 1e-4,
            last_seen_ns: 1_000_000_000,
        };
        FleetMap {
            fleet: "t".into(),
            producer: "central".into(),
            seq: 1,
            stamp_ns: 1_000_000_000,
            reference: 1,
            vehicles: vec![est(1, proto::Pose::identity()), est(2, v_pose)],
            edges: vec![],
            solve_time_us: 0,
        }
    }

    fn controller() -> FormationController {
        FormationController {
            reference: 1,
            slots: [(2, Vector3::new(0.0, 2.0, 0.0))].into_iter().collect(),
            cruise_m_s: 0.3,
            k_position: 0.5,
            k_yaw: 0.5,
            max_speed_m_s: 1.0,
            max_yaw_rate: 0.3,
            max_age_s: 2.0,
        }
    }

    #[test]
    fn follower_too_close_is_steered_outwards_and_back_in_line() {
        // Follower at 1.5 m to starboard, 0.2 m ahead, yawed 0.1 rad to starboard.
        let map = map_with(pose_from_xyz_rpy([0.2, 1.5, 0.0], [0.0, 0.0, 0.1]));
        let cmds = controller().commands(&MapView::new(map));
        assert_eq!(cmds.len(), 1);
        let c = cmds[0];
        assert!(
            c.velocity_body[1] > 0.0,
            "must move to starboard: {:?}",
            c.velocity_body
        );
        assert!(
            c.velocity_body[0] < 0.3,
            "must slow down to drop back: {:?}",
            c.velocity_body
        );
        assert!(c.yaw_rate < 0.0, "must turn back to port");
    }

    #[test]
    fn follower_on_its_slot_just_cruises() {
        let map = map_with(pose_from_xyz_rpy([0.0, 2.0, 0.0], [0.0; 3]));
        let c = controller().commands(&MapView::new(map))[0];
        assert!((c.velocity_body[0] - 0.3).abs() < 1e-12 && c.velocity_body[1].abs() < 1e-12);
        assert!(c.yaw_rate.abs() < 1e-12);
    }

    #[test]
    fn stale_follower_gets_no_command() {
        let mut map = map_with(pose_from_xyz_rpy([0.0, 2.0, 0.0], [0.0; 3]));
        map.vehicles[1].state = VehicleState::Stale;
        assert!(controller().commands(&MapView::new(map)).is_empty());
    }

    #[test]
    fn a_follower_carried_by_odometry_is_steered_however_long_unseen() {
        // Last seen 5 s before the map (beyond max_age_s), but Predicted.
        let mut map = map_with(pose_from_xyz_rpy([0.0, 1.5, 0.0], [0.0; 3]));
        map.stamp_ns += 5_000_000_000;
        map.vehicles[1].state = VehicleState::Predicted;
        let cmds = controller().commands(&MapView::new(map.clone()));
        assert_eq!(cmds.len(), 1);
        assert!(cmds[0].velocity_body[1] > 0.0, "{:?}", cmds[0]);
        // The same age without a prediction is too old to steer by.
        map.vehicles[1].state = VehicleState::Live;
        assert!(controller().commands(&MapView::new(map)).is_empty());
    }
}
