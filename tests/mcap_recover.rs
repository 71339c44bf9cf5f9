//! A recorder killed with SIGKILL leaves a file whose complete chunks are
//! readable, and `shoal log recover` rewrites it with a proper summary.
//! The recorder runs as a child process (`shoal record`), the test hosts the
//! Zenoh router and publishes observations into it.

use shoal_bus::{client_of, free_port, Bus, Connect};
use shoal_proto::config::Fleet;
use shoal_proto::messages::{Observation, SimTruth};
use shoal_record::mcap;
use shoal_record::reader::{scan, Item};
use shoal_sim_bridge::obs_synth::{line_abreast, ObsSynth, ObsSynthParams};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// The recorder's `--flush-ms`: at most this much is lost by a kill.
const FLUSH_MS: u64 = 200;

fn count_messages(buf: &[u8]) -> (u64, shoal_record::reader::ScanOutcome) {
    let mut n = 0;
    let outcome = scan(buf, |item| -> Result<(), ()> {
        if let Item::Message { channel, .. } = item {
            if channel.is_wire() {
                n += 1;
            }
        }
        Ok(())
    })
    .unwrap();
    (n, outcome)
}

#[test]
#[allow(
    clippy::too_many_lines,
    reason = "one scenario in order: record, SIGKILL the recorder, read the damaged file, recover it, read it again"
)]
fn sigkilled_recorder_leaves_a_readable_file_that_recover_fixes() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let fleet_path = root.join("configs/fleets/paper.toml");
    let fleet = Fleet::load(&fleet_path).unwrap();
    let keys = fleet.keys();
    let dir =
        Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("mcap_recover-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let killed = dir.join("killed.mcap");
    let fixed = dir.join("fixed.mcap");
    let _ = std::fs::remove_file(&killed);

    let port = free_port().unwrap();
    let _router = Bus::open(&Connect::Router { port }).unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_shoal"))
        .args(["record", "--fleet"])
        .arg(&fleet_path)
        .arg("--out")
        .arg(&killed)
        .args([
            "--port",
            &port.to_string(),
            "--flush-ms",
            &FLUSH_MS.to_string(),
            "--log",
            "warn",
        ])
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    // Wait for the recorder to open its file (metadata is written first), then for its subscription to propagate.
    let t0 = Instant::now();
    while !killed.exists() && t0.elapsed() < Duration::from_secs(30) {
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(killed.exists(), "the recorder did not start");
    std::thread::sleep(Duration::from_millis(1500));

    let bus = Bus::open(&client_of(port)).unwrap();
    let truth_pub = bus.publisher::<SimTruth>(keys.truth()).unwrap();
    let obs_pubs: Vec<_> = fleet
        .vehicles
        .iter()
        .map(|v| {
            (
                v.id,
                bus.publisher::<Observation>(keys.observations(v.id))
                    .unwrap(),
            )
        })
        .collect();
    let ids: Vec<u32> = fleet.vehicles.iter().map(|v| v.id).collect();
    let mut synth = ObsSynth::new(&fleet, ObsSynthParams::default(), 3);
    let mut published = 0u64;
    // 3 s at 20 Hz, then kill -9 without warning.
    for tick in 0..60u64 {
        let stamp = tick * 50_000_000;
        let truth = line_abreast(&ids, 1.75);
        truth_pub
            .put(&SimTruth {
                stamp_ns: stamp,
                tick,
                water_c_per_m: 0.5,
                vehicles: truth.clone(),
                visible: vec![],
            })
            .unwrap();
        published += 1;
        for o in synth.observe(&truth, stamp) {
            obs_pubs
                .iter()
                .find(|(v, _)| *v == o.obs.observer)
                .unwrap()
                .1
                .put(&o.obs)
                .unwrap();
            published += 1;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    child.kill().unwrap(); // SIGKILL on Unix
    child.wait().unwrap();

    let buf = std::fs::read(&killed).unwrap();
    assert!(
        mcap::Summary::read(&buf).map_or(true, |s| s.is_none()),
        "a killed recorder cannot have written a summary"
    );
    assert!(
        mcap::MessageStream::new(&buf)
            .and_then(|mut s| s.try_for_each(|m| m.map(|_| ())))
            .is_err(),
        "strict readers must refuse the killed file"
    );
    let (readable, outcome) = count_messages(&buf);
    assert!(!outcome.complete);
    assert!(outcome.damage.is_some());
    // Everything but the last flush interval or so must be in complete chunks.
    let per_second = published as f64 / 3.0;
    let lost_at_most = (per_second * (FLUSH_MS as f64 / 1000.0 + 0.3)).ceil() as u64;
    eprintln!("published {published}, readable after SIGKILL {readable} ({} chunks), allowed loss {lost_at_most}", outcome.chunks);
    assert!(
        readable + lost_at_most >= published && readable <= published,
        "readable {readable} of {published}"
    );
    let info = shoal_record::info(&killed).unwrap();
    assert!(!info.complete && info.metadata.get("fleet").map(String::as_str) == Some("paper"));

    let out = Command::new(env!("CARGO_BIN_EXE_shoal"))
        .args(["log", "recover"])
        .arg(&killed)
        .arg("--out")
        .arg(&fixed)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let fixed_buf = std::fs::read(&fixed).unwrap();
    let summary = mcap::Summary::read(&fixed_buf)
        .unwrap()
        .expect("recovered file has a summary");
    let stats = summary.stats.expect("statistics");
    let strict: u64 = mcap::MessageStream::new(&fixed_buf)
        .unwrap()
        .map(|m| m.map(|_| 1))
        .sum::<Result<u64, _>>()
        .unwrap();
    assert_eq!(strict, stats.message_count);
    let (wire, outcome) = count_messages(&fixed_buf);
    assert!(outcome.complete && outcome.damage.is_none());
    assert_eq!(wire, readable, "recover keeps every readable wire message");
    // The header items survive too.
    let h = shoal_record::reader::header(&fixed_buf).unwrap();
    assert_eq!(h.metadata.get("fleet").map(String::as_str), Some("paper"));
    assert!(h
        .fleet_toml
        .is_some_and(|t| t.contains("reference_vehicle = 10")));
}
