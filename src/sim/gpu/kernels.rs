//! The cubecl kernels of the batched MLS-MPM substep on CUDA (feature `cuda`): the substep
//! split per scene ([`parts_kernel`]), P2G with each particle's stress ([`p2g_kernel`], 64-bit
//! fixed-point sums), the grid update ([`grid_kernel`]) and G2P with the `F` update and the
//! plastic projection ([`g2p_kernel`]). Each is the GPU form of one step of
//! [`crate::sim::mpm::Solver::substep`] and keeps its arithmetic in the same order; `mod.rs`
//! launches them.
//!
//! Layout: particles of all scenes back to back, flat `f32` arrays (`x`, `v` `[P 2]`, `c`, `f`
//! `[P 4]` row-major, `jp` `[P]`), `material` and `scene` `[P]` as `u32`; per scene `parts`
//! `[B]` (the substep's equal parts) and `tally` `[B TALLY]` ([`TALLY`]); the grids
//! `[B n^2 3]` (`acc`: momentum x, y and mass in fixed point; `grid`: velocity x, y and the
//! inverse mass).

use burn_cubecl::cubecl;
use cubecl::prelude::*;

use super::constitutive::{base_node, deform, kirchhoff, weight};

/// Words of a scene's tally: `max |v|^2`, `max |C|_F^2` and `max k phi` of the last G2P (as
/// `f32` bits: non-negative floats order like their bits), particle-substeps that left the
/// interpolation band, extra parts taken.
pub(super) const TALLY: usize = 5;

/// Per scene: the equal parts its next substep is taken in, from the last G2P's maxima, as
/// `Solver::substep` decides them (the CFL and strain-increment limits and the elastic
/// stability bound; at most 64); adds the extra parts to the scene's split count and raises
/// `most[0]` to the largest. One thread per scene.
#[cube(launch)]
pub(super) fn parts_kernel(
    tally: &mut Array<u32>,
    parts: &mut Array<u32>,
    most: &mut Array<Atomic<u32>>,
    dt: f32,
    n: u32,
    max_cfl: f32,
    max_strain: f32,
) {
    let s = ABSOLUTE_POS;
    if s >= parts.len() {
        terminate!();
    }
    let t = s * TALLY;
    let vmax = f32::sqrt(f32::reinterpret(tally[t]));
    let cmax = f32::sqrt(f32::reinterpret(tally[t + 1]));
    let kphi = f32::reinterpret(tally[t + 2]);
    let dx = f32::new(1.0) / f32::cast_from(n);
    let mut cfl = vmax * dt / dx / max_cfl;
    let strain = cmax * dt / max_strain;
    if strain > cfl {
        cfl = strain;
    }
    let stiff = f32::sqrt(f32::new(2.0) * kphi * dt * dt / (dx * dx) / f32::new(0.7));
    let mut need = cfl;
    if stiff > need {
        need = stiff;
    }
    let mut count = 1u32;
    if need > f32::new(64.0) {
        count = 64u32;
    } else if need > f32::new(1.0) {
        count = u32::cast_from(f32::ceil(need));
    }
    parts[s] = count;
    tally[t + 4] += count - 1;
    most[0].fetch_max(count);
}

/// Adds `w (mx, my, m)` to node `node` of `acc` in fixed point (`scale` units per unit).
#[cube]
fn splat_node(
    acc: &mut Array<Atomic<i64>>,
    node: usize,
    w: f32,
    mx: f32,
    my: f32,
    m: f32,
    scale: f32,
) {
    acc[node * 3].fetch_add(i64::cast_from(w * mx * scale));
    acc[node * 3 + 1].fetch_add(i64::cast_from(w * my * scale));
    acc[node * 3 + 2].fetch_add(i64::cast_from(w * m * scale));
}

