//! Swarm fusion: composes every vehicle's marker observations into one
//! consistent relative map over the vehicle IDs.
//!
//! [`Fusion`] keeps a sliding window of observations (each admitted or
//! rejected with a [`RejectReason`] on arrival), and on [`Fusion::solve`]:
//!
//! 1. inflates each observation's covariance with its age ([`AgeInflation`]);
//! 2. picks, per vehicle pair, the mutually consistent hypotheses and between
//!    pairs the cycle-consistent ones, the planar-flip twins being mutually
//!    exclusive candidates ([`consistency`], PCM-style);
//! 3. solves the pose graph on SE(3) by Levenberg–Marquardt with a robust
//!    kernel, the reference vehicle fixing the gauge, initialized by the
//!    spanning tree of step 2 ([`solver`]);
//! 4. gates every accepted observation's residual against the solution
//!    (chi-square), re-solving without the rejects;
//! 5. writes a [`FleetMap`]: every vehicle's `reference_from_vehicle` with its
//!    marginal covariance and state, every observation's verdict.
//!
//! Same inputs give a bit-identical map, whatever the order they arrived in
//! (everything is kept in ordered maps keyed by capture time and identity), so
//! a central instance and per-vehicle instances hearing the same observations
//! agree. The library never reads the clock for `now`: callers pass `now_ns`.
//! The one wall-clock figure is [`FleetMap::solve_time_us`], a diagnostic that
//! [`FusionParams::record_solve_time`] can switch off.
//!
//! **Why a hand-written solver.** The crates.io candidates were checked
//! (November 2026): `factrs` 0.3 and `tiny-solver` 0.18 are built on nalgebra
//! 0.34 and faer (the workspace is on nalgebra 0.33; two nalgebra versions and
//! faer's build on a shared 2-core machine), `factrs` needs Rust 1.87 and
//! `apex-solver` 1.5 Rust 1.93 (the workspace promises 1.85), and none exposes
//! marginal covariances in shoal's perturbation convention
//! ([`proto::geometry`]). The problem is small (≤ a few hundred vehicles ×
//! 6 DoF, sparse), so a profile Cholesky on the normal equations is ~300
//! lines, and `benches/solve.rs` measures it.
//!
//! The Zenoh service around this library is `service.rs` (separate);
//! formation controllers read maps through [`client::MapView`].

extern crate shoal_proto as proto;

pub mod client;
pub mod consistency;
pub mod formation;
pub mod service;
pub mod solver;
mod window;

pub use client::{MapView, RelativePose};
pub use consistency::ConsistencyParams;
pub use solver::RobustKernel;
pub use window::AgeInflation;

use consistency::{Candidate, PairCandidates};
use proto::config::Fleet;
use proto::geometry::{Cov6, Pose, PoseWithCovariance};
use proto::{EdgeReport, FleetMap, Observation, RejectReason, VehicleEstimate, VehicleId, VehicleState};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};
use window::{early_report, Admission, ObservationKey, Window};

/// Fusion settings. `Default` gives the documented values.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FusionParams {
    /// Sliding window, seconds (default 2 s: 20 frames per camera at 10 Hz).
    pub window_s: f64,
    /// How far in the future (relative to `now`) a capture stamp may be, seconds (default 0.25 s).
    pub max_clock_skew_s: f64,
    /// Gate on an accepted observation's squared Mahalanobis residual after the
    /// solve (6 DoF; default 27.86 = χ²₆ at 99.99%).
    pub chi2_gate: f64,
    /// Covariance growth with age (random walk).
    pub age_inflation: AgeInflation,
    /// Robust kernel of the solver (default Huber, k = 4.1 = √χ²₆(0.99)).
    pub robust: RobustKernel,
    /// Pairwise / cycle consistency before the solve.
    pub consistency: ConsistencyParams,
    /// An observation whose covariance has a standard deviation above this (m or rad) is `Invalid` (default 5).
    pub max_std: f64,
    /// Levenberg–Marquardt iteration limit per solve (default 30).
    pub max_iterations: usize,
    /// Solve / chi-square gate rounds at most (default 3).
    pub max_gate_rounds: usize,
    /// Early rejections kept for the next map at most (default 4096; more are counted, not reported).
    pub max_pending_reports: usize,
    /// Fill [`FleetMap::solve_time_us`] from the wall clock (default true; off for bit-identical maps).
    pub record_solve_time: bool,
}

