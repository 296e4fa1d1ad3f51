//! Direct evaluation (docs/design.md, "Metrics"): every predictor rolled out autoregressively from
//! ground-truth seed frames of each trajectory, and each predicted frame scored against the
//! truth.
//!
//! Input: trajectories (usually the test split), predictors, the [`Scaler`] and
//! [`RolloutOptions`]. A rollout starts at offset `s` of a trajectory: its seed is frames
//! `s..s + W` (W = the largest window of the predictors, so all of them predict the same
//! frames; a predictor with a smaller T reads the last T of them) and it predicts frames
//! `s + W .. s + W + H`, step `k` being frame `s + W + k - 1`. With `starts = 1` there is
//! one rollout per trajectory, from its first frame (the paper's protocol); with K starts,
//! K offsets evenly spaced over `0 ..= F - W - H` ([`start_offsets`]). A trajectory shorter
//! than `W + H` frames is rolled out as far as it goes (noted); a scene split into segments
//! at a gap gets the rollouts of every segment. Output: one [`Evaluation`], per scene the
//! per-step metrics averaged over its rollouts. Used by `minflow eval --data` and `report`.

use std::collections::BTreeMap;

use rayon::prelude::*;

use super::conservation::{Bodies, MomentumDrift};
use super::front::{Fronts, Towards};
use super::plausibility::{probe_steps, EnergySums, Neighbours, Plausibility};
use super::{
    frame_metrics, EvalError, Evaluation, Predictor, Probe, SceneResult, Snapshots, StepSums,
};
use crate::data::{Scaler, Trajectory};

/// Settings of [`evaluate`].
#[derive(Debug, Clone)]
pub struct RolloutOptions {
    /// Steps predicted per rollout, H (the paper: 20).
    pub horizon: usize,
    /// Start frames per trajectory (1: from the first frame only).
    pub starts: usize,
    /// Seed frames W before the first prediction, at least every predictor's window (the
    /// largest is used when this is smaller).
    pub window: usize,
    /// Density-map grid G for the density error (0: skip).
    pub density_grid: usize,
    /// Keep the first rollout's frames of each scene for the renders.
    pub snapshots: bool,
    /// Roll out from the seed frames to each trajectory's end (`--horizon full`): one
    /// rollout per trajectory from its first frame; `horizon` and `starts` are not used.
    pub full: bool,
    /// Score plausibility ([`super::plausibility`]) at the [`probe_steps`].
    pub plausibility: bool,
    /// Write each rollout's predicted frames as an MCAP bag under this folder
    /// ([`super::save_pred`], `eval --save-pred DIR`).
    pub save_pred: Option<std::path::PathBuf>,
}

impl Default for RolloutOptions {
    fn default() -> Self {
        Self {
            horizon: 20,
            starts: 1,
            window: 2,
            density_grid: 32,
            snapshots: true,
            full: false,
            plausibility: true,
            save_pred: None,
        }
    }
}

/// The start offsets of `starts` rollouts over a trajectory of `frames` frames with `window`
/// seed frames and `horizon` steps: evenly spaced over `0 ..= frames - window - horizon`,
/// rounded, duplicates removed; `[0]` when the trajectory is too short for more than one
/// full rollout, empty when it has no frame to predict.
pub fn start_offsets(frames: usize, window: usize, horizon: usize, starts: usize) -> Vec<usize> {
    if frames <= window {
        return Vec::new();
    }
    let last = frames.saturating_sub(window + horizon);
    if starts <= 1 || last == 0 {
        return vec![0];
    }
    let mut out: Vec<usize> = (0..starts)
        .map(|i| ((i as f64) * last as f64 / (starts - 1) as f64).round() as usize)
        .collect();
    out.dedup();
    out
}

/// Rolls out every predictor on every trajectory and scores each step (see the module doc).
/// `progress` is advanced by one per (rollout, predictor). Errors when a model refuses a
/// trajectory or when no trajectory has a frame to predict.
pub fn evaluate(
    trajs: &[Trajectory],
    predictors: &[&dyn Predictor],
    scaler: &Scaler,
    scaler_source: &str,
    opts: &RolloutOptions,
    progress: &indicatif::ProgressBar,
) -> Result<Evaluation, EvalError> {
    let w = predictors
        .iter()
        .map(|p| p.window())
        .chain([opts.window, 1])
        .max()
        .unwrap_or(1);
    let h = match opts.full {
        true => trajs
            .iter()
            .map(|t| t.frames.saturating_sub(w))
            .max()
            .unwrap_or(0),
        false => opts.horizon,
    }
    .max(1);
    let (plan, notes) = plan(trajs, w, h, opts);
    if plan.is_empty() {
        return Err(EvalError::Empty(format!(
            "no trajectory has more than {w} frames"
        )));
    }
    progress.set_length((plan.len() * predictors.len()) as u64);
    let mut scenes: BTreeMap<String, SceneSums> = BTreeMap::new();
    for rollout in plan {
        let sums = scenes
            .entry(rollout.traj.scene.clone())
            .or_insert_with(|| SceneSums::new(&rollout.traj.scene, predictors.len(), h));
        sums.add(&rollout, predictors, (scaler, opts, w, h), progress)?;
    }
    Ok(Evaluation {
        predictors: predictors.iter().map(|p| p.name().to_owned()).collect(),
        horizon: h,
        full: opts.full,
        scaler: *scaler,
        scaler_source: scaler_source.to_owned(),
        scenes: scenes.into_values().map(|s| s.finish(opts.full)).collect(),
        notes,
        corrections: predictors.iter().map(|p| p.corrections()).collect(),
    })
}

