//! A vehicle's camera threads, whatever carries their frames: each camera's
//! thread takes frames from a [`FrameInput`], runs its [`CameraPipeline`] and
//! hands every observation to a sink; [`NodeStats`] counts what they did and
//! builds the vehicle's [`NodeStatus`] report.
//!
//! The node service (`shoal_services::node`) feeds these threads from Zenoh
//! and publishes what they produce; [`LocalInput`] feeds one from a
//! [`crate::source`] reader thread (a folder of images, a video, a camera).

use crate::detect::CornerFitCounts;
use crate::mat::gray_as_mat;
use crate::pipeline::CameraPipeline;
use opencv::prelude::*;
use shoal_proto::config::Camera;
use shoal_proto::image::GrayImage;
use shoal_proto::messages::{
    CameraFrame, CameraStatus, NodeStatus, Observation, PixelFormat, StampSource, VehicleId,
};
use shoal_proto::queue::DropOldestQueue;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Where one camera thread's frames come from.
pub trait FrameInput: Send {
    /// Wait up to `timeout` for the next frame.
    fn next(&self, timeout: Duration) -> Option<CameraFrame>;
    /// Frames dropped because the camera thread fell behind.
    fn dropped(&self) -> u64;
    /// Frames refused before reaching the pipeline: undecodable or invalid
    /// envelopes (Zenoh), unreadable images or video frames (local).
    fn rejected(&self) -> u64;
    /// Envelopes that failed decoding or validation (counted in the node's
    /// `messages_rejected`); 0 for inputs that do not receive envelopes.
    fn messages_rejected(&self) -> u64;
    /// Where the stamps of the frames it gives come from (default: the
    /// stamp each frame arrived with).
    fn stamp_source(&self) -> StampSource {
        StampSource::Sender
    }
    /// Frames the source's own timing shows it never delivered (default 0:
    /// the input cannot tell).
    fn frames_missed(&self) -> u64 {
        0
    }
    /// Times the source was reopened after its stream ended or failed.
    fn reconnects(&self) -> u64 {
        0
    }
}

/// What a local source's reader thread reports besides its frames.
#[derive(Debug, Default)]
pub struct SourceCounters {
    /// Images or video frames it could not decode.
    pub unreadable: AtomicU64,
    /// Frames its timing shows the device or pipeline never delivered.
    pub missed: AtomicU64,
    /// Reopenings after the stream ended or failed.
    pub reconnects: AtomicU64,
    /// The [`StampSource`] of the newest frame (its `as u8`).
    stamp_source: AtomicU8,
}

impl SourceCounters {
    pub fn set_stamp_source(&self, source: StampSource) {
        self.stamp_source.store(source as u8, Ordering::Relaxed);
    }
    pub fn stamp_source(&self) -> StampSource {
        stamp_source_from_u8(self.stamp_source.load(Ordering::Relaxed))
    }
}

fn stamp_source_from_u8(v: u8) -> StampSource {
    [
        StampSource::Unknown,
        StampSource::Sender,
        StampSource::Driver,
        StampSource::Pipeline,
        StampSource::Arrival,
        StampSource::Playback,
    ]
    .into_iter()
    .find(|s| *s as u8 == v)
    .unwrap_or(StampSource::Unknown)
}

/// A local source's queue and its counters.
#[derive(Debug, Clone)]
pub struct LocalInput {
    pub queue: DropOldestQueue<CameraFrame>,
    pub counters: Arc<SourceCounters>,
}

impl LocalInput {
    /// An empty input holding at most `capacity` frames before the oldest is dropped.
    pub fn new(capacity: usize) -> LocalInput {
        LocalInput {
            queue: DropOldestQueue::new(capacity),
            counters: Arc::default(),
        }
    }
}

impl FrameInput for LocalInput {
    fn next(&self, timeout: Duration) -> Option<CameraFrame> {
        self.queue.pop_timeout(timeout).ok()
    }
    fn dropped(&self) -> u64 {
        self.queue.dropped()
    }
    fn rejected(&self) -> u64 {
        self.counters.unreadable.load(Ordering::Relaxed)
    }
    fn messages_rejected(&self) -> u64 {
        0
    }
    fn stamp_source(&self) -> StampSource {
        self.counters.stamp_source()
    }
    fn frames_missed(&self) -> u64 {
        self.counters.missed.load(Ordering::Relaxed)
    }
    fn reconnects(&self) -> u64 {
        self.counters.reconnects.load(Ordering::Relaxed)
    }
}

