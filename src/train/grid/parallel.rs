//! The grid trainer's data-parallel step over several devices of one machine
//! (`--device cuda:0,cuda:1,...`), burn's multi-device strategy as the paper's trainer uses
//! it (`burn-train`'s `MultiDevice` with `OptimSharded`): a batch is cut into one share of
//! consecutive windows per device ([`crate::data::Batch::shards`], its windows' mirroring
//! drawn before the cut, so a share mirrors as the whole batch would); per chunk of the
//! rollout every device runs its share's forward and backward on a fork of the model, its
//! loss weighted by its share of the batch (`b_d / B`), and
//! [`Optimizer::step_multi`](burn::optim::Optimizer::step_multi) sums each parameter's
//! gradients on one device (chosen by parameter id, so the optimizer state is sharded over
//! the devices) and updates it there. The sum of the weighted gradients is the batch-mean
//! gradient: the global batch, learning rate and schedule are a one-device run's, and so are
//! the weights, up to float summation order, where no term depends on the batch as a whole
//! (the input noise, drawn per device, and the structure terms, normalised per share, do).

use burn::module::Module;
use burn::optim::{GradientsParams, MultiGradientsParams, Optimizer};
use burn::tensor::backend::{AutodiffBackend, DeviceOps};
use burn::tensor::{ElementConversion, StreamId};

use super::batch::HostBatch;
use super::rollout_loss::Rollout;
use super::{GridOptim, GridTrainer};
use crate::model::grid::GridModel;
use crate::ops::NetOps;

/// What one device did in a chunk: its rollout (carried into the next chunk; dropped on its
/// own thread after the last), its weighted gradients, its device's id and its weighted
/// loss, read back on its own thread. A device's tensors are used and dropped only on the
/// thread of its stream but for the gradients `step_multi` takes: a rollout dropped on the
/// main thread once panicked burn's fusion layer ("Should have handle for tensor").
type Share<'r, B> = (
    Option<Rollout<'r, B>>,
    GradientsParams,
    burn::tensor::backend::DeviceId,
    f64,
);

impl<B: AutodiffBackend + NetOps> GridTrainer<B>
where
    B::InnerBackend: NetOps,
{
    /// One batch's optimizer steps with its `shares` (one per device, in the order of
    /// [`GridTrainer::devices`]) at learning rate `lr`, on the run's `streams`: per chunk,
    /// each device's forward and backward on a fork of the model, then one `step_multi`.
    /// Returns the model, the batch's loss (the mean over its chunks) and 0 s of waiting
    /// (each device's loss is read back on its own thread, inside the step).
    pub(super) fn parallel_step(
        &self,
        mut model: GridModel<B>,
        optim: &mut GridOptim<B>,
        shares: Vec<HostBatch>,
        (lr, step): (f64, u64),
        streams: &[StreamId],
    ) -> (GridModel<B>, f64, f64) {
        let total: usize = shares.iter().map(HostBatch::b).sum();
        let devices = self.devices();
        let mut hosts: Vec<Option<HostBatch>> = shares.into_iter().map(Some).collect();
        let mut rollouts: Vec<Option<Rollout<'_, B>>> = hosts.iter().map(|_| None).collect();
        let (chunks, mut value) = (self.opts.chunks(), 0.0);
        for chunk in 0..chunks {
            let last = chunk + 1 == chunks;
            let results: Vec<Share<'_, B>> = std::thread::scope(|workers| {
                let handles: Vec<_> = (hosts.iter_mut().zip(rollouts.iter_mut()))
                    .zip(devices.iter().zip(streams).enumerate())
                    .map(|((host, rollout), (k, (device, &stream)))| {
                        let (model, host, rollout) = (&model, host.take(), rollout.take());
                        workers.spawn(move || {
                            stream.executes(|| {
                                let seed = (self.opts.seed.wrapping_mul(1_000_003))
                                    .wrapping_add(step)
                                    .wrapping_add((k as u64) << 32);
                                let share = (host, rollout, last);
                                self.share_chunk(model, share, device, (seed, total))
                            })
                        })
                    })
                    .collect();
                (handles.into_iter())
                    .map(|h| h.join().expect("a data-parallel worker panicked"))
                    .collect()
            });
            let mut multi = MultiGradientsParams::default();
            let mut sum = 0.0;
            for (k, (rollout, grads, id, loss)) in results.into_iter().enumerate() {
                rollouts[k] = rollout;
                multi.grads.push((grads, id));
                sum += loss;
            }
            model = optim.step_multi(lr, model, multi);
            value += sum / chunks as f64;
        }
        (model, value, 0.0)
    }

    /// One device's part of a chunk: the model forked to `device`, its share's rollout
    /// begun (`host`, uploaded, its noise drawn from `seed`, its push-forward calls made)
    /// or carried on (`rollout`, cut from the last chunk's gradient), its chunk loss
    /// weighted by its `b / total` of the batch, differentiated and read back; the rollout
    /// dropped here after the `last` chunk.
    fn share_chunk<'r>(
        &'r self,
        model: &GridModel<B>,
        (host, rollout, last): (Option<HostBatch>, Option<Rollout<'r, B>>, bool),
        device: &B::Device,
        (seed, total): (u64, usize),
    ) -> Share<'r, B> {
        let local = model.clone().fork(device);
        let mut rollout = match (rollout, host) {
            (Some(mut rollout), _) => {
                rollout.detach();
                rollout
            }
            (None, Some(host)) => {
                B::seed(device, seed);
                let mut rollout = Rollout::new(&self.config, &self.opts, host.upload::<B>(device));
                rollout.pushforward(&local);
                rollout
            }
            (None, None) => unreachable!("a share is uploaded in its first chunk"),
        };
        let weight = rollout.windows() as f32 / total.max(1) as f32;
        let loss = rollout.chunk_loss(&local).mul_scalar(weight);
        let grads = GradientsParams::from_grads(loss.backward(), &local);
        let value = loss.into_scalar().elem::<f64>();
        (
            if last { None } else { Some(rollout) },
            grads,
            device.id(),
            value,
        )
    }
}
