//! Step 4 of the solve: the pose graph to optimize, from the consistency
//! checks' choice. One fused constraint per chosen pair inside the
//! reference's spanning tree (its accepted groups, each without the frames
//! the chi-square gate has rejected so far), the vehicles connected to the
//! reference by them, and their initial poses from the spanning tree.

use super::frames::Frame;
use super::groups::TrackGroups;
use super::hypotheses::Hypotheses;
use crate::consistency::Candidate;
use crate::solver::Constraint;
use proto::geometry::Pose;
use proto::VehicleId;
use std::collections::{BTreeMap, BTreeSet};

/// The input of the Levenberg–Marquardt solve.
#[derive(Debug, Clone, Default, PartialEq)]
pub(crate) struct Graph {
    /// Constraints among vehicles connected to the reference.
    pub constraints: Vec<Constraint>,
    /// `reference_from_vehicle` from the spanning tree, per connected vehicle.
    pub initial: BTreeMap<VehicleId, Pose>,
}

/// The graph of [`Hypotheses`] without the hypotheses in `gated`
/// ((frame, hypothesis) pairs).
pub(crate) fn graph(
    hyps: &Hypotheses,
    groups: &TrackGroups,
    frames: &[Frame],
    gated: &BTreeSet<(usize, u8)>,
    reference: VehicleId,
    threads: usize,
) -> Graph {
    let tree = &hyps.selection.trees[0];
    // One constraint per pair, independent: on up to `threads`.
    let per_pair = crate::par::map(&hyps.pairs, threads, 32, |pi, p| {
        // Pairs without a chosen cluster give no constraint.
        hyps.selection.choice[pi]?;
        if !tree.contains(p.a) || !tree.contains(p.b) {
            return None;
        }
        // The accepted groups of the pair, each without its gated frames,
        // with the inflation its candidate carries (its freshest frame's)
        // and whether it was measured by `b`.
        let items: Vec<(Candidate, [f64; 2], bool)> = hyps.accepted_groups[pi]
            .iter()
            .filter_map(|&(g, h, m)| {
                let out: Vec<usize> = groups.members[g]
                    .iter()
                    .copied()
                    .filter(|&i| gated.contains(&(i, h)))
                    .collect();
                let cand = if out.is_empty() {
                    Some(p.candidates[m])
                } else {
                    groups.candidate(frames, g, h, &out)
                }?;
                let used = groups.members[g]
                    .iter()
                    .filter(|&&i| !out.contains(&i) && frames[i].hyps[usize::from(h)].is_some());
                let inflation = used.fold([f64::INFINITY; 2], |m, &i| {
                    let f = frames[i].inflation;
                    [m[0].min(f[0]), m[1].min(f[1])]
                });
                let inverted = frames[groups.members[g][0]].observer != p.a;
                Some((cand, inflation, inverted))
            })
            .collect();
        let refs: Vec<(&Candidate, [f64; 2], bool)> =
            items.iter().map(|(c, i, inv)| (c, *i, *inv)).collect();
        let (pose, cov) = super::groups::fuse_sharing_inflation(&refs, false)?;
        Some(Constraint {
            a: p.a,
            b: p.b,
            a_from_b: pose,
            covariance: cov,
        })
    });
    let mut constraints: Vec<Constraint> = per_pair.into_iter().flatten().collect();
    let connected = connected_to(reference, &constraints);
    constraints.retain(|c| connected.contains(&c.a));
    let initial = tree
        .poses()
        .into_iter()
        .filter(|(v, _)| connected.contains(v))
        .collect();
    Graph {
        constraints,
        initial,
    }
}

/// Vehicles reachable from `root` through `constraints`.
fn connected_to(root: VehicleId, constraints: &[Constraint]) -> BTreeSet<VehicleId> {
    let mut seen = BTreeSet::from([root]);
    loop {
        let before = seen.len();
        for c in constraints {
            if seen.contains(&c.a) || seen.contains(&c.b) {
                seen.insert(c.a);
                seen.insert(c.b);
            }
        }
        if seen.len() == before {
            return seen;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::consistency::{ConsistencyParams, Prior};
    use crate::solve::groups::group_tracks;
    use crate::solve::hypotheses::{choose, pair_candidates};
    use crate::solve::testing::frame;
    use proto::geometry::pose_from_xyz_rpy;

    const GATE: f64 = 27.86;

    fn hypotheses(frames: &[Frame]) -> (TrackGroups, Hypotheses) {
        let groups = group_tracks(frames, GATE, true, 2);
        let pairs = pair_candidates(frames, &groups, &ConsistencyParams::default(), 2);
        let h = choose(pairs, frames, &groups, 1, GATE, &Prior::new());
        (groups, h)
    }

    #[test]
    fn a_gated_frame_leaves_its_pairs_constraint() {
        let near = pose_from_xyz_rpy([2.0, 0.0, 0.0], [0.0, 0.0, 0.0]);
        let off = pose_from_xyz_rpy([2.0, 0.02, 0.0], [0.0, 0.0, 0.0]);
        let frames = vec![
            frame(0, 1, 2, 0, near, None),
            frame(1, 1, 2, 100_000_000, off, None),
        ];
        let (groups, h) = hypotheses(&frames);
        let all = graph(&h, &groups, &frames, &BTreeSet::new(), 1, 2);
        assert_eq!(all.constraints.len(), 1);
        let y = all.constraints[0].a_from_b.translation.vector.y;
        assert!((y - 0.01).abs() < 1e-9, "the mean of both: {y}");
        let without = graph(&h, &groups, &frames, &BTreeSet::from([(1, 0)]), 1, 2);
        let e = proto::geometry::difference(&without.constraints[0].a_from_b, &near);
        assert!(e.norm() < 1e-12, "the first frame alone: {e}");
        assert_eq!(
            without.initial.keys().copied().collect::<Vec<_>>(),
            vec![1, 2]
        );
    }

    #[test]
    fn vehicles_not_connected_to_the_reference_are_left_out() {
        let p = pose_from_xyz_rpy([2.0, 0.0, 0.0], [0.0, 0.0, 0.0]);
        // 1–2 seen; 3–4 seen only by each other.
        let frames = vec![frame(0, 1, 2, 0, p, None), frame(1, 3, 4, 0, p, None)];
        let (groups, h) = hypotheses(&frames);
        assert_eq!(
            h.selection.trees.len(),
            2,
            "a second tree grows from vehicle 3"
        );
        let g = graph(&h, &groups, &frames, &BTreeSet::new(), 1, 2);
        assert_eq!(g.constraints.len(), 1);
        assert_eq!((g.constraints[0].a, g.constraints[0].b), (1, 2));
        assert_eq!(g.initial.keys().copied().collect::<Vec<_>>(), vec![1, 2]);
        assert!(proto::geometry::difference(&g.initial[&2], &p).norm() < 1e-12);
    }
}
