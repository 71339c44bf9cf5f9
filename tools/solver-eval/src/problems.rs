//! The pose graphs shoal's fusion solves, built as `fusion/benches/solve.rs`
//! builds them: one 2 s window (20 frames at 10 Hz) of synthetic observations
//! with 10 % wrong IDs and ~10 % planar flips for 10 and 100 vehicles, taken
//! from the fusion's last solve (`Fusion::last_graph`: the constraints its LM
//! minimised after the chi-square gate, from the spanning-tree start), and the
//! bench's `lm_only_100_vehicles` graph (one exact constraint per neighbouring
//! pair, a noisy start).

use nalgebra::Vector6;
use shoal_fusion::export::PoseGraph;
use shoal_fusion::solver::Constraint;
use shoal_fusion::{Fusion, FusionParams};
use shoal_proto::config::Fleet;
use shoal_proto::geometry::{perturb, Cov6, Pose};
use shoal_proto::{CodeSet, VehicleTruth};
use shoal_sim_bridge::obs_synth::{
    grid_formation, synthetic_fleet, FormationJitter, ObsSynth, ObsSynthParams, OutlierModel,
};
use std::collections::BTreeMap;

const FRAME_NS: u64 = 100_000_000; // 10 Hz cameras
const T0_NS: u64 = 1_000_000_000_000;

/// One problem: a name and its graph.
#[derive(Debug, Clone)]
pub struct Problem {
    pub name: String,
    pub graph: PoseGraph,
}

/// The bench's fleet and formation for `n` vehicles (n ≥ 10).
fn scenario(n: usize) -> (Fleet, Vec<VehicleTruth>) {
    let ids: Vec<u32> = (1..=n as u32).collect();
    let cols = if n <= 10 { 5 } else { 10 };
    (
        synthetic_fleet(n, CodeSet::Aruco4x4_1000).expect("synthetic fleet"),
        grid_formation(&ids, cols, 1.5, FormationJitter::default(), 1),
    )
}

/// The bench's synthetic observations: 10 % wrong IDs, ~10 % flips.
fn synth_params() -> ObsSynthParams {
    ObsSynthParams {
        outliers: OutlierModel {
            wrong_id_rate: 0.1,
            flip_rate: 0.1 / 0.9,
            ..OutlierModel::default()
        },
        ..ObsSynthParams::default()
    }
}

/// The graph of a fusion solve of one 2 s window of `n` vehicles (seed 1,
/// 20 frames, as the bench's `fusion_solve_2s_window/n`).
pub fn window(n: usize) -> Problem {
    let (fleet, truth) = scenario(n);
    let mut synth = ObsSynth::new(&fleet, synth_params(), 1);
    let mut fusion = Fusion::new(&fleet, FusionParams::default(), "solver-eval");
    let mut now = T0_NS;
    for k in 0..20u64 {
        now = T0_NS + k * FRAME_NS;
        for s in synth.observe(&truth, now) {
            let _ = fusion.ingest(s.obs.clone(), s.obs.observer, now);
        }
    }
    fusion.solve(now);
    let graph = fusion.last_graph().expect("the solve has a graph").clone();
    Problem {
        name: format!("window_{n}"),
        graph,
    }
}

/// The bench's `lm_only_100_vehicles`: 100 vehicles, one constraint (σ 1 cm /
/// 0.01 rad) per pair closer than 3.2 m, every pose but the reference's
/// perturbed by (5, -3, 2) cm and (0.01, 0.02, -0.01) rad.
pub fn lm_only_100() -> Problem {
    let (_, truth) = scenario(100);
    let poses: BTreeMap<u32, Pose> = truth
        .iter()
        .map(|t| {
            (
                t.vehicle,
                truth[0].world_from_body.inverse() * t.world_from_body,
            )
        })
        .collect();
    let mut constraints = Vec::new();
    for (a, pa) in &poses {
        for (b, pb) in &poses {
            if a < b && (pa.translation.vector - pb.translation.vector).norm() < 3.2 {
                constraints.push(Constraint {
                    a: *a,
                    b: *b,
                    a_from_b: pa.inverse() * pb,
                    covariance: Cov6::identity() * 1e-4,
                });
            }
        }
    }
    let initial: BTreeMap<u32, Pose> = poses
        .iter()
        .map(|(v, p)| {
            (
                *v,
                if *v == 1 {
                    *p
                } else {
                    perturb(p, &Vector6::new(0.05, -0.03, 0.02, 0.01, 0.02, -0.01))
                },
            )
        })
        .collect();
    Problem {
        name: "lm_only_100".to_string(),
        graph: PoseGraph {
            reference: 1,
            initial,
            constraints,
        },
    }
}
