//! Replay (`shoal replay`): republish a log's wire messages on Zenoh, byte
//! for byte, with their original relative timing (log time), optionally
//! faster or slower and within a time range.

use crate::reader::{read_file, scan_wire, ScanError};
use crate::recorder::envelope_kind;
use crate::RecordError;
use proto::MessageKind;
use shoal_bus::{Bus, Publisher};
use std::collections::HashMap;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

#[derive(Debug, Clone)]
pub struct ReplayOptions {
    /// Speed factor (2.0: twice as fast). `f64::INFINITY`: as fast as possible.
    pub rate: f64,
    /// Seconds from the start of the log.
    pub from_s: Option<f64>,
    pub to_s: Option<f64>,
    /// Which message kinds to republish (`None`: all).
    pub kinds: Option<Vec<MessageKind>>,
    /// Only keys starting with this (e.g. one vehicle's cameras,
    /// `shoal/<fleet>/<vehicle>/cam/`); `None`: every key.
    pub key_prefix: Option<String>,
    /// Pause between declaring the publishers (from the file's summary) and
    /// the first message, so subscribers' routes are in place and the first
    /// messages are not lost.
    pub settle: Duration,
}

impl Default for ReplayOptions {
    fn default() -> Self {
        Self {
            rate: 1.0,
            from_s: None,
            to_s: None,
            kinds: None,
            key_prefix: None,
            settle: Duration::from_millis(300),
        }
    }
}

#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct ReplaySummary {
    pub messages: u64,
    pub bytes: u64,
    /// Log seconds replayed.
    pub log_span_s: f64,
    pub wall_time_s: f64,
    /// Largest lateness of a message against its schedule, milliseconds.
    pub max_late_ms: f64,
}

/// One publisher per key; the type parameter of `Publisher` only matters for
/// typed `put`, replay sends the recorded envelope bytes as they are.
enum AnyPublisher {
    Observation(Publisher<proto::Observation>),
    FleetMap(Publisher<proto::FleetMap>),
    CameraFrame(Publisher<proto::CameraFrame>),
    SimTruth(Publisher<proto::SimTruth>),
    NodeStatus(Publisher<proto::NodeStatus>),
    VehicleCommand(Publisher<proto::VehicleCommand>),
}

impl AnyPublisher {
    fn declare(bus: &Bus, key: &str, kind: MessageKind) -> Result<AnyPublisher, RecordError> {
        let k = key.to_string();
        Ok(match kind {
            MessageKind::Observation => AnyPublisher::Observation(bus.publisher(k)?),
            MessageKind::FleetMap => AnyPublisher::FleetMap(bus.publisher(k)?),
            MessageKind::CameraFrame => AnyPublisher::CameraFrame(bus.publisher(k)?),
            MessageKind::SimTruth => AnyPublisher::SimTruth(bus.publisher(k)?),
            MessageKind::NodeStatus => AnyPublisher::NodeStatus(bus.publisher(k)?),
            MessageKind::VehicleCommand => AnyPublisher::VehicleCommand(bus.publisher(k)?),
        })
    }
    fn put_bytes(&self, bytes: Vec<u8>) -> Result<(), shoal_bus::BusError> {
        match self {
            AnyPublisher::Observation(p) => p.put_bytes(bytes),
            AnyPublisher::FleetMap(p) => p.put_bytes(bytes),
            AnyPublisher::CameraFrame(p) => p.put_bytes(bytes),
            AnyPublisher::SimTruth(p) => p.put_bytes(bytes),
            AnyPublisher::NodeStatus(p) => p.put_bytes(bytes),
            AnyPublisher::VehicleCommand(p) => p.put_bytes(bytes),
        }
    }
}

/// Republish `path` on `bus`; `stop` ends it early (Ctrl-C).
pub fn replay(
    bus: &Bus,
    path: &Path,
    opts: &ReplayOptions,
    stop: &AtomicBool,
) -> Result<ReplaySummary, RecordError> {
    let buf = read_file(path)?;
    let mut publishers: HashMap<String, AnyPublisher> = HashMap::new();
    let mut summary = ReplaySummary::default();
    let mut first_log: Option<u64> = None;
    let mut start: Option<(Instant, u64)> = None;
    let mut last_log = 0u64;
    let rate = if opts.rate > 0.0 { opts.rate } else { 1.0 };
    // Declare every publisher up front when the file has a summary (a
    // recovered or cleanly closed log); a killed log declares them as it goes.
    if let Ok(Some(summary)) = mcap::Summary::read(&buf) {
        for c in summary.channels.values() {
            let kind = c
                .metadata
                .get("kind")
                .and_then(|k| k.parse::<u16>().ok())
                .and_then(MessageKind::from_u16);
            if let (Some(kind), true) = (kind, c.message_encoding == crate::writer::WIRE_ENCODING) {
                if opts.kinds.as_ref().is_none_or(|ks| ks.contains(&kind))
                    && opts
                        .key_prefix
                        .as_ref()
                        .is_none_or(|p| c.topic.starts_with(p.as_str()))
                {
                    publishers.insert(c.topic.clone(), AnyPublisher::declare(bus, &c.topic, kind)?);
                }
            }
        }
    }
    std::thread::sleep(opts.settle);
    let res = scan_wire(&buf, |channel, log_time, data| -> Result<(), RecordError> {
        if stop.load(Ordering::Relaxed) {
            return Err(RecordError::Interrupted);
        }
        let t0 = *first_log.get_or_insert(log_time);
        let rel_s = log_time.saturating_sub(t0) as f64 * 1e-9;
        if opts.from_s.is_some_and(|f| rel_s < f) {
            return Ok(());
        }
        if opts.to_s.is_some_and(|t| rel_s > t) {
            return Err(RecordError::Interrupted);
        }
        let Some(kind) = envelope_kind(data) else {
            return Ok(());
        };
        if opts.kinds.as_ref().is_some_and(|ks| !ks.contains(&kind))
            || opts
                .key_prefix
                .as_ref()
                .is_some_and(|p| !channel.topic.starts_with(p.as_str()))
        {
            return Ok(());
        }
        let (wall0, log0) = *start.get_or_insert((Instant::now(), log_time));
        if rate.is_finite() {
            let due =
                wall0 + Duration::from_secs_f64(log_time.saturating_sub(log0) as f64 * 1e-9 / rate);
            let now = Instant::now();
            if due > now {
                std::thread::sleep(due - now);
            } else {
                summary.max_late_ms = summary.max_late_ms.max((now - due).as_secs_f64() * 1e3);
            }
        }
        let key = channel.topic.as_str();
        if !publishers.contains_key(key) {
            publishers.insert(key.to_string(), AnyPublisher::declare(bus, key, kind)?);
        }
        if let Some(p) = publishers.get(key) {
            p.put_bytes(data.to_vec())?;
        }
        summary.messages += 1;
        summary.bytes += data.len() as u64;
        last_log = log_time;
        Ok(())
    });
    match res {
        Ok(_) | Err(ScanError::Visitor(RecordError::Interrupted)) => {}
        Err(ScanError::Visitor(e)) => return Err(e),
        Err(e) => return Err(RecordError::Format(format!("{}: {e}", path.display()))),
    }
    if let Some((wall0, log0)) = start {
        summary.wall_time_s = wall0.elapsed().as_secs_f64();
        summary.log_span_s = last_log.saturating_sub(log0) as f64 * 1e-9;
    }
    Ok(summary)
}
