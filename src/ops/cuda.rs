//! [`NetOps`] for burn's CUDA backend (feature `cuda`, `--device cuda`): the composed
//! defaults, with the large products through cuBLAS ([`super::cublas`]), the grid model's
//! im2col / col2im as single kernels ([`super::cuda_conv`]), and sparse stencil, P2G and G2P
//! kernels ([`super::cuda_stencil`]; inference and training take them).

use burn::tensor::ops::{FloatTensor, IntTensor};

use super::NetOps;

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
        static DENSE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
        *DENSE.get_or_init(|| std::env::var("MINFLOW_CUDA_TRANSFERS").is_ok_and(|v| v == "dense"))
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
