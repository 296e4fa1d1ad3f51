//! Structure of a predicted frame, per material: what a user sees in a render and the MSE
//! hides (docs/design.md, "Metrics").
//!
//! - [`covered_area`]: the area a material covers, as the number of cells of a fixed
//!   [`AREA_GRID`] x [`AREA_GRID`] grid over the unit box that hold at least one of its
//!   particles. Prediction over truth is the volume ratio: 1 when the material keeps its
//!   volume, below 1 when it is pressed together, above when it is spread apart. (MPM's
//!   liquid keeps its volume through `J = det F`; a surrogate that presses the liquid into a
//!   layer covers fewer cells.)
//! - [`Neighbours::intact_fraction`]: the share of the rest-neighbour pairs of a solid (each
//!   particle's [`REST_NEIGHBOURS`] nearest of the same material in the
//!   rollout's first frame) still within [`INTACT_STRETCH`] times their rest distance: 1 for a
//!   body in one piece, lower where it is torn or crumpled. The truth's own value stands
//!   beside the prediction's (snow fractures in the truth too).
//! - [`Neighbours::connected_share`]: the share of a material's particles in the largest
//!   piece of the graph whose edges are the intact rest-neighbour pairs ([`Components`]): 1 for
//!   one rope, 0.5 for a rope cut in two halves.
//!
//! [`Neighbours`] (each solid particle's nearest neighbours in the rollout's first frame, by
//! the cell-bin search of [`crate::neighbours`]) lives here whole, with the strain error of
//! [`super::plausibility`]. Used by [`super::plausibility::Plausibility::of`].

use super::metrics::MATERIALS;
use crate::model::grid::rest::REST_NEIGHBOURS;
use crate::neighbours::{Bins, Components};

/// Cells per side of [`Neighbours::new`]'s search grid: 1/64 of the box, a few particles of
/// a body per cell.
const SEARCH_CELLS: usize = 64;

/// Cells per side of the grid [`covered_area`] counts on: 1/64 of the box, the `multi`
/// family's MPM cell (docs/mpm.md, "Scene families"); a body of 2,500 particles spans
/// hundreds of them.
pub const AREA_GRID: usize = 64;

/// A rest-neighbour pair is intact while its distance is at most this many times its rest
/// distance.
pub const INTACT_STRETCH: f64 = 1.5;

/// The number of [`AREA_GRID`] cells holding at least one particle `i` with `keep(i)`, of
/// `state` (`[N, 4]` physical; positions outside the box count in its border cells).
pub fn covered_area(state: &[f32], keep: impl Fn(usize) -> bool) -> usize {
    let g = AREA_GRID;
    let mut hit = vec![false; g * g];
    let cell = |x: f32| ((x * g as f32).floor().max(0.0) as usize).min(g - 1);
    for (i, row) in state.chunks_exact(4).enumerate() {
        if keep(i) {
            hit[cell(row[0]) * g + cell(row[1])] = true;
        }
    }
    hit.iter().filter(|&&h| h).count()
}

impl Neighbours {
    /// The rest-neighbour pairs of material `m`'s particles as `(i, j, intact)` in `state`
    /// (`[N, 4]` physical): intact when `|x_i - x_j| <= INTACT_STRETCH d_0`.
    fn pairs_in<'a>(
        &'a self,
        state: &'a [f32],
        m: usize,
    ) -> impl Iterator<Item = (usize, usize, bool)> + 'a {
        self.of()
            .iter()
            .enumerate()
            .filter(move |&(i, _)| self.material_of(i) == m)
            .flat_map(move |(i, near)| {
                near.iter().map(move |&(j, d0)| {
                    let (dx, dy) = (
                        state[4 * i] - state[4 * j],
                        state[4 * i + 1] - state[4 * j + 1],
                    );
                    (
                        i,
                        j,
                        f64::from(dx).hypot(f64::from(dy)) <= INTACT_STRETCH * d0,
                    )
                })
            })
    }

    /// The share of material `m`'s rest-neighbour pairs intact in `state` (see the module
    /// doc), in `[0, 1]`; `None` for liquid (`m = 0`) or a material without pairs.
    pub fn intact_fraction(&self, state: &[f32], m: usize) -> Option<f64> {
        if m == 0 {
            return None;
        }
        let (mut intact, mut all) = (0usize, 0usize);
        for (_, _, ok) in self.pairs_in(state, m) {
            all += 1;
            intact += usize::from(ok);
        }
        (all > 0).then(|| intact as f64 / all as f64)
    }

    /// The share of material `m`'s particles in the largest piece held together by intact
    /// rest-neighbour pairs in `state` (see the module doc), in `(0, 1]`; `None` for liquid or
    /// a material without pairs.
    pub fn connected_share(&self, state: &[f32], m: usize) -> Option<f64> {
        if m == 0 {
            return None;
        }
        let mut pieces = Components::new(self.of().len());
        let mut any = false;
        for (i, j, ok) in self.pairs_in(state, m) {
            any = true;
            if ok {
                pieces.join(i, j);
            }
        }
        let members: Vec<usize> = (0..self.of().len())
            .filter(|&i| self.material_of(i) == m)
            .collect();
        if !any || members.is_empty() {
            return None;
        }
        let mut count = std::collections::HashMap::<usize, usize>::new();
        for &i in &members {
            *count.entry(pieces.root(i)).or_default() += 1;
        }
        let largest = count.values().copied().max().unwrap_or(0);
        Some(largest as f64 / members.len() as f64)
    }
}

/// Each solid particle's [`REST_NEIGHBOURS`] nearest neighbours of the same material in a reference
/// frame (the rollout's first), and their distances there, nearest first.
#[derive(Debug, Clone, Default)]
pub struct Neighbours {
    /// Per particle: `(neighbour index, reference distance)`, nearest first; empty for liquid
    /// particles.
    of: Vec<Vec<(usize, f64)>>,
    /// Material id per particle (clamped to `MATERIALS - 1`).
    material: Vec<usize>,
}

