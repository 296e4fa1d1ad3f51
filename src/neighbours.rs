//! The one neighbour search over a scene's particles: a cell list (as SPH and position-based
//! fluid codes use; Macklin & Müller 2013, section 6). [`Bins`] counting-sorts particles,
//! given by index into `[N, stride]` rows whose first two values are x and y (domain units;
//! the unit box, positions outside it falling in its border cells), by the cell of a uniform
//! grid over the unit box, once; a query then reads whole cells:
//!
//! - [`Bins::around`]: every binned particle in the 3 x 3 cells around a point, a
//!   fixed-radius search where the cells are at least the radius wide ([`Bins::for_radius`]);
//! - [`Bins::nearest`]: the `k` nearest binned particles of a point by a caller's distance,
//!   nearest first, found by searching rings of cells outwards until the `k`-th nearest so
//!   far is no farther than the searched rings reach. The same neighbours as a brute-force
//!   sort of every binned particle, up to particles at exactly equal distance: of those, the
//!   one met first comes first (ring by ring outwards, a ring's cells by x then y index, a
//!   cell's particles in the order `ids` gave them).
//!
//! [`Components`] joins particles into connected sets over these searches.
//!
//! Used, each for same-material neighbours in a frame, by `eval`'s rest neighbours
//! (`eval::structure::Neighbours`: strain error, intact fraction, rope connectivity) and
//! the grid model's rest neighbourhoods (`model::grid::rest`: `train`, `eval`, `node`), both
//! the 8 nearest (`model::grid::rest::REST_NEIGHBOURS`), and the constraint projection
//! (`model::constraints`: the particle spacing from the 8-th nearest within 1/64 of the
//! box, bodies and contacts as fixed-radius searches).

mod components;

pub use components::Components;

/// Particles of one scene sorted by the cell of a `cells` x `cells` grid over the unit box
/// (see the module doc).
#[derive(Debug, Clone)]
pub struct Bins {
    cells: usize,
    /// `[cells^2 + 1]`: where each cell's particles start in `order` (cell `gx cells + gy`).
    start: Vec<u32>,
    /// Particle indices, cell by cell, each cell's in the order of `ids`.
    order: Vec<u32>,
}

impl Bins {
    /// The particles `ids` of `pos` (`[N, stride]` rows, x and y first, domain units) on a
    /// `cells` x `cells` grid (at least 1). [`Self::nearest`] is exact (up to ties) for a
    /// power of two, whose cell edges `x * cells` hits without rounding.
    pub fn new(pos: &[f32], stride: usize, ids: &[u32], cells: usize) -> Self {
        let cells = cells.max(1);
        let keys: Vec<usize> = ids
            .iter()
            .map(|&i| {
                let row = &pos[stride * i as usize..];
                cell(cells, row[0]) * cells + cell(cells, row[1])
            })
            .collect();
        let mut start = vec![0u32; cells * cells + 1];
        for &k in &keys {
            start[k + 1] += 1;
        }
        for c in 0..cells * cells {
            start[c + 1] += start[c];
        }
        let mut fill = start.clone();
        let mut order = vec![0u32; ids.len()];
        for (&k, &i) in keys.iter().zip(ids) {
            order[fill[k] as usize] = i;
            fill[k] += 1;
        }
        Self {
            cells,
            start,
            order,
        }
    }

    /// [`Self::new`] with cells of side at least `radius` (at most 256 per side), so that
    /// every particle within `radius` of a point lies in its 3 x 3 block ([`Self::around`]).
    pub fn for_radius(pos: &[f32], stride: usize, ids: &[u32], radius: f32) -> Self {
        let cells = ((1.0 / radius.max(1e-6)).floor() as usize).clamp(1, 256);
        Self::new(pos, stride, ids, cells)
    }

    /// Calls `visit(j)` for every binned particle in the 3 x 3 cells around `(x, y)`, cell by
    /// cell in a fixed order (x index, then y index; deterministic).
    pub fn around(&self, x: f32, y: f32, mut visit: impl FnMut(usize)) {
        let g = self.cells as i64;
        let (cx, cy) = (cell(self.cells, x) as i64, cell(self.cells, y) as i64);
        for gx in (cx - 1).max(0)..=(cx + 1).min(g - 1) {
            let (low, high) = ((cy - 1).max(0), (cy + 1).min(g - 1));
            self.run(gx, low, high, &mut |from, to| {
                self.visit(from, to, &mut visit)
            });
        }
    }

