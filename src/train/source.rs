//! Where the trainer's batches come from: the in-memory [`WindowIndex`] (a dataset that fits)
//! or the [`StreamingLoader`] (a dataset larger than memory, read from the bags chunk by
//! chunk each epoch under a resident-frame budget). Both shuffle deterministically from
//! (seed, epoch), so a resumed run sees the same order.

use crate::data::windows::rng;
use crate::data::{Batch, DataError, StreamingLoader, WindowIndex};

/// The batches of one epoch.
pub type Batches<'a> = Box<dyn Iterator<Item = Result<Batch, DataError>> + Send + 'a>;

/// A source of training or validation batches.
pub trait BatchSource {
    /// The batches of `epoch` (shuffled when `seed` is given).
    fn batches(
        &mut self,
        batch_size: usize,
        seed: Option<u64>,
        epoch: u64,
    ) -> Result<Batches<'_>, DataError> {
        self.batches_from(batch_size, seed, epoch, 0)
    }
    /// The batches of `epoch` after its first `skip`, without preparing the skipped ones
    /// (a run resumed mid-epoch, or an epoch shorter than a pass continuing it).
    fn batches_from(
        &mut self,
        batch_size: usize,
        seed: Option<u64>,
        epoch: u64,
        skip: usize,
    ) -> Result<Batches<'_>, DataError>;
    /// Batches per epoch (for progress bars).
    fn num_batches(&self, batch_size: usize) -> usize;
    /// The particle counts N present.
    fn particle_counts(&self) -> Vec<usize>;
    /// Windows per epoch.
    fn windows(&self) -> usize;
    /// T, the frames of a window's input.
    fn t(&self) -> usize;
}

impl BatchSource for &WindowIndex {
    fn batches_from(
        &mut self,
        batch_size: usize,
        seed: Option<u64>,
        epoch: u64,
        skip: usize,
    ) -> Result<Batches<'_>, DataError> {
        let index: &WindowIndex = self;
        let plan = index.plan(batch_size, seed.map(|s| rng(s, epoch, 0)));
        let plan = plan.into_iter().skip(skip);
        Ok(Box::new(plan.map(move |windows| Ok(index.batch(&windows)))))
    }
    fn num_batches(&self, batch_size: usize) -> usize {
        WindowIndex::num_batches(self, batch_size)
    }
    fn particle_counts(&self) -> Vec<usize> {
        WindowIndex::particle_counts(self)
    }
    fn windows(&self) -> usize {
        self.len()
    }
    fn t(&self) -> usize {
        WindowIndex::t(self)
    }
}

impl BatchSource for StreamingLoader {
    fn batches_from(
        &mut self,
        batch_size: usize,
        seed: Option<u64>,
        epoch: u64,
        skip: usize,
    ) -> Result<Batches<'_>, DataError> {
        Ok(Box::new(self.epoch_from(batch_size, seed, epoch, skip)?))
    }
    fn num_batches(&self, batch_size: usize) -> usize {
        self.len().div_ceil(batch_size.max(1))
    }
    fn particle_counts(&self) -> Vec<usize> {
        StreamingLoader::particle_counts(self)
    }
    fn windows(&self) -> usize {
        self.len()
    }
    fn t(&self) -> usize {
        StreamingLoader::t(self)
    }
}
