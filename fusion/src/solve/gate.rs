//! Steps 5 and 6 of the solve: Levenberg–Marquardt on the graph
//! ([`solver::solve`]), then the chi-square gate on every accepted
//! hypothesis' own residual against the solution, re-solving without the
//! rejects until none is new or the rounds run out.

use super::frames::Frame;
use super::groups::TrackGroups;
use super::hypotheses::Hypotheses;
use super::init::{graph, Graph};
use crate::consistency::Tree;
use crate::solver::{self, SolverParams};
use proto::geometry::{Cov6, Pose};
use proto::VehicleId;
use std::collections::{BTreeMap, BTreeSet};

/// `reference_from_vehicle` and its marginal covariance per localized vehicle.
pub(crate) type Poses = BTreeMap<VehicleId, (Pose, Cov6)>;

/// Settings of the solve-and-gate rounds.
#[derive(Debug, Clone, Copy)]
pub(crate) struct GateParams {
    /// Gate on an accepted hypothesis' squared Mahalanobis residual.
    pub chi2_gate: f64,
    /// Solve / gate rounds at most (at least one is run).
    pub max_rounds: usize,
    pub solver: SolverParams,
    /// Threads for the graph's constraints and the gate's residuals.
    pub threads: usize,
}

/// The solution after the last round, and what the gate decided.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct GatedSolution {
    pub solution: Poses,
    /// Hypotheses (frame, hypothesis) rejected by the gate.
    pub gated: BTreeSet<(usize, u8)>,
    /// Per frame and hypothesis, the chi2 of the last round's gate (`None`:
    /// not accepted, or gated in an earlier round).
    pub chi2: Vec<[Option<f64>; 2]>,
    pub rounds: usize,
    /// LM iterations over all rounds.
    pub lm_iterations: usize,
    /// The last round's solver failed and reported the spanning-tree poses.
    pub solver_failed: bool,
    /// The last round's graph.
    pub graph: Graph,
}

/// Solve, gate, and re-solve without the rejects.
pub(crate) fn solve_and_gate(
    frames: &[Frame],
    groups: &TrackGroups,
    hyps: &Hypotheses,
    reference: VehicleId,
    params: &GateParams,
) -> GatedSolution {
    let mut out = GatedSolution {
        solution: Poses::new(),
        gated: BTreeSet::new(),
        chi2: vec![[None; 2]; frames.len()],
        rounds: 0,
        lm_iterations: 0,
        solver_failed: false,
        graph: Graph::default(),
    };
    for round in 0..params.max_rounds.max(1) {
        out.rounds = round + 1;
        let g = graph(hyps, groups, frames, &out.gated, reference, params.threads);
        let (solution, iterations) =
            optimize(reference, &g, &hyps.selection.trees[0], &params.solver);
        out.solution = solution;
        out.solver_failed = iterations.is_none();
        out.lm_iterations += iterations.unwrap_or(0);
        out.graph = g;
        let newly = gate_round(
            frames,
            &hyps.accepted,
            &mut out.gated,
            &mut out.chi2,
            &out.solution,
            params.chi2_gate,
            params.threads,
        );
        if newly == 0 {
            break;
        }
    }
    out
}

/// LM on `graph`, and its iterations; when it fails, the spanning-tree poses
/// of the graph's vehicles, and `None`.
fn optimize(
    reference: VehicleId,
    graph: &Graph,
    tree: &Tree,
    params: &SolverParams,
) -> (Poses, Option<usize>) {
    match solver::solve(reference, &graph.initial, &graph.constraints, params) {
        Ok(s) => {
            let poses = s
                .poses
                .iter()
                .map(|(v, p)| {
                    (
                        *v,
                        (*p, s.covariances.get(v).copied().unwrap_or(Cov6::zeros())),
                    )
                })
                .collect();
            (poses, Some(s.iterations))
        }
        Err(e) => {
            tracing::warn!("pose graph solve failed ({e}); reporting the spanning-tree poses");
            let poses = graph
                .initial
                .keys()
                .map(|&v| {
                    let r = tree.relative(reference, v);
                    (v, (r.pose, r.covariance))
                })
                .collect();
            (poses, None)
        }
    }
}

/// The chi-square gate on every accepted hypothesis not gated yet (each
/// observation on its own): those whose residual against `solution` exceeds
/// `chi2_gate` join `gated`. Every chi2 of this round is kept in `chi2`
/// (cleared first). Returns how many were gated.
fn gate_round(
    frames: &[Frame],
    accepted: &BTreeMap<(usize, u8), usize>,
    gated: &mut BTreeSet<(usize, u8)>,
    chi2: &mut [[Option<f64>; 2]],
    solution: &Poses,
    chi2_gate: f64,
    threads: usize,
) -> usize {
    let mut newly = 0;
    chi2.iter_mut().for_each(|c| *c = [None; 2]);
    // The residuals (independent: on up to `threads`), then the verdicts.
    let judged: Vec<(usize, u8)> = accepted
        .keys()
        .filter(|k| !gated.contains(k))
        .copied()
        .collect();
    let residuals = crate::par::map(&judged, threads, 256, |_, &(oi, h)| {
        frames[oi].chi2(usize::from(h), solution)
    });
    for (&(oi, h), x2) in judged.iter().zip(residuals) {
        chi2[oi][usize::from(h)] = Some(x2);
        if x2 > chi2_gate {
            gated.insert((oi, h));
            newly += 1;
        }
    }
    newly
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::testing::{frame, COV};
    use proto::geometry::pose_from_xyz_rpy;

    #[test]
    fn the_gate_rejects_a_residual_beyond_its_threshold_and_keeps_one_within() {
        let at = |y: f64| pose_from_xyz_rpy([2.0, y, 0.0], [0.0, 0.0, 0.0]);
        // Solution: 2 at (2, 0, 0) from 1. Frame 0 is 3σ off in y (chi2 9),
        // frame 1 6σ off (chi2 36); the gate is χ²₆ at 99.99% (27.86).
        let sigma = COV.sqrt();
        let frames = vec![
            frame(0, 1, 2, 0, at(3.0 * sigma), None),
            frame(1, 1, 2, 0, at(6.0 * sigma), None),
        ];
        let solution = Poses::from([
            (1, (Pose::identity(), Cov6::zeros())),
            (2, (at(0.0), Cov6::zeros())),
        ]);
        let accepted = BTreeMap::from([((0, 0), 0), ((1, 0), 0)]);
        let mut gated = BTreeSet::new();
        let mut chi2 = vec![[None; 2]; 2];
        let newly = gate_round(
            &frames, &accepted, &mut gated, &mut chi2, &solution, 27.86, 2,
        );
        assert_eq!(newly, 1);
        assert_eq!(gated, BTreeSet::from([(1, 0)]));
        assert!((chi2[0][0].unwrap() - 9.0).abs() < 1e-6, "{chi2:?}");
        assert!((chi2[1][0].unwrap() - 36.0).abs() < 1e-6, "{chi2:?}");
        // The next round does not judge a gated hypothesis again.
        let newly = gate_round(
            &frames, &accepted, &mut gated, &mut chi2, &solution, 27.86, 2,
        );
        assert_eq!((newly, chi2[1][0]), (0, None));
    }
}
