//! cuDNN's plans for the grid model's 3x3 convolutions on CUDA (feature `cuda`; what the
//! convolutions are and why: `cuda/net/cudnn.rs`): a convolution's passes and sizes, and for
//! each shape and pass its descriptors (NHWC, same padding, stride 1) and the fastest
//! algorithm cuDNN times for it (`cudnnFindConvolution*Algorithm`, as PyTorch's
//! `cudnn.benchmark`; the gradients' deterministic ones only, so a training step gives the
//! same bits on every run with the same algorithms). `cuda/net/cudnn_calls.rs` makes each plan
//! once per GPU and shape and runs it.

use std::mem::MaybeUninit;

use burn::tensor::Shape;
use cudarc::cudnn::{result as dnn, sys};

use crate::ops::OpsError;

/// Which of a convolution's three passes an operation runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(in crate::ops) enum Pass {
    /// `y = conv(x, w)`: inputs `[x, w]`, output `y` `[B, H, W, C_out]`.
    Forward,
    /// `dx` from `dy` and `w`: inputs `[dy, w]`, output `[B, H, W, C_in]`.
    Data,
    /// `dw` from `x` and `dy`: inputs `[x, dy]`, output `[C_out, 3, 3, C_in]`.
    Filter,
}

/// A convolution's sizes: `[B, H, W, C_in, C_out]`.
pub(in crate::ops) type Dims = [usize; 5];

impl Pass {
    /// The output's shape of this pass on `dims`.
    pub(in crate::ops) fn out_shape(self, [b, h, w, c_in, c_out]: Dims) -> Shape {
        match self {
            Pass::Forward => Shape::new([b, h, w, c_out]),
            Pass::Data => Shape::new([b, h, w, c_in]),
            Pass::Filter => Shape::new([c_out, 3, 3, c_in]),
        }
    }
}

/// What a [`Plan`] is made for: the pass, the sizes, TF32 math, and whether the filter is
/// flipped (a true convolution, `cuda/net/cudnn.rs`'s `Transposed`).
pub(in crate::ops) type Key = (Pass, Dims, bool, bool);

/// A shape's descriptors: its input's, output's, filter's and convolution's.
type Descriptors = (
    sys::cudnnTensorDescriptor_t,
    sys::cudnnTensorDescriptor_t,
    sys::cudnnFilterDescriptor_t,
    sys::cudnnConvolutionDescriptor_t,
);

/// A cuDNN descriptor set and algorithm for one convolution shape and pass: what
/// `cudnn_calls::run` needs besides the pointers. Created once per (GPU, pass, shape,
/// math) and kept.
pub(in crate::ops) struct Plan {
    /// The input's descriptor, `[B, H, W, C_in]` (NHWC).
    pub(in crate::ops) x: sys::cudnnTensorDescriptor_t,
    /// The output's descriptor, `[B, H, W, C_out]` (NHWC).
    pub(in crate::ops) y: sys::cudnnTensorDescriptor_t,
    /// The filter's descriptor, `[C_out, 3, 3, C_in]` (`KRSC`).
    pub(in crate::ops) w: sys::cudnnFilterDescriptor_t,
    /// Padding 1, stride 1, no dilation; a true convolution or a cross-correlation.
    pub(in crate::ops) conv: sys::cudnnConvolutionDescriptor_t,
    /// The pass's algorithm.
    pub(in crate::ops) algo: Algo,
    /// The algorithm's workspace, in bytes.
    pub(in crate::ops) workspace: usize,
}

/// The algorithm of a [`Plan`], by pass.
#[derive(Clone, Copy)]
pub(in crate::ops) enum Algo {
    /// Of [`Pass::Forward`].
    Forward(sys::cudnnConvolutionFwdAlgo_t),
    /// Of [`Pass::Data`].
    Data(sys::cudnnConvolutionBwdDataAlgo_t),
    /// Of [`Pass::Filter`].
    Filter(sys::cudnnConvolutionBwdFilterAlgo_t),
}

/// cuDNN's error for `what`.
pub(in crate::ops) fn check<T>(what: &str, r: Result<T, dnn::CudnnError>) -> Result<T, OpsError> {
    r.map_err(|e| OpsError::cudnn(what, e))
}

