//! Pinhole camera with one of OpenCV's lens models.
//!
//! The models are OpenCV's and ROS `camera_info`'s, by the same names:
//! `plumb_bob` (`cv::projectPoints` with 5 coefficients `k1 k2 p1 p2 k3`),
//! `rational_polynomial` (8 coefficients, `cv::CALIB_RATIONAL_MODEL`) and
//! `equidistant` (`cv::fisheye`, 4 coefficients). A calibration from
//! OpenCV/ROS means the same here, and the simulator renders exactly what the
//! node's PnP assumes. Frame: OpenCV optical (x right, y down, z forward).

use nalgebra::{Point2, Point3};
use serde::{Deserialize, Serialize};

pub use crate::port::FlatPort;

/// A lens model and its coefficients (OpenCV's order).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Distortion {
    /// ROS `plumb_bob`: radial–tangential `k1 k2 p1 p2 k3`.
    PlumbBob([f64; 5]),
    /// ROS `rational_polynomial`: `k1 k2 p1 p2 k3 k4 k5 k6`, the radial factor
    /// `(1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)`.
    Rational([f64; 8]),
    /// ROS `equidistant` (OpenCV `cv::fisheye`): `k1 k2 k3 k4`; a ray at angle
    /// θ off the axis lands at normalized radius `θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)`.
    Equidistant([f64; 4]),
}

/// The lens model names [`Distortion::from_ros`] knows, as ROS spells them.
pub const DISTORTION_MODELS: [&str; 3] = ["plumb_bob", "rational_polynomial", "equidistant"];

impl Distortion {
    /// No distortion (a plumb-bob lens with every coefficient 0).
    pub const NONE: Distortion = Distortion::PlumbBob([0.0; 5]);

    /// The model's name in ROS `camera_info` (`distortion_model`).
    pub fn ros_name(&self) -> &'static str {
        match self {
            Distortion::PlumbBob(_) => "plumb_bob",
            Distortion::Rational(_) => "rational_polynomial",
            Distortion::Equidistant(_) => "equidistant",
        }
    }

    /// The coefficients in OpenCV's order.
    pub fn coefficients(&self) -> &[f64] {
        match self {
            Distortion::PlumbBob(d) => d,
            Distortion::Rational(d) => d,
            Distortion::Equidistant(d) => d,
        }
    }

    /// The model named `model` (ROS spelling; `None`: chosen by the count, as
    /// OpenCV writes them: 4 or 5 plumb-bob, 8 rational) with coefficients
    /// `d`. Terms OpenCV has beyond a model's own (the thin-prism and tilt
    /// terms of a 12- or 14-coefficient list) are accepted only when zero,
    /// never dropped; an unknown model is an error, never read as another.
    pub fn from_ros(model: Option<&str>, d: &[f64]) -> Result<Distortion, String> {
        let model = match model {
            Some(m) => m,
            None if d.len() >= 8 && d[5..8].iter().any(|v| *v != 0.0) => "rational_polynomial",
            None => "plumb_bob",
        };
        let (n, min) = match model {
            "plumb_bob" => (5, 4),
            "rational_polynomial" => (8, 8),
            "equidistant" => (4, 4),
            other => {
                return Err(format!(
                    "distortion model `{other}` is not supported (supported: {})",
                    DISTORTION_MODELS.join(", ")
                ))
            }
        };
        if d.len() < min && !d.is_empty() {
            return Err(format!(
                "{} distortion coefficients; the {model} model has {min}{}",
                d.len(),
                if n > min {
                    format!(" or {n}")
                } else {
                    String::new()
                }
            ));
        }
        if let Some((i, v)) = d.iter().enumerate().skip(n).find(|(_, v)| **v != 0.0) {
            return Err(format!(
                "distortion coefficient {} is {v} (of {}); the {model} model has {n}, and the terms beyond them (thin prism, tilt) are not supported",
                i + 1,
                d.len()
            ));
        }
        let mut out = [0.0; 8];
        for (o, v) in out.iter_mut().zip(d) {
            *o = *v;
        }
        Ok(match model {
            "plumb_bob" => Distortion::PlumbBob([out[0], out[1], out[2], out[3], out[4]]),
            "rational_polynomial" => Distortion::Rational(out),
            _ => Distortion::Equidistant([out[0], out[1], out[2], out[3]]),
        })
    }

    /// Distort normalized undistorted `(x, y)`, with the 2x2 Jacobian
    /// `d(xd, yd) / d(x, y)` (row-major).
    #[inline]
    pub fn apply(&self, x: f64, y: f64) -> (f64, f64, [f64; 4]) {
        match *self {
            Distortion::PlumbBob([k1, k2, p1, p2, k3]) => {
                let r2 = x * x + y * y;
                let rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
                let drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2);
                radial_tangential(x, y, rad, drad, p1, p2)
            }
            Distortion::Rational([k1, k2, p1, p2, k3, k4, k5, k6]) => {
                let r2 = x * x + y * y;
                let num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
                let den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6));
                let dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2);
                let dden = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2);
                let drad = (dnum * den - num * dden) / (den * den);
                radial_tangential(x, y, num / den, drad, p1, p2)
            }
            Distortion::Equidistant([k1, k2, k3, k4]) => {
                let r2 = x * x + y * y;
                // s = θd / r and (ds/dr) / r, by their series near the axis.
                let (s, ds_r) = if r2 < 1e-16 {
                    (1.0 + (k1 - 1.0 / 3.0) * r2, 2.0 * (k1 - 1.0 / 3.0))
                } else {
                    let r = r2.sqrt();
                    let t = r.atan();
                    let t2 = t * t;
                    let poly = 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)));
                    let dpoly =
                        1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + 9.0 * t2 * k4)));
                    let td = t * poly;
                    let dtd_dr = dpoly / (1.0 + r2);
                    (td / r, (dtd_dr * r - td) / (r2 * r))
                };
                (
                    s * x,
                    s * y,
                    [
                        s + ds_r * x * x,
                        ds_r * x * y,
                        ds_r * x * y,
                        s + ds_r * y * y,
                    ],
                )
            }
        }
    }
}

