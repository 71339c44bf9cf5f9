//! `fusion`: the swarm fusion at scale, on observations synthesized from
//! ground truth (`sim_bridge::obs_synth`, no rendering): fused map error,
//! outlier precision/recall and solve time for 3…100 vehicles at outlier
//! rates 0…40 %.
//!
//! The outlier rate is split evenly between wrong IDs (another vehicle's
//! marker), unknown IDs and planar flips. Precision/recall are over the
//! ID outliers (an observation is flagged when fusion accepted none of its
//! hypotheses); flips are reported separately, as the fraction fusion
//! rejected outright — the others were resolved (a hypothesis accepted,
//! which for a flip with a true alternative the map error confirms).

use super::features::plot_or_warn;
use super::plot::{self, Grouped};
use super::table::{median, Csv};
use super::{EvalError, EvalOptions};
use serde_json::{json, Map, Value};
use shoal_fusion::{Fusion, FusionParams};
use shoal_proto::{CodeSet, VehicleId, VehicleState};
use shoal_sim_bridge::obs_synth::{
    grid_formation, synthetic_fleet, FormationJitter, ObsSynth, ObsSynthParams, OutlierKind,
    OutlierModel,
};
use std::collections::BTreeMap;

/// Fleet sizes and outlier rates of the full run.
pub const SIZES: [usize; 6] = [3, 5, 10, 20, 50, 100];
pub const OUTLIER_RATES: [f64; 5] = [0.0, 0.1, 0.2, 0.3, 0.4];
/// Spacing of the grid formation (m): neighbours within the 4 m visibility range.
const SPACING_M: f64 = 1.75;
const FRAME_NS: u64 = 100_000_000;

/// An observation's identity: observer, camera, frame, marker.
type ObsKey = (VehicleId, u8, u64, u32);

/// One (fleet size, outlier rate) result.
#[derive(Debug, Clone, Default)]
struct Cell {
    localized: usize,
    median_error_m: Option<f64>,
    max_error_m: Option<f64>,
    median_angle_deg: Option<f64>,
    precision: Option<f64>,
    recall: Option<f64>,
    flips_rejected: Option<f64>,
    observations: usize,
    solve_ms: f64,
    /// Why inliers were rejected (reason → count).
    inlier_rejections: BTreeMap<String, usize>,
}

fn run_cell(n: usize, rate: f64, frames: usize, seed: u64) -> Result<Cell, EvalError> {
    let fleet =
        synthetic_fleet(n, CodeSet::Aruco4x4_1000).map_err(|e| EvalError::Setup(e.to_string()))?;
    let ids: Vec<VehicleId> = fleet.vehicles.iter().map(|v| v.id).collect();
    let columns = (n as f64).sqrt().ceil() as usize;
    let truth = grid_formation(&ids, columns, SPACING_M, FormationJitter::default(), seed);
    let params = ObsSynthParams {
        outliers: OutlierModel {
            wrong_id_rate: rate / 3.0,
            unknown_id_rate: rate / 3.0,
            flip_rate: rate / 3.0,
            ..OutlierModel::default()
        },
        ..ObsSynthParams::default()
    };
    let mut synth = ObsSynth::new(&fleet, params, seed);
    let mut fusion = Fusion::new(&fleet, FusionParams::default(), "eval");
    let mut labels: BTreeMap<ObsKey, OutlierKind> = BTreeMap::new();
    let mut observations = 0;
    let mut last_stamp = 0;
    for k in 0..frames {
        let stamp = (k as u64 + 1) * FRAME_NS;
        last_stamp = stamp;
        for s in synth.observe(&truth, stamp) {
            let o = &s.obs;
            labels.insert(
                (o.observer, o.camera, o.frame_seq, o.target_marker),
                s.outlier,
            );
            observations += 1;
            let _ = fusion.ingest(s.obs.clone(), s.obs.observer, stamp);
        }
    }
    let t0 = std::time::Instant::now();
    let map = fusion.solve(last_stamp);
    let solve_ms = t0.elapsed().as_secs_f64() * 1e3;

    // Map error against the truth, in the reference vehicle's frame.
    let world_from: BTreeMap<VehicleId, _> = truth
        .iter()
        .map(|t| (t.vehicle, t.world_from_body))
        .collect();
    let reference = world_from.get(&map.reference).copied();
    let (mut errs, mut angs) = (Vec::new(), Vec::new());
    let mut localized = 0;
    for v in &map.vehicles {
        if v.state != VehicleState::Live {
            continue;
        }
        let (Some(r), Some(w)) = (reference, world_from.get(&v.vehicle)) else {
            continue;
        };
        localized += 1;
        if v.vehicle == map.reference {
            continue;
        }
        let t = r.inverse() * w;
        errs.push((v.reference_from_vehicle.translation.vector - t.translation.vector).norm());
        angs.push(
            (v.reference_from_vehicle.rotation * t.rotation.inverse())
                .angle()
                .to_degrees(),
        );
    }
    // Outlier classification from the edge reports: there is one report per
    // hypothesis, so an observation is *flagged* when none of its hypotheses
    // was accepted (an inlier whose flipped twin is rejected is not flagged).
    let mut verdicts: BTreeMap<ObsKey, (bool, Vec<String>)> = BTreeMap::new();
    for e in &map.edges {
        let v = verdicts
            .entry((e.observer, e.camera, e.frame_seq, e.target_marker))
            .or_insert((false, Vec::new()));
        match &e.rejected {
            None => v.0 = true,
            Some(reason) => v.1.push(format!("{reason:?}")),
        }
    }
    let (mut tp, mut fp, mut fn_, mut flips, mut flips_rej) =
        (0usize, 0usize, 0usize, 0usize, 0usize);
    let mut inlier_rejections = BTreeMap::new();
    for (key, (accepted, reasons)) in &verdicts {
        let Some(kind) = labels.get(key) else {
            continue;
        };
        let flagged = !accepted;
        match kind {
            OutlierKind::WrongId | OutlierKind::UnknownId => {
                if flagged {
                    tp += 1
                } else {
                    fn_ += 1
                }
            }
            OutlierKind::Flipped => {
                flips += 1;
                flips_rej += usize::from(flagged);
            }
            OutlierKind::Inlier => {
                if flagged {
                    fp += 1;
                    for r in reasons {
                        *inlier_rejections.entry(r.clone()).or_insert(0) += 1;
                    }
                }
            }
        }
    }
    Ok(Cell {
        localized,
        median_error_m: median(&errs),
        max_error_m: errs.iter().copied().reduce(f64::max),
        median_angle_deg: median(&angs),
        precision: (tp + fp > 0).then(|| tp as f64 / (tp + fp) as f64),
        recall: (tp + fn_ > 0).then(|| tp as f64 / (tp + fn_) as f64),
        flips_rejected: (flips > 0).then(|| flips_rej as f64 / flips as f64),
        observations,
        solve_ms,
        inlier_rejections,
    })
}

