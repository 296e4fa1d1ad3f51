//! The loss of one predicted frame of the grid trainer's rollout (`rollout_loss.rs`): the
//! MSE of the next velocity in units of `dv_scale` and of the next position in units of
//! `dv_scale * dt`, the weights of a discounted rollout's frames, and two structure terms
//! ([`crate::model::grid::rest`]):
//! - strain (`strain_weight`): for every solid rest-neighbour pair (8 nearest of the same
//!   material in the scene's first frame), the squared difference of the pair's length `|x_i -
//!   x_j| / d0_i` (`d0_i` the particle's rest neighbour distance), prediction against truth,
//!   averaged over the pairs: a body torn apart or crumpled pays for it even where each
//!   particle's own error is small;
//! - volume (`volume_weight`): for every liquid particle with liquid neighbours in the sample's
//!   first input frame, the squared difference of its fitted `J = det F` relative to that frame
//!   (clamped to `[0, 2]`), prediction against truth: liquid pressed together (J < 1 where the
//!   truth keeps 1) pays for it. MPM's liquid keeps its volume through J (docs/mpm.md); the
//!   paper adds a density-map loss for the same reason (section 3);
//! - energy (`energy_weight`): each sample's RMS particle speed against the truth's, relative:
//!   trained through the constraint projection (which only takes kinetic energy away), the
//!   network learns to supply the motion the projection removes (a liquid's splash).

use burn::tensor::backend::Backend;
use burn::tensor::Tensor;

use super::super::batch::BatchTensors;
use super::super::options::GridTrainOptions;
use crate::model::grid::NeighbourTensors;

/// One predicted frame's loss: velocity and position MSE in the loss's units (`scale`,
/// [`BatchTensors::scales`]) plus the structure terms, against `target` (`[B, N, 4]`).
pub(super) fn frame_loss<B: Backend>(
    opts: &GridTrainOptions,
    batch: &BatchTensors<B>,
    (dv_scale, pos_scale): &(Tensor<B, 3>, Tensor<B, 3>),
    pos: &Tensor<B, 3>,
    vel: &Tensor<B, 3>,
    target: &Tensor<B, 3>,
) -> Tensor<B, 1> {
    let lv = ((vel.clone() - target.clone().narrow(2, 2, 2)) / dv_scale.clone())
        .powi_scalar(2)
        .mean();
    let target_pos = target.clone().narrow(2, 0, 2);
    let lx = ((pos.clone() - target_pos.clone()) / pos_scale.clone())
        .powi_scalar(2)
        .mean();
    let rest = batch.rest.as_ref();
    let target_vel = target.clone().narrow(2, 2, 2);
    lv + lx
        + structure_loss(opts, rest, batch.liquid.as_ref(), pos, &target_pos)
        + energy_loss(opts, vel, &target_vel)
}

/// Speed (domain units per time unit) under which a sample's RMS speed error is taken
/// against this instead of its own speed, so a resting scene's noise does not weigh.
const ENERGY_FLOOR: f32 = 0.1;

/// The energy term (`energy_weight`): per sample, `((s_pred - s_true) / (s_true + floor))^2`
/// with `s` the RMS particle speed of the frame (`sqrt(mean |v|^2)`, equal particle masses,
/// so `s^2` is twice the mean kinetic energy), averaged over the batch and weighted; 0 when
/// the weight is 0. `vel` and `truth` are `[B, N, 2]`.
fn energy_loss<B: Backend>(
    opts: &GridTrainOptions,
    vel: &Tensor<B, 3>,
    truth: &Tensor<B, 3>,
) -> Tensor<B, 1> {
    if opts.energy_weight <= 0.0 {
        return Tensor::zeros([1], &vel.device());
    }
    let speed = |v: Tensor<B, 3>| {
        v.powi_scalar(2)
            .sum_dim(2)
            .mean_dim(1)
            .add_scalar(1e-8)
            .sqrt()
    };
    let (p, t) = (speed(vel.clone()), speed(truth.clone().detach()));
    let err = (p - t.clone()) / t.add_scalar(ENERGY_FLOOR);
    err.powi_scalar(2).mean().mul_scalar(opts.energy_weight)
}

/// The weights of a rollout's `frames` losses under `discount` (in `(0, 1]`): frame `j`'s
/// is `discount^j / sum_k discount^k`, so they sum to 1; all `1 / frames` for 1.
pub(super) fn frame_weights(frames: usize, discount: f32) -> Vec<f32> {
    let raw: Vec<f64> = (0..frames)
        .map(|j| f64::from(discount).powi(j as i32))
        .collect();
    let sum: f64 = raw.iter().sum();
    raw.iter().map(|w| (w / sum) as f32).collect()
}

/// The strain and volume terms of one predicted frame (see the module doc), weighted; 0
/// when both weights are 0.
fn structure_loss<B: Backend>(
    opts: &GridTrainOptions,
    rest: Option<&(NeighbourTensors<B>, f32)>,
    liquid: Option<&(NeighbourTensors<B>, f32)>,
    pred: &Tensor<B, 3>,
    truth: &Tensor<B, 3>,
) -> Tensor<B, 1> {
    let mut loss = Tensor::zeros([1], &pred.device());
    if let (Some((nb, pairs)), true) = (rest, opts.strain_weight > 0.0) {
        let stretch = |x: &Tensor<B, 3>| nb.lengths(nb.offsets(x.clone()));
        let err = (stretch(pred) - stretch(&truth.clone().detach())).powi_scalar(2);
        loss = loss + err.sum().div_scalar(*pairs).mul_scalar(opts.strain_weight);
    }
    if let (Some((nb, count)), true) = (liquid, opts.volume_weight > 0.0) {
        // J clamped to [0, 2]: a pair of particles sampled next to each other can make a
        // fitted J huge, and one such particle would outweigh the rest.
        let j = |x: &Tensor<B, 3>| nb.det(nb.offsets(x.clone())).clamp(0.0, 2.0);
        let err = (j(pred) - j(&truth.clone().detach())).powi_scalar(2);
        loss = loss + err.sum().div_scalar(*count).mul_scalar(opts.volume_weight);
    }
    loss
}
