//! Levenberg–Marquardt on SE(3) over the vehicle poses `reference_from_vehicle`,
//! with a robust kernel, the reference vehicle fixing the gauge.
//!
//! Hand-written rather than taken from a solver crate (see the crate docs for
//! why): the problem is at most a few hundred vehicles × 6 DoF with a sparse,
//! sparse information matrix. The normal equations are kept in 6×6 blocks,
//! ordered by minimum degree over the vehicle graph and factored by a
//! block-sparse Cholesky (`sparse.rs`); the marginal covariances are
//! the diagonal 6×6 blocks of the inverse Gauss–Newton information, from a
//! selected inversion over the factor's pattern.
//!
//! Perturbations follow [`proto::geometry`]: `t + δt`, `Exp(δθ)·R`, both in
//! the reference frame; an edge's residual is `difference(a_from_ref·ref_from_b,
//! measured a_from_b)`, expressed in frame `a` like the measurement's covariance.

use crate::sparse::{Block, Factor, Symbolic};
use nalgebra::{Matrix3, Matrix6, Vector3, Vector6};
use proto::geometry::{
    compose_jacobians, inverse_jacobian, perturb, skew, Cov6, Pose, PoseWithCovariance,
};
use proto::VehicleId;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};

/// Robust loss applied to each edge's squared Mahalanobis distance `s`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum RobustKernel {
    /// Plain least squares.
    None,
    /// Huber on `√s` with threshold `k` (Mahalanobis units): quadratic inside, linear outside.
    Huber { k: f64 },
    /// Cauchy: `ρ(s) = c²·ln(1 + s/c²)`.
    Cauchy { c: f64 },
}

impl RobustKernel {
    /// `ρ(s)`, the cost of an edge with squared Mahalanobis distance `s`.
    pub fn cost(&self, s: f64) -> f64 {
        match *self {
            RobustKernel::None => s,
            RobustKernel::Huber { k } => {
                let r = s.sqrt();
                if r <= k {
                    s
                } else {
                    2.0 * k * r - k * k
                }
            }
            RobustKernel::Cauchy { c } => c * c * (1.0 + s / (c * c)).ln(),
        }
    }

    /// IRLS weight `ρ'(s)`.
    pub fn weight(&self, s: f64) -> f64 {
        match *self {
            RobustKernel::None => 1.0,
            RobustKernel::Huber { k } => {
                let r = s.sqrt();
                if r <= k {
                    1.0
                } else {
                    k / r
                }
            }
            RobustKernel::Cauchy { c } => 1.0 / (1.0 + s / (c * c)),
        }
    }
}

/// One relative-pose constraint `a_from_b` between two vehicles.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Constraint {
    pub a: VehicleId,
    pub b: VehicleId,
    pub a_from_b: Pose,
    /// Covariance of `a_from_b` (frame `a`, [`proto::geometry`] convention).
    pub covariance: Cov6,
}

/// Solver settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SolverParams {
    pub robust: RobustKernel,
    pub max_iterations: usize,
    /// Stop when the relative cost decrease falls below this.
    pub relative_tolerance: f64,
    /// Initial Marquardt damping, relative to the information diagonal.
    pub initial_lambda: f64,
    /// Stop when the largest update component falls below this (m or rad).
    pub min_step: f64,
}

impl Default for SolverParams {
    fn default() -> Self {
        Self {
            // √χ²₆(0.99) = 4.1: inliers keep weight 1, so the returned covariance is the plain GN one.
            robust: RobustKernel::Huber { k: 4.1 },
            max_iterations: 30,
            relative_tolerance: 1e-8,
            initial_lambda: 1e-4,
            min_step: 1e-9,
        }
    }
}

/// Errors of the solver.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SolveError {
    #[error("constraint {a}->{b} names a vehicle without an initial pose")]
    UnknownVehicle { a: VehicleId, b: VehicleId },
    #[error("constraint {a}->{b} has a covariance that is not positive definite")]
    BadCovariance { a: VehicleId, b: VehicleId },
    #[error(
        "the information matrix is singular (a vehicle is not constrained in every direction)"
    )]
    Singular,
}

