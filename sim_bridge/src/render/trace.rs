//! Ray casting in the camera frame: exact inverse lens distortion per
//! sample, refraction through the flat port when there is one, and ray
//! intersections with marker plates and hull cylinders.
//!
//! A sample ray is given by its in-air direction `(x, y, 1)` from the lens
//! centre. Without a port that is the ray; with one ([`Objects::port`]) it
//! continues in the water from a point `o` on the port's outer surface
//! along `(a, b, 1)` (`FlatPort::refract`), and a hit's `t` is measured
//! along z from `o`.

use nalgebra::{Isometry3, Point3, Vector3};
use shoal_proto::{CameraModel, FlatPort};

/// Albedos of the printed marker and the vehicles (clean radiance is
/// `albedo · shading`, see `docs/water-model.md`).
pub const ALBEDO_WHITE: f64 = 0.90;
pub const ALBEDO_BLACK: f64 = 0.04;
pub const ALBEDO_PLATE_BACK: f64 = 0.35;
pub const ALBEDO_HULL: f64 = 0.55;

/// Lambertian shading by the downwelling ambient light: a surface facing up
/// gets 1, a vertical one 0.75, one facing down 0.5.
pub fn ambient_shading(normal: &Vector3<f64>, up: &Vector3<f64>) -> f64 {
    0.75 + 0.25 * normal.dot(up)
}

/// The viewing ray `(x, y, 1)` through pixel `(u, v)` by Newton's method from
/// `guess` (a nearby pixel's ray): exact to ~1e-13 in normalized units.
#[inline]
pub fn ray_from(cam: &CameraModel, u: f64, v: f64, guess: (f64, f64)) -> (f64, f64) {
    let tx = (u - cam.cx) / cam.fx;
    let ty = (v - cam.cy) / cam.fy;
    let (mut x, mut y) = guess;
    for _ in 0..8 {
        let (xd, yd, j) = cam.distortion.apply(x, y);
        let (ex, ey) = (tx - xd, ty - yd);
        if ex.abs() + ey.abs() < 1e-13 {
            break;
        }
        let det = j[0] * j[3] - j[1] * j[2];
        if det.abs() < 1e-12 {
            return cam.undistort(tx, ty);
        }
        x += (j[3] * ex - j[1] * ey) / det;
        y += (-j[2] * ex + j[0] * ey) / det;
    }
    (x, y)
}

/// [`ray_from`] from a guess already within ~1e-8 of the ray (normalized
/// units), such as the bilinear blend of the pixel's exact corner rays:
/// Newton converges quadratically, so one step lands within rounding of
/// the solution and the convergence check is skipped.
#[inline]
pub fn ray_near(cam: &CameraModel, u: f64, v: f64, guess: (f64, f64)) -> (f64, f64) {
    let tx = (u - cam.cx) / cam.fx;
    let ty = (v - cam.cy) / cam.fy;
    let (x, y) = guess;
    let (xd, yd, j) = cam.distortion.apply(x, y);
    let (ex, ey) = (tx - xd, ty - yd);
    let det = j[0] * j[3] - j[1] * j[2];
    if det.abs() < 1e-12 || ex.abs() + ey.abs() > 1e-6 {
        return ray_from(cam, u, v, guess);
    }
    (
        x + (j[3] * ex - j[1] * ey) / det,
        y + (-j[2] * ex + j[0] * ey) / det,
    )
}

/// What a sample ray hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Ray parameter along the in-water `(a, b, 1)`: the hit's depth `z`
    /// beyond the ray's origin (the lens centre without a port).
    pub t: f64,
    /// Path length in the water from the ray's origin to the hit (m).
    pub range: f64,
    /// Index into the traced objects (plates first, then hulls).
    pub object: u32,
    /// Which uniform patch: for plates the module index `row·(m+2)+col` in
    /// the grid including the quiet zone (`(m+2)²` for the back), for hulls 0.
    pub patch: u32,
    /// Plate coordinates of the hit (m, marker frame x and y); 0 for hulls.
    pub plane: (f64, f64),
    /// Clean radiance under the ambient light (albedo · shading), 0..1.
    pub radiance: f64,
    /// `albedo · max(0, cos incidence)` for a lamp at the camera.
    pub lamp_geom: f64,
}

