//! The baselines report the same IDs and corner order as `CodeSet::corners_3d`.

use nalgebra::{Translation3, UnitQuaternion, Vector3};
use shoal_node::baseline::{AprilTag, OpenCvAruco};
use shoal_node::detect::{DetectError, MarkerDetector};
use shoal_node::mat::gray_as_mat;
use shoal_proto::{camera::CameraModel, geometry::Pose, marker::CodeSet};
use shoal_sim_bridge::render::{Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;

/// OpenCV's and AprilTag's own refinements are accurate to well under a
/// pixel on clean renders; 1 px catches any corner-order mistake (those are
/// tens of pixels).
const CORNER_TOL_PX: f64 = 1.0;

fn check(det: &mut dyn MarkerDetector, codes: CodeSet, id: u32, roll_deg: f64) {
    let cam = CameraModel::vehicle_1440();
    let pose = Pose::from_parts(
        Translation3::new(0.02, -0.01, 0.61),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll_deg.to_radians())
            * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
            * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.4),
    );
    let scene = Scene::single_marker(codes, id, 0.1, pose);
    let img = Renderer::new()
        .render(
            &cam,
            &Pose::identity(),
            &scene,
            &WaterParams::clear(),
            0.0,
            1,
        )
        .unwrap()
        .image;
    let mat = gray_as_mat(&img).unwrap().clone_pointee();
    let found = det.detect(&mat).unwrap();
    assert_eq!(
        found.iter().map(|d| d.id).collect::<Vec<_>>(),
        vec![id],
        "{} roll {roll_deg}",
        det.name()
    );
    let d = &found[0];
    let all = codes.corners_3d(0.1);
    for (k, &cid) in d.corner_ids.iter().enumerate() {
        let q = cam.project(&(pose * all[cid as usize])).unwrap();
        let e = ((q.x - d.corners_px[k][0]).powi(2) + (q.y - d.corners_px[k][1]).powi(2)).sqrt();
        assert!(
            e < CORNER_TOL_PX,
            "{} roll {roll_deg} corner {cid}: {e} px",
            det.name()
        );
    }
}

#[test]
fn opencv_aruco_corners_follow_corners_3d_order() {
    let mut det = OpenCvAruco::new(CodeSet::Aruco4x4_50).unwrap();
    for roll in [0.0, 90.0, 200.0] {
        check(&mut det, CodeSet::Aruco4x4_50, 17, roll);
    }
    // On the enhanced marker OpenCV reads the code square: corners 8..12.
    let mut det = OpenCvAruco::new(CodeSet::Shoal).unwrap();
    check(&mut det, CodeSet::Shoal, 17, 30.0);
}

#[test]
fn apriltag_corners_follow_corners_3d_order() {
    let mut det = AprilTag::new(CodeSet::AprilTag36h11).unwrap();
    for roll in [0.0, 90.0, 200.0] {
        check(&mut det, CodeSet::AprilTag36h11, 17, roll);
    }
    let mut det = AprilTag::new(CodeSet::AprilTag16h5).unwrap();
    check(&mut det, CodeSet::AprilTag16h5, 7, 45.0);
}

#[test]
fn baselines_refuse_code_sets_they_cannot_read() {
    assert!(matches!(
        AprilTag::new(CodeSet::Shoal),
        Err(DetectError::Unsupported { .. })
    ));
}
