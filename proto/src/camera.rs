//! Pinhole camera with OpenCV's radial–tangential lens distortion.
//!
//! The model is OpenCV's (`cv::projectPoints` with 5 coefficients
//! `k1 k2 p1 p2 k3`), so calibrations from OpenCV/ROS mean the same here, and
//! the simulator renders exactly what the node's PnP assumes.
//! Frame: OpenCV optical (x right, y down, z forward).

use nalgebra::{Point2, Point3};
use serde::{Deserialize, Serialize};

/// Intrinsics, distortion and resolution of one camera.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CameraModel {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// `k1 k2 p1 p2 k3` (OpenCV order).
    pub distortion: [f64; 5],
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
            distortion: [0.33049, 4.74831, 0.0, 0.0, 0.0],
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
            distortion: [-0.05, 0.01, 0.0, 0.0, 0.0],
        }
    }

    /// Apply distortion to normalized image coordinates `(x/z, y/z)`.
    pub fn distort(&self, xn: f64, yn: f64) -> (f64, f64) {
        let [k1, k2, p1, p2, k3] = self.distortion;
        let r2 = xn * xn + yn * yn;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn);
        let yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn;
        (xd, yd)
    }

    /// Invert [`CameraModel::distort`] by fixed-point iteration (as OpenCV's
    /// `undistortPoints`); accurate to ~1e-12 for the moderate distortions used here.
    pub fn undistort(&self, xd: f64, yd: f64) -> (f64, f64) {
        let [k1, k2, p1, p2, k3] = self.distortion;
        let (mut x, mut y) = (xd, yd);
        for _ in 0..50 {
            let r2 = x * x + y * y;
            let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            let dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
            let dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
            let nx = (xd - dx) / radial;
            let ny = (yd - dy) / radial;
            let done = (nx - x).abs() + (ny - y).abs() < 1e-15;
            x = nx;
            y = ny;
            if done {
                break;
            }
        }
        (x, y)
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

    /// A short description of why the model is unusable, or `None`.
    pub fn problem(&self) -> Option<String> {
        if self.width == 0 || self.height == 0 || self.width > 16384 || self.height > 16384 {
            return Some(format!(
                "resolution {}x{} is outside 1..=16384",
                self.width, self.height
            ));
        }
        let all = [self.fx, self.fy, self.cx, self.cy];
        if !all
            .iter()
            .chain(self.distortion.iter())
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
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn undistort_inverts_distort() {
        let cam = CameraModel::vehicle_1440();
        for &(x, y) in &[(0.0, 0.0), (0.5, -0.3), (-0.9, 0.7)] {
            let (xd, yd) = cam.distort(x, y);
            let (xu, yu) = cam.undistort(xd, yd);
            assert!((xu - x).abs() < 1e-10 && (yu - y).abs() < 1e-10);
        }
    }

    #[test]
    fn principal_point_projects_to_centre() {
        let cam = CameraModel::paper_eq3();
        let p = cam.project(&Point3::new(0.0, 0.0, 1.0)).unwrap();
        assert!((p.x - cam.cx).abs() < 1e-12 && (p.y - cam.cy).abs() < 1e-12);
        assert!(cam.project(&Point3::new(0.0, 0.0, -1.0)).is_none());
    }
}
