//! One Gauss–Newton step of the pattern fit ([`evaluate`]): the linear
//! weights (region × kernel gains, the white print's gain gradients, the
//! veil's quadratic) and the eight corner coordinates solved together from
//! normal equations over every fitted pixel, with a ridge relative to each
//! column's scale.

use super::derivatives::GeometricFields;
use super::model::{build_bases, Bases, BLACK, WHITE};
use super::{Lens, PatternFit, PatternFitError, Window, GEOM, HALO_SIGMAS_PX};
use crate::detect::geom::{homography_4, Px};
use crate::mat::GrayView;
use nalgebra::{DMatrix, DVector, Matrix3, SMatrix};

/// 1, x, y, x², xy, y².
const POLY: usize = 6;

/// Ridge relative to each column's scale (the system scaled to a unit
/// diagonal): the regions' bases under the narrow kernels sum to the
/// constant where fitted (the plate is uniform beyond the quiet zone's
/// first 0.6 module), and wide kernels come near the veil's polynomial;
/// the null directions get no weight instead of any.
const RIDGE: f64 = 1e-8;

/// The model evaluated at one geometry.
pub(super) struct Step {
    /// Residual rms with the linear weights fitted at this geometry.
    pub rms: f64,
    /// Gauss–Newton update of the corners.
    pub delta: [f64; GEOM],
    /// Linear weights fitted at this geometry, and predicted after `delta`.
    pub coef_here: DVector<f64>,
    pub coef_next: DVector<f64>,
    covariance: SMatrix<f64, 8, 8>,
    pixels: usize,
}

impl Step {
    /// The fit result at `corners`, this step's geometry.
    pub(super) fn fit(
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

/// The linear part of the model at one geometry: the pattern bases and the
/// veil's polynomial per pixel of the window, and the observed grey levels.
struct LinearRows<'a> {
    bases: &'a [Vec<f32>],
    win: &'a Window,
    raw: &'a GrayView<'a>,
}

impl LinearRows<'_> {
    /// Columns: the bases, then [`POLY`].
    fn len(&self) -> usize {
        self.bases.len() + POLY
    }

    /// The linear columns at pixel `k` into `r` (`len()` values).
    fn row(&self, k: usize, r: &mut [f64]) {
        let w = self.win.w;
        let (cx, cy, scale) = self.win.frame();
        for (j, b) in self.bases.iter().enumerate() {
            r[j] = b[k] as f64;
        }
        let x = ((k % w) as f64 - cx) / scale;
        let y = ((k / w) as f64 - cy) / scale;
        r[self.bases.len()..].copy_from_slice(&[1.0, x, y, x * x, x * y, y * y]);
    }

    /// The raw frame's grey level at pixel `k` of the window.
    fn observed(&self, k: usize) -> f64 {
        let w = self.win.w;
        let (x, y) = (self.win.x0 + k % w, self.win.y0 + k / w);
        self.raw.data[y * self.raw.stride + x] as f64
    }

    /// The linear weights alone, at this geometry, over the pixels `idx`.
    fn fit(&self, idx: &[usize]) -> Result<DVector<f64>, PatternFitError> {
        let mut ne = Normal::new(self.len());
        let mut r = vec![0.0; self.len()];
        for &k in idx {
            self.row(k, &mut r);
            ne.add(&r, self.observed(k));
        }
        let (a, b) = ne.finish();
        solve_ridge(&a, &b).ok_or(PatternFitError::Singular)
    }
}

/// The model at `corners` (homography `h`): residual, linear weights and
/// the Gauss–Newton step. `coef` (the weights predicted from the previous
/// step) sets the geometric derivatives; without it they are fitted first.
#[allow(clippy::too_many_arguments)]
pub(super) fn evaluate(
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
    let Bases { bases, uv, grads } = build_bases(grid, m, h, win, &sigmas)?;
    let lin = LinearRows {
        bases: &bases,
        win,
        raw,
    };
    let linear = lin.len();
    // Linear weights to start from.
    let coef = match coef {
        Some(c) if c.len() == linear => c.clone(),
        _ => lin.fit(idx)?,
    };
    // White must read brighter than black through the whole PSF.
    let gain = |reg: usize| (0..kernels).map(|k| coef[reg * kernels + k]).sum::<f64>();
    if gain(WHITE) <= gain(BLACK) {
        return Err(PatternFitError::NoContrast);
    }
    let geometry = GeometricFields::new(
        unit,
        corners,
        h,
        &uv,
        &grads,
        &coef,
        &kernel_sigma,
        win,
        idx,
    )?;

    let all = GEOM + linear;
    let mut ne = Normal::new(all);
    let mut row = vec![0.0f64; all];
    let mut sse = 0.0;
    let w = win.w;
    for &k in idx {
        let (x, y) = (k % w, k / w);
        if x == 0 || y == 0 || x + 1 == w || y + 1 == win.h {
            continue;
        }
        geometry.row(k, &mut row[..GEOM]);
        lin.row(k, &mut row[GEOM..]);
        let model: f64 = row[GEOM..]
            .iter()
            .zip(coef.iter())
            .map(|(a, b)| a * b)
            .sum();
        let res = lin.observed(k) - model;
        sse += res * res;
        ne.add(&row, res);
    }
    solve_step(ne, sse, idx.len(), &coef)
}

/// The step from the normal equations `ne` over `pixels` pixels (residual
/// sum of squares `sse` at the weights `coef`): the linear weights re-fitted
/// at this geometry, the joint Gauss–Newton update, the corners' covariance.
fn solve_step(
    ne: Normal,
    sse: f64,
    pixels: usize,
    coef: &DVector<f64>,
) -> Result<Step, PatternFitError> {
    let all = ne.cols;
    let linear = all - GEOM;
    let (a, atr) = ne.finish();
    // The weights re-fitted at this geometry: the linear block alone.
    let lin_a = a.view((GEOM, GEOM), (linear, linear)).into_owned();
    let lin_b = atr.rows(GEOM, linear).into_owned();
    let dc = solve_ridge(&lin_a, &lin_b).ok_or(PatternFitError::Singular)?;
    let sse_here = (sse - lin_b.dot(&dc)).max(0.0);
    let dof = pixels.saturating_sub(all).max(1) as f64;
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
        coef_here: coef + dc,
        coef_next: coef + delta_all.rows(GEOM, linear),
        covariance,
        pixels,
    })
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

    /// The ridge ([`RIDGE`], relative to a unit diagonal) moves an exact
    /// solution of this well-conditioned system by ~1e-8 of its size.
    const EXACT_TOL: f64 = 1e-6;

    #[test]
    fn normal_equations_solve_a_least_squares_line() {
        // y = 2 + 3x, exactly.
        let mut ne = Normal::new(2);
        for i in 0..10 {
            let x = i as f64;
            ne.add(&[1.0, x], 2.0 + 3.0 * x);
        }
        let (a, b) = ne.finish();
        assert_eq!(a[(1, 0)], a[(0, 1)]);
        let s = solve_ridge(&a, &b).unwrap();
        assert!(
            (s[0] - 2.0).abs() < EXACT_TOL && (s[1] - 3.0).abs() < EXACT_TOL,
            "{s}"
        );
    }
}
