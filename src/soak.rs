//! `shoal soak`: the simulated swarm for a long time (an hour by default)
//! with faults on a schedule, watching for leaks and lost maps (issue #22).
//!
//! The paper's three vehicles publish synthesized observations (observation
//! mode: `obs_synth`, no rendering) on their side of a link; fusion and a
//! ground station listen on the other side, behind a relay
//! ([`shoal_services::relay`]). Every cycle (`every_s`, default 60 s):
//!
//! 1. at ¼: the link is cut for `partition_s` (default 5 s), then healed;
//! 2. at ½: the fusion service is killed and started again;
//! 3. at ¾: one vehicle's session is closed for 2 s and reopened (each cycle
//!    the next vehicle).
//!
//! Every 10 s the process's resident memory and open file descriptors are
//! sampled. The report says, per event, how long until the ground station
//! again had a map with every vehicle Live; the longest gap between maps;
//! and whether memory and descriptors stayed flat (the last fifth of the
//! samples against the first fifth after the first cycle). It passes when
//! every event recovered within `recover_s`, no gap between maps outside a
//! fusion restart exceeded 2 s, memory grew by less than 10 % + 16 MB and
//! descriptors by at most 4.
//!
//! Time: a manual clock advanced 100 ms per tick, a tick every 100 ms of
//! wall time (the services read the injected clock; the faults are real).

use anyhow::Context;
use shoal_bus::{client_of, free_port, Bus, Connect, Publisher, Subscription, Token};
use shoal_fusion::FusionParams;
use shoal_proto::clock::ManualClock;
use shoal_proto::config::Fleet;
use shoal_proto::messages::{FleetMap, Observation, VehicleState};
use shoal_services::fusion::{FusionConfig, FusionHandle, Placement};
use shoal_services::relay::{FaultPlan, Relay};
use shoal_sim_bridge::obs_synth::{line_abreast, ObsSynth, ObsSynthParams};
use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

const TICK: Duration = Duration::from_millis(100);
const TICK_NS: u64 = 100_000_000;
/// Line abreast this far apart: the side cameras see the neighbours' markers.
const SPACING_M: f64 = 2.5;
/// A gap between maps longer than this, outside a fusion restart, is a lost map.
const MAX_MAP_GAP_S: f64 = 2.0;
const SAMPLE_EVERY_S: f64 = 10.0;

/// What to run.
#[derive(Debug, Clone)]
pub struct SoakConfig {
    pub duration_s: f64,
    /// Length of one cycle of faults.
    pub every_s: f64,
    /// How long each partition lasts.
    pub partition_s: f64,
    /// Bound on the time from an event's end to a map with every vehicle Live.
    pub recover_s: f64,
    pub seed: u64,
}

impl Default for SoakConfig {
    fn default() -> Self {
        Self {
            duration_s: 3600.0,
            every_s: 60.0,
            partition_s: 5.0,
            recover_s: 10.0,
            seed: 7,
        }
    }
}

impl SoakConfig {
    fn check(&self) -> anyhow::Result<()> {
        let ok = |v: f64| v.is_finite() && v > 0.0;
        anyhow::ensure!(
            ok(self.duration_s) && ok(self.every_s) && ok(self.partition_s) && ok(self.recover_s),
            "soak: durations must be positive and finite ({self:?})"
        );
        anyhow::ensure!(
            self.partition_s < self.every_s / 4.0,
            "soak: a partition of {} s does not fit in a quarter of a {} s cycle",
            self.partition_s,
            self.every_s
        );
        Ok(())
    }
}

/// One scheduled fault and how the swarm came back from it.
#[derive(Debug, Clone, serde::Serialize)]
pub struct SoakEvent {
    pub at_s: f64,
    pub what: String,
    /// Seconds from the fault's end to the first map with every vehicle Live (`None`: never).
    pub recovered_after_s: Option<f64>,
}

