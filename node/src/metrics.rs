//! Image-quality metrics for scoring restoration against the simulator's
//! clean image (paper §6.1, Tables 1–4): SSIM, PSNR and the marker's
//! contrast-to-noise ratio (CNR).
//!
//! - [`ssim`]: Wang, Bovik, Sheikh, Simoncelli 2004 ("Image quality
//!   assessment: from error visibility to structural similarity", the
//!   paper's [45]) exactly as their reference `ssim_index.m`: an 11x11
//!   Gaussian window with σ = 1.5, `K1 = 0.01`, `K2 = 0.03`, dynamic range
//!   `L = 255`, statistics only where the window fits inside the image
//!   ("valid" filtering), and the mean of the SSIM map.
//! - [`psnr`]: `10·log10(255² / MSE)` in dB; `+∞` for identical images.
//! - [`cnr`]: `|μ_w − μ_b| / sqrt(σ_w² + σ_b²)` between the pixels of a
//!   marker's white cells and of its black cells (population variances).
//!   This is the two-region CNR of the paper's [46]: a difference of means
//!   in units of the pooled noise. It is signless (a contrast reversal is
//!   still contrast) and dimensionless, so it is invariant to any affine
//!   grey-level change `a·I + b` — CLAHE-like gains do not raise it by
//!   themselves; only a better separation of the two populations does.
//!
//! - [`michelson_contrast`]: `|μ_w − μ_b| / (μ_w + μ_b)` of the same two
//!   populations, 0..1: how much of the grey range the marker still spans
//!   (unlike CNR it falls with the water's veil, whatever the noise).
//! - [`marker_contrast`]: both of the above on the white and black modules
//!   of a *detected* marker, located from its corners alone (what the node
//!   reports on the wire as `ImageQuality`).
//!
//! All functions take 8-bit grey [`GrayImage`]s; `*_mat` variants take
//! single-channel 8-bit `cv::Mat`s.

use crate::detect::Detection;
use nalgebra::{Matrix3, SMatrix, SVector, Vector3};
use opencv::core::{Mat, Rect, CV_8UC1};
use opencv::prelude::*;
use shoal_proto::GrayImage;

/// Side of the SSIM window (Wang et al. 2004).
pub const SSIM_WINDOW: usize = 11;
/// Standard deviation of the SSIM Gaussian window, pixels.
pub const SSIM_SIGMA: f64 = 1.5;
/// SSIM stabilizing constants' factors.
pub const SSIM_K1: f64 = 0.01;
pub const SSIM_K2: f64 = 0.03;
/// Dynamic range of 8-bit images.
const L: f64 = 255.0;

