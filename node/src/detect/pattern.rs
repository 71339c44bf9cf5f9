//! The whole marker fitted at once to the camera's raw pixels: one
//! homography for all its module edges, seen through a forward-scatter
//! halo (`docs/detector.md`, "Fitting the whole pattern").
//!
//! Per side, a step-edge fit ([`super::edge_model`]) sees one edge and a
//! band around it. In turbid water the halo of the forward-scattered light
//! is wider than a module: the dark one-module bands of the enhanced marker
//! (its outer frame, the code border) are lit from both sides and a single
//! edge's profile is bent by its neighbours, so its line is pulled into the
//! dark band; where the sharp part of an edge sinks into the noise no side
//! fit holds on the raw frame at all.
//!
//! Here the model image is the whole printed pattern — its decoded
//! modules, the quiet zone ([`QUIET_MODULES`] wide), whatever lies beyond —
//! rendered with exact pixel-area coverage and seen through a point-spread
//! function that is the sharp (unscattered) part plus Gaussians of fixed
//! widths ([`HALO_SIGMAS_PX`]) with free weights, so the halo may have any
//! radial shape. Each region (white modules, black modules, quiet zone)
//! has its own weight per kernel, the white print's weights change linearly
//! across the marker (a tilted marker's far side is dimmer by e^(−c·Δr)),
//! and a quadratic veil is added. The geometry is the image positions of the
//! four outer corners; every pixel of the marker and of the first
//! `FIT_REACH_MODULES` around it is fitted by Gauss–Newton on all
//! parameters at once, with the exact derivatives (each kernel applied to
//! the sharp rendering's analytic image gradient times the corners'
//! displacement field) and backtracking.
//!
//! - `pattern.rs`: the fit's loop ([`fit_pattern`]), its result and errors,
//!   the lens model and the window of fitted pixels;
//! - `pattern/model.rs`: the rendering — coverage, regions, the blurred bases;
//! - `pattern/derivatives.rs`: the model's derivatives in the corners;
//! - `pattern/solver.rs`: one Gauss–Newton step from the normal equations.

mod derivatives;
mod model;
mod solver;

use super::geom::{apply, homography_4, Px};
use crate::mat::GrayView;
use model::unit_corners;
use nalgebra::{DMatrix, DVector, Matrix3, SMatrix, Vector3};
use shoal_proto::camera::CameraModel;
use solver::{evaluate, Step};

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
/// Spacing (px) of the exactly undistorted grid of [`Lens::ideal_grid`].
const IDEAL_GRID_PX: usize = 8;
/// The geometric parameters: the four outer corners' coordinates.
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

    /// The covariance (px², `2n`x`2n`: x then y of each point) of
    /// [`PatternFit::project`] at the module coordinates `pts` of an
    /// `m`x`m` pattern, to first order from [`PatternFit::covariance`]: every
    /// point is a function of the same four outer corners, so the points'
    /// errors are correlated (the fit moves them together). `None` when the
    /// homography is degenerate.
    pub fn points_covariance(&self, m: usize, pts: &[Px]) -> Option<DMatrix<f64>> {
        let unit = unit_corners(m as f64);
        let outer = unit.map(|u| apply(&self.homography, u));
        // Steps of 1e-4 px: the map is smooth, and far above rounding.
        const STEP_PX: f64 = 1e-4;
        let mut g = DMatrix::zeros(2 * pts.len(), GEOM);
        for c in 0..GEOM {
            let moved = |d: f64| {
                let mut q = outer;
                q[c / 2][c % 2] += d;
                homography_4(&unit, &q)
            };
            let (plus, minus) = (moved(STEP_PX)?, moved(-STEP_PX)?);
            for (k, &p) in pts.iter().enumerate() {
                let (a, b) = (
                    self.lens.pixel(apply(&plus, p)),
                    self.lens.pixel(apply(&minus, p)),
                );
                g[(2 * k, c)] = (a[0] - b[0]) / (2.0 * STEP_PX);
                g[(2 * k + 1, c)] = (a[1] - b[1]) / (2.0 * STEP_PX);
            }
        }
        let s = DMatrix::from_iterator(GEOM, GEOM, self.covariance.iter().copied());
        let cov = &g * s * g.transpose();
        cov.iter().all(|v| v.is_finite()).then_some(cov)
    }
}

/// Why a pattern fit was not made.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum PatternFitError {
    /// The marker with its quiet zone is not wholly inside the frame.
    Clipped,
    /// Degenerate geometry or normal equations.
    Singular,
    /// No convergence, or corners slid more than `MAX_SHIFT_MODULES`.
    Diverged,
    /// The fitted pattern is not brighter on white modules than on black.
    NoContrast,
    /// The code set has no module grid for the marker's ID.
    UnknownCode,
    #[serde(rename = "opencv")]
    OpenCv,
}