    /// The (at most) `k` nearest binned particles of `(x, y)` within `reach`, nearest first,
    /// into `near` as `(distance, index)`: `distance(j)` is particle `j`'s distance (domain
    /// units, not NaN), or `None` to leave `j` out (the particle itself, another material,
    /// a duplicate at distance 0). Rings of cells around `(x, y)`'s are searched outwards
    /// until the `k`-th nearest found is within the rings' reach (`r` rings reach `r / cells`:
    /// every particle that near has been met), the rings reach `reach` (`f64::INFINITY`: no
    /// limit), or they cover the grid. Ties: the particle met first first (module doc).
    pub fn nearest(
        &self,
        [x, y]: [f32; 2],
        k: usize,
        reach: f64,
        mut distance: impl FnMut(usize) -> Option<f64>,
        near: &mut Vec<(f64, usize)>,
    ) {
        near.clear();
        if k == 0 {
            return;
        }
        for r in 0.. {
            let seen = self.ring_around([x, y], r, |j| {
                if let Some(d) = distance(j) {
                    keep_nearest(near, k, (d, j));
                }
            });
            let Some(seen) = seen else { break };
            if seen >= reach || (near.len() == k && near[k - 1].0 <= seen) {
                break;
            }
        }
        let inside = near.partition_point(|&(d, _)| d <= reach);
        near.truncate(inside);
    }

    /// Calls `visit(j)` for the binned particles of ring `r` around `(x, y)`'s cell (the
    /// cells at Chebyshev distance `r`); returns the distance within which rings `0..=r` have
    /// met every particle (`r / cells`, domain units), or `None` when they cover the grid.
    /// Searching ring by ring outwards finds what lies near a point at any density (cells of
    /// a fixed size would hold ever more particles).
    pub fn ring_around(
        &self,
        [x, y]: [f32; 2],
        r: i64,
        mut visit: impl FnMut(usize),
    ) -> Option<f64> {
        self.ring_spans([x, y], r, |from, to| self.visit(from, to, &mut visit))
    }

    /// [`Self::ring_around`] handing out the ring's particles as runs of positions in
    /// [`Self::order`] (`spans(from, to)`: `order[from..to]`, in the order `ring_around`
    /// visits them), for callers that keep the particles' data packed in that order.
    pub fn ring_spans(
        &self,
        [x, y]: [f32; 2],
        r: i64,
        mut spans: impl FnMut(usize, usize),
    ) -> Option<f64> {
        let g = self.cells as i64;
        let (cx, cy) = (cell(self.cells, x) as i64, cell(self.cells, y) as i64);
        self.ring_runs(cx, cy, r, &mut spans);
        let whole = cx - r <= 0 && cy - r <= 0 && cx + r >= g - 1 && cy + r >= g - 1;
        (!whole).then(|| r as f64 / self.cells as f64)
    }

    /// The binned particles' indices, cell by cell (cell `gx cells + gy`), each cell's in the
    /// order of `ids`.
    pub fn order(&self) -> &[u32] {
        &self.order
    }

    /// Calls `visit(j)` for each particle of `order[from..to]`.
    fn visit(&self, from: usize, to: usize, visit: &mut impl FnMut(usize)) {
        for &j in &self.order[from..to] {
            visit(j as usize);
        }
    }

    /// How many cells hold a binned particle.
    pub fn occupied(&self) -> usize {
        self.start.windows(2).filter(|w| w[1] > w[0]).count()
    }

    /// The runs of [`Self::order`] that make up ring `r` around cell `(cx, cy)` (the cells at
    /// Chebyshev distance `r`), by x index, then y index.
    fn ring_runs(&self, cx: i64, cy: i64, r: i64, spans: &mut impl FnMut(usize, usize)) {
        let g = self.cells as i64;
        let (low, high) = ((cy - r).max(0), (cy + r).min(g - 1));
        for gx in (cx - r).max(0)..=(cx + r).min(g - 1) {
            if (gx - cx).abs() == r {
                self.run(gx, low, high, spans);
            } else {
                if cy - r >= 0 {
                    self.run(gx, cy - r, cy - r, spans);
                }
                if cy + r < g {
                    self.run(gx, cy + r, cy + r, spans);
                }
            }
        }
    }

    /// The binned particles of cell `c` (`gx cells + gy`), in the order of `ids`.
    fn cell(&self, c: usize) -> &[u32] {
        &self.order[self.start[c] as usize..self.start[c + 1] as usize]
    }

