//! MCAP logs end to end (issue #8): a short live recording of every message
//! kind over Zenoh (in-process router, real fusion service, synthetic
//! observations of the paper fleet), then
//! - the independent Python `mcap` reader opens it with CRCs validated and
//!   every Foxglove channel validates against the JSON schema in the file;
//! - offline re-fusion is bit-identical twice and matches the live maps;
//! - replaying it into a fresh fusion service reproduces the live map.

use shoal_bus::{client_of, free_port, Bus, Connect, Subscription};
use shoal_fusion::FusionParams;
use shoal_proto::clock::{Clock, ManualClock};
use shoal_proto::config::Fleet;
use shoal_proto::messages::*;
use shoal_proto::CameraModel;
use shoal_record::reader::{scan, Item};
use shoal_record::refuse::compare_maps;
use shoal_record::{FuseOptions, RecordOptions, RecordSummary, ReplayOptions, SolveAt};
use shoal_services::fusion::{FusionConfig, Placement};
use shoal_services::recorder::Recorder;
use shoal_sim_bridge::obs_synth::{line_abreast, ObsSynth, ObsSynthParams};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, OnceLock};
use std::time::Duration;

/// Simulated seconds of the recorded trial and its tick rate.
const TRIAL_S: f64 = 10.0;
const TICK_HZ: f64 = 10.0;

struct Recorded {
    path: PathBuf,
    summary: RecordSummary,
    published: std::collections::HashMap<MessageKind, u64>,
}

fn fleet() -> Arc<Fleet> {
    Arc::new(
        Fleet::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/fleets/paper.toml"))
            .unwrap(),
    )
}

