//! `shoal eval real-twin` (issue #16): the simulator set to a real
//! recording's conditions, run through the same detectors and the same
//! scoring as the recording, so that what the simulator predicts (recall,
//! jitter, the spread of pair distances) is checked against what the real
//! frames gave.
//!
//! For each recording with a `layout` truth, a camera and a video:
//!
//! 1. **Geometry, from the real frames.** AprilTag 3 (decimate 1, a
//!    detector family other than shoal's) reads every frame; per frame the
//!    tags' measured centres are aligned to the layout by a similarity
//!    (Umeyama; every three tags not in a line propose one, the one most
//!    tags fit within 10 cm is refitted on them: a misread ID does not move
//!    the camera), for the camera's pose in the layout's frame; frames up to
//!    1 s between two aligned ones are interpolated. Each tag is placed
//!    where the frames measured it (the median of its aligned centres: the
//!    layout as built), facing and turned as most frames saw it; the frames
//!    are then aligned to that layout instead of the survey, five rounds, so
//!    that a survey error does not pull each frame its own way. The survey
//!    stays the truth the reads are scored against, so its error is in the
//!    simulated figures as in the real ones. Frames without a pose are not
//!    simulated, and not scored on the real side either (counted). Before
//!    that, each tag's **effective size** is fitted on the `dev` frames
//!    ([`tag_sizes`]: the size under which its distances to the other tags
//!    vary least from view to view; the tank's tags differ by up to 7 %),
//!    the reads are put where tags of those sizes would have been measured,
//!    and each tag is rendered at its size, so that PnP with the manifest's
//!    side errs on the twin as on the real frames. The camera's poses are
//!    then averaged over ±2 frames ([`smooth_track`]): the real camera moves
//!    smoothly, a frame's alignment carries the reads' noise.
//! 2. **Conditions, fitted on the `dev` split only.** The realistic camera
//!    profile with the recording's codec (the manifest's `codec`, else H.264
//!    for a video), its camera,
//!    marker size and, from the geometry, distance and view. Three numbers
//!    are fitted by bisection so that the simulated frames measure like the
//!    real ones at the tags' outer edges (the same measurement on both: the
//!    dark and light levels across each side's middle and the edge's width):
//!    the veiling light of the clearest water preset (contrast, dark/light),
//!    the auto-exposure's target (the light level) and the PSF's width
//!    (edge width; a Moffat of β 2.5–4.8, whose FWHM governs the edge down
//!    to the camera's own blur, see [`twin_profile`]).
//! 3. **Every split simulated** with those conditions, several seeds, the
//!    real frame's geometry and the camera's motion to the next frame; every
//!    method reads the simulated frames as it read the real ones (the node's
//!    calibration: a lab's through the port, off by the calibration error,
//!    as in `eval profiles`), scored by the same code as `eval real`. The
//!    real side is scored on the same frames.
//!
//! The verdict per method and figure: the simulated value over the real
//! one, within a factor of 2 or not.

use super::score::{scores, MethodRun, Scores};
use super::{
    data_root, find_recordings, for_frames, load_manifest, read_fields, reads_of, run_split,
    runners, verify_staged, Manifest, Truth, MANIFEST_DIR, READ_COLUMNS,
};
use crate::eval::plot::{self, Grouped};
use crate::eval::profiles::{mean_ci, node_camera, POSITIVE};
use crate::eval::table::{median, Csv};
use crate::eval::{EvalError, EvalOptions};
use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use opencv::core::Mat;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use serde_json::{json, Value};
use shoal_node::mat::GrayView;
use shoal_proto::camera::CameraModel;
use shoal_proto::geometry::Pose;
use shoal_proto::marker::CodeSet;
use shoal_sim_bridge::profile::{CameraProfile, Effect};
use shoal_sim_bridge::render::motion::{RigidMotion, Twist};
use shoal_sim_bridge::render::realistic::render_profiled;
use shoal_sim_bridge::render::{Renderer, Scene, SceneMarker};
use shoal_sim_bridge::water::{WaterParams, WaterPresets};
use std::collections::BTreeMap;
use std::path::Path;
use std::time::Instant;

/// The method whose reads give the geometry: not shoal's own detector.
const GEOMETRY_METHOD: &str = "apriltag3-d1";
/// Frames of the recordings' videos are this far apart (10 fps, as `eval real` assumes).
const FRAME_INTERVAL_S: f64 = 0.1;
/// A frame's alignment is kept when its tags fit the layout this well (RMS, m).
const MAX_ALIGN_RMS_M: f64 = 0.05;
/// A tag farther than this from the layout after alignment is not used (m).
const OUTLIER_M: f64 = 0.1;
/// The tags must span at least this much across their line (m): not collinear.
const MIN_SPREAD_M: f64 = 0.05;
/// Seeds of the simulated frames (issue #16: at least 5).
const SEEDS: u64 = 5;
const QUICK_SEEDS: u64 = 2;
/// Dev frames the conditions are fitted on, and bisection steps per number.
const FIT_FRAMES: usize = 24;
const QUICK_FIT_FRAMES: usize = 3;
const FIT_STEPS: usize = 7;
const QUICK_FIT_STEPS: usize = 5;
/// A figure is predicted when simulated / real lies within this factor.
pub const FACTOR: f64 = 2.0;

/// The camera's pose in the layout's frame per frame index.
#[derive(Debug, Default)]
struct Track {
    layout_from_camera: BTreeMap<usize, Pose>,
    rms_m: Vec<f64>,
    /// Layout distance over measured distance per aligned frame.
    scale: Vec<f64>,
    /// Frames posed between two aligned ones.
    interpolated: usize,
    frames_without: usize,
    /// The aligned frames' fits and the tags that fitted.
    fits: BTreeMap<usize, Fit>,
    inliers: BTreeMap<usize, Vec<u32>>,
}

/// The similarity taking each pair's first point onto its second (least
/// squares, Umeyama): the rotation and translation as a pose, the scale, the
/// RMS residual and the points' spread across their line (m).
#[derive(Debug, Clone, Copy)]
struct Fit {
    pose: Pose,
    scale: f64,
    rms: f64,
    spread: f64,
}

impl Fit {
    fn map(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.scale * (self.pose.rotation * p) + self.pose.translation.vector
    }
}

fn umeyama(pairs: &[(Vector3<f64>, Vector3<f64>)]) -> Option<Fit> {
    let n = pairs.len() as f64;
    if pairs.len() < 3 {
        return None;
    }
    let pc = pairs.iter().map(|p| p.0).sum::<Vector3<f64>>() / n;
    let qc = pairs.iter().map(|p| p.1).sum::<Vector3<f64>>() / n;
    let mut h = Matrix3::zeros();
    for (p, q) in pairs {
        h += (p - pc) * (q - qc).transpose();
    }
    let svd = h.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    // Spread across the line through the points: the second singular value of the centred set.
    let spread = {
        let mut c = Matrix3::zeros();
        for (p, _) in pairs {
            c += (p - pc) * (p - pc).transpose();
        }
        let mut e = c.symmetric_eigenvalues().as_slice().to_vec();
        e.sort_by(|a, b| b.total_cmp(a));
        (e[1].max(0.0) / n).sqrt()
    };
    let v = v_t.transpose();
    let d = (v * u.transpose()).determinant().signum();
    let r = v * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * u.transpose();
    // Umeyama's scale: the measured distances may all be off by one factor
    // (the recording's calibration); a uniformly scaled scene makes the same
    // image, so the camera's position is the scaled fit's.
    let var_p = pairs
        .iter()
        .map(|(p, _)| (p - pc).norm_squared())
        .sum::<f64>()
        / n;
    let sv = svd.singular_values;
    let scale = (sv[0] + sv[1] + d * sv[2]) / n / var_p;
    // `r` is orthonormal by construction (U and V are); nalgebra's iterative
    // `from_matrix` would loop without end on a degenerate set's NaNs. A set
    // without extent (one point) has no fit.
    if !(r.iter().all(|x| x.is_finite()) && scale.is_finite() && var_p > 1e-12) {
        return None;
    }
    let rotation =
        UnitQuaternion::from_rotation_matrix(&nalgebra::Rotation3::from_matrix_unchecked(r));
    let t = qc - scale * (rotation * pc);
    let pose = Pose::from_parts(t.into(), rotation);
    let rms = (pairs
        .iter()
        .map(|(p, q)| (scale * (rotation * p) + t - q).norm_squared())
        .sum::<f64>()
        / n)
        .sqrt();
    Some(Fit {
        pose,
        scale,
        rms,
        spread,
    })
}

/// The measured centres (camera frame) and surveyed centres of the tags of
/// the layout read in one frame.
fn frame_pairs(
    centres: &BTreeMap<u32, [f64; 3]>,
    reads: &[super::score::Read],
) -> Vec<(u32, Vector3<f64>, Vector3<f64>)> {
    reads
        .iter()
        .filter_map(|r| {
            let c = centres.get(&r.id)?;
            Some((
                r.id,
                r.camera_from_marker?.translation.vector,
                Vector3::from(*c),
            ))
        })
        .collect()
}

