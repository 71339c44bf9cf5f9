//! The pose covariance is honest (NEES ≈ 6 with the corner noise given; on
//! rendered frames through the production path, conservative within a stated
//! factor) and both planar hypotheses are kept.

use nalgebra::{Point3, Vector6};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use shoal_node::pose::{estimate_pose, PoseError};
use shoal_proto::camera::CameraModel;
use shoal_proto::geometry::{covariance_problem, difference, pose_from_xyz_rpy};
use shoal_proto::marker::CodeSet;

fn project_all(
    cam: &CameraModel,
    pose: &shoal_proto::geometry::Pose,
    pts: &[Point3<f64>],
) -> Vec<[f64; 2]> {
    pts.iter()
        .map(|p| {
            let q = cam.project(&(pose * p)).unwrap();
            [q.x, q.y]
        })
        .collect()
}

#[test]
fn recovers_the_pose_from_clean_corners() {
    let cam = CameraModel::vehicle_1440();
    let truth = pose_from_xyz_rpy([0.05, -0.03, 0.61], [3.0, 0.5, 0.2]);
    let obj = CodeSet::Shoal.corners_3d(0.1);
    let img = project_all(&cam, &truth, &obj);
    let sol = estimate_pose(&cam, &obj, &img, Some(0.2)).unwrap();
    assert!(difference(&sol.best.camera_from_marker, &truth).norm() < 1e-8);
    assert!(sol.best.rms_px < 1e-6);
    assert_eq!(covariance_problem(&sol.best.covariance, 1.0), None);
    // IPPE's flipped alternative is kept, with a worse fit.
    let alt = sol.alternative.expect("planar target gives two hypotheses");
    assert!(alt.rms_px >= sol.best.rms_px);
}

/// Mean NEES over many noisy trials must be near the dimension, 6; the
/// tolerance 4.5..7.5 leaves room for linearization at 1 px noise while
/// catching a covariance off by a factor ~1.3 or more.
#[test]
fn covariance_is_consistent_nees_near_six() {
    let cam = CameraModel::vehicle_1440();
    let truth = pose_from_xyz_rpy([0.08, 0.02, 0.61], [std::f64::consts::PI, 0.52, 0.1]);
    let obj = CodeSet::Shoal.corners_3d(0.1);
    let clean = project_all(&cam, &truth, &obj);
    let sigma = 1.0;
    let noise = Normal::new(0.0, sigma).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let trials = 400;
    let mut sum = 0.0;
    for _ in 0..trials {
        let img: Vec<[f64; 2]> = clean
            .iter()
            .map(|u| [u[0] + noise.sample(&mut rng), u[1] + noise.sample(&mut rng)])
            .collect();
        let sol = estimate_pose(&cam, &obj, &img, Some(sigma)).unwrap();
        // Truth = perturb(estimate, ξ): ξ in the estimate's convention.
        let xi: Vector6<f64> = difference(&truth, &sol.best.camera_from_marker);
        let inv = sol.best.covariance.try_inverse().unwrap();
        sum += (xi.transpose() * inv * xi)[0];
    }
    let mean = sum / trials as f64;
    eprintln!("mean NEES over {trials} trials: {mean:.2}");
    assert!((4.5..7.5).contains(&mean), "mean NEES {mean}");
}

#[test]
fn rejects_bad_input() {
    let cam = CameraModel::vehicle_1440();
    let obj = CodeSet::Shoal.corners_3d(0.1);
    let img = vec![[1.0, 2.0]; 3];
    assert!(matches!(
        estimate_pose(&cam, &obj[..3], &img, None),
        Err(PoseError::TooFewPoints { .. })
    ));
    assert!(matches!(
        estimate_pose(&cam, &obj, &img, None),
        Err(PoseError::CountMismatch { .. })
    ));
    let nan = vec![[f64::NAN, 0.0]; 12];
    assert!(matches!(
        estimate_pose(&cam, &obj, &nan, None),
        Err(PoseError::NonFinite)
    ));
    let ok = vec![[700.0, 500.0]; 12];
    assert!(matches!(
        estimate_pose(&cam, &obj, &ok, Some(-1.0)),
        Err(PoseError::BadSigma(_))
    ));
}

