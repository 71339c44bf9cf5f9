//! The simulator on Zenoh (`shoal sim`): steps the swarm world, renders every
//! selected camera of every vehicle, and publishes frames, ground truth and
//! the simulation clock exactly as a real fleet's camera drivers would; takes
//! vehicle commands from formation controllers.
//!
//! **Plugging in another simulator** (Gazebo, Stonefish, HoloOcean): publish,
//! with any Zenoh binding, envelopes (`docs/wire.md`) of
//! - `CameraFrame` (Mono8) on `shoal/<fleet>/<vehicle>/cam/<k>/frame` for every
//!   camera `k` of the fleet file, stamped with the simulation time;
//! - optionally `SimTruth` on `shoal/<fleet>/sim/truth` (for error figures);
//! - optionally each vehicle's `NavState` on `shoal/<fleet>/<vehicle>/nav`
//!   (depth, roll/pitch, velocity: what its own sensors say), which fusion
//!   uses to settle planar flips by gravity;
//!
//! and subscribe to `VehicleCommand` on `shoal/<fleet>/*/cmd`. Nothing else in
//! shoal knows which simulator is running. The world and the renderer are
//! `shoal_sim_bridge`'s.

use shoal_bus::{Bus, BusError, Publisher, Subscription};
use shoal_proto::clock::ManualClock;
use shoal_proto::config::Fleet;
use shoal_proto::geometry::Pose;
use shoal_proto::messages::{
    CameraFrame, CameraInfo, PixelFormat, SimTruth, VehicleCommand, VehicleId,
};
use shoal_proto::NavState;
use shoal_proto::{KeyKind, Keys};
use shoal_sim_bridge::nav::{NavSensorParams, NavSensors};
use shoal_sim_bridge::profile::CameraProfile;
use shoal_sim_bridge::render::motion::Timeline;
use shoal_sim_bridge::render::realistic::render_profiled;
use shoal_sim_bridge::render::{fleet_camera, render_fleet_view, RenderOutput, Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;
use shoal_sim_bridge::world::{Formation, Mode, SwarmWorld};
use shoal_sim_bridge::SimError;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

#[derive(Debug, Clone)]
pub struct SimConfig {
    pub fleet: Arc<Fleet>,
    pub water: WaterParams,
    pub formation: Formation,
    pub spacing_m: f64,
    pub seed: u64,
    /// Camera frames per simulated second (every selected camera).
    pub frame_rate_hz: f64,
    /// Names of the cameras to render (`None`: all of each vehicle's cameras).
    pub cameras: Option<Vec<String>>,
    /// Simulated seconds per wall-clock second; 0 runs as fast as rendering allows.
    pub time_scale: f64,
    /// Stop after this much simulated time (`None`: until stopped).
    pub duration_s: Option<f64>,
    /// Vehicles driven by commands from the start (closed loop).
    pub commanded: Vec<VehicleId>,
    /// Each vehicle's navigation sensors, published every tick on its nav
    /// key (`None`: no nav data, as from vehicles without it).
    pub nav: Option<NavSensorParams>,
    /// Vehicles hidden for a while: no other camera sees them and their own
    /// cameras publish nothing (murk, a rock, a blinded rig); their nav goes on.
    pub hidden: Vec<Occlusion>,
    /// The camera every frame is rendered through (issue #16: motion blur
    /// and rolling shutter over the swarm's own motion, the port, lamps,
    /// marine snow, PSF, exposure, compression; `docs/water-model.md`), its
    /// seed drawn already; `None`: the ideal renderer. A frame through a
    /// profile is stamped, as a camera driver stamps it, at the tick that
    /// triggered it: the start of its exposure (its middle row's mid-exposure
    /// comes later by the exposure and line times; part of the error
    /// measured). The nodes should
    /// hold the calibration a lab would have for such a camera, not the
    /// renderer's (the demo's `--profile`).
    pub profile: Option<CameraProfile>,
    /// Before the first tick, wait up to this long until every vehicle whose
    /// cameras are rendered has a node alive (its liveliness token, declared
    /// after its frame subscriptions on the same session, so the router knows
    /// them by then) and each rendered camera's publisher knows of a
    /// subscriber (else its session does not send), so that the first frames
    /// are not published to no one; the clock starts after (zero: start at
    /// once). Either alone lost frames: a recorder subscribed to every key
    /// matches at once, and the token can arrive before the subscriptions.
    pub wait_for_nodes: Duration,
}

/// Vehicle `vehicle`'s camera in the swarm world over a frame's exposure,
/// the vehicles hidden at each instant left out of the scene (the
/// profile's renderer steps a copy of the world through the exposure).
struct SimTimeline<'a> {
    fleet: &'a Fleet,
    world: SwarmWorld,
    vehicle: VehicleId,
    camera_index: u8,
    hidden: &'a [Occlusion],
}

