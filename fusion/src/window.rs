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
    /// Arrived over a slow link ([`crate::Fusion::ingest_linked`]): kept for
    /// the link window instead of the window.
    pub linked: bool,
}

/// Limits the admission checks use.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Admission {
    pub window_ns: u64,
    /// The window of observations that arrived over a slow link.
    pub link_window_ns: u64,
    pub max_clock_skew_ns: u64,
    pub max_std: f64,
    /// Observations one observer may hold in the window; beyond, its
    /// oldest are dropped and counted ([`Window::crowded_out`]).
    pub max_per_observer: usize,
}

/// The sliding window.
#[derive(Debug, Clone, Default)]
pub(crate) struct Window {
    pub entries: BTreeMap<ObservationKey, Stored>,
    duplicates: BTreeSet<DuplicateKey>,
    /// Each observer's entries, oldest first: what the per-observer cap drops.
    by_observer: BTreeMap<VehicleId, BTreeSet<ObservationKey>>,
    /// Observations dropped, oldest first, because their observer held
    /// more than [`Admission::max_per_observer`] in the window.
    pub crowded_out: u64,
}

impl Window {
    /// Admit `obs` or say why not (never double-counts a detection).
    #[cfg(test)]
    pub fn admit(
        &mut self,
        fleet: &Fleet,
        obs: Observation,
        arrived_on: VehicleId,
        now_ns: u64,
        limits: &Admission,
    ) -> Result<VehicleId, RejectReason> {
        self.admit_from(fleet, obs, (arrived_on, false), now_ns, limits)
    }

    /// Admit `obs`, which arrived on `source.0`'s key (over a slow link when
    /// `source.1`), or say why not (never double-counts a detection).
    pub fn admit_from(
        &mut self,
        fleet: &Fleet,
        obs: Observation,
        source: (VehicleId, bool),
        now_ns: u64,
        limits: &Admission,
    ) -> Result<VehicleId, RejectReason> {
        let (arrived_on, linked) = source;
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
        let window_ns = if linked {
            limits.link_window_ns
        } else {
            limits.window_ns
        };
        if obs.stamp_ns.saturating_add(window_ns) < now_ns {
            return Err(RejectReason::Stale);
        }
        let key = ObservationKey::of(&obs);
        if !self.duplicates.insert(key.duplicate_key()) {
            return Err(RejectReason::Duplicate);
        }
        let observer = obs.observer;
        self.entries.insert(
            key,
            Stored {
                obs,
                target,
                linked,
            },
        );
        let mine = self.by_observer.entry(observer).or_default();
        mine.insert(key);
        // A node that floods (a bug, a replay, a compromised vehicle with its
        // certificate) fills its own share, not the memory and the solve:
        // its oldest go first, as in the node's drop-oldest queues.
        while mine.len() > limits.max_per_observer.max(1) {
            if let Some(oldest) = mine.pop_first() {
                self.entries.remove(&oldest);
                self.duplicates.remove(&oldest.duplicate_key());
                self.crowded_out += 1;
            }
        }
        Ok(target)
    }

