//! The forward of the U-Net's 3x3 same-padding convolutions on the CPU by Winograd's minimal
//! filtering F(4x4, 3x3) (Lavin & Gray 2016, "Fast Algorithms for Convolutional Neural
//! Networks", arXiv 1509.09308, sections 4 and 5): each 4x4 block of outputs from its 6x6
//! input tile with 36 multiplies per channel pair instead of im2col's 144, as 36 independent
//! products `[tiles, C_in] x [C_in, C_out]`. Inference only (`eval`, `node`): training keeps
//! im2col, whose backward is the col2im of `conv.rs`.
//!
//! Why: im2col + gemm was 60 % of the full-size grid model's step on 2 cores (perf over
//! `minflow eval`: gemm 43 %, im2col 17 %), and the step missed the 16 ms frame interval.
//! F(2x2, 3x3) (16 multiplies per 2x2 block) cut that to 0.76x the CPU time; F(4x4, 3x3)
//! multiplies 1.78x less again and expands the input 2.25x instead of 4x (docs/grid.md, "CPU
//! speed").
//!
//! With `d` the 6x6 input tile (zeros outside the grid) and `g` the 3x3 kernel, the 4x4 output
//! block is `A^T [ Σ_c (G g_c G^T) ⊙ (B^T d_c B) ] A`, the sum over input channels being the
//! 36 products, with Lavin & Gray's interpolation points 0, ±1, ±2 (their equation 9's
//! matrices, written out in [`transform_weight`], [`input_tile`] and [`output_tile`]). Grids
//! that are not a multiple of 4 get partial tiles at their far edges. The result equals the
//! direct convolution up to rounding, which these points make ~10x larger than F(2x2, 3x3)'s
//! (`model_grid` tests it against burn's `Conv2d`).

use std::borrow::Cow;
use std::mem::MaybeUninit;
use std::sync::Arc;

use burn::backend::ndarray::NdArrayTensor;

use ndarray::{ArrayView2, ShapeBuilder};
use rayon::prelude::*;

use super::activation::sigmoid1;
use super::gemm::gemm_serial;
use super::{dense, slice1, tensor, CpuTensor, PrimitiveInfo, PARALLEL_WORK};
use crate::ops::PreparedWeights;

/// Outputs per tile side (the m of F(m x m, 3x3)).
const TILE: usize = 4;

/// Input pixels per tile side, `TILE + 2`.
const ALPHA: usize = TILE + 2;

/// Points of the 6x6 transformed tile.
const POINTS: usize = ALPHA * ALPHA;

/// Channels handled in step by the tile transforms (one AVX-512 register, two AVX2 ones).
const LANES: usize = 16;

