//! Issue #21: shoal's own pose-graph Levenberg–Marquardt
//! (`shoal_fusion::solver::solve`, the fusion's and the bench's entry point)
//! against the `factrs` and `tiny-solver` crates on the graphs the fusion
//! solves. See README.md.
//!
//! `cargo run --release [-- REPETITIONS]` (default 40).

mod convert;
mod marginals;
mod problems;
mod with_factrs;
mod with_tiny;

use shoal_fusion::export::PoseGraph;
use shoal_fusion::solver::{self, RobustKernel, SolverParams};
use shoal_proto::geometry::{difference, Cov6, Pose};
use shoal_proto::VehicleId;
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

/// Counts tiny-solver's LM iterations from its trace log (it reports none):
/// each iteration that solves its linear system logs "Time elapsed in solve".
struct IterationLog;

static TINY_SOLVES: AtomicUsize = AtomicUsize::new(0);
static TINY_FAILED_SOLVES: AtomicUsize = AtomicUsize::new(0);

impl log::Log for IterationLog {
    fn enabled(&self, metadata: &log::Metadata<'_>) -> bool {
        metadata.target().starts_with("tiny_solver")
    }
    fn log(&self, record: &log::Record<'_>) {
        if !self.enabled(record.metadata()) {
            return;
        }
        let text = record.args().to_string();
        if text.starts_with("Time elapsed in solve") {
            TINY_SOLVES.fetch_add(1, Ordering::Relaxed);
        } else if text.starts_with("solve ax=b failed") {
            TINY_FAILED_SOLVES.fetch_add(1, Ordering::Relaxed);
        }
    }
    fn flush(&self) {}
}

static LOGGER: IterationLog = IterationLog;

/// One solver's result on one problem.
struct Run {
    poses: BTreeMap<VehicleId, Pose>,
    iterations: usize,
    note: String,
}

/// The timed calls, alternated within each repetition.
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Debug)]
enum Call {
    Shoal,
    Factrs,
    Tiny,
    ShoalMarginals,
    FactrsMarginals,
    TinyMarginals,
}

const CALLS: [Call; 6] = [
    Call::Shoal,
    Call::Factrs,
    Call::Tiny,
    Call::ShoalMarginals,
    Call::FactrsMarginals,
    Call::TinyMarginals,
];

fn params() -> SolverParams {
    SolverParams::default()
}

fn huber_k() -> f64 {
    match params().robust {
        RobustKernel::Huber { k } => k,
        other => panic!("shoal's default kernel is Huber, not {other:?}"),
    }
}

/// Largest translation (mm) and rotation (degrees) between two pose sets.
fn max_difference(a: &BTreeMap<VehicleId, Pose>, b: &BTreeMap<VehicleId, Pose>) -> (f64, f64) {
    a.iter().fold((0.0f64, 0.0f64), |(t, r), (v, p)| {
        let e = difference(p, &b[v]);
        (
            t.max(e.fixed_rows::<3>(0).norm() * 1e3),
            r.max(e.fixed_rows::<3>(3).norm().to_degrees()),
        )
    })
}

/// Largest `‖Σ − Σ_shoal‖_F / ‖Σ_shoal‖_F` over the vehicles.
fn max_marginal_difference(
    theirs: &BTreeMap<VehicleId, Cov6>,
    shoal: &BTreeMap<VehicleId, Cov6>,
) -> f64 {
    theirs
        .iter()
        .map(|(v, m)| (m - shoal[v]).norm() / shoal[v].norm())
        .fold(0.0, f64::max)
}

/// Median and quartiles (linear interpolation) of `xs`.
fn quartiles(xs: &[f64]) -> (f64, f64, f64) {
    let mut s = xs.to_vec();
    s.sort_by(|a, b| a.total_cmp(b));
    let at = |p: f64| {
        let x = p * (s.len() - 1) as f64;
        let (lo, hi) = (x.floor() as usize, x.ceil() as usize);
        s[lo] + (s[hi] - s[lo]) * (x - lo as f64)
    };
    (at(0.25), at(0.5), at(0.75))
}

/// The threads of rayon's global pool (tiny-solver's): `RAYON_NUM_THREADS` or the cores.
fn rayon_threads() -> usize {
    std::env::var("RAYON_NUM_THREADS")
        .ok()
        .and_then(|s| s.parse().ok())
        .filter(|n| *n > 0)
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
}

fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "?".into())
}

fn command_line(program: &str, args: &[&str]) -> String {
    std::process::Command::new(program)
        .args(args)
        .output()
        .ok()
        .and_then(|o| String::from_utf8(o.stdout).ok())
        .map(|s| s.trim().to_string())
        .unwrap_or_else(|| "?".into())
}

/// A crate's version in this tool's Cargo.lock.
fn locked(name: &str) -> Vec<String> {
    let lock = include_str!("../Cargo.lock");
    let mut out = Vec::new();
    let mut lines = lock.lines();
    while let Some(l) = lines.next() {
        if l == format!("name = \"{name}\"") {
            if let Some(v) = lines.next() {
                out.push(
                    v.trim_start_matches("version = ")
                        .trim_matches('"')
                        .to_string(),
                );
            }
        }
    }
    out
}

