//! Contact between shape-matched bodies on the device (feature `cuda`): the device form of
//! `model::constraints`' contact part (`Contact::separate`; Müller et al. 2007, section 3.5)
//! for one scene, by the whole cube of the call's kernel (`cuda/projection/call.rs`), between
//! the ropes and the shape matching (`cuda/projection/solids.rs`; `solids`: `ProjectionPlan::solids`).
//!
//! Each pass finds the pairs of bodies whose particles come closer than the contact distance:
//! the close particle pairs' mean direction (f64 sums over the cube's threads, where the host
//! sums in f32 in particle order) or the line between the centres as the normal, the
//! separating-axis depth along it, then one thread shares each pair's push between its two
//! bodies in the host's pair order and every body moves rigidly. Particles farther than the
//! contact distance from the other body's box are not visited (they cannot touch it): the
//! pairs found are the host's cell list's. The pairs' first normals and the bodies' pushes
//! then set the velocities (restitution above the resting speed). Per-scene scratch lives in
//! `cs` (shared, [`CONTACT_SHARED`] values): [`PER_BODY`] values a body (push, total push,
//! box or mean velocity and velocity change) and [`PER_PAIR`] a pair `(a, b)` at `a
//! MAX_BODIES + b` (this pass's normal and depth, pushed, the first normal, seen).

use burn_cubecl::cubecl;
use cubecl::prelude::*;

use super::liquid_solve::{reduce, THREADS};
use super::solids::{centre, index, BODY, HEAD, PER_SCENE};

/// `MAX_BODIES` (`projection_plan.rs`).
const MAXB: usize = 16;
/// Values of `cs` per body and per pair, where the pairs start, and its size.
const PER_BODY: usize = 8;
const PER_PAIR: usize = 7;
const PAIRS: usize = MAXB * PER_BODY;
pub(in crate::ops) const CONTACT_SHARED: usize = PAIRS + MAXB * MAXB * PER_PAIR;

/// Scene `s`'s contact in its frame starting at `base` of `frames` (time step `dt`): the head's
/// passes of pushes, then the velocities (`Contact::separate`). Every thread calls it.
#[cube]
#[allow(clippy::too_many_arguments)]
pub(in crate::ops) fn contact(
    frames: &mut Array<f32>,
    solids: &Array<f32>,
    shared: &mut SharedMemory<f64>,
    cs: &mut SharedMemory<f32>,
    partial: &mut Array<f64>,
    base: usize,
    dt: f32,
    s: usize,
    u: usize,
) {
    let row = HEAD + PER_SCENE * s;
    let (first, end) = (index(solids, row + 2), index(solids, row + 3));
    let d = solids[row + 4];
    if d > f32::new(0.0) && end >= first + 2 {
        let nb = end - first;
        if u < MAXB * MAXB {
            cs[PAIRS + u * PER_PAIR + 6] = f32::new(0.0);
        }
        if u < MAXB {
            cs[u * PER_BODY + 2] = f32::new(0.0);
            cs[u * PER_BODY + 3] = f32::new(0.0);
        }
        sync_cube();
        let mut passes = index(solids, 5);
        if passes < 1 {
            passes = 1;
        }
        let mut pass = 0usize;
        loop {
            if pass >= passes {
                break;
            }
            pass += 1;
            boxes(frames, solids, shared, cs, partial, base, first, nb, u);
            let pushes = overlaps(frames, solids, shared, cs, partial, base, first, nb, d, u);
            sync_cube();
            if pushes == 0u32 {
                break;
            }
            push(frames, solids, cs, base, first, nb, u);
        }
        if dt > f32::new(0.0) {
            velocities(frames, solids, shared, cs, partial, base, first, nb, dt, u);
        }
    }
}