/// The best alignment of one frame's tags: every three tags not in a line
/// propose a similarity; the one that most tags fit within [`OUTLIER_M`]
/// (then the smallest residual) is refitted on those tags. A misread ID or
/// a wrong pose does not move the camera.
fn align(pairs: &[(u32, Vector3<f64>, Vector3<f64>)]) -> Option<(Fit, Vec<u32>)> {
    let pts: Vec<(Vector3<f64>, Vector3<f64>)> = pairs.iter().map(|p| (p.1, p.2)).collect();
    let n = pts.len();
    let mut best: Option<(usize, f64, Vec<usize>)> = None;
    for i in 0..n {
        for j in i + 1..n {
            for k in j + 1..n {
                let Some(f) = umeyama(&[pts[i], pts[j], pts[k]]) else {
                    continue;
                };
                if f.spread < MIN_SPREAD_M || !(0.8..=1.25).contains(&f.scale) {
                    continue;
                }
                let inliers: Vec<usize> = (0..n)
                    .filter(|&q| (f.map(&pts[q].0) - pts[q].1).norm() <= OUTLIER_M)
                    .collect();
                let sub: Vec<_> = inliers.iter().map(|&q| pts[q]).collect();
                let Some(refit) = umeyama(&sub) else { continue };
                let better = best.as_ref().is_none_or(|(count, rms, _)| {
                    inliers.len() > *count || (inliers.len() == *count && refit.rms < *rms)
                });
                if better {
                    best = Some((inliers.len(), refit.rms, inliers));
                }
            }
        }
    }
    let (_, _, inliers) = best?;
    let sub: Vec<_> = inliers.iter().map(|&q| pts[q]).collect();
    let fit = umeyama(&sub)?;
    Some((fit, inliers.iter().map(|&q| pairs[q].0).collect()))
}

/// Frames between two aligned ones at most this far apart are interpolated (s).
const MAX_INTERPOLATED_GAP_S: f64 = 1.0;

fn camera_track(
    centres: &BTreeMap<u32, [f64; 3]>,
    run: &MethodRun,
    frame_interval_s: f64,
) -> Track {
    let mut track = Track::default();
    let mut fits: BTreeMap<usize, Fit> = BTreeMap::new();
    for (idx, _, reads) in &run.frames {
        let pairs = frame_pairs(centres, reads);
        match align(&pairs) {
            Some((f, inliers)) if f.rms <= MAX_ALIGN_RMS_M && inliers.len() >= 3 => {
                fits.insert(*idx, f);
                track.rms_m.push(f.rms);
                track.scale.push(f.scale);
                track.inliers.insert(*idx, inliers);
            }
            _ => {}
        }
    }
    let max_gap = (MAX_INTERPOLATED_GAP_S / frame_interval_s).round() as usize;
    for (idx, _, _) in &run.frames {
        if let Some(f) = fits.get(idx) {
            track.layout_from_camera.insert(*idx, f.pose);
            continue;
        }
        let before = fits.range(..*idx).next_back();
        let after = fits.range(*idx..).next();
        match (before, after) {
            (Some((&a, fa)), Some((&b, fb))) if b - a <= max_gap => {
                let w = (*idx - a) as f64 / (b - a) as f64;
                let t = fa
                    .pose
                    .translation
                    .vector
                    .lerp(&fb.pose.translation.vector, w);
                let r = fa.pose.rotation.slerp(&fb.pose.rotation, w);
                track
                    .layout_from_camera
                    .insert(*idx, Pose::from_parts(t.into(), r));
                track.interpolated += 1;
            }
            _ => track.frames_without += 1,
        }
    }
    track.fits = fits;
    track
}

/// Each tag's pose in the layout's frame as the frames measured it (the
/// layout as built): its centre the median over the aligned frames of its
/// measured centre, facing the way most frames saw it, turned about the
/// layout's z axis by the median of the frames' turns. The surveyed centres
/// stay the truth the reads are scored against, so the survey's own error
/// is in the simulated figures as in the real ones.
fn tag_poses(
    run: &MethodRun,
    centres: &BTreeMap<u32, [f64; 3]>,
    track: &Track,
) -> BTreeMap<u32, Pose> {
    #[derive(Default)]
    struct Seen {
        yaws: Vec<f64>,
        facing: i64,
        at: [Vec<f64>; 3],
    }
    let mut seen: BTreeMap<u32, Seen> = BTreeMap::new();
    for (idx, _, reads) in &run.frames {
        let (Some(fit), Some(inliers)) = (track.fits.get(idx), track.inliers.get(idx)) else {
            continue;
        };
        for r in reads
            .iter()
            .filter(|r| inliers.contains(&r.id) && centres.contains_key(&r.id))
        {
            let Some(p) = r.camera_from_marker else {
                continue;
            };
            let rot = fit.pose.rotation * p.rotation;
            let x = rot * Vector3::x();
            let z = rot * Vector3::z();
            let at = fit.map(&p.translation.vector);
            let e = seen.entry(r.id).or_default();
            e.yaws.push(x.y.atan2(x.x));
            e.facing += if z.z >= 0.0 { 1 } else { -1 };
            for (k, v) in e.at.iter_mut().enumerate() {
                v.push(at[k]);
            }
        }
    }
    seen.into_iter()
        .filter_map(|(id, e)| {
            // Median of the turns about their circular mean.
            let (s, c) = e
                .yaws
                .iter()
                .fold((0.0, 0.0), |a, y| (a.0 + y.sin(), a.1 + y.cos()));
            let mean = s.atan2(c);
            let wrap = |a: f64| {
                (a + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI
            };
            let dev: Vec<f64> = e.yaws.iter().map(|y| wrap(y - mean)).collect();
            let yaw = mean + median(&dev)?;
            let mut rotation = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw);
            if e.facing < 0 {
                rotation *=
                    UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
            }
            let at = Vector3::new(median(&e.at[0])?, median(&e.at[1])?, median(&e.at[2])?);
            Some((id, Pose::from_parts(at.into(), rotation)))
        })
        .collect()
}

/// How one tag looks across its outer edge, averaged over the middle of its
/// four sides: the black border's level, the light surround's, and the
/// edge's width as the σ of a Gaussian blur (25–75 % rise / 1.349).
#[derive(Debug, Clone, Copy, Serialize)]
struct EdgeLook {
    dark: f64,
    light: f64,
    sigma_px: f64,
}

fn edge_look(img: &GrayView<'_>, outer: &[[f64; 2]], modules: usize) -> Option<EdgeLook> {
    if outer.len() != 4 {
        return None;
    }
    let centre = outer
        .iter()
        .fold([0.0, 0.0], |a, c| [a[0] + c[0] / 4.0, a[1] + c[1] / 4.0]);
    let side = (0..4)
        .map(|k| {
            let (a, b) = (outer[k], outer[(k + 1) % 4]);
            (a[0] - b[0]).hypot(a[1] - b[1])
        })
        .sum::<f64>()
        / 4.0;
    let module = side / modules as f64;
    // Out to 0.9 of a module each way: the black border inside, the light
    // quiet zone (at least one module) outside.
    let reach = 0.9 * module;
    if reach < 3.0 {
        return None;
    }
    let steps = (2.0 * reach / 0.25).round() as usize;
    let mut profile = vec![0.0; steps + 1];
    let mut lines = 0.0;
    for k in 0..4 {
        let (a, b) = (outer[k], outer[(k + 1) % 4]);
        let (tx, ty) = ((b[0] - a[0]) / side, (b[1] - a[1]) / side);
        let (mut nx, mut ny) = (-ty, tx);
        let mid = [(a[0] + b[0]) / 2.0, (a[1] + b[1]) / 2.0];
        if nx * (mid[0] - centre[0]) + ny * (mid[1] - centre[1]) < 0.0 {
            (nx, ny) = (-nx, -ny);
        }
        for f in [0.35, 0.45, 0.55, 0.65] {
            let p = [a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f];
            let (x0, y0) = (p[0] - nx * reach, p[1] - ny * reach);
            let (x1, y1) = (p[0] + nx * reach, p[1] + ny * reach);
            if !img.contains(x0, y0, 1.0) || !img.contains(x1, y1, 1.0) {
                continue;
            }
            for (j, v) in profile.iter_mut().enumerate() {
                let s = -reach + j as f64 * 0.25;
                *v += img.sample(p[0] + nx * s, p[1] + ny * s);
            }
            lines += 1.0;
        }
    }
    if lines < 8.0 {
        return None;
    }
    profile.iter_mut().for_each(|v| *v /= lines);
    let q = steps / 4;
    let dark = profile[..=q].iter().sum::<f64>() / (q + 1) as f64;
    let light = profile[steps - q..].iter().sum::<f64>() / (q + 1) as f64;
    if light - dark < 2.0 {
        return None;
    }
    let crossing = |level: f64| {
        let target = dark + level * (light - dark);
        profile.windows(2).enumerate().find_map(|(j, w)| {
            (w[0] < target && w[1] >= target).then(|| j as f64 + (target - w[0]) / (w[1] - w[0]))
        })
    };
    let rise = (crossing(0.75)? - crossing(0.25)?) * 0.25;
    Some(EdgeLook {
        dark,
        light,
        sigma_px: rise / 1.349,
    })
}

/// Medians over many tags' looks: dark / light, light, σ.
#[derive(Debug, Clone, Copy, Serialize)]
struct Looks {
    tags: usize,
    contrast: f64,
    light: f64,
    sigma_px: f64,
}

fn summarize(looks: &[EdgeLook]) -> Option<Looks> {
    let ratio: Vec<f64> = looks.iter().map(|l| l.dark / l.light).collect();
    let light: Vec<f64> = looks.iter().map(|l| l.light).collect();
    let sigma: Vec<f64> = looks.iter().map(|l| l.sigma_px).collect();
    Some(Looks {
        tags: looks.len(),
        contrast: median(&ratio)?,
        light: median(&light)?,
        sigma_px: median(&sigma)?,
    })
}

/// What the simulator is set to.
#[derive(Debug, Clone, Serialize)]
struct Conditions {
    /// The water preset by its attenuation coefficient, 1/m: the clearest
    /// (a tank's water; the recordings in the set are clear).
    c_per_m: f64,
    /// The preset's veiling light (ambient and lamp backscatter) times this.
    veil: f64,
    /// Auto-exposure's target mean (linear).
    exposure_target: f64,
    /// The PSF's FWHM, the middle of its per-frame range, px.
    psf_fwhm_px: f64,
}

/// The range the PSF's FWHM is fitted in, px.
const PSF_FWHM_RANGE_PX: (f64, f64) = (0.3, 8.0);
/// The twin's Moffat exponents: a clear water's and a lens's PSF (2.5–4.8,
/// as in astronomy), not a family the detector models.
const TWIN_MOFFAT_BETA: [f64; 2] = [2.5, 4.8];

