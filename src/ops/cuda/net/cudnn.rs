//! The grid model's 3x3 convolutions on CUDA through cuDNN (feature `cuda`), forward and
//! backward, recorded as custom operations of burn's fusion layer: no im2col columns are
//! written, and a training step's convolution is one forward kernel and two backward ones
//! (data and filter gradients) instead of im2col, products and col2im.
//!
//! Why: im2col wrote 9x each convolution's input as columns for cuBLAS to read back, 11.4 GB a
//! 256-scene call of `all-grid-mingru` and the call's largest kernel cost (docs/kernels.md,
//! "Roofline"); training recomputed the columns in its backward and summed their gradients
//! back with col2im. cuDNN's implicit-GEMM and Winograd convolutions (Chetlur et al. 2014,
//! "cuDNN: Efficient Primitives for Deep Learning") read each tile of the input in place; they
//! are the kernels PyTorch's `conv2d` runs. cuDNN is a library of NVIDIA's, loaded at run
//! time (`libcudnn.so.9`, the `nvidia-cudnn-cu13` wheel PyTorch installs, or a system cuDNN)
//! when `MINFLOW_CUDA_CONV=cudnn` asks for it; without it the convolutions stay im2col and
//! cuBLAS ([`available`], `cuda/mod.rs`'s `conv_form`).
//!
//! Each call is queued on cubecl's device thread like a kernel launch (`cuda::device::on_device`).
//! It used to read its tensors' device pointers from the caller's thread through cubecl's
//! device queue, which waited for every launch queued before it (0.8-1.3 ms a call on one
//! H100), so the host could not run ahead of the GPU; with that wait cuDNN was not worth it
//! (docs/kernels.md, "Where a GPU call's time goes").
//!
//! Layout: the grid is channels-last, `[B, H, W, C]` (cuDNN's `NHWC`). Inference's weights
//! go to cuDNN as `[C_out, 3, 3, C_in]` (`KRSC`, its NHWC filter layout), copied from burn's
//! `[C_out, C_in, 3, 3]`; training's im2col matrix `[C_in 9, C_out]` is read in place as the
//! filter of the transposed convolution, and its gradient written in place ([`Transposed`]).
//! Same padding, stride 1, cross-correlation (burn's and PyTorch's `Conv2d`). The math
//! follows `--gpu-gemm`: TF32 tensor cores for `tf32`, FMA only (full FP32) otherwise. Each
//! algorithm is the fastest of those cuDNN times on the shape, once per shape
//! (`cudnnFindConvolution*Algorithm`, as PyTorch's `cudnn.benchmark`), the gradients'
//! restricted to deterministic ones, so a training step gives the same bits on every run
//! with the same algorithms, as the fixed-point P2G does (two runs may time differently and
//! pick others, which round differently).
//!
//! How a custom operation joins the fusion stream, and why no host wait is needed: see
//! `cublas.rs`; the cuDNN handle is bound to the same cubecl stream in the same way, and its
//! workspace is a cubecl allocation dropped on the device thread right after the enqueue
//! (stream order keeps it alive for the kernel).
//!
//! Where: this file records the convolutions on burn's fusion stream (the passes, the
//! layouts, [`Transposed`]); `cuda/net/cudnn_plan.rs` makes a shape's descriptors and picks its
//! algorithm; `cuda/net/cudnn_calls.rs` keeps the handles and plans and queues the calls. A GPU
//! where cuDNN loads but does not start runs its convolutions as im2col ([`ready`]).

use burn::tensor::ops::{FloatTensor, FloatTensorOps};
use burn::tensor::{DType, Shape, Slice, TensorMetadata, TensorPrimitive};
use burn_fusion::stream::{Operation, OperationStreams};
use burn_fusion::FusionRuntime;
use burn_ir::{CustomOpIr, HandleContainer, OperationIr, TensorIr};
use cudarc::cudnn::sys;

use super::conv::{contiguous, Cuda, Inner, Runtime};
use super::cudnn_calls::{run, start};
use super::cudnn_plan::{Dims, Pass};
use crate::ops::composed_grid::dims4;

/// Whether cuDNN can be loaded (checked once).
pub(in crate::ops) fn available() -> bool {
    static PRESENT: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    // SAFETY: only tries to open the shared library.
    *PRESENT.get_or_init(|| unsafe { sys::is_culib_present() })
}

