//! Plain-f32 kernels for host passes outside the tensor operations (the grid model's CPU
//! inference pass, `model/grid/host_pass.rs`): the CPU backend's own product and SiLU, so such a
//! pass computes what the tensor path computes up to the summation order of its products.

use ndarray::ArrayView2;

/// `dst = a @ b`, or `dst += a @ b` with `accumulate`, on the calling thread: row-major
/// `a` `[m, k]`, `b` `[k, n]`, `dst` `[m, n]`.
///
/// # Panics
/// When a slice's length is not its shape's.
pub fn matmul(dst: &mut [f32], a: &[f32], b: &[f32], [m, k, n]: [usize; 3], accumulate: bool) {
    let a = ArrayView2::from_shape((m, k), a).expect("a is [m, k]");
    let b = ArrayView2::from_shape((k, n), b).expect("b is [k, n]");
    super::cpu::gemm::gemm_serial(dst, &a, &b, accumulate);
}

/// SiLU, `v sigmoid(v)`, as the CPU backend's [`super::NetOps::silu`] computes it.
#[inline(always)]
pub fn silu(v: f32) -> f32 {
    v * super::cpu::activation::sigmoid1(v)
}
