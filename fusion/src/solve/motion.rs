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

/// One group's velocity fit of one hypothesis (tangent space at its newest
/// frame): the velocity, its covariance, and whether it is significant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Fit {
    pub v: SVector<f64, 6>,
    pub cov_v: Cov6,
    /// `vᵀ·Σ_v⁻¹·v`.
    pub significance: f64,
    pub significant: bool,
}

impl Fit {
    /// The fit's resolution: the standard deviation of its speed and of its
    /// turn rate along their least certain axis (m/s, rad/s).
    fn resolution(&self) -> (f64, f64) {
        let largest = |o: usize| {
            (o..o + 3)
                .map(|i| self.cov_v[(i, i)])
                .fold(0.0, f64::max)
                .sqrt()
        };
        (largest(0), largest(3))
    }
}

/// Every group's velocity fit per hypothesis; `None` where the group has too
/// few frames or is superseded, or the model is off.
pub(crate) type GroupFits = Vec<[Option<Fit>; 2]>;

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
            *fit = Some(Fit {
                v,
                cov_v,
                significance,
                significant: !significance.is_nan() && significance > model.significance_chi2,
            });
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

/// What the window's tracks show of each vehicle pair's relative motion
/// (pairs lower ID first).
#[derive(Debug, Clone, Default, PartialEq)]
pub(crate) struct PairMotion {
    /// The fastest relative motion fitted on any of the pair's groups where
    /// the motion is significant: translation speed (m/s) and turn rate
    /// (rad/s) of the relative pose. Pairs that hold still are absent.
    pub moving: BTreeMap<(VehicleId, VehicleId), (f64, f64)>,
    /// Pairs not moving, with the finest resolution (σ of speed, σ of turn
    /// rate) of a velocity fit of theirs that found no motion: a pair whose
    /// fit would have shown a motion of that size is known not to have it.
    pub still: BTreeMap<(VehicleId, VehicleId), (f64, f64)>,
    /// The motion model's significance gate ([`MotionModel::significance_chi2`]).
    pub gate_chi2: f64,
    /// Groups whose primary hypothesis was fitted, and how many of them
    /// showed a motion (significant and above the rates worth inflating).
    pub fitted: usize,
    pub moved: usize,
    /// The largest significance (`vᵀ·Σ_v⁻¹·v`) among the moving groups.
    pub strongest: f64,
    /// Pairs one of whose tracks superseded an older group (its newest
    /// frame no longer agrees with it, [`super::groups::group_tracks`]), with
    /// the speed and turn rate that displacement took: the pair moved, even
    /// where no velocity fit was significant. A pair's own evidence only:
    /// never given to other pairs as [`Self::fastest`].
    pub displaced: BTreeMap<(VehicleId, VehicleId), (f64, f64)>,
}

impl PairMotion {
    pub fn is_empty(&self) -> bool {
        self.moving.is_empty() && self.displaced.is_empty()
    }

    /// Whether the swarm as a whole is seen to move: more groups moving than
    /// a still swarm shows by chance, or one group moving too clearly for
    /// chance among all those fitted (Bonferroni), either at most
    /// [`SWARM_FALSE_ALARM`]. A few vehicles seen to manoeuvre pass the second
    /// test (their fits are far beyond the gate); a still swarm of a thousand
    /// passes neither (measured: `shoal eval fusion --profile realistic`).
    pub fn swarm_moves(&self) -> bool {
        // A still group passes the gate with probability P(χ²₆ > gate) (1 %).
        let by_count = || {
            binomial_tail(self.fitted, self.moved, chi2_6_tail(self.gate_chi2)) < SWARM_FALSE_ALARM
        };
        let by_strength = || chi2_6_tail(self.strongest) * (self.fitted as f64) < SWARM_FALSE_ALARM;
        self.moved > 0 && (by_count() || by_strength())
    }

