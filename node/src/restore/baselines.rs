//! The baselines HOIRM is compared with (paper §6.1), for grey images.
//!
//! - [`Passthrough`]: no restoration.
//! - [`ClaheOnly`]: CLAHE with the usual clip limit 2 and an 8x8 tile grid.
//! - [`DarkChannel`] (DCP, He, Sun, Tang 2010): dark channel = local minimum
//!   over a 15x15 patch (a grey image has one channel, so only the spatial
//!   minimum remains); atmospheric light `A` = the brightest input pixel among
//!   the 0.1 % brightest dark-channel pixels; transmission
//!   `t = 1 − ω·dark(I/A)` (ω = 0.95 keeps a little haze), refined with
//!   the guided filter (He et al. 2013, radius 40, ε = 1e-3, the image as
//!   guide) instead of soft matting; `J = (I − A)/max(t, t0) + A`, t0 = 0.1.
//! - [`DarkChannel`] with `underwater = true` (UDCP, Drews et al. 2013):
//!   UDCP computes the dark channel over the green and blue channels only,
//!   because red is absorbed within metres and would make every underwater
//!   dark channel ≈ 0. A grey camera has no red channel to leave out — its
//!   single channel already plays the role of the least-attenuated ones — so
//!   on grey images the channel restriction is vacuous. What remains of
//!   UDCP, and what we implement, is its background-light estimate: the
//!   water's colour at the pixel where the dark channel is *largest* (the
//!   most haze-opaque point, normally open water), not the brightest pixel
//!   among the haziest ones, which on a marker picks the white ring
//!   and over-estimates `B∞`; and ω = 1, since underwater the veil carries
//!   no aerial-perspective depth cue worth keeping. Everything else is DCP's.

use super::water::{histogram, WaterEstimate};
use super::{
    check_input, clahe_grid, coarse_level, snapshot, Method, RestoreError, RestoreParams, Restored,
    Restorer,
};
use opencv::core::{self, Mat, Point, Size, BORDER_REFLECT_101, CV_32F, CV_8U};
use opencv::imgproc;
use opencv::prelude::*;

/// Water estimate and reported `c` shared by the baselines (they do not use it).
fn describe(gray: &Mat, params: &RestoreParams) -> Result<(f64, f64), RestoreError> {
    let coarse = coarse_level(gray, 8)?;
    let w = WaterEstimate::from_image(gray, &coarse, params)?;
    Ok((params.c_per_m.unwrap_or(w.c_per_m), w.backscatter))
}

fn finish(
    gray: &Mat,
    image: Mat,
    params: &RestoreParams,
    stages: Vec<(String, Mat)>,
) -> Result<Restored, RestoreError> {
    let (c, b) = describe(gray, params)?;
    let frame = core::Rect::new(0, 0, gray.cols(), gray.rows());
    Ok(Restored {
        image,
        pyramid_level: 0,
        level_image: None,
        estimated_c_per_m: c,
        backscatter: b,
        rois: vec![frame],
        stages: params.keep_stages.then_some(stages),
        fine: None,
    })
}

/// No restoration.
#[derive(Debug)]
pub struct Passthrough {
    params: RestoreParams,
}

impl Passthrough {
    pub fn new(params: &RestoreParams) -> Self {
        Self {
            params: params.clone(),
        }
    }
}

impl Restorer for Passthrough {
    fn method(&self) -> Method {
        Method::None
    }
    fn restore(&mut self, gray: &Mat, _stamp_ns: u64) -> Result<Restored, RestoreError> {
        check_input(gray)?;
        finish(gray, gray.try_clone()?, &self.params, Vec::new())
    }
}

/// CLAHE alone.
#[derive(Debug)]
pub struct ClaheOnly {
    params: RestoreParams,
}

impl ClaheOnly {
    pub fn new(params: &RestoreParams) -> Self {
        Self {
            params: params.clone(),
        }
    }
}

impl Restorer for ClaheOnly {
    fn method(&self) -> Method {
        Method::Clahe
    }
    fn restore(&mut self, gray: &Mat, _stamp_ns: u64) -> Result<Restored, RestoreError> {
        check_input(gray)?;
        if let Some(e) = self.params.problem() {
            return Err(e);
        }
        let g = self.params.baseline_clahe_grid;
        let out = clahe_grid(gray, self.params.baseline_clahe_clip, Size::new(g, g))?;
        finish(gray, out, &self.params, Vec::new())
    }
}

/// DCP (`underwater = false`) or its UDCP adaptation (`true`), see the module docs.
#[derive(Debug)]
pub struct DarkChannel {
    params: RestoreParams,
    underwater: bool,
}

/// Fraction of the brightest dark-channel pixels He et al. take for `A`.
const DCP_TOP_FRACTION: f64 = 0.001;

impl DarkChannel {
    pub fn new(params: &RestoreParams, underwater: bool) -> Self {
        Self {
            params: params.clone(),
            underwater,
        }
    }

    /// The dark channel of a grey image: the minimum over a `patch`x`patch` window.
    pub fn dark_channel(gray: &Mat, patch: i32) -> Result<Mat, RestoreError> {
        let kernel = imgproc::get_structuring_element(
            imgproc::MORPH_RECT,
            Size::new(patch, patch),
            Point::new(-1, -1),
        )?;
        let mut dark = Mat::default();
        imgproc::erode(
            gray,
            &mut dark,
            &kernel,
            Point::new(-1, -1),
            1,
            core::BORDER_REPLICATE,
            imgproc::morphology_default_border_value()?,
        )?;
        Ok(dark)
    }

