//! The grid model's sparse particle <-> grid transfers on the CPU (the CPU's
//! `NetOps::stencil_gather` / `NetOps::stencil_splat`): G2P as one weighted gather
//! (`out_p = sum_k w_pk grid[i_pk]`) and P2G as one weighted scatter-add
//! (`grid[i_pk] += w_pk v_p`).
//!
//! Why: burn-ndarray's `select` and `select_assign` (element by element through `IxDyn`
//! indices, with a `[B, N, 9, C]` intermediate) were 29 % of a grid step of a small model
//! (`perf` over `minflow eval`, U-Net width 16, grid 48).
//!
//! Shapes: `index` `[B N 9]` (flat rows `b n^2 + node` of a `[B n^2, C]` grid, particle-major),
//! `weight` `[B, N, 9]`, `grid` `[B, n^2, C]`, `values` `[B, N, C]`.

use burn::backend::ndarray::NdArrayTensor;
use burn::backend::NdArray;
use burn::tensor::ops::IntTensor;
use rayon::prelude::*;

use super::{dense, tensor, CpuTensor};
use crate::ops::STENCIL_NODES as NODES;

/// Particles per task of the parallel gather.
const PARTICLES_PER_TASK: usize = 256;

/// The stencil's flat node rows as `usize`, checked against `rows` (a damaged index would
/// otherwise write out of bounds). None for other dtypes or any row out of range.
fn rows_of(index: &IntTensor<NdArray<f32>>, rows: usize) -> Option<Vec<usize>> {
    let NdArrayTensor::I64(s) = index else {
        return None;
    };
    let row = |&i: &i64| usize::try_from(i).ok().filter(|&i| i < rows);
    let view = s.view();
    // A contiguous index as a slice: iterating the dynamic-rank view element by element was
    // 5 % of the full-size model's step.
    match view.as_slice() {
        Some(flat) => flat.iter().map(row).collect(),
        None => view.iter().map(row).collect(),
    }
}

/// The sparse stencil ([`NetOps::sparse_stencil`](crate::ops::NetOps::sparse_stencil)) of
/// `pos` `[B, N, 2]` on an `n x n` grid, one pass over the particles through
/// [`bspline_axis`]: `index` `[B N 9]` (i64) and `weight` `[B, N, 9]`. None for operands it
/// does not take (not f32 or not `[B, N, 2]`).
pub(crate) fn sparse_stencil(
    pos: &CpuTensor,
    n: usize,
) -> Option<(IntTensor<NdArray<f32>>, CpuTensor)> {
    let (pos, shape) = dense(pos)?;
    let &[b, particles, 2] = shape.as_slice() else {
        return None;
    };
    let mut index = Vec::with_capacity(b * particles * NODES);
    let mut weight = Vec::with_capacity(b * particles * NODES);
    for (p, xy) in pos.chunks_exact(2).enumerate() {
        let row = (p / particles * n * n) as i64;
        let ((bx, wx), (by, wy)) = (bspline_axis(xy[0], n), bspline_axis(xy[1], n));
        for k in 0..NODES {
            let (i, j) = (k / 3, k % 3);
            index.push(row + ((bx + i) * n + by + j) as i64);
            weight.push(wx[i] * wy[j]);
        }
    }
    let index = ndarray::ArrayD::from_shape_vec(ndarray::IxDyn(&[index.len()]), index)
        .expect("one index per node");
    Some((
        NdArrayTensor::from(index.into_shared()),
        tensor(weight, &[b, particles, NODES]),
    ))
}

/// Positions are clamped into `[lo, hi]` before their stencil is taken, so every node index
/// stays inside the grid: `lo = dx / 2`, `hi = 1 - 1.5 dx - 1e-5` (`dx = 1 / n`).
pub fn stencil_bounds(n: usize) -> (f32, f32) {
    let dx = 1.0 / n as f32;
    (0.5 * dx, 1.0 - 1.5 * dx - 1e-5)
}

