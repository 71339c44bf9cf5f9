//! [`Fusion::solve`] as its steps, each a module with its own input and
//! output types:
//!
//! ```text
//! window ─▶ frames ─▶ nav ─▶ groups ─▶ motion ─▶ hypotheses ─▶ init ─▶ gate (LM ⇄ chi-square) ─▶ [smooth] ─▶ map
//!          (age       (gravity, (tracks    (velocity  (PCM clusters,  (graph,   (solver.rs, re-solve     (over time:  (verdicts,
//!          inflation)  depth)    cut by     of each    triangle votes, spanning  without the rejects)     odometry     vehicle states)
//!                      time)      group)     spanning tree)  tree init)                               factors)
//! ```
//!
//! `smooth` runs only with [`NavParams::odometry_factors`](crate::NavParams::odometry_factors)
//! and the vehicles' odometry; it replaces the poses, not the verdicts.

mod frames;
mod gate;
mod groups;
mod hypotheses;
mod init;
mod map;
pub(crate) mod motion;
mod nav;
mod smooth;
#[cfg(test)]
pub(crate) mod testing;

use crate::window::{ObservationKey, Stored};
use crate::{seconds_to_ns, solver, Fusion, SolveStats};
use proto::{FleetMap, VehicleId};
use std::collections::BTreeSet;
use std::time::Instant;

/// Wall time since `t`, µs (0 when not measured).
fn elapsed_us(t: Option<Instant>) -> u64 {
    t.map_or(0, |t| t.elapsed().as_micros() as u64)
}

/// A solve's graph for export (none when it had no constraint).
fn exported(reference: VehicleId, graph: init::Graph) -> Option<crate::export::PoseGraph> {
    (!graph.constraints.is_empty()).then_some(crate::export::PoseGraph {
        reference,
        initial: graph.initial,
        constraints: graph.constraints,
    })
}

impl Fusion {
    /// Fuse the window into a map at `now_ns` (the steps: see the crate docs).
    /// Runs on [`FusionParams::threads`](crate::FusionParams::threads)
    /// threads; the map is the same on any number.
    pub fn solve(&mut self, now_ns: u64) -> FleetMap {
        let started = self.params.record_solve_time.then(Instant::now);
        let threads = crate::par::resolve_threads(self.params.threads);
        crate::par::install(threads, |threads| self.solve_on(now_ns, started, threads))
    }

    /// Drop what left the windows at `now_ns`: observations (an own frame
    /// of a vehicle whose nav crosses a link is kept the window from when
    /// that nav covered it, `Window::evict`), then nav samples.
    fn evict(&mut self, now_ns: u64) {
        let window_ns = seconds_to_ns(self.params.window_s);
        let link_window_ns = seconds_to_ns(self.params.link_window_s);
        let max_gap_ns = seconds_to_ns(self.params.nav.max_gap_s);
        let (nav, nav_on) = (&self.nav, self.params.nav.enabled);
        let nav_ready = |o, t, stamp| -> Option<Option<u64>> {
            if !nav_on {
                return None;
            }
            match (
                nav.linked_arrival(o, stamp, max_gap_ns),
                nav.linked_arrival(t, stamp, max_gap_ns),
            ) {
                (None, None) => None,
                (Some(None), _) | (_, Some(None)) => Some(None),
                (a, b) => Some(a.flatten().max(b.flatten())),
            }
        };
        self.stats.expired +=
            self.window
                .evict(now_ns, window_ns, link_window_ns, nav_ready) as u64;
        let nav_keep_ns = window_ns.max(link_window_ns).saturating_add(max_gap_ns);
        self.nav.evict(now_ns, nav_keep_ns);
    }

