//! A node whose camera is a GStreamer pipeline (`shoal node --source
//! gst:PIPELINE`), end to end over Zenoh: a `videotestsrc` at camera 0's
//! size, faster than the node's pipeline keeps up with, and ending every few
//! frames. The node's status on its key must say the stamps are the
//! pipeline's, count the frames its queue dropped, count the reopenings of
//! the stream, carry the kernel's clock state, and be stamped with a capture
//! time on this machine's wall clock.
//!
//! The GStreamer elements come from Debian's gstreamer1.0-plugins-base
//! (`./run test` installs it); a missing one fails the test, naming it.

use shoal_bus::{client_of, free_port, Bus, Connect, Subscription};
use shoal_node::pipeline::PipelineParams;
use shoal_node::source::LocalSource;
use shoal_proto::messages::{NodeStatus, StampSource};
use shoal_services::node::{NodeConfig, Source};
use std::sync::Arc;
use std::time::{Duration, Instant};

fn require_gst_elements(elements: &[&str]) {
    for e in elements {
        let ok = std::process::Command::new("gst-inspect-1.0")
            .args(["--exists", e])
            .status()
            .unwrap_or_else(|err| {
                panic!("gst-inspect-1.0 cannot run ({err}): install gstreamer1.0-tools (./run test does)")
            })
            .success();
        assert!(
            ok,
            "GStreamer element {e} missing: install gstreamer1.0-plugins-base (./run test does)"
        );
    }
}

#[test]
fn a_node_on_a_gstreamer_pipeline_reports_stamps_drops_and_reconnects() {
    require_gst_elements(&["videotestsrc", "videoconvert", "appsink"]);
    let fleet = Arc::new(
        shoal_proto::config::Fleet::load(std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/configs/fleets/paper.toml"
        )))
        .unwrap(),
    );
    let model = fleet.vehicle(15).unwrap().cameras[0].model;
    // 120 frames a second of the camera's full size, 45 per stream
    // (0.375 s): a checkerboard of 4 px squares is ~48 000 contours at full
    // contrast, so restoring and searching it takes ~27 ms a frame (release,
    // idle 2-core machine; a debug build longer), well over the 8.3 ms
    // between frames, and the queue of 2 drops frames; each end of stream
    // is a reopening. (Noise, `snow`, no longer serves: the detector judges
    // it flat against itself and searches it in ~1 ms.)
    let pipeline = format!(
        "videotestsrc is-live=true num-buffers=45 pattern=checkers-4 \
         ! video/x-raw,format=GRAY8,width={},height={},framerate=120/1 ! appsink",
        model.width, model.height
    );
    let port = free_port().unwrap();
    let _router = Bus::open(&Connect::Router { port }).unwrap();
    let bus = Bus::open(&client_of(port)).unwrap();
    let status: Subscription<NodeStatus> = bus.subscribe(&fleet.keys().status(15), 64).unwrap();
    let started = shoal_node::clock::wall_now_ns();
    let node = shoal_services::node::spawn(
        &bus,
        NodeConfig {
            fleet: fleet.clone(),
            vehicle: 15,
            params: PipelineParams::default(),
            source: Source::Local(LocalSource::Gst {
                pipeline,
                camera: 0,
            }),
            queue_capacity: 2,
            status_period: Duration::from_millis(500),
        },
    )
    .unwrap();
    let mut last: Option<NodeStatus> = None;
    let deadline = Instant::now() + Duration::from_secs(90);
    let done = |s: &NodeStatus| {
        let c = &s.cameras[0];
        c.frames_in >= 3 && c.frames_dropped > 0 && c.reconnects >= 1
    };
    while Instant::now() < deadline && !last.as_ref().is_some_and(done) {
        if let Some(r) = status.recv_timeout(Duration::from_millis(200)) {
            last = Some(r.msg);
        }
    }
    node.stop();
    let s = last.expect("a status within 90 s");
    let c = &s.cameras[0];
    assert!(done(&s), "camera 0 after 90 s: {c:?}");
    assert_eq!(c.stamp_source, StampSource::Pipeline, "{c:?}");
    assert_eq!(c.frames_invalid, 0, "{c:?}");
    assert!(
        s.stamp_ns >= started && s.stamp_ns <= shoal_node::clock::wall_now_ns(),
        "status stamped {} (newest capture), not within the run from {started}",
        s.stamp_ns
    );
    assert!(
        s.clock.is_some(),
        "the kernel's clock state is read on Linux"
    );
    assert!(s.cameras[1..]
        .iter()
        .all(|c| c.frames_in == 0 && c.stamp_source == StampSource::Unknown));
}
