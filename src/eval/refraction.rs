//! `refraction`: what a flat port costs a PnP that ignores it, measured on
//! rendered frames.
//!
//! The camera sits behind a flat port ([`port`]: 10 mm of air from the
//! lens centre, 8 mm of acrylic, sea water), and the simulator renders
//! through it. The lens in air is `CameraModel::vehicle_1440()` with its
//! focal length divided by n_water, so that behind the port it is the
//! 1440x1080 camera of about 60° in water that the fleet files describe.
//! Each frame shows the 100 mm enhanced marker (`CodeSet::Shoal`, ID 17;
//! beyond 2 m printed larger in proportion, see [`FULL_SIZE_RANGE_M`]) at
//! a range from the lens centre and an angle off the optical axis (along
//! the image diagonal, where 25° still fits), in clear water, with sensor
//! noise, restored as every other experiment's frames (HOIRM by default,
//! `--restore`). shoal's detector reads its corners once; the same corners are
//! solved two ways:
//!
//! - `pinhole`: the in-water pinhole a lab would have. It is obtained by
//!   calibrating: a 9x6 chessboard of 30 mm squares is seen through the
//!   port at the distances a lab calibrates at (0.5–1.5 m, tilted, all over
//!   the image), its corners projected exactly and given 0.05 px of noise,
//!   and OpenCV's `calibrateCamera` fits a pinhole with plumb-bob distortion
//!   to them. The node's ordinary `estimate_pose` uses that model.
//! - `refractive`: `estimate_pose_with` through the true port and lens.
//!
//! Output: `refraction.csv` (every frame), `summary.json` (per method,
//! range and angle: position and angle error, median and p95 over every
//! frame of every seed, and the 95 % interval of the per-seed medians),
//! `refraction_position.png/svg` (median position error against range, one
//! line per method and angle).

use super::features::plot_or_warn;
use super::plot;
use super::scene::{
    frame_rng, make_restorer, pose_errors, restore, MarkerMethod, FRAME_INTERVAL_S, MARKER_ID,
};
use super::table::{cell, median, quantile, Csv};
use super::{EvalError, EvalOptions};
use nalgebra::{Point3, Vector3};
use opencv::core::{Mat, Point2f, Point3f, Size, TermCriteria, TermCriteria_Type, Vector};
use opencv::prelude::*;
use rand::Rng;
use rand_distr::{Distribution, Normal};
use serde_json::{json, Map, Value};
use shoal_node::pipeline::detect_restoration;
use shoal_node::pose::{estimate_pose, estimate_pose_with};
use shoal_proto::camera::{CameraModel, Distortion, FlatPort};
use shoal_proto::geometry::{pose_from_xyz_rpy, Pose};
use shoal_proto::CodeSet;
use shoal_sim_bridge::render::{facing_camera, Renderer, Scene};

/// Marker side (m): the paper's 100 mm marker, up to [`FULL_SIZE_RANGE_M`].
const SIDE_M: f64 = 0.100;
/// Beyond this range the detector no longer reads the 100 mm marker
/// reliably (`fit-noise`: 8/60 at 2.75 m, 0/60 at 3.25 m), so the same
/// marker is printed larger in proportion to the range: it covers as many
/// pixels as the 100 mm one at 2 m. Refraction's error depends on the
/// rays' angles and the range, not on the marker's size.
const FULL_SIZE_RANGE_M: f64 = 2.0;

/// The marker's side at `range_m`.
fn side_m(range_m: f64) -> f64 {
    SIDE_M * (range_m / FULL_SIZE_RANGE_M).max(1.0)
}
/// Clear water (1/m): the paper's clearest coefficient.
const WATER_C_PER_M: f64 = 0.126;
/// The two PnP models compared, in output order.
pub const METHODS: [&str; 2] = ["pinhole", "refractive"];
/// Per-frame jitter of the marker's orientation (± rad, about its own axes)
/// and position (± m), so frames are not noise-only copies.
const JITTER_RAD: f64 = 0.17;
const JITTER_M: f64 = 0.002;
/// Corner noise of the synthetic lab calibration (px, 1σ): a chessboard's
/// sub-pixel corners in a lab are good to about this.
const CALIBRATION_NOISE_PX: f64 = 0.05;

