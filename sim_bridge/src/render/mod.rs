//! The image synthesizer: what a calibrated camera sees underwater.
//!
//! Geometry is exact: every sample ray is the camera model's inverse
//! distortion of its sub-pixel position (`CameraModel::project` of a marker
//! corner lands where the rendered corner is), and pixels are anti-aliased
//! by adaptive supersampling on a sheared 8x8 grid (64 distinct offsets in
//! x and in y), so edges can be measured to a few hundredths of a pixel.
//! Pixel centres are at integer coordinates (OpenCV).
//!
//! Only pixels whose region of interest (the projected bounds of a marker
//! plate or a hull) is on screen are ray-cast; the water background, the
//! veil, vignetting and noise are analytic. The water model and its sources
//! are in `docs/water-model.md`.

#[cfg(test)]
mod geometry_tests;
pub mod optics;
pub mod trace;

use crate::error::SimError;
use crate::water::WaterParams;
use nalgebra::{Point3, Vector3};
use optics::{blur_add, quantize_with_noise, Ambient, LampIntegral, Psf, Rect};
use shoal_proto::config::Fleet;
use shoal_proto::geometry::pose_is_finite;
use shoal_proto::{
    CameraModel, CodeSet, GrayImage, MarkerId, Pose, VehicleId, VehicleTruth, VisibleMarker,
};
use std::path::Path;
use trace::{Hit, Hull, Objects, Plate};

/// A marker in the world (with its one-module white quiet zone).
#[derive(Debug, Clone, PartialEq)]
pub struct SceneMarker {
    pub codes: CodeSet,
    pub id: MarkerId,
    /// Side of the outer black square (the footprint), metres.
    pub side_m: f64,
    pub world_from_marker: Pose,
    /// The vehicle carrying it (`VisibleMarker::target_vehicle`); 0 when none.
    pub owner: VehicleId,
}

/// A vehicle hull: a closed cylinder centred on the body origin, axis along body x.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneHull {
    pub vehicle: VehicleId,
    pub world_from_body: Pose,
    pub diameter_m: f64,
    pub length_m: f64,
}

/// Everything that can be seen.
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    pub markers: Vec<SceneMarker>,
    pub hulls: Vec<SceneHull>,
    /// The world's up direction (unit), for the downwelling light: `(0, 0, −1)` in NED.
    pub up_world: Vector3<f64>,
}

impl Scene {
    /// An empty NED scene.
    pub fn empty() -> Scene {
        Scene {
            markers: Vec::new(),
            hulls: Vec::new(),
            up_world: Vector3::new(0.0, 0.0, -1.0),
        }
    }

    /// One marker in front of a camera placed at the world origin (render
    /// with `world_from_camera = Pose::identity()`); the camera's image-up
    /// is the world's up. Used by the evaluation at 600 mm.
    pub fn single_marker(
        codes: CodeSet,
        id: MarkerId,
        side_m: f64,
        camera_from_marker: Pose,
    ) -> Scene {
        Scene {
            markers: vec![SceneMarker {
                codes,
                id,
                side_m,
                world_from_marker: camera_from_marker,
                owner: 0,
            }],
            hulls: Vec::new(),
            up_world: Vector3::new(0.0, -1.0, 0.0),
        }
    }

    /// Hulls and markers of every vehicle of `fleet` that has a pose in `truth`.
    pub fn from_fleet(fleet: &Fleet, truth: &[VehicleTruth]) -> Scene {
        let mut scene = Scene::empty();
        for t in truth {
            let Some(v) = fleet.vehicle(t.vehicle) else {
                continue;
            };
            scene.hulls.push(SceneHull {
                vehicle: v.id,
                world_from_body: t.world_from_body,
                diameter_m: v.hull.diameter_m,
                length_m: v.hull.length_m,
            });
            for m in &v.markers {
                scene.markers.push(SceneMarker {
                    codes: m.codes,
                    id: m.id,
                    side_m: m.side_m,
                    world_from_marker: t.world_from_body * m.body_from_marker,
                    owner: v.id,
                });
            }
        }
        scene
    }

    /// Check poses, sizes and marker IDs.
    pub fn validate(&self) -> Result<(), SimError> {
        if !(self.up_world.iter().all(|v| v.is_finite())
            && (self.up_world.norm() - 1.0).abs() < 1e-6)
        {
            return Err(SimError::InvalidArgument {
                field: "scene.up_world",
                value: self.up_world.norm(),
                reason: "must be a finite unit vector",
            });
        }
        for m in &self.markers {
            if !pose_is_finite(&m.world_from_marker) {
                return Err(SimError::NonFinitePose {
                    what: format!("marker {}#{}", m.codes, m.id),
                });
            }
            if !(m.side_m > 0.0 && m.side_m.is_finite()) {
                return Err(SimError::Marker {
                    codes: m.codes,
                    id: m.id,
                    reason: format!("side {} m must be positive", m.side_m),
                });
            }
            grid_of(m.codes, m.id)?;
        }
        for h in &self.hulls {
            if !pose_is_finite(&h.world_from_body) {
                return Err(SimError::NonFinitePose {
                    what: format!("hull of vehicle {}", h.vehicle),
                });
            }
            if !(h.diameter_m > 0.0
                && h.length_m > 0.0
                && h.diameter_m.is_finite()
                && h.length_m.is_finite())
            {
                return Err(SimError::Hull {
                    vehicle: h.vehicle,
                    diameter_m: h.diameter_m,
                    length_m: h.length_m,
                });
            }
        }
        Ok(())
    }
}

