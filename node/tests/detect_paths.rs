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
    // Clear water, the frame as the camera's: every square's sides fitted on
    // it, edges far above the pattern fit's threshold.
    assert_eq!(det["corner_fit"], "raw_sides", "{det}");
    assert_eq!(det["corner_fit_reason"]["why"], "edges_strong", "{det}");
    assert!(det["corner_fit_reason"]["step_dn"].as_f64().unwrap() >= 16.0);
    let squares = det["squares"].as_array().unwrap();
    assert_eq!(squares.len(), 3);
    assert_eq!(squares[2]["first_corner"], 8);
    let z = det["camera_from_marker"]["t_m"][2].as_f64().unwrap();
    assert!((z - 0.61).abs() < 0.005, "z = {z}");
    assert!(lines[1]["error"].as_str().unwrap().contains("cannot read"));
    assert!(lines[2]["error"].as_str().unwrap().contains("no such file"));
    std::fs::remove_dir_all(&dir).ok();
}

/// The video path: every frame of an MJPEG AVI is read, numbered from 0 and
/// solved; a file with a video extension that no backend can open is an
/// error line, not a silent skip.
#[test]
fn reads_every_frame_of_a_video_and_numbers_them() {
    use opencv::prelude::*;
    use opencv::videoio::{VideoWriter, CAP_OPENCV_MJPEG};

    let dir = std::env::temp_dir().join(format!("shoal_detect_video_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let cam = CameraModel::vehicle_1440();
    let avi = dir.join("swim.avi");
    let fourcc = VideoWriter::fourcc('M', 'J', 'P', 'G').unwrap();
    let size = opencv::core::Size::new(cam.width as i32, cam.height as i32);
    // OpenCV's built-in MJPEG writer: no FFmpeg needed, so this runs wherever OpenCV does.
    let mut writer = VideoWriter::new_with_backend(
        avi.to_str().unwrap(),
        CAP_OPENCV_MJPEG,
        fourcc,
        5.0,
        size,
        true,
    )
    .unwrap();
    assert!(
        writer.is_opened().unwrap(),
        "no MJPEG writer in this OpenCV"
    );
    let mut renderer = Renderer::new();
    let depths = [0.55, 0.61, 0.70];
    for (k, z) in depths.iter().enumerate() {
        let truth = Pose::from_parts(
            Translation3::new(0.01 * k as f64, 0.0, *z),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
        );
        let scene = Scene::single_marker(CodeSet::Shoal, 10, 0.1, truth);
        let img = renderer
            .render(
                &cam,
                &Pose::identity(),
                &scene,
                &WaterParams::preset(0.5),
                0.1 * k as f64,
                k as u64,
            )
            .unwrap()
            .image;
        // Colour frames, as cameras write them (the built-in encoder's grey path asserts in 4.6).
        let mut bgr = opencv::core::Mat::default();
        opencv::imgproc::cvt_color_def(
            &gray_as_mat(&img).unwrap(),
            &mut bgr,
            opencv::imgproc::COLOR_GRAY2BGR,
        )
        .unwrap();
        writer.write(&bgr).unwrap();
    }
    writer.release().unwrap();
    let broken = dir.join("broken.mp4");
    std::fs::write(&broken, b"\x00\x00\x00\x18ftypmp42 truncated").unwrap();

    let mut out = Vec::new();
    let sum = detect_paths(
        &[&avi, &broken],
        CodeSet::Shoal,
        Some(cam),
        Some(0.1),
        &mut out,
    )
    .unwrap();
    assert_eq!(
        (sum.files, sum.frames, sum.detections, sum.errors),
        (2, 3, 3, 1),
        "{}",
        String::from_utf8_lossy(&out)
    );
    let lines: Vec<serde_json::Value> = String::from_utf8(out)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    for (k, z) in depths.iter().enumerate() {
        let det = &lines[k];
        assert_eq!(det["frame"], k, "{det}");
        assert_eq!(det["id"], 10);
        assert!(det["source"].as_str().unwrap().ends_with("swim.avi"));
        let got = det["camera_from_marker"]["t_m"][2].as_f64().unwrap();
        // JPEG-compressed frames: a few millimetres is what we ask.
        assert!((got - z).abs() < 0.005, "frame {k}: z = {got}, truth {z}");
    }
    assert!(
        lines[3]["error"]
            .as_str()
            .unwrap()
            .contains("cannot open as a video"),
        "{}",
        lines[3]
    );
    std::fs::remove_dir_all(&dir).ok();
}