/// The port of the experiment: a typical small-AUV camera housing. 10 mm
/// from the lens's entrance pupil to the window (lens barrels sit a few mm
/// to a centimetre behind it) and an 8 mm acrylic window (what depth
/// ratings of a few hundred metres need at a 50–75 mm aperture).
pub fn port() -> FlatPort {
    FlatPort {
        distance_m: 0.010,
        glass_m: 0.008,
        n_glass: FlatPort::N_ACRYLIC,
        n_water: FlatPort::N_SEA_WATER,
    }
}

/// The lens in air: `vehicle_1440` with its focal length divided by
/// n_water, so that behind the port it sees what `vehicle_1440` describes.
pub fn lens_in_air() -> CameraModel {
    let wet = CameraModel::vehicle_1440();
    CameraModel {
        fx: wet.fx / FlatPort::N_SEA_WATER,
        fy: wet.fy / FlatPort::N_SEA_WATER,
        ..wet
    }
}

/// The lab's in-water calibration and how well it fitted.
#[derive(Debug, Clone, Copy)]
pub struct LabCalibration {
    pub camera: CameraModel,
    pub rms_px: f64,
    pub views: usize,
}

/// Calibrate an in-water pinhole (plumb-bob) from a chessboard seen through
/// `port`, as a lab would: `views` poses at 0.5–1.5 m.
pub fn calibrate_in_water(
    lens: &CameraModel,
    port: &FlatPort,
    views: usize,
    seed: u64,
) -> Result<LabCalibration, EvalError> {
    let (cols, rows, square) = (9usize, 6usize, 0.030);
    let board: Vec<Point3<f64>> = (0..rows)
        .flat_map(|r| {
            (0..cols).map(move |c| {
                Point3::new(
                    (c as f64 - 0.5 * (cols - 1) as f64) * square,
                    (r as f64 - 0.5 * (rows - 1) as f64) * square,
                    0.0,
                )
            })
        })
        .collect();
    let mut rng = frame_rng(seed, 0xCA11, 0);
    let noise =
        Normal::new(0.0, CALIBRATION_NOISE_PX).map_err(|e| EvalError::Setup(e.to_string()))?;
    let mut obj_all: Vector<Vector<Point3f>> = Vector::new();
    let mut img_all: Vector<Vector<Point2f>> = Vector::new();
    let (w, h) = (f64::from(lens.width), f64::from(lens.height));
    let mut tries = 0;
    while img_all.len() < views && tries < views * 50 {
        tries += 1;
        // The board's centre on a random pixel's in-water ray, at 0.5–1.5 m.
        let (u, v) = (rng.gen_range(0.1..0.9) * w, rng.gen_range(0.1..0.9) * h);
        let (o, dir) = port.ray(lens, u, v);
        let centre = o + dir * rng.gen_range(0.5..1.5);
        let tilt = 35f64.to_radians();
        let pose = pose_from_xyz_rpy(
            [centre.x, centre.y, centre.z],
            [
                rng.gen_range(-tilt..tilt),
                rng.gen_range(-tilt..tilt),
                rng.gen_range(-0.3..0.3),
            ],
        );
        let px: Option<Vec<Point2f>> = board
            .iter()
            .map(|p| {
                let q = port.project(lens, &(pose * p))?;
                let (x, y) = (q.x + noise.sample(&mut rng), q.y + noise.sample(&mut rng));
                let inside = x > 5.0 && y > 5.0 && x < w - 6.0 && y < h - 6.0;
                inside.then_some(Point2f::new(x as f32, y as f32))
            })
            .collect();
        if let Some(px) = px {
            img_all.push(px.into_iter().collect());
            obj_all.push(
                board
                    .iter()
                    .map(|p| Point3f::new(p.x as f32, p.y as f32, 0.0))
                    .collect(),
            );
        }
    }
    let mut k = Mat::default();
    let mut d = Mat::default();
    let (mut rvecs, mut tvecs) = (Vector::<Mat>::new(), Vector::<Mat>::new());
    let criteria = TermCriteria::new(
        TermCriteria_Type::COUNT as i32 + TermCriteria_Type::EPS as i32,
        100,
        1e-12,
    )?;
    let rms_px = opencv::calib3d::calibrate_camera(
        &obj_all,
        &img_all,
        Size::new(lens.width as i32, lens.height as i32),
        &mut k,
        &mut d,
        &mut rvecs,
        &mut tvecs,
        0,
        criteria,
    )?;
    let kd = |r: i32, c: i32| k.at_2d::<f64>(r, c).copied();
    let mut coeffs = [0.0; 5];
    for (i, c) in coeffs.iter_mut().enumerate() {
        *c = *d.at::<f64>(i as i32)?;
    }
    let camera = CameraModel {
        fx: kd(0, 0)?,
        fy: kd(1, 1)?,
        cx: kd(0, 2)?,
        cy: kd(1, 2)?,
        distortion: Distortion::PlumbBob(coeffs),
        ..*lens
    };
    if let Some(p) = camera.problem() {
        return Err(EvalError::Setup(format!(
            "the synthetic lab calibration is unusable: {p}"
        )));
    }
    Ok(LabCalibration {
        camera,
        rms_px,
        views: img_all.len(),
    })
}

