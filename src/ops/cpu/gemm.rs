//! The dense layer `x @ W + b` on the CPU, optionally followed by ELU, and its backward: on
//! the `gemm` crate (runtime dispatch to AVX-512 or AVX2 micro-kernels, split over the rayon
//! pool) with the bias and the ELU fused into one pass over the product, or for a handful of
//! rows (the inference step) by streaming each weight once.

use burn::backend::ndarray::NdArrayTensor;
use ndarray::ArrayView2;
use rayon::prelude::*;

use super::activation::elu1;
use super::{for_rows, rows_view, slice1, tensor, view2, CpuTensor, PrimitiveInfo, PARALLEL_WORK};

/// `dst = a @ b` (or `dst += a @ b` with `accumulate`): `a` `[m, k]`, `b` `[k, n]` with any
/// strides, `dst` row-major `[m, n]`.
fn gemm_into(dst: &mut [f32], a: &ArrayView2<f32>, b: &ArrayView2<f32>, accumulate: bool) {
    let (m, k) = a.dim();
    let parallelism = if m * b.ncols() * k >= PARALLEL_WORK {
        gemm::Parallelism::Rayon(rayon::current_num_threads())
    } else {
        gemm::Parallelism::None
    };
    gemm_with(dst, a, b, accumulate, parallelism);
}

/// `dst = a @ b`, or `dst += a @ b` with `accumulate`, on the calling thread, for callers
/// that run several products in parallel themselves; shapes as [`gemm_into`].
pub(crate) fn gemm_serial(
    dst: &mut [f32],
    a: &ArrayView2<f32>,
    b: &ArrayView2<f32>,
    accumulate: bool,
) {
    gemm_with(dst, a, b, accumulate, gemm::Parallelism::None);
}

fn gemm_with(
    dst: &mut [f32],
    a: &ArrayView2<f32>,
    b: &ArrayView2<f32>,
    accumulate: bool,
    parallelism: gemm::Parallelism,
) {
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

/// Rows up to which [`linear_stream`] multiplies by streaming the weights (a matrix-vector
/// product per row) instead of calling sgemm, which packs the whole weight matrix on every
/// call: the inference step has 1 row, and its weights (tens of MB) dominate its cost.
const STREAM_ROWS: usize = 8;

/// `x @ weight + bias` for a CPU tensor with at most [`STREAM_ROWS`] rows, reading each
/// weight once; None when the operands are not plain contiguous f32 (the caller falls back).
pub(crate) fn linear_stream(
    x: &CpuTensor,
    weight: &CpuTensor,
    bias: Option<&CpuTensor>,
) -> Option<CpuTensor> {
    let (NdArrayTensor::F32(xs), NdArrayTensor::F32(ws)) = (x, weight) else {
        return None;
    };
    let (xv, wv) = (xs.view(), ws.view());
    let &[w_in, d_out] = wv.shape() else {
        return None;
    };
    let x_shape = xv.shape().to_vec();
    let (&d_in, lead) = x_shape.split_last()?;
    let rows = lead.iter().product::<usize>();
    if rows > STREAM_ROWS || w_in != d_in {
        return None;
    }
    let (xs, ws) = (xv.as_slice()?, wv.as_slice()?);
    let bias_view = match bias {
        Some(NdArrayTensor::F32(b)) => Some(b.view()),
        Some(_) => return None,
        None => None,
    };
    let bias = match &bias_view {
        Some(b) => Some(b.as_slice()?),
        None => None,
    };
    let mut out = vec![0f32; rows * d_out];
    // Columns in chunks (one task each), rows of the weight streamed once per chunk.
    const CHUNK: usize = 512;
    let chunks = d_out.div_ceil(CHUNK);
    let mut per_chunk: Vec<Vec<f32>> = (0..chunks)
        .into_par_iter()
        .map(|c| {
            let (lo, hi) = (c * CHUNK, ((c + 1) * CHUNK).min(d_out));
            let w = hi - lo;
            let mut acc = vec![0f32; rows * w];
            if let Some(b) = bias {
                for r in 0..rows {
                    acc[r * w..(r + 1) * w].copy_from_slice(&b[lo..hi]);
                }
            }
            for i in 0..d_in {
                let wrow = &ws[i * d_out + lo..i * d_out + hi];
                for r in 0..rows {
                    let xi = xs[r * d_in + i];
                    if xi != 0.0 {
                        for (a, &wv) in acc[r * w..(r + 1) * w].iter_mut().zip(wrow) {
                            *a += xi * wv;
                        }
                    }
                }
            }
            acc
        })
        .collect();
    for (c, acc) in per_chunk.iter_mut().enumerate() {
        let (lo, hi) = (c * CHUNK, ((c + 1) * CHUNK).min(d_out));
        let w = hi - lo;
        for r in 0..rows {
            out[r * d_out + lo..r * d_out + hi].copy_from_slice(&acc[r * w..(r + 1) * w]);
        }
    }
    let mut shape = x_shape;
    *shape.last_mut()? = d_out;
    Some(tensor(out, &shape))
}

#[cfg(test)]
mod tests {
    use super::*;

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
