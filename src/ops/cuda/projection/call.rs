//! The projection of one call as one kernel (feature `cuda`): a cube a scene ([`THREADS`]
//! threads over the scene's particles and node slots, `sync_cube` between the steps), the
//! call's K frames in order, each the ropes, contact and shape matching of `cuda/projection/solids.rs`
//! and `cuda/projection/contact.rs`, then the liquid's steps of `cuda/projection/liquid.rs` and
//! `cuda/projection/liquid_solve.rs` (layout there). The sweeps visit only the scene's full nodes, red
//! and black, listed as the right-hand side is made (as the host's stencils list them):
//! sweeps over every node slot cost 3.6x the host's projection (`fluid`, 256 scenes a call,
//! one H100: 0.143 against 0.040 ms a scene-frame beyond `-small-k4`'s network), and as a
//! kernel per step (~90 launches a frame) 3.4x. A colour's nodes read only the other
//! colour's, so the order the list is filled in (atomics) changes no result.

use burn_cubecl::cubecl;
use cubecl::prelude::*;

use super::buffers::Buffers;
use super::contact::{contact, CONTACT_SHARED};
use super::liquid::{begin, node, splat};
use super::liquid_solve::{displace, energy, faces, finish, rhs, sor, THREADS};
use super::momentum::{join_frame, reset, CELL_SLOTS};
use super::momentum_sums::conserve;
use super::rebound::rebound;
use super::solids::{bodies, index, ropes, HEAD, PER_SCENE};

/// Where the momentum part's values start in `solids` (`MOMENTUM_AT`).
const MOMENTUM_AT: usize = crate::ops::MOMENTUM_AT;

/// Values per scene of `scenes` (`ProjectionPlan`'s `SCENE_VALUES`).
const SV: usize = 14;

/// Every frame of the call for scene `CUBE_POS_X`: `count` frames of `n` particles, `nodes`
/// node slots a scene, `iterations` half-sweep pairs, `flags` the walls (bit 0) and the
/// liquid's material id (above), `velocity` 1 where the divergence part is on; then the
/// pressure part's full share, stiffness and over-relaxation, and the energy step's share
/// restored and largest scale; `laws` 1 where the momentum and rebound parts act (the call
/// has its input frames), `rb` the rebound tables' bodies a row.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub(in crate::ops) fn call_kernel(
    b: &mut Buffers,
    laws: u32,
    rb: u32,
    n: u32,
    nodes: u32,
    count: u32,
    iterations: u32,
    flags: u32,
    velocity: u32,
    full: f32,
    stiffness: f32,
    omega: f32,
    restore: f32,
    max_scale: f32,
) {
    let s = CUBE_POS_X as usize;
    let u = UNIT_POS as usize;
    let side = u32::cast_from(b.scenes[s * SV + 1]);
    let solve = side > 0 && iterations > 0;
    let mut shared = SharedMemory::<f64>::new(5 * THREADS as usize);
    let mut listed = SharedMemory::<Atomic<u32>>::new(2usize);
    let mut cs = SharedMemory::<f32>::new(CONTACT_SHARED);
    let mut partial = Array::<f64>::new(5usize);
    let mut cells = SharedMemory::<Atomic<u32>>::new(2 * CELL_SLOTS);
    let mut chunk = SharedMemory::<u32>::new(THREADS as usize);
    for k in 0..count {
        let mut p = s * n as usize + u;
        let end = (s + 1) * n as usize;
        loop {
            if p >= end {
                break;
            }
            begin(&mut b.frames, &b.net, &mut b.before, k, p);
            p += THREADS as usize;
        }
        sync_cube();
        solids(b, &mut shared, &mut cs, &mut partial, n, k, s, u);
        if solve {
            grid_steps(b, &mut listed, n, nodes, k, velocity, full, stiffness, s, u);
            sweeps(b, &mut listed, n, nodes, k, iterations, omega, s, u);
        }
        if laws == 1 {
            fetch_prev(b, n, k, s, u);
            let (c, h, sh) = (&mut cells, &mut chunk, &mut shared);
            momentum_and_rebound(b, rb, &mut cs, c, h, sh, &mut partial, n, k, s, u);
        }
        let mut p = s * n as usize + u;
        loop {
            if p >= end {
                break;
            }
            let (f, bf, vol, sc) = (&mut b.frames, &b.before, &b.volume, &b.scenes);
            finish(f, bf, vol, sc, &mut b.moves, n, k, flags, p);
            p += THREADS as usize;
        }
        sync_cube();
        if solve && restore > f32::new(0.0) {
            let (f, bf, vol) = (&mut b.frames, &b.before, &b.volume);
            energy(f, bf, vol, &mut shared, n, k, restore, max_scale, s, u);
        }
    }
}

