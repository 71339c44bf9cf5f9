//! Hostile and broken input over Zenoh (issue #10): running services are fed
//! truncated, oversized, wrong-version and wrong-kind envelopes, NaN and
//! infinite poses, absurd covariances, observer mismatches, and frames of the
//! wrong size or format. Each is counted where the service reports it, and
//! the services keep working: fusion still fuses the next valid observations
//! into a map, the node still processes the next valid frame.
//!
//! Where each rejection is counted:
//! - undecodable or invalid envelopes: by the receiving `shoal_bus`
//!   subscription (`SubscriptionStats::rejected`, with the reason in
//!   `last_error`); a node reports them in `NodeStatus.messages_rejected` and
//!   its camera's `frames_invalid`;
//! - well-formed observations fusion refuses: `FusionStats::rejected_at_ingest`
//!   per `RejectReason`, and an `EdgeReport` in the next map;
//! - well-formed frames a node cannot use (size, format, camera): the
//!   camera's `frames_invalid` in `NodeStatus`.

use shoal_bus::{client_of, free_port, Bus, Connect, Publisher, Subscription};
use shoal_fusion::FusionParams;
use shoal_node::pipeline::PipelineParams;
use shoal_proto::clock::ManualClock;
use shoal_proto::codec::{encode, HEADER_LEN, MAX_PAYLOAD, SCHEMA_VERSION};
use shoal_proto::config::Fleet;
use shoal_proto::messages::*;
use shoal_proto::Cov6;
use shoal_services::fusion::{FusionConfig, FusionHandle, Placement};
use shoal_services::node::{NodeConfig, Source};
use shoal_sim_bridge::obs_synth::{line_abreast, ObsSynth, ObsSynthParams};
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

#[path = "common/wait.rs"]
mod wait;
use wait::wait_for;

fn fleet() -> Arc<Fleet> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    Arc::new(Fleet::load(&root.join("configs/fleets/paper.toml")).expect("paper fleet"))
}

/// Envelope bytes with the header rewritten.
fn with_header(bytes: &[u8], version: u16, kind: u16, declared: u32) -> Vec<u8> {
    let mut b = bytes.to_vec();
    b[4..6].copy_from_slice(&version.to_le_bytes());
    b[6..8].copy_from_slice(&kind.to_le_bytes());
    b[8..12].copy_from_slice(&declared.to_le_bytes());
    b
}

