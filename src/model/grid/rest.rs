//! Per-particle neighbourhoods in a reference configuration and what they measure of a later
//! one: the deformation gradient fitted by least squares, its Green strain and `J = det F`,
//! the shape-matching restoring offset and the stretch of each neighbour pair. The grid
//! model's rest-shape features ([`super::GridConfig::rest_shape`]) and the trainer's strain
//! and volume losses read them.
//!
//! A [`Neighbourhood`] is built on the host, once per reference configuration: for each
//! selected particle its [`REST_NEIGHBOURS`] nearest particles of the same material (a
//! 1/64 cell grid searched ring by ring), their rest offsets `dX_j = X_j - X_i` and the
//! inverse of `B_i = sum_j dX_j dX_j^T + lambda I` (`lambda = 1e-3 tr B / 2`, so a rope, one
//! particle wide, still has an inverse; its `F` then reads 0 across the rope). Uploaded as a
//! [`NeighbourTensors`], it measures a configuration `x` (`[B, N, 2]`) differentiably:
//!
//! - `A_i = sum_j dx_j dX_j^T` with `dx_j = x_j - x_i`, and `F_i = A_i B_i^-1`: the
//!   least-squares fit of `dx_j = F dX_j` (the deformation gradient of MPM, `F = dx/dX`,
//!   measured from the particles; Müller et al. 2005, "Meshless deformations based on shape
//!   matching", section 4.2, the linear fit `A = A_pq A_qq^-1`);
//! - Green strain `E = (F^T F - I) / 2` and `J - 1 = det F - 1`: zero for a rigid motion;
//! - the restoring offset `o_i = mean_j (dx_j - R dX_j) / d0_i`, `R` the rotation of the polar
//!   decomposition of `A_i` (shape matching's optimal rotation, Müller et al. 2005, eq. 5;
//!   in 2D `R` has angle `atan2(A10 - A01, A00 + A11)`), `d0_i` the rest neighbour distance:
//!   where the particle's neighbours, moved rigidly, would put it, relative to where it is;
//! - the length `|dx_j| / d0_i` of each pair, in units of the rest neighbour distance (the
//!   strain loss).
//!
//! Liquid particles (and any particle not selected) have no neighbours: their features are 0.

use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor, TensorData};

