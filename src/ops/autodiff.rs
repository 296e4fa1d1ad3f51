//! [`NetOps`] for burn's `Autodiff<B>`: each fused forward of the inner backend is recorded
//! as one node of the graph whose backward calls the inner backend's backward operation: a
//! dense layer (with ELU when fused) -> [`NetOps::linear_backward`], ELU ->
//! [`NetOps::elu_backward`], the pooled ELU -> [`NetOps::elu_mean_backward`] (or one
//! broadcast pass and [`NetOps::linear_backward`] where the activations are kept), the
//! recurrence -> [`NetOps::recurrence_backward`]. The grid model's nodes are in
//! `autodiff_grid.rs`. Where the inner backend has no kernel of its own (its `const` flags),
//! the operation is composed on `Autodiff<B>` itself, from burn's nodes.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{unary, Backward, Ops, OpsKind};
use burn::backend::Autodiff;
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::ops::{FloatTensor, IntTensor};
use burn::tensor::{Tensor, TensorPrimitive};

use super::composed::{composed_elu_mean, elu_slope, particle_mean};
use super::scan::log_scan_recurrence;
use super::{autodiff_grid, composed_grid, NetOps};

impl<B: NetOps, C: CheckpointStrategy> NetOps for Autodiff<B, C> {
    const ON_HOST: bool = B::ON_HOST;
    const FUSED_ELU_MEAN: bool = B::FUSED_ELU_MEAN;
    const NATIVE_CONV_OPS: bool = B::NATIVE_CONV_OPS;
    /// The inner backend's: training takes the transfers inference takes (on CUDA the sparse
    /// kernels, whose P2G sums in fixed point, so gradients are the same on every run).
    const DENSE_STENCIL: bool = B::DENSE_STENCIL;

    /// The inner backend's projection, its result a constant of the graph (training adds the
    /// move it makes to the prediction: a straight-through gradient).
    fn project_constraints(
        out: FloatTensor<Self>,
        input: Option<FloatTensor<Self>>,
        plan: &super::ProjectionPlan,
    ) -> Option<(FloatTensor<Self>, FloatTensor<Self>)> {
        let input = input.map(Self::inner);
        let (projected, moves) = B::project_constraints(Self::inner(out), input, plan)?;
        Some((Self::from_inner(projected), Self::from_inner(moves)))
    }

    fn projects_constraints() -> bool {
        B::projects_constraints()
    }

    fn dense_stencil() -> bool {
        B::dense_stencil()
    }

    fn im2col(x: FloatTensor<Self>, k: usize) -> FloatTensor<Self> {
        match B::NATIVE_CONV_OPS {
            true => autodiff_grid::autodiff_im2col::<B, C>(x, k),
            false => composed_grid::composed_im2col::<Self>(x, k),
        }
    }

    fn silu(x: FloatTensor<Self>) -> FloatTensor<Self> {
        match B::NATIVE_CONV_OPS {
            true => autodiff_grid::autodiff_silu::<B, C>(x),
            false => composed_grid::composed_silu::<Self>(x),
        }
    }

    fn im2col_linear(
        x: FloatTensor<Self>,
        matrix: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
        k: usize,
    ) -> FloatTensor<Self> {
        match B::NATIVE_CONV_OPS {
            true => autodiff_grid::autodiff_im2col_linear::<B, C>(x, matrix, bias, k),
            false => composed_grid::composed_im2col_linear::<Self>(x, matrix, bias, k),
        }
    }

    /// The inner backend's stencil of the detached positions (a constant of the graph, as
    /// `model::grid::transfer::composed_stencil` builds it), where it has one: on CUDA one
    /// kernel instead of ~25 tensor operations, on the CPU one pass.
    fn sparse_stencil(
        pos: &FloatTensor<Self>,
        n: usize,
    ) -> Option<(IntTensor<Self>, FloatTensor<Self>)> {
        let (index, weight) = B::sparse_stencil(&pos.primitive, n)?;
        Some((index, <Self as AutodiffBackend>::from_inner(weight)))
    }

    fn stencil_gather(
        grid: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        match B::NATIVE_CONV_OPS {
            true => autodiff_grid::autodiff_gather::<B, C>(grid, index, weight),
            false => composed_grid::composed_gather::<Self>(grid, index, weight),
        }
    }

    fn stencil_splat(
        values: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
        nodes: usize,
    ) -> FloatTensor<Self> {
        match B::NATIVE_CONV_OPS {
            true => autodiff_grid::autodiff_splat::<B, C>(values, index, weight, nodes),
            false => composed_grid::composed_splat::<Self>(values, index, weight, nodes),
        }
    }

