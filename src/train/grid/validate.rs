//! The grid run's validation score: the mean scaled MSE of closed-loop rollouts of the
//! validation scenes (as `eval` scores them, with the training split's min-max scaler), all
//! starts of a scene as one batch, ceil(H / K) network calls each. Used by
//! [`super::GridTrainer`] to pick the kept model.

use crate::data::{Scaler, Trajectory};
use crate::eval::rollout::start_offsets;
use crate::model::store::{self, Surrogate};
use crate::ops::NetOps;

/// Mean scaled MSE of `horizon`-frame rollouts of `surrogate` from `starts` starts of every
/// trajectory (all starts of a scene as one batch).
///
/// # Errors
/// A step failed ([`store::StoreError`]).
pub fn validation_rollout<B: NetOps>(
    surrogate: &Surrogate<B>,
    trajs: &[Trajectory],
    scaler: &Scaler,
    starts: usize,
    horizon: usize,
) -> Result<f64, store::StoreError> {
    let window = surrogate.meta().window();
    let (mut sum, mut count) = (0.0f64, 0usize);
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
        let score = |k: usize, pred: &[f32]| {
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
            }
        };
        surrogate.rollout_batch(Some(&first), &seed, &material, &dt, horizon, score)?;
    }
    Ok(if count == 0 {
        f64::NAN
    } else {
        sum / count as f64
    })
}
