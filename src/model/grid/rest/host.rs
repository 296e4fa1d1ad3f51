//! The host side of [`super`]: a [`Neighbourhood`] built from a reference configuration (the
//! ring search of [`crate::neighbours`] on a 1/64 cell grid), uploaded as
//! [`NeighbourTensors`], and the rest-shape features computed in one pass over the particles
//! for inference on the CPU ([`NeighbourTensors::features_host`]).

use burn::tensor::backend::Backend;
use burn::tensor::{Tensor, TensorData};

use super::{NeighbourTensors, REST_CLAMP, REST_FEATURES, REST_NEIGHBOURS};
use crate::neighbours::Bins;
use crate::ops::{host_indices, host_values, NetOps};

/// Each selected particle's neighbours in a reference configuration, on the host (see the
/// module doc). Rows of the batch's `B N` particles, scene-major.
#[derive(Debug, Clone)]
pub struct Neighbourhood {
    /// Scenes B.
    pub b: usize,
    /// Particles per scene N.
    pub n: usize,
    /// `[B N K]`: neighbour row `b N + j`; a particle's own row where it has fewer than K.
    pub index: Vec<i64>,
    /// `[B N K 2]`: rest offsets `X_j - X_i`, domain units (0 where padded).
    pub offset: Vec<f32>,
    /// `[B N K]`: 1 for a neighbour, 0 for padding.
    pub weight: Vec<f32>,
    /// `[B N 4]`: `B_i^-1` row-major (0 for particles without neighbours).
    pub binv: Vec<f32>,
    /// `[B N]`: `1 / d0_i`, the inverse root-mean-square rest distance (0 without neighbours).
    pub inv_d0: Vec<f32>,
}

/// Cells per side of the search grid of [`Neighbourhood::build`].
const CELLS: usize = 64;

impl Neighbourhood {
    /// The neighbourhoods of `reference` (`[B, N, 2]` positions, domain units) for every
    /// particle whose material id (`[B, N]`) passes `select`, among the particles of its own
    /// material in its own scene. A material with fewer than 3 particles in a scene gets none.
    pub fn build(
        reference: &[f32],
        material: &[u8],
        [b, n]: [usize; 2],
        select: impl Fn(u8) -> bool + Sync,
    ) -> Self {
        use rayon::prelude::*;
        let scenes: Vec<Self> = (0..b)
            .into_par_iter()
            .map(|s| {
                let pos = &reference[s * n * 2..(s + 1) * n * 2];
                Self::scene(pos, &material[s * n..(s + 1) * n], &select)
            })
            .collect();
        Self::concat(scenes, n)
    }

    /// The neighbourhoods of several batches of scenes of `n` particles each as one batch,
    /// scenes in order (neighbour rows offset by the scenes before).
    pub fn concat(parts: Vec<Self>, n: usize) -> Self {
        let mut out = Self::empty(0, n);
        for part in parts {
            let base = (out.b * n) as i64;
            out.b += part.b;
            out.index.extend(part.index.iter().map(|&j| j + base));
            out.offset.extend(part.offset);
            out.weight.extend(part.weight);
            out.binv.extend(part.binv);
            out.inv_d0.extend(part.inv_d0);
        }
        out
    }

    /// No neighbours for `b` scenes of `n` particles.
    fn empty(b: usize, n: usize) -> Self {
        let k = REST_NEIGHBOURS;
        Self {
            b,
            n,
            index: (0..b * n)
                .flat_map(|row| std::iter::repeat_n(row as i64, k))
                .collect(),
            offset: vec![0.0; b * n * k * 2],
            weight: vec![0.0; b * n * k],
            binv: vec![0.0; b * n * 4],
            inv_d0: vec![0.0; b * n],
        }
    }

    /// One scene's neighbourhoods (`pos` `[N, 2]`, `mat` `[N]`): each selected particle's
    /// [`REST_NEIGHBOURS`] nearest of its material at a distance above 0, nearest first (f32
    /// distances; of equal ones, the one the search meets first: [`crate::neighbours`]).
    fn scene(pos: &[f32], mat: &[u8], select: &(impl Fn(u8) -> bool + Sync)) -> Self {
        let n = mat.len();
        let mut out = Self::empty(1, n);
        let mut materials: Vec<u8> = mat.iter().copied().filter(|&m| select(m)).collect();
        materials.sort_unstable();
        materials.dedup();
        let mut near = Vec::with_capacity(REST_NEIGHBOURS);
        let mut rows = Vec::with_capacity(REST_NEIGHBOURS);
        for m in materials {
            let ids: Vec<u32> = (0..n as u32).filter(|&i| mat[i as usize] == m).collect();
            let bins = Bins::new(pos, 2, &ids, CELLS);
            for &i in &ids {
                let (i, p) = (i as usize, [pos[2 * i as usize], pos[2 * i as usize + 1]]);
                let distance = |j: usize| {
                    let d = (pos[2 * j] - p[0]).hypot(pos[2 * j + 1] - p[1]);
                    (j != i && d > 0.0).then_some(f64::from(d))
                };
                bins.nearest(p, REST_NEIGHBOURS, f64::INFINITY, distance, &mut near);
                if near.len() >= 2 {
                    rows.clear();
                    rows.extend(near.iter().map(|&(_, j)| j));
                    out.fill_row(0, i, pos, &rows);
                }
            }
        }
        out
    }

