//! The paper's Table 5 on simulated frames: success rate of the enhanced-marker
//! detector (`ShoalDetector`) on images restored by none / CLAHE / DCP / UDCP /
//! HOIRM, marker at 600 mm, across water presets. Every method sees the same
//! frames; a frame counts as a success when marker 17 is found (and no other ID).
//! Extra rows run the detector on every output `pyrDown`-ed twice (level 2),
//! and on the level HOIRM chose (`Restored::level_image`).
//!
//! `cargo run --release -p shoal-node --example restore_detection [frames_per_water]`

use opencv::core::Mat;
use opencv::prelude::*;
use shoal_node::detect::{DetectParams, MarkerDetector, ShoalDetector};
use shoal_node::restore::{restorer, Method, RestoreParams};
use shoal_proto::geometry::pose_from_xyz_rpy;
use shoal_proto::{CameraModel, CodeSet, Pose};
use shoal_sim_bridge::render::{Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;

const WATERS: [f64; 6] = [5.16, 6.12, 8.22, 10.13, 12.20, 14.20];
const ID: u32 = 17;

fn to_mat(g: &shoal_proto::GrayImage) -> Mat {
    Mat::new_rows_cols_with_data(g.height as i32, g.width as i32, &g.data)
        .unwrap()
        .try_clone()
        .unwrap()
}

fn main() {
    let frames: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(20);
    let cam = CameraModel::vehicle_1440();
    let mut renderer = Renderer::new();
    let mut detector = ShoalDetector::new(CodeSet::Shoal, DetectParams::default());
    println!("# detection success rate, marker {ID} (100 mm) at 600 mm, {frames} frames per water");
    print!("| method |");
    for c in WATERS {
        print!(" {c:.2}/m |");
    }
    println!();
    println!("|---|{}", "---|".repeat(WATERS.len()));
    // Rows: every method on its full-resolution output, then every method's
    // output `pyrDown`-ed twice (level 2), then HOIRM's own chosen level.
    let n = Method::ALL.len();
    let mut table = vec![vec![0usize; WATERS.len()]; 2 * n + 1];
    let mut levels = vec![Vec::new(); WATERS.len()];
    for (wi, &c) in WATERS.iter().enumerate() {
        let water = WaterParams::preset(c);
        let mut restorers: Vec<_> = Method::ALL
            .iter()
            .map(|&m| restorer(m, &RestoreParams::default()))
            .collect();
        for k in 0..frames {
            let t = k as f64 / 30.0;
            // Small motion at 600 mm: lateral offsets and tilts as on the paper's platform.
            let ph = k as f64 * 0.7;
            let pose: Pose = pose_from_xyz_rpy(
                [0.05 * ph.sin(), 0.03 * (1.3 * ph).cos(), 0.6],
                [
                    std::f64::consts::PI + 0.2 * ph.cos(),
                    0.25 * (0.9 * ph).sin(),
                    0.3 * ph.sin(),
                ],
            );
            let scene = Scene::single_marker(CodeSet::Shoal, ID, 0.1, pose);
            let out = renderer
                .render(&cam, &Pose::identity(), &scene, &water, t, 1000 + k as u64)
                .unwrap();
            let img = to_mat(&out.image);
            for (mi, r) in restorers.iter_mut().enumerate() {
                let res = r.restore(&img, (t * 1e9) as u64).unwrap();
                let mut found = |m: &Mat, row: usize| {
                    let dets = detector.detect(m).unwrap();
                    if !dets.is_empty() && dets.iter().all(|d| d.id == ID) {
                        table[row][wi] += 1;
                    }
                };
                found(&res.image, mi);
                let mut l1 = Mat::default();
                opencv::imgproc::pyr_down_def(&res.image, &mut l1).unwrap();
                let mut l2 = Mat::default();
                opencv::imgproc::pyr_down_def(&l1, &mut l2).unwrap();
                found(&l2, n + mi);
                if Method::ALL[mi] == Method::Hoirm {
                    found(res.level_image.as_ref().unwrap_or(&res.image), 2 * n);
                    levels[wi].push(res.pyramid_level);
                }
            }
        }
        eprintln!("done {c}");
    }
    let names: Vec<String> = Method::ALL
        .iter()
        .map(|m| m.to_string())
        .chain(Method::ALL.iter().map(|m| format!("{m}, level 2")))
        .chain(["hoirm, chosen level".to_string()])
        .collect();
    for (mi, m) in names.iter().enumerate() {
        print!("| {m} |");
        for n in &table[mi] {
            print!(" {:.2} |", *n as f64 / frames as f64);
        }
        println!();
    }
    for (wi, c) in WATERS.iter().enumerate() {
        println!("chosen pyramid levels at {c}/m: {:?}", levels[wi]);
    }
}
