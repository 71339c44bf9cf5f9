//! Real hosts: the vehicles (simulator + three `shoal node`s) in one network
//! namespace with their own Zenoh router, the ground station (`shoal fusion`
//! and `shoal record`) in another with its own router, and the only path
//! between them a `shoal relay` process in the root namespace. Every part is
//! its own process. Then, mid-run: kill -9 and restart a node, the fusion
//! service and the recorder, and cut and heal the link.
//!
//! Needs root (or CAP_NET_ADMIN) for `ip netns`; where namespaces cannot be
//! created the test prints `SKIPPED: …` and passes. Bounded: every wait
//! fails with a message at its deadline.

#[path = "common/faults.rs"]
mod common;
#[path = "common/netns.rs"]
mod netns;

use common::*;
use netns::{Procs, TwoNamespaces};
use shoal_bus::{Bus, Connect, Subscription};
use shoal_proto::config::Fleet;
use shoal_proto::messages::{FleetMap, SimTruth, VehicleState, VehicleTruth};
use std::collections::BTreeMap;
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

/// Map error bound with the image pipeline (rendered frames, HOIRM,
/// detection, PnP) for every vehicle with a pose in a map, whatever the
/// fault: the last pose of a Stale vehicle must stay right too.
const MAX_POSITION_ERROR_M: f64 = 0.15;
const MAX_ANGLE_ERROR_DEG: f64 = 5.0;
/// A vehicle localized through one flip-ambiguous track could be put on the
/// planar-flip twin (≈ 1.7 m / 56° off, turned about the vertical) for up to
/// 2.2 s: 1 run in ~15 before fusion checked the vehicles' compass headings
/// (issue #21). Since: 11 runs, 10 with no map over the bound and one with 4
/// of 176 on-vehicle maps in a single 0.2 s run (a misread that passed every
/// gate). So at most this share of maps over the bound (was 10 %) ...
const MAX_SHARE_OVER_BOUND: f64 = 0.05;
/// ... and no excursion longer than this (map time; was 2 s): a twin held
/// for seconds fails, a lone bad solve does not.
const MAX_EXCURSION_NS: u64 = 600_000_000;
/// Maps per second of `shoal fusion` (its default).
const MAP_PERIOD_NS: u64 = 200_000_000;

/// The paper fleet with side cameras only (the ones that see neighbours in
/// line abreast): the simulator renders 6 cameras instead of 15, which is
/// what two shared cores can render and detect at 1 Hz.
fn side_camera_fleet(dir: &Path) -> std::path::PathBuf {
    let text = std::fs::read_to_string(fleet_path()).unwrap();
    let kept: Vec<&str> = text
        .split("\n\n")
        .filter(|block| {
            !(block.trim_start().starts_with("[[rigs.")
                && ["\"forward\"", "\"up\"", "\"down\""]
                    .iter()
                    .any(|n| block.contains(&format!("name = {n}"))))
        })
        .collect();
    let path = dir.join("side-cameras.toml");
    std::fs::write(&path, kept.join("\n\n")).unwrap();
    let fleet = Fleet::load(&path).expect("derived fleet");
    assert!(fleet.vehicles.iter().all(|v| v
        .cameras
        .iter()
        .map(|c| c.name.as_str())
        .eq(["port", "starboard"])));
    path
}

/// What the ground station sees, from the root namespace.
struct Monitor {
    maps: Subscription<FleetMap>,
    truth: Subscription<SimTruth>,
    truths: BTreeMap<u64, Vec<VehicleTruth>>,
    last: Option<FleetMap>,
    received: u64,
    /// Worst position (m) and angle (°) error per phase.
    worst: BTreeMap<&'static str, (f64, f64, u64)>,
    /// The worst map error seen, described.
    worst_map: (f64, String),
    /// Maps with a vehicle over the bound.
    over: u64,
    /// The current run of such maps (first and last stamp), and the longest.
    excursion: Option<(u64, u64)>,
    longest_excursion_ns: u64,
    phase: &'static str,
}

