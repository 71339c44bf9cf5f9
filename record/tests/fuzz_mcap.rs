//! Fuzzing the MCAP reader and `log recover` (issue #10): a small shoal log
//! of several zstd chunks, cut at random points (a recording killed
//! mid-chunk) or with random bytes overwritten. Reading never panics; a cut
//! file yields exactly the messages of its complete chunks, never more than
//! were written and each one byte for byte; `recover` turns whatever is
//! readable into a complete file.
//!
//! Cases per property: `SHOAL_FUZZ_CASES` (default 256).
//! Longer on demand: `SHOAL_FUZZ_CASES=5000 cargo test -p shoal-record --test fuzz_mcap`.

use proptest::prelude::*;
use proptest::test_runner::Config as ProptestConfig;
use shoal_proto::geometry::{pose_from_xyz_rpy, Cov6};
use shoal_proto::messages::*;
use shoal_proto::CodeSet;
use shoal_record::reader::{header, scan_wire};
use shoal_record::recover;
use shoal_record::{info, LogWriter, WriterOptions};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// Failures print the minimal input; no regression files in the source tree.
fn fuzz_config(default_cases: u32) -> ProptestConfig {
    ProptestConfig {
        failure_persistence: None,
        ..ProptestConfig::with_cases(shoal_proto::samples::fuzz_cases(default_cases))
    }
}

const MESSAGES: u64 = 200;

fn scratch(name: &str) -> PathBuf {
    let dir =
        Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("fuzz_mcap-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn observation(i: u64) -> Observation {
    Observation {
        observer: 10,
        camera: (i % 5) as u8,
        codes: CodeSet::Shoal,
        target_marker: 15,
        target_vehicle: Some(15),
        stamp_ns: 1_000_000 * i,
        frame_seq: i,
        observer_from_target: pose_from_xyz_rpy(
            [0.1, 1.0 + i as f64 * 1e-3, 0.2],
            [0.0, 0.1, -0.2],
        ),
        covariance: Cov6::identity() * 1e-4,
        reprojection_rms_px: 0.2,
        alternative: None,
        corner_count: 12,
        corners_px: vec![[i as f32, 2.0]; 12],
        quality: ImageQuality::default(),
        predicted: false,
    }
}

/// The intact log's bytes and the envelopes written, in order.
fn intact() -> &'static (Vec<u8>, Vec<Vec<u8>>) {
    static LOG: OnceLock<(Vec<u8>, Vec<Vec<u8>>)> = OnceLock::new();
    LOG.get_or_init(|| {
        let path = scratch("intact.mcap");
        let opts = WriterOptions {
            chunk_size: 4096,
            zstd_level: 0,
            ..Default::default()
        };
        let mut meta = BTreeMap::new();
        meta.insert("fleet".to_string(), "paper".to_string());
        let mut w = LogWriter::create(&path, &opts, &meta, Some("fleet = \"paper\"\n"), 1).unwrap();
        let mut sent = Vec::new();
        for i in 0..MESSAGES {
            let bytes = shoal_proto::encode(&observation(i)).unwrap();
            w.write_wire(
                "shoal/paper/10/obs",
                Some(MessageKind::Observation),
                &bytes,
                i + 10,
                i + 10,
            )
            .unwrap();
            sent.push(bytes);
        }
        w.finish().unwrap();
        (std::fs::read(&path).unwrap(), sent)
    })
}

fn wire_messages(buf: &[u8]) -> Option<(Vec<Vec<u8>>, shoal_record::reader::ScanOutcome)> {
    let mut got = Vec::new();
    let outcome = scan_wire(buf, |_, _, data| -> Result<(), ()> {
        got.push(data.to_vec());
        Ok(())
    })
    .ok()?;
    Some((got, outcome))
}

#[test]
fn the_intact_log_reads_completely_over_several_chunks() {
    let (buf, sent) = intact();
    let (got, outcome) = wire_messages(buf).unwrap();
    assert!(outcome.complete, "{:?}", outcome.damage);
    assert!(outcome.chunks >= 4, "only {} chunks", outcome.chunks);
    assert_eq!(&got, sent);
}

/// Each chunk of the intact log as (byte where it ends, messages it holds),
/// from its summary by the `mcap` crate's indexed reader.
fn chunks() -> &'static [(usize, usize)] {
    static CHUNKS: OnceLock<Vec<(usize, usize)>> = OnceLock::new();
    CHUNKS.get_or_init(|| {
        let (buf, _) = intact();
        let summary = shoal_record::mcap::Summary::read(buf).unwrap().unwrap();
        summary
            .chunk_indexes
            .iter()
            .map(|ci| {
                let messages = summary
                    .read_message_indexes(buf, ci)
                    .unwrap()
                    .values()
                    .map(Vec::len)
                    .sum();
                ((ci.chunk_start_offset + ci.chunk_length) as usize, messages)
            })
            .collect()
    })
}

/// The most messages one chunk of the intact log holds.
fn messages_per_chunk_max() -> usize {
    chunks().iter().map(|&(_, n)| n).max().unwrap()
}

/// Messages of the intact log's chunks that end at or before byte `cut`.
fn messages_in_chunks_before(cut: usize) -> usize {
    chunks()
        .iter()
        .filter(|&&(end, _)| end <= cut)
        .map(|&(_, n)| n)
        .sum()
}

/// Whether `got` is `sent` with some messages left out (same order, each byte for byte).
fn is_subsequence(got: &[Vec<u8>], sent: &[Vec<u8>]) -> bool {
    let mut it = sent.iter();
    got.iter().all(|g| it.any(|s| s == g))
}

