//! The record framing of an MCAP file read through any `Read + Seek`, with
//! the checks that let a reader skip exactly the damaged records.
//!
//! Every top-level record is `opcode: u8, length: u64, body`. A record is
//! *plausible* at an offset when its opcode is one MCAP defines and its length
//! fits the file; it is *framed* when, in addition, the record after it is
//! plausible too (or the file ends there). A record that is framed but whose
//! content is damaged (chunk or attachment CRC, decompression, parse) is
//! skipped by its length: only it is lost. A record that is not framed (a
//! damaged opcode or length) is resynchronized on: at the next offset the
//! summary's index lists, when the summary is intact, else at the next byte
//! offset where a framed record parses and passes its checks.

use mcap::records::{op, Record};
use std::collections::BTreeSet;
use std::io::{self, Read, Seek, SeekFrom};

/// Largest uncompressed chunk a reader accepts. shoal's recorder closes a
/// chunk after about 4 MiB ([`crate::WriterOptions::chunk_size`]); one record
/// can exceed that by a whole message (at most 64 MiB,
/// `proto::codec::MAX_PAYLOAD`) plus its Foxglove copy (in format-1 logs base64, 4/3 larger),
/// so 256 MiB leaves room for any file shoal writes.
pub const MAX_CHUNK_UNCOMPRESSED: u64 = 256 << 20;

/// Largest record body a reader loads (a chunk's compressed bytes, an
/// attachment): a file declaring more is damaged or not shoal's.
pub const MAX_RECORD: u64 = 320 << 20;

/// Decompressed bytes one file may yield in all: 64 MiB plus 64 times its
/// size. shoal's logs compress 3–20 fold; a file that claims more is a
/// decompression bomb and its excess chunks are reported as damage.
pub fn decompression_budget(file_bytes: u64) -> u64 {
    (64u64 << 20).saturating_add(file_bytes.saturating_mul(64))
}

/// Size of a record's opcode and length.
pub const HEAD: u64 = 9;
/// The footer record: head + summary start, summary offset start, CRC.
const FOOTER_RECORD: u64 = HEAD + 8 + 8 + 4;
/// Bytes scanned per read while resynchronizing.
const SCAN_BLOCK: usize = 1 << 20;

/// Opcode and body length of a record, if plausible where it stands.
pub fn plausible(opcode: u8, len: u64, at: u64, file_len: u64) -> bool {
    (op::HEADER..=op::DATA_END).contains(&opcode)
        && len <= MAX_RECORD
        && at
            .checked_add(HEAD)
            .and_then(|b| b.checked_add(len))
            .is_some_and(|end| end <= file_len)
}

fn head_of(bytes: &[u8]) -> (u8, u64) {
    let mut len = [0u8; 8];
    len.copy_from_slice(&bytes[1..9]);
    (bytes[0], u64::from_le_bytes(len))
}

/// What the summary section says, once its CRC (or, without one, its framing) checked out.
#[derive(Debug, Default, Clone)]
pub struct SummaryIndex {
    /// Offsets of every chunk, attachment and metadata record of the data section.
    pub offsets: BTreeSet<u64>,
    /// Where the data section ends (the data-end record), when known.
    pub data_end: Option<u64>,
    /// Messages the writer counted.
    pub message_count: Option<u64>,
    /// Every channel and schema of the file, as the summary repeats them.
    pub channels: Vec<mcap::records::Channel>,
    pub schemas: Vec<(mcap::records::SchemaHeader, Vec<u8>)>,
}

/// A file being read, with one reusable buffer for record bodies.
pub struct Framer<R> {
    r: R,
    pub len: u64,
    body: Vec<u8>,
}

impl<R: Read + Seek> Framer<R> {
    pub fn new(mut r: R) -> io::Result<Self> {
        let len = r.seek(SeekFrom::End(0))?;
        Ok(Self {
            r,
            len,
            body: Vec::new(),
        })
    }

    /// `n` bytes at `at` (fewer at the end of the file).
    pub fn bytes_at(&mut self, at: u64, n: usize) -> io::Result<Vec<u8>> {
        let n = n.min(self.len.saturating_sub(at) as usize);
        let mut out = vec![0u8; n];
        self.r.seek(SeekFrom::Start(at))?;
        self.r.read_exact(&mut out)?;
        Ok(out)
    }

    /// Opcode and length of the record at `at`, if nine bytes remain.
    pub fn head(&mut self, at: u64) -> io::Result<Option<(u8, u64)>> {
        if at.saturating_add(HEAD) > self.len {
            return Ok(None);
        }
        let b = self.bytes_at(at, HEAD as usize)?;
        Ok(Some(head_of(&b)))
    }

