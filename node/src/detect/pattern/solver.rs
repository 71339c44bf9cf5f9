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
use nalgebra::{DMatrix, DMatrixView, DVector, DVectorView, Matrix3, SMatrix};

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
    /// The inverse normal matrix and the linear weights' re-fit at this
    /// geometry: what [`Step::fit`]'s covariance needs with the rows below.
    inverse: DMatrix<f64>,
    refit: DVector<f64>,
    /// The Jacobian rows (single precision, [`GEOM`] + linear columns
    /// each) and residuals of the pixels fitted, and their window indices:
    /// kept for [`Step::fit`]'s covariance, which would otherwise build the
    /// rows again (as much as a step's own pass over them).
    rows: Vec<f32>,
    residuals: Vec<f64>,
    at: Vec<u32>,
    pixels: usize,
}

impl Step {
    /// The fit result at `corners`, this step's geometry, with the corners'
    /// covariance from the residuals' own spatial correlation
    /// ([`sandwich_covariance`]).
    pub(super) fn fit(
        &self,
        unit: &[Px; 4],
        corners: &[Px; 4],
        win: &Window,
        iterations: usize,
        lens: Lens,
    ) -> Result<PatternFit, PatternFitError> {
        let homography = homography_4(unit, corners).ok_or(PatternFitError::Singular)?;
        let covariance = sandwich_covariance(win, self)?;
        Ok(PatternFit {
            homography,
            lens,
            covariance,
            rms: self.rms,
            iterations,
            pixels: self.pixels,
        })
    }
}

/// Largest lag (px, either axis) of the residuals' correlation the corners'
/// covariance takes in ([`sandwich_covariance`]). Chosen, not fitted to any
/// evaluation: noise blurred by a Gaussian of 1 px (about what a camera's
/// demosaicing leaves) is correlated 0.78 / 0.37 / 0.11 / 0.02 at lags
/// 1 / 2 / 3 / 4 px; correlations wider than this (compression blocks, a
/// halo the model misses) are taken in only in part.
pub(super) const CORRELATION_LAG_PX: usize = 4;

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

    let mut ne = Normal::new(GEOM + linear);
    let mut sse = 0.0;
    let mut kept = Kept {
        rows: Vec::with_capacity(idx.len() * (GEOM + linear)),
        residuals: Vec::with_capacity(idx.len()),
        at: Vec::with_capacity(idx.len()),
    };
    for_each_row(&geometry, &lin, &coef, idx, |k, row, res| {
        sse += res * res;
        ne.add(row, res);
        kept.rows.extend(row.iter().map(|&v| v as f32));
        kept.residuals.push(res);
        kept.at.push(k as u32);
    });
    solve_step(ne, sse, idx.len(), coef, kept)
}

/// What a step keeps of its pass over the pixels ([`Step::rows`]).
struct Kept {
    rows: Vec<f32>,
    residuals: Vec<f64>,
    at: Vec<u32>,
}

/// Every inner pixel `k` of `idx` (the window's outermost pixels have no
/// derivative fields) with its Jacobian row (the geometric columns, then the
/// linear ones) and its residual at the weights `coef`.
fn for_each_row(
    geometry: &GeometricFields,
    lin: &LinearRows<'_>,
    coef: &DVector<f64>,
    idx: &[usize],
    mut visit: impl FnMut(usize, &[f64], f64),
) {
    let mut row = vec![0.0f64; GEOM + lin.len()];
    let w = lin.win.w;
    for &k in idx {
        let (x, y) = (k % w, k / w);
        if x == 0 || y == 0 || x + 1 == w || y + 1 == lin.win.h {
            continue;
        }
        geometry.row(k, &mut row[..GEOM]);
        lin.row(k, &mut row[GEOM..]);
        let model: f64 = row[GEOM..]
            .iter()
            .zip(coef.iter())
            .map(|(a, b)| a * b)
            .sum();
        visit(k, &row, lin.observed(k) - model);
    }
}

