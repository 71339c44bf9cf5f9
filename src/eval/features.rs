//! `features` (paper §3.1, Fig. 3): PnP distance error against the number of
//! feature points (4…20) at corner noise σ = 1, 2, 4, 8, 16 px, the paper's
//! Eq. (3)/(4) camera, `trials` noisy solves per cell (1000 in full).

use super::plot::{self, Grouped};
use super::table::Csv;
use super::{EvalError, EvalOptions};
use serde_json::json;
use shoal_node::pose::{features_experiment, FeaturesRow};

/// The paper's noise levels (px).
pub const SIGMAS_PX: [f64; 5] = [1.0, 2.0, 4.0, 8.0, 16.0];
/// The paper's reduction of cumulative error from 4 to 12 points at σ = 16 (mm, §3.1).
pub const PAPER_REDUCTION_4_TO_12_AT_16PX_MM: f64 = 588.32;

pub fn run(opts: &EvalOptions) -> Result<serde_json::Value, EvalError> {
    let trials = opts.count(100, 1000);
    let counts: Vec<usize> = (4..=20).collect();
    let bar = opts.bar(SIGMAS_PX.len(), "features: noise levels");
    let mut rows: Vec<FeaturesRow> = Vec::new();
    for &sigma in &SIGMAS_PX {
        rows.extend(features_experiment(trials, &[sigma], &counts, opts.seed));
        bar.inc(1);
    }
    bar.finish_and_clear();

    let mut csv = Csv::new(&[
        "sigma_px",
        "points",
        "trials",
        "cumulative_mm",
        "relative_mm",
        "mean_mm",
        "failures",
    ]);
    for r in &rows {
        let ok = (r.trials - r.failures).max(1) as f64;
        csv.row(vec![
            r.sigma_px.to_string(),
            r.points.to_string(),
            r.trials.to_string(),
            format!("{:.4}", r.cumulative_mm),
            format!("{:.4}", r.relative_mm),
            format!("{:.5}", r.cumulative_mm / ok),
            r.failures.to_string(),
        ]);
    }
    csv.write(&opts.out.join("features.csv"))?;

    let cell = |sigma: f64, n: usize| rows.iter().find(|r| r.sigma_px == sigma && r.points == n);
    let spec = Grouped {
        title: format!("Cumulative PnP distance error over {trials} trials (paper Fig. 3)"),
        x_label: "feature points".into(),
        y_label: "cumulative error (mm)".into(),
        categories: counts.iter().map(|n| n.to_string()).collect(),
        series: SIGMAS_PX.iter().map(|s| format!("σ = {s} px")).collect(),
    };
    let values: Vec<Vec<Option<f64>>> = SIGMAS_PX
        .iter()
        .map(|&s| {
            counts
                .iter()
                .map(|&n| cell(s, n).map(|r| r.cumulative_mm))
                .collect()
        })
        .collect();
    let plots = plot_or_warn(plot::bars(&opts.out.join("eval-features"), &spec, &values));

    let mut per_sigma = serde_json::Map::new();
    for &s in &SIGMAS_PX {
        let get = |n| cell(s, n).map(|r| r.cumulative_mm);
        per_sigma.insert(
            format!("{s}"),
            json!({
                "cumulative_mm_4": get(4),
                "cumulative_mm_12": get(12),
                "cumulative_mm_20": get(20),
                "reduction_4_to_12_mm": get(4).zip(get(12)).map(|(a, b)| a - b),
                "failures": counts.iter().filter_map(|&n| cell(s, n)).map(|r| r.failures).sum::<usize>(),
            }),
        );
    }
    Ok(json!({
        "trials": trials,
        "points": counts,
        "sigmas_px": SIGMAS_PX,
        "results": per_sigma,
        "paper": { "reduction_4_to_12_at_16px_mm": PAPER_REDUCTION_4_TO_12_AT_16PX_MM },
        "setup": "paper Eq. (3)/(4) camera, 120 mm planar marker at 1 m tilted 20°/15°, points from five nested squares (first 12 = the enhanced marker's corners); see node::pose::features_experiment",
        "plots": plots,
    }))
}

/// Plot paths as JSON, or the reason they are missing (logged, not fatal:
/// the CSV and summary are the results; plots are their illustration).
pub fn plot_or_warn(r: Result<Vec<std::path::PathBuf>, EvalError>) -> serde_json::Value {
    match r {
        Ok(paths) => json!(paths
            .iter()
            .filter_map(|p| p.file_name().map(|f| f.to_string_lossy().into_owned()))
            .collect::<Vec<_>>()),
        Err(e) => {
            tracing::warn!("{e}");
            json!({ "error": e.to_string() })
        }
    }
}
