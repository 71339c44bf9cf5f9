//! `shoal detect`: run the detector over image and video files and print one
//! JSON line per detection (with the pose when the camera and marker size are known).

use super::{DetectError, MarkerDetector, ShoalDetector};
use crate::pose::estimate_pose;
use opencv::core::Mat;
use opencv::imgproc;
use opencv::prelude::*;
use shoal_proto::camera::{CameraModel, FrameCamera};
use shoal_proto::marker::CodeSet;
use std::io::Write;
use std::path::Path;

/// What [`detect_paths`] went through.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct DetectSummary {
    pub files: usize,
    pub frames: usize,
    pub detections: usize,
    /// Files that could not be read, or not wholly (each reported as an `"error"` line).
    pub errors: usize,
    /// Things done to make a file usable that the user should know (each a `"warning"` line):
    /// 16-bit pixels scaled, a calibration scaled to a resized stream.
    pub warnings: usize,
}

const VIDEO_EXTENSIONS: [&str; 7] = ["mp4", "m4v", "avi", "mkv", "mov", "webm", "mjpeg"];

/// A file OpenCV is asked to open as a video (by its extension), not an image.
pub(crate) fn is_video(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| VIDEO_EXTENSIONS.iter().any(|v| v.eq_ignore_ascii_case(e)))
}

fn to_gray(frame: &Mat) -> Result<Mat, DetectError> {
    if frame.channels() == 1 && frame.depth() == opencv::core::CV_8U {
        return Ok(frame.try_clone()?);
    }
    let mut g = Mat::default();
    let code = if frame.channels() == 4 {
        imgproc::COLOR_BGRA2GRAY
    } else {
        imgproc::COLOR_BGR2GRAY
    };
    if frame.channels() == 1 {
        frame.convert_to(&mut g, opencv::core::CV_8U, 1.0, 0.0)?;
    } else {
        imgproc::cvt_color_def(frame, &mut g, code)?;
    }
    Ok(g)
}

/// Why one input file was not (wholly) used. Writing the output is not such
/// a failure: it ends the run ([`DetectError::Io`]).
enum FileFailure {
    /// Reported as the file's `"error"` line; the run goes on.
    Input(String),
    Output(DetectError),
}

impl From<DetectError> for FileFailure {
    fn from(e: DetectError) -> Self {
        match e {
            DetectError::Io(_) => FileFailure::Output(e),
            other => FileFailure::Input(other.to_string()),
        }
    }
}

impl From<std::io::Error> for FileFailure {
    fn from(e: std::io::Error) -> Self {
        FileFailure::Output(DetectError::Io(e))
    }
}

/// The run's settings and its output, shared by every file.
struct Run<'a> {
    det: ShoalDetector,
    /// The calibration as given, and the marker side.
    camera: Option<CameraModel>,
    side_m: Option<f64>,
    out: &'a mut dyn Write,
    sum: DetectSummary,
}