impl Neighbours {
    /// The neighbours in `frame` (`[N, 4]` physical) of every particle of a solid material
    /// (jelly 1, snow 2, rope 3), among the particles of its own material at a distance above
    /// 0, nearest first: a cell-bin search per material ([`crate::neighbours::Bins`], cells
    /// of 1/64 of the box), once per rollout. Of particles at equal distance the one the
    /// search meets first is taken (see [`crate::neighbours`]).
    pub fn new(frame: &[f32], material: &[u8]) -> Self {
        let n = material.len();
        let material: Vec<usize> = material
            .iter()
            .map(|&m| usize::from(m).min(MATERIALS - 1))
            .collect();
        let pos = |i: usize| [f64::from(frame[4 * i]), f64::from(frame[4 * i + 1])];
        let mut of = vec![Vec::new(); n];
        let mut near = Vec::with_capacity(REST_NEIGHBOURS);
        for m in 1..MATERIALS {
            let ids: Vec<u32> = (0..n as u32)
                .filter(|&i| material[i as usize] == m)
                .collect();
            let bins = Bins::new(frame, 4, &ids, SEARCH_CELLS);
            for &i in &ids {
                let i = i as usize;
                let p = pos(i);
                let distance = |j: usize| {
                    let q = pos(j);
                    Some((p[0] - q[0]).hypot(p[1] - q[1])).filter(|&d| j != i && d > 0.0)
                };
                bins.nearest(
                    [frame[4 * i], frame[4 * i + 1]],
                    REST_NEIGHBOURS,
                    f64::INFINITY,
                    distance,
                    &mut near,
                );
                of[i] = near.iter().map(|&(d, j)| (j, d)).collect();
            }
        }
        Self { of, material }
    }

    /// Per particle: `(neighbour index, reference distance)`; empty for liquid particles.
    pub(super) fn of(&self) -> &[Vec<(usize, f64)>] {
        &self.of
    }

    /// Material id of particle `i` (clamped to `MATERIALS - 1`).
    pub(super) fn material_of(&self, i: usize) -> usize {
        self.material[i]
    }

    /// The strain error of material `m` (see the module doc): the mean over its particles
    /// and their neighbours of `|d_pred / d_0 - d_true / d_0|`; `None` for liquid or a
    /// material without neighbour pairs.
    pub fn strain_error(&self, pred: &[f32], truth: &[f32], m: usize) -> Option<f64> {
        if m == 0 {
            return None;
        }
        let dist = |s: &[f32], i: usize, j: usize| {
            let (dx, dy) = (s[4 * i] - s[4 * j], s[4 * i + 1] - s[4 * j + 1]);
            f64::from(dx).hypot(f64::from(dy))
        };
        let (mut sum, mut count) = (0.0, 0usize);
        for (i, near) in self.of.iter().enumerate() {
            if self.material[i] != m {
                continue;
            }
            for &(j, d0) in near {
                sum += (dist(pred, i, j) - dist(truth, i, j)).abs() / d0;
                count += 1;
            }
        }
        (count > 0).then(|| sum / count as f64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A rope of 20 particles 0.01 apart along x.
    fn rope() -> (Vec<f32>, Vec<u8>) {
        let frame = (0..20)
            .flat_map(|i| [0.3 + 0.01 * i as f32, 0.5, 0.0, 0.0])
            .collect();
        (frame, vec![3u8; 20])
    }

    /// Moved rigidly the rope is whole (intact 1, one piece); cut in the middle (the right
    /// half shifted 0.1 away) it is two pieces of 10 and only the pairs across the cut break.
    #[test]
    fn a_cut_rope_is_two_pieces() {
        let (frame, material) = rope();
        let nb = Neighbours::new(&frame, &material);
        let moved: Vec<f32> = frame
            .chunks_exact(4)
            .flat_map(|r| [r[1], r[0], 0.0, 0.0])
            .collect();
        assert_eq!(nb.intact_fraction(&moved, 3), Some(1.0));
        assert_eq!(nb.connected_share(&moved, 3), Some(1.0));
        let cut: Vec<f32> = frame
            .chunks_exact(4)
            .enumerate()
            .flat_map(|(i, r)| [r[0] + if i >= 10 { 0.1 } else { 0.0 }, r[1], 0.0, 0.0])
            .collect();
        assert_eq!(nb.connected_share(&cut, 3), Some(0.5));
        let intact = nb.intact_fraction(&cut, 3).unwrap();
        assert!(intact > 0.5 && intact < 1.0, "{intact}");
        assert_eq!(nb.intact_fraction(&frame, 0), None, "liquid has no pairs");
    }

    /// A 16 x 16 block of particles 1/128 apart covers 8 x 8 cells of 1/64; pressed to half
    /// its height it covers half of them.
    #[test]
    fn a_pressed_block_covers_less_area() {
        let block: Vec<f32> = (0..256)
            .flat_map(|i| {
                let (a, b) = ((i % 16) as f32, (i / 16) as f32);
                [0.25 + (a + 0.5) / 128.0, 0.25 + (b + 0.5) / 128.0, 0.0, 0.0]
            })
            .collect();
        let pressed: Vec<f32> = block
            .chunks_exact(4)
            .flat_map(|r| [r[0], 0.25 + 0.5 * (r[1] - 0.25), 0.0, 0.0])
            .collect();
        assert_eq!(covered_area(&block, |_| true), 64);
        assert_eq!(covered_area(&pressed, |_| true), 32);
        assert_eq!(covered_area(&block, |i| i < 16), 8, "one row of particles");
    }
}
