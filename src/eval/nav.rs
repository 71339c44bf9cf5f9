//! `nav`: fusion with and without the vehicles' own navigation (issue #21),
//! on observations synthesized from ground truth (`sim_bridge::obs_synth`)
//! and nav states from the simulated sensors (`sim_bridge::nav`, default
//! noise: depth 1 cm + 2 cm offset, IMU 0.1° + 0.2° misalignment), the same
//! seeds both ways. Fusion solves after every frame (10 Hz), so every map a
//! formation controller would get is scored.
//!
//! Scenarios:
//! - `one-track`: two vehicles, one camera heard, every visible planar flip
//!   taken as the primary — the case no vote can settle;
//! - `grid-3`, `grid-10`: jittered grid formations (±8° roll, pitch, yaw),
//!   every camera, a third of the primaries flipped (the image pipeline's
//!   rate between 1.25 and 2.25 m, `eval fit-noise`).
//!
//! Nav settings: none; the IMU's roll/pitch and the pressure sensor's depth;
//! those and a compass (AHRS heading 0.5° + 1.5° offset).
//!
//! Per scenario and nav setting: the fraction of maps with a *flip error*
//! (some Live vehicle more than 10° off), the position error of every Live
//! vehicle in every map (median, 95th percentile), its NEES (6 DoF: 6 when
//! the covariance is honest), and the true hypotheses the nav checks
//! rejected (must be none).

use super::features::plot_or_warn;
use super::plot::{self, Grouped};
use super::table::{median, Csv};
use super::{EvalError, EvalOptions};
use serde_json::{json, Map, Value};
use shoal_fusion::{Fusion, FusionParams};
use shoal_proto::geometry::difference;
use shoal_proto::{CodeSet, FleetMap, RejectReason, VehicleId, VehicleState, VehicleTruth};
use shoal_sim_bridge::nav::{NavSensorParams, NavSensors};
use shoal_sim_bridge::obs_synth::{
    grid_formation, synthetic_fleet, FormationJitter, ObsSynth, ObsSynthParams, OutlierModel,
    SyntheticObservation,
};
use std::collections::BTreeMap;

const FRAME_NS: u64 = 100_000_000;
/// A Live vehicle this far off in rotation is on a flip twin, degrees.
const FLIP_ERROR_DEG: f64 = 10.0;
const SPACING_M: f64 = 1.5;

#[derive(Debug, Clone, Copy)]
struct Scenario {
    name: &'static str,
    vehicles: usize,
    only_observer: Option<VehicleId>,
    flip_rate: f64,
}

const SCENARIOS: [Scenario; 3] = [
    Scenario {
        name: "one-track",
        vehicles: 2,
        only_observer: Some(1),
        flip_rate: 1.0,
    },
    Scenario {
        name: "grid-3",
        vehicles: 3,
        only_observer: None,
        flip_rate: 0.3,
    },
    Scenario {
        name: "grid-10",
        vehicles: 10,
        only_observer: None,
        flip_rate: 0.3,
    },
];

/// What one run (scenario, seed, nav setting) measured.
#[derive(Debug, Clone, Default)]
struct Run {
    maps: usize,
    maps_flipped: usize,
    position_errors_m: Vec<f64>,
    nees: Vec<f64>,
    /// True hypotheses rejected as `Gravity` / `Depth` / `Heading`, and false ones.
    true_rejected_by_nav: usize,
    false_rejected_by_nav: usize,
}

/// Score one map against the truth (in the reference's frame).
fn score_map(map: &FleetMap, world: &BTreeMap<VehicleId, shoal_proto::Pose>, run: &mut Run) {
    let Some(world_from_ref) = world.get(&map.reference) else {
        return;
    };
    run.maps += 1;
    let mut flipped = false;
    for v in map
        .vehicles
        .iter()
        .filter(|v| v.state == VehicleState::Live && v.vehicle != map.reference)
    {
        let Some(w) = world.get(&v.vehicle) else {
            continue;
        };
        let truth = world_from_ref.inverse() * w;
        let e = difference(&v.reference_from_vehicle, &truth);
        let angle = e.fixed_rows::<3>(3).norm().to_degrees();
        flipped |= angle > FLIP_ERROR_DEG;
        run.position_errors_m.push(e.fixed_rows::<3>(0).norm());
        if let Some(info) = v.covariance.try_inverse() {
            run.nees.push((e.transpose() * info * e)[0]);
        }
    }
    run.maps_flipped += usize::from(flipped);
}

