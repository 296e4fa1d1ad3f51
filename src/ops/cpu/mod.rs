//! CPU kernels behind [`NetOps`](super::NetOps) for burn's `NdArray<f32>` backend
//! (`ops/ndarray.rs` calls them), and the helpers they share: views of the tensor primitive,
//! a buffer wrapped as a tensor, and passes over row blocks on the rayon pool.
//!
//! Why: burn-ndarray multiplies through `matrixmultiply` (AVX2 only, ~1.2x on 2 threads),
//! builds a dense layer from separate matmul, broadcast add and five-pass ELU, and gathers
//! rows element by element through `IxDyn` indices; at the paper's sizes the encoder's
//! `[B T N, 256] x [256, 1250]` products are ~98 % of the work, so these kernels set the CPU
//! training speed (`minflow bench train`) and the node's step time.
//!
//! - `gemm.rs`: the dense layer `x @ W + b` (optionally followed by ELU) and its backward on
//!   the `gemm` crate (runtime dispatch to AVX-512 or AVX2 micro-kernels), or streaming the
//!   weights for a handful of rows (the inference step).
//! - `activation.rs`: ELU and SiLU and their gradients through a vectorisable `expm1`.
//! - `elu_mean.rs`: the encoder's first layer, ELU and mean pooling in one pass.
//! - `grid.rs`: the grid model's input channels, 2x2 pooling and 2x upsampling (inference).
//! - `mingru.rs`: the minGRU's and the minLSTM's inference updates in one pass each.
//! - `scan.rs`: the linear recurrence of minGRU / minLSTM as one sequential pass.
//! - `adam_pass.rs`: one Adam step in one pass, in place.
//! - `conv.rs`: im2col and col2im of the grid model's convolutions.
//! - `transfer.rs`: the grid model's P2G scatter-add and G2P gather, and its sparse stencil.
//! - `pool.rs`: a whole inference step on the rayon pool with a worker kept awake.
//! - `winograd.rs`: the forward of the grid model's 3x3 convolutions by Winograd F(4x4, 3x3)
//!   (inference).
//!
//! The kernels take operands with any strides (transposes are free) and return row-major
//! contiguous tensors, or None (or their input back) for operands they do not handle. Results
//! are deterministic for a given thread count: every output element is reduced by one thread
//! in a fixed order.

pub(crate) mod activation;
pub(crate) mod adam_pass;
pub(crate) mod conv;
pub(crate) mod elu_mean;
pub(crate) mod gemm;
pub(crate) mod grid;
pub(crate) mod mingru;
pub(crate) mod pool;
pub(crate) mod scan;
pub(crate) mod transfer;
pub(crate) mod winograd;

use burn::backend::ndarray::{NdArrayTensor, SharedArray};
use burn::backend::NdArray;
use burn::tensor::ops::FloatTensor;
use ndarray::{ArrayView2, CowArray, Ix2, IxDyn};
use rayon::prelude::*;

/// The CPU float tensor primitive.
pub(crate) type CpuTensor = FloatTensor<NdArray<f32>>;

/// Products with fewer multiply-adds than this run on the calling thread.
pub(crate) const PARALLEL_WORK: usize = 1 << 20;

/// Rows per task in the element-wise passes.
pub(crate) const ROWS_PER_TASK: usize = 64;

/// A 2-D view of an f32 CPU tensor (any strides); None for other dtypes or ranks.
pub(crate) fn view2(t: &CpuTensor) -> Option<ArrayView2<'_, f32>> {
    match t {
        NdArrayTensor::F32(s) => s.view().into_dimensionality().ok(),
        _ => None,
    }
}

/// An f32 CPU tensor `[..., cols]` as a `[rows, cols]` matrix: a view when its layout allows
/// (2-D with any non-zero strides, or row-major), else a row-major copy. None for other
/// dtypes and scalars.
pub(crate) fn rows_view(t: &CpuTensor) -> Option<CowArray<'_, f32, Ix2>> {
    let NdArrayTensor::F32(s) = t else {
        return None;
    };
    let v = s.view();
    let cols = *v.shape().last()?;
    let rows = v.shape()[..v.ndim() - 1].iter().product::<usize>();
    if v.ndim() == 2 && v.strides().iter().all(|&s| s != 0) {
        return v.into_dimensionality::<Ix2>().ok().map(CowArray::from);
    }
    if v.is_standard_layout() {
        return v
            .into_shape_with_order((rows, cols))
            .ok()
            .map(CowArray::from);
    }
    let owned = v.as_standard_layout().into_owned();
    owned
        .into_shape_with_order((rows, cols))
        .ok()
        .map(CowArray::from)
}

