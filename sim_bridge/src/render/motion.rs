//! Time within a frame: where the camera and the scene are during the
//! exposure ([`Timeline`]), and which sub-frames each row integrates
//! ([`ExposureSchedule`]) — motion blur (the exposure time) and the rolling
//! shutter (the line time). `docs/water-model.md`, "Camera effects".

use super::scene::Scene;
use crate::error::SimError;
use crate::world::SwarmWorld;
use nalgebra::{Point3, Translation3, UnitQuaternion, Vector3};
use shoal_proto::config::Fleet;
use shoal_proto::{CameraModel, FlatPort, Pose, VehicleId};

/// The camera's pose and the scene `dt_s` seconds after the frame starts
/// (row 0's exposure starts at `dt_s = 0`).
pub trait Timeline {
    fn at(&self, dt_s: f64) -> Result<(Pose, Scene), SimError>;
}

/// Nothing moves.
#[derive(Debug, Clone)]
pub struct StaticView {
    pub world_from_camera: Pose,
    pub scene: Scene,
}

impl Timeline for StaticView {
    fn at(&self, _dt_s: f64) -> Result<(Pose, Scene), SimError> {
        Ok((self.world_from_camera, self.scene.clone()))
    }
}

/// A constant velocity and angular velocity.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Twist {
    /// m/s.
    pub linear_mps: Vector3<f64>,
    /// rad/s (rotation vector rate).
    pub angular_radps: Vector3<f64>,
}

impl Twist {
    /// The rigid motion after `dt_s`: rotation about the frame's own origin, then translation.
    pub fn after(&self, dt_s: f64) -> Pose {
        Pose::from_parts(
            Translation3::from(self.linear_mps * dt_s),
            UnitQuaternion::from_scaled_axis(self.angular_radps * dt_s),
        )
    }

    pub fn is_zero(&self) -> bool {
        self.linear_mps == Vector3::zeros() && self.angular_radps == Vector3::zeros()
    }
}

/// A camera and a scene moving rigidly: the camera with `camera` (in its
/// own frame: `world_from_camera(t) = world_from_camera · camera.after(t)`),
/// every marker and hull with `targets` (in the world frame, about each
/// object's own origin).
#[derive(Debug, Clone)]
pub struct RigidMotion {
    pub world_from_camera: Pose,
    pub scene: Scene,
    pub camera: Twist,
    pub targets: Twist,
}

impl Timeline for RigidMotion {
    fn at(&self, dt_s: f64) -> Result<(Pose, Scene), SimError> {
        let cam = self.world_from_camera * self.camera.after(dt_s);
        let mut scene = self.scene.clone();
        if !self.targets.is_zero() {
            let m = self.targets.after(dt_s);
            let moved = |p: &Pose| {
                Pose::from_parts(
                    Translation3::from(p.translation.vector + m.translation.vector),
                    m.rotation * p.rotation,
                )
            };
            for mk in &mut scene.markers {
                mk.world_from_marker = moved(&mk.world_from_marker);
            }
            for h in &mut scene.hulls {
                h.world_from_body = moved(&h.world_from_body);
            }
        }
        Ok((cam, scene))
    }
}

/// A vehicle's camera in the swarm world: the world is cloned and stepped
/// to each time (its dynamics and random drift are deterministic).
#[derive(Debug, Clone)]
pub struct FleetTimeline<'a> {
    pub fleet: &'a Fleet,
    /// The world at the start of the frame.
    pub world: SwarmWorld,
    pub vehicle: VehicleId,
    pub camera_index: u8,
}

impl Timeline for FleetTimeline<'_> {
    fn at(&self, dt_s: f64) -> Result<(Pose, Scene), SimError> {
        let mut world = self.world.clone();
        world.step(dt_s);
        let truth = world.truth();
        let (_, world_from_camera) =
            super::fleet_camera(self.fleet, &truth, self.vehicle, self.camera_index)?;
        Ok((world_from_camera, Scene::from_fleet(self.fleet, &truth)))
    }
}

/// Which sub-frames make each row: sub-frame `j` is rendered at `times_s[j]`
/// (seconds after the frame starts) and stands for the interval of width
/// `step_s` around it; row `y` integrates `[y·line, y·line + exposure]`.
#[derive(Debug, Clone, PartialEq)]
pub struct ExposureSchedule {
    pub times_s: Vec<f64>,
    pub step_s: f64,
    pub exposure_s: f64,
    pub line_time_s: f64,
}

