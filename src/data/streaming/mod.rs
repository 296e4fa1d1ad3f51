//! Batches from a dataset larger than memory: [`StreamingLoader`] keeps only the scene index
//! (from [`scan`](super::scan)) and loads scenes from their bags a chunk at a time.
//!
//! Each epoch visits the scenes in an order shuffled from (seed, epoch) (index order without a
//! seed) and packs consecutive scenes into chunks whose frames total at most half of
//! `max_resident_frames` (the whole budget when a scene is larger than half of it); a chunk
//! is loaded (only the bags that hold its scenes are read), its windows are shuffled and
//! batched as [`WindowIndex`] does, and it is dropped when its last batch is taken. While a
//! chunk is trained on, the next one is read on a worker thread ([`chunks::Prefetch`]), so
//! the step rarely waits for the bags and at most the budget is resident. An epoch can start
//! part-way (`skip` batches, [`StreamingLoader::epoch_from`]): whole chunks before that point
//! are not read, and an epoch that continues where the previous call's batches stopped takes
//! over its loaded chunk and its read-ahead (a run whose epochs are shorter than a pass
//! reads each chunk once). When the whole dataset fits the budget it is loaded once, kept,
//! and its batches are exactly those of a [`WindowIndex`] over the same trajectories.
//! Trajectory ids in [`Batch::ids`](super::Batch) are global: scenes sorted by id, segments
//! in frame order, the numbering [`load()`](fn@super::load) and [`WindowIndex::new`] give the
//! same scenes. Every window is visited exactly once per epoch. Used by `minflow train` for
//! large datasets.
//!
//! Files: this one holds the loader; `chunks.rs` the packing, reading and read-ahead of
//! chunks; `epoch.rs` the iterator over an epoch's batches.

mod chunks;
mod epoch;

use std::sync::{Arc, Mutex};

use super::{DataError, Layout, Scaler, ScalerFit, SceneInfo, Trajectory};
use chunks::{load_chunk, pack, ChunkReader, Loaded};
pub use epoch::EpochBatches;
use epoch::Parked;

/// Streams the windows of the scenes in its index under a budget of resident frames.
pub struct StreamingLoader {
    /// The scenes (sorted by id), topic, window length and scaler, as chunks are read.
    reader: ChunkReader,
    budget: usize,
    /// Everything, when it fits the budget (loaded at the first epoch).
    resident: Option<Loaded>,
    /// The loaded chunk and read-ahead an epoch's iterator left when dropped early.
    parked: Mutex<Option<Parked>>,
}

impl std::fmt::Debug for StreamingLoader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StreamingLoader")
            .field("scenes", &self.reader.scenes.len())
            .field("t", &self.reader.t)
            .field("budget", &self.budget)
            .finish()
    }
}

impl StreamingLoader {
    /// A loader over `scenes` (normally the training scenes of a [`scan`](super::scan)),
    /// reading `topic`'s frames (every ParticleFrame channel when `None`), with windows of `t`
    /// input frames scaled by `scaler`, holding at most `max_resident_frames` frames at once.
    /// A scene larger than the budget, a scene listed twice, `t = 0` or a zero budget are errors.
    pub fn new(
        mut scenes: Vec<SceneInfo>,
        topic: Option<&str>,
        t: usize,
        scaler: Scaler,
        max_resident_frames: usize,
    ) -> Result<Self, DataError> {
        if t == 0 {
            return Err(DataError::config("window length T", "must be at least 1"));
        }
        check_scenes(&mut scenes, max_resident_frames)?;
        Ok(Self {
            reader: ChunkReader {
                scenes: scenes.into(),
                topic: topic.map(str::to_owned),
                t,
                scaler,
                layout: Layout::Scaled,
                residency: Arc::default(),
            },
            budget: max_resident_frames,
            resident: None,
            parked: Mutex::new(None),
        })
    }
    /// The loader with its batches in `layout` ([`Layout::Scaled`] by default).
    pub fn with_layout(mut self, layout: Layout) -> Self {
        self.reader.layout = layout;
        self
    }

    /// Fits a [`Scaler`] on `scenes` (the training scenes only) reading them chunk by chunk
    /// under the same budget.
    pub fn fit_scaler(
        scenes: Vec<SceneInfo>,
        topic: Option<&str>,
        max_resident_frames: usize,
    ) -> Result<Scaler, DataError> {
        let mut fit = ScalerFit::new();
        Self::for_each_chunk(scenes, topic, max_resident_frames, |trajs| {
            trajs.iter().for_each(|t| fit.add(t));
        })?;
        Ok(fit.finish())
    }

    /// One pass over `scenes` in id order, a chunk of at most `max_resident_frames` frames at
    /// a time: `visit` sees each chunk's trajectories, which are dropped before the next chunk
    /// is read. For statistics of a dataset larger than memory ([`Self::fit_scaler`], the
    /// grid model's velocity statistics).
    ///
    /// # Errors
    /// A zero budget, a scene larger than it or listed twice, a bag that is unreadable or
    /// changed since the scan.
    pub fn for_each_chunk(
        mut scenes: Vec<SceneInfo>,
        topic: Option<&str>,
        max_resident_frames: usize,
        mut visit: impl FnMut(&[Trajectory]),
    ) -> Result<(), DataError> {
        check_scenes(&mut scenes, max_resident_frames)?;
        let order: Vec<usize> = (0..scenes.len()).collect();
        for chunk in pack(&scenes, &order, max_resident_frames) {
            let (trajs, _) = load_chunk(&scenes, &chunk, topic)?;
            visit(&trajs);
        }
        Ok(())
    }

