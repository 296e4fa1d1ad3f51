//! The momentum part on the device (feature `cuda`): the device form of
//! `model::constraints::momentum::conserve` for one scene, a step of the call's kernel
//! (`cuda/projection/call.rs`) after the rebound and before the walls. The clusters of a
//! frame transition (particles within `reach` of each other in the frame before or the
//! predicted one) are found as grid-based DBSCAN finds its clusters (Gunawan 2013, "A faster
//! algorithm for DBSCAN", section 3): cells of side `reach / sqrt(2)`, whose particles are all
//! within `reach` of each other, each joined whole to its first particle, and two cells
//! within reach of each other joined where any of their pairs is near (the test of
//! `Components::join_within`, so the clusters are the host's). The joins are a lock-free
//! union-find over the scene's particles (Jayanti & Tarjan 2016, "A randomized concurrent
//! algorithm for disjoint set union": hooks by compare-and-swap, finds with path halving);
//! which join lands first changes no component. A particle outside the cells (beyond a
//! quarter of the domain past a wall) is joined by a search over every particle.
//! [`conserve`](super::momentum_sums::conserve) then moves the clusters.
//!
//! Scratch (`Buffers`, `[B N]` each): `parent` the union-find, `sorted` the particles by
//! cell, `cellof` a particle's cell; `cells` (shared) the counts, starts and cursors of the
//! cells, `chunk` (shared, a value a thread) the scan's chunks.

use burn_cubecl::cubecl;
use cubecl::prelude::*;

use super::buffers::{read, Buffers};
use super::liquid_solve::THREADS;

/// Cells per axis at most; cells cover `[0.5 - g side / 2, 0.5 + g side / 2)` on each axis.
pub(in crate::ops) const MAX_CELLS: usize = 48;
/// The domain widths the cells cover at most.
const SPAN: f32 = 1.5;
/// Values of the shared `cells` array: the starts (`g^2 + 1`) then the cursors.
pub(in crate::ops) const CELL_SLOTS: usize = MAX_CELLS * MAX_CELLS + 1;
/// Where the part's values start in `solids` (`MOMENTUM_AT`).
pub(in crate::ops) const LAW: usize = crate::ops::MOMENTUM_AT;
/// A particle outside the cells.
const STRAY: i64 = 4294967295;

/// The grid of the cells for `reach`: side, cells per axis and the low corner.
#[cube]
pub(in crate::ops) fn cell_grid(reach: f32) -> (f32, u32, f32) {
    // 2 side^2 below reach^2 (1 - 1e-4), the test's sure bound, with room for rounding.
    let side = reach * f32::sqrt(f32::new(0.49989));
    let g = u32::min(
        u32::cast_from(f32::ceil(f32::new(SPAN) / side)),
        MAX_CELLS as u32,
    );
    let origin = f32::new(0.5) - f32::cast_from(g) * side * f32::new(0.5);
    (side, g, origin)
}

/// The cell of `(x, y)`, or [`STRAY`] outside the cells (or not finite).
#[cube]
fn cell_of(x: f32, y: f32, side: f32, g: u32, origin: f32) -> u32 {
    let fx = (x - origin) / side;
    let fy = (y - origin) / side;
    let top = f32::cast_from(g);
    let mut c = u32::new(STRAY);
    if fx >= f32::new(0.0) && fy >= f32::new(0.0) && fx < top && fy < top {
        c = u32::cast_from(fy) * g + u32::cast_from(fx);
    }
    c
}

/// Whether two particles are within `reach` (`Components::join_within`'s test).
#[cube]
pub(in crate::ops) fn near(ax: f32, ay: f32, bx: f32, by: f32, reach: f32) -> bool {
    let (dx, dy) = (bx - ax, by - ay);
    let d2 = dx * dx + dy * dy;
    let r2 = reach * reach;
    let mut yes = d2 < r2 * f32::new(0.9999);
    if !yes && d2 <= r2 * f32::new(1.0001) {
        yes = f32::hypot(dx, dy) <= reach;
    }
    yes
}

/// The root of `x`'s set, halving its path.
#[cube]
pub(in crate::ops) fn find(b: &mut Buffers, x: u32) -> u32 {
    let mut x = x;
    loop {
        let p = b.parent[x as usize].load();
        if p == x {
            break;
        }
        let gp = b.parent[p as usize].load();
        if gp != p {
            b.parent[x as usize].compare_exchange_weak(p, gp);
        }
        x = gp;
    }
    x
}

