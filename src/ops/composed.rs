//! [`NetOps`]'s defaults for the dense layer, ELU and the pooled ELU in burn's tensor
//! operations: what a backend without its own kernels runs (burn's CUDA backend fuses their
//! element-wise chains into single kernels), and what the CPU falls back to for operands its
//! kernels do not take. The dense layer's backward splits a long weight-gradient reduction
//! into row chunks ([`weight_grad_chunks`]) so that a GPU has enough output tiles to spread.

use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Tensor, TensorMetadata, TensorPrimitive};

use super::NetOps;

/// [`NetOps::elu_mean_forward`]'s default: ELU of the dense layer, then the mean over N.
pub(crate) fn composed_elu_mean<B: NetOps>(
    x: FloatTensor<B>,
    w: FloatTensor<B>,
    b: FloatTensor<B>,
) -> FloatTensor<B> {
    particle_mean::<B>(B::linear_elu_forward(x, w, Some(b)))
}

/// The mean over particles: `[M, N, H]` -> `[M, H]`.
pub(crate) fn particle_mean<B: Backend>(a: FloatTensor<B>) -> FloatTensor<B> {
    let a = Tensor::<B, 3>::from_primitive(TensorPrimitive::Float(a));
    let [m, _, h] = a.dims();
    a.mean_dim(1).reshape([m, h]).into_primitive().tensor()
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
/// through [`NetOps::matmul`].
pub(crate) fn composed_linear<B: NetOps>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    bias: Option<FloatTensor<B>>,
) -> FloatTensor<B> {
    composed_linear_map::<B>(x, weight, bias, |y| y)
}

/// `f(x @ weight + bias)` with `f` applied to the `[rows, out]` rows.
pub(crate) fn composed_linear_map<B: NetOps>(
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

/// [`NetOps::elu_backward`] with burn's tensor ops: `grad` where `out > 0`, else
/// `grad * (out + 1)`.
pub(crate) fn composed_elu_backward<B: Backend>(
    out: FloatTensor<B>,
    grad: FloatTensor<B>,
) -> FloatTensor<B> {
    let shape = out.shape();
    let n = shape.num_elements();
    let flat =
        |t| Tensor::<B, 1>::from_primitive(TensorPrimitive::Float(B::float_reshape(t, [n].into())));
    let (out, grad) = (flat(out), flat(grad));
    B::float_reshape((grad * elu_slope(out)).into_primitive().tensor(), shape)
}

/// `d ELU / dx` from the ELU output: 1 where `out > 0`, `out + 1` elsewhere.
pub(crate) fn elu_slope<B: Backend, const D: usize>(out: Tensor<B, D>) -> Tensor<B, D> {
    let positive = out.clone().greater_elem(0.0);
    (out + 1.0).mask_fill(positive, 1.0)
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
    if rows < 2 * MIN_CHUNK_ROWS {
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

/// [`NetOps::linear_backward`] with burn's tensor ops: `dx = g w^T`, `dw = x^T g`,
/// `db = sum_rows g`, the last two as sums of [`weight_grad_chunks`] partial products when
/// the rows are many (what lets a GPU spread them).
pub(crate) fn composed_linear_backward<B: NetOps>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    grad: FloatTensor<B>,
    need: [bool; 3],
) -> [Option<FloatTensor<B>>; 3] {
    let shape = x.shape();
    let d_in = *shape.last().expect("rank >= 2");
    let d_out = *grad.shape().last().expect("rank >= 2");
    let rows = shape.num_elements() / d_in.max(1);
    let device = B::float_device(&x);
    let split = B::kernels(&device).split_weight_grad;
    let chunks = if !split || B::splits_reduction(&device, d_in, rows, d_out) {
        1
    } else {
        weight_grad_chunks(rows, d_in, d_out)
    };
    linear_backward_in_chunks::<B>(x, weight, grad, need, chunks, split)
}

/// A dense layer's bias gradient `sum_rows g` (`grad` `[rows, d_out]` -> `[d_out]`): a
/// reduction over the rows with `d_out` outputs, split into [`weight_grad_chunks`] for
/// `d_out` alone unless `split` is off (a `[16, 25,000, 1,250]` middle-axis sum ran on 40
/// thread blocks; the cuDNN convolutions' `[B H W, C_out]` sums took 63 % of a training
/// step's kernel time unsplit).
pub(crate) fn bias_grad<B: NetOps>(grad: Tensor<B, 2>, split: bool) -> FloatTensor<B> {
    let [rows, d_out] = grad.dims();
    let chunks = if split {
        weight_grad_chunks(rows, 1, d_out)
    } else {
        1
    };
    let db = if chunks > 1 {
        grad.reshape([chunks, rows / chunks, d_out])
            .sum_dim(1)
            .sum_dim(0)
    } else {
        grad.sum_dim(0).unsqueeze::<3>()
    };
    db.reshape([d_out]).into_primitive().tensor()
}

/// [`composed_linear_backward`] with `chunks` row chunks (dividing the rows) for the weight
/// gradient; the bias gradient is split by its own [`weight_grad_chunks`] unless `split` is off.
fn linear_backward_in_chunks<B: NetOps>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    grad: FloatTensor<B>,
    need: [bool; 3],
    chunks: usize,
    split: bool,
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
    let db = need[2].then(|| bias_grad(grad, split));
    [dx, dw, db]
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::ops::FloatTensorOps;
    use burn::tensor::Distribution;

    type C = burn::backend::NdArray<f32>;

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
        let one =
            linear_backward_in_chunks::<C>(x.clone(), w.clone(), g.clone(), [true; 3], 1, true);
        let split = linear_backward_in_chunks::<C>(x, w, g, [true; 3], 12, true);
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
