//! `shoal node`, `shoal fusion`, `shoal sim`: the services as standalone processes.

use super::net::{wait_for_ctrl_c, NetArgs, Ros2Args};
use anyhow::{bail, Context};
use clap::{Args, Subcommand};
use shoal_fusion::FusionParams;
use shoal_node::pipeline::PipelineParams;
use shoal_node::restore::Method;
use shoal_node::source::LocalSource;
use shoal_proto::clock::{Clock, ManualClock, WallClock};
use shoal_proto::config::Fleet;
use shoal_proto::messages::SimTruth;
use shoal_services::fusion::{FusionConfig, Placement};
use shoal_services::node::{NodeConfig, Source};
use shoal_services::sim::SimConfig;
use shoal_sim_bridge::water::WaterPresets;
use shoal_sim_bridge::world::Formation;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

fn fleet(path: &Path) -> anyhow::Result<Arc<Fleet>> {
    Ok(Arc::new(Fleet::load(path)?))
}

#[derive(Debug, Args)]
pub struct NodeArgs {
    /// Fleet file.
    #[arg(long, default_value = "configs/fleets/paper.toml")]
    fleet: PathBuf,
    /// This vehicle's ID in the fleet file.
    #[arg(long)]
    vehicle: u32,
    /// Frames from: `zenoh` (simulator or camera drivers), `images:DIR`,
    /// `video:FILE`, `camera:N` (OpenCV device index), `v4l2:/dev/videoN`
    /// (stamped with the driver's buffer time), `gst:PIPELINE` (a GStreamer
    /// pipeline ending in `appsink`, stamped with its buffer times; RTSP,
    /// UDP/RTP, files, cameras), `ros2:TOPIC` (a ROS 2
    /// `sensor_msgs/msg/Image` or `CompressedImage` topic over rmw_zenoh,
    /// domain as --ros2-domain), or `mcap:FILE` — re-run detection on
    /// this vehicle's frames of a recorded trial (`shoal record --frames`)
    /// and exit when they are done. Live sources (camera, v4l2, gst) are
    /// reopened when their stream ends or fails.
    #[arg(long, default_value = "zenoh")]
    source: String,
    /// Pace of an `mcap:FILE` source: 1 = as recorded, 4 = four times faster.
    #[arg(long, default_value_t = 1.0, value_parser = super::args::positive)]
    replay_rate: f64,
    /// Which of the vehicle's cameras a non-Zenoh source is (index in the fleet file).
    #[arg(long, default_value_t = 0)]
    camera_index: u8,
    /// Frame rate for `images:DIR`.
    #[arg(long, default_value_t = 10.0, value_parser = super::args::positive)]
    image_rate: f64,
    /// Restoration: none, clahe, dcp, udcp, hoirm.
    #[arg(long, default_value = "hoirm")]
    restore: String,
    /// Water attenuation coefficient (1/m) for restoration; default: estimated from the images.
    #[arg(long, value_parser = super::args::non_negative)]
    water: Option<f64>,
    /// ROS 2 domain of a `ros2:TOPIC` source, 0–232 (default: `ROS_DOMAIN_ID`,
    /// else the fleet file's `[ros2] domain`, else 0).
    #[arg(long, value_parser = super::net::parse_domain)]
    ros2_domain: Option<u32>,
    #[command(flatten)]
    net: NetArgs,
}

