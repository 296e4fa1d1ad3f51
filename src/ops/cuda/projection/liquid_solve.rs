//! The rest of the liquid's projection on the device (feature `cuda`, layout in
//! `cuda/projection/liquid.rs`): the right-hand side at the full nodes, the red-black projected SOR
//! sweeps, the displacement on the faces and each liquid particle moved by it
//! (`Pressure::project`'s steps 4 and 5), then every particle's walls and velocity update
//! and the liquid's energy step (`SceneShape::project`, `energy::restore`).

use burn_cubecl::cubecl;
use cubecl::prelude::*;

use super::liquid::face_corner;

/// Values per scene of `scenes` (`ProjectionPlan`'s `SCENE_VALUES`), the materials' spacings from
/// `SPACING`.
const SV: usize = 14;
const SPACING: usize = 10;
/// Fixed-point units of a move's sum per particle spacing (`2^20`).
pub(in crate::ops) const MOVE_UNITS: f32 = 1_048_576.0;
/// The node kinds below which a node is open (free surface or full), and the wall's.
const FULL: u32 = 1;
const CLOSED: u32 = 2;
const WALL: u32 = 3;

/// The node slot's scene, its node index within the scene and the scene's side; `side` 0
/// (or a slot past the scene's nodes) marks a thread with no node.
#[cube]
fn slot(g: usize, nodes: u32, scenes: &Array<f32>) -> (usize, u32, u32) {
    let s = g / nodes as usize;
    let local = (g % nodes as usize) as u32;
    let mut side = u32::cast_from(scenes[s * SV + 1]);
    if local >= side * side {
        side = 0;
    }
    (s, local, side)
}

/// A face's velocity for the divergence: the wall's (0) when `other` is a wall node, else
/// the liquid's where the face holds liquid; `ok` cleared where it holds none.
#[cube]
fn face(grid: &Array<f32>, kind: &Array<u32>, f: usize, other: usize, word: usize) -> (f32, bool) {
    let mut v = f32::new(0.0);
    let mut ok = true;
    if kind[other] != WALL {
        if grid[f * 5 + word + 1] > f32::new(0.0) {
            v = grid[f * 5 + word];
        } else {
            ok = false;
        }
    }
    (v, ok)
}

/// Node slot `g`'s right-hand side: at a full node `r = stiffness max(phi - rest, 0) / phi -
/// dt div v` (the divergence part where `velocity`), `rest` the band's threshold near the
/// walls; 0 at the scene's other nodes.
#[cube]
#[allow(clippy::too_many_arguments)]
pub(in crate::ops) fn rhs(
    grid: &Array<f32>,
    kind: &Array<u32>,
    rhs: &mut Array<f32>,
    scenes: &Array<f32>,
    nodes: u32,
    stiffness: f32,
    velocity: u32,
    g: usize,
) {
    let (s, local, side) = slot(g, nodes, scenes);
    if side > 0 {
        rhs[g] = f32::new(0.0);
        if kind[g] == FULL {
            rhs[g] = rhs_at(grid, kind, scenes, stiffness, velocity, g, s, local, side);
        }
    }
}

/// [`rhs`] at a full node.
#[cube]
#[allow(clippy::too_many_arguments)]
fn rhs_at(
    grid: &Array<f32>,
    kind: &Array<u32>,
    scenes: &Array<f32>,
    stiffness: f32,
    velocity: u32,
    g: usize,
    s: usize,
    local: u32,
    side: u32,
) -> f32 {
    let h = scenes[s * SV];
    let (band, lo, hi) = (scenes[s * SV + 3], scenes[s * SV + 5], scenes[s * SV + 6]);
    let (i, j) = (local / side, local % side);
    let (x, y) = (f32::cast_from(i) * h, f32::cast_from(j) * h);
    let inside = x > lo + band && x < hi - band && y > lo + band && y < hi - band;
    let mut rest = scenes[s * SV + 4];
    if inside {
        rest = scenes[s * SV + 2];
    }
    let phi = grid[g * 5];
    let r = stiffness * f32::max(phi - rest, f32::new(0.0)) / phi;
    let mut div = f32::new(0.0);
    if velocity == 1 && i > 0 && j > 0 && i + 1 < side && j + 1 < side {
        let sd = side as usize;
        let (left, down) = (g - sd, g - 1);
        let (r_v, r_ok) = face(grid, kind, g, g + sd, 1usize);
        let (l_v, l_ok) = face(grid, kind, left, left, 1usize);
        let (u_v, u_ok) = face(grid, kind, g, g + 1, 3usize);
        let (d_v, d_ok) = face(grid, kind, down, down, 3usize);
        if r_ok && l_ok && u_ok && d_ok {
            div = (r_v - l_v + u_v - d_v) / h;
        }
    }
    let mut out = r;
    if velocity == 1 {
        out = r - scenes[s * SV + 7] * div;
    }
    out
}

