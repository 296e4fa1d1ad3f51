//! The large dense-layer products of training on burn's CUDA backend through cuBLAS, as a
//! custom operation of burn's fusion layer. The choice of kernel ([`GpuGemm`], `--gpu-gemm`)
//! and the layout logic are always built; the CUDA side (`matmul`) with the feature `cuda`.
//!
//! Why: the paper's encoder spends most of a GPU training step in three
//! `[400,000 x 256] x [256 x 1,250]` products (forward, input gradient, weight gradient),
//! which cubek's default tiled TF32 kernel ran at ~36 TFLOP/s on an H200 (docs/cuda.md).
//! cuBLAS (`cublasSgemm`, NVIDIA cuBLAS Library, "cublas<t>gemm") is the kernel library
//! PyTorch calls for the same products; it picks tile shapes and split-K per shape.
//!
//! How: [`matmul`] records a `CustomOpIr` on the fusion stream, so it runs in order with the
//! fused kernels around it. When the stream reaches it, a fresh output is allocated and the
//! cuBLAS call is queued on cubecl's device thread like a kernel launch ([`on_device`]): there
//! the device pointers of the inputs and the output are read from cubecl's memory pool, and
//! `cublasSgemm` is enqueued on the CUDA stream that pool belongs to, the stream cubecl
//! launches this thread's kernels on (exposed by the vendored cubecl-cuda, vendor/README.md).
//! Every kernel queued before is launched first and every kernel after is launched after:
//! stream order does the rest, and the host waits for nothing. [`worth_it`] sends products of
//! at least 2^30 multiply-adds here; smaller ones stay with cubecl.
//!
//! [`GpuGemm`] picks the math: TF32 tensor cores (what cubek does for f32 products, and
//! PyTorch with `allow_tf32`), full FP32 (PyTorch's default), or cubecl's own kernel. It is a
//! setting of the GPU, like the math mode of the cuBLAS handle it becomes: [`open`] fixes a
//! GPU's [`Kernels`] when the command opens that device (`cli::device`), and the device's ops
//! read them back through [`kernels`] (the tensor knows its GPU). A GPU never opened runs the
//! defaults.

use std::collections::HashMap;
use std::sync::Mutex;

use super::Kernels;

/// Which kernel multiplies the large dense-layer products on the GPU (`--gpu-gemm`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GpuGemm {
    /// cuBLAS with TF32 tensor cores (`CUBLAS_TF32_TENSOR_OP_MATH`): inputs rounded to a
    /// 10-bit mantissa, products accumulated in f32, as cubek's f32 matmul does.
    Tf32,
    /// cuBLAS in full FP32 (`CUBLAS_DEFAULT_MATH`; PyTorch's default for f32).
    Fp32,
    /// cubecl's matmul (burn's own), with the split-K weight gradients of `ops::composed`.
    Cubecl,
}

impl GpuGemm {
    /// Parses `tf32 | fp32 | cubecl`; None for any other text.
    pub fn parse(text: &str) -> Option<Self> {
        match text {
            "tf32" => Some(Self::Tf32),
            "fp32" => Some(Self::Fp32),
            "cubecl" => Some(Self::Cubecl),
            _ => None,
        }
    }
}

/// The kernel choices of each GPU opened so far, by ordinal (written by [`open`] only).
static OPENED: Mutex<Option<HashMap<usize, Kernels>>> = Mutex::new(None);

/// Fixes GPU `index`'s kernel choices: called once per device by the command that opens it
/// (`cli::device::cuda::device`), before any of its tensors exist.
pub fn open(index: usize, kernels: Kernels) {
    let mut guard = OPENED.lock().unwrap_or_else(|e| e.into_inner());
    guard
        .get_or_insert_with(HashMap::new)
        .insert(index, kernels);
}

/// GPU `index`'s kernel choices: what [`open`] fixed, or the defaults.
pub fn kernels(index: usize) -> Kernels {
    let guard = OPENED.lock().unwrap_or_else(|e| e.into_inner());
    guard
        .as_ref()
        .and_then(|opened| opened.get(&index).copied())
        .unwrap_or_default()
}

