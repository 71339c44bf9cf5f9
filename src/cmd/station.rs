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
    /// Also write what the Foxglove server sends to this MCAP file (the station's view, Foxglove
    /// channels only; `shoal record` keeps the full log).
    #[arg(long, value_name = "FILE", conflicts_with = "no_foxglove")]
    foxglove_mcap: Option<PathBuf>,
    /// Address to bind both servers to (default loopback: reach it through an SSH tunnel). Any other
    /// address needs --token (and --no-foxglove), or --insecure-public.
    #[arg(long, default_value = "127.0.0.1")]
    bind: IpAddr,
    /// Access token the page requires (16-256 of A-Z a-z 0-9 -._~+/=, e.g. `openssl rand -hex 16`):
    /// scripts send `Authorization: Bearer TOKEN`, a browser opens /?token=TOKEN once (then a cookie).
    #[arg(
        long,
        env = "SHOAL_STATION_TOKEN",
        hide_env_values = true,
        value_name = "TOKEN"
    )]
    token: Option<String>,
    /// Another host name the page answers to (NAME or NAME:PORT; repeatable). By default only its
    /// own address, localhost, 127.0.0.1 and [::1] at its port: other Hosts are refused (DNS rebinding).
    #[arg(long = "allow-host", value_name = "NAME")]
    allow_host: Vec<String>,
    /// Serve the page over HTTPS with this certificate chain (PEM; with --tls-key).
    #[arg(long, value_name = "PEM", requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// The certificate's private key (PEM; with --tls-cert).
    #[arg(long, value_name = "PEM", requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// Serve on a non-loopback --bind without a token, and the Foxglove server there: anyone on
    /// that network can watch the swarm.
    #[arg(long)]
    insecure_public: bool,
    /// Snapshots pushed to the page per second.
    #[arg(long, default_value_t = 10.0, value_parser = super::args::positive)]
    rate: f64,
    #[command(flatten)]
    net: NetArgs,
}

pub fn run_station(a: StationArgs) -> anyhow::Result<()> {
    let fleet = Arc::new(Fleet::load(&a.fleet)?);
    let cfg = StationConfig {
        bind: a.bind,
        http_port: a.http_port,
        foxglove_port: (!a.no_foxglove).then_some(a.foxglove_port),
        foxglove_mcap: a.foxglove_mcap.clone(),
        rate_hz: a.rate,
        token: a.token.clone(),
        allow_hosts: a.allow_host,
        tls: a
            .tls_cert
            .zip(a.tls_key)
            .map(|(cert, key)| shoal_station::TlsFiles { cert, key }),
        insecure_public: a.insecure_public,
    };
    // A refused token, host name, certificate or public address is reported before Zenoh opens.
    cfg.check()?;
    let bus = a.net.open()?;
    let station = shoal_station::spawn(&bus, fleet, cfg)?;
    if a.token.is_some() {
        shoal::errln!(
            "shoal station: open {}?token=TOKEN in a browser (your token; the page then keeps a cookie)",
            station.url()
        );
    } else {
        shoal::errln!("shoal station: open {} in a browser", station.url());
    }
    if let Some(p) = station.foxglove_port() {
        shoal::errln!("shoal station: Foxglove live at ws://{}:{p}", a.bind);
    }
    if let Some(path) = &a.foxglove_mcap {
        shoal::errln!(
            "shoal station: writing what Foxglove is sent to {}",
            path.display()
        );
    }
    wait_for_ctrl_c(|| false);
    station.stop();
    Ok(())
}
