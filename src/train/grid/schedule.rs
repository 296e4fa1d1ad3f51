//! What a grid run fixes before and as it trains: the velocity statistics of the training
//! split that normalise the network ([`fit_stats`], or [`StatsFit`] a chunk at a time), the
//! cosine learning-rate decay ([`learning_rate`]) and the run's clock ([`RunClock`]: progress
//! by steps or by the time limit). Used by [`super::GridTrainer`] and `minflow train`.

use std::time::Instant;

use super::options::GridTrainOptions;
use crate::data::Trajectory;

/// The velocity statistics that normalise a grid model's inputs and outputs (the fields of
/// the same names in [`crate::model::grid::GridConfig`]), per component x, y.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VelocityStats {
    /// The velocities' standard deviation (domain units per time unit).
    pub vel_scale: [f32; 2],
    /// The mean change of the velocity over one frame.
    pub dv_mean: [f32; 2],
    /// The standard deviation of that change.
    pub dv_scale: [f32; 2],
}

impl VelocityStats {
    /// Writes these statistics into `config`.
    pub fn apply(&self, config: &mut crate::model::grid::GridConfig) {
        config.vel_scale = self.vel_scale;
        config.dv_mean = self.dv_mean;
        config.dv_scale = self.dv_scale;
    }
}

/// Velocity and velocity-change statistics of `trajs` (the training split): per component
/// `vel_scale` = the velocities' standard deviation, `dv_mean` and `dv_scale` = the mean
/// and standard deviation of the change over one frame. Used to fill [`crate::model::grid::GridConfig`].
pub fn fit_stats(trajs: &[&Trajectory]) -> VelocityStats {
    let mut fit = StatsFit::default();
    trajs.iter().for_each(|t| fit.add(t));
    fit.finish()
}

/// [`fit_stats`] a trajectory at a time, for a training split read in chunks
/// ([`crate::data::StreamingLoader::for_each_chunk`]): the same sums, so the same result as
/// one call over every trajectory.
#[derive(Debug, Clone, Default)]
pub struct StatsFit {
    /// Per component: count, sum, sum of squares of the velocities.
    v: [[f64; 3]; 2],
    /// The same of the change over one frame.
    dv: [[f64; 3]; 2],
}

impl StatsFit {
    /// Adds every frame of `traj`.
    pub fn add(&mut self, traj: &Trajectory) {
        let (v, dv) = (&mut self.v, &mut self.dv);
        for k in 0..traj.frames {
            let now = traj.state(k);
            let next = (k + 1 < traj.frames).then(|| traj.state(k + 1));
            for (p, row) in now.chunks_exact(4).enumerate() {
                for c in 0..2 {
                    let x = f64::from(row[2 + c]);
                    v[c][0] += 1.0;
                    v[c][1] += x;
                    v[c][2] += x * x;
                    if let Some(next) = next {
                        let d = f64::from(next[4 * p + 2 + c]) - x;
                        dv[c][0] += 1.0;
                        dv[c][1] += d;
                        dv[c][2] += d * d;
                    }
                }
            }
        }
    }

    /// The statistics of what was added.
    pub fn finish(&self) -> VelocityStats {
        let mean = |s: [f64; 3]| if s[0] > 0.0 { s[1] / s[0] } else { 0.0 };
        let std = |s: [f64; 3]| {
            let m = mean(s);
            let var = if s[0] > 0.0 { s[2] / s[0] - m * m } else { 1.0 };
            (var.max(0.0).sqrt() as f32).max(1e-6)
        };
        let (v, dv) = (self.v, self.dv);
        VelocityStats {
            vel_scale: [std(v[0]), std(v[1])],
            dv_mean: [mean(dv[0]) as f32, mean(dv[1]) as f32],
            dv_scale: [std(dv[0]), std(dv[1])],
        }
    }
}

/// The learning rate at `progress` (0 to 1) through the run: cosine from `lr` to `lr_final`
/// (Loshchilov and Hutter 2017, "SGDR", eq. 5, one cycle).
pub fn learning_rate(opts: &GridTrainOptions, progress: f64) -> f64 {
    let progress = progress.clamp(0.0, 1.0);
    opts.lr_final
        + 0.5 * (opts.lr - opts.lr_final) * (1.0 + (std::f64::consts::PI * progress).cos())
}

/// Where a run is in its schedule.
pub(super) struct RunClock {
    pub(super) started: Instant,
    /// Batches per epoch, and over all epochs.
    pub(super) batches: usize,
    pub(super) total_steps: usize,
}

impl RunClock {
    /// Progress through the run (0 to 1) at batch `k` of `epoch`: by steps, or by time when
    /// a time limit ends the run first (the decay then finishes at the limit).
    pub(super) fn progress(&self, opts: &GridTrainOptions, epoch: usize, k: usize) -> f64 {
        let steps = (epoch * self.batches + k) as f64 / self.total_steps.max(1) as f64;
        if opts.max_minutes > 0.0 {
            steps.max(self.started.elapsed().as_secs_f64() / (opts.max_minutes * 60.0))
        } else {
            steps
        }
    }

    /// Whether `--max-minutes` have passed since the run began.
    pub(super) fn out_of_time(&self, opts: &GridTrainOptions) -> bool {
        opts.max_minutes > 0.0 && self.started.elapsed().as_secs_f64() > opts.max_minutes * 60.0
    }
}
