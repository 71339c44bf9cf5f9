//! Zenoh connection options shared by the service subcommands.

use clap::Args;
use shoal_bus::{Bus, Connect};
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct NetArgs {
    /// A Zenoh JSON5 config (routers, TLS, access control); see configs/zenoh/.
    #[arg(long)]
    pub zenoh_config: Option<PathBuf>,
    /// Embedded default: the loopback port where shoal processes meet (the
    /// first process listens on it, the others connect to it).
    #[arg(long, default_value_t = 7447)]
    pub port: u16,
}

impl NetArgs {
    pub fn open(&self) -> anyhow::Result<Bus> {
        let connect = match &self.zenoh_config {
            Some(p) => Connect::File(p.clone()),
            None => Connect::loopback_rendezvous(self.port),
        };
        Ok(Bus::open(&connect)?)
    }
}

/// Block until Ctrl-C (SIGINT/SIGTERM) or `done()` says so.
pub fn wait_for_ctrl_c(done: impl Fn() -> bool) {
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        let _ = signal_hook::flag::register(sig, stop.clone());
    }
    while !stop.load(Ordering::Relaxed) && !done() {
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
}
