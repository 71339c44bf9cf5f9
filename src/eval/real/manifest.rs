//! The recordings `shoal eval real` measures: each one's manifest (source,
//! license, code set, camera, splits, ground truth; format in
//! `docs/real-data.md`) and where its frames are found.

use crate::eval::EvalError;
use serde::Deserialize;
use shoal_proto::camera::CameraModel;
use shoal_proto::config::IntrinsicsSpec;
use shoal_proto::marker::CodeSet;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Where `shoal eval real` looks for recordings when `--data` is not given:
/// `$SHOAL_REAL_DATA`, then these, relative to the working directory.
pub const DEFAULT_DATA_DIRS: [&str; 2] = ["../shared/data/real", "data/real"];

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
    pub camera: Option<IntrinsicsSpec>,
    /// A video file, or …
    #[serde(default)]
    pub video: Option<String>,
    /// … image files, in order.
    #[serde(default)]
    pub images: Vec<String>,
    /// How the frames were compressed on their way from the camera:
    /// `h264` or `jpeg` (default: `h264` for a video, `jpeg` for images);
    /// `eval real-twin` simulates that codec.
    #[serde(default)]
    pub codec: Option<String>,
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
    /// Where each frame file comes from, pinned: `shoal eval stage-real`
    /// copies them into the data root, and `shoal eval real` checks the
    /// staged files against their SHA-256 before measuring.
    #[serde(default)]
    pub fetch: Option<Fetch>,
}

/// The pinned upstream of a recording's files.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Fetch {
    /// GitHub `owner/name`.
    pub repo: String,
    /// The commit the files are taken from (40 hex digits).
    pub commit: String,
    pub files: Vec<FetchFile>,
}

/// One staged file: its name in the recording's folder, its path in the
/// upstream repository, and its SHA-256.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FetchFile {
    pub file: String,
    pub path: String,
    pub sha256: String,
}

impl Fetch {
    /// What is wrong with this block, if anything.
    pub fn problem(&self) -> Option<String> {
        let hex = |s: &str, n: usize| s.len() == n && s.bytes().all(|b| b.is_ascii_hexdigit());
        let mut parts = self.repo.split('/');
        let repo_ok = matches!((parts.next(), parts.next(), parts.next()), (Some(o), Some(n), None)
            if !o.is_empty() && !n.is_empty()
                && self.repo.bytes().all(|b| b.is_ascii_alphanumeric() || b"-_./".contains(&b))
                && !self.repo.contains(".."));
        if !repo_ok {
            return Some(format!(
                "fetch.repo {:?} is not a GitHub owner/name",
                self.repo
            ));
        }
        if !hex(&self.commit, 40) {
            return Some(format!(
                "fetch.commit {:?} is not a 40-digit commit",
                self.commit
            ));
        }
        if self.files.is_empty() {
            return Some("fetch.files is empty".into());
        }
        for f in &self.files {
            let plain = !f.file.is_empty()
                && !f.file.contains(['/', '\\'])
                && f.file != "."
                && f.file != "..";
            if !plain {
                return Some(format!(
                    "fetch.files: {:?} must be a plain file name",
                    f.file
                ));
            }
            if f.path.is_empty() || f.path.starts_with('/') || f.path.split('/').any(|c| c == "..")
            {
                return Some(format!(
                    "fetch.files: path {:?} must be relative to the repository",
                    f.path
                ));
            }
            if !hex(&f.sha256, 64) {
                return Some(format!(
                    "fetch.files: sha256 of {:?} is not 64 hex digits",
                    f.file
                ));
            }
        }
        None
    }
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
    pub(super) fn kind(&self) -> &'static str {
        match self {
            Truth::Layout { .. } => "layout",
            Truth::Corners { .. } => "corners",
            Truth::RotationSteps { .. } => "rotation_steps",
        }
    }
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
        if let Some(p) = CameraModel::from(c).problem() {
            return Err(bad(format!("camera: {p}")));
        }
    }
    if let Some(p) = m.fetch.as_ref().and_then(Fetch::problem) {
        return Err(bad(p));
    }
    Ok(m)
}
