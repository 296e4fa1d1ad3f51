//! The grid trainer's data-parallel step over several devices of one machine
//! (`--device cuda:0,cuda:1,...`), synchronous data-parallel SGD with one persistent
//! replica per device: the main thread trains the main device's model, and one worker
//! thread per further device ([`Replicas`]) holds a replica of the model and of the
//! optimizer, started from the main ones for each stretch of an epoch (`pass.rs`) and kept
//! for its steps. A batch is cut into one share of consecutive windows per device
//! ([`crate::data::Batch::shards`], its windows' mirroring drawn before the cut, so a share
//! mirrors as the whole batch would); per chunk of the rollout every rank runs its share's
//! forward and backward, its loss weighted by its share of the batch (`b_k / B`), sums the
//! gradients over the ranks ([`ReduceGroup`]: NCCL's all-reduce on CUDA) and takes the same
//! Adam step. The sum of the weighted gradients is the batch-mean gradient: the global
//! batch, learning rate and schedule are a one-device run's, and so are the weights, up to
//! float summation order, where no term depends on the batch as a whole (the input noise,
//! drawn per device, and the structure terms, normalised per share, do). Equal gradients
//! and a deterministic Adam keep the replicas equal without a broadcast (PyTorch's
//! `DistributedDataParallel` works the same way); the next stretch starts them from the
//! main model again.
//!
//! Nothing crosses devices but the all-reduce: no fork of the model and no gradient
//! transfer per step (burn's `step_multi`, which this replaced, did both, each a round trip
//! that held the step: 1.3x on 2 GPUs and 1.3x on 4, docs/training.md).

use std::thread::Scope;

use burn::tensor::backend::AutodiffBackend;
use burn::tensor::StreamId;

use super::batch::HostBatch;
use super::{GridOptim, GridTrainer};
use crate::model::grid::GridModel;
use crate::ops::NetOps;
use crate::train::reduce::ReduceGroup;
use crate::train::workers::Workers;

/// One step's share for a worker: its windows, the learning rate, the run's step and the
/// batch's size.
pub(super) struct Job {
    host: HostBatch,
    lr: f64,
    step: u64,
    total: usize,
}

/// The worker threads of a data-parallel stretch, one per device after the main one
/// (`train/workers.rs`).
pub(super) type Replicas<B> = Workers<Job, B>;

/// A share's rank, the batch's size and the group, as a step sums its gradients.
pub(super) type Reduce<'g, B> = (
    usize,
    usize,
    &'g ReduceGroup<<B as AutodiffBackend>::InnerBackend>,
);

impl<B: AutodiffBackend + NetOps> GridTrainer<B>
where
    B::InnerBackend: NetOps,
{
    /// Starts one worker per device after the main one in `scope`, each on its stream of
    /// `streams`, with a replica of `model` and of `optim` on its device.
    pub(super) fn replicas<'scope>(
        &'scope self,
        scope: &'scope Scope<'scope, '_>,
        model: &GridModel<B>,
        optim: &GridOptim<B>,
        streams: &[StreamId],
    ) -> Replicas<B> {
        let group = ReduceGroup::new(self.devices());
        let step = move |model: GridModel<B>,
                         optim: &mut GridOptim<B>,
                         job: Job,
                         rank: usize,
                         group: &ReduceGroup<B::InnerBackend>| {
            let reduce = Some((rank, job.total, group));
            let (model, value, _) = self.step(model, optim, job.host, (job.lr, job.step), reduce);
            (model, value)
        };
        Workers::start(
            scope,
            group,
            streams,
            (model, optim),
            || self.optimizer(),
            step,
        )
    }

    /// One batch's optimizer steps with its `shares` (one per device, in the order of
    /// [`GridTrainer::devices`]) at learning rate `lr`: the main device's share here, the
    /// others on their workers, all at once. Returns the model, the batch's loss (the sum
    /// of the shares' weighted losses) and 0 s of waiting (each rank reads its loss back).
    pub(super) fn parallel_step(
        &self,
        model: GridModel<B>,
        optim: &mut GridOptim<B>,
        shares: Vec<HostBatch>,
        (lr, step): (f64, u64),
        replicas: &Replicas<B>,
    ) -> (GridModel<B>, f64, f64) {
        let total: usize = shares.iter().map(HostBatch::b).sum();
        let mut shares = shares.into_iter();
        let own = shares.next().expect("a share per device");
        replicas.send(shares.map(|host| Job {
            host,
            lr,
            step,
            total,
        }));
        let (model, mut value, _) =
            replicas.own(|group| self.step(model, optim, own, (lr, step), Some((0, total, group))));
        value += replicas.sum();
        (model, value, 0.0)
    }
}
