//! `profiles` (issue #16): shoal's detector on the same scenes rendered
//! through the ideal camera profile (the renderer as every other
//! experiment uses it) and the realistic one (every camera effect of
//! `docs/water-model.md`, "Camera effects"), over several seeds, each
//! figure with its 95 % interval across seeds; and, at one condition, each
//! effect alone (which effect costs what).
//!
//! Scenes: a 100 mm enhanced marker at 1–2 m, up to ±0.25 of the range
//! off the axis, turned up to ±30°, in 0.5, 1.38 and 3.92 /m water; the camera
//! drifts as a vehicle holding formation does (up to 0.1 m/s, up to 4°/s
//! about each axis). Both profiles see the same scene, motion and noise
//! seed; the truth is the marker's pose at the frame's reference time
//! (mid-exposure of the middle row; the start of the frame for `ideal`).
//!
//! The node's camera: the in-water pinhole for `ideal`; for a profile
//! with the port, a lab's in-water plumb-bob calibration through that port
//! ([`super::refraction::calibrate_in_water`], one per seed), moved by the
//! calibration error when that effect is on.

use super::features::plot_or_warn;
use super::plot::{self, Grouped};
use super::scene::{
    frame_rng, locate, make_restorer, pose_errors, restore, MarkerMethod, FRAME_INTERVAL_S,
    MARKER_ID, MARKER_SIDE_M,
};
use super::table::{cell, median, Csv};
use super::{water_key, EvalError, EvalOptions};
use nalgebra::Vector3;
use rand::Rng;
use serde_json::{json, Map, Value};
use shoal_proto::{CameraModel, CodeSet, Pose};
use shoal_sim_bridge::profile::{CameraProfile, Effect};
use std::path::PathBuf;

/// The camera profile options of `shoal sim render`, `shoal demo`, `shoal
/// eval` and its HOIRM probe.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ProfileArgs {
    /// Camera profile: `ideal` (the renderer as it is; the default) or
    /// `realistic` (motion blur, rolling shutter, flat port, lamps, marine
    /// snow, other PSFs, vignetting, exposure, compression, calibration error,
    /// typical parameters; docs/water-model.md).
    #[arg(long)]
    pub profile: Option<String>,
    /// Only these effects, with typical parameters (repeatable; replaces --profile): motion-blur,
    /// rolling-shutter, port, lamps, snow, psf, vignetting, colour, exposure, jpeg, h264, calibration.
    #[arg(long = "effect", value_name = "NAME")]
    pub effects: Vec<String>,
    /// A camera profile file (TOML; replaces --profile and --effect).
    #[arg(long)]
    pub profile_file: Option<PathBuf>,
}

impl ProfileArgs {
    /// The profile asked for, validated, its own draws seeded by `seed`
    /// when given; `None` when no option was.
    pub fn selected(
        &self,
        seed: Option<u64>,
    ) -> Result<Option<CameraProfile>, shoal_sim_bridge::SimError> {
        if self.profile.is_none() && self.effects.is_empty() && self.profile_file.is_none() {
            return Ok(None);
        }
        let mut p = CameraProfile::selected(
            self.profile.as_deref().unwrap_or("ideal"),
            &self.effects,
            self.profile_file.as_deref(),
        )?;
        if let Some(s) = seed {
            p.seed = s;
        }
        Ok(Some(p))
    }
}
use shoal_sim_bridge::render::motion::{RigidMotion, Timeline, Twist};
use shoal_sim_bridge::render::realistic::{calibration_error, lens_in_air, render_profiled};
use shoal_sim_bridge::render::{facing_camera, Renderer, Scene};

/// Seeds per condition (issue #16: at least 5).
pub const SEEDS: u64 = 5;
/// `(c per m, range m)` of the main comparison.
pub const CONDITIONS: [(f64, f64); 4] = [(0.5, 1.0), (0.5, 2.0), (1.38, 1.5), (3.92, 1.0)];
/// The condition of the one-effect-at-a-time runs.
pub const ABLATION: (f64, f64) = (0.5, 2.0);
/// Relative motion of a vehicle holding formation: speed (m/s) and rate about each axis (rad/s).
const MAX_SPEED_MPS: f64 = 0.1;
const MAX_RATE_RADPS: f64 = 4.0 * std::f64::consts::PI / 180.0;
/// Chessboard views of the synthetic lab calibration behind the port.
const LAB_VIEWS: usize = 30;

/// One frame's outcome.
#[derive(Debug, Clone)]
struct Row {
    profile: String,
    c_per_m: f64,
    range_m: f64,
    seed: u64,
    frame: usize,
    found: bool,
    position_mm: Option<f64>,
    rotation_deg: Option<f64>,
    sub_frames: usize,
}