    fn elu_mean_forward(
        x: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        if !B::FUSED_ELU_MEAN {
            // No recomputing kernel here: the node that keeps the activations.
            return Self::linear_elu_mean_forward(x, w, b);
        }
        let nodes = [x.node.clone(), w.node.clone(), b.node.clone()];
        match EluMeanBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let out = B::elu_mean_forward(
                    x.primitive.clone(),
                    w.primitive.clone(),
                    b.primitive.clone(),
                );
                prep.finish((x.primitive, w.primitive, b.primitive), out)
            }
            OpsKind::UnTracked(prep) => {
                prep.finish(B::elu_mean_forward(x.primitive, w.primitive, b.primitive))
            }
        }
    }

    fn recurrence(
        a: FloatTensor<Self>,
        b: FloatTensor<Self>,
        h0: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        if !B::ON_HOST {
            return log_scan_recurrence::<Self>(a, b, h0);
        }
        macro_rules! node {
            ($p:literal, $nodes:expr) => {
                match <RecurrenceBackward as Backward<B, $p>>::prepare::<C>(
                    RecurrenceBackward,
                    $nodes,
                )
                .compute_bound()
                .stateful()
                {
                    OpsKind::Tracked(prep) => {
                        let h0p = h0.as_ref().map(|h| h.primitive.clone());
                        let out =
                            B::recurrence(a.primitive.clone(), b.primitive.clone(), h0p.clone());
                        prep.finish((a.primitive.clone(), h0p, out.clone()), out)
                    }
                    OpsKind::UnTracked(prep) => prep.finish(B::recurrence(
                        a.primitive.clone(),
                        b.primitive.clone(),
                        h0.as_ref().map(|h| h.primitive.clone()),
                    )),
                }
            };
        }
        match &h0 {
            Some(h) => node!(3, [a.node.clone(), b.node.clone(), h.node.clone()]),
            None => node!(2, [a.node.clone(), b.node.clone()]),
        }
    }

    fn linear_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        linear_node::<B, C>(x, weight, bias, false)
    }

    fn linear_elu_mean_forward(
        x: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let nodes = [x.node.clone(), w.node.clone(), b.node.clone()];
        match LinearEluMeanBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let out = B::linear_elu_forward(
                    x.primitive.clone(),
                    w.primitive.clone(),
                    Some(b.primitive),
                );
                let pooled = particle_mean::<B>(out.clone());
                prep.finish((x.primitive, w.primitive, out), pooled)
            }
            OpsKind::UnTracked(prep) => prep.finish(composed_elu_mean::<B>(
                x.primitive,
                w.primitive,
                b.primitive,
            )),
        }
    }

    fn linear_elu_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        linear_node::<B, C>(x, weight, bias, true)
    }

    fn elu_forward(x: FloatTensor<Self>) -> FloatTensor<Self> {
        #[derive(Debug)]
        struct EluBackward;

        impl<B: NetOps> Backward<B, 1> for EluBackward {
            type State = FloatTensor<B>;

            fn backward(
                self,
                ops: Ops<Self::State, 1>,
                grads: &mut Gradients,
                _: &mut Checkpointer,
            ) {
                let out = ops.state;
                unary::<B, _>(ops.parents, ops.node, grads, |grad| {
                    B::elu_backward(out, grad)
                });
            }
        }

        match EluBackward
            .prepare::<C>([x.node.clone()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let out = B::elu_forward(x.primitive);
                prep.finish(out.clone(), out)
            }
            OpsKind::UnTracked(prep) => prep.finish(B::elu_forward(x.primitive)),
        }
    }
}

/// The backward node of a dense layer (`P` = 3 parents with a bias, 2 without): keeps the
/// input and the weight (and the output when ELU follows) and calls
/// [`NetOps::linear_backward`] of the inner backend.
#[derive(Debug)]
struct LinearBackward;

impl<B: NetOps, const P: usize> Backward<B, P> for LinearBackward {
    /// (input `[rows, in]`, weight `[in, out]`, ELU output `[rows, out]` when fused).
    type State = (FloatTensor<B>, FloatTensor<B>, Option<FloatTensor<B>>);

    fn backward(self, ops: Ops<Self::State, P>, grads: &mut Gradients, _: &mut Checkpointer) {
        let (x, weight, elu_out) = ops.state;
        let mut grad = grads.consume::<B>(&ops.node);
        if let Some(out) = elu_out {
            grad = B::elu_backward(out, grad);
        }
        let need = std::array::from_fn(|i| ops.parents.get(i).is_some_and(|p| p.is_some()));
        let parent_grads = B::linear_backward(x, weight, grad, need);
        for (parent, g) in ops.parents.into_iter().zip(parent_grads) {
            if let (Some(parent), Some(g)) = (parent, g) {
                grads.register::<B>(parent.id, g);
            }
        }
    }
}

