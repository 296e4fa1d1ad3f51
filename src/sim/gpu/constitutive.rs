//! Per-particle pieces of the GPU solver's kernels (`kernels.rs`), as `#[cube]` functions:
//! the B-spline weights and stencil base, the Kirchhoff stress (the liquid's pressure, each
//! material's hardening, the polar rotation), and the `F` update with the plastic projection
//! (snow's through the signed 2 x 2 SVD). Each is the GPU form
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
fn liquid_pressure(j: f32, lambda0: f32) -> f32 {
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
fn hardening(material: u32, jp: f32) -> f32 {
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

/// The rotation `R = [[rc, -rs], [rs, rc]]` of the polar decomposition of `F` (row-major
/// `f0..f3`) into `r` `[rc, rs]` ([`crate::sim::linalg::polar_rotation`]: `(rc, rs)` along
/// `(F00 + F11, F10 - F01)`, the identity where both vanish).
#[cube]
fn polar_rotation(f0: f32, f1: f32, f2: f32, f3: f32, r: &mut Array<f32>) {
    let px = f0 + f3;
    let py = f2 - f1;
    let norm2 = px * px + py * py;
    r[0] = f32::new(1.0);
    r[1] = f32::new(0.0);
    if norm2 > f32::new(1.175_494_4e-38) {
        let inv = f32::new(1.0) / f32::sqrt(norm2);
        r[0] = px * inv;
        r[1] = py * inv;
    }
}

/// Snow's plastic projection ([`crate::sim::material::project`], material 2) of `F` (row-major
/// in `f`): the signed SVD (`linalg::svd`: polar rotation, then the symmetric factor's
/// closed-form eigenvectors), singular values clamped into `[lo, hi]`, the clamped-off volume
/// change multiplied into `jp[p]`; `f` rewritten as `U diag(clamped) V^T`.
#[cube]
fn snow_project(f: &mut Array<f32>, jp: &mut Array<f32>, p: usize, lo: f32, hi: f32) {
    let (f0, f1, f2, f3) = (f[p * 4], f[p * 4 + 1], f[p * 4 + 2], f[p * 4 + 3]);
    let mut r = Array::<f32>::new(2usize);
    polar_rotation(f0, f1, f2, f3, &mut r);
    let (rc, rs) = (r[0], r[1]);
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

/// The Kirchhoff stress of particle `p` (`f` row-major, its `jp` and `material`) into `tau`
/// `[5]`: `tau` row-major, then the stiffness `k` of the substep's stability bound
/// ([`crate::sim::material::kirchhoff_stress`]: liquid `p(J) I` with `k = lambda0 max(2 J -
/// 1, 1)`; the solids fixed-corotated with the polar rotation, hardened, `k = lambda + 2 mu`,
/// snow's 0).
#[cube]
#[allow(unused_assignments)]
pub(super) fn kirchhoff(
    f: &Array<f32>,
    jp: f32,
    p: usize,
    m: u32,
    mu0: f32,
    lambda0: f32,
    tau: &mut Array<f32>,
) {
    let (f0, f1, f2, f3) = (f[p * 4], f[p * 4 + 1], f[p * 4 + 2], f[p * 4 + 3]);
    let j = f0 * f3 - f1 * f2;
    let mut t0 = f32::new(0.0);
    let mut t1 = f32::new(0.0);
    let mut t2 = f32::new(0.0);
    let mut t3 = f32::new(0.0);
    let mut k = f32::new(0.0);
    if m == 0 {
        let pr = liquid_pressure(j, lambda0);
        t0 = pr;
        t3 = pr;
        let mut g = f32::new(2.0) * j - f32::new(1.0);
        if g < f32::new(1.0) {
            g = f32::new(1.0);
        }
        k = lambda0 * g;
    } else {
        let hard = hardening(m, jp);
        let mu = mu0 * hard;
        let la = lambda0 * hard;
        if m != 2 {
            k = la + f32::new(2.0) * mu;
        }
        let mut r = Array::<f32>::new(2usize);
        polar_rotation(f0, f1, f2, f3, &mut r);
        let (rc, rs) = (r[0], r[1]);
        let (d0, d1, d2, d3) = (f0 - rc, f1 + rs, f2 - rs, f3 - rc);
        let pj = la * j * (j - f32::new(1.0));
        let mu2 = f32::new(2.0) * mu;
        t0 = mu2 * (d0 * f0 + d1 * f1) + pj;
        t1 = mu2 * (d0 * f2 + d1 * f3);
        t2 = mu2 * (d2 * f0 + d3 * f1);
        t3 = mu2 * (d2 * f2 + d3 * f3) + pj;
    }
    tau[0] = t0;
    tau[1] = t1;
    tau[2] = t2;
    tau[3] = t3;
    tau[4] = k;
}

/// `F <- (I + h C) F` for particle `p` (`f` row-major, `C` in `cm`), in `m` equal steps when
/// `h |C|_F > 0.25` (`mpm::update_deformation`), then the plastic projection of its
/// `material` (`material::project`: liquid `diag(max(J, j_min), 1)`, snow
/// [`snow_project`] with the clamp `[snow_lo, snow_hi]`).
#[cube]
#[allow(clippy::too_many_arguments)]
pub(super) fn deform(
    f: &mut Array<f32>,
    jp: &mut Array<f32>,
    p: usize,
    m: u32,
    cm: &Array<f32>,
    h: f32,
    snow_lo: f32,
    snow_hi: f32,
    j_min: f32,
) {
    let (c0, c1, c2, c3) = (cm[0], cm[1], cm[2], cm[3]);
    // F <- (I + h C) F, in equal steps when one would be too large (`update_deformation`).
    let norm2 = h * h * (c0 * c0 + c1 * c1 + c2 * c2 + c3 * c3);
    let mut steps = 1u32;
    if norm2 > f32::new(0.0625) {
        let want = f32::ceil(f32::sqrt(norm2) / f32::new(0.25));
        steps = 1024u32;
        if want < f32::new(1024.0) {
            steps = u32::cast_from(want);
        }
    }
    let hh = h / f32::cast_from(steps);
    let (s0, s1, s2, s3) = (
        f32::new(1.0) + hh * c0,
        hh * c1,
        hh * c2,
        f32::new(1.0) + hh * c3,
    );
    let mut o0 = f[p * 4];
    let mut o1 = f[p * 4 + 1];
    let mut o2 = f[p * 4 + 2];
    let mut o3 = f[p * 4 + 3];
    for _ in 0..steps {
        let (n0, n1) = (s0 * o0 + s1 * o2, s0 * o1 + s1 * o3);
        let (n2, n3) = (s2 * o0 + s3 * o2, s2 * o1 + s3 * o3);
        o0 = n0;
        o1 = n1;
        o2 = n2;
        o3 = n3;
    }
    if m == 0 {
        let mut jj = o0 * o3 - o1 * o2;
        // `max(J, j_min)` that also takes a NaN J to `j_min`, as the CPU's `f32::max`.
        #[allow(clippy::neg_cmp_op_on_partial_ord)]
        if !(jj >= j_min) {
            jj = j_min;
        }
        o0 = jj;
        o1 = f32::new(0.0);
        o2 = f32::new(0.0);
        o3 = f32::new(1.0);
    }
    f[p * 4] = o0;
    f[p * 4 + 1] = o1;
    f[p * 4 + 2] = o2;
    f[p * 4 + 3] = o3;
    if m == 2 {
        snow_project(f, jp, p, snow_lo, snow_hi);
    }
}
