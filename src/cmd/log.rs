//! `shoal record`, `shoal replay`, `shoal fuse`, `shoal log info|recover`: MCAP logs of swarm trials.

use super::net::{wait_for_ctrl_c, NetArgs};
use anyhow::{bail, Context};
use clap::{Args, Subcommand};
use shoal_fusion::FusionParams;
use shoal_proto::config::Fleet;
use shoal_proto::MessageKind;
use shoal_record::{FuseOptions, RecordOptions, ReplayOptions, SolveAt};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

#[derive(Debug, Args)]
pub struct RecordArgs {
    #[arg(long, default_value = "configs/fleets/paper.toml")]
    fleet: PathBuf,
    /// Output MCAP file.
    #[arg(long)]
    out: PathBuf,
    /// Also record camera frames (raw, and as PNG for Foxglove); they dominate the size.
    #[arg(long)]
    frames: bool,
    /// At most this many frames per second per camera (0: every frame).
    #[arg(long, default_value_t = 2.0, value_parser = super::args::non_negative)]
    frame_rate: f64,
    /// At most this many Foxglove PNG images per second per camera (0: every recorded frame); PNG costs ~50 ms a frame.
    #[arg(long, default_value_t = 1.0, value_parser = super::args::non_negative)]
    image_rate: f64,
    /// Raw wire channels only, no Foxglove channels.
    #[arg(long)]
    no_foxglove: bool,
    /// `shoal`: wire + Foxglove channels (replay, fuse, log info read it);
    /// `ros2`: only the ROS 2 topics `--ros2` publishes, CDR with `ros2msg`
    /// schemas, for `ros2 bag`, rosbags and Rerun (docs/ros2.md).
    #[arg(long, default_value = "shoal", value_parser = ["shoal", "ros2"])]
    profile: String,
    /// Water attenuation coefficient of the trial, per metre (file metadata).
    #[arg(long, value_parser = super::args::non_negative)]
    water: Option<f64>,
    /// Close a chunk at least this often (milliseconds): a killed recorder loses at most this much.
    #[arg(long, default_value_t = 1000)]
    flush_ms: u64,
    /// Stop after this many seconds (default: Ctrl-C).
    #[arg(long, value_parser = super::args::positive)]
    duration: Option<f64>,
    #[command(flatten)]
    net: NetArgs,
}

pub fn run_record(a: RecordArgs) -> anyhow::Result<()> {
    let fleet = Arc::new(Fleet::load(&a.fleet)?);
    let bus = a.net.open()?;
    let opts = RecordOptions {
        frames: a.frames,
        frame_rate_limit_hz: (a.frame_rate > 0.0).then_some(a.frame_rate),
        image_rate_limit_hz: (a.image_rate > 0.0).then_some(a.image_rate),
        foxglove: !a.no_foxglove,
        ros2_profile: a.profile == "ros2",
        flush_interval: Duration::from_millis(a.flush_ms.max(1)),
        water_c_per_m: a.water,
        ..RecordOptions::default()
    };
    let rec = shoal_services::recorder::Recorder::spawn(&bus, fleet, &a.out, opts)?;
    tracing::info!("recording to {}; Ctrl-C to stop", a.out.display());
    let started = std::time::Instant::now();
    wait_for_ctrl_c(|| {
        rec.failed()
            || a.duration
                .is_some_and(|d| started.elapsed().as_secs_f64() >= d)
    });
    let s = rec.stop()?;
    shoal::outln!(
        "wrote {} ({:.2} MB, {} wire messages, {} dropped, {} frames rate-limited, {} undecodable, {} PNG images dropped) in {:.1} s, writer CPU {:.2} s",
        s.path.display(),
        s.file_bytes as f64 / 1e6,
        s.wire_messages,
        s.dropped,
        s.frames_rate_limited,
        s.undecodable,
        s.images_dropped,
        s.wall_time_s,
        s.writer_cpu_s
    );
    for (topic, c) in &s.channels {
        shoal::outln!(
            "  {topic:<44} {:>7} messages {:>10.3} MB",
            c.messages,
            c.bytes as f64 / 1e6
        );
    }
    Ok(())
}

