//! Step 2 of the solve: each track's frames cut into time-consistent groups,
//! so that the consistency checks run over a pair's tracks, not over every
//! frame, and a group's frames fused into one candidate per hypothesis.

use super::frames::{Frame, TrackKey};
use crate::consistency::{self, Candidate};
use crate::solver;
use proto::geometry::{Cov6, Pose, PoseWithCovariance};
use std::collections::BTreeMap;

/// The groups of the window's frames ([`group_tracks`]).
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct TrackGroups {
    /// Indices into the frames, ascending within a group; groups in
    /// ascending order of their first frame.
    pub members: Vec<Vec<usize>>,
    /// Per group: an older group of a track that no longer agrees with the
    /// track's newest frame (its target moved since).
    pub superseded: Vec<bool>,
}

impl TrackGroups {
    /// Per frame: whether its group is superseded.
    pub fn superseded_frames(&self, n_frames: usize) -> Vec<bool> {
        let mut out = vec![false; n_frames];
        for (members, &gone) in self.members.iter().zip(&self.superseded) {
            if gone {
                members.iter().for_each(|&i| out[i] = true);
            }
        }
        out
    }

    /// Hypothesis `h` of group `g` (the frames in `without` left out) fused
    /// into one candidate `a_from_b` of the pair (a < b): the
    /// information-weighted mean in the observer's frame, then inverted once
    /// if the observer is `b`. `None` when no frame has the hypothesis.
    /// The frames are weighed as of the newest of them
    /// ([`fuse_sharing_inflation`]).
    pub fn candidate(
        &self,
        frames: &[Frame],
        g: usize,
        h: u8,
        without: &[usize],
    ) -> Option<Candidate> {
        let members = &self.members[g];
        let used: Vec<(&Candidate, [f64; 2])> = members
            .iter()
            .filter(|i| !without.contains(i))
            .filter_map(|&i| {
                let f = &frames[i];
                f.hyps[usize::from(h)].as_ref().map(|c| (c, f.inflation))
            })
            .collect();
        let (pose, cov) = match used.as_slice() {
            [] => return None,
            [(one, _)] => (one.a_from_b, one.covariance),
            many => {
                let items: Vec<(&Candidate, [f64; 2], bool)> =
                    many.iter().map(|&(c, i)| (c, i, false)).collect();
                fuse_sharing_inflation(&items, true)?
            }
        };
        let f = &frames[members[0]];
        if let ([(one, _)], true) = (used.as_slice(), f.observer < f.target) {
            // The frame itself (its information already computed).
            return Some(Candidate {
                observation: g,
                hypothesis: h,
                ..**one
            });
        }
        let measured = PoseWithCovariance::new(pose, cov);
        let a_from_b = if f.observer < f.target {
            measured
        } else {
            solver::invert(&measured)
        };
        Candidate::new(g, h, a_from_b.pose, a_from_b.covariance).map(|c| c.with_weight(used.len()))
    }
}

