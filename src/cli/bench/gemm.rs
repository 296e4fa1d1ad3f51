//! `minflow bench gemm --device cuda`: the three large products of a GPU training step of the
//! paper's encoder (its second layer; batch 80 x T 2 x 2,500 particles = 400,000 rows), each
//! with cubecl's matmul and with cuBLAS in TF32 and FP32 (`--gpu-gemm`; the first layer's
//! products, under 2^30 multiply-adds, always run on cubecl): milliseconds, TFLOP/s, and the
//! largest difference from cuBLAS FP32 relative to the largest FP32 entry. The difference
//! column is also the check that the cuBLAS path reads transposed views right: a wrong layout
//! differs by O(1), TF32 rounding by ~1e-3.

use crate::cli::device::DeviceArgs;
use crate::cli::Outcome;
use clap::Args;

/// Flags of `bench gemm`.
#[derive(Debug, Args)]
pub struct GemmBenchArgs {
    /// Rows of the per-particle products (samples x T x particles).
    #[arg(long, default_value_t = 400_000)]
    rows: usize,
    /// Encoder hidden width (the first layer's output, the second's input).
    #[arg(long, default_value_t = 256)]
    hidden: usize,
    /// Encoder output width W.
    #[arg(long, default_value_t = 1250)]
    width: usize,
    /// Timed repetitions of each product (after one untimed).
    #[arg(long, default_value_t = 10)]
    reps: usize,
    #[command(flatten)]
    device: DeviceArgs,
}

/// Runs the table (CUDA builds only).
///
/// # Errors
/// A CPU device, a build without `cuda`, or no usable GPU.
pub fn run(args: GemmBenchArgs) -> anyhow::Result<Outcome> {
    let device = args.device.parse()?;
    #[cfg(feature = "cuda")]
    {
        let Some(index) = device.single("bench gemm")? else {
            anyhow::bail!("bench gemm measures GPU products: give --device cuda[:N]");
        };
        cuda::table(
            &args,
            index,
            crate::cli::device::cuda::device(index, args.device.kernels())?,
        )
    }
    #[cfg(not(feature = "cuda"))]
    {
        let _ = device;
        anyhow::bail!("bench gemm needs --device cuda (a build with --features cuda)")
    }
}

#[cfg(feature = "cuda")]
mod cuda {
    use super::{GemmBenchArgs, Outcome};
    use crate::cli::device::cuda::{CudaDevice, CudaInfer};
    use crate::ops::cublas::{kernels, open, GpuGemm};
    use crate::ops::Kernels;
    use crate::ops::NetOps;
    use burn::tensor::backend::Backend;
    use burn::tensor::{Distribution, ElementConversion, Tensor, TensorPrimitive};
    use std::time::Instant;

    type T2 = Tensor<CudaInfer, 2>;

    /// `a @ b` through the training path's product ([`NetOps::matmul`]).
    fn product(a: &T2, b: &T2) -> T2 {
        let p = |t: &T2| t.clone().into_primitive().tensor();
        Tensor::from_primitive(TensorPrimitive::Float(CudaInfer::matmul(p(a), p(b))))
    }

    /// Times each product under each kernel: GPU `index` is reopened with that kernel
    /// ([`open`]) before its products, and with the flags' choice again at the end.
    pub(super) fn table(
        args: &GemmBenchArgs,
        index: usize,
        device: CudaDevice,
    ) -> anyhow::Result<Outcome> {
        let chosen = kernels(index);
        let with = |gemm| open(index, Kernels { gemm, ..chosen });
        let (rows, hidden, width) = (args.rows, args.hidden, args.width);
        let rand = |r, c| T2::random([r, c], Distribution::Uniform(-1.0, 1.0), &device);
        let x = rand(rows, hidden);
        let w = rand(hidden, width);
        let g = rand(rows, width);
        // (name, lhs, rhs): the transposed operands are views, as in the backward.
        let cases: Vec<(&str, T2, T2)> = vec![
            ("layer 2 forward  x w", x.clone(), w.clone()),
            ("layer 2 dx       g w^T", g.clone(), w.transpose()),
            ("layer 2 dw       x^T g", x.transpose(), g),
        ];
        println!(
            "rows {rows}, hidden {hidden}, width {width}, {} reps, {}",
            args.reps,
            CudaInfer::name(&device)
        );
        println!(
            "{:<24} {:>22} {:>7} {:>9} {:>9} {:>12}",
            "product", "[m x k] x [k x n]", "kernel", "ms", "TFLOP/s", "rel. diff"
        );
        for (name, a, b) in &cases {
            let ([m, k], n) = (a.dims(), b.dims()[1]);
            with(GpuGemm::Fp32);
            let reference = product(a, b);
            // Reductions on the GPU: downloading a [400,000 x 1,250] product is slow.
            let largest = |t: T2| t.abs().max().into_scalar().elem::<f32>();
            let scale = largest(reference.clone()).max(1e-30);
            for (label, gemm) in [
                ("cubecl", GpuGemm::Cubecl),
                ("tf32", GpuGemm::Tf32),
                ("fp32", GpuGemm::Fp32),
            ] {
                with(gemm);
                let diff = largest(product(a, b) - reference.clone());
                // One untimed run of exactly the timed graph (a lone product compiles to
                // another kernel than the product fused with the subtraction above).
                let mut last = product(a, b);
                CudaInfer::sync(&device)?;
                let start = Instant::now();
                for _ in 0..args.reps.max(1) {
                    last = product(a, b);
                }
                CudaInfer::sync(&device)?;
                let ms = start.elapsed().as_secs_f64() * 1e3 / args.reps.max(1) as f64;
                drop(last);
                let tflops = 2.0 * (m * k * n) as f64 / (ms * 1e-3) / 1e12;
                println!(
                    "{:<24} {:>22} {:>7} {:>9.3} {:>9.1} {:>12.2e}",
                    name,
                    format!("[{m} x {k}] x [{k} x {n}]"),
                    label,
                    ms,
                    tflops,
                    diff / scale
                );
            }
        }
        open(index, chosen);
        Ok(Outcome::Done)
    }
}
