//! Step 1 of the consistency checks: the clusters of one pair's candidates,
//! maximum cliques of their pairwise consistency graph.

use super::{
    consistent_with, fuse_members, mahalanobis2, primary_frames, Candidate, Cluster,
    ConsistencyParams,
};
use proto::geometry::{Cov6, Pose};
use std::cmp::Reverse;
use std::collections::BTreeSet;

/// Maximum-weight clique: weight `frames·(W+1) + primary frames` (`W` the
/// total weight), so supporting frames first, then primary hypotheses. Exact
/// branch-and-bound; `None` when `budget` nodes are exceeded.
fn exact_clique(adj: &[Vec<bool>], weight: &[(usize, usize)], budget: usize) -> Option<Vec<usize>> {
    struct Search<'a> {
        adj: &'a [Vec<bool>],
        weight: &'a [(usize, usize)],
        scale: usize,
        best: Vec<usize>,
        best_score: usize,
        nodes: usize,
        budget: usize,
    }
    impl Search<'_> {
        fn score(&self, set: &[usize]) -> usize {
            set.iter()
                .map(|&i| self.weight[i].0 * self.scale + self.weight[i].1)
                .sum()
        }
        fn expand(&mut self, r: &mut Vec<usize>, p: &[usize]) -> bool {
            self.nodes += 1;
            if self.nodes > self.budget {
                return false;
            }
            let rs = self.score(r);
            if rs > self.best_score {
                self.best_score = rs;
                self.best = r.clone();
            }
            for (k, &v) in p.iter().enumerate() {
                let rest = &p[k..];
                if rs + self.score(rest) <= self.best_score {
                    return true;
                }
                let next: Vec<usize> = p[k + 1..]
                    .iter()
                    .copied()
                    .filter(|&u| self.adj[v][u])
                    .collect();
                r.push(v);
                let ok = self.expand(r, &next);
                r.pop();
                if !ok {
                    return false;
                }
            }
            true
        }
    }
    let m = adj.len();
    let mut s = Search {
        adj,
        weight,
        scale: weight.iter().map(|w| w.0).sum::<usize>() + 1,
        best: Vec::new(),
        best_score: 0,
        nodes: 0,
        budget,
    };
    // High-degree vertices first finds a big clique early, so the bound prunes.
    let mut order: Vec<usize> = (0..m).collect();
    order.sort_by_key(|&i| (Reverse(adj[i].iter().filter(|&&x| x).count()), i));
    let ok = s.expand(&mut Vec::new(), &order);
    ok.then_some(s.best)
}

/// Greedy clique from every start vertex, best weight kept.
fn greedy_clique(adj: &[Vec<bool>], weight: &[(usize, usize)]) -> Vec<usize> {
    let m = adj.len();
    let scale = weight.iter().map(|w| w.0).sum::<usize>() + 1;
    let score =
        |set: &[usize]| -> usize { set.iter().map(|&i| weight[i].0 * scale + weight[i].1).sum() };
    let mut order: Vec<usize> = (0..m).collect();
    order.sort_by_key(|&i| (Reverse(adj[i].iter().filter(|&&x| x).count()), i));
    let mut best: Vec<usize> = Vec::new();
    for &start in &order {
        let mut clique = vec![start];
        for &v in &order {
            if v != start && clique.iter().all(|&u| adj[u][v]) {
                clique.push(v);
            }
        }
        if score(&clique) > score(&best) {
            best = clique;
        }
    }
    best
}

/// Step 1 for large candidate sets (many frames of a pair in the window): a
/// linear-time stand-in for the maximum clique. Leader clustering in window
/// order (a candidate joins the first cluster whose leader it is consistent
/// with and that lacks its observation), then one reassignment pass of every
/// candidate to the best-supported fused cluster it is consistent with.
fn cluster_pair_large(candidates: &[Candidate], params: &ConsistencyParams) -> Vec<Cluster> {
    let mut leaders: Vec<(usize, Vec<usize>)> = Vec::new();
    for (i, c) in candidates.iter().enumerate() {
        let home = leaders.iter_mut().find(|(l, members)| {
            members
                .iter()
                .all(|&m| candidates[m].observation != c.observation)
                && consistent_with(
                    c,
                    &candidates[*l].a_from_b,
                    &candidates[*l].covariance,
                    params.gate_chi2,
                )
        });
        match home {
            Some((_, members)) => members.push(i),
            None => leaders.push((i, vec![i])),
        }
    }
    leaders.sort_by_key(|(l, members)| {
        let frames: usize = members.iter().map(|&m| candidates[m].weight).sum();
        (Reverse(frames), *l)
    });
    leaders.truncate(params.max_clusters_per_pair);
    let fused: Vec<(Pose, Cov6)> = leaders
        .iter()
        .filter_map(|(_, members)| fuse_members(candidates, members))
        .collect();
    let mut assigned: Vec<Vec<usize>> = vec![Vec::new(); fused.len()];
    let mut taken: Vec<BTreeSet<usize>> = vec![BTreeSet::new(); fused.len()];
    for (i, c) in candidates.iter().enumerate() {
        if let Some(k) = (0..fused.len()).find(|&k| {
            !taken[k].contains(&c.observation)
                && consistent_with(c, &fused[k].0, &fused[k].1, params.gate_chi2)
        }) {
            assigned[k].push(i);
            taken[k].insert(c.observation);
        }
    }
    assigned
        .into_iter()
        .filter(|m| !m.is_empty())
        .filter_map(|members| {
            let (pose, cov) = fuse_members(candidates, &members)?;
            Some(Cluster {
                primaries: primary_frames(candidates, &members),
                frames: members.iter().map(|&i| candidates[i].weight).sum(),
                members,
                a_from_b: pose,
                covariance: cov,
                votes: 0,
                weak_votes: 0,
            })
        })
        .collect()
}

