//! [`LogWriter`]: an MCAP file in shoal's layout.
//!
//! - one channel per Zenoh key, carrying the envelope bytes unchanged
//!   (message encoding [`WIRE_ENCODING`]; schema named after the message kind,
//!   `MessageKind::schema_name`; channel metadata `schema`, `schema_version`,
//!   `kind`);
//! - Foxglove channels in protobuf ([`crate::foxglove`]);
//! - or, in the ROS 2 profile ([`ROS2_PROFILE`]), only ROS 2 channels: CDR
//!   messages with `ros2msg` schemas, as `rosbag2`'s MCAP storage writes them;
//! - a `shoal` metadata record (fleet, water, software, start time) and the
//!   fleet file as an attachment, both at the start of the file so that a
//!   killed recording still carries them;
//! - zstd chunks, closed at least every `flush_interval` by the recorder.

use crate::foxglove::{FoxgloveMessage, FoxgloveSchema};
use crate::RecordError;
use mcap::records::{MessageHeader, Metadata};
use proto::codec::SCHEMA_VERSION;
use proto::ros2::msgs::RosType;
use proto::MessageKind;
use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

/// Message encoding of the raw channels: shoal's versioned envelope (`docs/wire.md`).
pub const WIRE_ENCODING: &str = "shoal-envelope";
/// Schema encoding of the raw channels' schema records (their data is a pointer to `docs/wire.md`).
pub const WIRE_SCHEMA_ENCODING: &str = "shoal-wire";
/// Name of the file-level metadata record.
pub const METADATA_NAME: &str = "shoal";
/// Name of the fleet-file attachment.
pub const FLEET_ATTACHMENT: &str = "fleet.toml";
/// Version of shoal's log layout, in the `shoal` metadata record as
/// `log_format`: 2 writes the Foxglove channels in protobuf; 1 (no
/// `log_format` key) wrote them in JSON. The wire channels are the same in
/// both, and the readers use only those, so every version reads.
pub const LOG_FORMAT: u32 = 2;
/// MCAP profile string of shoal logs.
pub const PROFILE: &str = "shoal";
/// MCAP profile string of ROS 2 logs (only CDR channels with `ros2msg` schemas).
pub const ROS2_PROFILE: &str = "ros2";

/// Messages and bytes written on one channel.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct ChannelCount {
    pub messages: u64,
    /// Message payload bytes (before compression).
    pub bytes: u64,
}

/// Settings of the file itself.
#[derive(Debug, Clone)]
pub struct WriterOptions {
    /// Target uncompressed chunk size, bytes.
    pub chunk_size: u64,
    /// zstd level (0: the library default, 3).
    pub zstd_level: u32,
    /// The header's profile: [`PROFILE`] or [`ROS2_PROFILE`].
    pub profile: &'static str,
}

impl Default for WriterOptions {
    fn default() -> Self {
        Self {
            chunk_size: 4 << 20,
            zstd_level: 0,
            profile: PROFILE,
        }
    }
}

/// An MCAP log being written.
pub struct LogWriter {
    path: PathBuf,
    w: mcap::Writer<BufWriter<File>>,
    raw_schemas: HashMap<MessageKind, u16>,
    fox_schemas: HashMap<FoxgloveSchema, u16>,
    ros2_schemas: HashMap<&'static str, u16>,
    channels: HashMap<String, u16>,
    sequence: HashMap<u16, u32>,
    counts: BTreeMap<String, ChannelCount>,
}

impl std::fmt::Debug for LogWriter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LogWriter")
            .field("path", &self.path)
            .finish()
    }
}

fn mcap_err(path: &Path) -> impl Fn(mcap::McapError) -> RecordError + '_ {
    move |source| RecordError::Mcap {
        path: path.to_path_buf(),
        source,
    }
}

