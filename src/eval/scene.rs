//! The simulated test tank of the paper's §6: one marker in front of the
//! camera, rendered through a water preset, restored, detected and solved.
//!
//! Every marker type gets its own frame (different pattern) with the same
//! pose, water and noise seed, so the methods differ only in their marker
//! and detector; all of them go through the same restoration and the same
//! PnP (`shoal_node::pose::estimate_pose`).

use super::EvalError;
use nalgebra::{Point3, Vector3};
use opencv::core::Mat;
use opencv::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use shoal_node::baseline::{AprilTag, OpenCvAruco};
use shoal_node::detect::{DetectParams, MarkerDetector, ShoalDetector};
use shoal_node::pipeline::detect_restoration;
use shoal_node::pose::estimate_pose;
use shoal_node::restore::{restorer, Method, RestoreParams, Restored, Restorer};
use shoal_proto::geometry::Pose;
use shoal_proto::{CameraModel, CodeSet, GrayImage, MarkerId};
use shoal_sim_bridge::profile::CameraProfile;
use shoal_sim_bridge::render::motion::{RigidMotion, Twist};
use shoal_sim_bridge::render::realistic::render_profiled;
use shoal_sim_bridge::render::{facing_camera, RenderOutput, Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;

/// Footprint (outer black square) of every marker in the tests, metres.
pub const MARKER_SIDE_M: f64 = 0.100;
/// The marker ID used throughout (the paper's Fig. 4 example, in every code set).
pub const MARKER_ID: MarkerId = 17;
/// Frames are 0.1 s apart (HOIRM's ambient estimate is temporal).
pub const FRAME_INTERVAL_S: f64 = 0.1;

/// A marker and the detector that reads it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MarkerMethod {
    /// The enhanced 12-corner marker, shoal's detector.
    Shoal,
    /// ArUco 4x4_50 of the same footprint, OpenCV's detector (the baseline).
    Aruco,
    /// AprilTag 36h11 of the same footprint, libapriltag 3.
    AprilTag,
    /// The ArUco frames read by shoal's detector.
    ShoalOnAruco,
    /// The AprilTag frames read by shoal's detector.
    ShoalOnAprilTag,
}

impl MarkerMethod {
    /// The paper's three markers.
    pub const PAPER: [MarkerMethod; 3] = [
        MarkerMethod::Shoal,
        MarkerMethod::Aruco,
        MarkerMethod::AprilTag,
    ];
    /// The paper's three plus shoal's detector on the other two code sets.
    pub const ALL: [MarkerMethod; 5] = [
        MarkerMethod::Shoal,
        MarkerMethod::Aruco,
        MarkerMethod::AprilTag,
        MarkerMethod::ShoalOnAruco,
        MarkerMethod::ShoalOnAprilTag,
    ];

    pub fn name(self) -> &'static str {
        match self {
            MarkerMethod::Shoal => "shoal",
            MarkerMethod::Aruco => "aruco-opencv",
            MarkerMethod::AprilTag => "apriltag3",
            MarkerMethod::ShoalOnAruco => "aruco-shoal",
            MarkerMethod::ShoalOnAprilTag => "apriltag-shoal",
        }
    }

    /// The code set printed on the marker.
    pub fn codes(self) -> CodeSet {
        match self {
            MarkerMethod::Shoal => CodeSet::Shoal,
            MarkerMethod::Aruco | MarkerMethod::ShoalOnAruco => CodeSet::Aruco4x4_50,
            MarkerMethod::AprilTag | MarkerMethod::ShoalOnAprilTag => CodeSet::AprilTag36h11,
        }
    }

    /// The method's detector for frames of `camera` (shoal's takes the
    /// lens distortion out of its whole-pattern fit).
    pub fn detector(self, camera: &CameraModel) -> Result<Box<dyn MarkerDetector>, EvalError> {
        Ok(match self {
            MarkerMethod::Shoal | MarkerMethod::ShoalOnAruco | MarkerMethod::ShoalOnAprilTag => {
                Box::new(ShoalDetector::new(
                    self.codes(),
                    DetectParams {
                        lens: Some(*camera),
                        ..DetectParams::default()
                    },
                ))
            }
            MarkerMethod::Aruco => Box::new(OpenCvAruco::new(self.codes())?),
            MarkerMethod::AprilTag => Box::new(AprilTag::new(self.codes())?),
        })
    }
}