    /// Every scene of `scenes` (an index from [`scan`](super::scan)) loaded whole from the
    /// bags that hold it, in id order: a part of a dataset that must be in memory (the grid
    /// architecture's validation scenes) when the rest is streamed.
    ///
    /// # Errors
    /// A scene listed twice, a bag that is unreadable or changed since the scan.
    pub fn load_whole(
        mut scenes: Vec<SceneInfo>,
        topic: Option<&str>,
    ) -> Result<Vec<Trajectory>, DataError> {
        if scenes.is_empty() {
            return Ok(Vec::new());
        }
        check_scenes(&mut scenes, usize::MAX)?;
        let all: Vec<usize> = (0..scenes.len()).collect();
        Ok(load_chunk(&scenes, &all, topic)?.0)
    }

    /// T, the input frames of a window.
    pub fn t(&self) -> usize {
        self.reader.t
    }

    /// Frames of all scenes.
    pub fn total_frames(&self) -> usize {
        self.reader.scenes.iter().map(|s| s.frames).sum()
    }

    /// Whether everything fits the budget (then it is loaded once and kept).
    pub fn fits(&self) -> bool {
        self.total_frames() <= self.budget
    }

    /// The frames of one chunk: half the budget, so that the chunk trained on and the one
    /// read ahead fit it together; the whole budget (and no read-ahead) when a scene is
    /// larger than half of it.
    fn chunk_frames(&self) -> usize {
        match self.read_ahead() {
            true => self.budget / 2,
            false => self.budget,
        }
    }

    /// Whether the next chunk is read while the current one is trained on.
    fn read_ahead(&self) -> bool {
        let largest = self.reader.scenes.iter().map(|s| s.frames).max();
        largest.is_some_and(|f| f <= self.budget / 2)
    }

    /// Windows per epoch.
    pub fn len(&self) -> usize {
        let t = self.reader.t;
        self.reader.scenes.iter().map(|s| s.windows(t)).sum()
    }

    /// Whether an epoch yields nothing.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The scenes, sorted by id.
    pub fn scenes(&self) -> &[SceneInfo] {
        &self.reader.scenes
    }

    /// The distinct particle counts of scenes that give windows, ascending.
    pub fn particle_counts(&self) -> Vec<usize> {
        let t = self.reader.t;
        let mut counts: Vec<usize> = (self.reader.scenes.iter())
            .filter(|s| s.windows(t) > 0)
            .map(|s| s.n)
            .collect();
        counts.sort_unstable();
        counts.dedup();
        counts
    }

    /// The most frames held at once so far (the chunk trained on and the one read ahead, or
    /// everything when resident).
    pub fn peak_resident_frames(&self) -> usize {
        self.reader.residency.peak()
    }

    /// The batches of one epoch, with the shuffling of [`WindowIndex::batches`]. Loading a chunk
    /// can fail (bags changed or removed since the scan): that error is yielded and ends the
    /// epoch.
    pub fn epoch(
        &mut self,
        batch_size: usize,
        shuffle_seed: Option<u64>,
        epoch: u64,
    ) -> Result<EpochBatches<'_>, DataError> {
        self.epoch_from(batch_size, shuffle_seed, epoch, 0)
    }

    /// [`Self::epoch`]'s batches after its first `skip`: chunks whose batches all come
    /// before that point are not read. When the previous epoch iterator of the same
    /// (`batch_size`, `shuffle_seed`, `epoch`) was dropped after exactly `skip` batches, its
    /// loaded chunk and read-ahead are taken over instead of being read again.
    ///
    /// # Errors
    /// Loading the whole dataset failed (when it fits the budget).
    pub fn epoch_from(
        &mut self,
        batch_size: usize,
        shuffle_seed: Option<u64>,
        epoch: u64,
        skip: usize,
    ) -> Result<EpochBatches<'_>, DataError> {
        if self.fits() && self.resident.is_none() {
            let all: Vec<usize> = (0..self.reader.scenes.len()).collect();
            self.resident = Some(self.reader.read(&all)?);
        }
        let key = (batch_size, shuffle_seed, epoch);
        let parked = self.parked.get_mut().map_or(None, Option::take);
        let this: &Self = self;
        if let Some(index) = this.resident.as_ref() {
            return Ok(EpochBatches::resident(this, &index.index, key, skip));
        }
        if let Some(parked) = parked.filter(|p| p.continues(key, skip)) {
            return Ok(EpochBatches::unpark(this, parked));
        }
        let order = epoch::scene_order(this.reader.scenes.len(), shuffle_seed, epoch);
        let chunks = pack(&this.reader.scenes, &order, this.chunk_frames());
        Ok(EpochBatches::chunked(this, chunks, key, skip))
    }
}

/// Sorts `scenes` by id and checks them against the budget.
fn check_scenes(scenes: &mut [SceneInfo], budget: usize) -> Result<(), DataError> {
    if budget == 0 {
        return Err(DataError::config(
            "max_resident_frames",
            "must be at least 1",
        ));
    }
    scenes.sort_by(|a, b| a.scene.cmp(&b.scene));
    if let Some(w) = scenes.windows(2).find(|w| w[0].scene == w[1].scene) {
        let why = format!("scene {:?} is listed twice", w[0].scene);
        return Err(DataError::config("scene index", why));
    }
    match scenes.iter().find(|s| s.frames > budget) {
        Some(s) => Err(DataError::SceneTooLarge {
            scene: s.scene.clone(),
            frames: s.frames,
            budget,
        }),
        None => Ok(()),
    }
}
