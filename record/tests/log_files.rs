//! Issue #22, logs: files the recorder did not write the way it writes them
//! (LZ4 chunks, decompression bombs, damaged summaries and attachments) and
//! outputs that must never destroy what they replace.

use shoal_proto::config::Fleet;
use shoal_proto::geometry::{pose_from_xyz_rpy, Cov6};
use shoal_proto::messages::*;
use shoal_proto::CodeSet;
use shoal_record::mcap;
use shoal_record::reader::{scan, scan_wire, Item};
use shoal_record::{recover, refuse, FuseOptions, LogWriter, RecordError, WriterOptions};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

const MESSAGES: u64 = 120;

fn scratch(name: &str) -> PathBuf {
    let dir =
        Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("log_files-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn fleet_path() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/fleets/paper.toml")
}

fn observation(i: u64) -> Observation {
    Observation {
        observer: 10,
        camera: 0,
        codes: CodeSet::Shoal,
        target_marker: 15,
        target_vehicle: Some(15),
        stamp_ns: 50_000_000 * i,
        frame_seq: i,
        observer_from_target: pose_from_xyz_rpy([0.1, 1.5, 0.2], [0.0, 0.1, -0.2]),
        covariance: Cov6::identity() * 1e-4,
        reprojection_rms_px: 0.2,
        alternative: None,
        corner_count: 12,
        corners_px: vec![[i as f32, 2.0]; 12],
        quality: ImageQuality::default(),
        predicted: false,
    }
}

/// A shoal log of the paper fleet with `MESSAGES` observations in small chunks.
fn paper_log(name: &str) -> PathBuf {
    let path = scratch(name);
    let fleet_toml = std::fs::read_to_string(fleet_path()).unwrap();
    let mut meta = BTreeMap::new();
    meta.insert("fleet".to_string(), "paper".to_string());
    let opts = WriterOptions {
        chunk_size: 4096,
        zstd_level: 0,
        ..Default::default()
    };
    let mut w = LogWriter::create(&path, &opts, &meta, Some(&fleet_toml), 1).unwrap();
    for i in 0..MESSAGES {
        let bytes = shoal_proto::encode(&observation(i)).unwrap();
        w.write_wire(
            "shoal/paper/10/obs",
            Some(MessageKind::Observation),
            &bytes,
            i * 50_000_000,
            i * 50_000_000,
        )
        .unwrap();
    }
    w.finish().unwrap();
    path
}

fn count_wire(path: &Path) -> (u64, shoal_record::reader::ScanOutcome) {
    let mut n = 0;
    let outcome = scan_wire(path, |_, _, _| -> Result<(), ()> {
        n += 1;
        Ok(())
    })
    .unwrap();
    (n, outcome)
}

/// The byte range of the first record with `opcode` at the top level of `buf`.
fn top_record(buf: &[u8], opcode: u8) -> std::ops::Range<usize> {
    let mut at = 8;
    while at + 9 <= buf.len() {
        let len = u64::from_le_bytes(buf[at + 1..at + 9].try_into().unwrap()) as usize;
        if buf[at] == opcode {
            return at..at + 9 + len;
        }
        at += 9 + len;
    }
    panic!("no record {opcode:#04x}");
}

#[test]
fn lz4_chunks_written_by_liblz4_are_read() {
    let path = scratch("lz4.mcap");
    let mut w = mcap::WriteOptions::new()
        .compression(Some(mcap::Compression::Lz4))
        .chunk_size(Some(2048))
        .create(std::io::BufWriter::new(
            std::fs::File::create(&path).unwrap(),
        ))
        .unwrap();
    let ch = w
        .add_channel(0, "shoal/paper/10/obs", "shoal-envelope", &BTreeMap::new())
        .unwrap();
    let mut sent = Vec::new();
    for i in 0..MESSAGES {
        let bytes = shoal_proto::encode(&observation(i)).unwrap();
        w.write_to_known_channel(
            &mcap::records::MessageHeader {
                channel_id: ch,
                sequence: i as u32,
                log_time: i,
                publish_time: i,
            },
            &bytes,
        )
        .unwrap();
        sent.push(bytes);
    }
    w.finish().unwrap();
    drop(w);
    let mut got = Vec::new();
    let outcome = scan(&path, |item| -> Result<(), ()> {
        if let Item::Message { data, .. } = item {
            got.push(data.to_vec());
        }
        Ok(())
    })
    .unwrap();
    assert!(outcome.complete, "{:?}", outcome.damage);
    assert!(outcome.chunks > 3);
    assert_eq!(got, sent);
}