/// The radial–tangential form shared by plumb-bob and rational: `rad` is the
/// radial factor and `drad` its derivative in r².
#[inline]
fn radial_tangential(
    x: f64,
    y: f64,
    rad: f64,
    drad: f64,
    p1: f64,
    p2: f64,
) -> (f64, f64, [f64; 4]) {
    let r2 = x * x + y * y;
    let xd = x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
    let yd = y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
    let j00 = rad + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x;
    let j01 = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y;
    let j10 = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y;
    let j11 = rad + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x;
    (xd, yd, [j00, j01, j10, j11])
}

/// Intrinsics, distortion and resolution of one camera.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CameraModel {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// The lens model and its coefficients.
    pub distortion: Distortion,
}

impl CameraModel {
    /// The paper's Eq. (3)/(4) calibration (an underwater camera, long focal
    /// length). The paper gives no resolution; the principal point
    /// (1239, 1088) implies a sensor of about 2448x2048, which we use.
    pub fn paper_eq3() -> Self {
        Self {
            width: 2448,
            height: 2048,
            fx: 14914.22,
            fy: 14912.74,
            cx: 1239.18,
            cy: 1088.06,
            distortion: Distortion::PlumbBob([0.33049, 4.74831, 0.0, 0.0, 0.0]),
        }
    }

    /// The vehicles' 1440x1080 cameras (paper §6.3). The paper gives no
    /// intrinsics for them; we assume a 60° horizontal field of view, a
    /// centred principal point and mild barrel distortion, typical of the
    /// wide lenses behind flat ports on small AUVs.
    pub fn vehicle_1440() -> Self {
        let fx = 1250.0; // ~60° horizontal field of view
        Self {
            width: 1440,
            height: 1080,
            fx,
            fy: fx,
            cx: 719.5,
            cy: 539.5,
            distortion: Distortion::PlumbBob([-0.05, 0.01, 0.0, 0.0, 0.0]),
        }
    }

    /// Apply distortion to normalized image coordinates `(x/z, y/z)`.
    pub fn distort(&self, xn: f64, yn: f64) -> (f64, f64) {
        let (xd, yd, _) = self.distortion.apply(xn, yn);
        (xd, yd)
    }

