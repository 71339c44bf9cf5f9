//! Messages the view's unit tests start from.

use nalgebra::{Isometry3, Vector3};
use proto::config::Fleet;
use proto::geometry::Pose;
use proto::{
    CameraStatus, EdgeReport, NodeStatus, RejectReason, SimTruth, VehicleId, VehicleTruth,
};

const PAPER: &str = include_str!("../../../configs/fleets/paper.toml");

pub(super) fn paper() -> Fleet {
    Fleet::parse(PAPER, std::path::Path::new("configs/fleets/paper.toml")).unwrap()
}

pub(super) fn pose(xyz: [f64; 3], yaw_rad: f64) -> Pose {
    Isometry3::new(Vector3::from(xyz), Vector3::z() * yaw_rad)
}

pub(super) fn truth_of(poses: &[(VehicleId, Pose)], stamp_ns: u64) -> SimTruth {
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

pub(super) fn status(uptime_s: f64, frames_in: u64, detections: u64) -> NodeStatus {
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
        clock: None,
    }
}

pub(super) fn edge(
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
