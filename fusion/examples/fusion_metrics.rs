//! Prints map error, outlier precision/recall and solve time of the fusion on
//! synthetic observations for 3 (paper fleet), 10 and 100 vehicles, over
//! several seeds.
//!
//! `cargo run --release -p shoal-fusion --example fusion_metrics [seeds] [frames]`

#[path = "../tests/common/mod.rs"]
mod common;

use common::*;
use shoal_fusion::FusionParams;
use shoal_proto::geometry::difference;
use shoal_proto::{CodeSet, VehicleState};
use shoal_sim_bridge::obs_synth::{
    grid_formation, line_abreast, synthetic_fleet, FormationJitter, ObsSynthParams, OutlierKind,
    OutlierModel,
};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let seeds: u64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(5);
    let frames: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(10);
    let outliers = ObsSynthParams {
        outliers: OutlierModel {
            wrong_id_rate: 0.1,
            flip_rate: 0.1 / 0.9,
            ..OutlierModel::default()
        },
        ..ObsSynthParams::default()
    };
    println!("frames per run: {frames} (10 Hz), window 2 s; outliers: 10% wrong IDs + ~10% flips");
    println!(
        "{:>4} {:>6} {:>5} {:>7} {:>9} {:>9} {:>9} {:>9} {:>6} {:>6} {:>9}",
        "N",
        "mode",
        "seed",
        "obs",
        "outl.%",
        "max_t_mm",
        "max_r_deg",
        "rms_t_mm",
        "prec",
        "recall",
        "solve_ms"
    );
    for n in [3usize, 10, 100] {
        for (mode, synth) in [("clean", ObsSynthParams::default()), ("20%", outliers)] {
            for seed in 0..seeds {
                let (fleet, truth) = if n == 3 {
                    (paper_fleet(), line_abreast(&[10, 15, 17], 2.0))
                } else {
                    let ids: Vec<u32> = (1..=n as u32).collect();
                    let cols = if n == 10 { 5 } else { 10 };
                    (
                        synthetic_fleet(n, CodeSet::Aruco4x4_1000).unwrap(),
                        grid_formation(&ids, cols, 1.5, FormationJitter::default(), seed),
                    )
                };
                let (mut fusion, obs, now) =
                    run_frames(&fleet, &truth, synth, FusionParams::default(), seed, frames);
                let t = std::time::Instant::now();
                let map = fusion.solve(now);
                let ms = t.elapsed().as_secs_f64() * 1e3;
                let want = truth_poses(&fleet, &truth);
                let (t_err, r_err, live) = map_error(&map, &want);
                let mut sq = 0.0;
                for v in map
                    .vehicles
                    .iter()
                    .filter(|v| v.state == VehicleState::Live)
                {
                    sq += difference(&v.reference_from_vehicle, &want[&v.vehicle])
                        .fixed_rows::<3>(0)
                        .norm_squared();
                }
                let s = score(&map, &obs);
                let outl = obs
                    .iter()
                    .filter(|o| o.outlier != OutlierKind::Inlier)
                    .count();
                println!(
                    "{:>4} {:>6} {:>5} {:>7} {:>9.1} {:>9.2} {:>9.3} {:>9.2} {:>6.3} {:>6.3} {:>9.2}{}",
                    n,
                    mode,
                    seed,
                    obs.len(),
                    100.0 * outl as f64 / obs.len().max(1) as f64,
                    t_err * 1e3,
                    r_err.to_degrees(),
                    (sq / live.max(1) as f64).sqrt() * 1e3,
                    s.precision(),
                    s.recall(),
                    ms,
                    if live < n { format!("  ({live}/{n} live)") } else { String::new() }
                );
            }
        }
    }
}
