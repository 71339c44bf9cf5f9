//! Contact sheet of the water presets: shoal's enhanced marker #17, 100 mm,
//! 600 mm in front of the vehicles' 1440x1080 camera, turned 20° (the
//! paper's §6.2 set-up), under each of the paper's attenuation coefficients
//! (left to right, top to bottom: 0.126, 0.5, 1.38, 3.92, 5.16 / 6.12, 8.22,
//! 10.13, 12.20, 14.20 per metre). Each tile is a 360x360 crop around the
//! marker at full resolution, the last column of the sheet is the clean twin.
//!
//! Run: `cargo run -p shoal-sim-bridge --example contact_sheet [out.png]`
//! (default `docs/img/water-contact-sheet.png`).

use shoal_proto::{CameraModel, CodeSet, GrayImage, Pose};
use shoal_sim_bridge::render::{facing_camera, write_png, Renderer, Scene};
use shoal_sim_bridge::water::WaterPresets;
use std::path::PathBuf;

const TILE: usize = 360;
const GAP: usize = 6;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::env::args()
        .nth(1)
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../docs/img/water-contact-sheet.png")
        });
    let cam = CameraModel::vehicle_1440();
    let pose = facing_camera([0.0, 0.0, 0.6], [0.0, 20f64.to_radians(), 0.0]);
    let scene = Scene::single_marker(CodeSet::Shoal, 17, 0.1, pose);
    let presets = WaterPresets::builtin();
    let coefficients = presets.coefficients();
    let mut renderer = Renderer::new();
    let cols = 6;
    let rows = coefficients.len().div_ceil(5);
    let (w, h) = (
        cols * TILE + (cols - 1) * GAP,
        rows * TILE + (rows - 1) * GAP,
    );
    let mut sheet = GrayImage::filled(w as u32, h as u32, 255);
    let centre = cam
        .project(&nalgebra::Point3::from(pose.translation.vector))
        .ok_or("marker behind camera")?;
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
        blit(&frame.image, k % 5, k / 5);
        if k % 5 == 4 || k + 1 == coefficients.len() {
            blit(&frame.clean, 5, k / 5);
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
        println!("c = {c:>6.3} /m: crop min {lo:>3} max {hi:>3}");
    }
    write_png(&sheet, &out)?;
    println!("wrote {}", out.display());
    Ok(())
}
