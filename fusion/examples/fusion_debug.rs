//! Lists the wrong verdicts of one run: `cargo run --release -p shoal-fusion --example fusion_debug [n] [seed] [frames]`
#[path = "../tests/common/mod.rs"]
mod common;
use common::*;
use shoal_fusion::FusionParams;
use shoal_proto::CodeSet;
use shoal_sim_bridge::obs_synth::*;
fn main() {
    let a: Vec<String> = std::env::args().collect();
    let n: usize = a.get(1).and_then(|s| s.parse().ok()).unwrap_or(10);
    let seed: u64 = a.get(2).and_then(|s| s.parse().ok()).unwrap_or(0);
    let frames: usize = a.get(3).and_then(|s| s.parse().ok()).unwrap_or(20);
    let rate: f64 = a.get(4).and_then(|s| s.parse().ok()).unwrap_or(0.1);
    let (fleet, truth) = if n == 3 {
        (paper_fleet(), line_abreast(&[10, 15, 17], 2.0))
    } else {
        let ids: Vec<u32> = (1..=n as u32).collect();
        (
            synthetic_fleet(n, CodeSet::Aruco4x4_1000).unwrap(),
            grid_formation(
                &ids,
                if n <= 10 { 5 } else { 10 },
                1.5,
                FormationJitter::default(),
                seed,
            ),
        )
    };
    let sp = ObsSynthParams {
        outliers: OutlierModel {
            wrong_id_rate: rate,
            flip_rate: rate / (1.0 - rate),
            ..Default::default()
        },
        ..Default::default()
    };
    let (mut fusion, obs, now) =
        run_frames(&fleet, &truth, sp, FusionParams::default(), seed, frames);
    let map = fusion.solve(now);
    for o in &obs {
        let reps: Vec<_> = map
            .edges
            .iter()
            .filter(|r| {
                r.stamp_ns == o.obs.stamp_ns
                    && r.observer == o.obs.observer
                    && r.camera == o.obs.camera
                    && r.frame_seq == o.obs.frame_seq
                    && r.target_marker == o.obs.target_marker
            })
            .collect();
        let n_hyp = if o.obs.alternative.is_some() { 2 } else { 1 };
        for h in 0..n_hyp {
            let r = reps.get(h as usize).unwrap_or(&reps[0]);
            if o.hypothesis_is_true(h) == r.rejected.is_some() {
                println!("  reps {:?}", reps);
                let e = shoal_proto::geometry::difference(
                    &o.obs.observer_from_target,
                    &o.truth_observer_from_target,
                );
                let d2 = (e.transpose() * o.obs.covariance.try_inverse().unwrap() * e)[0];
                println!("WRONG {}->{} (claimed {:?}) cam{} t={} hyp{} {:?} twin {:.0}°: verdict {:?} chi2 {:.1}; primary-vs-truth chi2 {:.1} err {:.4?}", o.obs.observer, o.true_target, o.obs.target_vehicle, o.obs.camera, (o.obs.stamp_ns - T0_NS) / FRAME_NS, h, o.outlier, o.twin_angle_rad.to_degrees(), r.rejected, r.chi2, d2, e.as_slice());
                if let Some(rel) =
                    shoal_fusion::MapView::new(map.clone()).relative(o.obs.observer, o.true_target)
                {
                    let e2 = shoal_proto::geometry::difference(
                        &rel.a_from_b.pose,
                        &o.truth_observer_from_target,
                    );
                    let e3 = shoal_proto::geometry::difference(
                        &o.obs.observer_from_target,
                        &rel.a_from_b.pose,
                    );
                    println!(
                        "    map-vs-truth {:.4?}; obs-vs-map chi2 {:.1}",
                        e2.as_slice(),
                        (e3.transpose() * o.obs.covariance.try_inverse().unwrap() * e3)[0]
                    );
                }
            }
        }
    }
    println!("{:?}", score(&map, &obs));
}
