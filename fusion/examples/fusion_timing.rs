//! Stage timings of one solve: `cargo run --release -p shoal-fusion --example fusion_timing [n] [frames] [outlier_rate]`
//! (outlier rate: wrong IDs + flips, default 0.2; 0 is the clean stream of `tests/fusion_scale.rs`).
#[path = "../tests/common/mod.rs"]
mod common;
use common::*;
use shoal_fusion::FusionParams;
use shoal_proto::CodeSet;
use shoal_sim_bridge::obs_synth::*;
fn main() {
    let n: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(100);
    let frames: usize = std::env::args()
        .nth(2)
        .and_then(|s| s.parse().ok())
        .unwrap_or(20);
    let outliers: f64 = std::env::args()
        .nth(3)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0.2);
    let ids: Vec<u32> = (1..=n as u32).collect();
    let fleet = synthetic_fleet(n, CodeSet::Aruco4x4_1000).unwrap();
    let truth = grid_formation(
        &ids,
        if n <= 10 { 5 } else { 10 },
        1.5,
        FormationJitter::default(),
        1,
    );
    let sp = ObsSynthParams {
        outliers: OutlierModel {
            wrong_id_rate: outliers / 2.0,
            flip_rate: (outliers / 2.0) / (1.0 - outliers / 2.0),
            ..Default::default()
        },
        ..Default::default()
    };
    let (fusion, obs, now) = run_frames(&fleet, &truth, sp, FusionParams::default(), 1, frames);
    for _ in 0..3 {
        let mut f = fusion.clone();
        let map = f.solve(now);
        let st = f.stats().last_solve;
        println!("{n} vehicles, {} obs: total {} us, consistency {} us, lm+gate {} us, lm iterations {}, gate rounds {}, pairs {}, clusters {}", obs.len(), map.solve_time_us, st.consistency_us, st.lm_us, st.lm_iterations, st.gate_rounds, st.pairs, st.clusters);
    }
}
