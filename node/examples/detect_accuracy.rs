//! Accuracy of the enhanced marker + shoal detector against OpenCV ArUco
//! (4x4_50) and AprilTag 3 (36h11), all with the same outer black square
//! (100 mm), on the same simulated poses: 610 mm away, yaw 30°, with a few
//! millimetres of lateral jitter per frame (so pixel phase varies), across
//! water presets. Pose: `shoal_node::pose::estimate_pose`, σ estimated.
//!
//! `cargo run -p shoal-node --example detect_accuracy -- [frames] [c_per_m,...]`
//! (defaults: 15 frames; presets 0 (clear), 0.5, 1.38, 3.92, 5.16).

use nalgebra::{Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use shoal_node::baseline::{AprilTag, OpenCvAruco};
use shoal_node::detect::{DetectParams, Detection, MarkerDetector, Refinement, ShoalDetector};
use shoal_node::mat::gray_as_mat;
use shoal_node::pose::estimate_pose;
use shoal_proto::{camera::CameraModel, geometry::Pose, marker::CodeSet};
use shoal_sim_bridge::render::{Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;

const SIDE_M: f64 = 0.1;

struct Row {
    name: String,
    pos_mm: Vec<f64>,
    ang_deg: Vec<f64>,
    corners: Vec<f64>,
    missed: usize,
}

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    let frames: usize = a.get(1).map_or(Ok(15), |s| s.parse())?;
    let presets: Vec<f64> = a
        .get(2)
        .map_or("0,0.5,1.38,3.92,5.16", |s| s)
        .split(',')
        .map(str::parse)
        .collect::<Result<_, _>>()?;
    let cam = CameraModel::vehicle_1440();
    let mut renderer = Renderer::new();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    println!(
        "| c [1/m] | detector | found | corners | median pos err [mm] | median angle err [deg] |"
    );
    println!("|---|---|---|---|---|---|");
    for &c in &presets {
        let water = if c == 0.0 {
            WaterParams::clear()
        } else {
            WaterParams::preset(c)
        };
        // (label, code set of the rendered marker, detector)
        let mut dets: Vec<(CodeSet, Box<dyn MarkerDetector>, String)> = vec![
            (
                CodeSet::Shoal,
                Box::new(ShoalDetector::new(CodeSet::Shoal, DetectParams::default())),
                "shoal (12 corners, edge lines)".into(),
            ),
            (
                CodeSet::Shoal,
                Box::new(ShoalDetector::new(
                    CodeSet::Shoal,
                    DetectParams {
                        refinement: Refinement::CornerSubPix,
                        ..DetectParams::default()
                    },
                )),
                "shoal (12 corners, cornerSubPix)".into(),
            ),
            (
                CodeSet::Aruco4x4_50,
                Box::new(ShoalDetector::new(
                    CodeSet::Aruco4x4_50,
                    DetectParams::default(),
                )),
                "shoal detector on ArUco 4x4_50 (4 corners)".into(),
            ),
            (
                CodeSet::Aruco4x4_50,
                Box::new(OpenCvAruco::new(CodeSet::Aruco4x4_50)?),
                "OpenCV ArUco 4x4_50".into(),
            ),
            (
                CodeSet::AprilTag36h11,
                Box::new(AprilTag::new(CodeSet::AprilTag36h11)?),
                "AprilTag 3 36h11".into(),
            ),
        ];
        let mut rows: Vec<Row> = dets
            .iter()
            .map(|d| Row {
                name: d.2.clone(),
                pos_mm: vec![],
                ang_deg: vec![],
                corners: vec![],
                missed: 0,
            })
            .collect();
        for f in 0..frames {
            let jitter = [rng.gen_range(-0.02..0.02), rng.gen_range(-0.02..0.02)];
            let truth = Pose::from_parts(
                Translation3::new(jitter[0], jitter[1], 0.61),
                UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
                    * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 30f64.to_radians()),
            );
            let mut cache: Vec<(CodeSet, shoal_proto::image::GrayImage)> = Vec::new();
            for (k, (codes, det, _)) in dets.iter_mut().enumerate() {
                let id = 17;
                if !cache.iter().any(|(cs, _)| cs == codes) {
                    let scene = Scene::single_marker(*codes, id, SIDE_M, truth);
                    let img = renderer
                        .render(
                            &cam,
                            &Pose::identity(),
                            &scene,
                            &water,
                            f as f64 * 0.1,
                            f as u64 + 1,
                        )?
                        .image;
                    cache.push((*codes, img));
                }
                let img = &cache.iter().find(|(cs, _)| cs == codes).unwrap().1;
                let mat = gray_as_mat(img)?;
                let found: Vec<Detection> = det.detect(&mat.clone_pointee())?;
                let Some(d) = found.iter().find(|d| d.id == id) else {
                    rows[k].missed += 1;
                    continue;
                };
                rows[k].corners.push(d.corners_px.len() as f64);
                let Ok(sol) = estimate_pose(&cam, &d.object_points(SIDE_M), &d.corners_px, None)
                else {
                    rows[k].missed += 1;
                    continue;
                };
                let est = sol.best.camera_from_marker;
                rows[k]
                    .pos_mm
                    .push(1000.0 * (est.translation.vector - truth.translation.vector).norm());
                rows[k].ang_deg.push(
                    (est.rotation * truth.rotation.inverse())
                        .angle()
                        .to_degrees(),
                );
            }
        }
        for r in &mut rows {
            println!(
                "| {c} | {} | {}/{frames} | {:.0} | {:.2} | {:.3} |",
                r.name,
                frames - r.missed,
                median(&mut r.corners),
                median(&mut r.pos_mm),
                median(&mut r.ang_deg)
            );
        }
    }
    Ok(())
}
