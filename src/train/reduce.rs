//! The gradient all-reduce of data-parallel training (the grid trainer's `grid/parallel.rs`,
//! the paper's `paper/step.rs`): a
//! [`ReduceGroup`] of one rank per device sums each parameter's gradient over the ranks,
//! in the model's parameter order, through the backend's collective
//! ([`NetOps::all_reduce_sum`]: NCCL on CUDA), or, where the backend has none (the CPU
//! backend, a GPU named twice), through a host rendezvous: each rank hands its tensors in,
//! the last one sums them in rank order (so every rank gets the same bits) and every rank
//! takes the sums back onto its device.
//!
//! This is the all-reduce step of synchronous data-parallel SGD (PyTorch's
//! `DistributedDataParallel`, Li et al. 2020, "PyTorch Distributed: Experiences on
//! Accelerating Data Parallel Training", section 3: every replica applies the same summed
//! gradient, so the replicas stay equal without a broadcast).

use std::sync::{Condvar, Mutex, MutexGuard};

use burn::module::{AutodiffModule, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::tensor::backend::{AutodiffBackend, Backend};
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Tensor, TensorPrimitive};

use crate::ops::NetOps;

/// The ranks of one data-parallel run: rank `k` trains on `devices[k]`.
pub(crate) struct ReduceGroup<B: Backend> {
    devices: Vec<B::Device>,
    host: Rendezvous<B>,
}

impl<B: Backend + NetOps> ReduceGroup<B> {
    /// A group of one rank per device of `devices` (the main device first).
    pub(crate) fn new(devices: Vec<B::Device>) -> Self {
        let host = Rendezvous::new(devices.len());
        Self { devices, host }
    }

    /// The ranks.
    pub(crate) fn ranks(&self) -> usize {
        self.devices.len()
    }

    /// Rank `rank`'s device.
    pub(crate) fn device(&self, rank: usize) -> &B::Device {
        &self.devices[rank]
    }

    /// Tells the other ranks that this one failed (called while a rank's thread unwinds),
    /// so that a host rendezvous does not wait for it forever.
    pub(crate) fn fail(&self) {
        self.host.fail();
    }

    /// `grads` of rank `rank`'s replica `model`, each replaced by its sum over the ranks.
    /// Every rank calls this once per optimizer step, with the same parameters.
    ///
    /// # Panics
    /// When another rank failed during a host rendezvous.
    pub(crate) fn sum_grads<A, M>(
        &self,
        rank: usize,
        model: &M,
        grads: GradientsParams,
    ) -> GradientsParams
    where
        A: AutodiffBackend<InnerBackend = B>,
        M: AutodiffModule<A>,
    {
        let mut take = Take::<B> {
            grads,
            taken: Vec::new(),
        };
        model.visit(&mut take);
        let Take { grads, taken } = take;
        let (ids, tensors): (Vec<_>, Vec<_>) = taken.into_iter().unzip();
        let sums = match B::all_reduce_sum(tensors, &self.devices) {
            Ok(sums) => sums,
            Err(tensors) => self.host.sum(rank, tensors, &self.devices),
        };
        let mut put = Put::<B> {
            grads,
            sums: ids.into_iter().zip(sums).collect::<Vec<_>>().into_iter(),
        };
        model.visit(&mut put);
        put.grads
    }
}

/// Takes each parameter's gradient out of `grads`, in the model's order.
struct Take<B: Backend> {
    grads: GradientsParams,
    taken: Vec<(burn::module::ParamId, FloatTensor<B>)>,
}

impl<A: AutodiffBackend> ModuleVisitor<A> for Take<A::InnerBackend> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<A, D>>) {
        if let Some(grad) = self.grads.remove::<A::InnerBackend, D>(param.id) {
            self.taken.push((param.id, grad.into_primitive().tensor()));
        }
    }
}

/// Puts the summed gradients back into `grads`, in the order [`Take`] took them.
struct Put<B: Backend> {
    grads: GradientsParams,
    sums: std::vec::IntoIter<(burn::module::ParamId, FloatTensor<B>)>,
}

impl<A: AutodiffBackend> ModuleVisitor<A> for Put<A::InnerBackend> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<A, D>>) {
        let next = self.sums.as_slice().first().map(|(id, _)| *id);
        if next == Some(param.id) {
            let (id, sum) = self.sums.next().expect("peeked");
            let sum = Tensor::<A::InnerBackend, D>::from_primitive(TensorPrimitive::Float(sum));
            self.grads.register::<A::InnerBackend, D>(id, sum);
        }
    }
}

/// The host all-reduce: one round at a time, each rank's tensors handed in, summed once
/// by the last rank in, taken back by every rank.
struct Rendezvous<B: Backend> {
    round: Mutex<Round<B>>,
    turn: Condvar,
}

/// One round's state.
struct Round<B: Backend> {
    /// Each rank's tensors, until the last rank in sums them.
    handed: Vec<Option<Vec<FloatTensor<B>>>>,
    /// The sums, until every rank has taken them.
    sums: Option<Vec<FloatTensor<B>>>,
    taken: usize,
    /// Set by a rank that panicked, so that the others stop waiting.
    broken: bool,
}

