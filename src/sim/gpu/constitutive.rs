//! Per-particle pieces of the GPU solver's kernels (`kernels.rs`), as `#[cube]` functions:
//! the B-spline weights and stencil base, the liquid's pressure, the hardening of each
//! material and snow's plastic projection through the signed 2 x 2 SVD. Each is the GPU form
//! of the CPU solver's function it names, with the same operations in the same order.

use burn_cubecl::cubecl;
use cubecl::prelude::*;

/// MLS-MPM's quadratic B-spline weight of the stencil's node `i` (0, 1, 2) along one axis at
/// the fractional offset `f` in `[0.5, 1.5)`: `0.5 (1.5 - f)^2`, `0.75 - (f - 1)^2`, `0.5 (f -
/// 0.5)^2` ([`crate::bspline::weights`], the same operations).
#[cube]
#[allow(unused_assignments)]
pub(super) fn weight(f: f32, #[comptime] i: u32) -> f32 {
    let mut w = f32::new(0.0);
    if comptime![i == 0] {
        let a = f32::new(1.5) - f;
        w = f32::new(0.5) * a * a;
    } else if comptime![i == 1] {
        let b = f - f32::new(1.0);
        w = f32::new(0.75) - b * b;
    } else {
        let c = f - f32::new(0.5);
        w = f32::new(0.5) * c * c;
    }
    w
}

/// The stencil's base node along one axis: `trunc(g - 0.5)` clamped into `[0, n - 3]`, as
/// `Stencil::new` of the CPU solver.
#[cube]
pub(super) fn base_node(g: f32, n: u32) -> u32 {
    let hi = i32::cast_from(n) - 3;
    let mut b = i32::cast_from(g - f32::new(0.5));
    if b < 0 {
        b = 0;
    }
    if b > hi {
        b = hi;
    }
    u32::cast_from(b)
}

/// The liquid's Kirchhoff pressure term ([`crate::sim::material::liquid_pressure`]).
#[cube]
#[allow(unused_assignments)]
pub(super) fn liquid_pressure(j: f32, lambda0: f32) -> f32 {
    let mut p = f32::new(0.0);
    if j >= f32::new(0.5) {
        p = lambda0 * j * (j - f32::new(1.0));
    } else {
        let d = f32::new(0.5) - j;
        p = -lambda0 * (f32::new(0.25) + d * d);
    }
    p
}

/// The hardening factor of a material ([`crate::sim::material::hardening`]).
#[cube]
pub(super) fn hardening(material: u32, jp: f32) -> f32 {
    let mut h = f32::new(0.5);
    if material == 0 {
        h = f32::new(1.0);
    } else if material == 1 {
        h = f32::new(0.3);
    } else if material == 2 {
        h = f32::exp(f32::new(10.0) * (f32::new(1.0) - jp));
        if h < f32::new(0.1) {
            h = f32::new(0.1);
        }
        if h > f32::new(5.0) {
            h = f32::new(5.0);
        }
    }
    h
}

/// Snow's plastic projection ([`crate::sim::material::project`], material 2) of `F` (row-major
/// in `f`): the signed SVD (`linalg::svd`: polar rotation, then the symmetric factor's
/// closed-form eigenvectors), singular values clamped into `[lo, hi]`, the clamped-off volume
/// change multiplied into `jp[p]`; `f` rewritten as `U diag(clamped) V^T`.
#[cube]
pub(super) fn snow_project(f: &mut Array<f32>, jp: &mut Array<f32>, p: usize, lo: f32, hi: f32) {
    let (f0, f1, f2, f3) = (f[p * 4], f[p * 4 + 1], f[p * 4 + 2], f[p * 4 + 3]);
    let px = f0 + f3;
    let py = f2 - f1;
    let norm2 = px * px + py * py;
    let mut rc = f32::new(1.0);
    let mut rs = f32::new(0.0);
    if norm2 > f32::new(1.175_494_4e-38) {
        let inv = f32::new(1.0) / f32::sqrt(norm2);
        rc = px * inv;
        rs = py * inv;
    }
    // R = [rc, -rs, rs, rc]; S = R^T F, symmetrised.
    let s00 = rc * f0 + rs * f2;
    let s11 = -rs * f1 + rc * f3;
    let s01 = f32::new(0.5) * ((rc * f1 + rs * f3) + (-rs * f0 + rc * f2));
    let tau = f32::new(0.5) * (s00 - s11);
    let w = f32::sqrt(tau * tau + s01 * s01);
    let mean = f32::new(0.5) * (s00 + s11);
    let sig0 = mean + w;
    let sig1 = mean - w;
    let mut vc = f32::new(1.0);
    let mut vs = f32::new(0.0);
    if w > f32::new(1e-12) {
        let mut a = s01;
        let mut b = w - tau;
        if tau >= f32::new(0.0) {
            a = w + tau;
            b = s01;
        }
        let inv = f32::new(1.0) / f32::sqrt(a * a + b * b);
        vc = a * inv;
        vs = b * inv;
    }
    // V = [vc, -vs, vs, vc]; U = R V.
    let u0 = rc * vc + -rs * vs;
    let u1 = rc * -vs + -rs * vc;
    let u2 = rs * vc + rc * vs;
    let u3 = rs * -vs + rc * vc;
    let s0 = f32::min(f32::max(sig0, lo), hi);
    let s1 = f32::min(f32::max(sig1, lo), hi);
    jp[p] = jp[p] * ((sig0 / s0) * (sig1 / s1));
    let (a0, a1, a2, a3) = (u0 * s0, u1 * s1, u2 * s0, u3 * s1);
    f[p * 4] = a0 * vc + a1 * -vs;
    f[p * 4 + 1] = a0 * vs + a1 * vc;
    f[p * 4 + 2] = a2 * vc + a3 * -vs;
    f[p * 4 + 3] = a2 * vs + a3 * vc;
}
