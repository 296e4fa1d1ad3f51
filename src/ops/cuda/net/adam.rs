//! One Adam step as one cubecl kernel on burn's CUDA backend (feature `cuda`), the gradient's
//! norm clipping folded in: [`adam_step`], recorded as a custom operation of burn's fusion
//! layer (how one joins the fusion stream: see `cublas.rs`).
//!
//! Why: composed from burn's tensor operations, a parameter's step is about 13 operations
//! and its clipping (burn's `GradientClipping::Norm`) about 7 more, each recorded by the host;
//! a grid training step's 40 parameters made ~700 of its ~2,600 launches, and that step is
//! bound by the host's recording, not the GPU (docs/kernels.md, "Roofline"). Here a parameter
//! costs one sum of squares (burn's reduction, when clipping) and one element-wise kernel
//! that reads the parameter, gradient and moments once and writes the three new tensors.

use burn::cubecl::cuda::CudaRuntime;
use burn::tensor::ops::{FloatTensor, FloatTensorOps};
use burn::tensor::{Shape, TensorMetadata};
use burn_cubecl::cubecl;
use burn_fusion::stream::{Operation, OperationStreams};
use burn_fusion::FusionRuntime;
use burn_ir::{CustomOpIr, HandleContainer, OperationIr, TensorIr};
use cubecl::prelude::*;

use super::conv::{contiguous, elementwise, Cuda, Inner, Runtime};
use crate::ops::adam_step::AdamStep;

/// One Adam step per element (Kingma & Ba 2015, Algorithm 1, in burn's and PyTorch's `eps *
/// sqrt(1 - b2^t)` form): `g` = `grad[i]`, times `min(1, max_norm / (sqrt(squares[0]) +
/// tiny))` when `clip` (burn's `GradientClipping::Norm`, `squares` the gradient's sum of
/// squares, `[1]`); `m = b1 m + (1 - b1) g`, `v = b2 v + (1 - b2) g^2` (from zero when
/// `fresh`: `m` and `v` are then not read), `param -= lr (m factor) / (sqrt(v) + eps)`. All
/// tensors contiguous and of one length but `squares`; one thread per element. `tiny` is
/// `f32::MIN_POSITIVE`, burn's guard.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn adam_kernel<F: Float>(
    param: &Tensor<F>,
    grad: &Tensor<F>,
    m: &Tensor<F>,
    v: &Tensor<F>,
    squares: &Tensor<F>,
    param_out: &mut Tensor<F>,
    m_out: &mut Tensor<F>,
    v_out: &mut Tensor<F>,
    lr: f32,
    beta_1: f32,
    beta_2: f32,
    factor: f32,
    eps: f32,
    max_norm: f32,
    tiny: f32,
    #[comptime] clip: bool,
    #[comptime] fresh: bool,
    #[define(F)] _dtype: StorageType,
) {
    let i = ABSOLUTE_POS;
    if i >= param_out.len() {
        terminate!();
    }
    let (lr, b1, b2) = (F::cast_from(lr), F::cast_from(beta_1), F::cast_from(beta_2));
    let (factor, eps) = (F::cast_from(factor), F::cast_from(eps));
    let mut g = grad[i];
    if clip {
        let coef = F::cast_from(max_norm) / (F::sqrt(squares[0]) + F::cast_from(tiny));
        if coef < F::new(1.0) {
            g *= coef;
        }
    }
    let mut m1 = (F::new(1.0) - b1) * g;
    let mut m2 = (F::new(1.0) - b2) * (g * g);
    if !fresh {
        m1 += b1 * m[i];
        m2 += b2 * v[i];
    }
    m_out[i] = m1;
    v_out[i] = m2;
    param_out[i] = param[i] - lr * ((m1 * factor) / (F::sqrt(m2) + eps));
}

/// The recorded step: inputs `[param, grad]`, then `[m, v]` unless it is the first step,
/// then `[squares]` when clipping; outputs `[param, m, v]`.
#[derive(Debug)]
struct AdamOp {
    desc: CustomOpIr,
    step: AdamStep,
    fresh: bool,
}