/// `camera_from_marker` for a marker facing the camera upright (its face
/// towards the camera, its y axis image-up) and then rotated by
/// `rpy` (rad, `R = Rz·Ry·Rx` about the camera's axes: pitch turns it about
/// the image vertical like the paper's rotation platform), centred at `xyz_m`.
pub fn facing_camera(xyz_m: [f64; 3], rpy: [f64; 3]) -> Pose {
    shoal_proto::geometry::pose_from_xyz_rpy(xyz_m, rpy)
        * shoal_proto::geometry::pose_from_xyz_rpy([0.0; 3], [std::f64::consts::PI, 0.0, 0.0])
}

/// One rendered frame: the underwater image, its clean twin (same view, no
/// water, no noise, no vignetting; background black), and the ground truth
/// of which markers are visible where.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderOutput {
    pub image: GrayImage,
    pub clean: GrayImage,
    /// `observer`, `camera`, `frame_seq` are 0 here; [`render_fleet_view`] fills them.
    pub visible: Vec<VisibleMarker>,
}

/// Per-pixel accumulators of the ray-cast part (see `docs/water-model.md`).
#[derive(Debug, Default, Clone, Copy)]
struct Sample {
    clean: f64,
    direct: f64,
    scatter: f64,
    veil: f64,
    lamp: f64,
}

/// Water terms that are constant for a frame.
#[derive(Debug, Clone)]
struct Medium {
    c: f64,
    s: f64,
    illum: f64,
    lamp_power: f64,
    lamp: LampIntegral,
}

impl Medium {
    #[inline]
    fn sample(&self, hit: Option<Hit>, x: f64, y: f64) -> Sample {
        match hit {
            None => Sample {
                clean: 0.0,
                direct: 0.0,
                scatter: 0.0,
                veil: 1.0,
                lamp: 1.0,
            },
            Some(h) => {
                let r = h.t * (x * x + y * y + 1.0).sqrt();
                let tr = (-self.c * r).exp();
                let lamp_in = if self.lamp_power > 0.0 {
                    self.lamp_power * h.lamp_geom * tr / (r * r).max(1e-4)
                } else {
                    0.0
                };
                let j = self.illum * h.radiance + lamp_in;
                Sample {
                    clean: h.radiance,
                    direct: j * tr,
                    scatter: j * tr * ((self.s * self.c * r).exp() - 1.0),
                    veil: 1.0 - tr,
                    lamp: if self.lamp_power > 0.0 {
                        self.lamp.fraction(r)
                    } else {
                        1.0
                    },
                }
            }
        }
    }
}

/// Sheared-grid supersampling offsets: N² samples whose x (and y)
/// coordinates are all distinct multiples of 1/N², so even an axis-aligned
/// edge is resolved to 1/N² of a pixel.
fn sample_offsets(n: usize) -> Vec<(f64, f64)> {
    let nn = (n * n) as f64;
    let mut v = Vec::with_capacity(n * n);
    for j in 0..n {
        for i in 0..n {
            v.push((
                ((i * n + j) as f64 + 0.5) / nn - 0.5,
                ((j * n + i) as f64 + 0.5) / nn - 0.5,
            ));
        }
    }
    v
}

/// Reusable frame buffers; one per thread that renders.
#[derive(Debug)]
pub struct Renderer {
    /// Samples per axis for pixels that straddle an edge (default 8: 64 samples).
    pub supersample: usize,
    offsets: Vec<(f64, f64)>,
    clean: Vec<f32>,
    direct: Vec<f32>,
    scatter: Vec<f32>,
    scattered: Vec<f32>,
    veil: Vec<f32>,
    lamp: Vec<f32>,
    dn: Vec<f32>,
    scratch: Vec<f32>,
}

impl Default for Renderer {
    fn default() -> Self {
        Self::new()
    }
}

/// Everything known about one object before ray casting.
#[derive(Debug, Clone)]
struct Roi {
    rect: Rect,
    /// Range for the object's PSF (m).
    range_m: f64,
    /// Always supersample (features smaller than a few pixels).
    fine: bool,
}

impl Renderer {
    pub fn new() -> Self {
        Renderer {
            supersample: 8,
            offsets: sample_offsets(8),
            clean: Vec::new(),
            direct: Vec::new(),
            scatter: Vec::new(),
            scattered: Vec::new(),
            veil: Vec::new(),
            lamp: Vec::new(),
            dn: Vec::new(),
            scratch: Vec::new(),
        }
    }

