//! `train`: fits either architecture on trajectories from bags. The epoch loop is shared
//! ([`epochs::run_epochs`]: validation, keep-best, checkpoint, resume, early stop); each
//! architecture brings its pass over the batches and its validation score:
//!
//! - [`paper`]: the paper's network ([`paper::Trainer`]): one-frame windows, the loss on the
//!   next frame ([`paper::loss`]), data-parallel on several devices;
//! - [`grid`]: the grid architecture ([`grid::GridTrainer`]): short rollouts on the model's
//!   own predictions, validation by rollouts.
//!
//! Shared here: the error type, the per-epoch record, the progress observer and the seeded
//! CPU draw of initial weights. [`checkpoint`] is what a run writes (the kept model, the
//! resumable checkpoint, [`checkpoint::RunOutput`]), [`optimizer`] the fused Adam optimizer,
//! [`source`] the batch sources, `reduce.rs` the gradient all-reduce of data-parallel runs and
//! `workers.rs` their worker threads. Used by `minflow train` and `minflow bench train`.

pub mod checkpoint;
pub mod epochs;
pub mod grid;
pub mod ledger;
pub mod optimizer;
pub mod paper;
pub mod progress;
pub(crate) mod reduce;
pub mod source;
mod workers;

pub use epochs::{run_epochs, EpochPass, EpochRun, Unfinished};
pub use ledger::{CallShare, DatasetInfo, RunLedger};
pub use paper::{evaluate, initial_model, TrainOptions, Trainer};
pub use source::BatchSource;

use burn::backend::NdArray;
use burn::module::Module;
use burn::record::{BinBytesRecorder, FullPrecisionSettings, Recorder};
use burn::tensor::backend::Backend;

use crate::model::store;

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
    /// Seconds of `seconds` the training loop waited for host batches (assembly runs on a
    /// helper thread; this is what it did not hide).
    #[serde(default)]
    pub data_seconds: f64,
    /// Seconds of `seconds` the host waited for the device to finish queued work (reading
    /// the loss back once per step): near `seconds` when the device is the bottleneck, near
    /// 0 when issuing the work (kernel launches, autodiff bookkeeping) is.
    #[serde(default)]
    pub wait_seconds: f64,
    /// Samples (windows) trained on in the epoch (0 in runs saved before it was recorded).
    #[serde(default)]
    pub samples: usize,
}

/// One fixed stream id per device of a data-parallel run, for its whole length (this
/// thread's for the main device, a fresh one each for the others), as both trainers run
/// their workers on. burn's fusion streams and cubecl's CUDA streams and memory pools are
/// per stream id, which is per thread by default: workers spawned every step would open a
/// new ~10 GB pool per step at the paper's size (the allocator then failed), and two
/// threads sharing one id on a device corrupt its stream (illegal addresses).
pub(crate) fn stream_ids(devices: usize) -> Vec<burn::tensor::StreamId> {
    use burn::tensor::StreamId;
    (0..devices)
        .map(|k| match k {
            0 => StreamId::current(),
            _ => std::thread::spawn(StreamId::current)
                .join()
                .expect("a thread that only reads its id"),
        })
        .collect()
}

/// The weights `draw` makes on the CPU backend after seeding it with `seed`, loaded into
/// `fresh` (the same network on `device`) through an f32 record. Every architecture's
/// trainer starts from this, so a CUDA run starts from a CPU run's weights.
///
/// # Errors
/// The record could not be moved.
pub fn drawn_on_cpu<B: Backend, C: Module<NdArray<f32>>, M: Module<B>>(
    seed: u64,
    draw: impl FnOnce(&burn::backend::ndarray::NdArrayDevice) -> C,
    fresh: M,
    device: &B::Device,
) -> Result<M, TrainError> {
    // burn's CPU generator is one per process: trainers started at once in one process
    // (parallel tests) draw from it in turn, so only a lone trainer's draw is reproducible.
    let cpu = Default::default();
    NdArray::<f32>::seed(&cpu, seed);
    let drawn = draw(&cpu);
    let recorder = BinBytesRecorder::<FullPrecisionSettings>::default();
    let bytes = Recorder::<NdArray<f32>>::record(&recorder, drawn.into_record(), ())
        .map_err(|e| TrainError::Mismatch(format!("moving the initial weights: {e}")))?;
    let record = Recorder::<B>::load(&recorder, bytes, device)
        .map_err(|e| TrainError::Mismatch(format!("moving the initial weights: {e}")))?;
    Ok(fresh.load_record(record))
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
