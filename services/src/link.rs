//! The link sender (`shoal link`): one vehicle's observations and navigation
//! → compact packets at the rate of an acoustic modem (issue #22).
//!
//! It subscribes to the vehicle's own observations, keeps them in a
//! [`LinkQueue`] (per track the frames since it was last sent; the most
//! informative, longest-waiting pair first) and, one packet at a time as a
//! half-duplex modem sends them, publishes a [`LinkPacket`] on
//! `shoal/<fleet>/<vehicle>/link`: the compact observation is the packet's
//! payload, and a packet of `n` payload bytes occupies the modem for
//! `(n + overhead) · 8 / rate` seconds. It also subscribes to the vehicle's
//! own navigation and, every [`nav_span_period_ns`] of it, sends a compact
//! navigation span ([`NavSpanner`]) ahead of the next observation, so that
//! the receivers settle planar flips by both vehicles' gravity. A modem driver forwards the payloads;
//! on the far side it publishes them under the sender's key, where a fusion
//! service started with `--link` (`FusionConfig::link`) reads them.

use shoal_bus::{Bus, BusError, Publisher, Subscription, Worker};
use shoal_fusion::link::{
    airtime_ns, nav_span_period_ns, LinkQueue, LinkQueueStats, NavSpanner, LINK_WINDOW_S,
    MODEM_LATENCY_NS,
};
use shoal_proto::clock::Clock;
use shoal_proto::compact::{self, LinkPacket};
use shoal_proto::config::Fleet;
use shoal_proto::{NavState, Observation, VehicleId};
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// What to send, and at what rate.
#[derive(Debug, Clone)]
pub struct LinkConfig {
    pub fleet: Arc<Fleet>,
    pub vehicle: VehicleId,
    /// The modem's rate for this vehicle, bit/s (positive, finite).
    pub rate_bps: f64,
    /// Bytes the modem adds to every packet (sync, address, CRC).
    pub overhead_bytes: usize,
    /// Observations buffered between sends before the oldest are dropped.
    pub queue_capacity: usize,
    /// Send the vehicle's own navigation as spans this often, ns (`None`:
    /// [`nav_span_period_ns`] of the rate; `Some(0)`: never).
    pub nav_period_ns: Option<u64>,
}

#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    #[error("link rate {0} bit/s: expected a positive number")]
    Rate(f64),
    #[error("vehicle {0} is not in fleet {1:?}")]
    UnknownVehicle(VehicleId, String),
    #[error(transparent)]
    Bus(#[from] BusError),
}

/// What a link sender has done so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LinkStats {
    /// Packets published and their bytes on the modem (payload + overhead).
    pub packets: u64,
    pub modem_bytes: u64,
    /// Observations that do not fit the compact form (counted, not sent).
    pub unencodable: u64,
    /// Observations on this vehicle's key claiming another observer (counted, not sent).
    pub wrong_observer: u64,
    /// Observations and nav states dropped because the sender's subscriptions overflowed.
    pub dropped: u64,
    /// Of the packets, navigation spans.
    pub nav_spans: u64,
    /// Nav states of another vehicle, or not newer than the last, on this vehicle's key (counted, not sent).
    pub nav_refused: u64,
    pub queue: LinkQueueStats,
}

/// A running link sender.
pub struct LinkHandle {
    worker: Worker,
    stats: Arc<Mutex<LinkStats>>,
}

impl std::fmt::Debug for LinkHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LinkHandle")
            .field("stats", &self.stats())
            .finish()
    }
}

impl LinkHandle {
    pub fn stats(&self) -> LinkStats {
        self.stats.lock().map(|g| *g).unwrap_or_default()
    }
    pub fn stop(self) {
        self.worker.stop();
    }
}

