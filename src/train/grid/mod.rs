//! Training of the grid architecture ([`crate::model::grid`]) for stable rollouts, after GNS
//! (Sanchez-Gonzalez et al. 2020, "Learning to Simulate Complex Physics with Graph
//! Networks", section 3: normalised targets, noise on the inputs), NeuralMPM (Rochman-Sharabi
//! et al. 2024: loss over short autoregressive rollouts) and LagrangeBench (Toshev et al.
//! 2023: push-forward, best checkpoint by validation rollout error).
//!
//! A sample is `T + (M + C P) K` consecutive frames of one scene (K = [`GridConfig::bundle`],
//! the frames one call predicts; M the push-forward calls, `pushforward`, 0 by default: made
//! first, on the model's own predictions, without gradient or loss, the memory carried into
//! the P; C the chunks, `chunks`, 1 by default: the P calls made C times in a row, an
//! optimizer step after each, the rollout carried on with its gradient cut between them).
//! The model makes P calls from frame `T - 1` (or after the M), each predicting K frames:
//! the first `teacher` calls read the true frames (velocities with Gaussian noise of
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
//!
//! Files: this one holds the trainer and its run over the shared epoch loop;
//! `batch.rs` the batch upload, `rollout_loss.rs` the rollout loss, `validate.rs` the validation
//! rollouts, `schedule.rs` the normalisation statistics, the learning-rate schedule and the
//! run's clock.

mod batch;
mod rollout_loss;
mod schedule;
mod validate;

pub use schedule::{fit_stats, learning_rate, StatsFit, VelocityStats};
pub use validate::validation_rollout;

use std::path::PathBuf;
use std::time::Instant;

use burn::module::AutodiffModule;
use burn::optim::adaptor::OptimizerAdaptor;
use burn::optim::{GradientsParams, Optimizer};
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::ElementConversion;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::checkpoint::{self, RunOutput};
use super::epochs::{run_epochs, EpochPass, EpochRun};
use super::optimizer::FusedAdam;
use super::source::BatchSource;
use super::{EpochRecord, Observer, TrainError};
use crate::data::{Batch, DataError, Scaler, Trajectory};
use crate::model::grid::{GridConfig, GridModel};
use crate::model::store::{self, Net, NetConfig, Surrogate};
use crate::ops::NetOps;
use batch::{prepare_batch, HostBatch, Needs};
use rollout_loss::Rollout;
use schedule::RunClock;

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
    /// Calls made before the P, without gradient and without loss (push-forward, Brandstetter
    /// et al. 2022, "Message passing neural PDE solvers", section 2.3): the P calls start
    /// from the model's own rollout of `pushforward` calls, its memory and state carried, so
    /// the loss sees the inputs a long rollout produces. 0 in runs saved before it existed.
    #[serde(default)]
    pub pushforward: usize,
    /// Chunks of P calls per sample (truncated backpropagation through time, Williams &
    /// Peng 1990): the P calls with a loss are made `chunks` times in a row, an optimizer
    /// step after each, the rollout (frames, memory state, F) carried on from one chunk to
    /// the next with its gradient cut there, so training sees `chunks P K` frames of the
    /// model's own rollout at the memory cost of P calls. 0 (runs saved before it existed)
    /// and 1: one chunk.
    #[serde(default)]
    pub chunks: usize,
    /// Input-velocity noise, in units of `dv_scale`.
    pub noise: f32,
    /// Train on each sample or, with probability 1/2, its mirror image about the box's
    /// vertical midline (`x -> 1 - x`, `vx -> -vx`; see
    /// [`crate::model::grid::mirror_rows`]).
    #[serde(default)]
    pub mirror: bool,
    /// Weight of the strain loss (solids' rest-neighbour stretch; [`rollout_loss`]).
    #[serde(default)]
    pub strain_weight: f32,
    /// Weight of the volume loss (liquid particles' fitted J; [`rollout_loss`]).
    #[serde(default)]
    pub volume_weight: f32,
    /// Discount of the loss along a sample's rollout, in `(0, 1]`: frame `j` of the P K
    /// frames (from 0) weighs `discount^j`, the weights normalised to sum to 1, so a long
    /// rollout (large P) keeps its first frames' error in view while the later frames still
    /// teach what only many frames show. 1 (the default, and runs saved before it existed):
    /// every frame alike, the plain mean.
    #[serde(default = "no_discount")]
    pub discount: f32,
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
    /// Project every frame the training rollouts feed on (after the teacher-forced calls)
    /// onto these material constraints ([`crate::model::constraints`]), with a
    /// straight-through gradient: the loss and the next call read the projected frame, the
    /// gradient passes the projection as the identity. The trained model keeps them in its
    /// `model.json`. None: no projection.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub constraints: Option<crate::model::constraints::Constraints>,
}

