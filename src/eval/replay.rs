//! Replay evaluation: scoring a bag of predicted frames (recorded from a running surrogate
//! node, or written offline) against the ground truth, matched by scene and `frame_index`.
//!
//! Predicted frames are ParticleFrames with `frame_index` = input's + 1 (docs/design.md,
//! "Messages"). Per scene, step `k` = `frame_index - first + 1`, where `first` is the scene's
//! smallest predicted `frame_index`; steps 1..=H are scored. A closed-loop node (`--rollout
//! K`: K predicted frames after its first T truth frames) thus publishes exactly the frames of
//! the direct rollout from the scene's first frame, and its bag scores exactly like `minflow
//! eval --model` (the baselines are seeded with truth frame `first - 1` as there). For a node
//! publishing one-step predictions of every replayed frame, `one_step` makes the baselines
//! one-step too (step k predicted from truth frame `first + k - 2`); the step axis is then
//! the position in the scene.
//!
//! Steps with ground truth but no predicted frame are counted per scene
//! ([`SceneResult::missing`]) and excluded, never scored as zero error; predicted frames
//! without ground truth are counted as `unmatched`, those past the horizon as `beyond`. Used
//! by `minflow eval --pred BAG --truth BAG|DIR`.
//!
//! Each scene's frame at the horizon's last step is also scored for structure
//! ([`Probe::End`], the measures of [`super::plausibility`] that `eval --model` probes: area,
//! intact fraction, rope connectivity, strain, kinetic energy summed over the steps), so a
//! closed loop's bag says whether its liquid kept its area and its solids held.

use std::collections::BTreeMap;
use std::path::PathBuf;

use super::conservation::Bodies;
use super::plausibility::{EnergySums, Neighbours, Plausibility};
use super::{frame_metrics, EvalError, Evaluation, Predictor, Probe, SceneResult};
use super::{Snapshots, StepSums};
use crate::bag::{bag_paths, BagError, BagReader, Truncation};
use crate::data::{Scaler, Trajectory};

/// The predicted frames of one scene.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ScenePredictions {
    /// N material ids (of the first frame read).
    pub material: Vec<u8>,
    /// `frame_index` -> physical `[N, 4]` (x, y, vx, vy).
    pub frames: BTreeMap<u32, Vec<f32>>,
    /// Frames dropped because the same `frame_index` came earlier.
    pub duplicates: usize,
}

/// Predicted frames by scene, as read from bags.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Predictions {
    /// Scene id -> its frames.
    pub scenes: BTreeMap<String, ScenePredictions>,
    /// Bags that were cut or damaged (everything before the damage was read).
    pub truncated: Vec<(PathBuf, Truncation)>,
}

/// Reads the predicted frames on `topic` (every ParticleFrame channel when `None`) of the
/// bags in `inputs` (files, folders, patterns). Errors on unreadable bags and on frames whose
/// particle count or materials change within a scene; a truncated bag gives what was read.
pub fn read_predictions(inputs: &[PathBuf], topic: Option<&str>) -> Result<Predictions, EvalError> {
    let mut out = Predictions::default();
    let mut read = 0usize;
    for path in bag_paths(inputs)? {
        for item in BagReader::open(&path)?.frames_on(topic) {
            let frame = match item {
                Ok(m) => m.frame,
                Err(BagError::Truncated { truncation, .. }) => {
                    out.truncated.push((path.clone(), truncation));
                    break;
                }
                Err(err) => return Err(err.into()),
            };
            read += 1;
            let scene = out
                .scenes
                .entry(frame.scene.clone())
                .or_insert_with(|| ScenePredictions {
                    material: frame.material.clone(),
                    ..ScenePredictions::default()
                });
            if frame.material != scene.material {
                return Err(EvalError::Mismatch {
                    scene: frame.scene,
                    frame: frame.frame_index,
                    what: format!(
                        "{}: particle count or materials differ from the scene's first predicted frame",
                        path.display()
                    ),
                });
            }
            if scene.frames.contains_key(&frame.frame_index) {
                scene.duplicates += 1;
                continue;
            }
            let state = frame
                .position
                .chunks_exact(2)
                .zip(frame.velocity.chunks_exact(2))
                .flat_map(|(p, v)| [p[0], p[1], v[0], v[1]])
                .collect();
            scene.frames.insert(frame.frame_index, state);
        }
    }
    if read == 0 {
        return Err(EvalError::Empty(format!(
            "no predicted frames{} in {inputs:?}",
            topic.map_or(String::new(), |t| format!(" on topic {t}"))
        )));
    }
    Ok(out)
}

/// Settings of [`score_predictions`].
#[derive(Debug, Clone)]
pub struct ReplayOptions {
    /// Steps scored per scene, H.
    pub horizon: usize,
    /// Baselines predict one step from the truth (for one-step prediction bags) instead of
    /// rolling out from truth frame `first - 1`.
    pub one_step: bool,
    /// Density-map grid G (0: skip).
    pub density_grid: usize,
    /// Keep frames for the renders.
    pub snapshots: bool,
}

