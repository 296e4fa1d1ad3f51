//! `train`: fits a model on trajectories from bags (DESIGN.md, "Model"): Adam (lr 1e-3,
//! epsilon 1e-8 as PyTorch), effective batch reached by micro-batches with gradient
//! accumulation, early stopping on the validation loss, a metrics CSV per epoch, and a
//! checkpoint (model + optimizer + state) written atomically every epoch so a killed run
//! resumes where it stopped, bit for bit (the backend RNG and the data order are reseeded
//! from (seed, epoch)). The best epoch's model is kept as `model.json` + `model.mpk`.
//! Used by `minflow train` and `minflow bench train`.

pub mod checkpoint;
pub mod loss;
pub mod source;

pub use source::BatchSource;

use crate::data::{Batch, Scaler, WindowIndex};
use crate::model::store::{self, ModelMeta};
use crate::model::{Model, ModelConfig, Scaling};
use burn::module::AutodiffModule;
use burn::optim::{AdamConfig, GradientsAccumulator, GradientsParams, Optimizer};
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::{ElementConversion, Tensor, TensorData};
use std::path::PathBuf;
use std::time::Instant;

/// Errors of a training run.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// The loss became NaN or infinite.
    #[error("non-finite loss {loss} at epoch {epoch}, batch {batch}")]
    NonFinite {
        /// Epoch (1-based).
        epoch: usize,
        /// Batch within the epoch (0-based).
        batch: usize,
        /// The value.
        loss: f32,
    },
    /// Data and model disagree.
    #[error("{0}")]
    Mismatch(String),
    /// Reading the training data failed.
    #[error(transparent)]
    Data(#[from] crate::data::DataError),
    /// Saving or loading failed.
    #[error(transparent)]
    Store(#[from] store::StoreError),
}

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

/// What one epoch measured.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct EpochRecord {
    /// 1-based epoch.
    pub epoch: usize,
    /// Mean training loss.
    pub train_loss: f64,
    /// Mean validation loss (training loss when there is no validation split).
    pub val_loss: f64,
    /// Wall-clock seconds of the epoch (training part).
    pub seconds: f64,
    /// Training windows per second.
    pub samples_per_sec: f64,
}

/// Tensors of a batch slice `[start, start + len)`.
struct Slice<B: burn::tensor::backend::Backend> {
    inputs: Tensor<B, 4>,
    targets: Tensor<B, 3>,
    target_pos: Tensor<B, 3>,
    dt: Tensor<B, 1>,
}

fn slice<B: burn::tensor::backend::Backend>(
    batch: &Batch,
    start: usize,
    len: usize,
    device: &B::Device,
) -> Slice<B> {
    let (t, n) = (batch.t, batch.n);
    let inputs = batch.inputs[start * t * n * 5..(start + len) * t * n * 5].to_vec();
    let targets = batch.targets[start * n * 4..(start + len) * n * 4].to_vec();
    let pos: Vec<f32> = batch.target_phys[start * n * 4..(start + len) * n * 4]
        .chunks_exact(4)
        .flat_map(|r| [r[0], r[1]])
        .collect();
    Slice {
        inputs: Tensor::from_data(TensorData::new(inputs, [len, t, n, 5]), device),
        targets: Tensor::from_data(TensorData::new(targets, [len, n, 4]), device),
        target_pos: Tensor::from_data(TensorData::new(pos, [len, n, 2]), device),
        dt: Tensor::from_data(
            TensorData::new(batch.dt[start..start + len].to_vec(), [len]),
            device,
        ),
    }
}

/// Predicted positions in domain units from a scaled prediction `[B, N, 4]`.
fn positions<B: burn::tensor::backend::Backend>(
    pred: Tensor<B, 3>,
    scaling: &Scaling,
) -> Tensor<B, 3> {
    let (min, range) = scaling.tensors::<B>(&pred.device());
    (pred * range + min).narrow(2, 0, 2)
}

/// Mean loss of `model` over `index` (no gradients, no dropout).
pub fn evaluate<B: crate::model::FusedElu>(
    model: &Model<B>,
    index: &mut dyn BatchSource,
    scaling: &Scaling,
    opts: &TrainOptions,
    device: &B::Device,
) -> Result<f64, TrainError> {
    let (mut sum, mut count) = (0.0, 0usize);
    for batch in index.batches(opts.micro_batch.max(1), None, 0)? {
        let batch = batch?;
        let s = slice::<B>(&batch, 0, batch.b, device);
        let pred = model.forward(s.inputs, s.dt, scaling);
        let parts = loss::loss(
            pred.clone(),
            s.targets,
            positions(pred, scaling),
            s.target_pos,
            opts.density_grid,
            opts.density_weight,
        );
        sum += parts.total.into_scalar().elem::<f64>() * batch.b as f64;
        count += batch.b;
    }
    Ok(if count == 0 {
        f64::NAN
    } else {
        sum / count as f64
    })
}

/// Sees training progress (progress bars, logs, tests); every method has a default.
pub trait Observer {
    /// Called after each optimizer step: `done` of `total` batches this epoch, the batch's
    /// mean loss and the epoch's samples per second so far.
    fn batch(
        &mut self,
        _epoch: usize,
        _done: usize,
        _total: usize,
        _loss: f64,
        _samples_per_sec: f64,
    ) {
    }
    /// Called after each epoch with its record.
    fn epoch(&mut self, _record: &EpochRecord, _history: &[EpochRecord]) {}
}

