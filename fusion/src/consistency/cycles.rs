//! Step 2 of the consistency checks: votes of consistent triangles of pairs.

use super::{compose_variance_bound, mahalanobis2, trace6, PairCandidates};
use crate::solver::{compose, difference};
use proto::geometry::PoseWithCovariance;
use proto::VehicleId;
use std::collections::{BTreeMap, BTreeSet};

/// Step 2: votes from consistent triangles (see the module docs). `pairs` must
/// have `a < b` and be unique per pair.
pub fn vote_triangles(pairs: &mut [PairCandidates], gate_chi2: f64) {
    vote_triangles_threads(pairs, gate_chi2, 1);
}

/// [`vote_triangles`] with the triangles checked on up to `threads` threads
/// (the votes are the same at any count).
pub fn vote_triangles_threads(pairs: &mut [PairCandidates], gate_chi2: f64, threads: usize) {
    let index: BTreeMap<(VehicleId, VehicleId), usize> = pairs
        .iter()
        .enumerate()
        .map(|(i, p)| ((p.a, p.b), i))
        .collect();
    let mut neighbours: BTreeMap<VehicleId, BTreeSet<VehicleId>> = BTreeMap::new();
    for p in pairs.iter() {
        neighbours.entry(p.a).or_default().insert(p.b);
        neighbours.entry(p.b).or_default().insert(p.a);
    }
    // Every triangle (a < b < k) as its pairs' indices (ab, bk, ak).
    let mut triangles: Vec<[usize; 3]> = Vec::new();
    for (&(a, b), &ab) in &index {
        let (Some(na), Some(nb)) = (neighbours.get(&a), neighbours.get(&b)) else {
            continue;
        };
        for &k in na.intersection(nb).filter(|&&k| k > b) {
            triangles.push([ab, index[&(b, k)], index[&(a, k)]]);
        }
    }
    let shared: &[PairCandidates] = pairs;
    let hits = crate::par::map(&triangles, threads, 64, |_, &t| {
        triangle_hits(shared, t, gate_chi2)
    });
    let mut votes: Vec<Vec<[usize; 2]>> = pairs
        .iter()
        .map(|p| vec![[0; 2]; p.clusters.len()])
        .collect();
    for (t, hit) in triangles.iter().zip(hits) {
        for (&p, hits) in t.iter().zip(hit) {
            for (c, h) in hits.into_iter().enumerate() {
                match h {
                    Hit::Repeated => votes[p][c][0] += 1,
                    Hit::Single => votes[p][c][1] += 1,
                    Hit::None => {}
                }
            }
        }
    }
    for (p, v) in pairs.iter_mut().zip(votes) {
        for (c, n) in p.clusters.iter_mut().zip(v) {
            (c.votes, c.weak_votes) = (n[0], n[1]);
        }
    }
}

/// Frames a cluster must stand for to give a full vote in a cycle. A single
/// frame is as likely a misread ID (whose pose is that of the neighbour
/// actually seen) as a true view, and a misread neighbour closes a triangle
/// with that neighbour's own pairs by construction; with a single frame's
/// wide covariance it also closes them with planar flips (the realistic
/// camera's 1 000-vehicle fleet, seed 4: a flip cluster of 11 frames voted in
/// by one such triangle placed a vehicle 1.4 m / 40° off). Cycles through a
/// single frame still give a *weak* vote ([`Cluster::weak_votes`]), which
/// only settles clusters of equal support: right after a window opens every
/// pair has one frame, and they are all the evidence there is.
const MIN_VOTING_FRAMES: usize = 2;

/// How a cluster took part in a triangle: in a consistent cycle whose
/// clusters all stand for repeated frames, only in ones through a single
/// frame, or in none.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Hit {
    None,
    Single,
    Repeated,
}

