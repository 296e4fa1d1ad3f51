//! Shape matching of solid bodies (Müller, Heidelberger, Teschner & Gross 2005, "Meshless
//! Deformations Based on Shape Matching", sections 3-4): a body's particles are pulled
//! towards goal positions `g_i = G q_i + c`, with `c` their centre of mass, `q_i` their rest
//! offsets from the rest centre, and `G` the rotation `R` of the polar decomposition of
//! `A_pq = sum_i (x_i - c) q_i^T`, blended with the volume-preserving linear fit
//! `A = A_pq A_qq^-1 / sqrt(det)` by `linear` (the paper's beta). Each particle moves
//! `stiffness` of the way (alpha). The centre of mass is kept, so momentum is too. With
//! `plastic` > 0 the rest offsets take on that share of the remaining deformation each frame
//! (`q_i += plastic (R^T (x_i - c) - q_i)`): a rest shape that yields, as the solver's snow
//! does (its singular values clamped, docs/mpm.md).
//!
//! A body is a connected piece of one material in the scene's rest frame: particles closer
//! than [`LINK`] spacings are joined (union-find, [`Components`]).

use super::ShapeParams;
use crate::geometry::centre_of_mass;
use crate::neighbours::{Bins, Components};

/// Particles of one material closer than this many spacings in the rest frame belong to one
/// body.
const LINK: f32 = 2.5;

/// Nearest neighbours whose distance estimates the spacing ([`spacing_of`]).
const SPACING_NEIGHBOURS: usize = 8;

/// One body: its particles and their rest shape.
#[derive(Clone, Debug)]
pub(super) struct Body {
    /// Material id.
    pub(super) material: u8,
    ids: Vec<u32>,
    /// `[len]`: rest offsets from the rest centre of mass (domain units).
    rest: Vec<[f32; 2]>,
    /// `A_qq^-1`, row-major.
    aqq_inv: [f32; 4],
}

/// The particle spacing of material `m` in `rest` (`[N, stride]` rows): the median over its
/// particles of the distance to the [`SPACING_NEIGHBOURS`]-th nearest particle of the same
/// material times `sqrt(pi / 8)` (the spacing `s` of a uniform cloud with one particle per
/// `s^2` has 8 particles within `s sqrt(8 / pi)`). Neighbours count within 1/64 of the box;
/// 0 when the scene has none of `m` close enough. Distances are f32 `hypot`s, taken only
/// where the squared distances cannot decide ([`kth_within`]).
///
/// Each particle's neighbours are met ring of cells by ring ([`Bins::ring_spans`]) until the
/// k-th nearest so far lies well inside the rings' reach (every row it could tie with met) or
/// the reach passes 1/64: the rows [`kth_within`] decides on are those of all particles
/// within 1/64, so the result is theirs. The cells are 1/64 wide, narrower where the particles
/// crowd them ([`spacing_bins`]), so that a search meets a few dozen particles at any density;
/// their positions are packed in the cells' order and read run by run.
pub(super) fn spacing_of(rest: &[f32], stride: usize, material: &[u8], m: u8) -> f32 {
    let ids: Vec<u32> = (0..material.len() as u32)
        .filter(|&i| material[i as usize] == m)
        .collect();
    if ids.len() <= SPACING_NEIGHBOURS {
        return 0.0;
    }
    let radius = 1.0 / 64.0;
    let far = radius * radius * (1.0 + 1e-4);
    let bins = spacing_bins(rest, stride, &ids);
    let packed: Vec<[f32; 2]> = (bins.order().iter())
        .map(|&i| [rest[stride * i as usize], rest[stride * i as usize + 1]])
        .collect();
    let mut kth = Vec::with_capacity(ids.len());
    let (mut near, mut tied): (Vec<[f32; 3]>, Vec<f32>) = (Vec::new(), Vec::new());
    for (me, &[x, y]) in packed.iter().enumerate() {
        near.clear();
        for r in 0.. {
            let reach = bins.ring_spans([x, y], r, |from, to| {
                // Every row written, the count advanced only past those kept: no branch to
                // mispredict on a particle that half the time lies outside the radius.
                let mut kept = near.len();
                near.resize(kept + (to - from), [0.0; 3]);
                for (j, &[px, py]) in packed[from..to].iter().enumerate() {
                    let (dx, dy) = (px - x, py - y);
                    let d2 = dx * dx + dy * dy;
                    near[kept] = [d2, dx, dy];
                    kept += usize::from((d2 <= far) & (from + j != me));
                }
                near.truncate(kept);
            });
            // Settled: every particle within the radius met, or k rows inside the reach by
            // far more than `kth_within`'s tie band (1e-4) and f32 rounding, so every row
            // within the band of the k-th is met.
            let Some(reach) = reach else { break };
            let inside = (reach * reach / (1.0 + 1e-3)) as f32;
            if reach > radius as f64 * (1.0 + 1e-3)
                || near.iter().filter(|r| r[0] <= inside).count() >= SPACING_NEIGHBOURS
            {
                break;
            }
        }
        if let Some(d) = kth_within(&mut near, &mut tied, SPACING_NEIGHBOURS, radius) {
            kth.push(d);
        }
    }
    if kth.is_empty() {
        return 0.0;
    }
    let mid = kth.len() / 2;
    kth.select_nth_unstable_by(mid, f32::total_cmp);
    kth[mid] * (std::f32::consts::PI / SPACING_NEIGHBOURS as f32).sqrt()
}

