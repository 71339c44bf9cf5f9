//! Fault injection for shoal's fault tests and trials: a TCP relay that
//! degrades the link between two Zenoh routers, and a message-level fault
//! model for the transport boundary.
//!
//! What each fault **means** (TCP is a reliable byte stream, so packet-level
//! faults do not exist above it; this relay models what they become):
//!
//! | fault | [`Relay`] (byte stream between two routers) |
//! |---|---|
//! | delay | every chunk read is written `latency` later |
//! | jitter | plus a uniform `0..jitter` per chunk; order is kept (a chunk never overtakes the previous one), so jitter shows as head-of-line blocking, as on a real TCP link |
//! | packet loss | a lost segment on TCP is retransmitted: with probability `loss_stall_probability` per chunk, the chunk (and everything behind it) is held `loss_stall` longer (Linux's minimum RTO is 200 ms) |
//! | link loss / partition | [`LinkSwitch::cut`]: every open connection is shut down (both peers see the session break) and new ones are closed on accept until [`LinkSwitch::heal`]; Zenoh's routers then reconnect on their own |
//! | flapping link | [`Flap`]: the link is cut for `down` every `period` |
//! | bandwidth cap (acoustic modem) | `rate_bps`: each direction passes at most that many bits a second (a token bucket of 1 s burst); the relay reads no faster, so the sender's TCP window fills and its queue backs up (Zenoh's `CongestionControl::Drop` publishers then drop) — the kernel buffers on both sides still hold bytes, so latency grows until they are full: an acoustic link carries packets, not TCP, which is what `shoal eval links` measures |
//!
//! Message-level loss, duplication and reordering (a vehicle's radio
//! retransmitting, two paths to the ground station, a store-and-forward
//! hop) cannot be made by bending a TCP stream without corrupting it; they
//! are applied to the messages themselves before publishing, by
//! [`MessageFaults`], which counts each fault so a test can check that the
//! receiver neither double-counts nor misses them.
//!
//! Everything is seeded. The sockets and timers run as tasks on one
//! single-threaded tokio runtime on the relay's own thread (`relay`): a
//! relay is waiting on many sockets and timers at once, which is what tokio
//! is for, where the thread version needed two threads per direction per
//! connection. Its API stays synchronous ([`Relay::start`], drop to stop,
//! [`LinkSwitch`] from any thread).

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use shoal_fusion::link::TokenBucket;
use shoal_proto::splitmix::SplitMix64;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::tcp::{OwnedReadHalf, OwnedWriteHalf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, watch};
use tokio::task::JoinSet;

/// Errors of the relay.
#[derive(Debug, thiserror::Error)]
pub enum RelayError {
    #[error("relay cannot listen on {addr}: {source}")]
    Bind {
        addr: String,
        #[source]
        source: std::io::Error,
    },
    #[error("relay cannot start its thread: {0}")]
    Thread(#[source] std::io::Error),
    #[error("relay cannot start its tokio runtime: {0}")]
    Runtime(#[source] std::io::Error),
    #[error("fault plan: {0}")]
    Plan(String),
}

/// The link is cut for `down` at the start of every `period`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Flap {
    pub period: Duration,
    pub down: Duration,
}

/// Faults of the byte stream (see the module docs for what each means).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FaultPlan {
    /// Added to every chunk, each direction.
    pub latency: Duration,
    /// Plus uniform `0..jitter` per chunk (order kept).
    pub jitter: Duration,
    /// Probability per chunk of a retransmission stall (a lost TCP segment).
    pub loss_stall_probability: f64,
    /// Length of such a stall.
    pub loss_stall: Duration,
    /// Periodic link cuts.
    pub flap: Option<Flap>,
    /// Bits per second each direction passes at most (`None`: unlimited).
    pub rate_bps: Option<f64>,
    /// Seed of the relay's random stream.
    pub seed: u64,
}

impl Default for FaultPlan {
    /// A clean link.
    fn default() -> Self {
        Self {
            latency: Duration::ZERO,
            jitter: Duration::ZERO,
            loss_stall_probability: 0.0,
            loss_stall: Duration::from_millis(200),
            flap: None,
            rate_bps: None,
            seed: 1,
        }
    }
}

