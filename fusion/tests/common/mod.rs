//! Shared scaffolding of the fusion tests, bench and metrics example: feed
//! synthetic observations through a `Fusion` and score the map against truth.
#![allow(dead_code)]

use shoal_fusion::{Fusion, FusionParams};
use shoal_proto::config::Fleet;
use shoal_proto::geometry::{difference, Pose};
use shoal_proto::{EdgeReport, FleetMap, VehicleId, VehicleState, VehicleTruth};
use shoal_sim_bridge::obs_synth::{ObsSynth, ObsSynthParams, OutlierKind, SyntheticObservation};
use std::collections::BTreeMap;
use std::path::Path;

pub const FRAME_NS: u64 = 100_000_000; // 10 Hz cameras
pub const T0_NS: u64 = 1_000_000_000_000;

pub fn paper_fleet() -> Fleet {
    Fleet::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/fleets/paper.toml"))
        .expect("paper fleet loads")
}

/// `frames` frames of every camera at 10 Hz, fed to a new `Fusion` as they
/// are captured; returns the fusion (not yet solved), the observations and
/// the time of the last frame.
pub fn run_frames(
    fleet: &Fleet,
    truth: &[VehicleTruth],
    synth_params: ObsSynthParams,
    params: FusionParams,
    seed: u64,
    frames: usize,
) -> (Fusion, Vec<SyntheticObservation>, u64) {
    let mut synth = ObsSynth::new(fleet, synth_params, seed);
    let mut fusion = Fusion::new(fleet, params, "central");
    let mut all = Vec::new();
    let mut now = T0_NS;
    for k in 0..frames {
        now = T0_NS + k as u64 * FRAME_NS;
        for s in synth.observe(truth, now) {
            let _ = fusion.ingest(s.obs.clone(), s.obs.observer, now);
            all.push(s);
        }
    }
    (fusion, all, now)
}

/// `reference_from_vehicle` truth.
pub fn truth_poses(fleet: &Fleet, truth: &[VehicleTruth]) -> BTreeMap<VehicleId, Pose> {
    let world: BTreeMap<VehicleId, Pose> = truth
        .iter()
        .map(|t| (t.vehicle, t.world_from_body))
        .collect();
    let world_from_ref = world[&fleet.reference_vehicle];
    world
        .iter()
        .map(|(v, p)| (*v, world_from_ref.inverse() * p))
        .collect()
}

/// Largest translation (m) and rotation (rad) error over the Live vehicles, and how many were Live.
pub fn map_error(map: &FleetMap, truth: &BTreeMap<VehicleId, Pose>) -> (f64, f64, usize) {
    let (mut t, mut r, mut n) = (0.0f64, 0.0f64, 0);
    for v in map
        .vehicles
        .iter()
        .filter(|v| v.state == VehicleState::Live)
    {
        let e = difference(&v.reference_from_vehicle, &truth[&v.vehicle]);
        t = t.max(e.fixed_rows::<3>(0).norm());
        r = r.max(e.fixed_rows::<3>(3).norm());
        n += 1;
    }
    (t, r, n)
}

/// Verdicts on hypotheses against the labels.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Scores {
    pub true_accepted: usize,
    pub true_rejected: usize,
    pub false_accepted: usize,
    pub false_rejected: usize,
    pub outlier_observations: usize,
    pub observations: usize,
}

impl Scores {
    /// Of the rejected hypotheses, the fraction that were false.
    pub fn precision(&self) -> f64 {
        let rej = self.true_rejected + self.false_rejected;
        if rej == 0 {
            1.0
        } else {
            self.false_rejected as f64 / rej as f64
        }
    }
    /// Of the false hypotheses, the fraction rejected.
    pub fn recall(&self) -> f64 {
        let f = self.false_accepted + self.false_rejected;
        if f == 0 {
            1.0
        } else {
            self.false_rejected as f64 / f as f64
        }
    }
}

/// Match every hypothesis of `obs` to its report in `map` (primary, then the
/// alternative; a rejection on arrival covers both) and count the verdicts.
pub fn score(map: &FleetMap, obs: &[SyntheticObservation]) -> Scores {
    type Key = (u64, VehicleId, u8, u64, u32);
    let mut reports: BTreeMap<Key, Vec<&EdgeReport>> = BTreeMap::new();
    for e in &map.edges {
        reports
            .entry((
                e.stamp_ns,
                e.observer,
                e.camera,
                e.frame_seq,
                e.target_marker,
            ))
            .or_default()
            .push(e);
    }
    let mut s = Scores::default();
    for o in obs {
        s.observations += 1;
        if o.outlier != OutlierKind::Inlier {
            s.outlier_observations += 1;
        }
        let k = (
            o.obs.stamp_ns,
            o.obs.observer,
            o.obs.camera,
            o.obs.frame_seq,
            o.obs.target_marker,
        );
        let r = reports
            .get(&k)
            .unwrap_or_else(|| panic!("no report for {k:?}"));
        let n_hyp = if o.obs.alternative.is_some() { 2 } else { 1 };
        for h in 0..n_hyp {
            let rejected = r.get(h as usize).unwrap_or(&r[0]).rejected.is_some();
            match (o.hypothesis_is_true(h), rejected) {
                (true, false) => s.true_accepted += 1,
                (true, true) => s.true_rejected += 1,
                (false, false) => s.false_accepted += 1,
                (false, true) => s.false_rejected += 1,
            }
        }
    }
    s
}

/// Every vehicle's nav (default simulated sensors) at each of `frames` 10 Hz
/// frames from [`T0_NS`], fed to `fusion` at `now` (the truth held still).
pub fn ingest_nav_frames(
    fusion: &mut Fusion,
    truth: &[VehicleTruth],
    frames: usize,
    seed: u64,
    now: u64,
) {
    let mut sensors = shoal_sim_bridge::nav::NavSensors::new(
        shoal_sim_bridge::nav::NavSensorParams::default(),
        seed,
    )
    .expect("default sensors are valid");
    for k in 0..frames {
        let stamp = T0_NS + k as u64 * FRAME_NS;
        for t in truth {
            fusion
                .ingest_nav(sensors.measure(t, stamp), t.vehicle, now)
                .expect("simulated nav is admitted");
        }
    }
}
