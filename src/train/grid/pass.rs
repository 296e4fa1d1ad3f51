//! A grid run over the shared epoch loop ([`GridRun`], an [`EpochRun`]) and one epoch's pass
//! over its batches.
//!
//! The run's batches are one sequence over all epochs: batch `g` is batch `g mod B` of data
//! pass `g / B` (B the batches of a pass; pass `p` shuffled from (seed, p)), and epoch `e`
//! trains on batches `e E .. (e + 1) E` (E = B, or fewer with `samples_per_epoch`), so short
//! epochs go on through a pass where the one before stopped, and a streamed dataset reads
//! each chunk once a pass. A batch's mirroring ([`Flips`]) and noise (the device's generator,
//! seeded per step) come from `g`: a run resumed at any batch of an epoch trains on what the
//! uninterrupted one did. After each step the call's share ([`CallShare`]) may ask for a
//! mid-epoch checkpoint, or end the call with one.

use std::time::Instant;

use burn::module::AutodiffModule;
use burn::optim::{GradientsParams, Optimizer};
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::ElementConversion;

use super::batch::{HostBatch, Needs};
use super::feed::{BatchFeed, Flips};
use super::parallel::{Reduce, Replicas};
use super::rollout_loss::Rollout;
use super::schedule::RunClock;
use super::{learning_rate, validation_rollout, GridOptim, GridTrainer};
use crate::data::Trajectory;
use crate::model::grid::GridModel;
use crate::model::store::{Net, Surrogate};
use crate::ops::NetOps;
use crate::train::checkpoint::RunOutput;
use crate::train::epochs::{EpochPass, EpochRun, Unfinished};
use crate::train::ledger::{AfterStep, CallShare};
use crate::train::source::BatchSource;
use crate::train::{EpochRecord, Observer, TrainError};

/// A grid run in progress: the trainer, its data, its output, its clock and this call's
/// share, as [`crate::train::run_epochs`] drives it.
pub(super) struct GridRun<'a, B: AutodiffBackend> {
    pub(super) trainer: &'a GridTrainer<B>,
    pub(super) train: &'a mut dyn BatchSource,
    /// Batches of one pass over the training data.
    pub(super) pass_batches: usize,
    pub(super) val: &'a [Trajectory],
    pub(super) output: RunOutput,
    pub(super) clock: RunClock,
    pub(super) share: CallShare,
    /// One stream id per device (`train::stream_ids`; one: a one-device run).
    pub(super) streams: Vec<burn::tensor::StreamId>,
}

/// One stretch of an epoch within one data pass: the pass, the batches of it skipped, the
/// batches taken.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Stretch {
    pass: u64,
    skip: usize,
    take: usize,
}

/// The stretches of run batches `from .. to` over passes of `pass_batches` batches.
fn stretches(from: usize, to: usize, pass_batches: usize) -> Vec<Stretch> {
    let per = pass_batches.max(1);
    let mut out = Vec::new();
    let mut g = from;
    while g < to {
        let (pass, skip) = (g / per, g % per);
        let take = (per - skip).min(to - g);
        out.push(Stretch {
            pass: pass as u64,
            skip,
            take,
        });
        g += take;
    }
    out
}