/// Joins the sets of particles `x` and `y`: the larger root hooked under the smaller.
#[cube]
fn join(b: &mut Buffers, x: u32, y: u32) {
    let mut ra = find(b, x);
    let mut rb = find(b, y);
    loop {
        if ra == rb {
            break;
        }
        if ra < rb {
            let t = ra;
            ra = rb;
            rb = t;
        }
        let old = b.parent[ra as usize].compare_exchange_weak(ra, rb);
        if old == ra {
            break;
        }
        ra = find(b, ra);
        rb = find(b, rb);
    }
}

/// Every particle of scene `s` its own set. Every thread calls it.
#[cube]
pub(in crate::ops) fn reset(b: &mut Buffers, n: u32, s: usize, u: usize) {
    let mut p = s * n as usize + u;
    loop {
        if p >= (s + 1) * n as usize {
            break;
        }
        b.parent[p].store(p as u32);
        p += THREADS as usize;
    }
    sync_cube();
}

/// Joins the particles of scene `s` within `reach` of each other in the frame before
/// (`which` 0) or the predicted one (1), whose scene rows start at `base` (module doc). Every
/// thread calls it.
#[cube]
#[allow(clippy::too_many_arguments)]
pub(in crate::ops) fn join_frame(
    b: &mut Buffers,
    which: u32,
    base: usize,
    cells: &mut SharedMemory<Atomic<u32>>,
    chunk: &mut SharedMemory<u32>,
    n: u32,
    reach: f32,
    s: usize,
    u: usize,
) {
    let (side, g, origin) = cell_grid(reach);
    bin(b, which, base, cells, chunk, n, side, g, origin, s, u);
    let first = s * n as usize;
    // Each cell whole to its first particle.
    let total = cells[(g * g) as usize].load() as usize;
    let mut e = u;
    loop {
        if e >= total {
            break;
        }
        let i = b.sorted[first + e];
        let c = b.cellof[first + i as usize] as usize;
        let leader = b.sorted[first + cells[c].load() as usize];
        if leader != i {
            join(b, first as u32 + i, first as u32 + leader);
        }
        e += THREADS as usize;
    }
    sync_cube();
    // Neighbouring cells, then the cells two apart (most already joined by then).
    for phase in 0..2u32 {
        let offsets = 4u32 + 4 * phase;
        let mut t = u as u32;
        loop {
            if t >= g * g * offsets {
                break;
            }
            let (dx, dy) = offset(phase, t % offsets);
            link_cells(b, which, base, cells, t / offsets, dx, dy, g, reach, first);
            t += THREADS;
        }
        sync_cube();
    }
    // Particles outside the cells: against every particle.
    let mut i = u;
    loop {
        if i >= n as usize {
            break;
        }
        if b.cellof[first + i] == u32::new(STRAY) {
            let (x, y) = (
                read(b, which, base + 4 * i),
                read(b, which, base + 4 * i + 1),
            );
            for j in 0..n as usize {
                let (xj, yj) = (
                    read(b, which, base + 4 * j),
                    read(b, which, base + 4 * j + 1),
                );
                if j != i && near(x, y, xj, yj, reach) {
                    join(b, (first + i) as u32, (first + j) as u32);
                }
            }
        }
        i += THREADS as usize;
    }
    sync_cube();
}

/// Half-neighbourhood offset `o` of `phase` 0 (the 4 adjacent cells) or 1 (the 8 cells two
/// apart; with the 4 and their mirrors, every cell within reach).
#[cube]
fn offset(phase: u32, o: u32) -> (i32, i32) {
    let o = i32::cast_from(o);
    let mut dx = o - 5;
    let mut dy = 2i32;
    if phase == 0 {
        dx = o - 2;
        dy = 1;
        if o == 0 {
            dx = 1;
            dy = 0;
        }
    } else if o < 3 {
        dx = 2;
        dy = 1;
        if o == 1 {
            dx = -2;
        }
        if o == 0 {
            dy = 0;
        }
    }
    (dx, dy)
}

