//! Step 6b of the solve, with [`NavParams::odometry_factors`](crate::NavParams::odometry_factors):
//! the window as a factor graph **over time**. Each vehicle with odometry
//! over the window gets a state per time slot it was seen in (and one at the
//! window's newest accepted frame, `T`), joined to its neighbours by
//! **odometry between-factors** from its own dead reckoning
//! ([`crate::nav::Odometry`]); each accepted, ungated frame is a
//! **marker-edge factor** between the observer's and the target's states at
//! its slot; the reference's state at `T` fixes the gauge. Solved by the same
//! Levenberg–Marquardt and robust kernel as the per-vehicle graph, the
//! vehicles' states at `T` with their marginal covariances are the map.
//!
//! ```text
//!   ref   ○───odo───○───odo───●(fixed, T)
//!         │ marker  │         │
//!   v     ○───odo───○───odo───○  ← the map's pose of v, as of T
//!           slot 2    slot 1    slot 0
//! ```
//!
//! Why: the per-vehicle graph brings a track's older frames to its newest by
//! a fitted relative velocity ([`super::motion`]) or widens them by their age
//! ([`crate::AgeInflation`]); a vehicle whose own DVL and compass say how it
//! moved needs neither: its older frames count at full weight, moved by what
//! it measured, and a vehicle last seen a second ago is carried to `T`.
//!
//! Slots: a frame taken at `t` belongs to slot `k = round((T − t)/slot)`, at
//! `t_k = T − k·slot`; both its ends are moved there by their own odometry
//! (`a(t_k)_from_b(t_k) = a(t_k)_from_a(t) · Z · b(t)_from_b(t_k)`), the
//! motions' variances added. A vehicle whose odometry does not cover the
//! window (no nav with velocity and heading, a gap) keeps one state; its
//! frames enter as the per-vehicle graph has them (brought to their track's
//! newest frame, widened by age), tied to the other end's state at `T`.
//! Without any vehicle with odometry this step does nothing.
//!
//! What the factors leave out: consecutive odometry increments share the
//! compass and IMU sample between them, so their rotation errors are
//! negatively correlated; each increment's rotation variance is both ends'
//! (conservative over several slots). Depth and gravity enter as gates
//! ([`super::nav`]), not as factors.

use super::frames::Frame;
use super::gate::Poses;
use crate::nav::Odometry;
use crate::solver::{self, Constraint, SolverParams};
use crate::window::{ObservationKey, Stored};
use proto::geometry::{Cov6, Pose};
use proto::VehicleId;
use std::collections::{BTreeMap, BTreeSet};

/// Variance floors of an odometry factor whose two ends rest on one nav
/// sample (no motion measured, none possible to speak of): m², rad².
const MIN_POSITION_VAR: f64 = 1e-8;
const MIN_ATTITUDE_VAR: f64 = 1e-10;

/// The shortest slot: a setting of 0 (or not a number) means this, so that
/// slot numbers stay small whatever the window.
const MIN_SLOT_NS: u64 = 1_000_000;

/// What the smoother needs from the solve so far.
pub(crate) struct Inputs<'a> {
    pub entries: &'a [(&'a ObservationKey, &'a Stored)],
    /// After the motion model and the nav checks (used for vehicles without odometry).
    pub frames: &'a [Frame],
    /// Accepted (frame, hypothesis) keys.
    pub accepted: &'a BTreeMap<(usize, u8), usize>,
    /// Rejected by the chi-square gate.
    pub gated: &'a BTreeSet<(usize, u8)>,
    /// The per-vehicle graph's solution (the start, and who is localized).
    pub solution: &'a Poses,
    pub reference: VehicleId,
    pub odometry: &'a Odometry,
    pub max_gap_ns: u64,
    pub slot_ns: u64,
    /// States of the vehicles over time at most: each keeps
    /// `max(1, max_states / vehicles over time)` states, its state at T and
    /// its newest slots with a frame.
    pub max_states: usize,
}

