//! cuDNN's calls for the grid model's 3x3 convolutions on CUDA (feature `cuda`; what they
//! are and why: `cuda/net/cudnn.rs`): one handle per GPU, bound to cubecl's stream; the plans
//! (`cuda/net/cudnn_plan.rs`) made once per GPU and shape and kept with the handle; and [`run`],
//! which queues a recorded convolution's calls on cubecl's device thread (`cuda/device.rs`'s
//! `on_device`), so the host does not wait. Every failing call is an [`OpsError`].

use std::collections::hash_map::Entry;
use std::collections::HashMap;
use std::sync::Mutex;

use burn::cubecl::cuda::CudaRuntime;
use burn::tensor::{DType, Shape};
use burn_cubecl::tensor::CubeTensor;
use cudarc::cudnn::{result as dnn, sys};
use cudarc::driver::{result as driver, sys as driver_sys};

use super::cudnn_plan::{check, plan, Algo, Dims, Key, Pass, Plan};
use crate::ops::cublas::{kernels, GpuGemm};
use crate::ops::cuda::device::{after_foreign, on_device, primary_context, Resource};
use crate::ops::OpsError;

/// One cuDNN handle per GPU, the stream it is bound to, the GPU's primary context (cubecl's),
/// and the plans made so far.
struct Dnn {
    handle: sys::cudnnHandle_t,
    stream: driver_sys::CUstream,
    ctx: driver_sys::CUcontext,
    plans: HashMap<Key, Plan>,
}

// SAFETY: the handle, context and descriptors are plain library handles; every use holds
// `DNN`'s lock and makes the context current on the calling thread first.
unsafe impl Send for Dnn {}

static DNN: Mutex<Option<HashMap<usize, Dnn>>> = Mutex::new(None);

impl Dnn {
    /// GPU `index`'s handle, made in its primary context.
    ///
    /// # Errors
    /// The context's, or cuDNN's (`libcudnn.so.9` missing or not starting).
    fn new(index: usize) -> Result<Self, OpsError> {
        let ctx = primary_context(index)?;
        let handle = dnn::create_handle()
            .map_err(|e| OpsError::cudnn("handle (is libcudnn.so.9 on the library path?)", e))?;
        Ok(Dnn {
            handle,
            stream: std::ptr::null_mut(),
            ctx,
            plans: HashMap::new(),
        })
    }
}

/// Runs `f` with GPU `index`'s cuDNN handle (created on first use), its context current on
/// this thread.
///
/// # Errors
/// The handle's, the context's, or `f`'s.
fn with_dnn<T>(
    index: usize,
    f: impl FnOnce(&mut Dnn) -> Result<T, OpsError>,
) -> Result<T, OpsError> {
    let mut guard = DNN.lock().unwrap_or_else(|e| e.into_inner());
    let map = guard.get_or_insert_with(HashMap::new);
    let dnn = match map.entry(index) {
        Entry::Occupied(entry) => entry.into_mut(),
        Entry::Vacant(entry) => entry.insert(Dnn::new(index)?),
    };
    // SAFETY: the context was retained when the handle was made and is never released.
    unsafe { driver::ctx::set_current(dnn.ctx) }.map_err(|e| OpsError::driver("context", e))?;
    f(dnn)
}

/// Makes GPU `index`'s cuDNN handle, if not made yet: whether cuDNN starts there.
///
/// # Errors
/// The handle's or the context's.
pub(in crate::ops) fn start(index: usize) -> Result<(), OpsError> {
    with_dnn(index, |_| Ok(()))
}

/// The plans of `keys` on GPU `index`, made where missing (cuDNN times its algorithms then,
/// once per shape): the largest workspace they need, in bytes.
///
/// # Errors
/// The handle's, or [`plan`]'s.
fn planned(index: usize, keys: &[Key]) -> Result<usize, OpsError> {
    with_dnn(index, |dnn| {
        let handle = dnn.handle;
        let mut most = 0;
        for &key in keys {
            let plan = match dnn.plans.entry(key) {
                Entry::Occupied(entry) => entry.into_mut(),
                // SAFETY: the handle is alive and its context current (`with_dnn`).
                Entry::Vacant(entry) => entry.insert(unsafe { plan(handle, key)? }),
            };
            most = most.max(plan.workspace);
        }
        Ok(most)
    })
}