/// [`GridTrainOptions::discount`] of runs saved before it existed: none.
fn no_discount() -> f32 {
    1.0
}

impl Default for GridTrainOptions {
    /// A plain run: one epoch of every window, batch 1, one call per sample from the true
    /// frame, Adam at 1e-3 without decay floor or clipping, no noise, mirror, structure loss,
    /// push-forward or limits (tests and `bench train` override what they measure).
    fn default() -> Self {
        Self {
            epochs: 1,
            batch_size: 1,
            samples_per_epoch: 0,
            lr: 1e-3,
            lr_final: 0.0,
            clip: 0.0,
            steps: 1,
            teacher: 1,
            pushforward: 0,
            chunks: 1,
            noise: 0.0,
            mirror: false,
            strain_weight: 0.0,
            volume_weight: 0.0,
            discount: 1.0,
            seed: 0,
            patience: 0,
            val_starts: 1,
            val_horizon: 1,
            max_minutes: 0.0,
            constraints: None,
        }
    }
}

impl GridTrainOptions {
    /// Network calls per training sample: the push-forward ones and the P with a loss in
    /// each chunk.
    pub fn calls(&self) -> usize {
        self.pushforward + self.steps * self.chunks()
    }

    /// Chunks of P calls per sample (at least 1; [`GridTrainOptions::chunks`]).
    pub fn chunks(&self) -> usize {
        self.chunks.max(1)
    }
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

impl<B: AutodiffBackend + NetOps> GridTrainer<B>
where
    B::InnerBackend: NetOps,
{
    /// Trains on `train` (windows of `T + (M + C P) K - 1` input frames built with the identity
    /// scaler: a [`crate::data::WindowIndex`] in memory or a [`crate::data::StreamingLoader`]
    /// reading the bags chunk by chunk), validating by rollouts of `val`; `scaler` is the
    /// training split's min-max scaler (saved with the model, used for the validation score).
    /// Resumes from `out/checkpoint` when `resume`.
    ///
    /// # Errors
    /// A non-finite loss, a failed save or load, a failed validation step, a chunk of
    /// streamed scenes that could not be read.
    pub fn fit(
        &self,
        train: &mut dyn BatchSource,
        val: &[Trajectory],
        scaler: &Scaler,
        resume: bool,
        observer: &mut dyn Observer,
    ) -> Result<Vec<EpochRecord>, TrainError> {
        let opts = &self.opts;
        let needed = self.config.window + opts.calls() * self.config.bundle.max(1) - 1;
        if train.t() != needed {
            return Err(TrainError::Mismatch(format!(
                "windows of {} frames, the run needs T + (M + C P) K - 1 = {needed}",
                train.t(),
            )));
        }
        let start = self.start(resume)?;
        let per_epoch = match opts.samples_per_epoch {
            0 => train.windows(),
            s => s.min(train.windows()),
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
            output: RunOutput {
                folder: store::RunFolder::new(&self.out),
                net: NetConfig::Grid(self.config.clone()),
                scaler: *scaler,
                epochs: opts.epochs,
                patience: opts.patience,
                constraints: opts.constraints.clone(),
            },
            clock,
        };
        run_epochs(&mut run, start, observer)
    }

    /// `model` (`--init-from`) grown into what [`GridTrainer::config`] asks for, in the order
    /// the channels are laid out: reference, bundle, rest shape, update.
    fn grown(&self, model: GridModel<B>) -> GridModel<B> {
        let c = &self.config;
        let model = match c.reference {
            true => model.with_reference(),
            false => model,
        };
        let model = model.with_bundle(c.bundle);
        let model = match c.rest_shape {
            true => model.with_rest_shape().with_deformation(c.deformation),
            false => model,
        };
        model.with_update(c.update)
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
                // single-frame model grows its bundle (`GridModel::with_bundle`), then the
                // rest shape and the grid update (`model::grid::grow`).
                (Net::Grid(model), _) => self.grown(model),
                (Net::Paper(_), _) => {
                    return Err(TrainError::Mismatch(format!(
                        "{}: a paper model, where a grid model was expected",
                        dir.display()
                    )))
                }
            },
            None => initial_grid_model(&self.config, opts.seed, &self.device)?,
        };
        let clip = (opts.clip > 0.0).then_some(opts.clip);
        let mut optim = FusedAdam::default().init_clipped::<B, GridModel<B>>(clip);
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
    /// Adam per batch and chunk (`chunks`, [`Rollout`]) at the batch's decayed learning
    /// rate, the observer told after each batch. Stops
    /// early, with `out_of_time` set, once `--max-minutes` have passed since the run began.
    ///
    /// # Errors
    /// [`TrainError::NonFinite`] for a NaN or infinite batch loss; [`TrainError::Data`] for a
    /// streamed chunk that could not be read.
    fn train_epoch(
        &self,
        mut model: GridModel<B>,
        optim: &mut GridOptim<B>,
        train: &mut dyn BatchSource,
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
        let flips = ChaCha8Rng::seed_from_u64(opts.seed ^ (epoch as u64).wrapping_mul(0x9e37_79b9));
        let needs = Needs {
            rest: self.config.rest_shape || opts.strain_weight > 0.0,
            liquid_at: (opts.volume_weight > 0.0).then_some(self.config.window - 1),
            materials: self.config.materials,
        };
        let mut fetch = Instant::now();
        let batches = train.batches(opts.batch_size.max(1), Some(opts.seed), epoch as u64)?;
        let batches = batches.take(clock.batches);
        let model = std::thread::scope(|scope| {
            let feed = BatchFeed::start(scope, batches, flips, opts.mirror, needs);
            for (k, host) in std::iter::from_fn(|| feed.next()).enumerate() {
                let host = host?;
                let b = host.b();
                let tensors = host.upload::<B>(&self.device);
                pass.data_seconds += fetch.elapsed().as_secs_f64();
                let lr = learning_rate(opts, clock.progress(opts, epoch, k));
                let mut rollout = Rollout::new(&self.config, opts, tensors);
                rollout.pushforward(&model);
                let mut value = 0.0;
                for chunk in 0..opts.chunks() {
                    if chunk > 0 {
                        rollout.detach();
                    }
                    let loss = rollout.chunk_loss(&model);
                    let grads = GradientsParams::from_grads(loss.backward(), &model);
                    model = optim.step(lr, model, grads);
                    let waited = Instant::now();
                    value += loss.into_scalar().elem::<f64>() / opts.chunks() as f64;
                    pass.wait_seconds += waited.elapsed().as_secs_f64();
                }
                pass.add_step(value, b, (epoch, k, clock.batches), started, observer)?;
                if clock.out_of_time(opts) {
                    pass.out_of_time = true;
                    break;
                }
                fetch = Instant::now();
            }
            Ok::<_, TrainError>(model)
        })?;
        Ok((model, pass))
    }
}

