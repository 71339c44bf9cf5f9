//! shoal's Zenoh plumbing, shared by the services (`shoal-services`: node,
//! fusion, simulator, recorder, replay) and the ground station, so that none
//! of them touches raw bytes or key strings.
//!
//! - [`Bus`]: one Zenoh session (every shoal component owns its own), opened
//!   from the embedded default (peer mode, loopback TCP, no multicast) or a
//!   Zenoh config file;
//! - typed [`Publisher`]s and [`Subscription`]s that encode/decode through
//!   `shoal_proto::codec`, count what they reject, and queue into a
//!   [`DropOldestQueue`] (`shoal_proto::queue`);
//! - liveliness tokens and watchers, and a late-joiner queryable;
//! - [`Worker`]: a named background thread with a stop flag (the services'
//!   and the station's loops).
//!
//! It uses Zenoh's synchronous API (`Wait`), so services are plain threads.

// A library reports failures as errors; an `unwrap()` that cannot fail says why with `expect`.
#![warn(clippy::unwrap_used)]

pub mod acl;
pub mod worker;

pub use worker::{join_reporting, Worker};

use shoal_proto::codec::{self, DecodeError};
use shoal_proto::messages::WireMessage;
use shoal_proto::queue::DropOldestQueue;
use std::marker::PhantomData;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use zenoh::Wait;

/// Errors of the bus.
#[derive(Debug, thiserror::Error)]
pub enum BusError {
    #[error("zenoh config {path}: {reason}")]
    Config { path: PathBuf, reason: String },
    #[error("zenoh config: {0}")]
    ConfigValue(String),
    #[error("cannot open zenoh session: {0}")]
    Open(String),
    #[error("cannot start the {what} thread")]
    Thread {
        what: &'static str,
        #[source]
        source: std::io::Error,
    },
    #[error("zenoh {what} on {key}: {reason}")]
    Declare {
        what: &'static str,
        key: String,
        reason: String,
    },
    #[error("encoding for {key}")]
    Encode {
        key: String,
        #[source]
        source: codec::EncodeError,
    },
    #[error("publishing on {key}: {reason}")]
    Put { key: String, reason: String },
}

/// How to reach the other shoal processes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Connect {
    /// Embedded default: peer mode, loopback TCP only, no multicast. Listens
    /// on `listen` (port 0 = any) and connects to `peers`.
    Loopback { listen: Vec<u16>, peers: Vec<u16> },
    /// A full Zenoh JSON5 configuration file (routers, TLS, access control…).
    File(PathBuf),
    /// An in-process router for the demo and tests: listens on `port`.
    Router { port: u16 },
    /// An in-process router on `port` that also connects to the routers on
    /// `routers` (loopback ports), retrying every ≤ 0.5 s: two sides of a
    /// link, possibly through a relay.
    RouterLinked { port: u16, routers: Vec<u16> },
    /// A client of a router on loopback `port` (the demo's components).
    Client { port: u16 },
}

impl Connect {
    /// The usual embedded default: try to be the rendezvous on `port`, else join it.
    pub fn loopback_rendezvous(port: u16) -> Connect {
        if std::net::TcpListener::bind(("127.0.0.1", port)).is_ok() {
            Connect::Loopback {
                listen: vec![port],
                peers: vec![],
            }
        } else {
            Connect::Loopback {
                listen: vec![0],
                peers: vec![port],
            }
        }
    }

