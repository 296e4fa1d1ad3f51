//! A fused ELU (`x` for `x > 0`, `exp(x) - 1` otherwise; Clevert et al. 2016) through burn's
//! backend extension: burn composes ELU from five passes (compare, exp, sub, mul, select)
//! with boolean masks, which cost most of the paper configuration's training time on the
//! CPU. Here the forward is one pass, and the autodiff node keeps only the output, since
//! `d ELU / dx = 1` where the output is positive and `output + 1` elsewhere.
//!
//! [`FusedElu`] has composed default methods, so any backend can opt in with an empty impl;
//! `NdArray<f32>` overrides them with single-pass loops (parallel over chunks), and
//! `Autodiff<B>` records one backward node. burn's CUDA backend (feature `cuda`) takes the
//! composed defaults, whose element-wise chains its fusion layer compiles into one kernel,
//! and sends the large products of [`FusedElu::matmul`] to cuBLAS (`model::cublas`). Used by
//! the encoder, the core's MLPs and the pointwise decoder.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{unary, Backward, Ops, OpsKind};
use burn::backend::{Autodiff, NdArray};
use burn::tensor::backend::Backend;
use burn::tensor::ops::{FloatTensor, IntTensor};
use burn::tensor::{Tensor, TensorMetadata, TensorPrimitive};
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, Ordering};

