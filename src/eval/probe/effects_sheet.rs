//! `shoal eval probe effects-sheet`: contact sheet of the camera effects of
//! issue #16 (`docs/water-model.md`, "Camera effects"). shoal's enhanced
//! marker #17, 100 mm, 1 m in front of the vehicles' 1440x1080 camera, up
//! and right of the axis (so vignetting and the lamps' beams show), the
//! camera sliding sideways at 0.3 m/s and turning at 8°/s, in 1.38 /m water.
//! Tiles (300x300 crops at full resolution, left to right, top to bottom):
//! ideal; each image effect alone in `Effect::ALL` order; all of them
//! (the realistic profile); the clean twin. Each tile is named in a strip
//! above it. Calibration error changes no pixel and has no tile.

use super::restore_sheet::{imwrite, label};
use crate::eval::EvalError;
use nalgebra::Vector3;
use shoal_proto::{CameraModel, CodeSet, GrayImage, Pose};
use shoal_sim_bridge::profile::{CameraProfile, Effect};
use shoal_sim_bridge::render::motion::{RigidMotion, Twist};
use shoal_sim_bridge::render::realistic::render_profiled;
use shoal_sim_bridge::render::{facing_camera, Renderer, Scene};
use shoal_sim_bridge::water::WaterPresets;
use std::path::PathBuf;

const TILE: usize = 300;
const GAP: usize = 6;
const COLS: usize = 7;
/// Height of the name strip above each tile.
const LABEL_H: usize = 24;

/// The effects with a tile of their own, in sheet order: every one but the
/// calibration error, which changes no pixel.
fn tile_effects() -> impl Iterator<Item = Effect> {
    Effect::ALL
        .into_iter()
        .filter(|e| *e != Effect::Calibration)
}

#[derive(Debug, clap::Args)]
pub struct EffectsSheetArgs {
    /// The contact sheet (PNG).
    #[arg(long, default_value = "docs/img/sim-effects-contact-sheet.png")]
    pub out: PathBuf,
    /// Water attenuation (1/m), a preset.
    #[arg(long, default_value_t = 1.38)]
    pub water: f64,
    /// Seed of the frame noise and of the profile's draws.
    #[arg(long, default_value_t = 3)]
    pub seed: u64,
}

pub fn run(a: &EffectsSheetArgs) -> Result<(), EvalError> {
    let cam = CameraModel::vehicle_1440();
    let pose = facing_camera([0.30, -0.12, 1.0], [0.0, 20f64.to_radians(), 0.0]);
    let timeline = RigidMotion {
        world_from_camera: Pose::identity(),
        scene: Scene::single_marker(CodeSet::Shoal, 17, 0.1, pose),
        camera: Twist {
            linear_mps: Vector3::new(0.3, 0.0, 0.0),
            angular_radps: Vector3::new(0.0, 8f64.to_radians(), 0.0),
        },
        targets: Twist::default(),
    };
    let water = WaterPresets::builtin().get(a.water)?;
    let mut profiles: Vec<CameraProfile> = vec![CameraProfile::ideal()];
    profiles.extend(tile_effects().map(|e| CameraProfile::only(&[e])));
    profiles.push(CameraProfile::realistic());
    let profiles: Vec<CameraProfile> = profiles.into_iter().map(|p| p.with_seed(a.seed)).collect();
    let tiles = profiles.len() + 1;
    let rows = tiles.div_ceil(COLS);
    let (w, h) = (
        COLS * TILE + (COLS - 1) * GAP,
        rows * (LABEL_H + TILE) + (rows - 1) * GAP,
    );
    let mut sheet = GrayImage::filled(w as u32, h as u32, 255);
    let centre = cam
        .project(&nalgebra::Point3::from(pose.translation.vector))
        .ok_or_else(|| EvalError::Setup("marker behind the camera".into()))?;
    let (x0, y0) = (
        (centre.x.round() as usize).saturating_sub(TILE / 2),
        (centre.y.round() as usize).saturating_sub(TILE / 2),
    );
    let mut blit = |img: &GrayImage, k: usize| {
        let (col, row) = (k % COLS, k / COLS);
        for y in 0..TILE {
            for x in 0..TILE {
                let v = img.get((x0 + x) as u32, (y0 + y) as u32);
                sheet.data
                    [(row * (LABEL_H + TILE + GAP) + LABEL_H + y) * w + col * (TILE + GAP) + x] = v;
            }
        }
    };
    let mut renderer = Renderer::new();
    let mut clean = None;
    for (k, p) in profiles.iter().enumerate() {
        let f = render_profiled(&mut renderer, p, &cam, None, &timeline, &water, 0.0, a.seed)?;
        blit(&f.output.image, k);
        let r = &f.report;
        crate::outln!(
            "{:>2} {:<16} {:>2} sub-frame(s), {:>4.0} px/s, gain {:.2}, snow {:>4}{}",
            k,
            p.name,
            r.sub_frames,
            r.image_speed_px_per_s,
            r.gain,
            r.snow_particles,
            r.psf
                .as_ref()
                .map_or(String::new(), |s| format!(", PSF {s}"))
        );
        clean = Some(f.output.clean);
    }
    if let Some(c) = clean {
        blit(&c, profiles.len());
    }
    let mut sheet = shoal_node::mat::gray_to_mat(&sheet)
        .map_err(|e| EvalError::Setup(format!("effects sheet: {e}")))?;
    let names = profiles
        .iter()
        .map(|p| p.name.as_str())
        .chain(["clean twin"]);
    for (k, name) in names.enumerate() {
        let (col, row) = (k % COLS, k / COLS);
        let at = opencv::core::Point::new(
            (col * (TILE + GAP) + 4) as i32,
            (row * (LABEL_H + TILE + GAP) + LABEL_H - 7) as i32,
        );
        label(&mut sheet, name, at, 0.55)?;
    }
    imwrite(&a.out, &sheet)?;
    crate::outln!("wrote {}", a.out.display());
    Ok(())
}
