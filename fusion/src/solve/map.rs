//! Step 7 of the solve: the [`FleetMap`]'s contents. One edge report per
//! hypothesis of every observation in the window (plus the rejections on
//! arrival), and every fleet vehicle's estimate and state.
//!
//! [`FleetMap`]: proto::FleetMap

use super::frames::Frame;
use super::gate::{GatedSolution, Poses};
use crate::window::{ObservationKey, Stored};
use crate::{AgeInflation, ReasonCounts, NO_INFORMATION_VARIANCE};
use proto::geometry::{Cov6, Pose};
use proto::{EdgeReport, RejectReason, VehicleEstimate, VehicleId, VehicleState};
use std::collections::{BTreeMap, BTreeSet};

/// The verdicts of the window's observations.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Verdicts {
    /// One per hypothesis (primary, then the alternative), window order.
    pub edges: Vec<EdgeReport>,
    /// Rejected hypotheses per reason.
    pub rejected: ReasonCounts,
    /// Accepted hypotheses.
    pub accepted: usize,
}

/// `[hypothesis 0, hypothesis 1]` flags of `n` observations, set for `keys`.
fn hypothesis_flags(n: usize, keys: impl Iterator<Item = (usize, u8)>) -> Vec<[bool; 2]> {
    let mut v = vec![[false; 2]; n];
    for (i, h) in keys {
        if let Some(f) = v.get_mut(i).and_then(|f| f.get_mut(usize::from(h))) {
            *f = true;
        }
    }
    v
}

/// Each hypothesis' verdict: failed a nav check → `Gravity` / `Depth` /
/// `Heading` (`nav`); gated → `ChiSquare`; accepted → `None`; of a
/// superseded group → `Superseded`; the other hypothesis of an accepted one →
/// `FlippedHypothesis`; otherwise `Inconsistent`. `chi2` against the solution.
pub(crate) fn verdicts(
    entries: &[(&ObservationKey, &Stored)],
    frames: &[Frame],
    accepted: &BTreeMap<(usize, u8), usize>,
    gate: &GatedSolution,
    superseded: &[bool],
    nav: &[[Option<RejectReason>; 2]],
    threads: usize,
) -> Verdicts {
    let mut out = Verdicts {
        edges: Vec::new(),
        rejected: ReasonCounts::default(),
        accepted: 0,
    };
    // Per observation and hypothesis, looked up by index (the sets are
    // keyed by it; tree lookups for every hypothesis were a twentieth of a
    // 100-vehicle solve).
    let is_gated = hypothesis_flags(entries.len(), gate.gated.iter().copied());
    let is_accepted = hypothesis_flags(entries.len(), accepted.keys().copied());
    // Every hypothesis' residual against the solution (the gate's where it
    // judged it), independent: on up to `threads`.
    let chi2s = crate::par::map(entries, threads, 256, |i, _| {
        let x2 = |h: usize| gate.chi2[i][h].unwrap_or_else(|| frames[i].chi2(h, &gate.solution));
        [
            x2(0),
            if entries[i].1.obs.alternative.is_some() {
                x2(1)
            } else {
                f64::NAN
            },
        ]
    });
    for (i, (_, s)) in entries.iter().enumerate() {
        let o = &s.obs;
        let n_hyp: u8 = if o.alternative.is_some() { 2 } else { 1 };
        let (gated, accepted) = (is_gated[i], is_accepted[i]);
        let any_accepted = (0..usize::from(n_hyp)).any(|h| accepted[h] && !gated[h]);
        for h in 0..n_hyp {
            let verdict = if let Some(r) = &nav[i][usize::from(h)] {
                Some(r.clone())
            } else if gated[usize::from(h)] {
                Some(RejectReason::ChiSquare)
            } else if accepted[usize::from(h)] {
                None
            } else if superseded[i] {
                Some(RejectReason::Superseded)
            } else if any_accepted {
                Some(RejectReason::FlippedHypothesis)
            } else {
                Some(RejectReason::Inconsistent)
            };
            let chi2 = chi2s[i][usize::from(h)];
            match &verdict {
                Some(r) => out.rejected.add(r),
                None => out.accepted += 1,
            }
            out.edges.push(EdgeReport {
                observer: o.observer,
                camera: o.camera,
                target_marker: o.target_marker,
                target_vehicle: Some(s.target),
                stamp_ns: o.stamp_ns,
                frame_seq: o.frame_seq,
                rejected: verdict,
                chi2,
            });
        }
    }
    out
}