/// One rollout to make: trajectory, start offset, steps.
struct Rollout<'a> {
    traj: &'a Trajectory,
    start: usize,
    steps: usize,
}

/// The rollouts of every trajectory with `w` seed frames and `h` steps (one from the start
/// with `opts.full`, else `opts.starts` of them), and notes on the trajectories that are
/// skipped or cut short.
fn plan<'a>(
    trajs: &'a [Trajectory],
    w: usize,
    h: usize,
    opts: &RolloutOptions,
) -> (Vec<Rollout<'a>>, Vec<String>) {
    let mut notes = Vec::new();
    let mut plan = Vec::new();
    for traj in trajs {
        let span = |t: &Trajectory| {
            format!(
                "scene {:?} (frames {}..{})",
                t.scene,
                t.start_index,
                t.start_index as usize + t.frames
            )
        };
        let starts = if opts.full { 1 } else { opts.starts };
        let offsets = start_offsets(traj.frames, w, h, starts);
        if offsets.is_empty() {
            notes.push(format!(
                "{}: {} frames, too short for {w} seed frames; skipped",
                span(traj),
                traj.frames
            ));
            continue;
        }
        let steps = h.min(traj.frames - w);
        if steps < h && !opts.full {
            notes.push(format!(
                "{}: only {steps} of {h} steps after {w} seed frames",
                span(traj)
            ));
        }
        plan.extend(
            offsets
                .into_iter()
                .map(|start| Rollout { traj, start, steps }),
        );
    }
    (plan, notes)
}

/// What the rollouts of one scene added up to so far, per predictor.
struct SceneSums {
    result: SceneResult,
    steps: Vec<StepSums>,
    probes: Vec<ProbeSums>,
}

impl SceneSums {
    fn new(scene: &str, predictors: usize, h: usize) -> Self {
        Self {
            result: SceneResult {
                scene: scene.to_owned(),
                missing: vec![0; predictors],
                ..SceneResult::default()
            },
            steps: vec![StepSums::new(h); predictors],
            probes: vec![ProbeSums::default(); predictors],
        }
    }

    /// Rolls every predictor out once from `w` seed frames and scores it; the scene's first
    /// rollout is kept for the renders when `opts.snapshots`.
    fn add(
        &mut self,
        rollout: &Rollout<'_>,
        predictors: &[&dyn Predictor],
        (scaler, opts, w, h): (&Scaler, &RolloutOptions, usize, usize),
        progress: &indicatif::ProgressBar,
    ) -> Result<(), EvalError> {
        let (traj, steps) = (rollout.traj, rollout.steps);
        let first = rollout.start + w;
        let reference = opts
            .plausibility
            .then(|| Reference::new(traj, first, steps));
        self.result.rollouts += 1;
        let keep = opts.snapshots && self.result.snapshots.is_none();
        let mut snap = keep.then(|| Snapshots {
            material: traj.material.clone(),
            truth: (0..=h)
                .map(|k| (k <= steps).then(|| traj.state(first + k - 1).to_vec()))
                .collect(),
            preds: Vec::new(),
        });
        // The liquid's surge front, on the scene's first rollout.
        let start = traj.state(first - 1);
        let towards = (self.result.rollouts == 1)
            .then(|| Towards::far_wall(start, &traj.material))
            .flatten();
        let mut fronts = Vec::new();
        for (p, predictor) in predictors.iter().enumerate() {
            let frames = predictor.rollout(traj, first, steps)?;
            if let Some(dir) = &opts.save_pred {
                super::save_pred::write_rollout(dir, predictor.name(), traj, first, &frames)?;
            }
            for (k, pred) in frames.iter().enumerate().take(steps) {
                check_len(traj, first + k, pred.len(), predictor.name())?;
                let truth = traj.state(first + k);
                let m = frame_metrics(pred, truth, &traj.material, scaler, opts.density_grid);
                self.steps[p].steps[k].push(m);
            }
            if let Some(reference) = &reference {
                self.probes[p].add(traj, first, &frames, steps, reference);
            }
            if let Some(t) = towards {
                let rolled = frames.iter().take(steps).map(Vec::as_slice);
                fronts.push(t.series(start, rolled, &traj.material));
            }
            if let Some(snap) = snap.as_mut() {
                let mut row = vec![Some(traj.state(first - 1).to_vec())];
                row.extend(frames.into_iter().map(Some));
                row.resize(h + 1, None);
                snap.preds.push(row);
            }
            progress.inc(1);
        }
        if snap.is_some() {
            self.result.snapshots = snap;
        }
        if let Some(t) = towards {
            let truth = (first..first + steps).map(|k| traj.state(k));
            self.result.fronts = Some(Fronts {
                scene: traj.scene.clone(),
                towards: t,
                truth: t.series(start, truth, &traj.material),
                preds: fronts,
            });
        }
        Ok(())
    }

