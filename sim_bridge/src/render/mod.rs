//! The image synthesizer: what a calibrated camera sees underwater.
//!
//! Geometry is exact: every sample ray is the camera model's inverse
//! distortion of its sub-pixel position (`CameraModel::project` of a marker
//! corner lands where the rendered corner is), and pixels are anti-aliased
//! by adaptive supersampling on a sheared 8x8 grid (64 distinct offsets in
//! x and in y), so edges can be measured to a few hundredths of a pixel.
//! Pixel centres are at integer coordinates (OpenCV).
//!
//! With a flat port (`render_with_port`) each in-air ray refracts at the
//! window's two surfaces and continues in the water from the outer one; the
//! regions of interest and the ground-truth corners are projected through
//! the port (`FlatPort::project`), so they stay exact too.
//!
//! Only pixels whose region of interest (the projected bounds of a marker
//! plate or a hull) is on screen are ray-cast; the water background, the
//! veil, vignetting and noise are analytic. The water model and its sources
//! are in `docs/water-model.md`.
//!
//! Speed (issue #18): the rays of a camera's pixel centres and corners are
//! solved once and kept for its later frames; a frame's work runs in bands
//! of rows over [`Renderer::threads`] threads, each value computed in the
//! same order whatever their number, so frames are bit-identical on any
//! number of threads.

mod cast;
pub mod codec;
pub mod effects;
mod frame_files;
#[cfg(test)]
mod geometry_tests;
pub mod motion;
pub mod noise;
pub mod optics;
mod par;
mod rays;
pub mod realistic;
mod roi;
mod scene;
pub mod trace;
mod visibility;

pub use frame_files::{clean_twin_path, write_frame_pair, write_png};
pub use scene::{facing_camera, Scene, SceneHull, SceneMarker};
pub use visibility::{all_corners_in_frame, visible_in_view, visible_in_view_with_port};

use crate::error::SimError;
use crate::water::WaterParams;
use cast::{sample_offsets, Band, Caster, Medium};
use nalgebra::Vector3;
use optics::{blur_add_threads, quantize_row, round_to_u8_f32, Ambient, LampIntegral, Psf, Rect};
use rays::RayTable;
use roi::{hull_roi, plate_roi, psf_groups, Roi};
use shoal_proto::config::Fleet;
use shoal_proto::geometry::pose_is_finite;
use shoal_proto::{CameraModel, FlatPort, GrayImage, Pose, VehicleId, VehicleTruth, VisibleMarker};
use trace::Objects;
use visibility::{build_objects, visible_markers};

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

