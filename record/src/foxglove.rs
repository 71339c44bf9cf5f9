//! shoal's messages in Foxglove's well-known schemas, JSON encoding
//! (`message_encoding = "json"`, `schema encoding = "jsonschema"`), so a log
//! opens in Foxglove with no shoal code.
//!
//! The JSON schemas below are written here from Foxglove's published schema
//! definitions (<https://docs.foxglove.dev/docs/visualization/message-schemas>):
//! same type names, field names, units and enum values. Times are
//! `{sec, nsec}`; `bytes` fields are base64 strings (Foxglove's JSON
//! convention). Only the fields shoal fills are listed as properties; Foxglove
//! treats absent arrays as empty.
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

use nalgebra::{Matrix3, Rotation3, SymmetricEigen, UnitQuaternion, Vector3};
use proto::config::Fleet;
use proto::geometry::{Cov6, Pose};
use proto::{FleetMap, NodeStatus, Observation, PixelFormat, SimTruth, VehicleId, VehicleState};
use serde_json::{json, Value};

/// A Foxglove well-known schema shoal writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum FoxgloveSchema {
    FrameTransforms,
    PosesInFrame,
    Log,
    SceneUpdate,
    CompressedImage,
    ImageAnnotations,
}

impl FoxgloveSchema {
    pub const ALL: [FoxgloveSchema; 6] = [
        FoxgloveSchema::FrameTransforms,
        FoxgloveSchema::PosesInFrame,
        FoxgloveSchema::Log,
        FoxgloveSchema::SceneUpdate,
        FoxgloveSchema::CompressedImage,
        FoxgloveSchema::ImageAnnotations,
    ];

    /// Schema name as Foxglove knows it.
    pub fn name(self) -> &'static str {
        match self {
            FoxgloveSchema::FrameTransforms => "foxglove.FrameTransforms",
            FoxgloveSchema::PosesInFrame => "foxglove.PosesInFrame",
            FoxgloveSchema::Log => "foxglove.Log",
            FoxgloveSchema::SceneUpdate => "foxglove.SceneUpdate",
            FoxgloveSchema::CompressedImage => "foxglove.CompressedImage",
            FoxgloveSchema::ImageAnnotations => "foxglove.ImageAnnotations",
        }
    }

    /// The JSON schema (draft 2020-12) embedded in the log.
    pub fn json_schema(self) -> Value {
        let mut s = match self {
            FoxgloveSchema::FrameTransforms => object(
                "A list of transforms",
                &[("transforms", array(frame_transform()))],
            ),
            FoxgloveSchema::PosesInFrame => object(
                "An array of timestamped poses for an object or reference frame in 3D space",
                &[
                    ("timestamp", time()),
                    ("frame_id", string()),
                    ("poses", array(pose())),
                ],
            ),
            FoxgloveSchema::Log => object(
                "A log message",
                &[
                    ("timestamp", time()),
                    (
                        "level",
                        json!({"type": "integer", "description": "Log level: 0 UNKNOWN, 1 DEBUG, 2 INFO, 3 WARNING, 4 ERROR, 5 FATAL",
                               "minimum": 0, "maximum": 5}),
                    ),
                    ("message", string()),
                    ("name", string()),
                    ("file", string()),
                    ("line", json!({"type": "integer", "minimum": 0})),
                ],
            ),
            FoxgloveSchema::SceneUpdate => object(
                "An update to the entities displayed in a 3D scene",
                &[
                    ("deletions", array(scene_entity_deletion())),
                    ("entities", array(scene_entity())),
                ],
            ),
            FoxgloveSchema::CompressedImage => object(
                "A compressed image",
                &[
                    ("timestamp", time()),
                    ("frame_id", string()),
                    (
                        "data",
                        json!({"type": "string", "contentEncoding": "base64"}),
                    ),
                    ("format", string()),
                ],
            ),
            FoxgloveSchema::ImageAnnotations => object(
                "Array of annotations for a 2D image",
                &[
                    ("circles", array(json!({"type": "object"}))),
                    ("points", array(points_annotation())),
                    ("texts", array(text_annotation())),
                ],
            ),
        };
        s["$schema"] = json!("https://json-schema.org/draft/2020-12/schema");
        s["title"] = json!(self.name());
        s
    }
}

