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

/// ROS 2 publication options shared by the services that host it.
#[derive(Debug, Args)]
pub struct Ros2Args {
    /// Also publish in ROS 2 over rmw_zenoh (no bridge): fused poses, /tf,
    /// observations and /diagnostics (docs/ros2.md). On by default when the
    /// fleet file has a `[ros2]` table.
    #[arg(long)]
    pub ros2: bool,
    /// ROS 2 domain ID, 0–232 (default: `ROS_DOMAIN_ID`, else the fleet
    /// file's `[ros2] domain`, else 0). Implies --ros2.
    #[arg(long, value_parser = parse_domain)]
    pub ros2_domain: Option<u32>,
}

pub fn parse_domain(s: &str) -> Result<u32, String> {
    shoal_services::ros2::parse_domain(s)
}

impl Ros2Args {
    /// The domain to publish in, or `None` when ROS 2 publication is off.
    pub fn domain(&self, fleet: &shoal_proto::config::Fleet) -> anyhow::Result<Option<u32>> {
        if !self.ros2 && self.ros2_domain.is_none() && fleet.ros2.is_none() {
            return Ok(None);
        }
        ros2_domain(self.ros2_domain, fleet).map(Some)
    }
}

/// The ROS 2 domain: `explicit` (`--ros2-domain`), else `ROS_DOMAIN_ID`,
/// else the fleet file's `[ros2] domain`, else 0.
pub fn ros2_domain(
    explicit: Option<u32>,
    fleet: &shoal_proto::config::Fleet,
) -> anyhow::Result<u32> {
    if let Some(d) = explicit {
        return Ok(d);
    }
    if std::env::var_os("ROS_DOMAIN_ID").is_some() {
        return shoal_services::ros2::domain_from_env().map_err(anyhow::Error::msg);
    }
    Ok(fleet.ros2.map_or(0, |r| r.domain))
}
