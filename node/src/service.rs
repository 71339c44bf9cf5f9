//! The vehicle node service (`shoal node`): one named thread per camera,
//! each fed by a drop-oldest queue, running [`CameraPipeline`] and publishing
//! observations on the vehicle's key; a status thread publishing
//! [`NodeStatus`] and holding the vehicle's liveliness token.

use crate::mat::gray_as_mat;
use crate::pipeline::{CameraPipeline, PipelineError, PipelineParams};
use opencv::prelude::*;
use shoal_bus::{Bus, BusError, DropOldestQueue, Publisher, Subscription};
use shoal_proto::config::Fleet;
use shoal_proto::image::GrayImage;
use shoal_proto::messages::{
    CameraFrame, CameraInfo, CameraStatus, NodeStatus, Observation, PixelFormat, VehicleId,
};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Where a node's frames come from.
#[derive(Debug, Clone, PartialEq)]
pub enum Source {
    /// Camera frames published on the fleet's Zenoh keys (the simulator, or camera drivers).
    Zenoh,
    /// A folder of images (sorted by name) played as one camera at `rate_hz`.
    Images {
        dir: PathBuf,
        camera: u8,
        rate_hz: f64,
    },
    /// A video file played as one camera at its own frame rate.
    Video { path: PathBuf, camera: u8 },
    /// A live camera through OpenCV's VideoCapture (device index).
    Live { device: i32, camera: u8 },
}

#[derive(Debug, Clone)]
pub struct NodeConfig {
    pub fleet: Arc<Fleet>,
    pub vehicle: VehicleId,
    pub params: PipelineParams,
    pub source: Source,
    /// Frames queued per camera before the oldest is dropped.
    pub queue_capacity: usize,
    pub status_period: Duration,
}

#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    #[error("vehicle {0} is not in fleet {1:?}")]
    UnknownVehicle(VehicleId, String),
    #[error(transparent)]
    Bus(#[from] BusError),
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    #[error("source {0}: {1}")]
    Source(String, String),
    #[error("cannot start thread: {0}")]
    Thread(#[from] std::io::Error),
}

#[derive(Debug, Default)]
struct CameraCounters {
    frames_in: AtomicU64,
    frames_dropped: AtomicU64,
    frames_invalid: AtomicU64,
    detections: AtomicU64,
    /// Sums over the current status period: (frames, restore, detect, pose ms).
    period: Mutex<(u64, f64, f64, f64)>,
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
}

/// A running node; stops its threads when dropped or on [`NodeHandle::stop`].
pub struct NodeHandle {
    stop: Arc<AtomicBool>,
    threads: Vec<JoinHandle<()>>,
    stats: Arc<NodeStats>,
}

impl std::fmt::Debug for NodeHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NodeHandle")
            .field("threads", &self.threads.len())
            .finish()
    }
}

impl NodeHandle {
    pub fn stats(&self) -> &Arc<NodeStats> {
        &self.stats
    }

