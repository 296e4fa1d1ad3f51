//! CPU kernels behind [`super::elu::FusedElu`] for burn's `NdArray<f32>` backend: the dense
//! layer `x @ W + b` (optionally followed by ELU) and its backward pass, on the `gemm` crate
//! (runtime dispatch to AVX-512 or AVX2 micro-kernels, split over the rayon pool), with the
//! bias and the ELU fused into one pass over the product, and a vectorisable `expm1`.
//!
//! Why: burn-ndarray multiplies through `matrixmultiply` (AVX2 only, ~1.2x on 2 threads) and
//! builds a dense layer from separate matmul, broadcast add and five-pass ELU; at the paper's
//! sizes the encoder's `[B T N, 256] x [256, 1250]` products are ~98 % of the work, so these
//! kernels set the CPU training speed (`minflow bench train`).
//!
//! All functions take 2-D operands with any strides (transposes are free) and return
//! row-major contiguous tensors. Results are deterministic for a given thread count: every
//! output element is reduced by one thread in a fixed order.

use burn::backend::ndarray::{NdArrayTensor, SharedArray};
use burn::backend::NdArray;
use burn::tensor::ops::FloatTensor;
use ndarray::{ArrayView2, CowArray, Ix2, IxDyn};
use rayon::prelude::*;

/// The CPU float tensor primitive.
pub(crate) type CpuTensor = FloatTensor<NdArray<f32>>;

/// Products with fewer multiply-adds than this run on the calling thread.
const PARALLEL_WORK: usize = 1 << 20;

/// Rows per task in the element-wise passes.
const ROWS_PER_TASK: usize = 64;

/// A 2-D view of an f32 CPU tensor (any strides); None for other dtypes or ranks.
pub(crate) fn view2(t: &CpuTensor) -> Option<ArrayView2<'_, f32>> {
    match t {
        NdArrayTensor::F32(s) => s.view().into_dimensionality().ok(),
        _ => None,
    }
}

/// An f32 CPU tensor `[..., cols]` as a `[rows, cols]` matrix: a view when its layout allows
/// (2-D with any non-zero strides, or row-major), else a row-major copy. None for other
/// dtypes and scalars.
fn rows_view(t: &CpuTensor) -> Option<CowArray<'_, f32, Ix2>> {
    let NdArrayTensor::F32(s) = t else {
        return None;
    };
    let v = s.view();
    let cols = *v.shape().last()?;
    let rows = v.shape()[..v.ndim() - 1].iter().product::<usize>();
    if v.ndim() == 2 && v.strides().iter().all(|&s| s != 0) {
        return v.into_dimensionality::<Ix2>().ok().map(CowArray::from);
    }
    if v.is_standard_layout() {
        return v
            .into_shape_with_order((rows, cols))
            .ok()
            .map(CowArray::from);
    }
    let owned = v.as_standard_layout().into_owned();
    owned
        .into_shape_with_order((rows, cols))
        .ok()
        .map(CowArray::from)
}

/// A 1-D contiguous slice of an f32 CPU tensor (the bias).
fn slice1(t: &CpuTensor) -> Option<ndarray::ArrayView1<'_, f32>> {
    match t {
        NdArrayTensor::F32(s) => s.view().into_dimensionality().ok(),
        _ => None,
    }
}

/// Wraps a row-major buffer as a CPU tensor of `shape` (no copy).
pub(crate) fn tensor(data: Vec<f32>, shape: &[usize]) -> CpuTensor {
    let array = SharedArray::<f32>::from_shape_vec(IxDyn(shape), data)
        .expect("buffer length matches the shape");
    NdArrayTensor::from(array)
}