/// The solution: every vehicle's `reference_from_vehicle` and its marginal covariance.
#[derive(Debug, Clone, PartialEq)]
pub struct Solution {
    pub poses: BTreeMap<VehicleId, Pose>,
    /// Marginal covariance per vehicle (zero for the reference).
    pub covariances: BTreeMap<VehicleId, Cov6>,
    pub iterations: usize,
    pub initial_cost: f64,
    pub final_cost: f64,
}

/// [`proto::geometry::difference`] (the perturbation taking `reference` to
/// `pose`), the same operations compiled in this crate so that they inline
/// into the per-observation loops (grouping, fusion, chi-square of every
/// hypothesis), which call it tens of thousands of times per solve.
/// `tests::local_difference_is_bit_identical_to_proto` pins the equality.
#[inline]
pub(crate) fn difference(pose: &Pose, reference: &Pose) -> Vector6<f64> {
    let dt = pose.translation.vector - reference.translation.vector;
    let dtheta = (pose.rotation * reference.rotation.inverse()).scaled_axis();
    Vector6::new(dt.x, dt.y, dt.z, dtheta.x, dtheta.y, dtheta.z)
}

/// [`PoseWithCovariance::compose`], compiled here for the same reason as
/// [`difference`] (the spanning tree composes along its paths per verified pair).
#[inline]
pub(crate) fn compose(x: &PoseWithCovariance, y: &PoseWithCovariance) -> PoseWithCovariance {
    let (ja, jb) = compose_jacobians(&x.pose, &y.pose);
    PoseWithCovariance {
        pose: x.pose * y.pose,
        covariance: ja * x.covariance * ja.transpose() + jb * y.covariance * jb.transpose(),
    }
}

/// [`PoseWithCovariance::inverse`], compiled here (see [`compose`]).
#[inline]
pub(crate) fn invert(x: &PoseWithCovariance) -> PoseWithCovariance {
    let j = inverse_jacobian(&x.pose);
    PoseWithCovariance {
        pose: x.pose.inverse(),
        covariance: j * x.covariance * j.transpose(),
    }
}

/// Inverse of the left Jacobian of SO(3), `J_l⁻¹(φ)`: `Log(Exp(δ)·Exp(φ)) ≈ φ + J_l⁻¹(φ)·δ`.
pub fn so3_left_jacobian_inverse(phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta = phi.norm();
    let k = skew(phi);
    if theta < 1e-6 {
        return Matrix3::identity() - 0.5 * k + k * k / 12.0;
    }
    let coef = 1.0 / (theta * theta) - (1.0 + theta.cos()) / (2.0 * theta * theta.sin());
    Matrix3::identity() - 0.5 * k + coef * k * k
}

/// Residual of a constraint and its Jacobians with respect to the perturbations
/// of `ref_from_a` and `ref_from_b`.
pub fn residual_and_jacobians(
    ref_from_a: &Pose,
    ref_from_b: &Pose,
    measured_a_from_b: &Pose,
) -> (Vector6<f64>, Matrix6<f64>, Matrix6<f64>) {
    let a_from_ref = ref_from_a.inverse();
    let predicted = a_from_ref * ref_from_b;
    let r = difference(&predicted, measured_a_from_b);
    let (j1, j2) = compose_jacobians(&a_from_ref, ref_from_b);
    let jinv = inverse_jacobian(ref_from_a);
    let mut d = Matrix6::identity();
    let phi = Vector3::new(r[3], r[4], r[5]);
    d.fixed_view_mut::<3, 3>(3, 3)
        .copy_from(&so3_left_jacobian_inverse(&phi));
    (r, d * j1 * jinv, d * j2)
}

