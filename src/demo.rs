//! `shoal demo`: the paper's §6.3 swarm trial, simulated end to end in one
//! process — simulator, one node per vehicle, fusion and a formation
//! controller, each with its own Zenoh session, all talking over loopback TCP
//! through an in-process router. Prints, per vehicle pair, the fused relative
//! position and angle error against ground truth.

use anyhow::{anyhow, Context};
use serde::Serialize;
use shoal_bus::{client_of, free_port, Bus, Clock, Connect, ManualClock, Subscription};
use shoal_fusion::formation::FormationController;
use shoal_fusion::service::{FusionConfig, MapClient, Placement};
use shoal_fusion::FusionParams;
use shoal_node::pipeline::PipelineParams;
use shoal_node::service::{NodeConfig, NodeHandle, Source};
use shoal_proto::config::Fleet;
use shoal_proto::geometry::difference;
use shoal_proto::messages::{FleetMap, SimTruth, VehicleCommand, VehicleId, VehicleState};
use shoal_sim_bridge::bridge::SimConfig;
use shoal_sim_bridge::water::WaterPresets;
use shoal_sim_bridge::world::Formation;
use std::collections::{BTreeMap, VecDeque};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The paper's three-vehicle fleet, built into the binary.
pub const PAPER_FLEET: &str = include_str!("../configs/fleets/paper.toml");

#[derive(Debug, Clone)]
pub struct DemoConfig {
    /// Fleet file; `None` uses the built-in paper fleet.
    pub fleet: Option<PathBuf>,
    /// Water attenuation coefficient (1/m); the paper's trial was at 0.5.
    pub water_c_per_m: f64,
    /// Simulated seconds to run.
    pub duration_s: f64,
    /// Camera frames per simulated second.
    pub frame_rate_hz: f64,
    /// Cameras rendered (names); `None`: all five.
    pub cameras: Option<Vec<String>>,
    pub spacing_m: f64,
    pub seed: u64,
    /// Show a progress bar.
    pub progress: bool,
    /// Steer the followers with the formation controller.
    pub closed_loop: bool,
}

impl Default for DemoConfig {
    fn default() -> Self {
        Self {
            fleet: None,
            water_c_per_m: 0.5,
            duration_s: 30.0,
            frame_rate_hz: 2.0,
            cameras: None,
            spacing_m: 1.75,
            seed: 7,
            progress: true,
            closed_loop: true,
        }
    }
}

/// Error of one vehicle pair, averaged over the maps of the run's second half.
#[derive(Debug, Clone, Serialize)]
pub struct PairError {
    pub a: VehicleId,
    pub b: VehicleId,
    pub position_error_m: f64,
    pub angle_error_deg: f64,
    /// Maps in which the pair was localized (both Live), of those evaluated.
    pub maps_localized: usize,
    pub maps_evaluated: usize,
}

#[derive(Debug, Clone, Serialize)]
pub struct DemoSummary {
    pub pairs: Vec<PairError>,
    pub frames_processed: u64,
    pub frames_dropped: u64,
    pub mean_latency_ms: f64,
    pub maps_received: usize,
    pub observations_sent: u64,
    pub edges_accepted: usize,
    pub edges_rejected: usize,
    pub sim_ticks: u64,
    pub sim_ticks_skipped: u64,
    pub wall_time_s: f64,
}

fn load_fleet(cfg: &DemoConfig) -> anyhow::Result<Fleet> {
    Ok(match &cfg.fleet {
        Some(p) => Fleet::load(p)?,
        None => Fleet::parse(PAPER_FLEET, std::path::Path::new("configs/fleets/paper.toml"))?,
    })
}

