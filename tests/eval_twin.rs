//! `shoal eval real-twin` on a recording made here with known geometry and
//! known camera conditions (the real recordings live outside the
//! repository, docs/real-data.md): the twin must find the camera in every
//! frame, place the tags where they were rendered (not where a wrong survey
//! says), match the recording's contrast, light level and edge blur, and
//! predict the detectors' recall within the factor of 2 the issue asks for.

use nalgebra::{UnitQuaternion, Vector3};
use opencv::core::Size;
use opencv::prelude::*;
use opencv::videoio::VideoWriter;
use serde_json::{json, Value};
use shoal::eval::{self, EvalOptions, Experiment};
use shoal_proto::camera::CameraModel;
use shoal_proto::geometry::Pose;
use shoal_proto::marker::CodeSet;
use shoal_sim_bridge::profile::CameraProfile;
use shoal_sim_bridge::render::motion::{RigidMotion, Twist};
use shoal_sim_bridge::render::realistic::render_profiled;
use shoal_sim_bridge::render::{Renderer, Scene, SceneMarker};
use shoal_sim_bridge::water::WaterPresets;
use std::path::PathBuf;

const SIDE_M: f64 = 0.15;
const FRAMES: usize = 12;
/// Where the tags are (the floor, z = 0).
const TAGS: [(u32, [f64; 2]); 5] = [
    (0, [0.0, 0.0]),
    (1, [0.5, 0.0]),
    (2, [1.0, 0.05]),
    (3, [0.0, 0.5]),
    (4, [0.55, 0.5]),
];
/// The survey's mistake: tag 3 written down 10 cm off.
const SURVEY_ERROR_M: f64 = 0.1;
/// The as-built layout's shape from the frames: per-tag PnP at ~1.4 m with
/// 64 px tags through this camera (port, calibration error) measures pair
/// distances to a few per cent, and the survey's error still pulls the
/// frames' alignment a little (3.1 % on tag 3's worst pair with two rounds
/// of re-alignment, measured); the survey's error itself, which a twin
/// placing the tags where the survey says would copy, moves tag 3's pairs
/// by up to 20 %.
const AS_BUILT_TOL: f64 = 0.05;

fn camera() -> CameraModel {
    CameraModel {
        width: 640,
        height: 480,
        fx: 600.0,
        fy: 600.0,
        cx: 319.5,
        cy: 239.5,
        distortion: shoal_proto::Distortion::NONE,
    }
}

/// The camera over the floor, looking down, drifting along x and turning
/// slowly (`DRIFT`, over the whole recording).
fn layout_from_camera(k: usize) -> Pose {
    let t = k as f64 / (FRAMES - 1) as f64;
    Pose::from_parts(
        Vector3::new(0.4 + DRIFT.0 * t, 0.25, 1.4).into(),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), DRIFT.1 * t)
            * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
    )
}

/// Metres along x and radians about the vertical over the recording.
const DRIFT: (f64, f64) = (0.2, 0.15);

/// The camera's motion during a frame (in its own frame: looking down, the
/// layout's x is the camera's x, its z the camera's −z).
fn twist(k: usize) -> Twist {
    let seconds = (FRAMES - 1) as f64 * 0.1;
    let yaw = DRIFT.1 * k as f64 / (FRAMES - 1) as f64;
    Twist {
        linear_mps: Vector3::new(yaw.cos(), yaw.sin(), 0.0) * DRIFT.0 / seconds,
        angular_radps: Vector3::new(0.0, 0.0, -DRIFT.1 / seconds),
    }
}

fn out_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("shoal-eval-twin-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

/// The "recording": a realistic camera with a blur, exposure and veil the
/// twin does not know, as an MJPG video.
fn make_recording(root: &std::path::Path) {
    let dir = root.join("floor");
    std::fs::create_dir_all(&dir).unwrap();
    let scene = Scene {
        markers: TAGS
            .iter()
            .map(|(id, [x, y])| SceneMarker {
                codes: CodeSet::AprilTag16h5,
                id: *id,
                side_m: SIDE_M,
                world_from_marker: Pose::from_parts(
                    Vector3::new(*x, *y, 0.0).into(),
                    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.3 * *id as f64),
                ),
                owner: 0,
            })
            .collect(),
        hulls: Vec::new(),
        up_world: Vector3::z(),
    };
    let mut profile = CameraProfile::realistic().with_seed(9);
    profile.params.psf.fwhm_px = [2.0, 2.4];
    profile.params.exposure.target_mean = 0.08;
    let presets = WaterPresets::builtin();
    let mut water = presets.get(presets.min_c()).unwrap();
    water.backscatter_inf *= 0.4;
    let path = dir.join("floor.avi");
    let fourcc = VideoWriter::fourcc('M', 'J', 'P', 'G').unwrap();
    let mut writer = VideoWriter::new(
        path.to_str().unwrap(),
        fourcc,
        10.0,
        Size::new(640, 480),
        false,
    )
    .unwrap();
    assert!(writer.is_opened().unwrap(), "an MJPG writer");
    let mut renderer = Renderer::new();
    for k in 0..FRAMES {
        let view = RigidMotion {
            world_from_camera: layout_from_camera(k),
            scene: scene.clone(),
            camera: twist(k),
            targets: Twist::default(),
        };
        let f = render_profiled(
            &mut renderer,
            &profile,
            &camera(),
            None,
            &view,
            &water,
            k as f64 * 0.1,
            100 + k as u64,
        )
        .unwrap();
        let mat = shoal_node::mat::gray_to_mat(&f.output.image).unwrap();
        writer.write(&mat).unwrap();
    }
    writer.release().unwrap();
    let centres: serde_json::Map<String, Value> = TAGS
        .iter()
        .map(|(id, [x, y])| {
            let x = if *id == 3 { x + SURVEY_ERROR_M } else { *x };
            (id.to_string(), json!([x, y, 0.0]))
        })
        .collect();
    let manifest = json!({
        "name": "floor", "underwater": true, "codes": "apriltag16h5", "side_m": SIDE_M,
        "camera": {"width": 640, "height": 480, "fx": 600.0, "fy": 600.0, "cx": 319.5, "cy": 239.5},
        "video": "floor.avi", "codec": "jpeg",
        "splits": {"dev": [0, FRAMES / 2], "holdout": [FRAMES / 2, FRAMES]},
        "truth": {"layout": {"centres_m": centres}}
    });
    std::fs::write(
        dir.join("eval.json"),
        serde_json::to_string_pretty(&manifest).unwrap(),
    )
    .unwrap();
}

