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

use super::plot::{self, Grouped};
use super::table::{median, quantile, Csv};
use super::{EvalError, EvalOptions};
use opencv::core::Mat;
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc, videoio};
use serde::Deserialize;
use serde_json::{json, Value};
use shoal_node::baseline::{AprilTag, OpenCvAruco};
use shoal_node::detect::{DetectParams, MarkerDetector, ShoalDetector};
use shoal_node::pose::estimate_pose;
use shoal_node::restore::{restorer, Method, RestoreParams, Restorer};
use shoal_proto::camera::CameraModel;
use shoal_proto::geometry::Pose;
use shoal_proto::marker::CodeSet;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Where `shoal eval real` looks for recordings when `--data` is not given:
/// `$SHOAL_REAL_DATA`, then these, relative to the working directory.
pub const DEFAULT_DATA_DIRS: [&str; 2] = ["../shared/data/real", "data/real"];

/// Frames per split in `--quick` (CI) runs.
const QUICK_FRAMES: usize = 12;

/// A reference corner farther than this fraction of the marker's side from
/// the detected one means the detection is somewhere else: a false read.
const MISPLACED_FRACTION: f64 = 0.25;

/// The manifest of one recording (`eval.json`).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    pub name: String,
    #[serde(default)]
    pub description: String,
    /// Where the frames and the ground truth come from (repository, commit, paths).
    #[serde(default)]
    pub source: String,
    #[serde(default)]
    pub license: String,
    pub underwater: bool,
    /// Code set name (`apriltag16h5`, `aruco6x6_250`, …).
    pub codes: String,
    /// Side of the marker's outer black square, metres.
    pub side_m: f64,
    #[serde(default)]
    pub camera: Option<CameraJson>,
    /// A video file, or …
    #[serde(default)]
    pub video: Option<String>,
    /// … image files, in order.
    #[serde(default)]
    pub images: Vec<String>,
    /// Named frame ranges `[first, end)` over the frame index.
    pub splits: BTreeMap<String, [usize; 2]>,
    pub truth: Truth,
    /// Detectors whose output the ground truth is (e.g. `apriltag3`).
    #[serde(default)]
    pub truth_from: Vec<String>,
    /// The folder under the data root with the frames (default: the
    /// manifest's file stem; recordings that share frames name one folder).
    #[serde(default)]
    pub folder: Option<String>,
    /// IDs that are there (seen in the frames) but whose place the truth
    /// does not give: their reads are neither scored nor false.
    #[serde(default)]
    pub unlisted_ids: Vec<u32>,
}

/// Pinhole + plumb-bob intrinsics as written in a manifest.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraJson {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    #[serde(default)]
    pub distortion: [f64; 5],
}

/// The ground truth a recording allows.
#[derive(Debug, Clone, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Truth {
    /// Marker centres in one rigid frame, metres.
    Layout { centres_m: BTreeMap<u32, [f64; 3]> },
    /// Reference markers per image file: ID and outer corners (pixels, any
    /// order); an image may show the same ID several times.
    Corners {
        images: BTreeMap<String, Vec<ReferenceMarker>>,
    },
    /// One marker, turned to a known angle in each image (degrees).
    RotationSteps {
        id: u32,
        angle_deg: BTreeMap<String, f64>,
    },
}

/// One marker of a [`Truth::Corners`] list.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReferenceMarker {
    pub id: u32,
    pub corners: [[f64; 2]; 4],
    /// Added by a person who checked the frame (a marker the reference
    /// detector missed): counts as present, but its corners are only
    /// approximate, so it gives no corner error.
    #[serde(default)]
    pub hand_checked: bool,
}

impl Truth {
    fn kind(&self) -> &'static str {
        match self {
            Truth::Layout { .. } => "layout",
            Truth::Corners { .. } => "corners",
            Truth::RotationSteps { .. } => "rotation_steps",
        }
    }
}

/// One marker a method read in one frame.
#[derive(Debug, Clone)]
struct Read {
    id: u32,
    /// The outer square's corners (corner IDs 0..4), in corner-ID order.
    outer_px: Vec<[f64; 2]>,
    camera_from_marker: Option<Pose>,
    /// PnP's other planar hypothesis (the flip), when it has one.
    alternative: Option<Pose>,
}

