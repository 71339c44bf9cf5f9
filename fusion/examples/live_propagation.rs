//! Issue #21, "Rate" and the window over time: the error of `Live` poses at
//! the map's stamp, with the solved poses carried to it by odometry
//! (`NavParams::propagate_live`) or not (as of their frames), each with the
//! per-vehicle graph and with the odometry factors over time
//! (`NavParams::odometry_factors`).
//!
//! Three vehicles (the synthetic fleet, a jittered line 1.5 m apart)
//! cruise at 0.5 m/s and weave sideways (±0.3 m, 12 s period, each in its own
//! phase: relative speeds up to ~0.3 m/s); cameras at 2 Hz, observations
//! fused 0.1 s after capture, every vehicle's nav (the simulator's default
//! sensors: DVL, tilt, compass, with their noise, biases and dropouts) at
//! 10 Hz, the map solved at 10 Hz. The same observations and nav are fused
//! four times (`MODES`), and each map's `Live` vehicles (reference
//! excluded) are scored against the truth at the map's stamp, from 5 s on.
//! Deterministic: no clock is read.
//!
//! ```sh
//! cargo run --release -p shoal-fusion --example live_propagation -- [SEEDS] [DURATION_S] [WEAVE_M] [HEADING_NOISE_DEG]
//! ```
//! (defaults: seeds 1–5, 40 s, ±0.3 m, the simulator's 0.5° of white
//! compass noise per sample: the heading change over an interval is the
//! difference of two samples, so that noise turns the reference's frame and
//! swings the others' positions by it; an AHRS's filtered heading is smoother).

use nalgebra::Vector3;
use shoal_fusion::{Fusion, FusionParams};
use shoal_proto::config::Fleet;
use shoal_proto::geometry::{difference, Pose};
use shoal_proto::{CodeSet, FleetMap, VehicleId, VehicleState, VehicleTruth};
use shoal_sim_bridge::nav::{NavSensorParams, NavSensors};
use shoal_sim_bridge::obs_synth::{
    grid_formation, synthetic_fleet, FormationJitter, ObsSynth, ObsSynthParams,
};
use std::collections::BTreeMap;

const T0_NS: u64 = 1_000_000_000_000;
/// Map (and nav) period.
const TICK_NS: u64 = 100_000_000;
/// Camera frames every this many ticks (2 Hz).
const CAMERA_EVERY: u64 = 5;
/// Scored from this time on (the window has filled).
const SCORE_FROM_S: f64 = 5.0;
const CRUISE_M_S: f64 = 0.5;
const WEAVE_PERIOD_S: f64 = 12.0;

/// One scored estimate: translation error (m), rotation error (rad), and
/// whether the translation error is within 3σ of the reported covariance
/// along it.
#[derive(Debug, Clone, Copy)]
struct Scored {
    t_err: f64,
    r_err: f64,
    within_3_sigma: bool,
}

fn truth_at(start: &[VehicleTruth], weave_m: f64, t: f64) -> Vec<VehicleTruth> {
    let w = std::f64::consts::TAU / WEAVE_PERIOD_S;
    start
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let phase = 2.1 * i as f64;
            let mut pose = s.world_from_body;
            let offset = Vector3::new(
                CRUISE_M_S * t,
                weave_m * ((w * t + phase).sin() - phase.sin()),
                0.0,
            );
            pose.translation.vector += offset;
            let world_velocity = Vector3::new(CRUISE_M_S, weave_m * w * (w * t + phase).cos(), 0.0);
            VehicleTruth {
                vehicle: s.vehicle,
                world_from_body: pose,
                velocity_body: (pose.rotation.inverse() * world_velocity).into(),
            }
        })
        .collect()
}

fn reference_from(fleet: &Fleet, truth: &[VehicleTruth]) -> BTreeMap<VehicleId, Pose> {
    let world: BTreeMap<VehicleId, Pose> = truth
        .iter()
        .map(|t| (t.vehicle, t.world_from_body))
        .collect();
    let world_from_ref = world[&fleet.reference_vehicle];
    world
        .iter()
        .map(|(v, p)| (*v, world_from_ref.inverse() * p))
        .collect()
}

