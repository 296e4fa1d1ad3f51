//! The rebound part on the device (feature `cuda`): the device form of
//! `model::constraints::rebound::Rebound::apply` for one scene, a step of the call's kernel
//! (`cuda/projection/call.rs`) after the liquid's steps and before the momentum part. Its
//! bodies are the scene's first shape-matched ones (jelly), read from the body table of
//! `solids`. The whole cube sums each body's means and bounds in f64 (`reduce`, the host sums
//! in particle order: the same to f32 rounding) and finds the nearest particles of each pair
//! of bodies within reach in both frames (only particles within reach of the other body's
//! box look: the host's cell list finds the same pairs and distances); then one thread walks
//! the contacts in the host's order (walls per body and side, the pairs that ended, the pairs
//! near) with the scene's table of contacts in progress (`events`, the layout of
//! `ProjectionPlan::events`), and every body is moved by the speed it lacks times `dt`.
//! Velocity-level restitution with per-contact state is Müller et al. 2020, "Detailed Rigid
//! Body Simulation with Extended Position Based Dynamics", section 3.6.
//!
//! Scratch: `b.prev` the frame before, `st` (shared f32) [`STATS`] values a body, then 2 a
//! body of speed to add; `gaps` (shared atomics) the pairs' nearest distances (f32 bits),
//! frame then before.

use burn_cubecl::cubecl;
use cubecl::prelude::*;

use super::buffers::Buffers;
use super::liquid_solve::{reduce, THREADS};
use super::solids::{index, BODY, HEAD, PER_SCENE};

/// `MAX_BODIES` (`projection_plan.rs`).
const MAXB: usize = crate::ops::MAX_BODIES;
/// Values of `st` a body: centre before (2), centre now (2), mean velocity before (2), mean
/// velocity the frame ends with (2), lowest then highest coordinates now (4), before (4).
const STATS: usize = 16;
/// Where the speeds to add start in `st`.
const ADD: usize = MAXB * STATS;
/// Where the part's values start in `solids` (`REBOUND_AT`).
const LAW: usize = crate::ops::REBOUND_AT;
/// Values a contact of the table (`EVENT_VALUES`).
const EV: usize = crate::ops::EVENT_VALUES;
/// f32::INFINITY's bits.
const FAR: i64 = 2139095040;

/// Scene `s`'s rebound in frame `k` (module doc; `rb` the table's bodies a row). Every
/// thread calls it.
#[cube]
#[allow(clippy::too_many_arguments)]
pub(in crate::ops) fn rebound(
    b: &mut Buffers,
    rb: u32,
    st: &mut SharedMemory<f32>,
    gaps: &mut SharedMemory<Atomic<u32>>,
    shared: &mut SharedMemory<f64>,
    partial: &mut Array<f64>,
    dt: f32,
    n: u32,
    k: u32,
    s: usize,
    u: usize,
) {
    let row = HEAD + PER_SCENE * s;
    let r = index(&b.solids, row + 5);
    let b0 = index(&b.solids, row + 2);
    let prev_at = s * n as usize * 4;
    let at = k as usize * b.before.len() + prev_at;
    for a in 0..r {
        stats(b, st, shared, partial, b0 + a, a, prev_at, at, dt, u);
    }
    nearest(b, st, gaps, r, b0, prev_at, at, u);
    if u == 0 {
        for i in 0..2 * r {
            st[ADD + i] = f32::new(0.0);
        }
        walls(b, rb, st, r, dt, s);
        pairs(b, rb, st, gaps, r, b0, s);
    }
    sync_cube();
    let bodies_at = index(&b.solids, 1);
    for a in 0..r {
        let row = bodies_at + BODY * (b0 + a);
        let (e0, len) = (index(&b.solids, row), index(&b.solids, row + 1));
        let (mx, my) = (st[ADD + 2 * a] * dt, st[ADD + 2 * a + 1] * dt);
        let mut e = u;
        loop {
            if e >= len {
                break;
            }
            let p = at + 4 * index(&b.solids, e0 + 3 * e);
            b.frames[p] += mx;
            b.frames[p + 1] += my;
            e += THREADS as usize;
        }
    }
    sync_cube();
}