/// Node slot `g` in one colour's half sweep of the projected SOR for `q = p / h^2`
/// (`Pressure::solve`): a full node of colour `colour` (`(i + j) % 2`) with open neighbours,
/// summed in the order `i - 1, i + 1, j - 1, j + 1`, relaxed towards `(r + sum) / k` and
/// kept `>= 0`. A colour's nodes read only the other colour's, so a sweep is the host's in
/// any order.
#[cube]
#[allow(clippy::too_many_arguments)]
pub(in crate::ops) fn sor(
    kind: &Array<u32>,
    rhs: &Array<f32>,
    q: &mut Array<f32>,
    scenes: &Array<f32>,
    nodes: u32,
    omega: f32,
    colour: u32,
    g: usize,
) {
    let (_s, local, side) = slot(g, nodes, scenes);
    if side > 0 && kind[g] == FULL && (local / side + local % side) % 2 == colour {
        let (i, j) = (local / side, local % side);
        let sd = side as usize;
        let mut sum = f32::new(0.0);
        let mut k: u32 = 0u32;
        if i > 0 && kind[g - sd] < CLOSED {
            sum += q[g - sd];
            k += 1u32;
        }
        if i + 1 < side && kind[g + sd] < CLOSED {
            sum += q[g + sd];
            k += 1u32;
        }
        if j > 0 && kind[g - 1] < CLOSED {
            sum += q[g - 1];
            k += 1u32;
        }
        if j + 1 < side && kind[g + 1] < CLOSED {
            sum += q[g + 1];
            k += 1u32;
        }
        if k > 0 {
            let old = q[g];
            let target = (rhs[g] + sum) / f32::cast_from(k);
            q[g] = f32::max(old + omega * (target - old), f32::new(0.0));
        }
    }
}

/// Node slot `g`'s faces: the displacement on each face between two open nodes, `(q_i -
/// q_n) h`, 0 elsewhere (`Pressure::displace`).
#[cube]
pub(in crate::ops) fn faces(
    kind: &Array<u32>,
    q: &Array<f32>,
    faces: &mut Array<f32>,
    scenes: &Array<f32>,
    nodes: u32,
    g: usize,
) {
    let (s, local, side) = slot(g, nodes, scenes);
    if side > 0 {
        let h = scenes[s * SV];
        let (i, j) = (local / side, local % side);
        let sd = side as usize;
        let open = kind[g] < CLOSED;
        let mut dx = f32::new(0.0);
        let mut dy = f32::new(0.0);
        if i + 1 < side && open && kind[g + sd] < CLOSED {
            dx = (q[g] - q[g + sd]) * h;
        }
        if j + 1 < side && open && kind[g + 1] < CLOSED {
            dy = (q[g] - q[g + 1]) * h;
        }
        faces[g * 2] = dx;
        faces[g * 2 + 1] = dy;
    }
}

/// The bilinear average of word `word` of `faces` at `(x, y)` on the lattice offset by
/// `(ox, oy)` cells (faces off the grid skipped).
#[cube]
#[allow(clippy::too_many_arguments)]
fn gather_faces(
    faces: &Array<f32>,
    x: f32,
    y: f32,
    h: f32,
    ox: f32,
    oy: f32,
    #[comptime] word: usize,
    first: usize,
    side: u32,
) -> f32 {
    let mut d = f32::new(0.0);
    #[unroll]
    for a in 0..2u32 {
        #[unroll]
        for b in 0..2u32 {
            let (node, w, on) = face_corner(x, y, h, ox, oy, a, b, first, side);
            if on {
                d += w * faces[node * 2 + word];
            }
        }
    }
    d
}

