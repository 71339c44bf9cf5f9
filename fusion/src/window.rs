//! The sliding window of admitted observations, the checks that admit them,
//! and the age inflation of their covariances.

use proto::config::{Fleet, MarkerOwner};
use proto::geometry::{covariance_problem, pose_is_finite, Cov6};
use proto::{EdgeReport, Observation, RejectReason, VehicleId};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};

/// Growth of an observation's covariance with its age, for vehicles that keep
/// moving after the frame was taken: a random walk,
/// `Σ(age) = Σ + age · diag(q_t, q_t, q_t, q_r, q_r, q_r)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AgeInflation {
    /// `q_t`, m²/s.
    pub translation_m2_per_s: f64,
    /// `q_r`, rad²/s.
    pub rotation_rad2_per_s: f64,
}

impl Default for AgeInflation {
    fn default() -> Self {
        // 2 cm and 0.5° of standard deviation after one second (6 mm and
        // 0.16° after one 10 Hz frame): the relative drift of AUVs holding a
        // formation. Manoeuvring swarms want more; the price is that older
        // frames count for less.
        Self {
            translation_m2_per_s: 0.02 * 0.02,
            rotation_rad2_per_s: 0.5f64.to_radians().powi(2),
        }
    }
}

impl AgeInflation {
    pub fn inflate(&self, covariance: &Cov6, age_s: f64) -> Cov6 {
        let age = age_s.max(0.0);
        let mut c = *covariance;
        for i in 0..3 {
            c[(i, i)] += age * self.translation_m2_per_s;
            c[(i + 3, i + 3)] += age * self.rotation_rad2_per_s;
        }
        c
    }
}

/// Ordering key of an observation: capture time first, then who/what.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) struct ObservationKey {
    pub stamp_ns: u64,
    pub observer: VehicleId,
    pub camera: u8,
    pub frame_seq: u64,
    pub codes: &'static str,
    pub marker: u32,
    /// Bits of the measured pose: a re-sent message repeats them exactly;
    /// two detections of one ID in one frame (a misread colliding with the
    /// marker itself) do not, and both must reach the consistency checks.
    pub pose_bits: u64,
}

impl ObservationKey {
    pub fn of(obs: &Observation) -> Self {
        Self {
            stamp_ns: obs.stamp_ns,
            observer: obs.observer,
            camera: obs.camera,
            frame_seq: obs.frame_seq,
            codes: obs.codes.name(),
            marker: obs.target_marker,
            pose_bits: pose_fingerprint(obs),
        }
    }
    /// What makes two observations the same detection. The capture stamp is
    /// part of it: a restarted node numbers its frames from 0 again, and its
    /// new frames are not the old ones.
    pub fn duplicate_key(&self) -> DuplicateKey {
        (
            self.observer,
            self.camera,
            self.frame_seq,
            self.stamp_ns,
            self.codes,
            self.marker,
            self.pose_bits,
        )
    }
}

/// Observer, camera, frame number, capture stamp, code set, marker, pose bits.
pub(crate) type DuplicateKey = (VehicleId, u8, u64, u64, &'static str, u32, u64);

/// FNV-1a over the bit patterns of the primary pose (translation, quaternion).
fn pose_fingerprint(obs: &Observation) -> u64 {
    let p = &obs.observer_from_target;
    let t = p.translation.vector;
    let q = p.rotation.coords;
    [t.x, t.y, t.z, q.x, q.y, q.z, q.w]
        .iter()
        .flat_map(|v| v.to_bits().to_le_bytes())
        .fold(0xcbf2_9ce4_8422_2325u64, |h, byte| {
            (h ^ u64::from(byte)).wrapping_mul(0x0100_0000_01b3)
        })
}

/// An admitted observation.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Stored {
    pub obs: Observation,
    /// The vehicle carrying the marker, per the fleet file.
    pub target: VehicleId,
}

/// Limits the admission checks use.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Admission {
    pub window_ns: u64,
    pub max_clock_skew_ns: u64,
    pub max_std: f64,
}

/// The sliding window.
#[derive(Debug, Clone, Default)]
pub(crate) struct Window {
    pub entries: BTreeMap<ObservationKey, Stored>,
    duplicates: BTreeSet<DuplicateKey>,
}

