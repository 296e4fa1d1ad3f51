//! [`NetOps`] for burn's CUDA backend (feature `cuda`, `--device cuda`): the composed
//! defaults, with the large products through cuBLAS ([`crate::ops::cublas`]), the grid model's
//! im2col / col2im as single kernels ([`crate::ops::cuda::net::conv`]), and sparse stencil, P2G and G2P
//! kernels ([`crate::ops::cuda::net::stencil`]; inference and training take them), and the Adam step
//! with its gradient clipping as one kernel ([`crate::ops::cuda::net::adam`]); the inference 3x3
//! convolutions run as im2col and cuBLAS by default, through cuDNN forward and backward
//! (`MINFLOW_CUDA_CONV=cudnn`, [`crate::ops::cuda::net::cudnn`]), or as burn-cubecl's implicit GEMMs
//! for inference (`MINFLOW_CUDA_CONV=implicit`, [`crate::ops::cuda::net::implicit_conv`]).

//!
//! The device code by job: `net/` the network's layers (the convolutions, cuDNN, the
//! stencil transfers, the minRNN updates, Adam), `projection/` the constraint projection's
//! parts (one file per part, named as its host form in `model/constraints/`), and here what
//! both share: `device.rs` (a GPU's context and the calls queued on cubecl's device thread),
//! `read.rs` (a tensor read back behind the recorded work) and `collective.rs` (the
//! all-reduce of data-parallel training's gradients over NCCL).

pub(in crate::ops) mod collective;
pub(in crate::ops) mod device;
pub(in crate::ops) mod net;
pub(in crate::ops) mod projection;
pub(in crate::ops) mod read;

use burn::tensor::ops::{FloatTensor, IntTensor};

use std::sync::OnceLock;

use crate::ops::cuda::net::conv::Cuda;
use crate::ops::NetOps;
use crate::switches::{self, CudaConv};

/// How the grid model's 3x3 convolutions run on CUDA (`MINFLOW_CUDA_CONV`; docs/speed.md,
/// "Where a GPU call's time goes", has the measurements that chose the default).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(in crate::ops) enum ConvForm {
    /// im2col and a product (cuBLAS for the large ones), col2im in the backward
    /// ([`crate::ops::cuda::net::conv`]): `MINFLOW_CUDA_CONV=im2col`, and the default where cuDNN does
    /// not load.
    Im2col,
    /// cuDNN's kernels for inference (`NetOps::conv3x3_forward`: `eval`, `node`, rollouts),
    /// im2col for training: the default where `libcudnn.so.9` loads. A 256-scene call of
    /// `all-grid-mingru` took 0.094 ms a scene-frame against 0.141 with im2col on one H100;
    /// training at batch 16 / 32, 245.6 / 456.0 samples/s with cuDNN against 298.9 / 499.1
    /// (two rounds' means, one H100 call).
    CudnnInference,
    /// cuDNN's kernels, forward and backward ([`crate::ops::cuda::net::cudnn`]):
    /// `MINFLOW_CUDA_CONV=cudnn`. Training takes about half im2col's GPU memory (less than
    /// PyTorch's) at 0.78-0.92x its speed (docs/train_speed.md, "Training's convolutions through
    /// cuDNN, in place").
    Cudnn,
    /// burn-cubecl's implicit-GEMM convolution for inference, im2col for training
    /// ([`crate::ops::cuda::net::implicit_conv`]): `MINFLOW_CUDA_CONV=implicit`.
    Implicit,
}

/// The [`ConvForm`] of this process: `MINFLOW_CUDA_CONV=im2col | cudnn | implicit`
/// ([`switches::cuda_conv`]), read once; [`ConvForm::CudnnInference`] when unset and cuDNN
/// loads, im2col when it does not. cuDNN asked for and missing falls back to im2col with a
/// warning; so does a GPU where cuDNN loads but does not start ([`cudnn_on`]).
pub(in crate::ops) fn conv_form() -> ConvForm {
    static FORM: OnceLock<ConvForm> = OnceLock::new();
    *FORM.get_or_init(|| {
        let asked = switches::cuda_conv();
        let cudnn = crate::ops::cuda::net::cudnn::available();
        let form = match asked {
            Some(CudaConv::Implicit) => ConvForm::Implicit,
            Some(CudaConv::Im2col) => ConvForm::Im2col,
            Some(CudaConv::Cudnn) if cudnn => ConvForm::Cudnn,
            Some(CudaConv::Cudnn) => {
                tracing::warn!("MINFLOW_CUDA_CONV=cudnn: libcudnn.so.9 not found, im2col instead");
                ConvForm::Im2col
            }
            None if cudnn => ConvForm::CudnnInference,
            None => ConvForm::Im2col,
        };
        tracing::debug!("CUDA convolutions: {form:?}");
        form
    })
}