    /// Render `scene` as seen by `cam` at `world_from_camera` through
    /// `water`, at simulation time `time_s` (drives the ambient light);
    /// `seed` drives the sensor noise only (same seed → same bytes).
    pub fn render(
        &mut self,
        cam: &CameraModel,
        world_from_camera: &Pose,
        scene: &Scene,
        water: &WaterParams,
        time_s: f64,
        seed: u64,
    ) -> Result<RenderOutput, SimError> {
        if let Some(p) = cam.problem() {
            return Err(SimError::Camera(p));
        }
        if !pose_is_finite(world_from_camera) {
            return Err(SimError::NonFinitePose {
                what: "world_from_camera".into(),
            });
        }
        if !time_s.is_finite() {
            return Err(SimError::InvalidArgument {
                field: "time_s",
                value: time_s,
                reason: "must be finite",
            });
        }
        water.validate()?;
        scene.validate()?;
        if self.offsets.len() != self.supersample * self.supersample {
            self.supersample = self.supersample.clamp(1, 32);
            self.offsets = sample_offsets(self.supersample);
        }
        let (w, h) = (cam.width as usize, cam.height as usize);
        let n = w * h;
        let camera_from_world = world_from_camera.inverse();
        let up = camera_from_world.rotation * scene.up_world;

        let objects = build_objects(scene, &camera_from_world, true)?;

        let ambient = Ambient::new(water, time_s);
        let medium = Medium {
            c: water.c_per_m,
            s: water.forward_scatter,
            illum: water.illumination * ambient.temporal,
            lamp_power: water.lamp_power,
            lamp: LampIntegral::new(water.c_per_m),
        };

        for buf in [
            &mut self.clean,
            &mut self.direct,
            &mut self.scatter,
            &mut self.scattered,
        ] {
            buf.clear();
            buf.resize(n, 0.0);
        }
        for buf in [&mut self.veil, &mut self.lamp] {
            buf.clear();
            buf.resize(n, 1.0);
        }

        // Regions of interest.
        let rois: Vec<Option<Roi>> = objects
            .plates
            .iter()
            .map(|p| plate_roi(cam, p))
            .chain(objects.hulls.iter().map(|hl| hull_roi(cam, hl)))
            .collect();
        self.cast(cam, &objects, &rois, &medium);

        // Forward scatter: blur the scattered light per group of overlapping ROIs.
        for (rect, range) in psf_groups(cam, water, &rois) {
            let psf = Psf::for_range(water, 0.5 * (cam.fx + cam.fy), range);
            let margin = psf.radius_px().ceil() as usize + 1;
            let region = rect.dilated(margin, w, h);
            blur_add(
                &self.scatter,
                w,
                region,
                &psf,
                &mut self.scattered,
                &mut self.scratch,
            );
        }

        // Compose: veil, vignetting, exposure (docs/water-model.md, Eq. (W1)).
        self.compose(cam, water, &ambient, &medium, &up);
        let mut image = vec![0u8; n];
        quantize_with_noise(&self.dn, w, water, seed, &mut image);
        let clean: Vec<u8> = self
            .clean
            .iter()
            .map(|v| (255.0 * v).round().clamp(0.0, 255.0) as u8)
            .collect();

        let visible = visible_markers(cam, scene, &objects);
        Ok(RenderOutput {
            image: GrayImage {
                width: cam.width,
                height: cam.height,
                data: image,
            },
            clean: GrayImage {
                width: cam.width,
                height: cam.height,
                data: clean,
            },
            visible,
        })
    }

    /// The last rendered frame before noise and quantization, in DN (row-major floats).
    pub fn last_frame_dn(&self) -> &[f32] {
        &self.dn
    }