/// A marker on its plate (the printed square plus its one-module white quiet
/// zone), in the camera frame.
#[derive(Debug, Clone)]
pub struct Plate {
    pub origin: Vector3<f64>,
    pub ex: Vector3<f64>,
    pub ey: Vector3<f64>,
    pub normal: Vector3<f64>,
    /// Modules across the black square.
    pub modules: usize,
    pub module_m: f64,
    /// Half side of the plate (black square plus quiet zone).
    pub half_m: f64,
    /// Module grid across the black square, row-major from the top-left, true = white.
    pub grid: Vec<bool>,
    /// Ambient shading of the face (constant over a plane).
    pub shade: f64,
}

/// A hull: a closed cylinder, in the camera frame.
#[derive(Debug, Clone)]
pub struct Hull {
    pub center: Vector3<f64>,
    pub axis: Vector3<f64>,
    pub radius: f64,
    pub half_len: f64,
}

/// Everything a ray can hit, in the camera frame.
#[derive(Debug, Clone, Default)]
pub struct Objects {
    pub plates: Vec<Plate>,
    pub hulls: Vec<Hull>,
    /// The world's up direction in the camera frame.
    pub up: Vector3<f64>,
    /// The flat port the camera looks through, if any.
    pub port: Option<FlatPort>,
}

/// Hits closer than this (m along z) are ignored: cameras sit on hull surfaces.
const NEAR_M: f64 = 1e-4;

impl Plate {
    pub fn new(
        camera_from_marker: &Isometry3<f64>,
        modules: usize,
        side_m: f64,
        grid: Vec<bool>,
        up: &Vector3<f64>,
    ) -> Plate {
        let r = camera_from_marker.rotation;
        let normal = r * Vector3::z();
        let module_m = side_m / modules as f64;
        Plate {
            origin: camera_from_marker.translation.vector,
            ex: r * Vector3::x(),
            ey: r * Vector3::y(),
            normal,
            modules,
            module_m,
            half_m: 0.5 * side_m + module_m,
            grid,
            shade: ambient_shading(&normal, up),
        }
    }

    /// The module colour at plate coordinates (col, row) counted from the
    /// plate's top-left quiet-zone module: `None` off the plate.
    #[inline]
    fn white_at(&self, col: i64, row: i64) -> Option<bool> {
        let m = self.modules as i64;
        if col < 0 || row < 0 || col > m + 1 || row > m + 1 {
            return None;
        }
        if col == 0 || row == 0 || col == m + 1 || row == m + 1 {
            return Some(true);
        }
        Some(self.grid[((row - 1) * m + (col - 1)) as usize])
    }

    /// Whether all modules in the inclusive plate-index rectangle share one colour.
    pub fn uniform(&self, c0: i64, c1: i64, r0: i64, r1: i64) -> bool {
        let first = self.white_at(c0, r0);
        if first.is_none() {
            return false;
        }
        for r in r0..=r1 {
            for c in c0..=c1 {
                if self.white_at(c, r) != first {
                    return false;
                }
            }
        }
        true
    }

    /// Fraction of the convex quadrilateral `quad` (plate coordinates, the
    /// footprint of a pixel whose corners all hit this plate's face) that is
    /// white: exact area coverage over the modules in the inclusive index
    /// rectangle `c0..=c1` x `r0..=r1`. `None` for a degenerate footprint.
    pub fn white_coverage(
        &self,
        quad: &[(f64, f64); 4],
        c0: i64,
        c1: i64,
        r0: i64,
        r1: i64,
    ) -> Option<f64> {
        let total = polygon_area(quad);
        if total.is_nan() || total <= 0.0 {
            return None;
        }
        let (mut white, mut covered) = (0.0, 0.0);
        let mut poly = Vec::with_capacity(8);
        let mut tmp = Vec::with_capacity(8);
        for r in r0..=r1 {
            for c in c0..=c1 {
                let is_white = self.white_at(c, r)?;
                let xlo = -self.half_m + c as f64 * self.module_m;
                let yhi = self.half_m - r as f64 * self.module_m;
                poly.clear();
                poly.extend_from_slice(quad);
                clip(&mut poly, &mut tmp, |p| p.0 - xlo);
                clip(&mut poly, &mut tmp, |p| xlo + self.module_m - p.0);
                clip(&mut poly, &mut tmp, |p| yhi - p.1);
                clip(&mut poly, &mut tmp, |p| p.1 - (yhi - self.module_m));
                let a = polygon_area(&poly);
                covered += a;
                if is_white {
                    white += a;
                }
            }
        }
        // The cells must tile the footprint (else it left the plate).
        ((covered - total).abs() <= 1e-6 * total).then_some(white / total)
    }

