//! The worker threads of synchronous data-parallel training on the devices of one machine,
//! shared by both trainers (`grid/parallel.rs`, `paper/replicas.rs`): one thread per device
//! after the main one ([`Workers`]), each holding a replica of the model and of its optimizer
//! for a stretch of steps and fed one job a step. Every rank sums its gradients through the
//! [`ReduceGroup`] and takes the same optimizer step, so the replicas stay equal without a
//! broadcast (PyTorch's `DistributedDataParallel` works the same way).

use std::sync::mpsc::{channel, Receiver, Sender};
use std::sync::Arc;
use std::thread::Scope;

use burn::module::AutodiffModule;
use burn::optim::Optimizer;
use burn::record::{FullPrecisionSettings, Record};
use burn::tensor::backend::{AutodiffBackend, Backend};
use burn::tensor::StreamId;

use super::reduce::ReduceGroup;
use crate::ops::NetOps;

/// The workers of a data-parallel stretch, fed jobs of type `J`, and the group they reduce
/// with. Dropping it ends the workers (their scope joins them).
pub(crate) struct Workers<J, A: AutodiffBackend>
where
    A::InnerBackend: NetOps,
{
    jobs: Vec<Sender<J>>,
    /// Each worker's value of its last step (its summed loss), in any order.
    values: Receiver<f64>,
    /// The group every rank sums its gradients with; rank 0 is the caller's ([`Workers::own`]).
    group: Arc<ReduceGroup<A::InnerBackend>>,
}

impl<J: Send, A: AutodiffBackend> Workers<J, A>
where
    A::InnerBackend: NetOps,
{
    /// Starts one worker for each rank of `group` after the first in `scope`, each on its
    /// stream of `streams`, with a replica of `model` on its device and an optimizer made by
    /// `fresh` and loaded with `optim`'s state. For each job a worker runs `step(model,
    /// optimizer, job, rank, group)`, which returns the stepped model and the value sent
    /// back. A worker that panics marks the group failed, so the other ranks stop waiting.
    pub(crate) fn start<'scope, M, O>(
        scope: &'scope Scope<'scope, '_>,
        group: ReduceGroup<A::InnerBackend>,
        streams: &[StreamId],
        (model, optim): (&M, &O),
        fresh: impl Fn() -> O + Send + Sync + 'scope,
        step: impl Fn(M, &mut O, J, usize, &ReduceGroup<A::InnerBackend>) -> (M, f64)
            + Send
            + Sync
            + 'scope,
    ) -> Self
    where
        M: AutodiffModule<A> + 'scope,
        O: Optimizer<M, A> + 'scope,
        J: 'scope,
    {
        let group = Arc::new(group);
        let (done, values) = channel();
        let (copied, ready) = channel::<()>();
        let (fresh, step) = (Arc::new(fresh), Arc::new(step));
        let jobs = (1..group.ranks())
            .map(|rank| {
                let (send, jobs) = channel::<J>();
                let (model, record) = (model.clone(), optim.to_record());
                let (group, done, stream) = (Arc::clone(&group), done.clone(), streams[rank]);
                let (fresh, step, copied) = (Arc::clone(&fresh), Arc::clone(&step), copied.clone());
                scope.spawn(move || {
                    stream.executes(|| {
                        let guard = FailGuard(&*group);
                        let (mut model, mut optim) =
                            replica(model, record, fresh(), group.device(rank));
                        // The sender goes with the message: a worker that panicked
                        // before it drops its own, and the main thread's wait still ends.
                        copied.send(()).ok();
                        drop(copied);
                        for job in jobs {
                            let value;
                            (model, value) = step(model, &mut optim, job, rank, &group);
                            if done.send(value).is_err() {
                                break;
                            }
                        }
                        std::mem::forget(guard);
                    })
                });
                send
            })
            .collect();
        // The main thread's next step waits for every replica's copies (see `replica`).
        drop(copied);
        while ready.recv().is_ok() {}
        Self {
            jobs,
            values,
            group,
        }
    }

    /// Hands each worker its job of this step, in rank order from rank 1.
    ///
    /// # Panics
    /// A worker has ended (it panicked).
    pub(crate) fn send(&self, jobs: impl IntoIterator<Item = J>) {
        for (worker, job) in self.jobs.iter().zip(jobs) {
            worker
                .send(job)
                .expect("a data-parallel worker ended early");
        }
    }

    /// Runs rank 0's share of this step, `f` with the group to sum its gradients in; if it
    /// panics the group is marked failed, so that the workers stop waiting for it.
    pub(crate) fn own<R>(&self, f: impl FnOnce(&ReduceGroup<A::InnerBackend>) -> R) -> R {
        let guard = FailGuard(&*self.group);
        let out = f(&self.group);
        std::mem::forget(guard);
        out
    }

    /// The sum of the workers' values of this step, once each has sent its.
    ///
    /// # Panics
    /// A worker failed.
    pub(crate) fn sum(&self) -> f64 {
        (self.jobs.iter())
            .map(|_| (self.values.recv()).expect("a data-parallel worker failed"))
            .sum()
    }
}

/// A replica of `model` on `device` and `optim` loaded with `record` moved there, made on
/// a worker's thread while the main thread waits for it ([`Workers::start`]).
///
/// Everything read from the main device is read here, before the main thread takes its next
/// step, while it still holds every tensor. Left to the worker's first step (where Adam
/// moves its moments lazily), the worker's copy of a moment could be its last reference;
/// burn-fusion then lets the worker's read take the tensor's handle while an operation of the
/// main thread's stream that reads it still waits in its queue, which then panics ("Should
/// have handle for tensor": 3 runs of 5 of the small shape on 4 H200, issue 82). The moments
/// go through host memory (`Record::into_item` at full precision, exact for f32).
fn replica<A, M, O>(model: M, record: O::Record, optim: O, device: &A::Device) -> (M, O)
where
    A: AutodiffBackend,
    M: AutodiffModule<A>,
    O: Optimizer<M, A>,
{
    let item = record.into_item::<FullPrecisionSettings>();
    let record = <O::Record as Record<A>>::from_item::<FullPrecisionSettings>(item, device);
    (model.fork(device), optim.load_record(record))
}

/// Marks the group failed if its rank's thread unwinds before it is forgotten, so that the
/// other ranks stop waiting for it in a host rendezvous.
struct FailGuard<'g, B: Backend + NetOps>(&'g ReduceGroup<B>);

impl<B: Backend + NetOps> Drop for FailGuard<'_, B> {
    fn drop(&mut self) {
        self.0.fail();
    }
}
