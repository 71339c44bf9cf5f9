//! The scene in the camera frame, and which markers a camera sees (the
//! ground truth of a frame, also computed without rendering).

use super::roi::ROI_NEAR_M;
use super::trace::{Hull, Objects, Plate};
use super::Scene;
use crate::error::SimError;
use nalgebra::Point3;
use shoal_proto::geometry::pose_is_finite;
use shoal_proto::{CameraModel, CodeSet, FlatPort, MarkerId, Pose, VisibleMarker};

/// The module grid of a marker (see `CodeSet::module_grid`).
pub(super) fn grid_of(codes: CodeSet, id: MarkerId) -> Result<Vec<bool>, SimError> {
    match codes.module_grid(id) {
        Ok(g) => Ok(g),
        Err(e) => Err(SimError::Marker {
            codes,
            id,
            reason: e.to_string(),
        }),
    }
}

/// The scene's plates and hulls in the camera frame; without `grids` every
/// module is white (enough for visibility, no code tables needed).
pub(super) fn build_objects(
    scene: &Scene,
    camera_from_world: &Pose,
    grids: bool,
) -> Result<Objects, SimError> {
    let up = camera_from_world.rotation * scene.up_world;
    let mut objects = Objects {
        plates: Vec::with_capacity(scene.markers.len()),
        hulls: Vec::with_capacity(scene.hulls.len()),
        up,
        port: None,
    };
    for m in &scene.markers {
        let grid = if grids {
            grid_of(m.codes, m.id)?
        } else {
            vec![true; m.codes.modules() * m.codes.modules()]
        };
        objects.plates.push(Plate::new(
            &(camera_from_world * m.world_from_marker),
            m.codes.modules(),
            m.side_m,
            grid,
            &up,
        ));
    }
    for hl in &scene.hulls {
        objects.hulls.push(Hull::new(
            &(camera_from_world * hl.world_from_body),
            hl.diameter_m,
            hl.length_m,
        ));
    }
    Ok(objects)
}

/// Which markers `cam` at `world_from_camera` sees and where their corners
/// project, without rendering (the same computation as
/// [`RenderOutput::visible`]; `observer`, `camera`, `frame_seq` are 0).
pub fn visible_in_view(
    cam: &CameraModel,
    world_from_camera: &Pose,
    scene: &Scene,
) -> Result<Vec<VisibleMarker>, SimError> {
    visible_in_view_with_port(cam, None, world_from_camera, scene)
}

/// [`visible_in_view`] for a camera behind a flat port (corners projected
/// through it, as [`super::Renderer::render_with_port`] draws them).
pub fn visible_in_view_with_port(
    cam: &CameraModel,
    port: Option<&FlatPort>,
    world_from_camera: &Pose,
    scene: &Scene,
) -> Result<Vec<VisibleMarker>, SimError> {
    if let Some(p) = cam.problem() {
        return Err(SimError::Camera(p));
    }
    if let Some(p) = port.and_then(FlatPort::problem) {
        return Err(SimError::Camera(p));
    }
    if !pose_is_finite(world_from_camera) {
        return Err(SimError::NonFinitePose {
            what: "world_from_camera".into(),
        });
    }
    for m in &scene.markers {
        if !pose_is_finite(&m.world_from_marker)
            || m.side_m.is_nan()
            || m.side_m <= 0.0
            || m.side_m.is_infinite()
        {
            return Err(SimError::NonFinitePose {
                what: format!("marker {}#{}", m.codes, m.id),
            });
        }
    }
    let mut objects = build_objects(scene, &world_from_camera.inverse(), false)?;
    objects.port = port.copied();
    Ok(visible_markers(cam, scene, &objects))
}

/// Markers whose front face is at least partly visible: projected corners
/// (in `CodeSet::corners_3d` order) and the fraction of the black square's
/// face that is in frame, facing the camera and not occluded.
pub(super) fn visible_markers(
    cam: &CameraModel,
    scene: &Scene,
    objects: &Objects,
) -> Vec<VisibleMarker> {
    let mut out = Vec::new();
    let k = 12usize;
    for (m, plate) in scene.markers.iter().zip(&objects.plates) {
        let camera_from_marker = |p: &Point3<f64>| {
            Point3::from(plate.origin + plate.ex * p.x + plate.ey * p.y + plate.normal * p.z)
        };
        let corners: Vec<Point3<f64>> = m
            .codes
            .corners_3d(m.side_m)
            .iter()
            .map(camera_from_marker)
            .collect();
        if corners.iter().any(|c| c.z <= ROI_NEAR_M) {
            continue;
        }
        if plate.normal.dot(&plate.origin) >= 0.0 {
            continue; // seen from behind
        }
        let mut seen = 0usize;
        for j in 0..k {
            for i in 0..k {
                let a = m.side_m * ((i as f64 + 0.5) / k as f64 - 0.5);
                let b = m.side_m * ((j as f64 + 0.5) / k as f64 - 0.5);
                let p = Point3::from(plate.origin + plate.ex * a + plate.ey * b);
                let in_frame = objects.project(cam, &p).is_some_and(|q| {
                    q.x >= -0.5
                        && q.y >= -0.5
                        && q.x <= cam.width as f64 - 0.5
                        && q.y <= cam.height as f64 - 0.5
                });
                if in_frame && objects.sees(&p) {
                    seen += 1;
                }
            }
        }
        if seen == 0 {
            continue;
        }
        let corners_px = corners
            .iter()
            .filter_map(|c| objects.project(cam, c))
            .map(|q| [q.x, q.y])
            .collect();
        out.push(VisibleMarker {
            observer: 0,
            camera: 0,
            frame_seq: 0,
            codes: m.codes,
            marker: m.id,
            target_vehicle: m.owner,
            corners_px,
            visible_fraction: seen as f32 / (k * k) as f32,
            range_m: plate.origin.norm(),
        });
    }
    out
}

/// True when every corner of `v` is inside the image (pixel-centre convention).
pub fn all_corners_in_frame(cam: &CameraModel, v: &VisibleMarker) -> bool {
    v.corners_px.len() == v.codes.corner_count()
        && v.corners_px.iter().all(|c| {
            c[0] >= -0.5
                && c[1] >= -0.5
                && c[0] <= cam.width as f64 - 0.5
                && c[1] <= cam.height as f64 - 0.5
        })
}
