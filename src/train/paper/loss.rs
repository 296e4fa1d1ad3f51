//! The paper trainer's loss (`train --arch paper`; docs/design.md, "Models"; the paper's eq. 2
//! plus its density term): MSE over the next frame's scaled (x, y, vx, vy), plus `weight`
//! times the MSE between density maps of the predicted and true positions. The grid trainer
//! has its own, over short rollouts ([`crate::train::grid`], `rollout_loss.rs`).
//!
//! The density map splats each particle onto a G x G grid over the unit square with the
//! bilinear (tent) kernel `w(x) = max(0, 1 - |x G - (i + 1/2)|)` per axis. The kernel is
//! separable, so the map is one batched matrix product `Kx^T Ky` (`[B, G, N] x [B, N, G]`),
//! differentiable in the positions, with no scatter. Maps are normalised to mean 1 for a
//! uniform distribution (`G^2 / N` per particle). Used by [`super::Trainer`] (`minflow train
//! --arch paper`, `minflow bench train --arch paper`).

use burn::tensor::activation::relu;
use burn::tensor::backend::Backend;
use burn::tensor::Tensor;

/// Per-axis tent weights of positions against G cell centres.
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

/// Density map of positions.
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