    /// Each cell's bounding box of its particles, `[x_min, y_min, x_max, y_max]` (an empty
    /// cell's is inverted, infinite).
    fn boxes(&self, pos: &[f32], stride: usize) -> Vec<[f32; 4]> {
        (0..self.cells * self.cells)
            .map(|c| {
                let init = [
                    f32::INFINITY,
                    f32::INFINITY,
                    f32::NEG_INFINITY,
                    f32::NEG_INFINITY,
                ];
                self.cell(c).iter().fold(init, |b, &i| {
                    let row = &pos[stride * i as usize..];
                    [
                        b[0].min(row[0]),
                        b[1].min(row[1]),
                        b[2].max(row[0]),
                        b[3].max(row[1]),
                    ]
                })
            })
            .collect()
    }

    /// The run of [`Self::order`] that holds cells `(gx, low..=high)`, as `spans(from, to)`:
    /// the cells of one x index are consecutive.
    fn run(&self, gx: i64, low: i64, high: i64, spans: &mut impl FnMut(usize, usize)) {
        let c = (gx * self.cells as i64) as usize;
        let from = self.start[c + low as usize] as usize;
        let to = self.start[c + high as usize + 1] as usize;
        if to > from {
            spans(from, to);
        }
    }
}

/// The cell of coordinate `x` on a grid of `cells` per side (border cells beyond the box).
fn cell(cells: usize, x: f32) -> usize {
    ((x * cells as f32).floor().max(0.0) as usize).min(cells - 1)
}