/// The ground truth of one scene, frame by frame.
struct Truth<'a> {
    segments: Vec<&'a Trajectory>,
}

impl<'a> Truth<'a> {
    /// The segment holding `frame_index` and the frame's offset in it.
    fn find(&self, index: i64) -> Option<(&'a Trajectory, usize)> {
        self.segments.iter().find_map(|t| {
            let off = index - i64::from(t.start_index);
            (off >= 0 && (off as usize) < t.frames).then_some((*t, off as usize))
        })
    }

    /// The truth state `[N, 4]` of frame `index`, where there is one.
    fn state(&self, index: i64) -> Option<&'a [f32]> {
        self.find(index).map(|(t, off)| t.state(off))
    }
}

/// Scores `preds` (the column `name`) and the `baselines` against `truth` (see the module
/// doc). Scenes without ground truth are noted and skipped; a scene whose particle count or
/// materials differ from its truth is an error.
pub fn score_predictions(
    preds: &Predictions,
    name: &str,
    truth: &[Trajectory],
    baselines: &[&dyn Predictor],
    scaler: &Scaler,
    scaler_source: &str,
    opts: &ReplayOptions,
) -> Result<Evaluation, EvalError> {
    let h = opts.horizon.max(1);
    let by_scene = truth_by_scene(truth);
    let mut notes = Vec::new();
    let mut scenes = Vec::new();
    for (scene, sp) in &preds.scenes {
        let Some(tr) = by_scene.get(scene.as_str()) else {
            notes.push(format!(
                "scene {scene:?}: {} predicted frames but no ground truth; skipped",
                sp.frames.len()
            ));
            continue;
        };
        let Some(&first) = sp.frames.keys().next() else {
            continue;
        };
        let result = score_scene(scene, sp, first, tr, baselines, scaler, opts)?;
        notes.extend(scene_notes(scene, sp, &result, h));
        scenes.push(result);
    }
    for (path, t) in &preds.truncated {
        notes.push(format!("{}: truncated: {t}", path.display()));
    }
    if scenes.is_empty() {
        return Err(EvalError::Empty(
            "no predicted scene has ground truth".into(),
        ));
    }
    let mut predictors = vec![name.to_owned()];
    predictors.extend(baselines.iter().map(|b| b.name().to_owned()));
    Ok(Evaluation {
        predictors,
        horizon: h,
        full: false,
        scaler: *scaler,
        scaler_source: scaler_source.to_owned(),
        scenes,
        notes,
        corrections: Vec::new(),
    })
}

/// The ground-truth segments grouped by scene id.
fn truth_by_scene(truth: &[Trajectory]) -> BTreeMap<&str, Truth<'_>> {
    let mut by_scene: BTreeMap<&str, Truth> = BTreeMap::new();
    for t in truth {
        by_scene
            .entry(t.scene.as_str())
            .or_insert_with(|| Truth {
                segments: Vec::new(),
            })
            .segments
            .push(t);
    }
    by_scene
}

/// Scores steps 1..=H of one scene whose first predicted frame is `first`: the predictions
/// (column 0) and each baseline against the truth `tr`. Counts missing, unmatched and
/// beyond-horizon frames; keeps the frames for renders when `opts.snapshots`.
fn score_scene(
    scene: &str,
    sp: &ScenePredictions,
    first: u32,
    tr: &Truth,
    baselines: &[&dyn Predictor],
    scaler: &Scaler,
    opts: &ReplayOptions,
) -> Result<SceneResult, EvalError> {
    let h = opts.horizon.max(1);
    let columns = 1 + baselines.len();
    let material = &tr.segments[0].material;
    if *material != sp.material {
        return Err(EvalError::Mismatch {
            scene: scene.to_owned(),
            frame: first,
            what: format!(
                "predicted frames have {} particles / materials unlike the truth's {}",
                sp.material.len(),
                material.len()
            ),
        });
    }
    let first = i64::from(first);
    let mut result = SceneResult {
        scene: scene.to_owned(),
        rollouts: 1,
        missing: vec![0; columns],
        ..SceneResult::default()
    };
    let mut sums = vec![StepSums::new(h); columns];
    // Baseline predictions per step (None where they cannot be seeded).
    let base: Vec<Vec<Option<Vec<f32>>>> = baselines
        .iter()
        .map(|b| baseline_steps(*b, tr, first, h, opts.one_step))
        .collect::<Result<_, _>>()?;
    let mut snap = Snapshots {
        material: material.clone(),
        truth: vec![tr.state(first - 1).map(<[f32]>::to_vec)],
        preds: vec![vec![tr.state(first - 1).map(<[f32]>::to_vec)]; columns],
    };
    for k in 1..=h {
        let index = first + k as i64 - 1;
        let truth_frame = tr.state(index);
        let pred = sp.frames.get(&(index as u32));
        snap.truth.push(truth_frame.map(<[f32]>::to_vec));
        snap.preds[0].push(pred.cloned());
        for (b, steps) in base.iter().enumerate() {
            snap.preds[b + 1].push(steps[k - 1].clone());
        }
        let Some(truth_frame) = truth_frame else {
            result.unmatched += usize::from(pred.is_some());
            continue;
        };
        let score = |p: &[f32]| frame_metrics(p, truth_frame, material, scaler, opts.density_grid);
        match pred {
            Some(p) => sums[0].steps[k - 1].push(score(p)),
            None => result.missing[0] += 1,
        }
        for (b, steps) in base.iter().enumerate() {
            if let Some(p) = &steps[k - 1] {
                sums[b + 1].steps[k - 1].push(score(p));
            }
        }
    }
    result.beyond = sp.frames.range((first + h as i64) as u32..).count();
    result.curves = sums.iter().map(StepSums::curve).collect();
    result.probes = end_structure(&snap, h);
    result.snapshots = opts.snapshots.then_some(snap);
    Ok(result)
}

