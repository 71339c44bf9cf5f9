//! The `--quick` variant of every `shoal eval` experiment, run through the
//! library into a temporary directory: the files exist, `summary.json` holds
//! the headline figures under their names, and a few facts the paper
//! predicts hold (each of which a regression can break).

use serde_json::Value;
use shoal::eval::{self, EvalOptions, Experiment};
use shoal_node::restore::Method;
use std::path::PathBuf;

#[path = "common/scratch.rs"]
mod scratch;

fn out_dir(name: &str) -> PathBuf {
    scratch::scratch_dir("shoal-eval-quick", name)
}

fn run_quick(experiment: Experiment) -> (PathBuf, Value) {
    run_quick_with(experiment, Method::Hoirm)
}

fn run_quick_with(experiment: Experiment, restore: Method) -> (PathBuf, Value) {
    run_quick_opts(experiment, restore, None)
}

/// The quick run of `experiment` with `frames` per condition instead of its
/// quick count, where a claim needs more samples than that.
fn run_quick_opts(
    experiment: Experiment,
    restore: Method,
    frames: Option<usize>,
) -> (PathBuf, Value) {
    let dir = out_dir(&format!("{}-{restore}", experiment.name()));
    let opts = EvalOptions {
        quick: true,
        progress: false,
        restore,
        frames,
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
    // Clear water, no restoration: the marker, detector and PnP alone.
    // The 100-frame run reads 0.083 mm / 0.0061° at 0.126 /m and 0.080 mm /
    // 0.0094° at 1.38 /m (docs/results.md, "No restoration"); this 3-frame
    // run 0.083 / 0.0026 and 0.082 / 0.0196. The bounds are 3x the 100-frame
    // distance and 4x its worse angle: room for the median of 3 frames, not
    // for a detector as good as AprilTag 3's (0.34 mm / 0.061° here).
    const MAX_CLEAR_DISTANCE_MM: f64 = 0.25;
    const MAX_CLEAR_ANGLE_DEG: f64 = 0.04;
    // Issue #4's target, measured 0.23–0.26 of the better baseline here
    // (distance and angle, both waters): shoal at most half of it.
    const MAX_RATIO_TO_BEST_BASELINE: f64 = 0.5;
    for water in ["0.126", "1.38"] {
        let clear = &s["results"]["shoal"][water];
        assert_eq!(
            num(&clear["success_rate"]),
            1.0,
            "shoal at {water}/m: {clear}"
        );
        assert!(
            num(&clear["median_distance_error_mm"]) < MAX_CLEAR_DISTANCE_MM,
            "{water}: {clear}"
        );
        assert!(
            num(&clear["median_angle_error_deg"]) < MAX_CLEAR_ANGLE_DEG,
            "{water}: {clear}"
        );
        for key in ["median_distance_error_mm", "median_angle_error_deg"] {
            let best = ["aruco-opencv", "apriltag3"]
                .iter()
                .map(|m| num(&s["results"][m][water][key]))
                .fold(f64::INFINITY, f64::min);
            let ratio = num(&clear[key]) / best;
            assert!(
                ratio <= MAX_RATIO_TO_BEST_BASELINE,
                "{water} {key}: shoal {} vs best baseline {best} (ratio {ratio:.2})",
                clear[key]
            );
        }
    }
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
    // Yaw at 3.92 /m (paper Fig. 15): the 100-frame run reads a median
    // |yaw error| of 0.012° over all angles for shoal, against 0.053°
    // (AprilTag 3) and 0.174° (OpenCV ArUco) (docs/results.md,
    // "accuracy-yaw"); this 2-frame run 0.015° against 0.076° and 0.249°.
    // Bound: 4x the 100-frame median, and at most half the better baseline
    // (measured 0.20–0.23 of it).
    const MAX_YAW_ERROR_DEG: f64 = 0.05;
    const MAX_YAW_RATIO_TO_BEST_BASELINE: f64 = 0.5;
    let yaw = |m: &str| num(&s["results"][m]["all"]["median_abs_yaw_error_deg"]);
    let shoal = yaw("shoal");
    let best = yaw("apriltag3").min(yaw("aruco-opencv"));
    assert!(shoal < MAX_YAW_ERROR_DEG, "{}", s["results"]["shoal"]);
    assert!(
        shoal <= MAX_YAW_RATIO_TO_BEST_BASELINE * best,
        "shoal {shoal}° vs best baseline {best}°"
    );
    for y in ["-50", "0", "50"] {
        assert_eq!(
            num(&s["results"]["shoal"][y]["success_rate"]),
            1.0,
            "yaw {y}: {}",
            s["results"]["shoal"]
        );
    }

    let (dir, s) = run_quick(Experiment::AccuracyRmse);
    assert_files(
        &dir,
        &[
            "accuracy-rmse.csv",
            "eval-accuracy-rmse-distance.png",
            "eval-accuracy-rmse-angle.svg",
        ],
    );
    // RMSE at 600 mm (paper Figs. 16–17): the 100-frame run reads 0.10 mm /
    // 0.01° at 0.126 /m and 0.09 mm / 0.05° at 5.16 /m (docs/results.md,
    // "accuracy-rmse"); this 2-frame run 0.10 / 0.008 and 0.11 / 0.036.
    // Bounds: 4x the 100-frame figures; and the paper's claim up to 5.16 /m,
    // an RMSE lower than the better baseline's by more than 40 % (measured
    // here: 0.11–0.26 of it).
    const MAX_RMSE_DISTANCE_MM: f64 = 0.4;
    const MAX_RMSE_ANGLE_DEG: f64 = 0.2;
    const MAX_RMSE_RATIO_TO_BEST_BASELINE: f64 = 0.6;
    for water in ["0.126", "5.16"] {
        let r = &s["results"]["shoal"][water];
        assert_eq!(num(&r["success_rate"]), 1.0, "{water}: {r}");
        assert!(
            num(&r["rmse_distance_mm"]) < MAX_RMSE_DISTANCE_MM,
            "{water}: {r}"
        );
        assert!(
            num(&r["rmse_angle_deg"]) < MAX_RMSE_ANGLE_DEG,
            "{water}: {r}"
        );
        for key in ["rmse_distance_mm", "rmse_angle_deg"] {
            let best = ["aruco-opencv", "apriltag3"]
                .iter()
                .map(|m| num(&s["results"][m][water][key]))
                .fold(f64::INFINITY, f64::min);
            assert!(
                num(&r[key]) <= MAX_RMSE_RATIO_TO_BEST_BASELINE * best,
                "{water} {key}: shoal {} vs best baseline {best}",
                r[key]
            );
        }
    }
}

/// Table 5's shape, from what this 3-frame run measures (shipped water; the
/// 100-frame table is in docs/results.md, "detection"): every method reads
/// the marker at 5.16 /m; the raw frame is lost by 8.22 /m, every baseline
/// restoration by 10.13 /m, HOIRM reads on there (3-frame rates: none
/// 1, 1, 0, 0, 0, 0; CLAHE 1, 1, 0.67, 0, 0, 0; DCP 1, 1, 1, 0, 0, 0; UDCP as
/// CLAHE; HOIRM 1, 1, 1, 0.67, 0.33, 0), and nothing reads at 14.20 /m.
/// `--profile realistic` reaches the detection experiment's renderer (the
/// summary names it, and its frames are not the ideal ones: the realistic
/// camera's rates differ from the ideal run's at some water), rates still
/// fall with turbidity; the accuracy experiments take it too (below); an
/// experiment that renders only through the ideal camera refuses the option
/// instead of ignoring it.
#[test]
fn detection_quick_renders_through_a_camera_profile_and_the_others_refuse_one() {
    use shoal_sim_bridge::profile::CameraProfile;
    let with_profile = |name: &str, profile: Option<CameraProfile>| {
        let dir = out_dir(name);
        EvalOptions {
            quick: true,
            progress: false,
            profile,
            ..EvalOptions::new(&dir)
        }
    };
    let refused = eval::run(
        Experiment::Features,
        &with_profile("features-realistic", Some(CameraProfile::realistic())),
    )
    .expect_err("features does not take a profile");
    let msg = format!("{refused:#}");
    assert!(
        msg.contains("camera profile `realistic`")
            && msg.contains("detection")
            && msg.contains("restoration")
            && msg.contains("accuracy-rmse")
            && msg.contains("swarm"),
        "{msg}"
    );
    // Accuracy through the realistic camera, one frame per water: the node
    // holds a lab's in-water calibration behind the port, off by the
    // calibration error, so the pose carries millimetres of bias the ideal
    // camera does not have (ideal, 100 frames: 0.083 mm at 0.126 /m; the
    // realistic seeds 1-5 in docs/results.md, "accuracy": ~5 mm).
    let accuracy = eval::run(
        Experiment::Accuracy,
        &EvalOptions {
            frames: Some(1),
            restore: Method::None,
            ..with_profile("accuracy-realistic", Some(CameraProfile::realistic()))
        },
    )
    .expect("accuracy through the realistic profile");
    assert_eq!(accuracy["camera_profile"], "realistic");
    let clear = &accuracy["results"]["shoal"]["0.126"];
    assert_eq!(num(&clear["success_rate"]), 1.0, "{clear}");
    let err = num(&clear["median_distance_error_mm"]);
    assert!(err > 1.0 && err < 20.0, "{clear}");
    // Restoration through the realistic camera: HOIRM's marker CNR stays
    // above the raw frame's at every water, though its lead over the best
    // other method shrinks from 2.3-10x to 1.3-1.8x (docs/results.md,
    // "restoration through the realistic camera": raw 0.12-2.1, HOIRM
    // 0.44-6.5, seeds 1-5). Bound: twice the raw frame's.
    let restored = eval::run(
        Experiment::Restoration,
        &with_profile("restoration-realistic", Some(CameraProfile::realistic())),
    )
    .expect("restoration through the realistic profile");
    assert_eq!(restored["camera_profile"], "realistic");
    for w in ["6.12", "8.22", "10.13", "12.20"] {
        let cnr = |m: &str| num(&restored["results"][m][w]["cnr"]);
        assert!(
            cnr("hoirm") >= 2.0 * cnr("none"),
            "CNR at {w}/m: hoirm {}, none {}",
            cnr("hoirm"),
            cnr("none")
        );
    }
    let realistic = eval::run(
        Experiment::Detection,
        &with_profile("detection-realistic", Some(CameraProfile::realistic())),
    )
    .expect("detection through the realistic profile");
    let ideal = eval::run(
        Experiment::Detection,
        &with_profile("detection-ideal", None),
    )
    .expect("detection through the ideal camera");
    assert_eq!(realistic["camera_profile"], "realistic");
    assert_eq!(ideal["camera_profile"], "ideal");
    const WATERS: [&str; 6] = ["5.16", "6.12", "8.22", "10.13", "12.20", "14.20"];
    let rates = |s: &Value| -> Vec<f64> {
        ["none", "clahe", "dcp", "udcp", "hoirm"]
            .iter()
            .flat_map(|m| WATERS.map(|w| num(&s["results"][*m][w]["success_rate"])))
            .collect()
    };
    assert_ne!(
        rates(&realistic),
        rates(&ideal),
        "the profile changed no frame"
    );
    let one_frame = 1.0 / num(&realistic["frames"]);
    for method in ["none", "clahe", "dcp", "udcp", "hoirm"] {
        let r = |w: &str| num(&realistic["results"][method][w]["success_rate"]);
        assert!(
            r("14.20") <= one_frame + 1e-9,
            "{method}: {}",
            realistic["results"]
        );
    }
}

#[test]
fn detection_quick_falls_with_turbidity_and_hoirm_holds_longest() {
    let (dir, s) = run_quick(Experiment::Detection);
    assert_files(
        &dir,
        &["detection.csv", "eval-detection.png", "eval-detection.svg"],
    );
    const WATERS: [&str; 6] = ["5.16", "6.12", "8.22", "10.13", "12.20", "14.20"];
    // One frame of the run: a rate may wobble by one frame between waters,
    // and "lost" means at most one frame read (100-frame rates there: 0.00–0.08).
    let one_frame = 1.0 / num(&s["frames"]);
    let rate = |m: &str, w: &str| num(&s["results"][m][w]["success_rate"]);
    for method in ["none", "clahe", "dcp", "udcp", "hoirm"] {
        let r = &s["results"][method];
        assert!(rate(method, "5.16") >= 0.6, "{method} at 5.16/m: {r}");
        for pair in WATERS.windows(2) {
            assert!(
                rate(method, pair[1]) <= rate(method, pair[0]) + one_frame + 1e-9,
                "{method} improves from {} to {} /m: {r}",
                pair[0],
                pair[1]
            );
        }
        assert!(rate(method, "14.20") <= one_frame + 1e-9, "{method}: {r}");
    }
    assert!(
        rate("none", "8.22") <= one_frame + 1e-9,
        "{}",
        s["results"]["none"]
    );
    let best_baseline = ["none", "clahe", "dcp", "udcp"]
        .iter()
        .map(|m| rate(m, "10.13"))
        .fold(0.0, f64::max);
    assert!(best_baseline <= one_frame + 1e-9, "{}", s["results"]);
    assert!(
        rate("hoirm", "10.13") > best_baseline && rate("hoirm", "8.22") == 1.0,
        "HOIRM {} vs the best baseline at 10.13 /m {best_baseline}",
        s["results"]["hoirm"]
    );
}

/// HOIRM against every other method on the marker region (paper Tables
/// 1–4). CNR alone a low-pass filter could raise; that HOIRM is more than a
/// low-pass is pinned by node/tests/restore_synthetic.rs (CNR and edge
/// sharpness against every Gaussian of the input) and by the detection
/// test above. Here: what the paper claims and this run measures.
#[test]
fn restoration_quick_hoirm_doubles_every_methods_marker_cnr_and_raises_ssim() {
    let (dir, s) = run_quick(Experiment::Restoration);
    assert_files(
        &dir,
        &[
            "restoration.csv",
            "eval-restoration-cnr.png",
            "eval-restoration-ssim.svg",
        ],
    );
    // The paper: HOIRM's CNR "at least double" CLAHE's. Measured (2 frames,
    // shipped water) 2.7–8.6x the best other method at every water (10
    // frames: 2.8–9x, docs/results.md "restoration").
    const MIN_CNR_RATIO_TO_OTHERS: f64 = 2.0;
    // SSIM against the clean twin: HOIRM 9–18 % above the raw frame at 6.12–10.13
    // /m here and in the 10-frame run; at 12.20 /m it is not (0.23 vs 0.25),
    // so that water is not asserted. Bound: 5 % above.
    const MIN_SSIM_RATIO_TO_RAW: f64 = 1.05;
    let get = |m: &str, w: &str, k: &str| num(&s["results"][m][w][k]);
    for w in ["6.12", "8.22", "10.13", "12.20"] {
        let h = get("hoirm", w, "cnr");
        for other in ["none", "clahe", "dcp", "udcp"] {
            let o = get(other, w, "cnr");
            assert!(
                h >= MIN_CNR_RATIO_TO_OTHERS * o,
                "CNR at {w}/m: hoirm {h}, {other} {o}"
            );
        }
    }
    for w in ["6.12", "8.22", "10.13"] {
        let (h, n) = (get("hoirm", w, "ssim"), get("none", w, "ssim"));
        assert!(
            h >= MIN_SSIM_RATIO_TO_RAW * n,
            "SSIM at {w}/m: hoirm {h}, none {n}"
        );
    }
}

#[test]
fn fit_noise_quick_agrees_with_the_synthesizers_noise_model() {
    // 12 frames per condition, not the quick 4: with 4, the 1.75 m tilt σ
    // ranged 0.07–0.20° over seeds 1–10 (0.05–0.17° with the renderer's
    // noise before session 29, which drew the same model in another order),
    // too wide for the band below; with 12, 0.059–0.100° over seeds 1–8.
    let (dir, s) = run_quick_opts(Experiment::FitNoise, Method::Hoirm, Some(12));
    assert_files(&dir, &["noise.csv", "noise-model.json"]);
    // Two claims at the demo's 1.75 m spacing:
    //
    // 1. The pipeline's precision: session 4's 60-frame fit reads depth σ
    //    0.23 mm and tilt σ 0.061° at 1.75 m (docs/results.md, "Observation
    //    noise fitted to the image pipeline"); 60-frame runs of session 29,
    //    seeds 1–7: 0.20–0.28 mm and 0.072–0.094°. The band is the fit's
    //    figure ÷2 … ×2: a pipeline twice as noisy fails.
    // 2. The observation-level synthesizer's defaults are never optimistic
    //    (fresh σ below the shipped one) nor absurdly pessimistic (at least
    //    0.05x). Session 4's own 60-frame fit is 0.097x the shipped depth σ
    //    (0.23 against 2.37 mm), so the 0.1x this bound was before passed
    //    only on a lucky 4-frame draw (0.13x); seed 1 with 12 frames reads
    //    0.09x depth and 0.15x tilt. They are deliberately conservative:
    //    adopting session 4's fit broke fusion tests tuned to the old noise
    //    (same section of docs/results.md); refitting them means revisiting
    //    this bound.
    const PIPELINE_DEPTH_SIGMA_MM: f64 = 0.23;
    const PIPELINE_TILT_SIGMA_DEG: f64 = 0.061;
    const SAMPLING_BAND: f64 = 2.0;
    const MIN_RATIO_TO_SHIPPED: f64 = 0.05;
    const MAX_RATIO_TO_SHIPPED: f64 = 1.0;
    let shipped = shoal_sim_bridge::obs_synth::NoiseModel::default().camera_covariance(1.75);
    let at = s["results"]["ranges"]
        .as_array()
        .unwrap()
        .iter()
        .find(|r| (num(&r["range_m"]) - 1.75).abs() < 1e-9)
        .expect("1.75 m measured")
        .clone();
    assert!(num(&at["detection_rate"]) > 0.9, "{at}");
    assert_eq!(at["gross_errors"].as_u64(), Some(0), "{at}");
    for (name, measured, pipeline) in [
        ("depth mm", num(&at["depth_mm"]), PIPELINE_DEPTH_SIGMA_MM),
        ("tilt deg", num(&at["tilt_deg"]), PIPELINE_TILT_SIGMA_DEG),
    ] {
        assert!(
            measured > pipeline / SAMPLING_BAND && measured < pipeline * SAMPLING_BAND,
            "{name}: σ {measured} against the 60-frame fit's {pipeline}: {at}"
        );
    }
    for (measured, var) in [
        (num(&at["depth_mm"]) * 1e-3, shipped[(2, 2)]),
        (num(&at["tilt_deg"]).to_radians(), shipped[(3, 3)]),
    ] {
        let ratio = measured / var.sqrt();
        assert!(
            ratio > MIN_RATIO_TO_SHIPPED && ratio < MAX_RATIO_TO_SHIPPED,
            "measured {measured} vs shipped σ {}: {at}",
            var.sqrt()
        );
    }
}

/// The search's bookkeeping, which a broken loss or search would break: the
/// reported deviation is the largest |rate − Table 5| of the reported
/// rates, the verdict follows from it, the result is never worse than the
/// start (the first evaluation in calibration.csv), the budget is spent
/// (3 evaluations in --quick: measured, the shipped water stays at 0.61,
/// far from the ±0.15 band), and the file holds the knobs reported.
#[test]
fn calibrate_water_quick_writes_a_loadable_presets_file() {
    let (dir, s) = run_quick(Experiment::CalibrateWater);
    assert_files(&dir, &["calibration.csv", "water-calibrated.toml"]);
    let presets =
        shoal_sim_bridge::water::WaterPresets::load(&dir.join("water-calibrated.toml")).unwrap();
    let k = &s["knobs"];
    for (name, v) in [
        ("backscatter_scale", presets.knobs.backscatter_scale),
        ("noise_scale", presets.knobs.noise_scale),
        ("psf_width_scale", presets.knobs.psf_width_scale),
        ("forward_scatter_scale", presets.knobs.forward_scatter_scale),
    ] {
        assert!(
            (v - num(&k[name])).abs() < 1e-3,
            "{name}: file {v}, summary {k}"
        );
    }
    let tolerance = num(&s["tolerance"]);
    assert_eq!(tolerance, 0.15, "issue #6's band");
    let worst = s["results"]["clahe"]
        .as_object()
        .unwrap()
        .values()
        .map(|r| (num(&r["success_rate"]) - num(&r["paper_success_rate"])).abs())
        .fold(0.0, f64::max);
    let reported = num(&s["max_deviation"]);
    assert!(
        (worst - reported).abs() < 1e-9,
        "max_deviation {reported}, rates say {worst}"
    );
    assert_eq!(s["within_tolerance"].as_bool(), Some(reported <= tolerance));
    let csv = std::fs::read_to_string(dir.join("calibration.csv")).unwrap();
    let rows: Vec<&str> = csv.lines().skip(1).collect();
    assert_eq!(
        rows.len() as u64,
        s["evaluations"].as_u64().unwrap(),
        "{csv}"
    );
    assert!(
        reported <= tolerance / 2.0 || rows.len() == 3,
        "budget not spent: {csv}"
    );
    let start: f64 = rows[0].rsplit(',').next().unwrap().parse().unwrap();
    assert!(
        reported <= start + 1e-9,
        "worse than the start ({start}): {reported}"
    );
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
    assert_eq!(s["observation_model"], "ideal");
}

/// `--profile realistic` gives fusion the observations the realistic
/// camera's pipeline makes (`ObsSynthParams::realistic`: each camera's
/// calibration bias, a depth bias all share, shorter reach): every vehicle is
/// still localized, but the map carries millimetres of bias the ideal
/// observations do not (quick run: 8 / 17 mm median at 3 / 10 vehicles,
/// ideal 2.0 / 0.5 mm). `links` and `nav` take the same model. An
/// image-level profile they have no model for is refused, not ignored.
#[test]
fn fusion_quick_takes_the_realistic_observation_model_and_refuses_other_profiles() {
    use shoal_sim_bridge::profile::{CameraProfile, Effect};
    let opts = |name: &str, profile: Option<CameraProfile>| EvalOptions {
        quick: true,
        progress: false,
        profile,
        ..EvalOptions::new(out_dir(name))
    };
    let ideal = eval::run(Experiment::Fusion, &opts("fusion-ideal", None)).expect("ideal");
    let realistic = eval::run(
        Experiment::Fusion,
        &opts("fusion-realistic", Some(CameraProfile::realistic())),
    )
    .expect("fusion on the realistic observation model");
    assert_eq!(realistic["observation_model"], "realistic");
    for n in ["3", "10"] {
        let (r, i) = (&realistic["results"][n]["0"], &ideal["results"][n]["0"]);
        assert_eq!(r["localized"].as_u64(), n.parse().ok(), "{n}: {r}");
        let (er, ei) = (
            num(&r["median_position_error_m"]),
            num(&i["median_position_error_m"]),
        );
        assert!(
            er > 0.003 && er < 0.05 && er > 2.0 * ei,
            "{n}: realistic {er} m vs ideal {ei} m"
        );
        assert!(num(&r["mean_nees"]).is_finite(), "{r}");
    }
    let refused = eval::run(
        Experiment::Fusion,
        &opts("fusion-port", Some(CameraProfile::only(&[Effect::Port]))),
    )
    .expect_err("no observation model for a port alone");
    assert!(
        format!("{refused:#}").contains("fitted to the `realistic` profile only"),
        "{refused:#}"
    );
    // The links experiment draws its observations from the same model.
    let links = eval::run(
        Experiment::Links,
        &opts("links-realistic", Some(CameraProfile::realistic())),
    )
    .expect("links on the realistic observation model");
    assert_eq!(links["observation_model"], "realistic");
    // Its planar twins put the maps metres off unless the vehicles' nav
    // crosses the link as well (session 33, quick: p95 142.6 cm without,
    // 4.9–6.8 cm with; the full-rate map 242 cm without nav, 5.5 with).
    let holding = &links["results"]["holding"];
    let (plain, nav) = (&holding["compact"]["1000"], &holding["compact+nav"]["1000"]);
    assert!(num(&plain["p95_diff_cm"]["min"]) > 50.0, "{plain}");
    assert!(num(&nav["p95_diff_cm"]["max"]) < 10.0, "{nav}");
    assert!(
        num(&nav["p95_full_rate_vs_truth_cm"]["max"]) < 10.0,
        "{nav}"
    );
    assert!(num(&nav["nav_spans_per_s"]["min"]) > 0.4, "{nav}");
    let refused = eval::run(
        Experiment::Links,
        &opts("links-port", Some(CameraProfile::only(&[Effect::Port]))),
    )
    .expect_err("no observation model for a port alone");
    assert!(
        format!("{refused:#}").contains("links: camera profile `port`"),
        "{refused:#}"
    );
    // So does nav: the vehicles' own IMU, depth and compass still settle the
    // realistic pipeline's flips and refuse no true hypothesis (quick: the
    // lone track 22 of 24 maps flipped without nav, 0 with all three).
    let nav = eval::run(
        Experiment::Nav,
        &opts("nav-realistic", Some(CameraProfile::realistic())),
    )
    .expect("nav on the realistic observation model");
    assert_eq!(nav["observation_model"], "realistic");
    assert_nav_settles_every_flip(&nav["results"]);
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
    // The fine pass is counted per camera frame, at most once each.
    let fine = &s["fine_pass"];
    assert!(
        num(&fine["camera_frames"]) > 0.0 && num(&fine["searched"]) <= num(&fine["camera_frames"]),
        "{fine}"
    );
    assert_eq!(
        (s["camera_profile"].as_str(), s["restore"].as_str()),
        (Some("ideal"), Some("hoirm"))
    );
}

#[test]
fn unknown_experiment_names_the_known_ones() {
    let e = "swarms".parse::<Experiment>().unwrap_err().to_string();
    assert!(e.contains("swarms") && e.contains("accuracy-rmse"), "{e}");
}

/// Issue #22: at 1 000 bit/s per vehicle (1 s latency, 10 % loss) the
/// compact observations keep every vehicle's map of the paper's three
/// vehicles, holding station, within 5 cm of the full-rate map with every
/// pair localized; today's ~600-byte messages through the same link leave
/// most pairs unknown.
#[test]
fn links_quick_compact_observations_keep_the_map_within_5_cm_at_1000_bits() {
    let (dir, s) = run_quick(Experiment::Links);
    assert_files(
        &dir,
        &[
            "links.csv",
            "eval-links-difference.png",
            "eval-links-unknown.svg",
        ],
    );
    let compact = &s["results"]["holding"]["compact"]["1000"];
    assert!(num(&compact["max_diff_cm"]["max"]) <= 5.0, "{compact}");
    assert!(num(&compact["pairs_missing"]["max"]) == 0.0, "{compact}");
    assert!(
        num(&compact["bytes_per_packet"]["max"]) <= 66.0 + 8.0,
        "{compact}"
    );
    // With the vehicles' nav as spans beside the observations, the same.
    let nav = &s["results"]["holding"]["compact+nav"]["1000"];
    assert!(num(&nav["max_diff_cm"]["max"]) <= 5.0, "{nav}");
    assert!(num(&nav["pairs_missing"]["max"]) == 0.0, "{nav}");
    let full = &s["results"]["holding"]["full"]["1000"];
    assert!(num(&full["pairs_missing"]["min"]) >= 0.5, "{full}");
    assert!(num(&full["bytes_per_packet"]["min"]) >= 400.0, "{full}");
    // Less bandwidth, older news.
    let slow = &s["results"]["holding"]["compact"]["300"];
    assert!(
        num(&slow["median_oldest_news_s"]["mean"]) > num(&compact["median_oldest_news_s"]["mean"]),
        "{slow} vs {compact}"
    );
}

/// Issue #21: with both vehicles' IMU roll/pitch, depth and compass heading,
/// no map puts a vehicle on its planar-flip twin, even where one camera's
/// track is the only evidence and every primary is the twin (without nav,
/// every such map is wrong); and no true hypothesis is refused by the nav
/// checks anywhere.
#[test]
fn nav_quick_settles_every_planar_flip_and_refuses_no_true_hypothesis() {
    let (dir, s) = run_quick(Experiment::Nav);
    assert_files(
        &dir,
        &["nav.csv", "eval-nav-flips.png", "eval-nav-flips.svg"],
    );
    let r = &s["results"];
    assert_nav_settles_every_flip(r);
    for scenario in ["one-track", "grid-3", "grid-10"] {
        for setting in ["tilt_depth", "tilt_depth_heading"] {
            let v = &r[scenario][setting];
            assert!(num(&v["maps"]) > 0.0, "{scenario} {setting}: {v}");
        }
    }
    assert!(num(&r["one-track"]["tilt_depth_heading"]["false_rejected_by_nav"]) > 0.0);
}

/// The nav experiment's `results`: without nav the lone track's twin wins
/// (the premise); with IMU, depth and compass no map is flipped in any
/// scenario, and no nav setting refuses a true hypothesis.
fn assert_nav_settles_every_flip(r: &Value) {
    assert!(
        num(&r["one-track"]["no_nav"]["maps_flipped_fraction"]) >= 0.5,
        "premise: without nav the lone track's twin wins: {}",
        r["one-track"]
    );
    for scenario in ["one-track", "grid-3", "grid-10"] {
        let full = &r[scenario]["tilt_depth_heading"];
        assert_eq!(num(&full["maps_flipped"]), 0.0, "{scenario}: {full}");
        for setting in ["tilt_depth", "tilt_depth_heading"] {
            let v = &r[scenario][setting];
            assert_eq!(
                num(&v["true_rejected_by_nav"]),
                0.0,
                "{scenario} {setting}: {v}"
            );
        }
    }
}

/// Measured (quick, seed 1, 2 frames per condition): median position error
/// of the lab's in-water pinhole 3.48 / 3.50 mm at 1 m (0° / 20° off axis)
/// and 5.19 / 3.24 mm at 4 m; of the refractive model 0.40 / 0.45 and
/// 0.87 / 0.44 mm. The lab calibration: fx 1250.7 (the lens's 932.8 × 1.34 =
/// 1250.0), k1 +0.30 (the port's pincushion), RMS 0.067 px on corners with
/// 0.05 px of noise (the pinhole cannot fit the port exactly).
#[test]
fn refraction_quick_the_port_model_beats_the_lab_pinhole_off_axis_and_far() {
    let (dir, s) = run_quick(Experiment::Refraction);
    assert_files(
        &dir,
        &[
            "summary.json",
            "refraction.csv",
            "refraction_position.png",
            "refraction_position.svg",
        ],
    );
    let r = &s["results"];
    let lab = &r["lab_calibration"];
    // The calibration finds the in-water focal length (lens fx × n_water)...
    let fx_wet = 1250.0;
    assert!((num(&lab["fx"]) / fx_wet - 1.0).abs() < 0.005, "{lab}");
    // ... absorbs the port's pincushion in k1 (the lens alone has -0.05) ...
    assert!(num(&lab["distortion"][0]) > 0.1, "{lab}");
    // ... and leaves a misfit above the corners' 0.05 px noise, which alone
    // would give ~0.049 px.
    assert!(num(&lab["rms_px"]) > 0.055, "{lab}");
    let c = &r["conditions"];
    let pos = |m: &str, key: &str| num(&c[m][key]["position_mm"]["median"]);
    for key in ["r1.0_a0", "r1.0_a20", "r4.0_a0", "r4.0_a20"] {
        let (p, q) = (pos("pinhole", key), pos("refractive", key));
        println!("{key}: pinhole {p:.2} mm, refractive {q:.2} mm");
        // Measured 6-8x apart; half would already be a regression.
        assert!(q < 0.5 * p, "{key}: refractive {q} vs pinhole {p}");
        assert!(q < 2.0, "{key}: refractive {q} mm");
        assert_eq!(num(&c["pinhole"][key]["solved"]), 2.0, "{key}");
    }
    // On the axis the pinhole's error grows with the range (measured 3.5 → 5.2 mm).
    assert!(pos("pinhole", "r4.0_a0") > pos("pinhole", "r1.0_a0"));
}

#[test]
fn node_rate_quick_accounts_for_every_frame_offered_and_reads_markers() {
    let (dir, s) = run_quick(Experiment::NodeRate);
    assert_files(&dir, &["node-rate.md", "summary.json"]);
    let runs = s["runs"].as_array().expect("runs");
    assert_eq!(runs.len(), 2, "{s}");
    for r in runs {
        let offered = num(&r["offered"]);
        let accounted =
            num(&r["processed"]) + num(&r["dropped"]) + num(&r["invalid"]) + num(&r["queued"]);
        assert_eq!(
            offered, accounted,
            "every frame offered is processed, dropped or queued: {r}"
        );
        assert_eq!(num(&r["invalid"]), 0.0, "{r}");
        assert!(num(&r["processed"]) > 0.0, "{r}");
        let cpu = num(&r["cpu_ms_per_frame"]);
        assert!(cpu > 0.5 && cpu < 5000.0, "{r}");
        assert_eq!(num(&r["cameras"]), 5.0);
        assert_eq!(tallied_frames(r), num(&r["processed"]), "{r}");
    }
    // At 0.5 /m the neighbours' markers read on most side-camera frames (at
    // 8.22 /m on about a quarter of the port camera's: not asserted).
    assert!(num(&runs[0]["observations"]) > 0.0, "{}", runs[0]);
    // The ideal camera's noise is what HOIRM predicts: the three cameras
    // that see no marker restore no region, and the two that see one at
    // 1.8 m read clear water (1.3–1.5 /m measured; turbid would be ≥ 3).
    for t in runs[0]["restoration"].as_array().expect("restoration") {
        let c = num(&t["water_c_per_m"]["most"]);
        match t["camera"].as_str() {
            Some("port" | "starboard") => assert!(c < 3.0, "{t}"),
            _ => assert_eq!(num(&t["mean_restored_fraction"]), 0.0, "{t}"),
        }
    }
}

/// Frames in a node-rate run's per-camera restoration tallies.
fn tallied_frames(run: &Value) -> f64 {
    run["restoration"]
        .as_array()
        .expect("restoration")
        .iter()
        .map(|t| num(&t["frames"]))
        .sum()
}

/// `node-rate --profile realistic` (issues #16, #18): the node fed frames
/// rendered through the realistic camera (marine snow, JPEG, blur…) with a
/// lab's calibration of each camera; every frame offered is accounted for
/// and the neighbours still read at 0.5 /m (docs/results.md, *node-rate*:
/// through it the node needs ~2 cores at 0.5 /m, not 0.6).
#[test]
fn node_rate_quick_takes_the_realistic_camera() {
    let dir = out_dir("node-rate-realistic");
    let opts = EvalOptions {
        quick: true,
        progress: false,
        profile: Some(shoal_sim_bridge::profile::CameraProfile::realistic()),
        ..EvalOptions::new(&dir)
    };
    let s = eval::run(Experiment::NodeRate, &opts).expect("node-rate through the realistic camera");
    assert_eq!(s["camera_profile"], "realistic", "{s}");
    let runs = s["runs"].as_array().expect("runs");
    assert_eq!(runs.len(), 2, "{s}");
    for r in runs {
        let accounted =
            num(&r["processed"]) + num(&r["dropped"]) + num(&r["invalid"]) + num(&r["queued"]);
        assert_eq!(num(&r["offered"]), accounted, "{r}");
        assert_eq!(num(&r["invalid"]), 0.0, "{r}");
        assert!(num(&r["processed"]) > 0.0, "{r}");
        assert_eq!(tallied_frames(r), num(&r["processed"]), "{r}");
        // A frame HOIRM restored whole is searched once (the default
        // `fine_pass_whole_frame = false`): the fine passes fit in the
        // frames restored in regions.
        for t in r["restoration"].as_array().expect("restoration") {
            assert!(
                num(&t["fine_searches"]) <= num(&t["frames"]) - num(&t["restored_whole"]),
                "{t}"
            );
        }
    }
    assert!(num(&runs[0]["observations"]) > 0.0, "{}", runs[0]);
}

/// `nees` (issue #16): the node as shipped on the ideal and realistic
/// profiles. Fails if the covariance is off: for `ideal`, the mean NEES
/// (6-DoF) of the reads within 3° of the truth must lie above a quarter of
/// the lower end of the χ² band a consistent covariance gives (conservative
/// by at most a factor 2 in σ: the 0.05 px floor makes clear water
/// cautious) and below 1.5 times its upper end (overconfident by at most
/// 1.22 in σ: fusion gates on it). The band is the 95 % interval of the
/// mean of those reads. Reads more than 3° off (planar flips and gross
/// misreads, which fusion settles with the other hypothesis and other
/// observations) are left out, as every table of `docs/results.md` *nees*
/// leaves them out, and counted: at most a quarter of the reads. One of
/// them decides the plain mean: at 3.92 /m a 4-corner read of a 57 px
/// marker at 1.2 m (contrast 0.015), 5.6° off with NEES 67, took it to
/// 10.0 on 13 reads, and read 40° off (HOIRM's water estimate less the
/// noise's share, session 41) to 23.1, while the other reads gave 5.20 and
/// 4.75 (band 4.1–8.2). Measured (2026-12-06, session 41): 3.28 at 1.38 /m
/// (15 reads, none off; band 4.4–7.9) and 4.75 at 3.92 /m (11 of 13 reads;
/// band 4.1–8.2). Without the pattern fit's corner covariance in the pose
/// (`shoal_node::pose::corner_covariance`) 3.92 /m reads 14.5 on the same
/// 11 and fails here. For `realistic`, the stated calibration σ must lower
/// the NEES and a scale must be fitted on 1.38 /m.
#[test]
fn nees_quick_covariance_neither_overconfident_nor_far_too_cautious() {
    let (dir, s) = run_quick(Experiment::Nees);
    assert_files(&dir, &["frames.csv", "summary.json"]);
    for c in ["1.38", "3.92"] {
        let cell = &s["results"]["ideal"][c];
        let (read, flips) = (num(&cell["read"]), num(&cell["flips"]));
        assert!(
            4.0 * flips <= read,
            "ideal {c}: {flips} of {read} reads > 3° off"
        );
        let n = &cell["nees6_without_flips"];
        assert!(num(&n["frames"]) >= 5.0, "ideal {c}: {n}");
        let band = &n["chi2_band95"];
        let (lo, hi) = (num(&band[0]), num(&band[1]));
        let mean = num(&n["mean"]);
        assert!(
            mean > lo / 4.0 && mean < hi * 1.5,
            "ideal {c}: mean NEES {mean} vs χ² band {lo}..{hi}"
        );
    }
    let cal = &s["calibration_scale"]["per_water"]["1.38"];
    assert!(
        num(&cal["scale_1"]["mean"]) < num(&cal["scale_0"]["mean"]),
        "{cal}"
    );
    assert!(num(&s["calibration_scale"]["fitted"]) > 0.0);
}

/// `profiles --quick`: clear water at 1 m (three seeds, two frames each) and
/// the motion-blur ablation. Measured in the full run (seeds 1-5): the ideal
/// camera reads every frame with a 0.05 mm median position error; the
/// realistic one 6.3 mm, mostly the lab's in-water pinhole behind the flat
/// port (5.3 mm alone) and the calibration error (3.2 mm alone).
#[test]
fn profiles_quick_the_realistic_camera_costs_millimetres_the_ideal_does_not() {
    let (dir, s) = run_quick(Experiment::Profiles);
    assert_files(
        &dir,
        &[
            "summary.json",
            "frames.csv",
            "profiles-recall.png",
            "profiles-position.png",
        ],
    );
    let r = &s;
    assert_eq!(num(&r["seeds"]), 3.0, "{r}");
    let c = &r["conditions"]["c0.50_r1"];
    let (ideal, real) = (&c["ideal"], &c["realistic"]);
    assert_eq!(num(&ideal["recall"]["mean"]), 1.0, "{ideal}");
    // An interval over three seeds, and it holds the mean.
    let ci = ideal["median_position_mm"]["ci95"]
        .as_array()
        .expect("interval over seeds");
    let mean = num(&ideal["median_position_mm"]["mean"]);
    assert!(num(&ci[0]) <= mean && mean <= num(&ci[1]), "{ideal}");
    // 0.05 mm measured: a tenth of a millimetre leaves room for three seeds.
    assert!(mean < 0.5, "ideal {mean} mm");
    let real_mm = num(&real["median_position_mm"]["mean"]);
    // The port alone costs millimetres at 1 m (refraction experiment: 3.5 mm).
    assert!(real_mm > 1.0 && real_mm < 50.0, "realistic {real_mm} mm");
    assert!(
        num(&real["position_ratio_to_ideal"]["mean"]) > 5.0,
        "{real}"
    );
    // Motion blur alone integrates several sub-frames over the exposure.
    let blur = &r["each_effect_alone"]["profiles"]["motion-blur"];
    assert!(num(&blur["sub_frames_mean"]) > 1.0, "{blur}");
    assert_eq!(
        num(&r["each_effect_alone"]["profiles"]["ideal"]["sub_frames_mean"]),
        1.0
    );
}