/// The conditions of a run: ranges (m), off-axis angles (deg), seeds, frames.
#[derive(Debug, Clone)]
struct Plan {
    ranges_m: Vec<f64>,
    angles_deg: Vec<f64>,
    seeds: Vec<u64>,
    frames: usize,
    calibration_views: usize,
}

impl Plan {
    fn new(opts: &EvalOptions) -> Plan {
        let seeds = if opts.quick { 1 } else { 3 };
        Plan {
            ranges_m: if opts.quick {
                vec![1.0, 4.0]
            } else {
                vec![0.5, 1.0, 1.5, 2.0, 3.0, 4.0]
            },
            angles_deg: if opts.quick {
                vec![0.0, 20.0]
            } else {
                vec![0.0, 10.0, 20.0, 25.0]
            },
            seeds: (0..seeds).map(|k| opts.seed + k).collect(),
            frames: opts.count(2, 8),
            calibration_views: if opts.quick { 20 } else { 40 },
        }
    }
}

/// One frame: the errors of each method (`None`: not detected or no pose).
#[derive(Debug, Clone)]
struct Row {
    seed: u64,
    range_m: f64,
    angle_deg: f64,
    frame: usize,
    corners: usize,
    corner_err_px: f64,
    /// Position error (mm) and angle error (deg), per method of [`METHODS`].
    errors: [Option<(f64, f64)>; 2],
}

/// The marker's pose: at `range_m` from the lens centre, `angle_deg` off
/// the axis along the image diagonal, facing the camera, jittered.
fn marker_pose(range_m: f64, angle_deg: f64, rng: &mut impl Rng) -> Pose {
    let cam = lens_in_air();
    let azimuth = (f64::from(cam.height)).atan2(f64::from(cam.width));
    let a = angle_deg.to_radians();
    let mut j = |s: f64| rng.gen_range(-s..=s);
    let dir = Vector3::new(a.sin() * azimuth.cos(), a.sin() * azimuth.sin(), a.cos());
    let p = dir * range_m + Vector3::new(j(JITTER_M), j(JITTER_M), j(JITTER_M));
    facing_camera(
        [p.x, p.y, p.z],
        [j(JITTER_RAD), j(JITTER_RAD), j(JITTER_RAD)],
    )
}

