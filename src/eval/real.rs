//! `shoal eval real`: the detectors on public real recordings, judged by the
//! ground truth each recording allows (issue #15).
//!
//! A data root holds one folder per recording, each with an `eval.json`
//! manifest (format in `docs/real-data.md`): the frames (a video or a list of
//! images), the code set and marker side, the camera when it is known, named
//! frame ranges (`dev` for development, `holdout` for the final figure only),
//! and one kind of ground truth:
//!
//! - `layout`: the markers' centres in one rigid frame (a surveyed tank floor,
//!   a board). Each method's pose of every pair of markers read in one frame
//!   gives a distance, compared with the known one; across consecutive video
//!   frames the change of a pair's distance is its jitter.
//! - `corners`: reference corners per image (made by another detector; the
//!   manifest names which, so a comparison with that detector is not called
//!   independent).
//! - `rotation_steps`: one marker turned by known angles; the measured
//!   rotation between consecutive steps against the nominal one.
//!
//! Every method reads the same decoded frames and goes through the same PnP
//! ([`estimate_pose`]): shoal's detector (raw frames as `shoal detect` reads
//! them, and on underwater recordings after CLAHE and HOIRM), AprilTag 3 at
//! `quad_decimate` 1 and at its default 2, and OpenCV's ArUco detector.
//! *Present* markers are the reference list where the truth has one, else the
//! union of what any method read of the markers the truth knows; a read of a
//! marker the truth does not know is a *false read*.

mod manifest;
mod score;
mod stage;
pub mod twin;

pub use manifest::{
    data_root, find_recordings, load_manifest, Manifest, Recording, ReferenceMarker, Truth,
    DEFAULT_DATA_DIRS, MANIFEST_DIR,
};
pub use stage::{manifest_dir, sha256_hex, stage_all, verify_staged, Staged};

use super::plot::{self, Grouped};
use super::table::Csv;
use super::{EvalError, EvalOptions};
use opencv::core::Mat;
use opencv::imgproc;
use opencv::prelude::*;
use score::{scores, MethodRun, Read};
use serde_json::{json, Value};
use shoal_node::baseline::{AprilTag, OpenCvAruco};
use shoal_node::detect::{DetectParams, MarkerDetector, ShoalDetector};
use shoal_node::image_file;
use shoal_node::pipeline::detect_restoration;
use shoal_node::pose::{estimate_pose, stated_covariance};
use shoal_node::restore::{restorer, Method, RestoreParams, Restorer};
use shoal_proto::camera::CameraModel;
use shoal_proto::marker::CodeSet;
use std::collections::BTreeMap;
use std::path::Path;
use std::time::Instant;

/// Frames per split in `--quick` (CI) runs.
const QUICK_FRAMES: usize = 12;

/// A method under test.
struct Runner {
    name: String,
    detector: Box<dyn MarkerDetector>,
    restorer: Option<Box<dyn Restorer>>,
    /// Fit corners on the raw frame while detecting on the restoration.
    raw_fit: bool,
}

impl Runner {
    fn detect(
        &mut self,
        gray: &Mat,
        stamp_ns: u64,
    ) -> Result<Vec<shoal_node::detect::Detection>, EvalError> {
        match self.restorer.as_mut() {
            Some(r) => {
                let restored = r.restore(gray, stamp_ns)?;
                Ok(detect_restoration(self.detector.as_mut(), &restored, gray)?.detections)
            }
            None if self.raw_fit => Ok(self.detector.detect_restored(gray, gray)?),
            None => Ok(self.detector.detect(gray)?),
        }
    }
}

/// The columns of a read in `real.csv` and `twin-reads.csv` ([`read_fields`]).
const READ_COLUMNS: [&str; 7] = ["id", "tx_m", "ty_m", "tz_m", "rx_rad", "ry_rad", "rz_rad"];