/// A marker at `range_m` (off the axis, turned) and the camera drifting as a
/// vehicle holding formation.
pub(super) fn scene_and_motion(range_m: f64, rng: &mut impl Rng) -> RigidMotion {
    let mut u = |a: f64| rng.gen_range(-a..=a);
    let pose = facing_camera(
        [u(0.25 * range_m), u(0.18 * range_m), range_m],
        [u(0.1), u(30f64.to_radians()), u(0.2)],
    );
    let dir = u(std::f64::consts::PI);
    let speed = u(MAX_SPEED_MPS).abs();
    RigidMotion {
        world_from_camera: Pose::identity(),
        scene: Scene::single_marker(CodeSet::Shoal, MARKER_ID, MARKER_SIDE_M, pose),
        camera: Twist {
            linear_mps: Vector3::new(speed * dir.cos(), speed * dir.sin(), u(0.3 * MAX_SPEED_MPS)),
            angular_radps: Vector3::new(u(MAX_RATE_RADPS), u(MAX_RATE_RADPS), u(MAX_RATE_RADPS)),
        },
        targets: Twist::default(),
    }
}

/// The marker's pose in the camera at time `t` of `tl`.
pub(super) fn camera_from_marker(tl: &RigidMotion, t: f64) -> Result<Pose, EvalError> {
    let (world_from_camera, scene) = tl.at(t)?;
    let m = scene
        .markers
        .first()
        .ok_or_else(|| EvalError::Setup("the scene has no marker".into()))?;
    Ok(world_from_camera.inverse() * m.world_from_marker)
}

/// The calibration the node holds for `cam` under `profile` (seeded): the
/// in-water pinhole itself for a profile without the port; with the port, a
/// lab's in-water plumb-bob calibration through it; moved by the
/// calibration error when that effect is on.
pub(super) fn node_camera(
    profile: &CameraProfile,
    cam: &CameraModel,
    seed: u64,
) -> Result<CameraModel, EvalError> {
    let base = if profile.is_on(Effect::Port) {
        let port = profile.port()?;
        super::refraction::calibrate_in_water(&lens_in_air(cam, &port), &port, LAB_VIEWS, seed)?
            .camera
    } else {
        *cam
    };
    Ok(if profile.is_on(Effect::Calibration) {
        calibration_error(&base, &profile.params.calibration, seed)
    } else {
        base
    })
}

/// The seed of vehicle `v`'s camera `cam` in frame `k` (its noise; with
/// `k = 0` its calibration draw too).
pub fn camera_seed(seed: u64, v: shoal_proto::VehicleId, cam: u8, k: u64) -> u64 {
    seed ^ ((v as u64) << 40) ^ ((cam as u64) << 32) ^ k
}

/// `fleet`'s cameras as its nodes would hold them behind `profile`'s
/// camera: each one's calibration as a lab would have it ([`node_camera`],
/// drawn per camera from `seed`), and with `state_sigma` the uncertainty
/// that lab's report would state ([`super::nees::stated_sigma`]). An error
/// when the fleet gives a camera a flat port of its own (the profile adds
/// its own port: the fleet must give in-water cameras).
pub fn lab_fleet(
    fleet: &shoal_proto::config::Fleet,
    profile: &CameraProfile,
    seed: u64,
    state_sigma: bool,
) -> Result<shoal_proto::config::Fleet, EvalError> {
    for v in &fleet.vehicles {
        if let Some(cam) = v.cameras.iter().find(|c| c.port.is_some()) {
            return Err(EvalError::Setup(format!(
                "vehicle {} camera {}: the fleet gives a flat port and the profile adds \
                 its own; a camera profile takes in-water cameras",
                v.id, cam.name
            )));
        }
    }
    let sigma = state_sigma
        .then(|| super::nees::stated_sigma(profile))
        .flatten();
    let mut held = fleet.clone();
    // Each camera's lab calibration is its own (OpenCV's calibration over
    // the lab's views, ~0.5 s each): over the cores.
    let mut cams: Vec<(u64, &mut shoal_proto::config::Camera)> = held
        .vehicles
        .iter_mut()
        .flat_map(|v| {
            let id = v.id;
            v.cameras
                .iter_mut()
                .enumerate()
                .map(move |(c, cam)| (camera_seed(seed, id, c as u8, 0), cam))
        })
        .collect();
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let per_thread = cams.len().div_ceil(threads).max(1);
    std::thread::scope(|scope| {
        let workers: Vec<_> = cams
            .chunks_mut(per_thread)
            .map(|chunk| {
                scope.spawn(move || -> Result<(), EvalError> {
                    for (cam_seed, cam) in chunk {
                        cam.model = node_camera(profile, &cam.model, *cam_seed)?;
                        if sigma.is_some() {
                            cam.calibration_sigma = sigma;
                        }
                    }
                    Ok(())
                })
            })
            .collect();
        workers.into_iter().try_for_each(|w| {
            w.join().unwrap_or_else(|_| {
                Err(EvalError::Setup("a lab calibration thread panicked".into()))
            })
        })
    })?;
    Ok(held)
}