fn tmp(name: &str) -> PathBuf {
    // Per process: nextest runs each test in its own process, all sharing the recording path otherwise.
    let dir =
        Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("mcap_record-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn small_frame(vehicle: VehicleId, camera: u8, seq: u64, stamp_ns: u64) -> CameraFrame {
    let (w, h) = (64u32, 48u32);
    CameraFrame {
        vehicle,
        camera,
        seq,
        stamp_ns,
        info: CameraInfo {
            model: CameraModel {
                width: w,
                height: h,
                fx: 50.0,
                fy: 50.0,
                cx: 32.0,
                cy: 24.0,
                distortion: shoal_proto::Distortion::NONE,
            },
            body_from_camera: shoal_proto::Pose::identity(),
        },
        format: PixelFormat::Mono8,
        data: (0..w * h)
            .map(|i| ((i % w) * 4 + seq as u32) as u8)
            .collect(),
    }
}

/// The shared live recording (made once per test process).
fn recording() -> &'static Recorded {
    static REC: OnceLock<Recorded> = OnceLock::new();
    REC.get_or_init(|| {
        let fleet = fleet();
        let keys = fleet.keys();
        let port = free_port().unwrap();
        let _router = Bus::open(&Connect::Router { port }).unwrap();
        let path = tmp("live.mcap");
        let rec_bus = Bus::open(&client_of(port)).unwrap();
        let recorder = Recorder::spawn(
            &rec_bus,
            fleet.clone(),
            &path,
            RecordOptions {
                frames: true,
                frame_rate_limit_hz: Some(2.0),
                flush_interval: Duration::from_millis(200),
                water_c_per_m: Some(0.5),
                ..RecordOptions::default()
            },
        )
        .unwrap();
        let clock = Arc::new(ManualClock::new(0));
        let fusion = shoal_services::fusion::spawn(
            &Bus::open(&client_of(port)).unwrap(),
            FusionConfig::central(fleet.clone(), 10.0),
            clock.clone(),
        )
        .unwrap();
        let bus = Bus::open(&client_of(port)).unwrap();
        let ids: Vec<VehicleId> = fleet.vehicles.iter().map(|v| v.id).collect();
        let obs_pubs: Vec<_> = ids
            .iter()
            .map(|&v| {
                (
                    v,
                    bus.publisher::<Observation>(keys.observations(v)).unwrap(),
                )
            })
            .collect();
        let status_pubs: Vec<_> = ids
            .iter()
            .map(|&v| bus.publisher::<NodeStatus>(keys.status(v)).unwrap())
            .collect();
        let truth_pub = bus.publisher::<SimTruth>(keys.truth()).unwrap();
        let cmd_pub = bus.publisher::<VehicleCommand>(keys.command(15)).unwrap();
        let frame_pub = bus.publisher::<CameraFrame>(keys.frame(10, 4)).unwrap();
        // A node outside the fleet (fusion ignores it, so the maps are not
        // affected) is alive for the first half of the trial.
        let mut token = Some(bus.liveliness_token(keys.alive(99)).unwrap());
        std::thread::sleep(Duration::from_millis(600));

        let mut synth = ObsSynth::new(&fleet, ObsSynthParams::default(), 11);
        let mut published = std::collections::HashMap::new();
        let mut count = |k: MessageKind| *published.entry(k).or_insert(0u64) += 1;
        let ticks = (TRIAL_S * TICK_HZ) as u64;
        for tick in 0..ticks {
            if tick == ticks / 2 {
                token.take();
            }
            let stamp = (tick as f64 / TICK_HZ * 1e9) as u64;
            // The formation drifts ahead slowly, so the log has motion.
            let mut truth = line_abreast(&ids, 1.75);
            for t in &mut truth {
                t.world_from_body.translation.vector.x += 0.2 * stamp as f64 * 1e-9;
            }
            clock.advance_to(stamp);
            truth_pub
                .put(&SimTruth {
                    stamp_ns: stamp,
                    tick,
                    water_c_per_m: 0.5,
                    vehicles: truth.clone(),
                    visible: vec![],
                })
                .unwrap();
            count(MessageKind::SimTruth);
            for o in synth.observe(&truth, stamp) {
                let (_, p) = obs_pubs.iter().find(|(v, _)| *v == o.obs.observer).unwrap();
                p.put(&o.obs).unwrap();
                count(MessageKind::Observation);
            }
            // 5 Hz frames, of which the recorder keeps 2 Hz.
            if tick % 2 == 0 {
                frame_pub.put(&small_frame(10, 4, tick, stamp)).unwrap();
                count(MessageKind::CameraFrame);
            }
            if tick % 10 == 0 {
                for (p, &v) in status_pubs.iter().zip(&ids) {
                    p.put(&NodeStatus {
                        vehicle: v,
                        stamp_ns: stamp,
                        uptime_s: stamp as f64 * 1e-9,
                        ..Default::default()
                    })
                    .unwrap();
                    count(MessageKind::NodeStatus);
                }
                cmd_pub
                    .put(&VehicleCommand {
                        vehicle: 15,
                        stamp_ns: stamp,
                        velocity_body: [0.2, 0.0, 0.0],
                        yaw_rate: 0.0,
                    })
                    .unwrap();
                count(MessageKind::VehicleCommand);
            }
            std::thread::sleep(Duration::from_millis(25));
        }
        std::thread::sleep(Duration::from_millis(400));
        fusion.stop();
        std::thread::sleep(Duration::from_millis(200));
        let summary = recorder.stop().unwrap();
        Recorded {
            path,
            summary,
            published,
        }
    })
}

fn wire_messages<M: WireMessage>(path: &Path, key: &str) -> Vec<M> {
    let buf = std::fs::read(path).unwrap();
    let mut out = Vec::new();
    scan(&buf, |item| -> Result<(), ()> {
        if let Item::Message { channel, data, .. } = item {
            if channel.is_wire() && channel.topic == key {
                out.push(shoal_proto::decode::<M>(data).unwrap());
            }
        }
        Ok(())
    })
    .unwrap();
    out
}

fn wire_bytes(path: &Path, key: &str) -> Vec<Vec<u8>> {
    let buf = std::fs::read(path).unwrap();
    let mut out = Vec::new();
    scan(&buf, |item| -> Result<(), ()> {
        if let Item::Message { channel, data, .. } = item {
            if channel.is_wire() && channel.topic == key {
                out.push(data.to_vec());
            }
        }
        Ok(())
    })
    .unwrap();
    out
}