/// The [`READ_COLUMNS`] of a read (the pose's translation and rotation
/// vector; empty without a pose).
fn read_fields(r: &Read) -> [String; 7] {
    let t = r.camera_from_marker.map(|p| p.translation.vector);
    let rv = r.camera_from_marker.map(|p| p.rotation.scaled_axis());
    let num = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.5}"));
    [
        r.id.to_string(),
        num(t.map(|t| t.x)),
        num(t.map(|t| t.y)),
        num(t.map(|t| t.z)),
        num(rv.map(|r| r.x)),
        num(rv.map(|r| r.y)),
        num(rv.map(|r| r.z)),
    ]
}

fn runners(
    m: &Manifest,
    codes: CodeSet,
    lens: Option<CameraModel>,
) -> Result<Vec<Runner>, EvalError> {
    let shoal = |restore: Method| -> Runner {
        let params = DetectParams {
            lens,
            ..DetectParams::default()
        };
        Runner {
            name: if restore == Method::None {
                "shoal".to_string()
            } else {
                format!("shoal+{restore}")
            },
            detector: Box::new(ShoalDetector::new(codes, params)),
            restorer: (restore != Method::None)
                .then(|| restorer(restore, &RestoreParams::default())),
            raw_fit: true,
        }
    };
    let mut out = vec![shoal(Method::None)];
    if m.underwater {
        out.push(shoal(Method::Clahe));
        out.push(shoal(Method::Hoirm));
    }
    if matches!(codes, CodeSet::AprilTag16h5 | CodeSet::AprilTag36h11) {
        for (name, decimate) in [("apriltag3-d1", 1.0), ("apriltag3", 2.0)] {
            let mut det = AprilTag::new(codes)?;
            det.set_quad_decimate(decimate);
            out.push(Runner {
                name: name.to_string(),
                detector: Box::new(det),
                restorer: None,
                raw_fit: false,
            });
        }
    }
    if let Ok(det) = OpenCvAruco::new(codes) {
        out.push(Runner {
            name: "opencv-aruco".to_string(),
            detector: Box::new(det),
            restorer: None,
            raw_fit: false,
        });
    }
    Ok(out)
}

fn to_gray(frame: &Mat) -> Result<Mat, EvalError> {
    if frame.channels() == 1 {
        return Ok(frame
            .try_clone()
            .map_err(shoal_node::detect::DetectError::from)?);
    }
    let mut g = Mat::default();
    imgproc::cvt_color_def(frame, &mut g, imgproc::COLOR_BGR2GRAY)
        .map_err(shoal_node::detect::DetectError::from)?;
    Ok(g)
}

/// Calls `each(index, name, gray)` for the frames of `range` in order.
fn for_frames(
    dir: &Path,
    m: &Manifest,
    range: [usize; 2],
    mut each: impl FnMut(usize, &str, &Mat) -> Result<(), EvalError>,
) -> Result<usize, EvalError> {
    let unreadable =
        |path: &Path, what: &str| EvalError::Setup(format!("{}: {what}", path.display()));
    let mut n = 0;
    if let Some(video) = &m.video {
        let path = dir.join(video);
        let (mut cap, _) = image_file::open_video(&path, image_file::MAX_IMAGE_PIXELS)
            .map_err(|e| EvalError::Setup(e.to_string()))?;
        let mut frame = Mat::default();
        for idx in 0..range[1] {
            match cap.read(&mut frame) {
                Ok(true) if !frame.empty() => {}
                Ok(_) => break,
                Err(e) => {
                    return Err(unreadable(
                        &path,
                        &format!("read failed at frame {idx}: {e}"),
                    ))
                }
            }
            if idx >= range[0] {
                each(idx, &format!("{video}#{idx}"), &to_gray(&frame)?)?;
                n += 1;
            }
        }
    } else {
        for (idx, name) in m.images.iter().enumerate().take(range[1]).skip(range[0]) {
            let path = dir.join(name);
            let img = image_file::read_gray(&path, image_file::MAX_IMAGE_PIXELS)
                .map_err(|e| EvalError::Setup(e.to_string()))?;
            each(idx, name, &img.gray)?;
            n += 1;
        }
    }
    Ok(n)
}