impl Timeline for SimTimeline<'_> {
    fn at(&self, dt_s: f64) -> Result<(Pose, Scene), SimError> {
        let mut world = self.world.clone();
        world.step(dt_s);
        let t_s = world.time_s();
        let truth = world.truth();
        let (_, world_from_camera) =
            fleet_camera(self.fleet, &truth, self.vehicle, self.camera_index)?;
        let seen: Vec<_> = truth
            .into_iter()
            .filter(|t| !self.hidden.iter().any(|o| o.covers(t.vehicle, t_s)))
            .collect();
        Ok((world_from_camera, Scene::from_fleet(self.fleet, &seen)))
    }
}

/// One camera's frame triggered at the world's present (through
/// `cfg.profile` when set), its visible markers labelled.
fn render_camera(
    renderer: &mut Renderer,
    cfg: &SimConfig,
    world: &SwarmWorld,
    seen: &[shoal_proto::VehicleTruth],
    (v, k): (VehicleId, u8),
    tick: u64,
    seed: u64,
) -> Result<RenderOutput, SimError> {
    let t_s = world.time_s();
    let Some(profile) = &cfg.profile else {
        return render_fleet_view(
            renderer, &cfg.fleet, seen, v, k, &cfg.water, t_s, tick, seed,
        );
    };
    let (camera, _) = fleet_camera(&cfg.fleet, seen, v, k)?;
    let timeline = SimTimeline {
        fleet: &cfg.fleet,
        world: world.clone(),
        vehicle: v,
        camera_index: k,
        hidden: &cfg.hidden,
    };
    let f = render_profiled(
        renderer,
        profile,
        &camera.model,
        camera.port.as_ref(),
        &timeline,
        &cfg.water,
        t_s,
        seed,
    )?;
    let mut out = f.output;
    for vm in &mut out.visible {
        vm.observer = v;
        vm.camera = k;
        vm.frame_seq = tick;
    }
    Ok(out)
}

/// One vehicle out of every camera's sight from `from_s` to `to_s` of simulated time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Occlusion {
    pub vehicle: VehicleId,
    pub from_s: f64,
    pub to_s: f64,
}

impl Occlusion {
    pub fn covers(&self, vehicle: VehicleId, t_s: f64) -> bool {
        vehicle == self.vehicle && (self.from_s..self.to_s).contains(&t_s)
    }
}

impl std::str::FromStr for Occlusion {
    type Err = String;
    /// `VEHICLE:FROM:TO` (seconds of simulated time), e.g. `17:5:15`.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let bad = || format!("{s:?}: expected VEHICLE:FROM_S:TO_S, e.g. 17:5:15");
        let parts: Vec<&str> = s.split(':').collect();
        let [v, from, to] = parts.as_slice() else {
            return Err(bad());
        };
        let vehicle = v.trim().parse().map_err(|_| bad())?;
        let (from_s, to_s): (f64, f64) = (
            from.trim().parse().map_err(|_| bad())?,
            to.trim().parse().map_err(|_| bad())?,
        );
        if !(from_s.is_finite() && to_s.is_finite() && from_s >= 0.0 && to_s > from_s) {
            return Err(format!(
                "{s:?}: the span must be finite, from ≥ 0 and to > from"
            ));
        }
        Ok(Occlusion {
            vehicle,
            from_s,
            to_s,
        })
    }
}

/// Counters of a running simulator.
#[derive(Debug, Default)]
pub struct SimStats {
    pub ticks: AtomicU64,
    pub frames_published: AtomicU64,
    pub nav_published: AtomicU64,
    /// Ticks whose frames were not rendered because rendering fell behind the wall clock.
    pub ticks_skipped: AtomicU64,
    pub commands_applied: AtomicU64,
    pub commands_rejected: AtomicU64,
    /// Sum of render time (µs) and count, for the mean.
    pub render_us: AtomicU64,
}

