//! Reading shoal MCAP logs, including damaged ones.
//!
//! [`scan`] walks the file record by record (chunks decompressed, CRCs
//! checked by the `mcap` crate where present) and stops at the first record
//! it cannot read, reporting where: a recording killed mid-chunk yields every
//! complete chunk before the damage. [`recover`] rewrites such a file with a
//! proper summary.

use crate::writer::{FLEET_ATTACHMENT, METADATA_NAME, WIRE_ENCODING};
use crate::RecordError;
use mcap::read::{LinearReader, Options};
use mcap::records::Record;
use std::collections::BTreeMap;
use std::path::Path;

/// Largest uncompressed chunk a reader accepts. shoal's recorder closes a
/// chunk after about 4 MiB ([`crate::WriterOptions::chunk_size`]); one record
/// can exceed that by a whole message (at most 64 MiB,
/// `proto::codec::MAX_PAYLOAD`) plus its Foxglove copy (base64, 4/3 larger),
/// so 256 MiB leaves room for any file shoal writes.
pub const MAX_CHUNK_UNCOMPRESSED: u64 = 256 << 20;

/// A channel as declared in the file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChannelInfo {
    pub id: u16,
    pub topic: String,
    pub message_encoding: String,
    pub metadata: BTreeMap<String, String>,
    pub schema_id: u16,
}

impl ChannelInfo {
    /// A raw shoal wire channel (envelope bytes of a Zenoh key).
    pub fn is_wire(&self) -> bool {
        self.message_encoding == WIRE_ENCODING
    }
}

/// A schema as declared in the file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SchemaInfo {
    pub id: u16,
    pub name: String,
    pub encoding: String,
    pub data: Vec<u8>,
}

/// One item of the file, in file order.
#[derive(Debug)]
pub enum Item<'a> {
    Schema(&'a SchemaInfo),
    Channel(&'a ChannelInfo),
    Message {
        channel: &'a ChannelInfo,
        sequence: u32,
        log_time: u64,
        publish_time: u64,
        data: &'a [u8],
    },
    Metadata {
        name: &'a str,
        metadata: &'a BTreeMap<String, String>,
    },
    Attachment {
        name: &'a str,
        media_type: &'a str,
        log_time: u64,
        create_time: u64,
        data: &'a [u8],
    },
}

/// How far a scan got.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct ScanOutcome {
    /// The file ended with a data-end record, a footer and the closing magic.
    pub complete: bool,
    /// Why reading stopped early, if it did.
    pub damage: Option<String>,
    pub messages: u64,
    pub chunks: u64,
    pub channels: BTreeMap<u16, ChannelInfo>,
    pub schemas: BTreeMap<u16, SchemaInfo>,
}