    /// Ray-cast every pixel inside some ROI.
    fn cast(
        &mut self,
        cam: &CameraModel,
        objects: &Objects,
        rois: &[Option<Roi>],
        medium: &Medium,
    ) {
        let w = cam.width as usize;
        let h = cam.height as usize;
        let mut spans: Vec<(usize, usize, bool)> = Vec::new();
        // Objects whose ROI covers the current row: (id, x0, x1).
        let mut row_objects: Vec<(u32, usize, usize)> = Vec::new();
        let mut span_ids: Vec<u32> = Vec::new();
        let mut pixel_ids: Vec<u32> = Vec::new();
        let mut fine_objects = vec![false; rois.len()];
        for (i, r) in rois.iter().enumerate() {
            if let Some(r) = r {
                fine_objects[i] = r.fine;
            }
        }
        let nsamples = self.offsets.len() as f64;
        let mut prev: Vec<(usize, usize, Vec<LatticePoint>)> = Vec::new();
        for y in 0..h {
            spans.clear();
            row_objects.clear();
            for (id, r) in rois.iter().enumerate() {
                if let Some(r) = r {
                    if y >= r.rect.y0 && y <= r.rect.y1 {
                        spans.push((r.rect.x0, r.rect.x1, r.fine));
                        row_objects.push((id as u32, r.rect.x0, r.rect.x1));
                    }
                }
            }
            if spans.is_empty() {
                prev.clear();
                continue;
            }
            spans.sort_unstable_by_key(|s| s.0);
            let mut merged: Vec<(usize, usize)> = Vec::new();
            for &(a, b, _) in &spans {
                match merged.last_mut() {
                    Some(last) if a <= last.1 + 1 => last.1 = last.1.max(b),
                    _ => merged.push((a, b)),
                }
            }
            let v = y as f64;
            let mut next_prev = Vec::with_capacity(merged.len());
            for &(x0, x1) in &merged {
                // Pixel-corner lattice rows above and below this row (shared by
                // neighbouring pixels; the upper one reused from the row above).
                // ROIs have a margin of ≥ 2 px around their objects, so rays
                // through this span can only hit objects whose ROI meets it.
                span_ids.clear();
                span_ids.extend(
                    row_objects
                        .iter()
                        .filter(|o| o.1 <= x1 && o.2 >= x0)
                        .map(|o| o.0),
                );
                let top = match prev.iter().position(|(a, b, _)| *a == x0 && *b == x1) {
                    Some(k) => prev.swap_remove(k).2,
                    None => lattice_row(cam, objects, &span_ids, x0, x1, v - 0.5),
                };
                let bottom = lattice_row(cam, objects, &span_ids, x0, x1, v + 0.5);
                for x in x0..=x1 {
                    let k = x - x0;
                    let u = x as f64;
                    let guess = (
                        0.25 * (top[k].0 .0
                            + top[k + 1].0 .0
                            + bottom[k].0 .0
                            + bottom[k + 1].0 .0),
                        0.25 * (top[k].0 .1
                            + top[k + 1].0 .1
                            + bottom[k].0 .1
                            + bottom[k + 1].0 .1),
                    );
                    let centre = trace::ray_from(cam, u, v, guess);
                    pixel_ids.clear();
                    pixel_ids.extend(
                        row_objects
                            .iter()
                            .filter(|o| o.1 <= x && o.2 >= x)
                            .map(|o| o.0),
                    );
                    let hit_c = objects.trace_in(&pixel_ids, centre.0, centre.1);
                    let corners = [top[k].1, top[k + 1].1, bottom[k + 1].1, bottom[k].1];
                    let kind = classify_pixel(objects, &hit_c, &corners, &fine_objects);
                    let s = if let PixelKind::Uniform = kind {
                        medium.sample(hit_c, centre.0, centre.1)
                    } else if let (PixelKind::PlateEdge(white), Some(h)) = (kind, hit_c) {
                        // Exact area coverage of the modules under the pixel.
                        let plate = &objects.plates[h.object as usize];
                        let mix = |a: f64, b: f64| white * a + (1.0 - white) * b;
                        let cos_i = h.lamp_geom
                            / if h.radiance > 0.5 * plate.shade {
                                trace::ALBEDO_WHITE
                            } else {
                                trace::ALBEDO_BLACK
                            };
                        let hit = Hit {
                            radiance: plate.shade * mix(trace::ALBEDO_WHITE, trace::ALBEDO_BLACK),
                            lamp_geom: cos_i * mix(trace::ALBEDO_WHITE, trace::ALBEDO_BLACK),
                            ..h
                        };
                        medium.sample(Some(hit), centre.0, centre.1)
                    } else {
                        let mut acc = Sample::default();
                        for &(du, dv) in &self.offsets {
                            let r = trace::ray_from(cam, u + du, v + dv, centre);
                            let s = medium.sample(objects.trace_in(&pixel_ids, r.0, r.1), r.0, r.1);
                            acc.clean += s.clean;
                            acc.direct += s.direct;
                            acc.scatter += s.scatter;
                            acc.veil += s.veil;
                            acc.lamp += s.lamp;
                        }
                        Sample {
                            clean: acc.clean / nsamples,
                            direct: acc.direct / nsamples,
                            scatter: acc.scatter / nsamples,
                            veil: acc.veil / nsamples,
                            lamp: acc.lamp / nsamples,
                        }
                    };
                    let i = y * w + x;
                    self.clean[i] = s.clean as f32;
                    self.direct[i] = s.direct as f32;
                    self.scatter[i] = s.scatter as f32;
                    self.veil[i] = s.veil as f32;
                    self.lamp[i] = s.lamp as f32;
                }
                next_prev.push((x0, x1, bottom));
            }
            prev = next_prev;
        }
    }

    /// Final radiance to DN: `exposure · V(x) · [D + h∗F + B(x)·β + lamp veil]`.
    fn compose(
        &mut self,
        cam: &CameraModel,
        water: &WaterParams,
        ambient: &Ambient,
        medium: &Medium,
        up: &Vector3<f64>,
    ) {
        let (w, h) = (cam.width as usize, cam.height as usize);
        // The veil and vignetting are smooth: evaluate them on a coarse grid.
        let step = 8usize;
        let gw = (w - 1) / step + 2;
        let gh = (h - 1) / step + 2;
        let mut veil_grid = vec![0.0f32; gw * gh];
        let mut vig_grid = vec![0.0f32; gw * gh];
        for gy in 0..gh {
            for gx in 0..gw {
                let (u, v) = ((gx * step) as f64, (gy * step) as f64);
                let (x, y) = cam.ray(u, v);
                let d = Vector3::new(x, y, 1.0);
                let norm = d.norm();
                let cos_zenith = d.dot(up) / norm;
                let dir_gain = (1.0 + water.backscatter_up_gain * cos_zenith).max(0.1);
                let spatial = ambient.spatial(u / w as f64, v / h as f64);
                veil_grid[gy * gw + gx] = (water.backscatter_inf
                    * dir_gain
                    * spatial
                    * ambient.temporal
                    * water.illumination) as f32;
                let cos_t = 1.0 / norm;
                vig_grid[gy * gw + gx] = (1.0 - water.vignetting * (1.0 - cos_t.powi(4))) as f32;
            }
        }
        let lamp_veil = (water.lamp_power * water.lamp_backscatter * medium.lamp.total) as f32;
        let gain = (255.0 * water.exposure) as f32;
        self.dn.clear();
        self.dn.resize(w * h, 0.0);
        let inv = 1.0 / step as f32;
        let mut veil_row = vec![0.0f32; gw];
        let mut vig_row = vec![0.0f32; gw];
        for y in 0..h {
            let fy = y as f32 * inv;
            let gy = (fy as usize).min(gh - 2);
            let ty = fy - gy as f32;
            for gx in 0..gw {
                veil_row[gx] =
                    veil_grid[gy * gw + gx] * (1.0 - ty) + veil_grid[(gy + 1) * gw + gx] * ty;
                vig_row[gx] =
                    vig_grid[gy * gw + gx] * (1.0 - ty) + vig_grid[(gy + 1) * gw + gx] * ty;
            }
            let row = y * w;
            let (direct, scattered) = (&self.direct[row..row + w], &self.scattered[row..row + w]);
            let (veil, lamp) = (&self.veil[row..row + w], &self.lamp[row..row + w]);
            for (x, out) in self.dn[row..row + w].iter_mut().enumerate() {
                let gx = x / step;
                let tx = (x % step) as f32 * inv;
                let b = veil_row[gx] * (1.0 - tx) + veil_row[gx + 1] * tx;
                let vg = vig_row[gx] * (1.0 - tx) + vig_row[gx + 1] * tx;
                *out = gain * vg * (direct[x] + scattered[x] + b * veil[x] + lamp_veil * lamp[x]);
            }
        }
    }
}