    /// Invert [`CameraModel::distort`]. Equidistant: the angle off the axis
    /// by Newton's method in one dimension (as `cv::fisheye::undistortPoints`).
    /// The others: fixed-point iteration (as OpenCV's `undistortPoints`), then
    /// Newton steps from the better of that and the distorted point, so
    /// strong distortion near the image corners (where the fixed point stops
    /// contracting) is inverted too. Accurate to ~1e-12 wherever the model is
    /// one-to-one ([`CameraModel::distortion_fold`] checks the image is).
    pub fn undistort(&self, xd: f64, yd: f64) -> (f64, f64) {
        let residual = |x: f64, y: f64| {
            let (dx, dy) = self.distort(x, y);
            (dx - xd, dy - yd)
        };
        let size = |(a, b): (f64, f64)| a.abs() + b.abs();
        let (mut x, mut y) = match self.distortion {
            Distortion::Equidistant(k) => undistort_equidistant(k, xd, yd),
            _ => self.undistort_fixed_point(xd, yd),
        };
        let fixed = size(residual(x, y));
        let start = size(residual(xd, yd));
        if fixed.is_nan() || fixed >= start {
            (x, y) = (xd, yd);
        }
        for _ in 0..30 {
            let (ex, ey) = residual(x, y);
            if size((ex, ey)) < 1e-15 {
                break;
            }
            let (j00, j01, j10, j11) = self.distortion_jacobian(x, y);
            let det = j00 * j11 - j01 * j10;
            if det.is_nan() || det.abs() <= 1e-300 {
                break;
            }
            let (nx, ny) = (
                x - (j11 * ex - j01 * ey) / det,
                y - (-j10 * ex + j00 * ey) / det,
            );
            if !(nx.is_finite() && ny.is_finite()) {
                break;
            }
            (x, y) = (nx, ny);
        }
        (x, y)
    }

    /// OpenCV's fixed point for the radial–tangential models:
    /// `x = (xd − tangential(x)) / radial(x)`.
    fn undistort_fixed_point(&self, xd: f64, yd: f64) -> (f64, f64) {
        let d = self.distortion.coefficients();
        let (p1, p2) = (d[2], d[3]);
        let (mut x, mut y) = (xd, yd);
        for _ in 0..20 {
            let r2 = x * x + y * y;
            let radial = self.radial_factor(r2);
            let dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
            let dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
            let nx = (xd - dx) / radial;
            let ny = (yd - dy) / radial;
            let done = (nx - x).abs() + (ny - y).abs() < 1e-15;
            x = nx;
            y = ny;
            if done || !(x.is_finite() && y.is_finite()) {
                break;
            }
        }
        (x, y)
    }