impl Default for FusionParams {
    fn default() -> Self {
        let solver = solver::SolverParams::default();
        Self {
            window_s: 2.0,
            max_clock_skew_s: 0.25,
            chi2_gate: 27.86,
            age_inflation: AgeInflation::default(),
            robust: solver.robust,
            consistency: ConsistencyParams::default(),
            max_std: 5.0,
            max_iterations: solver.max_iterations,
            max_gate_rounds: 3,
            max_pending_reports: 4096,
            record_solve_time: true,
        }
    }
}

/// Counts per [`RejectReason`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReasonCounts([u64; 11]);

impl ReasonCounts {
    fn index(reason: &RejectReason) -> usize {
        use RejectReason::*;
        match reason {
            UnknownMarker => 0,
            AmbiguousMarker => 1,
            SelfObservation => 2,
            Stale => 3,
            ClockSkew => 4,
            ObserverMismatch => 5,
            ChiSquare => 6,
            FlippedHypothesis => 7,
            Inconsistent => 8,
            Invalid => 9,
            Duplicate => 10,
        }
    }
    pub fn get(&self, reason: &RejectReason) -> u64 {
        self.0[Self::index(reason)]
    }
    pub fn total(&self) -> u64 {
        self.0.iter().sum()
    }
    fn add(&mut self, reason: &RejectReason) {
        self.0[Self::index(reason)] += 1;
    }
}

/// Figures of the last solve.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SolveStats {
    pub window_observations: usize,
    /// Hypotheses accepted into the graph (at most one per observation).
    pub accepted: usize,
    /// Verdicts on hypotheses rejected by consistency or the gate.
    pub rejected: ReasonCounts,
    pub pairs: usize,
    pub clusters: usize,
    /// Vehicles localized relative to the reference (reference included).
    pub localized: usize,
    pub lm_iterations: usize,
    pub gate_rounds: usize,
    /// The solver failed and the spanning-tree poses were reported instead.
    pub solver_failed: bool,
}

/// Running counters of a [`Fusion`].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FusionStats {
    /// Calls to [`Fusion::ingest`].
    pub received: u64,
    /// Admitted into the window.
    pub ingested: u64,
    /// Rejected on arrival, per reason (duplicates under `Duplicate`).
    pub rejected_at_ingest: ReasonCounts,
    /// Observations that aged out of the window.
    pub expired: u64,
    /// Early rejections not reported because the pending list was full.
    pub reports_dropped: u64,
    pub solves: u64,
    pub last_solve: SolveStats,
}

/// The swarm fusion: see the crate docs.
#[derive(Debug, Clone)]
pub struct Fusion {
    fleet: Fleet,
    producer: String,
    params: FusionParams,
    window: Window,
    pending: Vec<EdgeReport>,
    alive: BTreeMap<VehicleId, bool>,
    last_seen: BTreeMap<VehicleId, u64>,
    last_estimate: BTreeMap<VehicleId, (Pose, Cov6, u64)>,
    seq: u64,
    stats: FusionStats,
}

/// Covariance reported for a vehicle nothing is known about (σ = 1 km / 1000 rad).
pub const NO_INFORMATION_VARIANCE: f64 = 1e6;

fn seconds_to_ns(s: f64) -> u64 {
    if s.is_finite() && s > 0.0 {
        (s * 1e9).min(u64::MAX as f64) as u64
    } else {
        0
    }
}

impl Fusion {
    /// A fusion instance for `fleet`; `producer` names it in the maps (`"central"` or a vehicle ID).
    pub fn new(fleet: &Fleet, params: FusionParams, producer: &str) -> Self {
        Self {
            fleet: fleet.clone(),
            producer: producer.to_string(),
            params,
            window: Window::default(),
            pending: Vec::new(),
            alive: fleet.vehicles.iter().map(|v| (v.id, true)).collect(),
            last_seen: BTreeMap::new(),
            last_estimate: BTreeMap::new(),
            seq: 0,
            stats: FusionStats::default(),
        }
    }

    pub fn params(&self) -> &FusionParams {
        &self.params
    }

    fn admission(&self) -> Admission {
        Admission {
            window_ns: seconds_to_ns(self.params.window_s),
            max_clock_skew_ns: seconds_to_ns(self.params.max_clock_skew_s),
            max_std: self.params.max_std,
        }
    }