/// Reusable frame buffers and the camera's viewing rays (solved once per
/// camera model, reused by its later frames); one per thread that renders.
/// A frame's work is split over [`Renderer::threads`] threads; the output
/// does not depend on their number.
#[derive(Debug)]
pub struct Renderer {
    /// Samples per axis for pixels that straddle an edge (default 8: 64 samples).
    pub supersample: usize,
    /// Threads a frame is rendered on (default: the machine's parallelism, at most 8).
    pub threads: usize,
    offsets: Vec<(f64, f64)>,
    rays: RayTable,
    veil_rays: Option<VeilRays>,
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

impl Renderer {
    pub fn new() -> Self {
        Renderer {
            supersample: 8,
            threads: par::default_threads(),
            offsets: sample_offsets(8),
            rays: RayTable::default(),
            veil_rays: None,
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
        self.render_with_port(cam, None, world_from_camera, scene, water, time_s, seed)
    }

    /// [`Renderer::render`] with the camera behind `port` when given: `cam`
    /// is then the lens in air, and every ray refracts through the window.
    #[allow(clippy::too_many_arguments)]
    pub fn render_with_port(
        &mut self,
        cam: &CameraModel,
        port: Option<&FlatPort>,
        world_from_camera: &Pose,
        scene: &Scene,
        water: &WaterParams,
        time_s: f64,
        seed: u64,
    ) -> Result<RenderOutput, SimError> {
        if let Some(p) = cam.problem() {
            return Err(SimError::Camera(p));
        }
        if let Some(p) = port.and_then(FlatPort::problem) {
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

        let mut objects = build_objects(scene, &camera_from_world, true)?;
        objects.port = port.copied();

        let ambient = Ambient::new(water, time_s);
        let medium = Medium {
            c: water.c_per_m,
            s: water.forward_scatter,
            illum: water.illumination * ambient.temporal,
            lamp_power: water.lamp_power,
            lamp: LampIntegral::new(water.c_per_m),
        };

        // Regions of interest, and the regions their forward scatter reaches.
        let rois: Vec<Option<Roi>> = objects
            .plates
            .iter()
            .map(|p| plate_roi(cam, port, p))
            .chain(objects.hulls.iter().map(|hl| hull_roi(cam, port, hl)))
            .collect();
        let blurs: Vec<(Rect, Psf)> = psf_groups(cam, water, &rois)
            .into_iter()
            .map(|(rect, range)| {
                let psf = Psf::for_range(water, 0.5 * (cam.fx + cam.fy), range);
                let margin = psf.radius_px().ceil() as usize + 1;
                (rect.dilated(margin, w, h), psf)
            })
            .collect();
        // Outside these rectangles the frame is water alone: the buffers
        // there are neither written nor read.
        let active: Vec<Rect> = rois
            .iter()
            .flatten()
            .map(|r| r.rect)
            .chain(blurs.iter().map(|b| b.0))
            .collect();
        self.reset_buffers(w, n, &active);
        let mut rows = vec![false; h];
        for r in rois.iter().flatten() {
            rows[r.rect.y0..=r.rect.y1].fill(true);
        }
        self.rays.prepare(cam, &rows, self.threads);
        self.cast(cam, &objects, &rois, &medium);

        // Forward scatter: blur the scattered light per group of overlapping ROIs.
        for (region, psf) in &blurs {
            blur_add_threads(
                &self.scatter,
                w,
                *region,
                psf,
                &mut self.scattered,
                &mut self.scratch,
                self.threads,
            );
        }

        // Compose: veil, vignetting, exposure (docs/water-model.md, Eq. (W1)),
        // then noise and quantization.
        let mut image = vec![0u8; n];
        let mut clean = vec![0u8; n];
        self.finish(
            cam,
            port,
            water,
            &ambient,
            &medium,
            &up,
            &active,
            seed,
            (&mut image, &mut clean),
        );

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

    /// Size the buffers for `n` pixels and set them to the water alone
    /// (nothing hit: no direct or scattered light, full veil) inside `active`.
    fn reset_buffers(&mut self, w: usize, n: usize, active: &[Rect]) {
        let zero = [
            &mut self.clean,
            &mut self.direct,
            &mut self.scatter,
            &mut self.scattered,
        ];
        if self.veil.len() != n {
            for buf in zero {
                buf.clear();
                buf.resize(n, 0.0);
            }
            for buf in [&mut self.veil, &mut self.lamp] {
                buf.clear();
                buf.resize(n, 1.0);
            }
            return;
        }
        for buf in zero {
            for r in active {
                for y in r.y0..=r.y1 {
                    buf[y * w + r.x0..=y * w + r.x1].fill(0.0);
                }
            }
        }
        for buf in [&mut self.veil, &mut self.lamp] {
            for r in active {
                for y in r.y0..=r.y1 {
                    buf[y * w + r.x0..=y * w + r.x1].fill(1.0);
                }
            }
        }
    }

    /// Ray-cast every pixel inside some ROI, in bands of rows over the threads.
    fn cast(
        &mut self,
        cam: &CameraModel,
        objects: &Objects,
        rois: &[Option<Roi>],
        medium: &Medium,
    ) {
        const BAND_ROWS: usize = 8;
        let w = cam.width as usize;
        let caster = Caster {
            cam,
            objects,
            rois,
            medium,
            rays: &self.rays,
            offsets: &self.offsets,
            fine: rois
                .iter()
                .map(|r| r.as_ref().is_some_and(|r| r.fine))
                .collect(),
        };
        let in_roi = |y0: usize, rows: usize| {
            rois.iter()
                .flatten()
                .any(|r| r.rect.y0 < y0 + rows && r.rect.y1 >= y0)
        };
        let chunk = BAND_ROWS * w;
        let tasks: Vec<Band<'_>> = self
            .clean
            .chunks_mut(chunk)
            .zip(self.direct.chunks_mut(chunk))
            .zip(self.scatter.chunks_mut(chunk))
            .zip(self.veil.chunks_mut(chunk))
            .zip(self.lamp.chunks_mut(chunk))
            .enumerate()
            .map(|(i, ((((clean, direct), scatter), veil), lamp))| Band {
                y0: i * BAND_ROWS,
                clean,
                direct,
                scatter,
                veil,
                lamp,
            })
            .filter(|b| in_roi(b.y0, BAND_ROWS))
            .collect();
        par::run_tasks(tasks, self.threads, |band| caster.cast_band(band));
    }

    /// Final radiance to DN, `exposure · V(x) · [D + h∗F + B(x)·β + lamp
    /// veil]` (kept in `self.dn`), then noise and quantization into
    /// `image`, and the clean twin into `clean`; in bands of rows over the
    /// threads. Outside `active` the frame is the water alone.
    #[allow(clippy::too_many_arguments)]
    fn finish(
        &mut self,
        cam: &CameraModel,
        port: Option<&FlatPort>,
        water: &WaterParams,
        ambient: &Ambient,
        medium: &Medium,
        up: &Vector3<f64>,
        active: &[Rect],
        seed: u64,
        (image, clean_out): (&mut [u8], &mut [u8]),
    ) {
        const BAND_ROWS: usize = 16;
        let (w, h) = (cam.width as usize, cam.height as usize);
        if !self
            .veil_rays
            .as_ref()
            .is_some_and(|g| g.cam == *cam && g.port.as_ref() == port)
        {
            self.veil_rays = Some(VeilRays::new(cam, port));
        }
        let Some(grid) = self.veil_rays.as_ref() else {
            return;
        };
        let (veil_grid, vig_grid) = grid.veil_and_vignetting(water, ambient, up);
        let lamp_veil = (water.lamp_power * water.lamp_backscatter * medium.lamp.total) as f32;
        let gain = (255.0 * water.exposure) as f32;
        self.dn.clear();
        self.dn.resize(w * h, 0.0);
        let chunk = BAND_ROWS * w;
        let tasks: Vec<_> = self
            .dn
            .chunks_mut(chunk)
            .zip(image.chunks_mut(chunk))
            .zip(clean_out.chunks_mut(chunk))
            .enumerate()
            .collect();
        let (gw, gh, step) = (grid.gw, grid.gh, VeilRays::STEP);
        let inv = 1.0 / step as f32;
        let (direct, scattered) = (&self.direct, &self.scattered);
        let (veil, lamp, clean) = (&self.veil, &self.lamp, &self.clean);
        par::run_tasks(tasks, self.threads, |(band, ((dn, img), cln))| {
            let mut veil_row = vec![0.0f32; gw];
            let mut vig_row = vec![0.0f32; gw];
            // Per pixel of the row: the veil and the vignetting.
            let (mut b_px, mut vg_px) = (vec![0.0f32; w], vec![0.0f32; w]);
            let mut spans: Vec<(usize, usize)> = Vec::new();
            let rows = dn.len() / w;
            for r in 0..rows {
                let y = band * BAND_ROWS + r;
                let fy = y as f32 * inv;
                let gy = (fy as usize).min(gh - 2);
                let ty = fy - gy as f32;
                for gx in 0..gw {
                    veil_row[gx] =
                        veil_grid[gy * gw + gx] * (1.0 - ty) + veil_grid[(gy + 1) * gw + gx] * ty;
                    vig_row[gx] =
                        vig_grid[gy * gw + gx] * (1.0 - ty) + vig_grid[(gy + 1) * gw + gx] * ty;
                }
                // Interpolated along the row one grid cell at a time (the
                // same weights as pixel by pixel, in loops that vectorize).
                for (gx, (b_cell, vg_cell)) in b_px
                    .chunks_mut(step)
                    .zip(vg_px.chunks_mut(step))
                    .enumerate()
                {
                    let (b0, b1) = (veil_row[gx], veil_row[gx + 1]);
                    let (v0, v1) = (vig_row[gx], vig_row[gx + 1]);
                    for (k, (b, vg)) in b_cell.iter_mut().zip(vg_cell.iter_mut()).enumerate() {
                        let tx = k as f32 * inv;
                        *b = b0 * (1.0 - tx) + b1 * tx;
                        *vg = v0 * (1.0 - tx) + v1 * tx;
                    }
                }
                let out = &mut dn[r * w..(r + 1) * w];
                // The water alone everywhere, then the active spans over it.
                for ((o, &b), &vg) in out.iter_mut().zip(&b_px).zip(&vg_px) {
                    *o = gain * vg * (b + lamp_veil);
                }
                let cln = &mut cln[r * w..(r + 1) * w];
                cln.fill(0);
                row_spans(active, y, &mut spans);
                let row = y * w;
                for &(x0, x1) in &spans {
                    for x in x0..=x1 {
                        let (b, vg) = (b_px[x], vg_px[x]);
                        let i = row + x;
                        out[x] = gain
                            * vg
                            * (direct[i] + scattered[i] + b * veil[i] + lamp_veil * lamp[i]);
                        cln[x] = round_to_u8_f32(255.0 * clean[i]);
                    }
                }
                quantize_row(out, y, water, seed, &mut img[r * w..(r + 1) * w]);
            }
        });
    }
}

/// The merged x spans (inclusive) of the rectangles of `rects` on row `y`.
fn row_spans(rects: &[Rect], y: usize, spans: &mut Vec<(usize, usize)>) {
    spans.clear();
    spans.extend(
        rects
            .iter()
            .filter(|r| r.y0 <= y && y <= r.y1)
            .map(|r| (r.x0, r.x1)),
    );
    spans.sort_unstable();
    let mut k = 0;
    for i in 0..spans.len() {
        if k > 0 && spans[i].0 <= spans[k - 1].1 + 1 {
            spans[k - 1].1 = spans[k - 1].1.max(spans[i].1);
        } else {
            spans[k] = spans[i];
            k += 1;
        }
    }
    spans.truncate(k);
}

/// The viewing rays of a coarse grid over the image (every
/// [`VeilRays::STEP`] pixels), where the smooth veil and vignetting are
/// evaluated; kept per camera and port.
#[derive(Debug)]
struct VeilRays {
    cam: CameraModel,
    port: Option<FlatPort>,
    gw: usize,
    gh: usize,
    /// Per grid point: the ray in the water (for the veil's direction),
    /// that ray's length, and the in-air ray's length (for vignetting).
    rays: Vec<(Vector3<f64>, f64, f64)>,
}

impl VeilRays {
    const STEP: usize = 8;

    fn new(cam: &CameraModel, port: Option<&FlatPort>) -> VeilRays {
        let (w, h) = (cam.width as usize, cam.height as usize);
        let gw = (w - 1) / Self::STEP + 2;
        let gh = (h - 1) / Self::STEP + 2;
        let mut rays = Vec::with_capacity(gw * gh);
        for gy in 0..gh {
            for gx in 0..gw {
                let (u, v) = ((gx * Self::STEP) as f64, (gy * Self::STEP) as f64);
                let (x, y) = cam.ray(u, v);
                let d = Vector3::new(x, y, 1.0);
                let norm = d.norm();
                // The veil comes along the in-water ray; vignetting is the lens's.
                let water = match port {
                    None => d,
                    Some(port) => {
                        let (_, (a, b)) = port.refract(x, y);
                        Vector3::new(a, b, 1.0)
                    }
                };
                let water_norm = match port {
                    None => norm,
                    Some(_) => water.norm(),
                };
                rays.push((water, water_norm, norm));
            }
        }
        VeilRays {
            cam: *cam,
            port: port.copied(),
            gw,
            gh,
            rays,
        }
    }

    /// The veil `B(x)·β` and the vignetting `V(x)` on the grid.
    fn veil_and_vignetting(
        &self,
        water: &WaterParams,
        ambient: &Ambient,
        up: &Vector3<f64>,
    ) -> (Vec<f32>, Vec<f32>) {
        let (w, h) = (self.cam.width as f64, self.cam.height as f64);
        let mut veil = Vec::with_capacity(self.rays.len());
        let mut vig = Vec::with_capacity(self.rays.len());
        for (i, (d, d_norm, norm)) in self.rays.iter().enumerate() {
            let (gx, gy) = (i % self.gw, i / self.gw);
            let (u, v) = ((gx * Self::STEP) as f64, (gy * Self::STEP) as f64);
            let cos_zenith = d.dot(up) / d_norm;
            let dir_gain = (1.0 + water.backscatter_up_gain * cos_zenith).max(0.1);
            let spatial = ambient.spatial(u / w, v / h);
            veil.push(
                (water.backscatter_inf * dir_gain * spatial * ambient.temporal * water.illumination)
                    as f32,
            );
            let cos_t = 1.0 / norm;
            vig.push((1.0 - water.vignetting * (1.0 - cos_t.powi(4))) as f32);
        }
        (veil, vig)
    }
}

/// Vehicle `vehicle`'s camera `camera_index` in `fleet`, and where it is in
/// the world by `truth`; an error names the unknown vehicle or camera.
pub fn fleet_camera<'a>(
    fleet: &'a Fleet,
    truth: &[VehicleTruth],
    vehicle: VehicleId,
    camera_index: u8,
) -> Result<(&'a shoal_proto::config::Camera, Pose), SimError> {
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
    Ok((cam, me.world_from_body * cam.body_from_camera))
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
    let (cam, world_from_camera) = fleet_camera(fleet, truth, vehicle, camera_index)?;
    let scene = Scene::from_fleet(fleet, truth);
    let mut out = renderer.render_with_port(
        &cam.model,
        cam.port.as_ref(),
        &world_from_camera,
        &scene,
        water,
        time_s,
        seed,
    )?;
    for vm in &mut out.visible {
        vm.observer = vehicle;
        vm.camera = camera_index;
        vm.frame_seq = frame_seq;
    }
    Ok(out)
}

#[cfg(test)]
mod thread_tests {
    use super::*;
    use crate::world::{Formation, SwarmWorld};
    use shoal_proto::CodeSet;

    #[test]
    fn frames_are_the_same_bytes_on_any_number_of_threads() {
        let fleet = Fleet::load(
            &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/fleets/paper.toml"),
        )
        .unwrap();
        let world = SwarmWorld::new(&fleet, Formation::Line, 2.0, 1).unwrap();
        let mut truth = world.truth();
        truth[2].world_from_body.translation.z += 0.5;
        let water = WaterParams::preset(0.5);
        let mut one = Renderer::new();
        one.threads = 1;
        let a = render_fleet_view(&mut one, &fleet, &truth, 10, 4, &water, 1.0, 3, 9).unwrap();
        assert_eq!(a.visible.len(), 2, "two markers in view");
        let dn_one = one.last_frame_dn().to_vec();
        // A marker through a flat port too, then the fleet view again (the
        // buffers of the other frame must not leak into this one).
        let cam = CameraModel::vehicle_1440();
        let scene = Scene::single_marker(
            CodeSet::Shoal,
            17,
            0.1,
            facing_camera([0.0, 0.0, 0.6], [0.0, 0.35, 0.0]),
        );
        let port = FlatPort {
            distance_m: 0.010,
            glass_m: 0.008,
            n_glass: FlatPort::N_ACRYLIC,
            n_water: FlatPort::N_SEA_WATER,
        };
        let murky = WaterParams::preset(8.22);
        let m1 = one
            .render_with_port(&cam, Some(&port), &Pose::identity(), &scene, &murky, 0.0, 4)
            .unwrap();
        for threads in [2, 3, 8] {
            let mut many = Renderer::new();
            many.threads = threads;
            let m = many
                .render_with_port(&cam, Some(&port), &Pose::identity(), &scene, &murky, 0.0, 4)
                .unwrap();
            assert_eq!(m, m1, "{threads} threads, port");
            let b = render_fleet_view(&mut many, &fleet, &truth, 10, 4, &water, 1.0, 3, 9).unwrap();
            assert_eq!(b, a, "{threads} threads");
            assert!(
                many.last_frame_dn()
                    .iter()
                    .zip(&dn_one)
                    .all(|(x, y)| x.to_bits() == y.to_bits()),
                "{threads} threads: DN"
            );
        }
    }
}
