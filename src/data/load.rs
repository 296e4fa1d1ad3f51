//! Reading a dataset: bags (files, folders of `*.mcap`, glob patterns; see
//! [`crate::bag::bag_paths`]) in, trajectories or a scene index out.
//!
//! [`load()`] decodes every ParticleFrame (on one topic, or on every ParticleFrame channel) and
//! groups frames by `scene`, whatever bag they come from and in whatever order; frames are
//! ordered by `frame_index`, duplicates dropped and counted, and a scene with missing frames is
//! split into contiguous segments (see [`Trajectory`]). [`load_scenes`] does the same for a
//! chosen set of scenes only, and [`scan`] builds the index ([`SceneInfo`]: particle count,
//! frames, segments, bags) while keeping no frame data. Truncated bags contribute what was
//! read before the damage and are listed in [`LoadReport::truncated`]. Used by `minflow
//! train` and `minflow eval`.

use std::collections::{BTreeMap, BTreeSet};
use std::ops::Range;
use std::path::PathBuf;

use super::decode::for_each_frame;
use super::trajectory::{contiguous_runs, gaps_between, SceneFrames, SceneHead};
use super::{DataError, LoadReport, Trajectory};
use crate::bag::bag_paths;

/// One scene of a dataset, without its frames.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneInfo {
    /// Scene id.
    pub scene: String,
    /// Particle count N.
    pub n: usize,
    /// Frame spacing, simulation time units.
    pub dt: f32,
    /// Distinct frames (duplicates not counted).
    pub frames: usize,
    /// Contiguous runs of `frame_index` (end exclusive); more than one when frames are missing.
    /// Each becomes one [`Trajectory`] when loaded.
    pub segments: Vec<Range<u32>>,
    /// Bags holding at least one frame of the scene, in reading order.
    pub bags: Vec<PathBuf>,
    /// The solver grid that made the scene, when its bag says ([`Trajectory::solver_grid`]).
    pub solver_grid: Option<u32>,
}

impl SceneInfo {
    /// The index of loaded trajectories (sorted by scene, as [`load()`] returns them): what
    /// [`scan`] would have found, without reading the bags again (`bags` is left empty).
    pub fn of(trajectories: &[Trajectory]) -> Vec<SceneInfo> {
        let mut infos: Vec<SceneInfo> = Vec::new();
        for t in trajectories {
            let segment = t.start_index..t.start_index + t.frames as u32;
            match infos.last_mut() {
                Some(info) if info.scene == t.scene => {
                    info.frames += t.frames;
                    info.segments.push(segment);
                }
                _ => infos.push(SceneInfo {
                    scene: t.scene.clone(),
                    n: t.n,
                    dt: t.dt,
                    frames: t.frames,
                    segments: vec![segment],
                    bags: Vec::new(),
                    solver_grid: t.solver_grid,
                }),
            }
        }
        infos
    }

    /// Windows of `t` input frames plus a target over all segments.
    pub fn windows(&self, t: usize) -> usize {
        self.segments
            .iter()
            .map(|s| s.len().saturating_sub(t))
            .sum()
    }
}

/// Loads every scene of the bags in `inputs` (only `topic`'s frames when given). Trajectories
/// come sorted by scene id, a scene's segments by `start_index`. Inputs with no frames at all
/// are an error; so is a frame whose particle count, materials or `dt` differ from its scene's.
pub fn load(
    inputs: &[PathBuf],
    topic: Option<&str>,
) -> Result<(Vec<Trajectory>, LoadReport), DataError> {
    load_filtered(inputs, topic, None)
}

/// As [`load()`], keeping only the scenes named in `scenes` (others are decoded and skipped).
/// Scenes that are not found are simply absent from the result.
pub fn load_scenes(
    inputs: &[PathBuf],
    topic: Option<&str>,
    scenes: &[String],
) -> Result<(Vec<Trajectory>, LoadReport), DataError> {
    let wanted: BTreeSet<&str> = scenes.iter().map(String::as_str).collect();
    load_filtered(inputs, topic, Some(&wanted))
}