    /// Admit an observation that arrived on `arrived_on`'s key at `now_ns`.
    /// Rejections are also kept for the next map's edge reports.
    pub fn ingest(&mut self, obs: Observation, arrived_on: VehicleId, now_ns: u64) -> Result<(), RejectReason> {
        self.stats.received += 1;
        let limits = self.admission();
        let target = match self.fleet.marker_owner(obs.codes, obs.target_marker) {
            proto::config::MarkerOwner::Vehicle(v) => Some(v),
            _ => None,
        };
        let report = early_report(&obs, target, RejectReason::Invalid);
        let (observer, stamp) = (obs.observer, obs.stamp_ns);
        match self.window.admit(&self.fleet, obs, arrived_on, now_ns, &limits) {
            Ok(target) => {
                self.stats.ingested += 1;
                for v in [observer, target] {
                    let seen = self.last_seen.entry(v).or_insert(0);
                    *seen = (*seen).max(stamp);
                }
                Ok(())
            }
            Err(reason) => {
                self.stats.rejected_at_ingest.add(&reason);
                if self.pending.len() < self.params.max_pending_reports {
                    self.pending.push(EdgeReport {
                        rejected: Some(reason.clone()),
                        ..report
                    });
                } else {
                    self.stats.reports_dropped += 1;
                }
                Err(reason)
            }
        }
    }

    /// Liveliness of a vehicle's node (its token appeared or disappeared).
    pub fn set_alive(&mut self, vehicle: VehicleId, alive: bool, _now_ns: u64) {
        if self.fleet.vehicle(vehicle).is_some() {
            self.alive.insert(vehicle, alive);
        }
    }

    pub fn stats(&self) -> FusionStats {
        self.stats.clone()
    }

    /// Observations currently in the window.
    pub fn window_len(&self) -> usize {
        self.window.entries.len()
    }

