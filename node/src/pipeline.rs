//! One camera's processing chain (paper Fig. 8): restoration → marker
//! detection → PnP → `observer_from_target` observations between vehicle
//! bodies, plus the tracker's predictions across short occlusions.
//!
//! No Zenoh here: the service (`service.rs`), the evaluation and offline
//! re-runs from logs all drive this same type.

use crate::detect::{
    CornerFitCounts, DetectError, DetectParams, Detection, MarkerDetector, ShoalDetector,
};
use crate::pose::{estimate_pose_with, stated_covariance, Hypothesis, PoseError};
use crate::restore::{restorer, Method, RestoreError, RestoreParams, Restored, Restorer};
use crate::track::{Track, TrackParams};
use opencv::core::{Mat, Rect};
use shoal_proto::config::{Camera, Fleet, MarkerOwner};
use shoal_proto::geometry::{Cov6, Pose, PoseWithCovariance};
use shoal_proto::marker::{CodeSet, MarkerId};
use shoal_proto::messages::{ImageQuality, Observation, PoseHypothesis, VehicleId};
use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Instant;

/// Everything tunable in a camera pipeline.
#[derive(Debug, Clone)]
pub struct PipelineParams {
    pub restore: Method,
    pub restore_params: RestoreParams,
    /// The code set the fleet's markers use.
    pub codes: CodeSet,
    pub detect: DetectParams,
    /// Corner noise for the PnP covariance; `None` estimates it from the residuals.
    pub corner_sigma_px: Option<f64>,
    pub track: TrackParams,
}

impl Default for PipelineParams {
    fn default() -> Self {
        Self {
            restore: Method::Hoirm,
            restore_params: RestoreParams::default(),
            codes: CodeSet::Shoal,
            detect: DetectParams::default(),
            corner_sigma_px: None,
            track: TrackParams::default(),
        }
    }
}

