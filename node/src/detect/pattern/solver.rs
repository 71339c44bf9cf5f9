//! One Gauss–Newton step of the pattern fit ([`evaluate`]): the linear
//! weights (region × kernel gains, the white print's gain gradients, the
//! veil's quadratic) and the eight corner coordinates solved together from
//! normal equations, with a ridge relative to each column's scale.
//!
//! The gradient `Jᵀr` is summed over every fitted pixel at every step; the
//! curvature `JᵀJ` ([`Curvature`]) over every other pixel of every other
//! row, scaled up, once per fit (again after a backtrack). Only the gradient
//! decides where the fit stops (`Jᵀr = 0`), so the corners are those of the
//! exact Gauss–Newton; the curvature only sets the path there, and the
//! geometry moves a fraction of a pixel over the fit. The 39-column outer
//! product per pixel was most of the fit's cost (`docs/detector.md`).

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

/// The fitted pixels, fixed for the whole fit: their window index, the
/// veil's polynomial there, the observed grey level, and whether the
/// pixel is in the curvature's sample (even column and even row).
pub(super) struct Fitted {
    pub k: Vec<usize>,
    poly: Vec<[f64; POLY]>,
    observed: Vec<f64>,
    sample: Vec<bool>,
}

impl Fitted {
    /// The pixels of `win` where `fitted` holds, but not on its border
    /// (the derivatives take central differences), read from `raw`.
    pub(super) fn new(raw: &GrayView<'_>, win: &Window, fitted: &[bool]) -> Fitted {
        let (cx, cy, scale) = win.frame();
        let mut f = Fitted {
            k: Vec::new(),
            poly: Vec::new(),
            observed: Vec::new(),
            sample: Vec::new(),
        };
        for y in 1..win.h.saturating_sub(1) {
            let row = &raw.data[(win.y0 + y) * raw.stride + win.x0..];
            for x in 1..win.w - 1 {
                let k = y * win.w + x;
                if !fitted[k] {
                    continue;
                }
                let (xn, yn) = ((x as f64 - cx) / scale, (y as f64 - cy) / scale);
                f.k.push(k);
                f.poly.push([1.0, xn, yn, xn * xn, xn * yn, yn * yn]);
                f.observed.push(f64::from(row[x]));
                f.sample.push(x % 2 == 0 && y % 2 == 0);
            }
        }
        f
    }

    pub(super) fn len(&self) -> usize {
        self.k.len()
    }
}

/// The linear part of the model at one geometry: the pattern bases and the
/// veil's polynomial per fitted pixel.
struct LinearRows<'a> {
    bases: &'a [Vec<f32>],
    px: &'a Fitted,
}

/// The curvature `JᵀJ` of the joint system (linear weights and corners),
/// estimated on a quarter of the pixels and scaled to all of them, with its
/// ridge-regularized inverse.
pub(super) struct Curvature {
    ata: DMatrix<f64>,
    inv: DMatrix<f64>,
}

impl LinearRows<'_> {
    /// Columns: the bases, then [`POLY`].
    fn len(&self) -> usize {
        self.bases.len() + POLY
    }

    /// Calls `f(p, bases)` for every fitted pixel `p` in order (or only
    /// those in the curvature's sample), `bases` its basis values.
    ///
    /// The bases are one window-sized array each, 25 of them: read pixel
    /// by pixel they were a cache miss per value (a quarter of the fit's
    /// time). Here a span of [`SPAN`] window pixels of every basis is
    /// first copied, contiguously, into a small pixel-major buffer.
    fn for_each_row(&self, sample_only: bool, mut f: impl FnMut(usize, &[f32])) {
        const SPAN: usize = 256;
        let nb = self.bases.len();
        let n = self.bases.first().map_or(0, Vec::len);
        let mut buf = vec![0f32; nb * SPAN];
        let mut p = 0;
        while p < self.px.len() {
            let s = self.px.k[p];
            let e = (s + SPAN).min(n);
            for (j, b) in self.bases.iter().enumerate() {
                for (o, &v) in b[s..e].iter().enumerate() {
                    buf[o * nb + j] = v;
                }
            }
            while p < self.px.len() && self.px.k[p] < e {
                if !sample_only || self.px.sample[p] {
                    let o = self.px.k[p] - s;
                    f(p, &buf[o * nb..(o + 1) * nb]);
                }
                p += 1;
            }
        }
    }

    /// The linear columns of fitted pixel `p` with basis values `bases`
    /// into `r` (`len()` values).
    #[inline]
    fn row(&self, p: usize, bases: &[f32], r: &mut [f64]) {
        let nb = bases.len();
        for (rj, &b) in r.iter_mut().zip(bases) {
            *rj = f64::from(b);
        }
        r[nb..nb + POLY].copy_from_slice(&self.px.poly[p]);
    }

    /// The linear weights alone, at this geometry, over the curvature's
    /// sample of the pixels: the start of the joint fit, which refits them
    /// with the corners.
    fn fit(&self) -> Result<DVector<f64>, PatternFitError> {
        let mut ne = Normal::new(self.len());
        let mut r = vec![0.0; self.len()];
        self.for_each_row(true, |p, b| {
            self.row(p, b, &mut r);
            ne.add(&r, self.px.observed[p]);
        });
        let (a, b) = ne.finish();
        solve_ridge(&a, &b).ok_or(PatternFitError::Singular)
    }
}