/// Render, detect and solve every frame of `plan`.
fn run_frames(opts: &EvalOptions, plan: &Plan, lab: &CameraModel) -> Result<Vec<Row>, EvalError> {
    let (lens, port) = (lens_in_air(), port());
    let water = opts.presets()?.get(WATER_C_PER_M)?;
    let mut renderer = Renderer::new();
    let mut detector = MarkerMethod::Shoal.detector(lab)?;
    let total = plan.seeds.len() * plan.ranges_m.len() * plan.angles_deg.len() * plan.frames;
    let bar = opts.bar(total, "refraction");
    let mut rows = Vec::new();
    for &seed in &plan.seeds {
        for (ri, &range_m) in plan.ranges_m.iter().enumerate() {
            for (ai, &angle_deg) in plan.angles_deg.iter().enumerate() {
                // One restorer per condition: HOIRM's ambient estimate follows its own frames.
                let mut restorer = make_restorer(opts.restore, &opts.restore_params);
                for frame in 0..plan.frames {
                    let condition = (ri * plan.angles_deg.len() + ai) as u64;
                    let mut rng = frame_rng(seed, condition, frame as u64);
                    let truth = marker_pose(range_m, angle_deg, &mut rng);
                    let side = side_m(range_m);
                    let scene = Scene::single_marker(CodeSet::Shoal, MARKER_ID, side, truth);
                    let time_s = frame as f64 * FRAME_INTERVAL_S;
                    let out = renderer.render_with_port(
                        &lens,
                        Some(&port),
                        &Pose::identity(),
                        &scene,
                        &water,
                        time_s,
                        rng.gen(),
                    )?;
                    let raw = shoal_node::mat::gray_to_mat(&out.image)
                        .map_err(shoal_node::detect::DetectError::from)?;
                    let restored = restore(restorer.as_mut(), &out.image, (time_s * 1e9) as u64)?;
                    let dets = detect_restoration(detector.as_mut(), &restored, &raw)?.detections;
                    let best = dets
                        .iter()
                        .filter(|d| d.id == MARKER_ID)
                        .max_by_key(|d| d.corners_px.len());
                    let mut row = Row {
                        seed,
                        range_m,
                        angle_deg,
                        frame,
                        corners: 0,
                        corner_err_px: f64::NAN,
                        errors: [None, None],
                    };
                    if let Some(d) = best {
                        let pts = d.object_points(side);
                        row.corners = d.corners_px.len();
                        let errs: Vec<f64> = pts
                            .iter()
                            .zip(&d.corners_px)
                            .filter_map(|(p, c)| {
                                let q = port.project(&lens, &(truth * p))?;
                                Some((q.x - c[0]).hypot(q.y - c[1]))
                            })
                            .collect();
                        row.corner_err_px = median(&errs).unwrap_or(f64::NAN);
                        let pinhole = estimate_pose(lab, &pts, &d.corners_px, None);
                        let refractive =
                            estimate_pose_with(&lens, Some(&port), &pts, &d.corners_px, None);
                        for (slot, sol) in row.errors.iter_mut().zip([pinhole, refractive]) {
                            *slot = sol
                                .ok()
                                .map(|s| pose_errors(&s.best.camera_from_marker, &truth));
                        }
                    }
                    rows.push(row);
                    bar.inc(1);
                }
            }
        }
    }
    bar.finish_and_clear();
    Ok(rows)
}

/// Student's t at 97.5 % for `dof` degrees of freedom (1..=9; 1.96 beyond).
fn t975(dof: usize) -> f64 {
    const T: [f64; 9] = [12.71, 4.30, 3.18, 2.78, 2.57, 2.45, 2.36, 2.31, 2.26];
    T.get(dof.wrapping_sub(1)).copied().unwrap_or(1.96)
}

/// Median, p95 and the 95 % interval (Student's t) of the mean of the
/// per-seed medians of `values` (`(seed, value)`); `None` with one seed.
fn stats(values: &[(u64, f64)]) -> Value {
    let all: Vec<f64> = values.iter().map(|v| v.1).collect();
    let mut seeds: Vec<u64> = values.iter().map(|v| v.0).collect();
    seeds.sort_unstable();
    seeds.dedup();
    let per_seed: Vec<f64> = seeds
        .iter()
        .filter_map(|s| {
            let v: Vec<f64> = values.iter().filter(|v| v.0 == *s).map(|v| v.1).collect();
            median(&v)
        })
        .collect();
    let ci = (per_seed.len() >= 2).then(|| {
        let n = per_seed.len() as f64;
        let mean = per_seed.iter().sum::<f64>() / n;
        let var = per_seed.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0);
        let half = t975(per_seed.len() - 1) * (var / n).sqrt();
        // An error is never negative: the interval is clipped at 0.
        [(mean - half).max(0.0), mean + half]
    });
    json!({
        "median": median(&all),
        "p95": quantile(&all, 0.95),
        "seed_median_ci95": ci,
    })
}

