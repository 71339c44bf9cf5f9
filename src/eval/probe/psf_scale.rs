//! `shoal eval probe psf-scale`: the pixel scale of Eq. (14)'s σ = 1/(2√p),
//! measured on the simulator. For each water, fit `I ≈ a·(J * h) + b` on the
//! marker's box (J the clean image, I the underwater one, noiseless, no
//! vignetting, no ambient gradient; least squares in a, b) for PSFs
//! `h = GgPsf { p, σ = s/(2√p) }`, and print the residual per (p, s).

use crate::eval::EvalError;
use opencv::core::{Mat, Point, Rect, BORDER_REFLECT_101, CV_32F};
use opencv::imgproc;
use opencv::prelude::*;
use shoal_node::restore::psf::GgPsf;
use shoal_node::restore::{water, RestoreParams};
use shoal_proto::geometry::pose_from_xyz_rpy;
use shoal_proto::{CameraModel, CodeSet, GrayImage, Pose};
use shoal_sim_bridge::render::{Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;

/// Pixels per unit of σ tried.
const SCALES: [f64; 9] = [0.5, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0];
/// PSF shapes tried (HOIRM's own `p(c)` is added per water).
const SHAPES: [f64; 6] = [0.6, 0.8, 1.0, 1.25, 1.5, 2.0];

#[derive(Debug, clap::Args)]
pub struct PsfScaleArgs {
    /// Waters (1/m, comma-separated).
    #[arg(long, value_delimiter = ',', default_value = "6.12,8.22,10.13,12.20")]
    pub c: Vec<f64>,
}

fn to_f32(g: &GrayImage, r: Rect) -> Result<Mat, EvalError> {
    let m = shoal_node::mat::gray_to_mat(g)?;
    let mut f = Mat::default();
    Mat::roi(&m, r)?.convert_to(&mut f, CV_32F, 1.0, 0.0)?;
    Ok(f)
}

/// Residual RMS of the best affine fit of `model` to `obs`.
fn affine_residual(model: &Mat, obs: &Mat) -> Result<f64, EvalError> {
    let (mut n, mut sx, mut sy, mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    for y in 0..model.rows() {
        let (a, b) = (model.at_row::<f32>(y)?, obs.at_row::<f32>(y)?);
        for (&x, &o) in a.iter().zip(b) {
            let (x, o) = (x as f64, o as f64);
            n += 1.0;
            sx += x;
            sy += o;
            sxx += x * x;
            sxy += x * o;
            syy += o * o;
        }
    }
    let vx = sxx / n - (sx / n).powi(2);
    let cxy = sxy / n - sx / n * sy / n;
    let vy = syy / n - (sy / n).powi(2);
    Ok((vy - cxy * cxy / vx.max(1e-12)).max(0.0).sqrt())
}

pub fn run(a: &PsfScaleArgs) -> Result<(), EvalError> {
    let cam = CameraModel::vehicle_1440();
    let params = RestoreParams::default();
    let pose: Pose = pose_from_xyz_rpy([0.0, 0.0, 0.6], [std::f64::consts::PI + 0.12, 0.18, 0.05]);
    let scene = Scene::single_marker(CodeSet::Shoal, 17, 0.1, pose);
    for &c in &a.c {
        let mut w = WaterParams::preset(c).noiseless();
        w.vignetting = 0.0;
        w.ambient_spatial = 0.0;
        let out = Renderer::new().render(&cam, &Pose::identity(), &scene, &w, 0.0, 1)?;
        let q = &out
            .visible
            .first()
            .ok_or_else(|| EvalError::Setup("the marker is not in view".into()))?
            .corners_px;
        let xs: Vec<f64> = q[..4].iter().map(|p| p[0]).collect();
        let ys: Vec<f64> = q[..4].iter().map(|p| p[1]).collect();
        let m = 60.0;
        let x0 = xs.iter().cloned().fold(f64::MAX, f64::min) - m;
        let y0 = ys.iter().cloned().fold(f64::MAX, f64::min) - m;
        let x1 = xs.iter().cloned().fold(f64::MIN, f64::max) + m;
        let y1 = ys.iter().cloned().fold(f64::MIN, f64::max) + m;
        let r = Rect::new(x0 as i32, y0 as i32, (x1 - x0) as i32, (y1 - y0) as i32);
        let (clean, obs) = (to_f32(&out.clean, r)?, to_f32(&out.image, r)?);
        let p_hoirm = water::psf_p(c, &params);
        crate::outln!("c = {c}: HOIRM p(c) = {p_hoirm:.2}; residual RMS (grey levels) per p, s:");
        let mut best = (f64::MAX, 0.0, 0.0);
        for p in SHAPES.into_iter().chain([p_hoirm]) {
            let mut line = format!("  p {p:4.2}:");
            for &s in &SCALES {
                let psf = GgPsf {
                    p,
                    sigma_px: s / (2.0 * p.sqrt()),
                    direct: 0.0,
                };
                let mut blurred = Mat::default();
                imgproc::filter_2d(
                    &clean,
                    &mut blurred,
                    CV_32F,
                    &psf.kernel()?,
                    Point::new(-1, -1),
                    0.0,
                    BORDER_REFLECT_101,
                )?;
                let e = affine_residual(&blurred, &obs)?;
                line += &format!(" s{s}={e:.3}");
                if e < best.0 {
                    best = (e, p, s);
                }
            }
            crate::outln!("{line}");
        }
        crate::outln!(
            "  best: p {:.2}, s {} px/unit (residual {:.3})",
            best.1,
            best.2,
            best.0
        );
    }
    Ok(())
}
