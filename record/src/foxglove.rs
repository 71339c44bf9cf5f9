//! shoal's messages in Foxglove's well-known schemas, as the `foxglove`
//! crate's typed messages: protobuf (`message_encoding = "protobuf"`, the
//! schema record a `FileDescriptorSet` as the crate ships it), so a log opens
//! in Foxglove, Rerun or any MCAP reader with the published `.proto` files and
//! no shoal code. The recorder writes these bytes to the log and the
//! station's live server sends the very same bytes on the same topics with the
//! same schema records ([`FoxgloveMessage::encode`], [`FoxgloveSchema::schema`]).
//!
//! Log format 1 (before `log_format` metadata existed) held these channels as
//! JSON with JSON schemas; the readers never depended on them, so old logs
//! still read (`tests/data/logs/format1_demo.mcap`).
//!
//! Frame names (DESIGN.md: "anything exported to ROS-style tools states its
//! frame names"):
//!
//! | frame | what |
//! |---|---|
//! | `world` | simulator world, NED (ground truth only) |
//! | `truth/v<id>` | body (FRD) of vehicle `<id>` from ground truth |
//! | `v<id>` | body (FRD) of vehicle `<id>` as fused; the reference vehicle is the root of the fused tree, tied to its truth frame by an identity transform when truth is logged |
//! | `v<id>/cam/<name>` | camera `<name>` of vehicle `<id>`, OpenCV optical |

mod frame;
mod schema;

pub use frame::{camera_image, FrameView};
pub use schema::{FoxgloveMessage, FoxgloveSchema, FoxgloveValue};

use foxglove::messages as fm;
use nalgebra::{Matrix3, Rotation3, SymmetricEigen, UnitQuaternion, Vector3};
use proto::config::Fleet;
use proto::geometry::{Cov6, Pose};
use proto::{FleetMap, NodeStatus, Observation, SimTruth, VehicleId, VehicleState};

// ---------------------------------------------------------------- values

/// A stamp in nanoseconds as a Foxglove time (seconds saturate past 2106).
fn t(stamp_ns: u64) -> Option<fm::Timestamp> {
    let sec = u32::try_from(stamp_ns / 1_000_000_000).unwrap_or(u32::MAX);
    // The remainder is below 10^9, which fits a u32.
    let nsec = u32::try_from(stamp_ns % 1_000_000_000).unwrap_or(0);
    Some(fm::Timestamp::new(sec, nsec))
}
fn v3(v: &Vector3<f64>) -> Option<fm::Vector3> {
    Some(fm::Vector3 {
        x: v.x,
        y: v.y,
        z: v.z,
    })
}
fn q(r: &UnitQuaternion<f64>) -> Option<fm::Quaternion> {
    Some(fm::Quaternion {
        x: r.i,
        y: r.j,
        z: r.k,
        w: r.w,
    })
}
fn pose_value(p: &Pose) -> fm::Pose {
    fm::Pose {
        position: v3(&p.translation.vector),
        orientation: q(&p.rotation),
    }
}
fn rgba(r: f64, g: f64, b: f64, a: f64) -> Option<fm::Color> {
    Some(fm::Color { r, g, b, a })
}
fn point2(c: [f32; 2]) -> fm::Point2 {
    fm::Point2 {
        x: f64::from(c[0]),
        y: f64::from(c[1]),
    }
}
fn kv(key: &str, value: &str) -> fm::KeyValuePair {
    fm::KeyValuePair {
        key: key.into(),
        value: value.into(),
    }
}
fn transform(
    stamp_ns: u64,
    parent: &str,
    child: &str,
    parent_from_child: &Pose,
) -> fm::FrameTransform {
    fm::FrameTransform {
        timestamp: t(stamp_ns),
        parent_frame_id: parent.into(),
        child_frame_id: child.into(),
        translation: v3(&parent_from_child.translation.vector),
        rotation: q(&parent_from_child.rotation),
    }
}