fn score(map: &FleetMap, truth: &BTreeMap<VehicleId, Pose>, out: &mut Vec<Scored>) {
    for v in map
        .vehicles
        .iter()
        .filter(|v| v.state == VehicleState::Live && v.vehicle != map.reference)
    {
        let e = difference(&v.reference_from_vehicle, &truth[&v.vehicle]);
        let t = e.fixed_rows::<3>(0).into_owned();
        let t_err = t.norm();
        let within_3_sigma = if t_err > 0.0 {
            let dir = t / t_err;
            let var = (dir.transpose() * v.covariance.fixed_view::<3, 3>(0, 0) * dir)[0];
            t_err <= 3.0 * var.max(0.0).sqrt()
        } else {
            true
        };
        out.push(Scored {
            t_err,
            r_err: e.fixed_rows::<3>(3).norm(),
            within_3_sigma,
        });
    }
}

/// The fusion settings compared: (name, `propagate_live`, `odometry_factors`).
const MODES: [(&str, bool, bool); 4] = [
    ("as of frames", false, false),
    ("propagated", true, false),
    ("factors over time", false, true),
    ("factors + propagated", true, true),
];

/// Per seed: the scored estimates of every [`MODES`] entry, and the maps
/// solved.
fn run(
    seed: u64,
    duration_s: f64,
    weave_m: f64,
    nav: NavSensorParams,
) -> Result<(Vec<Vec<Scored>>, usize), String> {
    let fleet = synthetic_fleet(3, CodeSet::Aruco4x4_1000).map_err(|e| e.to_string())?;
    let ids: Vec<VehicleId> = fleet.vehicles.iter().map(|v| v.id).collect();
    let jitter = FormationJitter {
        position_m: 0.1,
        attitude_deg: 3.0,
    };
    let start = grid_formation(&ids, ids.len(), 1.5, jitter, seed);
    let mut synth = ObsSynth::new(&fleet, ObsSynthParams::default(), seed);
    let mut sensors = NavSensors::new(nav, seed).map_err(|e| e.to_string())?;
    let mut fusions: Vec<Fusion> = MODES
        .iter()
        .map(|&(_, propagate_live, odometry_factors)| {
            let mut p = FusionParams {
                record_solve_time: false,
                ..FusionParams::default()
            };
            p.nav.propagate_live = propagate_live;
            p.nav.odometry_factors = odometry_factors;
            Fusion::new(&fleet, p, "central")
        })
        .collect();
    let mut scored = vec![Vec::new(); MODES.len()];
    let mut in_flight = Vec::new();
    let ticks = (duration_s * 1e9 / TICK_NS as f64).round() as u64;
    let mut maps = 0;
    for k in 0..=ticks {
        let now = T0_NS + k * TICK_NS;
        let t = k as f64 * TICK_NS as f64 * 1e-9;
        let truth = truth_at(&start, weave_m, t);
        // Last tick's frames arrive now, captured 0.1 s ago.
        let arrived = std::mem::take(&mut in_flight);
        if k % CAMERA_EVERY == 0 {
            in_flight = synth.observe(&truth, now);
        }
        let navs: Vec<_> = truth.iter().map(|v| sensors.measure(v, now)).collect();
        let reference = reference_from(&fleet, &truth);
        for (f, out) in fusions.iter_mut().zip(scored.iter_mut()) {
            for n in &navs {
                f.ingest_nav(*n, n.vehicle, now)
                    .map_err(|e| format!("seed {seed}: nav refused: {e}"))?;
            }
            for o in &arrived {
                // A refusal (a synthesized outlier) is the fusion's business.
                let _ = f.ingest(o.obs.clone(), o.obs.observer, now);
            }
            let map = f.solve(now);
            if t >= SCORE_FROM_S {
                score(&map, &reference, out);
            }
        }
        if t >= SCORE_FROM_S {
            maps += 1;
        }
    }
    Ok((scored, maps))
}

fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() - 1) as f64 * q).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

