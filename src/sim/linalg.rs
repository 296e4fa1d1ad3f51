//! Small 2x2 linear algebra for the MLS-MPM particle update: the polar rotation of a
//! deformation gradient and the signed 2x2 SVD used by snow plasticity.
//!
//! Matrices are row-major `[m00, m01, m10, m11]` in `f32`, the solver's state precision.
//! Used by [`crate::sim::material`] (stress, plasticity and the elastic energy density that
//! [`crate::sim::diagnostics`] sums), [`crate::sim::mpm`] (the `F` update) and
//! [`crate::sim::sanity`] (liquid `J`).

/// A 2x2 matrix, row-major: `[m00, m01, m10, m11]`.
pub type Mat2 = [f32; 4];

/// The identity matrix.
pub const IDENTITY: Mat2 = [1.0, 0.0, 0.0, 1.0];

/// `a * b`.
#[inline(always)]
pub fn mul(a: &Mat2, b: &Mat2) -> Mat2 {
    [
        a[0] * b[0] + a[1] * b[2],
        a[0] * b[1] + a[1] * b[3],
        a[2] * b[0] + a[3] * b[2],
        a[2] * b[1] + a[3] * b[3],
    ]
}

/// `a * b^T`.
#[inline(always)]
pub fn mul_bt(a: &Mat2, b: &Mat2) -> Mat2 {
    [
        a[0] * b[0] + a[1] * b[1],
        a[0] * b[2] + a[1] * b[3],
        a[2] * b[0] + a[3] * b[1],
        a[2] * b[2] + a[3] * b[3],
    ]
}

/// Determinant.
#[inline(always)]
pub fn det(a: &Mat2) -> f32 {
    a[0] * a[3] - a[1] * a[2]
}

/// Rotation part `R` of the polar decomposition `F = R S` (S symmetric), computed in closed
/// form: `R = [[c, -s], [s, c]]` with `(c, s) ∝ (F00 + F11, F10 - F01)`.
///
/// For the signed SVD `F = U Σ V^T` with `U`, `V` rotations, `R = U V^T`, which is all the
/// fixed-corotated stress needs, so jelly and rope particles skip the SVD. Returns the
/// identity for the degenerate `F` where both sums vanish.
/// Source: the 2D polar decomposition of Shoemake & Duff (1992), as used by MLS-MPM codes.
#[inline(always)]
pub fn polar_rotation(f: &Mat2) -> Mat2 {
    let x = f[0] + f[3];
    let y = f[2] - f[1];
    let norm2 = x * x + y * y;
    if norm2 <= f32::MIN_POSITIVE {
        return IDENTITY;
    }
    let inv = norm2.sqrt().recip();
    let (c, s) = (x * inv, y * inv);
    [c, -s, s, c]
}

/// Signed SVD `F = U diag(sigma) V^T` with `U` and `V` proper rotations (det = +1) and
/// `sigma[0] >= sigma[1]`; `sigma[1]` is negative when `det F < 0`.
///
/// Computed as the polar decomposition `F = R S` followed by the closed-form eigen
/// decomposition of the symmetric `S = V diag(sigma) V^T`; then `U = R V`.
/// Source: the "signed SVD" of fixed-corotated elasticity (Stomakhin et al. 2012, snow MPM;
/// Hu et al. 2018, MLS-MPM), derived here from the 2x2 eigenproblem.
#[inline]
pub fn svd(f: &Mat2) -> (Mat2, [f32; 2], Mat2) {
    let r = polar_rotation(f);
    // S = R^T F (symmetric up to rounding; symmetrise).
    let s00 = r[0] * f[0] + r[2] * f[2];
    let s11 = r[1] * f[1] + r[3] * f[3];
    let s01 = 0.5 * ((r[0] * f[1] + r[2] * f[3]) + (r[1] * f[0] + r[3] * f[2]));
    let tau = 0.5 * (s00 - s11);
    let w = (tau * tau + s01 * s01).sqrt();
    let mean = 0.5 * (s00 + s11);
    let sigma = [mean + w, mean - w];
    // Eigenvector of the larger eigenvalue, picked from the better-conditioned formula.
    let (c, s) = if w <= 1e-12 {
        (1.0, 0.0)
    } else {
        let (a, b) = if tau >= 0.0 {
            (w + tau, s01)
        } else {
            (s01, w - tau)
        };
        let inv = (a * a + b * b).sqrt().recip();
        (a * inv, b * inv)
    };
    let v = [c, -s, s, c];
    let u = mul(&r, &v);
    (u, sigma, v)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &Mat2, b: &Mat2, tol: f32) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol)
    }

    #[test]
    fn svd_reconstructs_and_is_signed() {
        let cases: [Mat2; 6] = [
            [1.0, 0.0, 0.0, 1.0],
            [1.2, 0.3, -0.1, 0.9],
            [0.5, 2.0, 0.0, 0.7],
            [0.0, -1.0, 1.0, 0.0],
            [1.0, 0.2, 0.3, -0.8],
            [0.97, 0.0, 0.0, 1.003],
        ];
        for f in cases {
            let (u, s, v) = svd(&f);
            let back = mul_bt(&mul(&u, &[s[0], 0.0, 0.0, s[1]]), &v);
            assert!(close(&back, &f, 1e-5), "{f:?} -> {back:?}");
            assert!((det(&u) - 1.0).abs() < 1e-5 && (det(&v) - 1.0).abs() < 1e-5);
            assert!(s[0] >= s[1]);
            assert!((s[0] * s[1] - det(&f)).abs() < 1e-5);
            assert!(close(&mul_bt(&u, &v), &polar_rotation(&f), 1e-5));
        }
    }
}