/// Frames per water for the production-path test: 2 waters x 24 frames
/// render and detect in ~10 s in a debug build.
const PRODUCTION_FRAMES: u64 = 24;
/// The covariance the node reports when no corner noise is given
/// (`PipelineParams::corner_sigma_px: None`: σ estimated from the residuals,
/// floored at 0.05 px) on rendered frames read by the production chain
/// (HOIRM, `detect_restored` with the lens, `estimate_pose(.., None)`).
/// Measured mean NEES over these 24 frames: 2.5 at 0.126 /m and 2.3 at
/// 1.38 /m (2.9 and 2.5 over 30) — the covariance is ~2.4x conservative: the residuals (~0.01 px RMS) are
/// below the floor, and the floor over-covers the corners' real error.
/// Allowed: mean NEES in 1.5 … 4.5: the covariance at most 4x too large
/// (6 / 4 = 1.5; fusion then under-weighs the camera, it does not reject
/// it) and below the χ²₆ expectation of 6 by a margin, i.e. never
/// overconfident (fusion's χ² gates trust it). ±2 standard errors of a
/// 24-frame mean at the measured scale are ±0.7. Doubling the reported
/// covariance fails (measured: mean NEES 1.26); halving it lands at 4.5–5.0,
/// on or over the upper bound.
const PRODUCTION_NEES_MIN: f64 = 1.5;
const PRODUCTION_NEES_MAX: f64 = 4.5;

/// Mean NEES of the production path's best hypothesis over rendered frames
/// of the enhanced marker at `c_per_m`, random poses 0.5–1.0 m, ±0.5 rad tilt.
fn production_mean_nees(c_per_m: f64, seed: u64) -> (f64, usize) {
    use nalgebra::{Translation3, UnitQuaternion, Vector3};
    use rand::Rng;
    use shoal_node::detect::{DetectParams, MarkerDetector, ShoalDetector};
    use shoal_node::mat::gray_to_mat;
    use shoal_node::restore::{restorer, Method, RestoreParams};
    use shoal_proto::geometry::Pose;
    use shoal_sim_bridge::render::{Renderer, Scene};
    use shoal_sim_bridge::water::WaterParams;
    let cam = CameraModel::vehicle_1440();
    let water = WaterParams::preset(c_per_m);
    let mut renderer = Renderer::new();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    // As `CameraPipeline::new` builds them.
    let mut detector = ShoalDetector::new(
        CodeSet::Shoal,
        DetectParams {
            lens: Some(cam),
            ..DetectParams::default()
        },
    );
    let mut restore = restorer(Method::Hoirm, &RestoreParams::default());
    let (mut sum, mut n) = (0.0, 0usize);
    for f in 0..PRODUCTION_FRAMES {
        let truth = Pose::from_parts(
            Translation3::new(
                rng.gen_range(-0.1..0.1),
                rng.gen_range(-0.08..0.08),
                rng.gen_range(0.5..1.0),
            ),
            UnitQuaternion::from_axis_angle(
                &Vector3::x_axis(),
                std::f64::consts::PI + rng.gen_range(-0.5..0.5),
            ) * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), rng.gen_range(-0.6..0.6))
                * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), rng.gen_range(-3.0..3.0)),
        );
        let scene = Scene::single_marker(CodeSet::Shoal, 17, 0.1, truth);
        let img = renderer
            .render(
                &cam,
                &Pose::identity(),
                &scene,
                &water,
                f as f64 * 0.1,
                f + 1,
            )
            .unwrap()
            .image;
        let raw = gray_to_mat(&img).unwrap();
        let restored = restore.restore(&raw, f * 100_000_000).unwrap();
        let found = detector.detect_restored(&restored.image, &raw).unwrap();
        let Some(d) = found.iter().find(|d| d.id == 17) else {
            continue;
        };
        let sol = estimate_pose(&cam, &d.object_points(0.1), &d.corners_px, None).unwrap();
        let xi: Vector6<f64> = difference(&truth, &sol.best.camera_from_marker);
        let inv = sol.best.covariance.try_inverse().unwrap();
        sum += (xi.transpose() * inv * xi)[0];
        n += 1;
    }
    (sum / n.max(1) as f64, n)
}