/// The batches of an epoch, prepared on a thread of their own ([`prepare_batch`]: read,
/// packed, mirrored where `flips` draws so, neighbourhoods built) one batch ahead of the
/// step that uses them (the thread holds the one it prepared until it is taken). Each step reads its loss back at its end, so whatever the host did
/// between two steps, the GPU and burn's fusion and launch threads waited for (docs/speed.md,
/// "Where a training step's host time goes"). `MINFLOW_TRAIN_PREFETCH=off` has the thread
/// read and prepare each batch only when [`BatchFeed::next`] asks for it, as the loop did
/// itself before, to compare the two in one binary. The thread ends when the feed is
/// dropped, after the last batch, or after a batch that could not be read.
struct BatchFeed {
    /// Whether the thread works a batch ahead.
    ahead: bool,
    /// Without `ahead`: one message a batch asked for.
    ask: std::sync::mpsc::Sender<()>,
    prepared: std::sync::mpsc::Receiver<Result<HostBatch, DataError>>,
}

impl BatchFeed {
    /// Starts the thread in `scope` over `batches`; `mirror` draws a window's mirroring
    /// from `flips` (in batch order, as the loop drew them).
    fn start<'scope, I>(
        scope: &'scope std::thread::Scope<'scope, '_>,
        batches: I,
        mut flips: ChaCha8Rng,
        mirror: bool,
        needs: Needs,
    ) -> Self
    where
        I: Iterator<Item = Result<Batch, DataError>> + Send + 'scope,
    {
        let ahead = crate::switches::train_prefetch();
        // A rendezvous: the thread holds at most the one batch it prepared.
        let (ready, prepared) = std::sync::mpsc::sync_channel(0);
        let (ask, asked) = std::sync::mpsc::channel::<()>();
        scope.spawn(move || {
            let mut batches = batches;
            loop {
                if !ahead && asked.recv().is_err() {
                    return;
                }
                let Some(batch) = batches.next() else {
                    return;
                };
                let failed = batch.is_err();
                let host = batch.map(|batch| {
                    let flips: Vec<bool> = (0..batch.b)
                        .map(|_| mirror && flips.random_bool(0.5))
                        .collect();
                    prepare_batch(batch, &flips, needs)
                });
                // After an error the epoch ends: nothing more is read.
                if ready.send(host).is_err() || failed {
                    return;
                }
            }
        });
        Self {
            ahead,
            ask,
            prepared,
        }
    }

    /// The next batch; None after the last.
    fn next(&self) -> Option<Result<HostBatch, DataError>> {
        if !self.ahead {
            let _ = self.ask.send(());
        }
        self.prepared.recv().ok()
    }
}

