//! The epoch loop both architectures train with ([`run_epochs`]): per epoch, one pass over
//! the training batches, a validation score, the model saved when that score is the best so
//! far (`model.json` + `model.mpk`, the run's kept model), a resumable checkpoint
//! (`checkpoint/`), the last `--keep-epochs` epochs' weights (`epochs/`, a failure there only
//! warned of), and the observer told; it stops after `epochs`, after `patience` epochs
//! without a better score, or when a pass ran out of time. A pass that ends the call's share
//! mid-epoch ([`super::ledger::CallShare`]) leaves a checkpoint of its unfinished epoch
//! ([`Unfinished`]) and no record; the resumed run finishes that epoch from the next step. Early stopping on the validation
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
pub use super::progress::{EpochPass, Unfinished};
use super::{EpochRecord, Observer, TrainError};

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

    /// One pass over the training batches of epoch `epoch.0` (0-based), from `from.steps` on
    /// with `from`'s sums (`from` = `epoch.1`) (a resumed epoch; the default pass otherwise): the trained model and the
    /// pass's sums; `observer` is told after each optimizer step. `history` is every epoch
    /// finished, for a checkpoint written mid-epoch.
    ///
    /// # Errors
    /// A non-finite loss, unreadable data, a mid-epoch checkpoint that could not be written.
    fn train_epoch(
        &mut self,
        model: Self::Model,
        optim: &mut Self::Optim,
        epoch: (usize, EpochPass),
        history: &[EpochRecord],
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

/// Where a run starts: the weights, the optimizer, the epochs already done (non-empty when
/// resumed) and the unfinished epoch a mid-epoch checkpoint left.
pub type Start<M, O> = (M, O, Vec<EpochRecord>, Option<Unfinished>);

/// Trains `run` from `model`, `optim`, the epochs already done and the unfinished one, one
/// [`EpochRun::train_epoch`] per epoch; see the module doc. Returns every epoch's record,
/// the resumed ones included.
///
/// # Errors
/// The first error of a pass, a validation, a save or a checkpoint.
pub fn run_epochs<R: EpochRun>(
    run: &mut R,
    (mut model, mut optim, mut history, mut unfinished): Start<R::Model, R::Optim>,
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
        let from = (unfinished.take())
            .filter(|u| u.epoch == epoch)
            .map_or_else(EpochPass::default, |u| u.pass);
        let before = from.seconds;
        let (trained, mut pass) =
            run.train_epoch(model, &mut optim, (epoch, from), &history, observer)?;
        model = trained;
        let seconds = before + started.elapsed().as_secs_f64();
        if pass.stopped {
            pass.seconds = seconds;
            let unfinished = Unfinished { epoch, pass };
            (run.output()).checkpoint(&model, &optim, &history, Some(&unfinished))?;
            break;
        }
        let train_loss = pass.sum / pass.seen.max(1) as f64;
        let val_loss = run.validate(&model, epoch + 1, train_loss)?;
        let record = EpochRecord {
            epoch: epoch + 1,
            train_loss,
            val_loss,
            seconds,
            samples_per_sec: pass.seen as f64 / seconds.max(1e-9),
            samples: pass.seen,
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
        run.output().checkpoint(&model, &optim, &history, None)?;
        // An optional copy: a failure is told and the run goes on (its checkpoint is written).
        if let Err(e) = (run.output()).keep_epoch::<R::Backend, _>(&model, epoch + 1, val_loss) {
            tracing::warn!("epoch {} not kept in epochs/: {e}", epoch + 1);
        }
        observer.epoch(&record, &history);
        if pass.out_of_time {
            break;
        }
    }
    Ok(history)
}
