//! The fusion service (`shoal fusion`): subscribes to every vehicle's
//! observations, navigation states and liveliness, solves at a fixed rate, publishes the fleet
//! map and serves the newest one to late joiners (a Zenoh queryable).
//! With [`FusionConfig::link`] it hears the other vehicles over an
//! acoustic-rate link instead: their compact packets (`shoal link`) and, on a
//! vehicle, its own observations and navigation in full.
//! Also [`MapClient`], the subscription half of the controller API. The
//! fusion itself is `shoal_fusion::Fusion`.

use shoal_bus::{Bus, BusError, Publisher, Subscription, Worker};
use shoal_fusion::{Fusion, FusionParams, FusionStats, LatestMap, MapView};
use shoal_proto::clock::Clock;
use shoal_proto::compact::{LinkContent, LinkPacket};
use shoal_proto::config::Fleet;
use shoal_proto::queue::DropOldestQueue;
use shoal_proto::{FleetMap, KeyKind, Keys, NavState, Observation, VehicleId};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Central (ground station) or on one vehicle (decentralized).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Placement {
    /// Hears every vehicle; publishes on `shoal/<fleet>/map`.
    Central,
    /// Runs on this vehicle from what it hears; publishes on `shoal/<fleet>/map/<vehicle>`.
    OnVehicle(VehicleId),
}

impl Placement {
    /// Who produces the map (`central` or the vehicle's ID) and the key it is published on.
    pub fn producer_and_key(self, keys: &Keys) -> (String, String) {
        match self {
            Placement::Central => ("central".to_string(), keys.map()),
            Placement::OnVehicle(v) => (v.to_string(), keys.map_of(&v.to_string())),
        }
    }
}

#[derive(Debug, Clone)]
pub struct FusionConfig {
    pub fleet: Arc<Fleet>,
    pub params: FusionParams,
    pub placement: Placement,
    /// Maps published per second.
    pub rate_hz: f64,
    /// Observations buffered between solves before the oldest are dropped.
    pub queue_capacity: usize,
    /// Fed over an acoustic-rate link: the vehicles' [`LinkPacket`]s (not
    /// their full observations; compact observations and navigation spans,
    /// kept for `params.link_window_s`), plus, on a
    /// vehicle, its own observations and navigation (kept for `params.window_s`).
    pub link: bool,
}

impl FusionConfig {
    /// Central fusion of every vehicle's full observations, default
    /// parameters, `rate_hz` maps a second, 4096 observations buffered.
    pub fn central(fleet: Arc<Fleet>, rate_hz: f64) -> Self {
        Self {
            fleet,
            params: FusionParams::default(),
            placement: Placement::Central,
            rate_hz,
            queue_capacity: 4096,
            link: false,
        }
    }
}

/// What fusion subscribes to: every vehicle's observations and navigation,
/// or (link mode) the link packets and, on a vehicle, its own.
struct Inputs {
    observations: Option<Subscription<Observation>>,
    nav: Option<Subscription<NavState>>,
    links: Option<Subscription<LinkPacket>>,
    /// Link packets from this vehicle are its own observations again: skipped.
    own: Option<VehicleId>,
}

impl Inputs {
    fn subscribe(bus: &Bus, cfg: &FusionConfig) -> Result<Inputs, BusError> {
        let keys = cfg.fleet.keys();
        let cap = cfg.queue_capacity;
        let own = match cfg.placement {
            Placement::OnVehicle(v) => Some(v),
            Placement::Central => None,
        };
        Ok(if !cfg.link {
            Inputs {
                observations: Some(bus.subscribe(&keys.all_observations(), cap)?),
                nav: Some(bus.subscribe(&keys.all_nav(), cap)?),
                links: None,
                own,
            }
        } else {
            Inputs {
                observations: own
                    .map(|v| bus.subscribe(&keys.observations(v), cap))
                    .transpose()?,
                nav: own.map(|v| bus.subscribe(&keys.nav(v), cap)).transpose()?,
                links: Some(bus.subscribe(&keys.all_links(), cap)?),
                own,
            }
        })
    }

    fn dropped(&self) -> u64 {
        self.observations.as_ref().map_or(0, |s| s.dropped())
            + self.links.as_ref().map_or(0, |s| s.dropped())
    }

    fn rejected(&self) -> u64 {
        self.observations
            .as_ref()
            .map_or(0, |s| s.stats().rejected())
            + self.links.as_ref().map_or(0, |s| s.stats().rejected())
    }

