//! Outlier rejection before the solve: which hypothesis of which observation
//! enters the pose graph.
//!
//! In the spirit of PCM (Mangelson et al. 2018, "Pairwise Consistency
//! Maximization for Robust Multi-robot Map Merging"), in three steps:
//!
//! 1. **Same relative pose** ([`cluster_pair`]): every hypothesis of every
//!    observation of a vehicle pair `(a, b)`, `a < b`, expressed as `a_from_b`
//!    (B→A observations inverted), is a *candidate*. Two candidates of
//!    different observations are consistent when the Mahalanobis distance of
//!    their difference under the summed covariances passes the chi-square
//!    gate; the two hypotheses of one observation are mutually exclusive (never
//!    adjacent). The maximum clique of that consistency graph (exact
//!    branch-and-bound for small sets, greedy for large ones) is the pair's best
//!    *cluster*; it is fused (information-weighted) into one edge; repeating on
//!    the candidates left gives the runner-up clusters (up to
//!    [`ConsistencyParams::max_clusters_per_pair`]).
//! 2. **Cycles** ([`vote_triangles`]): a pair's clusters carry no information
//!    on their own about which one is true (a single flipped observation gives
//!    two one-member clusters). Every triangle of pairs `(a,b),(b,k),(a,k)` is
//!    checked: each combination of clusters whose cycle error
//!    `a_from_b·b_from_k` vs `a_from_k` passes the gate votes for its three
//!    clusters. Departure from PCM: PCM's pairwise test needs odometry to relate
//!    two loop closures; here the only composable relations are cycles of
//!    relative poses, so the consistency test is over triangles (group-3, as in
//!    generalized PCM) and is resolved by voting plus step 3 instead of a
//!    hyper-clique search.
//! 3. **Selection** ([`select`]): a spanning forest grown Prim-style from the
//!    reference, preferring *verification*: whenever a pair has both ends in
//!    the tree, its best-scored cluster consistent with the tree's prediction
//!    (composed along the tree path, covariances propagated) is accepted and
//!    the others rejected; only when nothing is verifiable is the tree extended,
//!    by the frontier pair whose best cluster has the most votes, then margin
//!    over its runner-up, then support. That tree is also the solver's
//!    initialization.

use crate::solver::{compose, difference, invert};
use proto::geometry::{Cov6, Pose, PoseWithCovariance};
use proto::VehicleId;
use std::cmp::Reverse;
use std::collections::{BTreeMap, BTreeSet};

/// Settings of the consistency checks.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ConsistencyParams {
    /// Gate on the squared Mahalanobis distance between two candidates, or of a
    /// cycle error (6 DoF).
    pub gate_chi2: f64,
    /// Up to this many candidates per pair the maximum clique is exact.
    pub exact_clique_limit: usize,
    /// Clusters kept per pair (the rest of the candidates are `Inconsistent`).
    pub max_clusters_per_pair: usize,
    /// Fuse each track's time-consistent frames (same observer, camera,
    /// marker and hypothesis) into one candidate before the checks (default
    /// true; false: one candidate per frame, the slow reference behaviour).
    #[serde(default = "default_fuse_tracks")]
    pub fuse_tracks: bool,
}

fn default_fuse_tracks() -> bool {
    true
}

impl Default for ConsistencyParams {
    fn default() -> Self {
        Self {
            // χ²₆ at 99.99%: gross outliers (flips, wrong IDs) are far beyond
            // it, and a clique of n true candidates has n² chances to break at 99.9%.
            gate_chi2: 27.86,
            exact_clique_limit: 16,
            max_clusters_per_pair: 4,
            fuse_tracks: true,
        }
    }
}

/// One hypothesis of one observation, as `a_from_b` of its pair.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Candidate {
    /// Index of the observation (caller's numbering).
    pub observation: usize,
    /// 0: the primary hypothesis, 1: the planar-flip alternative.
    pub hypothesis: u8,
    pub a_from_b: Pose,
    pub covariance: Cov6,
    /// `covariance⁻¹`.
    pub information: Cov6,
    /// Frames this candidate stands for (a track's frames fused into one
    /// measurement count as many); 1 for a single observation.
    pub weight: usize,
}

impl Candidate {
    /// A candidate; `None` when the covariance is not invertible.
    pub fn new(
        observation: usize,
        hypothesis: u8,
        a_from_b: Pose,
        covariance: Cov6,
    ) -> Option<Self> {
        let covariance = (covariance + covariance.transpose()) * 0.5;
        let information = covariance.cholesky()?.inverse();
        Some(Self {
            observation,
            hypothesis,
            a_from_b,
            covariance,
            information,
            weight: 1,
        })
    }

    /// The same candidate standing for `weight` frames (at least 1).
    pub fn with_weight(self, weight: usize) -> Self {
        Self {
            weight: weight.max(1),
            ..self
        }
    }
}