/// Fewest multiply-adds (`m * k * n`) a product needs to go to cuBLAS (2^30: the paper
/// encoder's second layer, 1.3e11, goes; its first, 400,000 x 5 x 256 = 5.1e8, stays). Set
/// when each cuBLAS call read its three resources from the caller's thread, a host round trip
/// that stopped the host from running ahead of the GPU (now queued on cubecl's device
/// thread); where the host is the limit (minflow's default encoder) that cost more than
/// cuBLAS saved on the small products (`bench train`: default encoder, minGRU, T = 2, 6,752
/// -> 5,151 samples/s with the first layer on cuBLAS).
const MIN_MACS: usize = 1 << 30;

/// Whether a `[m, k] x [k, n]` product goes to cuBLAS under `gemm` (then it also splits its
/// long reductions itself: no row chunks needed for the weight gradients).
pub fn worth_it(gemm: GpuGemm, m: usize, k: usize, n: usize) -> bool {
    gemm != GpuGemm::Cubecl && m.saturating_mul(k).saturating_mul(n) >= MIN_MACS
}

/// How cuBLAS reads a row-major 2-D view: `(transposed, leading dimension)`, or None when it
/// is neither rows nor columns with unit stride (then it is copied contiguous first).
#[cfg_attr(not(feature = "cuda"), allow(dead_code))]
fn layout(shape: [usize; 2], strides: [usize; 2]) -> Option<(bool, usize)> {
    let [r, c] = shape;
    let [sr, sc] = strides;
    if (c == 1 || sc == 1) && (r == 1 || sr >= c) {
        return Some((false, if r == 1 { c } else { sr }.max(1)));
    }
    if (r == 1 || sr == 1) && (c == 1 || sc >= r) {
        return Some((true, if c == 1 { r } else { sc }.max(1)));
    }
    None
}

#[cfg(feature = "cuda")]
pub use gpu::matmul;
#[cfg(feature = "cuda")]
pub(crate) use gpu::{after_foreign, flush_device, on_device, primary_context};

/// The CUDA side: the fusion custom operation and the cuBLAS calls.
#[cfg(feature = "cuda")]
mod gpu {
    use super::{kernels, layout, worth_it, GpuGemm};
    use std::collections::HashMap;
    use std::sync::Mutex;

    use burn::cubecl::cuda::CudaRuntime;
    use burn::tensor::ops::FloatTensor;
    use burn::tensor::{DType, Shape, TensorMetadata};
    use burn_cubecl::tensor::CubeTensor;
    use burn_cubecl::CubeBackend;
    use burn_fusion::stream::{Operation, OperationStreams};
    use burn_fusion::FusionRuntime;
    use burn_ir::{CustomOpIr, HandleContainer, OperationIr, TensorIr};
    use cudarc::cublas::{result as cublas, sys as cublas_sys};
    use cudarc::driver::{result as driver, sys as driver_sys};

    /// The backend under burn's fusion layer for `Cuda<f32, i32>`.
    type Inner = CubeBackend<CudaRuntime, f32, i32, u8>;
    /// burn's CUDA backend with fusion (what `--device cuda` trains on).
    type Cuda = burn::backend::Cuda<f32, i32>;
    /// The fusion runtime of [`Inner`].
    type Runtime = <Inner as burn_fusion::FusionBackend>::FusionRuntime;

