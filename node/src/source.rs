//! Frame sources on the vehicle itself: a folder of images, a video file, a
//! live camera (OpenCV `VideoCapture`: a device index, a V4L2 device, or a
//! GStreamer pipeline). Each runs on its own named thread and feeds one
//! camera's drop-oldest queue (a [`crate::vehicle::LocalInput`]), with its
//! counters: undecodable frames, frames the source's timing shows it never
//! delivered, reconnections, and where the stamps came from
//! ([`StampSource`], `docs/time.md`). Frames that arrive over Zenoh are the
//! node service's business (`shoal_services::node`).

mod live;

pub use live::{
    gst_pipeline_problem, GapCounter, PipelineClock, StampClock, INITIAL_BACKOFF, MAX_BACKOFF,
    MAX_SOURCE_DISAGREEMENT_NS,
};

use crate::mat::mat_to_gray;
use crate::vehicle::SourceCounters;
use opencv::core::Mat;
use opencv::imgproc;
use opencv::prelude::*;
use shoal_proto::image::GrayImage;
use shoal_proto::messages::{CameraFrame, CameraInfo, PixelFormat, StampSource, VehicleId};
use shoal_proto::queue::DropOldestQueue;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

/// A frame source on this machine, played as one of the vehicle's cameras.
#[derive(Debug, Clone, PartialEq)]
pub enum LocalSource {
    /// A folder of images (sorted by name) played as one camera at `rate_hz`.
    Images {
        dir: PathBuf,
        camera: u8,
        rate_hz: f64,
    },
    /// A video file played as one camera at its own frame rate.
    Video { path: PathBuf, camera: u8 },
    /// A live camera through OpenCV's VideoCapture (device index, any backend).
    Live { device: i32, camera: u8 },
    /// A V4L2 device (`/dev/videoN`) through OpenCV's V4L2 backend.
    V4l2 { device: PathBuf, camera: u8 },
    /// A GStreamer pipeline ending in `appsink`, through OpenCV's GStreamer backend.
    Gst { pipeline: String, camera: u8 },
}

impl LocalSource {
    /// Which of the vehicle's cameras (index in the fleet file) this source is.
    pub fn camera(&self) -> u8 {
        match self {
            LocalSource::Images { camera, .. }
            | LocalSource::Video { camera, .. }
            | LocalSource::Live { camera, .. }
            | LocalSource::V4l2 { camera, .. }
            | LocalSource::Gst { camera, .. } => *camera,
        }
    }

    /// The source as `shoal node --source` spells it.
    pub fn describe(&self) -> String {
        match self {
            LocalSource::Images { dir, .. } => format!("images:{}", dir.display()),
            LocalSource::Video { path, .. } => format!("video:{}", path.display()),
            LocalSource::Live { device, .. } => format!("camera:{device}"),
            LocalSource::V4l2 { device, .. } => format!("v4l2:{}", device.display()),
            LocalSource::Gst { pipeline, .. } => format!("gst:{pipeline}"),
        }
    }
}

/// Errors of the frame sources.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// `what` (a folder, file or camera device) cannot be opened or read.
    #[error("source {what}: {reason}")]
    Unreadable { what: String, reason: String },
    /// An image file that is not read (its name is in the error).
    #[error("source {0}")]
    Image(#[from] crate::image_file::ImageError),
    #[error("cannot start thread: {0}")]
    Thread(#[from] std::io::Error),
}

fn source_error(what: impl Into<String>, reason: impl Into<String>) -> SourceError {
    SourceError::Unreadable {
        what: what.into(),
        reason: reason.into(),
    }
}

/// Image files in `dir`, sorted by name.
pub fn image_files(dir: &Path) -> Result<Vec<PathBuf>, SourceError> {
    let rd = std::fs::read_dir(dir)
        .map_err(|e| source_error(dir.display().to_string(), e.to_string()))?;
    let mut files: Vec<PathBuf> = rd
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            matches!(
                p.extension()
                    .and_then(|e| e.to_str())
                    .map(|e| e.to_ascii_lowercase())
                    .as_deref(),
                Some("png" | "jpg" | "jpeg" | "bmp" | "tif" | "tiff" | "pgm")
            )
        })
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(source_error(dir.display().to_string(), "no image files"));
    }
    Ok(files)
}