/// The smoothed window.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Smoothed {
    /// Every localized vehicle's `reference_from_vehicle` at [`Self::as_of_ns`]
    /// (its single state for a vehicle without odometry) and its marginal covariance.
    pub solution: Poses,
    /// `T`: the newest accepted frame's capture time.
    pub as_of_ns: u64,
    /// Vehicles with states over time (odometry over the window) in the graph.
    pub over_time: BTreeSet<VehicleId>,
    /// The factor graph, its nodes numbered (see [`Self::nodes`]).
    pub graph: crate::export::PoseGraph,
    /// Node number → (vehicle, slot); a vehicle's single state is slot 0.
    pub nodes: Vec<(VehicleId, u32)>,
    /// Accepted frames left out: an end's odometry did not reach its slot.
    pub frames_left_out: usize,
    /// Accepted frames older than the slots an end keeps (the budget of states).
    pub frames_too_old: usize,
    pub marker_factors: usize,
    pub odometry_factors: usize,
    pub iterations: usize,
}

impl Smoothed {
    /// Make this the map's solution: `solution` replaced, every vehicle over
    /// time as of T in `as_of`. Returns the stats and the graph with its
    /// states (for [`crate::Fusion::last_time_graph`]).
    pub fn adopt(
        self,
        smooth_us: u64,
        as_of: &mut BTreeMap<VehicleId, u64>,
        solution: &mut Poses,
    ) -> (
        crate::SmoothingStats,
        (crate::export::PoseGraph, Vec<State>),
    ) {
        for v in &self.over_time {
            as_of.insert(*v, self.as_of_ns);
        }
        *solution = self.solution;
        let stats = crate::SmoothingStats {
            states: self.nodes.len(),
            vehicles_over_time: self.over_time.len(),
            marker_factors: self.marker_factors,
            odometry_factors: self.odometry_factors,
            frames_left_out: self.frames_left_out,
            frames_too_old: self.frames_too_old,
            iterations: self.iterations,
            smooth_us,
        };
        (stats, (self.graph, self.nodes))
    }
}

/// A state: a vehicle at a time slot (0: the newest accepted frame's).
type State = (VehicleId, u32);

/// A factor between two states, before the states are numbered.
struct Factor {
    a: State,
    b: State,
    a_from_b: Pose,
    covariance: Cov6,
}

/// Node numbers of states.
struct Nodes {
    index: BTreeMap<State, u32>,
    list: Vec<State>,
}

impl Nodes {
    fn id(&mut self, state: State) -> u32 {
        let n = self.list.len() as u32;
        *self.index.entry(state).or_insert_with(|| {
            self.list.push(state);
            n
        })
    }
}

/// The states reachable from `root` through `factors`.
fn connected_to(root: State, factors: &[Factor]) -> BTreeSet<State> {
    let mut adjacent: BTreeMap<State, Vec<State>> = BTreeMap::new();
    for f in factors {
        adjacent.entry(f.a).or_default().push(f.b);
        adjacent.entry(f.b).or_default().push(f.a);
    }
    let mut seen = BTreeSet::from([root]);
    let mut stack = vec![root];
    while let Some(n) = stack.pop() {
        for m in adjacent.get(&n).into_iter().flatten() {
            if seen.insert(*m) {
                stack.push(*m);
            }
        }
    }
    seen
}

/// `cov` with `position` added to each translation variance and `attitude`
/// to each rotation variance.
fn widened(cov: &Cov6, position: f64, attitude: f64) -> Cov6 {
    let mut c = *cov;
    for i in 0..3 {
        c[(i, i)] += position;
        c[(i + 3, i + 3)] += attitude;
    }
    c
}

/// The window's time slots: `T` (the newest accepted frame's capture), the
/// slot length, and the vehicles' odometry.
struct Slots<'a> {
    newest: u64,
    slot_ns: u64,
    inp: &'a Inputs<'a>,
}

impl Slots<'_> {
    fn of(&self, t: u64) -> u64 {
        ((self.newest - t.min(self.newest)) + self.slot_ns / 2) / self.slot_ns
    }

    fn time(&self, k: u64) -> u64 {
        self.newest.saturating_sub(k * self.slot_ns)
    }

    /// `v(from)_from_v(to)`, its position and attitude variances.
    fn motion(&self, v: VehicleId, from: u64, to: u64) -> Option<(Pose, f64, f64)> {
        self.inp.odometry.motion(v, from, to, self.inp.max_gap_ns)
    }
}