/// One sample of the process's resources.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct SoakSample {
    pub at_s: f64,
    pub rss_kb: u64,
    pub open_fds: u64,
    pub maps_received: u64,
}

/// What a soak found.
#[derive(Debug, Clone, serde::Serialize)]
pub struct SoakReport {
    pub duration_s: f64,
    pub maps_received: u64,
    pub observations_published: u64,
    /// Longest time without a map outside fusion restarts, and when it ended (s since start).
    pub longest_map_gap_s: f64,
    pub longest_map_gap_at_s: f64,
    pub events: Vec<SoakEvent>,
    pub samples: Vec<SoakSample>,
    pub rss_growth_kb: i64,
    pub fd_growth: i64,
    pub problems: Vec<String>,
    /// Stopped early by the caller.
    pub interrupted: bool,
}

impl SoakReport {
    pub fn passed(&self) -> bool {
        self.problems.is_empty()
    }

    /// A few lines for a person.
    pub fn summary(&self) -> String {
        let recovered: Vec<f64> = self
            .events
            .iter()
            .filter_map(|e| e.recovered_after_s)
            .collect();
        let worst = recovered.iter().copied().fold(0.0, f64::max);
        let mut s = format!(
            "soak: {:.0} s{}, {} observations published, {} maps received\n\
             events: {} ({} recovered, slowest {:.1} s); longest gap between maps outside restarts {:.2} s (at {:.0} s)\n\
             memory: {} -> {} kB ({:+} kB); open files: {} -> {} ({:+})\n",
            self.duration_s,
            if self.interrupted { " (interrupted)" } else { "" },
            self.observations_published,
            self.maps_received,
            self.events.len(),
            recovered.len(),
            worst,
            self.longest_map_gap_s,
            self.longest_map_gap_at_s,
            self.samples.first().map_or(0, |x| x.rss_kb),
            self.samples.last().map_or(0, |x| x.rss_kb),
            self.rss_growth_kb,
            self.samples.first().map_or(0, |x| x.open_fds),
            self.samples.last().map_or(0, |x| x.open_fds),
            self.fd_growth,
        );
        if self.problems.is_empty() {
            s += "PASS\n";
        } else {
            for p in &self.problems {
                s += &format!("FAIL: {p}\n");
            }
        }
        s
    }
}

/// Resident memory (kB) and open descriptors of this process (Linux `/proc`; 0 elsewhere).
fn resources() -> (u64, u64) {
    let rss = std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse().ok())
        })
        .unwrap_or(0);
    let fds = std::fs::read_dir("/proc/self/fd").map_or(0, |d| d.count() as u64);
    (rss, fds)
}

/// A vehicle's session on its side of the link.
struct Vehicle {
    publisher: Publisher<Observation>,
    _token: Token,
    bus: Bus,
}

fn open_vehicle(port: u16, fleet: &Fleet, v: u32) -> anyhow::Result<Vehicle> {
    let bus = Bus::open(&client_of(port)).with_context(|| format!("vehicle {v}: session"))?;
    let keys = fleet.keys();
    Ok(Vehicle {
        publisher: bus.publisher(keys.observations(v))?,
        _token: bus.liveliness_token(keys.alive(v))?,
        bus,
    })
}

fn spawn_fusion(
    port: u16,
    fleet: &Arc<Fleet>,
    clock: &Arc<ManualClock>,
) -> anyhow::Result<(FusionHandle, Bus)> {
    let bus = Bus::open(&client_of(port)).context("fusion: session")?;
    let handle = shoal_services::fusion::spawn(
        &bus,
        FusionConfig {
            fleet: fleet.clone(),
            params: FusionParams {
                record_solve_time: false,
                ..FusionParams::default()
            },
            placement: Placement::Central,
            rate_hz: 10.0,
            queue_capacity: 10_000,
            link: false,
        },
        clock.clone(),
    )?;
    Ok((handle, bus))
}

