//! Wall time of a few representative renders (debug or release).
//!
//! Run: `cargo run --release -p shoal-sim-bridge --example render_timing`.

use shoal_proto::config::Fleet;
use shoal_proto::{CameraModel, CodeSet, Pose};
use shoal_sim_bridge::render::{facing_camera, render_fleet_view, Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;
use shoal_sim_bridge::world::{Formation, SwarmWorld};
use std::path::Path;
use std::time::Instant;

fn time<T>(label: &str, n: u32, mut f: impl FnMut() -> T) {
    f();
    let t0 = Instant::now();
    for _ in 0..n {
        std::hint::black_box(f());
    }
    println!(
        "{label:<44} {:>7.1} ms",
        t0.elapsed().as_secs_f64() * 1e3 / n as f64
    );
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let fleet =
        Fleet::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/fleets/paper.toml"))?;
    let truth = SwarmWorld::new(&fleet, Formation::Line, 2.0, 1).truth();
    let cam = CameraModel::vehicle_1440();
    let mut r = Renderer::new();
    let empty = Scene::empty();
    let marker = Scene::single_marker(
        CodeSet::Shoal,
        17,
        0.1,
        facing_camera([0.0, 0.0, 0.6], [0.0, 0.35, 0.0]),
    );
    let w = WaterParams::preset(0.5);
    time("empty scene, noiseless", 5, || {
        r.render(&cam, &Pose::identity(), &empty, &w.noiseless(), 0.0, 1)
    });
    time("empty scene, noise", 5, || {
        r.render(&cam, &Pose::identity(), &empty, &w, 0.0, 1)
    });
    time("marker at 600 mm, 0.5 /m", 5, || {
        r.render(&cam, &Pose::identity(), &marker, &w, 0.0, 1)
    });
    time("marker at 600 mm, 8.22 /m", 5, || {
        r.render(
            &cam,
            &Pose::identity(),
            &marker,
            &WaterParams::preset(8.22),
            0.0,
            1,
        )
    });
    time("fleet: vehicle 10 starboard, 0.5 /m", 5, || {
        render_fleet_view(&mut r, &fleet, &truth, 10, 4, &w, 0.0, 0, 1)
    });
    let eq3 = CameraModel::paper_eq3();
    let big = Scene::single_marker(
        CodeSet::Shoal,
        17,
        0.1,
        facing_camera([0.0, 0.0, 0.8], [0.0, 0.35, 0.0]),
    );
    time("paper_eq3 2448x2048, marker at 800 mm, 8.22", 2, || {
        r.render(
            &eq3,
            &Pose::identity(),
            &big,
            &WaterParams::preset(8.22),
            0.0,
            1,
        )
    });
    Ok(())
}
