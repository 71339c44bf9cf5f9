//! Swarm fusion: composes every vehicle's marker observations into one
//! consistent relative map over the vehicle IDs.
//!
//! [`Fusion`] keeps a sliding window of observations (each admitted or
//! rejected with a [`RejectReason`] on arrival), and on [`Fusion::solve`]:
//!
//! 1. inflates each observation's covariance with its age ([`AgeInflation`]);
//! 2. fuses each track's frames (same observer, camera and marker) into
//!    time-consistent groups, one information-weighted candidate per group and
//!    hypothesis, so that the checks run over a pair's tracks rather than
//!    over every frame; then picks, per vehicle pair, the mutually consistent
//!    candidates and between pairs the cycle-consistent ones, the planar-flip
//!    twins being mutually exclusive candidates ([`consistency`], PCM-style).
//!    Every observation inherits its group's verdict. Groups are built from
//!    each track's newest frame backwards; an older group that no longer
//!    agrees with the newest frame is `Superseded` (the vehicles moved), and
//!    a group whose frames show a significant relative velocity is brought to
//!    its newest frame's time first ([`MotionModel`]), so that a manoeuvring
//!    vehicle is followed rather than outvoted by where it has been;
//! 3. solves the pose graph on SE(3) by Levenberg–Marquardt with a robust
//!    kernel, the reference vehicle fixing the gauge, initialized by the
//!    spanning tree of step 2 ([`solver`]);
//! 4. gates every accepted observation's own residual against the solution
//!    (chi-square), re-solving without the rejects;
//! 5. writes a [`FleetMap`]: every vehicle's `reference_from_vehicle` with its
//!    marginal covariance and state, every observation's verdict.
//!
//! **Edge reports** are per *hypothesis*: an observation carrying a planar-flip
//! `alternative` gets two [`EdgeReport`]s with the same key, the primary's
//! first, then the alternative's. When the flip was the primary, the primary
//! reads `FlippedHypothesis` and the alternative `None` (accepted). Rejections
//! on arrival are reported once, in the next map. `chi2` is the squared
//! Mahalanobis residual against the solution under the age-inflated
//! covariance (NaN when either vehicle is not localized).
//!
//! **Vehicle states**: `Live` (localized from the window, liveliness token
//! present); `Stale` (token gone, or no data in the window though seen before:
//! the last fused pose is reported, its covariance grown by [`AgeInflation`]
//! since); `Unobserved` (never seen, or data in the window but no accepted
//! path to the reference: identity pose, covariance
//! [`NO_INFORMATION_VARIANCE`]·I unless a last pose exists).
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
//! `apex-solver` 1.5 Rust 1.93 (the workspace promises 1.88), and none exposes
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
use proto::{
    EdgeReport, FleetMap, Observation, RejectReason, VehicleEstimate, VehicleId, VehicleState,
};
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
    /// Constant-velocity compensation of each track's frames.
    #[serde(default)]
    pub motion: MotionModel,
}

/// How a track's frames taken at different times are brought to one instant.
///
/// Within a group of a track (frames of one camera seeing one marker that
/// agree with its newest frame), the relative pose is fitted as
/// `ξ(t) = x + v·(t − t_newest)` in the tangent space at the newest frame
/// (weighted least squares with the frames' information and a zero-mean
/// prior on `v`). When `v` is significant (its squared Mahalanobis norm above
/// `significance_chi2`), every frame is moved to `t_newest` along `v` and its
/// covariance grows by `Δt²·Σ_v`; otherwise the frames are fused as they are
/// (a static pair loses no precision to a velocity it does not have).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MotionModel {
    /// Switch (default true; false: frames are fused as if nothing moved).
    pub enabled: bool,
    /// Prior standard deviation of the relative linear velocity, m/s (default 0.5).
    pub velocity_prior_m_s: f64,
    /// Prior standard deviation of the relative angular velocity, rad/s (default 0.3).
    pub angular_velocity_prior_rad_s: f64,
    /// Gate on `vᵀ Σ_v⁻¹ v` above which the velocity is used (default 16.81 = χ²₆ at 99%).
    pub significance_chi2: f64,
}

impl Default for MotionModel {
    fn default() -> Self {
        Self {
            enabled: true,
            velocity_prior_m_s: 0.5,
            angular_velocity_prior_rad_s: 0.3,
            significance_chi2: 16.81,
        }
    }
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
            motion: MotionModel::default(),
        }
    }
}