/// P2G for part `part` of the substep: each particle of a scene with more than `part` parts
/// computes its Kirchhoff stress (liquid pressure, or fixed-corotated with the polar rotation
/// and hardening) and scatters mass and APIC momentum `m v + A (x_i - x_p)`, `A = -h p_vol 4
/// inv_dx^2 tau + m C` (`h` = `dt` / parts), to its 3 x 3 nodes in 64-bit fixed point, and
/// keeps its stiffness for G2P's stability bound. One thread per particle.
///
/// Fixed point makes the sums independent of the order the atomics land in, so every run
/// gives the same bits (Le Grand, Götz and Walker 2013, as the grid model's P2G,
/// `ops::cuda::net::stencil_kernels`).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub(super) fn p2g_kernel(
    x: &Array<f32>,
    v: &Array<f32>,
    c: &Array<f32>,
    f: &Array<f32>,
    jp: &Array<f32>,
    material: &Array<u32>,
    scene: &Array<u32>,
    parts: &Array<u32>,
    stiffness: &mut Array<f32>,
    acc: &mut Array<Atomic<i64>>,
    part: u32,
    n: u32,
    dt: f32,
    mu0: f32,
    lambda0: f32,
    scale: f32,
) {
    let p = ABSOLUTE_POS;
    if p >= material.len() {
        terminate!();
    }
    let s = scene[p] as usize;
    let count = parts[s];
    if part >= count {
        terminate!();
    }
    let h = dt / f32::cast_from(count);
    let inv_dx = f32::cast_from(n);
    let dx = f32::new(1.0) / inv_dx;
    let half = f32::new(0.5) * dx;
    let p_mass = half * half;
    let stress_scale = -h * p_mass * f32::new(4.0) * inv_dx * inv_dx;
    // The stencil.
    let gx = x[p * 2] * inv_dx;
    let gy = x[p * 2 + 1] * inv_dx;
    let bi = base_node(gx, n);
    let bj = base_node(gy, n);
    let fx = gx - f32::cast_from(bi);
    let fy = gy - f32::cast_from(bj);
    // The stress (`material::kirchhoff_stress`): tau and the stiffness k.
    let mut tau = Array::<f32>::new(5usize);
    kirchhoff(f, jp[p], p, material[p], mu0, lambda0, &mut tau);
    let (t0, t1, t2, t3, k) = (tau[0], tau[1], tau[2], tau[3], tau[4]);
    stiffness[p] = k;
    let a0 = (stress_scale * t0 + p_mass * c[p * 4]) * dx;
    let a1 = (stress_scale * t1 + p_mass * c[p * 4 + 1]) * dx;
    let a2 = (stress_scale * t2 + p_mass * c[p * 4 + 2]) * dx;
    let a3 = (stress_scale * t3 + p_mass * c[p * 4 + 3]) * dx;
    let q0 = p_mass * v[p * 2] - a0 * fx - a1 * fy;
    let q1 = p_mass * v[p * 2 + 1] - a2 * fx - a3 * fy;
    let nn = n as usize;
    let base = s * nn * nn + (bi as usize) * nn + bj as usize;
    let (wy0, wy1, wy2) = (weight(fy, 0u32), weight(fy, 1u32), weight(fy, 2u32));
    #[unroll]
    for i in 0..3u32 {
        let wx = weight(fx, i);
        let fi = f32::cast_from(i);
        let r0 = q0 + a0 * fi;
        let r1 = q1 + a2 * fi;
        let row = base + (i as usize) * nn;
        splat_node(acc, row, wx * wy0, r0, r1, p_mass, scale);
        splat_node(acc, row + 1, wx * wy1, r0 + a1, r1 + a3, p_mass, scale);
        let two = f32::new(2.0);
        splat_node(
            acc,
            row + 2,
            wx * wy2,
            r0 + a1 * two,
            r1 + a3 * two,
            p_mass,
            scale,
        );
    }
}