pub struct SimHandle {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<Result<(), String>>>,
    stats: Arc<SimStats>,
    finished: Arc<AtomicBool>,
}

impl std::fmt::Debug for SimHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimHandle")
            .field("stats", &self.stats)
            .finish()
    }
}

impl SimHandle {
    pub fn stats(&self) -> &Arc<SimStats> {
        &self.stats
    }
    /// True once `duration_s` of simulated time has been run.
    pub fn finished(&self) -> bool {
        self.finished.load(Ordering::Relaxed)
    }
    /// Stop and report the loop's error, if it failed.
    pub fn stop(mut self) -> Result<(), String> {
        self.stop.store(true, Ordering::Relaxed);
        match self.thread.take().map(|t| t.join()) {
            Some(Ok(r)) => r,
            Some(Err(_)) => Err("simulator thread panicked".into()),
            None => Ok(()),
        }
    }
}

impl Drop for SimHandle {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            shoal_bus::join_reporting(t);
        }
    }
}

/// A selected camera: (vehicle, camera index, its calibration, publisher).
type SimCamera = (VehicleId, u8, CameraInfo, Publisher<CameraFrame>);

/// Every camera of the fleet that `cfg.cameras` selects (all when unset), with its publisher.
fn selected_cameras(bus: &Bus, cfg: &SimConfig, keys: &Keys) -> Result<Vec<SimCamera>, BusError> {
    let mut cams: Vec<SimCamera> = Vec::new();
    for v in &cfg.fleet.vehicles {
        for c in &v.cameras {
            let selected = cfg
                .cameras
                .as_ref()
                .is_none_or(|names| names.iter().any(|n| n == &c.name));
            if selected {
                let info = CameraInfo {
                    model: c.model,
                    body_from_camera: c.body_from_camera,
                };
                cams.push((
                    v.id,
                    c.index,
                    info,
                    bus.publisher(keys.frame(v.id, c.index))?,
                ));
            }
        }
    }
    Ok(cams)
}

/// Every vehicle's simulated nav sensors and the publisher of its nav key.
struct NavPublishers {
    sensors: NavSensors,
    publishers: Vec<(VehicleId, Publisher<NavState>)>,
}

impl NavPublishers {
    /// What each vehicle's sensors say of `truth` at `stamp_ns`, published.
    fn publish(&mut self, truth: &[shoal_proto::VehicleTruth], stamp_ns: u64, stats: &SimStats) {
        for (v, publisher) in &self.publishers {
            let Some(t) = truth.iter().find(|t| t.vehicle == *v) else {
                continue;
            };
            match publisher.put(&self.sensors.measure(t, stamp_ns)) {
                Ok(()) => {
                    stats.nav_published.fetch_add(1, Ordering::Relaxed);
                }
                Err(e) => tracing::warn!("simulator: {e}"),
            }
        }
    }
}

/// The nav sensors of `cfg` (`None` when it has none).
fn nav_sensors(bus: &Bus, cfg: &SimConfig, keys: &Keys) -> Result<Option<NavPublishers>, BusError> {
    let Some(p) = cfg.nav else {
        return Ok(None);
    };
    let sensors = NavSensors::new(p, cfg.seed)
        .map_err(|e| BusError::ConfigValue(format!("simulator nav sensors: {e}")))?;
    let mut publishers = Vec::new();
    for v in &cfg.fleet.vehicles {
        publishers.push((v.id, bus.publisher(keys.nav(v.id))?));
    }
    Ok(Some(NavPublishers {
        sensors,
        publishers,
    }))
}

/// Sleep until simulated time `t_s` is due on the wall clock (scaled by
/// `cfg.time_scale`; 0 runs unpaced); true when already more than one tick
/// (`dt`) behind, so the tick's rendering is skipped.
fn pace(cfg: &SimConfig, started: Instant, t_s: f64, dt: f64) -> bool {
    if cfg.time_scale > 0.0 {
        let due = Duration::from_secs_f64(t_s / cfg.time_scale);
        let now = started.elapsed();
        if now < due {
            std::thread::sleep(due - now);
            false
        } else {
            now - due > Duration::from_secs_f64(dt / cfg.time_scale)
        }
    } else {
        false
    }
}

