//! Contact sheet of HOIRM's stages and the baselines on simulated frames:
//! rows 6.12, 8.22, 10.13, 12.20 /m (the paper's Fig. 7/10 waters); columns
//! input, each HOIRM stage, the final image, CLAHE, DCP, UDCP — cropped
//! around the marker.
//!
//! `cargo run --release -p shoal-node --example restore_contact_sheet [out.png]`
//! (default `docs/img/restoration-contact-sheet.png`)

use opencv::core::{Mat, Point, Rect, Scalar, Size, Vector, CV_8UC1};
use opencv::imgproc;
use opencv::prelude::*;
use shoal_node::restore::{restorer, Hoirm, Method, RestoreParams};
use shoal_proto::geometry::pose_from_xyz_rpy;
use shoal_proto::{CameraModel, CodeSet, Pose};
use shoal_sim_bridge::render::{Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;

const WATERS: [f64; 4] = [6.12, 8.22, 10.13, 12.20];
/// Side of each tile of the sheet, pixels.
const TILE: i32 = 220;
/// Height of the label strip above each column.
const LABEL_H: i32 = 26;
/// Frames of history HOIRM sees before the one shown (30 fps).
const HISTORY: usize = 4;

fn to_mat(g: &shoal_proto::GrayImage) -> Mat {
    Mat::new_rows_cols_with_data(g.height as i32, g.width as i32, &g.data)
        .unwrap()
        .try_clone()
        .unwrap()
}

fn tile(img: &Mat, crop: Rect) -> Mat {
    let mut out = Mat::default();
    imgproc::resize(
        &Mat::roi(img, crop).unwrap(),
        &mut out,
        Size::new(TILE, TILE),
        0.0,
        0.0,
        imgproc::INTER_AREA,
    )
    .unwrap();
    out
}

fn main() {
    let out_path = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "docs/img/restoration-contact-sheet.png".into());
    let cam = CameraModel::vehicle_1440();
    let mut renderer = Renderer::new();
    let mut rows: Vec<(f64, Vec<(String, Mat)>)> = Vec::new();
    for c in WATERS {
        let water = WaterParams::preset(c);
        let params = RestoreParams {
            keep_stages: true,
            ..RestoreParams::default()
        };
        let mut hoirm = Hoirm::new(params.clone());
        let mut last = None;
        for k in 0..=HISTORY {
            let t = k as f64 / 30.0;
            let pose: Pose = pose_from_xyz_rpy(
                [0.02 * (t * 3.0).sin(), 0.0, 0.6],
                [std::f64::consts::PI + 0.12, 0.18, 0.05],
            );
            let scene = Scene::single_marker(CodeSet::Shoal, 17, 0.1, pose);
            let out = renderer
                .render(&cam, &Pose::identity(), &scene, &water, t, 7 + k as u64)
                .unwrap();
            let img = to_mat(&out.image);
            let (res, p) = hoirm.restore_with_params(&img, (t * 1e9) as u64).unwrap();
            if k == HISTORY {
                println!(
                    "c = {c:5.2}: estimated c {:.2}, backscatter {:.0}, α {:.2}, clip {:.2}, p {:.2}, σ {:.2} px, level {}, ROIs {:?}",
                    p.c_per_m, p.water.backscatter, p.alpha, p.clahe_clip, p.psf.p, p.psf.sigma_px,
                    res.pyramid_level, res.rois
                );
                last = Some((img, out, res));
            }
        }
        let (img, out, res) = last.unwrap();
        let q = &out.visible[0].corners_px;
        let (cx, cy) = (
            q[..4].iter().map(|p| p[0]).sum::<f64>() / 4.0,
            q[..4].iter().map(|p| p[1]).sum::<f64>() / 4.0,
        );
        let half = 200;
        let crop = Rect::new(cx as i32 - half, cy as i32 - half, 2 * half, 2 * half)
            & Rect::new(0, 0, img.cols(), img.rows());
        let mut cols: Vec<(String, Mat)> = res
            .stages
            .unwrap()
            .into_iter()
            .map(|(n, m)| (n, tile(&m, crop)))
            .collect();
        cols.push(("HOIRM final".into(), tile(&res.image, crop)));
        for m in [Method::Clahe, Method::Dcp, Method::Udcp] {
            let r = restorer(m, &RestoreParams::default())
                .restore(&img, 0)
                .unwrap();
            cols.push((m.name().to_uppercase(), tile(&r.image, crop)));
        }
        cols.push(("clean (sim)".into(), tile(&to_mat(&out.clean), crop)));
        rows.push((c, cols));
    }
    let ncols = rows[0].1.len() as i32;
    let left = 70;
    let width = left + ncols * TILE;
    let height = LABEL_H + rows.len() as i32 * TILE;
    let mut sheet =
        Mat::new_rows_cols_with_default(height, width, CV_8UC1, Scalar::all(255.0)).unwrap();
    for (j, (name, _)) in rows[0].1.iter().enumerate() {
        let short: String = name.chars().take(24).collect();
        imgproc::put_text(
            &mut sheet,
            &short,
            Point::new(left + j as i32 * TILE + 4, 18),
            imgproc::FONT_HERSHEY_SIMPLEX,
            0.45,
            Scalar::all(0.0),
            1,
            imgproc::LINE_AA,
            false,
        )
        .unwrap();
    }
    for (i, (c, cols)) in rows.iter().enumerate() {
        let y = LABEL_H + i as i32 * TILE;
        imgproc::put_text(
            &mut sheet,
            &format!("{c:.2}/m"),
            Point::new(4, y + TILE / 2),
            imgproc::FONT_HERSHEY_SIMPLEX,
            0.5,
            Scalar::all(0.0),
            1,
            imgproc::LINE_AA,
            false,
        )
        .unwrap();
        for (j, (_, m)) in cols.iter().enumerate() {
            let mut dst =
                Mat::roi_mut(&mut sheet, Rect::new(left + j as i32 * TILE, y, TILE, TILE)).unwrap();
            m.copy_to(&mut dst).unwrap();
        }
    }
    if let Some(dir) = std::path::Path::new(&out_path).parent() {
        std::fs::create_dir_all(dir).ok();
    }
    opencv::imgcodecs::imwrite(&out_path, &sheet, &Vector::new()).unwrap();
    println!("wrote {out_path}");
}
