//! One epoch of a paper run and its optimizer steps: host batches assembled one ahead on a
//! second thread, each batch one optimizer step (on the main device, or data-parallel over
//! several with a persistent replica on each, `replicas.rs`), the loss read back once per
//! step. Part of [`super::Trainer`].

use std::time::Instant;

use burn::optim::{GradientsAccumulator, GradientsParams, Optimizer};
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::{StreamId, Tensor};

use super::replicas::{loss_value, Replicas};
use super::slices::{deal, host_slices, slice_loss, HostSlice};
use super::{Optim, Trainer};
use crate::model::{Model, Scaling};
use crate::train::{BatchSource, EpochPass, Observer, TrainError};

impl<B: AutodiffBackend + crate::ops::NetOps> Trainer<B>
where
    B::InnerBackend: crate::ops::NetOps,
{
    /// Forward and backward of `slices` (micro-batches of one optimizer step of `b`
    /// windows) on `device`: the accumulated gradients (scaled so that the shares of all
    /// devices sum to the batch mean) and the summed, window-weighted loss (not read back).
    pub(super) fn shard_step(
        &self,
        model: &Model<B>,
        slices: Vec<HostSlice>,
        b: usize,
        scaling: &Scaling,
        device: &B::Device,
    ) -> (GradientsParams, Option<Tensor<B::InnerBackend, 1>>) {
        let mut accumulator = GradientsAccumulator::new();
        let mut batch_loss: Option<Tensor<B::InnerBackend, 1>> = None;
        let started = Instant::now();
        for host in slices {
            let len = host.len;
            let parts = slice_loss(model, host.upload::<B>(device), scaling, &self.opts);
            let weighted = parts.total.clone().inner().mul_scalar(len as f32);
            batch_loss = Some(match batch_loss {
                Some(acc) => acc + weighted,
                None => weighted,
            });
            let forward = started.elapsed();
            let grads = parts.total.mul_scalar(len as f32 / b as f32).backward();
            let backward = started.elapsed();
            accumulator.accumulate(model, GradientsParams::from_grads(grads, model));
            tracing::trace!(?forward, ?backward, accumulated = ?started.elapsed(), "micro-batch");
        }
        (accumulator.grads(), batch_loss)
    }

    /// One epoch over `train` (0-based `epoch`, started at `started`): host batches are
    /// assembled one ahead on a second thread; each is one optimizer step, its loss read
    /// back once. Returns the trained model (on the main device) and the epoch's totals.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn train_epoch(
        &self,
        model: Model<B>,
        optim: &mut Optim<B>,
        train: &mut dyn BatchSource,
        epoch: usize,
        scaling: &Scaling,
        streams: &[StreamId],
        observer: &mut dyn Observer,
        started: Instant,
    ) -> Result<(Model<B>, EpochPass), TrainError> {
        let batch_size = self.opts.batch_size.max(1);
        let total = train.num_batches(batch_size);
        let batches = train.batches(batch_size, Some(self.opts.seed), epoch as u64)?;
        let micro = self.opts.micro_batch;
        let parallel = self.devices.len();
        // The model moves into the step loop and back out (`optim.step` consumes it, so
        // the parameters are updated in place when nothing else holds them).
        let mut slot = Some(model);
        let totals = std::thread::scope(|scope| {
            // Host batches are assembled (and cut into micro-batches) one ahead.
            let (tx, rx) = std::sync::mpsc::sync_channel(1);
            scope.spawn(move || {
                for batch in batches {
                    // Data parallel: at least one micro-batch per device.
                    let item = batch.map(|b| {
                        let micro = micro.min(b.b.div_ceil(parallel));
                        (b.b, host_slices(b, micro))
                    });
                    if tx.send(item).is_err() {
                        break;
                    }
                }
            });
            let mut totals = EpochPass::default();
            let mut k = 0;
            // The replicas on the other devices, started by the epoch's first data-parallel
            // step (`replicas.rs`).
            let mut replicas: Option<Replicas<B>> = None;
            loop {
                let waited = Instant::now();
                let Ok(item) = rx.recv() else { break };
                totals.data_seconds += waited.elapsed().as_secs_f64();
                let (b, slices) = item?;
                let model = slot.take().expect("the model is put back after every step");
                let step_started = Instant::now();
                let (model, loss, others) = if parallel == 1 || slices.len() < parallel {
                    // A batch of fewer micro-batches than devices (a short last batch) steps
                    // on the main device alone (every rank of the all-reduce needs a share):
                    // the replicas, a step behind now, are ended.
                    replicas = None;
                    let (grads, loss) = self.shard_step(&model, slices, b, scaling, self.main());
                    (optim.step(self.opts.lr, model, grads), loss, 0.0)
                } else {
                    let from = (&model, &*optim);
                    let r = replicas
                        .get_or_insert_with(|| self.replicas(scope, from, scaling, streams));
                    self.parallel_step((model, optim), deal(slices, parallel), (b, scaling), r)
                };
                slot = Some(model);
                tracing::trace!(step = ?step_started.elapsed(), "optimizer step");
                // One read per step, after the step is queued: the host waits here for
                // the device to finish it.
                let waited = Instant::now();
                let value = (loss_value(loss) + others) / b.max(1) as f64;
                totals.wait_seconds += waited.elapsed().as_secs_f64();
                totals.add_step(value, b, (epoch, k, total), started, &mut *observer)?;
                k += 1;
            }
            Ok::<EpochPass, TrainError>(totals)
        })?;
        let model = slot.expect("the model is put back after every step");
        Ok((model, totals))
    }
}