/// Run `profile` on `frames` frames of each seed at one condition.
fn run_profile(
    opts: &EvalOptions,
    profile: &CameraProfile,
    (c_per_m, range_m): (f64, f64),
    condition: u64,
    frames: usize,
    rows: &mut Vec<Row>,
) -> Result<(), EvalError> {
    let cam = CameraModel::vehicle_1440();
    let water = opts.presets()?.get(c_per_m)?;
    let mut renderer = Renderer::new();
    for s in 0..seeds(opts) {
        let seed = opts.seed + s;
        let profile = profile.clone().with_seed(seed);
        let node_cam = node_camera(&profile, &cam, seed)?;
        let mut detector = MarkerMethod::Shoal.detector(&node_cam)?;
        let mut restorer = make_restorer(opts.restore, &opts.restore_params);
        for k in 0..frames {
            let mut rng = frame_rng(seed, condition, k as u64);
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
            let restored = restore(restorer.as_mut(), &f.output.image, (time_s * 1e9) as u64)?;
            let raw = shoal_node::mat::gray_to_mat(&f.output.image)?;
            let located = locate(detector.as_mut(), &restored, &raw, &node_cam)?;
            let errors = located.camera_from_marker.map(|p| pose_errors(&p, &truth));
            rows.push(Row {
                profile: profile.name.clone(),
                c_per_m,
                range_m,
                seed,
                frame: k,
                found: errors.is_some(),
                position_mm: errors.map(|e| e.0),
                rotation_deg: errors.map(|e| e.1),
                sub_frames: f.report.sub_frames,
            });
        }
    }
    Ok(())
}

/// Student's t at 97.5 % for `dof` degrees of freedom.
pub(super) fn t975(dof: usize) -> f64 {
    const T: [f64; 9] = [12.71, 4.30, 3.18, 2.78, 2.57, 2.45, 2.36, 2.31, 2.26];
    T.get(dof.wrapping_sub(1)).copied().unwrap_or(1.96)
}

/// Mean of per-seed values and its 95 % interval (Student's t), clipped to
/// `bounds` (a recall lies in 0..=1, an error or a ratio is never negative);
/// `None` without two seeds.
pub(super) fn mean_ci(per_seed: &[f64], bounds: (f64, f64)) -> Value {
    let v: Vec<f64> = per_seed.iter().copied().filter(|x| x.is_finite()).collect();
    let n = v.len() as f64;
    if v.len() < 2 {
        return json!({ "mean": v.first(), "ci95": null, "seeds": v.len() });
    }
    let mean = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
    let half = t975(v.len() - 1) * (var / n).sqrt();
    let clip = |x: f64| x.clamp(bounds.0, bounds.1);
    json!({ "mean": mean, "ci95": [clip(mean - half), clip(mean + half)], "seeds": v.len() })
}

/// Bounds of a recall and of an error or ratio.
const UNIT: (f64, f64) = (0.0, 1.0);
pub(super) const POSITIVE: (f64, f64) = (0.0, f64::INFINITY);

fn per_seed(rows: &[&Row], f: impl Fn(&[&Row]) -> Option<f64>) -> Vec<f64> {
    let mut seeds: Vec<u64> = rows.iter().map(|r| r.seed).collect();
    seeds.sort_unstable();
    seeds.dedup();
    seeds
        .iter()
        .filter_map(|s| {
            let of: Vec<&Row> = rows.iter().copied().filter(|r| r.seed == *s).collect();
            f(&of)
        })
        .collect()
}

fn recall(rows: &[&Row]) -> Option<f64> {
    (!rows.is_empty()).then(|| rows.iter().filter(|r| r.found).count() as f64 / rows.len() as f64)
}

fn median_of(rows: &[&Row], f: impl Fn(&Row) -> Option<f64>) -> Option<f64> {
    median(&rows.iter().filter_map(|r| f(r)).collect::<Vec<_>>())
}