/// Whether cuDNN starts on GPU `index` (its handle made on the first call, checked once a
/// GPU): where it does not, the failure is logged once and the caller runs the convolution
/// as im2col instead, as `MINFLOW_CUDA_CONV=im2col` would (`cuda/mod.rs`).
pub(in crate::ops) fn ready(index: usize) -> bool {
    static KNOWN: std::sync::Mutex<Vec<(usize, bool)>> = std::sync::Mutex::new(Vec::new());
    let mut known = KNOWN.lock().unwrap_or_else(|e| e.into_inner());
    if let Some(&(_, ok)) = known.iter().find(|(i, _)| *i == index) {
        return ok;
    }
    let ok = match start(index) {
        Ok(()) => true,
        Err(e) => {
            tracing::warn!("cuDNN does not start on GPU {index} ({e}): im2col instead");
            false
        }
    };
    known.push((index, ok));
    ok
}

/// The recorded operation: one output, the sum of one or more passes of one kind, each with
/// two inputs (see [`Pass`]; the inputs in order, two a pass). Several forward passes are
/// the convolution of a channel concatenation, part by part: the output accumulates them
/// (cuDNN's `beta` = 1), so the concatenation is never written.
#[derive(Debug)]
struct ConvOp {
    desc: CustomOpIr,
    pass: Pass,
    flip: bool,
    dims: Vec<Dims>,
}

impl Operation<Runtime> for ConvOp {
    fn execute(&self, handles: &mut HandleContainer<<Runtime as FusionRuntime>::FusionHandle>) {
        let inputs = (self.desc.inputs.iter())
            .map(|t| contiguous(handles.get_float_tensor::<Inner>(t)))
            .collect();
        let out = (run(self.pass, self.flip, &self.dims, inputs))
            .unwrap_or_else(|e| e.raise("cuDNN convolution"));
        handles.register_float_tensor::<Inner>(&self.desc.outputs[0].id, out);
    }
}

/// Records the sum of `pass` over `passes` (each its sizes and two inputs, see [`Pass`]) on
/// the inputs' fusion stream; returns its output. `flip`: a true convolution (cuDNN's
/// `CUDNN_CONVOLUTION`, the filter flipped in space) instead of a cross-correlation, for the
/// passes of [`Transposed`].
fn record(
    pass: Pass,
    flip: bool,
    passes: Vec<(Dims, [FloatTensor<Cuda>; 2])>,
) -> FloatTensor<Cuda> {
    let client = passes[0].1[0].client.clone();
    let inputs: Vec<FloatTensor<Cuda>> = passes.iter().flat_map(|(_, t)| t.clone()).collect();
    let streams = OperationStreams::with_inputs(&inputs);
    let dims: Vec<Dims> = passes.iter().map(|(d, _)| *d).collect();
    let out = TensorIr::uninit(
        client.create_empty_handle(),
        pass.out_shape(dims[0]),
        DType::F32,
    );
    let name = match (pass, flip) {
        (Pass::Forward, false) => "minflow_cudnn_conv",
        (Pass::Data, false) => "minflow_cudnn_conv_data",
        (Pass::Filter, false) => "minflow_cudnn_conv_filter",
        (Pass::Forward, true) => "minflow_cudnn_flipped_conv",
        (Pass::Data, true) => "minflow_cudnn_flipped_conv_data",
        (Pass::Filter, true) => "minflow_cudnn_flipped_conv_filter",
    };
    let irs: Vec<TensorIr> = inputs.into_iter().map(|t| t.into_ir()).collect();
    let desc = CustomOpIr::new(name, &irs, &[out]);
    let op = ConvOp {
        desc: desc.clone(),
        pass,
        flip,
        dims,
    };
    client
        .register(streams, OperationIr::Custom(desc), op)
        .remove(0)
}

/// `weight` `[C_out, C_in, 3, 3]` (burn's `Conv2d`) as cuDNN's `[C_out, 3, 3, C_in]`.
fn krsc_of_oihw(weight: FloatTensor<Cuda>) -> FloatTensor<Cuda> {
    <Cuda as FloatTensorOps<Cuda>>::float_permute(weight, &[0, 2, 3, 1])
}

/// An im2col product's matrix `[C_in 9, C_out]` (row `i 9 + s`, offset `s = 3 ky + kx`) as
/// cuDNN's `[C_out, 3, 3, C_in]`.
fn krsc_of_matrix(matrix: FloatTensor<Cuda>, c_in: usize, c_out: usize) -> FloatTensor<Cuda> {
    type F = Cuda;
    let m = <F as FloatTensorOps<F>>::float_reshape(matrix, Shape::new([c_in, 3, 3, c_out]));
    <F as FloatTensorOps<F>>::float_permute(m, &[3, 1, 2, 0])
}

