//! The pattern fit's image model: the printed marker rendered with exact
//! pixel-area coverage (a trapezoid CDF per module boundary) into one sharp
//! image per region (white modules, black modules, quiet zone), each seen
//! through the sharp part of the point-spread function and through every
//! Gaussian of [`HALO_SIGMAS_PX`], plus the white print times x and y (the
//! contrast gradient across a tilted marker): the linear bases whose weights
//! the fit solves for ([`build_bases`]).

use super::{PatternFitError, Window, QUIET_MODULES};
use crate::detect::geom::Px;
use nalgebra::{Matrix3, Vector3};
use opencv::core::{Mat, Size, BORDER_REPLICATE, CV_32F};
use opencv::prelude::*;

/// Region kinds of the printed pattern.
pub(super) const WHITE: usize = 0;
pub(super) const BLACK: usize = 1;
pub(super) const QUIET: usize = 2;
pub(super) const REGIONS: usize = 3;

/// Module coordinates of the outer corners of an `m`-module marker.
pub(super) fn unit_corners(m: f64) -> [Px; 4] {
    [[0.0, 0.0], [m, 0.0], [m, m], [0.0, m]]
}

/// Fraction of a unit pixel, projected onto a unit normal with components
/// of magnitude `a ≥ b`, lying below offset `t` (px) from its centre: the
/// CDF of the trapezoid that is the sum of two uniform widths `a` and `b`.
#[inline]
fn coverage(t: f64, a: f64, b: f64) -> f64 {
    let (t1, t2) = (0.5 * (a - b), 0.5 * (a + b));
    if t <= -t2 {
        0.0
    } else if t >= t2 {
        1.0
    } else if b < 1e-9 {
        (t / a + 0.5).clamp(0.0, 1.0)
    } else if t <= -t1 {
        (t + t2) * (t + t2) / (2.0 * a * b)
    } else if t <= t1 {
        b / (2.0 * a) + (t + t1) / a
    } else {
        1.0 - (t2 - t) * (t2 - t) / (2.0 * a * b)
    }
}

/// The derivative of [`coverage`] in `t`: the trapezoid's density.
#[inline]
fn coverage_density(t: f64, a: f64, b: f64) -> f64 {
    let (t1, t2) = (0.5 * (a - b), 0.5 * (a + b));
    let t = t.abs();
    if t >= t2 {
        0.0
    } else if b < 1e-9 || t <= t1 {
        1.0 / a
    } else {
        (t2 - t) / (a * b)
    }
}

/// The printed pattern's region at module (column `c`, row `r`).
#[inline]
fn region(grid: &[bool], m: i64, c: i64, r: i64) -> Option<usize> {
    if (0..m).contains(&c) && (0..m).contains(&r) {
        Some(if grid[(r * m + c) as usize] {
            WHITE
        } else {
            BLACK
        })
    } else {
        let q = QUIET_MODULES as i64;
        ((-q..m + q).contains(&c) && (-q..m + q).contains(&r)).then_some(QUIET)
    }
}

/// Weights of the module columns `i − 1, i, i + 1` (`i = ⌊u⌋`) in a pixel
/// whose centre sits at module coordinate `u` with gradient `grad` (modules
/// per px).
/// Also returns the weights' gradients in the image (per px).
#[inline]
fn axis_weights(u: f64, grad: [f64; 2]) -> (i64, [f64; 3], [[f64; 2]; 3]) {
    let g = (grad[0] * grad[0] + grad[1] * grad[1]).sqrt().max(1e-12);
    let (na, nb) = (grad[0].abs() / g, grad[1].abs() / g);
    let (a, b) = if na >= nb { (na, nb) } else { (nb, na) };
    let i = u.floor();
    let (sl, sr) = ((i - u) / g, (i + 1.0 - u) / g);
    let below = coverage(sl, a, b);
    let above = 1.0 - coverage(sr, a, b);
    // ∂s/∂x = −∇u / g (the spacing g taken as locally constant).
    let (dl, dr) = (coverage_density(sl, a, b), coverage_density(sr, a, b));
    let n = [grad[0] / g, grad[1] / g];
    let d_below = [-dl * n[0], -dl * n[1]];
    let d_above = [dr * n[0], dr * n[1]];
    (
        i as i64,
        [below, 1.0 - below - above, above],
        [
            d_below,
            [-d_below[0] - d_above[0], -d_below[1] - d_above[1]],
            d_above,
        ],
    )
}

