//! The grid architecture's training loss (see [`super`]): a batch of windows uploaded as
//! physical frames (mirrored where drawn so), and the loss of P network calls of K frames each
//! over it (after M push-forward calls without gradient or loss, when asked), from the true
//! frame `T - 1`, teacher-forced for the first calls, then on the model's own predictions, the
//! memory state carried through; with C chunks the P calls run C times in a row, the rollout
//! carried from one chunk into the next with its gradient cut ([`Rollout`]). Used by
//! [`super::GridTrainer`]; the batch it reads is uploaded by `batch.rs`. Each predicted frame's
//! loss, the velocity and position MSE and two structure terms (strain and volume), is
//! `rollout_loss/terms.rs`'s; the tests of the rollout's loss are in `rollout_loss/tests.rs`.

use burn::module::Module;
use burn::tensor::backend::Backend;
use burn::tensor::{Distribution, Tensor, TensorPrimitive};

use super::batch::{BatchTensors, HostRows};
use super::options::GridTrainOptions;
use crate::model::constraints::{projection_plan, SceneShape};
use crate::model::grid::{GridConfig, GridModel, MemoryState, StepInput};
use crate::model::upload;
use crate::ops::{NetOps, ProjectionPlan};
use terms::{frame_loss, frame_weights};

mod terms;
#[cfg(test)]
mod tests;

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
    /// The batch's projection laid out for the device, where the backend projects there and
    /// every sample's parts are ones it projects (`model::constraints::projection_plan`).
    plan: Option<ProjectionPlan>,
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
                    solver_grid,
                } = &batch.host;
                use rayon::prelude::*;
                let n = material.len() / dt.len().max(1);
                (0..dt.len())
                    .into_par_iter()
                    .map(|i| {
                        let rest = &first[i * n * 2..(i + 1) * n * 2];
                        let ids = &material[i * n..(i + 1) * n];
                        SceneShape::on_grid(rest, 2, ids, c, solver_grid[i])
                    })
                    .collect()
            }
            None => Vec::new(),
        };
        let plan = device_plan::<B>(opts, &shapes, &batch.host);
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
            plan,
        }
    }

    /// A predicted frame (`pos`, `vel`: `[B, N, 2]`) projected onto the options' constraints
    /// with a straight-through gradient (`x + (P(x) - x)` with the move a constant): on the
    /// device with the batch's plan where there is one (one H100, `-small-k4`: 165 samples/s
    /// against 110 through the host), else on the host; as it is without constraints or when
    /// it cannot be read back.
    fn projected(&mut self, pos: Tensor<B, 3>, vel: Tensor<B, 3>) -> (Tensor<B, 3>, Tensor<B, 3>) {
        let Some(c) = self.opts.constraints.as_ref() else {
            return (pos, vel);
        };
        let [b, n, _] = pos.dims();
        let frame = Tensor::cat(vec![pos.clone().detach(), vel.clone().detach()], 2);
        // On the device where it projects: no read-back, the move a constant of the graph.
        let on_device = (self.plan.as_ref()).and_then(|plan| {
            // No frame before, as on the host: the momentum and rebound parts left out.
            B::project_constraints(frame.clone().into_primitive().tensor(), None, plan)
        });
        let moved = match on_device {
            Some((projected, _)) => {
                Tensor::<B, 3>::from_primitive(TensorPrimitive::Float(projected)) - frame
            }
            None => match self.moved_on_host(c, frame, [b, n]) {
                Some(moved) => moved,
                None => return (pos, vel),
            },
        };
        (
            pos + moved.clone().narrow(2, 0, 2),
            vel + moved.narrow(2, 2, 2),
        )
    }

    /// How far the host's projection onto `c` moves each sample of `frame` (`[B, N, 4]`,
    /// detached; `bn` = `[B, N]`), as a `[B, N, 4]` tensor on its device; None when `frame`
    /// cannot be read back.
    fn moved_on_host(
        &mut self,
        c: &crate::model::constraints::Constraints,
        frame: Tensor<B, 3>,
        [b, n]: [usize; 2],
    ) -> Option<Tensor<B, 3>> {
        let device = frame.device();
        let host = crate::model::download(frame).ok()?;
        // [B, N, 4] rows from the [B, N, 2 | 2] layout of the cat; the samples projected in
        // parallel (one after another, training through the projection ran at 20 samples/s
        // against 130 without it: 10,000 particles, one H100's host).
        use rayon::prelude::*;
        let HostRows { material, dt, .. } = &self.batch.host;
        let mut moved = host.clone();
        self.shapes
            .par_iter_mut()
            .zip(moved.par_chunks_mut(n * 4))
            .zip(host.par_chunks(n * 4))
            .enumerate()
            .for_each(|(i, ((shape, rows), before))| {
                shape.project(c, (None, rows), &material[i * n..(i + 1) * n], dt[i]);
                for (m, o) in rows.iter_mut().zip(before) {
                    *m -= o;
                }
            });
        Some(upload::<B, 3>(moved, [b, n, 4], &device))
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
                // With the density term on, frames past the first chunk are scored by the
                // liquid's shape rather than each particle's place.
                let past_first = self.calls > opts.pushforward + opts.steps;
                let mse = !(opts.density_weight > 0.0 && past_first);
                let step = frame_loss(opts, &self.batch, &scale, (&pos, &vel), &target, mse);
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

/// The batch's projection laid out for the device: where the options project, the backend
/// projects on its device ([`NetOps::projects_constraints`]) and every sample's parts are
/// ones it projects (one frame a call, [`projection_plan`]); None otherwise (the host
/// projects, one sample a thread).
fn device_plan<B: NetOps>(
    opts: &GridTrainOptions,
    shapes: &[SceneShape],
    host: &HostRows,
) -> Option<ProjectionPlan> {
    let c = opts.constraints.as_ref()?;
    if !B::projects_constraints() || shapes.is_empty() {
        return None;
    }
    let shapes: Vec<&SceneShape> = shapes.iter().collect();
    projection_plan(c, &shapes, &host.material, &host.dt, 1)
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