/// Errors that stop a frame from being processed at all.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error("vehicle {0} is not in the fleet")]
    UnknownVehicle(VehicleId),
    #[error("vehicle {vehicle} has no camera {camera}")]
    UnknownCamera { vehicle: VehicleId, camera: u8 },
    #[error("restoration: {0}")]
    Restore(#[from] RestoreError),
    #[error("detection: {0}")]
    Detect(#[from] DetectError),
}

/// Markers found in one restored frame ([`detect_restoration`]).
#[derive(Debug, Default)]
pub struct Found {
    pub detections: Vec<Detection>,
    /// Of them, read on the detail-keeping restoration of a region where
    /// the frame's restoration read nothing ([`Restored::fine`]).
    pub fine_reads: usize,
    /// Whether that restoration was made and searched (what the pass costs).
    pub fine_searched: bool,
}

/// Find markers in `restored`, the restoration of `raw`: in its image, then,
/// where it gave up detail in a region ([`Restored::fine`]: smoothed, or
/// deconvolved with the scatter halo alone) and no marker was read there,
/// in the region's detail-keeping restoration, keeping what is read inside
/// such a region. A far marker's 2–4 px modules do not survive the first
/// and a turbid frame's noise is what the second leaves in, so the frame
/// is searched first as restored for the water, and again only where that
/// read nothing.
pub fn detect_restoration<D: MarkerDetector + ?Sized>(
    detector: &mut D,
    restored: &Restored,
    raw: &Mat,
) -> Result<Found, PipelineError> {
    let mut found = Found {
        detections: detector.detect_restored(&restored.image, raw)?,
        ..Found::default()
    };
    let Some(fine) = &restored.fine else {
        return Ok(found);
    };
    let unread: Vec<Rect> = fine
        .regions
        .iter()
        .copied()
        .filter(|r| !found.detections.iter().any(|d| inside(d, *r)))
        .collect();
    if unread.is_empty() {
        return Ok(found);
    }
    let image = fine.image(&restored.image, raw, &unread)?;
    found.fine_searched = true;
    // Only markers near those regions are kept: the rest of the frame,
    // searched already, is not traced again.
    let (w, h) = (
        opencv::prelude::MatTraitConst::cols(raw),
        opencv::prelude::MatTraitConst::rows(raw),
    );
    let windows: Vec<Rect> = unread
        .iter()
        .map(|r| {
            let m = FINE_SEARCH_MARGIN_PX;
            let (x0, y0) = ((r.x - m).max(0), (r.y - m).max(0));
            let (x1, y1) = ((r.x + r.width + m).min(w), (r.y + r.height + m).min(h));
            Rect::new(x0, y0, (x1 - x0).max(0), (y1 - y0).max(0))
        })
        .collect();
    for d in detector.detect_restored_within(&image, raw, &windows)? {
        if unread.iter().any(|r| inside(&d, *r)) {
            found.fine_reads += 1;
            found.detections.push(d);
        }
    }
    Ok(found)
}

/// Full-resolution pixels around each of HOIRM's detail-keeping regions
/// that its second search also traces: a marker whose centre is in the
/// region (what is kept) reaches out of it by up to half its size, and
/// the markers that search is for are far ones, tens of pixels wide.
const FINE_SEARCH_MARGIN_PX: i32 = 48;

/// Share of `frame` that `rois` (disjoint, as restorations give them) cover.
fn restored_fraction(rois: &[Rect], frame: &Mat) -> f64 {
    use opencv::prelude::MatTraitConst;
    let whole = Rect::new(0, 0, frame.cols(), frame.rows());
    let area: f64 = rois.iter().map(|r| f64::from((*r & whole).area())).sum();
    (area / f64::from(whole.area().max(1))).min(1.0)
}

/// Whether the centre of `d`'s corners lies in `r`.
fn inside(d: &Detection, r: Rect) -> bool {
    let n = d.corners_px.len().max(1) as f64;
    let (x, y) = d
        .corners_px
        .iter()
        .fold((0.0, 0.0), |(x, y), c| (x + c[0] / n, y + c[1] / n));
    x >= f64::from(r.x)
        && y >= f64::from(r.y)
        && x < f64::from(r.x + r.width)
        && y < f64::from(r.y + r.height)
}

/// What one frame produced.
#[derive(Debug, Default)]
pub struct FrameOutput {
    /// Measured observations, then predicted ones (flagged) for occluded tracks.
    pub observations: Vec<Observation>,
    /// Markers decoded in the frame.
    pub detections: usize,
    /// The detections per corner fit ([`crate::detect::CornerFit`]): which
    /// fits ran, for the node's status.
    pub corner_fits: CornerFitCounts,
    /// Of `detections`, read only on the detail-keeping restoration ([`detect_restoration`]).
    pub fine_reads: usize,
    /// Whether the detail-keeping restoration was made and searched.
    pub fine_searched: bool,
    /// Share of the frame the restoration's regions cover (1: restored whole).
    pub restored_fraction: f64,
    /// The water the restoration read off the frame (or was given), 1/m
    /// (`Restored::estimated_c_per_m`).
    pub water_c_per_m: f64,
    /// Detections dropped: PnP failed, or the marker size is unknown.
    pub pose_failures: Vec<String>,
    /// Detections of a marker the observing vehicle carries itself, dropped
    /// (a misread, or a camera that sees its own hull: no relative pose to
    /// report, and fusion would refuse it as a self-observation).
    pub own_marker_reads: usize,
    pub restore_ms: f64,
    pub detect_ms: f64,
    pub pose_ms: f64,
}

/// The chain for one camera of one vehicle; holds per-camera state
/// (HOIRM's ambient estimate, the trackers).
pub struct CameraPipeline {
    fleet: Arc<Fleet>,
    observer: VehicleId,
    camera: Camera,
    params: PipelineParams,
    restorer: Box<dyn Restorer>,
    detector: ShoalDetector,
    tracks: BTreeMap<MarkerId, Track>,
}

impl std::fmt::Debug for CameraPipeline {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CameraPipeline")
            .field("observer", &self.observer)
            .field("camera", &self.camera.name)
            .finish()
    }
}

