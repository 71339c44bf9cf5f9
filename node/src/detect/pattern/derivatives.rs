//! The pattern model's derivatives in the four outer corners' eight
//! coordinates, exact up to second order in the smooth displacement field.
//!
//! The model moves with the sharp pattern: a sharp rendering S changes by
//! −∇S·D_j when corner coordinate j moves (D_j the displacement field of the
//! homography), and each basis is a kernel over (gain ×) S, so
//! ∂M/∂p_j = −Σ_kernels G ∗ (E·D_j), E the kernel's weighted sum of the
//! regions' analytic ∇S (the gain gradients stay with the image). D_j is
//! smooth (a homography's derivative), and for a Gaussian
//! G ∗ (E_a·D_a) = D_a·(G∗E_a) + σ² Σ_b ∂_b D_a · ∂_b(G∗E_a) to second
//! order: two blurs per kernel, not one per corner coordinate.

use super::model::{blur, mat_from, mat_values, BLACK};
use super::{PatternFitError, Window, GEOM};
use crate::detect::geom::{homography_4, Px};
use nalgebra::{DVector, Matrix3};

/// What the geometric derivatives need at each pixel of the window.
pub(super) struct GeometricFields {
    /// `disp[j]` = (∂H/∂p_j)·H⁻¹: the displacement field of corner
    /// coordinate `j` at ideal pixel x is `(A x̃)_xy − x·(A x̃)_z`, x̃ = (x, y, 1)
    /// — a quadratic in x, so it and its derivatives are exact and cheap
    /// at any pixel ([`displacement`]).
    disp: [Matrix3<f64>; GEOM],
    /// Σ_kernels G∗E, per pixel.
    along: Vec<[f64; 2]>,
    /// `spread[k][a][b]` = Σ_kernels σ²·∂_b(G∗E_a).
    spread: Vec<[[f64; 2]; 2]>,
}

impl GeometricFields {
    /// The fields at `corners` (homography `h` from `unit`), for the pixels
    /// `idx` of `win`, the regions' sharp image gradients `grads` and the
    /// linear weights `coef` (region × kernel gains, then the white print's
    /// gain gradients per kernel).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn new(
        unit: &[Px; 4],
        corners: &[Px; 4],
        h: &Matrix3<f64>,
        grads: &[Vec<[f32; 2]>],
        coef: &DVector<f64>,
        kernel_sigma: &[f64],
        win: &Window,
        idx: &[usize],
    ) -> Result<GeometricFields, PatternFitError> {
        let disp = displacement_fields(unit, corners, h)?;
        let (along, spread) = blurred_gradients(grads, coef, kernel_sigma, win, idx)?;
        Ok(GeometricFields {
            disp,
            along,
            spread,
        })
    }

    /// The model's derivative in each corner coordinate at pixel `k` of
    /// the window, whose ideal position is `pos`, negated: the Jacobian's
    /// geometric columns.
    #[inline]
    pub(super) fn row(&self, k: usize, pos: Px, row: &mut [f64]) {
        let (al, sp) = (self.along[k], self.spread[k]);
        for (r, a) in row.iter_mut().zip(&self.disp) {
            let (d, dd) = displacement(a, pos);
            let mut v = d[0] * al[0] + d[1] * al[1];
            for i in 0..2 {
                v += dd[i][0] * sp[i][0] + dd[i][1] * sp[i][1];
            }
            *r = -v;
        }
    }
}

/// The displacement D of ideal pixel `p` under `a` = (∂H/∂p_j)·H⁻¹, and
/// its derivatives `dd[c][b]` = ∂D_c/∂x_b.
#[inline]
fn displacement(a: &Matrix3<f64>, p: Px) -> ([f64; 2], [[f64; 2]; 2]) {
    let [x, y] = p;
    let r = |i: usize| a[(i, 0)] * x + a[(i, 1)] * y + a[(i, 2)];
    let (a0, a1, a2) = (r(0), r(1), r(2));
    (
        [a0 - x * a2, a1 - y * a2],
        [
            [a[(0, 0)] - a2 - x * a[(2, 0)], a[(0, 1)] - x * a[(2, 1)]],
            [a[(1, 0)] - y * a[(2, 0)], a[(1, 1)] - a2 - y * a[(2, 1)]],
        ],
    )
}

