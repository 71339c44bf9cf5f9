//! shoal's constraints in the convention both libraries read.
//!
//! shoal's covariance of `a_from_b` is over its left perturbation in frame `a`,
//! translation first (`t + δt`, `Exp(δθ)·R`). Both factrs' and tiny-solver's
//! SE(3) between residuals are `Log(T_b⁻¹·T_a·Z)`: the right (local)
//! perturbation of the measurement `Z`, rotation first. To first order the
//! two agree through `Λ_local = Bᵀ Λ B`, `B = diag(R_Z, R_Z)` (as
//! `shoal_fusion::export` writes g2o), then the two 3-blocks swapped.

use nalgebra::{Matrix3, Matrix6};
use shoal_fusion::export::PoseGraph;
use shoal_proto::geometry::Pose;
use shoal_proto::VehicleId;

/// One constraint as the libraries take it.
#[derive(Debug, Clone)]
pub struct Edge {
    pub a: VehicleId,
    pub b: VehicleId,
    /// Measured `a_from_b`: quaternion (x, y, z, w) and translation.
    pub q_xyzw: [f64; 4],
    pub t: [f64; 3],
    /// The square root `S` of the information over the right perturbation,
    /// rotation first (`SᵀS = Λ`, upper triangular): the residual's whitening.
    pub sqrt_information: Matrix6<f64>,
}

/// `(t, θ)` order to `(θ, t)` order, or back (the same swap).
pub fn swap_blocks(m: &Matrix6<f64>) -> Matrix6<f64> {
    Matrix6::from_fn(|i, j| m[((i + 3) % 6, (j + 3) % 6)])
}

/// Every constraint of `graph` in the libraries' convention.
pub fn edges(graph: &PoseGraph) -> Vec<Edge> {
    graph
        .constraints
        .iter()
        .map(|c| {
            let info = c
                .covariance
                .try_inverse()
                .expect("shoal's constraints have invertible covariances");
            let info = (info + info.transpose()) * 0.5;
            let r: Matrix3<f64> = c.a_from_b.rotation.to_rotation_matrix().into_inner();
            let mut b = Matrix6::zeros();
            b.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
            b.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
            let local = swap_blocks(&(b.transpose() * info * b));
            let local = (local + local.transpose()) * 0.5;
            let sqrt = local
                .cholesky()
                .expect("an information is positive definite")
                .l()
                .transpose();
            let (t, q) = (c.a_from_b.translation.vector, c.a_from_b.rotation.coords);
            Edge {
                a: c.a,
                b: c.b,
                q_xyzw: [q.x, q.y, q.z, q.w],
                t: [t.x, t.y, t.z],
                sqrt_information: sqrt,
            }
        })
        .collect()
}

/// A pose from a quaternion (x, y, z, w) and a translation.
pub fn pose(q_xyzw: [f64; 4], t: [f64; 3]) -> Pose {
    Pose::from_parts(
        nalgebra::Translation3::new(t[0], t[1], t[2]),
        nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            q_xyzw[3], q_xyzw[0], q_xyzw[1], q_xyzw[2],
        )),
    )
}

/// A marginal over a library's right perturbation of `ref_from_v`
/// (rotation first) in shoal's convention (left perturbation in the
/// reference frame, translation first): `δt = R·v`, `δθ = R·θ` to first
/// order, so `Σ_shoal = M Σ Mᵀ`, `M = [[0, R], [R, 0]]`.
pub fn marginal_to_shoal(right_rot_first: &Matrix6<f64>, ref_from_v: &Pose) -> Matrix6<f64> {
    let r: Matrix3<f64> = ref_from_v.rotation.to_rotation_matrix().into_inner();
    let mut m = Matrix6::zeros();
    m.fixed_view_mut::<3, 3>(0, 3).copy_from(&r);
    m.fixed_view_mut::<3, 3>(3, 0).copy_from(&r);
    m * right_rot_first * m.transpose()
}
