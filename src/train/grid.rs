//! Training of the grid architecture ([`crate::model::grid`]) for stable rollouts, after GNS
//! (Sanchez-Gonzalez et al. 2020, "Learning to Simulate Complex Physics with Graph
//! Networks", section 3: normalised targets, noise on the inputs), NeuralMPM (Rochman-Sharabi
//! et al. 2024: loss over short autoregressive rollouts) and LagrangeBench (Toshev et al.
//! 2023: push-forward, best checkpoint by validation rollout error).
//!
//! A sample is `T + P K` consecutive frames of one scene (K = [`GridConfig::bundle`], the
//! frames one call predicts). The model makes P calls from frame `T - 1`, each predicting K
//! frames: the first `teacher` calls read the true frames (velocities with Gaussian noise of
//! `noise * dv_scale`), the rest read the model's own previous predictions, and the memory
//! state runs through all P calls, so gradients flow through the state and through the
//! fed-back predictions (backpropagation through the short rollout). Loss per frame: the MSE
//! of the next velocity in units of `dv_scale` plus the MSE of the next position in units of
//! `dv_scale * dt`, averaged over the P K frames. Adam with gradient-norm clipping and a cosine
//! learning-rate decay from `lr` to `lr_final` over the run; after each epoch the validation
//! scenes are rolled out `val_horizon` frames from `val_starts` starts and the mean scaled
//! MSE (as `eval` scores, with the training split's min-max scaler) picks the kept model.
//! A model with reference positions takes each sample's from its trajectory's frame 0, in
//! training and in validation rollouts alike.
//! A checkpoint is written every epoch; a resumed run continues bit for bit (the noise and
//! the data order are reseeded from (seed, epoch)) unless a time limit (`max_minutes`) set
//! the learning-rate decay by the clock. Used by `minflow train --arch grid`.

use std::path::PathBuf;
use std::time::Instant;

use burn::grad_clipping::GradientClippingConfig;
use burn::module::AutodiffModule;
use burn::optim::adaptor::OptimizerAdaptor;
use burn::optim::{Adam, AdamConfig, GradientsParams, Optimizer};
use burn::tensor::backend::{AutodiffBackend, Backend};
use burn::tensor::{Distribution, ElementConversion, Tensor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::epochs::{run_epochs, EpochPass, EpochRun};
use super::{checkpoint, EpochRecord, Observer, TrainError};
use crate::data::{Batch, Scaler, Trajectory, WindowIndex};
use crate::eval::rollout::start_offsets;
use crate::model::grid::{mirror_rows, one_hot, GridConfig, GridModel, MemoryState, StepInput};
use crate::model::store::{self, ModelMeta, Net, NetConfig, Surrogate};
use crate::model::upload;
use crate::ops::NetOps;

/// Optimisation settings of a grid run.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct GridTrainOptions {
    /// Epochs at most.
    pub epochs: usize,
    /// Samples per optimizer step.
    pub batch_size: usize,
    /// Samples per epoch at most (0: every window of the training split).
    pub samples_per_epoch: usize,
    /// Peak learning rate.
    pub lr: f64,
    /// Learning rate at the end of the cosine decay.
    pub lr_final: f64,
    /// Gradient-norm clipping threshold (0: none).
    pub clip: f32,
    /// Steps per sample P.
    pub steps: usize,
    /// Of those, steps that read the true frame.
    pub teacher: usize,
    /// Input-velocity noise, in units of `dv_scale`.
    pub noise: f32,
    /// Train on each sample or, with probability 1/2, its mirror image about the box's
    /// vertical midline (`x -> 1 - x`, `vx -> -vx`; see
    /// [`crate::model::grid::mirror_rows`]).
    #[serde(default)]
    pub mirror: bool,
    /// Seed of the weights, data order and noise.
    pub seed: u64,
    /// Stop after this many epochs without a better validation rollout (0: never).
    pub patience: usize,
    /// Validation rollouts per scene.
    pub val_starts: usize,
    /// Validation rollout length.
    pub val_horizon: usize,
    /// Stop (after validating) once training has run this many minutes (0: no limit).
    pub max_minutes: f64,
}