/// Whether `form` runs `x`'s convolution through cuDNN: a cuDNN form, on a GPU where cuDNN
/// starts ([`crate::ops::cuda::net::cudnn::ready`]; where it does not, the convolution runs as im2col,
/// as [`ConvForm::Im2col`] would, after one warning).
fn cudnn_on(form: ConvForm, x: &FloatTensor<Cuda>) -> bool {
    matches!(form, ConvForm::Cudnn | ConvForm::CudnnInference)
        && crate::ops::cuda::net::cudnn::ready(x.client.device().index)
}

/// The composed defaults, whose element-wise chains burn's fusion layer compiles into single
/// kernels; the large products go to cuBLAS, which also splits their long reductions.
impl NetOps for burn::backend::Cuda<f32, i32> {
    /// im2col and col2im are single kernels; SiLU stays composed (fused by burn) under its own
    /// autodiff node.
    const NATIVE_CONV_OPS: bool = true;
    /// The sparse kernels of [`crate::ops::cuda::net::stencil`] (P2G in fixed point, the same to the
    /// bit on every run), for inference and for training through the autodiff backend.
    const DENSE_STENCIL: bool = false;

    /// [`NetOps::DENSE_STENCIL`] unless `MINFLOW_CUDA_TRANSFERS=dense`
    /// ([`switches::cuda_dense_transfers`]), which takes the separable dense products
    /// instead, to compare the two in one binary (docs/scale.md, docs/cuda.md).
    fn dense_stencil() -> bool {
        switches::cuda_dense_transfers()
    }

    fn sparse_stencil(
        pos: &FloatTensor<Self>,
        n: usize,
    ) -> Option<(IntTensor<Self>, FloatTensor<Self>)> {
        Some(crate::ops::cuda::net::stencil::stencil(pos.clone(), n))
    }

    fn stencil_gather(
        grid: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        crate::ops::cuda::net::stencil::gather(grid, index, weight)
    }

    fn stencil_splat(
        values: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
        nodes: usize,
    ) -> FloatTensor<Self> {
        crate::ops::cuda::net::stencil::splat(values, index, weight, nodes)
    }

    fn im2col(x: FloatTensor<Self>, k: usize) -> FloatTensor<Self> {
        crate::ops::cuda::net::conv::im2col(x, k)
    }

    fn col2im(cols: FloatTensor<Self>, shape: [usize; 4], k: usize) -> FloatTensor<Self> {
        crate::ops::cuda::net::conv::col2im(cols, shape, k)
    }

    fn adam_step(
        param: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        m: Option<FloatTensor<Self>>,
        v: Option<FloatTensor<Self>>,
        c: &crate::ops::AdamStep,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        if switches::cuda_composed_adam() {
            return crate::ops::adam_step::composed_adam::<Self>(param, grad, m, v, c);
        }
        crate::ops::cuda::net::adam::adam_step(param, grad, m, v, c)
    }

    fn conv3x3_forward(
        parts: &[FloatTensor<Self>],
        weight: &FloatTensor<Self>,
        bias: Option<&FloatTensor<Self>>,
        silu: bool,
        prepared: &crate::ops::PreparedWeights,
    ) -> Option<FloatTensor<Self>> {
        let _ = prepared;
        let y = match conv_form() {
            form if cudnn_on(form, weight) => {
                crate::ops::cuda::net::cudnn::conv3x3(parts, weight, bias)
            }
            ConvForm::Implicit => {
                crate::ops::cuda::net::implicit_conv::conv3x3(parts, weight, bias)
            }
            _ => return None,
        };
        Some(if silu { Self::silu(y) } else { y })
    }

