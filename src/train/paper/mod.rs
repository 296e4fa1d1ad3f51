//! Training of the paper's architecture ([`crate::model::paper`]; docs/design.md, "Models"):
//! Adam (lr 1e-3, epsilon 1e-8 as PyTorch), effective batch reached by micro-batches with
//! gradient accumulation, the loss on the next frame ([`loss`]), and the shared epoch
//! loop ([`super::epochs`]: early stopping on the validation loss, best model kept,
//! checkpoint every epoch so a killed run resumes bit for bit; the backend RNG and the data
//! order are reseeded from (seed, epoch)). Backend-generic: the initial weights are always
//! drawn on the CPU backend from the seed and then moved to the training device, so a CUDA
//! run starts from the same weights as a CPU run. Batches are assembled on a helper thread
//! one ahead of the device, and the loss is read back once per optimizer step (after the
//! step is queued), so an accelerator is not left waiting on the host between micro-batches.
//! Used by `minflow train --arch paper` and `minflow bench train --arch paper`.
//!
//! Files: this one holds the trainer and its run over the shared epoch loop, `step.rs` an
//! epoch's pass and its optimizer steps, `replicas.rs` its data-parallel steps, `slices.rs`
//! the micro-batches, `loss.rs` their loss.

pub mod loss;
mod replicas;
mod slices;
mod step;

pub use slices::evaluate;

use super::checkpoint::{self, RunOutput};
use super::epochs::{run_epochs, EpochPass, EpochRun, Start};
use super::ledger::{DatasetInfo, RunLedger};
use super::{drawn_on_cpu, optimizer, BatchSource, EpochRecord, Observer, TrainError};
use crate::data::{Scaler, WindowIndex};
use crate::model::store::{NetConfig, RunFolder};
use crate::model::{Model, ModelConfig, Scaling};
use burn::module::AutodiffModule;
use burn::optim::adaptor::OptimizerAdaptor;
use burn::optim::Optimizer;
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::StreamId;
use std::path::PathBuf;
use std::time::Instant;

/// Optimisation settings.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct TrainOptions {
    /// Epochs to run at most.
    pub epochs: usize,
    /// Effective batch size (windows per optimizer step).
    pub batch_size: usize,
    /// Windows per forward/backward pass; gradients are accumulated up to `batch_size`.
    pub micro_batch: usize,
    /// Adam learning rate.
    pub lr: f64,
    /// Seed of weights, data order and dropout.
    pub seed: u64,
    /// Stop after this many epochs without a better validation loss (0: never).
    pub patience: usize,
    /// Density-map grid size G.
    pub density_grid: usize,
    /// Weight of the density-map loss.
    pub density_weight: f32,
}

/// Fresh weights from `seed`, drawn on the CPU backend whatever `B` is and moved to `device`
/// through an f32 record, so runs on different backends start from identical weights. (For
/// `B` on ndarray these are the weights `config.init::<B>` draws after seeding.)
pub fn initial_model<B: crate::ops::NetOps>(
    config: &ModelConfig,
    seed: u64,
    device: &B::Device,
) -> Result<Model<B>, TrainError> {
    drawn_on_cpu(
        seed,
        |cpu| config.init(cpu),
        config.init::<B>(device),
        device,
    )
}

/// A training run over in-memory windows.
pub struct Trainer<B: AutodiffBackend> {
    /// Network hyper-parameters.
    pub config: ModelConfig,
    /// Optimisation settings.
    pub opts: TrainOptions,
    /// Output folder.
    pub out: PathBuf,
    /// The devices it trains on (never empty); the first, the main device, holds the model
    /// between epochs, validates and checkpoints; more than one train data-parallel.
    devices: Vec<B::Device>,
    /// What the run trains on, for its ledger (`run.json`).
    pub dataset: DatasetInfo,
}

