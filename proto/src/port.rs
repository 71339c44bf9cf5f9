//! A camera behind a flat window (a "flat port"): the refractive camera
//! model.
//!
//! The lens looks through a plane window perpendicular to its optical axis:
//! air inside, the glass, the water outside. A ray leaving the lens centre
//! refracts twice by Snell's law, at the inner surface (`z = d`, air to
//! glass) and at the outer one (`z = d + t`, glass to water), and continues
//! in the water from a point on the outer surface. The in-water rays do not
//! meet in one point, so no pinhole, however calibrated, reproduces the
//! geometry exactly; `docs/water-model.md` says what an in-water pinhole
//! absorbs and what it cannot.
//!
//! Frame: the camera's (OpenCV optical, z forward); the lens model
//! ([`CameraModel`]) maps pixels to the in-air rays. Because both surfaces
//! are normal to z, every ray stays in the plane of the axis and its first
//! direction, and is described by its radial slope `ρ = tan θ`.

use crate::camera::CameraModel;
use nalgebra::{Point2, Point3, Vector3};
use serde::{Deserialize, Serialize};

/// A flat window in front of the lens, perpendicular to its optical axis.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FlatPort {
    /// From the lens centre (its entrance pupil) to the inner glass surface (m).
    pub distance_m: f64,
    /// Glass thickness (m).
    pub glass_m: f64,
    /// Refractive index of the glass.
    pub n_glass: f64,
    /// Refractive index of the water.
    pub n_water: f64,
}

impl FlatPort {
    /// Cast acrylic (PMMA) at visible wavelengths (1.49 at 589 nm).
    pub const N_ACRYLIC: f64 = 1.49;
    /// Sea water at visible wavelengths (1.34 at 589 nm, 35 PSU, 15 °C; fresh water 1.333).
    pub const N_SEA_WATER: f64 = 1.34;
    /// Largest index accepted: no window material or water comes near it
    /// (sapphire 1.77, diamond 2.42); larger is a typo.
    pub const N_MAX: f64 = 3.0;
    /// Largest port distance or glass thickness accepted (m).
    pub const MAX_M: f64 = 1.0;

    /// Why the port is unusable, or `None`; the message names the field.
    pub fn problem(&self) -> Option<String> {
        for (name, v) in [("distance", self.distance_m), ("glass", self.glass_m)] {
            if !v.is_finite() {
                return Some(format!("port {name} is not finite ({v} m)"));
            }
            if !(0.0..=Self::MAX_M).contains(&v) {
                return Some(format!(
                    "port {name} {:.1} mm is outside 0..={:.0} mm",
                    v * 1e3,
                    Self::MAX_M * 1e3
                ));
            }
        }
        for (name, n) in [("n_glass", self.n_glass), ("n_water", self.n_water)] {
            if !n.is_finite() {
                return Some(format!("port {name} is not finite ({n})"));
            }
            if !(1.0..=Self::N_MAX).contains(&n) {
                return Some(format!(
                    "port {name} {n} is not a refractive index of glass or water (1 ≤ n ≤ {})",
                    Self::N_MAX
                ));
            }
        }
        None
    }

    /// The outer (water-side) surface's depth `d + t` (m).
    pub fn outer_z(&self) -> f64 {
        self.distance_m + self.glass_m
    }

    /// `tan θₙ / tan θ_air` for a ray of in-air slope² `rho2` entering a
    /// medium of index `n` from air, by Snell (`sin θ_air = n sin θₙ`):
    /// `1 / √(n² + (n² − 1) ρ²)`, finite on the axis.
    #[inline]
    fn slope_ratio(n: f64, rho2: f64) -> f64 {
        1.0 / (n * n + (n * n - 1.0) * rho2).sqrt()
    }

    /// The in-water ray of the in-air ray `(x, y, 1)` from the lens centre:
    /// its origin on the outer surface and its slope `(a, b)`, the direction
    /// being `(a, b, 1)` (a ray leaving the lens forward stays forward).
    #[inline]
    pub fn refract(&self, x: f64, y: f64) -> (Vector3<f64>, (f64, f64)) {
        let rho2 = x * x + y * y;
        let through = self.distance_m + self.glass_m * Self::slope_ratio(self.n_glass, rho2);
        let w = Self::slope_ratio(self.n_water, rho2);
        (
            Vector3::new(x * through, y * through, self.outer_z()),
            (x * w, y * w),
        )
    }

    /// The in-water ray through pixel `(u, v)`: origin on the outer surface
    /// and unit direction.
    pub fn ray(&self, cam: &CameraModel, u: f64, v: f64) -> (Point3<f64>, Vector3<f64>) {
        let (x, y) = cam.ray(u, v);
        let (o, (a, b)) = self.refract(x, y);
        (Point3::from(o), Vector3::new(a, b, 1.0).normalize())
    }