/// The model at `corners` (homography `h`): residual, linear weights and
/// the Gauss–Newton step. `coef` (the weights predicted from the previous
/// step) sets the geometric derivatives; without it they are fitted first.
/// `curvature` is estimated here when `None`, else reused.
#[allow(clippy::too_many_arguments)]
pub(super) fn evaluate(
    grid: &[bool],
    m: usize,
    unit: &[Px; 4],
    corners: &[Px; 4],
    h: &Matrix3<f64>,
    win: &Window,
    px: &Fitted,
    coef: Option<&DVector<f64>>,
    curvature: &mut Option<Curvature>,
) -> Result<Step, PatternFitError> {
    let sigmas = HALO_SIGMAS_PX;
    let kernels = 1 + sigmas.len();
    let kernel_sigma: Vec<f64> = std::iter::once(0.0).chain(sigmas.iter().copied()).collect();
    let Bases { bases, grads } = build_bases(grid, m, h, win, &sigmas)?;
    let lin = LinearRows { bases: &bases, px };
    let linear = lin.len();
    // Linear weights to start from.
    let coef = match coef {
        Some(c) if c.len() == linear => c.clone(),
        _ => lin.fit()?,
    };
    // White must read brighter than black through the whole PSF.
    let gain = |reg: usize| (0..kernels).map(|k| coef[reg * kernels + k]).sum::<f64>();
    if gain(WHITE) <= gain(BLACK) {
        return Err(PatternFitError::NoContrast);
    }
    let geometry =
        GeometricFields::new(unit, corners, h, &grads, &coef, &kernel_sigma, win, &px.k)?;

    let all = GEOM + linear;
    // The curvature's sample, when it is to be estimated at this step.
    let mut sample = curvature.is_none().then(|| Normal::new(all));
    let mut atr = vec![0.0f64; all];
    let mut row = vec![0.0f64; all];
    let (mut sse, mut sampled) = (0.0, 0usize);
    lin.for_each_row(false, |p, b| {
        geometry.row(px.k[p], win.pos[px.k[p]], &mut row[..GEOM]);
        lin.row(p, b, &mut row[GEOM..]);
        let model: f64 = row[GEOM..]
            .iter()
            .zip(coef.iter())
            .map(|(a, b)| a * b)
            .sum();
        let res = px.observed[p] - model;
        sse += res * res;
        for (g, &j) in atr.iter_mut().zip(&row) {
            *g += j * res;
        }
        if let Some(ne) = sample.as_mut().filter(|_| px.sample[p]) {
            ne.add(&row, 0.0);
            sampled += 1;
        }
    });
    if let Some(ne) = sample {
        let (mut ata, _) = ne.finish();
        ata *= px.len() as f64 / sampled.max(1) as f64;
        let inv = ridge_inverse(&ata).ok_or(PatternFitError::Singular)?;
        *curvature = Some(Curvature { ata, inv });
    }
    let curvature = curvature.as_ref().ok_or(PatternFitError::Singular)?;
    solve_step(curvature, DVector::from_vec(atr), sse, px.len(), &coef)
}

/// The step from the curvature and the gradient `atr` over `pixels` pixels
/// (residual sum of squares `sse` at the weights `coef`): the linear
/// weights re-fitted at this geometry, the joint Gauss–Newton update, the
/// corners' covariance.
fn solve_step(
    curvature: &Curvature,
    atr: DVector<f64>,
    sse: f64,
    pixels: usize,
    coef: &DVector<f64>,
) -> Result<Step, PatternFitError> {
    let all = atr.len();
    let linear = all - GEOM;
    let (a, inv) = (&curvature.ata, &curvature.inv);
    // The weights re-fitted at this geometry: the linear block alone.
    let lin_a = a.view((GEOM, GEOM), (linear, linear)).into_owned();
    let lin_b = atr.rows(GEOM, linear).into_owned();
    let dc = solve_ridge(&lin_a, &lin_b).ok_or(PatternFitError::Singular)?;
    let sse_here = (sse - lin_b.dot(&dc)).max(0.0);
    let dof = pixels.saturating_sub(all).max(1) as f64;
    let sigma2 = sse_here / dof;
    let delta_all = inv * &atr;
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
