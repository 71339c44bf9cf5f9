//! Live sources through GStreamer, no hardware needed: `videotestsrc`
//! pipelines played as a camera (`shoal node --source gst:PIPELINE`).
//! Frames must arrive stamped with the pipeline's own buffer times on the
//! wall clock; a stream that ends is reopened and its frames resume; a
//! silent stream does not hold up a stop; bad pipelines and devices are
//! errors that name them.
//!
//! The GStreamer elements come from Debian's gstreamer1.0-plugins-base and
//! -good (`./run test` installs them); a missing one fails the test, naming
//! it.

use shoal_node::source::{join_within, spawn_reader, LocalSource};
use shoal_node::vehicle::SourceCounters;
use shoal_proto::messages::{CameraFrame, CameraInfo, StampSource};
use shoal_proto::queue::DropOldestQueue;
use shoal_proto::CameraModel;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Frame period of the test pipelines (`framerate=20/1`), ns.
const PERIOD_NS: u64 = 50_000_000;
/// How far the median spacing of pipeline stamps may be from one period.
const SPACING_TOLERANCE_NS: u64 = 5_000_000;

/// Fails, naming them, if GStreamer lacks any of `elements`.
fn require_gst_elements(elements: &[&str]) {
    let missing: Vec<&str> = elements
        .iter()
        .copied()
        .filter(|e| {
            !std::process::Command::new("gst-inspect-1.0")
                .args(["--exists", e])
                .status()
                .unwrap_or_else(|err| {
                    panic!("gst-inspect-1.0 cannot run ({err}): install gstreamer1.0-tools (./run test does)")
                })
                .success()
        })
        .collect();
    assert!(
        missing.is_empty(),
        "GStreamer elements missing: {missing:?}; install gstreamer1.0-plugins-base and \
         gstreamer1.0-plugins-good (./run test does)"
    );
}

fn info() -> CameraInfo {
    CameraInfo {
        model: CameraModel::vehicle_1440(),
        body_from_camera: shoal_proto::Pose::identity(),
    }
}

/// A small test picture at 20 frames per second, `extra` on the source.
fn test_pipeline(extra: &str) -> String {
    format!(
        "videotestsrc is-live=true {extra} ! video/x-raw,width=64,height=48,framerate=20/1 \
         ! videoconvert ! appsink"
    )
}

struct Running {
    queue: DropOldestQueue<CameraFrame>,
    counters: Arc<SourceCounters>,
    stop: Arc<AtomicBool>,
    thread: JoinHandle<()>,
}

fn start(pipeline: String) -> Running {
    let queue = DropOldestQueue::new(256);
    let counters = Arc::new(SourceCounters::default());
    let stop = Arc::new(AtomicBool::new(false));
    let thread = spawn_reader(
        LocalSource::Gst {
            pipeline,
            camera: 0,
        },
        10,
        info(),
        queue.clone(),
        counters.clone(),
        stop.clone(),
    )
    .expect("the pipeline opens");
    Running {
        queue,
        counters,
        stop,
        thread,
    }
}

impl Running {
    /// Frames taken from the queue until `done` or `timeout`.
    fn collect(
        &self,
        timeout: Duration,
        done: impl Fn(&[CameraFrame]) -> bool,
    ) -> Vec<CameraFrame> {
        let mut frames = Vec::new();
        let deadline = Instant::now() + timeout;
        while !done(&frames) && Instant::now() < deadline {
            if let Ok(f) = self.queue.pop_timeout(Duration::from_millis(50)) {
                frames.push(f);
            }
        }
        frames
    }

    fn stop(self) {
        self.stop.store(true, Ordering::Relaxed);
        assert!(
            join_within(self.thread, Duration::from_secs(5)),
            "the source thread ends on stop"
        );
    }
}

fn now_ns() -> u64 {
    shoal_node::clock::wall_now_ns()
}

