//! Ground-station monitoring of a shoal swarm (issue #9): what an operator on
//! the support vessel watches during a trial.
//!
//! [`spawn`] starts, on one Zenoh session:
//! - a **web page** (`http://<bind>:<port>/`): top and side views of the fused
//!   map with each vehicle's hull, ID and 3-sigma covariance ellipse, the
//!   accepted and rejected edges coloured by reason, per-vehicle last-seen
//!   age and liveliness, per-camera frame rate, detection rate and latency,
//!   and in simulation the ground truth as ghosts with the error. The page is
//!   plain JS + SVG embedded in the binary (no network assets); it gets a
//!   JSON snapshot ([`view::SwarmView`]) pushed as server-sent events at
//!   [`StationConfig::rate_hz`] (`/events`), or on request (`/api/snapshot`);
//! - **Foxglove's live WebSocket protocol** ([`live`]) with the same channels
//!   and JSON schemas as the MCAP logs.
//!
//! Both only listen to Zenoh, so `shoal replay LOG.mcap` drives them exactly
//! as a live swarm does.
//!
//! The page's server ([`http`]) is axum on a tokio runtime of its own; the
//! snapshots are computed on a plain thread. It answers only to its own
//! host names ([`access`]: no DNS rebinding of a loopback page), can require
//! a token, and serves HTTPS ([`tls`]) when given a certificate. A station
//! bound beyond loopback without a token is refused
//! ([`StationConfig::insecure_public`] overrides).

// A library reports failures as errors; an `unwrap()` that cannot fail says why with `expect`.
#![warn(clippy::unwrap_used)]

extern crate shoal_proto as proto;

pub mod access;
pub mod http;
pub mod live;
pub mod tls;
pub mod view;

pub use tls::TlsFiles;

use proto::config::Fleet;
use proto::{FleetMap, KeyKind, NodeStatus, Observation, SimTruth, VehicleId};
use shoal_bus::{Bus, Declaration, Subscription, Worker};
use std::collections::{BTreeMap, VecDeque};
use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use view::{build_view, pair_map_with_truth, NodeReports, ViewInputs};

