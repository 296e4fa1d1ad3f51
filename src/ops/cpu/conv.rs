//! im2col and col2im of the grid model's same-padding convolutions on the CPU (the CPU's
//! `NetOps::im2col` / `NetOps::col2im`; column order in `NetOps::im2col`'s doc): each output
//! row written in order, one task per image row.
//!
//! Why: burn-ndarray's row gather (`select`, element by element through `IxDyn` indices) was
//! half of a grid step (`perf` over `minflow eval` with the shipped grid model: 222 ms per
//! step).

use std::mem::MaybeUninit;

use rayon::prelude::*;

use super::{dense, tensor, CpuTensor};

/// CPU im2col: one task per image row; each output row is written once, in order (channel,
/// then offset), reading the `k^2` source pixels it needs (zeros outside the grid), into
/// uninitialised memory (no zero fill first). Interior positions of a 3 x 3 kernel take an
/// unrolled path: nine source slices of `C` floats, read in step. None for tensors that are
/// not f32 of rank 4, or kernels larger than 3 x 3.
pub(crate) fn im2col(x: &CpuTensor, k: usize) -> Option<CpuTensor> {
    let (data, shape) = dense(x)?;
    let [b, h, w, c] = <[usize; 4]>::try_from(shape).ok()?;
    let kk = k * k;
    if kk > MAX_KK {
        return None;
    }
    let row = c * kk;
    let n = b * h * w * row;
    let mut out: Vec<f32> = Vec::with_capacity(n);
    let spare = &mut out.spare_capacity_mut()[..n];
    let fill =
        |by: usize, dst: &mut [MaybeUninit<f32>]| im2col_image_row(&data, [h, w, c], k, by, dst);
    if n * 4 >= 1 << 20 {
        spare
            .par_chunks_mut(w * row)
            .enumerate()
            .for_each(|(by, dst)| fill(by, dst));
    } else {
        spare
            .chunks_mut(w * row)
            .enumerate()
            .for_each(|(by, dst)| fill(by, dst));
    }
    // SAFETY: `im2col_image_row` wrote every element of every chunk, and the chunks cover
    // the first `n` elements.
    unsafe { out.set_len(n) };
    Some(tensor(out, &[b * h * w, row]))
}

/// Largest `k^2` of [`im2col`].
const MAX_KK: usize = 9;

/// The im2col rows of image row `by` (`b H + y`) of `data` (`[B, H, W, C]`) into `dst`
/// (`W` rows of `C k^2`), every element written.
fn im2col_image_row(
    data: &[f32],
    [h, w, c]: [usize; 3],
    k: usize,
    by: usize,
    dst: &mut [MaybeUninit<f32>],
) {
    let (kk, half) = (k * k, (k / 2) as isize);
    let (bb, y) = (by / h, (by % h) as isize);
    for (x, dst) in dst.chunks_exact_mut(c * kk).enumerate() {
        // Source offset of each kernel offset, or None outside the grid.
        let mut src = [None; MAX_KK];
        for (s, src) in src.iter_mut().enumerate().take(kk) {
            let yy = y + (s / k) as isize - half;
            let xx = x as isize + (s % k) as isize - half;
            if yy >= 0 && xx >= 0 && yy < h as isize && xx < w as isize {
                *src = Some(((bb * h + yy as usize) * w + xx as usize) * c);
            }
        }
        if kk == MAX_KK && src.iter().all(Option::is_some) {
            let rows: [&[f32]; MAX_KK] = std::array::from_fn(|s| {
                let o = src[s].unwrap_or(0);
                &data[o..o + c]
            });
            for (i, dst) in dst.chunks_exact_mut(MAX_KK).enumerate() {
                for (d, r) in dst.iter_mut().zip(rows) {
                    d.write(r[i]);
                }
            }
        } else {
            for (i, dst) in dst.chunks_exact_mut(kk).enumerate() {
                for (d, o) in dst.iter_mut().zip(&src[..kk]) {
                    d.write(o.map_or(0.0, |o| data[o + i]));
                }
            }
        }
    }
}

/// CPU col2im: each output position sums its `k^2` entries of `cols` (a gather, so one task
/// per image row writes only its own row, in a fixed order). None for tensors that are not
/// f32 of rank 2 with `B H W` rows and `C k^2` columns.
pub(crate) fn col2im(cols: &CpuTensor, shape: [usize; 4], k: usize) -> Option<CpuTensor> {
    let (data, cshape) = dense(cols)?;
    let [b, h, w, c] = shape;
    let (kk, half) = (k * k, (k / 2) as isize);
    let row = c * kk;
    if cshape != [b * h * w, row] {
        return None;
    }
    let mut out = vec![0f32; b * h * w * c];
    let fill = |by: usize, dst: &mut [f32]| {
        let (bb, y) = (by / h, (by % h) as isize);
        for (x, dst) in dst.chunks_exact_mut(c).enumerate() {
            for s in 0..kk {
                // Output (y, x) was read as offset s by position (y - dy, x - dx).
                let yy = y - ((s / k) as isize - half);
                let xx = x as isize - ((s % k) as isize - half);
                if yy < 0 || xx < 0 || yy >= h as isize || xx >= w as isize {
                    continue;
                }
                let src = ((bb * h + yy as usize) * w + xx as usize) * row;
                for (i, v) in dst.iter_mut().enumerate() {
                    *v += data[src + i * kk + s];
                }
            }
        }
    };
    if out.len() * 4 * kk >= 1 << 20 {
        out.par_chunks_mut(w * c)
            .enumerate()
            .for_each(|(by, dst)| fill(by, dst));
    } else {
        out.chunks_mut(w * c)
            .enumerate()
            .for_each(|(by, dst)| fill(by, dst));
    }
    Some(tensor(out, &shape))
}
