//! Regression guard for the headline figure (full table: `shoal eval
//! accuracy`): on the same simulated poses in
//! moderately turbid water, the enhanced marker read by the shoal detector
//! localizes at most half as far off as OpenCV's ArUco and AprilTag 3 with
//! the same outer black square.

use nalgebra::{Translation3, UnitQuaternion, Vector3};
use shoal_node::baseline::{AprilTag, OpenCvAruco};
use shoal_node::detect::{DetectParams, MarkerDetector, ShoalDetector};
use shoal_node::mat::gray_to_mat;
use shoal_node::pose::estimate_pose;
use shoal_proto::{camera::CameraModel, geometry::Pose, marker::CodeSet};
use shoal_sim_bridge::render::{Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;

const SIDE_M: f64 = 0.1;
const FRAMES: usize = 5;

/// Median position error (mm) over the frames, `None` if a frame was missed.
fn median_error_mm(codes: CodeSet, det: &mut dyn MarkerDetector) -> Option<f64> {
    let cam = CameraModel::vehicle_1440();
    let water = WaterParams::preset(1.38);
    let mut r = Renderer::new();
    let mut errs = Vec::new();
    for f in 0..FRAMES {
        let truth = Pose::from_parts(
            Translation3::new(0.007 * f as f64 - 0.015, 0.004 * f as f64 - 0.01, 0.61),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
                * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 30f64.to_radians()),
        );
        let scene = Scene::single_marker(codes, 17, SIDE_M, truth);
        let img = r
            .render(&cam, &Pose::identity(), &scene, &water, 0.0, f as u64 + 1)
            .ok()?
            .image;
        let found = det.detect(&gray_to_mat(&img).ok()?).ok()?;
        let d = found.iter().find(|d| d.id == 17)?;
        let sol = estimate_pose(&cam, &d.object_points(SIDE_M), &d.corners_px, None).ok()?;
        errs.push(
            1000.0
                * (sol.best.camera_from_marker.translation.vector - truth.translation.vector)
                    .norm(),
        );
    }
    errs.sort_by(f64::total_cmp);
    Some(errs[FRAMES / 2])
}

#[test]
fn enhanced_marker_halves_the_better_baselines_distance_error() {
    let shoal = median_error_mm(
        CodeSet::Shoal,
        &mut ShoalDetector::new(CodeSet::Shoal, DetectParams::default()),
    )
    .unwrap();
    let aruco = median_error_mm(
        CodeSet::Aruco4x4_50,
        &mut OpenCvAruco::new(CodeSet::Aruco4x4_50).unwrap(),
    )
    .unwrap();
    let april = median_error_mm(
        CodeSet::AprilTag36h11,
        &mut AprilTag::new(CodeSet::AprilTag36h11).unwrap(),
    )
    .unwrap();
    eprintln!(
        "median position error: shoal {shoal:.3} mm, ArUco {aruco:.3} mm, AprilTag {april:.3} mm"
    );
    assert!(
        shoal <= 0.5 * aruco.min(april),
        "shoal {shoal}, aruco {aruco}, apriltag {april}"
    );
}
