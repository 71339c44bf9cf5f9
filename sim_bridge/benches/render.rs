//! One 1440x1080 frame with two vehicles in view: vehicle 10's starboard
//! camera in the paper fleet's line abreast (2 m), vehicle 17 (the far one)
//! moved 0.5 m deeper so it shows below vehicle 15; water 0.5 /m, with noise.
//!
//! The same and the water alone on one thread too (`threads = 1`: the
//! frame's CPU time; the others use the machine's parallelism).
//!
//! Also single markers at 600 mm (0.5 and 8.22 /m; 0.5 /m through a flat port too), the water alone with and
//! without noise, and the paper's 2448x2048 Eq. (3) camera.
//!
//! Run: `cargo bench -p shoal-sim-bridge --bench render`.
//! On a loaded machine the CPU time per frame is steadier:
//! `cargo run --release -p shoal-sim-bridge --example render_cpu -- 15`.

use criterion::{criterion_group, criterion_main, Criterion};
use shoal_proto::config::Fleet;
use shoal_proto::{CameraModel, CodeSet, Pose};
use shoal_sim_bridge::render::{facing_camera, render_fleet_view, Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;
use shoal_sim_bridge::world::{Formation, SwarmWorld};
use std::path::Path;

/// The paper fleet in line abreast (2 m), vehicle 17 0.5 m deeper, and the 0.5 /m water.
fn two_vehicle_scene() -> (Fleet, Vec<shoal_proto::VehicleTruth>, WaterParams) {
    let fleet =
        Fleet::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/fleets/paper.toml"))
            .expect("paper fleet");
    let world = SwarmWorld::new(&fleet, Formation::Line, 2.0, 1).unwrap();
    let mut truth = world.truth();
    truth[2].world_from_body.translation.z += 0.5;
    (fleet, truth, WaterParams::preset(0.5))
}

/// The two-vehicle frame and the water alone on one thread: a frame's CPU time.
fn one_thread(c: &mut Criterion) {
    let (fleet, truth, water) = two_vehicle_scene();
    let mut single = Renderer::new();
    single.threads = 1;
    let mut seed = 0;
    c.bench_function("render_1440x1080_two_vehicles_1thread", |b| {
        b.iter(|| {
            seed += 1;
            render_fleet_view(&mut single, &fleet, &truth, 10, 4, &water, 0.0, seed, seed)
                .expect("render")
        })
    });
    let cam = CameraModel::vehicle_1440();
    c.bench_function("render_1440x1080_empty_noise_1thread", |b| {
        b.iter(|| {
            single
                .render(&cam, &Pose::identity(), &Scene::empty(), &water, 0.0, 1)
                .expect("render")
        })
    });
}

fn bench(c: &mut Criterion) {
    let (fleet, truth, water) = two_vehicle_scene();
    let mut renderer = Renderer::new();
    let probe =
        render_fleet_view(&mut renderer, &fleet, &truth, 10, 4, &water, 0.0, 0, 1).expect("render");
    let owners: std::collections::BTreeSet<u32> =
        probe.visible.iter().map(|v| v.target_vehicle).collect();
    assert!(
        owners.len() == 2,
        "two vehicles' markers in view: {owners:?}"
    );
    println!(
        "visible markers: {:?} (vehicles {owners:?})",
        probe.visible.iter().map(|v| v.marker).collect::<Vec<_>>()
    );
    let mut seed = 0;
    c.bench_function("render_1440x1080_two_vehicles", |b| {
        b.iter(|| {
            seed += 1;
            render_fleet_view(
                &mut renderer,
                &fleet,
                &truth,
                10,
                4,
                &water,
                0.0,
                seed,
                seed,
            )
            .expect("render")
        })
    });
    let cam = CameraModel::vehicle_1440();
    let scene = Scene::single_marker(
        CodeSet::Shoal,
        17,
        0.1,
        facing_camera([0.0, 0.0, 0.6], [0.0, 0.35, 0.0]),
    );
    let murky = WaterParams::preset(8.22);
    c.bench_function("render_1440x1080_marker_600mm_c8.22", |b| {
        b.iter(|| {
            renderer
                .render(&cam, &Pose::identity(), &scene, &murky, 0.0, 1)
                .expect("render")
        })
    });
    c.bench_function("render_1440x1080_marker_600mm_c0.5", |b| {
        b.iter(|| {
            renderer
                .render(&cam, &Pose::identity(), &scene, &water, 0.0, 1)
                .expect("render")
        })
    });
    // The same marker through a flat port (10 mm air, 8 mm acrylic; the lens
    // in air with the focal length / 1.34, so the view matches).
    let port = shoal_proto::FlatPort {
        distance_m: 0.010,
        glass_m: 0.008,
        n_glass: shoal_proto::FlatPort::N_ACRYLIC,
        n_water: shoal_proto::FlatPort::N_SEA_WATER,
    };
    let lens = CameraModel {
        fx: cam.fx / port.n_water,
        fy: cam.fy / port.n_water,
        ..cam
    };
    c.bench_function("render_1440x1080_marker_600mm_c0.5_port", |b| {
        b.iter(|| {
            renderer
                .render_with_port(
                    &lens,
                    Some(&port),
                    &Pose::identity(),
                    &scene,
                    &water,
                    0.0,
                    1,
                )
                .expect("render")
        })
    });
    // The water alone (no marker), with and without the sensor's noise.
    let empty = Scene::empty();
    for (name, w) in [
        ("render_1440x1080_empty_noiseless", water.noiseless()),
        ("render_1440x1080_empty_noise", water),
    ] {
        c.bench_function(name, |b| {
            b.iter(|| {
                renderer
                    .render(&cam, &Pose::identity(), &empty, &w, 0.0, 1)
                    .expect("render")
            })
        });
    }
    // The paper's Eq. (3) camera, 2448x2048.
    let eq3 = CameraModel::paper_eq3();
    let far = Scene::single_marker(
        CodeSet::Shoal,
        17,
        0.1,
        facing_camera([0.0, 0.0, 0.8], [0.0, 0.35, 0.0]),
    );
    c.bench_function("render_2448x2048_marker_800mm_c8.22", |b| {
        b.iter(|| {
            renderer
                .render(&eq3, &Pose::identity(), &far, &murky, 0.0, 1)
                .expect("render")
        })
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10);
    targets = bench, one_thread
}
criterion_main!(benches);
