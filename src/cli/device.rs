//! `--device`: where a command runs its model, shared by `train`, `eval`, `node` and the
//! benches that run a model (`bench train`, `node`, `rollout`, `gemm`, `transfer`; each
//! flattens [`DeviceArgs`]). `cpu` is burn's ndarray backend (the default, always built);
//! `cuda` or `cuda:N` is burn's CUDA backend on GPU N, in a build with the `cuda` feature
//! (docs/cuda.md); `cuda:0,cuda:1,...` lists several GPUs for data-parallel training (`train`
//! and `bench train`). Also the backend types of each device and the CUDA memory query the
//! training benchmark reports.

use anyhow::bail;
use clap::Args;

use crate::ops::cublas::GpuGemm;
use crate::ops::Kernels;

/// The `--device` flag.
#[derive(Debug, Clone, Args)]
pub struct DeviceArgs {
    /// Where the model runs: cpu | cuda | cuda:N | cuda:0,cuda:1 (data-parallel training:
    /// train and bench train only). CUDA needs a build with `--features cuda` (docs/cuda.md).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// The kernel for the large dense-layer products on a GPU: tf32 (cuBLAS on TF32 tensor
    /// cores, as cubecl's own f32 matmul) | fp32 (cuBLAS, full FP32) | cubecl (burn's
    /// matmul). Ignored on the CPU.
    #[arg(long, default_value = "tf32", value_parser = ["tf32", "fp32", "cubecl"])]
    pub gpu_gemm: String,
}

/// A parsed `--device`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Device {
    /// burn's ndarray backend, f32.
    Cpu,
    /// burn's CUDA backend, f32, on these GPU ordinals (at least one, no repeats).
    Cuda(Vec<usize>),
}

impl DeviceArgs {
    /// Validates the flags (a CUDA device in a build without the feature is an error).
    pub fn parse(&self) -> anyhow::Result<Device> {
        let device = parse(&self.device)?;
        self.gemm()?;
        Ok(device)
    }

    /// The kernel choices a GPU is opened with ([`cuda::device`]): `--gpu-gemm`, the rest
    /// as default. Call after [`DeviceArgs::parse`] (which checks the flag).
    pub fn kernels(&self) -> Kernels {
        Kernels {
            gemm: self.gemm().unwrap_or(Kernels::default().gemm),
            ..Kernels::default()
        }
    }

    fn gemm(&self) -> anyhow::Result<GpuGemm> {
        GpuGemm::parse(&self.gpu_gemm).ok_or_else(|| {
            anyhow::anyhow!(
                "--gpu-gemm {:?}: expected tf32 | fp32 | cubecl",
                self.gpu_gemm
            )
        })
    }
}

impl Device {
    /// The single CUDA ordinal of a command that runs on one device (`None` for the CPU);
    /// an error naming `command` for a list.
    pub fn single(&self, command: &str) -> anyhow::Result<Option<usize>> {
        match self {
            Device::Cpu => Ok(None),
            Device::Cuda(ids) if ids.len() == 1 => Ok(Some(ids[0])),
            Device::Cuda(ids) => {
                bail!(
                    "`{command}` runs on one device; got {} CUDA devices",
                    ids.len()
                )
            }
        }
    }
}

/// Parses `cpu`, `cuda`, `cuda:N` or a comma-separated list of CUDA devices.
pub fn parse(text: &str) -> anyhow::Result<Device> {
    let text = text.trim();
    if text == "cpu" {
        return Ok(Device::Cpu);
    }
    let mut ids = Vec::new();
    for part in text.split(',').map(str::trim) {
        let id = match part.strip_prefix("cuda") {
            Some("") => 0,
            Some(rest) => match rest.strip_prefix(':').map(str::parse::<usize>) {
                Some(Ok(id)) => id,
                _ => bail!("--device {text:?}: expected cuda:N with N a GPU ordinal, got {part:?}"),
            },
            None => bail!("--device {text:?}: expected cpu, cuda, cuda:N or cuda:0,cuda:1"),
        };
        if ids.contains(&id) {
            bail!("--device {text:?}: cuda:{id} given twice");
        }
        ids.push(id);
    }
    if !cfg!(feature = "cuda") {
        bail!(
            "--device {text}: this minflow was built without CUDA; rebuild with \
             `cargo build --release --features cuda` (docs/cuda.md)"
        );
    }
    Ok(Device::Cuda(ids))
}

/// The GPU the MLS-MPM solver runs on for a `--device` flag (`simulate`, `bench sim`): `None`
/// for `cpu`, else the one ordinal of `cuda` / `cuda:N`.
///
/// # Errors
/// As [`parse`]; a usage error for several GPUs (the solver batches scenes on one).
pub fn solver_gpu(text: &str) -> anyhow::Result<Option<usize>> {
    match parse(text)? {
        Device::Cpu => Ok(None),
        Device::Cuda(ids) if ids.len() == 1 => Ok(Some(ids[0])),
        Device::Cuda(_) => Err(super::UsageError(
            "--device: the GPU solver runs on one GPU (cuda or cuda:N)".into(),
        )
        .into()),
    }
}

