//! The messages shoal's processes exchange. Each implements [`WireMessage`]
//! and travels inside the versioned envelope of [`crate::codec`].
//!
//! Vehicle IDs are `u32`; a vehicle is usually numbered after the marker it
//! carries (the paper's 10, 15, 17). Times are nanoseconds of the injected
//! clock (`stamp_ns`): simulation time in the simulator, the capture clock on
//! a vehicle.

use crate::camera::CameraModel;
use crate::codec::DecodeError;
use crate::geometry::{covariance_problem, pose_is_finite, Cov6, Pose};
use crate::marker::{CodeSet, MarkerId};
use serde::{Deserialize, Serialize};

pub type VehicleId = u32;

/// Message kinds, as carried in the envelope header (`u16`, never reused).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[repr(u16)]
pub enum MessageKind {
    Observation = 1,
    FleetMap = 2,
    CameraFrame = 3,
    SimTruth = 4,
    NodeStatus = 5,
    VehicleCommand = 6,
    NavState = 7,
    LinkPacket = 8,
}

impl MessageKind {
    pub const ALL: [MessageKind; 8] = [
        MessageKind::Observation,
        MessageKind::FleetMap,
        MessageKind::CameraFrame,
        MessageKind::SimTruth,
        MessageKind::NodeStatus,
        MessageKind::VehicleCommand,
        MessageKind::NavState,
        MessageKind::LinkPacket,
    ];

    pub fn from_u16(v: u16) -> Option<MessageKind> {
        Self::ALL.iter().copied().find(|k| *k as u16 == v)
    }

    /// Schema name, as written in MCAP channel metadata.
    pub fn schema_name(self) -> &'static str {
        match self {
            MessageKind::Observation => "shoal.Observation",
            MessageKind::FleetMap => "shoal.FleetMap",
            MessageKind::CameraFrame => "shoal.CameraFrame",
            MessageKind::SimTruth => "shoal.SimTruth",
            MessageKind::NodeStatus => "shoal.NodeStatus",
            MessageKind::VehicleCommand => "shoal.VehicleCommand",
            MessageKind::NavState => "shoal.NavState",
            MessageKind::LinkPacket => "shoal.LinkPacket",
        }
    }
}

/// A message type that can cross the wire.
pub trait WireMessage: Serialize + for<'de> Deserialize<'de> {
    const KIND: MessageKind;
    /// Semantic checks beyond what decoding proves (finite poses, sizes that
    /// agree); `Err` names the field and the reason.
    fn validate(&self) -> Result<(), (&'static str, String)> {
        Ok(())
    }
    /// Decode a payload of an older schema `version` (one of
    /// [`crate::codec::OLDEST_READABLE_VERSION`] up to today's) whose layout
    /// differs from today's; `None`: the layout has not changed since
    /// `version`, and the payload decodes as today's.
    fn decode_older(version: u16, payload: &[u8]) -> Option<Result<Self, DecodeError>> {
        let _ = (version, payload);
        None
    }
}

/// Image-quality figures the node measured on the frame a detection came from.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct ImageQuality {
    /// Michelson contrast between the marker's black and white cells (0..1).
    pub marker_contrast: f32,
    /// Contrast-to-noise ratio between black and white cells.
    pub cnr: f32,
    /// Estimated backscatter (veiling light) level, 0..1 of full scale.
    pub backscatter: f32,
    /// Water attenuation coefficient the restoration estimated or was told, per metre.
    pub estimated_c_per_m: f32,
}

/// The other solution of a planar PnP (the "flip" of IPPE).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseHypothesis {
    pub observer_from_target: Pose,
    pub covariance: Cov6,
    pub reprojection_rms_px: f64,
}

