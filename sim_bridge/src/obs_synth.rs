//! Observation-level synthesizer: relative-pose [`Observation`]s straight from
//! ground truth, without rendering a pixel, so fusion can be exercised with
//! hundreds of vehicles.
//!
//! For every observer camera and every marker of every other vehicle:
//!
//! - **visibility**: the marker centre is in front of the camera and inside its
//!   image (pinhole, distortion ignored), within [`VisibilityModel::max_range_m`]
//!   (4 m: the paper's effective range at c = 0.5/m, §6.3), seen from its front
//!   side at an incidence below [`VisibilityModel::max_incidence_deg`], and
//!   detected with a probability that falls with range. Hulls do not occlude
//!   each other here.
//! - **noise** ([`NoiseModel`]): a perturbation of `camera_from_marker` drawn in
//!   the camera frame, σ growing with range; the observation carries the
//!   matching covariance propagated to `observer_from_target` (body frames,
//!   [`shoal_proto::geometry`] convention), so the noise is exactly what the
//!   covariance claims.
//! - **outliers** ([`OutlierModel`]), each labelled ([`OutlierKind`]) for
//!   precision/recall: a wrong marker ID (another vehicle's, or one no vehicle
//!   carries), and the planar flip: the IPPE twin of the marker pose, the
//!   marker's normal mirrored about the line of sight, reported as the primary
//!   hypothesis with the true (noisy) pose as `alternative`.
//!
//! Deterministic for a seed (ChaCha8). [`synthetic_fleet`] builds fleets of N
//! vehicles and [`grid_formation`] / [`line_abreast`] their ground truth.

use nalgebra::{Matrix6, Unit, UnitQuaternion, Vector3, Vector6};
use rand::Rng;
use rand_chacha::rand_core::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use shoal_proto::config::{Fleet, MarkerOwner};
use shoal_proto::geometry::{compose_jacobians, perturb, pose_from_xyz_rpy, Cov6, Pose};
use shoal_proto::{
    CodeSet, ImageQuality, MarkerId, Observation, PoseHypothesis, VehicleId, VehicleTruth,
};
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// Errors of this module.
#[derive(Debug, thiserror::Error)]
pub enum ObsSynthError {
    #[error("a synthetic fleet of {n} vehicles needs {needed} IDs but {codes} has {available}")]
    TooManyVehicles {
        n: usize,
        needed: usize,
        codes: &'static str,
        available: usize,
    },
    #[error("a synthetic fleet needs at least one vehicle")]
    EmptyFleet,
    #[error("generated fleet file is invalid: {0}")]
    Fleet(#[from] shoal_proto::config::ConfigError),
}

/// Measurement noise of one marker pose, in the camera frame.
///
/// The defaults are fitted to what the image-level pipeline (render at
/// 0.5 /m → HOIRM → shoal's detector → PnP) measures for a 100 mm enhanced
/// marker seen by the 1440x1080, 60° vehicle camera, face-on and at 30°
/// (`shoal eval fit-noise --frames 30`, docs/results.md): at 1.75 m, 0.1 mm
/// across, 2.4 mm in depth, 0.4° of tilt. Planar flips (a quarter to a third
/// of the poses between 1.25 and 2.25 m) are not noise: they are the
/// [`OutlierModel`]'s `flip_rate`. Beyond 2 m the pipeline's depth error
/// steps up (18.6 mm measured at 2.25 m, where the fit gives 3.4 mm) as the
/// inner corners are lost; the model does not follow that step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NoiseModel {
    /// σ of the position across the line of sight, metres per metre of range.
    pub lateral_std_per_m: f64,
    /// σ of the position along the line of sight (depth), metres per metre of range…
    pub depth_std_per_m: f64,
    /// …plus this times the range squared, metres per m² (PnP's depth error
    /// grows with the square of the range at a fixed pixel noise).
    pub depth_std_per_m2: f64,
    /// Added to both translation σ, metres.
    pub translation_std_floor_m: f64,
    /// σ of the marker's tilt (rotation about the camera x and y axes), radians, at zero range.
    pub tilt_std_rad: f64,
    /// Growth of the tilt σ with range, radians per metre.
    pub tilt_std_per_m: f64,
    /// σ of the rotation about the optical axis, radians.
    pub roll_std_rad: f64,
    /// When given, the depth σ (beyond the floor) at a range is read from
    /// this table of (range m, σ m) instead of the lines above: linear
    /// between its rows, its end values beyond them. For a pipeline whose
    /// depth error steps up where the marker's inner corners are lost,
    /// which no line or parabola follows.
    pub depth_std_table: Option<&'static [(f64, f64)]>,
}

impl Default for NoiseModel {
    fn default() -> Self {
        Self {
            lateral_std_per_m: 0.000064,
            depth_std_per_m: 0.00086,
            depth_std_per_m2: 0.00028,
            // The fit's intercepts are zero; a floor keeps covariances invertible at any range.
            translation_std_floor_m: 0.00001,
            tilt_std_rad: 0.05f64.to_radians(),
            tilt_std_per_m: 0.23f64.to_radians(),
            roll_std_rad: 0.13f64.to_radians(),
            depth_std_table: None,
        }
    }
}

