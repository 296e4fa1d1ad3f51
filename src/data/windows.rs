//! Training samples: windows of T consecutive frames of one trajectory as input and the frame
//! after them as target, batched.
//!
//! A window `(traj, start)` uses frames `start .. start + T` of trajectory `traj` as input and
//! frame `start + T` as target; it never leaves its trajectory, and a trajectory is a gap-free
//! segment, so no window spans missing frames. A trajectory of F frames gives `F - T` windows.
//! A [`Batch`] carries the scaled inputs `[B, T, N, 5]` (x, y, vx, vy, m) and targets
//! `[B, N, 4]`, plus the physical last input frame and target (domain units, domain units per
//! time unit) for integration and metrics, `dt` (time units) and the materials. In the
//! grid trainer's [`Layout::Frames`] it carries instead the window's frames, inputs and
//! target, physical and unscaled `[B, T + 1, N, 4]`: a copy of consecutive frames a window;
//! in [`Layout::Shares`] the same, written straight into the data-parallel shares' vectors.
//!
//! Order: without a seed, windows in (trajectory, start) order; with one, shuffled by
//! `ChaCha8Rng` seeded from (seed, epoch), so a resumed run sees the same order for the same
//! epoch. All windows of a batch have the same particle count N: windows are grouped by N (in
//! ascending N), each group is cut into batches (its last one may be partial), and with a seed
//! the batches of all groups are shuffled together. Used by `minflow train`.

use std::collections::BTreeMap;
use std::ops::Range;

use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use super::{DataError, Scaler, Trajectory};

/// What a [`WindowIndex`]'s batches carry beside the materials, `dt`, ids, reference
/// positions and solver grids.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Layout {
    /// The paper's architecture's: [`Batch::inputs`] scaled by the index's [`Scaler`],
    /// [`Batch::targets`], [`Batch::last`] and [`Batch::target_phys`]; `frames` empty.
    #[default]
    Scaled,
    /// The grid trainer's on one device: [`Batch::frames`] only (the four vectors above
    /// empty), about half the bytes written a batch and no scaling (`train --arch grid`, its
    /// `bench train`).
    Frames,
    /// The grid trainer's on k devices: as `Frames`, the frames written straight into the
    /// batch's shares ([`Batch::share_ranges`]`(k)`), one vector each in
    /// [`Batch::frame_shares`] (`frames` empty), so that no share copies its rows again.
    Shares(usize),
}

impl Layout {
    /// The grid trainer's layout for `devices` devices: `Frames` for one, `Shares` beyond.
    pub fn frames_for(devices: usize) -> Self {
        if devices > 1 {
            Layout::Shares(devices)
        } else {
            Layout::Frames
        }
    }
}

/// One batch of windows, all with the same particle count N. Arrays are row-major; which of
/// them are filled, the [`Layout`] of the index that made it says.
#[derive(Debug, Clone, PartialEq)]
pub struct Batch {
    /// B, windows in this batch.
    pub b: usize,
    /// T, input frames per window.
    pub t: usize,
    /// N, particles per frame.
    pub n: usize,
    /// `[B, T, N, 5]`: scaled x, y, vx, vy, m of the input frames.
    pub inputs: Vec<f32>,
    /// `[B, N, 4]`: scaled x, y, vx, vy of the frame after the inputs.
    pub targets: Vec<f32>,
    /// `[B, N, 4]`: physical x, y, vx, vy of the last input frame.
    pub last: Vec<f32>,
    /// `[B, N, 4]`: physical x, y, vx, vy of the target frame.
    pub target_phys: Vec<f32>,
    /// `[B, T + 1, N, 4]`: physical x, y, vx, vy of the input frames and the target
    /// ([`Layout::Frames`]; empty otherwise).
    pub frames: Vec<f32>,
    /// `frames` cut into the batch's shares, `[B_s, T + 1, N, 4]` each, B_s the windows of
    /// [`Batch::share_ranges`]`(k)`'s s-th range ([`Layout::Shares`]`(k)`; empty otherwise).
    pub frame_shares: Vec<Vec<f32>>,
    /// `[B]`: frame spacing of each window's trajectory, time units.
    pub dt: Vec<f32>,
    /// `[B, N]`: material ids.
    pub material: Vec<u8>,
    /// `[B]`: (trajectory id, offset of the first input frame in that trajectory).
    pub ids: Vec<(u32, u32)>,
    /// `[B, N, 2]`: physical x, y of each window's trajectory in its first frame (frame 0):
    /// the reference positions of the grid model's `--reference first-frame`.
    pub first_pos: Vec<f32>,
    /// `[B]`: the solver grid of each window's scene, when its bag says
    /// ([`Trajectory::solver_grid`]).
    pub solver_grid: Vec<Option<u32>>,
}