/// The cells [`spacing_of`] searches `ids` of `rest` in: 64 a side (1/64, its radius, so two
/// rings cover it), or 128 or 256 where the occupied cells hold more than 16 or 64 particles
/// on average (a 40,000-particle scene on a 256^2 solver grid holds ~90). Powers of two, on
/// whose edges `x * cells` falls without rounding, so the rings' reach is exact.
fn spacing_bins(rest: &[f32], stride: usize, ids: &[u32]) -> Bins {
    let coarse = Bins::new(rest, stride, ids, 64);
    let crowd = ids.len() / coarse.occupied().max(1);
    match crowd {
        0..=16 => coarse,
        17..=64 => Bins::new(rest, stride, ids, 128),
        _ => Bins::new(rest, stride, ids, 256),
    }
}

/// The `k`-th smallest `hypot(dx, dy)` of `near` (`[d2, dx, dy]` rows, `d2 = dx^2 + dy^2`
/// in f32) among those no farther than `radius`, or None when fewer are (`tied`: scratch).
/// Exactly what sorting every `hypot` gives: the squared distances order the rows but where
/// two lie within 1e-4 of each other (far above their rounding), and only those rows get a
/// `hypot`.
fn kth_within(near: &mut Vec<[f32; 3]>, tied: &mut Vec<f32>, k: usize, radius: f32) -> Option<f32> {
    let hypot = |r: &[f32; 3]| r[1].hypot(r[2]);
    let inside = radius * radius * (1.0 - 1e-4);
    near.retain(|r| r[0] < inside || hypot(r) <= radius);
    if near.len() < k {
        return None;
    }
    near.select_nth_unstable_by(k - 1, |a, b| a[0].total_cmp(&b[0]));
    let t = near[k - 1][0];
    let (lo, hi) = (t * (1.0 - 1e-4), t * (1.0 + 1e-4));
    let below = near.iter().filter(|r| r[0] < lo).count();
    tied.clear();
    tied.extend(near.iter().filter(|r| (lo..=hi).contains(&r[0])).map(hypot));
    tied.sort_unstable_by(f32::total_cmp);
    tied.get(k - 1 - below).copied()
}

/// The bodies of material `m` in `rest` (`[N, stride]` rows) whose spacing is `spacing`:
/// [`pieces`] turned into shape-matching bodies.
pub(super) fn bodies(
    rest: &[f32],
    stride: usize,
    material: &[u8],
    m: u8,
    spacing: f32,
) -> Vec<Body> {
    pieces(rest, stride, material, m, spacing)
        .into_iter()
        .map(|p| Body::new(rest, stride, m, p))
        .collect()
}

