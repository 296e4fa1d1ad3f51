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
    s.view()
        .iter()
        .map(|&i| usize::try_from(i).ok().filter(|&i| i < rows))
        .collect()
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