/// Read one image file as 8-bit grey, as the image-folder source does. A
/// missing, truncated or undecodable file is an error naming it, never a panic.
pub fn read_image_gray(path: &Path) -> Result<GrayImage, SourceError> {
    let name = path.display().to_string();
    let file = crate::image_file::read_gray(path, crate::image_file::MAX_IMAGE_PIXELS)?;
    mat_to_gray(&file.gray).map_err(|e| source_error(name, e.to_string()))
}

/// An 8-bit BGR, BGRA or grey frame as grey.
pub(crate) fn to_gray(mat: &Mat) -> opencv::Result<Mat> {
    if mat.channels() == 1 {
        return mat.try_clone();
    }
    let mut g = Mat::default();
    let code = if mat.channels() == 4 {
        imgproc::COLOR_BGRA2GRAY
    } else {
        imgproc::COLOR_BGR2GRAY
    };
    imgproc::cvt_color(mat, &mut g, code, 0)?;
    Ok(g)
}

/// Start the reader thread of a local source; it runs until `stop` is
/// raised or the source ends (a folder or video at its end; a live source
/// only on `stop`: when its stream ends or fails, it is reopened, see
/// [`live`]). Images or video frames it cannot decode are skipped and counted
/// in `counters.unreadable`.
///
/// A live source's read can block inside OpenCV (a network stream gone
/// silent: OpenCV 4.6's GStreamer backend has no read timeout), so its
/// thread sees `stop` only when the read returns; whoever joins it should
/// wait a bounded time ([`join_within`]).
pub fn spawn_reader(
    source: LocalSource,
    vehicle: VehicleId,
    info: CameraInfo,
    queue: DropOldestQueue<CameraFrame>,
    counters: Arc<SourceCounters>,
    stop: Arc<AtomicBool>,
) -> Result<JoinHandle<()>, SourceError> {
    let name = format!("source-{vehicle}");
    let camera = source.camera();
    let feed = Feed {
        vehicle,
        camera,
        info,
        queue,
        counters,
    };
    // Open up front so a bad path is an error of `spawn`, not a log line.
    enum Opened {
        Files(Vec<PathBuf>, f64),
        /// The video and the frame count the file declares.
        Video(opencv::videoio::VideoCapture, u64),
    }
    let opened = match &source {
        LocalSource::Images { dir, rate_hz, .. } => Opened::Files(image_files(dir)?, *rate_hz),
        LocalSource::Video { path, .. } => {
            let (cap, declared) =
                crate::image_file::open_video(path, crate::image_file::MAX_IMAGE_PIXELS)?;
            Opened::Video(cap, declared)
        }
        LocalSource::Live { .. } | LocalSource::V4l2 { .. } | LocalSource::Gst { .. } => {
            return spawn_live(name, source, feed, stop);
        }
    };
    Ok(std::thread::Builder::new().name(name).spawn(move || {
        match opened {
            Opened::Files(files, rate_hz) => play_files(&feed, &files, rate_hz, &stop),
            Opened::Video(cap, declared) => play_video(&feed, cap, declared, &stop),
        }
        tracing::info!("source of vehicle {vehicle} camera {camera} finished");
    })?)
}

/// How long starting a live source waits for its first opening: one that
/// fails within it is an error of [`spawn_reader`]; one still opening after
/// it (OpenCV's GStreamer backend waits for a live pipeline's first buffer:
/// a network stream not sending yet) goes on opening on its thread.
pub const LIVE_OPEN_WAIT: Duration = Duration::from_secs(5);

/// A live source's thread: it opens the capture itself, since OpenCV's open
/// can block until the stream sends (see [`LIVE_OPEN_WAIT`]).
fn spawn_live(
    name: String,
    source: LocalSource,
    feed: Feed,
    stop: Arc<AtomicBool>,
) -> Result<JoinHandle<()>, SourceError> {
    let (opened_tx, opened_rx) = std::sync::mpsc::sync_channel::<Result<(), SourceError>>(1);
    let what = source.describe();
    let thread = std::thread::Builder::new().name(name).spawn(move || {
        let cap = match live::LiveCapture::open(source) {
            Ok(cap) => {
                let _ = opened_tx.send(Ok(()));
                cap
            }
            Err(e) => {
                let _ = opened_tx.send(Err(e));
                return;
            }
        };
        live::run(&feed, cap, &stop);
        tracing::info!(
            "source of vehicle {} camera {} finished",
            feed.vehicle,
            feed.camera
        );
    })?;
    match opened_rx.recv_timeout(LIVE_OPEN_WAIT) {
        Ok(Ok(())) => Ok(thread),
        Ok(Err(e)) => {
            let _ = thread.join();
            Err(e)
        }
        Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {
            tracing::warn!(
                "{what}: still opening after {:.0} s: a stream that is not sending yet, \
                 or a pipeline GStreamer cannot run (OpenCV's warnings above say which; \
                 without gst-inspect-1.0 an unknown element is not caught before)",
                LIVE_OPEN_WAIT.as_secs_f64()
            );
            Ok(thread)
        }
        Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => {
            Err(source_error(what, "the source thread ended while opening"))
        }
    }
}