/// What one method read over one split.
#[derive(Debug, Default)]
struct MethodRun {
    /// Per frame: (frame index, frame name, reads).
    frames: Vec<(usize, String, Vec<Read>)>,
    detect_ms: Vec<f64>,
}

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
                Ok(self.detector.detect_restored(&restored.image, gray)?)
            }
            None if self.raw_fit => Ok(self.detector.detect_restored(gray, gray)?),
            None => Ok(self.detector.detect(gray)?),
        }
    }
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

/// The manifests of the public recordings this project measures itself on
/// (split and ground truth under version control; the frames live under the
/// data root, `docs/real-data.md`).
pub const MANIFEST_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/configs/real");

/// One recording found: the folder holding its frames and its manifest.
#[derive(Debug, Clone)]
pub struct Recording {
    pub dir: PathBuf,
    pub manifest: PathBuf,
}

/// The recordings under `root`: each manifest of `manifests` whose frames
/// folder (`folder`, default the manifest's file stem) is there, and every
/// sub-folder of `root` holding its own `eval.json`; sorted by name. Also
/// the manifests whose folder is missing.
pub fn find_recordings(
    root: &Path,
    manifests: &Path,
) -> Result<(Vec<Recording>, Vec<PathBuf>), EvalError> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| EvalError::Io { path, source }
    };
    let mut found = BTreeMap::new();
    let mut missing = Vec::new();
    if manifests.is_dir() {
        for e in std::fs::read_dir(manifests).map_err(io(manifests))? {
            let path = e.map_err(io(manifests))?.path();
            if path.extension().is_none_or(|x| x != "json") {
                continue;
            }
            let m = load_manifest(&path)?;
            let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned());
            let folder = m.folder.clone().or(stem).unwrap_or_default();
            let dir = root.join(&folder);
            if dir.is_dir() {
                found.insert(
                    m.name.clone(),
                    Recording {
                        dir,
                        manifest: path,
                    },
                );
            } else {
                missing.push(path);
            }
        }
    }
    for e in std::fs::read_dir(root).map_err(io(root))? {
        let dir = e.map_err(io(root))?.path();
        let manifest = dir.join("eval.json");
        if manifest.is_file() {
            let m = load_manifest(&manifest)?;
            found.insert(m.name.clone(), Recording { dir, manifest });
        }
    }
    missing.sort();
    Ok((found.into_values().collect(), missing))
}

/// The data root: `explicit`, else `$SHOAL_REAL_DATA`, else the first of
/// [`DEFAULT_DATA_DIRS`] that exists.
pub fn data_root(explicit: Option<&Path>) -> Result<PathBuf, EvalError> {
    if let Some(p) = explicit {
        return Ok(p.to_path_buf());
    }
    if let Some(p) = std::env::var_os("SHOAL_REAL_DATA") {
        return Ok(PathBuf::from(p));
    }
    DEFAULT_DATA_DIRS
        .iter()
        .map(PathBuf::from)
        .find(|p| p.is_dir())
        .ok_or_else(|| {
            EvalError::Setup(format!(
                "no real recordings: pass --data DIR or set SHOAL_REAL_DATA (looked in {}); docs/real-data.md says what a recording folder holds",
                DEFAULT_DATA_DIRS.join(", ")
            ))
        })
}

/// Read and check one manifest.
pub fn load_manifest(path: &Path) -> Result<Manifest, EvalError> {
    let path = path.to_path_buf();
    let text = std::fs::read_to_string(&path).map_err(|source| EvalError::Io {
        path: path.clone(),
        source,
    })?;
    let bad = |reason: String| EvalError::Setup(format!("{}: {reason}", path.display()));
    let m: Manifest = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
    CodeSet::from_name(&m.codes).map_err(|e| bad(e.to_string()))?;
    if !(m.side_m > 0.0 && m.side_m < 10.0) {
        return Err(bad(format!(
            "side_m {} is not a plausible marker side",
            m.side_m
        )));
    }
    if m.video.is_some() != m.images.is_empty() {
        return Err(bad("give exactly one of `video` and `images`".into()));
    }
    if m.splits.is_empty() || m.splits.values().any(|[a, b]| a >= b) {
        return Err(bad(
            "`splits` needs at least one non-empty [first, end) range".into(),
        ));
    }
    if let Some(c) = m.camera {
        if let Some(p) = camera_model(&c).problem() {
            return Err(bad(format!("camera: {p}")));
        }
    }
    Ok(m)
}