/// Mutually consistent candidates of one pair, fused into one edge.
#[derive(Debug, Clone, PartialEq)]
pub struct Cluster {
    /// Indices into the pair's candidates, ascending.
    pub members: Vec<usize>,
    pub a_from_b: Pose,
    pub covariance: Cov6,
    /// Frames of primary hypotheses among the members (ranking tie-break: the PnP's own choice).
    pub primaries: usize,
    /// Frames the members stand for (sum of their weights).
    pub frames: usize,
    /// Triangles in which this cluster closes a consistent cycle.
    pub votes: usize,
}

impl Cluster {
    /// Frames supporting the cluster.
    pub fn support(&self) -> usize {
        self.frames
    }
    fn score(&self) -> (usize, usize, usize) {
        (self.votes, self.frames, self.primaries)
    }
}

/// A vehicle pair's candidates and clusters.
#[derive(Debug, Clone, PartialEq)]
pub struct PairCandidates {
    pub a: VehicleId,
    pub b: VehicleId,
    pub candidates: Vec<Candidate>,
    pub clusters: Vec<Cluster>,
}

impl PairCandidates {
    /// Cluster indices, best score first.
    pub fn ranked(&self) -> Vec<usize> {
        let mut idx: Vec<usize> = (0..self.clusters.len()).collect();
        idx.sort_by_key(|&i| (Reverse(self.clusters[i].score()), i));
        idx
    }
}

/// Squared Mahalanobis distance between two poses with independent covariances.
pub fn mahalanobis2(x: &Pose, cov_x: &Cov6, y: &Pose, cov_y: &Cov6) -> f64 {
    let r = difference(x, y);
    match (cov_x + cov_y).cholesky() {
        Some(ch) => {
            let z = ch.solve(&r);
            r.dot(&z)
        }
        None => f64::INFINITY,
    }
}

/// Upper bound of the largest eigenvalue of the covariance of `x·y`
/// (independent covariances): the trace of the propagated covariance, bounded
/// without forming it. Used to skip the exact test of hopeless combinations:
/// `rᵀS⁻¹r ≥ |r|²/λ_max(S)`.
fn compose_variance_bound(cov_x: &Cov6, y: &Pose, cov_y: &Cov6) -> f64 {
    let tr = |c: &Cov6, o: usize| c[(o, o)] + c[(o + 1, o + 1)] + c[(o + 2, o + 2)];
    let u = y.translation.vector.norm();
    let (tt, rr) = (tr(cov_x, 0), tr(cov_x, 3));
    (tt.sqrt() + u * rr.sqrt()).powi(2) + rr + tr(cov_y, 0) + tr(cov_y, 3)
}

fn trace6(c: &Cov6) -> f64 {
    (0..6).map(|i| c[(i, i)]).sum()
}

/// Information-weighted mean of poses given with their information matrices,
/// in the tangent space (Gauss–Newton passes around the first one), and the
/// covariance of that mean. Treats the items as independent: frames of one
/// camera with a common bias make the fused covariance optimistic.
pub fn fuse(items: &[(Pose, Cov6)]) -> Option<(Pose, Cov6)> {
    let (first, _) = items.first()?;
    let total: Cov6 = items.iter().map(|(_, info)| info).sum();
    let cov = total.cholesky()?.inverse();
    let mut mean = *first;
    for _ in 0..2 {
        let mut acc = nalgebra::Vector6::zeros();
        for (p, info) in items {
            acc += info * difference(p, &mean);
        }
        mean = proto::geometry::perturb(&mean, &(cov * acc));
    }
    Some((mean, (cov + cov.transpose()) * 0.5))
}

/// [`fuse`] for items known to lie close together (one track's frames, each
/// within the gate of the first): a single Gauss–Newton pass around the first
/// item. The second pass of [`fuse`] moves the mean by the square of the
/// spread (~1e-4 of a frame's σ at the noise of a marker pose), far below
/// the fused σ, and costs a tangent-space difference per item.
pub fn fuse_close(items: &[(Pose, Cov6)]) -> Option<(Pose, Cov6)> {
    let (first, _) = items.first()?;
    let total: Cov6 = items.iter().map(|(_, info)| info).sum();
    let cov = total.cholesky()?.inverse();
    let mut acc = nalgebra::Vector6::zeros();
    for (p, info) in &items[1..] {
        acc += info * difference(p, first);
    }
    let mean = proto::geometry::perturb(first, &(cov * acc));
    Some((mean, (cov + cov.transpose()) * 0.5))
}

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

/// Whether candidate `c` is consistent with `pose` (covariance `cov`):
/// `rᵀ(Σ_c + Σ)⁻¹r` under the gate. `rᵀΣ_c⁻¹r` bounds it from above and
/// needs no factorization, so it settles the common case first.
fn consistent_with(c: &Candidate, pose: &Pose, cov: &Cov6, gate_chi2: f64) -> bool {
    let r = difference(&c.a_from_b, pose);
    (r.transpose() * c.information * r)[0] <= gate_chi2
        || mahalanobis2(&c.a_from_b, &c.covariance, pose, cov) <= gate_chi2
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
        });
    }
    clusters
}

