//! The ropes and the bodies' shape matching on the device (feature `cuda`): the device form
//! of `model::constraints`' rope part (`Chain::project`: Kim, Chentanez & Müller 2012, "Long
//! Range Attachments") and shape matching (`Body::project`, elastic bodies: Müller et al.
//! 2005, "Meshless Deformations Based on Shape Matching"), each a `#[cube]` step of the call's
//! kernel (`cuda/projection/call.rs`) for one scene, run before the contact
//! (`cuda/projection/contact.rs`, which sits between the two) and the liquid's steps, in
//! `SceneShape::project`'s order. Layout of `solids`: `ProjectionPlan::solids`' doc; `frames`
//! `[K B N 4]` as in `cuda/projection/liquid.rs`.
//!
//! A chain is one thread's, swept in the host's order (Gauss-Seidel along the chain): the
//! same arithmetic as the host's, pair by pair. A body is the whole cube's: its sums (centre
//! of mass, `A_pq`) are f64 over the cube's threads (`liquid_solve::reduce`), where the
//! host sums in f64 in particle order, so the two agree to f32 rounding.

use burn_cubecl::cubecl;
use cubecl::prelude::*;

use super::liquid_solve::{reduce, THREADS};

/// Values at the head of `solids` (`SOLIDS_HEAD`) and per scene after it (`SCENE_SOLIDS`).
pub(in crate::ops) const HEAD: usize = crate::ops::SOLIDS_HEAD;
pub(in crate::ops) const PER_SCENE: usize = crate::ops::SCENE_SOLIDS;
/// Values per body of the body table (`BODY_VALUES`).
pub(in crate::ops) const BODY: usize = 8;

/// `solids[at]` as an index.
#[cube]
pub(in crate::ops) fn index(solids: &Array<f32>, at: usize) -> usize {
    u32::cast_from(solids[at]) as usize
}

/// Scene `s`'s ropes in its frame starting at `base` of `frames`: each chain by one thread,
/// the head's sweeps from the coarsest long-range level (where on) to the chain's links,
/// every pair stretched past the stretch limit times its rest distance along the chain moved
/// half each along its axis (`Chain::project`).
#[cube]
pub(in crate::ops) fn ropes(
    frames: &mut Array<f32>,
    solids: &Array<f32>,
    base: usize,
    s: usize,
    u: usize,
) {
    let row = HEAD + PER_SCENE * s;
    let (first, end) = (index(solids, row), index(solids, row + 1));
    let chains_at = index(solids, 0);
    let stretch = solids[2];
    let sweeps = u32::cast_from(solids[3]);
    let long_range = index(solids, 4);
    let mut c = first + u;
    loop {
        if c >= end {
            break;
        }
        let e0 = index(solids, chains_at + 2 * c);
        let len = index(solids, chains_at + 2 * c + 1);
        // floor(log2(len - 1)): the coarsest level whose pairs fit.
        let mut top = 0u32;
        if long_range == 1 {
            let mut m = u32::cast_from(len) - 1;
            loop {
                if m <= 1 {
                    break;
                }
                m /= 2;
                top += 1;
            }
        }
        for _ in 0..sweeps {
            let mut level = top + 1;
            loop {
                if level == 0 {
                    break;
                }
                level -= 1;
                let mut step = 1usize;
                for _ in 0..level {
                    step *= 2;
                }
                chain_level(frames, solids, e0, len, step, stretch, base);
            }
        }
        c += THREADS as usize;
    }
}

/// One level of a chain's sweep: pairs `a, a + step` in order (`Chain::project`).
#[cube]
fn chain_level(
    frames: &mut Array<f32>,
    solids: &Array<f32>,
    e0: usize,
    len: usize,
    step: usize,
    stretch: f32,
    base: usize,
) {
    if len > step {
        for a in 0..len - step {
            let b = a + step;
            let limit = stretch * (solids[e0 + 2 * b + 1] - solids[e0 + 2 * a + 1]);
            let i = base + 4 * index(solids, e0 + 2 * a);
            let j = base + 4 * index(solids, e0 + 2 * b);
            let dx = frames[j] - frames[i];
            let dy = frames[j + 1] - frames[i + 1];
            let d = f32::hypot(dx, dy);
            if d > limit && d > f32::new(0.0) {
                let f = f32::new(0.5) * (d - limit) / d;
                frames[i] += f * dx;
                frames[i + 1] += f * dy;
                frames[j] -= f * dx;
                frames[j + 1] -= f * dy;
            }
        }
    }
}

