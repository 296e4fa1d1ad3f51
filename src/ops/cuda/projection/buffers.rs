//! The arrays of a call's projection kernel (feature `cuda`), shared by its steps
//! (`cuda/projection/call.rs` runs them): the frames and their copies, the liquid's node
//! slots (`cuda/projection/liquid.rs`' layout), the solids' table (`ProjectionPlan::solids`), and the
//! momentum and rebound parts' scratch (`cuda/projection/momentum.rs`, `cuda/projection/rebound.rs`).

use burn_cubecl::cubecl;
use cubecl::prelude::*;

/// The call's arrays. `frames` `[K B N 4]` (projected in place), `net` the network's frames,
/// `before` `[B N 4]` the frame being projected as it came in; `list` `[B nodes]`: each
/// scene's full nodes, red from the front, black from the back; `input` `[B N 4]` the call's
/// input frames and `prev` `[B N 4]` the frame before the one being projected; `parent`,
/// `sorted`, `cellof`, `sums` and `free` the momentum part's (`cuda/projection/momentum.rs`); `events`
/// the rebound part's contacts in progress (`ProjectionPlan::events`).
#[derive(CubeLaunch, CubeType)]
pub(in crate::ops) struct Buffers {
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
    pub input: Array<f32>,
    pub prev: Array<f32>,
    pub parent: Array<Atomic<u32>>,
    pub sorted: Array<u32>,
    pub cellof: Array<u32>,
    pub sums: Array<Atomic<i64>>,
    pub free: Array<Atomic<u32>>,
    pub events: Array<f32>,
}

/// Value `i` of the frame before (`which` 0: `prev`) or of the predicted frames (1:
/// `frames`).
#[cube]
pub(in crate::ops) fn read(b: &Buffers, which: u32, i: usize) -> f32 {
    let mut v = b.frames[i];
    if which == 0 {
        v = b.prev[i];
    }
    v
}