/// Body `body`'s [`STATS`] into `st` at its rebound index `a`, the frame before's scene rows
/// from `prev_at` (and `before`'s), the predicted frame's from `at`.
#[cube]
#[allow(clippy::too_many_arguments)]
fn stats(
    b: &Buffers,
    st: &mut SharedMemory<f32>,
    shared: &mut SharedMemory<f64>,
    partial: &mut Array<f64>,
    body: usize,
    a: usize,
    prev_at: usize,
    at: usize,
    dt: f32,
    u: usize,
) {
    let row = index(&b.solids, 1) + BODY * body;
    let (e0, len) = (index(&b.solids, row), index(&b.solids, row + 1));
    let m = f64::cast_from(u32::cast_from(len));
    for pass in 0..4u32 {
        for w in 0..4usize {
            partial[w] = f64::new(0.0);
            if pass >= 2 {
                partial[w] = f64::new(1e30);
            }
        }
        let mut e = u;
        loop {
            if e >= len {
                break;
            }
            let i = 4 * index(&b.solids, e0 + 3 * e);
            let (p, f) = (prev_at + i, at + i);
            for c in 0..2usize {
                let (xp, x) = (b.prev[p + c], b.frames[f + c]);
                if pass == 0 {
                    partial[c] += f64::cast_from(xp);
                    partial[2 + c] += f64::cast_from(x);
                } else if pass == 1 {
                    partial[c] += f64::cast_from(b.prev[p + 2 + c]);
                    let v = b.frames[f + 2 + c] + (x - b.before[p + c]) / dt;
                    partial[2 + c] += f64::cast_from(v);
                } else if pass == 2 {
                    partial[c] = f64::min(partial[c], f64::cast_from(x));
                    partial[2 + c] = f64::min(partial[2 + c], f64::cast_from(xp));
                } else {
                    partial[c] = f64::min(partial[c], f64::cast_from(-x));
                    partial[2 + c] = f64::min(partial[2 + c], f64::cast_from(-xp));
                }
            }
            e += THREADS as usize;
        }
        reduce(shared, partial, 4u32, pass / 2, u);
        if u == 0 {
            let o = a * STATS;
            for c in 0..2usize {
                if pass < 2 {
                    st[o + 4 * pass as usize + c] = f32::cast_from(shared[c] / m);
                    st[o + 4 * pass as usize + 2 + c] = f32::cast_from(shared[2 + c] / m);
                } else if pass == 2 {
                    st[o + 8 + c] = f32::cast_from(shared[c]);
                    st[o + 12 + c] = f32::cast_from(shared[2 + c]);
                } else {
                    st[o + 10 + c] = f32::cast_from(-shared[c]);
                    st[o + 14 + c] = f32::cast_from(-shared[2 + c]);
                }
            }
        }
    }
    sync_cube();
}

/// The nearest distance of each pair of rebound bodies within the part's reach, in the
/// predicted frame (`gaps[a MAXB + b]`, `a < b`) and the one before (`+ MAXB^2`); `FAR`
/// where none is.
#[cube]
#[allow(clippy::too_many_arguments)]
fn nearest(
    b: &Buffers,
    st: &SharedMemory<f32>,
    gaps: &mut SharedMemory<Atomic<u32>>,
    r: usize,
    b0: usize,
    prev_at: usize,
    at: usize,
    u: usize,
) {
    let mut t = u;
    loop {
        if t >= 2 * MAXB * MAXB {
            break;
        }
        gaps[t].store(u32::new(FAR));
        t += THREADS as usize;
    }
    sync_cube();
    let reach = b.solids[LAW + 1];
    let bodies_at = index(&b.solids, 1);
    for a in 0..r {
        let row = bodies_at + BODY * (b0 + a);
        let (e0, len) = (index(&b.solids, row), index(&b.solids, row + 1));
        let mut e = u;
        loop {
            if e >= len {
                break;
            }
            let i = 4 * index(&b.solids, e0 + 3 * e);
            for before in 0..2usize {
                let (x, y) = position(b, i, before, prev_at, at);
                for other in a + 1..r {
                    // Its box (before: the frame before's), widened by the reach.
                    let o = other * STATS + 8 + 4 * before;
                    let inside = x >= st[o] - reach
                        && y >= st[o + 1] - reach
                        && x <= st[o + 2] + reach
                        && y <= st[o + 3] + reach;
                    if inside {
                        let bt = bodies_at + BODY * (b0 + other);
                        let (f0, flen) = (index(&b.solids, bt), index(&b.solids, bt + 1));
                        for f in 0..flen {
                            let j = 4 * index(&b.solids, f0 + 3 * f);
                            let (xj, yj) = position(b, j, before, prev_at, at);
                            let d = f32::hypot(xj - x, yj - y);
                            if d <= reach {
                                let slot = before * MAXB * MAXB + a * MAXB + other;
                                gaps[slot].fetch_min(u32::reinterpret(d));
                            }
                        }
                    }
                }
            }
            e += THREADS as usize;
        }
    }
    sync_cube();
}