/// `table`'s value at `x`: linear between rows (sorted by x), the end
/// values beyond them.
fn interpolate(table: &[(f64, f64)], x: f64) -> f64 {
    let (Some(first), Some(last)) = (table.first(), table.last()) else {
        return 0.0;
    };
    if x <= first.0 {
        return first.1;
    }
    table.windows(2).find(|w| x <= w[1].0).map_or(last.1, |w| {
        let t = (x - w[0].0) / (w[1].0 - w[0].0).max(1e-12);
        w[0].1 + t * (w[1].1 - w[0].1)
    })
}

impl NoiseModel {
    /// Covariance of `camera_from_marker` at `range_m` (camera frame, translation then rotation).
    pub fn camera_covariance(&self, range_m: f64) -> Cov6 {
        let lat = self.translation_std_floor_m + self.lateral_std_per_m * range_m;
        let depth = self.translation_std_floor_m
            + match self.depth_std_table {
                Some(t) => interpolate(t, range_m),
                None => self.depth_std_per_m * range_m + self.depth_std_per_m2 * range_m * range_m,
            };
        let tilt = self.tilt_std_rad + self.tilt_std_per_m * range_m;
        Cov6::from_diagonal(&Vector6::new(
            lat * lat,
            lat * lat,
            depth * depth,
            tilt * tilt,
            tilt * tilt,
            self.roll_std_rad * self.roll_std_rad,
        ))
    }
}

/// A camera's systematic error: the same on every frame it takes, drawn once
/// per camera. A node holds an in-water calibration a little off from its
/// lens and port (`realistic` camera profile: fx ±0.3 %, principal point
/// ±2 px, the flat port's residual); what that does to a marker pose is a
/// position error growing with range (a focal length off scales the depth,
/// a principal point off turns the line of sight) and a constant rotation.
/// Frames of one camera do not average it away, nor do several frames
/// fused: only other cameras' views do. Each σ is across cameras; zero
/// (the default, the ideal camera) draws nothing.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct BiasModel {
    /// σ of the position bias across the line of sight (x and y each), metres per metre of range.
    pub lateral_std_per_m: f64,
    /// σ of the position bias along the line of sight, metres per metre of range.
    pub depth_std_per_m: f64,
    /// A depth bias common to every camera (the same lens, port and
    /// calibration procedure): this many metres, plus `depth_mean_per_m`
    /// per metre of range. No node knows it (it would correct it), so it is
    /// not in the reported covariance.
    pub depth_mean_m: f64,
    pub depth_mean_per_m: f64,
    /// σ of the rotation bias about the camera x and y axes, radians.
    pub tilt_std_rad: f64,
    /// σ of the rotation bias about the optical axis, radians.
    pub roll_std_rad: f64,
}

impl BiasModel {
    /// No bias drawn at all (the ideal camera).
    pub fn is_zero(&self) -> bool {
        *self == BiasModel::default()
    }

    /// The σ of each component of a camera's bias at `range_m` (camera
    /// frame, translation then rotation, as [`NoiseModel::camera_covariance`]).
    pub fn std_at(&self, range_m: f64) -> Vector6<f64> {
        let lat = self.lateral_std_per_m * range_m;
        let depth = self.depth_std_per_m * range_m;
        Vector6::new(
            lat,
            lat,
            depth,
            self.tilt_std_rad,
            self.tilt_std_rad,
            self.roll_std_rad,
        )
    }

    /// Covariance of the bias over cameras at `range_m`: what an honest
    /// node adds to its per-frame covariance for a calibration of this
    /// uncertainty.
    pub fn camera_covariance(&self, range_m: f64) -> Cov6 {
        Cov6::from_diagonal(&self.std_at(range_m).map(|s| s * s))
    }
}

/// Which markers a camera detects.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VisibilityModel {
    pub max_range_m: f64,
    /// Largest angle between the marker's normal and the direction to the camera.
    pub max_incidence_deg: f64,
    /// Detection probability up to `full_detection_range_m`…
    pub detection_prob_near: f64,
    pub full_detection_range_m: f64,
    /// …falling linearly to this at `max_range_m`.
    pub detection_prob_at_max: f64,
}

impl Default for VisibilityModel {
    /// Ranges as measured by `shoal eval fit-noise` (100 mm enhanced marker,
    /// vehicle camera, 0.5 /m): every frame read up to 2.25 m, 5/60 at
    /// 2.75 m, 1/60 at 3.25 m, none at 4 m.
    fn default() -> Self {
        Self {
            max_range_m: 3.25,
            max_incidence_deg: 70.0,
            detection_prob_near: 0.99,
            full_detection_range_m: 2.25,
            detection_prob_at_max: 0.02,
        }
    }
}

impl VisibilityModel {
    pub fn detection_probability(&self, range_m: f64) -> f64 {
        if range_m > self.max_range_m {
            0.0
        } else if range_m <= self.full_detection_range_m {
            self.detection_prob_near
        } else {
            let f = (range_m - self.full_detection_range_m)
                / (self.max_range_m - self.full_detection_range_m).max(1e-9);
            self.detection_prob_near + f * (self.detection_prob_at_max - self.detection_prob_near)
        }
    }
}

/// Outlier injection rates (per detected observation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OutlierModel {
    /// Probability the ID read is another vehicle's marker.
    pub wrong_id_rate: f64,
    /// Probability the ID read is one no vehicle carries.
    pub unknown_id_rate: f64,
    /// Probability the primary hypothesis is the planar flip (when the flip is
    /// at least `min_flip_deg` away from the truth; smaller "flips" are
    /// indistinguishable from noise and are not generated).
    pub flip_rate: f64,
    pub min_flip_deg: f64,
    /// Probability a correct observation still reports its twin as `alternative`.
    pub alternative_rate: f64,
    /// When given, the flip probability at a range is at least this
    /// table's (range m, probability), read as [`NoiseModel::depth_std_table`]:
    /// a pipeline that flips more often as the marker shrinks.
    pub flip_rate_table: Option<&'static [(f64, f64)]>,
}