/// Adam over a grid model, as [`GridTrainer`] builds it: one fused step per parameter
/// ([`FusedAdam`]) that clips the parameter's gradient first (`AdamStep::max_norm`, burn's
/// `GradientClipping::Norm` arithmetic).
type GridOptim<B> = OptimizerAdaptor<FusedAdam, GridModel<B>, B>;
/// The weights, the optimiser and the epochs done, where a run starts or resumes.
type GridStart<B> = (GridModel<B>, GridOptim<B>, Vec<EpochRecord>);

/// A grid run in progress: the trainer, its data, its output and its clock, as
/// [`run_epochs`] drives it.
struct GridRun<'a, B: AutodiffBackend> {
    trainer: &'a GridTrainer<B>,
    train: &'a mut dyn BatchSource,
    val: &'a [Trajectory],
    output: RunOutput,
    clock: RunClock,
}

impl<B: AutodiffBackend + NetOps> EpochRun for GridRun<'_, B>
where
    B::InnerBackend: NetOps,
{
    type Backend = B;
    type Model = GridModel<B>;
    type Optim = GridOptim<B>;

    fn output(&self) -> &RunOutput {
        &self.output
    }

    fn train_epoch(
        &mut self,
        model: GridModel<B>,
        optim: &mut GridOptim<B>,
        epoch: usize,
        observer: &mut dyn Observer,
    ) -> Result<(GridModel<B>, EpochPass), TrainError> {
        self.trainer
            .train_epoch(model, optim, &mut *self.train, epoch, &self.clock, observer)
    }

    /// The mean scaled MSE of validation rollouts ([`validation_rollout`]), times their
    /// structure factor when the run trains with a structure loss.
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
        let meta = self.output.meta(epoch, 0.0);
        let surrogate = Surrogate::from_net(Net::Grid(model.valid()), meta, &t.device);
        let (starts, horizon) = (t.opts.val_starts, t.opts.val_horizon);
        let structure = t.opts.strain_weight > 0.0 || t.opts.volume_weight > 0.0;
        Ok(validation_rollout(
            &surrogate,
            self.val,
            &self.output.scaler,
            (starts, horizon),
            structure,
        )?)
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
