//! Replay (`shoal replay`): republish a log's wire messages on Zenoh, byte
//! for byte, with their original relative timing (log time), optionally
//! faster or slower and within a time range. Reading and pacing the log is
//! `shoal_record::replay`; this module declares the publishers.

use shoal_bus::{Bus, BusError, Publisher};
use shoal_proto::MessageKind;
use shoal_record::replay::{replay_into, ReplaySink};
use shoal_record::{RecordError, ReplayOptions, ReplaySummary};
use std::collections::HashMap;
use std::path::Path;
use std::sync::atomic::AtomicBool;

/// One publisher per key; the type parameter of `Publisher` only matters for
/// typed `put`, replay sends the recorded envelope bytes as they are.
enum AnyPublisher {
    Observation(Publisher<shoal_proto::Observation>),
    FleetMap(Publisher<shoal_proto::FleetMap>),
    CameraFrame(Publisher<shoal_proto::CameraFrame>),
    SimTruth(Publisher<shoal_proto::SimTruth>),
    NodeStatus(Publisher<shoal_proto::NodeStatus>),
    VehicleCommand(Publisher<shoal_proto::VehicleCommand>),
    NavState(Publisher<shoal_proto::NavState>),
    LinkPacket(Publisher<shoal_proto::compact::LinkPacket>),
}

impl AnyPublisher {
    fn declare(bus: &Bus, key: &str, kind: MessageKind) -> Result<AnyPublisher, BusError> {
        let k = key.to_string();
        Ok(match kind {
            MessageKind::Observation => AnyPublisher::Observation(bus.publisher(k)?),
            MessageKind::FleetMap => AnyPublisher::FleetMap(bus.publisher(k)?),
            MessageKind::CameraFrame => AnyPublisher::CameraFrame(bus.publisher(k)?),
            MessageKind::SimTruth => AnyPublisher::SimTruth(bus.publisher(k)?),
            MessageKind::NodeStatus => AnyPublisher::NodeStatus(bus.publisher(k)?),
            MessageKind::VehicleCommand => AnyPublisher::VehicleCommand(bus.publisher(k)?),
            MessageKind::NavState => AnyPublisher::NavState(bus.publisher(k)?),
            MessageKind::LinkPacket => AnyPublisher::LinkPacket(bus.publisher(k)?),
        })
    }
    fn put_bytes(&self, bytes: Vec<u8>) -> Result<(), BusError> {
        match self {
            AnyPublisher::Observation(p) => p.put_bytes(bytes),
            AnyPublisher::FleetMap(p) => p.put_bytes(bytes),
            AnyPublisher::CameraFrame(p) => p.put_bytes(bytes),
            AnyPublisher::SimTruth(p) => p.put_bytes(bytes),
            AnyPublisher::NodeStatus(p) => p.put_bytes(bytes),
            AnyPublisher::VehicleCommand(p) => p.put_bytes(bytes),
            AnyPublisher::NavState(p) => p.put_bytes(bytes),
            AnyPublisher::LinkPacket(p) => p.put_bytes(bytes),
        }
    }
}

/// The log's keys as Zenoh publishers on one session.
struct ZenohSink<'a> {
    bus: &'a Bus,
    publishers: HashMap<String, AnyPublisher>,
}

fn transport(e: BusError) -> RecordError {
    RecordError::Transport(Box::new(e))
}

impl ReplaySink for ZenohSink<'_> {
    fn declare(&mut self, key: &str, kind: MessageKind) -> Result<(), RecordError> {
        let p = AnyPublisher::declare(self.bus, key, kind).map_err(transport)?;
        self.publishers.insert(key.to_string(), p);
        Ok(())
    }
    fn send(&mut self, key: &str, envelope: &[u8]) -> Result<(), RecordError> {
        match self.publishers.get(key) {
            Some(p) => p.put_bytes(envelope.to_vec()).map_err(transport),
            None => Ok(()),
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
    let mut sink = ZenohSink {
        bus,
        publishers: HashMap::new(),
    };
    replay_into(&mut sink, path, opts, stop)
}
