//! The JSON schemas of the Foxglove well-known types shoal writes, written
//! from Foxglove's published definitions (see the parent module).

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
