//! The grid architecture's sparse particle <-> grid transfers behind [`super::FusedElu`]:
//! G2P as one weighted gather (`out_p = sum_k w_pk grid[i_pk]`) and P2G as its adjoint, one
//! weighted scatter-add (`grid[i_pk] += w_pk v_p`), each the other's gradient (the stencil's
//! nodes and weights are constants: `model::grid::transfer` builds them from detached
//! positions). Here live the autodiff nodes and the single-pass CPU kernels; other backends
//! keep `model::grid::transfer`'s composed path (burn's `select` / `select_assign`, or the
//! separable dense products on accelerators).
//!
//! Why: on the CPU, burn-ndarray's `select` and `select_assign` (element by element through
//! `IxDyn` indices, with a `[B, N, 9, C]` intermediate) were 29 % of a grid step of a small
//! model (`perf` over `minflow eval`, U-Net width 16, grid 48).
//!
//! Shapes: `index` `[B N 9]` (flat rows `b n^2 + node` of a `[B n^2, C]` grid, particle-major),
//! `weight` `[B, N, 9]`, `grid` `[B, n^2, C]`, `values` `[B, N, C]`.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{unary, Backward, Ops, OpsKind};
use burn::backend::ndarray::NdArrayTensor;
use burn::backend::{Autodiff, NdArray};
use burn::tensor::ops::{FloatTensor, IntTensor};
use burn::tensor::{IndexingUpdateOp, Int, Tensor, TensorMetadata, TensorPrimitive};
use rayon::prelude::*;

use super::cpu_kernels::{self, CpuTensor};
use super::FusedElu;

/// Stencil nodes per particle (3 x 3, quadratic B-spline).
const NODES: usize = 9;

/// Particles per task of the parallel gather.
const PARTICLES_PER_TASK: usize = 256;

/// The autodiff node of [`FusedElu::stencil_gather`] (G2P): its backward is
/// [`FusedElu::stencil_splat`] of the output gradient onto the grid.
pub(crate) fn autodiff_gather<B: FusedElu, C: CheckpointStrategy>(
    grid: FloatTensor<Autodiff<B, C>>,
    index: IntTensor<B>,
    weight: FloatTensor<Autodiff<B, C>>,
) -> FloatTensor<Autodiff<B, C>> {
    #[derive(Debug)]
    struct GatherBackward;

    impl<B: FusedElu> Backward<B, 1> for GatherBackward {
        type State = (IntTensor<B>, FloatTensor<B>, usize);

        fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
            let (index, weight, nodes) = ops.state;
            unary::<B, _>(ops.parents, ops.node, grads, |grad| {
                B::stencil_splat(grad, index, weight, nodes)
            });
        }
    }

    let weight = weight.primitive;
    let nodes = grid.primitive.shape()[1];
    match GatherBackward
        .prepare::<C>([grid.node.clone()])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => {
            let out = B::stencil_gather(grid.primitive, index.clone(), weight.clone());
            prep.finish((index, weight, nodes), out)
        }
        OpsKind::UnTracked(prep) => prep.finish(B::stencil_gather(grid.primitive, index, weight)),
    }
}

/// The autodiff node of [`FusedElu::stencil_splat`] (P2G): its backward is
/// [`FusedElu::stencil_gather`] of the grid gradient.
pub(crate) fn autodiff_splat<B: FusedElu, C: CheckpointStrategy>(
    values: FloatTensor<Autodiff<B, C>>,
    index: IntTensor<B>,
    weight: FloatTensor<Autodiff<B, C>>,
    nodes: usize,
) -> FloatTensor<Autodiff<B, C>> {
    #[derive(Debug)]
    struct SplatBackward;

    impl<B: FusedElu> Backward<B, 1> for SplatBackward {
        type State = (IntTensor<B>, FloatTensor<B>);

        fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
            let (index, weight) = ops.state;
            unary::<B, _>(ops.parents, ops.node, grads, |grad| {
                B::stencil_gather(grad, index, weight)
            });
        }
    }

    let weight = weight.primitive;
    match SplatBackward
        .prepare::<C>([values.node.clone()])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => {
            let out = B::stencil_splat(values.primitive, index.clone(), weight.clone(), nodes);
            prep.finish((index, weight), out)
        }
        OpsKind::UnTracked(prep) => {
            prep.finish(B::stencil_splat(values.primitive, index, weight, nodes))
        }
    }
}