    /// Step 2: the tracks' groups and each group's motion fit. Once pairs
    /// are seen to move, older frames describe the past to within how far a
    /// pair moves in that time: the tracks whose frames grew are grouped and
    /// fitted again with that known.
    fn group_and_fit(
        &self,
        frames: &mut [frames::Frame],
        now_ns: u64,
        threads: usize,
    ) -> (groups::TrackGroups, motion::GroupFits) {
        let (gate, fuse) = (
            self.params.consistency.gate_chi2,
            self.params.consistency.fuse_tracks,
        );
        let groups = groups::group_tracks(frames, gate, fuse, threads);
        let fits = motion::fit_groups(frames, &groups, &self.params.motion, threads);
        let moving = motion::pair_motion(frames, &groups, &fits, &self.params.motion);
        if moving.is_empty() {
            return (groups, fits);
        }
        let changed = frames::inflate_moving(frames, &moving, now_ns, threads);
        let frames = &*frames;
        groups::regroup_changed(
            frames,
            (groups, fits),
            &changed,
            gate,
            fuse,
            |g| motion::fit_groups(frames, g, &self.params.motion, threads),
            threads,
        )
    }

    /// [`Self::solve`] on `threads` threads of the current pool, its wall
    /// clock started at `started`.
    fn solve_on(&mut self, now_ns: u64, started: Option<Instant>, threads: usize) -> FleetMap {
        self.evict(now_ns);
        let reference = self.fleet.reference_vehicle;
        let consistency = &self.params.consistency;
        let entries: Vec<(&ObservationKey, &Stored)> = self.window.entries.iter().collect();

        let mut frames = frames::measured(&entries, now_ns, &self.params.age_inflation, threads);
        let (nav_verdicts, nav_stats) = nav::check(&mut frames, &self.nav, &self.params.nav);
        let frames_us = elapsed_us(started);
        let (groups, fits) = self.group_and_fit(&mut frames, now_ns, threads);
        let superseded = groups.superseded_frames(frames.len());
        let moving_groups = motion::compensate(&mut frames, &groups, &fits, threads);
        let groups_us = elapsed_us(started).saturating_sub(frames_us);
        let pairs = hypotheses::pair_candidates(&frames, &groups, consistency, threads);
        let prior = hypotheses::attitude_prior(
            &self.last_estimate,
            &pairs,
            now_ns,
            seconds_to_ns(self.params.window_s),
        );
        let hyps = hypotheses::choose(
            pairs,
            &frames,
            &groups,
            reference,
            consistency.gate_chi2,
            &prior,
        );
        let consistency_us = elapsed_us(started);
        let hypotheses_us = consistency_us.saturating_sub(frames_us + groups_us);

        let lm_started = self.params.record_solve_time.then(Instant::now);
        let gate_params = gate::GateParams {
            chi2_gate: self.params.chi2_gate,
            max_rounds: self.params.max_gate_rounds,
            solver: solver::SolverParams {
                robust: self.params.robust,
                max_iterations: self.params.max_iterations,
                ..solver::SolverParams::default()
            },
            threads,
        };
        let mut gated = gate::solve_and_gate(&frames, &groups, &hyps, reference, &gate_params);
        let lm_us = elapsed_us(lm_started);
        let (smoothed, smooth_us) =
            self.over_time(&entries, &frames, &hyps, &gated, &gate_params.solver);
        let map_started = self.params.record_solve_time.then(Instant::now);

        self.last_graph = exported(reference, std::mem::take(&mut gated.graph));
        let verdicts = map::verdicts(
            &entries,
            &frames,
            &hyps.accepted,
            &gated,
            &superseded,
            &nav_verdicts,
            threads,
        );
        let in_window: BTreeSet<VehicleId> = entries
            .iter()
            .flat_map(|(_, s)| [s.obs.observer, s.target])
            .collect();
        let solve_stats = SolveStats {
            window_observations: entries.len(),
            moving_groups,
            accepted: verdicts.accepted,
            rejected: verdicts.rejected,
            pairs: hyps.pairs.len(),
            clusters: hyps.pairs.iter().map(|p| p.clusters.len()).sum(),
            localized: gated.solution.len().max(1),
            lm_iterations: gated.lm_iterations,
            gate_rounds: gated.rounds,
            nav_tilt_checked: nav_stats.tilt_checked,
            nav_depth_checked: nav_stats.depth_checked,
            nav_heading_checked: nav_stats.heading_checked,
            solver_failed: gated.solver_failed,
            consistency_us,
            lm_us,
            frames_us,
            groups_us,
            hypotheses_us,
            ..SolveStats::default()
        };
        let mut as_of = map::newest_accepted(&verdicts.edges);
        // The map is the states at T; the verdicts above stay the
        // per-vehicle graph's (its gate judged every frame).
        let adopted = smoothed.map(|s| s.adopt(smooth_us, &mut as_of, &mut gated.solution));
        let (smoothing, time_graph) = adopted.map_or_else(Default::default, |(s, g)| (s, Some(g)));
        self.last_time_graph = time_graph;
        let edges = map::merge_pending(verdicts.edges, std::mem::take(&mut self.pending));
        let vehicles = self.estimates(now_ns, &in_window, &gated.solution, &as_of);

        self.seq += 1;
        self.stats.solves += 1;
        self.stats.last_solve = SolveStats {
            map_us: elapsed_us(map_started),
            smoothing,
            ..solve_stats
        };
        FleetMap {
            fleet: self.fleet.name.clone(),
            producer: self.producer.clone(),
            seq: self.seq,
            stamp_ns: now_ns,
            reference,
            vehicles,
            edges,
            solve_time_us: elapsed_us(started),
        }
    }

