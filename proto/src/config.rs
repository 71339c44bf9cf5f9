//! Fleet files (TOML) and camera calibrations (OpenCV / ROS YAML).
//!
//! A fleet file names the vehicles, the markers each carries
//! (`body_from_marker`) and its cameras (`body_from_camera`, intrinsics).
//! Cameras are usually shared through a named *rig*. Loading rejects unknown
//! fields and reports the file, the field and the reason. See
//! `configs/fleets/paper.toml` for a complete, commented example.

use crate::camera::{CalibrationSigma, CameraModel, Distortion, DISTORTION_MODELS};
use crate::geometry::{pose_from_xyz_rpy, Pose};
use crate::keys::Keys;
use crate::marker::{CodeSet, MarkerId};
use crate::messages::VehicleId;
use crate::port::FlatPort;
use serde::Deserialize;
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{}: cannot read", path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: {message}", path.display())]
    Parse { path: PathBuf, message: String },
    #[error("{}: field `{field}`: {reason}", path.display())]
    Invalid {
        path: PathBuf,
        field: String,
        reason: String,
    },
}

/// A mounting transform as written in config files.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MountSpec {
    /// Translation, metres.
    #[serde(deserialize_with = "exactly")]
    pub xyz_m: [f64; 3],
    /// Roll, pitch, yaw in degrees, `R = Rz(yaw)·Ry(pitch)·Rx(roll)`.
    #[serde(default, deserialize_with = "exactly")]
    pub rpy_deg: [f64; 3],
}

impl MountSpec {
    pub fn pose(&self) -> Pose {
        pose_from_xyz_rpy(self.xyz_m, self.rpy_deg.map(f64::to_radians))
    }
}

/// Intrinsics written inline.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(try_from = "RawIntrinsics")]
pub struct IntrinsicsSpec {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// `distortion_model` (ROS names, default `plumb_bob`) with `distortion`:
    /// `k1 k2 p1 p2 [k3]`, `k1 … k6` (rational) or `k1 k2 k3 k4` (equidistant);
    /// further coefficients only when zero (as in a calibration file).
    pub distortion: Distortion,
}

/// [`IntrinsicsSpec`] as written, before its lens model is checked.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawIntrinsics {
    width: u32,
    height: u32,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    #[serde(default)]
    distortion_model: Option<String>,
    #[serde(default)]
    distortion: Vec<f64>,
}

impl TryFrom<RawIntrinsics> for IntrinsicsSpec {
    type Error = String;
    fn try_from(r: RawIntrinsics) -> Result<Self, String> {
        let model = r.distortion_model.as_deref().or(Some("plumb_bob"));
        Ok(IntrinsicsSpec {
            width: r.width,
            height: r.height,
            fx: r.fx,
            fy: r.fy,
            cx: r.cx,
            cy: r.cy,
            distortion: Distortion::from_ros(model, &r.distortion)?,
        })
    }
}

/// A fixed-length array written as a TOML array of exactly `N` numbers (a
/// plain `[f64; N]` would take the first `N` of a longer one and drop the rest).
fn exactly<'de, D, const N: usize>(d: D) -> Result<[f64; N], D::Error>
where
    D: serde::Deserializer<'de>,
{
    let v: Vec<f64> = Vec::deserialize(d)?;
    let n = v.len();
    v.try_into().map_err(|_| {
        serde::de::Error::invalid_length(n, &format!("an array of exactly {N} numbers").as_str())
    })
}

impl From<IntrinsicsSpec> for CameraModel {
    fn from(i: IntrinsicsSpec) -> CameraModel {
        CameraModel {
            width: i.width,
            height: i.height,
            fx: i.fx,
            fy: i.fy,
            cx: i.cx,
            cy: i.cy,
            distortion: i.distortion,
        }
    }
}

/// One camera of a rig: exactly one of `preset`, `calibration`, `intrinsics`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    pub name: String,
    /// `vehicle_1440` or `paper_eq3`.
    pub preset: Option<String>,
    /// OpenCV or ROS calibration YAML, relative to the fleet file.
    pub calibration: Option<PathBuf>,
    pub intrinsics: Option<IntrinsicsSpec>,
    pub body_from_camera: MountSpec,
    /// The flat window the camera looks through, if the node's PnP should
    /// model its refraction (`docs/water-model.md`). Without it the
    /// calibration is taken as the in-water pinhole a lab would measure.
    #[serde(default)]
    pub port: Option<PortSpec>,
    /// How uncertain the calibration is (one σ of fx and fy relative, of cx
    /// and cy in px, of k1): the node's pose covariance then includes the
    /// error it causes. Without it the calibration is taken as exact.
    #[serde(default)]
    pub calibration_sigma: Option<CalibrationSigma>,
}

/// A flat port as written in a fleet file: air inside, then the glass,
/// then the water; the window perpendicular to the optical axis.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PortSpec {
    /// From the lens centre (entrance pupil) to the inner glass surface, mm.
    pub distance_mm: f64,
    /// Glass thickness, mm.
    pub glass_mm: f64,
    /// Refractive index of the glass; default acrylic, 1.49.
    #[serde(default = "default_n_glass")]
    pub n_glass: f64,
    /// Refractive index of the water; default sea water, 1.34 (fresh: 1.333).
    #[serde(default = "default_n_water")]
    pub n_water: f64,
}

fn default_n_glass() -> f64 {
    FlatPort::N_ACRYLIC
}