/// Count the nav verdicts of the last map against the labels.
fn score_nav_verdicts(map: &FleetMap, obs: &[SyntheticObservation], run: &mut Run) {
    let mut reports: BTreeMap<shoal_proto::DetectionKey, Vec<&Option<RejectReason>>> =
        BTreeMap::new();
    for e in &map.edges {
        reports
            .entry(e.detection_key())
            .or_default()
            .push(&e.rejected);
    }
    for o in obs {
        let Some(r) = reports.get(&o.obs.detection_key()) else {
            continue;
        };
        for (h, verdict) in r.iter().enumerate().take(2) {
            if matches!(
                verdict,
                Some(RejectReason::Gravity | RejectReason::Depth | RejectReason::Heading)
            ) {
                if o.hypothesis_is_true(h as u8) {
                    run.true_rejected_by_nav += 1;
                } else {
                    run.false_rejected_by_nav += 1;
                }
            }
        }
    }
}

/// The nav settings compared: none, the IMU's roll/pitch and the pressure
/// sensor, and those with a compass.
const SETTINGS: [(&str, &str); 3] = [
    ("no_nav", "no nav"),
    ("tilt_depth", "IMU roll/pitch + depth"),
    ("tilt_depth_heading", "+ compass heading"),
];

fn sensors(setting: usize) -> Option<NavSensorParams> {
    match setting {
        0 => None,
        1 => Some(NavSensorParams {
            heading: false,
            ..NavSensorParams::default()
        }),
        _ => Some(NavSensorParams::default()),
    }
}

fn run_one(
    s: &Scenario,
    setting: usize,
    frames: usize,
    seed: u64,
    base: &ObsSynthParams,
) -> Result<Run, EvalError> {
    let setup = |e: String| EvalError::Setup(e);
    let fleet =
        synthetic_fleet(s.vehicles, CodeSet::Aruco4x4_1000).map_err(|e| setup(e.to_string()))?;
    let ids: Vec<VehicleId> = fleet.vehicles.iter().map(|v| v.id).collect();
    let columns = (s.vehicles as f64).sqrt().ceil() as usize;
    let truth: Vec<VehicleTruth> =
        grid_formation(&ids, columns, SPACING_M, FormationJitter::default(), seed);
    let world: BTreeMap<VehicleId, shoal_proto::Pose> = truth
        .iter()
        .map(|t| (t.vehicle, t.world_from_body))
        .collect();
    let params = ObsSynthParams {
        outliers: OutlierModel {
            flip_rate: s.flip_rate,
            alternative_rate: 1.0,
            ..base.outliers
        },
        ..*base
    };
    let mut synth = ObsSynth::new(&fleet, params, seed);
    let mut sensors = match sensors(setting) {
        Some(p) => Some(NavSensors::new(p, seed).map_err(|e| setup(e.to_string()))?),
        None => None,
    };
    let fusion_params = FusionParams {
        record_solve_time: false,
        ..FusionParams::default()
    };
    let mut fusion = Fusion::new(&fleet, fusion_params, "eval");
    let mut run = Run::default();
    let mut recent: Vec<SyntheticObservation> = Vec::new();
    for k in 0..frames {
        let now = (k as u64 + 1) * FRAME_NS;
        if let Some(sensors) = sensors.as_mut() {
            for t in &truth {
                fusion
                    .ingest_nav(sensors.measure(t, now), t.vehicle, now)
                    .map_err(|e| setup(format!("nav of vehicle {}: {e}", t.vehicle)))?;
            }
        }
        recent.clear();
        for o in synth.observe(&truth, now) {
            if s.only_observer.is_some_and(|v| v != o.obs.observer) {
                continue;
            }
            let _ = fusion.ingest(o.obs.clone(), o.obs.observer, now);
            recent.push(o);
        }
        let map = fusion.solve(now);
        score_map(&map, &world, &mut run);
        score_nav_verdicts(&map, &recent, &mut run);
    }
    Ok(run)
}

fn percentile(v: &[f64], q: f64) -> Option<f64> {
    let mut s: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    if s.is_empty() {
        return None;
    }
    s.sort_by(f64::total_cmp);
    Some(s[((s.len() - 1) as f64 * q).round() as usize])
}

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

