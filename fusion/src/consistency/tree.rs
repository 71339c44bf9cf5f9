//! Step 3 of the consistency checks: spanning trees grown from the
//! reference, choosing one cluster per pair; the reference's tree
//! initializes the solver.

use super::{compose_variance_bound, mahalanobis2, trace6, PairCandidates};
use crate::solver::{compose, difference, invert};
use proto::geometry::{Cov6, Pose, PoseWithCovariance};
use proto::VehicleId;
use std::cmp::Reverse;
use std::collections::{BTreeMap, BinaryHeap};

/// Whether the best cluster was seen in two frames or more, votes, vote and
/// support margins over the runner-up, support, weak votes, primaries, and
/// the pair (lowest first on a tie).
type FrontierKey = (
    bool,
    usize,
    i64,
    i64,
    usize,
    usize,
    usize,
    Reverse<(VehicleId, VehicleId)>,
);

/// The tree's predictions of one pair's relative pose, computed on first use:
/// the independent-path pose and variance bound, and the exact composition.
#[derive(Debug, Default)]
struct Prediction {
    bound: Option<(Pose, f64)>,
    exact: Option<PoseWithCovariance>,
}

/// One spanning tree of the selection.
#[derive(Debug, Clone, PartialEq)]
pub struct Tree {
    pub root: VehicleId,
    /// `(parent, parent_from_vehicle)` per non-root vehicle.
    parents: BTreeMap<VehicleId, (VehicleId, PoseWithCovariance)>,
    depth: BTreeMap<VehicleId, usize>,
    /// `root_from_v` composed down the tree, covariance included.
    root_from: BTreeMap<VehicleId, PoseWithCovariance>,
}

impl Tree {
    fn new(root: VehicleId) -> Self {
        Self {
            root,
            parents: BTreeMap::new(),
            depth: BTreeMap::from([(root, 0)]),
            root_from: BTreeMap::from([(
                root,
                PoseWithCovariance::new(Pose::identity(), Cov6::zeros()),
            )]),
        }
    }
    pub fn contains(&self, v: VehicleId) -> bool {
        self.depth.contains_key(&v)
    }
    pub fn vehicles(&self) -> impl Iterator<Item = VehicleId> + '_ {
        self.depth.keys().copied()
    }
    fn add(&mut self, parent: VehicleId, v: VehicleId, parent_from_v: PoseWithCovariance) {
        let d = self.depth[&parent] + 1;
        self.depth.insert(v, d);
        let root_from_v = compose(&self.root_from[&parent], &parent_from_v);
        self.root_from.insert(v, root_from_v);
        self.parents.insert(v, (parent, parent_from_v));
    }
    /// Whether `a_from_b` with covariance `cov` passes the gate against the
    /// tree. A cheap bound on the independent-path prediction rejects
    /// hopeless cases first; the exact test composes through the lowest
    /// common ancestor.
    pub fn consistent(
        &self,
        a: VehicleId,
        b: VehicleId,
        a_from_b: &Pose,
        cov: &Cov6,
        gate_chi2: f64,
    ) -> bool {
        self.consistent_with_prediction(a, b, a_from_b, cov, gate_chi2, &mut Prediction::default())
    }
    /// [`Tree::consistent`], the tree's predictions of `a_from_b` kept in
    /// `prediction` for the next candidate of the same pair.
    fn consistent_with_prediction(
        &self,
        a: VehicleId,
        b: VehicleId,
        a_from_b: &Pose,
        cov: &Cov6,
        gate_chi2: f64,
        prediction: &mut Prediction,
    ) -> bool {
        let (predicted, bound) = *prediction.bound.get_or_insert_with(|| {
            let (ra, rb) = (&self.root_from[&a], &self.root_from[&b]);
            let a_from_root = invert(ra);
            (
                ra.pose.inverse() * rb.pose,
                compose_variance_bound(&a_from_root.covariance, &rb.pose, &rb.covariance),
            )
        });
        let r = difference(a_from_b, &predicted);
        if r.norm_squared() > gate_chi2 * (bound + trace6(cov)) {
            return false;
        }
        let exact = prediction.exact.get_or_insert_with(|| self.relative(a, b));
        mahalanobis2(a_from_b, cov, &exact.pose, &exact.covariance) <= gate_chi2
    }
    /// `ancestor_from_v`, composed up the tree.
    fn up_to(&self, mut v: VehicleId, ancestor: VehicleId) -> PoseWithCovariance {
        let mut acc = PoseWithCovariance::new(Pose::identity(), Cov6::zeros());
        while v != ancestor {
            let (p, p_from_v) = &self.parents[&v];
            acc = compose(p_from_v, &acc);
            v = *p;
        }
        acc
    }
    /// `a_from_b` along the tree path (through the lowest common ancestor, so
    /// the shared part of the paths adds no uncertainty).
    pub fn relative(&self, a: VehicleId, b: VehicleId) -> PoseWithCovariance {
        let (mut x, mut y) = (a, b);
        while x != y {
            if self.depth[&x] >= self.depth[&y] {
                x = self.parents[&x].0;
            } else {
                y = self.parents[&y].0;
            }
        }
        compose(&invert(&self.up_to(a, x)), &self.up_to(b, x))
    }
    /// `root_from_v` for every vehicle of the tree.
    pub fn poses(&self) -> BTreeMap<VehicleId, Pose> {
        self.root_from.iter().map(|(v, p)| (*v, p.pose)).collect()
    }
}