/// The Gaussian of `sigma` px, applied at 1/2 or 1/4 resolution when it
/// is wide (area-averaged down, bilinear up, both centre-aligned; the
/// window's sides are multiples of 4): the same linear operator for the
/// bases and their derivatives, a fraction of the cost.
pub(super) fn blur(src: &Mat, sigma: f64) -> Result<Mat, PatternFitError> {
    let cv = |_| PatternFitError::OpenCv;
    let f = if sigma >= 12.0 {
        4
    } else if sigma >= 6.0 {
        2
    } else {
        1
    };
    let mut dst = Mat::default();
    if f == 1 {
        opencv::imgproc::gaussian_blur(
            src,
            &mut dst,
            Size::new(0, 0),
            sigma,
            sigma,
            BORDER_REPLICATE,
        )
        .map_err(cv)?;
        return Ok(dst);
    }
    let small_size = Size::new(src.cols() / f, src.rows() / f);
    let (mut small, mut blurred) = (Mat::default(), Mat::default());
    opencv::imgproc::resize(
        src,
        &mut small,
        small_size,
        0.0,
        0.0,
        opencv::imgproc::INTER_AREA,
    )
    .map_err(cv)?;
    let s = sigma / f as f64;
    opencv::imgproc::gaussian_blur(
        &small,
        &mut blurred,
        Size::new(0, 0),
        s,
        s,
        BORDER_REPLICATE,
    )
    .map_err(cv)?;
    opencv::imgproc::resize(
        &blurred,
        &mut dst,
        src.size().map_err(cv)?,
        0.0,
        0.0,
        opencv::imgproc::INTER_LINEAR,
    )
    .map_err(cv)?;
    Ok(dst)
}

pub(super) fn mat_from(v: &[f32], w: usize, h: usize) -> Result<Mat, PatternFitError> {
    let m =
        Mat::new_rows_cols_with_data(h as i32, w as i32, v).map_err(|_| PatternFitError::OpenCv)?;
    m.try_clone().map_err(|_| PatternFitError::OpenCv)
}

pub(super) fn mat_values(m: &Mat) -> Result<Vec<f32>, PatternFitError> {
    if m.typ() != CV_32F || !m.is_continuous() {
        return Err(PatternFitError::OpenCv);
    }
    m.data_typed::<f32>()
        .map(|s| s.to_vec())
        .map_err(|_| PatternFitError::OpenCv)
}

/// The model's pattern bases at homography `h` over `win`: each region
/// (white, black, quiet zone) rendered sharp and through each Gaussian of
/// `sigmas` (index `region · kernels + kernel`, kernel 0 = sharp), then the
/// white print × x and × y through each kernel (a pair per kernel); with
/// each pixel's module point and the sharp renderings' image gradients.
pub(super) fn build_bases(
    grid: &[bool],
    m: usize,
    h: &Matrix3<f64>,
    win: &Window,
    sigmas: &[f64],
) -> Result<Bases, PatternFitError> {
    let kernels = 1 + sigmas.len();
    let kernel_sigma: Vec<f64> = std::iter::once(0.0).chain(sigmas.iter().copied()).collect();
    let n = win.w * win.h;
    let w = win.w;
    let hinv = h.try_inverse().ok_or(PatternFitError::Singular)?;

    // Sharp renderings of each region (pixel-area coverage), and their
    // gradients in the image.
    let mut sharp = vec![vec![0f32; n]; REGIONS];
    let mut grads = vec![vec![[0f32; 2]; n]; REGIONS];
    let mut uv = vec![[0f64; 2]; n];
    for y in 0..win.h {
        for x in 0..win.w {
            let [px, py] = win.pos[y * w + x];
            let p = hinv * Vector3::new(px, py, 1.0);
            if p.z.abs() < 1e-12 {
                return Err(PatternFitError::Singular);
            }
            let (u, v) = (p.x / p.z, p.y / p.z);
            let gu = [
                (hinv[(0, 0)] - u * hinv[(2, 0)]) / p.z,
                (hinv[(0, 1)] - u * hinv[(2, 1)]) / p.z,
            ];
            let gv = [
                (hinv[(1, 0)] - v * hinv[(2, 0)]) / p.z,
                (hinv[(1, 1)] - v * hinv[(2, 1)]) / p.z,
            ];
            let k = y * w + x;
            uv[k] = [u, v];
            // Most pixels lie wholly inside one module (a pixel's footprint
            // spans ½(|∂u/∂x| + |∂u/∂y|) modules either side): weight 1, no
            // gradient — what `axis_weights` gives there, without it.
            let (fu, fv) = (u - u.floor(), v - v.floor());
            let (tu, tv) = (
                0.5 * (gu[0].abs() + gu[1].abs()),
                0.5 * (gv[0].abs() + gv[1].abs()),
            );
            if fu >= tu && 1.0 - fu >= tu && fv >= tv && 1.0 - fv >= tv {
                if let Some(reg) = region(grid, m as i64, u.floor() as i64, v.floor() as i64) {
                    sharp[reg][k] = 1.0;
                }
                continue;
            }
            let (ci, wu, gwu) = axis_weights(u, gu);
            let (ri, wv, gwv) = axis_weights(v, gv);
            for dr in 0..3 {
                for dc in 0..3 {
                    let Some(reg) = region(grid, m as i64, ci + dc as i64 - 1, ri + dr as i64 - 1)
                    else {
                        continue;
                    };
                    sharp[reg][k] += (wv[dr] * wu[dc]) as f32;
                    let g = &mut grads[reg][k];
                    for ax in 0..2 {
                        g[ax] += (gwv[dr][ax] * wu[dc] + wv[dr] * gwu[dc][ax]) as f32;
                    }
                }
            }
        }
    }
    // Bases: each region through each kernel, then the white print (modules
    // and quiet zone) × x and × y through each kernel — the contrast changes
    // across a tilted marker with the range (transmission e^(−c·r)). For a
    // Gaussian G, G ∗ (x·S) = x·(G∗S) + σ²·∂x(G∗S): no more blurs.
    let (cx, cy, scale) = win.frame();
    let mut bases: Vec<Vec<f32>> = Vec::with_capacity(5 * kernels);
    for s in &sharp {
        let mat = mat_from(s, win.w, win.h)?;
        bases.push(s.clone());
        for &sigma in sigmas {
            bases.push(mat_values(&blur(&mat, sigma)?)?);
        }
    }
    for (k, &sigma) in kernel_sigma.iter().enumerate() {
        let white: Vec<f32> = bases[WHITE * kernels + k]
            .iter()
            .zip(&bases[QUIET * kernels + k])
            .map(|(a, b)| a + b)
            .collect();
        let s2 = (sigma * sigma / scale) as f32;
        let mut gx = vec![0f32; n];
        let mut gy = vec![0f32; n];
        for y in 1..win.h - 1 {
            for x in 1..w - 1 {
                let i = y * w + x;
                let xn = ((x as f64 - cx) / scale) as f32;
                let yn = ((y as f64 - cy) / scale) as f32;
                gx[i] = xn * white[i] + s2 * 0.5 * (white[i + 1] - white[i - 1]);
                gy[i] = yn * white[i] + s2 * 0.5 * (white[i + w] - white[i - w]);
            }
        }
        bases.push(gx);
        bases.push(gy);
    }
    Ok(Bases { bases, uv, grads })
}

