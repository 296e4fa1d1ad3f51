//! Tests of the grid trainer's rollout loss (`rollout_loss.rs`): push-forward, chunks and
//! the discount against the plain rollout loss of one sample.

use super::super::batch::{upload_batch, Needs};
use super::*;
use crate::data::Batch;
use burn::backend::{Autodiff, NdArray};

/// One sample of `calls` single-frame calls (T = 2, 30 particles of two materials moving
/// uniformly under gravity) and a tiny grid model.
fn sample(calls: usize) -> (Batch, GridConfig) {
    let (t, n) = (2, 30);
    let frames = t + calls; // the inputs and the target
    let row = |f: usize, i: usize| {
        let (x0, y0) = (0.3 + 0.013 * (i % 6) as f32, 0.4 + 0.011 * (i / 6) as f32);
        let (vx, vy) = (0.2 + 0.01 * i as f32, -0.3 * f as f32 * 0.016);
        [
            x0 + vx * 0.016 * f as f32,
            y0 + vy * 0.016 * f as f32,
            vx,
            vy,
        ]
    };
    let batch = Batch {
        b: 1,
        t: frames - 1,
        n,
        inputs: (0..frames - 1)
            .flat_map(|f| (0..n).flat_map(move |i| [row(f, i).as_slice(), &[1.0]].concat()))
            .collect(),
        targets: vec![0.0; n * 4],
        last: vec![0.0; n * 4],
        target_phys: (0..n).flat_map(|i| row(frames - 1, i)).collect(),
        frames: Vec::new(),
        frame_shares: Vec::new(),
        dt: vec![0.016],
        material: (0..n).map(|i| (i % 2) as u8).collect(),
        ids: vec![(0, 0)],
        first_pos: (0..n).flat_map(|i| [row(0, i)[0], row(0, i)[1]]).collect(),
        solver_grid: vec![None],
    };
    let config = GridConfig::new(crate::model::grid::MemoryKind::MinGru)
        .with_grid(16)
        .with_levels(2)
        .with_unet_width(4)
        .with_latent(4)
        .with_hidden(4)
        .with_head_hidden(8)
        .with_dv_scale([0.1, 0.1])
        .with_head_zero_init(false);
    (batch, config)
}

/// The push-forward calls, then the P calls with a loss, in one graph.
fn sequence_loss<B: NetOps>(
    model: &GridModel<B>,
    config: &GridConfig,
    opts: &GridTrainOptions,
    batch: BatchTensors<B>,
) -> Tensor<B, 1> {
    let mut rollout = Rollout::new(config, opts, batch);
    rollout.pushforward(model);
    rollout.chunk_loss(model)
}

/// [`sequence_loss`] of `sample(calls)` under the options given, from weights seeded the
/// same for every call (the backend's own generator is shared by the tests running at
/// once).
fn loss_of_sample(calls: usize) -> impl Fn(GridTrainOptions) -> f32 {
    type B = Autodiff<NdArray<f32>>;
    let (batch, config) = sample(calls);
    let device = Default::default();
    let model = super::super::initial_grid_model::<B>(&config, 11, &device).unwrap();
    move |opts| {
        let needs = Needs {
            materials: config.materials,
            ..Needs::default()
        };
        let tensors = upload_batch::<B>(batch.clone(), &[false], needs, &device);
        sequence_loss(&model, &config, &opts, tensors).into_scalar()
    }
}

/// Push-forward: the M calls without loss are the model's own rollout (the frozen copy
/// predicts what the model does) and the loss covers the P calls after them only. So,
/// from one sample, `(M + P) L(P = M + P) = M L(P = M) + P L(P, push-forward M)`.
#[test]
fn pushforward_loss_is_the_tail_of_the_rollout_loss() {
    let (m, p) = (2, 2);
    let sample_loss = loss_of_sample(m + p);
    let loss = |steps: usize, pushforward: usize| {
        sample_loss(GridTrainOptions {
            steps,
            pushforward,
            ..GridTrainOptions::default()
        })
    };
    let (all, head, tail) = (loss(m + p, 0), loss(m, 0), loss(p, m));
    let (lhs, rhs) = ((m + p) as f32 * all, m as f32 * head + p as f32 * tail);
    assert!((lhs - rhs).abs() <= 1e-4 * lhs.abs(), "{lhs} against {rhs}");
    assert!(
        (tail - all).abs() > 1e-3 * all.abs(),
        "the tail's loss is its own: {tail}, {all}"
    );
}

