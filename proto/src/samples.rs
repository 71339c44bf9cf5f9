//! Example messages of every kind, valid and small: what the codec's tests,
//! the fuzz targets and the documentation start from (each test damages its
//! own copy). Also the fuzz targets' case count.

use crate::codec::encode;
use crate::geometry::{pose_from_xyz_rpy, Cov6};
use crate::messages::*;
use crate::{CameraModel, CodeSet};

/// Cases per fuzz property: `SHOAL_FUZZ_CASES` when set (a long run on
/// demand, e.g. `SHOAL_FUZZ_CASES=100000 cargo test -p shoal-proto --test
/// fuzz_wire`), else `default_cases` (the short run CI does).
pub fn fuzz_cases(default_cases: u32) -> u32 {
    std::env::var("SHOAL_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default_cases)
}

pub fn observation() -> Observation {
    let pose = pose_from_xyz_rpy([0.1, 1.0, 0.2], [0.0, 0.1, -0.2]);
    Observation {
        observer: 10,
        camera: 4,
        codes: CodeSet::Shoal,
        target_marker: 15,
        target_vehicle: Some(15),
        stamp_ns: 123_456_789,
        frame_seq: 42,
        observer_from_target: pose,
        covariance: Cov6::identity() * 1e-4,
        reprojection_rms_px: 0.2,
        alternative: Some(PoseHypothesis {
            observer_from_target: pose_from_xyz_rpy([0.1, 1.0, 0.2], [0.0, -0.1, -0.2]),
            covariance: Cov6::identity() * 2e-4,
            reprojection_rms_px: 0.9,
        }),
        corner_count: 12,
        corners_px: vec![[1.0, 2.0]; 12],
        quality: ImageQuality {
            marker_contrast: 0.5,
            cnr: 12.0,
            backscatter: 0.1,
            estimated_c_per_m: 0.5,
        },
        predicted: false,
    }
}

pub fn fleet_map() -> FleetMap {
    FleetMap {
        fleet: "paper".into(),
        producer: "central".into(),
        seq: 3,
        stamp_ns: 77,
        reference: 10,
        vehicles: vec![VehicleEstimate {
            vehicle: 15,
            state: VehicleState::Live,
            reference_from_vehicle: pose_from_xyz_rpy([0.0, 1.0, 0.0], [0.0; 3]),
            covariance: Cov6::identity(),
            last_seen_ns: 70,
        }],
        edges: vec![EdgeReport {
            observer: 10,
            camera: 4,
            target_marker: 99,
            target_vehicle: None,
            stamp_ns: 70,
            frame_seq: 1,
            rejected: Some(RejectReason::ObserverMismatch),
            chi2: 1.5,
        }],
        solve_time_us: 12,
    }
}

pub fn camera_frame() -> CameraFrame {
    let mut model = CameraModel::vehicle_1440();
    model.width = 8;
    model.height = 4;
    CameraFrame {
        vehicle: 17,
        camera: 0,
        seq: 9,
        stamp_ns: 5,
        info: CameraInfo {
            model,
            body_from_camera: pose_from_xyz_rpy([0.7, 0.0, 0.0], [1.0, 0.0, 1.0]),
        },
        format: PixelFormat::Mono8,
        data: (0..32).collect(),
    }
}

pub fn sim_truth() -> SimTruth {
    SimTruth {
        stamp_ns: 1,
        tick: 2,
        water_c_per_m: 0.5,
        vehicles: vec![VehicleTruth {
            vehicle: 10,
            world_from_body: pose_from_xyz_rpy([1.0, 2.0, 3.0], [0.0; 3]),
            velocity_body: [0.5, 0.0, 0.0],
        }],
        visible: vec![VisibleMarker {
            observer: 10,
            camera: 3,
            frame_seq: 2,
            codes: CodeSet::AprilTag36h11,
            marker: 15,
            target_vehicle: 15,
            corners_px: vec![[1.0, 2.0]; 4],
            visible_fraction: 1.0,
            range_m: 1.2,
        }],
    }
}

pub fn node_status() -> NodeStatus {
    NodeStatus {
        vehicle: 10,
        stamp_ns: 4,
        uptime_s: 1.5,
        cameras: vec![CameraStatus {
            camera: 0,
            name: "forward".into(),
            frames_in: 10,
            corner_fits: vec![("raw_sides".into(), 7), ("pattern".into(), 2)],
            stamp_source: StampSource::Pipeline,
            frames_missed: 2,
            reconnects: 1,
            ..Default::default()
        }],
        observations_sent: 3,
        messages_rejected: 1,
        clock: Some(ClockSync {
            synchronised: true,
            offset_ns: -1_500,
            est_error_ns: 20_000,
            max_error_ns: 150_000,
        }),
    }
}

pub fn vehicle_command() -> VehicleCommand {
    VehicleCommand {
        vehicle: 10,
        stamp_ns: 1,
        velocity_body: [0.5, 0.0, 0.0],
        yaw_rate: 0.01,
    }
}

pub fn nav_state() -> crate::nav::NavState {
    use crate::nav::{BodyVelocity, Depth, Heading, Tilt};
    crate::nav::NavState {
        vehicle: 15,
        stamp_ns: 1_000_000_000,
        depth: Some(Depth {
            depth_m: 5.0,
            std_m: 0.02,
        }),
        tilt: Some(Tilt {
            roll_rad: 0.01,
            pitch_rad: -0.02,
            covariance: [[1e-5, 0.0], [0.0, 1e-5]],
        }),
        heading: Some(Heading {
            yaw_rad: 0.5,
            std_rad: 0.03,
        }),
        velocity: Some(BodyVelocity {
            velocity_mps: [0.3, 0.0, 0.01],
            covariance: [[1e-4, 0.0, 0.0], [0.0, 1e-4, 0.0], [0.0, 0.0, 1e-4]],
        }),
    }
}

/// [`observation`] as a vehicle's link sender puts it on the bus.
pub fn link_packet() -> crate::compact::LinkPacket {
    let obs = observation();
    crate::compact::LinkPacket {
        sender: obs.observer,
        seq: 3,
        payload: crate::compact::encode(&obs)
            .expect("the sample observation fits the compact form"),
    }
}

/// A valid envelope of each kind, in `MessageKind::ALL` order.
pub fn samples() -> Vec<Vec<u8>> {
    // Every sample above is a few hundred bytes of plain serde data: bincode
    // cannot fail on it and it is far below `MAX_PAYLOAD`.
    const SMALL_AND_VALID: &str = "a sample message is small and serializable";
    vec![
        encode(&observation()).expect(SMALL_AND_VALID),
        encode(&fleet_map()).expect(SMALL_AND_VALID),
        encode(&camera_frame()).expect(SMALL_AND_VALID),
        encode(&sim_truth()).expect(SMALL_AND_VALID),
        encode(&node_status()).expect(SMALL_AND_VALID),
        encode(&vehicle_command()).expect(SMALL_AND_VALID),
        encode(&nav_state()).expect(SMALL_AND_VALID),
        encode(&link_packet()).expect(SMALL_AND_VALID),
    ]
}
