//! Faults of the links between vehicles and the ground station, injected at
//! the transport: a fault-injecting TCP relay between two Zenoh routers
//! (`shoal_services::relay`: partitions, delay, jitter, retransmission stalls) and
//! message-level faults before publishing (`MessageFaults`: loss,
//! duplication, reordering), and vehicle clocks off by a set skew.
//!
//! Observations come from the observation-level synthesizer (ground truth
//! plus the noise their covariances claim), so map errors can be checked
//! against the truth; fusion runs as its Zenoh service. Time is a shared
//! manual clock advanced by the test, 10 ticks per second of wall time.
//! Every wait is bounded. The figures printed here are those in
//! `docs/results.md`, "Faults survived".

#[path = "common/faults.rs"]
mod common;

use common::*;
use shoal_bus::{client_of, free_port, Bus, Connect, Publisher, Token};
use shoal_fusion::{Fusion, FusionParams};
use shoal_proto::clock::ManualClock;
use shoal_proto::config::Fleet;
use shoal_proto::geometry::difference;
use shoal_proto::messages::{FleetMap, Observation, RejectReason, VehicleState, VehicleTruth};
use shoal_services::fusion::{FusionConfig, FusionHandle, Placement};
use shoal_services::relay::{FaultPlan, MessageFaultPlan, MessageFaults, Relay};
use shoal_sim_bridge::obs_synth::{line_abreast, ObsSynth, ObsSynthParams};
use std::collections::{BTreeMap, BTreeSet};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

const TICK: Duration = Duration::from_millis(100);
const TICK_NS: u64 = 100_000_000;
/// Line abreast this far apart: each vehicle's side cameras see its
/// neighbours' markers (at 1.75 m the middle vehicle's cameras, 0.95 m
/// ahead of its marker, see neither neighbour's marker inside their 60°).
const SPACING_M: f64 = 2.5;
/// Map error bound under every fault, for every vehicle with a pose (Stale
/// ones at their last pose too), derived from the same observation stream
/// fused with no network at all ([`LinkFree`], measured by each test on its
/// own synthesizer seed; 300 ticks: 0.9–3.0 cm / 0.2–0.7° with the full
/// window, 15–20 cm / 2.5–2.7° for a map of a single tick, seeds 5, 11, 21,
/// 31). A map under faults is within `WINDOW_MARGIN` times the link-free
/// full-window worst, or, above it, within what the map itself claims
/// (position error inside the 99.99% ellipsoid of its covariance, χ²₃ =
/// 21.1) and never worse than `PARTIAL_TICK_MARGIN` times the worst
/// link-free map of one tick, nor its angle worse than that margin times
/// the single-tick map's. Vehicle 17 is 5 m from the reference
/// through two 2.5 m links; the worst maps are the first ones after a
/// recovery, when the window holds only a frame or two per track — the
/// map's covariance says so too.
///
/// `WINDOW_MARGIN`: a faulted window holds the same observations as the
/// link-free one less those lost or late; with half of them the error grows
/// by √2 and the margin leaves the rest for which half. The central test
/// also bounds its maps' p95 error by it (measured 0.9–1.0 cm against
/// 1.7 cm; a fusion that keeps only ~1 tick, `window_s` 0.15, reads 6.5 cm
/// and fails, though it passed the former 5 cm / 25 cm / 3° bounds).
const WINDOW_MARGIN: f64 = 2.0;
/// The fewest observations a map can hold is not a whole tick: a cut drops
/// the tick in flight part-way through (100–200 ms of delay and jitter), so
/// as the window drains during the cut the last map that still localizes a
/// vehicle may rest on part of its tick, and that vehicle then stays Stale
/// at that pose. With half a tick's observations the error grows by √2
/// (measured once: vehicle 17 Stale at 0.174 m against a single-tick worst
/// of 0.170 m, its NEES 3.7 — the map said so).
const PARTIAL_TICK_MARGIN: f64 = std::f64::consts::SQRT_2;
const MAX_POSITION_NEES: f64 = 21.1;
/// Ticks of the link-free reference: more than any test publishes (the
/// partition test at most ~240), so every observation a test sends is in it.
const LINK_FREE_TICKS: u64 = 300;

