//! One Adam step on the CPU in one pass over the parameter, its gradient and both moments,
//! in place where the buffers are unshared (the CPU's `NetOps::adam_step`; the composed
//! default makes about 13 passes over memory).

use burn::backend::ndarray::NdArrayTensor;
use rayon::prelude::*;

use super::{into_vec, tensor, CpuTensor, PrimitiveInfo, PARALLEL_WORK};
use crate::ops::adam_step::AdamStep;

/// One Adam step over a parameter (Kingma & Ba 2015, Algorithm 1, in the `eps * sqrt(bias
/// correction 2)` form PyTorch and burn use), one pass over `param`, `grad`, `m` and `v`:
/// `m = b1 m + (1 - b1) g`, `v = b2 v + (1 - b2) g^2`,
/// `param -= lr * (m * bc) / (sqrt(v) + eps * sqrt(1 - b2^t))` with
/// `bc = sqrt(1 - b2^t) / (1 - b1^t)`, after `g` is clipped to norm `c.max_norm` (burn's
/// `GradientClipping::Norm`, one more pass for the norm). `m` and `v` None start from zero
/// (the first step).
/// In place where the buffers are unshared. Returns (param, m, v), shaped like `param`.
// The error hands the caller's tensors back (moved, not cloned, so the fallback keeps them
// unshared); it is a few hundred bytes on the stack on a path that does not happen for f32.
#[allow(clippy::result_large_err)]
pub(crate) fn adam(
    param: CpuTensor,
    grad: &CpuTensor,
    m: Option<CpuTensor>,
    v: Option<CpuTensor>,
    c: &AdamStep,
) -> AdamResult {
    let NdArrayTensor::F32(g) = grad else {
        return Err((param, m, v));
    };
    let g = g.view();
    let Some(g) = g.as_slice() else {
        return Err((param, m, v));
    };
    let f32_of_len = |t: &CpuTensor| {
        matches!(t, NdArrayTensor::F32(_)) && t.shape_vec().iter().product::<usize>() == g.len()
    };
    if !f32_of_len(&param) || !m.iter().chain(v.iter()).all(f32_of_len) {
        return Err((param, m, v));
    }
    let (mut p, shape) = into_vec(param);
    let moment = |t: Option<CpuTensor>| match t {
        Some(t) => into_vec(t).0,
        None => vec![0f32; g.len()],
    };
    let (mut m, mut v) = (moment(m), moment(v));
    let (b1, b2, lr) = (c.beta_1, c.beta_2, c.lr);
    let scale = clip_scale(g, c.max_norm);
    let (bc2, factor) = c.corrections();
    let eps = c.epsilon * bc2;
    const BLOCK: usize = 1 << 14;
    // (parameter block, gradient block), (first-moment block, second-moment block).
    type Blocks<'a> = ((&'a mut [f32], &'a [f32]), (&'a mut [f32], &'a mut [f32]));
    let step = |((p, g), (m, v)): Blocks| {
        for (((p, &g), m), v) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
            let g = g * scale;
            *m = b1 * *m + (1.0 - b1) * g;
            *v = b2 * *v + (1.0 - b2) * (g * g);
            *p -= lr * ((*m * factor) / (v.sqrt() + eps));
        }
    };
    if p.len() * 4 >= PARALLEL_WORK {
        p.par_chunks_mut(BLOCK)
            .zip(g.par_chunks(BLOCK))
            .zip(m.par_chunks_mut(BLOCK).zip(v.par_chunks_mut(BLOCK)))
            .for_each(step);
    } else {
        p.chunks_mut(BLOCK)
            .zip(g.chunks(BLOCK))
            .zip(m.chunks_mut(BLOCK).zip(v.chunks_mut(BLOCK)))
            .for_each(step);
    }
    Ok((tensor(p, &shape), tensor(m, &shape), tensor(v, &shape)))
}

/// The factor that clips `g` to L2 norm `max_norm` as burn's `GradientClipping::Norm` does,
/// `min(1, max_norm / (|g| + f32::MIN_POSITIVE))`, the squares summed in f64
/// (chunk by chunk, in order; burn sums in f32, ~1e-7 apart, and where burn's f32 sum
/// overflows to infinity and zeroes the gradient this one still clips it); 1 for None.
fn clip_scale(g: &[f32], max_norm: Option<f32>) -> f32 {
    let Some(max_norm) = max_norm else {
        return 1.0;
    };
    let sum = |g: &[f32]| g.iter().map(|&x| f64::from(x) * f64::from(x)).sum::<f64>();
    // Chunk sums collected, then added in order: the same bits however rayon splits.
    let squares: f64 = if g.len() * 4 >= PARALLEL_WORK {
        let parts: Vec<f64> = g.par_chunks(1 << 14).map(sum).collect();
        parts.iter().sum()
    } else {
        sum(g)
    };
    (max_norm / (squares.sqrt() as f32 + f32::MIN_POSITIVE)).min(1.0)
}

/// (param, m, v) after the step, or the inputs back when they are not f32 tensors of one size.
pub(crate) type AdamResult =
    Result<(CpuTensor, CpuTensor, CpuTensor), (CpuTensor, Option<CpuTensor>, Option<CpuTensor>)>;
