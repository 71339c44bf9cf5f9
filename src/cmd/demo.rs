use anyhow::Context;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use shoal::demo::{run_until, DemoConfig};
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Fleet file (default: the paper's three vehicles, built in).
    #[arg(long)]
    fleet: Option<PathBuf>,
    /// Water attenuation coefficient, per metre (the paper's swarm trial: 0.5).
    #[arg(long, default_value_t = 0.5, value_parser = super::args::non_negative)]
    water: f64,
    /// Simulated seconds to run.
    #[arg(long, default_value_t = 20.0, value_parser = super::args::positive)]
    duration: f64,
    /// Camera frames per simulated second (each of the five cameras of each vehicle).
    #[arg(long, default_value_t = 2.0, value_parser = super::args::positive)]
    rate: f64,
    /// Simulated seconds per wall-clock second. At 1 (real time) the simulator
    /// skips the ticks it cannot render in time and says how many; on a busy
    /// machine `--time-scale 0.5` (or `--rate 1`) lets rendering keep up.
    /// Default: 1, or 0.1 through a camera profile (each of its frames takes
    /// ~0.3 s to render on two cores).
    #[arg(long, value_parser = super::args::positive)]
    time_scale: Option<f64>,
    /// Render only these cameras (comma-separated names, e.g. `port,starboard`).
    #[arg(long, value_delimiter = ',')]
    cameras: Option<Vec<String>>,
    /// Spacing between neighbours, metres.
    #[arg(long, default_value_t = 1.75, value_parser = super::args::positive)]
    spacing: f64,
    #[arg(long, default_value_t = 7)]
    seed: u64,
    /// Let the followers drift instead of steering them with the formation controller.
    #[arg(long)]
    open_loop: bool,
    /// MCAP log of the run (opens in Foxglove; `shoal log info`, `shoal replay`, `shoal fuse` read it).
    #[arg(long, default_value = "out/demo.mcap")]
    mcap: PathBuf,
    /// Write no log.
    #[arg(long)]
    no_mcap: bool,
    /// Include camera frames in the log (about 0.8 MB each).
    #[arg(long)]
    mcap_frames: bool,
    /// Also write the figures as JSON.
    #[arg(long)]
    summary_json: Option<PathBuf>,
    /// Port of the ground-station page (http://127.0.0.1:PORT/ during the run).
    #[arg(long, default_value_t = 8080)]
    station_port: u16,
    /// Port of the station's Foxglove live server.
    #[arg(long, default_value_t = 8765)]
    foxglove_port: u16,
    /// Start no ground station.
    #[arg(long)]
    no_station: bool,
    /// The vehicles publish no navigation data (depth, IMU, DVL): fusion
    /// settles planar flips by votes and the previous map alone.
    #[arg(long)]
    no_nav: bool,
    /// Hide a vehicle from every camera for a span, `VEHICLE:FROM_S:TO_S`
    /// (e.g. `17:5:15`); the figures then say how the map kept it.
    #[arg(long, value_name = "V:FROM:TO")]
    occlude: Option<shoal_services::sim::Occlusion>,
    /// Loopback port of the demo's Zenoh router, where `shoal station`,
    /// `shoal record` or a Python/ROS 2 client in another terminal attach
    /// (when taken, a free port is used and printed; 0: any free port).
    #[arg(long, default_value_t = 7447)]
    port: u16,
    #[command(flatten)]
    ros2: super::net::Ros2Args,
    #[command(flatten)]
    profile: shoal::eval::profiles::ProfileArgs,
}

/// The default time scale through a camera profile: its frames (motion
/// blur's sub-frames, marine snow, the port's rays, the codec) take ~0.3 s
/// each to render here, 15 of them a tick.
const PROFILE_TIME_SCALE: f64 = 0.1;