#[test]
fn pipeline_frames_carry_the_pipeline_buffer_times_on_the_wall_clock() {
    require_gst_elements(&["videotestsrc", "videoconvert", "appsink"]);
    let started = now_ns();
    let src = start(test_pipeline(""));
    let frames = src.collect(Duration::from_secs(20), |f| f.len() >= 20);
    let ended = now_ns();
    assert!(frames.len() >= 20, "{} frames in 20 s", frames.len());
    assert_eq!(src.counters.stamp_source(), StampSource::Pipeline);
    for f in &frames {
        assert!(
            (started..=ended).contains(&f.stamp_ns),
            "frame {} stamped {} outside the run [{started}, {ended}]",
            f.seq,
            f.stamp_ns
        );
        assert_eq!((f.info.model.width, f.info.model.height), (64, 48));
    }
    // The stamps run on the pipeline's clock: successive frames one period
    // apart. OpenCV 4.6 gives the sink's position, not the pulled buffer's
    // time (`docs/time.md`), so a reader that lags on a loaded machine
    // shifts single stamps by up to its lag (and the anchor steps down while
    // it settles), but the typical spacing is the period.
    let mut spacings: Vec<u64> = frames
        .windows(2)
        .map(|pair| {
            assert_eq!(pair[1].seq, pair[0].seq + 1);
            pair[1].stamp_ns.saturating_sub(pair[0].stamp_ns)
        })
        .collect();
    spacings.sort_unstable();
    let median = spacings[spacings.len() / 2];
    assert!(
        median.abs_diff(PERIOD_NS) <= SPACING_TOLERANCE_NS,
        "the median spacing of the stamps is {median} ns, the pipeline's period {PERIOD_NS}: {spacings:?}"
    );
    assert_eq!(src.counters.reconnects.load(Ordering::Relaxed), 0);
    assert_eq!(src.counters.missed.load(Ordering::Relaxed), 0);
    src.stop();
}

#[test]
fn a_stream_that_ends_is_reopened_and_its_frames_resume() {
    require_gst_elements(&["videotestsrc", "videoconvert", "appsink"]);
    // Each opening gives 6 frames (0.3 s), then the end of the stream.
    let src = start(test_pipeline("num-buffers=6"));
    let frames = src.collect(Duration::from_secs(30), |f| f.len() >= 20);
    let reconnects = src.counters.reconnects.load(Ordering::Relaxed);
    assert!(frames.len() >= 20, "{} frames in 30 s", frames.len());
    assert!(
        reconnects >= 3,
        "{reconnects} reconnects for 20 frames of 6 per stream"
    );
    // Stamps and frame numbers keep increasing across the reopenings, and
    // the wait before each (0.5 s) is not counted as missed frames: it is
    // a new stream, not a gap in one.
    for pair in frames.windows(2) {
        assert!(
            pair[1].stamp_ns > pair[0].stamp_ns,
            "stamps go back at frame {}",
            pair[1].seq
        );
        assert!(pair[1].seq > pair[0].seq);
    }
    let gaps = frames
        .windows(2)
        .filter(|p| p[1].stamp_ns - p[0].stamp_ns >= 400_000_000)
        .count();
    assert!(gaps >= 3, "the reopenings show as {gaps} pauses of ≥ 0.4 s");
    assert_eq!(src.counters.missed.load(Ordering::Relaxed), 0);
    assert_eq!(src.counters.stamp_source(), StampSource::Pipeline);
    src.stop();
}

#[test]
fn a_silent_stream_does_not_hold_up_the_stop_for_long() {
    require_gst_elements(&[
        "udpsrc",
        "rtpjpegdepay",
        "jpegdec",
        "videoconvert",
        "appsink",
    ]);
    // Nothing is ever sent to this port: the read blocks inside GStreamer.
    let port = std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let src = start(format!(
        "udpsrc address=127.0.0.1 port={port} \
         caps=\"application/x-rtp,media=video,encoding-name=JPEG,payload=26,clock-rate=90000\" \
         ! rtpjpegdepay ! jpegdec ! videoconvert ! appsink"
    ));
    std::thread::sleep(Duration::from_millis(300));
    assert!(src.queue.is_empty());
    src.stop.store(true, Ordering::Relaxed);
    let t = Instant::now();
    let joined = join_within(src.thread, Duration::from_millis(500));
    assert!(!joined, "a read of a silent stream only ends with data");
    assert!(
        t.elapsed() < Duration::from_secs(2),
        "stop waited {:?}",
        t.elapsed()
    );
}

#[test]
fn bad_pipelines_and_devices_are_errors_that_name_them() {
    let open = |source: LocalSource| {
        spawn_reader(
            source,
            10,
            info(),
            DropOldestQueue::new(2),
            Arc::default(),
            Arc::new(AtomicBool::new(false)),
        )
        .map(|_| ())
        .unwrap_err()
        .to_string()
    };
    let e = open(LocalSource::Gst {
        pipeline: "videotestsrc ! autovideosink".into(),
        camera: 0,
    });
    assert!(
        e.contains("gst:videotestsrc ! autovideosink") && e.contains("must end in `appsink`"),
        "{e}"
    );
    let e = open(LocalSource::Gst {
        pipeline: "shoalnosuchsrc ! videoconvert ! appsink".into(),
        camera: 0,
    });
    assert!(
        e.contains("GStreamer could not open the pipeline") && e.contains("`shoalnosuchsrc`"),
        "{e}"
    );
    let e = open(LocalSource::V4l2 {
        device: "/dev/video-shoal-absent".into(),
        camera: 0,
    });
    assert!(
        e.contains("v4l2:/dev/video-shoal-absent: no such device"),
        "{e}"
    );
}
