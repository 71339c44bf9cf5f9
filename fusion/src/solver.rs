//! Levenberg–Marquardt on SE(3) over the vehicle poses `reference_from_vehicle`,
//! with a robust kernel, the reference vehicle fixing the gauge.
//!
//! Hand-written rather than taken from a solver crate (see the crate docs for
//! why): the problem is at most a few hundred vehicles × 6 DoF with a sparse,
//! nearly banded information matrix. The normal equations are ordered by
//! reverse Cuthill–McKee over the vehicle graph and factored with a profile
//! (skyline) Cholesky, whose fill stays inside the envelope; the marginal
//! covariances are the diagonal 6×6 blocks of the inverse Gauss–Newton
//! information, computed by forward substitution from each block down.
//!
//! Perturbations follow [`proto::geometry`]: `t + δt`, `Exp(δθ)·R`, both in
//! the reference frame; an edge's residual is `difference(a_from_ref·ref_from_b,
//! measured a_from_b)`, expressed in frame `a` like the measurement's covariance.

use nalgebra::{Matrix3, Matrix6, Vector3, Vector6};
use proto::geometry::{
    compose_jacobians, inverse_jacobian, perturb, skew, Cov6, Pose, PoseWithCovariance,
};
use proto::VehicleId;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet, VecDeque};

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

/// `Σ aᵢ·bᵢ` over the common length, in four interleaved partial sums: the
/// inner loop of the profile factorization and of the marginals, which a
/// single running sum keeps from vectorizing (floating-point addition is not
/// reassociated by the compiler). The order is fixed, so results stay
/// bit-reproducible. (Eight partial sums measured no faster.)
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0.0f64; 4];
    let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for k in 0..4 {
            acc[k] += x[k] * y[k];
        }
    }
    let tail: f64 = ra.iter().zip(rb).map(|(x, y)| x * y).sum();
    (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
}

/// A symmetric positive-definite matrix stored by its lower profile: row `i`
/// holds columns `first[i]..=i`, the rows one after another in one buffer
/// (one allocation; a damped copy per Levenberg–Marquardt try is one memcpy).
#[derive(Debug, Clone)]
struct Profile {
    first: Vec<usize>,
    /// Where row `i` starts in `data`; `start[n]` is its length.
    start: Vec<usize>,
    data: Vec<f64>,
}

impl Profile {
    fn zeros(first: Vec<usize>) -> Self {
        let mut start = Vec::with_capacity(first.len() + 1);
        let mut len = 0;
        for (i, f) in first.iter().enumerate() {
            start.push(len);
            len += i + 1 - f;
        }
        start.push(len);
        Self {
            first,
            start,
            data: vec![0.0; len],
        }
    }
    fn n(&self) -> usize {
        self.first.len()
    }
    /// Row `i`, columns `first[i]..=i`.
    fn row(&self, i: usize) -> &[f64] {
        &self.data[self.start[i]..self.start[i + 1]]
    }
    fn get(&self, i: usize, j: usize) -> f64 {
        debug_assert!(j <= i);
        if j < self.first[i] {
            0.0
        } else {
            self.data[self.start[i] + j - self.first[i]]
        }
    }
    fn add(&mut self, i: usize, j: usize, v: f64) {
        let (i, j) = if j > i { (j, i) } else { (i, j) };
        let f = self.first[i];
        self.data[self.start[i] + j - f] += v;
    }
    /// In-place Cholesky `A = L·Lᵀ` within the profile; `None` if not positive definite.
    fn cholesky(mut self) -> Option<Profile> {
        let n = self.n();
        for i in 0..n {
            let fi = self.first[i];
            // Rows before i (finished) and row i (being factored).
            let (done, rest) = self.data.split_at_mut(self.start[i]);
            let row = &mut rest[..i + 1 - fi];
            for j in fi..i {
                let fj = self.first[j];
                let k0 = fi.max(fj);
                let row_j = &done[self.start[j]..self.start[j + 1]];
                let d = dot(&row[k0 - fi..j - fi], &row_j[k0 - fj..j - fj]);
                row[j - fi] = (row[j - fi] - d) / row_j[j - fj];
            }
            let d = row[i - fi] - dot(&row[..i - fi], &row[..i - fi]);
            if d.is_nan() || d <= 0.0 || !d.is_finite() {
                return None;
            }
            row[i - fi] = d.sqrt();
        }
        Some(self)
    }
    /// Solve `L·Lᵀ x = b` with `self` the factor `L`.
    fn solve(&self, b: &[f64]) -> Vec<f64> {
        let n = self.n();
        let mut y = b.to_vec();
        for i in 0..n {
            let fi = self.first[i];
            let row = self.row(i);
            let s = y[i] - dot(&row[..i - fi], &y[fi..i]);
            y[i] = s / row[i - fi];
        }
        // Backward with Lᵀ: column-oriented over the rows of L.
        for i in (0..n).rev() {
            let fi = self.first[i];
            let row = self.row(i);
            y[i] /= row[i - fi];
            let yi = y[i];
            for k in fi..i {
                y[k] -= row[k - fi] * yi;
            }
        }
        y
    }
    /// Diagonal 6×6 block `p` of `(L·Lᵀ)⁻¹`: `Yᵀ·Y` with `Y = L⁻¹·E_p`
    /// (forward substitution from row `6p` down; rows above are zero).
    fn inverse_diagonal_block(&self, p: usize) -> Cov6 {
        let n = self.n();
        let start = 6 * p;
        // Column-major: y[c][i - start].
        let mut y = vec![vec![0.0f64; n - start]; 6];
        for i in start..n {
            let f = self.first[i];
            let k0 = f.max(start);
            let row = self.row(i);
            let lii = row[i - f];
            let lrow = &row[k0 - f..i - f];
            for (c, yc) in y.iter_mut().enumerate() {
                let d = dot(lrow, &yc[k0 - start..i - start]);
                let e = if i - start == c { 1.0 } else { 0.0 };
                yc[i - start] = (e - d) / lii;
            }
        }
        let mut cov = Cov6::zeros();
        for r in 0..6 {
            for c in r..6 {
                let v = dot(&y[r], &y[c]);
                cov[(r, c)] = v;
                cov[(c, r)] = v;
            }
        }
        cov
    }
}