impl FaultPlan {
    /// Say what is wrong with the plan, if anything.
    pub fn validate(&self) -> Result<(), RelayError> {
        if !(0.0..=1.0).contains(&self.loss_stall_probability) {
            return Err(RelayError::Plan(format!(
                "loss_stall_probability {} is not in [0, 1]",
                self.loss_stall_probability
            )));
        }
        if let Some(r) = self.rate_bps {
            if !(r.is_finite() && r >= 8.0) {
                return Err(RelayError::Plan(format!(
                    "rate {r} bit/s is not a finite rate of at least one byte a second"
                )));
            }
        }
        if let Some(f) = self.flap {
            if f.period.is_zero() || f.down >= f.period {
                return Err(RelayError::Plan(format!(
                    "flap: down {:?} must be shorter than a non-zero period {:?}",
                    f.down, f.period
                )));
            }
        }
        Ok(())
    }
}

/// Counters of a relay.
#[derive(Debug, Default)]
pub struct RelayStats {
    pub connections: AtomicU64,
    /// Connections closed on accept because the link was cut.
    pub refused: AtomicU64,
    /// Open connections closed by a cut.
    pub cut: AtomicU64,
    pub bytes_forwarded: AtomicU64,
    pub chunks_forwarded: AtomicU64,
    pub stalls: AtomicU64,
    /// Bytes passed through the bandwidth cap.
    pub rate_limited_bytes: AtomicU64,
}

/// The link's switch: cut (partition) and heal, from any thread.
#[derive(Debug, Clone)]
pub struct LinkSwitch {
    up: Arc<watch::Sender<bool>>,
}

impl LinkSwitch {
    fn new() -> Self {
        Self {
            up: Arc::new(watch::Sender::new(true)),
        }
    }
    pub fn is_up(&self) -> bool {
        *self.up.borrow()
    }
    /// Partition: close every open connection and refuse new ones.
    pub fn cut(&self) {
        self.up.send_replace(false);
    }
    /// Heal: accept connections again.
    pub fn heal(&self) {
        self.up.send_replace(true);
    }
    /// A connection's view of the link: subscribed before its first check,
    /// so a cut that comes after that check is always seen.
    fn watch(&self) -> watch::Receiver<bool> {
        self.up.subscribe()
    }
}

/// Resolves when the link is (or goes) down.
async fn link_down(link: &mut watch::Receiver<bool>) {
    loop {
        if !*link.borrow_and_update() {
            return;
        }
        if link.changed().await.is_err() {
            return;
        }
    }
}

/// A running fault-injecting TCP relay: accepts on `listen`, connects each
/// accepted connection to `upstream`, and forwards both directions under a
/// [`FaultPlan`]. Stops (closing everything) when dropped.
#[derive(Debug)]
pub struct Relay {
    local: SocketAddr,
    switch: LinkSwitch,
    stats: Arc<RelayStats>,
    stop: watch::Sender<bool>,
    thread: Option<JoinHandle<()>>,
}

impl Relay {
    /// Start relaying `listen` → `upstream`.
    pub fn start(listen: &str, upstream: SocketAddr, plan: FaultPlan) -> Result<Relay, RelayError> {
        plan.validate()?;
        let bind = |source| RelayError::Bind {
            addr: listen.to_string(),
            source,
        };
        let listener = std::net::TcpListener::bind(listen).map_err(bind)?;
        let local = listener.local_addr().map_err(bind)?;
        listener.set_nonblocking(true).map_err(bind)?;
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(RelayError::Runtime)?;
        let stats = Arc::new(RelayStats::default());
        let switch = LinkSwitch::new();
        let stop = watch::Sender::new(false);
        let (sw, st, stop_rx) = (switch.clone(), stats.clone(), stop.subscribe());
        let thread = std::thread::Builder::new()
            .name("relay".into())
            .spawn(move || {
                runtime.block_on(async move {
                    let listener = match TcpListener::from_std(listener) {
                        Ok(l) => l,
                        Err(e) => {
                            tracing::error!("relay: listener on {local}: {e}");
                            return;
                        }
                    };
                    let mut tasks = JoinSet::new();
                    if let Some(flap) = plan.flap {
                        tasks.spawn(flap_loop(flap, sw.clone()));
                    }
                    accept_loop(listener, upstream, plan, (sw, st), stop_rx, &mut tasks).await;
                    // The cut that came with the stop closed the connections; end what is left.
                    tasks.shutdown().await;
                });
            })
            .map_err(RelayError::Thread)?;
        Ok(Relay {
            local,
            switch,
            stats,
            stop,
            thread: Some(thread),
        })
    }