/// `dst = a @ b` (or `dst += a @ b` with `accumulate`): `a` `[m, k]`, `b` `[k, n]` with any
/// strides, `dst` row-major `[m, n]`.
fn gemm_into(dst: &mut [f32], a: &ArrayView2<f32>, b: &ArrayView2<f32>, accumulate: bool) {
    let (m, k) = a.dim();
    let (k2, n) = b.dim();
    assert_eq!(k, k2, "inner dimensions differ");
    assert_eq!(dst.len(), m * n, "output size");
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        if !accumulate {
            dst.fill(0.0);
        }
        return;
    }
    let parallelism = if m * n * k >= PARALLEL_WORK {
        gemm::Parallelism::Rayon(rayon::current_num_threads())
    } else {
        gemm::Parallelism::None
    };
    let (sa, sb) = (a.strides(), b.strides());
    // SAFETY: the views are valid for their shapes and strides for the call's duration; dst
    // is a distinct, exclusively borrowed row-major m x n buffer.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            n as isize,
            accumulate,
            a.as_ptr(),
            sa[1],
            sa[0],
            b.as_ptr(),
            sb[1],
            sb[0],
            1.0,
            1.0,
            false,
            false,
            false,
            parallelism,
        );
    }
}

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
fn elu1(v: f32) -> f32 {
    let e = expm1(v.min(0.0));
    if v > 0.0 {
        v
    } else {
        e
    }
}

/// Runs `f` over row blocks of a row-major `[rows, cols]` buffer, in parallel for large ones.
fn for_rows(buf: &mut [f32], cols: usize, f: impl Fn(&mut [f32]) + Sync + Send) {
    let chunk = (ROWS_PER_TASK * cols.max(1)).max(1);
    if buf.len() * 4 >= PARALLEL_WORK {
        buf.par_chunks_mut(chunk).for_each(f);
    } else {
        buf.chunks_mut(chunk).for_each(f);
    }
}