pub fn run(opts: &EvalOptions) -> Result<Value, EvalError> {
    let frames = opts.count(5, 20);
    let sizes: Vec<usize> = if opts.quick {
        vec![3, 10]
    } else {
        SIZES.to_vec()
    };
    let rates: Vec<f64> = if opts.quick {
        vec![0.0, 0.2]
    } else {
        OUTLIER_RATES.to_vec()
    };
    let bar = opts.bar(sizes.len() * rates.len(), "fusion: fleets");
    let mut csv = Csv::new(&[
        "vehicles",
        "outlier_rate",
        "frames",
        "observations",
        "localized",
        "median_position_error_m",
        "max_position_error_m",
        "median_angle_error_deg",
        "id_outlier_precision",
        "id_outlier_recall",
        "flips_rejected",
        "solve_ms",
    ]);
    let mut results = Map::new();
    let mut err_vals: Vec<Vec<Option<f64>>> = vec![Vec::new(); rates.len()];
    let mut time_vals: Vec<Vec<Option<f64>>> = vec![Vec::new(); rates.len()];
    for &n in &sizes {
        let mut per = Map::new();
        for (ri, &r) in rates.iter().enumerate() {
            let c = run_cell(
                n,
                r,
                frames,
                opts.seed.wrapping_add(n as u64 * 101 + ri as u64),
            )?;
            let f = |v: Option<f64>| v.map(|x| format!("{x:.6}")).unwrap_or_default();
            csv.row(vec![
                n.to_string(),
                r.to_string(),
                frames.to_string(),
                c.observations.to_string(),
                c.localized.to_string(),
                f(c.median_error_m),
                f(c.max_error_m),
                f(c.median_angle_deg),
                f(c.precision),
                f(c.recall),
                f(c.flips_rejected),
                format!("{:.3}", c.solve_ms),
            ]);
            per.insert(
                format!("{r}"),
                json!({
                    "localized": c.localized,
                    "median_position_error_m": c.median_error_m,
                    "max_position_error_m": c.max_error_m,
                    "median_angle_error_deg": c.median_angle_deg,
                    "id_outlier_precision": c.precision,
                    "id_outlier_recall": c.recall,
                    "flips_rejected": c.flips_rejected,
                    "solve_ms": c.solve_ms,
                    "observations": c.observations,
                    "inlier_rejections": c.inlier_rejections,
                }),
            );
            err_vals[ri].push(c.median_error_m.map(|m| m * 1e3));
            time_vals[ri].push(Some(c.solve_ms));
            bar.inc(1);
        }
        results.insert(n.to_string(), Value::Object(per));
    }
    bar.finish_and_clear();
    csv.write(&opts.out.join("fusion.csv"))?;
    let categories: Vec<String> = sizes.iter().map(|n| n.to_string()).collect();
    let series: Vec<String> = rates
        .iter()
        .map(|r| format!("{:.0} % outliers", r * 100.0))
        .collect();
    let p1 = plot_or_warn(plot::bars(
        &opts.out.join("eval-fusion-error"),
        &Grouped {
            title: format!("Fused map: median position error ({frames} frames)"),
            x_label: "vehicles".into(),
            y_label: "median position error (mm)".into(),
            categories: categories.clone(),
            series: series.clone(),
        },
        &err_vals,
    ));
    let p2 = plot_or_warn(plot::bars(
        &opts.out.join("eval-fusion-solve-time"),
        &Grouped {
            title: "Fusion solve time".into(),
            x_label: "vehicles".into(),
            y_label: "solve time (ms)".into(),
            categories,
            series,
        },
        &time_vals,
    ));
    Ok(json!({
        "frames": frames,
        "setup": "synthetic fleets (obs_synth::synthetic_fleet, ArUco 4x4_1000 IDs), grid formation 1.75 m apart, default noise/visibility models; outlier rate split evenly between wrong IDs, unknown IDs and planar flips; one solve after the window fills",
        "results": results,
        "plots": [p1, p2],
    }))
}