    /// Plate module index (col, row) encoded in a patch id.
    pub fn decode_patch(&self, patch: u32) -> (i64, i64) {
        let w = self.modules as u32 + 2;
        ((patch % w) as i64, (patch / w) as i64)
    }

    #[inline]
    #[allow(clippy::type_complexity)]
    fn intersect(
        &self,
        o: &Vector3<f64>,
        x: f64,
        y: f64,
        t_max: f64,
    ) -> Option<(f64, u32, f64, f64, (f64, f64))> {
        let d = Vector3::new(x, y, 1.0);
        let denom = self.normal.dot(&d);
        if denom.abs() < 1e-15 {
            return None;
        }
        // The plate's origin from the ray's (exactly `self.origin` when `o` is 0).
        let from_o = self.origin - o;
        let t = self.normal.dot(&from_o) / denom;
        if !(t > NEAR_M && t < t_max) {
            return None;
        }
        let rel = d * t - from_o;
        let px = rel.dot(&self.ex);
        let py = rel.dot(&self.ey);
        if px.abs() > self.half_m || py.abs() > self.half_m {
            return None;
        }
        let front = denom < 0.0;
        let w = self.modules as i64 + 2;
        let col = (((px + self.half_m) / self.module_m).floor() as i64).clamp(0, w - 1);
        let row = (((self.half_m - py) / self.module_m).floor() as i64).clamp(0, w - 1);
        let cos_i = (denom.abs() / d.norm()).min(1.0);
        if front {
            let white = self.white_at(col, row).unwrap_or(true);
            let albedo = if white { ALBEDO_WHITE } else { ALBEDO_BLACK };
            Some((
                t,
                (row * w + col) as u32,
                albedo * self.shade,
                albedo * cos_i,
                (px, py),
            ))
        } else {
            // The back of the plate: one uniform patch id past the grid.
            let back_shade = 0.75 - (self.shade - 0.75);
            Some((
                t,
                (w * w) as u32,
                ALBEDO_PLATE_BACK * back_shade,
                ALBEDO_PLATE_BACK * cos_i,
                (px, py),
            ))
        }
    }
}

/// Area of a simple polygon (absolute, shoelace).
fn polygon_area(p: &[(f64, f64)]) -> f64 {
    let n = p.len();
    if n < 3 {
        return 0.0;
    }
    let mut a = 0.0;
    for i in 0..n {
        let (x0, y0) = p[i];
        let (x1, y1) = p[(i + 1) % n];
        a += x0 * y1 - x1 * y0;
    }
    0.5 * a.abs()
}

/// Sutherland–Hodgman: keep the part of `poly` where `inside(p) ≥ 0` (a half-plane).
fn clip(
    poly: &mut Vec<(f64, f64)>,
    tmp: &mut Vec<(f64, f64)>,
    inside: impl Fn(&(f64, f64)) -> f64,
) {
    tmp.clear();
    let n = poly.len();
    for i in 0..n {
        let (a, b) = (poly[i], poly[(i + 1) % n]);
        let (da, db) = (inside(&a), inside(&b));
        if da >= 0.0 {
            tmp.push(a);
        }
        if (da >= 0.0) != (db >= 0.0) {
            let t = da / (da - db);
            tmp.push((a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t));
        }
    }
    std::mem::swap(poly, tmp);
}

impl Hull {
    pub fn new(camera_from_body: &Isometry3<f64>, diameter_m: f64, length_m: f64) -> Hull {
        Hull {
            center: camera_from_body.translation.vector,
            axis: camera_from_body.rotation * Vector3::x(),
            radius: 0.5 * diameter_m,
            half_len: 0.5 * length_m,
        }
    }

