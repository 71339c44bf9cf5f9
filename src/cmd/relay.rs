//! `shoal relay` (a fault-injecting TCP relay between two Zenoh routers) and
//! `shoal router` (a plain Zenoh router, one per network side), so fault
//! trials can run each part as its own process, e.g. in its own network
//! namespace.

use super::net::wait_for_ctrl_c;
use anyhow::Context;
use clap::Args;
use shoal_bus::{Bus, Connect};
use shoal_services::relay::{FaultPlan, Flap, Relay};
use std::net::ToSocketAddrs;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

#[derive(Debug, Args)]
pub struct RelayArgs {
    /// Listen here (e.g. `10.0.0.1:7448`).
    #[arg(long)]
    listen: String,
    /// Forward each connection to this address (the far side's Zenoh router).
    #[arg(long)]
    to: String,
    /// Added to every chunk, each direction, milliseconds.
    #[arg(long, default_value_t = 0)]
    delay_ms: u64,
    /// Plus uniform 0..jitter per chunk (order kept: head-of-line blocking), milliseconds.
    #[arg(long, default_value_t = 0)]
    jitter_ms: u64,
    /// Probability per chunk of a TCP retransmission stall (a lost segment).
    #[arg(long, default_value_t = 0.0, value_parser = super::args::probability)]
    loss: f64,
    /// Length of a retransmission stall, milliseconds.
    #[arg(long, default_value_t = 200)]
    stall_ms: u64,
    /// Cut the link every this many seconds (0: never) ...
    #[arg(long, default_value_t = 0.0, value_parser = super::args::non_negative)]
    flap_period_s: f64,
    /// ... for this many milliseconds.
    #[arg(long, default_value_t = 500)]
    flap_down_ms: u64,
    /// Cap each direction at this many bits per second (an acoustic modem: 300 … 5000).
    #[arg(long, value_parser = super::args::positive)]
    rate_bps: Option<f64>,
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

/// Runs until SIGINT/SIGTERM. SIGUSR1 cuts the link (partition: open
/// connections shut down, new ones refused), SIGUSR2 heals it.
pub fn run_relay(a: RelayArgs) -> anyhow::Result<()> {
    let upstream =
        a.to.to_socket_addrs()
            .with_context(|| format!("--to {:?}", a.to))?
            .next()
            .with_context(|| format!("--to {:?} resolves to no address", a.to))?;
    let plan = FaultPlan {
        latency: Duration::from_millis(a.delay_ms),
        jitter: Duration::from_millis(a.jitter_ms),
        loss_stall_probability: a.loss,
        loss_stall: Duration::from_millis(a.stall_ms),
        flap: (a.flap_period_s > 0.0).then(|| Flap {
            period: Duration::from_secs_f64(a.flap_period_s),
            down: Duration::from_millis(a.flap_down_ms),
        }),
        rate_bps: a.rate_bps,
        seed: a.seed,
    };
    let relay = Relay::start(&a.listen, upstream, plan)?;
    let (cut, heal) = (
        Arc::new(AtomicBool::new(false)),
        Arc::new(AtomicBool::new(false)),
    );
    signal_hook::flag::register(signal_hook::consts::SIGUSR1, cut.clone())
        .context("SIGUSR1 handler")?;
    signal_hook::flag::register(signal_hook::consts::SIGUSR2, heal.clone())
        .context("SIGUSR2 handler")?;
    // Printed on stdout so a parent process knows the port when --listen asked for 0.
    shoal::outln!("relay {} -> {upstream}", relay.local_addr());
    tracing::info!(
        "relaying {} -> {upstream} with {plan:?}; SIGUSR1 cuts, SIGUSR2 heals",
        relay.local_addr()
    );
    wait_for_ctrl_c(|| {
        if cut.swap(false, Ordering::SeqCst) {
            tracing::info!("link cut");
            relay.switch().cut();
        }
        if heal.swap(false, Ordering::SeqCst) {
            tracing::info!("link healed");
            relay.switch().heal();
        }
        false
    });
    let s = relay.stats();
    shoal::outln!(
        "relay: {} connections, {} cut, {} refused, {} bytes, {} stalls",
        s.connections.load(Ordering::Relaxed),
        s.cut.load(Ordering::Relaxed),
        s.refused.load(Ordering::Relaxed),
        s.bytes_forwarded.load(Ordering::Relaxed),
        s.stalls.load(Ordering::Relaxed)
    );
    Ok(())
}

#[derive(Debug, Args)]
pub struct RouterArgs {
    /// The router's Zenoh JSON5 config (mode "router"; see configs/zenoh/router.json5).
    #[arg(long)]
    zenoh_config: PathBuf,
}

/// A Zenoh router in this process until SIGINT/SIGTERM (for machines without `zenohd`).
pub fn run_router(a: RouterArgs) -> anyhow::Result<()> {
    let bus = Bus::open(&Connect::File(a.zenoh_config.clone()))?;
    tracing::info!("zenoh router {bus:?} running; Ctrl-C to stop");
    wait_for_ctrl_c(|| false);
    bus.close();
    Ok(())
}