fn default_n_water() -> f64 {
    FlatPort::N_SEA_WATER
}

impl PortSpec {
    /// The port in SI units, validated; the error names the bad value.
    pub fn port(&self) -> Result<FlatPort, String> {
        let port = FlatPort {
            distance_m: self.distance_mm * 1e-3,
            glass_m: self.glass_mm * 1e-3,
            n_glass: self.n_glass,
            n_water: self.n_water,
        };
        match port.problem() {
            Some(p) => Err(p),
            None => Ok(port),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RigSpec {
    pub cameras: Vec<CameraSpec>,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MarkerSpec {
    /// Code set name (`shoal`, `aruco4x4_50`, `apriltag36h11`, …).
    pub codes: String,
    pub id: MarkerId,
    /// Side of the outer black square, metres.
    pub side_m: f64,
    pub body_from_marker: MountSpec,
}

#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HullSpec {
    pub diameter_m: f64,
    pub length_m: f64,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VehicleSpec {
    pub id: VehicleId,
    pub name: String,
    pub hull: HullSpec,
    /// Name of a rig in `[rigs]`.
    pub rig: String,
    #[serde(default)]
    pub markers: Vec<MarkerSpec>,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
struct FleetFile {
    fleet: String,
    reference_vehicle: VehicleId,
    #[serde(default)]
    description: String,
    rigs: BTreeMap<String, RigSpec>,
    vehicles: Vec<VehicleSpec>,
    #[serde(default)]
    ros2: Option<Ros2Settings>,
}

/// A fleet file's `[ros2]` table: the services hosting a ROS 2 publisher
/// (`shoal fusion`, `shoal demo`) publish in ROS 2 as if given `--ros2`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ros2Settings {
    /// The ROS 2 domain ID (0–232); `ROS_DOMAIN_ID` and `--ros2-domain` override it.
    #[serde(default)]
    pub domain: u32,
}

/// A resolved camera.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    pub index: u8,
    pub name: String,
    pub model: CameraModel,
    pub body_from_camera: Pose,
    /// The flat port in front of the lens, when the fleet file gives one:
    /// PnP then models its refraction instead of taking `model` as an
    /// in-water pinhole.
    pub port: Option<FlatPort>,
    /// The calibration's uncertainty, when the fleet file states it
    /// ([`CalibrationSigma`]); `None`: taken as exact.
    pub calibration_sigma: Option<CalibrationSigma>,
}

/// A resolved marker mounted on a vehicle.
#[derive(Debug, Clone, PartialEq)]
pub struct Marker {
    pub codes: CodeSet,
    pub id: MarkerId,
    pub side_m: f64,
    pub body_from_marker: Pose,
}

/// A resolved vehicle.
#[derive(Debug, Clone, PartialEq)]
pub struct Vehicle {
    pub id: VehicleId,
    pub name: String,
    pub hull: HullSpec,
    pub markers: Vec<Marker>,
    pub cameras: Vec<Camera>,
}

/// A loaded, validated fleet.
#[derive(Debug, Clone, PartialEq)]
pub struct Fleet {
    pub name: String,
    pub description: String,
    pub reference_vehicle: VehicleId,
    pub vehicles: Vec<Vehicle>,
    /// Publish in ROS 2 too (the file's `[ros2]` table).
    pub ros2: Option<Ros2Settings>,
    /// Where it was loaded from (for messages and relative paths).
    pub source: PathBuf,
}

/// Who carries a marker, as far as the fleet file says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MarkerOwner {
    Vehicle(VehicleId),
    Unknown,
    /// Two or more vehicles list the same code set and ID.
    Ambiguous,
}

/// The cameras of every rig in `[rigs]`, validated (a step of [`Fleet::parse`]).
fn parse_rigs<'a>(
    specs: &'a BTreeMap<String, RigSpec>,
    base: &Path,
    invalid: &impl Fn(String, String) -> ConfigError,
) -> Result<HashMap<&'a str, Vec<Camera>>, ConfigError> {
    let mut rigs: HashMap<&str, Vec<Camera>> = HashMap::new();
    for (rig_name, rig) in specs {
        if rig.cameras.len() > 255 {
            return Err(invalid(
                format!("rigs.{rig_name}.cameras"),
                "at most 255 cameras".into(),
            ));
        }
        let mut cams = Vec::new();
        for (i, c) in rig.cameras.iter().enumerate() {
            let field = format!("rigs.{rig_name}.cameras[{i}]");
            let model = resolve_camera(c, base).map_err(|r| invalid(field.clone(), r))?;
            if let Some(p) = model.problem() {
                return Err(invalid(field, p));
            }
            check_mount(&c.body_from_camera)
                .map_err(|r| invalid(format!("{field}.body_from_camera"), r))?;
            let port = c
                .port
                .map(|p| p.port())
                .transpose()
                .map_err(|r| invalid(format!("{field}.port"), r))?;
            if let Some(p) = c.calibration_sigma.and_then(|s| s.problem()) {
                return Err(invalid(format!("{field}.calibration_sigma"), p));
            }
            cams.push(Camera {
                index: i as u8,
                name: c.name.clone(),
                model,
                body_from_camera: c.body_from_camera.pose(),
                port,
                calibration_sigma: c.calibration_sigma,
            });
        }
        rigs.insert(rig_name.as_str(), cams);
    }
    Ok(rigs)
}