/// The result of step 3.
#[derive(Debug, Clone, PartialEq)]
pub struct Selection {
    /// Chosen cluster per pair (index into `pairs`), `None`: every cluster rejected
    /// or the pair never decided.
    pub choice: Vec<Option<usize>>,
    /// The tree grown from the reference (first) and from any other component.
    pub trees: Vec<Tree>,
}

/// The previous map's relative pose of a pair `(a, b)`, `a < b`, and how far
/// (radians of attitude) the pair may have turned since.
pub type Prior = BTreeMap<(VehicleId, VehicleId), (Pose, f64)>;

/// Hysteresis against planar flips: when the tree grows by a pair whose best
/// cluster contradicts the previous map's attitude (a planar flip is tens of
/// degrees off), and a cluster with as many cycle votes agrees with it, that
/// one is taken — unless the evidence against the prior is overwhelming (the
/// best cluster's primary hypotheses outnumber the other's 3 to 1, at least
/// 3), so that a wrong prior cannot lock the map in.
fn prior_pick(p: &PairCandidates, ranked: &[usize], prior: &Prior) -> Option<usize> {
    let (prev, tol) = prior.get(&(p.a, p.b))?;
    let off = |c: usize| (p.clusters[c].a_from_b.rotation.inverse() * prev.rotation).angle();
    let top = *ranked.first()?;
    if off(top) <= *tol {
        return None;
    }
    let t = &p.clusters[top];
    ranked[1..].iter().copied().find(|&c| {
        let cl = &p.clusters[c];
        cl.votes == t.votes
            && off(c) <= *tol
            && !(t.primaries >= 3 && t.primaries >= 3 * cl.primaries)
    })
}

/// Step 3: grow spanning trees and choose one cluster per pair (module docs).
pub fn select(pairs: &[PairCandidates], reference: VehicleId, gate_chi2: f64) -> Selection {
    select_with_prior(pairs, reference, gate_chi2, &Prior::new())
}

