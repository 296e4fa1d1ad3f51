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
//! A checkpoint is written every epoch, every `--checkpoint-minutes` within one, and when the
//! call's share ends (`--call-minutes`, `--call-steps`: [`CallShare`]); a resumed run
//! continues bit for bit from any of them, mid-epoch too (the data order is seeded from
//! (seed, pass), a batch's mirroring and noise from its place in the run) unless a time limit
//! (`max_minutes`) set the learning-rate decay by the clock. Used by `minflow train --arch
//! grid`.
//!
//! Files: this one holds the trainer; `pass.rs` its run over the shared epoch loop and an
//! epoch's pass over the batches; `parallel.rs` the data-parallel step over several devices (its all-reduce: `train::reduce`); `options.rs` the run's settings, `batch.rs` the batch upload, `feed.rs` the thread that
//! prepares the batches, `rollout_loss.rs` the rollout loss (its terms in
//! `rollout_loss/terms.rs`), `validate.rs` the validation rollouts, `schedule.rs` the
//! normalisation statistics, the learning-rate schedule and the run's clock.

mod batch;
mod feed;
mod options;
mod parallel;
mod pass;
mod rollout_loss;
mod schedule;
mod validate;

pub use feed::feed_rate;
pub use options::GridTrainOptions;
pub use schedule::{fit_stats, learning_rate, StatsFit, VelocityStats};
pub use validate::validation_rollout;

use std::path::PathBuf;
use std::time::Instant;

use burn::optim::adaptor::OptimizerAdaptor;
use burn::optim::Optimizer;
use burn::tensor::backend::AutodiffBackend;

use super::checkpoint::{self, RunOutput};
use super::epochs::{run_epochs, Start};
use super::ledger::{CallShare, DatasetInfo, RunLedger};
use super::optimizer::FusedAdam;
use super::source::BatchSource;
use super::{EpochRecord, Observer, TrainError};
use crate::data::{Scaler, Trajectory};
use crate::model::grid::{GridConfig, GridModel};
use crate::model::store::{self, Net, NetConfig};
use crate::ops::NetOps;
use pass::GridRun;
use schedule::RunClock;

