//! MCAP logs of swarm trials (issue #8).
//!
//! - [`Recording`]: writes every wire message it is handed **unchanged** (one
//!   channel per key, so replay is bit-exact), and beside it the same
//!   information in Foxglove's well-known schemas ([`foxglove`]), into
//!   zstd-chunked MCAP flushed often enough that a killed recorder leaves
//!   every complete chunk readable;
//! - [`reader`]: tolerant scanning and [`reader::recover`] of such files;
//! - [`replay`]: a log's messages with their original timing, into a [`ReplaySink`];
//! - [`refuse`]: offline, deterministic re-fusion of a log's observations;
//! - [`info`]: vehicles, duration, messages per channel, detection rate, gaps.
//!
//! No Zenoh: the recorder's subscriptions and replay's publishers are
//! `shoal_services::recorder` and `shoal_services::replay`. File layout and
//! channel names are documented in `docs/logs.md`.

// A library reports failures as errors; an `unwrap()` that cannot fail says why with `expect`.
#![warn(clippy::unwrap_used)]

extern crate shoal_proto as proto;

pub mod foxglove;
pub mod info;
pub mod reader;
pub mod recorder;
pub mod recover;
pub mod refuse;
pub mod replay;
pub mod truth_score;
pub mod writer;

/// The `mcap` crate this one is built on (for strict readers in tests and tools).
pub use mcap;

pub use info::{info, LogInfo};
pub use recorder::{RecordOptions, RecordSummary, Recording};
pub use recover::{recover, RecoverReport};
pub use refuse::{refuse, FuseOptions, FuseSummary, SolveAt};
pub use replay::{replay_into, ReplayOptions, ReplaySink, ReplaySummary};
pub use writer::{ChannelCount, LogWriter, WriterOptions};

use std::path::PathBuf;

/// Errors of recording, reading, replaying and re-fusing logs.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("MCAP {path}: {source}")]
    Mcap {
        path: PathBuf,
        #[source]
        source: mcap::McapError,
    },
    #[error("{}", path.display())]
    NotMcap {
        path: PathBuf,
        #[source]
        source: reader::NotMcap,
    },
    #[error("{}: fleet attached to the log", path.display())]
    AttachedFleet {
        path: PathBuf,
        #[source]
        source: proto::config::ConfigError,
    },
    #[error("ROS 2 type {0} has no ros2msg definition in shoal (it is read, never written)")]
    NoRos2Definition(&'static str),
    #[error("encoding a {what}")]
    Encode {
        what: &'static str,
        #[source]
        source: proto::codec::EncodeError,
    },
    #[error("{}: the log was recorded with fleet {recorded:?}, the fleet given is {given:?}", path.display())]
    FleetMismatch {
        path: std::path::PathBuf,
        recorded: String,
        given: String,
    },
    #[error("{0}: the log carries no fleet file (or its attachment is damaged, see `shoal log info`); pass one with --fleet")]
    NoFleet(PathBuf),
    #[error("Foxglove message on {topic}: protobuf encoding failed: {reason}")]
    FoxgloveEncode { topic: String, reason: String },
    /// The transport a recording or replay runs over (Zenoh, in `shoal-services`).
    #[error(transparent)]
    Transport(Box<dyn std::error::Error + Send + Sync>),
    #[error("cannot start the recorder thread")]
    Thread(#[source] std::io::Error),
    #[error("the recorder's writer thread panicked")]
    WriterPanicked,
    #[error("the recorder was already stopped")]
    AlreadyStopped,
    #[error("interrupted")]
    Interrupted,
    #[error(transparent)]
    Output(#[from] proto::files::OutputError),
    #[error("solve rate {rate_hz} Hz: expected a finite rate above 0 and at most 1e9 Hz (one solve per nanosecond of the log's clock)")]
    SolveRate { rate_hz: f64 },
}
