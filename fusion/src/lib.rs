//! Swarm fusion: composes every vehicle's marker observations into one
//! consistent relative map over the vehicle IDs.
//!
//! [`Fusion`] keeps a sliding window of observations (each admitted or
//! rejected with a [`RejectReason`] on arrival), and [`Fusion::solve`] runs
//! these steps (each a module of `solve/` with its own input and output):
//!
//! 1. **frames**: each observation's hypotheses with their covariance
//!    inflated by age ([`AgeInflation`]);
//!    With the vehicles' own navigation ([`nav`]), each hypothesis whose
//!    implied tilt, depth or heading of the target contradicts the target's
//!    IMU, pressure sensor or compass is taken out here (`Gravity`, `Depth`,
//!    `Heading`);
//! 2. **groups**: each track's frames (same observer, camera and marker) cut
//!    into time-consistent groups, newest frame first; an older group that no
//!    longer agrees with the newest frame is `Superseded` (the vehicles
//!    moved), and a group whose frames show a significant relative velocity
//!    is brought to its newest frame's time ([`MotionModel`]), so that a
//!    manoeuvring vehicle is followed rather than outvoted by where it has
//!    been. A pair seen to move (a significant fit, or a track of its
//!    own whose confirmed present superseded its past) has every one of
//!    its frames made as uncertain as that motion over its age, so its
//!    other tracks' older frames cannot outvote its newest either;
//! 3. **hypotheses**: one information-weighted candidate per group and
//!    hypothesis; per vehicle pair the mutually consistent candidates,
//!    between pairs the cycle-consistent ones, the planar-flip twins being
//!    mutually exclusive ([`consistency`], PCM-style), chosen along a
//!    spanning tree grown from the reference. Every observation inherits its
//!    group's verdict;
//! 4. **init**: one fused constraint per chosen pair, initialized by that
//!    spanning tree;
//! 5. **LM**: the pose graph solved on SE(3) by Levenberg–Marquardt with a
//!    robust kernel, the reference vehicle fixing the gauge ([`solver`]);
//! 6. **gate**: every accepted observation's own residual against the
//!    solution gated (chi-square), re-solving without the rejects;
//!    with [`NavParams::odometry_factors`] (off by default) the window is
//!    then solved again **over time**: a state per vehicle and 0.1 s slot,
//!    each accepted frame a marker edge at its slot, each vehicle's own
//!    odometry (DVL velocity, tilt, heading) a between-factor from slot to
//!    slot, and the map the states at the newest accepted frame
//!    (`solve/smooth.rs`; vehicles without odometry keep one state);
//! 7. **map**: a [`FleetMap`](proto::FleetMap): every vehicle's
//!    `reference_from_vehicle` with its marginal covariance and state, every
//!    observation's verdict.
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
//! [`NO_INFORMATION_VARIANCE`]·I unless a last pose exists); `Predicted`
//! (alive but not localized in this solve, last localized at most
//! [`NavParams::max_predict_s`] ago, and both it and the reference send nav
//! with velocity and heading: its last fused pose carried forward by both
//! vehicles' odometry, the covariance grown by the dead reckoning). With
//! [`NavParams::propagate_live`] (off by default) and that nav, a `Live` vehicle's
//! pose is likewise carried from the newest accepted frame it rests on to
//! the map's `now_ns` (the map says where the vehicles are now, not at
//! their last camera frame), the covariance grown the same way; without it
//! the pose is as of its frames.
//!
//! Same inputs give a bit-identical map, whatever the order they arrived in
//! (everything is kept in ordered maps keyed by capture time and identity), so
//! a central instance and per-vehicle instances hearing the same observations
//! agree. The library never reads the clock for `now`: callers pass `now_ns`.
//! The one wall-clock figure is [`FleetMap::solve_time_us`](proto::FleetMap::solve_time_us),
//! a diagnostic that [`FusionParams::record_solve_time`] can switch off.
//!
//! The solver is written here rather than taken from a pose-graph crate
//! because none gives marginal covariances in shoal's perturbation
//! convention ([`proto::geometry`]) on the workspace's nalgebra and Rust
//! versions (ARCHITECTURE.md, "Dependencies and why"); `benches/solve.rs`
//! measures it.
//!
//! The Zenoh service around this library is `shoal_services::fusion`;
//! formation controllers read maps through [`client::MapView`] (and keep the
//! newest with [`client::LatestMap`]).