/// (∂H/∂p_j)·H⁻¹ for each corner coordinate `j`, H's derivative taken
/// numerically. With ũ = H⁻¹x̃ (so Hũ = x̃ = (x, y, 1)), the pixel of
/// module point ũ moves by (∂H ũ)_xy − x·(∂H ũ)_z.
fn displacement_fields(
    unit: &[Px; 4],
    corners: &[Px; 4],
    h: &Matrix3<f64>,
) -> Result<[Matrix3<f64>; GEOM], PatternFitError> {
    let eps = 1e-3;
    let hinv = h.try_inverse().ok_or(PatternFitError::Singular)?;
    let mut out = [Matrix3::zeros(); GEOM];
    for (j, o) in out.iter_mut().enumerate() {
        let mut c = *corners;
        c[j / 2][j % 2] += eps;
        let hj = homography_4(unit, &c).ok_or(PatternFitError::Singular)?;
        *o = (hj - h) / eps * hinv;
    }
    Ok(out)
}

/// Per pixel, Σ_kernels G∗E (`along`) and Σ_kernels σ²·∂_b(G∗E_a)
/// (`spread[a][b]`).
type BlurredGradients = (Vec<[f64; 2]>, Vec<[[f64; 2]; 2]>);

/// Per kernel, the weighted sum E of the regions' sharp gradients blurred
/// by that kernel: `along` = Σ_kernels G∗E and `spread[a][b]` =
/// Σ_kernels σ²·∂_b(G∗E_a), at the pixels `idx` (inner pixels only).
fn blurred_gradients(
    grads: &[Vec<[f32; 2]>],
    coef: &DVector<f64>,
    kernel_sigma: &[f64],
    win: &Window,
    idx: &[usize],
) -> Result<BlurredGradients, PatternFitError> {
    let (n, w) = (win.w * win.h, win.w);
    let (cx, cy, scale) = win.frame();
    let kernels = kernel_sigma.len();
    let first_gradient_basis = grads.len() * kernels;
    let mut along = vec![[0f64; 2]; n];
    let mut spread = vec![[[0f64; 2]; 2]; n];
    let mut field = [vec![0f32; n], vec![0f32; n]];
    for (k, &sigma) in kernel_sigma.iter().enumerate() {
        let (cgx, cgy) = (
            coef[first_gradient_basis + 2 * k],
            coef[first_gradient_basis + 2 * k + 1],
        );
        let c: Vec<f64> = (0..grads.len())
            .map(|reg| coef[reg * kernels + k])
            .collect();
        for y in 0..win.h {
            let yn = (y as f64 - cy) / scale;
            for x in 0..w {
                let i = y * w + x;
                let xn = (x as f64 - cx) / scale;
                let gain_white = cgx * xn + cgy * yn;
                let mut acc = [0.0; 2];
                for (reg, g) in grads.iter().enumerate() {
                    let c = if reg == BLACK {
                        c[reg]
                    } else {
                        c[reg] + gain_white
                    };
                    acc[0] += c * f64::from(g[i][0]);
                    acc[1] += c * f64::from(g[i][1]);
                }
                field[0][i] = acc[0] as f32;
                field[1][i] = acc[1] as f32;
            }
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
        // `idx` holds no border pixel (`solver::Fitted`).
        for &i in idx {
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
    Ok((along, spread))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::detect::geom::apply;

    #[test]
    fn the_displacement_field_is_the_pixels_motion_with_a_corner() {
        let unit = [[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]];
        let corners = [[112.3, 95.6], [318.9, 80.2], [324.4, 301.7], [106.1, 287.5]];
        let h = homography_4(&unit, &corners).unwrap();
        let fields = displacement_fields(&unit, &corners, &h).unwrap();
        let eps = 1e-6;
        for uv in [[0.5, 0.5], [3.2, 7.9], [9.7, 1.1]] {
            let p = apply(&h, uv);
            for (j, a) in fields.iter().enumerate() {
                let mut c = corners;
                c[j / 2][j % 2] += eps;
                let q = apply(&homography_4(&unit, &c).unwrap(), uv);
                let (d, dd) = displacement(a, p);
                for i in 0..2 {
                    let num = (q[i] - p[i]) / eps;
                    assert!((d[i] - num).abs() < 1e-3, "D {j} {i}: {} vs {num}", d[i]);
                }
                // Its derivative in the pixel: D at the module points of p ± 1 px.
                for b in 0..2 {
                    let mut lo = p;
                    let mut hi = p;
                    lo[b] -= 0.5;
                    hi[b] += 0.5;
                    let (dl, dh) = (displacement(a, lo).0, displacement(a, hi).0);
                    for i in 0..2 {
                        assert!((dd[i][b] - (dh[i] - dl[i])).abs() < 1e-6);
                    }
                }
            }
        }
    }
}