    /// The in-air ray `(x, y, 1)` whose in-water continuation passes through
    /// `p` (camera frame); `None` when `p` is not beyond the outer surface or
    /// no ray reaches it (beyond the critical angle of a port with no
    /// distance to the lens).
    ///
    /// In the plane of the axis and `p`, the radial distance the ray of
    /// in-air slope ρ reaches at depth `Z` is
    /// `r(ρ) = ρ [d + t/√(n_g² + (n_g²−1)ρ²) + (Z−d−t)/√(n_w² + (n_w²−1)ρ²)]`,
    /// increasing and concave in ρ with `r(0) = 0`. Newton's method from the
    /// paraxial slope `R / r'(0)` (which lies below the root, since `r` is
    /// concave) climbs monotonically to the root `r(ρ) = R`.
    pub fn air_ray(&self, p: &Point3<f64>) -> Option<(f64, f64)> {
        let (d, t) = (self.distance_m, self.glass_m);
        let l = p.z - self.outer_z();
        // Beyond the outer surface (NaN fails too).
        if l.is_nan() || l <= 0.0 || !p.x.is_finite() || !p.y.is_finite() {
            return None;
        }
        let big_r = p.x.hypot(p.y);
        if big_r == 0.0 {
            return Some((0.0, 0.0));
        }
        let (ng2, nw2) = (self.n_glass * self.n_glass, self.n_water * self.n_water);
        let mut rho = big_r / (d + t / self.n_glass + l / self.n_water);
        for _ in 0..100 {
            let rho2 = rho * rho;
            let (sg, sw) = (
                Self::slope_ratio(self.n_glass, rho2),
                Self::slope_ratio(self.n_water, rho2),
            );
            let r = rho * (d + t * sg + l * sw);
            // d/dρ [ρ / √(n² + (n²−1)ρ²)] = n² / (n² + (n²−1)ρ²)^{3/2} = n² s³.
            let dr = d + t * ng2 * sg * sg * sg + l * nw2 * sw * sw * sw;
            let step = (big_r - r) / dr;
            if !(step.is_finite() && dr > 0.0) {
                return None;
            }
            rho += step;
            if rho > 1e6 {
                return None;
            }
            if step.abs() <= 1e-15 * rho {
                let k = rho / big_r;
                return Some((p.x * k, p.y * k));
            }
        }
        None
    }

    /// Project `p` (camera frame) through the port and the lens to pixel
    /// coordinates; `None` where [`FlatPort::air_ray`] has no ray.
    pub fn project(&self, cam: &CameraModel, p: &Point3<f64>) -> Option<Point2<f64>> {
        let (x, y) = self.air_ray(p)?;
        cam.project(&Point3::new(x, y, 1.0))
    }
}

/// Project through the port when there is one, else the plain lens.
pub fn project(cam: &CameraModel, port: Option<&FlatPort>, p: &Point3<f64>) -> Option<Point2<f64>> {
    match port {
        Some(port) => port.project(cam, p),
        None => cam.project(p),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The evaluation's port: 10 mm from the lens, 8 mm acrylic, sea water.
    fn port() -> FlatPort {
        FlatPort {
            distance_m: 0.010,
            glass_m: 0.008,
            n_glass: FlatPort::N_ACRYLIC,
            n_water: FlatPort::N_SEA_WATER,
        }
    }

    /// `sin θ` of a direction against the z axis.
    fn sin_off_axis(v: &Vector3<f64>) -> f64 {
        v.xy().norm() / v.norm()
    }

    #[test]
    fn snell_holds_at_both_surfaces_and_the_path_is_continuous() {
        let p = port();
        for &(x, y) in &[(0.0, 0.0), (0.3, -0.2), (-0.55, 0.4), (1.5, 2.0)] {
            let air = Vector3::new(x, y, 1.0);
            let (origin, (a, b)) = p.refract(x, y);
            let water = Vector3::new(a, b, 1.0);
            // Inner surface hit, then the glass leg to the outer surface.
            let inner = air * (p.distance_m / air.z);
            let glass = origin - inner;
            assert!((glass.z - p.glass_m).abs() < 1e-15);
            let (sa, sg, sw) = (
                sin_off_axis(&air),
                sin_off_axis(&glass),
                sin_off_axis(&water),
            );
            // 1·sin θa = n_g sin θg = n_w sin θw (f64 rounding: 1e-15 relative).
            assert!((sa - p.n_glass * sg).abs() < 1e-14, "{x},{y}");
            assert!((sa - p.n_water * sw).abs() < 1e-14, "{x},{y}");
            // Each leg stays in the plane of the axis and the first direction.
            for v in [glass, water] {
                assert!((v.x * y - v.y * x).abs() < 1e-14);
            }
        }
    }

    #[test]
    fn projection_and_ray_are_inverse() {
        let cam = CameraModel::vehicle_1440();
        let p = port();
        for &(u, v) in &[(719.5, 539.5), (0.0, 0.0), (1439.0, 1079.0), (100.3, 900.7)] {
            let (o, dir) = p.ray(&cam, u, v);
            for s in [0.05, 0.5, 4.0, 30.0] {
                let q = p.project(&cam, &(o + dir * s)).unwrap();
                assert!(
                    (q.x - u).abs() < 1e-9 && (q.y - v).abs() < 1e-9,
                    "({u}, {v}) at {s} m: {q}"
                );
            }
        }
        // Inside the housing there is nothing to project.
        assert!(p.project(&cam, &Point3::new(0.0, 0.0, 0.015)).is_none());
        // A port of no thickness at the lens is the lens alone in water: the
        // slope shrinks by n_w on the axis.
        let bare = FlatPort {
            distance_m: 0.0,
            glass_m: 0.0,
            ..p
        };
        let (x, _) = bare.air_ray(&Point3::new(1e-6, 0.0, 1.0)).unwrap();
        assert!((x / 1e-6 - bare.n_water).abs() < 1e-9);
        // ... and sees nothing beyond the critical angle (48.3° in sea water).
        assert!(bare.air_ray(&Point3::new(1.2, 0.0, 1.0)).is_none());
    }

    #[test]
    fn bad_ports_are_named() {
        let bad = |f: fn(&mut FlatPort)| {
            let mut p = port();
            f(&mut p);
            p.problem().expect("refused")
        };
        assert_eq!(port().problem(), None);
        assert!(bad(|p| p.distance_m = -0.001).contains("port distance -1.0 mm"));
        assert!(bad(|p| p.glass_m = f64::NAN).contains("glass is not finite"));
        assert!(bad(|p| p.n_glass = 0.9).contains("n_glass 0.9"));
        assert!(bad(|p| p.n_water = 134.0).contains("n_water 134"));
    }
}