fn all_live(map: &FleetMap, n: usize) -> bool {
    map.vehicles.len() == n && map.vehicles.iter().all(|e| e.state == VehicleState::Live)
}

/// What is in progress: the fault and when it ends (s since start).
#[derive(Debug, Clone, Copy, PartialEq)]
enum Fault {
    None,
    Partition { heal_at: f64 },
    VehicleDown { vehicle: u32, up_at: f64 },
}

/// The running swarm and its ground station.
struct Swarm {
    fleet: Arc<Fleet>,
    port_a: u16,
    port_b: u16,
    relay: Relay,
    _routers: (Bus, Bus),
    clock: Arc<ManualClock>,
    fusion: Option<(FusionHandle, Bus)>,
    vehicles: BTreeMap<u32, Vehicle>,
    maps: Subscription<FleetMap>,
    _ground: Bus,
}

impl Swarm {
    fn start(fleet: Arc<Fleet>) -> anyhow::Result<Swarm> {
        let (port_a, port_b) = (free_port()?, free_port()?);
        let router_b = Bus::open(&Connect::Router { port: port_b }).context("router B")?;
        let upstream: SocketAddr = ([127, 0, 0, 1], port_b).into();
        let relay = Relay::start("127.0.0.1:0", upstream, FaultPlan::default())?;
        let router_a = Bus::open(&Connect::RouterLinked {
            port: port_a,
            routers: vec![relay.local_addr().port()],
        })
        .context("router A")?;
        let clock = Arc::new(ManualClock::new(TICK_NS));
        let fusion = Some(spawn_fusion(port_b, &fleet, &clock)?);
        let ground = Bus::open(&client_of(port_b)).context("ground station: session")?;
        let maps = ground.subscribe::<FleetMap>(&fleet.keys().map(), 4096)?;
        let vehicles = fleet
            .vehicles
            .iter()
            .map(|v| Ok((v.id, open_vehicle(port_a, &fleet, v.id)?)))
            .collect::<anyhow::Result<_>>()?;
        Ok(Swarm {
            fleet,
            port_a,
            port_b,
            relay,
            _routers: (router_a, router_b),
            clock,
            fusion,
            vehicles,
            maps,
            _ground: ground,
        })
    }

    fn restart_fusion(&mut self) -> anyhow::Result<()> {
        if let Some((handle, bus)) = self.fusion.take() {
            handle.stop();
            bus.close();
        }
        self.fusion = Some(spawn_fusion(self.port_b, &self.fleet, &self.clock)?);
        Ok(())
    }
}

