//! The grid model's 3x3 inference convolutions on CUDA without materialised im2col columns
//! (feature `cuda`): [`conv3x3`], burn-cubecl's implicit-GEMM convolution on the
//! channels-last grid, recorded as a custom operation of burn's fusion layer.
//!
//! An implicit-GEMM convolution (cuDNN's "implicit GEMM", Chetlur et al. 2014, "cuDNN:
//! Efficient Primitives for Deep Learning", section 3) is the im2col product with the columns
//! never written: each tile of the product loads its rows of the virtual column matrix
//! straight from the input. burn-cubecl's `conv_forward_nhwc` with `ConvStrategy::ImplicitGemm`
//! runs cubek's simple synchronous CMMA convolution (TF32 tensor cores for f32, f32
//! accumulation, the bias loaded into the accumulator); it takes NHWC input and `[C_out, 3, 3,
//! C_in]` weights. im2col + cuBLAS wrote 9x each convolution's input as columns and read them
//! back: 11.4 GB a 256-scene call of `all-grid-mingru` (docs/kernels.md, "Roofline").
//!
//! Measured slower, so not the default: `MINFLOW_CUDA_CONV=implicit` takes it, to compare
//! the two in one binary (`tests/gpu/run.sh fused`). On one H200 the 256-scene call of
//! `all-grid-mingru` took 0.165 ms a scene-frame with it against 0.134 with im2col and
//! cuBLAS, 0.164 against 0.146 on another (docs/kernels.md, "Roofline"). Training keeps
//! im2col (its backward is col2im and products: `cuda/net/conv.rs`).

use burn::cubecl::cuda::CudaRuntime;
use burn::tensor::ops::{ConvOptions, FloatTensor, FloatTensorOps};
use burn::tensor::{Shape, TensorMetadata};
use burn_cubecl::kernel::conv::{conv_forward_nhwc, ConvStrategy};
use burn_fusion::stream::{Operation, OperationStreams};
use burn_fusion::FusionRuntime;
use burn_ir::{CustomOpIr, HandleContainer, OperationIr, TensorIr};

use super::conv::{contiguous, Cuda, Inner, Runtime};
use crate::ops::OpsError;

/// The recorded convolution: inputs `[x, weight]` and `[bias]` when it has one, output `[y]`.
#[derive(Debug)]
struct ConvOp {
    desc: CustomOpIr,
}

impl Operation<Runtime> for ConvOp {
    fn execute(&self, handles: &mut HandleContainer<<Runtime as FusionRuntime>::FusionHandle>) {
        let inputs = &self.desc.inputs;
        let mut get = |k: usize| contiguous(handles.get_float_tensor::<Inner>(&inputs[k]));
        let (x, weight) = (get(0), get(1));
        let bias = (inputs.len() > 2).then(|| get(2));
        let options = ConvOptions::new([1, 1], [1, 1], [1, 1], 1);
        let y = conv_forward_nhwc::<CudaRuntime, 2>(
            x.clone(),
            weight.clone(),
            bias.clone(),
            options.clone(),
            ConvStrategy::ImplicitGemm,
        )
        .or_else(|e| {
            static WARNED: std::sync::Once = std::sync::Once::new();
            WARNED.call_once(|| {
                tracing::warn!("implicit-GEMM convolution refused ({e:?}): direct convolution")
            });
            conv_forward_nhwc::<CudaRuntime, 2>(x, weight, bias, options, ConvStrategy::Direct)
        })
        .unwrap_or_else(|e| OpsError::cubecl("direct convolution", e).raise("3x3 convolution"));
        handles.register_float_tensor::<Inner>(&self.desc.outputs[0].id, contiguous(y));
    }
}

/// [`NetOps::conv3x3_forward`](crate::ops::NetOps::conv3x3_forward) on the GPU, without SiLU: the
/// 3x3 same-padding convolution of the channel concatenation of `parts` (`[B, H, W, C_p]`
/// each), `weight` `[C_out, C_in, 3, 3]` (burn's `Conv2d` layout), `bias` `[C_out]` ->
/// `[B, H, W, C_out]`. One concatenation when there are several parts, one copy of the
/// weights into `[C_out, 3, 3, C_in]`, one convolution kernel.
///
/// # Panics
/// The parts' channels do not add up to the weight's `C_in`, or the kernel is not 3x3.
pub(in crate::ops) fn conv3x3(
    parts: &[FloatTensor<Cuda>],
    weight: &FloatTensor<Cuda>,
    bias: Option<&FloatTensor<Cuda>>,
) -> FloatTensor<Cuda> {
    let x = super::conv::cat_channels(parts);
    let (xs, ws) = (x.shape(), weight.shape());
    assert!(
        ws[1] == xs[3] && ws[2] == 3 && ws[3] == 3,
        "conv3x3: weight {ws:?} does not take input {xs:?} with a 3x3 kernel"
    );
    let weight = <Cuda as FloatTensorOps<Cuda>>::float_permute(weight.clone(), &[0, 2, 3, 1]);
    let client = x.client.clone();
    let dtype = x.dtype();
    let out_shape = Shape::new([xs[0], xs[1], xs[2], ws[0]]);
    let mut inputs = vec![x, weight];
    inputs.extend(bias.cloned());
    let streams = OperationStreams::with_inputs(&inputs);
    let out = TensorIr::uninit(client.create_empty_handle(), out_shape, dtype);
    let irs: Vec<TensorIr> = inputs.into_iter().map(|t| t.into_ir()).collect();
    let desc = CustomOpIr::new("minflow_conv3x3_implicit", &irs, &[out]);
    let op = ConvOp { desc: desc.clone() };
    client
        .register(streams, OperationIr::Custom(desc), op)
        .remove(0)
}
