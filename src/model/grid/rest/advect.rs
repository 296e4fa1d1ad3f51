//! The advected deformation gradient of [`super::super::Deformation::Advect`] (variant (a) of
//! the rest-shape state): each particle carries `F` (`[B, N, 4]`, row-major) from frame to
//! frame as MLS-MPM carries it, `F <- (I + dt C) F`, with `C` the affine velocity gradient
//! gathered in G2P from a grid velocity field (Hu et al. 2018, "A moving least squares
//! material point method", eq. 17-18; Jiang et al. 2015, APIC, `C_p = D_p^-1 sum_i w_ip v_i
//! (x_i - x_p)^T`, `D_p^-1 = 4 / dx^2` for quadratic B-splines). The grid velocity is the
//! P2G of the particles' predicted velocities, mass-normalised (PIC's transfer, whatever
//! [`super::super::Update`] produced them), so `C` is the gradient of the network's own
//! velocity field, smoothed over a stencil. The liquid (particles without rest neighbours)
//! keeps only `J = det F`: its `F` is reset to `sqrt(J) I` every frame, as MPM resets its
//! fluid's (docs/mpm.md).

use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor, TensorData};

use super::{matmul2, NeighbourTensors, REST_CLAMP};
use crate::model::grid::transfer::{self, Stencil};
use crate::ops::NetOps;

impl<B: Backend> NeighbourTensors<B> {
    /// `[B, N, 1]`: 1 for a particle with rest neighbours, 0 for the others (the liquid).
    pub fn has_neighbours(&self) -> Tensor<B, 3> {
        self.inv_d0.clone().greater_elem(0.0).float()
    }

    /// `[B, N, 4]`: the deformation gradient of positions `pos` (`[B, N, 2]`) fitted to the
    /// rest neighbours ([`NeighbourTensors::deformation`]), the identity for a particle
    /// without them: where an advected F starts.
    pub fn fitted(&self, pos: Tensor<B, 3>) -> Tensor<B, 3> {
        let f = self.deformation(self.offsets(pos));
        let has = self.has_neighbours();
        let [b, n] = self.dims;
        f * has.clone() + identity::<B>([b, n], &has.device()) * (has.neg().add_scalar(1.0))
    }
}

/// `[B, N, 4]`: the 2 x 2 identity, row-major, for every particle.
pub fn identity<B: Backend>([b, n]: [usize; 2], device: &B::Device) -> Tensor<B, 3> {
    Tensor::<B, 1>::from_floats([1.0, 0.0, 0.0, 1.0], device)
        .reshape([1, 1, 4])
        .repeat_dim(0, b)
        .repeat_dim(1, n)
}

/// `[B, N, REST_FEATURES]`: `E_xx, E_xy, E_yy, J - 1, 0, 0` of deformation gradients `f`
/// (`[B, N, 4]`), `E = (F^T F - I) / 2` the Green strain, clamped to `REST_CLAMP`: the same
/// layout as [`NeighbourTensors::features`], without its restoring offset (an advected F has
/// no neighbours to match).
pub fn features_of<B: Backend>(f: Tensor<B, 3>) -> Tensor<B, 3> {
    let c = |i: usize| f.clone().narrow(2, i, 1);
    let (f00, f01, f10, f11) = (c(0), c(1), c(2), c(3));
    let exx = (f00.clone().powi_scalar(2) + f10.clone().powi_scalar(2)).sub_scalar(1.0) / 2.0;
    let eyy = (f01.clone().powi_scalar(2) + f11.clone().powi_scalar(2)).sub_scalar(1.0) / 2.0;
    let exy = (f00.clone() * f01.clone() + f10.clone() * f11.clone()) / 2.0;
    let j = (f00 * f11 - f01 * f10).sub_scalar(1.0);
    let zeros = j.zeros_like();
    Tensor::cat(vec![exx, exy, eyy, j, zeros.clone(), zeros], 2).clamp(-REST_CLAMP, REST_CLAMP)
}