pub fn run_demo(a: DemoArgs) -> anyhow::Result<()> {
    let mut cfg = DemoConfig {
        fleet: a.fleet,
        water_c_per_m: a.water,
        duration_s: a.duration,
        frame_rate_hz: a.rate,
        cameras: a.cameras,
        spacing_m: a.spacing,
        seed: a.seed,
        time_scale: a.time_scale.unwrap_or(1.0),
        progress: true,
        closed_loop: !a.open_loop,
        log: (!a.no_mcap).then_some(a.mcap),
        log_frames: a.mcap_frames,
        station: (!a.no_station).then(|| shoal_station::StationConfig {
            http_port: a.station_port,
            foxglove_port: Some(a.foxglove_port),
            ..Default::default()
        }),
        nav: !a.no_nav,
        occlude: a.occlude,
        router_port: Some(a.port),
        ros2: None,
        profile: None,
    };
    cfg.profile = a
        .profile
        .selected(None)
        .context("the camera profile (--profile, --effect, --profile-file)")?
        .filter(|p| !p.is_ideal());
    if cfg.profile.is_some() && a.time_scale.is_none() {
        cfg.time_scale = PROFILE_TIME_SCALE;
    }
    cfg.ros2 = a.ros2.domain(&shoal::demo::load_fleet(&cfg)?)?;
    let bar = ProgressBar::new((cfg.duration_s * 10.0) as u64);
    bar.set_style(
        ProgressStyle::with_template("{spinner} sim {pos:>4}/{len} ds [{bar:30}] {elapsed} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    shoal::errln!(
        "shoal demo: 3 vehicles, water {} /m, {} s simulated at {} frames/s per camera, time scale {}, camera profile {}",
        cfg.water_c_per_m,
        cfg.duration_s,
        cfg.frame_rate_hz,
        cfg.time_scale,
        cfg.profile.as_ref().map_or("ideal", |p| p.name.as_str())
    );
    if let Some(st) = &cfg.station {
        shoal::errln!(
            "ground station: open http://{}:{}/ in a browser (Foxglove: ws://{}:{}); --no-station to skip",
            st.bind,
            st.http_port,
            st.bind,
            st.foxglove_port.unwrap_or_default()
        );
    }
    // The first Ctrl-C / SIGTERM ends the run cleanly (log finished, figures
    // printed); a second one exits at once.
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register_conditional_shutdown(sig, 130, stop.clone())?;
        signal_hook::flag::register(sig, stop.clone())?;
    }
    let summary = run_until(&cfg, &stop, |t, _total, msg| {
        bar.set_position((t * 10.0) as u64);
        bar.set_message(msg.to_string());
    })?;
    bar.finish_and_clear();
    if let Some(t) = summary.interrupted_at_s {
        shoal::outln!(
            "interrupted at {t:.1} s of {} s simulated: services stopped, log finished",
            cfg.duration_s
        );
    }
    print_figures(&summary);
    if let Some(log) = &summary.log {
        shoal::outln!(
            "log: {} ({} messages, {} dropped, {:.1} MB) — try `shoal log info {}`",
            log.path.display(),
            log.messages,
            log.dropped,
            log.file_bytes as f64 / 1e6,
            log.path.display()
        );
    }
    if let Some(path) = a.summary_json {
        std::fs::write(&path, serde_json::to_string_pretty(&summary)?)?;
        shoal::outln!("summary written to {}", path.display());
    }
    Ok(())
}

/// The run's figures: per pair, the pipeline, the last map's verdicts, the vehicles' nav, the occlusion.
fn print_figures(summary: &shoal::demo::DemoSummary) {
    shoal::outln!(
        "fused relative pose error against ground truth (mean over the second half of the run):"
    );
    shoal::outln!(
        "  pair      position error   angle error   localized in   on a flip twin   mean NEES (6 honest)"
    );
    for p in &summary.pairs {
        shoal::outln!(
            "  {:>3}-{:<3}  {:>10.1} mm   {:>9.2}°   {:>5}/{:<3} maps  {:>5} maps       {:>8.1}",
            p.a,
            p.b,
            p.position_error_m * 1e3,
            p.angle_error_deg,
            p.maps_localized,
            p.maps_evaluated,
            p.maps_flipped,
            p.mean_nees
        );
    }
    shoal::outln!(
        "frames published {}, processed {} (dropped by the nodes {}, never received {}), mean per-frame pipeline latency {:.1} ms, frame-to-map latency {:.0} ms, observations {}, maps {}, sim ticks {} ({} skipped), wall time {:.1} s ({:.1} s start-up, {:.1} s running, {:.1} s finishing)",
        summary.frames_published,
        summary.frames_processed,
        summary.frames_dropped,
        summary.frames_lost,
        summary.mean_latency_ms,
        summary.mean_end_to_end_latency_ms,
        summary.observations_sent,
        summary.maps_received,
        summary.sim_ticks,
        summary.sim_ticks_skipped,
        summary.wall_time_s,
        summary.startup_s,
        summary.running_s,
        summary.finishing_s
    );
    shoal::outln!(
        "last map: {} hypotheses accepted, {} observations rejected, {} planar-flip twins rejected (by vote or by the vehicles' nav)",
        summary.edges_accepted,
        summary.edges_rejected,
        summary.flip_twins_rejected
    );
    shoal::outln!(
        "vehicles' nav (depth, IMU, compass): {} observations refused outright, {} with one hypothesis (a planar-flip twin) refused, over the run",
        summary.observations_refused_by_nav,
        summary.twins_refused_by_nav
    );
    if let Some(o) = &summary.occlusion {
        shoal::outln!(
            "vehicle {} hidden: over {} maps live {}, predicted {}, stale {}, unobserved {}; position error ≤ {:.0} mm, within 3σ in {}; ≤ {:.0} mm from its formation slot",
            o.vehicle,
            o.maps,
            o.live,
            o.predicted,
            o.stale,
            o.unobserved,
            o.max_position_error_m * 1e3,
            o.within_3_sigma,
            o.max_slot_error_m * 1e3
        );
    }
}
