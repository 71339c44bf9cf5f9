#[path = "../tests/common/mod.rs"]
mod common;
use common::*;
use shoal_fusion::FusionParams;
use shoal_proto::geometry::difference;
use shoal_sim_bridge::obs_synth::*;
fn main() {
    let seed: u64 = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(1);
    let rate: f64 = std::env::args().nth(2).and_then(|s| s.parse().ok()).unwrap_or(0.0);
    let fleet = paper_fleet();
    let truth = line_abreast(&[10, 15, 17], 2.0);
    let sp = ObsSynthParams { outliers: OutlierModel { wrong_id_rate: rate, flip_rate: rate / (1.0 - rate), ..Default::default() }, ..Default::default() };
    let (mut fusion, obs, now) = run_frames(&fleet, &truth, sp, FusionParams::default(), seed, 10);
    let map = fusion.solve(now);
    let want = truth_poses(&fleet, &truth);
    for v in &map.vehicles {
        let e = difference(&v.reference_from_vehicle, &want[&v.vehicle]);
        let sd: Vec<f64> = (0..6).map(|i| v.covariance[(i, i)].sqrt() * 1e3).collect();
        println!("{} {:?} err_mm {:.2} {:.2} {:.2} sd_mm {:.2} {:.2} {:.2}", v.vehicle, v.state, e[0]*1e3, e[1]*1e3, e[2]*1e3, sd[0], sd[1], sd[2]);
    }
    for o in &obs {
        let e = difference(&o.obs.observer_from_target, &o.truth_observer_from_target);
        let sd: Vec<f64> = (0..3).map(|i| o.obs.covariance[(i, i)].sqrt() * 1e3).collect();
        let rep: Vec<_> = map.edges.iter().filter(|r| r.stamp_ns == o.obs.stamp_ns && r.observer == o.obs.observer && r.camera == o.obs.camera && r.target_marker == o.obs.target_marker).map(|r| (r.rejected.clone(), (r.chi2 * 10.0).round() / 10.0)).collect();
        println!("{}->{} cam{} {:?} twin {:.0}° err_mm {:.1} {:.1} {:.1} sd {:.1} {:.1} {:.1} {:?}", o.obs.observer, o.true_target, o.obs.camera, o.outlier, o.twin_angle_rad.to_degrees(), e[0]*1e3, e[1]*1e3, e[2]*1e3, sd[0], sd[1], sd[2], rep);
    }
    println!("{:?}", fusion.stats());
}
