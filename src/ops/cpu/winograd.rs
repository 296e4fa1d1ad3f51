//! The forward of the U-Net's 3x3 same-padding convolutions on the CPU by Winograd's minimal
//! filtering F(2x2, 3x3) (Lavin & Gray 2016, "Fast Algorithms for Convolutional Neural
//! Networks", arXiv 1509.09308, section 4): each 2x2 block of outputs from its 4x4 input
//! tile with 16 multiplies per channel pair instead of im2col's 36, as 16 independent
//! products `[tiles, C_in] x [C_in, C_out]`. Inference only (`eval`, `node`): training keeps
//! im2col, whose backward is the col2im of `conv.rs`.
//!
//! Why: im2col + gemm was 60 % of the full-size grid model's step on 2 cores (perf over
//! `minflow eval`: gemm 43 %, im2col 17 %), and the step missed the 16 ms frame interval.
//!
//! With `d` the 4x4 input tile (zeros outside the grid), `g` the 3x3 kernel and
//! `B^T = [[1,0,-1,0],[0,1,1,0],[0,-1,1,0],[0,1,0,-1]]`, `G = [[1,0,0],[½,½,½],[½,-½,½],[0,0,1]]`,
//! `A^T = [[1,1,1,0],[0,1,-1,-1]]`, the 2x2 output block is
//! `A^T [ Σ_c (G g_c G^T) ⊙ (B^T d_c B) ] A`, the sum over input channels being the 16
//! products. The result equals the direct convolution up to rounding (`model_grid` tests it
//! against burn's `Conv2d`).

use std::borrow::Cow;
use std::sync::{Arc, Mutex};

use burn::backend::ndarray::NdArrayTensor;

use ndarray::{ArrayView2, ShapeBuilder};
use rayon::prelude::*;

use super::gemm::gemm_serial;
use super::{dense, slice1, tensor, CpuTensor, PrimitiveInfo, PARALLEL_WORK};

/// Points of the 4x4 transformed tile.
const POINTS: usize = 16;

/// Channels handled in step by the tile transforms (one AVX-512 register, two AVX2 ones).
const LANES: usize = 16;

