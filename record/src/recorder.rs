//! The writing half of a recording: [`Recording`] writes an MCAP log on its
//! own thread from bounded drop-oldest queues of received wire messages
//! (drops are counted and reported in the [`RecordSummary`], never silent).
//! The Zenoh subscriptions that fill the queues are
//! `shoal_services::recorder`.

use crate::foxglove;
use crate::writer::{ChannelCount, LogWriter, WriterOptions};
use crate::RecordError;
use proto::clock::{Clock, WallClock};
use proto::codec::{self, HEADER_LEN};
use proto::config::Fleet;
use proto::queue::{DropOldestQueue, PopError};
use proto::{FleetMap, KeyKind, MessageKind, NodeStatus, Observation, SimTruth};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// What and how to record.
#[derive(Debug, Clone)]
pub struct RecordOptions {
    /// Record camera frames (raw and as PNG images). They dominate the file size.
    pub frames: bool,
    /// Keep at most this many frames per second per camera (`None`: every frame).
    pub frame_rate_limit_hz: Option<f64>,
    /// Of the frames kept, convert at most this many per second per camera to
    /// Foxglove PNG images (`None`: all). PNG encoding costs ~50 ms per
    /// 1440x1080 frame, far more than writing the raw frame.
    pub image_rate_limit_hz: Option<f64>,
    /// Frames buffered before the writer (each ~1.5 MB at 1440x1080), separately from `queue_capacity`.
    pub frame_queue_capacity: usize,
    /// Also write Foxglove well-known-schema channels.
    pub foxglove: bool,
    /// A ROS 2 log instead (MCAP profile `ros2`, `docs/ros2.md`): only the
    /// ROS 2 topics that `--ros2` publishes (fused poses, `/tf`, observations,
    /// `/diagnostics`), CDR with `ros2msg` schemas, so `ros2 bag`, `rosbags`
    /// and Rerun read it. No wire or Foxglove channels and no frames: shoal's
    /// own tools (`log info`, `replay`, `fuse`) need a shoal-profile log.
    pub ros2_profile: bool,
    /// Messages buffered between the Zenoh callback and the writer thread.
    pub queue_capacity: usize,
    /// Close the current chunk at least this often, so a killed recorder loses at most this much.
    pub flush_interval: Duration,
    pub writer: WriterOptions,
    /// Water attenuation coefficient of the trial (file metadata), if known.
    pub water_c_per_m: Option<f64>,
    /// The fleet file's text (attached to the log); `None`: read from `fleet.source`.
    pub fleet_toml: Option<String>,
    /// Extra `key = value` pairs for the file's metadata record.
    pub extra_metadata: BTreeMap<String, String>,
}

impl Default for RecordOptions {
    fn default() -> Self {
        Self {
            frames: false,
            frame_rate_limit_hz: Some(2.0),
            image_rate_limit_hz: Some(1.0),
            frame_queue_capacity: 128,
            foxglove: true,
            ros2_profile: false,
            queue_capacity: 4096,
            flush_interval: Duration::from_secs(1),
            writer: WriterOptions::default(),
            water_c_per_m: None,
            fleet_toml: None,
            extra_metadata: BTreeMap::new(),
        }
    }
}

/// What a recording wrote.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct RecordSummary {
    pub path: PathBuf,
    /// Per channel (Zenoh key or Foxglove topic).
    pub channels: BTreeMap<String, ChannelCount>,
    /// Wire messages received from Zenoh and written.
    pub wire_messages: u64,
    /// Dropped in the queue because the writer fell behind.
    pub dropped: u64,
    /// Frames skipped by the per-camera rate limit.
    pub frames_rate_limited: u64,
    /// Messages whose envelope did not decode (kept raw, no Foxglove twin).
    pub undecodable: u64,
    /// Foxglove conversions that failed (e.g. PNG encoding).
    pub conversion_errors: u64,
    /// PNG images not made because the image thread fell behind (the raw frames are all written).
    pub images_dropped: u64,
    pub file_bytes: u64,
    pub wall_time_s: f64,
    /// CPU time of the writer thread, seconds (Linux; 0 elsewhere); PNG encoding runs on its own thread.
    pub writer_cpu_s: f64,
}

