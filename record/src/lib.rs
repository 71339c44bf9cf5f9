//! MCAP logs of swarm trials (issue #8).
//!
//! - [`Recorder`]: subscribes to a fleet's Zenoh keys and writes every wire
//!   message **unchanged** (one channel per key, so replay is bit-exact), and
//!   beside it the same information in Foxglove's well-known schemas
//!   ([`foxglove`]), into zstd-chunked MCAP flushed often enough that a
//!   killed recorder leaves every complete chunk readable;
//! - [`reader`]: tolerant scanning and [`reader::recover`] of such files;
//! - [`replay`]: republish a log on Zenoh with its original timing;
//! - [`refuse`]: offline, deterministic re-fusion of a log's observations;
//! - [`info`]: vehicles, duration, messages per channel, detection rate, gaps.
//!
//! File layout and channel names are documented in `docs/logs.md`.

extern crate shoal_proto as proto;

pub mod foxglove;
pub mod info;
pub mod reader;
pub mod recorder;
pub mod refuse;
pub mod replay;
pub mod writer;

/// The `mcap` crate this one is built on (for strict readers in tests and tools).
pub use mcap;

pub use info::{info, LogInfo};
pub use reader::{recover, RecoverReport};
pub use recorder::{RecordOptions, RecordSummary, Recorder, RecorderHandle};
pub use refuse::{refuse, FuseOptions, FuseSummary, SolveAt};
pub use replay::{replay, ReplayOptions, ReplaySummary};
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
    #[error("{0}")]
    Format(String),
    #[error("{0}: the log carries no fleet file; pass one with --fleet")]
    NoFleet(PathBuf),
    #[error("JSON: {0}")]
    Json(String),
    #[error(transparent)]
    Bus(#[from] shoal_bus::BusError),
    #[error("cannot start the recorder thread: {0}")]
    Thread(String),
    #[error("the recorder's writer thread panicked")]
    WriterPanicked,
    #[error("the recorder was already stopped")]
    AlreadyStopped,
    #[error("interrupted")]
    Interrupted,
}
