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

    /// `x @ weight + bias`: `x` `[rows, in]`, `weight` `[in, out]` (burn's `Linear` layout),
    /// `bias` `[out]`; returns `[rows, out]`. Composed from matmul and add by default; the CPU
    /// backend streams the weights for a handful of rows (the inference step).
    fn linear_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        composed_linear::<Self>(x, weight, bias)
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

/// Rows up to which the CPU backend multiplies by streaming the weights (a matrix-vector
/// product per row) instead of calling sgemm, which packs the whole weight matrix on every
/// call: the inference step has 1 row, and its weights (tens of MB) dominate its cost.
const STREAM_ROWS: usize = 8;

/// `x @ weight + bias` for a CPU tensor with at most [`STREAM_ROWS`] rows, reading each
/// weight once; None when the operands are not plain contiguous f32 (the caller falls back).
fn linear_stream(
    x: &FloatTensor<NdArray<f32>>,
    weight: &FloatTensor<NdArray<f32>>,
    bias: Option<&FloatTensor<NdArray<f32>>>,
) -> Option<FloatTensor<NdArray<f32>>> {
    use burn::backend::ndarray::NdArrayTensor;
    let (NdArrayTensor::F32(xs), NdArrayTensor::F32(ws)) = (x, weight) else {
        return None;
    };
    let (xv, wv) = (xs.view(), ws.view());
    let (&[rows, d_in], &[w_in, d_out]) = (xv.shape(), wv.shape()) else {
        return None;
    };
    if rows > STREAM_ROWS || w_in != d_in {
        return None;
    }
    let (xs, ws) = (xv.as_slice()?, wv.as_slice()?);
    let bias_view = match bias {
        Some(NdArrayTensor::F32(b)) => Some(b.view()),
        Some(_) => return None,
        None => None,
    };
    let bias = match &bias_view {
        Some(b) => Some(b.as_slice()?),
        None => None,
    };
    let mut out = vec![0f32; rows * d_out];
    // Columns in chunks (one task each), rows of the weight streamed once per chunk.
    const CHUNK: usize = 512;
    let chunks = d_out.div_ceil(CHUNK);
    let mut per_chunk: Vec<Vec<f32>> = (0..chunks)
        .into_par_iter()
        .map(|c| {
            let (lo, hi) = (c * CHUNK, ((c + 1) * CHUNK).min(d_out));
            let w = hi - lo;
            let mut acc = vec![0f32; rows * w];
            if let Some(b) = bias {
                for r in 0..rows {
                    acc[r * w..(r + 1) * w].copy_from_slice(&b[lo..hi]);
                }
            }
            for i in 0..d_in {
                let wrow = &ws[i * d_out + lo..i * d_out + hi];
                for r in 0..rows {
                    let xi = xs[r * d_in + i];
                    if xi != 0.0 {
                        for (a, &wv) in acc[r * w..(r + 1) * w].iter_mut().zip(wrow) {
                            *a += xi * wv;
                        }
                    }
                }
            }
            acc
        })
        .collect();
    for (c, acc) in per_chunk.iter_mut().enumerate() {
        let (lo, hi) = (c * CHUNK, ((c + 1) * CHUNK).min(d_out));
        let w = hi - lo;
        for r in 0..rows {
            out[r * d_out + lo..r * d_out + hi].copy_from_slice(&acc[r * w..(r + 1) * w]);
        }
    }
    let y = Tensor::<NdArray<f32>, 2>::from_data(
        TensorData::new(out, [rows, d_out]),
        &Default::default(),
    );
    Some(y.into_primitive().tensor())
}

/// `x @ weight + bias` with burn's tensor ops (what `Linear::forward` does).
fn composed_linear<B: Backend>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    bias: Option<FloatTensor<B>>,
) -> FloatTensor<B> {
    let x = Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(x));
    let w = Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(weight));
    let y = x.matmul(w);
    let y = match bias {
        Some(b) => y + Tensor::<B, 1>::from_primitive(TensorPrimitive::Float(b)).unsqueeze::<2>(),
        None => y,
    };
    y.into_primitive().tensor()
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
    fn linear_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        match linear_stream(&x, &weight, bias.as_ref()) {
            Some(y) => y,
            None => composed_linear::<Self>(x, weight, bias),
        }
    }

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

/// `linear.forward(x)` through [`FusedElu::linear_forward`]: any leading dims, the last one
/// `in`; returns the same leading dims and `out`. Equal to burn's `Linear::forward` up to
/// float summation order (the CPU backend's streamed product for a few rows).
pub fn linear<B: FusedElu, const D: usize>(
    l: &burn::nn::Linear<B>,
    x: Tensor<B, D>,
) -> Tensor<B, D> {
    let dims = x.dims();
    let d_in = dims[D - 1];
    let rows = dims[..D - 1].iter().product::<usize>();
    let weight = l.weight.val();
    let d_out = weight.dims()[1];
    let x2 = x.reshape([rows, d_in]).into_primitive().tensor();
    let bias = l.bias.as_ref().map(|b| b.val().into_primitive().tensor());
    let y = Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(B::linear_forward(
        x2,
        weight.into_primitive().tensor(),
        bias,
    )));
    let mut out_dims = dims;
    out_dims[D - 1] = d_out;
    y.reshape(out_dims)
}

/// ELU with alpha = 1 on any backend with [`FusedElu`].
pub fn elu<B: FusedElu, const D: usize>(x: Tensor<B, D>) -> Tensor<B, D> {
    Tensor::from_primitive(TensorPrimitive::Float(B::elu_forward(
        x.into_primitive().tensor(),
    )))
}