/// The covariance of the four outer corners at `step`'s geometry, from the
/// residuals themselves: a sandwich `A⁻¹ M A⁻¹`, `M` the residual-weighted
/// outer products of the Jacobian rows of every pair of pixels up to
/// [`CORRELATION_LAG_PX`] apart along each axis (the truncated kernel, which
/// has no bias where the correlation is gone by that lag; when its estimate
/// is not positive definite, Bartlett weights, Newey–West's estimator,
/// which always is). `σ² A⁻¹` assumes independent pixels; a real camera's
/// are not (demosaicing, compression, a point-spread function the model
/// does not have all leave residuals correlated over neighbours, and the
/// corners then wander more than `σ² A⁻¹` says). On independent noise the
/// two agree; the residual weighting also takes in noise that grows with
/// the grey level.
fn sandwich_covariance(win: &Window, step: &Step) -> Result<SMatrix<f64, 8, 8>, PatternFitError> {
    // Each pixel's residual (at the weights re-fitted here) times its row
    // carried through the first GEOM rows of A⁻¹: its pull on the corners.
    // The first GEOM rows of A⁻¹, row-major.
    let all = step.inverse.ncols();
    let p: Vec<f64> = (0..GEOM)
        .flat_map(|i| (0..all).map(move |j| (i, j)))
        .map(|(i, j)| step.inverse[(i, j)])
        .collect();
    let (w, hgt) = (win.w, win.h);
    let mut pull = vec![[0.0f64; GEOM]; w * hgt];
    let used = step.at.len();
    if step.rows.len() != used * all {
        return Err(PatternFitError::Singular);
    }
    let mut row = vec![0.0f64; all];
    for ((src, &res), &k) in step
        .rows
        .chunks_exact(all)
        .zip(&step.residuals)
        .zip(&step.at)
    {
        for (r, &v) in row.iter_mut().zip(src) {
            *r = f64::from(v);
        }
        let res = res
            - row[GEOM..]
                .iter()
                .zip(step.refit.iter())
                .map(|(a, b)| a * b)
                .sum::<f64>();
        for (ui, pi) in pull[k as usize].iter_mut().zip(p.chunks_exact(all)) {
            *ui = res * pi.iter().zip(&row).map(|(a, b)| a * b).sum::<f64>();
        }
    }
    let truncated = lagged_outer_sum(&pull, w, hgt, &step.at, false);
    let cov = if truncated.cholesky().is_some() {
        truncated
    } else {
        lagged_outer_sum(&pull, w, hgt, &step.at, true)
    };
    // The linear weights and the corners absorb part of the residual.
    let dof = used as f64 / used.saturating_sub(all).max(1) as f64;
    let cov = cov * dof;
    if cov.iter().all(|v| v.is_finite()) && (0..GEOM).all(|i| cov[(i, i)] > 0.0) {
        Ok(cov)
    } else {
        Err(PatternFitError::Singular)
    }
}

/// `Σ_k Σ_d w(d) u_k u_{k+d}ᵀ` over the `w` x `h` grid of 8-vectors `u`
/// (zero outside the pixels `idx`), `d` every offset up to
/// [`CORRELATION_LAG_PX`] along either axis; `w(d)` is 1, or with
/// `bartlett` the product of `1 − |d_x| / (lag + 1)` and
/// `1 − |d_y| / (lag + 1)` (positive semidefinite: a product of Fejér
/// kernels). The inner sum is a box filter of `u` (Bartlett's: two boxes
/// of half the lag, each axis), by running sums.
fn lagged_outer_sum(
    u: &[[f64; GEOM]],
    w: usize,
    h: usize,
    idx: &[u32],
    bartlett: bool,
) -> SMatrix<f64, 8, 8> {
    const _: () = assert!(
        CORRELATION_LAG_PX & 1 == 0,
        "Bartlett as two boxes needs an even lag"
    );
    let s = if bartlett {
        // On a grid padded by the lag: the first box spreads into the
        // padding and the second must sum it back.
        let (r, pad) = (CORRELATION_LAG_PX / 2, CORRELATION_LAG_PX);
        let (pw, ph) = (w + 2 * pad, h + 2 * pad);
        let mut padded = vec![[0.0f64; GEOM]; pw * ph];
        for (y, row) in u.chunks_exact(w).enumerate() {
            padded[(y + pad) * pw + pad..][..w].copy_from_slice(row);
        }
        box_sum(&mut padded, pw, ph, r);
        box_sum(&mut padded, pw, ph, r);
        let norm = 1.0 / ((2 * r + 1) * (2 * r + 1)) as f64;
        (0..w * h)
            .map(|k| padded[(k / w + pad) * pw + k % w + pad].map(|v| v * norm))
            .collect()
    } else {
        let mut s = u.to_vec();
        box_sum(&mut s, w, h, CORRELATION_LAG_PX);
        s
    };
    let mut cov = SMatrix::<f64, 8, 8>::zeros();
    for &k in idx {
        let (a, b) = (&u[k as usize], &s[k as usize]);
        for i in 0..GEOM {
            for j in 0..GEOM {
                cov[(i, j)] += a[i] * b[j];
            }
        }
    }
    0.5 * (cov + cov.transpose())
}