impl Run<'_> {
    /// One image or video file; what cannot be read of it is an error line.
    fn file(&mut self, path: &Path) -> Result<(), DetectError> {
        self.sum.files += 1;
        let source = path.display().to_string();
        let result = if is_video(path) {
            self.video(path, &source)
        } else {
            self.image(path, &source)
        };
        match result {
            Ok(()) => Ok(()),
            Err(FileFailure::Output(e)) => Err(e),
            Err(FileFailure::Input(reason)) => {
                self.sum.errors += 1;
                Ok(self.line(&source, "error", &reason)?)
            }
        }
    }

    fn line(&mut self, source: &str, key: &str, text: &str) -> std::io::Result<()> {
        writeln!(
            self.out,
            "{}",
            serde_json::json!({"source": source, key: text})
        )
    }

    fn warn(&mut self, source: &str, text: &str) -> std::io::Result<()> {
        self.sum.warnings += 1;
        self.line(source, "warning", text)
    }

    /// The calibration for a `w` x `h` frame of `source`, set on the detector;
    /// a scaled one is announced (once per file, `announced`).
    fn fit_camera(
        &mut self,
        source: &str,
        w: i32,
        h: i32,
        announced: &mut bool,
    ) -> Result<Option<CameraModel>, FileFailure> {
        let Some(cam) = self.camera else {
            return Ok(None);
        };
        let fitted = cam
            .for_frame(w.max(0) as u32, h.max(0) as u32)
            .map_err(FileFailure::Input)?;
        if let FrameCamera::Scaled { scale, from, .. } = fitted {
            if !*announced {
                *announced = true;
                self.warn(
                    source,
                    &format!(
                        "the calibration for {}x{} is scaled by {scale:.4} to these {w}x{h} frames",
                        from.0, from.1
                    ),
                )?;
            }
        }
        let fitted = *fitted.camera();
        if self.det.params().lens != Some(fitted) {
            self.det.set_lens(Some(fitted));
        }
        Ok(Some(fitted))
    }

    fn frame(
        &mut self,
        gray: &Mat,
        source: &str,
        index: Option<usize>,
        announced: &mut bool,
    ) -> Result<(), FileFailure> {
        let camera = self.fit_camera(source, gray.cols(), gray.rows(), announced)?;
        self.sum.frames += 1;
        self.sum.detections += detect_one(
            &mut self.det,
            gray,
            source,
            index,
            camera.as_ref(),
            self.side_m,
            self.out,
        )?;
        Ok(())
    }

    fn video(&mut self, path: &Path, source: &str) -> Result<(), FileFailure> {
        let (mut cap, declared) =
            crate::image_file::open_video(path, crate::image_file::MAX_IMAGE_PIXELS)
                .map_err(|e| FileFailure::Input(e.to_string()))?;
        let mut frame = Mat::default();
        let mut idx = 0usize;
        let mut announced = false;
        loop {
            match cap.read(&mut frame) {
                Ok(true) if !frame.empty() => {}
                // The end of the stream.
                Ok(_) => break,
                // A decoder error mid-stream: say where, keep what was read.
                Err(e) => {
                    return Err(FileFailure::Input(format!(
                        "video read failed after frame {idx}: {e}"
                    )))
                }
            }
            let gray = to_gray(&frame)?;
            self.frame(&gray, source, Some(idx), &mut announced)?;
            idx += 1;
        }
        if let Some(why) = crate::image_file::video_shortfall(idx as u64, declared) {
            return Err(FileFailure::Input(why));
        }
        if idx == 0 {
            return Err(FileFailure::Input(
                "opened as a video, but it has no frames".into(),
            ));
        }
        Ok(())
    }

    fn image(&mut self, path: &Path, source: &str) -> Result<(), FileFailure> {
        let file = crate::image_file::read_gray(path, crate::image_file::MAX_IMAGE_PIXELS)
            .map_err(|e| FileFailure::Input(e.to_string()))?;
        for note in &file.notes {
            self.warn(source, note)?;
        }
        self.frame(&file.gray, source, None, &mut false)
    }
}

