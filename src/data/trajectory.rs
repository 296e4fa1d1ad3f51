//! Trajectories: the frames of one scene as one dense buffer, and how frames read from bags
//! become trajectories.
//!
//! A [`Trajectory`] holds a contiguous run of frames (no missing `frame_index`) of one scene:
//! `states` is `[F, N, 4]` frame-major with per particle x, y (domain units) and vx, vy (domain
//! units per time unit), copied bit for bit from the messages' interleaved `position` and
//! `velocity` ([`crate::msgs::state_rows`]); `material` is the scene's N material ids; `dt` is
//! the frame spacing in time units from the messages. A scene with missing frames becomes
//! several trajectories (segments), and the missing ranges are reported as [`Gap`]s in the
//! [`LoadReport`]. `SceneFrames` (internal) collects the frames of one scene as they are read
//! (in any order, from any number of bags), checks that particle count, materials and `dt`
//! never change, drops duplicates, and cuts the result into segments. Used by `minflow train`
//! and `minflow eval`.

use std::collections::BTreeMap;
use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};

use super::DataError;
use crate::bag::Truncation;
use crate::msgs::ParticleFrame;

/// A contiguous run of frames of one scene. (`Debug` prints the shape, not the values.)
#[derive(Clone, PartialEq)]
pub struct Trajectory {
    /// Scene id (several segments of one scene share it).
    pub scene: String,
    /// Frame spacing, simulation time units (the messages' `dt`).
    pub dt: f32,
    /// N material ids (0 liquid, 1 jelly, 2 snow, 3 rope), the same in every frame.
    pub material: Vec<u8>,
    /// `frame_index` of the first frame; frame `k` of this trajectory is `start_index + k`.
    pub start_index: u32,
    /// `[F, N, 4]`, frame-major: x, y (domain units), vx, vy (domain units per time unit).
    pub states: Vec<f32>,
    /// F, the number of frames.
    pub frames: usize,
    /// N, the number of particles.
    pub n: usize,
    /// The solver's grid (cells per side) that made the scene, when its bag says
    /// ([`crate::bag::SOLVER_GRID_KEY`], written by `simulate`); the liquid's pressure
    /// projection picks its threshold by it.
    pub solver_grid: Option<u32>,
}

impl Trajectory {
    /// Frame `k`'s state, `[N, 4]` (x, y, vx, vy per particle). Panics when `k >= frames`.
    pub fn state(&self, k: usize) -> &[f32] {
        let row = self.n * 4;
        &self.states[k * row..(k + 1) * row]
    }

    /// `frame_index` of frame `k`.
    pub fn frame_index(&self, k: usize) -> u32 {
        self.start_index + k as u32
    }

    /// Windows of `t` input frames plus one target frame: `frames - t` (0 when too short).
    pub fn windows(&self, t: usize) -> usize {
        self.frames.saturating_sub(t)
    }
}

impl fmt::Debug for Trajectory {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Trajectory")
            .field("scene", &self.scene)
            .field("dt", &self.dt)
            .field("start_index", &self.start_index)
            .field("frames", &self.frames)
            .field("n", &self.n)
            .finish_non_exhaustive()
    }
}

/// Frames missing inside a scene: the scene is split around them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Gap {
    /// Scene id.
    pub scene: String,
    /// The missing `frame_index`es (end exclusive).
    pub missing: Range<u32>,
}

impl fmt::Display for Gap {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let Range { start, end } = self.missing;
        match end - start {
            1 => write!(f, "scene {:?}: frame {start} missing", self.scene),
            k => write!(
                f,
                "scene {:?}: {k} frames {start}..={} missing",
                self.scene,
                end - 1
            ),
        }
    }
}

/// What loading found besides the trajectories.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LoadReport {
    /// Bags read.
    pub bags: usize,
    /// Frames kept (after dropping duplicates).
    pub frames: u64,
    /// Frames dropped because a frame with the same (scene, frame_index) came earlier.
    pub duplicates: u64,
    /// Missing frame ranges inside scenes, by scene then frame.
    pub gaps: Vec<Gap>,
    /// Bags cut or damaged: everything before the damage was used.
    pub truncated: Vec<(PathBuf, Truncation)>,
    /// Messages on other topics or with other schemas, passed over.
    pub skipped: u64,
}

