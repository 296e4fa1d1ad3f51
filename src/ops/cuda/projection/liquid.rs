//! The steps of the liquid's projection on the device (feature `cuda`): the device form of
//! `model::constraints`' pressure part, walls, velocity update and energy step
//! (`model::constraints::projection_plan` says which scenes take it), each `#[cube]` function
//! one step of `SceneShape::project` for one particle or node with the host's arithmetic,
//! called in order by the call's kernel (`cuda/projection/call.rs`); here the first half
//! (begin, splat, nodes) and the copy and zeroing kernels, the rest in
//! `cuda/projection/liquid_solve.rs`.
//!
//! Layout: `frames` `[K B N 4]` (the call's predictions, projected in place), `net` the
//! network's own frames (the same shape), `before` `[B N 4]` (the frame being projected as
//! it was before the projection), `volume` `[B N]` (the liquid's rest volume, `-(1 + m)`
//! for a particle of another material `m`), `scenes` `[B SCENE_VALUES]` (`ProjectionPlan`'s
//! doc); per scene `nodes` node slots: `acc` `[B nodes 6]` fixed-point sums (phi, solid,
//! face x momentum and weight, face y momentum and weight), `grid` `[B nodes 5]` (phi, face
//! x velocity, its weight, face y velocity, its weight), `rhs`, `q`, `kind` `[B nodes]` and
//! `faces` `[B nodes 2]` (the displacement on the faces), `moves` `[B MATERIALS]`, `list`
//! `[B nodes]`. Node `(i, j)` of a scene with `side` nodes a side is its slot `i side + j`.
//! The grid's sums are 64-bit fixed point (the order the atomics land in changes no bit;
//! the host sums in particle order, so the two agree to f32 rounding).

use burn_cubecl::cubecl;
use cubecl::prelude::*;

/// Fixed-point units per unit of a node's sums (`2^32`).
pub(in crate::ops) const FIXED: f32 = 4_294_967_296.0;
/// Values per scene of `scenes` (`ProjectionPlan`'s `SCENE_VALUES`).
const SV: usize = 14;
/// Node kinds, as the host's (`pressure.rs`): free surface 0, full 1, closed 2, wall 3
/// (written as literals in [`nodes_kernel`]).

/// Particle `p` of frame `k`: for `k > 0` its position first moved by frame `k - 1`'s
/// correction (projected minus the network's own), then the frame copied to `before`.
#[cube]
pub(in crate::ops) fn begin(
    frames: &mut Array<f32>,
    net: &Array<f32>,
    before: &mut Array<f32>,
    k: u32,
    p: usize,
) {
    let per = before.len();
    if p * 4 < per {
        let at = k as usize * per + p * 4;
        if k > 0 {
            let prev = at - per;
            frames[at] += frames[prev] - net[prev];
            frames[at + 1] += frames[prev + 1] - net[prev + 1];
        }
        #[unroll]
        for c in 0..4usize {
            before[p * 4 + c] = frames[at + c];
        }
    }
}

/// Adds `w v` to word `word` of node slot `node` in fixed point.
#[cube]
fn add_fixed(acc: &mut Array<Atomic<i64>>, node: usize, word: usize, v: f32) {
    acc[node * 6 + word].fetch_add(i64::cast_from(v * f32::new(FIXED)));
}

/// The liquid's splat of particle `p` of frame `k` (a scene with liquid nodes): a liquid
/// particle past a wall is mirrored back inside, then adds its volume to its 3 x 3 nodes
/// (quadratic B-spline, clamped into the grid) and its velocity and weight to the 2 x 2
/// faces of each axis (bilinear, faces off the grid skipped); a particle of another
/// material adds the solids' volume to its nodes.
#[cube]
#[allow(clippy::too_many_arguments)]
pub(in crate::ops) fn splat(
    frames: &mut Array<f32>,
    volume: &Array<f32>,
    scenes: &Array<f32>,
    acc: &mut Array<Atomic<i64>>,
    n: u32,
    nodes: u32,
    k: u32,
    p: usize,
) {
    let s = p / n as usize;
    let side = u32::cast_from(scenes[s * SV + 1]);
    let h = scenes[s * SV];
    let at = k as usize * volume.len() * 4 + p * 4;
    let mut x = frames[at];
    let mut y = frames[at + 1];
    let vol = volume[p];
    let first = s * nodes as usize;
    if vol >= f32::new(0.0) {
        let (lo, hi) = (scenes[s * SV + 5], scenes[s * SV + 6]);
        if lo < hi {
            x = reflect(x, lo, hi);
            y = reflect(y, lo, hi);
            frames[at] = x;
            frames[at + 1] = y;
        }
    }
    let mut amount = vol;
    let mut word = 0usize;
    if vol < f32::new(0.0) {
        amount = scenes[s * SV + 8];
        word = 1usize;
    }
    splat_nodes(acc, x, y, h, amount, word, first, side);
    if vol >= f32::new(0.0) {
        let (vx, vy) = (frames[at + 2], frames[at + 3]);
        splat_faces(
            acc,
            x,
            y,
            h,
            f32::new(0.5),
            f32::new(0.0),
            vx,
            2usize,
            first,
            side,
        );
        splat_faces(
            acc,
            x,
            y,
            h,
            f32::new(0.0),
            f32::new(0.5),
            vy,
            4usize,
            first,
            side,
        );
    }
}