fn run_shoal(graph: &PoseGraph) -> (Run, BTreeMap<VehicleId, Cov6>) {
    let s = solver::solve(
        graph.reference,
        &graph.initial,
        &graph.constraints,
        &params(),
    )
    .expect("shoal solves its own graphs");
    let note = format!("marginals: {} vehicles", s.covariances.len() - 1);
    (
        Run {
            poses: s.poses,
            iterations: s.iterations,
            note,
        },
        s.covariances,
    )
}

/// shoal's solve from its own optimum with no LM iteration: the setup, one
/// cost, the Gauss–Newton information and the marginals.
fn shoal_marginals_only(graph: &PoseGraph, optimum: &BTreeMap<VehicleId, Pose>) {
    let p = SolverParams {
        max_iterations: 0,
        ..params()
    };
    solver::solve(graph.reference, optimum, &graph.constraints, &p).expect("marginals");
}

fn main() {
    let reps: usize = std::env::args()
        .nth(1)
        .map(|s| s.parse().expect("REPETITIONS is a number"))
        .unwrap_or(40);
    log::set_logger(&LOGGER).expect("one logger");
    log::set_max_level(log::LevelFilter::Off);
    let (p, k) = (params(), huber_k());

    println!("# solver-eval (issue #21)");
    println!();
    println!(
        "- date: {}",
        command_line("date", &["-u", "+%Y-%m-%d %H:%M UTC"])
    );
    println!("- load average at start (1/5/15 min): {}", load_average());
    println!(
        "- cores: {}",
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    println!("- rustc: {}", command_line("rustc", &["--version"]));
    println!(
        "- factrs {:?}, tiny-solver {:?}, faer {:?}, nalgebra {:?} (shoal 0.33, the libraries 0.34)",
        locked("factrs"),
        locked("tiny-solver"),
        locked("faer"),
        locked("nalgebra")
    );
    println!(
        "- settings (all three): Huber k = {k}, at most {} iterations, stop at a relative cost decrease < {:e}; shoal also stops at a step < {:e}",
        p.max_iterations, p.relative_tolerance, p.min_step
    );
    println!("  (tiny-solver also stops at a step ‖dx‖ ≤ 1e-8·(‖x‖ + 1e-8), a constant of the crate; factrs has no step test)");
    println!("- gauge: shoal holds the reference out of the unknowns; tiny-solver fixes its 7 entries (`fix_variable`); factrs cannot fix a variable: a prior on the reference, σ = 1e-9");
    println!("- factrs and tiny-solver: shoal's constraints as `Log(T_b⁻¹·T_a·Z)` residuals whitened by the information over Z's right perturbation (`convert.rs`); tiny-solver evaluates its residual blocks on rayon's pool ({} threads), shoal and factrs on one thread", rayon_threads());
    println!("- {reps} repetitions, the six calls alternated (rotated start) in each; times are wall clock per call, graph building included");
    println!();

    let problems = [
        problems::window(10),
        problems::window(100),
        problems::lm_only_100(),
    ];
    for problem in &problems {
        evaluate(problem, reps, k, &p);
    }
    println!("- load average at end (1/5/15 min): {}", load_average());
}

fn evaluate(problem: &problems::Problem, reps: usize, k: f64, p: &SolverParams) {
    let graph = &problem.graph;
    let edges = convert::edges(graph);
    let variables = with_factrs::variables(&edges).len();
    let kernel = RobustKernel::Huber { k };
    let cost = |poses: &BTreeMap<VehicleId, Pose>| graph.cost(poses, kernel).expect("cost");

    // One untimed run of each, for the results.
    let (shoal, shoal_cov) = run_shoal(graph);
    let f = with_factrs::solve(graph, &edges, k, p.max_iterations, p.relative_tolerance);
    let factrs_run = Run {
        poses: f.poses.clone(),
        iterations: f.iterations,
        note: format!("ended: {}", f.ending),
    };
    log::set_max_level(log::LevelFilter::Trace);
    TINY_SOLVES.store(0, Ordering::Relaxed);
    TINY_FAILED_SOLVES.store(0, Ordering::Relaxed);
    let tiny = with_tiny::solve(graph, &edges, k, p.max_iterations, p.relative_tolerance);
    log::set_max_level(log::LevelFilter::Off);
    let (tiny_poses, tiny_values) = tiny.expect("tiny-solver returned no solution");
    let tiny_run = Run {
        poses: tiny_poses,
        iterations: TINY_SOLVES.load(Ordering::Relaxed)
            + TINY_FAILED_SOLVES.load(Ordering::Relaxed),
        note: String::new(),
    };

    // The marginals the libraries do not give, from their Jacobians at their optimum.
    let (factrs_graph, _) = with_factrs::build(graph, &edges, k);
    let (tiny_problem, _) = with_tiny::build(graph, &edges, k);
    let factrs_cov = with_factrs::marginals(
        &factrs_graph,
        &f.values,
        &factrs_run.poses,
        graph.reference,
        &edges,
    );
    let tiny_cov = with_tiny::marginals(
        &tiny_problem,
        &tiny_values,
        &tiny_run.poses,
        graph.reference,
        &edges,
    );

    // Timed: every call once per repetition, the order rotated.
    let mut times: BTreeMap<Call, Vec<f64>> = BTreeMap::new();
    for r in 0..reps {
        for i in 0..CALLS.len() {
            let call = CALLS[(r + i) % CALLS.len()];
            let t0 = Instant::now();
            match call {
                Call::Shoal => {
                    std::hint::black_box(run_shoal(graph));
                }
                Call::Factrs => {
                    std::hint::black_box(with_factrs::solve(
                        graph,
                        &edges,
                        k,
                        p.max_iterations,
                        p.relative_tolerance,
                    ));
                }
                Call::Tiny => {
                    std::hint::black_box(with_tiny::solve(
                        graph,
                        &edges,
                        k,
                        p.max_iterations,
                        p.relative_tolerance,
                    ));
                }
                Call::ShoalMarginals => shoal_marginals_only(graph, &shoal.poses),
                Call::FactrsMarginals => {
                    std::hint::black_box(with_factrs::marginals(
                        &factrs_graph,
                        &f.values,
                        &factrs_run.poses,
                        graph.reference,
                        &edges,
                    ));
                }
                Call::TinyMarginals => {
                    std::hint::black_box(with_tiny::marginals(
                        &tiny_problem,
                        &tiny_values,
                        &tiny_run.poses,
                        graph.reference,
                        &edges,
                    ));
                }
            }
            times
                .entry(call)
                .or_default()
                .push(t0.elapsed().as_secs_f64() * 1e3);
        }
    }

    let start_cost = cost(&graph.initial);
    let shoal_cost = cost(&shoal.poses);
    println!(
        "## {}: {} vehicles ({} variables besides the reference {}), {} constraints; cost at the start {:.6e}",
        problem.name,
        graph.initial.len(),
        variables - 1,
        graph.reference,
        graph.constraints.len(),
        start_cost
    );
    println!();
    println!("| solver | solve ms, median [IQR] | ratio to shoal (medians) | iterations | final cost (`PoseGraph::cost`, Huber 4.1) | vs shoal's | max pose difference to shoal | own objective: at its result / at shoal's | marginals (6x6 per vehicle) |");
    println!("|---|---|---|---|---|---|---|---|---|");
    let median = |c: Call| quartiles(&times[&c]).1;
    let cell = |c: Call| {
        let (q1, m, q3) = quartiles(&times[&c]);
        format!("{m:.2} [{q1:.2}–{q3:.2}]")
    };
    for (label, call, marg_call, run, cov) in [
        (
            "shoal (own LM)",
            Call::Shoal,
            Call::ShoalMarginals,
            &shoal,
            Some(&shoal_cov),
        ),
        (
            "factrs",
            Call::Factrs,
            Call::FactrsMarginals,
            &factrs_run,
            factrs_cov.as_ref(),
        ),
        (
            "tiny-solver",
            Call::Tiny,
            Call::TinyMarginals,
            &tiny_run,
            tiny_cov.as_ref(),
        ),
    ] {
        let c = cost(&run.poses);
        let versus = if shoal_cost > 1e-6 {
            format!("{:+.4} %", (c - shoal_cost) / shoal_cost * 100.0)
        } else {
            format!("{:+.2e} (absolute)", c - shoal_cost)
        };
        let (dt, dr) = max_difference(&run.poses, &shoal.poses);
        let own = match call {
            Call::Factrs => {
                let o = |poses| with_factrs::objective(&factrs_graph, poses, &edges);
                format!("{:.6e} / {:.6e}", o(&run.poses), o(&shoal.poses))
            }
            Call::Tiny => {
                let o = |poses| with_tiny::objective(&tiny_problem, poses, &edges);
                format!("{:.6e} / {:.6e}", o(&run.poses), o(&shoal.poses))
            }
            _ => "–".to_string(),
        };
        let marginals = match (call, cov) {
            (Call::Shoal, _) => format!(
                "in the solve (and its time); alone (setup + one cost + marginals) {} ms",
                cell(marg_call)
            ),
            (_, Some(m)) => format!(
                "none in the API; own code from its Jacobian (faer Cholesky, dense inverse) {} ms, {:.1}x shoal's; ≤ {:.1e} relative from shoal's",
                cell(marg_call),
                median(marg_call) / median(Call::ShoalMarginals),
                max_marginal_difference(m, &shoal_cov)
            ),
            (_, None) => "none in the API; its JᵀJ not positive definite".to_string(),
        };
        println!(
            "| {label} | {} | {:.2}x | {}{} | {c:.6e} | {versus} | {dt:.4} mm / {dr:.5}° | {own} | {marginals} |",
            cell(call),
            median(call) / median(Call::Shoal),
            run.iterations,
            if run.note.is_empty() || call == Call::Shoal {
                String::new()
            } else {
                format!(" ({})", run.note)
            },
        );
    }
    println!();
}
