//! Step 3 of the solve: which hypothesis of which track group enters the
//! pose graph. Per vehicle pair the groups' candidates are clustered
//! (mutually consistent, PCM-style), the clusters vote in consistent
//! triangles, and a spanning tree grown from the reference picks one cluster
//! per pair ([`consistency`]). Every frame inherits its group's verdict.

use super::frames::Frame;
use super::groups::TrackGroups;
use crate::consistency::{self, Candidate, ConsistencyParams, PairCandidates, Prior, Selection};
use proto::geometry::{Cov6, Pose};
use proto::VehicleId;
use std::collections::BTreeMap;

/// The outcome of the consistency checks.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Hypotheses {
    /// Every pair's group candidates and clusters (with their votes).
    pub pairs: Vec<PairCandidates>,
    /// The chosen cluster per pair, and the spanning trees.
    pub selection: Selection,
    /// Accepted frame hypotheses: (frame, hypothesis) → pair index.
    pub accepted: BTreeMap<(usize, u8), usize>,
    /// Per pair, the accepted group candidates: (group, hypothesis, candidate index).
    pub accepted_groups: Vec<Vec<(usize, u8, usize)>>,
}

/// Every pair's candidates, one per group and hypothesis (superseded groups
/// left out), with their clusters and triangle votes.
pub(crate) fn pair_candidates(
    frames: &[Frame],
    groups: &TrackGroups,
    params: &ConsistencyParams,
    threads: usize,
) -> Vec<PairCandidates> {
    // Each group's fused candidates (independent: on up to `threads`), then
    // gathered per pair in group order.
    let per_group = crate::par::map(&groups.members, threads, 64, |g, _| {
        let h = |h: u8| groups.candidate(frames, g, h, &[]);
        if groups.superseded[g] {
            [None, None]
        } else {
            [h(0), h(1)]
        }
    });
    let mut by_pair: BTreeMap<(VehicleId, VehicleId), Vec<Candidate>> = BTreeMap::new();
    for (members, cands) in groups.members.iter().zip(per_group) {
        for c in cands.into_iter().flatten() {
            by_pair
                .entry(frames[members[0]].pair())
                .or_default()
                .push(c);
        }
    }
    let by_pair: Vec<((VehicleId, VehicleId), Vec<Candidate>)> = by_pair.into_iter().collect();
    let clusters = crate::par::map(&by_pair, threads, 16, |_, (_, candidates)| {
        consistency::cluster_pair(candidates, params)
    });
    let mut pairs: Vec<PairCandidates> = by_pair
        .into_iter()
        .zip(clusters)
        .map(|(((a, b), candidates), clusters)| PairCandidates {
            a,
            b,
            candidates,
            clusters,
        })
        .collect();
    consistency::vote_triangles_threads(&mut pairs, params.gate_chi2, threads);
    pairs
}

/// The previous solution's relative attitude of every pair in `pairs` whose
/// two vehicles were fused within the window (`last_estimate`: pose,
/// covariance and last-seen stamp per vehicle), with the turn allowed since:
/// 8° plus 30°/s of age, at most 30° (planar-flip twins of a marker seen
/// obliquely are tens of degrees apart).
pub(crate) fn attitude_prior(
    last_estimate: &BTreeMap<VehicleId, (Pose, Cov6, u64)>,
    pairs: &[PairCandidates],
    now_ns: u64,
    window_ns: u64,
) -> Prior {
    let mut prior = Prior::new();
    for p in pairs {
        let (Some(a), Some(b)) = (last_estimate.get(&p.a), last_estimate.get(&p.b)) else {
            continue;
        };
        let seen = a.2.min(b.2);
        let age_ns = now_ns.saturating_sub(seen);
        if age_ns > window_ns {
            continue;
        }
        let tol = (8.0 + 30.0 * age_ns as f64 * 1e-9).min(30.0).to_radians();
        prior.insert((p.a, p.b), (a.0.inverse() * b.0, tol));
    }
    prior
}

