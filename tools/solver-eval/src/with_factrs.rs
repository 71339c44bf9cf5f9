//! The graph solved by factrs: an `SE3` variable per vehicle, a
//! `BetweenResidual` per constraint with its full 6×6 information
//! (`GaussianNoise::from_matrix_inf`) and factrs' Huber kernel (k = 4.1 on the
//! whitened residual's norm, as shoal's), Levenberg–Marquardt.
//!
//! Gauge: factrs cannot hold a variable fixed, so the reference gets a
//! `PriorResidual` at its pose with σ = 1e-9 (m, rad), as the gtsam check in
//! `fusion/tests/python/solve_g2o.py` does.

use crate::convert::{self, Edge};
use factrs::assign_symbols;
use factrs::containers::{FactorBuilder, Graph, Values};
use factrs::linalg::{Matrix6, Vector3};
use factrs::noise::GaussianNoise;
use factrs::optimizers::{
    BaseOptParams, LevenMarquardt, LevenParams, OptError, OptObserver, Optimizer,
};
use factrs::residuals::{BetweenResidual, PriorResidual};
use factrs::robust::Huber;
use factrs::variables::{SE3, SO3};
use shoal_fusion::export::PoseGraph;
use shoal_proto::geometry::Pose;
use shoal_proto::VehicleId;
use std::cell::RefCell;
use std::collections::{BTreeMap, BTreeSet};
use std::rc::Rc;

// One symbol per vehicle pose: `V(vehicle id)`.
assign_symbols!(V: SE3);

/// Sigma of the reference's prior (the gauge).
const GAUGE_SIGMA: f64 = 1e-9;

/// What one factrs solve returns.
#[derive(Debug)]
pub struct Outcome {
    pub poses: BTreeMap<VehicleId, Pose>,
    /// Linearizations (LM steps, the failed last one included).
    pub iterations: usize,
    /// How the optimizer ended: `converged`, `max iterations`, `failed to step`.
    pub ending: &'static str,
    pub values: Values,
}

fn se3(pose: &Pose) -> SE3 {
    let (t, q) = (pose.translation.vector, pose.rotation.coords);
    SE3::from_rot_trans(
        SO3::from_xyzw(q.x, q.y, q.z, q.w),
        Vector3::new(t.x, t.y, t.z),
    )
}

fn pose(x: &SE3) -> Pose {
    let (r, t) = (x.rot(), x.xyz());
    convert::pose([r.x(), r.y(), r.z(), r.w()], [t[0], t[1], t[2]])
}

fn matrix6(m: &nalgebra::Matrix6<f64>) -> Matrix6 {
    Matrix6::from_fn(|i, j| m[(i, j)])
}

/// The vehicles the constraints name.
pub fn variables(edges: &[Edge]) -> BTreeSet<VehicleId> {
    edges.iter().flat_map(|e| [e.a, e.b]).collect()
}

/// factrs' graph and initial values for `graph`.
pub fn build(graph: &PoseGraph, edges: &[Edge], huber_k: f64) -> (Graph, Values) {
    let mut values = Values::new();
    for v in variables(edges) {
        values.insert(V(v), se3(&graph.initial[&v]));
    }
    let mut g = Graph::with_capacity(edges.len() + 1);
    g.add_factor(
        FactorBuilder::<6>::new1(
            PriorResidual::new(se3(&graph.initial[&graph.reference])),
            V(graph.reference),
        )
        .noise(GaussianNoise::<6>::from_scalar_sigma(GAUGE_SIGMA))
        .build(),
    );
    for e in edges {
        let z = se3(&convert::pose(e.q_xyzw, e.t));
        let noise = GaussianNoise::<6>::from_matrix_sqrt_inf(matrix6(&e.sqrt_information));
        g.add_factor(
            FactorBuilder::<6>::new2(BetweenResidual::new(z), V(e.a), V(e.b))
                .noise(noise)
                .robust(Huber::new(huber_k))
                .build(),
        );
    }
    (g, values)
}

/// Counts the optimizer's steps and keeps the last values (factrs returns
/// none when it fails to step).
#[derive(Clone, Default)]
struct Watch(Rc<RefCell<(usize, Option<Values>)>>);

impl OptObserver for Watch {
    fn on_step(&self, values: &Values, _time: i64) {
        let mut w = self.0.borrow_mut();
        w.0 += 1;
        w.1 = Some(values.clone());
    }
}

/// Solve `graph` with factrs' LM: at most `max_iterations` steps, stop on a
/// relative cost decrease below `relative_tolerance`.
pub fn solve(
    graph: &PoseGraph,
    edges: &[Edge],
    huber_k: f64,
    max_iterations: usize,
    relative_tolerance: f64,
) -> Outcome {
    let (g, values) = build(graph, edges, huber_k);
    let params = LevenParams {
        base: BaseOptParams {
            max_iterations,
            error_tol_relative: relative_tolerance,
            error_tol_absolute: 0.0,
            error_tol: 0.0,
        },
        ..LevenParams::default()
    };
    let mut opt = LevenMarquardt::new(params, g);
    let watch = Watch::default();
    opt.add_observer(watch.clone());
    let start = values.clone();
    let (values, ending, failed) = match opt.optimize(values) {
        Ok(v) => (v, "converged", 0),
        Err(OptError::MaxIterations(v)) => (v, "max iterations", 0),
        Err(OptError::FailedToStep) => {
            let last = watch.0.borrow().1.clone().unwrap_or(start);
            (last, "failed to step", 1)
        }
        Err(OptError::InvalidSystem) => panic!("factrs: invalid system"),
    };
    let iterations = watch.0.borrow().0 + failed;
    let mut poses = graph.initial.clone();
    for v in variables(edges) {
        let x: &SE3 = values.get(V(v)).expect("every variable has a value");
        poses.insert(v, pose(x));
    }
    Outcome {
        poses,
        iterations,
        ending,
        values,
    }
}

/// The marginals of a factrs solution (`values`, `poses`) of `graph` (as
/// [`build`] makes it), in shoal's convention, from factrs' own whitened
/// Jacobian at the solution (the reference excluded; its tight prior fixes
/// the gauge).
pub fn marginals(
    graph: &Graph,
    values: &Values,
    poses: &BTreeMap<VehicleId, Pose>,
    reference: VehicleId,
    edges: &[Edge],
) -> Option<BTreeMap<VehicleId, nalgebra::Matrix6<f64>>> {
    let order = factrs::containers::ValuesOrder::from_values(values);
    let graph_order = graph.sparsity_pattern(order);
    let linear = graph.linearize(values);
    let j = linear.residual_jacobian(&graph_order).diff;
    let columns: Vec<(VehicleId, usize)> = variables(edges)
        .into_iter()
        .filter(|v| *v != reference)
        .map(|v| (v, graph_order.order.get(V(v)).expect("a column").idx))
        .collect();
    let blocks = crate::marginals::inverse_diagonal_blocks(j.as_ref(), &columns)?;
    Some(
        blocks
            .into_iter()
            .map(|(v, m)| (v, convert::marginal_to_shoal(&m, &poses[&v])))
            .collect(),
    )
}

/// factrs' own objective (`Graph::error`: ½ Σ ρ over its whitened residuals,
/// the gauge prior included) at `poses`.
pub fn objective(graph: &Graph, poses: &BTreeMap<VehicleId, Pose>, edges: &[Edge]) -> f64 {
    let mut values = Values::new();
    for v in variables(edges) {
        values.insert(V(v), se3(&poses[&v]));
    }
    graph.error(&values)
}