    /// The window over time (`smooth.rs`), when [`crate::NavParams::odometry_factors`]
    /// asks for it and the per-vehicle solve succeeded, and its wall time
    /// (µs, 0 unless recorded).
    fn over_time(
        &self,
        entries: &[(&ObservationKey, &Stored)],
        frames: &[frames::Frame],
        hyps: &hypotheses::Hypotheses,
        gated: &gate::GatedSolution,
        solver: &solver::SolverParams,
    ) -> (Option<smooth::Smoothed>, u64) {
        let nav = &self.params.nav;
        if !nav.enabled || !nav.odometry_factors || gated.solver_failed {
            return (None, 0);
        }
        let started = self.params.record_solve_time.then(Instant::now);
        let smoothed = smooth::smooth(
            &smooth::Inputs {
                entries,
                frames,
                accepted: &hyps.accepted,
                gated: &gated.gated,
                solution: &gated.solution,
                reference: self.fleet.reference_vehicle,
                odometry: &self.odometry,
                max_gap_ns: seconds_to_ns(nav.max_gap_s),
                slot_ns: seconds_to_ns(nav.odometry_slot_s),
                max_states: nav.odometry_max_states,
            },
            solver,
        );
        (smoothed, elapsed_us(started))
    }

    /// Every fleet vehicle's estimate and state from `solution` (step 7).
    fn estimates(
        &mut self,
        now_ns: u64,
        in_window: &BTreeSet<VehicleId>,
        solution: &gate::Poses,
        as_of: &std::collections::BTreeMap<VehicleId, u64>,
    ) -> Vec<proto::VehicleEstimate> {
        let mut ids: Vec<VehicleId> = self.fleet.vehicles.iter().map(|v| v.id).collect();
        ids.sort_unstable();
        let nav = &self.params.nav;
        let max_gap_ns = seconds_to_ns(nav.max_gap_s);
        let evidence = map::Evidence {
            reference: self.fleet.reference_vehicle,
            alive: &self.alive,
            last_seen: &self.last_seen,
            in_window,
            inflation: &self.params.age_inflation,
            now_ns,
            predictor: (nav.enabled && nav.max_predict_s > 0.0).then(|| map::Predictor {
                odometry: &self.odometry,
                max_predict_ns: seconds_to_ns(nav.max_predict_s),
                max_gap_ns,
            }),
            // A localized vehicle's frames are in the window: the window,
            // not `max_predict_s`, bounds how far it is carried.
            live_predictor: (nav.enabled && nav.propagate_live).then_some(map::Predictor {
                odometry: &self.odometry,
                max_predict_ns: u64::MAX,
                max_gap_ns,
            }),
            as_of,
        };
        map::vehicle_estimates(&ids, &evidence, solution, &mut self.last_estimate)
    }
}