#[derive(Debug, Args)]
pub struct ReplayArgs {
    /// The MCAP log.
    #[arg(value_name = "LOG.mcap")]
    file: PathBuf,
    /// Speed factor (2.0: twice as fast; `max`: as fast as possible).
    #[arg(long, default_value = "1.0")]
    rate: String,
    /// Start this many seconds into the log.
    #[arg(long, value_parser = super::args::non_negative)]
    from: Option<f64>,
    /// Stop this many seconds into the log.
    #[arg(long, value_parser = super::args::non_negative)]
    to: Option<f64>,
    /// Only these message kinds (comma-separated: observation, map, frame, truth, status, command, nav, link).
    #[arg(long, value_delimiter = ',')]
    only: Option<Vec<String>>,
    #[command(flatten)]
    net: NetArgs,
}

fn kind_of(name: &str) -> anyhow::Result<MessageKind> {
    Ok(match name {
        "observation" | "obs" => MessageKind::Observation,
        "map" => MessageKind::FleetMap,
        "frame" => MessageKind::CameraFrame,
        "truth" => MessageKind::SimTruth,
        "status" => MessageKind::NodeStatus,
        "command" | "cmd" => MessageKind::VehicleCommand,
        "nav" => MessageKind::NavState,
        "link" => MessageKind::LinkPacket,
        other => bail!(
            "message kind {other:?}: expected observation, map, frame, truth, status, command, nav or link"
        ),
    })
}

pub fn run_replay(a: ReplayArgs) -> anyhow::Result<()> {
    let rate = match a.rate.as_str() {
        "max" => f64::INFINITY,
        r => r
            .parse::<f64>()
            .ok()
            .filter(|r| *r > 0.0)
            .with_context(|| format!("--rate {r:?}: expected a positive number or `max`"))?,
    };
    let kinds = a
        .only
        .as_ref()
        .map(|ks| {
            ks.iter()
                .map(|k| kind_of(k))
                .collect::<anyhow::Result<Vec<_>>>()
        })
        .transpose()?;
    let bus = a.net.open()?;
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        let _ = signal_hook::flag::register(sig, stop.clone());
    }
    let s = shoal_services::replay::replay(
        &bus,
        &a.file,
        &ReplayOptions {
            rate,
            from_s: a.from,
            to_s: a.to,
            kinds,
            ..ReplayOptions::default()
        },
        &stop,
    )?;
    shoal::outln!(
        "replayed {} messages ({:.2} MB) covering {:.1} s of log in {:.1} s (latest message {:.1} ms behind schedule){}",
        s.messages,
        s.bytes as f64 / 1e6,
        s.log_span_s,
        s.wall_time_s,
        s.max_late_ms,
        if stop.load(Ordering::Relaxed) { ", interrupted" } else { "" }
    );
    Ok(())
}

#[derive(Debug, Args)]
pub struct FuseArgs {
    /// The MCAP log.
    #[arg(value_name = "LOG.mcap")]
    file: PathBuf,
    /// Output MCAP with the re-fused map track.
    #[arg(long)]
    out: PathBuf,
    /// Solve at this rate of the log's clock instead of at the original maps' stamps.
    #[arg(long, value_parser = super::args::positive)]
    rate: Option<f64>,
    /// Fleet file (default: the one attached to the log).
    #[arg(long)]
    fleet: Option<PathBuf>,
    /// Also write the summary as JSON.
    #[arg(long)]
    summary_json: Option<PathBuf>,
    /// Leave the vehicles' nav states out of fusion (they are still copied):
    /// the same observations settled by votes alone, for comparison.
    #[arg(long)]
    no_nav: bool,
    /// Carry each localized vehicle's pose by odometry to the map's time
    /// (`NavParams::propagate_live`, as `shoal fusion --propagate-live`).
    #[arg(long)]
    propagate_live: bool,
    /// Solve each window as a factor graph over time with the vehicles'
    /// odometry between-factors (`NavParams::odometry_factors`, as `shoal
    /// fusion --odometry-factors`); `--g2o` then writes that graph.
    #[arg(long)]
    odometry_factors: bool,
    /// Also write the last map's pose graph as g2o (for g2o, gtsam, Ceres;
    /// format in `shoal_fusion::export`).
    #[arg(long, value_name = "FILE.g2o")]
    g2o: Option<PathBuf>,
    /// Fusion's sliding window, seconds (default: the services', 2 s): how
    /// the maps of a log change with a shorter or longer memory.
    #[arg(long, value_name = "S", value_parser = super::args::positive)]
    window: Option<f64>,
}