use super::cpu_kernels;

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

    /// `x @ weight + bias`: `x` `[..., in]` (any rank >= 2), `weight` `[in, out]` (burn's
    /// `Linear` layout), `bias` `[out]`; returns `[..., out]`. Composed from matmul and add by
    /// default; the CPU backend calls AVX-512/AVX2 `gemm` (with the bias added in the same
    /// pass, and no copies for reshapes), or streams the weights for a handful of rows (the
    /// inference step).
    fn linear_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        composed_linear::<Self>(x, weight, bias)
    }

    /// `elu(x @ weight + bias)`, shapes as [`FusedElu::linear_forward`]. The CPU backend
    /// adds the bias and applies ELU in one pass over the product; by default bias and ELU
    /// are applied to the `[rows, out]` product before it takes `x`'s leading dims back (a
    /// fusing backend then compiles them into one kernel: a reshape between them split it).
    fn linear_elu_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        composed_linear_map::<Self>(x, weight, bias, |y| burn::tensor::activation::elu(y, 1.0))
    }

    /// Gradients of `y = x @ weight (+ bias)` from `grad` = dL/dy `[..., out]`:
    /// `[dx [..., in], dweight [in, out], dbias [out]]`, each computed only when `need[i]`.
    fn linear_backward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        need: [bool; 3],
    ) -> [Option<FloatTensor<Self>>; 3] {
        composed_linear_backward::<Self>(x, weight, grad, need)
    }

    /// `a @ b` for 2-D `a` `[m, k]` and `b` `[k, n]` (either may be a transposed view) ->
    /// `[m, n]`: the products of the composed dense layer and its backward. burn's matmul
    /// by default; the CUDA backend sends large ones to cuBLAS (`model::cublas`).
    fn matmul(a: FloatTensor<Self>, b: FloatTensor<Self>) -> FloatTensor<Self> {
        Self::float_matmul(a, b)
    }

    /// Whether [`FusedElu::matmul`] takes a `[m, k] x [k, n]` product with a long reduction
    /// `k` whole and still fills the device (cuBLAS chooses split-K itself), so the composed
    /// backward does not cut the weight gradient into row chunks ([`weight_grad_chunks`]).
    fn splits_reduction(m: usize, k: usize, n: usize) -> bool {
        let _ = (m, k, n);
        false
    }

    /// One Adam step on a parameter (see [`AdamStep`]): returns the new parameter and the
    /// new first and second moments, all shaped like `param`; `m` / `v` None = zero (the
    /// first step). Composed from tensor ops by default (about 13 passes over memory); the
    /// CPU backend does it in one pass, in place.
    fn adam_step(
        param: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        m: Option<FloatTensor<Self>>,
        v: Option<FloatTensor<Self>>,
        c: &AdamStep,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        composed_adam::<Self>(param, grad, m, v, c)
    }

    /// True where [`FusedElu::im2col`], [`FusedElu::col2im`] and [`FusedElu::silu`] are
    /// single-pass kernels with their own autodiff nodes (the CPU backend); elsewhere the grid
    /// model composes its convolutions from burn's tensor operations.
    const NATIVE_CONV_OPS: bool = false;

    /// im2col of a same-padding `k x k` convolution (column order in `model::conv_ops`).
    /// `x` `[B, H, W, C]` -> `[B H W, C k^2]`.
    fn im2col(x: FloatTensor<Self>, k: usize) -> FloatTensor<Self> {
        super::conv_ops::composed_im2col::<Self>(x, k)
    }

    /// The adjoint of [`FusedElu::im2col`] (im2col's gradient): `cols` `[B H W, C k^2]` ->
    /// `[B, H, W, C]` = `shape`.
    fn col2im(cols: FloatTensor<Self>, shape: [usize; 4], k: usize) -> FloatTensor<Self> {
        super::conv_ops::composed_col2im::<Self>(cols, shape, k)
    }

    /// `x sigmoid(x)`, any shape.
    fn silu(x: FloatTensor<Self>) -> FloatTensor<Self> {
        super::conv_ops::composed_silu::<Self>(x)
    }

    /// SiLU's input gradient from its input `x` and the output gradient (same shape).
    fn silu_backward(x: FloatTensor<Self>, grad: FloatTensor<Self>) -> FloatTensor<Self> {
        super::conv_ops::composed_silu_backward::<Self>(x, grad)
    }

    /// G2P of a sparse stencil (`model::transfer_ops`): `grid` `[B, n^2, C]`, `index`
    /// `[B N 9]` flat grid rows, `weight` `[B, N, 9]` -> `[B, N, C]`.
    fn stencil_gather(
        grid: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        super::transfer_ops::composed_gather::<Self>(grid, index, weight)
    }

    /// P2G of a sparse stencil, the adjoint of [`FusedElu::stencil_gather`]: `values`
    /// `[B, N, C]` -> `[B, nodes, C]`.
    fn stencil_splat(
        values: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
        nodes: usize,
    ) -> FloatTensor<Self> {
        super::transfer_ops::composed_splat::<Self>(values, index, weight, nodes)
    }

    /// True where [`FusedElu::elu_mean_forward`] has its own backward (the CPU backend).
    const FUSED_ELU_MEAN: bool = false;

    /// `mean_n elu(x @ w + b)`: the encoder's first layer and mean pooling (used when the
    /// second layer is applied after pooling). `x` `[M, N, F]`, `w` `[F, H]`, `b` `[H]` ->
    /// `[M, H]`. Composed by default; the CPU backend does it in one pass without the
    /// `[M, N, H]` activations and recomputes them in the backward; the autodiff backend over
    /// any other backend takes [`FusedElu::linear_elu_mean_forward`]'s node.
    fn elu_mean_forward(
        x: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        composed_elu_mean::<Self>(x, w, b)
    }

    /// Gradients of [`FusedElu::elu_mean_forward`] from `grad` `[M, H]`: `[dx, dw, db]`, each
    /// only when `need[i]`. Only called where `FUSED_ELU_MEAN` is true.
    fn elu_mean_backward(
        x: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        need: [bool; 3],
    ) -> [Option<FloatTensor<Self>>; 3] {
        let _ = (x, w, b, grad, need);
        unreachable!("elu_mean_backward is only called on backends with FUSED_ELU_MEAN")
    }

    /// `mean_n elu(x @ w + b)` keeping the activations (the paper encoder's second layer on
    /// the GPU, and the first where no recomputing kernel exists): `x` `[M, N, H]`, `w`
    /// `[H, W]`, `b` `[W]` -> `[M, W]`. Composed by default; the
    /// autodiff backend records it as one node whose backward forms the pre-activation
    /// gradient `elu'(out) * g / N` in one broadcast element-wise pass (burn's `mean_dim`
    /// backward writes the broadcast `g / N` out first, then ELU's backward reads it back).
    fn linear_elu_mean_forward(
        x: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        composed_elu_mean::<Self>(x, w, b)
    }

    /// True where [`FusedElu::recurrence`] is a fused sequential pass (the CPU backend):
    /// minGRU and minLSTM then train through it in linear space; elsewhere they use the
    /// log-space parallel scan, which is what pays on a GPU.
    const SEQUENTIAL_SCAN: bool = false;

    /// The linear recurrence `h_t = a_t h_{t-1} + b_t` along T (`h_{-1}` = `h0` or 0), with
    /// `a`, `b` positive: `a`, `b` `[B, T, H]`, `h0` `[B, H]` -> `h` `[B, T, H]`. By default the
    /// log-space parallel scan (Heinsen 2023) of `log a`, `log b`.
    fn recurrence(
        a: FloatTensor<Self>,
        b: FloatTensor<Self>,
        h0: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        log_scan_recurrence::<Self>(a, b, h0)
    }

    /// Gradients of [`FusedElu::recurrence`] from `a`, `h0`, its output `h` and `grad` =
    /// dL/dh: `[da, db, dh0]` (`dh0` None without `h0`). By default a reverse loop of tensor
    /// ops: `d_t = grad_t + a_{t+1} d_{t+1}`, `da_t = d_t h_{t-1}`, `db_t = d_t`, `dh0 = a_0 d_0`.
    fn recurrence_backward(
        a: FloatTensor<Self>,
        h0: Option<FloatTensor<Self>>,
        h: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> [Option<FloatTensor<Self>>; 3] {
        composed_recurrence_backward::<Self>(a, h0, h, grad)
    }

    /// The input gradient from the forward output and the output gradient.
    fn elu_backward(out: FloatTensor<Self>, grad: FloatTensor<Self>) -> FloatTensor<Self> {
        composed_elu_backward::<Self>(out, grad)
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
    let &[w_in, d_out] = wv.shape() else {
        return None;
    };
    let x_shape = xv.shape().to_vec();
    let (&d_in, lead) = x_shape.split_last()?;
    let rows = lead.iter().product::<usize>();
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
    let mut shape = x_shape;
    *shape.last_mut()? = d_out;
    Some(cpu_kernels::tensor(out, &shape))
}

/// [`FusedElu::elu_mean_forward`]'s default: ELU of the dense layer, then the mean over N.
fn composed_elu_mean<B: FusedElu>(
    x: FloatTensor<B>,
    w: FloatTensor<B>,
    b: FloatTensor<B>,
) -> FloatTensor<B> {
    particle_mean::<B>(B::linear_elu_forward(x, w, Some(b)))
}

/// The mean over particles: `[M, N, H]` -> `[M, H]`.
fn particle_mean<B: Backend>(a: FloatTensor<B>) -> FloatTensor<B> {
    let a = Tensor::<B, 3>::from_primitive(TensorPrimitive::Float(a));
    let [m, _, h] = a.dims();
    a.mean_dim(1).reshape([m, h]).into_primitive().tensor()
}

/// [`FusedElu::recurrence`]'s default: `exp` of the log-space scan of `log a`, `log b`.
fn log_scan_recurrence<B: Backend>(
    a: FloatTensor<B>,
    b: FloatTensor<B>,
    h0: Option<FloatTensor<B>>,
) -> FloatTensor<B> {
    let t3 = |p| Tensor::<B, 3>::from_primitive(TensorPrimitive::Float(p));
    let h0 = h0.map(|p| Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(p)));
    super::minrnn::scan_with_state(t3(a).log(), t3(b).log(), h0)
        .into_primitive()
        .tensor()
}