    /// The scene's result: per predictor its curve (ending at the scene's own last frame
    /// when `full`) and its mean plausibility per probe.
    fn finish(self, full: bool) -> SceneResult {
        let mut result = self.result;
        result.curves = self.steps.iter().map(StepSums::curve).collect();
        if full {
            for curve in &mut result.curves {
                while curve.steps.len() > 1 && curve.steps.last() == Some(&None) {
                    curve.steps.pop();
                }
            }
        }
        result.probes = self.probes.iter().map(ProbeSums::means).collect();
        result
    }
}

/// A predicted frame must have the trajectory's `[N, 4]` shape.
fn check_len(traj: &Trajectory, offset: usize, len: usize, who: &str) -> Result<(), EvalError> {
    if len == traj.n * 4 {
        return Ok(());
    }
    Err(EvalError::Mismatch {
        scene: traj.scene.clone(),
        frame: traj.frame_index(offset),
        what: format!(
            "{who} predicted {len} values, the truth has {} particles x 4",
            traj.n
        ),
    })
}

/// What every predictor's rollout from one start is scored against, made once per start:
/// the neighbours and bodies of the rollout's first frame and the truth's momentum drift.
struct Reference {
    neighbours: Neighbours,
    bodies: Bodies,
    drift_truth: MomentumDrift,
}

impl Reference {
    /// The reference of a rollout of `steps` steps whose step k is trajectory frame
    /// `first + k - 1`.
    fn new(traj: &Trajectory, first: usize, steps: usize) -> Self {
        let start = traj.state(first - 1);
        Self {
            neighbours: Neighbours::new(start, &traj.material),
            bodies: Bodies::new(start, &traj.material),
            drift_truth: MomentumDrift::of(|k| traj.state(first + k - 1), steps, traj.dt),
        }
    }
}

/// The plausibility of one predictor's rollouts of one scene, by probe.
#[derive(Debug, Clone, Default)]
struct ProbeSums {
    /// Per probe label (`"20"`, `"100"`, ..., `"end"`): the rollouts' plausibility there.
    by_probe: BTreeMap<Probe, Vec<Plausibility>>,
}

impl ProbeSums {
    /// Scores `frames` (a rollout of `steps` steps whose step k is trajectory frame
    /// `first + k - 1`) at its [`probe_steps`], the last as [`Probe::End`], against the
    /// neighbours and bodies of the rollout's first frame; the probes run in parallel.
    fn add(
        &mut self,
        traj: &Trajectory,
        first: usize,
        frames: &[Vec<f32>],
        steps: usize,
        reference: &Reference,
    ) {
        let steps = steps.min(frames.len());
        let pairs = (1..=steps).map(|k| (frames[k - 1].as_slice(), traj.state(first + k - 1)));
        let energy = EnergySums::of(pairs, &traj.material);
        let seed = traj.state(first - 1);
        let drift = MomentumDrift::of(
            |k| if k == 0 { seed } else { &frames[k - 1] },
            steps,
            traj.dt,
        );
        let scored: Vec<(usize, Plausibility)> = probe_steps(steps)
            .into_par_iter()
            .map(|k| {
                let truth = traj.state(first + k - 1);
                let nb = &reference.neighbours;
                let mut value = Plausibility::of(&frames[k - 1], truth, &traj.material, nb);
                (value.energy, value.energy_all) = energy.ratio_at(k);
                value.com = reference.bodies.com_error(&frames[k - 1], truth);
                value.momentum = drift.mean_to(k);
                value.momentum_truth = reference.drift_truth.mean_to(k);
                (k, value)
            })
            .collect();
        for (k, value) in scored {
            let label = if k == steps {
                Probe::End
            } else {
                Probe::Step(k)
            };
            self.by_probe.entry(label).or_default().push(value);
            if k == steps && k <= 200 {
                // The horizon's own step is a probe too (f20, f100, f200 alike).
                self.by_probe.entry(Probe::Step(k)).or_default().push(value);
            }
        }
    }

    /// The mean plausibility at each probe.
    fn means(&self) -> Vec<(Probe, Plausibility)> {
        self.by_probe
            .iter()
            .filter_map(|(&probe, all)| Plausibility::mean(all).map(|m| (probe, m)))
            .collect()
    }
}