/// Start `cfg.vehicle`'s link sender on `bus`, taking `now` from `clock`
/// (the clock of the observations' capture stamps).
pub fn spawn(bus: &Bus, cfg: LinkConfig, clock: Arc<dyn Clock>) -> Result<LinkHandle, LinkError> {
    if !(cfg.rate_bps.is_finite() && cfg.rate_bps > 0.0) {
        return Err(LinkError::Rate(cfg.rate_bps));
    }
    if cfg.fleet.vehicle(cfg.vehicle).is_none() {
        return Err(LinkError::UnknownVehicle(
            cfg.vehicle,
            cfg.fleet.name.clone(),
        ));
    }
    let keys = cfg.fleet.keys();
    let own: Subscription<Observation> =
        bus.subscribe(&keys.observations(cfg.vehicle), cfg.queue_capacity)?;
    let nav_period_ns = cfg
        .nav_period_ns
        .unwrap_or_else(|| nav_span_period_ns(cfg.rate_bps, cfg.overhead_bytes));
    let own_nav: Option<Subscription<NavState>> = (nav_period_ns > 0)
        .then(|| bus.subscribe(&keys.nav(cfg.vehicle), cfg.queue_capacity))
        .transpose()?;
    let publisher: Publisher<LinkPacket> = bus.publisher(keys.link(cfg.vehicle))?;
    let stats: Arc<Mutex<LinkStats>> = Arc::default();
    let stats2 = stats.clone();
    // What the receivers' fusion window still takes when it arrives.
    let max_age_ns = (LINK_WINDOW_S * 1e9) as u64 - MODEM_LATENCY_NS;
    // The session lives as long as the sender, whatever the caller does with its `Bus`.
    let bus = bus.clone();
    let worker = Worker::spawn(format!("link-{}", cfg.vehicle), move |stop| {
        let _keep = &bus;
        let mut queue = LinkQueue::new(max_age_ns);
        let mut spanner = NavSpanner::new(cfg.vehicle, nav_period_ns);
        let mut busy_until = 0u64;
        let mut seq = 0u32;
        let mut local = LinkStats::default();
        while !stop.load(Ordering::Relaxed) {
            let first = own.recv_timeout(Duration::from_millis(10));
            for r in first.into_iter().chain(own.drain()) {
                if r.msg.observer == cfg.vehicle {
                    queue.offer(r.msg);
                } else {
                    local.wrong_observer += 1;
                }
            }
            for r in own_nav.iter().flat_map(|s| s.drain()) {
                spanner.offer(r.msg);
            }
            let now = clock.now_ns();
            while busy_until <= now {
                // A span when one is due, else the next observation.
                let (payload, is_nav) = match own_nav.as_ref().and_then(|_| spanner.due(now)) {
                    Some(span) => match compact::encode_nav_span(&span) {
                        Ok(p) => (p, true),
                        Err(e) => {
                            tracing::debug!("navigation span not sent over the link: {e}");
                            local.unencodable += 1;
                            continue;
                        }
                    },
                    None => {
                        let Some(obs) = queue.next(now) else { break };
                        match compact::encode(&obs) {
                            Ok(p) => (p, false),
                            Err(e) => {
                                tracing::debug!("observation not sent over the link: {e}");
                                local.unencodable += 1;
                                continue;
                            }
                        }
                    }
                };
                let n = payload.len();
                let packet = LinkPacket {
                    sender: cfg.vehicle,
                    seq,
                    payload,
                };
                match publisher.put(&packet) {
                    Ok(()) => {
                        seq = seq.wrapping_add(1);
                        local.packets += 1;
                        local.nav_spans += u64::from(is_nav);
                        local.modem_bytes += (n + cfg.overhead_bytes) as u64;
                    }
                    Err(e) => tracing::warn!("publishing link packet: {e}"),
                }
                busy_until = busy_until.max(now) + airtime_ns(n, cfg.overhead_bytes, cfg.rate_bps);
            }
            local.queue = queue.stats();
            local.dropped = own.dropped() + own_nav.as_ref().map_or(0, |s| s.dropped());
            local.nav_refused = spanner.refused();
            if let Ok(mut g) = stats2.lock() {
                *g = local;
            }
        }
    })
    .map_err(|source| BusError::Thread {
        what: "link",
        source,
    })?;
    Ok(LinkHandle { worker, stats })
}
