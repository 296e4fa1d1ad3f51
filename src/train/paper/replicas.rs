//! The paper trainer's data-parallel steps over several devices of one machine
//! (`--device cuda:0,cuda:1,...`) with one persistent replica per further device, as the grid
//! trainer's (`train/grid/parallel.rs`): the main thread trains the main device's model, and
//! one worker thread per further device ([`Replicas`], `train/workers.rs`) holds a replica of
//! the model and of Adam, started from the main ones by an epoch's first data-parallel step
//! and kept for the epoch's steps. A batch's micro-batches are dealt over the devices
//! ([`super::slices::deal`]); every rank runs its share's forward and backward (its loss
//! scaled by its windows' share of the batch), sums the gradients over the ranks
//! ([`ReduceGroup`]: NCCL's all-reduce on CUDA) and takes the same Adam step, so the replicas
//! stay equal without a broadcast. No model is forked per step (the step before forked the
//! model to every device every step).

use std::thread::Scope;

use burn::optim::Optimizer;
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::{ElementConversion, StreamId, Tensor};

use super::slices::HostSlice;
use super::{Optim, Trainer};
use crate::model::{Model, Scaling};
use crate::ops::NetOps;
use crate::train::optimizer::FusedAdam;
use crate::train::reduce::ReduceGroup;
use crate::train::workers::Workers;

/// One step's share for a worker: its micro-batches and the batch's windows.
pub(super) struct Job {
    slices: Vec<HostSlice>,
    b: usize,
}

/// The worker threads of an epoch's data-parallel steps, one per device after the main one.
pub(super) type Replicas<B> = Workers<Job, B>;

impl<B: AutodiffBackend + NetOps> Trainer<B>
where
    B::InnerBackend: NetOps,
{
    /// Starts one worker per device after the main one in `scope`, each on its stream of
    /// `streams`, with a replica of `model` and of `optim` on its device.
    pub(super) fn replicas<'scope>(
        &'scope self,
        scope: &'scope Scope<'scope, '_>,
        from: (&Model<B>, &Optim<B>),
        scaling: &'scope Scaling,
        streams: &[StreamId],
    ) -> Replicas<B> {
        let group = ReduceGroup::new(self.devices.clone());
        let fresh = || FusedAdam::default().init::<B, Model<B>>();
        let step = move |model: Model<B>,
                         optim: &mut Optim<B>,
                         job: Job,
                         rank: usize,
                         group: &ReduceGroup<B::InnerBackend>| {
            let device = group.device(rank);
            let (grads, loss) = self.shard_step(&model, job.slices, job.b, scaling, device);
            let grads = group.sum_grads(rank, &model, grads);
            (optim.step(self.opts.lr, model, grads), loss_value(loss))
        };
        Workers::start(scope, group, streams, from, fresh, step)
    }

    /// One data-parallel optimizer step of a batch of `b` windows dealt into `shards` (one
    /// per device, in the order of the trainer's devices): the main device's share here, the
    /// others on their workers, all at once. Returns the model, the main device's summed
    /// loss (not read back) and the workers' summed losses (read back).
    pub(super) fn parallel_step(
        &self,
        (model, optim): (Model<B>, &mut Optim<B>),
        shards: Vec<Vec<HostSlice>>,
        (b, scaling): (usize, &Scaling),
        replicas: &Replicas<B>,
    ) -> (Model<B>, Option<Tensor<B::InnerBackend, 1>>, f64) {
        let mut shards = shards.into_iter();
        let own = shards.next().expect("a share per device");
        replicas.send(shards.map(|slices| Job { slices, b }));
        let (model, loss) = replicas.own(|group| {
            let (grads, loss) = self.shard_step(&model, own, b, scaling, self.main());
            let grads = group.sum_grads(0, &model, grads);
            (optim.step(self.opts.lr, model, grads), loss)
        });
        (model, loss, replicas.sum())
    }
}

/// A device's summed loss of one step, read back (0 for a share without windows).
pub(super) fn loss_value<B: burn::tensor::backend::Backend>(loss: Option<Tensor<B, 1>>) -> f64 {
    loss.map_or(0.0, |l| l.into_scalar().elem::<f64>())
}
