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

/// Issue #16: the demo through the realistic camera (blur, rolling shutter,
/// the port, lamps, snow, other PSFs, exposure, JPEG) with every node holding
/// a lab's calibration of its camera, not the renderer's. The pair 10–15 is
/// localized within centimetres, and not to the ideal camera's fractions of
/// a millimetre (`docs/results.md`, *swarm demo*: 7–10 mm over seeds 1–5; the
/// pairs with vehicle 17 vary from seed to seed, its marker half outside the
/// one view that has it behind the port).
#[test]
fn demo_swarm_through_the_realistic_camera_localizes_its_near_pair_within_centimetres() {
    let cfg = DemoConfig {
        duration_s: 4.0,
        frame_rate_hz: 1.0,
        cameras: side_cameras(),
        // A realistic frame takes ~0.3 s to render: six a tick within 5 s of wall time.
        time_scale: 0.2,
        progress: false,
        log: None,
        profile: Some(shoal_sim_bridge::profile::CameraProfile::realistic()),
        ..DemoConfig::default()
    };
    let s = shoal::demo::run(&cfg, |_, _, _| {}).unwrap();
    assert!(s.frames_processed > 0 && s.observations_sent > 0, "{s:?}");
    let p = s
        .pairs
        .iter()
        .find(|p| (p.a, p.b) == (10, 15))
        .expect("the pair 10-15");
    eprintln!("through the realistic camera: {:?}", s.pairs);
    assert!(
        p.maps_localized * 2 >= p.maps_evaluated && p.maps_evaluated > 0,
        "pair 10-15 localized in only {}/{} maps",
        p.maps_localized,
        p.maps_evaluated
    );
    // A node that took the renderer's lens in air for its camera would be
    // ~34 % off in range (0.6 m at 1.75 m); the ideal camera reads the pair
    // to ~0.1 mm (the test above, the demo).
    assert!(
        p.position_error_m < 0.03 && p.angle_error_deg < 1.0 && p.position_error_m > 0.002,
        "pair 10-15: {:.4} m, {:.2}°",
        p.position_error_m,
        p.angle_error_deg
    );
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

/// Issue #21: vehicle 17 hidden from every camera for 10 s of the closed-loop
/// demo. With the vehicles' nav it stays in the map as `Predicted`, inside
/// its reported 3σ, and the controller keeps it near its slot; without nav
/// it is marked `Stale` (lost) for the same span.
#[test]
fn a_vehicle_hidden_for_10_s_is_carried_by_odometry_and_lost_without() {
    let run = |nav: bool| {
        let cfg = DemoConfig {
            duration_s: 18.0,
            frame_rate_hz: 1.0,
            cameras: side_cameras(),
            // Half speed, as above: at full speed a loaded machine skips
            // ticks' rendering, and a skipped last frame before the
            // occlusion hides the vehicle for longer than the 10 s carried.
            time_scale: 0.5,
            progress: false,
            log: None,
            nav,
            occlude: Some("17:5:15".parse().unwrap()),
            ..DemoConfig::default()
        };
        let s = shoal::demo::run(&cfg, |_, _, _| {}).unwrap();
        let o = s.occlusion.expect("an occlusion report");
        eprintln!("nav {nav}: {o:?}");
        o
    };
    let with = run(true);
    // Live while the window still holds its last frames (~2 s), then predicted.
    assert!(with.maps >= 30, "{with:?}");
    assert!(with.predicted * 2 >= with.maps, "{with:?}");
    assert_eq!((with.stale, with.unobserved), (0, 0), "{with:?}");
    assert_eq!(with.within_3_sigma, with.maps, "{with:?}");
    assert!(with.max_position_error_m < 0.3, "{with:?}");
    assert!(with.max_slot_error_m < 0.6, "the formation holds: {with:?}");
    let without = run(false);
    assert_eq!(without.predicted, 0, "{without:?}");
    assert!(without.stale * 2 >= without.maps, "{without:?}");
}
