//! Step 2, continued: a group whose frames show a significant relative
//! velocity is brought to its newest frame's time ([`MotionModel`]), so that
//! a manoeuvring vehicle is followed rather than outvoted by where it has been.

use super::frames::Frame;
use super::groups::TrackGroups;
use crate::consistency::Candidate;
use nalgebra::SVector;
use proto::geometry::Cov6;
use proto::VehicleId;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// How a track's frames taken at different times are brought to one instant.
///
/// Within a group of a track (frames of one camera seeing one marker that
/// agree with its newest frame), the relative pose is fitted as
/// `ξ(t) = x + v·(t − t_newest)` in the tangent space at the newest frame
/// (weighted least squares with the frames' information and a zero-mean
/// prior on `v`). When `v` is significant (its squared Mahalanobis norm above
/// `significance_chi2`), every frame is moved to `t_newest` along `v` and its
/// covariance grows by `Δt²·Σ_v`; otherwise the frames are fused as they are
/// (a static pair loses no precision to a velocity it does not have).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MotionModel {
    /// Switch (default true; false: frames are fused as if nothing moved).
    pub enabled: bool,
    /// Prior standard deviation of the relative linear velocity, m/s (default 0.5).
    pub velocity_prior_m_s: f64,
    /// Prior standard deviation of the relative angular velocity, rad/s (default 0.3).
    pub angular_velocity_prior_rad_s: f64,
    /// Gate on `vᵀ Σ_v⁻¹ v` above which the velocity is used (default 16.81 = χ²₆ at 99%).
    pub significance_chi2: f64,
}

impl Default for MotionModel {
    fn default() -> Self {
        Self {
            enabled: true,
            velocity_prior_m_s: 0.5,
            angular_velocity_prior_rad_s: 0.3,
            significance_chi2: 16.81,
        }
    }
}

/// A group's significant relative velocity per hypothesis (tangent space
/// at its newest frame) and its covariance; `None` where the group has too
/// few frames, is superseded, or the velocity is not significant.
pub(crate) type GroupFits = Vec<[Option<(SVector<f64, 6>, Cov6)>; 2]>;

/// [`GroupFits`] of every group (all `None` when the model is off): the one
/// velocity fit per group and hypothesis that both [`pair_motion`] and
/// [`compensate`] use.
pub(crate) fn fit_groups(
    frames: &[Frame],
    groups: &TrackGroups,
    model: &MotionModel,
    threads: usize,
) -> GroupFits {
    crate::par::map(&groups.members, threads, GROUPS_PER_THREAD, |g, members| {
        let gone = groups.superseded[g];
        let mut fits = [None, None];
        let newest = match members.last() {
            Some(&n) if model.enabled && !gone && members.len() >= 2 => n,
            _ => return fits,
        };
        let t_n = frames[newest].stamp_ns;
        for (h, fit) in fits.iter_mut().enumerate() {
            let Some(anchor) = frames[newest].hyps[h].map(|c| c.a_from_b) else {
                continue;
            };
            let Some((v, cov_v, significance)) =
                fit_velocity(frames, members, h, t_n, &anchor, model)
            else {
                continue;
            };
            if !significance.is_nan() && significance > model.significance_chi2 {
                *fit = Some((v, cov_v));
            }
        }
        fits
    })
}

/// Groups per thread at least ([`crate::par`]).
const GROUPS_PER_THREAD: usize = 64;

/// [`MotionModel`] on every group with a significant velocity (`fits`, from
/// [`fit_groups`] on these groups); returns how many groups were moved.
pub(crate) fn compensate(
    frames: &mut [Frame],
    groups: &TrackGroups,
    fits: &GroupFits,
    threads: usize,
) -> usize {
    // Each group's frames moved on up to `threads` (groups share no
    // frame), then written back.
    let moved = crate::par::map(&groups.members, threads, GROUPS_PER_THREAD, |g, members| {
        compensate_group(frames, members, &fits[g])
    });
    let mut count = 0;
    for (members, updates) in groups.members.iter().zip(moved) {
        let Some(updates) = updates else {
            continue;
        };
        count += 1;
        for (&i, hyps) in members.iter().zip(updates) {
            frames[i].hyps = hyps;
        }
    }
    count
}

/// Per vehicle pair (lower ID first), the fastest relative motion fitted on
/// any of its groups where the motion is significant: translation speed
/// (m/s) and turn rate (rad/s) of the relative pose. Pairs that hold still
/// are absent.
pub(crate) type PairMotion = BTreeMap<(VehicleId, VehicleId), (f64, f64)>;

/// Relative motion slower than this (and [`MIN_TURN_RAD_S`]) is left out
/// of [`PairMotion`]: 2 cm of drift over a 2 s window.
const MIN_SPEED_M_S: f64 = 0.01;
/// 0.3° a second.
const MIN_TURN_RAD_S: f64 = 0.005;

