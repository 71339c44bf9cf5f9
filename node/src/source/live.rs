//! Live camera sources (`camera:N`, `v4l2:/dev/videoN`, `gst:PIPELINE`):
//! opening them through OpenCV with an error that names what failed, stamping
//! each frame on the wall clock (`docs/time.md`), counting the frames the
//! source's own timing shows it never delivered, and reopening a stream that
//! ended or failed.
//!
//! Stamps ([`StampClock`]):
//! - V4L2 gives each buffer's time on `CLOCK_MONOTONIC` (OpenCV's
//!   `CAP_PROP_POS_MSEC`); it is moved to the wall clock by the current
//!   `CLOCK_REALTIME − CLOCK_MONOTONIC` ([`StampSource::Driver`]).
//! - GStreamer gives the pipeline's position on its running time, which
//!   starts near 0 when the pipeline starts; it is placed on the wall clock
//!   by the earliest arrival seen ([`PipelineClock`],
//!   [`StampSource::Pipeline`]). OpenCV 4.6 answers `CAP_PROP_POS_MSEC` by
//!   asking the `appsink` for its position (not the pulled buffer's time):
//!   the buffer's time when the reader keeps up, up to the reader's lag
//!   later when it does not.
//! - Anything else, or a source time that disagrees with the arrival by more
//!   than [`MAX_SOURCE_DISAGREEMENT_NS`], is stamped on arrival
//!   ([`StampSource::Arrival`]).

use super::{mat_as_gray, source_error, Feed, LocalSource, SourceError};
use crate::clock::{realtime_minus_monotonic_ns, wall_now_ns};
use opencv::core::Mat;
use opencv::prelude::*;
use opencv::videoio::{self, VideoCapture};
use shoal_proto::messages::StampSource;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// A source time further than this from the frame's arrival on the wall
/// clock is not believed, and the frame is stamped on arrival: a second is
/// far beyond any capture-to-read latency of a live camera (tens of
/// milliseconds) and well inside what a wrong clock domain gives (a
/// monotonic time read as wall time is off by years).
pub const MAX_SOURCE_DISAGREEMENT_NS: i128 = 1_000_000_000;

/// First wait before reopening a stream that ended; doubled after every
/// failed reopening up to [`MAX_BACKOFF`], back to this once frames flow.
pub const INITIAL_BACKOFF: Duration = Duration::from_millis(500);
/// Longest wait between reopenings.
pub const MAX_BACKOFF: Duration = Duration::from_secs(5);

/// How a live capture's frames are stamped on the wall clock.
#[derive(Debug, Clone, PartialEq)]
pub enum StampClock {
    /// The driver's buffer time on `CLOCK_MONOTONIC` (V4L2).
    Driver,
    /// The GStreamer pipeline's buffer time.
    Pipeline(PipelineClock),
    /// The wall clock when the frame was read.
    Arrival,
}

/// Places a GStreamer pipeline's buffer times on the wall clock: stamp =
/// anchor + pipeline time, the anchor being the smallest `arrival − pipeline
/// time` seen (the frame that reached the node fastest), so a stamp is never
/// later than its frame's arrival and successive stamps keep the pipeline's
/// own spacing instead of the reader's jitter. A jump of the pipeline's time
/// against the arrivals by over [`MAX_SOURCE_DISAGREEMENT_NS`] (a restarted
/// stream, a discontinuity) re-anchors on that frame.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PipelineClock {
    anchor_ns: Option<i128>,
}

impl PipelineClock {
    /// The wall-clock stamp of a buffer at `pipeline_ns` that arrived at `arrival_ns`.
    pub fn stamp(&mut self, pipeline_ns: i128, arrival_ns: i128) -> i128 {
        let candidate = arrival_ns - pipeline_ns;
        let anchor = match self.anchor_ns {
            Some(a) if (candidate - a).abs() <= MAX_SOURCE_DISAGREEMENT_NS => a.min(candidate),
            Some(a) => {
                tracing::debug!(
                    "pipeline time jumped {:.3} s against the arrivals: re-anchored",
                    (a - candidate) as f64 * 1e-9
                );
                candidate
            }
            None => candidate,
        };
        self.anchor_ns = Some(anchor);
        anchor + pipeline_ns
    }
}