#[test]
fn a_decompression_bomb_is_refused_before_it_is_allocated() {
    // A chunk of 100 MiB of zeros compresses to a few kilobytes.
    let size = 100usize << 20;
    let compressed = zstd_bomb(size);
    // Chunk header: start and end time, uncompressed size and CRC, compression, compressed size.
    let mut body = Vec::new();
    body.extend_from_slice(&0u64.to_le_bytes());
    body.extend_from_slice(&0u64.to_le_bytes());
    body.extend_from_slice(&(size as u64).to_le_bytes());
    body.extend_from_slice(&0u32.to_le_bytes());
    body.extend_from_slice(&4u32.to_le_bytes());
    body.extend_from_slice(b"zstd");
    body.extend_from_slice(&(compressed.len() as u64).to_le_bytes());
    body.extend_from_slice(&compressed);
    let mut file = mcap::MAGIC.to_vec();
    for _ in 0..4 {
        file.push(0x06);
        file.extend_from_slice(&(body.len() as u64).to_le_bytes());
        file.extend_from_slice(&body);
    }
    assert!(file.len() < 64 << 10, "bomb of {} bytes", file.len());
    let outcome = scan(&file, |_| Ok::<(), ()>(())).unwrap();
    assert!(!outcome.complete);
    assert_eq!(outcome.chunks, 0);
    assert_eq!(outcome.decompressed_bytes, 0);
    assert_eq!(outcome.skipped_regions, 4, "{:?}", outcome.skipped);
    assert!(
        outcome.skipped[0].reason.contains("decompression budget"),
        "{:?}",
        outcome.skipped[0]
    );
}

fn zstd_bomb(size: usize) -> Vec<u8> {
    let mut enc = zstd_encoder();
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..size >> 20 {
        std::io::Write::write_all(&mut enc, &zeros).unwrap();
    }
    enc.finish().unwrap()
}

fn zstd_encoder() -> zstd::stream::Encoder<'static, Vec<u8>> {
    zstd::stream::Encoder::new(Vec::new(), 3).unwrap()
}

#[test]
fn a_damaged_summary_or_footer_is_not_called_complete_and_loses_no_message() {
    let path = paper_log("summary.mcap");
    let buf = std::fs::read(&path).unwrap();
    let stats = top_record(&buf, 0x0B);
    // One byte in the statistics record (summary), one in the footer's CRC, one in the closing magic.
    for at in [stats.start + 12, buf.len() - 10, buf.len() - 3] {
        let mut d = buf.clone();
        d[at] ^= 0x40;
        let damaged = scratch(&format!("summary-{at}.mcap"));
        std::fs::write(&damaged, &d).unwrap();
        let (n, outcome) = count_wire(&damaged);
        assert_eq!(n, MESSAGES, "byte {at}");
        assert!(!outcome.complete, "byte {at} flipped, called complete");
        assert!(
            outcome
                .damage
                .as_deref()
                .unwrap_or("")
                .contains("indexed readers"),
            "byte {at}: {:?}",
            outcome.damage
        );
        let info = shoal_record::info(&damaged).unwrap();
        assert!(!info.complete);
        let report = recover(&damaged, &scratch("summary-fixed.mcap")).unwrap();
        assert!(
            report.damage.is_some(),
            "recover called byte {at}'s file intact"
        );
        assert_eq!(report.messages, MESSAGES);
    }
}

#[test]
fn a_damaged_fleet_attachment_costs_the_attachment_only() {
    let path = paper_log("attachment.mcap");
    let mut buf = std::fs::read(&path).unwrap();
    let att = top_record(&buf, 0x09);
    buf[att.start + 60] ^= 0x01;
    let damaged = scratch("attachment-damaged.mcap");
    std::fs::write(&damaged, &buf).unwrap();
    let (n, outcome) = count_wire(&damaged);
    assert_eq!(n, MESSAGES);
    assert_eq!(outcome.skipped_regions, 1);
    assert!(
        outcome.skipped[0].reason.contains("CRC"),
        "{:?}",
        outcome.skipped
    );
    // Re-fusion needs the fleet: it says so, and works when given one.
    let out = scratch("attachment-fused.mcap");
    match refuse(&damaged, &out, &FuseOptions::default()) {
        Err(RecordError::NoFleet(p)) => assert_eq!(p, damaged),
        other => panic!("expected NoFleet, got {other:?}"),
    }
    let opts = FuseOptions {
        fleet: Some(Fleet::load(&fleet_path()).unwrap()),
        ..FuseOptions::default()
    };
    let s = refuse(&damaged, &out, &opts).unwrap();
    assert_eq!(s.observations, MESSAGES);
    assert!(s.input_damage.is_some());
}

