//! Issue #7 probe: HOIRM + shoal's detector on the frames of `shoal eval
//! detection` (same camera, marker, 600 mm with ±5 mm / ±5° jitter, seed 1,
//! same per-frame seeds), for a water presets file, with per-frame
//! diagnostics of what HOIRM estimated. Faster to iterate on than the CLI
//! (HOIRM only; raw frames cached as PNG under `SHOAL_FRAME_CACHE`).
//!
//! `cargo run --release -p shoal-node --example restore_issue7 -- configs/water-calibrated.toml 20 [c ...]`
//!
//! Environment overrides of [`RestoreParams`] fields (for tuning):
//! `SHOAL_<FIELD>=<value>` for the numeric fields listed in `overrides`.

use opencv::core::{Mat, Vector};
use opencv::imgcodecs;
use opencv::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use shoal_node::detect::{DetectParams, ShoalDetector};
use shoal_node::pose::estimate_pose;
use shoal_node::restore::{Hoirm, RestoreParams};
use shoal_proto::geometry::Pose;
use shoal_proto::{CameraModel, CodeSet};
use shoal_sim_bridge::render::{facing_camera, Renderer, Scene};
use shoal_sim_bridge::water::WaterPresets;
use std::path::{Path, PathBuf};

const WATERS: [f64; 6] = [5.16, 6.12, 8.22, 10.13, 12.20, 14.20];
const ID: u32 = 17;

/// As `src/eval/scene.rs`.
fn frame_rng(seed: u64, condition: u64, frame: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (condition << 32) ^ frame)
}