impl ExposureSchedule {
    /// Sub-frames spanning the exposures of all `rows`, at most `max_step_px`
    /// of image motion apart (`speed_px_per_s`, the fastest image motion),
    /// at most `max_samples` of them.
    pub fn new(
        exposure_s: f64,
        line_time_s: f64,
        rows: usize,
        speed_px_per_s: f64,
        max_step_px: f64,
        max_samples: usize,
    ) -> ExposureSchedule {
        let span = exposure_s + line_time_s * rows.saturating_sub(1) as f64;
        let moves_px = speed_px_per_s.max(0.0) * span;
        let n = if span <= 0.0 || !moves_px.is_finite() {
            1
        } else {
            ((moves_px / max_step_px.max(1e-6)).ceil() as usize).clamp(1, max_samples.max(1))
        };
        let step_s = span / n as f64;
        ExposureSchedule {
            times_s: (0..n).map(|j| (j as f64 + 0.5) * step_s).collect(),
            step_s,
            exposure_s,
            line_time_s,
        }
    }

    /// The weight of sub-frame `j` in row `y` (a row's weights sum to 1):
    /// the overlap of the sub-frame's interval with the row's exposure; an
    /// instantaneous exposure is interpolated linearly between the two
    /// sub-frames around its time.
    pub fn weight(&self, j: usize, y: usize) -> f64 {
        let start = y as f64 * self.line_time_s;
        let (a, b) = (
            self.times_s[j] - 0.5 * self.step_s,
            self.times_s[j] + 0.5 * self.step_s,
        );
        if self.step_s <= 0.0 {
            return 1.0;
        }
        if self.exposure_s <= 0.0 {
            // An instant: interpolate between the two sub-frames around it
            // (the first and the last hold beyond the ends).
            let n = self.times_s.len();
            let t = start.clamp(self.times_s[0], self.times_s[n - 1]);
            return (1.0 - (t - self.times_s[j]).abs() / self.step_s).max(0.0);
        }
        let overlap = (b.min(start + self.exposure_s) - a.max(start)).max(0.0);
        overlap / self.exposure_s
    }

    /// The time the frame's ground truth refers to: mid-exposure of the middle row.
    pub fn reference_s(&self, rows: usize) -> f64 {
        0.5 * self.exposure_s + self.line_time_s * (rows / 2) as f64
    }
}

/// The fastest image motion (px/s) of any marker corner between `0` and
/// `span_s` (checked at three instants), as seen through `cam` and `port`.
pub fn image_speed_px_per_s(
    timeline: &dyn Timeline,
    cam: &CameraModel,
    port: Option<&FlatPort>,
    span_s: f64,
) -> Result<f64, SimError> {
    if span_s <= 0.0 {
        return Ok(0.0);
    }
    let times = [0.0, 0.5 * span_s, span_s];
    let mut tracks: Vec<Vec<Option<nalgebra::Point2<f64>>>> = Vec::new();
    for t in times {
        let (world_from_camera, scene) = timeline.at(t)?;
        let camera_from_world = world_from_camera.inverse();
        let mut pts = Vec::new();
        for m in &scene.markers {
            let h = 0.5 * m.side_m;
            for (x, y) in [(-h, -h), (h, -h), (h, h), (-h, h), (0.0, 0.0)] {
                let p = camera_from_world * m.world_from_marker * Point3::new(x, y, 0.0);
                pts.push(shoal_proto::port::project(cam, port, &p));
            }
        }
        tracks.push(pts);
    }
    let mut fastest: f64 = 0.0;
    for k in 1..tracks.len() {
        for (a, b) in tracks[k - 1].iter().zip(&tracks[k]) {
            if let (Some(a), Some(b)) = (a, b) {
                fastest = fastest.max((b - a).norm() / (times[k] - times[k - 1]));
            }
        }
    }
    Ok(fastest)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_row_weighs_one_in_total() {
        for (exp, line) in [(0.008, 15e-6), (0.0, 15e-6), (0.008, 0.0), (0.0, 0.0)] {
            let s = ExposureSchedule::new(exp, line, 1080, 2000.0, 0.5, 48);
            for y in [0, 1, 539, 1079] {
                let total: f64 = (0..s.times_s.len()).map(|j| s.weight(j, y)).sum();
                assert!(
                    (total - 1.0).abs() < 1e-9,
                    "exp {exp} line {line} row {y}: {total}"
                );
            }
        }
    }

    #[test]
    fn sub_frames_follow_the_image_motion() {
        // 500 px/s over 8 ms is 4 px: 8 sub-frames 0.5 px apart.
        let s = ExposureSchedule::new(0.008, 0.0, 100, 500.0, 0.5, 48);
        assert_eq!(s.times_s.len(), 8);
        assert_eq!(
            ExposureSchedule::new(0.008, 0.0, 100, 0.0, 0.5, 48)
                .times_s
                .len(),
            1
        );
        assert_eq!(
            ExposureSchedule::new(0.008, 0.0, 100, 1e6, 0.5, 48)
                .times_s
                .len(),
            48
        );
    }
}
