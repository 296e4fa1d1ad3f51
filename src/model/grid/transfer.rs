//! Particle <-> grid transfers of the grid architecture: the quadratic B-spline stencil of
//! each particle on an `n x n` grid, P2G (splat particle values onto grid nodes, summed) and
//! G2P (gather grid values back to each particle, weighted), as tensors on any burn backend
//! and differentiable in the values (the stencil itself is built from detached positions).
//!
//! The weights are MLS-MPM's (Hu et al. 2018; Taichi's mpm99, the same as `sim::mpm`):
//! `base = floor(x / dx - 0.5)`, `f = x / dx - base`,
//! `w = [0.5 (1.5 - f)^2, 0.75 - (f - 1)^2, 0.5 (f - 0.5)^2]` per axis, node `base + (i, j)`
//! for `i, j` in `0..3`, node `(i, j)` at `(i dx, j dx)`, `dx = 1 / n`. They sum to 1 for
//! every particle, so P2G conserves what it splats and G2P of a uniform field returns it
//! exactly. [`stencil_host`] is the same computation in plain f32 for tests.
//!
//! Two equal ways to apply a stencil ([`Stencil::dense`] picks; [`NetOps::dense_stencil`]
//! says which a backend takes):
//! - sparse, for the CPU and CUDA: the 9 node indices and weights of each particle, P2G a
//!   weighted scatter-add and G2P a weighted gather ([`ops::splat`], [`ops::gather`]: one
//!   pass each on the CPU, one kernel each on CUDA, `ops/cuda/net/stencil.rs`; burn's
//!   `select_assign` / `select` on other backends);
//! - separable dense, for accelerators without transfer kernels: the weights factor per
//!   axis, `w_ip = wx_p[i_x] wy_p[i_y]`, so with `Wx, Wy` (`[B, N, n]`, three non-zeros per
//!   row) P2G is `Wx^T (Wy (x) v)` and G2P `sum_y Wy (Wx G)`: two batched matrix products, no
//!   scatter. burn-cubecl's `select_assign` made a training step of a batch of 16 take over
//!   a second on an H100; the products take milliseconds, the CUDA kernels a tenth of that
//!   (`MINFLOW_CUDA_TRANSFERS=dense` takes the products there, to compare).

use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor, TensorData, TensorPrimitive};

use crate::ops::{self, NetOps};

/// The grid nodes and weights of every particle of a batch, sparse or separable dense.
#[derive(Clone, Debug)]
pub struct Stencil<B: Backend> {
    /// `[B N 9]`: flat node index `b n^2 + i n + j` into a `[B n^2, C]` grid (sparse form).
    pub index: Tensor<B, 1, Int>,
    /// `[B, N, 9]`: the weights (each particle's nine sum to 1; sparse form).
    pub weight: Tensor<B, 3>,
    /// `([B, N, n], [B, N, n])`: the per-axis weights `Wx, Wy` (dense form), if built.
    pub dense: Option<(Tensor<B, 3>, Tensor<B, 3>)>,
    /// Grid size n.
    pub n: usize,
    /// Batch size B.
    pub batch: usize,
    /// Particles N.
    pub particles: usize,
}

/// The stencil of positions `pos` (`[B, N, 2]`, domain units) on an `n x n` grid over the
/// unit square, in sparse form, and with `dense` also in separable dense form (then P2G and
/// G2P use that). Positions are clamped into the box MPM keeps its particles in, `[0.5 dx,
/// 1 - 1.5 dx)`, for the stencil only, so every stencil lies inside the grid (docs/mpm.md,
/// "Validation checks", check 6). Without `dense` the sparse form comes from
/// [`NetOps::sparse_stencil`] where the backend computes it (the CPU, one pass over the
/// particles); otherwise, and always with `dense`, from [`composed_stencil`].
pub fn stencil<B: NetOps>(pos: Tensor<B, 3>, n: usize, dense: bool) -> Stencil<B> {
    let [batch, particles, _] = pos.dims();
    if !dense {
        if let Some((index, weight)) = B::sparse_stencil(&pos.clone().into_primitive().tensor(), n)
        {
            return Stencil {
                index: Tensor::from_primitive(index),
                weight: Tensor::from_primitive(TensorPrimitive::Float(weight)),
                dense: None,
                n,
                batch,
                particles,
            };
        }
    }
    composed_stencil(pos, n, dense)
}