/// Median, p95 and max of the translation errors (mm), the median rotation
/// error (deg), and the share within 3σ (%).
fn summary(s: &[Scored]) -> [f64; 5] {
    let mut t: Vec<f64> = s.iter().map(|x| x.t_err * 1e3).collect();
    t.sort_by(f64::total_cmp);
    let mut r: Vec<f64> = s.iter().map(|x| x.r_err.to_degrees()).collect();
    r.sort_by(f64::total_cmp);
    let within = s.iter().filter(|x| x.within_3_sigma).count() as f64;
    [
        quantile(&t, 0.5),
        quantile(&t, 0.95),
        t.last().copied().unwrap_or(f64::NAN),
        quantile(&r, 0.5),
        100.0 * within / s.len().max(1) as f64,
    ]
}

/// A [`summary`] as the table's columns.
fn columns(a: &[f64; 5]) -> String {
    format!(
        "{:6.1} {:6.1} {:6.1} {:6.2} {:5.1}",
        a[0], a[1], a[2], a[3], a[4]
    )
}

fn parse_seeds(arg: &str) -> Result<Vec<u64>, String> {
    let bad = |e: std::num::ParseIntError| format!("seeds {arg:?}: {e} (e.g. 1-5 or 3)");
    match arg.split_once('-') {
        Some((a, b)) => {
            let (a, b) = (a.parse().map_err(bad)?, b.parse().map_err(bad)?);
            if a > b {
                return Err(format!("seeds {arg:?}: {a} > {b}"));
            }
            Ok((a..=b).collect())
        }
        None => Ok(vec![arg.parse().map_err(bad)?]),
    }
}

fn main() -> Result<(), String> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let seeds = parse_seeds(args.first().map_or("1-5", String::as_str))?;
    let duration_s: f64 = match args.get(1) {
        Some(d) => d
            .parse()
            .map_err(|e| format!("duration {d:?}: {e}"))
            .and_then(|d: f64| {
                if d.is_finite() && d > SCORE_FROM_S {
                    Ok(d)
                } else {
                    Err(format!("duration {d} s: must exceed {SCORE_FROM_S} s"))
                }
            })?,
        None => 40.0,
    };
    let weave_m: f64 = match args.get(2) {
        Some(a) => a
            .parse()
            .map_err(|e| format!("weave {a:?}: {e}"))
            .and_then(|a: f64| {
                if a.is_finite() && a >= 0.0 {
                    Ok(a)
                } else {
                    Err(format!("weave {a} m: must be finite and non-negative"))
                }
            })?,
        None => 0.3,
    };
    let mut nav = NavSensorParams::default();
    if let Some(a) = args.get(3) {
        let deg: f64 = a.parse().map_err(|e| format!("heading noise {a:?}: {e}"))?;
        nav.heading_noise_rad = deg.to_radians();
        nav.validate()
            .map_err(|e| format!("heading noise {deg}°: {e}"))?;
    }
    println!(
        "Live pose error at the map's stamp (mm; rotation deg); \
         {duration_s} s, weave ±{weave_m} m, compass noise {:.2}°, scored from {SCORE_FROM_S} s",
        nav.heading_noise_rad.to_degrees()
    );
    println!(
        "{:<22} seed  maps  poses | median    p95    max    rot  3σ%",
        "mode"
    );
    let mut pooled = vec![Vec::new(); MODES.len()];
    let mut per_seed: Vec<Vec<[f64; 5]>> = vec![Vec::new(); MODES.len()];
    for &seed in &seeds {
        let (scored, maps) = run(seed, duration_s, weave_m, nav)?;
        for (m, s) in scored.into_iter().enumerate() {
            let a = summary(&s);
            println!(
                "{:<22} {seed:4} {maps:5} {:6} | {}",
                MODES[m].0,
                s.len(),
                columns(&a)
            );
            per_seed[m].push(a);
            pooled[m].extend(s);
        }
    }
    for (m, s) in pooled.iter().enumerate() {
        let a = summary(s);
        let range = |i: usize| {
            let v = per_seed[m].iter().map(|s| s[i]);
            let lo = v.clone().fold(f64::INFINITY, f64::min);
            (lo, v.fold(f64::NEG_INFINITY, f64::max))
        };
        let ((m_lo, m_hi), (p_lo, p_hi)) = (range(0), range(1));
        println!(
            "{:<22}  all        {:6} | {}   per seed: median {m_lo:.1}–{m_hi:.1}, p95 {p_lo:.1}–{p_hi:.1}",
            MODES[m].0,
            s.len(),
            columns(&a)
        );
    }
    Ok(())
}
