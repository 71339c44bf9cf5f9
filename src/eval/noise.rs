//! `fit-noise`: fit the observation-level synthesizer's noise model
//! ([`NoiseModel`]) to what the image-level pipeline measures.
//!
//! The enhanced marker is rendered at the swarm trial's water (0.5 /m) over a
//! range of distances and two platform yaws (face-on and 30°, how side
//! cameras see their neighbours), restored and located exactly as in the
//! accuracy experiments; every pose error is split in the camera frame into
//! lateral (x, y), depth (z), tilt (rotation about x, y) and roll (about z).
//! Per range a robust σ of each is taken (1.4826 × the median absolute error,
//! so that the few planar flips, counted separately as the flip rate, do not
//! swamp the noise), with the detection rate; then the model's lines are fitted by
//! least squares: `σ_lat = floor + a·r`, `σ_depth = floor + b·r + c·r²` (the
//! lateral floor), `σ_tilt = t₀ + k·r`, `σ_roll` constant. The result is printed next
//! to the shipped defaults, and written as `noise-model.json` for
//! `NoiseModel::default` to adopt. Through `--profile` the frames come from
//! that camera and the node holds the calibration it would (as in
//! `accuracy`); the port's and the calibration's bias, the same on every
//! frame of a seed, then counts as noise here (it is an error fusion cannot
//! average away either).

use super::accuracy::{run_conditions, Condition, Record};
use super::scene::MarkerMethod;
use super::table::{cell, median, Csv};
use super::{EvalError, EvalOptions};
use nalgebra::{DMatrix, DVector};
use serde_json::{json, Value};
use shoal_proto::geometry::difference;
use shoal_sim_bridge::obs_synth::NoiseModel;

/// Distances of the fit (m): from a close neighbour to the side cameras' far range.
const RANGES_M: [f64; 7] = [0.75, 1.25, 1.75, 2.25, 2.75, 3.25, 4.0];
/// A located pose whose rotation is off by more than this (degrees) is a
/// gross error — in practice the planar flip — counted apart, not as noise.
const GROSS_DEG: f64 = 3.0;
/// A range enters the fit with at least this many frames that are not gross errors.
pub const MIN_INLIERS: usize = 5;
/// Platform yaws (degrees).
const YAWS_DEG: [f64; 2] = [0.0, 30.0];
/// The swarm trial's water (1/m).
const WATER_PER_M: f64 = 0.5;

/// Robust σ of the error components at one range.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RangeStats {
    pub range_m: f64,
    pub frames: usize,
    pub located: usize,
    /// Located poses off by more than [`GROSS_DEG`] (flips).
    pub gross: usize,
    pub lateral_m: f64,
    pub depth_m: f64,
    pub tilt_rad: f64,
    pub roll_rad: f64,
    /// Median of each signed error component (x, y, z in m; rotation about
    /// x, y, z in rad): the part the same on every frame, the camera's bias
    /// (NaN without a good frame).
    pub bias: [f64; 6],
    /// Robust σ of the components around their median (lateral, depth,
    /// tilt, roll): the frame-to-frame noise with the bias taken out.
    pub spread: [f64; 4],
}

impl RangeStats {
    /// These statistics with the spread around the bias as the σ (what
    /// varies from frame to frame), for [`fit`].
    pub fn around_bias(&self) -> RangeStats {
        RangeStats {
            lateral_m: self.spread[0],
            depth_m: self.spread[1],
            tilt_rad: self.spread[2],
            roll_rad: self.spread[3],
            ..*self
        }
    }
}

/// One camera's bias as lines in the range (what a calibration error does:
/// a focal length off scales the depth, a principal point off tilts the
/// line of sight): position per metre of range, rotation constant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BiasFit {
    /// x, y, z bias per metre of range (m/m).
    pub per_m: [f64; 3],
    /// Rotation bias about x, y, z (rad).
    pub rotation_rad: [f64; 3],
}

