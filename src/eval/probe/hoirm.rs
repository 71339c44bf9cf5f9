//! `shoal eval probe hoirm`: HOIRM + shoal's detector on the frames of
//! `shoal eval detection` (same camera, marker, 600 mm with ±5 mm / ±5°
//! jitter, seed 1, same per-frame seeds), with what HOIRM estimated on each
//! frame — faster to iterate on than the experiment (HOIRM only, restoration
//! parameters set with `--restore-param`). `--scene accuracy` renders the
//! accuracy experiment's marker (610 mm, yaw 30°, ±2 mm / ±0.3°) instead and
//! prints shoal's median pose error.

use super::median;
use crate::eval::scene::{
    frame_rng, jittered_pose, render_marker_through, MARKER_ID, MARKER_SIDE_M,
};
use crate::eval::{detection, profiles, restore_params, EvalError};
use opencv::core::{Mat, Vector};
use opencv::imgcodecs;
use opencv::prelude::*;
use rand::Rng;
use shoal_node::detect::{DetectParams, ShoalDetector};
use shoal_node::pose::estimate_pose;
use shoal_node::restore::Hoirm;
use shoal_proto::geometry::Pose;
use shoal_proto::{CameraModel, CodeSet};
use shoal_sim_bridge::profile::CameraProfile;
use shoal_sim_bridge::render::Renderer;
use shoal_sim_bridge::water::{WaterParams, WaterPresets};
use std::path::PathBuf;

/// Which experiment's frames to render.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ProbeScene {
    /// `detection`: 600 mm, face-on, ±5 mm / ±5°.
    Detection,
    /// `accuracy`: 610 mm, yaw 30°, ±2 mm / ±0.3°.
    Accuracy,
}

#[derive(Debug, clap::Args)]
pub struct HoirmArgs {
    /// Water presets file (configs/water.toml format, e.g. configs/water-calibrated.toml); default the built-in presets.
    #[arg(long)]
    pub water: Option<PathBuf>,
    /// Frames per water.
    #[arg(long, default_value_t = 10)]
    pub frames: usize,
    /// Waters (1/m, comma-separated); default the detection experiment's 5.16 … 14.20.
    #[arg(long, value_delimiter = ',')]
    pub c: Vec<f64>,
    /// Which experiment's frames.
    #[arg(long, value_enum, default_value = "detection")]
    pub scene: ProbeScene,
    /// Set a HOIRM parameter (`RestoreParams` field), e.g. `--restore-param psf_px_per_unit=8`; repeatable.
    #[arg(long = "restore-param", value_name = "NAME=VALUE")]
    pub restore_param: Vec<String>,
    /// Print HOIRM's estimates for every frame (else the first of each water).
    #[arg(long)]
    pub verbose: bool,
    /// Save one restored frame per water as PNG into this folder.
    #[arg(long)]
    pub save: Option<PathBuf>,
    /// Which frame `--save` writes.
    #[arg(long, default_value_t = 0)]
    pub save_frame: usize,
    /// The camera profile the frames are rendered through, as `shoal eval
    /// detection --profile` (`ideal` by default); the detector then holds the
    /// node's calibration.
    #[command(flatten)]
    pub profile: crate::eval::profiles::ProfileArgs,
    /// Cache the rendered raw frames as PNG in this folder (and read them back on the next run).
    #[arg(long)]
    pub frame_cache: Option<PathBuf>,
}

fn imwrite(path: &std::path::Path, m: &Mat) -> Result<(), EvalError> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|source| EvalError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
    }
    imgcodecs::imwrite(&path.display().to_string(), m, &Vector::new())?;
    Ok(())
}

/// The rendered raw frame, read from `cached` when it exists there, else
/// rendered (and written to `cached` when given).
#[allow(clippy::too_many_arguments)]
fn raw_frame(
    cached: Option<&std::path::Path>,
    renderer: &mut Renderer,
    profile: Option<&CameraProfile>,
    cam: &CameraModel,
    truth: &Pose,
    water: &WaterParams,
    time_s: f64,
    noise_seed: u64,
) -> Result<Mat, EvalError> {
    let raw = match cached.filter(|p| p.exists()) {
        Some(p) => imgcodecs::imread(&p.display().to_string(), imgcodecs::IMREAD_GRAYSCALE)?,
        None => {
            let out = render_marker_through(
                renderer,
                profile,
                cam,
                CodeSet::Shoal,
                truth,
                water,
                time_s,
                noise_seed,
            )?;
            let m = shoal_node::mat::gray_to_mat(&out.image)?;
            if let Some(p) = cached {
                imwrite(p, &m)?;
            }
            m
        }
    };
    if raw.empty() {
        return Err(EvalError::Setup(format!(
            "{}: not an image",
            cached.map_or(String::new(), |p| p.display().to_string())
        )));
    }
    Ok(raw)
}

/// The camera profile the arguments name (none: the ideal renderer) and the
/// lens the detector holds through it (the node's calibration, as in `eval detection`).
fn profile_and_lens(
    a: &HoirmArgs,
    cam: &CameraModel,
) -> Result<(Option<CameraProfile>, CameraModel), EvalError> {
    let Some(p) = a.profile.selected(None)? else {
        return Ok((None, *cam));
    };
    let lens = profiles::node_camera(&p, cam, 1)?;
    Ok((Some(p), lens))
}

