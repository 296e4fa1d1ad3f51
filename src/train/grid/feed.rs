//! The grid trainer's prefetch thread ([`BatchFeed`]): an epoch's batches read, packed,
//! mirrored and their neighbourhoods built one batch ahead of the step that uses them
//! (`MINFLOW_TRAIN_PREFETCH=off`: each only when asked). Used by `train_epoch` (`mod.rs`).

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::batch::{prepare_batch, prepare_packed, prepare_whole, HostBatch, Needs};
use crate::data::{Batch, DataError, WindowIndex};

/// The mirroring draws of a run's batches: batch `g` of the run (counted over all epochs
/// from 0) draws its windows' flips from stream `g` of a ChaCha8 generator seeded from
/// `seed`, so a run resumed at any batch draws what the uninterrupted run drew.
#[derive(Debug, Clone, Copy)]
pub(super) struct Flips {
    /// The generator's seed.
    pub(super) seed: u64,
    /// The run position of the feed's first batch.
    pub(super) first: u64,
}

impl Flips {
    /// The generator of the feed's `k`-th batch.
    fn of(&self, k: u64) -> ChaCha8Rng {
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed);
        rng.set_stream(self.first + k);
        rng
    }
}

/// The batches of an epoch, prepared on a thread of their own ([`prepare_shares`]: read,
/// packed, mirrored where [`Flips`] draws so, neighbourhoods built) one batch ahead of the
/// step that uses them (the thread holds the one it prepared until it is taken). Each step
/// reads its loss back at its end, so whatever the host did between two steps, the GPU and
/// burn's fusion and launch threads waited for (docs/train_speed.md, "Where a training
/// step's host time goes"). `MINFLOW_TRAIN_PREFETCH=off` has the thread
/// read and prepare each batch only when [`BatchFeed::next`] asks for it, as the loop did
/// itself before, to compare the two in one binary. The thread ends when the feed is
/// dropped, after the last batch, or after a batch that could not be read.
pub(super) struct BatchFeed {
    /// Whether the thread works a batch ahead.
    ahead: bool,
    /// Without `ahead`: one message a batch asked for.
    ask: std::sync::mpsc::Sender<()>,
    prepared: std::sync::mpsc::Receiver<Result<Vec<HostBatch>, DataError>>,
}

impl BatchFeed {
    /// Starts the thread in `scope` over `batches`; `mirror` draws a window's mirroring
    /// from `flips`; each batch comes as `shares` host batches of consecutive windows (one
    /// per device of a data-parallel run; [`Batch::share_ranges`], padded with shares that
    /// count 0 where the batch has fewer windows than devices: [`HostBatch::padding`]).
    pub(super) fn start<'scope, I>(
        scope: &'scope std::thread::Scope<'scope, '_>,
        batches: I,
        flips: Flips,
        (mirror, shares): (bool, usize),
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
            for k in 0.. {
                if !ahead && asked.recv().is_err() {
                    return;
                }
                let Some(batch) = batches.next() else {
                    return;
                };
                let failed = batch.is_err();
                let host = batch.map(|batch| {
                    let mut rng = flips.of(k);
                    let flips: Vec<bool> = (0..batch.b)
                        .map(|_| mirror && rng.random_bool(0.5))
                        .collect();
                    if shares <= 1 {
                        return vec![prepare_whole(batch, &flips, needs)];
                    }
                    prepare_shares(batch, &flips, shares, needs)
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

    /// The next batch, in its shares; None after the last.
    pub(super) fn next(&self) -> Option<Result<Vec<HostBatch>, DataError>> {
        if !self.ahead {
            let _ = self.ask.send(());
        }
        self.prepared.recv().ok()
    }
}

/// The `shares` shares of `batch` (one a device), prepared on a thread each (a share's
/// neighbourhoods are built serially): from their own vectors where the batch was written
/// in them ([`crate::data::Layout::Shares`]`(shares)`, the index's layout for this many
/// devices: another share count is a panic), else from their windows' rows of the whole
/// batch. A batch of fewer windows than devices is padded with shares of its first window
/// that count 0.
pub(super) fn prepare_shares(
    mut batch: Batch,
    flips: &[bool],
    shares: usize,
    needs: Needs,
) -> Vec<HostBatch> {
    let mut ranges = batch.share_ranges(shares);
    let real = ranges.len();
    ranges.resize(shares, 0..batch.b.min(1));
    let mut packed: Vec<Option<Vec<f32>>> = (std::mem::take(&mut batch.frame_shares))
        .into_iter()
        .map(Some)
        .collect();
    if !packed.is_empty() {
        assert_eq!(packed.len(), real, "the batch's shares are the feed's");
        let first = (batch.t + 1) * batch.n * 4;
        let pad = packed[0].as_ref().map(|share| share[..first].to_vec());
        packed.resize(shares, pad);
    }
    let batch = &batch;
    std::thread::scope(|each| {
        let handles: Vec<_> = (ranges.into_iter().enumerate())
            .map(|(k, share)| {
                let (mirrored, frames) = (
                    &flips[share.clone()],
                    packed.get_mut(k).and_then(Option::take),
                );
                each.spawn(move || {
                    let host = match frames {
                        Some(frames) => prepare_packed(batch, share, frames, mirrored, needs),
                        None => prepare_batch(batch, share, mirrored, needs),
                    };
                    if k < real {
                        host
                    } else {
                        host.padding()
                    }
                })
            })
            .collect();
        (handles.into_iter())
            .map(|h| h.join().expect("a batch share's preparation panicked"))
            .collect()
    })
}

/// Samples per second at which the trainer's feed prepares an epoch of `index` in batches of
/// `batch_size` cut into `shares` (one per device of a data-parallel run), the windows
/// mirrored half the time and no neighbourhoods built, with nothing taking its batches but a
/// loop that drops them: the rate a training step cannot beat (`minflow bench train --arch
/// grid --feed`). Batches are assembled as training assembles resident ones
/// ([`WindowIndex::batch`], in the index's layout: `Layout::frames_for(shares)` as `train`
/// sets it).
pub fn feed_rate(index: &WindowIndex, batch_size: usize, shares: usize) -> f64 {
    let plan = index.plan(batch_size, None);
    let started = std::time::Instant::now();
    std::thread::scope(|scope| {
        let batches = plan.iter().map(|windows| Ok(index.batch(windows)));
        let flips = Flips { seed: 1, first: 0 };
        let feed = BatchFeed::start(scope, batches, flips, (true, shares), Needs::default());
        while let Some(batch) = feed.next() {
            drop(batch.expect("resident batches do not fail"));
        }
    });
    index.len() as f64 / started.elapsed().as_secs_f64().max(1e-9)
}