/// A pixel corner's ray and what it hits.
type LatticePoint = ((f64, f64), Option<Hit>);

/// The pixel-corner points `u = x0 − ½ … x1 + ½` at image row `v`.
fn lattice_row(
    cam: &CameraModel,
    objects: &Objects,
    ids: &[u32],
    x0: usize,
    x1: usize,
    v: f64,
) -> Vec<LatticePoint> {
    let first = cam.ray(x0 as f64 - 0.5, v);
    let (mut prev, mut last) = (first, first);
    (x0..=x1 + 1)
        .map(|x| {
            // Linear extrapolation from the two previous rays: Newton then
            // converges in one step.
            let guess = (2.0 * last.0 - prev.0, 2.0 * last.1 - prev.1);
            let r = trace::ray_from(cam, x as f64 - 0.5, v, guess);
            prev = if x == x0 { r } else { last };
            last = r;
            (r, objects.trace_in(ids, r.0, r.1))
        })
        .collect()
}

/// How a pixel is rendered.
#[derive(Debug, Clone, Copy, PartialEq)]
enum PixelKind {
    /// One uniform patch: its centre sample.
    Uniform,
    /// Inside one plate's face, across module edges: this white fraction.
    PlateEdge(f64),
    /// Anything else (silhouettes, occlusions, tiny features): supersampled.
    Mixed,
}

/// Classify a pixel from the hits at its centre and corners (see
/// [`pixel_is_uniform`]). Plate edges: all five on one plate's face; the
/// pixel's footprint is the corners' quadrilateral in plate coordinates and
/// its white fraction is computed exactly.
fn classify_pixel(
    objects: &Objects,
    centre: &Option<Hit>,
    corners: &[Option<Hit>; 4],
    fine: &[bool],
) -> PixelKind {
    if pixel_is_uniform(objects, centre, corners, fine) {
        return PixelKind::Uniform;
    }
    let (Some(c), [Some(a), Some(b), Some(d), Some(e)]) = (centre, corners) else {
        return PixelKind::Mixed;
    };
    let Some(plate) = objects.plates.get(c.object as usize) else {
        return PixelKind::Mixed;
    };
    let back = (plate.modules as u32 + 2).pow(2);
    let hits = [a, b, d, e, c];
    if fine.get(c.object as usize).copied().unwrap_or(true)
        || hits.iter().any(|h| h.object != c.object || h.patch == back)
    {
        return PixelKind::Mixed;
    }
    let (mut c0, mut c1, mut r0, mut r1) = (i64::MAX, i64::MIN, i64::MAX, i64::MIN);
    for h in hits {
        let (col, row) = plate.decode_patch(h.patch);
        c0 = c0.min(col);
        c1 = c1.max(col);
        r0 = r0.min(row);
        r1 = r1.max(row);
    }
    let quad = [a.plane, b.plane, d.plane, e.plane];
    match plate.white_coverage(&quad, c0, c1, r0, r1) {
        Some(f) => PixelKind::PlateEdge(f),
        None => PixelKind::Mixed,
    }
}

/// Whether a pixel is one uniform patch, from the hits at its centre and
/// corners: same object, and for a plate all modules between the corners'
/// modules of one colour (the pixel's footprint on a plane is convex, so a
/// module edge crossing it separates its corners).
fn pixel_is_uniform(
    objects: &Objects,
    centre: &Option<Hit>,
    corners: &[Option<Hit>; 4],
    fine: &[bool],
) -> bool {
    let obj = |h: &Option<Hit>| h.map(|h| h.object);
    let o = obj(centre);
    if corners.iter().any(|c| obj(c) != o) {
        return false;
    }
    let Some(o) = o else {
        return true;
    };
    if fine.get(o as usize).copied().unwrap_or(true) {
        return false;
    }
    let Some(plate) = objects.plates.get(o as usize) else {
        return true; // a hull: smooth shading
    };
    let patches: Vec<u32> = corners
        .iter()
        .chain([centre])
        .flatten()
        .map(|h| h.patch)
        .collect();
    let back = (plate.modules as u32 + 2).pow(2);
    if patches.iter().all(|&p| p == back) {
        return true;
    }
    if patches.contains(&back) {
        return false;
    }
    let (mut c0, mut c1, mut r0, mut r1) = (i64::MAX, i64::MIN, i64::MAX, i64::MIN);
    for &p in &patches {
        let (c, r) = plate.decode_patch(p);
        c0 = c0.min(c);
        c1 = c1.max(c);
        r0 = r0.min(r);
        r1 = r1.max(r);
    }
    plate.uniform(c0, c1, r0, r1)
}