/// Fused body frame of a vehicle.
pub fn body_frame(v: VehicleId) -> String {
    format!("v{v}")
}
/// Ground-truth body frame of a vehicle.
pub fn truth_frame(v: VehicleId) -> String {
    format!("truth/v{v}")
}
/// Camera `k` of vehicle `v` (its fleet-file name, else `cam<k>`).
pub fn camera_name(fleet: &Fleet, v: VehicleId, k: u8) -> String {
    fleet
        .vehicle(v)
        .and_then(|veh| veh.cameras.iter().find(|c| c.index == k))
        .map_or_else(|| format!("cam{k}"), |c| c.name.clone())
}
pub fn camera_frame(fleet: &Fleet, v: VehicleId, k: u8) -> String {
    format!("v{v}/cam/{}", camera_name(fleet, v, k))
}
/// Topic prefix of a camera's Foxglove channels.
pub fn camera_topic(fleet: &Fleet, v: VehicleId, k: u8) -> String {
    format!("/v{v}/cam/{}", camera_name(fleet, v, k))
}

fn msg(topic: String, value: FoxgloveValue) -> FoxgloveMessage {
    FoxgloveMessage { topic, value }
}

/// A vehicle's display colour (stable per ID).
fn vehicle_color(v: VehicleId, a: f64) -> Option<fm::Color> {
    const PALETTE: [(f64, f64, f64); 6] = [
        (0.90, 0.30, 0.20),
        (0.20, 0.60, 0.90),
        (0.30, 0.80, 0.30),
        (0.95, 0.75, 0.20),
        (0.70, 0.40, 0.85),
        (0.30, 0.85, 0.85),
    ];
    let (r, g, b) = PALETTE[v as usize % PALETTE.len()];
    rgba(r, g, b, a)
}

/// An observation: the seen vehicle's pose in the observer's body frame, and
/// its corners as an annotation of the camera image it came from.
pub fn observation(fleet: &Fleet, o: &Observation) -> Vec<FoxgloveMessage> {
    let poses = fm::PosesInFrame {
        timestamp: t(o.stamp_ns),
        frame_id: body_frame(o.observer),
        poses: vec![pose_value(&o.observer_from_target)],
    };
    let color = if o.predicted {
        rgba(0.6, 0.6, 0.6, 1.0)
    } else {
        rgba(0.1, 1.0, 0.2, 1.0)
    };
    let target = o
        .target_vehicle
        .map_or_else(|| "?".to_string(), |v| v.to_string());
    let annotations = fm::ImageAnnotations {
        timestamp: t(o.stamp_ns),
        circles: Vec::new(),
        // Observations without corners (predicted, or sent compact over a link) get only the label.
        points: (!o.corners_px.is_empty())
            .then(|| fm::PointsAnnotation {
                timestamp: t(o.stamp_ns),
                r#type: fm::points_annotation::Type::Points as i32,
                points: o.corners_px.iter().map(|c| point2(*c)).collect(),
                outline_color: color,
                outline_colors: Vec::new(),
                fill_color: color,
                thickness: 6.0,
                metadata: Vec::new(),
            })
            .into_iter()
            .collect(),
        texts: vec![fm::TextAnnotation {
            timestamp: t(o.stamp_ns),
            position: Some(point2(o.corners_px.first().copied().unwrap_or([0.0, 0.0]))),
            text: format!(
                "{}#{} -> v{target}, rms {:.2} px",
                o.codes, o.target_marker, o.reprojection_rms_px
            ),
            font_size: 24.0,
            text_color: rgba(1.0, 1.0, 1.0, 1.0),
            background_color: rgba(0.0, 0.0, 0.0, 0.6),
            metadata: Vec::new(),
        }],
        metadata: Vec::new(),
    };
    vec![
        msg(
            format!("/v{}/observations", o.observer),
            FoxgloveValue::PosesInFrame(poses),
        ),
        msg(
            format!("{}/annotations", camera_topic(fleet, o.observer, o.camera)),
            FoxgloveValue::ImageAnnotations(annotations),
        ),
    ]
}