    fn config(&self) -> Result<zenoh::Config, BusError> {
        let endpoints = |ports: &[u16]| -> String {
            let list: Vec<String> = ports
                .iter()
                .map(|p| format!("\"tcp/127.0.0.1:{p}\""))
                .collect();
            format!("[{}]", list.join(","))
        };
        let set = |c: &mut zenoh::Config, k: &str, v: &str| {
            c.insert_json5(k, v)
                .map_err(|e| BusError::ConfigValue(format!("{k} = {v}: {e}")))
        };
        match self {
            Connect::File(path) => zenoh::Config::from_file(path).map_err(|e| BusError::Config {
                path: path.clone(),
                reason: e.to_string(),
            }),
            Connect::Loopback { listen, peers } => {
                let mut c = zenoh::Config::default();
                set(&mut c, "mode", "\"peer\"")?;
                set(&mut c, "listen/endpoints", &endpoints(listen))?;
                set(&mut c, "connect/endpoints", &endpoints(peers))?;
                set(&mut c, "scouting/multicast/enabled", "false")?;
                set(&mut c, "scouting/gossip/enabled", "true")?;
                Ok(c)
            }
            Connect::Client { port } => {
                let mut c = zenoh::Config::default();
                set(&mut c, "mode", "\"client\"")?;
                set(&mut c, "connect/endpoints", &endpoints(&[*port]))?;
                set(&mut c, "scouting/multicast/enabled", "false")?;
                Ok(c)
            }
            Connect::Router { port } => {
                let mut c = zenoh::Config::default();
                set(&mut c, "mode", "\"router\"")?;
                set(&mut c, "listen/endpoints", &endpoints(&[*port]))?;
                set(&mut c, "connect/endpoints", "[]")?;
                set(&mut c, "scouting/multicast/enabled", "false")?;
                // Nothing to connect to and no multicast: nobody to scout
                // for, so the open need not wait its 500 ms for them.
                set(&mut c, "scouting/delay", "0")?;
                Ok(c)
            }
            Connect::RouterLinked { port, routers } => {
                let mut c = zenoh::Config::default();
                set(&mut c, "mode", "\"router\"")?;
                set(&mut c, "listen/endpoints", &endpoints(&[*port]))?;
                set(&mut c, "connect/endpoints", &endpoints(routers))?;
                set(
                    &mut c,
                    "connect/retry",
                    "{ period_init_ms: 100, period_max_ms: 500, period_increase_factor: 2 }",
                )?;
                set(&mut c, "scouting/multicast/enabled", "false")?;
                set(&mut c, "scouting/gossip/enabled", "false")?;
                Ok(c)
            }
        }
    }
}

/// A free loopback TCP port (for the demo's in-process router).
pub fn free_port() -> std::io::Result<u16> {
    Ok(std::net::TcpListener::bind(("127.0.0.1", 0))?
        .local_addr()?
        .port())
}

/// Clients of an in-process router connect with this.
pub fn client_of(port: u16) -> Connect {
    Connect::Client { port }
}

/// One Zenoh session.
#[derive(Clone)]
pub struct Bus {
    session: zenoh::Session,
}

impl std::fmt::Debug for Bus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Bus")
            .field("zid", &self.session.zid())
            .finish()
    }
}

/// Counters of what a subscription received and rejected.
#[derive(Debug, Default)]
pub struct SubscriptionStats {
    pub received: AtomicU64,
    pub rejected: AtomicU64,
    last_error: Mutex<Option<String>>,
}

impl SubscriptionStats {
    pub fn received(&self) -> u64 {
        self.received.load(Ordering::Relaxed)
    }
    pub fn rejected(&self) -> u64 {
        self.rejected.load(Ordering::Relaxed)
    }
    /// The newest rejection's reason, for status reports.
    pub fn last_error(&self) -> Option<String> {
        self.last_error.lock().ok().and_then(|g| g.clone())
    }
}

/// Raw envelopes with the key each arrived on.
pub type RawQueue = DropOldestQueue<(String, Vec<u8>)>;

/// A decoded message with the key it arrived on.
#[derive(Debug, Clone)]
pub struct Received<M> {
    pub key: String,
    pub msg: M,
    /// The envelope bytes exactly as received (for recording).
    pub bytes: Arc<[u8]>,
    /// When the message arrived (monotonic), for latency measurements.
    pub received_at: std::time::Instant,
}