impl<B: AutodiffBackend + crate::ops::NetOps> Trainer<B>
where
    B::InnerBackend: crate::ops::NetOps,
{
    /// A trainer writing to `out`.
    pub fn new(config: ModelConfig, opts: TrainOptions, out: PathBuf, device: B::Device) -> Self {
        Self::data_parallel(config, opts, out, vec![device])
    }

    /// A trainer that trains data-parallel on `devices` (the first is the main device): each
    /// further device keeps a replica of the model and of Adam through an epoch, each device
    /// runs forward and backward on its share of the batch's micro-batches, the gradients
    /// are summed over the devices by the all-reduce the grid trainer uses
    /// ([`crate::train::reduce`]: NCCL's on CUDA), and every device takes the same step. The
    /// effective batch, the data order and the loss scaling are those of a one-device run;
    /// only the dropout masks differ (each device draws its own).
    ///
    /// # Panics
    /// If `devices` is empty.
    pub fn data_parallel(
        config: ModelConfig,
        opts: TrainOptions,
        out: PathBuf,
        devices: Vec<B::Device>,
    ) -> Self {
        assert!(
            !devices.is_empty(),
            "data_parallel needs at least one device"
        );
        Self {
            config,
            opts,
            out,
            devices,
            dataset: DatasetInfo::default(),
        }
    }

    /// The main device.
    fn main(&self) -> &B::Device {
        &self.devices[0]
    }

    /// Trains on `train`, validating on `val`; resumes from `out/checkpoint` when `resume`.
    /// `on_epoch` sees each finished epoch with the number of batches per epoch.
    pub fn fit(
        &self,
        train: &WindowIndex,
        val: Option<&WindowIndex>,
        scaler: &Scaler,
        resume: bool,
        mut on_epoch: impl FnMut(&EpochRecord, usize),
    ) -> Result<Vec<EpochRecord>, TrainError> {
        struct Adapter<'a, F: FnMut(&EpochRecord, usize)>(&'a mut F, usize);
        impl<F: FnMut(&EpochRecord, usize)> Observer for Adapter<'_, F> {
            fn epoch(&mut self, record: &EpochRecord, _: &[EpochRecord]) {
                (self.0)(record, self.1)
            }
        }
        let batches = train.num_batches(self.opts.batch_size.max(1));
        let mut train = train;
        let mut val = val;
        self.fit_observed(
            &mut train,
            val.as_mut().map(|v| v as &mut dyn BatchSource),
            scaler,
            resume,
            &mut Adapter(&mut on_epoch, batches),
        )
    }

    /// [`Trainer::fit`] over any [`BatchSource`] (in memory or streamed from the bags),
    /// reporting to an [`Observer`] (per batch and per epoch).
    ///
    /// Per epoch ([`run_epochs`]): seed every device, train ([`Trainer::train_epoch`]),
    /// validate, save the model when its validation loss is the best so far, checkpoint.
    /// Stops after `epochs`, or `patience` epochs without a better validation loss.
    pub fn fit_observed(
        &self,
        train: &mut dyn BatchSource,
        val: Option<&mut dyn BatchSource>,
        scaler: &Scaler,
        resume: bool,
        observer: &mut dyn Observer,
    ) -> Result<Vec<EpochRecord>, TrainError> {
        self.check_particle_counts(&train.particle_counts())?;
        let (start, ledger) = self.start(resume)?;
        let devices = self.devices.iter().map(|d| format!("{d:?}")).collect();
        let output = RunOutput {
            folder: RunFolder::new(&self.out),
            net: NetConfig::Paper(self.config.clone()),
            scaler: *scaler,
            epochs: self.opts.epochs,
            patience: self.opts.patience,
            keep_epochs: 0,
            constraints: None,
            ledger: RunLedger::begin_call(ledger, devices, self.dataset.clone()).shared(),
            call_started: Instant::now(),
        };
        let mut run = PaperRun {
            trainer: self,
            scaling: output.meta(0, 0.0).scaling(),
            streams: super::stream_ids(self.devices.len()),
            output,
            train,
            val,
        };
        run_epochs(&mut run, start, observer)
    }

    /// The global decoder is built for the config's N: an error when the data has another.
    fn check_particle_counts(&self, counts: &[usize]) -> Result<(), TrainError> {
        if self.config.decoder == crate::model::DecoderKind::Global
            && counts.iter().any(|&n| n != self.config.particles)
        {
            return Err(TrainError::Mismatch(format!(
                "the global decoder is built for N = {} particles but the data has N = {counts:?}; use --decoder pointwise or matching bags",
                self.config.particles
            )));
        }
        Ok(())
    }

    /// The model, optimizer and history to start from: freshly initialised (seeded), or
    /// those of `out/checkpoint` when `resume` and there is one, with its ledger. (A paper
    /// run checkpoints after whole epochs only: it has no unfinished epoch.)
    fn start(
        &self,
        resume: bool,
    ) -> Result<(Start<Model<B>, Optim<B>>, Option<RunLedger>), TrainError> {
        B::seed(self.main(), self.opts.seed);
        let model: Model<B> = initial_model(&self.config, self.opts.seed, self.main())?;
        let optim = optimizer::FusedAdam::default().init::<B, Model<B>>();
        if resume {
            if let Some(state) = checkpoint::load::<B, _, _>(
                &self.out,
                self.config.init::<B>(self.main()),
                self.main(),
                &optim,
            )? {
                let optim = optim.load_record(state.optim);
                return Ok(((state.model, optim, state.history, None), state.ledger));
            }
        }
        Ok(((model, optim, Vec::new(), None), None))
    }

    /// Seeds each device's random numbers (dropout) for `epoch`.
    fn seed_epoch(&self, epoch: usize) {
        for (k, device) in self.devices.iter().enumerate() {
            B::seed(
                device,
                self.opts
                    .seed
                    .wrapping_mul(1_000_003)
                    .wrapping_add(epoch as u64)
                    .wrapping_add((k as u64) << 32),
            );
        }
    }
}