/// One vehicle's marker-derived estimate of another vehicle's pose.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Observation {
    /// The vehicle whose camera saw the marker.
    pub observer: VehicleId,
    /// Camera index on the observer (order of the fleet file).
    pub camera: u8,
    /// Code set and ID of the marker read.
    pub codes: CodeSet,
    pub target_marker: MarkerId,
    /// The vehicle the fleet file says carries that marker (`None`: unknown ID).
    pub target_vehicle: Option<VehicleId>,
    /// Capture time of the frame.
    pub stamp_ns: u64,
    /// Frame sequence number of that camera.
    pub frame_seq: u64,
    /// Best hypothesis: target body in observer body frame (FRD).
    pub observer_from_target: Pose,
    /// Covariance of `observer_from_target` (see [`crate::geometry`]).
    pub covariance: Cov6,
    pub reprojection_rms_px: f64,
    /// The planar flip, when PnP found a second minimum.
    pub alternative: Option<PoseHypothesis>,
    /// Corners used by PnP (12 for a fully visible enhanced marker).
    pub corner_count: u8,
    /// Refined corner positions in the image (pixels), for annotation.
    pub corners_px: Vec<[f32; 2]>,
    pub quality: ImageQuality,
    /// True when this pose is the tracker's prediction bridging an occlusion, not a measurement.
    pub predicted: bool,
}

/// What identifies one detection across observations and edge reports:
/// capture stamp, observer, camera, frame number, marker ID.
pub type DetectionKey = (u64, VehicleId, u8, u64, MarkerId);

impl Observation {
    /// This detection's [`DetectionKey`] (its edge reports carry the same).
    pub fn detection_key(&self) -> DetectionKey {
        (
            self.stamp_ns,
            self.observer,
            self.camera,
            self.frame_seq,
            self.target_marker,
        )
    }
}

impl WireMessage for Observation {
    const KIND: MessageKind = MessageKind::Observation;
    fn validate(&self) -> Result<(), (&'static str, String)> {
        if !pose_is_finite(&self.observer_from_target) {
            return Err(("observer_from_target", "pose is not finite".into()));
        }
        if let Some(p) = covariance_problem(&self.covariance, 1e3) {
            return Err(("covariance", p.into()));
        }
        if let Some(alt) = &self.alternative {
            if !pose_is_finite(&alt.observer_from_target) {
                return Err((
                    "alternative.observer_from_target",
                    "pose is not finite".into(),
                ));
            }
            if let Some(p) = covariance_problem(&alt.covariance, 1e3) {
                return Err(("alternative.covariance", p.into()));
            }
        }
        if !self.reprojection_rms_px.is_finite() || self.reprojection_rms_px < 0.0 {
            return Err((
                "reprojection_rms_px",
                "must be finite and non-negative".into(),
            ));
        }
        if self.corners_px.len() > 64 {
            return Err((
                "corners_px",
                format!("{} corners is too many", self.corners_px.len()),
            ));
        }
        Ok(())
    }
}

/// Liveness of a vehicle in the fleet map.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum VehicleState {
    /// Localized from fresh observations.
    Live,
    /// Its liveliness token disappeared or its data is older than the window.
    Stale,
    /// In the fleet but not connected to the reference by any accepted edge.
    Unobserved,
    /// Unseen by any camera for a while but carried forward from its last
    /// fused pose by its own and the reference's odometry (nav velocity and
    /// attitude); the covariance grows with the distance dead-reckoned.
    Predicted,
}

/// One vehicle in the fused map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VehicleEstimate {
    pub vehicle: VehicleId,
    pub state: VehicleState,
    /// Pose relative to the map's reference vehicle (identity for the reference).
    pub reference_from_vehicle: Pose,
    pub covariance: Cov6,
    /// Capture time of the newest observation involving this vehicle (0: never).
    pub last_seen_ns: u64,
}

