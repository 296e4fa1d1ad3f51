//! The all-reduce of data-parallel training's gradients on burn's CUDA backend
//! ([`NetOps::all_reduce_sum`](crate::ops::NetOps::all_reduce_sum)): NCCL's `ncclAllReduce`
//! (NVIDIA Collective Communications Library, "Collective Operations": every rank gets the
//! element-wise sum of every rank's buffer), as burn's distributed backend drives it through
//! cubecl-cuda (burn-fusion records an all-reduce operation on the tensor's fusion stream;
//! cubecl-cuda issues it on a communication stream of the GPU that waits for the compute
//! stream, from one NCCL communicator per set of GPUs, made on first use). The sums are
//! ordered before later work by one `sync_collective` a call: the compute stream waits for
//! the communication stream, the host for nothing but the fusion stream's hand-over.
//!
//! Every rank must reduce the same tensors in the same order (NCCL matches the calls of a
//! communicator by their order), which the caller's fixed parameter order gives.

use burn::backend::cuda::CudaDevice;
use burn::tensor::backend::distributed::{DistributedBackend, ReduceOperation};
use burn::tensor::backend::{DeviceId, DeviceOps};
use burn::tensor::ops::FloatTensor;
use burn::tensor::ops::FloatTensorOps;

use crate::ops::cuda::net::conv::Cuda;

/// [`NetOps::all_reduce_sum`](crate::ops::NetOps::all_reduce_sum) on `devices` through
/// NCCL; `Err` (the tensors back) for fewer than two GPUs or a GPU named twice, which one
/// NCCL communicator cannot hold.
#[allow(clippy::type_complexity)]
pub(in crate::ops) fn all_reduce_sum(
    tensors: Vec<FloatTensor<Cuda>>,
    devices: &[CudaDevice],
) -> Result<Vec<FloatTensor<Cuda>>, Vec<FloatTensor<Cuda>>> {
    let ids: Vec<DeviceId> = devices.iter().map(DeviceOps::id).collect();
    let mut distinct = ids.clone();
    distinct.sort();
    distinct.dedup();
    if ids.len() < 2 || distinct.len() != ids.len() {
        return Err(tensors);
    }
    let Some(device) = tensors.first().map(Cuda::float_device) else {
        return Ok(tensors);
    };
    let sums = (tensors.into_iter())
        .map(|t| {
            let sum = Cuda::all_reduce(t, ReduceOperation::Sum, ids.clone());
            // SAFETY: `sync_collective` below orders the sums before any later use.
            unsafe { sum.assume_resolved() }
        })
        .collect();
    Cuda::sync_collective(&device);
    Ok(sums)
}