impl CameraPipeline {
    pub fn new(
        fleet: Arc<Fleet>,
        observer: VehicleId,
        camera_index: u8,
        params: PipelineParams,
    ) -> Result<CameraPipeline, PipelineError> {
        let vehicle = fleet
            .vehicle(observer)
            .ok_or(PipelineError::UnknownVehicle(observer))?;
        let camera = vehicle.cameras.get(camera_index as usize).cloned().ok_or(
            PipelineError::UnknownCamera {
                vehicle: observer,
                camera: camera_index,
            },
        )?;
        if let Some(e) = params.restore_params.problem() {
            return Err(e.into());
        }
        Ok(CameraPipeline {
            restorer: restorer(params.restore, &params.restore_params),
            detector: ShoalDetector::new(
                params.codes,
                DetectParams {
                    lens: Some(camera.model),
                    ..params.detect.clone()
                },
            ),
            fleet,
            observer,
            camera,
            params,
            tracks: BTreeMap::new(),
        })
    }

    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    /// Process one 8-bit grey frame captured at `stamp_ns`.
    pub fn process(
        &mut self,
        gray: &Mat,
        stamp_ns: u64,
        frame_seq: u64,
    ) -> Result<FrameOutput, PipelineError> {
        let mut out = FrameOutput::default();
        let t0 = Instant::now();
        let restored = self.restorer.restore(gray, stamp_ns)?;
        let t1 = Instant::now();
        let found = detect_restoration(&mut self.detector, &restored, gray)?;
        let detections = found.detections;
        let t2 = Instant::now();
        out.detections = detections.len();
        out.fine_reads = found.fine_reads;
        out.fine_searched = found.fine_searched;
        out.restored_fraction = restored_fraction(&restored.rois, gray);
        out.water_c_per_m = restored.estimated_c_per_m;
        out.corner_fits = detections.iter().collect();
        // The frame's figures; the marker's own contrast is added per
        // detection (and stays 0 on predictions, where no marker was seen).
        let frame_quality = ImageQuality {
            marker_contrast: 0.0,
            cnr: 0.0,
            backscatter: (restored.backscatter / 255.0) as f32,
            estimated_c_per_m: restored.estimated_c_per_m as f32,
        };
        let mut seen = Vec::new();
        for det in &detections {
            if self.fleet.marker_owner(det.codes, det.id) == MarkerOwner::Vehicle(self.observer) {
                out.own_marker_reads += 1;
                continue;
            }
            let quality = marker_quality(gray, det, frame_quality);
            match self.observation(det, stamp_ns, frame_seq, quality) {
                Ok(obs) => {
                    seen.push(det.id);
                    self.track(&obs);
                    out.observations.push(obs);
                }
                Err(reason) => out.pose_failures.push(reason),
            }
        }
        self.bridge_occlusions(
            &seen,
            stamp_ns,
            frame_seq,
            frame_quality,
            &mut out.observations,
        );
        let t3 = Instant::now();
        out.restore_ms = (t1 - t0).as_secs_f64() * 1e3;
        out.detect_ms = (t2 - t1).as_secs_f64() * 1e3;
        out.pose_ms = (t3 - t2).as_secs_f64() * 1e3;
        Ok(out)
    }

    /// Marker side and mounting: from the fleet when a vehicle carries the
    /// marker, else the side of any marker of the same code set (so an
    /// unknown ID is still reported, in the marker's own frame).
    fn marker_geometry(&self, det: &Detection) -> Option<(f64, Option<(VehicleId, Pose)>)> {
        match self.fleet.marker_owner(det.codes, det.id) {
            MarkerOwner::Vehicle(v) => {
                let m = self.fleet.marker(v, det.codes, det.id)?;
                Some((m.side_m, Some((v, m.body_from_marker))))
            }
            MarkerOwner::Unknown | MarkerOwner::Ambiguous => self
                .fleet
                .vehicles
                .iter()
                .flat_map(|v| v.markers.iter())
                .find(|m| m.codes == det.codes)
                .map(|m| (m.side_m, None)),
        }
    }

