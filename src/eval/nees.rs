//! `nees` (issue #16): is the covariance the node reports honest, in the
//! production configuration?
//!
//! The node's camera chain exactly as shipped ([`CameraPipeline`] with
//! [`PipelineParams::default`]: HOIRM, shoal's detector with the lens,
//! PnP with the corner noise it estimates itself, nothing given by the
//! test) reads rendered frames whose truth is known, per water preset and
//! per camera profile (`ideal`, `realistic`), over [`SEEDS`] seeds. Each
//! frame read gives the normalized estimation error squared of its best
//! hypothesis, `NEES = ξᵀ Σ⁻¹ ξ` with `truth = perturb(estimate, ξ)`, over
//! the 6-DoF pose and over the position alone (3-DoF).
//!
//! A consistent covariance gives a mean NEES of 6 (3), and over `N`
//! independent frames `N · mean` follows χ²(6N) (χ²(3N)): the *χ² band* is
//! the 95 % interval the mean must fall in. The mean's own 95 % intervals:
//! across seeds (Student's t over the per-seed means) and a bootstrap over
//! the frames. Planar flips (the best hypothesis more than
//! [`FLIP_DEG`] from the truth) are counted and also left out in a second
//! mean, since fusion resolves them with the alternative.
//!
//! Scenes as in [`super::profiles`]: the 100 mm enhanced marker at
//! 0.5–1.5 m, off the axis and turned, the camera drifting as a vehicle
//! holding formation; the node's calibration as there (the in-water pinhole
//! for `ideal`, a lab's calibration through the port, off by the
//! calibration error, for `realistic`).

use super::plot::{self, Grouped};
use super::profiles::{camera_from_marker, mean_ci, node_camera, scene_and_motion, POSITIVE};
use super::scene::{frame_rng, FRAME_INTERVAL_S, MARKER_ID, MARKER_SIDE_M};
use super::table::{cell, median, quantile, Csv};
use super::{water_key, EvalError, EvalOptions};
use nalgebra::{Matrix3, Vector3, Vector6};
use rand::{Rng, SeedableRng};
use serde_json::{json, Map, Value};
use shoal_node::pipeline::{CameraPipeline, PipelineParams};
use shoal_proto::config::{Camera, Fleet, HullSpec, Marker, Vehicle};
use shoal_proto::geometry::{difference, Cov6};
use shoal_proto::{CalibrationSigma, CameraModel, CodeSet, Pose};
use shoal_sim_bridge::profile::{CameraProfile, Effect};
use shoal_sim_bridge::render::realistic::render_profiled;
use shoal_sim_bridge::render::Renderer;
use std::sync::Arc;

/// Seeds per condition (issue #16: at least 5).
pub const SEEDS: u64 = 5;
/// Range of the marker, drawn uniformly per frame (m).
pub const RANGE_M: (f64, f64) = (0.5, 1.5);
/// Scales of the stated calibration σ at which every frame's NEES is also
/// computed (the fit of the scale picks among them).
pub const SCALES: [f64; 13] = [
    0.0, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0,
];
/// Waters whose frames fit the scale; the others are held out.
pub const FIT_WATERS: [f64; 3] = [0.126, 1.38, 5.16];
/// A best hypothesis further than this from the truth in rotation is a planar flip (°).
pub const FLIP_DEG: f64 = 3.0;
/// The waters of the quick run (CI): one the calibration scale is fitted on, one held out.
const QUICK_WATERS: [f64; 2] = [1.38, 3.92];
/// Bootstrap resamples of the mean.
const BOOTSTRAP: usize = 2000;

/// The observing vehicle and the one carrying the marker.
const OBSERVER: u32 = 1;
const TARGET: u32 = 2;

/// One frame's outcome.
#[derive(Debug, Clone)]
pub struct Row {
    pub profile: String,
    pub c_per_m: f64,
    pub seed: u64,
    pub frame: usize,
    pub range_m: f64,
    pub read: bool,
    pub nees6: Option<f64>,
    pub nees3: Option<f64>,
    pub position_mm: Option<f64>,
    pub rotation_deg: Option<f64>,
    /// Reprojection RMS of the best hypothesis (px).
    pub rms_px: Option<f64>,
    pub corners: usize,
    /// Side of the marker in the image (px, mean of its outer edges).
    pub side_px: Option<f64>,
    /// The marker's Michelson contrast on the raw frame.
    pub contrast: Option<f64>,
    /// The PSF family the frame was blurred with (`model` for the renderer's own).
    pub psf: String,
    /// The corners came from the whole-pattern fit (their covariance is
    /// then the fit's, correlated across corners).
    pub pattern_fit: bool,
    /// The error whitened by the corner-noise part of the covariance alone
    /// and by the calibration part alone are not separable; kept instead:
    /// the NEES with the calibration part scaled by each of [`SCALES`].
    pub nees6_scaled: Vec<f64>,
}

