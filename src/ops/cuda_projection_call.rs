//! The projection of one call as one kernel (feature `cuda`): a cube a scene ([`THREADS`]
//! threads over the scene's particles and node slots, `sync_cube` between the steps), the
//! call's K frames in order, each the ropes, contact and shape matching of `cuda_solids.rs`
//! and `cuda_contact.rs`, then the liquid's steps of `cuda_liquid.rs` and
//! `cuda_liquid_solve.rs` (layout there). The sweeps visit only the scene's full nodes, red
//! and black, listed as the right-hand side is made (as the host's stencils list them):
//! sweeps over every node slot cost 3.6x the host's projection (`fluid`, 256 scenes a call,
//! one H100: 0.143 against 0.040 ms a scene-frame beyond `-small-k4`'s network), and as a
//! kernel per step (~90 launches a frame) 3.4x. A colour's nodes read only the other
//! colour's, so the order the list is filled in (atomics) changes no result.

use burn_cubecl::cubecl;
use cubecl::prelude::*;

use super::cuda_contact::{contact, CONTACT_SHARED};
use super::cuda_liquid::{begin, node, splat};
use super::cuda_liquid_solve::{displace, energy, faces, finish, rhs, sor, THREADS};
use super::cuda_solids::{bodies, ropes, HEAD, PER_SCENE};

/// Values per scene of `scenes` (`ProjectionPlan`'s `SCENE_VALUES`).
const SV: usize = 14;

/// The call's arrays (`cuda_liquid.rs`'s layout; `list` `[B nodes]`: each scene's full
/// nodes, red from the front, black from the back).
#[derive(CubeLaunch, CubeType)]
pub(super) struct Buffers {
    pub frames: Array<f32>,
    pub net: Array<f32>,
    pub before: Array<f32>,
    pub volume: Array<f32>,
    pub scenes: Array<f32>,
    pub acc: Array<Atomic<i64>>,
    pub grid: Array<f32>,
    pub kind: Array<u32>,
    pub q: Array<f32>,
    pub rhs: Array<f32>,
    pub faces: Array<f32>,
    pub moves: Array<Atomic<i64>>,
    pub list: Array<u32>,
    pub solids: Array<f32>,
}

/// Every frame of the call for scene `CUBE_POS_X`: `count` frames of `n` particles, `nodes`
/// node slots a scene, `iterations` half-sweep pairs, `flags` the walls (bit 0) and the
/// liquid's material id (above), `velocity` 1 where the divergence part is on; then the
/// pressure part's full share, stiffness and over-relaxation, and the energy step's share
/// restored and largest scale.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub(super) fn call_kernel(
    b: &mut Buffers,
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

/// Frame `k`'s ropes, contact and shape matching for scene `s` (thread `u`), in
/// `SceneShape::project`'s order (`cuda_solids.rs`, `cuda_contact.rs`).
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
