//! The grid architecture's training loss (see [`super`]): a batch of windows uploaded as
//! physical frames (mirrored where drawn so), and the loss of P network calls of K frames each
//! over it (after M push-forward calls without gradient or loss, when asked), from the true
//! frame `T - 1`, teacher-forced for the first calls, then on the model's own predictions, the
//! memory state carried through; with C chunks the P calls run C times in a row, the rollout
//! carried from one chunk into the next with its gradient cut ([`Rollout`]). Used by
//! [`super::GridTrainer`]; the batch it reads is uploaded by `batch.rs`.
//!
//! Beside the velocity and position MSE, two structure terms ([`crate::model::grid::rest`]):
//! - strain (`strain_weight`): for every solid rest-neighbour pair (8 nearest of the same
//!   material in the scene's first frame), the squared difference of the pair's length `|x_i -
//!   x_j| / d0_i` (`d0_i` the particle's rest neighbour distance), prediction against truth,
//!   averaged over the pairs: a body torn apart or crumpled pays for it even where each
//!   particle's own error is small;
//! - volume (`volume_weight`): for every liquid particle with liquid neighbours in the sample's
//!   first input frame, the squared difference of its fitted `J = det F` relative to that frame
//!   (clamped to `[0, 2]`), prediction against truth: liquid pressed together (J < 1 where the
//!   truth keeps 1) pays for it. MPM's liquid keeps its volume through J (docs/mpm.md); the
//!   paper adds a density-map loss for the same reason (section 3).

use burn::module::Module;
use burn::tensor::backend::Backend;
use burn::tensor::{Distribution, Tensor};

use super::batch::{BatchTensors, HostRows};
use super::GridTrainOptions;
use crate::model::constraints::SceneShape;
use crate::model::grid::{GridConfig, GridModel, MemoryState, NeighbourTensors, StepInput};
use crate::model::upload;
use crate::ops::NetOps;

/// One batch's rollout in progress (see the module doc): the frames predicted so far, the
/// memory state and the carried F, so the P calls of the loss can run as several chunks of
/// P with an optimizer step after each (truncated backpropagation through time: the
/// rollout carried on from where the last chunk left it, its gradient cut there;
/// `--chunks`), as well as in one.
pub(super) struct Rollout<'a, B: Backend> {
    config: &'a GridConfig,
    opts: &'a GridTrainOptions,
    batch: BatchTensors<B>,
    /// `[B, N, 2]` velocity frames, oldest first: the T true input frames (noisy), then the
    /// frames the calls so far fed on.
    history: Vec<Tensor<B, 3>>,
    /// `[B, N, 2]` the positions the next call starts from.
    pos: Tensor<B, 3>,
    state: MemoryState<B>,
    /// The advected F ([`crate::model::grid::Deformation::Advect`]): fitted to the true
    /// frame T - 1 by the first call, then carried.
    deformation: Option<Tensor<B, 3>>,
    /// Network calls made so far (push-forward ones included).
    calls: usize,
    /// Each sample's constraint data (built from its first frame) when the options project.
    shapes: Vec<SceneShape>,
}

impl<'a, B: NetOps> Rollout<'a, B> {
    /// A rollout of `batch` about to make its first call from the true frame `T - 1`.
    pub(super) fn new(
        config: &'a GridConfig,
        opts: &'a GridTrainOptions,
        batch: BatchTensors<B>,
    ) -> Self {
        let t = config.window;
        let history = (0..t)
            .map(|k| {
                let v = batch.truth(k).narrow(2, 2, 2);
                noisy(opts, config, &batch.dt.device(), v)
            })
            .collect();
        let pos = batch.truth(t - 1).narrow(2, 0, 2);
        let shapes = match &opts.constraints {
            Some(c) => {
                let HostRows {
                    first_pos: first,
                    material,
                    dt,
                } = &batch.host;
                let n = material.len() / dt.len().max(1);
                (0..dt.len())
                    .map(|i| {
                        let rest = &first[i * n * 2..(i + 1) * n * 2];
                        SceneShape::new(rest, 2, &material[i * n..(i + 1) * n], c)
                    })
                    .collect()
            }
            None => Vec::new(),
        };
        Self {
            config,
            opts,
            batch,
            history,
            pos,
            state: MemoryState::Empty,
            deformation: None,
            calls: 0,
            shapes,
        }
    }