/// Errors of the station.
#[derive(Debug, thiserror::Error)]
pub enum StationError {
    #[error("cannot listen for {what} on {addr} (is another station or program using that port? choose another port)")]
    Bind {
        what: &'static str,
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot start the Foxglove server on {addr}: {reason} (is another program using that port? choose another port)")]
    Foxglove { addr: String, reason: String },
    #[error("cannot write the Foxglove MCAP file {}: {reason}", path.display())]
    FoxgloveMcap {
        path: std::path::PathBuf,
        reason: String,
    },
    #[error("--foxglove-mcap writes what the Foxglove live server sends: it needs that server (drop --no-foxglove)")]
    FoxgloveMcapWithoutServer,
    #[error(transparent)]
    Bus(#[from] shoal_bus::BusError),
    #[error("cannot start a station thread: {0}")]
    Thread(String),
    #[error("station rate {0} Hz: must be between 1 and 100")]
    Rate(f64),
    #[error("station token refused: {0}")]
    Token(String),
    #[error("--allow-host {name:?}: {reason}")]
    AllowHost { name: String, reason: String },
    #[error("cannot read the station's TLS {what} {path}: {source}")]
    TlsRead {
        what: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("the station's TLS {what} {path} is not usable: {reason}")]
    TlsPem {
        what: &'static str,
        path: PathBuf,
        reason: String,
    },
    #[error("the TLS key {key} does not go with the certificate {cert}: {reason}")]
    TlsKey {
        cert: PathBuf,
        key: PathBuf,
        reason: String,
    },
    #[error("refusing to serve the station on {bind}, beyond loopback, without a token: anyone on that network could watch the swarm. Give a token (--token or SHOAL_STATION_TOKEN; with --tls-cert/--tls-key so it does not cross the network in clear), reach a loopback station through an SSH tunnel, or pass --insecure-public to serve it open anyway")]
    PublicWithoutToken { bind: IpAddr },
    #[error("refusing to serve the Foxglove live server on {bind}, beyond loopback: it has no token or TLS of its own. Pass --no-foxglove (and reach it through an SSH tunnel from a loopback station), or --insecure-public to serve it open anyway")]
    PublicFoxglove { bind: IpAddr },
}

/// Where the station listens, how often it pushes, and who may see it.
#[derive(Clone, PartialEq)]
pub struct StationConfig {
    /// Address both servers bind (default loopback: reach it over an SSH tunnel).
    pub bind: IpAddr,
    /// HTTP port of the page (0: any free port).
    pub http_port: u16,
    /// Foxglove WebSocket port (0: any free port; `None`: no Foxglove server).
    pub foxglove_port: Option<u16>,
    /// Also write what the Foxglove server sends to this MCAP file (same
    /// `foxglove::Context`, the `foxglove` crate's writer).
    pub foxglove_mcap: Option<std::path::PathBuf>,
    /// Snapshots pushed to the page per second.
    pub rate_hz: f64,
    /// Access token: when set, every page request needs it ([`access`]).
    pub token: Option<String>,
    /// Host names the page answers to besides its own address and the
    /// loopback names (`NAME` or `NAME:PORT`, see [`access`]).
    pub allow_hosts: Vec<String>,
    /// Serve the page over HTTPS with this certificate.
    pub tls: Option<TlsFiles>,
    /// Serve beyond loopback without a token (and the Foxglove server there at all).
    pub insecure_public: bool,
}

impl Default for StationConfig {
    fn default() -> Self {
        StationConfig {
            bind: IpAddr::V4(Ipv4Addr::LOCALHOST),
            http_port: 8080,
            foxglove_port: Some(8765),
            foxglove_mcap: None,
            rate_hz: 10.0,
            token: None,
            allow_hosts: Vec::new(),
            tls: None,
            insecure_public: false,
        }
    }
}

/// Debug without the token's value.
impl std::fmt::Debug for StationConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StationConfig")
            .field("bind", &self.bind)
            .field("http_port", &self.http_port)
            .field("foxglove_port", &self.foxglove_port)
            .field("foxglove_mcap", &self.foxglove_mcap)
            .field("rate_hz", &self.rate_hz)
            .field("token", &self.token.as_ref().map(|_| "(set)"))
            .field("allow_hosts", &self.allow_hosts)
            .field("tls", &self.tls)
            .field("insecure_public", &self.insecure_public)
            .finish()
    }
}

impl StationConfig {
    /// Check everything that can be checked before binding: rate, token,
    /// host names, TLS files (loaded), and the rule for public addresses.
    pub fn check(&self) -> Result<http::ServeOptions, StationError> {
        if !(1.0..=100.0).contains(&self.rate_hz) {
            return Err(StationError::Rate(self.rate_hz));
        }
        if self.foxglove_mcap.is_some() && self.foxglove_port.is_none() {
            return Err(StationError::FoxgloveMcapWithoutServer);
        }
        let token = self.token.as_deref().map(access::Token::new).transpose()?;
        let allowed_hosts = self
            .allow_hosts
            .iter()
            .map(|h| access::parse_allowed_host(h))
            .collect::<Result<Vec<_>, _>>()?;
        let tls = self.tls.as_ref().map(tls::server_config).transpose()?;
        if !self.bind.is_loopback() && !self.insecure_public {
            if self.token.is_none() {
                return Err(StationError::PublicWithoutToken { bind: self.bind });
            }
            if self.foxglove_port.is_some() {
                return Err(StationError::PublicFoxglove { bind: self.bind });
            }
        }
        Ok(http::ServeOptions {
            allowed_hosts,
            token,
            tls,
        })
    }
    /// Say loudly what a station beyond loopback exposes.
    fn warn_if_exposed(&self) {
        if self.bind.is_loopback() {
            return;
        }
        if self.token.is_none() {
            tracing::warn!(
                "station: serving on {} with no token (--insecure-public): anyone who reaches it sees the swarm",
                self.bind
            );
        } else if self.tls.is_none() {
            tracing::warn!(
                "station: serving on {} without TLS: the token crosses the network in clear (add --tls-cert/--tls-key)",
                self.bind
            );
        }
    }
}