/// The marker-edge factors of the `used` (frame, hypothesis) keys, and how
/// many frames were left out for want of odometry and for age.
fn marker_factors(
    used: &[(usize, u8)],
    over_time: &BTreeSet<VehicleId>,
    slots: &Slots<'_>,
) -> (Vec<Factor>, usize, usize) {
    let inp = slots.inp;
    let both_over_time = |i: usize| {
        let f = &inp.frames[i];
        over_time.contains(&f.observer) && over_time.contains(&f.target)
    };
    // Each vehicle's newest slots with a frame between two vehicles over
    // time, within the budget: a frame enters at a slot both its ends keep.
    let max_slots = (inp.max_states / over_time.len().max(1)).max(1);
    let mut kept: BTreeMap<VehicleId, BTreeSet<u64>> = BTreeMap::new();
    for &(i, _) in used.iter().filter(|(i, _)| both_over_time(*i)) {
        let f = &inp.frames[i];
        for v in [f.observer, f.target] {
            kept.entry(v).or_default().insert(slots.of(f.stamp_ns));
        }
    }
    for s in kept.values_mut() {
        // The state at T counts too: every vehicle over time has one.
        let room = if s.contains(&0) {
            max_slots
        } else {
            max_slots - 1
        };
        while s.len() > room {
            s.pop_last();
        }
    }
    let keeps = |v: VehicleId, k: u64| kept.get(&v).is_some_and(|s| s.contains(&k));
    let mut factors = Vec::new();
    let (mut left_out, mut too_old) = (0, 0);
    for &(i, h) in used {
        let f = &inp.frames[i];
        let (a, b) = (f.observer, f.target);
        if !both_over_time(i) {
            // The per-vehicle graph's frame, tied to the state at T.
            if let Some(c) = f.hyps[usize::from(h)] {
                factors.push(Factor {
                    a: (a, 0),
                    b: (b, 0),
                    a_from_b: c.a_from_b,
                    covariance: c.covariance,
                });
            }
            continue;
        }
        let o = &inp.entries[i].1.obs;
        let (z, cov) = match (h, &o.alternative) {
            (0, _) => (o.observer_from_target, o.covariance),
            (_, Some(alt)) => (alt.observer_from_target, alt.covariance),
            _ => continue,
        };
        let k = slots.of(f.stamp_ns);
        if !keeps(a, k) || !keeps(b, k) {
            too_old += 1;
            continue;
        }
        let t_k = slots.time(k);
        let (Some((ma, pa, ra)), Some((mb, pb, rb))) = (
            slots.motion(a, f.stamp_ns, t_k),
            slots.motion(b, f.stamp_ns, t_k),
        ) else {
            left_out += 1;
            continue;
        };
        // a's turn swings b's position by the lever arm.
        let swing = z.translation.vector.norm_squared() * ra;
        factors.push(Factor {
            a: (a, k as u32),
            b: (b, k as u32),
            a_from_b: ma.inverse() * z * mb,
            covariance: widened(&cov, pa + pb + swing, ra + rb),
        });
    }
    (factors, left_out, too_old)
}

/// The odometry between-factors of every vehicle over time that the marker
/// factors name: between its consecutive states, its state at T included.
/// `None` when a vehicle's odometry does not reach between two of them.
fn odometry_factors(
    markers: &[Factor],
    over_time: &BTreeSet<VehicleId>,
    slots: &Slots<'_>,
) -> Option<Vec<Factor>> {
    let mut states: BTreeMap<VehicleId, BTreeSet<u32>> = BTreeMap::new();
    for f in markers {
        for (v, k) in [f.a, f.b] {
            if over_time.contains(&v) {
                states.entry(v).or_default().extend([k, 0]);
            }
        }
    }
    let mut factors = Vec::new();
    for (v, ks) in &states {
        let ks: Vec<u32> = ks.iter().copied().collect();
        for w in ks.windows(2) {
            // Older (larger k) to newer.
            let (new_k, old_k) = (w[0], w[1]);
            let (t_old, t_new) = (slots.time(u64::from(old_k)), slots.time(u64::from(new_k)));
            let (m, p, r) = slots.motion(*v, t_old, t_new)?;
            factors.push(Factor {
                a: (*v, old_k),
                b: (*v, new_k),
                a_from_b: m,
                covariance: widened(
                    &Cov6::zeros(),
                    p.max(MIN_POSITION_VAR),
                    r.max(MIN_ATTITUDE_VAR),
                ),
            });
        }
    }
    Some(factors)
}