/// Scene `s`'s shape-matched bodies in frame `k`, one after another by the whole cube
/// (`Body::project`, elastic): the centre of mass and `A_pq` summed in f64, the rotation of
/// `A_pq`'s polar decomposition blended with the volume-preserving linear fit by the body's
/// linear share, each particle moved its stiffness of the way to its goal.
#[cube]
#[allow(clippy::too_many_arguments)]
pub(in crate::ops) fn bodies(
    frames: &mut Array<f32>,
    solids: &Array<f32>,
    shared: &mut SharedMemory<f64>,
    partial: &mut Array<f64>,
    base: usize,
    s: usize,
    u: usize,
) {
    let row = HEAD + PER_SCENE * s;
    let (first, end) = (index(solids, row + 2), index(solids, row + 3));
    let bodies_at = index(solids, 1);
    for body in first..end {
        let at = bodies_at + BODY * body;
        let (e0, len) = (index(solids, at), index(solids, at + 1));
        let (cx, cy) = centre(frames, solids, shared, partial, e0, len, 3, base, u);
        for i in 0..4usize {
            partial[i] = f64::new(0.0);
        }
        let mut e = u;
        loop {
            if e >= len {
                break;
            }
            let p = base + 4 * index(solids, e0 + 3 * e);
            let dx = f64::cast_from(frames[p] - cx);
            let dy = f64::cast_from(frames[p + 1] - cy);
            let qx = f64::cast_from(solids[e0 + 3 * e + 1]);
            let qy = f64::cast_from(solids[e0 + 3 * e + 2]);
            partial[0] += dx * qx;
            partial[1] += dx * qy;
            partial[2] += dy * qx;
            partial[3] += dy * qy;
            e += THREADS as usize;
        }
        reduce(shared, partial, 4u32, 0u32, u);
        let mut goal = Array::<f32>::new(4usize);
        goal_matrix(solids, shared, at, &mut goal);
        let stiffness = solids[at + 2];
        let mut e = u;
        loop {
            if e >= len {
                break;
            }
            let p = base + 4 * index(solids, e0 + 3 * e);
            let (qx, qy) = (solids[e0 + 3 * e + 1], solids[e0 + 3 * e + 2]);
            let gx = goal[0] * qx + goal[1] * qy + cx;
            let gy = goal[2] * qx + goal[3] * qy + cy;
            frames[p] += stiffness * (gx - frames[p]);
            frames[p + 1] += stiffness * (gy - frames[p + 1]);
            e += THREADS as usize;
        }
    }
}

/// The centre of mass (f32 of the f64 mean) of the `len` particles listed from `e0`, every
/// `stride` values, of `solids` (`base` the scene's first value of the frame); every thread
/// of the cube calls it.
#[cube]
#[allow(clippy::too_many_arguments)]
pub(in crate::ops) fn centre(
    frames: &Array<f32>,
    solids: &Array<f32>,
    shared: &mut SharedMemory<f64>,
    partial: &mut Array<f64>,
    e0: usize,
    len: usize,
    stride: usize,
    base: usize,
    u: usize,
) -> (f32, f32) {
    partial[0] = f64::new(0.0);
    partial[1] = f64::new(0.0);
    let mut e = u;
    loop {
        if e >= len {
            break;
        }
        let p = base + 4 * index(solids, e0 + stride * e);
        partial[0] += f64::cast_from(frames[p]);
        partial[1] += f64::cast_from(frames[p + 1]);
        e += THREADS as usize;
    }
    reduce(shared, partial, 2u32, 0u32, u);
    let count = f64::cast_from(u32::cast_from(len));
    (
        f32::cast_from(shared[0] / count),
        f32::cast_from(shared[1] / count),
    )
}

/// The goal's matrix (row-major, into `goal[0..4]`) of the body whose table row starts at
/// `at`, from `A_pq` in `shared[0..4]`: the rotation of its polar decomposition, blended with
/// `A_pq A_qq^-1 / sqrt(det)` by the linear share where that is above 0 and the determinant
/// above 1e-12.
#[cube]
fn goal_matrix(solids: &Array<f32>, shared: &SharedMemory<f64>, at: usize, goal: &mut Array<f32>) {
    let theta = f64::atan2(shared[2] - shared[1], shared[0] + shared[3]);
    let sn = f32::cast_from(f64::sin(theta));
    let co = f32::cast_from(f64::cos(theta));
    goal[0] = co;
    goal[1] = f32::new(0.0) - sn;
    goal[2] = sn;
    goal[3] = co;
    let linear = solids[at + 3];
    if linear > f32::new(0.0) {
        let a0 = f32::cast_from(shared[0]);
        let a1 = f32::cast_from(shared[1]);
        let a2 = f32::cast_from(shared[2]);
        let a3 = f32::cast_from(shared[3]);
        let (q0, q1, q2, q3) = (
            solids[at + 4],
            solids[at + 5],
            solids[at + 6],
            solids[at + 7],
        );
        let m0 = a0 * q0 + a1 * q2;
        let m1 = a0 * q1 + a1 * q3;
        let m2 = a2 * q0 + a3 * q2;
        let m3 = a2 * q1 + a3 * q3;
        let det = m0 * m3 - m1 * m2;
        if det > f32::new(1e-12) {
            let f = f32::new(1.0) / f32::sqrt(det);
            let rest = f32::new(1.0) - linear;
            goal[0] = linear * m0 * f + rest * co;
            goal[1] = linear * m1 * f - rest * sn;
            goal[2] = linear * m2 * f + rest * sn;
            goal[3] = linear * m3 * f + rest * co;
        }
    }
}
