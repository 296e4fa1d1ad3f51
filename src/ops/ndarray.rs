//! [`NetOps`] for burn's `NdArray<f32>` (the CPU): every operation through the single-pass
//! kernels of `cpu/`, falling back to the composed default where an operand is not what the
//! kernel takes (another dtype, rank or layout). Turns on the sequential scan, the pooled ELU
//! that recomputes its activations, and the native grid operations (each with its node in
//! `autodiff.rs` / `autodiff_grid.rs`).

use burn::backend::NdArray;
use burn::tensor::ops::{FloatTensor, IntTensor};

use super::adam_step::{composed_adam, AdamStep};
use super::composed::{
    composed_elu_backward, composed_elu_mean, composed_linear, composed_linear_backward,
};
use super::composed_grid::{
    composed_col2im, composed_gather, composed_grid_channels, composed_im2col, composed_pool2,
    composed_silu_backward, composed_splat, composed_upsample2,
};
use super::scan::{composed_recurrence_backward, log_scan_recurrence};
use super::{cpu, NetOps};

impl NetOps for NdArray<f32> {
    fn run_step<R: Send>(f: impl FnOnce() -> R + Send) -> R {
        cpu::pool::hot(f)
    }

    fn linear_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        cpu::gemm::linear_stream(&x, &weight, bias.as_ref())
            .or_else(|| cpu::gemm::linear(&x, &weight, bias.as_ref(), false))
            .unwrap_or_else(|| composed_linear::<Self>(x, weight, bias))
    }

    fn linear_elu_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        if let Some(y) = cpu::gemm::linear_stream(&x, &weight, bias.as_ref()) {
            return cpu::activation::elu(y);
        }
        cpu::gemm::linear(&x, &weight, bias.as_ref(), true)
            .unwrap_or_else(|| Self::elu_forward(composed_linear::<Self>(x, weight, bias)))
    }

    fn linear_backward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        need: [bool; 3],
    ) -> [Option<FloatTensor<Self>>; 3] {
        cpu::gemm::linear_backward(&x, &weight, &grad, need)
            .unwrap_or_else(|| composed_linear_backward::<Self>(x, weight, grad, need))
    }

    fn adam_step(
        param: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        m: Option<FloatTensor<Self>>,
        v: Option<FloatTensor<Self>>,
        c: &AdamStep,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        match cpu::adam_pass::adam(param, &grad, m, v, c) {
            Ok(out) => out,
            Err((param, m, v)) => composed_adam::<Self>(param, grad, m, v, c),
        }
    }

    const ON_HOST: bool = true;
    const FUSED_ELU_MEAN: bool = true;
    const NATIVE_CONV_OPS: bool = true;

    fn im2col(x: FloatTensor<Self>, k: usize) -> FloatTensor<Self> {
        cpu::conv::im2col(&x, k).unwrap_or_else(|| composed_im2col::<Self>(x, k))
    }

    fn col2im(cols: FloatTensor<Self>, shape: [usize; 4], k: usize) -> FloatTensor<Self> {
        cpu::conv::col2im(&cols, shape, k)
            .unwrap_or_else(|| composed_col2im::<Self>(cols, shape, k))
    }

    fn conv3x3_forward(
        parts: &[FloatTensor<Self>],
        weight: &FloatTensor<Self>,
        bias: Option<&FloatTensor<Self>>,
        silu: bool,
        prepared: &super::PreparedWeights,
    ) -> Option<FloatTensor<Self>> {
        cpu::winograd::conv3x3(parts, weight, bias, silu, prepared)
    }

    fn silu(x: FloatTensor<Self>) -> FloatTensor<Self> {
        cpu::activation::silu(x)
    }

    fn grid_channels(splat: FloatTensor<Self>, n: usize, own: usize) -> FloatTensor<Self> {
        cpu::grid::grid_channels(&splat, n, own)
            .unwrap_or_else(|| composed_grid_channels::<Self>(splat, n, own))
    }

    fn host_values(x: &FloatTensor<Self>) -> Option<Vec<f32>> {
        cpu::dense(x).map(|(data, _)| data.into_owned())
    }

    fn host_indices(x: &IntTensor<Self>) -> Option<Vec<i64>> {
        let burn::backend::ndarray::NdArrayTensor::I64(s) = x else {
            return None;
        };
        let v = s.view();
        Some(match v.as_slice() {
            Some(flat) => flat.to_vec(),
            None => v.iter().copied().collect(),
        })
    }

    fn sparse_stencil(
        pos: &FloatTensor<Self>,
        n: usize,
    ) -> Option<(IntTensor<Self>, FloatTensor<Self>)> {
        cpu::transfer::sparse_stencil(pos, n)
    }

    fn pool2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        cpu::grid::pool2(&x).unwrap_or_else(|| composed_pool2::<Self>(x))
    }

    fn upsample2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        cpu::grid::upsample2(&x).unwrap_or_else(|| composed_upsample2::<Self>(x))
    }

    fn minlstm_update(
        hfi: &FloatTensor<Self>,
        h: Option<&FloatTensor<Self>>,
    ) -> Option<FloatTensor<Self>> {
        cpu::mingru::lstm_update(hfi, h)
    }

    fn mingru_update(hg: FloatTensor<Self>, h: Option<FloatTensor<Self>>) -> FloatTensor<Self> {
        match cpu::mingru::update(&hg, h.as_ref()) {
            Some(out) => out,
            None => super::mingru::composed_mingru_update::<Self>(hg, h),
        }
    }

    fn stencil_gather(
        grid: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        match cpu::transfer::gather(&grid, &index, &weight) {
            Some(out) => out,
            None => composed_gather::<Self>(grid, index, weight),
        }
    }

    fn stencil_splat(
        values: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
        nodes: usize,
    ) -> FloatTensor<Self> {
        match cpu::transfer::splat(&values, &index, &weight, nodes) {
            Some(out) => out,
            None => composed_splat::<Self>(values, index, weight, nodes),
        }
    }

    fn silu_backward(x: FloatTensor<Self>, grad: FloatTensor<Self>) -> FloatTensor<Self> {
        match cpu::activation::silu_backward(&x, grad) {
            Ok(g) => g,
            Err(grad) => composed_silu_backward::<Self>(x, grad),
        }
    }

    fn elu_mean_forward(
        x: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        cpu::elu_mean::elu_mean(&x, &w, &b).unwrap_or_else(|| composed_elu_mean::<Self>(x, w, b))
    }

    fn elu_mean_backward(
        x: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        need: [bool; 3],
    ) -> [Option<FloatTensor<Self>>; 3] {
        cpu::elu_mean::elu_mean_backward(&x, &w, &b, &grad, need)
            .expect("elu_mean_backward on f32 tensors of the forward's shapes")
    }

    fn recurrence(
        a: FloatTensor<Self>,
        b: FloatTensor<Self>,
        h0: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        cpu::scan::recurrence(&a, &b, h0.as_ref())
            .unwrap_or_else(|| log_scan_recurrence::<Self>(a, b, h0))
    }

    fn recurrence_backward(
        a: FloatTensor<Self>,
        h0: Option<FloatTensor<Self>>,
        h: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> [Option<FloatTensor<Self>>; 3] {
        cpu::scan::recurrence_backward(&a, h0.as_ref(), &h, &grad)
            .unwrap_or_else(|| composed_recurrence_backward::<Self>(a, h0, h, grad))
    }

    fn elu_forward(x: FloatTensor<Self>) -> FloatTensor<Self> {
        cpu::activation::elu(x)
    }

    fn elu_backward(out: FloatTensor<Self>, grad: FloatTensor<Self>) -> FloatTensor<Self> {
        match cpu::activation::elu_backward(&out, grad) {
            Ok(g) => g,
            Err(grad) => composed_elu_backward::<Self>(out, grad),
        }
    }
}