/// [`FusedElu::recurrence_backward`]'s default, with tensor ops.
fn composed_recurrence_backward<B: Backend>(
    a: FloatTensor<B>,
    h0: Option<FloatTensor<B>>,
    h: FloatTensor<B>,
    grad: FloatTensor<B>,
) -> [Option<FloatTensor<B>>; 3] {
    let t3 = |p| Tensor::<B, 3>::from_primitive(TensorPrimitive::Float(p));
    let (a, h, grad) = (t3(a), t3(h), t3(grad));
    let h0 = h0.map(|p| Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(p)));
    let [batch, t, w] = a.dims();
    let step = |x: &Tensor<B, 3>, s: usize| x.clone().narrow(1, s, 1).reshape([batch, w]);
    let mut carry = Tensor::<B, 2>::zeros([batch, w], &a.device());
    let (mut da, mut db) = (Vec::with_capacity(t), Vec::with_capacity(t));
    for s in (0..t).rev() {
        let d = step(&grad, s) + carry;
        let prev = if s > 0 {
            step(&h, s - 1)
        } else {
            h0.clone()
                .unwrap_or_else(|| Tensor::zeros([batch, w], &a.device()))
        };
        da.push((d.clone() * prev).reshape([batch, 1, w]));
        carry = step(&a, s) * d.clone();
        db.push(d.reshape([batch, 1, w]));
    }
    da.reverse();
    db.reverse();
    let prim = |x: Tensor<B, 3>| Some(x.into_primitive().tensor());
    [
        prim(Tensor::cat(da, 1)),
        prim(Tensor::cat(db, 1)),
        h0.map(|_| carry.into_primitive().tensor()),
    ]
}

/// The scalars of one Adam step (Kingma & Ba 2015, Algorithm 1; epsilon added to
/// `sqrt(v) * sqrt(1 - b2^t)` as in PyTorch and burn): learning rate, betas, epsilon and the
/// step number `t` (1 for the first step).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamStep {
    /// Learning rate.
    pub lr: f32,
    /// First-moment decay.
    pub beta_1: f32,
    /// Second-moment decay.
    pub beta_2: f32,
    /// Denominator epsilon.
    pub epsilon: f32,
    /// Step number, from 1.
    pub time: usize,
}

impl AdamStep {
    /// (`sqrt(1 - b2^t)`, `sqrt(1 - b2^t) / (1 - b1^t)`): burn's bias corrections.
    pub fn corrections(&self) -> (f32, f32) {
        let t = self.time as i32;
        let bc2 = (1.0 - self.beta_2.powi(t)).sqrt();
        (bc2, bc2 / (1.0 - self.beta_1.powi(t)))
    }
}

/// [`FusedElu::adam_step`] with burn's tensor ops (the same arithmetic as `burn::optim::Adam`).
pub(crate) fn composed_adam<B: Backend>(
    param: FloatTensor<B>,
    grad: FloatTensor<B>,
    m: Option<FloatTensor<B>>,
    v: Option<FloatTensor<B>>,
    c: &AdamStep,
) -> (FloatTensor<B>, FloatTensor<B>, FloatTensor<B>) {
    let t = |p| Tensor::<B, 1>::from_primitive(TensorPrimitive::Float(p));
    let shape = param.shape();
    let n = shape.num_elements();
    let flat = |p| t(B::float_reshape(p, [n].into()));
    let (param, grad) = (flat(param), flat(grad));
    let m1 = grad.clone().mul_scalar(1.0 - c.beta_1);
    let m2 = grad.square().mul_scalar(1.0 - c.beta_2);
    let m1 = match m {
        Some(m) => flat(m).mul_scalar(c.beta_1).add(m1),
        None => m1,
    };
    let m2 = match v {
        Some(v) => flat(v).mul_scalar(c.beta_2).add(m2),
        None => m2,
    };
    let (bc2, factor) = c.corrections();
    let update = m1
        .clone()
        .mul_scalar(factor)
        .div(m2.clone().sqrt().add_scalar(c.epsilon * bc2));
    let param = param - update.mul_scalar(c.lr);
    let back = |x: Tensor<B, 1>| B::float_reshape(x.into_primitive().tensor(), shape.clone());
    (back(param), back(m1), back(m2))
}