/// A 1-D contiguous slice of an f32 CPU tensor (the bias).
pub(crate) fn slice1(t: &CpuTensor) -> Option<ndarray::ArrayView1<'_, f32>> {
    match t {
        NdArrayTensor::F32(s) => s.view().into_dimensionality().ok(),
        _ => None,
    }
}

/// Wraps a row-major buffer as a CPU tensor of `shape` (no copy).
pub(crate) fn tensor(data: Vec<f32>, shape: &[usize]) -> CpuTensor {
    let array = SharedArray::<f32>::from_shape_vec(IxDyn(shape), data)
        .expect("buffer length matches the shape");
    NdArrayTensor::from(array)
}

/// Runs `f` over row blocks of a row-major `[rows, cols]` buffer, in parallel for large ones.
pub(crate) fn for_rows(buf: &mut [f32], cols: usize, f: impl Fn(&mut [f32]) + Sync + Send) {
    let chunk = (ROWS_PER_TASK * cols.max(1)).max(1);
    if buf.len() * 4 >= PARALLEL_WORK {
        buf.par_chunks_mut(chunk).for_each(f);
    } else {
        buf.chunks_mut(chunk).for_each(f);
    }
}

/// The tensor's buffer as a uniquely owned row-major Vec (a copy only when shared or strided).
pub(crate) fn into_vec(x: CpuTensor) -> (Vec<f32>, Vec<usize>) {
    let shape = x.shape_vec();
    let array = match x {
        NdArrayTensor::F32(s) => s.into_owned(),
        other => panic!("expected an f32 tensor, got {:?}", other.dtype_name()),
    };
    let data = if array.is_standard_layout() {
        match array.try_into_owned_nocopy() {
            Ok(owned) => owned.into_raw_vec_and_offset().0,
            Err(shared) => shared.iter().copied().collect(),
        }
    } else {
        array.iter().copied().collect()
    };
    (data, shape)
}

/// Applies `f` to row blocks of the tensor's own buffer (in place when unshared).
pub(crate) fn map_owned(x: CpuTensor, f: impl Fn(&mut [f32]) + Sync + Send) -> CpuTensor {
    let (mut data, shape) = into_vec(x);
    let cols = shape.last().copied().unwrap_or(1);
    for_rows(&mut data, cols, f);
    tensor(data, &shape)
}

/// Applies `f` to aligned blocks of the tensor's own buffer and `other` (same length).
pub(crate) fn map_owned_zip(
    x: CpuTensor,
    other: &[f32],
    f: impl Fn(&mut [f32], &[f32]) + Sync + Send,
) -> CpuTensor {
    let (mut data, shape) = into_vec(x);
    const BLOCK: usize = 1 << 14;
    if data.len() * 4 >= PARALLEL_WORK {
        data.par_chunks_mut(BLOCK)
            .zip(other.par_chunks(BLOCK))
            .for_each(|(a, b)| f(a, b));
    } else {
        data.chunks_mut(BLOCK)
            .zip(other.chunks(BLOCK))
            .for_each(|(a, b)| f(a, b));
    }
    tensor(data, &shape)
}

/// The f32 tensor's elements in row-major order (borrowed when already so) and its shape.
pub(crate) fn dense(t: &CpuTensor) -> Option<(std::borrow::Cow<'_, [f32]>, Vec<usize>)> {
    let NdArrayTensor::F32(s) = t else {
        return None;
    };
    let v = s.view();
    let shape = v.shape().to_vec();
    let data = match v.to_slice() {
        Some(slice) => std::borrow::Cow::Borrowed(slice),
        None => std::borrow::Cow::Owned(v.iter().copied().collect()),
    };
    Some((data, shape))
}

/// Shape and dtype helpers on the primitive.
pub(crate) trait PrimitiveInfo {
    fn shape_vec(&self) -> Vec<usize>;
    fn dtype_name(&self) -> String;
}

impl PrimitiveInfo for CpuTensor {
    fn shape_vec(&self) -> Vec<usize> {
        use burn::tensor::TensorMetadata;
        self.shape().iter().copied().collect()
    }
    fn dtype_name(&self) -> String {
        use burn::tensor::TensorMetadata;
        format!("{:?}", self.dtype())
    }
}