/// Candidates of one vehicle pair fused as of the freshest of them. Each
/// item is a candidate, the
/// inflation its covariance carries for its age ([`Frame::inflation`],
/// diagonal in the frame it was measured in) and whether it was inverted
/// since (measured by the pair's `b`). What their ages added up to the
/// freshest one's age is the pair's motion since that one was taken, common
/// to all of them: it is taken out of every item before they are weighed
/// against each other, and added once to the fused covariance. Weighed with
/// it in, as independent errors, frames a second or two old count nearly as
/// much as the newest (their ages dominate every covariance), so the mean
/// trails a moving pair while the covariance shrinks as if the motion were
/// noise that averages out. Where an item cannot be taken apart (a
/// covariance that is not positive definite without it) the items are
/// fused as they are. `close`: the items lie within a gate of each other
/// (one Gauss–Newton pass).
pub(crate) fn fuse_sharing_inflation(
    items: &[(&Candidate, [f64; 2], bool)],
    close: bool,
) -> Option<(Pose, Cov6)> {
    let fuse = |weighed: &[(Pose, Cov6)]| {
        if close {
            consistency::fuse_close(weighed)
        } else {
            consistency::fuse(weighed)
        }
    };
    let as_they_are = || {
        let weighed: Vec<(Pose, Cov6)> = items
            .iter()
            .map(|(c, _, _)| (c.a_from_b, c.information))
            .collect();
        fuse(&weighed)
    };
    let shared = items.iter().fold([f64::INFINITY; 2], |m, (_, i, _)| {
        [m[0].min(i[0]), m[1].min(i[1])]
    });
    if !(shared[0] > 0.0 || shared[1] > 0.0) || !shared.iter().all(|s| s.is_finite()) {
        return as_they_are();
    }
    // The shared inflation in the frame of a candidate at `pose`: diagonal
    // where measured, carried through the inversion otherwise.
    let in_frame = |pose: &Pose, inverted: bool| {
        let mut d = Cov6::zeros();
        for k in 0..3 {
            d[(k, k)] = shared[0];
            d[(k + 3, k + 3)] = shared[1];
        }
        if inverted {
            solver::invert(&PoseWithCovariance::new(pose.inverse(), d)).covariance
        } else {
            d
        }
    };
    let weighed = items
        .iter()
        .map(|(c, _, inverted)| {
            let own = c.covariance - in_frame(&c.a_from_b, *inverted);
            Some((c.a_from_b, crate::linalg::spd_inverse6(&own)?))
        })
        .collect::<Option<Vec<_>>>();
    let Some(weighed) = weighed else {
        return as_they_are();
    };
    let (pose, own) = fuse(&weighed)?;
    // Added back in the frame of the item the shared part came from.
    let (_, _, inverted) = items
        .iter()
        .min_by(|a, b| (a.1[0] + a.1[1]).total_cmp(&(b.1[0] + b.1[1])))?;
    let cov = own + in_frame(&pose, *inverted);
    Some((pose, (cov + cov.transpose()) * 0.5))
}

/// A group of a track being built: its index and its leader per hypothesis.
type OpenGroup = (usize, [Option<usize>; 2]);

/// Whether `c` agrees with a group's `leader`: its own information settles
/// the common case without a factorization, the summed covariances the rest.
fn consistent(c: &Candidate, leader: &Candidate, gate_chi2: f64) -> bool {
    let r = solver::difference(&c.a_from_b, &leader.a_from_b);
    (r.transpose() * c.information * r)[0] <= gate_chi2
        || consistency::mahalanobis2(
            &c.a_from_b,
            &c.covariance,
            &leader.a_from_b,
            &leader.covariance,
        ) <= gate_chi2
}

/// Groups of frames that are fused into one candidate per hypothesis before
/// the consistency checks.
///
/// A track is one camera's view of one marker ID ([`TrackKey`]). Within a
/// track, newest first, a frame joins the first group whose leaders (its
/// newest frame with each hypothesis) it is consistent with, hypothesis by
/// hypothesis (squared Mahalanobis distance under the summed covariances
/// within `gate_chi2`), and starts a new group otherwise. A flipped frame
/// (primary = the twin) thus never shares a group with unflipped ones, nor a
/// misread ID with the true owner of the marker, and the two hypotheses of
/// one group stay mutually exclusive exactly like those of one observation.
/// `fuse = false` gives one group per observation.
///
/// Motion: vehicles that manoeuvre change their relative pose by more than a
/// frame's noise within the window. A track whose newest frame no longer
/// agrees with an older group under any pairing of hypotheses (flips
/// excepted: a group that matches with the hypotheses swapped is kept) has
/// seen its target move: that older group is *superseded* and must not
/// outvote the present. Only frames of the same camera and marker can
/// supersede each other, so a misread ID or a flip never erases another
/// track's evidence.
pub(crate) fn group_tracks(
    frames: &[Frame],
    gate_chi2: f64,
    fuse: bool,
    threads: usize,
) -> TrackGroups {
    group_tracks_where(frames, gate_chi2, fuse, threads, |_| true)
}