#[derive(Debug, Default)]
struct CameraCounters {
    frames_in: AtomicU64,
    frames_dropped: AtomicU64,
    frames_invalid: AtomicU64,
    detections: AtomicU64,
    /// Reads of a marker this vehicle carries itself, dropped by the pipeline.
    own_marker_reads: AtomicU64,
    /// The input's [`StampSource`] (`as u8`), once it gave a frame.
    stamp_source: AtomicU8,
    frames_missed: AtomicU64,
    reconnects: AtomicU64,
    /// Detections since start by the corner fit that ran.
    corner_fits: Mutex<CornerFitCounts>,
    /// What the restoration did, since start.
    restoration: Mutex<RestorationTally>,
    /// Sums over the current status period: (frames, restore, detect, pose ms).
    period: Mutex<(u64, f64, f64, f64)>,
}

impl CameraCounters {
    /// Counts what camera `i` of `vehicle` made of frame `seq`: detections,
    /// corner fits, the restoration's tally, reads of the vehicle's own
    /// markers (logged once, then counted), pose failures (logged at debug).
    fn count(&self, out: &crate::pipeline::FrameOutput, i: usize, vehicle: VehicleId, seq: u64) {
        self.detections
            .fetch_add(out.detections as u64, Ordering::Relaxed);
        if let Ok(mut fits) = self.corner_fits.lock() {
            fits.merge(&out.corner_fits);
        }
        if let Ok(mut tally) = self.restoration.lock() {
            tally.add(out);
        }
        for reason in &out.pose_failures {
            tracing::debug!("camera {i}: {reason}");
        }
        if out.own_marker_reads > 0 {
            let before = self
                .own_marker_reads
                .fetch_add(out.own_marker_reads as u64, Ordering::Relaxed);
            if before == 0 {
                tracing::warn!(
                    "camera {i}: frame {seq} read a marker vehicle {vehicle} carries itself — dropped (further ones counted, not logged)"
                );
            }
        }
    }
}

/// What one camera's restoration did over the frames it processed
/// ([`NodeStats::restoration`]): where its time goes (issue #18).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RestorationTally {
    /// Frames processed.
    pub frames: u64,
    /// Of them, restored whole (no region stood out, or a whole-frame method).
    pub restored_whole: u64,
    /// Sum over the frames of the share of the frame restored.
    pub restored_fraction_sum: f64,
    /// Frames whose detail-keeping restoration was searched too.
    pub fine_searches: u64,
    /// The water the restoration worked for (1/m): sum, least and most.
    pub water_c_sum: f64,
    pub water_c_min: f64,
    pub water_c_max: f64,
}

impl RestorationTally {
    fn add(&mut self, out: &crate::pipeline::FrameOutput) {
        let c = out.water_c_per_m;
        if self.frames == 0 {
            (self.water_c_min, self.water_c_max) = (c, c);
        }
        self.frames += 1;
        self.restored_whole += u64::from(out.restored_fraction >= 1.0);
        self.restored_fraction_sum += out.restored_fraction;
        self.fine_searches += u64::from(out.fine_searched);
        self.water_c_sum += c;
        self.water_c_min = self.water_c_min.min(c);
        self.water_c_max = self.water_c_max.max(c);
    }
    /// Mean share of the frame restored (0 before any frame).
    pub fn mean_restored_fraction(&self) -> f64 {
        self.restored_fraction_sum / self.frames.max(1) as f64
    }
    /// Mean water the restoration worked for, 1/m (0 before any frame).
    pub fn mean_water_c_per_m(&self) -> f64 {
        self.water_c_sum / self.frames.max(1) as f64
    }
}

/// Live counters of a running node (also what its status messages report).
#[derive(Debug, Default)]
pub struct NodeStats {
    cameras: Vec<(u8, String, CameraCounters)>,
    pub observations_sent: AtomicU64,
    pub messages_rejected: AtomicU64,
    /// Newest frame capture time seen (the node's clock for status stamps).
    newest_stamp_ns: AtomicU64,
    /// Sum and count of per-frame pipeline latency (ms), since start.
    latency: Mutex<(f64, u64)>,
}

