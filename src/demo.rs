//! `shoal demo`: the paper's §6.3 swarm trial, simulated end to end in one
//! process — simulator, one node per vehicle, fusion and a formation
//! controller, each with its own Zenoh session, all talking over loopback TCP
//! through an in-process router. Prints, per vehicle pair, the fused relative
//! position and angle error against ground truth.

mod occlusion;

use anyhow::{anyhow, Context};
use serde::Serialize;
use shoal_bus::{client_of, free_port, Bus, Connect, Publisher, Received, Subscription};
use shoal_fusion::formation::FormationController;
use shoal_fusion::FusionParams;
use shoal_node::pipeline::PipelineParams;
use shoal_proto::clock::{Clock, ManualClock};
use shoal_proto::config::Fleet;
use shoal_proto::geometry::difference;
use shoal_proto::messages::{
    FleetMap, RejectReason, SimTruth, VehicleCommand, VehicleId, VehicleState,
};
use shoal_services::fusion::{FusionConfig, MapClient, Placement};
use shoal_services::node::{NodeConfig, NodeHandle, Source};
use shoal_services::sim::SimConfig;
use shoal_sim_bridge::water::WaterPresets;
use shoal_sim_bridge::world::Formation;
use std::collections::{BTreeMap, VecDeque};
use std::path::PathBuf;
use std::sync::atomic::Ordering;
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
    /// Simulated seconds per wall-clock second. Below 1 gives rendering (15
    /// frames per tick on two cores) time to keep up without skipping ticks.
    pub time_scale: f64,
    /// Show a progress bar.
    pub progress: bool,
    /// Steer the followers with the formation controller.
    pub closed_loop: bool,
    /// MCAP log of the run (wire messages + Foxglove channels); `None`: no log.
    pub log: Option<PathBuf>,
    /// Include camera frames in the log (they dominate its size).
    pub log_frames: bool,
    /// Ground-station page and Foxglove live server (`shoal-station`); `None`: none.
    pub station: Option<shoal_station::StationConfig>,
    /// The vehicles publish their own navigation (simulated depth, IMU, DVL)
    /// and fusion settles planar flips with it.
    pub nav: bool,
    /// A vehicle hidden from every camera for a span of the run (its own
    /// cameras blind too); the summary then reports how the map kept it.
    pub occlude: Option<shoal_services::sim::Occlusion>,
    /// Loopback port of the in-process Zenoh router, where outside clients
    /// (`shoal station`, `shoal record`, a Python or ROS 2 client) attach;
    /// `None`: any free port. When the port is taken the router listens on a
    /// free one and [`SimulatedSwarm::port_taken`] says so (with `ros2`, it
    /// also joins the router holding the port: a ROS 2 `rmw_zenohd`).
    pub router_port: Option<u16>,
    /// Publish in ROS 2 over `rmw_zenoh` in this domain (`shoal_services::ros2`).
    pub ros2: Option<u32>,
    /// The camera the simulator renders through (issue #16; `None`: the
    /// ideal renderer). With one, every node holds the calibration a lab
    /// would have for its camera behind that camera's port, off by the
    /// profile's calibration error, and states that lab's uncertainty
    /// ([`crate::eval::profiles::lab_fleet`], drawn from [`DemoConfig::seed`]).
    pub profile: Option<shoal_sim_bridge::profile::CameraProfile>,
}