/// Velocity and velocity-change statistics of `trajs` (the training split): per component
/// `vel_scale` = the velocities' standard deviation, `dv_mean` and `dv_scale` = the mean
/// and standard deviation of the change over one frame. Used to fill [`GridConfig`].
pub fn fit_stats(trajs: &[&Trajectory]) -> ([f32; 2], [f32; 2], [f32; 2]) {
    let mut v = [[0.0f64; 3]; 2]; // count, sum, sum of squares
    let mut dv = [[0.0f64; 3]; 2];
    for traj in trajs {
        for k in 0..traj.frames {
            let now = traj.state(k);
            let next = (k + 1 < traj.frames).then(|| traj.state(k + 1));
            for (p, row) in now.chunks_exact(4).enumerate() {
                for c in 0..2 {
                    let x = f64::from(row[2 + c]);
                    v[c][0] += 1.0;
                    v[c][1] += x;
                    v[c][2] += x * x;
                    if let Some(next) = next {
                        let d = f64::from(next[4 * p + 2 + c]) - x;
                        dv[c][0] += 1.0;
                        dv[c][1] += d;
                        dv[c][2] += d * d;
                    }
                }
            }
        }
    }
    let mean = |s: [f64; 3]| if s[0] > 0.0 { s[1] / s[0] } else { 0.0 };
    let std = |s: [f64; 3]| {
        let m = mean(s);
        let var = if s[0] > 0.0 { s[2] / s[0] - m * m } else { 1.0 };
        (var.max(0.0).sqrt() as f32).max(1e-6)
    };
    (
        [std(v[0]), std(v[1])],
        [mean(dv[0]) as f32, mean(dv[1]) as f32],
        [std(dv[0]), std(dv[1])],
    )
}

/// The learning rate at `progress` (0 to 1) through the run: cosine from `lr` to `lr_final`
/// (Loshchilov and Hutter 2017, "SGDR", eq. 5, one cycle).
pub fn learning_rate(opts: &GridTrainOptions, progress: f64) -> f64 {
    let progress = progress.clamp(0.0, 1.0);
    opts.lr_final
        + 0.5 * (opts.lr - opts.lr_final) * (1.0 + (std::f64::consts::PI * progress).cos())
}

/// A grid training run.
pub struct GridTrainer<B: AutodiffBackend> {
    /// The network (with its normalisation constants filled in).
    pub config: GridConfig,
    /// Optimisation settings.
    pub opts: GridTrainOptions,
    /// Run folder.
    pub out: PathBuf,
    /// Device.
    pub device: B::Device,
    /// A run folder whose weights replace the fresh ones (`--init-from`; its architecture
    /// is `config`'s). A resumed checkpoint takes precedence.
    pub init_from: Option<PathBuf>,
}

/// What [`sequence_loss`] reads of one batch, on the device, physical units.
struct BatchTensors<B: Backend> {
    /// `[B, S, N, 4]`: the window's frames and its target frame.
    frames: Tensor<B, 4>,
    /// `[B, N, 4]`: material one-hot.
    material: Tensor<B, 3>,
    /// `[B]`: frame spacing.
    dt: Tensor<B, 1>,
    /// `[B, N, 2]`: positions in the trajectory's first frame (the reference positions).
    first_pos: Tensor<B, 3>,
}

/// The tensors of a batch of windows built with the identity scaler (inputs then hold
/// physical values); the windows `w` with `mirror[w]` are mirrored ([`mirror_rows`]).
fn upload_batch<B: Backend>(batch: Batch, mirror: &[bool], device: &B::Device) -> BatchTensors<B> {
    let (b, t, n) = (batch.b, batch.t, batch.n);
    let mut frames = Vec::with_capacity(b * (t + 1) * n * 4);
    let mut first_pos = batch.first_pos;
    for w in 0..b {
        let start = frames.len();
        for k in 0..t {
            let start = ((w * t + k) * n) * 5;
            for row in batch.inputs[start..start + n * 5].chunks_exact(5) {
                frames.extend_from_slice(&row[..4]);
            }
        }
        frames.extend_from_slice(&batch.target_phys[w * n * 4..(w + 1) * n * 4]);
        if mirror.get(w).copied().unwrap_or(false) {
            mirror_rows(&mut frames[start..], 4);
            mirror_rows(&mut first_pos[w * n * 2..(w + 1) * n * 2], 2);
        }
    }
    BatchTensors {
        frames: upload(frames, [b, t + 1, n, 4], device),
        material: one_hot(&batch.material, b, n, device),
        dt: upload(batch.dt, [b], device),
        first_pos: upload(first_pos, [b, n, 2], device),
    }
}