pub fn run_node(a: NodeArgs) -> anyhow::Result<()> {
    let fleet = fleet(&a.fleet)?;
    let mut log: Option<PathBuf> = None;
    let source = match a.source.split_once(':') {
        None if a.source == "zenoh" => Source::Zenoh,
        Some(("mcap", path)) => {
            let path = PathBuf::from(path);
            if !path.is_file() {
                bail!("--source mcap:{}: no such file", path.display());
            }
            if !(a.replay_rate > 0.0 && a.replay_rate.is_finite()) {
                bail!(
                    "--replay-rate {}: expected a positive number",
                    a.replay_rate
                );
            }
            log = Some(path);
            Source::Zenoh
        }
        Some(("images", dir)) => Source::Local(LocalSource::Images {
            dir: dir.into(),
            camera: a.camera_index,
            rate_hz: a.image_rate,
        }),
        Some(("video", path)) => Source::Local(LocalSource::Video {
            path: path.into(),
            camera: a.camera_index,
        }),
        Some(("camera", dev)) => Source::Local(LocalSource::Live {
            device: dev.parse().with_context(|| {
                format!("--source camera:{dev}: the device is not a number (for a device path use v4l2:{dev})")
            })?,
            camera: a.camera_index,
        }),
        Some(("v4l2", dev)) => {
            if !dev.starts_with("/dev/") {
                bail!("--source v4l2:{dev}: expected a device path such as /dev/video0");
            }
            Source::Local(LocalSource::V4l2 {
                device: dev.into(),
                camera: a.camera_index,
            })
        }
        Some(("gst", pipeline)) => {
            if let Some(problem) = shoal_node::source::gst_pipeline_problem(pipeline) {
                bail!("--source gst:{pipeline}: {problem}");
            }
            Source::Local(LocalSource::Gst {
                pipeline: pipeline.trim().to_string(),
                camera: a.camera_index,
            })
        }
        Some(("ros2", topic)) => Source::Ros2(shoal_services::ros2::Ros2ImageSource {
            domain: super::net::ros2_domain(a.ros2_domain, &fleet)?,
            topic: topic.to_string(),
            camera: a.camera_index,
        }),
        _ => bail!(
            "--source {:?}: expected zenoh, images:DIR, video:FILE, camera:N, v4l2:/dev/videoN, gst:PIPELINE, ros2:TOPIC or mcap:FILE",
            a.source
        ),
    };
    let method: Method = a.restore.parse()?;
    let mut params = PipelineParams {
        restore: method,
        ..Default::default()
    };
    params.restore_params.c_per_m = a.water;
    let bus = a.net.open()?;
    let cfg = NodeConfig {
        fleet,
        vehicle: a.vehicle,
        params,
        source,
        queue_capacity: 2,
        status_period: Duration::from_secs(1),
    };
    if let Some(path) = log {
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
            let _ = signal_hook::flag::register(sig, stop.clone());
        }
        tracing::info!(
            "node {}: re-running detection on the frames of {}",
            a.vehicle,
            path.display()
        );
        let s = shoal::redetect::redetect(&bus, cfg, &path, a.replay_rate, &stop)?;
        shoal::outln!(
            "vehicle {}: {} frames replayed, {} processed, {} dropped, {} observations published; mean pipeline {} in {:.1} s",
            a.vehicle,
            s.frames_replayed,
            s.frames_processed,
            s.frames_dropped,
            s.observations_sent,
            s.mean_latency_ms
                .map_or("n/a".to_string(), |m| format!("{m:.1} ms/frame")),
            s.wall_time_s
        );
        return Ok(());
    }
    let node = shoal_services::node::spawn(&bus, cfg)?;
    tracing::info!("node {} running; Ctrl-C to stop", a.vehicle);
    wait_for_ctrl_c(|| false);
    node.stop();
    Ok(())
}

#[derive(Debug, Args)]
pub struct FusionArgs {
    #[arg(long, default_value = "configs/fleets/paper.toml")]
    fleet: PathBuf,
    /// Run decentralized on this vehicle (publishes on shoal/<fleet>/map/<vehicle>); default: central.
    #[arg(long)]
    on_vehicle: Option<u32>,
    /// Maps per second.
    #[arg(long, default_value_t = 5.0, value_parser = super::args::positive)]
    rate: f64,
    /// Time line: `wall` (live vehicles) or `sim` (follow the simulator's ground-truth clock).
    #[arg(long, default_value = "wall")]
    clock: String,
    /// Hear the other vehicles over an acoustic-rate link: their compact
    /// packets (`shoal link`) instead of their full observations, kept 8 s
    /// (what crosses the link is old). On a vehicle, its own observations
    /// and navigation are still used in full.
    #[arg(long)]
    link: bool,
    /// Carry each localized vehicle's pose by both vehicles' odometry from
    /// its newest frame to the map's time (`NavParams::propagate_live`): for a
    /// manoeuvring fleet; on a formation holding still the compass noise costs
    /// more than it gains (docs/results.md, nav).
    #[arg(long)]
    propagate_live: bool,
    /// Solve each window as a factor graph over time: a state per vehicle
    /// and 0.1 s slot joined by its own odometry (`NavParams::odometry_factors`;
    /// docs/results.md, nav).
    #[arg(long)]
    odometry_factors: bool,
    #[command(flatten)]
    ros2: Ros2Args,
    #[command(flatten)]
    net: NetArgs,
}

#[derive(Debug, Args)]
pub struct LinkArgs {
    #[arg(long, default_value = "configs/fleets/paper.toml")]
    fleet: PathBuf,
    /// The vehicle whose observations and navigation are sent.
    #[arg(long)]
    vehicle: u32,
    /// The modem's rate for this vehicle, bit/s.
    #[arg(long, value_parser = super::args::positive)]
    rate_bps: f64,
    /// Bytes the modem adds to every packet (sync, address, CRC).
    #[arg(long, default_value_t = shoal_fusion::link::MODEM_OVERHEAD_BYTES)]
    overhead_bytes: usize,
    /// Send the vehicle's own navigation (its `nav` key) as a compact span
    /// this often, seconds; 0: never (default: at most 15 % of the modem's
    /// airtime, every 1–4 s: `shoal_fusion::link::nav_span_period_ns`).
    #[arg(long, value_parser = super::args::non_negative)]
    nav_every_s: Option<f64>,
    /// Time line of the observations' stamps: `wall` or `sim`.
    #[arg(long, default_value = "wall")]
    clock: String,
    #[command(flatten)]
    net: NetArgs,
}