/// A grid training run.
pub struct GridTrainer<B: AutodiffBackend> {
    /// The network (with its normalisation constants filled in).
    pub config: GridConfig,
    /// Optimisation settings.
    pub opts: GridTrainOptions,
    /// Run folder.
    pub out: PathBuf,
    /// The main device: it holds the model between steps, validates and checkpoints.
    pub device: B::Device,
    /// More devices to train data-parallel on with the main one (`parallel.rs`; none: one
    /// device).
    pub replicas: Vec<B::Device>,
    /// A run folder whose weights replace the fresh ones (`--init-from`; its architecture
    /// is `config`'s). A resumed checkpoint takes precedence.
    pub init_from: Option<PathBuf>,
    /// What this call may do before it checkpoints mid-epoch and ends, and how often it
    /// checkpoints meanwhile (its clock starts when [`GridTrainer::fit`] does).
    pub share: CallShare,
    /// What the run trains on, for its ledger (`run.json`).
    pub dataset: DatasetInfo,
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
    /// streamed scenes that could not be read; validation scenes all shorter than `T +
    /// val_horizon` frames ([`TrainError::Mismatch`], before any step).
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
        let longest = val.iter().map(|v| v.frames).max();
        if longest.is_some_and(|f| f < self.config.window + opts.val_horizon) {
            // No validation rollout would fit: every epoch would score NaN and none be kept.
            return Err(TrainError::Mismatch(format!(
                "--val-horizon {} needs validation scenes of T + {} = {} frames; the longest \
                 has {}: lower --val-horizon",
                opts.val_horizon,
                opts.val_horizon,
                self.config.window + opts.val_horizon,
                longest.unwrap_or(0),
            )));
        }
        let (start, ledger) = self.start(resume)?;
        // An epoch is a pass over the data, or `samples_per_epoch` of it: then the epochs
        // go on through the passes where the one before stopped (`pass.rs`).
        let pass_batches = train.num_batches(opts.batch_size.max(1));
        let batches = match opts.samples_per_epoch {
            0 => pass_batches,
            s => s.div_ceil(opts.batch_size.max(1)).min(pass_batches),
        };
        let clock = RunClock {
            started: Instant::now(),
            total_steps: batches * opts.epochs,
            batches,
        };
        let devices = (self.devices().iter()).map(|d| format!("{d:?}")).collect();
        let mut run = GridRun {
            trainer: self,
            train,
            pass_batches,
            val,
            output: RunOutput {
                folder: store::RunFolder::new(&self.out),
                net: NetConfig::Grid(self.config.clone()),
                scaler: *scaler,
                epochs: opts.epochs,
                patience: opts.patience,
                keep_epochs: opts.keep_epochs,
                constraints: opts.constraints.clone(),
                ledger: RunLedger::begin_call(ledger, devices, self.dataset.clone()).shared(),
                call_started: Instant::now(),
            },
            clock,
            share: self.share.restarted(),
            streams: super::stream_ids(1 + self.replicas.len()),
        };
        run_epochs(&mut run, start, observer)
    }

    /// Every device it trains on, the main one first.
    pub fn devices(&self) -> Vec<B::Device> {
        let main = std::iter::once(self.device.clone());
        main.chain(self.replicas.iter().cloned()).collect()
    }

    /// A fresh Adam for the run's model, clipping each gradient's norm to `--clip` when
    /// it is positive.
    fn optimizer(&self) -> GridOptim<B> {
        let clip = (self.opts.clip > 0.0).then_some(self.opts.clip);
        FusedAdam::default().init_clipped::<B, GridModel<B>>(clip)
    }

    /// `model` (`--init-from`) grown into what [`GridTrainer::config`] asks for, in the order
    /// the channels are laid out: reference, bundle, rest shape, update; then the message
    /// passing; on the configured network grid.
    fn grown(&self, model: GridModel<B>) -> GridModel<B> {
        let c = &self.config;
        let model = (model.with_grid(c.grid))
            .with_substeps(c.substeps)
            .with_box_grid(c.box_grid);
        let model = match c.reference {
            true => model.with_reference(),
            false => model,
        };
        let model = model.with_bundle(c.bundle);
        let model = match c.rest_shape {
            true => model.with_rest_shape().with_deformation(c.deformation),
            false => model,
        };
        model.with_update(c.update).with_interaction(c)
    }

    /// The run's starting point: the weights (fresh, or `init_from`'s), Adam (with clipping
    /// when `clip > 0`), the epochs done so far and the unfinished one, all from
    /// `out/checkpoint` when `resume` finds one; and the run's ledger there.
    ///
    /// # Errors
    /// `init_from` or the checkpoint could not be loaded, or `init_from` is a paper model.
    fn start(&self, resume: bool) -> Result<(GridStart<B>, Option<RunLedger>), TrainError> {
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
        let mut optim = self.optimizer();
        let (mut history, mut unfinished, mut ledger) = (Vec::new(), None, None);
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
                unfinished = state.unfinished;
                ledger = state.ledger;
            }
        }
        Ok(((model, optim, history, unfinished), ledger))
    }
}

/// Adam over a grid model, as [`GridTrainer`] builds it: one fused step per parameter
/// ([`FusedAdam`]) that clips the parameter's gradient first (`AdamStep::max_norm`, burn's
/// `GradientClipping::Norm` arithmetic).
type GridOptim<B> = OptimizerAdaptor<FusedAdam, GridModel<B>, B>;
/// The weights, the optimiser, the epochs done and the unfinished one, where a run starts
/// or resumes.
type GridStart<B> = Start<GridModel<B>, GridOptim<B>>;

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