/// `conv(concat(parts, channels), weight) + bias` for a 3x3 kernel with same padding,
/// channels last, then SiLU (`x sigmoid(x)`, as `activation.rs` computes it) when `silu`.
///
/// # Shapes
/// - `parts`: `[B, H, W, C_p]` each, with `Σ C_p = C_in`
/// - `weight`: `[C_out, C_in, 3, 3]` (burn's `Conv2d` layout), `bias`: `[C_out]`
/// - returns `[B, H, W, C_out]`
///
/// The transformed weight comes from `prepared` while `weight` is the tensor it was made
/// from ([`transformed_weight`]). None for operands it does not take (not f32, other ranks or
/// sizes); the caller then runs im2col.
pub(crate) fn conv3x3(
    parts: &[CpuTensor],
    weight: &CpuTensor,
    bias: Option<&CpuTensor>,
    silu: bool,
    prepared: &PreparedWeights,
) -> Option<CpuTensor> {
    let parts: Vec<(Cow<'_, [f32]>, Vec<usize>)> =
        parts.iter().map(dense).collect::<Option<_>>()?;
    let (_, first) = parts.first()?;
    let [b, h, w, _] = <[usize; 4]>::try_from(first.as_slice()).ok()?;
    if b * h * w == 0 {
        return None;
    }
    let mut offsets = Vec::with_capacity(parts.len());
    let mut c_in = 0;
    for (_, shape) in &parts {
        if shape.len() != 4 || shape[..3] != [b, h, w] {
            return None;
        }
        offsets.push(c_in);
        c_in += shape[3];
    }
    let wshape = weight.shape_vec();
    if wshape.len() != 4 || wshape[1..] != [c_in, 3, 3] {
        return None;
    }
    let c_out = wshape[0];
    let u = transformed_weight(weight, c_in, c_out, prepared)?;
    let bias = match bias {
        Some(bias) => Some(slice1(bias)?.to_vec()),
        None => None,
    };
    if bias.as_ref().is_some_and(|b| b.len() != c_out) {
        return None;
    }
    let size = Size {
        b,
        h,
        w,
        c_in,
        c_out,
    };
    let inputs: Vec<Part<'_>> = parts
        .iter()
        .zip(&offsets)
        .map(|((data, shape), &offset)| Part {
            data,
            channels: shape[3],
            offset,
        })
        .collect();
    // The buffers are taken out of the thread's slot for the call and put back after: the
    // passes below run on the rayon pool, whose waiting thread may run another convolution
    // (another scene's, another test's) meanwhile, which then finds the slot empty and
    // allocates its own instead of borrowing the slot twice.
    let (mut v_buf, mut m_buf) = SCRATCH.with(|scratch| std::mem::take(&mut *scratch.borrow_mut()));
    let v = sized(&mut v_buf, size.tiles() * POINTS * c_in);
    transform_input(&inputs, size, v);
    let m = sized(&mut m_buf, POINTS * size.tiles() * c_out);
    products(v, &u, size, m);
    let y = transform_output(m, bias.as_deref(), silu, size);
    SCRATCH.with(|scratch| *scratch.borrow_mut() = (v_buf, m_buf));
    Some(tensor(y, &[b, h, w, c_out]))
}

thread_local! {
    /// The transformed input `V` and the products `M` of the last convolution on this
    /// thread, kept for the next: every element is written before it is read, so a buffer
    /// reused at its size needs no zero fill (which took 10 % of a step).
    static SCRATCH: std::cell::RefCell<(Vec<f32>, Vec<f32>)> = const {
        std::cell::RefCell::new((Vec::new(), Vec::new()))
    };
}

/// The first `len` elements of `buf`, grown (zero-filled) when shorter.
fn sized(buf: &mut Vec<f32>, len: usize) -> &mut [f32] {
    if buf.len() < len {
        buf.resize(len, 0.0);
    }
    &mut buf[..len]
}

/// The sizes of one convolution.
#[derive(Clone, Copy)]
struct Size {
    b: usize,
    h: usize,
    w: usize,
    c_in: usize,
    c_out: usize,
}

impl Size {
    /// Tile rows and columns: `ceil(H / 4)`, `ceil(W / 4)`.
    fn tile_grid(self) -> (usize, usize) {
        (self.h.div_ceil(TILE), self.w.div_ceil(TILE))
    }

    fn tiles(self) -> usize {
        let (th, tw) = self.tile_grid();
        self.b * th * tw
    }
}

/// One input part: its row-major `[B, H, W, channels]` data and the first input channel it
/// fills.
struct Part<'a> {
    data: &'a [f32],
    channels: usize,
    offset: usize,
}

/// Runs `f` over chunks of `buf` (with their index), on the rayon pool when `parallel`.
fn for_chunks(
    buf: &mut [f32],
    chunk: usize,
    parallel: bool,
    f: impl Fn(usize, &mut [f32]) + Sync + Send,
) {
    if parallel {
        buf.par_chunks_mut(chunk)
            .enumerate()
            .for_each(|(i, c)| f(i, c));
    } else {
        buf.chunks_mut(chunk).enumerate().for_each(|(i, c)| f(i, c));
    }
}

/// [`transform_weight`] of `weight` (`[C_out, C_in, 3, 3]`), kept in the convolution's
/// `prepared` slot with a handle on `weight` (inference runs the same weights step after
/// step). The handle keeps the buffer allocated and unchanged (burn-ndarray copies a shared
/// buffer before writing to it), so the same address, shape and strides are the same
/// values; other weights replace the entry.
fn transformed_weight(
    weight: &CpuTensor,
    c_in: usize,
    c_out: usize,
    prepared: &PreparedWeights,
) -> Option<Arc<Vec<f32>>> {
    let NdArrayTensor::F32(storage) = weight else {
        return None;
    };
    let view = storage.view();
    let same = |kept: &CpuTensor| match kept {
        NdArrayTensor::F32(kept) => {
            let kept = kept.view();
            kept.as_ptr() == view.as_ptr()
                && kept.shape() == view.shape()
                && kept.strides() == view.strides()
        }
        _ => false,
    };
    prepared.get_or_prepare(same, || {
        let (data, _) = dense(weight)?;
        Some((weight.clone(), transform_weight(&data, c_in, c_out)))
    })
}