/// Joins cell `c` with the cell `(dx, dy)` from it where both hold particles, are not
/// joined yet and one of their pairs is near.
#[cube]
#[allow(clippy::too_many_arguments)]
fn link_cells(
    b: &mut Buffers,
    which: u32,
    base: usize,
    cells: &SharedMemory<Atomic<u32>>,
    c: u32,
    dx: i32,
    dy: i32,
    g: u32,
    reach: f32,
    first: usize,
) {
    let nx = i32::cast_from(c % g) + dx;
    let ny = i32::cast_from(c / g) + dy;
    let gi = i32::cast_from(g);
    if nx >= 0 && ny >= 0 && nx < gi && ny < gi {
        let d = u32::cast_from(ny) * g + u32::cast_from(nx);
        let (a0, a1) = (cells[c as usize].load(), cells[c as usize + 1].load());
        let (d0, d1) = (cells[d as usize].load(), cells[d as usize + 1].load());
        if a0 < a1 && d0 < d1 {
            let la = first as u32 + b.sorted[first + a0 as usize];
            let lb = first as u32 + b.sorted[first + d0 as usize];
            if find(b, la) != find(b, lb) {
                let mut found = false;
                let mut e = a0;
                loop {
                    if found || e >= a1 {
                        break;
                    }
                    let i = base + 4 * b.sorted[first + e as usize] as usize;
                    let mut f = d0;
                    loop {
                        if found || f >= d1 {
                            break;
                        }
                        let j = base + 4 * b.sorted[first + f as usize] as usize;
                        let (xi, yi) = (read(b, which, i), read(b, which, i + 1));
                        let (xj, yj) = (read(b, which, j), read(b, which, j + 1));
                        found = near(xi, yi, xj, yj, reach);
                        f += 1;
                    }
                    e += 1;
                }
                if found {
                    join(b, la, lb);
                }
            }
        }
    }
}

/// The counting sort of scene `s`'s particles into the cells: `cellof`, then `cells`' starts
/// (`g^2 + 1`, [`starts`]) and cursors, then `sorted`.
#[cube]
#[allow(clippy::too_many_arguments)]
fn bin(
    b: &mut Buffers,
    which: u32,
    base: usize,
    cells: &mut SharedMemory<Atomic<u32>>,
    chunk: &mut SharedMemory<u32>,
    n: u32,
    side: f32,
    g: u32,
    origin: f32,
    s: usize,
    u: usize,
) {
    let count = (g * g) as usize;
    let mut c = u;
    loop {
        if c > count {
            break;
        }
        cells[c].store(0u32);
        c += THREADS as usize;
    }
    sync_cube();
    let first = s * n as usize;
    let mut i = u;
    loop {
        if i >= n as usize {
            break;
        }
        let (x, y) = (
            read(b, which, base + 4 * i),
            read(b, which, base + 4 * i + 1),
        );
        let c = cell_of(x, y, side, g, origin);
        b.cellof[first + i] = c;
        if c != u32::new(STRAY) {
            cells[c as usize].fetch_add(1u32);
        }
        i += THREADS as usize;
    }
    sync_cube();
    starts(cells, chunk, count, u);
    let mut i = u;
    loop {
        if i >= n as usize {
            break;
        }
        let c = b.cellof[first + i];
        if c != u32::new(STRAY) {
            let at = cells[CELL_SLOTS + c as usize].fetch_add(1u32) as usize;
            b.sorted[first + at] = i as u32;
        }
        i += THREADS as usize;
    }
    sync_cube();
}

/// The cells' counts (`cells[..count]`) turned into their starts, the total at `count` and
/// the cursors (from [`CELL_SLOTS`]) set to the starts: each thread sums its chunk of cells,
/// one thread scans the chunks, each thread its cells.
#[cube]
fn starts(
    cells: &mut SharedMemory<Atomic<u32>>,
    chunk: &mut SharedMemory<u32>,
    count: usize,
    u: usize,
) {
    let per = (count + THREADS as usize - 1) / THREADS as usize;
    let (c0, c1) = (usize::min(u * per, count), usize::min((u + 1) * per, count));
    let mut sum = 0u32;
    for c in c0..c1 {
        sum += cells[c].load();
    }
    chunk[u] = sum;
    sync_cube();
    if u == 0 {
        let mut run = 0u32;
        for t in 0..THREADS as usize {
            let here = chunk[t];
            chunk[t] = run;
            run += here;
        }
        cells[count].store(run);
    }
    sync_cube();
    let mut run = chunk[u];
    for c in c0..c1 {
        let here = cells[c].load();
        cells[c].store(run);
        cells[CELL_SLOTS + c].store(run);
        run += here;
    }
    sync_cube();
}