impl LogWriter {
    /// Create `path`, writing the `shoal` metadata and, if given, the fleet file.
    pub fn create(
        path: &Path,
        opts: &WriterOptions,
        metadata: &BTreeMap<String, String>,
        fleet_toml: Option<&str>,
        create_time_ns: u64,
    ) -> Result<LogWriter, RecordError> {
        let file = File::create(path).map_err(|source| RecordError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let w = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .compression_level(opts.zstd_level)
            // One writer thread per recorder; zstd worker threads would compete with the fleet for 2 cores.
            .compression_threads(0)
            .chunk_size(Some(opts.chunk_size))
            .profile(opts.profile)
            .library(format!(
                "shoal-record/{} ({})",
                env!("CARGO_PKG_VERSION"),
                mcap::LIBRARY_IDENTIFIER
            ))
            .create(BufWriter::with_capacity(1 << 20, file))
            .map_err(mcap_err(path))?;
        let mut lw = LogWriter {
            path: path.to_path_buf(),
            w,
            raw_schemas: HashMap::new(),
            fox_schemas: HashMap::new(),
            ros2_schemas: HashMap::new(),
            channels: HashMap::new(),
            sequence: HashMap::new(),
            counts: BTreeMap::new(),
        };
        let mut metadata = metadata.clone();
        metadata.insert("log_format".into(), LOG_FORMAT.to_string());
        lw.w.write_metadata(&Metadata {
            name: METADATA_NAME.into(),
            metadata,
        })
        .map_err(mcap_err(path))?;
        if let Some(text) = fleet_toml {
            lw.w.attach(&mcap::Attachment {
                log_time: create_time_ns,
                create_time: create_time_ns,
                name: FLEET_ATTACHMENT.into(),
                media_type: "application/toml".into(),
                data: std::borrow::Cow::Borrowed(text.as_bytes()),
            })
            .map_err(mcap_err(path))?;
        }
        lw.w.flush().map_err(mcap_err(path))?;
        Ok(lw)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    fn next_sequence(&mut self, channel: u16) -> u32 {
        let s = self.sequence.entry(channel).or_insert(0);
        *s = s.wrapping_add(1);
        *s
    }

    fn write(
        &mut self,
        topic: &str,
        channel: u16,
        data: &[u8],
        log_time: u64,
        publish_time: u64,
    ) -> Result<(), RecordError> {
        let sequence = self.next_sequence(channel);
        self.w
            .write_to_known_channel(
                &MessageHeader {
                    channel_id: channel,
                    sequence,
                    log_time,
                    publish_time,
                },
                data,
            )
            .map_err(mcap_err(&self.path))?;
        let c = self.counts.entry(topic.to_string()).or_default();
        c.messages += 1;
        c.bytes += data.len() as u64;
        Ok(())
    }

    /// Write envelope bytes received on Zenoh `key`, unchanged. `kind` is
    /// `None` when the header was unreadable (the bytes are still kept).
    pub fn write_wire(
        &mut self,
        key: &str,
        kind: Option<MessageKind>,
        bytes: &[u8],
        log_time: u64,
        publish_time: u64,
    ) -> Result<(), RecordError> {
        let channel = match self.channels.get(key) {
            Some(&c) => c,
            None => {
                let schema = match kind {
                    Some(k) => self.raw_schema(k)?,
                    None => 0,
                };
                let mut meta = BTreeMap::new();
                meta.insert("zenoh_key".to_string(), key.to_string());
                meta.insert("schema_version".to_string(), SCHEMA_VERSION.to_string());
                if let Some(k) = kind {
                    meta.insert("schema".to_string(), k.schema_name().to_string());
                    meta.insert("kind".to_string(), (k as u16).to_string());
                }
                let c = self
                    .w
                    .add_channel(schema, key, WIRE_ENCODING, &meta)
                    .map_err(mcap_err(&self.path))?;
                self.channels.insert(key.to_string(), c);
                c
            }
        };
        self.write(key, channel, bytes, log_time, publish_time)
    }

    fn raw_schema(&mut self, kind: MessageKind) -> Result<u16, RecordError> {
        if let Some(&id) = self.raw_schemas.get(&kind) {
            return Ok(id);
        }
        let text = format!(
            "{} (kind {}), shoal wire schema version {}: a 12-byte envelope (magic SHOL, u16 version, u16 kind, u32 length) and a bincode 2 payload; field layout in docs/wire.md",
            kind.schema_name(),
            kind as u16,
            SCHEMA_VERSION
        );
        let id = self
            .w
            .add_schema(kind.schema_name(), WIRE_SCHEMA_ENCODING, text.as_bytes())
            .map_err(mcap_err(&self.path))?;
        self.raw_schemas.insert(kind, id);
        Ok(id)
    }

    /// Write one Foxglove message (protobuf, with the `foxglove` crate's
    /// schema record, as the station's live server declares it).
    pub fn write_foxglove(
        &mut self,
        m: &FoxgloveMessage,
        log_time: u64,
        publish_time: u64,
    ) -> Result<(), RecordError> {
        let data = m.encode()?;
        let schema = m.schema();
        let channel = match self.channels.get(&m.topic) {
            Some(&c) => c,
            None => {
                let sid = match self.fox_schemas.get(&schema) {
                    Some(&s) => s,
                    None => {
                        let record = schema.schema();
                        let s = self
                            .w
                            .add_schema(&record.name, &record.encoding, &record.data)
                            .map_err(mcap_err(&self.path))?;
                        self.fox_schemas.insert(schema, s);
                        s
                    }
                };
                let c = self
                    .w
                    .add_channel(sid, &m.topic, schema.message_encoding(), &BTreeMap::new())
                    .map_err(mcap_err(&self.path))?;
                self.channels.insert(m.topic.clone(), c);
                c
            }
        };
        self.write(&m.topic, channel, &data, log_time, publish_time)
    }

    /// Write one CDR-encoded ROS 2 message of type `ty` on `topic`.
    pub fn write_ros2(
        &mut self,
        topic: &str,
        ty: &RosType,
        cdr: &[u8],
        log_time: u64,
        publish_time: u64,
    ) -> Result<(), RecordError> {
        let channel = match self.channels.get(topic) {
            Some(&c) => c,
            None => {
                let sid = match self.ros2_schemas.get(ty.name) {
                    Some(&s) => s,
                    None => {
                        let text = ty.ros2msg().ok_or(RecordError::NoRos2Definition(ty.name))?;
                        let s = self
                            .w
                            .add_schema(ty.name, "ros2msg", text.as_bytes())
                            .map_err(mcap_err(&self.path))?;
                        self.ros2_schemas.insert(ty.name, s);
                        s
                    }
                };
                let c = self
                    .w
                    .add_channel(sid, topic, "cdr", &BTreeMap::new())
                    .map_err(mcap_err(&self.path))?;
                self.channels.insert(topic.to_string(), c);
                c
            }
        };
        self.write(topic, channel, cdr, log_time, publish_time)
    }

    /// Close the current chunk and push it to the file, so a crash after this keeps it.
    pub fn flush(&mut self) -> Result<(), RecordError> {
        self.w.flush().map_err(mcap_err(&self.path))
    }

    /// Messages and bytes per channel (topic) so far.
    pub fn counts(&self) -> &BTreeMap<String, ChannelCount> {
        &self.counts
    }

    /// Write the summary section and close the file.
    pub fn finish(mut self) -> Result<BTreeMap<String, ChannelCount>, RecordError> {
        self.w.finish().map_err(mcap_err(&self.path))?;
        let mut inner = self.w.into_inner();
        std::io::Write::flush(&mut inner).map_err(|source| RecordError::Io {
            path: self.path.clone(),
            source,
        })?;
        Ok(self.counts)
    }
}
