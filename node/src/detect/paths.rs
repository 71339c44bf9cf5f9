//! `shoal detect`: run the detector over image and video files and print one
//! JSON line per detection (with the pose when the camera and marker size are known).

use super::{DetectError, MarkerDetector, ShoalDetector};
use crate::pose::estimate_pose;
use opencv::core::Mat;
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc, videoio};
use shoal_proto::camera::CameraModel;
use shoal_proto::marker::CodeSet;
use std::io::Write;
use std::path::Path;

/// What [`detect_paths`] went through.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct DetectSummary {
    pub files: usize,
    pub frames: usize,
    pub detections: usize,
    /// Files that could not be read (each reported as an `"error"` line).
    pub errors: usize,
}

const VIDEO_EXTENSIONS: [&str; 6] = ["mp4", "avi", "mkv", "mov", "webm", "mjpeg"];

fn is_video(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| VIDEO_EXTENSIONS.iter().any(|v| v.eq_ignore_ascii_case(e)))
}

fn to_gray(frame: &Mat) -> Result<Mat, DetectError> {
    if frame.channels() == 1 {
        return Ok(frame.try_clone()?);
    }
    let mut g = Mat::default();
    let code = if frame.channels() == 4 {
        imgproc::COLOR_BGRA2GRAY
    } else {
        imgproc::COLOR_BGR2GRAY
    };
    imgproc::cvt_color_def(frame, &mut g, code)?;
    Ok(g)
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
/// `side_m` are given. A file that cannot be read gives `{"source", "error"}`.
pub fn detect_paths(
    paths: &[impl AsRef<Path>],
    codes: CodeSet,
    camera: Option<CameraModel>,
    side_m: Option<f64>,
    out: &mut dyn Write,
) -> Result<DetectSummary, DetectError> {
    let mut det = ShoalDetector::new(
        codes,
        super::DetectParams {
            lens: camera,
            ..super::DetectParams::default()
        },
    );
    let mut sum = DetectSummary::default();
    for path in paths {
        let path = path.as_ref();
        sum.files += 1;
        let source = path.display().to_string();
        let emit_error = |out: &mut dyn Write, reason: String| -> Result<(), DetectError> {
            writeln!(
                out,
                "{}",
                serde_json::json!({"source": source, "error": reason})
            )?;
            Ok(())
        };
        if !path.is_file() {
            sum.errors += 1;
            emit_error(out, "no such file".into())?;
            continue;
        }
        if is_video(path) {
            let mut cap = match videoio::VideoCapture::from_file(&source, videoio::CAP_ANY) {
                Ok(c) if c.is_opened().unwrap_or(false) => c,
                _ => {
                    sum.errors += 1;
                    emit_error(out, "cannot open as a video".into())?;
                    continue;
                }
            };
            let mut frame = Mat::default();
            let mut idx = 0usize;
            let mut read_failed = false;
            loop {
                match cap.read(&mut frame) {
                    Ok(true) if !frame.empty() => {}
                    // The end of the stream.
                    Ok(_) => break,
                    // A decoder error mid-stream: say where, keep what was read.
                    Err(e) => {
                        sum.errors += 1;
                        emit_error(out, format!("video read failed after frame {idx}: {e}"))?;
                        read_failed = true;
                        break;
                    }
                }
                let gray = to_gray(&frame)?;
                sum.frames += 1;
                sum.detections += detect_one(
                    &mut det,
                    &gray,
                    &source,
                    Some(idx),
                    camera.as_ref(),
                    side_m,
                    out,
                )?;
                idx += 1;
            }
            if idx == 0 && !read_failed {
                sum.errors += 1;
                emit_error(out, "opened as a video, but it has no frames".into())?;
            }
        } else {
            let img = match imgcodecs::imread(&source, imgcodecs::IMREAD_GRAYSCALE) {
                Ok(m) if !m.empty() => m,
                _ => {
                    sum.errors += 1;
                    emit_error(out, "cannot read as an image".into())?;
                    continue;
                }
            };
            sum.frames += 1;
            sum.detections +=
                detect_one(&mut det, &img, &source, None, camera.as_ref(), side_m, out)?;
        }
    }
    Ok(sum)
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