/// Composed G2P: burn's row gather of the 9 nodes, weighted and summed.
pub(crate) fn composed_gather<B: FusedElu>(
    grid: FloatTensor<B>,
    index: IntTensor<B>,
    weight: FloatTensor<B>,
) -> FloatTensor<B> {
    let grid = Tensor::<B, 3>::from_primitive(TensorPrimitive::Float(grid));
    let weight = Tensor::<B, 3>::from_primitive(TensorPrimitive::Float(weight));
    let ([b, nodes, c], [_, n, _]) = (grid.dims(), weight.dims());
    let picked = grid
        .reshape([b * nodes, c])
        .select(0, Tensor::<B, 1, Int>::from_primitive(index))
        .reshape([b, n, NODES, c]);
    (picked * weight.unsqueeze_dim::<4>(3))
        .sum_dim(2)
        .reshape([b, n, c])
        .into_primitive()
        .tensor()
}

/// Composed P2G: burn's row scatter-add of the weighted values onto a zero grid.
pub(crate) fn composed_splat<B: FusedElu>(
    values: FloatTensor<B>,
    index: IntTensor<B>,
    weight: FloatTensor<B>,
    nodes: usize,
) -> FloatTensor<B> {
    let values = Tensor::<B, 3>::from_primitive(TensorPrimitive::Float(values));
    let weight = Tensor::<B, 3>::from_primitive(TensorPrimitive::Float(weight));
    let [b, n, c] = values.dims();
    let spread = weight.unsqueeze_dim::<4>(3) * values.unsqueeze_dim::<4>(2); // [B, N, 9, C]
    Tensor::<B, 2>::zeros([b * nodes, c], &spread.device())
        .select_assign(
            0,
            Tensor::<B, 1, Int>::from_primitive(index),
            spread.reshape([b * n * NODES, c]),
            IndexingUpdateOp::Add,
        )
        .reshape([b, nodes, c])
        .into_primitive()
        .tensor()
}

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
pub(crate) fn cpu_gather(
    grid: &CpuTensor,
    index: &IntTensor<NdArray<f32>>,
    weight: &CpuTensor,
) -> Option<CpuTensor> {
    let (grid, gshape) = cpu_kernels::dense(grid)?;
    let (weight, wshape) = cpu_kernels::dense(weight)?;
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
    Some(cpu_kernels::tensor(out, &[b, n, c]))
}

/// CPU P2G: a scatter-add, one task per batch item (each writes only its own grid, in
/// particle order, so sums are deterministic). None when the inputs are not f32 / i64 of the
/// documented shapes or an index leaves its batch item's grid.
pub(crate) fn cpu_splat(
    values: &CpuTensor,
    index: &IntTensor<NdArray<f32>>,
    weight: &CpuTensor,
    nodes: usize,
) -> Option<CpuTensor> {
    let (values, vshape) = cpu_kernels::dense(values)?;
    let (weight, wshape) = cpu_kernels::dense(weight)?;
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
    Some(cpu_kernels::tensor(out, &[b, nodes, c]))
}

/// G2P through [`FusedElu::stencil_gather`]: `grid` `[B, n^2, C]` -> `[B, N, C]`.
pub fn gather<B: FusedElu>(
    grid: Tensor<B, 3>,
    index: Tensor<B, 1, Int>,
    weight: Tensor<B, 3>,
) -> Tensor<B, 3> {
    let out = B::stencil_gather(
        grid.into_primitive().tensor(),
        index.into_primitive(),
        weight.into_primitive().tensor(),
    );
    Tensor::from_primitive(TensorPrimitive::Float(out))
}

/// P2G through [`FusedElu::stencil_splat`]: `values` `[B, N, C]` -> `[B, nodes, C]`.
pub fn splat<B: FusedElu>(
    values: Tensor<B, 3>,
    index: Tensor<B, 1, Int>,
    weight: Tensor<B, 3>,
    nodes: usize,
) -> Tensor<B, 3> {
    let out = B::stencil_splat(
        values.into_primitive().tensor(),
        index.into_primitive(),
        weight.into_primitive().tensor(),
        nodes,
    );
    Tensor::from_primitive(TensorPrimitive::Float(out))
}
