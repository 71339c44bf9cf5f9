//! The calibration files `shoal calibrate` writes, read by OpenCV's own
//! reader (`cv::FileStorage`): the same camera matrix and coefficients, for
//! every lens model (the round trip through shoal's reader is in
//! `proto/src/config.rs`).

use opencv::core::{FileStorage, FileStorage_Mode, Mat};
use opencv::prelude::*;
use shoal_proto::camera::{CameraModel, Distortion};
use shoal_proto::config::{write_calibration_yaml, CalibrationFormat};

#[test]
fn opencv_reads_the_calibrations_shoal_writes() {
    for distortion in [
        Distortion::PlumbBob([-0.1, 0.02, 0.001, -0.002, 0.003]),
        Distortion::Rational([0.5, -0.1, 0.001, 0.0, 0.01, 0.6, 0.02, 0.001]),
        Distortion::Equidistant([-0.01, 0.004, -0.002, 0.0005]),
    ] {
        let cam = CameraModel {
            width: 1280,
            height: 960,
            fx: 1200.123456789,
            fy: 1201.987654321,
            cx: 639.25,
            cy: 481.0625,
            distortion,
        };
        let text = write_calibration_yaml(&cam, CalibrationFormat::OpenCv, "cam", Some(0.25));
        let fs = FileStorage::new(
            &text,
            FileStorage_Mode::READ as i32 | FileStorage_Mode::MEMORY as i32,
            "",
        )
        .unwrap();
        assert!(fs.is_opened().unwrap());
        let k: Mat = fs.get("camera_matrix").unwrap().mat().unwrap();
        let d: Mat = fs.get("distortion_coefficients").unwrap().mat().unwrap();
        let at = |m: &Mat, r: i32, c: i32| *m.at_2d::<f64>(r, c).unwrap();
        assert_eq!(
            [
                at(&k, 0, 0),
                at(&k, 1, 1),
                at(&k, 0, 2),
                at(&k, 1, 2),
                at(&k, 2, 2)
            ],
            [cam.fx, cam.fy, cam.cx, cam.cy, 1.0]
        );
        let coeffs: Vec<f64> = (0..d.cols()).map(|i| at(&d, 0, i)).collect();
        assert_eq!(coeffs, distortion.coefficients());
        let w = fs.get("image_width").unwrap().to_i32().unwrap();
        let model = fs.get("distortion_model").unwrap().to_string().unwrap();
        assert_eq!((w, model.as_str()), (1280, distortion.ros_name()));
    }
}