    /// A predicted frame (`pos`, `vel`: `[B, N, 2]`) projected onto the options' constraints
    /// with a straight-through gradient (`x + (P(x) - x)` with the move a constant); as it is
    /// without constraints or when it cannot be read back.
    fn projected(&mut self, pos: Tensor<B, 3>, vel: Tensor<B, 3>) -> (Tensor<B, 3>, Tensor<B, 3>) {
        let Some(c) = self.opts.constraints.as_ref() else {
            return (pos, vel);
        };
        let [b, n, _] = pos.dims();
        let frame = Tensor::cat(vec![pos.clone().detach(), vel.clone().detach()], 2);
        let Ok(host) = crate::model::download(frame) else {
            return (pos, vel);
        };
        // [B, N, 4] rows from the [B, N, 2 | 2] layout of the cat.
        let mut rows = host.clone();
        let HostRows { material, dt, .. } = &self.batch.host;
        let mut moved = vec![0.0f32; b * n * 4];
        for (i, shape) in self.shapes.iter_mut().enumerate() {
            let span = i * n * 4..(i + 1) * n * 4;
            shape.project(
                c,
                (None, &mut rows[span.clone()]),
                &material[i * n..(i + 1) * n],
                dt[i],
            );
            for ((m, a), o) in moved[span.clone()]
                .iter_mut()
                .zip(&rows[span.clone()])
                .zip(&host[span])
            {
                *m = a - o;
            }
        }
        let moved = upload::<B, 3>(moved, [b, n, 4], &pos.device());
        (
            pos + moved.clone().narrow(2, 0, 2),
            vel + moved.narrow(2, 2, 2),
        )
    }

    /// The M push-forward calls, on a copy of `model` whose parameters track no gradient, so
    /// they record no autodiff graph (detaching their outputs alone left every call's
    /// activations held until the backward pass: 3x the GPU memory at 24 calls); their
    /// frames, memory and F carried on detached.
    pub(super) fn pushforward(&mut self, model: &GridModel<B>) {
        if self.opts.pushforward == 0 {
            return;
        }
        let frozen = model.clone().no_grad();
        for _ in 0..self.opts.pushforward {
            for out in self.call(&frozen) {
                let (pos, vel) = self.projected(out.pos.detach(), out.vel.detach());
                self.pos = pos;
                self.history.push(vel);
            }
        }
        self.detach();
    }

    /// The loss of the next P calls (`steps`), averaged over their P K frames (weighted by
    /// [`frame_weights`] under a discount), the rollout carried on past them: teacher-forced
    /// while the call count is below `teacher`, then on the model's own predictions.
    pub(super) fn chunk_loss(&mut self, model: &GridModel<B>) -> Tensor<B, 1> {
        let opts = self.opts;
        let bundle = self.config.bundle.max(1);
        let scale = self.batch.scales(self.config);
        let frames = opts.steps.max(1) * bundle;
        // The discount's weights, or None for the plain mean (one division at the end, no
        // multiply a frame).
        let mut weights =
            (opts.discount < 1.0).then(|| frame_weights(frames, opts.discount).into_iter());
        let mut total: Option<Tensor<B, 1>> = None;
        for _ in 0..opts.steps {
            let first = self.config.window + self.calls * bundle;
            let teacher = self.calls + 1 < opts.teacher;
            for (k, out) in self.call(model).into_iter().enumerate() {
                let target = self.batch.truth(first + k);
                let (pos, vel) = match teacher {
                    true => (out.pos, out.vel),
                    false => self.projected(out.pos, out.vel),
                };
                let step = frame_loss(opts, &self.batch, &scale, &pos, &vel, &target);
                let step = match weights.as_mut() {
                    Some(w) => step.mul_scalar(w.next().expect("one weight a frame")),
                    None => step,
                };
                total = Some(match total {
                    Some(acc) => acc + step,
                    None => step,
                });
                // The next call reads the truth (teacher steps) or the bundle's own frames.
                if teacher {
                    self.pos = target.clone().narrow(2, 0, 2);
                    let v = target.narrow(2, 2, 2);
                    self.history
                        .push(noisy(opts, self.config, &self.pos.device(), v));
                } else {
                    self.pos = pos;
                    self.history.push(vel);
                }
            }
        }
        let total = total.expect("at least one step");
        match weights {
            Some(_) => total,
            None => total.div_scalar(frames as f32),
        }
    }

    /// Cuts the gradient at the rollout's current point: what the next chunk reads (frames,
    /// memory state, F) is kept detached, and frames it no longer reads are dropped.
    pub(super) fn detach(&mut self) {
        let t = self.config.window;
        let keep = self.history.split_off(self.history.len() - t);
        self.history = keep.into_iter().map(|v| v.detach()).collect();
        self.pos = self.pos.clone().detach();
        self.state = std::mem::replace(&mut self.state, MemoryState::Empty).detach();
        self.deformation = self.deformation.take().map(|f| f.detach());
    }