/// `x` `[..., cols]` as a `[rows, cols]` tensor, and its original shape.
fn as_rows<B: Backend>(x: FloatTensor<B>) -> (Tensor<B, 2>, burn::tensor::Shape) {
    let shape = x.shape();
    let dims: Vec<usize> = shape.iter().copied().collect();
    let cols = *dims.last().expect("rank >= 1");
    let rows = dims[..dims.len() - 1].iter().product::<usize>();
    let x = B::float_reshape(x, [rows, cols].into());
    (Tensor::from_primitive(TensorPrimitive::Float(x)), shape)
}

/// `y` `[rows, out]` back to `shape` with its last dimension replaced by `out`.
fn from_rows<B: Backend>(y: Tensor<B, 2>, shape: &burn::tensor::Shape) -> FloatTensor<B> {
    let mut dims: Vec<usize> = shape.iter().copied().collect();
    *dims.last_mut().expect("rank >= 1") = y.dims()[1];
    B::float_reshape(y.into_primitive().tensor(), dims.into())
}

/// `x @ weight + bias` with burn's tensor ops (what `Linear::forward` does), the product
/// through [`FusedElu::matmul`].
fn composed_linear<B: FusedElu>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    bias: Option<FloatTensor<B>>,
) -> FloatTensor<B> {
    composed_linear_map::<B>(x, weight, bias, |y| y)
}

/// `f(x @ weight + bias)` with `f` applied to the `[rows, out]` rows.
fn composed_linear_map<B: FusedElu>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    bias: Option<FloatTensor<B>>,
    f: impl FnOnce(Tensor<B, 2>) -> Tensor<B, 2>,
) -> FloatTensor<B> {
    let (x, shape) = as_rows::<B>(x);
    let y = Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(B::matmul(
        x.into_primitive().tensor(),
        weight,
    )));
    let y = match bias {
        Some(b) => y + Tensor::<B, 1>::from_primitive(TensorPrimitive::Float(b)).unsqueeze::<2>(),
        None => y,
    };
    from_rows(f(y), &shape)
}

/// [`FusedElu::elu_backward`] with burn's tensor ops: `grad` where `out > 0`, else
/// `grad * (out + 1)`.
fn composed_elu_backward<B: Backend>(out: FloatTensor<B>, grad: FloatTensor<B>) -> FloatTensor<B> {
    let shape = out.shape();
    let n = shape.num_elements();
    let flat =
        |t| Tensor::<B, 1>::from_primitive(TensorPrimitive::Float(B::float_reshape(t, [n].into())));
    let (out, grad) = (flat(out), flat(grad));
    B::float_reshape((grad * elu_slope(out)).into_primitive().tensor(), shape)
}

/// `d ELU / dx` from the ELU output: 1 where `out > 0`, `out + 1` elsewhere.
fn elu_slope<B: Backend, const D: usize>(out: Tensor<B, D>) -> Tensor<B, D> {
    let positive = out.clone().greater_elem(0.0);
    (out + 1.0).mask_fill(positive, 1.0)
}

/// Whether [`composed_linear_backward`] splits long weight-gradient reductions into row
/// chunks (see [`weight_grad_chunks`]); on by default, switched off by `bench train
/// --split-weight-grad off` to measure what it buys.
static SPLIT_WEIGHT_GRAD: AtomicBool = AtomicBool::new(true);

/// Turns the chunked weight gradient of the composed dense-layer backward on or off (process
/// wide; the CPU backend has its own backward and ignores it).
pub fn set_split_weight_grad(on: bool) {
    SPLIT_WEIGHT_GRAD.store(on, Ordering::Relaxed);
}

/// Fewest rows per chunk of a split weight gradient.
const MIN_CHUNK_ROWS: usize = 512;
/// Partial-gradient elements (chunks x in x out) a split aims for: enough output tiles to
/// fill a GPU (~1,000 tiles of 64 x 64), a few MB of partials.
const TARGET_PARTIALS: usize = 1 << 22;