/// [`group_tracks`] of the frames `take` keeps only (a frame's whole track
/// must be kept or left, as [`regroup_changed`] does).
fn group_tracks_where(
    frames: &[Frame],
    gate_chi2: f64,
    fuse: bool,
    threads: usize,
    take: impl Fn(usize) -> bool,
) -> TrackGroups {
    // Each track's frames, newest first (frames are in time order): a
    // group's leaders are its most recent frames, so it describes the
    // present. A frame without a primary hypothesis has nothing to compare
    // with: it stands alone.
    let mut groups: Vec<(Vec<usize>, bool)> = Vec::new();
    let mut tracks: BTreeMap<TrackKey, Vec<usize>> = BTreeMap::new();
    for (i, f) in frames.iter().enumerate().rev().filter(|(i, _)| take(*i)) {
        if f.hyps[0].is_none() {
            groups.push((vec![i], false));
        } else {
            tracks.entry(f.track).or_default().push(i);
        }
    }
    // Tracks are independent of each other: grouped on up to `threads`.
    let tracks: Vec<Vec<usize>> = tracks.into_values().collect();
    let per_track = crate::par::map(&tracks, threads, TRACKS_PER_THREAD, |_, track| {
        group_track(frames, track, gate_chi2, fuse)
    });
    groups.extend(per_track.into_iter().flatten());
    // Groups in ascending order of their first frame (each frame is in one
    // group, so the order is total), members ascending.
    groups.iter_mut().for_each(|(m, _)| m.sort_unstable());
    groups.sort_unstable_by_key(|(m, _)| m[0]);
    let (members, superseded) = groups.into_iter().unzip();
    TrackGroups {
        members,
        superseded,
    }
}

/// A group's members and whether it is superseded; a group's fits.
type GroupEntry = (Vec<usize>, bool);
type FitPair = [Option<super::motion::Fit>; 2];

/// The groups and their motion fits after some frames `changed` (their
/// covariances grown, [`super::frames::inflate_moving`]): the tracks with a
/// changed frame grouped and fitted again, every other group and fit kept as
/// it was (tracks are grouped and groups fitted independently, so the result
/// is the same, bit for bit, as grouping and fitting everything again).
pub(crate) fn regroup_changed(
    frames: &[Frame],
    old: (TrackGroups, super::motion::GroupFits),
    changed: &[bool],
    gate_chi2: f64,
    fuse: bool,
    fit: impl Fn(&TrackGroups) -> super::motion::GroupFits,
    threads: usize,
) -> (TrackGroups, super::motion::GroupFits) {
    // A frame without a primary hypothesis stands alone: regrouped when changed.
    let dirty: std::collections::BTreeSet<TrackKey> = frames
        .iter()
        .zip(changed)
        .filter(|(f, c)| **c && f.hyps[0].is_some())
        .map(|(f, _)| f.track)
        .collect();
    let redo = |i: usize| {
        if frames[i].hyps[0].is_some() {
            dirty.contains(&frames[i].track)
        } else {
            changed[i]
        }
    };
    let (old_groups, old_fits) = old;
    if dirty.is_empty() && !changed.iter().any(|c| *c) {
        return (old_groups, old_fits);
    }
    let new_groups = group_tracks_where(frames, gate_chi2, fuse, threads, redo);
    let new_fits = fit(&new_groups);
    // A group lies in one track (or is one frame): kept when its first frame is not redone.
    let kept = old_groups
        .members
        .into_iter()
        .zip(old_groups.superseded)
        .zip(old_fits)
        .filter(|((m, _), _)| !redo(m[0]));
    let fresh = new_groups
        .members
        .into_iter()
        .zip(new_groups.superseded)
        .zip(new_fits);
    let mut all: Vec<(GroupEntry, FitPair)> = kept.chain(fresh).collect();
    all.sort_unstable_by_key(|((m, _), _)| m[0]);
    let (groups, fits): (Vec<GroupEntry>, super::motion::GroupFits) = all.into_iter().unzip();
    let (members, superseded) = groups.into_iter().unzip();
    (
        TrackGroups {
            members,
            superseded,
        },
        fits,
    )
}

/// Tracks per thread at least ([`crate::par`]).
const TRACKS_PER_THREAD: usize = 64;