/// Step 1: the clusters of one pair's candidates (see the module docs).
pub fn cluster_pair(candidates: &[Candidate], params: &ConsistencyParams) -> Vec<Cluster> {
    if candidates.len() > params.exact_clique_limit {
        return cluster_pair_large(candidates, params);
    }
    let m = candidates.len();
    let mut adj = vec![vec![false; m]; m];
    for i in 0..m {
        for j in i + 1..m {
            let (ci, cj) = (&candidates[i], &candidates[j]);
            if ci.observation == cj.observation {
                continue;
            }
            let d2 = mahalanobis2(&ci.a_from_b, &ci.covariance, &cj.a_from_b, &cj.covariance);
            if d2 <= params.gate_chi2 {
                adj[i][j] = true;
                adj[j][i] = true;
            }
        }
    }
    let mut remaining: Vec<usize> = (0..m).collect();
    let mut clusters = Vec::new();
    while !remaining.is_empty() && clusters.len() < params.max_clusters_per_pair {
        let sub_adj: Vec<Vec<bool>> = remaining
            .iter()
            .map(|&i| remaining.iter().map(|&j| adj[i][j]).collect())
            .collect();
        let weight: Vec<(usize, usize)> = remaining
            .iter()
            .map(|&i| {
                let c = &candidates[i];
                (c.weight, if c.hypothesis == 0 { c.weight } else { 0 })
            })
            .collect();
        let local = exact_clique(&sub_adj, &weight, 20_000)
            .unwrap_or_else(|| greedy_clique(&sub_adj, &weight));
        let mut members: Vec<usize> = local.iter().map(|&k| remaining[k]).collect();
        members.sort_unstable();
        let Some(mut fused) = fuse_members(candidates, &members) else {
            break;
        };
        // Relaxation: a clique needs every pair consistent, so one noisy true
        // candidate may miss it; admit any candidate (of an observation not yet
        // in the cluster) consistent with the fused mean.
        let in_obs: BTreeSet<usize> = members.iter().map(|&i| candidates[i].observation).collect();
        let extra: Vec<usize> = remaining
            .iter()
            .copied()
            .filter(|i| !members.contains(i) && !in_obs.contains(&candidates[*i].observation))
            .filter(|&i| {
                let c = &candidates[i];
                mahalanobis2(&c.a_from_b, &c.covariance, &fused.0, &fused.1) <= params.gate_chi2
            })
            .collect();
        if !extra.is_empty() {
            let mut seen = in_obs;
            for i in extra {
                if seen.insert(candidates[i].observation) {
                    members.push(i);
                }
            }
            members.sort_unstable();
            if let Some(f) = fuse_members(candidates, &members) {
                fused = f;
            }
        }
        remaining.retain(|i| !members.contains(i));
        clusters.push(Cluster {
            primaries: primary_frames(candidates, &members),
            frames: members.iter().map(|&i| candidates[i].weight).sum(),
            members,
            a_from_b: fused.0,
            covariance: fused.1,
            votes: 0,
            weak_votes: 0,
        });
    }
    clusters
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::consistency::{Candidate, ConsistencyParams};
    use proto::geometry::{pose_from_xyz_rpy, Cov6, Pose};

    fn cand(obs: usize, hyp: u8, p: Pose) -> Candidate {
        Candidate::new(obs, hyp, p, Cov6::identity() * 1e-4).unwrap()
    }

    #[test]
    fn exclusive_hypotheses_never_share_a_cluster() {
        let p = pose_from_xyz_rpy([1.0, 0.0, 0.0], [0.0, 0.0, 0.0]);
        // One observation whose two hypotheses are (numerically) the same pose.
        let cs = [cand(0, 0, p), cand(0, 1, p), cand(1, 0, p)];
        let clusters = cluster_pair(&cs, &ConsistencyParams::default());
        assert_eq!(clusters[0].members, vec![0, 2], "primary wins the tie");
        assert_eq!(clusters[1].members, vec![1]);
    }

    #[test]
    fn a_fused_track_outweighs_more_but_lighter_candidates() {
        let p = pose_from_xyz_rpy([1.0, 0.0, 0.0], [0.0, 0.0, 0.0]);
        let q = pose_from_xyz_rpy([1.0, 0.5, 0.0], [0.0, 0.0, 0.4]);
        // One track fused from 20 frames vs two single frames agreeing elsewhere.
        let cs = [cand(0, 0, p).with_weight(20), cand(1, 0, q), cand(2, 0, q)];
        let clusters = cluster_pair(&cs, &ConsistencyParams::default());
        assert_eq!(clusters[0].members, vec![0]);
        assert_eq!(clusters[0].support(), 20);
        assert_eq!(clusters[1].members, vec![1, 2]);
        assert_eq!(clusters[1].support(), 2);
    }
}