    /// `a @ b` for 2-D `a` `[m, k]` and `b` `[k, n]` -> `[m, n]` (contiguous), through cuBLAS when
    /// [`worth_it`], else burn's matmul. Either input may be a transposed view (as `w^T` and `x^T`
    /// in a dense layer's backward are); other strided views are made contiguous first.
    ///
    /// # Panics
    /// A cuBLAS or CUDA driver error (cuBLAS missing: `libcublas.so.13` not found) panics, as
    /// burn's own kernels do on a device error.
    pub fn matmul(a: FloatTensor<Cuda>, b: FloatTensor<Cuda>) -> FloatTensor<Cuda> {
        use burn::tensor::ops::FloatTensorOps;
        let (sa, sb) = (a.shape(), b.shape());
        assert!(
            sa.num_dims() == 2 && sb.num_dims() == 2 && sa[1] == sb[0],
            "cublas::matmul: [m, k] x [k, n], got {sa:?} x {sb:?}"
        );
        let (m, k, n) = (sa[0], sa[1], sb[1]);
        let gemm = kernels(a.client.device().index).gemm;
        if !worth_it(gemm, m, k, n) {
            return Cuda::float_matmul(a, b);
        }

        /// The recorded operation: inputs `[a, b]`, output `[c]`.
        #[derive(Debug)]
        struct Gemm {
            desc: CustomOpIr,
            gemm: GpuGemm,
        }

        impl Operation<Runtime> for Gemm {
            fn execute(
                &self,
                handles: &mut HandleContainer<<Runtime as FusionRuntime>::FusionHandle>,
            ) {
                let ([a, b], [c]) = self.desc.as_fixed();
                let a = handles.get_float_tensor::<Inner>(a);
                let b = handles.get_float_tensor::<Inner>(b);
                let out = gemm_cube(a, b, self.gemm);
                handles.register_float_tensor::<Inner>(&c.id, out);
            }
        }

        let client = a.client.clone();
        let streams = OperationStreams::with_inputs([&a, &b]);
        let out = TensorIr::uninit(client.create_empty_handle(), Shape::new([m, n]), DType::F32);
        let desc = CustomOpIr::new("minflow_cublas_sgemm", &[a.into_ir(), b.into_ir()], &[out]);
        client
            .register(
                streams,
                OperationIr::Custom(desc.clone()),
                Gemm { desc, gemm },
            )
            .remove(0)
    }

    /// A 2-D CubeTensor's shape and strides.
    fn dims(t: &CubeTensor<CudaRuntime>) -> ([usize; 2], [usize; 2]) {
        let (shape, strides) = (t.meta.shape(), t.meta.strides());
        ([shape[0], shape[1]], [strides[0], strides[1]])
    }

    /// The view cuBLAS reads for `t`, copying it contiguous when it has no such layout.
    fn readable(t: CubeTensor<CudaRuntime>) -> (CubeTensor<CudaRuntime>, bool, usize) {
        let (shape, strides) = dims(&t);
        if let Some((trans, ld)) = layout(shape, strides) {
            return (t, trans, ld);
        }
        let t = burn_cubecl::kernel::into_contiguous(t);
        let (shape, strides) = dims(&t);
        let (trans, ld) = layout(shape, strides).expect("a contiguous tensor is row-major");
        (t, trans, ld)
    }

    /// One cuBLAS handle per GPU, the stream it is bound to, and the GPU's primary context (the
    /// one cubecl uses). Process-wide, behind a lock (data-parallel workers are new threads
    /// every step; a handle per thread would be created and leaked per step).
    struct Blas {
        handle: cublas_sys::cublasHandle_t,
        stream: driver_sys::CUstream,
        ctx: driver_sys::CUcontext,
        math: Option<GpuGemm>,
    }

    // SAFETY: the handle and context are plain driver handles; every use holds `BLAS`'s lock and
    // makes the context current on the calling thread first.
    unsafe impl Send for Blas {}

    static BLAS: Mutex<Option<HashMap<usize, Blas>>> = Mutex::new(None);

    /// Runs `f` with GPU `index`'s cuBLAS handle, its math mode set for `gemm` and bound to
    /// `stream`, the GPU's context current on this thread.
    fn with_blas<T>(
        index: usize,
        gemm: GpuGemm,
        stream: driver_sys::CUstream,
        f: impl FnOnce(cublas_sys::cublasHandle_t) -> T,
    ) -> T {
        let mut guard = BLAS.lock().unwrap_or_else(|e| e.into_inner());
        let map = guard.get_or_insert_with(HashMap::new);
        let blas = map.entry(index).or_insert_with(|| {
            let ctx = primary_context(index);
            let handle = cublas::create_handle().unwrap_or_else(|e| {
                panic!("cuBLAS handle ({e:?}); is libcublas.so.13 on the library path?")
            });
            Blas {
                handle,
                stream: std::ptr::null_mut(),
                ctx,
                math: None,
            }
        });
        // SAFETY: the context and handle were created above and are alive.
        unsafe {
            driver::ctx::set_current(blas.ctx).expect("CUDA context");
            if blas.math != Some(gemm) {
                let mode = match gemm {
                    GpuGemm::Tf32 => cublas_sys::cublasMath_t::CUBLAS_TF32_TENSOR_OP_MATH,
                    _ => cublas_sys::cublasMath_t::CUBLAS_DEFAULT_MATH,
                };
                cublas_sys::cublasSetMathMode(blas.handle, mode)
                    .result()
                    .expect("cuBLAS math mode");
                blas.math = Some(gemm);
            }
            if blas.stream != stream {
                // (Resets cuBLAS's workspace to its default pool: done only on a change.)
                cublas::set_stream(blas.handle, stream as _).expect("cuBLAS stream");
                blas.stream = stream;
            }
        }
        f(blas.handle)
    }