/// The optimizer of a run: [`optimizer::FusedAdam`] through burn's adaptor.
type Optim<B> = OptimizerAdaptor<optimizer::FusedAdam, Model<B>, B>;

/// A paper run in progress: the trainer, its output and the batch sources, as
/// [`run_epochs`] drives it.
struct PaperRun<'a, 't, 'v, B: AutodiffBackend> {
    trainer: &'a Trainer<B>,
    scaling: Scaling,
    streams: Vec<StreamId>,
    output: RunOutput,
    train: &'t mut dyn BatchSource,
    val: Option<&'v mut dyn BatchSource>,
}

impl<B: AutodiffBackend + crate::ops::NetOps> EpochRun for PaperRun<'_, '_, '_, B>
where
    B::InnerBackend: crate::ops::NetOps,
{
    type Backend = B;
    type Model = Model<B>;
    type Optim = Optim<B>;

    fn output(&self) -> &RunOutput {
        &self.output
    }

    /// A whole epoch each time (`from` is always a fresh pass: paper runs checkpoint after
    /// whole epochs only).
    fn train_epoch(
        &mut self,
        model: Model<B>,
        optim: &mut Optim<B>,
        (epoch, _from): (usize, EpochPass),
        _history: &[EpochRecord],
        observer: &mut dyn Observer,
    ) -> Result<(Model<B>, EpochPass), TrainError> {
        self.trainer.seed_epoch(epoch);
        let started = Instant::now();
        self.trainer.train_epoch(
            model,
            optim,
            &mut *self.train,
            epoch,
            &self.scaling,
            &self.streams,
            observer,
            started,
        )
    }

    fn validate(&mut self, model: &Model<B>, _: usize, train_loss: f64) -> Result<f64, TrainError> {
        let t = self.trainer;
        match self.val.as_mut() {
            Some(v) if v.windows() > 0 => {
                evaluate(&model.valid(), &mut **v, &self.scaling, &t.opts, t.main())
            }
            _ => Ok(train_loss),
        }
    }
}