/// The vehicles whose node is alive, watched while the first tick waits for
/// them ([`SimConfig::wait_for_nodes`]).
struct NodeWait {
    alive: Arc<std::sync::Mutex<std::collections::BTreeSet<VehicleId>>>,
    until: Instant,
    _watch: shoal_bus::Declaration,
}

impl NodeWait {
    fn watch(bus: &Bus, keys: &Keys, longest: Duration) -> Result<Option<NodeWait>, BusError> {
        if longest.is_zero() {
            return Ok(None);
        }
        let alive: Arc<std::sync::Mutex<std::collections::BTreeSet<VehicleId>>> = Arc::default();
        let (alive2, keys2) = (alive.clone(), keys.clone());
        let watch = bus.watch_liveliness(&keys.all_alive(), move |key, up| {
            if let (Ok(KeyKind::Alive { vehicle }), Ok(mut a)) = (keys2.parse(key), alive2.lock()) {
                if up {
                    a.insert(vehicle);
                } else {
                    a.remove(&vehicle);
                }
            }
        })?;
        Ok(Some(NodeWait {
            alive,
            until: Instant::now() + longest,
            _watch: watch,
        }))
    }

    /// Until every camera's vehicle has a node alive and its publisher knows
    /// of a subscriber, the time is up, or `stop`.
    fn wait(self, cams: &[SimCamera], stop: &AtomicBool) {
        let ready = |c: &SimCamera| {
            self.alive.lock().is_ok_and(|a| a.contains(&c.0)) && c.3.has_subscribers()
        };
        while Instant::now() < self.until
            && !stop.load(Ordering::Relaxed)
            && !cams.iter().all(ready)
        {
            std::thread::sleep(Duration::from_millis(2));
        }
    }
}