// A library reports failures as errors; an `unwrap()` that cannot fail says why with `expect`.
#![warn(clippy::unwrap_used)]

extern crate shoal_proto as proto;

pub mod client;
pub mod consistency;
pub mod export;
pub mod formation;
pub mod linalg;
pub mod link;
pub mod nav;
mod par;
mod solve;
pub mod solver;
mod sparse;
mod window;

pub use client::{LatestMap, MapView, RelativePose};
pub use consistency::ConsistencyParams;
pub use nav::{NavParams, NavRejected};
pub use solve::motion::MotionModel;
pub use solver::RobustKernel;
pub use window::AgeInflation;

use proto::config::Fleet;
use proto::geometry::{Cov6, Pose};
use proto::{EdgeReport, NavState, Observation, RejectReason, VehicleId};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use window::{early_report, Admission, Window};

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
    /// Fill [`FleetMap::solve_time_us`](proto::FleetMap::solve_time_us) from the wall clock (default true; off for bit-identical maps).
    pub record_solve_time: bool,
    /// Constant-velocity compensation of each track's frames.
    #[serde(default)]
    pub motion: MotionModel,
    /// Gravity and depth checks with the vehicles' own navigation.
    #[serde(default)]
    pub nav: NavParams,
    /// Window of observations that arrived over a slow link
    /// ([`Fusion::ingest_linked`]), seconds (default
    /// [`link::LINK_WINDOW_S`], 8 s: what crosses an acoustic link is 1 s
    /// old or more). A vehicle's own observations keep `window_s`, so a
    /// manoeuvring neighbour it sees itself is not outvoted by seconds-old news.
    #[serde(default = "default_link_window_s")]
    pub link_window_s: f64,
    /// Threads for the solve's per-observation steps (default 0: the
    /// machine's available parallelism; 1: the calling thread only). The
    /// map is bit for bit the same at any count; only the wall time changes.
    /// On a machine whose cores are busy with other processes a second
    /// thread gains nothing and costs a little (docs/results.md): use 1.
    #[serde(default)]
    pub threads: usize,
    /// Observations one vehicle may hold in the window (default
    /// [`DEFAULT_MAX_WINDOW_PER_OBSERVER`]); beyond, its oldest are dropped
    /// and counted ([`FusionStats::crowded_out`]). Bounds fusion's memory and
    /// solve time against a node that floods, whatever its stamps.
    #[serde(default = "default_max_window_per_observer")]
    pub max_window_per_observer: usize,
}

/// Default of [`FusionParams::max_window_per_observer`]: about twice what
/// five cameras at 30 frames/s, each frame reading 7 markers, send in a 2 s
/// window (2 100), so only a node sending far beyond any camera rig is
/// capped. At ~1.4 kB an entry (`shoal eval fusion` at 1 000 vehicles, an
/// upper bound: docs/results.md) that is under 6 MB per vehicle.
pub const DEFAULT_MAX_WINDOW_PER_OBSERVER: usize = 4096;

fn default_link_window_s() -> f64 {
    link::LINK_WINDOW_S
}

fn default_max_window_per_observer() -> usize {
    DEFAULT_MAX_WINDOW_PER_OBSERVER
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
            nav: NavParams::default(),
            link_window_s: link::LINK_WINDOW_S,
            threads: 0,
            max_window_per_observer: DEFAULT_MAX_WINDOW_PER_OBSERVER,
        }
    }
}

/// Counts per [`RejectReason`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReasonCounts([u64; 15]);

