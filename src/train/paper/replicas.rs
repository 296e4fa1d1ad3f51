//! The paper trainer's data-parallel steps over several devices of one machine
//! (`--device cuda:0,cuda:1,...`) with one persistent replica per further device, as the grid
//! trainer's (`train/grid/parallel.rs`): the main thread trains the main device's model, and
//! one worker thread per further device ([`Replicas`]) holds a replica of the model and of
//! Adam, started from the main ones when an epoch's first data-parallel step needs them and
//! kept for the epoch's steps. A batch's micro-batches are dealt over the devices
//! ([`super::slices::deal`]); every rank runs its share's forward and backward (its loss
//! scaled by its windows' share of the batch), sums the gradients over the ranks
//! ([`ReduceGroup`]: NCCL's all-reduce on CUDA) and takes the same Adam step, so the replicas
//! stay equal without a broadcast. No model is forked per step (the step before forked the
//! model to every device every step).

use std::sync::mpsc::{channel, Receiver, Sender};
use std::sync::Arc;
use std::thread::Scope;

use burn::module::Module;
use burn::optim::Optimizer;
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::{ElementConversion, StreamId, Tensor};

use super::slices::HostSlice;
use super::{Optim, Trainer};
use crate::model::{Model, Scaling};
use crate::ops::NetOps;
use crate::train::optimizer::FusedAdam;
use crate::train::reduce::{FailGuard, ReduceGroup};

/// One step's share for a worker: its micro-batches and the batch's windows.
struct Job {
    slices: Vec<HostSlice>,
    b: usize,
}

/// The worker threads of an epoch's data-parallel steps, one per device after the main one,
/// and the group they reduce with. Dropping it ends the workers (their scope joins them).
pub(super) struct Replicas<B: AutodiffBackend> {
    jobs: Vec<Sender<Job>>,
    /// Each worker's summed, window-weighted loss of its last step, in any order.
    losses: Receiver<f64>,
    group: Arc<ReduceGroup<B::InnerBackend>>,
}

impl<B: AutodiffBackend + NetOps> Trainer<B>
where
    B::InnerBackend: NetOps,
{
    /// Starts one worker per device after the main one in `scope`, each on its stream of
    /// `streams`, with a replica of `model` and of `optim` on its device.
    pub(super) fn replicas<'scope>(
        &'scope self,
        scope: &'scope Scope<'scope, '_>,
        (model, optim): (&Model<B>, &Optim<B>),
        scaling: &'scope Scaling,
        streams: &[StreamId],
    ) -> Replicas<B> {
        let group = Arc::new(ReduceGroup::new(self.devices.clone()));
        let (done, losses) = channel();
        let jobs = (1..group.ranks())
            .map(|rank| {
                let (send, jobs) = channel::<Job>();
                let (model, record) = (model.clone(), optim.to_record());
                let (group, done, stream) = (Arc::clone(&group), done.clone(), streams[rank]);
                scope.spawn(move || {
                    stream.executes(|| {
                        let guard = FailGuard(&*group);
                        let device = group.device(rank);
                        let mut model = model.fork(device);
                        let mut optim = FusedAdam::default()
                            .init::<B, Model<B>>()
                            .load_record(record);
                        for job in jobs {
                            let (grads, loss) =
                                self.shard_step(&model, job.slices, job.b, scaling, device);
                            let grads = group.sum_grads(rank, &model, grads);
                            model = optim.step(self.opts.lr, model, grads);
                            if done.send(loss_value(loss)).is_err() {
                                break;
                            }
                        }
                        std::mem::forget(guard);
                    })
                });
                send
            })
            .collect();
        Replicas {
            jobs,
            losses,
            group,
        }
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
        for (send, slices) in replicas.jobs.iter().zip(shards) {
            send.send(Job { slices, b })
                .expect("a data-parallel worker ended early");
        }
        let guard = FailGuard(&*replicas.group);
        let (grads, loss) = self.shard_step(&model, own, b, scaling, self.main());
        let grads = replicas.group.sum_grads(0, &model, grads);
        let model = optim.step(self.opts.lr, model, grads);
        std::mem::forget(guard);
        let others = (replicas.jobs.iter())
            .map(|_| (replicas.losses.recv()).expect("a data-parallel worker failed"))
            .sum();
        (model, loss, others)
    }
}

/// A device's summed loss of one step, read back (0 for a share without windows).
pub(super) fn loss_value<B: burn::tensor::backend::Backend>(loss: Option<Tensor<B, 1>>) -> f64 {
    loss.map_or(0.0, |l| l.into_scalar().elem::<f64>())
}