/// Topic prefix of a map's producer (`/fused` for the central map).
pub fn map_prefix(producer: &str) -> String {
    if producer == "central" {
        "/fused".into()
    } else {
        format!("/fused_{producer}")
    }
}

/// A fused map: one transform per localized vehicle (plus the camera mounts),
/// the poses, and a scene of hulls with 3-sigma position ellipsoids.
pub fn fleet_map(fleet: &Fleet, m: &FleetMap) -> Vec<FoxgloveMessage> {
    let prefix = map_prefix(&m.producer);
    let reference = body_frame(m.reference);
    let mut transforms = Vec::new();
    let mut poses = Vec::new();
    let mut entities = Vec::new();
    for v in &m.vehicles {
        let localized = v.vehicle == m.reference || v.state != VehicleState::Unobserved;
        if v.vehicle != m.reference && localized {
            transforms.push(transform(
                m.stamp_ns,
                &reference,
                &body_frame(v.vehicle),
                &v.reference_from_vehicle,
            ));
        }
        if localized {
            poses.push(pose_value(&v.reference_from_vehicle));
        }
        if let Some(veh) = fleet.vehicle(v.vehicle) {
            for c in &veh.cameras {
                transforms.push(transform(
                    m.stamp_ns,
                    &body_frame(v.vehicle),
                    &camera_frame(fleet, v.vehicle, c.index),
                    &c.body_from_camera,
                ));
            }
            if localized {
                entities.extend(vehicle_entity(
                    m.stamp_ns,
                    &reference,
                    v.vehicle,
                    (veh.hull.diameter_m, veh.hull.length_m),
                    &v.reference_from_vehicle,
                    &v.covariance,
                    v.state,
                ));
            }
        }
    }
    let rejected = m.edges.iter().filter(|e| e.rejected.is_some()).count();
    let live = m
        .vehicles
        .iter()
        .filter(|v| v.state == VehicleState::Live)
        .count();
    vec![
        msg(
            format!("{prefix}/tf"),
            FoxgloveValue::FrameTransforms(fm::FrameTransforms { transforms }),
        ),
        msg(
            format!("{prefix}/poses"),
            FoxgloveValue::PosesInFrame(fm::PosesInFrame {
                timestamp: t(m.stamp_ns),
                frame_id: reference,
                poses,
            }),
        ),
        msg(
            format!("{prefix}/scene"),
            FoxgloveValue::SceneUpdate(fm::SceneUpdate {
                deletions: Vec::new(),
                entities,
            }),
        ),
        msg(
            format!("{prefix}/log"),
            log_value(
                m.stamp_ns,
                fm::log::Level::Info,
                format!(
                    "map {}: {live}/{} vehicles live, {} edges ({} rejected), solve {} us",
                    m.seq,
                    m.vehicles.len(),
                    m.edges.len(),
                    rejected,
                    m.solve_time_us
                ),
                &format!("fusion/{}", m.producer),
            ),
        ),
    ]
}

/// A node's liveliness token appearing or going away, as a `foxglove.Log`
/// line on `/liveliness` (the token is Zenoh's, not a wire message: the
/// recorder's clock stamps it).
pub fn liveliness_message(
    key: &str,
    vehicle: Option<VehicleId>,
    alive: bool,
    stamp_ns: u64,
) -> FoxgloveMessage {
    let who = vehicle.map_or(key.to_string(), |v| format!("vehicle {v}"));
    let text = if alive {
        format!("{who}: node alive ({key})")
    } else {
        format!("{who}: node gone — liveliness token withdrawn ({key})")
    };
    let level = if alive {
        fm::log::Level::Info
    } else {
        fm::log::Level::Warning
    };
    msg(
        "/liveliness".to_string(),
        log_value(stamp_ns, level, text, "liveliness"),
    )
}