/// [`select`] with the previous map's attitudes as a tie-breaker ([`Prior`]).
pub fn select_with_prior(
    pairs: &[PairCandidates],
    reference: VehicleId,
    gate_chi2: f64,
    prior: &Prior,
) -> Selection {
    let ranked: Vec<Vec<usize>> = pairs.iter().map(PairCandidates::ranked).collect();
    // The frontier's ranking of each pair with clusters (fixed: clusters and
    // votes do not change during the selection), kept in a heap rather than
    // found by a scan of every pair per vehicle added.
    let keys: Vec<Option<FrontierKey>> = pairs
        .iter()
        .zip(&ranked)
        .map(|(p, r)| {
            let top = &p.clusters[*r.first()?];
            let (sv, ss) = r
                .get(1)
                .map_or((0, 0), |&s| (p.clusters[s].votes, p.clusters[s].support()));
            Some((
                top.support() >= 2,
                top.votes,
                top.votes as i64 - sv as i64,
                top.support() as i64 - ss as i64,
                top.support(),
                top.weak_votes,
                top.primaries,
                Reverse((p.a, p.b)),
            ))
        })
        .collect();
    let mut choice = vec![None; pairs.len()];
    let mut decided = vec![false; pairs.len()];
    let mut by_vehicle: BTreeMap<VehicleId, Vec<usize>> = BTreeMap::new();
    for (i, p) in pairs.iter().enumerate() {
        by_vehicle.entry(p.a).or_default().push(i);
        by_vehicle.entry(p.b).or_default().push(i);
    }
    let mut trees: Vec<Tree> = Vec::new();
    let mut tree_of: BTreeMap<VehicleId, usize> = BTreeMap::new();
    let mut root = Some(reference);
    while let Some(r) = root {
        let t = trees.len();
        trees.push(Tree::new(r));
        tree_of.insert(r, t);
        let mut just_added = vec![r];
        let mut frontier = BinaryHeap::new();
        loop {
            // Verify every pair that closes a cycle with the new vehicles.
            for v in just_added.drain(..) {
                for &pi in by_vehicle.get(&v).into_iter().flatten() {
                    if let Some(key) = &keys[pi] {
                        if !decided[pi] {
                            frontier.push((*key, pi));
                        }
                    }
                    let p = &pairs[pi];
                    if decided[pi] || tree_of.get(&p.a) != Some(&t) || tree_of.get(&p.b) != Some(&t)
                    {
                        continue;
                    }
                    decided[pi] = true;
                    let mut prediction = Prediction::default();
                    choice[pi] = ranked[pi].iter().copied().find(|&c| {
                        let cl = &p.clusters[c];
                        trees[t].consistent_with_prediction(
                            p.a,
                            p.b,
                            &cl.a_from_b,
                            &cl.covariance,
                            gate_chi2,
                            &mut prediction,
                        )
                    });
                }
            }
            // Extend by the most trustworthy frontier pair: the heap's best
            // that is still undecided with one vehicle in the tree (a pair
            // leaves the frontier for good once decided or inside the tree).
            let mut best = None;
            while let Some((_, pi)) = frontier.pop() {
                let p = &pairs[pi];
                if !decided[pi]
                    && (tree_of.get(&p.a) == Some(&t)) != (tree_of.get(&p.b) == Some(&t))
                {
                    best = Some((pi, p));
                    break;
                }
            }
            let Some((pi, p)) = best else { break };
            decided[pi] = true;
            let c = prior_pick(p, &ranked[pi], prior).unwrap_or(ranked[pi][0]);
            choice[pi] = Some(c);
            let cl = &p.clusters[c];
            let a_from_b = PoseWithCovariance::new(cl.a_from_b, cl.covariance);
            let (parent, child, parent_from_child) = if tree_of.get(&p.a) == Some(&t) {
                (p.a, p.b, a_from_b)
            } else {
                (p.b, p.a, invert(&a_from_b))
            };
            trees[t].add(parent, child, parent_from_child);
            tree_of.insert(child, t);
            just_added.push(child);
        }
        root = pairs
            .iter()
            .enumerate()
            .filter(|(i, _)| !decided[*i] && !ranked[*i].is_empty())
            .flat_map(|(_, p)| [p.a, p.b])
            .filter(|v| !tree_of.contains_key(v))
            .min();
    }
    Selection { choice, trees }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::consistency::cluster_pair;
    use crate::consistency::{Candidate, ConsistencyParams};
    use proto::geometry::{pose_from_xyz_rpy, Cov6, Pose};

    fn cand(obs: usize, hyp: u8, p: Pose) -> Candidate {
        Candidate::new(obs, hyp, p, Cov6::identity() * 1e-4).unwrap()
    }

    /// One pair seen by `n` frames, `flipped` of them with the planar flip as
    /// their primary: two clusters of equal support and no cycle votes.
    fn flip_pair(n: usize, flipped: usize) -> (PairCandidates, Pose, Pose) {
        let truth = pose_from_xyz_rpy([1.7, 0.2, 0.0], [0.0, 0.0, 0.1]);
        let flip = pose_from_xyz_rpy([1.7, 0.2, 0.0], [0.0, 0.9, 0.1]);
        let mut candidates = Vec::new();
        for i in 0..n {
            let (h0, h1) = if i < flipped {
                (flip, truth)
            } else {
                (truth, flip)
            };
            candidates.push(cand(i, 0, h0));
            candidates.push(cand(i, 1, h1));
        }
        let clusters = cluster_pair(&candidates, &ConsistencyParams::default());
        (
            PairCandidates {
                a: 1,
                b: 2,
                candidates,
                clusters,
            },
            truth,
            flip,
        )
    }

    fn chosen(sel: &Selection, pairs: &[PairCandidates]) -> Pose {
        pairs[0].clusters[sel.choice[0].expect("a choice")].a_from_b
    }

    #[test]
    fn the_previous_attitude_breaks_a_flip_tie_but_not_overwhelming_evidence() {
        let angle = |a: &Pose, b: &Pose| (a.rotation.inverse() * b.rotation).angle();
        // Two of three frames flipped: alone, the primaries' majority picks the flip…
        let (pair, truth, flip) = flip_pair(3, 2);
        let pairs = [pair];
        let alone = select(&pairs, 1, 27.86);
        assert!(angle(&chosen(&alone, &pairs), &flip) < 1e-6);
        // …the previous map's attitude keeps the truth.
        let prior = Prior::from([((1, 2), (truth, 8f64.to_radians()))]);
        let held = select_with_prior(&pairs, 1, 27.86, &prior);
        assert!(angle(&chosen(&held, &pairs), &truth) < 1e-6);
        // Seven of eight flipped (7 primaries against 1): the evidence wins over the prior.
        let (pair, _, flip) = flip_pair(8, 7);
        let pairs = [pair];
        let overruled = select_with_prior(&pairs, 1, 27.86, &prior);
        assert!(angle(&chosen(&overruled, &pairs), &flip) < 1e-6);
    }

    #[test]
    fn the_tree_grows_by_the_best_supported_pair_and_verifies_the_rest() {
        let truth = |v: u32| pose_from_xyz_rpy([v as f64, 0.0, 0.0], [0.0, 0.0, 0.1 * v as f64]);
        let rel = |a: u32, b: u32| truth(a).inverse() * truth(b);
        // 1–2 seen in 1 frame, 1–3 in 5 (one fused track), 2–3 in 3.
        let pair = |a: u32, b: u32, frames: usize| {
            let candidates = vec![cand(0, 0, rel(a, b)).with_weight(frames)];
            let clusters = cluster_pair(&candidates, &ConsistencyParams::default());
            PairCandidates {
                a,
                b,
                candidates,
                clusters,
            }
        };
        let pairs = [pair(1, 2, 1), pair(1, 3, 5), pair(2, 3, 3)];
        let sel = select(&pairs, 1, 27.86);
        let tree = &sel.trees[0];
        // 3 joins by its 5 frames, then 2 through 3 (3 frames) rather than
        // directly (1 frame); the direct pair is then verified and kept.
        assert_eq!(tree.parents[&3].0, 1);
        assert_eq!(tree.parents[&2].0, 3);
        assert_eq!(sel.choice, vec![Some(0), Some(0), Some(0)]);
        let e = difference(&tree.poses()[&2], &rel(1, 2));
        assert!(e.norm() < 1e-12, "{e}");
        // A verification that fails leaves the pair without a choice.
        let mut wrong = pairs.clone();
        wrong[0] = pair(1, 2, 1);
        wrong[0].candidates[0].a_from_b = rel(1, 2) * pose_from_xyz_rpy([0.3, 0.0, 0.0], [0.0; 3]);
        wrong[0].clusters = cluster_pair(&wrong[0].candidates, &ConsistencyParams::default());
        assert_eq!(
            select(&wrong, 1, 27.86).choice,
            vec![None, Some(0), Some(0)]
        );
    }

    #[test]
    fn a_single_frame_links_a_vehicle_only_when_nothing_repeated_does() {
        let truth = |v: u32| pose_from_xyz_rpy([v as f64, 0.0, 0.0], [0.0, 0.0, 0.1 * v as f64]);
        let rel = |a: u32, b: u32| truth(a).inverse() * truth(b);
        let pair = |a: u32, b: u32, frames: usize, votes: usize| {
            let candidates = vec![cand(0, 0, rel(a, b)).with_weight(frames)];
            let mut clusters = cluster_pair(&candidates, &ConsistencyParams::default());
            clusters[0].votes = votes;
            PairCandidates {
                a,
                b,
                candidates,
                clusters,
            }
        };
        // 1–2 in one frame, with a vote; 1–3 and 3–2 in two frames each, none.
        let pairs = [pair(1, 2, 1, 1), pair(1, 3, 2, 0), pair(2, 3, 2, 0)];
        let tree = &select(&pairs, 1, 27.86).trees[0];
        assert_eq!(tree.parents[&3].0, 1);
        assert_eq!(
            tree.parents[&2].0, 3,
            "2 joins through 3, not by its single frame"
        );
        // Without the repeated path, the single frame links 2.
        let tree = &select(&pairs[..1], 1, 27.86).trees[0];
        assert_eq!(tree.parents[&2].0, 1);
    }
}