/// A vehicle's markers, validated; `field` names the vehicle in messages
/// (a step of [`Fleet::parse`]).
fn parse_markers(
    field: &str,
    specs: &[MarkerSpec],
    invalid: &impl Fn(String, String) -> ConfigError,
) -> Result<Vec<Marker>, ConfigError> {
    let mut markers: Vec<Marker> = Vec::new();
    for (mi, m) in specs.iter().enumerate() {
        let mfield = format!("{field}.markers[{mi}]");
        let codes = CodeSet::from_name(&m.codes)
            .map_err(|e| invalid(format!("{mfield}.codes"), e.to_string()))?;
        if let Some(prev) = markers
            .iter()
            .position(|p| p.codes == codes && p.id == m.id)
        {
            return Err(invalid(
                format!("{mfield}.id"),
                format!(
                    "{codes}#{} is already {field}.markers[{prev}]: one vehicle cannot carry the same marker twice (its observations could not say which one was seen)",
                    m.id
                ),
            ));
        }
        if (m.id as usize) >= codes.len() && !codes.table().codes.is_empty() {
            return Err(invalid(
                format!("{mfield}.id"),
                format!("ID {} is not in {} (0..{})", m.id, codes, codes.len()),
            ));
        }
        if !(m.side_m > 0.0 && m.side_m < 10.0) {
            return Err(invalid(
                format!("{mfield}.side_m"),
                format!("{} m is not a plausible marker side", m.side_m),
            ));
        }
        check_mount(&m.body_from_marker)
            .map_err(|r| invalid(format!("{mfield}.body_from_marker"), r))?;
        markers.push(Marker {
            codes,
            id: m.id,
            side_m: m.side_m,
            body_from_marker: m.body_from_marker.pose(),
        });
    }
    Ok(markers)
}

impl Fleet {
    /// Load and validate a fleet file.
    pub fn load(path: &Path) -> Result<Fleet, ConfigError> {
        let text = crate::files::read_text_bounded(path, crate::files::MAX_CONFIG_BYTES).map_err(
            |source| ConfigError::Read {
                path: path.to_path_buf(),
                source,
            },
        )?;
        Self::parse(&text, path)
    }

    /// Parse fleet TOML; `path` is used in messages and to resolve calibration files.
    pub fn parse(text: &str, path: &Path) -> Result<Fleet, ConfigError> {
        let file: FleetFile = toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: path.to_path_buf(),
            message: e.to_string().trim_end().to_string(),
        })?;
        let invalid = |field: String, reason: String| ConfigError::Invalid {
            path: path.to_path_buf(),
            field,
            reason,
        };
        Keys::new(&file.fleet).map_err(|e| invalid("fleet".into(), e.to_string()))?;
        if file.vehicles.is_empty() {
            return Err(invalid(
                "vehicles".into(),
                "a fleet needs at least one vehicle".into(),
            ));
        }
        let base = path.parent().unwrap_or(Path::new("."));
        let rigs = parse_rigs(&file.rigs, base, &invalid)?;
        let mut vehicles = Vec::new();
        let mut seen_ids = HashMap::new();
        for (vi, v) in file.vehicles.iter().enumerate() {
            let field = format!("vehicles[{vi}]");
            if let Some(prev) = seen_ids.insert(v.id, vi) {
                return Err(invalid(
                    format!("{field}.id"),
                    format!("vehicle ID {} already used by vehicles[{prev}]", v.id),
                ));
            }
            let h = v.hull;
            if !(h.diameter_m > 0.0
                && h.length_m > 0.0
                && h.diameter_m.is_finite()
                && h.length_m.is_finite())
            {
                return Err(invalid(
                    format!("{field}.hull"),
                    "diameter and length must be positive".into(),
                ));
            }
            let cameras = rigs.get(v.rig.as_str()).cloned().ok_or_else(|| {
                invalid(
                    format!("{field}.rig"),
                    format!(
                        "no rig named {:?} (rigs: {})",
                        v.rig,
                        file.rigs.keys().cloned().collect::<Vec<_>>().join(", ")
                    ),
                )
            })?;
            let markers = parse_markers(&field, &v.markers, &invalid)?;
            vehicles.push(Vehicle {
                id: v.id,
                name: v.name.clone(),
                hull: v.hull,
                markers,
                cameras,
            });
        }
        if !vehicles.iter().any(|v| v.id == file.reference_vehicle) {
            return Err(invalid(
                "reference_vehicle".into(),
                format!("vehicle {} is not in the fleet", file.reference_vehicle),
            ));
        }
        if let Some(r) = file.ros2 {
            if r.domain > 232 {
                return Err(invalid(
                    "ros2.domain".into(),
                    format!("{}: a ROS 2 domain ID is 0 to 232", r.domain),
                ));
            }
        }
        Ok(Fleet {
            name: file.fleet,
            description: file.description,
            reference_vehicle: file.reference_vehicle,
            vehicles,
            ros2: file.ros2,
            source: path.to_path_buf(),
        })
    }

    pub fn vehicle(&self, id: VehicleId) -> Option<&Vehicle> {
        self.vehicles.iter().find(|v| v.id == id)
    }

    pub fn keys(&self) -> Keys {
        // Validated at load time.
        Keys::new(&self.name).expect("fleet name validated in Fleet::parse")
    }

    /// The vehicle carrying marker `id` of `codes`, if exactly one does.
    pub fn marker_owner(&self, codes: CodeSet, id: MarkerId) -> MarkerOwner {
        let mut owners = self
            .vehicles
            .iter()
            .filter(|v| v.markers.iter().any(|m| m.codes == codes && m.id == id))
            .map(|v| v.id);
        match (owners.next(), owners.next()) {
            (None, _) => MarkerOwner::Unknown,
            (Some(v), None) => MarkerOwner::Vehicle(v),
            (Some(_), Some(_)) => MarkerOwner::Ambiguous,
        }
    }

    /// The mounted marker `id` of `codes` on vehicle `vehicle`.
    pub fn marker(&self, vehicle: VehicleId, codes: CodeSet, id: MarkerId) -> Option<&Marker> {
        self.vehicle(vehicle)?
            .markers
            .iter()
            .find(|m| m.codes == codes && m.id == id)
    }

    /// A one-screen human summary (for `shoal config check`).
    pub fn summary(&self) -> String {
        let mut s = format!(
            "fleet {:?}: {} vehicles, reference vehicle {}\n",
            self.name,
            self.vehicles.len(),
            self.reference_vehicle
        );
        for v in &self.vehicles {
            let markers: Vec<String> = v
                .markers
                .iter()
                .map(|m| format!("{}#{} ({:.0} mm)", m.codes, m.id, m.side_m * 1e3))
                .collect();
            let cams: Vec<String> = v
                .cameras
                .iter()
                .map(|c| {
                    let port = c.port.map_or(String::new(), |p| {
                        format!(
                            " behind a port ({:.1} mm air, {:.1} mm glass n {}, water n {})",
                            p.distance_m * 1e3,
                            p.glass_m * 1e3,
                            p.n_glass,
                            p.n_water
                        )
                    });
                    format!("{} {}x{}{port}", c.name, c.model.width, c.model.height)
                })
                .collect();
            s += &format!(
                "  vehicle {:>3} {:<12} hull {:.3} m x {:.2} m  markers [{}]  cameras [{}]\n",
                v.id,
                v.name,
                v.hull.diameter_m,
                v.hull.length_m,
                markers.join(", "),
                cams.join(", ")
            );
        }
        for v in &self.vehicles {
            for m in &v.markers {
                if self.marker_owner(m.codes, m.id) == MarkerOwner::Ambiguous {
                    s += &format!(
                        "  warning: {}#{} is carried by more than one vehicle\n",
                        m.codes, m.id
                    );
                }
            }
        }
        s
    }
}