/// Read a whole file into memory.
pub fn read_file(path: &Path) -> Result<Vec<u8>, RecordError> {
    std::fs::read(path).map_err(|source| RecordError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// [`scan`] restricted to the shoal wire messages (envelopes as received on
/// Zenoh, one channel per key): `visit(channel, log_time, envelope bytes)`.
pub fn scan_wire<E>(
    buf: &[u8],
    mut visit: impl FnMut(&ChannelInfo, u64, &[u8]) -> Result<(), E>,
) -> Result<ScanOutcome, ScanError<E>> {
    scan(buf, |item| match item {
        Item::Message {
            channel,
            log_time,
            data,
            ..
        } if channel.is_wire() => visit(channel, log_time, data),
        _ => Ok(()),
    })
}

/// Visit every schema, channel, message, metadata record and attachment of
/// `buf` in file order. A visitor error stops the scan and is returned; damage
/// to the file stops it and is reported in [`ScanOutcome::damage`].
pub fn scan<E>(
    buf: &[u8],
    mut visit: impl FnMut(Item<'_>) -> Result<(), E>,
) -> Result<ScanOutcome, ScanError<E>> {
    let mut out = ScanOutcome::default();
    if buf.len() < 8 || &buf[..8] != mcap::MAGIC {
        return Err(NotMcap::NoMagic.into());
    }
    let reader = LinearReader::new_with_options(buf, Options::IgnoreEndMagic.into())
        .map_err(|e| ScanError::NotMcap(NotMcap::Unreadable(e)))?;
    let mut saw_footer = false;
    for record in reader {
        let record = match record {
            Ok(r) => r,
            Err(e) => {
                out.damage = Some(format!("stopped at an unreadable record: {e}"));
                break;
            }
        };
        match record {
            Record::Chunk { header, data } => {
                // Decode the chunk fully first: a damaged chunk contributes nothing.
                let records = match chunk_records(&header, &data) {
                    Ok(records) => records,
                    Err(e) => {
                        out.damage = Some(format!("chunk {} is damaged: {e}", out.chunks + 1));
                        break;
                    }
                };
                out.chunks += 1;
                for r in records {
                    handle(r, &mut out, &mut visit)?;
                }
            }
            Record::Footer(_) => saw_footer = true,
            other => handle(other, &mut out, &mut visit)?,
        }
    }
    out.complete =
        saw_footer && out.damage.is_none() && buf.ends_with(mcap::MAGIC) && buf.len() >= 16;
    if !out.complete && out.damage.is_none() {
        out.damage = Some("the file ends without a footer (recording interrupted)".into());
    }
    Ok(out)
}

/// The records of one chunk, or why it is unusable. Decompressed here rather
/// than by `mcap::read::ChunkReader`, which allocates whatever sizes a
/// damaged chunk declares (found by `record/tests/fuzz_mcap.rs`): the size is
/// bounded by [`MAX_CHUNK_UNCOMPRESSED`], the CRC checked before any record
/// is parsed, and every record length checked against the bytes present.
fn chunk_records(
    header: &mcap::records::ChunkHeader,
    data: &[u8],
) -> Result<Vec<Record<'static>>, String> {
    if header.uncompressed_size > MAX_CHUNK_UNCOMPRESSED {
        return Err(format!(
            "declares {} uncompressed bytes, over the {MAX_CHUNK_UNCOMPRESSED}-byte limit",
            header.uncompressed_size
        ));
    }
    let size = header.uncompressed_size as usize;
    let plain: std::borrow::Cow<'_, [u8]> = match header.compression.as_str() {
        "" => std::borrow::Cow::Borrowed(data),
        "zstd" => std::borrow::Cow::Owned(
            zstd::bulk::decompress(data, size).map_err(|e| format!("zstd: {e}"))?,
        ),
        other => return Err(format!("unsupported compression {other:?}")),
    };
    if plain.len() != size {
        return Err(format!(
            "{} bytes uncompressed, the header says {size}",
            plain.len()
        ));
    }
    if header.uncompressed_crc != 0 {
        let calculated = crc32fast::hash(&plain);
        if calculated != header.uncompressed_crc {
            return Err(format!(
                "CRC {calculated:08x}, the header says {:08x}",
                header.uncompressed_crc
            ));
        }
    }
    let mut records = Vec::new();
    let mut rest: &[u8] = &plain;
    while !rest.is_empty() {
        if rest.len() < 9 {
            return Err(format!("{} stray bytes at the end", rest.len()));
        }
        let opcode = rest[0];
        let len = u64::from_le_bytes(rest[1..9].try_into().unwrap_or([0xff; 8]));
        if len > (rest.len() - 9) as u64 {
            return Err(format!(
                "record (opcode {opcode:#04x}) of {len} bytes, {} left",
                rest.len() - 9
            ));
        }
        let (body, next) = rest[9..].split_at(len as usize);
        records.push(
            mcap::parse_record(opcode, body)
                .map_err(|e| e.to_string())?
                .into_owned(),
        );
        rest = next;
    }
    Ok(records)
}

/// A visitor's request to end a scan early.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Stop;

impl std::fmt::Display for Stop {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("scan stopped early")
    }
}

