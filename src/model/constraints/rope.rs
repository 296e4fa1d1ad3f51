//! Rope constraints (Kim, Chentanez & Müller 2012, "Long Range Attachments - A Method to
//! Simulate Inextensible Clothing in Computer Games"): a rope is a chain of particles of
//! consecutive index; each pair `i, i + 2^m` of a chain may be at most `stretch` times its
//! rest distance along the chain apart. Levels are swept coarse to fine (m from the largest
//! that fits down to 0, the chain's own links), pairs in index order, each violated pair
//! moved half each along its axis (equal masses; Gauss-Seidel). A falling rope's particles
//! move ~24 spacings a frame, and the chain's links alone close a stretch by about one
//! spacing per sweep; the long pairs pull the whole rope together in one sweep. The pairs are
//! unilateral: a rope may bend and fold, never stretch past the limit.

use super::RopeParams;

/// One rope: its particles in chain order and their rest distance along the chain.
#[derive(Clone, Debug)]
pub(super) struct Chain {
    /// Particle indices, in chain order.
    ids: Vec<u32>,
    /// `[len]`: rest distance along the chain from its first particle (domain units).
    along: Vec<f32>,
}

/// A rope particle `i + 1` continues `i`'s chain while their rest distance is at most this
/// many times the median link.
const LINK_BREAK: f32 = 3.0;

/// The chains of material `rope` in the rest frame `rest` (`[N, stride]` rows): runs of
/// consecutive indices of that material whose rest links are at most [`LINK_BREAK`] times
/// the median link (the solver lays a rope out as one line of consecutive particles). Runs of
/// one particle are left out.
pub(super) fn chains(rest: &[f32], stride: usize, material: &[u8], rope: u8) -> Vec<Chain> {
    let n = material.len();
    let dist = |i: usize, j: usize| {
        (rest[stride * j] - rest[stride * i]).hypot(rest[stride * j + 1] - rest[stride * i + 1])
    };
    let mut links: Vec<f32> = (1..n)
        .filter(|&i| material[i] == rope && material[i - 1] == rope)
        .map(|i| dist(i - 1, i))
        .collect();
    if links.is_empty() {
        return Vec::new();
    }
    links.sort_by(f32::total_cmp);
    let limit = LINK_BREAK * links[links.len() / 2];
    let mut out = Vec::new();
    let mut current: Option<Chain> = None;
    for i in 0..n {
        if material[i] != rope {
            out.extend(current.take());
            continue;
        }
        match current.as_mut() {
            Some(c) if dist(*c.ids.last().unwrap() as usize, i) <= limit => {
                let s = c.along.last().copied().unwrap_or(0.0) + dist(i - 1, i);
                c.ids.push(i as u32);
                c.along.push(s);
            }
            _ => {
                out.extend(current.take());
                current = Some(Chain {
                    ids: vec![i as u32],
                    along: vec![0.0],
                });
            }
        }
    }
    out.extend(current);
    out.retain(|c| c.ids.len() > 1);
    out
}

/// The median rest link of `chains` (domain units), None without links.
pub(super) fn median_link(chains: &[Chain]) -> Option<f32> {
    let mut links: Vec<f32> = chains
        .iter()
        .flat_map(|c| c.along.windows(2).map(|w| w[1] - w[0]))
        .collect();
    links.sort_by(f32::total_cmp);
    links.get(links.len() / 2).copied()
}

impl Chain {
    /// The chain's particles in chain order and their rest distance along it (domain units).
    pub(super) fn parts(&self) -> (&[u32], &[f32]) {
        (&self.ids, &self.along)
    }

    /// The chain's links as `(i, j, rest length)`: particle indices and domain units.
    pub(super) fn links(&self) -> Vec<(usize, usize, f32)> {
        self.ids
            .windows(2)
            .zip(self.along.windows(2))
            .map(|(i, s)| (i[0] as usize, i[1] as usize, s[1] - s[0]))
            .filter(|l| l.2 > 0.0)
            .collect()
    }