fn camera_model(c: &CameraJson) -> CameraModel {
    CameraModel {
        width: c.width,
        height: c.height,
        fx: c.fx,
        fy: c.fy,
        cx: c.cx,
        cy: c.cy,
        distortion: c.distortion,
    }
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
        let mut cap =
            videoio::VideoCapture::from_file(&path.display().to_string(), videoio::CAP_ANY)
                .map_err(|e| unreadable(&path, &format!("cannot open as a video: {e}")))?;
        if !cap.is_opened().unwrap_or(false) {
            return Err(unreadable(&path, "cannot open as a video"));
        }
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
            let img = imgcodecs::imread(&path.display().to_string(), imgcodecs::IMREAD_GRAYSCALE)
                .map_err(|e| unreadable(&path, &format!("cannot read: {e}")))?;
            if img.empty() {
                return Err(unreadable(&path, "not an image, or missing"));
            }
            each(idx, name, &img)?;
            n += 1;
        }
    }
    Ok(n)
}

/// The IDs the truth knows.
fn known_ids(truth: &Truth) -> BTreeSet<u32> {
    match truth {
        Truth::Layout { centres_m } => centres_m.keys().copied().collect(),
        Truth::Corners { images } => images.values().flatten().map(|t| t.id).collect(),
        Truth::RotationSteps { id, .. } => [*id].into(),
    }
}

/// Mean distance of each reference corner to the nearest detected one, px.
fn corner_error(reference: &[[f64; 2]; 4], found: &[[f64; 2]]) -> Option<f64> {
    if found.is_empty() {
        return None;
    }
    let mut sum = 0.0;
    for r in reference {
        let d = found
            .iter()
            .map(|f| ((f[0] - r[0]).powi(2) + (f[1] - r[1]).powi(2)).sqrt())
            .fold(f64::INFINITY, f64::min);
        sum += d;
    }
    Some(sum / 4.0)
}

fn side_px(corners: &[[f64; 2]; 4]) -> f64 {
    (0..4)
        .map(|k| {
            let (a, b) = (corners[k], corners[(k + 1) % 4]);
            ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
        })
        .sum::<f64>()
        / 4.0
}

/// The figures of one method on one split.
#[derive(Debug, Default, Clone, serde::Serialize)]
struct Scores {
    frames: usize,
    present: usize,
    read: usize,
    recall: Option<f64>,
    false_reads: usize,
    /// Reads of a known ID that no other detector family confirmed.
    unconfirmed: usize,
    corner_err_px_median: Option<f64>,
    pairs: usize,
    distance_ratio_median: Option<f64>,
    distance_ratio_iqr: Option<f64>,
    jitter_mm_median: Option<f64>,
    /// Jitter over the (frame, pair)s every method read.
    jitter_mm_median_common: Option<f64>,
    rotation_err_deg_median: Option<f64>,
    /// The same with each image's planar flip chosen to agree best.
    rotation_err_deg_median_flip_resolved: Option<f64>,
    detect_ms_mean: Option<f64>,
}

/// Reads of known markers by `(frame, key)`, false reads, corner errors (px).
type Tally = (BTreeSet<(usize, u32)>, usize, Vec<f64>);

