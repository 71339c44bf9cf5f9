//! Replay (`shoal replay`): a log's wire messages, byte for byte, with their
//! original relative timing (log time), optionally faster or slower and
//! within a time range, sent to a [`ReplaySink`]; republishing them on
//! Zenoh is `shoal_services::replay`.

use crate::reader::{scan_wire, summary_channels, ScanError};
use crate::recorder::envelope_kind;
use crate::RecordError;
use proto::MessageKind;
use std::collections::HashSet;
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

/// Where a replay sends a log's wire messages (Zenoh, in
/// `shoal_services::replay`).
pub trait ReplaySink {
    /// Get ready to send `kind` envelopes on `key`; called once per key,
    /// before its first message (for every wire channel of the file's summary
    /// up front, when it has one).
    fn declare(&mut self, key: &str, kind: MessageKind) -> Result<(), RecordError>;
    /// Send one recorded envelope on `key`, byte for byte.
    fn send(&mut self, key: &str, envelope: &[u8]) -> Result<(), RecordError>;
}

/// Send `path`'s wire messages to `sink` with their original relative
/// timing (scaled by `opts.rate`); `stop` ends it early (Ctrl-C).
pub fn replay_into(
    sink: &mut dyn ReplaySink,
    path: &Path,
    opts: &ReplayOptions,
    stop: &AtomicBool,
) -> Result<ReplaySummary, RecordError> {
    let mut declared: HashSet<String> = HashSet::new();
    let mut summary = ReplaySummary::default();
    let mut first_log: Option<u64> = None;
    let mut start: Option<(Instant, u64)> = None;
    let mut last_log = 0u64;
    let rate = if opts.rate > 0.0 { opts.rate } else { 1.0 };
    // Declare every publisher up front when the file has a summary (a
    // recovered or cleanly closed log); a killed log declares them as it goes.
    {
        let channels = summary_channels(path).map_err(|source| RecordError::NotMcap {
            path: path.to_path_buf(),
            source,
        })?;
        for c in &channels {
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
                    sink.declare(&c.topic, kind)?;
                    declared.insert(c.topic.clone());
                }
            }
        }
    }
    std::thread::sleep(opts.settle);
    let res = scan_wire(path, |channel, log_time, data| -> Result<(), RecordError> {
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
        if !declared.contains(key) {
            sink.declare(key, kind)?;
            declared.insert(key.to_string());
        }
        sink.send(key, data)?;
        summary.messages += 1;
        summary.bytes += data.len() as u64;
        last_log = log_time;
        Ok(())
    });
    match res {
        Ok(_) | Err(ScanError::Visitor(RecordError::Interrupted)) => {}
        Err(ScanError::Visitor(e)) => return Err(e),
        Err(ScanError::NotMcap(source)) => {
            return Err(RecordError::NotMcap {
                path: path.to_path_buf(),
                source,
            })
        }
    }
    if let Some((wall0, log0)) = start {
        summary.wall_time_s = wall0.elapsed().as_secs_f64();
        summary.log_span_s = last_log.saturating_sub(log0) as f64 * 1e-9;
    }
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::writer::{LogWriter, WriterOptions};
    use std::collections::BTreeMap;

    /// What a sink was given, in order.
    #[derive(Default)]
    struct Collect {
        declared: Vec<(String, MessageKind)>,
        sent: Vec<(String, Vec<u8>)>,
    }

    impl ReplaySink for Collect {
        fn declare(&mut self, key: &str, kind: MessageKind) -> Result<(), RecordError> {
            self.declared.push((key.to_string(), kind));
            Ok(())
        }
        fn send(&mut self, key: &str, envelope: &[u8]) -> Result<(), RecordError> {
            assert!(
                self.declared.iter().any(|(k, _)| k == key),
                "{key} sent before it was declared"
            );
            self.sent.push((key.to_string(), envelope.to_vec()));
            Ok(())
        }
    }

    /// Commands of vehicles 15 and 17 interleaved, 1 ms apart in log time.
    fn command_log(path: &Path) -> Vec<(String, Vec<u8>)> {
        let mut w =
            LogWriter::create(path, &WriterOptions::default(), &BTreeMap::new(), None, 1).unwrap();
        let mut written = Vec::new();
        for i in 0..20u64 {
            let vehicle = if i % 2 == 0 { 15 } else { 17 };
            let cmd = proto::VehicleCommand {
                vehicle,
                stamp_ns: i,
                velocity_body: [i as f64, 0.0, 0.0],
                yaw_rate: 0.0,
            };
            let key = format!("shoal/paper/{vehicle}/cmd");
            let bytes = proto::encode(&cmd).unwrap();
            w.write_wire(
                &key,
                Some(MessageKind::VehicleCommand),
                &bytes,
                1_000_000 * (i + 1),
                i,
            )
            .unwrap();
            written.push((key, bytes));
        }
        w.finish().unwrap();
        written
    }

    #[test]
    fn replay_sends_every_envelope_unchanged_in_order_and_filters_by_key() {
        let dir = std::env::temp_dir().join(format!("shoal-record-replay-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("commands.mcap");
        let written = command_log(&path);
        let fast = ReplayOptions {
            rate: f64::INFINITY,
            settle: Duration::ZERO,
            ..ReplayOptions::default()
        };
        let mut all = Collect::default();
        let s = replay_into(&mut all, &path, &fast, &AtomicBool::new(false)).unwrap();
        assert_eq!(all.sent, written);
        assert_eq!((s.messages, s.log_span_s), (20, 19e-3));
        // Both keys come from the file's summary, before the first message.
        let mut keys: Vec<&str> = all.declared.iter().map(|(k, _)| k.as_str()).collect();
        keys.sort();
        assert_eq!(keys, ["shoal/paper/15/cmd", "shoal/paper/17/cmd"]);

        let only_17 = ReplayOptions {
            key_prefix: Some("shoal/paper/17/".into()),
            ..fast
        };
        let mut some = Collect::default();
        replay_into(&mut some, &path, &only_17, &AtomicBool::new(false)).unwrap();
        let expected: Vec<_> = written
            .into_iter()
            .filter(|(k, _)| k.contains("/17/"))
            .collect();
        assert_eq!(some.sent, expected);
        assert_eq!(some.declared.len(), 1);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
