//! The momentum part's clusters moved onto free flight on the device (feature `cuda`): the
//! second half of `cuda/projection/momentum.rs`, after its clusters are found. Each cluster sums its
//! particles' positions and velocities in fixed point (2^-32 domain units, 2^-24 velocity
//! units, rounded: the same bits in any order, on every run) at its root, and every particle
//! of a free axis of a cluster takes the cluster's shift and kick
//! (`model::constraints::momentum::conserve`'s arithmetic, in f64; its position lag held in
//! f32). Scratch (`Buffers`): `cellof` a particle's root, `sums` `[B N SUMS]` a root's sums,
//! `free` a root's walls flags.

use burn_cubecl::cubecl;
use cubecl::prelude::*;

use super::buffers::Buffers;
use super::liquid_solve::THREADS;
use super::momentum::{find, LAW};

/// Sums a root holds: the positions before (x, y), the positions now, the velocities before,
/// the velocities the frame ends with, the count.
pub(in crate::ops) const SUMS: usize = 9;
/// Fixed-point units of a position and of a velocity.
const POSITION_UNITS: f64 = 4294967296.0;
const VELOCITY_UNITS: f64 = 16777216.0;

/// Moves each free cluster of scene `s` onto free flight (`conserve`): its sums at its root
/// (`cellof` takes the roots), then every particle its cluster's shift and kick on each free
/// axis, in frame `k` (`solids`' head holds the part's reach, clearance, lag and gravity x
/// and y from [`LAW`]; `dt` the scene's time step). Every thread calls it, after
/// [`join_frame`](super::momentum::join_frame) of both frames.
#[cube]
pub(in crate::ops) fn conserve(b: &mut Buffers, dt: f32, n: u32, k: u32, s: usize, u: usize) {
    let prev_at = s * n as usize * 4;
    let at = k as usize * b.before.len() + prev_at;
    sum_clusters(b, dt, n, at, s, u);
    let first = s * n as usize;
    let lag = f64::cast_from(b.solids[LAW + 2]);
    let dt64 = f64::cast_from(dt);
    let mut i = u;
    loop {
        if i >= n as usize {
            break;
        }
        let r = b.cellof[first + i] as usize;
        let m = f64::cast_from(b.sums[r * SUMS + 8].load());
        let flags = b.free[r].load();
        for axis in 0..2usize {
            if (flags >> axis as u32) & 1u32 == 0 {
                let w = r * SUMS + axis;
                let xp = mean(&b.sums, w, POSITION_UNITS, m);
                let xc = mean(&b.sums, w + 2, POSITION_UNITS, m);
                let vp = mean(&b.sums, w + 4, VELOCITY_UNITS, m);
                let vc = mean(&b.sums, w + 6, VELOCITY_UNITS, m);
                let g = f64::cast_from(b.solids[LAW + 3 + axis]);
                let shift = xp + vp * dt64 + lag * g * dt64 * dt64 - xc;
                let kick = vp + g * dt64 - vc - shift / dt64;
                let fa = at + 4 * i;
                b.frames[fa + axis] += f32::cast_from(shift);
                b.frames[fa + 2 + axis] += f32::cast_from(kick);
            }
        }
        i += THREADS as usize;
    }
    sync_cube();
}

/// The mean of sum `w` in fixed point of `units` over `m` particles.
#[cube]
fn mean(sums: &Array<Atomic<i64>>, w: usize, units: f64, m: f64) -> f64 {
    f64::cast_from(sums[w].load()) / units / m
}

/// Adds `v` to sum `w` in fixed point of `units` (rounded to the nearest unit).
#[cube]
fn add(sums: &mut Array<Atomic<i64>>, w: usize, v: f64, units: f64) {
    sums[w].fetch_add(i64::cast_from(f64::round(v * units)));
}

/// Each cluster's sums at its root (`cellof` takes the roots; the roots' slots zeroed first)
/// and its walls flags, for scene `s`'s frame `k` (predicted rows from `at`).
#[cube]
fn sum_clusters(b: &mut Buffers, dt: f32, n: u32, at: usize, s: usize, u: usize) {
    let prev_at = s * n as usize * 4;
    let first = s * n as usize;
    let mut i = u;
    loop {
        if i >= n as usize {
            break;
        }
        let p = first + i;
        b.cellof[p] = find(b, p as u32);
        for w in 0..SUMS {
            // No 64-bit atomic store in CUDA: the slot is this thread's alone here.
            let v = b.sums[p * SUMS + w].load();
            b.sums[p * SUMS + w].fetch_sub(v);
        }
        b.free[p].store(0u32);
        i += THREADS as usize;
    }
    sync_cube();
    let (lo, hi) = (b.solids[LAW + 1], f32::new(1.0) - b.solids[LAW + 1]);
    let mut i = u;
    loop {
        if i >= n as usize {
            break;
        }
        let r = b.cellof[first + i] as usize;
        let (pa, fa) = (prev_at + 4 * i, at + 4 * i);
        for axis in 0..2usize {
            let (xp, xc) = (b.prev[pa + axis], b.frames[fa + axis]);
            // The frame's velocity plus its moves so far over dt, in f64 as the host sums it.
            let moved = f64::cast_from(xc - b.before[pa + axis]) / f64::cast_from(dt);
            let vc = f64::cast_from(b.frames[fa + 2 + axis]) + moved;
            let vp = f64::cast_from(b.prev[pa + 2 + axis]);
            add(
                &mut b.sums,
                r * SUMS + axis,
                f64::cast_from(xp),
                POSITION_UNITS,
            );
            add(
                &mut b.sums,
                r * SUMS + 2 + axis,
                f64::cast_from(xc),
                POSITION_UNITS,
            );
            add(&mut b.sums, r * SUMS + 4 + axis, vp, VELOCITY_UNITS);
            add(&mut b.sums, r * SUMS + 6 + axis, vc, VELOCITY_UNITS);
            let inside = xp >= lo && xp <= hi && xc >= lo && xc <= hi;
            if !inside {
                b.free[r].fetch_or(1u32 << axis as u32);
            }
        }
        b.sums[r * SUMS + 8].fetch_add(1i64);
        i += THREADS as usize;
    }
    sync_cube();
}