/// What [`build_bases`] renders.
pub(super) struct Bases {
    pub bases: Vec<Vec<f32>>,
    /// Each pixel's module point.
    pub uv: Vec<[f64; 2]>,
    /// Per region, the sharp rendering's image gradient.
    pub grads: Vec<Vec<[f32; 2]>>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn coverage_density_is_the_derivative_of_coverage() {
        let d = std::f64::consts::FRAC_1_SQRT_2;
        for (a, b) in [(1.0, 0.0), (0.8, 0.6), (d, d), (0.95, 0.3122)] {
            for i in -90..=90 {
                let t = i as f64 * 0.01 + 0.003;
                let num = (coverage(t + 1e-6, a, b) - coverage(t - 1e-6, a, b)) / 2e-6;
                assert!(
                    (num - coverage_density(t, a, b)).abs() < 1e-4,
                    "{a} {b} {t}"
                );
            }
        }
    }

    #[test]
    fn coverage_is_the_pixel_area_below_a_line() {
        // Axis-aligned: linear ramp over one pixel.
        assert!((coverage(0.0, 1.0, 0.0) - 0.5).abs() < 1e-12);
        assert!((coverage(0.25, 1.0, 0.0) - 0.75).abs() < 1e-12);
        // Diagonal: a = b = √½; a quarter of the way from the corner.
        let s = 0.5f64.sqrt();
        let t = -s + 0.25 * s; // 0.25 of the half-diagonal from the corner
        let exact = 0.5 * (0.25 * s * 2.0f64.sqrt()).powi(2);
        assert!(
            (coverage(t, s, s) - exact).abs() < 1e-9,
            "{}",
            coverage(t, s, s)
        );
        // Monotone and symmetric for any orientation.
        for (a, b) in [(0.9, 0.3), (0.6, 0.55)] {
            let n: f64 = a * a + b * b;
            let (a, b) = (a / n.sqrt(), b / n.sqrt());
            let mut prev = 0.0;
            for i in -100..=100 {
                let t = i as f64 * 0.01;
                let c = coverage(t, a, b);
                assert!(c >= prev - 1e-12);
                assert!((c + coverage(-t, a, b) - 1.0).abs() < 1e-12);
                prev = c;
            }
        }
    }
}