/// An observer that does nothing.
pub struct Quiet;
impl Observer for Quiet {}

/// A training run over in-memory windows.
pub struct Trainer<B: AutodiffBackend> {
    /// Network hyper-parameters.
    pub config: ModelConfig,
    /// Optimisation settings.
    pub opts: TrainOptions,
    /// Output folder.
    pub out: PathBuf,
    device: B::Device,
}

impl<B: AutodiffBackend + crate::model::FusedElu> Trainer<B>
where
    B::InnerBackend: crate::model::FusedElu,
{
    /// A trainer writing to `out`.
    pub fn new(config: ModelConfig, opts: TrainOptions, out: PathBuf, device: B::Device) -> Self {
        Self {
            config,
            opts,
            out,
            device,
        }
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
    pub fn fit_observed(
        &self,
        train: &mut dyn BatchSource,
        mut val: Option<&mut dyn BatchSource>,
        scaler: &Scaler,
        resume: bool,
        observer: &mut dyn Observer,
    ) -> Result<Vec<EpochRecord>, TrainError> {
        let counts = train.particle_counts();
        if self.config.decoder == crate::model::DecoderKind::Global
            && counts.iter().any(|&n| n != self.config.particles)
        {
            return Err(TrainError::Mismatch(format!(
                "the global decoder is built for N = {} particles but the data has N = {counts:?}; use --decoder pointwise or matching bags",
                self.config.particles
            )));
        }
        let scaling = ModelMeta {
            config: self.config.clone(),
            scaler: *scaler,
            epoch: 0,
            val_loss: 0.0,
        }
        .scaling();
        B::seed(&self.device, self.opts.seed);
        let mut model: Model<B> = self.config.init(&self.device);
        let mut optim = AdamConfig::new().with_epsilon(1e-8).init::<B, Model<B>>();
        let mut history = Vec::new();
        let mut start_epoch = 0;
        let mut best = f64::INFINITY;
        if resume {
            if let Some(state) =
                checkpoint::load::<B, _>(&self.out, &self.config, &self.device, &optim)?
            {
                model = state.model;
                optim = optim.load_record(state.optim);
                history = state.history;
                start_epoch = history.len();
                best = history
                    .iter()
                    .map(|r: &EpochRecord| r.val_loss)
                    .fold(f64::INFINITY, f64::min);
            }
        }
        let mut since_best = history
            .iter()
            .rev()
            .take_while(|r| r.val_loss > best)
            .count();
        for epoch in start_epoch..self.opts.epochs {
            if self.opts.patience > 0 && since_best >= self.opts.patience {
                break;
            }
            B::seed(
                &self.device,
                self.opts
                    .seed
                    .wrapping_mul(1_000_003)
                    .wrapping_add(epoch as u64),
            );
            let started = Instant::now();
            let (mut sum, mut seen) = (0.0f64, 0usize);
            let total = train.num_batches(self.opts.batch_size.max(1));
            for (k, batch) in train
                .batches(
                    self.opts.batch_size.max(1),
                    Some(self.opts.seed),
                    epoch as u64,
                )?
                .enumerate()
            {
                let batch = batch?;
                let mut accumulator = GradientsAccumulator::new();
                let micro = self.opts.micro_batch.clamp(1, batch.b);
                let mut start = 0;
                while start < batch.b {
                    let len = micro.min(batch.b - start);
                    let s = slice::<B>(&batch, start, len, &self.device);
                    let pred = model.forward(s.inputs, s.dt, &scaling);
                    let parts = loss::loss(
                        pred.clone(),
                        s.targets,
                        positions(pred, &scaling),
                        s.target_pos,
                        self.opts.density_grid,
                        self.opts.density_weight,
                    );
                    let value: f32 = parts.total.clone().into_scalar().elem();
                    if !value.is_finite() {
                        return Err(TrainError::NonFinite {
                            epoch: epoch + 1,
                            batch: k,
                            loss: value,
                        });
                    }
                    sum += value as f64 * len as f64;
                    let grads = parts
                        .total
                        .mul_scalar(len as f32 / batch.b as f32)
                        .backward();
                    accumulator.accumulate(&model, GradientsParams::from_grads(grads, &model));
                    start += len;
                }
                seen += batch.b;
                model = optim.step(self.opts.lr, model, accumulator.grads());
                let rate = seen as f64 / started.elapsed().as_secs_f64().max(1e-9);
                observer.batch(epoch + 1, k + 1, total, sum / seen as f64, rate);
            }
            let seconds = started.elapsed().as_secs_f64();
            let train_loss = sum / seen.max(1) as f64;
            let valid = model.valid();
            let val_loss = match val.as_mut() {
                Some(v) if v.windows() > 0 => {
                    evaluate(&valid, &mut **v, &scaling, &self.opts, &self.device)?
                }
                _ => train_loss,
            };
            let record = EpochRecord {
                epoch: epoch + 1,
                train_loss,
                val_loss,
                seconds,
                samples_per_sec: seen as f64 / seconds.max(1e-9),
            };
            if val_loss < best {
                best = val_loss;
                since_best = 0;
                let meta = ModelMeta {
                    config: self.config.clone(),
                    scaler: *scaler,
                    epoch: epoch + 1,
                    val_loss,
                };
                store::save(&self.out, &model, &meta)?;
            } else {
                since_best += 1;
            }
            history.push(record.clone());
            checkpoint::save(&self.out, &model, &optim, &history)?;
            observer.epoch(&record, &history);
        }
        Ok(history)
    }
}
