//! CPU time per frame of the renderer on one thread (this thread's
//! scheduler time from /proc, so it hardly depends on the machine's load),
//! and the wall time on the default threads: the bench's two-vehicle frame
//! and the water alone.
//!
//! Run: `cargo run --release -p shoal-sim-bridge --example render_cpu -- [frames]`.

use shoal_proto::config::Fleet;
use shoal_proto::{CameraModel, Pose};
use shoal_sim_bridge::render::{render_fleet_view, Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;
use shoal_sim_bridge::world::{Formation, SwarmWorld};
use std::path::Path;
use std::time::Instant;

/// This thread's CPU time in ns (first field of /proc/thread-self/schedstat).
fn thread_cpu_ns() -> u64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse().ok())
        .unwrap_or(0)
}

fn main() {
    let frames: u64 = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(20);
    let fleet =
        Fleet::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/fleets/paper.toml"))
            .expect("paper fleet");
    let world = SwarmWorld::new(&fleet, Formation::Line, 2.0, 1).expect("world");
    let mut truth = world.truth();
    truth[2].world_from_body.translation.z += 0.5;
    let water = WaterParams::preset(0.5);
    let cam = CameraModel::vehicle_1440();
    let mut one = Renderer::new();
    one.threads = 1;
    let mut many = Renderer::new();
    type Job<'a> = Box<dyn FnMut(&mut Renderer, u64) + 'a>;
    let jobs: Vec<(&str, Job<'_>)> = vec![
        (
            "two_vehicles",
            Box::new(|r: &mut Renderer, s: u64| {
                render_fleet_view(r, &fleet, &truth, 10, 4, &water, 0.0, s, s).expect("render");
            }),
        ),
        (
            "empty_noise",
            Box::new(|r: &mut Renderer, s: u64| {
                r.render(&cam, &Pose::identity(), &Scene::empty(), &water, 0.0, s)
                    .expect("render");
            }),
        ),
    ];
    for (name, mut job) in jobs {
        job(&mut one, 0);
        job(&mut many, 0);
        let c0 = thread_cpu_ns();
        for s in 1..=frames {
            job(&mut one, s);
        }
        let cpu = (thread_cpu_ns() - c0) as f64 / frames as f64 / 1e6;
        let t0 = Instant::now();
        for s in 1..=frames {
            job(&mut many, s);
        }
        let wall = t0.elapsed().as_secs_f64() * 1e3 / frames as f64;
        println!(
            "{name}: 1 thread {cpu:.1} ms CPU per frame; {} threads {wall:.1} ms wall per frame",
            many.threads
        );
    }
}