/// Row chunks `C` for the weight gradient `x^T g` of a dense layer with `rows` rows: 1 (one
/// product) unless the reduction is long and the output small. A product with a reduction
/// dimension K of 400,000 particle rows and a `5 x 256` or `256 x 1,250` output runs on a
/// handful of output tiles, one multiprocessor each, in a tiled GPU matmul without split-K
/// (cubecl's); as `C` batched products of `rows / C` rows summed afterwards ("split-K", as
/// cuBLAS and CUTLASS do it: Kerr et al., "CUTLASS: Fast Linear Algebra in CUDA C++", NVIDIA
/// 2017) it has `C` times the tiles. `C` divides `rows` exactly (the nearest divisor of the
/// wanted count with at least [`MIN_CHUNK_ROWS`] rows per chunk), so the chunks are views.
pub fn weight_grad_chunks(rows: usize, d_in: usize, d_out: usize) -> usize {
    if !SPLIT_WEIGHT_GRAD.load(Ordering::Relaxed) || rows < 2 * MIN_CHUNK_ROWS {
        return 1;
    }
    let most = rows / MIN_CHUNK_ROWS;
    let want = TARGET_PARTIALS.div_ceil((d_in * d_out).max(1)).min(most);
    if want < 2 {
        return 1;
    }
    // The divisor of `rows` nearest to `want` within [want / 2, most].
    (0..want)
        .flat_map(|d| [want - d, want + d])
        .filter(|&c| c >= want.div_ceil(2).max(2) && c <= most)
        .find(|&c| rows % c == 0)
        .unwrap_or(1)
}

/// [`FusedElu::linear_backward`] with burn's tensor ops: `dx = g w^T`, `dw = x^T g`,
/// `db = sum_rows g`, the last two as sums of [`weight_grad_chunks`] partial products when
/// the rows are many (what lets a GPU spread them).
fn composed_linear_backward<B: FusedElu>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    grad: FloatTensor<B>,
    need: [bool; 3],
) -> [Option<FloatTensor<B>>; 3] {
    let shape = x.shape();
    let d_in = *shape.last().expect("rank >= 2");
    let d_out = *grad.shape().last().expect("rank >= 2");
    let rows = shape.num_elements() / d_in.max(1);
    let chunks = if B::splits_reduction(d_in, rows, d_out) {
        1
    } else {
        weight_grad_chunks(rows, d_in, d_out)
    };
    linear_backward_in_chunks::<B>(x, weight, grad, need, chunks)
}

/// [`composed_linear_backward`] with `chunks` row chunks (dividing the rows) for the weight
/// gradient; the bias gradient is split by its own [`weight_grad_chunks`].
fn linear_backward_in_chunks<B: FusedElu>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    grad: FloatTensor<B>,
    need: [bool; 3],
    chunks: usize,
) -> [Option<FloatTensor<B>>; 3] {
    let (x, shape) = as_rows::<B>(x);
    let (grad, _) = as_rows::<B>(grad);
    let weight = Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(weight));
    let [rows, d_out] = grad.dims();
    let d_in = x.dims()[1];
    let product = |a: Tensor<B, 2>, b: Tensor<B, 2>| {
        Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(B::matmul(
            a.into_primitive().tensor(),
            b.into_primitive().tensor(),
        )))
    };
    let dx = need[0].then(|| from_rows(product(grad.clone(), weight.transpose()), &shape));
    let dw = need[1].then(|| {
        if chunks > 1 {
            let xs = x.reshape([chunks, rows / chunks, d_in]).swap_dims(1, 2);
            let gs = grad.clone().reshape([chunks, rows / chunks, d_out]);
            let dw = xs.matmul(gs).sum_dim(0).reshape([d_in, d_out]);
            dw.into_primitive().tensor()
        } else {
            product(x.transpose(), grad.clone())
                .into_primitive()
                .tensor()
        }
    });
    let db = need[2].then(|| {
        // The bias gradient is a reduction over the rows with `d_out` outputs: split it for
        // `d_out` alone (a `[16, 25,000, 1,250]` middle-axis sum ran on 40 thread blocks).
        let chunks = weight_grad_chunks(rows, 1, d_out);
        let db = if chunks > 1 {
            grad.reshape([chunks, rows / chunks, d_out])
                .sum_dim(1)
                .sum_dim(0)
        } else {
            grad.sum_dim(0).unsqueeze::<3>()
        };
        db.reshape([d_out]).into_primitive().tensor()
    });
    [dx, dw, db]
}