/// Run the soak; `stop` ends it early (the report says so); `progress` gets a line a minute.
#[allow(
    clippy::too_many_lines,
    reason = "one loop: tick, the schedule's faults, map bookkeeping and sampling, in the order they happen each tick"
)]
pub fn run(
    cfg: &SoakConfig,
    stop: &AtomicBool,
    mut progress: impl FnMut(&str),
) -> anyhow::Result<SoakReport> {
    cfg.check()?;
    let fleet = Arc::new(
        Fleet::parse(
            crate::demo::PAPER_FLEET,
            std::path::Path::new("configs/fleets/paper.toml"),
        )
        .context("the paper fleet")?,
    );
    let ids: Vec<u32> = fleet.vehicles.iter().map(|v| v.id).collect();
    let truth = line_abreast(&ids, SPACING_M);
    let mut synth = ObsSynth::new(&fleet, ObsSynthParams::default(), cfg.seed);
    let mut swarm = Swarm::start(fleet.clone())?;
    std::thread::sleep(Duration::from_millis(500));

    let started = Instant::now();
    let since = || started.elapsed().as_secs_f64();
    let mut tick = 1u64;
    let mut fault = Fault::None;
    let mut events: Vec<SoakEvent> = Vec::new();
    // Index of the event waiting for a map with every vehicle Live, and since when.
    let mut awaiting: Option<(usize, f64)> = None;
    let mut samples = Vec::new();
    let mut next_sample = 0.0;
    let mut next_progress = 60.0;
    let (mut maps_received, mut published) = (0u64, 0u64);
    let mut last_map_at = 0.0f64;
    let mut longest_gap = 0.0f64;
    // When the longest gap ended (s since start).
    let mut longest_gap_at = 0.0f64;
    // Until this time, a gap between maps is the fusion restart's.
    let mut restart_grace_until = 0.0f64;
    let mut next_vehicle = 0usize;
    let mut last_seq = 0u64;
    let mut new_instance_below_seq: Option<u64> = None;
    let mut done_in_cycle = [false; 3];
    let mut cycle = 0u64;
    let mut problems = Vec::new();

    while since() < cfg.duration_s && !stop.load(Ordering::Relaxed) {
        let t0 = Instant::now();
        let now = since();
        tick += 1;
        let stamp = tick * TICK_NS;
        swarm.clock.advance_to(stamp);
        for o in synth.observe(&truth, stamp) {
            if let Some(v) = swarm.vehicles.get(&o.obs.observer) {
                if v.publisher.put(&o.obs).is_ok() {
                    published += 1;
                }
            }
        }

        // The schedule.
        let c = (now / cfg.every_s).floor() as u64;
        if c != cycle {
            cycle = c;
            done_in_cycle = [false; 3];
        }
        let phase = now / cfg.every_s - c as f64;
        if phase >= 0.25 && !done_in_cycle[0] && fault == Fault::None {
            done_in_cycle[0] = true;
            swarm.relay.switch().cut();
            fault = Fault::Partition {
                heal_at: now + cfg.partition_s,
            };
            events.push(SoakEvent {
                at_s: now,
                what: format!("link cut for {} s", cfg.partition_s),
                recovered_after_s: None,
            });
        }
        if phase >= 0.5 && !done_in_cycle[1] && fault == Fault::None {
            done_in_cycle[1] = true;
            swarm.restart_fusion()?;
            // Maps of the old instance may still be on their way: only the
            // new one's (its sequence numbers start again) show recovery.
            new_instance_below_seq = Some(last_seq.max(1));
            restart_grace_until = since() + cfg.recover_s;
            events.push(SoakEvent {
                at_s: now,
                what: "fusion killed and restarted".into(),
                recovered_after_s: None,
            });
            awaiting = Some((events.len() - 1, since()));
        }
        if phase >= 0.75 && !done_in_cycle[2] && fault == Fault::None {
            done_in_cycle[2] = true;
            let v = ids[next_vehicle % ids.len()];
            next_vehicle += 1;
            if let Some(old) = swarm.vehicles.remove(&v) {
                old.bus.close();
            }
            fault = Fault::VehicleDown {
                vehicle: v,
                up_at: now + 2.0,
            };
            events.push(SoakEvent {
                at_s: now,
                what: format!("vehicle {v} session closed for 2 s"),
                recovered_after_s: None,
            });
        }
        match fault {
            Fault::Partition { heal_at } if now >= heal_at => {
                swarm.relay.switch().heal();
                fault = Fault::None;
                awaiting = Some((events.len() - 1, now));
            }
            Fault::VehicleDown { vehicle, up_at } if now >= up_at => {
                swarm
                    .vehicles
                    .insert(vehicle, open_vehicle(swarm.port_a, &fleet, vehicle)?);
                fault = Fault::None;
                awaiting = Some((events.len() - 1, now));
            }
            _ => {}
        }

        // Maps at the ground station.
        for m in swarm.maps.drain() {
            maps_received += 1;
            if let Some(below) = new_instance_below_seq {
                if m.msg.seq >= below {
                    continue;
                }
                new_instance_below_seq = None;
            }
            last_seq = m.msg.seq;
            let at = since();
            if at > restart_grace_until && at - last_map_at > longest_gap {
                longest_gap = at - last_map_at;
                longest_gap_at = at;
            }
            last_map_at = at;
            if let Some((i, from)) = awaiting {
                if fault == Fault::None && all_live(&m.msg, ids.len()) {
                    events[i].recovered_after_s = Some(at - from);
                    awaiting = None;
                }
            }
        }
        if now - last_map_at > longest_gap.max(MAX_MAP_GAP_S)
            && now > restart_grace_until
            && now > 5.0
        {
            longest_gap = now - last_map_at;
            longest_gap_at = now;
        }

        if now >= next_sample {
            next_sample += SAMPLE_EVERY_S;
            let (rss_kb, open_fds) = resources();
            samples.push(SoakSample {
                at_s: now,
                rss_kb,
                open_fds,
                maps_received,
            });
        }
        if now >= next_progress {
            next_progress += 60.0;
            let (rss, fds) = resources();
            progress(&format!(
                "soak {:.0}/{:.0} s: {} events, {} maps, {} kB resident, {} open files",
                now,
                cfg.duration_s,
                events.len(),
                maps_received,
                rss,
                fds
            ));
        }
        if let Some(rest) = TICK.checked_sub(t0.elapsed()) {
            std::thread::sleep(rest);
        }
    }
    let interrupted = stop.load(Ordering::Relaxed);
    if let Some((handle, bus)) = swarm.fusion.take() {
        handle.stop();
        bus.close();
    }

    // Flat resources: the last fifth of the samples against the first fifth after the first cycle.
    let settled: Vec<&SoakSample> = samples.iter().filter(|s| s.at_s >= cfg.every_s).collect();
    let fifth = (settled.len() / 5).max(1);
    let mean = |xs: &[&SoakSample], f: fn(&SoakSample) -> u64| -> i64 {
        if xs.is_empty() {
            0
        } else {
            (xs.iter().map(|s| f(s)).sum::<u64>() / xs.len() as u64) as i64
        }
    };
    let (first, last) = if settled.len() >= 2 {
        (&settled[..fifth], &settled[settled.len() - fifth..])
    } else {
        (&settled[..], &settled[..])
    };
    let rss_growth_kb = mean(last, |s| s.rss_kb) - mean(first, |s| s.rss_kb);
    let fd_growth = mean(last, |s| s.open_fds) - mean(first, |s| s.open_fds);
    let rss_base = mean(first, |s| s.rss_kb);
    if rss_growth_kb > rss_base / 10 + 16 * 1024 {
        problems.push(format!(
            "resident memory grew by {rss_growth_kb} kB (from {rss_base} kB)"
        ));
    }
    if fd_growth > 4 {
        problems.push(format!("open file descriptors grew by {fd_growth}"));
    }
    if longest_gap > MAX_MAP_GAP_S {
        problems.push(format!(
            "{longest_gap:.2} s without a map outside a fusion restart (ending {longest_gap_at:.0} s into the run)"
        ));
    }
    let end = since();
    for e in &events {
        match e.recovered_after_s {
            Some(r) if r <= cfg.recover_s => {}
            Some(r) => problems.push(format!(
                "{:.0} s: \"{}\": every vehicle Live again only after {r:.1} s (bound {} s)",
                e.at_s, e.what, cfg.recover_s
            )),
            // The run may end before the last event could recover.
            None if end - e.at_s <= cfg.recover_s + cfg.partition_s + 2.0 => {}
            None => problems.push(format!(
                "{:.0} s: \"{}\": no map with every vehicle Live afterwards",
                e.at_s, e.what
            )),
        }
    }
    if events.is_empty() && !interrupted {
        problems.push("no fault was injected: the run is shorter than a quarter cycle".into());
    }
    Ok(SoakReport {
        duration_s: end,
        maps_received,
        observations_published: published,
        longest_map_gap_s: longest_gap,
        longest_map_gap_at_s: longest_gap_at,
        events,
        samples,
        rss_growth_kb,
        fd_growth,
        problems,
        interrupted,
    })
}
