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
//! cuBLAS call is queued on cubecl's device thread like a kernel launch (`cuda/device.rs`'s
//! `on_device`, which cuDNN's calls and the read back share): there
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

/// The CUDA side: the fusion custom operation and the cuBLAS calls.
#[cfg(feature = "cuda")]
mod gpu {
    use super::{kernels, layout, worth_it, GpuGemm};
    use std::collections::hash_map::Entry;
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

    use crate::ops::cuda::device::{after_foreign, on_device, primary_context};
    use crate::ops::OpsError;

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
    /// The operands are not `[m, k] x [k, n]`. A cuBLAS or CUDA driver error (cuBLAS missing:
    /// `libcublas.so.13` not found) is raised ([`OpsError::raise`]) where the product runs, as
    /// burn's own kernels panic on a device error.
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

    /// The recorded product of [`matmul`]: inputs `[a, b]`, output `[c]`.
    #[derive(Debug)]
    struct Gemm {
        desc: CustomOpIr,
        gemm: GpuGemm,
    }

    impl Operation<Runtime> for Gemm {
        fn execute(&self, handles: &mut HandleContainer<<Runtime as FusionRuntime>::FusionHandle>) {
            let ([a, b], [c]) = self.desc.as_fixed();
            let a = handles.get_float_tensor::<Inner>(a);
            let b = handles.get_float_tensor::<Inner>(b);
            let out = gemm_cube(a, b, self.gemm).unwrap_or_else(|e| e.raise("cuBLAS product"));
            handles.register_float_tensor::<Inner>(&c.id, out);
        }
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

    impl Blas {
        /// GPU `index`'s handle, made in its primary context.
        ///
        /// # Errors
        /// The context's, or cuBLAS's (`libcublas.so.13` missing, no memory).
        fn new(index: usize) -> Result<Self, OpsError> {
            let ctx = primary_context(index)?;
            let handle = cublas::create_handle().map_err(|e| {
                OpsError::cublas("handle (is libcublas.so.13 on the library path?)", e)
            })?;
            Ok(Blas {
                handle,
                stream: std::ptr::null_mut(),
                ctx,
                math: None,
            })
        }

        /// Makes the context current, and sets the math mode for `gemm` and the stream where
        /// they changed.
        ///
        /// # Safety
        /// `stream` is a live stream of the handle's context.
        unsafe fn bind(
            &mut self,
            gemm: GpuGemm,
            stream: driver_sys::CUstream,
        ) -> Result<(), OpsError> {
            driver::ctx::set_current(self.ctx).map_err(|e| OpsError::driver("context", e))?;
            if self.math != Some(gemm) {
                let mode = match gemm {
                    GpuGemm::Tf32 => cublas_sys::cublasMath_t::CUBLAS_TF32_TENSOR_OP_MATH,
                    _ => cublas_sys::cublasMath_t::CUBLAS_DEFAULT_MATH,
                };
                (cublas_sys::cublasSetMathMode(self.handle, mode).result())
                    .map_err(|e| OpsError::cublas("math mode", e))?;
                self.math = Some(gemm);
            }
            if self.stream != stream {
                // (Resets cuBLAS's workspace to its default pool: done only on a change.)
                cublas::set_stream(self.handle, stream as _)
                    .map_err(|e| OpsError::cublas("stream", e))?;
                self.stream = stream;
            }
            Ok(())
        }
    }

    /// Runs `f` with GPU `index`'s cuBLAS handle (made on first use), its math mode set for
    /// `gemm` and bound to `stream`, the GPU's context current on this thread.
    ///
    /// # Errors
    /// The handle's, its binding's, or `f`'s.
    fn with_blas<T>(
        index: usize,
        gemm: GpuGemm,
        stream: driver_sys::CUstream,
        f: impl FnOnce(cublas_sys::cublasHandle_t) -> Result<T, OpsError>,
    ) -> Result<T, OpsError> {
        let mut guard = BLAS.lock().unwrap_or_else(|e| e.into_inner());
        let map = guard.get_or_insert_with(HashMap::new);
        let blas = match map.entry(index) {
            Entry::Occupied(entry) => entry.into_mut(),
            Entry::Vacant(entry) => entry.insert(Blas::new(index)?),
        };
        // SAFETY: the context and handle were created by `Blas::new` and are alive; `stream`
        // is the live stream cubecl's pool gave the output.
        unsafe { blas.bind(gemm, stream)? };
        f(blas.handle)
    }

    /// `a @ b` on cubecl tensors through `cublasSgemm` (row-major `C = A B` as the column-major
    /// `C^T = B^T A^T`), enqueued on cubecl's stream.
    ///
    /// # Errors
    /// A size that does not fit cuBLAS's `i32`; the library's errors end the process on the
    /// device thread ([`on_device`]).
    fn gemm_cube(
        a: CubeTensor<CudaRuntime>,
        b: CubeTensor<CudaRuntime>,
        gemm: GpuGemm,
    ) -> Result<CubeTensor<CudaRuntime>, OpsError> {
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
        let int = |v: usize| OpsError::fit_i32("cuBLAS dimension", v);
        let (m, k, n, lda, ldb) = (int(m)?, int(k)?, int(n)?, int(lda)?, int(ldb)?);
        let op = |t: bool| match t {
            true => cublas_sys::cublasOperation_t::CUBLAS_OP_T,
            false => cublas_sys::cublasOperation_t::CUBLAS_OP_N,
        };
        let (op_a, op_b) = (op(a_trans), op(b_trans));
        // The output was just allocated from this thread's pool: its stream is the one cubecl
        // launches on for this thread.
        on_device(vec![a, b, out.clone()], "cuBLAS product", move |r| {
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
                    .map_err(|e| OpsError::cublas("sgemm", e))?;
                    after_foreign(stream, &[sa, sb])
                }
            })
        });
        Ok(out)
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
