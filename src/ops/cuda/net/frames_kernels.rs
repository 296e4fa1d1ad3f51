//! The cubecl kernel of a grid call's per-particle frames on CUDA (feature `cuda`):
//! [`frames_kernel`] and its parts (the stencil and G2P, the head, the integration).
//! `cuda/net/frames.rs` records and launches it; why it is written this way is its module doc.

use burn_cubecl::cubecl;
use cubecl::prelude::*;

use super::stencil_kernels::bspline;

/// `x` clamped into `[lo, hi]`.
#[cube]
fn clamp(x: f32, lo: f32, hi: f32) -> f32 {
    let mut y = x;
    if y < lo {
        y = lo;
    }
    if y > hi {
        y = hi;
    }
    y
}

/// `x sigmoid(x)`.
#[cube]
fn silu(x: f32) -> f32 {
    x / (f32::new(1.0) + f32::exp(f32::new(0.0) - x))
}

/// `acc[o] += x w[row, o]` for the `width` outputs of a dense layer whose weight (`[in,
/// width]`) starts at `at` in the shared `w`: input `row`'s contribution.
#[cube]
fn accumulate(
    acc: &mut Array<f32>,
    w: &SharedMemory<f32>,
    at: usize,
    row: usize,
    x: f32,
    #[comptime] width: usize,
) {
    let start = at + row * width;
    #[unroll]
    for o in 0..width {
        acc[o] += x * w[start + o];
    }
}

/// `src`'s `len` values into the shared `to` from `at`, by the cube's threads together.
#[cube]
fn load(to: &mut SharedMemory<f32>, src: &Tensor<f32>, at: usize, len: usize) {
    let mut i = UNIT_POS as usize;
    while i < len {
        to[at + i] = src[i];
        i += CUBE_DIM as usize;
    }
}

/// The head's weights and biases a cube's shared memory holds (48 KiB, what CUDA gives a
/// cube without asking for more).
pub(in crate::ops) const SHARED_VALUES: usize = 12 * 1024;

/// Threads a cube of [`frames_kernel`].
pub(in crate::ops) const FRAMES_CUBE: u32 = 128;

/// The sizes a kernel is compiled for: L latent channels, the window's `2T` values, M
/// materials, H memory values, the head's widths A and A'.
#[derive(Clone, Copy, Debug, Hash, PartialEq, Eq)]
pub(in crate::ops) struct Widths {
    pub(in crate::ops) l: usize,
    pub(in crate::ops) w2: usize,
    pub(in crate::ops) m: usize,
    pub(in crate::ops) h: usize,
    pub(in crate::ops) a: usize,
    pub(in crate::ops) a2: usize,
}

impl Widths {
    /// The head's first layer's inputs: L + 2T + M + 2 + H.
    fn inputs(&self) -> usize {
        self.l + self.w2 + self.m + 2 + self.h
    }

    /// Where each of the head's weights and biases starts in shared memory (`wa` at 0, then
    /// `ba`, `wb`, `bb`, `wo`, `bo`), and the values in all.
    pub(in crate::ops) fn offsets(&self) -> [usize; 6] {
        let ba = self.inputs() * self.a;
        let wb = ba + self.a;
        let bb = wb + self.a * self.a2;
        [
            ba,
            wb,
            bb,
            bb + self.a2,
            bb + 3 * self.a2,
            bb + 3 * self.a2 + 2,
        ]
    }
}