impl Default for OutlierModel {
    fn default() -> Self {
        Self {
            wrong_id_rate: 0.0,
            unknown_id_rate: 0.0,
            flip_rate: 0.0,
            min_flip_deg: 15.0,
            alternative_rate: 0.5,
            flip_rate_table: None,
        }
    }
}

/// All settings of the synthesizer.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ObsSynthParams {
    pub noise: NoiseModel,
    /// Per-camera systematic error (default none).
    pub bias: BiasModel,
    pub visibility: VisibilityModel,
    pub outliers: OutlierModel,
}

impl ObsSynthParams {
    /// Observations as the `realistic` camera profile's pipeline makes them
    /// (render at 0.5 /m through every camera effect → HOIRM → shoal's
    /// detector → PnP with the node's in-water calibration): fitted to
    /// `shoal eval fit-noise --profile realistic --frames 20 --seed S`,
    /// seeds 1–5 (one calibration each; docs/results.md, *fit-noise*).
    /// Per camera a bias (the calibration's and port's error: 0.8 mm/m
    /// across and 0.7 mm/m along the line of sight, 0.15° of tilt between
    /// cameras, and a depth bias all five calibrations shared, 3.5 mm +
    /// 2.4 mm/m); around it, frame-to-frame noise (0.03 mm/m across, depth
    /// 0.8 mm at 0.75 m and 1.2 mm at 1.25 m stepping to 32 mm at 1.75 m,
    /// tilt 0.25°/m, roll 0.03°); reads to 2.1 m (95 % to 1.25 m, 66 % at
    /// 1.75 m) with flips rising to half the reads at 1.75 m.
    pub fn realistic() -> ObsSynthParams {
        ObsSynthParams {
            noise: NoiseModel {
                lateral_std_per_m: 0.00003,
                depth_std_per_m: 0.0,
                depth_std_per_m2: 0.0,
                translation_std_floor_m: 0.00001,
                tilt_std_rad: 0.0,
                tilt_std_per_m: 0.25f64.to_radians(),
                roll_std_rad: 0.03f64.to_radians(),
                depth_std_table: Some(&[(0.75, 0.00078), (1.25, 0.00124), (1.75, 0.0316)]),
            },
            bias: BiasModel {
                lateral_std_per_m: 0.0008,
                depth_std_per_m: 0.0007,
                depth_mean_m: 0.0035,
                depth_mean_per_m: 0.0024,
                tilt_std_rad: 0.15f64.to_radians(),
                roll_std_rad: 0.003f64.to_radians(),
            },
            visibility: VisibilityModel {
                max_range_m: 2.1,
                max_incidence_deg: 70.0,
                detection_prob_near: 0.95,
                full_detection_range_m: 1.25,
                detection_prob_at_max: 0.45,
            },
            outliers: OutlierModel {
                flip_rate_table: Some(&[(0.75, 0.0), (1.25, 0.09), (1.75, 0.53)]),
                ..OutlierModel::default()
            },
        }
    }
}

/// Ground-truth label of a synthetic observation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum OutlierKind {
    /// Correct ID, primary hypothesis true (the alternative, if any, is the twin).
    Inlier,
    /// The ID of another vehicle's marker: no hypothesis is true.
    WrongId,
    /// An ID no vehicle carries.
    UnknownId,
    /// Primary is the planar flip; the alternative is true.
    Flipped,
}

/// One synthetic observation with its ground truth.
#[derive(Debug, Clone, PartialEq)]
pub struct SyntheticObservation {
    pub obs: Observation,
    /// The vehicle actually seen.
    pub true_target: VehicleId,
    /// True `observer_from_target` of the vehicle actually seen.
    pub truth_observer_from_target: Pose,
    pub outlier: OutlierKind,
    /// Angle between the true marker pose and its planar-flip twin, radians.
    pub twin_angle_rad: f64,
}

impl SyntheticObservation {
    /// Whether hypothesis `h` (0 primary, 1 alternative) of this observation is true.
    pub fn hypothesis_is_true(&self, h: u8) -> bool {
        matches!(
            (self.outlier, h),
            (OutlierKind::Inlier, 0) | (OutlierKind::Flipped, 1)
        )
    }
}

/// The synthesizer. One call of [`ObsSynth::observe`] is one frame of every camera.
#[derive(Debug, Clone)]
pub struct ObsSynth {
    fleet: Fleet,
    params: ObsSynthParams,
    rng: ChaCha8Rng,
    seed: u64,
    /// Each camera's bias in σ units, drawn at its first observation from a
    /// stream of its own (so the other draws do not depend on it).
    biases: BTreeMap<(VehicleId, u8), Vector6<f64>>,
    frame_seq: BTreeMap<(VehicleId, u8), u64>,
    /// Every (code set, ID) carried, for wrong-ID draws.
    markers: Vec<(CodeSet, MarkerId, VehicleId)>,
}

