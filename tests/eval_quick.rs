//! The `--quick` variant of every `shoal eval` experiment, run through the
//! library into a temporary directory: the files exist, `summary.json` holds
//! the headline figures under their names, and a few facts the paper
//! predicts hold (each of which a regression can break).

use serde_json::Value;
use shoal::eval::{self, EvalOptions, Experiment};
use shoal_node::restore::Method;
use std::path::PathBuf;

fn out_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("shoal-eval-quick-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn run_quick(experiment: Experiment) -> (PathBuf, Value) {
    run_quick_with(experiment, Method::Hoirm)
}

fn run_quick_with(experiment: Experiment, restore: Method) -> (PathBuf, Value) {
    let dir = out_dir(&format!("{}-{restore}", experiment.name()));
    let opts = EvalOptions {
        quick: true,
        progress: false,
        restore,
        ..EvalOptions::new(&dir)
    };
    let summary = eval::run(experiment, &opts).unwrap_or_else(|e| panic!("{experiment}: {e}"));
    let on_disk: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("summary.json")).unwrap()).unwrap();
    // Same fields (floats may differ in the last digit after a text round trip).
    let keys = |v: &Value| v.as_object().map(|o| o.keys().cloned().collect::<Vec<_>>());
    assert_eq!(
        keys(&on_disk),
        keys(&summary),
        "summary.json holds the returned summary"
    );
    assert_eq!(keys(&on_disk["results"]), keys(&summary["results"]));
    assert_eq!(summary["experiment"], experiment.name());
    (dir, summary)
}

fn assert_files(dir: &std::path::Path, names: &[&str]) {
    for n in names {
        let p = dir.join(n);
        let len = std::fs::metadata(&p).map(|m| m.len()).unwrap_or(0);
        assert!(len > 0, "{} missing or empty", p.display());
    }
}

fn num(v: &Value) -> f64 {
    v.as_f64().unwrap_or_else(|| panic!("not a number: {v}"))
}

#[test]
fn features_error_at_16px_falls_from_4_to_12_points() {
    let (dir, s) = run_quick(Experiment::Features);
    assert_files(
        &dir,
        &["features.csv", "eval-features.png", "eval-features.svg"],
    );
    let r16 = &s["results"]["16"];
    let (e4, e12) = (num(&r16["cumulative_mm_4"]), num(&r16["cumulative_mm_12"]));
    assert!(e12 < 0.9 * e4, "σ=16: 4 points {e4} mm, 12 points {e12} mm");
    // More noise, more error (paper Fig. 3), at every point count reported.
    for key in ["cumulative_mm_4", "cumulative_mm_12", "cumulative_mm_20"] {
        assert!(
            num(&s["results"]["1"][key]) < num(&s["results"]["16"][key]),
            "{key}"
        );
    }
    let rows = std::fs::read_to_string(dir.join("features.csv"))
        .unwrap()
        .lines()
        .count();
    assert_eq!(rows, 1 + 5 * 17, "one row per σ and point count");
}

/// Without restoration, so that this pins the marker, detector and PnP
/// (HOIRM's behaviour in clear water is measured, not asserted: docs/results.md).
#[test]
fn accuracy_quick_locates_shoal_in_clear_water_with_millimetre_error() {
    let (dir, s) = run_quick_with(Experiment::Accuracy, Method::None);
    assert_files(
        &dir,
        &[
            "accuracy.csv",
            "eval-accuracy-distance.png",
            "eval-accuracy-distance.svg",
            "eval-accuracy-angle.png",
            "eval-accuracy-angle.svg",
        ],
    );
    for method in ["shoal", "aruco-opencv", "apriltag3"] {
        for water in ["0.126", "1.38", "5.16", "8.22"] {
            let r = &s["results"][method][water];
            for key in [
                "median_distance_error_mm",
                "median_angle_error_deg",
                "success_rate",
            ] {
                assert!(r.get(key).is_some(), "{method} @ {water}: no {key}");
            }
        }
    }
    let clear = &s["results"]["shoal"]["0.126"];
    assert!(
        num(&clear["success_rate"]) >= 0.6,
        "shoal at 0.126/m: {clear}"
    );
    assert!(num(&clear["median_distance_error_mm"]) < 2.0, "{clear}");
    assert!(num(&clear["median_angle_error_deg"]) < 0.5, "{clear}");
}

#[test]
fn accuracy_yaw_and_rmse_quick_write_their_figures() {
    let (dir, s) = run_quick(Experiment::AccuracyYaw);
    assert_files(
        &dir,
        &[
            "accuracy-yaw.csv",
            "eval-accuracy-yaw.png",
            "eval-accuracy-yaw.svg",
        ],
    );
    assert!(
        s["results"]["shoal"]["0"]["median_abs_yaw_error_deg"].is_number(),
        "{}",
        s["results"]["shoal"]
    );
    let (dir, s) = run_quick(Experiment::AccuracyRmse);
    assert_files(
        &dir,
        &[
            "accuracy-rmse.csv",
            "eval-accuracy-rmse-distance.png",
            "eval-accuracy-rmse-angle.svg",
        ],
    );
    let moderate = &s["results"]["shoal"]["5.16"];
    assert!(num(&moderate["rmse_distance_mm"]) < 5.0, "{moderate}");
}