fn log_value(stamp_ns: u64, level: fm::log::Level, message: String, name: &str) -> FoxgloveValue {
    FoxgloveValue::Log(fm::Log {
        timestamp: t(stamp_ns),
        level: level as i32,
        message,
        name: name.into(),
        file: String::new(),
        line: 0,
    })
}

fn entity(
    stamp_ns: u64,
    frame_id: String,
    id: String,
    metadata: Vec<fm::KeyValuePair>,
) -> fm::SceneEntity {
    fm::SceneEntity {
        timestamp: t(stamp_ns),
        frame_id,
        id,
        // Zero: shown until replaced by the next map's entity of the same id.
        lifetime: Some(fm::Duration::new(0, 0)),
        frame_locked: true,
        metadata,
        ..Default::default()
    }
}

/// Hull (cylinder along body x) in the vehicle's body frame, and the 3-sigma
/// ellipsoid of its position covariance in the reference frame (covariances
/// are over the left-frame perturbation, `proto::geometry`).
fn vehicle_entity(
    stamp_ns: u64,
    reference: &str,
    v: VehicleId,
    (diameter_m, length_m): (f64, f64),
    reference_from_vehicle: &Pose,
    cov: &Cov6,
    state: VehicleState,
) -> Vec<fm::SceneEntity> {
    let alpha = if state == VehicleState::Live {
        0.9
    } else {
        0.35
    };
    let hull_axis =
        UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_2);
    let mut hull = entity(
        stamp_ns,
        body_frame(v),
        format!("vehicle/{v}"),
        vec![
            kv("state", &format!("{state:?}")),
            kv("reference", reference),
        ],
    );
    hull.cylinders.push(fm::CylinderPrimitive {
        pose: Some(fm::Pose {
            position: v3(&Vector3::zeros()),
            orientation: q(&hull_axis),
        }),
        size: v3(&Vector3::new(diameter_m, diameter_m, length_m)),
        bottom_scale: 1.0,
        top_scale: 1.0,
        color: vehicle_color(v, alpha),
    });
    hull.texts.push(fm::TextPrimitive {
        pose: Some(fm::Pose {
            position: v3(&Vector3::new(0.0, 0.0, -diameter_m)),
            orientation: q(&UnitQuaternion::identity()),
        }),
        billboard: true,
        font_size: 14.0,
        scale_invariant: true,
        color: rgba(1.0, 1.0, 1.0, 1.0),
        text: format!("v{v} {state:?}"),
    });
    let mut out = vec![hull];
    // The ellipsoid lives in the reference frame (left-frame perturbation): a second entity.
    if let Some((axes, rotation)) = position_ellipsoid(cov) {
        let mut e = entity(
            stamp_ns,
            reference.to_string(),
            format!("covariance/{v}"),
            vec![kv("sigma", "3")],
        );
        e.spheres.push(fm::SpherePrimitive {
            pose: Some(fm::Pose {
                position: v3(&reference_from_vehicle.translation.vector),
                orientation: q(&rotation),
            }),
            size: v3(&axes),
            color: vehicle_color(v, 0.3),
        });
        out.push(e);
    }
    out
}

/// Axes (full lengths, 3 sigma) and orientation of the position block's
/// ellipsoid; `None` when degenerate (the reference) or uninformative (σ > 10 m).
pub fn position_ellipsoid(cov: &Cov6) -> Option<(Vector3<f64>, UnitQuaternion<f64>)> {
    let p: Matrix3<f64> = cov.fixed_view::<3, 3>(0, 0).into_owned();
    if !p.iter().all(|x| x.is_finite()) {
        return None;
    }
    let eig = SymmetricEigen::new(0.5 * (p + p.transpose()));
    let max = eig.eigenvalues.max();
    if max <= 0.0 || max > 100.0 {
        return None;
    }
    let axes = eig.eigenvalues.map(|l| 6.0 * l.max(0.0).sqrt());
    let mut r = eig.eigenvectors;
    if r.determinant() < 0.0 {
        r.set_column(2, &(-r.column(2)));
    }
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    Some((axes, rotation))
}