/// `U = G g G^T` for every (input, output) channel pair: `[36, C_in, C_out]`, point
/// `6 a + b` of the transformed kernel first. `G` is Lavin & Gray's for F(4, 3):
/// rows `[1/4, 0, 0]`, `-[1, 1, 1]/6`, `-[1, -1, 1]/6`, `[1/24, 1/12, 1/6]`,
/// `[1/24, -1/12, 1/6]`, `[0, 0, 1]`.
fn transform_weight(weight: &[f32], c_in: usize, c_out: usize) -> Vec<f32> {
    /// `G x` for a kernel column or row `x`.
    fn g_times(x: [f32; 3]) -> [f32; ALPHA] {
        let [g0, g1, g2] = x;
        [
            g0 / 4.0,
            -(g0 + g1 + g2) / 6.0,
            -(g0 - g1 + g2) / 6.0,
            g0 / 24.0 + g1 / 12.0 + g2 / 6.0,
            g0 / 24.0 - g1 / 12.0 + g2 / 6.0,
            g2,
        ]
    }
    let mut u = vec![0f32; POINTS * c_in * c_out];
    for i in 0..c_in {
        for o in 0..c_out {
            let g = &weight[(o * c_in + i) * 9..][..9];
            // G g: 6 rows of 3 (one column of g at a time).
            let columns: [[f32; ALPHA]; 3] =
                std::array::from_fn(|x| g_times([g[x], g[3 + x], g[6 + x]]));
            for a in 0..ALPHA {
                let row = g_times([columns[0][a], columns[1][a], columns[2][a]]);
                for (bb, value) in row.into_iter().enumerate() {
                    u[((ALPHA * a + bb) * c_in + i) * c_out + o] = value;
                }
            }
        }
    }
    u
}