/// Why fusion rejected an observation.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum RejectReason {
    /// The marker ID belongs to no vehicle of the fleet.
    UnknownMarker,
    /// The marker ID is claimed by more than one vehicle in the fleet file.
    AmbiguousMarker,
    /// The observation names the observer as its own target.
    SelfObservation,
    /// Older than the sliding window, or from the future beyond the skew bound.
    Stale,
    ClockSkew,
    /// The claimed observer is not the vehicle whose key it arrived on.
    ObserverMismatch,
    /// Mahalanobis distance to the fused estimate above the chi-square gate.
    ChiSquare,
    /// The planar-flip hypothesis lost against its twin.
    FlippedHypothesis,
    /// Inconsistent with the largest mutually consistent set (pairwise / cycle check).
    Inconsistent,
    /// Pose or covariance unusable.
    Invalid,
    /// Same observer, camera, frame and marker already seen.
    Duplicate,
    /// An older frame of a track (same observer, camera and marker) that no
    /// longer agrees with the track's newest frame: the vehicles have moved
    /// since, so it describes a past relative pose, not a wrong one.
    Superseded,
    /// The hypothesis implies a tilt of the target that its own IMU, seen
    /// through the observer's, contradicts (the planar-flip twin, mostly):
    /// see `shoal_proto::nav`.
    Gravity,
    /// The hypothesis puts the target at a depth, relative to the observer,
    /// that their pressure sensors contradict (a misread ID, mostly).
    Depth,
    /// The hypothesis implies a heading of the target, relative to the
    /// observer, that their compasses contradict (the twin turned about the
    /// vertical, which gravity cannot see).
    Heading,
}

/// Verdict on one edge (an observation between two vehicles).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EdgeReport {
    pub observer: VehicleId,
    pub camera: u8,
    pub target_marker: MarkerId,
    pub target_vehicle: Option<VehicleId>,
    pub stamp_ns: u64,
    pub frame_seq: u64,
    /// `None` when accepted.
    pub rejected: Option<RejectReason>,
    /// Mahalanobis distance squared against the fused solution (NaN when not computed).
    pub chi2: f64,
}

impl EdgeReport {
    /// The [`DetectionKey`] of the observation this verdict is about.
    pub fn detection_key(&self) -> DetectionKey {
        (
            self.stamp_ns,
            self.observer,
            self.camera,
            self.frame_seq,
            self.target_marker,
        )
    }
}

/// The fused, fleet-wide relative map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FleetMap {
    pub fleet: String,
    /// Which fusion instance produced it (`"central"` or a vehicle's ID in decentralized mode).
    pub producer: String,
    pub seq: u64,
    pub stamp_ns: u64,
    pub reference: VehicleId,
    pub vehicles: Vec<VehicleEstimate>,
    pub edges: Vec<EdgeReport>,
    /// Wall time the solve took.
    pub solve_time_us: u64,
}

impl FleetMap {
    /// Capture time of the newest accepted observation: the instant the map's
    /// freshest information describes (its own stamp when nothing was accepted).
    pub fn valid_at_ns(&self) -> u64 {
        self.edges
            .iter()
            .filter(|e| e.rejected.is_none())
            .map(|e| e.stamp_ns)
            .max()
            .unwrap_or(self.stamp_ns)
    }
}

impl WireMessage for FleetMap {
    const KIND: MessageKind = MessageKind::FleetMap;
    fn validate(&self) -> Result<(), (&'static str, String)> {
        for v in &self.vehicles {
            if !pose_is_finite(&v.reference_from_vehicle) {
                return Err((
                    "vehicles.reference_from_vehicle",
                    format!("vehicle {} pose is not finite", v.vehicle),
                ));
            }
            if !v.covariance.iter().all(|x| x.is_finite()) {
                return Err((
                    "vehicles.covariance",
                    format!("vehicle {} covariance is not finite", v.vehicle),
                ));
            }
        }
        Ok(())
    }
}

/// Pixel layout of a camera frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum PixelFormat {
    /// 8-bit grey, one byte per pixel.
    Mono8,
    /// 8-bit RGB, three bytes per pixel.
    Rgb8,
}

impl PixelFormat {
    pub fn channels(self) -> usize {
        match self {
            PixelFormat::Mono8 => 1,
            PixelFormat::Rgb8 => 3,
        }
    }
}