/// `edges` with the rejections on arrival (`pending`) merged in, in the
/// map's order: capture time, observer, camera, frame, marker (a stable
/// sort: the reports of one detection keep their order, the pending ones
/// after the window's, ordered by reason and chi2 among themselves).
pub(crate) fn merge_pending(
    mut edges: Vec<EdgeReport>,
    mut pending: Vec<EdgeReport>,
) -> Vec<EdgeReport> {
    pending.sort_by_key(report_order);
    edges.extend(pending);
    edges.sort_by_key(|e| {
        (
            e.stamp_ns,
            e.observer,
            e.camera,
            e.frame_seq,
            e.target_marker,
        )
    });
    edges
}

/// Total order of reports of the same detection (rejection reason, then chi2 bits).
fn report_order(r: &EdgeReport) -> (u64, VehicleId, u8, u64, u32, Option<usize>, u64) {
    (
        r.stamp_ns,
        r.observer,
        r.camera,
        r.frame_seq,
        r.target_marker,
        r.rejected.as_ref().map(ReasonCounts::index),
        r.chi2.to_bits(),
    )
}

/// What the map knows about the vehicles beyond this solve.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Evidence<'a> {
    pub reference: VehicleId,
    /// Liveliness per vehicle (absent: alive).
    pub alive: &'a BTreeMap<VehicleId, bool>,
    /// Newest capture stamp involving each vehicle.
    pub last_seen: &'a BTreeMap<VehicleId, u64>,
    /// Vehicles observing or observed in the window.
    pub in_window: &'a BTreeSet<VehicleId>,
    pub inflation: &'a AgeInflation,
    pub now_ns: u64,
    /// Dead reckoning of vehicles no camera sees (`None`: off).
    pub predictor: Option<Predictor<'a>>,
    /// Dead reckoning of localized vehicles from the newest frame their
    /// pose rests on to `now_ns` (`None`: off).
    pub live_predictor: Option<Predictor<'a>>,
    /// Per vehicle, the newest capture stamp of an accepted observation
    /// involving it (the time its solved pose describes, see
    /// [`newest_accepted`]).
    pub as_of: &'a BTreeMap<VehicleId, u64>,
}

/// Per vehicle (observer or target), the newest capture stamp among the
/// accepted hypotheses in `edges`. A localized vehicle's solved pose
/// describes this instant: a track seen to move is brought to its newest
/// frame ([`super::motion`]), a track that is not has no motion to speak
/// of. `last_seen` is not that time: it also counts observations the solve
/// rejected (gated, flipped, a wrong ID) and ones it has not judged yet.
pub(crate) fn newest_accepted(edges: &[EdgeReport]) -> BTreeMap<VehicleId, u64> {
    let mut out = BTreeMap::new();
    for e in edges.iter().filter(|e| e.rejected.is_none()) {
        for v in std::iter::once(e.observer).chain(e.target_vehicle) {
            let t = out.entry(v).or_insert(0);
            *t = (*t).max(e.stamp_ns);
        }
    }
    out
}

/// What carries an unseen vehicle forward.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Predictor<'a> {
    pub odometry: &'a crate::nav::Odometry,
    pub max_predict_ns: u64,
    pub max_gap_ns: u64,
}

impl Predictor<'_> {
    /// `reference_from_vehicle` now, from its value `last` at `seen_ns`:
    /// both vehicles' own motion since (`D_ref⁻¹ · last · D_v`), the
    /// covariance grown by their odometry's position variance, the
    /// reference's attitude error swinging the vehicle's position, and both
    /// attitudes' own errors. `None` when either track does not cover it.
    fn predict(
        &self,
        reference: VehicleId,
        vehicle: VehicleId,
        last: (&Pose, &Cov6, u64),
        now_ns: u64,
    ) -> Option<(Pose, Cov6)> {
        let (pose, cov, seen_ns) = last;
        if now_ns.saturating_sub(seen_ns) > self.max_predict_ns {
            return None;
        }
        let (d_v, pos_v, att_v) =
            self.odometry
                .motion(vehicle, seen_ns, now_ns, self.max_gap_ns)?;
        let (d_r, pos_r, att_r) =
            self.odometry
                .motion(reference, seen_ns, now_ns, self.max_gap_ns)?;
        let predicted = d_r.inverse() * pose * d_v;
        let swing = predicted.translation.vector.norm_squared() * att_r;
        let mut c = *cov;
        for i in 0..3 {
            c[(i, i)] += pos_v + pos_r + swing;
            c[(i + 3, i + 3)] += att_v + att_r;
        }
        Some((predicted, c))
    }
}