/// `v` (a `w` x `h` grid of 8-vectors) replaced by its sums over the
/// (2r + 1) x (2r + 1) box around each point, cut by the grid's edges:
/// running sums along rows, then along columns.
fn box_sum(v: &mut [[f64; GEOM]], w: usize, h: usize, r: usize) {
    let add = |acc: &mut [f64; GEOM], x: &[f64; GEOM], sign: f64| {
        for (a, b) in acc.iter_mut().zip(x) {
            *a += sign * b;
        }
    };
    let mut line = vec![[0.0f64; GEOM]; w.max(h)];
    for row in v.chunks_exact_mut(w).take(h) {
        line[..w].copy_from_slice(row);
        let mut acc = [0.0f64; GEOM];
        for x in line.iter().take(r.min(w - 1) + 1) {
            add(&mut acc, x, 1.0);
        }
        for x in 0..w {
            row[x] = acc;
            if x + r + 1 < w {
                add(&mut acc, &line[x + r + 1], 1.0);
            }
            if x >= r {
                add(&mut acc, &line[x - r], -1.0);
            }
        }
    }
    // Columns: one running sum per column, rows taken in turn.
    let src = v.to_vec();
    let mut acc = vec![[0.0f64; GEOM]; w];
    for y in 0..=r.min(h - 1) {
        for (a, x) in acc.iter_mut().zip(&src[y * w..(y + 1) * w]) {
            add(a, x, 1.0);
        }
    }
    for y in 0..h {
        v[y * w..(y + 1) * w].copy_from_slice(&acc);
        if y + r + 1 < h {
            for (a, x) in acc.iter_mut().zip(&src[(y + r + 1) * w..(y + r + 2) * w]) {
                add(a, x, 1.0);
            }
        }
        if y >= r {
            for (a, x) in acc.iter_mut().zip(&src[(y - r) * w..(y - r + 1) * w]) {
                add(a, x, -1.0);
            }
        }
    }
}

/// The step from the normal equations `ne` over `pixels` pixels (residual
/// sum of squares `sse` at the weights `coef`): the linear weights re-fitted
/// at this geometry, the joint Gauss–Newton update, the corners' covariance.
fn solve_step(
    ne: Normal,
    sse: f64,
    pixels: usize,
    coef: DVector<f64>,
    kept: Kept,
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
    Ok(Step {
        rms: sigma2.sqrt(),
        delta,
        coef_here: &coef + &dc,
        coef_next: &coef + delta_all.rows(GEOM, linear),
        inverse: inv,
        refit: dc,
        rows: kept.rows,
        residuals: kept.residuals,
        at: kept.at,
        pixels,
    })
}

/// Rows gathered before they are added to the normal equations as one
/// matrix product (a fit adds one row of 39 values per pixel, tens of thousands of them).
const BLOCK_ROWS: usize = 128;

/// Normal equations over rows of `cols` values: `AᵀA` and `Aᵀr`, the rows
/// gathered [`BLOCK_ROWS`] at a time and added as one product each
/// (nalgebra's `gemm`, a blocked kernel: the row-by-row update it replaced
/// loaded and stored every entry of `AᵀA` once per row, ~a quarter of a
/// pattern fit's time).
struct Normal {
    cols: usize,
    ata: DMatrix<f64>,
    atr: DVector<f64>,
    /// Rows not yet added, row-major.
    block: Vec<f64>,
    residuals: Vec<f64>,
}

impl Normal {
    fn new(cols: usize) -> Normal {
        Normal {
            cols,
            ata: DMatrix::zeros(cols, cols),
            atr: DVector::zeros(cols),
            block: Vec::with_capacity(BLOCK_ROWS * cols),
            residuals: Vec::with_capacity(BLOCK_ROWS),
        }
    }

    #[inline]
    fn add(&mut self, row: &[f64], r: f64) {
        self.block.extend_from_slice(&row[..self.cols]);
        self.residuals.push(r);
        if self.residuals.len() == BLOCK_ROWS {
            self.flush();
        }
    }