    /// Writes particle `i`'s (row `base + i`) neighbours `near` (indices within its scene).
    fn fill_row(&mut self, base: usize, i: usize, pos: &[f32], near: &[usize]) {
        let k = REST_NEIGHBOURS;
        let row = base + i;
        let (mut bm, mut sq) = ([0.0f64; 4], 0.0f64);
        for (slot, &j) in near.iter().enumerate() {
            let d = [pos[2 * j] - pos[2 * i], pos[2 * j + 1] - pos[2 * i + 1]];
            self.index[row * k + slot] = (base + j) as i64;
            self.offset[(row * k + slot) * 2..(row * k + slot) * 2 + 2].copy_from_slice(&d);
            self.weight[row * k + slot] = 1.0;
            let (x, y) = (f64::from(d[0]), f64::from(d[1]));
            bm[0] += x * x;
            bm[1] += x * y;
            bm[3] += y * y;
            sq += x * x + y * y;
        }
        bm[2] = bm[1];
        let lambda = 1e-3 * (bm[0] + bm[3]) / 2.0;
        let (a, bb, c, d) = (bm[0] + lambda, bm[1], bm[2], bm[3] + lambda);
        let det = a * d - bb * c;
        if det <= 0.0 {
            return;
        }
        let inv = [d / det, -bb / det, -c / det, a / det];
        for (o, v) in self.binv[row * 4..row * 4 + 4].iter_mut().zip(inv) {
            *o = v as f32;
        }
        self.inv_d0[row] = (1.0 / (sq / near.len() as f64).sqrt()) as f32;
    }

    /// The tensors on `device`.
    pub fn upload<B: Backend>(&self, device: &B::Device) -> NeighbourTensors<B> {
        let (b, n, k) = (self.b, self.n, REST_NEIGHBOURS);
        let f = |v: &[f32], shape: [usize; 3]| {
            Tensor::<B, 3>::from_data(TensorData::new(v.to_vec(), shape), device)
        };
        // Indices within each scene: scenes' neighbourhoods then stack and split as rows.
        let local: Vec<i64> = self.index.iter().map(|&j| j % n.max(1) as i64).collect();
        NeighbourTensors {
            index: Tensor::from_data(TensorData::new(local, [b * n * k]), device),
            offset: f(&self.offset, [b * n, k, 2]),
            weight: f(&self.weight, [b * n, k, 1]),
            binv: f(&self.binv, [b, n, 4]),
            inv_d0: f(&self.inv_d0, [b, n, 1]),
            dims: [b, n],
        }
    }
}

impl<B: NetOps> NeighbourTensors<B> {
    /// [`Self::features`] computed on the host in one pass over the particles, for inference
    /// on the CPU (about 40 small tensor operations per frame cost a 2,500-particle step more
    /// than the network did; this is one loop): the same values, no gradient.
    pub fn features_host(&self, pos: Tensor<B, 3>) -> Tensor<B, 3> {
        let [b, n] = self.dims;
        let device = pos.device();
        let rows = self.features_rows(&host_values(pos.clone()));
        match rows {
            Some(out) => Tensor::from_data(TensorData::new(out, [b, n, REST_FEATURES]), &device),
            None => self.features(pos),
        }
    }