/// `[B, N, 4]`: the affine velocity gradient `C` (row-major, `C_ab = dv_a / dx_b`, per time
/// unit) of every particle at positions `pos` (`[B, N, 2]`, the stencil `s`'s), gathered from
/// the P2G of velocities `vel` (`[B, N, 2]`): `C_p = 4 n^2 sum_i w_ip v_i (x_i - x_p)^T`.
/// The offsets `x_i - x_p` go into the stencil's weights (two G2Ps with weights
/// `w_ip (x_i - x_p)_b n`, each offset within 1.5 cells), so nothing cancels: the same sum
/// written as `G2P(v x_i^T) - G2P(v) x_p^T` subtracts two values of size `|v| x` and, with a
/// GPU's TF32 matrix products (10-bit mantissa), loses C entirely. The offsets come from the
/// stencil's own (detached, clamped) positions, so no gradient flows through them.
pub fn velocity_gradient<B: NetOps>(
    s: &Stencil<B>,
    pos: &Tensor<B, 3>,
    vel: Tensor<B, 3>,
) -> Tensor<B, 3> {
    let [b, n_p, _] = pos.dims();
    let n = s.n;
    let device = pos.device();
    let ones = Tensor::ones([b, n_p, 1], &device);
    let splat = transfer::p2g(s, Tensor::cat(vec![ones, vel], 2)); // [B, n^2, 3]
    let mass = splat.clone().narrow(2, 0, 1);
    let v = splat.narrow(2, 1, 2) / mass.add_scalar(1e-12); // 0 where no particle splats
    let [along_x, along_y] = offset_stencils(s, pos);
    // sum_i w_ip (x_i - x_p)_b n v_i, per axis b: [B, N, 2] each (v_x, v_y).
    let (gx, gy) = (
        transfer::g2p(&along_x, v.clone()),
        transfer::g2p(&along_y, v),
    );
    let c = |g: &Tensor<B, 3>, a: usize| g.clone().narrow(2, a, 1);
    Tensor::cat(vec![c(&gx, 0), c(&gy, 0), c(&gx, 1), c(&gy, 1)], 2).mul_scalar(4.0 * n as f32)
}

/// The stencil `s` of positions `pos` with each weight `w_ip` times the node's offset from
/// the particle along x, then along y, in cells: `w_ip (x_i - x_p) n` (the stencil's
/// clamped, detached positions; the sparse and the dense form alike).
fn offset_stencils<B: NetOps>(s: &Stencil<B>, pos: &Tensor<B, 3>) -> [Stencil<B>; 2] {
    let n = s.n;
    let device = pos.device();
    let (lo, hi) = crate::ops::stencil_bounds(n);
    let g = pos.clone().detach().clamp(lo, hi).mul_scalar(n as f32); // [B, N, 2], cells
    let f = g.clone() - g.clone().sub_scalar(0.5).floor(); // from the stencil's first node
    let axis = |a: usize| -> Stencil<B> {
        let mut out = s.clone();
        let (ga, fa) = (g.clone().narrow(2, a, 1), f.clone().narrow(2, a, 1));
        // Sparse: node k of the nine is (k / 3, k % 3) from the first node.
        let steps: Vec<f32> = (0..9)
            .map(|k| if a == 0 { k / 3 } else { k % 3 } as f32)
            .collect();
        let steps =
            Tensor::<B, 1>::from_data(TensorData::new(steps, [9]), &device).reshape([1, 1, 9]);
        out.weight = s.weight.clone() * (steps - fa);
        // Dense: node i of the axis at i cells.
        if let Some((wx, wy)) = &s.dense {
            let nodes = Tensor::<B, 1, Int>::arange(0..n as i64, &device)
                .float()
                .reshape([1, 1, n]);
            let offset = nodes - ga;
            out.dense = Some(match a {
                0 => (wx.clone() * offset, wy.clone()),
                _ => (wx.clone(), wy.clone() * offset),
            });
        }
        out
    };
    [axis(0), axis(1)]
}

