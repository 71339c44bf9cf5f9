//! Per-frame cost on 1440x1080 frames, one thread: shoal's detection + pose
//! (12 corners, IPPE + LM + covariance) beside OpenCV's ArUco detector alone,
//! on the same simulated frames (an enhanced marker 610 mm away at yaw 30°,
//! water c = 1.38 /m; OpenCV reads its code square as ArUco 4x4_50), and
//! libapriltag 3 alone on frames of an AprilTag 36h11 of the same footprint
//! and pose.
//!
//! `cargo bench -p shoal-node --bench detect`

use criterion::{criterion_group, criterion_main, Criterion};
use nalgebra::{Translation3, UnitQuaternion, Vector3};
use opencv::core::Mat;
use shoal_node::baseline::{AprilTag, OpenCvAruco};
use shoal_node::detect::{DetectParams, MarkerDetector, ShoalDetector};
use shoal_node::mat::gray_as_mat;
use shoal_node::pose::estimate_pose;
use shoal_proto::{camera::CameraModel, geometry::Pose, marker::CodeSet};
use shoal_sim_bridge::render::{Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;

const SIDE_M: f64 = 0.1;

fn frames(codes: CodeSet) -> Vec<Mat> {
    let cam = CameraModel::vehicle_1440();
    let mut r = Renderer::new();
    (0..4)
        .map(|k| {
            let pose = Pose::from_parts(
                Translation3::new(0.03 * f64::from(k) - 0.05, 0.01, 0.61),
                UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
                    * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 30f64.to_radians()),
            );
            let scene = Scene::single_marker(codes, 17, SIDE_M, pose);
            let img = r
                .render(
                    &cam,
                    &Pose::identity(),
                    &scene,
                    &WaterParams::preset(1.38),
                    f64::from(k),
                    k as u64,
                )
                .expect("render")
                .image;
            gray_as_mat(&img).expect("mat").clone_pointee()
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    opencv::core::set_num_threads(1).expect("threads");
    let tag_frames = frames(CodeSet::AprilTag36h11);
    let frames = frames(CodeSet::Shoal);
    let mut apriltag = AprilTag::new(CodeSet::AprilTag36h11).expect("apriltag");
    for f in &tag_frames {
        assert_eq!(apriltag.detect(f).expect("apriltag").len(), 1);
    }
    let cam = CameraModel::vehicle_1440();
    let mut shoal = ShoalDetector::new(CodeSet::Shoal, DetectParams::default());
    let mut aruco = OpenCvAruco::new(CodeSet::Shoal).expect("aruco");
    for f in &frames {
        assert_eq!(shoal.detect(f).expect("shoal").len(), 1);
        assert_eq!(aruco.detect(f).expect("aruco").len(), 1);
    }
    let mut g = c.benchmark_group("detect_1440x1080");
    g.bench_function("shoal_detect_and_pose", |b| {
        let mut i = 0;
        b.iter(|| {
            let f = &frames[i % frames.len()];
            i += 1;
            // As the node calls it: HOIRM passes 1.38 /m through, so the
            // restored frame is the raw one, and the corners are fitted to
            // it with the halo profile.
            let found = shoal.detect_restored(f, f).expect("detect");
            for d in &found {
                let _ = estimate_pose(&cam, &d.object_points(SIDE_M), &d.corners_px, None);
            }
            found.len()
        })
    });
    g.bench_function("opencv_aruco_detect", |b| {
        let mut i = 0;
        b.iter(|| {
            let f = &frames[i % frames.len()];
            i += 1;
            aruco.detect(f).expect("detect").len()
        })
    });
    g.bench_function("apriltag3_detect", |b| {
        let mut i = 0;
        b.iter(|| {
            let f = &tag_frames[i % tag_frames.len()];
            i += 1;
            apriltag.detect(f).expect("detect").len()
        })
    });
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(30);
    targets = bench
}
criterion_main!(benches);