/// Neighbours per particle in a [`Neighbourhood`].
pub const REST_NEIGHBOURS: usize = 8;
/// Rest-shape features per particle: `E_xx, E_xy, E_yy, J - 1, o_x, o_y`.
pub const REST_FEATURES: usize = 6;
/// Features are clamped to `[-REST_CLAMP, REST_CLAMP]` (a torn body's values grow without
/// bound; the network needs to know only that they are large).
pub const REST_CLAMP: f32 = 4.0;

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

    /// One scene's neighbourhoods (`pos` `[N, 2]`, `mat` `[N]`).
    fn scene(pos: &[f32], mat: &[u8], select: &(impl Fn(u8) -> bool + Sync)) -> Self {
        let n = mat.len();
        let mut out = Self::empty(1, n);
        let bins = Bins::new(pos);
        for i in (0..n).filter(|&i| select(mat[i])) {
            let near = bins.nearest(pos, i, REST_NEIGHBOURS, |j| mat[j] == mat[i]);
            if near.len() >= 2 {
                out.fill_row(0, i, pos, &near);
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

/// Particles of one scene binned on a [`CELLS`] x [`CELLS`] grid.
struct Bins {
    cells: Vec<Vec<u32>>,
}

impl Bins {
    fn cell(x: f32) -> usize {
        ((x * CELLS as f32).floor().max(0.0) as usize).min(CELLS - 1)
    }

    fn new(pos: &[f32]) -> Self {
        let mut cells = vec![Vec::new(); CELLS * CELLS];
        for (i, p) in pos.chunks_exact(2).enumerate() {
            cells[Self::cell(p[0]) * CELLS + Self::cell(p[1])].push(i as u32);
        }
        Self { cells }
    }

    /// The (at most) `k` nearest particles `j != i` with `keep(j)` and a distance above 0,
    /// nearest first: rings of cells around `i`'s are searched until the k-th nearest found
    /// is no farther than the searched rings reach.
    fn nearest(&self, pos: &[f32], i: usize, k: usize, keep: impl Fn(usize) -> bool) -> Vec<usize> {
        let (x, y) = (pos[2 * i], pos[2 * i + 1]);
        let (cx, cy) = (Self::cell(x) as i64, Self::cell(y) as i64);
        let mut found: Vec<(f32, usize)> = Vec::new();
        let h = 1.0 / CELLS as f32;
        for r in 0..CELLS as i64 {
            for gx in (cx - r)..=(cx + r) {
                for gy in (cy - r)..=(cy + r) {
                    let on_ring = (gx - cx).abs() == r || (gy - cy).abs() == r;
                    let inside = (0..CELLS as i64).contains(&gx) && (0..CELLS as i64).contains(&gy);
                    if !on_ring || !inside {
                        continue;
                    }
                    for &j in &self.cells[gx as usize * CELLS + gy as usize] {
                        let j = j as usize;
                        let d = (pos[2 * j] - x).hypot(pos[2 * j + 1] - y);
                        if j != i && d > 0.0 && keep(j) {
                            found.push((d, j));
                        }
                    }
                }
            }
            found.sort_by(|a, b| a.0.total_cmp(&b.0));
            // Every particle within r cells' distance has been seen.
            if found.len() >= k && found[k - 1].0 <= r as f32 * h {
                break;
            }
        }
        found.truncate(k);
        found.into_iter().map(|(_, j)| j).collect()
    }
}

/// A [`Neighbourhood`] on a device: measures configurations of its `B N` particles. Every
/// tensor's leading axis runs over the scenes (indices are within each scene), so the
/// neighbourhoods of several scenes stack into one batch and split back as rows
/// (`model::store`'s batched node step).
#[derive(Debug, Clone)]
pub struct NeighbourTensors<B: Backend> {
    /// `[B N K]` neighbour index within its scene.
    pub(crate) index: Tensor<B, 1, Int>,
    /// `[B N, K, 2]` rest offsets.
    pub(crate) offset: Tensor<B, 3>,
    /// `[B N, K, 1]` neighbour weights.
    pub(crate) weight: Tensor<B, 3>,
    /// `[B, N, 4]` `B_i^-1`.
    pub(crate) binv: Tensor<B, 3>,
    /// `[B, N, 1]` `1 / d0`.
    pub(crate) inv_d0: Tensor<B, 3>,
    /// `[B, N]`.
    pub(crate) dims: [usize; 2],
}

impl<B: Backend> NeighbourTensors<B> {
    /// `[B, N]`: scenes and particles.
    pub fn dims(&self) -> [usize; 2] {
        self.dims
    }

    /// `[B N, K, 2]`: current neighbour offsets `x_j - x_i` of positions `pos` (`[B, N, 2]`).
    pub fn offsets(&self, pos: Tensor<B, 3>) -> Tensor<B, 3> {
        let [b, n] = self.dims;
        let k = REST_NEIGHBOURS;
        let rows = pos.reshape([b * n, 2]);
        let scene = Tensor::<B, 1, Int>::arange(0..b as i64, &rows.device())
            .mul_scalar(n as i64)
            .reshape([b, 1])
            .repeat_dim(1, n * k)
            .reshape([b * n * k]);
        let near = rows
            .clone()
            .select(0, self.index.clone() + scene)
            .reshape([b * n, k, 2]);
        (near - rows.unsqueeze_dim::<3>(1)) * self.weight.clone()
    }

    /// `[B, N, 4]`: `A_i = sum_j dx_j dX_j^T` row-major from offsets `dx` ([`Self::offsets`]).
    fn cross(&self, dx: Tensor<B, 3>) -> Tensor<B, 3> {
        let [b, n] = self.dims;
        let x0 = self.offset.clone().narrow(2, 0, 1);
        let y0 = self.offset.clone().narrow(2, 1, 1);
        let (x, y) = (dx.clone().narrow(2, 0, 1), dx.narrow(2, 1, 1));
        let sum = |t: Tensor<B, 3>| t.sum_dim(1).reshape([b, n, 1]);
        Tensor::cat(
            vec![
                sum(x.clone() * x0.clone()),
                sum(x * y0.clone()),
                sum(y.clone() * x0),
                sum(y * y0),
            ],
            2,
        )
    }

    /// `[B, N, 4]`: the fitted deformation gradient `F = A B^-1` row-major, from offsets `dx`.
    pub fn deformation(&self, dx: Tensor<B, 3>) -> Tensor<B, 3> {
        matmul2(self.cross(dx), self.binv.clone())
    }

    /// `[B, N, 1]`: `J = det F` from offsets `dx` (0 for particles without neighbours).
    pub fn det(&self, dx: Tensor<B, 3>) -> Tensor<B, 3> {
        let f = self.deformation(dx);
        let c = |i: usize| f.clone().narrow(2, i, 1);
        c(0) * c(3) - c(1) * c(2)
    }

    /// `[B, N, REST_FEATURES]`: `E_xx, E_xy, E_yy, J - 1, o_x, o_y` of positions `pos`
    /// (`[B, N, 2]`), each clamped to `REST_CLAMP` (see the module doc); 0 for particles
    /// without neighbours.
    pub fn features(&self, pos: Tensor<B, 3>) -> Tensor<B, 3> {
        let [b, n] = self.dims;
        let k = REST_NEIGHBOURS;
        let dx = self.offsets(pos);
        let a = self.cross(dx.clone());
        let f = matmul2(a.clone(), self.binv.clone());
        let c = |t: &Tensor<B, 3>, i: usize| t.clone().narrow(2, i, 1);
        let (f00, f01, f10, f11) = (c(&f, 0), c(&f, 1), c(&f, 2), c(&f, 3));
        let has = self.inv_d0.clone().greater_elem(0.0).float(); // [B, N, 1]
        let exx = (f00.clone().powi_scalar(2) + f10.clone().powi_scalar(2) - has.clone()) / 2.0;
        let eyy = (f01.clone().powi_scalar(2) + f11.clone().powi_scalar(2) - has.clone()) / 2.0;
        let exy = (f00.clone() * f01.clone() + f10.clone() * f11.clone()) / 2.0;
        let j = f00 * f11 - f01 * f10 - has;
        // Shape matching's rotation from A: angle atan2(A10 - A01, A00 + A11).
        let (p, q) = (c(&a, 0) + c(&a, 3), c(&a, 2) - c(&a, 1));
        let r = (p.clone().powi_scalar(2) + q.clone().powi_scalar(2)).add_scalar(1e-20).sqrt();
        let (cos, sin) = (p / r.clone(), q / r);
        let (cos, sin) = (cos.reshape([b * n, 1, 1]), sin.reshape([b * n, 1, 1]));
        let x0 = self.offset.clone().narrow(2, 0, 1);
        let y0 = self.offset.clone().narrow(2, 1, 1);
        let rx = cos.clone() * x0.clone() - sin.clone() * y0.clone();
        let ry = sin * x0 + cos * y0;
        let rotated = Tensor::cat(vec![rx, ry], 2) * self.weight.clone(); // [B N, K, 2]
        let o = (dx - rotated).sum_dim(1).reshape([b, n, 2]).div_scalar(k as f32)
            * self.inv_d0.clone();
        Tensor::cat(vec![exx, exy, eyy, j, o], 2).clamp(-REST_CLAMP, REST_CLAMP)
    }

    /// [`Self::features`] computed on the host in one pass over the particles, for inference
    /// on the CPU (about 40 small tensor operations per frame cost a 2,500-particle step more
    /// than the network did; this is one loop): the same values, no gradient.
    pub fn features_host(&self, pos: Tensor<B, 3>) -> Tensor<B, 3> {
        let [b, n] = self.dims;
        let device = pos.device();
        let host = |t: Tensor<B, 3>| t.into_data().convert::<f32>().to_vec::<f32>();
        let (Ok(x), Ok(offset), Ok(weight), Ok(binv), Ok(inv_d0)) = (
            host(pos.clone()),
            host(self.offset.clone()),
            host(self.weight.clone()),
            host(self.binv.clone()),
            host(self.inv_d0.clone()),
        ) else {
            return self.features(pos);
        };
        let Ok(index) = self.index.clone().into_data().convert::<i64>().to_vec::<i64>() else {
            return self.features(pos);
        };
        let k = REST_NEIGHBOURS;
        let mut out = vec![0.0f32; b * n * REST_FEATURES];
        for (row, feats) in out.chunks_exact_mut(REST_FEATURES).enumerate() {
            let base = (row / n.max(1)) * n;
            let near = (0..k).map(|j| {
                let slot = row * k + j;
                let other = base + index[slot] as usize;
                let w = weight[slot];
                let dx = [(x[2 * other] - x[2 * row]) * w, (x[2 * other + 1] - x[2 * row + 1]) * w];
                (dx, [offset[2 * slot], offset[2 * slot + 1]], w)
            });
            let g = Geometry::of(near.clone(), &binv[row * 4..row * 4 + 4], inv_d0[row]);
            let mut o = [0.0f32; 2];
            for (dx, x0, w) in near {
                o[0] += dx[0] - (g.cos * x0[0] - g.sin * x0[1]) * w;
                o[1] += dx[1] - (g.sin * x0[0] + g.cos * x0[1]) * w;
            }
            let scale = inv_d0[row] / k as f32;
            let values = [g.exx, g.exy, g.eyy, g.j, o[0] * scale, o[1] * scale];
            for (f, v) in feats.iter_mut().zip(values) {
                *f = v.clamp(-REST_CLAMP, REST_CLAMP);
            }
        }
        Tensor::from_data(TensorData::new(out, [b, n, REST_FEATURES]), &device)
    }

    /// `[B N, K, 1]`: each pair's length `|dx_j| / d0_i` from offsets `dx`, in units of the
    /// particle's rest neighbour distance (0 where padded): a pair's stretch, measured against
    /// a distance that is never tiny (two particles sampled next to each other would make
    /// `|dx_j| / |dX_j|` blow up).
    pub fn lengths(&self, dx: Tensor<B, 3>) -> Tensor<B, 3> {
        let [b, n] = self.dims;
        let len = dx.powi_scalar(2).sum_dim(2).add_scalar(1e-20).sqrt(); // [B N, K, 1]
        len * self.inv_d0.clone().reshape([b * n, 1, 1]) * self.weight.clone()
    }

    /// `[B N, K, 1]`: the neighbour weights (1 for a pair, 0 for padding).
    pub fn weight(&self) -> Tensor<B, 3> {
        self.weight.clone()
    }
}

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
    fn of(near: impl Iterator<Item = ([f32; 2], [f32; 2], f32)>, binv: &[f32], inv_d0: f32) -> Self {
        let mut a = [0.0f32; 4];
        for (dx, x0, _) in near {
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

/// `[B, N, 4]`: the row-major 2 x 2 products `a b` of `[B, N, 4]` row-major matrices.
fn matmul2<B: Backend>(a: Tensor<B, 3>, b: Tensor<B, 3>) -> Tensor<B, 3> {
    let c = |t: &Tensor<B, 3>, i: usize| t.clone().narrow(2, i, 1);
    Tensor::cat(
        vec![
            c(&a, 0) * c(&b, 0) + c(&a, 1) * c(&b, 2),
            c(&a, 0) * c(&b, 1) + c(&a, 1) * c(&b, 3),
            c(&a, 2) * c(&b, 0) + c(&a, 3) * c(&b, 2),
            c(&a, 2) * c(&b, 1) + c(&a, 3) * c(&b, 3),
        ],
        2,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::NdArray;

    type Nd = NdArray<f32>;

    /// A 6 x 6 jelly block 0.01 apart.
    fn block() -> (Vec<f32>, Vec<u8>) {
        let pos = (0..36)
            .flat_map(|i| [0.4 + 0.01 * (i % 6) as f32, 0.4 + 0.01 * (i / 6) as f32])
            .collect();
        (pos, vec![1u8; 36])
    }

    fn host(t: Tensor<Nd, 3>) -> Vec<f32> {
        t.into_data().to_vec::<f32>().unwrap()
    }

    /// Under a rotation and a translation the strain, `J - 1` and the restoring offset stay
    /// (near) 0; under a 10 % stretch along x, `E_xx` is (1.1^2 - 1) / 2 = 0.105 in the block's
    /// interior and `J - 1` 0.1.
    #[test]
    fn features_vanish_for_rigid_motion_and_see_a_stretch() {
        let (pos, mat) = block();
        let nb = Neighbourhood::build(&pos, &mat, [1, 36], |m| m != 0);
        let t = nb.upload::<Nd>(&Default::default());
        let (c, s) = (0.7f32.cos(), 0.7f32.sin());
        let moved: Vec<f32> = pos
            .chunks_exact(2)
            .flat_map(|p| [c * p[0] - s * p[1] + 0.2, s * p[0] + c * p[1] - 0.1])
            .collect();
        let up = |v: &[f32]| Tensor::<Nd, 3>::from_data(TensorData::new(v.to_vec(), [1, 36, 2]), &Default::default());
        let rigid = host(t.features(up(&moved)));
        // lambda = 1e-3 tr B / 2 biases F by about 0.1 %: E and J - 1 near -0.002, not 0.
        assert!(rigid.iter().all(|v| v.abs() < 0.02), "{rigid:?}");
        let stretched: Vec<f32> = pos.chunks_exact(2).flat_map(|p| [0.4 + 1.1 * (p[0] - 0.4), p[1]]).collect();
        let f = host(t.features(up(&stretched)));
        let interior = 2 * 6 + 2; // particle (2, 2)
        let row = &f[interior * 6..interior * 6 + 6];
        assert!((row[0] - 0.105).abs() < 0.01, "{row:?}");
        assert!((row[3] - 0.1).abs() < 0.01, "{row:?}");
        assert!(row[1].abs() < 0.01 && row[2].abs() < 0.02, "{row:?}");
    }

    /// The host pass gives the tensor operations' features (rigid, stretched and random
    /// configurations of a block beside unselected liquid).
    #[test]
    fn host_features_equal_the_tensor_ones() {
        let (pos, mut mat) = block();
        mat[..6].iter_mut().for_each(|m| *m = 0);
        let nb = Neighbourhood::build(&[pos.clone(), pos.clone()].concat(), &[mat.clone(), mat].concat(), [2, 36], |m| m != 0);
        let t = nb.upload::<Nd>(&Default::default());
        let moved: Vec<f32> = pos
            .iter()
            .enumerate()
            .map(|(i, v)| v + 0.003 * ((i * 7919 % 13) as f32 - 6.0) / 6.0)
            .collect();
        let up = Tensor::<Nd, 3>::from_data(TensorData::new([pos, moved].concat(), [2, 36, 2]), &Default::default());
        let (a, b) = (host(t.features(up.clone())), host(t.features_host(up)));
        let worst = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max);
        assert!(worst < 1e-4, "{worst}");
        assert!(a.iter().any(|v| v.abs() > 1e-2), "the random moves strain the block");
    }

    /// Liquid particles are not selected: no neighbours, features 0.
    #[test]
    fn unselected_particles_have_no_features() {
        let (pos, _) = block();
        let nb = Neighbourhood::build(&pos, &[0u8; 36], [1, 36], |m| m != 0);
        assert!(nb.weight.iter().all(|&w| w == 0.0));
        let t = nb.upload::<Nd>(&Default::default());
        let up = Tensor::<Nd, 3>::from_data(TensorData::new(pos, [1, 36, 2]), &Default::default());
        assert!(host(t.features(up)).iter().all(|&v| v == 0.0));
    }

    /// The ring search finds the same neighbours as a brute-force sort.
    #[test]
    fn ring_search_matches_brute_force() {
        let pos: Vec<f32> = (0..200)
            .flat_map(|i| {
                let a = i as f32 * 2.399;
                let r = 0.002 * (i as f32).sqrt();
                [0.5 + r * a.cos(), 0.5 + r * a.sin()]
            })
            .collect();
        let bins = Bins::new(&pos);
        for i in [0, 17, 99, 199] {
            let got = bins.nearest(&pos, i, 8, |_| true);
            let mut all: Vec<(f32, usize)> = (0..200)
                .filter(|&j| j != i)
                .map(|j| ((pos[2 * j] - pos[2 * i]).hypot(pos[2 * j + 1] - pos[2 * i + 1]), j))
                .collect();
            all.sort_by(|a, b| a.0.total_cmp(&b.0));
            let want: Vec<usize> = all[..8].iter().map(|x| x.1).collect();
            assert_eq!(got, want, "particle {i}");
        }
    }
}
