//! [`NetOps::read_ahead`](crate::ops::NetOps::read_ahead) on burn's CUDA backend (feature
//! `cuda`): a tensor copied to pinned host memory in stream order, behind the kernels
//! recorded before it, and an event after the copy that the host waits on. The copy is a
//! custom operation of burn's fusion layer (how one joins the fusion stream, and how it is
//! queued on cubecl's device thread without a host wait: `cublas.rs`), and the fusion stream
//! is drained when it is recorded, so the copy is queued at once, before the work the host
//! records next (cubecl's device thread is handed its queued tasks at once,
//! `cuda::device::flush_device`). Waiting on the event waits for the copy and what came
//! before it, not for what was queued after: the next network call runs on the GPU while the
//! host takes this one's predictions (the surrogate node's pipelined calls, docs/scale.md).
//!
//! cubecl's own read (`into_data`) could not do this: the read is queued only when its future
//! is polled, and then it waits on a fence recorded after everything queued so far.

use std::collections::HashMap;
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

use burn::tensor::ops::FloatTensor;
use burn::tensor::{DType, Shape};
use burn_fusion::stream::{Operation, OperationStreams};
use burn_fusion::FusionRuntime;
use burn_ir::{CustomOpIr, HandleContainer, OperationIr, TensorIr};
use cudarc::driver::{result as driver, sys as driver_sys};

use crate::ops::cuda::device::{flush_device, on_device, primary_context};
use crate::ops::cuda::net::conv::{contiguous, Cuda, Inner, Runtime};
use crate::ops::{OpsError, ReadAhead};

/// How long a wait gives the device thread to queue the copy before it reports an error
/// (the copy is queued right after the work before it is launched, so only a stuck device
/// thread takes this long).
const QUEUE_TIMEOUT: Duration = Duration::from_secs(60);

/// Where a copy lands: pinned host memory of `len` f32 values, and the event recorded after
/// the copy on its stream, in the GPU's context.
#[derive(Debug)]
struct Landing {
    host: *mut f32,
    len: usize,
    bytes: usize,
    event: driver_sys::CUevent,
    ctx: driver_sys::CUcontext,
}

// SAFETY: the pointer is pinned host memory owned by this landing (given back to the pool
// after the wait); the event and context are driver handles usable from any thread.
unsafe impl Send for Landing {}

/// The landing the device thread fills in (or its error), and the wait's wake-up.
type Slot = Arc<(Mutex<Option<Result<Landing, OpsError>>>, Condvar)>;

/// Pinned host buffers of finished reads, `(pointer, bytes)`, for the next reads: pinning
/// 10 MB costs milliseconds, and the node reads one call's predictions after another.
static POOL: Mutex<Vec<(usize, usize)>> = Mutex::new(Vec::new());

/// Buffers kept in [`POOL`] at most.
const POOL_SIZE: usize = 4;

/// GPU contexts by device index (pointers), retained once each ([`primary_context`]).
static CONTEXTS: Mutex<Option<HashMap<usize, usize>>> = Mutex::new(None);

/// GPU `index`'s primary context, made current on this thread.
///
/// # Errors
/// The CUDA driver's.
fn context(index: usize) -> Result<driver_sys::CUcontext, OpsError> {
    let mut all = CONTEXTS.lock().unwrap_or_else(|e| e.into_inner());
    let all = all.get_or_insert_with(HashMap::new);
    let ctx = match all.get(&index) {
        Some(&ctx) => ctx as driver_sys::CUcontext,
        None => {
            let ctx = primary_context(index)?;
            all.insert(index, ctx as usize);
            ctx
        }
    };
    // SAFETY: a retained primary context of a valid device.
    unsafe { driver::ctx::set_current(ctx) }.map_err(|e| OpsError::driver("context", e))?;
    Ok(ctx)
}