    /// One network call of `net` from the rollout's current point: its K frames; the memory
    /// state and F move on (the frames are the caller's to feed on).
    fn call(&mut self, net: &GridModel<B>) -> Vec<crate::model::grid::StepOutput<B>> {
        let t = self.config.window;
        let b = &self.batch;
        let input = StepInput {
            pos: self.pos.clone(),
            vel: Tensor::cat(self.history[self.history.len() - t..].to_vec(), 2),
            material: b.material.clone(),
            dt: b.dt.clone(),
            reference: Some(b.first_pos.clone()),
            rest: b.rest.as_ref().map(|(r, _)| r.clone()),
            deformation: self.deformation.take(),
        };
        let state = std::mem::replace(&mut self.state, MemoryState::Empty);
        let (outs, state) = net.step_bundle(input, state);
        self.state = state;
        self.deformation = outs.last().and_then(|o| o.deformation.clone());
        self.calls += 1;
        outs
    }
}

/// `v` (`[B, N, 2]`) with Gaussian noise of `noise * dv_scale` added (as it is without noise).
fn noisy<B: Backend>(
    opts: &GridTrainOptions,
    config: &GridConfig,
    device: &B::Device,
    v: Tensor<B, 3>,
) -> Tensor<B, 3> {
    if opts.noise <= 0.0 {
        return v;
    }
    let dv = Tensor::<B, 1>::from_floats(config.dv_scale, device).reshape([1, 1, 2]);
    let e = Tensor::random(v.dims(), Distribution::Normal(0.0, 1.0), device);
    v + e * dv.mul_scalar(opts.noise)
}

/// One predicted frame's loss: velocity and position MSE in the loss's units (`scale`,
/// [`BatchTensors::scales`]) plus the structure terms, against `target` (`[B, N, 4]`).
fn frame_loss<B: Backend>(
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
    lv + lx + structure_loss(opts, rest, batch.liquid.as_ref(), pos, &target_pos)
}

/// The weights of a rollout's `frames` losses under `discount` (in `(0, 1]`): frame `j`'s
/// is `discount^j / sum_k discount^k`, so they sum to 1; all `1 / frames` for 1.
fn frame_weights(frames: usize, discount: f32) -> Vec<f32> {
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
            dt: vec![0.016],
            material: (0..n).map(|i| (i % 2) as u8).collect(),
            ids: vec![(0, 0)],
            first_pos: (0..n).flat_map(|i| [row(0, i)[0], row(0, i)[1]]).collect(),
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

    /// `--mirror`: a flagged window's frames and reference positions are mirrored about x =
    /// 1/2 (x -> 1 - x, vx -> -vx, y and vy kept); an unflagged one is uploaded as it is.
    #[test]
    fn mirrored_windows_are_uploaded_mirrored() {
        let (b, t, n) = (2, 2, 3);
        let value = |i: usize| 0.01 * i as f32 + 0.1;
        let batch = Batch {
            b,
            t,
            n,
            inputs: (0..b * t * n * 5).map(value).collect(),
            targets: vec![0.0; b * n * 4],
            last: vec![0.0; b * n * 4],
            target_phys: (0..b * n * 4).map(|i| value(i + 7)).collect(),
            dt: vec![0.016; b],
            material: vec![0; b * n],
            ids: vec![(0, 0); b],
            first_pos: (0..b * n * 2).map(|i| value(i + 3)).collect(),
        };
        let device = Default::default();
        let none = Needs {
            materials: 4,
            ..Needs::default()
        };
        let plain = upload_batch::<NdArray<f32>>(batch.clone(), &[false, false], none, &device);
        let mirrored = upload_batch::<NdArray<f32>>(batch, &[false, true], none, &device);
        let host = |t: Tensor<NdArray<f32>, 4>| t.into_data().to_vec::<f32>().unwrap();
        let (p, m) = (host(plain.frames), host(mirrored.frames));
        let per_window = (t + 1) * n * 4;
        assert_eq!(p[..per_window], m[..per_window], "window 0 is not flagged");
        for (i, (x, y)) in p.iter().zip(&m).enumerate().skip(per_window) {
            let want = match i % 4 {
                0 => 1.0 - x,
                2 => -x,
                _ => *x,
            };
            assert_eq!(*y, want, "value {i}");
        }
        let host3 = |t: Tensor<NdArray<f32>, 3>| t.into_data().to_vec::<f32>().unwrap();
        let (p, m) = (host3(plain.first_pos), host3(mirrored.first_pos));
        assert_eq!(p[..n * 2], m[..n * 2]);
        for (i, (x, y)) in p.iter().zip(&m).enumerate().skip(n * 2) {
            assert_eq!(*y, if i % 2 == 0 { 1.0 - x } else { *x }, "reference {i}");
        }
    }
}
