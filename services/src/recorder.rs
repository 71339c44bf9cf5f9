//! The recorder (`shoal record`): subscribes to a fleet's Zenoh keys (and,
//! with Foxglove channels on, its liveliness tokens) and hands every wire
//! message, unchanged, to a `shoal_record::Recording`, which writes the MCAP
//! log on its own thread behind bounded drop-oldest queues.

use shoal_bus::{Bus, Declaration};
use shoal_proto::clock::{Clock, WallClock};
use shoal_proto::config::Fleet;
use shoal_record::recorder::{self, LivelinessEvents, RecorderStats, Recording};
use shoal_record::{RecordError, RecordOptions, RecordSummary};
use std::path::Path;
use std::sync::Arc;

/// The recorder (see [`Recorder::spawn`]).
#[derive(Debug)]
pub struct Recorder;

/// A running recorder; [`RecorderHandle::stop`] finishes the file.
pub struct RecorderHandle {
    declarations: Vec<Declaration>,
    /// Keeps the Zenoh session open even if the caller drops its `Bus`.
    bus: Option<Bus>,
    recording: Recording,
}

impl std::fmt::Debug for RecorderHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RecorderHandle")
            .field("stats", self.recording.stats())
            .finish()
    }
}

impl RecorderHandle {
    /// Messages dropped so far because the writer fell behind.
    pub fn dropped(&self) -> u64 {
        self.recording.dropped()
    }
    pub fn stats(&self) -> &RecorderStats {
        self.recording.stats()
    }
    /// Whether the writer thread ended early (an I/O error); `stop` returns it.
    pub fn failed(&self) -> bool {
        self.recording.failed()
    }

    /// Unsubscribe, write what is queued, close the file with its summary.
    pub fn stop(mut self) -> Result<RecordSummary, RecordError> {
        self.unsubscribe();
        self.recording.finish()
    }

    fn unsubscribe(&mut self) {
        self.declarations.clear();
        self.bus = None;
    }
}

impl Drop for RecorderHandle {
    fn drop(&mut self) {
        // Unsubscribe first; the recording then finishes the file as it drops.
        self.unsubscribe();
    }
}

fn transport(e: shoal_bus::BusError) -> RecordError {
    RecordError::Transport(Box::new(e))
}

impl Recorder {
    /// Start recording `fleet`'s traffic on `bus` into `path`.
    pub fn spawn(
        bus: &Bus,
        fleet: Arc<Fleet>,
        path: &Path,
        opts: RecordOptions,
    ) -> Result<RecorderHandle, RecordError> {
        let writer = recorder::create_log(&fleet, path, &opts)?;
        let keys = fleet.keys();
        let mut queues = Vec::new();
        let mut declarations = Vec::new();
        // Nodes appearing and going away (their liveliness tokens), with the
        // wall time the recorder heard it.
        let liveliness: LivelinessEvents = LivelinessEvents::new(1024);
        if opts.foxglove {
            let l = liveliness.clone();
            declarations.push(
                bus.watch_liveliness(&keys.all_alive(), move |key, alive| {
                    l.push((key.to_string(), alive, WallClock.now_ns()));
                })
                .map_err(transport)?,
            );
        }
        for (e, capacity) in &recorder::subscriptions(&keys, &opts) {
            let (q, d) = bus.subscribe_raw(e, *capacity).map_err(transport)?;
            queues.push(q);
            declarations.push(d);
        }
        let recording = Recording::start(writer, fleet, path, opts, queues, liveliness)?;
        Ok(RecorderHandle {
            declarations,
            bus: Some(bus.clone()),
            recording,
        })
    }
}