/// Squared Mahalanobis distance of `measured_a_from_b` to the prediction from two poses.
pub fn edge_chi2(
    ref_from_a: &Pose,
    ref_from_b: &Pose,
    measured_a_from_b: &Pose,
    information: &Cov6,
) -> f64 {
    let r = difference(&(ref_from_a.inverse() * ref_from_b), measured_a_from_b);
    (r.transpose() * information * r)[0]
}

/// Solve the pose graph. `initial` must hold a pose for every vehicle named by
/// a constraint; `reference` is held fixed (gauge). Vehicles in `initial` that
/// no constraint touches keep their initial pose and get no covariance.
pub fn solve(
    reference: VehicleId,
    initial: &BTreeMap<VehicleId, Pose>,
    constraints: &[Constraint],
    params: &SolverParams,
) -> Result<Solution, SolveError> {
    let mut informations = Vec::with_capacity(constraints.len());
    for c in constraints {
        if !initial.contains_key(&c.a) || !initial.contains_key(&c.b) {
            return Err(SolveError::UnknownVehicle { a: c.a, b: c.b });
        }
        let info = c
            .covariance
            .try_inverse()
            .filter(|m| m.iter().all(|v| v.is_finite()))
            .ok_or(SolveError::BadCovariance { a: c.a, b: c.b })?;
        informations.push((info + info.transpose()) * 0.5);
    }
    let problem = Problem {
        constraints,
        informations,
        params,
        layout: Layout::new(reference, constraints),
    };
    let mut poses = initial.clone();
    let initial_cost = problem.cost(&poses);
    let (iterations, cost) = problem.levenberg_marquardt(&mut poses, initial_cost);
    let covariances = problem.marginals(reference, &poses)?;
    Ok(Solution {
        poses,
        covariances,
        iterations,
        initial_cost,
        final_cost: cost,
    })
}

/// Where each vehicle's 6 unknowns sit in the normal equations: the
/// block-sparse structure ([`Symbolic`]: minimum-degree order, the factor's
/// pattern) and, per constraint, the slots its blocks add to.
struct Layout {
    /// Vehicle → elimination position (the reference has none).
    position: BTreeMap<VehicleId, usize>,
    symbolic: Symbolic,
    /// Per constraint: the slots of `(a, a)`, `(b, b)` and `(a, b)` (`None`
    /// for the reference), and whether the off-diagonal slot holds `H_ab`
    /// (`a` eliminated after `b`) or its transpose.
    slots: Vec<[Option<usize>; 3]>,
    a_after_b: Vec<bool>,
    n: usize,
}

impl Layout {
    fn new(reference: VehicleId, constraints: &[Constraint]) -> Self {
        let variables: Vec<VehicleId> = constraints
            .iter()
            .flat_map(|c| [c.a, c.b])
            .filter(|v| *v != reference)
            .collect::<BTreeSet<_>>()
            .into_iter()
            .collect();
        let index = |v: VehicleId| variables.binary_search(&v).ok();
        let mut neighbours = vec![Vec::new(); variables.len()];
        for c in constraints {
            if let (Some(a), Some(b)) = (index(c.a), index(c.b)) {
                neighbours[a].push(b);
                neighbours[b].push(a);
            }
        }
        let symbolic = Symbolic::new(&neighbours);
        let position: BTreeMap<VehicleId, usize> = variables
            .iter()
            .enumerate()
            .map(|(i, v)| (*v, symbolic.position[i]))
            .collect();
        let mut slots = Vec::with_capacity(constraints.len());
        let mut a_after_b = Vec::with_capacity(constraints.len());
        for c in constraints {
            let (pa, pb) = (position.get(&c.a).copied(), position.get(&c.b).copied());
            let off = match (pa, pb) {
                (Some(x), Some(y)) if x != y => symbolic.slot(x.max(y), x.min(y)),
                _ => None,
            };
            slots.push([pa, pb, off]);
            a_after_b.push(matches!((pa, pb), (Some(x), Some(y)) if x > y));
        }
        Self {
            n: 6 * variables.len(),
            position,
            symbolic,
            slots,
            a_after_b,
        }
    }
}

