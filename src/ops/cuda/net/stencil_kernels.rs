//! The cubecl kernels of the sparse particle-grid transfers on CUDA (feature `cuda`): the
//! stencil ([`stencil_kernel`]), G2P ([`gather_kernel`]) and P2G in 64-bit fixed point
//! ([`clear_kernel`], [`splat_kernel`], [`unfix_kernel`]). `cuda/net/stencil.rs` records and
//! launches them; why they are written this way is its module doc.

use burn_cubecl::cubecl;
use cubecl::prelude::*;

/// G2P: `out[p, j] = sum_k weight[p, k] grid[index[p, k], j]` for every particle `p` of the
/// batch (`B N` of them) and channel `j < c`; `grid` `[B n^2, c]`, `index` and `weight`
/// `[B N, 9]`, `out` `[B N, c]`, all contiguous. One thread per output element.
#[cube(launch)]
pub(in crate::ops) fn gather_kernel<F: Float>(
    grid: &Tensor<F>,
    index: &Tensor<i32>,
    weight: &Tensor<F>,
    out: &mut Tensor<F>,
    c: u32,
    #[define(F)] _dtype: StorageType,
) {
    if ABSOLUTE_POS >= out.len() {
        terminate!();
    }
    let c = c as usize;
    let p = ABSOLUTE_POS / c;
    let j = ABSOLUTE_POS % c;
    let mut acc = F::new(0.0);
    #[unroll]
    for k in 0..9 {
        let row = usize::cast_from(index[p * 9 + k]);
        acc += weight[p * 9 + k] * grid[row * c + j];
    }
    out[ABSOLUTE_POS] = acc;
}

/// One axis of MLS-MPM's quadratic B-spline at distance `x` (grid units) from a node: `0.75 -
/// x^2` within 0.5, `0.5 (1.5 - |x|)^2` within 1.5, else 0 (Hu et al. 2018; the GPU form of
/// [`crate::bspline::weights`], which the CPU sites share, at distances `f`, `f - 1`, `f - 2`;
/// a `#[cube]` function cannot call it).
#[cube]
pub(in crate::ops) fn bspline<F: Float>(x: F) -> F {
    let a = F::abs(x);
    let mut w = F::new(0.0);
    if a < F::new(0.5) {
        w = F::new(0.75) - a * a;
    } else if a < F::new(1.5) {
        let d = F::new(1.5) - a;
        w = F::new(0.5) * d * d;
    }
    w
}

/// The sparse stencil of every particle (as `ops::cpu::transfer::sparse_stencil`): `pos`
/// `[B N, 2]` (domain units, contiguous), clamped into `[dx / 2, 1 - 1.5 dx - 1e-5]`, ->
/// `index` `[B N 9]` (flat rows `b n^2 + (bx + i) n + by + j` for node `k = 3 i + j`) and
/// `weight` `[B N 9]`. One thread per particle; `particles` = N, `n` the grid size.
#[cube(launch)]
pub(in crate::ops) fn stencil_kernel<F: Float>(
    pos: &Tensor<F>,
    index: &mut Tensor<i32>,
    weight: &mut Tensor<F>,
    particles: u32,
    n: u32,
    #[define(F)] _dtype: StorageType,
) {
    if ABSOLUTE_POS * 9 >= weight.len() {
        terminate!();
    }
    let p = ABSOLUTE_POS;
    let nn = n as usize;
    let b = p / (particles as usize);
    let nf = F::cast_from(n);
    let dx = F::new(1.0) / nf;
    let lo = F::new(0.5) * dx;
    let hi = F::new(1.0) - F::new(1.5) * dx - F::new(0.00001);
    let mut x = pos[p * 2];
    let mut y = pos[p * 2 + 1];
    if x < lo {
        x = lo;
    }
    if x > hi {
        x = hi;
    }
    if y < lo {
        y = lo;
    }
    if y > hi {
        y = hi;
    }
    let (gx, gy) = (x * nf, y * nf);
    let (bx, by) = (F::floor(gx - F::new(0.5)), F::floor(gy - F::new(0.5)));
    let (fx, fy) = (gx - bx, gy - by);
    let row = b * nn * nn + usize::cast_from(bx) * nn + usize::cast_from(by);
    #[unroll]
    for k in 0..9usize {
        let i = k / 3;
        let j = k % 3;
        index[p * 9 + k] = i32::cast_from(row + i * nn + j);
        weight[p * 9 + k] = bspline::<F>(fx - F::cast_from(i)) * bspline::<F>(fy - F::cast_from(j));
    }
}