/// The bias lines of one camera from its per-range medians: each slope the
/// median over the ranges of bias / range, each rotation the median bias
/// (ranges with fewer than [`MIN_INLIERS`] good frames left out). `None`
/// with fewer than two such ranges.
pub fn fit_bias(stats: &[RangeStats]) -> Option<BiasFit> {
    let ok: Vec<&RangeStats> = stats
        .iter()
        .filter(|s| s.located >= s.gross + MIN_INLIERS && s.bias.iter().all(|b| b.is_finite()))
        .collect();
    if ok.len() < 2 {
        return None;
    }
    let med = |f: &dyn Fn(&RangeStats) -> f64| -> Option<f64> {
        median(&ok.iter().map(|s| f(s)).collect::<Vec<_>>())
    };
    Some(BiasFit {
        per_m: [
            med(&|s| s.bias[0] / s.range_m)?,
            med(&|s| s.bias[1] / s.range_m)?,
            med(&|s| s.bias[2] / s.range_m)?,
        ],
        rotation_rad: [
            med(&|s| s.bias[3])?,
            med(&|s| s.bias[4])?,
            med(&|s| s.bias[5])?,
        ],
    })
}

/// 1.4826 × the median of |x|: σ of a zero-mean normal sample, robust to a few gross errors.
fn robust_std(values: &[f64]) -> f64 {
    let abs: Vec<f64> = values.iter().map(|v| v.abs()).collect();
    median(&abs).map_or(f64::NAN, |m| 1.4826 * m)
}

/// Per-range robust σ of each error component over the located frames that
/// are not gross errors.
pub fn range_stats(records: &[Record], conditions: &[Condition]) -> Vec<RangeStats> {
    RANGES_M
        .iter()
        .map(|&r| {
            let mut comp: [Vec<f64>; 6] = Default::default();
            let (mut frames, mut located, mut gross) = (0, 0usize, 0usize);
            for rec in records
                .iter()
                .filter(|rec| (conditions[rec.condition].distance_m - r).abs() < 1e-9)
            {
                frames += 1;
                let Some(est) = rec.located.camera_from_marker else {
                    continue;
                };
                located += 1;
                let e = difference(&est, &rec.truth);
                if e.fixed_rows::<3>(3).norm() > GROSS_DEG.to_radians() {
                    gross += 1;
                    continue;
                }
                for (c, v) in comp.iter_mut().zip(e.iter()) {
                    c.push(*v);
                }
            }
            let bias = [0, 1, 2, 3, 4, 5].map(|i| median(&comp[i]).unwrap_or(f64::NAN));
            // Each component around its own median, the pairs pooled as the σ are.
            let around = |ix: &[usize]| -> Vec<f64> {
                ix.iter()
                    .flat_map(|&i| comp[i].iter().map(move |v| v - bias[i]))
                    .collect()
            };
            let pooled = |ix: &[usize]| -> Vec<f64> {
                ix.iter().flat_map(|&i| comp[i].iter().copied()).collect()
            };
            RangeStats {
                range_m: r,
                frames,
                located,
                gross,
                lateral_m: robust_std(&pooled(&[0, 1])),
                depth_m: robust_std(&comp[2]),
                tilt_rad: robust_std(&pooled(&[3, 4])),
                roll_rad: robust_std(&comp[5]),
                bias,
                spread: [
                    robust_std(&around(&[0, 1])),
                    robust_std(&around(&[2])),
                    robust_std(&around(&[3, 4])),
                    robust_std(&around(&[5])),
                ],
            }
        })
        .collect()
}