/// Run the demo; `on_progress(sim_s, total_s)` is called as simulated time advances.
pub fn run(cfg: &DemoConfig, mut on_progress: impl FnMut(f64, f64, &str)) -> anyhow::Result<DemoSummary> {
    let started = Instant::now();
    let fleet = Arc::new(load_fleet(cfg)?);
    let water = WaterPresets::builtin()
        .get(cfg.water_c_per_m)
        .with_context(|| format!("water {} /m", cfg.water_c_per_m))?;
    let port = free_port().context("no free loopback port")?;
    let _router = Bus::open(&Connect::Router { port })?;
    let session = || Bus::open(&client_of(port));
    let clock = Arc::new(ManualClock::new(0));

    // Fusion first, so it hears everything.
    let fusion = shoal_fusion::service::spawn(
        &session()?,
        FusionConfig {
            fleet: fleet.clone(),
            params: FusionParams::default(),
            placement: Placement::Central,
            rate_hz: 5.0,
            queue_capacity: 4096,
        },
        clock.clone(),
    )?;
    let mut nodes: Vec<NodeHandle> = Vec::new();
    for v in &fleet.vehicles {
        nodes.push(shoal_node::service::spawn(
            &session()?,
            NodeConfig {
                fleet: fleet.clone(),
                vehicle: v.id,
                params: PipelineParams::default(),
                source: Source::Zenoh,
                queue_capacity: 2,
                status_period: Duration::from_secs(1),
            },
        )?);
    }
    let observer_bus = session()?;
    let truth_sub: Subscription<SimTruth> = observer_bus.subscribe(&fleet.keys().truth(), 256)?;
    let map_sub: Subscription<FleetMap> = observer_bus.subscribe(&fleet.keys().map(), 256)?;
    let controller_bus = session()?;
    let mut map_client = MapClient::connect(&controller_bus, &fleet)?;
    let followers: Vec<VehicleId> = fleet
        .vehicles
        .iter()
        .map(|v| v.id)
        .filter(|&v| v != fleet.reference_vehicle)
        .collect();
    let mut cmd_pubs = BTreeMap::new();
    for &v in &followers {
        cmd_pubs.insert(v, controller_bus.publisher::<VehicleCommand>(fleet.keys().command(v))?);
    }
    // Let subscriptions propagate before the first frame.
    std::thread::sleep(Duration::from_millis(300));
    let sim = shoal_sim_bridge::bridge::spawn(
        &session()?,
        SimConfig {
            fleet: fleet.clone(),
            water,
            formation: Formation::Line,
            spacing_m: cfg.spacing_m,
            seed: cfg.seed,
            frame_rate_hz: cfg.frame_rate_hz,
            cameras: cfg.cameras.clone(),
            time_scale: 1.0,
            duration_s: Some(cfg.duration_s),
            commanded: if cfg.closed_loop { followers.clone() } else { vec![] },
        },
        clock.clone(),
    )?;

    let mut truths: VecDeque<SimTruth> = VecDeque::new();
    let mut maps: Vec<FleetMap> = Vec::new();
    let mut controller: Option<FormationController> = None;
    let mut last_cmd = Instant::now();
    while !sim.finished() {
        std::thread::sleep(Duration::from_millis(50));
        for t in truth_sub.drain() {
            if controller.is_none() && cfg.closed_loop {
                controller = Some(formation_from_truth(&fleet, &t.msg));
            }
            truths.push_back(t.msg);
            if truths.len() > 2000 {
                truths.pop_front();
            }
        }
        maps.extend(map_sub.drain().into_iter().map(|r| r.msg));
        if let (Some(c), Some(view)) = (&controller, map_client.latest()) {
            if last_cmd.elapsed() >= Duration::from_millis(200) {
                last_cmd = Instant::now();
                for cmd in c.commands(view) {
                    if let Some(p) = cmd_pubs.get(&cmd.vehicle) {
                        if let Err(e) = p.put(&cmd) {
                            tracing::warn!("controller: {e}");
                        }
                    }
                }
            }
        }
        let live = maps.last().map(|m| m.vehicles.iter().filter(|v| v.state == VehicleState::Live).count()).unwrap_or(0);
        on_progress(
            clock.now_ns() as f64 * 1e-9,
            cfg.duration_s,
            &format!("{} maps, {live}/{} vehicles localized", maps.len(), fleet.vehicles.len()),
        );
        if started.elapsed() > Duration::from_secs_f64(cfg.duration_s * 4.0 + 60.0) {
            return Err(anyhow!("demo did not finish in time: simulator stalled"));
        }
    }
    // Give the pipeline a moment to drain the last frames.
    std::thread::sleep(Duration::from_millis(500));
    maps.extend(map_sub.drain().into_iter().map(|r| r.msg));
    truths.extend(truth_sub.drain().into_iter().map(|r| r.msg));
    let sim_stats = sim.stats().clone();
    sim.stop().map_err(|e| anyhow!(e))?;

    let frames_processed = nodes.iter().map(|n| n.stats().frames_processed()).sum();
    let frames_dropped = nodes.iter().map(|n| n.stats().frames_dropped()).sum();
    let observations_sent = nodes.iter().map(|n| n.stats().observations_sent.load(std::sync::atomic::Ordering::Relaxed)).sum();
    let latencies: Vec<f64> = nodes.iter().filter_map(|n| n.stats().mean_latency_ms()).collect();
    for n in nodes {
        n.stop();
    }
    fusion.stop();

    let half = maps.len() / 2;
    let evaluated = &maps[half..];
    let pairs = pair_errors(&fleet, evaluated, &truths);
    let (acc, rej) = evaluated.last().map(|m| {
        let rej = m.edges.iter().filter(|e| e.rejected.is_some()).count();
        (m.edges.len() - rej, rej)
    }).unwrap_or((0, 0));
    Ok(DemoSummary {
        pairs,
        frames_processed,
        frames_dropped,
        mean_latency_ms: if latencies.is_empty() { f64::NAN } else { latencies.iter().sum::<f64>() / latencies.len() as f64 },
        maps_received: maps.len(),
        observations_sent,
        edges_accepted: acc,
        edges_rejected: rej,
        sim_ticks: sim_stats.ticks.load(std::sync::atomic::Ordering::Relaxed),
        sim_ticks_skipped: sim_stats.ticks_skipped.load(std::sync::atomic::Ordering::Relaxed),
        wall_time_s: started.elapsed().as_secs_f64(),
    })
}

