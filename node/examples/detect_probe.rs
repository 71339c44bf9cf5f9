//! Probe: render one marker with the simulator and print detection corner errors.
//! `cargo run -p shoal-node --example detect_probe -- [codes] [c_per_m] [yaw_deg] [dist_m]`
//! (`SHOAL_PROBE_X=-0.31` shifts the marker sideways)
use nalgebra::{Translation3, UnitQuaternion, Vector3};
use shoal_node::detect::{DetectParams, MarkerDetector, ShoalDetector};
use shoal_proto::{camera::CameraModel, geometry::Pose, marker::CodeSet};
use shoal_sim_bridge::render::{Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    let codes: CodeSet = a.get(1).map_or("shoal", |s| s).parse()?;
    let c: f64 = a.get(2).map_or(Ok(0.0), |s| s.parse())?;
    let yaw: f64 = a.get(3).map_or(Ok(30.0), |s| s.parse())?;
    let d: f64 = a.get(4).map_or(Ok(0.61), |s| s.parse())?;
    // Lateral offset (m), e.g. -0.31 to clip the frame at the left border.
    let x_m: f64 = std::env::var("SHOAL_PROBE_X").map_or(Ok(0.0), |s| s.parse())?;
    let cam = CameraModel::vehicle_1440();
    let pose = Pose::from_parts(
        Translation3::new(x_m, 0.0, d),
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
            * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), yaw.to_radians()),
    );
    let id = if codes == CodeSet::AprilTag16h5 {
        7
    } else {
        17
    };
    let scene = Scene::single_marker(codes, id, 0.1, pose);
    let water = if c == 0.0 {
        WaterParams::clear()
    } else {
        WaterParams::preset(c)
    };
    let t = std::time::Instant::now();
    let out = Renderer::new().render(&cam, &Pose::identity(), &scene, &water, 0.0, 1)?;
    eprintln!("render {:?}", t.elapsed());
    if let Some(p) = a.get(5) {
        shoal_sim_bridge::render::write_png(&out.image, std::path::Path::new(p))?;
    }
    let mut det = ShoalDetector::new(codes, DetectParams::default());
    let t = std::time::Instant::now();
    let found = det.detect_gray(&out.image)?;
    eprintln!("detect {:?}", t.elapsed());
    opencv::core::set_num_threads(1)?;
    let mat = shoal_node::mat::gray_as_mat(&out.image)?.clone_pointee();
    let reps = 20;
    let t = std::time::Instant::now();
    for _ in 0..reps {
        for d in det.detect(&mat)? {
            let _ =
                shoal_node::pose::estimate_pose(&cam, &d.object_points(0.1), &d.corners_px, None);
        }
    }
    eprintln!("shoal detect+pose: {:?} per frame", t.elapsed() / reps);
    {
        use shoal_node::detect::Refinement;
        let mut variants: Vec<(&str, ShoalDetector, std::time::Duration)> = [
            ("no refinement", Refinement::None),
            ("edge lines", Refinement::EdgeLines),
            ("edge model", Refinement::EdgeModel),
        ]
        .into_iter()
        .map(|(l, r)| {
            let p = DetectParams {
                refinement: r,
                ..DetectParams::default()
            };
            (l, ShoalDetector::new(codes, p), std::time::Duration::ZERO)
        })
        .collect();
        // Interleaved, so that machine load hits every variant alike.
        for _ in 0..reps {
            for (_, d2, acc) in variants.iter_mut() {
                let t = std::time::Instant::now();
                d2.detect(&mat)?;
                *acc += t.elapsed();
            }
        }
        for (label, _, acc) in &variants {
            eprintln!("{label}: detect only {:?} per frame", *acc / reps);
        }
    }
    let t = std::time::Instant::now();
    for _ in 0..reps {
        det.detect(&mat)?;
    }
    eprintln!("default: detect only {:?} per frame", t.elapsed() / reps);
    if let Ok(mut aruco) = shoal_node::baseline::OpenCvAruco::new(codes) {
        let t = std::time::Instant::now();
        for _ in 0..reps {
            aruco.detect(&mat)?;
        }
        eprintln!("opencv aruco detect: {:?} per frame", t.elapsed() / reps);
    }
    if let Some(d) = found.first() {
        let t = std::time::Instant::now();
        for _ in 0..reps {
            let _ =
                shoal_node::pose::estimate_pose(&cam, &d.object_points(0.1), &d.corners_px, None);
        }
        eprintln!("pose only: {:?}", t.elapsed() / reps);
    }
    if let Some(d) = found.first().filter(|d| d.corners_px.len() == 12) {
        use shoal_node::detect::{edge_model, refine};
        let view = shoal_node::mat::GrayView::new(&mat)?;
        let squares: Vec<([[f64; 2]; 4], refine::Polarity)> = (0..3)
            .map(|s| {
                let q = [
                    d.corners_px[4 * s],
                    d.corners_px[4 * s + 1],
                    d.corners_px[4 * s + 2],
                    d.corners_px[4 * s + 3],
                ];
                let pol = if s == 1 {
                    refine::Polarity::BrightInside
                } else {
                    refine::Polarity::DarkInside
                };
                (q, pol)
            })
            .collect();
        let reps = 50;
        let t = std::time::Instant::now();
        for _ in 0..reps {
            for (q, pol) in &squares {
                let _ = refine::refine_by_edge_lines(&view, q, d.module_px, *pol);
            }
        }
        eprintln!("edge lines, 3 squares: {:?}", t.elapsed() / reps);
        let t = std::time::Instant::now();
        for _ in 0..reps {
            for (q, pol) in &squares {
                let _ = refine::refine_by_edge_lines_coarse(&view, q, d.module_px, *pol);
            }
        }
        eprintln!("edge lines coarse, 3 squares: {:?}", t.elapsed() / reps);
        let t = std::time::Instant::now();
        for _ in 0..reps {
            for (q, pol) in &squares {
                let sign = if *pol == refine::Polarity::DarkInside {
                    1.0
                } else {
                    -1.0
                };
                let _ = edge_model::refine_by_edge_model(&view, q, d.module_px, sign);
            }
        }
        eprintln!("edge model, 3 squares: {:?}", t.elapsed() / reps);
    }
    let truth: Vec<[f64; 2]> = codes
        .corners_3d(0.1)
        .iter()
        .map(|p| {
            let q = cam.project(&(pose * p)).unwrap();
            [q.x, q.y]
        })
        .collect();
    for f in &found {
        println!(
            "id {} hamming {} module {:.2} px, corners {:?}",
            f.id, f.hamming, f.module_px, f.corner_ids
        );
        for (k, &cid) in f.corner_ids.iter().enumerate() {
            let t = truth[cid as usize];
            let e = [f.corners_px[k][0] - t[0], f.corners_px[k][1] - t[1]];
            println!("  corner {cid:2}: err ({:+.3}, {:+.3})", e[0], e[1]);
        }
    }
    Ok(())
}