/// What one method read of what the truth knows: `(frame, key)` where the
/// key is the marker ID, or with [`Truth::Corners`] the reference marker's
/// index in its image's list; the false reads; the corner errors (px).
fn tally(m: &Manifest, run: &MethodRun) -> Tally {
    let known = known_ids(&m.truth);
    let mut good = BTreeSet::new();
    let mut false_reads = 0;
    let mut corner_errs = Vec::new();
    for (idx, name, reads) in &run.frames {
        if let Truth::Corners { images } = &m.truth {
            let refs = images.get(name).map_or(&[][..], Vec::as_slice);
            for r in reads {
                // The nearest reference of that ID not taken yet, if close enough.
                let best = refs
                    .iter()
                    .enumerate()
                    .filter(|(k, t)| t.id == r.id && !good.contains(&(*idx, *k as u32)))
                    .filter_map(|(k, t)| corner_error(&t.corners, &r.outer_px).map(|e| (k, t, e)))
                    .min_by(|a, b| a.2.total_cmp(&b.2));
                match best {
                    Some((k, t, e)) if e < MISPLACED_FRACTION * side_px(&t.corners) => {
                        if !t.hand_checked {
                            corner_errs.push(e);
                        }
                        good.insert((*idx, k as u32));
                    }
                    _ => false_reads += 1,
                }
            }
        } else {
            for r in reads.iter().filter(|r| !m.unlisted_ids.contains(&r.id)) {
                if known.contains(&r.id) {
                    good.insert((*idx, r.id));
                } else {
                    false_reads += 1;
                }
            }
        }
    }
    (good, false_reads, corner_errs)
}

/// Pair distances per (frame, pair) for a layout truth: (measured, known), metres.
fn pair_distances(
    centres: &BTreeMap<u32, [f64; 3]>,
    run: &MethodRun,
) -> BTreeMap<(usize, u32, u32), (f64, f64)> {
    let mut out = BTreeMap::new();
    for (idx, _, reads) in &run.frames {
        let posed: Vec<(u32, Pose)> = reads
            .iter()
            .filter(|r| centres.contains_key(&r.id))
            .filter_map(|r| r.camera_from_marker.map(|p| (r.id, p)))
            .collect();
        for (i, (a, pa)) in posed.iter().enumerate() {
            for (b, pb) in &posed[i + 1..] {
                let (a, b, pa, pb) = if a < b {
                    (*a, *b, pa, pb)
                } else {
                    (*b, *a, pb, pa)
                };
                let measured = (pa.translation.vector - pb.translation.vector).norm();
                let (ca, cb) = (centres[&a], centres[&b]);
                let known =
                    ((ca[0] - cb[0]).powi(2) + (ca[1] - cb[1]).powi(2) + (ca[2] - cb[2]).powi(2))
                        .sqrt();
                out.insert((*idx, a, b), (measured, known));
            }
        }
    }
    out
}

/// Median |change| of each pair's distance between consecutive frames, mm,
/// over the (frame, pair)s in `keep` (all when `None`).
fn jitter_mm(
    d: &BTreeMap<(usize, u32, u32), (f64, f64)>,
    keep: Option<&BTreeSet<(usize, u32, u32)>>,
) -> Option<f64> {
    let mut steps = Vec::new();
    for (&(idx, a, b), &(measured, _)) in d {
        if idx == 0 || keep.is_some_and(|k| !k.contains(&(idx, a, b))) {
            continue;
        }
        if let Some(&(prev, _)) = d.get(&(idx - 1, a, b)) {
            if keep.is_none_or(|k| k.contains(&(idx - 1, a, b))) {
                steps.push((measured - prev).abs() * 1e3);
            }
        }
    }
    median(&steps)
}

/// |measured − nominal| rotation between consecutive steps, degrees: with
/// PnP's best hypothesis of each image, or (`resolve_flips`) with whichever
/// of each image's two planar hypotheses agrees best — the detector-bound
/// error, since a flip is resolved downstream by other observations.
fn rotation_errors(
    id: u32,
    angle_deg: &BTreeMap<String, f64>,
    run: &MethodRun,
    resolve_flips: bool,
) -> Vec<f64> {
    let mut steps: Vec<(f64, Vec<Pose>)> = run
        .frames
        .iter()
        .filter_map(|(_, name, reads)| {
            let angle = *angle_deg.get(name)?;
            let read = reads.iter().find(|r| r.id == id)?;
            let mut poses = vec![read.camera_from_marker?];
            if resolve_flips {
                poses.extend(read.alternative);
            }
            Some((angle, poses))
        })
        .collect();
    steps.sort_by(|a, b| a.0.total_cmp(&b.0));
    steps
        .windows(2)
        .map(|w| {
            let nominal = (w[1].0 - w[0].0).abs();
            w[0].1
                .iter()
                .flat_map(|a| w[1].1.iter().map(move |b| (a, b)))
                .map(|(a, b)| {
                    ((a.rotation.inverse() * b.rotation).angle().to_degrees() - nominal).abs()
                })
                .fold(f64::INFINITY, f64::min)
        })
        .collect()
}

