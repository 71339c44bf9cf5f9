//! Per-corner residuals and pose errors of shoal's detector against the true
//! projections, on the accuracy test's frames (paper §6.2 set-up: 100 mm
//! enhanced marker at 610 mm, yaw 30°, ±2 mm / ±0.3° jitter), through a
//! restoration, for several detector settings on the same frames. Separates
//! bias (mean corner error over frames) from noise (its spread).
//!
//! `cargo run --release -p shoal-node --example detect_residuals -- [c_per_m] [frames] [none|hoirm] [noiseless]`
//! (`edge-model-raw`: detected on the restoration, fitted on the raw frame, the node's default).
//! (`SHOAL_PROBE_DIST=2.25 SHOAL_PROBE_YAW=0` for another distance or yaw;
//! `SHOAL_PROBE_WATER_FILE=configs/water-calibrated.toml` for another water file).

use rand::{Rng, SeedableRng};
use shoal_node::detect::{DetectParams, FitPattern, Refinement, ShoalDetector};
use shoal_node::pose::estimate_pose;
use shoal_node::restore::{restorer, Method, RestoreParams};
use shoal_proto::{camera::CameraModel, geometry::Pose, marker::CodeSet};
use shoal_sim_bridge::render::{facing_camera, Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;

const SIDE_M: f64 = 0.1;

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn errors(est: &Pose, truth: &Pose) -> (f64, f64) {
    let d = (est.translation.vector - truth.translation.vector).norm() * 1e3;
    let a = (est.rotation * truth.rotation.inverse())
        .angle()
        .to_degrees();
    (d, a)
}

struct Stats {
    label: String,
    dist: Vec<f64>,
    ang: Vec<f64>,
    /// Per corner id: sum of errors, sum of squares, count.
    corner: [([f64; 2], [f64; 2], usize); 12],
    missed: usize,
    ms: f64,
}

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    let c: f64 = a.get(1).map_or(Ok(0.126), |s| s.parse())?;
    let frames: usize = a.get(2).map_or(Ok(20), |s| s.parse())?;
    let method = match a.get(3).map_or("hoirm", |s| s.as_str()) {
        "none" => Method::None,
        _ => Method::Hoirm,
    };
    let noiseless = a.get(4).is_some_and(|s| s == "noiseless");
    // Distance (m) and platform yaw (deg) other than the accuracy test's 0.61 / 30.
    let dist_m: f64 = std::env::var("SHOAL_PROBE_DIST").map_or(Ok(0.61), |s| s.parse())?;
    let yaw_deg: f64 = std::env::var("SHOAL_PROBE_YAW").map_or(Ok(30.0), |s| s.parse())?;
    // Another code set on the same footprint (e.g. `aruco4x4_50`), read by shoal's detector.
    let codes: CodeSet =
        std::env::var("SHOAL_PROBE_CODES").map_or(Ok(CodeSet::Shoal), |s| s.parse())?;
    let cam = CameraModel::vehicle_1440();
    // `SHOAL_PROBE_WATER_FILE=configs/water-calibrated.toml`: presets and knobs from a file.
    let mut water = match std::env::var("SHOAL_PROBE_WATER_FILE") {
        Ok(path) => {
            shoal_sim_bridge::water::WaterPresets::load(std::path::Path::new(&path))?.get(c)?
        }
        Err(_) => WaterParams::preset(c),
    };
    if noiseless {
        water = water.noiseless();
    }
    // Switch parts of the water model off to attribute a bias (e.g. `vig0,fs0,bs0`).
    for part in std::env::var("SHOAL_PROBE_WATER")
        .unwrap_or_default()
        .split(',')
    {
        match part {
            "vig0" => water.vignetting = 0.0,
            "fs0" => water.forward_scatter = 0.0,
            "bs0" => water.backscatter_inf = 0.0,
            _ => {}
        }
    }
    let variants: Vec<(String, DetectParams)> = vec![
        ("edge-model".into(), DetectParams::default()),
        (
            "edge-model-raw".into(),
            DetectParams {
                fit_pattern: FitPattern::Never,
                ..DetectParams::default()
            },
        ),
        (
            "pattern-auto-raw".into(),
            DetectParams {
                lens: Some(CameraModel::vehicle_1440()),
                ..DetectParams::default()
            },
        ),
        (
            "pattern-always-raw".into(),
            DetectParams {
                fit_pattern: FitPattern::Always,
                lens: Some(CameraModel::vehicle_1440()),
                ..DetectParams::default()
            },
        ),
        (
            "edge-lines".into(),
            DetectParams {
                refinement: Refinement::EdgeLines,
                ..DetectParams::default()
            },
        ),
        (
            "corner-subpix".into(),
            DetectParams {
                refinement: Refinement::CornerSubPix,
                ..DetectParams::default()
            },
        ),
    ];
    let mut dets: Vec<ShoalDetector> = variants
        .iter()
        .map(|(_, p)| ShoalDetector::new(codes, p.clone()))
        .collect();
    let mut stats: Vec<Stats> = variants
        .iter()
        .map(|(l, _)| Stats {
            label: l.clone(),
            dist: vec![],
            ang: vec![],
            corner: [([0.0; 2], [0.0; 2], 0); 12],
            missed: 0,
            ms: 0.0,
        })
        .collect();
    let mut renderer = Renderer::new();
    let mut rest = restorer(method, &RestoreParams::default());
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let j = 0.3f64.to_radians();
    for k in 0..frames {
        let truth = facing_camera(
            [
                rng.gen_range(-0.002..0.002),
                rng.gen_range(-0.002..0.002),
                dist_m + rng.gen_range(-0.002..0.002),
            ],
            [
                rng.gen_range(-j..j),
                yaw_deg.to_radians() + rng.gen_range(-j..j),
                rng.gen_range(-j..j),
            ],
        );
        let scene = Scene::single_marker(codes, 17, SIDE_M, truth);
        let out = renderer.render(
            &cam,
            &Pose::identity(),
            &scene,
            &water,
            k as f64 * 0.1,
            rng.gen(),
        )?;
        let mat = shoal_node::mat::gray_as_mat(&out.image)?.clone_pointee();
        let restored = rest.restore(&mat, (k as u64) * 100_000_000)?.image;
        let true_px: Vec<[f64; 2]> = codes
            .corners_3d(SIDE_M)
            .iter()
            .map(|p| {
                let q = cam.project(&(truth * p)).expect("in front");
                [q.x, q.y]
            })
            .collect();
        for (det, st) in dets.iter_mut().zip(stats.iter_mut()) {
            let t0 = std::time::Instant::now();
            let found = if st.label.ends_with("-raw") {
                det.detect_with_raw_fit(&restored, &mat)?
            } else {
                det.detect_in(&restored)?
            };
            st.ms += t0.elapsed().as_secs_f64() * 1e3;
            let Some(d) = found
                .iter()
                .filter(|d| d.id == 17)
                .max_by_key(|d| d.corners_px.len())
            else {
                st.missed += 1;
                continue;
            };
            if std::env::var("SHOAL_PROBE_FRAMES").is_ok() {
                let ex: Vec<String> = d
                    .corner_ids
                    .iter()
                    .enumerate()
                    .map(|(i, &cid)| {
                        format!("{:+.2}", d.corners_px[i][0] - true_px[cid as usize][0])
                    })
                    .collect();
                println!("{} frame {k} x errors {}", st.label, ex.join(" "));
            }
            for (i, &cid) in d.corner_ids.iter().enumerate() {
                let t = true_px[cid as usize];
                let e = [d.corners_px[i][0] - t[0], d.corners_px[i][1] - t[1]];
                let s = &mut st.corner[cid as usize];
                for ax in 0..2 {
                    s.0[ax] += e[ax];
                    s.1[ax] += e[ax] * e[ax];
                }
                s.2 += 1;
            }
            // `SHOAL_PROBE_SQUARES=0,1`: the pose from those squares' corners only
            // (0 outer frame edge, 1 frame inner edge, 2 code square).
            let keep: Vec<bool> = match std::env::var("SHOAL_PROBE_SQUARES") {
                Ok(s) => {
                    let sq: Vec<u8> = s.split(',').filter_map(|v| v.parse().ok()).collect();
                    d.corner_ids.iter().map(|c| sq.contains(&(c / 4))).collect()
                }
                Err(_) => vec![true; d.corner_ids.len()],
            };
            let obj: Vec<_> = d
                .object_points(SIDE_M)
                .into_iter()
                .zip(&keep)
                .filter_map(|(p, &k)| k.then_some(p))
                .collect();
            let img: Vec<[f64; 2]> = d
                .corners_px
                .iter()
                .zip(&keep)
                .filter_map(|(p, &k)| k.then_some(*p))
                .collect();
            match estimate_pose(&cam, &obj, &img, None) {
                Ok(sol) => {
                    let (dd, aa) = errors(&sol.best.camera_from_marker, &truth);
                    st.dist.push(dd);
                    st.ang.push(aa);
                }
                Err(_) => st.missed += 1,
            }
        }
    }
    println!(
        "water {c} /m, {frames} frames, {method:?}{}",
        if noiseless { ", noiseless" } else { "" }
    );
    for st in &mut stats {
        println!(
            "{:>16}: median dist {:.3} mm, angle {:.4} deg, missed {}, flips (> 3°) {}, detect {:.1} ms/frame",
            st.label,
            median(&mut st.dist),
            median(&mut st.ang),
            st.missed,
            st.ang.iter().filter(|&&a| a > 3.0).count(),
            st.ms / frames as f64
        );
        for (cid, (s, s2, n)) in st.corner.iter().enumerate() {
            if *n == 0 {
                continue;
            }
            let nf = *n as f64;
            let mean = [s[0] / nf, s[1] / nf];
            let sd = [
                (s2[0] / nf - mean[0] * mean[0]).max(0.0).sqrt(),
                (s2[1] / nf - mean[1] * mean[1]).max(0.0).sqrt(),
            ];
            println!(
                "    corner {cid:2}: n {n:3} bias ({:+.3}, {:+.3}) px  sd ({:.3}, {:.3}) px",
                mean[0], mean[1], sd[0], sd[1]
            );
        }
    }
    Ok(())
}
