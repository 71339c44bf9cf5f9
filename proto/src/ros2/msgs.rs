//! The ROS 2 messages shoal speaks, field for field as their `.msg` files
//! define them (Jazzy), with their CDR encoding and type identity.
//!
//! Type hashes are REP-2011's `RIHS01` of each type description; the test
//! `tests/ros2_python.rs` recomputes them with Python `rosbags`
//! (`Typestore.hash_rihs01`), an independent implementation.

use super::cdr::{CdrError, CdrReader, CdrWriter};

/// A ROS 2 interface type: `package/msg/Name` and its RIHS01 hash.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RosType {
    pub name: &'static str,
    pub hash: &'static str,
}

impl RosType {
    /// The DDS type name rmw implementations put in keys and tokens:
    /// `geometry_msgs/msg/Pose` → `geometry_msgs::msg::dds_::Pose_`.
    pub fn dds_name(&self) -> String {
        match self.name.rsplit_once('/') {
            Some((ns, name)) => format!("{}::dds_::{name}_", ns.replace('/', "::")),
            None => format!("{}_", self.name),
        }
    }
}

pub const POSE_WITH_COVARIANCE_STAMPED: RosType = RosType {
    name: "geometry_msgs/msg/PoseWithCovarianceStamped",
    hash: "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e",
};
pub const TF_MESSAGE: RosType = RosType {
    name: "tf2_msgs/msg/TFMessage",
    hash: "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
};
pub const DIAGNOSTIC_ARRAY: RosType = RosType {
    name: "diagnostic_msgs/msg/DiagnosticArray",
    hash: "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e",
};
pub const IMAGE: RosType = RosType {
    name: "sensor_msgs/msg/Image",
    hash: "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
};
pub const COMPRESSED_IMAGE: RosType = RosType {
    name: "sensor_msgs/msg/CompressedImage",
    hash: "RIHS01_15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a",
};

/// Every type shoal publishes or subscribes to.
pub const ALL_TYPES: [RosType; 5] = [
    POSE_WITH_COVARIANCE_STAMPED,
    TF_MESSAGE,
    DIAGNOSTIC_ARRAY,
    IMAGE,
    COMPRESSED_IMAGE,
];

/// The separator between definitions in a `ros2msg` schema (80 `=`).
const SEPARATOR: &str =
    "================================================================================\n";
const TIME: &str = "int32 sec\nuint32 nanosec\n";
const HEADER: &str = "builtin_interfaces/Time stamp\nstring frame_id\n";
const QUATERNION: &str = "float64 x\nfloat64 y\nfloat64 z\nfloat64 w\n";
const XYZ: &str = "float64 x\nfloat64 y\nfloat64 z\n";

impl RosType {
    /// The type's full `.msg` definition as MCAP's `ros2msg` schema encoding
    /// (and `rosbag2`) carry it: the type's own fields, then each type it
    /// uses after a line of 80 `=` and `MSG: pkg/Name`. `None` for the
    /// image types, which shoal reads but never writes.
    pub fn ros2msg(&self) -> Option<String> {
        let (own, deps): (&str, &[(&str, &str)]) = match self.name {
            "geometry_msgs/msg/PoseWithCovarianceStamped" => (
                "std_msgs/Header header\ngeometry_msgs/PoseWithCovariance pose\n",
                &[
                    ("std_msgs/Header", HEADER),
                    ("builtin_interfaces/Time", TIME),
                    (
                        "geometry_msgs/PoseWithCovariance",
                        "geometry_msgs/Pose pose\nfloat64[36] covariance\n",
                    ),
                    (
                        "geometry_msgs/Pose",
                        "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
                    ),
                    ("geometry_msgs/Point", XYZ),
                    ("geometry_msgs/Quaternion", QUATERNION),
                ],
            ),
            "tf2_msgs/msg/TFMessage" => (
                "geometry_msgs/TransformStamped[] transforms\n",
                &[
                    (
                        "geometry_msgs/TransformStamped",
                        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n",
                    ),
                    ("std_msgs/Header", HEADER),
                    ("builtin_interfaces/Time", TIME),
                    (
                        "geometry_msgs/Transform",
                        "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
                    ),
                    ("geometry_msgs/Vector3", XYZ),
                    ("geometry_msgs/Quaternion", QUATERNION),
                ],
            ),
            "diagnostic_msgs/msg/DiagnosticArray" => (
                "std_msgs/Header header\ndiagnostic_msgs/DiagnosticStatus[] status\n",
                &[
                    ("std_msgs/Header", HEADER),
                    ("builtin_interfaces/Time", TIME),
                    (
                        "diagnostic_msgs/DiagnosticStatus",
                        "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\nbyte level\nstring name\nstring message\nstring hardware_id\ndiagnostic_msgs/KeyValue[] values\n",
                    ),
                    ("diagnostic_msgs/KeyValue", "string key\nstring value\n"),
                ],
            ),
            _ => return None,
        };
        let mut text = own.to_string();
        for (name, body) in deps {
            text.push_str(SEPARATOR);
            text.push_str("MSG: ");
            text.push_str(name);
            text.push('\n');
            text.push_str(body);
        }
        Some(text)
    }
}