#[test]
fn live_recording_keeps_every_kind_byte_for_byte_without_drops() {
    let r = recording();
    let s = &r.summary;
    assert_eq!(s.dropped, 0, "{s:?}");
    assert_eq!(s.undecodable, 0);
    assert_eq!(s.images_dropped, 0);
    let keys = fleet().keys();
    let count = |k: &str| s.channels.get(k).map_or(0, |c| c.messages);
    let obs: u64 = [10, 15, 17]
        .iter()
        .map(|&v| count(&keys.observations(v)))
        .sum();
    assert_eq!(
        obs,
        r.published[&MessageKind::Observation],
        "observations recorded vs published"
    );
    assert_eq!(count(&keys.truth()), r.published[&MessageKind::SimTruth]);
    assert_eq!(
        count(&keys.command(15)),
        r.published[&MessageKind::VehicleCommand]
    );
    // Frames at 5 Hz, kept at most 2 Hz per camera; the rest are counted as rate-limited.
    let frames = count(&keys.frame(10, 4));
    assert!(
        frames > 0 && frames + s.frames_rate_limited == r.published[&MessageKind::CameraFrame],
        "{frames} + {}",
        s.frames_rate_limited
    );
    assert!(
        count(&keys.map()) >= 10,
        "maps recorded: {}",
        count(&keys.map())
    );
    for topic in [
        "/fused/tf",
        "/fused/poses",
        "/fused/scene",
        "/fused/log",
        "/truth/tf",
        "/v10/status",
        "/v10/cam/starboard/image",
        "/liveliness",
    ] {
        assert!(
            count(topic) > 0,
            "no messages on {topic}: {:?}",
            s.channels.keys().collect::<Vec<_>>()
        );
    }
    // Node 99 appeared, then went away.
    assert!(
        count("/liveliness") >= 2,
        "{:?}",
        s.channels.get("/liveliness")
    );
    // Bytes on the raw channels are the envelopes as published.
    let truths: Vec<SimTruth> = wire_messages(&r.path, &keys.truth());
    assert_eq!(truths.len() as u64, r.published[&MessageKind::SimTruth]);
    assert!(truths.windows(2).all(|w| w[0].tick < w[1].tick));
}

fn python_has_mcap() -> bool {
    let ok = |c: &mut Command| c.output().map(|o| o.status.success()).unwrap_or(false);
    let import = ["-c", "import mcap, mcap_protobuf"];
    if ok(Command::new("python3").args(import)) {
        return true;
    }
    eprintln!("installing the Python mcap readers: python3 -m pip install --quiet mcap mcap-protobuf-support");
    ok(Command::new("python3").args([
        "-m",
        "pip",
        "install",
        "--quiet",
        "mcap",
        "mcap-protobuf-support",
    ])) && ok(Command::new("python3").args(import))
}

