//! Frame sources on the vehicle itself: a folder of images, a video file, a
//! live camera (OpenCV `VideoCapture`). Each runs on its own named thread and
//! feeds one camera's drop-oldest queue (a [`crate::vehicle::LocalInput`]).
//! Frames that arrive over Zenoh are the node service's business
//! (`shoal_services::node`).

use crate::mat::mat_to_gray;
use opencv::core::Mat;
use opencv::prelude::*;
use opencv::{imgproc, videoio};
use shoal_proto::image::GrayImage;
use shoal_proto::messages::{CameraFrame, CameraInfo, PixelFormat, VehicleId};
use shoal_proto::queue::DropOldestQueue;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

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
    /// A live camera through OpenCV's VideoCapture (device index).
    Live { device: i32, camera: u8 },
}

impl LocalSource {
    /// Which of the vehicle's cameras (index in the fleet file) this source is.
    pub fn camera(&self) -> u8 {
        match self {
            LocalSource::Images { camera, .. }
            | LocalSource::Video { camera, .. }
            | LocalSource::Live { camera, .. } => *camera,
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

fn to_gray(mat: &Mat) -> opencv::Result<Mat> {
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

/// Start the reader thread of a local source. Images or video frames it
/// cannot decode are skipped and counted in `unreadable`.
pub fn spawn_reader(
    source: LocalSource,
    vehicle: VehicleId,
    info: CameraInfo,
    queue: DropOldestQueue<CameraFrame>,
    unreadable: Arc<AtomicU64>,
    stop: Arc<AtomicBool>,
) -> Result<JoinHandle<()>, SourceError> {
    let name = format!("source-{vehicle}");
    let camera = source.camera();
    // Open up front so a bad path is an error of `spawn`, not a log line.
    enum Opened {
        Files(Vec<PathBuf>, f64),
        /// The capture, whether it is live, the frame count the file declares.
        Capture(videoio::VideoCapture, bool, u64),
    }
    let opened = match &source {
        LocalSource::Images { dir, rate_hz, .. } => Opened::Files(image_files(dir)?, *rate_hz),
        LocalSource::Video { path, .. } => {
            let (cap, declared) =
                crate::image_file::open_video(path, crate::image_file::MAX_IMAGE_PIXELS)?;
            Opened::Capture(cap, false, declared)
        }
        LocalSource::Live { device, .. } => {
            let cap = videoio::VideoCapture::new(*device, videoio::CAP_ANY)
                .map_err(|e| source_error(format!("camera {device}"), e.to_string()))?;
            if !cap.is_opened().unwrap_or(false) {
                return Err(source_error(
                    format!("camera {device}"),
                    "cannot open camera",
                ));
            }
            Opened::Capture(cap, true, 0)
        }
    };
    let make_frame = move |g: GrayImage, seq: u64, stamp_ns: u64| -> CameraFrame {
        let mut info = info;
        info.model.width = g.width;
        info.model.height = g.height;
        CameraFrame {
            vehicle,
            camera,
            seq,
            stamp_ns,
            info,
            format: PixelFormat::Mono8,
            data: g.data,
        }
    };
    Ok(std::thread::Builder::new().name(name).spawn(move || {
        let started = Instant::now();
        match opened {
            Opened::Files(files, rate_hz) => {
                let period = Duration::from_secs_f64(1.0 / rate_hz.max(1e-3));
                for (seq, path) in files.iter().enumerate() {
                    if stop.load(Ordering::Relaxed) {
                        break;
                    }
                    match read_image_gray(path) {
                        Ok(g) => {
                            let stamp = (seq as f64 * period.as_secs_f64() * 1e9) as u64;
                            queue.push(make_frame(g, seq as u64, stamp));
                        }
                        Err(e) => {
                            unreadable.fetch_add(1, Ordering::Relaxed);
                            tracing::warn!("{e}, skipped");
                        }
                    }
                    std::thread::sleep(period);
                }
            }
            Opened::Capture(mut cap, live, declared) => {
                let fps = cap.get(videoio::CAP_PROP_FPS).unwrap_or(0.0);
                let period = Duration::from_secs_f64(if fps > 0.0 { 1.0 / fps } else { 0.1 });
                let mut seq = 0u64;
                let mut frame = Mat::default();
                while !stop.load(Ordering::Relaxed) {
                    match cap.read(&mut frame) {
                        Ok(true) if !frame.empty() => {}
                        _ => break,
                    }
                    let stamp = if live {
                        started.elapsed().as_nanos() as u64
                    } else {
                        (cap.get(videoio::CAP_PROP_POS_MSEC).unwrap_or(0.0) * 1e6) as u64
                    };
                    match to_gray(&frame)
                        .map_err(|e| e.to_string())
                        .and_then(|g| mat_to_gray(&g).map_err(|e| e.to_string()))
                    {
                        Ok(g) => {
                            queue.push(make_frame(g, seq, stamp));
                        }
                        Err(e) => {
                            unreadable.fetch_add(1, Ordering::Relaxed);
                            tracing::warn!("vehicle {vehicle} camera {camera}: frame {seq}: {e}");
                        }
                    }
                    seq += 1;
                    if !live {
                        std::thread::sleep(period);
                    }
                }
                if !stop.load(Ordering::Relaxed) {
                    if let Some(why) = crate::image_file::video_shortfall(seq, declared) {
                        // The frames the file declares but could not give are unreadable ones.
                        unreadable.fetch_add(declared - seq, Ordering::Relaxed);
                        tracing::warn!("vehicle {vehicle} camera {camera}: {why}");
                    }
                }
            }
        }
        tracing::info!("source of vehicle {vehicle} camera {camera} finished");
    })?)
}
