//! How the map kept a vehicle the demo hid from every camera
//! ([`DemoConfig::occlude`](super::DemoConfig::occlude)): its state in each
//! map of the span, how far the reported pose was from the truth and whether
//! that was inside the reported 3σ, and how far the vehicle strayed from its
//! formation slot (the formation holds when the controller can still steer it).

use proto::geometry::difference;
use serde::Serialize;
use shoal_proto as proto;
use shoal_proto::config::Fleet;
use shoal_proto::{FleetMap, SimTruth, VehicleState};
use shoal_services::sim::Occlusion;
use std::collections::VecDeque;

/// The hidden vehicle over the maps stamped from one second into its span
/// until it is seen again.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct OcclusionReport {
    pub vehicle: u32,
    pub maps: usize,
    pub live: usize,
    pub predicted: usize,
    pub stale: usize,
    pub unobserved: usize,
    /// Of the maps with a pose for it (any state but unobserved): the
    /// position error's largest value, and the maps where it was within 3σ
    /// (the largest standard deviation of the reported position covariance).
    pub max_position_error_m: f64,
    pub within_3_sigma: usize,
    /// Largest distance of the vehicle from its slot relative to the
    /// reference (the slot: where it was in the first truth), from the truth.
    pub max_slot_error_m: f64,
}

pub(super) fn report(
    fleet: &Fleet,
    maps: &[FleetMap],
    truths: &VecDeque<SimTruth>,
    occ: &Occlusion,
) -> OcclusionReport {
    let mut r = OcclusionReport {
        vehicle: occ.vehicle,
        ..OcclusionReport::default()
    };
    let reference = fleet.reference_vehicle;
    let relative = |t: &SimTruth| {
        let pose = |v| {
            t.vehicles
                .iter()
                .find(|x| x.vehicle == v)
                .map(|x| x.world_from_body)
        };
        Some(pose(reference)?.inverse() * pose(occ.vehicle)?)
    };
    let Some(slot) = truths.front().and_then(relative) else {
        return r;
    };
    // Hidden over [from, to) (`Occlusion::covers`): at `to` it is seen again.
    let span = (occ.from_s + 1.0)..occ.to_s;
    for m in maps {
        let t_s = m.stamp_ns as f64 * 1e-9;
        if !span.contains(&t_s) {
            continue;
        }
        let Some(est) = m.vehicles.iter().find(|v| v.vehicle == occ.vehicle) else {
            continue;
        };
        let Some(truth) = truths
            .iter()
            .min_by_key(|t| t.stamp_ns.abs_diff(m.stamp_ns))
        else {
            continue;
        };
        let Some(now) = relative(truth) else { continue };
        r.maps += 1;
        r.max_slot_error_m = r
            .max_slot_error_m
            .max((now.translation.vector - slot.translation.vector).norm());
        match est.state {
            VehicleState::Live => r.live += 1,
            VehicleState::Predicted => r.predicted += 1,
            VehicleState::Stale => r.stale += 1,
            VehicleState::Unobserved => {
                r.unobserved += 1;
                continue;
            }
        }
        let error = difference(&est.reference_from_vehicle, &now)
            .fixed_rows::<3>(0)
            .norm();
        r.max_position_error_m = r.max_position_error_m.max(error);
        let sigma = (0..3)
            .map(|i| est.covariance[(i, i)])
            .fold(0.0, f64::max)
            .sqrt();
        r.within_3_sigma += usize::from(error <= 3.0 * sigma);
    }
    r
}