/// Smallest depth a ROI sample may have; nearer surfaces are clipped there.
const ROI_NEAR_M: f64 = 1e-3;

/// Pixel bounds of a set of camera-frame points, with the segments given
/// as index pairs clipped at the near plane (a clipped point projects far
/// out, extending the ROI to the image border on its side).
fn roi_of(
    cam: &CameraModel,
    pts: &[Point3<f64>],
    segments: &[(usize, usize)],
    margin_frac: f64,
) -> Option<Rect> {
    let (w, h) = (cam.width as f64, cam.height as f64);
    let (mut u0, mut v0, mut u1, mut v1) = (
        f64::INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NEG_INFINITY,
    );
    let mut add = |p: &Point3<f64>| {
        // Outside the lens model's sane range, clamp the direction to far off-screen.
        let (xn, yn) = (p.x / p.z, p.y / p.z);
        let lim = 4.0;
        let (u, v) = if xn.abs() > lim || yn.abs() > lim {
            (
                if xn > 0.0 {
                    1e9
                } else if xn < 0.0 {
                    -1e9
                } else {
                    cam.cx
                },
                if yn > 0.0 {
                    1e9
                } else if yn < 0.0 {
                    -1e9
                } else {
                    cam.cy
                },
            )
        } else {
            let q = cam
                .project(p)
                .unwrap_or(Point3::new(cam.cx, cam.cy, 1.0).xy());
            (q.x, q.y)
        };
        u0 = u0.min(u);
        v0 = v0.min(v);
        u1 = u1.max(u);
        v1 = v1.max(v);
    };
    for p in pts.iter().filter(|p| p.z > ROI_NEAR_M) {
        add(p);
    }
    for &(a, b) in segments {
        let (pa, pb) = (pts[a], pts[b]);
        if (pa.z > ROI_NEAR_M) != (pb.z > ROI_NEAR_M) {
            let t = (ROI_NEAR_M * 1.0001 - pa.z) / (pb.z - pa.z);
            add(&(pa + (pb - pa) * t));
        }
    }
    if !u0.is_finite() {
        return None;
    }
    let margin = 2.0 + margin_frac * (u1 - u0).max(v1 - v0).min(w.max(h));
    let (u0, v0, u1, v1) = (u0 - margin, v0 - margin, u1 + margin, v1 + margin);
    if u1 < -0.5 || v1 < -0.5 || u0 > w - 0.5 || v0 > h - 0.5 {
        return None;
    }
    Some(Rect {
        x0: u0.max(0.0).floor() as usize,
        y0: v0.max(0.0).floor() as usize,
        x1: (u1.min(w - 1.0).ceil() as usize).min(cam.width as usize - 1),
        y1: (v1.min(h - 1.0).ceil() as usize).min(cam.height as usize - 1),
    })
}

/// A grid of points over the plate and its mesh segments.
fn plate_roi(cam: &CameraModel, p: &Plate) -> Option<Roi> {
    let k = 16usize;
    let mut pts = Vec::with_capacity((k + 1) * (k + 1));
    let mut segs = Vec::new();
    for j in 0..=k {
        for i in 0..=k {
            let a = -p.half_m + 2.0 * p.half_m * i as f64 / k as f64;
            let b = -p.half_m + 2.0 * p.half_m * j as f64 / k as f64;
            pts.push(Point3::from(p.origin + p.ex * a + p.ey * b));
            let idx = j * (k + 1) + i;
            if i < k {
                segs.push((idx, idx + 1));
            }
            if j < k {
                segs.push((idx, idx + k + 1));
            }
        }
    }
    let rect = roi_of(cam, &pts, &segs, 0.01)?;
    let depth = p.origin.z.max(ROI_NEAR_M);
    let module_px = cam.fx.min(cam.fy) * p.module_m / depth;
    Some(Roi {
        rect,
        range_m: p.origin.norm(),
        fine: module_px < 3.0,
    })
}