impl FusedElu for NdArray<f32> {
    fn linear_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        linear_stream(&x, &weight, bias.as_ref())
            .or_else(|| cpu_kernels::linear(&x, &weight, bias.as_ref(), false))
            .unwrap_or_else(|| composed_linear::<Self>(x, weight, bias))
    }

    fn linear_elu_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        if let Some(y) = linear_stream(&x, &weight, bias.as_ref()) {
            return cpu_kernels::elu(y);
        }
        cpu_kernels::linear(&x, &weight, bias.as_ref(), true)
            .unwrap_or_else(|| Self::elu_forward(composed_linear::<Self>(x, weight, bias)))
    }

    fn linear_backward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        need: [bool; 3],
    ) -> [Option<FloatTensor<Self>>; 3] {
        cpu_kernels::linear_backward(&x, &weight, &grad, need)
            .unwrap_or_else(|| composed_linear_backward::<Self>(x, weight, grad, need))
    }

    fn adam_step(
        param: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        m: Option<FloatTensor<Self>>,
        v: Option<FloatTensor<Self>>,
        c: &AdamStep,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        match cpu_kernels::adam(param, &grad, m, v, c) {
            Ok(out) => out,
            Err((param, m, v)) => composed_adam::<Self>(param, grad, m, v, c),
        }
    }

    const SEQUENTIAL_SCAN: bool = true;
    const FUSED_ELU_MEAN: bool = true;
    const NATIVE_CONV_OPS: bool = true;

    fn im2col(x: FloatTensor<Self>, k: usize) -> FloatTensor<Self> {
        super::conv_ops::cpu_im2col(&x, k)
            .unwrap_or_else(|| super::conv_ops::composed_im2col::<Self>(x, k))
    }

    fn col2im(cols: FloatTensor<Self>, shape: [usize; 4], k: usize) -> FloatTensor<Self> {
        super::conv_ops::cpu_col2im(&cols, shape, k)
            .unwrap_or_else(|| super::conv_ops::composed_col2im::<Self>(cols, shape, k))
    }

    fn silu(x: FloatTensor<Self>) -> FloatTensor<Self> {
        super::conv_ops::cpu_silu(x)
    }

    fn stencil_gather(
        grid: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        match super::transfer_ops::cpu_gather(&grid, &index, &weight) {
            Some(out) => out,
            None => super::transfer_ops::composed_gather::<Self>(grid, index, weight),
        }
    }

    fn stencil_splat(
        values: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
        nodes: usize,
    ) -> FloatTensor<Self> {
        match super::transfer_ops::cpu_splat(&values, &index, &weight, nodes) {
            Some(out) => out,
            None => super::transfer_ops::composed_splat::<Self>(values, index, weight, nodes),
        }
    }

    fn silu_backward(x: FloatTensor<Self>, grad: FloatTensor<Self>) -> FloatTensor<Self> {
        match super::conv_ops::cpu_silu_backward(&x, grad) {
            Ok(g) => g,
            Err(grad) => super::conv_ops::composed_silu_backward::<Self>(x, grad),
        }
    }

    fn elu_mean_forward(
        x: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        cpu_kernels::elu_mean(&x, &w, &b).unwrap_or_else(|| composed_elu_mean::<Self>(x, w, b))
    }

    fn elu_mean_backward(
        x: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        need: [bool; 3],
    ) -> [Option<FloatTensor<Self>>; 3] {
        cpu_kernels::elu_mean_backward(&x, &w, &b, &grad, need)
            .expect("elu_mean_backward on f32 tensors of the forward's shapes")
    }

    fn recurrence(
        a: FloatTensor<Self>,
        b: FloatTensor<Self>,
        h0: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        cpu_kernels::recurrence(&a, &b, h0.as_ref())
            .unwrap_or_else(|| log_scan_recurrence::<Self>(a, b, h0))
    }

    fn recurrence_backward(
        a: FloatTensor<Self>,
        h0: Option<FloatTensor<Self>>,
        h: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> [Option<FloatTensor<Self>>; 3] {
        cpu_kernels::recurrence_backward(&a, h0.as_ref(), &h, &grad)
            .unwrap_or_else(|| composed_recurrence_backward::<Self>(a, h0, h, grad))
    }

    fn elu_forward(x: FloatTensor<Self>) -> FloatTensor<Self> {
        cpu_kernels::elu(x)
    }

    fn elu_backward(out: FloatTensor<Self>, grad: FloatTensor<Self>) -> FloatTensor<Self> {
        match cpu_kernels::elu_backward(&out, grad) {
            Ok(g) => g,
            Err(grad) => composed_elu_backward::<Self>(out, grad),
        }
    }
}

/// CUDA (feature `cuda`): the composed defaults, whose element-wise chains burn's fusion
/// layer compiles into single kernels, with the large products through cuBLAS.
#[cfg(feature = "cuda")]
impl FusedElu for burn::backend::Cuda<f32, i32> {
    fn matmul(a: FloatTensor<Self>, b: FloatTensor<Self>) -> FloatTensor<Self> {
        super::cublas::matmul(a, b)
    }

    fn splits_reduction(m: usize, k: usize, n: usize) -> bool {
        super::cublas::worth_it(m, k, n)
    }
}

/// The backward node of a dense layer (`P` = 3 parents with a bias, 2 without): keeps the
/// input and the weight (and the output when ELU follows) and calls
/// [`FusedElu::linear_backward`] of the inner backend.
#[derive(Debug)]
struct LinearBackward;

