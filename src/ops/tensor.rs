//! The [`NetOps`] operations on burn `Tensor`s, as `model/` calls them: the dense layer
//! through a `burn::nn::Linear`'s parameters ([`linear`], [`linear_elu`], and with mean
//! pooling [`linear_elu_mean`], [`linear_elu_mean_pool`]), [`elu`], [`silu`], minGRU's and
//! minLSTM's [`recurrence`], [`im2col`], and the stencil transfers [`gather`] (G2P) and
//! [`splat`] (P2G). Each unwraps the primitives, calls the backend's operation and wraps the
//! result, so on `Autodiff<B>` it is one node of the graph.

use burn::tensor::ops::FloatTensor;
use burn::tensor::{Int, Tensor, TensorPrimitive};

use super::NetOps;

/// A float primitive as a tensor of rank `D`.
fn wrap<B: NetOps, const D: usize>(x: FloatTensor<B>) -> Tensor<B, D> {
    Tensor::from_primitive(TensorPrimitive::Float(x))
}

/// The f32 elements of `t` in row-major order on the host, through [`NetOps::host_values`]
/// where the backend reads them in one copy, else burn's `into_data` (empty if they cannot be
/// read as f32).
pub fn host_values<B: NetOps, const D: usize>(t: Tensor<B, D>) -> Vec<f32> {
    let x = t.into_primitive().tensor();
    match B::host_values(&x) {
        Some(v) => v,
        None => wrap::<B, D>(x)
            .into_data()
            .convert::<f32>()
            .to_vec::<f32>()
            .unwrap_or_default(),
    }
}

/// [`host_values`] of an integer tensor, as i64, through [`NetOps::host_indices`].
pub fn host_indices<B: NetOps, const D: usize>(t: Tensor<B, D, Int>) -> Vec<i64> {
    let x = t.into_primitive();
    match B::host_indices(&x) {
        Some(v) => v,
        None => Tensor::<B, D, Int>::from_primitive(x)
            .into_data()
            .convert::<i64>()
            .to_vec::<i64>()
            .unwrap_or_default(),
    }
}

/// `linear.forward(x)` through [`NetOps::linear_forward`]: any leading dims, the last one
/// `in`; returns the same leading dims and `out`. Equal to burn's `Linear::forward` up to
/// float summation order (the CPU backend's streamed product for a few rows).
pub fn linear<B: NetOps, const D: usize>(l: &burn::nn::Linear<B>, x: Tensor<B, D>) -> Tensor<B, D> {
    linear_impl(l, x, false)
}

fn linear_impl<B: NetOps, const D: usize>(
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

/// `elu(linear.forward(x))` through [`NetOps::linear_elu_forward`] (one node on the
/// autodiff graph, one pass for bias and ELU on the CPU); shapes as [`linear`].
pub fn linear_elu<B: NetOps, const D: usize>(
    l: &burn::nn::Linear<B>,
    x: Tensor<B, D>,
) -> Tensor<B, D> {
    linear_impl(l, x, true)
}

/// `mean over particles of elu(first.forward(x))` through [`NetOps::elu_mean_forward`]
/// (falls back to the composed form for a layer without bias).
///
/// # Shapes
/// - `x`: `[M, N, F]` -> `[M, H]`
pub fn linear_elu_mean<B: NetOps>(l: &burn::nn::Linear<B>, x: Tensor<B, 3>) -> Tensor<B, 2> {
    pooled_layer(l, x, B::elu_mean_forward)
}

/// `mean over particles of elu(layer.forward(x))` through
/// [`NetOps::linear_elu_mean_forward`] (one autodiff node; a layer without bias takes the
/// composed form).
///
/// # Shapes
/// - `x`: `[M, N, H]` -> `[M, W]`
pub fn linear_elu_mean_pool<B: NetOps>(l: &burn::nn::Linear<B>, x: Tensor<B, 3>) -> Tensor<B, 2> {
    pooled_layer(l, x, B::linear_elu_mean_forward)
}

/// A dense layer + ELU + mean over particles through `op(x, w, b)`, or composed without bias.
fn pooled_layer<B: NetOps>(
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

/// [`NetOps::recurrence`] on tensors: `h_t = a_t h_{t-1} + b_t`.
///
/// # Shapes
/// - `a`, `b`: `[B, T, H]` (positive), `h0`: `[B, H]` or None (zeros) -> `[B, T, H]`
pub fn recurrence<B: NetOps>(
    a: Tensor<B, 3>,
    b: Tensor<B, 3>,
    h0: Option<Tensor<B, 2>>,
) -> Tensor<B, 3> {
    let p = |x: Tensor<B, 3>| x.into_primitive().tensor();
    let h0 = h0.map(|h| h.into_primitive().tensor());
    Tensor::from_primitive(TensorPrimitive::Float(B::recurrence(p(a), p(b), h0)))
}

/// ELU with alpha = 1 on any backend with [`NetOps`].
pub fn elu<B: NetOps, const D: usize>(x: Tensor<B, D>) -> Tensor<B, D> {
    Tensor::from_primitive(TensorPrimitive::Float(B::elu_forward(
        x.into_primitive().tensor(),
    )))
}

/// `silu(x)` through [`NetOps::silu`], any shape.
pub fn silu<B: NetOps, const D: usize>(x: Tensor<B, D>) -> Tensor<B, D> {
    wrap(B::silu(x.into_primitive().tensor()))
}

/// `splat` `[B, n^2, 1 + own + r]` -> `[B, n^2, 1 + own + 2 + r]` through
/// [`NetOps::grid_channels`].
pub fn grid_channels<B: NetOps>(splat: Tensor<B, 3>, n: usize, own: usize) -> Tensor<B, 3> {
    wrap(B::grid_channels(splat.into_primitive().tensor(), n, own))
}

/// `[B, h, w, C]` -> `[B, h/2, w/2, C]` through [`NetOps::pool2`].
pub fn pool2<B: NetOps>(x: Tensor<B, 4>) -> Tensor<B, 4> {
    wrap(B::pool2(x.into_primitive().tensor()))
}

/// `[B, h, w, C]` -> `[B, 2h, 2w, C]` through [`NetOps::upsample2`].
pub fn upsample2<B: NetOps>(x: Tensor<B, 4>) -> Tensor<B, 4> {
    wrap(B::upsample2(x.into_primitive().tensor()))
}

/// `[B, H, W, C]` -> `[B H W, C k^2]` through [`NetOps::im2col`] (column order in
/// [`NetOps::im2col`]).
pub fn im2col<B: NetOps>(x: Tensor<B, 4>, k: usize) -> Tensor<B, 2> {
    wrap(B::im2col(x.into_primitive().tensor(), k))
}

/// G2P through [`NetOps::stencil_gather`]: `grid` `[B, n^2, C]` -> `[B, N, C]`.
pub fn gather<B: NetOps>(
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

/// P2G through [`NetOps::stencil_splat`]: `values` `[B, N, C]` -> `[B, nodes, C]`.
pub fn splat<B: NetOps>(
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