/// Subscription queue sizes: the station keeps only the newest of each, so
/// small queues suffice; drops are harmless (the next message supersedes).
const MAP_QUEUE: usize = 16;
const TRUTH_QUEUE: usize = 64;
const STATUS_QUEUE: usize = 64;
const OBS_QUEUE: usize = 512;
/// Ground-truth messages and maps kept to pair a map with its truth.
const TRUTH_HISTORY: usize = 64;
const MAP_HISTORY: usize = 32;

/// A running station.
pub struct StationHandle {
    // Dropped in this order: the station thread first, then the page server.
    worker: Worker,
    http: http::HttpServer,
    foxglove_port: Option<u16>,
    hub: Arc<http::Hub>,
}

impl std::fmt::Debug for StationHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StationHandle")
            .field("http", &self.http.addr)
            .field("foxglove_port", &self.foxglove_port)
            .finish()
    }
}

impl StationHandle {
    /// Where the page is served.
    pub fn http_addr(&self) -> SocketAddr {
        self.http.addr
    }

    /// The page's URL (`https://` when serving TLS; without any token).
    pub fn url(&self) -> String {
        let scheme = if self.http.tls { "https" } else { "http" };
        format!("{scheme}://{}/", self.http.addr)
    }

    /// The Foxglove WebSocket port, if that server runs.
    pub fn foxglove_port(&self) -> Option<u16> {
        self.foxglove_port
    }

    /// The newest snapshot (number, JSON).
    pub fn latest(&self) -> (u64, Arc<str>) {
        self.hub.latest()
    }

    /// Stop both servers and the Zenoh subscriptions.
    pub fn stop(self) {
        self.worker.stop();
        self.http.stop();
    }
}

/// What the station has heard.
struct Heard {
    /// Oldest first, each with its arrival time.
    maps: VecDeque<(FleetMap, Instant)>,
    truths: VecDeque<SimTruth>,
    nodes: BTreeMap<VehicleId, (NodeReports, Instant)>,
}

struct Feeds {
    maps: Subscription<FleetMap>,
    truths: Subscription<SimTruth>,
    status: Subscription<NodeStatus>,
    observations: Subscription<Observation>,
    alive: Arc<Mutex<BTreeMap<VehicleId, bool>>>,
    _liveliness: Declaration,
}

impl Feeds {
    fn rejected(&self) -> u64 {
        self.maps.stats().rejected()
            + self.truths.stats().rejected()
            + self.status.stats().rejected()
            + self.observations.stats().rejected()
    }
}

/// Start the station on `bus` for `fleet`. Fails (without panicking) when a
/// port is taken or the configuration is refused ([`StationConfig::check`]).
pub fn spawn(
    bus: &Bus,
    fleet: Arc<Fleet>,
    cfg: StationConfig,
) -> Result<StationHandle, StationError> {
    let options = cfg.check()?;
    cfg.warn_if_exposed();
    let hub = http::Hub::new();
    let http = http::HttpServer::start(
        SocketAddr::new(cfg.bind, cfg.http_port),
        hub.clone(),
        options,
    )?;
    let foxglove = match cfg.foxglove_port {
        Some(port) => {
            let mut f = live::FoxgloveLive::start(&cfg.bind.to_string(), port)?;
            if let Some(path) = &cfg.foxglove_mcap {
                f.record(path)?;
            }
            Some(f)
        }
        None => None,
    };
    let foxglove_port = foxglove.as_ref().map(|f| f.port());
    let keys = fleet.keys();
    let alive = Arc::new(Mutex::new(BTreeMap::new()));
    let (a, k) = (alive.clone(), keys.clone());
    let liveliness = bus.watch_liveliness(&keys.all_alive(), move |key, is_alive| {
        if let Ok(KeyKind::Alive { vehicle }) = k.parse(key) {
            if let Ok(mut g) = a.lock() {
                g.insert(vehicle, is_alive);
            }
        }
    })?;
    let feeds = Feeds {
        maps: bus.subscribe(&keys.map(), MAP_QUEUE)?,
        truths: bus.subscribe(&keys.truth(), TRUTH_QUEUE)?,
        status: bus.subscribe(&keys.all_status(), STATUS_QUEUE)?,
        observations: bus.subscribe(&keys.all_observations(), OBS_QUEUE)?,
        alive,
        _liveliness: liveliness,
    };
    // The thread owns a clone of the session: callers may drop theirs (the
    // session closes with its last clone, and the subscriptions with it).
    let session = bus.clone();
    let h = hub.clone();
    let period = Duration::from_secs_f64(1.0 / cfg.rate_hz);
    let worker = Worker::spawn("station", move |st| {
        let mut heard = Heard {
            maps: VecDeque::new(),
            truths: VecDeque::new(),
            nodes: BTreeMap::new(),
        };
        // A station started mid-trial shows the current map at once.
        match session.query_latest::<FleetMap>(&fleet.keys().map(), Duration::from_millis(500)) {
            Ok(Some(m)) => heard.maps.push_back((m, Instant::now())),
            Ok(None) => {}
            Err(e) => tracing::debug!("station: map query: {e}"),
        }
        run(&fleet, feeds, foxglove, &mut heard, &h, &st, period);
        drop(session);
    })
    .map_err(|e| StationError::Thread(e.to_string()))?;
    Ok(StationHandle {
        worker,
        http,
        foxglove_port,
        hub,
    })
}