#[test]
fn python_mcap_readers_decode_every_foxglove_channel() {
    let r = recording();
    if !python_has_mcap() {
        eprintln!(
            "SKIPPED: pip could not install the Python `mcap` and `mcap-protobuf-support` packages"
        );
        return;
    }
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/check_mcap.py");
    let out = Command::new("python3")
        .arg(&script)
        .arg(&r.path)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "check_mcap.py failed:\n{stderr}");
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let fleet = fleet();
    let keys = fleet.keys();
    let total: u64 = r.summary.channels.values().map(|c| c.messages).sum();
    assert_eq!(
        report["messages"].as_u64().unwrap(),
        total,
        "python saw a different message count"
    );
    for schema in [
        "foxglove.FrameTransforms",
        "foxglove.PosesInFrame",
        "foxglove.Log",
        "foxglove.SceneUpdate",
        "foxglove.CompressedImage",
        "foxglove.ImageAnnotations",
    ] {
        assert!(
            report["decoded_per_schema"][schema].as_u64().unwrap_or(0) > 0,
            "no {schema} decoded: {report}"
        );
    }
    // Every Foxglove message was decoded: with the wire channels, they are all messages.
    let foxglove: u64 = r
        .summary
        .channels
        .iter()
        .filter(|(topic, _)| topic.starts_with('/'))
        .map(|(_, c)| c.messages)
        .sum();
    let decoded: u64 = report["decoded_per_schema"]
        .as_object()
        .unwrap()
        .values()
        .map(|n| n.as_u64().unwrap())
        .sum();
    assert_eq!(decoded, foxglove, "{report}");
    // The fused poses Python decoded are the wire maps' localized vehicles.
    let maps: Vec<FleetMap> = wire_messages(&r.path, &keys.map());
    let samples = report["poses"]["/fused/poses"].as_array().unwrap();
    assert!(!samples.is_empty());
    for s in samples {
        let stamp = s["stamp_ns"].as_u64().unwrap();
        let got: Vec<[f64; 3]> = s["positions"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| [0, 1, 2].map(|i| p[i].as_f64().unwrap()))
            .collect();
        let matches = |m: &FleetMap| {
            let want: Vec<[f64; 3]> = m
                .vehicles
                .iter()
                .filter(|v| v.vehicle == m.reference || v.state != VehicleState::Unobserved)
                .map(|v| {
                    let t = v.reference_from_vehicle.translation.vector;
                    [t.x, t.y, t.z]
                })
                .collect();
            m.stamp_ns == stamp && want == got
        };
        assert!(
            maps.iter().any(matches),
            "no wire map at {stamp} ns with positions {got:?}"
        );
        assert_eq!(s["frame_id"], "v10");
    }
    assert_eq!(
        report["png_images"].as_u64(),
        r.summary
            .channels
            .get("/v10/cam/starboard/image")
            .map(|c| c.messages)
    );
    assert_eq!(
        report["wire_channels"][keys.map()]["schema"],
        "shoal.FleetMap"
    );
    assert_eq!(
        report["wire_channels"][keys.map()]["schema_version"],
        shoal_proto::codec::SCHEMA_VERSION.to_string()
    );
    assert_eq!(report["metadata"]["shoal"]["fleet"], "paper");
    assert_eq!(
        report["metadata"]["shoal"]["log_format"],
        shoal_record::writer::LOG_FORMAT.to_string()
    );
    assert_eq!(report["metadata"]["shoal"]["water_c_per_m"], "0.5");
    assert!(report["attachments"]
        .as_array()
        .unwrap()
        .iter()
        .any(|a| a == "fleet.toml"));
}

#[test]
fn offline_refusion_is_bit_identical_twice_and_matches_the_live_maps() {
    let r = recording();
    let (a, b) = (tmp("refused_a.mcap"), tmp("refused_b.mcap"));
    let sa = shoal_record::refuse(&r.path, &a, &FuseOptions::default()).unwrap();
    let sb = shoal_record::refuse(&r.path, &b, &FuseOptions::default()).unwrap();
    assert_eq!(
        std::fs::read(&a).unwrap(),
        std::fs::read(&b).unwrap(),
        "two re-fusions differ"
    );
    assert_eq!(
        sa,
        shoal_record::FuseSummary {
            output: a.clone(),
            ..sb
        }
    );
    assert_eq!(sa.maps_written, sa.original_maps);
    assert!(sa.comparison.estimates_compared > 0);
    eprintln!("offline vs live: {:?}", sa.comparison);
    // The live service ingested each observation at a slightly different `now`
    // (wall-clock batching), so its windows can differ by an observation at
    // the edge; the solutions agree to well under the method's error.
    assert!(
        sa.comparison.mean_position_diff_m < 0.005,
        "{:?}",
        sa.comparison
    );
    // At a fixed rate of the log's clock, also deterministic.
    let opts = FuseOptions {
        solve_at: SolveAt::RateHz(5.0),
        ..FuseOptions::default()
    };
    let (c, d) = (tmp("refused_c.mcap"), tmp("refused_d.mcap"));
    let sc = shoal_record::refuse(&r.path, &c, &opts).unwrap();
    shoal_record::refuse(&r.path, &d, &opts).unwrap();
    assert_eq!(std::fs::read(&c).unwrap(), std::fs::read(&d).unwrap());
    assert!(
        (sc.maps_written as f64 - TRIAL_S * 5.0).abs() <= 2.0,
        "{} maps at 5 Hz",
        sc.maps_written
    );
}

