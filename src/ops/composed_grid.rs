//! [`NetOps`]'s defaults for the grid model's operations in burn's tensor operations:
//! im2col as the `k^2` shifted slices of the zero-padded input and its adjoint col2im (column
//! order in [`NetOps::im2col`]), SiLU (`x sigmoid(x)`, Elfwing et al. 2018) and its gradient,
//! the stencil transfers (G2P through burn's row gather `select`, P2G through its
//! scatter-add `select_assign`), and the U-Net's glue: the grid channels from P2G's splat,
//! 2x2 average pooling and nearest 2x upsampling. The CPU has single-pass kernels for all of
//! them (`cpu/`).

use burn::tensor::backend::Backend;
use burn::tensor::ops::{FloatTensor, IntTensor};
use burn::tensor::{IndexingUpdateOp, Int, Tensor, TensorMetadata, TensorPrimitive};

use super::NetOps;
use super::STENCIL_NODES as NODES;

/// A float primitive as a tensor of rank `D`.
fn wrap<B: NetOps, const D: usize>(x: FloatTensor<B>) -> Tensor<B, D> {
    Tensor::from_primitive(TensorPrimitive::Float(x))
}

/// The dims of a rank-4 primitive.
pub(crate) fn dims4<B: NetOps>(x: &FloatTensor<B>) -> [usize; 4] {
    let s = x.shape();
    [s[0], s[1], s[2], s[3]]
}

/// `x` `[B, H, W, C]` with `half` zero rows above and below and `half` zero columns left
/// and right: `[B, H + 2 half, W + 2 half, C]` (the "same" padding of a `2 half + 1`
/// convolution, channels last).
pub fn pad_hw<B: Backend>(x: Tensor<B, 4>, half: usize) -> Tensor<B, 4> {
    let [b, h, w, c] = x.dims();
    let device = x.device();
    let zeros_h = Tensor::zeros([b, half, w, c], &device);
    let x = Tensor::cat(vec![zeros_h.clone(), x, zeros_h], 1);
    let zeros_w = Tensor::zeros([b, h + 2 * half, half, c], &device);
    Tensor::cat(vec![zeros_w.clone(), x, zeros_w], 2)
}

/// Composed im2col: the `k^2` shifted slices of the zero-padded input, interleaved so that
/// the offset is the fastest column index.
///
/// # Shapes
/// - `x`: `[B, H, W, C]` -> `[B H W, C k^2]`
pub(crate) fn composed_im2col<B: NetOps>(x: FloatTensor<B>, k: usize) -> FloatTensor<B> {
    let [b, h, w, c] = dims4::<B>(&x);
    let x = wrap::<B, 4>(x);
    let x = pad_hw(x, k / 2);
    let shifted: Vec<Tensor<B, 5>> = (0..k * k)
        .map(|s| {
            x.clone()
                .narrow(1, s / k, h)
                .narrow(2, s % k, w)
                .unsqueeze_dim(4)
        })
        .collect();
    Tensor::cat(shifted, 4)
        .reshape([b * h * w, c * k * k])
        .into_primitive()
        .tensor()
}

/// Composed [`NetOps::im2col_linear`]: the columns materialised, then one product,
/// `im2col(x, k) @ matrix + bias` (on the autodiff backend both are nodes, and the columns
/// are kept for the backward).
///
/// # Shapes
/// - `x`: `[B, H, W, C]`, `matrix` `[C k^2, C_out]`, `bias` `[C_out]` -> `[B H W, C_out]`
pub(crate) fn composed_im2col_linear<B: NetOps>(
    x: FloatTensor<B>,
    matrix: FloatTensor<B>,
    bias: Option<FloatTensor<B>>,
    k: usize,
) -> FloatTensor<B> {
    B::linear_forward(B::im2col(x, k), matrix, bias)
}

/// [`NetOps::im2col_linear_backward`] by im2col: the columns recomputed from `x`, the
/// product's gradients from [`NetOps::linear_backward`], the input's through
/// [`NetOps::col2im`].
pub(crate) fn im2col_linear_backward<B: NetOps>(
    x: FloatTensor<B>,
    matrix: FloatTensor<B>,
    grad: FloatTensor<B>,
    k: usize,
    need: [bool; 3],
) -> [Option<FloatTensor<B>>; 3] {
    let shape = dims4::<B>(&x);
    let cols = B::im2col(x, k);
    let [dcols, dmatrix, dbias] = B::linear_backward(cols, matrix, grad, need);
    [dcols.map(|d| B::col2im(d, shape, k)), dmatrix, dbias]
}