/// `shoal eval refraction`.
pub fn run(opts: &EvalOptions) -> Result<Value, EvalError> {
    let plan = Plan::new(opts);
    let (lens, port) = (lens_in_air(), port());
    let lab = calibrate_in_water(&lens, &port, plan.calibration_views, opts.seed)?;
    let rows = run_frames(opts, &plan, &lab.camera)?;
    write_csv(opts, &rows)?;

    let mut conditions = Map::new();
    let mut table = Vec::new();
    for (m, method) in METHODS.iter().enumerate() {
        let mut per = Map::new();
        for &r in &plan.ranges_m {
            for &a in &plan.angles_deg {
                let sel: Vec<&Row> = rows
                    .iter()
                    .filter(|x| x.range_m == r && x.angle_deg == a)
                    .collect();
                let ok: Vec<(u64, (f64, f64))> = sel
                    .iter()
                    .filter_map(|x| x.errors[m].map(|e| (x.seed, e)))
                    .collect();
                let pos: Vec<(u64, f64)> = ok.iter().map(|(s, e)| (*s, e.0)).collect();
                let ang: Vec<(u64, f64)> = ok.iter().map(|(s, e)| (*s, e.1)).collect();
                let key = format!("r{r:.1}_a{a:.0}");
                let entry = json!({
                    "range_m": r,
                    "marker_side_mm": side_m(r) * 1e3,
                    "angle_deg": a,
                    "frames": sel.len(),
                    "solved": ok.len(),
                    "position_mm": stats(&pos),
                    "angle_deg_error": stats(&ang),
                });
                table.push((method.to_string(), r, a, entry.clone()));
                per.insert(key, entry);
            }
        }
        conditions.insert(method.to_string(), Value::Object(per));
    }
    let corner: Vec<f64> = rows.iter().map(|r| r.corner_err_px).collect();
    let plot = plot_or_warn(plot_position(opts, &plan, &table));
    Ok(json!({
        "results": {
            "port": {
                "distance_mm": port.distance_m * 1e3,
                "glass_mm": port.glass_m * 1e3,
                "n_glass": port.n_glass,
                "n_water": port.n_water,
            },
            "lens_in_air": { "fx": lens.fx, "fy": lens.fy, "distortion": lens.distortion.coefficients() },
            "lab_calibration": {
                "views": lab.views,
                "rms_px": lab.rms_px,
                "fx": lab.camera.fx,
                "fy": lab.camera.fy,
                "cx": lab.camera.cx,
                "cy": lab.camera.cy,
                "distortion": lab.camera.distortion.coefficients(),
                "corner_noise_px": CALIBRATION_NOISE_PX,
            },
            "water_c_per_m": WATER_C_PER_M,
            "seeds": plan.seeds,
            "frames_per_condition_and_seed": plan.frames,
            "corner_error_px_median": median(&corner),
            "conditions": conditions,
        },
        "camera": "vehicle_1440 in water: lens fx/n_water behind the port; realistic sensor noise",
        "plots": plot,
    }))
}

fn write_csv(opts: &EvalOptions, rows: &[Row]) -> Result<(), EvalError> {
    let mut csv = Csv::new(&[
        "seed",
        "range_m",
        "angle_deg",
        "frame",
        "corners",
        "corner_err_px",
        "pinhole_position_mm",
        "pinhole_angle_deg",
        "refractive_position_mm",
        "refractive_angle_deg",
    ]);
    for r in rows {
        let e = |m: usize, k: usize| cell(r.errors[m].map(|e| if k == 0 { e.0 } else { e.1 }));
        csv.row(vec![
            r.seed.to_string(),
            format!("{}", r.range_m),
            format!("{}", r.angle_deg),
            r.frame.to_string(),
            r.corners.to_string(),
            cell(Some(r.corner_err_px)),
            e(0, 0),
            e(0, 1),
            e(1, 0),
            e(1, 1),
        ]);
    }
    csv.write(&opts.out.join("refraction.csv"))
}

/// Median position error against range, one line per method and angle.
fn plot_position(
    opts: &EvalOptions,
    plan: &Plan,
    table: &[(String, f64, f64, Value)],
) -> Result<Vec<std::path::PathBuf>, EvalError> {
    let mut series = Vec::new();
    for method in METHODS {
        for &a in &plan.angles_deg {
            let pts = table
                .iter()
                .filter(|t| t.0 == method && t.2 == a)
                .map(|t| {
                    (
                        t.1,
                        t.3["position_mm"]["median"].as_f64().unwrap_or(f64::NAN),
                    )
                })
                .collect();
            series.push((format!("{method} {a:.0}°"), pts));
        }
    }
    plot::lines(
        &opts.out.join("refraction_position"),
        "Flat port: median position error, in-water pinhole vs refractive PnP",
        "range (m)",
        "position error (mm)",
        &series,
    )
}