/// A ROS 2 message with its CDR encoding.
pub trait RosMessage: Sized {
    const TYPE: RosType;
    fn write(&self, w: &mut CdrWriter);
    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError>;

    /// The serialized message with its encapsulation header.
    fn to_cdr(&self) -> Vec<u8> {
        let mut w = CdrWriter::new();
        self.write(&mut w);
        w.finish()
    }

    fn from_cdr(bytes: &[u8]) -> Result<Self, CdrError> {
        Self::read(&mut CdrReader::new(bytes)?)
    }
}

/// `builtin_interfaces/msg/Time`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    /// From nanoseconds since the epoch (saturating at 2038's `i32` seconds).
    pub fn from_ns(ns: u64) -> Self {
        Self {
            sec: (ns / 1_000_000_000).min(i32::MAX as u64) as i32,
            nanosec: (ns % 1_000_000_000) as u32,
        }
    }

    /// Nanoseconds since the epoch; `None` before it or with `nanosec` ≥ 1 s.
    pub fn to_ns(self) -> Option<u64> {
        (self.sec >= 0 && self.nanosec < 1_000_000_000)
            .then(|| self.sec as u64 * 1_000_000_000 + self.nanosec as u64)
    }

    fn write(&self, w: &mut CdrWriter) {
        w.i32(self.sec);
        w.u32(self.nanosec);
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(Self {
            sec: r.i32("stamp.sec")?,
            nanosec: r.u32("stamp.nanosec")?,
        })
    }
}

/// `std_msgs/msg/Header`.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

impl Header {
    pub fn new(stamp_ns: u64, frame_id: impl Into<String>) -> Self {
        Self {
            stamp: Time::from_ns(stamp_ns),
            frame_id: frame_id.into(),
        }
    }

    fn write(&self, w: &mut CdrWriter) {
        self.stamp.write(w);
        w.string(&self.frame_id);
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(Self {
            stamp: Time::read(r)?,
            frame_id: r.string("header.frame_id")?,
        })
    }
}

fn write_f64s(w: &mut CdrWriter, values: &[f64]) {
    for &v in values {
        w.f64(v);
    }
}

fn read_f64s<const N: usize>(
    r: &mut CdrReader<'_>,
    field: &'static str,
) -> Result<[f64; N], CdrError> {
    let mut a = [0.0; N];
    for v in &mut a {
        *v = r.f64(field)?;
    }
    Ok(a)
}

/// `geometry_msgs/msg/PoseWithCovarianceStamped`: position, orientation as
/// `(x, y, z, w)`, and the row-major 6x6 covariance over
/// `(x, y, z, rotation about X, Y, Z)` in the header's frame.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseWithCovarianceStamped {
    pub header: Header,
    pub position: [f64; 3],
    pub orientation: [f64; 4],
    pub covariance: [f64; 36],
}

impl RosMessage for PoseWithCovarianceStamped {
    const TYPE: RosType = POSE_WITH_COVARIANCE_STAMPED;

    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        write_f64s(w, &self.position);
        write_f64s(w, &self.orientation);
        write_f64s(w, &self.covariance);
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(Self {
            header: Header::read(r)?,
            position: read_f64s(r, "pose.position")?,
            orientation: read_f64s(r, "pose.orientation")?,
            covariance: read_f64s(r, "pose.covariance")?,
        })
    }
}

/// `geometry_msgs/msg/TransformStamped`.
#[derive(Debug, Clone, PartialEq)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub translation: [f64; 3],
    /// `(x, y, z, w)`.
    pub rotation: [f64; 4],
}