/// [`PairMotion`] of the window's groups, from their fits' primary hypotheses.
pub(crate) fn pair_motion(frames: &[Frame], groups: &TrackGroups, fits: &GroupFits) -> PairMotion {
    let mut out = PairMotion::new();
    for (members, fit) in groups.members.iter().zip(fits) {
        let (Some(&newest), Some((v, _))) = (members.last(), &fit[0]) else {
            continue;
        };
        let speed = v.fixed_rows::<3>(0).norm();
        let turn = v.fixed_rows::<3>(3).norm();
        // Among hundreds of groups of a still swarm, some pass the test by
        // chance: below these rates old frames are not worth inflating.
        if speed < MIN_SPEED_M_S && turn < MIN_TURN_RAD_S {
            continue;
        }
        let e = out.entry(frames[newest].pair()).or_insert((0.0, 0.0));
        *e = (e.0.max(speed), e.1.max(turn));
    }
    out
}

/// One group (`members` ascending in time) moved along its significant
/// velocities (`fit`, per hypothesis) to its newest member's time: the
/// members' new hypotheses, in `members` order; `None` when nothing moved.
fn compensate_group(
    frames: &[Frame],
    members: &[usize],
    fit: &[Option<(SVector<f64, 6>, Cov6)>; 2],
) -> Option<Vec<[Option<Candidate>; 2]>> {
    let &newest = members.last()?;
    let t_n = frames[newest].stamp_ns;
    let mut moved: Option<Vec<[Option<Candidate>; 2]>> = None;
    for h in 0..2 {
        let (Some(anchor), Some((v, cov_v))) = (frames[newest].hyps[h].map(|c| c.a_from_b), fit[h])
        else {
            continue;
        };
        let out = moved.get_or_insert_with(|| members.iter().map(|&i| frames[i].hyps).collect());
        for (&i, hyps) in members.iter().zip(out.iter_mut()) {
            let Some(c) = frames[i].hyps[h] else {
                continue;
            };
            let d = -((t_n - frames[i].stamp_ns) as f64) * 1e-9;
            let r = proto::geometry::difference(&c.a_from_b, &anchor);
            let pose = proto::geometry::perturb(&anchor, &(r - v * d));
            let grown = c.covariance + cov_v * (d * d);
            hyps[h] = Candidate::new(c.observation, c.hypothesis, pose, grown);
        }
    }
    moved
}