/// Least-squares fit of the model's lines to per-range σ (ranges with fewer
/// than [`MIN_INLIERS`] good frames are left out). `None` with fewer than
/// three ranges.
pub fn fit(stats: &[RangeStats]) -> Option<NoiseModel> {
    let ok: Vec<&RangeStats> = stats
        .iter()
        .filter(|s| s.located >= s.gross + MIN_INLIERS && s.lateral_m.is_finite())
        .collect();
    if ok.len() < 3 {
        return None;
    }
    // Lateral: floor + a·r; then depth − floor = b·r + c·r² (the floor is
    // the lateral one: depth has no better-observed intercept).
    let n = ok.len();
    let line = |xs: &dyn Fn(f64) -> [f64; 2], ys: &dyn Fn(&RangeStats) -> f64| {
        let mut m = DMatrix::<f64>::zeros(n, 2);
        let mut y = DVector::<f64>::zeros(n);
        // Relative residuals: a σ of 1 mm and one of 20 mm weigh alike.
        for (i, s) in ok.iter().enumerate() {
            let x = xs(s.range_m);
            let w = 1.0 / ys(s).abs().max(1e-9);
            m[(i, 0)] = x[0] * w;
            m[(i, 1)] = x[1] * w;
            y[i] = ys(s) * w;
        }
        m.svd(true, true).solve(&y, 1e-12).ok()
    };
    let lat = line(&|r| [1.0, r], &|s| s.lateral_m)?;
    let floor = lat[0].max(0.0);
    let depth = line(&|r| [r, r * r], &|s| s.depth_m - floor)?;
    let t = [floor, lat[1], depth[0], depth[1]];
    let r = line(&|r| [1.0, r], &|s| s.tilt_rad)?;
    let roll = (ok.iter().map(|s| s.roll_rad * s.roll_rad).sum::<f64>() / n as f64).sqrt();
    // A negative intercept or slope is noise of the fit: clamp to what a σ can be.
    Some(NoiseModel {
        translation_std_floor_m: t[0],
        lateral_std_per_m: t[1].max(0.0),
        depth_std_per_m: t[2].max(0.0),
        depth_std_per_m2: t[3].max(0.0),
        tilt_std_rad: r[0].max(0.0),
        tilt_std_per_m: r[1].max(0.0),
        roll_std_rad: roll,
        depth_std_table: None,
    })
}

fn model_json(m: &NoiseModel) -> Value {
    json!({
        "translation_std_floor_m": m.translation_std_floor_m,
        "lateral_std_per_m": m.lateral_std_per_m,
        "depth_std_per_m": m.depth_std_per_m,
        "depth_std_per_m2": m.depth_std_per_m2,
        "tilt_std_deg": m.tilt_std_rad.to_degrees(),
        "tilt_std_deg_per_m": m.tilt_std_per_m.to_degrees(),
        "roll_std_deg": m.roll_std_rad.to_degrees(),
    })
}

/// The model's σ at `r` (lateral, depth, tilt, roll).
fn predicted(m: &NoiseModel, r: f64) -> [f64; 4] {
    let c = m.camera_covariance(r);
    [
        c[(0, 0)].sqrt(),
        c[(2, 2)].sqrt(),
        c[(3, 3)].sqrt(),
        c[(5, 5)].sqrt(),
    ]
}

/// The columns of `noise.csv`, one row per range.
const CSV_COLUMNS: [&str; 26] = [
    "range_m",
    "frames",
    "located",
    "gross",
    "lateral_mm",
    "depth_mm",
    "tilt_deg",
    "roll_deg",
    "fit_lateral_mm",
    "fit_depth_mm",
    "fit_tilt_deg",
    "fit_roll_deg",
    "shipped_lateral_mm",
    "shipped_depth_mm",
    "shipped_tilt_deg",
    "shipped_roll_deg",
    "bias_x_mm",
    "bias_y_mm",
    "bias_z_mm",
    "bias_rx_deg",
    "bias_ry_deg",
    "bias_rz_deg",
    "spread_lateral_mm",
    "spread_depth_mm",
    "spread_tilt_deg",
    "spread_roll_deg",
];