pub fn run_fuse(a: FuseArgs) -> anyhow::Result<()> {
    let mut params = FusionParams::default();
    params.nav.enabled = !a.no_nav;
    params.nav.propagate_live = a.propagate_live;
    params.nav.odometry_factors = a.odometry_factors;
    if let Some(w) = a.window {
        params.window_s = w;
    }
    let opts = FuseOptions {
        params,
        solve_at: a.rate.map_or(SolveAt::OriginalMaps, SolveAt::RateHz),
        fleet: a.fleet.as_deref().map(Fleet::load).transpose()?,
    };
    let started = std::time::Instant::now();
    let s = shoal_record::refuse(&a.file, &a.out, &opts)?;
    shoal::outln!(
        "re-fused {} observations ({} rejected on arrival) into {} maps in {:.2} s → {}",
        s.observations,
        s.rejected_at_ingest,
        s.maps_written,
        started.elapsed().as_secs_f64(),
        s.output.display()
    );
    if s.nav_states > 0 {
        shoal::outln!(
            "with {} nav states of the vehicles ({} refused)",
            s.nav_states,
            s.nav_refused
        );
    }
    if let Some(path) = &a.g2o {
        let graph = s.last_graph.as_ref().ok_or_else(|| {
            anyhow::anyhow!("the last map has no pose graph to export (nothing connected)")
        })?;
        let mut text = Vec::new();
        graph.write_g2o(&mut text)?;
        std::fs::write(path, text).with_context(|| format!("cannot write {}", path.display()))?;
        shoal::outln!(
            "pose graph of the last map: {} vehicles, {} constraints → {}",
            graph.initial.len(),
            graph.constraints.len(),
            path.display()
        );
    }
    if let Some(t) = &s.truth {
        shoal::outln!(
            "against the log's ground truth: {} maps, {} with a vehicle on a planar-flip twin (> {}°), position error mean {:.1} mm (max {:.1} mm), mean NEES {:.1} (6 honest)",
            t.maps_scored,
            t.maps_flipped,
            shoal_record::truth_score::FLIP_ERROR_DEG,
            t.mean_position_error_m * 1e3,
            t.max_position_error_m * 1e3,
            t.mean_nees
        );
        if t.maps_without_truth > 0 {
            shoal::outln!(
                "{} maps not scored: the log lost the truth of their capture's tick",
                t.maps_without_truth
            );
        }
    }
    if s.undecodable > 0 {
        shoal::outln!(
            "{} envelopes of the log did not decode and were left out",
            s.undecodable
        );
    }
    if let Some(d) = &s.input_damage {
        shoal::outln!("the input log is damaged: {d}");
    }
    let c = &s.comparison;
    if c.maps_compared > 0 {
        shoal::outln!(
            "against the {} original maps: {} estimates compared, position difference mean {:.2} mm, max {:.2} mm, angle max {:.3}°",
            s.original_maps,
            c.estimates_compared,
            c.mean_position_diff_m * 1e3,
            c.max_position_diff_m * 1e3,
            c.max_angle_diff_deg
        );
    }
    if let Some(p) = a.summary_json {
        std::fs::write(&p, serde_json::to_string_pretty(&s)?)
            .with_context(|| format!("cannot write {}", p.display()))?;
    }
    Ok(())
}

#[derive(Debug, Subcommand)]
pub enum LogCmd {
    /// Vehicles, duration, messages per channel, detection rate and gaps of a log.
    Info {
        #[arg(value_name = "LOG.mcap")]
        file: PathBuf,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Rewrite a log whose recorder was killed (no summary) with every readable record and a proper summary.
    Recover {
        #[arg(value_name = "LOG.mcap")]
        file: PathBuf,
        #[arg(long)]
        out: PathBuf,
    },
}

pub fn run_log(c: LogCmd) -> anyhow::Result<()> {
    match c {
        LogCmd::Info { file, json } => {
            let i = shoal_record::info(&file)?;
            if json {
                shoal::outln!("{}", serde_json::to_string_pretty(&i)?);
            } else {
                shoal::out!("{i}");
            }
        }
        LogCmd::Recover { file, out } => {
            let r = shoal_record::recover(&file, &out)?;
            shoal::outln!(
                "recovered {} messages on {} channels from {} chunks into {}{}",
                r.messages,
                r.channels,
                r.chunks_read,
                out.display(),
                r.damage.as_ref().map_or_else(
                    || " (the input was intact)".to_string(),
                    |d| format!(" (input: {d})")
                )
            );
            for s in &r.skipped {
                shoal::outln!(
                    "  skipped bytes {}..{} of the input: {}",
                    s.offset,
                    s.offset + s.bytes,
                    s.reason
                );
            }
        }
    }
    Ok(())
}