/// The station's loop: drain what arrived, forward it to Foxglove, publish a snapshot.
fn run(
    fleet: &Fleet,
    feeds: Feeds,
    mut foxglove: Option<live::FoxgloveLive>,
    heard: &mut Heard,
    hub: &http::Hub,
    stop: &AtomicBool,
    period: Duration,
) {
    use shoal_record::foxglove as fx;
    let mut update = 0u64;
    let mut next = Instant::now();
    while !stop.load(Ordering::Relaxed) {
        for r in feeds.maps.drain() {
            if let Some(f) = foxglove.as_mut() {
                f.send(fx::fleet_map(fleet, &r.msg));
            }
            heard.maps.push_back((r.msg, r.received_at));
            while heard.maps.len() > MAP_HISTORY {
                heard.maps.pop_front();
            }
        }
        for r in feeds.truths.drain() {
            if let Some(f) = foxglove.as_mut() {
                f.send(fx::sim_truth(fleet, &r.msg));
            }
            heard.truths.push_back(r.msg);
            while heard.truths.len() > TRUTH_HISTORY {
                heard.truths.pop_front();
            }
        }
        for r in feeds.status.drain() {
            if let Some(f) = foxglove.as_mut() {
                f.send(fx::node_status(&r.msg));
            }
            let entry = heard
                .nodes
                .entry(r.msg.vehicle)
                .or_insert_with(|| (NodeReports::default(), r.received_at));
            entry.0.push(r.msg);
            entry.1 = r.received_at;
        }
        for r in feeds.observations.drain() {
            if let Some(f) = foxglove.as_mut() {
                f.send(fx::observation(fleet, &r.msg));
            }
        }
        let now = Instant::now();
        for (reports, at) in heard.nodes.values_mut() {
            reports.age_s = now.saturating_duration_since(*at).as_secs_f64();
        }
        let nodes: BTreeMap<VehicleId, NodeReports> = heard
            .nodes
            .iter()
            .map(|(v, (r, _))| (*v, r.clone()))
            .collect();
        let alive = feeds.alive.lock().map(|g| g.clone()).unwrap_or_default();
        heard.maps.make_contiguous();
        heard.truths.make_contiguous();
        let (map, truth) =
            pair_map_with_truth(heard.maps.as_slices().0, heard.truths.as_slices().0);
        let map = map.map(|(m, at)| (m, now.saturating_duration_since(*at).as_secs_f64()));
        // Before the first map, show the newest truth (the ghosts).
        let truth = truth.or(heard.truths.back());
        update += 1;
        let view = build_view(
            &ViewInputs {
                fleet,
                map,
                truth,
                nodes: &nodes,
                alive: &alive,
                messages_rejected: feeds.rejected(),
            },
            update,
        );
        match serde_json::to_string(&view) {
            Ok(json) => hub.publish(update, json),
            Err(e) => tracing::warn!("station: snapshot: {e}"),
        }
        next += period;
        let now = Instant::now();
        if next > now {
            std::thread::sleep(next - now);
        } else {
            next = now; // fell behind: do not try to catch up with a burst
        }
    }
    if let Some(f) = foxglove {
        f.stop();
    }
}