fn check_mount(m: &MountSpec) -> Result<(), String> {
    if m.xyz_m
        .iter()
        .chain(m.rpy_deg.iter())
        .all(|v| v.is_finite())
    {
        Ok(())
    } else {
        Err("values must be finite".into())
    }
}

fn resolve_camera(c: &CameraSpec, base: &Path) -> Result<CameraModel, String> {
    match (&c.preset, &c.calibration, &c.intrinsics) {
        (Some(p), None, None) => camera_preset(p),
        (None, Some(file), None) => {
            let path = base.join(file);
            let text = crate::files::read_text_bounded(&path, crate::files::MAX_CONFIG_BYTES)
                .map_err(|e| format!("cannot read calibration {}: {e}", path.display()))?;
            parse_calibration_yaml(&text)
                .map_err(|e| format!("calibration {}: {e}", path.display()))
        }
        (None, None, Some(i)) => Ok(CameraModel::from(*i)),
        _ => Err("give exactly one of `preset`, `calibration`, `intrinsics`".into()),
    }
}

/// A camera preset by name.
pub fn camera_preset(name: &str) -> Result<CameraModel, String> {
    match name {
        "vehicle_1440" => Ok(CameraModel::vehicle_1440()),
        "paper_eq3" => Ok(CameraModel::paper_eq3()),
        other => Err(format!(
            "unknown camera preset {other:?} (known: vehicle_1440, paper_eq3)"
        )),
    }
}

