//! `detect_paths`: one JSON line per detection, with pose; clear error lines for bad files.

use nalgebra::{Translation3, UnitQuaternion, Vector3};
use opencv::core::Vector;
use opencv::imgcodecs;
use opencv::prelude::*;
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
    let junk_err = lines[1]["error"].as_str().unwrap();
    assert!(junk_err.contains("not an image"), "{junk_err}");
    let missing_err = lines[2]["error"].as_str().unwrap();
    assert!(missing_err.contains("No such file"), "{missing_err}");
    std::fs::remove_dir_all(&dir).ok();
}

/// The video path: every frame of an MJPEG AVI is read, numbered from 0 and
/// solved; a file with a video extension that no backend can open is an
/// error line, not a silent skip.
#[test]
fn reads_every_frame_of_a_video_and_numbers_them() {
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
    // The same video cut inside its first frame (the header still declares three;
    // the decoder returns what it has of the first without an error).
    let bytes = std::fs::read(&avi).unwrap();
    let cut = dir.join("cut.avi");
    std::fs::write(&cut, &bytes[..bytes.len() / 4]).unwrap();

    let mut out = Vec::new();
    let sum = detect_paths(
        &[&avi, &broken, &cut],
        CodeSet::Shoal,
        Some(cam),
        Some(0.1),
        &mut out,
    )
    .unwrap();
    assert_eq!(
        (sum.files, sum.files - sum.errors, sum.errors),
        (3, 1, 2),
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
    // What the cut video gave is printed, then the error saying it is short.
    let last = lines.last().unwrap();
    assert!(
        last["source"].as_str().unwrap().ends_with("cut.avi"),
        "{last}"
    );
    let err = last["error"].as_str().unwrap_or_default();
    assert!(err.contains("of the 3 frames"), "{last}");
    std::fs::remove_dir_all(&dir).ok();
}

/// A folder is its image files, sorted by name, as the node's `images:`
/// source plays them; a folder without images is one error line naming it.
#[test]
fn a_folder_is_read_as_its_images_in_name_order() {
    let dir = scratch("folder");
    let cam = CameraModel::vehicle_1440();
    for (name, z) in [("b.png", 0.61), ("a.png", 0.8)] {
        imgcodecs::imwrite(
            dir.join(name).to_str().unwrap(),
            &marker_frame(&cam, z),
            &Vector::new(),
        )
        .unwrap();
    }
    std::fs::write(dir.join("notes.txt"), b"not an image, not listed").unwrap();
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).unwrap();

    let mut out = Vec::new();
    let sum = detect_paths(
        &[&dir, &empty],
        CodeSet::Shoal,
        Some(cam),
        Some(0.1),
        &mut out,
    )
    .unwrap();
    assert_eq!(
        (sum.files, sum.frames, sum.detections, sum.errors),
        (3, 2, 2, 1)
    );
    let lines = json_lines(out);
    let sources: Vec<&str> = lines
        .iter()
        .map(|l| l["source"].as_str().unwrap())
        .collect();
    assert!(
        sources[0].ends_with("a.png") && sources[1].ends_with("b.png"),
        "{sources:?}"
    );
    let zs: Vec<f64> = lines[..2]
        .iter()
        .map(|l| l["camera_from_marker"]["t_m"][2].as_f64().unwrap())
        .collect();
    assert!(
        (zs[0] - 0.8).abs() < 0.005 && (zs[1] - 0.61).abs() < 0.005,
        "{zs:?}"
    );
    let err = lines[2]["error"].as_str().unwrap();
    assert!(
        lines[2]["source"].as_str().unwrap().ends_with("empty") && err.contains("no image files"),
        "{}",
        lines[2]
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// A marker at `z` metres in front of `cam`, in clear water, as 8-bit grey.
fn marker_frame(cam: &CameraModel, z: f64) -> opencv::core::Mat {
    let truth = Pose::from_parts(
        Translation3::new(0.0, 0.0, z),
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
    );
    let scene = Scene::single_marker(CodeSet::Shoal, 15, 0.1, truth);
    let img = Renderer::new()
        .render(
            cam,
            &Pose::identity(),
            &scene,
            &WaterParams::preset(0.5),
            0.0,
            2,
        )
        .unwrap()
        .image;
    gray_as_mat(&img).unwrap().try_clone().unwrap()
}

fn scratch(tag: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("shoal_detect_{tag}_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn json_lines(out: Vec<u8>) -> Vec<serde_json::Value> {
    String::from_utf8(out)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

/// Issue #22: a 1-row image 1 200 px wide aborted the whole batch with an
/// OpenCV assertion naming no file; a truncated JPEG was read as a whole
/// picture with a grey bottom. Now the thin image has no markers, the cut
/// JPEG is an error line naming what is missing, and the good file after
/// both is still read.
#[test]
fn a_thin_image_or_a_cut_jpeg_costs_only_itself() {
    let dir = scratch("thin");
    let cam = CameraModel::vehicle_1440();
    let thin = dir.join("thin.png");
    let row = opencv::core::Mat::new_rows_cols_with_default(
        1,
        1200,
        opencv::core::CV_8UC1,
        opencv::core::Scalar::all(128.0),
    )
    .unwrap();
    imgcodecs::imwrite(thin.to_str().unwrap(), &row, &Vector::new()).unwrap();
    let good = dir.join("good.jpg");
    let frame = marker_frame(&cam, 0.61);
    imgcodecs::imwrite(good.to_str().unwrap(), &frame, &Vector::new()).unwrap();
    let bytes = std::fs::read(&good).unwrap();
    let cut = dir.join("cut.jpg");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    assert!(frame.rows() > 100);

    let mut out = Vec::new();
    let sum = detect_paths(&[&thin, &cut, &good], CodeSet::Shoal, None, None, &mut out).unwrap();
    let text = String::from_utf8_lossy(&out).into_owned();
    assert_eq!(
        (sum.files, sum.frames, sum.detections, sum.errors),
        (3, 2, 1, 1),
        "{text}"
    );
    let lines = json_lines(out);
    let err = lines[0]["error"].as_str().unwrap();
    assert!(lines[0]["source"].as_str().unwrap().ends_with("cut.jpg"));
    assert!(
        err.contains("truncated") && err.contains("end-of-image"),
        "{err}"
    );
    assert_eq!(lines[1]["id"], 15);
    std::fs::remove_dir_all(&dir).ok();
}

/// Issue #22: 12-bit data in a 16-bit PNG was squashed to 16 grey levels
/// (the top byte) with no word said; now it is scaled from its significant
/// bits, the marker is found, and a warning line says what was done.
#[test]
fn twelve_bit_frames_keep_their_contrast_and_say_so() {
    let dir = scratch("twelve");
    let cam = CameraModel::vehicle_1440();
    let frame = marker_frame(&cam, 0.61);
    let mut wide = opencv::core::Mat::default();
    // 8-bit values x 16: a 12-bit camera's range, in a 16-bit PNG.
    frame
        .convert_to(&mut wide, opencv::core::CV_16U, 16.0, 0.0)
        .unwrap();
    let png = dir.join("mono12.png");
    imgcodecs::imwrite(png.to_str().unwrap(), &wide, &Vector::new()).unwrap();
    let mut out = Vec::new();
    let sum = detect_paths(&[&png], CodeSet::Shoal, Some(cam), Some(0.1), &mut out).unwrap();
    let text = String::from_utf8_lossy(&out).into_owned();
    assert_eq!(
        (sum.frames, sum.detections, sum.warnings),
        (1, 1, 1),
        "{text}"
    );
    let lines = json_lines(out);
    assert!(
        lines[0]["warning"]
            .as_str()
            .unwrap()
            .contains("12 significant bits"),
        "{text}"
    );
    let z = lines[1]["camera_from_marker"]["t_m"][2].as_f64().unwrap();
    assert!((z - 0.61).abs() < 0.005, "z = {z}");
    std::fs::remove_dir_all(&dir).ok();
}

/// Issue #22: a 2448x2048 calibration on 1440x1080 frames printed 19.6 m
/// for 1.8 m. Now a frame the calibration does not fit is an error line with
/// both sizes and no pose; a stream resized from the calibrated sensor (same
/// aspect) gets the scaled calibration, the right pose, and a warning.
#[test]
fn the_calibration_must_fit_the_frame() {
    let dir = scratch("fit");
    let cam = CameraModel::vehicle_1440();
    let frame = marker_frame(&cam, 0.61);
    let full = dir.join("full.png");
    imgcodecs::imwrite(full.to_str().unwrap(), &frame, &Vector::new()).unwrap();
    let mut half = opencv::core::Mat::default();
    opencv::imgproc::resize(
        &frame,
        &mut half,
        opencv::core::Size::new(720, 540),
        0.0,
        0.0,
        opencv::imgproc::INTER_AREA,
    )
    .unwrap();
    let small = dir.join("half.png");
    imgcodecs::imwrite(small.to_str().unwrap(), &half, &Vector::new()).unwrap();

    // Another camera's calibration: refused per file, with both sizes.
    let mut out = Vec::new();
    let sum = detect_paths(
        &[&full],
        CodeSet::Shoal,
        Some(CameraModel::paper_eq3()),
        Some(0.1),
        &mut out,
    )
    .unwrap();
    assert_eq!((sum.frames, sum.detections, sum.errors), (0, 0, 1));
    let lines = json_lines(out);
    let err = lines[0]["error"].as_str().unwrap();
    assert!(
        err.contains("1440x1080") && err.contains("2448x2048"),
        "{err}"
    );

    // The sensor's own calibration on a half-size stream.
    let mut out = Vec::new();
    let sum = detect_paths(&[&small], CodeSet::Shoal, Some(cam), Some(0.1), &mut out).unwrap();
    let text = String::from_utf8_lossy(&out).into_owned();
    assert_eq!(
        (sum.detections, sum.errors, sum.warnings),
        (1, 0, 1),
        "{text}"
    );
    let lines = json_lines(out);
    assert!(lines[0]["warning"]
        .as_str()
        .unwrap()
        .contains("scaled by 0.5000"));
    let z = lines[1]["camera_from_marker"]["t_m"][2].as_f64().unwrap();
    assert!((z - 0.61).abs() < 0.01, "z = {z}");
    assert!(frame.cols() == 1440);

    // Absurd distortion and a negative marker side end the run before any file.
    let mut folded = cam;
    folded.distortion = shoal_proto::Distortion::PlumbBob([-2.0, 0.0, 0.0, 0.0, 0.0]);
    let e = detect_paths(
        &[&full],
        CodeSet::Shoal,
        Some(folded),
        Some(0.1),
        &mut Vec::new(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("not a valid calibration"), "{e}");
    let e = detect_paths(
        &[&full],
        CodeSet::Shoal,
        Some(cam),
        Some(-0.1),
        &mut Vec::new(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("not a positive length"), "{e}");
    std::fs::remove_dir_all(&dir).ok();
}