/// One axis of MLS-MPM's quadratic B-spline stencil (Hu et al. 2018; Taichi's mpm99, as in
/// `sim::mpm`) for a coordinate `p` (domain units) on an `n`-node axis: the first node,
/// `floor(g - 0.5)` with `g = n clamp(p)`, and the weights ([`crate::bspline::weights`])
/// `[0.5 (1.5 - f)^2, 0.75 - (f - 1)^2, 0.5 (f - 0.5)^2]` of it and the next two, `f = g - base`.
pub fn bspline_axis(p: f32, n: usize) -> (usize, [f32; 3]) {
    let (lo, hi) = stencil_bounds(n);
    let g = p.clamp(lo, hi) * n as f32;
    let base = (g - 0.5).floor();
    let f = g - base;
    (base as usize, crate::bspline::weights(f))
}

/// CPU G2P: one task per block of particles, each output row a weighted sum of 9 grid rows.
/// None when the inputs are not f32 / i64 of the documented shapes.
pub(crate) fn gather(
    grid: &CpuTensor,
    index: &IntTensor<NdArray<f32>>,
    weight: &CpuTensor,
) -> Option<CpuTensor> {
    let (grid, gshape) = dense(grid)?;
    let (weight, wshape) = dense(weight)?;
    let (&[b, nodes, c], &[b2, n, NODES]) = (gshape.as_slice(), wshape.as_slice()) else {
        return None;
    };
    let rows = rows_of(index, b * nodes)?;
    if b2 != b || rows.len() != b * n * NODES {
        return None;
    }
    let mut out = vec![0f32; b * n * c];
    let fill = |p0: usize, dst: &mut [f32]| {
        for (q, dst) in dst.chunks_exact_mut(c).enumerate() {
            let p = p0 + q;
            for k in 0..NODES {
                let (w, src) = (weight[p * NODES + k], rows[p * NODES + k] * c);
                for (d, g) in dst.iter_mut().zip(&grid[src..src + c]) {
                    *d += w * g;
                }
            }
        }
    };
    if b * n > PARTICLES_PER_TASK {
        out.par_chunks_mut(PARTICLES_PER_TASK * c)
            .enumerate()
            .for_each(|(t, dst)| fill(t * PARTICLES_PER_TASK, dst));
    } else {
        fill(0, &mut out);
    }
    Some(tensor(out, &[b, n, c]))
}

/// CPU P2G: a scatter-add, one task per batch item (each writes only its own grid, in
/// particle order, so sums are deterministic). None when the inputs are not f32 / i64 of the
/// documented shapes or an index leaves its batch item's grid.
pub(crate) fn splat(
    values: &CpuTensor,
    index: &IntTensor<NdArray<f32>>,
    weight: &CpuTensor,
    nodes: usize,
) -> Option<CpuTensor> {
    let (values, vshape) = dense(values)?;
    let (weight, wshape) = dense(weight)?;
    let (&[b, n, c], &[b2, n2, NODES]) = (vshape.as_slice(), wshape.as_slice()) else {
        return None;
    };
    let rows = rows_of(index, b * nodes)?;
    if (b2, n2) != (b, n) || rows.len() != b * n * NODES {
        return None;
    }
    // Each batch item's rows must stay in its own grid for the per-item tasks.
    let own = rows
        .chunks(n * NODES)
        .enumerate()
        .all(|(bb, r)| r.iter().all(|&i| i / nodes == bb));
    if !own {
        return None;
    }
    let mut out = vec![0f32; b * nodes * c];
    out.par_chunks_mut(nodes * c.max(1))
        .enumerate()
        .for_each(|(bb, grid)| {
            for p in bb * n..(bb + 1) * n {
                let v = &values[p * c..(p + 1) * c];
                for k in 0..NODES {
                    let w = weight[p * NODES + k];
                    let dst = (rows[p * NODES + k] - bb * nodes) * c;
                    for (g, x) in grid[dst..dst + c].iter_mut().zip(v) {
                        *g += w * x;
                    }
                }
            }
        });
    Some(tensor(out, &[b, nodes, c]))
}
