//! The demo scenario: the paper's three vehicles line abreast; every vehicle
//! has a camera that sees a neighbour's side marker whole.

use shoal_proto::config::Fleet;
use shoal_sim_bridge::render::{all_corners_in_frame, visible_in_view, Scene};
use shoal_sim_bridge::world::{Formation, SwarmWorld};
use std::path::Path;

fn paper_fleet() -> Fleet {
    Fleet::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/fleets/paper.toml"))
        .unwrap()
}

/// Per vehicle: (camera name, marker ID, visible fraction) of markers seen with all corners in frame.
type Views = Vec<(u32, Vec<(String, u32, f32)>)>;

/// For each vehicle: (camera name, marker ID) pairs seen with all corners in frame.
fn whole_views(fleet: &Fleet, world: &SwarmWorld) -> Views {
    let truth = world.truth();
    let scene = Scene::from_fleet(fleet, &truth);
    truth
        .iter()
        .map(|t| {
            let v = fleet.vehicle(t.vehicle).unwrap();
            let mut seen = Vec::new();
            for cam in &v.cameras {
                let world_from_camera = t.world_from_body * cam.body_from_camera;
                for vm in visible_in_view(&cam.model, &world_from_camera, &scene).unwrap() {
                    if vm.target_vehicle != v.id && all_corners_in_frame(&cam.model, &vm) {
                        seen.push((cam.name.clone(), vm.marker, vm.visible_fraction));
                    }
                }
            }
            (v.id, seen)
        })
        .collect()
}

#[test]
fn line_abreast_every_vehicle_sees_a_neighbours_whole_marker() {
    let fleet = paper_fleet();
    // Side cameras see ±30° along-track and sit 0.6–0.95 m ahead of the
    // mid-body markers, so a mutual pair needs ≳ 1.7 m between hulls.
    for (spacing, steps) in [(1.75, 1), (2.0, 4)] {
        let mut world = SwarmWorld::new(&fleet, Formation::Line, spacing, 11).unwrap();
        for step in 0..steps {
            let views = whole_views(&fleet, &world);
            println!(
                "spacing {spacing} m, t = {:.0} s: {views:?}",
                world.time_s()
            );
            for (vehicle, seen) in &views {
                assert!(
                    seen.iter().any(|(_, _, frac)| *frac > 0.99),
                    "spacing {spacing}, step {step}: vehicle {vehicle} sees no neighbour's marker whole: {seen:?}"
                );
            }
            world.step(10.0);
        }
    }
}

#[test]
fn own_markers_are_not_seen_by_own_cameras() {
    let fleet = paper_fleet();
    let world = SwarmWorld::new(&fleet, Formation::Line, 1.5, 1).unwrap();
    let truth = world.truth();
    let scene = Scene::from_fleet(&fleet, &truth);
    for t in &truth {
        let v = fleet.vehicle(t.vehicle).unwrap();
        for cam in &v.cameras {
            let vis = visible_in_view(
                &cam.model,
                &(t.world_from_body * cam.body_from_camera),
                &scene,
            )
            .unwrap();
            assert!(
                vis.iter().all(|m| m.target_vehicle != v.id),
                "{} {}: {vis:?}",
                v.id,
                cam.name
            );
        }
    }
}
