//! Step 1 of the solve: every admitted observation's hypotheses as measured
//! (`observer_from_target`, not yet inverted into a pair's `a_from_b`), with
//! its covariance grown by its age ([`AgeInflation`]). Admission itself (the
//! window, clock skew, validity) happened on arrival, in `window.rs`.

use crate::consistency::Candidate;
use crate::solver;
use crate::window::{ObservationKey, Stored};
use crate::AgeInflation;
use proto::geometry::{Cov6, Pose};
use proto::VehicleId;
use std::collections::BTreeMap;

/// One camera's view of one marker ID: what the frames of a track share
/// (observer, camera, code set, marker).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) struct TrackKey {
    pub observer: VehicleId,
    pub camera: u8,
    pub codes: &'static str,
    pub marker: u32,
}

/// One observation's hypotheses as measured, `observer_from_target` (in the
/// [`Candidate`]'s `a_from_b`), with age-inflated covariances (`None`: absent
/// or with a covariance that cannot be inverted). Candidates are numbered by
/// the observation's index in the window.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Frame {
    pub observer: VehicleId,
    pub target: VehicleId,
    pub stamp_ns: u64,
    pub track: TrackKey,
    pub hyps: [Option<Candidate>; 2],
    /// What the solve added to each hypothesis' covariance for the frame's
    /// age at `now` (the random walk, and the motion of a moving pair):
    /// variance per translation axis (m²) and per rotation axis (rad²).
    /// Frames of one pair share the part of it since the newest of them was
    /// taken, which [`super::groups::TrackGroups::candidate`] and the pose
    /// graph's constraints ([`super::init::graph`]) count once, not once per
    /// frame.
    pub inflation: [f64; 2],
}

impl Frame {
    /// The vehicle pair, lower ID first.
    pub fn pair(&self) -> (VehicleId, VehicleId) {
        (
            self.observer.min(self.target),
            self.observer.max(self.target),
        )
    }

    /// Squared Mahalanobis residual of hypothesis `h` against the solution
    /// (NaN when either vehicle is not localized or the hypothesis is absent).
    pub fn chi2(&self, h: usize, solution: &BTreeMap<VehicleId, (Pose, Cov6)>) -> f64 {
        match (
            self.hyps[h].as_ref(),
            solution.get(&self.observer),
            solution.get(&self.target),
        ) {
            (Some(c), Some(xo), Some(xt)) => {
                solver::edge_chi2(&xo.0, &xt.0, &c.a_from_b, &c.information)
            }
            _ => f64::NAN,
        }
    }
}

/// The window's observations (in window order) as [`Frame`]s at `now_ns`:
/// each hypothesis' covariance grown by the observation's age (a capture
/// stamp after `now_ns`, within the allowed clock skew, counts as age 0).
pub(crate) fn measured(
    entries: &[(&ObservationKey, &Stored)],
    now_ns: u64,
    inflation: &AgeInflation,
    threads: usize,
) -> Vec<Frame> {
    crate::par::map(entries, threads, PER_THREAD, |i, (key, s)| {
        let o = &s.obs;
        let age_s = now_ns.saturating_sub(o.stamp_ns) as f64 * 1e-9;
        let inflate = |c: &Cov6| inflation.inflate(c, age_s);
        Frame {
            observer: o.observer,
            target: s.target,
            stamp_ns: o.stamp_ns,
            track: TrackKey {
                observer: key.observer,
                camera: key.camera,
                codes: key.codes,
                marker: key.marker,
            },
            hyps: [
                Candidate::new(i, 0, o.observer_from_target, inflate(&o.covariance)),
                o.alternative.as_ref().and_then(|alt| {
                    Candidate::new(i, 1, alt.observer_from_target, inflate(&alt.covariance))
                }),
            ],
            inflation: [
                age_s * inflation.translation_m2_per_s,
                age_s * inflation.rotation_rad2_per_s,
            ],
        }
    })
}

/// Frames per thread at least ([`crate::par`]): two 6×6 inverses each, ~0.2 µs.
const PER_THREAD: usize = 256;

