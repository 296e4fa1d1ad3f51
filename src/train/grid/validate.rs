//! The grid run's validation score: the mean scaled MSE of closed-loop rollouts of the
//! validation scenes (as `eval` scores them, with the training split's min-max scaler), the
//! rollouts of scenes with one particle count packed into batches, ceil(H / K) network calls
//! each; with `structure`, times `1 + strain + |1 - volume|` of the rollouts' last frames
//! (`eval`'s strain error of the solids and volume ratio of the liquid,
//! [`crate::eval::structure`]), so a checkpoint that tears a body or presses the liquid
//! together scores worse than its MSE alone says. Used by [`super::GridTrainer`] to pick the
//! kept model.

use crate::data::{Scaler, Trajectory};
use crate::eval::plausibility::Neighbours;
use crate::eval::rollout::start_offsets;
use crate::eval::structure::covered_area;
use crate::model::store::{self, Surrogate};
use crate::ops::NetOps;

/// Most particles in one validation call: the rollouts of scenes of one particle count are
/// packed into a call until it holds this many (256 scenes of 2,500 particles, the node's
/// largest batch; 16 of 40,000). A batch a scene made a long run's 200 validation scenes
/// 1,000 network calls of one scene an epoch (K = 4, 20 frames), each bound on a GPU by the
/// host's recording of its kernels, and as many on every GPU count (docs/training.md).
const VAL_PARTICLES: usize = 640_000;

/// Mean scaled MSE of `horizon`-frame rollouts of `surrogate` from `starts` starts of every
/// trajectory, the rollouts of scenes with the same particle count packed into calls of up
/// to [`VAL_PARTICLES`] particles (each row scored against its own scene: the same score as
/// one call a scene, up to float summation order); with `structure`, times the structure
/// factor of the module doc.
///
/// # Errors
/// A step failed ([`store::StoreError`]).
pub fn validation_rollout<B: NetOps>(
    surrogate: &Surrogate<B>,
    trajs: &[Trajectory],
    scaler: &Scaler,
    (starts, horizon): (usize, usize),
    structure: bool,
) -> Result<f64, store::StoreError> {
    let window = surrogate.meta().window();
    let mut score = Score::default();
    for rows in pack(trajs, window, (starts, horizon)) {
        let frames = (window, horizon);
        rollout_rows(surrogate, &rows, frames, (scaler, structure), &mut score)?;
    }
    Ok(score.value())
}

/// One validation rollout: `traj` from its frame `offset` (the first seed frame).
#[derive(Clone, Copy)]
struct Row<'a> {
    traj: &'a Trajectory,
    offset: usize,
}

/// Every trajectory's rollouts ([`start_offsets`], those with `window + horizon` frames to
/// read), in order, packed into calls of one particle count and at most [`VAL_PARTICLES`]
/// particles.
fn pack(
    trajs: &[Trajectory],
    window: usize,
    (starts, horizon): (usize, usize),
) -> Vec<Vec<Row<'_>>> {
    let mut calls: Vec<Vec<Row>> = Vec::new();
    for traj in trajs {
        let cap = (VAL_PARTICLES / traj.n.max(1)).max(1);
        for offset in start_offsets(traj.frames, window, horizon, starts) {
            if offset + window + horizon > traj.frames {
                continue;
            }
            let row = Row { traj, offset };
            match calls
                .iter_mut()
                .find(|c| c[0].traj.n == traj.n && c.len() < cap)
            {
                Some(call) => call.push(row),
                None => calls.push(vec![row]),
            }
        }
    }
    calls
}