/// A typed subscription feeding a drop-oldest queue.
pub struct Subscription<M> {
    queue: DropOldestQueue<Received<M>>,
    stats: Arc<SubscriptionStats>,
    _sub: zenoh::pubsub::Subscriber<()>,
}

impl<M> std::fmt::Debug for Subscription<M> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Subscription")
            .field("stats", &self.stats)
            .finish()
    }
}

impl<M> Subscription<M> {
    pub fn recv_timeout(&self, timeout: Duration) -> Option<Received<M>> {
        self.queue.pop_timeout(timeout).ok()
    }
    pub fn drain(&self) -> Vec<Received<M>> {
        self.queue.drain()
    }
    pub fn stats(&self) -> &SubscriptionStats {
        &self.stats
    }
    /// Messages dropped because the consumer fell behind.
    pub fn dropped(&self) -> u64 {
        self.queue.dropped()
    }
}

/// A typed publisher on one key.
pub struct Publisher<M> {
    key: String,
    publisher: zenoh::pubsub::Publisher<'static>,
    _m: PhantomData<fn(M)>,
}

impl<M> std::fmt::Debug for Publisher<M> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Publisher").field("key", &self.key).finish()
    }
}

impl<M: WireMessage> Publisher<M> {
    /// Encode and publish.
    pub fn put(&self, msg: &M) -> Result<(), BusError> {
        let bytes = codec::encode(msg).map_err(|source| BusError::Encode {
            key: self.key.clone(),
            source,
        })?;
        self.put_bytes(bytes)
    }

    /// Publish already-encoded envelope bytes (replay).
    pub fn put_bytes(&self, bytes: Vec<u8>) -> Result<(), BusError> {
        self.publisher.put(bytes).wait().map_err(|e| BusError::Put {
            key: self.key.clone(),
            reason: e.to_string(),
        })
    }

    /// Whether a subscriber matching this key is known to the session now
    /// (its own, or one the router has told it of): a publisher whose
    /// session does not know of one does not send. `false` when the session
    /// cannot say.
    pub fn has_subscribers(&self) -> bool {
        self.publisher
            .matching_status()
            .wait()
            .is_ok_and(|s| s.matching())
    }

    pub fn key(&self) -> &str {
        &self.key
    }
}

/// A publisher of bytes in another vocabulary than shoal's envelope (ROS 2
/// CDR samples), each with an optional attachment.
pub struct RawPublisher {
    key: String,
    publisher: zenoh::pubsub::Publisher<'static>,
}

impl std::fmt::Debug for RawPublisher {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RawPublisher")
            .field("key", &self.key)
            .finish()
    }
}

impl RawPublisher {
    pub fn put(&self, bytes: Vec<u8>, attachment: Option<Vec<u8>>) -> Result<(), BusError> {
        let mut put = self.publisher.put(bytes);
        if let Some(a) = attachment {
            put = put.attachment(a);
        }
        put.wait().map_err(|e| BusError::Put {
            key: self.key.clone(),
            reason: e.to_string(),
        })
    }

    pub fn key(&self) -> &str {
        &self.key
    }
}

/// Keeps a liveliness token (or any declaration) alive until dropped.
pub struct Token {
    _token: zenoh::liveliness::LivelinessToken,
}

impl std::fmt::Debug for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Token")
    }
}

/// Keeps a callback declaration (liveliness watcher, queryable, raw subscriber) alive.
pub struct Declaration {
    _inner: Box<dyn std::any::Any + Send + Sync>,
}

impl std::fmt::Debug for Declaration {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Declaration")
    }
}

fn declare_err(what: &'static str, key: &str) -> impl FnOnce(zenoh::Error) -> BusError {
    let key = key.to_string();
    move |e| BusError::Declare {
        what,
        key,
        reason: e.to_string(),
    }
}

impl Bus {
    /// Open a session.
    pub fn open(connect: &Connect) -> Result<Bus, BusError> {
        let config = connect.config()?;
        let session = zenoh::open(config)
            .wait()
            .map_err(|e| BusError::Open(e.to_string()))?;
        Ok(Bus { session })
    }