/// Which clusters of the triangle's pairs `[ab, bk, ak]` close a consistent
/// cycle with some clusters of the other two, and how ([`Hit`]).
fn triangle_hits(
    pairs: &[PairCandidates],
    [ab, bk, ak]: [usize; 3],
    gate_chi2: f64,
) -> [Vec<Hit>; 3] {
    let mut hit_ab = vec![Hit::None; pairs[ab].clusters.len()];
    let mut hit_bk = vec![Hit::None; pairs[bk].clusters.len()];
    let mut hit_ak = vec![Hit::None; pairs[ak].clusters.len()];
    for (i, c_ab) in pairs[ab].clusters.iter().enumerate() {
        for (j, c_bk) in pairs[bk].clusters.iter().enumerate() {
            let pose = c_ab.a_from_b * c_bk.a_from_b;
            let bound = compose_variance_bound(&c_ab.covariance, &c_bk.a_from_b, &c_bk.covariance);
            let mut composed: Option<PoseWithCovariance> = None;
            for (l, c_ak) in pairs[ak].clusters.iter().enumerate() {
                let r = difference(&pose, &c_ak.a_from_b);
                if r.norm_squared() > gate_chi2 * (bound + trace6(&c_ak.covariance)) {
                    continue;
                }
                let composed = composed.get_or_insert_with(|| {
                    compose(
                        &PoseWithCovariance::new(c_ab.a_from_b, c_ab.covariance),
                        &PoseWithCovariance::new(c_bk.a_from_b, c_bk.covariance),
                    )
                });
                let d2 = mahalanobis2(
                    &composed.pose,
                    &composed.covariance,
                    &c_ak.a_from_b,
                    &c_ak.covariance,
                );
                if d2 <= gate_chi2 {
                    let repeated = [c_ab, c_bk, c_ak]
                        .iter()
                        .all(|c| c.frames >= MIN_VOTING_FRAMES);
                    let hit = if repeated { Hit::Repeated } else { Hit::Single };
                    hit_ab[i] = hit_ab[i].max(hit);
                    hit_bk[j] = hit_bk[j].max(hit);
                    hit_ak[l] = hit_ak[l].max(hit);
                }
            }
        }
    }
    [hit_ab, hit_bk, hit_ak]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::consistency::{cluster_pair, select};
    use crate::consistency::{Candidate, ConsistencyParams};
    use proto::geometry::{pose_from_xyz_rpy, Cov6, Pose};

    fn cand(obs: usize, hyp: u8, p: Pose) -> Candidate {
        Candidate::new(obs, hyp, p, Cov6::identity() * 1e-4).unwrap()
    }

    /// The triangle 1–2–3 with pair 1–3's primary flipped (its alternative
    /// true), every candidate standing for `frames` frames.
    fn flipped_triangle(frames: usize) -> Vec<PairCandidates> {
        let truth =
            |v: u32| pose_from_xyz_rpy([v as f64, 0.5 * v as f64, 0.0], [0.0, 0.0, 0.1 * v as f64]);
        let rel = |a: u32, b: u32| truth(a).inverse() * truth(b);
        let twin = pose_from_xyz_rpy([0.0, 0.0, 0.0], [0.6, 0.0, 0.0]);
        let c = |obs: usize, hyp: u8, p: Pose| cand(obs, hyp, p).with_weight(frames);
        let mut pairs = vec![
            PairCandidates {
                a: 1,
                b: 2,
                candidates: vec![c(0, 0, rel(1, 2))],
                clusters: vec![],
            },
            PairCandidates {
                a: 2,
                b: 3,
                candidates: vec![c(1, 0, rel(2, 3))],
                clusters: vec![],
            },
            // Flipped primary, true alternative.
            PairCandidates {
                a: 1,
                b: 3,
                candidates: vec![c(2, 0, twin * rel(1, 3)), c(2, 1, rel(1, 3))],
                clusters: vec![],
            },
        ];
        for p in &mut pairs {
            p.clusters = cluster_pair(&p.candidates, &ConsistencyParams::default());
        }
        pairs
    }

    #[test]
    fn triangle_votes_pick_the_consistent_flip() {
        let mut pairs = flipped_triangle(2);
        vote_triangles(&mut pairs, 27.86);
        let votes = |p: &PairCandidates, h: u8| {
            let c = p
                .clusters
                .iter()
                .find(|c| p.candidates[c.members[0]].hypothesis == h);
            c.map(|c| c.votes)
        };
        assert_eq!(
            (votes(&pairs[2], 0), votes(&pairs[2], 1)),
            (Some(0), Some(1))
        );
        assert_eq!(
            (pairs[0].clusters[0].votes, pairs[1].clusters[0].votes),
            (1, 1)
        );
        let sel = select(&pairs, 1, 27.86);
        let chosen = &pairs[2].clusters[sel.choice[2].unwrap()];
        assert_eq!(pairs[2].candidates[chosen.members[0]].hypothesis, 1);
    }

    #[test]
    fn cycles_through_a_single_frame_give_only_weak_votes() {
        let mut pairs = flipped_triangle(1);
        vote_triangles(&mut pairs, 27.86);
        assert!(pairs.iter().flat_map(|p| &p.clusters).all(|c| c.votes == 0));
        let weak: Vec<usize> = pairs[2].clusters.iter().map(|c| c.weak_votes).collect();
        assert_eq!(weak.iter().sum::<usize>(), 1, "{weak:?}");
        // Among clusters of equal support, the weak vote still picks the truth.
        let sel = select(&pairs, 1, 27.86);
        let chosen = &pairs[2].clusters[sel.choice[2].unwrap()];
        assert_eq!(pairs[2].candidates[chosen.members[0]].hypothesis, 1);
    }
}