impl Batch {
    /// The batch cut into at most `parts` batches of consecutive windows
    /// ([`Batch::share_ranges`]): a data-parallel step's shares, one per device.
    pub fn shards(&self, parts: usize) -> Vec<Batch> {
        let (t, n) = (self.t, self.n);
        // A batch of `Layout::Shares` is cut from its frames put back in one piece.
        let whole = self.frame_shares.concat();
        let frames = if self.frames.is_empty() {
            &whole
        } else {
            &self.frames
        };
        (self.share_ranges(parts).into_iter())
            .map(|Range { start, end }| {
                let rows = |per: usize| start * per..end * per;
                // The rows of a vector the batch's layout fills; an empty one stays empty.
                let part = |v: &[f32], per: usize| match v.is_empty() {
                    true => Vec::new(),
                    false => v[rows(per)].to_vec(),
                };
                Batch {
                    b: end - start,
                    t,
                    n,
                    inputs: part(&self.inputs, t * n * 5),
                    targets: part(&self.targets, n * 4),
                    last: part(&self.last, n * 4),
                    target_phys: part(&self.target_phys, n * 4),
                    frames: part(frames, (t + 1) * n * 4),
                    frame_shares: Vec::new(),
                    dt: self.dt[rows(1)].to_vec(),
                    material: self.material[rows(n)].to_vec(),
                    ids: self.ids[rows(1)].to_vec(),
                    first_pos: self.first_pos[rows(n * 2)].to_vec(),
                    solver_grid: self.solver_grid[rows(1)].to_vec(),
                }
            })
            .collect()
    }

    /// The windows of at most `parts` shares of consecutive windows, as even as can be (the
    /// first ones one window larger). Fewer than asked when the batch has fewer windows;
    /// none when it is empty.
    pub fn share_ranges(&self, parts: usize) -> Vec<Range<usize>> {
        share_ranges(self.b, parts)
    }
}

/// [`Batch::share_ranges`] of a batch of `b` windows.
fn share_ranges(b: usize, parts: usize) -> Vec<Range<usize>> {
    let parts = parts.max(1).min(b);
    let mut start = 0;
    (0..parts)
        .map(|k| {
            let size = b / parts + usize::from(k < b % parts);
            start += size;
            start - size..start
        })
        .collect()
}

/// Every window of a set of trajectories, and the batches made from them. (`Debug` prints
/// counts, not values.)
#[derive(Clone)]
pub struct WindowIndex {
    trajs: Vec<Trajectory>,
    /// The id each trajectory carries in [`Batch::ids`].
    ids: Vec<u32>,
    scaler: Scaler,
    layout: Layout,
    t: usize,
    /// (position in `trajs`, start).
    windows: Vec<(u32, u32)>,
}

impl std::fmt::Debug for WindowIndex {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WindowIndex")
            .field("trajectories", &self.trajs.len())
            .field("t", &self.t)
            .field("windows", &self.windows.len())
            .field("scaler", &self.scaler)
            .field("layout", &self.layout)
            .finish()
    }
}

impl WindowIndex {
    /// Lists the windows of `t` input frames of `trajs`; a trajectory's id in batches is its
    /// position in `trajs`. `t = 0` is an error.
    pub fn new(trajs: Vec<Trajectory>, t: usize, scaler: Scaler) -> Result<Self, DataError> {
        let ids = (0..trajs.len() as u32).collect();
        Self::with_ids(trajs, ids, t, scaler)
    }