/// The figures of one profile at one condition, and its ratio to `ideal` there.
fn summarize(rows: &[Row], profile: &str, c: f64, r: f64, ideal: Option<&str>) -> Value {
    let pick = |name: &str| -> Vec<&Row> {
        rows.iter()
            .filter(|x| x.profile == name && x.c_per_m == c && x.range_m == r)
            .collect()
    };
    let mine = pick(profile);
    let pos = |rs: &[&Row]| median_of(rs, |x| x.position_mm);
    let mut out = json!({
        "frames": mine.len(),
        "recall": mean_ci(&per_seed(&mine, recall), UNIT),
        "median_position_mm": mean_ci(&per_seed(&mine, pos), POSITIVE),
        "median_rotation_deg": mean_ci(
            &per_seed(&mine, |rs| median_of(rs, |x| x.rotation_deg)),
            POSITIVE,
        ),
        "sub_frames_mean": mine.iter().map(|x| x.sub_frames as f64).sum::<f64>() / mine.len().max(1) as f64,
    });
    if let Some(base) = ideal {
        let theirs = pick(base);
        let ratios: Vec<f64> = per_seed(&mine, |rs| {
            let seed = rs.first()?.seed;
            let b: Vec<&Row> = theirs.iter().copied().filter(|x| x.seed == seed).collect();
            Some(pos(rs)? / pos(&b)?)
        });
        out["position_ratio_to_ideal"] = mean_ci(&ratios, POSITIVE);
    }
    out
}

/// The summary's key of a condition, e.g. `c0.50_r1`.
fn condition_key(c_per_m: f64, range_m: f64) -> String {
    format!("c{}_r{range_m}", water_key(c_per_m))
}

/// Seeds per condition: [`SEEDS`], three in `--quick` (still an interval).
fn seeds(opts: &EvalOptions) -> u64 {
    if opts.quick {
        3
    } else {
        SEEDS
    }
}

/// The main comparison's conditions: all of [`CONDITIONS`], the first (clear
/// water at 1 m) in `--quick`.
fn conditions(opts: &EvalOptions) -> &'static [(f64, f64)] {
    if opts.quick {
        &CONDITIONS[..1]
    } else {
        &CONDITIONS
    }
}

