//! Issue #22, the services across an acoustic-rate link: each of the paper's
//! three vehicles runs `shoal link` (its observations as compact packets at
//! 1 000 bit/s, 8 bytes of modem framing per packet) and its own fusion with
//! `--link` (its own observations in full, the others' packets); a central
//! fusion fed every full observation is the full-rate reference. Holding
//! station in line abreast, observations synthesized at 2 Hz per camera.
//!
//! In this geometry only 10 and 17 see a neighbour (each sees 15), so a
//! vehicle's map holds the third pair only through the link. Every map must
//! hold every pair within 5 cm of the full-rate map, and no sender may exceed
//! its modem's rate. Every vehicle also publishes its own nav (10 Hz, the
//! simulated sensors): each sender must send it as navigation spans at its
//! period, and every fusion on the link must take the other vehicles' spans.

#[path = "common/fusion_rig.rs"]
mod fusion_rig;

use fusion_rig::Rig;
use shoal_fusion::FusionParams;
use shoal_proto::compact::LinkPacket;
use shoal_proto::config::Fleet;
use shoal_proto::messages::{FleetMap, VehicleState};
use shoal_proto::{Pose, VehicleId};
use shoal_services::fusion::{FusionConfig, FusionHandle, Placement};
use shoal_services::link::{LinkConfig, LinkHandle};
use shoal_sim_bridge::obs_synth::{line_abreast, ObsSynth, ObsSynthParams};
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

const RATE_BPS: f64 = 1000.0;
const STEP_NS: u64 = 100_000_000;
/// Simulated time runs this many times faster than the wall clock.
const SPEED_UP: u64 = 4;
const WARMUP_S: u64 = 20;
const DURATION_S: u64 = 50;
/// The bound on a decentralized map against the full-rate one.
const MAX_DIFFERENCE_M: f64 = 0.05;

fn live_poses(map: &FleetMap) -> BTreeMap<VehicleId, Pose> {
    map.vehicles
        .iter()
        .filter(|v| v.state == VehicleState::Live)
        .map(|v| (v.vehicle, v.reference_from_vehicle))
        .collect()
}

/// Pair differences of the decentralized maps against the full-rate one.
#[derive(Default)]
struct Tally {
    diffs: Vec<f64>,
    slots: usize,
    missing: usize,
}

impl Tally {
    fn compare(
        &mut self,
        reference: &BTreeMap<VehicleId, Pose>,
        mine: &BTreeMap<VehicleId, Pose>,
        ids: &[VehicleId],
    ) {
        for (k, i) in ids.iter().enumerate() {
            for j in &ids[k + 1..] {
                let (Some(fi), Some(fj)) = (reference.get(i), reference.get(j)) else {
                    continue;
                };
                self.slots += 1;
                let (Some(li), Some(lj)) = (mine.get(i), mine.get(j)) else {
                    self.missing += 1;
                    continue;
                };
                let d =
                    (li.inverse() * lj).translation.vector - (fi.inverse() * fj).translation.vector;
                self.diffs.push(d.norm());
            }
        }
    }
}

fn link_fusion(rig: &Rig, placement: Placement) -> FusionHandle {
    shoal_services::fusion::spawn(
        &rig.session(),
        FusionConfig {
            fleet: rig.fleet.clone(),
            params: FusionParams::default(),
            placement,
            rate_hz: 10.0,
            queue_capacity: 4096,
            link: true,
        },
        rig.clock.clone(),
    )
    .expect("link fusion starts")
}

fn link_sender(rig: &Rig, vehicle: VehicleId) -> LinkHandle {
    shoal_services::link::spawn(
        &rig.session(),
        LinkConfig {
            fleet: rig.fleet.clone(),
            vehicle,
            rate_bps: RATE_BPS,
            overhead_bytes: shoal_fusion::link::MODEM_OVERHEAD_BYTES,
            queue_capacity: 1024,
            nav_period_ns: None,
        },
        rig.clock.clone(),
    )
    .expect("link sender starts")
}