/// The spanning-tree selection over `pairs` from `reference`, and the frames
/// it accepts: every frame of an accepted group candidate that has the
/// candidate's hypothesis.
pub(crate) fn choose(
    pairs: Vec<PairCandidates>,
    frames: &[Frame],
    groups: &TrackGroups,
    reference: VehicleId,
    gate_chi2: f64,
    prior: &Prior,
) -> Hypotheses {
    let selection = consistency::select_with_prior(&pairs, reference, gate_chi2, prior);
    // Collected, then built in one go from the sorted keys (thousands of
    // single inserts into the tree were a twentieth of a 100-vehicle solve).
    let mut accepted: Vec<((usize, u8), usize)> = Vec::new();
    let mut accepted_groups: Vec<Vec<(usize, u8, usize)>> = vec![Vec::new(); pairs.len()];
    for (pi, p) in pairs.iter().enumerate() {
        if let Some(c) = selection.choice[pi] {
            for &m in &p.clusters[c].members {
                let cand = &p.candidates[m];
                let h = cand.hypothesis;
                accepted_groups[pi].push((cand.observation, h, m));
                for &i in &groups.members[cand.observation] {
                    if frames[i].hyps[usize::from(h)].is_some() {
                        accepted.push(((i, h), pi));
                    }
                }
            }
        }
    }
    accepted.sort_by_key(|(k, _)| *k);
    Hypotheses {
        pairs,
        selection,
        accepted: accepted.into_iter().collect(),
        accepted_groups,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::groups::group_tracks;
    use crate::solve::testing::frame;
    use proto::geometry::pose_from_xyz_rpy;

    const GATE: f64 = 27.86;

    #[test]
    fn frames_inherit_their_groups_verdict_and_the_flip_twin_is_left_out() {
        let truth = pose_from_xyz_rpy([2.0, 0.0, 0.0], [0.0, 0.0, 0.0]);
        let twin = pose_from_xyz_rpy([2.0, 0.0, 0.0], [0.0, 0.8, 0.0]);
        // Vehicle 1 sees 2 three times (true primary, flip as alternative);
        // 2 sees 1 once, which agrees with the primaries.
        let frames = vec![
            frame(0, 1, 2, 0, truth, Some(twin)),
            frame(1, 1, 2, 100_000_000, truth, Some(twin)),
            frame(2, 1, 2, 200_000_000, truth, Some(twin)),
            frame(3, 2, 1, 200_000_000, truth.inverse(), None),
        ];
        let groups = group_tracks(&frames, GATE, true, 2);
        assert_eq!(groups.members, vec![vec![0, 1, 2], vec![3]]);
        let pairs = pair_candidates(&frames, &groups, &ConsistencyParams::default(), 2);
        assert_eq!(pairs.len(), 1);
        assert_eq!(
            pairs[0].candidates.len(),
            3,
            "two hypotheses of one group, one of the other"
        );
        let h = choose(pairs, &frames, &groups, 1, GATE, &Prior::new());
        let accepted: Vec<(usize, u8)> = h.accepted.keys().copied().collect();
        assert_eq!(accepted, vec![(0, 0), (1, 0), (2, 0), (3, 0)]);
        assert_eq!(h.accepted_groups[0].len(), 2);
        assert!(h.selection.trees[0].contains(2));
    }

    #[test]
    fn the_attitude_prior_allows_more_turn_with_age_and_forgets_beyond_the_window() {
        let p = |yaw: f64| pose_from_xyz_rpy([0.0, 0.0, 0.0], [0.0, 0.0, yaw]);
        let last = BTreeMap::from([
            (1, (p(0.0), Cov6::zeros(), 1_000_000_000)),
            (2, (p(0.3), Cov6::zeros(), 2_000_000_000)),
        ]);
        let pair = PairCandidates {
            a: 1,
            b: 2,
            candidates: vec![],
            clusters: vec![],
        };
        // Seen 0.5 s ago (the older of the two): 8° + 15°.
        let prior = attitude_prior(
            &last,
            std::slice::from_ref(&pair),
            1_500_000_000,
            2_000_000_000,
        );
        let (rel, tol) = prior[&(1, 2)];
        assert!((tol - 23f64.to_radians()).abs() < 1e-12);
        assert!((rel.rotation.angle() - 0.3).abs() < 1e-12);
        // 1.5 s ago: capped at 30°; 2.5 s ago: beyond the window, no prior.
        let prior = attitude_prior(
            &last,
            std::slice::from_ref(&pair),
            2_500_000_000,
            2_000_000_000,
        );
        assert!((prior[&(1, 2)].1 - 30f64.to_radians()).abs() < 1e-12);
        assert!(attitude_prior(&last, &[pair], 3_500_000_000, 2_000_000_000).is_empty());
    }
}