impl Monitor {
    fn poll(&mut self, wait: Duration) {
        for t in self.truth.drain() {
            self.truths.insert(t.msg.stamp_ns, t.msg.vehicles);
        }
        if let Some(r) = self.maps.recv_timeout(wait) {
            let mut all = vec![r];
            all.extend(self.maps.drain());
            for r in all {
                self.received += 1;
                let m = r.msg;
                let truth = self.truths.range(..=m.stamp_ns).next_back().map(|(_, t)| t);
                if let Some(truth) = truth {
                    let w = self.worst.entry(self.phase).or_insert((0.0, 0.0, 0));
                    w.2 += 1;
                    let errors = map_errors(&m, truth);
                    let bad = errors.iter().any(|e| {
                        e.position_m >= MAX_POSITION_ERROR_M || e.angle_deg >= MAX_ANGLE_ERROR_DEG
                    });
                    if bad {
                        self.over += 1;
                        let (first, _) = self.excursion.unwrap_or((m.stamp_ns, m.stamp_ns));
                        self.excursion = Some((first, m.stamp_ns));
                        self.longest_excursion_ns = self
                            .longest_excursion_ns
                            .max(m.stamp_ns.saturating_sub(first) + MAP_PERIOD_NS);
                    } else {
                        self.excursion = None;
                    }
                    for e in errors {
                        w.0 = w.0.max(e.position_m);
                        w.1 = w.1.max(e.angle_deg);
                        if e.position_m > self.worst_map.0 {
                            let verdicts: Vec<_> = m
                                .edges
                                .iter()
                                .map(|x| (x.observer, x.target_marker, x.rejected.clone()))
                                .collect();
                            self.worst_map = (
                                e.position_m,
                                format!(
                                    "[{}] map {} seq {} stamp {}: vehicle {} {:?} off {:.3} m / {:.2}°; edges {verdicts:?}",
                                    self.phase, m.producer, m.seq, m.stamp_ns, e.vehicle, e.state, e.position_m, e.angle_deg
                                ),
                            );
                        }
                    }
                }
                self.last = Some(m);
            }
        }
    }

    /// Wait until a map satisfies `pred`; the time it took.
    fn wait(
        &mut self,
        timeout: Duration,
        what: &str,
        pred: impl Fn(&FleetMap) -> bool,
    ) -> Duration {
        let t0 = Instant::now();
        while t0.elapsed() < timeout {
            self.poll(Duration::from_millis(200));
            if self.last.as_ref().is_some_and(&pred) {
                return t0.elapsed();
            }
        }
        panic!(
            "timed out after {timeout:?} waiting for {what}; last map: {:?}",
            self.last.as_ref().map(|m| m
                .vehicles
                .iter()
                .map(|e| (e.vehicle, e.state))
                .collect::<Vec<_>>())
        );
    }

    /// Keep the subscription drained for `d`.
    fn idle(&mut self, d: Duration) {
        let t0 = Instant::now();
        while t0.elapsed() < d {
            self.poll(Duration::from_millis(100));
        }
    }
}

fn wait_listening(addr: SocketAddr, timeout: Duration) {
    let ok = wait_for(timeout, || {
        TcpStream::connect_timeout(&addr, Duration::from_millis(200)).ok()
    });
    assert!(ok.is_some(), "nothing listens on {addr} after {timeout:?}");
}