/// Every sender sent what it was offered, within its modem's rate.
fn check_senders(
    senders: &[LinkHandle],
    ids: &[VehicleId],
    published: &BTreeMap<VehicleId, u64>,
    sim_s: f64,
) {
    for (s, v) in senders.iter().zip(ids) {
        let st = s.stats();
        eprintln!(
            "LINK vehicle {v}: {} packets ({} navigation spans), {} modem bytes ({:.0} bit/s), {} offered, {} folded, {} expired, {} dropped",
            st.packets,
            st.nav_spans,
            st.modem_bytes,
            st.modem_bytes as f64 * 8.0 / sim_s,
            st.queue.offered,
            st.queue.superseded,
            st.queue.expired,
            st.dropped
        );
        let offered = published.get(v).copied().unwrap_or(0);
        assert_eq!(st.queue.offered + st.dropped, offered, "vehicle {v}");
        if offered > 0 {
            assert!(st.packets > 20, "vehicle {v} sent {} packets", st.packets);
        }
        // One packet may be on the air when the run ends.
        assert!(
            st.modem_bytes as f64 * 8.0 <= RATE_BPS * sim_s + 8.0 * 80.0,
            "vehicle {v} sent {} bytes in {sim_s} s at {RATE_BPS} bit/s",
            st.modem_bytes
        );
        assert_eq!(st.unencodable + st.wrong_observer, 0);
    }
}

/// Every sender sent its vehicle's nav as spans at its period, and every
/// fusion on the link took the other vehicles' spans.
fn check_nav(
    senders: &[LinkHandle],
    ids: &[VehicleId],
    local: &[(String, FusionHandle)],
    sim_s: f64,
) {
    let period_s =
        shoal_fusion::link::nav_span_period_ns(RATE_BPS, shoal_fusion::link::MODEM_OVERHEAD_BYTES)
            as f64
            * 1e-9;
    for (s, v) in senders.iter().zip(ids) {
        let st = s.stats();
        // One span a period, but for the first and one on the air at the end.
        let want = (sim_s / period_s).floor() as u64 - 2;
        assert!(
            st.nav_spans >= want && st.nav_spans <= want + 3,
            "vehicle {v}: {} navigation spans in {sim_s} s, every {period_s:.2} s",
            st.nav_spans
        );
        assert_eq!(st.nav_refused, 0, "vehicle {v}");
    }
    for (name, f) in local {
        assert_eq!(f.observations_rejected(), 0, "{name} refused packets");
        let st = f.stats();
        // The others' spans (two or three vehicles', at least ~20 each), and
        // on a vehicle its own nav in full (500 samples).
        let others = if name.starts_with("on") { 2 } else { 3 };
        assert!(
            st.nav_ingested >= others * 20 && st.nav_rejected == 0,
            "{name}: {} nav states and spans taken, {} refused",
            st.nav_ingested,
            st.nav_rejected
        );
    }
}

