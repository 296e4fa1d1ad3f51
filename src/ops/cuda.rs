//! [`NetOps`] for burn's CUDA backend (feature `cuda`, `--device cuda`): the composed
//! defaults, with the large products through cuBLAS ([`super::cublas`]) and the grid model's
//! im2col / col2im as single kernels ([`super::cuda_conv`]).

use burn::tensor::ops::FloatTensor;

use super::NetOps;

/// The composed defaults, whose element-wise chains burn's fusion layer compiles into single
/// kernels; the large products go to cuBLAS, which also splits their long reductions.
impl NetOps for burn::backend::Cuda<f32, i32> {
    /// im2col and col2im are single kernels; SiLU stays composed (fused by burn) under its own
    /// autodiff node. The stencil transfers never reach the sparse ops here: the GPU applies
    /// stencils in their separable dense form (`model::grid::transfer`).
    const NATIVE_CONV_OPS: bool = true;

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