/// The grid update for part `part`: each node of a scene with more than `part` parts turns
/// its fixed-point momentum into velocity, adds gravity and applies the walls (the outward
/// component zeroed on nodes with index < 3 or > n - 3), writes `(vx, vy, 1 / m)` (zeros
/// where no mass landed) and clears its sums for the next P2G. One thread per node.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub(super) fn grid_kernel(
    acc: &mut Array<i64>,
    grid: &mut Array<f32>,
    parts: &Array<u32>,
    part: u32,
    n: u32,
    dt: f32,
    gravity_x: f32,
    gravity_y: f32,
    scale: f32,
) {
    let g = ABSOLUTE_POS;
    if g * 3 >= grid.len() {
        terminate!();
    }
    let nn = (n * n) as usize;
    let s = g / nn;
    let local = (g % nn) as u32;
    let i = local / n;
    let j = local % n;
    let count = parts[s];
    if part >= count {
        terminate!();
    }
    let mx = f32::cast_from(acc[g * 3]) / scale;
    let my = f32::cast_from(acc[g * 3 + 1]) / scale;
    let m = f32::cast_from(acc[g * 3 + 2]) / scale;
    acc[g * 3] = 0;
    acc[g * 3 + 1] = 0;
    acc[g * 3 + 2] = 0;
    let h = dt / f32::cast_from(count);
    let mut vx = f32::new(0.0);
    let mut vy = f32::new(0.0);
    let mut inv = f32::new(0.0);
    if m > f32::new(0.0) {
        inv = f32::new(1.0) / m;
        vx = mx * inv + h * gravity_x;
        vy = my * inv + h * gravity_y;
        if i < 3 && vx < f32::new(0.0) {
            vx = f32::new(0.0);
        }
        if i > n - 3 && vx > f32::new(0.0) {
            vx = f32::new(0.0);
        }
        if j < 3 && vy < f32::new(0.0) {
            vy = f32::new(0.0);
        }
        if j > n - 3 && vy > f32::new(0.0) {
            vy = f32::new(0.0);
        }
    }
    grid[g * 3] = vx;
    grid[g * 3 + 1] = vy;
    grid[g * 3 + 2] = inv;
}

/// Stores particle `p`'s new velocity `(vx, vy)` and `C` (`cm`) and moves it by `h v`; true
/// when it lands outside the interpolation band `[0.5 dx, 1 - 1.5 dx)` (as the CPU's
/// `escaped` count).
#[cube]
#[allow(clippy::too_many_arguments)]
fn advect(
    x: &mut Array<f32>,
    v: &mut Array<f32>,
    c: &mut Array<f32>,
    p: usize,
    vx: f32,
    vy: f32,
    cm: &Array<f32>,
    h: f32,
    inv_dx: f32,
) -> bool {
    #[unroll]
    for k in 0..4usize {
        c[p * 4 + k] = cm[k];
    }
    v[p * 2] = vx;
    v[p * 2 + 1] = vy;
    let nx = x[p * 2] + h * vx;
    let ny = x[p * 2 + 1] + h * vy;
    x[p * 2] = nx;
    x[p * 2 + 1] = ny;
    let lo = f32::new(0.5) / inv_dx;
    let hi = f32::new(1.0) - f32::new(1.5) / inv_dx;
    !(nx >= lo && nx < hi && ny >= lo && ny < hi)
}

/// Row `i` of a particle's G2P gather from the grid's `(vx, vy, 1 / m)` at node `row` and
/// the next two: adds to `acc` `[v x, v y, b_i x, b_i y, b_j x, b_j y, phi]` as the CPU
/// solver's `g2p` does for one row (`s = sum_j w_j v_ij`, `t = sum_j j w_j v_ij`).
#[cube]
#[allow(clippy::too_many_arguments)]
fn gather_row(
    grid: &Array<f32>,
    row: usize,
    wx: f32,
    fi: f32,
    wy0: f32,
    wy1: f32,
    wy2: f32,
    acc: &mut Array<f32>,
) {
    let (c0, c1, c2) = (row * 3, row * 3 + 3, row * 3 + 6);
    let w2 = wy0 * wy0 * grid[c0 + 2] + wy1 * wy1 * grid[c1 + 2] + wy2 * wy2 * grid[c2 + 2];
    acc[6] += wx * wx * w2;
    #[unroll]
    for k in 0..2usize {
        let s = wy0 * grid[c0 + k] + wy1 * grid[c1 + k] + wy2 * grid[c2 + k];
        let t = wy1 * grid[c1 + k] + f32::new(2.0) * wy2 * grid[c2 + k];
        acc[k] += wx * s;
        acc[2 + k] += wx * fi * s;
        acc[4 + k] += wx * t;
    }
}