/// Why a camera calibration file could not be read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibrationError {
    #[error("missing `{key}`")]
    Missing { key: &'static str },
    #[error("`{key}`: {value:?} is not a whole number of pixels")]
    BadInteger { key: &'static str, value: String },
    #[error("`{key}`: bad number {token:?}")]
    BadNumber { key: String, token: String },
    #[error("`data` outside a matrix")]
    DataOutsideMatrix,
    #[error("unterminated `data: [` list")]
    Unterminated,
    #[error("`{key}` has {got} values, expected {expected}")]
    WrongLength {
        key: &'static str,
        got: usize,
        expected: usize,
    },
    #[error("`camera_matrix` is not an upper-triangular pinhole matrix ({what}); skew and a non-unit K[8] are not supported")]
    NotPinhole { what: String },
    #[error("`distortion_model: {model}` is not supported (supported: plumb_bob, rational_polynomial, equidistant; a calibration in another model must not be read as one of those)")]
    UnsupportedModel { model: String },
    #[error("`distortion_coefficients`: {0}")]
    Coefficients(String),
    #[error("{0}")]
    Implausible(String),
}

/// Read a camera calibration in OpenCV `FileStorage` YAML (`camera_matrix:
/// !!opencv-matrix`, `distortion_coefficients`, `image_width`,
/// `image_height`) or ROS `camera_info` YAML (the same keys with plain
/// `rows/cols/data` maps). Only the fields shoal needs are read; a
/// `distortion_model` other than `plumb_bob` and a camera matrix with skew are
/// refused rather than read as something they are not.
pub fn parse_calibration_yaml(text: &str) -> Result<CameraModel, CalibrationError> {
    let mut scalars: HashMap<String, String> = HashMap::new();
    let mut matrices: HashMap<String, Vec<f64>> = HashMap::new();
    let mut current: Option<String> = None;
    let mut collecting: Option<String> = None;
    for raw in text.lines() {
        let line = raw.split('#').next().unwrap_or("");
        if line.trim().is_empty() || line.starts_with('%') || line.trim() == "---" {
            continue;
        }
        if let Some(buf) = collecting.as_mut() {
            buf.push_str(line);
            if line.contains(']') {
                let key = current.clone().unwrap_or_default();
                let data = parse_list(buf, &key)?;
                matrices.insert(key, data);
                collecting = None;
            }
            continue;
        }
        let indented = line.starts_with(' ') || line.starts_with('\t');
        let Some((k, v)) = line.split_once(':') else {
            continue;
        };
        let (k, v) = (k.trim().to_string(), v.trim());
        if !indented {
            current = Some(k.clone());
            if !v.is_empty() && !v.starts_with("!!") {
                scalars.insert(k, v.to_string());
            }
        } else if k == "data" {
            let key = current.clone().ok_or(CalibrationError::DataOutsideMatrix)?;
            if v.contains(']') {
                let data = parse_list(v, &key)?;
                matrices.insert(key, data);
            } else {
                collecting = Some(v.to_string());
            }
        }
    }
    if collecting.is_some() {
        return Err(CalibrationError::Unterminated);
    }
    let get_u32 = |key: &'static str| -> Result<u32, CalibrationError> {
        let value = scalars.get(key).ok_or(CalibrationError::Missing { key })?;
        value.parse().map_err(|_| CalibrationError::BadInteger {
            key,
            value: value.clone(),
        })
    };
    if let Some(model) = scalars.get("distortion_model") {
        let model = model.trim_matches(|c| c == '"' || c == '\'');
        if !DISTORTION_MODELS.contains(&model) {
            return Err(CalibrationError::UnsupportedModel {
                model: model.to_string(),
            });
        }
    }
    let k = matrices
        .get("camera_matrix")
        .ok_or(CalibrationError::Missing {
            key: "camera_matrix",
        })?;
    if k.len() != 9 {
        return Err(CalibrationError::WrongLength {
            key: "camera_matrix",
            got: k.len(),
            expected: 9,
        });
    }
    if k[1] != 0.0 || k[3] != 0.0 || k[6] != 0.0 || k[7] != 0.0 || k[8] != 1.0 {
        return Err(CalibrationError::NotPinhole {
            what: format!(
                "K[1]={}, K[3]={}, K[6]={}, K[7]={}, K[8]={}",
                k[1], k[3], k[6], k[7], k[8]
            ),
        });
    }
    let d = matrices
        .get("distortion_coefficients")
        .cloned()
        .unwrap_or_default();
    let named = scalars
        .get("distortion_model")
        .map(|m| m.trim_matches(|c| c == '"' || c == '\'').to_string());
    let dist =
        Distortion::from_ros(named.as_deref(), &d).map_err(CalibrationError::Coefficients)?;
    let model = CameraModel {
        width: get_u32("image_width")?,
        height: get_u32("image_height")?,
        fx: k[0],
        fy: k[4],
        cx: k[2],
        cy: k[5],
        distortion: dist,
    };
    match model.problem() {
        Some(p) => Err(CalibrationError::Implausible(p)),
        None => Ok(model),
    }
}

/// Which YAML a calibration is written as.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CalibrationFormat {
    /// OpenCV `cv::FileStorage` (`!!opencv-matrix`), as OpenCV's own
    /// calibration samples write it, plus `distortion_model` (ROS's name,
    /// which OpenCV's reader ignores and shoal's reads).
    OpenCv,
    /// ROS `camera_info` (`camera_calibration_parsers`), with the identity
    /// rectification and the projection `[fx 0 cx 0; 0 fy cy 0; 0 0 1 0]`
    /// of a monocular camera.
    Ros,
}