/// Rings of points along the hull (48 around, 17 along) and its mesh segments.
fn hull_roi(cam: &CameraModel, hl: &Hull) -> Option<Roi> {
    let (na, nl) = (48usize, 16usize);
    let e1 = hl
        .axis
        .cross(&Vector3::x())
        .try_normalize(1e-9)
        .unwrap_or_else(|| hl.axis.cross(&Vector3::y()).normalize());
    let e2 = hl.axis.cross(&e1);
    let mut pts = Vec::with_capacity((na + 1) * (nl + 1));
    let mut segs = Vec::new();
    for j in 0..=nl {
        let s = -hl.half_len + 2.0 * hl.half_len * j as f64 / nl as f64;
        // Centre of each ring too, so the end caps are covered.
        let c = hl.center + hl.axis * s;
        pts.push(Point3::from(c));
        let base = pts.len();
        for i in 0..na {
            let a = std::f64::consts::TAU * i as f64 / na as f64;
            pts.push(Point3::from(c + (e1 * a.cos() + e2 * a.sin()) * hl.radius));
        }
        for i in 0..na {
            segs.push((base + i, base + (i + 1) % na));
            segs.push((base - 1, base + i));
            if j < nl {
                segs.push((base + i, base + i + na + 1));
            }
        }
    }
    let rect = roi_of(cam, &pts, &segs, 0.02)?;
    // Range for the PSF: nearest point of the axis segment, at least a radius.
    let s = (-hl.center).dot(&hl.axis).clamp(-hl.half_len, hl.half_len);
    let range_m = (hl.center + hl.axis * s).norm().max(hl.radius);
    let depth = (hl.center + hl.axis * s).z.max(ROI_NEAR_M);
    let diameter_px = cam.fx.min(cam.fy) * 2.0 * hl.radius / depth;
    Some(Roi {
        rect,
        range_m,
        fine: diameter_px < 4.0,
    })
}

/// Groups of overlapping ROIs (after dilating each by its PSF radius), each
/// with one PSF range: the area-weighted mean of its members' ranges.
fn psf_groups(cam: &CameraModel, water: &WaterParams, rois: &[Option<Roi>]) -> Vec<(Rect, f64)> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let f = 0.5 * (cam.fx + cam.fy);
    let mut groups: Vec<(Rect, f64, f64)> = Vec::new(); // rect, Σ area·range, Σ area
    for r in rois.iter().flatten() {
        let margin = Psf::for_range(water, f, r.range_m).radius_px().ceil() as usize;
        let rect = r.rect.dilated(margin, w, h);
        let area = (r.rect.width() * r.rect.height()) as f64;
        groups.push((rect, area * r.range_m, area));
    }
    loop {
        let mut merged = false;
        'outer: for i in 0..groups.len() {
            for j in i + 1..groups.len() {
                if groups[i].0.overlaps(&groups[j].0) {
                    let g = groups.swap_remove(j);
                    groups[i] = (
                        groups[i].0.union(&g.0),
                        groups[i].1 + g.1,
                        groups[i].2 + g.2,
                    );
                    merged = true;
                    break 'outer;
                }
            }
        }
        if !merged {
            break;
        }
    }
    groups
        .into_iter()
        .map(|(r, ar, a)| (r, ar / a.max(1e-12)))
        .collect()
}

/// The module grid of a marker (see `CodeSet::module_grid`).
fn grid_of(codes: CodeSet, id: MarkerId) -> Result<Vec<bool>, SimError> {
    match codes.module_grid(id) {
        Ok(g) => Ok(g),
        Err(e) => Err(SimError::Marker {
            codes,
            id,
            reason: e.to_string(),
        }),
    }
}

/// The scene's plates and hulls in the camera frame; without `grids` every
/// module is white (enough for visibility, no code tables needed).
fn build_objects(
    scene: &Scene,
    camera_from_world: &Pose,
    grids: bool,
) -> Result<Objects, SimError> {
    let up = camera_from_world.rotation * scene.up_world;
    let mut objects = Objects {
        plates: Vec::with_capacity(scene.markers.len()),
        hulls: Vec::with_capacity(scene.hulls.len()),
        up,
    };
    for m in &scene.markers {
        let grid = if grids {
            grid_of(m.codes, m.id)?
        } else {
            vec![true; m.codes.modules() * m.codes.modules()]
        };
        objects.plates.push(Plate::new(
            &(camera_from_world * m.world_from_marker),
            m.codes.modules(),
            m.side_m,
            grid,
            &up,
        ));
    }
    for hl in &scene.hulls {
        objects.hulls.push(Hull::new(
            &(camera_from_world * hl.world_from_body),
            hl.diameter_m,
            hl.length_m,
        ));
    }
    Ok(objects)
}

/// Which markers `cam` at `world_from_camera` sees and where their corners
/// project, without rendering (the same computation as
/// [`RenderOutput::visible`]; `observer`, `camera`, `frame_seq` are 0).
pub fn visible_in_view(
    cam: &CameraModel,
    world_from_camera: &Pose,
    scene: &Scene,
) -> Result<Vec<VisibleMarker>, SimError> {
    if let Some(p) = cam.problem() {
        return Err(SimError::Camera(p));
    }
    if !pose_is_finite(world_from_camera) {
        return Err(SimError::NonFinitePose {
            what: "world_from_camera".into(),
        });
    }
    for m in &scene.markers {
        if !pose_is_finite(&m.world_from_marker)
            || m.side_m.is_nan()
            || m.side_m <= 0.0
            || m.side_m.is_infinite()
        {
            return Err(SimError::NonFinitePose {
                what: format!("marker {}#{}", m.codes, m.id),
            });
        }
    }
    let objects = build_objects(scene, &world_from_camera.inverse(), false)?;
    Ok(visible_markers(cam, scene, &objects))
}