/// [`stencil`] in burn's tensor operations, on any backend.
pub fn composed_stencil<B: Backend>(pos: Tensor<B, 3>, n: usize, dense: bool) -> Stencil<B> {
    let [batch, particles, _] = pos.dims();
    let device = pos.device();
    let (lo, hi) = ops::stencil_bounds(n);
    let g = pos.detach().clamp(lo, hi).mul_scalar(n as f32); // [B, N, 2] in grid units
    let base = g.clone().sub_scalar(0.5).floor();
    let f = g - base.clone();
    let w0 = f
        .clone()
        .neg()
        .add_scalar(1.5)
        .powi_scalar(2)
        .mul_scalar(0.5);
    let w1 = f
        .clone()
        .sub_scalar(1.0)
        .powi_scalar(2)
        .neg()
        .add_scalar(0.75);
    let w2 = f.sub_scalar(0.5).powi_scalar(2).mul_scalar(0.5);
    let dense = dense.then(|| {
        // Wa[b, p, i] = w_k(f) where k = i - base is 0, 1 or 2, else 0, for axis a.
        let nodes = Tensor::<B, 1, Int>::arange(0..n as i64, &device)
            .float()
            .reshape([1, 1, n]);
        let axis = |a: usize| {
            let k = nodes.clone() - base.clone().narrow(2, a, 1); // [B, N, n]
            let pick = |at: f32, w: &Tensor<B, 3>| {
                k.clone().equal_elem(at).float() * w.clone().narrow(2, a, 1)
            };
            pick(0.0, &w0) + pick(1.0, &w1) + pick(2.0, &w2)
        };
        (axis(0), axis(1))
    });
    let w = Tensor::stack::<4>(vec![w0, w1, w2], 3); // [B, N, 2, 3]
    let wx = w.clone().narrow(2, 0, 1).reshape([batch, particles, 3, 1]);
    let wy = w.narrow(2, 1, 1).reshape([batch, particles, 1, 3]);
    let weight = (wx * wy).reshape([batch, particles, 9]);
    let base = base.int(); // [B, N, 2]
    let bx = base.clone().narrow(2, 0, 1);
    let by = base.narrow(2, 1, 1);
    let offsets: Vec<i32> = (0..9).map(|k| ((k / 3) * n + k % 3) as i32).collect();
    let offsets =
        Tensor::<B, 1, Int>::from_data(TensorData::new(offsets, [9]), &device).reshape([1, 1, 9]);
    let rows = Tensor::<B, 1, Int>::arange(0..batch as i64, &device)
        .mul_scalar((n * n) as i64)
        .reshape([batch, 1, 1]);
    let index = (bx.mul_scalar(n as i64) + by + rows) + offsets; // [B, N, 9]
    Stencil {
        index: index.reshape([batch * particles * 9]),
        weight,
        dense,
        n,
        batch,
        particles,
    }
}

/// P2G: `values` (`[B, N, C]`) splatted onto the grid, `sum_p w_ip v_p` per node, as
/// `[B, n^2, C]` (node `i n + j` at `(i dx, j dx)`).
pub fn p2g<B: NetOps>(s: &Stencil<B>, values: Tensor<B, 3>) -> Tensor<B, 3> {
    if let Some((wx, wy)) = &s.dense {
        let ([b, n_p, c], n) = (values.dims(), s.n);
        let spread = wy.clone().unsqueeze_dim::<4>(3) * values.unsqueeze_dim::<4>(2); // [B,N,n,C]
        return wx
            .clone()
            .swap_dims(1, 2)
            .matmul(spread.reshape([b, n_p, n * c]))
            .reshape([b, n * n, c]);
    }
    ops::splat(values, s.index.clone(), s.weight.clone(), s.n * s.n)
}

/// G2P: grid values (`[B, n^2, C]`) gathered to every particle, `sum_i w_ip g_i`, as
/// `[B, N, C]`.
pub fn g2p<B: NetOps>(s: &Stencil<B>, grid: Tensor<B, 3>) -> Tensor<B, 3> {
    if let Some((wx, wy)) = &s.dense {
        let ([b, _, c], n) = (grid.dims(), s.n);
        let rows = wx.clone().matmul(grid.reshape([b, n, n * c])); // [B, N, n C]
        return (rows.reshape([b, s.particles, n, c]) * wy.clone().unsqueeze_dim::<4>(3))
            .sum_dim(2)
            .reshape([b, s.particles, c]);
    }
    ops::gather(grid, s.index.clone(), s.weight.clone())
}

/// [`stencil`] for one particle at `(x, y)` in plain f32: the nine `(i, j, w)`.
pub fn stencil_host(x: f32, y: f32, n: usize) -> [(usize, usize, f32); 9] {
    let ((bx, wx), (by, wy)) = (ops::bspline_axis(x, n), ops::bspline_axis(y, n));
    std::array::from_fn(|k| {
        let (i, j) = (k / 3, k % 3);
        (bx + i, by + j, wx[i] * wy[j])
    })
}
