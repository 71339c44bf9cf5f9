//! Small fixed-size linear algebra on the fusion's hot path.

use proto::geometry::Cov6;

/// The lower Cholesky factor `L` (`A = L·Lᵀ`) of a symmetric 6×6 matrix,
/// from its lower triangle; `None` when `A` is not positive definite (or
/// holds a NaN).
fn cholesky6(a: &Cov6) -> Option<[[f64; 6]; 6]> {
    let mut l = [[0.0f64; 6]; 6];
    for j in 0..6 {
        let mut d = a[(j, j)];
        for k in 0..j {
            d -= l[j][k] * l[j][k];
        }
        // Also refuses NaN.
        if !(d > 0.0 && d.is_finite()) {
            return None;
        }
        let ljj = d.sqrt();
        l[j][j] = ljj;
        let inv = 1.0 / ljj;
        for i in j + 1..6 {
            let mut s = a[(i, j)];
            for k in 0..j {
                s -= l[i][k] * l[j][k];
            }
            l[i][j] = s * inv;
        }
    }
    Some(l)
}

/// Inverse of a symmetric positive-definite 6×6 matrix through its Cholesky
/// factor `L` (`A⁻¹ = L⁻ᵀ L⁻¹`); `None` when `A` is not positive definite
/// (or holds a NaN). Reads the lower triangle, as nalgebra's `cholesky()`
/// does; the result is exactly symmetric.
///
/// Written out for the fixed size because every observation's hypotheses
/// need their information matrix on every solve: nalgebra's generic
/// `Cholesky::inverse` solves six triangular systems column by column and
/// was an eighth of a 100-vehicle solve (`cargo bench -p shoal-fusion
/// --bench solve`, which also times the two side by side).
pub fn spd_inverse6(a: &Cov6) -> Option<Cov6> {
    let l = cholesky6(a)?;
    // M = L⁻¹, lower triangular.
    let mut m = [[0.0f64; 6]; 6];
    for i in 0..6 {
        m[i][i] = 1.0 / l[i][i];
        for j in 0..i {
            let mut s = 0.0;
            for k in j..i {
                s -= l[i][k] * m[k][j];
            }
            m[i][j] = s * m[i][i];
        }
    }
    // A⁻¹ = Mᵀ M: entry (i, j), i ≥ j, sums over k ≥ i.
    let mut out = Cov6::zeros();
    for i in 0..6 {
        for j in 0..=i {
            let mut s = 0.0;
            for row in &m[i..] {
                s += row[i] * row[j];
            }
            out[(i, j)] = s;
            out[(j, i)] = s;
        }
    }
    out.iter().all(|v| v.is_finite()).then_some(out)
}

/// `rᵀ·A⁻¹·r` for a symmetric positive-definite 6×6 `A` (lower triangle
/// read), through its Cholesky factor: `|L⁻¹·r|²`. `None` when `A` is not
/// positive definite. Every squared Mahalanobis distance under summed
/// covariances (clusters, triangle votes, the spanning tree) is one; the
/// generic `cholesky().solve()` it replaces allocates nothing either but
/// runs column by column through nalgebra's general code.
pub fn spd_quadratic6(a: &Cov6, r: &nalgebra::Vector6<f64>) -> Option<f64> {
    let l = cholesky6(a)?;
    let mut z = [0.0f64; 6];
    let mut sum = 0.0;
    for j in 0..6 {
        // Forward substitution, row j: z_j = (r_j − Σ L_jk z_k) / L_jj.
        let mut s = r[j];
        for k in 0..j {
            s -= l[j][k] * z[k];
        }
        z[j] = s * (1.0 / l[j][j]);
        sum += z[j] * z[j];
    }
    sum.is_finite().then_some(sum)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proto::splitmix::SplitMix64;

    fn random_spd(rng: &mut SplitMix64, scale: f64) -> Cov6 {
        let b = Cov6::from_fn(|_, _| rng.unit() - 0.5);
        b * b.transpose() * scale + Cov6::identity() * 1e-3 * scale
    }

    #[test]
    fn matches_nalgebras_inverse_and_refuses_what_it_refuses() {
        let mut rng = SplitMix64::new(3);
        for scale in [1e-8, 1e-4, 1.0, 1e3] {
            for _ in 0..200 {
                let a = random_spd(&mut rng, scale);
                let want = a.cholesky().unwrap().inverse();
                let got = spd_inverse6(&a).unwrap();
                let err = (got - want).norm() / want.norm();
                assert!(err < 1e-9, "relative error {err:e} at scale {scale}");
                assert_eq!(got, got.transpose());
                assert!(((got * a) - Cov6::identity()).norm() < 1e-6);
            }
        }
        let mut indefinite = Cov6::identity();
        indefinite[(4, 4)] = -1.0;
        assert!(spd_inverse6(&indefinite).is_none());
        assert!(indefinite.cholesky().is_none());
        assert!(spd_inverse6(&Cov6::zeros()).is_none());
        let mut nan = Cov6::identity();
        nan[(2, 1)] = f64::NAN;
        assert!(spd_inverse6(&nan).is_none());
        assert!(spd_quadratic6(&nan, &nalgebra::Vector6::repeat(1.0)).is_none());
        assert!(spd_quadratic6(&indefinite, &nalgebra::Vector6::repeat(1.0)).is_none());
    }

    #[test]
    fn the_quadratic_form_matches_nalgebras_solve() {
        let mut rng = SplitMix64::new(5);
        for scale in [1e-8, 1e-4, 1.0, 1e3] {
            for _ in 0..200 {
                let a = random_spd(&mut rng, scale);
                let r = nalgebra::Vector6::from_fn(|_, _| rng.unit() - 0.5);
                let want = r.dot(&a.cholesky().unwrap().solve(&r));
                let got = spd_quadratic6(&a, &r).unwrap();
                assert!(
                    (got - want).abs() <= 1e-9 * want,
                    "{got} vs {want} at scale {scale}"
                );
            }
        }
    }
}