/// The realistic profile under `cond`, with H.264 instead of JPEG when
/// `h264`. Its PSF is a Moffat only: the realistic mix's generalized
/// Gaussians of shape 0.6–1 (turbid water's heavy tails) spread an edge
/// far beyond their FWHM (p = 0.6 at 0.3 px FWHM: σ 1.3 px on a still tank
/// tag, where the rest of the camera gives 0.9), so their FWHM has no hold
/// on the narrow end of the fit. A Moffat's FWHM governs its edge down to
/// the camera's own blur (the test below).
fn twin_profile(cond: &Conditions, h264: bool, seed: u64) -> CameraProfile {
    let mut p = CameraProfile::realistic().with_seed(seed);
    if h264 {
        p.enabled.remove(&Effect::Jpeg);
        p.enabled.insert(Effect::H264);
    }
    p.params.exposure.target_mean = cond.exposure_target;
    // The tank's frames are dimmer than auto-exposure's usual floor allows.
    p.params.exposure.min_gain = 0.01;
    p.params.psf.fwhm_px = [0.75 * cond.psf_fwhm_px, 1.25 * cond.psf_fwhm_px];
    p.params.psf.moffat_share = 1.0;
    p.params.psf.moffat_beta = TWIN_MOFFAT_BETA;
    p.name = "twin".into();
    p
}

/// Everything a simulated frame needs besides its seed.
struct Twin<'a> {
    m: &'a Manifest,
    codes: CodeSet,
    camera: CameraModel,
    track: &'a Track,
    tags: &'a BTreeMap<u32, Pose>,
    /// Each tag's effective size relative to the manifest's ([`tag_sizes`]).
    sizes: &'a BTreeMap<u32, f64>,
    presets: WaterPresets,
    up: Vector3<f64>,
    frame_interval_s: f64,
    /// The recording's codec is H.264 (else JPEG).
    h264: bool,
    /// The tags' side as rendered: the manifest's times the alignment's
    /// median scale. The world is in the survey's units, where the real
    /// camera measured every distance 1/scale as long; a tag of this side
    /// makes the image the real camera saw, and PnP with the manifest's side
    /// then measures as short as it did on the real frames.
    side_m: f64,
}

impl<'a> Twin<'a> {
    fn new(
        m: &'a Manifest,
        (codes, camera): (CodeSet, CameraModel),
        (track, tags, sizes): (&'a Track, &'a BTreeMap<u32, Pose>, &'a BTreeMap<u32, f64>),
        opts: &EvalOptions,
    ) -> Result<Twin<'a>, EvalError> {
        let mean_cam_z = track
            .layout_from_camera
            .values()
            .map(|p| p.translation.vector.z)
            .sum::<f64>()
            / track.layout_from_camera.len().max(1) as f64;
        Ok(Twin {
            m,
            codes,
            camera,
            track,
            tags,
            sizes,
            presets: opts.presets()?,
            up: Vector3::new(0.0, 0.0, (mean_cam_z - Self::layout_z(m)).signum()),
            frame_interval_s: FRAME_INTERVAL_S,
            side_m: m.side_m * median(&track.scale).unwrap_or(1.0),
            h264: match m.codec.as_deref() {
                Some("h264") => true,
                Some("jpeg") => false,
                None => m.video.is_some(),
                Some(other) => {
                    return Err(EvalError::Setup(format!(
                        "{}: codec {other:?}: expected \"h264\" or \"jpeg\"",
                        m.name
                    )))
                }
            },
        })
    }

    /// The surveyed layout's mean height.
    fn layout_z(m: &Manifest) -> f64 {
        match &m.truth {
            Truth::Layout { centres_m } => {
                centres_m.values().map(|c| c[2]).sum::<f64>() / centres_m.len().max(1) as f64
            }
            _ => 0.0,
        }
    }

    /// The camera's median distance from the layout's plane, m.
    fn distance_m_median(&self) -> Option<f64> {
        let z = Self::layout_z(self.m);
        let d: Vec<f64> = self
            .track
            .layout_from_camera
            .values()
            .map(|p| (p.translation.vector.z - z).abs())
            .collect();
        median(&d)
    }

    fn profile(&self, cond: &Conditions, seed: u64) -> CameraProfile {
        twin_profile(cond, self.h264, seed)
    }

    fn water(&self, cond: &Conditions) -> Result<WaterParams, EvalError> {
        let mut w = self.presets.get(cond.c_per_m)?;
        w.backscatter_inf *= cond.veil;
        w.lamp_backscatter *= cond.veil;
        Ok(w)
    }

    /// The scene and the camera's motion over frame `idx`.
    fn timeline(&self, idx: usize) -> Option<RigidMotion> {
        let pose = *self.track.layout_from_camera.get(&idx)?;
        // The camera's motion from the poses two frames either side (one
        // frame's pose error over 0.1 s would be a fast, false motion).
        let near = |d: isize| {
            let k = idx.checked_add_signed(d)?;
            Some((d, *self.track.layout_from_camera.get(&k)?))
        };
        let before = near(-2).or_else(|| near(-1)).unwrap_or((0, pose));
        let after = near(2).or_else(|| near(1)).unwrap_or((0, pose));
        let span = (after.0 - before.0) as f64 * self.frame_interval_s;
        let (a, b, dt) = if span > 0.0 {
            (before.1, after.1, span)
        } else {
            (pose, pose, 1.0)
        };
        let step = a.inverse() * b;
        let scene = Scene {
            markers: self
                .tags
                .iter()
                .map(|(id, p)| SceneMarker {
                    codes: self.codes,
                    id: *id,
                    side_m: self.side_m * self.sizes.get(id).copied().unwrap_or(1.0),
                    world_from_marker: *p,
                    owner: 0,
                })
                .collect(),
            hulls: Vec::new(),
            up_world: self.up,
        };
        Some(RigidMotion {
            world_from_camera: pose,
            scene,
            camera: Twist {
                linear_mps: step.translation.vector / dt,
                angular_radps: step.rotation.scaled_axis() / dt,
            },
            targets: Twist::default(),
        })
    }

    /// Frame `idx` rendered under `cond` (its noise from `seed`).
    fn render(
        &self,
        renderer: &mut Renderer,
        profile: &CameraProfile,
        water: &WaterParams,
        idx: usize,
        seed: u64,
    ) -> Result<Option<(Mat, RigidMotion)>, EvalError> {
        let Some(tl) = self.timeline(idx) else {
            return Ok(None);
        };
        let noise_seed = ChaCha8Rng::seed_from_u64(seed ^ ((idx as u64) << 24)).gen();
        let f = render_profiled(
            renderer,
            profile,
            &self.camera,
            None,
            &tl,
            water,
            idx as f64 * self.frame_interval_s,
            noise_seed,
        )?;
        let mat = shoal_node::mat::gray_to_mat(&f.output.image)
            .map_err(shoal_node::detect::DetectError::from)?;
        Ok(Some((mat, tl)))
    }

    /// The looks of the simulated `frames` under `cond`.
    fn looks(
        &self,
        frames: &[usize],
        cond: &Conditions,
        seed: u64,
    ) -> Result<Option<Looks>, EvalError> {
        let profile = self.profile(cond, seed);
        let water = self.water(cond)?;
        let mut renderer = Renderer::new();
        // Measured at the outlines the same detector reads, as on the real
        // frames: the projected truth at the frame's start is off the
        // rendered edges by the motion over the exposure and the rolling
        // shutter (about a pixel here), which, averaged over a tag's four
        // sides, widened the simulated edges (σ 1.47 px at the narrowest
        // PSF against 0.9 px on a still tag).
        let mut geometry = runners(self.m, self.codes, None)?
            .into_iter()
            .find(|r| r.name == GEOMETRY_METHOD)
            .ok_or_else(|| {
                EvalError::Setup(format!("no {GEOMETRY_METHOD} detector for {}", self.codes))
            })?;
        let mut looks = Vec::new();
        for &idx in frames {
            let Some((mat, _)) = self.render(&mut renderer, &profile, &water, idx, seed)? else {
                continue;
            };
            let found = geometry.detect(&mat, idx as u64 * 100_000_000)?;
            let view = GrayView::new(&mat).map_err(shoal_node::detect::DetectError::from)?;
            looks.extend(
                reads_of(&found, None, self.side_m)
                    .iter()
                    .filter_map(|r| edge_look(&view, &r.outer_px, self.codes.modules())),
            );
        }
        Ok(summarize(&looks))
    }
}

/// Where `f` measures nothing at `x` (no tag read or no edge measured).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Unmeasured {
    /// `x` is too small (e.g. an exposure too dim to see an edge).
    BelowTarget,
    /// `x` is too large (e.g. a blur or a veil no detector reads through).
    AboveTarget,
}

/// `x` in `[lo, hi]` (geometric steps when `log`) where `f(x)` meets
/// `target`, `f` increasing in `x`; `steps` bisections; where `f` measures
/// nothing, `unmeasured` says which side of the target that is.
fn bisect(
    (mut lo, mut hi): (f64, f64),
    log: bool,
    steps: usize,
    target: f64,
    unmeasured: Unmeasured,
    mut f: impl FnMut(f64) -> Result<Option<f64>, EvalError>,
) -> Result<f64, EvalError> {
    for _ in 0..steps {
        let mid = if log {
            (lo * hi).sqrt()
        } else {
            0.5 * (lo + hi)
        };
        match (f(mid)?, unmeasured) {
            (Some(v), _) if v < target => lo = mid,
            (Some(_), _) | (None, Unmeasured::AboveTarget) => hi = mid,
            (None, Unmeasured::BelowTarget) => lo = mid,
        }
    }
    Ok(if log {
        (lo * hi).sqrt()
    } else {
        0.5 * (lo + hi)
    })
}

