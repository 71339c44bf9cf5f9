//! `shoal eval probe residuals`: per-corner residuals and pose errors of
//! shoal's detector against the true projections, on the accuracy test's
//! frames (paper §6.2 set-up: 100 mm enhanced marker at 610 mm, yaw 30°,
//! ±2 mm / ±0.3° jitter), through a restoration, for several detector
//! settings on the same frames. Separates bias (mean corner error over
//! frames) from noise (its spread). `edge-model-raw` (detected on the
//! restoration, fitted on the raw frame) is the node's default.
//!
//! `--frames 1 --per-frame` prints the corner errors of a single frame.

use super::{median, water};
use crate::eval::EvalError;
use rand::{Rng, SeedableRng};
use shoal_node::detect::{DetectParams, Detection, FitPattern, Refinement, ShoalDetector};
use shoal_node::pose::estimate_pose;
use shoal_node::restore::{restorer, Method, RestoreParams};
use shoal_proto::{camera::CameraModel, geometry::Pose, marker::CodeSet};
use shoal_sim_bridge::render::{facing_camera, Renderer, Scene};
use std::path::PathBuf;

const SIDE_M: f64 = 0.1;
const ID: u32 = 17;

/// Parts of the water model that can be switched off to attribute a bias.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum WaterPart {
    /// Vignetting.
    Vignetting,
    /// Forward scatter.
    ForwardScatter,
    /// Backscatter (the veil).
    Backscatter,
}

#[derive(Debug, clap::Args)]
pub struct ResidualsArgs {
    /// Water attenuation coefficient (1/m).
    #[arg(long, default_value_t = 0.126)]
    pub c: f64,
    /// Frames.
    #[arg(long, default_value_t = 20)]
    pub frames: usize,
    /// Restoration before detection: none, clahe, dcp, udcp, hoirm.
    #[arg(long, default_value = "hoirm")]
    pub restore: String,
    /// Render without sensor noise.
    #[arg(long)]
    pub noiseless: bool,
    /// Marker distance (m).
    #[arg(long, default_value_t = 0.61)]
    pub distance_m: f64,
    /// Platform yaw (deg).
    #[arg(long, default_value_t = 30.0)]
    pub yaw_deg: f64,
    /// Lateral offset of the marker (m), e.g. -0.31 to cut it at the frame's left border.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub x_m: f64,
    /// Code set of the marker on the same footprint (e.g. aruco4x4_50), read by shoal's detector.
    #[arg(long, default_value = "shoal")]
    pub codes: String,
    /// Water presets file (configs/water.toml format) instead of the built-in presets.
    #[arg(long)]
    pub water: Option<PathBuf>,
    /// Switch parts of the water model off (comma-separated).
    #[arg(long, value_delimiter = ',')]
    pub water_off: Vec<WaterPart>,
    /// Print every frame's x errors per corner.
    #[arg(long)]
    pub per_frame: bool,
    /// Pose from these squares' corners only (0 outer frame edge, 1 frame inner edge, 2 code square).
    #[arg(long, value_delimiter = ',')]
    pub squares: Vec<u8>,
}

struct Stats {
    label: &'static str,
    dist: Vec<f64>,
    ang: Vec<f64>,
    /// Per corner id: sum of errors, sum of squares, count.
    corner: [([f64; 2], [f64; 2], usize); 12],
    missed: usize,
    ms: f64,
}

impl Stats {
    /// Add detection `d` of frame `k`: corner residuals against `true_px`,
    /// and the pose error against `truth` from the corners of `a.squares`.
    fn add(
        &mut self,
        a: &ResidualsArgs,
        k: usize,
        cam: &CameraModel,
        d: &Detection,
        true_px: &[Option<[f64; 2]>],
        truth: &Pose,
    ) {
        let mut line = Vec::new();
        for (i, &cid) in d.corner_ids.iter().enumerate() {
            let Some(t) = true_px.get(cid as usize).copied().flatten() else {
                continue;
            };
            let e = [d.corners_px[i][0] - t[0], d.corners_px[i][1] - t[1]];
            line.push(format!("{cid}:({:+.3}, {:+.3})", e[0], e[1]));
            let s = &mut self.corner[cid as usize % 12];
            for ax in 0..2 {
                s.0[ax] += e[ax];
                s.1[ax] += e[ax] * e[ax];
            }
            s.2 += 1;
        }
        if a.per_frame {
            crate::outln!("{} frame {k} errors (px) {}", self.label, line.join(" "));
        }
        let keep: Vec<bool> = d
            .corner_ids
            .iter()
            .map(|c| a.squares.is_empty() || a.squares.contains(&(c / 4)))
            .collect();
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
        match estimate_pose(cam, &obj, &img, None) {
            Ok(sol) => {
                let (dd, aa) = errors(&sol.best.camera_from_marker, truth);
                self.dist.push(dd);
                self.ang.push(aa);
            }
            Err(_) => self.missed += 1,
        }
    }
}