impl<B: AutodiffBackend + NetOps> GridRun<'_, B>
where
    B::InnerBackend: NetOps,
{
    /// Trains `epoch` from its step `pass.steps` on (module doc): a step of Adam per batch
    /// and chunk ([`Rollout`]) at the batch's decayed learning rate, the observer told after
    /// each batch. Stops early, with `out_of_time` set, once `--max-minutes` have passed
    /// since the run began, and with `stopped` set when the call's share ends mid-epoch.
    ///
    /// # Errors
    /// [`TrainError::NonFinite`] for a NaN or infinite batch loss; [`TrainError::Data`] for a
    /// streamed chunk that could not be read; a mid-epoch checkpoint that failed.
    fn pass(
        &mut self,
        mut model: GridModel<B>,
        optim: &mut GridOptim<B>,
        (epoch, mut pass): (usize, EpochPass),
        history: &[EpochRecord],
        observer: &mut dyn Observer,
    ) -> Result<(GridModel<B>, EpochPass), TrainError> {
        let t = self.trainer;
        let opts = &t.opts;
        let (started, before) = (Instant::now(), pass.seconds);
        let needs = t.needs();
        let first = epoch * self.clock.batches;
        let spans = stretches(
            first + pass.steps,
            first + self.clock.batches,
            self.pass_batches,
        );
        for span in spans {
            let g = first + pass.steps;
            let batches = (self.train)
                .batches_from(
                    opts.batch_size.max(1),
                    Some(opts.seed),
                    span.pass,
                    span.skip,
                )?
                .take(span.take);
            let flips = Flips {
                seed: opts.seed ^ 0x9e37_79b9,
                first: g as u64,
            };
            let (clock, share, output) = (&self.clock, &mut self.share, &self.output);
            let (streams, shares) = (&self.streams, self.streams.len());
            model = std::thread::scope(|scope| {
                let feed = BatchFeed::start(scope, batches, flips, (opts.mirror, shares), needs);
                let replicas = (shares > 1).then(|| t.replicas(scope, &model, optim, streams));
                let mut fetch = Instant::now();
                while let Some(hosts) = feed.next() {
                    let hosts = hosts?;
                    let k = pass.steps;
                    let step = (first + k) as u64;
                    let b = hosts.iter().map(|h| h.b()).sum();
                    pass.data_seconds += fetch.elapsed().as_secs_f64();
                    let lr = learning_rate(opts, clock.progress(opts, epoch, k));
                    let (value, waited);
                    (model, value, waited) =
                        t.batch_step(model, optim, hosts, (lr, step), replicas.as_ref());
                    pass.wait_seconds += waited;
                    pass.add_step(value, b, (epoch, k, clock.batches), started, observer)?;
                    let last = pass.steps >= clock.batches;
                    match share.after_step() {
                        AfterStep::Stop if last => pass.out_of_time = true,
                        AfterStep::Stop => pass.stopped = true,
                        AfterStep::Checkpoint if !last => {
                            let mut now = pass.clone();
                            now.seconds = before + started.elapsed().as_secs_f64();
                            let unfinished = Unfinished { epoch, pass: now };
                            output.checkpoint(&model, optim, history, Some(&unfinished))?;
                        }
                        _ => {}
                    }
                    if clock.out_of_time(opts) {
                        pass.out_of_time = true;
                    }
                    if pass.out_of_time || pass.stopped {
                        break;
                    }
                    fetch = Instant::now();
                }
                Ok::<_, TrainError>(model)
            })?;
            if pass.out_of_time || pass.stopped {
                break;
            }
        }
        Ok((model, pass))
    }
}