/// Reverse Cuthill–McKee order of `vertices` (sorted) under `neighbours`,
/// deterministic: each BFS starts at the lowest-degree unvisited vertex,
/// neighbours are visited by (degree, ID).
fn reverse_cuthill_mckee(
    vertices: &[VehicleId],
    neighbours: &BTreeMap<VehicleId, BTreeSet<VehicleId>>,
) -> Vec<VehicleId> {
    let degree = |v: &VehicleId| neighbours.get(v).map_or(0, BTreeSet::len);
    let mut by_degree: Vec<VehicleId> = vertices.to_vec();
    by_degree.sort_by_key(|v| (degree(v), *v));
    let mut visited = BTreeSet::new();
    let mut order = Vec::with_capacity(vertices.len());
    for &start in &by_degree {
        if !visited.insert(start) {
            continue;
        }
        let mut queue = VecDeque::from([start]);
        while let Some(v) = queue.pop_front() {
            order.push(v);
            let mut next: Vec<VehicleId> = neighbours
                .get(&v)
                .into_iter()
                .flatten()
                .copied()
                .filter(|u| !visited.contains(u))
                .collect();
            next.sort_by_key(|u| (degree(u), *u));
            for u in next {
                visited.insert(u);
                queue.push_back(u);
            }
        }
    }
    order.reverse();
    order
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

/// Where each vehicle's 6 unknowns sit in the normal equations: reverse
/// Cuthill–McKee order, and the profile (each row's first stored column).
struct Layout {
    position: BTreeMap<VehicleId, usize>,
    first: Vec<usize>,
    n: usize,
}

impl Layout {
    fn new(reference: VehicleId, constraints: &[Constraint]) -> Self {
        let mut neighbours: BTreeMap<VehicleId, BTreeSet<VehicleId>> = BTreeMap::new();
        for c in constraints {
            if c.a != reference && c.b != reference {
                neighbours.entry(c.a).or_default().insert(c.b);
                neighbours.entry(c.b).or_default().insert(c.a);
            }
        }
        let variables: Vec<VehicleId> = constraints
            .iter()
            .flat_map(|c| [c.a, c.b])
            .filter(|v| *v != reference)
            .collect::<BTreeSet<_>>()
            .into_iter()
            .collect();
        let order = reverse_cuthill_mckee(&variables, &neighbours);
        let position: BTreeMap<VehicleId, usize> =
            order.iter().enumerate().map(|(i, v)| (*v, i)).collect();
        let n = 6 * order.len();
        // Profile: each block row starts at its lowest-positioned neighbour.
        let mut first = vec![0usize; n];
        for (p, v) in order.iter().enumerate() {
            let lowest = neighbours
                .get(v)
                .into_iter()
                .flatten()
                .filter_map(|u| position.get(u))
                .copied()
                .chain([p])
                .min()
                .unwrap_or(p);
            for r in 0..6 {
                first[6 * p + r] = 6 * lowest;
            }
        }
        Self { position, first, n }
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
    /// information (lower triangle, in the profile) and the gradient.
    fn normal_equations(&self, poses: &BTreeMap<VehicleId, Pose>) -> (Profile, Vec<f64>) {
        let position = &self.layout.position;
        let mut h = Profile::zeros(self.layout.first.clone());
        let mut g = vec![0.0; self.layout.n];
        for (c, info) in self.constraints.iter().zip(&self.informations) {
            let (r, ja, jb) = residual_and_jacobians(&poses[&c.a], &poses[&c.b], &c.a_from_b);
            let s = (r.transpose() * info * r)[0];
            let w = self.params.robust.weight(s);
            let wi = info * w;
            let blocks = [
                (position.get(&c.a).copied(), ja),
                (position.get(&c.b).copied(), jb),
            ];
            for (pi, ji) in &blocks {
                let Some(pi) = pi else { continue };
                let jt_w = ji.transpose() * wi;
                let gi = jt_w * r;
                for k in 0..6 {
                    g[6 * pi + k] += gi[k];
                }
                for (pj, jj) in &blocks {
                    let Some(pj) = pj else { continue };
                    if pj > pi {
                        continue;
                    }
                    let hij = jt_w * jj;
                    for r_ in 0..6 {
                        for c_ in 0..6 {
                            let (row, col) = (6 * pi + r_, 6 * pj + c_);
                            if pi == pj && col > row {
                                continue;
                            }
                            h.add(row, col, hij[(r_, c_)]);
                        }
                    }
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
        let n = self.layout.n;
        let mut lambda = self.params.initial_lambda;
        let mut iterations = 0;
        if n == 0 {
            return (iterations, cost);
        }
        for _ in 0..self.params.max_iterations {
            iterations += 1;
            let (h, g) = self.normal_equations(poses);
            let mut improved = false;
            for _ in 0..10 {
                let mut damped = h.clone();
                for i in 0..n {
                    let d = damped.get(i, i);
                    damped.add(i, i, lambda * d.max(1e-12));
                }
                let Some(l) = damped.cholesky() else {
                    lambda *= 10.0;
                    continue;
                };
                let neg_g: Vec<f64> = g.iter().map(|v| -v).collect();
                let dx = l.solve(&neg_g);
                let mut trial = poses.clone();
                for (v, p) in &self.layout.position {
                    let xi = Vector6::from_iterator(dx[6 * p..6 * p + 6].iter().copied());
                    trial.insert(*v, perturb(&poses[v], &xi));
                }
                let trial_cost = self.cost(&trial);
                if trial_cost.is_finite() && trial_cost <= cost {
                    let decrease = cost - trial_cost;
                    let step = dx.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                    *poses = trial;
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
            let (h, _) = self.normal_equations(poses);
            let l = h.cholesky().ok_or(SolveError::Singular)?;
            for (v, p) in &self.layout.position {
                let c = l.inverse_diagonal_block(*p);
                covariances.insert(*v, (c + c.transpose()) * 0.5);
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

    #[test]
    fn profile_cholesky_inverse_blocks_match_dense_inverse() {
        // A banded SPD matrix of 3 blocks.
        let n = 18;
        let mut dense = nalgebra::DMatrix::<f64>::zeros(n, n);
        for i in 0..n {
            dense[(i, i)] = 4.0 + i as f64 * 0.1;
            if i >= 5 {
                dense[(i, i - 5)] = 0.5;
                dense[(i - 5, i)] = 0.5;
            }
        }
        let first: Vec<usize> = (0..n).map(|i| 6 * ((i / 6).saturating_sub(1))).collect();
        let mut p = Profile::zeros(first);
        for i in 0..n {
            for j in p.first[i]..=i {
                p.add(i, j, dense[(i, j)]);
            }
        }
        let l = p.cholesky().unwrap();
        let inv = dense.clone().try_inverse().unwrap();
        for b in 0..3 {
            let blk = l.inverse_diagonal_block(b);
            for r in 0..6 {
                for c in 0..6 {
                    assert!((blk[(r, c)] - inv[(6 * b + r, 6 * b + c)]).abs() < 1e-12);
                }
            }
        }
        let rhs: Vec<f64> = (0..n).map(|i| i as f64 - 3.0).collect();
        let x = l.solve(&rhs);
        let back = &dense * nalgebra::DVector::from_vec(x);
        for i in 0..n {
            assert!((back[i] - rhs[i]).abs() < 1e-10);
        }
    }
}
