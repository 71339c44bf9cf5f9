//! End to end over Zenoh (in-process router, loopback TCP): simulator →
//! three nodes → fusion. Each test is bounded in time.

use shoal::demo::{DemoConfig, SimulatedSwarm};
use shoal_proto::messages::{FleetMap, VehicleState};
use std::time::{Duration, Instant};

/// Side cameras only: they are the ones that see neighbours in line abreast,
/// and rendering all five per vehicle would triple the test's time.
fn side_cameras() -> Option<Vec<String>> {
    Some(vec!["port".into(), "starboard".into()])
}

#[test]
fn demo_swarm_fuses_within_a_few_centimetres_at_half_per_metre() {
    let cfg = DemoConfig {
        duration_s: 14.0,
        frame_rate_hz: 1.0,
        cameras: side_cameras(),
        // Half speed: rendering must keep up even when CI shares the cores.
        time_scale: 0.5,
        progress: false,
        log: Some(std::env::temp_dir().join(format!("shoal-e2e-{}.mcap", std::process::id()))),
        ..DemoConfig::default()
    };
    let s = shoal::demo::run(&cfg, |_, _, _| {}).unwrap();
    assert!(s.frames_processed > 0 && s.observations_sent > 0, "{s:?}");
    let log = s.log.as_ref().expect("the demo writes a log");
    assert!(log.messages > 0 && log.dropped == 0, "{log:?}");
    let info = shoal_record::info(&log.path).unwrap();
    assert!(
        format!("{info}").contains("obs"),
        "log info lacks observations: {info}"
    );
    std::fs::remove_file(&log.path).ok();
    for p in &s.pairs {
        assert!(
            p.maps_localized * 2 >= p.maps_evaluated && p.maps_evaluated > 0,
            "pair {}-{} localized in only {}/{} maps",
            p.a,
            p.b,
            p.maps_localized,
            p.maps_evaluated
        );
        assert!(
            p.position_error_m < 0.05,
            "pair {}-{}: {:.3} m",
            p.a,
            p.b,
            p.position_error_m
        );
        assert!(
            p.angle_error_deg < 2.0,
            "pair {}-{}: {:.2}°",
            p.a,
            p.b,
            p.angle_error_deg
        );
    }
}

fn state_of(map: &FleetMap, v: u32) -> Option<VehicleState> {
    map.vehicles
        .iter()
        .find(|e| e.vehicle == v)
        .map(|e| e.state)
}

fn wait_for_state(
    maps: &shoal_bus::Subscription<FleetMap>,
    v: u32,
    want: VehicleState,
    timeout: Duration,
) -> bool {
    let deadline = Instant::now() + timeout;
    while Instant::now() < deadline {
        if let Some(r) = maps.recv_timeout(Duration::from_millis(200)) {
            if state_of(&r.msg, v) == Some(want) {
                return true;
            }
        }
    }
    false
}

#[test]
fn killed_node_is_marked_stale_then_rejoins() {
    let cfg = DemoConfig {
        duration_s: 120.0, // stopped by the test long before
        frame_rate_hz: 1.0,
        cameras: side_cameras(),
        time_scale: 1.0,
        progress: false,
        log: None,
        ..DemoConfig::default()
    };
    let mut swarm = SimulatedSwarm::start(&cfg, vec![]).unwrap();
    let bus = swarm.session().unwrap();
    let maps = bus
        .subscribe::<FleetMap>(&swarm.fleet.keys().map(), 64)
        .unwrap();
    assert!(
        wait_for_state(&maps, 15, VehicleState::Live, Duration::from_secs(30)),
        "vehicle 15 never localized"
    );
    assert!(swarm.kill_node(15));
    assert!(
        wait_for_state(&maps, 15, VehicleState::Stale, Duration::from_secs(20)),
        "vehicle 15 not marked stale after its node stopped"
    );
    swarm.start_node(15).unwrap();
    assert!(
        wait_for_state(&maps, 15, VehicleState::Live, Duration::from_secs(30)),
        "vehicle 15 did not rejoin after its node restarted"
    );
    swarm.shutdown().unwrap();
}
