//! SE(3) poses and their 6x6 covariances.
//!
//! Transforms are named `a_from_b`: `p_a = a_from_b * p_b`.
//!
//! **Covariance convention** (used by every message, the node's PnP and the
//! fusion solver): a covariance is over the perturbation
//! `ξ = (δt, δθ) ∈ R⁶`, translation in metres first, then a rotation vector in
//! radians, with
//!
//! ```text
//! t = t̂ + δt,     R = Exp(δθ) · R̂
//! ```
//!
//! i.e. both parts are expressed in the *left* frame `a` of `a_from_b`. With
//! that convention the Jacobians of composition and inversion are the small
//! closed forms in [`compose_jacobians`] and [`inverse_jacobian`].

use nalgebra::{Isometry3, Matrix3, Matrix6, Translation3, UnitQuaternion, Vector3, Vector6};
use serde::{Deserialize, Serialize};

/// A rigid transform `a_from_b` (rotation + translation, metres).
pub type Pose = Isometry3<f64>;
/// 6x6 covariance over `(δt [m], δθ [rad])`, see the module docs.
pub type Cov6 = Matrix6<f64>;

/// A pose with its uncertainty.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    pub pose: Pose,
    pub covariance: Cov6,
}

/// Skew-symmetric matrix `[v]×` with `[v]× w = v × w`.
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// Pose from translation (m) and roll/pitch/yaw (rad), `R = Rz(yaw)·Ry(pitch)·Rx(roll)`.
pub fn pose_from_xyz_rpy(xyz: [f64; 3], rpy: [f64; 3]) -> Pose {
    Isometry3::from_parts(
        Translation3::new(xyz[0], xyz[1], xyz[2]),
        UnitQuaternion::from_euler_angles(rpy[0], rpy[1], rpy[2]),
    )
}

/// Roll/pitch/yaw (rad) of a pose's rotation, inverse of [`pose_from_xyz_rpy`].
pub fn rpy_of(pose: &Pose) -> [f64; 3] {
    let (r, p, y) = pose.rotation.euler_angles();
    [r, p, y]
}

/// An angle brought into `[-π, π)`, rad.
pub fn wrap_angle(a: f64) -> f64 {
    (a + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI
}

/// Apply a perturbation in the module's convention: `t + δt`, `Exp(δθ)·R`.
pub fn perturb(pose: &Pose, xi: &Vector6<f64>) -> Pose {
    let dt = Vector3::new(xi[0], xi[1], xi[2]);
    let dtheta = Vector3::new(xi[3], xi[4], xi[5]);
    Isometry3::from_parts(
        Translation3::from(pose.translation.vector + dt),
        UnitQuaternion::from_scaled_axis(dtheta) * pose.rotation,
    )
}

/// The perturbation `ξ` that takes `reference` to `pose`: `perturb(reference, ξ) == pose`.
pub fn difference(pose: &Pose, reference: &Pose) -> Vector6<f64> {
    let dt = pose.translation.vector - reference.translation.vector;
    let dtheta = (pose.rotation * reference.rotation.inverse()).scaled_axis();
    Vector6::new(dt.x, dt.y, dt.z, dtheta.x, dtheta.y, dtheta.z)
}

/// Jacobians of `a_from_c = a_from_b * b_from_c` with respect to the
/// perturbations of `a_from_b` and of `b_from_c` (module convention).
pub fn compose_jacobians(a_from_b: &Pose, b_from_c: &Pose) -> (Matrix6<f64>, Matrix6<f64>) {
    let ra = a_from_b.rotation.to_rotation_matrix().into_inner();
    let ra_tb = ra * b_from_c.translation.vector;
    let mut j_a = Matrix6::identity();
    j_a.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-skew(&ra_tb)));
    let mut j_b = Matrix6::zeros();
    j_b.fixed_view_mut::<3, 3>(0, 0).copy_from(&ra);
    j_b.fixed_view_mut::<3, 3>(3, 3).copy_from(&ra);
    (j_a, j_b)
}

/// Jacobian of `b_from_a = a_from_b⁻¹` with respect to the perturbation of `a_from_b`.
pub fn inverse_jacobian(a_from_b: &Pose) -> Matrix6<f64> {
    let rt = a_from_b
        .rotation
        .to_rotation_matrix()
        .into_inner()
        .transpose();
    let t = a_from_b.translation.vector;
    let mut j = Matrix6::zeros();
    j.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-rt));
    j.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-rt * skew(&t)));
    j.fixed_view_mut::<3, 3>(3, 3).copy_from(&(-rt));
    j
}

impl PoseWithCovariance {
    pub fn new(pose: Pose, covariance: Cov6) -> Self {
        Self { pose, covariance }
    }