fn jittered_pose(
    distance_m: f64,
    yaw_rad: f64,
    jitter_m: f64,
    jitter_rad: f64,
    rng: &mut ChaCha8Rng,
) -> Pose {
    let mut j = |a: f64| rng.gen_range(-a..=a);
    let xyz = [j(jitter_m), j(jitter_m), distance_m + j(jitter_m)];
    let rpy = [j(jitter_rad), yaw_rad + j(jitter_rad), j(jitter_rad)];
    facing_camera(xyz, rpy)
}

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn overrides(p: &mut RestoreParams) {
    let get = |name: &str| -> Option<f64> {
        std::env::var(format!("SHOAL_{}", name.to_uppercase()))
            .ok()
            .and_then(|v| v.parse().ok())
    };
    macro_rules! f64_field {
        ($($f:ident),*) => {$(
            if let Some(v) = get(stringify!($f)) { p.$f = v; }
        )*};
    }
    f64_field!(
        psf_px_per_unit,
        nsr_gain,
        nsr_min,
        nsr_max,
        clahe_clip_base,
        clahe_clip_per_c,
        stretch_max_gain,
        deconv_min_c_per_m,
        edge_snr_target,
        roi_noise_k,
        denoise_edge_snr,
        denoise_min_sigma_px,
        denoise_max_sigma_px,
        clahe_contrast_target,
        roi_min_gradient,
        roi_background_k,
        roi_hysteresis
    );
    if let Some(v) = get("clahe_tile_px") {
        p.clahe_tile_px = v as i32;
    }
    if let Some(v) = get("c_per_m") {
        p.c_per_m = Some(v);
    }
    if let Some(v) = get("psf_sigma_from_image") {
        p.psf_sigma_from_image = v != 0.0;
    }
    if let Some(v) = get("deconv_when_denoised") {
        p.deconv_when_denoised = v != 0.0;
    }
    if let Some(v) = get("denoised_deconv_level") {
        p.denoised_deconv_level = v as u32;
    }
    if let Some(v) = get("roi_only") {
        p.roi_only = v != 0.0;
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let presets = match args.get(1).filter(|a| *a != "-") {
        Some(path) => WaterPresets::load(Path::new(path)).expect("water presets"),
        None => WaterPresets::builtin(),
    };
    let frames: usize = args.get(2).and_then(|a| a.parse().ok()).unwrap_or(10);
    let waters: Vec<f64> = if args.len() > 3 {
        args[3..].iter().filter_map(|a| a.parse().ok()).collect()
    } else {
        WATERS.to_vec()
    };
    let tag = args
        .get(1)
        .map(|a| {
            Path::new(a)
                .file_stem()
                .map_or("x".into(), |s| s.to_string_lossy().into_owned())
        })
        .unwrap_or_else(|| "shipped".into());
    let cache: Option<PathBuf> = std::env::var("SHOAL_FRAME_CACHE").ok().map(PathBuf::from);
    let save: Option<PathBuf> = std::env::var("SHOAL_SAVE").ok().map(PathBuf::from);
    let verbose = std::env::var("SHOAL_VERBOSE").is_ok();
    let save_frame: usize = std::env::var("SHOAL_SAVE_FRAME")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    // `SHOAL_SCENE=accuracy`: the accuracy experiment's 610 mm, yaw 30°, ±2 mm / ±0.3°.
    let accuracy_scene = std::env::var("SHOAL_SCENE").is_ok_and(|v| v == "accuracy");
    let (distance_m, yaw_rad, jitter_m, jitter_rad) = if accuracy_scene {
        (0.610, 30f64.to_radians(), 0.002, 0.3f64.to_radians())
    } else {
        (0.600, 0.0, 0.005, 5f64.to_radians())
    };
    let tag = if accuracy_scene {
        format!("{tag}-acc")
    } else {
        tag
    };
    let mut params = RestoreParams::default();
    overrides(&mut params);
    let cam = CameraModel::vehicle_1440();
    let mut renderer = Renderer::new();
    let mut detector = ShoalDetector::new(CodeSet::Shoal, DetectParams::default());
    let all_waters = WATERS;
    for &c in &waters {
        let wi = all_waters
            .iter()
            .position(|w| (w - c).abs() < 1e-9)
            .unwrap_or(99);
        let water = presets.get(c).expect("water");
        let mut hoirm = Hoirm::new(params.clone());
        let mut ok = 0;
        let (mut dist_err, mut ang_err) = (Vec::new(), Vec::new());
        let mut line = String::new();
        for k in 0..frames {
            let mut rng = frame_rng(1, 1000 + wi as u64, k as u64);
            let truth = jittered_pose(distance_m, yaw_rad, jitter_m, jitter_rad, &mut rng);
            let noise_seed: u64 = rng.gen();
            let time_s = k as f64 * 0.1;
            let cached = cache
                .as_ref()
                .map(|d| d.join(format!("{tag}_c{c:.2}_{k:03}.png")));
            let raw = match cached.as_ref().filter(|p| p.exists()) {
                Some(p) => imgcodecs::imread(&p.display().to_string(), imgcodecs::IMREAD_GRAYSCALE)
                    .unwrap(),
                None => {
                    let scene = Scene::single_marker(CodeSet::Shoal, ID, 0.100, truth);
                    let out = renderer
                        .render(&cam, &Pose::identity(), &scene, &water, time_s, noise_seed)
                        .unwrap();
                    let g = out.image;
                    let m = Mat::new_rows_cols_with_data(g.height as i32, g.width as i32, &g.data)
                        .unwrap()
                        .try_clone()
                        .unwrap();
                    if let Some(p) = &cached {
                        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
                        imgcodecs::imwrite(&p.display().to_string(), &m, &Vector::new()).unwrap();
                    }
                    m
                }
            };
            let (r, fp) = hoirm
                .restore_with_params(&raw, (time_s * 1e9) as u64)
                .unwrap();
            if let (Some(d), true) = (&save, k == save_frame) {
                std::fs::create_dir_all(d).unwrap();
                let name = d.join(format!("{tag}_c{c:.2}_hoirm.png"));
                imgcodecs::imwrite(&name.display().to_string(), &r.image, &Vector::new()).unwrap();
            }
            let dets = detector.detect_in(&r.image).unwrap();
            let found = dets.iter().any(|d| d.id == ID);
            // Pose error of the detection with the most corners (as the evals).
            if let Some(d) = dets
                .iter()
                .filter(|d| d.id == ID)
                .max_by_key(|d| d.corners_px.len())
            {
                if let Ok(sol) = estimate_pose(&cam, &d.object_points(0.100), &d.corners_px, None) {
                    let est = sol.best.camera_from_marker;
                    dist_err.push((est.translation.vector - truth.translation.vector).norm() * 1e3);
                    ang_err.push(
                        (est.rotation * truth.rotation.inverse())
                            .angle()
                            .to_degrees(),
                    );
                }
            }
            ok += usize::from(found);
            line.push(if found { '+' } else { '.' });
            if verbose || k == 0 {
                println!(
                    "  c {c:5.2} frame {k:3}: est c {:5.2} noise {:.2} ΔI {:5.2} B {:5.1} gain {:.2} clip {:.1} denoise σ {:.2} psf p {:.2} σ {:.2} measured {:?} rois {:?} found {found} ({} dets)",
                    fp.water.c_per_m,
                    fp.water.noise_sigma,
                    fp.water.local_contrast,
                    fp.water.backscatter,
                    fp.gain,
                    fp.clahe_clip,
                    fp.denoise_sigma_px,
                    fp.psf.p,
                    fp.psf.sigma_px,
                    fp.measured_psf_sigma_px,
                    r.rois,
                    dets.len()
                );
            }
        }
        println!(
            "c {c:5.2}: success {:.2} ({ok}/{frames}) {line}  median error {:.3} mm {:.3}°",
            ok as f64 / frames as f64,
            median(&mut dist_err),
            median(&mut ang_err)
        );
    }
}