/// Live counters of a running recorder.
#[derive(Debug, Default)]
pub struct RecorderStats {
    pub written: AtomicU64,
    pub frames_rate_limited: AtomicU64,
    pub undecodable: AtomicU64,
    pub conversion_errors: AtomicU64,
}

/// The queue of liveliness changes a recording writes (Foxglove channel):
/// the token's key, whether it appeared, and the UNIX time it was heard.
pub type LivelinessEvents = DropOldestQueue<(String, bool, u64)>;

/// A log being written on its own thread from queues of received wire
/// messages, `(key, envelope bytes)` (see [`Recording::start`]); what fills
/// the queues (Zenoh subscriptions, in `shoal_services::recorder`) is not
/// this crate's business. [`Recording::stop`] finishes the file.
pub struct Recording {
    stop: Arc<AtomicBool>,
    queues: Vec<DropOldestQueue<(String, Vec<u8>)>>,
    thread: Option<JoinHandle<Result<RecordSummary, RecordError>>>,
    stats: Arc<RecorderStats>,
}

impl std::fmt::Debug for Recording {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recording")
            .field("stats", &self.stats)
            .finish()
    }
}

/// Create the log file at `path` for `fleet`, with its file-level metadata
/// and the fleet file attached (the first step of a recording).
pub fn create_log(
    fleet: &Fleet,
    path: &Path,
    opts: &RecordOptions,
) -> Result<LogWriter, RecordError> {
    let start = WallClock.now_ns();
    let fleet_toml = match &opts.fleet_toml {
        Some(t) => Some(t.clone()),
        None => std::fs::read_to_string(&fleet.source).ok(),
    };
    if fleet_toml.is_none() {
        tracing::warn!(
            "recorder: fleet file {} unreadable; the log will not carry it",
            fleet.source.display()
        );
    }
    let mut writer_options = opts.writer.clone();
    if opts.ros2_profile {
        writer_options.profile = crate::writer::ROS2_PROFILE;
    }
    LogWriter::create(
        path,
        &writer_options,
        &file_metadata(fleet, opts, start),
        fleet_toml.as_deref(),
        start,
    )
}

/// The key expressions a recording of `keys`' fleet listens to, each with the
/// capacity of its queue; the first (observations) is the one the writer
/// waits on. Frames get their own, smaller queue: 4096 frames would be 6 GB.
pub fn subscriptions(keys: &proto::Keys, opts: &RecordOptions) -> Vec<(String, usize)> {
    let mut exprs: Vec<(String, usize)> = [
        keys.all_observations(),
        // `map/**` also matches `map` itself (`**` is zero or more chunks).
        keys.all_maps(),
        keys.all_status(),
        keys.all_commands(),
        keys.all_nav(),
        keys.truth(),
    ]
    .into_iter()
    .map(|k| (k, opts.queue_capacity))
    .collect();
    if opts.frames {
        exprs.push((keys.all_frames(), opts.frame_queue_capacity));
    }
    exprs
}