/// Detect markers of `codes` in every image or video in `paths`, writing one
/// JSON object per line to `out`: `{"source", "frame", "codes", "id",
/// "hamming", "corner_ids", "corners_px", "module_px", "corner_fit",
/// "corner_fit_reason", "squares"}` — the corner stage's choice
/// ([`super::CornerChoice`]: e.g. `"corner_fit": "pattern"`,
/// `"corner_fit_reason": {"why": "edges_weak", "step_dn": 7.4}`, and per
/// square `{"first_corner", "found_by", "corners"}`) — plus
/// `"camera_from_marker"` (translation in metres, quaternion `[x, y, z, w]`,
/// RMS, 6x6 covariance, and the flipped alternative) when `camera` and
/// `side_m` are given.
///
/// A folder stands for its image files, sorted by name (what the node's
/// `images:` source plays, [`crate::source::image_files`]); a folder with
/// none, or that cannot be listed, is one error line naming it.
///
/// Every image file goes through [`crate::image_file::read_gray`] (size,
/// pixel and truncation checks, 16-bit scaling) and every video through
/// [`crate::image_file::open_video`]. A file that cannot be used, or not
/// wholly (cut short, a frame whose size the calibration does not fit), gives
/// `{"source", "error"}` and the run goes on with the next file; what was
/// done to make one usable gives `{"source", "warning"}`. Only a failure to
/// write `out`, an invalid `camera` or a `side_m` that is not a positive
/// length ends the run.
pub fn detect_paths(
    paths: &[impl AsRef<Path>],
    codes: CodeSet,
    camera: Option<CameraModel>,
    side_m: Option<f64>,
    out: &mut dyn Write,
) -> Result<DetectSummary, DetectError> {
    if let Some(side) = side_m {
        if !(side.is_finite() && side > 0.0) {
            return Err(DetectError::Input {
                path: "marker side".into(),
                reason: format!("{side} m is not a positive length"),
            });
        }
    }
    if let Some(p) = camera.as_ref().and_then(CameraModel::problem) {
        return Err(DetectError::Input {
            path: "camera".into(),
            reason: p,
        });
    }
    let mut run = Run {
        det: ShoalDetector::new(
            codes,
            super::DetectParams {
                lens: camera,
                ..super::DetectParams::default()
            },
        ),
        camera,
        side_m,
        out,
        sum: DetectSummary::default(),
    };
    for path in paths {
        let path = path.as_ref();
        if !path.is_dir() {
            run.file(path)?;
            continue;
        }
        match crate::source::image_files(path) {
            Ok(files) => {
                for file in &files {
                    run.file(file)?;
                }
            }
            Err(e) => {
                run.sum.files += 1;
                run.sum.errors += 1;
                run.line(&path.display().to_string(), "error", &e.to_string())?;
            }
        }
    }
    Ok(run.sum)
}

fn detect_one(
    det: &mut ShoalDetector,
    gray: &Mat,
    source: &str,
    frame: Option<usize>,
    camera: Option<&CameraModel>,
    side_m: Option<f64>,
    out: &mut dyn Write,
) -> Result<usize, DetectError> {
    // The user's frames are the camera's own (no restoration here): the
    // corners are fitted to them as the node fits its raw frames.
    let found = det.detect_restored(gray, gray)?;
    for d in &found {
        let mut obj = serde_json::json!({
            "source": source,
            "frame": frame,
            "codes": d.codes.name(),
            "id": d.id,
            "hamming": d.hamming,
            "corner_ids": d.corner_ids,
            "corners_px": d.corners_px,
            "module_px": d.module_px,
            "corner_fit": d.corner_fit.fit,
            "corner_fit_reason": d.corner_fit.reason,
            "squares": d.corner_fit.squares,
        });
        if let (Some(cam), Some(side)) = (camera, side_m) {
            let pose = match estimate_pose(cam, &d.object_points(side), &d.corners_px, None) {
                Ok(sol) => {
                    let h = |h: &crate::pose::Hypothesis| {
                        let t = h.camera_from_marker.translation.vector;
                        let q = h.camera_from_marker.rotation.coords;
                        let cov: Vec<Vec<f64>> = (0..6)
                            .map(|r| (0..6).map(|c| h.covariance[(r, c)]).collect())
                            .collect();
                        serde_json::json!({"t_m": [t.x, t.y, t.z], "q_xyzw": [q.x, q.y, q.z, q.w], "rms_px": h.rms_px, "covariance": cov})
                    };
                    let mut p = h(&sol.best);
                    p["alternative"] = sol.alternative.as_ref().map_or(serde_json::Value::Null, h);
                    p
                }
                Err(e) => serde_json::json!({"error": e.to_string()}),
            };
            obj["camera_from_marker"] = pose;
        }
        writeln!(out, "{obj}")?;
    }
    Ok(found.len())
}