/// The detector family of a method (`shoal+hoirm` → `shoal`, `apriltag3-d1` → `apriltag3`).
fn family(method: &str) -> &str {
    method.split(['+', '-']).next().unwrap_or(method)
}

/// The (frame, ID)s read by at least two detector families (by one when
/// only two families run): a weak code family's false positives that happen
/// to carry a listed ID are not taken for present markers.
fn confirmed(tallies: &BTreeMap<&String, Tally>) -> BTreeSet<(usize, u32)> {
    let mut by: BTreeMap<(usize, u32), BTreeSet<&str>> = BTreeMap::new();
    for (method, (good, _, _)) in tallies {
        for key in good {
            by.entry(*key).or_default().insert(family(method));
        }
    }
    let families: BTreeSet<&str> = tallies.keys().map(|m| family(m)).collect();
    let need = if families.len() >= 3 { 2 } else { 1 };
    by.into_iter()
        .filter(|(_, f)| f.len() >= need)
        .map(|(k, _)| k)
        .collect()
}

fn scores(m: &Manifest, runs: &BTreeMap<String, MethodRun>) -> BTreeMap<String, Scores> {
    let tallies: BTreeMap<&String, _> = runs.iter().map(|(k, r)| (k, tally(m, r))).collect();
    let present: BTreeSet<(usize, u32)> = match &m.truth {
        Truth::Corners { images } => {
            let frames: BTreeMap<&str, usize> = runs
                .values()
                .flat_map(|r| r.frames.iter().map(|(i, n, _)| (n.as_str(), *i)))
                .collect();
            images
                .iter()
                .filter_map(|(name, tags)| frames.get(name.as_str()).map(|i| (*i, tags.len())))
                .flat_map(|(i, n)| (0..n as u32).map(move |k| (i, k)))
                .collect()
        }
        _ => confirmed(&tallies),
    };
    let distances: BTreeMap<&String, _> = match &m.truth {
        Truth::Layout { centres_m } => runs
            .iter()
            .map(|(k, r)| (k, pair_distances(centres_m, r)))
            .collect(),
        _ => BTreeMap::new(),
    };
    let common: Option<BTreeSet<(usize, u32, u32)>> = distances
        .values()
        .map(|d| d.keys().copied().collect::<BTreeSet<_>>())
        .reduce(|a, b| a.intersection(&b).copied().collect());
    runs.iter()
        .map(|(name, run)| {
            let (good, false_reads, corner_errs) = &tallies[name];
            let mut s = Scores {
                frames: run.frames.len(),
                present: present.len(),
                read: good.intersection(&present).count(),
                unconfirmed: good.difference(&present).count(),
                false_reads: *false_reads,
                corner_err_px_median: median(corner_errs),
                detect_ms_mean: (!run.detect_ms.is_empty())
                    .then(|| run.detect_ms.iter().sum::<f64>() / run.detect_ms.len() as f64),
                ..Scores::default()
            };
            s.recall = (s.present > 0).then(|| s.read as f64 / s.present as f64);
            if let Some(d) = distances.get(name) {
                let ratios: Vec<f64> = d.values().map(|(me, kn)| me / kn).collect();
                s.pairs = ratios.len();
                s.distance_ratio_median = median(&ratios);
                s.distance_ratio_iqr = quantile(&ratios, 0.75)
                    .zip(quantile(&ratios, 0.25))
                    .map(|(a, b)| a - b);
                if m.video.is_some() {
                    s.jitter_mm_median = jitter_mm(d, None);
                    s.jitter_mm_median_common = jitter_mm(d, common.as_ref());
                }
            }
            if let Truth::RotationSteps { id, angle_deg } = &m.truth {
                s.rotation_err_deg_median = median(&rotation_errors(*id, angle_deg, run, false));
                s.rotation_err_deg_median_flip_resolved =
                    median(&rotation_errors(*id, angle_deg, run, true));
            }
            (name.clone(), s)
        })
        .collect()
}