/// Errors of the metrics.
#[derive(Debug, thiserror::Error)]
pub enum MetricError {
    #[error("image sizes differ: {a_width}x{a_height} vs {b_width}x{b_height}")]
    SizeMismatch {
        a_width: u32,
        a_height: u32,
        b_width: u32,
        b_height: u32,
    },
    #[error("image {width}x{height} is smaller than the {min}x{min} minimum of this metric")]
    TooSmall { width: u32, height: u32, min: u32 },
    #[error("image {width}x{height} holds {actual} bytes, expected {expected}")]
    BadBuffer {
        width: u32,
        height: u32,
        actual: usize,
        expected: usize,
    },
    #[error("mask {which} has {actual} entries, the image {expected} pixels")]
    MaskSize {
        which: &'static str,
        actual: usize,
        expected: usize,
    },
    #[error("mask {which} selects fewer than 2 pixels ({count})")]
    MaskTooSmall { which: &'static str, count: usize },
    #[error("both regions are noiseless (σ_w = σ_b = 0): CNR is undefined")]
    NoNoise,
    #[error("Mat is not single-channel 8-bit (type {typ})")]
    MatType { typ: i32 },
    #[error("OpenCV")]
    OpenCv(#[from] opencv::Error),
    #[error("marker {marker}: {reason}")]
    Marker { marker: String, reason: String },
}

fn check_buffer(img: &GrayImage) -> Result<(), MetricError> {
    let expected = img.width as usize * img.height as usize;
    if img.data.len() != expected {
        return Err(MetricError::BadBuffer {
            width: img.width,
            height: img.height,
            actual: img.data.len(),
            expected,
        });
    }
    Ok(())
}

fn check_pair(a: &GrayImage, b: &GrayImage) -> Result<(), MetricError> {
    check_buffer(a)?;
    check_buffer(b)?;
    if a.width != b.width || a.height != b.height {
        return Err(MetricError::SizeMismatch {
            a_width: a.width,
            a_height: a.height,
            b_width: b.width,
            b_height: b.height,
        });
    }
    Ok(())
}

/// The normalized 1-D Gaussian of the SSIM window (its outer product is the 2-D window).
fn gaussian_1d() -> [f64; SSIM_WINDOW] {
    let mut g = [0.0; SSIM_WINDOW];
    let c = (SSIM_WINDOW / 2) as f64;
    for (i, v) in g.iter_mut().enumerate() {
        let d = i as f64 - c;
        *v = (-d * d / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp();
    }
    let s: f64 = g.iter().sum();
    g.iter_mut().for_each(|v| *v /= s);
    g
}

/// "Valid" separable filtering of a `w`x`h` f64 image with the SSIM window.
fn filter_valid(src: &[f64], w: usize, h: usize, g: &[f64; SSIM_WINDOW]) -> Vec<f64> {
    let ow = w + 1 - SSIM_WINDOW;
    let oh = h + 1 - SSIM_WINDOW;
    // Horizontal pass: h rows x ow columns.
    let mut tmp = vec![0.0; ow * h];
    for y in 0..h {
        let row = &src[y * w..(y + 1) * w];
        for x in 0..ow {
            let mut s = 0.0;
            for k in 0..SSIM_WINDOW {
                s += g[k] * row[x + k];
            }
            tmp[y * ow + x] = s;
        }
    }
    let mut out = vec![0.0; ow * oh];
    for y in 0..oh {
        for k in 0..SSIM_WINDOW {
            let gk = g[k];
            let row = &tmp[(y + k) * ow..(y + k + 1) * ow];
            let orow = &mut out[y * ow..(y + 1) * ow];
            for x in 0..ow {
                orow[x] += gk * row[x];
            }
        }
    }
    out
}

/// Mean structural similarity of `a` and `b` (Wang et al. 2004), in `[-1, 1]`, 1 iff identical.
pub fn ssim(a: &GrayImage, b: &GrayImage) -> Result<f64, MetricError> {
    check_pair(a, b)?;
    let (w, h) = (a.width as usize, a.height as usize);
    if w < SSIM_WINDOW || h < SSIM_WINDOW {
        return Err(MetricError::TooSmall {
            width: a.width,
            height: a.height,
            min: SSIM_WINDOW as u32,
        });
    }
    let g = gaussian_1d();
    let fa: Vec<f64> = a.data.iter().map(|&v| v as f64).collect();
    let fb: Vec<f64> = b.data.iter().map(|&v| v as f64).collect();
    let aa: Vec<f64> = fa.iter().map(|v| v * v).collect();
    let bb: Vec<f64> = fb.iter().map(|v| v * v).collect();
    let ab: Vec<f64> = fa.iter().zip(&fb).map(|(x, y)| x * y).collect();
    let mu_a = filter_valid(&fa, w, h, &g);
    let mu_b = filter_valid(&fb, w, h, &g);
    let e_aa = filter_valid(&aa, w, h, &g);
    let e_bb = filter_valid(&bb, w, h, &g);
    let e_ab = filter_valid(&ab, w, h, &g);
    let c1 = (SSIM_K1 * L).powi(2);
    let c2 = (SSIM_K2 * L).powi(2);
    let n = mu_a.len();
    let mut sum = 0.0;
    for i in 0..n {
        let (ma, mb) = (mu_a[i], mu_b[i]);
        let va = e_aa[i] - ma * ma;
        let vb = e_bb[i] - mb * mb;
        let cov = e_ab[i] - ma * mb;
        sum +=
            ((2.0 * ma * mb + c1) * (2.0 * cov + c2)) / ((ma * ma + mb * mb + c1) * (va + vb + c2));
    }
    Ok(sum / n as f64)
}

/// Mean squared error between two same-size images.
pub fn mse(a: &GrayImage, b: &GrayImage) -> Result<f64, MetricError> {
    check_pair(a, b)?;
    if a.data.is_empty() {
        return Err(MetricError::TooSmall {
            width: a.width,
            height: a.height,
            min: 1,
        });
    }
    let s: f64 = a
        .data
        .iter()
        .zip(&b.data)
        .map(|(&x, &y)| {
            let d = x as f64 - y as f64;
            d * d
        })
        .sum();
    Ok(s / a.data.len() as f64)
}

/// Peak signal-to-noise ratio in dB for 8-bit images: `10·log10(255²/MSE)`;
/// `f64::INFINITY` when the images are identical.
pub fn psnr(a: &GrayImage, b: &GrayImage) -> Result<f64, MetricError> {
    let m = mse(a, b)?;
    if m == 0.0 {
        return Ok(f64::INFINITY);
    }
    Ok(10.0 * (L * L / m).log10())
}

/// Mean and population variance of the pixels selected by `mask`.
fn masked_stats(
    img: &GrayImage,
    mask: &[bool],
    which: &'static str,
) -> Result<(f64, f64), MetricError> {
    if mask.len() != img.data.len() {
        return Err(MetricError::MaskSize {
            which,
            actual: mask.len(),
            expected: img.data.len(),
        });
    }
    let (mut n, mut s, mut s2) = (0usize, 0.0, 0.0);
    for (&v, &m) in img.data.iter().zip(mask) {
        if m {
            let v = v as f64;
            n += 1;
            s += v;
            s2 += v * v;
        }
    }
    if n < 2 {
        return Err(MetricError::MaskTooSmall { which, count: n });
    }
    let mean = s / n as f64;
    let var = (s2 / n as f64 - mean * mean).max(0.0);
    Ok((mean, var))
}

/// Contrast-to-noise ratio between the `white` and `black` regions (row-major
/// masks of the image's size): `|μ_w − μ_b| / sqrt(σ_w² + σ_b²)`.
pub fn cnr(img: &GrayImage, white: &[bool], black: &[bool]) -> Result<f64, MetricError> {
    check_buffer(img)?;
    let (mw, vw) = masked_stats(img, white, "white")?;
    let (mb, vb) = masked_stats(img, black, "black")?;
    let noise = (vw + vb).sqrt();
    if noise == 0.0 {
        return Err(MetricError::NoNoise);
    }
    Ok((mw - mb).abs() / noise)
}

/// Michelson contrast `|μ_w − μ_b| / (μ_w + μ_b)` between the mean grey
/// levels of the `white` and `black` regions (row-major masks of the
/// image's size), in 0..1; 0 when both regions are black.
pub fn michelson_contrast(
    img: &GrayImage,
    white: &[bool],
    black: &[bool],
) -> Result<f64, MetricError> {
    check_buffer(img)?;
    let (mw, _) = masked_stats(img, white, "white")?;
    let (mb, _) = masked_stats(img, black, "black")?;
    Ok(if mw + mb > 0.0 {
        (mw - mb).abs() / (mw + mb)
    } else {
        0.0
    })
}

/// Part of each module's side that [`marker_contrast`] samples: the central
/// 60 %, so blurred module borders and corner errors of a few tenths of a
/// module do not mix the two populations (the evaluation's masks keep the
/// same part, `shoal::eval::scene::module_masks`).
pub const MARKER_MODULE_INNER: f64 = 0.6;

/// The contrast of one detected marker's modules on one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MarkerContrast {
    /// [`michelson_contrast`] of its white and black modules, 0..1.
    pub michelson: f64,
    /// [`cnr`] of its white and black modules.
    pub cnr: f64,
}

/// [`michelson_contrast`] and [`cnr`] of the white and black modules of
/// `det` on `gray` (8-bit, the frame its corners were measured on).
///
/// The modules are located from the detection alone: the largest square of
/// corners it holds completely (for the enhanced marker the outer frame, else
/// the frame's inner edge or the code border, whichever is complete) gives a
/// homography from pixels to the module grid, and each pixel of the marker's
/// bounding box whose grid position falls in the central
/// [`MARKER_MODULE_INNER`] of a module counts as white or black after
/// [`CodeSet::module_grid`](shoal_proto::CodeSet::module_grid) of the
/// decoded ID. Lens distortion is not taken out (it moves a 300 px marker's
/// modules by well under the 20 % margin kept on each side).
pub fn marker_contrast(gray: &Mat, det: &Detection) -> Result<MarkerContrast, MetricError> {
    let marker = || format!("{}#{}", det.codes, det.id);
    let err = |reason: String| MetricError::Marker {
        marker: marker(),
        reason,
    };
    if gray.typ() != CV_8UC1 {
        return Err(MetricError::MatType { typ: gray.typ() });
    }
    let grid = det
        .codes
        .module_grid(det.id)
        .map_err(|e| err(e.to_string()))?;
    let m = det.codes.modules();
    // Square s of `corners_3d` has half-side halves[s] of the black square,
    // i.e. it starts `(0.5 - half) * m` modules inside it.
    let squares = det.codes.corner_count() / 4;
    let outer = det.codes.corners_3d(1.0);
    let (square, px) = (0..squares)
        .find_map(|s| {
            let px: Option<Vec<[f64; 2]>> = (0..4)
                .map(|k| {
                    det.corner_ids
                        .iter()
                        .position(|&c| usize::from(c) == 4 * s + k)
                        .and_then(|i| det.corners_px.get(i).copied())
                })
                .collect();
            px.map(|px| (s, px))
        })
        .ok_or_else(|| err("no complete square of corners".into()))?;
    let inset = (0.5 - outer[4 * square].x.abs()) * m as f64;
    let far = m as f64 - inset;
    // corners_3d order: top-left, top-right, bottom-right, bottom-left
    // (grid columns to the right, rows down).
    let grid_pts = [[inset, inset], [far, inset], [far, far], [inset, far]];
    let to_grid = homography(&px, &grid_pts).ok_or_else(|| err("degenerate corners".into()))?;
    let to_px = to_grid
        .try_inverse()
        .ok_or_else(|| err("degenerate corners".into()))?;
    let apply = |h: &Matrix3<f64>, x: f64, y: f64| {
        let p = h * Vector3::new(x, y, 1.0);
        [p.x / p.z, p.y / p.z]
    };
    // Bounding box of the whole black square, clipped to the frame.
    let ends = [0.0, m as f64];
    let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for &u in &ends {
        for &v in &ends {
            let [x, y] = apply(&to_px, u, v);
            (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x), y1.max(y));
        }
    }
    let clip = |v: f64, hi: i32| (v.max(0.0) as i32).min(hi);
    let (x0, y0) = (clip(x0.floor(), gray.cols()), clip(y0.floor(), gray.rows()));
    let (x1, y1) = (clip(x1.ceil(), gray.cols()), clip(y1.ceil(), gray.rows()));
    if x1 - x0 < 2 || y1 - y0 < 2 {
        return Err(err("outside the frame".into()));
    }
    let roi = Mat::roi(gray, Rect::new(x0, y0, x1 - x0, y1 - y0))?.clone_pointee();
    let crop = gray_from_mat(&roi)?;
    let n = crop.data.len();
    let (mut white, mut black) = (vec![false; n], vec![false; n]);
    let margin = 0.5 * (1.0 - MARKER_MODULE_INNER);
    for y in 0..crop.height as usize {
        for x in 0..crop.width as usize {
            // Pixel centres are at integer coordinates (OpenCV's convention).
            let [u, v] = apply(&to_grid, (x0 as usize + x) as f64, (y0 as usize + y) as f64);
            if !(u >= 0.0 && v >= 0.0 && u < m as f64 && v < m as f64) {
                continue;
            }
            let (fu, fv) = (u.fract(), v.fract());
            if fu < margin || fu > 1.0 - margin || fv < margin || fv > 1.0 - margin {
                continue;
            }
            let i = y * crop.width as usize + x;
            if grid[v as usize * m + u as usize] {
                white[i] = true;
            } else {
                black[i] = true;
            }
        }
    }
    Ok(MarkerContrast {
        michelson: michelson_contrast(&crop, &white, &black)?,
        cnr: cnr(&crop, &white, &black)?,
    })
}

/// The projective map taking each `from` point to its `to` point (four
/// correspondences, `h33 = 1`); `None` when they are degenerate.
fn homography(from: &[[f64; 2]], to: &[[f64; 2]; 4]) -> Option<Matrix3<f64>> {
    let mut a = SMatrix::<f64, 8, 8>::zeros();
    let mut b = SVector::<f64, 8>::zeros();
    for (k, (p, q)) in from.iter().zip(to).enumerate() {
        let (x, y, u, v) = (p[0], p[1], q[0], q[1]);
        a.set_row(
            2 * k,
            &SMatrix::<f64, 1, 8>::from_row_slice(&[x, y, 1.0, 0.0, 0.0, 0.0, -x * u, -y * u]),
        );
        a.set_row(
            2 * k + 1,
            &SMatrix::<f64, 1, 8>::from_row_slice(&[0.0, 0.0, 0.0, x, y, 1.0, -x * v, -y * v]),
        );
        b[2 * k] = u;
        b[2 * k + 1] = v;
    }
    let h = a.lu().solve(&b)?;
    let h = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], 1.0);
    h.iter().all(|v| v.is_finite()).then_some(h)
}