impl Recording {
    /// Start writing into `writer` (from [`create_log`]) what arrives in
    /// `queues` (one per entry of [`subscriptions`], in that order) and, with
    /// Foxglove channels on, the liveliness changes in `liveliness`.
    pub fn start(
        mut writer: LogWriter,
        fleet: Arc<Fleet>,
        path: &Path,
        opts: RecordOptions,
        queues: Vec<DropOldestQueue<(String, Vec<u8>)>>,
        liveliness: LivelinessEvents,
    ) -> Result<Recording, RecordError> {
        let keys = fleet.keys();
        let stop = Arc::new(AtomicBool::new(false));
        let stats = Arc::new(RecorderStats::default());
        let (stop2, stats2, qs) = (stop.clone(), stats.clone(), queues.clone());
        let (liveliness2, keys2) = (liveliness, keys);
        let path_buf = path.to_path_buf();
        let thread = std::thread::Builder::new()
            .name("recorder".into())
            .spawn(move || {
                let started = Instant::now();
                let cpu0 = thread_cpu_s();
                let mut conv = Converter::new(fleet.clone(), opts.clone());
                let png_jobs: DropOldestQueue<PngJob> = DropOldestQueue::new(8);
                let png_done: DropOldestQueue<PngDone> = DropOldestQueue::new(32);
                let png_thread = if opts.frames && opts.foxglove {
                    conv.png_jobs = Some(png_jobs.clone());
                    let (j, d, st) = (png_jobs.clone(), png_done.clone(), stats2.clone());
                    Some(
                        std::thread::Builder::new()
                            .name("recorder-png".into())
                            .spawn(move || png_worker(fleet, j, d, st))
                            .map_err(RecordError::Thread)?,
                    )
                } else {
                    None
                };
                let write_images = |writer: &mut LogWriter| -> Result<(), RecordError> {
                    for (m, log_time, publish_time) in png_done.drain() {
                        writer.write_foxglove(&m, log_time, publish_time)?;
                    }
                    Ok(())
                };
                let mut last_flush = Instant::now();
                loop {
                    let first = match qs[0].pop_timeout(Duration::from_millis(20)) {
                        Ok(m) => Some(m),
                        Err(PopError::Timeout) => None,
                        Err(PopError::Closed) => None,
                    };
                    let mut batch: Vec<(String, Vec<u8>)> = first.into_iter().collect();
                    for q in &qs {
                        batch.extend(q.drain());
                    }
                    let now = WallClock.now_ns();
                    for (key, bytes) in batch {
                        conv.write(&mut writer, &key, &bytes, now, &stats2)?;
                    }
                    for (key, alive, heard_ns) in liveliness2.drain() {
                        if opts.ros2_profile {
                            continue;
                        }
                        let vehicle = match keys2.parse(&key) {
                            Ok(KeyKind::Alive { vehicle }) => Some(vehicle),
                            _ => None,
                        };
                        let m = crate::foxglove::liveliness_message(&key, vehicle, alive, heard_ns);
                        writer.write_foxglove(&m, heard_ns, heard_ns)?;
                    }
                    write_images(&mut writer)?;
                    if last_flush.elapsed() >= opts.flush_interval {
                        writer.flush()?;
                        last_flush = Instant::now();
                    }
                    if stop2.load(Ordering::Relaxed) && qs.iter().all(|q| q.is_empty()) {
                        break;
                    }
                }
                png_jobs.close();
                if let Some(t) = png_thread {
                    t.join().map_err(|_| RecordError::WriterPanicked)?;
                }
                write_images(&mut writer)?;
                let channels = writer.finish()?;
                let file_bytes = std::fs::metadata(&path_buf).map(|m| m.len()).unwrap_or(0);
                Ok(RecordSummary {
                    path: path_buf,
                    channels,
                    wire_messages: stats2.written.load(Ordering::Relaxed),
                    dropped: qs.iter().map(|q| q.dropped()).sum(),
                    frames_rate_limited: stats2.frames_rate_limited.load(Ordering::Relaxed),
                    undecodable: stats2.undecodable.load(Ordering::Relaxed),
                    conversion_errors: stats2.conversion_errors.load(Ordering::Relaxed),
                    images_dropped: png_jobs.dropped() + png_done.dropped(),
                    file_bytes,
                    wall_time_s: started.elapsed().as_secs_f64(),
                    writer_cpu_s: thread_cpu_s() - cpu0,
                })
            })
            .map_err(RecordError::Thread)?;
        Ok(Recording {
            stop,
            queues,
            thread: Some(thread),
            stats,
        })
    }

    /// Messages dropped so far because the writer fell behind.
    pub fn dropped(&self) -> u64 {
        self.queues.iter().map(|q| q.dropped()).sum()
    }
    pub fn stats(&self) -> &RecorderStats {
        &self.stats
    }
    /// Whether the writer thread ended early (an I/O error); `stop` returns it.
    pub fn failed(&self) -> bool {
        self.thread.as_ref().is_none_or(|t| t.is_finished())
    }

    /// Write what is queued, close the file with its summary.
    pub fn stop(mut self) -> Result<RecordSummary, RecordError> {
        self.finish()
    }

    /// As [`Recording::stop`], for an owner that cannot give the recording
    /// away; a second call is [`RecordError::AlreadyStopped`]. Whoever fills
    /// the queues should have stopped first.
    pub fn finish(&mut self) -> Result<RecordSummary, RecordError> {
        self.stop.store(true, Ordering::Relaxed);
        for q in &self.queues {
            q.close();
        }
        match self.thread.take() {
            Some(t) => t.join().map_err(|_| RecordError::WriterPanicked)?,
            None => Err(RecordError::AlreadyStopped),
        }
    }
}