/// The marker's pose for one frame: `base` distance and rotation (rpy,
/// radians, about the camera axes as in [`facing_camera`]) plus a small
/// random jitter (± `jitter_m` in position, ± `jitter_rad` in each angle).
pub fn jittered_pose(
    distance_m: f64,
    rpy: [f64; 3],
    jitter_m: f64,
    jitter_rad: f64,
    rng: &mut ChaCha8Rng,
) -> Pose {
    let mut j = |a: f64| if a > 0.0 { rng.gen_range(-a..=a) } else { 0.0 };
    let xyz = [j(jitter_m), j(jitter_m), distance_m + j(jitter_m)];
    let rpy = [
        rpy[0] + j(jitter_rad),
        rpy[1] + j(jitter_rad),
        rpy[2] + j(jitter_rad),
    ];
    facing_camera(xyz, rpy)
}

/// A seeded stream for frame `frame` of condition `condition`.
pub fn frame_rng(seed: u64, condition: u64, frame: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (condition << 32) ^ frame)
}

/// Render marker `codes` #[`MARKER_ID`] at `camera_from_marker` through `water`.
pub fn render_marker(
    renderer: &mut Renderer,
    cam: &CameraModel,
    codes: CodeSet,
    camera_from_marker: &Pose,
    water: &WaterParams,
    time_s: f64,
    noise_seed: u64,
) -> Result<RenderOutput, EvalError> {
    let scene = Scene::single_marker(codes, MARKER_ID, MARKER_SIDE_M, *camera_from_marker);
    Ok(renderer.render(cam, &Pose::identity(), &scene, water, time_s, noise_seed)?)
}

/// [`render_marker`] through a camera profile (`None`: the ideal renderer).
/// The marker is held still, so only the profile's own effects apply (no
/// motion blur or shutter shear).
#[allow(clippy::too_many_arguments)]
pub fn render_marker_through(
    renderer: &mut Renderer,
    profile: Option<&CameraProfile>,
    cam: &CameraModel,
    codes: CodeSet,
    camera_from_marker: &Pose,
    water: &WaterParams,
    time_s: f64,
    noise_seed: u64,
) -> Result<RenderOutput, EvalError> {
    let Some(p) = profile else {
        return render_marker(
            renderer,
            cam,
            codes,
            camera_from_marker,
            water,
            time_s,
            noise_seed,
        );
    };
    let still = RigidMotion {
        world_from_camera: Pose::identity(),
        scene: Scene::single_marker(codes, MARKER_ID, MARKER_SIDE_M, *camera_from_marker),
        camera: Twist::default(),
        targets: Twist::default(),
    };
    Ok(render_profiled(renderer, p, cam, None, &still, water, time_s, noise_seed)?.output)
}

/// A restorer of `method` with `params` (by default HOIRM estimates the water itself).
pub fn make_restorer(method: Method, params: &RestoreParams) -> Box<dyn Restorer> {
    restorer(method, params)
}

/// Restore a rendered frame.
pub fn restore(
    restorer: &mut dyn Restorer,
    img: &GrayImage,
    stamp_ns: u64,
) -> Result<Restored, EvalError> {
    let mat = shoal_node::mat::gray_as_mat(img)?;
    let owned = mat.try_clone().map_err(shoal_node::mat::MatError::from)?;
    Ok(restorer.restore(&owned, stamp_ns)?)
}

/// What one detector made of one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Located {
    /// The right ID was decoded.
    pub decoded: bool,
    /// Detections with another ID (false positives).
    pub wrong_ids: usize,
    /// Corners used for the pose.
    pub corners: usize,
    /// The best PnP hypothesis, when the right ID was decoded and PnP succeeded.
    pub camera_from_marker: Option<Pose>,
    pub rms_px: f64,
    pub detect_ms: f64,
}