/// Calibration and mounting of the camera a frame came from.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CameraInfo {
    pub model: CameraModel,
    pub body_from_camera: Pose,
}

/// One 8-bit image from a vehicle camera (or the simulator standing in for it).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraFrame {
    pub vehicle: VehicleId,
    pub camera: u8,
    pub seq: u64,
    pub stamp_ns: u64,
    pub info: CameraInfo,
    pub format: PixelFormat,
    /// Row-major pixels, `width * height * channels` bytes, no padding.
    pub data: Vec<u8>,
}

impl WireMessage for CameraFrame {
    const KIND: MessageKind = MessageKind::CameraFrame;
    fn decode_older(version: u16, payload: &[u8]) -> Option<Result<Self, DecodeError>> {
        (version == 4).then(|| {
            crate::codec::decode_payload::<legacy::CameraFrameV4>(Self::KIND, payload)
                .map(CameraFrame::from)
        })
    }
    fn validate(&self) -> Result<(), (&'static str, String)> {
        if let Some(p) = self.info.model.problem() {
            return Err(("info.model", p));
        }
        let want = self.info.model.width as usize
            * self.info.model.height as usize
            * self.format.channels();
        if self.data.len() != want {
            return Err((
                "data",
                format!(
                    "{} bytes for a {}x{} {:?} frame (expected {want})",
                    self.data.len(),
                    self.info.model.width,
                    self.info.model.height,
                    self.format
                ),
            ));
        }
        if !pose_is_finite(&self.info.body_from_camera) {
            return Err(("info.body_from_camera", "pose is not finite".into()));
        }
        Ok(())
    }
}

/// Where a marker is visible in one simulated camera frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VisibleMarker {
    pub observer: VehicleId,
    pub camera: u8,
    pub frame_seq: u64,
    pub codes: CodeSet,
    pub marker: MarkerId,
    pub target_vehicle: VehicleId,
    /// Projected corners (pixels), in [`CodeSet::corners_3d`] order.
    pub corners_px: Vec<[f64; 2]>,
    /// Fraction of the marker's face not occluded (0..1).
    pub visible_fraction: f32,
    pub range_m: f64,
}

/// Ground truth of a vehicle in the simulated world.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct VehicleTruth {
    pub vehicle: VehicleId,
    /// World frame is NED.
    pub world_from_body: Pose,
    /// Body-frame linear velocity (m/s).
    pub velocity_body: [f64; 3],
}

/// The simulator's ground truth at one tick.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SimTruth {
    pub stamp_ns: u64,
    pub tick: u64,
    pub water_c_per_m: f64,
    pub vehicles: Vec<VehicleTruth>,
    pub visible: Vec<VisibleMarker>,
}

impl WireMessage for SimTruth {
    const KIND: MessageKind = MessageKind::SimTruth;
    fn validate(&self) -> Result<(), (&'static str, String)> {
        if let Some(v) = self
            .vehicles
            .iter()
            .find(|v| !pose_is_finite(&v.world_from_body))
        {
            return Err((
                "vehicles.world_from_body",
                format!("vehicle {} pose is not finite", v.vehicle),
            ));
        }
        Ok(())
    }
}

/// Per-camera counters and timings of a node.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct CameraStatus {
    pub camera: u8,
    pub name: String,
    pub frames_in: u64,
    /// Dropped because the stage's queue was full (oldest frame dropped).
    pub frames_dropped: u64,
    /// Frames rejected as malformed (wrong size, format, undecodable).
    pub frames_invalid: u64,
    pub detections: u64,
    /// Frames per second over the last status period.
    pub frame_rate_hz: f32,
    /// Mean stage latencies over the last status period, milliseconds.
    pub restore_ms: f32,
    pub detect_ms: f32,
    pub pose_ms: f32,
    /// Detections since start by the corner fit that gave their corners, by
    /// the names `shoal detect` prints as `corner_fit` (`pattern`,
    /// `raw_sides`, …); fits that never ran are left out.
    pub corner_fits: Vec<(String, u64)>,
    /// Where the capture stamps of the camera's newest frame came from.
    pub stamp_source: StampSource,
    /// Frames the source's own timing shows were never delivered, since
    /// start: a gap of k frame periods between successive capture stamps
    /// counts k − 1 (lost in the driver, the pipeline or the network, before
    /// the node's queue; `frames_dropped` counts the queue's own drops).
    pub frames_missed: u64,
    /// Times a live source was reopened after its stream ended or failed.
    pub reconnects: u64,
}