/// The position of the particle whose row is `i` values into the scene: in the predicted
/// frame (scene rows from `at`), or (`before` 1) in the frame before (from `prev_at`).
#[cube]
fn position(b: &Buffers, i: usize, before: usize, prev_at: usize, at: usize) -> (f32, f32) {
    let mut x = b.frames[at + i];
    let mut y = b.frames[at + i + 1];
    if before == 1 {
        x = b.prev[prev_at + i];
        y = b.prev[prev_at + i + 1];
    }
    (x, y)
}

/// The speed to add to a body leaving the contact at `at` of the table at separating speed
/// `u` (`Event::exit`): 0 without a known approach speed or while not separating; `fall`
/// gravity's speed change a frame along the normal, counted over the frames it has left.
#[cube]
fn exit(events: &mut Array<f32>, at: usize, restitution: f32, u: f32, fall: f32) -> f32 {
    let speed_in = events[at + 1];
    let mut d = f32::new(0.0);
    // -1 (unknown) fails the test.
    if speed_in > f32::new(0.0) && u > f32::new(0.0) {
        let fall = fall * events[at + 2];
        events[at + 2] += f32::new(1.0);
        let (low, high) = (restitution * speed_in + fall, speed_in + fall);
        d = f32::min(f32::max(u, low), f32::max(high, low)) - u;
    }
    d
}

/// A new contact at `at`: in progress, its approach speed `speed` (kept above `resting`,
/// else 0) or unknown (`known` false: -1), no frame leaving yet.
#[cube]
fn begin(events: &mut Array<f32>, at: usize, known: bool, speed: f32, resting: f32) {
    let mut kept = f32::new(0.0);
    if speed > resting {
        kept = speed;
    }
    if !known {
        kept = f32::new(-1.0);
    }
    events[at] = f32::new(1.0);
    events[at + 1] = kept;
    events[at + 2] = f32::new(0.0);
}

/// Where contact `(a, column)` of scene `s` starts in the tables of `rb` bodies a row.
#[cube]
fn slot(rb: u32, s: usize, a: usize, column: usize) -> usize {
    let rb = rb as usize;
    ((s * rb + a) * (rb + 4) + column) * EV
}

/// The walls' contacts of scene `s` (`Rebound::walls`), one thread.
#[cube]
fn walls(b: &mut Buffers, rb: u32, st: &mut SharedMemory<f32>, r: usize, dt: f32, s: usize) {
    let (restitution, clearance) = (b.solids[LAW], b.solids[LAW + 2]);
    let (release, resting) = (b.solids[LAW + 3], b.solids[LAW + 4]);
    for body in 0..r {
        for side in 0..4usize {
            let axis = side / 2;
            let o = body * STATS;
            let mut gap = st[o + 8 + axis];
            let mut gap_prev = st[o + 12 + axis];
            let mut normal = f32::new(1.0);
            if side % 2 == 1 {
                gap = f32::new(1.0) - st[o + 10 + axis];
                gap_prev = f32::new(1.0) - st[o + 14 + axis];
                normal = f32::new(-1.0);
            }
            let at = slot(rb, s, body, rb as usize + side);
            let u = st[o + 6 + axis] * normal;
            let fall = b.solids[LAW + 5 + axis] * normal * dt;
            let on = b.events[at] == f32::new(1.0);
            let add = ADD + 2 * body + axis;
            if gap >= clearance {
                if on {
                    st[add] += exit(&mut b.events, at, restitution, u, fall) * normal;
                    b.events[at] = f32::new(0.0);
                }
            } else {
                if !on {
                    let v_in = f32::new(0.0) - st[o + 4 + axis] * normal;
                    begin(&mut b.events, at, gap_prev >= clearance, v_in, resting);
                }
                if gap >= release {
                    st[add] += exit(&mut b.events, at, restitution, u, fall) * normal;
                }
            }
        }
    }
}

