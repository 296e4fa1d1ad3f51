//! [`NetOps`] for burn's CUDA backend (feature `cuda`, `--device cuda`): the composed
//! defaults, with the large products through cuBLAS ([`super::cublas`]), the grid model's
//! im2col / col2im as single kernels ([`super::cuda_conv`]), and sparse stencil, P2G and G2P
//! kernels ([`super::cuda_stencil`]; inference takes them, training the dense products).

use burn::tensor::ops::{FloatTensor, IntTensor};

use super::NetOps;

/// The composed defaults, whose element-wise chains burn's fusion layer compiles into single
/// kernels; the large products go to cuBLAS, which also splits their long reductions.
impl NetOps for burn::backend::Cuda<f32, i32> {
    /// im2col and col2im are single kernels; SiLU stays composed (fused by burn) under its own
    /// autodiff node.
    const NATIVE_CONV_OPS: bool = true;
    /// The autodiff backend's training keeps the dense products (its own const); inference
    /// takes the sparse kernels of [`super::cuda_stencil`] ([`NetOps::dense_stencil`]).
    const DENSE_STENCIL: bool = true;

    /// The sparse kernels of [`super::cuda_stencil`] for inference: on one H100 they match the
    /// CPU backend to 1.2e-7 (`bench transfer`; the dense products, TF32, to 3.2e-4), cost
    /// 0.29 / 0.25 ms for P2G / G2P of 256 scenes against 10.4 / 17.9 ms, and took
    /// `all-grid-mingru`'s 16-scene frame from 0.81x to 0.67x the solver's with avg100 equal
    /// to 4e-4 of itself (docs/scale.md). `MINFLOW_CUDA_TRANSFERS=dense` takes the dense
    /// products instead, to compare the two in one binary.
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
