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
    pub fn candidate(
        &self,
        frames: &[Frame],
        g: usize,
        h: u8,
        without: &[usize],
    ) -> Option<Candidate> {
        let members = &self.members[g];
        let hyp: Vec<&Candidate> = members
            .iter()
            .filter(|i| !without.contains(i))
            .filter_map(|&i| frames[i].hyps[usize::from(h)].as_ref())
            .collect();
        let (pose, cov) = match hyp.as_slice() {
            [] => return None,
            [one] => (one.a_from_b, one.covariance),
            many => {
                let items: Vec<(Pose, Cov6)> =
                    many.iter().map(|c| (c.a_from_b, c.information)).collect();
                consistency::fuse_close(&items)?
            }
        };
        let f = &frames[members[0]];
        if let ([one], true) = (hyp.as_slice(), f.observer < f.target) {
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
        Candidate::new(g, h, a_from_b.pose, a_from_b.covariance).map(|c| c.with_weight(hyp.len()))
    }
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
    // Each track's frames, newest first (frames are in time order): a
    // group's leaders are its most recent frames, so it describes the
    // present. A frame without a primary hypothesis has nothing to compare
    // with: it stands alone.
    let mut groups: Vec<(Vec<usize>, bool)> = Vec::new();
    let mut tracks: BTreeMap<TrackKey, Vec<usize>> = BTreeMap::new();
    for (i, f) in frames.iter().enumerate().rev() {
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
    fn without_fusion_every_frame_is_its_own_group() {
        let frames: Vec<Frame> = (0..3)
            .map(|k| frame(k, 1, 2, k as u64 * FRAME_NS, at(0.0), None))
            .collect();
        let g = group_tracks(&frames, GATE, false, 2);
        assert_eq!(g.members, vec![vec![0], vec![1], vec![2]]);
    }
}