fn object(description: &str, props: &[(&str, Value)]) -> Value {
    let mut p = serde_json::Map::new();
    let mut required = Vec::new();
    for (k, v) in props {
        p.insert((*k).to_string(), v.clone());
        required.push(json!(k));
    }
    json!({"type": "object", "description": description, "properties": p, "required": required})
}
fn array(item: Value) -> Value {
    json!({"type": "array", "items": item})
}
fn string() -> Value {
    json!({"type": "string"})
}
fn number() -> Value {
    json!({"type": "number"})
}
fn time() -> Value {
    object(
        "Timestamp",
        &[
            ("sec", json!({"type": "integer", "minimum": 0})),
            (
                "nsec",
                json!({"type": "integer", "minimum": 0, "maximum": 999_999_999}),
            ),
        ],
    )
}
fn vector3() -> Value {
    object(
        "A vector in 3D space",
        &[("x", number()), ("y", number()), ("z", number())],
    )
}
fn quaternion() -> Value {
    object(
        "A quaternion (x, y, z, w)",
        &[
            ("x", number()),
            ("y", number()),
            ("z", number()),
            ("w", number()),
        ],
    )
}
fn pose() -> Value {
    object(
        "A position and orientation",
        &[("position", vector3()), ("orientation", quaternion())],
    )
}
fn color() -> Value {
    object(
        "RGBA color, 0..1",
        &[
            ("r", number()),
            ("g", number()),
            ("b", number()),
            ("a", number()),
        ],
    )
}
fn point2() -> Value {
    object(
        "A point in 2D (pixels)",
        &[("x", number()), ("y", number())],
    )
}
fn frame_transform() -> Value {
    object(
        "A transform between two reference frames in 3D space",
        &[
            ("timestamp", time()),
            ("parent_frame_id", string()),
            ("child_frame_id", string()),
            ("translation", vector3()),
            ("rotation", quaternion()),
        ],
    )
}
fn scene_entity_deletion() -> Value {
    object(
        "Command to remove previously published entities",
        &[
            ("timestamp", time()),
            (
                "type",
                json!({"type": "integer", "minimum": 0, "maximum": 1}),
            ),
            ("id", string()),
        ],
    )
}
fn primitive(description: &str, extra: &[(&str, Value)]) -> Value {
    let mut props = vec![("pose", pose()), ("size", vector3()), ("color", color())];
    props.extend(extra.iter().cloned());
    object(description, &props)
}
fn scene_entity() -> Value {
    object(
        "A visual element in a 3D scene",
        &[
            ("timestamp", time()),
            ("frame_id", string()),
            ("id", string()),
            (
                "lifetime",
                object(
                    "Duration",
                    &[
                        ("sec", json!({"type": "integer"})),
                        ("nsec", json!({"type": "integer", "minimum": 0})),
                    ],
                ),
            ),
            ("frame_locked", json!({"type": "boolean"})),
            (
                "metadata",
                array(object(
                    "A key with its associated value",
                    &[("key", string()), ("value", string())],
                )),
            ),
            ("arrows", array(json!({"type": "object"}))),
            ("cubes", array(json!({"type": "object"}))),
            ("spheres", array(primitive("A sphere or ellipsoid", &[]))),
            (
                "cylinders",
                array(primitive(
                    "A cylinder, cone or truncated cone",
                    &[("bottom_scale", number()), ("top_scale", number())],
                )),
            ),
            ("lines", array(json!({"type": "object"}))),
            ("triangles", array(json!({"type": "object"}))),
            (
                "texts",
                array(object(
                    "A text label",
                    &[
                        ("pose", pose()),
                        ("billboard", json!({"type": "boolean"})),
                        ("font_size", number()),
                        ("scale_invariant", json!({"type": "boolean"})),
                        ("color", color()),
                        ("text", string()),
                    ],
                )),
            ),
            ("models", array(json!({"type": "object"}))),
        ],
    )
}
fn points_annotation() -> Value {
    object(
        "An array of points on a 2D image",
        &[
            ("timestamp", time()),
            (
                "type",
                json!({"type": "integer", "description": "0 UNKNOWN, 1 POINTS, 2 LINE_LOOP, 3 LINE_STRIP, 4 LINE_LIST", "minimum": 0, "maximum": 4}),
            ),
            ("points", array(point2())),
            ("outline_color", color()),
            ("outline_colors", array(color())),
            ("fill_color", color()),
            ("thickness", number()),
        ],
    )
}
fn text_annotation() -> Value {
    object(
        "A text label on a 2D image",
        &[
            ("timestamp", time()),
            ("position", point2()),
            ("text", string()),
            ("font_size", number()),
            ("text_color", color()),
            ("background_color", color()),
        ],
    )
}