fn errors(est: &Pose, truth: &Pose) -> (f64, f64) {
    let d = (est.translation.vector - truth.translation.vector).norm() * 1e3;
    let a = (est.rotation * truth.rotation.inverse())
        .angle()
        .to_degrees();
    (d, a)
}

/// The detector variants compared, by label (`-raw`: corners fitted on the raw frame).
fn variants() -> Vec<(&'static str, DetectParams)> {
    let lens = Some(CameraModel::vehicle_1440());
    vec![
        ("edge-model", DetectParams::default()),
        (
            "edge-model-raw",
            DetectParams {
                fit_pattern: FitPattern::Never,
                ..DetectParams::default()
            },
        ),
        (
            "pattern-auto-raw",
            DetectParams {
                lens,
                ..DetectParams::default()
            },
        ),
        (
            "pattern-always-raw",
            DetectParams {
                fit_pattern: FitPattern::Always,
                lens,
                ..DetectParams::default()
            },
        ),
        (
            "edge-lines",
            DetectParams {
                refinement: Refinement::EdgeLines,
                ..DetectParams::default()
            },
        ),
        (
            "corner-subpix",
            DetectParams {
                refinement: Refinement::CornerSubPix,
                ..DetectParams::default()
            },
        ),
    ]
}

/// Print each variant's pose errors and per-corner bias and spread.
fn report(a: &ResidualsArgs, method: Method, codes: CodeSet, stats: &mut [Stats]) {
    crate::outln!(
        "water {} /m, {} frames, {method}{}, {codes} at {} m, yaw {}°",
        a.c,
        a.frames,
        if a.noiseless { ", noiseless" } else { "" },
        a.distance_m,
        a.yaw_deg
    );
    for st in stats.iter_mut() {
        crate::outln!(
            "{:>18}: median dist {:.3} mm, angle {:.4} deg, missed {}, flips (> 3°) {}, detect {:.1} ms/frame",
            st.label,
            median(&mut st.dist),
            median(&mut st.ang),
            st.missed,
            st.ang.iter().filter(|&&a| a > 3.0).count(),
            st.ms / a.frames.max(1) as f64
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
            crate::outln!(
                "    corner {cid:2}: n {n:3} bias ({:+.3}, {:+.3}) px  sd ({:.3}, {:.3}) px",
                mean[0],
                mean[1],
                sd[0],
                sd[1]
            );
        }
    }
}

pub fn run(a: &ResidualsArgs) -> Result<(), EvalError> {
    let method: Method = a.restore.parse()?;
    let codes: CodeSet = a
        .codes
        .parse()
        .map_err(|e| EvalError::Setup(format!("--codes: {e}")))?;
    let cam = CameraModel::vehicle_1440();
    let mut water = water(a.water.as_deref(), a.c)?;
    if a.noiseless {
        water = water.noiseless();
    }
    for part in &a.water_off {
        match part {
            WaterPart::Vignetting => water.vignetting = 0.0,
            WaterPart::ForwardScatter => water.forward_scatter = 0.0,
            WaterPart::Backscatter => water.backscatter_inf = 0.0,
        }
    }
    let variants = variants();
    let mut dets: Vec<ShoalDetector> = variants
        .iter()
        .map(|(_, p)| ShoalDetector::new(codes, p.clone()))
        .collect();
    let mut stats: Vec<Stats> = variants
        .iter()
        .map(|&(label, _)| Stats {
            label,
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
    for k in 0..a.frames {
        let truth = facing_camera(
            [
                a.x_m + rng.gen_range(-0.002..0.002),
                rng.gen_range(-0.002..0.002),
                a.distance_m + rng.gen_range(-0.002..0.002),
            ],
            [
                rng.gen_range(-j..j),
                a.yaw_deg.to_radians() + rng.gen_range(-j..j),
                rng.gen_range(-j..j),
            ],
        );
        let scene = Scene::single_marker(codes, ID, SIDE_M, truth);
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
        let true_px: Vec<Option<[f64; 2]>> = codes
            .corners_3d(SIDE_M)
            .iter()
            .map(|p| cam.project(&(truth * p)).map(|q| [q.x, q.y]))
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
                .filter(|d| d.id == ID)
                .max_by_key(|d| d.corners_px.len())
            else {
                st.missed += 1;
                continue;
            };
            st.add(a, k, &cam, d, &true_px, &truth);
        }
    }
    report(a, method, codes, &mut stats);
    Ok(())
}
