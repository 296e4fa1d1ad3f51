//! The batches of one epoch of a [`StreamingLoader`] ([`EpochBatches`]): the resident
//! dataset's plan, or the epoch's chunks read one after the other with the next one read
//! ahead on a worker thread. An iterator dropped before its epoch's end leaves its loaded
//! chunk, its read-ahead and its place with the loader ([`Parked`]), where the next epoch
//! iterator that starts at that place takes them over.

use std::collections::VecDeque;

use rand::seq::SliceRandom;

use super::chunks::{chunk_batches, Loaded, Prefetch};
use super::StreamingLoader;
use crate::data::windows::rng;
use crate::data::{Batch, DataError, WindowIndex};

/// What an epoch's batches are drawn with: batch size, shuffle seed, epoch.
pub(super) type EpochKey = (usize, Option<u64>, u64);

/// The order an epoch visits the scenes in (positions in the loader's sorted scenes):
/// shuffled from (seed, epoch), index order without a seed.
pub(super) fn scene_order(scenes: usize, seed: Option<u64>, epoch: u64) -> Vec<usize> {
    let mut order: Vec<usize> = (0..scenes).collect();
    if let Some(seed) = seed {
        order.shuffle(&mut rng(seed, epoch, 1));
    }
    order
}

/// The chunk being batched: the resident dataset, or a chunk read for this epoch.
enum Current<'a> {
    Resident(&'a WindowIndex),
    Chunk(Loaded),
}

impl Current<'_> {
    fn index(&self) -> &WindowIndex {
        match self {
            Current::Resident(index) => index,
            Current::Chunk(loaded) => &loaded.index,
        }
    }
}

/// The state of a chunked epoch left by an iterator dropped before its end.
pub(super) struct Parked {
    key: EpochKey,
    /// Batches of the epoch taken so far.
    position: usize,
    chunks: VecDeque<Vec<usize>>,
    chunk_no: u64,
    current: Option<(Loaded, Vec<Vec<u32>>, usize)>,
    pending: Option<(u64, Prefetch)>,
}

impl Parked {
    /// Whether an epoch of `key` starting after `skip` batches continues this one.
    pub(super) fn continues(&self, key: EpochKey, skip: usize) -> bool {
        self.key == key && self.position == skip
    }
}

/// The batches of one epoch of a [`StreamingLoader`]; see [`StreamingLoader::epoch`].
pub struct EpochBatches<'a> {
    loader: &'a StreamingLoader,
    key: EpochKey,
    /// Batches of the epoch taken so far, the skipped ones included.
    position: usize,
    /// Batches still to skip in the next chunk read.
    skip: usize,
    /// Chunks still to load, as positions in the loader's scenes.
    chunks: VecDeque<Vec<usize>>,
    chunk_no: u64,
    /// The loaded chunk, its batches as window positions, and the next batch.
    current: Option<(Current<'a>, Vec<Vec<u32>>, usize)>,
    /// The next chunk (its number), being read.
    pending: Option<(u64, Prefetch)>,
}

impl<'a> EpochBatches<'a> {
    fn new(loader: &'a StreamingLoader, key: EpochKey) -> Self {
        Self {
            loader,
            key,
            position: 0,
            skip: 0,
            chunks: VecDeque::new(),
            chunk_no: 0,
            current: None,
            pending: None,
        }
    }

    /// The resident dataset's epoch, after `skip` batches.
    pub(super) fn resident(
        loader: &'a StreamingLoader,
        index: &'a WindowIndex,
        key: EpochKey,
        skip: usize,
    ) -> Self {
        let (batch_size, seed, epoch) = key;
        let plan = index.plan(batch_size, seed.map(|s| rng(s, epoch, 0)));
        let mut batches = Self::new(loader, key);
        batches.position = skip;
        batches.current = Some((Current::Resident(index), plan, skip));
        batches
    }