    /// [`Self::features_host`] of the host positions `x` (`[B N, 2]`, row-major): `[B N, 6]`
    /// rows; None where the neighbourhoods cannot be read back as f32 and i64 or `x` is not
    /// `B N` rows.
    pub fn features_rows(&self, x: &[f32]) -> Option<Vec<f32>> {
        let [b, n] = self.dims;
        if x.len() != b * n * 2 {
            return None;
        }
        let host = |t: &Tensor<B, 3>| Some(host_values(t.clone())).filter(|v| !v.is_empty());
        let offset = host(&self.offset)?;
        let weight = host(&self.weight)?;
        let binv = host(&self.binv)?;
        let inv_d0 = host(&self.inv_d0)?;
        let index = Some(host_indices(self.index.clone())).filter(|v| !v.is_empty())?;
        let k = REST_NEIGHBOURS;
        let mut out = vec![0.0f32; b * n * REST_FEATURES];
        for (row, feats) in out.chunks_exact_mut(REST_FEATURES).enumerate() {
            let base = (row / n.max(1)) * n;
            let near: [Pair; REST_NEIGHBOURS] = std::array::from_fn(|j| {
                let slot = row * k + j;
                let other = base + index[slot] as usize;
                let w = weight[slot];
                let dx = [
                    (x[2 * other] - x[2 * row]) * w,
                    (x[2 * other + 1] - x[2 * row + 1]) * w,
                ];
                (dx, [offset[2 * slot], offset[2 * slot + 1]], w)
            });
            let g = Geometry::of(&near, &binv[row * 4..row * 4 + 4], inv_d0[row]);
            let mut o = [0.0f32; 2];
            for &(dx, x0, w) in &near {
                o[0] += dx[0] - (g.cos * x0[0] - g.sin * x0[1]) * w;
                o[1] += dx[1] - (g.sin * x0[0] + g.cos * x0[1]) * w;
            }
            let scale = inv_d0[row] / k as f32;
            let values = [g.exx, g.exy, g.eyy, g.j, o[0] * scale, o[1] * scale];
            for (f, v) in feats.iter_mut().zip(values) {
                *f = v.clamp(-REST_CLAMP, REST_CLAMP);
            }
        }
        Some(out)
    }
}

/// One neighbour pair on the host: current offset `dx`, rest offset `dX`, weight.
type Pair = ([f32; 2], [f32; 2], f32);

/// One particle's fit on the host ([`NeighbourTensors::features_host`]): the strain, `J - 1`
/// and the rotation of shape matching, as [`NeighbourTensors::features`] computes them.
struct Geometry {
    exx: f32,
    exy: f32,
    eyy: f32,
    j: f32,
    cos: f32,
    sin: f32,
}

impl Geometry {
    /// From the particle's neighbours `(dx, dX, weight)`, its `B^-1` (row-major) and `1 / d0`.
    fn of(near: &[Pair], binv: &[f32], inv_d0: f32) -> Self {
        let mut a = [0.0f32; 4];
        for &(dx, x0, _) in near {
            a[0] += dx[0] * x0[0];
            a[1] += dx[0] * x0[1];
            a[2] += dx[1] * x0[0];
            a[3] += dx[1] * x0[1];
        }
        let f = [
            a[0] * binv[0] + a[1] * binv[2],
            a[0] * binv[1] + a[1] * binv[3],
            a[2] * binv[0] + a[3] * binv[2],
            a[2] * binv[1] + a[3] * binv[3],
        ];
        let has = if inv_d0 > 0.0 { 1.0 } else { 0.0 };
        let (p, q) = (a[0] + a[3], a[2] - a[1]);
        let r = (p * p + q * q + 1e-20).sqrt();
        Self {
            exx: (f[0] * f[0] + f[2] * f[2] - has) / 2.0,
            exy: (f[0] * f[1] + f[2] * f[3]) / 2.0,
            eyy: (f[1] * f[1] + f[3] * f[3] - has) / 2.0,
            j: f[0] * f[3] - f[1] * f[2] - has,
            cos: p / r,
            sin: q / r,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each particle's rows are its 8 nearest of its material by a brute-force sort, nearest
    /// first, on a spiral of two materials (no equal distances).
    #[test]
    fn rows_are_the_brute_force_neighbours() {
        let n = 200;
        let pos: Vec<f32> = (0..n)
            .flat_map(|i| {
                let a = i as f32 * 2.399;
                let r = 0.002 * (i as f32).sqrt();
                [0.5 + r * a.cos(), 0.5 + r * a.sin()]
            })
            .collect();
        let mat: Vec<u8> = (0..n).map(|i| 1 + (i % 7 == 0) as u8).collect();
        let nb = Neighbourhood::build(&pos, &mat, [1, n], |m| m > 0);
        for i in 0..n {
            let mut all: Vec<(f32, usize)> = (0..n)
                .filter(|&j| j != i && mat[j] == mat[i])
                .map(|j| {
                    (
                        (pos[2 * j] - pos[2 * i]).hypot(pos[2 * j + 1] - pos[2 * i + 1]),
                        j,
                    )
                })
                .collect();
            all.sort_by(|a, b| a.0.total_cmp(&b.0));
            let want: Vec<i64> = all[..REST_NEIGHBOURS].iter().map(|x| x.1 as i64).collect();
            let k = REST_NEIGHBOURS;
            assert_eq!(nb.index[i * k..(i + 1) * k], want[..], "particle {i}");
        }
    }
}