/// Where a camera's capture stamps come from (`docs/time.md`). Every stamp
/// is on the capturing machine's wall clock (UNIX time) except `Playback`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum StampSource {
    /// No frame yet (or a status from before schema version 5).
    #[default]
    Unknown,
    /// The stamp the frame arrived with: a `CameraFrame` on Zenoh, a ROS 2
    /// image header; its sender chose the clock.
    Sender,
    /// The camera driver's buffer time (V4L2: `CLOCK_MONOTONIC`, moved to the
    /// wall clock by the offset between the two clocks when it is read).
    Driver,
    /// The GStreamer pipeline's buffer time, placed on the wall clock at the
    /// earliest arrival seen (so a stamp is never after its frame's arrival).
    Pipeline,
    /// The wall clock when the node read the frame: the source gave no time
    /// of its own, or gave one too far from the arrival to be believed.
    Arrival,
    /// The frame's place in a file or folder, from 0 (a video's own time,
    /// or frame number / rate for an image folder): not a wall clock.
    Playback,
}

impl StampSource {
    /// The name the status and the docs use.
    pub fn name(self) -> &'static str {
        match self {
            StampSource::Unknown => "unknown",
            StampSource::Sender => "sender",
            StampSource::Driver => "driver",
            StampSource::Pipeline => "pipeline",
            StampSource::Arrival => "arrival",
            StampSource::Playback => "playback",
        }
    }
}

/// What the kernel says of the node's clock discipline (`adjtimex(2)`), as
/// NTP or PTP daemons maintain it (`docs/time.md`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct ClockSync {
    /// The kernel considers the clock synchronised (`STA_UNSYNC` clear and
    /// the clock state not `TIME_ERROR`).
    pub synchronised: bool,
    /// Offset the discipline is still correcting (the daemon's last measured
    /// offset, being slewed away), nanoseconds.
    pub offset_ns: i64,
    /// Estimated error of the clock, nanoseconds (`esterror`).
    pub est_error_ns: u64,
    /// Maximum error of the clock, nanoseconds (`maxerror`: grows by 500 ppm
    /// of elapsed time until the daemon next sets it).
    pub max_error_ns: u64,
}

/// Periodic health report of a vehicle node.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct NodeStatus {
    pub vehicle: VehicleId,
    pub stamp_ns: u64,
    pub uptime_s: f64,
    pub cameras: Vec<CameraStatus>,
    /// Observations published since start.
    pub observations_sent: u64,
    /// Messages received that failed decoding or validation.
    pub messages_rejected: u64,
    /// The node's clock discipline when the status was made (None: not
    /// known, e.g. not Linux, or a status from before schema version 5).
    pub clock: Option<ClockSync>,
}

impl WireMessage for NodeStatus {
    const KIND: MessageKind = MessageKind::NodeStatus;
    fn decode_older(version: u16, payload: &[u8]) -> Option<Result<Self, DecodeError>> {
        (version == 4).then(|| {
            crate::codec::decode_payload::<legacy::NodeStatusV4>(Self::KIND, payload)
                .map(NodeStatus::from)
        })
    }
}

/// Layouts of schema versions before today's that are still decoded, so
/// older logs stay readable (`docs/wire.md`).
mod legacy {
    use super::{CameraFrame, CameraInfo, CameraStatus, NodeStatus, PixelFormat, VehicleId};
    use crate::camera::{CameraModel, Distortion};
    use crate::geometry::Pose;
    use serde::Deserialize;