/// Records `x @ weight + bias` (then ELU when `elu`) on the autodiff graph as one node.
fn linear_node<B: NetOps, C: CheckpointStrategy>(
    x: FloatTensor<Autodiff<B, C>>,
    weight: FloatTensor<Autodiff<B, C>>,
    bias: Option<FloatTensor<Autodiff<B, C>>>,
    elu: bool,
) -> FloatTensor<Autodiff<B, C>> {
    let inner = (x.primitive.clone(), weight.primitive.clone());
    match &bias {
        Some(b) => {
            linear_parents_node::<B, C, 3>([&x, &weight, b], inner, Some(b.primitive.clone()), elu)
        }
        None => linear_parents_node::<B, C, 2>([&x, &weight], inner, None, elu),
    }
}

/// [`linear_node`] with its `P` parents (`x`, the weight and, when there is one, the bias)
/// and their inner tensors.
fn linear_parents_node<B: NetOps, C: CheckpointStrategy, const P: usize>(
    parents: [&FloatTensor<Autodiff<B, C>>; P],
    (x, weight): (FloatTensor<B>, FloatTensor<B>),
    bias: Option<FloatTensor<B>>,
    elu: bool,
) -> FloatTensor<Autodiff<B, C>> {
    let forward = |x, w, b| {
        if elu {
            B::linear_elu_forward(x, w, b)
        } else {
            B::linear_forward(x, w, b)
        }
    };
    let nodes = parents.map(|t| t.node.clone());
    match <LinearBackward as Backward<B, P>>::prepare::<C>(LinearBackward, nodes)
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => {
            let out = forward(x.clone(), weight.clone(), bias);
            let keep = elu.then(|| out.clone());
            prep.finish((x, weight, keep), out)
        }
        OpsKind::UnTracked(prep) => prep.finish(forward(x, weight, bias)),
    }
}

/// The backward node of [`NetOps::linear_elu_mean_forward`]: keeps the input, the weight
/// and the ELU output `[M, N, W]` (before the mean).
#[derive(Debug)]
struct LinearEluMeanBackward;

impl<B: NetOps> Backward<B, 3> for LinearEluMeanBackward {
    type State = (FloatTensor<B>, FloatTensor<B>, FloatTensor<B>);

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _: &mut Checkpointer) {
        let (x, weight, out) = ops.state;
        let grad = grads.consume::<B>(&ops.node);
        let out = Tensor::<B, 3>::from_primitive(TensorPrimitive::Float(out));
        let [m, n, width] = out.dims();
        // One broadcast pass: `g / N` `[M, 1, W]` against the `[M, N, W]` output. (Expanding
        // `g` first and flattening both, as `elu_backward` does, copied the expanded
        // gradient out: a 2 GB copy per step at the paper's sizes.)
        let g = Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(grad))
            .div_scalar(n as f32)
            .reshape([m, 1, width]);
        let dz = (elu_slope(out) * g).into_primitive().tensor();
        let need = std::array::from_fn(|i| ops.parents[i].is_some());
        let parent_grads = B::linear_backward(x, weight, dz, need);
        for (parent, g) in ops.parents.into_iter().zip(parent_grads) {
            if let (Some(parent), Some(g)) = (parent, g) {
                grads.register::<B>(parent.id, g);
            }
        }
    }
}

/// The backward node of [`NetOps::recurrence`] (`P` = 3 parents with `h0`, 2 without).
#[derive(Debug)]
struct RecurrenceBackward;

impl<B: NetOps, const P: usize> Backward<B, P> for RecurrenceBackward {
    /// (`a`, `h0`, output `h`).
    type State = (FloatTensor<B>, Option<FloatTensor<B>>, FloatTensor<B>);

    fn backward(self, ops: Ops<Self::State, P>, grads: &mut Gradients, _: &mut Checkpointer) {
        let (a, h0, h) = ops.state;
        let grad = grads.consume::<B>(&ops.node);
        let parent_grads = B::recurrence_backward(a, h0, h, grad);
        for (parent, g) in ops.parents.into_iter().zip(parent_grads) {
            if let (Some(parent), Some(g)) = (parent, g) {
                grads.register::<B>(parent.id, g);
            }
        }
    }
}

/// The backward node of [`NetOps::elu_mean_forward`]: keeps `x`, `w`, `b`.
#[derive(Debug)]
struct EluMeanBackward;

impl<B: NetOps> Backward<B, 3> for EluMeanBackward {
    type State = (FloatTensor<B>, FloatTensor<B>, FloatTensor<B>);

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _: &mut Checkpointer) {
        let (x, w, b) = ops.state;
        let grad = grads.consume::<B>(&ops.node);
        let need = std::array::from_fn(|i| ops.parents[i].is_some());
        let parent_grads = B::elu_mean_backward(x, w, b, grad, need);
        for (parent, g) in ops.parents.into_iter().zip(parent_grads) {
            if let (Some(parent), Some(g)) = (parent, g) {
                grads.register::<B>(parent.id, g);
            }
        }
    }
}
