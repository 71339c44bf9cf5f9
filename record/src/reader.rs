//! Reading shoal MCAP logs, including damaged ones.
//!
//! [`scan`] streams the file record by record (one record in memory at a
//! time; each chunk decoded by the `mcap` crate's streaming reader within a
//! per-chunk and a per-file bound, CRCs checked where present). Damage costs only the record it is in: the scan
//! skips it, resumes at the next readable record (found from the summary's
//! index when that is intact, else by the records' framing, see
//! [`framing`]) and reports every skipped region. The summary and footer are
//! checked too, so a file is called complete only when an indexed reader
//! would open it. [`crate::recover`] rewrites a damaged or interrupted file
//! with a proper summary.

mod framing;

pub use framing::{decompression_budget, MAX_CHUNK_UNCOMPRESSED, MAX_RECORD};

use crate::writer::{FLEET_ATTACHMENT, METADATA_NAME, WIRE_ENCODING};
use framing::{plausible, ChunkDecoder, Framer, SummaryIndex, HEAD};
use mcap::records::{op, Record};
use std::collections::BTreeMap;
use std::io::{Read, Seek};
use std::path::Path;

/// A channel as declared in the file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChannelInfo {
    pub id: u16,
    pub topic: String,
    pub message_encoding: String,
    pub metadata: BTreeMap<String, String>,
    pub schema_id: u16,
}

impl From<mcap::records::Channel> for ChannelInfo {
    fn from(c: mcap::records::Channel) -> Self {
        Self {
            id: c.id,
            topic: c.topic,
            message_encoding: c.message_encoding,
            metadata: c.metadata,
            schema_id: c.schema_id,
        }
    }
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

/// One damaged region a scan skipped.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct Skipped {
    /// Byte offset where the damaged record starts.
    pub offset: u64,
    /// Bytes skipped, up to the next readable record.
    pub bytes: u64,
    pub reason: String,
}

/// How many skipped regions a [`ScanOutcome`] lists (all are counted).
pub const MAX_SKIPPED_LISTED: usize = 64;

/// How far a scan got.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct ScanOutcome {
    /// Every record read, a data-end record whose CRC matches, a summary whose
    /// CRC matches, a footer and the closing magic: an indexed reader opens it.
    pub complete: bool,
    /// What is wrong with the file, in one paragraph (None when complete).
    pub damage: Option<String>,
    /// The damaged regions skipped, in file order (the first [`MAX_SKIPPED_LISTED`]).
    pub skipped: Vec<Skipped>,
    /// All damaged regions skipped, and their bytes.
    pub skipped_regions: u64,
    pub skipped_bytes: u64,
    /// Problems of the file as a whole (summary, footer, data CRC, messages of unknown channels).
    pub problems: Vec<String>,
    pub messages: u64,
    /// Messages whose channel record was never read (it was damaged): counted and dropped.
    pub orphan_messages: u64,
    pub chunks: u64,
    pub file_bytes: u64,
    pub decompressed_bytes: u64,
    pub channels: BTreeMap<u16, ChannelInfo>,
    pub schemas: BTreeMap<u16, SchemaInfo>,
}

impl ScanOutcome {
    fn skip(&mut self, offset: u64, bytes: u64, reason: String) {
        self.skipped_regions += 1;
        self.skipped_bytes += bytes;
        if self.skipped.len() < MAX_SKIPPED_LISTED {
            self.skipped.push(Skipped {
                offset,
                bytes,
                reason,
            });
        }
    }

    fn describe(&self) -> Option<String> {
        let mut parts: Vec<String> = Vec::new();
        if self.skipped_regions > 0 {
            let first: Vec<String> = self
                .skipped
                .iter()
                .take(3)
                .map(|s| format!("byte {} ({} bytes): {}", s.offset, s.bytes, s.reason))
                .collect();
            parts.push(format!(
                "{} damaged region(s), {} bytes, skipped — {}{}",
                self.skipped_regions,
                self.skipped_bytes,
                first.join("; "),
                if self.skipped_regions > 3 {
                    "; …"
                } else {
                    ""
                }
            ));
        }
        parts.extend(self.problems.iter().cloned());
        (!parts.is_empty()).then(|| parts.join(". "))
    }
}

