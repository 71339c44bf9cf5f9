//! `shoal eval probe restore-sheet`: HOIRM stage by stage beside the
//! baselines on simulated frames. Rows are waters (default the paper's
//! Fig. 7/10 waters, 6.12 … 12.20 /m); columns the input, each HOIRM stage,
//! the final image, CLAHE, DCP, UDCP and the simulator's clean image, cropped
//! around the marker. For every row the marker's CNR after each stage is
//! printed (white and black modules from the known pose, as the
//! `restoration` experiment: `scene::module_masks`).

use crate::eval::scene::module_masks;
use crate::eval::{restore_params, EvalError};
use opencv::core::{Mat, Point, Rect, Scalar, Size, Vector, CV_8UC1};
use opencv::imgproc;
use opencv::prelude::*;
use shoal_node::metrics::{cnr, gray_from_mat};
use shoal_node::restore::{restorer, Hoirm, Method, RestoreParams};
use shoal_proto::geometry::pose_from_xyz_rpy;
use shoal_proto::{CameraModel, CodeSet, Pose};
use shoal_sim_bridge::render::{Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;
use std::path::PathBuf;

/// Side of each tile of the sheet, pixels.
const TILE: i32 = 220;
/// Height of the label strip above each column.
const LABEL_H: i32 = 26;
/// Frames of history HOIRM sees before the one shown (30 fps).
const HISTORY: usize = 4;
/// Part of each module's side whose pixels count for the CNR (as the `restoration` experiment).
const MODULE_INNER: f64 = 0.6;

#[derive(Debug, clap::Args)]
pub struct RestoreSheetArgs {
    /// The contact sheet (PNG).
    #[arg(long, default_value = "docs/img/restoration-contact-sheet.png")]
    pub out: PathBuf,
    /// Waters (1/m, comma-separated), one row each.
    #[arg(long, value_delimiter = ',', default_value = "6.12,8.22,10.13,12.20")]
    pub c: Vec<f64>,
    /// Also write every stage of every row at full resolution as PNG into this folder.
    #[arg(long)]
    pub stages_dir: Option<PathBuf>,
    /// Set a HOIRM parameter (`RestoreParams` field), e.g. `--restore-param order=physical`; repeatable.
    #[arg(long = "restore-param", value_name = "NAME=VALUE")]
    pub restore_param: Vec<String>,
}

fn tile(img: &Mat, crop: Rect) -> Result<Mat, EvalError> {
    let mut out = Mat::default();
    imgproc::resize(
        &Mat::roi(img, crop)?,
        &mut out,
        Size::new(TILE, TILE),
        0.0,
        0.0,
        imgproc::INTER_AREA,
    )?;
    Ok(out)
}

pub(super) fn imwrite(path: &std::path::Path, m: &Mat) -> Result<(), EvalError> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|source| EvalError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
    }
    if !opencv::imgcodecs::imwrite(&path.display().to_string(), m, &Vector::new())? {
        return Err(EvalError::Setup(format!("{}: not written", path.display())));
    }
    Ok(())
}

pub(super) fn label(sheet: &mut Mat, text: &str, at: Point, scale: f64) -> Result<(), EvalError> {
    imgproc::put_text(
        sheet,
        text,
        at,
        imgproc::FONT_HERSHEY_SIMPLEX,
        scale,
        Scalar::all(0.0),
        1,
        imgproc::LINE_AA,
        false,
    )?;
    Ok(())
}