    /// The radial factor at squared radius `r2` of the radial–tangential models.
    fn radial_factor(&self, r2: f64) -> f64 {
        match self.distortion {
            Distortion::PlumbBob([k1, k2, _, _, k3]) => 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)),
            Distortion::Rational([k1, k2, _, _, k3, k4, k5, k6]) => {
                (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
            }
            Distortion::Equidistant(_) => 1.0,
        }
    }

    /// Project a point in the camera frame to pixel coordinates; `None`
    /// behind the camera. Pixel centres are at integer coordinates (OpenCV).
    pub fn project(&self, p: &Point3<f64>) -> Option<Point2<f64>> {
        if p.z <= 1e-9 {
            return None;
        }
        let (xd, yd) = self.distort(p.x / p.z, p.y / p.z);
        Some(Point2::new(self.fx * xd + self.cx, self.fy * yd + self.cy))
    }

    /// The normalized, undistorted viewing ray `(x, y, 1)` through a pixel.
    pub fn ray(&self, u: f64, v: f64) -> (f64, f64) {
        self.undistort((u - self.cx) / self.fx, (v - self.cy) / self.fy)
    }

    /// A short description of why the model is unusable, or `None`: its
    /// parameters ([`CameraModel::parameter_problem`]) and its lens over the
    /// image ([`CameraModel::distortion_fold`], a walk of a few thousand
    /// evaluations). For where a calibration enters: loading, the command
    /// line, the wire.
    pub fn problem(&self) -> Option<String> {
        self.parameter_problem().or_else(|| self.distortion_fold())
    }

    /// [`CameraModel::problem`] without the lens walk: resolution, finite
    /// values, positive focal lengths. For hot paths handed a camera that was
    /// checked where it entered (one PnP per detection).
    pub fn parameter_problem(&self) -> Option<String> {
        if self.width == 0 || self.height == 0 || self.width > 16384 || self.height > 16384 {
            return Some(format!(
                "resolution {}x{} is outside 1..=16384",
                self.width, self.height
            ));
        }
        let all = [self.fx, self.fy, self.cx, self.cy];
        if !all
            .iter()
            .chain(self.distortion.coefficients())
            .all(|v| v.is_finite())
        {
            return Some("a parameter is not finite".into());
        }
        if self.fx <= 0.0 || self.fy <= 0.0 {
            return Some(format!(
                "focal lengths must be positive (fx={}, fy={})",
                self.fx, self.fy
            ));
        }
        None
    }

    /// Why the lens model is not one-to-one over the image, or `None`.
    ///
    /// Walking out from the principal point towards each corner and edge
    /// midpoint, the distorted point must keep moving outwards (positive
    /// Jacobian determinant and radial progress) until it leaves the image.
    /// A model that folds back inside the image (absurd or mistyped
    /// coefficients) maps two directions to one pixel: PnP through it gives
    /// poses kilometres away, so it is refused. A ray must leave the image
    /// within 85° of the axis (`tan 85° ≈ 11.4`): a lens seeing further is no
    /// pinhole-and-polynomial lens.
    pub fn distortion_fold(&self) -> Option<String> {
        const R_MAX: f64 = 11.4;
        let (w, h) = (f64::from(self.width) - 0.5, f64::from(self.height) - 0.5);
        let targets = [
            ("top-left corner", -0.5, -0.5),
            ("top-right corner", w, -0.5),
            ("bottom-left corner", -0.5, h),
            ("bottom-right corner", w, h),
            ("top edge", self.cx, -0.5),
            ("bottom edge", self.cx, h),
            ("left edge", -0.5, self.cy),
            ("right edge", w, self.cy),
        ];
        let inside = |u: f64, v: f64| (-0.5..=w).contains(&u) && (-0.5..=h).contains(&v);
        for (towards, tu, tv) in targets {
            let (dx, dy) = ((tu - self.cx) / self.fx, (tv - self.cy) / self.fy);
            let len = dx.hypot(dy);
            if len < 1e-12 {
                continue;
            }
            let (ux, uy) = (dx / len, dy / len);
            let mut prev_along = 0.0;
            let mut left = false;
            // Steps of 1 % of the undistorted distance to the target, growing
            // by 1 % per step beyond it (a few hundred evaluations per ray).
            let mut r = 0.0;
            while r < R_MAX {
                r += (len / 100.0).max(r * 0.01);
                let (x, y) = (r * ux, r * uy);
                let (xd, yd) = self.distort(x, y);
                let along = xd * ux + yd * uy;
                let (j00, j01, j10, j11) = self.distortion_jacobian(x, y);
                if along <= prev_along || j00 * j11 - j01 * j10 <= 0.0 {
                    return Some(format!(
                        "the lens distortion {:?} folds back {:.0}° off axis, inside the {}x{} image (towards its {towards}): not a valid calibration for this resolution",
                        self.distortion,
                        r.atan().to_degrees(),
                        self.width,
                        self.height
                    ));
                }
                let (xu, yu) = self.undistort(xd, yd);
                if (xu - x).hypot(yu - y) > 1e-6 * (1.0 + r) {
                    return Some(format!(
                        "the lens distortion {:?} is too strong to invert {:.0}° off axis, inside the {}x{} image (towards its {towards}): not a valid calibration for this resolution",
                        self.distortion,
                        r.atan().to_degrees(),
                        self.width,
                        self.height
                    ));
                }
                prev_along = along;
                if !inside(self.fx * xd + self.cx, self.fy * yd + self.cy) {
                    left = true;
                    break;
                }
            }
            // A fisheye lens may see beyond 85°; a polynomial one may not.
            if !left && !matches!(self.distortion, Distortion::Equidistant(_)) {
                return Some(format!(
                    "with distortion {:?} a ray 85° off axis still lands inside the {}x{} image (towards its {towards}): not a pinhole lens",
                    self.distortion, self.width, self.height
                ));
            }
        }
        None
    }

    /// `d(xd, yd) / d(x, y)` of [`CameraModel::distort`] (row-major).
    fn distortion_jacobian(&self, x: f64, y: f64) -> (f64, f64, f64, f64) {
        let (_, _, [j00, j01, j10, j11]) = self.distortion.apply(x, y);
        (j00, j01, j10, j11)
    }

    /// This calibration for frames of `width` x `height`: itself when the
    /// sizes match; scaled when the frames are the calibrated sensor
    /// resized by one factor (a binned or downscaled stream, aspect equal
    /// within 0.2 %); an error naming both sizes otherwise (a calibration
    /// of another camera or a cropped stream would give wrong poses).
    pub fn for_frame(&self, width: u32, height: u32) -> Result<FrameCamera, String> {
        if (width, height) == (self.width, self.height) {
            return Ok(FrameCamera::Same(*self));
        }
        let sx = f64::from(width) / f64::from(self.width);
        let sy = f64::from(height) / f64::from(self.height);
        if (sx / sy - 1.0).abs() > 2e-3 {
            return Err(format!(
                "the frame is {width}x{height} but the calibration is for {}x{} (another aspect ratio: another camera or a cropped stream, so poses would be wrong)",
                self.width, self.height
            ));
        }
        // Pixel centres at integers: x' = (x + 0.5) s - 0.5.
        let scaled = CameraModel {
            width,
            height,
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: (self.cx + 0.5) * sx - 0.5,
            cy: (self.cy + 0.5) * sy - 0.5,
            distortion: self.distortion,
        };
        Ok(FrameCamera::Scaled {
            camera: scaled,
            scale: sx,
            from: (self.width, self.height),
        })
    }
}

