//! Connected sets of particles: [`Components`], union-find over particle indices, and its
//! fixed-radius joins over the cell list of [`super::Bins`] (the constraint projection's
//! bodies and momentum clusters, `eval`'s connected share).

use super::Bins;

/// Union-find over particle indices `0..n` (path halving). A union makes the lower of the two
/// roots the root, so each set's root is its lowest index and [`Components::groups`] comes out
/// in index order. The connected pieces of the constraint projection's bodies, its momentum
/// clusters and `eval`'s connected share are its sets.
#[derive(Debug, Clone)]
pub struct Components {
    parent: Vec<u32>,
}

impl Components {
    /// `n` particles, each its own set.
    pub fn new(n: usize) -> Self {
        Self {
            parent: (0..n as u32).collect(),
        }
    }

    /// The root (lowest index) of `i`'s set.
    pub fn root(&mut self, i: usize) -> usize {
        let mut i = i as u32;
        while self.parent[i as usize] != i {
            self.parent[i as usize] = self.parent[self.parent[i as usize] as usize];
            i = self.parent[i as usize];
        }
        i as usize
    }

    /// Joins the sets of `a` and `b`.
    pub fn join(&mut self, a: usize, b: usize) {
        let (a, b) = (self.root(a), self.root(b));
        self.parent[a.max(b)] = a.min(b) as u32;
    }

    /// Joins every two particles of `ids` no farther than `radius` apart in `pos` (`[N,
    /// stride]` rows, x and y first, domain units): the connected pieces of that graph.
    ///
    /// The cell-list form of grid-based DBSCAN (Gunawan 2013, "A faster algorithm for
    /// DBSCAN", section 3): on cells of side below `radius / sqrt(2)` the particles of one
    /// cell are all within `radius` of each other and join without a test; two cells up to 2
    /// apart are tested pair by pair only until one pair joins them, and not at all when they
    /// are joined already. The same sets as testing every pair (`hypot <= radius`); cells that
    /// hold particles outside the box (its border cells) test every pair.
    pub fn join_within(&mut self, pos: &[f32], stride: usize, ids: &[u32], radius: f32) {
        let cells = (std::f32::consts::SQRT_2 * 1.001 / radius.max(1e-6)).ceil() as usize;
        let bins = Bins::new(pos, stride, ids, cells.clamp(1, 1024));
        // `hypot <= radius`, its libm call made only where the squared distance is within
        // 1e-4 of radius^2 (the squares' rounding is far below that).
        let (below, above) = (
            radius * radius * (1.0 - 1e-4),
            radius * radius * (1.0 + 1e-4),
        );
        let near = |i: usize, j: usize| {
            let (a, b) = (&pos[stride * i..], &pos[stride * j..]);
            let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
            let d2 = dx * dx + dy * dy;
            d2 < below || (d2 <= above && dx.hypot(dy) <= radius)
        };
        let g = bins.cells;
        let inside = |i: u32| {
            let row = &pos[stride * i as usize..];
            (0.0..1.0).contains(&row[0]) && (0.0..1.0).contains(&row[1])
        };
        // A cell is whole when its particles are joined to each other by the rule above.
        let whole: Vec<bool> = (0..g * g)
            .map(|c| cells <= 1024 && bins.cell(c).iter().all(|&i| inside(i)))
            .collect();
        let boxes = bins.boxes(pos, stride);
        let occupied: Vec<usize> = (0..g * g).filter(|&c| !bins.cell(c).is_empty()).collect();
        for &c in &occupied {
            let here = bins.cell(c);
            if whole[c] {
                here[1..]
                    .iter()
                    .for_each(|&j| self.join(here[0] as usize, j as usize));
            } else {
                self.join_pairs(here, here, true, &near);
            }
        }
        // Cells are at least radius / 2 wide: a pair within radius is at most 2 apart. The
        // adjacent cells first: where they join a region, the farther ones need no test.
        for ring in 1..=2 {
            for &c in &occupied {
                let (cx, cy) = ((c / g) as i64, (c % g) as i64);
                for (dx, dy) in (0..=2).flat_map(|dx| (-2..=2i64).map(move |dy| (dx, dy))) {
                    let (ox, oy) = (cx + dx, cy + dy);
                    let outside = ox >= g as i64 || oy < 0 || oy >= g as i64;
                    if (dx == 0 && dy <= 0) || dx.max(dy.abs()) != ring || outside {
                        continue;
                    }
                    let d = ox as usize * g + oy as usize;
                    let (here, there) = (bins.cell(c), bins.cell(d));
                    if there.is_empty() {
                        continue;
                    }
                    let both = whole[c] && whole[d];
                    if both && self.root(here[0] as usize) == self.root(there[0] as usize) {
                        continue;
                    }
                    // No pair can be near when the cells' bounding boxes are farther apart.
                    let (a, b) = (boxes[c], boxes[d]);
                    let gap = |lo: usize, hi: usize| (b[lo] - a[hi]).max(a[lo] - b[hi]).max(0.0);
                    if gap(0, 2).powi(2) + gap(1, 3).powi(2) <= above {
                        self.join_pairs(here, there, !both, &near);
                    }
                }
            }
        }
    }

    /// Joins the pairs of `a` x `b` that `near` accepts; after the first join when `every`
    /// is false (each side already one set).
    fn join_pairs(
        &mut self,
        a: &[u32],
        b: &[u32],
        every: bool,
        near: &impl Fn(usize, usize) -> bool,
    ) {
        for &i in a {
            for &j in b {
                let (i, j) = (i as usize, j as usize);
                if i != j && near(i, j) {
                    self.join(i, j);
                    if !every {
                        return;
                    }
                }
            }
        }
    }

    /// The sets the particles `ids` fall in, each its members in the order of `ids`, the sets
    /// in order of their roots.
    pub fn groups(&mut self, ids: &[u32]) -> Vec<Vec<u32>> {
        let mut groups: std::collections::BTreeMap<usize, Vec<u32>> = Default::default();
        for &i in ids {
            groups.entry(self.root(i as usize)).or_default().push(i);
        }
        groups.into_values().collect()
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::cloud;
    use super::*;

    /// `join_within` gives the sets of testing every pair, for a cloud with duplicates and
    /// points outside the box, at radii from below a lattice spacing to where most join.
    #[test]
    fn join_within_matches_every_pair() {
        let (pos, mat) = cloud(1200, 30, 11);
        let ids: Vec<u32> = (0..1200).filter(|&i| mat[i as usize] != 2).collect();
        for radius in [0.005f32, 1.0 / 128.0, 0.02, 0.035] {
            let mut fast = Components::new(1200);
            fast.join_within(&pos, 2, &ids, radius);
            let mut every = Components::new(1200);
            for &i in &ids {
                for &j in &ids {
                    let (i, j) = (i as usize, j as usize);
                    if (pos[2 * j] - pos[2 * i]).hypot(pos[2 * j + 1] - pos[2 * i + 1]) <= radius {
                        every.join(i, j);
                    }
                }
            }
            let (got, want) = (fast.groups(&ids), every.groups(&ids));
            assert!(
                want.len() > 1 && want.len() < ids.len(),
                "{radius}: {}",
                want.len()
            );
            assert_eq!(got, want, "radius {radius}");
        }
    }
}