impl Row {
    fn held_out(&self) -> bool {
        !FIT_WATERS.iter().any(|c| (c - self.c_per_m).abs() < 1e-9)
    }

    fn flip(&self) -> bool {
        self.rotation_deg.is_some_and(|a| a > FLIP_DEG)
    }
}

/// A fleet of two vehicles for the node's pipeline: the observer's camera
/// `cam` at its body origin, the target's marker #[`MARKER_ID`] at its body
/// origin, so an observation is the camera-from-marker pose itself.
fn fleet_for(cam: &CameraModel, calibration_sigma: Option<CalibrationSigma>) -> Arc<Fleet> {
    let hull = HullSpec {
        diameter_m: 0.2,
        length_m: 1.0,
    };
    Arc::new(Fleet {
        name: "nees".into(),
        description: "one camera, one marker (shoal eval nees)".into(),
        reference_vehicle: OBSERVER,
        vehicles: vec![
            Vehicle {
                id: OBSERVER,
                name: "observer".into(),
                hull,
                markers: Vec::new(),
                cameras: vec![Camera {
                    index: 0,
                    name: "front".into(),
                    model: *cam,
                    body_from_camera: Pose::identity(),
                    port: None,
                    calibration_sigma,
                }],
            },
            Vehicle {
                id: TARGET,
                name: "target".into(),
                hull,
                markers: vec![Marker {
                    codes: CodeSet::Shoal,
                    id: MARKER_ID,
                    side_m: MARKER_SIDE_M,
                    body_from_marker: Pose::identity(),
                }],
                cameras: Vec::new(),
            },
        ],
        ros2: None,
        source: "shoal eval nees".into(),
    })
}

/// `ξᵀ Σ⁻¹ ξ` over the whole pose and over the position block; `None` if
/// the covariance is not invertible.
pub fn nees(truth: &Pose, estimate: &Pose, cov: &Cov6) -> Option<(f64, f64)> {
    let xi: Vector6<f64> = difference(truth, estimate);
    let full = cov.cholesky()?.solve(&xi).dot(&xi);
    let p: Matrix3<f64> = cov.fixed_view::<3, 3>(0, 0).into_owned();
    let t: Vector3<f64> = xi.fixed_rows::<3>(0).into_owned();
    let pos = p.cholesky()?.solve(&t).dot(&t);
    Some((full, pos))
}

/// The frame's NEES with the calibration part of the covariance scaled by
/// each of [`SCALES`] (σ scaled, so the covariance part by its square):
/// the part is recomputed by the function the pipeline calls, at the
/// observation's pose, and taken off the reported covariance.
fn scaled_nees(
    cam: &CameraModel,
    stated: Option<CalibrationSigma>,
    obs: &shoal_proto::Observation,
    truth: &Pose,
) -> Vec<f64> {
    let cal = stated.and_then(|s| {
        shoal_node::pose::calibration_covariance(
            cam,
            None,
            &CodeSet::Shoal.corners_3d(MARKER_SIDE_M),
            &obs.observer_from_target,
            &s,
        )
    });
    // The observation does not say which corners it used: only full reads.
    let (Some(cal), 12) = (cal, obs.corners_px.len()) else {
        return Vec::new();
    };
    let corner = obs.covariance - cal;
    SCALES
        .iter()
        .map(|k| {
            nees(truth, &obs.observer_from_target, &(corner + cal * (k * k)))
                .map_or(f64::NAN, |v| v.0)
        })
        .collect()
}

fn side_px(corners: &[[f32; 2]]) -> Option<f64> {
    let c = corners.get(..4)?;
    let edge = |a: &[f32; 2], b: &[f32; 2]| f64::from(a[0] - b[0]).hypot(f64::from(a[1] - b[1]));
    Some((0..4).map(|k| edge(&c[k], &c[(k + 1) % 4])).sum::<f64>() / 4.0)
}