/// Markers whose front face is at least partly visible: projected corners
/// (in `CodeSet::corners_3d` order) and the fraction of the black square's
/// face that is in frame, facing the camera and not occluded.
fn visible_markers(cam: &CameraModel, scene: &Scene, objects: &Objects) -> Vec<VisibleMarker> {
    let mut out = Vec::new();
    let k = 12usize;
    for (m, plate) in scene.markers.iter().zip(&objects.plates) {
        let camera_from_marker = |p: &Point3<f64>| {
            Point3::from(plate.origin + plate.ex * p.x + plate.ey * p.y + plate.normal * p.z)
        };
        let corners: Vec<Point3<f64>> = m
            .codes
            .corners_3d(m.side_m)
            .iter()
            .map(camera_from_marker)
            .collect();
        if corners.iter().any(|c| c.z <= ROI_NEAR_M) {
            continue;
        }
        if plate.normal.dot(&plate.origin) >= 0.0 {
            continue; // seen from behind
        }
        let mut seen = 0usize;
        for j in 0..k {
            for i in 0..k {
                let a = m.side_m * ((i as f64 + 0.5) / k as f64 - 0.5);
                let b = m.side_m * ((j as f64 + 0.5) / k as f64 - 0.5);
                let p = Point3::from(plate.origin + plate.ex * a + plate.ey * b);
                let in_frame = cam.project(&p).is_some_and(|q| {
                    q.x >= -0.5
                        && q.y >= -0.5
                        && q.x <= cam.width as f64 - 0.5
                        && q.y <= cam.height as f64 - 0.5
                });
                if in_frame && objects.sees(&p) {
                    seen += 1;
                }
            }
        }
        if seen == 0 {
            continue;
        }
        let corners_px = corners
            .iter()
            .filter_map(|c| cam.project(c))
            .map(|q| [q.x, q.y])
            .collect();
        out.push(VisibleMarker {
            observer: 0,
            camera: 0,
            frame_seq: 0,
            codes: m.codes,
            marker: m.id,
            target_vehicle: m.owner,
            corners_px,
            visible_fraction: seen as f32 / (k * k) as f32,
            range_m: plate.origin.norm(),
        });
    }
    out
}

/// True when every corner of `v` is inside the image (pixel-centre convention).
pub fn all_corners_in_frame(cam: &CameraModel, v: &VisibleMarker) -> bool {
    v.corners_px.len() == v.codes.corner_count()
        && v.corners_px.iter().all(|c| {
            c[0] >= -0.5
                && c[1] >= -0.5
                && c[0] <= cam.width as f64 - 0.5
                && c[1] <= cam.height as f64 - 0.5
        })
}

/// What vehicle `vehicle`'s camera `camera_index` sees: the library call
/// behind `shoal sim render`. `truth` gives every vehicle's pose (the
/// observer's own hull occludes like any other); `frame_seq` goes into the
/// ground truth.
pub fn render_fleet_view(
    renderer: &mut Renderer,
    fleet: &Fleet,
    truth: &[VehicleTruth],
    vehicle: VehicleId,
    camera_index: u8,
    water: &WaterParams,
    time_s: f64,
    frame_seq: u64,
    seed: u64,
) -> Result<RenderOutput, SimError> {
    let v = fleet.vehicle(vehicle).ok_or(SimError::UnknownVehicle {
        vehicle,
        context: "fleet",
    })?;
    let cam = v
        .cameras
        .get(camera_index as usize)
        .ok_or(SimError::UnknownCamera {
            vehicle,
            camera: camera_index,
            count: v.cameras.len(),
        })?;
    let me = truth
        .iter()
        .find(|t| t.vehicle == vehicle)
        .ok_or(SimError::UnknownVehicle {
            vehicle,
            context: "ground truth",
        })?;
    let scene = Scene::from_fleet(fleet, truth);
    let world_from_camera = me.world_from_body * cam.body_from_camera;
    let mut out = renderer.render(&cam.model, &world_from_camera, &scene, water, time_s, seed)?;
    for vm in &mut out.visible {
        vm.observer = vehicle;
        vm.camera = camera_index;
        vm.frame_seq = frame_seq;
    }
    Ok(out)
}

/// Where [`write_frame_pair`] puts the clean twin of `path`: `frame.png` → `frame_clean.png`.
pub fn clean_twin_path(path: &Path) -> std::path::PathBuf {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "frame".into());
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().into_owned())
        .unwrap_or_else(|| "png".into());
    path.with_file_name(format!("{stem}_clean.{ext}"))
}

/// Write a frame to `path` and its clean twin next to it
/// ([`clean_twin_path`]); returns the twin's path. What `shoal sim render` does.
pub fn write_frame_pair(out: &RenderOutput, path: &Path) -> Result<std::path::PathBuf, SimError> {
    write_png(&out.image, path)?;
    let twin = clean_twin_path(path);
    write_png(&out.clean, &twin)?;
    Ok(twin)
}

/// Write an 8-bit grey image as PNG.
pub fn write_png(img: &GrayImage, path: &Path) -> Result<(), SimError> {
    let buf =
        image::GrayImage::from_raw(img.width, img.height, img.data.clone()).ok_or_else(|| {
            SimError::ImageWrite {
                path: path.to_path_buf(),
                message: format!("{} bytes for {}x{}", img.data.len(), img.width, img.height),
            }
        })?;
    buf.save(path).map_err(|e| SimError::ImageWrite {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}