/// The training loss of one batch (see the module doc).
fn sequence_loss<B: NetOps>(
    model: &GridModel<B>,
    config: &GridConfig,
    opts: &GridTrainOptions,
    batch: BatchTensors<B>,
) -> Tensor<B, 1> {
    let BatchTensors {
        frames,
        material,
        dt,
        first_pos,
    } = batch;
    let [b, _, n, _] = frames.dims();
    let t = config.window;
    let device = frames.device();
    let truth = |k: usize| frames.clone().narrow(1, k, 1).reshape([b, n, 4]);
    let dv_scale = Tensor::<B, 1>::from_floats(config.dv_scale, &device).reshape([1, 1, 2]);
    let noisy = |v: Tensor<B, 3>| {
        if opts.noise > 0.0 {
            let e = Tensor::random([b, n, 2], Distribution::Normal(0.0, 1.0), &device);
            v + e * dv_scale.clone().mul_scalar(opts.noise)
        } else {
            v
        }
    };
    let mut history: Vec<Tensor<B, 3>> = (0..t).map(|k| noisy(truth(k).narrow(2, 2, 2))).collect();
    let mut pos = truth(t - 1).narrow(2, 0, 2);
    let mut state = MemoryState::Empty;
    let pos_scale = dv_scale.clone() * dt.clone().reshape([b, 1, 1]);
    let bundle = config.bundle.max(1);
    let mut total: Option<Tensor<B, 1>> = None;
    for p in 0..opts.steps {
        let vel = Tensor::cat(history[history.len() - t..].to_vec(), 2);
        let input = StepInput {
            pos,
            vel,
            material: material.clone(),
            dt: dt.clone(),
            reference: Some(first_pos.clone()),
        };
        let (outs, next_state) = model.step_bundle(input, state);
        state = next_state;
        let mut last_pos = None;
        for (k, out) in outs.into_iter().enumerate() {
            let target = truth(t + p * bundle + k);
            let lv = ((out.vel.clone() - target.clone().narrow(2, 2, 2)) / dv_scale.clone())
                .powi_scalar(2)
                .mean();
            let lx = ((out.pos.clone() - target.clone().narrow(2, 0, 2)) / pos_scale.clone())
                .powi_scalar(2)
                .mean();
            let step = lv + lx;
            total = Some(match total {
                Some(acc) => acc + step,
                None => step,
            });
            // The next call reads the truth (teacher steps) or the bundle's own frames.
            if p + 1 < opts.teacher {
                last_pos = Some(target.clone().narrow(2, 0, 2));
                history.push(noisy(target.narrow(2, 2, 2)));
            } else {
                last_pos = Some(out.pos);
                history.push(out.vel);
            }
        }
        pos = last_pos.expect("a bundle has at least one frame");
    }
    total
        .expect("at least one step")
        .div_scalar((opts.steps.max(1) * bundle) as f32)
}