pub fn run_link(a: LinkArgs) -> anyhow::Result<()> {
    let fleet = fleet(&a.fleet)?;
    let bus = a.net.open()?;
    let clock = service_clock(&a.clock, &bus, &fleet)?;
    let handle = shoal_services::link::spawn(
        &bus,
        shoal_services::link::LinkConfig {
            fleet,
            vehicle: a.vehicle,
            rate_bps: a.rate_bps,
            overhead_bytes: a.overhead_bytes,
            queue_capacity: 1024,
            nav_period_ns: a.nav_every_s.map(|s| (s * 1e9).round() as u64),
        },
        clock,
    )?;
    tracing::info!(
        "link sender of vehicle {} at {} bit/s; Ctrl-C to stop",
        a.vehicle,
        a.rate_bps
    );
    wait_for_ctrl_c(|| false);
    let s = handle.stats();
    handle.stop();
    shoal::outln!(
        "vehicle {}: {} observations offered, {} packets sent ({} of them navigation spans; {} modem bytes, {:.1} per packet), {} folded into summaries, {} expired, {} not encodable, {} on the wrong key, {} nav states refused, {} dropped",
        a.vehicle,
        s.queue.offered,
        s.packets,
        s.nav_spans,
        s.modem_bytes,
        s.modem_bytes as f64 / s.packets.max(1) as f64,
        s.queue.superseded,
        s.queue.expired,
        s.unencodable,
        s.wrong_observer,
        s.nav_refused,
        s.dropped
    );
    Ok(())
}

/// The time line a service follows: `wall`, or `sim` (the simulator's
/// ground-truth clock, followed by a thread that lives as long as the process).
fn service_clock(
    which: &str,
    bus: &shoal_bus::Bus,
    fleet: &Fleet,
) -> anyhow::Result<Arc<dyn Clock>> {
    match which {
        "wall" => Ok(Arc::new(WallClock)),
        "sim" => {
            let clock = Arc::new(ManualClock::new(0));
            let sub = bus.subscribe::<SimTruth>(&fleet.keys().truth(), 16)?;
            let c = clock.clone();
            // The simulator publishes a tick's truth after streaming its
            // frames, so observations of tick k+1 can arrive while the last
            // truth is tick k's: the clock is the latest truth plus one tick
            // period (the sim has reached at least that), never less.
            std::thread::Builder::new()
                .name("sim-clock".into())
                .spawn(move || {
                    let mut previous: Option<u64> = None;
                    loop {
                        if let Some(r) = sub.recv_timeout(Duration::from_millis(200)) {
                            let stamp = r.msg.stamp_ns;
                            let tick_ns = previous
                                .map_or(0, |p| stamp.saturating_sub(p))
                                .min(2_000_000_000);
                            previous = Some(stamp);
                            c.advance_to(stamp.saturating_add(tick_ns));
                        }
                    }
                })?;
            Ok(clock)
        }
        other => bail!("--clock {other:?}: expected wall or sim"),
    }
}

pub fn run_fusion(a: FusionArgs) -> anyhow::Result<()> {
    let fleet = fleet(&a.fleet)?;
    if let Some(v) = a.on_vehicle {
        if fleet.vehicle(v).is_none() {
            bail!("--on-vehicle {v}: no such vehicle in {}", a.fleet.display());
        }
    }
    let ros2_domain = a.ros2.domain(&fleet)?;
    let placement = a
        .on_vehicle
        .map_or(Placement::Central, Placement::OnVehicle);
    let bus = a.net.open()?;
    let clock = service_clock(&a.clock, &bus, &fleet)?;
    let ros2 = ros2_domain
        .map(|domain| {
            let cfg =
                shoal_services::ros2::Ros2Config::for_fusion(fleet.clone(), domain, placement);
            shoal_services::ros2::spawn(&bus, cfg)
        })
        .transpose()?;
    if let Some(r) = &ros2 {
        tracing::info!("ROS 2 node announced: {}", r.node_token());
    }
    let handle = shoal_services::fusion::spawn(
        &bus,
        FusionConfig {
            fleet,
            params: {
                let mut p = FusionParams::default();
                p.nav.propagate_live = a.propagate_live;
                p.nav.odometry_factors = a.odometry_factors;
                p
            },
            placement,
            rate_hz: a.rate,
            queue_capacity: 4096,
            link: a.link,
        },
        clock,
    )?;
    tracing::info!("fusion running; Ctrl-C to stop");
    wait_for_ctrl_c(|| false);
    let s = handle.stats();
    handle.stop();
    shoal::outln!(
        "fusion: {} observations received, {} admitted, {} rejected on arrival, {} aged out, {} dropped over a vehicle's window share, {} solves",
        s.received,
        s.ingested,
        s.rejected_at_ingest.total(),
        s.expired,
        s.crowded_out,
        s.solves
    );
    if let Some(r) = ros2 {
        let s = r.stats();
        r.stop();
        shoal::outln!(
            "ROS 2: {} maps as {} poses and {} /tf messages, {} observations, {} diagnostics, {} failed",
            s.maps, s.poses, s.tf, s.observations, s.diagnostics, s.failed
        );
    }
    Ok(())
}