/// Where a log is read from: a file (streamed, never loaded whole) or bytes in memory.
pub trait LogSource {
    type Reader: Read + Seek;
    fn open(self) -> std::io::Result<Self::Reader>;
}

impl<'a> LogSource for &'a [u8] {
    type Reader = std::io::Cursor<&'a [u8]>;
    fn open(self) -> std::io::Result<Self::Reader> {
        Ok(std::io::Cursor::new(self))
    }
}

impl<'a> LogSource for &'a Vec<u8> {
    type Reader = std::io::Cursor<&'a [u8]>;
    fn open(self) -> std::io::Result<Self::Reader> {
        Ok(std::io::Cursor::new(self.as_slice()))
    }
}

impl LogSource for &Path {
    type Reader = std::io::BufReader<std::fs::File>;
    fn open(self) -> std::io::Result<Self::Reader> {
        Ok(std::io::BufReader::with_capacity(
            1 << 16,
            std::fs::File::open(self)?,
        ))
    }
}

impl LogSource for &std::path::PathBuf {
    type Reader = std::io::BufReader<std::fs::File>;
    fn open(self) -> std::io::Result<Self::Reader> {
        self.as_path().open()
    }
}

/// [`scan`] restricted to the shoal wire messages (envelopes as received on
/// Zenoh, one channel per key): `visit(channel, log_time, envelope bytes)`.
pub fn scan_wire<E>(
    src: impl LogSource,
    mut visit: impl FnMut(&ChannelInfo, u64, &[u8]) -> Result<(), E>,
) -> Result<ScanOutcome, ScanError<E>> {
    scan(src, |item| match item {
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
/// the data section in file order, streaming (one record in memory at a
/// time). A visitor error stops the scan and is returned. Damage costs only
/// the damaged record: it is skipped, the scan resumes at the next readable
/// record, and the outcome lists what was skipped and why.
pub fn scan<E>(
    src: impl LogSource,
    mut visit: impl FnMut(Item<'_>) -> Result<(), E>,
) -> Result<ScanOutcome, ScanError<E>> {
    let mut f = Framer::new(src.open()?)?;
    let mut out = ScanOutcome {
        file_bytes: f.len,
        ..ScanOutcome::default()
    };
    let magic = f.bytes_at(0, 8)?;
    if magic != mcap::MAGIC {
        if !header_at_8(&mut f)? {
            return Err(NotMcap::NoMagic.into());
        }
        out.skip(0, 8, "the opening MCAP magic is damaged".into());
    }
    let index = match f.summary()? {
        Ok(index) => index,
        Err(problem) => {
            out.problems.push(format!(
                "{problem}: indexed readers cannot open the file (`shoal log recover` rewrites it)"
            ));
            None
        }
    };
    let mut chunks = ChunkDecoder::new(decompression_budget(f.len));
    let mut data_crc = Some(crc32fast::Hasher::new());
    if let Some(h) = data_crc.as_mut() {
        h.update(&magic);
    }
    let mut at = 8u64;
    let mut data_end = None;
    // With an intact summary, the data section ends exactly where it says.
    let limit = index
        .as_ref()
        .and_then(|ix| ix.data_end)
        .map_or(f.len, |d| d + HEAD + 4);
    while at < limit {
        let head = f.head(at)?;
        let framed = match head {
            Some((opcode, len)) => {
                plausible(opcode, len, at, limit)
                    && !SUMMARY_OPCODES.contains(&opcode)
                    && (opcode != op::DATA_END || data_end_here(len, at, index.as_ref()))
                    && f.framed(opcode, len, at)?
            }
            None => false,
        };
        let Some((opcode, len)) = head.filter(|_| framed) else {
            data_crc = None;
            let next = resync(&mut f, at + 1, index.as_ref(), chunks.budget)?;
            out.skip(
                at,
                next.unwrap_or(f.len) - at,
                unframed_reason(head, at, f.len, next.is_none()),
            );
            match next {
                Some(n) => {
                    at = n;
                    continue;
                }
                None => break,
            }
        };
        let mut body = f.body(at, len)?;
        let mut len = len;
        if let Some(extent) = chunk_extent(opcode, body).filter(|&e| e < len) {
            // A chunk whose length field grew (one damaged byte) still
            // frames: its own fields say where it ends. Read it to there and
            // go on with the next record, rather than jump over the chunks
            // in between; the file is not called complete. (MCAP allows
            // fields appended to a record in later versions; shoal's writer
            // appends none, and a foreign file that did would be read the
            // same way, flagged.)
            out.skip(
                at,
                0,
                format!(
                    "the chunk record at byte {at} says it is {len} bytes long, its contents {extent}: its length is damaged"
                ),
            );
            data_crc = None;
            len = extent;
            body = &body[..extent as usize];
        }
        if opcode == op::DATA_END {
            data_end = Some(match mcap::parse_record(opcode, body) {
                Ok(Record::DataEnd(d)) => d.data_section_crc,
                _ => 0,
            });
            break;
        }
        if let Some(h) = data_crc.as_mut() {
            h.update(&[opcode]);
            h.update(&len.to_le_bytes());
            h.update(body);
        }
        match process(
            opcode,
            body,
            &mut out,
            &mut chunks,
            index.as_ref(),
            &mut visit,
        ) {
            Ok(()) => at += HEAD + len,
            Err(Problem::Damaged(reason)) => {
                // A damaged length can still look framed: with an intact
                // summary, resume where it says the next record is.
                let next = match index.as_ref() {
                    Some(_) => {
                        resync(&mut f, at + 1, index.as_ref(), chunks.budget)?.unwrap_or(f.len)
                    }
                    None => at + HEAD + len,
                };
                out.skip(at, next - at, reason);
                at = next;
            }
            Err(Problem::Visitor(e)) => return Err(ScanError::Visitor(e)),
        }
    }
    out.decompressed_bytes = decompression_budget(f.len) - chunks.budget;
    finish(&mut out, index.as_ref(), data_end, data_crc);
    Ok(out)
}

/// Whether a data-end record at byte `at`, `len` bytes long, is the data
/// section's end: where an intact summary says it is, else the 4 bytes of
/// its one field (shoal's writer appends none). One damaged opcode can turn
/// any record into a data end (a message index's 0x07 with bit 3 flipped is
/// 0x0F), which would end the scan and lose every chunk after it.
fn data_end_here(len: u64, at: u64, index: Option<&SummaryIndex>) -> bool {
    match index.and_then(|ix| ix.data_end) {
        Some(d) => d == at,
        None => len == 4,
    }
}

/// The length a chunk record's own fields give its body (start, end,
/// uncompressed size and CRC, the compression name, the records' length and
/// the records), when they fit in `body`; `None` for other records.
fn chunk_extent(opcode: u8, body: &[u8]) -> Option<u64> {
    if opcode != op::CHUNK {
        return None;
    }
    let u32_at = |i: usize| -> Option<u64> {
        Some(u64::from(u32::from_le_bytes(
            body.get(i..i + 4)?.try_into().ok()?,
        )))
    };
    let u64_at = |i: usize| -> Option<u64> {
        Some(u64::from_le_bytes(body.get(i..i + 8)?.try_into().ok()?))
    };
    let name_len = u32_at(28)?;
    let records_at = 32u64.checked_add(name_len)?;
    let records_len = u64_at(usize::try_from(records_at).ok()?)?;
    records_at.checked_add(8)?.checked_add(records_len)
}

/// Records that only the summary section holds: reaching one ends the data section.
const SUMMARY_OPCODES: [u8; 6] = [
    op::CHUNK_INDEX,
    op::ATTACHMENT_INDEX,
    op::STATISTICS,
    op::METADATA_INDEX,
    op::SUMMARY_OFFSET,
    op::FOOTER,
];

fn header_at_8<R: Read + Seek>(f: &mut Framer<R>) -> std::io::Result<bool> {
    Ok(match f.head(8)? {
        Some((opcode, len)) if opcode == op::HEADER && plausible(opcode, len, 8, f.len) => {
            matches!(
                mcap::parse_record(opcode, f.body(8, len)?),
                Ok(Record::Header(_))
            )
        }
        _ => false,
    })
}

fn unframed_reason(head: Option<(u8, u64)>, at: u64, file_len: u64, to_end: bool) -> String {
    match head {
        None => format!("{} stray bytes at the end", file_len - at),
        Some((opcode, _)) if SUMMARY_OPCODES.contains(&opcode) => format!(
            "a summary record (opcode {opcode:#04x}) inside the data section"
        ),
        Some((opcode, len)) if to_end && at + HEAD + len > file_len && len <= MAX_RECORD => format!(
            "the file ends inside a record (opcode {opcode:#04x}, {len} bytes; recording interrupted?)"
        ),
        Some((opcode, len)) => format!(
            "no readable record here (opcode {opcode:#04x}, length {len})"
        ),
    }
}

/// Where reading resumes after an unreadable record: the next record the
/// (intact) summary lists, else the next offset where a framed record passes
/// its checks.
fn resync<R: Read + Seek>(
    f: &mut Framer<R>,
    from: u64,
    index: Option<&SummaryIndex>,
    budget: u64,
) -> std::io::Result<Option<u64>> {
    if let Some(ix) = index {
        if ix.data_end.is_some_and(|d| from > d) {
            return Ok(None);
        }
        if let Some(&n) = ix.offsets.range(from..).next() {
            return Ok(Some(n));
        }
        if let Some(d) = ix.data_end.filter(|&d| d >= from) {
            return Ok(Some(d));
        }
    }
    f.scan_for(from, |f, at| {
        let Some((opcode, len)) = f.head(at)? else {
            return Ok(false);
        };
        if opcode == op::HEADER || (opcode == op::FOOTER && at + HEAD + len + 8 != f.len) {
            return Ok(false);
        }
        let body = f.body(at, len)?;
        Ok(match mcap::parse_record(opcode, body) {
            Ok(Record::Chunk { header, .. }) => {
                ChunkDecoder::new(budget).read(&header, body).is_ok()
            }
            Ok(_) => true,
            Err(_) => false,
        })
    })
}

enum Problem<E> {
    Damaged(String),
    Visitor(E),
}

/// Decode one framed data-section record and visit what it holds (a chunk
/// whole or not at all).
fn process<E>(
    opcode: u8,
    body: &[u8],
    out: &mut ScanOutcome,
    chunks: &mut ChunkDecoder,
    index: Option<&SummaryIndex>,
    visit: &mut impl FnMut(Item<'_>) -> Result<(), E>,
) -> Result<(), Problem<E>> {
    if matches!(opcode, op::HEADER | op::MESSAGE_INDEX) {
        return Ok(());
    }
    let record = mcap::parse_record(opcode, body).map_err(|e| Problem::Damaged(e.to_string()))?;
    if let Record::Chunk { header, .. } = record {
        let records = chunks
            .read(&header, body)
            .map_err(|e| Problem::Damaged(format!("chunk: {e}")))?;
        out.chunks += 1;
        for r in records {
            handle(r, out, index, visit).map_err(Problem::Visitor)?;
        }
        return Ok(());
    }
    handle(record, out, index, visit).map_err(Problem::Visitor)
}

/// Whole-file checks once the data section is read.
fn finish(
    out: &mut ScanOutcome,
    index: Option<&SummaryIndex>,
    data_end: Option<u32>,
    data_crc: Option<crc32fast::Hasher>,
) {
    match data_end {
        None => out.problems.push(
            "the file ends without a data-end record, summary and footer (recording interrupted?)"
                .into(),
        ),
        Some(saved) => {
            if let Some(calculated) = data_crc.map(crc32fast::Hasher::finalize) {
                if saved != 0 && saved != calculated && out.skipped_regions == 0 {
                    out.problems.push(format!(
                        "the data section's CRC is {calculated:08x}, its data-end record says {saved:08x}: a record without a CRC of its own (metadata, schema, channel) is damaged"
                    ));
                }
            }
            if index.is_none() && out.problems.is_empty() {
                out.problems.push(
                    "the file has a data-end record but no summary or footer after it".into(),
                );
            }
        }
    }
    if let Some(n) = index.and_then(|ix| ix.message_count) {
        if n != out.messages + out.orphan_messages && out.skipped_regions == 0 {
            out.problems.push(format!(
                "the summary counts {n} messages, {} were read",
                out.messages + out.orphan_messages
            ));
        }
    }
    if out.orphan_messages > 0 {
        out.problems.push(format!(
            "{} messages on channels whose channel record was not read were dropped",
            out.orphan_messages
        ));
    }
    out.damage = out.describe();
    out.complete = out.damage.is_none();
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

/// Why a file cannot be read as an MCAP log at all.
#[derive(Debug, thiserror::Error)]
pub enum NotMcap {
    #[error("not an MCAP file (no magic, and no header record where it belongs)")]
    NoMagic,
    #[error("reading the file")]
    Io(#[from] std::io::Error),
}

impl<E> From<std::io::Error> for ScanError<E> {
    fn from(e: std::io::Error) -> Self {
        ScanError::NotMcap(NotMcap::Io(e))
    }
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
    index: Option<&SummaryIndex>,
    visit: &mut impl FnMut(Item<'_>) -> Result<(), E>,
) -> Result<(), E> {
    if let Record::Message { header, .. } = &record {
        if !out.channels.contains_key(&header.channel_id) {
            declare_from_summary(header.channel_id, out, index, visit)?;
        }
    }
    match record {
        Record::Schema { header, data } => {
            let s = SchemaInfo {
                id: header.id,
                name: header.name,
                encoding: header.encoding,
                data: data.into_owned(),
            };
            // The summary repeats schemas and channels; a reader that resumed
            // after damage may meet one twice: visit each once.
            if out.schemas.get(&s.id) != Some(&s) {
                visit(Item::Schema(&s))?;
                out.schemas.insert(s.id, s);
            }
        }
        Record::Channel(c) => {
            let c = ChannelInfo::from(c);
            if out.channels.get(&c.id) != Some(&c) {
                visit(Item::Channel(&c))?;
                out.channels.insert(c.id, c);
            }
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
                })?;
            } else {
                out.orphan_messages += 1;
            }
        }
        Record::Metadata(m) => visit(Item::Metadata {
            name: &m.name,
            metadata: &m.metadata,
        })?,
        Record::Attachment { header, data, .. } => visit(Item::Attachment {
            name: &header.name,
            media_type: &header.media_type,
            log_time: header.log_time,
            create_time: header.create_time,
            data: &data,
        })?,
        _ => {}
    }
    Ok(())
}

/// A message whose channel record was lost with a damaged chunk: the intact
/// summary still lists the channel (and its schema), so declare it from there.
fn declare_from_summary<E>(
    channel_id: u16,
    out: &mut ScanOutcome,
    index: Option<&SummaryIndex>,
    visit: &mut impl FnMut(Item<'_>) -> Result<(), E>,
) -> Result<(), E> {
    let Some(ix) = index else {
        return Ok(());
    };
    let Some(c) = ix.channels.iter().find(|c| c.id == channel_id) else {
        return Ok(());
    };
    if !out.schemas.contains_key(&c.schema_id) {
        if let Some((h, data)) = ix.schemas.iter().find(|(h, _)| h.id == c.schema_id) {
            let s = SchemaInfo {
                id: h.id,
                name: h.name.clone(),
                encoding: h.encoding.clone(),
                data: data.clone(),
            };
            visit(Item::Schema(&s))?;
            out.schemas.insert(s.id, s);
        }
    }
    let c = ChannelInfo::from(c.clone());
    visit(Item::Channel(&c))?;
    out.channels.insert(c.id, c);
    Ok(())
}

/// The `shoal` metadata record and the fleet file of a log.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LogHeader {
    pub metadata: BTreeMap<String, String>,
    pub fleet_toml: Option<String>,
}

/// The channels an intact summary lists (empty for an interrupted or damaged
/// file, whose channels are only met as the scan goes).
pub fn summary_channels(src: impl LogSource) -> Result<Vec<ChannelInfo>, NotMcap> {
    let mut f = Framer::new(src.open()?)?;
    Ok(match f.summary()? {
        Ok(Some(index)) => index.channels.into_iter().map(ChannelInfo::from).collect(),
        _ => Vec::new(),
    })
}

/// Read the header items of a log (they are written first, so this is quick to find).
pub fn header(src: impl LogSource) -> Result<LogHeader, NotMcap> {
    let mut h = LogHeader::default();
    let res = scan(src, |item| {
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
        let report = crate::recover(&cut_path, &fixed).unwrap();
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
        assert!(scan(&b"not an mcap file"[..], |_| Ok::<(), Stop>(())).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