/// The structure of each column's frame at step `h` against the truth's there (one
/// [`Probe::End`] per column; [`Plausibility::of`] against the neighbours of the truth's frame
/// before step 1, and the centre-of-mass error of its bodies), with the kinetic energy summed
/// over the steps 1..=h where both frames exist, prediction over truth (no momentum drift:
/// a bag's frames need not be consecutive). Empty for a column without a frame at step `h`, and for
/// every column without the truth's frames at steps 0 and `h`.
fn end_structure(snap: &Snapshots, h: usize) -> Vec<Vec<(Probe, Plausibility)>> {
    let columns = snap.preds.len();
    let (Some(Some(start)), Some(Some(truth))) = (snap.truth.first(), snap.truth.get(h)) else {
        return vec![Vec::new(); columns];
    };
    let material = &snap.material;
    let neighbours = Neighbours::new(start, material);
    let bodies = Bodies::new(start, material);
    let column = |steps: &Vec<Option<Vec<f32>>>| {
        let Some(Some(pred)) = steps.get(h) else {
            return Vec::new();
        };
        let mut value = Plausibility::of(pred, truth, material, &neighbours);
        value.com = bodies.com_error(pred, truth);
        let pairs = steps[1..=h].iter().zip(&snap.truth[1..=h]);
        let both = pairs.filter_map(|(p, t)| Some((p.as_deref()?, t.as_deref()?)));
        let energy = EnergySums::of(both, material);
        (value.energy, value.energy_all) = energy.ratio_at(energy.steps());
        vec![(Probe::End, value)]
    };
    snap.preds.iter().map(column).collect()
}

/// The notes on one scored scene: predicted frames missing, without ground truth, past
/// the horizon `h`, duplicated.
fn scene_notes(scene: &str, sp: &ScenePredictions, result: &SceneResult, h: usize) -> Vec<String> {
    let mut notes = Vec::new();
    if result.missing[0] > 0 {
        notes.push(format!(
            "scene {scene:?}: {} of {h} predicted frames missing (excluded from the scores)",
            result.missing[0]
        ));
    }
    if result.unmatched > 0 {
        notes.push(format!(
            "scene {scene:?}: {} predicted frames have no ground truth (excluded)",
            result.unmatched
        ));
    }
    if result.beyond > 0 {
        notes.push(format!(
            "scene {scene:?}: {} predicted frames past the {h}-step horizon (not scored)",
            result.beyond
        ));
    }
    if sp.duplicates > 0 {
        notes.push(format!(
            "scene {scene:?}: {} duplicate predicted frames dropped",
            sp.duplicates
        ));
    }
    notes
}

/// A baseline's prediction for steps 1..=h of a scene whose first predicted frame is
/// `first`: one rollout seeded with truth frame `first - 1`, or (one-step) each step from the
/// truth frame before it. `None` where the seed frame is absent.
fn baseline_steps(
    b: &dyn Predictor,
    truth: &Truth,
    first: i64,
    h: usize,
    one_step: bool,
) -> Result<Vec<Option<Vec<f32>>>, EvalError> {
    if one_step {
        return (0..h as i64)
            .map(|k| match truth.find(first + k - 1) {
                Some((t, off)) => Ok(b.rollout(t, off + 1, 1)?.pop()),
                None => Ok(None),
            })
            .collect();
    }
    match truth.find(first - 1) {
        Some((t, off)) if off + 1 >= b.window() => {
            Ok(b.rollout(t, off + 1, h)?.into_iter().map(Some).collect())
        }
        _ => Ok(vec![None; h]),
    }
}
