//! Where a training epoch stands: [`EpochPass`], what a pass over its batches has summed so
//! far (loss, samples, waits, steps), and [`Unfinished`], an epoch a checkpoint was written
//! in before its end (`partial.json`). Used by [`super::epochs::run_epochs`], the
//! architectures' passes and [`super::checkpoint`].

use std::time::Instant;

use super::{Observer, TrainError};

/// What one pass over an epoch's training batches summed up (a resumed epoch's pass starts
/// from what its calls before summed).
#[derive(Debug, Default, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EpochPass {
    /// Sum over batches of the batch-mean loss times the batch size.
    pub sum: f64,
    /// Samples (windows) trained on.
    pub seen: usize,
    /// Seconds waiting for host batches.
    pub data_seconds: f64,
    /// Seconds waiting for the device (reading the loss back).
    pub wait_seconds: f64,
    /// Optimizer batches done in the epoch.
    #[serde(default)]
    pub steps: usize,
    /// Seconds the epoch has trained, over its calls before this one.
    #[serde(default)]
    pub seconds: f64,
    /// The run's time limit ran out during the pass: the loop stops after this epoch.
    #[serde(skip)]
    pub out_of_time: bool,
    /// The call's share ended during the pass: the epoch is unfinished, checkpointed as it
    /// stands, and the loop stops.
    #[serde(skip)]
    pub stopped: bool,
}

/// An epoch a checkpoint was written in (`partial.json`): a resumed run goes on from its
/// `pass.steps`-th batch with its sums.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Unfinished {
    /// The epoch, 0-based.
    pub epoch: usize,
    /// What its steps so far summed up.
    pub pass: EpochPass,
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
        self.steps += 1;
        let rate = self.seen as f64 / started.elapsed().as_secs_f64().max(1e-9);
        observer.batch(epoch + 1, k + 1, total, self.sum / self.seen as f64, rate);
        Ok(())
    }
}
