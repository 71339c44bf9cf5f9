//! Outlier rejection before the solve: which hypothesis of which observation
//! enters the pose graph.
//!
//! In the spirit of PCM (Mangelson et al. 2018, "Pairwise Consistency
//! Maximization for Robust Multi-robot Map Merging"), in three steps:
//!
//! 1. **Same relative pose** ([`cluster_pair`], `consistency/clique.rs`): every hypothesis of every
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
//! 2. **Cycles** ([`vote_triangles`], `consistency/cycles.rs`): a pair's clusters carry no information
//!    on their own about which one is true (a single flipped observation gives
//!    two one-member clusters). Every triangle of pairs `(a,b),(b,k),(a,k)` is
//!    checked: each combination of clusters whose cycle error
//!    `a_from_b·b_from_k` vs `a_from_k` passes the gate votes for its three
//!    clusters; a cycle through a single-frame cluster gives only a weak vote,
//!    which ranks after support (a misread ID closes triangles with the
//!    neighbour actually seen). Departure from PCM: PCM's pairwise test needs odometry to relate
//!    two loop closures; here the only composable relations are cycles of
//!    relative poses, so the consistency test is over triangles (group-3, as in
//!    generalized PCM) and is resolved by voting plus step 3 instead of a
//!    hyper-clique search.
//! 3. **Selection** ([`select`], `consistency/tree.rs`): a spanning forest grown Prim-style from the
//!    reference, preferring *verification*: whenever a pair has both ends in
//!    the tree, its best-scored cluster consistent with the tree's prediction
//!    (composed along the tree path, covariances propagated) is accepted and
//!    the others rejected; only when nothing is verifiable is the tree extended,
//!    by the frontier pair whose best cluster was seen in more than one frame
//!    (a single frame links a vehicle only when nothing else does), then has
//!    the most votes, then margin over its runner-up, then support. That tree is also the solver's
//!    initialization.

mod clique;
mod cycles;
mod tree;

pub use clique::cluster_pair;
pub use cycles::{vote_triangles, vote_triangles_threads};
pub use tree::{select, select_with_prior, Prior, Selection, Tree};

use crate::solver::difference;
use proto::geometry::{Cov6, Pose};
use proto::VehicleId;
use std::cmp::Reverse;

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
        let information = crate::linalg::spd_inverse6(&covariance)?;
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
    /// Triangles in which this cluster closes a consistent cycle, every
    /// cluster of it standing for two frames or more.
    pub votes: usize,
    /// Triangles in which it closes a consistent cycle only through a
    /// single-frame cluster: a tie-breaker after support.
    pub weak_votes: usize,
}

impl Cluster {
    /// Frames supporting the cluster.
    pub fn support(&self) -> usize {
        self.frames
    }
    fn score(&self) -> (usize, usize, usize, usize) {
        (self.votes, self.frames, self.weak_votes, self.primaries)
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
    crate::linalg::spd_quadratic6(&(cov_x + cov_y), &r).unwrap_or(f64::INFINITY)
}

/// Upper bound of the largest eigenvalue of the covariance of `x·y`
/// (independent covariances): the trace of the propagated covariance, bounded
/// without forming it. Used to skip the exact test of hopeless combinations:
/// `rᵀS⁻¹r ≥ |r|²/λ_max(S)`.
pub(crate) fn compose_variance_bound(cov_x: &Cov6, y: &Pose, cov_y: &Cov6) -> f64 {
    let tr = |c: &Cov6, o: usize| c[(o, o)] + c[(o + 1, o + 1)] + c[(o + 2, o + 2)];
    let u = y.translation.vector.norm();
    let (tt, rr) = (tr(cov_x, 0), tr(cov_x, 3));
    (tt.sqrt() + u * rr.sqrt()).powi(2) + rr + tr(cov_y, 0) + tr(cov_y, 3)
}

pub(crate) fn trace6(c: &Cov6) -> f64 {
    (0..6).map(|i| c[(i, i)]).sum()
}

/// Information-weighted mean of poses given with their information matrices,
/// in the tangent space (Gauss–Newton passes around the first one), and the
/// covariance of that mean. Treats the items as independent: frames of one
/// camera with a common bias make the fused covariance optimistic.
pub fn fuse(items: &[(Pose, Cov6)]) -> Option<(Pose, Cov6)> {
    let (first, _) = items.first()?;
    let total: Cov6 = items.iter().map(|(_, info)| info).sum();
    let cov = crate::linalg::spd_inverse6(&total)?;
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
    let cov = crate::linalg::spd_inverse6(&total)?;
    let mut acc = nalgebra::Vector6::zeros();
    for (p, info) in &items[1..] {
        acc += info * difference(p, first);
    }
    let mean = proto::geometry::perturb(first, &(cov * acc));
    Some((mean, (cov + cov.transpose()) * 0.5))
}

/// Whether candidate `c` is consistent with `pose` (covariance `cov`):
/// `rᵀ(Σ_c + Σ)⁻¹r` under the gate. `rᵀΣ_c⁻¹r` bounds it from above and
/// needs no factorization, so it settles the common case first.
pub(crate) fn consistent_with(c: &Candidate, pose: &Pose, cov: &Cov6, gate_chi2: f64) -> bool {
    let r = difference(&c.a_from_b, pose);
    (r.transpose() * c.information * r)[0] <= gate_chi2
        || mahalanobis2(&c.a_from_b, &c.covariance, pose, cov) <= gate_chi2
}

pub(crate) fn primary_frames(candidates: &[Candidate], members: &[usize]) -> usize {
    members
        .iter()
        .filter(|&&i| candidates[i].hypothesis == 0)
        .map(|&i| candidates[i].weight)
        .sum()
}

pub(crate) fn fuse_members(candidates: &[Candidate], members: &[usize]) -> Option<(Pose, Cov6)> {
    let items: Vec<(Pose, Cov6)> = members
        .iter()
        .map(|&i| (candidates[i].a_from_b, candidates[i].information))
        .collect();
    fuse(&items)
}