/// Composed col2im, the adjoint of [`composed_im2col`]: each offset's block added back at
/// its shifted position of a zero-padded grid, which is then cropped.
///
/// # Shapes
/// - `cols`: `[B H W, C k^2]` -> `[B, H, W, C]` (= `shape`)
pub(crate) fn composed_col2im<B: NetOps>(
    cols: FloatTensor<B>,
    shape: [usize; 4],
    k: usize,
) -> FloatTensor<B> {
    let [b, h, w, c] = shape;
    let half = k / 2;
    let cols = wrap::<B, 2>(cols).reshape([b, h, w, c, k * k]);
    let mut acc = Tensor::<B, 4>::zeros([b, h + 2 * half, w + 2 * half, c], &cols.device());
    for s in 0..k * k {
        let (ky, kx) = (s / k, s % k);
        let block = cols.clone().narrow(4, s, 1).reshape([b, h, w, c]);
        let at = [0..b, ky..ky + h, kx..kx + w, 0..c];
        let sum = acc.clone().slice(at.clone()) + block;
        acc = acc.slice_assign(at, sum);
    }
    acc.narrow(1, half, h)
        .narrow(2, half, w)
        .into_primitive()
        .tensor()
}

/// Composed SiLU.
pub(crate) fn composed_silu<B: NetOps>(x: FloatTensor<B>) -> FloatTensor<B> {
    let shape = x.shape();
    let flat = wrap::<B, 1>(B::float_reshape(x, [shape.num_elements()].into()));
    let y = burn::tensor::activation::silu(flat)
        .into_primitive()
        .tensor();
    B::float_reshape(y, shape)
}

/// Composed SiLU gradient: `grad (s + x s (1 - s))`, `s = sigmoid(x)`.
pub(crate) fn composed_silu_backward<B: NetOps>(
    x: FloatTensor<B>,
    grad: FloatTensor<B>,
) -> FloatTensor<B> {
    let shape = x.shape();
    let n = [shape.num_elements()].into();
    let x = wrap::<B, 1>(B::float_reshape(x, n));
    let grad = wrap::<B, 1>(B::float_reshape(grad, [shape.num_elements()].into()));
    let s = burn::tensor::activation::sigmoid(x.clone());
    let slope = s.clone() + x * s.clone() * (s.neg() + 1.0);
    B::float_reshape((grad * slope).into_primitive().tensor(), shape)
}

/// Composed G2P: burn's row gather of the 9 nodes, weighted and summed.
pub(crate) fn composed_gather<B: NetOps>(
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
pub(crate) fn composed_splat<B: NetOps>(
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

/// Whether grid node `i` of an `n`-node axis is a wall node: index < 3 or > n - 3, where
/// `sim` zeroes the outward velocity (`sim::mpm`).
pub(crate) fn is_wall(i: usize, n: usize) -> bool {
    i < 3 || i + 3 > n
}

/// Composed grid channels (see [`NetOps::grid_channels`]): narrows, a division and a
/// concatenation with the wall masks.
pub(crate) fn composed_grid_channels<B: NetOps>(
    splat: FloatTensor<B>,
    n: usize,
    own: usize,
) -> FloatTensor<B> {
    let splat = wrap::<B, 3>(splat);
    let [b, cells, c_s] = splat.dims();
    let device = splat.device();
    let mass = splat.clone().narrow(2, 0, 1);
    let per_mass = splat.narrow(2, 1, c_s - 1) / mass.clone().clamp_min(1e-6);
    let walls: Vec<f32> = (0..cells)
        .flat_map(|k| [is_wall(k / n, n), is_wall(k % n, n)])
        .map(|wall| f32::from(u8::from(wall)))
        .collect();
    let walls =
        Tensor::<B, 3>::from_data(burn::tensor::TensorData::new(walls, [1, cells, 2]), &device)
            .repeat_dim(0, b);
    let mut parts = vec![
        mass.mul_scalar(0.25),
        per_mass.clone().narrow(2, 0, own),
        walls,
    ];
    if c_s > 1 + own {
        parts.push(per_mass.narrow(2, own, c_s - 1 - own));
    }
    Tensor::cat(parts, 2).into_primitive().tensor()
}

/// Composed 2x2 average pooling (see [`NetOps::pool2`]): two `mean_dim`s over a 6-D view.
pub(crate) fn composed_pool2<B: NetOps>(x: FloatTensor<B>) -> FloatTensor<B> {
    let x = wrap::<B, 4>(x);
    let [b, h, w, c] = x.dims();
    x.reshape([b, h / 2, 2, w / 2, 2, c])
        .mean_dim(4)
        .mean_dim(2)
        .reshape([b, h / 2, w / 2, c])
        .into_primitive()
        .tensor()
}

/// Composed nearest 2x upsampling (see [`NetOps::upsample2`]), by broadcasting, so every
/// backend differentiates it.
pub(crate) fn composed_upsample2<B: NetOps>(x: FloatTensor<B>) -> FloatTensor<B> {
    let x = wrap::<B, 4>(x);
    let [b, h, w, c] = x.dims();
    x.reshape([b, h, 1, w, 1, c])
        .expand([b, h, 2, w, 2, c])
        .reshape([b, 2 * h, 2 * w, c])
        .into_primitive()
        .tensor()
}