/// A calibration as YAML that [`parse_calibration_yaml`] (and OpenCV's or
/// ROS's reader) reads back to the same numbers: every value is written in
/// Rust's shortest round-trip form. `name` is ROS's `camera_name`; `rms_px`,
/// when given, is recorded as `avg_reprojection_error`.
pub fn write_calibration_yaml(
    model: &CameraModel,
    format: CalibrationFormat,
    name: &str,
    rms_px: Option<f64>,
) -> String {
    let list = |v: &[f64]| {
        v.iter()
            .map(|x| format!("{x:?}"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let k = [
        model.fx, 0.0, model.cx, 0.0, model.fy, model.cy, 0.0, 0.0, 1.0,
    ];
    let d = model.distortion.coefficients();
    let kind = model.distortion.ros_name();
    let (w, h) = (model.width, model.height);
    let mut out = String::new();
    match format {
        CalibrationFormat::OpenCv => {
            out.push_str(&format!(
                "%YAML:1.0\n---\nimage_width: {w}\nimage_height: {h}\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ {} ]\ndistortion_model: \"{kind}\"\ndistortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: {}\n   dt: d\n   data: [ {} ]\n",
                list(&k),
                d.len(),
                list(d)
            ));
            if let Some(r) = rms_px {
                out.push_str(&format!("avg_reprojection_error: {r:?}\n"));
            }
        }
        CalibrationFormat::Ros => {
            let name: String = name
                .chars()
                .map(|c| {
                    if c.is_ascii_alphanumeric() || c == '_' {
                        c
                    } else {
                        '_'
                    }
                })
                .collect();
            let p = [
                model.fx, 0.0, model.cx, 0.0, 0.0, model.fy, model.cy, 0.0, 0.0, 0.0, 1.0, 0.0,
            ];
            out.push_str(&format!(
                "image_width: {w}\nimage_height: {h}\ncamera_name: {name}\ncamera_matrix:\n  rows: 3\n  cols: 3\n  data: [{}]\ndistortion_model: {kind}\ndistortion_coefficients:\n  rows: 1\n  cols: {}\n  data: [{}]\nrectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]\nprojection_matrix:\n  rows: 3\n  cols: 4\n  data: [{}]\n",
                list(&k),
                d.len(),
                list(d),
                list(&p)
            ));
        }
    }
    out
}

fn parse_list(s: &str, key: &str) -> Result<Vec<f64>, CalibrationError> {
    let inner = s
        .trim()
        .trim_start_matches('[')
        .split(']')
        .next()
        .unwrap_or("");
    inner
        .split(',')
        .map(str::trim)
        .filter(|t| !t.is_empty())
        .map(|t| {
            t.parse::<f64>().map_err(|_| CalibrationError::BadNumber {
                key: key.to_string(),
                token: t.to_string(),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const MINI: &str = r#"
fleet = "mini"
reference_vehicle = 1
[rigs.one]
cameras = [ { name = "fwd", preset = "vehicle_1440", body_from_camera = { xyz_m = [0.5, 0, 0], rpy_deg = [90, 0, 90] } } ]
[[vehicles]]
id = 1
name = "a"
rig = "one"
hull = { diameter_m = 0.125, length_m = 1.5 }
[[vehicles]]
id = 2
name = "b"
rig = "one"
hull = { diameter_m = 0.125, length_m = 1.5 }
markers = [ { codes = "shoal", id = 7, side_m = 0.1, body_from_marker = { xyz_m = [0, 0.07, 0], rpy_deg = [-90, 0, 0] } } ]
"#;

    #[test]
    fn loads_a_minimal_fleet() {
        let f = Fleet::parse(MINI, Path::new("mini.toml")).unwrap();
        assert_eq!(f.vehicles.len(), 2);
        assert_eq!(f.marker_owner(CodeSet::Shoal, 7), MarkerOwner::Vehicle(2));
        assert_eq!(f.marker_owner(CodeSet::Shoal, 8), MarkerOwner::Unknown);
        assert_eq!(f.vehicle(1).unwrap().cameras[0].model.width, 1440);
    }

    #[test]
    fn a_calibration_sigma_is_read_and_bad_ones_are_named() {
        let with = |sigma: &str| {
            MINI.replace(
                "rpy_deg = [90, 0, 90] } }",
                &format!("rpy_deg = [90, 0, 90] }}, calibration_sigma = {{ {sigma} }} }}"),
            )
        };
        let f = Fleet::parse(
            &with("focal_rel = 0.002, principal_px = 1.5"),
            Path::new("m.toml"),
        )
        .unwrap();
        assert_eq!(
            f.vehicle(1).unwrap().cameras[0].calibration_sigma,
            Some(CalibrationSigma {
                focal_rel: 0.002,
                principal_px: 1.5,
                k1: 0.0
            })
        );
        assert_eq!(
            Fleet::parse(MINI, Path::new("m.toml")).unwrap().vehicles[0].cameras[0]
                .calibration_sigma,
            None
        );
        let e = Fleet::parse(
            &with("focal_rel = -0.002, principal_px = 1.5"),
            Path::new("m.toml"),
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("rigs.one.cameras[0].calibration_sigma") && e.contains("non-negative"),
            "{e}"
        );
        let e = Fleet::parse(&with("focal_rel = 0.002"), Path::new("m.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("principal_px"), "{e}");
    }

    #[test]
    fn a_port_is_read_in_millimetres_with_default_indices_and_bad_ones_are_named() {
        let with = |port: &str| {
            MINI.replace(
                "rpy_deg = [90, 0, 90] } }",
                &format!("rpy_deg = [90, 0, 90] }}, port = {{ {port} }} }}"),
            )
        };
        let f = Fleet::parse(&with("distance_mm = 10, glass_mm = 8"), Path::new("m.toml")).unwrap();
        let port = f.vehicle(1).unwrap().cameras[0].port.unwrap();
        assert!(
            f.summary().contains(
                "fwd 1440x1080 behind a port (10.0 mm air, 8.0 mm glass n 1.49, water n 1.34)"
            ),
            "{}",
            f.summary()
        );
        assert_eq!(
            port,
            FlatPort {
                distance_m: 0.010,
                glass_m: 0.008,
                n_glass: 1.49,
                n_water: 1.34
            }
        );
        assert_eq!(
            Fleet::parse(MINI, Path::new("m.toml")).unwrap().vehicles[0].cameras[0].port,
            None
        );
        for (bad, says) in [
            ("distance_mm = -1, glass_mm = 8", "port distance -1.0 mm"),
            (
                "distance_mm = 10, glass_mm = nan",
                "port glass is not finite",
            ),
            (
                "distance_mm = 10, glass_mm = 8, n_glass = 0.5",
                "n_glass 0.5",
            ),
            (
                "distance_mm = 10, glass_mm = 8, n_water = 0.99",
                "n_water 0.99",
            ),
        ] {
            let e = Fleet::parse(&with(bad), Path::new("m.toml"))
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("rigs.one.cameras[0].port") && e.contains(says),
                "{bad}: {e}"
            );
        }
        for (bad, says) in [
            ("distance_mm = 10", "glass_mm"),
            ("distance_mm = 10, glass_mm = 8, n_air = 1", "n_air"),
        ] {
            let e = Fleet::parse(&with(bad), Path::new("m.toml"))
                .unwrap_err()
                .to_string();
            assert!(e.contains(says), "{bad}: {e}");
        }
    }

    #[test]
    fn a_ros2_table_turns_ros2_on_and_its_domain_is_checked() {
        assert_eq!(Fleet::parse(MINI, Path::new("m.toml")).unwrap().ros2, None);
        let on = format!("{MINI}\n[ros2]\ndomain = 5\n");
        let f = Fleet::parse(&on, Path::new("m.toml")).unwrap();
        assert_eq!(f.ros2, Some(Ros2Settings { domain: 5 }));
        let default = format!("{MINI}\n[ros2]\n");
        let f = Fleet::parse(&default, Path::new("m.toml")).unwrap();
        assert_eq!(f.ros2, Some(Ros2Settings { domain: 0 }));
        for (bad, field) in [("domain = 233", "ros2.domain"), ("topic = 1", "topic")] {
            let text = format!("{MINI}\n[ros2]\n{bad}\n");
            let e = Fleet::parse(&text, Path::new("m.toml"))
                .unwrap_err()
                .to_string();
            assert!(e.contains(field), "{bad}: {e}");
        }
    }

    #[test]
    fn unknown_field_is_named() {
        let bad = MINI.replace("name = \"a\"", "name = \"a\"\nspeed = 3");
        let e = Fleet::parse(&bad, Path::new("mini.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("mini.toml") && e.contains("speed"), "{e}");
    }

    #[test]
    fn duplicate_vehicle_and_bad_rig_are_named() {
        let dup = MINI.replace("id = 2", "id = 1");
        let e = Fleet::parse(&dup, Path::new("f.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("vehicles[1].id"), "{e}");
        let rig = MINI.replace("rig = \"one\"\nhull", "rig = \"two\"\nhull");
        let e = Fleet::parse(&rig, Path::new("f.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("rig") && e.contains("two"), "{e}");
        let codes = MINI.replace("codes = \"shoal\"", "codes = \"qr\"");
        let e = Fleet::parse(&codes, Path::new("f.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("markers[0].codes"), "{e}");
    }

    /// Issue #22: extra array elements were dropped (even wrong-typed ones),
    /// rational-model coefficients silently cut to five, and one vehicle
    /// could list the same marker twice.
    #[test]
    fn arrays_have_their_length_and_markers_are_listed_once() {
        let parse = |text: &str| Fleet::parse(text, Path::new("f.toml")).map(|_| ());
        assert!(parse(MINI).is_ok());
        for (from, to) in [
            ("xyz_m = [0.5, 0, 0]", "xyz_m = [0.5, 0, 0, 7]"),
            ("xyz_m = [0.5, 0, 0]", "xyz_m = [0.5, 0, 0, \"x\"]"),
            ("xyz_m = [0.5, 0, 0]", "xyz_m = [0.5, 0]"),
            ("rpy_deg = [90, 0, 90]", "rpy_deg = [90, 0, 90, 0]"),
            ("rpy_deg = [-90, 0, 0]", "rpy_deg = [-90, 0]"),
        ] {
            assert!(MINI.contains(from), "{from}");
            let e = parse(&MINI.replacen(from, to, 1)).unwrap_err().to_string();
            assert!(e.contains("f.toml"), "{to}: {e}");
            assert!(e.contains("3") || e.contains("invalid type"), "{to}: {e}");
        }
        let inline = |d: &str| {
            MINI.replace(
                "preset = \"vehicle_1440\"",
                &format!("intrinsics = {{ width = 1440, height = 1080, fx = 1250.0, fy = 1250.0, cx = 719.5, cy = 539.5, distortion = {d} }}"),
            )
        };
        assert!(parse(&inline("[-0.05, 0.01, 0, 0, 0]")).is_ok());
        assert!(parse(&inline("[-0.05, 0.01, 0, 0]")).is_ok());
        assert!(parse(&inline("[-0.05, 0.01, 0, 0, 0, 0, 0, 0]")).is_ok());
        let e = parse(&inline("[-0.05, 0.01, 0, 0, 0, 0.2, 0, 0]"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("coefficient 6 is 0.2"), "{e}");
        assert!(parse(&inline("[-0.05, 0.01]")).is_err());
        // A distortion that folds inside the frame is no calibration.
        let e = parse(&inline("[-2.0, 0, 0, 0, 0]"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("folds back"), "{e}");

        let twice = MINI.replace(
            "markers = [ { codes = \"shoal\", id = 7, side_m = 0.1, body_from_marker = { xyz_m = [0, 0.07, 0], rpy_deg = [-90, 0, 0] } } ]",
            "markers = [ { codes = \"shoal\", id = 7, side_m = 0.1, body_from_marker = { xyz_m = [0, 0.07, 0], rpy_deg = [-90, 0, 0] } }, { codes = \"shoal\", id = 7, side_m = 0.1, body_from_marker = { xyz_m = [0, -0.07, 0], rpy_deg = [90, 0, 0] } } ]",
        );
        assert_ne!(twice, MINI);
        let e = parse(&twice).unwrap_err().to_string();
        assert!(
            e.contains("vehicles[1].markers[1].id") && e.contains("markers[0]"),
            "{e}"
        );
    }

    #[test]
    fn calibration_coefficients_beyond_five_must_be_zero_and_must_not_fold() {
        let ros = |d: &str| {
            format!("image_width: 640\nimage_height: 480\ncamera_matrix:\n  rows: 3\n  cols: 3\n  data: [500, 0, 320, 0, 500, 240, 0, 0, 1]\ndistortion_model: plumb_bob\ndistortion_coefficients:\n  data: [{d}]\n")
        };
        assert!(parse_calibration_yaml(&ros("0.1, 0, 0, 0, 0, 0, 0, 0")).is_ok());
        assert!(matches!(
            parse_calibration_yaml(&ros("0.1, 0, 0, 0, 0, 0.3, 0, 0")),
            Err(CalibrationError::Coefficients(_))
        ));
        assert!(matches!(
            parse_calibration_yaml(&ros("-3.0, 0, 0, 0, 0")),
            Err(CalibrationError::Implausible(p)) if p.contains("folds back")
        ));
    }

    #[test]
    fn reads_opencv_and_ros_calibrations() {
        let opencv = "%YAML:1.0\n---\nimage_width: 1440\nimage_height: 1080\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1250., 0., 719.5, 0.,\n       1251., 539.5, 0., 0., 1. ]\ndistortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ -0.1, 0.02, 0., 0., 0. ]\n";
        let m = parse_calibration_yaml(opencv).unwrap();
        assert_eq!((m.width, m.fx, m.fy, m.cy), (1440, 1250.0, 1251.0, 539.5));
        assert_eq!(m.distortion.coefficients()[0], -0.1);
        let ros = "image_width: 640\nimage_height: 480\ncamera_name: cam\ncamera_matrix:\n  rows: 3\n  cols: 3\n  data: [500, 0, 320, 0, 500, 240, 0, 0, 1]\ndistortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [0.1, 0, 0, 0, 0]\n";
        let m = parse_calibration_yaml(ros).unwrap();
        assert_eq!((m.width, m.cx), (640, 320.0));
        assert_eq!(
            parse_calibration_yaml("image_width: 3\n"),
            Err(CalibrationError::Missing {
                key: "camera_matrix"
            })
        );
        // A fisheye calibration is read as one (5 coefficients, the fifth 0).
        let fisheye = ros.replace("plumb_bob", "equidistant");
        let f = parse_calibration_yaml(&fisheye).unwrap();
        assert_eq!(f.distortion, Distortion::Equidistant([0.1, 0.0, 0.0, 0.0]));
        let rational = ros.replace("plumb_bob", "rational_polynomial").replace(
            "cols: 5\n  data: [0.1, 0, 0, 0, 0]",
            "cols: 8\n  data: [0.1, 0, 0, 0, 0, 0.2, 0, 0]",
        );
        let r = parse_calibration_yaml(&rational).unwrap();
        assert_eq!(
            r.distortion,
            Distortion::Rational([0.1, 0.0, 0.0, 0.0, 0.0, 0.2, 0.0, 0.0])
        );
        // A model shoal does not know is refused, never read as another.
        let unknown = ros.replace("plumb_bob", "kannala_brandt");
        assert!(matches!(
            parse_calibration_yaml(&unknown),
            Err(CalibrationError::UnsupportedModel { model }) if model == "kannala_brandt"
        ));
        // A plumb-bob file with rational terms is refused, not truncated.
        let extra = ros.replace(
            "cols: 5\n  data: [0.1, 0, 0, 0, 0]",
            "cols: 8\n  data: [0.1, 0, 0, 0, 0, 0.2, 0, 0]",
        );
        assert!(matches!(
            parse_calibration_yaml(&extra),
            Err(CalibrationError::Coefficients(e)) if e.contains("coefficient 6")
        ));
        // Our writer's files read back to the same numbers, in both formats and every model.
        for distortion in [
            Distortion::PlumbBob([-0.1, 0.02, 0.001, -0.002, 0.003]),
            Distortion::Rational([0.5, -0.1, 0.001, 0.0, 0.01, 0.6, 0.02, 0.001]),
            Distortion::Equidistant([-0.01, 0.004, -0.002, 0.0005]),
        ] {
            let cam = CameraModel {
                width: 1280,
                height: 960,
                fx: 1200.123456789,
                fy: 1201.987654321,
                cx: 639.25,
                cy: 481.0625,
                distortion,
            };
            for format in [CalibrationFormat::OpenCv, CalibrationFormat::Ros] {
                let text = write_calibration_yaml(&cam, format, "port cam", Some(0.25));
                assert_eq!(
                    parse_calibration_yaml(&text),
                    Ok(cam),
                    "{format:?}:\n{text}"
                );
            }
        }
        let skewed = ros.replace("500, 0, 320", "500, 0.5, 320");
        assert!(matches!(
            parse_calibration_yaml(&skewed),
            Err(CalibrationError::NotPinhole { .. })
        ));
    }
}