pub fn run(a: &RestoreSheetArgs) -> Result<(), EvalError> {
    let cam = CameraModel::vehicle_1440();
    let mut renderer = Renderer::new();
    let params = RestoreParams {
        keep_stages: true,
        ..restore_params::from_assignments(&a.restore_param)?
    };
    let mut rows: Vec<(f64, Vec<(String, Mat)>)> = Vec::new();
    for &c in &a.c {
        let water = WaterParams::preset(c);
        let mut hoirm = Hoirm::new(params.clone());
        let mut last = None;
        for k in 0..=HISTORY {
            let t = k as f64 / 30.0;
            let pose: Pose = pose_from_xyz_rpy(
                [0.02 * (t * 3.0).sin(), 0.0, 0.6],
                [std::f64::consts::PI + 0.12, 0.18, 0.05],
            );
            let scene = Scene::single_marker(CodeSet::Shoal, 17, 0.1, pose);
            let out = renderer.render(&cam, &Pose::identity(), &scene, &water, t, 7 + k as u64)?;
            let img = shoal_node::mat::gray_to_mat(&out.image)?;
            let (res, p) = hoirm.restore_with_params(&img, (t * 1e9) as u64)?;
            if k == HISTORY {
                crate::outln!(
                    "c = {c:5.2}: estimated c {:.2}, backscatter {:.0}, α {:.2}, clip {:.2}, p {:.2}, σ {:.2} px, level {}, ROIs {:?}",
                    p.c_per_m, p.water.backscatter, p.alpha, p.clahe_clip, p.psf.p, p.psf.sigma_px,
                    res.pyramid_level, res.rois
                );
                last = Some((img, out, res, pose));
            }
        }
        let Some((img, out, res, pose)) = last else {
            continue;
        };
        let (white, black) = module_masks(&cam, &pose, CodeSet::Shoal, 17, 0.1, MODULE_INNER)
            .ok_or_else(|| EvalError::Setup("the marker is not in view".into()))?;
        let q = &out
            .visible
            .first()
            .ok_or_else(|| EvalError::Setup("the marker is not in view".into()))?
            .corners_px;
        let (cx, cy) = (
            q[..4].iter().map(|p| p[0]).sum::<f64>() / 4.0,
            q[..4].iter().map(|p| p[1]).sum::<f64>() / 4.0,
        );
        let half = 200;
        let crop = Rect::new(cx as i32 - half, cy as i32 - half, 2 * half, 2 * half)
            & Rect::new(0, 0, img.cols(), img.rows());
        // The stages start with HOIRM's input.
        let mut columns: Vec<(String, Mat)> = res.stages.unwrap_or_default();
        columns.push(("HOIRM final".into(), res.image));
        for m in [Method::Clahe, Method::Dcp, Method::Udcp] {
            let r = restorer(m, &RestoreParams::default()).restore(&img, 0)?;
            columns.push((m.name().to_uppercase(), r.image));
        }
        columns.push((
            "clean (sim)".into(),
            shoal_node::mat::gray_to_mat(&out.clean)?,
        ));
        let mut tiles = Vec::with_capacity(columns.len());
        for (i, (name, m)) in columns.iter().enumerate() {
            let value = cnr(&gray_from_mat(m)?, &white, &black)
                .map_or("n/a".to_string(), |v| format!("{v:7.2}"));
            crate::outln!("  {i:2} {name:<28} CNR {value}");
            if let Some(dir) = &a.stages_dir {
                let file: String = name
                    .chars()
                    .map(|ch| if ch.is_ascii_alphanumeric() { ch } else { '_' })
                    .collect();
                imwrite(&dir.join(format!("c{c:.2}_{i:02}_{file}.png")), m)?;
            }
            tiles.push((name.clone(), tile(m, crop)?));
        }
        rows.push((c, tiles));
    }
    let Some(first) = rows.first() else {
        return Err(EvalError::Setup("no water given (--c)".into()));
    };
    let ncols = first.1.len() as i32;
    let left = 70;
    let width = left + ncols * TILE;
    let height = LABEL_H + rows.len() as i32 * TILE;
    let mut sheet = Mat::new_rows_cols_with_default(height, width, CV_8UC1, Scalar::all(255.0))?;
    for (j, (name, _)) in first.1.iter().enumerate() {
        let short: String = name.chars().take(24).collect();
        label(
            &mut sheet,
            &short,
            Point::new(left + j as i32 * TILE + 4, 18),
            0.45,
        )?;
    }
    for (i, (c, cols)) in rows.iter().enumerate() {
        let y = LABEL_H + i as i32 * TILE;
        label(
            &mut sheet,
            &format!("{c:.2}/m"),
            Point::new(4, y + TILE / 2),
            0.5,
        )?;
        for (j, (_, m)) in cols.iter().enumerate() {
            let mut dst =
                Mat::roi_mut(&mut sheet, Rect::new(left + j as i32 * TILE, y, TILE, TILE))?;
            m.copy_to(&mut dst)?;
        }
    }
    imwrite(&a.out, &sheet)?;
    crate::outln!("wrote {}", a.out.display());
    Ok(())
}
