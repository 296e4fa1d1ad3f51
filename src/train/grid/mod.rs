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
//! `options.rs` the run's settings, `batch.rs` the batch upload, `feed.rs` the thread that
//! prepares the batches, `rollout_loss.rs` the rollout loss (its terms in
//! `rollout_loss/terms.rs`), `validate.rs` the validation rollouts, `schedule.rs` the
//! normalisation statistics, the learning-rate schedule and the run's clock.

mod batch;
mod feed;
mod options;
mod rollout_loss;
mod schedule;
mod validate;

pub use options::GridTrainOptions;
pub use schedule::{fit_stats, learning_rate, StatsFit, VelocityStats};
pub use validate::validation_rollout;

use std::path::PathBuf;
use std::time::Instant;

use burn::module::AutodiffModule;
use burn::optim::adaptor::OptimizerAdaptor;
use burn::optim::{GradientsParams, Optimizer};
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::ElementConversion;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::checkpoint::{self, RunOutput};
use super::epochs::{run_epochs, EpochPass, EpochRun};
use super::optimizer::FusedAdam;
use super::source::BatchSource;
use super::{EpochRecord, Observer, TrainError};
use crate::data::{Scaler, Trajectory};
use crate::model::grid::{GridConfig, GridModel};
use crate::model::store::{self, Net, NetConfig, Surrogate};
use crate::ops::NetOps;
use batch::Needs;
use feed::BatchFeed;
use rollout_loss::Rollout;
use schedule::RunClock;

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
    /// the channels are laid out: reference, bundle, rest shape, update; on the configured
    /// network grid.
    fn grown(&self, model: GridModel<B>) -> GridModel<B> {
        let c = &self.config;
        let model = model.with_grid(c.grid);
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
