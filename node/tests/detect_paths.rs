//! `detect_paths`: one JSON line per detection, with pose; clear error lines for bad files.

use nalgebra::{Translation3, UnitQuaternion, Vector3};
use opencv::core::Vector;
use opencv::imgcodecs;
use shoal_node::detect::detect_paths;
use shoal_node::mat::gray_as_mat;
use shoal_proto::{camera::CameraModel, geometry::Pose, marker::CodeSet};
use shoal_sim_bridge::render::{Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;

#[test]
fn prints_detections_with_pose_and_reports_unreadable_files() {
    let dir = std::env::temp_dir().join(format!("shoal_detect_paths_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let cam = CameraModel::vehicle_1440();
    let truth = Pose::from_parts(
        Translation3::new(0.0, 0.0, 0.61),
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
    );
    let scene = Scene::single_marker(CodeSet::Shoal, 15, 0.1, truth);
    let img = Renderer::new()
        .render(
            &cam,
            &Pose::identity(),
            &scene,
            &WaterParams::preset(0.5),
            0.0,
            2,
        )
        .unwrap()
        .image;
    let png = dir.join("m15.png");
    imgcodecs::imwrite(
        png.to_str().unwrap(),
        &gray_as_mat(&img).unwrap(),
        &Vector::new(),
    )
    .unwrap();
    let junk = dir.join("junk.png");
    std::fs::write(&junk, b"not a png").unwrap();
    let missing = dir.join("missing.png");

    let mut out = Vec::new();
    let sum = detect_paths(
        &[&png, &junk, &missing],
        CodeSet::Shoal,
        Some(cam),
        Some(0.1),
        &mut out,
    )
    .unwrap();
    assert_eq!(
        (sum.files, sum.frames, sum.detections, sum.errors),
        (3, 1, 1, 2)
    );
    let lines: Vec<serde_json::Value> = String::from_utf8(out)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 3);
    let det = &lines[0];
    assert_eq!(det["id"], 15);
    assert_eq!(det["codes"], "shoal");
    assert_eq!(det["corners_px"].as_array().unwrap().len(), 12);
    let z = det["camera_from_marker"]["t_m"][2].as_f64().unwrap();
    assert!((z - 0.61).abs() < 0.005, "z = {z}");
    assert!(lines[1]["error"].as_str().unwrap().contains("cannot read"));
    assert!(lines[2]["error"].as_str().unwrap().contains("no such file"));
    std::fs::remove_dir_all(&dir).ok();
}
