//! The shipped configuration files load, and the paper fleet's cameras and
//! markers point where their comments say.

use nalgebra::Vector3;
use shoal_proto::config::{parse_calibration_yaml, Fleet};
use std::path::Path;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn every_shipped_fleet_and_camera_file_loads() {
    let mut n = 0;
    for dir in ["configs/fleets", "configs/cameras"] {
        for entry in std::fs::read_dir(root().join(dir)).unwrap() {
            let path = entry.unwrap().path();
            match path.extension().and_then(|e| e.to_str()) {
                Some("toml") => {
                    Fleet::load(&path).unwrap_or_else(|e| panic!("{e}"));
                }
                Some("yaml") => {
                    parse_calibration_yaml(&std::fs::read_to_string(&path).unwrap())
                        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
                }
                _ => continue,
            }
            n += 1;
        }
    }
    assert!(
        n >= 3,
        "expected the shipped fleet and camera files, found {n}"
    );
}

#[test]
fn paper_fleet_cameras_look_where_they_are_named() {
    let fleet = Fleet::load(&root().join("configs/fleets/paper.toml")).unwrap();
    assert_eq!(fleet.vehicles.len(), 3);
    let expected = [
        ("forward", Vector3::x()),
        ("up", -Vector3::z()),
        ("down", Vector3::z()),
        ("port", -Vector3::y()),
        ("starboard", Vector3::y()),
    ];
    for v in &fleet.vehicles {
        assert_eq!(v.cameras.len(), 5);
        for (name, axis) in expected {
            let cam = v.cameras.iter().find(|c| c.name == name).unwrap();
            // The optical axis (camera z) expressed in the body frame.
            let z = cam.body_from_camera.rotation * Vector3::z();
            assert!(
                (z - axis).norm() < 1e-9,
                "vehicle {} camera {name}: z = {z}",
                v.id
            );
        }
        // Side cameras keep "image down" = body down.
        for name in ["port", "starboard"] {
            let cam = v.cameras.iter().find(|c| c.name == name).unwrap();
            let y = cam.body_from_camera.rotation * Vector3::y();
            assert!((y - Vector3::z()).norm() < 1e-9, "{name}: image down = {y}");
        }
    }
}

#[test]
fn paper_fleet_markers_face_outwards_upright() {
    let fleet = Fleet::load(&root().join("configs/fleets/paper.toml")).unwrap();
    for v in &fleet.vehicles {
        assert_eq!(v.markers.len(), 2);
        for m in &v.markers {
            let normal = m.body_from_marker.rotation * Vector3::z();
            let up = m.body_from_marker.rotation * Vector3::y();
            let side = m.body_from_marker.translation.vector.y.signum();
            // Face points away from the hull, on the side it is mounted on.
            assert!(
                (normal - Vector3::y() * side).norm() < 1e-9,
                "marker {}: normal {normal}",
                m.id
            );
            // Upright: the print's "up" is the body's up (-z).
            assert!(
                (up + Vector3::z()).norm() < 1e-9,
                "marker {}: up {up}",
                m.id
            );
            assert!(m.body_from_marker.translation.vector.y.abs() > v.hull.diameter_m / 2.0);
        }
    }
}
