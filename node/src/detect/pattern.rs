//! The whole marker fitted at once to the camera's raw pixels: one
//! homography for all its module edges, seen through a forward-scatter
//! halo (`docs/detector.md`, "Fitting the whole pattern").
//!
//! Per side, a step-edge fit ([`super::edge_model`]) sees one edge and a
//! band around it. In turbid water the halo of the forward-scattered light
//! is wider than a module: the dark one-module bands of the enhanced marker
//! (its outer frame, the code border) are lit from both sides and a single
//! edge's profile is bent by its neighbours — at 8.22 /m the sharp part of
//! an edge is 2–4 grey levels, no side fit holds on the raw frame, and on
//! the restoration the corners were pulled 0.3–0.5 px into those bands.
//!
//! Here the model image is the whole printed pattern — its decoded
//! modules, the quiet zone ([`QUIET_MODULES`] wide), whatever lies beyond —
//! rendered with exact pixel-area coverage and seen through a point-spread
//! function that is the sharp (unscattered) part plus Gaussians of fixed
//! widths ([`HALO_SIGMAS_PX`]) with free weights, so the halo may have any
//! radial shape. Each region (white modules, black modules, quiet zone)
//! has its own weight per kernel, the white print's weights change linearly
//! across the marker (a tilted marker's far side is dimmer by e^(−c·Δr):
//! ±10–20 % at 8.22 /m and 30° — without this the corners moved 0.5 px),
//! and a quadratic veil is added. The geometry is the image positions of the
//! four outer corners; every pixel of the marker and of the first
//! [`FIT_REACH_MODULES`] around it is fitted by Gauss–Newton on all
//! parameters at once, with the exact derivatives (each kernel applied to
//! the sharp rendering's analytic image gradient times the corners'
//! displacement field) and backtracking.

use super::geom::{apply, homography_4, Px};
use crate::mat::GrayView;
use nalgebra::{DMatrix, DVector, Matrix3, SMatrix, Vector3};
use opencv::core::{Mat, Size, BORDER_REPLICATE, CV_32F};
use opencv::prelude::*;
use shoal_proto::camera::CameraModel;

/// Widths (px) of the halo's Gaussians; their weights are fitted.
pub const HALO_SIGMAS_PX: [f64; 4] = [1.2, 3.0, 7.5, 18.0];
/// Width of the printed quiet zone around the black frame, in modules.
pub const QUIET_MODULES: f64 = 1.0;
/// How far outside the black frame pixels are fitted, in modules.
const FIT_REACH_MODULES: f64 = 0.6;
const MAX_ITERATIONS: usize = 10;
/// Converged when no outer corner moves more than this (px).
const STEP_TOL_PX: f64 = 1e-2;
/// … or when a step lowers the residual rms by less than this fraction.
const RMS_TOL: f64 = 2e-5;
/// A fit whose corners end farther than this (modules) from where they
/// started is rejected: it slid to another edge.
const MAX_SHIFT_MODULES: f64 = 0.35;

/// Region kinds of the printed pattern.
const WHITE: usize = 0;
const BLACK: usize = 1;
const QUIET: usize = 2;
const REGIONS: usize = 3;
/// 1, x, y, x², xy, y².
const POLY: usize = 6;
const GEOM: usize = 8;

/// The fitted pattern.
#[derive(Debug, Clone)]
pub struct PatternFit {
    /// Module coordinates (column, row from the frame's top-left outer
    /// corner, in the marker's upright orientation) → ideal pixels.
    pub homography: Matrix3<f64>,
    pub lens: Lens,
    /// Covariance (px²) of the four outer corners `x0, y0, … x3, y3`
    /// (ideal pixels).
    pub covariance: SMatrix<f64, 8, 8>,
    /// Residual standard deviation (grey levels).
    pub rms: f64,
    pub iterations: usize,
    pub pixels: usize,
}

impl PatternFit {
    /// The pixel at module coordinates `p`.
    pub fn project(&self, p: Px) -> Px {
        self.lens.pixel(apply(&self.homography, p))
    }
}

/// Why a pattern fit was not made.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PatternFitError {
    /// The marker with its quiet zone is not wholly inside the frame.
    Clipped,
    /// Degenerate geometry or normal equations.
    Singular,
    /// No convergence, or corners slid more than [`MAX_SHIFT_MODULES`].
    Diverged,
    /// The fitted pattern is not brighter on white modules than on black.
    NoContrast,
    OpenCv,
}

