//! What the library calls of `ops` on burn's CUDA backend share (feature `cuda`): a GPU's
//! primary context, the calls queued on cubecl's device thread in stream order with its
//! kernels ([`on_device`]), the hand-over of that thread's queue ([`flush_device`]), and the
//! ordering of inputs from other streams after a call ([`after_foreign`]). cuBLAS
//! (`cublas.rs`), cuDNN (`cuda/net/cudnn_calls.rs`) and the read back (`cuda/read.rs`) go through
//! here; how a custom operation joins burn's fusion stream is told in `cublas.rs`.

use burn::cubecl::cuda::CudaRuntime;
use burn_cubecl::tensor::CubeTensor;
use cudarc::driver::{result as driver, sys as driver_sys};

use crate::ops::OpsError;

/// GPU `index`'s primary context (the one cubecl uses), retained again and made current
/// on this thread: what a library handle of the GPU is created in. Never released: the
/// handles live as long as the process.
///
/// # Errors
/// The CUDA driver's, when the device, its context or making it current fails.
pub(in crate::ops) fn primary_context(index: usize) -> Result<driver_sys::CUcontext, OpsError> {
    let ordinal = OpsError::fit_i32("CUDA device ordinal", index)?;
    // SAFETY: driver FFI on an ordinal; the context is retained before it is made current.
    unsafe {
        let dev = driver::device::get(ordinal).map_err(|e| OpsError::driver("device", e))?;
        let ctx =
            driver::primary_ctx::retain(dev).map_err(|e| OpsError::driver("primary context", e))?;
        driver::ctx::set_current(ctx).map_err(|e| OpsError::driver("context", e))?;
        Ok(ctx)
    }
}

/// cubecl's CUDA compute server: the service that owns a GPU's memory pools and launches
/// its kernels, from a device thread of its own.
type Server = <CudaRuntime as burn::cubecl::Runtime>::Server;

/// A device pointer and the CUDA stream of the memory pool it comes from.
pub(in crate::ops) type Resource = (u64, driver_sys::CUstream);

/// Runs `f` on cubecl's device thread of the tensors' GPU, with each tensor's device
/// pointer and the stream of the memory pool it comes from, in order with cubecl's own
/// launches: after every kernel launched before this call, before every kernel launched
/// after it. A library call that `f` enqueues on the output's stream (a tensor this thread
/// allocated: the stream cubecl launches this thread's kernels on) therefore runs in
/// stream order with them, and the host does not wait for anything: the call is queued
/// like a kernel launch (`cubecl_common`'s `DeviceHandle::submit`, the queue
/// `ComputeClient::launch` itself goes through). Reading the pointers from this thread
/// instead (`ComputeClient::get_resource`) blocked the host until the device thread had
/// launched everything queued before: 0.8-1.3 ms a library call (docs/speed.md, "Where a
/// GPU call's time goes").
///
/// The tensors are moved into the task and dropped on the device thread once `f` has
/// returned, so their memory goes back to the pool only for kernels launched after the
/// library's; the task runs with the caller's cubecl stream id (`submit` carries it).
///
/// A tensor's memory that cannot be read (a cubecl error), an error `f` returns (a library
/// error) or a panic in `f` aborts the process, naming `operation` ([`OpsError::abort`]):
/// the output would never be written.
pub(in crate::ops) fn on_device(
    tensors: Vec<CubeTensor<CudaRuntime>>,
    operation: &'static str,
    f: impl FnOnce(&[Resource]) -> Result<(), OpsError> + Send + 'static,
) {
    use burn::cubecl::device::Device;
    use burn::cubecl::device_handle::DeviceHandle;
    use burn::cubecl::server::ComputeServer;
    use burn::cubecl::stream_id::StreamId;
    let device = tensors[0].device.to_id();
    DeviceHandle::<Server>::new(device).submit(move |server: &mut Server| {
        let stream = StreamId::current();
        let resources: Result<Vec<_>, OpsError> = (tensors.iter())
            .map(|t| {
                (server.get_resource(t.handle.clone().binding(), stream))
                    .map_err(|e| OpsError::cubecl("resource", e))
            })
            .collect();
        let resources = resources.unwrap_or_else(|e| e.abort(operation));
        let pointers: Vec<Resource> = resources
            .iter()
            .map(|r| (r.resource().ptr, r.resource().stream))
            .collect();
        // A failure here would otherwise be caught by cubecl's device thread and only
        // logged, and the output, never written, read as a result: stop the process, as
        // a failed call on the caller's thread did.
        let call = std::panic::AssertUnwindSafe(|| f(&pointers));
        match std::panic::catch_unwind(call) {
            Ok(Ok(())) => {}
            Ok(Err(e)) => e.abort(operation),
            Err(e) => {
                let why = (e.downcast_ref::<String>().map(String::as_str))
                    .or_else(|| e.downcast_ref::<&str>().copied())
                    .unwrap_or("a panic");
                tracing::error!("{operation} panicked on the device thread: {why}");
                eprintln!("minflow: {operation} panicked on the device thread: {why}");
                std::process::abort();
            }
        }
        drop(resources);
        drop(tensors);
    });
}

/// Hands the tasks queued for `device`'s cubecl device thread over to it now (launches,
/// library calls, [`on_device`]'s tasks): its channel batches them, and hands a batch
/// over only when it is full or a caller waits on the device thread, so a last task
/// whose effect the host waits for outside cubecl (an event) would otherwise stay
/// queued.
pub(in crate::ops) fn flush_device(device: &burn::backend::cuda::CudaDevice) {
    use burn::cubecl::device::Device;
    use burn::cubecl::device_handle::DeviceHandle;
    DeviceHandle::<Server>::new(device.to_id()).flush_queue();
}

/// Orders the streams of inputs from other streams' pools (`inputs`; data parallel
/// workers, a loader thread, weights made on another thread) after the work just enqueued
/// on `stream`: such an input may be freed as soon as its tensor drops, and its memory
/// reused by later work on its own stream while our kernel still reads it. An event
/// recorded on `stream` and waited for on each foreign stream holds that later work back,
/// with no host wait (`cuStreamWaitEvent`; a host synchronisation here made every call
/// with a foreign input wait for the GPU).
///
/// # Errors
/// The CUDA driver's, when an event cannot be made, recorded, waited for or released.
///
/// # Safety
/// The streams are live CUDA streams of the current context.
pub(in crate::ops) unsafe fn after_foreign(
    stream: driver_sys::CUstream,
    inputs: &[driver_sys::CUstream],
) -> Result<(), OpsError> {
    let mut done: Vec<driver_sys::CUstream> = Vec::new();
    for &other in inputs {
        if other == stream || done.contains(&other) {
            continue;
        }
        done.push(other);
        static SEEN: std::sync::Once = std::sync::Once::new();
        SEEN.call_once(|| tracing::debug!("a library kernel read an input of another stream"));
        let flags = driver_sys::CUevent_flags::CU_EVENT_DISABLE_TIMING;
        let event = driver::event::create(flags).map_err(|e| OpsError::driver("event", e))?;
        driver::event::record(event, stream).map_err(|e| OpsError::driver("event record", e))?;
        let wait = driver_sys::CUevent_wait_flags::CU_EVENT_WAIT_DEFAULT;
        driver::stream::wait_event(other, event, wait)
            .map_err(|e| OpsError::driver("stream wait", e))?;
        // Released by the driver once the wait is done.
        driver::event::destroy(event).map_err(|e| OpsError::driver("event release", e))?;
    }
    Ok(())
}
