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
//!   network learns to supply the motion the projection removes (a liquid's splash);
//! - fast particles (`fast_weight`): the MSE's squared errors weighed by each particle's true
//!   speed over its sample's mean ([`fast_weights`]), normalised over the batch;
//! - density (`density_weight`): the liquid's particles per cell on a coarse grid, prediction
//!   against truth ([`density_loss`]): on frames past a sample's first chunk it stands in for
//!   the MSE, which over a rollout carried far from the truth rewards the mean of where a
//!   splash could have gone, a flat liquid (docs/liquid.md).

use burn::tensor::backend::Backend;
use burn::tensor::Tensor;

use super::super::batch::BatchTensors;
use super::super::options::GridTrainOptions;
use crate::model::grid::NeighbourTensors;

/// One predicted frame's loss: velocity and position MSE in the loss's units (`scale`,
/// [`BatchTensors::scales`]; left out without `mse`) plus the structure, energy and density
/// terms, against `target` (`[B, N, 4]`).
pub(super) fn frame_loss<B: Backend>(
    opts: &GridTrainOptions,
    batch: &BatchTensors<B>,
    (dv_scale, pos_scale): &(Tensor<B, 3>, Tensor<B, 3>),
    (pos, vel): (&Tensor<B, 3>, &Tensor<B, 3>),
    target: &Tensor<B, 3>,
    mse: bool,
) -> Tensor<B, 1> {
    let target_vel = target.clone().narrow(2, 2, 2);
    let weights = fast_weights(opts.fast_weight, &target_vel);
    let mean = |sq: Tensor<B, 3>| match &weights {
        Some(w) => (sq * w.clone()).mean(),
        None => sq.mean(),
    };
    let lv = mean(((vel.clone() - target_vel.clone()) / dv_scale.clone()).powi_scalar(2));
    let target_pos = target.clone().narrow(2, 0, 2);
    let lx = mean(((pos.clone() - target_pos.clone()) / pos_scale.clone()).powi_scalar(2));
    let rest = batch.rest.as_ref();
    let shape = structure_loss(opts, rest, batch.liquid.as_ref(), pos, &target_pos)
        + energy_loss(opts, vel, &target_vel)
        + density_loss(opts, &batch.material, pos, &target_pos);
    match mse {
        true => lv + lx + shape,
        false => shape,
    }
}

/// Speed (domain units per time unit) added to a sample's mean speed in the fast-particle
/// weights ([`fast_weights`]), so a scene at rest weighs its particles alike.
const FAST_FLOOR: f32 = 0.1;

/// The fast-particle weights of the MSE (`fast_weight` `W` > 0; None at 0): `[B, N, 1]`,
/// `1 + W |v| / (mean_N |v| + floor)` for each particle's true speed `|v|` (`truth`: `[B, N,
/// 2]`), divided by their mean over the batch so the loss keeps the plain MSE's scale. A
/// splash's thrown particles are a few of a scene's (docs/liquid.md, "the jet"), and under
/// the plain mean the network predicts the mean of where they go; GNS-style losses weigh
/// every particle alike (Sanchez-Gonzalez et al. 2020), this one asks for the fast ones.
pub(super) fn fast_weights<B: Backend>(weight: f32, truth: &Tensor<B, 3>) -> Option<Tensor<B, 3>> {
    if weight <= 0.0 {
        return None;
    }
    let speed = truth.clone().detach().powi_scalar(2).sum_dim(2).sqrt();
    let mean = speed.clone().mean_dim(1).add_scalar(FAST_FLOOR);
    let w = (speed / mean).mul_scalar(weight).add_scalar(1.0);
    let norm = w.clone().mean().reshape([1, 1, 1]);
    Some(w / norm)
}

/// Cells per side of the density term's grid (its nodes `0..=DENSITY_CELLS`).
const DENSITY_CELLS: usize = 32;

/// The density term (`density_weight`): the liquid particles' quadratic B-spline splat on
/// the nodes `i / DENSITY_CELLS` of the unit square (`[B, n, n]`, `n = DENSITY_CELLS + 1`,
/// the weights a function of the positions, so the gradient moves particles), in units of
/// the scene's mean particles per cell, squared difference of `pred`'s and the detached
/// `truth`'s (`[B, N, 2]`) averaged over the nodes, weighted; 0 when the weight is 0.
/// `material` is the `[B, N, M]` one-hot, liquid first. The paper's density loss (section 3)
/// on MPM's kernel (`crate::bspline`).
fn density_loss<B: Backend>(
    opts: &GridTrainOptions,
    material: &Tensor<B, 3>,
    pred: &Tensor<B, 3>,
    truth: &Tensor<B, 3>,
) -> Tensor<B, 1> {
    if opts.density_weight <= 0.0 {
        return Tensor::zeros([1], &pred.device());
    }
    let [_, n, _] = pred.dims();
    let nodes = DENSITY_CELLS + 1;
    let liquid = material.clone().narrow(2, 0, 1);
    let unit = n as f32 / (DENSITY_CELLS * DENSITY_CELLS) as f32;
    let map = |x: Tensor<B, 3>| {
        let wx = axis_weights(x.clone().narrow(2, 0, 1), nodes);
        let wy = axis_weights(x.narrow(2, 1, 1), nodes) * liquid.clone();
        wx.swap_dims(1, 2).matmul(wy).div_scalar(unit)
    };
    let err = map(pred.clone()) - map(truth.clone().detach());
    err.powi_scalar(2).mean().mul_scalar(opts.density_weight)
}