/// A pinned host buffer of at least `bytes` bytes: one from the pool, or a new one.
///
/// # Errors
/// The CUDA driver's, when no pinned memory could be allocated.
fn pinned(bytes: usize) -> Result<(usize, usize), OpsError> {
    let mut pool = POOL.lock().unwrap_or_else(|e| e.into_inner());
    if let Some(i) = pool.iter().position(|&(_, size)| size >= bytes) {
        return Ok(pool.swap_remove(i));
    }
    drop(pool);
    // SAFETY: plain allocation; freed by `give_back` (or kept in the pool for the process).
    let ptr = unsafe { driver::malloc_host(bytes.max(4), 0) }
        .map_err(|e| OpsError::driver(format!("pinned host memory of {bytes} bytes"), e))?;
    Ok((ptr as usize, bytes.max(4)))
}

/// Returns a pinned buffer to the pool, or frees it when the pool is full.
fn give_back((ptr, bytes): (usize, usize)) {
    let mut pool = POOL.lock().unwrap_or_else(|e| e.into_inner());
    if pool.len() < POOL_SIZE {
        pool.push((ptr, bytes));
        return;
    }
    // SAFETY: a buffer from `pinned`, no copy in flight into it (its event was waited for).
    let _ = unsafe { driver::free_host(ptr as *mut std::ffi::c_void) };
}

/// The recorded read: input `[x]`; a one-element output nothing reads (an operation of the
/// fusion stream has outputs); the landing goes to `slot`.
#[derive(Debug)]
struct ReadOp {
    desc: CustomOpIr,
    slot: Slot,
}

impl Operation<Runtime> for ReadOp {
    fn execute(&self, handles: &mut HandleContainer<<Runtime as FusionRuntime>::FusionHandle>) {
        let x = contiguous(handles.get_float_tensor::<Inner>(&self.desc.inputs[0]));
        let marker = burn_cubecl::ops::numeric::empty_device_contiguous_dtype(
            x.client.clone(),
            x.device.clone(),
            Shape::new([1]),
            DType::F32,
        );
        handles.register_float_tensor::<Inner>(&self.desc.outputs[0].id, marker);
        let (len, index) = (x.meta.num_elements(), x.device.index);
        let slot = self.slot.clone();
        // The copy's errors go to the waiting host (a read back's `Result`).
        on_device(vec![x], "CUDA read back", move |resources| {
            let (ptr, stream) = resources[0];
            let landing = enqueue(ptr, stream, len, index);
            let (lock, woken) = &*slot;
            *lock.lock().unwrap_or_else(|e| e.into_inner()) = Some(landing);
            woken.notify_all();
            Ok(())
        });
    }
}

/// On cubecl's device thread: the copy of `len` f32 values at device pointer `ptr` into a
/// pinned buffer, then an event, both on `stream` (the one the values were written on).
///
/// # Errors
/// The CUDA driver's: the context, the pinned buffer, the copy or the event.
fn enqueue(
    ptr: u64,
    stream: driver_sys::CUstream,
    len: usize,
    index: usize,
) -> Result<Landing, OpsError> {
    let ctx = context(index)?;
    let (host, bytes) = pinned(len * 4)?;
    // SAFETY: `host` holds at least `len` f32 and stays allocated until the event after the
    // copy has been waited for (`wait`); `ptr` is a live cubecl allocation of `len` f32 on
    // `stream`, kept by stream order until the copy is done (on_device's tensors).
    unsafe {
        let dst = std::slice::from_raw_parts_mut(host as *mut f32, len);
        let copied = driver::memcpy_dtoh_async(dst, ptr, stream);
        let event = copied.and_then(|()| {
            let event = driver::event::create(driver_sys::CUevent_flags::CU_EVENT_DISABLE_TIMING)?;
            driver::event::record(event, stream).map(|()| event)
        });
        match event {
            Ok(event) => Ok(Landing {
                host: host as *mut f32,
                len,
                bytes,
                event,
                ctx,
            }),
            Err(e) => {
                // The copy may be queued into the buffer: it is left allocated, never reused.
                Err(OpsError::driver(format!("read of {len} values"), e))
            }
        }
    }
}