/// The pose graph: constraints with their (symmetrized) informations.
struct Problem<'a> {
    constraints: &'a [Constraint],
    informations: Vec<Cov6>,
    params: &'a SolverParams,
    layout: Layout,
}

impl Problem<'_> {
    /// Robust cost at `poses`.
    fn cost(&self, poses: &BTreeMap<VehicleId, Pose>) -> f64 {
        self.constraints
            .iter()
            .zip(&self.informations)
            .map(|(c, info)| {
                self.params
                    .robust
                    .cost(edge_chi2(&poses[&c.a], &poses[&c.b], &c.a_from_b, info))
            })
            .sum()
    }

    /// Gauss–Newton system at `poses`, robust weights included: the
    /// information (its blocks, per slot of the layout) and the gradient
    /// (by position).
    fn normal_equations(&self, poses: &BTreeMap<VehicleId, Pose>) -> (Vec<Block>, Vec<f64>) {
        let layout = &self.layout;
        let mut h = vec![Block::zeros(); layout.symbolic.slots()];
        let mut g = vec![0.0; layout.n];
        for (k, (c, info)) in self.constraints.iter().zip(&self.informations).enumerate() {
            let (r, ja, jb) = residual_and_jacobians(&poses[&c.a], &poses[&c.b], &c.a_from_b);
            let s = (r.transpose() * info * r)[0];
            let wi = info * self.params.robust.weight(s);
            let [sa, sb, sab] = layout.slots[k];
            let (jta_w, jtb_w) = (ja.transpose() * wi, jb.transpose() * wi);
            for (slot, jt_w, j) in [(sa, &jta_w, &ja), (sb, &jtb_w, &jb)] {
                let Some(p) = slot else { continue };
                let gi = jt_w * r;
                for i in 0..6 {
                    g[6 * p + i] += gi[i];
                }
                h[p] += jt_w * j;
            }
            if let Some(off) = sab {
                if layout.a_after_b[k] {
                    h[off] += jta_w * jb;
                } else {
                    h[off] += jtb_w * ja;
                }
            }
        }
        (h, g)
    }

    /// Levenberg–Marquardt from `poses` (cost `cost`), in place: returns the
    /// iterations and the final cost.
    fn levenberg_marquardt(
        &self,
        poses: &mut BTreeMap<VehicleId, Pose>,
        mut cost: f64,
    ) -> (usize, f64) {
        let sym = &self.layout.symbolic;
        let mut lambda = self.params.initial_lambda;
        let mut iterations = 0;
        if self.layout.n == 0 {
            return (iterations, cost);
        }
        let mut trial = poses.clone();
        for _ in 0..self.params.max_iterations {
            iterations += 1;
            let (h, g) = self.normal_equations(poses);
            let neg_g: Vec<f64> = g.iter().map(|v| -v).collect();
            let mut improved = false;
            for _ in 0..10 {
                let mut damped = h.clone();
                for d in &mut damped[..sym.m()] {
                    for i in 0..6 {
                        d[(i, i)] += lambda * d[(i, i)].max(1e-12);
                    }
                }
                let Some(l) = Factor::new(sym, damped) else {
                    lambda *= 10.0;
                    continue;
                };
                let dx = l.solve(sym, &neg_g);
                for (v, p) in &self.layout.position {
                    let xi = Vector6::from_column_slice(&dx[6 * p..6 * p + 6]);
                    trial.insert(*v, perturb(&poses[v], &xi));
                }
                let trial_cost = self.cost(&trial);
                if trial_cost.is_finite() && trial_cost <= cost {
                    let decrease = cost - trial_cost;
                    let step = dx.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                    std::mem::swap(poses, &mut trial);
                    cost = trial_cost;
                    lambda = (lambda / 10.0).max(1e-12);
                    // Converged: negligible relative decrease, or a step below `min_step`.
                    improved = decrease > self.params.relative_tolerance * cost
                        && step > self.params.min_step;
                    break;
                }
                lambda *= 10.0;
            }
            if !improved {
                break;
            }
        }
        (iterations, cost)
    }

    /// Marginals: the inverse of the (undamped) Gauss–Newton information at
    /// `poses`, one 6x6 diagonal block per vehicle (zero for the reference).
    fn marginals(
        &self,
        reference: VehicleId,
        poses: &BTreeMap<VehicleId, Pose>,
    ) -> Result<BTreeMap<VehicleId, Cov6>, SolveError> {
        let mut covariances = BTreeMap::new();
        covariances.insert(reference, Cov6::zeros());
        if self.layout.n > 0 {
            let sym = &self.layout.symbolic;
            let (h, _) = self.normal_equations(poses);
            let l = Factor::new(sym, h).ok_or(SolveError::Singular)?;
            let blocks = l.inverse_diagonal_blocks(sym);
            for (v, p) in &self.layout.position {
                covariances.insert(*v, blocks[*p]);
            }
        }
        Ok(covariances)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proto::geometry::pose_from_xyz_rpy;

    fn numeric(f: impl Fn(&Vector6<f64>) -> Vector6<f64>) -> Matrix6<f64> {
        let h = 1e-6;
        let mut j = Matrix6::zeros();
        for k in 0..6 {
            let mut d = Vector6::zeros();
            d[k] = h;
            let mut m = Vector6::zeros();
            m[k] = -h;
            j.set_column(k, &((f(&d) - f(&m)) / (2.0 * h)));
        }
        j
    }

    #[test]
    fn local_difference_is_bit_identical_to_proto() {
        let a = pose_from_xyz_rpy([1.0, -2.0, 0.5], [0.3, -0.2, 1.0]);
        let b = pose_from_xyz_rpy([-0.5, 1.5, 2.0], [-0.4, 0.6, -2.0]);
        let c = perturb(&a, &Vector6::new(1e-3, -2e-3, 5e-4, 1e-4, -3e-4, 2e-4));
        for (x, y) in [(a, b), (b, a), (a, c), (c, a), (a, a)] {
            let (ours, theirs) = (difference(&x, &y), proto::geometry::difference(&x, &y));
            for k in 0..6 {
                assert_eq!(ours[k].to_bits(), theirs[k].to_bits());
            }
            let cov = Cov6::from_fn(|r, c| if r == c { 1e-3 * (r + 1) as f64 } else { 1e-5 });
            let (px, py) = (
                PoseWithCovariance::new(x, cov),
                PoseWithCovariance::new(y, cov * 2.0),
            );
            assert_eq!(compose(&px, &py), px.compose(&py));
            assert_eq!(invert(&px), px.inverse());
        }
    }

    #[test]
    fn residual_jacobians_match_finite_differences() {
        let a = pose_from_xyz_rpy([1.0, -2.0, 0.5], [0.3, -0.2, 1.0]);
        let b = pose_from_xyz_rpy([-0.5, 1.5, 2.0], [-0.4, 0.6, -2.0]);
        // Measurement off by a sizeable rotation so J_l⁻¹ matters.
        let z = perturb(
            &(a.inverse() * b),
            &Vector6::new(0.1, -0.05, 0.2, 0.3, -0.2, 0.25),
        );
        let (_, ja, jb) = residual_and_jacobians(&a, &b, &z);
        let na = numeric(|d| difference(&(perturb(&a, d).inverse() * b), &z));
        let nb = numeric(|d| difference(&(a.inverse() * perturb(&b, d)), &z));
        assert!((ja - na).abs().max() < 1e-6, "{ja} vs {na}");
        assert!((jb - nb).abs().max() < 1e-6, "{jb} vs {nb}");
    }
}