/// The real frames' looks at `run`'s reads (AprilTag 3's outlines).
fn real_looks(
    dir: &Path,
    m: &Manifest,
    frames: &[usize],
    run: &MethodRun,
    modules: usize,
) -> Result<Option<Looks>, EvalError> {
    let Some(&last) = frames.last() else {
        return Ok(None);
    };
    let outlines: BTreeMap<usize, Vec<Vec<[f64; 2]>>> = run
        .frames
        .iter()
        .filter(|(i, _, _)| frames.contains(i))
        .map(|(i, _, reads)| (*i, reads.iter().map(|r| r.outer_px.clone()).collect()))
        .collect();
    let mut looks = Vec::new();
    for_frames(dir, m, [frames[0], last + 1], |idx, _, gray| {
        if let Some(o) = outlines.get(&idx) {
            let view = GrayView::new(gray).map_err(shoal_node::detect::DetectError::from)?;
            looks.extend(o.iter().filter_map(|o| edge_look(&view, o, modules)));
        }
        Ok(())
    })?;
    Ok(summarize(&looks))
}

/// Real frames beside their simulated twins (one row each), as a PNG.
fn sheet(
    dir: &Path,
    twin: &Twin<'_>,
    cond: &Conditions,
    frames: &[usize],
    seed: u64,
    path: &Path,
) -> Result<(), EvalError> {
    let (Some(&first), Some(&last)) = (frames.first(), frames.last()) else {
        return Ok(());
    };
    let mut real: BTreeMap<usize, shoal_proto::GrayImage> = BTreeMap::new();
    for_frames(dir, twin.m, [first, last + 1], |idx, _, gray| {
        if frames.contains(&idx) {
            real.insert(
                idx,
                shoal_node::mat::mat_to_gray(gray)
                    .map_err(shoal_node::detect::DetectError::from)?,
            );
        }
        Ok(())
    })?;
    let profile = twin.profile(cond, seed);
    let water = twin.water(cond)?;
    let mut renderer = Renderer::new();
    let (w, h) = (twin.camera.width as usize, twin.camera.height as usize);
    let mut out = vec![0u8; 2 * w * h * frames.len()];
    for (row, idx) in frames.iter().enumerate() {
        let (Some(r), Some((sim, _))) = (
            real.get(idx),
            twin.render(&mut renderer, &profile, &water, *idx, seed)?,
        ) else {
            continue;
        };
        let sim =
            shoal_node::mat::mat_to_gray(&sim).map_err(shoal_node::detect::DetectError::from)?;
        for y in 0..h {
            let o = (row * h + y) * 2 * w;
            out[o..o + w].copy_from_slice(&r.data[y * w..(y + 1) * w]);
            out[o + w..o + 2 * w].copy_from_slice(&sim.data[y * w..(y + 1) * w]);
        }
    }
    let img = shoal_proto::GrayImage {
        width: 2 * w as u32,
        height: (h * frames.len()) as u32,
        data: out,
    };
    shoal_sim_bridge::render::write_png(&img, path)?;
    Ok(())
}

/// Keeps only the frames in `keep` of each run.
fn restrict(
    runs: &BTreeMap<String, MethodRun>,
    keep: &BTreeMap<usize, Pose>,
) -> BTreeMap<String, MethodRun> {
    runs.iter()
        .map(|(k, r)| {
            (
                k.clone(),
                MethodRun {
                    frames: r
                        .frames
                        .iter()
                        .filter(|f| keep.contains_key(&f.0))
                        .cloned()
                        .collect(),
                    detect_ms: Vec::new(),
                },
            )
        })
        .collect()
}