/// `[B, N, nodes]`: MPM's quadratic B-spline weight of each coordinate `x` (`[B, N, 1]`,
/// domain units) at the nodes `i / (nodes - 1)`: `3/4 - r^2` for `|r| < 1/2`, `(3/2 - |r|)^2
/// / 2` for `|r| < 3/2`, 0 beyond, `r = x (nodes - 1) - i`.
fn axis_weights<B: Backend>(x: Tensor<B, 3>, nodes: usize) -> Tensor<B, 3> {
    let device = x.device();
    let i = Tensor::<B, 1, burn::tensor::Int>::arange(0..nodes as i64, &device)
        .float()
        .reshape([1, 1, nodes]);
    let r = (x.mul_scalar((nodes - 1) as f32) - i).abs();
    let near = r.clone().lower_elem(0.5).float();
    let far = r.clone().lower_elem(1.5).float() - near.clone();
    let inner = r.clone().powi_scalar(2).neg().add_scalar(0.75);
    let outer = r.neg().add_scalar(1.5).powi_scalar(2).mul_scalar(0.5);
    near * inner + far * outer
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

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::{Autodiff, NdArray};

    type Ad = Autodiff<NdArray<f32>>;

    #[test]
    fn axis_weights_are_mpms_quadratic_bspline() {
        let device = Default::default();
        // x on node 8 of 0..=32, and a quarter cell past node 20.
        let x = Tensor::<NdArray<f32>, 3>::from_floats([[[0.25], [20.25 / 32.0]]], &device);
        let w = axis_weights(x, DENSITY_CELLS + 1)
            .into_data()
            .to_vec::<f32>()
            .unwrap();
        let (on, off) = w.split_at(DENSITY_CELLS + 1);
        assert_eq!((on[7], on[8], on[9]), (0.125, 0.75, 0.125));
        // r = 0.25 from node 20: 3/4 - 1/16; 1.25 and 0.75 from 19 and 21.
        let want = [
            (19, 0.5 * 0.25 * 0.25),
            (20, 0.6875),
            (21, 0.5 * 0.75 * 0.75),
        ];
        for (i, v) in want {
            assert!((off[i] - v).abs() < 1e-6, "node {i}: {}", off[i]);
        }
        for row in [on, off] {
            assert!((row.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        }
    }

    #[test]
    fn fast_weights_weigh_the_fast_particles_and_keep_the_mean() {
        let device = Default::default();
        // One sample: three particles at rest and one moving at speed 2 (vx = 1.2, vy = 1.6).
        let v = Tensor::<NdArray<f32>, 3>::from_floats(
            [[[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [1.2, 1.6]]],
            &device,
        );
        assert!(fast_weights(0.0, &v).is_none());
        let w = fast_weights(2.0, &v).unwrap();
        assert_eq!(w.dims(), [1, 4, 1]);
        let w = w.into_data().to_vec::<f32>().unwrap();
        // Mean speed 0.5, plus the floor 0.1: the fast one 1 + 2 * 2 / 0.6, the others 1.
        let fast = 1.0 + 2.0 * 2.0 / 0.6;
        let norm = (3.0 + fast) / 4.0;
        for (got, want) in w.iter().zip([1.0, 1.0, 1.0, fast]) {
            assert!((got - want / norm).abs() < 1e-5, "{w:?}");
        }
        assert!((w.iter().sum::<f32>() / 4.0 - 1.0).abs() < 1e-6);
    }

    #[test]
    fn density_loss_sees_a_squashed_liquid_and_moves_its_particles() {
        let device = Default::default();
        let opts = GridTrainOptions {
            density_weight: 1.0,
            ..GridTrainOptions::default()
        };
        // A 10 x 10 liquid block 0.01 apart, and the same block squashed to half its height.
        let block = |squash: f32| -> Vec<f32> {
            (0..100)
                .flat_map(|i| {
                    [
                        0.4 + 0.01 * (i % 10) as f32,
                        0.1 + squash * 0.01 * (i / 10) as f32,
                    ]
                })
                .collect()
        };
        let at =
            |v: Vec<f32>| Tensor::<Ad, 1>::from_floats(v.as_slice(), &device).reshape([1, 100, 2]);
        let liquid = Tensor::<Ad, 3>::ones([1, 100, 1], &device);
        let truth = at(block(1.0));
        let same = density_loss(&opts, &liquid, &at(block(1.0)), &truth).into_scalar();
        assert_eq!(same, 0.0);
        let squashed = at(block(0.5)).require_grad();
        let loss = density_loss(&opts, &liquid, &squashed, &truth);
        assert!(
            loss.clone().into_scalar() > 0.1,
            "{}",
            loss.clone().into_scalar()
        );
        let grads = loss.backward();
        let g = squashed
            .grad(&grads)
            .unwrap()
            .into_data()
            .to_vec::<f32>()
            .unwrap();
        // The top row is pulled up (a negative gradient in y), towards the truth's height.
        let top_y: f32 = (90..100).map(|i| g[2 * i + 1]).sum();
        assert!(top_y < 0.0, "{top_y}");
    }
}
