//! [`NetOps`] for burn's CUDA backend (feature `cuda`, `--device cuda`): the composed
//! defaults, with the large products through cuBLAS ([`super::cublas`]), the grid model's
//! im2col / col2im as single kernels ([`super::cuda_conv`]), and sparse stencil, P2G and G2P
//! kernels ([`super::cuda_stencil`]; inference and training take them), and the Adam step
//! with its gradient clipping as one kernel ([`super::cuda_adam`]); the inference 3x3
//! convolutions can run as implicit GEMMs (`MINFLOW_CUDA_CONV=implicit`,
//! [`super::cuda_implicit_conv`]; slower than im2col and cuBLAS, so not the default).

use burn::tensor::ops::{FloatTensor, IntTensor};

use std::sync::OnceLock;

use super::NetOps;

/// Whether the environment variable `var` is `value`, read once into `cell`: the switches
/// that pick another form of a CUDA operation, to compare two forms in one binary
/// (`MINFLOW_CUDA_TRANSFERS`, `MINFLOW_CUDA_ADAM`, `MINFLOW_CUDA_CONV`; docs/cuda.md).
pub(super) fn env_is(cell: &'static OnceLock<bool>, var: &str, value: &str) -> bool {
    *cell.get_or_init(|| std::env::var(var).is_ok_and(|v| v == value))
}

/// Whether `MINFLOW_CUDA_ADAM=composed` asks for burn's composed Adam step instead of the
/// kernel of [`super::cuda_adam`], to compare the two in one binary (docs/speed.md).
fn composed_adam() -> bool {
    static COMPOSED: OnceLock<bool> = OnceLock::new();
    env_is(&COMPOSED, "MINFLOW_CUDA_ADAM", "composed")
}

/// The composed defaults, whose element-wise chains burn's fusion layer compiles into single
/// kernels; the large products go to cuBLAS, which also splits their long reductions.
impl NetOps for burn::backend::Cuda<f32, i32> {
    /// im2col and col2im are single kernels; SiLU stays composed (fused by burn) under its own
    /// autodiff node.
    const NATIVE_CONV_OPS: bool = true;
    /// The sparse kernels of [`super::cuda_stencil`] (P2G in fixed point, the same to the
    /// bit on every run), for inference and for training through the autodiff backend.
    const DENSE_STENCIL: bool = false;

    /// [`NetOps::DENSE_STENCIL`] unless `MINFLOW_CUDA_TRANSFERS=dense`, which takes the
    /// separable dense products instead, to compare the two in one binary (docs/scale.md,
    /// docs/cuda.md).
    fn dense_stencil() -> bool {
        static DENSE: OnceLock<bool> = OnceLock::new();
        env_is(&DENSE, "MINFLOW_CUDA_TRANSFERS", "dense")
    }

    fn sparse_stencil(
        pos: &FloatTensor<Self>,
        n: usize,
    ) -> Option<(IntTensor<Self>, FloatTensor<Self>)> {
        Some(super::cuda_stencil::stencil(pos.clone(), n))
    }

    fn stencil_gather(
        grid: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        super::cuda_stencil::gather(grid, index, weight)
    }

    fn stencil_splat(
        values: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
        nodes: usize,
    ) -> FloatTensor<Self> {
        super::cuda_stencil::splat(values, index, weight, nodes)
    }

    fn im2col(x: FloatTensor<Self>, k: usize) -> FloatTensor<Self> {
        super::cuda_conv::im2col(x, k)
    }

    fn col2im(cols: FloatTensor<Self>, shape: [usize; 4], k: usize) -> FloatTensor<Self> {
        super::cuda_conv::col2im(cols, shape, k)
    }

    fn adam_step(
        param: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        m: Option<FloatTensor<Self>>,
        v: Option<FloatTensor<Self>>,
        c: &super::AdamStep,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        if composed_adam() {
            return super::adam_step::composed_adam::<Self>(param, grad, m, v, c);
        }
        super::cuda_adam::adam_step(param, grad, m, v, c)
    }

    fn conv3x3_forward(
        parts: &[FloatTensor<Self>],
        weight: &FloatTensor<Self>,
        bias: Option<&FloatTensor<Self>>,
        silu: bool,
        prepared: &super::PreparedWeights,
    ) -> Option<FloatTensor<Self>> {
        let _ = prepared;
        if !super::cuda_implicit_conv::implicit() {
            return None;
        }
        let y = super::cuda_implicit_conv::conv3x3(parts, weight, bias);
        Some(if silu { Self::silu(y) } else { y })
    }

    fn matmul(a: FloatTensor<Self>, b: FloatTensor<Self>) -> FloatTensor<Self> {
        super::cublas::matmul(a, b)
    }

    fn splits_reduction(device: &Self::Device, m: usize, k: usize, n: usize) -> bool {
        super::cublas::worth_it(Self::kernels(device).gemm, m, k, n)
    }

    fn kernels(device: &Self::Device) -> super::Kernels {
        super::cublas::kernels(device.index)
    }
}