/// `V = B^T d B` of every tile and input channel: `[tiles, 36, C_in]`, tiles in row-major
/// order of `[B, ceil(H/4), ceil(W/4)]`; one task per row of tiles.
fn transform_input(parts: &[Part<'_>], size: Size, v: &mut [f32]) {
    let Size { h, w, c_in, .. } = size;
    let (th, tw) = size.tile_grid();
    let widest = parts.iter().map(|p| p.channels).max().unwrap_or(0);
    let zeros = vec![0f32; widest];
    let parallel = v.len() * 4 >= PARALLEL_WORK;
    for_chunks(v, tw * POINTS * c_in, parallel, |row, dst| {
        let (bb, ty) = (row / th, row % th);
        let mut lanes = [[0f32; LANES]; POINTS];
        let mut out = [[0f32; LANES]; POINTS];
        for (tx, tile) in dst.chunks_exact_mut(POINTS * c_in).enumerate() {
            for part in parts {
                let c = part.channels;
                // The 36 input pixels of the tile, row by row (zeros outside the grid).
                let d: [&[f32]; POINTS] = std::array::from_fn(|s| {
                    let y = (TILE * ty + s / ALPHA) as isize - 1;
                    let x = (TILE * tx + s % ALPHA) as isize - 1;
                    if y < 0 || x < 0 || y >= h as isize || x >= w as isize {
                        &zeros[..c]
                    } else {
                        &part.data[((bb * h + y as usize) * w + x as usize) * c..][..c]
                    }
                });
                let mut start = 0;
                while start < c {
                    let n = LANES.min(c - start);
                    for (l, src) in lanes.iter_mut().zip(&d) {
                        load(&src[start..start + n], l);
                    }
                    input_tile(&lanes, &mut out);
                    for (s, values) in out.iter().enumerate() {
                        let at = s * c_in + part.offset + start;
                        store(&mut tile[at..at + n], values);
                    }
                    start += n;
                }
            }
        }
    });
}

/// Up to `LANES` values, zero-padded (a fixed-size copy for a full block, so no call to
/// `memcpy`).
#[inline(always)]
fn load(src: &[f32], lanes: &mut [f32; LANES]) {
    match <&[f32; LANES]>::try_from(src) {
        Ok(full) => *lanes = *full,
        Err(_) => {
            lanes.fill(0.0);
            lanes[..src.len()].copy_from_slice(src);
        }
    }
}

/// The first `dst.len()` (at most `LANES`) of `values` into `dst`.
#[inline(always)]
fn store(dst: &mut [f32], values: &[f32; LANES]) {
    match <&mut [f32; LANES]>::try_from(&mut *dst) {
        Ok(full) => *full = *values,
        Err(_) => {
            let n = dst.len();
            dst.copy_from_slice(&values[..n]);
        }
    }
}

/// `B^T x` for one column (or row) `x` of a tile, `LANES` channels at a time. Lavin & Gray's
/// `B^T` for F(4, 3): rows `[4, 0, -5, 0, 1, 0]`, `[0, -4, -4, 1, 1, 0]`,
/// `[0, 4, -4, -1, 1, 0]`, `[0, -2, -1, 2, 1, 0]`, `[0, 2, -1, -2, 1, 0]`,
/// `[0, 4, 0, -5, 0, 1]`.
#[inline(always)]
fn bt_times(x: [f32; ALPHA]) -> [f32; ALPHA] {
    let [d0, d1, d2, d3, d4, d5] = x;
    let (a, b) = (d4 - 4.0 * d2, d3 - 4.0 * d1);
    let (c, e) = (d4 - d2, 2.0 * (d3 - d1));
    [
        4.0 * d0 - 5.0 * d2 + d4,
        a + b,
        a - b,
        c + e,
        c - e,
        4.0 * d1 - 5.0 * d3 + d5,
    ]
}

/// `B^T d B` on `LANES` channels at once; `d` and the result row-major 6x6.
#[inline(always)]
fn input_tile(d: &[[f32; LANES]; POINTS], v: &mut [[f32; LANES]; POINTS]) {
    let mut t = [[0f32; LANES]; POINTS];
    for j in 0..ALPHA {
        for l in 0..LANES {
            let col = bt_times(std::array::from_fn(|r| d[ALPHA * r + j][l]));
            for (r, value) in col.into_iter().enumerate() {
                t[ALPHA * r + j][l] = value;
            }
        }
    }
    for i in 0..ALPHA {
        for l in 0..LANES {
            let row = bt_times(std::array::from_fn(|k| t[ALPHA * i + k][l]));
            for (k, value) in row.into_iter().enumerate() {
                v[ALPHA * i + k][l] = value;
            }
        }
    }
}

/// `M_s = V_s U_s` for the 36 points `s`: `[36, tiles, C_out]`; one task per point, each a
/// single-threaded product.
fn products(v: &[f32], u: &[f32], size: Size, m: &mut [f32]) {
    let Size { c_in, c_out, .. } = size;
    let tiles = size.tiles();
    let product = |s: usize, dst: &mut [f32]| {
        // Point s of every tile: rows 36 C_in apart.
        let vs = ArrayView2::from_shape((tiles, c_in).strides((POINTS * c_in, 1)), &v[s * c_in..])
            .expect("V holds every tile's 36 points");
        let us = ArrayView2::from_shape((c_in, c_out), &u[s * c_in * c_out..][..c_in * c_out])
            .expect("U holds 36 C_in x C_out matrices");
        gemm_serial(dst, &vs, &us, false);
    };
    let parallel = tiles * c_in * c_out * POINTS >= PARALLEL_WORK;
    for_chunks(m, tiles * c_out, parallel, product);
}

/// `A^T M A + bias` of every tile (then SiLU when `silu`) into the row-major
/// `[B, H, W, C_out]` output; one task per row of tiles (four image rows, fewer in a partial
/// last row).
fn transform_output(m: &[f32], bias: Option<&[f32]>, silu: bool, size: Size) -> Vec<f32> {
    let Size { b, h, w, c_out, .. } = size;
    let (th, tw) = size.tile_grid();
    let plane = size.tiles() * c_out;
    let zeros = vec![0f32; c_out];
    let bias = bias.unwrap_or(&zeros);
    let len = b * h * w * c_out;
    let mut y: Vec<f32> = Vec::with_capacity(len);
    let parallel = len * 4 >= PARALLEL_WORK;
    // One chunk per row of tiles: up to four image rows.
    let row_len = w * c_out;
    let rows_of = |ty: usize| TILE.min(h - ty * TILE);
    let mut chunks: Vec<(usize, &mut [MaybeUninit<f32>])> = Vec::with_capacity(b * th);
    let mut rest = &mut y.spare_capacity_mut()[..len];
    for bb in 0..b {
        for ty in 0..th {
            let (chunk, tail) = rest.split_at_mut(rows_of(ty) * row_len);
            chunks.push((bb * th + ty, chunk));
            rest = tail;
        }
    }
    let run = |(row, dst): (usize, &mut [MaybeUninit<f32>])| {
        let rows = dst.len() / row_len;
        let mut lanes = [[0f32; LANES]; POINTS];
        let mut out = [[0f32; LANES]; TILE * TILE];
        let mut shift = [0f32; LANES];
        for tx in 0..tw {
            let tile = row * tw + tx;
            let cols = TILE.min(w - tx * TILE);
            let mut start = 0;
            while start < c_out {
                let n = LANES.min(c_out - start);
                for (s, l) in lanes.iter_mut().enumerate() {
                    load(&m[s * plane + tile * c_out + start..][..n], l);
                }
                load(&bias[start..start + n], &mut shift);
                output_tile(&lanes, &mut out);
                for r in 0..rows {
                    for q in 0..cols {
                        let values = &mut out[TILE * r + q];
                        let at = (r * w + TILE * tx + q) * c_out + start;
                        for (v, b) in values.iter_mut().zip(&shift) {
                            *v += b;
                        }
                        if silu {
                            for v in values.iter_mut() {
                                *v *= sigmoid1(*v);
                            }
                        }
                        for (d, v) in dst[at..at + n].iter_mut().zip(values.iter()) {
                            d.write(*v);
                        }
                    }
                }
                start += n;
            }
        }
    };
    if parallel {
        chunks.into_par_iter().for_each(run);
    } else {
        chunks.into_iter().for_each(run);
    }
    // SAFETY: the chunks cover the first `len` elements, and every tile wrote each of its
    // image rows' columns (`cols` of 4 at the right edge) and channels.
    unsafe { y.set_len(len) };
    y
}

/// `A^T x` for one column (or row) `x` of a transformed tile. Lavin & Gray's `A^T` for
/// F(4, 3): rows `[1, 1, 1, 1, 1, 0]`, `[0, 1, -1, 2, -2, 0]`, `[0, 1, 1, 4, 4, 0]`,
/// `[0, 1, -1, 8, -8, 1]`.
#[inline(always)]
fn at_times(x: [f32; ALPHA]) -> [f32; TILE] {
    let [m0, m1, m2, m3, m4, m5] = x;
    let (p, q) = (m1 + m2, m3 + m4);
    let (r, t) = (m1 - m2, m3 - m4);
    [m0 + p + q, r + 2.0 * t, p + 4.0 * q, r + 8.0 * t + m5]
}

/// `A^T m A` on `LANES` channels at once: the 4x4 outputs, row-major.
#[inline(always)]
fn output_tile(m: &[[f32; LANES]; POINTS], y: &mut [[f32; LANES]; TILE * TILE]) {
    let mut s = [[0f32; LANES]; TILE * ALPHA];
    for j in 0..ALPHA {
        for l in 0..LANES {
            let col = at_times(std::array::from_fn(|r| m[ALPHA * r + j][l]));
            for (r, value) in col.into_iter().enumerate() {
                s[ALPHA * r + j][l] = value;
            }
        }
    }
    for r in 0..TILE {
        for l in 0..LANES {
            let row = at_times(std::array::from_fn(|k| s[ALPHA * r + k][l]));
            for (q, value) in row.into_iter().enumerate() {
                y[TILE * r + q][l] = value;
            }
        }
    }
}