impl StampClock {
    /// The stamp of a frame the capture says is at `source_ms` on its own
    /// clock (OpenCV's `CAP_PROP_POS_MSEC`) and that was read at
    /// `arrival_ns` (wall clock), with `realtime_minus_monotonic_ns` the
    /// current offset between the two clocks: the stamp, where it came from,
    /// and the source's own time in nanoseconds when it was used (for
    /// counting missed frames).
    pub fn stamp(
        &mut self,
        source_ms: f64,
        arrival_ns: u64,
        realtime_minus_monotonic_ns: Option<i128>,
    ) -> (u64, StampSource, Option<i128>) {
        let arrival = arrival_ns as i128;
        let on_arrival = (arrival_ns, StampSource::Arrival, None);
        // Beyond 10^12 ms (31 years) is a "no time" sentinel, not a time.
        if !(source_ms.is_finite() && source_ms > 0.0 && source_ms < 1e12) {
            return on_arrival;
        }
        let source_ns = (source_ms * 1e6).round() as i128;
        let (stamp, kind) = match self {
            StampClock::Arrival => return on_arrival,
            StampClock::Driver => match realtime_minus_monotonic_ns {
                Some(offset) => (source_ns + offset, StampSource::Driver),
                None => return on_arrival,
            },
            StampClock::Pipeline(clock) => (clock.stamp(source_ns, arrival), StampSource::Pipeline),
        };
        if stamp <= 0 || (stamp - arrival).abs() > MAX_SOURCE_DISAGREEMENT_NS {
            return on_arrival;
        }
        (stamp as u64, kind, Some(source_ns))
    }
}

/// Frames a source's own timing shows it never delivered: successive
/// source times `k` nominal frame periods apart (rounded) mean `k − 1`
/// frames were lost before the node read them.
#[derive(Debug, Clone, PartialEq)]
pub struct GapCounter {
    period_ns: Option<f64>,
    last_ns: Option<i128>,
}

impl GapCounter {
    /// A counter for a source of `fps` frames per second (0 or unknown: no
    /// nominal period, nothing is counted).
    pub fn new(fps: f64) -> GapCounter {
        GapCounter {
            period_ns: (fps.is_finite() && fps > 0.0).then(|| 1e9 / fps),
            last_ns: None,
        }
    }

    /// Frames missed between the previous source time and `source_ns`.
    pub fn missed(&mut self, source_ns: i128) -> u64 {
        let last = self.last_ns.replace(source_ns);
        match (last, self.period_ns) {
            (Some(last), Some(period)) if source_ns > last => {
                let periods = ((source_ns - last) as f64 / period).round();
                if periods >= 2.0 {
                    periods as u64 - 1
                } else {
                    0
                }
            }
            _ => 0,
        }
    }
}

/// Why a GStreamer pipeline cannot be a source before OpenCV tries it:
/// OpenCV takes frames from its last element, which must be an `appsink`.
pub fn gst_pipeline_problem(pipeline: &str) -> Option<String> {
    let last = pipeline.rsplit('!').next().unwrap_or("").trim();
    let element = last.split_whitespace().next().unwrap_or("");
    (element != "appsink").then(|| {
        format!(
            "the pipeline must end in `appsink` (e.g. `… ! videoconvert ! appsink`), \
             where OpenCV takes its frames; it ends in `{last}`"
        )
    })
}