/// `x @ weight + bias`, then ELU when `elu`: `x` `[..., in]`, `weight` `[in, out]`, `bias`
/// `[out]`; returns `[..., out]`. None when an operand is not an f32 tensor of those ranks.
pub(crate) fn linear(
    x: &CpuTensor,
    weight: &CpuTensor,
    bias: Option<&CpuTensor>,
    elu: bool,
) -> Option<CpuTensor> {
    let (xv, wv) = (rows_view(x)?, view2(weight)?);
    let bias = match bias {
        Some(b) => Some(slice1(b)?),
        None => None,
    };
    let (rows, d_out) = (xv.nrows(), wv.ncols());
    if xv.ncols() != wv.nrows() || bias.as_ref().is_some_and(|b| b.len() != d_out) {
        return None;
    }
    let bias: Option<Vec<f32>> = bias.map(|b| b.to_vec());
    let mut out = vec![0f32; rows * d_out];
    gemm_into(&mut out, &xv.view(), &wv, false);
    if bias.is_some() || elu {
        for_rows(&mut out, d_out, |block| {
            for row in block.chunks_exact_mut(d_out) {
                match &bias {
                    Some(b) if elu => row.iter_mut().zip(b).for_each(|(v, b)| *v = elu1(*v + b)),
                    Some(b) => row.iter_mut().zip(b).for_each(|(v, b)| *v += b),
                    None => row.iter_mut().for_each(|v| *v = elu1(*v)),
                }
            }
        });
    }
    let mut shape = x.shape_vec();
    *shape.last_mut()? = d_out;
    Some(tensor(out, &shape))
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

/// Gradients of `y = x @ weight (+ bias)` from `grad` = dL/dy `[..., out]`: `dx = grad @
/// weight^T` `[..., in]`, `dweight = x^T @ grad` `[in, out]`, `dbias` = column sums `[out]`;
/// each computed only when `need[i]`. None when an operand is not an f32 tensor of those
/// ranks.
pub(crate) fn linear_backward(
    x: &CpuTensor,
    weight: &CpuTensor,
    grad: &CpuTensor,
    need: [bool; 3],
) -> Option<[Option<CpuTensor>; 3]> {
    let (xv, wv, gv) = (rows_view(x)?, view2(weight)?, rows_view(grad)?);
    let (rows, d_in, d_out) = (xv.nrows(), xv.ncols(), wv.ncols());
    if gv.dim() != (rows, d_out) || wv.nrows() != d_in {
        return None;
    }
    let dx = need[0].then(|| {
        let mut dx = vec![0f32; rows * d_in];
        gemm_into(&mut dx, &gv.view(), &wv.t(), false);
        tensor(dx, &x.shape_vec())
    });
    let dw = need[1].then(|| {
        let mut dw = vec![0f32; d_in * d_out];
        gemm_into(&mut dw, &xv.t(), &gv.view(), false);
        tensor(dw, &[d_in, d_out])
    });
    let db = need[2].then(|| tensor(column_sums(&gv.view()), &[d_out]));
    Some([dx, dw, db])
}

/// Column sums of `[rows, cols]`, columns split across threads (fixed summation order).
fn column_sums(g: &ArrayView2<f32>) -> Vec<f32> {
    const COLS: usize = 128;
    let (rows, cols) = g.dim();
    let mut sums = vec![0f32; cols];
    let work = |(c, out): (usize, &mut [f32])| {
        let lo = c * COLS;
        for r in 0..rows {
            let row = g.row(r);
            for (j, s) in out.iter_mut().enumerate() {
                *s += row[lo + j];
            }
        }
    };
    if rows * cols >= PARALLEL_WORK / 4 {
        sums.par_chunks_mut(COLS).enumerate().for_each(work);
    } else {
        sums.chunks_mut(COLS).enumerate().for_each(work);
    }
    sums
}

/// The tensor's buffer as a uniquely owned row-major Vec (a copy only when shared or strided).
fn into_vec(x: CpuTensor) -> (Vec<f32>, Vec<usize>) {
    let shape = x.shape_vec();
    let array = match x {
        NdArrayTensor::F32(s) => s.into_owned(),
        other => panic!("expected an f32 tensor, got {:?}", other.dtype_name()),
    };
    let data = if array.is_standard_layout() {
        match array.try_into_owned_nocopy() {
            Ok(owned) => owned.into_raw_vec_and_offset().0,
            Err(shared) => shared.iter().copied().collect(),
        }
    } else {
        array.iter().copied().collect()
    };
    (data, shape)
}

/// Applies `f` to row blocks of the tensor's own buffer (in place when unshared).
pub(crate) fn map_owned(x: CpuTensor, f: impl Fn(&mut [f32]) + Sync + Send) -> CpuTensor {
    let (mut data, shape) = into_vec(x);
    let cols = shape.last().copied().unwrap_or(1);
    for_rows(&mut data, cols, f);
    tensor(data, &shape)
}

/// Applies `f` to aligned blocks of the tensor's own buffer and `other` (same length).
pub(crate) fn map_owned_zip(
    x: CpuTensor,
    other: &[f32],
    f: impl Fn(&mut [f32], &[f32]) + Sync + Send,
) -> CpuTensor {
    let (mut data, shape) = into_vec(x);
    const BLOCK: usize = 1 << 14;
    if data.len() * 4 >= PARALLEL_WORK {
        data.par_chunks_mut(BLOCK)
            .zip(other.par_chunks(BLOCK))
            .for_each(|(a, b)| f(a, b));
    } else {
        data.chunks_mut(BLOCK)
            .zip(other.chunks(BLOCK))
            .for_each(|(a, b)| f(a, b));
    }
    tensor(data, &shape)
}

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

/// The f32 tensor's elements in row-major order (borrowed when already so) and its shape.
pub(crate) fn dense(t: &CpuTensor) -> Option<(std::borrow::Cow<'_, [f32]>, Vec<usize>)> {
    let NdArrayTensor::F32(s) = t else {
        return None;
    };
    let v = s.view();
    let shape = v.shape().to_vec();
    let data = match v.to_slice() {
        Some(slice) => std::borrow::Cow::Borrowed(slice),
        None => std::borrow::Cow::Owned(v.iter().copied().collect()),
    };
    Some((data, shape))
}

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

/// One Adam step over a parameter (Kingma & Ba 2015, Algorithm 1, in the `eps * sqrt(bias
/// correction 2)` form PyTorch and burn use), one pass over `param`, `grad`, `m` and `v`:
/// `m = b1 m + (1 - b1) g`, `v = b2 v + (1 - b2) g^2`,
/// `param -= lr * (m * bc) / (sqrt(v) + eps * sqrt(1 - b2^t))` with
/// `bc = sqrt(1 - b2^t) / (1 - b1^t)`. `m` and `v` None start from zero (the first step).
/// In place where the buffers are unshared. Returns (param, m, v), shaped like `param`.
// The error hands the caller's tensors back (moved, not cloned, so the fallback keeps them
// unshared); it is a few hundred bytes on the stack on a path that does not happen for f32.
#[allow(clippy::result_large_err)]
pub(crate) fn adam(
    param: CpuTensor,
    grad: &CpuTensor,
    m: Option<CpuTensor>,
    v: Option<CpuTensor>,
    c: &crate::model::elu::AdamStep,
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
    let (bc2, factor) = c.corrections();
    let eps = c.epsilon * bc2;
    const BLOCK: usize = 1 << 14;
    // (parameter block, gradient block), (first-moment block, second-moment block).
    type Blocks<'a> = ((&'a mut [f32], &'a [f32]), (&'a mut [f32], &'a mut [f32]));
    let step = |((p, g), (m, v)): Blocks| {
        for (((p, &g), m), v) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
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

/// (param, m, v) after the step, or the inputs back when they are not f32 tensors of one size.
pub(crate) type AdamResult =
    Result<(CpuTensor, CpuTensor, CpuTensor), (CpuTensor, Option<CpuTensor>, Option<CpuTensor>)>;

/// Shape and dtype helpers on the primitive.
pub(crate) trait PrimitiveInfo {
    fn shape_vec(&self) -> Vec<usize>;
    fn dtype_name(&self) -> String;
}

impl PrimitiveInfo for CpuTensor {
    fn shape_vec(&self) -> Vec<usize> {
        use burn::tensor::TensorMetadata;
        self.shape().iter().copied().collect()
    }
    fn dtype_name(&self) -> String {
        use burn::tensor::TensorMetadata;
        format!("{:?}", self.dtype())
    }
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

    fn reference(a: &[f32], b: &[f32], m: usize, k: usize, n: usize) -> Vec<f32> {
        let mut c = vec![0f64; m * n];
        for i in 0..m {
            for p in 0..k {
                for j in 0..n {
                    c[i * n + j] += a[i * k + p] as f64 * b[p * n + j] as f64;
                }
            }
        }
        c.into_iter().map(|v| v as f32).collect()
    }

    #[test]
    fn linear_and_backward_match_a_reference() {
        let (m, k, n) = (300, 37, 91);
        let x: Vec<f32> = (0..m * k)
            .map(|i| ((i * 7919) % 113) as f32 / 56.0 - 1.0)
            .collect();
        let w: Vec<f32> = (0..k * n)
            .map(|i| ((i * 104_729) % 97) as f32 / 48.0 - 1.0)
            .collect();
        let b: Vec<f32> = (0..n).map(|i| i as f32 / n as f32 - 0.5).collect();
        let (xt, wt, bt) = (
            tensor(x.clone(), &[m, k]),
            tensor(w.clone(), &[k, n]),
            tensor(b.clone(), &[n]),
        );
        let y = linear(&xt, &wt, Some(&bt), true).unwrap();
        let want: Vec<f32> = reference(&x, &w, m, k, n)
            .iter()
            .enumerate()
            .map(|(i, v)| {
                let z = v + b[i % n];
                if z > 0.0 {
                    z
                } else {
                    z.exp_m1()
                }
            })
            .collect();
        let got = view2(&y).unwrap().iter().copied().collect::<Vec<_>>();
        for (g, w) in got.iter().zip(&want) {
            assert!((g - w).abs() < 1e-4 * (1.0 + w.abs()), "{g} vs {w}");
        }
        // Backward against the reference products.
        let g: Vec<f32> = (0..m * n)
            .map(|i| ((i * 31) % 17) as f32 / 8.0 - 1.0)
            .collect();
        let gt = tensor(g.clone(), &[m, n]);
        let [dx, dw, db] = linear_backward(&xt, &wt, &gt, [true; 3]).unwrap();
        let wt_rows: Vec<f32> = (0..n * k).map(|i| w[(i % k) * n + i / k]).collect(); // w^T [n, k]
        let xt_rows: Vec<f32> = (0..k * m).map(|i| x[(i % m) * k + i / m]).collect(); // x^T [k, m]
        let check = |t: CpuTensor, want: Vec<f32>| {
            let got: Vec<f32> = match &t {
                NdArrayTensor::F32(s) => s.view().iter().copied().collect(),
                _ => unreachable!(),
            };
            assert_eq!(got.len(), want.len());
            for (g, w) in got.iter().zip(&want) {
                assert!((g - w).abs() < 1e-3 * (1.0 + w.abs()), "{g} vs {w}");
            }
        };
        check(dx.unwrap(), reference(&g, &wt_rows, m, n, k));
        check(dw.unwrap(), reference(&xt_rows, &g, k, m, n));
        let sums: Vec<f32> = (0..n).map(|j| (0..m).map(|i| g[i * n + j]).sum()).collect();
        check(db.unwrap(), sums);
    }
}