/// cuDNN's `[C_out, 3, 3, C_in]` filter gradient as the matrix's `[C_in 9, C_out]`.
fn matrix_of_krsc(dw: FloatTensor<Cuda>, c_in: usize, c_out: usize) -> FloatTensor<Cuda> {
    type F = Cuda;
    let m = <F as FloatTensorOps<F>>::float_permute(dw, &[3, 1, 2, 0]);
    <F as FloatTensorOps<F>>::float_reshape(m, Shape::new([c_in * 9, c_out]))
}

/// `y + bias` over the last dim (`bias` `[C]`).
fn add_bias(y: FloatTensor<Cuda>, bias: FloatTensor<Cuda>) -> FloatTensor<Cuda> {
    type F = Cuda;
    let c = bias.shape()[0];
    let rank = y.shape().num_dims();
    let mut dims = vec![1; rank];
    dims[rank - 1] = c;
    let bias = <F as FloatTensorOps<F>>::float_reshape(bias, Shape::from(dims));
    <F as FloatTensorOps<F>>::float_add(y, bias)
}

/// [`NetOps::conv3x3_forward`](crate::ops::NetOps::conv3x3_forward) on the GPU through cuDNN,
/// without SiLU: the 3x3 same-padding convolution of the channel concatenation of `parts`
/// (`[B, H, W, C_p]` each), `weight` `[C_out, C_in, 3, 3]`, `bias` `[C_out]` ->
/// `[B, H, W, C_out]`. One concatenation when there are several parts, one copy of the
/// weights into `[C_out, 3, 3, C_in]`, one cuDNN kernel, the bias added by burn (fused with
/// what follows).
///
/// # Panics
/// The parts' channels do not add up to the weight's `C_in`, or the kernel is not 3x3; a
/// cuDNN error.
pub(in crate::ops) fn conv3x3(
    parts: &[FloatTensor<Cuda>],
    weight: &FloatTensor<Cuda>,
    bias: Option<&FloatTensor<Cuda>>,
) -> FloatTensor<Cuda> {
    type F = Cuda;
    let ws = weight.shape();
    let c: usize = parts.iter().map(|p| p.shape()[3]).sum();
    assert!(
        ws[1] == c && ws[2] == 3 && ws[3] == 3,
        "conv3x3: weight {ws:?} does not take {c} input channels with a 3x3 kernel"
    );
    let mut first = 0;
    let passes = (parts.iter())
        .map(|x| {
            let [b, h, w, c] = dims4::<Cuda>(x);
            let part = match parts.len() {
                1 => weight.clone(),
                _ => {
                    let all = Slice::new(0, None, 1);
                    let these = Slice::new(first as isize, Some((first + c) as isize), 1);
                    <F as FloatTensorOps<F>>::float_slice(weight.clone(), &[all, these, all, all])
                }
            };
            first += c;
            ([b, h, w, c, ws[0]], [x.clone(), krsc_of_oihw(part)])
        })
        .collect();
    let y = record(Pass::Forward, false, passes);
    match bias {
        Some(bias) => add_bias(y, bias.clone()),
        None => y,
    }
}

/// Whether `MINFLOW_CUDNN_FILTER=permuted` asks for training's convolutions on weights copied
/// into cuDNN's `KRSC` layout, each pass, instead of the [`Transposed`] passes that read the
/// matrix in place: to compare the two in one binary (docs/kernels.md; [`crate::switches`]).
fn permuted_filter() -> bool {
    crate::switches::cudnn_permuted_filter()
}

/// Training's three passes on an im2col matrix `[C_in 9, C_out]` read in place, without the
/// copy into `[C_out, 3, 3, C_in]` a pass that [`krsc_of_matrix`] makes.
///
/// The matrix's memory, `[C_in, 3, 3, C_out]`, is the `KRSC` filter of the *transposed*
/// convolution: `K` = `C_in`, `C` = `C_out`. A convolution's data gradient is the
/// convolution of `dy` with the filter transposed in its channels and flipped in space
/// (Dumoulin and Visin 2016, "A guide to convolution arithmetic for deep learning", section
/// 4), so with cuDNN's true convolution (`CUDNN_CONVOLUTION`, which flips the filter) the
/// passes swap roles on the transposed sizes `[B, H, W, C_out, C_in]`:
///
/// - forward, `y` `[B, H, W, C_out]`: the transposed convolution's data pass, `dy` = `x`;
/// - data gradient, `dx` `[B, H, W, C_in]`: its forward pass on `x` = `dy`;
/// - filter gradient, `[C_in, 3, 3, C_out]` (the matrix's layout): its filter pass with
///   `x` = `dy` and `dy` = `x`.
///
/// Same padding (1 on each side) is symmetric, so it carries over unchanged.
struct Transposed;

