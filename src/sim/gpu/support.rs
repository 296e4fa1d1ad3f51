//! The GPU solver's bookkeeping kernels (feature `cuda`): each scene's maxima of a part,
//! reduced from its particles' words ([`maxima_kernel`]), and the zeroing and copies of the
//! speculative frame (`GpuSolver::advance`). Layout: `kernels.rs`.

use burn_cubecl::cubecl;
use cubecl::prelude::*;

use super::kernels::TALLY;

/// `a[i] = 0` for every element.
#[cube(launch)]
pub(super) fn zero_kernel(a: &mut Array<u32>) {
    if ABSOLUTE_POS < a.len() {
        a[ABSOLUTE_POS] = 0;
    }
}

/// `dst[i] = src[i]` for every element (`f32`).
#[cube(launch)]
pub(super) fn copy_f32_kernel(src: &Array<f32>, dst: &mut Array<f32>) {
    if ABSOLUTE_POS < dst.len() {
        dst[ABSOLUTE_POS] = src[ABSOLUTE_POS];
    }
}

/// `dst[i] = src[i]` for every element (`u32`).
#[cube(launch)]
pub(super) fn copy_u32_kernel(src: &Array<u32>, dst: &mut Array<u32>) {
    if ABSOLUTE_POS < dst.len() {
        dst[ABSOLUTE_POS] = src[ABSOLUTE_POS];
    }
}

/// Threads of a [`maxima_kernel`] cube.
pub(super) const REDUCE_THREADS: u32 = 1024;

/// The maxima of part `part` per scene: cube `s` (one per scene, [`REDUCE_THREADS`] threads)
/// takes the largest of each of the three words G2P left in `pmax` for the scene's particles
/// `offsets[s]..offsets[s + 1]` and writes them to the scene's tally (scenes with no part
/// `part` keep theirs). Maxima of non-negative floats as their bits: the same on every run.
#[cube(launch)]
pub(super) fn maxima_kernel(
    pmax: &Array<u32>,
    offsets: &Array<u32>,
    parts: &Array<u32>,
    tally: &mut Array<u32>,
    part: u32,
) {
    let s = CUBE_POS_X as usize;
    if part >= parts[s] {
        terminate!();
    }
    let end = offsets[s + 1] as usize;
    let mut i = offsets[s] as usize + UNIT_POS as usize;
    let mut m0 = 0u32;
    let mut m1 = 0u32;
    let mut m2 = 0u32;
    loop {
        if i >= end {
            break;
        }
        if pmax[i * 3] > m0 {
            m0 = pmax[i * 3];
        }
        if pmax[i * 3 + 1] > m1 {
            m1 = pmax[i * 3 + 1];
        }
        if pmax[i * 3 + 2] > m2 {
            m2 = pmax[i * 3 + 2];
        }
        i += CUBE_DIM as usize;
    }
    let mut shared = SharedMemory::<u32>::new(3 * REDUCE_THREADS as usize);
    let u = UNIT_POS as usize;
    shared[u * 3] = m0;
    shared[u * 3 + 1] = m1;
    shared[u * 3 + 2] = m2;
    sync_cube();
    // A tree over the cube's threads: halves until one is left.
    let mut half = (CUBE_DIM / 2) as usize;
    loop {
        if half == 0 {
            break;
        }
        if u < half {
            #[unroll]
            for k in 0..3usize {
                if shared[(u + half) * 3 + k] > shared[u * 3 + k] {
                    shared[u * 3 + k] = shared[(u + half) * 3 + k];
                }
            }
        }
        sync_cube();
        half /= 2;
    }
    if u == 0 {
        m0 = shared[0];
        m1 = shared[1];
        m2 = shared[2];
        tally[s * TALLY] = m0;
        tally[s * TALLY + 1] = m1;
        tally[s * TALLY + 2] = m2;
    }
}
