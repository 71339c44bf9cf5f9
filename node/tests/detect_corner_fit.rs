//! The detector's corner stage on rendered frames of the accuracy test's
//! set-up (paper §6.2: the 100 mm enhanced marker at 610 mm, yaw 30°): which
//! fit gives the corners in which water ([`Detection::corner_fit`]), and
//! that each fit is as accurate as it is chosen for.

use opencv::core::Mat;
use shoal_node::detect::geom::dist;
use shoal_node::detect::{
    CornerFit, CornerFitCounts, DetectError, DetectParams, Detection, FitPattern, FitReason,
    MarkerDetector, Refinement, ShoalDetector, SquareCorners,
};
use shoal_node::restore::{restorer, Method, RestoreParams, Restorer};
use shoal_proto::camera::CameraModel;
use shoal_proto::geometry::Pose;
use shoal_proto::image::GrayImage;
use shoal_proto::marker::CodeSet;
use shoal_sim_bridge::render::{facing_camera, Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;

/// Position (mm) and rotation (deg) errors of the best pose of marker 17
/// among `found`, and its corner count.
fn errors_of_17(found: &[Detection], truth: &Pose) -> (f64, f64, usize) {
    let cam = CameraModel::vehicle_1440();
    let d = found.iter().find(|d| d.id == 17).expect("marker 17");
    let sol = shoal_node::pose::estimate_pose(&cam, &d.object_points(0.1), &d.corners_px, None)
        .expect("pose");
    let est = sol.best.camera_from_marker;
    let dd = (est.translation.vector - truth.translation.vector).norm() * 1e3;
    let da = (est.rotation * truth.rotation.inverse())
        .angle()
        .to_degrees();
    (dd, da, d.corners_px.len())
}

/// Marker 17 of the enhanced set (100 mm) at `truth`, seen by the vehicle camera.
fn render_17(
    renderer: &mut Renderer,
    truth: Pose,
    water: &WaterParams,
    time_s: f64,
    seed: u64,
) -> GrayImage {
    let scene = Scene::single_marker(CodeSet::Shoal, 17, 0.1, truth);
    renderer
        .render(
            &CameraModel::vehicle_1440(),
            &Pose::identity(),
            &scene,
            water,
            time_s,
            seed,
        )
        .expect("render")
        .image
}

/// Frame `k` of the accuracy test's pose (jittered by `k · step`) in
/// water `c_per_m`, noise `seed`, restored by `hoirm`: `(raw, restored,
/// the twelve corners' true pixels)`.
fn accuracy_frame(
    renderer: &mut Renderer,
    hoirm: &mut dyn Restorer,
    c_per_m: f64,
    k: u64,
    step: f64,
    seed: u64,
) -> (Mat, Mat, Vec<[f64; 2]>) {
    let cam = CameraModel::vehicle_1440();
    let j = k as f64 * step;
    let truth = facing_camera([j, -j, 0.61 - j], [0.002, (30.0 + j).to_radians(), 0.001]);
    let water = WaterParams::preset(c_per_m);
    let img = render_17(renderer, truth, &water, k as f64 * 0.1, seed);
    let truth_px = CodeSet::Shoal
        .corners_3d(0.1)
        .iter()
        .map(|p| {
            let q = cam.project(&(truth * p)).expect("in front");
            [q.x, q.y]
        })
        .collect();
    let raw = shoal_node::mat::gray_to_mat(&img).expect("mat");
    let restored = hoirm.restore(&raw, k * 100_000_000).expect("restore").image;
    (raw, restored, truth_px)
}

/// Marker 17 with all twelve corners among `found`.
fn twelve(found: Vec<Detection>) -> Option<Detection> {
    found
        .into_iter()
        .find(|d| d.id == 17 && d.corners_px.len() == 12)
}

/// Sum of squared corner errors (px²) of `d` against `truth_px`.
fn squared_error(d: &Detection, truth_px: &[[f64; 2]]) -> f64 {
    d.corner_ids
        .iter()
        .zip(&d.corners_px)
        .map(|(&c, p)| dist(*p, truth_px[c as usize]).powi(2))
        .sum()
}

#[test]
fn edge_model_recovers_the_accuracy_test_pose_to_hundredths_of_a_degree() {
    // Clear water, no sensor noise; three sub-pixel phases. The
    // gradient-peak edge lines lock to the pixel grid (~0.03° here); the
    // step model must not.
    /// Angle bound: half the edge lines' phase-locked error (0.031° median
    /// on these frames, `docs/detector.md`); the step model gives ~0.007°.
    const MAX_ANGLE_DEG: f64 = 0.015;
    /// Distance bound: twice the lens-distortion scale bias of a straight
    /// line through a bowed side (~0.09 mm at 610 mm, `docs/detector.md`).
    const MAX_DISTANCE_MM: f64 = 0.2;
    let water = WaterParams::preset(0.126).noiseless();
    let mut renderer = Renderer::new();
    let mut det = ShoalDetector::new(CodeSet::Shoal, DetectParams::default());
    assert_eq!(det.params().refinement, Refinement::EdgeModel);
    for (k, dx) in [0.0, 0.00037, 0.00081].into_iter().enumerate() {
        let truth = facing_camera([dx, -0.0004, 0.61], [0.001, 30f64.to_radians(), 0.002]);
        let img = render_17(&mut renderer, truth, &water, 0.0, k as u64);
        let found = det.detect_gray(&img).expect("detect");
        let (dd, da, n) = errors_of_17(&found, &truth);
        assert_eq!(n, 12, "all twelve corners");
        assert!(da < MAX_ANGLE_DEG, "frame {k}: angle error {da:.4}°");
        assert!(dd < MAX_DISTANCE_MM, "frame {k}: distance error {dd:.3} mm");
        // One image only: the sides are fitted on it, no pattern fit.
        let fit = &found.iter().find(|d| d.id == 17).expect("17").corner_fit;
        assert_eq!(
            (fit.fit, fit.reason),
            (CornerFit::RestoredSides, FitReason::NoRawFrame)
        );
    }
}

#[test]
fn raw_fits_in_clear_water_keep_every_frame_within_three_hundredths_of_a_degree() {
    // Clear water with sensor noise, the node's call (HOIRM passes clear
    // water through: restored = raw). A halo profile on these sharp sides
    // put one frame in eight at 0.05–0.26°; they must stay one Gaussian.
    /// The clear-water accuracy the one-Gaussian rule keeps: without it one
    /// of these twelve frames reached 0.035° (`docs/detector.md`).
    const MAX_ANGLE_DEG: f64 = 0.03;
    let cam = CameraModel::vehicle_1440();
    let mut renderer = Renderer::new();
    let mut det = ShoalDetector::new(CodeSet::Shoal, DetectParams::default());
    for k in 0..12u64 {
        let j = k as f64 * 1e-4;
        let truth = facing_camera([j, -j, 0.6 + j], [0.001, (20.0 + j).to_radians(), -0.002]);
        let img = render_17(&mut renderer, truth, &WaterParams::preset(0.126), 0.0, k);
        let mat = shoal_node::mat::gray_to_mat(&img).expect("mat");
        let found = MarkerDetector::detect_restored(&mut det, &mat, &mat).expect("detect");
        let d = found.iter().find(|d| d.id == 17).expect("marker 17");
        let sol = shoal_node::pose::estimate_pose(&cam, &d.object_points(0.1), &d.corners_px, None)
            .expect("pose");
        let da = (sol.best.camera_from_marker.rotation * truth.rotation.inverse())
            .angle()
            .to_degrees();
        assert!(da < MAX_ANGLE_DEG, "frame {k}: angle error {da:.4}°");
        // Sharp raw edges: one Gaussian on every square, strong enough
        // that the pattern fit is not wanted.
        let fit = &d.corner_fit;
        assert_eq!(fit.fit, CornerFit::RawSides, "frame {k}: {fit:?}");
        assert!(
            fit.squares
                .iter()
                .all(|s| s.corners == SquareCorners::RawSharp),
            "frame {k}: {fit:?}"
        );
        assert!(
            matches!(fit.reason, FitReason::EdgesStrong { step_dn } if step_dn >= 16.0),
            "frame {k}: {fit:?}"
        );
    }
}

#[test]
fn turbid_corners_fitted_on_the_raw_frame_beat_the_restored_ones() {
    // 5.16 /m, the accuracy test's pose, eight frames through HOIRM: the
    // twelve corners fitted on the raw frame (halo profile) must beat those
    // fitted on the restoration.
    const FRAMES: u64 = 8;
    /// Frames allowed without twelve corners in either call. Measured: all
    /// eight read twelve in both; six frames (72 corners) still tell an rms
    /// ratio of 0.53 from one of 0.8.
    const MAX_UNREAD_FRAMES: u64 = 2;
    /// Raw over restored rms: 0.53 measured on these frames (0.116 vs
    /// 0.219 px, `docs/detector.md`); 0.8 still says the raw fit is better.
    const MAX_RMS_RATIO: f64 = 0.8;
    let mut renderer = Renderer::new();
    let mut hoirm = restorer(Method::Hoirm, &RestoreParams::default());
    // The side fits (the whole-pattern fit would take over at 5.16 /m:
    // its raw steps are 7–8 grey levels).
    let mut det = ShoalDetector::new(
        CodeSet::Shoal,
        DetectParams {
            fit_pattern: FitPattern::Never,
            ..DetectParams::default()
        },
    );
    let (mut sq_raw, mut sq_restored, mut frames) = (0.0, 0.0, 0u64);
    for k in 0..FRAMES {
        let (raw, restored, truth_px) =
            accuracy_frame(&mut renderer, hoirm.as_mut(), 5.16, k, 2e-4, 100 + k);
        let a = twelve(det.detect_with_raw_fit(&restored, &raw).expect("detect"));
        let b = twelve(det.detect_in(&restored).expect("detect"));
        if let (Some(a), Some(b)) = (a, b) {
            assert_eq!(a.corner_fit.reason, FitReason::PatternNever);
            assert_eq!(a.corner_fit.fit, CornerFit::RawSides, "{:?}", a.corner_fit);
            assert_eq!(b.corner_fit.fit, CornerFit::RestoredSides);
            sq_raw += squared_error(&a, &truth_px);
            sq_restored += squared_error(&b, &truth_px);
            frames += 1;
        }
    }
    assert!(
        frames + MAX_UNREAD_FRAMES >= FRAMES,
        "twelve corners in {frames} of {FRAMES} frames"
    );
    let n = (12 * frames) as f64;
    let (rms_raw, rms_restored) = ((sq_raw / n).sqrt(), (sq_restored / n).sqrt());
    eprintln!("{frames} of {FRAMES} frames; corner rms: raw {rms_raw:.3} px, restored {rms_restored:.3} px");
    assert!(
        rms_raw < MAX_RMS_RATIO * rms_restored,
        "raw {rms_raw:.3} px vs restored {rms_restored:.3} px"
    );
}

#[test]
fn a_turbid_marker_is_read_on_the_restoration_and_fitted_on_the_raw_frame() {
    // 5.16 /m, the accuracy test's pose: HOIRM's restoration for the quads
    // and the code, the raw frame for the corner fits.
    /// Bounds an order of magnitude above the pattern fit's medians at
    /// 5.16 /m (0.066 mm / 0.035°, `docs/detector.md`): one frame, noise.
    const MAX_ANGLE_DEG: f64 = 0.3;
    const MAX_DISTANCE_MM: f64 = 1.0;
    let truth = facing_camera([0.0004, -0.0003, 0.61], [0.002, 30f64.to_radians(), 0.001]);
    let img = render_17(
        &mut Renderer::new(),
        truth,
        &WaterParams::preset(5.16),
        0.0,
        3,
    );
    let raw = shoal_node::mat::gray_to_mat(&img).expect("mat");
    let restored = restorer(Method::Hoirm, &RestoreParams::default())
        .restore(&raw, 0)
        .expect("restore")
        .image;
    let mut det = ShoalDetector::new(CodeSet::Shoal, DetectParams::default());
    let found = det.detect_with_raw_fit(&restored, &raw).expect("detect");
    let (dd, da, n) = errors_of_17(&found, &truth);
    assert_eq!(n, 12, "all twelve corners");
    assert!(
        da < MAX_ANGLE_DEG && dd < MAX_DISTANCE_MM,
        "errors {dd:.3} mm, {da:.3}°"
    );
    // The raw steps at 5.16 /m are under the pattern fit's threshold: the
    // whole pattern gives the corners, and says why.
    let fit = &found.iter().find(|d| d.id == 17).expect("17").corner_fit;
    assert_eq!(fit.fit, CornerFit::Pattern, "{fit:?}");
    assert!(
        matches!(fit.reason, FitReason::EdgesWeak { step_dn } if step_dn < 16.0),
        "{fit:?}"
    );
    // What the node's status counts for this frame.
    let counts: CornerFitCounts = found.iter().collect();
    assert_eq!(counts.get(CornerFit::Pattern), 1);
    assert_eq!(counts.total(), found.len() as u64);
    // The two frames must be the same size.
    let half = shoal_node::mat::gray_to_mat(&GrayImage {
        width: img.width / 2,
        height: img.height / 2,
        data: vec![0; (img.width / 2 * img.height / 2) as usize],
    })
    .expect("mat");
    assert!(matches!(
        det.detect_with_raw_fit(&restored, &half),
        Err(DetectError::FrameSizes { .. })
    ));
}

#[test]
fn a_marker_in_murky_water_is_fitted_as_one_pattern() {
    // 8.22 /m, the accuracy test's pose, through HOIRM: no side fit holds
    // on the raw frame, and the whole-pattern fit must bring the twelve
    // corners' rms error well under that of the restored-frame side fits,
    // without the inward bias of the dark one-module bands.
    const FRAMES: u64 = 6;
    /// Frames allowed without twelve corners in either detector. Measured:
    /// one of these six (k = 4) reads eight — its outer frame square is
    /// neither a contour nor accepted from the prediction
    /// (`NotTwelveCorners`); each corner's mean error needs at least four
    /// frames, so at most two may be lost.
    const MAX_UNREAD_FRAMES: u64 = 2;
    /// Pattern over side-fit rms: 0.24 measured on these frames (0.23 vs
    /// 0.97 px); 0.6 still says the pattern fit is clearly better.
    const MAX_RMS_RATIO: f64 = 0.6;
    /// Worst corner's mean error over the frames: 0.24 px measured; the
    /// pattern without the gain gradient across the tilted marker gave 0.5.
    const MAX_CORNER_BIAS_PX: f64 = 0.35;
    let mut renderer = Renderer::new();
    let mut hoirm = restorer(Method::Hoirm, &RestoreParams::default());
    let with_lens = DetectParams {
        lens: Some(CameraModel::vehicle_1440()),
        ..DetectParams::default()
    };
    let mut with = ShoalDetector::new(CodeSet::Shoal, with_lens.clone());
    let mut without = ShoalDetector::new(
        CodeSet::Shoal,
        DetectParams {
            fit_pattern: FitPattern::Never,
            ..with_lens
        },
    );
    let (mut sq_with, mut sq_without, mut frames) = (0.0, 0.0, 0u64);
    let mut bias = [[0.0f64; 2]; 12];
    for k in 0..FRAMES {
        let (raw, restored, truth_px) =
            accuracy_frame(&mut renderer, hoirm.as_mut(), 8.22, k, 3e-4, 300 + k);
        let a = twelve(with.detect_with_raw_fit(&restored, &raw).expect("detect"));
        let b = twelve(
            without
                .detect_with_raw_fit(&restored, &raw)
                .expect("detect"),
        );
        let (Some(a), Some(b)) = (a, b) else { continue };
        eprintln!("frame {k}: {:?} / {:?}", a.corner_fit, b.corner_fit);
        assert_eq!(a.corner_fit.fit, CornerFit::Pattern, "{:?}", a.corner_fit);
        assert_eq!(a.corner_fit.reason, FitReason::NoRawEdge);
        assert_eq!(b.corner_fit.reason, FitReason::PatternNever);
        for (&c, p) in a.corner_ids.iter().zip(&a.corners_px) {
            let t = truth_px[c as usize];
            bias[c as usize][0] += p[0] - t[0];
            bias[c as usize][1] += p[1] - t[1];
        }
        sq_with += squared_error(&a, &truth_px);
        sq_without += squared_error(&b, &truth_px);
        frames += 1;
    }
    assert!(
        frames + MAX_UNREAD_FRAMES >= FRAMES,
        "twelve corners in {frames} of {FRAMES} frames"
    );
    let n = (12 * frames) as f64;
    let (rms_with, rms_without) = ((sq_with / n).sqrt(), (sq_without / n).sqrt());
    let worst_bias = bias
        .iter()
        .map(|b| b[0].hypot(b[1]) / frames as f64)
        .fold(0.0, f64::max);
    eprintln!("{frames} of {FRAMES} frames; corner rms: pattern {rms_with:.3} px, sides {rms_without:.3} px; worst mean corner error {worst_bias:.3} px");
    assert!(
        rms_with < MAX_RMS_RATIO * rms_without,
        "pattern {rms_with:.3} px vs sides {rms_without:.3} px"
    );
    assert!(
        worst_bias < MAX_CORNER_BIAS_PX,
        "a corner biased by {worst_bias:.3} px"
    );
}