/// `tf2_msgs/msg/TFMessage`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TfMessage {
    pub transforms: Vec<TransformStamped>,
}

impl RosMessage for TfMessage {
    const TYPE: RosType = TF_MESSAGE;

    fn write(&self, w: &mut CdrWriter) {
        w.sequence_len(self.transforms.len());
        for t in &self.transforms {
            t.header.write(w);
            w.string(&t.child_frame_id);
            write_f64s(w, &t.translation);
            write_f64s(w, &t.rotation);
        }
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        // Header (8 + 4) + child frame (4) + 7 doubles at the least.
        let n = r.sequence_len("transforms", 72)?;
        let mut transforms = Vec::with_capacity(n);
        for _ in 0..n {
            transforms.push(TransformStamped {
                header: Header::read(r)?,
                child_frame_id: r.string("child_frame_id")?,
                translation: read_f64s(r, "transform.translation")?,
                rotation: read_f64s(r, "transform.rotation")?,
            });
        }
        Ok(Self { transforms })
    }
}

/// `diagnostic_msgs/msg/KeyValue`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct KeyValue {
    pub key: String,
    pub value: String,
}

/// `diagnostic_msgs/msg/DiagnosticStatus` level constants.
pub mod level {
    pub const OK: u8 = 0;
    pub const WARN: u8 = 1;
    pub const ERROR: u8 = 2;
    pub const STALE: u8 = 3;
}

/// `diagnostic_msgs/msg/DiagnosticStatus`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DiagnosticStatus {
    /// One of [`level`].
    pub level: u8,
    pub name: String,
    pub message: String,
    pub hardware_id: String,
    pub values: Vec<KeyValue>,
}

/// `diagnostic_msgs/msg/DiagnosticArray`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DiagnosticArray {
    pub header: Header,
    pub status: Vec<DiagnosticStatus>,
}

impl RosMessage for DiagnosticArray {
    const TYPE: RosType = DIAGNOSTIC_ARRAY;

    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        w.sequence_len(self.status.len());
        for s in &self.status {
            w.u8(s.level);
            w.string(&s.name);
            w.string(&s.message);
            w.string(&s.hardware_id);
            w.sequence_len(s.values.len());
            for kv in &s.values {
                w.string(&kv.key);
                w.string(&kv.value);
            }
        }
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        let header = Header::read(r)?;
        let n = r.sequence_len("status", 17)?;
        let mut status = Vec::with_capacity(n);
        for _ in 0..n {
            let level = r.u8("status.level")?;
            let name = r.string("status.name")?;
            let message = r.string("status.message")?;
            let hardware_id = r.string("status.hardware_id")?;
            let m = r.sequence_len("status.values", 8)?;
            let mut values = Vec::with_capacity(m);
            for _ in 0..m {
                values.push(KeyValue {
                    key: r.string("values.key")?,
                    value: r.string("values.value")?,
                });
            }
            status.push(DiagnosticStatus {
                level,
                name,
                message,
                hardware_id,
                values,
            });
        }
        Ok(Self { header, status })
    }
}

/// `sensor_msgs/msg/Image`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Image {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    /// `mono8`, `rgb8`, `bgr8`, `mono16`, … (REP-104 / `sensor_msgs/image_encodings.hpp`).
    pub encoding: String,
    pub is_bigendian: u8,
    /// Bytes per row.
    pub step: u32,
    pub data: Vec<u8>,
}

impl RosMessage for Image {
    const TYPE: RosType = IMAGE;

    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        w.u32(self.height);
        w.u32(self.width);
        w.string(&self.encoding);
        w.u8(self.is_bigendian);
        w.u32(self.step);
        w.bytes(&self.data);
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(Self {
            header: Header::read(r)?,
            height: r.u32("height")?,
            width: r.u32("width")?,
            encoding: r.string("encoding")?,
            is_bigendian: r.u8("is_bigendian")?,
            step: r.u32("step")?,
            data: r.bytes("data")?.to_vec(),
        })
    }
}

/// `sensor_msgs/msg/CompressedImage`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CompressedImage {
    pub header: Header,
    /// `jpeg`, `png`, or image_transport's `"<enc>; jpeg compressed <enc>"`.
    pub format: String,
    pub data: Vec<u8>,
}

