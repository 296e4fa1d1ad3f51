//! The paper encoder's first layer and mean pooling on the CPU in one pass (the CPU's
//! `NetOps::elu_mean_forward`), and its backward, which recomputes the activations instead of
//! keeping them.

use rayon::prelude::*;

use super::activation::{elu1, expm1};
use super::{dense, tensor, CpuTensor};

/// The encoder's first layer and mean pooling in one pass: `pooled[m] = mean_n elu(x[m, n] @
/// w + b)`, never materialising the `[M, N, H]` activations (at T = 32 and batch 16 those
/// are 1.3 GB, and burn's mean backward fills a tensor of ones that size).
///
/// # Shapes
/// - `x`: `[M, N, F]`, `w`: `[F, H]`, `b`: `[H]` -> `[M, H]`
pub(crate) fn elu_mean(x: &CpuTensor, w: &CpuTensor, b: &CpuTensor) -> Option<CpuTensor> {
    let ((x, xs), (w, ws), (b, bs)) = (dense(x)?, dense(w)?, dense(b)?);
    let (&[m, n, f], &[wf, h], &[bh]) = (xs.as_slice(), ws.as_slice(), bs.as_slice()) else {
        return None;
    };
    if wf != f || bh != h || n == 0 {
        return None;
    }
    let mut out = vec![0f32; m * h];
    let scale = 1.0 / n as f32;
    out.par_chunks_mut(h).enumerate().for_each(|(i, acc)| {
        let mut z = vec![0f32; h];
        for p in 0..n {
            let xp = &x[(i * n + p) * f..(i * n + p + 1) * f];
            pre_activation(xp, &w, &b, &mut z);
            for (a, &z) in acc.iter_mut().zip(&z) {
                *a += elu1(z);
            }
        }
        acc.iter_mut().for_each(|a| *a *= scale);
    });
    Some(tensor(out, &[m, h]))
}

/// One particle's pre-activation `z = x w + b`: `xp` `[F]`, `w` `[F, H]`, `b` `[H]`, into `z`
/// `[H]` (the encoder's first layer, for [`elu_mean`] and its backward).
#[inline]
fn pre_activation(xp: &[f32], w: &[f32], b: &[f32], z: &mut [f32]) {
    let h = z.len();
    z.copy_from_slice(b);
    for (k, &xk) in xp.iter().enumerate() {
        for (z, &wv) in z.iter_mut().zip(&w[k * h..(k + 1) * h]) {
            *z += xk * wv;
        }
    }
}

/// One particle's `dz = grad / N * elu'(x w + b)` for [`elu_mean_backward`], recomputing
/// the pre-activation; `grad` `[H]`, `scale` = 1 / N, into `dz` `[H]`.
#[inline]
fn elu_mean_dz(xp: &[f32], w: &[f32], b: &[f32], grad: &[f32], scale: f32, dz: &mut [f32]) {
    pre_activation(xp, w, b, dz);
    for (d, &gv) in dz.iter_mut().zip(grad) {
        let z = *d;
        let slope = if z > 0.0 {
            1.0
        } else {
            expm1(z.min(0.0)) + 1.0
        };
        *d = gv * scale * slope;
    }
}

/// Backward of [`elu_mean`] from `grad` = dL/dpooled `[M, H]`, recomputing the pre-activations:
/// `dz = grad[m] / N * elu'(z)`, `dw = sum x^T dz`, `db = sum dz`, `dx = dz w^T`.
/// Returns `[dx, dw, db]`, each only when `need[i]`. The sums run over fixed chunks of
/// frames added in order, so the result does not depend on the thread count.
pub(crate) fn elu_mean_backward(
    x: &CpuTensor,
    w: &CpuTensor,
    b: &CpuTensor,
    grad: &CpuTensor,
    need: [bool; 3],
) -> Option<[Option<CpuTensor>; 3]> {
    let ((x, xs), (w, ws), (b, _), (g, gs)) = (dense(x)?, dense(w)?, dense(b)?, dense(grad)?);
    let (&[m, n, f], &[_, h]) = (xs.as_slice(), ws.as_slice()) else {
        return None;
    };
    if gs != [m, h] || b.len() != h {
        return None;
    }
    let scale = 1.0 / n as f32;
    const FRAMES: usize = 4;
    let mut dx = vec![0f32; if need[0] { m * n * f } else { 0 }];
    // Per chunk of frames: (dw [F, H], db [H]) partial sums.
    let partials: Vec<(Vec<f32>, Vec<f32>)> = (0..m.div_ceil(FRAMES))
        .into_par_iter()
        .map(|c| {
            let mut dw = vec![0f32; f * h];
            let mut db = vec![0f32; h];
            let mut dz = vec![0f32; h];
            for i in c * FRAMES..((c + 1) * FRAMES).min(m) {
                let gi = &g[i * h..(i + 1) * h];
                for p in 0..n {
                    let xp = &x[(i * n + p) * f..(i * n + p + 1) * f];
                    elu_mean_dz(xp, &w, &b, gi, scale, &mut dz);
                    for (d, &v) in db.iter_mut().zip(&dz) {
                        *d += v;
                    }
                    for (k, &xk) in xp.iter().enumerate() {
                        for (d, &v) in dw[k * h..(k + 1) * h].iter_mut().zip(&dz) {
                            *d += xk * v;
                        }
                    }
                }
            }
            (dw, db)
        })
        .collect();
    if need[0] {
        // dx[m, n, k] = sum_j dz_j w[k, j]: recomputes dz per particle (only when x is tracked).
        dx.par_chunks_mut(n * f).enumerate().for_each(|(i, dxi)| {
            let gi = &g[i * h..(i + 1) * h];
            let mut dz = vec![0f32; h];
            for p in 0..n {
                let xp = &x[(i * n + p) * f..(i * n + p + 1) * f];
                elu_mean_dz(xp, &w, &b, gi, scale, &mut dz);
                for k in 0..f {
                    dxi[p * f + k] = dz
                        .iter()
                        .zip(&w[k * h..(k + 1) * h])
                        .map(|(a, b)| a * b)
                        .sum();
                }
            }
        });
    }
    let mut dw = vec![0f32; f * h];
    let mut db = vec![0f32; h];
    for (pw, pb) in &partials {
        dw.iter_mut().zip(pw).for_each(|(a, b)| *a += b);
        db.iter_mut().zip(pb).for_each(|(a, b)| *a += b);
    }
    Some([
        need[0].then(|| tensor(dx, &[m, n, f])),
        need[1].then(|| tensor(dw, &[f, h])),
        need[2].then(|| tensor(db, &[h])),
    ])
}
