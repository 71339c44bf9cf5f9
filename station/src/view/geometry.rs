//! Where the page draws a vehicle: poses in the map's reference frame,
//! confidence ellipses of their covariance, and errors against ground truth.

use nalgebra::{Matrix2, UnitQuaternion, Vector3};
use proto::geometry::{Cov6, Pose};
use proto::{SimTruth, VehicleId};
use serde::Serialize;
use std::collections::BTreeMap;

/// Confidence region drawn around each estimate: 3 sigma, the same as the
/// ellipsoids of the Foxglove scene in the MCAP logs (`record/src/foxglove.rs`).
pub const ELLIPSE_SIGMAS: f64 = 3.0;

/// Estimates with a position sigma above this are drawn without an ellipse
/// (they are not localized in any useful sense; the ellipse would fill the view).
pub const MAX_DRAWN_SIGMA_M: f64 = 10.0;

/// A 2-D confidence ellipse: semi-axes (metres) and the major axis' angle
/// from the view's first axis towards its second (radians).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Ellipse {
    pub semi_major_m: f64,
    pub semi_minor_m: f64,
    pub angle_rad: f64,
}

/// The `sigmas`-sigma ellipse of a 2x2 position covariance block; `None` when
/// the block is not finite, not positive semi-definite, or wider than
/// [`MAX_DRAWN_SIGMA_M`].
pub fn ellipse_of(block: &Matrix2<f64>, sigmas: f64) -> Option<Ellipse> {
    if !block.iter().all(|x| x.is_finite()) {
        return None;
    }
    let (a, c) = (block[(0, 0)], block[(1, 1)]);
    let b = 0.5 * (block[(0, 1)] + block[(1, 0)]);
    // Closed-form eigenvalues of a symmetric 2x2 matrix.
    let mean = 0.5 * (a + c);
    let radius = (0.25 * (a - c) * (a - c) + b * b).sqrt();
    let (major, minor) = (mean + radius, mean - radius);
    if minor < -1e-12 || major > MAX_DRAWN_SIGMA_M * MAX_DRAWN_SIGMA_M {
        return None;
    }
    Some(Ellipse {
        semi_major_m: sigmas * major.max(0.0).sqrt(),
        semi_minor_m: sigmas * minor.max(0.0).sqrt(),
        angle_rad: 0.5 * (2.0 * b).atan2(a - c),
    })
}

/// The position block of a pose covariance restricted to axes `i`, `j`
/// (0 x, 1 y, 2 z). The covariance is over `(δt, δθ)` with `δt` in the
/// reference frame (`proto/src/geometry.rs`), so this block is directly the
/// uncertainty of the vehicle's position in the map.
pub fn position_block(cov: &Cov6, i: usize, j: usize) -> Matrix2<f64> {
    Matrix2::new(cov[(i, i)], cov[(i, j)], cov[(j, i)], cov[(j, j)])
}

/// Where a vehicle is in the map, as the page draws it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PlacedPose {
    pub position_m: [f64; 3],
    /// The body's x axis (bow direction) in the reference frame, unit length.
    pub forward: [f64; 3],
}

impl PlacedPose {
    pub fn of(reference_from_vehicle: &Pose) -> PlacedPose {
        let t = reference_from_vehicle.translation.vector;
        let f = reference_from_vehicle.rotation * Vector3::x();
        PlacedPose {
            position_m: [t.x, t.y, t.z],
            forward: [f.x, f.y, f.z],
        }
    }
}

/// Ground truth of every simulated vehicle relative to `reference` (the
/// fused map's gauge): `reference_from_vehicle = world_from_reference⁻¹ ·
/// world_from_vehicle`. Empty when the reference is not in the truth.
pub fn truth_relative_to(truth: &SimTruth, reference: VehicleId) -> BTreeMap<VehicleId, Pose> {
    let Some(world_from_reference) = truth
        .vehicles
        .iter()
        .find(|v| v.vehicle == reference)
        .map(|v| v.world_from_body)
    else {
        return BTreeMap::new();
    };
    let reference_from_world = world_from_reference.inverse();
    truth
        .vehicles
        .iter()
        .map(|v| (v.vehicle, reference_from_world * v.world_from_body))
        .collect()
}