/// `conv(concat(parts, channels), weight) + bias` for a 3x3 kernel with same padding,
/// channels last.
///
/// # Shapes
/// - `parts`: `[B, H, W, C_p]` each, with `H` and `W` even and `Σ C_p = C_in`
/// - `weight`: `[C_out, C_in, 3, 3]` (burn's `Conv2d` layout), `bias`: `[C_out]`
/// - returns `[B, H, W, C_out]`
///
/// None for operands it does not take (not f32, other ranks or sizes, odd `H` or `W`); the
/// caller then runs im2col.
pub(crate) fn conv3x3(
    parts: &[CpuTensor],
    weight: &CpuTensor,
    bias: Option<&CpuTensor>,
) -> Option<CpuTensor> {
    let parts: Vec<(Cow<'_, [f32]>, Vec<usize>)> =
        parts.iter().map(dense).collect::<Option<_>>()?;
    let (_, first) = parts.first()?;
    let [b, h, w, _] = <[usize; 4]>::try_from(first.as_slice()).ok()?;
    if h % 2 != 0 || w % 2 != 0 || b * h * w == 0 {
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
    let u = transformed_weight(weight, c_in, c_out)?;
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
    let y = SCRATCH.with(|scratch| {
        let (v, m) = &mut *scratch.borrow_mut();
        let v = sized(v, size.tiles() * POINTS * c_in);
        transform_input(&inputs, size, v);
        let m = sized(m, POINTS * size.tiles() * c_out);
        products(v, &u, size, m);
        transform_output(m, bias.as_deref(), size)
    });
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
    fn tiles(self) -> usize {
        self.b * (self.h / 2) * (self.w / 2)
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

/// Weights seen lately, each with its transform: inference runs the same weights step after
/// step, and transforming them every step wrote as many bytes as the products read.
static WEIGHTS: Mutex<Vec<(CpuTensor, Arc<Vec<f32>>)>> = Mutex::new(Vec::new());

/// Most weights kept in [`WEIGHTS`] (the full-size U-Net has 14 3x3 convolutions).
const KEPT_WEIGHTS: usize = 64;

/// [`transform_weight`] of `weight` (`[C_out, C_in, 3, 3]`), from [`WEIGHTS`] when the same
/// buffer was transformed before. A kept entry holds a reference to the buffer, so the
/// buffer stays allocated and unchanged (burn-ndarray copies a shared or borrowed buffer
/// before writing to it): the same address, shape and strides are the same values.
fn transformed_weight(weight: &CpuTensor, c_in: usize, c_out: usize) -> Option<Arc<Vec<f32>>> {
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
    let mut kept = WEIGHTS.lock().unwrap_or_else(|e| e.into_inner());
    if let Some((_, u)) = kept.iter().find(|(w, _)| same(w)) {
        return Some(Arc::clone(u));
    }
    let (data, _) = dense(weight)?;
    let u = Arc::new(transform_weight(&data, c_in, c_out));
    if kept.len() == KEPT_WEIGHTS {
        kept.remove(0);
    }
    kept.push((weight.clone(), Arc::clone(&u)));
    Some(u)
}

/// `U = G g G^T` for every (input, output) channel pair: `[16, C_in, C_out]`, point
/// `4 a + b` of the transformed kernel first.
fn transform_weight(weight: &[f32], c_in: usize, c_out: usize) -> Vec<f32> {
    let mut u = vec![0f32; POINTS * c_in * c_out];
    for i in 0..c_in {
        for o in 0..c_out {
            let g = &weight[(o * c_in + i) * 9..][..9];
            // G g: 4 rows of 3.
            let mut gg = [[0f32; 3]; 4];
            for x in 0..3 {
                let (g0, g1, g2) = (g[x], g[3 + x], g[6 + x]);
                gg[0][x] = g0;
                gg[1][x] = 0.5 * (g0 + g1 + g2);
                gg[2][x] = 0.5 * (g0 - g1 + g2);
                gg[3][x] = g2;
            }
            for (a, r) in gg.iter().enumerate() {
                let row = [
                    r[0],
                    0.5 * (r[0] + r[1] + r[2]),
                    0.5 * (r[0] - r[1] + r[2]),
                    r[2],
                ];
                for (bb, value) in row.into_iter().enumerate() {
                    u[((4 * a + bb) * c_in + i) * c_out + o] = value;
                }
            }
        }
    }
    u
}

/// `V = B^T d B` of every tile and input channel: `[tiles, 16, C_in]`, tiles in row-major
/// order of `[B, H/2, W/2]`; one task per row of tiles.
fn transform_input(parts: &[Part<'_>], size: Size, v: &mut [f32]) {
    let Size { h, w, c_in, .. } = size;
    let (th, tw) = (h / 2, w / 2);
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
                // The 16 input pixels of the tile, row by row (zeros outside the grid).
                let d: [&[f32]; POINTS] = std::array::from_fn(|s| {
                    let y = (2 * ty + s / 4) as isize - 1;
                    let x = (2 * tx + s % 4) as isize - 1;
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

/// `B^T d B` on `LANES` channels at once; `d` and the result row-major 4x4.
#[inline(always)]
fn input_tile(d: &[[f32; LANES]; POINTS], v: &mut [[f32; LANES]; POINTS]) {
    let mut t = [[0f32; LANES]; POINTS];
    for j in 0..4 {
        for l in 0..LANES {
            let (d0, d1, d2, d3) = (d[j][l], d[4 + j][l], d[8 + j][l], d[12 + j][l]);
            t[j][l] = d0 - d2;
            t[4 + j][l] = d1 + d2;
            t[8 + j][l] = d2 - d1;
            t[12 + j][l] = d1 - d3;
        }
    }
    for i in 0..4 {
        for l in 0..LANES {
            let (t0, t1, t2, t3) = (
                t[4 * i][l],
                t[4 * i + 1][l],
                t[4 * i + 2][l],
                t[4 * i + 3][l],
            );
            v[4 * i][l] = t0 - t2;
            v[4 * i + 1][l] = t1 + t2;
            v[4 * i + 2][l] = t2 - t1;
            v[4 * i + 3][l] = t1 - t3;
        }
    }
}

/// `M_s = V_s U_s` for the 16 points `s`: `[16, tiles, C_out]`; one task per point, each a
/// single-threaded product.
fn products(v: &[f32], u: &[f32], size: Size, m: &mut [f32]) {
    let Size { c_in, c_out, .. } = size;
    let tiles = size.tiles();
    let product = |s: usize, dst: &mut [f32]| {
        // Point s of every tile: rows 16 C_in apart.
        let vs = ArrayView2::from_shape((tiles, c_in).strides((POINTS * c_in, 1)), &v[s * c_in..])
            .expect("V holds every tile's 16 points");
        let us = ArrayView2::from_shape((c_in, c_out), &u[s * c_in * c_out..][..c_in * c_out])
            .expect("U holds 16 C_in x C_out matrices");
        gemm_serial(dst, &vs, &us);
    };
    let parallel = tiles * c_in * c_out * POINTS >= PARALLEL_WORK;
    for_chunks(m, tiles * c_out, parallel, product);
}

/// `A^T M A + bias` of every tile into the row-major `[B, H, W, C_out]` output; one task per
/// row of tiles (two image rows).
fn transform_output(m: &[f32], bias: Option<&[f32]>, size: Size) -> Vec<f32> {
    let Size { b, h, w, c_out, .. } = size;
    let tw = w / 2;
    let plane = size.tiles() * c_out;
    let zeros = vec![0f32; c_out];
    let bias = bias.unwrap_or(&zeros);
    let mut y = vec![0f32; b * h * w * c_out];
    let parallel = y.len() * 4 >= PARALLEL_WORK;
    for_chunks(&mut y, 2 * w * c_out, parallel, |row, dst| {
        let mut lanes = [[0f32; LANES]; POINTS];
        let mut out = [[0f32; LANES]; 4];
        let mut shift = [0f32; LANES];
        for tx in 0..tw {
            let tile = row * tw + tx;
            let mut start = 0;
            while start < c_out {
                let n = LANES.min(c_out - start);
                for (s, l) in lanes.iter_mut().enumerate() {
                    load(&m[s * plane + tile * c_out + start..][..n], l);
                }
                load(&bias[start..start + n], &mut shift);
                output_tile(&lanes, &mut out);
                for (q, values) in out.iter_mut().enumerate() {
                    let (r, x) = (q / 2, 2 * tx + q % 2);
                    let at = (r * w + x) * c_out + start;
                    for (v, b) in values.iter_mut().zip(&shift) {
                        *v += b;
                    }
                    store(&mut dst[at..at + n], values);
                }
                start += n;
            }
        }
    });
    y
}

/// `A^T m A` on `LANES` channels at once: the 2x2 outputs, row-major.
#[inline(always)]
fn output_tile(m: &[[f32; LANES]; POINTS], y: &mut [[f32; LANES]; 4]) {
    let mut s = [[0f32; LANES]; 8];
    for j in 0..4 {
        for l in 0..LANES {
            let (m0, m1, m2, m3) = (m[j][l], m[4 + j][l], m[8 + j][l], m[12 + j][l]);
            s[j][l] = m0 + m1 + m2;
            s[4 + j][l] = m1 - m2 - m3;
        }
    }
    for r in 0..2 {
        for l in 0..LANES {
            let (s0, s1, s2, s3) = (
                s[4 * r][l],
                s[4 * r + 1][l],
                s[4 * r + 2][l],
                s[4 * r + 3][l],
            );
            y[2 * r][l] = s0 + s1 + s2;
            y[2 * r + 1][l] = s1 - s2 - s3;
        }
    }
}