/// Copy a single-channel 8-bit `Mat` into a [`GrayImage`].
pub fn gray_from_mat(m: &Mat) -> Result<GrayImage, MetricError> {
    if m.typ() != CV_8UC1 {
        return Err(MetricError::MatType { typ: m.typ() });
    }
    let (w, h) = (m.cols().max(0) as u32, m.rows().max(0) as u32);
    let mut data = Vec::with_capacity(w as usize * h as usize);
    for y in 0..h as i32 {
        data.extend_from_slice(m.at_row::<u8>(y)?);
    }
    Ok(GrayImage {
        width: w,
        height: h,
        data,
    })
}

/// [`ssim`] of two 8-bit single-channel `Mat`s.
pub fn ssim_mat(a: &Mat, b: &Mat) -> Result<f64, MetricError> {
    ssim(&gray_from_mat(a)?, &gray_from_mat(b)?)
}

/// [`psnr`] of two 8-bit single-channel `Mat`s.
pub fn psnr_mat(a: &Mat, b: &Mat) -> Result<f64, MetricError> {
    psnr(&gray_from_mat(a)?, &gray_from_mat(b)?)
}

/// [`cnr`] of an 8-bit single-channel `Mat`.
pub fn cnr_mat(img: &Mat, white: &[bool], black: &[bool]) -> Result<f64, MetricError> {
    cnr(&gray_from_mat(img)?, white, black)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_image(w: u32, h: u32, seed: u64) -> GrayImage {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let data = (0..w * h).map(|_| rng.gen::<u8>()).collect();
        GrayImage::from_vec(w, h, data).unwrap()
    }

    #[test]
    fn ssim_of_an_image_with_itself_is_one() {
        let a = random_image(40, 30, 1);
        assert!((ssim(&a, &a).unwrap() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn ssim_of_two_flat_images_matches_the_luminance_term_by_hand() {
        // Flat 100 vs flat 120: variances and covariance are 0, so
        // SSIM = (2·100·120 + C1) / (100² + 120² + C1), C1 = (0.01·255)² = 6.5025.
        let a = GrayImage::filled(20, 15, 100);
        let b = GrayImage::filled(20, 15, 120);
        let expected = (24_000.0 + 6.5025) / (24_400.0 + 6.5025);
        assert!((ssim(&a, &b).unwrap() - expected).abs() < 1e-12);
    }

    #[test]
    fn ssim_of_an_11x11_image_equals_the_single_window_formula() {
        // On an 11x11 image "valid" filtering leaves exactly one window:
        // compute its weighted statistics directly with the 2-D Gaussian.
        let a = random_image(11, 11, 2);
        let b = random_image(11, 11, 3);
        let mut wsum = 0.0;
        let (mut ma, mut mb, mut saa, mut sbb, mut sab) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for y in 0..11 {
            for x in 0..11 {
                let (dx, dy) = (x as f64 - 5.0, y as f64 - 5.0);
                let wgt = (-(dx * dx + dy * dy) / (2.0 * 1.5 * 1.5)).exp();
                let (va, vb) = (a.get(x, y) as f64, b.get(x, y) as f64);
                wsum += wgt;
                ma += wgt * va;
                mb += wgt * vb;
                saa += wgt * va * va;
                sbb += wgt * vb * vb;
                sab += wgt * va * vb;
            }
        }
        let (ma, mb) = (ma / wsum, mb / wsum);
        let va = saa / wsum - ma * ma;
        let vb = sbb / wsum - mb * mb;
        let cov = sab / wsum - ma * mb;
        let (c1, c2) = (6.5025, 58.5225);
        let expected =
            ((2.0 * ma * mb + c1) * (2.0 * cov + c2)) / ((ma * ma + mb * mb + c1) * (va + vb + c2));
        assert!((ssim(&a, &b).unwrap() - expected).abs() < 1e-9);
    }

    #[test]
    fn ssim_rejects_images_smaller_than_the_window_and_mismatched_sizes() {
        let a = GrayImage::filled(10, 20, 0);
        assert!(matches!(ssim(&a, &a), Err(MetricError::TooSmall { .. })));
        let b = GrayImage::filled(20, 20, 0);
        let c = GrayImage::filled(20, 21, 0);
        assert!(matches!(
            ssim(&b, &c),
            Err(MetricError::SizeMismatch { .. })
        ));
        let bad = GrayImage {
            width: 20,
            height: 20,
            data: vec![0; 5],
        };
        assert!(matches!(ssim(&bad, &b), Err(MetricError::BadBuffer { .. })));
    }

    #[test]
    fn psnr_of_a_known_mse() {
        // Every pixel off by 5: MSE = 25, PSNR = 10·log10(65025/25) = 34.1514 dB.
        let a = GrayImage::filled(8, 8, 100);
        let b = GrayImage::filled(8, 8, 105);
        let expected = 10.0 * (65025.0f64 / 25.0).log10();
        assert!((psnr(&a, &b).unwrap() - expected).abs() < 1e-12);
        assert!((expected - 34.1514).abs() < 1e-3);
        assert_eq!(psnr(&a, &a).unwrap(), f64::INFINITY);
    }

    #[test]
    fn cnr_of_a_two_level_image_with_known_noise() {
        // Left half 60, right half 180, each ± a symmetric ±d pattern:
        // σ_w² = σ_b² = d², CNR = 120 / sqrt(2 d²).
        let (w, h) = (64u32, 32u32);
        let d = 10i32;
        let mut data = Vec::new();
        let mut white = Vec::new();
        let mut black = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let sign = if (x + y) % 2 == 0 { 1 } else { -1 };
                let base = if x < w / 2 { 60 } else { 180 };
                data.push((base + sign * d) as u8);
                white.push(x >= w / 2);
                black.push(x < w / 2);
            }
        }
        let img = GrayImage::from_vec(w, h, data).unwrap();
        let expected = 120.0 / (2.0 * (d * d) as f64).sqrt();
        assert!((cnr(&img, &white, &black).unwrap() - expected).abs() < 1e-9);
    }

    #[test]
    fn cnr_of_gaussian_noise_is_near_its_expected_value() {
        use rand_distr::{Distribution, Normal};
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let noise = Normal::new(0.0, 8.0).unwrap();
        let (w, h) = (200u32, 200u32);
        let mut data = Vec::new();
        let mut white = Vec::new();
        for y in 0..h {
            for _x in 0..w {
                let is_white = y < h / 2;
                let base = if is_white { 170.0 } else { 90.0 };
                let v: f64 = base + noise.sample(&mut rng);
                data.push(v.round().clamp(0.0, 255.0) as u8);
                white.push(is_white);
            }
        }
        let black: Vec<bool> = white.iter().map(|w| !w).collect();
        let img = GrayImage::from_vec(w, h, data).unwrap();
        // 80 / sqrt(64 + 64) = 7.07; rounding adds 1/12 to each variance.
        let expected = 80.0 / (2.0 * (64.0 + 1.0 / 12.0f64)).sqrt();
        let got = cnr(&img, &white, &black).unwrap();
        assert!(
            (got - expected).abs() < 0.1,
            "got {got}, expected {expected}"
        );
    }

    #[test]
    fn cnr_rejects_bad_masks() {
        let img = GrayImage::filled(4, 4, 9);
        let m = vec![true; 16];
        assert!(matches!(
            cnr(&img, &m[..3], &m),
            Err(MetricError::MaskSize { .. })
        ));
        let none = vec![false; 16];
        assert!(matches!(
            cnr(&img, &m, &none),
            Err(MetricError::MaskTooSmall { .. })
        ));
        assert!(matches!(cnr(&img, &m, &m), Err(MetricError::NoNoise)));
    }

    #[test]
    fn mat_variants_agree_with_gray_image_ones() {
        let a = random_image(30, 20, 4);
        let b = random_image(30, 20, 5);
        let ma = Mat::new_rows_cols_with_data(20, 30, &a.data)
            .unwrap()
            .try_clone()
            .unwrap();
        let mb = Mat::new_rows_cols_with_data(20, 30, &b.data)
            .unwrap()
            .try_clone()
            .unwrap();
        assert_eq!(gray_from_mat(&ma).unwrap(), a);
        assert_eq!(ssim_mat(&ma, &mb).unwrap(), ssim(&a, &b).unwrap());
        assert_eq!(psnr_mat(&ma, &mb).unwrap(), psnr(&a, &b).unwrap());
    }

    /// Shoal marker #17 drawn axis-aligned with 20-px modules from (40, 40),
    /// white 200 and black 50 grey levels, plus a ±2 checkerboard: every
    /// sampled module is 12x12 px (balanced), so the populations' means are
    /// exactly 200 and 50 and their variances exactly 4.
    fn drawn_marker() -> (Mat, Vec<[f64; 2]>) {
        use shoal_proto::CodeSet;
        let grid = CodeSet::Shoal.module_grid(17).unwrap();
        let (side, module, x0) = (280usize, 20usize, 40usize);
        let mut data = vec![128u8; side * side];
        for y in 0..side {
            for x in 0..side {
                let (u, v) = (x as i64 - x0 as i64, y as i64 - x0 as i64);
                let inside = u >= 0 && v >= 0 && u < 200 && v < 200;
                let base: i32 = if !inside {
                    128
                } else if grid[(v as usize / module) * 10 + u as usize / module] {
                    200
                } else {
                    50
                };
                let noise = if (x + y).is_multiple_of(2) { 2 } else { -2 };
                data[y * side + x] = (base + noise) as u8;
            }
        }
        let mat = Mat::new_rows_cols_with_data(side as i32, side as i32, &data)
            .unwrap()
            .try_clone()
            .unwrap();
        // Module edges fall between pixel centres: the marker covers columns 40..=239.
        let corners = [0.0, 20.0, 40.0]
            .iter()
            .flat_map(|&inset| {
                let (a, b) = (39.5 + inset, 239.5 - inset);
                [[a, a], [b, a], [b, b], [a, b]]
            })
            .collect();
        (mat, corners)
    }

    fn detection(corners_px: Vec<[f64; 2]>, corner_ids: Vec<u8>) -> Detection {
        Detection {
            codes: shoal_proto::CodeSet::Shoal,
            id: 17,
            corners_px,
            corner_ids,
            corner_covariance: None,
            hamming: 0,
            module_px: 20.0,
            corner_fit: crate::detect::CornerChoice::baseline(),
        }
    }

    #[test]
    fn marker_contrast_of_a_drawn_marker_is_its_drawn_contrast() {
        let (img, corners) = drawn_marker();
        let c = marker_contrast(&img, &detection(corners.clone(), (0..12).collect())).unwrap();
        assert!((c.michelson - 150.0 / 250.0).abs() < 1e-12, "{c:?}");
        assert!((c.cnr - 150.0 / 8f64.sqrt()).abs() < 1e-9, "{c:?}");
        // Without the outer frame's corners the code border's square maps the same modules.
        let inner = detection(corners[8..].to_vec(), (8..12).collect());
        assert_eq!(marker_contrast(&img, &inner).unwrap(), c);
        // Corners of no complete square: an error naming the marker.
        let partial = detection(corners[..3].to_vec(), vec![0, 1, 2]);
        let e = marker_contrast(&img, &partial).unwrap_err();
        assert!(e.to_string().contains("shoal#17"), "{e}");
    }

    #[test]
    fn michelson_contrast_is_signless_and_zero_on_black() {
        let img = GrayImage::from_vec(2, 2, vec![150, 150, 50, 50]).unwrap();
        let (top, bottom) = (
            vec![true, true, false, false],
            vec![false, false, true, true],
        );
        let c = michelson_contrast(&img, &top, &bottom).unwrap();
        assert!((c - 0.5).abs() < 1e-12);
        assert_eq!(michelson_contrast(&img, &bottom, &top).unwrap(), c);
        let black = GrayImage::filled(2, 2, 0);
        assert_eq!(michelson_contrast(&black, &top, &bottom).unwrap(), 0.0);
    }
}