#[test]
fn the_twin_of_a_known_recording_finds_its_geometry_and_conditions_and_predicts_its_recall() {
    let data = out_dir("data");
    make_recording(&data);
    let out = out_dir("out");
    let opts = EvalOptions {
        progress: false,
        quick: true,
        data: Some(data.clone()),
        ..EvalOptions::new(&out)
    };
    let summary = eval::run(Experiment::RealTwin, &opts).unwrap();
    let r = &summary["results"]["floor"];
    assert_eq!(r["frames_posed"], FRAMES, "{r:#}");
    assert_eq!(r["frames_without_pose"], 0, "{r:#}");
    // The as-built layout is in the survey's frame, aligned to all its tags
    // by a similarity (tag 3's survey error shrinks it), so its shape is
    // what is checked: every pair's distance over the rendered one is the
    // same to AS_BUILT_TOL, where the survey's are up to 20 % apart.
    let built = |id: u32| -> Vector3<f64> {
        let c = &r["tags_as_built"][id.to_string()]["centre_m"];
        let v: Vec<f64> = c
            .as_array()
            .expect("a centre")
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        Vector3::new(v[0], v[1], v[2])
    };
    let mut ratios = Vec::new();
    for (i, (a, pa)) in TAGS.iter().enumerate() {
        for (b, pb) in &TAGS[i + 1..] {
            let truth = ((pa[0] - pb[0]).powi(2) + (pa[1] - pb[1]).powi(2)).sqrt();
            ratios.push(((a, b), (built(*a) - built(*b)).norm() / truth));
        }
    }
    let mean = ratios.iter().map(|r| r.1).sum::<f64>() / ratios.len() as f64;
    // Its scale is the survey's: aligned to it, not left to drift.
    assert!((mean - 1.0).abs() < 0.05, "as-built scale {mean:.3}: {r:#}");
    for ((a, b), q) in &ratios {
        assert!(
            (q / mean - 1.0).abs() < AS_BUILT_TOL,
            "tags {a}-{b}: as built {q:.3} of the rendered distance, the pairs' mean {mean:.3}: {r:#}"
        );
    }
    let looks = &r["looks"];
    let (real, sim) = (&looks["real"], &looks["sim"]);
    let f = |v: &Value, k: &str| v[k].as_f64().unwrap();
    assert!(
        (f(sim, "contrast") - f(real, "contrast")).abs() < 0.05,
        "{looks}"
    );
    assert!(
        (f(sim, "light") / f(real, "light") - 1.0).abs() < 0.15,
        "{looks}"
    );
    assert!(
        (f(sim, "sigma_px") / f(real, "sigma_px") - 1.0).abs() < 0.2,
        "{looks}"
    );
    for split in ["dev", "holdout"] {
        for method in ["shoal", "apriltag3-d1"] {
            let recall = &r["splits"][split]["methods"][method]["recall"];
            assert_eq!(recall["within_factor"], true, "{split} {method}: {recall}");
            assert!(
                recall["real"].as_f64().unwrap() > 0.9,
                "{split} {method}: {recall}"
            );
        }
    }
    for file in [
        "twin.csv",
        "twin-reads.csv",
        "twin.md",
        "twin-recall.png",
        "twin-jitter_mm.png",
        "twin-distance_iqr.png",
        "twin-floor-frames.png",
        "summary.json",
    ] {
        assert!(out.join(file).is_file(), "{file} written");
    }
    // Every simulated read is written, with its pose: shoal's on both splits.
    let reads = std::fs::read_to_string(out.join("twin-reads.csv")).unwrap();
    for split in ["dev", "holdout"] {
        let n = reads
            .lines()
            .filter(|l| l.starts_with(&format!("floor,{split},")) && l.contains(",shoal,"))
            .filter(|l| {
                l.split(',')
                    .nth(7)
                    .is_some_and(|tx| tx.parse::<f64>().is_ok())
            })
            .count();
        assert!(n > 0, "{split}: no posed shoal read in twin-reads.csv");
    }
    let _ = std::fs::remove_dir_all(&data);
    let _ = std::fs::remove_dir_all(&out);
}