    fn im2col_linear(
        x: FloatTensor<Self>,
        matrix: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
        k: usize,
    ) -> FloatTensor<Self> {
        match (k, conv_form()) {
            (3, ConvForm::Cudnn) if cudnn_on(ConvForm::Cudnn, &x) => {
                crate::ops::cuda::net::cudnn::im2col_linear(x, matrix, bias)
            }
            _ => crate::ops::composed_grid::composed_im2col_linear::<Self>(x, matrix, bias, k),
        }
    }

    fn im2col_linear_backward(
        x: FloatTensor<Self>,
        matrix: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        k: usize,
        need: [bool; 3],
    ) -> [Option<FloatTensor<Self>>; 3] {
        match (k, conv_form()) {
            (3, ConvForm::Cudnn) if cudnn_on(ConvForm::Cudnn, &x) => {
                crate::ops::cuda::net::cudnn::im2col_linear_backward(x, matrix, grad, need)
            }
            _ => {
                crate::ops::composed_grid::im2col_linear_backward::<Self>(x, matrix, grad, k, need)
            }
        }
    }

    fn matmul(a: FloatTensor<Self>, b: FloatTensor<Self>) -> FloatTensor<Self> {
        crate::ops::cublas::matmul(a, b)
    }

    /// A copy to pinned host memory queued behind the work recorded so far
    /// ([`crate::ops::cuda::read`]).
    fn read_ahead(x: FloatTensor<Self>) -> Option<crate::ops::ReadAhead> {
        Some(crate::ops::cuda::read::read_ahead(x))
    }

    /// The kernels of `projection/`, unless `MINFLOW_CUDA_PROJECTION=host`.
    fn project_constraints(
        out: FloatTensor<Self>,
        input: Option<FloatTensor<Self>>,
        plan: &crate::ops::ProjectionPlan,
    ) -> Option<(FloatTensor<Self>, FloatTensor<Self>)> {
        (Self::projects_constraints())
            .then(|| crate::ops::cuda::projection::op::project(out, input, plan))
    }

    /// Unless `MINFLOW_CUDA_PROJECTION=host`.
    fn projects_constraints() -> bool {
        !switches::cuda_host_projection()
    }

    /// One kernel ([`crate::ops::cuda::net::frames`]) with `MINFLOW_CUDA_FRAMES=kernel`.
    fn particle_frames(frames: crate::ops::ParticleFrames<Self>) -> Option<FloatTensor<Self>> {
        (switches::cuda_fused_frames())
            .then(|| crate::ops::cuda::net::frames::particle_frames(frames))
            .flatten()
    }

    /// One kernel ([`crate::ops::cuda::net::minrnn`]) unless `MINFLOW_CUDA_MINRNN=composed`.
    fn mingru_update(hg: FloatTensor<Self>, h: Option<FloatTensor<Self>>) -> FloatTensor<Self> {
        match switches::cuda_composed_minrnn() {
            true => crate::ops::mingru::composed_mingru_update::<Self>(hg, h),
            false => crate::ops::cuda::net::minrnn::mingru_update(hg, h),
        }
    }

    /// One kernel ([`crate::ops::cuda::net::minrnn`]) unless `MINFLOW_CUDA_MINRNN=composed`.
    fn minlstm_update(
        hfi: &FloatTensor<Self>,
        h: Option<&FloatTensor<Self>>,
    ) -> Option<FloatTensor<Self>> {
        (!switches::cuda_composed_minrnn())
            .then(|| crate::ops::cuda::net::minrnn::minlstm_update(hfi.clone(), h.cloned()))
    }

    fn splits_reduction(device: &Self::Device, m: usize, k: usize, n: usize) -> bool {
        crate::ops::cublas::worth_it(Self::kernels(device).gemm, m, k, n)
    }

    fn kernels(device: &Self::Device) -> crate::ops::Kernels {
        crate::ops::cublas::kernels(device.index)
    }

    fn all_reduce_sum(
        tensors: Vec<FloatTensor<Self>>,
        devices: &[Self::Device],
    ) -> Result<Vec<FloatTensor<Self>>, Vec<FloatTensor<Self>>> {
        collective::all_reduce_sum(tensors, devices)
    }
}
