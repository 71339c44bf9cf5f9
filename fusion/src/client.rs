//! Reading a fleet map the way a formation controller needs it: the pose of
//! one vehicle relative to another. The Zenoh subscription that feeds maps in
//! is the service's business; this is the pure part.
//!
//! **Correlation caveat.** A [`FleetMap`] carries each vehicle's *marginal*
//! covariance relative to the reference, not the cross-covariances. So
//! [`MapView::relative`] propagates `a_from_b = (ref_from_a)⁻¹ · ref_from_b`
//! as if the two marginals were independent. Errors the two vehicles share
//! (the part of their paths to the reference they have in common) cancel in
//! reality but add here: the returned covariance is conservative, most so for
//! neighbours far from the reference. The pose itself is exact.

use proto::geometry::PoseWithCovariance;
use proto::{FleetMap, VehicleEstimate, VehicleId, VehicleState};

/// `a_from_b` read from a map.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelativePose {
    pub a: VehicleId,
    pub b: VehicleId,
    /// Pose of `b` in `a`'s body frame (FRD) and its (conservative) covariance.
    pub a_from_b: PoseWithCovariance,
    /// Map stamp minus the older of the two vehicles' newest observations, ns.
    pub age_ns: u64,
    /// Both vehicles `Live` in the map.
    pub live: bool,
}

/// A fleet map indexed for queries.
#[derive(Debug, Clone, PartialEq)]
pub struct MapView {
    map: FleetMap,
}

impl MapView {
    pub fn new(map: FleetMap) -> Self {
        Self { map }
    }

    pub fn map(&self) -> &FleetMap {
        &self.map
    }

    /// The estimate of one vehicle.
    pub fn vehicle(&self, v: VehicleId) -> Option<&VehicleEstimate> {
        self.map.vehicles.iter().find(|e| e.vehicle == v)
    }

    /// `a_from_b` with covariance and age; `None` when either vehicle is
    /// unknown to the map or `Unobserved` (a `Stale` vehicle's last pose is
    /// returned with `live == false`).
    pub fn relative(&self, a: VehicleId, b: VehicleId) -> Option<RelativePose> {
        let ea = self.vehicle(a)?;
        let eb = self.vehicle(b)?;
        if ea.state == VehicleState::Unobserved || eb.state == VehicleState::Unobserved {
            return None;
        }
        let ref_from_a = PoseWithCovariance::new(ea.reference_from_vehicle, ea.covariance);
        let ref_from_b = PoseWithCovariance::new(eb.reference_from_vehicle, eb.covariance);
        let oldest = ea.last_seen_ns.min(eb.last_seen_ns);
        Some(RelativePose {
            a,
            b,
            a_from_b: ref_from_a.inverse().compose(&ref_from_b),
            age_ns: self.map.stamp_ns.saturating_sub(oldest),
            live: ea.state == VehicleState::Live && eb.state == VehicleState::Live,
        })
    }
}
