//! `shoal node --source mcap:FILE` (`shoal::redetect`): a node run again on
//! a recorded trial's frames publishes observations for exactly those
//! frames, stamped with the original capture times, and drops none.

use shoal::demo::DemoConfig;
use shoal_bus::{client_of, free_port, Bus, Connect};
use shoal_node::pipeline::PipelineParams;
use shoal_proto::config::Fleet;
use shoal_proto::decode;
use shoal_proto::messages::{CameraFrame, Observation};
use shoal_services::node::{NodeConfig, Source};
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

#[test]
fn redetection_on_recorded_frames_publishes_observations_at_their_original_stamps() {
    let log = std::env::temp_dir().join(format!("shoal-redetect-{}.mcap", std::process::id()));
    let cfg = DemoConfig {
        duration_s: 4.0,
        frame_rate_hz: 1.0,
        cameras: Some(vec!["port".into(), "starboard".into()]),
        time_scale: 0.5,
        progress: false,
        log: Some(log.clone()),
        log_frames: true,
        ..DemoConfig::default()
    };
    let live = shoal::demo::run(&cfg, |_, _, _| {}).unwrap();
    assert!(live.observations_sent > 0, "{live:?}");

    // The frames of vehicle 15 in the log, and their stamps.
    let buf = std::fs::read(&log).unwrap();
    let mut stamps = Vec::new();
    shoal_record::reader::scan_wire(&buf, |channel, _, data| -> Result<(), String> {
        if channel.topic.starts_with("shoal/paper/15/cam/") {
            if let Ok(f) = decode::<CameraFrame>(data) {
                stamps.push(f.stamp_ns);
            }
        }
        Ok(())
    })
    .unwrap();
    assert!(!stamps.is_empty(), "the log holds vehicle 15's frames");

    let fleet =
        Arc::new(Fleet::load(Path::new("configs/fleets/paper.toml")).expect("paper fleet loads"));
    let port = free_port().unwrap();
    let router = Bus::open(&Connect::Router { port }).unwrap();
    let listener = Bus::open(&client_of(port)).unwrap();
    let obs = listener
        .subscribe::<Observation>(&fleet.keys().observations(15), 1024)
        .unwrap();
    let bus = Bus::open(&client_of(port)).unwrap();
    let node = NodeConfig {
        fleet: fleet.clone(),
        vehicle: 15,
        params: PipelineParams::default(),
        source: Source::Zenoh,
        queue_capacity: 2,
        status_period: Duration::from_secs(1),
    };
    let s = shoal::redetect::redetect(&bus, node, &log, 4.0, &AtomicBool::new(false)).unwrap();
    assert_eq!(s.frames_replayed, stamps.len() as u64, "{s:?}");
    assert_eq!(s.frames_processed, s.frames_replayed, "{s:?}");
    assert_eq!(s.frames_dropped, 0, "{s:?}");
    assert!(s.observations_sent > 0, "{s:?}");
    let mut heard = Vec::new();
    while let Some(r) = obs.recv_timeout(Duration::from_millis(500)) {
        heard.push(r.msg);
    }
    assert_eq!(heard.len() as u64, s.observations_sent);
    assert!(
        heard.iter().all(|o| stamps.contains(&o.stamp_ns)),
        "every observation carries a recorded frame's capture time"
    );
    // A vehicle with no frames in the log is an error, not a silent no-op.
    let other = NodeConfig {
        fleet,
        vehicle: 99,
        params: PipelineParams::default(),
        source: Source::Zenoh,
        queue_capacity: 2,
        status_period: Duration::from_secs(1),
    };
    assert!(shoal::redetect::redetect(&bus, other, &log, 4.0, &AtomicBool::new(false)).is_err());
    drop(router);
    std::fs::remove_file(&log).ok();
}