/// The formation to hold: every follower's starting offset from the reference.
fn formation_from_truth(fleet: &Fleet, truth: &SimTruth) -> FormationController {
    let mut c = FormationController::line_abreast(fleet, 1.0, 0.2);
    let pose_of = |v: VehicleId| truth.vehicles.iter().find(|t| t.vehicle == v).map(|t| t.world_from_body);
    if let Some(world_from_ref) = pose_of(fleet.reference_vehicle) {
        for (v, slot) in c.slots.iter_mut() {
            if let Some(world_from_v) = pose_of(*v) {
                *slot = (world_from_ref.inverse() * world_from_v).translation.vector;
            }
        }
    }
    c
}

/// Mean error of every pair over `maps`, each map against the truth of its stamp.
pub fn pair_errors(fleet: &Fleet, maps: &[FleetMap], truths: &VecDeque<SimTruth>) -> Vec<PairError> {
    let ids: Vec<VehicleId> = fleet.vehicles.iter().map(|v| v.id).collect();
    let mut out = Vec::new();
    for (i, &a) in ids.iter().enumerate() {
        for &b in &ids[i + 1..] {
            let (mut pos, mut ang, mut n) = (0.0, 0.0, 0usize);
            for map in maps {
                let Some(truth) = truths.iter().min_by_key(|t| t.stamp_ns.abs_diff(map.stamp_ns)) else {
                    continue;
                };
                let view = shoal_fusion::MapView::new(map.clone());
                let Some(rel) = view.relative(a, b) else { continue };
                if !rel.live {
                    continue;
                }
                let pose_of = |v: VehicleId| truth.vehicles.iter().find(|t| t.vehicle == v).map(|t| t.world_from_body);
                let (Some(wa), Some(wb)) = (pose_of(a), pose_of(b)) else { continue };
                let true_a_from_b = wa.inverse() * wb;
                let d = difference(&rel.a_from_b.pose, &true_a_from_b);
                pos += d.fixed_rows::<3>(0).norm();
                ang += d.fixed_rows::<3>(3).norm().to_degrees();
                n += 1;
            }
            out.push(PairError {
                a,
                b,
                position_error_m: if n > 0 { pos / n as f64 } else { f64::NAN },
                angle_error_deg: if n > 0 { ang / n as f64 } else { f64::NAN },
                maps_localized: n,
                maps_evaluated: maps.len(),
            });
        }
    }
    out
}
