//! Errors of the simulator library (renderer, water model, swarm world).

use std::path::PathBuf;

/// What went wrong in the simulator; every variant names the offending input.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("{path}: cannot read water presets: {source}")]
    WaterRead {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: water presets: {message}")]
    WaterParse { path: PathBuf, message: String },
    #[error("water parameter `{field}` = {value}: {reason}")]
    WaterInvalid {
        field: &'static str,
        value: f64,
        reason: &'static str,
    },
    #[error("attenuation coefficient {c_per_m} /m is outside the presets' range {min}..={max} /m")]
    WaterOutOfRange { c_per_m: f64, min: f64, max: f64 },
    #[error("formation spacing {0} m must be positive and finite")]
    Spacing(f64),
    #[error("camera model unusable: {0}")]
    Camera(String),
    #[error("{what} pose is not finite")]
    NonFinitePose { what: String },
    #[error("marker {codes}#{id}: {reason}")]
    Marker {
        codes: shoal_proto::CodeSet,
        id: shoal_proto::MarkerId,
        reason: String,
    },
    #[error("hull of vehicle {vehicle}: diameter {diameter_m} m and length {length_m} m must be positive and finite")]
    Hull {
        vehicle: shoal_proto::VehicleId,
        diameter_m: f64,
        length_m: f64,
    },
    #[error("vehicle {vehicle} is not in the {context}")]
    UnknownVehicle {
        vehicle: shoal_proto::VehicleId,
        context: &'static str,
    },
    #[error("vehicle {vehicle} has no camera {camera} (it has {count})")]
    UnknownCamera {
        vehicle: shoal_proto::VehicleId,
        camera: u8,
        count: usize,
    },
    #[error("{field} = {value}: {reason}")]
    InvalidArgument {
        field: &'static str,
        value: f64,
        reason: &'static str,
    },
    #[error("{path}: cannot read the camera profile: {source}")]
    ProfileRead {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: camera profile: {message}")]
    ProfileParse { path: PathBuf, message: String },
    #[error("camera profile: {effect}.{field} = {value}: {reason}")]
    ProfileInvalid {
        effect: &'static str,
        field: &'static str,
        value: f64,
        reason: String,
    },
    #[error("unknown camera profile {name:?}; expected ideal or realistic")]
    UnknownProfile { name: String },
    #[error("unknown camera effect {name:?}; known: {known}")]
    UnknownEffect { name: String, known: String },
    #[error("{stage}: {message}")]
    Effect {
        stage: &'static str,
        message: String,
    },
    #[error("cannot write {path}: {message}")]
    ImageWrite { path: PathBuf, message: String },
}