#[test]
fn outputs_never_destroy_an_existing_file_or_their_input() {
    let good = paper_log("outputs.mcap");
    // A folder of its own: the other tests' outputs in the shared one have
    // temporary files of their own while they run.
    let dir =
        Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("log_outputs-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let existing = dir.join("existing.mcap");
    std::fs::write(&existing, b"an earlier result").unwrap();
    let garbage = dir.join("garbage.bin");
    std::fs::write(&garbage, b"this is not an MCAP file at all").unwrap();
    // An unreadable input leaves the existing output as it was, and no temporary file.
    assert!(recover(&garbage, &existing).is_err());
    assert!(recover(&scratch("missing.mcap"), &existing).is_err());
    assert!(refuse(&garbage, &existing, &FuseOptions::default()).is_err());
    assert_eq!(std::fs::read(&existing).unwrap(), b"an earlier result");
    let debris: Vec<_> = std::fs::read_dir(existing.parent().unwrap())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().contains(".partial-"))
        .collect();
    assert!(debris.is_empty(), "{debris:?}");
    // The output may not be the input.
    let before = std::fs::read(&good).unwrap();
    assert!(matches!(recover(&good, &good), Err(RecordError::Output(_))));
    assert!(matches!(
        refuse(&good, &good, &FuseOptions::default()),
        Err(RecordError::Output(_))
    ));
    assert_eq!(std::fs::read(&good).unwrap(), before);
}

#[test]
fn fuse_refuses_another_fleet_and_counts_what_it_cannot_decode() {
    let path = scratch("undecodable.mcap");
    let fleet_toml = std::fs::read_to_string(fleet_path()).unwrap();
    let mut meta = BTreeMap::new();
    meta.insert("fleet".to_string(), "paper".to_string());
    let mut w = LogWriter::create(
        &path,
        &WriterOptions::default(),
        &meta,
        Some(&fleet_toml),
        1,
    )
    .unwrap();
    for i in 0..10u64 {
        let mut bytes = shoal_proto::encode(&observation(i)).unwrap();
        if i % 2 == 1 {
            // A valid envelope header over a payload cut short.
            bytes.truncate(bytes.len() - 20);
        }
        w.write_wire(
            "shoal/paper/10/obs",
            Some(MessageKind::Observation),
            &bytes,
            i,
            i,
        )
        .unwrap();
    }
    w.finish().unwrap();
    let out = scratch("undecodable-fused.mcap");
    let s = refuse(&path, &out, &FuseOptions::default()).unwrap();
    assert_eq!((s.observations, s.undecodable), (5, 5));
    let mut other = Fleet::load(&fleet_path()).unwrap();
    other.name = "another".into();
    let opts = FuseOptions {
        fleet: Some(other),
        ..FuseOptions::default()
    };
    assert!(matches!(
        refuse(&path, &out, &opts),
        Err(RecordError::FleetMismatch { .. })
    ));
}

/// A log of format 1 (Foxglove channels in JSON, no `log_format` key), as
/// `shoal demo` wrote it before protobuf: `tests/data/logs/README.md`.
fn format1_log() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/data/logs/format1_demo.mcap")
}

/// Counts what a replay sends.
#[derive(Default)]
struct Count {
    keys: usize,
    messages: u64,
}

impl shoal_record::ReplaySink for Count {
    fn declare(&mut self, _key: &str, _kind: MessageKind) -> Result<(), RecordError> {
        self.keys += 1;
        Ok(())
    }
    fn send(&mut self, _key: &str, envelope: &[u8]) -> Result<(), RecordError> {
        shoal_proto::codec::peek_header(envelope).unwrap();
        self.messages += 1;
        Ok(())
    }
}

#[test]
fn format1_logs_still_read_replay_and_refuse() {
    let old = format1_log();
    let info = shoal_record::info(&old).unwrap();
    assert!(info.complete, "{:?}", info.damage);
    assert!(!info.metadata.contains_key("log_format"));
    assert!(info.has_fleet_file);
    assert_eq!(info.vehicles, vec![10, 15, 17]);
    let json = |c: &&shoal_record::info::ChannelFigures| c.message_encoding == "json";
    let wire = |c: &&shoal_record::info::ChannelFigures| c.message_encoding == "shoal-envelope";
    assert!(info.channels.iter().filter(json).count() >= 10);
    let wire_messages: u64 = info.channels.iter().filter(wire).map(|c| c.messages).sum();
    let obs: u64 = info
        .channels
        .iter()
        .filter(|c| c.schema == "shoal.Observation")
        .map(|c| c.messages)
        .sum();
    assert!(obs > 0);

    let mut sink = Count::default();
    let opts = shoal_record::ReplayOptions {
        rate: f64::INFINITY,
        settle: std::time::Duration::ZERO,
        ..Default::default()
    };
    let r = shoal_record::replay_into(
        &mut sink,
        &old,
        &opts,
        &std::sync::atomic::AtomicBool::new(false),
    )
    .unwrap();
    assert_eq!((r.messages, sink.messages), (wire_messages, wire_messages));

    // Re-fused into a format-2 log (its own folder: another test lists the shared one).
    let dir =
        Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("log_format1-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let out = dir.join("format1_refused.mcap");
    let s = refuse(&old, &out, &FuseOptions::default()).unwrap();
    assert_eq!(s.observations, obs);
    assert!(s.maps_written > 0 && s.undecodable == 0, "{s:?}");
    let new = shoal_record::info(&out).unwrap();
    assert_eq!(
        new.metadata.get("log_format"),
        Some(&shoal_record::writer::LOG_FORMAT.to_string())
    );
}
