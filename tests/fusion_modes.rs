//! Central fusion (ground station) and decentralized fusion (running on a
//! vehicle) agree when every message reaches both.

#[path = "common/fusion_rig.rs"]
mod fusion_rig;

use fusion_rig::Rig;
use shoal_fusion::{FusionParams, MapView};
use shoal_proto::config::Fleet;
use shoal_proto::geometry::difference;
use shoal_proto::messages::{FleetMap, VehicleState};
use shoal_services::fusion::Placement;
use shoal_sim_bridge::obs_synth::{line_abreast, ObsSynth, ObsSynthParams};
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

#[test]
fn central_and_on_vehicle_fusion_agree_when_all_messages_arrive() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let fleet = Arc::new(Fleet::load(&root.join("configs/fleets/paper.toml")).unwrap());
    let ids: Vec<u32> = fleet.vehicles.iter().map(|v| v.id).collect();
    let truth = line_abreast(&ids, 1.75);
    let rig = Rig::new(fleet.clone());
    let clock = rig.clock.clone();
    let params = FusionParams {
        record_solve_time: false,
        ..FusionParams::default()
    };
    let central = rig.fusion(Placement::Central, params, 10_000);
    let on_vehicle = rig.fusion(Placement::OnVehicle(15), params, 10_000);
    let bus = rig.session();
    let keys = fleet.keys();
    let pubs = rig.observation_publishers(&bus);
    let decentral = bus.subscribe::<FleetMap>(&keys.map_of("15"), 64).unwrap();
    std::thread::sleep(Duration::from_millis(300));

    let mut synth = ObsSynth::new(&fleet, ObsSynthParams::default(), 5);
    for tick in 0..15u64 {
        let stamp = tick * 100_000_000;
        clock.advance_to(stamp);
        for o in synth.observe(&truth, stamp) {
            pubs[&o.obs.observer].put(&o.obs).unwrap();
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    // Time stands still now: wait until both have solved over everything.
    std::thread::sleep(Duration::from_millis(1000));
    let a = central.latest().expect("central produced no map");
    let b = on_vehicle
        .latest()
        .expect("on-vehicle fusion produced no map");
    assert_eq!(a.producer, "central");
    assert_eq!(b.producer, "15");
    let deadline = Instant::now() + Duration::from_secs(5);
    let mut heard = false;
    while Instant::now() < deadline && !heard {
        heard = decentral.recv_timeout(Duration::from_millis(200)).is_some();
    }
    assert!(heard, "the on-vehicle map is not published on its own key");

    let (va, vb) = (MapView::new(a), MapView::new(b));
    for &v in &ids {
        let (ea, eb) = (va.vehicle(v).unwrap(), vb.vehicle(v).unwrap());
        assert_eq!(ea.state, VehicleState::Live);
        assert_eq!(ea.state, eb.state);
        let d = difference(&ea.reference_from_vehicle, &eb.reference_from_vehicle);
        assert!(
            d.fixed_rows::<3>(0).norm() < 1e-6,
            "vehicle {v}: {:.2e} m apart",
            d.fixed_rows::<3>(0).norm()
        );
        assert!(
            d.fixed_rows::<3>(3).norm() < 1e-6,
            "vehicle {v}: rotations differ"
        );
    }
}
