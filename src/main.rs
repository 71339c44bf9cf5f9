//! `shoal`: the one command-line tool. Each subcommand parses its arguments
//! and calls a library crate; no algorithm lives here.

mod cmd;

use clap::{Parser, Subcommand};

#[derive(Debug, Parser)]
#[command(
    name = "shoal",
    version,
    about = "Camera-only relative localization for AUV swarms (enhanced AR markers, HOIRM restoration, Zenoh)",
    long_about = "shoal finds where the vehicles of an AUV swarm are relative to each other from their \
cameras alone: HOIRM underwater image restoration, 12-corner enhanced AR markers, iterative PnP with \
covariance, and a Zenoh-based fusion service that keeps one consistent swarm map.\n\n\
Start with `shoal demo` (a simulated three-vehicle swarm, no setup needed)."
)]
struct Cli {
    /// Log filter (tracing EnvFilter syntax), e.g. `info`, `shoal=debug,zenoh=warn`.
    #[arg(
        long,
        global = true,
        env = "SHOAL_LOG",
        default_value = "info,zenoh=warn"
    )]
    log: String,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the simulated three-vehicle swarm of the paper's §6.3 end to end (no setup needed).
    ///
    /// Through a camera profile (`--profile realistic`) the simulator renders
    /// every camera through it and every node holds a lab's calibration of
    /// its camera, not the renderer's.
    Demo(cmd::demo::DemoArgs),
    /// Run one vehicle's node: cameras → restoration → detection → pose → observations on Zenoh.
    Node(cmd::services::NodeArgs),
    /// Run swarm fusion: observations of all vehicles → one fleet map on Zenoh.
    Fusion(cmd::services::FusionArgs),
    /// Send one vehicle's observations at an acoustic modem's rate: compact packets on shoal/<fleet>/<vehicle>/link.
    Link(cmd::services::LinkArgs),
    /// Run the simulator on Zenoh (frames, ground truth, commands), or render one frame (`sim render`).
    Sim(cmd::services::SimArgs),
    /// Printable markers.
    #[command(subcommand)]
    Marker(cmd::tools::MarkerCmd),
    /// Printable calibration boards (ChArUco, or a grid of shoal markers).
    #[command(subcommand)]
    Board(cmd::calib::BoardCmd),
    /// Calibrate a camera from views of a board: OpenCV and ROS YAML, per-view errors, coverage.
    Calibrate(cmd::calib::CalibrateArgs),
    /// Find markers in images or videos; one JSON line per detection (with pose given --camera and --size-mm).
    Detect(cmd::tools::DetectArgs),
    /// Restore an underwater image (HOIRM or a baseline).
    Restore(cmd::tools::RestoreArgs),
    /// Measure shoal against the paper and the baselines: CSV, plots and summary.json per experiment.
    ///
    /// `--profile`, `--effect` and `--profile-file` are taken by `detection`,
    /// `restoration`, `accuracy`, `accuracy-yaw`, `accuracy-rmse`, `fit-noise`,
    /// `swarm` and `node-rate` (the frames rendered through the profile);
    /// `fusion`, `links` and `nav` take `realistic` as the observation model
    /// fitted to that camera; the other experiments refuse them.
    Eval(cmd::eval::EvalArgs),
    /// Record the fleet's Zenoh traffic into an MCAP log (wire bytes unchanged + Foxglove channels).
    Record(cmd::log::RecordArgs),
    /// Republish an MCAP log's messages on Zenoh with their original timing.
    Replay(cmd::log::ReplayArgs),
    /// Re-run fusion offline over an MCAP log (deterministic) and write the new map track.
    Fuse(cmd::log::FuseArgs),
    /// Inspect or repair MCAP logs.
    #[command(subcommand)]
    Log(cmd::log::LogCmd),
    /// Serve the ground-station page (live swarm view) and Foxglove's live protocol, fed from Zenoh.
    Station(cmd::station::StationArgs),
    /// A fault-injecting TCP relay between two Zenoh routers (delay, jitter, stalls, cuts; SIGUSR1 cut, SIGUSR2 heal).
    Relay(cmd::relay::RelayArgs),
    /// A Zenoh router from a config file (one per network side, where there is no zenohd).
    Router(cmd::relay::RouterArgs),
    /// Validate configuration files.
    #[command(subcommand)]
    Config(cmd::config::ConfigCmd),
    /// The simulated swarm for an hour with link cuts, fusion restarts and vehicle dropouts; memory, open files and maps watched.
    Soak(cmd::soak::SoakArgs),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let filter = tracing_subscriber::EnvFilter::try_new(&cli.log)
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .init();
    let result = match cli.command {
        Command::Config(c) => cmd::config::run(c),
        Command::Demo(a) => cmd::demo::run_demo(a),
        Command::Node(a) => cmd::services::run_node(a),
        Command::Fusion(a) => cmd::services::run_fusion(a),
        Command::Link(a) => cmd::services::run_link(a),
        Command::Sim(a) => cmd::services::run_sim(a),
        Command::Marker(c) => cmd::tools::run_marker(c),
        Command::Board(c) => cmd::calib::run_board(c),
        Command::Calibrate(a) => cmd::calib::run_calibrate(a),
        Command::Detect(a) => cmd::tools::run_detect(a),
        Command::Restore(a) => cmd::tools::run_restore(a),
        Command::Record(a) => cmd::log::run_record(a),
        Command::Replay(a) => cmd::log::run_replay(a),
        Command::Fuse(a) => cmd::log::run_fuse(a),
        Command::Log(c) => cmd::log::run_log(c),
        Command::Station(a) => cmd::station::run_station(a),
        Command::Eval(a) => cmd::eval::run_eval(a),
        Command::Relay(a) => cmd::relay::run_relay(a),
        Command::Router(a) => cmd::relay::run_router(a),
        Command::Soak(a) => cmd::soak::run_soak(a),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            shoal::errln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    #[test]
    fn command_line_definition_is_consistent() {
        Cli::command().debug_assert();
    }

    #[test]
    fn every_subcommand_parses_its_defaults() {
        // Arguments that collide with globals only fail when parsed.
        for args in [
            vec!["shoal", "demo"],
            vec!["shoal", "sim"],
            vec!["shoal", "fusion"],
            vec!["shoal", "node", "--vehicle", "10"],
            vec!["shoal", "config", "check", "x.toml"],
            vec!["shoal", "eval", "accuracy", "--out", "x"],
            vec!["shoal", "eval", "probe", "residuals", "--frames", "1"],
            vec!["shoal", "eval", "probe", "record-cost", "x.mcap"],
            vec!["shoal", "eval", "probe", "hoirm", "--c", "8.22,12.2"],
            vec!["shoal", "eval", "probe", "psf-scale"],
            vec!["shoal", "eval", "probe", "restore-sheet"],
            vec!["shoal", "eval", "probe", "water-sheet"],
            vec!["shoal", "eval", "probe", "code-tables"],
        ] {
            if let Err(e) = Cli::try_parse_from(&args) {
                panic!("{args:?}: {e}");
            }
        }
    }
}