/// Why a scan failed.
#[derive(Debug, thiserror::Error)]
pub enum ScanError<E> {
    #[error(transparent)]
    NotMcap(#[from] NotMcap),
    #[error(transparent)]
    Visitor(E),
}

/// Why a file is not an MCAP log at all.
#[derive(Debug, thiserror::Error)]
pub enum NotMcap {
    #[error("not an MCAP file (no magic)")]
    NoMagic,
    #[error("not a readable MCAP file")]
    Unreadable(#[source] mcap::McapError),
}

impl<E> ScanError<E> {
    /// The visitor's own error, or the file's as a [`crate::RecordError`] naming `path`.
    pub fn into_record_error(self, path: &std::path::Path) -> Result<E, crate::RecordError> {
        match self {
            ScanError::Visitor(e) => Ok(e),
            ScanError::NotMcap(source) => Err(crate::RecordError::NotMcap {
                path: path.to_path_buf(),
                source,
            }),
        }
    }
}

fn handle<E>(
    record: Record<'_>,
    out: &mut ScanOutcome,
    visit: &mut impl FnMut(Item<'_>) -> Result<(), E>,
) -> Result<(), ScanError<E>> {
    match record {
        Record::Schema { header, data } => {
            let s = SchemaInfo {
                id: header.id,
                name: header.name,
                encoding: header.encoding,
                data: data.into_owned(),
            };
            visit(Item::Schema(&s)).map_err(ScanError::Visitor)?;
            out.schemas.insert(s.id, s);
        }
        Record::Channel(c) => {
            let c = ChannelInfo {
                id: c.id,
                topic: c.topic,
                message_encoding: c.message_encoding,
                metadata: c.metadata,
                schema_id: c.schema_id,
            };
            visit(Item::Channel(&c)).map_err(ScanError::Visitor)?;
            out.channels.insert(c.id, c);
        }
        Record::Message { header, data } => {
            if let Some(channel) = out.channels.get(&header.channel_id) {
                out.messages += 1;
                visit(Item::Message {
                    channel,
                    sequence: header.sequence,
                    log_time: header.log_time,
                    publish_time: header.publish_time,
                    data: &data,
                })
                .map_err(ScanError::Visitor)?;
            }
        }
        Record::Metadata(m) => visit(Item::Metadata {
            name: &m.name,
            metadata: &m.metadata,
        })
        .map_err(ScanError::Visitor)?,
        Record::Attachment { header, data, .. } => visit(Item::Attachment {
            name: &header.name,
            media_type: &header.media_type,
            log_time: header.log_time,
            create_time: header.create_time,
            data: &data,
        })
        .map_err(ScanError::Visitor)?,
        _ => {}
    }
    Ok(())
}

/// The `shoal` metadata record and the fleet file of a log.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LogHeader {
    pub metadata: BTreeMap<String, String>,
    pub fleet_toml: Option<String>,
}

/// Read the header items of a log (they are written first, so this is quick to find).
pub fn header(buf: &[u8]) -> Result<LogHeader, NotMcap> {
    let mut h = LogHeader::default();
    let res = scan(buf, |item| {
        match item {
            Item::Metadata { name, metadata } if name == METADATA_NAME => {
                h.metadata = metadata.clone()
            }
            Item::Attachment { name, data, .. } if name == FLEET_ATTACHMENT => {
                h.fleet_toml = Some(String::from_utf8_lossy(data).into_owned());
            }
            Item::Message { .. } => return Err(Stop),
            _ => {}
        }
        Ok(())
    });
    match res {
        Ok(_) | Err(ScanError::Visitor(Stop)) => Ok(h),
        Err(ScanError::NotMcap(e)) => Err(e),
    }
}

/// What [`recover`] did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RecoverReport {
    pub messages: u64,
    pub channels: usize,
    pub chunks_read: u64,
    /// Why the input stopped (None: the input was intact).
    pub damage: Option<String>,
}

/// Rewrite `input` (typically a recording killed before it could write its
/// summary) to `output` with every readable record and a proper summary.
pub fn recover(input: &Path, output: &Path) -> Result<RecoverReport, RecordError> {
    let buf = read_file(input)?;
    let file = std::fs::File::create(output).map_err(|source| RecordError::Io {
        path: output.to_path_buf(),
        source,
    })?;
    let merr = |source| RecordError::Mcap {
        path: output.to_path_buf(),
        source,
    };
    let mut w = mcap::WriteOptions::new()
        .compression(Some(mcap::Compression::Zstd))
        .compression_threads(0)
        .profile(crate::writer::PROFILE)
        .create(std::io::BufWriter::new(file))
        .map_err(merr)?;
    let mut schema_map: BTreeMap<u16, u16> = BTreeMap::new();
    let mut channel_map: BTreeMap<u16, u16> = BTreeMap::new();
    let outcome = scan(&buf, |item| -> Result<(), mcap::McapError> {
        match item {
            Item::Schema(s) => {
                let id = w.add_schema(&s.name, &s.encoding, &s.data)?;
                schema_map.insert(s.id, id);
            }
            Item::Channel(c) => {
                let schema = schema_map.get(&c.schema_id).copied().unwrap_or(0);
                let id = w.add_channel(schema, &c.topic, &c.message_encoding, &c.metadata)?;
                channel_map.insert(c.id, id);
            }
            Item::Message {
                channel,
                sequence,
                log_time,
                publish_time,
                data,
            } => {
                if let Some(&id) = channel_map.get(&channel.id) {
                    w.write_to_known_channel(
                        &mcap::records::MessageHeader {
                            channel_id: id,
                            sequence,
                            log_time,
                            publish_time,
                        },
                        data,
                    )?;
                }
            }
            Item::Metadata { name, metadata } => w.write_metadata(&mcap::records::Metadata {
                name: name.to_string(),
                metadata: metadata.clone(),
            })?,
            Item::Attachment {
                name,
                media_type,
                log_time,
                create_time,
                data,
            } => w.attach(&mcap::Attachment {
                log_time,
                create_time,
                name: name.to_string(),
                media_type: media_type.to_string(),
                data: std::borrow::Cow::Borrowed(data),
            })?,
        }
        Ok(())
    })
    .map_err(|e| match e {
        ScanError::Visitor(source) => RecordError::Mcap {
            path: output.to_path_buf(),
            source,
        },
        ScanError::NotMcap(source) => RecordError::NotMcap {
            path: input.to_path_buf(),
            source,
        },
    })?;
    w.finish().map_err(merr)?;
    let mut inner = w.into_inner();
    std::io::Write::flush(&mut inner).map_err(|source| RecordError::Io {
        path: output.to_path_buf(),
        source,
    })?;
    Ok(RecoverReport {
        messages: outcome.messages,
        channels: outcome.channels.len(),
        chunks_read: outcome.chunks,
        damage: if outcome.complete {
            None
        } else {
            outcome.damage
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::writer::{LogWriter, WriterOptions};

    fn sample_log(dir: &Path) -> (std::path::PathBuf, u64) {
        let path = dir.join("sample.mcap");
        let mut meta = BTreeMap::new();
        meta.insert("fleet".to_string(), "paper".to_string());
        let mut w = LogWriter::create(
            &path,
            &WriterOptions::default(),
            &meta,
            Some("fleet = \"paper\""),
            1,
        )
        .unwrap();
        let n = 200u64;
        for i in 0..n {
            let cmd = proto::VehicleCommand {
                vehicle: 15,
                stamp_ns: i,
                velocity_body: [i as f64, 0.0, 0.0],
                yaw_rate: 0.0,
            };
            let bytes = proto::encode(&cmd).unwrap();
            w.write_wire(
                "shoal/paper/15/cmd",
                Some(proto::MessageKind::VehicleCommand),
                &bytes,
                1_000 + i,
                i,
            )
            .unwrap();
            if i % 20 == 19 {
                w.flush().unwrap();
            }
        }
        w.finish().unwrap();
        (path, n)
    }

    fn wire_count(buf: &[u8]) -> Result<(u64, ScanOutcome), ScanError<Stop>> {
        let mut n = 0;
        let o = scan(buf, |item| {
            if matches!(item, Item::Message { .. }) {
                n += 1;
            }
            Ok(())
        })?;
        Ok((n, o))
    }

    #[test]
    fn truncated_logs_yield_their_complete_chunks_and_never_panic() {
        let dir = std::env::temp_dir().join(format!("shoal-record-reader-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (path, n) = sample_log(&dir);
        let full = std::fs::read(&path).unwrap();
        let (all, outcome) = wire_count(&full).unwrap();
        assert_eq!(all, n);
        assert!(outcome.complete && outcome.damage.is_none());
        let mut previous = 0;
        for cut in (8..full.len()).step_by(97) {
            let (got, outcome) = wire_count(&full[..cut]).unwrap();
            assert!(
                !outcome.complete && outcome.damage.is_some(),
                "cut at {cut}"
            );
            // Chunks hold 20 messages each: a cut keeps whole chunks only, and more bytes never give fewer messages.
            assert_eq!(got % 20, 0, "cut at {cut}: {got}");
            assert!(got >= previous && got <= n);
            previous = got;
        }
        assert_eq!(previous, n, "a cut inside the summary keeps every message");
        // Recover a file cut in the middle of its data.
        let cut_path = dir.join("cut.mcap");
        std::fs::write(&cut_path, &full[..full.len() / 2]).unwrap();
        let fixed = dir.join("fixed.mcap");
        let report = recover(&cut_path, &fixed).unwrap();
        let fixed_buf = std::fs::read(&fixed).unwrap();
        let (got, outcome) = wire_count(&fixed_buf).unwrap();
        assert!(outcome.complete);
        assert_eq!(got, report.messages);
        assert!(got > 0 && got < n);
        assert_eq!(
            header(&fixed_buf)
                .unwrap()
                .metadata
                .get("fleet")
                .map(String::as_str),
            Some("paper")
        );
        assert!(scan(b"not an mcap file", |_| Ok::<(), Stop>(())).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