    /// As [`WindowIndex::new`], with the trajectory ids to report in batches.
    pub(crate) fn with_ids(
        trajs: Vec<Trajectory>,
        ids: Vec<u32>,
        t: usize,
        scaler: Scaler,
    ) -> Result<Self, DataError> {
        if t == 0 {
            return Err(DataError::config("window length T", "must be at least 1"));
        }
        let mut windows = Vec::new();
        for (i, traj) in trajs.iter().enumerate() {
            windows.extend((0..traj.windows(t) as u32).map(|s| (i as u32, s)));
        }
        Ok(Self {
            trajs,
            ids,
            scaler,
            layout: Layout::Scaled,
            t,
            windows,
        })
    }

    /// The index with its batches in `layout` ([`Layout::Scaled`] by default).
    pub fn with_layout(mut self, layout: Layout) -> Self {
        self.layout = layout;
        self
    }

    /// Number of windows.
    pub fn len(&self) -> usize {
        self.windows.len()
    }

    /// Whether there are no windows (every trajectory has T frames or fewer).
    pub fn is_empty(&self) -> bool {
        self.windows.is_empty()
    }

    /// T, input frames per window.
    pub fn t(&self) -> usize {
        self.t
    }

    /// The scaler batches are scaled with.
    pub fn scaler(&self) -> &Scaler {
        &self.scaler
    }

    /// The trajectories.
    pub fn trajectories(&self) -> &[Trajectory] {
        &self.trajs
    }

    /// Every window as (trajectory id, start), in index order.
    pub fn window_ids(&self) -> Vec<(u32, u32)> {
        self.windows
            .iter()
            .map(|&(i, s)| (self.ids[i as usize], s))
            .collect()
    }

    /// The distinct particle counts of the windows, ascending. A model tied to one N (the
    /// `global` decoder) should refuse to train when this is not exactly its N.
    pub fn particle_counts(&self) -> Vec<usize> {
        self.groups().into_keys().collect()
    }

    /// Batches in one epoch for `batch_size` (each N group's last batch may be partial).
    pub fn num_batches(&self, batch_size: usize) -> usize {
        let size = batch_size.max(1);
        self.groups().values().map(|g| g.len().div_ceil(size)).sum()
    }

