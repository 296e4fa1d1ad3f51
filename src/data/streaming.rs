//! Batches from a dataset larger than memory: [`StreamingLoader`] keeps only the scene index
//! (from [`scan`](super::scan)) and loads scenes from their bags a chunk at a time.
//!
//! Each epoch visits the scenes in an order shuffled from (seed, epoch) (index order without a
//! seed) and packs consecutive scenes into chunks whose frames total at most
//! `max_resident_frames`; a chunk is loaded (only the bags that hold its scenes are read), its
//! windows are shuffled and batched as [`WindowIndex`] does, and it is dropped before the next
//! one is loaded. When the whole dataset fits the budget it is loaded once, kept, and its
//! batches are exactly those of a [`WindowIndex`] over the same trajectories. Trajectory ids in
//! [`Batch::ids`](super::Batch) are global: scenes sorted by id, segments in frame order, the
//! numbering [`load()`](fn@super::load) and [`WindowIndex::new`] give the same scenes. Every window
//! is visited exactly once per epoch. Used by `minflow train` for large datasets.

use std::borrow::Cow;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicUsize, Ordering};

use rand::seq::SliceRandom;

use super::windows::rng;
use super::{load_scenes, Batch, DataError, Scaler, ScalerFit, SceneInfo, Trajectory, WindowIndex};

/// Streams the windows of the scenes in its index under a budget of resident frames.
#[derive(Debug)]
pub struct StreamingLoader {
    /// Sorted by scene id.
    scenes: Vec<SceneInfo>,
    topic: Option<String>,
    t: usize,
    scaler: Scaler,
    budget: usize,
    resident: Option<WindowIndex>,
    peak: AtomicUsize,
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
            scenes,
            topic: topic.map(str::to_owned),
            t,
            scaler,
            budget: max_resident_frames,
            resident: None,
            peak: AtomicUsize::new(0),
        })
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
        self.t
    }

    /// Frames of all scenes.
    pub fn total_frames(&self) -> usize {
        self.scenes.iter().map(|s| s.frames).sum()
    }

    /// Whether everything fits the budget (then it is loaded once and kept).
    pub fn fits(&self) -> bool {
        self.total_frames() <= self.budget
    }

    /// Windows per epoch.
    pub fn len(&self) -> usize {
        self.scenes.iter().map(|s| s.windows(self.t)).sum()
    }

    /// Whether an epoch yields nothing.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The scenes, sorted by id.
    pub fn scenes(&self) -> &[SceneInfo] {
        &self.scenes
    }

    /// The distinct particle counts of scenes that give windows, ascending.
    pub fn particle_counts(&self) -> Vec<usize> {
        let mut counts: Vec<usize> = (self.scenes.iter())
            .filter(|s| s.windows(self.t) > 0)
            .map(|s| s.n)
            .collect();
        counts.sort_unstable();
        counts.dedup();
        counts
    }

    /// The most frames held at once so far (trajectories of one chunk, or everything when
    /// resident).
    pub fn peak_resident_frames(&self) -> usize {
        self.peak.load(Ordering::Relaxed)
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
        if self.fits() && self.resident.is_none() {
            let all: Vec<usize> = (0..self.scenes.len()).collect();
            self.resident = Some(self.load_index(&all)?);
        }
        let this: &Self = self;
        let mut batches = EpochBatches {
            loader: this,
            batch_size,
            seed: shuffle_seed,
            epoch,
            chunks: VecDeque::new(),
            chunk_no: 0,
            current: None,
        };
        if let Some(index) = this.resident.as_ref() {
            let plan = index.plan(batch_size, shuffle_seed.map(|s| rng(s, epoch, 0)));
            batches.current = Some((Cow::Borrowed(index), plan, 0));
        } else {
            let mut order: Vec<usize> = (0..this.scenes.len()).collect();
            if let Some(seed) = shuffle_seed {
                order.shuffle(&mut rng(seed, epoch, 1));
            }
            batches.chunks = pack(&this.scenes, &order, this.budget).into();
        }
        Ok(batches)
    }

    /// Loads the scenes at `positions` into a window index with global trajectory ids.
    fn load_index(&self, positions: &[usize]) -> Result<WindowIndex, DataError> {
        let (trajs, ids) = load_chunk(&self.scenes, positions, self.topic.as_deref())?;
        let frames = trajs.iter().map(|t| t.frames).sum();
        self.peak.fetch_max(frames, Ordering::Relaxed);
        WindowIndex::with_ids(trajs, ids, self.t, self.scaler)
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

/// Cuts `order` (positions in `scenes`) into consecutive chunks of at most `budget` frames.
fn pack(scenes: &[SceneInfo], order: &[usize], budget: usize) -> Vec<Vec<usize>> {
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
fn load_chunk(
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

/// The batches of one epoch of a [`StreamingLoader`]; see [`StreamingLoader::epoch`].
pub struct EpochBatches<'a> {
    loader: &'a StreamingLoader,
    batch_size: usize,
    seed: Option<u64>,
    epoch: u64,
    /// Chunks still to load, as positions in the loader's scenes.
    chunks: VecDeque<Vec<usize>>,
    chunk_no: u64,
    /// The loaded chunk, its batches as window positions, and the next batch.
    current: Option<(Cow<'a, WindowIndex>, Vec<Vec<u32>>, usize)>,
}

impl Iterator for EpochBatches<'_> {
    type Item = Result<Batch, DataError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            if let Some((index, plan, pos)) = self.current.as_mut() {
                if let Some(windows) = plan.get(*pos) {
                    *pos += 1;
                    return Some(Ok(index.batch(windows)));
                }
            }
            self.current = None; // drop the chunk before loading the next
            let chunk = self.chunks.pop_front()?;
            self.chunk_no += 1;
            match self.loader.load_index(&chunk) {
                Ok(index) => {
                    let rng = (self.seed).map(|s| rng(s, self.epoch, 1 + self.chunk_no));
                    let plan = index.plan(self.batch_size, rng);
                    self.current = Some((Cow::Owned(index), plan, 0));
                }
                Err(err) => {
                    self.chunks.clear(); // the error ends the epoch
                    return Some(Err(err));
                }
            }
        }
    }
}