/// Runs every method over one split; CSV rows of every read.
fn run_split(
    dir: &Path,
    m: &Manifest,
    split: &str,
    range: [usize; 2],
    opts: &EvalOptions,
    csv: &mut Csv,
) -> Result<BTreeMap<String, MethodRun>, EvalError> {
    let codes = CodeSet::from_name(&m.codes).map_err(|e| EvalError::Setup(e.to_string()))?;
    let camera = m.camera.as_ref().map(camera_model);
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
            let reads: Vec<Read> = found
                .iter()
                .map(|d| {
                    let outer_px = d
                        .corner_ids
                        .iter()
                        .zip(&d.corners_px)
                        .filter(|(cid, _)| **cid < 4)
                        .map(|(_, c)| *c)
                        .collect();
                    let solution = camera.as_ref().and_then(|cam| {
                        estimate_pose(cam, &d.object_points(m.side_m), &d.corners_px, None).ok()
                    });
                    Read {
                        id: d.id,
                        outer_px,
                        camera_from_marker: solution.map(|s| s.best.camera_from_marker),
                        alternative: solution
                            .and_then(|s| s.alternative)
                            .map(|h| h.camera_from_marker),
                    }
                })
                .collect();
            for r in &reads {
                let t = r.camera_from_marker.map(|p| p.translation.vector);
                let rv = r.camera_from_marker.map(|p| p.rotation.scaled_axis());
                let num = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.5}"));
                csv.row(vec![
                    m.name.clone(),
                    split.to_string(),
                    idx.to_string(),
                    name.to_string(),
                    method.name.clone(),
                    r.id.to_string(),
                    num(t.map(|t| t.x)),
                    num(t.map(|t| t.y)),
                    num(t.map(|t| t.z)),
                    num(rv.map(|r| r.x)),
                    num(rv.map(|r| r.y)),
                    num(rv.map(|r| r.z)),
                ]);
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
        eprintln!(
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
    let mut csv = Csv::new(&[
        "recording",
        "split",
        "frame",
        "name",
        "method",
        "id",
        "tx_m",
        "ty_m",
        "tz_m",
        "rx_rad",
        "ry_rad",
        "rz_rad",
    ]);
    let mut results = serde_json::Map::new();
    let mut table = String::from(
        "| recording / split | method | read / present | recall | false | unconfirmed | corner px | pairs | ratio IQR | jitter mm (common) | rot err ° (flip-resolved) | ms/frame |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    let mut categories = Vec::new();
    let mut recall: BTreeMap<String, Vec<Option<f64>>> = BTreeMap::new();
    for rec in &recordings {
        let (dir, m) = (&rec.dir, load_manifest(&rec.manifest)?);
        let mut per_split = serde_json::Map::new();
        for (split, range) in &m.splits {
            if opts.split.as_ref().is_some_and(|only| only != split) {
                continue;
            }
            let runs = run_split(dir, &m, split, *range, opts, &mut csv)?;
            let s = scores(&m, &runs);
            let cat = format!("{}/{split}", m.name);
            for (method, sc) in &s {
                table += &format!(
                    "| {cat} | {method} | {} / {} | {} | {} | {} | {} | {} | {} | {} ({}) | {} ({}) | {} |\n",
                    sc.read,
                    sc.present,
                    opt(sc.recall, 3),
                    sc.false_reads,
                    sc.unconfirmed,
                    opt(sc.corner_err_px_median, 2),
                    sc.pairs,
                    opt(sc.distance_ratio_iqr, 4),
                    opt(sc.jitter_mm_median, 2),
                    opt(sc.jitter_mm_median_common, 2),
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
    eprintln!("{table}");
    Ok(json!({
        "data": root.display().to_string(),
        "skipped_manifests": missing.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
        "results": results,
        "table": opts.out.join("real.md").display().to_string(),
        "plots": plots.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
    }))
}