/// Detect in `restored` (as the node does: [`detect_restoration`]) and
/// solve the pose of marker #[`MARKER_ID`].
pub fn locate(
    detector: &mut dyn MarkerDetector,
    restored: &Restored,
    raw: &Mat,
    cam: &CameraModel,
) -> Result<Located, EvalError> {
    let t0 = std::time::Instant::now();
    let dets = detect_restoration(detector, restored, raw)?.detections;
    let detect_ms = t0.elapsed().as_secs_f64() * 1e3;
    let wrong_ids = dets.iter().filter(|d| d.id != MARKER_ID).count();
    // Prefer the detection with the most corners (a full enhanced marker over its code square alone).
    let best = dets
        .iter()
        .filter(|d| d.id == MARKER_ID)
        .max_by_key(|d| d.corners_px.len());
    let mut out = Located {
        decoded: best.is_some(),
        wrong_ids,
        corners: 0,
        camera_from_marker: None,
        rms_px: f64::NAN,
        detect_ms,
    };
    if let Some(d) = best {
        out.corners = d.corners_px.len();
        if let Ok(sol) = estimate_pose(cam, &d.object_points(MARKER_SIDE_M), &d.corners_px, None) {
            out.camera_from_marker = Some(sol.best.camera_from_marker);
            out.rms_px = sol.best.rms_px;
        }
    }
    Ok(out)
}

/// Position error (mm, Euclidean) and rotation error (degrees, angle of `R̂·Rᵀ`).
pub fn pose_errors(estimate: &Pose, truth: &Pose) -> (f64, f64) {
    let d = (estimate.translation.vector - truth.translation.vector).norm() * 1e3;
    let a = (estimate.rotation * truth.rotation.inverse())
        .angle()
        .to_degrees();
    (d, a)
}

/// The platform yaw (rotation about the image vertical, degrees) of a marker
/// pose built by [`facing_camera`]: the `pitch` of its `rpy`.
pub fn platform_yaw_deg(camera_from_marker: &Pose) -> f64 {
    let unflipped = camera_from_marker * facing_camera([0.0; 3], [0.0; 3]).inverse();
    shoal_proto::geometry::rpy_of(&unflipped)[1].to_degrees()
}

/// Masks of the pixels of a marker's white and of its black modules
/// (row-major, the image's size), from its known pose: each pixel's ray is
/// intersected with the marker plane and kept when it falls in the central
/// `inner` fraction (0..1) of a module, away from the blurred edges.
pub fn module_masks(
    cam: &CameraModel,
    camera_from_marker: &Pose,
    codes: CodeSet,
    id: MarkerId,
    side_m: f64,
    inner: f64,
) -> Option<(Vec<bool>, Vec<bool>)> {
    let grid = codes.module_grid(id).ok()?;
    let m = codes.modules();
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut white = vec![false; w * h];
    let mut black = vec![false; w * h];
    let marker_from_camera = camera_from_marker.inverse();
    let normal = camera_from_marker.rotation * Vector3::z();
    let origin = camera_from_marker.translation.vector;
    // Pixel bounds of the black square, from its projected corners.
    let corners: Vec<_> = codes
        .corners_3d(side_m)
        .iter()
        .take(4)
        .filter_map(|p| cam.project(&(camera_from_marker * p)))
        .collect();
    if corners.len() < 4 {
        return None;
    }
    let clampx = |v: f64| v.clamp(0.0, (w - 1) as f64) as usize;
    let clampy = |v: f64| v.clamp(0.0, (h - 1) as f64) as usize;
    let x0 = clampx(
        corners
            .iter()
            .map(|p| p.x)
            .fold(f64::INFINITY, f64::min)
            .floor(),
    );
    let x1 = clampx(
        corners
            .iter()
            .map(|p| p.x)
            .fold(f64::NEG_INFINITY, f64::max)
            .ceil(),
    );
    let y0 = clampy(
        corners
            .iter()
            .map(|p| p.y)
            .fold(f64::INFINITY, f64::min)
            .floor(),
    );
    let y1 = clampy(
        corners
            .iter()
            .map(|p| p.y)
            .fold(f64::NEG_INFINITY, f64::max)
            .ceil(),
    );
    let module = side_m / m as f64;
    let margin = 0.5 * (1.0 - inner.clamp(0.0, 1.0));
    for y in y0..=y1 {
        for x in x0..=x1 {
            let (rx, ry) = cam.ray(x as f64, y as f64);
            let d = Vector3::new(rx, ry, 1.0);
            let denom = normal.dot(&d);
            if denom.abs() < 1e-9 {
                continue;
            }
            let s = normal.dot(&origin) / denom;
            if s <= 0.0 {
                continue;
            }
            let p = marker_from_camera * Point3::from(d * s);
            // Module coordinates from the top-left of the black square.
            let u = (p.x + 0.5 * side_m) / module;
            let v = (0.5 * side_m - p.y) / module;
            if u < 0.0 || v < 0.0 || u >= m as f64 || v >= m as f64 {
                continue;
            }
            let (fu, fv) = (u.fract(), v.fract());
            if fu < margin || fu > 1.0 - margin || fv < margin || fv > 1.0 - margin {
                continue;
            }
            let cell = grid[v as usize * m + u as usize];
            let i = y * w + x;
            if cell {
                white[i] = true;
            } else {
                black[i] = true;
            }
        }
    }
    Some((white, black))
}