/// The normalized undistorted point of an equidistant (fisheye) lens: the
/// angle θ with `θ (1 + k1 θ² + …) = θd` by Newton's method, then `r = tan θ`.
fn undistort_equidistant(k: [f64; 4], xd: f64, yd: f64) -> (f64, f64) {
    let [k1, k2, k3, k4] = k;
    let td = xd.hypot(yd);
    if td < 1e-15 {
        return (xd, yd);
    }
    let mut t = td.min(std::f64::consts::FRAC_PI_2 - 1e-9);
    for _ in 0..20 {
        let t2 = t * t;
        let f = t * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - td;
        let df = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + 9.0 * t2 * k4)));
        if !(df.is_finite() && df.abs() > 1e-300) {
            break;
        }
        let step = f / df;
        t = (t - step).clamp(0.0, std::f64::consts::FRAC_PI_2 - 1e-9);
        if step.abs() < 1e-15 {
            break;
        }
    }
    let scale = t.tan() / td;
    (xd * scale, yd * scale)
}

/// How uncertain a camera's calibration is (one standard deviation each,
/// independent): what a lab's calibration report states, or what a
/// deployment assumes. The node's PnP adds the pose error this causes to its
/// covariance (`shoal_node::pose::calibration_covariance`): an error of the
/// intrinsics is systematic (the same for every corner of a frame), which
/// the corner noise does not describe.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationSigma {
    /// Relative error of fx and of fy (0.0017 = 0.17 %), each.
    pub focal_rel: f64,
    /// Error of cx and of cy (px), each.
    pub principal_px: f64,
    /// Error of the first radial (or fisheye) coefficient k1.
    #[serde(default)]
    pub k1: f64,
}

impl CalibrationSigma {
    /// What is wrong with it, if anything (each term finite, ≥ 0).
    pub fn problem(&self) -> Option<String> {
        let ok = |v: f64| v.is_finite() && v >= 0.0;
        (!(ok(self.focal_rel) && ok(self.principal_px) && ok(self.k1))).then(|| {
            format!(
                "calibration sigma must be finite and non-negative (focal_rel {}, principal_px {}, k1 {})",
                self.focal_rel, self.principal_px, self.k1
            )
        })
    }

    /// Every term times `k`.
    pub fn scaled(&self, k: f64) -> CalibrationSigma {
        CalibrationSigma {
            focal_rel: self.focal_rel * k,
            principal_px: self.principal_px * k,
            k1: self.k1 * k,
        }
    }
}

/// A calibration made fit for a frame by [`CameraModel::for_frame`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FrameCamera {
    /// The frame has the calibrated size.
    Same(CameraModel),
    /// The frame is the calibrated sensor resized by `scale`.
    Scaled {
        camera: CameraModel,
        scale: f64,
        from: (u32, u32),
    },
}