/// Ground truth: `world → truth/v<id>` for every vehicle, and the fused tree
/// hung under the reference vehicle's truth frame.
pub fn sim_truth(fleet: &Fleet, s: &SimTruth) -> Vec<FoxgloveMessage> {
    let mut transforms: Vec<fm::FrameTransform> = s
        .vehicles
        .iter()
        .map(|v| {
            transform(
                s.stamp_ns,
                "world",
                &truth_frame(v.vehicle),
                &v.world_from_body,
            )
        })
        .collect();
    if s.vehicles
        .iter()
        .any(|v| v.vehicle == fleet.reference_vehicle)
    {
        transforms.push(transform(
            s.stamp_ns,
            &truth_frame(fleet.reference_vehicle),
            &body_frame(fleet.reference_vehicle),
            &Pose::identity(),
        ));
    }
    let poses = s
        .vehicles
        .iter()
        .map(|v| pose_value(&v.world_from_body))
        .collect();
    vec![
        msg(
            "/truth/tf".into(),
            FoxgloveValue::FrameTransforms(fm::FrameTransforms { transforms }),
        ),
        msg(
            "/truth/poses".into(),
            FoxgloveValue::PosesInFrame(fm::PosesInFrame {
                timestamp: t(s.stamp_ns),
                frame_id: "world".into(),
                poses,
            }),
        ),
    ]
}

/// Node status as a log line (WARNING when frames were dropped or rejected).
pub fn node_status(s: &NodeStatus) -> Vec<FoxgloveMessage> {
    let cams: Vec<String> = s
        .cameras
        .iter()
        .map(|c| {
            format!(
                "{} {:.1} Hz in {} drop {} missed {} bad {} det {} ({:.0}/{:.0}/{:.0} ms), {} stamps, {} reconnects",
                c.name,
                c.frame_rate_hz,
                c.frames_in,
                c.frames_dropped,
                c.frames_missed,
                c.frames_invalid,
                c.detections,
                c.restore_ms,
                c.detect_ms,
                c.pose_ms,
                c.stamp_source.name(),
                c.reconnects
            )
        })
        .collect();
    let trouble = s.messages_rejected > 0
        || s.cameras
            .iter()
            .any(|c| c.frames_dropped > 0 || c.frames_invalid > 0);
    let text = format!(
        "node {} up {:.1} s, {} observations sent, {} messages rejected; {}",
        s.vehicle,
        s.uptime_s,
        s.observations_sent,
        s.messages_rejected,
        cams.join("; ")
    );
    let level = if trouble {
        fm::log::Level::Warning
    } else {
        fm::log::Level::Info
    };
    vec![msg(
        format!("/v{}/status", s.vehicle),
        log_value(s.stamp_ns, level, text, &format!("node/{}", s.vehicle)),
    )]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ellipsoid_axes_are_three_sigma_and_skip_the_reference() {
        let mut c = Cov6::identity() * 1e-4;
        c[(0, 0)] = 0.04; // σx = 0.2 m
        let (axes, _) = position_ellipsoid(&c).unwrap();
        let mut a: Vec<f64> = axes.iter().copied().collect();
        a.sort_by(f64::total_cmp);
        assert!(
            (a[2] - 1.2).abs() < 1e-9 && (a[0] - 0.06).abs() < 1e-9,
            "{a:?}"
        );
        assert!(position_ellipsoid(&Cov6::zeros()).is_none());
        assert!(position_ellipsoid(&(Cov6::identity() * 1e6)).is_none());
    }
}
