//! The grid architecture's convolution and activation operations behind
//! [`super::FusedElu`]: im2col (the rows a 3x3 same-padding convolution multiplies), its
//! adjoint col2im, and SiLU (`x sigmoid(x)`, Elfwing et al. 2018) with its gradient. Here live
//! the composed defaults (any backend), the autodiff nodes and the single-pass CPU kernels.
//!
//! Why: on the CPU, burn-ndarray's row gather (`select`, element by element through `IxDyn`
//! indices) was half of a grid step and its sigmoid (an `exp` and a `log` per element)
//! another 13 % (`perf` over `minflow eval` with the shipped grid model: 222 ms per step).
//!
//! Column order: row `(b H + y) W + x` of im2col holds, at column `i k^2 + ky k + kx`,
//! channel `i` of input position `(y + ky - k/2, x + kx - k/2)` (zero outside the grid): the
//! order of burn's `Conv2d` weight `[C_out, C_in, k, k]` flattened over its last three dims,
//! so the product's weight matrix is a transposed view of it (no copy).

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{unary, Backward, Ops, OpsKind};
use burn::backend::Autodiff;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Tensor, TensorMetadata, TensorPrimitive};
use rayon::prelude::*;

use super::cpu_kernels::{self, CpuTensor, PrimitiveInfo};
use super::FusedElu;

fn wrap<B: FusedElu, const D: usize>(x: FloatTensor<B>) -> Tensor<B, D> {
    Tensor::from_primitive(TensorPrimitive::Float(x))
}

fn dims4<B: FusedElu>(x: &FloatTensor<B>) -> [usize; 4] {
    let s = x.shape();
    [s[0], s[1], s[2], s[3]]
}