/// Counts per [`RejectReason`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReasonCounts([u64; 12]);

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
            Superseded => 11,
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
    /// Track groups whose frames were moved to their newest frame's time ([`MotionModel`]).
    pub moving_groups: usize,
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
    /// Wall time of the consistency checks and of the LM solves (incl. gate
    /// rounds), µs; 0 unless [`FusionParams::record_solve_time`].
    pub consistency_us: u64,
    pub lm_us: u64,
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
    pub fn ingest(
        &mut self,
        obs: Observation,
        arrived_on: VehicleId,
        now_ns: u64,
    ) -> Result<(), RejectReason> {
        self.stats.received += 1;
        let limits = self.admission();
        let target = match self.fleet.marker_owner(obs.codes, obs.target_marker) {
            proto::config::MarkerOwner::Vehicle(v) => Some(v),
            _ => None,
        };
        let report = early_report(&obs, target, RejectReason::Invalid);
        let (observer, stamp) = (obs.observer, obs.stamp_ns);
        match self
            .window
            .admit(&self.fleet, obs, arrived_on, now_ns, &limits)
        {
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

    /// The previous solution's relative attitude of every pair in `pairs`
    /// whose two vehicles were fused within the window, with the turn
    /// allowed since: 8° plus 30°/s of age, at most 30° (planar-flip twins
    /// of a marker seen obliquely are tens of degrees apart).
    fn attitude_prior(&self, pairs: &[PairCandidates], now_ns: u64) -> consistency::Prior {
        let window_ns = seconds_to_ns(self.params.window_s);
        let mut prior = consistency::Prior::new();
        for p in pairs {
            let (Some(a), Some(b)) = (self.last_estimate.get(&p.a), self.last_estimate.get(&p.b))
            else {
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

        // Every hypothesis of every observation as measured (`observer_from_target`,
        // not inverted: that is done once per fused group) with its
        // age-inflated covariance.
        let entries: Vec<(&ObservationKey, &window::Stored)> = self.window.entries.iter().collect();
        let mut frames: Vec<Frame> = entries
            .iter()
            .enumerate()
            .map(|(i, (_, s))| {
                let o = &s.obs;
                let age_s = now_ns.saturating_sub(o.stamp_ns) as f64 * 1e-9;
                let inflate = |c: &Cov6| self.params.age_inflation.inflate(c, age_s);
                Frame {
                    observer: o.observer,
                    target: s.target,
                    stamp_ns: o.stamp_ns,
                    hyps: [
                        Candidate::new(i, 0, o.observer_from_target, inflate(&o.covariance)),
                        o.alternative.as_ref().and_then(|alt| {
                            Candidate::new(i, 1, alt.observer_from_target, inflate(&alt.covariance))
                        }),
                    ],
                }
            })
            .collect();
        // Tracks (observer, camera, marker) cut into time-consistent groups,
        // each group's frames fused per hypothesis into one candidate.
        let (groups, superseded) = group_tracks(
            &entries,
            &frames,
            self.params.consistency.gate_chi2,
            self.params.consistency.fuse_tracks,
        );
        let mut superseded_frame = vec![false; frames.len()];
        for (g, members) in groups.iter().enumerate() {
            if superseded[g] {
                members.iter().for_each(|&i| superseded_frame[i] = true);
            } else if self.params.motion.enabled {
                solve_stats.moving_groups +=
                    usize::from(compensate_motion(&mut frames, members, &self.params.motion));
            }
        }
        let mut by_pair: BTreeMap<(VehicleId, VehicleId), Vec<Candidate>> = BTreeMap::new();
        for (g, members) in groups.iter().enumerate() {
            if superseded[g] {
                continue;
            }
            let f = &frames[members[0]];
            for h in 0..2u8 {
                if let Some(c) = fuse_group(&frames, members, g, h, &[]) {
                    by_pair.entry(f.pair()).or_default().push(c);
                }
            }
        }
        let mut pairs: Vec<PairCandidates> = by_pair
            .into_iter()
            .map(|((a, b), candidates)| {
                let clusters = consistency::cluster_pair(&candidates, &self.params.consistency);
                PairCandidates {
                    a,
                    b,
                    candidates,
                    clusters,
                }
            })
            .collect();
        consistency::vote_triangles(&mut pairs, self.params.consistency.gate_chi2);
        let prior = self.attitude_prior(&pairs, now_ns);
        let selection = consistency::select_with_prior(
            &pairs,
            reference,
            self.params.consistency.gate_chi2,
            &prior,
        );
        solve_stats.pairs = pairs.len();
        solve_stats.clusters = pairs.iter().map(|p| p.clusters.len()).sum();

        // Accepted hypotheses: (observation, hypothesis) → pair index; an
        // observation inherits the verdict of its group's candidate.
        let mut accepted: BTreeMap<(usize, u8), usize> = BTreeMap::new();
        // Per pair, the accepted group candidates: (group, hypothesis, candidate index).
        let mut accepted_groups: Vec<Vec<(usize, u8, usize)>> = vec![Vec::new(); pairs.len()];
        for (pi, p) in pairs.iter().enumerate() {
            if let Some(c) = selection.choice[pi] {
                for &m in &p.clusters[c].members {
                    let cand = &p.candidates[m];
                    let h = cand.hypothesis;
                    accepted_groups[pi].push((cand.observation, h, m));
                    for &i in &groups[cand.observation] {
                        if frames[i].hyps[usize::from(h)].is_some() {
                            accepted.insert((i, h), pi);
                        }
                    }
                }
            }
        }
        let elapsed_us =
            |t: Option<std::time::Instant>| t.map_or(0, |t| t.elapsed().as_micros() as u64);
        solve_stats.consistency_us = elapsed_us(started);
        let lm_started = self.params.record_solve_time.then(std::time::Instant::now);
        let tree = &selection.trees[0];
        let initial = tree.poses();
        let mut gated: BTreeSet<(usize, u8)> = BTreeSet::new();
        // Each hypothesis' chi2 against the latest solution (filled by the gate).
        let mut chi2_cache: Vec<[Option<f64>; 2]> = vec![[None; 2]; frames.len()];
        let mut solution: BTreeMap<VehicleId, (Pose, Cov6)> = BTreeMap::new();
        for round in 0..self.params.max_gate_rounds.max(1) {
            solve_stats.gate_rounds = round + 1;
            // One fused constraint per chosen pair in the reference tree, without the gated members.
            let mut constraints = Vec::new();
            for (pi, p) in pairs.iter().enumerate() {
                if selection.choice[pi].is_none() {
                    continue;
                }
                if !tree.contains(p.a) || !tree.contains(p.b) {
                    continue;
                }
                // The accepted groups of the pair, each without its gated frames.
                let items: Vec<(Pose, Cov6)> = accepted_groups[pi]
                    .iter()
                    .filter_map(|&(g, h, m)| {
                        let members = &groups[g];
                        let out: Vec<usize> = members
                            .iter()
                            .copied()
                            .filter(|&i| gated.contains(&(i, h)))
                            .collect();
                        if out.is_empty() {
                            Some(p.candidates[m])
                        } else {
                            fuse_group(&frames, members, g, h, &out)
                        }
                    })
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
            let init: BTreeMap<VehicleId, Pose> = initial
                .iter()
                .filter(|(v, _)| connected.contains(v))
                .map(|(v, p)| (*v, *p))
                .collect();
            let sp = solver::SolverParams {
                robust: self.params.robust,
                max_iterations: self.params.max_iterations,
                ..solver::SolverParams::default()
            };
            solution = match solver::solve(reference, &init, &constraints, &sp) {
                Ok(s) => {
                    solve_stats.lm_iterations += s.iterations;
                    solve_stats.solver_failed = false;
                    s.poses
                        .iter()
                        .map(|(v, p)| {
                            (
                                *v,
                                (*p, s.covariances.get(v).copied().unwrap_or(Cov6::zeros())),
                            )
                        })
                        .collect()
                }
                Err(e) => {
                    tracing::warn!(
                        "pose graph solve failed ({e}); reporting the spanning-tree poses"
                    );
                    solve_stats.solver_failed = true;
                    init.keys()
                        .map(|&v| {
                            let r = tree.relative(reference, v);
                            (v, (r.pose, r.covariance))
                        })
                        .collect()
                }
            };
            // Chi-square gate on every accepted hypothesis (each observation on its own).
            let mut newly = 0;
            chi2_cache.iter_mut().for_each(|c| *c = [None; 2]);
            for &(oi, h) in accepted.keys() {
                if gated.contains(&(oi, h)) {
                    continue;
                }
                let chi2 = frames[oi].chi2(usize::from(h), &solution);
                chi2_cache[oi][usize::from(h)] = Some(chi2);
                if chi2 > self.params.chi2_gate {
                    gated.insert((oi, h));
                    newly += 1;
                }
            }
            if newly == 0 {
                break;
            }
        }

        solve_stats.lm_us = elapsed_us(lm_started);

        // Verdicts, one report per hypothesis (primary, then the alternative).
        let mut edges: Vec<EdgeReport> = Vec::new();
        let mut rejected = ReasonCounts::default();
        for (i, (_, s)) in entries.iter().enumerate() {
            let o = &s.obs;
            let n_hyp = if o.alternative.is_some() { 2 } else { 1 };
            let any_accepted =
                (0..n_hyp).any(|h| accepted.contains_key(&(i, h)) && !gated.contains(&(i, h)));
            for h in 0..n_hyp {
                let verdict = if gated.contains(&(i, h)) {
                    Some(RejectReason::ChiSquare)
                } else if accepted.contains_key(&(i, h)) {
                    None
                } else if superseded_frame[i] {
                    Some(RejectReason::Superseded)
                } else if any_accepted {
                    Some(RejectReason::FlippedHypothesis)
                } else {
                    Some(RejectReason::Inconsistent)
                };
                let chi2 = chi2_cache[i][usize::from(h)]
                    .unwrap_or_else(|| frames[i].chi2(usize::from(h), &solution));
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
        pending.sort_by_key(report_order);
        edges.extend(pending);
        edges.sort_by_key(|e| {
            (
                e.stamp_ns,
                e.observer,
                e.camera,
                e.frame_seq,
                e.target_marker,
            )
        });

        // Vehicles.
        let in_window: BTreeSet<VehicleId> = entries
            .iter()
            .flat_map(|(_, s)| [s.obs.observer, s.target])
            .collect();
        let mut vehicles = Vec::with_capacity(self.fleet.vehicles.len());
        let mut ids: Vec<VehicleId> = self.fleet.vehicles.iter().map(|v| v.id).collect();
        ids.sort_unstable();
        for v in ids {
            let alive = self.alive.get(&v).copied().unwrap_or(true);
            let last_seen_ns = self.last_seen.get(&v).copied().unwrap_or(0);
            let (state, pose, covariance) = if v == reference {
                (
                    if alive {
                        VehicleState::Live
                    } else {
                        VehicleState::Stale
                    },
                    Pose::identity(),
                    Cov6::zeros(),
                )
            } else if let Some((pose, cov)) = solution.get(&v) {
                self.last_estimate.insert(v, (*pose, *cov, last_seen_ns));
                (
                    if alive {
                        VehicleState::Live
                    } else {
                        VehicleState::Stale
                    },
                    *pose,
                    *cov,
                )
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
                    None => (
                        state,
                        Pose::identity(),
                        Cov6::identity() * NO_INFORMATION_VARIANCE,
                    ),
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

/// One observation's hypotheses as measured, `observer_from_target` (in the
/// [`Candidate`]'s `a_from_b`), with age-inflated covariances (`None`: absent
/// or with a covariance that cannot be inverted).
struct Frame {
    observer: VehicleId,
    target: VehicleId,
    stamp_ns: u64,
    hyps: [Option<Candidate>; 2],
}

impl Frame {
    /// The vehicle pair, lower ID first.
    fn pair(&self) -> (VehicleId, VehicleId) {
        (
            self.observer.min(self.target),
            self.observer.max(self.target),
        )
    }
    /// Squared Mahalanobis residual of hypothesis `h` against the solution
    /// (NaN when either vehicle is not localized or the hypothesis is absent).
    fn chi2(&self, h: usize, solution: &BTreeMap<VehicleId, (Pose, Cov6)>) -> f64 {
        match (
            self.hyps[h].as_ref(),
            solution.get(&self.observer),
            solution.get(&self.target),
        ) {
            (Some(c), Some(xo), Some(xt)) => {
                solver::edge_chi2(&xo.0, &xt.0, &c.a_from_b, &c.information)
            }
            _ => f64::NAN,
        }
    }
}

/// Hypothesis `h` of group `g` (its frames `members`, those in `without`
/// left out) fused into one candidate `a_from_b` of the pair (a < b): the
/// information-weighted mean in the observer's frame, then inverted once if
/// the observer is `b`. `None` when no frame has the hypothesis.
fn fuse_group(
    frames: &[Frame],
    members: &[usize],
    g: usize,
    h: u8,
    without: &[usize],
) -> Option<Candidate> {
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
    let measured = PoseWithCovariance::new(pose, cov);
    let a_from_b = if f.observer < f.target {
        measured
    } else {
        solver::invert(&measured)
    };
    Candidate::new(g, h, a_from_b.pose, a_from_b.covariance).map(|c| c.with_weight(hyp.len()))
}

/// Groups of observations (indices into `frames`, ascending) that are fused
/// into one candidate per hypothesis before the consistency checks, so that
/// PCM runs over a pair's tracks, not over every frame.
///
/// A track is one camera's view of one marker ID (same observer, camera,
/// code set, marker). Within a track, in window order, a frame joins the first
/// group whose leaders (its first frame with each hypothesis) it is consistent
/// with, hypothesis by hypothesis (squared Mahalanobis distance under the
/// summed covariances within `gate_chi2`), and starts a new group otherwise.
/// A flipped frame (primary = the twin) thus never shares a group with
/// unflipped ones, nor a misread ID with the true owner of the marker, and
/// the two hypotheses of one group stay mutually exclusive exactly like those
/// of one observation. `fuse = false` gives one group per observation.
///
/// Motion: the window spans seconds, and vehicles that manoeuvre change their
/// relative pose by more than a frame's noise in that time. A track whose
/// newest frame no longer agrees with an older group under any pairing of
/// hypotheses (flips excepted: a group that matches with the hypotheses
/// swapped is kept) has seen its target move: that older group is returned
/// as *superseded* and must not outvote the present. Only frames of the same
/// camera and marker can supersede each other, so a misread ID or a flip
/// never erases another track's evidence.
fn group_tracks(
    entries: &[(&ObservationKey, &window::Stored)],
    frames: &[Frame],
    gate_chi2: f64,
    fuse: bool,
) -> (Vec<Vec<usize>>, Vec<bool>) {
    let consistent = |c: &Candidate, leader: &Candidate| {
        let r = solver::difference(&c.a_from_b, &leader.a_from_b);
        (r.transpose() * c.information * r)[0] <= gate_chi2
            || consistency::mahalanobis2(
                &c.a_from_b,
                &c.covariance,
                &leader.a_from_b,
                &leader.covariance,
            ) <= gate_chi2
    };
    type Track = (VehicleId, u8, &'static str, u32);
    /// A group of a track: its index and its leader per hypothesis.
    type OpenGroup = (usize, [Option<usize>; 2]);
    let mut open: BTreeMap<Track, Vec<OpenGroup>> = BTreeMap::new();
    let mut groups: Vec<Vec<usize>> = Vec::new();
    // Each track's group holding its newest frame.
    let mut newest: BTreeMap<Track, usize> = BTreeMap::new();
    // Newest first (entries are in time order): a group's leaders are its
    // most recent frames, so it describes the present.
    for (i, (key, _)) in entries.iter().enumerate().rev() {
        let f = &frames[i];
        if f.hyps[0].is_none() {
            // Nothing to compare with: the observation stands alone.
            groups.push(vec![i]);
            continue;
        }
        let track = (key.observer, key.camera, key.codes, key.marker);
        let list = open.entry(track).or_default();
        let home = fuse
            .then(|| {
                list.iter_mut().find(|(_, leaders)| {
                    (0..2).all(|h| match (&f.hyps[h], leaders[h]) {
                        (Some(c), Some(l)) => {
                            frames[l].hyps[h].as_ref().is_some_and(|l| consistent(c, l))
                        }
                        _ => true,
                    })
                })
            })
            .flatten();
        let g = match home {
            Some((g, leaders)) => {
                groups[*g].push(i);
                for h in 0..2 {
                    if leaders[h].is_none() && f.hyps[h].is_some() {
                        leaders[h] = Some(i);
                    }
                }
                *g
            }
            None => {
                list.push((groups.len(), [Some(i), f.hyps[1].as_ref().map(|_| i)]));
                groups.push(vec![i]);
                groups.len() - 1
            }
        };
        newest.entry(track).or_insert(g);
    }
    let mut superseded = vec![false; groups.len()];
    for (track, list) in &open {
        let now = newest[track];
        // Members are still newest first.
        let Some(&latest) = groups[now].first() else {
            continue;
        };
        for &(g, _) in list {
            let Some(&last) = groups[g].first() else {
                continue;
            };
            // Only the past is superseded: two frames of one instant (a
            // misread ID beside the marker itself) are for the consistency
            // checks to judge, not for the motion rule.
            if g == now || frames[last].stamp_ns >= frames[latest].stamp_ns {
                continue;
            }
            let agrees = frames[last].hyps.iter().flatten().any(|old| {
                frames[latest]
                    .hyps
                    .iter()
                    .flatten()
                    .any(|new| consistent(old, new))
            });
            superseded[g] = !agrees;
        }
    }
    // Groups in ascending order of their first frame, members ascending.
    let mut order: Vec<usize> = (0..groups.len()).collect();
    groups.iter_mut().for_each(|m| m.sort_unstable());
    order.sort_by_key(|&g| groups[g][0]);
    let sorted = order.iter().map(|&g| groups[g].clone()).collect();
    let flags = order.iter().map(|&g| superseded[g]).collect();
    (sorted, flags)
}

/// [`MotionModel`] on one group (`members` ascending in time): fits the
/// relative velocity of each hypothesis and, when it is significant, moves
/// every member to the newest member's time. Returns whether any hypothesis
/// was moved.
fn compensate_motion(frames: &mut [Frame], members: &[usize], model: &MotionModel) -> bool {
    use nalgebra::{SMatrix, SVector};
    let Some(&newest) = members.last() else {
        return false;
    };
    if members.len() < 2 {
        return false;
    }
    let t_n = frames[newest].stamp_ns;
    let mut moved = false;
    for h in 0..2 {
        let Some(anchor) = frames[newest].hyps[h].map(|c| c.a_from_b) else {
            continue;
        };
        // Normal equations of [x; v] (12 unknowns).
        let mut a = SMatrix::<f64, 12, 12>::zeros();
        let mut b = SVector::<f64, 12>::zeros();
        let mut used = 0;
        for &i in members {
            let Some(c) = &frames[i].hyps[h] else {
                continue;
            };
            let d = -((t_n - frames[i].stamp_ns) as f64) * 1e-9;
            let r = proto::geometry::difference(&c.a_from_b, &anchor);
            let w = c.information;
            let wr = w * r;
            let mut block = |r0: usize, c0: usize, m: Cov6| {
                let mut view = a.fixed_view_mut::<6, 6>(r0, c0);
                view += m;
            };
            block(0, 0, w);
            block(0, 6, w * d);
            block(6, 0, w * d);
            block(6, 6, w * (d * d));
            let mut top = b.fixed_rows_mut::<6>(0);
            top += wr;
            let mut bottom = b.fixed_rows_mut::<6>(6);
            bottom += wr * d;
            used += 1;
        }
        if used < 2 {
            continue;
        }
        for k in 0..3 {
            a[(6 + k, 6 + k)] += model.velocity_prior_m_s.powi(-2);
            a[(9 + k, 9 + k)] += model.angular_velocity_prior_rad_s.powi(-2);
        }
        let Some(ch) = a.cholesky() else {
            continue;
        };
        let sol = ch.solve(&b);
        let cov = ch.inverse();
        let v: SVector<f64, 6> = sol.fixed_rows::<6>(6).into_owned();
        let cov_v: Cov6 = cov.fixed_view::<6, 6>(6, 6).into_owned();
        let significance = cov_v.cholesky().map_or(0.0, |c| v.dot(&c.solve(&v)));
        if significance.is_nan() || significance <= model.significance_chi2 {
            continue;
        }
        for &i in members {
            let Some(c) = frames[i].hyps[h] else {
                continue;
            };
            let d = -((t_n - frames[i].stamp_ns) as f64) * 1e-9;
            let r = proto::geometry::difference(&c.a_from_b, &anchor);
            let pose = proto::geometry::perturb(&anchor, &(r - v * d));
            let grown = c.covariance + cov_v * (d * d);
            frames[i].hyps[h] = Candidate::new(c.observation, c.hypothesis, pose, grown);
        }
        moved = true;
    }
    moved
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