/// Inserts `found` into `near` (at most `k`, by distance, a tie after those already there).
fn keep_nearest(near: &mut Vec<(f64, usize)>, k: usize, found: (f64, usize)) {
    if near.len() == k && near[k - 1].0 <= found.0 {
        return;
    }
    let at = near.partition_point(|&(d, _)| d <= found.0);
    if near.len() == k {
        near.pop();
    }
    near.insert(at, found);
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// `n` particles `[N, 2]` (half on a `sites` x `sites` lattice of spacing 1/128, with
    /// equal distances by the dozen and duplicated points; half uniform in and a little
    /// outside the box) and their materials 0..3.
    pub(super) fn cloud(n: usize, sites: u32, seed: u64) -> (Vec<f32>, Vec<u8>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let pos = (0..n)
            .flat_map(|i| {
                if i % 2 == 0 {
                    let l = (rng.random_range(0..sites), rng.random_range(0..sites));
                    [0.3 + l.0 as f32 / 128.0, 0.3 + l.1 as f32 / 128.0]
                } else {
                    [rng.random_range(-0.05..1.05), rng.random_range(-0.05..1.05)]
                }
            })
            .collect();
        let material = (0..n).map(|_| rng.random_range(0..3u8)).collect();
        (pos, material)
    }

    /// A distance between particles `i` and `j` of `[N, 2]` positions.
    type Metric = fn(&[f32], usize, usize) -> f64;

    /// The grid model's and the constraints' distance: f32, widened.
    fn in_f32(pos: &[f32], i: usize, j: usize) -> f64 {
        f64::from((pos[2 * j] - pos[2 * i]).hypot(pos[2 * j + 1] - pos[2 * i + 1]))
    }

    /// `eval`'s distance: of the positions widened to f64.
    fn in_f64(pos: &[f32], i: usize, j: usize) -> f64 {
        let at = |i: usize, c: usize| f64::from(pos[2 * i + c]);
        (at(j, 0) - at(i, 0)).hypot(at(j, 1) - at(i, 1))
    }

    /// Particle `i`'s `k` nearest above 0 in `bins` by `metric` (its own material's bins).
    fn search(
        bins: &Bins,
        pos: &[f32],
        i: usize,
        k: usize,
        reach: f64,
        metric: Metric,
    ) -> Vec<(f64, usize)> {
        let mut near = Vec::new();
        let p = [pos[2 * i], pos[2 * i + 1]];
        let distance = |j: usize| Some(metric(pos, i, j)).filter(|&d| j != i && d > 0.0);
        bins.nearest(p, k, reach, distance, &mut near);
        near
    }

    /// The `k` nearest above 0 of particle `i` among those of its material by sorting them
    /// all: by distance, ties in the order the ring search meets them (its ring, cell x,
    /// cell y, index: `ids` are in increasing order).
    fn brute(
        pos: &[f32],
        mat: &[u8],
        i: usize,
        k: usize,
        cells: usize,
        metric: Metric,
    ) -> Vec<(f64, usize)> {
        let key = |j: usize| {
            let c = |v: f32| cell(cells, v) as i64;
            let (ci, cj) = (
                [c(pos[2 * i]), c(pos[2 * i + 1])],
                [c(pos[2 * j]), c(pos[2 * j + 1])],
            );
            let ring = (ci[0] - cj[0]).abs().max((ci[1] - cj[1]).abs());
            (ring, cj[0], cj[1], j)
        };
        let mut all: Vec<(f64, usize)> = (0..mat.len())
            .filter(|&j| j != i && mat[j] == mat[i])
            .map(|j| (metric(pos, i, j), j))
            .filter(|&(d, _)| d > 0.0)
            .collect();
        all.sort_by(|a, b| a.0.total_cmp(&b.0).then(key(a.1).cmp(&key(b.1))));
        all.truncate(k);
        all
    }

    /// The ring search gives a brute-force sort's neighbours, ties in its documented order,
    /// for every particle of a cloud with ties, duplicates, points outside the box and three
    /// materials, on grids of 1, 8, 64 cells per side, for k of 1, 6 and 8, in f32 and f64.
    #[test]
    fn nearest_matches_brute_force() {
        let (pos, mat) = cloud(1500, 40, 45);
        let mut ties = 0;
        for cells in [1, 8, 64] {
            let bins: Vec<Bins> = (0..3u8)
                .map(|m| {
                    let ids: Vec<u32> = (0..1500).filter(|&i| mat[i as usize] == m).collect();
                    Bins::new(&pos, 2, &ids, cells)
                })
                .collect();
            for i in 0..mat.len() {
                for (k, metric) in [(1, in_f32 as Metric), (6, in_f64), (8, in_f32), (8, in_f64)] {
                    let near = search(&bins[mat[i] as usize], &pos, i, k, f64::INFINITY, metric);
                    let want = brute(&pos, &mat, i, k + 1, cells, metric);
                    ties += usize::from(want.len() > k && want[k].0 == want[k - 1].0);
                    assert_eq!(near, want[..want.len().min(k)], "{cells} cells, {i}, k {k}");
                }
            }
        }
        assert!(ties > 100, "ties at the k-th: {ties}");
    }

    /// Within a reach the search returns the brute force's neighbours that are within it.
    #[test]
    fn nearest_within_a_reach() {
        let (pos, mat) = cloud(800, 12, 7);
        let ids: Vec<u32> = (0..800).filter(|&i| mat[i as usize] == 1).collect();
        let bins = Bins::new(&pos, 2, &ids, 64);
        let (reach, mut short) = (1.0 / 64.0, 0);
        for &i in &ids {
            let near = search(&bins, &pos, i as usize, 8, reach, in_f32);
            let mut want = brute(&pos, &mat, i as usize, 8, 64, in_f32);
            want.retain(|&(d, _)| d <= reach);
            short += usize::from(want.len() < 8);
            assert_eq!(near, want, "particle {i}");
        }
        assert!(short > 0 && short < ids.len(), "both cases: {short}");
    }

    /// `around` visits every binned particle within the radius, and only binned ones.
    #[test]
    fn around_finds_every_particle_within_the_radius_and_only_binned_ones() {
        // A 20 x 20 lattice of spacing 0.05; particle 0 at (0, 0) left out of the bins.
        let pos: Vec<f32> = (0..400)
            .flat_map(|i| [(i / 20) as f32 * 0.05, (i % 20) as f32 * 0.05])
            .collect();
        let ids: Vec<u32> = (1..400).collect();
        let bins = Bins::for_radius(&pos, 2, &ids, 0.12);
        for (x, y) in [(0.5, 0.5), (0.0, 0.0), (0.97, 0.02)] {
            let mut got = Vec::new();
            bins.around(x, y, |j| {
                if (pos[2 * j] - x).hypot(pos[2 * j + 1] - y) <= 0.12 {
                    got.push(j);
                }
            });
            got.sort_unstable();
            let want: Vec<usize> = (1..400)
                .filter(|&j| (pos[2 * j] - x).hypot(pos[2 * j + 1] - y) <= 0.12)
                .collect();
            assert_eq!(got, want);
            assert!(!want.is_empty());
        }
    }
}