/// Blocks until the device thread has queued the copy and the copy is done; the values in
/// `parts` equal consecutive pieces (none for 0), each copied once out of the pinned buffer.
///
/// # Errors
/// The copy was not queued in time ([`OpsError::NotQueued`]), or the driver's (the copy,
/// the context, the wait).
fn wait(
    slot: &Slot,
    device: &burn::backend::cuda::CudaDevice,
    parts: usize,
) -> Result<Vec<Vec<f32>>, OpsError> {
    let (lock, woken) = &**slot;
    let guard = lock.lock().unwrap_or_else(|e| e.into_inner());
    if guard.is_none() {
        // The copy's task may still sit in the device thread's batch.
        flush_device(device);
    }
    let (mut guard, timeout) = woken
        .wait_timeout_while(guard, QUEUE_TIMEOUT, |l| l.is_none())
        .unwrap_or_else(|e| e.into_inner());
    if timeout.timed_out() {
        return Err(OpsError::NotQueued(QUEUE_TIMEOUT));
    }
    let landing = guard.take().expect("filled")?;
    // SAFETY: the landing's event, context and buffer, filled by `enqueue`; the buffer is read
    // only after the event (the copy's end) has been waited for.
    unsafe {
        driver::ctx::set_current(landing.ctx).map_err(|e| OpsError::driver("context", e))?;
        let synced = driver::event::synchronize(landing.event);
        let _ = driver::event::destroy(landing.event);
        let values = synced.map(|()| {
            let all = std::slice::from_raw_parts(landing.host, landing.len);
            match parts {
                0 => Vec::new(),
                _ => all
                    .chunks(landing.len.div_ceil(parts).max(1))
                    .map(copy_out)
                    .collect(),
            }
        });
        // After a failed wait the copy may still be under way: the buffer is left allocated,
        // never reused.
        if values.is_ok() {
            give_back((landing.host as usize, landing.bytes));
        }
        values.map_err(|e| OpsError::driver("read", e))
    }
}

/// Values of a read at least this large are copied out of the pinned buffer by rayon's
/// threads (a megabyte: below it a thread's start costs more than the copy).
const PARALLEL_COPY: usize = 1 << 18;

/// `src` (a piece of a pinned buffer) copied into a new vector, in slices of
/// [`PARALLEL_COPY`] values on rayon's threads where it is larger. The vector's pages are
/// faulted in and zeroed by the kernel as they are first written, so one thread copied a
/// 10,000-particle call's 164 MB of frames at 5-6 GB/s, a fifth of PCIe's rate
/// (docs/speed.md, "Roofline by part").
fn copy_out(src: &[f32]) -> Vec<f32> {
    use rayon::prelude::*;
    if src.len() < PARALLEL_COPY {
        return src.to_vec();
    }
    // Zeroed by `calloc`: pages the copy then writes once, not twice.
    let mut out = vec![0.0f32; src.len()];
    out.par_chunks_mut(PARALLEL_COPY)
        .zip(src.par_chunks(PARALLEL_COPY))
        .for_each(|(to, from)| to.copy_from_slice(from));
    out
}

/// [`NetOps::read_ahead`](crate::ops::NetOps::read_ahead) on the GPU: `x`'s values (row-major,
/// any shape) copied to the host behind the work recorded so far; the fusion stream is
/// drained so that the copy is queued now.
pub(crate) fn read_ahead(x: FloatTensor<Cuda>) -> ReadAhead {
    let client = x.client.clone();
    let slot: Slot = Arc::default();
    let marker = TensorIr::uninit(client.create_empty_handle(), Shape::new([1]), DType::F32);
    let streams = OperationStreams::with_inputs([&x]);
    let desc = CustomOpIr::new("minflow_read_ahead", &[x.into_ir()], &[marker]);
    let op = ReadOp {
        desc: desc.clone(),
        slot: slot.clone(),
    };
    let marker = client.register(streams, OperationIr::Custom(desc), op);
    // Executes what the stream holds (launches, no wait for the GPU), this read included,
    // and hands the launches and the copy's task to cubecl's device thread now (its channel
    // would hold a partial batch back until later work fills it). The marker, held until
    // the read has executed, is dropped here, on the thread that recorded it: the wait may
    // run on another (the node's lander thread).
    client.sync(|| ());
    drop(marker);
    let device = client.device().clone();
    flush_device(&device);
    // (ReadAhead's error is the message: its callers report it as text.)
    ReadAhead::new(move |parts| wait(&slot, &device, parts).map_err(|e| e.to_string()))
}
