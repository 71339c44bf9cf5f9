//! `shoal eval probe water-sheet`: contact sheet of the simulator's water
//! presets. shoal's enhanced marker #17, 100 mm, 600 mm in front of the
//! vehicles' 1440x1080 camera, turned 20° (the paper's §6.2 set-up), under
//! each attenuation coefficient of the presets (five per row, left to
//! right, top to bottom); each tile a 360x360 crop around the marker at full
//! resolution, the last column of every row the clean twin.

use crate::eval::EvalError;
use shoal_proto::{CameraModel, CodeSet, GrayImage, Pose};
use shoal_sim_bridge::render::{facing_camera, write_png, Renderer, Scene};
use shoal_sim_bridge::water::WaterPresets;
use std::path::PathBuf;

const TILE: usize = 360;
const GAP: usize = 6;
/// Waters per row (the row's clean twin follows them).
const PER_ROW: usize = 5;

#[derive(Debug, clap::Args)]
pub struct WaterSheetArgs {
    /// The contact sheet (PNG).
    #[arg(long, default_value = "docs/img/water-contact-sheet.png")]
    pub out: PathBuf,
    /// Water presets file (configs/water.toml format); default the built-in presets.
    #[arg(long)]
    pub water: Option<PathBuf>,
}

pub fn run(a: &WaterSheetArgs) -> Result<(), EvalError> {
    let cam = CameraModel::vehicle_1440();
    let pose = facing_camera([0.0, 0.0, 0.6], [0.0, 20f64.to_radians(), 0.0]);
    let scene = Scene::single_marker(CodeSet::Shoal, 17, 0.1, pose);
    let presets = match &a.water {
        Some(p) => WaterPresets::load(p)?,
        None => WaterPresets::builtin(),
    };
    let coefficients = presets.coefficients();
    let mut renderer = Renderer::new();
    let cols = PER_ROW + 1;
    let rows = coefficients.len().div_ceil(PER_ROW);
    let (w, h) = (
        cols * TILE + (cols - 1) * GAP,
        rows * TILE + (rows - 1) * GAP,
    );
    let mut sheet = GrayImage::filled(w as u32, h as u32, 255);
    let centre = cam
        .project(&nalgebra::Point3::from(pose.translation.vector))
        .ok_or_else(|| EvalError::Setup("marker behind the camera".into()))?;
    let (x0, y0) = (
        centre.x.round() as usize - TILE / 2,
        centre.y.round() as usize - TILE / 2,
    );
    let mut blit = |img: &GrayImage, col: usize, row: usize| {
        for y in 0..TILE {
            for x in 0..TILE {
                let v = img.get((x0 + x) as u32, (y0 + y) as u32);
                sheet.data[(row * (TILE + GAP) + y) * w + col * (TILE + GAP) + x] = v;
            }
        }
    };
    for (k, &c) in coefficients.iter().enumerate() {
        let water = presets.get(c)?;
        let frame = renderer.render(&cam, &Pose::identity(), &scene, &water, 0.0, k as u64)?;
        blit(&frame.image, k % PER_ROW, k / PER_ROW);
        if k % PER_ROW == PER_ROW - 1 || k + 1 == coefficients.len() {
            blit(&frame.clean, PER_ROW, k / PER_ROW);
        }
        let roi: Vec<u8> = (0..TILE * TILE)
            .map(|i| {
                frame
                    .image
                    .get((x0 + i % TILE) as u32, (y0 + i / TILE) as u32)
            })
            .collect();
        let (lo, hi) = (
            roi.iter().min().copied().unwrap_or(0),
            roi.iter().max().copied().unwrap_or(0),
        );
        crate::outln!("c = {c:>6.3} /m: crop min {lo:>3} max {hi:>3}");
    }
    write_png(&sheet, &a.out)?;
    crate::outln!("wrote {}", a.out.display());
    Ok(())
}