fn shoal(args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_shoal"))
        .args(args)
        .output()
        .expect("run shoal");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

#[test]
#[allow(
    clippy::too_many_lines,
    reason = "one end-to-end scenario across two network namespaces: setup, then five numbered phases (kills, restarts, a cut link), each on the processes the previous phase left running"
)]
fn separate_processes_in_namespaces_survive_kills_restarts_and_a_cut_link() {
    let ns = match TwoNamespaces::create() {
        Ok(ns) => ns,
        Err(e) => {
            eprintln!("SKIPPED: network namespaces cannot be created here ({e}); run as root with `ip netns` to test real hosts");
            return;
        }
    };
    let dir = scratch("faults-netns");
    let fleet_file = side_camera_fleet(&dir);
    let fleet_arg = fleet_file.to_str().unwrap().to_string();
    let fleet = Fleet::load(&fleet_file).unwrap();
    let keys = fleet.keys();
    let ids: Vec<u32> = fleet.vehicles.iter().map(|v| v.id).collect();
    let (a, b) = (ns.a.clone(), ns.b.clone());
    let relay_port = shoal_bus::free_port().unwrap();
    let relay_addr = format!("{}:{relay_port}", a.gateway);
    let router_b = write_router_config(&dir.join("router-b.json5"), &["0.0.0.0:7447".into()], &[]);
    let router_a = write_router_config(
        &dir.join("router-a.json5"),
        &["0.0.0.0:7447".into()],
        std::slice::from_ref(&relay_addr),
    );
    let client = write_client_config(&dir.join("client.json5"), "127.0.0.1:7447");
    let monitor_cfg = write_client_config(&dir.join("monitor.json5"), &format!("{}:7447", b.addr));
    let cfg = |p: &Path| p.to_str().unwrap().to_string();
    let (router_a, router_b, client) = (cfg(&router_a), cfg(&router_b), cfg(&client));
    let mut procs = Procs::new(&dir);
    let t_setup = Instant::now();

    // Ground station side.
    procs.spawn(
        "router-b",
        Some(&b.name),
        &["router", "--zenoh-config", &router_b],
    );
    wait_listening(
        SocketAddr::new(b.addr.into(), 7447),
        Duration::from_secs(20),
    );
    let fusion_args = [
        "fusion",
        "--fleet",
        &fleet_arg,
        "--clock",
        "sim",
        "--zenoh-config",
        &client,
    ];
    procs.spawn("fusion", Some(&b.name), &fusion_args);
    let rec = |n: u32| {
        dir.join(format!("trial-{n}.mcap"))
            .to_str()
            .unwrap()
            .to_string()
    };
    let (rec1, rec2) = (rec(1), rec(2));
    let record_args = |out: &str| -> Vec<String> {
        [
            "record",
            "--fleet",
            &fleet_arg,
            "--out",
            out,
            "--flush-ms",
            "200",
            "--zenoh-config",
            &client,
        ]
        .iter()
        .map(|s| s.to_string())
        .collect()
    };
    procs.spawn("recorder", Some(&b.name), &record_args(&rec1));
    // The link.
    let to = format!("{}:7447", b.addr);
    procs.spawn(
        "relay",
        None,
        // The link itself is poor throughout: 50 ms + 0–50 ms each way, and
        // 2% of chunks stalled 200 ms (lost TCP segments).
        &[
            "relay",
            "--listen",
            &relay_addr,
            "--to",
            &to,
            "--delay-ms",
            "50",
            "--jitter-ms",
            "50",
            "--loss",
            "0.02",
            "--stall-ms",
            "200",
        ],
    );
    wait_listening(relay_addr.parse().unwrap(), Duration::from_secs(20));
    // Vehicle side.
    procs.spawn(
        "router-a",
        Some(&a.name),
        &["router", "--zenoh-config", &router_a],
    );
    wait_listening(
        SocketAddr::new(a.addr.into(), 7447),
        Duration::from_secs(20),
    );
    // Decentralized fusion on vehicle 10, on the vehicles' side.
    let on_vehicle_args = [
        "fusion",
        "--fleet",
        &fleet_arg,
        "--on-vehicle",
        "10",
        "--clock",
        "sim",
        "--zenoh-config",
        &client,
    ];
    procs.spawn("fusion-v10", Some(&a.name), &on_vehicle_args);
    let node_args = |v: u32| -> Vec<String> {
        let v = v.to_string();
        [
            "node",
            "--fleet",
            &fleet_arg,
            "--vehicle",
            &v,
            "--water",
            "0.5",
            "--zenoh-config",
            &client,
        ]
        .iter()
        .map(|s| s.to_string())
        .collect()
    };
    for &v in &ids {
        procs.spawn(&format!("node{v}"), Some(&a.name), &node_args(v));
    }
    // At 5 ticks/s: `shoal fusion --clock sim` takes its time from the
    // simulator's truth messages, which the simulator publishes *after*
    // rendering a tick's frames; an observation of an early-rendered frame
    // can reach fusion before its tick's truth, one tick ahead of fusion's
    // clock, and must still be within `max_clock_skew_s` (0.25 s) of it.
    // (The simulator skips rendering, not time, when it falls behind, so
    // this costs no more rendering than the cores can give.)
    procs.spawn(
        "sim",
        Some(&a.name),
        &[
            "sim",
            "--fleet",
            &fleet_arg,
            "--rate",
            "5",
            "--zenoh-config",
            &client,
        ],
    );

    let bus = Bus::open(&Connect::File(monitor_cfg)).unwrap();
    let mut mon = Monitor {
        maps: bus.subscribe(&keys.map(), 1024).unwrap(),
        truth: bus.subscribe(&keys.truth(), 1024).unwrap(),
        truths: BTreeMap::new(),
        last: None,
        received: 0,
        worst: BTreeMap::new(),
        worst_map: (0.0, String::new()),
        over: 0,
        excursion: None,
        longest_excursion_ns: 0,
        phase: "start",
    };
    // The vehicles' side, watched directly (the root namespace reaches both sides).
    let monitor_a = write_client_config(&dir.join("monitor-a.json5"), &format!("{}:7447", a.addr));
    let bus_a = Bus::open(&Connect::File(monitor_a)).unwrap();
    let mut mon_a = Monitor {
        maps: bus_a.subscribe(&keys.map_of("10"), 4096).unwrap(),
        truth: bus_a.subscribe(&keys.truth(), 4096).unwrap(),
        truths: BTreeMap::new(),
        last: None,
        received: 0,
        worst: BTreeMap::new(),
        worst_map: (0.0, String::new()),
        over: 0,
        excursion: None,
        longest_excursion_ns: 0,
        phase: "on-vehicle start",
    };
    let live = |v: u32| move |m: &FleetMap| state_of(m, v) == Some(VehicleState::Live);
    let first_live = mon.wait(Duration::from_secs(120), "every vehicle Live", all_live);
    let first_live = t_setup.elapsed().max(first_live);
    mon.phase = "steady";
    mon.idle(Duration::from_secs(6));

    // 1. Kill -9 a node; the others keep going; it restarts and rejoins.
    mon.phase = "node killed";
    procs.kill("node15");
    let node_stale = mon.wait(Duration::from_secs(20), "vehicle 15 Stale", |m| {
        state_of(m, 15) == Some(VehicleState::Stale)
    });
    // The rest keeps going: maps keep coming with the reference Live, fused
    // from the other nodes' observations taken after the kill.
    let killed_at = mon.last.as_ref().map_or(0, |m| m.stamp_ns);
    mon.wait(
        Duration::from_secs(20),
        "maps judging 10's and 17's new observations",
        |m| {
            let observers: std::collections::BTreeSet<u32> = m
                .edges
                .iter()
                .filter(|e| e.stamp_ns > killed_at)
                .map(|e| e.observer)
                .collect();
            live(10)(m) && !observers.contains(&15) && !observers.is_empty()
        },
    );
    let verdicts: Vec<(u32, Option<shoal_proto::messages::RejectReason>)> = mon
        .last
        .as_ref()
        .map(|m| {
            m.edges
                .iter()
                .filter(|e| e.stamp_ns > killed_at)
                .map(|e| (e.observer, e.rejected.clone()))
                .collect()
        })
        .unwrap_or_default();
    eprintln!(
        "FAULTS netns: verdicts on the other nodes' observations with node 15 dead: {verdicts:?}"
    );
    mon.idle(Duration::from_secs(2));
    let started = Instant::now();
    procs.spawn("node15", Some(&a.name), &node_args(15));
    mon.phase = "node restarted";
    mon.wait(Duration::from_secs(60), "vehicle 15 Live again", all_live);
    let node_rejoin = started.elapsed();
    mon.idle(Duration::from_secs(3));

    // 2. Kill -9 the fusion service: no maps, and nothing to answer a late
    // joiner; restarted, it rebuilds the map from the observations that
    // keep flowing, and a late joiner's query gets it at once.
    mon.phase = "fusion killed";
    procs.kill("fusion");
    mon.idle(Duration::from_millis(500));
    let before = mon.received;
    mon.idle(Duration::from_secs(2));
    assert_eq!(mon.received, before, "maps published with fusion dead");
    assert!(
        bus.query_latest::<FleetMap>(&keys.map(), Duration::from_millis(500))
            .unwrap()
            .is_none(),
        "a map served with fusion dead"
    );
    mon.last = None;
    procs.spawn("fusion", Some(&b.name), &fusion_args);
    mon.phase = "fusion restarted";
    let fusion_first_map = mon.wait(
        Duration::from_secs(30),
        "a map from the restarted fusion",
        |_| true,
    );
    let fusion_recovered = fusion_first_map
        + mon.wait(
            Duration::from_secs(60),
            "all Live after fusion restart",
            all_live,
        );
    let late = Bus::open(&Connect::File(dir.join("monitor.json5"))).unwrap();
    let t_query = Instant::now();
    let caught_up = late
        .query_latest::<FleetMap>(&keys.map(), Duration::from_secs(2))
        .unwrap()
        .expect("a late joiner's query got no map");
    let query_time = t_query.elapsed();
    assert_eq!(caught_up.producer, "central");
    assert!(procs.running("recorder"), "the recorder died with fusion");
    mon.idle(Duration::from_secs(3));

    // 3. Kill -9 the recorder: its file is readable and recoverable; a new one starts.
    mon.phase = "recorder killed";
    procs.kill("recorder");
    let (ok, info1) = shoal(&["log", "info", &rec1]);
    assert!(
        ok && info1.contains("INCOMPLETE"),
        "log info on the killed recording:\n{info1}"
    );
    let fixed = dir
        .join("trial-1-recovered.mcap")
        .to_str()
        .unwrap()
        .to_string();
    let (ok, out) = shoal(&["log", "recover", &rec1, "--out", &fixed]);
    assert!(ok, "log recover:\n{out}");
    let (ok, info_fixed) = shoal(&["log", "info", &fixed]);
    assert!(ok && !info_fixed.contains("INCOMPLETE"), "{info_fixed}");
    let killed_wire = shoal_record::info(Path::new(&fixed)).unwrap();
    procs.spawn("recorder", Some(&b.name), &record_args(&rec2));
    mon.idle(Duration::from_secs(2));

    // 4. Cut the link between the sides, then heal it. The vehicles' side
    // keeps its own full map (decentralized fusion on vehicle 10); the
    // ground station keeps the last poses, Stale.
    // Every vehicle localized on the vehicles' side first. Not one poll: on
    // a loaded machine a single map may miss a vehicle for a moment (seen
    // once in CI: 15 and 17 carried as Predicted for one map while another
    // run's builds held the cores).
    mon_a.wait(
        Duration::from_secs(10),
        "every vehicle Live on the vehicles' side before the cut",
        all_live,
    );
    mon_a.phase = "on-vehicle, link cut";
    mon.phase = "link cut";
    procs.signal("relay", "USR1");
    let cut_stale = mon.wait(
        Duration::from_secs(20),
        "every vehicle Stale across the cut",
        |m| m.vehicles.iter().all(|e| e.state == VehicleState::Stale),
    );
    let before = mon.received;
    mon.idle(Duration::from_secs(4));
    assert!(
        mon.received > before + 10,
        "the ground station stopped publishing maps while cut off"
    );
    let before_a = mon_a.received;
    mon_a.poll(Duration::from_millis(200));
    let on_vehicle_during_cut = mon_a.received - before_a;
    assert!(
        on_vehicle_during_cut > 10,
        "the on-vehicle map stopped during the cut"
    );
    assert!(
        mon_a.last.as_ref().is_some_and(all_live),
        "the vehicles' side lost its map during the cut: {:?}",
        mon_a.last.as_ref().map(|m| &m.vehicles)
    );
    procs.signal("relay", "USR2");
    mon_a.phase = "on-vehicle, link healed";
    mon.phase = "link healed";
    let healed = mon.wait(Duration::from_secs(60), "all Live after the heal", all_live);
    mon.idle(Duration::from_secs(4));
    // One map again: the ground station's and vehicle 10's agree.
    mon_a.poll(Duration::from_millis(200));
    let apart = disagreement_m(mon.last.as_ref().unwrap(), mon_a.last.as_ref().unwrap());
    assert!(
        apart < 0.05,
        "central and on-vehicle maps {apart:.3} m apart after the heal"
    );

    // 5. Stop the second recording cleanly: complete, nothing dropped.
    procs.signal("recorder", "INT");
    let status = procs
        .wait_exit("recorder", Duration::from_secs(20))
        .expect("recorder did not stop on SIGINT");
    assert!(status.success());
    let rec_out = procs.log("recorder");
    assert!(
        rec_out.contains(" 0 dropped"),
        "recorder dropped messages:\n{rec_out}"
    );
    let (ok, info2) = shoal(&["log", "info", &rec2]);
    assert!(
        ok && info2.contains("complete") && !info2.contains("INCOMPLETE"),
        "{info2}"
    );
    assert!(info2.contains("/obs") && info2.contains("/map"), "{info2}");
    for name in [
        "router-a",
        "router-b",
        "relay",
        "sim",
        "fusion",
        "fusion-v10",
        "node10",
        "node15",
        "node17",
    ] {
        assert!(procs.running(name), "{name} exited: {}", procs.log(name));
    }

    eprintln!(
        "FAULTS netns: all Live {:.1} s after start; node 15 killed: Stale after {:.1} s, rejoined {:.1} s after restart; \
         fusion killed: restarted fusion's first map after {:.1} s, all Live after {:.1} s, late joiner's query answered in {:.2} s; \
         recorder killed: file readable ({} messages recovered); link cut: all Stale after {:.1} s, all Live {:.1} s after the heal; \
         maps received {}",
        first_live.as_secs_f64(),
        node_stale.as_secs_f64(),
        node_rejoin.as_secs_f64(),
        fusion_first_map.as_secs_f64(),
        fusion_recovered.as_secs_f64(),
        query_time.as_secs_f64(),
        killed_wire.messages,
        cut_stale.as_secs_f64(),
        healed.as_secs_f64(),
        mon.received
    );
    eprintln!(
        "FAULTS netns: on-vehicle map (fusion on 10, vehicles' side) during the cut: {on_vehicle_during_cut} maps, all Live; \
         4 s after the heal, central and on-vehicle maps {apart:.3} m apart"
    );
    eprintln!("FAULTS netns worst central map: {}", mon.worst_map.1);
    eprintln!("FAULTS netns worst on-vehicle map: {}", mon_a.worst_map.1);
    for (phase, (pos, ang, n)) in mon.worst.iter().chain(&mon_a.worst) {
        eprintln!("FAULTS netns error [{phase}]: {n} maps, worst {pos:.3} m / {ang:.2}°");
    }
    for (name, m) in [("central", &mon), ("on-vehicle", &mon_a)] {
        let n: u64 = m.worst.values().map(|w| w.2).sum();
        eprintln!(
            "FAULTS netns {name}: {} of {n} maps over {MAX_POSITION_ERROR_M} m / {MAX_ANGLE_ERROR_DEG}°, longest run {:.1} s",
            m.over,
            m.longest_excursion_ns as f64 * 1e-9
        );
        assert!(n > 0);
        assert!(
            m.over as f64 <= MAX_SHARE_OVER_BOUND * n as f64,
            "{name}: {} of {n} maps over the bound; worst {}",
            m.over,
            m.worst_map.1
        );
        assert!(
            m.longest_excursion_ns <= MAX_EXCURSION_NS,
            "{name}: over the bound for {:.1} s; worst {}",
            m.longest_excursion_ns as f64 * 1e-9,
            m.worst_map.1
        );
    }
    drop(procs);
    drop(ns);
}