fn load_filtered(
    inputs: &[PathBuf],
    topic: Option<&str>,
    wanted: Option<&BTreeSet<&str>>,
) -> Result<(Vec<Trajectory>, LoadReport), DataError> {
    let paths = bag_paths(inputs)?;
    let mut report = LoadReport::default();
    let mut scenes: BTreeMap<String, SceneFrames> = BTreeMap::new();
    let mut seen = 0u64;
    for_each_frame(&paths, topic, &mut report, |path, frame, grid| {
        seen += 1;
        if wanted.is_some_and(|w| !w.contains(frame.scene.as_str())) {
            return Ok(());
        }
        match scenes.get_mut(&frame.scene) {
            Some(acc) => acc.insert(path, &frame),
            None => {
                let mut acc = SceneFrames::new(&frame);
                acc.head.solver_grid = grid;
                acc.insert(path, &frame)?;
                scenes.insert(frame.scene.clone(), acc);
                Ok(())
            }
        }
    })?;
    if seen == 0 {
        return Err(DataError::NoFrames {
            bags: paths.len(),
            topic: topic.map(str::to_owned),
        });
    }
    let mut trajectories = Vec::new();
    while let Some((_, acc)) = scenes.pop_first() {
        report.duplicates += acc.duplicates;
        report.frames += acc.frames.len() as u64;
        let (segments, mut gaps) = acc.into_segments();
        trajectories.extend(segments);
        report.gaps.append(&mut gaps);
    }
    if report.duplicates > 0 {
        tracing::warn!("dropped {} duplicate frames", report.duplicates);
    }
    tracing::debug!(
        "loaded {} trajectories, {} frames from {} bags",
        trajectories.len(),
        report.frames,
        report.bags
    );
    Ok((trajectories, report))
}

/// ParticleFrames on `topic` in the bags of `inputs` by their summaries' statistics (no
/// message is read: see [`crate::bag::check_index::summary_frames`]); None when a bag has no
/// readable summary, or `inputs` names no bag.
pub fn summary_frames(inputs: &[PathBuf], topic: Option<&str>) -> Option<u64> {
    let paths = bag_paths(inputs).ok()?;
    paths.iter().try_fold(0u64, |sum, path| {
        Some(sum + crate::bag::check_index::summary_frames(path, topic)?)
    })
}

/// The index of the scenes in `inputs` (only `topic`'s frames when given), sorted by scene id.
/// Decodes every frame to check it as [`load()`] does, but keeps only frame indices.
/// [`scan_with_report`] also says which bags were truncated.
pub fn scan(inputs: &[PathBuf], topic: Option<&str>) -> Result<Vec<SceneInfo>, DataError> {
    scan_with_report(inputs, topic).map(|(infos, _)| infos)
}

/// [`scan`], with the [`LoadReport`] of the pass (truncated bags, skipped messages; its
/// `frames` and `gaps` are not filled in).
pub fn scan_with_report(
    inputs: &[PathBuf],
    topic: Option<&str>,
) -> Result<(Vec<SceneInfo>, LoadReport), DataError> {
    struct Acc {
        head: SceneHead,
        indices: BTreeSet<u32>,
        bags: Vec<PathBuf>,
    }
    let paths = bag_paths(inputs)?;
    let mut report = LoadReport::default();
    let mut scenes: BTreeMap<String, Acc> = BTreeMap::new();
    for_each_frame(&paths, topic, &mut report, |path, frame, grid| {
        let acc = scenes.entry(frame.scene.clone()).or_insert_with(|| Acc {
            head: SceneHead {
                solver_grid: grid,
                ..SceneHead::new(&frame)
            },
            indices: BTreeSet::new(),
            bags: Vec::new(),
        });
        acc.head.check(path, &frame)?;
        acc.indices.insert(frame.frame_index);
        if acc.bags.last().is_none_or(|b| b != path) {
            acc.bags.push(path.to_path_buf());
        }
        Ok(())
    })?;
    if scenes.is_empty() {
        return Err(DataError::NoFrames {
            bags: paths.len(),
            topic: topic.map(str::to_owned),
        });
    }
    let infos = scenes
        .into_values()
        .map(|acc| {
            let segments = contiguous_runs(acc.indices.iter().copied());
            for gap in gaps_between(&acc.head.scene, &segments) {
                tracing::warn!("{gap}: the scene will be split there into separate trajectories");
            }
            SceneInfo {
                n: acc.head.material.len(),
                dt: acc.head.dt,
                frames: acc.indices.len(),
                segments,
                bags: acc.bags,
                solver_grid: acc.head.solver_grid,
                scene: acc.head.scene,
            }
        })
        .collect();
    Ok((infos, report))
}