    /// The fastest speed and turn rate of any moving pair once the swarm is
    /// seen to move; zero while only chance detections stand out (in a
    /// still swarm of hundreds of pairs a few fits pass by chance, and the
    /// fastest of them is the extreme of noise, not a manoeuvre).
    pub fn fastest(&self) -> (f64, f64) {
        if !self.swarm_moves() {
            return (0.0, 0.0);
        }
        self.moving
            .values()
            .fold((0.0f64, 0.0f64), |a, b| (a.0.max(b.0), a.1.max(b.1)))
    }

    /// The motion a pair may have had in the window: its own when it was
    /// seen to move; otherwise, per component, the fastest of the swarm's
    /// (`fastest`) unless the pair's own fits would have shown a motion that
    /// fast (its resolution times `√gate_chi2` at most) and showed none.
    pub fn bound(&self, pair: (VehicleId, VehicleId), fastest: (f64, f64)) -> (f64, f64) {
        if let Some(&shown) = self.displaced.get(&pair) {
            let own = self.moving.get(&pair).copied().unwrap_or((0.0, 0.0));
            return (own.0.max(shown.0), own.1.max(shown.1));
        }
        if let Some(&own) = self.moving.get(&pair) {
            return own;
        }
        let Some(&(s_speed, s_turn)) = self.still.get(&pair) else {
            return fastest;
        };
        // A rate this many of the fit's σ would have passed its gate.
        let k = self.gate_chi2.sqrt();
        let unseen = |rate: f64, sigma: f64| if k * sigma <= rate { 0.0 } else { rate };
        (unseen(fastest.0, s_speed), unseen(fastest.1, s_turn))
    }
}

/// Chance below which the number of moving groups is taken for a motion of
/// the swarm rather than the still groups' false alarms.
const SWARM_FALSE_ALARM: f64 = 1e-3;

/// `P(χ²₆ > x)`: for six degrees of freedom, `e^(−x/2)·(1 + x/2 + (x/2)²/2)`.
fn chi2_6_tail(x: f64) -> f64 {
    let h = 0.5 * x.max(0.0);
    (-h).exp() * (1.0 + h + 0.5 * h * h)
}

/// `P(X ≥ m)` for `X ~ Binomial(n, p)`, summed in log space.
fn binomial_tail(n: usize, m: usize, p: f64) -> f64 {
    if m == 0 {
        return 1.0;
    }
    if m > n || p <= 0.0 {
        return 0.0;
    }
    if p >= 1.0 {
        return 1.0;
    }
    let (lp, lq) = (p.ln(), (1.0 - p).ln());
    // ln C(n, m) by the sum of logs (n is a window's groups: thousands at most).
    let mut ln_c: f64 = (0..m)
        .map(|i| ((n - i) as f64).ln() - ((i + 1) as f64).ln())
        .sum();
    let mut total = 0.0;
    for k in m..=n {
        let term = (ln_c + k as f64 * lp + (n - k) as f64 * lq).exp();
        total += term;
        if term < total * 1e-16 {
            break;
        }
        ln_c += ((n - k) as f64).ln() - ((k + 1) as f64).ln();
    }
    total.min(1.0)
}

/// Relative motion slower than this (and [`MIN_TURN_RAD_S`]) is left out
/// of [`PairMotion::moving`]: 2 cm of drift over a 2 s window.
const MIN_SPEED_M_S: f64 = 0.01;
/// 0.3° a second.
const MIN_TURN_RAD_S: f64 = 0.005;