// ---------------------------------------------------------------- values

fn t(stamp_ns: u64) -> Value {
    json!({"sec": stamp_ns / 1_000_000_000, "nsec": stamp_ns % 1_000_000_000})
}
fn v3(v: &Vector3<f64>) -> Value {
    json!({"x": v.x, "y": v.y, "z": v.z})
}
fn q(r: &UnitQuaternion<f64>) -> Value {
    json!({"x": r.i, "y": r.j, "z": r.k, "w": r.w})
}
fn pose_value(p: &Pose) -> Value {
    json!({"position": v3(&p.translation.vector), "orientation": q(&p.rotation)})
}
fn rgba(r: f64, g: f64, b: f64, a: f64) -> Value {
    json!({"r": r, "g": g, "b": b, "a": a})
}
fn transform(stamp_ns: u64, parent: &str, child: &str, parent_from_child: &Pose) -> Value {
    json!({
        "timestamp": t(stamp_ns),
        "parent_frame_id": parent,
        "child_frame_id": child,
        "translation": v3(&parent_from_child.translation.vector),
        "rotation": q(&parent_from_child.rotation),
    })
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

/// One Foxglove message to write.
#[derive(Debug, Clone, PartialEq)]
pub struct FoxgloveMessage {
    pub topic: String,
    pub schema: FoxgloveSchema,
    pub value: Value,
}

fn msg(topic: String, schema: FoxgloveSchema, value: Value) -> FoxgloveMessage {
    FoxgloveMessage {
        topic,
        schema,
        value,
    }
}

/// A vehicle's display colour (stable per ID).
fn vehicle_color(v: VehicleId, a: f64) -> Value {
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
    let poses = json!({
        "timestamp": t(o.stamp_ns),
        "frame_id": body_frame(o.observer),
        "poses": [pose_value(&o.observer_from_target)],
    });
    let color = if o.predicted {
        rgba(0.6, 0.6, 0.6, 1.0)
    } else {
        rgba(0.1, 1.0, 0.2, 1.0)
    };
    let points: Vec<Value> = o
        .corners_px
        .iter()
        .map(|c| json!({"x": c[0], "y": c[1]}))
        .collect();
    let label_at = o.corners_px.first().map_or(
        json!({"x": 0.0, "y": 0.0}),
        |c| json!({"x": c[0], "y": c[1]}),
    );
    let target = o
        .target_vehicle
        .map_or_else(|| "?".to_string(), |v| v.to_string());
    let annotations = json!({
        "circles": [],
        "points": [{
            "timestamp": t(o.stamp_ns),
            "type": 1,
            "points": points,
            "outline_color": color,
            "outline_colors": [],
            "fill_color": color,
            "thickness": 6.0,
        }],
        "texts": [{
            "timestamp": t(o.stamp_ns),
            "position": label_at,
            "text": format!("{}#{} -> v{target}, rms {:.2} px", o.codes, o.target_marker, o.reprojection_rms_px),
            "font_size": 24.0,
            "text_color": rgba(1.0, 1.0, 1.0, 1.0),
            "background_color": rgba(0.0, 0.0, 0.0, 0.6),
        }],
    });
    vec![
        msg(
            format!("/v{}/observations", o.observer),
            FoxgloveSchema::PosesInFrame,
            poses,
        ),
        msg(
            format!("{}/annotations", camera_topic(fleet, o.observer, o.camera)),
            FoxgloveSchema::ImageAnnotations,
            annotations,
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
                    veh.hull.diameter_m,
                    veh.hull.length_m,
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
            FoxgloveSchema::FrameTransforms,
            json!({"transforms": transforms}),
        ),
        msg(
            format!("{prefix}/poses"),
            FoxgloveSchema::PosesInFrame,
            json!({"timestamp": t(m.stamp_ns), "frame_id": reference, "poses": poses}),
        ),
        msg(
            format!("{prefix}/scene"),
            FoxgloveSchema::SceneUpdate,
            json!({"deletions": [], "entities": entities}),
        ),
        msg(
            format!("{prefix}/log"),
            FoxgloveSchema::Log,
            log_value(
                m.stamp_ns,
                2,
                &format!(
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
    msg(
        "/liveliness".to_string(),
        FoxgloveSchema::Log,
        log_value(stamp_ns, if alive { 2 } else { 3 }, &text, "liveliness"),
    )
}

fn log_value(stamp_ns: u64, level: u8, message: &str, name: &str) -> Value {
    json!({"timestamp": t(stamp_ns), "level": level, "message": message, "name": name, "file": "", "line": 0})
}

/// Hull (cylinder along body x) in the vehicle's body frame, and the 3-sigma
/// ellipsoid of its position covariance in the reference frame (covariances
/// are over the left-frame perturbation, `proto::geometry`).
fn vehicle_entity(
    stamp_ns: u64,
    reference: &str,
    v: VehicleId,
    diameter_m: f64,
    length_m: f64,
    reference_from_vehicle: &Pose,
    cov: &Cov6,
    state: VehicleState,
) -> Vec<Value> {
    let alpha = if state == VehicleState::Live {
        0.9
    } else {
        0.35
    };
    let hull_axis =
        UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_2);
    let hull = json!({
        "pose": {"position": v3(&Vector3::zeros()), "orientation": q(&hull_axis)},
        "size": {"x": diameter_m, "y": diameter_m, "z": length_m},
        "bottom_scale": 1.0, "top_scale": 1.0,
        "color": vehicle_color(v, alpha),
    });
    let mut out = vec![json!({
        "timestamp": t(stamp_ns),
        "frame_id": body_frame(v),
        "id": format!("vehicle/{v}"),
        "lifetime": {"sec": 0, "nsec": 0},
        "frame_locked": true,
        "metadata": [{"key": "state", "value": format!("{state:?}")}, {"key": "reference", "value": reference}],
        "arrows": [], "cubes": [], "spheres": [],
        "cylinders": [hull],
        "lines": [], "triangles": [],
        "texts": [{
            "pose": {"position": {"x": 0.0, "y": 0.0, "z": -diameter_m}, "orientation": q(&UnitQuaternion::identity())},
            "billboard": true, "font_size": 14.0, "scale_invariant": true,
            "color": rgba(1.0, 1.0, 1.0, 1.0),
            "text": format!("v{v} {state:?}"),
        }],
        "models": [],
    })];
    // The ellipsoid lives in the reference frame (left-frame perturbation): a second entity.
    if let Some((axes, rotation)) = position_ellipsoid(cov) {
        let center = reference_from_vehicle.translation.vector;
        out.push(json!({
            "timestamp": t(stamp_ns),
            "frame_id": reference,
            "id": format!("covariance/{v}"),
            "lifetime": {"sec": 0, "nsec": 0},
            "frame_locked": true,
            "metadata": [{"key": "sigma", "value": "3"}],
            "arrows": [], "cubes": [],
            "spheres": [{
                "pose": {"position": v3(&center), "orientation": q(&rotation)},
                "size": v3(&axes),
                "color": vehicle_color(v, 0.3),
            }],
            "cylinders": [], "lines": [], "triangles": [], "texts": [], "models": [],
        }));
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
    let mut transforms: Vec<Value> = s
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
    let poses: Vec<Value> = s
        .vehicles
        .iter()
        .map(|v| pose_value(&v.world_from_body))
        .collect();
    vec![
        msg(
            "/truth/tf".into(),
            FoxgloveSchema::FrameTransforms,
            json!({"transforms": transforms}),
        ),
        msg(
            "/truth/poses".into(),
            FoxgloveSchema::PosesInFrame,
            json!({"timestamp": t(s.stamp_ns), "frame_id": "world", "poses": poses}),
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
                "{} {:.1} Hz in {} drop {} bad {} det {} ({:.0}/{:.0}/{:.0} ms)",
                c.name,
                c.frame_rate_hz,
                c.frames_in,
                c.frames_dropped,
                c.frames_invalid,
                c.detections,
                c.restore_ms,
                c.detect_ms,
                c.pose_ms
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
    vec![msg(
        format!("/v{}/status", s.vehicle),
        FoxgloveSchema::Log,
        log_value(
            s.stamp_ns,
            if trouble { 3 } else { 2 },
            &text,
            &format!("node/{}", s.vehicle),
        ),
    )]
}

/// The fields of a `CameraFrame` envelope the recorder needs, read in place
/// at the offsets pinned by `docs/wire.md` (no copy of the pixels; decoding
/// the whole frame through serde costs more than encoding its PNG).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameView<'a> {
    pub vehicle: VehicleId,
    pub camera: u8,
    pub seq: u64,
    pub stamp_ns: u64,
    pub width: u32,
    pub height: u32,
    pub format: PixelFormat,
    pub data: &'a [u8],
}

impl<'a> FrameView<'a> {
    /// Byte offsets in the payload (after the 12-byte envelope header).
    const FORMAT_AT: usize = 4 + 1 + 8 + 8 + (2 * 4 + 4 * 8 + 5 * 8) + 7 * 8;
    const DATA_AT: usize = Self::FORMAT_AT + 4 + 8;

    /// `None` unless `envelope` is a well-formed `CameraFrame` whose pixel count agrees with its size.
    pub fn parse(envelope: &'a [u8]) -> Option<FrameView<'a>> {
        let header = proto::codec::peek_header(envelope).ok()?;
        if header.kind != proto::MessageKind::CameraFrame {
            return None;
        }
        let p = envelope.get(proto::codec::HEADER_LEN..)?;
        let u32_at = |o: usize| {
            p.get(o..o + 4)
                .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        };
        let u64_at = |o: usize| {
            p.get(o..o + 8)
                .map(|b| u64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]))
        };
        let format = match u32_at(Self::FORMAT_AT)? {
            0 => PixelFormat::Mono8,
            1 => PixelFormat::Rgb8,
            _ => return None,
        };
        let (width, height) = (u32_at(21)?, u32_at(25)?);
        let len = usize::try_from(u64_at(Self::FORMAT_AT + 4)?).ok()?;
        let want = (width as usize)
            .checked_mul(height as usize)?
            .checked_mul(format.channels())?;
        if len != want || p.len() != Self::DATA_AT + len {
            return None;
        }
        Some(FrameView {
            vehicle: u32_at(0)?,
            camera: p[4],
            seq: u64_at(5)?,
            stamp_ns: u64_at(13)?,
            width,
            height,
            format,
            data: &p[Self::DATA_AT..],
        })
    }
}

/// A camera frame as a PNG `CompressedImage` (Foxglove decodes PNG in the browser).
pub fn camera_image(
    fleet: &Fleet,
    f: &FrameView<'_>,
) -> Result<FoxgloveMessage, image::ImageError> {
    let color = match f.format {
        PixelFormat::Mono8 => image::ExtendedColorType::L8,
        PixelFormat::Rgb8 => image::ExtendedColorType::Rgb8,
    };
    let mut png = Vec::with_capacity(f.data.len() / 2);
    // Fast deflate: frames arrive at camera rate; zstd on the chunk does the rest.
    let encoder = image::codecs::png::PngEncoder::new_with_quality(
        &mut png,
        image::codecs::png::CompressionType::Fast,
        image::codecs::png::FilterType::Sub,
    );
    image::ImageEncoder::write_image(encoder, f.data, f.width, f.height, color)?;
    Ok(msg(
        format!("{}/image", camera_topic(fleet, f.vehicle, f.camera)),
        FoxgloveSchema::CompressedImage,
        json!({"timestamp": t(f.stamp_ns), "frame_id": camera_frame(fleet, f.vehicle, f.camera), "data": base64(&png), "format": "png"}),
    ))
}

/// Standard base64 with padding (RFC 4648 §4), Foxglove's JSON encoding of `bytes`.
pub fn base64(bytes: &[u8]) -> String {
    use base64::Engine;
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_matches_rfc4648_vectors() {
        for (plain, enc) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(plain.as_bytes()), enc);
        }
    }

    #[test]
    fn frame_view_reads_what_the_codec_wrote() {
        let f = proto::CameraFrame {
            vehicle: 15,
            camera: 3,
            seq: 9,
            stamp_ns: 123_456,
            info: proto::CameraInfo {
                model: proto::CameraModel {
                    width: 4,
                    height: 2,
                    fx: 5.0,
                    fy: 5.0,
                    cx: 2.0,
                    cy: 1.0,
                    distortion: [0.1; 5],
                },
                body_from_camera: Pose::identity(),
            },
            format: PixelFormat::Rgb8,
            data: (0..24).collect(),
        };
        let bytes = proto::encode(&f).unwrap();
        let v = FrameView::parse(&bytes).unwrap();
        assert_eq!(
            (v.vehicle, v.camera, v.seq, v.stamp_ns, v.width, v.height, v.format),
            (15, 3, 9, 123_456, 4, 2, PixelFormat::Rgb8)
        );
        assert_eq!(v.data, &f.data[..]);
        assert!(FrameView::parse(&bytes[..bytes.len() - 1]).is_none());
        let obs_like = proto::encode(&proto::VehicleCommand {
            vehicle: 1,
            stamp_ns: 2,
            velocity_body: [0.0; 3],
            yaw_rate: 0.0,
        })
        .unwrap();
        assert!(FrameView::parse(&obs_like).is_none());
    }

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