/// One call's rollouts (`rows`, all of N particles) of `horizon` frames after `window` seed
/// frames, each predicted frame `[B, N, 4]` scored row by row against its scene.
fn rollout_rows<B: NetOps>(
    surrogate: &Surrogate<B>,
    rows: &[Row],
    (window, horizon): (usize, usize),
    (scaler, structure): (&Scaler, bool),
    score: &mut Score,
) -> Result<(), store::StoreError> {
    let n = rows[0].traj.n;
    let material: Vec<u8> = rows
        .iter()
        .flat_map(|r| r.traj.material.iter().copied())
        .collect();
    let dt: Vec<f32> = rows.iter().map(|r| r.traj.dt).collect();
    let first: Vec<f32> = rows
        .iter()
        .flat_map(|r| r.traj.state(0).iter().copied())
        .collect();
    let seed: Vec<Vec<f32>> = (0..window)
        .map(|k| {
            rows.iter()
                .flat_map(|r| r.traj.state(r.offset + k).iter().copied())
                .collect()
        })
        .collect();
    let each = |k: usize, pred: Vec<f32>| {
        for (row, r) in rows.iter().enumerate() {
            let truth = r.traj.state(r.offset + window + k);
            let pred = &pred[row * n * 4..(row + 1) * n * 4];
            score.add(scaler, pred, truth);
            if structure && k + 1 == horizon {
                let seed = r.traj.state(r.offset + window - 1);
                score.damage.add(r.traj, seed, pred, truth);
            }
        }
    };
    surrogate.rollout_batch(Some(&first), &seed, &material, &dt, horizon, each)
}

/// The running validation score: scaled squared errors, how many, and the structure's.
#[derive(Debug, Default)]
struct Score {
    sum: f64,
    count: usize,
    damage: Damage,
}

impl Score {
    /// Adds one predicted frame `pred` against `truth` (`[N, 4]` each), scaled by `scaler`.
    fn add(&mut self, scaler: &Scaler, pred: &[f32], truth: &[f32]) {
        for (p, t) in pred.chunks_exact(4).zip(truth.chunks_exact(4)) {
            for f in 0..4 {
                let d = f64::from(scaler.scale(f, p[f])) - f64::from(scaler.scale(f, t[f]));
                self.sum += d * d;
            }
        }
        self.count += pred.len();
    }

    /// The mean scaled squared error times the structure factor; NaN with nothing scored.
    fn value(&self) -> f64 {
        if self.count == 0 {
            f64::NAN
        } else {
            self.sum / self.count as f64 * self.damage.factor()
        }
    }
}

/// Sums of the structure errors of the rollouts' last frames.
#[derive(Debug, Default)]
struct Damage {
    strain: Mean,
    volume: Mean,
}

/// A running mean: the sum of what was added and how many.
#[derive(Debug, Default, Clone, Copy)]
struct Mean {
    sum: f64,
    count: usize,
}

impl Mean {
    fn add(&mut self, x: f64) {
        self.sum += x;
        self.count += 1;
    }

    /// The mean, 0 with nothing added.
    fn value(self) -> f64 {
        if self.count == 0 {
            0.0
        } else {
            self.sum / self.count as f64
        }
    }
}

impl Damage {
    /// Adds one rollout's last frame `pred` against `truth` (`[N, 4]` each), its solids'
    /// neighbours taken in the seed frame `seed`.
    fn add(&mut self, traj: &Trajectory, seed: &[f32], pred: &[f32], truth: &[f32]) {
        let solids = traj.material.iter().any(|&m| m != 0);
        if solids {
            let nb = Neighbours::new(seed, &traj.material);
            for m in 1..crate::eval::MATERIALS {
                if let Some(e) = nb.strain_error(pred, truth, m) {
                    self.strain.add(e);
                }
            }
        }
        let liquid = |i: usize| traj.material[i] == 0;
        let true_area = covered_area(truth, liquid);
        if true_area > 0 {
            let ratio = covered_area(pred, liquid) as f64 / true_area as f64;
            self.volume.add((1.0 - ratio).abs());
        }
    }

    /// `1 + mean strain error + mean |1 - volume ratio|` (1 with nothing added).
    fn factor(&self) -> f64 {
        1.0 + self.strain.value() + self.volume.value()
    }
}