/// One track's groups (`track`: its frames newest first), each with its
/// members newest first and whether it is superseded ([`group_tracks`]).
fn group_track(
    frames: &[Frame],
    track: &[usize],
    gate_chi2: f64,
    fuse: bool,
) -> Vec<(Vec<usize>, bool)> {
    let mut groups: Vec<Vec<usize>> = Vec::new();
    let mut open: Vec<OpenGroup> = Vec::new();
    for &i in track {
        let f = &frames[i];
        let home = fuse
            .then(|| {
                open.iter_mut().find(|(_, leaders)| {
                    (0..2).all(|h| match (&f.hyps[h], leaders[h]) {
                        (Some(c), Some(l)) => frames[l].hyps[h]
                            .as_ref()
                            .is_some_and(|l| consistent(c, l, gate_chi2)),
                        _ => true,
                    })
                })
            })
            .flatten();
        match home {
            Some((g, leaders)) => {
                groups[*g].push(i);
                for h in 0..2 {
                    if leaders[h].is_none() && f.hyps[h].is_some() {
                        leaders[h] = Some(i);
                    }
                }
            }
            None => {
                open.push((groups.len(), [Some(i), f.hyps[1].as_ref().map(|_| i)]));
                groups.push(vec![i]);
            }
        }
    }
    let superseded = superseded_groups(frames, &groups, gate_chi2);
    groups.into_iter().zip(superseded).collect()
}