/// `shoal eval profiles`.
pub fn run(opts: &EvalOptions) -> Result<Value, EvalError> {
    let frames = opts.count(2, 6);
    let ablation_frames = opts.count(1, 4);
    let main = [CameraProfile::ideal(), CameraProfile::realistic()];
    let mut ablation: Vec<CameraProfile> = vec![CameraProfile::ideal()];
    ablation.extend(
        Effect::ALL
            .iter()
            .filter(|e| !opts.quick || **e == Effect::MotionBlur)
            .map(|e| CameraProfile::only(&[*e])),
    );
    let total = conditions(opts).len() * main.len() + ablation.len();
    let bar = opts.bar(total, "profiles");
    let mut rows = Vec::new();
    for (ci, cond) in conditions(opts).iter().enumerate() {
        for p in &main {
            run_profile(opts, p, *cond, ci as u64, frames, &mut rows)?;
            bar.inc(1);
        }
    }
    let mut ablation_rows = Vec::new();
    for p in &ablation {
        run_profile(opts, p, ABLATION, 100, ablation_frames, &mut ablation_rows)?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    write_csv(opts, rows.iter().chain(&ablation_rows))?;

    let mut summaries = Map::new();
    for &(c, r) in conditions(opts) {
        summaries.insert(
            condition_key(c, r),
            json!({
                "ideal": summarize(&rows, "ideal", c, r, None),
                "realistic": summarize(&rows, "realistic", c, r, Some("ideal")),
            }),
        );
    }
    let mut effects = Map::new();
    for p in &ablation {
        let base = (!p.is_ideal()).then_some("ideal");
        effects.insert(
            p.name.clone(),
            summarize(&ablation_rows, &p.name, ABLATION.0, ABLATION.1, base),
        );
    }
    let plots = plot_profiles(opts, &summaries);
    Ok(json!({
        "plots": plots,
        "seeds": seeds(opts),
        "frames_per_seed": frames,
        "conditions": summaries,
        "each_effect_alone": {
            "c_per_m": ABLATION.0,
            "range_m": ABLATION.1,
            "frames_per_seed": ablation_frames,
            "profiles": effects,
        },
        "restore": opts.restore.to_string(),
    }))
}

/// Recall and median position error of both profiles at every condition
/// (the means over seeds; the intervals are in `summary.json`).
fn plot_profiles(opts: &EvalOptions, summaries: &Map<String, Value>) -> Value {
    let conds = conditions(opts);
    let categories: Vec<String> = conds
        .iter()
        .map(|(c, r)| format!("{} /m, {r} m", water_key(*c)))
        .collect();
    let series = ["ideal", "realistic"];
    let values = |field: &str| -> Vec<Vec<Option<f64>>> {
        series
            .iter()
            .map(|p| {
                conds
                    .iter()
                    .map(|(c, r)| {
                        summaries.get(&condition_key(*c, *r))?[*p][field]["mean"].as_f64()
                    })
                    .collect()
            })
            .collect()
    };
    let spec = |title: &str, y: &str| Grouped {
        title: title.into(),
        x_label: "water c (1/m), range (m)".into(),
        y_label: y.into(),
        categories: categories.clone(),
        series: series.iter().map(|s| (*s).to_string()).collect(),
    };
    json!([
        plot_or_warn(plot::bars(
            &opts.out.join("profiles-recall"),
            &spec(
                "Markers read: ideal vs realistic camera",
                "recall (mean over seeds)"
            ),
            &values("recall"),
        )),
        plot_or_warn(plot::bars(
            &opts.out.join("profiles-position"),
            &spec(
                "Median position error: ideal vs realistic camera",
                "median position error (mm, mean over seeds)",
            ),
            &values("median_position_mm"),
        )),
    ])
}

fn write_csv<'a>(opts: &EvalOptions, rows: impl Iterator<Item = &'a Row>) -> Result<(), EvalError> {
    let mut csv = Csv::new(&[
        "profile",
        "c_per_m",
        "range_m",
        "seed",
        "frame",
        "found",
        "position_mm",
        "rotation_deg",
        "sub_frames",
    ]);
    for r in rows {
        csv.row(vec![
            r.profile.clone(),
            r.c_per_m.to_string(),
            r.range_m.to_string(),
            r.seed.to_string(),
            r.frame.to_string(),
            r.found.to_string(),
            cell(r.position_mm),
            cell(r.rotation_deg),
            r.sub_frames.to_string(),
        ]);
    }
    csv.write(&opts.out.join("frames.csv"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use shoal_proto::config::Fleet;

    /// The paper fleet's first vehicle with two of its cameras.
    fn small_fleet() -> Fleet {
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/fleets/paper.toml");
        let mut fleet = Fleet::load(&path).expect("the paper fleet");
        fleet.vehicles.truncate(1);
        fleet.vehicles[0].cameras.truncate(2);
        fleet
    }

    #[test]
    fn a_lab_fleet_holds_each_camera_as_a_lab_calibrated_it_and_states_the_sigma_when_asked() {
        let fleet = small_fleet();
        let profile = CameraProfile::realistic().with_seed(3);
        let held = lab_fleet(&fleet, &profile, 3, true).expect("lab calibrations");
        let (truth, cams) = (&fleet.vehicles[0].cameras, &held.vehicles[0].cameras);
        for (t, c) in truth.iter().zip(cams) {
            // Near the renderer's in-water camera (a port's pinhole, the
            // calibration error), not it, and not the lens in air (fx / 1.34).
            assert_ne!(t.model, c.model);
            assert!(
                (c.model.fx / t.model.fx - 1.0).abs() < 0.01,
                "{} vs {}",
                c.model.fx,
                t.model.fx
            );
            assert!(
                (c.model.cx - t.model.cx).abs() < 10.0,
                "{} vs {}",
                c.model.cx,
                t.model.cx
            );
            assert_eq!(
                c.calibration_sigma,
                super::super::nees::stated_sigma(&profile)
            );
            assert!(c.calibration_sigma.is_some());
            assert_eq!(
                (c.name.as_str(), c.body_from_camera),
                (t.name.as_str(), t.body_from_camera)
            );
        }
        // Each camera its own calibration; the same seed the same fleet.
        assert_ne!(cams[0].model, cams[1].model);
        let again = lab_fleet(&fleet, &profile, 3, false).expect("lab calibrations");
        for (a, b) in cams.iter().zip(&again.vehicles[0].cameras) {
            assert_eq!(a.model, b.model);
            assert_eq!(b.calibration_sigma, None);
        }
        // A fleet whose camera has a port of its own is refused, naming it.
        let mut ported = fleet.clone();
        ported.vehicles[0].cameras[1].port = Some(profile.port().expect("the profile's port"));
        let err = lab_fleet(&ported, &profile, 3, true)
            .expect_err("a camera with a port")
            .to_string();
        let (id, name) = (ported.vehicles[0].id, &ported.vehicles[0].cameras[1].name);
        assert!(
            err.contains(&format!("vehicle {id} camera {name}")),
            "{err}"
        );
    }
}
