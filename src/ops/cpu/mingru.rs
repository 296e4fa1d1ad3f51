//! The minGRU's inference update (`ops::mingru`) and the minLSTM's
//! ([`crate::ops::NetOps::minlstm_update`]) as one pass over the state each on the CPU.

use rayon::prelude::*;

use super::activation::expm1;
use super::{dense, tensor, CpuTensor};

/// Rows per task of the update.
const ROWS_PER_TASK: usize = 256;

/// `sigmoid(x) = 1 / (2 + expm1(-x))`, vectorisable.
#[inline(always)]
fn sigmoid1(x: f32) -> f32 {
    1.0 / (2.0 + expm1(-x))
}

/// `g(x)`: `x + 0.5` for `x >= 0`, `sigmoid(x)` otherwise (`ops::mingru::g`).
#[inline(always)]
fn g1(t: f32) -> f32 {
    if t >= 0.0 {
        t + 0.5
    } else {
        sigmoid1(t)
    }
}

/// The frame both updates share: `pre` `[M, k H]` (the layer's pre-activations) and `h`
/// `[M, H]` as row-major f32, then `row(pre_row, prev_row, out_row)` for every row (zeros for
/// `prev_row` without `h`), in parallel over blocks of rows. None when the inputs are not f32
/// of those shapes.
fn each_row(
    pre: &CpuTensor,
    h: Option<&CpuTensor>,
    k: usize,
    row: impl Fn(&[f32], &[f32], &mut [f32]) + Sync,
) -> Option<CpuTensor> {
    let (pre, shape) = dense(pre)?;
    let &[m, width] = shape.as_slice() else {
        return None;
    };
    let hidden = width / k;
    if width != k * hidden || hidden == 0 {
        return None;
    }
    let prev = match h {
        Some(h) => {
            let (h, hshape) = dense(h)?;
            if hshape != [m, hidden] {
                return None;
            }
            Some(h)
        }
        None => None,
    };
    let zeros = vec![0f32; hidden];
    let mut out = vec![0f32; m * hidden];
    let fill = |r0: usize, dst: &mut [f32]| {
        for (q, dst) in dst.chunks_exact_mut(hidden).enumerate() {
            let r = r0 + q;
            let p = prev
                .as_ref()
                .map_or(&zeros[..], |p| &p[r * hidden..][..hidden]);
            row(&pre[r * width..][..width], p, dst);
        }
    };
    if m > ROWS_PER_TASK {
        out.par_chunks_mut(ROWS_PER_TASK * hidden)
            .enumerate()
            .for_each(|(t, dst)| fill(t * ROWS_PER_TASK, dst));
    } else {
        fill(0, &mut out);
    }
    Some(tensor(out, &[m, hidden]))
}

/// `(1 - z) h + z g(h~)` in one pass: `hg` `[M, 2H]`, `h` `[M, H]` -> `[M, H]`; None when the
/// inputs are not f32 of those shapes (the caller then composes it).
pub(crate) fn update(hg: &CpuTensor, h: Option<&CpuTensor>) -> Option<CpuTensor> {
    each_row(hg, h, 2, |row, prev, dst| {
        let (tilde, gate) = row.split_at(dst.len());
        for (j, d) in dst.iter_mut().enumerate() {
            let (g, z, p) = (g1(tilde[j]), sigmoid1(gate[j]), prev[j]);
            *d = p + z * (g - p);
        }
    })
}

/// `exp(x)` for `x <= 0` through the vectorisable `expm1` (absolute error ~1e-7).
#[inline(always)]
fn exp_nonpositive(x: f32) -> f32 {
    expm1(x) + 1.0
}

