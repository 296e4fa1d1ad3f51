//! The particle spacing of a rest frame, per material: the median distance to the 8th
//! nearest particle of the same material, scaled to the spacing of a uniform cloud. Shape
//! matching joins a body's particles within 2.5 of it (`shape.rs`), the pressure part's grid
//! nodes stand 2 of the liquid's apart, the projection counts each material's moves in it,
//! and `eval`'s conservation diagnostics find pieces by it.

use crate::neighbours::Bins;

/// Nearest neighbours whose distance estimates the spacing ([`spacing_of`]).
const SPACING_NEIGHBOURS: usize = 8;

/// Particles of a material whose k-th neighbour distances [`spacing_of`] takes the median of
/// at most about twice this many; past that, every `count / SPACING_QUERIES`-th in the
/// cells' order (a sample spread over the body).
const SPACING_QUERIES: usize = 4096;

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
/// their positions are packed in the cells' order and read run by run. Above 2
/// [`SPACING_QUERIES`] particles of `m` (scenes at scale), the median is over every
/// `count / SPACING_QUERIES`-th particle in the cells' order, each searched among all: at
/// 40,000 particles the search was most of a scene's setup (0.45 us a particle).
pub(super) fn spacing_of(rest: &[f32], stride: usize, material: &[u8], m: u8) -> f32 {
    spacing_sampled(rest, stride, (material, m), SPACING_QUERIES)
}

/// [`spacing_of`] with `queries` in place of [`SPACING_QUERIES`] (`usize::MAX`: every
/// particle).
fn spacing_sampled(rest: &[f32], stride: usize, (material, m): (&[u8], u8), queries: usize) -> f32 {
    let ids: Vec<u32> = (0..material.len() as u32)
        .filter(|&i| material[i as usize] == m)
        .collect();
    if ids.len() <= SPACING_NEIGHBOURS {
        return 0.0;
    }
    let every = match ids.len() > queries.saturating_mul(2) {
        true => ids.len() / queries,
        false => 1,
    };
    let radius = 1.0 / 64.0;
    let far = radius * radius * (1.0 + 1e-4);
    let bins = spacing_bins(rest, stride, &ids);
    let packed: Vec<[f32; 2]> = (bins.order().iter())
        .map(|&i| [rest[stride * i as usize], rest[stride * i as usize + 1]])
        .collect();
    let mut kth = Vec::with_capacity(ids.len());
    let (mut near, mut tied): (Vec<[f32; 3]>, Vec<f32>) = (Vec::new(), Vec::new());
    for (me, &[x, y]) in packed.iter().enumerate().step_by(every) {
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

/// A 10 x 10 lattice block of spacing 0.01 at (0.3, 0.3), as `[N, 4]` rows (the spacing's and
/// the bodies' tests).
#[cfg(test)]
pub(super) fn lattice() -> Vec<f32> {
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

    /// At scale the median over a sample of the particles (every 9th of 40,000 here) is the
    /// median over all of them to within 1 %.
    #[test]
    fn at_scale_the_spacing_of_a_sample_is_the_whole_cloud_s() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let n = 40_000;
        let pos: Vec<f32> = (0..n)
            .flat_map(|_| {
                let (x, y) = (rng.random_range(0.2..0.6), rng.random_range(0.1..0.5));
                [x, y, 0.0, 0.0]
            })
            .collect();
        let material = vec![2u8; n];
        let all = spacing_sampled(&pos, 4, (&material, 2), usize::MAX);
        let sampled = spacing_of(&pos, 4, &material, 2);
        assert!(all > 0.0 && sampled != all, "{all} {sampled}");
        assert!(
            (sampled / all - 1.0).abs() < 0.01,
            "{sampled} against {all}"
        );
    }

    #[test]
    fn the_spacing_of_a_lattice_is_near_its_pitch() {
        let rest = lattice();
        let s = spacing_of(&rest, 4, &[1; 100], 1);
        // The 8th neighbour of a square lattice is at sqrt(2) s: sqrt(2 pi / 8) s = 0.89 s.
        assert!((s - 0.00886).abs() < 5e-4, "{s}");
    }
}