/// The pipeline's elements that GStreamer does not have, as
/// `gst-inspect-1.0 --exists` says (`None`: it could not be asked, as
/// without Debian's gstreamer1.0-tools).
fn missing_gst_elements(pipeline: &str) -> Option<Vec<String>> {
    let mut missing = Vec::new();
    for segment in pipeline.split('!') {
        let Some(name) = segment.split_whitespace().next() else {
            continue;
        };
        // Caps (`video/x-raw,…`) and references to named elements (`t.`) are not elements.
        if name.contains(['/', '.', '=', ',', '(']) {
            continue;
        }
        let status = std::process::Command::new("gst-inspect-1.0")
            .args(["--exists", name])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .status()
            .ok()?;
        if !status.success() {
            missing.push(name.to_string());
        }
    }
    Some(missing)
}

/// An open live capture and how its frames are stamped.
pub(super) struct LiveCapture {
    source: LocalSource,
    cap: VideoCapture,
    clock: StampClock,
}

fn opened(cap: VideoCapture, what: &str, why: &str) -> Result<VideoCapture, SourceError> {
    if cap.is_opened().unwrap_or(false) {
        Ok(cap)
    } else {
        Err(source_error(what, why))
    }
}

impl LiveCapture {
    /// Open `source` (a `Live`, `V4l2` or `Gst` one).
    pub(super) fn open(source: LocalSource) -> Result<LiveCapture, SourceError> {
        let what = source.describe();
        let cv = |e: opencv::Error| source_error(what.clone(), e.to_string());
        let (cap, clock) = match &source {
            LocalSource::Live { device, .. } => {
                let cap = VideoCapture::new(*device, videoio::CAP_ANY).map_err(cv)?;
                let cap = opened(cap, &what, "cannot open camera")?;
                // Stamped as its backend allows.
                let clock = match cap.get_backend_name().unwrap_or_default().as_str() {
                    "V4L2" => StampClock::Driver,
                    "GSTREAMER" => StampClock::Pipeline(PipelineClock::default()),
                    _ => StampClock::Arrival,
                };
                (cap, clock)
            }
            LocalSource::V4l2 { device, .. } => {
                if !device.exists() {
                    return Err(source_error(what, "no such device"));
                }
                let path = device.to_string_lossy();
                let cap = VideoCapture::from_file(&path, videoio::CAP_V4L2).map_err(cv)?;
                let why = "OpenCV's V4L2 backend cannot open it (not a video capture device, \
                           busy, or no permission)";
                (opened(cap, &what, why)?, StampClock::Driver)
            }
            LocalSource::Gst { pipeline, .. } => (
                open_gst(pipeline, &what)?,
                StampClock::Pipeline(PipelineClock::default()),
            ),
            LocalSource::Images { .. } | LocalSource::Video { .. } => {
                return Err(source_error(what, "not a live source"));
            }
        };
        Ok(LiveCapture { source, cap, clock })
    }
}