/// Adds `w amount` at word `word` of the 3 x 3 nodes of the quadratic stencil at `(x, y)`
/// (`bspline::stencil`, node indices clamped into the grid).
#[cube]
#[allow(clippy::too_many_arguments)]
fn splat_nodes(
    acc: &mut Array<Atomic<i64>>,
    x: f32,
    y: f32,
    h: f32,
    amount: f32,
    word: usize,
    first: usize,
    side: u32,
) {
    let top = i32::cast_from(side) - 1;
    let gx = x / h;
    let gy = y / h;
    let bx = f32::floor(gx - f32::new(0.5));
    let by = f32::floor(gy - f32::new(0.5));
    let (fx, fy) = (gx - bx, gy - by);
    let (ix, iy) = (i32::cast_from(bx), i32::cast_from(by));
    #[unroll]
    for a in 0..3u32 {
        let wa = bspline(fx, a);
        #[unroll]
        for b in 0..3u32 {
            let wb = bspline(fy, b);
            let i = clamp_i(ix + i32::cast_from(a), top);
            let j = clamp_i(iy + i32::cast_from(b), top);
            let node = first + (i as usize) * (side as usize) + j as usize;
            add_fixed(acc, node, word, wa * wb * amount);
        }
    }
}

/// `v` mirrored into `[lo, hi]` once (`Pressure::reflect`).
#[cube]
fn reflect(v: f32, lo: f32, hi: f32) -> f32 {
    let mut out = v;
    if v < lo {
        out = f32::min(f32::new(2.0) * lo - v, hi);
    } else if v > hi {
        out = f32::max(f32::new(2.0) * hi - v, lo);
    }
    out
}

/// The quadratic B-spline weight of node `a` (0, 1, 2) at offset `f` (`bspline::weights`).
#[cube]
#[allow(unused_assignments)]
fn bspline(f: f32, #[comptime] a: u32) -> f32 {
    let mut w = f32::new(0.0);
    if comptime![a == 0] {
        let d = f32::new(1.5) - f;
        w = f32::new(0.5) * d * d;
    } else if comptime![a == 1] {
        let d = f - f32::new(1.0);
        w = f32::new(0.75) - d * d;
    } else {
        let d = f - f32::new(0.5);
        w = f32::new(0.5) * d * d;
    }
    w
}

/// `v` clamped into `[0, top]`.
#[cube]
fn clamp_i(v: i32, top: i32) -> u32 {
    let mut c = v;
    if c < 0 {
        c = 0;
    }
    if c > top {
        c = top;
    }
    u32::cast_from(c)
}

/// Adds `w v` and `w` at words `word`, `word + 1` of the 2 x 2 faces of the lattice offset by
/// `(ox, oy)` cells around `(x, y)` (`Pressure::each_face`: faces off the grid skipped).
#[cube]
#[allow(clippy::too_many_arguments)]
fn splat_faces(
    acc: &mut Array<Atomic<i64>>,
    x: f32,
    y: f32,
    h: f32,
    ox: f32,
    oy: f32,
    v: f32,
    #[comptime] word: usize,
    first: usize,
    side: u32,
) {
    #[unroll]
    for a in 0..2u32 {
        #[unroll]
        for b in 0..2u32 {
            let (node, w, on) = face_corner(x, y, h, ox, oy, a, b, first, side);
            if on {
                add_fixed(acc, node, word, w * v);
                add_fixed(acc, node, word + 1, w);
            }
        }
    }
}