/// Join `thread` if it finishes within `wait`; otherwise leave it (a read
/// blocked in a driver or pipeline ends with the process) and say so.
/// Returns whether it was joined.
pub fn join_within(thread: JoinHandle<()>, wait: Duration) -> bool {
    let deadline = std::time::Instant::now() + wait;
    while !thread.is_finished() && std::time::Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(10));
    }
    if thread.is_finished() {
        if thread.join().is_err() {
            tracing::error!("a source thread panicked");
        }
        true
    } else {
        let name = thread.thread().name().unwrap_or("source").to_string();
        tracing::warn!(
            "{name}: still blocked in a read {:.1} s after stop (a stream gone silent); left to end with the process",
            wait.as_secs_f64()
        );
        false
    }
}

/// Where a reader thread's frames go.
struct Feed {
    vehicle: VehicleId,
    camera: u8,
    info: CameraInfo,
    queue: DropOldestQueue<CameraFrame>,
    counters: Arc<SourceCounters>,
}

impl Feed {
    fn push(&self, g: GrayImage, seq: u64, stamp_ns: u64, source: StampSource) {
        let mut info = self.info;
        info.model.width = g.width;
        info.model.height = g.height;
        self.counters.set_stamp_source(source);
        self.queue.push(CameraFrame {
            vehicle: self.vehicle,
            camera: self.camera,
            seq,
            stamp_ns,
            info,
            format: PixelFormat::Mono8,
            data: g.data,
        });
    }

    fn unreadable(&self, n: u64, why: impl std::fmt::Display) {
        self.counters.unreadable.fetch_add(n, Ordering::Relaxed);
        tracing::warn!("vehicle {} camera {}: {why}", self.vehicle, self.camera);
    }
}

/// A captured picture as 8-bit grey.
fn mat_as_gray(frame: &Mat) -> Result<GrayImage, String> {
    to_gray(frame)
        .map_err(|e| e.to_string())
        .and_then(|g| mat_to_gray(&g).map_err(|e| e.to_string()))
}

/// An image folder at `rate_hz`, stamped by its place in the folder.
fn play_files(feed: &Feed, files: &[PathBuf], rate_hz: f64, stop: &AtomicBool) {
    let period = Duration::from_secs_f64(1.0 / rate_hz.max(1e-3));
    for (seq, path) in files.iter().enumerate() {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        match read_image_gray(path) {
            Ok(g) => {
                let stamp = (seq as f64 * period.as_secs_f64() * 1e9) as u64;
                feed.push(g, seq as u64, stamp, StampSource::Playback);
            }
            Err(e) => feed.unreadable(1, format_args!("{e}, skipped")),
        }
        std::thread::sleep(period);
    }
}

/// A video file at its own frame rate, stamped by its own time.
fn play_video(
    feed: &Feed,
    mut cap: opencv::videoio::VideoCapture,
    declared: u64,
    stop: &AtomicBool,
) {
    use opencv::videoio;
    let fps = cap.get(videoio::CAP_PROP_FPS).unwrap_or(0.0);
    let period = Duration::from_secs_f64(if fps > 0.0 { 1.0 / fps } else { 0.1 });
    let mut seq = 0u64;
    let mut frame = Mat::default();
    while !stop.load(Ordering::Relaxed) {
        match cap.read(&mut frame) {
            Ok(true) if !frame.empty() => {}
            _ => break,
        }
        let stamp = (cap.get(videoio::CAP_PROP_POS_MSEC).unwrap_or(0.0) * 1e6) as u64;
        match mat_as_gray(&frame) {
            Ok(g) => feed.push(g, seq, stamp, StampSource::Playback),
            Err(e) => feed.unreadable(1, format_args!("frame {seq}: {e}")),
        }
        seq += 1;
        std::thread::sleep(period);
    }
    if !stop.load(Ordering::Relaxed) {
        if let Some(why) = crate::image_file::video_shortfall(seq, declared) {
            // The frames the file declares but could not give are unreadable ones.
            feed.unreadable(declared - seq, why);
        }
    }
}