/// [`PairMotion`] of the window's groups, from their fits' primary hypotheses.
pub(crate) fn pair_motion(
    frames: &[Frame],
    groups: &TrackGroups,
    fits: &GroupFits,
    model: &MotionModel,
) -> PairMotion {
    let mut out = PairMotion {
        gate_chi2: model.significance_chi2,
        ..PairMotion::default()
    };
    for (members, fit) in groups.members.iter().zip(fits) {
        let (Some(&newest), Some(fit)) = (members.last(), &fit[0]) else {
            continue;
        };
        let pair = frames[newest].pair();
        out.fitted += 1;
        let speed = fit.v.fixed_rows::<3>(0).norm();
        let turn = fit.v.fixed_rows::<3>(3).norm();
        // Among hundreds of groups of a still swarm, some pass the test by
        // chance: below these rates old frames are not worth inflating.
        if !fit.significant || (speed < MIN_SPEED_M_S && turn < MIN_TURN_RAD_S) {
            let (rs, rt) = fit.resolution();
            let e = out
                .still
                .entry(pair)
                .or_insert((f64::INFINITY, f64::INFINITY));
            *e = (e.0.min(rs), e.1.min(rt));
            continue;
        }
        out.moved += 1;
        out.strongest = out.strongest.max(fit.significance);
        let e = out.moving.entry(pair).or_insert((0.0, 0.0));
        *e = (e.0.max(speed), e.1.max(turn));
    }
    if model.enabled {
        out.displaced = displacements(frames, groups, model);
    }
    out.still
        .retain(|pair, _| !out.moving.contains_key(pair) && !out.displaced.contains_key(pair));
    out
}

/// A displacement implying a speed or turn rate beyond this many standard
/// deviations of [`MotionModel`]'s velocity prior (1.5 m/s, 0.9 rad/s by
/// default) is not taken for motion.
const PLAUSIBLE_PRIOR_SIGMAS: f64 = 3.0;

