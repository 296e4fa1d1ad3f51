//! A fused ELU (`x` for `x > 0`, `exp(x) - 1` otherwise; Clevert et al. 2016) through burn's
//! backend extension: burn composes ELU from five passes (compare, exp, sub, mul, select)
//! with boolean masks, which cost most of the paper configuration's training time on the
//! CPU. Here the forward is one pass, and the autodiff node keeps only the output, since
//! `d ELU / dx = 1` where the output is positive and `output + 1` elsewhere.
//!
//! [`FusedElu`] has composed default methods, so any backend can opt in with an empty impl;
//! `NdArray<f32>` overrides them with single-pass loops (parallel over chunks), and
//! `Autodiff<B>` records one backward node. burn's CUDA backend (feature `cuda`) takes the
//! composed defaults: its fusion layer compiles the element-wise chain into one kernel. Used by the encoder, the core's MLPs and the
//! pointwise decoder.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{unary, Backward, Ops, OpsKind};
use burn::backend::{Autodiff, NdArray};
use burn::tensor::backend::Backend;
use burn::tensor::ops::{FloatTensor, FloatTensorOps};
use burn::tensor::{Tensor, TensorData, TensorMetadata, TensorPrimitive};
use rayon::prelude::*;

/// A backend with a fused ELU (alpha = 1).
pub trait FusedElu: Backend {
    /// `elu(x)`, any shape.
    fn elu_forward(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let shape = x.shape();
        let n = shape.num_elements();
        let flat = Tensor::<Self, 1>::from_primitive(TensorPrimitive::Float(Self::float_reshape(
            x,
            [n].into(),
        )));
        let y = burn::tensor::activation::elu(flat, 1.0)
            .into_primitive()
            .tensor();
        Self::float_reshape(y, shape)
    }

    /// The input gradient from the forward output and the output gradient.
    fn elu_backward(out: FloatTensor<Self>, grad: FloatTensor<Self>) -> FloatTensor<Self> {
        let shape = out.shape();
        let n = shape.num_elements();
        let flat = |t| {
            Tensor::<Self, 1>::from_primitive(TensorPrimitive::Float(Self::float_reshape(
                t,
                [n].into(),
            )))
        };
        let (out, grad) = (flat(out), flat(grad));
        let positive = out.clone().greater_elem(0.0);
        let slope = (out + 1.0).mask_fill(positive, 1.0);
        Self::float_reshape((grad * slope).into_primitive().tensor(), shape)
    }
}

/// Applies `f` to every element of a CPU tensor in one pass (2 threads: chunks in parallel).
fn map_cpu(
    x: FloatTensor<NdArray<f32>>,
    f: impl Fn(f32) -> f32 + Sync,
) -> FloatTensor<NdArray<f32>> {
    let shape = x.shape();
    let device = Default::default();
    let t = Tensor::<NdArray<f32>, 1>::from_primitive(TensorPrimitive::Float(x))
        .reshape([shape.num_elements()]);
    let mut v: Vec<f32> = t.into_data().into_vec().unwrap_or_default();
    v.par_chunks_mut(1 << 16)
        .for_each(|c| c.iter_mut().for_each(|e| *e = f(*e)));
    let y =
        Tensor::<NdArray<f32>, 1>::from_data(TensorData::new(v, [shape.num_elements()]), &device);
    NdArray::<f32>::float_reshape(y.into_primitive().tensor(), shape)
}

impl FusedElu for NdArray<f32> {
    fn elu_forward(x: FloatTensor<Self>) -> FloatTensor<Self> {
        map_cpu(x, |v| if v > 0.0 { v } else { v.exp_m1() })
    }

    fn elu_backward(out: FloatTensor<Self>, grad: FloatTensor<Self>) -> FloatTensor<Self> {
        let shape = out.shape();
        let n = shape.num_elements();
        let device = Default::default();
        let vec = |t| {
            Tensor::<NdArray<f32>, 1>::from_primitive(TensorPrimitive::Float(t))
                .reshape([n])
                .into_data()
                .into_vec::<f32>()
                .unwrap_or_default()
        };
        let out = vec(out);
        let mut grad = vec(grad);
        grad.par_chunks_mut(1 << 16)
            .zip(out.par_chunks(1 << 16))
            .for_each(|(g, o)| {
                for (g, &o) in g.iter_mut().zip(o) {
                    if o <= 0.0 {
                        *g *= o + 1.0;
                    }
                }
            });
        let y = Tensor::<NdArray<f32>, 1>::from_data(TensorData::new(grad, [n]), &device);
        NdArray::<f32>::float_reshape(y.into_primitive().tensor(), shape)
    }
}

/// CUDA (feature `cuda`): the composed defaults, fused into one kernel by burn's fusion layer.
#[cfg(feature = "cuda")]
impl FusedElu for burn::backend::Cuda<f32, i32> {}

impl<B: FusedElu, C: CheckpointStrategy> FusedElu for Autodiff<B, C> {
    fn elu_forward(x: FloatTensor<Self>) -> FloatTensor<Self> {
        #[derive(Debug)]
        struct EluBackward;

        impl<B: FusedElu> Backward<B, 1> for EluBackward {
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

/// ELU with alpha = 1 on any backend with [`FusedElu`].
pub fn elu<B: FusedElu, const D: usize>(x: Tensor<B, D>) -> Tensor<B, D> {
    Tensor::from_primitive(TensorPrimitive::Float(B::elu_forward(
        x.into_primitive().tensor(),
    )))
}