pub fn run(opts: &EvalOptions) -> Result<Value, EvalError> {
    let frames = opts.count(12, 50);
    let base = super::fusion::observation_model(opts, "nav")?;
    let seeds: Vec<u64> = (0..if opts.quick { 2 } else { 5 })
        .map(|k| opts.seed.wrapping_add(k))
        .collect();
    let bar = opts.bar(SCENARIOS.len() * seeds.len() * SETTINGS.len(), "nav: runs");
    let mut csv = Csv::new(&[
        "scenario",
        "nav",
        "seed",
        "maps",
        "maps_flipped",
        "median_position_error_mm",
        "p95_position_error_mm",
        "mean_nees",
        "true_rejected_by_nav",
        "false_rejected_by_nav",
    ]);
    let mut results = Map::new();
    let mut flip_vals: Vec<Vec<Option<f64>>> = vec![Vec::new(); SETTINGS.len()];
    for s in &SCENARIOS {
        let mut per = Map::new();
        for (ni, (key, _)) in SETTINGS.iter().enumerate() {
            let mut all = Run::default();
            let mut flipped_per_seed = Vec::new();
            for &seed in &seeds {
                let r = run_one(s, ni, frames, seed, &base)?;
                let f = |v: Option<f64>| v.map(|x| format!("{x:.4}")).unwrap_or_default();
                csv.row(vec![
                    s.name.into(),
                    key.to_string(),
                    seed.to_string(),
                    r.maps.to_string(),
                    r.maps_flipped.to_string(),
                    f(median(&r.position_errors_m).map(|m| m * 1e3)),
                    f(percentile(&r.position_errors_m, 0.95).map(|m| m * 1e3)),
                    f(mean(&r.nees)),
                    r.true_rejected_by_nav.to_string(),
                    r.false_rejected_by_nav.to_string(),
                ]);
                flipped_per_seed.push(r.maps_flipped as f64 / r.maps.max(1) as f64);
                all.maps += r.maps;
                all.maps_flipped += r.maps_flipped;
                all.position_errors_m.extend(r.position_errors_m);
                all.nees.extend(r.nees);
                all.true_rejected_by_nav += r.true_rejected_by_nav;
                all.false_rejected_by_nav += r.false_rejected_by_nav;
                bar.inc(1);
            }
            let fraction = all.maps_flipped as f64 / all.maps.max(1) as f64;
            flip_vals[ni].push(Some(fraction * 100.0));
            let lo = flipped_per_seed
                .iter()
                .copied()
                .fold(f64::INFINITY, f64::min);
            let hi = flipped_per_seed.iter().copied().fold(0.0, f64::max);
            per.insert(
                key.to_string(),
                json!({
                    "maps": all.maps,
                    "maps_flipped": all.maps_flipped,
                    "maps_flipped_fraction": fraction,
                    "maps_flipped_fraction_seed_range": [lo, hi],
                    "median_position_error_mm": median(&all.position_errors_m).map(|m| m * 1e3),
                    "p95_position_error_mm": percentile(&all.position_errors_m, 0.95).map(|m| m * 1e3),
                    "mean_nees": mean(&all.nees),
                    "median_nees": median(&all.nees),
                    "true_rejected_by_nav": all.true_rejected_by_nav,
                    "false_rejected_by_nav": all.false_rejected_by_nav,
                }),
            );
        }
        results.insert(s.name.into(), Value::Object(per));
    }
    bar.finish_and_clear();
    csv.write(&opts.out.join("nav.csv"))?;
    let p = plot_or_warn(plot::bars(
        &opts.out.join("eval-nav-flips"),
        &Grouped {
            title: format!(
                "Maps with a vehicle on its flip twin (> {FLIP_ERROR_DEG}°), {} seeds x {frames} maps",
                seeds.len()
            ),
            x_label: "scenario".into(),
            y_label: "maps with a flip error (%)".into(),
            categories: SCENARIOS.iter().map(|s| s.name.to_string()).collect(),
            series: SETTINGS.iter().map(|(_, label)| label.to_string()).collect(),
        },
        &flip_vals,
    ));
    Ok(json!({
        "frames": frames,
        "seeds": seeds,
        "observation_model": opts.profile_name(),
        "setup": "synthetic fleets (obs_synth, ArUco 4x4_1000 IDs), grid formations 1.5 m apart jittered ±0.15 m / ±8°, default noise and visibility; simulated nav sensors (NavSensorParams::default); a solve after every 10 Hz frame; same seeds with and without nav",
        "results": results,
        "plots": [p],
    }))
}