    /// Whether the record at `at` (of body `len`) is followed by a plausible
    /// record, the end of the file, or — for a footer — the closing magic. A
    /// record the file ends inside (a recording killed while writing it)
    /// counts as plausible here: it must not cost the complete one before it.
    pub fn framed(&mut self, opcode: u8, len: u64, at: u64) -> io::Result<bool> {
        let next = at + HEAD + len;
        if next == self.len || (opcode == op::FOOTER && next + 8 == self.len) {
            return Ok(true);
        }
        Ok(match self.head(next)? {
            Some((o, l)) => {
                plausible(o, l, next, self.len)
                    || ((op::HEADER..=op::DATA_END).contains(&o) && l <= MAX_RECORD)
            }
            // Fewer than nine bytes left: the file ends inside the next head.
            None => true,
        })
    }

    /// The body of the record at `at`, `len` bytes (checked plausible by the caller).
    pub fn body(&mut self, at: u64, len: u64) -> io::Result<&[u8]> {
        self.body.clear();
        self.body.resize(len as usize, 0);
        self.r.seek(SeekFrom::Start(at + HEAD))?;
        self.r.read_exact(&mut self.body)?;
        Ok(&self.body)
    }

    /// Feed bytes `[from, to)` of the file to `hasher`.
    pub fn hash_range(
        &mut self,
        from: u64,
        to: u64,
        hasher: &mut crc32fast::Hasher,
    ) -> io::Result<()> {
        self.r.seek(SeekFrom::Start(from))?;
        let mut left = to.saturating_sub(from);
        let mut block = vec![0u8; SCAN_BLOCK];
        while left > 0 {
            let n = left.min(SCAN_BLOCK as u64) as usize;
            self.r.read_exact(&mut block[..n])?;
            hasher.update(&block[..n]);
            left -= n as u64;
        }
        Ok(())
    }

    /// The summary's index if the file ends with a footer whose summary
    /// checks out; otherwise why not (`Err` carries the reason, `Ok(None)`
    /// means the file simply has no footer yet).
    pub fn summary(&mut self) -> io::Result<Result<Option<SummaryIndex>, String>> {
        if self.len < 8 + 8 + FOOTER_RECORD {
            return Ok(Ok(None));
        }
        let tail = self.bytes_at(self.len - 8 - FOOTER_RECORD, (8 + FOOTER_RECORD) as usize)?;
        let ends_with_magic = &tail[FOOTER_RECORD as usize..] == mcap::MAGIC;
        let (opcode, len) = head_of(&tail);
        if opcode != op::FOOTER || len != FOOTER_RECORD - HEAD {
            return Ok(if ends_with_magic {
                Err("the file ends with the MCAP magic but no footer before it".into())
            } else {
                Ok(None)
            });
        }
        if !ends_with_magic {
            return Ok(Err(
                "the footer is not followed by the closing MCAP magic".into()
            ));
        }
        let footer = match mcap::parse_record(opcode, &tail[HEAD as usize..FOOTER_RECORD as usize])
        {
            Ok(Record::Footer(f)) => f,
            _ => return Ok(Err("the footer does not parse".into())),
        };
        let footer_at = self.len - 8 - FOOTER_RECORD;
        if footer.summary_start == 0 {
            return Ok(Ok(Some(SummaryIndex::default())));
        }
        if footer.summary_start < 8 || footer.summary_start > footer_at {
            return Ok(Err(format!(
                "the footer's summary start {} is outside the file",
                footer.summary_start
            )));
        }
        if footer.summary_crc != 0 {
            let mut h = crc32fast::Hasher::new();
            self.hash_range(footer.summary_start, self.len - 8 - 4, &mut h)?;
            let calculated = h.finalize();
            if calculated != footer.summary_crc {
                return Ok(Err(format!(
                    "the summary section's CRC is {calculated:08x}, the footer says {:08x}",
                    footer.summary_crc
                )));
            }
        }
        self.summary_records(footer.summary_start, footer_at)
            .map(|r| r.map(Some))
    }

    fn summary_records(
        &mut self,
        start: u64,
        end: u64,
    ) -> io::Result<Result<SummaryIndex, String>> {
        let mut index = SummaryIndex {
            data_end: start.checked_sub(HEAD + 4),
            ..SummaryIndex::default()
        };
        let mut at = start;
        while at < end {
            let Some((opcode, len)) = self.head(at)? else {
                return Ok(Err(format!("the summary is cut at byte {at}")));
            };
            if !plausible(opcode, len, at, end) {
                return Ok(Err(format!(
                    "the summary has an unreadable record at byte {at}"
                )));
            }
            let body = self.body(at, len)?;
            match mcap::parse_record(opcode, body) {
                Ok(Record::ChunkIndex(c)) => {
                    index.offsets.insert(c.chunk_start_offset);
                }
                Ok(Record::AttachmentIndex(a)) => {
                    index.offsets.insert(a.offset);
                }
                Ok(Record::MetadataIndex(m)) => {
                    index.offsets.insert(m.offset);
                }
                Ok(Record::Statistics(s)) => index.message_count = Some(s.message_count),
                Ok(Record::Channel(c)) => index.channels.push(c),
                Ok(Record::Schema { header, data }) => {
                    index.schemas.push((header, data.into_owned()))
                }
                Ok(_) => {}
                Err(e) => {
                    return Ok(Err(format!(
                        "the summary's record at byte {at} does not parse: {e}"
                    )))
                }
            }
            at += HEAD + len;
        }
        Ok(Ok(index))
    }