impl std::fmt::Display for PatternFitError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            PatternFitError::Clipped => "marker or quiet zone outside the frame",
            PatternFitError::Singular => "degenerate geometry or normal equations",
            PatternFitError::Diverged => "no convergence near the starting corners",
            PatternFitError::NoContrast => "white modules not brighter than black",
            PatternFitError::OpenCv => "OpenCV blur failed",
        })
    }
}

impl std::error::Error for PatternFitError {}

/// Module coordinates of the outer corners of an `m`-module marker.
fn unit_corners(m: f64) -> [Px; 4] {
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
    let g = grad[0].hypot(grad[1]).max(1e-12);
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

/// Pixel coordinates ↔ ideal (distortion-free) pixel coordinates, in
/// which a planar marker is exactly a homography: across a marker ~200 px
/// wide the vehicles' mild barrel distortion bends its pattern by
/// ~0.03 px, enough to bias a fit of all its pixels (0.128 → 0.059 mm median
/// distance error at 5.16 /m).
#[derive(Debug, Clone, Copy)]
pub struct Lens(pub Option<CameraModel>);

impl Lens {
    fn ideal(&self, p: Px) -> Px {
        match &self.0 {
            None => p,
            Some(c) => {
                let (x, y) = c.ray(p[0], p[1]);
                [c.fx * x + c.cx, c.fy * y + c.cy]
            }
        }
    }

    fn pixel(&self, p: Px) -> Px {
        match &self.0 {
            None => p,
            Some(c) => {
                let (x, y) = c.distort((p[0] - c.cx) / c.fx, (p[1] - c.cy) / c.fy);
                [c.fx * x + c.cx, c.fy * y + c.cy]
            }
        }
    }
}

/// The rendering window: image pixels `x0..x0+w`, `y0..y0+h`, and each
/// pixel's ideal position (where the model is rendered).
struct Window {
    x0: usize,
    y0: usize,
    w: usize,
    h: usize,
    pos: Vec<Px>,
}

impl Window {
    /// Centre and half-size (px): the veil's and gain gradients' coordinates.
    fn frame(&self) -> (f64, f64, f64) {
        (
            0.5 * self.w as f64,
            0.5 * self.h as f64,
            0.5 * self.w.max(self.h) as f64,
        )
    }
}

/// The Gaussian of `sigma` px, applied at 1/2 or 1/4 resolution when it
/// is wide (area-averaged down, bilinear up, both centre-aligned; the
/// window's sides are multiples of 4): the same linear operator for the
/// bases and their derivatives, a fraction of the cost.
fn blur(src: &Mat, sigma: f64) -> Result<Mat, PatternFitError> {
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

fn mat_from(v: &[f32], w: usize, h: usize) -> Result<Mat, PatternFitError> {
    let m =
        Mat::new_rows_cols_with_data(h as i32, w as i32, v).map_err(|_| PatternFitError::OpenCv)?;
    m.try_clone().map_err(|_| PatternFitError::OpenCv)
}

fn mat_values(m: &Mat) -> Result<Vec<f32>, PatternFitError> {
    if m.typ() != CV_32F || !m.is_continuous() {
        return Err(PatternFitError::OpenCv);
    }
    m.data_typed::<f32>()
        .map(|s| s.to_vec())
        .map_err(|_| PatternFitError::OpenCv)
}

/// Fit the marker whose `m`x`m` module grid is `grid` (row-major, `true` =
/// white) to `raw`, starting from `outer`, the image positions of module
/// coordinates (0, 0), (m, 0), (m, m), (0, m).
pub fn fit_pattern(
    raw: &GrayView<'_>,
    grid: &[bool],
    m: usize,
    outer: &[Px; 4],
    lens: Lens,
) -> Result<PatternFit, PatternFitError> {
    if grid.len() != m * m || m == 0 {
        return Err(PatternFitError::Singular);
    }
    let unit = unit_corners(m as f64);
    let start = outer.map(|p| lens.ideal(p));
    let mut corners = start;
    let module_px = (0..4)
        .map(|i| {
            let (a, b) = (corners[i], corners[(i + 1) % 4]);
            (a[0] - b[0]).hypot(a[1] - b[1])
        })
        .sum::<f64>()
        / (4.0 * m as f64);
    // One window and one set of fitted pixels for all steps (residuals comparable).
    let (win, fitted) = window(
        raw,
        &homography_4(&unit, &corners).ok_or(PatternFitError::Singular)?,
        m,
        &lens,
    )?;
    let idx: Vec<usize> = (0..win.w * win.h).filter(|&k| fitted[k]).collect();
    // Gauss–Newton with backtracking: a step that raises the residual is
    // halved from the last accepted point.
    let mut accepted: Option<([Px; 4], Step)> = None;
    let mut coef: Option<DVector<f64>> = None;
    let mut fraction = 1.0;
    for it in 0..MAX_ITERATIONS {
        let h = homography_4(&unit, &corners).ok_or(PatternFitError::Singular)?;
        let step = evaluate(raw, grid, m, &unit, &corners, &h, &win, &idx, coef.as_ref())?;
        if let Some((at, best)) = &accepted {
            if step.rms > best.rms {
                fraction *= 0.5;
                if fraction < 0.1 {
                    return best.fit(&unit, at, it + 1, lens);
                }
                for i in 0..4 {
                    corners[i][0] = at[i][0] + fraction * best.delta[2 * i];
                    corners[i][1] = at[i][1] + fraction * best.delta[2 * i + 1];
                }
                coef = Some(best.coef_here.clone());
                continue;
            }
        }
        fraction = 1.0;
        let moved = (0..4)
            .map(|i| step.delta[2 * i].hypot(step.delta[2 * i + 1]))
            .fold(0.0, f64::max);
        if !moved.is_finite() {
            return Err(PatternFitError::Diverged);
        }
        // Converged: the step is negligible, or the residual no longer
        // falls (the step then wanders along the noise floor).
        let settled = accepted
            .as_ref()
            .is_some_and(|(_, best)| best.rms - step.rms < RMS_TOL * step.rms);
        if moved < STEP_TOL_PX || settled {
            return step.fit(&unit, &corners, it + 1, lens);
        }
        coef = Some(step.coef_next.clone());
        let at = corners;
        for i in 0..4 {
            corners[i][0] += step.delta[2 * i];
            corners[i][1] += step.delta[2 * i + 1];
        }
        accepted = Some((at, step));
        let shifted = (0..4)
            .map(|i| (corners[i][0] - start[i][0]).hypot(corners[i][1] - start[i][1]))
            .fold(0.0, f64::max);
        if shifted > MAX_SHIFT_MODULES * module_px {
            return Err(PatternFitError::Diverged);
        }
    }
    // Not converged to the tolerance: the best point reached.
    let (at, best) = accepted.ok_or(PatternFitError::Diverged)?;
    best.fit(&unit, &at, MAX_ITERATIONS, lens)
}

/// The model evaluated at one geometry.
struct Step {
    /// Residual rms with the linear weights fitted at this geometry.
    rms: f64,
    /// Gauss–Newton update of the corners.
    delta: [f64; GEOM],
    /// Linear weights fitted at this geometry, and predicted after `delta`.
    coef_here: DVector<f64>,
    coef_next: DVector<f64>,
    covariance: SMatrix<f64, 8, 8>,
    pixels: usize,
}

impl Step {
    fn fit(
        &self,
        unit: &[Px; 4],
        corners: &[Px; 4],
        iterations: usize,
        lens: Lens,
    ) -> Result<PatternFit, PatternFitError> {
        Ok(PatternFit {
            homography: homography_4(unit, corners).ok_or(PatternFitError::Singular)?,
            lens,
            covariance: self.covariance,
            rms: self.rms,
            iterations,
            pixels: self.pixels,
        })
    }
}

/// The rendering window for the pattern at `h` — its quiet zone's footprint
/// with room for the corners to move [`MAX_SHIFT_MODULES`] and two pixels
/// (zero beyond, so the blur's replicated border is exact) — and the
/// pixels fitted: the marker and [`FIT_REACH_MODULES`] around it.
fn window(
    raw: &GrayView<'_>,
    h: &Matrix3<f64>,
    m: usize,
    lens: &Lens,
) -> Result<(Window, Vec<bool>), PatternFitError> {
    let mf = m as f64;
    let q = QUIET_MODULES + MAX_SHIFT_MODULES;
    let reach =
        [[-q, -q], [mf + q, -q], [mf + q, mf + q], [-q, mf + q]].map(|p| lens.pixel(apply(h, p)));
    let (mut xmin, mut ymin, mut xmax, mut ymax) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for p in reach {
        xmin = xmin.min(p[0]);
        ymin = ymin.min(p[1]);
        xmax = xmax.max(p[0]);
        ymax = ymax.max(p[1]);
    }
    let (xmin, ymin) = (xmin.floor() - 2.0, ymin.floor() - 2.0);
    // Sides a multiple of 4 (the wide blurs run at 1/4 resolution).
    let side = |lo: f64, hi: f64| ((hi.ceil() + 2.0 - lo) / 4.0).ceil() * 4.0;
    let (xmax, ymax) = (xmin + side(xmin, xmax) - 1.0, ymin + side(ymin, ymax) - 1.0);
    if !(xmin >= 0.0 && ymin >= 0.0 && xmax < raw.width as f64 && ymax < raw.height as f64) {
        return Err(PatternFitError::Clipped);
    }
    let (x0, y0) = (xmin as usize, ymin as usize);
    let (w, hgt) = ((xmax - xmin) as usize + 1, (ymax - ymin) as usize + 1);
    let pos: Vec<Px> = (0..w * hgt)
        .map(|k| lens.ideal([(x0 + k % w) as f64, (y0 + k / w) as f64]))
        .collect();
    let win = Window {
        x0,
        y0,
        w,
        h: hgt,
        pos,
    };
    let hinv = h.try_inverse().ok_or(PatternFitError::Singular)?;
    let (lo, hi) = (-FIT_REACH_MODULES, mf + FIT_REACH_MODULES);
    let fitted = win
        .pos
        .iter()
        .map(|p| {
            let p = hinv * Vector3::new(p[0], p[1], 1.0);
            let (u, v) = (p.x / p.z, p.y / p.z);
            p.z.abs() > 1e-12 && u > lo && u < hi && v > lo && v < hi
        })
        .collect();
    Ok((win, fitted))
}

/// Normal equations over rows of `cols` values: the upper triangle of
/// `AᵀA` (row-major, full width) and `Aᵀr`.
struct Normal {
    cols: usize,
    ata: Vec<f64>,
    atr: Vec<f64>,
}

impl Normal {
    fn new(cols: usize) -> Normal {
        Normal {
            cols,
            ata: vec![0.0; cols * cols],
            atr: vec![0.0; cols],
        }
    }

    #[inline]
    fn add(&mut self, row: &[f64], r: f64) {
        let n = self.cols;
        for i in 0..n {
            let ri = row[i];
            self.atr[i] += ri * r;
            let dst = &mut self.ata[i * n + i..(i + 1) * n];
            for (d, &rj) in dst.iter_mut().zip(&row[i..]) {
                *d += ri * rj;
            }
        }
    }

    /// `(AᵀA, Aᵀr)`.
    fn finish(self) -> (DMatrix<f64>, DVector<f64>) {
        let n = self.cols;
        let ata = DMatrix::from_fn(n, n, |i, j| {
            let (i, j) = if i <= j { (i, j) } else { (j, i) };
            self.ata[i * n + j]
        });
        (ata, DVector::from_vec(self.atr))
    }
}

/// The model's pattern bases at homography `h` over `win`: each region
/// (white, black, quiet zone) rendered sharp and through each Gaussian of
/// `sigmas` (index `region · kernels + kernel`, kernel 0 = sharp), then the
/// white print × x and × y through each kernel (a pair per kernel); with
/// each pixel's module point and the sharp renderings' image gradients.
fn build_bases(
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
struct Bases {
    bases: Vec<Vec<f32>>,
    /// Each pixel's module point.
    uv: Vec<[f64; 2]>,
    /// Per region, the sharp rendering's image gradient.
    grads: Vec<Vec<[f32; 2]>>,
}

/// The model at `corners` (homography `h`): residual, linear weights and
/// the Gauss–Newton step. `coef` (the weights predicted from the previous
/// step) sets the geometric derivatives; without it they are fitted first.
#[allow(clippy::too_many_arguments)]
fn evaluate(
    raw: &GrayView<'_>,
    grid: &[bool],
    m: usize,
    unit: &[Px; 4],
    corners: &[Px; 4],
    h: &Matrix3<f64>,
    win: &Window,
    idx: &[usize],
    coef: Option<&DVector<f64>>,
) -> Result<Step, PatternFitError> {
    let sigmas = HALO_SIGMAS_PX;
    let kernels = 1 + sigmas.len();
    let kernel_sigma: Vec<f64> = std::iter::once(0.0).chain(sigmas.iter().copied()).collect();
    let n = win.w * win.h;
    let w = win.w;
    let (cx, cy, scale) = win.frame();
    let Bases { bases, uv, grads } = build_bases(grid, m, h, win, &sigmas)?;
    let pattern_bases = bases.len();
    let linear = pattern_bases + POLY;
    let poly = |k: usize| -> [f64; POLY] {
        let x = ((k % w) as f64 - cx) / scale;
        let y = ((k / w) as f64 - cy) / scale;
        [1.0, x, y, x * x, x * y, y * y]
    };
    let obs = |k: usize| -> f64 {
        let (x, y) = (win.x0 + k % w, win.y0 + k / w);
        raw.data[y * raw.stride + x] as f64
    };
    let lin_row = |k: usize, r: &mut [f64]| {
        for (j, b) in bases.iter().enumerate() {
            r[j] = b[k] as f64;
        }
        r[pattern_bases..].copy_from_slice(&poly(k));
    };

    // Linear weights to start from.
    let coef = match coef {
        Some(c) if c.len() == linear => c.clone(),
        _ => {
            let mut ne = Normal::new(linear);
            let mut r = vec![0.0; linear];
            for &k in idx {
                lin_row(k, &mut r);
                ne.add(&r, obs(k));
            }
            let (a, b) = ne.finish();
            solve_ridge(&a, &b).ok_or(PatternFitError::Singular)?
        }
    };
    // White must read brighter than black through the whole PSF.
    let gain = |reg: usize| (0..kernels).map(|k| coef[reg * kernels + k]).sum::<f64>();
    if gain(WHITE) <= gain(BLACK) {
        return Err(PatternFitError::NoContrast);
    }
    // ∂x/∂(corner coordinate) at each pixel's module point: the
    // displacement fields D_j, numerically.
    let eps = 1e-3;
    let hj: Vec<Matrix3<f64>> = (0..GEOM)
        .map(|j| {
            let mut c = *corners;
            c[j / 2][j % 2] += eps;
            homography_4(unit, &c).ok_or(PatternFitError::Singular)
        })
        .collect::<Result<_, _>>()?;
    let disp: Vec<Vec<[f64; 2]>> = hj
        .iter()
        .map(|hj| {
            uv.iter()
                .map(|&p| {
                    let (a, b) = (apply(hj, p), apply(h, p));
                    [(a[0] - b[0]) / eps, (a[1] - b[1]) / eps]
                })
                .collect()
        })
        .collect();
    // The model moves with the sharp pattern: a sharp rendering S changes
    // by −∇S·D_j, and each basis is a kernel over (gain ×) S, so
    // ∂M/∂p_j = −Σ_kernels G ∗ (E·D_j), E the kernel's weighted sum of the
    // regions' analytic ∇S (the gain gradients stay with the image). D_j
    // is smooth (a homography's derivative), and for a Gaussian
    // G ∗ (E_a·D_a) = D_a·(G∗E_a) + σ² Σ_b ∂_b D_a · ∂_b(G∗E_a) to second
    // order: two blurs per kernel, not one per corner coordinate.
    // `along` = Σ_kernels G∗E; `spread[a][b]` = Σ_kernels σ²·∂_b(G∗E_a).
    let first_gradient_basis = REGIONS * kernels;
    let mut along = vec![[0f64; 2]; n];
    let mut spread = vec![[[0f64; 2]; 2]; n];
    let mut field = [vec![0f32; n], vec![0f32; n]];
    for (k, &sigma) in kernel_sigma.iter().enumerate() {
        let (cgx, cgy) = (
            coef[first_gradient_basis + 2 * k],
            coef[first_gradient_basis + 2 * k + 1],
        );
        for i in 0..n {
            let xn = ((i % w) as f64 - cx) / scale;
            let yn = ((i / w) as f64 - cy) / scale;
            let gain_white = cgx * xn + cgy * yn;
            let mut acc = [0.0; 2];
            for (reg, g) in grads.iter().enumerate() {
                let mut c = coef[reg * kernels + k];
                if reg != BLACK {
                    c += gain_white;
                }
                acc[0] += c * g[i][0] as f64;
                acc[1] += c * g[i][1] as f64;
            }
            field[0][i] = acc[0] as f32;
            field[1][i] = acc[1] as f32;
        }
        let blurred: [Vec<f32>; 2] = if sigma > 0.0 {
            [
                mat_values(&blur(&mat_from(&field[0], w, win.h)?, sigma)?)?,
                mat_values(&blur(&mat_from(&field[1], w, win.h)?, sigma)?)?,
            ]
        } else {
            field.clone()
        };
        let s2 = sigma * sigma;
        for &i in idx {
            let (x, y) = (i % w, i / w);
            if x == 0 || y == 0 || x + 1 == w || y + 1 == win.h {
                continue;
            }
            for a in 0..2 {
                let g = &blurred[a];
                along[i][a] += g[i] as f64;
                if s2 > 0.0 {
                    spread[i][a][0] += s2 * 0.5 * (g[i + 1] - g[i - 1]) as f64;
                    spread[i][a][1] += s2 * 0.5 * (g[i + w] - g[i - w]) as f64;
                }
            }
        }
    }

    let all = GEOM + linear;
    let mut ne = Normal::new(all);
    let mut row = vec![0.0f64; all];
    let mut sse = 0.0;
    for &k in idx {
        let (x, y) = (k % w, k / w);
        if x == 0 || y == 0 || x + 1 == w || y + 1 == win.h {
            continue;
        }
        for (j, d) in disp.iter().enumerate() {
            let mut v = d[k][0] * along[k][0] + d[k][1] * along[k][1];
            for a in 0..2 {
                let dbx = 0.5 * (d[k + 1][a] - d[k - 1][a]);
                let dby = 0.5 * (d[k + w][a] - d[k - w][a]);
                v += dbx * spread[k][a][0] + dby * spread[k][a][1];
            }
            row[j] = -v;
        }
        lin_row(k, &mut row[GEOM..]);
        let model: f64 = row[GEOM..]
            .iter()
            .zip(coef.iter())
            .map(|(a, b)| a * b)
            .sum();
        let res = obs(k) - model;
        sse += res * res;
        ne.add(&row, res);
    }
    let (a, atr) = ne.finish();
    // The weights re-fitted at this geometry: the linear block alone.
    let lin_a = a.view((GEOM, GEOM), (linear, linear)).into_owned();
    let lin_b = atr.rows(GEOM, linear).into_owned();
    let dc = solve_ridge(&lin_a, &lin_b).ok_or(PatternFitError::Singular)?;
    let sse_here = (sse - lin_b.dot(&dc)).max(0.0);
    let dof = idx.len().saturating_sub(all).max(1) as f64;
    let sigma2 = sse_here / dof;
    let inv = ridge_inverse(&a).ok_or(PatternFitError::Singular)?;
    let delta_all = &inv * &atr;
    let mut delta = [0.0; GEOM];
    delta.copy_from_slice(&delta_all.as_slice()[..GEOM]);
    let mut covariance = SMatrix::<f64, 8, 8>::zeros();
    for i in 0..GEOM {
        for j in 0..GEOM {
            covariance[(i, j)] = sigma2 * inv[(i, j)];
        }
    }
    Ok(Step {
        rms: sigma2.sqrt(),
        delta,
        coef_here: &coef + dc,
        coef_next: &coef + delta_all.rows(GEOM, linear),
        covariance,
        pixels: idx.len(),
    })
}

/// The homography taking `src` to `dst` in the least-squares sense
/// (normalized DLT, ≥ 4 correspondences).
pub fn homography_ls(src: &[Px], dst: &[Px]) -> Option<Matrix3<f64>> {
    let n = src.len();
    if n < 4 || dst.len() != n {
        return None;
    }
    let normalizer = |pts: &[Px]| -> Option<Matrix3<f64>> {
        let (mx, my) = pts.iter().fold((0.0, 0.0), |a, p| (a.0 + p[0], a.1 + p[1]));
        let (mx, my) = (mx / n as f64, my / n as f64);
        let d = pts
            .iter()
            .map(|p| (p[0] - mx).hypot(p[1] - my))
            .sum::<f64>()
            / n as f64;
        (d > 1e-12).then(|| {
            let s = std::f64::consts::SQRT_2 / d;
            Matrix3::new(s, 0.0, -s * mx, 0.0, s, -s * my, 0.0, 0.0, 1.0)
        })
    };
    let (ts, td) = (normalizer(src)?, normalizer(dst)?);
    let mut a = DMatrix::<f64>::zeros(2 * n, 9);
    for i in 0..n {
        let [x, y] = apply(&ts, src[i]);
        let [u, v] = apply(&td, dst[i]);
        let r = 2 * i;
        for (j, val) in [x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y, -u]
            .iter()
            .enumerate()
        {
            a[(r, j)] = *val;
        }
        for (j, val) in [0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y, -v]
            .iter()
            .enumerate()
        {
            a[(r + 1, j)] = *val;
        }
    }
    let ata = a.transpose() * &a;
    let eig = ata.symmetric_eigen();
    let (k, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    let h = eig.eigenvectors.column(k);
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
    let hm = td.try_inverse()? * hn * ts;
    (hm[(2, 2)].abs() > 1e-15).then(|| hm / hm[(2, 2)])
}

/// Ridge relative to each column's scale (the system scaled to a unit
/// diagonal): the regions' bases under the narrow kernels sum to the
/// constant where fitted (the plate is uniform beyond the quiet zone's
/// first 0.6 module), and wide kernels come near the veil's polynomial;
/// the null directions get no weight instead of any.
const RIDGE: f64 = 1e-8;

/// `(AᵀA + ridge)⁻¹` in the caller's scaling.
fn ridge_inverse(ata: &DMatrix<f64>) -> Option<DMatrix<f64>> {
    let n = ata.nrows();
    let d: Vec<f64> = (0..n)
        .map(|i| {
            let v = ata[(i, i)];
            if v > 0.0 {
                1.0 / v.sqrt()
            } else {
                1.0
            }
        })
        .collect();
    let mut a = DMatrix::from_fn(n, n, |i, j| ata[(i, j)] * d[i] * d[j]);
    for i in 0..n {
        a[(i, i)] += RIDGE;
    }
    let inv = a.cholesky()?.inverse();
    Some(DMatrix::from_fn(n, n, |i, j| inv[(i, j)] * d[i] * d[j]))
}

fn solve_ridge(ata: &DMatrix<f64>, atb: &DVector<f64>) -> Option<DVector<f64>> {
    Some(ridge_inverse(ata)? * atb)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A frame drawn from the model itself: `grid` at `truth` (outer
    /// corners) through the sharp part and each halo kernel, the white
    /// print 15 % brighter on the right, a veil, Gaussian noise σ 2 DN.
    fn synthetic(grid: &[bool], truth: &[Px; 4], seed: u64) -> (Vec<u8>, usize, usize) {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal as Gauss};
        let (w, hgt) = (420usize, 380usize); // multiples of 4, as `window` makes them
        let pos = (0..w * hgt)
            .map(|k| [(k % w) as f64, (k / w) as f64])
            .collect();
        let win = Window {
            x0: 0,
            y0: 0,
            w,
            h: hgt,
            pos,
        };
        let h = homography_4(&unit_corners(10.0), truth).unwrap();
        let b = build_bases(grid, 10, &h, &win, &HALO_SIGMAS_PX).unwrap();
        let kernels = 1 + HALO_SIGMAS_PX.len();
        // Sharp 6 DN, then the halo 10, 14, 10, 6 DN: white print; black 10 %.
        let weights = [6.0, 10.0, 14.0, 10.0, 6.0];
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let noise = Gauss::new(0.0, 2.0).unwrap();
        let (cx, _, scale) = win.frame();
        let mut img = vec![0u8; w * hgt];
        for (i, px) in img.iter_mut().enumerate() {
            let xn = ((i % w) as f64 - cx) / scale;
            let mut v = 90.0 + 3.0 * xn;
            for (k, wk) in weights.iter().enumerate() {
                let white =
                    (b.bases[WHITE * kernels + k][i] + b.bases[QUIET * kernels + k][i]) as f64;
                v += wk * (1.0 + 0.15 * xn) * white
                    + 0.1 * wk * b.bases[BLACK * kernels + k][i] as f64;
            }
            *px = (v + noise.sample(&mut rng)).round().clamp(0.0, 255.0) as u8;
        }
        (img, w, hgt)
    }

    #[test]
    fn the_pattern_fit_recovers_a_marker_drawn_from_its_model() {
        let grid = shoal_proto::marker::CodeSet::Shoal.module_grid(17).unwrap();
        // A perspective view: right side nearer, ~20 px modules.
        let truth = [[112.3, 95.6], [318.9, 80.2], [324.4, 301.7], [106.1, 287.5]];
        let start = [[112.9, 95.1], [318.2, 80.8], [325.0, 301.2], [105.6, 288.1]];
        let (mut worst, mut worst_start) = (0.0f64, 0.0f64);
        for seed in 0..3 {
            let (img, w, h) = synthetic(&grid, &truth, seed);
            let view = GrayView {
                data: &img,
                width: w,
                height: h,
                stride: w,
            };
            let fit = fit_pattern(&view, &grid, 10, &start, Lens(None)).expect("fit");
            for (i, t) in truth.iter().enumerate() {
                let p = fit.project(unit_corners(10.0)[i]);
                worst = worst.max((p[0] - t[0]).hypot(p[1] - t[1]));
                worst_start = worst_start.max((start[i][0] - t[0]).hypot(start[i][1] - t[1]));
            }
            // The covariance is of the right size for the error: σ ≤ 0.1 px.
            assert!((0..8).all(|j| fit.covariance[(j, j)] > 0.0 && fit.covariance[(j, j)] < 0.01));
            assert!((fit.rms - 2.0).abs() < 0.2, "rms {} for σ 2 noise", fit.rms);
        }
        eprintln!("worst outer corner error {worst:.3} px (start {worst_start:.3})");
        assert!(worst < 0.08, "worst corner {worst:.3} px");
    }

    #[test]
    fn a_clipped_or_unreadable_pattern_is_refused() {
        let grid = shoal_proto::marker::CodeSet::Shoal.module_grid(17).unwrap();
        let truth = [[112.3, 95.6], [318.9, 80.2], [324.4, 301.7], [106.1, 287.5]];
        let (img, w, h) = synthetic(&grid, &truth, 7);
        let view = GrayView {
            data: &img,
            width: w,
            height: h,
            stride: w,
        };
        let shifted = truth.map(|p| [p[0] - 100.0, p[1]]);
        assert_eq!(
            fit_pattern(&view, &grid, 10, &shifted, Lens(None)).unwrap_err(),
            PatternFitError::Clipped
        );
        // A flat grey frame has no marker to fit.
        let flat = vec![90u8; w * h];
        let view = GrayView {
            data: &flat,
            width: w,
            height: h,
            stride: w,
        };
        assert!(fit_pattern(&view, &grid, 10, &truth, Lens(None)).is_err());
        assert!(fit_pattern(&view, &grid[..50], 10, &truth, Lens(None)).is_err());
    }

    #[test]
    fn the_lens_maps_pixels_to_ideal_pixels_and_back() {
        let cam = CameraModel::vehicle_1440();
        let lens = Lens(Some(cam));
        for p in [[100.0, 80.0], [719.5, 539.5], [1300.0, 1000.0]] {
            let q = lens.pixel(lens.ideal(p));
            assert!((q[0] - p[0]).hypot(q[1] - p[1]) < 1e-9);
        }
        // Barrel distortion: an off-centre pixel's ideal position is farther out.
        let q = lens.ideal([100.0, 80.0]);
        assert!(q[0] < 100.0 && q[1] < 80.0);
        assert_eq!(Lens(None).ideal([3.0, 4.0]), [3.0, 4.0]);
    }

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
    fn least_squares_homography_maps_twelve_points() {
        let truth = Matrix3::new(20.0, 3.0, 400.0, -2.0, 18.0, 300.0, 1e-3, -2e-3, 1.0);
        let src: Vec<Px> = (0..12)
            .map(|i| [(i % 4) as f64 * 3.0, (i / 4) as f64 * 4.0 + 0.5])
            .collect();
        let dst: Vec<Px> = src.iter().map(|&p| apply(&truth, p)).collect();
        let h = homography_ls(&src, &dst).unwrap();
        for (s, d) in src.iter().zip(&dst) {
            let p = apply(&h, *s);
            assert!((p[0] - d[0]).hypot(p[1] - d[1]) < 1e-6);
        }
        assert!(homography_ls(&src[..3], &dst[..3]).is_none());
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