impl Drop for Recording {
    fn drop(&mut self) {
        if self.thread.is_some() {
            if let Err(e) = self.finish() {
                tracing::error!("recorder: {e}");
            }
        }
    }
}

/// The file-level metadata of a recording.
pub fn file_metadata(
    fleet: &Fleet,
    opts: &RecordOptions,
    start_unix_ns: u64,
) -> BTreeMap<String, String> {
    let mut m = opts.extra_metadata.clone();
    m.insert("fleet".into(), fleet.name.clone());
    m.insert("fleet_file".into(), fleet.source.display().to_string());
    m.insert(
        "reference_vehicle".into(),
        fleet.reference_vehicle.to_string(),
    );
    m.insert(
        "vehicles".into(),
        fleet
            .vehicles
            .iter()
            .map(|v| v.id.to_string())
            .collect::<Vec<_>>()
            .join(","),
    );
    if let Some(c) = opts.water_c_per_m {
        m.insert("water_c_per_m".into(), c.to_string());
    }
    m.insert(
        "software".into(),
        format!("shoal {}", env!("CARGO_PKG_VERSION")),
    );
    m.insert(
        "wire_schema_version".into(),
        codec::SCHEMA_VERSION.to_string(),
    );
    m.insert("start_time_unix_ns".into(), start_unix_ns.to_string());
    m.insert("frames".into(), opts.frames.to_string());
    if let Some(r) = opts.frame_rate_limit_hz {
        m.insert("frame_rate_limit_hz".into(), r.to_string());
    }
    if let Some(r) = opts.image_rate_limit_hz {
        m.insert("image_rate_limit_hz".into(), r.to_string());
    }
    m
}

/// The message kind in an envelope header, if the header is shoal's.
pub fn envelope_kind(bytes: &[u8]) -> Option<MessageKind> {
    if bytes.len() < HEADER_LEN || bytes[..4] != codec::MAGIC {
        return None;
    }
    MessageKind::from_u16(u16::from_le_bytes([bytes[6], bytes[7]]))
}

/// Turns received wire messages into log entries (raw + Foxglove).
pub(crate) struct Converter {
    fleet: Arc<Fleet>,
    opts: RecordOptions,
    keys: proto::Keys,
    last_frame_ns: HashMap<(u32, u8), u64>,
    last_image_ns: HashMap<(u32, u8), u64>,
    /// When set, PNG images are encoded on the image thread instead of inline.
    png_jobs: Option<DropOldestQueue<PngJob>>,
    /// ROS 2 topic names of the fleet (the ROS 2 profile).
    ros2_names: proto::ros2::Ros2Names,
}

/// A frame waiting for its PNG image.
pub(crate) struct PngJob {
    envelope: Vec<u8>,
    log_time: u64,
}

/// A finished Foxglove image with its log and publish times.
pub(crate) type PngDone = (foxglove::FoxgloveMessage, u64, u64);

/// The image thread: PNG-encodes frames off the writer thread, so the raw
/// copy is never held up by visualization (the second core does the PNG).
/// Under overload its bounded queues drop the oldest images, counted.
fn png_worker(
    fleet: Arc<Fleet>,
    jobs: DropOldestQueue<PngJob>,
    done: DropOldestQueue<PngDone>,
    stats: Arc<RecorderStats>,
) {
    loop {
        match jobs.pop_timeout(Duration::from_millis(100)) {
            Ok(job) => {
                let Some(f) = foxglove::FrameView::parse(&job.envelope) else {
                    continue;
                };
                match foxglove::camera_image(&fleet, &f) {
                    Ok(m) => {
                        done.push((m, job.log_time, f.stamp_ns));
                    }
                    Err(e) => {
                        stats.conversion_errors.fetch_add(1, Ordering::Relaxed);
                        tracing::debug!(
                            "recorder: PNG of vehicle {} camera {}: {e}",
                            f.vehicle,
                            f.camera
                        );
                    }
                }
            }
            Err(PopError::Timeout) => {}
            Err(PopError::Closed) => return,
        }
    }
}