/// Chunks: cutting the gradient between chunks changes no value, so the C chunks'
/// losses of one sample average to the loss of its C P calls made in one piece, the
/// memory state carried across the cuts (a chunk restarted from an empty state would
/// read other inputs and give another loss).
#[test]
fn chunked_losses_average_to_the_whole_rollout_loss() {
    type B = Autodiff<NdArray<f32>>;
    let (chunks, p) = (3, 2);
    let (batch, config) = sample(chunks * p);
    let device = Default::default();
    // Seeded weights: the backend's own generator is shared by the tests running at once.
    let model = super::super::initial_grid_model::<B>(&config, 11, &device).unwrap();
    let needs = Needs {
        materials: config.materials,
        ..Needs::default()
    };
    let tensors = || upload_batch::<B>(batch.clone(), &[false], needs, &device);
    let whole = GridTrainOptions {
        steps: chunks * p,
        ..GridTrainOptions::default()
    };
    let all = sequence_loss(&model, &config, &whole, tensors()).into_scalar();
    let opts = GridTrainOptions {
        steps: p,
        chunks,
        ..GridTrainOptions::default()
    };
    let mut rollout = Rollout::new(&config, &opts, tensors());
    let mut losses = Vec::new();
    for c in 0..chunks {
        if c > 0 {
            rollout.detach();
        }
        let loss = rollout.chunk_loss(&model);
        let grads = loss.backward();
        let params = burn::optim::GradientsParams::from_grads(grads, &model);
        assert!(!params.is_empty(), "chunk {c} has a gradient");
        losses.push(loss.into_scalar());
    }
    let mean = losses.iter().sum::<f32>() / chunks as f32;
    assert!(
        (mean - all).abs() <= 1e-4 * all.abs(),
        "{losses:?}: {mean} against {all}"
    );
    // The last chunk from an empty memory state reads other inputs.
    let mut fresh = Rollout::new(&config, &opts, tensors());
    for _ in 0..chunks - 1 {
        fresh.chunk_loss(&model);
        fresh.detach();
    }
    fresh.state = MemoryState::Empty;
    let restarted = fresh.chunk_loss(&model).into_scalar();
    let last = losses[chunks - 1];
    assert!(
        (restarted - last).abs() > 1e-4 * last.abs(),
        "{restarted} against {last} (diff {})",
        (restarted - last).abs()
    );
}

/// `--rollout-discount`: the loss of P calls under discount g is each frame's loss
/// weighted by `g^j / sum_k g^k`. Frame j's own loss comes from the undiscounted means of
/// the first j + 1 and j frames (`(j + 1) L(j + 1) - j L(j)`, the rollout being the same
/// for every P); the weights sum to 1.
#[test]
fn discounted_loss_weighs_each_frame_by_its_discount() {
    let p = 3;
    let sample_loss = loss_of_sample(p);
    let loss = |steps: usize, discount: f32| {
        sample_loss(GridTrainOptions {
            steps,
            discount,
            ..GridTrainOptions::default()
        })
    };
    let means: Vec<f32> = (0..=p)
        .map(|k| if k == 0 { 0.0 } else { loss(k, 1.0) })
        .collect();
    let frames: Vec<f32> = (0..p)
        .map(|j| (j + 1) as f32 * means[j + 1] - j as f32 * means[j])
        .collect();
    let weights = frame_weights(p, 0.5);
    assert!(
        (weights.iter().sum::<f32>() - 1.0).abs() < 1e-6,
        "{weights:?}"
    );
    assert!((weights[0] - 4.0 / 7.0).abs() < 1e-6, "{weights:?}");
    let want: f32 = frames.iter().zip(&weights).map(|(l, w)| l * w).sum();
    let got = loss(p, 0.5);
    assert!(
        (got - want).abs() <= 1e-4 * want.abs(),
        "{got} against {want}"
    );
    // The frames' losses differ, so the discount moves the loss off the plain mean.
    assert!(
        (got - means[p]).abs() > 1e-3 * means[p].abs(),
        "{got} against the mean {}",
        means[p]
    );
}
