//! `shoal eval probe big-log`: a log of a given size for measuring what
//! reading one costs (`shoal log info`, `log recover`, `fuse` on 2 GB, issue
//! #20). The wire messages of a real log are written again and again, each
//! pass shifted in time by the source's span (capture stamps inside the
//! envelopes too), so the result reads as one long trial. Link packets,
//! whose stamps sit inside a compact payload, are left out.

use crate::eval::EvalError;
use shoal_proto::codec::{self, decode};
use shoal_proto::messages::{
    CameraFrame, FleetMap, MessageKind, NodeStatus, Observation, SimTruth, VehicleCommand,
    WireMessage,
};
use shoal_proto::NavState;
use shoal_record::reader::{scan, Item};
use shoal_record::writer::{LogWriter, WriterOptions};
use std::collections::BTreeMap;
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct BigLogArgs {
    /// A shoal log to repeat (`shoal demo --mcap-frames` makes a dense one).
    #[arg(value_name = "LOG")]
    pub mcap: PathBuf,
    /// Stop once the file on disk holds this many gigabytes (10^9 bytes; zstd chunks).
    #[arg(long, default_value_t = 2.0, value_parser = positive_gb)]
    pub gb: f64,
    #[arg(long)]
    pub out: PathBuf,
}

fn positive_gb(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("{s:?}: expected a positive number of gigabytes")),
    }
}

fn setup(what: &str, e: impl std::fmt::Display) -> EvalError {
    EvalError::Setup(format!("{what}: {e}"))
}

/// One wire message of the source.
struct Wire {
    key: String,
    log_time: u64,
    kind: Option<MessageKind>,
    bytes: Vec<u8>,
}

/// `bytes` with its capture stamp(s) moved by `dt` ns; `None` for a message
/// that is not shifted (link packets) or does not decode.
fn shifted(kind: MessageKind, bytes: &[u8], dt: u64) -> Option<(Vec<u8>, u64)> {
    fn again<M: WireMessage>(m: &M, stamp: u64) -> Option<(Vec<u8>, u64)> {
        codec::encode(m).ok().map(|b| (b, stamp))
    }
    match kind {
        MessageKind::Observation => {
            let mut m: Observation = decode(bytes).ok()?;
            m.stamp_ns += dt;
            again(&m, m.stamp_ns)
        }
        MessageKind::FleetMap => {
            let mut m: FleetMap = decode(bytes).ok()?;
            m.stamp_ns += dt;
            for v in &mut m.vehicles {
                if v.last_seen_ns > 0 {
                    v.last_seen_ns += dt;
                }
            }
            for e in &mut m.edges {
                e.stamp_ns += dt;
            }
            again(&m, m.stamp_ns)
        }
        MessageKind::SimTruth => {
            let mut m: SimTruth = decode(bytes).ok()?;
            m.stamp_ns += dt;
            again(&m, m.stamp_ns)
        }
        MessageKind::CameraFrame => {
            let mut m: CameraFrame = decode(bytes).ok()?;
            m.stamp_ns += dt;
            again(&m, m.stamp_ns)
        }
        MessageKind::NodeStatus => {
            let mut m: NodeStatus = decode(bytes).ok()?;
            m.stamp_ns += dt;
            again(&m, m.stamp_ns)
        }
        MessageKind::NavState => {
            let mut m: NavState = decode(bytes).ok()?;
            m.stamp_ns += dt;
            again(&m, m.stamp_ns)
        }
        MessageKind::VehicleCommand => {
            let mut m: VehicleCommand = decode(bytes).ok()?;
            m.stamp_ns += dt;
            again(&m, m.stamp_ns)
        }
        MessageKind::LinkPacket => None,
    }
}

pub fn run(a: &BigLogArgs) -> Result<(), EvalError> {
    let path = &a.mcap;
    let name = path.display().to_string();
    let mut wire = Vec::new();
    let mut metadata = BTreeMap::new();
    let mut fleet_toml = None;
    scan(path, |item| -> Result<(), shoal_record::reader::Stop> {
        match item {
            Item::Message {
                channel,
                log_time,
                data,
                ..
            } if channel.is_wire() => wire.push(Wire {
                key: channel.topic.clone(),
                log_time,
                kind: shoal_record::recorder::envelope_kind(data),
                bytes: data.to_vec(),
            }),
            Item::Metadata { name, metadata: m } if name == shoal_record::writer::METADATA_NAME => {
                metadata = m.clone();
            }
            Item::Attachment { name, data, .. }
                if name == shoal_record::writer::FLEET_ATTACHMENT =>
            {
                fleet_toml = String::from_utf8(data.to_vec()).ok();
            }
            _ => {}
        }
        Ok(())
    })
    .map_err(|e| setup(&name, e))?;
    let (Some(first), Some(last)) = (
        wire.iter().map(|w| w.log_time).min(),
        wire.iter().map(|w| w.log_time).max(),
    ) else {
        return Err(setup(&name, "no wire message in the log"));
    };
    let span = last - first + 1_000_000_000;
    let target = (a.gb * 1e9) as u64;
    let mut w = LogWriter::create(
        &a.out,
        &WriterOptions::default(),
        &metadata,
        fleet_toml.as_deref(),
        first,
    )
    .map_err(|e| setup(&a.out.display().to_string(), e))?;
    let (mut written, mut messages, mut passes) = (0u64, 0u64, 0u64);
    let on_disk = || std::fs::metadata(&a.out).map_or(0, |m| m.len());
    'passes: loop {
        let dt = passes * span;
        for m in &wire {
            let moved = match m.kind {
                Some(k) if dt > 0 => shifted(k, &m.bytes, dt),
                _ => Some((m.bytes.clone(), m.log_time)),
            };
            let Some((bytes, stamp)) = moved else {
                continue;
            };
            w.write_wire(&m.key, m.kind, &bytes, m.log_time + dt, stamp)
                .map_err(|e| setup(&a.out.display().to_string(), e))?;
            written += bytes.len() as u64;
            messages += 1;
            if on_disk() >= target {
                break 'passes;
            }
        }
        passes += 1;
        crate::outln!(
            "pass {passes}: {:.2} GB of messages, {:.2} GB on disk",
            written as f64 / 1e9,
            on_disk() as f64 / 1e9
        );
    }
    w.finish()
        .map_err(|e| setup(&a.out.display().to_string(), e))?;
    let size = std::fs::metadata(&a.out).map_or(0, |m| m.len());
    crate::outln!(
        "{}: {messages} messages in {passes} whole passes and part of one of {name} ({:.1} s each), {:.2} GB of messages, {:.2} GB on disk",
        a.out.display(),
        span as f64 * 1e-9,
        written as f64 / 1e9,
        size as f64 / 1e9
    );
    Ok(())
}