fn params() -> FusionParams {
    FusionParams {
        record_solve_time: false,
        ..FusionParams::default()
    }
}

fn spawn_fusion(
    port: u16,
    fleet: &Arc<Fleet>,
    placement: Placement,
    clock: &Arc<ManualClock>,
) -> FusionHandle {
    shoal_services::fusion::spawn(
        &Bus::open(&client_of(port)).unwrap(),
        FusionConfig {
            fleet: fleet.clone(),
            params: params(),
            placement,
            rate_hz: 10.0,
            queue_capacity: 10_000,
            link: false,
        },
        clock.clone(),
    )
    .unwrap()
}

/// One vehicle's radio: its session on its side's router, its observation
/// publisher and its liveliness token.
struct Vehicle {
    publisher: Publisher<Observation>,
    _token: Token,
    _bus: Bus,
}

fn vehicle(port: u16, fleet: &Fleet, v: u32) -> Vehicle {
    let bus = Bus::open(&client_of(port)).unwrap();
    let keys = fleet.keys();
    Vehicle {
        publisher: bus.publisher(keys.observations(v)).unwrap(),
        _token: bus.liveliness_token(keys.alive(v)).unwrap(),
        _bus: bus,
    }
}

/// Router A (the vehicles' side) reaching router B only through a relay.
struct TwoSides {
    port_a: u16,
    port_b: u16,
    relay: Relay,
    _routers: (Bus, Bus),
    _dir: std::path::PathBuf,
}

fn two_sides(name: &str, plan: FaultPlan) -> TwoSides {
    let dir = scratch(name);
    let (port_a, port_b) = (free_port().unwrap(), free_port().unwrap());
    let b = write_router_config(&dir.join("b.json5"), &[format!("127.0.0.1:{port_b}")], &[]);
    let router_b = Bus::open(&Connect::File(b)).unwrap();
    let upstream: SocketAddr = ([127, 0, 0, 1], port_b).into();
    let relay = Relay::start("127.0.0.1:0", upstream, plan).unwrap();
    let a = write_router_config(
        &dir.join("a.json5"),
        &[format!("127.0.0.1:{port_a}")],
        &[format!("127.0.0.1:{}", relay.local_addr().port())],
    );
    let router_a = Bus::open(&Connect::File(a)).unwrap();
    TwoSides {
        port_a,
        port_b,
        relay,
        _routers: (router_a, router_b),
        _dir: dir,
    }
}

/// Publish one tick of synthesized observations from their observers.
fn publish(vehicles: &BTreeMap<u32, Vehicle>, obs: &[Observation]) {
    for o in obs {
        vehicles[&o.observer].publisher.put(o).unwrap();
    }
}

/// Sleep out the rest of a tick that started at `t0`.
fn end_tick(t0: Instant) {
    if let Some(rest) = TICK.checked_sub(t0.elapsed()) {
        std::thread::sleep(rest);
    }
}

/// The worst map errors of a test's observation stream fused without the
/// network: an in-process `Fusion` fed every tick in order and solved each
/// tick (`window_*`), and a fresh `Fusion` per tick holding that tick alone
/// (`single_*`).
#[derive(Debug, Clone, Copy)]
struct LinkFree {
    window_max_m: f64,
    single_max_m: f64,
    single_max_deg: f64,
}

fn link_free(fleet: &Fleet, truth: &[VehicleTruth], seed: u64) -> LinkFree {
    let mut synth = ObsSynth::new(fleet, ObsSynthParams::default(), seed);
    let mut window = Fusion::new(fleet, params(), "link-free");
    let (mut w, mut one) = ((0.0f64, 0.0f64), (0.0f64, 0.0f64));
    for tick in 2..2 + LINK_FREE_TICKS {
        let stamp = tick * TICK_NS;
        let mut single = Fusion::new(fleet, params(), "link-free-tick");
        for o in synth.observe(truth, stamp) {
            let v = o.obs.observer;
            single.ingest(o.obs.clone(), v, stamp).unwrap();
            window.ingest(o.obs, v, stamp).unwrap();
        }
        for (map, worst) in [
            (window.solve(stamp), &mut w),
            (single.solve(stamp), &mut one),
        ] {
            for e in map_errors(&map, truth) {
                *worst = (worst.0.max(e.position_m), worst.1.max(e.angle_deg));
            }
        }
    }
    let bound = LinkFree {
        window_max_m: w.0,
        single_max_m: one.0,
        single_max_deg: one.1,
    };
    eprintln!(
        "link-free (seed {seed}): {bound:?}, full-window angle max {:.2}°",
        w.1
    );
    bound
}

