//! Re-detection on recorded frames (`shoal node --source mcap:FILE`; not to
//! be confused with the Rerun viewer): one vehicle's node run again on the
//! camera frames of a recorded trial, with whatever pipeline parameters it is
//! given now — the frames are replayed onto Zenoh under their original keys and
//! stamps, the node hears them as it would the live cameras, and its
//! observations go out on Zenoh (for `shoal fusion`, `shoal record`, the
//! station) stamped with the original capture times.

use shoal_bus::Bus;
use shoal_proto::MessageKind;
use shoal_record::{RecordError, ReplayOptions};
use shoal_services::node::{spawn, NodeConfig, NodeError, Source};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// Frames a camera queue holds in a re-detection: the replay may run faster
/// than the pipeline, and a re-detection should drop nothing it can avoid dropping.
pub const REDETECT_QUEUE: usize = 64;

#[derive(Debug, thiserror::Error)]
pub enum RedetectError {
    #[error("node: {0}")]
    Node(#[from] NodeError),
    #[error("reading the log: {0}")]
    Log(#[from] RecordError),
    #[error("{0}: the log holds no camera frame of vehicle {1}")]
    NoFrames(String, u32),
}

/// What a re-detection did.
#[derive(Debug, Clone, PartialEq)]
pub struct RedetectSummary {
    pub frames_replayed: u64,
    pub frames_processed: u64,
    pub frames_dropped: u64,
    pub observations_sent: u64,
    pub mean_latency_ms: Option<f64>,
    pub wall_time_s: f64,
}

/// Run the node `cfg` (its `source` is replaced by the Zenoh one) on `log`'s frames
/// of `cfg.vehicle`, replayed at `rate` × their original pace; returns once
/// every replayed frame has been processed or dropped (or `stop` is set).
pub fn redetect(
    bus: &Bus,
    mut cfg: NodeConfig,
    log: &Path,
    rate: f64,
    stop: &AtomicBool,
) -> Result<RedetectSummary, RedetectError> {
    let started = Instant::now();
    let vehicle = cfg.vehicle;
    let prefix = cfg.fleet.keys().camera_prefix(vehicle);
    cfg.source = Source::Zenoh;
    cfg.queue_capacity = cfg.queue_capacity.max(REDETECT_QUEUE);
    let node = spawn(bus, cfg)?;
    let replayed = shoal_services::replay::replay(
        bus,
        log,
        &ReplayOptions {
            rate,
            kinds: Some(vec![MessageKind::CameraFrame]),
            key_prefix: Some(prefix),
            // The node's subscriptions must be routed before the first frame.
            settle: Duration::from_millis(800),
            ..ReplayOptions::default()
        },
        stop,
    )?;
    if replayed.messages == 0 {
        node.stop();
        return Err(RedetectError::NoFrames(log.display().to_string(), vehicle));
    }
    // Drain: wait until every replayed frame is accounted for, or nothing
    // has moved for 5 s (frames lost in transit are then reported as such).
    let stats = node.stats().clone();
    let done = || stats.frames_processed() + stats.frames_dropped();
    let (mut last, mut last_change) = (done(), Instant::now());
    while done() < replayed.messages
        && last_change.elapsed() < Duration::from_secs(5)
        && !stop.load(Ordering::Relaxed)
    {
        std::thread::sleep(Duration::from_millis(50));
        if done() != last {
            last = done();
            last_change = Instant::now();
        }
    }
    // Let the last observations leave before the publishers close.
    std::thread::sleep(Duration::from_millis(200));
    let summary = RedetectSummary {
        frames_replayed: replayed.messages,
        frames_processed: stats.frames_processed(),
        frames_dropped: stats.frames_dropped(),
        observations_sent: stats.observations_sent.load(Ordering::Relaxed),
        mean_latency_ms: stats.mean_latency_ms(),
        wall_time_s: started.elapsed().as_secs_f64(),
    };
    node.stop();
    Ok(summary)
}