/// The bias lines of this seed's camera and the frame-to-frame noise around them, printed.
fn print_bias_and_noise(b: &BiasFit, n: &NoiseModel) {
    crate::outln!(
        "bias of this seed's camera: position {:.2} / {:.2} / {:.2} mm per m of range (x / y / z), \
         rotation {:.3} / {:.3} / {:.3}° (x / y / z); frame-to-frame noise around it: \
         lateral {:.3} mm/m, depth {:.3} mm/m + {:.3} mm/m², tilt {:.3}° + {:.3}°/m, roll {:.3}°",
        b.per_m[0] * 1e3,
        b.per_m[1] * 1e3,
        b.per_m[2] * 1e3,
        b.rotation_rad[0].to_degrees(),
        b.rotation_rad[1].to_degrees(),
        b.rotation_rad[2].to_degrees(),
        n.lateral_std_per_m * 1e3,
        n.depth_std_per_m * 1e3,
        n.depth_std_per_m2 * 1e3,
        n.tilt_std_rad.to_degrees(),
        n.tilt_std_per_m.to_degrees(),
        n.roll_std_rad.to_degrees(),
    );
}

/// One range's figures in `summary.json`.
fn range_json(s: &RangeStats) -> Value {
    json!({
        "range_m": s.range_m,
        "frames": s.frames,
        "located": s.located,
        "detection_rate": s.located as f64 / s.frames.max(1) as f64,
        "gross_errors": s.gross,
        "lateral_mm": s.lateral_m * 1e3,
        "depth_mm": s.depth_m * 1e3,
        "tilt_deg": s.tilt_rad.to_degrees(),
        "roll_deg": s.roll_rad.to_degrees(),
        "bias_mm": [s.bias[0] * 1e3, s.bias[1] * 1e3, s.bias[2] * 1e3],
        "bias_deg": [s.bias[3].to_degrees(), s.bias[4].to_degrees(), s.bias[5].to_degrees()],
        "spread_lateral_mm": s.spread[0] * 1e3,
        "spread_depth_mm": s.spread[1] * 1e3,
        "spread_tilt_deg": s.spread[2].to_degrees(),
        "spread_roll_deg": s.spread[3].to_degrees(),
    })
}

