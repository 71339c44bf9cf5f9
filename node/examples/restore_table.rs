//! The paper's Tables 1–4 on simulated frames: SSIM, PSNR (against the
//! simulator's clean image) and the marker's CNR for none / CLAHE / DCP /
//! UDCP / HOIRM at 6.12, 8.22, 10.13 and 12.20 /m.
//!
//! `cargo run --release -p shoal-node --example restore_table [frames_per_water]`
//!
//! Each water gets a short sequence (30 fps) of a 100 mm enhanced marker at
//! about 600 mm, slowly moving, so HOIRM's ambient-light state sees a
//! history; every frame is scored and the means are printed. SSIM and PSNR
//! are given on the marker's bounding box (quiet zone included) — the
//! clean image's background is black (no water, nothing behind the marker),
//! so full-frame scores mostly measure how dark a method leaves the open
//! water — and on the full frame.

use opencv::core::{Mat, Point, Rect, Scalar, Size, Vector, CV_8UC1};
use opencv::imgproc;
use opencv::prelude::*;
use shoal_node::metrics::{cnr_mat, gray_from_mat, psnr, ssim};
use shoal_node::restore::{restorer, Method, RestoreParams};
use shoal_proto::geometry::pose_from_xyz_rpy;
use shoal_proto::{CameraModel, CodeSet, Pose};
use shoal_sim_bridge::render::{Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;

const WATERS: [f64; 4] = [6.12, 8.22, 10.13, 12.20];

fn to_mat(g: &shoal_proto::GrayImage) -> Mat {
    Mat::new_rows_cols_with_data(g.height as i32, g.width as i32, &g.data)
        .unwrap()
        .try_clone()
        .unwrap()
}

/// Marker masks from the clean image: inside the outer quad (shrunk), white
/// and black cells eroded by 3 px so blurred cell borders do not count.
fn masks(clean: &Mat, quad: &[[f64; 2]]) -> (Vec<bool>, Vec<bool>, Rect) {
    let pts: Vector<Point> = quad[..4]
        .iter()
        .map(|p| Point::new(p[0].round() as i32, p[1].round() as i32))
        .collect();
    let mut inside =
        Mat::new_size_with_default(clean.size().unwrap(), CV_8UC1, Scalar::all(0.0)).unwrap();
    imgproc::fill_convex_poly(&mut inside, &pts, Scalar::all(255.0), imgproc::LINE_8, 0).unwrap();
    let bbox = imgproc::bounding_rect(&pts).unwrap();
    let k =
        imgproc::get_structuring_element(imgproc::MORPH_RECT, Size::new(7, 7), Point::new(-1, -1))
            .unwrap();
    let erode = |m: &Mat| {
        let mut o = Mat::default();
        imgproc::erode(
            m,
            &mut o,
            &k,
            Point::new(-1, -1),
            1,
            opencv::core::BORDER_CONSTANT,
            Scalar::all(0.0),
        )
        .unwrap();
        o
    };
    let mut max = 0.0;
    opencv::core::min_max_loc(clean, None, Some(&mut max), None, None, &inside).unwrap();
    let mut white = Mat::default();
    let mut black = Mat::default();
    imgproc::threshold(clean, &mut white, 0.6 * max, 255.0, imgproc::THRESH_BINARY).unwrap();
    imgproc::threshold(
        clean,
        &mut black,
        0.4 * max,
        255.0,
        imgproc::THRESH_BINARY_INV,
    )
    .unwrap();
    let (mut w, mut b) = (Mat::default(), Mat::default());
    opencv::core::bitwise_and(&erode(&white), &inside, &mut w, &opencv::core::no_array()).unwrap();
    opencv::core::bitwise_and(&erode(&black), &inside, &mut b, &opencv::core::no_array()).unwrap();
    let to_vec = |m: &Mat| {
        gray_from_mat(m)
            .unwrap()
            .data
            .iter()
            .map(|&v| v > 0)
            .collect::<Vec<_>>()
    };
    (to_vec(&w), to_vec(&b), bbox)
}

fn main() {
    let frames: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(6);
    opencv::core::set_num_threads(1).unwrap();
    let cam = CameraModel::vehicle_1440();
    let mut renderer = Renderer::new();
    println!("# SSIM / PSNR (dB) on the marker box and full frame, CNR of the marker cells; mean of {frames} frames");
    println!("| c (1/m) | method | SSIM box | PSNR box | SSIM full | PSNR full | CNR | est. c |");
    println!("|---|---|---|---|---|---|---|---|");
    for c in WATERS {
        let water = WaterParams::preset(c);
        let mut params = RestoreParams::default();
        // Tuning hooks: SHOAL_PSF_PX_PER_UNIT, SHOAL_ORDER=physical.
        if let Some(s) = std::env::var("SHOAL_PSF_PX_PER_UNIT")
            .ok()
            .and_then(|v| v.parse().ok())
        {
            params.psf_px_per_unit = s;
        }
        if let Some(l) = std::env::var("SHOAL_DECONV_LEVEL")
            .ok()
            .and_then(|v| v.parse().ok())
        {
            params.deconv_level = l;
        }
        if std::env::var("SHOAL_ORDER").is_ok_and(|v| v == "physical") {
            params.order = shoal_node::restore::StageOrder::Physical;
        }
        let mut restorers: Vec<_> = Method::ALL.iter().map(|&m| restorer(m, &params)).collect();
        let mut sums = vec![[0.0f64; 6]; Method::ALL.len()];
        for k in 0..frames {
            let t = k as f64 / 30.0;
            let pose: Pose = pose_from_xyz_rpy(
                [0.03 * (t * 2.0).sin(), -0.02 + 0.01 * t, 0.6],
                [std::f64::consts::PI + 0.15, 0.2 + 0.05 * t, 0.1],
            );
            let scene = Scene::single_marker(CodeSet::Shoal, 17, 0.1, pose);
            let out = renderer
                .render(&cam, &Pose::identity(), &scene, &water, t, 100 + k as u64)
                .unwrap();
            let img = to_mat(&out.image);
            let clean = to_mat(&out.clean);
            let (white, black, bbox) = masks(&clean, &out.visible[0].corners_px);
            let m = 20;
            let frame = Rect::new(0, 0, img.cols(), img.rows());
            let boxr = Rect::new(
                bbox.x - m,
                bbox.y - m,
                bbox.width + 2 * m,
                bbox.height + 2 * m,
            ) & frame;
            let crop =
                |x: &Mat| gray_from_mat(&Mat::roi(x, boxr).unwrap().try_clone().unwrap()).unwrap();
            for (i, r) in restorers.iter_mut().enumerate() {
                let res = r.restore(&img, (t * 1e9) as u64).unwrap();
                let a = gray_from_mat(&res.image).unwrap();
                let cl = gray_from_mat(&clean).unwrap();
                sums[i][0] += ssim(&crop(&res.image), &crop(&clean)).unwrap();
                sums[i][1] += psnr(&crop(&res.image), &crop(&clean)).unwrap();
                sums[i][2] += ssim(&a, &cl).unwrap();
                sums[i][3] += psnr(&a, &cl).unwrap();
                sums[i][4] += cnr_mat(&res.image, &white, &black).unwrap();
                sums[i][5] += res.estimated_c_per_m;
            }
        }
        for (i, m) in Method::ALL.iter().enumerate() {
            let s: Vec<f64> = sums[i].iter().map(|v| v / frames as f64).collect();
            println!(
                "| {c:.2} | {m} | {:.4} | {:.2} | {:.4} | {:.2} | {:.2} | {:.2} |",
                s[0], s[1], s[2], s[3], s[4], s[5]
            );
        }
    }
}