/// Each detection as a [`Read`]: its outer corners and, with a camera, PnP's
/// pose and its planar alternative.
fn reads_of(
    found: &[shoal_node::detect::Detection],
    camera: Option<&CameraModel>,
    side_m: f64,
) -> Vec<Read> {
    found
        .iter()
        .map(|d| {
            let outer_px = d
                .corner_ids
                .iter()
                .zip(&d.corners_px)
                .filter(|(cid, _)| **cid < 4)
                .map(|(_, c)| *c)
                .collect();
            let object_points = d.object_points(side_m);
            let solution = camera.and_then(|cam| {
                estimate_pose(cam, &object_points, &d.corners_px, None)
                    .ok()
                    .map(|s| (cam, s))
            });
            // As the node states it (no calibration σ: the recordings' cameras state none).
            let position_cov = solution.and_then(|(cam, s)| {
                stated_covariance(
                    cam,
                    None,
                    &object_points,
                    &s.best,
                    None,
                    d.corner_covariance.as_ref(),
                )
                .ok()
                .map(|c| c.fixed_view::<3, 3>(0, 0).into_owned())
            });
            Read {
                id: d.id,
                outer_px,
                camera_from_marker: solution.map(|(_, s)| s.best.camera_from_marker),
                alternative: solution
                    .and_then(|(_, s)| s.alternative)
                    .map(|h| h.camera_from_marker),
                position_cov,
            }
        })
        .collect()
}

/// Runs every method over one split; CSV rows of every read (with `csv`).
fn run_split(
    dir: &Path,
    m: &Manifest,
    split: &str,
    range: [usize; 2],
    opts: &EvalOptions,
    mut csv: Option<&mut Csv>,
) -> Result<BTreeMap<String, MethodRun>, EvalError> {
    let codes = CodeSet::from_name(&m.codes).map_err(|e| EvalError::Setup(e.to_string()))?;
    let camera = m.camera.map(CameraModel::from);
    let mut methods = runners(m, codes, camera)?;
    let mut runs: BTreeMap<String, MethodRun> = methods
        .iter()
        .map(|r| (r.name.clone(), MethodRun::default()))
        .collect();
    let range = if opts.quick {
        [range[0], range[1].min(range[0] + QUICK_FRAMES)]
    } else {
        range
    };
    let bar = opts.bar(range[1] - range[0], &format!("{}/{split}", m.name));
    let n = for_frames(dir, m, range, |idx, name, gray| {
        if let Some(cam) = &camera {
            let (w, h) = (gray.cols() as u32, gray.rows() as u32);
            if (w, h) != (cam.width, cam.height) {
                return Err(EvalError::Setup(format!(
                    "{}: frame {name} is {w}x{h} but the camera is {}x{}",
                    m.name, cam.width, cam.height
                )));
            }
        }
        // Frames of a video are 1/10 s apart for HOIRM's ambient estimate; photos are independent.
        let stamp_ns = idx as u64 * 100_000_000;
        for method in methods.iter_mut() {
            let started = Instant::now();
            let found = method.detect(gray, stamp_ns)?;
            let ms = started.elapsed().as_secs_f64() * 1e3;
            let reads = reads_of(&found, camera.as_ref(), m.side_m);
            for r in &reads {
                let Some(csv) = csv.as_deref_mut() else {
                    break;
                };
                let mut row = vec![
                    m.name.clone(),
                    split.to_string(),
                    idx.to_string(),
                    name.to_string(),
                    method.name.clone(),
                ];
                row.extend(read_fields(r));
                csv.row(row);
            }
            let run = runs.get_mut(&method.name).expect("a run per method");
            run.frames.push((idx, name.to_string(), reads));
            run.detect_ms.push(ms);
        }
        bar.inc(1);
        Ok(())
    })?;
    bar.finish_and_clear();
    if n == 0 {
        return Err(EvalError::Setup(format!(
            "{}: split {split} {:?} holds no frame",
            m.name, range
        )));
    }
    Ok(runs)
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or("–".to_string(), |v| format!("{v:.digits$}"))
}

