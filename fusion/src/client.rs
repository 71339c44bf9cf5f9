//! The controller-side map API, everything of it that needs no Zenoh:
//! reading a fleet map the way a formation controller needs it (the pose of
//! one vehicle relative to another, [`MapView`]) and keeping the newest of
//! the maps that arrive ([`LatestMap`]). The Zenoh subscription that feeds
//! maps in (`MapClient`) is in `shoal_services::fusion`.
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
    /// Both vehicles `Live` or `Predicted` (carried forward by odometry),
    /// at least one `Predicted`: a current estimate, not a last-known one.
    pub predicted: bool,
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
            predicted: [ea.state, eb.state].contains(&VehicleState::Predicted)
                && [ea.state, eb.state]
                    .iter()
                    .all(|s| matches!(s, VehicleState::Live | VehicleState::Predicted)),
        })
    }
}

/// The newest map a controller holds, from the maps that arrive on the live
/// topic (possibly several between two reads) or from a late joiner's query.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LatestMap {
    view: Option<MapView>,
}

impl LatestMap {
    pub fn new(initial: Option<FleetMap>) -> Self {
        Self {
            view: initial.map(MapView::new),
        }
    }

    /// The map held (`None` before the first).
    pub fn view(&self) -> Option<&MapView> {
        self.view.as_ref()
    }

    /// Keeps the highest-`seq` map of `arrived` when it is not older than
    /// the one held: its `seq` or its stamp at least the held one's (a
    /// restarted fusion numbers its maps from 1 again, with later stamps).
    /// Returns whether the held map changed.
    pub fn offer(&mut self, arrived: impl IntoIterator<Item = FleetMap>) -> bool {
        let Some(m) = arrived.into_iter().max_by_key(|m| m.seq) else {
            return false;
        };
        let newer = self
            .view
            .as_ref()
            .is_none_or(|l| m.seq >= l.map().seq || m.stamp_ns >= l.map().stamp_ns);
        if newer {
            self.view = Some(MapView::new(m));
        }
        newer
    }

    /// Holds `map` whatever it replaces (a map just waited for).
    pub fn replace(&mut self, map: FleetMap) {
        self.view = Some(MapView::new(map));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map(seq: u64, stamp_ns: u64) -> FleetMap {
        FleetMap {
            fleet: "f".into(),
            producer: "central".into(),
            seq,
            stamp_ns,
            reference: 1,
            vehicles: Vec::new(),
            edges: Vec::new(),
            solve_time_us: 0,
        }
    }

    #[test]
    fn latest_map_keeps_the_newest_and_accepts_a_restarted_fusion() {
        let mut latest = LatestMap::new(None);
        assert!(!latest.offer([]));
        assert!(latest.offer([map(3, 300), map(5, 500), map(4, 400)]));
        assert_eq!(latest.view().unwrap().map().seq, 5);
        // An older map arriving late is ignored.
        assert!(!latest.offer([map(2, 200)]));
        assert_eq!(latest.view().unwrap().map().seq, 5);
        // A restarted fusion: seq from 1 again, later stamp.
        assert!(latest.offer([map(1, 900)]));
        assert_eq!(latest.view().unwrap().map().seq, 1);
        latest.replace(map(0, 0));
        assert_eq!(latest.view().unwrap().map().stamp_ns, 0);
    }
}