/// Particle `p` of frame `k`, if liquid, moved by the faces' displacement at its position
/// (bilinear G2P of the change).
#[cube]
#[allow(clippy::too_many_arguments)]
pub(in crate::ops) fn displace(
    frames: &mut Array<f32>,
    volume: &Array<f32>,
    faces: &Array<f32>,
    scenes: &Array<f32>,
    n: u32,
    nodes: u32,
    k: u32,
    p: usize,
) {
    let s = p / n as usize;
    let side = u32::cast_from(scenes[s * SV + 1]);
    if volume[p] >= f32::new(0.0) && side > 0 {
        let h = scenes[s * SV];
        let first = s * nodes as usize;
        let at = k as usize * volume.len() * 4 + p * 4;
        let (x, y) = (frames[at], frames[at + 1]);
        let half = f32::new(0.5);
        let zero = f32::new(0.0);
        let dx = gather_faces(faces, x, y, h, half, zero, 0usize, first, side);
        let dy = gather_faces(faces, x, y, h, zero, half, 1usize, first, side);
        frames[at] = x + dx;
        frames[at + 1] = y + dy;
    }
}

/// Particle `p` of frame `k` clamped into the walls (where `flags` has bit 0), then its
/// velocity given the move over `dt`: `v += (x - x_before) / dt` (`SceneShape::project`),
/// and the move in its material's spacings added to the scene's `moves` (`[B MATERIALS]`,
/// fixed point, [`MOVE_UNITS`]; the liquid's material id is `flags / 2`, the others' come
/// from `volume`).
#[cube]
#[allow(clippy::too_many_arguments)]
pub(in crate::ops) fn finish(
    frames: &mut Array<f32>,
    before: &Array<f32>,
    volume: &Array<f32>,
    scenes: &Array<f32>,
    moves: &mut Array<Atomic<i64>>,
    n: u32,
    k: u32,
    flags: u32,
    p: usize,
) {
    if p * 4 < before.len() {
        let s = p / n as usize;
        let at = k as usize * before.len() + p * 4;
        let (lo, hi, dt) = (scenes[s * SV + 5], scenes[s * SV + 6], scenes[s * SV + 7]);
        let mut x = frames[at];
        let mut y = frames[at + 1];
        if flags % 2 == 1 {
            x = f32::min(f32::max(x, lo), hi);
            y = f32::min(f32::max(y, lo), hi);
            frames[at] = x;
            frames[at + 1] = y;
        }
        let mut inv_dt = f32::new(0.0);
        if dt > f32::new(0.0) {
            inv_dt = f32::new(1.0) / dt;
        }
        let (dx, dy) = (x - before[p * 4], y - before[p * 4 + 1]);
        frames[at + 2] += dx * inv_dt;
        frames[at + 3] += dy * inv_dt;
        // The material: the liquid's id (`flags / 2`) where the volume is one, else `-(1 + m)`.
        let v = volume[p];
        let mut m = flags / 2;
        if v < f32::new(0.0) {
            m = u32::cast_from(f32::new(-1.0) - v);
        }
        let spacing = scenes[s * SV + SPACING + m as usize];
        if spacing > f32::new(0.0) {
            let d = f32::sqrt(dx * dx + dy * dy) / spacing;
            let slot = s * (SV - SPACING) + m as usize;
            moves[slot].fetch_add(i64::cast_from(d * f32::new(MOVE_UNITS)));
        }
    }
}

/// The moves' sums out of fixed point: `out[i] = moves[i] / MOVE_UNITS`.
#[cube(launch)]
pub(in crate::ops) fn moves_kernel(moves: &Array<i64>, out: &mut Array<f32>) {
    if ABSOLUTE_POS < out.len() {
        out[ABSOLUTE_POS] = f32::cast_from(moves[ABSOLUTE_POS]) / f32::new(MOVE_UNITS);
    }
}

/// Threads of a cube of the call's kernel (one cube a scene): [`reduce`]'s shared memory is
/// sized by it.
pub(in crate::ops) const THREADS: u32 = 256;