/// Each body's box (min x, min y, max x, max y) into its `cs` slot.
#[cube]
#[allow(clippy::too_many_arguments)]
fn boxes(
    frames: &Array<f32>,
    solids: &Array<f32>,
    shared: &mut SharedMemory<f64>,
    cs: &mut SharedMemory<f32>,
    partial: &mut Array<f64>,
    base: usize,
    first: usize,
    nb: usize,
    u: usize,
) {
    let bodies_at = index(solids, 1);
    for b in 0..nb {
        let at = bodies_at + BODY * (first + b);
        let (e0, len) = (index(solids, at), index(solids, at + 1));
        for i in 0..4usize {
            partial[i] = f64::new(1e30);
        }
        let mut e = u;
        loop {
            if e >= len {
                break;
            }
            let p = base + 4 * index(solids, e0 + 3 * e);
            let (x, y) = (f64::cast_from(frames[p]), f64::cast_from(frames[p + 1]));
            partial[0] = f64::min(partial[0], x);
            partial[1] = f64::min(partial[1], y);
            partial[2] = f64::min(partial[2], f64::new(0.0) - x);
            partial[3] = f64::min(partial[3], f64::new(0.0) - y);
            e += THREADS as usize;
        }
        reduce(shared, partial, 4u32, 1u32, u);
        if u == 0 {
            cs[b * PER_BODY + 4] = f32::cast_from(shared[0]);
            cs[b * PER_BODY + 5] = f32::cast_from(shared[1]);
            cs[b * PER_BODY + 6] = f32::cast_from(f64::new(0.0) - shared[2]);
            cs[b * PER_BODY + 7] = f32::cast_from(f64::new(0.0) - shared[3]);
        }
    }
    sync_cube();
}

/// This pass's pushes: for each pair of bodies in order whose boxes come within `d`, the
/// normal and the depth (`Contact::overlaps`) into the pair's slot, marked pushed (and its
/// first normal kept); returns how many pairs push (the same on every thread).
#[cube]
#[allow(clippy::too_many_arguments)]
fn overlaps(
    frames: &Array<f32>,
    solids: &Array<f32>,
    shared: &mut SharedMemory<f64>,
    cs: &mut SharedMemory<f32>,
    partial: &mut Array<f64>,
    base: usize,
    first: usize,
    nb: usize,
    d: f32,
    u: usize,
) -> u32 {
    let bodies_at = index(solids, 1);
    let mut pushes = 0u32;
    for a in 0..nb {
        for b in a + 1..nb {
            let slot = PAIRS + (a * MAXB + b) * PER_PAIR;
            if u == 0 {
                cs[slot + 3] = f32::new(0.0);
            }
            let (ba, bb) = (a * PER_BODY + 4, b * PER_BODY + 4);
            let near = cs[ba] - d <= cs[bb + 2]
                && cs[bb] - d <= cs[ba + 2]
                && cs[ba + 1] - d <= cs[bb + 3]
                && cs[bb + 1] - d <= cs[ba + 3];
            if near {
                let at_a = bodies_at + BODY * (first + a);
                let at_b = bodies_at + BODY * (first + b);
                close_sums(
                    frames, solids, shared, cs, partial, base, at_a, at_b, bb, d, u,
                );
                let count = shared[2];
                if count > f64::new(0.0) {
                    let (nx, ny, ok) =
                        normal(frames, solids, shared, partial, base, at_a, at_b, count, u);
                    if ok {
                        let dep = depth(
                            frames, solids, shared, partial, base, at_a, at_b, nx, ny, d, u,
                        );
                        if dep > f32::new(0.0) {
                            if u == 0 {
                                cs[slot] = nx;
                                cs[slot + 1] = ny;
                                cs[slot + 2] = dep;
                                cs[slot + 3] = f32::new(1.0);
                                if cs[slot + 6] < f32::new(0.5) {
                                    cs[slot + 4] = nx;
                                    cs[slot + 5] = ny;
                                    cs[slot + 6] = f32::new(1.0);
                                }
                            }
                            pushes += 1u32;
                        }
                    }
                }
            }
        }
    }
    pushes
}

