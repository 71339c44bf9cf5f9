//! [`recover`]: rewrite a damaged or interrupted log with every readable
//! record and a proper summary.

use crate::reader::{scan, Item, ScanError, Skipped};
use crate::RecordError;
use proto::files::OutputFile;
use std::collections::BTreeMap;
use std::path::Path;

/// What [`recover`] did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RecoverReport {
    pub messages: u64,
    pub channels: usize,
    pub chunks_read: u64,
    /// What was wrong with the input (None: the input was intact).
    pub damage: Option<String>,
    /// The damaged regions skipped (the first ones; `skipped_regions` counts all).
    pub skipped: Vec<Skipped>,
    pub skipped_regions: u64,
    pub skipped_bytes: u64,
}

/// Rewrite `input` (typically a recording killed before it could write its
/// summary, or one with damaged bytes) to `output` with every readable
/// record and a proper summary. The output is written under a temporary name
/// and renamed when complete: a failure leaves an existing `output`
/// untouched, and `output` may not be `input`.
pub fn recover(input: &Path, output: &Path) -> Result<RecoverReport, RecordError> {
    // Open the input first: an unreadable input must not cost an existing output.
    std::fs::File::open(input).map_err(|source| RecordError::Io {
        path: input.to_path_buf(),
        source,
    })?;
    let out = OutputFile::new(output, &[input])?;
    let file = std::fs::File::create(out.temp_path()).map_err(|source| RecordError::Io {
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
    let outcome = scan(input, |item| -> Result<(), mcap::McapError> {
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
    drop(inner);
    out.commit()?;
    Ok(RecoverReport {
        messages: outcome.messages,
        channels: outcome.channels.len(),
        chunks_read: outcome.chunks,
        damage: outcome.damage,
        skipped: outcome.skipped,
        skipped_regions: outcome.skipped_regions,
        skipped_bytes: outcome.skipped_bytes,
    })
}