impl Window {
    /// Admit `obs` or say why not (never double-counts a detection).
    pub fn admit(
        &mut self,
        fleet: &Fleet,
        obs: Observation,
        arrived_on: VehicleId,
        now_ns: u64,
        limits: &Admission,
    ) -> Result<VehicleId, RejectReason> {
        if obs.observer != arrived_on {
            return Err(RejectReason::ObserverMismatch);
        }
        if fleet.vehicle(obs.observer).is_none() {
            return Err(RejectReason::Invalid);
        }
        if !pose_is_finite(&obs.observer_from_target)
            || covariance_problem(&obs.covariance, limits.max_std).is_some()
            || !obs.reprojection_rms_px.is_finite()
        {
            return Err(RejectReason::Invalid);
        }
        if let Some(alt) = &obs.alternative {
            if !pose_is_finite(&alt.observer_from_target)
                || covariance_problem(&alt.covariance, limits.max_std).is_some()
            {
                return Err(RejectReason::Invalid);
            }
        }
        let target = match fleet.marker_owner(obs.codes, obs.target_marker) {
            MarkerOwner::Unknown => return Err(RejectReason::UnknownMarker),
            MarkerOwner::Ambiguous => return Err(RejectReason::AmbiguousMarker),
            MarkerOwner::Vehicle(v) => v,
        };
        if target == obs.observer {
            return Err(RejectReason::SelfObservation);
        }
        if obs.stamp_ns > now_ns.saturating_add(limits.max_clock_skew_ns) {
            return Err(RejectReason::ClockSkew);
        }
        if obs.stamp_ns.saturating_add(limits.window_ns) < now_ns {
            return Err(RejectReason::Stale);
        }
        let key = ObservationKey::of(&obs);
        if !self.duplicates.insert(key.duplicate_key()) {
            return Err(RejectReason::Duplicate);
        }
        self.entries.insert(key, Stored { obs, target });
        Ok(target)
    }

    /// Drop what fell out of the window; returns how many.
    pub fn evict(&mut self, now_ns: u64, window_ns: u64) -> usize {
        let expired: Vec<ObservationKey> = self
            .entries
            .keys()
            .take_while(|k| k.stamp_ns.saturating_add(window_ns) < now_ns)
            .copied()
            .collect();
        for k in &expired {
            self.entries.remove(k);
            self.duplicates.remove(&k.duplicate_key());
        }
        expired.len()
    }
}

/// The report of an observation rejected before the solve.
pub(crate) fn early_report(
    obs: &Observation,
    target: Option<VehicleId>,
    reason: RejectReason,
) -> EdgeReport {
    EdgeReport {
        observer: obs.observer,
        camera: obs.camera,
        target_marker: obs.target_marker,
        target_vehicle: target,
        stamp_ns: obs.stamp_ns,
        frame_seq: obs.frame_seq,
        rejected: Some(reason),
        chi2: f64::NAN,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::testing::observation;
    use crate::solve::testing::{paper_fleet, LIMITS, S};
    use proto::geometry::pose_from_xyz_rpy;

    /// Vehicle 10 seeing 15's marker 15 at `stamp_ns`.
    fn seen(stamp_ns: u64) -> Observation {
        observation(
            10,
            0,
            15,
            stamp_ns,
            pose_from_xyz_rpy([2.0, 0.0, 0.0], [0.0; 3]),
        )
    }

    #[test]
    fn admission_rejects_an_observation_older_than_the_window_or_from_the_future() {
        let fleet = paper_fleet();
        let mut w = Window::default();
        let now = 100 * S;
        assert_eq!(w.admit(&fleet, seen(now - 2 * S), 10, now, &LIMITS), Ok(15));
        assert_eq!(
            w.admit(&fleet, seen(now - 2 * S - 1), 10, now, &LIMITS),
            Err(RejectReason::Stale)
        );
        assert_eq!(w.admit(&fleet, seen(now + S / 4), 10, now, &LIMITS), Ok(15));
        assert_eq!(
            w.admit(&fleet, seen(now + S / 4 + 1), 10, now, &LIMITS),
            Err(RejectReason::ClockSkew)
        );
        assert_eq!(
            w.admit(&fleet, seen(now), 15, now, &LIMITS),
            Err(RejectReason::ObserverMismatch)
        );
        let mut loose = seen(now);
        loose.covariance[(2, 2)] = 36.0; // σ = 6 m > max_std
        assert_eq!(
            w.admit(&fleet, loose, 10, now, &LIMITS),
            Err(RejectReason::Invalid)
        );
        assert_eq!(w.entries.len(), 2);
    }

    #[test]
    fn eviction_drops_what_aged_out_and_forgets_its_duplicate_key() {
        let fleet = paper_fleet();
        let mut w = Window::default();
        let t0 = 100 * S;
        for k in 0..5 {
            w.admit(&fleet, seen(t0 + k * S / 2), 10, t0 + k * S / 2, &LIMITS)
                .unwrap();
        }
        assert_eq!(
            w.admit(&fleet, seen(t0 + S), 10, t0 + S, &LIMITS),
            Err(RejectReason::Duplicate)
        );
        // At t0 + 3 s the frames at t0 and t0 + 0.5 s are beyond 2 s.
        assert_eq!(w.evict(t0 + 3 * S, LIMITS.window_ns), 2);
        assert_eq!(w.entries.len(), 3);
        assert_eq!(w.duplicates.len(), 3);
    }
}