    /// GPU `index`'s primary context (the one cubecl uses), retained again and made current
    /// on this thread: what a library handle of the GPU is created in. Never released: the
    /// handles live as long as the process.
    pub(crate) fn primary_context(index: usize) -> driver_sys::CUcontext {
        // SAFETY: driver FFI on a valid ordinal.
        unsafe {
            let dev = driver::device::get(index as i32).expect("CUDA device");
            let ctx = driver::primary_ctx::retain(dev).expect("CUDA primary context");
            driver::ctx::set_current(ctx).expect("CUDA context");
            ctx
        }
    }

    /// cubecl's CUDA compute server: the service that owns a GPU's memory pools and launches
    /// its kernels, from a device thread of its own.
    type Server = <CudaRuntime as burn::cubecl::Runtime>::Server;

    /// A device pointer and the CUDA stream of the memory pool it comes from.
    pub(crate) type Resource = (u64, driver_sys::CUstream);

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
    /// # Panics
    /// On the device thread, when a tensor's memory cannot be read (a cubecl error). A panic
    /// in `f` (a library error) aborts the process: the output would never be written.
    pub(crate) fn on_device(
        tensors: Vec<CubeTensor<CudaRuntime>>,
        f: impl FnOnce(&[Resource]) + Send + 'static,
    ) {
        use burn::cubecl::device::Device;
        use burn::cubecl::device_handle::DeviceHandle;
        use burn::cubecl::server::ComputeServer;
        use burn::cubecl::stream_id::StreamId;
        let device = tensors[0].device.to_id();
        DeviceHandle::<Server>::new(device).submit(move |server: &mut Server| {
            let stream = StreamId::current();
            let resources: Vec<_> = tensors
                .iter()
                .map(|t| {
                    server
                        .get_resource(t.handle.clone().binding(), stream)
                        .expect("cubecl resource")
                })
                .collect();
            let pointers: Vec<Resource> = resources
                .iter()
                .map(|r| (r.resource().ptr, r.resource().stream))
                .collect();
            // A failure here would otherwise be caught by cubecl's device thread and only
            // logged, and the output, never written, read as a result: stop the process, as
            // a failed call on the caller's thread did.
            let call = std::panic::AssertUnwindSafe(|| f(&pointers));
            if let Err(e) = std::panic::catch_unwind(call) {
                let why = (e.downcast_ref::<String>().map(String::as_str))
                    .or_else(|| e.downcast_ref::<&str>().copied())
                    .unwrap_or("a panic");
                tracing::error!("a cuBLAS / cuDNN call failed on the device thread: {why}");
                eprintln!("minflow: a cuBLAS / cuDNN call failed on the device thread: {why}");
                std::process::abort();
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
    pub(crate) fn flush_device(device: &burn::backend::cuda::CudaDevice) {
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
    /// # Safety
    /// The streams are live CUDA streams of the current context.
    pub(crate) unsafe fn after_foreign(
        stream: driver_sys::CUstream,
        inputs: &[driver_sys::CUstream],
    ) {
        let mut done: Vec<driver_sys::CUstream> = Vec::new();
        for &other in inputs {
            if other == stream || done.contains(&other) {
                continue;
            }
            done.push(other);
            static SEEN: std::sync::Once = std::sync::Once::new();
            SEEN.call_once(|| tracing::debug!("a library kernel read an input of another stream"));
            let flags = driver_sys::CUevent_flags::CU_EVENT_DISABLE_TIMING;
            let event = driver::event::create(flags).expect("CUDA event");
            driver::event::record(event, stream).expect("CUDA event record");
            let wait = driver_sys::CUevent_wait_flags::CU_EVENT_WAIT_DEFAULT;
            driver::stream::wait_event(other, event, wait).expect("CUDA stream wait");
            // Released by the driver once the wait is done.
            driver::event::destroy(event).expect("CUDA event");
        }
    }

    /// `a @ b` on cubecl tensors through `cublasSgemm` (row-major `C = A B` as the column-major
    /// `C^T = B^T A^T`), enqueued on cubecl's stream.
    fn gemm_cube(
        a: CubeTensor<CudaRuntime>,
        b: CubeTensor<CudaRuntime>,
        gemm: GpuGemm,
    ) -> CubeTensor<CudaRuntime> {
        let (a, a_trans, lda) = readable(a);
        let (b, b_trans, ldb) = readable(b);
        let ([m, k], _) = dims(&a);
        let n = dims(&b).0[1];
        let client = a.client.clone();
        let out = burn_cubecl::ops::numeric::empty_device_contiguous_dtype(
            client.clone(),
            a.device.clone(),
            Shape::new([m, n]),
            DType::F32,
        );
        let index = a.device.index;
        let int = |v: usize| i32::try_from(v).expect("cuBLAS dimension fits i32");
        let (m, k, n, lda, ldb) = (int(m), int(k), int(n), int(lda), int(ldb));
        let op = |t: bool| match t {
            true => cublas_sys::cublasOperation_t::CUBLAS_OP_T,
            false => cublas_sys::cublasOperation_t::CUBLAS_OP_N,
        };
        let (op_a, op_b) = (op(a_trans), op(b_trans));
        // The output was just allocated from this thread's pool: its stream is the one cubecl
        // launches on for this thread.
        on_device(vec![a, b, out.clone()], move |r| {
            let [(pa, sa), (pb, sb), (pc, stream)] = [r[0], r[1], r[2]];
            with_blas(index, gemm, stream, |handle| {
                let (alpha, beta) = (1.0f32, 0.0f32);
                // SAFETY: the pointers are live allocations of the tensors `on_device` holds,
                // of the sizes the dimensions and leading dimensions describe (checked by
                // `layout`). The product is enqueued on the stream cubecl writes them on, in
                // order with cubecl's launches; their memory returns to the pool after it.
                unsafe {
                    cublas::sgemm(
                        handle,
                        op_b,
                        op_a,
                        n,
                        m,
                        k,
                        &alpha,
                        pb as *const f32,
                        ldb,
                        pa as *const f32,
                        lda,
                        &beta,
                        pc as *mut f32,
                        n,
                    )
                    .expect("cublasSgemm");
                    after_foreign(stream, &[sa, sb]);
                }
            })
        });
        out
    }
}

#[cfg(test)]
mod tests {
    use super::{kernels, layout, open, worth_it, GpuGemm, Kernels};

    #[test]
    fn the_flag_parses_and_picks_the_large_products() {
        assert_eq!(GpuGemm::parse("tf32"), Some(GpuGemm::Tf32));
        assert_eq!(GpuGemm::parse("fp32"), Some(GpuGemm::Fp32));
        assert_eq!(GpuGemm::parse("fp16"), None);
        // The paper encoder's second layer goes to cuBLAS, its first stays with cubecl.
        assert!(worth_it(GpuGemm::Fp32, 400_000, 256, 1250));
        assert!(!worth_it(GpuGemm::Fp32, 400_000, 5, 256));
        assert!(!worth_it(GpuGemm::Cubecl, 400_000, 256, 1250));
    }

    #[test]
    fn each_gpu_keeps_the_choices_it_was_opened_with() {
        let fp32 = Kernels {
            gemm: GpuGemm::Fp32,
            split_weight_grad: false,
        };
        open(7, fp32);
        assert_eq!(kernels(7), fp32);
        assert_eq!(
            kernels(8),
            Kernels::default(),
            "a GPU never opened runs the defaults"
        );
        assert_eq!(Kernels::default().gemm, GpuGemm::Tf32);
    }

    #[test]
    fn layouts_of_rows_columns_and_neither() {
        assert_eq!(layout([4, 3], [3, 1]), Some((false, 3)));
        assert_eq!(layout([4, 3], [8, 1]), Some((false, 8)), "pitched rows");
        assert_eq!(layout([3, 4], [1, 3]), Some((true, 3)), "transposed view");
        assert_eq!(layout([1, 5], [0, 1]), Some((false, 5)));
        assert_eq!(layout([5, 1], [1, 0]), Some((false, 1)));
        assert_eq!(layout([4, 3], [0, 1]), None, "broadcast rows");
        assert_eq!(layout([4, 3], [6, 2]), None, "strided columns");
    }
}
