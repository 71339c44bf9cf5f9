//! Solve time of the fusion (consistency checks + LM + marginals + map) for
//! 3 (paper fleet), 10 and 100 vehicles, one 2 s window of 10 Hz synthetic
//! observations with 10% wrong IDs and ~10% flips, plus the bare LM solve of
//! 100 vehicles.
//!
//! Before each fleet size's timings it prints where one solve's time goes
//! (consistency checks, LM and gate rounds, pairs, clusters).
//!
//! `cargo bench -p shoal-fusion --bench solve`

#[path = "../tests/common/mod.rs"]
mod common;

use common::*;
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use shoal_fusion::solver::{self, Constraint, SolverParams};
use shoal_fusion::FusionParams;
use shoal_proto::geometry::{perturb, Cov6};
use shoal_proto::CodeSet;
use shoal_sim_bridge::obs_synth::{
    grid_formation, line_abreast, synthetic_fleet, FormationJitter, ObsSynthParams, OutlierModel,
};
use std::collections::BTreeMap;

fn scenario(n: usize) -> (shoal_proto::config::Fleet, Vec<shoal_proto::VehicleTruth>) {
    if n == 3 {
        (paper_fleet(), line_abreast(&[10, 15, 17], 2.0))
    } else {
        let ids: Vec<u32> = (1..=n as u32).collect();
        let cols = if n <= 10 { 5 } else { 10 };
        (
            synthetic_fleet(n, CodeSet::Aruco4x4_1000).unwrap(),
            grid_formation(&ids, cols, 1.5, FormationJitter::default(), 1),
        )
    }
}

/// Nav on (every vehicle's depth, tilt, heading and velocity at every
/// frame) against off, and with the odometry factors over time, 100
/// vehicles: criterion for nav on, then the three timed on alternate calls
/// so that the machine's load hits them alike. Returns the scenario and its
/// fusion without nav.
fn nav_costs(
    c: &mut Criterion,
    synth: ObsSynthParams,
) -> (
    shoal_proto::config::Fleet,
    Vec<shoal_proto::VehicleTruth>,
    shoal_fusion::Fusion,
    u64,
) {
    let (fleet, truth) = scenario(100);
    let (plain, _, now) = run_frames(&fleet, &truth, synth, FusionParams::default(), 1, 20);
    let mut with_nav = plain.clone();
    ingest_nav_frames(&mut with_nav, &truth, 20, 1, now);
    let mut group = c.benchmark_group("fusion_solve_2s_window_nav");
    group.sample_size(10);
    group.bench_function("100", |b| {
        b.iter_batched(
            || with_nav.clone(),
            |mut f| f.solve(now),
            criterion::BatchSize::LargeInput,
        )
    });
    group.finish();
    // … and the window as a factor graph over time (odometry between-factors).
    let mut factors_params = FusionParams::default();
    factors_params.nav.odometry_factors = true;
    let (mut with_factors, _, _) = run_frames(&fleet, &truth, synth, factors_params, 1, 20);
    ingest_nav_frames(&mut with_factors, &truth, 20, 1, now);
    {
        let fastest = (0..5)
            .map(|_| {
                let mut once = with_factors.clone();
                let map = once.solve(now);
                (map.solve_time_us, once.stats().last_solve.smoothing)
            })
            .min_by_key(|(t, _)| *t)
            .expect("five solves");
        eprintln!(
            "100 vehicles, nav with odometry factors, one solve (fastest of 5): {} us in all; {:?}",
            fastest.0, fastest.1
        );
    }
    let (mut off, mut on, mut factors) = (0.0, 0.0, 0.0);
    for _ in 0..10 {
        for (fusion, sum) in [
            (&plain, &mut off),
            (&with_nav, &mut on),
            (&with_factors, &mut factors),
        ] {
            let mut f = fusion.clone();
            let t0 = std::time::Instant::now();
            f.solve(now);
            *sum += t0.elapsed().as_secs_f64() * 1e3;
        }
    }
    eprintln!(
        "100 vehicles, alternate calls: nav off {:.1} ms, nav on {:.1} ms, nav + odometry factors {:.1} ms per solve; ratio on/off {:.3}, factors/on {:.3}",
        off / 10.0,
        on / 10.0,
        factors / 10.0,
        on / off,
        factors / on
    );

    (fleet, truth, plain, now)
}

