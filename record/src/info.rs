//! `shoal log info`: what a log holds — vehicles, duration, messages per
//! channel, detection rate, gaps.

use crate::reader::{header, scan, ChannelInfo, Item, Skipped};
use crate::recorder::envelope_kind;
use crate::RecordError;
use proto::{KeyKind, MessageKind, NodeStatus, VehicleId};
use std::collections::BTreeMap;
use std::path::Path;

/// One channel's figures.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct ChannelFigures {
    pub topic: String,
    pub schema: String,
    pub message_encoding: String,
    pub messages: u64,
    pub bytes: u64,
    /// Messages per second of log time between its first and last message.
    pub rate_hz: f64,
}

/// A silence on a channel much longer than its usual spacing.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Gap {
    pub topic: String,
    /// Seconds from the start of the log.
    pub from_s: f64,
    pub length_s: f64,
}

/// Detections of one vehicle.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct DetectionFigures {
    pub vehicle: VehicleId,
    pub observations: u64,
    /// Observations per second of log time.
    pub per_second: f64,
    /// Detections per frame processed, from the vehicle's newest status (None: no status logged).
    pub per_frame: Option<f64>,
}

#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct LogInfo {
    pub complete: bool,
    pub damage: Option<String>,
    /// Damaged regions skipped (the first ones; `skipped_regions` counts all).
    pub skipped: Vec<Skipped>,
    pub skipped_regions: u64,
    pub skipped_bytes: u64,
    pub metadata: BTreeMap<String, String>,
    pub has_fleet_file: bool,
    pub vehicles: Vec<VehicleId>,
    pub start_unix_ns: u64,
    pub duration_s: f64,
    /// Span of the message stamps (simulated or capture clock), seconds.
    pub stamp_span_s: f64,
    pub messages: u64,
    pub chunks: u64,
    pub file_bytes: u64,
    pub channels: Vec<ChannelFigures>,
    pub detections: Vec<DetectionFigures>,
    pub gaps: Vec<Gap>,
}

/// A gap is a silence longer than this many times the channel's median spacing…
const GAP_FACTOR: f64 = 5.0;
/// …and longer than this (seconds), so jitter of fast channels is not reported.
const GAP_MIN_S: f64 = 1.0;

