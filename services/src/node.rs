//! The vehicle node service (`shoal node`): one named thread per camera
//! (`shoal_node::vehicle`), each fed by a drop-oldest queue — the camera's
//! Zenoh subscription, or a local source's reader — and publishing
//! observations on the vehicle's key; a status thread publishing
//! [`NodeStatus`] and holding the vehicle's liveliness token.

use shoal_bus::{Bus, BusError, Publisher, Subscription};
use shoal_node::pipeline::{CameraPipeline, PipelineError, PipelineParams};
use shoal_node::source::{LocalSource, SourceError};
use shoal_node::vehicle::{spawn_camera, FrameInput, LocalInput};
use shoal_proto::config::Fleet;
use shoal_proto::messages::{CameraFrame, CameraInfo, NodeStatus, Observation, VehicleId};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

pub use shoal_node::vehicle::NodeStats;

/// Where a node's frames come from.
#[derive(Debug, Clone, PartialEq)]
pub enum Source {
    /// Camera frames published on the fleet's Zenoh keys (the simulator, or camera drivers).
    Zenoh,
    /// A folder of images, a video file or a live camera, played as one of
    /// the vehicle's cameras.
    Local(LocalSource),
    /// A ROS 2 image topic over `rmw_zenoh`, played as one of the vehicle's cameras.
    Ros2(crate::ros2::Ros2ImageSource),
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
    #[error("source {what}: vehicle {vehicle} has no camera {camera}")]
    NoSuchCamera {
        what: String,
        vehicle: VehicleId,
        camera: u8,
    },
    #[error(transparent)]
    Bus(#[from] BusError),
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    #[error(transparent)]
    Source(#[from] SourceError),
    #[error("cannot start thread: {0}")]
    Thread(#[from] std::io::Error),
}

/// How long a node's stop waits for a local source's thread, which may be
/// blocked in a read of a stream gone silent (OpenCV 4.6's GStreamer
/// backend has no read timeout): it is then left to end with the process.
pub const SOURCE_STOP_WAIT: Duration = Duration::from_secs(2);

/// A running node; stops its threads when dropped or on [`NodeHandle::stop`].
pub struct NodeHandle {
    stop: Arc<AtomicBool>,
    threads: Vec<JoinHandle<()>>,
    /// A local source's reader, joined within [`SOURCE_STOP_WAIT`].
    source_thread: Option<JoinHandle<()>>,
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

    /// Tell the threads to stop without waiting for them: stopping several
    /// nodes, each told first and then joined, takes one poll of their
    /// inputs in all, not one each.
    pub fn request_stop(&self) {
        self.stop.store(true, Ordering::Relaxed);
    }

    /// Stop and wait for the threads (the liveliness token goes with them).
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for t in self.threads.drain(..) {
            shoal_bus::join_reporting(t);
        }
        if let Some(t) = self.source_thread.take() {
            shoal_node::source::join_within(t, SOURCE_STOP_WAIT);
        }
    }
}

impl Drop for NodeHandle {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// One camera's frames from its Zenoh key.
struct ZenohFrames(Subscription<CameraFrame>);

impl FrameInput for ZenohFrames {
    fn next(&self, timeout: Duration) -> Option<CameraFrame> {
        self.0.recv_timeout(timeout).map(|r| r.msg)
    }
    fn dropped(&self) -> u64 {
        self.0.dropped()
    }
    fn rejected(&self) -> u64 {
        self.0.stats().rejected()
    }
    fn messages_rejected(&self) -> u64 {
        self.0.stats().rejected()
    }
}

/// Inputs per camera (`None`: the camera gets no frames from this source),
/// and the local source's feed with the camera it plays.
type CameraInputs = (
    Vec<Option<Box<dyn FrameInput>>>,
    Option<(LocalInput, usize)>,
);

fn camera_inputs(
    bus: &Bus,
    cfg: &NodeConfig,
    vehicle: &shoal_proto::config::Vehicle,
) -> Result<CameraInputs, NodeError> {
    let keys = cfg.fleet.keys();
    let mut inputs: Vec<Option<Box<dyn FrameInput>>> = Vec::new();
    let mut local_feed: Option<(LocalInput, usize)> = None;
    for (i, cam) in vehicle.cameras.iter().enumerate() {
        inputs.push(match &cfg.source {
            Source::Zenoh => Some(Box::new(ZenohFrames(bus.subscribe::<CameraFrame>(
                &keys.frame(cfg.vehicle, cam.index),
                cfg.queue_capacity,
            )?))),
            Source::Local(local) if local.camera() == cam.index => {
                let input = LocalInput::new(cfg.queue_capacity);
                local_feed = Some((input.clone(), i));
                Some(Box::new(input))
            }
            Source::Local(_) => None,
            Source::Ros2(r) if r.camera == cam.index => {
                let info = CameraInfo {
                    model: cam.model,
                    body_from_camera: cam.body_from_camera,
                };
                Some(Box::new(crate::ros2::Ros2Frames::subscribe(
                    bus,
                    r,
                    cfg.vehicle,
                    info,
                    cfg.queue_capacity,
                )?))
            }
            Source::Ros2(_) => None,
        });
    }
    if let Source::Ros2(r) = &cfg.source {
        if !vehicle.cameras.iter().any(|c| c.index == r.camera) {
            return Err(NodeError::NoSuchCamera {
                what: format!("ROS 2 topic {}", r.topic),
                vehicle: cfg.vehicle,
                camera: r.camera,
            });
        }
    }
    Ok((inputs, local_feed))
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
    let stats = Arc::new(NodeStats::new(&vehicle.cameras));
    let publisher: Arc<Publisher<Observation>> =
        Arc::new(bus.publisher(keys.observations(cfg.vehicle))?);
    let mut threads = Vec::new();
    let mut source_thread = None;

    let (inputs, local_feed) = camera_inputs(bus, &cfg, &vehicle)?;
    if let Source::Local(local) = &cfg.source {
        let Some((feed, i)) = local_feed else {
            return Err(NodeError::NoSuchCamera {
                what: local.describe(),
                vehicle: cfg.vehicle,
                camera: local.camera(),
            });
        };
        let cam = &vehicle.cameras[i];
        let info = CameraInfo {
            model: cam.model,
            body_from_camera: cam.body_from_camera,
        };
        source_thread = Some(shoal_node::source::spawn_reader(
            local.clone(),
            cfg.vehicle,
            info,
            feed.queue,
            feed.counters,
            stop.clone(),
        )?);
    }

    for (i, input) in inputs.into_iter().enumerate() {
        let Some(input) = input else { continue };
        let pipeline =
            CameraPipeline::new(cfg.fleet.clone(), cfg.vehicle, i as u8, cfg.params.clone())?;
        let publisher = publisher.clone();
        threads.push(spawn_camera(
            cfg.vehicle,
            i,
            pipeline,
            input,
            move |obs: &Observation| publisher.put(obs),
            stats.clone(),
            stop.clone(),
        )?);
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
                        let mut status = stats.status_report(vehicle_id, started, secs);
                        status.clock = shoal_node::clock::kernel_clock_sync();
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
        source_thread,
        stats,
    })
}