/// Run `profile` at one water: `frames` frames per seed through a fresh
/// node pipeline per seed.
fn run_condition(
    opts: &EvalOptions,
    profile: &CameraProfile,
    c_per_m: f64,
    node_cams: &[CameraModel],
    stated: Option<CalibrationSigma>,
    frames: usize,
    rows: &mut Vec<Row>,
) -> Result<(), EvalError> {
    let cam = CameraModel::vehicle_1440();
    let water = opts.presets()?.get(c_per_m)?;
    let mut renderer = Renderer::new();
    for (s, node_cam) in node_cams.iter().enumerate() {
        let seed = opts.seed + s as u64;
        let profile = profile.clone().with_seed(seed);
        let mut pipeline = CameraPipeline::new(
            fleet_for(node_cam, stated),
            OBSERVER,
            0,
            PipelineParams::default(),
        )
        .map_err(|e| EvalError::Setup(e.to_string()))?;
        let condition = (c_per_m * 1000.0).round() as u64 + 7000;
        for k in 0..frames {
            let mut rng = frame_rng(seed, condition, k as u64);
            let range_m = rng.gen_range(RANGE_M.0..=RANGE_M.1);
            let tl = scene_and_motion(range_m, &mut rng);
            let noise_seed: u64 = rng.gen();
            let time_s = k as f64 * FRAME_INTERVAL_S;
            let f = render_profiled(
                &mut renderer,
                &profile,
                &cam,
                None,
                &tl,
                &water,
                time_s,
                noise_seed,
            )?;
            let truth = camera_from_marker(&tl, f.report.reference_s)?;
            let raw = shoal_node::mat::gray_to_mat(&f.output.image)?;
            let out = pipeline
                .process(&raw, (time_s * 1e9) as u64, k as u64)
                .map_err(|e| EvalError::Setup(format!("node pipeline: {e}")))?;
            let obs = out
                .observations
                .iter()
                .find(|o| !o.predicted && o.target_marker == MARKER_ID);
            let mut row = Row {
                profile: profile.name.clone(),
                c_per_m,
                seed,
                frame: k,
                range_m,
                read: obs.is_some(),
                nees6: None,
                nees3: None,
                position_mm: None,
                rotation_deg: None,
                rms_px: None,
                corners: 0,
                side_px: None,
                contrast: None,
                psf: f
                    .report
                    .psf
                    .as_deref()
                    .and_then(|d| d.split_whitespace().next())
                    .unwrap_or("model")
                    .to_lowercase(),
                pattern_fit: obs.is_some()
                    && out.corner_fits.get(shoal_node::detect::CornerFit::Pattern) > 0,
                nees6_scaled: Vec::new(),
            };
            if let Some(o) = obs {
                let (d, a) = super::scene::pose_errors(&o.observer_from_target, &truth);
                let n = nees(&truth, &o.observer_from_target, &o.covariance);
                row.nees6 = n.map(|v| v.0);
                row.nees3 = n.map(|v| v.1);
                row.position_mm = Some(d);
                row.rotation_deg = Some(a);
                row.rms_px = Some(o.reprojection_rms_px);
                row.corners = o.corners_px.len();
                row.side_px = side_px(&o.corners_px);
                row.contrast = Some(f64::from(o.quality.marker_contrast));
                row.nees6_scaled = scaled_nees(node_cam, stated, o, &truth);
            }
            rows.push(row);
        }
    }
    Ok(())
}

/// Quantile `p` of χ²(k) (Wilson–Hilferty): within 0.1 % for k ≥ 60 (the
/// bands of the means), 0.5 % in the upper tail at k = 3 or 6, 2.5 % at
/// k = 6's 2.5 % point.
pub fn chi2_quantile(p: f64, k: f64) -> f64 {
    let z = normal_quantile(p);
    let a = 2.0 / (9.0 * k);
    k * (1.0 - a + z * a.sqrt()).powi(3).max(0.0)
}

