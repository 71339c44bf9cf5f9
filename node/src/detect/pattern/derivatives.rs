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
use crate::detect::geom::{apply, homography_4, Px};
use nalgebra::{DVector, Matrix3};

/// What the geometric derivatives need at each pixel of the window.
pub(super) struct GeometricFields {
    /// `disp[k][j]`: how pixel `k`'s model point moves with corner
    /// coordinate `j` (the displacement field D_j), pixel-major: a row
    /// reads five pixels' fields, not forty scattered values.
    disp: Vec<[[f64; 2]; GEOM]>,
    /// Σ_kernels G∗E, per pixel.
    along: Vec<[f64; 2]>,
    /// `spread[k][a][b]` = Σ_kernels σ²·∂_b(G∗E_a).
    spread: Vec<[[f64; 2]; 2]>,
    w: usize,
}

impl GeometricFields {
    /// The fields at `corners` (homography `h` from `unit`), for the pixels
    /// `idx` of `win` whose module points are `uv`, the regions' sharp
    /// image gradients `grads` and the linear weights `coef` (region ×
    /// kernel gains, then the white print's gain gradients per kernel).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn new(
        unit: &[Px; 4],
        corners: &[Px; 4],
        h: &Matrix3<f64>,
        uv: &[[f64; 2]],
        grads: &[Vec<[f32; 2]>],
        coef: &DVector<f64>,
        kernel_sigma: &[f64],
        win: &Window,
        idx: &[usize],
    ) -> Result<GeometricFields, PatternFitError> {
        let disp = displacement_fields(unit, corners, h, uv)?;
        let (along, spread) = blurred_gradients(grads, coef, kernel_sigma, win, idx)?;
        Ok(GeometricFields {
            disp,
            along,
            spread,
            w: win.w,
        })
    }

    /// The model's derivative in each corner coordinate at pixel `k` (an
    /// inner pixel of the window), negated: the Jacobian's geometric columns.
    pub(super) fn row(&self, k: usize, row: &mut [f64]) {
        let w = self.w;
        let d = &self.disp;
        let (here, left, right, up, down) = (&d[k], &d[k - 1], &d[k + 1], &d[k - w], &d[k + w]);
        for j in 0..GEOM {
            let mut v = here[j][0] * self.along[k][0] + here[j][1] * self.along[k][1];
            for a in 0..2 {
                let dbx = 0.5 * (right[j][a] - left[j][a]);
                let dby = 0.5 * (down[j][a] - up[j][a]);
                v += dbx * self.spread[k][a][0] + dby * self.spread[k][a][1];
            }
            row[j] = -v;
        }
    }
}

/// ∂x/∂(corner coordinate) at each pixel's module point `uv`: the
/// displacement fields D_j, numerically, per pixel.
fn displacement_fields(
    unit: &[Px; 4],
    corners: &[Px; 4],
    h: &Matrix3<f64>,
    uv: &[[f64; 2]],
) -> Result<Vec<[[f64; 2]; GEOM]>, PatternFitError> {
    let eps = 1e-3;
    let hj: Vec<Matrix3<f64>> = (0..GEOM)
        .map(|j| {
            let mut c = *corners;
            c[j / 2][j % 2] += eps;
            homography_4(unit, &c).ok_or(PatternFitError::Singular)
        })
        .collect::<Result<_, _>>()?;
    Ok(uv
        .iter()
        .map(|&p| {
            let b = apply(h, p);
            std::array::from_fn(|j| {
                let a = apply(&hj[j], p);
                [(a[0] - b[0]) / eps, (a[1] - b[1]) / eps]
            })
        })
        .collect())
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
    Ok((along, spread))
}