pub fn info(path: &Path) -> Result<LogInfo, RecordError> {
    let h = header(path).map_err(|source| RecordError::NotMcap {
        path: path.to_path_buf(),
        source,
    })?;
    let mut times: BTreeMap<u16, Vec<u64>> = BTreeMap::new();
    let mut bytes: BTreeMap<u16, u64> = BTreeMap::new();
    let mut vehicles = std::collections::BTreeSet::new();
    let mut obs_per_vehicle: BTreeMap<VehicleId, u64> = BTreeMap::new();
    let mut last_status: BTreeMap<VehicleId, NodeStatus> = BTreeMap::new();
    let (mut stamp_min, mut stamp_max) = (u64::MAX, 0u64);
    let keys = h
        .metadata
        .get("fleet")
        .and_then(|f| proto::Keys::new(f).ok());
    let outcome = scan(path, |item| -> Result<(), std::convert::Infallible> {
        if let Item::Message {
            channel,
            log_time,
            publish_time,
            data,
            ..
        } = item
        {
            times.entry(channel.id).or_default().push(log_time);
            *bytes.entry(channel.id).or_default() += data.len() as u64;
            if channel.is_wire() {
                if publish_time != log_time {
                    stamp_min = stamp_min.min(publish_time);
                    stamp_max = stamp_max.max(publish_time);
                }
                let kk = keys.as_ref().and_then(|k| k.parse(&channel.topic).ok());
                match kk {
                    Some(KeyKind::Observations { vehicle }) => {
                        vehicles.insert(vehicle);
                        *obs_per_vehicle.entry(vehicle).or_default() += 1;
                    }
                    Some(
                        KeyKind::Status { vehicle }
                        | KeyKind::Frame { vehicle, .. }
                        | KeyKind::Command { vehicle },
                    ) => {
                        vehicles.insert(vehicle);
                    }
                    _ => {}
                }
                if envelope_kind(data) == Some(MessageKind::NodeStatus) {
                    if let Ok(s) = proto::decode::<NodeStatus>(data) {
                        last_status.insert(s.vehicle, s);
                    }
                }
            }
        }
        Ok(())
    })
    .map_err(|e| match e.into_record_error(path) {
        Ok(never) => match never {},
        Err(e) => e,
    })?;
    let all: Vec<u64> = times
        .values()
        .flat_map(|t| [t[0], t[t.len() - 1]])
        .collect();
    let t0 = all.iter().copied().min().unwrap_or(0);
    let t1 = all.iter().copied().max().unwrap_or(0);
    let duration_s = t1.saturating_sub(t0) as f64 * 1e-9;
    let mut channels = Vec::new();
    let mut gaps = Vec::new();
    for (id, c) in &outcome.channels {
        let t = times.get(id).cloned().unwrap_or_default();
        let schema = outcome
            .schemas
            .get(&c.schema_id)
            .map(|s| s.name.clone())
            .unwrap_or_default();
        channels.push(channel_figures(
            c,
            schema,
            &t,
            bytes.get(id).copied().unwrap_or(0),
        ));
        if c.is_wire() {
            gaps.extend(channel_gaps(&c.topic, &t, t0));
        }
    }
    channels.sort_by(|a, b| a.topic.cmp(&b.topic));
    let detections = detection_figures(&vehicles, &obs_per_vehicle, &last_status, duration_s);
    Ok(LogInfo {
        complete: outcome.complete,
        damage: outcome.damage,
        has_fleet_file: h.fleet_toml.is_some(),
        start_unix_ns: h
            .metadata
            .get("start_time_unix_ns")
            .and_then(|s| s.parse().ok())
            .unwrap_or(t0),
        metadata: h.metadata,
        vehicles: vehicles.into_iter().collect(),
        duration_s,
        stamp_span_s: if stamp_max >= stamp_min {
            (stamp_max - stamp_min) as f64 * 1e-9
        } else {
            0.0
        },
        messages: outcome.messages,
        chunks: outcome.chunks,
        file_bytes: outcome.file_bytes,
        skipped: outcome.skipped,
        skipped_regions: outcome.skipped_regions,
        skipped_bytes: outcome.skipped_bytes,
        channels,
        detections,
        gaps,
    })
}

/// One channel's figures from its message log times `t` and payload bytes.
fn channel_figures(c: &ChannelInfo, schema: String, t: &[u64], bytes: u64) -> ChannelFigures {
    let span = if t.len() > 1 {
        (t[t.len() - 1] - t[0]) as f64 * 1e-9
    } else {
        0.0
    };
    ChannelFigures {
        topic: c.topic.clone(),
        schema,
        message_encoding: c.message_encoding.clone(),
        messages: t.len() as u64,
        bytes,
        rate_hz: if span > 0.0 {
            (t.len() - 1) as f64 / span
        } else {
            0.0
        },
    }
}

/// Silences on one channel (message log times `t`, log start `t0`) longer
/// than `GAP_FACTOR` times its median spacing and than `GAP_MIN_S`.
fn channel_gaps(topic: &str, t: &[u64], t0: u64) -> Vec<Gap> {
    let mut gaps = Vec::new();
    if t.len() <= 2 {
        return gaps;
    }
    let d: Vec<u64> = t.windows(2).map(|w| w[1].saturating_sub(w[0])).collect();
    let mut sorted = d.clone();
    sorted.sort_unstable();
    let median = sorted[sorted.len() / 2] as f64 * 1e-9;
    let limit = (median * GAP_FACTOR).max(GAP_MIN_S);
    for (i, dt) in d.into_iter().enumerate() {
        let dt_s = dt as f64 * 1e-9;
        if dt_s > limit {
            gaps.push(Gap {
                topic: topic.to_string(),
                from_s: t[i].saturating_sub(t0) as f64 * 1e-9,
                length_s: dt_s,
            });
        }
    }
    gaps
}