/// Frame `k`'s rebound and momentum parts for scene `s` (thread `u`), in
/// `SceneShape::project`'s order (`cuda/projection/rebound.rs`, `cuda/projection/momentum.rs`); `prev` holds the
/// frame before.
#[cube]
#[allow(clippy::too_many_arguments)]
fn momentum_and_rebound(
    b: &mut Buffers,
    rb: u32,
    cs: &mut SharedMemory<f32>,
    cells: &mut SharedMemory<Atomic<u32>>,
    chunk: &mut SharedMemory<u32>,
    shared: &mut SharedMemory<f64>,
    partial: &mut Array<f64>,
    n: u32,
    k: u32,
    s: usize,
    u: usize,
) {
    // Both parts leave a frame without a time step alone, as on the host.
    let dt = b.scenes[s * SV + 7];
    let timed = dt > f32::new(0.0);
    if timed && index(&b.solids, HEAD + PER_SCENE * s + 5) > 0 {
        rebound(b, rb, cs, cells, shared, partial, dt, n, k, s, u);
    }
    let reach = b.solids[MOMENTUM_AT];
    if timed && reach > f32::new(0.0) {
        let (prev_at, at) = (s * n as usize * 4, k as usize * b.before.len());
        reset(b, n, s, u);
        join_frame(b, 0u32, prev_at, cells, chunk, n, reach, s, u);
        join_frame(b, 1u32, at + prev_at, cells, chunk, n, reach, s, u);
        conserve(b, dt, n, k, s, u);
    }
}

/// The frame before frame `k` of scene `s` into `prev`: the call's input for the first
/// frame, else frame `k - 1` as projected.
#[cube]
fn fetch_prev(b: &mut Buffers, n: u32, k: u32, s: usize, u: usize) {
    sync_cube();
    let per = b.before.len();
    let mut i = s * n as usize * 4 + u;
    loop {
        if i >= (s + 1) * n as usize * 4 {
            break;
        }
        if k == 0 {
            b.prev[i] = b.input[i];
        } else {
            b.prev[i] = b.frames[(k as usize - 1) * per + i];
        }
        i += THREADS as usize;
    }
    sync_cube();
}

/// Frame `k`'s ropes, contact and shape matching for scene `s` (thread `u`), in
/// `SceneShape::project`'s order (`cuda/projection/solids.rs`, `cuda/projection/contact.rs`).
#[cube]
#[allow(clippy::too_many_arguments)]
fn solids(
    b: &mut Buffers,
    shared: &mut SharedMemory<f64>,
    cs: &mut SharedMemory<f32>,
    partial: &mut Array<f64>,
    n: u32,
    k: u32,
    s: usize,
    u: usize,
) {
    let base = k as usize * b.before.len() + s * n as usize * 4;
    let row = HEAD + PER_SCENE * s;
    if b.solids[row] < b.solids[row + 1] {
        ropes(&mut b.frames, &b.solids, base, s, u);
        sync_cube();
    }
    if b.solids[row + 2] < b.solids[row + 3] {
        let dt = b.scenes[s * SV + 7];
        contact(
            &mut b.frames,
            &b.solids,
            shared,
            cs,
            partial,
            base,
            dt,
            s,
            u,
        );
        bodies(&mut b.frames, &b.solids, shared, partial, base, s, u);
        sync_cube();
    }
}

