//! The grid trainer's prefetch thread ([`BatchFeed`]): an epoch's batches read, packed,
//! mirrored and their neighbourhoods built one batch ahead of the step that uses them
//! (`MINFLOW_TRAIN_PREFETCH=off`: each only when asked). Used by `train_epoch` (`mod.rs`).

use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::batch::{prepare_batch, HostBatch, Needs};
use crate::data::{Batch, DataError};

/// The batches of an epoch, prepared on a thread of their own ([`prepare_batch`]: read,
/// packed, mirrored where `flips` draws so, neighbourhoods built) one batch ahead of the
/// step that uses them (the thread holds the one it prepared until it is taken). Each step reads its loss back at its end, so whatever the host did
/// between two steps, the GPU and burn's fusion and launch threads waited for (docs/speed.md,
/// "Where a training step's host time goes"). `MINFLOW_TRAIN_PREFETCH=off` has the thread
/// read and prepare each batch only when [`BatchFeed::next`] asks for it, as the loop did
/// itself before, to compare the two in one binary. The thread ends when the feed is
/// dropped, after the last batch, or after a batch that could not be read.
pub(super) struct BatchFeed {
    /// Whether the thread works a batch ahead.
    ahead: bool,
    /// Without `ahead`: one message a batch asked for.
    ask: std::sync::mpsc::Sender<()>,
    prepared: std::sync::mpsc::Receiver<Result<HostBatch, DataError>>,
}

impl BatchFeed {
    /// Starts the thread in `scope` over `batches`; `mirror` draws a window's mirroring
    /// from `flips` (in batch order, as the loop drew them).
    pub(super) fn start<'scope, I>(
        scope: &'scope std::thread::Scope<'scope, '_>,
        batches: I,
        mut flips: ChaCha8Rng,
        mirror: bool,
        needs: Needs,
    ) -> Self
    where
        I: Iterator<Item = Result<Batch, DataError>> + Send + 'scope,
    {
        let ahead = crate::switches::train_prefetch();
        // A rendezvous: the thread holds at most the one batch it prepared.
        let (ready, prepared) = std::sync::mpsc::sync_channel(0);
        let (ask, asked) = std::sync::mpsc::channel::<()>();
        scope.spawn(move || {
            let mut batches = batches;
            loop {
                if !ahead && asked.recv().is_err() {
                    return;
                }
                let Some(batch) = batches.next() else {
                    return;
                };
                let failed = batch.is_err();
                let host = batch.map(|batch| {
                    let flips: Vec<bool> = (0..batch.b)
                        .map(|_| mirror && flips.random_bool(0.5))
                        .collect();
                    prepare_batch(batch, &flips, needs)
                });
                // After an error the epoch ends: nothing more is read.
                if ready.send(host).is_err() || failed {
                    return;
                }
            }
        });
        Self {
            ahead,
            ask,
            prepared,
        }
    }

    /// The next batch; None after the last.
    pub(super) fn next(&self) -> Option<Result<HostBatch, DataError>> {
        if !self.ahead {
            let _ = self.ask.send(());
        }
        self.prepared.recv().ok()
    }
}