    /// `CameraModel` of schema version 4: always plumb-bob, 5 coefficients.
    #[derive(Deserialize)]
    pub struct CameraModelV4 {
        width: u32,
        height: u32,
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
        distortion: [f64; 5],
    }

    /// `CameraFrame` of schema version 4 (its camera's lens always plumb-bob).
    #[derive(Deserialize)]
    pub struct CameraFrameV4 {
        vehicle: VehicleId,
        camera: u8,
        seq: u64,
        stamp_ns: u64,
        model: CameraModelV4,
        body_from_camera: Pose,
        format: PixelFormat,
        data: Vec<u8>,
    }

    impl From<CameraFrameV4> for CameraFrame {
        fn from(f: CameraFrameV4) -> CameraFrame {
            let m = f.model;
            CameraFrame {
                vehicle: f.vehicle,
                camera: f.camera,
                seq: f.seq,
                stamp_ns: f.stamp_ns,
                info: CameraInfo {
                    model: CameraModel {
                        width: m.width,
                        height: m.height,
                        fx: m.fx,
                        fy: m.fy,
                        cx: m.cx,
                        cy: m.cy,
                        distortion: Distortion::PlumbBob(m.distortion),
                    },
                    body_from_camera: f.body_from_camera,
                },
                format: f.format,
                data: f.data,
            }
        }
    }

    /// `CameraStatus` of schema version 4 (no stamp source, missed frames, reconnects).
    #[derive(Deserialize)]
    pub struct CameraStatusV4 {
        camera: u8,
        name: String,
        frames_in: u64,
        frames_dropped: u64,
        frames_invalid: u64,
        detections: u64,
        frame_rate_hz: f32,
        restore_ms: f32,
        detect_ms: f32,
        pose_ms: f32,
        corner_fits: Vec<(String, u64)>,
    }

    /// `NodeStatus` of schema version 4 (no clock).
    #[derive(Deserialize)]
    pub struct NodeStatusV4 {
        vehicle: VehicleId,
        stamp_ns: u64,
        uptime_s: f64,
        cameras: Vec<CameraStatusV4>,
        observations_sent: u64,
        messages_rejected: u64,
    }

    impl From<NodeStatusV4> for NodeStatus {
        fn from(s: NodeStatusV4) -> NodeStatus {
            NodeStatus {
                vehicle: s.vehicle,
                stamp_ns: s.stamp_ns,
                uptime_s: s.uptime_s,
                cameras: s
                    .cameras
                    .into_iter()
                    .map(|c| CameraStatus {
                        camera: c.camera,
                        name: c.name,
                        frames_in: c.frames_in,
                        frames_dropped: c.frames_dropped,
                        frames_invalid: c.frames_invalid,
                        detections: c.detections,
                        frame_rate_hz: c.frame_rate_hz,
                        restore_ms: c.restore_ms,
                        detect_ms: c.detect_ms,
                        pose_ms: c.pose_ms,
                        corner_fits: c.corner_fits,
                        ..Default::default()
                    })
                    .collect(),
                observations_sent: s.observations_sent,
                messages_rejected: s.messages_rejected,
                clock: None,
            }
        }
    }
}

/// A velocity command for a (simulated) vehicle, body frame FRD.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct VehicleCommand {
    pub vehicle: VehicleId,
    pub stamp_ns: u64,
    /// Forward, starboard, down velocities (m/s).
    pub velocity_body: [f64; 3],
    /// Yaw rate (rad/s), positive turning to starboard.
    pub yaw_rate: f64,
}

impl WireMessage for VehicleCommand {
    const KIND: MessageKind = MessageKind::VehicleCommand;
    fn validate(&self) -> Result<(), (&'static str, String)> {
        if !self
            .velocity_body
            .iter()
            .chain([&self.yaw_rate])
            .all(|v| v.is_finite())
        {
            return Err(("velocity_body", "command is not finite".into()));
        }
        Ok(())
    }
}
