//! Small dense linear algebra used per pixel: 3×3 symmetric eigenvalues and solves.

use nalgebra::{Matrix3, Vector3};

/// Eigenvalues of a symmetric 3×3 matrix in ascending order, by the closed form of
/// Smith (1961), "Eigenvalues of a symmetric 3×3 matrix", CACM 4(4).
pub(crate) fn sym3_eigenvalues(a: &Matrix3<f64>) -> [f64; 3] {
    let p1 = a[(0, 1)].powi(2) + a[(0, 2)].powi(2) + a[(1, 2)].powi(2);
    if p1 == 0.0 {
        let mut e = [a[(0, 0)], a[(1, 1)], a[(2, 2)]];
        e.sort_by(f64::total_cmp);
        return e;
    }
    let q = a.trace() / 3.0;
    let p2 = (a[(0, 0)] - q).powi(2) + (a[(1, 1)] - q).powi(2) + (a[(2, 2)] - q).powi(2) + 2.0 * p1;
    let p = (p2 / 6.0).sqrt();
    let b = (a - Matrix3::identity() * q) / p;
    let r = (b.determinant() / 2.0).clamp(-1.0, 1.0);
    let phi = r.acos() / 3.0;
    let largest = q + 2.0 * p * phi.cos();
    let smallest = q + 2.0 * p * (phi + 2.0 * std::f64::consts::PI / 3.0).cos();
    let middle = 3.0 * q - largest - smallest;
    [smallest, middle, largest]
}

/// Condition number σ_max/σ_min of a matrix L whose Gram matrix LᵀL is `gram`
/// (the square root of the eigenvalue ratio); infinite when LᵀL is singular.
pub(crate) fn condition_from_gram(gram: &Matrix3<f64>) -> f64 {
    let [lo, _, hi] = sym3_eigenvalues(gram);
    if lo <= hi * 1e-15 || lo <= 0.0 {
        f64::INFINITY
    } else {
        (hi / lo).sqrt()
    }
}

/// Whether [`condition_from_gram`]`(gram) ≤ max_condition`, usually without the eigenvalues:
/// for eigenvalues 0 < λ₁ ≤ λ₂ ≤ λ₃, λ₁ = det/(λ₂λ₃) ≥ det/λ₃², so λ₃/λ₁ ≤ λ₃³/det ≤ trace³/det,
/// and trace³ ≤ max_condition²·det already settles it.
pub(crate) fn condition_at_most(gram: &Matrix3<f64>, max_condition: f64) -> bool {
    let limit = max_condition * max_condition;
    let det = gram.determinant();
    let trace = gram.trace();
    if det > 0.0 && trace.powi(3) <= limit * det {
        return true;
    }
    condition_from_gram(gram) <= max_condition
}

/// Solves the symmetric positive-definite system `a x = b` by Cholesky; `None` when `a` is
/// not positive definite.
pub(crate) fn solve_spd(a: Matrix3<f64>, b: Vector3<f64>) -> Option<Vector3<f64>> {
    a.cholesky().map(|c| c.solve(&b))
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    #[test]
    fn eigenvalues_match_nalgebra() {
        let m = Matrix3::new(4.0, 1.0, -2.0, 1.0, 2.0, 0.5, -2.0, 0.5, 3.0);
        let mut reference: Vec<f64> = m.symmetric_eigenvalues().iter().copied().collect();
        reference.sort_by(f64::total_cmp);
        let ours = sym3_eigenvalues(&m);
        for (a, b) in ours.iter().zip(&reference) {
            assert_relative_eq!(a, b, epsilon = 1e-10);
        }
    }

    #[test]
    fn diagonal_and_singular_cases() {
        let d = Matrix3::from_diagonal(&Vector3::new(3.0, 1.0, 2.0));
        assert_eq!(sym3_eigenvalues(&d), [1.0, 2.0, 3.0]);
        assert_relative_eq!(condition_from_gram(&d), 3f64.sqrt(), epsilon = 1e-12);
        let v = Vector3::new(1.0, 2.0, 3.0);
        assert!(condition_from_gram(&(v * v.transpose())).is_infinite());
        // The shortcut agrees with the eigenvalues on either side of the limit.
        for (m, limit) in [(d, 10.0), (d, 1.8), (d, 1.7), (v * v.transpose(), 1e9)] {
            assert_eq!(
                condition_at_most(&m, limit),
                condition_from_gram(&m) <= limit,
                "{m} {limit}"
            );
        }
        let spread = Matrix3::new(4.0, 1.0, -2.0, 1.0, 2.0, 0.5, -2.0, 0.5, 3.0);
        let c = condition_from_gram(&spread);
        assert!(condition_at_most(&spread, c * 1.001) && !condition_at_most(&spread, c * 0.999));
    }
}
