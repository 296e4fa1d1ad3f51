//! The grid run's validation score: the mean scaled MSE of closed-loop rollouts of the
//! validation scenes (as `eval` scores them, with the training split's min-max scaler), all
//! starts of a scene as one batch, ceil(H / K) network calls each; with `structure`, times
//! `1 + strain + |1 - volume|` of the rollouts' last frames (`eval`'s strain error of the
//! solids and volume ratio of the liquid, [`crate::eval::structure`]), so a checkpoint that
//! tears a body or presses the liquid together scores worse than its MSE alone says. Used by
//! [`super::GridTrainer`] to pick the kept model.

use crate::data::{Scaler, Trajectory};
use crate::eval::plausibility::Neighbours;
use crate::eval::rollout::start_offsets;
use crate::eval::structure::covered_area;
use crate::model::store::{self, Surrogate};
use crate::ops::NetOps;

/// Mean scaled MSE of `horizon`-frame rollouts of `surrogate` from `starts` starts of every
/// trajectory (all starts of a scene as one batch); with `structure`, times the structure
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
    let (mut sum, mut count) = (0.0f64, 0usize);
    let mut damage = Damage::default();
    for traj in trajs {
        let offsets = start_offsets(traj.frames, window, horizon, starts);
        let offsets: Vec<usize> = offsets
            .into_iter()
            .filter(|&o| o + window + horizon <= traj.frames)
            .collect();
        if offsets.is_empty() {
            continue;
        }
        let (b, n) = (offsets.len(), traj.n);
        let material: Vec<u8> = (0..b).flat_map(|_| traj.material.iter().copied()).collect();
        let dt = vec![traj.dt; b];
        let first: Vec<f32> = (0..b).flat_map(|_| traj.state(0).iter().copied()).collect();
        let seed: Vec<Vec<f32>> = (0..window)
            .map(|k| {
                offsets
                    .iter()
                    .flat_map(|&o| traj.state(o + k).iter().copied())
                    .collect()
            })
            .collect();
        let score = |k: usize, pred: Vec<f32>| {
            for (row, &o) in offsets.iter().enumerate() {
                let truth = traj.state(o + window + k);
                let pred = &pred[row * n * 4..(row + 1) * n * 4];
                for (p, t) in pred.chunks_exact(4).zip(truth.chunks_exact(4)) {
                    for f in 0..4 {
                        let d = f64::from(scaler.scale(f, p[f])) - f64::from(scaler.scale(f, t[f]));
                        sum += d * d;
                    }
                }
                count += n * 4;
                if structure && k + 1 == horizon {
                    let seed = traj.state(o + window - 1);
                    damage.add(traj, seed, pred, truth);
                }
            }
        };
        surrogate.rollout_batch(Some(&first), &seed, &material, &dt, horizon, score)?;
    }
    Ok(if count == 0 {
        f64::NAN
    } else {
        sum / count as f64 * damage.factor()
    })
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