/// The pixel rectangle `(x, y, w, h)` covering the marker and its quiet zone
/// (one module all round) plus `pad_px`, clipped to the image.
pub fn marker_roi(
    cam: &CameraModel,
    camera_from_marker: &Pose,
    codes: CodeSet,
    side_m: f64,
    pad_px: f64,
) -> Option<(usize, usize, usize, usize)> {
    let outer = side_m * (codes.modules() as f64 + 2.0) / codes.modules() as f64;
    let pts: Vec<_> = CodeSet::AprilTag36h11
        .corners_3d(outer)
        .iter()
        .filter_map(|p| cam.project(&(camera_from_marker * p)))
        .collect();
    if pts.len() < 4 {
        return None;
    }
    let (w, h) = (cam.width as f64, cam.height as f64);
    let x0 = (pts.iter().map(|p| p.x).fold(f64::INFINITY, f64::min) - pad_px)
        .floor()
        .clamp(0.0, w - 1.0);
    let x1 = (pts.iter().map(|p| p.x).fold(f64::NEG_INFINITY, f64::max) + pad_px)
        .ceil()
        .clamp(0.0, w - 1.0);
    let y0 = (pts.iter().map(|p| p.y).fold(f64::INFINITY, f64::min) - pad_px)
        .floor()
        .clamp(0.0, h - 1.0);
    let y1 = (pts.iter().map(|p| p.y).fold(f64::NEG_INFINITY, f64::max) + pad_px)
        .ceil()
        .clamp(0.0, h - 1.0);
    let (x0, y0) = (x0 as usize, y0 as usize);
    Some((x0, y0, x1 as usize + 1 - x0, y1 as usize + 1 - y0))
}

/// Crop a grey image (or a mask) to a rectangle.
pub fn crop<T: Copy>(data: &[T], width: usize, rect: (usize, usize, usize, usize)) -> Vec<T> {
    let (x, y, w, h) = rect;
    (y..y + h)
        .flat_map(|r| data[r * width + x..r * width + x + w].iter().copied())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn platform_yaw_reads_back_the_rendered_rotation() {
        let p = facing_camera([0.0, 0.0, 0.6], [0.0, 30f64.to_radians(), 0.0]);
        assert!((platform_yaw_deg(&p) - 30.0).abs() < 1e-9);
    }

    #[test]
    fn module_masks_split_a_frontal_marker_by_colour() {
        let cam = CameraModel::vehicle_1440();
        let pose = facing_camera([0.0, 0.0, 0.6], [0.0; 3]);
        let (white, black) = module_masks(&cam, &pose, CodeSet::Shoal, 17, 0.1, 0.6).unwrap();
        let (nw, nb) = (
            white.iter().filter(|b| **b).count(),
            black.iter().filter(|b| **b).count(),
        );
        // 100 modules of ~20 px side, 60 % of each side kept: ~145 px per module.
        assert!(nw > 1000 && nb > 4000, "white {nw}, black {nb}");
        assert!(!white.iter().zip(&black).any(|(a, b)| *a && *b));
        // The top-left module is the black frame.
        let tl = cam
            .project(&(pose * Point3::new(-0.045, 0.045, 0.0)))
            .unwrap();
        let i = tl.y.round() as usize * cam.width as usize + tl.x.round() as usize;
        assert!(black[i] && !white[i]);
    }
}