    /// Stop and wait for the threads (the liveliness token goes with them).
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

impl Drop for NodeHandle {
    fn drop(&mut self) {
        self.shutdown();
    }
}

enum FrameInput {
    Zenoh(Subscription<CameraFrame>),
    /// A local source's queue and its count of frames it could not decode.
    Local(DropOldestQueue<CameraFrame>, Arc<AtomicU64>),
}

impl FrameInput {
    fn next(&self, timeout: Duration) -> Option<CameraFrame> {
        match self {
            FrameInput::Zenoh(s) => s.recv_timeout(timeout).map(|r| r.msg),
            FrameInput::Local(q, _) => q.pop_timeout(timeout).ok(),
        }
    }
    fn dropped(&self) -> u64 {
        match self {
            FrameInput::Zenoh(s) => s.dropped(),
            FrameInput::Local(q, _) => q.dropped(),
        }
    }
    /// Frames refused before reaching the pipeline: undecodable or invalid
    /// envelopes (Zenoh), unreadable images or video frames (local).
    fn rejected(&self) -> u64 {
        match self {
            FrameInput::Zenoh(s) => s.stats().rejected(),
            FrameInput::Local(_, unreadable) => unreadable.load(Ordering::Relaxed),
        }
    }
    /// Envelopes that failed decoding or validation (counted in `messages_rejected`).
    fn messages_rejected(&self) -> u64 {
        match self {
            FrameInput::Zenoh(s) => s.stats().rejected(),
            FrameInput::Local(..) => 0,
        }
    }
}

/// Start a node on `bus`.
pub fn spawn(bus: &Bus, cfg: NodeConfig) -> Result<NodeHandle, NodeError> {
    let vehicle = cfg
        .fleet
        .vehicle(cfg.vehicle)
        .ok_or_else(|| NodeError::UnknownVehicle(cfg.vehicle, cfg.fleet.name.clone()))?
        .clone();
    let keys = cfg.fleet.keys();
    let stop = Arc::new(AtomicBool::new(false));
    let stats = Arc::new(NodeStats {
        cameras: vehicle
            .cameras
            .iter()
            .map(|c| (c.index, c.name.clone(), CameraCounters::default()))
            .collect(),
        ..Default::default()
    });
    let publisher: Arc<Publisher<Observation>> =
        Arc::new(bus.publisher(keys.observations(cfg.vehicle))?);
    let mut threads = Vec::new();

    // Inputs per camera.
    let mut inputs: Vec<Option<FrameInput>> = Vec::new();
    for cam in &vehicle.cameras {
        inputs.push(match &cfg.source {
            Source::Zenoh => Some(FrameInput::Zenoh(bus.subscribe::<CameraFrame>(
                &keys.frame(cfg.vehicle, cam.index),
                cfg.queue_capacity,
            )?)),
            Source::Images { camera, .. }
            | Source::Video { camera, .. }
            | Source::Live { camera, .. }
                if *camera == cam.index =>
            {
                Some(FrameInput::Local(
                    DropOldestQueue::new(cfg.queue_capacity),
                    Arc::default(),
                ))
            }
            _ => None,
        });
    }
    if let Some(cam_index) = local_camera(&cfg.source) {
        let Some(Some(FrameInput::Local(q, unreadable))) = inputs.get(cam_index as usize) else {
            return Err(NodeError::Source(
                format!("{:?}", cfg.source),
                format!("vehicle {} has no camera {cam_index}", cfg.vehicle),
            ));
        };
        let cam = &vehicle.cameras[cam_index as usize];
        let info = CameraInfo {
            model: cam.model,
            body_from_camera: cam.body_from_camera,
        };
        threads.push(crate::source::spawn_reader(
            cfg.source.clone(),
            cfg.vehicle,
            info,
            q.clone(),
            unreadable.clone(),
            stop.clone(),
        )?);
    }

    for (i, input) in inputs.into_iter().enumerate() {
        let Some(input) = input else { continue };
        let mut pipeline =
            CameraPipeline::new(cfg.fleet.clone(), cfg.vehicle, i as u8, cfg.params.clone())?;
        let (stop, stats, publisher) = (stop.clone(), stats.clone(), publisher.clone());
        let name = format!("cam-{}-{}", cfg.vehicle, pipeline.camera().name);
        let expected = (
            pipeline.camera().model.width,
            pipeline.camera().model.height,
        );
        threads.push(std::thread::Builder::new().name(name).spawn(move || {
            let counters = &stats.cameras[i].2;
            // Frames this thread refused (wrong format or size, pipeline
            // errors); `frames_invalid` reports them plus those the input
            // refused before they got here.
            let mut refused_here = 0u64;
            let mut rejected_seen = 0u64;
            while !stop.load(Ordering::Relaxed) {
                counters.frames_dropped.store(input.dropped(), Ordering::Relaxed);
                counters
                    .frames_invalid
                    .store(refused_here + input.rejected(), Ordering::Relaxed);
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
                stats.newest_stamp_ns.fetch_max(frame.stamp_ns, Ordering::Relaxed);
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
                    .and_then(|mat| pipeline.process(&mat, frame.stamp_ns, frame.seq).map_err(|e| e.to_string()));
                match result {
                    Ok(out) => {
                        counters.detections.fetch_add(out.detections as u64, Ordering::Relaxed);
                        for reason in &out.pose_failures {
                            tracing::debug!("camera {i}: {reason}");
                        }
                        for obs in &out.observations {
                            match publisher.put(obs) {
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
        })?);
    }

    // Status + liveliness.
    let status_pub: Publisher<NodeStatus> = bus.publisher(keys.status(cfg.vehicle))?;
    let token = bus.liveliness_token(keys.alive(cfg.vehicle))?;
    {
        let (stop, stats) = (stop.clone(), stats.clone());
        let (vehicle_id, period) = (cfg.vehicle, cfg.status_period);
        // The node's threads own its session: it lives as long as they do.
        let bus = bus.clone();
        threads.push(
            std::thread::Builder::new()
                .name(format!("status-{vehicle_id}"))
                .spawn(move || {
                    let _session = bus;
                    let _token = token;
                    let started = Instant::now();
                    let mut last = Instant::now();
                    while !stop.load(Ordering::Relaxed) {
                        std::thread::sleep(Duration::from_millis(50));
                        if last.elapsed() < period {
                            continue;
                        }
                        let secs = last.elapsed().as_secs_f64();
                        last = Instant::now();
                        let stamp = stats.newest_stamp_ns.load(Ordering::Relaxed);
                        let status = status_report(vehicle_id, &stats, started, secs, stamp);
                        if let Err(e) = status_pub.put(&status) {
                            tracing::warn!("publishing status: {e}");
                        }
                    }
                })?,
        );
    }
    Ok(NodeHandle {
        stop,
        threads,
        stats,
    })
}

fn status_report(
    vehicle: VehicleId,
    stats: &NodeStats,
    started: Instant,
    period_s: f64,
    stamp_ns: u64,
) -> NodeStatus {
    let cameras = stats
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
            }
        })
        .collect();
    NodeStatus {
        vehicle,
        stamp_ns,
        uptime_s: started.elapsed().as_secs_f64(),
        cameras,
        observations_sent: stats.observations_sent.load(Ordering::Relaxed),
        messages_rejected: stats.messages_rejected.load(Ordering::Relaxed),
    }
}

fn local_camera(source: &Source) -> Option<u8> {
    match source {
        Source::Zenoh => None,
        Source::Images { camera, .. }
        | Source::Video { camera, .. }
        | Source::Live { camera, .. } => Some(*camera),
    }
}