/// The motion rule of [`group_tracks`] on one track's groups (members still
/// newest first; group 0 holds the track's newest frame): per group, whether
/// that newest frame disagrees with it under every pairing of hypotheses.
fn superseded_groups(frames: &[Frame], groups: &[Vec<usize>], gate_chi2: f64) -> Vec<bool> {
    let mut superseded = vec![false; groups.len()];
    let Some(&latest) = groups.first().and_then(|g| g.first()) else {
        return superseded;
    };
    for (g, members) in groups.iter().enumerate().skip(1) {
        let Some(&last) = members.first() else {
            continue;
        };
        // Only the past is superseded: two frames of one instant (a
        // misread ID beside the marker itself) are for the consistency
        // checks to judge, not for the motion rule.
        if frames[last].stamp_ns >= frames[latest].stamp_ns {
            continue;
        }
        let agrees = frames[last].hyps.iter().flatten().any(|old| {
            frames[latest]
                .hyps
                .iter()
                .flatten()
                .any(|new| consistent(old, new, gate_chi2))
        });
        superseded[g] = !agrees;
    }
    superseded
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::testing::frame;
    use proto::geometry::pose_from_xyz_rpy;

    const GATE: f64 = 27.86;
    const FRAME_NS: u64 = 100_000_000;

    fn at(y: f64) -> Pose {
        pose_from_xyz_rpy([2.0, y, 0.0], [0.0, 0.0, 0.0])
    }

    #[test]
    fn agreeing_frames_of_a_track_form_one_group_fused_into_one_candidate() {
        let frames: Vec<Frame> = (0..3)
            .map(|k| frame(k, 1, 2, k as u64 * FRAME_NS, at(0.001 * k as f64), None))
            .collect();
        let g = group_tracks(&frames, GATE, true, 2);
        assert_eq!(g.members, vec![vec![0, 1, 2]]);
        assert_eq!(g.superseded, vec![false]);
        let c = g.candidate(&frames, 0, 0, &[]).unwrap();
        assert_eq!(c.weight, 3);
        // Three equal covariances: the fused one is a third of each.
        let single = frames[0].hyps[0].unwrap().covariance[(0, 0)];
        assert!((c.covariance[(0, 0)] - single / 3.0).abs() < 1e-12);
        assert!((c.a_from_b.translation.vector.y - 0.001).abs() < 1e-9);
        // Without two of its frames the group is the third one alone.
        let alone = g.candidate(&frames, 0, 0, &[0, 1]).unwrap();
        assert_eq!((alone.weight, alone.a_from_b), (1, at(0.002)));
    }

    #[test]
    fn a_track_whose_newest_frame_disagrees_is_split_and_its_past_superseded() {
        // Two frames at y = 0, then the target is 30 cm off (30σ): it moved.
        let frames = vec![
            frame(0, 1, 2, 0, at(0.0), None),
            frame(1, 1, 2, FRAME_NS, at(0.0), None),
            frame(2, 1, 2, 2 * FRAME_NS, at(0.3), None),
        ];
        let g = group_tracks(&frames, GATE, true, 2);
        assert_eq!(g.members, vec![vec![0, 1], vec![2]]);
        assert_eq!(g.superseded, vec![true, false]);
        assert_eq!(g.superseded_frames(3), vec![true, true, false]);
        // The same frames of another camera's track supersede nothing of this one.
        let mut other = frames[2].clone();
        other.track.camera = 1;
        let g = group_tracks(
            &[frames[0].clone(), frames[1].clone(), other],
            GATE,
            true,
            2,
        );
        assert_eq!(g.superseded, vec![false, false]);
    }

    #[test]
    fn a_flipped_frame_starts_its_own_group_but_does_not_supersede() {
        let (truth, twin) = (at(0.0), pose_from_xyz_rpy([2.0, 0.0, 0.0], [0.0, 0.8, 0.0]));
        let frames = vec![
            frame(0, 1, 2, 0, truth, Some(twin)),
            frame(1, 1, 2, FRAME_NS, twin, Some(truth)),
        ];
        let g = group_tracks(&frames, GATE, true, 2);
        assert_eq!(g.members, vec![vec![0], vec![1]]);
        assert_eq!(
            g.superseded,
            vec![false, false],
            "matches with hypotheses swapped"
        );
        // The observer being the pair's `b`, the candidate is inverted.
        let back = vec![frame(0, 2, 1, 0, truth, None)];
        let g = group_tracks(&back, GATE, true, 2);
        let c = g.candidate(&back, 0, 0, &[]).unwrap();
        assert!((c.a_from_b.translation.vector.x + 2.0).abs() < 1e-12);
    }

    #[test]
    fn a_moving_pair_is_fused_as_of_its_freshest_frame_and_inversion_changes_nothing() {
        // Frames 1.5, 1.0 and 0.5 s old (σ 1 mm each) of a pair moving 10
        // cm/s along y, each inflated by its age at 2 cm/√s: weighed as
        // independent errors the mean trails the freshest frame by ~2 cm;
        // as of the freshest, the older frames (now 1 s and 0.5 s of motion
        // away from it) hardly pull.
        let q = 0.02f64 * 0.02;
        let raw = 1e-6;
        let cands: Vec<(Candidate, [f64; 2])> = [(1.5, 0.0), (1.0, 0.05), (0.5, 0.10)]
            .iter()
            .enumerate()
            .map(|(k, &(age, y))| {
                let mut cov = Cov6::identity() * raw;
                for i in 0..6 {
                    cov[(i, i)] += age * q;
                }
                (
                    Candidate::new(k, 0, at(y), cov).unwrap(),
                    [age * q, age * q],
                )
            })
            .collect();
        let items: Vec<(&Candidate, [f64; 2], bool)> =
            cands.iter().map(|(c, i)| (c, *i, false)).collect();
        let (pose, cov) = fuse_sharing_inflation(&items, false).unwrap();
        let y = pose.translation.vector.y;
        assert!((y - 0.10).abs() < 1e-3, "{y}");
        // Its covariance: the freshest frame's own (nearly all the weight)
        // plus the 0.5 s of motion since, counted once.
        let want = raw + 0.5 * q;
        assert!(
            (cov[(1, 1)] - want).abs() < 0.05 * want,
            "{} vs {want}",
            cov[(1, 1)]
        );
        let plain: Vec<(Pose, Cov6)> = cands
            .iter()
            .map(|(c, _)| (c.a_from_b, c.information))
            .collect();
        let (trailing, _) = consistency::fuse(&plain).unwrap();
        assert!(
            (trailing.translation.vector.y - 0.10).abs() > 0.015,
            "the old weighing trails"
        );
        // The same frames measured by the pair's other vehicle: the inverse
        // of the same estimate.
        let inverted: Vec<Candidate> = cands
            .iter()
            .map(|(c, _)| {
                let m = solver::invert(&PoseWithCovariance::new(c.a_from_b, c.covariance));
                Candidate::new(c.observation, 0, m.pose, m.covariance).unwrap()
            })
            .collect();
        let items: Vec<(&Candidate, [f64; 2], bool)> = inverted
            .iter()
            .zip(&cands)
            .map(|(c, (_, i))| (c, *i, true))
            .collect();
        let (back, back_cov) = fuse_sharing_inflation(&items, false).unwrap();
        let e = proto::geometry::difference(&back.inverse(), &pose);
        assert!(e.norm() < 1e-6, "{e}");
        let again = solver::invert(&PoseWithCovariance::new(back, back_cov)).covariance;
        assert!((again - cov).norm() < 1e-3 * cov.norm(), "{again} vs {cov}");
        // Nothing shared (the freshest frame taken now): the weighing as before.
        let fresh: Vec<(Candidate, [f64; 2])> = cands
            .iter()
            .map(|(c, i)| {
                let mut cov = c.covariance;
                for k in 0..6 {
                    cov[(k, k)] -= 0.5 * q;
                }
                (
                    Candidate::new(c.observation, 0, c.a_from_b, cov).unwrap(),
                    [i[0] - 0.5 * q, i[1] - 0.5 * q],
                )
            })
            .collect();
        let items: Vec<(&Candidate, [f64; 2], bool)> =
            fresh.iter().map(|(c, i)| (c, *i, false)).collect();
        let plain: Vec<(Pose, Cov6)> = fresh
            .iter()
            .map(|(c, _)| (c.a_from_b, c.information))
            .collect();
        assert_eq!(
            fuse_sharing_inflation(&items, false),
            consistency::fuse(&plain)
        );
    }

    #[test]
    fn regrouping_the_changed_tracks_only_gives_what_regrouping_all_gives() {
        use crate::solve::motion::{fit_groups, MotionModel};
        // Three tracks of observer 1, interleaved in time: 2 moving 3 cm a
        // frame (split into groups by its motion), 3 still, 4 with a frame
        // that has no primary (standing alone) and a flip.
        let mut frames = Vec::new();
        for k in 0..6 {
            let t = k as u64 * FRAME_NS;
            let n = frames.len();
            frames.push(frame(n, 1, 2, t, at(0.03 * k as f64), None));
            frames.push(frame(n + 1, 1, 3, t, at(0.5), None));
            let mut f = frame(n + 2, 1, 4, t, at(-0.5), Some(at(-0.4)));
            if k == 2 {
                f.hyps[0] = None;
            }
            frames.push(f);
        }
        let model = MotionModel::default();
        let fit = |fr: &[Frame], g: &TrackGroups| fit_groups(fr, g, &model, 2);
        let before = group_tracks(&frames, GATE, true, 2);
        let before_fits = fit(&frames, &before);
        assert_eq!(before.members.len(), 5, "{:?}", before.members);
        // Track 2's frames and the lone frame grown, as a pair seen to move would be.
        let mut changed = vec![false; frames.len()];
        for (i, f) in frames.iter_mut().enumerate() {
            if f.track.marker == 2 || f.hyps[0].is_none() {
                for h in f.hyps.iter_mut().flatten() {
                    let mut cov = h.covariance;
                    for d in 0..3 {
                        cov[(d, d)] += 1e-3;
                    }
                    *h = Candidate::new(h.observation, h.hypothesis, h.a_from_b, cov).unwrap();
                }
                changed[i] = true;
            }
        }
        let all = group_tracks(&frames, GATE, true, 2);
        let all_fits = fit(&frames, &all);
        // The premise: track 2's groups change with its covariances.
        assert_ne!(all.members, before.members);
        let (g, fits) = regroup_changed(
            &frames,
            (before, before_fits),
            &changed,
            GATE,
            true,
            |g| fit(&frames, g),
            2,
        );
        assert_eq!(g.members, all.members);
        assert_eq!(g.superseded, all.superseded);
        assert_eq!(fits, all_fits);
    }

    #[test]
    fn without_fusion_every_frame_is_its_own_group() {
        let frames: Vec<Frame> = (0..3)
            .map(|k| frame(k, 1, 2, k as u64 * FRAME_NS, at(0.0), None))
            .collect();
        let g = group_tracks(&frames, GATE, false, 2);
        assert_eq!(g.members, vec![vec![0], vec![1], vec![2]]);
    }
}