fn check_errors(
    map: &FleetMap,
    truth: &[VehicleTruth],
    bound: &LinkFree,
    when: &str,
) -> (f64, f64) {
    let mut worst = (0.0f64, 0.0f64);
    for e in map_errors(map, truth) {
        let within = e.position_m < WINDOW_MARGIN * bound.window_max_m
            || (e.position_nees < MAX_POSITION_NEES
                && e.position_m <= PARTIAL_TICK_MARGIN * bound.single_max_m);
        assert!(
            within && e.angle_deg <= PARTIAL_TICK_MARGIN * bound.single_max_deg,
            "{when}: map of {} seq {}: vehicle {} ({:?}) off by {:.3} m (NEES {:.1}) / {:.2}°; \
             link-free {bound:?}",
            map.producer,
            map.seq,
            e.vehicle,
            e.state,
            e.position_m,
            e.position_nees,
            e.angle_deg
        );
        worst = (worst.0.max(e.position_m), worst.1.max(e.angle_deg));
    }
    worst
}

/// Decentralized fusion on every vehicle; vehicle 10 on one side of the
/// relay, 15 and 17 on the other. Cut: each side keeps publishing a map of
/// what it can hear (its own observations only; the far side's vehicles
/// Stale at their last pose). Heal: the three maps converge to one.
#[test]
#[allow(
    clippy::too_many_lines,
    reason = "one fault scenario in order (steady state, cut, heal, convergence), each phase asserting on what the previous one left"
)]
fn decentralized_maps_split_under_partition_and_converge_after_heal() {
    /// The convergence bound stated in docs/results.md: the 2 s window must
    /// refill with observations every side heard, plus router reconnection.
    const CONVERGENCE_BOUND: Duration = Duration::from_secs(6);
    let fleet = fleet();
    let ids: Vec<u32> = fleet.vehicles.iter().map(|v| v.id).collect();
    let truth = line_abreast(&ids, SPACING_M);
    let net = two_sides("faults-partition", FaultPlan::default());
    let side = |v: u32| if v == 10 { net.port_a } else { net.port_b };
    let clock = Arc::new(ManualClock::new(TICK_NS));
    let fusions: BTreeMap<u32, FusionHandle> = ids
        .iter()
        .map(|&v| {
            (
                v,
                spawn_fusion(side(v), &fleet, Placement::OnVehicle(v), &clock),
            )
        })
        .collect();
    let vehicles: BTreeMap<u32, Vehicle> = ids
        .iter()
        .map(|&v| (v, vehicle(side(v), &fleet, v)))
        .collect();
    std::thread::sleep(Duration::from_millis(500));
    let mut synth = ObsSynth::new(&fleet, ObsSynthParams::default(), 11);
    let bound = link_free(&fleet, &truth, 11);
    let tick = std::cell::Cell::new(1u64);
    let step = |synth: &mut ObsSynth| {
        let t0 = Instant::now();
        tick.set(tick.get() + 1);
        let stamp = tick.get() * TICK_NS;
        clock.advance_to(stamp);
        let obs: Vec<Observation> = synth
            .observe(&truth, stamp)
            .into_iter()
            .map(|o| o.obs)
            .collect();
        publish(&vehicles, &obs);
        end_tick(t0);
    };
    let latest = |v: u32| fusions[&v].latest();
    // One map: every vehicle Live in every map, and the maps fuse the same
    // observations over the part of the window they share (their stamps
    // differ by up to a solve period, so their windows end differently).
    let agree = || -> Option<f64> {
        let maps: Vec<FleetMap> = ids.iter().filter_map(|&v| latest(v)).collect();
        if maps.len() != ids.len() || !maps.iter().all(all_live) {
            return None;
        }
        let window_ns = (params().window_s * 1e9) as u64;
        let lo = maps
            .iter()
            .map(|m| m.stamp_ns)
            .max()?
            .saturating_sub(window_ns)
            + 2 * TICK_NS;
        let hi = maps
            .iter()
            .map(|m| m.stamp_ns)
            .min()?
            .checked_sub(3 * TICK_NS)?;
        let fused = |m: &FleetMap| -> BTreeSet<(u32, u8, u64, u32)> {
            m.edges
                .iter()
                .filter(|e| e.stamp_ns >= lo && e.stamp_ns <= hi)
                .map(|e| (e.observer, e.camera, e.frame_seq, e.target_marker))
                .collect()
        };
        let first = fused(&maps[0]);
        if first.is_empty() || maps.iter().any(|m| fused(m) != first) {
            return None;
        }
        Some(
            maps.iter()
                .flat_map(|a| maps.iter().map(move |b| disagreement_m(a, b)))
                .fold(0.0, f64::max),
        )
    };

    // Connected: one map everywhere.
    let t_start = Instant::now();
    let mut connected_at = None;
    while connected_at.is_none() && t_start.elapsed() < Duration::from_secs(10) {
        step(&mut synth);
        if agree().is_some() {
            connected_at = Some(t_start.elapsed());
        }
    }
    let connected_at =
        connected_at.expect("the three on-vehicle maps never agreed while connected");

    // Partition for 3 s.
    net.relay.switch().cut();
    let cut_stamp = tick.get() * TICK_NS;
    let mut seq_at_cut = BTreeMap::new();
    for &v in &ids {
        seq_at_cut.insert(v, latest(v).map_or(0, |m| m.seq));
    }
    let mut worst = (0.0f64, 0.0f64);
    for i in 0..30 {
        step(&mut synth);
        if i < 15 {
            continue;
        }
        for &v in &ids {
            let m = latest(v).unwrap();
            let w = check_errors(&m, &truth, &bound, "partitioned");
            worst = (worst.0.max(w.0), worst.1.max(w.1));
        }
    }
    let (m10, m15, m17) = (
        latest(10).unwrap(),
        latest(15).unwrap(),
        latest(17).unwrap(),
    );
    for (m, v) in [(&m10, 10), (&m15, 15), (&m17, 17)] {
        assert!(
            m.seq > seq_at_cut[&v] + 10,
            "map of {v} stopped during the partition"
        );
    }
    // Each side hears only its own side's vehicles: alive there, Stale across.
    assert_eq!(state_of(&m10, 10), Some(VehicleState::Live));
    assert_eq!(state_of(&m10, 15), Some(VehicleState::Stale));
    assert_eq!(state_of(&m10, 17), Some(VehicleState::Stale));
    for m in [&m15, &m17] {
        assert_eq!(state_of(m, 10), Some(VehicleState::Stale), "{}", m.producer);
        assert_eq!(state_of(m, 15), Some(VehicleState::Live), "{}", m.producer);
        assert_eq!(state_of(m, 17), Some(VehicleState::Live), "{}", m.producer);
    }
    // ... and fuses only its own side's observations.
    let after_cut = |m: &FleetMap| -> BTreeSet<u32> {
        m.edges
            .iter()
            .filter(|e| e.stamp_ns > cut_stamp + 5 * TICK_NS)
            .map(|e| e.observer)
            .collect()
    };
    assert_eq!(after_cut(&m10), BTreeSet::from([10]));
    assert_eq!(after_cut(&m15), BTreeSet::from([15, 17]));
    assert_eq!(after_cut(&m17), BTreeSet::from([15, 17]));
    // Side B still sees all three vehicles (15 and 17 look at 10).
    assert!(m15
        .vehicles
        .iter()
        .all(|e| e.state != VehicleState::Unobserved));

    // Heal.
    net.relay.switch().heal();
    let healed = Instant::now();
    let mut converged = None;
    while healed.elapsed() < CONVERGENCE_BOUND + Duration::from_secs(4) {
        step(&mut synth);
        if converged.is_none() {
            if let Some(d) = agree() {
                converged = Some((healed.elapsed(), d));
            }
        }
        if converged.is_some() && healed.elapsed() > Duration::from_secs(3) {
            break;
        }
    }
    let (converged_after, d) = converged.expect("maps did not converge after the heal");
    // Freeze time: same window everywhere → the same map, to rounding.
    std::thread::sleep(Duration::from_millis(800));
    let maps: Vec<FleetMap> = ids.iter().map(|&v| latest(v).unwrap()).collect();
    for m in &maps {
        assert!(
            all_live(m),
            "map of {} after heal: {:?}",
            m.producer,
            m.vehicles
        );
        check_errors(m, &truth, &bound, "healed");
        assert!(disagreement_m(m, &maps[0]) < 1e-6, "maps differ after heal");
    }
    eprintln!(
        "FAULTS partition: connected maps agreed after {:.1} s; partitioned 3.0 s: worst error {:.3} m / {:.2}°; \
         healed maps fused the same observations after {:.2} s (disagreement {:.4} m), identical once time stood still",
        connected_at.as_secs_f64(),
        worst.0,
        worst.1,
        converged_after.as_secs_f64(),
        d
    );
    assert!(
        converged_after < CONVERGENCE_BOUND,
        "converged after {converged_after:?}, bound {CONVERGENCE_BOUND:?}"
    );
}