/// The planar-flip (IPPE) twin of `camera_from_marker`: the marker normal
/// mirrored about the line of sight, same position. Returns the twin and the
/// angle between the two rotations.
pub fn planar_flip_twin(camera_from_marker: &Pose) -> (Pose, f64) {
    let p = camera_from_marker.translation.vector;
    let n = camera_from_marker.rotation * Vector3::z();
    let v = -p / p.norm().max(1e-12);
    let axis = n.cross(&v);
    let theta = n.dot(&v).clamp(-1.0, 1.0).acos();
    if axis.norm() < 1e-9 {
        return (*camera_from_marker, 0.0);
    }
    let rot = UnitQuaternion::from_axis_angle(&Unit::new_normalize(axis), 2.0 * theta);
    let mut twin = *camera_from_marker;
    twin.rotation = rot * camera_from_marker.rotation;
    (twin, 2.0 * theta)
}

impl ObsSynth {
    pub fn new(fleet: &Fleet, params: ObsSynthParams, seed: u64) -> Self {
        let mut markers: Vec<(CodeSet, MarkerId, VehicleId)> = fleet
            .vehicles
            .iter()
            .flat_map(|v| v.markers.iter().map(move |m| (m.codes, m.id, v.id)))
            .collect();
        markers.sort_by_key(|(c, id, v)| (c.name(), *id, *v));
        Self {
            fleet: fleet.clone(),
            params,
            rng: ChaCha8Rng::seed_from_u64(seed),
            seed,
            biases: BTreeMap::new(),
            frame_seq: BTreeMap::new(),
            markers,
        }
    }

    pub fn params(&self) -> &ObsSynthParams {
        &self.params
    }

    /// Camera `camera` of `observer`'s bias at `range_m`, camera frame
    /// (translation then rotation, as [`perturb`] takes it).
    pub fn camera_bias(&mut self, observer: VehicleId, camera: u8, range_m: f64) -> Vector6<f64> {
        let seed = self.seed;
        let unit = *self.biases.entry((observer, camera)).or_insert_with(|| {
            let mut rng = ChaCha8Rng::seed_from_u64(
                seed ^ 0xB1A5_0000_0000_0000 ^ (u64::from(observer) << 8) ^ u64::from(camera),
            );
            Vector6::from_fn(|_, _| StandardNormal.sample(&mut rng))
        });
        let b = &self.params.bias;
        let mut bias = unit.component_mul(&b.std_at(range_m));
        bias[2] += b.depth_mean_m + b.depth_mean_per_m * range_m;
        bias
    }

    fn gaussian6(&mut self, cov: &Cov6) -> Vector6<f64> {
        let l = cov.cholesky().map(|c| c.l()).unwrap_or_else(Matrix6::zeros);
        let z = Vector6::from_fn(|_, _| StandardNormal.sample(&mut self.rng));
        l * z
    }

