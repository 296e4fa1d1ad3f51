//! The autodiff nodes of the grid model's operations, on backends with native kernels for
//! them ([`NetOps::NATIVE_CONV_OPS`]): im2col, whose backward is [`NetOps::col2im`]; a
//! convolution's im2col and product as one node that keeps the input, not the columns
//! ([`NetOps::im2col_linear`]); SiLU,
//! whose backward is [`NetOps::silu_backward`] of the kept input; and the stencil transfers,
//! each the other's gradient (G2P's backward is P2G of the output gradient, and P2G's is G2P;
//! the stencil's nodes and weights are constants, so no gradient flows to them).

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{unary, Backward, Ops, OpsKind};
use burn::backend::Autodiff;
use burn::tensor::ops::{FloatTensor, IntTensor};
use burn::tensor::TensorMetadata;

use super::composed_grid::dims4;
use super::NetOps;

/// The autodiff node of [`NetOps::im2col`] on backends with native kernels: its backward
/// is [`NetOps::col2im`].
pub(crate) fn autodiff_im2col<B: NetOps, C: CheckpointStrategy>(
    x: FloatTensor<Autodiff<B, C>>,
    k: usize,
) -> FloatTensor<Autodiff<B, C>> {
    #[derive(Debug)]
    struct Im2colBackward;

    impl<B: NetOps> Backward<B, 1> for Im2colBackward {
        type State = ([usize; 4], usize);

        fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
            let (shape, k) = ops.state;
            unary::<B, _>(ops.parents, ops.node, grads, |grad| {
                B::col2im(grad, shape, k)
            });
        }
    }

    let shape = dims4::<B>(&x.primitive);
    match Im2colBackward
        .prepare::<C>([x.node.clone()])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => prep.finish((shape, k), B::im2col(x.primitive, k)),
        OpsKind::UnTracked(prep) => prep.finish(B::im2col(x.primitive, k)),
    }
}

/// The backward of [`NetOps::im2col_linear`] (`P` = 3 parents with a bias, 2 without): keeps
/// the input `x` and the matrix, not the columns; the gradients come from
/// [`NetOps::im2col_linear_backward`] (by default the columns recomputed, then
/// [`NetOps::linear_backward`] and [`NetOps::col2im`]).
#[derive(Debug)]
struct Im2colLinearBackward;

impl<B: NetOps, const P: usize> Backward<B, P> for Im2colLinearBackward {
    /// (input `[B, H, W, C]`, matrix `[C k^2, C_out]`, k).
    type State = (FloatTensor<B>, FloatTensor<B>, usize);

    fn backward(self, ops: Ops<Self::State, P>, grads: &mut Gradients, _: &mut Checkpointer) {
        let (x, matrix, k) = ops.state;
        let grad = grads.consume::<B>(&ops.node);
        let need = std::array::from_fn(|i| ops.parents.get(i).is_some_and(|p| p.is_some()));
        let parent_grads = B::im2col_linear_backward(x, matrix, grad, k, need);
        for (parent, g) in ops.parents.into_iter().zip(parent_grads) {
            if let (Some(parent), Some(g)) = (parent, g) {
                grads.register::<B>(parent.id, g);
            }
        }
    }
}

/// The autodiff node of [`NetOps::im2col_linear`] on backends with native kernels: one node
/// that keeps `x`, not its columns.
pub(crate) fn autodiff_im2col_linear<B: NetOps, C: CheckpointStrategy>(
    x: FloatTensor<Autodiff<B, C>>,
    matrix: FloatTensor<Autodiff<B, C>>,
    bias: Option<FloatTensor<Autodiff<B, C>>>,
    k: usize,
) -> FloatTensor<Autodiff<B, C>> {
    let inner = (x.primitive.clone(), matrix.primitive.clone());
    match &bias {
        Some(b) => {
            im2col_linear_node::<B, C, 3>([&x, &matrix, b], inner, Some(b.primitive.clone()), k)
        }
        None => im2col_linear_node::<B, C, 2>([&x, &matrix], inner, None, k),
    }
}

/// [`autodiff_im2col_linear`] with its `P` parents (`x`, the matrix and, when there is one,
/// the bias) and their inner tensors.
fn im2col_linear_node<B: NetOps, C: CheckpointStrategy, const P: usize>(
    parents: [&FloatTensor<Autodiff<B, C>>; P],
    (x, matrix): (FloatTensor<B>, FloatTensor<B>),
    bias: Option<FloatTensor<B>>,
    k: usize,
) -> FloatTensor<Autodiff<B, C>> {
    let nodes = parents.map(|t| t.node.clone());
    match <Im2colLinearBackward as Backward<B, P>>::prepare::<C>(Im2colLinearBackward, nodes)
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => {
            let out = B::im2col_linear(x.clone(), matrix.clone(), bias, k);
            prep.finish((x, matrix, k), out)
        }
        OpsKind::UnTracked(prep) => prep.finish(B::im2col_linear(x, matrix, bias, k)),
    }
}

/// The autodiff node of [`NetOps::silu`]: keeps the input.
pub(crate) fn autodiff_silu<B: NetOps, C: CheckpointStrategy>(
    x: FloatTensor<Autodiff<B, C>>,
) -> FloatTensor<Autodiff<B, C>> {
    #[derive(Debug)]
    struct SiluBackward;

    impl<B: NetOps> Backward<B, 1> for SiluBackward {
        type State = FloatTensor<B>;

        fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
            let x = ops.state;
            unary::<B, _>(ops.parents, ops.node, grads, |grad| {
                B::silu_backward(x, grad)
            });
        }
    }

    match SiluBackward
        .prepare::<C>([x.node.clone()])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => {
            let out = B::silu(x.primitive.clone());
            prep.finish(x.primitive, out)
        }
        OpsKind::UnTracked(prep) => prep.finish(B::silu(x.primitive)),
    }
}

/// The autodiff node of [`NetOps::stencil_gather`] (G2P): its backward is
/// [`NetOps::stencil_splat`] of the output gradient onto the grid.
pub(crate) fn autodiff_gather<B: NetOps, C: CheckpointStrategy>(
    grid: FloatTensor<Autodiff<B, C>>,
    index: IntTensor<B>,
    weight: FloatTensor<Autodiff<B, C>>,
) -> FloatTensor<Autodiff<B, C>> {
    #[derive(Debug)]
    struct GatherBackward;

    impl<B: NetOps> Backward<B, 1> for GatherBackward {
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

/// The autodiff node of [`NetOps::stencil_splat`] (P2G): its backward is
/// [`NetOps::stencil_gather`] of the grid gradient.
pub(crate) fn autodiff_splat<B: NetOps, C: CheckpointStrategy>(
    values: FloatTensor<Autodiff<B, C>>,
    index: IntTensor<B>,
    weight: FloatTensor<Autodiff<B, C>>,
    nodes: usize,
) -> FloatTensor<Autodiff<B, C>> {
    #[derive(Debug)]
    struct SplatBackward;

    impl<B: NetOps> Backward<B, 1> for SplatBackward {
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