/// The contiguous runs of a sorted, duplicate-free sequence of frame indices.
pub(crate) fn contiguous_runs(indices: impl IntoIterator<Item = u32>) -> Vec<Range<u32>> {
    let mut runs: Vec<Range<u32>> = Vec::new();
    for i in indices {
        match runs.last_mut() {
            Some(run) if run.end == i => run.end += 1,
            _ => runs.push(i..i + 1),
        }
    }
    runs
}

/// The gaps between consecutive runs of a scene.
pub(crate) fn gaps_between(scene: &str, runs: &[Range<u32>]) -> Vec<Gap> {
    runs.windows(2)
        .map(|w| Gap {
            scene: scene.to_owned(),
            missing: w[0].end..w[1].start,
        })
        .collect()
}

/// What every frame of a scene must share with the first one read.
#[derive(Debug, Clone)]
pub(crate) struct SceneHead {
    pub scene: String,
    pub dt: f32,
    pub material: Vec<u8>,
    /// `frame_index` of the first frame read.
    pub reference: u32,
    /// The solver's grid, when the bag says ([`crate::bag::SOLVER_GRID_KEY`]).
    pub solver_grid: Option<u32>,
}

impl SceneHead {
    pub fn new(frame: &ParticleFrame) -> Self {
        Self {
            scene: frame.scene.clone(),
            dt: frame.dt,
            material: frame.material.clone(),
            reference: frame.frame_index,
            solver_grid: None,
        }
    }

    /// Checks `frame` (read from `path`) against the first frame of the scene.
    pub fn check(&self, path: &Path, frame: &ParticleFrame) -> Result<(), DataError> {
        let fail = |what: String| DataError::Inconsistent {
            path: path.to_path_buf(),
            scene: self.scene.clone(),
            frame: frame.frame_index,
            reference: self.reference,
            what,
        };
        let (n0, n) = (self.material.len(), frame.material.len());
        if n != n0 {
            return Err(fail(format!(
                "particle count changed: {n} particles, the scene's first frame has {n0}"
            )));
        }
        if let Some(i) = (0..n).find(|&i| frame.material[i] != self.material[i]) {
            return Err(fail(format!(
                "material of particle {i} changed: {}, the scene's first frame has {}",
                frame.material[i], self.material[i]
            )));
        }
        if (frame.dt - self.dt).abs() > 1e-4 * self.dt.abs() {
            return Err(fail(format!(
                "dt changed: {}, the scene's first frame has {}",
                frame.dt, self.dt
            )));
        }
        Ok(())
    }
}

/// The frames of one scene collected so far, keyed by `frame_index`; each is `[N, 4]`.
#[derive(Debug)]
pub(crate) struct SceneFrames {
    pub head: SceneHead,
    pub frames: BTreeMap<u32, Vec<f32>>,
    pub duplicates: u64,
}

impl SceneFrames {
    pub fn new(frame: &ParticleFrame) -> Self {
        Self {
            head: SceneHead::new(frame),
            frames: BTreeMap::new(),
            duplicates: 0,
        }
    }

    /// Checks and adds one frame; a second frame with the same index is counted and dropped.
    pub fn insert(&mut self, path: &Path, frame: &ParticleFrame) -> Result<(), DataError> {
        self.head.check(path, frame)?;
        if self.frames.contains_key(&frame.frame_index) {
            self.duplicates += 1;
            return Ok(());
        }
        self.frames
            .insert(frame.frame_index, crate::msgs::state_rows(frame));
        Ok(())
    }

    /// The scene's contiguous segments, in frame order, and the gaps between them (also
    /// logged). Frames are moved, not copied, one at a time.
    pub fn into_segments(self) -> (Vec<Trajectory>, Vec<Gap>) {
        let head = self.head;
        let runs = contiguous_runs(self.frames.keys().copied());
        let gaps = gaps_between(&head.scene, &runs);
        for gap in &gaps {
            tracing::warn!("{gap}: the scene is split there into separate trajectories");
        }
        let n = head.material.len();
        let mut frames = self.frames.into_iter();
        let mut out = Vec::with_capacity(runs.len());
        for run in runs {
            let count = run.len();
            let mut states = Vec::with_capacity(count * n * 4);
            for (_, state) in frames.by_ref().take(count) {
                states.extend_from_slice(&state);
            }
            out.push(Trajectory {
                scene: head.scene.clone(),
                dt: head.dt,
                material: head.material.clone(),
                start_index: run.start,
                states,
                frames: count,
                n,
                solver_grid: head.solver_grid,
            });
        }
        (out, gaps)
    }
}