/// Damaged observation envelopes, each with the text its rejection must carry.
fn broken_observation_envelopes(valid: &Observation) -> Vec<(&'static str, Vec<u8>, &'static str)> {
    let good = encode(valid).unwrap();
    let n = (good.len() - HEADER_LEN) as u32;
    let mut out: Vec<(&'static str, Vec<u8>, &'static str)> = vec![
        ("truncated header", good[..7].to_vec(), "too short"),
        (
            "truncated payload",
            good[..good.len() - 40].to_vec(),
            "header says",
        ),
        (
            "payload cut, length fixed",
            {
                let cut = &good[..good.len() - 40];
                with_header(cut, SCHEMA_VERSION, 1, n - 40)
            },
            "malformed",
        ),
        (
            "bad magic",
            {
                let mut b = good.clone();
                b[0..4].copy_from_slice(b"JUNK");
                b
            },
            "bad magic",
        ),
        (
            "wrong version",
            with_header(&good, SCHEMA_VERSION + 1, 1, n),
            "from peer, this build speaks",
        ),
        (
            "unknown kind",
            with_header(&good, SCHEMA_VERSION, 77, n),
            "unknown message kind 77",
        ),
        (
            "oversized length",
            with_header(&good, SCHEMA_VERSION, 1, (MAX_PAYLOAD + 1) as u32),
            "exceeds",
        ),
        (
            "trailing bytes",
            {
                let mut b = good.clone();
                b.extend_from_slice(&[0; 16]);
                with_header(&b, SCHEMA_VERSION, 1, n + 16)
            },
            "trailing",
        ),
        (
            "wrong kind on the key",
            encode(&VehicleCommand {
                vehicle: valid.observer,
                stamp_ns: valid.stamp_ns,
                velocity_body: [0.0; 3],
                yaw_rate: 0.0,
            })
            .unwrap(),
            "expected a Observation",
        ),
    ];
    let mut pose_nan = valid.clone();
    pose_nan.observer_from_target.translation.vector.x = f64::NAN;
    out.push((
        "NaN pose",
        encode(&pose_nan).unwrap(),
        "observer_from_target",
    ));
    let mut pose_inf = valid.clone();
    pose_inf.observer_from_target.translation.vector.z = f64::INFINITY;
    out.push((
        "infinite pose",
        encode(&pose_inf).unwrap(),
        "observer_from_target",
    ));
    let mut quat = valid.clone();
    quat.observer_from_target
        .rotation
        .as_mut_unchecked()
        .coords
        .w = 7.0;
    out.push((
        "non-unit rotation",
        encode(&quat).unwrap(),
        "observer_from_target",
    ));
    let mut cov_nan = valid.clone();
    cov_nan.covariance[(2, 2)] = f64::NAN;
    out.push(("NaN covariance", encode(&cov_nan).unwrap(), "covariance"));
    let mut cov_neg = valid.clone();
    cov_neg.covariance[(4, 4)] = -1e-3;
    out.push(("negative variance", encode(&cov_neg).unwrap(), "covariance"));
    let mut cov_huge = valid.clone();
    cov_huge.covariance = Cov6::identity() * 1e12;
    out.push((
        "absurd covariance (σ = 1000 km)",
        encode(&cov_huge).unwrap(),
        "covariance",
    ));
    let mut cov_asym = valid.clone();
    cov_asym.covariance[(0, 5)] = 0.5;
    out.push((
        "asymmetric covariance",
        encode(&cov_asym).unwrap(),
        "covariance",
    ));
    let mut rms = valid.clone();
    rms.reprojection_rms_px = f64::NEG_INFINITY;
    out.push((
        "infinite reprojection error",
        encode(&rms).unwrap(),
        "reprojection_rms_px",
    ));
    out
}

struct FusionRig {
    _router: Bus,
    fusion: FusionHandle,
    clock: Arc<ManualClock>,
    bus: Bus,
    fleet: Arc<Fleet>,
}

impl FusionRig {
    fn start() -> FusionRig {
        let fleet = fleet();
        let port = free_port().unwrap();
        let router = Bus::open(&Connect::Router { port }).unwrap();
        let clock = Arc::new(ManualClock::new(0));
        let fusion = shoal_services::fusion::spawn(
            &Bus::open(&client_of(port)).unwrap(),
            FusionConfig {
                fleet: fleet.clone(),
                params: FusionParams {
                    record_solve_time: false,
                    ..FusionParams::default()
                },
                placement: Placement::Central,
                rate_hz: 20.0,
                queue_capacity: 10_000,
                link: false,
            },
            clock.clone(),
        )
        .unwrap();
        let bus = Bus::open(&client_of(port)).unwrap();
        FusionRig {
            _router: router,
            fusion,
            clock,
            bus,
            fleet,
        }
    }
}