/// Mean scaled MSE of `horizon`-frame rollouts of `surrogate` from `starts` starts of every
/// trajectory (all starts of a scene as one batch).
///
/// # Errors
/// A step failed ([`store::StoreError`]).
pub fn validation_rollout<B: NetOps>(
    surrogate: &Surrogate<B>,
    trajs: &[Trajectory],
    scaler: &Scaler,
    starts: usize,
    horizon: usize,
) -> Result<f64, store::StoreError> {
    let window = surrogate.meta().window();
    let (mut sum, mut count) = (0.0f64, 0usize);
    for traj in trajs {
        let offsets = start_offsets(traj.frames, window, horizon, starts);
        let offsets: Vec<usize> = offsets
            .into_iter()
            .filter(|&o| o + window + horizon <= traj.frames)
            .collect();
        if offsets.is_empty() {
            continue;
        }
        let (b, n) = (offsets.len(), traj.n);
        let material: Vec<u8> = (0..b).flat_map(|_| traj.material.iter().copied()).collect();
        let dt = vec![traj.dt; b];
        let first: Vec<f32> = (0..b).flat_map(|_| traj.state(0).iter().copied()).collect();
        let mut state = surrogate.init_state_at(&first, b)?;
        for k in 0..window - 1 {
            let frame: Vec<f32> = offsets
                .iter()
                .flat_map(|&o| traj.state(o + k).iter().copied())
                .collect();
            state = surrogate.step(&frame, &material, &dt, state)?.1;
        }
        // ceil(horizon / K) calls, each from the last frame the one before predicted.
        let mut next: Vec<f32> = offsets
            .iter()
            .flat_map(|&o| traj.state(o + window - 1).iter().copied())
            .collect();
        let mut k = 0;
        while k < horizon {
            let (bundle, s) = surrogate.step_bundle(&next, &material, &dt, state)?;
            state = s;
            for pred in bundle.into_iter().take(horizon - k) {
                for (row, &o) in offsets.iter().enumerate() {
                    let truth = traj.state(o + window + k);
                    let pred = &pred[row * n * 4..(row + 1) * n * 4];
                    for (p, t) in pred.chunks_exact(4).zip(truth.chunks_exact(4)) {
                        for f in 0..4 {
                            let d =
                                f64::from(scaler.scale(f, p[f])) - f64::from(scaler.scale(f, t[f]));
                            sum += d * d;
                        }
                    }
                    count += n * 4;
                }
                k += 1;
                next = pred;
            }
        }
    }
    Ok(if count == 0 {
        f64::NAN
    } else {
        sum / count as f64
    })
}

