//! The paper run's batches on their way to the device: a batch cut into micro-batches on the
//! host ([`HostSlice`]), dealt to the devices of a data-parallel run, uploaded, and the
//! loss of the model's prediction on one ([`slice_loss`]); [`evaluate`] is the validation
//! loss over a whole batch source. Used by [`super::Trainer`].

use burn::tensor::backend::Backend;
use burn::tensor::{ElementConversion, Tensor};

use super::{loss, TrainOptions};
use crate::data::Batch;
use crate::model::{upload, Model, Scaling};
use crate::train::{BatchSource, TrainError};

/// Host data of a batch slice `[start, start + len)`, ready to upload.
pub(super) struct HostSlice {
    pub(super) len: usize,
    pub(super) t: usize,
    pub(super) n: usize,
    pub(super) inputs: Vec<f32>,
    pub(super) targets: Vec<f32>,
    pub(super) target_pos: Vec<f32>,
    pub(super) dt: Vec<f32>,
}

/// Tensors of a batch slice.
pub(super) struct Slice<B: Backend> {
    inputs: Tensor<B, 4>,
    targets: Tensor<B, 3>,
    target_pos: Tensor<B, 3>,
    dt: Tensor<B, 1>,
}

/// Deals micro-batches to `k` devices in turn (the first devices get one more when they do
/// not divide evenly).
pub(super) fn deal(slices: Vec<HostSlice>, k: usize) -> Vec<Vec<HostSlice>> {
    let mut shards: Vec<Vec<HostSlice>> = (0..k).map(|_| Vec::new()).collect();
    for (i, s) in slices.into_iter().enumerate() {
        shards[i % k].push(s);
    }
    shards
}

/// Cuts `batch` into micro-batches of at most `micro` windows (host side).
pub(super) fn host_slices(batch: Batch, micro: usize) -> Vec<HostSlice> {
    let (t, n, b) = (batch.t, batch.n, batch.b);
    let micro = micro.clamp(1, b.max(1));
    let mut out = Vec::with_capacity(b.div_ceil(micro));
    let mut start = 0;
    while start < b {
        let len = micro.min(b - start);
        let target_pos = batch.target_phys[start * n * 4..(start + len) * n * 4]
            .chunks_exact(4)
            .flat_map(|r| [r[0], r[1]])
            .collect();
        let (inputs, targets) = if len == b {
            (batch.inputs.clone(), batch.targets.clone())
        } else {
            (
                batch.inputs[start * t * n * 5..(start + len) * t * n * 5].to_vec(),
                batch.targets[start * n * 4..(start + len) * n * 4].to_vec(),
            )
        };
        out.push(HostSlice {
            len,
            t,
            n,
            inputs,
            targets,
            target_pos,
            dt: batch.dt[start..start + len].to_vec(),
        });
        start += len;
    }
    out
}

impl HostSlice {
    pub(super) fn upload<B: Backend>(self, device: &B::Device) -> Slice<B> {
        let (len, t, n) = (self.len, self.t, self.n);
        Slice {
            inputs: upload(self.inputs, [len, t, n, 5], device),
            targets: upload(self.targets, [len, n, 4], device),
            target_pos: upload(self.target_pos, [len, n, 2], device),
            dt: upload(self.dt, [len], device),
        }
    }
}

/// Predicted positions in domain units from a scaled prediction `[B, N, 4]`.
fn positions<B: burn::tensor::backend::Backend>(
    pred: Tensor<B, 3>,
    scaling: &Scaling,
) -> Tensor<B, 3> {
    let (min, range) = scaling.tensors::<B>(&pred.device());
    (pred * range + min).narrow(2, 0, 2)
}

/// The model's prediction for a batch slice and its loss (train and validation alike).
pub(super) fn slice_loss<B: crate::ops::NetOps>(
    model: &Model<B>,
    s: Slice<B>,
    scaling: &Scaling,
    opts: &TrainOptions,
) -> loss::LossParts<B> {
    let pred = model.forward(s.inputs, s.dt, scaling);
    loss::loss(
        pred.clone(),
        s.targets,
        positions(pred, scaling),
        s.target_pos,
        opts.density_grid,
        opts.density_weight,
    )
}

/// Mean loss of `model` over `index` (no gradients, no dropout).
pub fn evaluate<B: crate::ops::NetOps>(
    model: &Model<B>,
    index: &mut dyn BatchSource,
    scaling: &Scaling,
    opts: &TrainOptions,
    device: &B::Device,
) -> Result<f64, TrainError> {
    let (mut sum, mut count) = (0.0, 0usize);
    for batch in index.batches(opts.micro_batch.max(1), None, 0)? {
        let batch = batch?;
        let b = batch.b;
        for host in host_slices(batch, b) {
            let len = host.len;
            let parts = slice_loss(model, host.upload::<B>(device), scaling, opts);
            sum += parts.total.into_scalar().elem::<f64>() * len as f64;
            count += len;
        }
    }
    Ok(if count == 0 {
        f64::NAN
    } else {
        sum / count as f64
    })
}