/// Scene `s`'s energy step of frame `k` (`energy::restore`), by the cube's threads (`u` of
/// [`THREADS`]; `shared` `[5 THREADS]`): the sums over the scene's liquid particles, in `f64`,
/// of the network's and the projected kinetic energies and the projected velocities; where
/// the projection took energy, the velocities about their mean are scaled by `s = sqrt((spread
/// + restore lost) / spread)`, at most `max_scale`. Every thread of the cube calls it.
#[cube]
#[allow(clippy::too_many_arguments)]
pub(in crate::ops) fn energy(
    frames: &mut Array<f32>,
    before: &Array<f32>,
    volume: &Array<f32>,
    shared: &mut SharedMemory<f64>,
    n: u32,
    k: u32,
    restore: f32,
    max_scale: f32,
    s: usize,
    u: usize,
) {
    energy_sums(frames, before, volume, shared, n, k, s, u);
    let first = s * n as usize;
    let end = first + n as usize;
    let base = k as usize * before.len();
    let count = shared[4];
    let (e_net, e_now) = (shared[0], shared[1]);
    let mut mx = f64::new(0.0);
    let mut my = f64::new(0.0);
    if count > f64::new(0.0) {
        mx = shared[2] / count;
        my = shared[3] / count;
    }
    let spread = e_now - count * (mx * mx + my * my);
    let lost = e_net - e_now;
    let mut floor = e_now;
    if floor < f64::new(1.0) {
        floor = f64::new(1.0);
    }
    let eps = f64::new(2.220446049250313e-16);
    if count >= f64::new(2.0) && lost > f64::new(0.0) && spread > eps * floor {
        let scale = f64::sqrt((spread + f64::cast_from(restore) * lost) / spread);
        let scale = f32::min(f32::cast_from(scale), max_scale);
        let (ux, uy) = (f32::cast_from(mx), f32::cast_from(my));
        let mut p = first + u;
        loop {
            if p >= end {
                break;
            }
            if volume[p] >= f32::new(0.0) {
                let at = base + p * 4;
                frames[at + 2] = ux + scale * (frames[at + 2] - ux);
                frames[at + 3] = uy + scale * (frames[at + 3] - uy);
            }
            p += THREADS as usize;
        }
    }
    // The shared sums are read by every thread before the next frame's reduction.
    sync_cube();
}

/// [`energy`]'s sums over scene `s`'s liquid particles, reduced into `shared[0..5]`: the
/// network's and the projected kinetic energies, the projected velocities' sums, the count.
#[cube]
#[allow(clippy::too_many_arguments)]
fn energy_sums(
    frames: &Array<f32>,
    before: &Array<f32>,
    volume: &Array<f32>,
    shared: &mut SharedMemory<f64>,
    n: u32,
    k: u32,
    s: usize,
    u: usize,
) {
    let first = s * n as usize;
    let end = first + n as usize;
    let base = k as usize * before.len();
    let mut sums = Array::<f64>::new(5usize);
    #[unroll]
    for w in 0..5usize {
        sums[w] = f64::new(0.0);
    }
    let mut p = first + u;
    loop {
        if p >= end {
            break;
        }
        if volume[p] >= f32::new(0.0) {
            let ax = f64::cast_from(before[p * 4 + 2]);
            let ay = f64::cast_from(before[p * 4 + 3]);
            let at = base + p * 4;
            let (bx, by) = (
                f64::cast_from(frames[at + 2]),
                f64::cast_from(frames[at + 3]),
            );
            sums[0] += ax * ax + ay * ay;
            sums[1] += bx * bx + by * by;
            sums[2] += bx;
            sums[3] += by;
            sums[4] += f64::new(1.0);
        }
        p += THREADS as usize;
    }
    reduce(shared, &sums, 5u32, 0u32, u);
}

/// Combines `partial[0..width]` of every thread of the cube (`u` of [`THREADS`]) into
/// `shared[0..width]`: sums where `op` is 0, minima where it is 1 (`shared` `[5 THREADS]`,
/// `width` at most 5). Every thread calls it; the result holds until the next call, whose
/// first barrier lets every thread read it.
#[cube]
pub(in crate::ops) fn reduce(
    shared: &mut SharedMemory<f64>,
    partial: &Array<f64>,
    width: u32,
    op: u32,
    u: usize,
) {
    sync_cube();
    let w = width as usize;
    for i in 0..width {
        shared[u * w + i as usize] = partial[i as usize];
    }
    sync_cube();
    let mut half = (CUBE_DIM / 2) as usize;
    loop {
        if half == 0 {
            break;
        }
        if u < half {
            for i in 0..width {
                let (a, b) = (u * w + i as usize, (u + half) * w + i as usize);
                if op == 0 {
                    shared[a] += shared[b];
                } else {
                    shared[a] = f64::min(shared[a], shared[b]);
                }
            }
        }
        sync_cube();
        half /= 2;
    }
}