fn open_gst(pipeline: &str, what: &str) -> Result<VideoCapture, SourceError> {
    if let Some(problem) = gst_pipeline_problem(pipeline) {
        return Err(source_error(what, problem));
    }
    if !videoio::has_backend(videoio::VideoCaptureAPIs::CAP_GSTREAMER).unwrap_or(false) {
        return Err(source_error(
            what,
            "this OpenCV has no GStreamer backend (Debian's libopencv-videoio406 has one)",
        ));
    }
    // Asked before OpenCV tries: OpenCV 4.6 runs what GStreamer could parse
    // of a pipeline with an unknown element, and its open then waits forever
    // for a first frame.
    if let Some(missing) = missing_gst_elements(pipeline).filter(|m| !m.is_empty()) {
        return Err(source_error(
            what,
            format!(
                "GStreamer could not open the pipeline: it has no element {} \
                 (install the GStreamer plugin package that provides it: \
                 gstreamer1.0-plugins-base, -good, -bad, -ugly or gstreamer1.0-libav)",
                missing
                    .iter()
                    .map(|e| format!("`{e}`"))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        ));
    }
    let cap = VideoCapture::from_file(pipeline, videoio::CAP_GSTREAMER)
        .map_err(|e| source_error(what, format!("GStreamer could not open the pipeline: {e}")))?;
    opened(
        cap,
        what,
        "GStreamer could not open the pipeline (a bad property, caps that do not \
         link, or a device or address it cannot open: OpenCV's warning above says which)",
    )
}

/// Sleep `wait` unless `stop` is raised first; false if it was.
fn sleep_unless_stopped(wait: Duration, stop: &AtomicBool) -> bool {
    let deadline = std::time::Instant::now() + wait;
    while std::time::Instant::now() < deadline {
        if stop.load(Ordering::Relaxed) {
            return false;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    !stop.load(Ordering::Relaxed)
}

/// Read `cap` until `stop`, reopening its stream whenever it ends or fails:
/// a wait of [`INITIAL_BACKOFF`] doubled after each failed reopening up to
/// [`MAX_BACKOFF`]; each reopening is counted and logged with its reason.
/// Frame numbers continue across reopenings (and skip what was missed).
pub(super) fn run(feed: &Feed, mut cap: LiveCapture, stop: &AtomicBool) {
    let source = cap.source.clone();
    let what = source.describe();
    let mut seq = 0u64;
    let mut backoff = INITIAL_BACKOFF;
    loop {
        let (delivered, reason) = read_frames(feed, &mut cap, &mut seq, stop);
        if stop.load(Ordering::Relaxed) {
            return;
        }
        if delivered > 0 {
            backoff = INITIAL_BACKOFF;
        }
        tracing::warn!(
            "vehicle {} camera {}: {what}: {reason}; reopening in {:.1} s",
            feed.vehicle,
            feed.camera,
            backoff.as_secs_f64()
        );
        drop(cap);
        cap = loop {
            if !sleep_unless_stopped(backoff, stop) {
                return;
            }
            backoff = (backoff * 2).min(MAX_BACKOFF);
            match LiveCapture::open(source.clone()) {
                Ok(c) => break c,
                Err(e) => tracing::warn!(
                    "vehicle {} camera {}: reopening failed: {e}; next try in {:.1} s",
                    feed.vehicle,
                    feed.camera,
                    backoff.as_secs_f64()
                ),
            }
        };
        feed.counters.reconnects.fetch_add(1, Ordering::Relaxed);
        tracing::warn!(
            "vehicle {} camera {}: {what}: reopened",
            feed.vehicle,
            feed.camera
        );
    }
}

/// Read frames until the stream ends or fails, or `stop`: how many were
/// delivered, and why the stream ended.
fn read_frames(
    feed: &Feed,
    cap: &mut LiveCapture,
    seq: &mut u64,
    stop: &AtomicBool,
) -> (u64, String) {
    let fps = cap.cap.get(videoio::CAP_PROP_FPS).unwrap_or(0.0);
    let mut gaps = GapCounter::new(fps);
    let mut frame = Mat::default();
    let mut delivered = 0u64;
    while !stop.load(Ordering::Relaxed) {
        match cap.cap.read(&mut frame) {
            Ok(true) if !frame.empty() => {}
            Ok(_) => {
                return (
                    delivered,
                    "the stream ended (end of stream, or the device or pipeline gave no frame)"
                        .into(),
                )
            }
            Err(e) => return (delivered, format!("read failed: {e}")),
        }
        let arrival = wall_now_ns();
        let source_ms = cap.cap.get(videoio::CAP_PROP_POS_MSEC).unwrap_or(f64::NAN);
        let (stamp, kind, source_ns) =
            cap.clock
                .stamp(source_ms, arrival, realtime_minus_monotonic_ns());
        let missed = source_ns.map_or(0, |t| gaps.missed(t));
        if missed > 0 {
            feed.counters.missed.fetch_add(missed, Ordering::Relaxed);
            tracing::debug!(
                "vehicle {} camera {}: {missed} frames missed before frame {}",
                feed.vehicle,
                feed.camera,
                *seq + missed
            );
            *seq += missed;
        }
        match mat_as_gray(&frame) {
            Ok(g) => feed.push(g, *seq, stamp, kind),
            Err(e) => feed.unreadable(1, format_args!("frame {seq}: {e}")),
        }
        *seq += 1;
        delivered += 1;
    }
    (delivered, "stopped".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: i128 = 1_000_000;
    /// A wall-clock time in 2026, ns.
    const T0: i128 = 1_780_000_000_000_000_000;

    #[test]
    fn pipeline_stamps_keep_the_pipeline_spacing_and_never_pass_the_arrival() {
        let mut clock = PipelineClock::default();
        // Buffers every 50 ms of pipeline time, read with 5–25 ms of latency.
        let latency = [20, 5, 25, 10];
        let stamps: Vec<i128> = latency
            .iter()
            .enumerate()
            .map(|(i, l)| {
                let pts = i as i128 * 50 * MS;
                let arrival = T0 + pts + l * MS;
                let s = clock.stamp(pts, arrival);
                assert!(s <= arrival, "frame {i}: stamp after its arrival");
                s
            })
            .collect();
        // After the fastest frame (5 ms), stamps are that frame's anchor + pts.
        assert_eq!(stamps[1], T0 + 50 * MS + 5 * MS);
        assert_eq!(stamps[3] - stamps[2], 50 * MS);
        // A restarted stream (pipeline time back at 0) re-anchors on its first frame.
        let arrival = T0 + 10_000 * MS;
        assert_eq!(clock.stamp(2 * MS, arrival), arrival);
    }

    #[test]
    fn driver_stamps_move_monotonic_time_to_the_wall_clock() {
        let offset = T0 - 5_000_000 * MS; // booted 5000 s ago
        let mono_ms = 5_000_000.0 + 12.5;
        let arrival = (T0 + 20 * MS) as u64;
        let (stamp, kind, source) = StampClock::Driver.stamp(mono_ms, arrival, Some(offset));
        assert_eq!(kind, StampSource::Driver);
        assert_eq!(stamp as i128, T0 + 12_500_000);
        assert_eq!(source, Some(5_000_012_500_000));
        // A driver time on another clock (here: off by an hour) is not believed.
        let (stamp, kind, _) = StampClock::Driver.stamp(mono_ms + 3.6e6, arrival, Some(offset));
        assert_eq!((stamp, kind), (arrival, StampSource::Arrival));
        // No time at all (0, NaN) is stamped on arrival.
        for ms in [0.0, f64::NAN, -1.0] {
            let (stamp, kind, _) = StampClock::Driver.stamp(ms, arrival, Some(offset));
            assert_eq!((stamp, kind), (arrival, StampSource::Arrival));
        }
    }

    #[test]
    fn gaps_of_k_periods_count_k_minus_one_missed_frames() {
        let mut gaps = GapCounter::new(20.0); // 50 ms
        let t = |ms: i128| ms * MS;
        assert_eq!(gaps.missed(t(0)), 0);
        assert_eq!(gaps.missed(t(50)), 0);
        assert_eq!(gaps.missed(t(110)), 0, "jitter within half a period");
        assert_eq!(gaps.missed(t(260)), 2, "three periods: two frames missing");
        assert_eq!(gaps.missed(t(300)), 0);
        let mut unknown = GapCounter::new(0.0);
        assert_eq!(unknown.missed(t(0)) + unknown.missed(t(1000)), 0);
    }

    #[test]
    fn a_pipeline_must_end_in_appsink() {
        assert_eq!(
            gst_pipeline_problem("videotestsrc ! videoconvert ! appsink"),
            None
        );
        assert_eq!(
            gst_pipeline_problem("videotestsrc ! appsink name=s drop=true"),
            None
        );
        let e = gst_pipeline_problem("videotestsrc ! autovideosink").unwrap();
        assert!(
            e.contains("must end in `appsink`") && e.contains("autovideosink"),
            "{e}"
        );
        assert!(gst_pipeline_problem("videotestsrc ! appsinkx").is_some());
    }
}