    /// The first offset at or after `from` where a framed record starts
    /// that `accept` (the full check) takes, or `None` at the end of the file.
    pub fn scan_for(
        &mut self,
        from: u64,
        mut accept: impl FnMut(&mut Self, u64) -> io::Result<bool>,
    ) -> io::Result<Option<u64>> {
        let mut block_start = from;
        while block_start + HEAD <= self.len {
            let block = self.bytes_at(block_start, SCAN_BLOCK + HEAD as usize - 1)?;
            let positions = block.len().saturating_sub(HEAD as usize - 1);
            for i in 0..positions {
                let (opcode, len) = head_of(&block[i..]);
                let at = block_start + i as u64;
                if plausible(opcode, len, at, self.len)
                    && self.framed(opcode, len, at)?
                    && accept(self, at)?
                {
                    return Ok(Some(at));
                }
            }
            block_start += positions.max(1) as u64;
        }
        Ok(None)
    }
}

/// Reads chunks with the `mcap` crate's own streaming reader
/// (`sans_io::LinearReader`: its decompressors, its CRC check of the whole
/// chunk, its record-length limit on every record inside and on the
/// compressed bytes it buffers). One reader serves every chunk of a file in
/// turn, so its buffers are reused; after a damaged chunk a fresh one
/// starts. shoal adds, checked on the chunk's header before anything is
/// decompressed, the declared size against [`MAX_CHUNK_UNCOMPRESSED`] and
/// against the file's decompression `budget` (a bomb spread over many
/// chunks), and the all-or-nothing rule: a chunk whose CRC fails or whose
/// records do not parse is lost whole, never half of it.
pub struct ChunkDecoder {
    reader: Option<mcap::sans_io::LinearReader>,
    /// Decompressed bytes the file may still yield ([`decompression_budget`]).
    pub budget: u64,
}

impl ChunkDecoder {
    pub fn new(budget: u64) -> Self {
        Self {
            reader: None,
            budget,
        }
    }

    fn fresh_reader() -> mcap::sans_io::LinearReader {
        let options = mcap::sans_io::LinearReaderOptions::default()
            .with_skip_start_magic(true)
            .with_skip_end_magic(true)
            .with_validate_chunk_crcs(true)
            .with_record_length_limit(MAX_CHUNK_UNCOMPRESSED as usize);
        mcap::sans_io::LinearReader::new_with_options(options)
    }

    /// The records of one chunk; `body` is the chunk record's body as it
    /// stands in the file, `header` its parsed header.
    pub fn read(
        &mut self,
        header: &mcap::records::ChunkHeader,
        body: &[u8],
    ) -> Result<Vec<Record<'static>>, String> {
        if header.uncompressed_size > MAX_CHUNK_UNCOMPRESSED {
            return Err(format!(
                "declares {} uncompressed bytes, over the {MAX_CHUNK_UNCOMPRESSED}-byte limit",
                header.uncompressed_size
            ));
        }
        if header.uncompressed_size > self.budget {
            return Err(format!(
                "declares {} uncompressed bytes, more than the {} left of the file's decompression budget (a decompression bomb?)",
                header.uncompressed_size, self.budget
            ));
        }
        let reader = self.reader.get_or_insert_with(Self::fresh_reader);
        let result = feed_chunk(reader, body);
        if result.is_err() {
            // Its state is mid-chunk: the next chunk starts on a fresh reader.
            self.reader = None;
        }
        let records = result?;
        self.budget -= header.uncompressed_size;
        Ok(records)
    }
}

/// Feed one chunk record to `reader` and collect its records, until the
/// reader asks for the next file record.
fn feed_chunk(
    reader: &mut mcap::sans_io::LinearReader,
    body: &[u8],
) -> Result<Vec<Record<'static>>, String> {
    let mut fed = false;
    let mut records = Vec::new();
    while let Some(event) = reader.next_event() {
        match event.map_err(|e| e.to_string())? {
            mcap::sans_io::LinearReadEvent::ReadRequest(_) if fed => return Ok(records),
            mcap::sans_io::LinearReadEvent::ReadRequest(_) => {
                // The chunk record as it stands in the file: opcode, length, body.
                let n = HEAD as usize + body.len();
                let buf = reader.insert(n);
                buf[0] = op::CHUNK;
                buf[1..HEAD as usize].copy_from_slice(&(body.len() as u64).to_le_bytes());
                buf[HEAD as usize..].copy_from_slice(body);
                reader.notify_read(n);
                fed = true;
            }
            mcap::sans_io::LinearReadEvent::Record { data, opcode } => {
                let r = mcap::parse_record(opcode, data)
                    .map_err(|e| format!("record (opcode {opcode:#04x}): {e}"))?;
                records.push(r.into_owned());
            }
        }
    }
    Err("the reader ended inside the chunk".into())
}