impl ReasonCounts {
    pub(crate) fn index(reason: &RejectReason) -> usize {
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
            Gravity => 12,
            Depth => 13,
            Heading => 14,
        }
    }
    pub fn get(&self, reason: &RejectReason) -> u64 {
        self.0[Self::index(reason)]
    }
    pub fn total(&self) -> u64 {
        self.0.iter().sum()
    }
    pub(crate) fn add(&mut self, reason: &RejectReason) {
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
    /// Hypotheses checked against both vehicles' roll/pitch, their depths and their headings.
    pub nav_tilt_checked: usize,
    pub nav_depth_checked: usize,
    pub nav_heading_checked: usize,
    /// The solver failed and the spanning-tree poses were reported instead.
    pub solver_failed: bool,
    /// Wall time of the consistency checks and of the LM solves (incl. gate
    /// rounds), µs; 0 unless [`FusionParams::record_solve_time`].
    pub consistency_us: u64,
    pub lm_us: u64,
    /// The consistency checks' time by step, µs (same condition): frames and
    /// nav checks; track groups and motion fits; pair candidates, clusters,
    /// triangle votes and the spanning-tree selection. Then the map (verdicts
    /// and vehicle estimates) after the LM.
    pub frames_us: u64,
    pub groups_us: u64,
    pub hypotheses_us: u64,
    pub map_us: u64,
    /// The window over time ([`NavParams::odometry_factors`]); all zero when it did not run.
    pub smoothing: SmoothingStats,
}

/// What the window over time ([`NavParams::odometry_factors`]) solved.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SmoothingStats {
    /// States (vehicle, time slot), and the vehicles with odometry over the window.
    pub states: usize,
    pub vehicles_over_time: usize,
    pub marker_factors: usize,
    pub odometry_factors: usize,
    /// Accepted frames left out because an end's odometry did not reach their slot.
    pub frames_left_out: usize,
    /// Accepted frames left out because they are older than the slots an
    /// end keeps ([`NavParams::odometry_max_states`]).
    pub frames_too_old: usize,
    pub iterations: usize,
    /// Wall time of building and solving the graph over time, µs (0 unless
    /// [`FusionParams::record_solve_time`]).
    pub smooth_us: u64,
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
    /// Admitted observations dropped again, oldest first, because their
    /// observer held more than [`FusionParams::max_window_per_observer`].
    pub crowded_out: u64,
    /// Nav states admitted, and refused (unknown vehicle, wrong key, invalid, stale, skewed).
    pub nav_ingested: u64,
    pub nav_rejected: u64,
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
    nav: nav::NavWindow,
    odometry: nav::Odometry,
    last_graph: Option<export::PoseGraph>,
    /// The last solve's factor graph over time, and its nodes' (vehicle, slot).
    last_time_graph: Option<(export::PoseGraph, Vec<(VehicleId, u32)>)>,
    pending: Vec<EdgeReport>,
    alive: BTreeMap<VehicleId, bool>,
    last_seen: BTreeMap<VehicleId, u64>,
    last_estimate: BTreeMap<VehicleId, (Pose, Cov6, u64)>,
    seq: u64,
    stats: FusionStats,
}

/// Covariance reported for a vehicle nothing is known about (σ = 1 km / 1000 rad).
pub const NO_INFORMATION_VARIANCE: f64 = 1e6;