    /// Close the session now (also done on drop of the last clone).
    pub fn close(&self) {
        if let Err(e) = self.session.close().wait() {
            tracing::debug!("closing zenoh session: {e}");
        }
    }

    /// A typed publisher on a concrete key. Camera frames go at Zenoh's
    /// `DataLow` priority, everything else at the default `Data`: a
    /// transport queues each priority apart, so a session whose queue is
    /// full of megabyte frames (a simulator, a camera driver) still sends
    /// the small messages it publishes beside them — truth, nav states,
    /// observations, commands — instead of dropping them on congestion,
    /// which Zenoh does without telling anyone.
    pub fn publisher<M: WireMessage>(&self, key: String) -> Result<Publisher<M>, BusError> {
        use zenoh::qos::Priority;
        let builder = self.session.declare_publisher(key.clone());
        let builder = if M::KIND == shoal_proto::MessageKind::CameraFrame {
            builder.priority(Priority::DataLow)
        } else {
            builder
        };
        let publisher = builder.wait().map_err(declare_err("publisher", &key))?;
        Ok(Publisher {
            key,
            publisher,
            _m: PhantomData,
        })
    }

    /// This session's Zenoh ID as Zenoh prints it (lowercase hex).
    pub fn zid(&self) -> String {
        self.session.zid().to_string()
    }

    /// A publisher of raw bytes on a concrete key.
    pub fn raw_publisher(&self, key: String) -> Result<RawPublisher, BusError> {
        let publisher = self
            .session
            .declare_publisher(key.clone())
            .wait()
            .map_err(declare_err("publisher", &key))?;
        Ok(RawPublisher { key, publisher })
    }