/// [`PairMotion::displaced`]: per pair, the fastest speed and turn rate
/// between a superseded group's newest frame and its track's newest frame
/// (the closest pairing of their hypotheses), when faster than the rates
/// worth inflating and within [`PLAUSIBLE_PRIOR_SIGMAS`] of the model's
/// velocity prior: a jump faster than vehicles move is a wrong ID read
/// twice, not a manoeuvre.
fn displacements(
    frames: &[Frame],
    groups: &TrackGroups,
    model: &MotionModel,
) -> BTreeMap<(VehicleId, VehicleId), (f64, f64)> {
    let mut out: BTreeMap<(VehicleId, VehicleId), (f64, f64)> = BTreeMap::new();
    if !groups.superseded.iter().any(|&s| s) {
        return out;
    }
    // Each track's newest frame (frames are in time order), where its group
    // holds another frame agreeing with it: one frame that jumps (a misread,
    // a bad fit) also supersedes the past, and is no evidence of motion.
    let mut newest: BTreeMap<super::frames::TrackKey, usize> = BTreeMap::new();
    for (i, f) in frames.iter().enumerate() {
        newest.insert(f.track, i);
    }
    let mut confirmed = vec![false; frames.len()];
    for members in groups.members.iter().filter(|m| m.len() >= 2) {
        members.iter().for_each(|&i| confirmed[i] = true);
    }
    newest.retain(|_, i| confirmed[*i]);
    for (members, _) in groups
        .members
        .iter()
        .zip(&groups.superseded)
        .filter(|(_, &gone)| gone)
    {
        let Some(&old) = members.last() else {
            continue;
        };
        let Some(&new) = newest.get(&frames[old].track) else {
            continue;
        };
        let dt = frames[new].stamp_ns.saturating_sub(frames[old].stamp_ns) as f64 * 1e-9;
        if dt <= 0.0 {
            continue;
        }
        let closest = frames[old]
            .hyps
            .iter()
            .flatten()
            .flat_map(|o| {
                frames[new].hyps.iter().flatten().map(move |n| {
                    let d = proto::geometry::difference(&n.a_from_b, &o.a_from_b);
                    (d.fixed_rows::<3>(0).norm(), d.fixed_rows::<3>(3).norm())
                })
            })
            .min_by(|a, b| a.0.total_cmp(&b.0));
        let Some((moved, turned)) = closest else {
            continue;
        };
        let (speed, turn) = (moved / dt, turned / dt);
        if speed < MIN_SPEED_M_S && turn < MIN_TURN_RAD_S {
            continue;
        }
        if speed > PLAUSIBLE_PRIOR_SIGMAS * model.velocity_prior_m_s
            || turn > PLAUSIBLE_PRIOR_SIGMAS * model.angular_velocity_prior_rad_s
        {
            continue;
        }
        let e = out.entry(frames[new].pair()).or_insert((0.0, 0.0));
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
    fit: &[Option<Fit>; 2],
) -> Option<Vec<[Option<Candidate>; 2]>> {
    let &newest = members.last()?;
    let t_n = frames[newest].stamp_ns;
    let mut moved: Option<Vec<[Option<Candidate>; 2]>> = None;
    for h in 0..2 {
        let (Some(anchor), Some(Fit { v, cov_v, .. })) = (
            frames[newest].hyps[h].map(|c| c.a_from_b),
            fit[h].filter(|f| f.significant),
        ) else {
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
    fn a_track_that_supersedes_its_past_shows_its_pair_moving_unless_its_present_is_one_frame() {
        let at = |y: f64| pose_from_xyz_rpy([2.0, y, 0.0], [0.0; 3]);
        // Pair 1–2: two frames at y = 0, then two at 15 cm (15σ: it moved,
        // and the present is confirmed by a second frame). Pair 1–3: three
        // frames at y = 0, then one frame 30 cm off (a misread, a bad fit).
        // Pair 1–4: two frames at 0, then two 1 m off, 5 m/s: faster than
        // vehicles move (a wrong ID read twice).
        let mut frames = Vec::new();
        let tracks = [
            (2, [0.0, 0.0, 0.15, 0.15]),
            (3, [0.0, 0.0, 0.0, 0.3]),
            (4, [0.0, 0.0, 1.0, 1.0]),
        ];
        for (target, ys) in tracks {
            for (k, y) in ys.into_iter().enumerate() {
                frames.push(frame(
                    frames.len(),
                    1,
                    target,
                    k as u64 * FRAME_NS,
                    at(y),
                    None,
                ));
            }
        }
        frames.sort_by_key(|f| f.stamp_ns);
        let groups = group_tracks(&frames, 27.86, true, 2);
        assert_eq!(groups.superseded.iter().filter(|&&s| s).count(), 3);
        let model = MotionModel::default();
        let fits = fit_groups(&frames, &groups, &model, 2);
        let motion = pair_motion(&frames, &groups, &fits, &model);
        // 15 cm between the superseded group's newest frame (0.1 s) and the
        // track's newest (0.3 s).
        assert_eq!(
            motion.displaced.keys().copied().collect::<Vec<_>>(),
            vec![(1, 2)]
        );
        let (speed, turn) = motion.displaced[&(1, 2)];
        assert!((speed - 0.15 / 0.2).abs() < 1e-9, "{speed}");
        assert!(turn < 1e-9, "{turn}");
        assert!(!motion.still.contains_key(&(1, 2)));
        // The pair's own motion, whatever the swarm's; none for 1–3 or 1–4.
        assert_eq!(motion.bound((1, 2), (0.0, 0.0)), (speed, turn));
        assert_eq!(motion.bound((1, 3), (0.0, 0.0)), (0.0, 0.0));
        assert_eq!(motion.bound((1, 4), (0.0, 0.0)), (0.0, 0.0));
        // So its older frames are inflated by it, and the others' are not.
        let before = frames.clone();
        crate::solve::frames::inflate_moving(&mut frames, &motion, 3 * FRAME_NS, 2);
        for (a, b) in frames.iter().zip(&before) {
            let age = (3 * FRAME_NS - a.stamp_ns) as f64 * 1e-9;
            let grown =
                a.hyps[0].unwrap().covariance[(1, 1)] - b.hyps[0].unwrap().covariance[(1, 1)];
            let want = if a.pair() == (1, 2) {
                (speed * age).powi(2)
            } else {
                0.0
            };
            assert!(
                (grown - want).abs() < 1e-12,
                "{:?} at {age} s: {grown}",
                a.pair()
            );
        }
        // A model switched off sees no motion at all.
        let off = MotionModel {
            enabled: false,
            ..MotionModel::default()
        };
        assert!(pair_motion(
            &before,
            &groups,
            &fit_groups(&before, &groups, &off, 2),
            &off
        )
        .is_empty());
    }

    #[test]
    fn only_pairs_seen_to_move_get_a_motion_and_only_pairs_that_cannot_show_it_the_fastest() {
        // Pair 1–2 drifts 2 cm/s (significant); pair 1–3 holds still, seen
        // in 20 frames; pair 1–4 is seen in one frame only.
        let mut frames = drifting(20, 0.02);
        for k in 0..20 {
            let p = pose_from_xyz_rpy([2.0, -1.0, 0.0], [0.0; 3]);
            frames.push(frame(20 + k, 1, 3, k as u64 * FRAME_NS, p, None));
        }
        let glimpse = pose_from_xyz_rpy([1.0, 1.0, 0.0], [0.0; 3]);
        frames.push(frame(40, 1, 4, 10 * FRAME_NS, glimpse, None));
        frames.sort_by_key(|f| f.stamp_ns);
        let groups = group_tracks(&frames, 27.86, true, 2);
        let model = MotionModel::default();
        let moving = pair_motion(
            &frames,
            &groups,
            &fit_groups(&frames, &groups, &model, 2),
            &model,
        );
        assert_eq!(
            moving.moving.keys().copied().collect::<Vec<_>>(),
            vec![(1, 2)]
        );
        let (speed, turn) = moving.moving[&(1, 2)];
        // The fit, pulled slightly towards rest by its prior.
        assert!((speed - 0.02).abs() < 1e-3, "{speed}");
        assert!(turn < 1e-3, "{turn}");
        // 1–3's fit resolves a few mm/s: 2 cm/s would have shown.
        let (still_speed, _) = moving.still[&(1, 3)];
        assert!(4.1 * still_speed < speed, "{still_speed}");
        assert!(!moving.still.contains_key(&(1, 4)));
        let off = MotionModel {
            enabled: false,
            ..MotionModel::default()
        };
        assert!(pair_motion(
            &frames,
            &groups,
            &fit_groups(&frames, &groups, &off, 2),
            &off
        )
        .is_empty());

        let before = frames.clone();
        let now = 19 * FRAME_NS;
        crate::solve::frames::inflate_moving(&mut frames, &moving, now, 2);
        for (a, b) in frames.iter().zip(&before) {
            let (ca, cb) = (a.hyps[0].unwrap().covariance, b.hyps[0].unwrap().covariance);
            let age = (now - a.stamp_ns) as f64 * 1e-9;
            // 1–2 by its own motion, 1–4 (nothing to show its own) by the
            // fastest seen, which is 1–2's; 1–3 not at all.
            let grown = if a.target == 3 {
                0.0
            } else {
                (speed * age).powi(2)
            };
            assert!(
                (ca[(1, 1)] - cb[(1, 1)] - grown).abs() < 1e-12,
                "{}",
                a.target
            );
            let turned = if a.target == 3 {
                0.0
            } else {
                (turn * age).powi(2)
            };
            assert!((ca[(4, 4)] - cb[(4, 4)] - turned).abs() < 1e-12);
        }
        assert!(frames.iter().any(|f| f.target == 4 && f.stamp_ns < now));
    }

    #[test]
    fn a_turning_pair_does_not_merge_a_still_pairs_planar_flips() {
        // Pair 1–2 turns at 0.3 rad/s; pair 1–3 holds still, its primary
        // every other frame the planar flip (17° off, the truth its
        // alternative). Given 1–2's turn rate over 2 s (~33°), the flips
        // of 1–3 would fall in one group with the truth and be fused with it.
        let truth = pose_from_xyz_rpy([1.75, 0.0, 0.0], [0.0; 3]);
        let twin = pose_from_xyz_rpy([1.75, 0.0, 0.0], [0.0, 0.3, 0.0]);
        let mut frames = Vec::new();
        for k in 0..20 {
            let t = k as u64 * FRAME_NS;
            let turning = pose_from_xyz_rpy([2.0, 0.0, 0.0], [0.0, 0.0, 0.03 * k as f64]);
            frames.push(frame(2 * k, 1, 2, t, turning, None));
            let (primary, alt) = if k % 2 == 0 {
                (truth, twin)
            } else {
                (twin, truth)
            };
            frames.push(frame(2 * k + 1, 1, 3, t, primary, Some(alt)));
        }
        let model = MotionModel::default();
        let groups = group_tracks(&frames, 27.86, true, 2);
        let fits = fit_groups(&frames, &groups, &model, 2);
        let moving = pair_motion(&frames, &groups, &fits, &model);
        assert!(moving.moving[&(1, 2)].1 > 0.25, "{:?}", moving.moving);
        assert!(!moving.moving.contains_key(&(1, 3)));
        crate::solve::frames::inflate_moving(&mut frames, &moving, 19 * FRAME_NS, 2);
        let regrouped = group_tracks(&frames, 27.86, true, 2);
        let angle = |i: usize| {
            let p = frames[i].hyps[0].expect("a primary").a_from_b;
            (p.rotation.inverse() * truth.rotation).angle()
        };
        for members in &regrouped.members {
            if frames[members[0]].target != 3 {
                continue;
            }
            let flipped: Vec<bool> = members.iter().map(|&i| angle(i) > 0.15).collect();
            assert!(
                flipped.iter().all(|&f| f == flipped[0]),
                "a group of 1–3 mixes flipped and true primaries: {members:?}"
            );
        }
    }

    #[test]
    fn a_few_chance_detections_in_a_large_swarm_are_not_a_manoeuvre() {
        // χ²₆ above 16.81 by chance: 1 %.
        assert!((chi2_6_tail(16.81) - 0.01).abs() < 1e-4);
        assert!((chi2_6_tail(0.0) - 1.0).abs() < 1e-15);
        // Binomial tails against sums of the exact terms.
        let exact = |n: u64, m: u64, p: f64| -> f64 {
            let c = |k: u64| (0..k).fold(1.0, |acc, i| acc * (n - i) as f64 / (i + 1) as f64);
            (m..=n)
                .map(|k| c(k) * p.powi(k as i32) * (1.0 - p).powi((n - k) as i32))
                .sum()
        };
        for (n, m) in [(2, 1), (10, 3), (50, 0), (50, 4), (60, 60)] {
            let (a, b) = (binomial_tail(n, m, 0.01), exact(n as u64, m as u64, 0.01));
            assert!(
                (a - b).abs() <= 1e-12 * b.max(1e-300) + 1e-15,
                "{n} {m}: {a} vs {b}"
            );
        }
        assert_eq!(binomial_tail(3, 4, 0.5), 0.0);
        // 42 of 5 311 groups at χ² 37 at most (the 1 000-vehicle realistic fleet,
        // still): as many as 1 % lets through, and the strongest within chance.
        let still = PairMotion {
            moving: BTreeMap::from([((1, 2), (0.16, 0.1))]),
            gate_chi2: MotionModel::default().significance_chi2,
            fitted: 5311,
            moved: 42,
            strongest: 37.0,
            ..PairMotion::default()
        };
        assert!(!still.swarm_moves());
        assert_eq!(still.fastest(), (0.0, 0.0));
        // A third of the groups moving is a manoeuvre; so is one group of two at χ² 60.
        let count = PairMotion {
            moved: 1770,
            ..still.clone()
        };
        assert!(count.swarm_moves());
        assert_eq!(count.fastest(), (0.16, 0.1));
        let clear = PairMotion {
            fitted: 2,
            moved: 1,
            strongest: 60.0,
            ..still
        };
        assert!(clear.swarm_moves());
    }
}
