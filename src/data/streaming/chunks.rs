//! The chunks a [`StreamingLoader`](super::StreamingLoader) reads: how an epoch's scene order
//! is cut into chunks under the frame budget ([`pack`]), how many batches a chunk gives
//! before it is read ([`chunk_batches`], so a resumed epoch skips whole chunks unread), how a
//! chunk is read from its bags with the scenes' global trajectory ids ([`load_chunk`]), and
//! the worker thread that reads the next chunk while the current one is trained on
//! ([`Prefetch`]). A chunk in memory is counted in the loader's [`Residency`] until dropped.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;

use crate::data::{load_scenes, DataError, Layout, Scaler, SceneInfo, Trajectory, WindowIndex};

/// Frames held by loaded chunks now, and the most held at once.
#[derive(Debug, Default)]
pub(super) struct Residency {
    now: AtomicUsize,
    peak: AtomicUsize,
}

impl Residency {
    /// The most frames held at once so far.
    pub(super) fn peak(&self) -> usize {
        self.peak.load(Ordering::Relaxed)
    }
}

/// A loaded chunk's window index; its frames count as resident until it is dropped.
pub(super) struct Loaded {
    pub(super) index: WindowIndex,
    frames: usize,
    residency: Arc<Residency>,
}

impl Loaded {
    /// `index`, counted in `residency` from now on.
    pub(super) fn new(index: WindowIndex, residency: Arc<Residency>) -> Self {
        let frames = index.trajectories().iter().map(|t| t.frames).sum();
        let now = residency.now.fetch_add(frames, Ordering::Relaxed) + frames;
        residency.peak.fetch_max(now, Ordering::Relaxed);
        Self {
            index,
            frames,
            residency,
        }
    }
}

impl Drop for Loaded {
    fn drop(&mut self) {
        self.residency.now.fetch_sub(self.frames, Ordering::Relaxed);
    }
}

/// What reading a chunk needs, shared with the worker thread.
#[derive(Clone)]
pub(super) struct ChunkReader {
    /// The loader's scenes, sorted by id.
    pub(super) scenes: Arc<[SceneInfo]>,
    pub(super) topic: Option<String>,
    pub(super) t: usize,
    pub(super) scaler: Scaler,
    /// What the chunks' batches carry.
    pub(super) layout: Layout,
    pub(super) residency: Arc<Residency>,
}

impl ChunkReader {
    /// Reads the scenes at `positions` into a counted window index with global ids.
    pub(super) fn read(&self, positions: &[usize]) -> Result<Loaded, DataError> {
        let (trajs, ids) = load_chunk(&self.scenes, positions, self.topic.as_deref())?;
        let index =
            WindowIndex::with_ids(trajs, ids, self.t, self.scaler)?.with_layout(self.layout);
        Ok(Loaded::new(index, self.residency.clone()))
    }
}

/// The next chunk, being read on a worker thread of its own.
pub(super) struct Prefetch(JoinHandle<Result<Loaded, DataError>>);

impl Prefetch {
    /// Starts reading `positions` with `reader`.
    pub(super) fn start(reader: &ChunkReader, positions: Vec<usize>) -> Self {
        let reader = reader.clone();
        Self(std::thread::spawn(move || reader.read(&positions)))
    }

    /// The chunk, waiting for the thread to finish it.
    pub(super) fn wait(self) -> Result<Loaded, DataError> {
        self.0
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
    }
}

/// Batches of `batch_size` a chunk of `scenes` at `positions` gives with windows of `t`
/// frames: [`WindowIndex::num_batches`] of the loaded chunk, known without reading it.
pub(super) fn chunk_batches(
    scenes: &[SceneInfo],
    positions: &[usize],
    t: usize,
    batch_size: usize,
) -> usize {
    let mut groups: BTreeMap<usize, usize> = BTreeMap::new();
    for &p in positions {
        *groups.entry(scenes[p].n).or_default() += scenes[p].windows(t);
    }
    let size = batch_size.max(1);
    groups.values().map(|w| w.div_ceil(size)).sum()
}

/// Cuts `order` (positions in `scenes`) into consecutive chunks of at most `budget` frames.
pub(super) fn pack(scenes: &[SceneInfo], order: &[usize], budget: usize) -> Vec<Vec<usize>> {
    let mut chunks: Vec<Vec<usize>> = Vec::new();
    let mut frames = 0;
    for &p in order {
        let f = scenes[p].frames;
        match chunks.last_mut() {
            Some(chunk) if frames + f <= budget => chunk.push(p),
            _ => {
                chunks.push(vec![p]);
                frames = 0;
            }
        }
        frames += f;
    }
    chunks
}

/// Loads the scenes at `positions` (sorted `scenes`) from their bags; returns the trajectories
/// and their global ids, after checking that each scene still has the segments of the scan.
pub(super) fn load_chunk(
    scenes: &[SceneInfo],
    positions: &[usize],
    topic: Option<&str>,
) -> Result<(Vec<Trajectory>, Vec<u32>), DataError> {
    let mut bags = Vec::new();
    let mut names = Vec::with_capacity(positions.len());
    for &p in positions {
        names.push(scenes[p].scene.clone());
        for bag in &scenes[p].bags {
            if !bags.contains(bag) {
                bags.push(bag.clone());
            }
        }
    }
    let (trajs, _) = load_scenes(&bags, topic, &names)?;
    let mut sorted = positions.to_vec();
    sorted.sort_unstable();
    // Global id of a scene's first segment: segments of all scenes before it.
    let mut first_id = Vec::with_capacity(scenes.len());
    let mut next = 0;
    for s in scenes {
        first_id.push(next);
        next += s.segments.len();
    }
    let mut ids = Vec::with_capacity(trajs.len());
    let mut rest = trajs.as_slice();
    for p in sorted {
        let info = &scenes[p];
        let base = first_id[p];
        let count = rest.iter().take_while(|t| t.scene == info.scene).count();
        let (mine, others) = rest.split_at(count);
        let found: Vec<_> = (mine.iter())
            .map(|t| t.start_index..t.start_index + t.frames as u32)
            .collect();
        if found != info.segments {
            let what = format!("segments {:?} now, {:?} when scanned", found, info.segments);
            return Err(DataError::Changed {
                scene: info.scene.clone(),
                what,
            });
        }
        ids.extend((0..count).map(|k| (base + k) as u32));
        rest = others;
    }
    Ok((trajs, ids))
}