/// Whether `stamp_ns` is at least `1/rate` after the last kept stamp of `cam` (and remember it if so).
fn rate_allows(
    last: &mut HashMap<(u32, u8), u64>,
    cam: (u32, u8),
    stamp_ns: u64,
    rate_hz: Option<f64>,
) -> bool {
    let Some(rate) = rate_hz.filter(|r| *r > 0.0) else {
        return true;
    };
    let min_gap = (1e9 / rate) as u64;
    if let Some(&prev) = last.get(&cam) {
        if stamp_ns >= prev && stamp_ns - prev < min_gap {
            return false;
        }
    }
    last.insert(cam, stamp_ns);
    true
}

impl Converter {
    pub(crate) fn new(fleet: Arc<Fleet>, opts: RecordOptions) -> Converter {
        let keys = fleet.keys();
        let ros2_names = proto::ros2::Ros2Names::new(&fleet.name);
        Converter {
            ros2_names,
            fleet,
            opts,
            keys,
            last_frame_ns: HashMap::new(),
            last_image_ns: HashMap::new(),
            png_jobs: None,
        }
    }

    /// Write one wire message received at `log_time` (UNIX ns) on `key`.
    pub(crate) fn write(
        &mut self,
        w: &mut LogWriter,
        key: &str,
        bytes: &[u8],
        log_time: u64,
        stats: &RecorderStats,
    ) -> Result<(), RecordError> {
        if self.opts.ros2_profile {
            return self.write_ros2(w, bytes, log_time, stats);
        }
        let kind = envelope_kind(bytes);
        let key_kind = self.keys.parse(key).ok();
        let mut fox = Vec::new();
        let mut publish_time = log_time;
        let mut undecodable = false;
        match kind {
            Some(MessageKind::CameraFrame) => {
                if !self.opts.frames {
                    return Ok(());
                }
                match foxglove::FrameView::parse(bytes) {
                    Some(f) => {
                        publish_time = f.stamp_ns;
                        let cam = (f.vehicle, f.camera);
                        if !rate_allows(
                            &mut self.last_frame_ns,
                            cam,
                            f.stamp_ns,
                            self.opts.frame_rate_limit_hz,
                        ) {
                            stats.frames_rate_limited.fetch_add(1, Ordering::Relaxed);
                            return Ok(());
                        }
                        if self.opts.foxglove
                            && rate_allows(
                                &mut self.last_image_ns,
                                cam,
                                f.stamp_ns,
                                self.opts.image_rate_limit_hz,
                            )
                        {
                            if let Some(jobs) = &self.png_jobs {
                                jobs.push(PngJob {
                                    envelope: bytes.to_vec(),
                                    log_time,
                                });
                            } else {
                                match foxglove::camera_image(&self.fleet, &f) {
                                    Ok(m) => fox.push(m),
                                    Err(e) => {
                                        stats.conversion_errors.fetch_add(1, Ordering::Relaxed);
                                        tracing::debug!("recorder: PNG of {key}: {e}");
                                    }
                                }
                            }
                        }
                    }
                    None => undecodable = true,
                }
            }
            Some(MessageKind::Observation) => match codec::decode::<Observation>(bytes) {
                Ok(o) => {
                    publish_time = o.stamp_ns;
                    fox = foxglove::observation(&self.fleet, &o);
                }
                Err(_) => undecodable = true,
            },
            Some(MessageKind::FleetMap) => match codec::decode::<FleetMap>(bytes) {
                Ok(m) => {
                    publish_time = m.stamp_ns;
                    fox = foxglove::fleet_map(&self.fleet, &m);
                }
                Err(_) => undecodable = true,
            },
            Some(MessageKind::SimTruth) => match codec::decode::<SimTruth>(bytes) {
                Ok(s) => {
                    publish_time = s.stamp_ns;
                    fox = foxglove::sim_truth(&self.fleet, &s);
                }
                Err(_) => undecodable = true,
            },
            Some(MessageKind::NodeStatus) => match codec::decode::<NodeStatus>(bytes) {
                Ok(s) => {
                    publish_time = s.stamp_ns;
                    fox = foxglove::node_status(&s);
                }
                Err(_) => undecodable = true,
            },
            Some(MessageKind::VehicleCommand) => {
                match codec::decode::<proto::VehicleCommand>(bytes) {
                    Ok(c) => publish_time = c.stamp_ns,
                    Err(_) => undecodable = true,
                }
            }
            Some(MessageKind::NavState) => match codec::decode::<proto::NavState>(bytes) {
                Ok(n) => publish_time = n.stamp_ns,
                Err(_) => undecodable = true,
            },
            Some(MessageKind::LinkPacket) => {
                match codec::decode::<proto::compact::LinkPacket>(bytes)
                    .ok()
                    .and_then(|p| p.content().ok())
                {
                    Some(c) => publish_time = c.stamp_ns(),
                    None => undecodable = true,
                }
            }
            None => undecodable = true,
        }
        if matches!(key_kind, Some(KeyKind::Frame { .. })) && !self.opts.frames {
            return Ok(());
        }
        if undecodable {
            stats.undecodable.fetch_add(1, Ordering::Relaxed);
        }
        w.write_wire(key, kind, bytes, log_time, publish_time)?;
        stats.written.fetch_add(1, Ordering::Relaxed);
        if self.opts.foxglove {
            for m in fox {
                w.write_foxglove(&m, log_time, publish_time)?;
            }
        }
        Ok(())
    }
}