#[test]
#[allow(
    clippy::too_many_lines,
    reason = "one sequence of hostile messages against one running fusion service, each rejection counted against the counts the previous step left"
)]
fn fusion_counts_every_hostile_observation_and_keeps_fusing() {
    let rig = FusionRig::start();
    let keys = rig.fleet.keys();
    let ids: Vec<u32> = rig.fleet.vehicles.iter().map(|v| v.id).collect();
    let truth = line_abreast(&ids, 1.75);
    let pubs: Vec<(u32, Publisher<Observation>)> = ids
        .iter()
        .map(|&v| (v, rig.bus.publisher(keys.observations(v)).unwrap()))
        .collect();
    let publisher_of = |v: u32| &pubs.iter().find(|(id, _)| *id == v).unwrap().1;
    // A witness subscription beside fusion's: it decodes exactly as fusion's
    // own subscription does and exposes the count and newest reason.
    let witness: Subscription<Observation> =
        rig.bus.subscribe(&keys.all_observations(), 10_000).unwrap();
    std::thread::sleep(Duration::from_millis(1000));

    let mut synth = ObsSynth::new(&rig.fleet, ObsSynthParams::default(), 7);
    let mut stamp = 0u64;
    let mut publish_valid = |ticks: u64, stamp: &mut u64| -> (u64, Option<Observation>) {
        let (mut n, mut sample) = (0, None);
        for _ in 0..ticks {
            *stamp += 100_000_000;
            rig.clock.advance_to(*stamp);
            for o in synth.observe(&truth, *stamp) {
                publisher_of(o.obs.observer).put(&o.obs).unwrap();
                n += 1;
                if o.obs.observer == 10 {
                    sample = Some(o.obs.clone());
                }
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        (n, sample)
    };

    // A healthy start: every vehicle localized.
    let (sent, sample) = publish_valid(6, &mut stamp);
    let sample = sample.expect("vehicle 10 saw someone");
    assert!(sent > 0);
    wait_for(
        "a first map with every vehicle live",
        Duration::from_secs(10),
        || {
            rig.fusion.latest().filter(|m| {
                m.vehicles.len() == ids.len()
                    && m.vehicles.iter().all(|v| v.state == VehicleState::Live)
            })
        },
    );
    // Both subscriptions heard the same healthy traffic (fusion's statistics
    // are refreshed after each solve): that is the baseline.
    let before = wait_for(
        "fusion and the witness to agree on the healthy traffic",
        Duration::from_secs(5),
        || {
            let s = rig.fusion.stats();
            (s.received > 0 && s.received == witness.stats().received()).then_some(s)
        },
    );
    assert!(before.received <= sent);

    // Envelope-level garbage on vehicle 10's key: refused before fusion sees it.
    let raw = publisher_of(10);
    let broken = broken_observation_envelopes(&sample);
    for (i, (what, bytes, reason)) in broken.iter().enumerate() {
        raw.put_bytes(bytes.clone()).unwrap();
        let want = i as u64 + 1;
        wait_for(
            &format!("the rejection of {what}"),
            Duration::from_secs(5),
            || (witness.stats().rejected() == want).then_some(()),
        );
        let last = witness.stats().last_error().unwrap_or_default();
        assert!(
            last.to_lowercase().contains(&reason.to_lowercase()),
            "{what}: rejection reason {last:?} does not mention {reason:?}"
        );
    }

    // Well-formed observations fusion must refuse, each for its reason.
    let now = stamp;
    let fresh = |seq: u64| {
        let mut o = sample.clone();
        o.stamp_ns = now;
        o.frame_seq = 1_000_000 + seq;
        o
    };
    let mut mismatch = fresh(1);
    mismatch.observer = 15; // claims to be 15, arrives on 10's key
    let mut wide = fresh(2);
    wide.covariance = Cov6::identity() * 1e3; // σ = 31.6 m: valid on the wire, useless to fuse
    let mut unknown = fresh(3);
    unknown.target_marker = 99;
    unknown.target_vehicle = None;
    let mut future = fresh(4);
    future.stamp_ns = now + 10_000_000_000;
    let mut own_marker = fresh(5);
    own_marker.target_marker = 10;
    own_marker.target_vehicle = Some(10);
    let refused = [
        (mismatch, RejectReason::ObserverMismatch),
        (wide, RejectReason::Invalid),
        (unknown, RejectReason::UnknownMarker),
        (future, RejectReason::ClockSkew),
        (own_marker, RejectReason::SelfObservation),
    ];
    for (obs, _) in &refused {
        raw.put(obs).unwrap();
    }
    let after_refused = wait_for(
        "fusion's verdicts on the refused observations",
        Duration::from_secs(5),
        || {
            let s = rig.fusion.stats();
            (s.received == before.received + refused.len() as u64).then_some(s)
        },
    );
    for (_, reason) in &refused {
        assert_eq!(
            after_refused.rejected_at_ingest.get(reason),
            before.rejected_at_ingest.get(reason) + 1,
            "{reason:?} not counted once"
        );
    }
    assert_eq!(
        after_refused.ingested, before.ingested,
        "a refused observation was ingested"
    );
    let reported = wait_for(
        "a map reporting the observer mismatch",
        Duration::from_secs(5),
        || {
            rig.fusion.latest().filter(|m| {
                m.edges
                    .iter()
                    .any(|e| e.rejected == Some(RejectReason::ObserverMismatch) && e.observer == 15)
            })
        },
    );
    assert!(reported
        .edges
        .iter()
        .any(|e| e.rejected == Some(RejectReason::Invalid)));

    // And it keeps fusing: fresh valid observations make a newer live map.
    let seq_before = rig.fusion.latest().map_or(0, |m| m.seq);
    let (sent_after, _) = publish_valid(5, &mut stamp);
    let last_stamp = stamp;
    let map = wait_for(
        "a live map after the garbage",
        Duration::from_secs(10),
        || {
            rig.fusion.latest().filter(|m| {
                m.seq > seq_before
                    && m.vehicles
                        .iter()
                        .all(|v| v.state == VehicleState::Live && v.last_seen_ns == last_stamp)
            })
        },
    );
    assert_eq!(map.vehicles.len(), ids.len());
    let after = rig.fusion.stats();
    assert_eq!(
        after.received,
        before.received + refused.len() as u64 + sent_after,
        "only decodable observations reach fusion"
    );
    assert_eq!(after.ingested, before.ingested + sent_after);
    assert_eq!(witness.stats().rejected(), broken.len() as u64);
    assert_eq!(
        rig.fusion.observations_rejected(),
        broken.len() as u64,
        "fusion's own subscription counted every broken envelope"
    );
    println!(
        "fusion: {} broken envelopes refused by the bus, {} well-formed observations refused by fusion, {} valid observations fused after them",
        broken.len(),
        refused.len(),
        sent_after
    );
}

fn frame(
    vehicle: u32,
    camera: u8,
    seq: u64,
    width: u32,
    height: u32,
    format: PixelFormat,
) -> CameraFrame {
    let fleet = fleet();
    let cam = &fleet.vehicle(vehicle).unwrap().cameras[camera as usize];
    let mut model = cam.model;
    model.width = width;
    model.height = height;
    CameraFrame {
        vehicle,
        camera,
        seq,
        stamp_ns: seq * 100_000_000,
        info: CameraInfo {
            model,
            body_from_camera: cam.body_from_camera,
        },
        format,
        data: vec![128; width as usize * height as usize * format.channels()],
    }
}

#[test]
fn node_counts_every_hostile_frame_and_keeps_processing() {
    let fleet = fleet();
    let keys = fleet.keys();
    let port = free_port().unwrap();
    let _router = Bus::open(&Connect::Router { port }).unwrap();
    let node = shoal_services::node::spawn(
        &Bus::open(&client_of(port)).unwrap(),
        NodeConfig {
            fleet: fleet.clone(),
            vehicle: 10,
            params: PipelineParams::default(),
            source: Source::Zenoh,
            queue_capacity: 32,
            status_period: Duration::from_millis(200),
        },
    )
    .unwrap();
    let bus = Bus::open(&client_of(port)).unwrap();
    let status: Subscription<NodeStatus> = bus.subscribe(&keys.status(10), 64).unwrap();
    let frames: Publisher<CameraFrame> = bus.publisher(keys.frame(10, 0)).unwrap();
    std::thread::sleep(Duration::from_millis(500));

    let cam = fleet.vehicle(10).unwrap().cameras[0].model;
    let (w, h) = (cam.width, cam.height);
    let good = encode(&frame(10, 0, 1, w, h, PixelFormat::Mono8)).unwrap();
    // Probe until the node's subscription is in place, then let it go idle:
    // the counts below are deltas from there.
    wait_for(
        "the node to receive a probe frame",
        Duration::from_secs(20),
        || {
            frames.put_bytes(good.clone()).unwrap();
            std::thread::sleep(Duration::from_millis(300));
            (node.stats().frames_in() > 0).then_some(())
        },
    );
    std::thread::sleep(Duration::from_millis(500)); // any probe still in flight lands
    let base = wait_for(
        "the node to finish the probe frames",
        Duration::from_secs(30),
        || {
            let st = node.stats();
            (st.frames_processed() == st.frames_in()).then(|| st.frames_in())
        },
    );
    let idle = wait_for("a status after the probes", Duration::from_secs(5), || {
        status
            .drain()
            .into_iter()
            .map(|r| r.msg)
            .find(|s| s.cameras[0].frames_in == base)
    });
    assert_eq!(idle.cameras[0].frames_invalid, 0);
    assert_eq!(idle.messages_rejected, 0);
    let n = (good.len() - HEADER_LEN) as u32;
    // Refused by decoding (counted in messages_rejected and frames_invalid).
    let mut short_data = frame(10, 0, 2, w, h, PixelFormat::Mono8);
    short_data.data.truncate(1000);
    let mut zero_size = frame(10, 0, 3, 8, 8, PixelFormat::Mono8);
    zero_size.info.model.width = 0;
    zero_size.data.clear();
    let mut nan_mount = frame(10, 0, 4, 8, 8, PixelFormat::Mono8);
    nan_mount.info.body_from_camera.translation.vector.y = f64::NAN;
    let undecodable: Vec<Vec<u8>> = vec![
        good[..100].to_vec(),
        with_header(&good, SCHEMA_VERSION + 1, 3, n),
        with_header(&good[..HEADER_LEN + 10], SCHEMA_VERSION, 3, u32::MAX),
        encode(&short_data).unwrap(),
        encode(&zero_size).unwrap(),
        encode(&nan_mount).unwrap(),
    ];
    // Well-formed but unusable for this camera (counted in frames_invalid).
    let unusable = [
        frame(10, 0, 5, 640, 480, PixelFormat::Mono8),
        frame(10, 0, 6, w, h, PixelFormat::Rgb8),
        frame(10, 3, 7, w, h, PixelFormat::Mono8),
    ];
    for b in &undecodable {
        frames.put_bytes(b.clone()).unwrap();
    }
    for f in &unusable {
        frames.put(f).unwrap();
        std::thread::sleep(Duration::from_millis(50));
    }
    // Then one good frame: the camera thread must still process it.
    frames.put_bytes(good).unwrap();

    // A probe still queued when `base` was read (a loaded machine: the
    // node took one probe off its queue, finished it, and the next was not
    // yet taken) arrives late and counts as one more good frame: the bad
    // frames' counts are exact, the good ones at least what was sent.
    let expected_invalid = (undecodable.len() + unusable.len()) as u64;
    let report = wait_for(
        "a node status counting every bad frame and the good one",
        Duration::from_secs(60),
        || {
            status.drain().into_iter().map(|r| r.msg).find(|s| {
                s.cameras[0].frames_invalid == expected_invalid
                    && s.messages_rejected == undecodable.len() as u64
                    && s.cameras[0].frames_in > base + unusable.len() as u64
            })
        },
    );
    // Every frame taken off the queue was processed or refused as unusable.
    let processed = wait_for(
        "the good frame to be processed",
        Duration::from_secs(30),
        || {
            let st = node.stats();
            let n = st.frames_processed();
            (n + unusable.len() as u64 == st.frames_in()).then_some(n)
        },
    );
    assert!(
        processed > base,
        "the good frame after the garbage was processed ({processed} frames, {base} before the garbage)"
    );
    assert_eq!(node.stats().frames_invalid(), expected_invalid);
    assert!(report.cameras[1..]
        .iter()
        .all(|c| c.frames_invalid == 0 && c.frames_in == 0));
    println!(
        "node: {} undecodable frame envelopes and {} unusable frames counted, then 1 good frame processed",
        undecodable.len(),
        unusable.len()
    );
    node.stop();
}