/// burn's CUDA backend (feature `cuda`): backend types, devices, memory.
#[cfg(feature = "cuda")]
pub mod cuda {
    use burn::cubecl::Runtime;

    use crate::ops::Kernels;

    /// Inference backend: burn's CUDA backend (with fusion), f32.
    pub type CudaInfer = burn::backend::Cuda<f32, i32>;
    /// Training backend.
    pub type CudaTrain = burn::backend::Autodiff<CudaInfer>;
    /// A GPU.
    pub type CudaDevice = burn::backend::cuda::CudaDevice;

    /// GPU `index`, opened with `kernels` ([`crate::ops::cublas::open`]), after checking that
    /// the driver, NVRTC and (unless `--gpu-gemm cubecl`) cuBLAS load and that the driver has
    /// such a GPU (burn would panic deep inside its
    /// first kernel launch otherwise). Sets `CUDA_PATH` to
    /// `/usr/local/cuda` when it is unset and that folder exists: NVRTC compiles burn's
    /// kernels with the toolkit's headers.
    ///
    /// # Errors
    /// No `libcuda` (no NVIDIA driver), no `libnvrtc` or `libcublas`, a driver error, or
    /// `index` beyond the GPUs present.
    pub fn device(index: usize, kernels: Kernels) -> anyhow::Result<CudaDevice> {
        // SAFETY: only tries to open the library (libloading), calls nothing in it.
        if !unsafe { cudarc::driver::sys::is_culib_present() } {
            anyhow::bail!(
                "--device cuda:{index}: no NVIDIA driver here (libcuda could not be loaded); use --device cpu, or run on a machine with a GPU (docs/cuda.md)"
            );
        }
        // SAFETY: as above, for NVRTC.
        if !unsafe { cudarc::nvrtc::sys::is_culib_present() } {
            anyhow::bail!(
                "--device cuda:{index}: libnvrtc (the CUDA toolkit's run-time compiler) could not be loaded; install the toolkit or add its lib64 to LD_LIBRARY_PATH"
            );
        }
        let cublas_wanted = kernels.gemm != crate::ops::cublas::GpuGemm::Cubecl;
        // SAFETY: as above, for cuBLAS (the large products, `--gpu-gemm`).
        if cublas_wanted && !unsafe { cudarc::cublas::sys::is_culib_present() } {
            anyhow::bail!(
                "--device cuda:{index}: libcublas.so.13 could not be loaded; add the CUDA toolkit's lib64 to LD_LIBRARY_PATH, or run with --gpu-gemm cubecl"
            );
        }
        let count = cudarc::driver::CudaContext::device_count()
            .map_err(|e| anyhow::anyhow!("--device cuda:{index}: the CUDA driver failed: {e}"))?;
        if index >= count.max(0) as usize {
            anyhow::bail!("--device cuda:{index}: this machine has {count} GPU(s)");
        }
        if !crate::switches::cuda_path_set() && std::path::Path::new(DEFAULT_CUDA_PATH).is_dir() {
            // SAFETY: called before burn starts its threads (the first device is created after this).
            unsafe { std::env::set_var("CUDA_PATH", DEFAULT_CUDA_PATH) };
        }
        crate::ops::cublas::open(index, kernels);
        Ok(CudaDevice { index })
    }

    /// Where the CUDA toolkit usually lives.
    const DEFAULT_CUDA_PATH: &str = "/usr/local/cuda";

    /// [`device`] for each ordinal, in order.
    ///
    /// # Errors
    /// As [`device`].
    pub fn devices(ids: &[usize], kernels: Kernels) -> anyhow::Result<Vec<CudaDevice>> {
        ids.iter().map(|&i| device(i, kernels)).collect()
    }

    /// Bytes that cubecl's memory pool holds on `device` (it keeps freed pages for reuse,
    /// so after a step this is the step's high-water mark, rounded up to pages).
    pub fn reserved_bytes(device: &CudaDevice) -> Option<u64> {
        burn::cubecl::cuda::CudaRuntime::client(device)
            .memory_usage()
            .ok()
            .map(|u| u.bytes_reserved)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_cpu_and_rejects_junk() {
        assert_eq!(parse("cpu").unwrap(), Device::Cpu);
        assert!(parse("gpu").is_err());
        assert!(parse("cuda:x").is_err());
        assert!(parse("cuda:0,cuda:0").is_err());
    }

    #[test]
    fn parses_cuda_lists_only_with_the_feature() {
        let parsed = parse("cuda:0, cuda:1");
        if cfg!(feature = "cuda") {
            assert_eq!(parsed.unwrap(), Device::Cuda(vec![0, 1]));
            assert_eq!(parse("cuda").unwrap(), Device::Cuda(vec![0]));
            assert!(parse("cuda:0,cuda:1").unwrap().single("eval").is_err());
        } else {
            let err = parsed.unwrap_err().to_string();
            assert!(err.contains("--features cuda"), "{err}");
        }
    }
}