/// The close particle pairs of bodies `at_a` and `at_b` (table rows; `bb` where b's box is
/// in `cs`): the sums of their unit directions from b's particle to a's and their count, into
/// `shared[0..3]`.
#[cube]
#[allow(clippy::too_many_arguments)]
fn close_sums(
    frames: &Array<f32>,
    solids: &Array<f32>,
    shared: &mut SharedMemory<f64>,
    cs: &SharedMemory<f32>,
    partial: &mut Array<f64>,
    base: usize,
    at_a: usize,
    at_b: usize,
    bb: usize,
    d: f32,
    u: usize,
) {
    let (e0a, lena) = (index(solids, at_a), index(solids, at_a + 1));
    let (e0b, lenb) = (index(solids, at_b), index(solids, at_b + 1));
    let (x0, y0) = (cs[bb] - d, cs[bb + 1] - d);
    let (x1, y1) = (cs[bb + 2] + d, cs[bb + 3] + d);
    for i in 0..3usize {
        partial[i] = f64::new(0.0);
    }
    let mut e = u;
    loop {
        if e >= lena {
            break;
        }
        let p = base + 4 * index(solids, e0a + 3 * e);
        let (x, y) = (frames[p], frames[p + 1]);
        if x >= x0 && x <= x1 && y >= y0 && y <= y1 {
            for j in 0..lenb {
                let q = base + 4 * index(solids, e0b + 3 * j);
                let (dx, dy) = (x - frames[q], y - frames[q + 1]);
                let r = f32::hypot(dx, dy);
                if r < d && r > f32::new(0.0) {
                    partial[0] += f64::cast_from(dx / r);
                    partial[1] += f64::cast_from(dy / r);
                    partial[2] += f64::new(1.0);
                }
            }
        }
        e += THREADS as usize;
    }
    reduce(shared, partial, 3u32, 0u32, u);
}

/// The contact normal from b towards a: the close pairs' mean direction (sums in
/// `shared[0..2]`, `count` of them) where its length is at least 0.3, else the line between
/// the centres of mass; not `ok` where the centres coincide.
#[cube]
#[allow(clippy::too_many_arguments)]
fn normal(
    frames: &Array<f32>,
    solids: &Array<f32>,
    shared: &mut SharedMemory<f64>,
    partial: &mut Array<f64>,
    base: usize,
    at_a: usize,
    at_b: usize,
    count: f64,
    u: usize,
) -> (f32, f32, bool) {
    let c = f32::cast_from(count);
    let mx = f32::cast_from(shared[0]) / c;
    let my = f32::cast_from(shared[1]) / c;
    let len = f32::hypot(mx, my);
    let mut nx = mx;
    let mut ny = my;
    let mut ok = true;
    if len >= f32::new(0.3) {
        nx = mx / len;
        ny = my / len;
    } else {
        let (e0a, lena) = (index(solids, at_a), index(solids, at_a + 1));
        let (e0b, lenb) = (index(solids, at_b), index(solids, at_b + 1));
        let (ax, ay) = centre(frames, solids, shared, partial, e0a, lena, 3, base, u);
        let (bx, by) = centre(frames, solids, shared, partial, e0b, lenb, 3, base, u);
        let (dx, dy) = (ax - bx, ay - by);
        let l = f32::hypot(dx, dy);
        if l > f32::new(0.0) {
            nx = dx / l;
            ny = dy / l;
        } else {
            ok = false;
        }
    }
    (nx, ny, ok)
}