/// Corner `(a, b)` (each 0 or 1) of the 2 x 2 faces of the lattice offset by `(ox, oy)` cells
/// around `(x, y)` (node spacing `h`, a scene of `side` nodes a side from slot `first`): its
/// node slot, its bilinear weight, and whether it lies on the grid (`Pressure::each_face`:
/// faces off the grid are skipped). The splat of the face velocities and the gather of the
/// faces' displacement (`cuda/projection/liquid_solve.rs`) share it.
#[cube]
#[allow(clippy::too_many_arguments)]
pub(in crate::ops) fn face_corner(
    x: f32,
    y: f32,
    h: f32,
    ox: f32,
    oy: f32,
    a: u32,
    b: u32,
    first: usize,
    side: u32,
) -> (usize, f32, bool) {
    let gx = x / h - ox;
    let gy = y / h - oy;
    let bx = f32::floor(gx);
    let by = f32::floor(gy);
    let (tx, ty) = (gx - bx, gy - by);
    let i = i32::cast_from(bx) + i32::cast_from(a);
    let j = i32::cast_from(by) + i32::cast_from(b);
    let s = i32::cast_from(side);
    let on = i >= 0 && j >= 0 && i < s && j < s;
    let mut wa = f32::new(1.0) - tx;
    if a == 1 {
        wa = tx;
    }
    let mut wb = f32::new(1.0) - ty;
    if b == 1 {
        wb = ty;
    }
    let mut node = first;
    if on {
        node = first + (i as usize) * (side as usize) + j as usize;
    }
    (node, wa * wb, on)
}

/// Node slot `g`: the sums out of fixed point (and cleared for the next frame), the face
/// velocities normalised by their weights, the node's kind (`Pressure::classify`) and its
/// pressure zeroed; nothing for a slot past its scene's nodes.
#[cube]
#[allow(clippy::too_many_arguments)]
pub(in crate::ops) fn node(
    acc: &mut Array<Atomic<i64>>,
    grid: &mut Array<f32>,
    kind: &mut Array<u32>,
    q: &mut Array<f32>,
    scenes: &Array<f32>,
    nodes: u32,
    full: f32,
    g: usize,
) {
    let s = g / nodes as usize;
    let local = (g % nodes as usize) as u32;
    let side = u32::cast_from(scenes[s * SV + 1]);
    if local < side * side {
        node_values(acc, grid, kind, q, scenes, full, g, s, local, side);
    }
}

/// [`node`]'s work for a node of the scene.
#[cube]
#[allow(clippy::too_many_arguments)]
fn node_values(
    acc: &mut Array<Atomic<i64>>,
    grid: &mut Array<f32>,
    kind: &mut Array<u32>,
    q: &mut Array<f32>,
    scenes: &Array<f32>,
    full: f32,
    g: usize,
    s: usize,
    local: u32,
    side: u32,
) {
    let unit = f32::new(1.0) / f32::new(FIXED);
    let mut v = Array::<f32>::new(6usize);
    #[unroll]
    for w in 0..6usize {
        // Cleared by subtracting what was read (CUDA has no 64-bit signed exchange).
        let raw = acc[g * 6 + w].load();
        acc[g * 6 + w].fetch_add(-raw);
        v[w] = f32::cast_from(raw) * unit;
    }
    let (phi, solid) = (v[0], v[1]);
    let mut fx = v[2];
    if v[3] > f32::new(0.0) {
        fx = v[2] / v[3];
    }
    let mut fy = v[4];
    if v[5] > f32::new(0.0) {
        fy = v[4] / v[5];
    }
    grid[g * 5] = phi;
    grid[g * 5 + 1] = fx;
    grid[g * 5 + 2] = v[3];
    grid[g * 5 + 3] = fy;
    grid[g * 5 + 4] = v[5];
    q[g] = f32::new(0.0);
    let h = scenes[s * SV];
    let (lo, hi) = (scenes[s * SV + 5], scenes[s * SV + 6]);
    let x = f32::cast_from(local / side) * h;
    let y = f32::cast_from(local % side) * h;
    let half = f32::new(0.5) * h;
    let wall = x + half <= lo || x - half >= hi || y + half <= lo || y - half >= hi;
    // A literal start: a variable set from a `const` item is a comptime value in cubecl,
    // which the runtime branches below would not change.
    let mut k = 0u32;
    if wall {
        k = 3u32;
    } else if solid > phi && solid > f32::new(0.0) {
        k = 2u32;
    } else if phi >= full * scenes[s * SV + 2] {
        k = 1u32;
    }
    kind[g] = k;
}

/// `a[i] = 0` for every element.
#[cube(launch)]
pub(in crate::ops) fn zero_kernel(a: &mut Array<i64>) {
    if ABSOLUTE_POS < a.len() {
        a[ABSOLUTE_POS] = 0;
    }
}

/// `dst[i] = src[i]` for every element.
#[cube(launch)]
pub(in crate::ops) fn copy_kernel(src: &Array<f32>, dst: &mut Array<f32>) {
    if ABSOLUTE_POS < dst.len() {
        dst[ABSOLUTE_POS] = src[ABSOLUTE_POS];
    }
}