    /// Nearest intersection `(t, outward normal)` with the closed cylinder.
    #[inline]
    fn intersect(
        &self,
        o: &Vector3<f64>,
        x: f64,
        y: f64,
        t_max: f64,
    ) -> Option<(f64, Vector3<f64>)> {
        let d = Vector3::new(x, y, 1.0);
        // The ray's origin from the centre (exactly `-self.center` when `o` is 0).
        let oc = -(self.center - o);
        let da = d.dot(&self.axis);
        let oa = oc.dot(&self.axis);
        let dp = d - self.axis * da;
        let op = oc - self.axis * oa;
        let a = dp.norm_squared();
        let b = 2.0 * dp.dot(&op);
        let c = op.norm_squared() - self.radius * self.radius;
        let mut best: Option<(f64, Vector3<f64>)> = None;
        if a > 1e-18 {
            let disc = b * b - 4.0 * a * c;
            if disc >= 0.0 {
                let sq = disc.sqrt();
                for t in [(-b - sq) / (2.0 * a), (-b + sq) / (2.0 * a)] {
                    if t > NEAR_M && t < t_max && best.is_none_or(|(bt, _)| t < bt) {
                        let s = oa + t * da;
                        if s.abs() <= self.half_len {
                            let n = (op + dp * t) / self.radius;
                            best = Some((t, n));
                        }
                    }
                }
            }
        }
        if da.abs() > 1e-15 {
            for sign in [-1.0, 1.0] {
                let t = (sign * self.half_len - oa) / da;
                if t > NEAR_M && t < t_max && best.is_none_or(|(bt, _)| t < bt) {
                    let p = op + dp * t;
                    if p.norm_squared() <= self.radius * self.radius {
                        best = Some((t, self.axis * sign));
                    }
                }
            }
        }
        best
    }
}

impl Objects {
    /// The nearest hit of the in-air ray `(x, y, 1)` (refracted by the port
    /// when there is one), if any.
    #[inline]
    pub fn trace(&self, x: f64, y: f64) -> Option<Hit> {
        let (o, (x, y)) = self.in_water(x, y);
        let mut best: Option<Hit> = None;
        for i in 0..self.object_count() as u32 {
            let t_max = best.map_or(f64::INFINITY, |h| h.t);
            if let Some(h) = self.hit_object(i, &o, x, y, t_max) {
                best = Some(h);
            }
        }
        best
    }

    /// As [`Objects::trace`] but only against the objects `ids` (those whose
    /// regions of interest contain the pixel).
    #[inline]
    pub fn trace_in(&self, ids: &[u32], x: f64, y: f64) -> Option<Hit> {
        let (o, (x, y)) = self.in_water(x, y);
        let mut best: Option<Hit> = None;
        for &i in ids {
            let t_max = best.map_or(f64::INFINITY, |h| h.t);
            if let Some(h) = self.hit_object(i, &o, x, y, t_max) {
                best = Some(h);
            }
        }
        best
    }

    /// The in-water ray of the in-air ray `(x, y, 1)`: its origin and slope.
    #[inline]
    fn in_water(&self, x: f64, y: f64) -> (Vector3<f64>, (f64, f64)) {
        match &self.port {
            None => (Vector3::zeros(), (x, y)),
            Some(port) => port.refract(x, y),
        }
    }

    /// The camera-frame point `p`'s pixel through the port and the lens (the
    /// lens alone without a port).
    pub fn project(&self, cam: &CameraModel, p: &Point3<f64>) -> Option<nalgebra::Point2<f64>> {
        shoal_proto::port::project(cam, self.port.as_ref(), p)
    }

    /// The hit on object `i` (plates first, then hulls) nearer than `t_max`
    /// along the ray from `o` along `(x, y, 1)`.
    #[inline]
    fn hit_object(&self, i: u32, o: &Vector3<f64>, x: f64, y: f64, t_max: f64) -> Option<Hit> {
        let np = self.plates.len() as u32;
        if i < np {
            let (t, patch, radiance, lamp_geom, plane) =
                self.plates[i as usize].intersect(o, x, y, t_max)?;
            Some(Hit {
                t,
                range: t * (x * x + y * y + 1.0).sqrt(),
                object: i,
                patch,
                plane,
                radiance,
                lamp_geom,
            })
        } else {
            let (t, n) = self
                .hulls
                .get((i - np) as usize)?
                .intersect(o, x, y, t_max)?;
            let d = Vector3::new(x, y, 1.0);
            let cos_i = (-n.dot(&d) / d.norm()).clamp(0.0, 1.0);
            Some(Hit {
                t,
                range: t * (x * x + y * y + 1.0).sqrt(),
                object: i,
                patch: 0,
                plane: (0.0, 0.0),
                radiance: ALBEDO_HULL * ambient_shading(&n, &self.up),
                lamp_geom: ALBEDO_HULL * cos_i,
            })
        }
    }