impl RosMessage for CompressedImage {
    const TYPE: RosType = COMPRESSED_IMAGE;

    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        w.string(&self.format);
        w.bytes(&self.data);
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(Self {
            header: Header::read(r)?,
            format: r.string("format")?,
            data: r.bytes("data")?.to_vec(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dds_names_follow_rmw() {
        assert_eq!(
            POSE_WITH_COVARIANCE_STAMPED.dds_name(),
            "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"
        );
        assert_eq!(TF_MESSAGE.dds_name(), "tf2_msgs::msg::dds_::TFMessage_");
        for t in ALL_TYPES {
            assert!(t.hash.starts_with("RIHS01_") && t.hash.len() == 71, "{t:?}");
        }
    }

    #[test]
    fn every_message_round_trips_and_a_cut_one_is_refused() {
        let header = Header::new(1_700_000_000_123_456_789, "auv10/base_link");
        let pose = PoseWithCovarianceStamped {
            header: header.clone(),
            position: [1.0, -2.0, 3.5],
            orientation: [0.0, 0.0, 0.6, 0.8],
            covariance: std::array::from_fn(|i| i as f64 * 0.5),
        };
        let bytes = pose.to_cdr();
        // Encapsulation 4; stamp 8 and "auv10/base_link\0" (4 + 16) end at
        // 28, padded to 32 for the 3 + 4 + 36 doubles.
        assert_eq!(bytes.len(), 4 + 28 + 4 + 43 * 8);
        assert_eq!(PoseWithCovarianceStamped::from_cdr(&bytes).unwrap(), pose);
        for cut in [0, 3, 10, bytes.len() - 1] {
            assert!(PoseWithCovarianceStamped::from_cdr(&bytes[..cut]).is_err());
        }
        let tf = TfMessage {
            transforms: vec![TransformStamped {
                header: header.clone(),
                child_frame_id: "auv17/base_link".into(),
                translation: [1.0, 2.0, 3.0],
                rotation: [0.0, 0.0, 0.0, 1.0],
            }],
        };
        assert_eq!(TfMessage::from_cdr(&tf.to_cdr()).unwrap(), tf);
        let diag = DiagnosticArray {
            header: header.clone(),
            status: vec![DiagnosticStatus {
                level: level::WARN,
                name: "shoal node auv10".into(),
                message: "camera 1 has no frames".into(),
                hardware_id: "auv10".into(),
                values: vec![KeyValue {
                    key: "uptime_s".into(),
                    value: "12.5".into(),
                }],
            }],
        };
        assert_eq!(DiagnosticArray::from_cdr(&diag.to_cdr()).unwrap(), diag);
        let image = Image {
            header: header.clone(),
            height: 2,
            width: 3,
            encoding: "mono8".into(),
            is_bigendian: 0,
            step: 3,
            data: vec![1, 2, 3, 4, 5, 6],
        };
        assert_eq!(Image::from_cdr(&image.to_cdr()).unwrap(), image);
        let jpeg = CompressedImage {
            header,
            format: "jpeg".into(),
            data: vec![0xFF, 0xD8, 0xFF],
        };
        assert_eq!(CompressedImage::from_cdr(&jpeg.to_cdr()).unwrap(), jpeg);
    }

    #[test]
    fn written_types_carry_their_whole_definition() {
        let pose = POSE_WITH_COVARIANCE_STAMPED.ros2msg().unwrap();
        assert!(pose.starts_with("std_msgs/Header header\n"));
        // Header, Time, PoseWithCovariance, Pose, Point, Quaternion.
        assert_eq!(pose.matches("\nMSG: ").count(), 6);
        assert!(pose.contains(&format!("\n{}\nMSG: std_msgs/Header\n", "=".repeat(80))));
        assert_eq!(TF_MESSAGE.ros2msg().unwrap().matches("MSG: ").count(), 6);
        assert_eq!(
            DIAGNOSTIC_ARRAY.ros2msg().unwrap().matches("MSG: ").count(),
            4
        );
        assert_eq!(IMAGE.ros2msg(), None);
    }

    #[test]
    fn time_splits_nanoseconds() {
        let t = Time::from_ns(5_000_000_007);
        assert_eq!((t.sec, t.nanosec), (5, 7));
        assert_eq!(t.to_ns(), Some(5_000_000_007));
        assert_eq!(
            Time {
                sec: -1,
                nanosec: 0
            }
            .to_ns(),
            None
        );
    }
}