/// The connected pieces of material `m` in `rest` (`[N, stride]` rows) whose spacing is
/// `spacing`: particles closer than [`LINK`] spacings are joined
/// ([`Components::join_within`]); pieces of 3 particles or more, each its particle indices in increasing
/// order, the pieces in order of their lowest index.
pub(super) fn pieces(
    rest: &[f32],
    stride: usize,
    material: &[u8],
    m: u8,
    spacing: f32,
) -> Vec<Vec<u32>> {
    let ids: Vec<u32> = (0..material.len() as u32)
        .filter(|&i| material[i as usize] == m)
        .collect();
    if ids.len() < 3 || spacing <= 0.0 {
        return Vec::new();
    }
    let mut sets = Components::new(material.len());
    sets.join_within(rest, stride, &ids, LINK * spacing);
    let mut pieces = sets.groups(&ids);
    pieces.retain(|p| p.len() >= 3);
    pieces
}

impl Body {
    /// The body's particles, in increasing order.
    pub(super) fn ids(&self) -> &[u32] {
        &self.ids
    }

    /// The body's rest offsets from its rest centre (domain units, `[len]`) and `A_qq^-1`
    /// (row-major).
    pub(super) fn rest_shape(&self) -> (&[[f32; 2]], [f32; 4]) {
        (&self.rest, self.aqq_inv)
    }

    fn new(rest: &[f32], stride: usize, material: u8, ids: Vec<u32>) -> Self {
        let at = |i: u32| [rest[stride * i as usize], rest[stride * i as usize + 1]];
        let c = centre_of_mass(rest, stride, &ids).map(|c| c as f32);
        let rest: Vec<[f32; 2]> = ids
            .iter()
            .map(|&i| {
                let p = at(i);
                [p[0] - c[0], p[1] - c[1]]
            })
            .collect();
        let mut body = Self {
            material,
            ids,
            rest,
            aqq_inv: [0.0; 4],
        };
        body.aqq_inv = body.aqq_inverse();
        body
    }

    /// `(sum_i q_i q_i^T)^-1`, row-major (0 when singular: a body in a line).
    fn aqq_inverse(&self) -> [f32; 4] {
        let mut a = [0.0f64; 3];
        for q in &self.rest {
            let (x, y) = (f64::from(q[0]), f64::from(q[1]));
            a[0] += x * x;
            a[1] += x * y;
            a[2] += y * y;
        }
        let det = a[0] * a[2] - a[1] * a[1];
        if det.abs() < 1e-18 {
            return [0.0; 4];
        }
        [a[2] / det, -a[1] / det, -a[1] / det, a[0] / det].map(|v| v as f32)
    }