/// Central fusion on the ground side of a relay that delays (100 ms),
/// jitters (+0–100 ms) and stalls (5% of chunks held 200 ms: lost segments)
/// the vehicles' link, which is also cut twice for 0.5 s.
#[test]
#[allow(
    clippy::too_many_lines,
    reason = "one fault scenario in order (impaired link, two cuts, recovery), each phase asserting on what the previous one left"
)]
fn central_map_stays_within_bound_under_delay_jitter_stalls_and_link_cuts() {
    let fleet = fleet();
    let ids: Vec<u32> = fleet.vehicles.iter().map(|v| v.id).collect();
    let truth = line_abreast(&ids, SPACING_M);
    let plan = FaultPlan {
        latency: Duration::from_millis(100),
        jitter: Duration::from_millis(100),
        loss_stall_probability: 0.05,
        loss_stall: Duration::from_millis(200),
        flap: None,
        rate_bps: None,
        seed: 3,
    };
    let net = two_sides("faults-delay", plan);
    let clock = Arc::new(ManualClock::new(TICK_NS));
    let fusion = spawn_fusion(net.port_b, &fleet, Placement::Central, &clock);
    let ground = Bus::open(&client_of(net.port_b)).unwrap();
    let maps = ground
        .subscribe::<FleetMap>(&fleet.keys().map(), 1024)
        .unwrap();
    let vehicles: BTreeMap<u32, Vehicle> = ids
        .iter()
        .map(|&v| (v, vehicle(net.port_a, &fleet, v)))
        .collect();
    std::thread::sleep(Duration::from_millis(500));
    let mut synth = ObsSynth::new(&fleet, ObsSynthParams::default(), 5);
    let bound = link_free(&fleet, &truth, 5);
    let mut nees = Figure::default();
    let (mut error, mut angle, mut age_up) =
        (Figure::default(), Figure::default(), Figure::default());
    let mut first_live = None;
    // Per cut: when and at which stamp it healed, and how long until fresh data made every vehicle Live again.
    let mut cuts: Vec<(Instant, u64, Option<Duration>)> = Vec::new();
    let mut maps_during_cuts = 0;
    let started = Instant::now();
    for tick in 2..=140u64 {
        let t0 = Instant::now();
        let stamp = tick * TICK_NS;
        clock.advance_to(stamp);
        let obs: Vec<Observation> = synth
            .observe(&truth, stamp)
            .into_iter()
            .map(|o| o.obs)
            .collect();
        publish(&vehicles, &obs);
        match tick {
            50 | 100 => {
                net.relay.switch().cut();
                cuts.push((Instant::now(), u64::MAX, None));
            }
            55 | 105 => {
                net.relay.switch().heal();
                let c = cuts.last_mut().unwrap();
                (c.0, c.1) = (Instant::now(), stamp);
            }
            _ => {}
        }
        let link_up = net.relay.switch().is_up();
        for r in maps.drain() {
            let m = r.msg;
            if first_live.is_none() && all_live(&m) {
                first_live = Some(started.elapsed());
            }
            if first_live.is_none() {
                continue;
            }
            for e in map_errors(&m, &truth) {
                error.add(e.position_m);
                angle.add(e.angle_deg);
                nees.add(e.position_nees);
            }
            check_errors(&m, &truth, &bound, "link faults");
            if !link_up {
                maps_during_cuts += 1;
            }
            // The most lagging vehicle's newest observation.
            let oldest = m.vehicles.iter().map(|e| e.last_seen_ns).min().unwrap_or(0);
            if let Some((healed, heal_stamp, recovered)) = cuts.last_mut() {
                // Recovered: every vehicle Live on observations taken after the heal.
                if link_up && recovered.is_none() && all_live(&m) && oldest > *heal_stamp {
                    *recovered = Some(healed.elapsed());
                }
            }
            if link_up && cuts.last().is_none_or(|c| c.2.is_some()) {
                age_up.add(m.stamp_ns.saturating_sub(oldest) as f64 * 1e-9);
            }
        }
        end_tick(t0);
    }
    let first_live = first_live.expect("no map ever had every vehicle Live");
    assert_eq!(cuts.len(), 2);
    let recoveries: Vec<Duration> = cuts
        .iter()
        .map(|(_, _, r)| r.expect("a link cut was never recovered from (all Live on fresh data)"))
        .collect();
    assert!(
        maps_during_cuts > 0,
        "the ground station published no map while cut off"
    );
    let stats = net.relay.stats();
    let age_p95 = age_up.percentile(0.95);
    eprintln!(
        "FAULTS link: first all-Live map after {:.1} s; {} maps; position error max {:.3} m (p95 {:.3}), position NEES max {:.1} (p95 {:.1}), angle max {:.2}°; \
         data age (most lagging vehicle) p95 {:.2} s with the link up; recovered (all Live on post-heal data) {:.2} s and {:.2} s after the two 0.5 s cuts; \
         relay {} connections, {} cut, {} stalls; fusion dropped {}",
        first_live.as_secs_f64(),
        error.samples.len() / ids.len(),
        error.max(),
        error.percentile(0.95),
        nees.max(),
        nees.percentile(0.95),
        angle.max(),
        age_p95,
        recoveries[0].as_secs_f64(),
        recoveries[1].as_secs_f64(),
        stats.connections.load(std::sync::atomic::Ordering::Relaxed),
        stats.cut.load(std::sync::atomic::Ordering::Relaxed),
        stats.stalls.load(std::sync::atomic::Ordering::Relaxed),
        fusion.observations_dropped()
    );
    assert!(stats.stalls.load(std::sync::atomic::Ordering::Relaxed) > 0);
    // The bulk of the maps is as good as the link-free window (p95 0.9 cm
    // measured against a link-free worst of 0.9 cm, seed 5): within its margin.
    let p95 = error.percentile(0.95);
    assert!(
        p95 < WINDOW_MARGIN * bound.window_max_m,
        "position error p95 {p95:.4} m, link-free window worst {:.4} m",
        bound.window_max_m
    );
    for r in &recoveries {
        assert!(*r < Duration::from_secs(4), "recovery took {r:?}");
    }
    assert!(age_p95 < 1.0, "maps lag the vehicles by {age_p95:.2} s");
    assert_eq!(fusion.observations_dropped(), 0);
}

