//! Marginal covariances for the libraries that give none: the 6×6 diagonal
//! blocks of `(JᵀJ)⁻¹`, `J` the whitened (and robustly weighted) Jacobian a
//! library builds at its optimum. faer's sparse Cholesky (the one both
//! libraries use) factors `JᵀJ`; solving it for the identity gives the whole
//! inverse, of which the diagonal blocks are kept: neither library nor faer
//! has a selected inversion like shoal's (`fusion/src/sparse.rs`).

use faer::linalg::solvers::Solve;
use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};
use faer::sparse::SparseColMatRef;
use faer::{Mat, Side};
use nalgebra::Matrix6;
use shoal_proto::VehicleId;
use std::collections::BTreeMap;
use std::ops::Mul;

/// The diagonal blocks of `(JᵀJ)⁻¹` at the columns `columns` (vehicle, first
/// column), or `None` when `JᵀJ` is not positive definite.
pub fn inverse_diagonal_blocks(
    j: SparseColMatRef<'_, usize, f64>,
    columns: &[(VehicleId, usize)],
) -> Option<BTreeMap<VehicleId, Matrix6<f64>>> {
    let jtj = j.transpose().to_col_major().ok()?.mul(j);
    let symbolic = SymbolicLlt::try_new(jtj.symbolic(), Side::Lower).ok()?;
    let llt = Llt::try_new_with_symbolic(symbolic, jtj.as_ref(), Side::Lower).ok()?;
    let n = jtj.ncols();
    let mut inverse = Mat::<f64>::identity(n, n);
    llt.solve_in_place(inverse.as_mut());
    Some(
        columns
            .iter()
            .map(|(v, c)| (*v, Matrix6::from_fn(|r, k| inverse[(c + r, c + k)])))
            .collect(),
    )
}