    /// One frame of every camera of every vehicle with a truth entry, captured at `stamp_ns`.
    pub fn observe(&mut self, truth: &[VehicleTruth], stamp_ns: u64) -> Vec<SyntheticObservation> {
        let world_from: BTreeMap<VehicleId, Pose> = truth
            .iter()
            .map(|t| (t.vehicle, t.world_from_body))
            .collect();
        let fleet = self.fleet.clone();
        let params = self.params;
        let mut out = Vec::new();
        for observer in &fleet.vehicles {
            let Some(world_from_obs) = world_from.get(&observer.id) else {
                continue;
            };
            for cam in &observer.cameras {
                let seq = self.frame_seq.entry((observer.id, cam.index)).or_insert(0);
                *seq += 1;
                let frame_seq = *seq;
                let world_from_cam = world_from_obs * cam.body_from_camera;
                // Detections of this frame first, so that a misread never
                // takes an ID this camera reads correctly in the same frame
                // (the node would report two detections of one ID).
                let mut detected = Vec::new();
                for target in &fleet.vehicles {
                    if target.id == observer.id {
                        continue;
                    }
                    let Some(world_from_tgt) = world_from.get(&target.id) else {
                        continue;
                    };
                    for marker in &target.markers {
                        let cam_from_marker =
                            world_from_cam.inverse() * world_from_tgt * marker.body_from_marker;
                        let p = cam_from_marker.translation.vector;
                        let range = p.norm();
                        if p.z <= 0.0 || range > params.visibility.max_range_m {
                            continue;
                        }
                        let m = &cam.model;
                        let (u, v) = (m.fx * p.x / p.z + m.cx, m.fy * p.y / p.z + m.cy);
                        if u < 0.0
                            || v < 0.0
                            || u > m.width as f64 - 1.0
                            || v > m.height as f64 - 1.0
                        {
                            continue;
                        }
                        let normal = cam_from_marker.rotation * Vector3::z();
                        let incidence = normal.dot(&(-p / range)).clamp(-1.0, 1.0).acos();
                        if incidence > params.visibility.max_incidence_deg.to_radians() {
                            continue;
                        }
                        if !self.rng.gen_bool(
                            params
                                .visibility
                                .detection_probability(range)
                                .clamp(0.0, 1.0),
                        ) {
                            continue;
                        }
                        detected.push((
                            target.id,
                            marker.clone(),
                            cam_from_marker,
                            world_from_obs.inverse() * world_from_tgt,
                        ));
                    }
                }
                let mut ids_in_frame: BTreeSet<(&'static str, MarkerId)> = detected
                    .iter()
                    .map(|(_, m, _, _)| (m.codes.name(), m.id))
                    .collect();
                for (target, marker, cam_from_marker, truth) in detected {
                    out.push(self.measure(
                        observer.id,
                        cam.index,
                        frame_seq,
                        stamp_ns,
                        &cam.body_from_camera,
                        &cam_from_marker,
                        target,
                        marker.codes,
                        marker.id,
                        &marker.body_from_marker,
                        &truth,
                        &mut ids_in_frame,
                    ));
                }
            }
        }
        out
    }

    fn measure(
        &mut self,
        observer: VehicleId,
        camera: u8,
        frame_seq: u64,
        stamp_ns: u64,
        body_from_camera: &Pose,
        cam_from_marker: &Pose,
        target: VehicleId,
        codes: CodeSet,
        marker_id: MarkerId,
        body_from_marker: &Pose,
        truth: &Pose,
        ids_in_frame: &mut BTreeSet<(&'static str, MarkerId)>,
    ) -> SyntheticObservation {
        let o = self.params.outliers;
        let range = cam_from_marker.translation.vector.norm();
        let mut cam_cov = self.params.noise.camera_covariance(range);
        let measured = if self.params.bias.is_zero() {
            perturb(cam_from_marker, &self.gaussian6(&cam_cov))
        } else {
            let biased = perturb(cam_from_marker, &self.camera_bias(observer, camera, range));
            let m = perturb(&biased, &self.gaussian6(&cam_cov));
            // The node's covariance covers its calibration's uncertainty too.
            cam_cov += self.params.bias.camera_covariance(range);
            m
        };
        // The ID read, and the mount the node would use for it.
        let mut outlier = OutlierKind::Inlier;
        let (mut read_id, mut claimed_mount, mut claimed_vehicle) =
            (marker_id, *body_from_marker, Some(target));
        let draw: f64 = self.rng.gen();
        if draw < o.wrong_id_rate {
            let others: Vec<(CodeSet, MarkerId, VehicleId)> = self
                .markers
                .iter()
                .copied()
                .filter(|(c, id, v)| {
                    *c == codes
                        && *v != target
                        && *v != observer
                        && !ids_in_frame.contains(&(c.name(), *id))
                })
                .collect();
            if !others.is_empty() {
                let (c, id, v) = others[self.rng.gen_range(0..others.len())];
                ids_in_frame.insert((c.name(), id));
                read_id = id;
                claimed_vehicle = Some(v);
                claimed_mount = self
                    .fleet
                    .marker(v, c, id)
                    .map_or(*body_from_marker, |m| m.body_from_marker);
                outlier = OutlierKind::WrongId;
            }
        } else if draw < o.wrong_id_rate + o.unknown_id_rate {
            let used: Vec<MarkerId> = self
                .markers
                .iter()
                .filter(|(c, _, _)| *c == codes)
                .map(|(_, id, _)| *id)
                .collect();
            // Any ID of the set no vehicle carries (the set's size, or past the largest used ID
            // while the code tables are not extracted).
            let n = (codes.len() as MarkerId).max(used.iter().max().map_or(1, |m| m + 2));
            let free: Vec<MarkerId> = (0..n)
                .filter(|id| !used.contains(id) && !ids_in_frame.contains(&(codes.name(), *id)))
                .collect();
            if !free.is_empty() {
                read_id = free[self.rng.gen_range(0..free.len())];
                ids_in_frame.insert((codes.name(), read_id));
                claimed_vehicle = None;
                outlier = OutlierKind::UnknownId;
            }
        }
        let (twin, twin_angle) = planar_flip_twin(&measured);
        let flip_rate = o
            .flip_rate_table
            .map_or(o.flip_rate, |t| o.flip_rate.max(interpolate(t, range)));
        let flip = self.rng.gen_bool(flip_rate.clamp(0.0, 1.0))
            && twin_angle >= o.min_flip_deg.to_radians();
        let with_alt = flip || self.rng.gen_bool(o.alternative_rate.clamp(0.0, 1.0));
        if flip && outlier == OutlierKind::Inlier {
            outlier = OutlierKind::Flipped;
        }
        // Covariance of observer_from_target = body_from_camera · camera_from_marker · marker_from_target.
        let marker_from_target = claimed_mount.inverse();
        let body_from_marker_meas = body_from_camera * measured;
        let (_, j_cm) = compose_jacobians(body_from_camera, &measured);
        let (j_bm, _) = compose_jacobians(&body_from_marker_meas, &marker_from_target);
        let j = j_bm * j_cm;
        let cov = j * cam_cov * j.transpose();
        let cov = (cov + cov.transpose()) * 0.5;
        let true_pose = body_from_marker_meas * marker_from_target;
        let twin_pose = body_from_camera * twin * marker_from_target;
        let (primary, alternative) = if flip {
            (twin_pose, true_pose)
        } else {
            (true_pose, twin_pose)
        };
        let rms = 0.3 + 0.1 * range;
        let obs = Observation {
            observer,
            camera,
            codes,
            target_marker: read_id,
            target_vehicle: claimed_vehicle
                .filter(|v| self.fleet.marker_owner(codes, read_id) == MarkerOwner::Vehicle(*v)),
            stamp_ns,
            frame_seq,
            observer_from_target: primary,
            covariance: cov,
            reprojection_rms_px: rms,
            alternative: with_alt.then_some(PoseHypothesis {
                observer_from_target: alternative,
                covariance: cov,
                reprojection_rms_px: rms * 1.2,
            }),
            corner_count: codes.corner_count() as u8,
            corners_px: Vec::new(),
            quality: ImageQuality::default(),
            predicted: false,
        };
        SyntheticObservation {
            obs,
            true_target: target,
            truth_observer_from_target: *truth,
            outlier,
            twin_angle_rad: twin_angle,
        }
    }
}

/// Fleet TOML of `n` vehicles (IDs 1..=n, reference 1), each with the paper's
/// five-camera 1.5 m rig and four 100 mm markers of `codes` (IDs `4(i−1)+k`):
/// starboard and port mid-body as in `configs/fleets/paper.toml`, and one on
/// top and one underneath 0.3 m ahead of mid-body, so that stacked layers see
/// each other through the up/down cameras.
pub fn synthetic_fleet_toml(n: usize, codes: CodeSet) -> Result<String, ObsSynthError> {
    if n == 0 {
        return Err(ObsSynthError::EmptyFleet);
    }
    // `len()` is 0 while the code tables are not extracted; Fleet::parse checks IDs then.
    if !codes.is_empty() && 4 * n > codes.len() {
        return Err(ObsSynthError::TooManyVehicles {
            n,
            needed: 4 * n,
            codes: codes.name(),
            available: codes.len(),
        });
    }
    let mut s = format!(
        "fleet = \"synthetic{n}\"\ndescription = \"{n} generated vehicles\"\nreference_vehicle = 1\n\n\
[[rigs.mini.cameras]]\nname = \"forward\"\npreset = \"vehicle_1440\"\nbody_from_camera = {{ xyz_m = [0.750, 0.0, 0.0], rpy_deg = [90, 0, 90] }}\n\
[[rigs.mini.cameras]]\nname = \"up\"\npreset = \"vehicle_1440\"\nbody_from_camera = {{ xyz_m = [0.600, 0.0, -0.0625], rpy_deg = [180, 0, 90] }}\n\
[[rigs.mini.cameras]]\nname = \"down\"\npreset = \"vehicle_1440\"\nbody_from_camera = {{ xyz_m = [0.600, 0.0, 0.0625], rpy_deg = [0, 0, 90] }}\n\
[[rigs.mini.cameras]]\nname = \"port\"\npreset = \"vehicle_1440\"\nbody_from_camera = {{ xyz_m = [0.600, -0.0625, 0.0], rpy_deg = [90, 0, 0] }}\n\
[[rigs.mini.cameras]]\nname = \"starboard\"\npreset = \"vehicle_1440\"\nbody_from_camera = {{ xyz_m = [0.600, 0.0625, 0.0], rpy_deg = [90, 0, 180] }}\n\n"
    );
    let c = codes.name();
    for i in 1..=n {
        let k = 4 * (i - 1) as u32;
        s += &format!(
            "[[vehicles]]\nid = {i}\nname = \"auv-{i}\"\nrig = \"mini\"\nhull = {{ diameter_m = 0.125, length_m = 1.5 }}\nmarkers = [\n\
  {{ codes = \"{c}\", id = {}, side_m = 0.100, body_from_marker = {{ xyz_m = [0.0, 0.0655, 0.0], rpy_deg = [-90, 0, 0] }} }},\n\
  {{ codes = \"{c}\", id = {}, side_m = 0.100, body_from_marker = {{ xyz_m = [0.0, -0.0655, 0.0], rpy_deg = [-90, 0, 180] }} }},\n\
  {{ codes = \"{c}\", id = {}, side_m = 0.100, body_from_marker = {{ xyz_m = [0.3, 0.0, -0.0655], rpy_deg = [180, 0, 0] }} }},\n\
  {{ codes = \"{c}\", id = {}, side_m = 0.100, body_from_marker = {{ xyz_m = [0.3, 0.0, 0.0655], rpy_deg = [0, 0, 0] }} }},\n]\n\n",
            k,
            k + 1,
            k + 2,
            k + 3
        );
    }
    Ok(s)
}

/// The fleet of [`synthetic_fleet_toml`], parsed.
pub fn synthetic_fleet(n: usize, codes: CodeSet) -> Result<Fleet, ObsSynthError> {
    let text = synthetic_fleet_toml(n, codes)?;
    Ok(Fleet::parse(
        &text,
        Path::new(&format!("synthetic{n}.toml")),
    )?)
}

/// Line abreast heading north (+x), `spacing_m` apart to starboard (+y), in the order given.
pub fn line_abreast(ids: &[VehicleId], spacing_m: f64) -> Vec<VehicleTruth> {
    ids.iter()
        .enumerate()
        .map(|(i, &vehicle)| VehicleTruth {
            vehicle,
            world_from_body: pose_from_xyz_rpy([0.0, spacing_m * i as f64, 5.0], [0.0, 0.0, 0.0]),
            velocity_body: [0.0; 3],
        })
        .collect()
}

/// [`line_abreast`] manoeuvring at `t_s`: each vehicle drifting `a` metres
/// around its slot (and `a / 3` in depth, `a / 0.3 × 5°` of yaw) on a 60 s
/// cycle, each a third of a turn out of phase with the one before, so that
/// every pair's relative pose keeps changing (up to ~5 cm/s at `a` = 0.3 m).
pub fn drifting_line_abreast(
    ids: &[VehicleId],
    spacing_m: f64,
    a: f64,
    t_s: f64,
) -> Vec<VehicleTruth> {
    let w = std::f64::consts::TAU / 60.0;
    ids.iter()
        .enumerate()
        .map(|(i, &vehicle)| {
            let phase = i as f64 * 2.1;
            let (s, c) = ((w * t_s + phase).sin(), (w * t_s + phase).cos());
            let xyz = [a * s, spacing_m * i as f64 + a * c, 5.0 + a / 3.0 * s];
            let yaw = (a / 0.3) * 5f64.to_radians() * c;
            VehicleTruth {
                vehicle,
                world_from_body: pose_from_xyz_rpy(xyz, [0.0, 0.0, yaw]),
                velocity_body: [a * w * c, -a * w * s, 0.0],
            }
        })
        .collect()
}

/// Random perturbation of a formation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FormationJitter {
    /// Uniform ± offset of each position coordinate, metres.
    pub position_m: f64,
    /// Uniform ± roll, pitch and yaw, degrees.
    pub attitude_deg: f64,
}

impl Default for FormationJitter {
    fn default() -> Self {
        Self {
            position_m: 0.15,
            attitude_deg: 8.0,
        }
    }
}

/// Vehicles abreast in `columns` (along +y) and stacked in layers (along +z,
/// deeper), `spacing_m` apart, all heading north, jittered (seeded).
pub fn grid_formation(
    ids: &[VehicleId],
    columns: usize,
    spacing_m: f64,
    jitter: FormationJitter,
    seed: u64,
) -> Vec<VehicleTruth> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let columns = columns.max(1);
    ids.iter()
        .enumerate()
        .map(|(i, &vehicle)| {
            let (col, layer) = ((i % columns) as f64, (i / columns) as f64);
            let mut j = || rng.gen_range(-1.0..=1.0);
            let xyz = [
                jitter.position_m * j(),
                spacing_m * col + jitter.position_m * j(),
                5.0 + spacing_m * layer + jitter.position_m * j(),
            ];
            let a = jitter.attitude_deg.to_radians();
            let rpy = [a * j(), a * j(), a * j()];
            VehicleTruth {
                vehicle,
                world_from_body: pose_from_xyz_rpy(xyz, rpy),
                velocity_body: [0.0; 3],
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use shoal_proto::geometry::difference;

    #[test]
    fn planar_flip_twin_mirrors_the_tilt_about_the_line_of_sight() {
        // Marker 2 m ahead, tilted 20° about the camera y axis.
        let m = pose_from_xyz_rpy([0.0, 0.0, 2.0], [0.0, std::f64::consts::PI + 0.35, 0.0]);
        let (twin, angle) = planar_flip_twin(&m);
        let n = m.rotation * Vector3::z();
        let n2 = twin.rotation * Vector3::z();
        assert!(
            (n.x + n2.x).abs() < 1e-9 && (n.z - n2.z).abs() < 1e-9,
            "{n} vs {n2}"
        );
        assert!((angle - 0.70).abs() < 1e-9);
        assert_eq!(twin.translation, m.translation);
    }

    #[test]
    fn synthetic_fleet_has_unique_markers_and_line_abreast_neighbours_see_each_other() {
        let fleet = synthetic_fleet(3, CodeSet::Aruco4x4_1000).unwrap();
        assert_eq!(fleet.vehicles.len(), 3);
        assert_eq!(
            fleet.marker_owner(CodeSet::Aruco4x4_1000, 5),
            MarkerOwner::Vehicle(2)
        );
        let truth = line_abreast(&[1, 2, 3], 1.5);
        let mut synth = ObsSynth::new(&fleet, ObsSynthParams::default(), 7);
        let obs = synth.observe(&truth, 1_000);
        assert!(obs
            .iter()
            .any(|o| o.obs.observer == 1 && o.true_target == 2));
        assert!(obs
            .iter()
            .any(|o| o.obs.observer == 2 && o.true_target == 1));
        for o in &obs {
            let err = difference(&o.obs.observer_from_target, &o.truth_observer_from_target);
            assert!(err.norm() < 0.2, "{err}");
            assert_eq!(o.outlier, OutlierKind::Inlier);
        }
    }

    #[test]
    fn same_seed_same_observations() {
        let fleet = synthetic_fleet(4, CodeSet::Aruco4x4_1000).unwrap();
        let truth = grid_formation(&[1, 2, 3, 4], 2, 1.5, FormationJitter::default(), 3);
        let params = ObsSynthParams {
            outliers: OutlierModel {
                wrong_id_rate: 0.1,
                flip_rate: 0.1,
                ..OutlierModel::default()
            },
            ..ObsSynthParams::default()
        };
        let a = ObsSynth::new(&fleet, params, 11).observe(&truth, 5);
        let b = ObsSynth::new(&fleet, params, 11).observe(&truth, 5);
        assert!(!a.is_empty());
        assert_eq!(a, b);
    }

    #[test]
    fn tables_interpolate_between_rows_and_hold_their_ends() {
        let t: &[(f64, f64)] = &[(1.0, 2.0), (2.0, 4.0), (4.0, 0.0)];
        assert_eq!(interpolate(t, 0.5), 2.0);
        assert_eq!(interpolate(t, 1.0), 2.0);
        assert!((interpolate(t, 1.5) - 3.0).abs() < 1e-12);
        assert_eq!(interpolate(t, 2.0), 4.0);
        assert!((interpolate(t, 3.0) - 2.0).abs() < 1e-12);
        assert_eq!(interpolate(t, 9.0), 0.0);
        assert_eq!(interpolate(&[(1.0, 7.0)], 3.0), 7.0);
        let m = NoiseModel {
            translation_std_floor_m: 0.0,
            depth_std_table: Some(&[(1.0, 0.001), (2.0, 0.003)]),
            ..NoiseModel::default()
        };
        assert!((m.camera_covariance(1.5)[(2, 2)].sqrt() - 0.002).abs() < 1e-12);
    }

    /// Every (observer, camera, marker) track's errors over `frames` frames
    /// of a 3-vehicle line 1.2 m apart, in the observer's body frame.
    fn track_errors(
        params: ObsSynthParams,
        frames: u64,
    ) -> BTreeMap<(u32, u8, u32), Vec<Vector6<f64>>> {
        let fleet = synthetic_fleet(3, CodeSet::Aruco4x4_1000).unwrap();
        let truth = line_abreast(&[1, 2, 3], 1.2);
        let mut synth = ObsSynth::new(&fleet, params, 5);
        let mut tracks: BTreeMap<_, Vec<Vector6<f64>>> = BTreeMap::new();
        for k in 0..frames {
            for s in synth.observe(&truth, 1 + k) {
                assert_eq!(s.outlier, OutlierKind::Inlier);
                let key = (s.obs.observer, s.obs.camera, s.obs.target_marker);
                tracks.entry(key).or_default().push(difference(
                    &s.truth_observer_from_target,
                    &s.obs.observer_from_target,
                ));
            }
        }
        tracks
    }

    #[test]
    fn a_camera_bias_is_the_same_on_every_frame_and_differs_between_cameras() {
        // The realistic model with its frame-to-frame noise and flips off:
        // what is left is each camera's bias.
        let still = NoiseModel {
            lateral_std_per_m: 0.0,
            depth_std_per_m: 0.0,
            depth_std_per_m2: 0.0,
            translation_std_floor_m: 1e-12,
            tilt_std_rad: 1e-12,
            tilt_std_per_m: 0.0,
            roll_std_rad: 1e-12,
            depth_std_table: None,
        };
        let mut params = ObsSynthParams::realistic();
        params.noise = still;
        params.outliers.flip_rate_table = None;
        let tracks = track_errors(params, 5);
        assert!(tracks.len() >= 4, "{} tracks", tracks.len());
        let mut firsts = Vec::new();
        for (key, errs) in &tracks {
            // The same error on every frame of a track…
            for e in errs {
                assert!((e - errs[0]).norm() < 1e-9, "{key:?}: {e} vs {}", errs[0]);
            }
            // …millimetres, not zero: 1.2 m with 3.5 mm + 2.4 mm/m of common depth bias.
            let t = errs[0].fixed_rows::<3>(0).norm();
            assert!(t > 2e-3 && t < 2e-2, "{key:?}: {t} m");
            firsts.push(errs[0]);
        }
        // …and another on another camera's.
        for (i, a) in firsts.iter().enumerate() {
            for b in &firsts[i + 1..] {
                assert!((a - b).norm() > 1e-5, "{a} vs {b}");
            }
        }
        // The same seed draws the same bias; the ideal camera has none.
        assert_eq!(tracks, track_errors(params, 5));
        let ideal = ObsSynthParams {
            noise: still,
            ..ObsSynthParams::default()
        };
        for errs in track_errors(ideal, 3).values() {
            assert!(errs.iter().all(|e| e.norm() < 1e-9), "{errs:?}");
        }
    }

    #[test]
    fn the_realistic_bias_does_not_average_away_and_the_covariance_covers_the_camera_part() {
        let mut params = ObsSynthParams::realistic();
        params.outliers.flip_rate_table = None;
        let frames = 400;
        let tracks = track_errors(params, frames);
        let mut biased = 0;
        for (key, errs) in &tracks {
            let n = errs.len() as f64;
            assert!(n > 0.8 * frames as f64, "{key:?}: {n} reads at 1.2 m");
            let mean: Vector6<f64> = errs.iter().sum::<Vector6<f64>>() / n;
            let var: Vector6<f64> = errs
                .iter()
                .map(|e| (e - mean).map(|x| x * x))
                .sum::<Vector6<f64>>()
                / (n - 1.0);
            // The position error's mean stands far outside what the frames'
            // scatter leaves of it (its standard error).
            let t = mean.fixed_rows::<3>(0).norm();
            let se = (var.fixed_rows::<3>(0).sum() / n).sqrt();
            if t > 10.0 * se {
                biased += 1;
            }
        }
        assert_eq!(biased, tracks.len(), "every track keeps its camera's bias");
        // The reported covariance holds the per-camera bias's σ on top of the noise.
        let fleet = synthetic_fleet(3, CodeSet::Aruco4x4_1000).unwrap();
        let truth = line_abreast(&[1, 2, 3], 1.2);
        let obs = ObsSynth::new(&fleet, params, 5).observe(&truth, 1);
        let o = obs.first().expect("a read at 1.2 m");
        let alone = ObsSynth::new(
            &fleet,
            ObsSynthParams {
                bias: BiasModel::default(),
                ..params
            },
            5,
        )
        .observe(&truth, 1);
        let trace = |c: &Cov6| c.fixed_view::<3, 3>(0, 0).trace();
        let with_bias = trace(&o.obs.covariance);
        let without = trace(&alone[0].obs.covariance);
        let bias_part = params
            .bias
            .std_at(1.2)
            .fixed_rows::<3>(0)
            .map(|s| s * s)
            .sum();
        assert!(
            with_bias > without + 0.5 * bias_part,
            "{with_bias} vs {without} + {bias_part}"
        );
    }
}