    /// Fuse the window into a map at `now_ns`.
    pub fn solve(&mut self, now_ns: u64) -> FleetMap {
        let started = self.params.record_solve_time.then(std::time::Instant::now);
        let limits = self.admission();
        self.stats.expired += self.window.evict(now_ns, limits.window_ns) as u64;
        let reference = self.fleet.reference_vehicle;
        let mut solve_stats = SolveStats {
            window_observations: self.window.entries.len(),
            ..SolveStats::default()
        };

        // Candidates per pair (a < b), every hypothesis as a_from_b with its age-inflated covariance.
        let entries: Vec<(&ObservationKey, &window::Stored)> = self.window.entries.iter().collect();
        let mut by_pair: BTreeMap<(VehicleId, VehicleId), Vec<Candidate>> = BTreeMap::new();
        for (i, (_, s)) in entries.iter().enumerate() {
            let o = &s.obs;
            let age_s = now_ns.saturating_sub(o.stamp_ns) as f64 * 1e-9;
            let mut hyps = vec![(o.observer_from_target, o.covariance)];
            if let Some(alt) = &o.alternative {
                hyps.push((alt.observer_from_target, alt.covariance));
            }
            for (h, (pose, cov)) in hyps.into_iter().enumerate() {
                let pwc = PoseWithCovariance::new(pose, self.params.age_inflation.inflate(&cov, age_s));
                let (a, b, a_from_b) = if o.observer < s.target {
                    (o.observer, s.target, pwc)
                } else {
                    (s.target, o.observer, pwc.inverse())
                };
                if let Some(c) = Candidate::new(i, h as u8, a_from_b.pose, a_from_b.covariance) {
                    by_pair.entry((a, b)).or_default().push(c);
                }
            }
        }
        let mut pairs: Vec<PairCandidates> = by_pair
            .into_iter()
            .map(|((a, b), candidates)| {
                let clusters = consistency::cluster_pair(&candidates, &self.params.consistency);
                PairCandidates { a, b, candidates, clusters }
            })
            .collect();
        // Where each hypothesis went: (pair, candidate) per (observation, hypothesis).
        let mut cand_index: Vec<[Option<(usize, usize)>; 2]> = vec![[None; 2]; entries.len()];
        for (pi, p) in pairs.iter().enumerate() {
            for (ci, c) in p.candidates.iter().enumerate() {
                cand_index[c.observation][usize::from(c.hypothesis)] = Some((pi, ci));
            }
        }
        consistency::vote_triangles(&mut pairs, self.params.consistency.gate_chi2);
        let selection = consistency::select(&pairs, reference, self.params.consistency.gate_chi2);
        solve_stats.pairs = pairs.len();
        solve_stats.clusters = pairs.iter().map(|p| p.clusters.len()).sum();

        // Accepted hypotheses: (observation, hypothesis) → pair index.
        let mut accepted: BTreeMap<(usize, u8), usize> = BTreeMap::new();
        for (pi, p) in pairs.iter().enumerate() {
            if let Some(c) = selection.choice[pi] {
                for &m in &p.clusters[c].members {
                    let cand = &p.candidates[m];
                    accepted.insert((cand.observation, cand.hypothesis), pi);
                }
            }
        }
        let tree = &selection.trees[0];
        let initial = tree.poses();
        let mut gated: BTreeSet<(usize, u8)> = BTreeSet::new();
        let mut solution: BTreeMap<VehicleId, (Pose, Cov6)> = BTreeMap::new();
        for round in 0..self.params.max_gate_rounds.max(1) {
            solve_stats.gate_rounds = round + 1;
            // One fused constraint per chosen pair in the reference tree, without the gated members.
            let mut constraints = Vec::new();
            for (pi, p) in pairs.iter().enumerate() {
                let Some(c) = selection.choice[pi] else { continue };
                if !tree.contains(p.a) || !tree.contains(p.b) {
                    continue;
                }
                let items: Vec<(Pose, Cov6)> = p.clusters[c]
                    .members
                    .iter()
                    .map(|&m| &p.candidates[m])
                    .filter(|cand| !gated.contains(&(cand.observation, cand.hypothesis)))
                    .map(|cand| (cand.a_from_b, cand.information))
                    .collect();
                if let Some((pose, cov)) = consistency::fuse(&items) {
                    constraints.push(solver::Constraint {
                        a: p.a,
                        b: p.b,
                        a_from_b: pose,
                        covariance: cov,
                    });
                }
            }
            let connected = connected_to(reference, &constraints);
            constraints.retain(|c| connected.contains(&c.a));
            let init: BTreeMap<VehicleId, Pose> = initial.iter().filter(|(v, _)| connected.contains(v)).map(|(v, p)| (*v, *p)).collect();
            let sp = solver::SolverParams {
                robust: self.params.robust,
                max_iterations: self.params.max_iterations,
                ..solver::SolverParams::default()
            };
            solution = match solver::solve(reference, &init, &constraints, &sp) {
                Ok(s) => {
                    solve_stats.lm_iterations += s.iterations;
                    solve_stats.solver_failed = false;
                    s.poses.iter().map(|(v, p)| (*v, (*p, s.covariances.get(v).copied().unwrap_or(Cov6::zeros())))).collect()
                }
                Err(e) => {
                    tracing::warn!("pose graph solve failed ({e}); reporting the spanning-tree poses");
                    solve_stats.solver_failed = true;
                    init.keys().map(|&v| { let r = tree.relative(reference, v); (v, (r.pose, r.covariance)) }).collect()
                }
            };
            // Chi-square gate on every accepted hypothesis.
            let mut newly = 0;
            for (&(oi, h), &pi) in &accepted {
                if gated.contains(&(oi, h)) {
                    continue;
                }
                let p = &pairs[pi];
                let (Some(xa), Some(xb)) = (solution.get(&p.a), solution.get(&p.b)) else { continue };
                let Some((_, ci)) = cand_index[oi][usize::from(h)] else { continue };
                let cand = &p.candidates[ci];
                let chi2 = candidate_chi2(&xa.0, &xb.0, cand);
                if chi2 > self.params.chi2_gate {
                    gated.insert((oi, h));
                    newly += 1;
                }
            }
            if newly == 0 {
                break;
            }
        }

        // Verdicts, one report per hypothesis (primary, then the alternative).
        let mut edges: Vec<EdgeReport> = Vec::new();
        let mut rejected = ReasonCounts::default();
        for (i, (_, s)) in entries.iter().enumerate() {
            let o = &s.obs;
            let n_hyp = if o.alternative.is_some() { 2 } else { 1 };
            let any_accepted = (0..n_hyp).any(|h| accepted.contains_key(&(i, h)) && !gated.contains(&(i, h)));
            for h in 0..n_hyp {
                let verdict = if gated.contains(&(i, h)) {
                    Some(RejectReason::ChiSquare)
                } else if accepted.contains_key(&(i, h)) {
                    None
                } else if any_accepted {
                    Some(RejectReason::FlippedHypothesis)
                } else {
                    Some(RejectReason::Inconsistent)
                };
                let chi2 = cand_index[i][usize::from(h)].map_or(f64::NAN, |(pi, ci)| {
                    let p = &pairs[pi];
                    match (solution.get(&p.a), solution.get(&p.b)) {
                        (Some(xa), Some(xb)) => candidate_chi2(&xa.0, &xb.0, &p.candidates[ci]),
                        _ => f64::NAN,
                    }
                });
                match &verdict {
                    Some(r) => rejected.add(r),
                    None => solve_stats.accepted += 1,
                }
                edges.push(EdgeReport {
                    observer: o.observer,
                    camera: o.camera,
                    target_marker: o.target_marker,
                    target_vehicle: Some(s.target),
                    stamp_ns: o.stamp_ns,
                    frame_seq: o.frame_seq,
                    rejected: verdict,
                    chi2,
                });
            }
        }
        solve_stats.rejected = rejected;
        let mut pending = std::mem::take(&mut self.pending);
        pending.sort_by(|x, y| report_order(x).cmp(&report_order(y)));
        edges.extend(pending);
        edges.sort_by(|x, y| (x.stamp_ns, x.observer, x.camera, x.frame_seq, x.target_marker).cmp(&(y.stamp_ns, y.observer, y.camera, y.frame_seq, y.target_marker)));

        // Vehicles.
        let in_window: BTreeSet<VehicleId> = entries.iter().flat_map(|(_, s)| [s.obs.observer, s.target]).collect();
        let mut vehicles = Vec::with_capacity(self.fleet.vehicles.len());
        let mut ids: Vec<VehicleId> = self.fleet.vehicles.iter().map(|v| v.id).collect();
        ids.sort_unstable();
        for v in ids {
            let alive = self.alive.get(&v).copied().unwrap_or(true);
            let last_seen_ns = self.last_seen.get(&v).copied().unwrap_or(0);
            let (state, pose, covariance) = if v == reference {
                (if alive { VehicleState::Live } else { VehicleState::Stale }, Pose::identity(), Cov6::zeros())
            } else if let Some((pose, cov)) = solution.get(&v) {
                self.last_estimate.insert(v, (*pose, *cov, last_seen_ns));
                (if alive { VehicleState::Live } else { VehicleState::Stale }, *pose, *cov)
            } else {
                let state = if !alive {
                    VehicleState::Stale
                } else if in_window.contains(&v) {
                    VehicleState::Unobserved
                } else if last_seen_ns > 0 {
                    VehicleState::Stale
                } else {
                    VehicleState::Unobserved
                };
                match self.last_estimate.get(&v) {
                    // The last fused pose, its covariance grown with the time since.
                    Some((pose, cov, seen)) => {
                        let age_s = now_ns.saturating_sub(*seen) as f64 * 1e-9;
                        (state, *pose, self.params.age_inflation.inflate(cov, age_s))
                    }
                    None => (state, Pose::identity(), Cov6::identity() * NO_INFORMATION_VARIANCE),
                }
            };
            vehicles.push(VehicleEstimate {
                vehicle: v,
                state,
                reference_from_vehicle: pose,
                covariance,
                last_seen_ns,
            });
        }
        solve_stats.localized = solution.len().max(1);

        self.seq += 1;
        self.stats.solves += 1;
        self.stats.last_solve = solve_stats;
        FleetMap {
            fleet: self.fleet.name.clone(),
            producer: self.producer.clone(),
            seq: self.seq,
            stamp_ns: now_ns,
            reference,
            vehicles,
            edges,
            solve_time_us: started.map_or(0, |t| t.elapsed().as_micros() as u64),
        }
    }
}

/// Total order of reports of the same detection (rejection reason, then chi2 bits).
fn report_order(r: &EdgeReport) -> (u64, VehicleId, u8, u64, u32, Option<usize>, u64) {
    (
        r.stamp_ns,
        r.observer,
        r.camera,
        r.frame_seq,
        r.target_marker,
        r.rejected.as_ref().map(ReasonCounts::index),
        r.chi2.to_bits(),
    )
}

fn candidate_chi2(ref_from_a: &Pose, ref_from_b: &Pose, c: &Candidate) -> f64 {
    solver::edge_chi2(ref_from_a, ref_from_b, &c.a_from_b, &c.information)
}

/// Vehicles reachable from `root` through `constraints`.
fn connected_to(root: VehicleId, constraints: &[solver::Constraint]) -> BTreeSet<VehicleId> {
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