/// The figures compared: name, value. Jitter and spread over the pairs of
/// present markers: a method's reads of a listed ID that no other family
/// confirms (AprilTag 3's tag16h5 false positives on the real frames) are
/// counted as misses and false reads, not as the consistency the twin
/// predicts (its frames have no texture to read them in).
fn figures(s: &Scores) -> [(&'static str, Option<f64>); 4] {
    [
        ("recall", s.recall),
        ("miss", s.recall.map(|r| 1.0 - r)),
        ("jitter_mm", s.jitter_mm_median_present),
        ("distance_iqr", s.distance_ratio_iqr_present),
    ]
}

/// The tags' centres.
/// Frames either side a camera pose is averaged over ([`smooth_track`]).
const SMOOTH_HALF_FRAMES: usize = 2;

/// The camera's poses averaged over the frames within
/// [`SMOOTH_HALF_FRAMES`] either side of each, as many on each side
/// (translations by their mean, rotations by the normalised sum of their
/// quaternions, signs aligned to the frame's own). A real camera moves smoothly; a frame's alignment carries the
/// reads' noise (a few mm, tenths of a degree), which the twin would render
/// as motion, and which, seen by tags whose effective sizes differ, moves
/// their measured distances from frame to frame.
fn smooth_track(poses: &BTreeMap<usize, Pose>) -> BTreeMap<usize, Pose> {
    poses
        .iter()
        .map(|(&idx, own)| {
            // A window symmetric about the frame, over posed frames only: at
            // the track's ends and beside a gap it narrows, so a steady
            // motion is never pulled towards one side.
            let h = (1..=SMOOTH_HALF_FRAMES)
                .take_while(|&h| {
                    idx >= h && poses.contains_key(&(idx - h)) && poses.contains_key(&(idx + h))
                })
                .last()
                .unwrap_or(0);
            let near: Vec<&Pose> = poses.range(idx - h..=idx + h).map(|(_, p)| p).collect();
            let t = near
                .iter()
                .map(|p| p.translation.vector)
                .sum::<Vector3<f64>>()
                / near.len() as f64;
            let q0 = own.rotation.into_inner();
            let sum = near
                .iter()
                .fold(nalgebra::Quaternion::new(0.0, 0.0, 0.0, 0.0), |acc, p| {
                    let q = p.rotation.into_inner();
                    if q.dot(&q0) < 0.0 {
                        acc - q
                    } else {
                        acc + q
                    }
                });
            let r = UnitQuaternion::try_new(sum, 1e-9).unwrap_or(own.rotation);
            (idx, Pose::from_parts(t.into(), r))
        })
        .collect()
}

/// A tag whose pairs were measured in fewer frames of the fit split than
/// this keeps the manifest's size.
const MIN_SIZE_PAIR_FRAMES: usize = 50;
/// The effective sizes searched, relative to the manifest's, and the step.
const SIZE_RANGE: (f64, f64) = (0.85, 1.15);
const SIZE_STEP: f64 = 0.0025;
/// Rounds of the coordinate search over the tags.
const SIZE_ROUNDS: usize = 4;
/// A pair's frame farther than this (relative) from the pair's median
/// distance is left out of the size fit.
const SIZE_GROSS: f64 = 0.2;

/// Each tag's **effective size** relative to the manifest's, from the reads
/// of `run` in the frames `fit` (the tags as built, with their centres).
/// PnP with the manifest's side puts a tag whose printed side is `k` times
/// it `1/k` as far along its ray; as the camera moves, the distance from it
/// to the other tags then changes from view to view. The sizes are those
/// under which every pair's measured distance varies least across the
/// frames (relative to its mean, so the whole layout's scale stays free;
/// the most-measured tag is the reference, 1). Only a frame's `inliers`
/// (the tags its alignment kept: no misread ID) count; a tag in fewer than
/// [`MIN_SIZE_PAIR_FRAMES`] pair-frames keeps 1.
fn tag_sizes(
    run: &MethodRun,
    inliers: &BTreeMap<usize, Vec<u32>>,
    fit: std::ops::Range<usize>,
) -> BTreeMap<u32, f64> {
    // Per pair (a < b): the two centres as measured, per frame.
    type Seen = Vec<(Vector3<f64>, Vector3<f64>)>;
    let mut pairs: BTreeMap<(u32, u32), Seen> = BTreeMap::new();
    for (idx, _, reads) in run.frames.iter().filter(|f| fit.contains(&f.0)) {
        let Some(keep) = inliers.get(idx) else {
            continue;
        };
        let mut at: Vec<(u32, Vector3<f64>)> = reads
            .iter()
            .filter(|r| keep.contains(&r.id))
            .filter_map(|r| Some((r.id, r.camera_from_marker?.translation.vector)))
            .collect();
        // An ID read twice in a frame (one of them misread) is left out there.
        at.sort_by_key(|(id, _)| *id);
        let twice: Vec<u32> = at
            .windows(2)
            .filter(|w| w[0].0 == w[1].0)
            .map(|w| w[0].0)
            .collect();
        at.retain(|(id, _)| !twice.contains(id));
        for (i, (a, pa)) in at.iter().enumerate() {
            for (b, pb) in &at[i + 1..] {
                pairs.entry((*a, *b)).or_default().push((*pa, *pb));
            }
        }
    }
    // A frame whose distance is far from the pair's median is a wrong pose
    // (a flip, a misread that fitted), not the view-to-view change sought.
    for seen in pairs.values_mut() {
        let d: Vec<f64> = seen.iter().map(|(pa, pb)| (pa - pb).norm()).collect();
        if let Some(mid) = median(&d) {
            seen.retain(|(pa, pb)| ((pa - pb).norm() / mid - 1.0).abs() <= SIZE_GROSS);
        }
    }
    let mut count: BTreeMap<u32, usize> = BTreeMap::new();
    for ((a, b), seen) in &pairs {
        *count.entry(*a).or_default() += seen.len();
        *count.entry(*b).or_default() += seen.len();
    }
    let mut k: BTreeMap<u32, f64> = count.keys().map(|id| (*id, 1.0)).collect();
    let Some(reference) = count
        .iter()
        .max_by_key(|(id, n)| (**n, std::cmp::Reverse(**id)))
        .map(|(id, _)| *id)
    else {
        return k;
    };
    let free: Vec<u32> = count
        .iter()
        .filter(|(id, n)| **id != reference && **n >= MIN_SIZE_PAIR_FRAMES)
        .map(|(id, _)| *id)
        .collect();
    // Mean squared relative deviation of every pair's distance from its mean.
    let cost = |k: &BTreeMap<u32, f64>| -> f64 {
        let (mut sum, mut n) = (0.0, 0usize);
        for ((a, b), seen) in pairs.iter().filter(|(_, s)| s.len() > 1) {
            let (ka, kb) = (k[a], k[b]);
            let d: Vec<f64> = seen
                .iter()
                .map(|(pa, pb)| (pa * ka - pb * kb).norm())
                .collect();
            let mean = d.iter().sum::<f64>() / d.len() as f64;
            if mean > 0.0 {
                sum += d.iter().map(|x| (x / mean - 1.0).powi(2)).sum::<f64>();
                n += d.len();
            }
        }
        if n == 0 {
            0.0
        } else {
            sum / n as f64
        }
    };
    let steps = ((SIZE_RANGE.1 - SIZE_RANGE.0) / SIZE_STEP).round() as usize;
    for _ in 0..SIZE_ROUNDS {
        for id in &free {
            let mut best = (cost(&k), k[id]);
            for i in 0..=steps {
                let v = SIZE_RANGE.0 + i as f64 * SIZE_STEP;
                k.insert(*id, v);
                let c = cost(&k);
                if c < best.0 {
                    best = (c, v);
                }
            }
            k.insert(*id, best.1);
        }
    }
    k
}

/// `run` with every read's centre put where a tag of its effective size
/// (`sizes`) would have been measured: `k` times as far along its ray.
fn at_sizes(run: &MethodRun, sizes: &BTreeMap<u32, f64>) -> MethodRun {
    let mut out = MethodRun {
        frames: run.frames.clone(),
        detect_ms: Vec::new(),
    };
    for (_, _, reads) in &mut out.frames {
        for r in reads.iter_mut() {
            let k = sizes.get(&r.id).copied().unwrap_or(1.0);
            if let Some(p) = r.camera_from_marker.as_mut() {
                *p = Pose::from_parts((p.translation.vector * k).into(), p.rotation);
            }
        }
    }
    out
}

fn again_centres(tags: &BTreeMap<u32, Pose>) -> BTreeMap<u32, [f64; 3]> {
    tags.iter()
        .map(|(id, p)| (*id, p.translation.vector.into()))
        .collect()
}

/// The camera's track and the tags as built, from `run`'s reads.
fn geometry(
    centres_m: &BTreeMap<u32, [f64; 3]>,
    all_geometry: &MethodRun,
) -> (Track, BTreeMap<u32, Pose>) {
    // Aligned to the survey first; then, five times, to the layout as the frames
    // built it (a survey error pulls each frame's alignment its own way,
    // depending on which tags that frame saw). The survey stays the truth
    // the reads are scored against.
    let mut track = camera_track(centres_m, all_geometry, FRAME_INTERVAL_S);
    let mut tags = tag_poses(all_geometry, centres_m, &track);
    for _ in 0..5 {
        let built = again_centres(&tags);
        let next = camera_track(&built, all_geometry, FRAME_INTERVAL_S);
        if next.layout_from_camera.len() < track.layout_from_camera.len() {
            break;
        }
        let mut again = tag_poses(all_geometry, &built, &next);
        // A tag no frame fitted this time (seen at the frame's edge only)
        // keeps its place.
        for (id, p) in &tags {
            again.entry(*id).or_insert(*p);
        }
        // The survey's frame and scale, kept: a layout aligned only to the
        // previous round's is free to drift in scale (every scale is a
        // fixed point), and the tags' own size would no longer match it.
        let pairs: Vec<(Vector3<f64>, Vector3<f64>)> = again
            .iter()
            .filter_map(|(id, p)| Some((p.translation.vector, Vector3::from(*centres_m.get(id)?))))
            .collect();
        let Some(gauge) = umeyama(&pairs) else {
            break;
        };
        for p in again.values_mut() {
            *p = Pose::from_parts(
                gauge.map(&p.translation.vector).into(),
                gauge.pose.rotation * p.rotation,
            );
        }
        tags = again;
        track = camera_track(&again_centres(&tags), all_geometry, FRAME_INTERVAL_S);
    }
    (track, tags)
}

/// The conditions under which `twin`'s `fit_frames` look like the real
/// ones (`real`), by `steps` bisections per number.
fn fit_conditions(
    twin: &Twin<'_>,
    real_fit_looks: &Looks,
    fit_frames: &[usize],
    steps: usize,
    fit_seed: u64,
) -> Result<Conditions, EvalError> {
    let mut cond = Conditions {
        c_per_m: twin.presets.min_c(),
        veil: 1.0,
        exposure_target: CameraProfile::realistic().params.exposure.target_mean,
        psf_fwhm_px: 1.75,
    };
    // Contrast (the veil) and the edge (the PSF), twice round, as each
    // moves the other a little; the light level (the gain) refitted after
    // each veil, which moves it: dark/light in DN does not depend on the gain
    // (the gamma comes after it) until the light clips at 255, and a clipped
    // edge measures sharp, which drove a second round's blur to 4.5 px (the
    // synthetic twin of `tests/eval_twin.rs`, PSF 3.0 px after one round).
    let fit_exposure = |cond: &mut Conditions| -> Result<(), EvalError> {
        cond.exposure_target = bisect(
            (0.01, 0.9),
            true,
            steps,
            real_fit_looks.light,
            Unmeasured::BelowTarget,
            |t| {
                let probe = Conditions {
                    exposure_target: t,
                    ..cond.clone()
                };
                Ok(twin.looks(fit_frames, &probe, fit_seed)?.map(|l| l.light))
            },
        )?;
        Ok(())
    };
    // A first gain so the edges are measured at about the real level.
    fit_exposure(&mut cond)?;
    for _ in 0..2 {
        // A veil or a blur no detector reads through is past the target.
        cond.veil = bisect(
            (0.0, 2.0),
            false,
            steps,
            real_fit_looks.contrast,
            Unmeasured::AboveTarget,
            |k| {
                let probe = Conditions {
                    veil: k,
                    ..cond.clone()
                };
                Ok(twin
                    .looks(fit_frames, &probe, fit_seed)?
                    .map(|l| l.contrast))
            },
        )?;
        fit_exposure(&mut cond)?;
        cond.psf_fwhm_px = bisect(
            PSF_FWHM_RANGE_PX,
            true,
            steps,
            real_fit_looks.sigma_px,
            Unmeasured::AboveTarget,
            |w| {
                let probe = Conditions {
                    psf_fwhm_px: w,
                    ..cond.clone()
                };
                Ok(twin
                    .looks(fit_frames, &probe, fit_seed)?
                    .map(|l| l.sigma_px))
            },
        )?;
    }
    fit_exposure(&mut cond)?;
    Ok(cond)
}

/// Every method's scores on `frames` (of `split`) simulated under `cond`, per
/// seed; every read a row of `reads_csv` (`twin-reads.csv`).
fn simulate(
    twin: &Twin<'_>,
    cond: &Conditions,
    (split, frames): (&str, &[usize]),
    (first_seed, seeds): (u64, u64),
    (bar, reads_csv): (&indicatif::ProgressBar, &mut Csv),
) -> Result<Vec<BTreeMap<String, Scores>>, EvalError> {
    let m = twin.m;
    let water = twin.water(cond)?;
    let mut sim_scores = Vec::new();
    for s in 0..seeds {
        let seed = first_seed + s;
        let profile = twin.profile(cond, seed);
        let node_cam = node_camera(&profile, &twin.camera, seed)?;
        let mut methods = runners(m, twin.codes, Some(node_cam))?;
        let mut runs: BTreeMap<String, MethodRun> = methods
            .iter()
            .map(|r| (r.name.clone(), MethodRun::default()))
            .collect();
        let mut renderer = Renderer::new();
        for &idx in frames {
            let Some((mat, _)) = twin.render(&mut renderer, &profile, &water, idx, seed)? else {
                continue;
            };
            let stamp_ns = idx as u64 * 100_000_000;
            for method in methods.iter_mut() {
                let t0 = Instant::now();
                let found = method.detect(&mat, stamp_ns)?;
                let ms = t0.elapsed().as_secs_f64() * 1e3;
                let reads = reads_of(&found, Some(&node_cam), m.side_m);
                let run = runs.get_mut(&method.name).expect("a run per method");
                run.frames.push((idx, format!("twin#{idx}"), reads));
                run.detect_ms.push(ms);
            }
            bar.inc(1);
        }
        for (name, run) in &runs {
            for (idx, frame, reads) in &run.frames {
                for r in reads {
                    let mut row = vec![
                        m.name.clone(),
                        split.to_string(),
                        seed.to_string(),
                        idx.to_string(),
                        frame.clone(),
                        name.clone(),
                    ];
                    row.extend(read_fields(r));
                    reads_csv.row(row);
                }
            }
        }
        sim_scores.push(scores(m, &runs));
    }
    Ok(sim_scores)
}

/// Per plot (`recall`, `jitter_mm`, `distance_iqr`): the methods, and per series (real or
/// simulated, per split) a value per method.
type Plots = BTreeMap<&'static str, (Vec<String>, BTreeMap<String, Vec<Option<f64>>>)>;

/// One split's figures, real against simulated: the table's rows, the CSV's,
/// the plots' values and the JSON per method.
fn report_split(
    m: &Manifest,
    split: &str,
    (real_scores, sim_scores): (&BTreeMap<String, Scores>, &[BTreeMap<String, Scores>]),
    first_seed: u64,
    (csv, table, plots): (&mut Csv, &mut String, &mut Plots),
) -> serde_json::Map<String, Value> {
    let mut methods_json = serde_json::Map::new();
    for (method, real_s) in real_scores {
        let mut figs = serde_json::Map::new();
        let mut cells = Vec::new();
        for (k, (name, real_v)) in figures(real_s).into_iter().enumerate() {
            let per_seed: Vec<f64> = sim_scores
                .iter()
                .filter_map(|s| s.get(method).and_then(|s| figures(s)[k].1))
                .collect();
            let bounds = if matches!(name, "recall" | "miss") {
                (0.0, 1.0)
            } else {
                POSITIVE
            };
            let sim = mean_ci(&per_seed, bounds);
            let sim_mean = sim["mean"].as_f64();
            let ratio = sim_mean
                .zip(real_v)
                .and_then(|(s, r)| (r > 0.0).then(|| s / r));
            let within = ratio.map(|q| (1.0 / FACTOR..=FACTOR).contains(&q));
            for (seed_k, v) in per_seed.iter().enumerate() {
                csv.row(vec![
                    m.name.clone(),
                    split.to_string(),
                    method.clone(),
                    name.to_string(),
                    real_v.map_or(String::new(), |v| format!("{v:.5}")),
                    (first_seed + seed_k as u64).to_string(),
                    format!("{v:.5}"),
                ]);
            }
            let ci = sim["ci95"]
                .as_array()
                .and_then(|a| Some((a.first()?.as_f64()?, a.get(1)?.as_f64()?)));
            let fmt = |v: Option<f64>| v.map_or("–".to_string(), |v| format!("{v:.3}"));
            cells.push(format!(
                "{} · {}{} · {}{}",
                fmt(real_v),
                fmt(sim_mean),
                ci.map_or(String::new(), |(a, b)| format!(" ({a:.3}–{b:.3})")),
                ratio.map_or("–".to_string(), |q| format!("{q:.2}x")),
                match within {
                    Some(true) => "",
                    Some(false) => " **out**",
                    None => "",
                }
            ));
            // The miss rate is the recall's complement: no plot of its own.
            if name != "miss" {
                let entry = plots.entry(name).or_default();
                let cat = method.to_string();
                if !entry.0.contains(&cat) {
                    entry.0.push(cat.clone());
                }
                let pos = entry.0.iter().position(|c| *c == cat).unwrap_or(0);
                for (series, v) in [
                    (format!("real {split}"), real_v),
                    (format!("sim {split}"), sim_mean),
                ] {
                    let col = entry.1.entry(series).or_default();
                    if col.len() <= pos {
                        col.resize(pos + 1, None);
                    }
                    col[pos] = v;
                }
            }
            figs.insert(
                name.to_string(),
                json!({"real": real_v, "sim": sim, "ratio": ratio, "within_factor": within}),
            );
        }
        *table += &format!(
            "| {}/{split} | {method} | {} |\n",
            m.name,
            cells.join(" | ")
        );
        methods_json.insert(method.clone(), Value::Object(figs));
    }
    methods_json
}

/// What the conditions were fitted on and how close the fit came.
struct Fitted {
    conditions: Conditions,
    split: String,
    frames: Vec<usize>,
    real: Looks,
    sim: Option<Looks>,
}

/// The conditions fitted on the `dev` split's frames (the first split's
/// without one), spread over it.
fn fit_on_dev(
    dir: &Path,
    twin: &Twin<'_>,
    real: &BTreeMap<String, BTreeMap<String, MethodRun>>,
    opts: &EvalOptions,
) -> Result<Fitted, EvalError> {
    let (m, track, codes) = (twin.m, twin.track, twin.codes);
    let fit_split = fit_split_of(m);
    let dev_range = m.splits.get(fit_split).copied().unwrap_or([0, 0]);
    let dev_frames: Vec<usize> = track
        .layout_from_camera
        .keys()
        .copied()
        .filter(|i| (dev_range[0]..dev_range[1]).contains(i))
        .collect();
    let n_fit = match (opts.quick, opts.frames) {
        (true, _) => QUICK_FIT_FRAMES,
        // `--frames N`: a quarter of the frames simulated per split.
        (false, Some(n)) => (n / 4).clamp(1, FIT_FRAMES),
        (false, None) => FIT_FRAMES,
    };
    let fit_frames: Vec<usize> = if dev_frames.len() <= n_fit {
        dev_frames.clone()
    } else {
        (0..n_fit)
            .map(|k| dev_frames[k * dev_frames.len() / n_fit])
            .collect()
    };
    let real_fit_looks = real_looks(
        dir,
        m,
        &fit_frames,
        &real[fit_split][GEOMETRY_METHOD],
        codes.modules(),
    )?
    .ok_or_else(|| {
        EvalError::Setup(format!(
            "{}: no tag edge measurable on the dev frames",
            m.name
        ))
    })?;
    let steps = if opts.quick {
        QUICK_FIT_STEPS
    } else {
        FIT_STEPS
    };
    let fit_seed = opts.seed ^ 0x7_1171;
    let cond = fit_conditions(twin, &real_fit_looks, &fit_frames, steps, fit_seed)?;
    let sim_fit_looks = twin.looks(&fit_frames, &cond, fit_seed)?;
    crate::errln!(
        "{}: fitted on {} {fit_split} frames: water {:.2} /m with its veil x {:.2}, exposure target {:.3}, PSF FWHM {:.2} px; real looks {:?}, simulated {:?}",
        m.name,
        fit_frames.len(),
        cond.c_per_m,
        cond.veil,
        cond.exposure_target,
        cond.psf_fwhm_px,
        real_fit_looks,
        sim_fit_looks
    );

    Ok(Fitted {
        conditions: cond,
        split: fit_split.to_string(),
        frames: fit_frames,
        real: real_fit_looks,
        sim: sim_fit_looks,
    })
}

/// The split the conditions and the tags' sizes are fitted on: `dev`, else
/// the first.
fn fit_split_of(m: &Manifest) -> &str {
    if m.splits.contains_key("dev") {
        "dev"
    } else {
        m.splits.keys().next().map_or("dev", |s| s)
    }
}

/// The camera's track (smoothed), the tags as built and their effective
/// sizes: the sizes from the fit split's frames only (the reads the first
/// alignment kept), then the geometry again with every read where a tag of
/// its size would have been measured.
fn geometry_at_sizes(
    m: &Manifest,
    centres_m: &BTreeMap<u32, [f64; 3]>,
    all_geometry: &MethodRun,
) -> (Track, BTreeMap<u32, Pose>, BTreeMap<u32, f64>) {
    let fit_range = m.splits.get(fit_split_of(m)).copied().unwrap_or([0, 0]);
    let first = camera_track(centres_m, all_geometry, FRAME_INTERVAL_S);
    let sizes = tag_sizes(all_geometry, &first.inliers, fit_range[0]..fit_range[1]);
    let (mut track, tags) = geometry(centres_m, &at_sizes(all_geometry, &sizes));
    track.layout_from_camera = smooth_track(&track.layout_from_camera);
    crate::errln!(
        "{}: the tags' effective sizes (x the manifest's {} m; fitted on {}): {}",
        m.name,
        m.side_m,
        fit_split_of(m),
        sizes
            .iter()
            .map(|(id, k)| format!("{id} {k:.4}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    (track, tags, sizes)
}

/// One recording's twin.
fn twin_recording(
    dir: &Path,
    m: &Manifest,
    opts: &EvalOptions,
    (csv, reads_csv): (&mut Csv, &mut Csv),
    table: &mut String,
    plots: &mut Plots,
) -> Result<Value, EvalError> {
    let Truth::Layout { centres_m } = &m.truth else {
        unreachable!("filtered by the caller");
    };
    let codes = CodeSet::from_name(&m.codes).map_err(|e| EvalError::Setup(e.to_string()))?;
    let camera: CameraModel = m
        .camera
        .map(CameraModel::from)
        .ok_or_else(|| EvalError::Setup(format!("{}: a twin needs the camera", m.name)))?;
    let started = Instant::now();
    // 1. The real side, every split; the geometry from AprilTag 3's reads of all of it.
    let mut real: BTreeMap<String, BTreeMap<String, MethodRun>> = BTreeMap::new();
    for (split, range) in &m.splits {
        real.insert(split.clone(), run_split(dir, m, split, *range, opts, None)?);
    }
    let mut all_geometry = MethodRun::default();
    for runs in real.values() {
        if let Some(r) = runs.get(GEOMETRY_METHOD) {
            all_geometry.frames.extend(r.frames.iter().cloned());
        }
    }
    if all_geometry.frames.is_empty() {
        return Err(EvalError::Setup(format!(
            "{}: no {GEOMETRY_METHOD} reads to take the geometry from",
            m.name
        )));
    }
    let (track, tags, sizes) = geometry_at_sizes(m, centres_m, &all_geometry);
    let twin = Twin::new(m, (codes, camera), (&track, &tags, &sizes), opts)?;
    crate::errln!(
        "{}: camera posed in {} frames ({} of them interpolated, {} without), {} tags placed, {:.1} s",
        m.name,
        track.layout_from_camera.len(),
        track.interpolated,
        track.frames_without,
        tags.len(),
        started.elapsed().as_secs_f64()
    );

    // 2. Conditions fitted on dev frames.
    let fitted = fit_on_dev(dir, &twin, &real, opts)?;
    let cond = fitted.conditions.clone();
    let shown: Vec<usize> = [0.2, 0.5, 0.8]
        .iter()
        .filter_map(|f| {
            let keys: Vec<usize> = track.layout_from_camera.keys().copied().collect();
            keys.get(((keys.len() as f64 - 1.0) * f).round() as usize)
                .copied()
        })
        .collect();
    let sheet_path = opts.out.join(format!("twin-{}-frames.png", m.name));
    sheet(dir, &twin, &cond, &shown, opts.seed, &sheet_path)?;

    // 3. Every split simulated, several seeds, scored like the real frames.
    let seeds = if opts.quick { QUICK_SEEDS } else { SEEDS };
    let mut per_split = serde_json::Map::new();
    for (split, range) in &m.splits {
        let frames: Vec<usize> = track
            .layout_from_camera
            .keys()
            .copied()
            .filter(|i| (range[0]..range[1]).contains(i))
            .filter(|i| {
                real[split]
                    .values()
                    .next()
                    .is_some_and(|r| r.frames.iter().any(|f| f.0 == *i))
            })
            // `--frames N`: the first N posed frames of the split (consecutive,
            // so that jitter is measured), on both sides.
            .take(opts.frames.filter(|_| !opts.quick).unwrap_or(usize::MAX))
            .collect();
        let keep: BTreeMap<usize, Pose> = frames
            .iter()
            .map(|i| (*i, track.layout_from_camera[i]))
            .collect();
        let real_runs = restrict(&real[split], &keep);
        let real_scores = scores(m, &real_runs);
        let bar = opts.bar(
            frames.len() * seeds as usize,
            &format!("twin {}/{split}", m.name),
        );
        let sim_scores = simulate(
            &twin,
            &cond,
            (split, &frames),
            (opts.seed, seeds),
            (&bar, &mut *reads_csv),
        )?;
        bar.finish_and_clear();
        let methods_json = report_split(
            m,
            split,
            (&real_scores, &sim_scores),
            opts.seed,
            (&mut *csv, &mut *table, &mut *plots),
        );
        per_split.insert(
            split.clone(),
            json!({"frames": frames.len(), "seeds": seeds, "methods": methods_json}),
        );
    }
    Ok(json!({
        "frames_posed": track.layout_from_camera.len(),
        "frames_interpolated": track.interpolated,
        "frames_without_pose": track.frames_without,
        "tags_as_built": tags.iter().map(|(id, p)| (id.to_string(), json!({
            "centre_m": [p.translation.vector.x, p.translation.vector.y, p.translation.vector.z],
            "surveyed_m": centres_m.get(id),
        }))).collect::<serde_json::Map<_, _>>(),
        "alignment_rms_m_median": median(&track.rms_m),
        "alignment_scale_median": median(&track.scale),
        "side_rendered_m": twin.side_m,
        "tag_sizes_relative": sizes.iter().map(|(id, k)| (id.to_string(), json!(k))).collect::<serde_json::Map<_, _>>(),
        "tag_sizes_fitted_on": fit_split_of(m),
        "camera_distance_m_median": twin.distance_m_median(),
        "fitted_on": {"split": fitted.split, "frames": fitted.frames},
        "sheet": {"path": sheet_path.display().to_string(), "frames": shown},
        "conditions": fitted.conditions,
        "looks": {"real": fitted.real, "sim": fitted.sim},
        "splits": per_split,
        "elapsed_s": started.elapsed().as_secs_f64(),
    }))
}

/// `shoal eval real-twin`.
pub fn run(opts: &EvalOptions) -> Result<Value, EvalError> {
    let root = data_root(opts.data.as_deref())?;
    let (recordings, _) = find_recordings(&root, Path::new(MANIFEST_DIR))?;
    let mut csv = Csv::new(&[
        "recording",
        "split",
        "method",
        "figure",
        "real",
        "seed",
        "sim",
    ]);
    // Every simulated read, as `eval real`'s real.csv (plus the seed).
    let mut reads_csv = Csv::new(
        &[
            &["recording", "split", "seed", "frame", "name", "method"],
            &READ_COLUMNS[..],
        ]
        .concat(),
    );
    let mut table = String::from(
        "| recording / split | method | recall: real · sim (95 % CI) · sim/real | miss | jitter mm | distance IQR |\n|---|---|---|---|---|---|\n",
    );
    let mut plots = Plots::new();
    let mut results = serde_json::Map::new();
    for rec in &recordings {
        let m = load_manifest(&rec.manifest)?;
        let usable =
            matches!(m.truth, Truth::Layout { .. }) && m.camera.is_some() && m.video.is_some();
        if !usable {
            continue;
        }
        verify_staged(&m, &rec.dir)?;
        let v = twin_recording(
            &rec.dir,
            &m,
            opts,
            (&mut csv, &mut reads_csv),
            &mut table,
            &mut plots,
        )?;
        results.insert(m.name.clone(), v);
    }
    if results.is_empty() {
        return Err(EvalError::Setup(format!(
            "{}: no recording a twin can be made of (a video with a camera and a layout truth; docs/real-data.md)",
            root.display()
        )));
    }
    csv.write(&opts.out.join("twin.csv"))?;
    reads_csv.write(&opts.out.join("twin-reads.csv"))?;
    std::fs::write(opts.out.join("twin.md"), &table).map_err(|source| EvalError::Io {
        path: opts.out.join("twin.md"),
        source,
    })?;
    let mut plot_paths = Vec::new();
    for (key, (categories, cols)) in plots {
        let (title, y) = match key {
            "recall" => ("Real recording and its simulated twin: recall", "recall"),
            "distance_iqr" => (
                "Real recording and its simulated twin: spread (IQR) of measured / surveyed pair distance, present markers",
                "IQR of distance ratio",
            ),
            _ => (
                "Real recording and its simulated twin: jitter of a pair's distance, present markers",
                "jitter (mm)",
            ),
        };
        let series: Vec<String> = cols.keys().cloned().collect();
        let values: Vec<Vec<Option<f64>>> = cols
            .into_values()
            .map(|mut v| {
                v.resize(categories.len(), None);
                v
            })
            .collect();
        plot_paths.extend(plot::bars(
            &opts.out.join(format!("twin-{key}")),
            &Grouped {
                title: title.into(),
                x_label: "method".into(),
                y_label: y.into(),
                categories: categories.clone(),
                series,
            },
            &values,
        )?);
    }
    crate::errln!("{table}");
    Ok(json!({
        "data": root.display().to_string(),
        "factor": FACTOR,
        "results": results,
        "table": opts.out.join("twin.md").display().to_string(),
        "plots": plot_paths.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A camera moving over a floor of four tags, one of them printed 6 %
    /// larger than the manifest says (PnP puts it 1/1.06 as far along its
    /// ray): its effective size is found, the others stay at 1 within two
    /// of the search's steps; a tag seen in too few frames keeps 1, and a frame
    /// where an ID was read twice (one of them misread) changes nothing.
    #[test]
    fn the_effective_size_of_a_tag_printed_larger_is_found_from_the_views() {
        use super::super::score::Read;
        let floor: [(u32, [f64; 2]); 5] = [
            (1, [0.0, 0.0]),
            (2, [0.8, 0.0]),
            (3, [0.0, 0.8]),
            (4, [0.8, 0.8]),
            (9, [0.4, 0.4]),
        ];
        let true_size = |id: u32| if id == 3 { 1.06 } else { 1.0 };
        let read = |id: u32, at: Vector3<f64>| Read {
            id,
            outer_px: Vec::new(),
            camera_from_marker: Some(Pose::from_parts(at.into(), UnitQuaternion::identity())),
            alternative: None,
            position_cov: None,
        };
        let mut run = MethodRun::default();
        let mut inliers = BTreeMap::new();
        for idx in 0..120usize {
            // The camera 3 m above the floor, sweeping 1.2 m across it and
            // back; the floor in the camera's frame (z along the view).
            let t = idx as f64 / 119.0;
            let cam = [-0.2 + 1.2 * t, 0.4 + 0.5 * (t * 6.0).sin()];
            let mut reads = Vec::new();
            let mut ids = Vec::new();
            for (id, xy) in floor {
                // Tag 9 only in the first frames.
                if id == 9 && idx >= 10 {
                    continue;
                }
                let p = Vector3::new(xy[0] - cam[0], xy[1] - cam[1], 3.0);
                reads.push(read(id, p / true_size(id)));
                ids.push(id);
            }
            if idx % 7 == 0 {
                // Tag 2 misread where tag 1 is: an ID read twice.
                reads.push(read(2, Vector3::new(-cam[0], -cam[1], 3.0)));
            }
            run.frames.push((idx, format!("{idx}"), reads));
            inliers.insert(idx, ids);
        }
        let k = tag_sizes(&run, &inliers, 0..120);
        // Tag 1..4 each in 360 pair-frames; the reference is the lowest ID of
        // the most measured: tag 1.
        assert_eq!(k[&1], 1.0);
        // Within two of the search's steps (the sizes are searched one tag
        // at a time, each against the others' current values).
        assert!((k[&3] - 1.06).abs() <= 2.0 * SIZE_STEP + 1e-9, "{k:?}");
        for id in [2, 4] {
            assert!((k[&id] - 1.0).abs() <= 2.0 * SIZE_STEP + 1e-9, "{k:?}");
        }
        assert_eq!(k[&9], 1.0, "too few frames to fit: {k:?}");
        // Frames outside the fit range are not read.
        let none = tag_sizes(&run, &inliers, 200..300);
        assert!(none.is_empty(), "{none:?}");
        // The reads moved to where a tag of that size is measured.
        let moved = at_sizes(&run, &k);
        let r = &moved.frames[0].2[2];
        assert_eq!(r.id, 3);
        let back = r.camera_from_marker.unwrap().translation.vector;
        assert!(
            (back - Vector3::new(0.2, 0.4, 3.0)).norm() < 0.01 * 3.0,
            "{back}"
        );
    }

    /// A camera gliding at constant speed and turning at a constant rate
    /// keeps every pose (the track's ends and a gap's sides too); one whose alignments jitter ±4 mm and
    /// ±0.3° from frame to frame keeps a fifth of that.
    #[test]
    fn the_smoothed_track_keeps_steady_motion_and_averages_the_jitter_out() {
        let pose = |idx: usize, jitter: f64| {
            let sign = if idx.is_multiple_of(2) { 1.0 } else { -1.0 };
            let t = Vector3::new(0.05 * idx as f64 + sign * jitter, 0.3, 3.0);
            let yaw = 0.01 * idx as f64 + sign * jitter * 0.3_f64.to_radians() / 0.004;
            Pose::from_parts(t.into(), UnitQuaternion::from_euler_angles(0.0, 0.0, yaw))
        };
        let steady: BTreeMap<usize, Pose> = (0..20).map(|i| (i, pose(i, 0.0))).collect();
        // Every pose kept, the ends and the frames beside a gap included.
        let mut gapped = steady.clone();
        gapped.remove(&9);
        for track in [&steady, &gapped] {
            let smooth = smooth_track(track);
            assert_eq!(smooth.len(), track.len());
            for (i, p) in track {
                let d = p.inverse() * smooth[i];
                assert!(d.translation.vector.norm() < 1e-9, "frame {i}: {d:?}");
                assert!(d.rotation.angle() < 1e-6, "frame {i}: {d:?}");
            }
        }
        let noisy: BTreeMap<usize, Pose> = (0..20).map(|i| (i, pose(i, 0.004))).collect();
        let smooth = smooth_track(&noisy);
        for i in SMOOTH_HALF_FRAMES..20 - SMOOTH_HALF_FRAMES {
            let d = steady[&i].inverse() * smooth[&i];
            // Five frames of ±e average to ±e/5.
            assert!(
                (d.translation.vector.norm() - 0.0008).abs() < 1e-6,
                "frame {i}: {d:?}"
            );
            assert!(
                d.rotation.angle() < 0.07_f64.to_radians(),
                "frame {i}: {d:?}"
            );
        }
    }

    #[test]
    fn umeyama_recovers_a_similarity_and_flags_collinear_points() {
        let truth = Pose::from_parts(
            Vector3::new(0.3, -1.2, 2.0).into(),
            UnitQuaternion::from_euler_angles(0.2, -0.4, 1.1),
        );
        let layout = [
            [0.0, 0.0, 0.0],
            [0.8, 0.0, 0.0],
            [0.0, 0.8, 0.0],
            [0.8, 0.8, 0.0],
        ];
        let pairs: Vec<_> = layout
            .iter()
            .map(|q| {
                let q = nalgebra::Point3::from(Vector3::from(*q));
                ((truth.inverse() * q).coords, q.coords)
            })
            .collect();
        let fit = umeyama(&pairs).expect("a fit");
        assert!(fit.rms < 1e-9, "{fit:?}");
        assert!(fit.spread > 0.3, "{fit:?}");
        assert!((fit.scale - 1.0).abs() < 1e-9, "{fit:?}");
        let e = shoal_proto::geometry::difference(&fit.pose, &truth);
        assert!(e.norm() < 1e-9, "{e:?}");
        // Measured 5 % short: the same pose, scale 1/0.95.
        let short: Vec<_> = pairs.iter().map(|(p, q)| (p * 0.95, *q)).collect();
        let fit = umeyama(&short).expect("a fit");
        assert!(
            fit.rms < 1e-9 && (fit.scale - 1.0 / 0.95).abs() < 1e-9,
            "{fit:?}"
        );
        let e = shoal_proto::geometry::difference(&fit.pose, &truth);
        assert!(e.norm() < 1e-9, "{e:?}");
        // Three points on a line: no spread across it.
        let line = umeyama(&[
            pairs[0],
            pairs[1],
            (pairs[1].0 * 2.0 - pairs[0].0, pairs[1].1 * 2.0 - pairs[0].1),
        ])
        .expect("a fit");
        assert!(line.spread < 1e-6, "{line:?}");
        // Three times one point: no fit (and no endless iteration on NaNs).
        let one = (Vector3::new(0.1, 0.2, 1.5), Vector3::new(0.5, 0.5, 0.0));
        assert!(umeyama(&[one, one, one]).is_none());
    }

    /// A dark square of 60 px (6 modules of 10 px), levels 40 and 160,
    /// blurred by a Gaussian of `sigma` px, and its look.
    fn look_of_square(sigma: f64) -> EdgeLook {
        let (w, h) = (160usize, 160usize);
        let erf_step = |d: f64| 0.5 * (1.0 + libm_erf(d / (sigma * std::f64::consts::SQRT_2)));
        let mut data = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                // Distance outside the square [50, 110]² (negative inside).
                let dx = (50.0 - x as f64).max(x as f64 - 110.0);
                let dy = (50.0 - y as f64).max(y as f64 - 110.0);
                data[y * w + x] = (40.0 + 120.0 * erf_step(dx.max(dy))).round() as u8;
            }
        }
        let view = GrayView {
            data: &data,
            width: w,
            height: h,
            stride: w,
        };
        edge_look(
            &view,
            &[[50.0, 50.0], [110.0, 50.0], [110.0, 110.0], [50.0, 110.0]],
            6,
        )
        .expect("a look")
    }

    #[test]
    fn edge_look_measures_the_levels_and_the_blur_of_a_step() {
        for sigma in [0.8, 1.5, 2.5] {
            let look = look_of_square(sigma);
            assert!((look.dark - 40.0).abs() < 2.0, "{sigma}: {look:?}");
            assert!((look.light - 160.0).abs() < 2.0, "{sigma}: {look:?}");
            assert!(
                (look.sigma_px - sigma).abs() < 0.1 * sigma + 0.1,
                "{sigma}: {look:?}"
            );
        }
    }

    /// Abramowitz–Stegun 7.1.26 (|error| < 1.5e-7), enough for a test image.
    fn libm_erf(x: f64) -> f64 {
        let t = 1.0 / (1.0 + 0.327_591_1 * x.abs());
        let y = 1.0
            - (((((1.061_405_429 * t - 1.453_152_027) * t) + 1.421_413_741) * t - 0.284_496_736)
                * t
                + 0.254_829_592)
                * t
                * (-x * x).exp();
        y.copysign(x)
    }

    /// The median edge σ of one tag of the tank recording's size and camera
    /// (16h5, 15.55 cm at 1.5 m: ~115 px) rendered through `profile`, over
    /// four frame seeds.
    fn tank_tag_sigma(profile: &CameraProfile) -> f64 {
        let codes = CodeSet::AprilTag16h5;
        let camera = CameraModel {
            width: 640,
            height: 480,
            fx: 1127.7,
            fy: 1139.3,
            cx: 314.7,
            cy: 226.3,
            distortion: shoal_proto::camera::Distortion::PlumbBob([0.0; 5]),
        };
        let presets = WaterPresets::builtin();
        let water = presets.get(presets.min_c()).expect("the clearest preset");
        let marker = Pose::from_parts(
            Vector3::zeros().into(),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.3),
        );
        let world_from_camera = Pose::from_parts(
            Vector3::new(0.01, 0.02, 1.5).into(),
            UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0),
        );
        let tl = RigidMotion {
            world_from_camera,
            scene: Scene {
                markers: vec![SceneMarker {
                    codes,
                    id: 3,
                    side_m: 0.1555,
                    world_from_marker: marker,
                    owner: 0,
                }],
                hulls: Vec::new(),
                up_world: Vector3::z(),
            },
            camera: Twist::default(),
            targets: Twist::default(),
        };
        let outline: Vec<[f64; 2]> = codes.corners_3d(0.1555)[..4]
            .iter()
            .map(|c| {
                let p = camera
                    .project(&(world_from_camera.inverse() * (marker * c)))
                    .expect("the tag is in view");
                [p.x, p.y]
            })
            .collect();
        let mut renderer = Renderer::new();
        let sigmas: Vec<f64> = (0..4)
            .map(|seed| {
                let f = render_profiled(
                    &mut renderer,
                    profile,
                    &camera,
                    None,
                    &tl,
                    &water,
                    0.0,
                    seed,
                )
                .expect("a frame");
                let mat = shoal_node::mat::gray_to_mat(&f.output.image).expect("a Mat");
                let view = GrayView::new(&mat).expect("a view");
                edge_look(&view, &outline, codes.modules())
                    .expect("the tag's edges are measured")
                    .sigma_px
            })
            .collect();
        median(&sigmas).expect("four frames")
    }

    #[test]
    fn the_twin_psf_width_governs_the_edge_down_to_the_cameras_own_blur() {
        let cond = |psf_fwhm_px| Conditions {
            c_per_m: 0.0,
            veil: 1.0,
            exposure_target: CameraProfile::realistic().params.exposure.target_mean,
            psf_fwhm_px,
        };
        let mut without_psf = twin_profile(&cond(1.0), true, 7);
        without_psf.enabled.remove(&Effect::Psf);
        let camera_only = tank_tag_sigma(&without_psf);
        let floor = tank_tag_sigma(&twin_profile(&cond(PSF_FWHM_RANGE_PX.0), true, 7));
        let wide = tank_tag_sigma(&twin_profile(&cond(2.5), true, 7));
        // At the fit's narrowest the PSF adds almost nothing (the realistic
        // mix's heavy-tailed shapes added 0.4–0.8 px σ here), and a wider
        // one widens the edge well past it.
        assert!(
            floor < camera_only + 0.1,
            "σ {floor:.2} px at the narrowest PSF, {camera_only:.2} px without one"
        );
        assert!(
            wide > floor + 0.4,
            "σ {wide:.2} px at FWHM 2.5 px, {floor:.2} px at the narrowest"
        );
    }

    #[test]
    fn bisection_finds_where_an_increasing_function_meets_its_target() {
        let below = Unmeasured::BelowTarget;
        let x = bisect((0.01, 100.0), true, 30, 4.0, below, |x| Ok(Some(x * x))).unwrap();
        assert!((x - 2.0).abs() < 1e-3, "{x}");
        let x = bisect((0.0, 10.0), false, 30, 3.0, below, |x| Ok(Some(x + 1.0))).unwrap();
        assert!((x - 2.0).abs() < 1e-3, "{x}");
        // Nothing measured past 5 (a blur no detector reads through): still 2
        // when that side is said to be above the target; pushed to the top
        // end when it is wrongly taken as below.
        let blur = |x: f64| Ok((x < 5.0).then_some(x + 1.0));
        let x = bisect((0.0, 20.0), false, 30, 3.0, Unmeasured::AboveTarget, blur).unwrap();
        assert!((x - 2.0).abs() < 1e-3, "{x}");
        let x = bisect((0.0, 20.0), false, 30, 3.0, below, blur).unwrap();
        assert!(x > 19.9, "{x}");
    }
}