/// Frame `k`'s grid for scene `s` (thread `u`): the splat, the nodes, the right-hand side,
/// each full node listed by colour (`listed`: the counts).
#[cube]
#[allow(clippy::too_many_arguments)]
fn grid_steps(
    b: &mut Buffers,
    listed: &mut SharedMemory<Atomic<u32>>,
    n: u32,
    nodes: u32,
    k: u32,
    velocity: u32,
    full: f32,
    stiffness: f32,
    s: usize,
    u: usize,
) {
    if u < 2 {
        let zero = listed[u].load();
        listed[u].fetch_sub(zero);
    }
    let (g0, g1) = (s * nodes as usize, (s + 1) * nodes as usize);
    let mut p = s * n as usize + u;
    loop {
        if p >= (s + 1) * n as usize {
            break;
        }
        splat(
            &mut b.frames,
            &b.volume,
            &b.scenes,
            &mut b.acc,
            n,
            nodes,
            k,
            p,
        );
        p += THREADS as usize;
    }
    sync_cube();
    let mut g = g0 + u;
    loop {
        if g >= g1 {
            break;
        }
        let (acc, grid, kind, q) = (&mut b.acc, &mut b.grid, &mut b.kind, &mut b.q);
        node(acc, grid, kind, q, &b.scenes, nodes, full, g);
        g += THREADS as usize;
    }
    sync_cube();
    let side = u32::cast_from(b.scenes[s * SV + 1]);
    let mut g = g0 + u;
    loop {
        if g >= g1 {
            break;
        }
        let (grid, kind, sc) = (&b.grid, &b.kind, &b.scenes);
        rhs(grid, kind, &mut b.rhs, sc, nodes, stiffness, velocity, g);
        let local = (g - g0) as u32;
        if local < side * side && b.kind[g] == 1u32 {
            let colour = (local / side + local % side) % 2;
            let at = listed[colour as usize].fetch_add(1u32) as usize;
            let mut slot = g0 + at;
            if colour == 1 {
                slot = g1 - 1 - at;
            }
            b.list[slot] = g as u32;
        }
        g += THREADS as usize;
    }
    sync_cube();
}

/// Frame `k`'s solve for scene `s` (thread `u`): the half sweeps over the listed full nodes,
/// the faces and the liquid moved.
#[cube]
#[allow(clippy::too_many_arguments)]
fn sweeps(
    b: &mut Buffers,
    listed: &mut SharedMemory<Atomic<u32>>,
    n: u32,
    nodes: u32,
    k: u32,
    iterations: u32,
    omega: f32,
    s: usize,
    u: usize,
) {
    let (g0, g1) = (s * nodes as usize, (s + 1) * nodes as usize);
    let reds = listed[0].load() as usize;
    let blacks = listed[1].load() as usize;
    for _ in 0..iterations {
        let mut e = u;
        loop {
            if e >= reds {
                break;
            }
            let g = b.list[g0 + e] as usize;
            sor(&b.kind, &b.rhs, &mut b.q, &b.scenes, nodes, omega, 0u32, g);
            e += THREADS as usize;
        }
        sync_cube();
        let mut e = u;
        loop {
            if e >= blacks {
                break;
            }
            let g = b.list[g1 - 1 - e] as usize;
            sor(&b.kind, &b.rhs, &mut b.q, &b.scenes, nodes, omega, 1u32, g);
            e += THREADS as usize;
        }
        sync_cube();
    }
    let mut g = g0 + u;
    loop {
        if g >= g1 {
            break;
        }
        faces(&b.kind, &b.q, &mut b.faces, &b.scenes, nodes, g);
        g += THREADS as usize;
    }
    sync_cube();
    let mut p = s * n as usize + u;
    loop {
        if p >= (s + 1) * n as usize {
            break;
        }
        displace(
            &mut b.frames,
            &b.volume,
            &b.faces,
            &b.scenes,
            n,
            nodes,
            k,
            p,
        );
        p += THREADS as usize;
    }
    sync_cube();
}