/// The window over time (see the module docs); `None` when no localized
/// vehicle has odometry over it, no frame is accepted, or the solver fails
/// (the per-vehicle solution stands, and the caller counts it).
pub(crate) fn smooth(inp: &Inputs<'_>, params: &SolverParams) -> Option<Smoothed> {
    let used: Vec<(usize, u8)> = inp
        .accepted
        .keys()
        .copied()
        .filter(|k| !inp.gated.contains(k))
        .filter(|&(i, _)| {
            let f = &inp.frames[i];
            inp.solution.contains_key(&f.observer) && inp.solution.contains_key(&f.target)
        })
        .collect();
    let stamps = used.iter().map(|&(i, _)| inp.frames[i].stamp_ns);
    let (oldest, newest) = (stamps.clone().min()?, stamps.max()?);
    let slots = Slots {
        newest,
        slot_ns: inp.slot_ns.max(MIN_SLOT_NS),
        inp,
    };
    // A vehicle is over time when its odometry spans the window's slots.
    let from = slots.time(slots.of(oldest)).min(oldest);
    let over_time: BTreeSet<VehicleId> = inp
        .solution
        .keys()
        .copied()
        .filter(|&v| slots.motion(v, from, newest).is_some())
        .collect();
    if over_time.is_empty() {
        return None;
    }
    let (mut factors, frames_left_out, frames_too_old) = marker_factors(&used, &over_time, &slots);
    let markers = factors.len();
    factors.extend(odometry_factors(&factors, &over_time, &slots)?);
    // Only what is connected to the reference's state at T: the rest keep
    // their per-vehicle poses.
    let connected = connected_to((inp.reference, 0), &factors);
    let marker_factors = factors[..markers]
        .iter()
        .filter(|f| connected.contains(&f.a))
        .count();
    factors.retain(|f| connected.contains(&f.a));
    if factors.is_empty() {
        return None;
    }
    let mut nodes = Nodes {
        index: BTreeMap::new(),
        list: Vec::new(),
    };
    let reference = nodes.id((inp.reference, 0));
    let constraints: Vec<Constraint> = factors
        .into_iter()
        .map(|f| Constraint {
            a: nodes.id(f.a),
            b: nodes.id(f.b),
            a_from_b: f.a_from_b,
            covariance: f.covariance,
        })
        .collect();
    let initial = start(&nodes.list, &over_time, &slots)?;
    let solved = match solver::solve(reference, &initial, &constraints, params) {
        Ok(s) => s,
        Err(e) => {
            tracing::warn!("the window over time did not solve ({e}); the per-vehicle map stands");
            return None;
        }
    };
    let mut solution = Poses::new();
    for (&(v, k), n) in nodes.list.iter().zip(0u32..) {
        if k == 0 {
            let pose = solved.poses[&n];
            let cov = solved.covariances.get(&n).copied().unwrap_or(Cov6::zeros());
            solution.insert(v, (pose, cov));
        }
    }
    // A localized vehicle all of whose frames were left out keeps its
    // per-vehicle pose (it has no state of its own here).
    for (v, p) in inp.solution {
        solution.entry(*v).or_insert(*p);
    }
    let odometry_factors = constraints.len() - marker_factors;
    let over_time = nodes
        .list
        .iter()
        .map(|&(v, _)| v)
        .filter(|v| over_time.contains(v))
        .collect();
    Some(Smoothed {
        solution,
        as_of_ns: newest,
        over_time,
        graph: crate::export::PoseGraph {
            reference,
            initial,
            constraints,
        },
        nodes: nodes.list,
        frames_left_out,
        frames_too_old,
        marker_factors,
        odometry_factors,
        iterations: solved.iterations,
    })
}

/// The LM's start: each state from the per-vehicle solution, moved from T
/// to its slot by its vehicle's odometry.
fn start(
    states: &[State],
    over_time: &BTreeSet<VehicleId>,
    slots: &Slots<'_>,
) -> Option<BTreeMap<u32, Pose>> {
    let inp = slots.inp;
    let mut initial = BTreeMap::new();
    for (&(v, k), n) in states.iter().zip(0u32..) {
        let at_t = if v == inp.reference {
            Pose::identity()
        } else {
            inp.solution.get(&v)?.0
        };
        let pose = if k == 0 || !over_time.contains(&v) {
            at_t
        } else {
            let (m, _, _) = slots.motion(v, slots.time(u64::from(k)), slots.newest)?;
            at_t * m.inverse()
        };
        initial.insert(n, pose);
    }
    Some(initial)
}