/// The fixed-point scale of P2G's deterministic sum: `2^61 / (count max)`, so that a node's
/// sum of at most `count` contributions of at most `max` each stays below `2^61` (an `i64`
/// holds `2^63`); 1 where `max` is 0. An infinite `max` gives 0 (the output is then NaN).
#[cube]
fn fixed_scale<F: Float>(max: F, count: u32) -> F {
    let mut s = F::new(1.0);
    if max > F::new(0.0) {
        s = F::new(2305843009213693952.0) / (F::cast_from(count) * max);
    }
    s
}

/// P2G, the adjoint of [`gather_kernel`]: `acc[index[p, k], j] += weight[p, k] values[p, j]`
/// in 64-bit fixed point: `values` `[B N, c]`, `index` and `weight` `[B N, 9]`, `max` `[1]`
/// (the largest `|value|`), `acc` `[B n^2, c]` zeroed first; `count` = `B N` bounds the
/// contributions to a node. One thread per value, nine atomic integer adds each.
///
/// Integer addition is associative, so the sum does not depend on the order the atomics land
/// in: the result is the same to the bit on every run, which f32 atomics are not (the
/// fixed-point accumulation of GPU molecular dynamics: Le Grand, Götz and Walker 2013,
/// "SPFP: Speed without compromise", Comput. Phys. Commun. 184). Each contribution is
/// truncated to `1 / scale` = `2^-61 count max`, about `3e-13 max` at 256 scenes of 2,500
/// particles, far below f32's rounding of the sum.
#[cube(launch)]
pub(in crate::ops) fn splat_kernel<F: Float>(
    values: &Tensor<F>,
    index: &Tensor<i32>,
    weight: &Tensor<F>,
    max: &Tensor<F>,
    acc: &mut Tensor<Atomic<i64>>,
    c: u32,
    count: u32,
    #[define(F)] _dtype: StorageType,
) {
    if ABSOLUTE_POS >= values.len() {
        terminate!();
    }
    let c = c as usize;
    let p = ABSOLUTE_POS / c;
    let j = ABSOLUTE_POS % c;
    let v = values[ABSOLUTE_POS] * fixed_scale::<F>(max[0], count);
    #[unroll]
    for k in 0..9 {
        let row = usize::cast_from(index[p * 9 + k]);
        acc[row * c + j].fetch_add(i64::cast_from(weight[p * 9 + k] * v));
    }
}

/// `acc[i] = 0` for every element of a contiguous `acc`: P2G's sums before their atomic adds.
/// (burn-cubecl's `zeros_client` allocates through the runtime's layout policy, which on CUDA
/// pitches each innermost row to a power of two bytes: `[B, n^2, 12]` gets row stride 16,
/// not 12, and [`splat_kernel`]'s flat `row * c + j` would land in the wrong rows.)
#[cube(launch)]
pub(in crate::ops) fn clear_kernel(acc: &mut Tensor<i64>) {
    if ABSOLUTE_POS >= acc.len() {
        terminate!();
    }
    acc[ABSOLUTE_POS] = i64::new(0);
}

/// P2G's output from its fixed-point sums: `out[i] = acc[i] / scale` (f32); NaN everywhere
/// when `max` is not finite (a NaN or infinite value went in).
#[cube(launch)]
pub(in crate::ops) fn unfix_kernel<F: Float>(
    acc: &Tensor<i64>,
    max: &Tensor<F>,
    out: &mut Tensor<F>,
    count: u32,
    #[define(F)] _dtype: StorageType,
) {
    if ABSOLUTE_POS >= out.len() {
        terminate!();
    }
    let m = max[0];
    let mut v = F::cast_from(acc[ABSOLUTE_POS]) / fixed_scale::<F>(m, count);
    // A NaN largest value (the only value unequal to itself) is passed on as NaN.
    #[allow(clippy::eq_op)]
    if m != m {
        v = m;
    }
    out[ABSOLUTE_POS] = v;
}
