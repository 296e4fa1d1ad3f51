//! The epoch loop both architectures train with ([`run_epochs`]): per epoch, one pass over
//! the training batches, a validation score, the model saved when that score is the best so
//! far (`model.json` + `model.mpk`, the run's kept model), a resumable checkpoint
//! (`checkpoint/`), and the observer told; it stops after `epochs`, after `patience` epochs
//! without a better score, or when a pass ran out of time. Early stopping on the validation
//! score and best-checkpoint selection as LagrangeBench (Toshev et al. 2023) and GNS
//! (Sanchez-Gonzalez et al. 2020) train. What differs between the architectures (the pass,
//! the score) is an [`EpochRun`]: [`super::paper::Trainer`] and [`super::grid::GridTrainer`];
//! what is the same (the run folder, the kept model, the checkpoint, the limits) is the
//! run's [`RunOutput`].

use std::time::Instant;

use burn::module::AutodiffModule;
use burn::optim::Optimizer;
use burn::tensor::backend::AutodiffBackend;

use super::checkpoint::RunOutput;
use super::{EpochRecord, Observer, TrainError};

/// What one pass over an epoch's training batches summed up.
#[derive(Debug, Default, Clone)]
pub struct EpochPass {
    /// Sum over batches of the batch-mean loss times the batch size.
    pub sum: f64,
    /// Samples (windows) trained on.
    pub seen: usize,
    /// Seconds waiting for host batches.
    pub data_seconds: f64,
    /// Seconds waiting for the device (reading the loss back).
    pub wait_seconds: f64,
    /// The run's time limit ran out during the pass: the loop stops after this epoch.
    pub out_of_time: bool,
}

impl EpochPass {
    /// Adds one optimizer step's batch-mean `loss` over `b` samples (step `k`, 0-based, of
    /// `total` in `epoch`, 0-based, begun at `started`) and tells `observer`.
    ///
    /// # Errors
    /// [`TrainError::NonFinite`] for a NaN or infinite loss.
    pub fn add_step(
        &mut self,
        loss: f64,
        b: usize,
        (epoch, k, total): (usize, usize, usize),
        started: Instant,
        observer: &mut dyn Observer,
    ) -> Result<(), TrainError> {
        if !loss.is_finite() {
            return Err(TrainError::NonFinite {
                epoch: epoch + 1,
                batch: k,
                loss: loss as f32,
            });
        }
        self.sum += loss * b as f64;
        self.seen += b;
        let rate = self.seen as f64 / started.elapsed().as_secs_f64().max(1e-9);
        observer.batch(epoch + 1, k + 1, total, self.sum / self.seen as f64, rate);
        Ok(())
    }
}

/// One architecture's training run, as [`run_epochs`] drives it.
pub trait EpochRun {
    /// The autodiff backend it trains on.
    type Backend: AutodiffBackend;
    /// The network being trained.
    type Model: AutodiffModule<Self::Backend>;
    /// Its optimizer.
    type Optim: Optimizer<Self::Model, Self::Backend>;

    /// The run folder, the kept model's `model.json` and the epoch limits.
    fn output(&self) -> &RunOutput;

    /// One pass over the training batches of `epoch` (0-based): the trained model and the
    /// pass's sums; `observer` is told after each optimizer step.
    ///
    /// # Errors
    /// A non-finite loss, unreadable data.
    fn train_epoch(
        &mut self,
        model: Self::Model,
        optim: &mut Self::Optim,
        epoch: usize,
        observer: &mut dyn Observer,
    ) -> Result<(Self::Model, EpochPass), TrainError>;

    /// The validation score of `model` after `epoch` epochs (lower is better);
    /// `train_loss` where there is nothing to validate on.
    ///
    /// # Errors
    /// Unreadable data, a failed validation step.
    fn validate(
        &mut self,
        model: &Self::Model,
        epoch: usize,
        train_loss: f64,
    ) -> Result<f64, TrainError>;
}

/// Trains `run` from `model`, `optim` and the epochs already done (`history`, non-empty when
/// resumed), one [`EpochRun::train_epoch`] per epoch; see the module doc. Returns every
/// epoch's record, the resumed ones included.
///
/// # Errors
/// The first error of a pass, a validation, a save or a checkpoint.
pub fn run_epochs<R: EpochRun>(
    run: &mut R,
    (mut model, mut optim, mut history): (R::Model, R::Optim, Vec<EpochRecord>),
    observer: &mut dyn Observer,
) -> Result<Vec<EpochRecord>, TrainError> {
    let (epochs, patience) = (run.output().epochs, run.output().patience);
    let mut best = history
        .iter()
        .map(|r| r.val_loss)
        .fold(f64::INFINITY, f64::min);
    let mut since_best = history
        .iter()
        .rev()
        .take_while(|r| r.val_loss > best)
        .count();
    for epoch in history.len()..epochs {
        if patience > 0 && since_best >= patience {
            break;
        }
        let started = Instant::now();
        let (trained, pass) = run.train_epoch(model, &mut optim, epoch, observer)?;
        model = trained;
        let seconds = started.elapsed().as_secs_f64();
        let train_loss = pass.sum / pass.seen.max(1) as f64;
        let val_loss = run.validate(&model, epoch + 1, train_loss)?;
        let record = EpochRecord {
            epoch: epoch + 1,
            train_loss,
            val_loss,
            seconds,
            samples_per_sec: pass.seen as f64 / seconds.max(1e-9),
            data_seconds: pass.data_seconds,
            wait_seconds: pass.wait_seconds,
        };
        if val_loss < best {
            best = val_loss;
            since_best = 0;
            run.output()
                .save_best::<R::Backend, _>(&model, epoch + 1, val_loss)?;
        } else {
            since_best += 1;
        }
        history.push(record.clone());
        run.output().checkpoint(&model, &optim, &history)?;
        observer.epoch(&record, &history);
        if pass.out_of_time {
            break;
        }
    }
    Ok(history)
}