    /// Projects the chain's particles in `frame` (`[N, 4]` rows) onto its distance limits:
    /// `p.iterations` sweeps, each coarse to fine (module doc).
    pub(super) fn project(&self, p: &RopeParams, frame: &mut [f32]) {
        let len = self.ids.len();
        let top = if p.long_range {
            (usize::BITS - 1 - (len - 1).leading_zeros()) as usize
        } else {
            0
        };
        for _ in 0..p.iterations {
            for level in (0..=top).rev() {
                let step = 1usize << level;
                for a in 0..len.saturating_sub(step) {
                    let b = a + step;
                    let limit = p.stretch * (self.along[b] - self.along[a]);
                    let (i, j) = (4 * self.ids[a] as usize, 4 * self.ids[b] as usize);
                    let (dx, dy) = (frame[j] - frame[i], frame[j + 1] - frame[i + 1]);
                    let d = dx.hypot(dy);
                    if d > limit && d > 0.0 {
                        let k = 0.5 * (d - limit) / d;
                        frame[i] += k * dx;
                        frame[i + 1] += k * dy;
                        frame[j] -= k * dx;
                        frame[j + 1] -= k * dy;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A straight rope of `n` particles 0.01 apart, as `[N, 4]` rows.
    fn rope(n: usize) -> Vec<f32> {
        (0..n)
            .flat_map(|i| [0.2 + 0.01 * i as f32, 0.5, 0.0, 0.0])
            .collect()
    }

    #[test]
    fn a_pulled_apart_rope_is_brought_back_within_its_stretch() {
        let n = 64;
        let rest = rope(n);
        let material = vec![3u8; n];
        let found = chains(&rest, 4, &material, 3);
        assert_eq!(found.len(), 1);
        // Every particle moved 0.05 further per index: 6x its rest length.
        let mut frame: Vec<f32> = (0..n)
            .flat_map(|i| [0.2 + 0.06 * i as f32, 0.5, 0.0, 0.0])
            .collect();
        let p = RopeParams {
            stretch: 1.2,
            iterations: 3,
            long_range: true,
        };
        found[0].project(&p, &mut frame);
        let end_to_end = frame[4 * (n - 1)] - frame[0];
        // At most 1.2 x 0.63, and the centre of mass kept (symmetric moves).
        assert!(end_to_end <= 1.2 * 0.63 + 1e-4, "{end_to_end}");
        let mean: f32 = (0..n).map(|i| frame[4 * i]).sum::<f32>() / n as f32;
        assert!((mean - (0.2 + 0.06 * 31.5)).abs() < 1e-4, "{mean}");
    }

    #[test]
    fn the_chain_alone_closes_a_stretch_slowly() {
        let n = 64;
        let rest = rope(n);
        let material = vec![3u8; n];
        let found = chains(&rest, 4, &material, 3);
        let mut frame: Vec<f32> = (0..n)
            .flat_map(|i| [0.2 + 0.06 * i as f32, 0.5, 0.0, 0.0])
            .collect();
        let p = RopeParams {
            stretch: 1.2,
            iterations: 3,
            long_range: false,
        };
        found[0].project(&p, &mut frame);
        assert!(frame[4 * (n - 1)] - frame[0] > 1.2 * 0.63 + 0.1);
    }

    #[test]
    fn ropes_are_split_at_other_materials_and_long_gaps() {
        // 0..10 rope, 10 liquid, 11..20 rope, then a far jump at 15.
        let mut rest = rope(20);
        rest[4 * 15] += 0.5;
        let mut material = vec![3u8; 20];
        material[10] = 0;
        let found = chains(&rest, 4, &material, 3);
        let lens: Vec<usize> = found.iter().map(|c| c.ids.len()).collect();
        assert_eq!(lens, [10, 4, 4]); // 15 alone is left out
    }
}