impl<B: Backend> Rendezvous<B> {
    fn new(ranks: usize) -> Self {
        let round = Round {
            handed: (0..ranks).map(|_| None).collect(),
            sums: None,
            taken: 0,
            broken: false,
        };
        Self {
            round: Mutex::new(round),
            turn: Condvar::new(),
        }
    }

    /// Rank `rank`'s `tensors` summed with every other rank's, on `devices[rank]`.
    fn sum(
        &self,
        rank: usize,
        tensors: Vec<FloatTensor<B>>,
        devices: &[B::Device],
    ) -> Vec<FloatTensor<B>> {
        let ranks = devices.len();
        let mut round = self.round.lock().unwrap_or_else(|e| e.into_inner());
        Self::check(&round);
        // The last round's sums not yet taken by every rank: wait for it to end.
        while round.sums.is_some() {
            round = self.wait(round);
        }
        round.handed[rank] = Some(tensors);
        if round.handed.iter().all(Option::is_some) {
            let handed: Vec<_> = round
                .handed
                .iter_mut()
                .map(|h| h.take().expect("all in"))
                .collect();
            round.sums = Some(Self::add(handed, &devices[0]));
            self.turn.notify_all();
        }
        while round.sums.is_none() {
            round = self.wait(round);
        }
        let sums = round.sums.as_ref().expect("summed");
        let mine = (sums.iter())
            .map(|s| B::float_to_device(s.clone(), &devices[rank]))
            .collect();
        round.taken += 1;
        if round.taken == ranks {
            round.sums = None;
            round.taken = 0;
            self.turn.notify_all();
        }
        mine
    }

    /// Waits for another rank's turn; panics when a rank failed meanwhile.
    fn wait<'a>(&self, round: MutexGuard<'a, Round<B>>) -> MutexGuard<'a, Round<B>> {
        let round = self.turn.wait(round).unwrap_or_else(|e| e.into_inner());
        Self::check(&round);
        round
    }

    /// The element-wise sums of each rank's tensors, in rank order, on `device`.
    fn add(handed: Vec<Vec<FloatTensor<B>>>, device: &B::Device) -> Vec<FloatTensor<B>> {
        let mut ranks = handed.into_iter();
        let first = ranks.next().unwrap_or_default();
        let mut sums: Vec<_> = (first.into_iter())
            .map(|t| B::float_to_device(t, device))
            .collect();
        for tensors in ranks {
            for (sum, t) in sums.iter_mut().zip(tensors) {
                let t = B::float_to_device(t, device);
                *sum = B::float_add(sum.clone(), t);
            }
        }
        sums
    }

    /// Panics when a rank failed: its tensors will never come.
    fn check(round: &Round<B>) {
        assert!(!round.broken, "another data-parallel rank failed");
    }

    /// Marks the group failed and wakes every waiting rank (a rank's panic guard).
    fn fail(&self) {
        let mut round = self.round.lock().unwrap_or_else(|e| e.into_inner());
        round.broken = true;
        self.turn.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use burn::backend::NdArray;
    use burn::tensor::{Tensor, TensorPrimitive};

    use super::ReduceGroup;

    type B = NdArray<f32>;

    /// Rank `rank`'s tensor `[rank + 10 round, 1]` summed over the group.
    fn summed(group: &ReduceGroup<B>, rank: usize, round: usize) -> Vec<f32> {
        let device = Default::default();
        let x = [rank as f32 + 10.0 * round as f32, 1.0];
        let t = Tensor::<B, 1>::from_floats(x, &device)
            .into_primitive()
            .tensor();
        let sums = group.host.sum(rank, vec![t], &group.devices);
        let sum = Tensor::<B, 1>::from_primitive(TensorPrimitive::Float(sums[0].clone()));
        sum.into_data().to_vec::<f32>().unwrap()
    }

    #[test]
    fn the_host_rendezvous_gives_every_rank_the_sums_round_after_round() {
        let group = ReduceGroup::<B>::new(vec![Default::default(); 3]);
        std::thread::scope(|s| {
            let ranks: Vec<_> = (0..3)
                .map(|rank| {
                    let group = &group;
                    s.spawn(move || (0..3).map(|r| summed(group, rank, r)).collect::<Vec<_>>())
                })
                .collect();
            for rank in ranks {
                let sums = rank.join().unwrap();
                assert_eq!(sums, [[3.0, 3.0], [33.0, 3.0], [63.0, 3.0]]);
            }
        });
    }

    #[test]
    fn a_failed_rank_stops_the_others_waiting() {
        let group = ReduceGroup::<B>::new(vec![Default::default(); 2]);
        std::thread::scope(|s| {
            let waiting = s.spawn(|| summed(&group, 0, 0));
            std::thread::sleep(std::time::Duration::from_millis(50));
            group.fail();
            assert!(waiting.join().is_err(), "rank 0 waited for a failed rank");
        });
    }
}