/// Quantile of the standard normal (Acklam's rational approximation, |ε| < 1.2e-9).
fn normal_quantile(p: f64) -> f64 {
    const A: [f64; 6] = [
        -3.969_683_028_665_376e1,
        2.209_460_984_245_205e2,
        -2.759_285_104_469_687e2,
        1.383_577_518_672_69e2,
        -3.066_479_806_614_716e1,
        2.506_628_277_459_239,
    ];
    const B: [f64; 5] = [
        -5.447_609_879_822_406e1,
        1.615_858_368_580_409e2,
        -1.556_989_798_598_866e2,
        6.680_131_188_771_972e1,
        -1.328_068_155_288_572e1,
    ];
    const C: [f64; 6] = [
        -7.784_894_002_430_293e-3,
        -3.223_964_580_411_365e-1,
        -2.400_758_277_161_838,
        -2.549_732_539_343_734,
        4.374_664_141_464_968,
        2.938_163_982_698_783,
    ];
    const D: [f64; 4] = [
        7.784_695_709_041_462e-3,
        3.224_671_290_700_398e-1,
        2.445_134_137_142_996,
        3.754_408_661_907_416,
    ];
    let p = p.clamp(1e-300, 1.0 - 1e-16);
    let tail = |q: f64| {
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    };
    if p < 0.02425 {
        tail((-2.0 * p.ln()).sqrt())
    } else if p > 1.0 - 0.02425 {
        -tail((-2.0 * (1.0 - p).ln()).sqrt())
    } else {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    }
}

/// The 95 % band a consistent covariance puts the mean NEES of `n` frames
/// of dimension `dim` in: χ²(dim·n) quantiles over n.
pub fn chi2_band(dim: usize, n: usize) -> Option<(f64, f64)> {
    (n > 0).then(|| {
        let k = (dim * n) as f64;
        (
            chi2_quantile(0.025, k) / n as f64,
            chi2_quantile(0.975, k) / n as f64,
        )
    })
}