    /// Moves the body's particles in `frame` (`[N, 4]` rows) towards their goal positions
    /// (module doc); with `p.plastic` > 0 the rest shape yields.
    pub(super) fn project(&mut self, p: &ShapeParams, frame: &mut [f32]) {
        let at = |frame: &[f32], i: u32| [frame[4 * i as usize], frame[4 * i as usize + 1]];
        let c = centre_of_mass(frame, 4, &self.ids).map(|c| c as f32);
        let mut apq = [0.0f64; 4];
        for (&i, q) in self.ids.iter().zip(&self.rest) {
            let x = at(frame, i);
            let d = [f64::from(x[0] - c[0]), f64::from(x[1] - c[1])];
            apq[0] += d[0] * f64::from(q[0]);
            apq[1] += d[0] * f64::from(q[1]);
            apq[2] += d[1] * f64::from(q[0]);
            apq[3] += d[1] * f64::from(q[1]);
        }
        // The rotation of the polar decomposition of a 2 x 2 matrix.
        let theta = (apq[2] - apq[1]).atan2(apq[0] + apq[3]);
        let (s, co) = (theta.sin() as f32, theta.cos() as f32);
        let rot = [co, -s, s, co];
        let goal = if p.linear > 0.0 {
            let q = self.aqq_inv;
            let a = [
                apq[0] as f32 * q[0] + apq[1] as f32 * q[2],
                apq[0] as f32 * q[1] + apq[1] as f32 * q[3],
                apq[2] as f32 * q[0] + apq[3] as f32 * q[2],
                apq[2] as f32 * q[1] + apq[3] as f32 * q[3],
            ];
            let det = a[0] * a[3] - a[1] * a[2];
            match det > 1e-12 {
                true => {
                    let k = 1.0 / det.sqrt();
                    std::array::from_fn(|r| p.linear * a[r] * k + (1.0 - p.linear) * rot[r])
                }
                false => rot,
            }
        } else {
            rot
        };
        for (&i, q) in self.ids.iter().zip(self.rest.iter_mut()) {
            let i = 4 * i as usize;
            let g = [
                goal[0] * q[0] + goal[1] * q[1] + c[0],
                goal[2] * q[0] + goal[3] * q[1] + c[1],
            ];
            frame[i] += p.stiffness * (g[0] - frame[i]);
            frame[i + 1] += p.stiffness * (g[1] - frame[i + 1]);
            if p.plastic > 0.0 {
                // R^T (x - c): the particle's offset in the body's rest orientation.
                let d = [frame[i] - c[0], frame[i + 1] - c[1]];
                let back = [co * d[0] + s * d[1], -s * d[0] + co * d[1]];
                q[0] += p.plastic * (back[0] - q[0]);
                q[1] += p.plastic * (back[1] - q[1]);
            }
        }
        if p.plastic > 0.0 && p.linear > 0.0 {
            self.aqq_inv = self.aqq_inverse();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The spacing's k-th distances are those of sorting every pair's `hypot` (within 1/64,
    /// the same material): a cloud with lattice ties, duplicates and points outside the box.
    #[test]
    fn kth_distances_match_sorting_every_hypot() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let pos: Vec<f32> = (0..1500)
            .flat_map(|i| match i % 3 {
                0 => [
                    0.3 + rng.random_range(0..30) as f32 / 256.0,
                    0.4 + rng.random_range(0..30) as f32 / 256.0,
                ],
                _ => [rng.random_range(-0.02..0.6), rng.random_range(-0.02..0.6)],
            })
            .collect();
        let radius = 1.0f32 / 64.0;
        let (mut found, mut checked) = (0, 0);
        for i in 0..1500 {
            let mut all: Vec<f32> = (0..1500)
                .filter(|&j| j != i)
                .map(|j| (pos[2 * j] - pos[2 * i]).hypot(pos[2 * j + 1] - pos[2 * i + 1]))
                .filter(|&d| d <= radius)
                .collect();
            all.sort_unstable_by(f32::total_cmp);
            let mut near: Vec<[f32; 3]> = (0..1500)
                .filter(|&j| j != i)
                .map(|j| {
                    let (dx, dy) = (pos[2 * j] - pos[2 * i], pos[2 * j + 1] - pos[2 * i + 1]);
                    [dx * dx + dy * dy, dx, dy]
                })
                .filter(|r| r[0] <= radius * radius * 1.001)
                .collect();
            let got = kth_within(&mut near, &mut Vec::new(), SPACING_NEIGHBOURS, radius);
            assert_eq!(
                got,
                all.get(SPACING_NEIGHBOURS - 1).copied(),
                "particle {i}"
            );
            found += usize::from(got.is_some());
            checked += 1;
        }
        assert!(found > 100 && found < checked, "{found} of {checked}");
    }

    /// The spacing from the ring search is the brute force's: the median over particles of
    /// the k-th sorted `hypot` within 1/64, for a sparse cloud, denser ones (searched on
    /// cells of 1/128 and of 1/256: the density of 40,000 particles on a 256^2 solver grid),
    /// lattice ties and points outside the box.
    #[test]
    fn the_spacing_equals_every_pair_sorted() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        for (n, side) in [(1500, 0.6f32), (4000, 0.2), (6000, 0.12), (1200, 0.05)] {
            let pos: Vec<f32> = (0..n)
                .flat_map(|i| {
                    let [x, y] = match i % 4 {
                        0 => [
                            0.3 + rng.random_range(0..40) as f32 / 512.0,
                            0.3 + rng.random_range(0..40) as f32 / 512.0,
                        ],
                        _ => [
                            rng.random_range(-0.01..side) + 0.2,
                            rng.random_range(-0.01..side) + 0.2,
                        ],
                    };
                    [x, y, 0.0, 0.0]
                })
                .collect();
            let material = vec![1u8; n];
            let radius = 1.0f32 / 64.0;
            let mut kth: Vec<f32> = (0..n)
                .filter_map(|i| {
                    let mut d: Vec<f32> = (0..n)
                        .filter(|&j| j != i)
                        .map(|j| (pos[4 * j] - pos[4 * i]).hypot(pos[4 * j + 1] - pos[4 * i + 1]))
                        .filter(|&d| d <= radius)
                        .collect();
                    d.sort_unstable_by(f32::total_cmp);
                    d.get(SPACING_NEIGHBOURS - 1).copied()
                })
                .collect();
            let mid = kth.len() / 2;
            kth.select_nth_unstable_by(mid, f32::total_cmp);
            let want = kth[mid] * (std::f32::consts::PI / SPACING_NEIGHBOURS as f32).sqrt();
            assert_eq!(
                spacing_of(&pos, 4, &material, 1),
                want,
                "{n} particles over {side}"
            );
        }
    }

    /// A 10 x 10 lattice block of spacing 0.01 at (0.3, 0.3), as `[N, 4]` rows.
    fn block() -> Vec<f32> {
        (0..100)
            .flat_map(|i| {
                [
                    0.3 + 0.01 * (i / 10) as f32,
                    0.3 + 0.01 * (i % 10) as f32,
                    0.0,
                    0.0,
                ]
            })
            .collect()
    }

    #[test]
    fn the_spacing_of_a_lattice_is_near_its_pitch() {
        let rest = block();
        let s = spacing_of(&rest, 4, &[1; 100], 1);
        // The 8th neighbour of a square lattice is at sqrt(2) s: sqrt(2 pi / 8) s = 0.89 s.
        assert!((s - 0.00886).abs() < 5e-4, "{s}");
    }

    #[test]
    fn two_apart_blocks_are_two_bodies() {
        let mut rest = block();
        rest.extend(block().chunks(4).flat_map(|r| [r[0] + 0.3, r[1], 0.0, 0.0]));
        let material = vec![1u8; 200];
        let found = bodies(&rest, 4, &material, 1, 0.01);
        assert_eq!(found.len(), 2);
        assert_eq!(found[0].ids.len(), 100);
    }

    #[test]
    fn a_rigidly_moved_body_stays_and_a_squashed_one_is_restored_to_a_rotation() {
        let rest = block();
        let material = vec![1u8; 100];
        let mut body = bodies(&rest, 4, &material, 1, 0.01).remove(0);
        let rigid = ShapeParams {
            stiffness: 1.0,
            linear: 0.0,
            plastic: 0.0,
        };
        // Rotated by 30 degrees about (0.5, 0.5) and moved: unchanged by the projection.
        let (s, c) = (0.5f32, 0.75f32.sqrt());
        let mut moved: Vec<f32> = rest
            .chunks(4)
            .flat_map(|r| {
                let (x, y) = (r[0] - 0.5, r[1] - 0.5);
                [c * x - s * y + 0.6, s * x + c * y + 0.4, 0.0, 0.0]
            })
            .collect();
        let want = moved.clone();
        body.project(&rigid, &mut moved);
        let err = moved
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        assert!(err < 1e-5, "{err}");
        // Squashed to half its height about its centre: back to the rest shape, same centre.
        let mut squashed: Vec<f32> = rest
            .chunks(4)
            .flat_map(|r| [r[0], 0.345 + 0.5 * (r[1] - 0.345), 0.0, 0.0])
            .collect();
        body.project(&rigid, &mut squashed);
        let err = squashed
            .iter()
            .zip(&rest)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        assert!(err < 1e-5, "{err}");
    }

    #[test]
    fn a_plastic_rest_shape_takes_on_the_deformation() {
        let rest = block();
        let material = vec![2u8; 100];
        let mut body = bodies(&rest, 4, &material, 2, 0.01).remove(0);
        let plastic = ShapeParams {
            stiffness: 0.5,
            linear: 0.0,
            plastic: 1.0,
        };
        let squash = |r: &[f32]| [r[0], 0.345 + 0.5 * (r[1] - 0.345), 0.0, 0.0];
        let mut frame: Vec<f32> = rest.chunks(4).flat_map(squash).collect();
        body.project(&plastic, &mut frame);
        // The rest shape is now the half-way shape: projecting it again moves nothing.
        let again = frame.clone();
        body.project(&plastic, &mut frame);
        let err = frame
            .iter()
            .zip(&again)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        assert!(err < 1e-5, "{err}");
    }
}