impl std::fmt::Display for PatternFitError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            PatternFitError::Clipped => "marker or quiet zone outside the frame",
            PatternFitError::Singular => "degenerate geometry or normal equations",
            PatternFitError::Diverged => "no convergence near the starting corners",
            PatternFitError::NoContrast => "white modules not brighter than black",
            PatternFitError::UnknownCode => "no module grid for the marker's ID",
            PatternFitError::OpenCv => "OpenCV blur failed",
        })
    }
}

impl std::error::Error for PatternFitError {}

/// Pixel coordinates ↔ ideal (distortion-free) pixel coordinates, in
/// which a planar marker is exactly a homography: across a marker ~200 px
/// wide the vehicles' mild barrel distortion bends its pattern by
/// ~0.03 px, enough to bias a fit of all its pixels.
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

    /// [`Lens::ideal`] of every pixel of the `w`x`h` block at `(x0, y0)`,
    /// row-major: exact on a grid every [`IDEAL_GRID_PX`] pixels,
    /// bilinear between, then one fixed-point step `q ← q + p − pixel(q)`
    /// (the distortion's derivative is within a few per cent of the
    /// identity, so the step leaves ~1e-4 px of the interpolation's
    /// ~1e-3 px). The iterative undistortion of every pixel took ~5 % of
    /// the pattern fit's time.
    fn ideal_grid(&self, x0: usize, y0: usize, w: usize, h: usize) -> Vec<Px> {
        let at = |x: usize, y: usize| [(x0 + x) as f64, (y0 + y) as f64];
        if self.0.is_none() {
            return (0..w * h).map(|k| at(k % w, k / w)).collect();
        }
        let g = IDEAL_GRID_PX;
        let (gw, gh) = ((w - 1) / g + 2, (h - 1) / g + 2);
        let grid: Vec<Px> = (0..gw * gh)
            .map(|i| self.ideal(at((i % gw) * g, (i / gw) * g)))
            .collect();
        let mut out = Vec::with_capacity(w * h);
        for y in 0..h {
            let (gy, fy) = (y / g, (y % g) as f64 / g as f64);
            for x in 0..w {
                let (gx, fx) = (x / g, (x % g) as f64 / g as f64);
                let c = |dx: usize, dy: usize| grid[(gy + dy) * gw + gx + dx];
                let (a, b, cc, d) = (c(0, 0), c(1, 0), c(0, 1), c(1, 1));
                let mut q = [0.0; 2];
                for i in 0..2 {
                    let top = a[i] + fx * (b[i] - a[i]);
                    let bottom = cc[i] + fx * (d[i] - cc[i]);
                    q[i] = top + fy * (bottom - top);
                }
                let p = at(x, y);
                let back = self.pixel(q);
                out.push([q[0] + p[0] - back[0], q[1] + p[1] - back[1]]);
            }
        }
        out
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
    // Gauss–Newton with backtracking: a step that raises the residual (by
    // more than `RMS_TOL`) is halved from the last accepted point.
    let mut accepted: Option<([Px; 4], Step)> = None;
    let mut coef: Option<DVector<f64>> = None;
    let mut fraction = 1.0;
    for it in 0..MAX_ITERATIONS {
        let h = homography_4(&unit, &corners).ok_or(PatternFitError::Singular)?;
        let step = evaluate(raw, grid, m, &unit, &corners, &h, &win, &idx, coef.as_ref())?;
        if let Some((at, best)) = &accepted {
            // A residual that rises by less than `RMS_TOL` is as flat as
            // one that falls by less: the last accepted point is the fit.
            if step.rms > best.rms && step.rms - best.rms < RMS_TOL * best.rms {
                return best.fit(&unit, at, &win, it + 1, lens);
            }
            if step.rms > best.rms {
                fraction *= 0.5;
                if fraction < 0.1 {
                    return best.fit(&unit, at, &win, it + 1, lens);
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
            return step.fit(&unit, &corners, &win, it + 1, lens);
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
    best.fit(&unit, &at, &win, MAX_ITERATIONS, lens)
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
    let pos = lens.ideal_grid(x0, y0, w, hgt);
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

#[cfg(test)]
mod tests {
    use super::model::{build_bases, BLACK, QUIET, WHITE};
    use super::*;

    /// A frame drawn from the model itself: `grid` at `truth` (outer
    /// corners) through the sharp part and each halo kernel, the white
    /// print 15 % brighter on the right, a veil, Gaussian noise σ 2 DN.
    fn synthetic(grid: &[bool], truth: &[Px; 4], seed: u64) -> (Vec<u8>, usize, usize) {
        synthetic_with_noise(grid, truth, seed, 0.0)
    }

    /// [`synthetic`] with its noise correlated between neighbouring pixels:
    /// independent draws blurred by a Gaussian of `correlation_px` (none
    /// when 0) and scaled back to σ 2 DN per pixel, as demosaicing and
    /// compression leave a camera's noise.
    fn synthetic_with_noise(
        grid: &[bool],
        truth: &[Px; 4],
        seed: u64,
        correlation_px: f64,
    ) -> (Vec<u8>, usize, usize) {
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
        let unit_normal = Gauss::new(0.0, 1.0).unwrap();
        let mut noise: Vec<f64> = (0..w * hgt).map(|_| unit_normal.sample(&mut rng)).collect();
        if correlation_px > 0.0 {
            use opencv::prelude::*;
            let src =
                opencv::core::Mat::new_rows_cols_with_data(hgt as i32, w as i32, &noise).unwrap();
            let mut blurred = opencv::core::Mat::default();
            opencv::imgproc::gaussian_blur_def(
                &src,
                &mut blurred,
                opencv::core::Size::new(0, 0),
                correlation_px,
            )
            .unwrap();
            noise = blurred.data_typed::<f64>().unwrap().to_vec();
            let sd = (noise.iter().map(|v| v * v).sum::<f64>() / noise.len() as f64).sqrt();
            noise.iter_mut().for_each(|v| *v /= sd);
        }
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
            *px = (v + 2.0 * noise[i]).round().clamp(0.0, 255.0) as u8;
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

    /// The corners' stated covariance against their scatter over noise
    /// draws: with independent pixel noise and with the same noise per pixel
    /// correlated over neighbours (blurred by σ 1 px). `σ² (JᵀJ)⁻¹`, which
    /// assumes independent pixels, states the same for both (the same
    /// geometry and noise per pixel), yet the correlated noise moves the
    /// corners several times more: the sandwich covariance must follow both.
    #[test]
    fn the_corner_covariance_follows_noise_correlated_between_pixels() {
        let grid = shoal_proto::marker::CodeSet::Shoal.module_grid(17).unwrap();
        let truth = [[112.3, 95.6], [318.9, 80.2], [324.4, 301.7], [106.1, 287.5]];
        let start = [[112.9, 95.1], [318.2, 80.8], [325.0, 301.2], [105.6, 288.1]];
        const DRAWS: u64 = 16;
        // (scatter, stated): sums over the eight coordinates, px².
        let run = |correlation_px: f64| {
            let (mut scatter, mut stated) = (0.0, 0.0);
            for seed in 0..DRAWS {
                let (img, w, h) = synthetic_with_noise(&grid, &truth, 100 + seed, correlation_px);
                let view = GrayView {
                    data: &img,
                    width: w,
                    height: h,
                    stride: w,
                };
                let fit = fit_pattern(&view, &grid, 10, &start, Lens(None)).expect("fit");
                let at = unit_corners(10.0).map(|u| fit.project(u));
                for (i, t) in truth.iter().enumerate() {
                    scatter += (at[i][0] - t[0]).powi(2) + (at[i][1] - t[1]).powi(2);
                }
                stated += fit.covariance.trace();
            }
            (scatter / DRAWS as f64, stated / DRAWS as f64)
        };
        let (white_scatter, white_stated) = run(0.0);
        let (corr_scatter, corr_stated) = run(1.0);
        // The correlated noise really moves the corners more (what an
        // independent-pixel covariance cannot see).
        assert!(
            corr_scatter > 3.0 * white_scatter,
            "scatter {corr_scatter:.2e} vs {white_scatter:.2e} px²"
        );
        // 16 draws of 8 coordinates: the scatter's own spread is ~±30 %.
        for (what, scatter, stated) in [
            ("independent", white_scatter, white_stated),
            ("correlated", corr_scatter, corr_stated),
        ] {
            let ratio = stated / scatter;
            println!(
                "{what} noise: stated {stated:.2e} px², scatter {scatter:.2e} (ratio {ratio:.2})"
            );
            assert!(
                (0.5..2.0).contains(&ratio),
                "{what} noise: stated {stated:.2e} px² against a scatter of {scatter:.2e} (ratio {ratio:.2})"
            );
        }
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
    fn the_interpolated_ideal_positions_match_the_exact_ones() {
        let lens = Lens(Some(CameraModel::vehicle_1440()));
        // A window near the frame's corner, where the distortion bends most.
        let (x0, y0, w, h) = (13, 21, 203, 117);
        let grid = lens.ideal_grid(x0, y0, w, h);
        let mut worst = 0.0f64;
        for (k, q) in grid.iter().enumerate() {
            let e = lens.ideal([(x0 + k % w) as f64, (y0 + k / w) as f64]);
            worst = worst.max((q[0] - e[0]).hypot(q[1] - e[1]));
        }
        // ~1e-4 px at the frame's corner: a hundredth of the fit's stop tolerance.
        assert!(worst < 2e-4, "worst {worst:e} px");
        let plain = Lens(None).ideal_grid(3, 4, 5, 6);
        assert_eq!(plain[7], [5.0, 5.0]);
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
}