/// The pairs' contacts of scene `s` (`Rebound::pairs`), one thread: those that ended (in
/// the host's key order), then those near.
#[cube]
#[allow(clippy::too_many_arguments)]
fn pairs(
    b: &mut Buffers,
    rb: u32,
    st: &mut SharedMemory<f32>,
    gaps: &SharedMemory<Atomic<u32>>,
    r: usize,
    b0: usize,
    s: usize,
) {
    let (release, resting) = (b.solids[LAW + 3], b.solids[LAW + 4]);
    for a in 0..r {
        for c in a + 1..r {
            let at = slot(rb, s, a, c);
            if b.events[at] == f32::new(1.0) && gaps[a * MAXB + c].load() == u32::new(FAR) {
                part(b, st, at, a, c, b0);
                b.events[at] = f32::new(0.0);
            }
        }
    }
    for a in 0..r {
        for c in a + 1..r {
            let near = gaps[a * MAXB + c].load();
            if near != u32::new(FAR) {
                let at = slot(rb, s, a, c);
                if b.events[at] != f32::new(1.0) {
                    let (oa, ob) = (a * STATS, c * STATS);
                    let (nx, ny) = unit(st[oa] - st[ob], st[oa + 1] - st[ob + 1]);
                    let closing = f32::new(0.0)
                        - ((st[oa + 4] - st[ob + 4]) * nx + (st[oa + 5] - st[ob + 5]) * ny);
                    let known = gaps[MAXB * MAXB + a * MAXB + c].load() == u32::new(FAR);
                    begin(&mut b.events, at, known, closing, resting);
                }
                if f32::reinterpret(near) >= release {
                    part(b, st, at, a, c, b0);
                }
            }
        }
    }
}

/// Pair `(a, c)` leaving the contact at `at` (`Rebound::part`): equal and opposite speeds
/// along the line between their centres, weighed by their particle counts.
#[cube]
#[allow(clippy::too_many_arguments)]
fn part(b: &mut Buffers, st: &mut SharedMemory<f32>, at: usize, a: usize, c: usize, b0: usize) {
    let (oa, ob) = (a * STATS, c * STATS);
    let (nx, ny) = unit(st[oa + 2] - st[ob + 2], st[oa + 3] - st[ob + 3]);
    let u = (st[oa + 6] - st[ob + 6]) * nx + (st[oa + 7] - st[ob + 7]) * ny;
    let restitution = b.solids[LAW];
    let d = exit(&mut b.events, at, restitution, u, f32::new(0.0));
    if d != f32::new(0.0) {
        let bodies_at = index(&b.solids, 1);
        let ma = b.solids[bodies_at + BODY * (b0 + a) + 1];
        let mb = b.solids[bodies_at + BODY * (b0 + c) + 1];
        st[ADD + 2 * a] += d * mb / (ma + mb) * nx;
        st[ADD + 2 * a + 1] += d * mb / (ma + mb) * ny;
        st[ADD + 2 * c] -= d * ma / (ma + mb) * nx;
        st[ADD + 2 * c + 1] -= d * ma / (ma + mb) * ny;
    }
}

/// `(x, y)` over its length (`(0, 0)` for a zero vector).
#[cube]
fn unit(x: f32, y: f32) -> (f32, f32) {
    let len = f32::hypot(x, y);
    let mut out = (f32::new(0.0), f32::new(0.0));
    if len > f32::new(0.0) {
        out = (x / len, y / len);
    }
    out
}