#[derive(Debug, Args)]
pub struct SimArgs {
    #[command(subcommand)]
    cmd: Option<SimCmd>,
    #[command(flatten)]
    run: SimRunArgs,
}

#[derive(Debug, Args)]
pub struct SimRunArgs {
    #[arg(long, default_value = "configs/fleets/paper.toml")]
    fleet: PathBuf,
    /// Water attenuation coefficient, per metre (a preset of configs/water.toml).
    #[arg(long, default_value_t = 0.5, value_parser = super::args::non_negative)]
    water: f64,
    /// Water presets file (default: the built-in copy of configs/water.toml).
    #[arg(long)]
    water_presets: Option<PathBuf>,
    /// Formation: line, column, v, circle.
    #[arg(long, default_value = "line")]
    formation: String,
    #[arg(long, default_value_t = 1.75, value_parser = super::args::positive)]
    spacing: f64,
    /// Camera frames per second.
    #[arg(long, default_value_t = 2.0, value_parser = super::args::positive)]
    rate: f64,
    /// Simulated seconds (default: until Ctrl-C).
    #[arg(long, value_parser = super::args::positive)]
    duration: Option<f64>,
    #[arg(long, default_value_t = 7)]
    seed: u64,
    /// Publish no navigation data (each vehicle's simulated depth, IMU and DVL).
    #[arg(long)]
    no_nav: bool,
    /// Hide a vehicle from every camera for a span, `VEHICLE:FROM_S:TO_S`.
    #[arg(long, value_name = "V:FROM:TO")]
    occlude: Option<shoal_services::sim::Occlusion>,
    #[command(flatten)]
    net: NetArgs,
}

#[derive(Debug, Subcommand)]
pub enum SimCmd {
    /// Render one camera frame (and its clean twin) for a person to look at, through a
    /// camera profile (`--profile realistic`, `--effect NAME`; docs/water-model.md).
    Render(super::sim_render::RenderArgs),
}

fn formation(name: &str) -> anyhow::Result<Formation> {
    Ok(match name {
        "line" => Formation::Line,
        "column" => Formation::Column,
        "v" => Formation::V,
        "circle" => Formation::Circle,
        other => bail!("formation {other:?}: expected line, column, v or circle"),
    })
}

fn presets(path: &Option<PathBuf>) -> anyhow::Result<WaterPresets> {
    Ok(match path {
        Some(p) => WaterPresets::load(p)?,
        None => WaterPresets::builtin(),
    })
}

pub fn run_sim(a: SimArgs) -> anyhow::Result<()> {
    if let Some(SimCmd::Render(r)) = a.cmd {
        return super::sim_render::run(r);
    }
    let a = a.run;
    let fleet = fleet(&a.fleet)?;
    let water = presets(&a.water_presets)?.get(a.water)?;
    let bus = a.net.open()?;
    let clock = Arc::new(ManualClock::new(0));
    let sim = shoal_services::sim::spawn(
        &bus,
        SimConfig {
            fleet,
            water,
            formation: formation(&a.formation)?,
            spacing_m: a.spacing,
            seed: a.seed,
            frame_rate_hz: a.rate,
            cameras: None,
            time_scale: 1.0,
            duration_s: a.duration,
            commanded: vec![],
            nav: (!a.no_nav).then(shoal_sim_bridge::nav::NavSensorParams::default),
            hidden: a.occlude.into_iter().collect(),
            profile: None,
            // Nodes started by hand in other terminals come when they come.
            wait_for_nodes: std::time::Duration::ZERO,
        },
        clock,
    )?;
    tracing::info!("simulator running; Ctrl-C to stop");
    wait_for_ctrl_c(|| sim.finished());
    sim.stop().map_err(|e| anyhow::anyhow!(e))
}
