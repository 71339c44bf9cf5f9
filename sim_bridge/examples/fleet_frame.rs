//! Render one vehicle camera's view of the paper fleet line abreast, and
//! its clean twin, as `shoal sim render` does.
//!
//! Run: `cargo run -p shoal-sim-bridge --example fleet_frame [c_per_m] [vehicle] [camera] [out.png]`
//! (defaults: 0.5 /m, vehicle 10, camera 4 = starboard, `/tmp/shoal-frame.png`).

use shoal_proto::config::Fleet;
use shoal_sim_bridge::render::{render_fleet_view, write_frame_pair, Renderer};
use shoal_sim_bridge::water::WaterPresets;
use shoal_sim_bridge::world::{Formation, SwarmWorld};
use std::path::{Path, PathBuf};
use std::time::Instant;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let c: f64 = args.first().map_or(Ok(0.5), |s| s.parse())?;
    let vehicle: u32 = args.get(1).map_or(Ok(10), |s| s.parse())?;
    let camera: u8 = args.get(2).map_or(Ok(4), |s| s.parse())?;
    let out = args
        .get(3)
        .map_or_else(|| PathBuf::from("/tmp/shoal-frame.png"), PathBuf::from);
    let fleet =
        Fleet::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/fleets/paper.toml"))?;
    let world = SwarmWorld::new(&fleet, Formation::Line, 2.0, 1);
    let water = WaterPresets::builtin().get(c)?;
    let mut renderer = Renderer::new();
    let t0 = Instant::now();
    let frame = render_fleet_view(
        &mut renderer,
        &fleet,
        &world.truth(),
        vehicle,
        camera,
        &water,
        world.time_s(),
        0,
        1,
    )?;
    println!("rendered in {:.1} ms", t0.elapsed().as_secs_f64() * 1e3);
    for v in &frame.visible {
        println!(
            "  sees {}#{} of vehicle {} at {:.2} m, {:.0}% visible, corner 0 at ({:.2}, {:.2})",
            v.codes,
            v.marker,
            v.target_vehicle,
            v.range_m,
            100.0 * v.visible_fraction,
            v.corners_px[0][0],
            v.corners_px[0][1]
        );
    }
    let twin = write_frame_pair(&frame, &out)?;
    println!("wrote {} and {}", out.display(), twin.display());
    Ok(())
}
