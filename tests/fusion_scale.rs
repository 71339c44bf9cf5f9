//! Fusion keeps up with 100 vehicles at 10 Hz in observation mode, over
//! Zenoh, and its last map is accurate against ground truth.
//! (Four markers per vehicle need 400 IDs: the enhanced set has 50, so the
//! synthetic fleet carries AprilTag 36h11 IDs; fusion does not care which.)

#[path = "common/fusion_rig.rs"]
mod fusion_rig;

use fusion_rig::Rig;
use shoal_fusion::FusionParams;
use shoal_proto::geometry::difference;
use shoal_proto::messages::{FleetMap, VehicleState};
use shoal_proto::CodeSet;
use shoal_services::fusion::Placement;
use shoal_sim_bridge::obs_synth::{
    grid_formation, synthetic_fleet, FormationJitter, ObsSynth, ObsSynthParams,
};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Bound on one vehicle's NEES `eᵀ Σ⁻¹ e` (error against truth under the
/// map's marginal covariance): χ²₆ at 1 − 10⁻⁶ (scipy.stats.chi2.ppf), a
/// family-wise 10⁻⁴ over 100 vehicles when the covariance is right. The
/// default age inflation makes the covariance of a still formation
/// conservative (fusion/tests/fusion.rs,
/// `reported_covariance_matches_the_error_over_many_seeds`), so a failure
/// means an error the covariance does not account for.
const MAX_NEES: f64 = 38.26;
/// Bound on a localized vehicle's reported translation σ, m: the error bound
/// of the in-process 100-vehicle test (fusion/tests/fusion.rs,
/// `hundred_vehicles_localize_in_one_map`), so that the NEES check cannot be
/// passed by a vacuous covariance.
const MAX_REPORTED_STD_M: f64 = 0.05;

#[test]
fn fusion_of_100_vehicles_keeps_up_at_10_hz() {
    let fleet = Arc::new(synthetic_fleet(100, CodeSet::AprilTag36h11).unwrap());
    let ids: Vec<u32> = fleet.vehicles.iter().map(|v| v.id).collect();
    let truth = grid_formation(&ids, 10, 1.5, FormationJitter::default(), 3);
    let rig = Rig::new(fleet.clone());
    let clock = rig.clock.clone();
    let fusion = rig.fusion(Placement::Central, FusionParams::default(), 100_000);
    let vehicles_bus = rig.session();
    let keys = fleet.keys();
    let pubs = rig.observation_publishers(&vehicles_bus);
    let observer = rig.session();
    let maps = observer.subscribe::<FleetMap>(&keys.map(), 1024).unwrap();
    std::thread::sleep(Duration::from_millis(300));

    let mut synth = ObsSynth::new(&fleet, ObsSynthParams::default(), 11);
    let run = Duration::from_secs(4);
    let started = Instant::now();
    let mut tick = 0u64;
    let mut sent = 0usize;
    while started.elapsed() < run {
        let stamp = tick * 100_000_000;
        clock.advance_to(stamp);
        for o in synth.observe(&truth, stamp) {
            pubs[&o.obs.observer].put(&o.obs).unwrap();
            sent += 1;
        }
        tick += 1;
        let due = Duration::from_millis(100 * tick);
        if let Some(wait) = due.checked_sub(started.elapsed()) {
            std::thread::sleep(wait);
        }
    }
    std::thread::sleep(Duration::from_millis(500));
    let received: Vec<FleetMap> = maps.drain().into_iter().map(|r| r.msg).collect();
    let elapsed = started.elapsed().as_secs_f64();
    let rate = fusion.maps_published() as f64 / elapsed;
    eprintln!(
        "{sent} observations in {tick} ticks; {} maps in {elapsed:.1} s ({rate:.1} Hz); {} dropped",
        fusion.maps_published(),
        fusion.observations_dropped()
    );
    assert_eq!(
        fusion.observations_dropped(),
        0,
        "fusion fell behind its input"
    );
    assert!(
        rate >= 7.0,
        "fusion published only {rate:.1} maps/s (target 10)"
    );
    let last = received.last().expect("no map received");
    let live = last
        .vehicles
        .iter()
        .filter(|v| v.state == VehicleState::Live)
        .count();
    assert!(
        live >= 95,
        "only {live}/100 vehicles localized in the last map"
    );
    // Accuracy against ground truth: every localized vehicle's error within
    // its reported covariance, and that covariance not vacuous.
    let world_from_ref = truth
        .iter()
        .find(|t| t.vehicle == fleet.reference_vehicle)
        .expect("the reference has a truth entry")
        .world_from_body;
    let mut worst_nees = 0.0f64;
    for v in last
        .vehicles
        .iter()
        .filter(|v| v.state == VehicleState::Live && v.vehicle != last.reference)
    {
        let world_from_v = truth.iter().find(|t| t.vehicle == v.vehicle).unwrap();
        let want = world_from_ref.inverse() * world_from_v.world_from_body;
        let e = difference(&v.reference_from_vehicle, &want);
        let info = v.covariance.try_inverse().expect("invertible covariance");
        let nees = (e.transpose() * info * e)[0];
        let max_std = (0..3)
            .map(|i| v.covariance[(i, i)].sqrt())
            .fold(0.0, f64::max);
        worst_nees = worst_nees.max(nees);
        assert!(
            nees <= MAX_NEES,
            "vehicle {}: error {:?} is {nees:.1} (χ²₆) under its covariance",
            v.vehicle,
            e.as_slice()
        );
        assert!(
            max_std <= MAX_REPORTED_STD_M,
            "vehicle {}: reported σ {max_std} m",
            v.vehicle
        );
    }
    eprintln!("largest NEES over the live vehicles: {worst_nees:.1}");
    fusion.stop();
}