    /// Drop what fell out of its window: `window_ns`, or `link_window_ns` for
    /// what arrived over a link. An own frame's window runs from when gravity
    /// can judge it: `nav_ready(observer, target, stamp)` is `None` where both
    /// vehicles' nav arrives with their frames (the window from the capture),
    /// `Some(None)` while a vehicle's nav that crosses a link has not covered
    /// the frame yet (kept, up to `link_window_ns`), `Some(Some(t))` once it
    /// arrived at `t` (the window from `t`, up to `link_window_ns`). Returns
    /// how many were dropped.
    pub fn evict(
        &mut self,
        now_ns: u64,
        window_ns: u64,
        link_window_ns: u64,
        nav_ready: impl Fn(VehicleId, VehicleId, u64) -> Option<Option<u64>>,
    ) -> usize {
        let shorter = window_ns.min(link_window_ns);
        let longer = window_ns.max(link_window_ns);
        let expired: Vec<ObservationKey> = self
            .entries
            .iter()
            .take_while(|(k, _)| k.stamp_ns.saturating_add(shorter) < now_ns)
            .filter(|(k, s)| {
                let own = k.stamp_ns.saturating_add(window_ns);
                let last = k.stamp_ns.saturating_add(longer);
                let end = if s.linked {
                    k.stamp_ns.saturating_add(link_window_ns)
                } else {
                    match nav_ready(k.observer, s.target, k.stamp_ns) {
                        None => own,
                        Some(None) => last,
                        Some(Some(t)) => own.max(t.saturating_add(window_ns)).min(last),
                    }
                };
                end < now_ns
            })
            .map(|(k, _)| *k)
            .collect();
        for k in &expired {
            self.entries.remove(k);
            self.duplicates.remove(&k.duplicate_key());
            if let Some(mine) = self.by_observer.get_mut(&k.observer) {
                mine.remove(k);
                if mine.is_empty() {
                    self.by_observer.remove(&k.observer);
                }
            }
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
        assert_eq!(
            w.evict(
                t0 + 3 * S,
                LIMITS.window_ns,
                LIMITS.link_window_ns,
                |_, _, _| None
            ),
            2
        );
        assert_eq!(w.entries.len(), 3);
        assert_eq!(w.duplicates.len(), 3);
    }

    #[test]
    fn what_crossed_a_link_is_kept_for_the_link_window_and_the_rest_for_the_window() {
        let fleet = paper_fleet();
        let mut w = Window::default();
        let now = 100 * S;
        // 5 s old: too old for the 2 s window, within the 8 s link window.
        assert_eq!(
            w.admit_from(&fleet, seen(now - 5 * S), (10, false), now, &LIMITS),
            Err(RejectReason::Stale)
        );
        assert_eq!(
            w.admit_from(&fleet, seen(now - 5 * S), (10, true), now, &LIMITS),
            Ok(15)
        );
        assert_eq!(
            w.admit_from(&fleet, seen(now - 8 * S - 1), (10, true), now, &LIMITS),
            Err(RejectReason::Stale)
        );
        w.admit_from(&fleet, seen(now - S), (10, false), now, &LIMITS)
            .unwrap();
        w.admit_from(&fleet, seen(now - S / 2), (10, true), now, &LIMITS)
            .unwrap();
        // 2.5 s later: the local frame (3.5 s old) is gone, both linked ones stay.
        assert_eq!(
            w.evict(
                now + 5 * S / 2,
                LIMITS.window_ns,
                LIMITS.link_window_ns,
                |_, _, _| None
            ),
            1
        );
        assert!(w.entries.values().all(|s| s.linked));
        // 3 s after that the older linked frame (10.5 s) goes, the newer (6 s) stays.
        assert_eq!(
            w.evict(
                now + 11 * S / 2,
                LIMITS.window_ns,
                LIMITS.link_window_ns,
                |_, _, _| None
            ),
            1
        );
        assert_eq!(w.entries.len(), 1);
    }

    #[test]
    fn an_own_frame_awaiting_linked_nav_stays_for_the_link_window_only() {
        let fleet = paper_fleet();
        let mut w = Window::default();
        let now = 100 * S;
        w.admit_from(&fleet, seen(now - S), (10, false), now, &LIMITS)
            .unwrap();
        let mut not_awaited = w.clone();
        let (win, link) = (LIMITS.window_ns, LIMITS.link_window_ns);
        // 4 s old: kept while its target's (15's) nav is awaited, not for another vehicle's.
        let awaited = |_: VehicleId, t: VehicleId, _: u64| (t == 15).then_some(None);
        assert_eq!(w.evict(now + 3 * S, win, link, awaited), 0);
        let other = |_: VehicleId, t: VehicleId, _: u64| (t == 16).then_some(None);
        assert_eq!(not_awaited.evict(now + 3 * S, win, link, other), 1);
        // Its nav arrived 4 s after the capture: the frame stays the window from then.
        let arrived = |_: VehicleId, _: VehicleId, stamp: u64| Some(Some(stamp + 4 * S));
        assert_eq!(w.evict(now + 5 * S, win, link, arrived), 0);
        assert_eq!(w.clone().evict(now + 5 * S + 1, win, link, arrived), 1);
        // Arrived 0.5 s after the capture: 2.5 s in all.
        let early = |_: VehicleId, _: VehicleId, stamp: u64| Some(Some(stamp + S / 2));
        assert_eq!(w.clone().evict(now + 3 * S / 2, win, link, early), 0);
        assert_eq!(w.clone().evict(now + 3 * S / 2 + 1, win, link, early), 1);
        // Awaited past the link window it goes even so.
        assert_eq!(w.evict(now + 7 * S + 1, win, link, awaited), 1);
    }

    #[test]
    fn a_flooding_observer_keeps_only_its_newest_share_and_the_others_keep_theirs() {
        let fleet = paper_fleet();
        let limits = Admission {
            max_per_observer: 8,
            ..LIMITS
        };
        let mut w = Window::default();
        let now = 100 * S;
        // Vehicle 15 sends three frames; vehicle 10 floods 50, out of order.
        for k in 0..3u64 {
            let mut o = observation(
                15,
                0,
                10,
                now - k * S / 10,
                pose_from_xyz_rpy([2.0, 0.0, 0.0], [0.0; 3]),
            );
            o.frame_seq = k;
            w.admit(&fleet, o, 15, now, &limits).unwrap();
        }
        let order: Vec<u64> = (0..50).map(|k| (k * 37) % 50).collect();
        for &k in &order {
            let mut o = seen(now - S + k * S / 50);
            o.frame_seq = k;
            assert_eq!(w.admit(&fleet, o, 10, now, &limits), Ok(15));
        }
        assert_eq!(w.crowded_out, 42);
        assert_eq!(w.entries.len(), 8 + 3);
        let tens: Vec<u64> = w
            .entries
            .keys()
            .filter(|k| k.observer == 10)
            .map(|k| k.frame_seq)
            .collect();
        assert_eq!(
            tens,
            (42..50).collect::<Vec<_>>(),
            "the newest eight by capture time"
        );
        assert_eq!(w.entries.keys().filter(|k| k.observer == 15).count(), 3);
        // What was crowded out is forgotten as a duplicate too: it may come back (and go again).
        let mut again = seen(now - S);
        again.frame_seq = 0;
        assert_eq!(w.admit(&fleet, again, 10, now, &limits), Ok(15));
        assert_eq!(w.crowded_out, 43);
        // Eviction keeps the per-observer index in step: after the window
        // passes, vehicle 10 has its whole share again.
        w.evict(
            now + 3 * S,
            limits.window_ns,
            limits.link_window_ns,
            |_, _, _| None,
        );
        assert!(w.entries.is_empty() && w.by_observer.is_empty() && w.duplicates.is_empty());
        for k in 0..8u64 {
            let mut o = seen(now + 3 * S + k);
            o.frame_seq = 100 + k;
            w.admit(&fleet, o, 10, now + 3 * S, &limits).unwrap();
        }
        assert_eq!((w.entries.len(), w.crowded_out), (8, 43));
    }
}
