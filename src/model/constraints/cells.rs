//! A fixed-radius neighbour search on a uniform cell grid over the unit box (a "cell list", as
//! SPH and position-based fluid codes use; Macklin & Müller 2013, section 6): particles are
//! counting-sorted by cell once, and a query visits the 3 x 3 cells around a point. Used by the
//! constraint projection ([`super`]): the bodies found in a scene's rest frame and each
//! material's particle spacing (`shape.rs`), and the pairs of bodies that come close
//! (`contact.rs`).

/// Particles of one scene sorted by the cell of a grid of `cells` x `cells` cells over the
/// unit box (positions outside it fall in the border cells).
pub struct CellList {
    cells: usize,
    /// `[cells^2 + 1]`: where each cell's particles start in `order`.
    start: Vec<u32>,
    /// Particle indices, cell by cell.
    order: Vec<u32>,
}

impl CellList {
    /// The particles `ids` at positions `pos` (`[N, stride]` rows whose first two values are
    /// x and y, domain units), binned in cells of side at least `radius` (at most 256 per
    /// side), so that every particle within `radius` of a point lies in its 3 x 3 block.
    pub fn new(pos: &[f32], stride: usize, ids: &[u32], radius: f32) -> Self {
        let cells = ((1.0 / radius.max(1e-6)).floor() as usize).clamp(1, 256);
        let mut count = vec![0u32; cells * cells + 1];
        let keys: Vec<usize> = ids
            .iter()
            .map(|&i| {
                Self::key(
                    cells,
                    pos[stride * i as usize],
                    pos[stride * i as usize + 1],
                )
            })
            .collect();
        for &k in &keys {
            count[k + 1] += 1;
        }
        for c in 0..cells * cells {
            count[c + 1] += count[c];
        }
        let mut fill = count.clone();
        let mut order = vec![0u32; ids.len()];
        for (&k, &i) in keys.iter().zip(ids) {
            order[fill[k] as usize] = i;
            fill[k] += 1;
        }
        Self {
            cells,
            start: count,
            order,
        }
    }

    fn cell(cells: usize, x: f32) -> usize {
        ((x * cells as f32).floor().max(0.0) as usize).min(cells - 1)
    }

    fn key(cells: usize, x: f32, y: f32) -> usize {
        Self::cell(cells, x) * cells + Self::cell(cells, y)
    }

    /// Calls `visit(j)` for every binned particle in the 3 x 3 cells around `(x, y)`, cell by
    /// cell in a fixed order (deterministic).
    pub fn around(&self, x: f32, y: f32, mut visit: impl FnMut(usize)) {
        let g = self.cells as i64;
        let (cx, cy) = (
            Self::cell(self.cells, x) as i64,
            Self::cell(self.cells, y) as i64,
        );
        for gx in (cx - 1).max(0)..=(cx + 1).min(g - 1) {
            for gy in (cy - 1).max(0)..=(cy + 1).min(g - 1) {
                let c = (gx * g + gy) as usize;
                for &j in &self.order[self.start[c] as usize..self.start[c + 1] as usize] {
                    visit(j as usize);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_every_particle_within_the_radius_and_only_binned_ones() {
        // A 20 x 20 lattice of spacing 0.05; particle 0 at (0, 0) left out of the list.
        let pos: Vec<f32> = (0..400)
            .flat_map(|i| [(i / 20) as f32 * 0.05, (i % 20) as f32 * 0.05])
            .collect();
        let ids: Vec<u32> = (1..400).collect();
        let list = CellList::new(&pos, 2, &ids, 0.12);
        let (x, y) = (0.5, 0.5);
        let mut got = Vec::new();
        list.around(x, y, |j| {
            let d = (pos[2 * j] - x).hypot(pos[2 * j + 1] - y);
            if d <= 0.12 {
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