/// The estimate of every vehicle in `ids` (ascending): `Live` when localized
/// and alive; `Stale` when localized but its token is gone, or not localized
/// and seen before but not in the window; `Unobserved` when never seen, or in
/// the window without an accepted path to the reference. A vehicle not
/// localized reports its last fused pose (`last_estimate`: pose, covariance,
/// last seen) with the covariance grown by the time since, or the identity
/// with [`NO_INFORMATION_VARIANCE`]. Every localized vehicle's estimate
/// replaces its entry in `last_estimate` (the solved pose, as of its newest
/// accepted frame, `as_of`, or `last_seen` without one). With a
/// `live_predictor`, a localized vehicle's pose is carried from that instant
/// to `now_ns` by both vehicles' odometry (state unchanged); where the
/// odometry does not cover the interval it is the solved pose.
pub(crate) fn vehicle_estimates(
    ids: &[VehicleId],
    evidence: &Evidence<'_>,
    solution: &Poses,
    last_estimate: &mut BTreeMap<VehicleId, (Pose, Cov6, u64)>,
) -> Vec<VehicleEstimate> {
    let mut vehicles = Vec::with_capacity(ids.len());
    for &v in ids {
        let alive = evidence.alive.get(&v).copied().unwrap_or(true);
        let live_or_stale = if alive {
            VehicleState::Live
        } else {
            VehicleState::Stale
        };
        let last_seen_ns = evidence.last_seen.get(&v).copied().unwrap_or(0);
        let (state, pose, covariance) = if v == evidence.reference {
            (live_or_stale, Pose::identity(), Cov6::zeros())
        } else if let Some((pose, cov)) = solution.get(&v) {
            let as_of = evidence.as_of.get(&v).copied().unwrap_or(last_seen_ns);
            last_estimate.insert(v, (*pose, *cov, as_of));
            let carried = evidence.live_predictor.and_then(|p| {
                p.predict(evidence.reference, v, (pose, cov, as_of), evidence.now_ns)
            });
            let (pose, cov) = carried.unwrap_or((*pose, *cov));
            (live_or_stale, pose, cov)
        } else {
            let state = if !alive {
                VehicleState::Stale
            } else if evidence.in_window.contains(&v) {
                VehicleState::Unobserved
            } else if last_seen_ns > 0 {
                VehicleState::Stale
            } else {
                VehicleState::Unobserved
            };
            let predicted = evidence
                .predictor
                .filter(|_| alive)
                .zip(last_estimate.get(&v))
                .and_then(|(p, (pose, cov, seen))| {
                    p.predict(evidence.reference, v, (pose, cov, *seen), evidence.now_ns)
                });
            match (predicted, last_estimate.get(&v)) {
                // Carried forward by the vehicles' odometry.
                (Some((pose, cov)), _) => (VehicleState::Predicted, pose, cov),
                // The last fused pose, its covariance grown with the time since.
                (None, Some((pose, cov, seen))) => {
                    let age_s = evidence.now_ns.saturating_sub(*seen) as f64 * 1e-9;
                    (state, *pose, evidence.inflation.inflate(cov, age_s))
                }
                (None, None) => (
                    state,
                    Pose::identity(),
                    Cov6::identity() * NO_INFORMATION_VARIANCE,
                ),
            }
        };
        vehicles.push(VehicleEstimate {
            vehicle: v,
            state,
            reference_from_vehicle: pose,
            covariance,
            last_seen_ns,
        });
    }
    vehicles
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::testing::{frame, observation, stored, with_alternative};
    use proto::geometry::pose_from_xyz_rpy;

    #[test]
    fn every_hypothesis_gets_the_verdict_of_the_step_that_decided_it() {
        let p = pose_from_xyz_rpy([2.0, 0.0, 0.0], [0.0, 0.0, 0.0]);
        let twin = pose_from_xyz_rpy([2.0, 0.0, 0.0], [0.0, 0.8, 0.0]);
        // 0: accepted primary, its twin; 1: gated; 2: superseded; 3: inconsistent.
        let obs = [
            stored(with_alternative(observation(1, 0, 2, 0, p), twin), 2),
            stored(observation(1, 0, 2, 1, p), 2),
            stored(observation(1, 0, 2, 2, p), 2),
            stored(observation(1, 1, 2, 3, p), 2),
        ];
        let keys: Vec<ObservationKey> = obs.iter().map(|s| ObservationKey::of(&s.obs)).collect();
        let entries: Vec<(&ObservationKey, &Stored)> = keys.iter().zip(&obs).collect();
        let frames: Vec<Frame> = (0..4).map(|i| frame(i, 1, 2, i as u64, p, None)).collect();
        let accepted = BTreeMap::from([((0, 0), 0), ((1, 0), 0)]);
        let gate = GatedSolution {
            solution: Poses::from([
                (1, (Pose::identity(), Cov6::zeros())),
                (2, (p, Cov6::zeros())),
            ]),
            gated: BTreeSet::from([(1, 0)]),
            chi2: vec![[Some(0.5), None], [Some(40.0), None], [None; 2], [None; 2]],
            rounds: 1,
            lm_iterations: 3,
            solver_failed: false,
            graph: crate::solve::init::Graph::default(),
        };
        let v = verdicts(
            &entries,
            &frames,
            &accepted,
            &gate,
            &[false, false, true, false],
            &[[None, None], [None, None], [None, None], [None, None]],
            2,
        );
        let reasons: Vec<Option<RejectReason>> =
            v.edges.iter().map(|e| e.rejected.clone()).collect();
        use RejectReason::*;
        assert_eq!(
            reasons,
            vec![
                None,
                Some(FlippedHypothesis),
                Some(ChiSquare),
                Some(Superseded),
                Some(Inconsistent)
            ]
        );
        assert_eq!(v.accepted, 1);
        assert_eq!(v.rejected.total(), 4);
        // The gate's chi2 where it judged, recomputed against the solution elsewhere.
        assert_eq!((v.edges[0].chi2, v.edges[2].chi2), (0.5, 40.0));
        assert!(v.edges[3].chi2.abs() < 1e-12);
        assert!(
            v.edges[1].chi2.is_nan(),
            "the frame has no second hypothesis"
        );
    }

    #[test]
    fn vehicle_states_follow_localization_liveliness_and_the_window() {
        let p = pose_from_xyz_rpy([2.0, 0.0, 0.0], [0.0, 0.0, 0.0]);
        let now = 10_000_000_000;
        // 1 reference; 2 localized; 3 in the window but unreachable; 4 never
        // seen; 5 seen 3 s ago with a last pose; 6 localized, token gone.
        let alive = BTreeMap::from([(6, false)]);
        let last_seen = BTreeMap::from([
            (1, now),
            (2, now),
            (3, now),
            (5, now - 3_000_000_000),
            (6, now),
        ]);
        let in_window = BTreeSet::from([1, 2, 3, 6]);
        let inflation = AgeInflation::default();
        let evidence = Evidence {
            reference: 1,
            alive: &alive,
            last_seen: &last_seen,
            in_window: &in_window,
            inflation: &inflation,
            now_ns: now,
            predictor: None,
            live_predictor: None,
            as_of: &BTreeMap::new(),
        };
        let cov = Cov6::identity() * 1e-4;
        let solution = Poses::from([
            (1, (Pose::identity(), Cov6::zeros())),
            (2, (p, cov)),
            (6, (p, cov)),
        ]);
        let mut last = BTreeMap::from([(5, (p, cov, now - 3_000_000_000))]);
        let est = vehicle_estimates(&[1, 2, 3, 4, 5, 6], &evidence, &solution, &mut last);
        let states: Vec<VehicleState> = est.iter().map(|e| e.state).collect();
        use VehicleState::*;
        assert_eq!(
            states,
            vec![Live, Live, Unobserved, Unobserved, Stale, Stale]
        );
        assert_eq!(est[0].covariance, Cov6::zeros());
        assert_eq!(est[1].reference_from_vehicle, p);
        for e in [&est[2], &est[3]] {
            assert_eq!(e.reference_from_vehicle, Pose::identity());
            assert_eq!(e.covariance, Cov6::identity() * NO_INFORMATION_VARIANCE);
        }
        // The last pose, its covariance grown over the 3 s since.
        assert_eq!(est[4].reference_from_vehicle, p);
        let grown = inflation.inflate(&cov, 3.0);
        assert!(
            (est[4].covariance - grown).abs().max() < 1e-15,
            "{}",
            est[4].covariance
        );
        // Localized vehicles are remembered.
        assert_eq!(last[&2], (p, cov, now));
        assert!(!last.contains_key(&3));
    }

    /// Vehicles 1 (reference) and 2 cruising at constant world velocities
    /// and headings, sending exact nav every 0.1 s from 0 to 1 s.
    struct Cruise {
        odometry: crate::nav::Odometry,
    }

    const S: u64 = 1_000_000_000;

    /// What `vehicle_estimates` remembers per vehicle: pose, covariance, as of.
    type LastEstimate = BTreeMap<VehicleId, (Pose, Cov6, u64)>;

    impl Cruise {
        /// World position, yaw and world velocity of each vehicle.
        fn motion(v: VehicleId) -> ([f64; 3], f64, [f64; 3]) {
            match v {
                1 => ([0.0, 0.0, 5.0], 0.3, [0.4, 0.1, 0.0]),
                _ => ([1.0, 2.0, 5.5], -0.2, [0.5, -0.15, 0.02]),
            }
        }

        fn world(v: VehicleId, t_ns: u64) -> Pose {
            let (p0, yaw, u) = Self::motion(v);
            let t = t_ns as f64 * 1e-9;
            pose_from_xyz_rpy(
                [p0[0] + u[0] * t, p0[1] + u[1] * t, p0[2] + u[2] * t],
                [0.0, 0.0, yaw],
            )
        }

        fn truth(t_ns: u64) -> Pose {
            Self::world(1, t_ns).inverse() * Self::world(2, t_ns)
        }

        fn new(vehicles: &[VehicleId]) -> Self {
            let mut odometry = crate::nav::Odometry::default();
            for k in 0..=10u64 {
                let t = k * S / 10;
                for &v in vehicles {
                    let (_, yaw, u) = Self::motion(v);
                    let w = Self::world(v, t);
                    let body = w.rotation.inverse() * nalgebra::Vector3::from(u);
                    let nav = proto::nav::NavState {
                        vehicle: v,
                        stamp_ns: t,
                        depth: None,
                        tilt: Some(proto::nav::Tilt {
                            roll_rad: 0.0,
                            pitch_rad: 0.0,
                            covariance: [[1e-6, 0.0], [0.0, 1e-6]],
                        }),
                        heading: Some(proto::nav::Heading {
                            yaw_rad: yaw,
                            std_rad: 1e-3,
                        }),
                        velocity: Some(proto::nav::BodyVelocity {
                            velocity_mps: body.into(),
                            covariance: [[1e-4, 0.0, 0.0], [0.0, 1e-4, 0.0], [0.0, 0.0, 1e-4]],
                        }),
                    };
                    odometry.add(&nav, 10 * S, 512);
                }
            }
            Self { odometry }
        }

        /// The estimates at `now` of 1 and 2, 2 solved as of `as_of`
        /// (`last_seen` later: a newer observation the solve rejected).
        fn estimates(
            &self,
            propagate: bool,
            as_of: u64,
            now: u64,
        ) -> (Vec<VehicleEstimate>, LastEstimate) {
            let alive = BTreeMap::new();
            let last_seen = BTreeMap::from([(1, now), (2, now)]);
            let in_window = BTreeSet::from([1, 2]);
            let inflation = AgeInflation::default();
            let predictor = Predictor {
                odometry: &self.odometry,
                max_predict_ns: u64::MAX,
                max_gap_ns: S / 2,
            };
            let accepted = BTreeMap::from([(1, as_of), (2, as_of)]);
            let evidence = Evidence {
                reference: 1,
                alive: &alive,
                last_seen: &last_seen,
                in_window: &in_window,
                inflation: &inflation,
                now_ns: now,
                predictor: Some(predictor),
                live_predictor: propagate.then_some(predictor),
                as_of: &accepted,
            };
            let solution = Poses::from([
                (1, (Pose::identity(), Cov6::zeros())),
                (2, (Self::truth(as_of), Cov6::identity() * 1e-4)),
            ]);
            let mut last = BTreeMap::new();
            let est = vehicle_estimates(&[1, 2], &evidence, &solution, &mut last);
            (est, last)
        }
    }

    #[test]
    fn a_live_vehicle_is_carried_to_now_by_both_vehicles_odometry() {
        let cruise = Cruise::new(&[1, 2]);
        // Solved as of 0.3 s (its newest accepted frame), the map at 0.8 s:
        // the pair moved 5.2 cm apart since.
        let (as_of, now) = (3 * S / 10, 8 * S / 10);
        let (est, last) = cruise.estimates(true, as_of, now);
        assert_eq!(est[0].reference_from_vehicle, Pose::identity());
        assert_eq!(est[0].covariance, Cov6::zeros());
        assert_eq!(est[1].state, VehicleState::Live);
        let e = proto::geometry::difference(&est[1].reference_from_vehicle, &Cruise::truth(now));
        assert!(e.norm() < 1e-9, "{e:?}");
        let stale = proto::geometry::difference(&Cruise::truth(as_of), &Cruise::truth(now));
        assert!(stale.fixed_rows::<3>(0).norm() > 0.05, "{stale:?}");
        // The covariance grew, by the dead reckoning's variance.
        for i in 0..6 {
            assert!(est[1].covariance[(i, i)] > 1e-4, "{}", est[1].covariance);
        }
        // What is remembered is the solved pose, as of its frame.
        assert_eq!(
            last[&2],
            (Cruise::truth(as_of), Cov6::identity() * 1e-4, as_of)
        );

        // Off, or without the vehicle's odometry: the solved pose as it was.
        let (off, _) = cruise.estimates(false, as_of, now);
        let (no_nav, _) = Cruise::new(&[1]).estimates(true, as_of, now);
        for est in [off, no_nav] {
            assert_eq!(est[1].state, VehicleState::Live);
            assert_eq!(est[1].reference_from_vehicle, Cruise::truth(as_of));
            assert_eq!(est[1].covariance, Cov6::identity() * 1e-4);
        }
        // Odometry that ends before `now` (the last samples at 1 s, nav still
        // in flight) is dead-reckoned on by the last velocities: exact for
        // this cruise, with the variance growing further...
        let at_end = cruise.estimates(true, as_of, S).0;
        let ahead = cruise.estimates(true, as_of, 16 * S / 10).0;
        let e = proto::geometry::difference(
            &ahead[1].reference_from_vehicle,
            &Cruise::truth(16 * S / 10),
        );
        assert!(e.norm() < 1e-9, "{e:?}");
        for i in 0..3 {
            assert!(
                ahead[1].covariance[(i, i)] > at_end[1].covariance[(i, i)],
                "{} vs {}",
                ahead[1].covariance,
                at_end[1].covariance
            );
        }
        // ...for at most the 2 s that break a track: beyond, not covered.
        let (beyond, _) = cruise.estimates(true, as_of, 31 * S / 10);
        assert_eq!(beyond[1].reference_from_vehicle, Cruise::truth(as_of));
        // Solved at `now` on one nav sample: unchanged (to rounding in the
        // identity's composition), and no variance added.
        let (fresh, _) = cruise.estimates(true, now, now);
        let e = proto::geometry::difference(&fresh[1].reference_from_vehicle, &Cruise::truth(now));
        assert!(e.norm() < 1e-12, "{e:?}");
        assert_eq!(fresh[1].covariance, Cov6::identity() * 1e-4);
    }

    #[test]
    fn a_pose_is_as_of_the_newest_accepted_frame_involving_the_vehicle() {
        let report = |observer, target, stamp_ns, rejected| EdgeReport {
            observer,
            camera: 0,
            target_marker: 0,
            target_vehicle: Some(target),
            stamp_ns,
            frame_seq: 0,
            rejected,
            chi2: 0.0,
        };
        let edges = [
            report(1, 2, 5, None),
            report(2, 3, 7, None),
            report(1, 2, 9, Some(RejectReason::ChiSquare)),
            report(3, 4, 8, Some(RejectReason::FlippedHypothesis)),
        ];
        assert_eq!(
            newest_accepted(&edges),
            BTreeMap::from([(1, 5), (2, 7), (3, 7)])
        );
    }
}