    /// Atmospheric (background) light, grey levels.
    fn background_light(&self, gray: &Mat, dark: &Mat) -> Result<f64, RestoreError> {
        if self.underwater {
            let mut loc = Point::default();
            core::min_max_loc(dark, None, None, None, Some(&mut loc), &core::no_array())?;
            return Ok(*gray.at_2d::<u8>(loc.y, loc.x)? as f64);
        }
        let hist = histogram(dark)?;
        let total: u64 = hist.iter().sum();
        let want = ((total as f64 * DCP_TOP_FRACTION).ceil() as u64).max(1);
        let mut acc = 0;
        let mut thr = 255u8;
        for v in (0..256).rev() {
            acc += hist[v];
            if acc >= want {
                thr = v as u8;
                break;
            }
        }
        let mut a = 0u8;
        for y in 0..gray.rows() {
            let (g, d) = (gray.at_row::<u8>(y)?, dark.at_row::<u8>(y)?);
            for (&gv, &dv) in g.iter().zip(d) {
                if dv >= thr && gv > a {
                    a = gv;
                }
            }
        }
        Ok(a as f64)
    }
}

/// He et al.'s guided filter of `p` with guide `guide` (both f32, same size).
pub fn guided_filter(guide: &Mat, p: &Mat, radius: i32, eps: f64) -> Result<Mat, RestoreError> {
    let k = Size::new(2 * radius + 1, 2 * radius + 1);
    let boxf = |m: &Mat| -> Result<Mat, RestoreError> {
        let mut o = Mat::default();
        imgproc::box_filter(
            m,
            &mut o,
            CV_32F,
            k,
            Point::new(-1, -1),
            true,
            BORDER_REFLECT_101,
        )?;
        Ok(o)
    };
    let mul = |a: &Mat, b: &Mat| -> Result<Mat, RestoreError> {
        let mut o = Mat::default();
        core::multiply(a, b, &mut o, 1.0, -1)?;
        Ok(o)
    };
    let mean_i = boxf(guide)?;
    let mean_p = boxf(p)?;
    let corr_ii = boxf(&mul(guide, guide)?)?;
    let corr_ip = boxf(&mul(guide, p)?)?;
    let (rows, cols) = (guide.rows(), guide.cols());
    let mut a = Mat::new_rows_cols_with_default(rows, cols, CV_32F, core::Scalar::all(0.0))?;
    let mut b = Mat::new_rows_cols_with_default(rows, cols, CV_32F, core::Scalar::all(0.0))?;
    for y in 0..rows {
        let (mi, mp) = (mean_i.at_row::<f32>(y)?, mean_p.at_row::<f32>(y)?);
        let (cii, cip) = (corr_ii.at_row::<f32>(y)?, corr_ip.at_row::<f32>(y)?);
        let ar = a.at_row_mut::<f32>(y)?;
        for x in 0..cols as usize {
            let var = cii[x] - mi[x] * mi[x];
            let cov = cip[x] - mi[x] * mp[x];
            ar[x] = cov / (var + eps as f32);
        }
        let ar = a.at_row::<f32>(y)?.to_vec();
        let br = b.at_row_mut::<f32>(y)?;
        for x in 0..cols as usize {
            br[x] = mp[x] - ar[x] * mi[x];
        }
    }
    let mean_a = boxf(&a)?;
    let mean_b = boxf(&b)?;
    let mut q = mul(&mean_a, guide)?;
    let mut sum = Mat::default();
    core::add(&q, &mean_b, &mut sum, &core::no_array(), -1)?;
    q = sum;
    Ok(q)
}

impl Restorer for DarkChannel {
    fn method(&self) -> Method {
        if self.underwater {
            Method::Udcp
        } else {
            Method::Dcp
        }
    }

    fn restore(&mut self, gray: &Mat, _stamp_ns: u64) -> Result<Restored, RestoreError> {
        check_input(gray)?;
        let p = &self.params;
        if let Some(e) = p.problem() {
            return Err(e);
        }
        let dark = Self::dark_channel(gray, p.dcp_patch)?;
        let a = self.background_light(gray, &dark)?.max(1.0);
        let omega = if self.underwater { 1.0 } else { p.dcp_omega };
        // t = 1 − ω·dark/A (the min filter commutes with dividing by A > 0).
        let mut t = Mat::default();
        dark.convert_to(&mut t, CV_32F, -omega / a, 1.0)?;
        if p.dcp_guided_radius > 0 {
            let mut guide = Mat::default();
            gray.convert_to(&mut guide, CV_32F, 1.0 / 255.0, 0.0)?;
            t = guided_filter(&guide, &t, p.dcp_guided_radius, p.dcp_guided_eps)?;
        }
        let t0 = p.dcp_t0 as f32;
        let a32 = a as f32;
        let mut out = Mat::new_rows_cols_with_default(
            gray.rows(),
            gray.cols(),
            CV_8U,
            core::Scalar::all(0.0),
        )?;
        for y in 0..gray.rows() {
            let (g, tr) = (gray.at_row::<u8>(y)?, t.at_row::<f32>(y)?);
            let o = out.at_row_mut::<u8>(y)?;
            for x in 0..g.len() {
                let j = (g[x] as f32 - a32) / tr[x].max(t0) + a32;
                o[x] = j.round().clamp(0.0, 255.0) as u8;
            }
        }
        let mut stages = Vec::new();
        if p.keep_stages {
            stages.push(("dark channel".to_string(), snapshot(&dark)?));
            let mut t8 = Mat::default();
            t.convert_to(&mut t8, CV_8U, 255.0, 0.0)?;
            stages.push(("transmission".to_string(), t8));
        }
        finish(gray, out, p, stages)
    }
}