impl<B: FusedElu, const P: usize> Backward<B, P> for LinearBackward {
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
fn linear_node<B: FusedElu, C: CheckpointStrategy>(
    x: FloatTensor<Autodiff<B, C>>,
    weight: FloatTensor<Autodiff<B, C>>,
    bias: Option<FloatTensor<Autodiff<B, C>>>,
    elu: bool,
) -> FloatTensor<Autodiff<B, C>> {
    let forward = |x, w, b| {
        if elu {
            B::linear_elu_forward(x, w, b)
        } else {
            B::linear_forward(x, w, b)
        }
    };
    match bias {
        Some(bias) => {
            let nodes = [x.node.clone(), weight.node.clone(), bias.node.clone()];
            match <LinearBackward as Backward<B, 3>>::prepare::<C>(LinearBackward, nodes)
                .compute_bound()
                .stateful()
            {
                OpsKind::Tracked(prep) => {
                    let out = forward(
                        x.primitive.clone(),
                        weight.primitive.clone(),
                        Some(bias.primitive),
                    );
                    let keep = elu.then(|| out.clone());
                    prep.finish((x.primitive, weight.primitive, keep), out)
                }
                OpsKind::UnTracked(prep) => {
                    prep.finish(forward(x.primitive, weight.primitive, Some(bias.primitive)))
                }
            }
        }
        None => {
            let nodes = [x.node.clone(), weight.node.clone()];
            match <LinearBackward as Backward<B, 2>>::prepare::<C>(LinearBackward, nodes)
                .compute_bound()
                .stateful()
            {
                OpsKind::Tracked(prep) => {
                    let out = forward(x.primitive.clone(), weight.primitive.clone(), None);
                    let keep = elu.then(|| out.clone());
                    prep.finish((x.primitive, weight.primitive, keep), out)
                }
                OpsKind::UnTracked(prep) => {
                    prep.finish(forward(x.primitive, weight.primitive, None))
                }
            }
        }
    }
}

/// The backward node of [`FusedElu::linear_elu_mean_forward`]: keeps the input, the weight
/// and the ELU output `[M, N, W]` (before the mean).
#[derive(Debug)]
struct LinearEluMeanBackward;

impl<B: FusedElu> Backward<B, 3> for LinearEluMeanBackward {
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

/// The backward node of [`FusedElu::recurrence`] (`P` = 3 parents with `h0`, 2 without).
#[derive(Debug)]
struct RecurrenceBackward;

impl<B: FusedElu, const P: usize> Backward<B, P> for RecurrenceBackward {
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

/// The backward node of [`FusedElu::elu_mean_forward`]: keeps `x`, `w`, `b`.
#[derive(Debug)]
struct EluMeanBackward;

impl<B: FusedElu> Backward<B, 3> for EluMeanBackward {
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

impl<B: FusedElu, C: CheckpointStrategy> FusedElu for Autodiff<B, C> {
    const SEQUENTIAL_SCAN: bool = B::SEQUENTIAL_SCAN;
    const FUSED_ELU_MEAN: bool = B::FUSED_ELU_MEAN;
    const NATIVE_CONV_OPS: bool = B::NATIVE_CONV_OPS;

    fn im2col(x: FloatTensor<Self>, k: usize) -> FloatTensor<Self> {
        match B::NATIVE_CONV_OPS {
            true => super::conv_ops::autodiff_im2col::<B, C>(x, k),
            false => super::conv_ops::composed_im2col::<Self>(x, k),
        }
    }

    fn silu(x: FloatTensor<Self>) -> FloatTensor<Self> {
        match B::NATIVE_CONV_OPS {
            true => super::conv_ops::autodiff_silu::<B, C>(x),
            false => super::conv_ops::composed_silu::<Self>(x),
        }
    }

    fn stencil_gather(
        grid: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        match B::NATIVE_CONV_OPS {
            true => super::transfer_ops::autodiff_gather::<B, C>(grid, index, weight),
            false => super::transfer_ops::composed_gather::<Self>(grid, index, weight),
        }
    }