/// Runs the sum of `pass` over `dims.len()` passes (with the filter flipped where `flip`
/// says) on the contiguous cubecl tensors `inputs` (two a pass, see [`Pass`]); returns the
/// new contiguous output. Each shape's plan is made here on first use ([`planned`]); the
/// convolutions themselves are queued on cubecl's device thread ([`on_device`], [`enqueue`]),
/// which enqueues them on cubecl's stream in order with its kernels, so the host does not
/// wait.
///
/// # Errors
/// The handle's or a plan's; a failed convolution ends the process on the device thread
/// ([`on_device`]).
pub(in crate::ops) fn run(
    pass: Pass,
    flip: bool,
    dims: &[Dims],
    inputs: Vec<CubeTensor<CudaRuntime>>,
) -> Result<CubeTensor<CudaRuntime>, OpsError> {
    let (client, device) = (inputs[0].client.clone(), inputs[0].device.clone());
    let index = device.index;
    let tf32 = kernels(index).gemm == GpuGemm::Tf32;
    let keys: Vec<Key> = dims.iter().map(|&d| (pass, d, tf32, flip)).collect();
    let empty = |shape: Shape| {
        burn_cubecl::ops::numeric::empty_device_contiguous_dtype(
            client.clone(),
            device.clone(),
            shape,
            DType::F32,
        )
    };
    let out = empty(pass.out_shape(dims[0]));
    let workspace = planned(index, &keys)?;
    // (A workspace of at least one float: the task's tensors are the inputs, out, workspace.)
    let workspace = empty(Shape::new([workspace.div_ceil(4).max(1)]));
    let mut tensors = inputs;
    tensors.extend([out.clone(), workspace]);
    on_device(tensors, "cuDNN convolution", move |r| {
        enqueue(index, &keys, r)
    });
    Ok(out)
}

/// On cubecl's device thread: binds GPU `index`'s handle to the output's stream and enqueues
/// the convolution of each of `keys` on it, the first writing the output and the others
/// adding to it (cuDNN's `beta` = 1). `r`: the inputs' resources, two a pass, then the
/// output's and the workspace's.
///
/// # Errors
/// The handle's, the stream's, a convolution's, or [`after_foreign`]'s.
fn enqueue(index: usize, keys: &[Key], r: &[Resource]) -> Result<(), OpsError> {
    let [(py, stream), (pw, _)] = [r[r.len() - 2], r[r.len() - 1]];
    with_dnn(index, |dnn| {
        if dnn.stream != stream {
            // SAFETY: a live handle and a live stream of its context.
            check("stream", unsafe {
                dnn::set_stream(dnn.handle, stream as _)
            })?;
            dnn.stream = stream;
        }
        for (i, key) in keys.iter().enumerate() {
            let [(pa, sa), (pb, sb)] = [r[2 * i], r[2 * i + 1]];
            let beta = if i == 0 { 0.0 } else { 1.0 };
            // SAFETY: the handle and plan were made by `with_dnn` and `planned` and are alive;
            // the pointers are live allocations of the tensors `on_device` holds, of the
            // sizes the plan's descriptors give (the inputs contiguous, as `ConvOp` made
            // them), and `stream` is the one cubecl writes them on; the foreign streams are
            // live streams of the context.
            unsafe {
                convolve(dnn.handle, &dnn.plans[key], [pa, pb, py, pw], beta)?;
                after_foreign(stream, &[sa, sb])?;
            }
        }
        Ok(())
    })
}

/// Enqueues one convolution of `plan` on the handle's stream: the pass of its algorithm on
/// the inputs at `pa`, `pb` (see [`Pass`]), into the output at `py` (scaled by `beta`
/// first), with the workspace at `pw`. The kernel runs in order with cubecl's launches; the
/// memory, and the workspace's, returns to the pool after it.
///
/// # Errors
/// cuDNN's.
///
/// # Safety
/// As [`enqueue`] says: a live handle bound to the stream the pointers are written on, a
/// live plan, and live allocations of its descriptors' sizes (the workspace of at least the
/// plan's bytes).
unsafe fn convolve(
    handle: sys::cudnnHandle_t,
    plan: &Plan,
    [pa, pb, py, pw]: [u64; 4],
    beta: f32,
) -> Result<(), OpsError> {
    let ws = pw as *mut std::ffi::c_void;
    let alpha = 1.0f32;
    let (alpha, beta) = (&alpha as *const f32 as _, &beta as *const f32 as _);
    let (pa, pb, py) = (pa as *const _, pb as *const _, py as *mut _);
    let r = match plan.algo {
        Algo::Forward(algo) => dnn::convolution_forward(
            handle,
            alpha,
            plan.x,
            pa,
            plan.w,
            pb,
            plan.conv,
            algo,
            ws,
            plan.workspace,
            beta,
            plan.y,
            py,
        ),
        Algo::Data(algo) => dnn::convolution_backward_data(
            handle,
            alpha,
            plan.w,
            pb,
            plan.y,
            pa,
            plan.conv,
            algo,
            ws,
            plan.workspace,
            beta,
            plan.x,
            py,
        ),
        Algo::Filter(algo) => dnn::convolution_backward_filter(
            handle,
            alpha,
            plan.x,
            pa,
            plan.y,
            pb,
            plan.conv,
            algo,
            ws,
            plan.workspace,
            beta,
            plan.w,
            py,
        ),
    };
    check("convolution", r)
}