/// G2P for part `part`: each particle of a scene with more than `part` parts gathers `v` and
/// `C = 4 inv_dx^2 sum w v_i (x_i - x_p)^T` from its nodes, raises its scene's maxima
/// (`|v|^2`, `|C|_F^2`, stiffness times its own share of its nodes' mass, atomically as
/// bits), moves by `h v` (counting a step that leaves the interpolation band in
/// its scene's tally), updates `F <- (I + h C) F` (in `m` equal steps past `h |C|_F > 0.25`)
/// and projects it (liquid: `diag(max(J, j_min), 1)`; snow: [`snow_project`]). One thread per
/// particle.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub(super) fn g2p_kernel(
    x: &mut Array<f32>,
    v: &mut Array<f32>,
    c: &mut Array<f32>,
    f: &mut Array<f32>,
    jp: &mut Array<f32>,
    material: &Array<u32>,
    scene: &Array<u32>,
    parts: &Array<u32>,
    stiffness: &Array<f32>,
    grid: &Array<f32>,
    pmax: &mut Array<u32>,
    tally: &mut Array<Atomic<u32>>,
    part: u32,
    n: u32,
    dt: f32,
    snow_lo: f32,
    snow_hi: f32,
    j_min: f32,
) {
    let p = ABSOLUTE_POS;
    if p >= material.len() {
        terminate!();
    }
    let s = scene[p] as usize;
    let count = parts[s];
    if part >= count {
        terminate!();
    }
    let h = dt / f32::cast_from(count);
    let inv_dx = f32::cast_from(n);
    let dx = f32::new(1.0) / inv_dx;
    let half = f32::new(0.5) * dx;
    let p_mass = half * half;
    let gx = x[p * 2] * inv_dx;
    let gy = x[p * 2 + 1] * inv_dx;
    let bi = base_node(gx, n);
    let bj = base_node(gy, n);
    let fx = gx - f32::cast_from(bi);
    let fy = gy - f32::cast_from(bj);
    let nn = n as usize;
    let base = s * nn * nn + (bi as usize) * nn + bj as usize;
    let (wy0, wy1, wy2) = (weight(fy, 0u32), weight(fy, 1u32), weight(fy, 2u32));
    let mut acc = Array::<f32>::new(7usize);
    #[unroll]
    for k in 0..7usize {
        acc[k] = f32::new(0.0);
    }
    #[unroll]
    for i in 0..3u32 {
        let row = base + (i as usize) * nn;
        gather_row(
            grid,
            row,
            weight(fx, i),
            f32::cast_from(i),
            wy0,
            wy1,
            wy2,
            &mut acc,
        );
    }
    let (vx, vy) = (acc[0], acc[1]);
    let k4 = f32::new(4.0) * inv_dx;
    let mut cm = Array::<f32>::new(4usize);
    cm[0] = k4 * (acc[2] - vx * fx);
    cm[1] = k4 * (acc[4] - vx * fy);
    cm[2] = k4 * (acc[3] - vy * fx);
    cm[3] = k4 * (acc[5] - vy * fy);
    let cnorm2 = cm[0] * cm[0] + cm[1] * cm[1] + cm[2] * cm[2] + cm[3] * cm[3];
    // Its share of the scene's maxima (`maxima_kernel`: atomics on 3 words would queue).
    pmax[p * 3] = u32::reinterpret(vx * vx + vy * vy);
    pmax[p * 3 + 1] = u32::reinterpret(cnorm2);
    pmax[p * 3 + 2] = u32::reinterpret(stiffness[p] * acc[6] * p_mass);
    if advect(x, v, c, p, vx, vy, &cm, h, inv_dx) {
        tally[s * TALLY + 3].fetch_add(1u32);
    }
    deform(f, jp, p, material[p], &cm, h, snow_lo, snow_hi, j_min);
}