    /// Adds the gathered rows.
    fn flush(&mut self) {
        let (rows, n) = (self.residuals.len(), self.cols);
        if rows == 0 {
            return;
        }
        // The row-major block is `A` (rows x n); the same slice with the
        // strides swapped is `Aᵀ`.
        let at = DMatrixView::from_slice_with_strides(&self.block, n, rows, 1, n);
        let a = DMatrixView::from_slice_with_strides(&self.block, rows, n, n, 1);
        self.ata.gemm(1.0, &at, &a, 1.0);
        let r = DVectorView::from_slice(&self.residuals, rows);
        self.atr.gemv(1.0, &at, &r, 1.0);
        self.block.clear();
        self.residuals.clear();
    }

    /// `(AᵀA, Aᵀr)`, `AᵀA` exactly symmetric (its upper triangle).
    fn finish(mut self) -> (DMatrix<f64>, DVector<f64>) {
        self.flush();
        let n = self.cols;
        let ata = DMatrix::from_fn(n, n, |i, j| {
            let (i, j) = if i <= j { (i, j) } else { (j, i) };
            self.ata[(i, j)]
        });
        (ata, self.atr)
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

    /// The blocked normal equations are the row-by-row sums, over more
    /// rows than one block and a part of the next (and over none).
    #[test]
    fn the_blocked_normal_equations_are_the_sums_over_the_rows() {
        let n = 11;
        for rows in [0, 5, BLOCK_ROWS, 2 * BLOCK_ROWS + 37] {
            let row_of = |k: usize| -> Vec<f64> {
                (0..n)
                    .map(|j| {
                        ((k * 31 + j * 17) % 23) as f64 / 7.0 - 1.5 + (j == k % n) as u8 as f64
                    })
                    .collect()
            };
            let res_of = |k: usize| ((k * 13) % 19) as f64 - 9.0;
            let mut ne = Normal::new(n);
            let (mut ata, mut atr) = (DMatrix::<f64>::zeros(n, n), DVector::<f64>::zeros(n));
            for k in 0..rows {
                let (row, r) = (row_of(k), res_of(k));
                ne.add(&row, r);
                for i in 0..n {
                    atr[i] += row[i] * r;
                    for j in 0..n {
                        ata[(i, j)] += row[i] * row[j];
                    }
                }
            }
            let (got_ata, got_atr) = ne.finish();
            let scale = ata.amax().max(atr.amax()).max(1.0);
            assert!(
                (&got_ata - &ata).amax() <= 1e-12 * scale,
                "{rows} rows: AᵀA"
            );
            assert!(
                (&got_atr - &atr).amax() <= 1e-12 * scale,
                "{rows} rows: Aᵀr"
            );
            assert_eq!(got_ata, got_ata.transpose(), "{rows} rows: not symmetric");
        }
    }

    /// The running-sum box and the Bartlett weights as two boxes against
    /// the sums written out, on a grid with a zero border and an odd size.
    #[test]
    fn the_lagged_sums_match_the_sums_written_out() {
        let (w, h) = (13usize, 9usize);
        let u: Vec<[f64; GEOM]> = (0..w * h)
            .map(|k| std::array::from_fn(|c| ((k * 7 + c * 3) % 11) as f64 - 5.0 + 0.1 * c as f64))
            .collect();
        let idx: Vec<u32> = (0..(w * h) as u32).filter(|k| k % 5 != 0).collect();
        let lag = CORRELATION_LAG_PX as i64;
        for bartlett in [false, true] {
            let got = lagged_outer_sum(&u, w, h, &idx, bartlett);
            let mut want = SMatrix::<f64, 8, 8>::zeros();
            for &k in &idx {
                let k = k as usize;
                let (x, y) = ((k % w) as i64, (k / w) as i64);
                for dy in -lag..=lag {
                    for dx in -lag..=lag {
                        let (xx, yy) = (x + dx, y + dy);
                        if xx < 0 || yy < 0 || xx >= w as i64 || yy >= h as i64 {
                            continue;
                        }
                        let wgt = if bartlett {
                            (1.0 - dx.abs() as f64 / (lag + 1) as f64)
                                * (1.0 - dy.abs() as f64 / (lag + 1) as f64)
                        } else {
                            1.0
                        };
                        let l = yy as usize * w + xx as usize;
                        for i in 0..GEOM {
                            for j in 0..GEOM {
                                want[(i, j)] += wgt * u[k][i] * u[l][j];
                            }
                        }
                    }
                }
            }
            let want = 0.5 * (want + want.transpose());
            let err = (got - want).abs().max();
            assert!(
                err < 1e-9 * want.abs().max(),
                "bartlett {bartlett}: off by {err}"
            );
        }
    }

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