    /// Where the relay listens (the port, if `listen` asked for port 0).
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }
    /// Cut and heal the link.
    pub fn switch(&self) -> &LinkSwitch {
        &self.switch
    }
    pub fn stats(&self) -> &RelayStats {
        &self.stats
    }
}

impl Drop for Relay {
    fn drop(&mut self) {
        self.switch.cut();
        self.stop.send_replace(true);
        if let Some(t) = self.thread.take() {
            shoal_bus::join_reporting(t);
        }
    }
}

async fn flap_loop(flap: Flap, switch: LinkSwitch) {
    let mut start = tokio::time::Instant::now() + flap.period - flap.down;
    loop {
        tokio::time::sleep_until(start).await;
        tracing::debug!("relay: link down for {:?}", flap.down);
        switch.cut();
        tokio::time::sleep_until(start + flap.down).await;
        switch.heal();
        start += flap.period;
    }
}

async fn accept_loop(
    listener: TcpListener,
    upstream: SocketAddr,
    plan: FaultPlan,
    (switch, stats): (LinkSwitch, Arc<RelayStats>),
    mut stop: watch::Receiver<bool>,
    tasks: &mut JoinSet<()>,
) {
    let mut seed = SplitMix64::new(plan.seed);
    loop {
        let accepted = tokio::select! {
            _ = stop.wait_for(|stop| *stop) => return,
            r = listener.accept() => r,
        };
        // Finished connections leave the set as they end.
        while tasks.try_join_next().is_some() {}
        match accepted {
            Ok((down, peer)) => {
                let rngs = [
                    SplitMix64::new(seed.next_u64()),
                    SplitMix64::new(seed.next_u64()),
                ];
                let link = switch.watch();
                tasks.spawn(connection(
                    down,
                    peer,
                    upstream,
                    plan,
                    rngs,
                    link,
                    stats.clone(),
                ));
            }
            Err(e) => {
                tracing::warn!("relay accept: {e}");
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        }
    }
}

/// One relayed connection: refused while the link is cut, else connected
/// upstream and pumped both ways until both directions end or the link is
/// cut (then both sockets close, and both peers see the session break).
async fn connection(
    down: TcpStream,
    peer: SocketAddr,
    upstream: SocketAddr,
    plan: FaultPlan,
    [rng_up, rng_down]: [SplitMix64; 2],
    mut link: watch::Receiver<bool>,
    stats: Arc<RelayStats>,
) {
    if !*link.borrow_and_update() {
        stats.refused.fetch_add(1, Ordering::Relaxed);
        return;
    }
    let up = match tokio::time::timeout(Duration::from_secs(2), TcpStream::connect(upstream)).await
    {
        Ok(Ok(s)) => s,
        Ok(Err(e)) => {
            tracing::debug!("relay: upstream {upstream} for {peer}: {e}");
            return;
        }
        Err(_) => {
            tracing::debug!("relay: upstream {upstream} for {peer}: no answer in 2 s");
            return;
        }
    };
    if !*link.borrow_and_update() {
        stats.refused.fetch_add(1, Ordering::Relaxed);
        return;
    }
    let _ = down.set_nodelay(true);
    let _ = up.set_nodelay(true);
    stats.connections.fetch_add(1, Ordering::Relaxed);
    let (down_read, down_write) = down.into_split();
    let (up_read, up_write) = up.into_split();
    tokio::select! {
        _ = async {
            tokio::join!(
                pump(down_read, up_write, plan, rng_up, stats.clone()),
                pump(up_read, down_write, plan, rng_down, stats.clone()),
            )
        } => {}
        () = link_down(&mut link) => {
            stats.cut.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// One direction: a reader that stamps each chunk with its due time and a
/// writer that sends it then, never before the previous chunk; at the
/// reader's end the writer sends what is queued, then closes its side.
async fn pump(
    mut from: OwnedReadHalf,
    mut to: OwnedWriteHalf,
    plan: FaultPlan,
    mut rng: SplitMix64,
    stats: Arc<RelayStats>,
) {
    let (tx, mut rx) = mpsc::unbounded_channel::<(Instant, Vec<u8>)>();
    let writer_stats = stats.clone();
    let writer = async move {
        while let Some((due, chunk)) = rx.recv().await {
            tokio::time::sleep_until(tokio::time::Instant::from_std(due)).await;
            if to.write_all(&chunk).await.is_err() {
                break;
            }
            writer_stats
                .bytes_forwarded
                .fetch_add(chunk.len() as u64, Ordering::Relaxed);
            writer_stats
                .chunks_forwarded
                .fetch_add(1, Ordering::Relaxed);
        }
        let _ = to.shutdown().await;
    };
    let reader = async move {
        let mut last_due = Instant::now();
        let started = Instant::now();
        let elapsed_ns = || started.elapsed().as_nanos() as u64;
        // A cap: a bucket of one second's bits, and reads no larger than that.
        let mut bucket = plan.rate_bps.and_then(|r| TokenBucket::new(r, r, 0).ok());
        let read_max = plan
            .rate_bps
            .map_or(64 * 1024, |r| ((r / 8.0) as usize).clamp(1, 64 * 1024));
        let mut buf = vec![0u8; read_max];
        loop {
            let n = match from.read(&mut buf).await {
                Ok(0) | Err(_) => break,
                Ok(n) => n,
            };
            if let Some(b) = bucket.as_mut() {
                let bits = (n * 8) as f64;
                while !b.try_take(bits, elapsed_ns()) {
                    let wait = b
                        .wait_ns(bits, elapsed_ns())
                        .unwrap_or(1_000_000)
                        .max(1_000_000);
                    tokio::time::sleep(Duration::from_nanos(wait)).await;
                }
                stats
                    .rate_limited_bytes
                    .fetch_add(n as u64, Ordering::Relaxed);
            }
            let mut extra = plan.latency;
            if !plan.jitter.is_zero() {
                extra += plan.jitter.mul_f64(rng.unit());
            }
            if plan.loss_stall_probability > 0.0 && rng.unit() < plan.loss_stall_probability {
                stats.stalls.fetch_add(1, Ordering::Relaxed);
                extra += plan.loss_stall;
            }
            let due = (Instant::now() + extra).max(last_due);
            last_due = due;
            if tx.send((due, buf[..n].to_vec())).is_err() {
                break;
            }
        }
    };
    tokio::join!(reader, writer);
}

/// Faults applied to whole messages at the transport boundary.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MessageFaultPlan {
    /// Probability a message is lost.
    pub loss: f64,
    /// Probability a (delivered) message is delivered twice.
    pub duplicate: f64,
    /// Messages are shuffled within consecutive windows of this many (0 or 1: order kept).
    pub reorder_window: usize,
    pub seed: u64,
}

impl Default for MessageFaultPlan {
    fn default() -> Self {
        Self {
            loss: 0.0,
            duplicate: 0.0,
            reorder_window: 0,
            seed: 1,
        }
    }
}

/// What [`MessageFaults`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MessageFaultStats {
    pub offered: u64,
    pub lost: u64,
    /// Extra copies delivered.
    pub duplicated: u64,
    /// Messages delivered at a different position than offered.
    pub reordered: u64,
    pub delivered: u64,
}

/// Applies a [`MessageFaultPlan`] to batches of messages, deterministically for a seed.
#[derive(Debug, Clone)]
pub struct MessageFaults {
    plan: MessageFaultPlan,
    rng: SplitMix64,
    stats: MessageFaultStats,
}

impl MessageFaults {
    pub fn new(plan: MessageFaultPlan) -> Self {
        Self {
            rng: SplitMix64::new(plan.seed),
            plan,
            stats: MessageFaultStats::default(),
        }
    }

    /// The batch as it arrives: some lost, some twice, shuffled within windows.
    pub fn apply<T: Clone>(&mut self, batch: Vec<T>) -> Vec<T> {
        self.stats.offered += batch.len() as u64;
        let mut out: Vec<(usize, T)> = Vec::with_capacity(batch.len());
        for (i, m) in batch.into_iter().enumerate() {
            if self.rng.unit() < self.plan.loss {
                self.stats.lost += 1;
                continue;
            }
            if self.rng.unit() < self.plan.duplicate {
                self.stats.duplicated += 1;
                out.push((i, m.clone()));
            }
            out.push((i, m));
        }
        let w = self.plan.reorder_window;
        if w > 1 {
            for window in out.chunks_mut(w) {
                for k in (1..window.len()).rev() {
                    let j = self.rng.below(k + 1);
                    window.swap(k, j);
                }
            }
            let mut sorted: Vec<usize> = out.iter().map(|(i, _)| *i).collect();
            sorted.sort_unstable();
            self.stats.reordered += out
                .iter()
                .zip(&sorted)
                .filter(|((i, _), s)| i != *s)
                .count() as u64;
        }
        self.stats.delivered += out.len() as u64;
        out.into_iter().map(|(_, m)| m).collect()
    }

    pub fn stats(&self) -> MessageFaultStats {
        self.stats
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{Read, Write};
    use std::net::{TcpListener, TcpStream};

    fn echo_server() -> (SocketAddr, JoinHandle<()>) {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = l.local_addr().unwrap();
        let t = std::thread::spawn(move || {
            for s in l.incoming().take(4) {
                let Ok(mut s) = s else { return };
                std::thread::spawn(move || {
                    let mut buf = [0u8; 4096];
                    while let Ok(n) = s.read(&mut buf) {
                        if n == 0 || s.write_all(&buf[..n]).is_err() {
                            break;
                        }
                    }
                });
            }
        });
        (addr, t)
    }

    fn round_trip(addr: SocketAddr, payload: &[u8]) -> std::io::Result<(Vec<u8>, Duration)> {
        let mut s = TcpStream::connect(addr)?;
        s.set_read_timeout(Some(Duration::from_secs(5)))?;
        let t0 = Instant::now();
        s.write_all(payload)?;
        let mut got = vec![0u8; payload.len()];
        s.read_exact(&mut got)?;
        Ok((got, t0.elapsed()))
    }

    #[test]
    fn delayed_jittery_stream_arrives_intact_and_in_order() {
        let (echo, _t) = echo_server();
        let plan = FaultPlan {
            latency: Duration::from_millis(40),
            jitter: Duration::from_millis(20),
            loss_stall_probability: 0.3,
            loss_stall: Duration::from_millis(30),
            ..FaultPlan::default()
        };
        let relay = Relay::start("127.0.0.1:0", echo, plan).unwrap();
        let payload: Vec<u8> = (0..200_000u32).map(|i| (i * 7 % 251) as u8).collect();
        let (got, rtt) = round_trip(relay.local_addr(), &payload).unwrap();
        assert_eq!(got, payload, "bytes changed or reordered through the relay");
        // Both directions delayed at least the latency.
        assert!(rtt >= Duration::from_millis(80), "round trip {rtt:?}");
        // The writer counts a chunk just after writing it: give it a moment.
        let t0 = Instant::now();
        while relay.stats().bytes_forwarded.load(Ordering::Relaxed) < 400_000
            && t0.elapsed() < Duration::from_secs(2)
        {
            std::thread::sleep(Duration::from_millis(5));
        }
        assert_eq!(
            relay.stats().bytes_forwarded.load(Ordering::Relaxed),
            400_000
        );
    }

    /// Issue #22: the bandwidth cap passes the stream intact at its rate:
    /// 60 kB through a 160 kbit/s cap (one second's burst, 20 kB) takes at
    /// least 2 s each way, where the clean relay takes milliseconds.
    #[test]
    fn capped_link_passes_the_stream_intact_at_its_rate() {
        let (echo, _t) = echo_server();
        let plan = FaultPlan {
            rate_bps: Some(160_000.0),
            ..FaultPlan::default()
        };
        let relay = Relay::start("127.0.0.1:0", echo, plan).unwrap();
        let payload: Vec<u8> = (0..60_000u32).map(|i| (i * 13 % 251) as u8).collect();
        let mut s = TcpStream::connect(relay.local_addr()).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
        let t0 = Instant::now();
        let writer = {
            let mut w = s.try_clone().unwrap();
            let p = payload.clone();
            std::thread::spawn(move || w.write_all(&p).unwrap())
        };
        let mut got = vec![0u8; payload.len()];
        s.read_exact(&mut got).unwrap();
        let took = t0.elapsed();
        writer.join().unwrap();
        assert_eq!(got, payload);
        assert!(took >= Duration::from_millis(1900), "{took:?}");
        assert!(took < Duration::from_secs(12), "{took:?}");
        assert!(relay.stats().rate_limited_bytes.load(Ordering::Relaxed) >= 60_000);
        let bad = FaultPlan {
            rate_bps: Some(0.0),
            ..FaultPlan::default()
        };
        assert!(bad.validate().is_err());
    }

    #[test]
    fn cut_link_breaks_sessions_and_refuses_until_healed() {
        let (echo, _t) = echo_server();
        let relay = Relay::start("127.0.0.1:0", echo, FaultPlan::default()).unwrap();
        let mut s = TcpStream::connect(relay.local_addr()).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        s.write_all(b"ping").unwrap();
        let mut b = [0u8; 4];
        s.read_exact(&mut b).unwrap();
        relay.switch().cut();
        // The open session ends (EOF or reset), it does not hang.
        let r = s.read(&mut b);
        assert!(matches!(r, Ok(0) | Err(_)), "{r:?}");
        // A new session is closed at once while cut.
        let mut s2 = TcpStream::connect(relay.local_addr()).unwrap();
        s2.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let _ = s2.write_all(b"ping");
        assert!(matches!(s2.read(&mut b), Ok(0) | Err(_)));
        relay.switch().heal();
        let (got, _) = round_trip(relay.local_addr(), b"pong").unwrap();
        assert_eq!(&got, b"pong");
        assert!(relay.stats().cut.load(Ordering::Relaxed) >= 1);
        assert!(relay.stats().refused.load(Ordering::Relaxed) >= 1);
    }

    #[test]
    fn flapping_link_is_down_for_its_share_of_each_period() {
        let (echo, _t) = echo_server();
        let plan = FaultPlan {
            flap: Some(Flap {
                period: Duration::from_millis(300),
                down: Duration::from_millis(100),
            }),
            ..FaultPlan::default()
        };
        let relay = Relay::start("127.0.0.1:0", echo, plan).unwrap();
        let (mut up, mut down) = (0u32, 0u32);
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_millis(1200) {
            if relay.switch().is_up() {
                up += 1;
            } else {
                down += 1;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        let share = f64::from(down) / f64::from(up + down);
        assert!((0.15..0.55).contains(&share), "down {share:.2} of the time");
    }

    #[test]
    fn invalid_plans_are_refused() {
        let bad = FaultPlan {
            loss_stall_probability: 1.5,
            ..FaultPlan::default()
        };
        assert!(matches!(bad.validate(), Err(RelayError::Plan(_))));
        let bad = FaultPlan {
            flap: Some(Flap {
                period: Duration::from_secs(1),
                down: Duration::from_secs(2),
            }),
            ..FaultPlan::default()
        };
        assert!(bad.validate().is_err());
    }

    #[test]
    fn message_faults_count_what_they_do_and_repeat_for_a_seed() {
        let plan = MessageFaultPlan {
            loss: 0.1,
            duplicate: 0.2,
            reorder_window: 5,
            seed: 42,
        };
        let mut a = MessageFaults::new(plan);
        let mut b = MessageFaults::new(plan);
        let input: Vec<u32> = (0..1000).collect();
        let out_a = a.apply(input.clone());
        assert_eq!(out_a, b.apply(input.clone()));
        let s = a.stats();
        assert_eq!(s.offered, 1000);
        assert_eq!(s.delivered, out_a.len() as u64);
        assert_eq!(s.delivered, 1000 - s.lost + s.duplicated);
        assert!(s.lost > 50 && s.lost < 150, "{s:?}");
        assert!(s.duplicated > 120 && s.duplicated < 280, "{s:?}");
        assert!(s.reordered > 0);
        let mut unique = out_a.clone();
        unique.sort_unstable();
        unique.dedup();
        assert_eq!(unique.len() as u64, 1000 - s.lost);
    }
}