    fn stencil_splat(
        values: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
        nodes: usize,
    ) -> FloatTensor<Self> {
        match B::NATIVE_CONV_OPS {
            true => super::transfer_ops::autodiff_splat::<B, C>(values, index, weight, nodes),
            false => super::transfer_ops::composed_splat::<Self>(values, index, weight, nodes),
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
        if !B::SEQUENTIAL_SCAN {
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
    linear_impl(l, x, false)
}

fn linear_impl<B: FusedElu, const D: usize>(
    l: &burn::nn::Linear<B>,
    x: Tensor<B, D>,
    elu: bool,
) -> Tensor<B, D> {
    let x = x.into_primitive().tensor();
    let weight = l.weight.val().into_primitive().tensor();
    let bias = l.bias.as_ref().map(|b| b.val().into_primitive().tensor());
    let y = if elu {
        B::linear_elu_forward(x, weight, bias)
    } else {
        B::linear_forward(x, weight, bias)
    };
    Tensor::from_primitive(TensorPrimitive::Float(y))
}

/// `elu(linear.forward(x))` through [`FusedElu::linear_elu_forward`] (one node on the
/// autodiff graph, one pass for bias and ELU on the CPU); shapes as [`linear`].
pub fn linear_elu<B: FusedElu, const D: usize>(
    l: &burn::nn::Linear<B>,
    x: Tensor<B, D>,
) -> Tensor<B, D> {
    linear_impl(l, x, true)
}

/// `mean over particles of elu(first.forward(x))` through [`FusedElu::elu_mean_forward`]
/// (falls back to the composed form for a layer without bias).
///
/// # Shapes
/// - `x`: `[M, N, F]` -> `[M, H]`
pub fn linear_elu_mean<B: FusedElu>(l: &burn::nn::Linear<B>, x: Tensor<B, 3>) -> Tensor<B, 2> {
    pooled_layer(l, x, B::elu_mean_forward)
}

/// `mean over particles of elu(layer.forward(x))` through
/// [`FusedElu::linear_elu_mean_forward`] (one autodiff node; a layer without bias takes the
/// composed form).
///
/// # Shapes
/// - `x`: `[M, N, H]` -> `[M, W]`
pub fn linear_elu_mean_pool<B: FusedElu>(l: &burn::nn::Linear<B>, x: Tensor<B, 3>) -> Tensor<B, 2> {
    pooled_layer(l, x, B::linear_elu_mean_forward)
}

/// A dense layer + ELU + mean over particles through `op(x, w, b)`, or composed without bias.
fn pooled_layer<B: FusedElu>(
    l: &burn::nn::Linear<B>,
    x: Tensor<B, 3>,
    op: fn(FloatTensor<B>, FloatTensor<B>, FloatTensor<B>) -> FloatTensor<B>,
) -> Tensor<B, 2> {
    let Some(bias) = &l.bias else {
        let a = linear_elu(l, x);
        let [m, _, h] = a.dims();
        return a.mean_dim(1).reshape([m, h]);
    };
    let y = op(
        x.into_primitive().tensor(),
        l.weight.val().into_primitive().tensor(),
        bias.val().into_primitive().tensor(),
    );
    Tensor::from_primitive(TensorPrimitive::Float(y))
}

/// [`FusedElu::recurrence`] on tensors: `h_t = a_t h_{t-1} + b_t`.
///
/// # Shapes
/// - `a`, `b`: `[B, T, H]` (positive), `h0`: `[B, H]` or None (zeros) -> `[B, T, H]`
pub fn recurrence<B: FusedElu>(
    a: Tensor<B, 3>,
    b: Tensor<B, 3>,
    h0: Option<Tensor<B, 2>>,
) -> Tensor<B, 3> {
    let p = |x: Tensor<B, 3>| x.into_primitive().tensor();
    let h0 = h0.map(|h| h.into_primitive().tensor());
    Tensor::from_primitive(TensorPrimitive::Float(B::recurrence(p(a), p(b), h0)))
}

/// ELU with alpha = 1 on any backend with [`FusedElu`].
pub fn elu<B: FusedElu, const D: usize>(x: Tensor<B, D>) -> Tensor<B, D> {
    Tensor::from_primitive(TensorPrimitive::Float(B::elu_forward(
        x.into_primitive().tensor(),
    )))
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::ops::FloatTensorOps;
    use burn::tensor::Distribution;

    type C = NdArray<f32>;

    #[test]
    fn chunk_counts_divide_the_rows() {
        // The paper configuration's encoder at batch 80, T = 2: 400,000 particle rows.
        assert_eq!(weight_grad_chunks(400_000, 256, 1250), 16);
        assert_eq!(weight_grad_chunks(400_000, 5, 256), 640);
        for (rows, d_in, d_out) in [(400_000, 5, 256), (6_400_000, 5, 256), (99_991, 5, 8)] {
            let c = weight_grad_chunks(rows, d_in, d_out);
            assert_eq!(rows % c, 0, "{rows} rows in {c} chunks");
            assert!(c == 1 || rows / c >= MIN_CHUNK_ROWS);
        }
        // Few rows (the core, the decoder) or a big output: one product.
        assert_eq!(weight_grad_chunks(160, 1250, 3750), 1);
        assert_eq!(weight_grad_chunks(4096, 1250, 5000), 1);
    }

    #[test]
    fn chunked_weight_gradient_equals_one_product() {
        let device = Default::default();
        let (rows, d_in, d_out) = (3 * 4 * 600, 5, 37);
        let t = |dims: [usize; 2]| {
            Tensor::<C, 2>::random(dims, Distribution::Normal(0.0, 1.0), &device)
                .into_primitive()
                .tensor()
        };
        let (x, w, g) = (t([rows, d_in]), t([d_in, d_out]), t([rows, d_out]));
        let flat = |p: FloatTensor<C>| -> Vec<f32> {
            let n = p.shape().num_elements();
            Tensor::<C, 1>::from_primitive(TensorPrimitive::Float(C::float_reshape(p, [n].into())))
                .into_data()
                .to_vec()
                .unwrap()
        };
        let one = linear_backward_in_chunks::<C>(x.clone(), w.clone(), g.clone(), [true; 3], 1);
        let split = linear_backward_in_chunks::<C>(x, w, g, [true; 3], 12);
        for (name, (a, b)) in ["dx", "dw", "db"].iter().zip(one.into_iter().zip(split)) {
            let (a, b) = (flat(a.unwrap()), flat(b.unwrap()));
            assert_eq!(a.len(), b.len(), "{name}");
            let scale = a.iter().fold(1f32, |m, v| m.max(v.abs()));
            let worst = a
                .iter()
                .zip(&b)
                .map(|(p, q)| (p - q).abs())
                .fold(0f32, f32::max);
            assert!(
                worst <= 1e-5 * scale,
                "{name}: max diff {worst} (scale {scale})"
            );
        }
    }
}