    fn observation(
        &self,
        det: &Detection,
        stamp_ns: u64,
        frame_seq: u64,
        quality: ImageQuality,
    ) -> Result<Observation, String> {
        let (side_m, owner) = self.marker_geometry(det).ok_or_else(|| {
            format!(
                "{}#{}: no marker of this code set in the fleet, size unknown",
                det.codes, det.id
            )
        })?;
        // Through the camera's flat port when the fleet file gives one;
        // otherwise its calibration is taken as an in-water pinhole.
        let object_points = det.object_points(side_m);
        let solution = estimate_pose_with(
            &self.camera.model,
            self.camera.port.as_ref(),
            &object_points,
            &det.corners_px,
            self.params.corner_sigma_px,
        )
        .map_err(|e: PoseError| format!("{}#{}: {e}", det.codes, det.id))?;
        // PnP's covariance, plus what the calibration's stated uncertainty
        // and correlated corner errors add (the residuals show neither).
        let stated = |h: &Hypothesis| -> Result<Cov6, String> {
            stated_covariance(
                &self.camera.model,
                self.camera.port.as_ref(),
                &object_points,
                h,
                self.camera.calibration_sigma.as_ref(),
                det.corner_covariance.as_ref(),
            )
            .map_err(|e| format!("{}#{}: {e}", det.codes, det.id))
        };
        let to_body = |h: &Hypothesis| -> Result<PoseWithCovariance, String> {
            let fixed = |p: Pose| PoseWithCovariance::new(p, Cov6::zeros());
            let camera_from_marker = PoseWithCovariance::new(h.camera_from_marker, stated(h)?);
            let marker_from_target = owner
                .map(|(_, body_from_marker)| body_from_marker.inverse())
                .unwrap_or_else(Pose::identity);
            Ok(fixed(self.camera.body_from_camera)
                .compose(&camera_from_marker)
                .compose(&fixed(marker_from_target)))
        };
        let best = to_body(&solution.best)?;
        let alternative = solution
            .alternative
            .map(|h| to_body(&h).map(|alt| (h, alt)))
            .transpose()?;
        Ok(Observation {
            observer: self.observer,
            camera: self.camera.index,
            codes: det.codes,
            target_marker: det.id,
            target_vehicle: owner.map(|(v, _)| v),
            stamp_ns,
            frame_seq,
            observer_from_target: best.pose,
            covariance: symmetric(best.covariance),
            reprojection_rms_px: solution.best.rms_px,
            alternative: alternative.map(|(h, alt)| PoseHypothesis {
                observer_from_target: alt.pose,
                covariance: symmetric(alt.covariance),
                reprojection_rms_px: h.rms_px,
            }),
            corner_count: det.corners_px.len() as u8,
            corners_px: det
                .corners_px
                .iter()
                .map(|c| [c[0] as f32, c[1] as f32])
                .collect(),
            quality,
            predicted: false,
        })
    }

    fn track(&mut self, obs: &Observation) {
        if obs.target_vehicle.is_none() {
            return;
        }
        let params = self.params.track;
        match self.tracks.get_mut(&obs.target_marker) {
            Some(t) if t.bridges(obs.stamp_ns, &params) => {
                t.update(
                    &obs.observer_from_target,
                    &obs.covariance,
                    obs.stamp_ns,
                    &params,
                );
            }
            _ => {
                self.tracks.insert(
                    obs.target_marker,
                    Track::new(obs.observer_from_target, obs.covariance, obs.stamp_ns),
                );
            }
        }
    }

    /// Predicted observations for tracked markers not seen in this frame.
    fn bridge_occlusions(
        &mut self,
        seen: &[MarkerId],
        stamp_ns: u64,
        frame_seq: u64,
        quality: ImageQuality,
        out: &mut Vec<Observation>,
    ) {
        let params = self.params.track;
        self.tracks
            .retain(|_, t| t.bridges(stamp_ns, &params) || t.last_measured_ns() >= stamp_ns);
        for (&id, track) in &self.tracks {
            if seen.contains(&id) || !track.bridges(stamp_ns, &params) {
                continue;
            }
            let MarkerOwner::Vehicle(target) = self.fleet.marker_owner(self.params.codes, id)
            else {
                continue;
            };
            let (pose, cov) = track.predict(stamp_ns, &params);
            out.push(Observation {
                observer: self.observer,
                camera: self.camera.index,
                codes: self.params.codes,
                target_marker: id,
                target_vehicle: Some(target),
                stamp_ns,
                frame_seq,
                observer_from_target: pose,
                covariance: symmetric(cov),
                reprojection_rms_px: 0.0,
                alternative: None,
                corner_count: 0,
                corners_px: Vec::new(),
                quality,
                predicted: true,
            });
        }
    }
}

/// `frame` with the contrast and CNR of `det`'s modules on the raw frame
/// `gray` ([`crate::metrics::marker_contrast`]): what the water and the
/// camera leave of the marker, before restoration. A marker whose modules
/// cannot be sampled (no complete square of corners) keeps 0.
fn marker_quality(gray: &Mat, det: &Detection, frame: ImageQuality) -> ImageQuality {
    match crate::metrics::marker_contrast(gray, det) {
        Ok(c) => ImageQuality {
            marker_contrast: c.michelson as f32,
            cnr: c.cnr as f32,
            ..frame
        },
        Err(e) => {
            tracing::debug!("{}#{}: no marker contrast: {e}", det.codes, det.id);
            frame
        }
    }
}

fn symmetric(c: Cov6) -> Cov6 {
    (c + c.transpose()) * 0.5
}