/// The separating-axis depth along `(nx, ny)`: `d + max_b(x . n) - min_a(x . n)`.
#[cube]
#[allow(clippy::too_many_arguments)]
fn depth(
    frames: &Array<f32>,
    solids: &Array<f32>,
    shared: &mut SharedMemory<f64>,
    partial: &mut Array<f64>,
    base: usize,
    at_a: usize,
    at_b: usize,
    nx: f32,
    ny: f32,
    d: f32,
    u: usize,
) -> f32 {
    partial[0] = f64::new(1e30);
    partial[1] = f64::new(1e30);
    for side in 0..2usize {
        let at = at_a + side * (at_b - at_a);
        let (e0, len) = (index(solids, at), index(solids, at + 1));
        let mut e = u;
        loop {
            if e >= len {
                break;
            }
            let p = base + 4 * index(solids, e0 + 3 * e);
            let along = f64::cast_from(frames[p] * nx + frames[p + 1] * ny);
            if side == 0 {
                partial[0] = f64::min(partial[0], along);
            } else {
                partial[1] = f64::min(partial[1], f64::new(0.0) - along);
            }
            e += THREADS as usize;
        }
    }
    reduce(shared, partial, 2u32, 1u32, u);
    let low_a = f32::cast_from(shared[0]);
    let high_b = f32::cast_from(f64::new(0.0) - shared[1]);
    d + high_b - low_a
}

/// This pass's pushes shared between each pushed pair's bodies in the host's pair order
/// (inversely to their particle counts), added to the totals, and every body moved by its own.
#[cube]
#[allow(clippy::too_many_arguments)]
fn push(
    frames: &mut Array<f32>,
    solids: &Array<f32>,
    cs: &mut SharedMemory<f32>,
    base: usize,
    first: usize,
    nb: usize,
    u: usize,
) {
    let bodies_at = index(solids, 1);
    if u == 0 {
        for b in 0..nb {
            cs[b * PER_BODY] = f32::new(0.0);
            cs[b * PER_BODY + 1] = f32::new(0.0);
        }
        for a in 0..nb {
            for b in a + 1..nb {
                let slot = PAIRS + (a * MAXB + b) * PER_PAIR;
                if cs[slot + 3] > f32::new(0.5) {
                    let na = solids[bodies_at + BODY * (first + a) + 1];
                    let nb2 = solids[bodies_at + BODY * (first + b) + 1];
                    let (wa, wb) = (nb2 / (na + nb2), na / (na + nb2));
                    let (nx, ny, depth) = (cs[slot], cs[slot + 1], cs[slot + 2]);
                    cs[a * PER_BODY] += nx * depth * wa;
                    cs[a * PER_BODY + 1] += ny * depth * wa;
                    cs[b * PER_BODY] -= nx * depth * wb;
                    cs[b * PER_BODY + 1] -= ny * depth * wb;
                }
            }
        }
        for b in 0..nb {
            cs[b * PER_BODY + 2] += cs[b * PER_BODY];
            cs[b * PER_BODY + 3] += cs[b * PER_BODY + 1];
        }
    }
    sync_cube();
    add_to_bodies(frames, solids, cs, base, first, nb, 0usize, u);
}

/// Adds each body's `cs` words `word, word + 1` to columns `column, column + 1` of its
/// particles' rows (`column` 0: positions, 2: velocities; `word` = `column`'s push or
/// velocity change slot).
#[cube]
#[allow(clippy::too_many_arguments)]
fn add_to_bodies(
    frames: &mut Array<f32>,
    solids: &Array<f32>,
    cs: &SharedMemory<f32>,
    base: usize,
    first: usize,
    nb: usize,
    column: usize,
    u: usize,
) {
    let bodies_at = index(solids, 1);
    let word = column * 3;
    for b in 0..nb {
        let at = bodies_at + BODY * (first + b);
        let (e0, len) = (index(solids, at), index(solids, at + 1));
        let (sx, sy) = (cs[b * PER_BODY + word], cs[b * PER_BODY + word + 1]);
        let mut e = u;
        loop {
            if e >= len {
                break;
            }
            let p = base + 4 * index(solids, e0 + 3 * e) + column;
            frames[p] += sx;
            frames[p + 1] += sy;
            e += THREADS as usize;
        }
    }
    sync_cube();
}