pub(crate) fn seconds_to_ns(s: f64) -> u64 {
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
            nav: nav::NavWindow::default(),
            odometry: nav::Odometry::default(),
            last_graph: None,
            last_time_graph: None,
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
            link_window_ns: seconds_to_ns(self.params.link_window_s),
            max_clock_skew_ns: seconds_to_ns(self.params.max_clock_skew_s),
            max_std: self.params.max_std,
            max_per_observer: self.params.max_window_per_observer,
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
        self.ingest_from(obs, (arrived_on, false), now_ns)
    }

    /// [`Fusion::ingest`] for an observation that crossed a slow link (a
    /// compact packet from `shoal link`): kept for `link_window_s`.
    pub fn ingest_linked(
        &mut self,
        obs: Observation,
        arrived_on: VehicleId,
        now_ns: u64,
    ) -> Result<(), RejectReason> {
        self.ingest_from(obs, (arrived_on, true), now_ns)
    }

    fn ingest_from(
        &mut self,
        obs: Observation,
        source: (VehicleId, bool),
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
            .admit_from(&self.fleet, obs, source, now_ns, &limits)
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

    /// Admit a vehicle's own navigation state that arrived on `arrived_on`'s
    /// key at `now_ns` (the same window and clock-skew bounds as observations).
    pub fn ingest_nav(
        &mut self,
        nav: NavState,
        arrived_on: VehicleId,
        now_ns: u64,
    ) -> Result<(), NavRejected> {
        let limits = self.admission();
        let p = self.params.nav;
        let r = self.nav.admit(
            &self.fleet,
            nav,
            arrived_on,
            now_ns,
            &limits,
            p.max_samples_per_vehicle,
        );
        match r {
            Ok(()) => {
                self.stats.nav_ingested += 1;
                let predict_s = p.max_predict_s.max(0.0);
                if p.enabled && (predict_s > 0.0 || p.propagate_live) {
                    // Back to the oldest frame a Live pose may rest on (the
                    // window, or the link window for relayed news), plus the
                    // prediction span of an unseen vehicle.
                    let span_s =
                        predict_s + self.params.window_s.max(self.params.link_window_s) + 1.0;
                    // Enough samples for the whole span at 100 Hz.
                    let max = (span_s * 100.0) as usize;
                    self.odometry.add(&nav, seconds_to_ns(span_s), max);
                }
            }
            Err(_) => self.stats.nav_rejected += 1,
        }
        r
    }

    /// Admit a span of another vehicle's navigation that crossed a slow link
    /// (a compact packet from `shoal link`) on `arrived_on`'s key at
    /// `now_ns`: held as samples across the span for the link window
    /// ([`nav::NavWindow::admit_span`]), used by the nav checks only (no
    /// odometry crosses a link).
    pub fn ingest_linked_nav(
        &mut self,
        span: &proto::compact::NavSpan,
        arrived_on: VehicleId,
        now_ns: u64,
    ) -> Result<(), NavRejected> {
        let limits = self.admission();
        let max = self.params.nav.max_samples_per_vehicle;
        let r = self
            .nav
            .admit_span(&self.fleet, span, arrived_on, now_ns, &limits, max);
        match r {
            Ok(()) => self.stats.nav_ingested += 1,
            Err(_) => self.stats.nav_rejected += 1,
        }
        r
    }

    /// The pose graph of the last solve's final round (the constraints LM
    /// minimised and its spanning-tree start), for export ([`export`]);
    /// `None` before the first solve or when nothing was connected.
    pub fn last_graph(&self) -> Option<&export::PoseGraph> {
        self.last_graph.as_ref()
    }

    /// The last solve's factor graph over time ([`NavParams::odometry_factors`]):
    /// its nodes are numbered, node `n` being vehicle `nodes[n].0` at time
    /// slot `nodes[n].1` (0: the newest accepted frame). `None` when the
    /// last solve did not smooth.
    pub fn last_time_graph(&self) -> Option<(&export::PoseGraph, &[(VehicleId, u32)])> {
        self.last_time_graph
            .as_ref()
            .map(|(g, n)| (g, n.as_slice()))
    }

    /// Nav samples currently held (all vehicles).
    pub fn nav_len(&self) -> usize {
        self.nav.len()
    }

    /// Liveliness of a vehicle's node (its token appeared or disappeared).
    pub fn set_alive(&mut self, vehicle: VehicleId, alive: bool, _now_ns: u64) {
        if self.fleet.vehicle(vehicle).is_some() {
            self.alive.insert(vehicle, alive);
        }
    }

    pub fn stats(&self) -> FusionStats {
        FusionStats {
            crowded_out: self.window.crowded_out,
            ..self.stats.clone()
        }
    }

    /// Observations currently in the window.
    pub fn window_len(&self) -> usize {
        self.window.entries.len()
    }
}
