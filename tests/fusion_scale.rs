//! Fusion keeps up with 100 vehicles at 10 Hz in observation mode, over Zenoh.
//! (Four markers per vehicle need 400 IDs: the enhanced set has 50, so the
//! synthetic fleet carries AprilTag 36h11 IDs; fusion does not care which.)

#[path = "common/fusion_rig.rs"]
mod fusion_rig;

use fusion_rig::Rig;
use shoal_fusion::service::Placement;
use shoal_fusion::FusionParams;
use shoal_proto::messages::{FleetMap, VehicleState};
use shoal_proto::CodeSet;
use shoal_sim_bridge::obs_synth::{
    grid_formation, synthetic_fleet, FormationJitter, ObsSynth, ObsSynthParams,
};
use std::sync::Arc;
use std::time::{Duration, Instant};

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
    fusion.stop();
}
