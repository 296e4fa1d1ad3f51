//! The paper trainer's loss (`train --arch paper`; docs/design.md, "Models"; the paper's eq. 2
//! plus its density term): MSE over the next frame's scaled (x, y, vx, vy), plus `weight`
//! times the MSE between density maps of the predicted and true positions. The grid trainer
//! has its own, over short rollouts ([`crate::train::grid`], `rollout_loss.rs`).
//!
//! The density map is the one `eval` scores (`density_err`): [`crate::eval::density_map`]
//! defines it (each particle splatted onto a G x G grid over the unit square with the tent
//! kernel, normalised to mean 1 for a uniform distribution); [`density_map`] here computes
//! the same map on tensors, in f32 and differentiable in the positions. The kernel is
//! separable, so the map is one batched matrix product `Kx^T Ky` (`[B, G, N] x [B, N, G]`),
//! with no scatter. Used by [`super::Trainer`] (`minflow train --arch paper`, `minflow bench
//! train --arch paper`).

use burn::tensor::activation::relu;
use burn::tensor::backend::Backend;
use burn::tensor::Tensor;

/// Per-axis tent weights `max(0, 1 - |x G - (i + 1/2)|)` of positions against the G cell
/// centres `(i + 1/2) / G` (the kernel of [`crate::eval::density_map`]).
///
/// # Shapes
/// - `coord`: `[B, N]` in domain units -> `[B, N, G]`
fn tent<B: Backend>(coord: Tensor<B, 2>, g: usize) -> Tensor<B, 3> {
    let [b, n] = coord.dims();
    let centres = Tensor::<B, 1, burn::tensor::Int>::arange(0..g as i64, &coord.device())
        .float()
        .add_scalar(0.5)
        .reshape([1, 1, g]);
    let scaled = coord.reshape([b, n, 1]).mul_scalar(g as f32);
    relu((scaled - centres).abs().neg().add_scalar(1.0))
}

/// Density map of positions: per scene of the batch, the map [`crate::eval::density_map`]
/// defines (index `[b, ix, iy]`, weight `G^2 / N` per particle), in f32 on tensors and
/// differentiable in the positions (the test below checks the two agree).
///
/// # Shapes
/// - `pos`: `[B, N, 2]` (x, y) in domain units -> `[B, G, G]`
pub fn density_map<B: Backend>(pos: Tensor<B, 3>, g: usize) -> Tensor<B, 3> {
    let [b, n, _] = pos.dims();
    let kx = tent(pos.clone().narrow(2, 0, 1).reshape([b, n]), g);
    let ky = tent(pos.narrow(2, 1, 1).reshape([b, n]), g);
    kx.swap_dims(1, 2)
        .matmul(ky)
        .mul_scalar((g * g) as f32 / n as f32)
}

/// The loss and its two parts.
pub struct LossParts<B: Backend> {
    /// `mse + weight * density` (scalar tensor, differentiable).
    pub total: Tensor<B, 1>,
    /// MSE on scaled (x, y, vx, vy).
    pub mse: Tensor<B, 1>,
    /// Density-map MSE.
    pub density: Tensor<B, 1>,
}

/// Computes the loss.
///
/// # Shapes
/// - `pred`, `target`: `[B, N, 4]` scaled; `pred_pos`, `target_pos`: `[B, N, 2]` domain units
pub fn loss<B: Backend>(
    pred: Tensor<B, 3>,
    target: Tensor<B, 3>,
    pred_pos: Tensor<B, 3>,
    target_pos: Tensor<B, 3>,
    grid: usize,
    weight: f32,
) -> LossParts<B> {
    let mse = (pred - target).powi_scalar(2).mean();
    let density = if weight > 0.0 && grid > 0 {
        (density_map(pred_pos, grid) - density_map(target_pos, grid))
            .powi_scalar(2)
            .mean()
    } else {
        Tensor::zeros([1], &mse.device())
    };
    LossParts {
        total: mse.clone() + density.clone().mul_scalar(weight),
        mse,
        density,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::NdArray;
    use burn::tensor::TensorData;

    /// Per scene, the tensor map is `eval`'s host map (its definition) to f32 rounding, for
    /// positions inside the box, on its edges and outside it.
    #[test]
    fn density_map_is_evals_map_on_tensors() {
        let (b, n, g) = (2, 50, 8);
        let mut seed = 12345u32;
        let mut next = || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (seed >> 8) as f32 / (1u32 << 24) as f32 * 1.2 - 0.1
        };
        let mut pos: Vec<f32> = (0..b * n * 2).map(|_| next()).collect();
        pos[..6].copy_from_slice(&[0.0, 1.0, 0.5, 0.0625, 1.0, 0.5]);
        let tensor = Tensor::<NdArray<f32>, 3>::from_data(
            TensorData::new(pos.clone(), [b, n, 2]),
            &Default::default(),
        );
        let maps = density_map(tensor, g).into_data().to_vec::<f32>().unwrap();
        for (scene, map) in pos.chunks_exact(2 * n).zip(maps.chunks_exact(g * g)) {
            let state: Vec<f32> = scene
                .chunks_exact(2)
                .flat_map(|p| [p[0], p[1], 0.0, 0.0])
                .collect();
            let host = crate::eval::density_map(&state, g);
            for (a, h) in map.iter().zip(&host) {
                assert!((f64::from(*a) - h).abs() < 1e-4, "{a} against {h}");
            }
        }
    }
}
