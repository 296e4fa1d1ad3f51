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
//!
//! [`advect`] holds the other source of F (variant (a), [`super::Deformation::Advect`]): F
//! carried per particle and advected with the predicted velocity field, started from the fit.

use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor};

pub mod advect;
mod host;
pub use host::Neighbourhood;

/// Rest neighbours per particle: the one count of every rest neighbourhood of a solid
/// particle, its `REST_NEIGHBOURS` nearest particles of the same material in a reference
/// frame. A [`Neighbourhood`] holds this many (the grid model's rest-shape features and the
/// trainer's strain loss, `train::grid`), and so do `eval`'s rest neighbours
/// ([`crate::eval::structure::Neighbours`]: the strain error, intact fraction and rope
/// connectivity of `minflow eval`, and the strain term of the grid trainer's validation
/// score), so the loss, the validation and the evaluation measure the same pairs.
///
/// 8, the grid model's: a shipped model's rest-shape features are fitted over 8 neighbours
/// (changing the count would change what those networks read), and 8 is the first shell of a
/// square lattice, the layout scenes seed their solids in (4 edge and 4 diagonal
/// neighbours), so a particle's fit of `F` sees every direction around it. (`eval` counted
/// 6 before; the strain and intact numbers of `plausibility.csv` from before differ.)
pub const REST_NEIGHBOURS: usize = 8;
/// Rest-shape features per particle: `E_xx, E_xy, E_yy, J - 1, o_x, o_y`.
pub const REST_FEATURES: usize = 6;
/// Features are clamped to `[-REST_CLAMP, REST_CLAMP]` (a torn body's values grow without
/// bound; the network needs to know only that they are large).
pub const REST_CLAMP: f32 = 4.0;

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

    /// `[B, N, 4]`: `A_i = sum_j dx_j dX_j^T` row-major from offsets `dx` ([`Self::offsets`]):
    /// the outer products as one broadcast product `[B N, K, 2, 1] x [B N, K, 1, 2]` summed
    /// over the neighbours, no slice of a `[B N, K, 2]` tensor (each slice of the last axis
    /// copied the whole tensor: a quarter of a training step with the volume loss on the CPU).
    fn cross(&self, dx: Tensor<B, 3>) -> Tensor<B, 3> {
        let [b, n] = self.dims;
        let outer = dx.unsqueeze_dim::<4>(3) * self.offset.clone().unsqueeze_dim::<4>(2);
        outer.sum_dim(1).reshape([b, n, 4])
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
        let r = (p.clone().powi_scalar(2) + q.clone().powi_scalar(2))
            .add_scalar(1e-20)
            .sqrt();
        let (cos, sin) = (p / r.clone(), q / r);
        let (cos, sin) = (cos.reshape([b * n, 1, 1]), sin.reshape([b * n, 1, 1]));
        let x0 = self.offset.clone().narrow(2, 0, 1);
        let y0 = self.offset.clone().narrow(2, 1, 1);
        let rx = cos.clone() * x0.clone() - sin.clone() * y0.clone();
        let ry = sin * x0 + cos * y0;
        let rotated = Tensor::cat(vec![rx, ry], 2) * self.weight.clone(); // [B N, K, 2]
        let o = (dx - rotated)
            .sum_dim(1)
            .reshape([b, n, 2])
            .div_scalar(k as f32)
            * self.inv_d0.clone();
        Tensor::cat(vec![exx, exy, eyy, j, o], 2).clamp(-REST_CLAMP, REST_CLAMP)
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
    use burn::tensor::TensorData;

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
        let up = |v: &[f32]| {
            Tensor::<Nd, 3>::from_data(TensorData::new(v.to_vec(), [1, 36, 2]), &Default::default())
        };
        let rigid = host(t.features(up(&moved)));
        // lambda = 1e-3 tr B / 2 biases F by about 0.1 %: E and J - 1 near -0.002, not 0.
        assert!(rigid.iter().all(|v| v.abs() < 0.02), "{rigid:?}");
        let stretched: Vec<f32> = pos
            .chunks_exact(2)
            .flat_map(|p| [0.4 + 1.1 * (p[0] - 0.4), p[1]])
            .collect();
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
        let nb = Neighbourhood::build(
            &[pos.clone(), pos.clone()].concat(),
            &[mat.clone(), mat].concat(),
            [2, 36],
            |m| m != 0,
        );
        let t = nb.upload::<Nd>(&Default::default());
        let moved: Vec<f32> = pos
            .iter()
            .enumerate()
            .map(|(i, v)| v + 0.003 * ((i * 7919 % 13) as f32 - 6.0) / 6.0)
            .collect();
        let up = Tensor::<Nd, 3>::from_data(
            TensorData::new([pos, moved].concat(), [2, 36, 2]),
            &Default::default(),
        );
        let (a, b) = (host(t.features(up.clone())), host(t.features_host(up)));
        let worst = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        assert!(worst < 1e-4, "{worst}");
        assert!(
            a.iter().any(|v| v.abs() > 1e-2),
            "the random moves strain the block"
        );
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
}