/// Clear and light water only (0.126 and 1.38 /m), where the production
/// covariance errs on the cautious side. In murky water (3.92-8.22 /m) it is
/// overconfident (mean NEES 18-57, `shoal eval nees`, docs/results.md#nees):
/// the corners' errors there are correlated and the residuals do not show
/// them. That is an open finding of issue #16, not covered here.
#[test]
fn production_covariance_in_clear_water_is_conservative_within_a_factor_4() {
    for (c, seed) in [(0.126, 5), (1.38, 6)] {
        let (mean, n) = production_mean_nees(c, seed);
        eprintln!("production path at {c} /m: mean NEES {mean:.2} over {n} frames");
        assert!(
            n as u64 >= PRODUCTION_FRAMES - 1,
            "{c} /m: marker read in {n} of {PRODUCTION_FRAMES} frames"
        );
        assert!(
            (PRODUCTION_NEES_MIN..PRODUCTION_NEES_MAX).contains(&mean),
            "{c} /m: mean NEES {mean:.2} over {n} frames (allowed {PRODUCTION_NEES_MIN}..{PRODUCTION_NEES_MAX})"
        );
    }
}

/// An error of the intrinsics is the same for every corner of a frame: the
/// residuals do not show it and the corner-noise covariance alone is
/// overconfident. Drawing the intrinsics' error from the stated σ,
/// `calibration_covariance` added to the corner part must bring the mean
/// NEES back to 6 (same tolerance as the corner-noise test: 400 trials,
/// ±2 standard errors of the mean are about ±0.6), and without it the mean
/// must be far above (measured ~40: the test fails if the term is ignored).
#[test]
fn calibration_error_is_covered_by_the_calibration_covariance() {
    use shoal_node::pose::calibration_covariance;
    use shoal_proto::camera::{CalibrationSigma, Distortion};
    let truth_cam = CameraModel::vehicle_1440();
    let truth = pose_from_xyz_rpy([0.06, -0.04, 0.9], [std::f64::consts::PI, 0.4, 0.3]);
    let obj = CodeSet::Shoal.corners_3d(0.1);
    let clean = project_all(&truth_cam, &truth, &obj);
    let stated = CalibrationSigma {
        focal_rel: 0.002,
        principal_px: 1.2,
        k1: 0.003,
    };
    let corner_sigma = 0.1;
    let std = Normal::new(0.0, 1.0).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let trials = 400;
    let (mut with, mut without) = (0.0, 0.0);
    for _ in 0..trials {
        // The node's calibration: the true camera moved by one draw of the error.
        let mut node = truth_cam;
        node.fx *= 1.0 + stated.focal_rel * std.sample(&mut rng);
        node.fy *= 1.0 + stated.focal_rel * std.sample(&mut rng);
        node.cx += stated.principal_px * std.sample(&mut rng);
        node.cy += stated.principal_px * std.sample(&mut rng);
        if let Distortion::PlumbBob(k) = &mut node.distortion {
            k[0] += stated.k1 * std.sample(&mut rng);
        }
        let img: Vec<[f64; 2]> = clean
            .iter()
            .map(|u| {
                [
                    u[0] + corner_sigma * std.sample(&mut rng),
                    u[1] + corner_sigma * std.sample(&mut rng),
                ]
            })
            .collect();
        let sol = estimate_pose(&node, &obj, &img, Some(corner_sigma)).unwrap();
        let est = sol.best.camera_from_marker;
        let cal = calibration_covariance(&node, None, &obj, &est, &stated).unwrap();
        // Rank ≤ 5 (five intrinsics): positive semi-definite, not definite.
        let eig = cal.symmetric_eigen().eigenvalues;
        assert!(eig.iter().all(|e| *e >= -1e-12 * eig.amax()), "{eig}");
        let xi: Vector6<f64> = difference(&truth, &est);
        let total = sol.best.covariance + cal;
        with += (xi.transpose() * total.try_inverse().unwrap() * xi)[0];
        without += (xi.transpose() * sol.best.covariance.try_inverse().unwrap() * xi)[0];
    }
    let (with, without) = (with / trials as f64, without / trials as f64);
    eprintln!("mean NEES: {with:.2} with the calibration term, {without:.2} without");
    assert!(
        (5.2..6.8).contains(&with),
        "with the calibration term: {with}"
    );
    assert!(without > 15.0, "without it: {without}");
    // An invalid σ is refused, not propagated.
    let bad = CalibrationSigma {
        focal_rel: -1.0,
        ..stated
    };
    assert_eq!(
        calibration_covariance(&truth_cam, None, &obj, &truth, &bad),
        None
    );
}