/// Observations lost (20%), duplicated (30%) and shuffled within windows of
/// 6 before they reach central fusion: every duplicate is rejected as such,
/// and the map is exactly the one fusion makes of the unique observations
/// that arrived, in order.
#[test]
fn duplicated_reordered_and_lost_observations_are_counted_once() {
    let fleet = fleet();
    let ids: Vec<u32> = fleet.vehicles.iter().map(|v| v.id).collect();
    let truth = line_abreast(&ids, SPACING_M);
    let port = free_port().unwrap();
    let _router = Bus::open(&Connect::Router { port }).unwrap();
    let clock = Arc::new(ManualClock::new(TICK_NS));
    let service = spawn_fusion(port, &fleet, Placement::Central, &clock);
    let vehicles: BTreeMap<u32, Vehicle> =
        ids.iter().map(|&v| (v, vehicle(port, &fleet, v))).collect();
    std::thread::sleep(Duration::from_millis(500));
    let mut faults = MessageFaults::new(MessageFaultPlan {
        loss: 0.2,
        duplicate: 0.3,
        reorder_window: 6,
        seed: 9,
    });
    let mut reference = Fusion::new(&fleet, params(), "central");
    let mut synth = ObsSynth::new(&fleet, ObsSynthParams::default(), 21);
    let bound = link_free(&fleet, &truth, 21);
    let mut seen = BTreeSet::new();
    let mut unique = 0u64;
    let mut stamp = 0;
    for tick in 2..=30u64 {
        let t0 = Instant::now();
        stamp = tick * TICK_NS;
        clock.advance_to(stamp);
        let offered: Vec<Observation> = synth
            .observe(&truth, stamp)
            .into_iter()
            .map(|o| o.obs)
            .collect();
        let arrived = faults.apply(offered.clone());
        publish(&vehicles, &arrived);
        // The reference: what arrived, once each, in the order it was offered.
        let key = |o: &Observation| (o.observer, o.camera, o.frame_seq, o.target_marker);
        let arrived_keys: BTreeSet<_> = arrived.iter().map(key).collect();
        for o in offered
            .into_iter()
            .filter(|o| arrived_keys.contains(&key(o)))
        {
            if seen.insert(key(&o)) {
                unique += 1;
                let v = o.observer;
                reference.ingest(o, v, stamp).unwrap();
            }
        }
        end_tick(t0);
    }
    // Time stands still: let the service drain and solve.
    let f = faults.stats();
    wait_for(Duration::from_secs(10), || {
        (service.stats().received >= f.delivered).then_some(())
    })
    .unwrap_or_else(|| {
        panic!(
            "fusion received {} of {} delivered",
            service.stats().received,
            f.delivered
        )
    });
    std::thread::sleep(Duration::from_millis(500));
    let got = service.latest().unwrap();
    let want = reference.solve(stamp);
    assert_eq!(got.stamp_ns, want.stamp_ns);
    let stats = service.stats();
    let dups = stats.rejected_at_ingest.get(&RejectReason::Duplicate);
    assert_eq!(dups, f.duplicated, "duplicates rejected vs injected");
    assert_eq!(
        stats.ingested, unique,
        "each arrived observation admitted once"
    );
    for (a, b) in got.vehicles.iter().zip(&want.vehicles) {
        assert_eq!((a.vehicle, a.state), (b.vehicle, b.state));
        let d = difference(&a.reference_from_vehicle, &b.reference_from_vehicle);
        assert!(
            d.norm() < 1e-9,
            "vehicle {}: {:.2e} from the clean fusion",
            a.vehicle,
            d.norm()
        );
    }
    assert!(all_live(&got));
    let (pos, ang) = check_errors(&got, &truth, &bound, "message faults");
    eprintln!(
        "FAULTS messages: offered {}, lost {}, duplicated {}, reordered {}, delivered {}; fusion received {}, \
         admitted {} (= unique arrivals), rejected {} as Duplicate; map equals the clean fusion of the arrivals \
         (< 1e-9); error {:.3} m / {:.2}°",
        f.offered,
        f.lost,
        f.duplicated,
        f.reordered,
        f.delivered,
        stats.received,
        stats.ingested,
        dups,
        pos,
        ang
    );
    assert!(
        f.duplicated >= 5 && f.reordered >= 5 && f.lost >= 5,
        "{f:?}"
    );
}