    /// Hand everything received to `fusion`; returns the link packets refused.
    fn feed(&self, fusion: &mut Fusion, keys: &Keys, now: u64) -> u64 {
        for r in self.nav.iter().flat_map(|s| s.drain()) {
            match keys.parse(&r.key) {
                Ok(KeyKind::Nav { vehicle }) => {
                    if let Err(e) = fusion.ingest_nav(r.msg, vehicle, now) {
                        tracing::debug!("nav state on {} refused: {e}", r.key);
                    }
                }
                _ => tracing::warn!("nav state on unexpected key {}", r.key),
            }
        }
        for r in self.observations.iter().flat_map(|s| s.drain()) {
            match keys.parse(&r.key) {
                Ok(KeyKind::Observations { vehicle }) => {
                    if let Err(reason) = fusion.ingest(r.msg, vehicle, now) {
                        tracing::debug!("observation on {} rejected: {reason:?}", r.key);
                    }
                }
                _ => tracing::warn!("observation on unexpected key {}", r.key),
            }
        }
        let mut refused = 0;
        for r in self.links.iter().flat_map(|s| s.drain()) {
            let vehicle = match keys.parse(&r.key) {
                Ok(KeyKind::Link { vehicle }) if vehicle == r.msg.sender => vehicle,
                _ => {
                    tracing::debug!(
                        "link packet of vehicle {} on key {}: refused",
                        r.msg.sender,
                        r.key
                    );
                    refused += 1;
                    continue;
                }
            };
            if Some(vehicle) == self.own {
                continue;
            }
            // Validated on receipt (`LinkPacket::validate`), so this decodes.
            match r.msg.content() {
                Ok(LinkContent::Observation(obs)) => {
                    if let Err(reason) = fusion.ingest_linked(*obs, vehicle, now) {
                        tracing::debug!("link observation on {} rejected: {reason:?}", r.key);
                    }
                }
                Ok(LinkContent::Nav(span)) => {
                    if let Err(e) = fusion.ingest_linked_nav(&span, vehicle, now) {
                        tracing::debug!("link navigation span on {} refused: {e}", r.key);
                    }
                }
                Err(e) => {
                    tracing::debug!("link packet on {}: {e}", r.key);
                    refused += 1;
                }
            }
        }
        refused
    }
}

/// A running fusion service.
pub struct FusionHandle {
    worker: Worker,
    latest: Arc<Mutex<Option<FleetMap>>>,
    stats: Arc<Mutex<FusionStats>>,
    dropped: Arc<AtomicU64>,
    rejected: Arc<AtomicU64>,
    maps: Arc<AtomicU64>,
}

impl std::fmt::Debug for FusionHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FusionHandle").finish()
    }
}

impl FusionHandle {
    /// The newest map this instance produced.
    pub fn latest(&self) -> Option<FleetMap> {
        self.latest.lock().ok().and_then(|g| g.clone())
    }
    pub fn stats(&self) -> FusionStats {
        self.stats.lock().map(|g| g.clone()).unwrap_or_default()
    }
    /// Observations dropped because fusion fell behind (its queue overflowed).
    pub fn observations_dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }
    /// Observations refused before fusion saw them (undecodable, wrong
    /// schema version, invalid content), as the subscription counted them.
    pub fn observations_rejected(&self) -> u64 {
        self.rejected.load(Ordering::Relaxed)
    }
    /// Maps published so far.
    pub fn maps_published(&self) -> u64 {
        self.maps.load(Ordering::Relaxed)
    }
    pub fn stop(self) {
        self.worker.stop();
    }
}

/// How often the service repeats its warning while a node floods fusion.
const CROWDED_WARN_EVERY: Duration = Duration::from_secs(10);