/// `[B, N, 4]`: `f` (`[B, N, 4]`) advected over one frame of `dt` (`[B, 1, 1]`) by the
/// velocity gradient `c` ([`velocity_gradient`]), `F' = (I + dt C) F`; where `has` (`[B, N,
/// 1]`, [`NeighbourTensors::has_neighbours`]) is 0, `F' = sqrt(J') I` with `J' = det F'`
/// (kept in `[0.05, 20]`).
pub fn advect<B: Backend>(
    f: Tensor<B, 3>,
    c: Tensor<B, 3>,
    dt: Tensor<B, 3>,
    has: Tensor<B, 3>,
) -> Tensor<B, 3> {
    let [b, n, _] = f.dims();
    let eye = identity::<B>([1, 1], &f.device());
    let step = eye.clone() + c * dt;
    let next = matmul2(step, f);
    let k = |i: usize| next.clone().narrow(2, i, 1);
    let j = (k(0) * k(3) - k(1) * k(2)).clamp(0.05, 20.0);
    let liquid = eye.repeat_dim(0, b).repeat_dim(1, n) * j.sqrt();
    next * has.clone() + liquid * has.neg().add_scalar(1.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::NdArray;
    use burn::tensor::TensorData;

    type Nd = NdArray<f32>;

    /// Particles of the block per side.
    const SIDE: usize = 30;
    /// Particles of the block.
    const COUNT: usize = SIDE * SIDE;
    /// Particle (15, 15) of the block, at (0.5, 0.5), 3.5 cells from its edges.
    const INNER: usize = 15 * SIDE + 15;

    /// A 30 x 30 block of particles 0.004 apart around (0.5, 0.5) with velocities `v(x)`.
    fn block(v: impl Fn(f32, f32) -> [f32; 2]) -> (Tensor<Nd, 3>, Tensor<Nd, 3>) {
        let (mut pos, mut vel) = (vec![], vec![]);
        for i in 0..COUNT {
            let (x, y) = (
                0.44 + 0.004 * (i % SIDE) as f32,
                0.44 + 0.004 * (i / SIDE) as f32,
            );
            pos.extend([x, y]);
            vel.extend(v(x, y));
        }
        let up =
            |d: Vec<f32>| Tensor::from_data(TensorData::new(d, [1, COUNT, 2]), &Default::default());
        (up(pos), up(vel))
    }

    fn row(t: Tensor<Nd, 3>, i: usize) -> Vec<f32> {
        let w = t.dims()[2];
        t.into_data().to_vec::<f32>().unwrap()[i * w..(i + 1) * w].to_vec()
    }

    /// A linear velocity field `v = v0 + A (x - x0)` has gradient `A` inside the body: the P2G
    /// of a linear field is linear where the stencils are full, and APIC's gather recovers it
    /// (the uniform part `v0` adds nothing).
    #[test]
    fn velocity_gradient_of_a_linear_field() {
        let a = [[0.3, -1.2], [0.7, 0.4]];
        let (pos, vel) = block(|x, y| {
            let (dx, dy) = (x - 0.5, y - 0.5);
            // A uniform part far larger than the gradient's: it must not leak into C.
            [
                3.0 + a[0][0] * dx + a[0][1] * dy,
                -5.0 + a[1][0] * dx + a[1][1] * dy,
            ]
        });
        // The sparse stencil (the CPU's) and the separable dense one (an accelerator's).
        for dense in [false, true] {
            let s = transfer::stencil(pos.clone(), 64, dense);
            let c = row(velocity_gradient(&s, &pos, vel.clone()), INNER);
            let want = [a[0][0], a[0][1], a[1][0], a[1][1]];
            for (got, want) in c.iter().zip(want) {
                assert!(
                    (got - want).abs() < 0.02,
                    "dense {dense}: {c:?} against {want:?}"
                );
            }
        }
    }

    /// Advected by a rigid rotation for 100 frames a solid's F stays a rotation (Green strain
    /// near 0, J near 1); by a uniform stretch its J grows as `(1 + dt a)^frames`; the
    /// liquid's F stays isotropic, `sqrt(J) I`.
    #[test]
    fn advected_f_follows_rotation_and_stretch() {
        let dt = Tensor::<Nd, 3>::from_floats([[[0.01]]], &Default::default());
        let spin = |x: f32, y: f32| [-(y - 0.5), x - 0.5];
        let (pos, vel) = block(spin);
        let s = transfer::stencil(pos.clone(), 64, false);
        let c = velocity_gradient(&s, &pos, vel);
        let solid = Tensor::ones([1, COUNT, 1], &Default::default());
        let mut f = identity::<Nd>([1, COUNT], &Default::default());
        for _ in 0..100 {
            f = advect(f, c.clone(), dt.clone(), solid.clone());
        }
        let e = row(features_of(f.clone()), INNER);
        // Explicit integration of a rotation grows |F| by (1 + dt^2)^(frames / 2): 0.5 %.
        assert!(e[..4].iter().all(|v| v.abs() < 0.02), "{e:?}");
        let fr = row(f, INNER);
        assert!(
            (fr[0] - 1.0f32.cos()).abs() < 0.02 && (fr[2] - 1.0f32.sin()).abs() < 0.02,
            "{fr:?}"
        );

        let (pos, vel) = block(|x, _| [0.5 * (x - 0.5), 0.0]);
        let s = transfer::stencil(pos.clone(), 64, false);
        let c = velocity_gradient(&s, &pos, vel);
        for has in [solid.clone(), solid.zeros_like()] {
            let mut f = identity::<Nd>([1, COUNT], &Default::default());
            for _ in 0..20 {
                f = advect(f, c.clone(), dt.clone(), has.clone());
            }
            let fr = row(f, INNER);
            let j = fr[0] * fr[3] - fr[1] * fr[2];
            let want = 1.005f32.powi(20);
            assert!((j - want).abs() < 0.01, "J {j} against {want}");
            if has.clone().sum().into_scalar() == 0.0 {
                assert!(
                    (fr[0] - fr[3]).abs() < 1e-5 && fr[1] == 0.0,
                    "isotropic: {fr:?}"
                );
            } else {
                assert!(
                    (fr[0] - want).abs() < 0.01 && (fr[3] - 1.0).abs() < 0.01,
                    "{fr:?}"
                );
            }
        }
    }
}