    /// Whether the point `p` (camera frame) is the first thing its ray hits
    /// (within 1e-6 relative depth), i.e. not occluded.
    pub fn sees(&self, p: &Point3<f64>) -> bool {
        let (x, y, depth) = match &self.port {
            None => (p.x / p.z, p.y / p.z, p.z),
            Some(port) => match port.air_ray(p) {
                Some((x, y)) => (x, y, p.z - port.outer_z()),
                None => return false,
            },
        };
        if depth <= NEAR_M {
            return false;
        }
        match self.trace(x, y) {
            Some(h) => h.t >= depth * (1.0 - 1e-6),
            None => true,
        }
    }

    pub fn object_count(&self) -> usize {
        self.plates.len() + self.hulls.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn newton_ray_matches_the_camera_models_undistort() {
        let cam = CameraModel::vehicle_1440();
        for &(u, v) in &[(0.0, 0.0), (719.5, 539.5), (1439.0, 1079.0), (100.3, 900.7)] {
            let guess = cam.ray(719.5, 539.5);
            let (x, y) = ray_from(&cam, u, v, guess);
            let p = cam.project(&Point3::new(x, y, 1.0)).unwrap();
            assert!(
                (p.x - u).abs() < 1e-9 && (p.y - v).abs() < 1e-9,
                "{u},{v} -> {p}"
            );
        }
    }

    #[test]
    fn white_coverage_is_the_exact_area_fraction() {
        // A 4-module marker: modules of 0.1 m, plate half side 0.3 m.
        let plate = Plate::new(
            &Isometry3::translation(0.0, 0.0, 1.0),
            4,
            0.4,
            vec![false; 16],
            &Vector3::y(),
        );
        // A square straddling the quiet zone (white, x < -0.2) and
        // the black frame, 30 % of it on the white side.
        let q = [(-0.23, 0.05), (-0.13, 0.05), (-0.13, -0.05), (-0.23, -0.05)];
        let (c0, r0) = (0, 2);
        let f = plate.white_coverage(&q, c0, c0 + 1, r0, r0 + 1).unwrap();
        assert!((f - 0.3).abs() < 1e-12, "{f}");
        // A diamond centred on the boundary: half white.
        let d = [(-0.2, 0.05), (-0.15, 0.0), (-0.2, -0.05), (-0.25, 0.0)];
        let f = plate.white_coverage(&d, 0, 1, 2, 3).unwrap();
        assert!((f - 0.5).abs() < 1e-12, "{f}");
        // A footprint not tiled by the given cells is refused.
        assert!(plate.white_coverage(&q, 1, 1, 2, 3).is_none());
    }

    #[test]
    fn cylinder_hit_is_on_its_surface_and_caps_close_it() {
        // A hull 2 m ahead, axis along camera x.
        let pose = Isometry3::translation(0.0, 0.0, 2.0);
        let h = Hull::new(&pose, 0.2, 1.0);
        let objs = Objects {
            plates: vec![],
            hulls: vec![h],
            up: -Vector3::y(),
            port: None,
        };
        let hit = objs.trace(0.0, 0.0).unwrap();
        assert!((hit.t - 1.9).abs() < 1e-12);
        // Looking along the axis from the side: hits the end cap at x = 0.5.
        let side = Objects {
            plates: vec![],
            hulls: vec![Hull::new(
                &Isometry3::from_parts(
                    nalgebra::Translation3::new(0.0, 0.0, 3.0),
                    nalgebra::UnitQuaternion::from_euler_angles(
                        0.0,
                        -std::f64::consts::FRAC_PI_2,
                        0.0,
                    ),
                ),
                0.2,
                1.0,
            )],
            up: -Vector3::y(),
            port: None,
        };
        let hit = side.trace(0.0, 0.0).unwrap();
        assert!((hit.t - 2.5).abs() < 1e-12, "{}", hit.t);
        assert!(side.trace(0.2, 0.0).is_none());
    }
}