/// The weighted least-squares fit of `[x; v]` (12 unknowns) to hypothesis
/// `h` of `members`, in the tangent space at `anchor` (the newest frame, at
/// `t_n`): the velocity, its covariance and its significance (`vᵀ·Σ⁻¹·v`).
/// `None` with fewer than two frames having the hypothesis, or normal
/// equations that cannot be factored.
fn fit_velocity(
    frames: &[Frame],
    members: &[usize],
    h: usize,
    t_n: u64,
    anchor: &proto::geometry::Pose,
    model: &MotionModel,
) -> Option<(SVector<f64, 6>, Cov6, f64)> {
    // The normal equations [[S0, S1], [S1, S2]]·[x; v] = [b0; b1] with
    // S_k = Σ W·d^k, b_k = Σ W·r·d^k, in 6×6 blocks.
    let (mut s0, mut s1, mut s2) = (Cov6::zeros(), Cov6::zeros(), Cov6::zeros());
    let (mut b0, mut b1) = (SVector::<f64, 6>::zeros(), SVector::<f64, 6>::zeros());
    let mut used = 0;
    for &i in members {
        let Some(c) = &frames[i].hyps[h] else {
            continue;
        };
        let d = -((t_n - frames[i].stamp_ns) as f64) * 1e-9;
        let r = proto::geometry::difference(&c.a_from_b, anchor);
        let w = &c.information;
        let wr = w * r;
        s0 += w;
        s1 += w * d;
        s2 += w * (d * d);
        b0 += wr;
        b1 += wr * d;
        used += 1;
    }
    if used < 2 {
        return None;
    }
    for k in 0..3 {
        s2[(k, k)] += model.velocity_prior_m_s.powi(-2);
        s2[(3 + k, 3 + k)] += model.angular_velocity_prior_rad_s.powi(-2);
    }
    // The velocity through the Schur complement of S0: its information is
    // S = S2 − S1·S0⁻¹·S1, its covariance S⁻¹ (the velocity block of the
    // inverse), and v = S⁻¹·(b1 − S1·S0⁻¹·b0).
    let s0_inv = crate::linalg::spd_inverse6(&s0)?;
    let k = s1 * s0_inv;
    let schur = s2 - k * s1;
    let schur = (schur + schur.transpose()) * 0.5;
    let cov_v = crate::linalg::spd_inverse6(&schur)?;
    let v = cov_v * (b1 - k * b0);
    // vᵀ·cov_v⁻¹·v: the velocity's significance.
    let significance = v.dot(&(schur * v));
    Some((v, cov_v, significance))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::groups::group_tracks;
    use crate::solve::testing::frame;
    use proto::geometry::pose_from_xyz_rpy;

    const FRAME_NS: u64 = 100_000_000;

    /// A track of `n` frames (σ = 1 cm) whose target drifts along y at `speed_m_s`.
    fn drifting(n: usize, speed_m_s: f64) -> Vec<Frame> {
        (0..n)
            .map(|k| {
                let y = speed_m_s * k as f64 * 0.1;
                let p = pose_from_xyz_rpy([2.0, y, 0.0], [0.0, 0.0, 0.0]);
                frame(k, 1, 2, k as u64 * FRAME_NS, p, None)
            })
            .collect()
    }

    #[test]
    fn a_drifting_track_is_moved_to_its_newest_frame() {
        // 2 cm/s over 20 frames: 3.8 cm of drift, 3.8σ (one group: within
        // the gate of the newest frame), a velocity ~5σ from zero (significant).
        let mut frames = drifting(20, 0.02);
        let groups = group_tracks(&frames, 27.86, true, 2);
        assert_eq!(groups.members.len(), 1);
        assert_eq!(
            {
                let fits = fit_groups(&frames, &groups, &MotionModel::default(), 2);
                compensate(&mut frames, &groups, &fits, 2)
            },
            1
        );
        let newest_y = 0.02 * 1.9;
        for f in &frames {
            let y = f.hyps[0].unwrap().a_from_b.translation.vector.y;
            // Within 0.1 mm (0.3% of the drift): the velocity prior pulls the fit slightly towards rest.
            assert!((y - newest_y).abs() < 1e-4, "{y} vs {newest_y}");
        }
        // The oldest frame's covariance grew with its distance in time.
        let (old, new) = (frames[0].hyps[0].unwrap(), frames[19].hyps[0].unwrap());
        assert!(old.covariance[(1, 1)] > new.covariance[(1, 1)]);
    }

    #[test]
    fn a_still_track_and_a_disabled_model_move_nothing() {
        let mut frames = drifting(20, 0.0);
        let before = frames.clone();
        let groups = group_tracks(&frames, 27.86, true, 2);
        assert_eq!(
            {
                let fits = fit_groups(&frames, &groups, &MotionModel::default(), 2);
                compensate(&mut frames, &groups, &fits, 2)
            },
            0
        );
        assert_eq!(frames, before);
        let mut moving = drifting(20, 0.02);
        let off = MotionModel {
            enabled: false,
            ..MotionModel::default()
        };
        let groups = group_tracks(&moving, 27.86, true, 2);
        assert_eq!(
            {
                let fits = fit_groups(&moving, &groups, &off, 2);
                compensate(&mut moving, &groups, &fits, 2)
            },
            0
        );
    }

    #[test]
    fn only_pairs_seen_to_move_get_a_motion_and_every_old_frame_the_fastest_uncertainty() {
        // Pair 1–2 drifts 2 cm/s (significant); pair 1–3 holds still.
        let mut frames = drifting(20, 0.02);
        for k in 0..20 {
            let p = pose_from_xyz_rpy([2.0, -1.0, 0.0], [0.0; 3]);
            frames.push(frame(20 + k, 1, 3, k as u64 * FRAME_NS, p, None));
        }
        frames.sort_by_key(|f| f.stamp_ns);
        let groups = group_tracks(&frames, 27.86, true, 2);
        let moving = pair_motion(
            &frames,
            &groups,
            &fit_groups(&frames, &groups, &MotionModel::default(), 2),
        );
        assert_eq!(moving.keys().copied().collect::<Vec<_>>(), vec![(1, 2)]);
        let (speed, turn) = moving[&(1, 2)];
        // The fit, pulled slightly towards rest by its prior.
        assert!((speed - 0.02).abs() < 1e-3, "{speed}");
        assert!(turn < 1e-3, "{turn}");
        let off = MotionModel {
            enabled: false,
            ..MotionModel::default()
        };
        assert!(pair_motion(&frames, &groups, &fit_groups(&frames, &groups, &off, 2)).is_empty());

        let before = frames.clone();
        let now = 19 * FRAME_NS;
        crate::solve::frames::inflate_moving(&mut frames, &moving, now, 2);
        for (a, b) in frames.iter().zip(&before) {
            let (ca, cb) = (a.hyps[0].unwrap().covariance, b.hyps[0].unwrap().covariance);
            let age = (now - a.stamp_ns) as f64 * 1e-9;
            // Pair 1–3 shows no motion of its own: it gets the fastest seen.
            assert!((ca[(1, 1)] - cb[(1, 1)] - (speed * age).powi(2)).abs() < 1e-12);
            assert!((ca[(4, 4)] - cb[(4, 4)] - (turn * age).powi(2)).abs() < 1e-12);
        }
    }
}
