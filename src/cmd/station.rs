//! `shoal station`: the ground-station page and Foxglove live server for a
//! running swarm (or a `shoal replay` of a log), fed from Zenoh.

use super::net::{wait_for_ctrl_c, NetArgs};
use clap::Args;
use shoal_proto::config::Fleet;
use shoal_station::StationConfig;
use std::net::IpAddr;
use std::path::PathBuf;
use std::sync::Arc;

#[derive(Debug, Args)]
pub struct StationArgs {
    #[arg(long, default_value = "configs/fleets/paper.toml")]
    fleet: PathBuf,
    /// HTTP port of the page.
    #[arg(long = "http-port", default_value_t = 8080)]
    http_port: u16,
    /// Foxglove WebSocket port (open `ws://HOST:PORT` in Foxglove).
    #[arg(long, default_value_t = 8765)]
    foxglove_port: u16,
    /// Do not start the Foxglove server.
    #[arg(long)]
    no_foxglove: bool,
    /// Address to bind both servers to (default loopback: reach it through an SSH tunnel; 0.0.0.0 exposes it).
    #[arg(long, default_value = "127.0.0.1")]
    bind: IpAddr,
    /// Snapshots pushed to the page per second.
    #[arg(long, default_value_t = 10.0, value_parser = super::args::positive)]
    rate: f64,
    #[command(flatten)]
    net: NetArgs,
}

pub fn run_station(a: StationArgs) -> anyhow::Result<()> {
    let fleet = Arc::new(Fleet::load(&a.fleet)?);
    let bus = a.net.open()?;
    let station = shoal_station::spawn(
        &bus,
        fleet,
        StationConfig {
            bind: a.bind,
            http_port: a.http_port,
            foxglove_port: (!a.no_foxglove).then_some(a.foxglove_port),
            rate_hz: a.rate,
        },
    )?;
    shoal::errln!("shoal station: open {} in a browser", station.url());
    if let Some(p) = station.foxglove_port() {
        shoal::errln!("shoal station: Foxglove live at ws://{}:{p}", a.bind);
    }
    wait_for_ctrl_c(|| false);
    station.stop();
    Ok(())
}
