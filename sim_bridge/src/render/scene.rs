//! What can be seen: markers and vehicle hulls in the world.

use super::visibility::grid_of;
use crate::error::SimError;
use nalgebra::Vector3;
use shoal_proto::config::Fleet;
use shoal_proto::geometry::pose_is_finite;
use shoal_proto::{CodeSet, MarkerId, Pose, VehicleId, VehicleTruth};

/// A marker in the world (with its one-module white quiet zone).
#[derive(Debug, Clone, PartialEq)]
pub struct SceneMarker {
    pub codes: CodeSet,
    pub id: MarkerId,
    /// Side of the outer black square (the footprint), metres.
    pub side_m: f64,
    pub world_from_marker: Pose,
    /// The vehicle carrying it (`VisibleMarker::target_vehicle`); 0 when none.
    pub owner: VehicleId,
}

/// A vehicle hull: a closed cylinder centred on the body origin, axis along body x.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneHull {
    pub vehicle: VehicleId,
    pub world_from_body: Pose,
    pub diameter_m: f64,
    pub length_m: f64,
}

/// Everything that can be seen.
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    pub markers: Vec<SceneMarker>,
    pub hulls: Vec<SceneHull>,
    /// The world's up direction (unit), for the downwelling light: `(0, 0, −1)` in NED.
    pub up_world: Vector3<f64>,
}

impl Scene {
    /// An empty NED scene.
    pub fn empty() -> Scene {
        Scene {
            markers: Vec::new(),
            hulls: Vec::new(),
            up_world: Vector3::new(0.0, 0.0, -1.0),
        }
    }

    /// One marker in front of a camera placed at the world origin (render
    /// with `world_from_camera = Pose::identity()`); the camera's image-up
    /// is the world's up. Used by the evaluation at 600 mm.
    pub fn single_marker(
        codes: CodeSet,
        id: MarkerId,
        side_m: f64,
        camera_from_marker: Pose,
    ) -> Scene {
        Scene {
            markers: vec![SceneMarker {
                codes,
                id,
                side_m,
                world_from_marker: camera_from_marker,
                owner: 0,
            }],
            hulls: Vec::new(),
            up_world: Vector3::new(0.0, -1.0, 0.0),
        }
    }

    /// Hulls and markers of every vehicle of `fleet` that has a pose in `truth`.
    pub fn from_fleet(fleet: &Fleet, truth: &[VehicleTruth]) -> Scene {
        let mut scene = Scene::empty();
        for t in truth {
            let Some(v) = fleet.vehicle(t.vehicle) else {
                continue;
            };
            scene.hulls.push(SceneHull {
                vehicle: v.id,
                world_from_body: t.world_from_body,
                diameter_m: v.hull.diameter_m,
                length_m: v.hull.length_m,
            });
            for m in &v.markers {
                scene.markers.push(SceneMarker {
                    codes: m.codes,
                    id: m.id,
                    side_m: m.side_m,
                    world_from_marker: t.world_from_body * m.body_from_marker,
                    owner: v.id,
                });
            }
        }
        scene
    }

    /// Check poses, sizes and marker IDs.
    pub fn validate(&self) -> Result<(), SimError> {
        if !(self.up_world.iter().all(|v| v.is_finite())
            && (self.up_world.norm() - 1.0).abs() < 1e-6)
        {
            return Err(SimError::InvalidArgument {
                field: "scene.up_world",
                value: self.up_world.norm(),
                reason: "must be a finite unit vector",
            });
        }
        for m in &self.markers {
            if !pose_is_finite(&m.world_from_marker) {
                return Err(SimError::NonFinitePose {
                    what: format!("marker {}#{}", m.codes, m.id),
                });
            }
            if !(m.side_m > 0.0 && m.side_m.is_finite()) {
                return Err(SimError::Marker {
                    codes: m.codes,
                    id: m.id,
                    reason: format!("side {} m must be positive", m.side_m),
                });
            }
            grid_of(m.codes, m.id)?;
        }
        for h in &self.hulls {
            if !pose_is_finite(&h.world_from_body) {
                return Err(SimError::NonFinitePose {
                    what: format!("hull of vehicle {}", h.vehicle),
                });
            }
            if !(h.diameter_m > 0.0
                && h.length_m > 0.0
                && h.diameter_m.is_finite()
                && h.length_m.is_finite())
            {
                return Err(SimError::Hull {
                    vehicle: h.vehicle,
                    diameter_m: h.diameter_m,
                    length_m: h.length_m,
                });
            }
        }
        Ok(())
    }
}

/// `camera_from_marker` for a marker facing the camera upright (its face
/// towards the camera, its y axis image-up) and then rotated by
/// `rpy` (rad, `R = Rz·Ry·Rx` about the camera's axes: pitch turns it about
/// the image vertical like the paper's rotation platform), centred at `xyz_m`.
pub fn facing_camera(xyz_m: [f64; 3], rpy: [f64; 3]) -> Pose {
    shoal_proto::geometry::pose_from_xyz_rpy(xyz_m, rpy)
        * shoal_proto::geometry::pose_from_xyz_rpy([0.0; 3], [std::f64::consts::PI, 0.0, 0.0])
}