fn primary_frames(candidates: &[Candidate], members: &[usize]) -> usize {
    members
        .iter()
        .filter(|&&i| candidates[i].hypothesis == 0)
        .map(|&i| candidates[i].weight)
        .sum()
}

fn fuse_members(candidates: &[Candidate], members: &[usize]) -> Option<(Pose, Cov6)> {
    let items: Vec<(Pose, Cov6)> = members
        .iter()
        .map(|&i| (candidates[i].a_from_b, candidates[i].information))
        .collect();
    fuse(&items)
}

/// Step 2: votes from consistent triangles (see the module docs). `pairs` must
/// have `a < b` and be unique per pair.
pub fn vote_triangles(pairs: &mut [PairCandidates], gate_chi2: f64) {
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
    let mut votes: Vec<Vec<usize>> = pairs.iter().map(|p| vec![0; p.clusters.len()]).collect();
    for (&(a, b), &ab) in &index {
        let (Some(na), Some(nb)) = (neighbours.get(&a), neighbours.get(&b)) else {
            continue;
        };
        for &k in na.intersection(nb).filter(|&&k| k > b) {
            let (bk, ak) = (index[&(b, k)], index[&(a, k)]);
            let mut hit_ab = vec![false; pairs[ab].clusters.len()];
            let mut hit_bk = vec![false; pairs[bk].clusters.len()];
            let mut hit_ak = vec![false; pairs[ak].clusters.len()];
            for (i, c_ab) in pairs[ab].clusters.iter().enumerate() {
                for (j, c_bk) in pairs[bk].clusters.iter().enumerate() {
                    let pose = c_ab.a_from_b * c_bk.a_from_b;
                    let bound =
                        compose_variance_bound(&c_ab.covariance, &c_bk.a_from_b, &c_bk.covariance);
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
                            hit_ab[i] = true;
                            hit_bk[j] = true;
                            hit_ak[l] = true;
                        }
                    }
                }
            }
            for (p, hits) in [(ab, hit_ab), (bk, hit_bk), (ak, hit_ak)] {
                for (c, h) in hits.into_iter().enumerate() {
                    votes[p][c] += usize::from(h);
                }
            }
        }
    }
    for (p, v) in pairs.iter_mut().zip(votes) {
        for (c, n) in p.clusters.iter_mut().zip(v) {
            c.votes = n;
        }
    }
}

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

/// Step 3: grow spanning trees and choose one cluster per pair (module docs).
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
        loop {
            // Verify every pair that closes a cycle with the new vehicles.
            for v in just_added.drain(..) {
                for &pi in by_vehicle.get(&v).into_iter().flatten() {
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
            // Extend by the most trustworthy frontier pair.
            let frontier = pairs.iter().enumerate().filter(|(i, p)| {
                !decided[*i]
                    && !ranked[*i].is_empty()
                    && (tree_of.get(&p.a) == Some(&t)) != (tree_of.get(&p.b) == Some(&t))
            });
            let best = frontier.max_by_key(|(i, p)| {
                let r = &ranked[*i];
                let top = &p.clusters[r[0]];
                let (sv, ss) = r
                    .get(1)
                    .map_or((0, 0), |&s| (p.clusters[s].votes, p.clusters[s].support()));
                (
                    top.votes,
                    top.votes as i64 - sv as i64,
                    top.support() as i64 - ss as i64,
                    top.support(),
                    top.primaries,
                    Reverse((p.a, p.b)),
                )
            });
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
    use proto::geometry::pose_from_xyz_rpy;

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

    #[test]
    fn triangle_votes_pick_the_consistent_flip() {
        let truth =
            |v: u32| pose_from_xyz_rpy([v as f64, 0.5 * v as f64, 0.0], [0.0, 0.0, 0.1 * v as f64]);
        let rel = |a: u32, b: u32| truth(a).inverse() * truth(b);
        let twin = pose_from_xyz_rpy([0.0, 0.0, 0.0], [0.6, 0.0, 0.0]);
        let mut pairs = vec![
            PairCandidates {
                a: 1,
                b: 2,
                candidates: vec![cand(0, 0, rel(1, 2))],
                clusters: vec![],
            },
            PairCandidates {
                a: 2,
                b: 3,
                candidates: vec![cand(1, 0, rel(2, 3))],
                clusters: vec![],
            },
            // Flipped primary, true alternative.
            PairCandidates {
                a: 1,
                b: 3,
                candidates: vec![cand(2, 0, twin * rel(1, 3)), cand(2, 1, rel(1, 3))],
                clusters: vec![],
            },
        ];
        for p in &mut pairs {
            p.clusters = cluster_pair(&p.candidates, &ConsistencyParams::default());
        }
        vote_triangles(&mut pairs, 27.86);
        let sel = select(&pairs, 1, 27.86);
        let chosen = &pairs[2].clusters[sel.choice[2].unwrap()];
        assert_eq!(pairs[2].candidates[chosen.members[0]].hypothesis, 1);
    }
}