/// The minLSTM's step (Feng et al. 2024, minLSTM with normalised gates) in one pass:
/// `f' h + i' g(h~)` with `(f', i') = (f, i) / (f + i)`, `f = sigmoid(a)`, `i = sigmoid(b)`,
/// from `hfi` `[M, 3H]` (`h~`, `a`, `b`) and `h` `[M, H]` (none: `i' g(h~)`) -> `[M, H]`.
/// None when the inputs are not f32 of those shapes (the caller then composes it).
///
/// `f' = v / (u + v)`, `i' = u / (u + v)` with `u = e^s + e^(s - a)`, `v = e^s + e^(s - b)`,
/// `s = min(a, b, 0)`: the quotient `(1 + e^-b) / (2 + e^-a + e^-b)` scaled so that no
/// exponent is positive and `u + v >= 1` (no overflow, no 0 / 0 where both gates underflow,
/// which the composed form avoids through softplus).
pub(crate) fn lstm_update(hfi: &CpuTensor, h: Option<&CpuTensor>) -> Option<CpuTensor> {
    each_row(hfi, h, 3, |row, prev, dst| {
        let (tilde, gates) = row.split_at(dst.len());
        let (a, b) = gates.split_at(dst.len());
        for (j, d) in dst.iter_mut().enumerate() {
            let s = a[j].min(b[j]).min(0.0);
            let e = exp_nonpositive(s);
            let u = e + exp_nonpositive(s - a[j]);
            let v = e + exp_nonpositive(s - b[j]);
            *d = (v * prev[j] + u * g1(tilde[j])) / (u + v);
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ops::mingru::composed_mingru_update;
    use burn::backend::NdArray;
    use burn::tensor::{Tensor, TensorData, TensorPrimitive};

    /// The one pass equals the composed formula, with and without a previous state, over
    /// negative and positive `h~` and gates.
    #[test]
    fn update_equals_the_composed_one() {
        type B = NdArray<f32>;
        let (m, hidden) = (300, 5);
        let values =
            |n: usize, k: f32| -> Vec<f32> { (0..n).map(|i| (i as f32 * k).sin() * 6.0).collect() };
        let hg = Tensor::<B, 2>::from_data(
            TensorData::new(values(m * 2 * hidden, 0.37), [m, 2 * hidden]),
            &Default::default(),
        );
        let h = Tensor::<B, 2>::from_data(
            TensorData::new(values(m * hidden, 0.11), [m, hidden]),
            &Default::default(),
        );
        let back = |x| Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(x));
        for prev in [None, Some(h)] {
            let p = prev.clone().map(|h| h.into_primitive().tensor());
            let cpu = update(&hg.clone().into_primitive().tensor(), p.as_ref()).expect("f32");
            let composed = composed_mingru_update::<B>(hg.clone().into_primitive().tensor(), p);
            let a: Vec<f32> = back(cpu).into_data().to_vec().unwrap();
            let b: Vec<f32> = back(composed).into_data().to_vec().unwrap();
            let worst = a
                .iter()
                .zip(&b)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0f32, f32::max);
            assert!(worst < 1e-5, "{worst}");
        }
    }

    /// The minLSTM's one pass equals `MinLstm`'s composed step (softplus-normalised gates),
    /// with and without a previous state, over gates from -120 (both underflow in f32) to
    /// +120.
    #[test]
    fn lstm_update_equals_the_composed_one() {
        use crate::model::minrnn::normalized_gates;
        use crate::ops::mingru::g;
        type B = NdArray<f32>;
        let device = Default::default();
        let (m, hidden) = (300, 7);
        let values = |n: usize, k: f32, scale: f32| -> Vec<f32> {
            (0..n).map(|i| (i as f32 * k).sin() * scale).collect()
        };
        let back = |x| Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(x));
        for scale in [6.0, 120.0] {
            let hfi = Tensor::<B, 2>::from_data(
                TensorData::new(values(m * 3 * hidden, 0.37, scale), [m, 3 * hidden]),
                &device,
            );
            let h = Tensor::<B, 2>::from_data(
                TensorData::new(values(m * hidden, 0.11, 3.0), [m, hidden]),
                &device,
            );
            for prev in [None, Some(h)] {
                let p = prev.clone().map(|h| h.into_primitive().tensor());
                let fused = back(
                    lstm_update(&hfi.clone().into_primitive().tensor(), p.as_ref()).expect("f32"),
                );
                let tilde = g(hfi.clone().narrow(1, 0, hidden));
                let (f, i) = normalized_gates(
                    hfi.clone().narrow(1, hidden, hidden),
                    hfi.clone().narrow(1, 2 * hidden, hidden),
                );
                let composed = match prev {
                    Some(h) => f * h + i * tilde,
                    None => i * tilde,
                };
                let a: Vec<f32> = fused.into_data().to_vec().unwrap();
                let b: Vec<f32> = composed.into_data().to_vec().unwrap();
                assert!(a.iter().all(|x| x.is_finite()), "scale {scale}");
                let worst = a
                    .iter()
                    .zip(&b)
                    .map(|(x, y)| (x - y).abs() / y.abs().max(1.0))
                    .fold(0.0f32, f32::max);
                assert!(worst < 1e-5, "scale {scale}: {worst}");
            }
        }
    }
}