impl<B: AutodiffBackend + NetOps> GridTrainer<B>
where
    B::InnerBackend: NetOps,
{
    /// Trains on `train` (windows of `T + P - 1` input frames built with the identity
    /// scaler), validating by rollouts of `val`; `scaler` is the training split's min-max
    /// scaler (saved with the model, used for the validation score). Resumes from
    /// `out/checkpoint` when `resume`.
    ///
    /// # Errors
    /// A non-finite loss, a failed save or load, a failed validation step.
    pub fn fit(
        &self,
        train: &WindowIndex,
        val: &[Trajectory],
        scaler: &Scaler,
        resume: bool,
        observer: &mut dyn Observer,
    ) -> Result<Vec<EpochRecord>, TrainError> {
        let opts = &self.opts;
        let needed = self.config.window + opts.steps * self.config.bundle.max(1) - 1;
        if train.t() != needed {
            return Err(TrainError::Mismatch(format!(
                "windows of {} frames, the run needs T + P K - 1 = {needed}",
                train.t(),
            )));
        }
        let start = self.start(resume)?;
        let per_epoch = match opts.samples_per_epoch {
            0 => train.len(),
            s => s.min(train.len()),
        };
        let batches = per_epoch.div_ceil(opts.batch_size.max(1));
        let clock = RunClock {
            started: Instant::now(),
            total_steps: batches * opts.epochs,
            batches,
        };
        let mut run = GridRun {
            trainer: self,
            train,
            val,
            scaler: *scaler,
            clock,
        };
        run_epochs(&mut run, start, observer)
    }

    /// The run's starting point: the weights (fresh, or `init_from`'s), Adam (with clipping
    /// when `clip > 0`) and the epochs done so far, all three from `out/checkpoint` when
    /// `resume` finds one.
    ///
    /// # Errors
    /// `init_from` or the checkpoint could not be loaded, or `init_from` is a paper model.
    fn start(&self, resume: bool) -> Result<GridStart<B>, TrainError> {
        let opts = &self.opts;
        B::seed(&self.device, opts.seed);
        let mut model: GridModel<B> = match &self.init_from {
            Some(dir) => match store::load_net::<B>(dir, &self.device)? {
                // A model without reference channels grows them, their weights zero; a
                // single-frame model grows its bundle (`GridModel::with_bundle`).
                (Net::Grid(model), _) if self.config.reference => {
                    model.with_reference().with_bundle(self.config.bundle)
                }
                (Net::Grid(model), _) => model.with_bundle(self.config.bundle),
                (Net::Paper(_), _) => {
                    return Err(TrainError::Mismatch(format!(
                        "{}: a paper model, where a grid model was expected",
                        dir.display()
                    )))
                }
            },
            None => initial_grid_model(&self.config, opts.seed, &self.device)?,
        };
        let mut adam = AdamConfig::new().with_epsilon(1e-8);
        if opts.clip > 0.0 {
            adam = adam.with_grad_clipping(Some(GradientClippingConfig::Norm(opts.clip)));
        }
        let mut optim = adam.init::<B, GridModel<B>>();
        let mut history = Vec::new();
        if resume {
            if let Some(state) = checkpoint::load::<B, _, _>(
                &self.out,
                self.config.init::<B>(&self.device),
                &self.device,
                &optim,
            )? {
                model = state.model;
                optim = optim.load_record(state.optim);
                history = state.history;
            }
        }
        Ok((model, optim, history))
    }

    /// One pass over `clock.batches` batches of `train` (epoch `epoch`, 0-based): a step of
    /// Adam per batch at the decayed learning rate, the observer told after each. Stops
    /// early, with `out_of_time` set, once `--max-minutes` have passed since the run began.
    ///
    /// # Errors
    /// [`TrainError::NonFinite`] for a NaN or infinite batch loss.
    fn train_epoch(
        &self,
        mut model: GridModel<B>,
        optim: &mut GridOptim<B>,
        train: &WindowIndex,
        epoch: usize,
        clock: &RunClock,
        observer: &mut dyn Observer,
    ) -> Result<(GridModel<B>, EpochPass), TrainError> {
        let opts = &self.opts;
        B::seed(
            &self.device,
            opts.seed.wrapping_mul(1_000_003).wrapping_add(epoch as u64),
        );
        let started = Instant::now();
        let mut pass = EpochPass::default();
        let mut flips =
            ChaCha8Rng::seed_from_u64(opts.seed ^ (epoch as u64).wrapping_mul(0x9e37_79b9));
        let mut fetch = Instant::now();
        for (k, batch) in train
            .batches(opts.batch_size.max(1), Some(opts.seed), epoch as u64)
            .take(clock.batches)
            .enumerate()
        {
            let b = batch.b;
            let mirror: Vec<bool> = (0..b)
                .map(|_| opts.mirror && flips.random_bool(0.5))
                .collect();
            let tensors = upload_batch::<B>(batch, &mirror, &self.device);
            pass.data_seconds += fetch.elapsed().as_secs_f64();
            let loss = sequence_loss(&model, &self.config, opts, tensors);
            let grads = GradientsParams::from_grads(loss.backward(), &model);
            let lr = learning_rate(opts, clock.progress(opts, epoch, k));
            model = optim.step(lr, model, grads);
            let waited = Instant::now();
            let value: f64 = loss.into_scalar().elem();
            pass.wait_seconds += waited.elapsed().as_secs_f64();
            if !value.is_finite() {
                return Err(TrainError::NonFinite {
                    epoch: epoch + 1,
                    batch: k,
                    loss: value as f32,
                });
            }
            pass.sum += value * b as f64;
            pass.seen += b;
            let rate = pass.seen as f64 / started.elapsed().as_secs_f64().max(1e-9);
            let mean = pass.sum / pass.seen as f64;
            observer.batch(epoch + 1, k + 1, clock.batches, mean, rate);
            if clock.out_of_time(opts) {
                pass.out_of_time = true;
                break;
            }
            fetch = Instant::now();
        }
        Ok((model, pass))
    }

    /// What `model.json` says of a checkpoint of epoch `epoch` with `val_loss`.
    fn meta(&self, scaler: &Scaler, epoch: usize, val_loss: f64) -> ModelMeta {
        ModelMeta {
            net: NetConfig::Grid(self.config.clone()),
            scaler: *scaler,
            epoch,
            val_loss,
        }
    }
}

/// Adam over a grid model, as [`GridTrainer`] builds it.
type GridOptim<B> = OptimizerAdaptor<Adam, GridModel<B>, B>;
/// The weights, the optimiser and the epochs done, where a run starts or resumes.
type GridStart<B> = (GridModel<B>, GridOptim<B>, Vec<EpochRecord>);