impl NodeStats {
    /// Zeroed counters for a vehicle with these cameras (in fleet-file order).
    pub fn new(cameras: &[Camera]) -> NodeStats {
        NodeStats {
            cameras: cameras
                .iter()
                .map(|c| (c.index, c.name.clone(), CameraCounters::default()))
                .collect(),
            ..Default::default()
        }
    }
    /// Mean per-frame pipeline latency (restore + detect + pose), ms.
    pub fn mean_latency_ms(&self) -> Option<f64> {
        let g = self.latency.lock().ok()?;
        (g.1 > 0).then(|| g.0 / g.1 as f64)
    }
    pub fn frames_processed(&self) -> u64 {
        self.latency.lock().map(|g| g.1).unwrap_or(0)
    }
    pub fn frames_dropped(&self) -> u64 {
        self.cameras
            .iter()
            .map(|c| c.2.frames_dropped.load(Ordering::Relaxed))
            .sum()
    }
    /// Frames received by the camera threads, all cameras.
    pub fn frames_in(&self) -> u64 {
        self.cameras
            .iter()
            .map(|c| c.2.frames_in.load(Ordering::Relaxed))
            .sum()
    }
    /// Frames refused as malformed (undecodable envelopes or images, wrong
    /// size or format, pipeline errors), all cameras.
    pub fn frames_invalid(&self) -> u64 {
        self.cameras
            .iter()
            .map(|c| c.2.frames_invalid.load(Ordering::Relaxed))
            .sum()
    }

    /// Per camera (name, in fleet-file order): what its restoration did since start.
    pub fn restoration(&self) -> Vec<(String, RestorationTally)> {
        self.cameras
            .iter()
            .map(|(_, name, c)| {
                let tally = c.restoration.lock().map(|t| t.clone()).unwrap_or_default();
                (name.clone(), tally)
            })
            .collect()
    }

    /// Reads of the vehicle's own markers, dropped before pose (all cameras).
    pub fn own_marker_reads(&self) -> u64 {
        self.cameras
            .iter()
            .map(|c| c.2.own_marker_reads.load(Ordering::Relaxed))
            .sum()
    }

    /// The vehicle's status over the last `period_s` seconds (resets the
    /// per-period sums), stamped with the newest frame capture time seen.
    pub fn status_report(&self, vehicle: VehicleId, started: Instant, period_s: f64) -> NodeStatus {
        let cameras = self
            .cameras
            .iter()
            .map(|(index, name, c)| {
                let (n, r, d, p) = c
                    .period
                    .lock()
                    .map(|mut g| std::mem::take(&mut *g))
                    .unwrap_or_default();
                let mean = |x: f64| if n > 0 { (x / n as f64) as f32 } else { 0.0 };
                CameraStatus {
                    camera: *index,
                    name: name.clone(),
                    frames_in: c.frames_in.load(Ordering::Relaxed),
                    frames_dropped: c.frames_dropped.load(Ordering::Relaxed),
                    frames_invalid: c.frames_invalid.load(Ordering::Relaxed),
                    detections: c.detections.load(Ordering::Relaxed),
                    frame_rate_hz: (n as f64 / period_s.max(1e-3)) as f32,
                    restore_ms: mean(r),
                    detect_ms: mean(d),
                    pose_ms: mean(p),
                    corner_fits: c
                        .corner_fits
                        .lock()
                        .map(|f| {
                            f.nonzero()
                                .map(|(fit, n)| (fit.name().to_string(), n))
                                .collect()
                        })
                        .unwrap_or_default(),
                    stamp_source: stamp_source_from_u8(c.stamp_source.load(Ordering::Relaxed)),
                    frames_missed: c.frames_missed.load(Ordering::Relaxed),
                    reconnects: c.reconnects.load(Ordering::Relaxed),
                }
            })
            .collect();
        NodeStatus {
            vehicle,
            stamp_ns: self.newest_stamp_ns.load(Ordering::Relaxed),
            uptime_s: started.elapsed().as_secs_f64(),
            cameras,
            observations_sent: self.observations_sent.load(Ordering::Relaxed),
            messages_rejected: self.messages_rejected.load(Ordering::Relaxed),
            clock: None,
        }
    }
}