pub fn run(opts: &EvalOptions) -> Result<Value, EvalError> {
    let frames = opts.count(4, 30);
    let conditions: Vec<Condition> = RANGES_M
        .iter()
        .flat_map(|&d| {
            YAWS_DEG.iter().map(move |&y| Condition {
                c_per_m: WATER_PER_M,
                distance_m: d,
                yaw_deg: y,
            })
        })
        .collect();
    let records = run_conditions(
        opts,
        &conditions,
        frames,
        &[MarkerMethod::Shoal],
        "fit-noise",
    )?;
    let stats = range_stats(&records, &conditions);
    let fitted = fit(&stats).ok_or_else(|| {
        EvalError::Setup("fit-noise: fewer than two ranges with a located marker".into())
    })?;
    let shipped = NoiseModel::default();
    // The bias (the same on every frame of this seed's camera) apart from
    // the frame-to-frame noise around it: the synthesizer draws the one per
    // camera and the other per frame (`obs_synth::BiasModel`).
    let around: Vec<RangeStats> = stats.iter().map(RangeStats::around_bias).collect();
    let frame_noise = fit(&around);
    let bias = fit_bias(&stats);
    let mut csv = Csv::new(&CSV_COLUMNS);
    crate::outln!(
        "range   located  flips  lateral mm (fit / shipped)   depth mm (fit / shipped)   tilt ° (fit / shipped)   roll ° (fit / shipped)"
    );
    let mut rows = Vec::new();
    for s in &stats {
        let f = predicted(&fitted, s.range_m);
        let d = predicted(&shipped, s.range_m);
        csv.row(vec![
            format!("{:.2}", s.range_m),
            s.frames.to_string(),
            s.located.to_string(),
            s.gross.to_string(),
            cell(Some(s.lateral_m * 1e3)),
            cell(Some(s.depth_m * 1e3)),
            cell(Some(s.tilt_rad.to_degrees())),
            cell(Some(s.roll_rad.to_degrees())),
            cell(Some(f[0] * 1e3)),
            cell(Some(f[1] * 1e3)),
            cell(Some(f[2].to_degrees())),
            cell(Some(f[3].to_degrees())),
            cell(Some(d[0] * 1e3)),
            cell(Some(d[1] * 1e3)),
            cell(Some(d[2].to_degrees())),
            cell(Some(d[3].to_degrees())),
            cell(Some(s.bias[0] * 1e3)),
            cell(Some(s.bias[1] * 1e3)),
            cell(Some(s.bias[2] * 1e3)),
            cell(Some(s.bias[3].to_degrees())),
            cell(Some(s.bias[4].to_degrees())),
            cell(Some(s.bias[5].to_degrees())),
            cell(Some(s.spread[0] * 1e3)),
            cell(Some(s.spread[1] * 1e3)),
            cell(Some(s.spread[2].to_degrees())),
            cell(Some(s.spread[3].to_degrees())),
        ]);
        crate::outln!(
            "{:>4.2} m  {:>3}/{:<3}  {:>4}  {:>6.2} ({:.2} / {:.2})     {:>6.2} ({:.2} / {:.2})     {:>5.3} ({:.3} / {:.3})    {:>5.3} ({:.3} / {:.3})",
            s.range_m,
            s.located,
            s.frames,
            s.gross,
            s.lateral_m * 1e3,
            f[0] * 1e3,
            d[0] * 1e3,
            s.depth_m * 1e3,
            f[1] * 1e3,
            d[1] * 1e3,
            s.tilt_rad.to_degrees(),
            f[2].to_degrees(),
            d[2].to_degrees(),
            s.roll_rad.to_degrees(),
            f[3].to_degrees(),
            d[3].to_degrees(),
        );
        rows.push(range_json(s));
    }
    let frame_noise_json = frame_noise.as_ref().map(model_json);
    let bias_json = bias.map(|b| {
        json!({
            "per_m_mm": b.per_m.map(|v| v * 1e3),
            "rotation_deg": b.rotation_rad.map(f64::to_degrees),
        })
    });
    if let (Some(n), Some(b)) = (&frame_noise, &bias) {
        print_bias_and_noise(b, n);
    }
    csv.write(&opts.out.join("noise.csv"))?;
    let model = json!({
        "fitted": model_json(&fitted),
        "shipped": model_json(&shipped),
        "frame_noise": frame_noise_json,
        "bias": bias_json,
    });
    super::write_json(&opts.out.join("noise-model.json"), &model)?;
    Ok(json!({
        "water_per_m": WATER_PER_M,
        "yaws_deg": YAWS_DEG,
        "frames_per_condition": frames,
        "camera_profile": opts.profile_name(),
        "results": { "ranges": rows },
        "fitted": model_json(&fitted),
        "shipped": model_json(&shipped),
        "frame_noise": frame_noise_json,
        "bias": bias_json,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stats(r: f64, lat: f64, depth: f64, tilt: f64) -> RangeStats {
        RangeStats {
            range_m: r,
            frames: 10,
            located: 10,
            gross: 0,
            lateral_m: lat,
            depth_m: depth,
            tilt_rad: tilt,
            roll_rad: 0.002,
            bias: [0.0; 6],
            spread: [lat, depth, tilt, 0.002],
        }
    }

    #[test]
    fn fit_recovers_the_lines_it_was_given() {
        let truth = NoiseModel {
            translation_std_floor_m: 0.0002,
            lateral_std_per_m: 0.0005,
            depth_std_per_m: 0.003,
            depth_std_per_m2: 0.001,
            tilt_std_rad: 0.001,
            tilt_std_per_m: 0.004,
            roll_std_rad: 0.002,
            depth_std_table: None,
        };
        let s: Vec<RangeStats> = RANGES_M
            .iter()
            .map(|&r| {
                let p = predicted(&truth, r);
                stats(r, p[0], p[1], p[2])
            })
            .collect();
        let f = fit(&s).unwrap();
        assert!((f.translation_std_floor_m - 0.0002).abs() < 1e-9, "{f:?}");
        assert!((f.lateral_std_per_m - 0.0005).abs() < 1e-9, "{f:?}");
        assert!((f.depth_std_per_m - 0.003).abs() < 1e-9, "{f:?}");
        assert!((f.depth_std_per_m2 - 0.001).abs() < 1e-9, "{f:?}");
        assert!((f.tilt_std_per_m - 0.004).abs() < 1e-9, "{f:?}");
        assert!((f.roll_std_rad - 0.002).abs() < 1e-9, "{f:?}");
    }

    #[test]
    fn the_bias_lines_come_from_the_medians_and_the_noise_from_the_spread_around_them() {
        // A camera 1 mm/m off across, 5 mm/m in depth, 0.1° tilted; its
        // frames scattered around that by a model of their own.
        let noise = NoiseModel {
            translation_std_floor_m: 0.0,
            lateral_std_per_m: 0.0002,
            depth_std_per_m: 0.001,
            depth_std_per_m2: 0.0,
            tilt_std_rad: 0.0,
            tilt_std_per_m: 0.002,
            roll_std_rad: 0.001,
            depth_std_table: None,
        };
        let s: Vec<RangeStats> = RANGES_M
            .iter()
            .map(|&r| {
                let p = predicted(&noise, r);
                RangeStats {
                    bias: [
                        0.001 * r,
                        -0.0005 * r,
                        0.005 * r,
                        0.1f64.to_radians(),
                        0.0,
                        0.0,
                    ],
                    spread: p,
                    // The σ around zero holds the bias too: much larger.
                    ..stats(r, 10.0 * p[0], 10.0 * p[1], 10.0 * p[2])
                }
            })
            .collect();
        let b = fit_bias(&s).unwrap();
        assert!((b.per_m[0] - 0.001).abs() < 1e-12, "{b:?}");
        assert!((b.per_m[1] + 0.0005).abs() < 1e-12, "{b:?}");
        assert!((b.per_m[2] - 0.005).abs() < 1e-12, "{b:?}");
        assert!(
            (b.rotation_rad[0] - 0.1f64.to_radians()).abs() < 1e-12,
            "{b:?}"
        );
        let around: Vec<RangeStats> = s.iter().map(RangeStats::around_bias).collect();
        let f = fit(&around).unwrap();
        assert!((f.depth_std_per_m - 0.001).abs() < 1e-9, "{f:?}");
        assert!((f.tilt_std_per_m - 0.002).abs() < 1e-9, "{f:?}");
        // One range left is too few for a line.
        let mut lone = s.clone();
        for r in &mut lone[1..] {
            r.located = 0;
        }
        assert!(fit_bias(&lone).is_none());
    }

    #[test]
    fn ranges_without_enough_good_frames_are_left_out() {
        let mut s = vec![
            stats(1.0, 0.001, 0.002, 0.01),
            stats(2.0, 0.002, 0.004, 0.02),
            stats(3.0, 0.003, 0.006, 0.03),
        ];
        // Nothing located, and mostly flips with wild figures: neither may bend the fit.
        s.push(RangeStats {
            located: 0,
            lateral_m: f64::NAN,
            ..stats(5.0, 0.0, 0.0, 0.0)
        });
        s.push(RangeStats {
            gross: 8,
            ..stats(4.0, 0.5, 0.9, 0.3)
        });
        let f = fit(&s).unwrap();
        assert!((f.lateral_std_per_m - 0.001).abs() < 1e-6, "{f:?}");
        assert!((f.depth_std_per_m - 0.002).abs() < 1e-6, "{f:?}");
        assert!(f.depth_std_per_m2.abs() < 1e-6, "{f:?}");
        assert!(fit(&s[1..]).is_none(), "two good ranges are too few");
    }
}
