//! The linear recurrence `h_t = a_t h_{t-1} + b_t` of minGRU and minLSTM on the CPU, as one
//! sequential pass per batch item, and its reverse pass (the CPU's `NetOps::recurrence`,
//! with `ON_HOST`: minGRU and minLSTM then train through it in linear space; the
//! log-space parallel scan, `ops::scan`, is what pays on a GPU).

use rayon::prelude::*;

use super::{dense, tensor, CpuTensor};

/// The linear recurrence `h_t = a_t h_{t-1} + b_t` along T, sequentially (minGRU's and
/// minLSTM's hidden state, Feng et al. 2024 eq. for `h_t`), `h_{-1} = h0` or 0.
///
/// # Shapes
/// - `a`, `b`: `[B, T, H]`, `h0`: `[B, H]` -> `h`: `[B, T, H]`
pub(crate) fn recurrence(
    a: &CpuTensor,
    b: &CpuTensor,
    h0: Option<&CpuTensor>,
) -> Option<CpuTensor> {
    let ((a, shape), (b, b_shape)) = (dense(a)?, dense(b)?);
    let &[batch, t, h] = shape.as_slice() else {
        return None;
    };
    if b_shape != shape {
        return None;
    }
    let h0 = match h0 {
        Some(h0) => {
            let (d, s) = dense(h0)?;
            if s != [batch, h] {
                return None;
            }
            Some(d)
        }
        None => None,
    };
    let mut out = vec![0f32; batch * t * h];
    out.par_chunks_mut(t * h).enumerate().for_each(|(i, o)| {
        let (a, b) = (
            &a[i * t * h..(i + 1) * t * h],
            &b[i * t * h..(i + 1) * t * h],
        );
        let mut prev: Vec<f32> = match &h0 {
            Some(h0) => h0[i * h..(i + 1) * h].to_vec(),
            None => vec![0.0; h],
        };
        for s in 0..t {
            let row = s * h..(s + 1) * h;
            for (((o, p), &a), &b) in o[row.clone()]
                .iter_mut()
                .zip(prev.iter_mut())
                .zip(&a[row.clone()])
                .zip(&b[row])
            {
                *p = a * *p + b;
                *o = *p;
            }
        }
    });
    Some(tensor(out, &shape))
}

/// Backward of [`recurrence`] from its output `h` and `grad` = dL/dh (both `[B, T, H]`):
/// `d_t = grad_t + a_{t+1} d_{t+1}` (from the end), then `da_t = d_t h_{t-1}`, `db_t = d_t`,
/// `dh0 = a_0 d_0`. Returns `[da, db, dh0]` (dh0 None without `h0`).
pub(crate) fn recurrence_backward(
    a: &CpuTensor,
    h0: Option<&CpuTensor>,
    h: &CpuTensor,
    grad: &CpuTensor,
) -> Option<[Option<CpuTensor>; 3]> {
    let ((a, shape), (hs, h_shape), (g, g_shape)) = (dense(a)?, dense(h)?, dense(grad)?);
    let &[batch, t, w] = shape.as_slice() else {
        return None;
    };
    if h_shape != shape || g_shape != shape {
        return None;
    }
    let h0 = match h0 {
        Some(h0) => {
            let (d, s) = dense(h0)?;
            if s != [batch, w] {
                return None;
            }
            Some(d)
        }
        None => None,
    };
    let n = t * w;
    let mut da = vec![0f32; batch * n];
    let mut db = vec![0f32; batch * n];
    let mut dh0 = vec![0f32; batch * w];
    da.par_chunks_mut(n)
        .zip(db.par_chunks_mut(n))
        .zip(dh0.par_chunks_mut(w))
        .enumerate()
        .for_each(|(i, ((da, db), dh0))| {
            let (a, hs, g) = (
                &a[i * n..(i + 1) * n],
                &hs[i * n..(i + 1) * n],
                &g[i * n..(i + 1) * n],
            );
            let mut carry = vec![0f32; w]; // a_{t+1} d_{t+1}
            for s in (0..t).rev() {
                let row = s * w..(s + 1) * w;
                for (j, c) in carry.iter_mut().enumerate() {
                    let d = g[row.start + j] + *c;
                    db[row.start + j] = d;
                    let prev = if s > 0 {
                        hs[row.start - w + j]
                    } else {
                        h0.as_ref().map_or(0.0, |h0| h0[i * w + j])
                    };
                    da[row.start + j] = d * prev;
                    *c = a[row.start + j] * d;
                }
            }
            dh0.copy_from_slice(&carry);
        });
    let dh0 = h0.is_some().then(|| tensor(dh0, &[batch, w]));
    Some([Some(tensor(da, &shape)), Some(tensor(db, &shape)), dh0])
}