impl Converter {
    /// The ROS 2 profile: a map, observation or node status as the ROS 2
    /// messages `--ros2` publishes for it; other kinds are not written.
    fn write_ros2(
        &mut self,
        w: &mut LogWriter,
        bytes: &[u8],
        log_time: u64,
        stats: &RecorderStats,
    ) -> Result<(), RecordError> {
        use proto::ros2::{self as ros, msgs::RosMessage};
        let mut out: Vec<(String, proto::ros2::msgs::RosType, Vec<u8>, u64)> = Vec::new();
        let mut put = |topic: &str, ty, cdr, stamp| out.push((topic.to_string(), ty, cdr, stamp));
        let undecodable = match envelope_kind(bytes) {
            Some(MessageKind::FleetMap) => match codec::decode::<FleetMap>(bytes) {
                Ok(m) => {
                    for (topic, msg) in ros::map_poses(&m, &self.ros2_names) {
                        put(&topic, msg_type(&msg), msg.to_cdr(), m.stamp_ns);
                    }
                    let tf = ros::map_tf(&m);
                    if !tf.transforms.is_empty() {
                        put(ros::Ros2Names::TF, msg_type(&tf), tf.to_cdr(), m.stamp_ns);
                    }
                    let d = ros::map_diagnostics(&m);
                    put(
                        ros::Ros2Names::DIAGNOSTICS,
                        msg_type(&d),
                        d.to_cdr(),
                        m.stamp_ns,
                    );
                    false
                }
                Err(_) => true,
            },
            Some(MessageKind::Observation) => match codec::decode::<Observation>(bytes) {
                Ok(o) => {
                    if let Some((topic, msg)) = ros::observation_pose(&o, &self.ros2_names) {
                        put(&topic, msg_type(&msg), msg.to_cdr(), o.stamp_ns);
                    }
                    false
                }
                Err(_) => true,
            },
            Some(MessageKind::NodeStatus) => match codec::decode::<NodeStatus>(bytes) {
                Ok(s) => {
                    let d = ros::node_diagnostics(&s);
                    put(
                        ros::Ros2Names::DIAGNOSTICS,
                        msg_type(&d),
                        d.to_cdr(),
                        s.stamp_ns,
                    );
                    false
                }
                Err(_) => true,
            },
            Some(_) => false,
            None => true,
        };
        if undecodable {
            stats.undecodable.fetch_add(1, Ordering::Relaxed);
        }
        for (topic, ty, cdr, stamp) in out {
            w.write_ros2(&topic, &ty, &cdr, log_time, stamp)?;
            stats.written.fetch_add(1, Ordering::Relaxed);
        }
        Ok(())
    }
}

fn msg_type<M: proto::ros2::msgs::RosMessage>(_: &M) -> proto::ros2::msgs::RosType {
    M::TYPE
}

/// CPU time of the calling thread, seconds (Linux `/proc/thread-self/stat`; 0 elsewhere).
pub fn thread_cpu_s() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/thread-self/stat") else {
        return 0.0;
    };
    // Fields after the command name (which is in parentheses and may contain spaces).
    let Some(rest) = stat.rsplit_once(')').map(|(_, r)| r) else {
        return 0.0;
    };
    let f: Vec<&str> = rest.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the full line: 12 and 13 after the name.
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (ticks(11) + ticks(12)) / 100.0
}