/// Error of an estimate against ground truth: position (metres) and
/// rotation angle (radians) of `truth⁻¹ · estimate`'s rotation.
pub fn pose_error(estimate: &Pose, truth: &Pose) -> (f64, f64) {
    let dt = (estimate.translation.vector - truth.translation.vector).norm();
    let dr: UnitQuaternion<f64> = truth.rotation.inverse() * estimate.rotation;
    (dt, dr.angle())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::view::fixtures::{pose, truth_of};
    use nalgebra::{Matrix6, Rotation2};

    #[test]
    fn ellipse_of_diagonal_block_is_axis_aligned_three_sigma() {
        let e = ellipse_of(&Matrix2::new(0.04, 0.0, 0.0, 0.01), 3.0).unwrap();
        assert!((e.semi_major_m - 0.6).abs() < 1e-12, "{e:?}");
        assert!((e.semi_minor_m - 0.3).abs() < 1e-12, "{e:?}");
        assert!(e.angle_rad.abs() < 1e-12, "{e:?}");
        // Larger along the second axis: major axis at 90°.
        let e = ellipse_of(&Matrix2::new(0.01, 0.0, 0.0, 0.04), 1.0).unwrap();
        assert!((e.semi_major_m - 0.2).abs() < 1e-12);
        assert!(
            (e.angle_rad.abs() - std::f64::consts::FRAC_PI_2).abs() < 1e-12,
            "{e:?}"
        );
    }

    #[test]
    fn ellipse_of_rotated_block_recovers_angle_and_axes() {
        let r = Rotation2::new(30f64.to_radians()).into_inner();
        let block = r * Matrix2::new(9e-4, 0.0, 0.0, 1e-4) * r.transpose();
        let e = ellipse_of(&block, 3.0).unwrap();
        assert!((e.semi_major_m - 0.09).abs() < 1e-9, "{e:?}");
        assert!((e.semi_minor_m - 0.03).abs() < 1e-9, "{e:?}");
        assert!((e.angle_rad.to_degrees() - 30.0).abs() < 1e-6, "{e:?}");
    }

    #[test]
    fn ellipse_of_refuses_nan_indefinite_and_huge_blocks() {
        assert!(ellipse_of(&Matrix2::new(f64::NAN, 0.0, 0.0, 1.0), 3.0).is_none());
        assert!(ellipse_of(&Matrix2::new(1e-2, 0.0, 0.0, -1e-2), 3.0).is_none());
        assert!(ellipse_of(&Matrix2::new(200.0, 0.0, 0.0, 1.0), 3.0).is_none());
        // The reference vehicle's zero covariance is a point, not an error.
        let e = ellipse_of(&Matrix2::zeros(), 3.0).unwrap();
        assert_eq!((e.semi_major_m, e.semi_minor_m), (0.0, 0.0));
    }

    #[test]
    fn position_block_picks_the_side_view_axes() {
        let mut cov = Matrix6::zeros();
        cov[(0, 0)] = 1.0;
        cov[(0, 2)] = 0.5;
        cov[(2, 0)] = 0.5;
        cov[(2, 2)] = 2.0;
        cov[(1, 1)] = 7.0;
        assert_eq!(position_block(&cov, 0, 2), Matrix2::new(1.0, 0.5, 0.5, 2.0));
        assert_eq!(position_block(&cov, 0, 1), Matrix2::new(1.0, 0.0, 0.0, 7.0));
    }

    #[test]
    fn truth_is_expressed_in_the_reference_body_frame() {
        // Reference heading east (yaw 90° in NED); vehicle 15 three metres east of it.
        let half_pi = std::f64::consts::FRAC_PI_2;
        let t = truth_of(
            &[
                (10, pose([1.0, 2.0, 0.0], half_pi)),
                (15, pose([1.0, 5.0, 0.5], half_pi)),
            ],
            0,
        );
        let rel = truth_relative_to(&t, 10);
        let p15 = rel[&15].translation.vector;
        assert!((p15 - Vector3::new(3.0, 0.0, 0.5)).norm() < 1e-12, "{p15}");
        assert!(rel[&10].translation.vector.norm() < 1e-12);
        assert!(truth_relative_to(&t, 99).is_empty());
    }

    #[test]
    fn pose_error_measures_position_and_angle() {
        let truth = pose([3.0, 0.0, 0.0], 0.0);
        let est = pose([3.0, 0.004, 0.003], 2f64.to_radians());
        let (dt, dr) = pose_error(&est, &truth);
        assert!((dt - 0.005).abs() < 1e-12, "{dt}");
        assert!((dr.to_degrees() - 2.0).abs() < 1e-9, "{dr}");
    }
}