    /// An epoch over `chunks`, after `skip` batches: chunks wholly before them are dropped
    /// unread (their numbers, which seed their shuffles, still counted).
    pub(super) fn chunked(
        loader: &'a StreamingLoader,
        mut chunks: Vec<Vec<usize>>,
        key: EpochKey,
        skip: usize,
    ) -> Self {
        let mut batches = Self::new(loader, key);
        batches.position = skip;
        let (scenes, t) = (&loader.reader.scenes, loader.reader.t);
        let mut skip = skip;
        let mut whole = 0;
        for chunk in &chunks {
            let n = chunk_batches(scenes, chunk, t, key.0);
            if skip == 0 || skip < n {
                break;
            }
            skip -= n;
            whole += 1;
        }
        chunks.drain(..whole);
        batches.chunk_no = whole as u64;
        batches.skip = skip;
        batches.chunks = chunks.into();
        batches
    }

    /// The epoch `parked` left, from where it stopped.
    pub(super) fn unpark(loader: &'a StreamingLoader, parked: Parked) -> Self {
        let mut batches = Self::new(loader, parked.key);
        batches.position = parked.position;
        batches.chunks = parked.chunks;
        batches.chunk_no = parked.chunk_no;
        batches.current = (parked.current).map(|(c, plan, pos)| (Current::Chunk(c), plan, pos));
        batches.pending = parked.pending;
        batches
    }

    /// The next chunk and its number: the one read ahead, or the next one read now; then
    /// the one after it starts being read ahead (when the budget leaves room for two).
    fn next_chunk(&mut self) -> Option<(u64, Result<Loaded, DataError>)> {
        let reader = &self.loader.reader;
        let (no, loaded) = match self.pending.take() {
            Some((no, prefetch)) => (no, prefetch.wait()),
            None => {
                let chunk = self.chunks.pop_front()?;
                self.chunk_no += 1;
                (self.chunk_no, reader.read(&chunk))
            }
        };
        if loaded.is_ok() && self.loader.read_ahead() {
            if let Some(chunk) = self.chunks.pop_front() {
                self.chunk_no += 1;
                self.pending = Some((self.chunk_no, Prefetch::start(reader, chunk)));
            }
        }
        Some((no, loaded))
    }
}

impl Iterator for EpochBatches<'_> {
    type Item = Result<Batch, DataError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            if let Some((index, plan, pos)) = self.current.as_mut() {
                if let Some(windows) = plan.get(*pos) {
                    *pos += 1;
                    self.position += 1;
                    return Some(Ok(index.index().batch(windows)));
                }
            }
            self.current = None; // drop the chunk before loading the next
            let (no, loaded) = self.next_chunk()?;
            match loaded {
                Ok(loaded) => {
                    let (batch_size, seed, epoch) = self.key;
                    let rng = seed.map(|s| rng(s, epoch, 1 + no));
                    let plan = loaded.index.plan(batch_size, rng);
                    let skip = std::mem::take(&mut self.skip);
                    self.current = Some((Current::Chunk(loaded), plan, skip));
                }
                Err(err) => {
                    // The error ends the epoch.
                    self.chunks.clear();
                    self.pending = None;
                    return Some(Err(err));
                }
            }
        }
    }
}

impl Drop for EpochBatches<'_> {
    /// A chunked epoch stopped before its end parks its state with the loader.
    fn drop(&mut self) {
        let current = match self.current.take() {
            Some((Current::Chunk(loaded), plan, pos)) => Some((loaded, plan, pos)),
            Some((Current::Resident(_), ..)) => return,
            None => None,
        };
        if current.is_none() && self.pending.is_none() && self.chunks.is_empty() {
            return;
        }
        let parked = Parked {
            key: self.key,
            position: self.position,
            chunks: std::mem::take(&mut self.chunks),
            chunk_no: self.chunk_no,
            current,
            pending: self.pending.take(),
        };
        if let Ok(mut slot) = self.loader.parked.lock() {
            *slot = Some(parked);
        }
    }
}