/// Corners that one whole-pattern fit gives move together: the fit's
/// error is one of its four outer corners, and every other corner follows
/// through the homography. The residuals then stay at the independent
/// noise while the pose moves. Drawing the outer corners' error from a
/// stated σ, `corner_covariance` of the corners' covariance (`G Σ Gᵀ`,
/// `G` their Jacobian in the outer corners) added to the residual part must
/// bring the mean NEES to 6 (±2 standard errors of 400 trials, as above),
/// and without it the mean must be far above (measured 6.06 with, 542
/// without).
#[test]
fn correlated_corner_errors_are_covered_by_the_corner_covariance() {
    use shoal_node::detect::geom::{apply, homography_4};
    use shoal_node::pose::corner_covariance;
    let cam = CameraModel::vehicle_1440();
    let truth = pose_from_xyz_rpy([0.05, 0.03, 1.2], [std::f64::consts::PI, 0.35, 0.2]);
    let obj = CodeSet::Shoal.corners_3d(0.1);
    let clean = project_all(&cam, &truth, &obj);
    let outer: [[f64; 2]; 4] = [clean[0], clean[1], clean[2], clean[3]];
    let moved = |d: &[f64; 8]| -> Vec<[f64; 2]> {
        let mut o = outer;
        for (k, v) in d.iter().enumerate() {
            o[k / 2][k % 2] += v;
        }
        let h = homography_4(&outer, &o).unwrap();
        clean.iter().map(|&u| apply(&h, u)).collect()
    };
    // G: the corners' Jacobian in the outer corners (central differences).
    let n = 2 * clean.len();
    let mut g = nalgebra::DMatrix::zeros(n, 8);
    for c in 0..8 {
        let mut d = [0.0; 8];
        d[c] = 1e-4;
        let plus = moved(&d);
        d[c] = -1e-4;
        let minus = moved(&d);
        for k in 0..clean.len() {
            g[(2 * k, c)] = (plus[k][0] - minus[k][0]) / 2e-4;
            g[(2 * k + 1, c)] = (plus[k][1] - minus[k][1]) / 2e-4;
        }
    }
    let (outer_sigma, corner_sigma) = (0.3, 0.05);
    let cov_u = &g * g.transpose() * (outer_sigma * outer_sigma);
    let std = Normal::new(0.0, 1.0).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(21);
    let trials = 400;
    let (mut with, mut without) = (0.0, 0.0);
    for _ in 0..trials {
        let d: [f64; 8] = std::array::from_fn(|_| outer_sigma * std.sample(&mut rng));
        let img: Vec<[f64; 2]> = moved(&d)
            .iter()
            .map(|u| {
                [
                    u[0] + corner_sigma * std.sample(&mut rng),
                    u[1] + corner_sigma * std.sample(&mut rng),
                ]
            })
            .collect();
        let sol = estimate_pose(&cam, &obj, &img, Some(corner_sigma)).unwrap();
        let est = sol.best.camera_from_marker;
        let extra = corner_covariance(&cam, None, &obj, &est, &cov_u).unwrap();
        let xi: Vector6<f64> = difference(&truth, &est);
        let total = sol.best.covariance + extra;
        with += (xi.transpose() * total.try_inverse().unwrap() * xi)[0];
        without += (xi.transpose() * sol.best.covariance.try_inverse().unwrap() * xi)[0];
    }
    let (with, without) = (with / trials as f64, without / trials as f64);
    eprintln!("mean NEES: {with:.2} with the corner covariance, {without:.2} without");
    assert!((5.2..6.8).contains(&with), "with the corner term: {with}");
    assert!(without > 15.0, "without it: {without}");
    // A covariance of the wrong size or not finite is refused.
    let small = nalgebra::DMatrix::<f64>::identity(8, 8);
    assert_eq!(corner_covariance(&cam, None, &obj, &truth, &small), None);
    let mut nan = cov_u.clone();
    nan[(0, 0)] = f64::NAN;
    assert_eq!(corner_covariance(&cam, None, &obj, &truth, &nan), None);
}