#[test]
fn replay_into_a_fresh_fusion_reproduces_the_live_map() {
    let r = recording();
    let fleet = fleet();
    let keys = fleet.keys();
    let live_maps: Vec<FleetMap> = wire_messages(&r.path, &keys.map());
    let live_last = live_maps.last().unwrap().clone();

    let port = free_port().unwrap();
    let _router = Bus::open(&Connect::Router { port }).unwrap();
    let clock = Arc::new(ManualClock::new(0));
    let fusion_bus = Bus::open(&client_of(port)).unwrap();
    // The fresh fusion follows the replayed simulator clock, like `shoal fusion --clock sim`.
    let truth_sub: Subscription<SimTruth> = fusion_bus.subscribe(&keys.truth(), 64).unwrap();
    let maps_sub: Subscription<FleetMap> = fusion_bus.subscribe(&keys.map(), 1024).unwrap();
    let fusion = shoal_services::fusion::spawn(
        &fusion_bus,
        FusionConfig {
            fleet: fleet.clone(),
            params: FusionParams::default(),
            placement: Placement::Central,
            rate_hz: 20.0,
            queue_capacity: 4096,
            link: false,
        },
        clock.clone(),
    )
    .unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let (c, st) = (clock.clone(), stop.clone());
    let follower = std::thread::spawn(move || {
        while !st.load(std::sync::atomic::Ordering::Relaxed) {
            if let Some(t) = truth_sub.recv_timeout(Duration::from_millis(20)) {
                c.advance_to(t.msg.stamp_ns);
            }
        }
    });
    // A second recorder on the fresh router: replay must republish the recorded bytes unchanged.
    let rerecorded = tmp("rerecorded.mcap");
    let rerecorder = Recorder::spawn(
        &Bus::open(&client_of(port)).unwrap(),
        fleet.clone(),
        &rerecorded,
        RecordOptions::default(),
    )
    .unwrap();
    let replay_bus = Bus::open(&client_of(port)).unwrap();
    std::thread::sleep(Duration::from_millis(600));
    let opts = ReplayOptions {
        rate: 2.0,
        kinds: Some(vec![MessageKind::Observation, MessageKind::SimTruth]),
        ..ReplayOptions::default()
    };
    let s = shoal_services::replay::replay(&replay_bus, &r.path, &opts, &AtomicBool::new(false))
        .unwrap();
    assert_eq!(
        s.messages,
        r.published[&MessageKind::Observation] + r.published[&MessageKind::SimTruth]
    );
    // Original timing at 2x: the log's span took about half as long.
    assert!(
        s.wall_time_s > 0.4 * s.log_span_s && s.wall_time_s < 0.5 * s.log_span_s + 1.0,
        "{s:?}"
    );
    std::thread::sleep(Duration::from_millis(500));
    fusion.stop();
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    follower.join().unwrap();
    rerecorder.stop().unwrap();
    for key in [keys.truth(), keys.observations(10), keys.observations(17)] {
        let (a, b) = (wire_bytes(&r.path, &key), wire_bytes(&rerecorded, &key));
        assert_eq!(a.len(), b.len(), "{key}: messages replayed and re-recorded");
        assert!(
            a == b,
            "{key}: replayed bytes differ from the recorded ones"
        );
    }
    let replayed: Vec<FleetMap> = maps_sub.drain().into_iter().map(|m| m.msg).collect();
    let last = replayed
        .iter()
        .max_by_key(|m| m.stamp_ns)
        .expect("the fresh fusion published maps");
    assert_eq!(last.stamp_ns, clock.now_ns());
    // Both final maps were solved on the last 2 s window of the same observations.
    assert_eq!(
        last.stamp_ns, live_last.stamp_ns,
        "both fusions end on the last tick"
    );
    let d = compare_maps(last, &live_last).unwrap();
    assert_eq!(d.len(), 2, "both followers live in both maps: {d:?}");
    for (v, (pos, ang)) in &d {
        eprintln!(
            "vehicle {v}: replayed vs live final map differ by {:.3} mm, {:.4} deg",
            pos * 1e3,
            ang
        );
        assert!(
            *pos < 0.002 && *ang < 0.1,
            "vehicle {v}: {pos} m, {ang} deg"
        );
    }
}