/// Vehicle clocks ahead of the ground station by up to
/// `max_clock_skew_s` (0.25 s), or behind by less than the window (2 s), are
/// tolerated; ahead by more is rejected as `ClockSkew`, behind by more than
/// the window as `Stale`, each reported in the map's edge reports.
#[test]
fn clock_skew_within_bound_is_tolerated_and_beyond_rejected_with_reason() {
    let fleet = fleet();
    let ids: Vec<u32> = fleet.vehicles.iter().map(|v| v.id).collect();
    let truth = line_abreast(&ids, SPACING_M);
    let port = free_port().unwrap();
    let _router = Bus::open(&Connect::Router { port }).unwrap();
    let clock = Arc::new(ManualClock::new(10 * TICK_NS));
    let service = spawn_fusion(port, &fleet, Placement::Central, &clock);
    let ground = Bus::open(&client_of(port)).unwrap();
    let maps = ground
        .subscribe::<FleetMap>(&fleet.keys().map(), 1024)
        .unwrap();
    let vehicles: BTreeMap<u32, Vehicle> =
        ids.iter().map(|&v| (v, vehicle(port, &fleet, v))).collect();
    std::thread::sleep(Duration::from_millis(500));
    let mut synth = ObsSynth::new(&fleet, ObsSynthParams::default(), 31);
    let bound = link_free(&fleet, &truth, 31);
    let mut tick = 10u64;
    // Run a phase with per-vehicle skews (ns, + = vehicle clock ahead); count what each vehicle sent.
    let mut run = |skew: &BTreeMap<u32, i64>, ticks: u64| -> (BTreeMap<u32, u64>, Vec<FleetMap>) {
        let mut sent = BTreeMap::new();
        maps.drain();
        for _ in 0..ticks {
            let t0 = Instant::now();
            tick += 1;
            let stamp = tick * TICK_NS;
            clock.advance_to(stamp);
            let obs: Vec<Observation> = synth
                .observe(&truth, stamp)
                .into_iter()
                .map(|o| {
                    let mut o = o.obs;
                    o.stamp_ns = o.stamp_ns.saturating_add_signed(skew[&o.observer]);
                    *sent.entry(o.observer).or_insert(0) += 1;
                    o
                })
                .collect();
            publish(&vehicles, &obs);
            end_tick(t0);
        }
        std::thread::sleep(Duration::from_millis(300));
        (sent, maps.drain().into_iter().map(|r| r.msg).collect())
    };
    let count = |maps: &[FleetMap], observer: u32, reason: RejectReason| {
        maps.iter()
            .flat_map(|m| &m.edges)
            .filter(|e| e.observer == observer && e.rejected.as_ref() == Some(&reason))
            .count() as u64
    };
    let ms = |x: i64| x * 1_000_000;

    // Within bounds: 15 is 0.2 s ahead, 17 is 1.2 s behind.
    let within = BTreeMap::from([(10, 0), (15, ms(200)), (17, ms(-1200))]);
    let (_, m1) = run(&within, 25);
    let s1 = service.stats();
    assert_eq!(s1.rejected_at_ingest.get(&RejectReason::ClockSkew), 0);
    assert_eq!(s1.rejected_at_ingest.get(&RejectReason::Stale), 0);
    let last = m1.last().expect("no maps");
    assert!(all_live(last), "{:?}", last.vehicles);
    let (pos1, ang1) = check_errors(last, &truth, &bound, "skew within bounds");

    // Beyond: 17 is 0.6 s ahead (ClockSkew), 15 is 2.5 s behind (Stale).
    let beyond = BTreeMap::from([(10, 0), (15, ms(-2500)), (17, ms(600))]);
    let (sent, m2) = run(&beyond, 20);
    let s2 = service.stats();
    let sent = |v: u32| sent.get(&v).copied().unwrap_or(0);
    assert!(sent(15) > 0 && sent(17) > 0);
    let skewed = s2.rejected_at_ingest.get(&RejectReason::ClockSkew);
    let stale = s2.rejected_at_ingest.get(&RejectReason::Stale);
    assert_eq!(
        skewed,
        sent(17),
        "every observation of 17 rejected as ClockSkew"
    );
    assert_eq!(stale, sent(15), "every observation of 15 rejected as Stale");
    assert_eq!(
        count(&m2, 17, RejectReason::ClockSkew),
        sent(17),
        "reported in the maps"
    );
    assert_eq!(
        count(&m2, 15, RejectReason::Stale),
        sent(15),
        "reported in the maps"
    );
    // 10 still sees 15; the map keeps 10 and 15, and its error bound.
    let last = m2.last().unwrap();
    assert_eq!(state_of(last, 15), Some(VehicleState::Live));
    let (pos2, _) = check_errors(last, &truth, &bound, "skew beyond bounds");
    eprintln!(
        "FAULTS clock skew: +0.2 s and -1.2 s tolerated (0 rejected, error {:.3} m / {:.2}°); +0.6 s: {}/{} rejected \
         ClockSkew; -2.5 s: {}/{} rejected Stale; map error {:.3} m",
        pos1, ang1, skewed, sent(17), stale, sent(15), pos2
    );
}