#[test]
fn detection_quick_succeeds_at_5_16_and_never_improves_with_turbidity() {
    let (dir, s) = run_quick(Experiment::Detection);
    assert_files(
        &dir,
        &["detection.csv", "eval-detection.png", "eval-detection.svg"],
    );
    for method in ["none", "clahe", "dcp", "udcp", "hoirm"] {
        let r = &s["results"][method];
        let at = |w: &str| num(&r[w]["success_rate"]);
        assert!(at("5.16") >= 0.6, "{method} at 5.16/m: {r}");
        assert!(at("14.20") <= at("5.16"), "{method}: {r}");
    }
}

#[test]
fn restoration_quick_hoirm_raises_marker_cnr_over_the_raw_frame() {
    let (dir, s) = run_quick(Experiment::Restoration);
    assert_files(
        &dir,
        &[
            "restoration.csv",
            "eval-restoration-cnr.png",
            "eval-restoration-ssim.svg",
        ],
    );
    for w in ["6.12", "8.22"] {
        let (h, n) = (
            num(&s["results"]["hoirm"][w]["cnr"]),
            num(&s["results"]["none"][w]["cnr"]),
        );
        assert!(h > n, "CNR at {w}/m: hoirm {h}, none {n}");
    }
    assert!(s["results"]["clahe"]["12.20"]["ssim"].is_number());
}

#[test]
fn fit_noise_quick_agrees_with_the_synthesizers_noise_model() {
    let (dir, s) = run_quick(Experiment::FitNoise);
    assert_files(&dir, &["noise.csv", "noise-model.json"]);
    // The observation-level synthesizer's defaults must never be more
    // optimistic than the pipeline (fresh σ at most 2.5x the shipped one at
    // the demo's 1.75 m spacing; few frames in --quick) nor absurdly
    // pessimistic (at least 0.1x). Since session 4's raw-frame corners the
    // pipeline is 7–10x better than the defaults; adopting its fit broke
    // fusion tests tuned to the old noise, so the defaults stay conservative
    // (docs/results.md, "Observation noise fitted to the image pipeline").
    let shipped = shoal_sim_bridge::obs_synth::NoiseModel::default().camera_covariance(1.75);
    let at = s["results"]["ranges"]
        .as_array()
        .unwrap()
        .iter()
        .find(|r| (num(&r["range_m"]) - 1.75).abs() < 1e-9)
        .expect("1.75 m measured")
        .clone();
    assert!(num(&at["detection_rate"]) > 0.9, "{at}");
    for (measured, var) in [
        (num(&at["depth_mm"]) * 1e-3, shipped[(2, 2)]),
        (num(&at["tilt_deg"]).to_radians(), shipped[(3, 3)]),
    ] {
        let ratio = measured / var.sqrt();
        assert!(
            ratio > 0.1 && ratio < 2.5,
            "measured {measured} vs shipped σ {}: {at}",
            var.sqrt()
        );
    }
}

#[test]
fn calibrate_water_quick_writes_a_loadable_presets_file() {
    let (dir, s) = run_quick(Experiment::CalibrateWater);
    assert_files(&dir, &["calibration.csv", "water-calibrated.toml"]);
    let presets =
        shoal_sim_bridge::water::WaterPresets::load(&dir.join("water-calibrated.toml")).unwrap();
    assert!((presets.knobs.backscatter_scale - num(&s["knobs"]["backscatter_scale"])).abs() < 1e-3);
    assert!(s["results"]["clahe"]["10.13"]["success_rate"].is_number());
    assert!(s["max_deviation"].is_number() && s["within_tolerance"].is_boolean());
}

#[test]
fn fusion_quick_rejects_wrong_ids_and_keeps_the_map_within_centimetres() {
    let (dir, s) = run_quick(Experiment::Fusion);
    assert_files(
        &dir,
        &[
            "fusion.csv",
            "eval-fusion-error.png",
            "eval-fusion-solve-time.svg",
        ],
    );
    for n in ["3", "10"] {
        let clean = &s["results"][n]["0"];
        assert_eq!(
            clean["localized"].as_u64(),
            n.parse().ok(),
            "{n} vehicles: {clean}"
        );
        assert!(num(&clean["median_position_error_m"]) < 0.02, "{clean}");
        let dirty = &s["results"][n]["0.2"];
        assert!(num(&dirty["id_outlier_recall"]) >= 0.9, "{dirty}");
        assert!(num(&dirty["median_position_error_m"]) < 0.02, "{dirty}");
    }
}

#[test]
fn swarm_quick_localizes_every_pair_of_the_paper_fleet() {
    let (dir, s) = run_quick(Experiment::Swarm);
    assert_files(
        &dir,
        &["swarm-pairs.csv", "swarm-range.csv", "eval-swarm-range.png"],
    );
    for pair in ["10-15", "10-17", "15-17"] {
        let r = &s["results"][pair];
        assert!(num(&r["median_position_error_mm"]) < 20.0, "{pair}: {r}");
        assert!(num(&r["median_angle_error_deg"]) < 1.0, "{pair}: {r}");
    }
    assert!(num(&s["processing"]["mean_camera_frame_ms"]) > 0.0);
}

#[test]
fn unknown_experiment_names_the_known_ones() {
    let e = "swarms".parse::<Experiment>().unwrap_err().to_string();
    assert!(e.contains("swarms") && e.contains("accuracy-rmse"), "{e}");
}