impl Default for DemoConfig {
    fn default() -> Self {
        Self {
            fleet: None,
            water_c_per_m: 0.5,
            duration_s: 20.0,
            frame_rate_hz: 2.0,
            cameras: None,
            spacing_m: 1.75,
            seed: 7,
            time_scale: 1.0,
            progress: true,
            closed_loop: true,
            log: Some(PathBuf::from("out/demo.mcap")),
            log_frames: false,
            station: None,
            nav: true,
            occlude: None,
            router_port: None,
            ros2: None,
            profile: None,
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
    /// Of the maps localizing the pair, those more than 10° off (a planar-flip twin).
    pub maps_flipped: usize,
    /// Mean normalized estimation error squared over those maps (6 DoF: 6
    /// when the reported covariance is the error's own; NaN without maps).
    pub mean_nees: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct DemoSummary {
    pub pairs: Vec<PairError>,
    /// Camera frames the simulator published; of them, processed by the
    /// nodes, dropped by their queues (a node behind), and never received by
    /// a node (lost on the bus: Zenoh drops a frame under congestion without
    /// telling anyone, the node sees the gap in the sequence; or published
    /// for a node that was stopped).
    pub frames_published: u64,
    pub frames_processed: u64,
    pub frames_dropped: u64,
    pub frames_lost: u64,
    pub mean_latency_ms: f64,
    /// Mean time from a tick's frames being published (its ground truth follows
    /// them) to the first fleet map that includes an observation of that tick, ms.
    pub mean_end_to_end_latency_ms: f64,
    pub maps_received: usize,
    pub observations_sent: u64,
    /// Verdicts in the last map: accepted hypotheses, rejected observations
    /// (any reason but a lost planar-flip twin), and lost twins (each
    /// observation with an IPPE alternative reports both hypotheses).
    pub edges_accepted: usize,
    pub edges_rejected: usize,
    pub flip_twins_rejected: usize,
    /// Over every map of the run, distinct observations: those the vehicles'
    /// nav refused outright (every hypothesis `Gravity` / `Depth` /
    /// `Heading` in some map: a misread, or a true one lost), and those with
    /// only some hypotheses refused by nav (a planar-flip twin, mostly).
    pub observations_refused_by_nav: usize,
    pub twins_refused_by_nav: usize,
    /// With [`DemoConfig::occlude`]: the hidden vehicle in the maps of its span.
    pub occlusion: Option<occlusion::OcclusionReport>,
    pub sim_ticks: u64,
    pub sim_ticks_skipped: u64,
    pub wall_time_s: f64,
    /// Of it: from the start to the simulator's start (router, services,
    /// subscriptions), the simulated run (with the simulator's own wait for
    /// the nodes before its first tick), and from its last tick to the end
    /// (the pipeline drained, the services stopped, the log finished).
    pub startup_s: f64,
    pub running_s: f64,
    pub finishing_s: f64,
    /// The MCAP log written, with its message count and messages dropped.
    pub log: Option<LogSummary>,
    /// Simulated time at which a stop request (Ctrl-C, SIGTERM) ended the run early.
    pub interrupted_at_s: Option<f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct LogSummary {
    pub path: PathBuf,
    pub messages: u64,
    pub dropped: u64,
    pub file_bytes: u64,
}

/// The demo's fleet: [`DemoConfig::fleet`], or the built-in paper fleet.
pub fn load_fleet(cfg: &DemoConfig) -> anyhow::Result<Fleet> {
    Ok(match &cfg.fleet {
        Some(p) => Fleet::load(p)?,
        None => Fleet::parse(
            PAPER_FLEET,
            std::path::Path::new("configs/fleets/paper.toml"),
        )?,
    })
}

/// A running simulated swarm: an in-process Zenoh router, fusion, one node
/// per vehicle and the simulator, each on its own session over loopback TCP.
pub struct SimulatedSwarm {
    pub fleet: Arc<Fleet>,
    /// The fleet as the nodes hold it: [`SimulatedSwarm::fleet`], but for
    /// the cameras' calibrations with [`DemoConfig::profile`].
    node_fleet: Arc<Fleet>,
    pub clock: Arc<ManualClock>,
    port: u16,
    /// The port asked for, when another process held it.
    port_taken: Option<u16>,
    _router: Bus,
    fusion: Option<shoal_services::fusion::FusionHandle>,
    ros2: Option<shoal_services::ros2::Ros2Handle>,
    nodes: BTreeMap<VehicleId, NodeHandle>,
    sim: Option<shoal_services::sim::SimHandle>,
    station: Option<shoal_station::StationHandle>,
}

impl std::fmt::Debug for SimulatedSwarm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimulatedSwarm")
            .field("port", &self.port)
            .finish()
    }
}

impl SimulatedSwarm {
    /// Start everything but the simulator's clock; `commanded` vehicles follow commands.
    pub fn start(cfg: &DemoConfig, commanded: Vec<VehicleId>) -> anyhow::Result<SimulatedSwarm> {
        Self::start_with(cfg, commanded, |_| Ok(()))
    }

    /// As [`SimulatedSwarm::start`], calling `before_sim` (e.g. to start a
    /// recorder) once everything but the simulator is up.
    pub fn start_with(
        cfg: &DemoConfig,
        commanded: Vec<VehicleId>,
        before_sim: impl FnOnce(&SimulatedSwarm) -> anyhow::Result<()>,
    ) -> anyhow::Result<SimulatedSwarm> {
        let fleet = Arc::new(load_fleet(cfg)?);
        let profile = cfg.profile.clone().map(|p| p.with_seed(cfg.seed));
        let node_fleet = match &profile {
            Some(p) => {
                let t0 = Instant::now();
                let held = crate::eval::profiles::lab_fleet(&fleet, p, cfg.seed, true)
                    .map_err(|e| anyhow!("the camera profile's calibrations: {e}"))?;
                tracing::info!(
                    "camera profile {}: the nodes' calibrations of {} cameras as a lab would have them, {:.1} s",
                    p.name,
                    held.vehicles.iter().map(|v| v.cameras.len()).sum::<usize>(),
                    t0.elapsed().as_secs_f64()
                );
                Arc::new(held)
            }
            None => fleet.clone(),
        };
        let water = WaterPresets::builtin()
            .get(cfg.water_c_per_m)
            .with_context(|| format!("water {} /m", cfg.water_c_per_m))?;
        let (port, port_taken, router) = open_router(cfg.router_port, cfg.ros2.is_some())?;
        let clock = Arc::new(ManualClock::new(0));
        let mut swarm = SimulatedSwarm {
            fleet: fleet.clone(),
            node_fleet,
            clock: clock.clone(),
            port,
            port_taken,
            _router: router,
            fusion: None,
            ros2: None,
            nodes: BTreeMap::new(),
            sim: None,
            station: None,
        };
        // Fusion first, so it hears everything.
        swarm.fusion = Some(shoal_services::fusion::spawn(
            &swarm.session()?,
            FusionConfig {
                fleet: fleet.clone(),
                params: FusionParams::default(),
                placement: Placement::Central,
                rate_hz: 5.0,
                queue_capacity: 4096,
                link: false,
            },
            clock.clone(),
        )?);
        if let Some(domain) = cfg.ros2 {
            swarm.ros2 = Some(shoal_services::ros2::spawn(
                &swarm.session()?,
                shoal_services::ros2::Ros2Config::for_fusion(
                    fleet.clone(),
                    domain,
                    Placement::Central,
                ),
            )?);
        }
        for v in fleet.vehicles.iter().map(|v| v.id).collect::<Vec<_>>() {
            swarm.start_node(v)?;
        }
        if let Some(sc) = &cfg.station {
            let station = shoal_station::spawn(&swarm.session()?, fleet.clone(), sc.clone())?;
            tracing::info!("ground station at {}", station.url());
            swarm.station = Some(station);
        }
        before_sim(&swarm)?;
        swarm.sim = Some(shoal_services::sim::spawn(
            &swarm.session()?,
            SimConfig {
                fleet: fleet.clone(),
                water,
                formation: Formation::Line,
                spacing_m: cfg.spacing_m,
                seed: cfg.seed,
                frame_rate_hz: cfg.frame_rate_hz,
                cameras: cfg.cameras.clone(),
                time_scale: cfg.time_scale,
                duration_s: Some(cfg.duration_s),
                commanded,
                nav: cfg
                    .nav
                    .then(shoal_sim_bridge::nav::NavSensorParams::default),
                hidden: cfg.occlude.into_iter().collect(),
                profile,
                // The first frames wait for the nodes (~0.1 s here), no longer.
                wait_for_nodes: NODES_TIMEOUT,
            },
            clock,
        )?);
        Ok(swarm)
    }

    /// Where outside Zenoh clients connect: `tcp/127.0.0.1:<port>`.
    pub fn endpoint(&self) -> String {
        format!("tcp/127.0.0.1:{}", self.port)
    }

    /// The port [`DemoConfig::router_port`] asked for, when it was taken.
    pub fn port_taken(&self) -> Option<u16> {
        self.port_taken
    }

    /// The ROS 2 publisher, when [`DemoConfig::ros2`] asked for one.
    pub fn ros2(&self) -> Option<&shoal_services::ros2::Ros2Handle> {
        self.ros2.as_ref()
    }

    /// A new Zenoh session on the swarm's router.
    pub fn session(&self) -> anyhow::Result<Bus> {
        Ok(Bus::open(&client_of(self.port))?)
    }

    /// Start (or restart) vehicle `v`'s node.
    pub fn start_node(&mut self, v: VehicleId) -> anyhow::Result<()> {
        let node = shoal_services::node::spawn(
            &self.session()?,
            NodeConfig {
                fleet: self.node_fleet.clone(),
                vehicle: v,
                params: PipelineParams::default(),
                source: Source::Zenoh,
                queue_capacity: 2,
                status_period: Duration::from_secs(1),
            },
        )?;
        if let Some(old) = self.nodes.insert(v, node) {
            old.stop();
        }
        Ok(())
    }

    /// Stop vehicle `v`'s node (its liveliness token disappears).
    pub fn kill_node(&mut self, v: VehicleId) -> bool {
        self.nodes.remove(&v).map(|n| n.stop()).is_some()
    }

    pub fn nodes(&self) -> impl Iterator<Item = &NodeHandle> {
        self.nodes.values()
    }

    /// The ground station, when [`DemoConfig::station`] asked for one.
    pub fn station(&self) -> Option<&shoal_station::StationHandle> {
        self.station.as_ref()
    }

    pub fn sim_finished(&self) -> bool {
        self.sim.as_ref().is_none_or(|s| s.finished())
    }

    /// Camera frames the simulator has published so far.
    pub fn frames_published(&self) -> u64 {
        self.sim
            .as_ref()
            .map_or(0, |s| s.stats().frames_published.load(Ordering::Relaxed))
    }

    /// Stop the simulator, then the nodes and fusion; returns the simulator's
    /// (ticks, ticks skipped because rendering fell behind).
    pub fn shutdown(mut self) -> anyhow::Result<(u64, u64)> {
        let mut counts = (0, 0);
        if let Some(sim) = self.sim.take() {
            let s = sim.stats();
            counts = (
                s.ticks.load(Ordering::Relaxed),
                s.ticks_skipped.load(Ordering::Relaxed),
            );
            sim.stop().map_err(|e| anyhow!(e))?;
        }
        for n in self.nodes.values() {
            n.request_stop();
        }
        for (_, n) in std::mem::take(&mut self.nodes) {
            n.stop();
        }
        if let Some(f) = self.fusion.take() {
            f.stop();
        }
        if let Some(r) = self.ros2.take() {
            r.stop();
        }
        if let Some(s) = self.station.take() {
            s.stop();
        }
        Ok(counts)
    }
}

/// Tell the user where outside clients attach (and ROS 2 users where to look).
fn say_where(cfg: &DemoConfig, swarm: &SimulatedSwarm) {
    let endpoint = swarm.endpoint();
    match swarm.port_taken() {
        None => crate::errln!(
            "zenoh: the demo's router listens on {endpoint}; `shoal station`, `shoal record` and Python zenoh clients connect there"
        ),
        Some(p) if cfg.ros2.is_some() => crate::errln!(
            "zenoh: port {p} is taken (a ROS 2 rmw_zenohd?): the demo's router joined it and listens on {endpoint}"
        ),
        Some(p) => crate::errln!(
            "zenoh: port {p} is taken (another demo or a zenohd?): the demo's router listens on {endpoint} instead; clients use --port {}",
            swarm.port
        ),
    }
    if let Some(domain) = cfg.ros2 {
        crate::errln!(
            "ROS 2: node /shoal_fusion in domain {domain} on rmw_zenoh; try `RMW_IMPLEMENTATION=rmw_zenoh_cpp ros2 topic echo /tf` (docs/ros2.md)"
        );
    }
}

/// The demo's router on `wanted` (else any free port): returns the port it
/// listens on, the wanted port when it was taken, and the session. With
/// `join`, a router found on the wanted port is joined (a ROS 2
/// `rmw_zenohd`, so ROS 2 nodes see the demo).
fn open_router(wanted: Option<u16>, join: bool) -> anyhow::Result<(u16, Option<u16>, Bus)> {
    // Port 0 asks for any free port, as `None` does (binding 0 would succeed, then nothing could connect to it).
    let wanted = wanted.filter(|&p| p != 0);
    if let Some(p) = wanted {
        if std::net::TcpListener::bind(("127.0.0.1", p)).is_ok() {
            // Free a moment ago; a race with another process is reported by Zenoh.
            let router = Bus::open(&Connect::Router { port: p })
                .with_context(|| format!("Zenoh router on tcp/127.0.0.1:{p}"))?;
            return Ok((p, None, router));
        }
    }
    let port = free_port().context("no free loopback port")?;
    let taken = wanted;
    let router = match taken.filter(|_| join) {
        Some(p) => Bus::open(&Connect::RouterLinked {
            port,
            routers: vec![p],
        })?,
        None => Bus::open(&Connect::Router { port })?,
    };
    Ok((port, taken, router))
}

/// Start the recorder on `sw` when `cfg.log` asks for a log (before the simulator starts).
fn start_recorder(
    cfg: &DemoConfig,
    sw: &SimulatedSwarm,
) -> anyhow::Result<Option<shoal_services::recorder::RecorderHandle>> {
    let Some(path) = &cfg.log else {
        return Ok(None);
    };
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let opts = shoal_record::RecordOptions {
        frames: cfg.log_frames,
        water_c_per_m: Some(cfg.water_c_per_m),
        fleet_toml: Some(match &cfg.fleet {
            Some(p) => std::fs::read_to_string(p)
                .with_context(|| format!("cannot read {}", p.display()))?,
            None => PAPER_FLEET.to_string(),
        }),
        ..Default::default()
    };
    Ok(Some(shoal_services::recorder::Recorder::spawn(
        &sw.session()?,
        sw.fleet.clone(),
        path,
        opts,
    )?))
}

/// What the demo's observer collects while the trial runs.
#[derive(Debug, Default)]
struct TrialWatch {
    /// The newest ground truth (at most `TRUTHS_KEPT`), oldest first.
    truths: VecDeque<SimTruth>,
    /// When each tick's truth arrived, until a map uses that tick's frames.
    tick_published: BTreeMap<u64, Instant>,
    /// Sum (ms) and count of tick-to-map latencies.
    e2e: (f64, usize),
    maps: Vec<FleetMap>,
}

/// Ground truth messages kept for scoring: the newest, so a long run's memory stays bounded.
const TRUTHS_KEPT: usize = 2000;

impl TrialWatch {
    fn add_truth(&mut self, t: Received<SimTruth>) {
        self.tick_published
            .entry(t.msg.stamp_ns)
            .or_insert(t.received_at);
        self.truths.push_back(t.msg);
        if self.truths.len() > TRUTHS_KEPT {
            self.truths.pop_front();
        }
    }

    /// Keep a map, and time from each tick's truth to the first map with its frames.
    fn add_map(&mut self, r: Received<FleetMap>) {
        let stamps: std::collections::BTreeSet<u64> = r
            .msg
            .edges
            .iter()
            .filter(|e| e.rejected.is_none())
            .map(|e| e.stamp_ns)
            .collect();
        for st in stamps {
            if let Some(t0) = self.tick_published.remove(&st) {
                self.e2e.0 += r.received_at.saturating_duration_since(t0).as_secs_f64() * 1e3;
                self.e2e.1 += 1;
            }
        }
        self.maps.push(r.msg);
    }
}

/// Edges of `map` accepted, rejected (other than as flip twins), and
/// rejected as flip twins (`FlippedHypothesis`, or `Gravity` / `Heading`:
/// the twin the vehicles' nav refused); zeros without a map.
fn verdict_counts(map: Option<&FleetMap>) -> (usize, usize, usize) {
    map.map(|m| {
        let count = |f: &dyn Fn(&Option<RejectReason>) -> bool| {
            m.edges.iter().filter(|e| f(&e.rejected)).count()
        };
        (
            count(&|r| r.is_none()),
            count(&|r| r.as_ref().is_some_and(|r| !is_twin(r))),
            count(&|r| r.as_ref().is_some_and(is_twin)),
        )
    })
    .unwrap_or((0, 0, 0))
}

/// `sum / n`, NaN when there is nothing to average.
fn mean_or_nan(sum: f64, n: usize) -> f64 {
    if n > 0 {
        sum / n as f64
    } else {
        f64::NAN
    }
}

/// Distinct observations over `maps` whose every hypothesis the nav checks
/// refused (in some map), and those with one refused by nav (and not all).
fn nav_verdicts(maps: &[FleetMap]) -> (usize, usize) {
    type Key = shoal_proto::DetectionKey;
    let is_nav = |r: &Option<RejectReason>| {
        matches!(
            r,
            Some(RejectReason::Gravity | RejectReason::Depth | RejectReason::Heading)
        )
    };
    // Per observation: refused outright in some map, refused in part in some map.
    let mut seen: BTreeMap<Key, (bool, bool)> = BTreeMap::new();
    for m in maps {
        // Per observation in this map: hypotheses reported, refused by nav.
        let mut per: BTreeMap<Key, (usize, usize)> = BTreeMap::new();
        for e in &m.edges {
            let v = per.entry(e.detection_key()).or_default();
            v.0 += 1;
            v.1 += usize::from(is_nav(&e.rejected));
        }
        for (k, (n, nav)) in per.into_iter().filter(|(_, v)| v.1 > 0) {
            let s = seen.entry(k).or_default();
            s.0 |= nav == n;
            s.1 |= nav < n;
        }
    }
    let refused = seen.values().filter(|(all, _)| *all).count();
    (refused, seen.len() - refused)
}

fn is_twin(r: &RejectReason) -> bool {
    matches!(
        r,
        RejectReason::FlippedHypothesis | RejectReason::Gravity | RejectReason::Heading
    )
}

/// The formation controller of a closed-loop demo: steers the followers
/// from the newest fused map, every `COMMAND_PERIOD`, over its own session.
struct ControlLoop {
    _bus: Bus,
    map_client: MapClient,
    publishers: BTreeMap<VehicleId, Publisher<VehicleCommand>>,
    /// Set from the first ground truth (the formation to hold); none in open loop.
    controller: Option<FormationController>,
    last_command: Instant,
}

/// How often the controller sends its commands.
const COMMAND_PERIOD: Duration = Duration::from_millis(200);

impl ControlLoop {
    fn connect(bus: Bus, fleet: &Fleet, followers: &[VehicleId]) -> anyhow::Result<ControlLoop> {
        let map_client = MapClient::connect(&bus, fleet)?;
        let mut publishers = BTreeMap::new();
        for &v in followers {
            publishers.insert(v, bus.publisher::<VehicleCommand>(fleet.keys().command(v))?);
        }
        Ok(ControlLoop {
            _bus: bus,
            map_client,
            publishers,
            controller: None,
            last_command: Instant::now(),
        })
    }

    /// Send the controller's commands when a period has passed and there is a map.
    fn step(&mut self) {
        let (Some(c), Some(view)) = (&self.controller, self.map_client.latest()) else {
            return;
        };
        if self.last_command.elapsed() < COMMAND_PERIOD {
            return;
        }
        self.last_command = Instant::now();
        for cmd in c.commands(view) {
            if let Some(p) = self.publishers.get(&cmd.vehicle) {
                if let Err(e) = p.put(&cmd) {
                    tracing::warn!("controller: {e}");
                }
            }
        }
    }
}

/// Close the log and summarize it.
fn stop_recorder(r: shoal_services::recorder::RecorderHandle) -> anyhow::Result<LogSummary> {
    let sum = r.stop()?;
    Ok(LogSummary {
        path: sum.path.clone(),
        messages: sum.wire_messages,
        dropped: sum.dropped,
        file_bytes: sum.file_bytes,
    })
}

/// How long the simulator waits for the nodes, and the run's end for the
/// pipeline to drain, at most.
const NODES_TIMEOUT: Duration = Duration::from_secs(2);
const DRAIN_TIMEOUT: Duration = Duration::from_secs(1);
/// No frame handled for this long: the rest of the last tick is not coming.
const DRAIN_QUIET: Duration = Duration::from_millis(200);

/// After the simulator's last tick: wait until every frame it published is
/// processed or dropped by its node (or none has been for [`DRAIN_QUIET`]:
/// a frame the bus lost under load never comes), then for the next fleet map
/// (which holds the last observations), within [`DRAIN_TIMEOUT`] in all.
fn drain(swarm: &SimulatedSwarm, map_sub: &Subscription<FleetMap>, watch: &mut TrialWatch) {
    let deadline = Instant::now() + DRAIN_TIMEOUT;
    let published = swarm.frames_published();
    let handled = || -> u64 {
        swarm
            .nodes()
            .map(|n| n.stats().frames_processed() + n.stats().frames_dropped())
            .sum()
    };
    let (mut last, mut since) = (handled(), Instant::now());
    while last < published && since.elapsed() < DRAIN_QUIET && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(5));
        let now = handled();
        if now != last {
            (last, since) = (now, Instant::now());
        }
    }
    let maps_before = watch.maps.len();
    while Instant::now() < deadline {
        for r in map_sub.drain() {
            watch.add_map(r);
        }
        if watch.maps.len() > maps_before {
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Run the demo; `on_progress(sim_s, total_s, status)` is called as simulated time advances.
pub fn run(
    cfg: &DemoConfig,
    on_progress: impl FnMut(f64, f64, &str),
) -> anyhow::Result<DemoSummary> {
    run_until(cfg, &std::sync::atomic::AtomicBool::new(false), on_progress)
}

/// [`run`], ended early when `stop` becomes true (the command sets it on
/// Ctrl-C or SIGTERM): the services stop in order, the log is finished with
/// its summary and the figures cover the time run.
pub fn run_until(
    cfg: &DemoConfig,
    stop: &std::sync::atomic::AtomicBool,
    mut on_progress: impl FnMut(f64, f64, &str),
) -> anyhow::Result<DemoSummary> {
    let started = Instant::now();
    let fleet = Arc::new(load_fleet(cfg)?);
    let followers: Vec<VehicleId> = fleet
        .vehicles
        .iter()
        .map(|v| v.id)
        .filter(|&v| v != fleet.reference_vehicle)
        .collect();
    let mut recorder = None;
    let swarm = SimulatedSwarm::start_with(
        cfg,
        if cfg.closed_loop {
            followers.clone()
        } else {
            vec![]
        },
        |sw| {
            recorder = start_recorder(cfg, sw)?;
            Ok(())
        },
    )?;
    let startup_s = started.elapsed().as_secs_f64();
    say_where(cfg, &swarm);
    let clock = swarm.clock.clone();
    let observer_bus = swarm.session()?;
    let truth_sub: Subscription<SimTruth> = observer_bus.subscribe(&fleet.keys().truth(), 256)?;
    let map_sub: Subscription<FleetMap> = observer_bus.subscribe(&fleet.keys().map(), 256)?;
    let mut control = ControlLoop::connect(swarm.session()?, &fleet, &followers)?;

    let mut watch = TrialWatch::default();
    let mut interrupted_at_s = None;
    while !swarm.sim_finished() {
        if stop.load(Ordering::Relaxed) {
            interrupted_at_s = Some(clock.now_ns() as f64 * 1e-9);
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
        for t in truth_sub.drain() {
            if control.controller.is_none() && cfg.closed_loop {
                control.controller = Some(formation_from_truth(&fleet, &t.msg));
            }
            watch.add_truth(t);
        }
        for r in map_sub.drain() {
            watch.add_map(r);
        }
        control.step();
        let live = watch.maps.last().map_or(0, |m| {
            m.vehicles
                .iter()
                .filter(|v| v.state == VehicleState::Live)
                .count()
        });
        on_progress(
            clock.now_ns() as f64 * 1e-9,
            cfg.duration_s,
            &format!(
                "{} maps, {live}/{} vehicles localized",
                watch.maps.len(),
                fleet.vehicles.len()
            ),
        );
        if started.elapsed()
            > Duration::from_secs_f64(cfg.duration_s / cfg.time_scale.max(0.05) * 4.0 + 60.0)
        {
            return Err(anyhow!("demo did not finish in time: simulator stalled"));
        }
    }
    let ran_until_s = started.elapsed().as_secs_f64();
    drain(&swarm, &map_sub, &mut watch);
    let TrialWatch {
        mut truths,
        mut maps,
        e2e,
        ..
    } = watch;
    maps.extend(map_sub.drain().into_iter().map(|r| r.msg));
    truths.extend(truth_sub.drain().into_iter().map(|r| r.msg));
    let frames_published = swarm.frames_published();
    let counts = NodeCounts::of(&swarm);
    let (sim_ticks, sim_ticks_skipped) = swarm.shutdown()?;
    let log = recorder.map(stop_recorder).transpose()?;

    let half = maps.len() / 2;
    let evaluated = &maps[half..];
    let pairs = pair_errors(&fleet, evaluated, &truths);
    let (acc, rej, twins) = verdict_counts(evaluated.last());
    let (nav_refused, nav_twins) = nav_verdicts(&maps);
    Ok(DemoSummary {
        pairs,
        frames_published,
        frames_processed: counts.processed,
        frames_dropped: counts.dropped,
        frames_lost: frames_published.saturating_sub(counts.received),
        mean_latency_ms: mean_or_nan(counts.latencies.iter().sum(), counts.latencies.len()),
        mean_end_to_end_latency_ms: mean_or_nan(e2e.0, e2e.1),
        maps_received: maps.len(),
        observations_sent: counts.observations_sent,
        edges_accepted: acc,
        edges_rejected: rej,
        flip_twins_rejected: twins,
        observations_refused_by_nav: nav_refused,
        occlusion: cfg
            .occlude
            .map(|o| occlusion::report(&fleet, &maps, &truths, &o)),
        twins_refused_by_nav: nav_twins,
        sim_ticks,
        sim_ticks_skipped,
        wall_time_s: started.elapsed().as_secs_f64(),
        startup_s,
        running_s: ran_until_s - startup_s,
        finishing_s: started.elapsed().as_secs_f64() - ran_until_s,
        log,
        interrupted_at_s,
    })
}

/// The nodes' counters, summed over the vehicles (latencies: each node's mean).
struct NodeCounts {
    processed: u64,
    dropped: u64,
    received: u64,
    observations_sent: u64,
    latencies: Vec<f64>,
}

impl NodeCounts {
    fn of(swarm: &SimulatedSwarm) -> NodeCounts {
        let sum = |f: &dyn Fn(&NodeHandle) -> u64| swarm.nodes().map(f).sum();
        NodeCounts {
            processed: sum(&|n| n.stats().frames_processed()),
            dropped: sum(&|n| n.stats().frames_dropped()),
            received: sum(&|n| n.stats().frames_in()),
            observations_sent: sum(&|n| n.stats().observations_sent.load(Ordering::Relaxed)),
            latencies: swarm
                .nodes()
                .filter_map(|n| n.stats().mean_latency_ms())
                .collect(),
        }
    }
}

/// The formation to hold: every follower's starting offset from the reference.
fn formation_from_truth(fleet: &Fleet, truth: &SimTruth) -> FormationController {
    let mut c = FormationController::line_abreast(fleet, 1.0, 0.2);
    let pose_of = |v: VehicleId| {
        truth
            .vehicles
            .iter()
            .find(|t| t.vehicle == v)
            .map(|t| t.world_from_body)
    };
    if let Some(world_from_ref) = pose_of(fleet.reference_vehicle) {
        for (v, slot) in c.slots.iter_mut() {
            if let Some(world_from_v) = pose_of(*v) {
                *slot = (world_from_ref.inverse() * world_from_v).translation.vector;
            }
        }
    }
    c
}

/// A pair this far off in rotation in one map is on a planar-flip twin, degrees.
pub const FLIP_ERROR_DEG: f64 = 10.0;

/// Mean error of every pair over `maps`. A map is the fused estimate as of its
/// newest accepted observation (the window's freshest information), so each
/// map is scored against the ground truth of that observation's capture time.
pub fn pair_errors(
    fleet: &Fleet,
    maps: &[FleetMap],
    truths: &VecDeque<SimTruth>,
) -> Vec<PairError> {
    let ids: Vec<VehicleId> = fleet.vehicles.iter().map(|v| v.id).collect();
    let views: Vec<shoal_fusion::MapView> = maps
        .iter()
        .cloned()
        .map(shoal_fusion::MapView::new)
        .collect();
    let mut out = Vec::new();
    for (i, &a) in ids.iter().enumerate() {
        for &b in &ids[i + 1..] {
            let (mut pos, mut ang, mut n) = (0.0, 0.0, 0usize);
            let (mut flipped, mut nees, mut n_nees) = (0usize, 0.0, 0usize);
            for view in &views {
                let map = view.map();
                let valid_at = map.valid_at_ns();
                // The truth of that capture's tick; a map whose tick's truth
                // was lost is not scored against a neighbouring tick's.
                let Some(truth) = truths
                    .iter()
                    .min_by_key(|t| t.stamp_ns.abs_diff(valid_at))
                    .filter(|t| {
                        t.stamp_ns.abs_diff(valid_at) <= shoal_record::truth_score::SAME_INSTANT_NS
                    })
                else {
                    continue;
                };
                let Some(rel) = view.relative(a, b) else {
                    continue;
                };
                if !rel.live {
                    continue;
                }
                let pose_of = |v: VehicleId| {
                    truth
                        .vehicles
                        .iter()
                        .find(|t| t.vehicle == v)
                        .map(|t| t.world_from_body)
                };
                let (Some(wa), Some(wb)) = (pose_of(a), pose_of(b)) else {
                    continue;
                };
                let true_a_from_b = wa.inverse() * wb;
                let d = difference(&rel.a_from_b.pose, &true_a_from_b);
                pos += d.fixed_rows::<3>(0).norm();
                let angle = d.fixed_rows::<3>(3).norm().to_degrees();
                ang += angle;
                flipped += usize::from(angle > FLIP_ERROR_DEG);
                if let Some(info) = rel.a_from_b.covariance.try_inverse() {
                    nees += (d.transpose() * info * d)[0];
                    n_nees += 1;
                }
                n += 1;
            }
            out.push(PairError {
                a,
                b,
                position_error_m: if n > 0 { pos / n as f64 } else { f64::NAN },
                angle_error_deg: if n > 0 { ang / n as f64 } else { f64::NAN },
                maps_localized: n,
                maps_evaluated: maps.len(),
                maps_flipped: flipped,
                mean_nees: if n_nees > 0 {
                    nees / n_nees as f64
                } else {
                    f64::NAN
                },
            });
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_router_takes_the_documented_port_and_says_when_it_cannot() {
        // Free: taken as asked.
        let p = free_port().unwrap();
        let (port, taken, router) = open_router(Some(p), false).unwrap();
        assert_eq!((port, taken), (p, None));
        // Held by that router now: the next one listens elsewhere and says so.
        let (other, taken2, second) = open_router(Some(p), false).unwrap();
        assert_ne!(other, p);
        assert_eq!(taken2, Some(p));
        // A client of the documented port reaches the first router.
        let client = Bus::open(&client_of(p)).unwrap();
        drop((client, second, router));
    }
}
