//! Where the trainer's batches come from: the in-memory [`WindowIndex`] (a dataset that fits)
//! or the [`StreamingLoader`] (a dataset larger than memory, read from the bags chunk by
//! chunk each epoch under a resident-frame budget). Both shuffle deterministically from
//! (seed, epoch), so a resumed run sees the same order.

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
    fn batches(
        &mut self,
        batch_size: usize,
        seed: Option<u64>,
        epoch: u64,
    ) -> Result<Batches<'_>, DataError> {
        Ok(Box::new(
            WindowIndex::batches(self, batch_size, seed, epoch).map(Ok),
        ))
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
    fn batches(
        &mut self,
        batch_size: usize,
        seed: Option<u64>,
        epoch: u64,
    ) -> Result<Batches<'_>, DataError> {
        Ok(Box::new(self.epoch(batch_size, seed, epoch)?))
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
