//! [`NetOps`] for burn's CUDA backend (feature `cuda`, `--device cuda`): the composed
//! defaults, with the large products through cuBLAS ([`super::cublas`]), the grid model's
//! im2col / col2im as single kernels ([`super::cuda_conv`]), and sparse stencil, P2G and G2P
//! kernels ([`super::cuda_stencil`], not yet taken by the model: `DENSE_STENCIL`).

use burn::tensor::ops::{FloatTensor, IntTensor};

use super::NetOps;

/// The composed defaults, whose element-wise chains burn's fusion layer compiles into single
/// kernels; the large products go to cuBLAS, which also splits their long reductions.
impl NetOps for burn::backend::Cuda<f32, i32> {
    /// im2col and col2im are single kernels; SiLU stays composed (fused by burn) under its own
    /// autodiff node.
    const NATIVE_CONV_OPS: bool = true;
    /// The model keeps the dense products (the default): its first GPU run on the sparse
    /// kernels of [`super::cuda_stencil`] was 1.7x faster but its rollouts diverged (avg20
    /// MSE NaN, docs/scale.md), so they stay off until `bench transfer`, which checks each
    /// part against the CPU backend, passes on a GPU.
    const DENSE_STENCIL: bool = true;

    /// `MINFLOW_CUDA_TRANSFERS=sparse` takes the sparse kernels of [`super::cuda_stencil`]
    /// for inference (training, on the autodiff backend, stays dense): the switch `bench
    /// transfer` and `bench rollout` compare the two forms with, in one binary.
    fn dense_stencil() -> bool {
        static DENSE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
        *DENSE
            .get_or_init(|| std::env::var("MINFLOW_CUDA_TRANSFERS").map_or(true, |v| v != "sparse"))
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