/// Frames made as uncertain as their age makes them once the swarm is seen
/// to move ([`super::motion::PairMotion`] not empty): a frame `age` seconds
/// old of a pair moving at `v` m/s and `ω` rad/s says where it was, not
/// where it is, to within `v·age` and `ω·age` in every direction (added to
/// each axis' variance). A pair's own motion is its fastest significant
/// velocity fit, or the rate at which one of its tracks' confirmed present
/// left a superseded past ([`super::motion::PairMotion::displaced`]),
/// whichever is faster. A pair with no motion of its own in the window gets
/// the fastest seen (vehicles of one formation manoeuvre together) where its
/// frames are too few or too spread to show a motion that fast; where they
/// would have shown it, it holds still ([`super::motion::PairMotion::bound`]):
/// in a large still swarm some fit passes the significance test by chance, and
/// its rate given to every pair would merge a marker's planar flips (tens of
/// degrees apart) into one track. Nothing changes while nothing moves.
///
/// Returns, per frame, whether it changed: a frame given no motion (or of
/// age zero) is left as it was, bit for bit, so its track's groups stand.
pub(crate) fn inflate_moving(
    frames: &mut [Frame],
    moving: &super::motion::PairMotion,
    now_ns: u64,
    threads: usize,
) -> Vec<bool> {
    let fastest = moving.fastest();
    let growth: Vec<(f64, f64)> = frames
        .iter()
        .map(|f| {
            let (speed, turn) = moving.bound(f.pair(), fastest);
            let age_s = now_ns.saturating_sub(f.stamp_ns) as f64 * 1e-9;
            ((speed * age_s).powi(2), (turn * age_s).powi(2))
        })
        .collect();
    crate::par::for_each_mut(frames, threads, PER_THREAD, |i, f| {
        let (dt2, dr2) = growth[i];
        if dt2 == 0.0 && dr2 == 0.0 {
            return;
        }
        f.inflation[0] += dt2;
        f.inflation[1] += dr2;
        for h in f.hyps.iter_mut() {
            if let Some(c) = h.as_ref() {
                let mut cov = c.covariance;
                for i in 0..3 {
                    cov[(i, i)] += dt2;
                    cov[(i + 3, i + 3)] += dr2;
                }
                *h = Candidate::new(c.observation, c.hypothesis, c.a_from_b, cov);
            }
        }
    });
    growth
        .into_iter()
        .map(|(dt2, dr2)| dt2 != 0.0 || dr2 != 0.0)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::testing::{observation, stored};
    use proto::geometry::pose_from_xyz_rpy;

    #[test]
    fn covariance_grows_with_age_and_a_future_stamp_is_age_zero() {
        let pose = pose_from_xyz_rpy([2.0, 0.0, 0.0], [0.0, 0.0, 0.0]);
        let now = 10_000_000_000;
        let old = stored(observation(1, 0, 20, now - 1_000_000_000, pose), 2);
        let early = stored(observation(1, 0, 20, now + 100_000_000, pose), 2);
        let (k_old, k_early) = (ObservationKey::of(&old.obs), ObservationKey::of(&early.obs));
        let inflation = AgeInflation::default();
        let frames = measured(&[(&k_old, &old), (&k_early, &early)], now, &inflation, 2);
        let base = old.obs.covariance;
        let c0 = frames[0].hyps[0].unwrap().covariance;
        assert!((c0[(0, 0)] - base[(0, 0)] - inflation.translation_m2_per_s).abs() < 1e-15);
        assert!((c0[(4, 4)] - base[(4, 4)] - inflation.rotation_rad2_per_s).abs() < 1e-15);
        assert_eq!(frames[1].hyps[0].unwrap().covariance, base);
        // Candidates are numbered by window index; no alternative, no second hypothesis.
        assert_eq!(frames[1].hyps[0].unwrap().observation, 1);
        assert!(frames[0].hyps[1].is_none());
        assert_eq!(frames[0].pair(), (1, 2));
    }
}