/// `shoal eval real`.
pub fn run(opts: &EvalOptions) -> Result<Value, EvalError> {
    let root = data_root(opts.data.as_deref())?;
    let (recordings, missing) = find_recordings(&root, Path::new(MANIFEST_DIR))?;
    for m in &missing {
        crate::errln!(
            "note: {}: its frames are not under {} (skipped)",
            m.display(),
            root.display()
        );
    }
    if recordings.is_empty() {
        return Err(EvalError::Setup(format!(
            "{}: no recording (a folder named as a manifest of {MANIFEST_DIR}, or one with its own eval.json; docs/real-data.md)",
            root.display()
        )));
    }
    let mut csv = Csv::new(
        &[
            &["recording", "split", "frame", "name", "method"],
            &READ_COLUMNS[..],
        ]
        .concat(),
    );
    let mut results = serde_json::Map::new();
    let mut table = String::from(
        "| recording / split | method | read / present | recall | false | unconfirmed | corner px | pairs | ratio IQR (present) | jitter mm (common; present) | jitter NEES mean (median; steps) | rot err ° (flip-resolved) | ms/frame |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    let mut categories = Vec::new();
    let mut recall: BTreeMap<String, Vec<Option<f64>>> = BTreeMap::new();
    for rec in &recordings {
        let (dir, m) = (&rec.dir, load_manifest(&rec.manifest)?);
        verify_staged(&m, dir)?;
        let mut per_split = serde_json::Map::new();
        for (split, range) in &m.splits {
            if opts.split.as_ref().is_some_and(|only| only != split) {
                continue;
            }
            let runs = run_split(dir, &m, split, *range, opts, Some(&mut csv))?;
            let s = scores(&m, &runs);
            let cat = format!("{}/{split}", m.name);
            for (method, sc) in &s {
                table += &format!(
                    "| {cat} | {method} | {} / {} | {} | {} | {} | {} | {} | {} ({}) | {} ({}; {}) | {} ({}; {}) | {} ({}) | {} |\n",
                    sc.read,
                    sc.present,
                    opt(sc.recall, 3),
                    sc.false_reads,
                    sc.unconfirmed,
                    opt(sc.corner_err_px_median, 2),
                    sc.pairs,
                    opt(sc.distance_ratio_iqr, 4),
                    opt(sc.distance_ratio_iqr_present, 4),
                    opt(sc.jitter_mm_median, 2),
                    opt(sc.jitter_mm_median_common, 2),
                    opt(sc.jitter_mm_median_present, 2),
                    opt(sc.jitter_nees_mean, 2),
                    opt(sc.jitter_nees_median, 2),
                    sc.jitter_nees_steps,
                    opt(sc.rotation_err_deg_median, 2),
                    opt(sc.rotation_err_deg_median_flip_resolved, 2),
                    opt(sc.detect_ms_mean, 2),
                );
                recall
                    .entry(method.clone())
                    .or_insert_with(|| vec![None; categories.len()])
                    .push(sc.recall);
            }
            // The plot's axis has room for the name's last word only.
            let short = m.name.rsplit('-').next().unwrap_or(&m.name);
            categories.push(format!("{short}/{}", &split[..split.len().min(4)]));
            for v in recall.values_mut() {
                v.resize(categories.len(), None);
            }
            per_split.insert(split.clone(), serde_json::to_value(&s)?);
        }
        results.insert(
            m.name.clone(),
            json!({
                "underwater": m.underwater,
                "codes": m.codes,
                "truth": m.truth.kind(),
                "truth_from": m.truth_from,
                "splits": per_split,
            }),
        );
    }
    csv.write(&opts.out.join("real.csv"))?;
    std::fs::write(opts.out.join("real.md"), &table).map_err(|source| EvalError::Io {
        path: opts.out.join("real.md"),
        source,
    })?;
    let series: Vec<String> = recall.keys().cloned().collect();
    let values: Vec<Vec<Option<f64>>> = recall.into_values().collect();
    let plots = plot::bars(
        &opts.out.join("real-recall"),
        &Grouped {
            title: "Real recordings: markers read of those present".into(),
            x_label: "recording / split".into(),
            y_label: "recall".into(),
            categories,
            series,
        },
        &values,
    )?;
    crate::errln!("{table}");
    Ok(json!({
        "data": root.display().to_string(),
        "skipped_manifests": missing.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
        "results": results,
        "table": opts.out.join("real.md").display().to_string(),
        "plots": plots.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
    }))
}
