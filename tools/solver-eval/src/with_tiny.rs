//! The graph solved by tiny-solver: a 7-vector `[qx, qy, qz, qw, tx, ty, tz]`
//! per vehicle on its `SE3Manifold`, one residual block per constraint and
//! its `HuberLoss` (k = 4.1: linear beyond `s > k²`, the same `ρ(s)` as
//! shoal's), Levenberg–Marquardt with its sparse Cholesky.
//!
//! tiny-solver's own `BetweenFactorSE3` has no noise model (unit
//! information), so the residual block here is that factor's residual,
//! `Log(T_b⁻¹·T_a·Z)` (its `SE3::log`: rotation, then the raw translation),
//! whitened by the constraint's square-root information. Gauge: the
//! reference's 7 entries are fixed (`Problem::fix_variable`, no manifold on
//! it, so it gets no column).

use crate::convert::{self, Edge};
use shoal_fusion::export::PoseGraph;
use shoal_proto::geometry::Pose;
use shoal_proto::VehicleId;
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::Arc;
use tiny_solver::factors::{na, Factor};
use tiny_solver::loss_functions::HuberLoss;
use tiny_solver::manifold::se3::{SE3Manifold, SE3};
use tiny_solver::optimizer::{Optimizer, OptimizerOptions};
use tiny_solver::{LevenbergMarquardtOptimizer, Problem};

/// `Log(T_b⁻¹·T_a·Z)` whitened: `S·r`.
struct WhitenedBetween {
    z: [f64; 7],
    sqrt_information: na::Matrix6<f64>,
}

impl<T: na::RealField> Factor<T> for WhitenedBetween {
    fn residual_func(&self, params: &[na::DVector<T>]) -> na::DVector<T> {
        let a = SE3::from_vec(params[0].as_view());
        let b = SE3::from_vec(params[1].as_view());
        let z = SE3::from_vec(na::DVector::from_row_slice(&self.z).as_view()).cast::<T>();
        let r = (b.inverse() * a * z).log();
        let s: na::Matrix6<T> = self.sqrt_information.cast::<T>();
        na::DVector::from_fn(6, |i, _| {
            (0..6).fold(T::zero(), |sum, k| sum + s[(i, k)].clone() * r[k].clone())
        })
    }
}

/// tiny-solver's values: a 7-vector per variable name.
pub type Values = HashMap<String, na::DVector<f64>>;

fn name(v: VehicleId) -> String {
    format!("x{v}")
}

fn vector(pose: &Pose) -> na::DVector<f64> {
    let (t, q) = (pose.translation.vector, pose.rotation.coords);
    na::DVector::from_row_slice(&[q.x, q.y, q.z, q.w, t.x, t.y, t.z])
}

fn pose(x: &na::DVector<f64>) -> Pose {
    convert::pose([x[0], x[1], x[2], x[3]], [x[4], x[5], x[6]])
}

/// The vehicles the constraints name.
fn variables(edges: &[Edge]) -> BTreeSet<VehicleId> {
    edges.iter().flat_map(|e| [e.a, e.b]).collect()
}

/// tiny-solver's problem and initial values for `graph`.
pub fn build(graph: &PoseGraph, edges: &[Edge], huber_k: f64) -> (Problem, Values) {
    let mut problem = Problem::new();
    let mut initial = HashMap::new();
    for v in variables(edges) {
        initial.insert(name(v), vector(&graph.initial[&v]));
        if v == graph.reference {
            for i in 0..7 {
                problem.fix_variable(&name(v), i);
            }
        } else {
            problem.set_variable_manifold(&name(v), Arc::new(SE3Manifold));
        }
    }
    for e in edges {
        let (a, b) = (name(e.a), name(e.b));
        let [qx, qy, qz, qw] = e.q_xyzw;
        let [tx, ty, tz] = e.t;
        let sqrt_information = na::Matrix6::from_fn(|i, j| e.sqrt_information[(i, j)]);
        problem.add_residual_block(
            6,
            &[a.as_str(), b.as_str()],
            Box::new(WhitenedBetween {
                z: [qx, qy, qz, qw, tx, ty, tz],
                sqrt_information,
            }),
            Some(Box::new(HuberLoss::new(huber_k))),
        );
    }
    (problem, initial)
}

/// Solve `graph` with tiny-solver's LM: at most `max_iterations` iterations,
/// stop on a relative cost decrease below `relative_tolerance`. `None` when
/// tiny-solver returns none (a NaN cost).
pub fn solve(
    graph: &PoseGraph,
    edges: &[Edge],
    huber_k: f64,
    max_iterations: usize,
    relative_tolerance: f64,
) -> Option<(BTreeMap<VehicleId, Pose>, Values)> {
    let (problem, initial) = build(graph, edges, huber_k);
    let options = OptimizerOptions {
        max_iteration: max_iterations,
        min_rel_error_decrease_threshold: relative_tolerance,
        min_abs_error_decrease_threshold: 0.0,
        min_error_threshold: 0.0,
        ..OptimizerOptions::default()
    };
    let result =
        LevenbergMarquardtOptimizer::default().optimize(&problem, &initial, Some(options))?;
    let mut poses = graph.initial.clone();
    for v in variables(edges) {
        poses.insert(v, pose(&result[&name(v)]));
    }
    Some((poses, result))
}

/// The marginals of a tiny-solver solution `values` of `problem` (as
/// [`build`] makes it), in shoal's convention, from tiny-solver's own
/// Jacobian at the solution.
pub fn marginals(
    problem: &Problem,
    values: &Values,
    poses: &BTreeMap<VehicleId, Pose>,
    reference: VehicleId,
    edges: &[Edge],
) -> Option<BTreeMap<VehicleId, nalgebra::Matrix6<f64>>> {
    let blocks = problem.initialize_parameter_blocks(values);
    let columns_by_name = problem.get_variable_name_to_col_idx_dict(&blocks);
    let n = variables(edges).len().saturating_sub(1) * 6;
    let symbolic = problem.build_symbolic_structure(&blocks, n, &columns_by_name);
    let (_, j) = problem.compute_residual_and_jacobian(&blocks, &columns_by_name, &symbolic);
    let columns: Vec<(VehicleId, usize)> = variables(edges)
        .into_iter()
        .filter(|v| *v != reference)
        .map(|v| (v, columns_by_name[&name(v)]))
        .collect();
    let inverse = crate::marginals::inverse_diagonal_blocks(j.as_ref(), &columns)?;
    Some(
        inverse
            .into_iter()
            .map(|(v, m)| (v, convert::marginal_to_shoal(&m, &poses[&v])))
            .collect(),
    )
}

/// tiny-solver's own objective (`Problem::compute_cost`: Σ ρ over its
/// whitened residuals) at `poses`.
pub fn objective(problem: &Problem, poses: &BTreeMap<VehicleId, Pose>, edges: &[Edge]) -> f64 {
    let values: Values = variables(edges)
        .into_iter()
        .map(|v| (name(v), vector(&poses[&v])))
        .collect();
    problem.compute_cost(&problem.initialize_parameter_blocks(&values))
}