fn bench_fusion(c: &mut Criterion) {
    let synth = ObsSynthParams {
        outliers: OutlierModel {
            wrong_id_rate: 0.1,
            flip_rate: 0.1 / 0.9,
            ..OutlierModel::default()
        },
        ..ObsSynthParams::default()
    };
    let mut group = c.benchmark_group("fusion_solve_2s_window");
    group.sample_size(10);
    for n in [3usize, 10, 100] {
        let (fleet, truth) = scenario(n);
        let (fusion, obs, now) = run_frames(&fleet, &truth, synth, FusionParams::default(), 1, 20);
        eprintln!("{n} vehicles: {} observations in the window", obs.len());
        // Where one solve's time goes (by step, and the LM + gate rounds):
        // the fastest of five solves, so that the first one's cold caches
        // and page faults do not count.
        let (time_us, stats) = (0..5)
            .map(|_| {
                let mut once = fusion.clone();
                let map = once.solve(now);
                (map.solve_time_us, once.stats().last_solve)
            })
            .min_by_key(|(t, _)| *t)
            .expect("five solves");
        eprintln!("  one solve (fastest of 5): {time_us} us in all; {stats:?}");
        group.bench_with_input(BenchmarkId::from_parameter(n), &n, |b, _| {
            b.iter_batched(
                || fusion.clone(),
                |mut f| f.solve(now),
                criterion::BatchSize::LargeInput,
            )
        });
    }
    group.finish();

    let (fleet, truth, plain, now) = nav_costs(c, synth);
    one_thread_against_all(&fleet, &truth, synth, &plain, now);

    // The LM solve alone: 100 vehicles, one fused constraint per neighbouring pair, noisy start.
    let (_, truth) = scenario(100);
    let poses: BTreeMap<u32, shoal_proto::Pose> = truth
        .iter()
        .map(|t| {
            (
                t.vehicle,
                truth[0].world_from_body.inverse() * t.world_from_body,
            )
        })
        .collect();
    let mut constraints = Vec::new();
    for (a, pa) in &poses {
        for (b, pb) in &poses {
            if a < b && (pa.translation.vector - pb.translation.vector).norm() < 3.2 {
                constraints.push(Constraint {
                    a: *a,
                    b: *b,
                    a_from_b: pa.inverse() * pb,
                    covariance: Cov6::identity() * 1e-4,
                });
            }
        }
    }
    let init: BTreeMap<u32, shoal_proto::Pose> = poses
        .iter()
        .map(|(v, p)| {
            (
                *v,
                if *v == 1 {
                    *p
                } else {
                    perturb(
                        p,
                        &nalgebra::Vector6::new(0.05, -0.03, 0.02, 0.01, 0.02, -0.01),
                    )
                },
            )
        })
        .collect();
    eprintln!("lm_only: 100 vehicles, {} constraints", constraints.len());
    c.bench_function("lm_only_100_vehicles", |b| {
        b.iter(|| solver::solve(1, &init, &constraints, &SolverParams::default()).unwrap())
    });
}

/// The solve's per-observation steps on one thread against the machine's
/// (`FusionParams::threads`, default: all cores), the window of `all_cores`,
/// on alternate calls; the maps must be the same.
fn one_thread_against_all(
    fleet: &shoal_proto::config::Fleet,
    truth: &[shoal_proto::VehicleTruth],
    synth: ObsSynthParams,
    all_cores: &shoal_fusion::Fusion,
    now: u64,
) {
    let serial_params = FusionParams {
        threads: 1,
        ..FusionParams::default()
    };
    let (serial, _, _) = run_frames(fleet, truth, synth, serial_params, 1, 20);
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let (mut t_one, mut t_all) = (0.0, 0.0);
    for _ in 0..10 {
        let mut maps = Vec::new();
        for (fusion, sum) in [(&serial, &mut t_one), (all_cores, &mut t_all)] {
            let mut f = fusion.clone();
            let t0 = std::time::Instant::now();
            maps.push(f.solve(now));
            *sum += t0.elapsed().as_secs_f64() * 1e3;
        }
        // Bit for bit (a NaN chi2 is not `==` itself), but for the wall time.
        maps[0].solve_time_us = maps[1].solve_time_us;
        assert!(
            shoal_proto::encode(&maps[0]).unwrap() == shoal_proto::encode(&maps[1]).unwrap(),
            "the map depends on the thread count"
        );
    }
    eprintln!(
        "100 vehicles, alternate calls: 1 thread {:.1} ms, {cores} threads {:.1} ms per solve, ratio {:.3} (maps identical)",
        t_one / 10.0,
        t_all / 10.0,
        t_all / t_one
    );
}

/// The 6×6 SPD inverse every hypothesis needs, shoal's written-out one
/// against nalgebra's `cholesky().inverse()`, timed on alternate batches in
/// one run (the ratio is the figure; the machine's load hits both alike).
fn bench_spd_inverse(c: &mut Criterion) {
    let mut rng = shoal_proto::splitmix::SplitMix64::new(11);
    let mats: Vec<Cov6> = (0..4096)
        .map(|_| {
            let b = Cov6::from_fn(|_, _| rng.unit() - 0.5);
            b * b.transpose() * 1e-4 + Cov6::identity() * 1e-6
        })
        .collect();
    let (mut ours, mut theirs) = (0.0, 0.0);
    let mut sink = 0.0;
    for _ in 0..20 {
        let t0 = std::time::Instant::now();
        for m in &mats {
            sink += shoal_fusion::linalg::spd_inverse6(m).map_or(0.0, |i| i[(0, 0)]);
        }
        ours += t0.elapsed().as_secs_f64();
        let t0 = std::time::Instant::now();
        for m in &mats {
            sink += m.cholesky().map_or(0.0, |ch| ch.inverse()[(0, 0)]);
        }
        theirs += t0.elapsed().as_secs_f64();
    }
    let per = |t: f64| t / (20.0 * mats.len() as f64) * 1e9;
    eprintln!(
        "6x6 SPD inverse, alternate batches: shoal {:.0} ns, nalgebra {:.0} ns, ratio {:.2} (checksum {sink:.3e})",
        per(ours),
        per(theirs),
        ours / theirs
    );
    c.bench_function("spd_inverse6", |b| {
        b.iter(|| {
            mats.iter()
                .map(|m| shoal_fusion::linalg::spd_inverse6(m).map_or(0.0, |i| i[(0, 0)]))
                .sum::<f64>()
        })
    });
}

criterion_group!(benches, bench_fusion, bench_spd_inverse);
criterion_main!(benches);