/// Where a run is in its schedule.
struct RunClock {
    started: Instant,
    /// Batches per epoch, and over all epochs.
    batches: usize,
    total_steps: usize,
}

impl RunClock {
    /// Progress through the run (0 to 1) at batch `k` of `epoch`: by steps, or by time when
    /// a time limit ends the run first (the decay then finishes at the limit).
    fn progress(&self, opts: &GridTrainOptions, epoch: usize, k: usize) -> f64 {
        let steps = (epoch * self.batches + k) as f64 / self.total_steps.max(1) as f64;
        if opts.max_minutes > 0.0 {
            steps.max(self.started.elapsed().as_secs_f64() / (opts.max_minutes * 60.0))
        } else {
            steps
        }
    }

    /// Whether `--max-minutes` have passed since the run began.
    fn out_of_time(&self, opts: &GridTrainOptions) -> bool {
        opts.max_minutes > 0.0 && self.started.elapsed().as_secs_f64() > opts.max_minutes * 60.0
    }
}

/// A grid run in progress: the trainer, its data and its clock, as [`run_epochs`] drives it.
struct GridRun<'a, B: AutodiffBackend> {
    trainer: &'a GridTrainer<B>,
    train: &'a WindowIndex,
    val: &'a [Trajectory],
    scaler: Scaler,
    clock: RunClock,
}

impl<B: AutodiffBackend + NetOps> EpochRun for GridRun<'_, B>
where
    B::InnerBackend: NetOps,
{
    type Model = GridModel<B>;
    type Optim = GridOptim<B>;

    fn limits(&self) -> (usize, usize) {
        (self.trainer.opts.epochs, self.trainer.opts.patience)
    }

    fn train_epoch(
        &mut self,
        model: GridModel<B>,
        optim: &mut GridOptim<B>,
        epoch: usize,
        observer: &mut dyn Observer,
    ) -> Result<(GridModel<B>, EpochPass), TrainError> {
        self.trainer
            .train_epoch(model, optim, self.train, epoch, &self.clock, observer)
    }

    /// The mean scaled MSE of validation rollouts ([`validation_rollout`]).
    fn validate(
        &mut self,
        model: &GridModel<B>,
        epoch: usize,
        train_loss: f64,
    ) -> Result<f64, TrainError> {
        let t = self.trainer;
        if self.val.is_empty() {
            return Ok(train_loss);
        }
        let meta = t.meta(&self.scaler, epoch, 0.0);
        let surrogate = Surrogate::from_net(Net::Grid(model.valid()), meta, &t.device);
        let (starts, horizon) = (t.opts.val_starts, t.opts.val_horizon);
        Ok(validation_rollout(
            &surrogate,
            self.val,
            &self.scaler,
            starts,
            horizon,
        )?)
    }

    fn save_best(
        &self,
        model: &GridModel<B>,
        epoch: usize,
        val_loss: f64,
    ) -> Result<(), TrainError> {
        let meta = self.trainer.meta(&self.scaler, epoch, val_loss);
        Ok(store::save(&self.trainer.out, model, &meta)?)
    }

    fn checkpoint(
        &self,
        model: &GridModel<B>,
        optim: &GridOptim<B>,
        history: &[EpochRecord],
    ) -> Result<(), TrainError> {
        checkpoint::save(&self.trainer.out, model, optim, history)
    }
}

/// Fresh weights from `seed`, drawn on the CPU and moved to `device` (as
/// [`super::initial_model`] does for the paper's model), so every backend starts alike.
///
/// # Errors
/// Moving the record failed.
pub fn initial_grid_model<B: NetOps>(
    config: &GridConfig,
    seed: u64,
    device: &B::Device,
) -> Result<GridModel<B>, TrainError> {
    super::drawn_on_cpu(
        seed,
        |cpu| config.init(cpu),
        config.init::<B>(device),
        device,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::NdArray;

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
        let plain = upload_batch::<NdArray<f32>>(batch.clone(), &[false, false], &device);
        let mirrored = upload_batch::<NdArray<f32>>(batch, &[false, true], &device);
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