/// The tensor, filter and convolution descriptors of `dims` (NHWC, same padding, stride 1;
/// a true convolution where `flip`), with `tf32`'s math type.
///
/// # Errors
/// A size that does not fit cuDNN's `i32`; cuDNN's.
///
/// # Safety
/// cuDNN is loaded (a handle was made).
unsafe fn descriptors(dims: Dims, tf32: bool, flip: bool) -> Result<Descriptors, OpsError> {
    use sys::cudnnDataType_t::CUDNN_DATA_FLOAT as FLOAT;
    use sys::cudnnTensorFormat_t::CUDNN_TENSOR_NHWC as NHWC;
    let int = |v: usize| OpsError::fit_i32("cuDNN size", v);
    let [b, h, w, c_in, c_out] = [
        int(dims[0])?,
        int(dims[1])?,
        int(dims[2])?,
        int(dims[3])?,
        int(dims[4])?,
    ];
    let x = check("tensor", dnn::create_tensor_descriptor())?;
    check(
        "tensor",
        dnn::set_tensor4d_descriptor(x, NHWC, FLOAT, [b, c_in, h, w]),
    )?;
    let y = check("tensor", dnn::create_tensor_descriptor())?;
    check(
        "tensor",
        dnn::set_tensor4d_descriptor(y, NHWC, FLOAT, [b, c_out, h, w]),
    )?;
    let wd = check("filter", dnn::create_filter_descriptor())?;
    check(
        "filter",
        dnn::set_filter4d_descriptor(wd, FLOAT, NHWC, [c_out, c_in, 3, 3]),
    )?;
    let conv = check("convolution", dnn::create_convolution_descriptor())?;
    let mode = match flip {
        false => sys::cudnnConvolutionMode_t::CUDNN_CROSS_CORRELATION,
        true => sys::cudnnConvolutionMode_t::CUDNN_CONVOLUTION,
    };
    check(
        "convolution",
        dnn::set_convolution2d_descriptor(conv, 1, 1, 1, 1, 1, 1, mode, FLOAT),
    )?;
    let math = match tf32 {
        true => sys::cudnnMathType_t::CUDNN_TENSOR_OP_MATH,
        false => sys::cudnnMathType_t::CUDNN_FMA_MATH,
    };
    check("math type", dnn::set_convolution_math_type(conv, math))?;
    Ok((x, y, wd, conv))
}

/// The fastest algorithm cuDNN times for `pass` on the descriptors `(x, y, w, conv)` of
/// `dims` (every algorithm run on buffers of these sizes, what PyTorch's `cudnn.benchmark`
/// does; the gradients' deterministic ones only): the algorithm, its workspace bytes, the
/// math type it ran with, and its time in ms.
///
/// # Errors
/// cuDNN's search failed, or found no algorithm that runs ([`OpsError::NoAlgorithm`]).
///
/// # Safety
/// `handle` is a live cuDNN handle with its GPU's context current; the descriptors are alive.
unsafe fn fastest(
    handle: sys::cudnnHandle_t,
    pass: Pass,
    dims: Dims,
    (x, y, wd, conv): Descriptors,
) -> Result<(Algo, usize, sys::cudnnMathType_t, f32), OpsError> {
    let ok = sys::cudnnStatus_t::CUDNN_STATUS_SUCCESS;
    let deterministic = sys::cudnnDeterminism_t::CUDNN_DETERMINISTIC;
    /// How many of cuDNN's timed algorithms are looked at.
    const RANKED: usize = 16;
    let mut count = 0;
    // The fastest successful algorithm of a search (`$perf` its result type, `$find` the
    // search's call with the descriptors in its order), the gradients' deterministic only.
    macro_rules! fastest {
        ($perf:ty, $kind:ident, $what:literal, $find:ident($($desc:expr),*)) => {{
            let mut perf = [MaybeUninit::<$perf>::zeroed(); RANKED];
            let found = sys::$find(
                handle,
                $($desc,)*
                RANKED as i32,
                &mut count,
                perf.as_mut_ptr().cast(),
            );
            check($what, found.result())?;
            let best = perf[..count as usize]
                .iter()
                .map(|p| p.assume_init())
                .find(|p| p.status == ok && (pass == Pass::Forward || p.determinism == deterministic))
                .ok_or(OpsError::NoAlgorithm { pass: $what, dims })?;
            (Algo::$kind(best.algo), best.memory, best.mathType, best.time)
        }};
    }
    Ok(match pass {
        Pass::Forward => fastest!(
            sys::cudnnConvolutionFwdAlgoPerf_t,
            Forward,
            "forward",
            cudnnFindConvolutionForwardAlgorithm(x, wd, conv, y)
        ),
        Pass::Data => fastest!(
            sys::cudnnConvolutionBwdDataAlgoPerf_t,
            Data,
            "data gradient",
            cudnnFindConvolutionBackwardDataAlgorithm(wd, y, conv, x)
        ),
        Pass::Filter => fastest!(
            sys::cudnnConvolutionBwdFilterAlgoPerf_t,
            Filter,
            "filter gradient",
            cudnnFindConvolutionBackwardFilterAlgorithm(x, y, conv, wd)
        ),
    })
}

/// Makes the descriptors of `pass` on `dims` and picks its algorithm (see the module doc);
/// the plan keeps the math type the timed algorithm ran with.
///
/// # Errors
/// [`descriptors`]' and [`fastest`]'s.
///
/// # Safety
/// `handle` is a live cuDNN handle with its GPU's context current.
pub(in crate::ops) unsafe fn plan(
    handle: sys::cudnnHandle_t,
    (pass, dims, tf32, flip): Key,
) -> Result<Plan, OpsError> {
    let descs = descriptors(dims, tf32, flip)?;
    let (x, y, w, conv) = descs;
    // cudnnFind*: once per shape.
    let (algo, workspace, math, ms) = fastest(handle, pass, dims, descs)?;
    check("math type", dnn::set_convolution_math_type(conv, math))?;
    tracing::debug!(
        "cuDNN {pass:?} {dims:?} (tf32 {tf32}, flipped {flip}): {:?}, {math:?}, {workspace} B workspace, {ms:.3} ms",
        match algo {
            Algo::Forward(a) => format!("{a:?}"),
            Algo::Data(a) => format!("{a:?}"),
            Algo::Filter(a) => format!("{a:?}"),
        }
    );
    Ok(Plan {
        x,
        y,
        w,
        conv,
        algo,
        workspace,
    })
}