/// The cached frames' name prefix: the water file, the scene, the profile.
fn frame_tag(a: &HoirmArgs, profile: Option<&CameraProfile>) -> String {
    let mut tag = a.water.as_ref().map_or("shipped".to_string(), |p| {
        p.file_stem()
            .map_or("x".into(), |s| s.to_string_lossy().into_owned())
    });
    if a.scene == ProbeScene::Accuracy {
        tag.push_str("-acc");
    }
    if let Some(p) = profile {
        tag.push('-');
        tag.push_str(&p.name);
    }
    tag
}

pub fn run(a: &HoirmArgs) -> Result<(), EvalError> {
    let presets = match &a.water {
        Some(path) => WaterPresets::load(path)?,
        None => WaterPresets::builtin(),
    };
    let waters: Vec<f64> = if a.c.is_empty() {
        detection::WATERS.to_vec()
    } else {
        a.c.clone()
    };
    let (distance_m, yaw_rad, jitter_m, jitter_rad) = match a.scene {
        ProbeScene::Accuracy => (0.610, 30f64.to_radians(), 0.002, 0.3f64.to_radians()),
        ProbeScene::Detection => (detection::DISTANCE_M, 0.0, 0.005, 5f64.to_radians()),
    };
    let params = restore_params::from_assignments(&a.restore_param)?;
    let cam = CameraModel::vehicle_1440();
    let (profile, lens) = profile_and_lens(a, &cam)?;
    let tag = frame_tag(a, profile.as_ref());
    let mut renderer = Renderer::new();
    let mut detector = ShoalDetector::new(
        CodeSet::Shoal,
        DetectParams {
            lens: Some(lens),
            ..DetectParams::default()
        },
    );
    for &c in &waters {
        // The detection experiment's condition index of this water (its frame seeds).
        let wi = detection::WATERS
            .iter()
            .position(|w| (w - c).abs() < 1e-9)
            .unwrap_or(99);
        let water = presets.get(c)?;
        let mut hoirm = Hoirm::new(params.clone());
        let mut ok = 0;
        let (mut dist_err, mut ang_err) = (Vec::new(), Vec::new());
        let mut line = String::new();
        for k in 0..a.frames {
            let mut rng = frame_rng(1, 1000 + wi as u64, k as u64);
            let truth = jittered_pose(
                distance_m,
                [0.0, yaw_rad, 0.0],
                jitter_m,
                jitter_rad,
                &mut rng,
            );
            let noise_seed: u64 = rng.gen();
            let time_s = k as f64 * 0.1;
            let cached = a
                .frame_cache
                .as_ref()
                .map(|d| d.join(format!("{tag}_c{c:.2}_{k:03}.png")));
            let raw = raw_frame(
                cached.as_deref(),
                &mut renderer,
                profile.as_ref(),
                &cam,
                &truth,
                &water,
                time_s,
                noise_seed,
            )?;
            let (r, fp) = hoirm.restore_with_params(&raw, (time_s * 1e9) as u64)?;
            if let (Some(d), true) = (&a.save, k == a.save_frame) {
                imwrite(&d.join(format!("{tag}_c{c:.2}_hoirm.png")), &r.image)?;
            }
            let dets = detector.detect_in(&r.image)?;
            let found = dets.iter().any(|d| d.id == MARKER_ID);
            // Pose error of the detection with the most corners (as the experiments).
            if let Some(d) = dets
                .iter()
                .filter(|d| d.id == MARKER_ID)
                .max_by_key(|d| d.corners_px.len())
            {
                if let Ok(sol) =
                    estimate_pose(&lens, &d.object_points(MARKER_SIDE_M), &d.corners_px, None)
                {
                    let est = sol.best.camera_from_marker;
                    dist_err.push((est.translation.vector - truth.translation.vector).norm() * 1e3);
                    ang_err.push(
                        (est.rotation * truth.rotation.inverse())
                            .angle()
                            .to_degrees(),
                    );
                }
            }
            ok += usize::from(found);
            line.push(if found { '+' } else { '.' });
            if a.verbose || k == 0 {
                crate::outln!(
                    "  c {c:5.2} frame {k:3}: est c {:5.2} noise {:.2} ΔI {:5.2} B {:5.1} gain {:.2} clip {:.1} denoise σ {:.2} psf p {:.2} σ {:.2} measured {:?} rois {:?} found {found} ({} dets)",
                    fp.water.c_per_m,
                    fp.water.noise_sigma,
                    fp.water.local_contrast,
                    fp.water.backscatter,
                    fp.gain,
                    fp.clahe_clip,
                    fp.denoise_sigma_px,
                    fp.psf.p,
                    fp.psf.sigma_px,
                    fp.measured_psf_sigma_px,
                    r.rois,
                    dets.len()
                );
            }
        }
        crate::outln!(
            "c {c:5.2}: success {:.2} ({ok}/{}) {line}  median error {:.3} mm {:.3}°",
            ok as f64 / a.frames.max(1) as f64,
            a.frames,
            median(&mut dist_err),
            median(&mut ang_err)
        );
    }
    Ok(())
}
