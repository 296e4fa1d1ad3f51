//! ELU and SiLU on the CPU, one pass each (in place where the buffer is not shared), with
//! their gradients, through a branch-free, auto-vectorisable `expm1`.
//!
//! Why: burn composes ELU (`x` for `x > 0`, `exp(x) - 1` otherwise; Clevert et al. 2016) from
//! five passes (compare, exp, sub, mul, select) with boolean masks, which cost most of the
//! paper configuration's training time on the CPU; its gradient needs only the output
//! (`d ELU / dx = 1` where the output is positive, `output + 1` elsewhere). burn-ndarray's
//! sigmoid (an `exp` and a `log` per element) was 13 % of a grid step (`perf` over `minflow
//! eval` with the shipped grid model: 222 ms per step), hence SiLU (`x sigmoid(x)`).

use burn::backend::ndarray::NdArrayTensor;
use rayon::prelude::*;

use super::{dense, map_owned, map_owned_zip, tensor, CpuTensor, PrimitiveInfo, ROWS_PER_TASK};

/// `exp(x) - 1` for any `x` in one branch-free, auto-vectorisable expression: Cody-Waite
/// range reduction `x = n ln2 + r`, `|r| <= ln2 / 2`, then a degree-7 Taylor polynomial for
/// `exp(r) - 1` (truncation error < 6e-9 relative) and `2^n (p + 1) - 1 = 2^n p + (2^n - 1)`,
/// which is exact for `n = 0` (no cancellation near 0). Absolute error about 1e-7 on
/// `[-87, 0]`; inputs below -87 give -1, above 88 give infinity (ELU only calls it for x <= 0).
#[inline(always)]
pub(crate) fn expm1(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_145_75;
    const LN2_LO: f32 = 1.428_606_8e-6;
    // Round to nearest by the 1.5 * 2^23 trick (vectorises without SSE4.1 rounding).
    const MAGIC: f32 = 12_582_912.0;
    let x = x.clamp(-87.0, 88.0);
    let shifted = x * LOG2E + MAGIC;
    let n = shifted - MAGIC;
    // The integer n sits in the low mantissa bits of `shifted`: integer lanes, no `as i32`
    // (whose NaN and saturation checks keep the loop from vectorising).
    let n_int = (shifted.to_bits() as i32).wrapping_sub(MAGIC.to_bits() as i32);
    let r = (x - n * LN2_HI) - n * LN2_LO;
    let p = r
        * (1.0
            + r * (0.5
                + r * (1.0 / 6.0
                    + r * (1.0 / 24.0
                        + r * (1.0 / 120.0 + r * (1.0 / 720.0 + r * (1.0 / 5040.0)))))));
    let scale = f32::from_bits(((n_int + 127) as u32) << 23);
    scale * p + (scale - 1.0)
}

/// ELU (alpha = 1) of one value.
#[inline(always)]
pub(crate) fn elu1(v: f32) -> f32 {
    let e = expm1(v.min(0.0));
    if v > 0.0 {
        v
    } else {
        e
    }
}

/// ELU over any f32 tensor, in place when the buffer is not shared.
pub(crate) fn elu(x: CpuTensor) -> CpuTensor {
    map_owned(x, |block| block.iter_mut().for_each(|v| *v = elu1(*v)))
}

/// ELU's input gradient from its output `out` and the output gradient `grad` (same shape):
/// `grad` where `out > 0`, `grad * (out + 1)` elsewhere; in place in `grad` when it is an
/// unshared row-major buffer, else into a new one (a broadcast `grad`, as the mean pooling's
/// backward gives, is read through its strides without being materialised first). Gives
/// `grad` back when `out` is not a row-major f32 tensor of the same shape.
pub(crate) fn elu_backward(out: &CpuTensor, grad: CpuTensor) -> Result<CpuTensor, CpuTensor> {
    let NdArrayTensor::F32(o) = out else {
        return Err(grad);
    };
    let o = o.view();
    let (Some(o), NdArrayTensor::F32(g)) = (o.as_slice(), &grad) else {
        return Err(grad);
    };
    let shape = grad.shape_vec();
    if shape.iter().product::<usize>() != o.len() || shape.is_empty() {
        return Err(grad);
    }
    let slope = |g: &mut f32, o: f32| *g *= if o > 0.0 { 1.0 } else { o + 1.0 };
    if g.view().is_standard_layout() {
        return Ok(map_owned_zip(grad, o, move |g, o| {
            g.iter_mut().zip(o).for_each(|(g, &o)| slope(g, o))
        }));
    }
    let cols = *shape.last().expect("non-empty shape");
    let gv = g.view();
    let lanes: Vec<ndarray::ArrayView1<f32>> = gv.rows().into_iter().collect();
    let mut dz = vec![0f32; o.len()];
    let block = ROWS_PER_TASK * cols.max(1);
    dz.par_chunks_mut(block)
        .zip(o.par_chunks(block))
        .zip(lanes.par_chunks(ROWS_PER_TASK))
        .for_each(|((dz, o), lanes)| {
            for ((dz, o), lane) in dz.chunks_mut(cols).zip(o.chunks(cols)).zip(lanes) {
                for ((d, &o), &g) in dz.iter_mut().zip(o).zip(lane.iter()) {
                    *d = g;
                    slope(d, o);
                }
            }
        });
    Ok(tensor(dz, &shape))
}

/// `x sigmoid(x)` through the vectorisable `expm1`: `sigmoid(x) = 1 / (2 + expm1(-x))`.
#[inline(always)]
pub(crate) fn sigmoid1(v: f32) -> f32 {
    1.0 / (2.0 + expm1(-v))
}

/// CPU SiLU, in place when the buffer is not shared.
pub(crate) fn silu(x: CpuTensor) -> CpuTensor {
    map_owned(x, |block| block.iter_mut().for_each(|v| *v *= sigmoid1(*v)))
}

/// CPU SiLU gradient, in place in `grad` when it is unshared; None when `x` is not a
/// row-major f32 tensor of `grad`'s size.
pub(crate) fn silu_backward(x: &CpuTensor, grad: CpuTensor) -> Result<CpuTensor, CpuTensor> {
    let Some((x, shape)) = dense(x) else {
        return Err(grad);
    };
    if shape != grad.shape_vec() {
        return Err(grad);
    }
    Ok(map_owned_zip(grad, &x, |g, x| {
        g.iter_mut().zip(x).for_each(|(g, &x)| {
            let s = sigmoid1(x);
            *g *= s + x * s * (1.0 - s);
        })
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn expm1_matches_libm() {
        let mut worst_abs = 0f32;
        let mut worst_rel = 0f32;
        let mut x = -90.0f32;
        while x <= 0.0 {
            let (got, want) = (expm1(x), x.exp_m1());
            worst_abs = worst_abs.max((got - want).abs());
            if want.abs() > 1e-3 {
                worst_rel = worst_rel.max(((got - want) / want).abs());
            }
            x += 0.000_37;
        }
        assert!(worst_abs < 2e-7, "abs error {worst_abs}");
        assert!(worst_rel < 4e-7, "rel error {worst_rel}");
        assert_eq!(expm1(0.0), 0.0);
        assert_eq!(expm1(-200.0), -1.0);
    }
}