    /// `self * other`, propagating both covariances (assumed independent).
    pub fn compose(&self, other: &PoseWithCovariance) -> PoseWithCovariance {
        let (ja, jb) = compose_jacobians(&self.pose, &other.pose);
        PoseWithCovariance {
            pose: self.pose * other.pose,
            covariance: ja * self.covariance * ja.transpose()
                + jb * other.covariance * jb.transpose(),
        }
    }

    /// The inverse transform with its propagated covariance.
    pub fn inverse(&self) -> PoseWithCovariance {
        let j = inverse_jacobian(&self.pose);
        PoseWithCovariance {
            pose: self.pose.inverse(),
            covariance: j * self.covariance * j.transpose(),
        }
    }
}

/// True when every entry of the pose is finite and the rotation is a unit quaternion.
pub fn pose_is_finite(pose: &Pose) -> bool {
    let q = pose.rotation.quaternion();
    pose.translation.vector.iter().all(|v| v.is_finite())
        && q.coords.iter().all(|v| v.is_finite())
        && (q.norm() - 1.0).abs() < 1e-6
}

/// Why a covariance is unusable, or `None` when it is a finite, symmetric,
/// positive-definite matrix with standard deviations below `max_std`
/// (metres / radians).
pub fn covariance_problem(cov: &Cov6, max_std: f64) -> Option<&'static str> {
    if !cov.iter().all(|v| v.is_finite()) {
        return Some("covariance has a non-finite entry");
    }
    let asym = (cov - cov.transpose()).abs().max();
    if asym > 1e-9 * (1.0 + cov.abs().max()) {
        return Some("covariance is not symmetric");
    }
    if (0..6).any(|i| cov[(i, i)] <= 0.0) {
        return Some("covariance has a non-positive variance");
    }
    if (0..6).any(|i| cov[(i, i)].sqrt() > max_std) {
        return Some("covariance is absurdly large");
    }
    if cov.cholesky().is_none() {
        return Some("covariance is not positive definite");
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample_pose(k: f64) -> Pose {
        pose_from_xyz_rpy([0.3 * k, -1.2, 2.0 + k], [0.2, -0.4 * k, 1.1])
    }

    fn numeric_jacobian(f: impl Fn(&Vector6<f64>) -> Pose, at: &Pose) -> Matrix6<f64> {
        let h = 1e-6;
        let mut j = Matrix6::zeros();
        for k in 0..6 {
            let mut d = Vector6::zeros();
            d[k] = h;
            let col = difference(&f(&d), at) / h;
            j.set_column(k, &col);
        }
        j
    }

    #[test]
    fn compose_jacobians_match_finite_differences() {
        let a = sample_pose(1.0);
        let b = sample_pose(-0.5);
        let ab = a * b;
        let (ja, jb) = compose_jacobians(&a, &b);
        let na = numeric_jacobian(|d| perturb(&a, d) * b, &ab);
        let nb = numeric_jacobian(|d| a * perturb(&b, d), &ab);
        assert!((ja - na).abs().max() < 1e-5, "{ja} vs {na}");
        assert!((jb - nb).abs().max() < 1e-5, "{jb} vs {nb}");
    }

    #[test]
    fn inverse_jacobian_matches_finite_differences() {
        let a = sample_pose(0.7);
        let j = inverse_jacobian(&a);
        let n = numeric_jacobian(|d| perturb(&a, d).inverse(), &a.inverse());
        assert!((j - n).abs().max() < 1e-5, "{j} vs {n}");
    }

    #[test]
    fn perturb_and_difference_are_inverse() {
        let a = sample_pose(0.2);
        let xi = Vector6::new(0.01, -0.02, 0.03, 0.05, -0.01, 0.02);
        let back = difference(&perturb(&a, &xi), &a);
        assert!((back - xi).norm() < 1e-12);
    }

    #[test]
    fn rpy_round_trips() {
        let p = pose_from_xyz_rpy([1.0, 2.0, 3.0], [0.1, -0.2, 0.3]);
        let rpy = rpy_of(&p);
        assert!((rpy[0] - 0.1).abs() < 1e-12 && (rpy[1] + 0.2).abs() < 1e-12);
    }

    #[test]
    fn covariance_checks_reject_nan_and_asymmetry() {
        let good = Cov6::identity() * 1e-4;
        assert_eq!(covariance_problem(&good, 10.0), None);
        let mut nan = good;
        nan[(2, 2)] = f64::NAN;
        assert!(covariance_problem(&nan, 10.0).is_some());
        let mut asym = good;
        asym[(0, 1)] = 1e-3;
        assert!(covariance_problem(&asym, 10.0).is_some());
        assert!(covariance_problem(&(Cov6::identity() * 1e6), 10.0).is_some());
    }
}