proptest! {
    #![proptest_config(fuzz_config(256))]

    /// Issue #22: one damaged byte anywhere costs at most the record it is
    /// in. Every message outside the damaged chunk is read, none is altered,
    /// and the file is never called complete; `recover` keeps the same.
    #[test]
    fn one_flipped_byte_costs_at_most_its_record(at in any::<usize>(), v in 1u8..=255) {
        let (buf, sent) = intact();
        let mut damaged = buf.clone();
        let i = at % damaged.len();
        damaged[i] ^= v;
        let (got, outcome) = wire_messages(&damaged).expect("one flipped byte keeps it MCAP");
        prop_assert!(!outcome.complete, "byte {i} flipped, still called complete");
        prop_assert!(outcome.damage.is_some());
        prop_assert!(is_subsequence(&got, sent), "byte {i}: a message came out altered or out of order");
        let lost = sent.len() - got.len();
        prop_assert!(lost <= messages_per_chunk_max(), "byte {i}: {lost} messages lost ({:?})", outcome.damage);
        let input = scratch(&format!("flip-{i}.mcap"));
        let output = scratch(&format!("flip-{i}-recovered.mcap"));
        std::fs::write(&input, &damaged).unwrap();
        let report = recover(&input, &output).unwrap();
        prop_assert_eq!(report.messages, got.len() as u64);
        let (again, fixed) = wire_messages(&std::fs::read(&output).unwrap()).unwrap();
        prop_assert!(fixed.complete, "{:?}", fixed.damage);
        prop_assert_eq!(again, got);
        let _ = std::fs::remove_file(&input);
        let _ = std::fs::remove_file(&output);
    }

    /// A recording killed at any byte: a prefix of what was written, read
    /// exactly, and `recover` writes a complete file holding the same.
    #[test]
    fn a_log_cut_anywhere_yields_a_prefix_and_recovers(cut in any::<usize>()) {
        let (buf, sent) = intact();
        let cut_at = cut % (buf.len() + 1);
        let damaged = &buf[..cut_at];
        match wire_messages(damaged) {
            None => prop_assert!(cut_at < 16, "a cut at {cut_at} of {} is not MCAP any more", buf.len()),
            Some((got, outcome)) => {
                prop_assert!(got.len() <= sent.len());
                prop_assert_eq!(&got[..], &sent[..got.len()]);
                // Every chunk that ends before the cut is read, whole.
                prop_assert_eq!(got.len(), messages_in_chunks_before(cut_at), "cut at {}", cut_at);
                if cut_at < buf.len() {
                    prop_assert!(!outcome.complete);
                    prop_assert!(outcome.damage.is_some());
                }
                let input = scratch(&format!("cut-{cut_at}.mcap"));
                let output = scratch(&format!("cut-{cut_at}-recovered.mcap"));
                std::fs::write(&input, damaged).unwrap();
                let report = recover(&input, &output).unwrap();
                prop_assert_eq!(report.messages, got.len() as u64);
                let fixed = std::fs::read(&output).unwrap();
                let (again, outcome) = wire_messages(&fixed).unwrap();
                prop_assert!(outcome.complete, "recovered file is incomplete: {:?}", outcome.damage);
                prop_assert_eq!(again, got);
                let _ = info(&output).unwrap();
                let _ = std::fs::remove_file(&input);
                let _ = std::fs::remove_file(&output);
            }
        }
    }

    /// Random bytes overwritten anywhere: reading, `header`, `info` and
    /// `recover` return (Ok or a typed error), and never invent a message.
    #[test]
    fn a_garbled_log_never_panics_the_reader(
        flips in proptest::collection::vec((any::<usize>(), 1u8..=255), 1..6),
        cut in proptest::option::of(any::<usize>()),
    ) {
        let (buf, sent) = intact();
        let mut damaged = buf.clone();
        for (at, v) in flips {
            let i = at % damaged.len();
            damaged[i] ^= v;
        }
        if let Some(c) = cut {
            damaged.truncate(c % (damaged.len() + 1));
        }
        if let Some((got, _)) = wire_messages(&damaged) {
            // Chunk CRCs catch damage inside compressed data; a message
            // record outside a chunk's payload may still be altered, but
            // never more messages than were written come out.
            prop_assert!(got.len() <= sent.len());
        }
        let _ = header(&damaged);
        let input = scratch("garbled.mcap");
        let output = scratch("garbled-recovered.mcap");
        std::fs::write(&input, &damaged).unwrap();
        let _ = info(&input);
        if recover(&input, &output).is_ok() {
            let fixed = std::fs::read(&output).unwrap();
            let (_, outcome) = wire_messages(&fixed).expect("recover writes MCAP");
            prop_assert!(outcome.complete);
        }
    }
}

/// Issue #22, exhaustively: every byte of the log flipped in turn (by a
/// value that varies with the offset). Not one of them is read as complete,
/// alters or reorders a message, or costs more than one chunk's messages.
#[test]
fn every_byte_flipped_in_turn_costs_at_most_its_record() {
    let (buf, sent) = intact();
    let max = messages_per_chunk_max();
    let mut failures = Vec::new();
    for i in 0..buf.len() {
        let v = (i * 37 % 255 + 1) as u8;
        let mut d = buf.clone();
        d[i] ^= v;
        let (got, outcome) = wire_messages(&d).expect("one flipped byte keeps it MCAP");
        let lost = sent.len() - got.len();
        if outcome.complete || lost > max || !is_subsequence(&got, sent) {
            failures.push(format!(
                "byte {i} ^ {v:#04x}: complete {}, {lost} lost, {:?}",
                outcome.complete, outcome.damage
            ));
        }
    }
    assert!(
        failures.is_empty(),
        "{} of {} flips: {:#?}",
        failures.len(),
        buf.len(),
        &failures[..failures.len().min(10)]
    );
}
