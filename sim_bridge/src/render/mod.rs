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

mod cast;
pub mod codec;
pub mod effects;
mod frame_files;
#[cfg(test)]
mod geometry_tests;
pub mod motion;
pub mod optics;
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
use cast::{sample_offsets, Medium};
use nalgebra::Vector3;
use optics::{blur_add, quantize_with_noise, Ambient, LampIntegral, Psf};
use roi::{hull_roi, plate_roi, psf_groups, Roi};
use shoal_proto::config::Fleet;
use shoal_proto::geometry::pose_is_finite;
use shoal_proto::{CameraModel, FlatPort, GrayImage, Pose, VehicleId, VehicleTruth, VisibleMarker};
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
            .map(|p| plate_roi(cam, port, p))
            .chain(objects.hulls.iter().map(|hl| hull_roi(cam, port, hl)))
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
        self.compose(cam, port, water, &ambient, &medium, &up);
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

    /// Final radiance to DN: `exposure · V(x) · [D + h∗F + B(x)·β + lamp veil]`.
    fn compose(
        &mut self,
        cam: &CameraModel,
        port: Option<&FlatPort>,
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
                // The veil comes along the in-water ray; vignetting is the lens's.
                let cos_zenith = match port {
                    None => d.dot(up) / norm,
                    Some(port) => {
                        let (_, (a, b)) = port.refract(x, y);
                        let dw = Vector3::new(a, b, 1.0);
                        dw.dot(up) / dw.norm()
                    }
                };
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