impl FrameCamera {
    pub fn camera(&self) -> &CameraModel {
        match self {
            FrameCamera::Same(c) | FrameCamera::Scaled { camera: c, .. } => c,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_cameras_do_not_fold_and_absurd_distortion_does() {
        assert_eq!(CameraModel::vehicle_1440().problem(), None);
        assert_eq!(CameraModel::paper_eq3().problem(), None);
        // Strong barrel that folds inside the frame: r(1 - 2 r^2) peaks at r = 0.41,
        // while the 1440x1080 corner is at r = 0.72.
        let mut cam = CameraModel::vehicle_1440();
        cam.distortion = Distortion::PlumbBob([-2.0, 0.0, 0.0, 0.0, 0.0]);
        let why = cam.problem().expect("folds");
        assert!(why.contains("folds back"), "{why}");
        // The same coefficient on a narrow lens (corner at r = 0.11) does not fold there.
        let mut narrow = CameraModel::paper_eq3();
        narrow.distortion = Distortion::PlumbBob([-2.0, 0.0, 0.0, 0.0, 0.0]);
        assert_eq!(narrow.problem(), None);
        // Pincushion so strong the image is never left: still one-to-one, refused as no pinhole lens
        // only when the rays stay inside; a moderate one is fine.
        let mut pin = CameraModel::vehicle_1440();
        pin.distortion = Distortion::PlumbBob([0.3, 0.1, 0.0, 0.0, 0.0]);
        assert_eq!(pin.problem(), None);
        // A mistyped tangential term (0.5 for 0.0005) folds too.
        let mut tang = CameraModel::vehicle_1440();
        tang.distortion = Distortion::PlumbBob([-0.05, 0.01, 0.5, 0.0, 0.0]);
        assert!(tang.problem().is_some());
    }

    #[test]
    fn a_calibration_fits_its_own_size_a_resized_stream_and_nothing_else() {
        let cam = CameraModel::paper_eq3();
        assert_eq!(cam.for_frame(2448, 2048), Ok(FrameCamera::Same(cam)));
        let half = cam.for_frame(1224, 1024).unwrap();
        let c = half.camera();
        assert!((c.fx - cam.fx / 2.0).abs() < 1e-9);
        assert!((c.cx - ((cam.cx + 0.5) / 2.0 - 0.5)).abs() < 1e-9);
        // A point projects to the same place, halved in pixel-edge coordinates.
        let p = Point3::new(0.1, -0.05, 2.0);
        let (a, b) = (cam.project(&p).unwrap(), c.project(&p).unwrap());
        assert!(((a.x + 0.5) / 2.0 - 0.5 - b.x).abs() < 1e-9);
        assert!(((a.y + 0.5) / 2.0 - 0.5 - b.y).abs() < 1e-9);
        let e = cam.for_frame(1440, 1080).unwrap_err();
        assert!(e.contains("1440x1080") && e.contains("2448x2048"), "{e}");
    }

    #[test]
    fn undistort_inverts_distort() {
        let cam = CameraModel::vehicle_1440();
        for &(x, y) in &[(0.0, 0.0), (0.5, -0.3), (-0.9, 0.7)] {
            let (xd, yd) = cam.distort(x, y);
            let (xu, yu) = cam.undistort(xd, yd);
            assert!((xu - x).abs() < 1e-10 && (yu - y).abs() < 1e-10);
        }
    }

    /// A fisheye seeing ~76° off axis in the image corners (coefficients of
    /// the order OpenCV's fisheye calibration gives), and a rational lens.
    pub(crate) fn fisheye() -> CameraModel {
        CameraModel {
            width: 1280,
            height: 960,
            fx: 600.0,
            fy: 600.0,
            cx: 639.5,
            cy: 479.5,
            distortion: Distortion::Equidistant([-0.012, 0.006, -0.004, 0.0008]),
        }
    }

    fn rational() -> CameraModel {
        CameraModel {
            distortion: Distortion::Rational([0.9, -0.2, 0.001, -0.0005, 0.01, 1.2, 0.05, 0.002]),
            ..CameraModel::vehicle_1440()
        }
    }

    #[test]
    fn every_model_inverts_and_its_jacobian_is_its_derivative() {
        for cam in [CameraModel::vehicle_1440(), fisheye(), rational()] {
            assert_eq!(cam.problem(), None, "{:?}", cam.distortion);
            let far = match cam.distortion {
                Distortion::Equidistant(_) => (1.5, 2.0),
                _ => (0.4, -0.3),
            };
            for &(x, y) in &[(0.0, 0.0), (1e-9, 2e-9), (0.3, -0.2), (-0.5, 0.35), far] {
                let (xd, yd) = cam.distort(x, y);
                let (xu, yu) = cam.undistort(xd, yd);
                assert!(
                    (xu - x).abs() < 1e-9 && (yu - y).abs() < 1e-9,
                    "{:?} at ({x}, {y}): ({xu}, {yu})",
                    cam.distortion
                );
                let h = 1e-6;
                let (_, _, j) = cam.distortion.apply(x, y);
                let (ax, ay) = cam.distort(x + h, y);
                let (bx, by) = cam.distort(x - h, y);
                let (cx, cy) = cam.distort(x, y + h);
                let (dx, dy) = cam.distort(x, y - h);
                let num = [
                    (ax - bx) / (2.0 * h),
                    (cx - dx) / (2.0 * h),
                    (ay - by) / (2.0 * h),
                    (cy - dy) / (2.0 * h),
                ];
                for (a, b) in j.iter().zip(num) {
                    assert!(
                        (a - b).abs() < 1e-6,
                        "{:?} at ({x}, {y}): {j:?} vs {num:?}",
                        cam.distortion
                    );
                }
            }
        }
    }

    #[test]
    fn the_fisheye_model_is_opencvs_equidistant() {
        // cv::fisheye::projectPoints: θ = atan r, θd = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸), x' = θd / r · x.
        let cam = fisheye();
        let p = Point3::new(1.0, -0.5, 0.4);
        let (a, b): (f64, f64) = (p.x / p.z, p.y / p.z);
        let r = a.hypot(b);
        let t = r.atan();
        let td = t
            * (1.0 - 0.012 * t.powi(2) + 0.006 * t.powi(4) - 0.004 * t.powi(6)
                + 0.0008 * t.powi(8));
        let q = cam.project(&p).unwrap();
        assert!((q.x - (600.0 * td / r * a + 639.5)).abs() < 1e-9);
        assert!((q.y - (600.0 * td / r * b + 479.5)).abs() < 1e-9);
        // A lens seeing 85° off axis inside its image is a fisheye, not a polynomial lens.
        let wide = CameraModel {
            fx: 60.0,
            fy: 60.0,
            ..cam
        };
        assert_eq!(wide.problem(), None);
        let pinhole = CameraModel {
            distortion: Distortion::NONE,
            ..wide
        };
        assert!(pinhole.problem().unwrap().contains("not a pinhole lens"));
    }

    #[test]
    fn models_come_by_their_ros_names_and_nothing_is_read_as_another() {
        let d = Distortion::from_ros(Some("equidistant"), &[0.1, 0.01, 0.0, 0.0]).unwrap();
        assert_eq!(d, Distortion::Equidistant([0.1, 0.01, 0.0, 0.0]));
        assert_eq!(d.ros_name(), "equidistant");
        let r = Distortion::from_ros(None, &[0.1, 0.0, 0.0, 0.0, 0.0, 0.2, 0.0, 0.0]).unwrap();
        assert!(matches!(r, Distortion::Rational(_)));
        let p = Distortion::from_ros(None, &[0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]).unwrap();
        assert_eq!(p, Distortion::PlumbBob([0.1, 0.0, 0.0, 0.0, 0.0]));
        let e = Distortion::from_ros(Some("kannala_brandt"), &[0.0; 4]).unwrap_err();
        assert!(
            e.contains("kannala_brandt") && e.contains("equidistant"),
            "{e}"
        );
        let e =
            Distortion::from_ros(Some("plumb_bob"), &[0.1, 0.0, 0.0, 0.0, 0.0, 0.3]).unwrap_err();
        assert!(e.contains("coefficient 6"), "{e}");
        let e = Distortion::from_ros(Some("equidistant"), &[0.1, 0.0]).unwrap_err();
        assert!(e.contains("2 distortion coefficients"), "{e}");
        let e = Distortion::from_ros(
            Some("rational_polynomial"),
            &[0.1, 0.0, 0.0, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5],
        )
        .unwrap_err();
        assert!(e.contains("coefficient 12"), "{e}");
    }

    #[test]
    fn principal_point_projects_to_centre() {
        let cam = CameraModel::paper_eq3();
        let p = cam.project(&Point3::new(0.0, 0.0, 1.0)).unwrap();
        assert!((p.x - cam.cx).abs() < 1e-12 && (p.y - cam.cy).abs() < 1e-12);
        assert!(cam.project(&Point3::new(0.0, 0.0, -1.0)).is_none());
    }
}