    /// Subscribe to `key_expr`; decoded messages go into a drop-oldest queue
    /// of `capacity`; undecodable ones are counted and logged once per reason.
    pub fn subscribe<M: WireMessage + Send + 'static>(
        &self,
        key_expr: &str,
        capacity: usize,
    ) -> Result<Subscription<M>, BusError> {
        let queue = DropOldestQueue::new(capacity);
        let stats = Arc::new(SubscriptionStats::default());
        let (q, st) = (queue.clone(), stats.clone());
        let sub = self
            .session
            .declare_subscriber(key_expr.to_string())
            .callback(move |sample| {
                if sample.kind() != zenoh::sample::SampleKind::Put {
                    return;
                }
                let bytes: Arc<[u8]> = Arc::from(sample.payload().to_bytes().as_ref());
                let key = sample.key_expr().as_str().to_string();
                match codec::decode::<M>(&bytes) {
                    Ok(msg) => {
                        st.received.fetch_add(1, Ordering::Relaxed);
                        q.push(Received {
                            key,
                            msg,
                            bytes,
                            received_at: std::time::Instant::now(),
                        });
                    }
                    Err(e) => note_rejection(&st, &key, &e),
                }
            })
            .wait()
            .map_err(declare_err("subscriber", key_expr))?;
        Ok(Subscription {
            queue,
            stats,
            _sub: sub,
        })
    }

    /// Subscribe to raw envelope bytes of any kind (the recorder).
    pub fn subscribe_raw(
        &self,
        key_expr: &str,
        capacity: usize,
    ) -> Result<(RawQueue, Declaration), BusError> {
        let queue = DropOldestQueue::new(capacity);
        let q = queue.clone();
        let sub = self
            .session
            .declare_subscriber(key_expr.to_string())
            .callback(move |sample| {
                if sample.kind() == zenoh::sample::SampleKind::Put {
                    q.push((
                        sample.key_expr().as_str().to_string(),
                        sample.payload().to_bytes().into_owned(),
                    ));
                }
            })
            .wait()
            .map_err(declare_err("subscriber", key_expr))?;
        Ok((
            queue,
            Declaration {
                _inner: Box::new(sub),
            },
        ))
    }

    /// Declare this process alive on `key` until the token is dropped.
    pub fn liveliness_token(&self, key: String) -> Result<Token, BusError> {
        let token = self
            .session
            .liveliness()
            .declare_token(key.clone())
            .wait()
            .map_err(declare_err("liveliness token", &key))?;
        Ok(Token { _token: token })
    }

    /// Watch liveliness tokens under `key_expr` (including those already
    /// alive): `on_change(key, alive)`.
    pub fn watch_liveliness(
        &self,
        key_expr: &str,
        on_change: impl Fn(&str, bool) + Send + Sync + 'static,
    ) -> Result<Declaration, BusError> {
        let sub = self
            .session
            .liveliness()
            .declare_subscriber(key_expr.to_string())
            .history(true)
            .callback(move |sample| {
                let alive = sample.kind() == zenoh::sample::SampleKind::Put;
                on_change(sample.key_expr().as_str(), alive);
            })
            .wait()
            .map_err(declare_err("liveliness subscriber", key_expr))?;
        Ok(Declaration {
            _inner: Box::new(sub),
        })
    }

    /// Answer queries on `key` with whatever `latest()` returns (already-encoded bytes).
    pub fn serve_latest(
        &self,
        key: String,
        latest: impl Fn() -> Option<Vec<u8>> + Send + Sync + 'static,
    ) -> Result<Declaration, BusError> {
        let reply_key = key.clone();
        let q = self
            .session
            .declare_queryable(key.clone())
            .callback(move |query| {
                if let Some(bytes) = latest() {
                    if let Err(e) = query.reply(reply_key.clone(), bytes).wait() {
                        tracing::debug!("replying on {reply_key}: {e}");
                    }
                }
            })
            .wait()
            .map_err(declare_err("queryable", &key))?;
        Ok(Declaration {
            _inner: Box::new(q),
        })
    }

    /// Ask a queryable for its latest message (the late-joiner catch-up).
    pub fn query_latest<M: WireMessage>(
        &self,
        key: &str,
        timeout: Duration,
    ) -> Result<Option<M>, BusError> {
        let replies = self
            .session
            .get(key.to_string())
            .timeout(timeout)
            .wait()
            .map_err(declare_err("query", key))?;
        while let Ok(reply) = replies.recv() {
            if let Ok(sample) = reply.result() {
                match codec::decode::<M>(&sample.payload().to_bytes()) {
                    Ok(m) => return Ok(Some(m)),
                    Err(e) => tracing::warn!("reply on {key} rejected: {e}"),
                }
            }
        }
        Ok(None)
    }
}

fn note_rejection(stats: &SubscriptionStats, key: &str, e: &DecodeError) {
    let n = stats.rejected.fetch_add(1, Ordering::Relaxed) + 1;
    let text = format!("{key}: {e}");
    if n.is_power_of_two() {
        tracing::warn!("rejected message #{n}: {text}");
    }
    if let Ok(mut g) = stats.last_error.lock() {
        *g = Some(text);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_router_with_nobody_to_scout_for_does_not_wait_to_scout() {
        // zenoh's default makes `open` wait 500 ms for peers to scout; the
        // demo's router has no endpoint to connect to and no multicast
        // (it was half of the demo's start-up, docs/results.md).
        let c = Connect::Router { port: 7447 }.config().unwrap();
        assert_eq!(c.get_json("scouting/delay").unwrap(), "0");
        assert_eq!(c.get_json("connect/endpoints").unwrap(), "[]");
        assert_eq!(c.get_json("scouting/multicast/enabled").unwrap(), "false");
        // Where there is someone to find, the wait stays zenoh's.
        let linked = Connect::RouterLinked {
            port: 7448,
            routers: vec![7447],
        }
        .config()
        .unwrap();
        assert_ne!(linked.get_json("scouting/delay").unwrap(), "0");
    }
}