/// One particle per thread through the call's `bundle` frames (`model::grid::step`'s
/// `tensor_frames`, the same formulas): the stencil of its position on the `n x n` grid
/// (clamped as `stencil_kernel` clamps), G2P of frame k's latent field (`fields` `[B n^2,
/// channels]`, channels `k L..`), the head on `[gathered, window, material, position,
/// memory]` (`wa` `[L + 2T + M + 2 + H, A]`, `wb` `[A, A']`, `wo` `[A', 2]`, SiLU between),
/// `dv = dv_scale out + dv_mean`, `v' = v + dv`, `x' = x + dt (v + v') / 2` clamped into
/// `bounds` (MPM's `[dx / 2, 1 - 1.5 dx]` on the model's box grid); then the window moves on
/// by `v' / vel_scale`. `out` `[K B N, 4]` (frame k's rows `k B N..`): position, velocity.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
pub(in crate::ops) fn frames_kernel(
    fields: &Tensor<f32>,
    memory: &Tensor<f32>,
    vel: &Tensor<f32>,
    material: &Tensor<f32>,
    pos: &Tensor<f32>,
    dt: &Tensor<f32>,
    wa: &Tensor<f32>,
    ba: &Tensor<f32>,
    wb: &Tensor<f32>,
    bb: &Tensor<f32>,
    wo: &Tensor<f32>,
    bo: &Tensor<f32>,
    out: &mut Tensor<f32>,
    particles: u32,
    n: u32,
    channels: u32,
    bundle: u32,
    vel_scale: (f32, f32),
    dv_scale: (f32, f32),
    dv_mean: (f32, f32),
    bounds: (f32, f32),
    #[comptime] w: Widths,
) {
    // The head's weights and biases in shared memory, read by every thread of the cube
    // (each read one value for all of a warp): `wa` from 0, then `ba`, `wb`, `bb`, `wo`, `bo`.
    let (o_ba, o_wb, o_bb) = (
        comptime!(w.offsets()[0]),
        comptime!(w.offsets()[1]),
        comptime!(w.offsets()[2]),
    );
    let (o_wo, o_bo) = (comptime!(w.offsets()[3]), comptime!(w.offsets()[4]));
    let mut sw = SharedMemory::<f32>::new(comptime!(w.offsets()[5]));
    load(&mut sw, wa, 0usize, o_ba);
    load(&mut sw, ba, o_ba, w.a);
    load(&mut sw, wb, o_wb, comptime!(w.a * w.a2));
    load(&mut sw, bb, o_bb, w.a2);
    load(&mut sw, wo, o_wo, comptime!(2 * w.a2));
    load(&mut sw, bo, o_bo, 2usize);
    sync_cube();
    let rows = pos.len() / 2;
    let p = ABSOLUTE_POS;
    if p < rows {
        particle(
            fields,
            memory,
            vel,
            material,
            pos,
            dt,
            &sw,
            out,
            (particles, n, channels, bundle),
            (vel_scale, dv_scale, dv_mean),
            bounds,
            w,
        );
    }
}

/// [`frames_kernel`]'s particle `ABSOLUTE_POS` (see there); `sw` the head's weights.
#[cube]
#[allow(clippy::too_many_arguments)]
fn particle(
    fields: &Tensor<f32>,
    memory: &Tensor<f32>,
    vel: &Tensor<f32>,
    material: &Tensor<f32>,
    pos: &Tensor<f32>,
    dt: &Tensor<f32>,
    sw: &SharedMemory<f32>,
    out: &mut Tensor<f32>,
    sizes: (u32, u32, u32, u32),
    scales: ((f32, f32), (f32, f32), (f32, f32)),
    bounds: (f32, f32),
    #[comptime] w: Widths,
) {
    let (particles, n, channels, bundle) = sizes;
    let (vel_scale, dv_scale, dv_mean) = scales;
    let rows = pos.len() / 2;
    let p = ABSOLUTE_POS;
    let (nn, c) = (n as usize, channels as usize);
    let b = p / particles as usize;
    let (lo, hi) = bounds;
    let step = dt[b] * f32::new(0.5);
    // The head's first layer's inputs, `u`: the gathered field (from 0), the window (`at_w`),
    // the material (`at_m`), the position (`at_p`), the memory (`at_h`). All are loaded before
    // the layer's products, so that their loads are in flight together and every index is
    // known when the kernel is compiled (the arrays live in registers).
    let (at_w, at_m) = (comptime!(w.l), comptime!(w.l + w.w2));
    let (at_p, at_h) = (comptime!(w.l + w.w2 + w.m), comptime!(w.l + w.w2 + w.m + 2));
    let last = comptime!(w.w2 - 2);
    let mut u = Array::<f32>::new(comptime!(w.inputs()));
    let mut win = Array::<f32>::new(w.w2);
    #[unroll]
    for i in 0..w.w2 {
        win[i] = vel[p * w.w2 + i];
    }
    // The material and the memory are the same for every frame of the call.
    #[unroll]
    for i in 0..w.m {
        u[at_m + i] = material[p * w.m + i];
    }
    #[unroll]
    for i in 0..w.h {
        u[at_h + i] = memory[p * w.h + i];
    }
    let (mut x, mut y) = (pos[p * 2], pos[p * 2 + 1]);
    for k in 0..bundle as usize {
        gather(fields, &mut u, x, y, b * nn * nn, k * w.l, n, c, w.l);
        #[unroll]
        for i in 0..w.w2 {
            u[at_w + i] = win[i];
        }
        u[at_p] = x;
        u[at_p + 1] = y;
        let (ox, oy) = head(sw, &u, w);
        // The integration: physical velocity change, trapezoid, the box.
        let vx = win[last] * vel_scale.0;
        let vy = win[last + 1] * vel_scale.1;
        let nvx = vx + (ox * dv_scale.0 + dv_mean.0);
        let nvy = vy + (oy * dv_scale.1 + dv_mean.1);
        x = clamp(x + (vx + nvx) * step, lo, hi);
        y = clamp(y + (vy + nvy) * step, lo, hi);
        let at = (k * rows + p) * 4;
        out[at] = x;
        out[at + 1] = y;
        out[at + 2] = nvx;
        out[at + 3] = nvy;
        #[unroll]
        for i in 0..last {
            win[i] = win[i + 2];
        }
        win[last] = nvx / vel_scale.0;
        win[last + 1] = nvy / vel_scale.1;
    }
}

