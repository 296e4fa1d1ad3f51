//! Decoding a dataset's bags on worker threads: [`for_each_frame`] hands every frame to one
//! callback on the calling thread in the order a one-thread read gives (bag by bag, each bag's
//! messages in log order), while up to one worker per core (16 at most) decompresses and
//! decodes the bags ahead of it. A bag's decoded frames wait in a bounded queue, and a worker
//! starts a bag only within twice the workers' count of the one being passed on, so at most
//! that many queues of a few frames are held, whatever the bags' sizes. Used by
//! [`super::load()`], [`super::scan`] and the streamed chunks of `train`: 2,000 bags of 200
//! frames (320,000 frames of 2,500 particles) took about a minute to read on one thread
//! (issue 82's long run).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender};
use std::sync::{Condvar, Mutex};

use super::{DataError, LoadReport};
use crate::bag::{BagError, BagReader, Truncation};
use crate::msgs::ParticleFrame;

/// Decoded frames a worker may hold ahead of the calling thread, per bag.
const QUEUE: usize = 32;

/// What a worker sends for one bag: its frames, a truncation, then its end (or an error).
enum Item {
    Frame(ParticleFrame, Option<u32>),
    Truncated(Truncation),
    Failed(BagError),
    Done { skipped: u64 },
}

/// Calls `each(path, frame, solver_grid)` with every ParticleFrame of every bag of `paths` (on
/// `topic`, or on every ParticleFrame channel) in turn: bag after bag, in `paths`' order.
/// Truncated bags are recorded in `report.truncated` (their frames before the damage are
/// kept), skipped messages in `report.skipped`, read bags in `report.bags`.
///
/// # Errors
/// The first bag that cannot be read (other than truncated), or the first error of `each`;
/// reading stops there, the bags before it having been passed on whole.
pub fn for_each_frame(
    paths: &[PathBuf],
    topic: Option<&str>,
    report: &mut LoadReport,
    mut each: impl FnMut(&Path, ParticleFrame, Option<u32>) -> Result<(), DataError>,
) -> Result<(), DataError> {
    let workers = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(WORKERS)
        .min(paths.len())
        .max(1);
    // A worker takes its bag's sender: the channel closes when the worker is done with the
    // bag, or if it panics, so the receiving side never waits on a sender nobody holds.
    let (senders, receivers): (Vec<_>, Vec<_>) = paths
        .iter()
        .map(|_| {
            let (sender, receiver) = sync_channel(QUEUE);
            (Mutex::new(Some(sender)), receiver)
        })
        .unzip();
    let next = AtomicUsize::new(0);
    let gate = Gate::new(2 * workers);
    std::thread::scope(|scope| {
        for _ in 0..workers {
            scope.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(path) = paths.get(i) else { break };
                if !gate.wait_for(i) {
                    break;
                }
                let sender = senders[i].lock().ok().and_then(|mut s| s.take());
                if let Some(sender) = sender {
                    decode_bag(path, topic, &sender);
                }
            });
        }
        // Stops the workers however the receiving side ends (an error, or a panic of `each`).
        let _stop = StopOnDrop(&gate);
        receive(paths, receivers, report, &mut each, &gate)
    })
}

/// The most worker threads a read starts.
const WORKERS: usize = 16;

/// How far ahead of the calling thread the workers may decode: bag i is started only once
/// fewer than `ahead` bags before it are still to be passed on, so at most `ahead` bags'
/// queues ([`QUEUE`] frames each) are held, whatever the bags' sizes.
struct Gate {
    /// (bags passed on whole, stopped).
    state: Mutex<(usize, bool)>,
    moved: Condvar,
    ahead: usize,
}

impl Gate {
    fn new(ahead: usize) -> Self {
        Self {
            state: Mutex::new((0, false)),
            moved: Condvar::new(),
            ahead,
        }
    }

    /// Waits until bag `i` may be decoded; false when the read has stopped.
    fn wait_for(&self, i: usize) -> bool {
        let Ok(mut state) = self.state.lock() else {
            return false;
        };
        while !state.1 && i >= state.0 + self.ahead {
            state = match self.moved.wait(state) {
                Ok(s) => s,
                Err(_) => return false,
            };
        }
        !state.1
    }

    /// One more bag passed on (`stop` false), or the read stopped.
    fn advance(&self, stop: bool) {
        if let Ok(mut state) = self.state.lock() {
            state.0 += 1;
            state.1 |= stop;
        }
        self.moved.notify_all();
    }
}

/// Stops the read's workers when dropped.
struct StopOnDrop<'a>(&'a Gate);

impl Drop for StopOnDrop<'_> {
    fn drop(&mut self) {
        self.0.advance(true);
    }
}

/// Passes the bags' items on in `paths`' order; drops every receiver when it returns. A
/// bag whose channel closes before its end was sent lost its worker to a panic: the read
/// stops there, and the scope's join passes the panic on.
fn receive(
    paths: &[PathBuf],
    receivers: Vec<Receiver<Item>>,
    report: &mut LoadReport,
    each: &mut impl FnMut(&Path, ParticleFrame, Option<u32>) -> Result<(), DataError>,
    gate: &Gate,
) -> Result<(), DataError> {
    for (path, receiver) in paths.iter().zip(receivers) {
        let mut done = false;
        for item in receiver {
            match item {
                Item::Frame(frame, grid) => each(path, frame, grid)?,
                Item::Truncated(truncation) => report.truncated.push((path.clone(), truncation)),
                Item::Failed(err) => return Err(err.into()),
                Item::Done { skipped } => {
                    report.skipped += skipped;
                    report.bags += 1;
                    done = true;
                }
            }
        }
        if !done {
            return Ok(());
        }
        gate.advance(false);
    }
    Ok(())
}

/// Decodes the bag at `path` into `out` (a one-thread read of it, item by item); returns early
/// when the receiving side has gone.
fn decode_bag(path: &Path, topic: Option<&str>, out: &SyncSender<Item>) {
    let mut frames = match BagReader::open(path) {
        Ok(reader) => reader.frames_on(topic),
        Err(err) => {
            let _ = out.send(Item::Failed(err));
            return;
        }
    };
    for item in frames.by_ref() {
        let item = match item {
            Ok(message) => Item::Frame(message.frame, message.solver_grid),
            Err(BagError::Truncated { truncation, .. }) => Item::Truncated(truncation),
            Err(err) => {
                let _ = out.send(Item::Failed(err));
                return;
            }
        };
        if out.send(item).is_err() {
            return;
        }
    }
    let _ = out.send(Item::Done {
        skipped: frames.skipped(),
    });
}