impl Transposed {
    /// `[B, H, W, C_out, C_in]`: the transposed convolution's sizes.
    fn dims([b, h, w, c_in, c_out]: Dims) -> Dims {
        [b, h, w, c_out, c_in]
    }

    /// The matrix `[C_in 9, C_out]` as the transposed convolution's filter `[C_in, 3, 3,
    /// C_out]` (a view, no copy).
    fn filter(matrix: FloatTensor<Cuda>, c_in: usize, c_out: usize) -> FloatTensor<Cuda> {
        <Cuda as FloatTensorOps<Cuda>>::float_reshape(matrix, Shape::new([c_in, 3, 3, c_out]))
    }
}

/// [`NetOps::im2col_linear`](crate::ops::NetOps::im2col_linear) for `k` = 3 through cuDNN: `x`
/// `[B, H, W, C_in]`, `matrix` `[C_in 9, C_out]`, `bias` `[C_out]` -> `[B H W, C_out]`; the
/// matrix read in place ([`Transposed`]).
pub(in crate::ops) fn im2col_linear(
    x: FloatTensor<Cuda>,
    matrix: FloatTensor<Cuda>,
    bias: Option<FloatTensor<Cuda>>,
) -> FloatTensor<Cuda> {
    let [b, h, w, c_in] = dims4::<Cuda>(&x);
    let c_out = matrix.shape()[1];
    let dims = [b, h, w, c_in, c_out];
    let y = match permuted_filter() {
        false => {
            let filter = Transposed::filter(matrix, c_in, c_out);
            record(
                Pass::Data,
                true,
                vec![(Transposed::dims(dims), [x, filter])],
            )
        }
        true => {
            let weight = krsc_of_matrix(matrix, c_in, c_out);
            record(Pass::Forward, false, vec![(dims, [x, weight])])
        }
    };
    let y = <Cuda as FloatTensorOps<Cuda>>::float_reshape(y, Shape::new([b * h * w, c_out]));
    match bias {
        Some(bias) => add_bias(y, bias),
        None => y,
    }
}

/// [`NetOps::im2col_linear_backward`](crate::ops::NetOps::im2col_linear_backward) for `k` = 3
/// through cuDNN: from `x` `[B, H, W, C_in]`, `matrix` `[C_in 9, C_out]` and `grad` `[B H W,
/// C_out]`, `[dx [B, H, W, C_in], dmatrix [C_in 9, C_out], dbias [C_out]]`, each where `need`
/// says; the matrix read and its gradient written in place ([`Transposed`]).
pub(in crate::ops) fn im2col_linear_backward(
    x: FloatTensor<Cuda>,
    matrix: FloatTensor<Cuda>,
    grad: FloatTensor<Cuda>,
    need: [bool; 3],
) -> [Option<FloatTensor<Cuda>>; 3] {
    type F = Cuda;
    let [b, h, w, c_in] = dims4::<Cuda>(&x);
    let c_out = matrix.shape()[1];
    let dims = [b, h, w, c_in, c_out];
    let dy = <F as FloatTensorOps<F>>::float_reshape(grad.clone(), Shape::new([b, h, w, c_out]));
    let permuted = permuted_filter();
    let dx = need[0].then(|| match permuted {
        false => {
            let filter = Transposed::filter(matrix, c_in, c_out);
            record(
                Pass::Forward,
                true,
                vec![(Transposed::dims(dims), [dy.clone(), filter])],
            )
        }
        true => {
            let weight = krsc_of_matrix(matrix, c_in, c_out);
            record(Pass::Data, false, vec![(dims, [dy.clone(), weight])])
        }
    });
    let dmatrix = need[1].then(|| {
        let dw = match permuted {
            false => record(Pass::Filter, true, vec![(Transposed::dims(dims), [dy, x])]),
            true => matrix_of_krsc(
                record(Pass::Filter, false, vec![(dims, [x, dy])]),
                c_in,
                c_out,
            ),
        };
        <F as FloatTensorOps<F>>::float_reshape(dw, Shape::new([c_in * 9, c_out]))
    });
    let dbias = need[2].then(|| {
        use crate::ops::NetOps;
        let split = F::kernels(&F::float_device(&grad)).split_weight_grad;
        let grad = burn::tensor::Tensor::<F, 2>::from_primitive(TensorPrimitive::Float(grad));
        crate::ops::composed::bias_grad(grad, split)
    });
    [dx, dmatrix, dbias]
}