/// G2P into `u[0..L]` at `(x, y)` (domain units) of the latent field whose channels start at
/// `at` in `fields` (`[B n^2, c]`), rows from `scene` (`b n^2`), with the stencil
/// `stencil_kernel` builds (the position clamped into `[dx / 2, 1 - 1.5 dx - 1e-5]`).
#[cube]
#[allow(clippy::too_many_arguments)]
fn gather(
    fields: &Tensor<f32>,
    u: &mut Array<f32>,
    x: f32,
    y: f32,
    scene: usize,
    at: usize,
    n: u32,
    c: usize,
    #[comptime] l: usize,
) {
    let (nn, nf) = (n as usize, f32::cast_from(n));
    let dx = f32::new(1.0) / nf;
    let (lo, hi) = (
        f32::new(0.5) * dx,
        f32::new(1.0) - f32::new(1.5) * dx - f32::new(0.00001),
    );
    let (gx, gy) = (clamp(x, lo, hi) * nf, clamp(y, lo, hi) * nf);
    let (bx, by) = (
        f32::floor(gx - f32::new(0.5)),
        f32::floor(gy - f32::new(0.5)),
    );
    let (fx, fy) = (gx - bx, gy - by);
    let base = scene + usize::cast_from(bx) * nn + usize::cast_from(by);
    let mut node = Array::<f32>::new(9usize);
    #[unroll]
    for q in 0..9usize {
        node[q] =
            bspline::<f32>(fx - f32::cast_from(q / 3)) * bspline::<f32>(fy - f32::cast_from(q % 3));
    }
    #[unroll]
    for j in 0..l {
        u[j] = f32::new(0.0);
    }
    #[unroll]
    for q in 0..9usize {
        let row = (base + (q / 3) * nn + q % 3) * c + at;
        #[unroll]
        for j in 0..l {
            u[j] += node[q] * fields[row + j];
        }
    }
}

/// The head on the inputs `u`, its weights in `sw` ([`Widths::offsets`]): the normalised
/// velocity change `(x, y)`.
#[cube]
fn head(sw: &SharedMemory<f32>, u: &Array<f32>, #[comptime] w: Widths) -> (f32, f32) {
    let (o_ba, o_wb, o_bb) = (
        comptime!(w.offsets()[0]),
        comptime!(w.offsets()[1]),
        comptime!(w.offsets()[2]),
    );
    let (o_wo, o_bo) = (comptime!(w.offsets()[3]), comptime!(w.offsets()[4]));
    let mut acc = Array::<f32>::new(w.a);
    let mut hid = Array::<f32>::new(w.a2);
    #[unroll]
    for o in 0..w.a {
        acc[o] = sw[o_ba + o];
    }
    #[unroll]
    for i in 0..comptime!(w.inputs()) {
        accumulate(&mut acc, sw, 0usize, i, u[i], w.a);
    }
    #[unroll]
    for o in 0..w.a2 {
        hid[o] = sw[o_bb + o];
    }
    #[unroll]
    for o in 0..w.a {
        accumulate(&mut hid, sw, o_wb, o, silu(acc[o]), w.a2);
    }
    let (mut ox, mut oy) = (sw[o_bo], sw[o_bo + 1]);
    #[unroll]
    for o in 0..w.a2 {
        let s = silu(hid[o]);
        ox += s * sw[o_wo + o * 2];
        oy += s * sw[o_wo + o * 2 + 1];
    }
    (ox, oy)
}