/// Detection figures of each vehicle seen in the log.
fn detection_figures(
    vehicles: &std::collections::BTreeSet<VehicleId>,
    obs_per_vehicle: &BTreeMap<VehicleId, u64>,
    last_status: &BTreeMap<VehicleId, NodeStatus>,
    duration_s: f64,
) -> Vec<DetectionFigures> {
    vehicles
        .iter()
        .map(|&v| {
            let n = obs_per_vehicle.get(&v).copied().unwrap_or(0);
            let per_frame = last_status.get(&v).and_then(|s| {
                let frames: u64 = s.cameras.iter().map(|c| c.frames_in).sum();
                let det: u64 = s.cameras.iter().map(|c| c.detections).sum();
                (frames > 0).then(|| det as f64 / frames as f64)
            });
            DetectionFigures {
                vehicle: v,
                observations: n,
                per_second: if duration_s > 0.0 {
                    n as f64 / duration_s
                } else {
                    0.0
                },
                per_frame,
            }
        })
        .collect()
}

impl std::fmt::Display for LogInfo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "{} — {:.1} MB, {} messages in {} chunks, {:.1} s of log time ({:.1} s of message stamps)",
            if self.complete { "complete" } else { "INCOMPLETE" },
            self.file_bytes as f64 / 1e6,
            self.messages,
            self.chunks,
            self.duration_s,
            self.stamp_span_s
        )?;
        if let Some(d) = &self.damage {
            writeln!(f, "  damage: {d} (run `shoal log recover`)")?;
        }
        for s in &self.skipped {
            writeln!(
                f,
                "  skipped bytes {}..{}: {}",
                s.offset,
                s.offset + s.bytes,
                s.reason
            )?;
        }
        if self.skipped_regions > self.skipped.len() as u64 {
            writeln!(
                f,
                "  … {} more damaged regions ({} bytes skipped in all)",
                self.skipped_regions - self.skipped.len() as u64,
                self.skipped_bytes
            )?;
        }
        for (k, v) in &self.metadata {
            writeln!(f, "  {k}: {v}")?;
        }
        writeln!(
            f,
            "  fleet file attached: {}",
            if self.has_fleet_file { "yes" } else { "no" }
        )?;
        writeln!(f, "vehicles: {:?}", self.vehicles)?;
        writeln!(f, "detections:")?;
        for d in &self.detections {
            let pf = d
                .per_frame
                .map_or_else(|| "-".to_string(), |p| format!("{p:.2}"));
            writeln!(
                f,
                "  v{:<4} {:>7} observations, {:>6.2}/s, {} per frame",
                d.vehicle, d.observations, d.per_second, pf
            )?;
        }
        writeln!(f, "channels:")?;
        writeln!(
            f,
            "  {:<42} {:<26} {:>8} {:>10} {:>8}",
            "topic", "schema", "messages", "MB", "Hz"
        )?;
        for c in &self.channels {
            writeln!(
                f,
                "  {:<42} {:<26} {:>8} {:>10.3} {:>8.2}",
                c.topic,
                c.schema,
                c.messages,
                c.bytes as f64 / 1e6,
                c.rate_hz
            )?;
        }
        if self.gaps.is_empty() {
            writeln!(f, "gaps: none")?;
        } else {
            writeln!(
                f,
                "gaps (> {GAP_FACTOR}x the median spacing and > {GAP_MIN_S} s):"
            )?;
            for g in &self.gaps {
                writeln!(
                    f,
                    "  {:<42} at {:>8.2} s for {:.2} s",
                    g.topic, g.from_s, g.length_s
                )?;
            }
        }
        Ok(())
    }
}