/// The velocities after the passes (`Contact::separate`): where any pair pushed, each body's
/// push taken back over `dt`, and each pushed pair closing along its first normal given
/// `restitution` times its closing speed (a stop below the resting speed) by an impulse
/// shared by the bodies' particle counts.
#[cube]
#[allow(clippy::too_many_arguments)]
fn velocities(
    frames: &mut Array<f32>,
    solids: &Array<f32>,
    shared: &mut SharedMemory<f64>,
    cs: &mut SharedMemory<f32>,
    partial: &mut Array<f64>,
    base: usize,
    first: usize,
    nb: usize,
    dt: f32,
    u: usize,
) {
    let bodies_at = index(solids, 1);
    let mut seen: u32 = 0u32;
    for a in 0..nb {
        for b in a + 1..nb {
            if cs[PAIRS + (a * MAXB + b) * PER_PAIR + 6] > f32::new(0.5) {
                seen += 1u32;
            }
        }
    }
    if seen > 0u32 {
        for b in 0..nb {
            let at = bodies_at + BODY * (first + b);
            let (e0, len) = (index(solids, at), index(solids, at + 1));
            partial[0] = f64::new(0.0);
            partial[1] = f64::new(0.0);
            let mut e = u;
            loop {
                if e >= len {
                    break;
                }
                let p = base + 4 * index(solids, e0 + 3 * e);
                partial[0] += f64::cast_from(frames[p + 2]);
                partial[1] += f64::cast_from(frames[p + 3]);
                e += THREADS as usize;
            }
            reduce(shared, partial, 2u32, 0u32, u);
            if u == 0 {
                let size = solids[at + 1];
                cs[b * PER_BODY + 4] = f32::cast_from(shared[0]) / size;
                cs[b * PER_BODY + 5] = f32::cast_from(shared[1]) / size;
            }
        }
        sync_cube();
        if u == 0 {
            impulses(solids, cs, first, nb, dt);
        }
        sync_cube();
        add_to_bodies(frames, solids, cs, base, first, nb, 2usize, u);
    }
}

/// One thread's velocity changes (`cs` words 6 and 7 of each body): the pushes over `dt`
/// taken back, then each seen pair's impulse in the host's pair order.
#[cube]
fn impulses(solids: &Array<f32>, cs: &mut SharedMemory<f32>, first: usize, nb: usize, dt: f32) {
    let bodies_at = index(solids, 1);
    let (restitution, resting) = (solids[6], solids[7]);
    for b in 0..nb {
        cs[b * PER_BODY + 6] = (f32::new(0.0) - cs[b * PER_BODY + 2]) / dt;
        cs[b * PER_BODY + 7] = (f32::new(0.0) - cs[b * PER_BODY + 3]) / dt;
    }
    for a in 0..nb {
        for b in a + 1..nb {
            let slot = PAIRS + (a * MAXB + b) * PER_PAIR;
            if cs[slot + 6] > f32::new(0.5) {
                let ma = solids[bodies_at + BODY * (first + a) + 1];
                let mb = solids[bodies_at + BODY * (first + b) + 1];
                let (nx, ny) = (cs[slot + 4], cs[slot + 5]);
                let (va, vb) = (a * PER_BODY + 4, b * PER_BODY + 4);
                let rel = (cs[va] - cs[vb]) * nx + (cs[va + 1] - cs[vb + 1]) * ny;
                if rel < f32::new(0.0) {
                    let mut target = f32::new(0.0);
                    if f32::new(0.0) - rel > resting {
                        target = f32::new(0.0) - restitution * rel;
                    }
                    let j = (target - rel) / (f32::new(1.0) / ma + f32::new(1.0) / mb);
                    cs[a * PER_BODY + 6] += j / ma * nx;
                    cs[a * PER_BODY + 7] += j / ma * ny;
                    cs[b * PER_BODY + 6] -= j / mb * nx;
                    cs[b * PER_BODY + 7] -= j / mb * ny;
                }
            }
        }
    }
}