    /// The batches of one epoch; see the module doc for the order. A `batch_size` of 0 is
    /// taken as 1.
    pub fn batches(
        &self,
        batch_size: usize,
        shuffle_seed: Option<u64>,
        epoch: u64,
    ) -> impl Iterator<Item = Batch> + '_ {
        let plan = self.plan(batch_size, shuffle_seed.map(|s| rng(s, epoch, 0)));
        plan.into_iter().map(move |windows| self.batch(&windows))
    }

    /// Window positions grouped by N, in index order.
    fn groups(&self) -> BTreeMap<usize, Vec<u32>> {
        let mut groups: BTreeMap<usize, Vec<u32>> = BTreeMap::new();
        for (w, &(i, _)) in self.windows.iter().enumerate() {
            let n = self.trajs[i as usize].n;
            groups.entry(n).or_default().push(w as u32);
        }
        groups
    }

    /// The batches of one epoch as lists of window positions: shuffled with `rng` when given,
    /// grouped by N, cut into batches, and the batches shuffled when there are several groups.
    pub(crate) fn plan(&self, batch_size: usize, mut rng: Option<ChaCha8Rng>) -> Vec<Vec<u32>> {
        if batch_size == 0 {
            tracing::warn!("batch size 0 taken as 1");
        }
        let size = batch_size.max(1);
        let mut groups = self.groups();
        let mut plan = Vec::with_capacity(self.num_batches(size));
        for windows in groups.values_mut() {
            if let Some(rng) = rng.as_mut() {
                windows.shuffle(rng);
            }
            plan.extend(windows.chunks(size).map(<[u32]>::to_vec));
        }
        if let (Some(rng), true) = (rng.as_mut(), groups.len() > 1) {
            plan.shuffle(rng);
        }
        plan
    }

    /// The batch of the windows at positions `windows` (all of one N), assembled on rayon's
    /// threads, each window into its own rows: a batch of the demo's shape (1,024 windows of
    /// 17 frames of 2,500 particles) is 0.9 GB, which one thread wrote slower than two H200
    /// trained on it (docs/training.md, "Several GPUs"). The index's [`Layout`] says which
    /// rows are written.
    pub(crate) fn batch(&self, windows: &[u32]) -> Batch {
        let mut batch = self.allocate(windows);
        let (t, n) = (self.t, batch.n);
        // Rows of `per` values a particle, a window of `ws` each; an empty vector stays empty.
        let each = |out: &mut [f32],
                    per: usize,
                    ws: &[u32],
                    f: &(dyn Fn(&Trajectory, usize, &mut [f32]) + Sync)| {
            (out.par_chunks_mut((n * per).max(1)).zip(ws.par_iter())).for_each(|(rows, &w)| {
                let (traj, start) = self.at(w);
                f(traj, start, rows)
            })
        };
        let frames = |k: usize| {
            move |traj: &Trajectory, s: usize, rows: &mut [f32]| {
                for (j, rows) in rows.chunks_exact_mut((n * 4).max(1)).enumerate() {
                    rows.copy_from_slice(traj.state(s + k + j));
                }
            }
        };
        each(&mut batch.inputs, t * 5, windows, &|traj, s, rows| {
            for (k, rows) in rows.chunks_exact_mut((n * 5).max(1)).enumerate() {
                self.scaler
                    .scale_to(traj.state(s + k), &traj.material, rows);
            }
        });
        each(&mut batch.targets, 4, windows, &|traj, s, rows| {
            self.scaler.scale_state_to(traj.state(s + t), rows)
        });
        each(&mut batch.last, 4, windows, &frames(t - 1));
        each(&mut batch.target_phys, 4, windows, &frames(t));
        each(&mut batch.frames, (t + 1) * 4, windows, &frames(0));
        let ranges = share_ranges(batch.b, batch.frame_shares.len());
        for (share, range) in batch.frame_shares.iter_mut().zip(ranges) {
            each(share, (t + 1) * 4, &windows[range], &frames(0));
        }
        each(&mut batch.first_pos, 2, windows, &|traj, _, rows| {
            for (to, row) in rows.chunks_exact_mut(2).zip(traj.state(0).chunks_exact(4)) {
                to.copy_from_slice(&row[..2]);
            }
        });
        for (rows, &w) in batch.material.chunks_exact_mut(n.max(1)).zip(windows) {
            rows.copy_from_slice(&self.at(w).0.material);
        }
        batch
    }

    /// The trajectory of the window at position `w` and the window's first frame in it.
    fn at(&self, w: u32) -> (&Trajectory, usize) {
        let (i, start) = self.windows[w as usize];
        (&self.trajs[i as usize], start as usize)
    }

    /// The batch of `windows` with the rows its [`Layout`] fills allocated (zeros) and the
    /// values of each window (dt, ids, solver grid) set.
    fn allocate(&self, windows: &[u32]) -> Batch {
        let (t, b) = (self.t, windows.len());
        let n = windows.first().map_or(0, |&w| self.at(w).0.n);
        debug_assert!(
            windows.iter().all(|&w| self.at(w).0.n == n),
            "a batch mixes particle counts"
        );
        let rows = |per: usize| vec![0.0f32; b * n * per];
        let scaled = self.layout == Layout::Scaled;
        let rows_if = |on: bool, per: usize| if on { rows(per) } else { Vec::new() };
        Batch {
            b,
            t,
            n,
            inputs: rows_if(scaled, t * 5),
            targets: rows_if(scaled, 4),
            last: rows_if(scaled, 4),
            target_phys: rows_if(scaled, 4),
            frames: rows_if(self.layout == Layout::Frames, (t + 1) * 4),
            frame_shares: match self.layout {
                Layout::Shares(k) => (share_ranges(b, k).into_iter())
                    .map(|range| vec![0.0f32; range.len() * n * (t + 1) * 4])
                    .collect(),
                _ => Vec::new(),
            },
            dt: windows.iter().map(|&w| self.at(w).0.dt).collect(),
            material: vec![0u8; b * n],
            ids: (windows.iter())
                .map(|&w| self.windows[w as usize])
                .map(|(i, start)| (self.ids[i as usize], start))
                .collect(),
            first_pos: rows(2),
            solver_grid: windows.iter().map(|&w| self.at(w).0.solver_grid).collect(),
        }
    }
}

/// The shuffling generator for (seed, epoch); `salt` separates independent uses of one seed.
pub(crate) fn rng(seed: u64, epoch: u64, salt: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ salt.wrapping_mul(0x9E37_79B9_7F4A_7C15));
    rng.set_stream(epoch);
    rng
}