#[test]
fn decentralized_maps_over_a_1000_bit_link_stay_within_5_cm_of_the_full_rate_map() {
    let fleet = Arc::new(
        Fleet::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/fleets/paper.toml"))
            .expect("paper fleet"),
    );
    let ids: Vec<VehicleId> = fleet.vehicles.iter().map(|v| v.id).collect();
    let rig = Rig::new(fleet.clone());
    let full = rig.fusion(Placement::Central, FusionParams::default(), 4096);
    let mut local: Vec<(String, FusionHandle)> = ids
        .iter()
        .map(|&v| {
            (
                format!("on {v}"),
                link_fusion(&rig, Placement::OnVehicle(v)),
            )
        })
        .collect();
    local.push((
        "ground station".into(),
        link_fusion(&rig, Placement::Central),
    ));
    let senders: Vec<LinkHandle> = ids.iter().map(|&v| link_sender(&rig, v)).collect();
    let bus = rig.session();
    let publishers = rig.observation_publishers(&bus);
    let keys = fleet.keys();
    let nav_publishers: Vec<shoal_bus::Publisher<shoal_proto::NavState>> = ids
        .iter()
        .map(|&v| bus.publisher(keys.nav(v)).expect("nav publisher"))
        .collect();
    let mut sensors = shoal_sim_bridge::nav::NavSensors::new(
        shoal_sim_bridge::nav::NavSensorParams::default(),
        7,
    )
    .expect("nav sensors");
    // Let the subscriptions reach the router before anything is published.
    std::thread::sleep(Duration::from_millis(500));

    let truth = line_abreast(&ids, 1.75);
    let mut synth = ObsSynth::new(&fleet, ObsSynthParams::default(), 7);
    let mut tally = Tally::default();
    let started = Instant::now();
    let mut now = 0u64;
    let mut published = BTreeMap::new();
    while now < DURATION_S * 1_000_000_000 {
        now += STEP_NS;
        rig.clock.advance_to(now);
        for (t, p) in truth.iter().zip(&nav_publishers) {
            p.put(&sensors.measure(t, now)).expect("publish nav");
        }
        if now.is_multiple_of(500_000_000) {
            for s in synth.observe(&truth, now) {
                if let Some(p) = publishers.get(&s.obs.observer) {
                    p.put(&s.obs).expect("publish observation");
                    *published.entry(s.obs.observer).or_insert(0u64) += 1;
                }
            }
        }
        if now >= WARMUP_S * 1_000_000_000 && now.is_multiple_of(1_000_000_000) {
            let reference = full.latest().map(|m| live_poses(&m)).unwrap_or_default();
            for (_, f) in &local {
                let mine = f.latest().map(|m| live_poses(&m)).unwrap_or_default();
                tally.compare(&reference, &mine, &ids);
            }
        }
        let due = started + Duration::from_nanos(now / SPEED_UP);
        std::thread::sleep(due.saturating_duration_since(Instant::now()));
    }

    let sim_s = DURATION_S as f64;
    // The last observations may still be on their way to the senders.
    let deadline = Instant::now() + Duration::from_secs(5);
    while Instant::now() < deadline
        && senders.iter().zip(&ids).any(|(s, v)| {
            let st = s.stats();
            st.queue.offered + st.dropped < published.get(v).copied().unwrap_or(0)
        })
    {
        std::thread::sleep(Duration::from_millis(20));
    }
    eprintln!("LINK observations published per vehicle: {published:?}");
    check_senders(&senders, &ids, &published, sim_s);
    check_nav(&senders, &ids, &local, sim_s);
    let Tally {
        mut diffs,
        slots,
        missing,
    } = tally;
    let worst = diffs.iter().copied().fold(0.0f64, f64::max);
    diffs.sort_by(f64::total_cmp);
    let p95 = diffs
        .get(diffs.len() * 95 / 100)
        .copied()
        .unwrap_or(f64::NAN);
    eprintln!(
        "LINK {} comparisons, {missing} of {slots} pairs unknown; difference p95 {:.2} cm, max {:.2} cm (wall {:.1} s)",
        diffs.len(),
        p95 * 100.0,
        worst * 100.0,
        started.elapsed().as_secs_f64()
    );
    assert!(slots >= 4 * 3 * 20, "only {slots} pair slots compared");
    assert!(
        missing * 20 <= slots,
        "{missing} of {slots} pairs unknown to a decentralized map"
    );
    assert!(
        worst <= MAX_DIFFERENCE_M,
        "decentralized map {:.1} cm from the full-rate map",
        worst * 100.0
    );
    for s in senders {
        s.stop();
    }
    for (_, f) in local {
        f.stop();
    }
    full.stop();
}

#[test]
fn packets_on_another_vehicles_key_or_that_do_not_decode_are_refused_and_counted() {
    let fleet = Arc::new(
        Fleet::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/fleets/paper.toml"))
            .expect("paper fleet"),
    );
    let rig = Rig::new(fleet.clone());
    let fusion = link_fusion(&rig, Placement::Central);
    let bus = rig.session();
    let keys = fleet.keys();
    let on_10: shoal_bus::Publisher<LinkPacket> = bus.publisher(keys.link(10)).unwrap();
    std::thread::sleep(Duration::from_millis(500));
    let mut obs = shoal_proto::samples::observation();
    obs.observer = 17;
    obs.target_marker = 15;
    let good = LinkPacket {
        sender: 17,
        seq: 0,
        payload: shoal_proto::compact::encode(&obs).unwrap(),
    };
    // 17's packet on 10's key.
    on_10.put(&good).unwrap();
    // Bytes that are no compact observation (the envelope itself is valid).
    let mut garbage = good.clone();
    garbage.sender = 10;
    garbage.payload.truncate(20);
    on_10
        .put_bytes(shoal_proto::encode(&garbage).unwrap())
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(5);
    while fusion.observations_rejected() < 2 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(20));
    }
    assert_eq!(fusion.observations_rejected(), 2);
    std::thread::sleep(Duration::from_millis(300));
    let map = fusion.latest().expect("a map");
    assert!(map.edges.is_empty(), "{:?}", map.edges);
    fusion.stop();
}