/// Start fusion on `bus`, taking `now` from `clock`.
pub fn spawn(
    bus: &Bus,
    cfg: FusionConfig,
    clock: Arc<dyn Clock>,
) -> Result<FusionHandle, BusError> {
    let keys = cfg.fleet.keys();
    let (producer, map_key) = cfg.placement.producer_and_key(&keys);
    let inputs = Inputs::subscribe(bus, &cfg)?;
    let liveliness: DropOldestQueue<(String, bool)> = DropOldestQueue::new(1024);
    let l = liveliness.clone();
    let watch = bus.watch_liveliness(&keys.all_alive(), move |k, alive| {
        l.push((k.to_string(), alive));
    })?;
    let publisher: Publisher<FleetMap> = bus.publisher(map_key.clone())?;
    let latest: Arc<Mutex<Option<FleetMap>>> = Arc::default();
    let latest_bytes: Arc<Mutex<Option<Vec<u8>>>> = Arc::default();
    let lb = latest_bytes.clone();
    let queryable = bus.serve_latest(map_key, move || lb.lock().ok().and_then(|g| g.clone()))?;
    let stats: Arc<Mutex<FusionStats>> = Arc::default();
    let (latest2, stats2) = (latest.clone(), stats.clone());
    let (dropped, maps) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let (dropped2, maps2) = (dropped.clone(), maps.clone());
    let rejected = Arc::new(AtomicU64::new(0));
    let rejected2 = rejected.clone();
    let mut fusion = Fusion::new(&cfg.fleet, cfg.params, &producer);
    let period = Duration::from_secs_f64(1.0 / cfg.rate_hz.max(0.1));
    let bus = bus.clone();
    let worker = Worker::spawn(format!("fusion-{producer}"), move |stop2| {
        let _keep = (watch, queryable, bus);
        let mut next = Instant::now();
        let (mut crowded_warned, mut warned_at) = (0u64, None::<Instant>);
        let mut refused_total = 0u64;
        while !stop2.load(Ordering::Relaxed) {
            let now = clock.now_ns();
            for (key, alive) in liveliness.drain() {
                if let Ok(KeyKind::Alive { vehicle }) = keys.parse(&key) {
                    fusion.set_alive(vehicle, alive, now);
                }
            }
            refused_total += inputs.feed(&mut fusion, &keys, now);
            dropped2.store(inputs.dropped(), Ordering::Relaxed);
            rejected2.store(inputs.rejected() + refused_total, Ordering::Relaxed);
            if Instant::now() >= next {
                next += period;
                let map = fusion.solve(now);
                match shoal_proto::encode(&map) {
                    Ok(bytes) => {
                        match publisher.put_bytes(bytes.clone()) {
                            Ok(()) => {
                                maps2.fetch_add(1, Ordering::Relaxed);
                            }
                            Err(e) => tracing::warn!("publishing map: {e}"),
                        }
                        if let Ok(mut g) = latest_bytes.lock() {
                            *g = Some(bytes);
                        }
                    }
                    Err(e) => tracing::error!("encoding map: {e}"),
                }
                if let Ok(mut g) = latest2.lock() {
                    *g = Some(map);
                }
                let now_stats = fusion.stats();
                // At most one warning per CROWDED_WARN_EVERY while a flood goes on.
                if now_stats.crowded_out > crowded_warned
                    && warned_at.is_none_or(|t| t.elapsed() >= CROWDED_WARN_EVERY)
                {
                    warned_at = Some(Instant::now());
                    tracing::warn!(
                        "{} observations dropped so far because a vehicle sent more than its \
                         window share ({} in the window; FusionParams::max_window_per_observer): \
                         a node sending far beyond its cameras' rate",
                        now_stats.crowded_out,
                        fusion.params().max_window_per_observer
                    );
                    crowded_warned = now_stats.crowded_out;
                }
                if let Ok(mut g) = stats2.lock() {
                    *g = now_stats;
                }
                // Don't try to catch up after a stall: one map per period at most.
                if next < Instant::now() {
                    next = Instant::now() + period;
                }
            }
            std::thread::sleep(Duration::from_millis(5).min(period));
        }
    })
    .map_err(|source| BusError::Thread {
        what: "fusion",
        source,
    })?;
    Ok(FusionHandle {
        worker,
        latest,
        stats,
        dropped,
        rejected,
        maps,
    })
}

/// The controller-side API: the newest fleet map, from the live topic or,
/// for a late joiner, from fusion's queryable.
pub struct MapClient {
    sub: Subscription<FleetMap>,
    latest: LatestMap,
}

impl std::fmt::Debug for MapClient {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MapClient").finish()
    }
}

impl MapClient {
    /// Subscribe to the central map of `fleet` and ask for the current one.
    pub fn connect(bus: &Bus, fleet: &Fleet) -> Result<MapClient, BusError> {
        let keys = fleet.keys();
        let sub = bus.subscribe(&keys.map(), 4)?;
        let latest =
            LatestMap::new(bus.query_latest::<FleetMap>(&keys.map(), Duration::from_millis(300))?);
        Ok(MapClient { sub, latest })
    }

    /// The newest map received so far (non-blocking).
    pub fn latest(&mut self) -> Option<&MapView> {
        self.latest
            .offer(self.sub.drain().into_iter().map(|r| r.msg));
        self.latest.view()
    }

    /// Wait up to `timeout` for a map newer than the current one.
    pub fn wait_newer(&mut self, timeout: Duration) -> Option<&MapView> {
        if let Some(r) = self.sub.recv_timeout(timeout) {
            self.latest.replace(r.msg);
        }
        self.latest()
    }
}