/// Composed im2col: the `k^2` shifted slices of the zero-padded input, interleaved so that
/// the offset is the fastest column index.
///
/// # Shapes
/// - `x`: `[B, H, W, C]` -> `[B H W, C k^2]`
pub(crate) fn composed_im2col<B: FusedElu>(x: FloatTensor<B>, k: usize) -> FloatTensor<B> {
    let [b, h, w, c] = dims4::<B>(&x);
    let x = wrap::<B, 4>(x);
    let half = k / 2;
    let device = x.device();
    let zeros_h = Tensor::zeros([b, half, w, c], &device);
    let x = Tensor::cat(vec![zeros_h.clone(), x, zeros_h], 1);
    let zeros_w = Tensor::zeros([b, h + 2 * half, half, c], &device);
    let x = Tensor::cat(vec![zeros_w.clone(), x, zeros_w], 2);
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

/// Composed col2im, the adjoint of [`composed_im2col`]: each offset's block added back at
/// its shifted position of a zero-padded grid, which is then cropped.
///
/// # Shapes
/// - `cols`: `[B H W, C k^2]` -> `[B, H, W, C]` (= `shape`)
pub(crate) fn composed_col2im<B: FusedElu>(
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
pub(crate) fn composed_silu<B: FusedElu>(x: FloatTensor<B>) -> FloatTensor<B> {
    let shape = x.shape();
    let flat = wrap::<B, 1>(B::float_reshape(x, [shape.num_elements()].into()));
    let y = burn::tensor::activation::silu(flat)
        .into_primitive()
        .tensor();
    B::float_reshape(y, shape)
}

/// Composed SiLU gradient: `grad (s + x s (1 - s))`, `s = sigmoid(x)`.
pub(crate) fn composed_silu_backward<B: FusedElu>(
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

/// The autodiff node of [`FusedElu::im2col`] on backends with native kernels: its backward
/// is [`FusedElu::col2im`].
pub(crate) fn autodiff_im2col<B: FusedElu, C: CheckpointStrategy>(
    x: FloatTensor<Autodiff<B, C>>,
    k: usize,
) -> FloatTensor<Autodiff<B, C>> {
    #[derive(Debug)]
    struct Im2colBackward;

    impl<B: FusedElu> Backward<B, 1> for Im2colBackward {
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

/// The autodiff node of [`FusedElu::silu`]: keeps the input.
pub(crate) fn autodiff_silu<B: FusedElu, C: CheckpointStrategy>(
    x: FloatTensor<Autodiff<B, C>>,
) -> FloatTensor<Autodiff<B, C>> {
    #[derive(Debug)]
    struct SiluBackward;

    impl<B: FusedElu> Backward<B, 1> for SiluBackward {
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

/// `x sigmoid(x)` through the vectorisable `expm1`: `sigmoid(x) = 1 / (2 + expm1(-x))`.
#[inline(always)]
fn sigmoid1(v: f32) -> f32 {
    1.0 / (2.0 + cpu_kernels::expm1(-v))
}

/// CPU SiLU, in place when the buffer is not shared.
pub(crate) fn cpu_silu(x: CpuTensor) -> CpuTensor {
    cpu_kernels::map_owned(x, |block| block.iter_mut().for_each(|v| *v *= sigmoid1(*v)))
}

/// CPU SiLU gradient, in place in `grad` when it is unshared; None when `x` is not a
/// row-major f32 tensor of `grad`'s size.
pub(crate) fn cpu_silu_backward(x: &CpuTensor, grad: CpuTensor) -> Result<CpuTensor, CpuTensor> {
    let Some((x, shape)) = cpu_kernels::dense(x) else {
        return Err(grad);
    };
    if shape != grad.shape_vec() {
        return Err(grad);
    }
    Ok(cpu_kernels::map_owned_zip(grad, &x, |g, x| {
        g.iter_mut().zip(x).for_each(|(g, &x)| {
            let s = sigmoid1(x);
            *g *= s + x * s * (1.0 - s);
        })
    }))
}

/// CPU im2col: one task per image row; each output row is written in order (channel, then
/// offset), reading the `k^2` source pixels it needs (zeros outside the grid). None for
/// tensors that are not f32 of rank 4, or kernels larger than 3 x 3.
pub(crate) fn cpu_im2col(x: &CpuTensor, k: usize) -> Option<CpuTensor> {
    const MAX_KK: usize = 9;
    let (data, shape) = cpu_kernels::dense(x)?;
    let [b, h, w, c] = <[usize; 4]>::try_from(shape).ok()?;
    let (kk, half) = (k * k, (k / 2) as isize);
    if kk > MAX_KK {
        return None;
    }
    let row = c * kk;
    let mut out = Vec::new();
    let fill = |by: usize, dst: &mut [f32]| {
        let (bb, y) = (by / h, (by % h) as isize);
        for (x, dst) in dst.chunks_exact_mut(row).enumerate() {
            // Source offset of each kernel offset, or None outside the grid.
            let mut src = [None; MAX_KK];
            for (s, src) in src.iter_mut().enumerate().take(kk) {
                let yy = y + (s / k) as isize - half;
                let xx = x as isize + (s % k) as isize - half;
                if yy >= 0 && xx >= 0 && yy < h as isize && xx < w as isize {
                    *src = Some(((bb * h + yy as usize) * w + xx as usize) * c);
                }
            }
            if src[..kk].iter().all(Option::is_some) {
                let src: [usize; MAX_KK] = std::array::from_fn(|s| src[s].unwrap_or(0));
                for (i, dst) in dst.chunks_exact_mut(kk).enumerate() {
                    for (d, &o) in dst.iter_mut().zip(&src[..kk]) {
                        *d = data[o + i];
                    }
                }
            } else {
                for (i, dst) in dst.chunks_exact_mut(kk).enumerate() {
                    for (d, o) in dst.iter_mut().zip(&src[..kk]) {
                        *d = o.map_or(0.0, |o| data[o + i]);
                    }
                }
            }
        }
    };
    out.resize(b * h * w * row, 0.0);
    if out.len() * 4 >= 1 << 20 {
        out.par_chunks_mut(w * row)
            .enumerate()
            .for_each(|(by, dst)| fill(by, dst));
    } else {
        out.chunks_mut(w * row)
            .enumerate()
            .for_each(|(by, dst)| fill(by, dst));
    }
    Some(cpu_kernels::tensor(out, &[b * h * w, row]))
}

/// CPU col2im: each output position sums its `k^2` entries of `cols` (a gather, so one task
/// per image row writes only its own row, in a fixed order). None for tensors that are not
/// f32 of rank 2 with `B H W` rows and `C k^2` columns.
pub(crate) fn cpu_col2im(cols: &CpuTensor, shape: [usize; 4], k: usize) -> Option<CpuTensor> {
    let (data, cshape) = cpu_kernels::dense(cols)?;
    let [b, h, w, c] = shape;
    let (kk, half) = (k * k, (k / 2) as isize);
    let row = c * kk;
    if cshape != [b * h * w, row] {
        return None;
    }
    let mut out = vec![0f32; b * h * w * c];
    let fill = |by: usize, dst: &mut [f32]| {
        let (bb, y) = (by / h, (by % h) as isize);
        for (x, dst) in dst.chunks_exact_mut(c).enumerate() {
            for s in 0..kk {
                // Output (y, x) was read as offset s by position (y - dy, x - dx).
                let yy = y - ((s / k) as isize - half);
                let xx = x as isize - ((s % k) as isize - half);
                if yy < 0 || xx < 0 || yy >= h as isize || xx >= w as isize {
                    continue;
                }
                let src = ((bb * h + yy as usize) * w + xx as usize) * row;
                for (i, v) in dst.iter_mut().enumerate() {
                    *v += data[src + i * kk + s];
                }
            }
        }
    };
    if out.len() * 4 * kk >= 1 << 20 {
        out.par_chunks_mut(w * c)
            .enumerate()
            .for_each(|(by, dst)| fill(by, dst));
    } else {
        out.chunks_mut(w * c)
            .enumerate()
            .for_each(|(by, dst)| fill(by, dst));
    }
    Some(cpu_kernels::tensor(out, &shape))
}

/// `silu(x)` through [`FusedElu::silu`], any shape.
pub fn silu<B: FusedElu, const D: usize>(x: Tensor<B, D>) -> Tensor<B, D> {
    wrap(B::silu(x.into_primitive().tensor()))
}

/// `[B, H, W, C]` -> `[B H W, C k^2]` through [`FusedElu::im2col`] (column order in the module
/// doc).
pub fn im2col<B: FusedElu>(x: Tensor<B, 4>, k: usize) -> Tensor<B, 2> {
    wrap(B::im2col(x.into_primitive().tensor(), k))
}