/// Start the thread of the vehicle's `i`-th camera (its position in the
/// fleet file, which [`NodeStats::new`] was given): frames from `input` that
/// are not Mono8 of the camera's size, or not for camera `i`, are refused and
/// counted; the others go through `pipeline`, and each observation it makes
/// goes to `publish` (counted in `observations_sent` when that succeeds).
/// Runs until `stop` is raised.
pub fn spawn_camera<E: std::fmt::Display>(
    vehicle: VehicleId,
    i: usize,
    mut pipeline: CameraPipeline,
    input: Box<dyn FrameInput>,
    publish: impl Fn(&Observation) -> Result<(), E> + Send + 'static,
    stats: Arc<NodeStats>,
    stop: Arc<AtomicBool>,
) -> std::io::Result<JoinHandle<()>> {
    let name = format!("cam-{}-{}", vehicle, pipeline.camera().name);
    let expected = (
        pipeline.camera().model.width,
        pipeline.camera().model.height,
    );
    std::thread::Builder::new().name(name).spawn(move || {
        let counters = &stats.cameras[i].2;
        // Frames this thread refused (wrong format or size, pipeline
        // errors); `frames_invalid` reports them plus those the input
        // refused before they got here.
        let mut refused_here = 0u64;
        let mut rejected_seen = 0u64;
        while !stop.load(Ordering::Relaxed) {
            counters
                .frames_dropped
                .store(input.dropped(), Ordering::Relaxed);
            counters
                .frames_invalid
                .store(refused_here + input.rejected(), Ordering::Relaxed);
            counters
                .frames_missed
                .store(input.frames_missed(), Ordering::Relaxed);
            counters
                .reconnects
                .store(input.reconnects(), Ordering::Relaxed);
            let rejected = input.messages_rejected();
            if rejected > rejected_seen {
                stats
                    .messages_rejected
                    .fetch_add(rejected - rejected_seen, Ordering::Relaxed);
                rejected_seen = rejected;
            }
            let Some(frame) = input.next(Duration::from_millis(100)) else {
                continue;
            };
            counters.frames_in.fetch_add(1, Ordering::Relaxed);
            counters
                .stamp_source
                .store(input.stamp_source() as u8, Ordering::Relaxed);
            stats
                .newest_stamp_ns
                .fetch_max(frame.stamp_ns, Ordering::Relaxed);
            if frame.format != PixelFormat::Mono8
                || (frame.info.model.width, frame.info.model.height) != expected
                || frame.camera as usize != i
            {
                refused_here += 1;
                counters.frames_invalid.fetch_add(1, Ordering::Relaxed);
                tracing::warn!(
                    "camera {i}: frame {} is {:?} {}x{} for camera {}, expected Mono8 {}x{} — dropped",
                    frame.seq,
                    frame.format,
                    frame.info.model.width,
                    frame.info.model.height,
                    frame.camera,
                    expected.0,
                    expected.1
                );
                continue;
            }
            let img = GrayImage {
                width: frame.info.model.width,
                height: frame.info.model.height,
                data: frame.data,
            };
            let result = gray_as_mat(&img)
                .map_err(|e| e.to_string())
                .and_then(|view| view.try_clone().map_err(|e| e.to_string()))
                .and_then(|mat| {
                    pipeline
                        .process(&mat, frame.stamp_ns, frame.seq)
                        .map_err(|e| e.to_string())
                });
            match result {
                Ok(out) => {
                    counters.count(&out, i, vehicle, frame.seq);
                    for obs in &out.observations {
                        match publish(obs) {
                            Ok(()) => {
                                stats.observations_sent.fetch_add(1, Ordering::Relaxed);
                            }
                            Err(e) => tracing::warn!("publishing observation: {e}"),
                        }
                    }
                    if let Ok(mut p) = counters.period.lock() {
                        p.0 += 1;
                        p.1 += out.restore_ms;
                        p.2 += out.detect_ms;
                        p.3 += out.pose_ms;
                    }
                    if let Ok(mut l) = stats.latency.lock() {
                        l.0 += out.restore_ms + out.detect_ms + out.pose_ms;
                        l.1 += 1;
                    }
                }
                Err(e) => {
                    refused_here += 1;
                    counters.frames_invalid.fetch_add(1, Ordering::Relaxed);
                    tracing::warn!("camera {i}: frame {} failed: {e}", frame.seq);
                }
            }
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::PipelineParams;
    use shoal_proto::config::Fleet;
    use shoal_proto::samples;
    use std::path::Path;

    fn paper_fleet() -> Arc<Fleet> {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/fleets/paper.toml");
        Arc::new(Fleet::load(&path).unwrap())
    }

    /// Runs camera `camera` of `vehicle` on `input` (observations
    /// discarded) until `done(stats)` or `timeout`, then stops its thread.
    fn run_camera(
        vehicle: VehicleId,
        camera: usize,
        pipeline: CameraPipeline,
        input: LocalInput,
        stats: &Arc<NodeStats>,
        timeout: Duration,
        done: impl Fn(&NodeStats) -> bool,
    ) {
        let stop = Arc::new(AtomicBool::new(false));
        let thread = spawn_camera(
            vehicle,
            camera,
            pipeline,
            Box::new(input),
            |_: &Observation| -> Result<(), String> { Ok(()) },
            stats.clone(),
            stop.clone(),
        )
        .unwrap();
        let deadline = Instant::now() + timeout;
        while !done(stats) && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(10));
        }
        stop.store(true, Ordering::Relaxed);
        thread.join().unwrap();
    }

    #[test]
    fn refused_and_unreadable_frames_are_counted_as_invalid() {
        let fleet = paper_fleet();
        let vehicle = fleet.vehicle(17).unwrap().clone();
        let stats = Arc::new(NodeStats::new(&vehicle.cameras));
        let pipeline =
            CameraPipeline::new(fleet.clone(), 17, 0, PipelineParams::default()).unwrap();
        let input = LocalInput::new(4);
        // What a local reader could not decode before the thread started.
        input.counters.unreadable.store(3, Ordering::Relaxed);
        // 8x4, not camera 0's size.
        let wrong_size = samples::camera_frame();
        // Camera 0's size, but addressed to camera 1.
        let model = vehicle.cameras[0].model;
        let mut wrong_camera = samples::camera_frame();
        wrong_camera.camera = 1;
        wrong_camera.stamp_ns = 40;
        wrong_camera.info.model = model;
        wrong_camera.data = vec![0; model.width as usize * model.height as usize];
        input.queue.push(wrong_size);
        input.queue.push(wrong_camera);
        run_camera(
            17,
            0,
            pipeline,
            input,
            &stats,
            Duration::from_secs(20),
            |s| s.frames_invalid() >= 5,
        );
        assert_eq!(stats.frames_in(), 2);
        assert_eq!(stats.frames_invalid(), 2 + 3);
        assert_eq!(stats.frames_processed(), 0);
        assert_eq!(stats.observations_sent.load(Ordering::Relaxed), 0);
        let status = stats.status_report(17, Instant::now(), 1.0);
        assert_eq!(status.stamp_ns, 40, "newest capture stamp seen");
        assert_eq!(status.cameras[0].frames_in, 2);
        assert_eq!(status.cameras[0].frames_invalid, 5);
        assert_eq!(status.cameras[1].frames_in, 0);
    }

    #[test]
    fn the_status_counts_detections_by_corner_fit() {
        use shoal_sim_bridge::render::{render_fleet_view, Renderer};
        use shoal_sim_bridge::water::WaterPresets;
        use shoal_sim_bridge::world::{Formation, SwarmWorld};
        let fleet = paper_fleet();
        let vehicle = fleet.vehicle(10).unwrap().clone();
        let truth = SwarmWorld::new(&fleet, Formation::Line, 2.0, 1)
            .unwrap()
            .truth();
        let water = WaterPresets::builtin().get(0.5).unwrap();
        // Vehicle 10's starboard camera sees vehicle 15's marker 2 m away.
        let view = render_fleet_view(
            &mut Renderer::new(),
            &fleet,
            &truth,
            10,
            4,
            &water,
            0.0,
            0,
            1,
        )
        .unwrap();
        let stats = Arc::new(NodeStats::new(&vehicle.cameras));
        let pipeline =
            CameraPipeline::new(fleet.clone(), 10, 4, PipelineParams::default()).unwrap();
        let input = LocalInput::new(4);
        let mut frame = samples::camera_frame();
        frame.camera = 4;
        frame.info.model = vehicle.cameras[4].model;
        frame.data = view.image.data.clone();
        input.queue.push(frame);
        run_camera(
            10,
            4,
            pipeline,
            input,
            &stats,
            Duration::from_secs(60),
            |s| s.frames_processed() >= 1,
        );
        let cam = &stats.status_report(10, Instant::now(), 1.0).cameras[4];
        assert!(cam.detections >= 1, "{cam:?}");
        let by_fit: u64 = cam.corner_fits.iter().map(|(_, n)| n).sum();
        assert_eq!(
            by_fit, cam.detections,
            "every detection has its fit: {cam:?}"
        );
        assert!(
            cam.corner_fits.iter().all(|(name, n)| *n > 0
                && crate::detect::CornerFit::ALL
                    .iter()
                    .any(|f| f.name() == name)),
            "{cam:?}"
        );
    }
}