impl Operation<Runtime> for AdamOp {
    fn execute(&self, handles: &mut HandleContainer<<Runtime as FusionRuntime>::FusionHandle>) {
        let (inputs, outputs) = (&self.desc.inputs, &self.desc.outputs);
        let mut get = |k: usize| contiguous(handles.get_float_tensor::<Inner>(&inputs[k]));
        let (param, grad) = (get(0), get(1));
        let (m, v) = match self.fresh {
            true => (grad.clone(), grad.clone()),
            false => (get(2), get(3)),
        };
        let clip = self.step.max_norm.is_some();
        let squares = match clip {
            true => get(inputs.len() - 1),
            false => grad.clone(),
        };
        let client = param.client.clone();
        let new = || {
            burn_cubecl::ops::numeric::empty_device_contiguous_dtype(
                client.clone(),
                param.device.clone(),
                param.meta.shape().clone(),
                param.dtype,
            )
        };
        let (param_out, m_out, v_out) = (new(), new(), new());
        let c = &self.step;
        let (bc2, factor) = c.corrections();
        let (cube_count, cube_dim) = elementwise(&client, param.meta.num_elements());
        let dtype = param.dtype.into();
        adam_kernel::launch::<CudaRuntime>(
            &client,
            cube_count,
            cube_dim,
            param.into_tensor_arg(),
            grad.into_tensor_arg(),
            m.into_tensor_arg(),
            v.into_tensor_arg(),
            squares.into_tensor_arg(),
            param_out.clone().into_tensor_arg(),
            m_out.clone().into_tensor_arg(),
            v_out.clone().into_tensor_arg(),
            c.lr,
            c.beta_1,
            c.beta_2,
            factor,
            c.epsilon * bc2,
            c.max_norm.unwrap_or(0.0),
            f32::MIN_POSITIVE,
            clip,
            self.fresh,
            dtype,
        );
        for (ir, out) in outputs.iter().zip([param_out, m_out, v_out]) {
            handles.register_float_tensor::<Inner>(&ir.id, out);
        }
    }
}

/// [`NetOps::adam_step`](crate::ops::NetOps::adam_step) on the GPU: the new parameter and moments
/// (each shaped like `param`) from one kernel, after one sum of squares of `grad` when
/// `c.max_norm` is set; `m` and `v` None for the first step (read as zero).
///
/// # Panics
/// `grad`, `m` or `v` not shaped like `param`, or only one of `m` and `v` given.
pub(crate) fn adam_step(
    param: FloatTensor<Cuda>,
    grad: FloatTensor<Cuda>,
    m: Option<FloatTensor<Cuda>>,
    v: Option<FloatTensor<Cuda>>,
    c: &AdamStep,
) -> (FloatTensor<Cuda>, FloatTensor<Cuda>, FloatTensor<Cuda>) {
    let shape: Shape = param.shape();
    for t in [Some(&grad), m.as_ref(), v.as_ref()].into_iter().flatten() {
        assert!(
            t.shape() == shape,
            "adam_step: {:?} is not shaped like the parameter {shape:?}",
            t.shape()
        );
    }
    let client = param.client.clone();
    let dtype = param.dtype();
    let squares = c.max_norm.map(|_| {
        <Cuda as FloatTensorOps<Cuda>>::float_sum(<Cuda as FloatTensorOps<Cuda>>::float_mul(
            grad.clone(),
            grad.clone(),
        ))
    });
    assert_eq!(
        m.is_none(),
        v.is_none(),
        "adam_step: both moments or neither (the first step)"
    );
    let fresh = m.is_none();
    let mut inputs = vec![param, grad];
    if !fresh {
        inputs.extend(m.into_iter().chain(v));
    }
    inputs.extend(squares);
    let streams = OperationStreams::with_inputs(&inputs);
    let out = || TensorIr::uninit(client.create_empty_handle(), shape.clone(), dtype);
    let outputs = [out(), out(), out()];
    let irs: Vec<TensorIr> = inputs.into_iter().map(|t| t.into_ir()).collect();
    let desc = CustomOpIr::new("minflow_adam_step", &irs, &outputs);
    let op = AdamOp {
        desc: desc.clone(),
        step: *c,
        fresh,
    };
    let mut out = client.register(streams, OperationIr::Custom(desc), op);
    let v = out.pop().expect("three outputs");
    let m = out.pop().expect("three outputs");
    let p = out.pop().expect("three outputs");
    (p, m, v)
}