impl<B: AutodiffBackend + NetOps> GridTrainer<B>
where
    B::InnerBackend: NetOps,
{
    /// What a batch's preparation builds for this run: the rest and liquid neighbourhoods
    /// its structure terms need, the one-hot width.
    fn needs(&self) -> Needs {
        let opts = &self.opts;
        Needs {
            rest: self.config.rest_shape || opts.strain_weight > 0.0,
            liquid_at: (opts.volume_weight > 0.0).then_some(self.config.window - 1),
            materials: self.config.materials,
        }
    }

    /// Run step `step`'s optimizer steps on its batch (`hosts`: one share per device) at
    /// learning rate `lr`: [`Self::step`] on one device, [`Self::parallel_step`] with the
    /// `replicas` of several. Returns what they return.
    fn batch_step(
        &self,
        model: GridModel<B>,
        optim: &mut GridOptim<B>,
        mut hosts: Vec<HostBatch>,
        (lr, step): (f64, u64),
        replicas: Option<&Replicas<B>>,
    ) -> (GridModel<B>, f64, f64) {
        match replicas {
            Some(replicas) => self.parallel_step(model, optim, hosts, (lr, step), replicas),
            None => self.step(model, optim, hosts.swap_remove(0), (lr, step), None),
        }
    }

    /// One batch's (or one share's) optimizer steps at learning rate `lr`: its noise seeded
    /// from the run's seed, `step` and the rank, the push-forward calls, then a step of Adam
    /// per chunk of the rollout ([`Rollout`]). With `reduce` (a rank of a data-parallel
    /// group, the batch's size), the chunk's loss is weighted by the share's part of the
    /// batch and its gradients summed over the ranks before the step (`parallel.rs`).
    /// Returns the model, the loss (the mean over the chunks) and the seconds spent waiting
    /// for the device.
    pub(super) fn step(
        &self,
        mut model: GridModel<B>,
        optim: &mut GridOptim<B>,
        host: HostBatch,
        (lr, step): (f64, u64),
        reduce: Option<Reduce<'_, B>>,
    ) -> (GridModel<B>, f64, f64) {
        let rank = reduce.map_or(0, |(rank, _, _)| rank);
        let device = reduce.map_or(&self.device, |(rank, _, group)| group.device(rank));
        let seed = (self.opts.seed.wrapping_mul(1_000_003))
            .wrapping_add(step)
            .wrapping_add((rank as u64) << 32);
        B::seed(device, seed);
        let chunks = self.opts.chunks();
        // The share's weight counts its windows as the batch does (0 for a padding share).
        let counted = host.b();
        let mut rollout = Rollout::new(&self.config, &self.opts, host.upload::<B>(device));
        rollout.pushforward(&model);
        let (mut value, mut wait) = (0.0, 0.0);
        for chunk in 0..chunks {
            if chunk > 0 {
                rollout.detach();
            }
            let mut loss = rollout.chunk_loss(&model);
            if let Some((_, total, _)) = reduce {
                loss = loss.mul_scalar(counted as f32 / total.max(1) as f32);
            }
            let mut grads = GradientsParams::from_grads(loss.backward(), &model);
            if let Some((rank, _, group)) = reduce {
                grads = group.sum_grads(rank, &model, grads);
            }
            model = optim.step(lr, model, grads);
            let waited = Instant::now();
            value += loss.into_scalar().elem::<f64>() / chunks as f64;
            wait += waited.elapsed().as_secs_f64();
        }
        (model, value, wait)
    }
}

impl<B: AutodiffBackend + NetOps> EpochRun for GridRun<'_, B>
where
    B::InnerBackend: NetOps,
{
    type Backend = B;
    type Model = GridModel<B>;
    type Optim = GridOptim<B>;

    fn output(&self) -> &RunOutput {
        &self.output
    }

    fn train_epoch(
        &mut self,
        model: GridModel<B>,
        optim: &mut GridOptim<B>,
        epoch: (usize, EpochPass),
        history: &[EpochRecord],
        observer: &mut dyn Observer,
    ) -> Result<(GridModel<B>, EpochPass), TrainError> {
        self.pass(model, optim, epoch, history, observer)
    }

    /// The mean scaled MSE of validation rollouts ([`validation_rollout`]), times their
    /// structure factor when the run trains with a structure loss.
    fn validate(
        &mut self,
        model: &GridModel<B>,
        epoch: usize,
        train_loss: f64,
    ) -> Result<f64, TrainError> {
        let t = self.trainer;
        if self.val.is_empty() {
            return Ok(train_loss);
        }
        let meta = self.output.meta(epoch, 0.0);
        let surrogate = Surrogate::from_net(Net::Grid(model.valid()), meta, &t.device);
        let (starts, horizon) = (t.opts.val_starts, t.opts.val_horizon);
        let structure = t.opts.strain_weight > 0.0 || t.opts.volume_weight > 0.0;
        Ok(validation_rollout(
            &surrogate,
            self.val,
            &self.output.scaler,
            (starts, horizon),
            structure,
        )?)
    }
}

#[cfg(test)]
mod tests {
    use super::{stretches, Stretch};

    #[test]
    fn epochs_go_on_through_the_passes() {
        let s = |pass, skip, take| Stretch { pass, skip, take };
        // A whole pass per epoch: epoch 2 is pass 2.
        assert_eq!(stretches(20, 30, 10), vec![s(2, 0, 10)]);
        // Epochs of 4 batches over passes of 10: the third spans passes 0 and 1.
        assert_eq!(stretches(8, 12, 10), vec![s(0, 8, 2), s(1, 0, 2)]);
        // Resumed at batch 3 of that epoch.
        assert_eq!(stretches(11, 12, 10), vec![s(1, 1, 1)]);
        assert!(stretches(12, 12, 10).is_empty());
    }
}