/// 95 % percentile-bootstrap interval of the mean of `v`.
fn bootstrap_mean(v: &[f64], seed: u64) -> Option<(f64, f64)> {
    if v.len() < 2 {
        return None;
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let means: Vec<f64> = (0..BOOTSTRAP)
        .map(|_| {
            (0..v.len())
                .map(|_| v[rng.gen_range(0..v.len())])
                .sum::<f64>()
                / v.len() as f64
        })
        .collect();
    Some((quantile(&means, 0.025)?, quantile(&means, 0.975)?))
}

/// Each frame's NEES with its seed.
fn seeded(rows: &[&Row], pick: impl Fn(&Row) -> Option<f64>) -> Vec<(u64, f64)> {
    rows.iter()
        .filter_map(|r| pick(r).map(|v| (r.seed, v)))
        .collect()
}

/// Mean NEES of dimension `dim` over frames `(seed, NEES)` with its
/// intervals and the χ² band.
fn nees_figures(frames: &[(u64, f64)], dim: usize) -> Value {
    let v: Vec<f64> = frames.iter().map(|f| f.1).collect();
    if v.is_empty() {
        return json!({ "frames": 0 });
    }
    let mean = v.iter().sum::<f64>() / v.len() as f64;
    let mut seeds: Vec<u64> = frames.iter().map(|f| f.0).collect();
    seeds.sort_unstable();
    seeds.dedup();
    let per_seed: Vec<f64> = seeds
        .iter()
        .map(|s| {
            let of: Vec<f64> = frames.iter().filter(|f| f.0 == *s).map(|f| f.1).collect();
            of.iter().sum::<f64>() / of.len() as f64
        })
        .collect();
    let band = chi2_band(dim, v.len());
    let boot = bootstrap_mean(&v, 0x4E45_4553 ^ v.len() as u64);
    let above95 = chi2_quantile(0.95, dim as f64);
    json!({
        "frames": v.len(),
        "mean": mean,
        "chi2_band95": band.map(|b| [b.0, b.1]),
        "consistent": band.map(|b| (b.0..=b.1).contains(&mean)),
        "bootstrap95": boot.map(|b| [b.0, b.1]),
        "per_seed": mean_ci(&per_seed, POSITIVE),
        "median": median(&v),
        "median_expected": chi2_quantile(0.5, dim as f64),
        "fraction_above_chi2_95": v.iter().filter(|x| **x > above95).count() as f64 / v.len() as f64,
    })
}

fn summarize(rows: &[&Row]) -> Value {
    let read: Vec<&Row> = rows.iter().copied().filter(|r| r.read).collect();
    let unflipped: Vec<&Row> = read.iter().copied().filter(|r| !r.flip()).collect();
    let per_seed_read: Vec<f64> = {
        let mut seeds: Vec<u64> = rows.iter().map(|r| r.seed).collect();
        seeds.sort_unstable();
        seeds.dedup();
        seeds
            .iter()
            .map(|s| {
                let of: Vec<&&Row> = rows.iter().filter(|r| r.seed == *s).collect();
                of.iter().filter(|r| r.read).count() as f64 / of.len().max(1) as f64
            })
            .collect()
    };
    json!({
        "frames": rows.len(),
        "read": read.len(),
        "fraction_read": read.len() as f64 / rows.len().max(1) as f64,
        "fraction_read_per_seed": mean_ci(&per_seed_read, (0.0, 1.0)),
        "flips": read.len() - unflipped.len(),
        "nees6": nees_figures(&seeded(&read, |r| r.nees6), 6),
        "nees3": nees_figures(&seeded(&read, |r| r.nees3), 3),
        "nees6_without_flips": nees_figures(&seeded(&unflipped, |r| r.nees6), 6),
        "nees3_without_flips": nees_figures(&seeded(&unflipped, |r| r.nees3), 3),
        "median_position_mm": median(&read.iter().filter_map(|r| r.position_mm).collect::<Vec<_>>()),
        "median_rms_px": median(&read.iter().filter_map(|r| r.rms_px).collect::<Vec<_>>()),
    })
}

/// `shoal eval nees`.
pub fn run(opts: &EvalOptions) -> Result<Value, EvalError> {
    let frames = opts.count(3, 12);
    let presets = opts.presets()?;
    let waters: Vec<f64> = if opts.quick {
        QUICK_WATERS.to_vec()
    } else {
        presets.presets.iter().map(|w| w.c_per_m).collect()
    };
    let profiles = [CameraProfile::ideal(), CameraProfile::realistic()];
    let cam = CameraModel::vehicle_1440();
    // The node's calibration per profile and seed (the lab calibration is drawn once per seed).
    let mut node_cams = Vec::new();
    for p in &profiles {
        let cams = (0..SEEDS)
            .map(|s| node_camera(&p.clone().with_seed(opts.seed + s), &cam, opts.seed + s))
            .collect::<Result<Vec<_>, _>>()?;
        node_cams.push(cams);
    }
    let bar = opts.bar(waters.len() * profiles.len(), "nees");
    let mut rows = Vec::new();
    for &c in &waters {
        for (p, cams) in profiles.iter().zip(&node_cams) {
            run_condition(opts, p, c, cams, stated_sigma(p), frames, &mut rows)?;
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    write_csv(opts, &rows)?;
    let mut results = Map::new();
    for p in &profiles {
        let mut per = Map::new();
        for &c in &waters {
            let of: Vec<&Row> = rows
                .iter()
                .filter(|r| r.profile == p.name && r.c_per_m == c)
                .collect();
            per.insert(water_key(c), summarize(&of));
        }
        results.insert(p.name.clone(), Value::Object(per));
    }
    let plots = plot_means(opts, &profiles, &waters, &results);
    let realistic: Vec<&Row> = rows.iter().filter(|r| r.profile == "realistic").collect();
    Ok(json!({
        "stated_calibration_sigma": profiles
            .iter()
            .map(|p| (p.name.clone(), json!(stated_sigma(p).map(|s| [s.focal_rel, s.principal_px, s.k1]))))
            .collect::<Map<_, _>>(),
        "calibration_scale": scale_fit(&realistic, &waters),
        "seeds": SEEDS,
        "frames_per_seed": frames,
        "range_m": [RANGE_M.0, RANGE_M.1],
        "pipeline": "PipelineParams::default() (HOIRM, shoal detector, corner noise estimated)",
        "results": results,
        "plots": plots,
    }))
}

/// The calibration uncertainty the node's fleet file states for `profile`'s
/// camera: none for `ideal` (the renderer's own camera); for a profile with
/// the calibration error, its uniform bounds as standard deviations
/// (bound / √3), what a lab's report of that calibration would say.
pub fn stated_sigma(profile: &CameraProfile) -> Option<CalibrationSigma> {
    profile.is_on(Effect::Calibration).then(|| {
        let e = &profile.params.calibration;
        let k = 1.0 / 3f64.sqrt();
        CalibrationSigma {
            focal_rel: e.focal_rel * k,
            principal_px: e.principal_px * k,
            k1: e.k1 * k,
        }
    })
}

/// The NEES at scale index `i` of the unflipped full reads of `rows`, with their seeds.
fn scaled_values(rows: &[&Row], i: usize) -> Vec<(u64, f64)> {
    rows.iter()
        .filter(|r| r.read && !r.flip())
        .filter_map(|r| r.nees6_scaled.get(i).map(|v| (r.seed, *v)))
        .filter(|v| v.1.is_finite())
        .collect()
}

/// The scale of the stated calibration σ that brings the mean NEES (6-DoF,
/// planar flips apart) of the [`FIT_WATERS`] frames nearest 6 (on a log
/// scale), and the NEES at scales 0, 1 and the fitted one per water, each
/// flagged fitted or held out, and per PSF family.
fn scale_fit(rows: &[&Row], waters: &[f64]) -> Value {
    let fit: Vec<&Row> = rows.iter().copied().filter(|r| !r.held_out()).collect();
    let best = (0..SCALES.len())
        .filter_map(|i| {
            let v = scaled_values(&fit, i);
            (!v.is_empty()).then(|| (i, v.iter().map(|x| x.1).sum::<f64>() / v.len() as f64))
        })
        .min_by(|a, b| (a.1 / 6.0).ln().abs().total_cmp(&(b.1 / 6.0).ln().abs()));
    let Some((k, fit_mean)) = best else {
        return json!({ "fitted": null, "reason": "no full unflipped reads at the fit waters" });
    };
    let at = |of: &[&Row], i: usize| nees_figures(&scaled_values(of, i), 6);
    let one = SCALES.iter().position(|s| *s == 1.0).unwrap_or(0);
    let mut per_water = Map::new();
    for &c in waters {
        let of: Vec<&Row> = rows.iter().copied().filter(|r| r.c_per_m == c).collect();
        if of.is_empty() {
            continue;
        }
        per_water.insert(
            water_key(c),
            json!({
                "held_out": of[0].held_out(),
                "scale_0": at(&of, 0),
                "scale_1": at(&of, one),
                "fitted": at(&of, k),
            }),
        );
    }
    let mut families: Vec<String> = rows.iter().map(|r| r.psf.clone()).collect();
    families.sort();
    families.dedup();
    let mut per_psf = Map::new();
    for fam in families {
        let of: Vec<&Row> = rows.iter().copied().filter(|r| r.psf == fam).collect();
        let held: Vec<&Row> = of.iter().copied().filter(|r| r.held_out()).collect();
        per_psf.insert(
            fam,
            json!({ "all_waters": at(&of, k), "held_out_waters": if held.is_empty() { Value::Null } else { at(&held, k) } }),
        );
    }
    let held: Vec<&Row> = rows.iter().copied().filter(|r| r.held_out()).collect();
    json!({
        "scales": SCALES,
        "fit_waters": FIT_WATERS,
        "fitted": SCALES[k],
        "fit_mean_nees6": fit_mean,
        "held_out_all": if held.is_empty() { Value::Null } else { at(&held, k) },
        "per_water": per_water,
        "per_psf_family": per_psf,
    })
}

/// Mean NEES (6-DoF) per water and profile beside the χ² band's top.
fn plot_means(
    opts: &EvalOptions,
    profiles: &[CameraProfile],
    waters: &[f64],
    results: &Map<String, Value>,
) -> Value {
    let mean = |p: &str, c: f64| results[p][water_key(c)]["nees6"]["mean"].as_f64();
    let mut values: Vec<Vec<Option<f64>>> = profiles
        .iter()
        .map(|p| waters.iter().map(|c| mean(&p.name, *c)).collect())
        .collect();
    let mut series: Vec<String> = profiles.iter().map(|p| p.name.clone()).collect();
    values.push(
        waters
            .iter()
            .map(|c| {
                let n = results[profiles[0].name.as_str()][water_key(*c)]["nees6"]["frames"]
                    .as_u64()?;
                chi2_band(6, n as usize).map(|b| b.1)
            })
            .collect(),
    );
    series.push("χ² 95 % top (ideal's frames)".into());
    // Means far above the band would flatten the chart: log10 of 1 + NEES.
    let values: Vec<Vec<Option<f64>>> = values
        .into_iter()
        .map(|s| {
            s.into_iter()
                .map(|v| v.map(|x| (1.0 + x).log10()))
                .collect()
        })
        .collect();
    super::features::plot_or_warn(plot::bars(
        &opts.out.join("eval-nees"),
        &Grouped {
            title: "mean NEES (6-DoF) of the node as shipped; consistent = 6, log10(1 + 6) = 0.85"
                .into(),
            x_label: "attenuation coefficient c (1/m)".into(),
            y_label: "log10(1 + mean NEES)".into(),
            categories: waters.iter().map(|c| water_key(*c)).collect(),
            series,
        },
        &values,
    ))
}

fn write_csv(opts: &EvalOptions, rows: &[Row]) -> Result<(), EvalError> {
    let mut csv = Csv::new(&[
        "profile",
        "c_per_m",
        "seed",
        "frame",
        "range_m",
        "read",
        "nees6",
        "nees3",
        "position_mm",
        "rotation_deg",
        "rms_px",
        "corners",
        "side_px",
        "contrast",
        "psf",
        "pattern_fit",
        "nees6_at_scales",
    ]);
    for r in rows {
        csv.row(vec![
            r.profile.clone(),
            r.c_per_m.to_string(),
            r.seed.to_string(),
            r.frame.to_string(),
            format!("{:.4}", r.range_m),
            r.read.to_string(),
            cell(r.nees6),
            cell(r.nees3),
            cell(r.position_mm),
            cell(r.rotation_deg),
            cell(r.rms_px),
            r.corners.to_string(),
            cell(r.side_px),
            cell(r.contrast),
            r.psf.clone(),
            r.pattern_fit.to_string(),
            r.nees6_scaled
                .iter()
                .map(|v| format!("{v:.4}"))
                .collect::<Vec<_>>()
                .join(";"),
        ]);
    }
    csv.write(&opts.out.join("frames.csv"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chi2_quantiles_match_tables() {
        // Tables: χ²(6) 2.5 % 1.237, 50 % 5.348, 95 % 12.592, 97.5 % 14.449; χ²(3) 95 % 7.815;
        // χ²(60) 2.5 % 40.482, 97.5 % 83.298.
        // Relative tolerances: Wilson–Hilferty's own error at these points.
        for (p, k, want, rel) in [
            (0.025, 6.0, 1.237, 0.03),
            (0.5, 6.0, 5.348, 0.003),
            (0.95, 6.0, 12.592, 0.003),
            (0.975, 6.0, 14.449, 0.002),
            (0.95, 3.0, 7.815, 0.007),
            (0.025, 60.0, 40.482, 0.001),
            (0.975, 60.0, 83.298, 0.001),
        ] {
            let got = chi2_quantile(p, k);
            assert!(
                ((got - want) / want).abs() < rel,
                "χ²({k}) at {p}: {got} vs {want}"
            );
        }
        let (lo, hi) = chi2_band(6, 10).unwrap();
        assert!((lo - 40.482 / 10.0).abs() < 0.01 && (hi - 83.298 / 10.0).abs() < 0.01);
        assert_eq!(chi2_band(6, 0), None);
    }

    #[test]
    fn nees_of_a_one_sigma_error_is_one_and_the_position_block_is_its_own() {
        use shoal_proto::geometry::perturb;
        let est = Pose::identity();
        let mut cov = Cov6::from_diagonal(&Vector6::new(1e-6, 4e-6, 9e-6, 1e-4, 1e-4, 1e-4));
        cov[(0, 3)] = 5e-6;
        cov[(3, 0)] = 5e-6;
        // One σ along y only: NEES 1 whatever the rotation block holds.
        let truth = perturb(&est, &Vector6::new(0.0, 2e-3, 0.0, 0.0, 0.0, 0.0));
        let (full, pos) = nees(&truth, &est, &cov).unwrap();
        assert!((full - 1.0).abs() < 1e-6 && (pos - 1.0).abs() < 1e-6);
        // An error in rotation only adds to the full NEES, not the position's.
        let truth = perturb(&est, &Vector6::new(0.0, 0.0, 0.0, 0.0, 0.0, 2e-2));
        let (full, pos) = nees(&truth, &est, &cov).unwrap();
        assert!((full - 4.0).abs() < 1e-6 && pos.abs() < 1e-12);
        assert_eq!(nees(&truth, &est, &Cov6::zeros()), None);
    }

    #[test]
    fn bootstrap_brackets_the_mean() {
        let v: Vec<f64> = (0..100).map(|k| f64::from(k % 10)).collect();
        let (lo, hi) = bootstrap_mean(&v, 1).unwrap();
        assert!(lo < 4.5 && hi > 4.5 && hi - lo < 1.5, "{lo}..{hi}");
        assert_eq!(bootstrap_mean(&[1.0], 1), None);
    }
}