/// Start the simulator on `bus`; `clock` follows simulation time.
pub fn spawn(bus: &Bus, cfg: SimConfig, clock: Arc<ManualClock>) -> Result<SimHandle, BusError> {
    let keys = cfg.fleet.keys();
    let mut world = SwarmWorld::new(&cfg.fleet, cfg.formation, cfg.spacing_m, cfg.seed)
        .map_err(|e| BusError::ConfigValue(format!("simulator: {e}")))?;
    for &v in &cfg.commanded {
        if let Err(e) = world.set_mode(v, Mode::Commanded) {
            tracing::warn!("simulator: {e}");
        }
    }
    let cams = selected_cameras(bus, &cfg, &keys)?;
    let truth_pub: Publisher<SimTruth> = bus.publisher(keys.truth())?;
    let mut nav = nav_sensors(bus, &cfg, &keys)?;
    let commands: Subscription<VehicleCommand> = bus.subscribe(&keys.all_commands(), 64)?;
    let nodes = NodeWait::watch(bus, &keys, cfg.wait_for_nodes)?;
    let stop = Arc::new(AtomicBool::new(false));
    let finished = Arc::new(AtomicBool::new(false));
    let stats = Arc::new(SimStats::default());
    let (stop2, finished2, stats2) = (stop.clone(), finished.clone(), stats.clone());
    let bus = bus.clone();
    let thread = std::thread::Builder::new()
        .name("sim".into())
        .spawn(move || -> Result<(), String> {
            let _session = bus;
            let mut renderer = Renderer::new();
            let dt = 1.0 / cfg.frame_rate_hz.max(0.1);
            if let Some(nodes) = nodes {
                nodes.wait(&cams, &stop2);
            }
            let started = Instant::now();
            let mut tick = 0u64;
            while !stop2.load(Ordering::Relaxed) {
                for r in commands.drain() {
                    let arrived_on = keys.parse(&r.key);
                    let ok = matches!(arrived_on, Ok(KeyKind::Command { vehicle }) if vehicle == r.msg.vehicle)
                        && world.apply_command(&r.msg).is_ok();
                    let counter = if ok { &stats2.commands_applied } else { &stats2.commands_rejected };
                    counter.fetch_add(1, Ordering::Relaxed);
                }
                if tick > 0 {
                    world.step(dt);
                }
                let t_s = world.time_s();
                let stamp_ns = world.time_ns();
                let truth = world.truth();
                // Pace to the wall clock; skip rendering (not time) when behind.
                let behind = pace(&cfg, started, t_s, dt);
                // The frames of this tick are captured now: time has reached their stamp.
                clock.advance_to(stamp_ns);
                // The vehicles' own sensors first, so fusion has them when the frames' observations arrive.
                if let Some(nav) = nav.as_mut() {
                    nav.publish(&truth, stamp_ns, &stats2);
                }
                let mut visible = Vec::new();
                if behind {
                    stats2.ticks_skipped.fetch_add(1, Ordering::Relaxed);
                } else {
                    let hidden = |v: VehicleId| cfg.hidden.iter().any(|o| o.covers(v, t_s));
                    let seen: Vec<_> = truth.iter().filter(|t| !hidden(t.vehicle)).cloned().collect();
                    for (v, k, info, publisher) in &cams {
                        if hidden(*v) {
                            continue;
                        }
                        let seed = cfg.seed ^ (tick << 20) ^ ((*v as u64) << 8) ^ *k as u64;
                        let t0 = Instant::now();
                        let out = render_camera(&mut renderer, &cfg, &world, &seen, (*v, *k), tick, seed)
                            .map_err(|e| format!("rendering vehicle {v} camera {k}: {e}"))?;
                        stats2.render_us.fetch_add(t0.elapsed().as_micros() as u64, Ordering::Relaxed);
                        let frame = CameraFrame {
                            vehicle: *v,
                            camera: *k,
                            seq: tick,
                            stamp_ns,
                            info: *info,
                            format: PixelFormat::Mono8,
                            data: out.image.data,
                        };
                        match publisher.put(&frame) {
                            Ok(()) => {
                                stats2.frames_published.fetch_add(1, Ordering::Relaxed);
                            }
                            Err(e) => tracing::warn!("simulator: {e}"),
                        }
                        visible.extend(out.visible);
                    }
                }
                let msg = SimTruth {
                    stamp_ns,
                    tick,
                    water_c_per_m: cfg.water.c_per_m,
                    vehicles: truth,
                    visible,
                };
                if let Err(e) = truth_pub.put(&msg) {
                    tracing::warn!("simulator: {e}");
                }
                stats2.ticks.fetch_add(1, Ordering::Relaxed);
                tick += 1;
                if cfg.duration_s.is_some_and(|d| t_s >= d) {
                    finished2.store(true, Ordering::Relaxed);
                    break;
                }
            }
            Ok(())
        })
        .map_err(|source| BusError::Thread {
        what: "simulator",
        source,
    })?;
    Ok(SimHandle {
        stop,
        thread: Some(thread),
        stats,
        finished,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeSet;

    fn paper_fleet() -> Fleet {
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/fleets/paper.toml");
        Fleet::load(&path).expect("the paper fleet")
    }

    #[test]
    fn a_vehicle_hidden_during_part_of_an_exposure_is_left_out_of_those_instants_only() {
        let fleet = paper_fleet();
        let world = SwarmWorld::new(&fleet, Formation::Line, 1.75, 1).expect("world");
        let hidden = [Occlusion {
            vehicle: 15,
            from_s: 0.0,
            to_s: 0.02,
        }];
        let timeline = SimTimeline {
            fleet: &fleet,
            world,
            vehicle: 10,
            camera_index: 0,
            hidden: &hidden,
        };
        let in_scene = |dt_s: f64| {
            let (_, scene) = timeline.at(dt_s).expect("an instant of the exposure");
            let markers: BTreeSet<VehicleId> = scene.markers.iter().map(|m| m.owner).collect();
            let hulls: BTreeSet<VehicleId> = scene.hulls.iter().map(|h| h.vehicle).collect();
            (markers, hulls)
        };
        let (markers, hulls) = in_scene(0.01);
        assert!(
            !markers.contains(&15) && !hulls.contains(&15),
            "{markers:?} {hulls:?}"
        );
        assert!(
            markers.contains(&17) && hulls.contains(&10),
            "{markers:?} {hulls:?}"
        );
        let (markers, hulls) = in_scene(0.03);
        assert!(
            markers.contains(&15) && hulls.contains(&15),
            "{markers:?} {hulls:?}"
        );
    }
}
