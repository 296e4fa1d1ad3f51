//! `minflow bench transfer --device cuda`: the grid model's particle-grid transfers on a GPU,
//! P2G and G2P, in their two forms (`model::grid::transfer`): the separable dense products
//! (`MINFLOW_CUDA_TRANSFERS=dense`) and the sparse kernels of `ops/cuda/net/stencil.rs`. Prints,
//! first, the check against the CPU backend (whose stencil and transfers are tested against
//! `stencil_host`): a small batch's stencil (nodes and weights), then P2G and G2P of random
//! values in each form and from each stencil (the CPU's, uploaded; the GPU's kernel; burn's
//! composed tensor operations), as the largest difference relative to the largest entry (f32
//! rounding is ~1e-6; a wrong node or layout is O(1)); then milliseconds a transfer at the
//! node's size (`--scenes` x `--particles` on an `--grid`^2 grid, `--channels` values
//! splatted, `--latent` gathered), the two forms' difference there, and whether the sparse
//! P2G gives the same bits again and with each scene's particles in reverse order.

use crate::cli::device::DeviceArgs;
use crate::cli::Outcome;
use clap::Args;

/// Flags of `bench transfer`.
#[derive(Debug, Args)]
pub struct TransferBenchArgs {
    /// Scenes in one call (B).
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u32).range(1..=4096))]
    scenes: u32,
    /// Particles per scene (N).
    #[arg(long, default_value_t = 2500, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    particles: u32,
    /// Grid size n (n x n nodes).
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u32).range(8..=512))]
    grid: u32,
    /// Values per particle that P2G splats (`all-grid-mingru`: 12).
    #[arg(long, default_value_t = 12, value_parser = clap::value_parser!(u32).range(1..=256))]
    channels: u32,
    /// Grid channels that G2P gathers (`all-grid-mingru`'s latent width: 32).
    #[arg(long, default_value_t = 32, value_parser = clap::value_parser!(u32).range(1..=256))]
    latent: u32,
    /// Timed repetitions of each transfer (after one untimed).
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u32).range(1..=1000))]
    reps: u32,
    #[command(flatten)]
    device: DeviceArgs,
}

/// Runs the check and the table (CUDA builds only).
///
/// # Errors
/// A CPU device, a build without `cuda`, no usable GPU, or a check that failed (a
/// difference above 1e-4 of the largest entry against the CPU, 2e-3 for the dense
/// products, above 1e-2 between the two forms at the timed size, or a sparse P2G whose bits
/// change with the particles' order).
pub fn run(args: TransferBenchArgs) -> anyhow::Result<Outcome> {
    let device = args.device.parse()?;
    #[cfg(feature = "cuda")]
    {
        let Some(index) = device.single("bench transfer")? else {
            anyhow::bail!("bench transfer measures GPU kernels: give --device cuda[:N]");
        };
        cuda::run(
            &args,
            crate::cli::device::cuda::device(index, args.device.kernels())?,
        )
    }
    #[cfg(not(feature = "cuda"))]
    {
        let _ = device;
        anyhow::bail!("bench transfer needs --device cuda (a build with --features cuda)")
    }
}

#[cfg(feature = "cuda")]
mod cuda {
    use super::{Outcome, TransferBenchArgs};
    use crate::cli::device::cuda::{CudaDevice, CudaInfer};
    use crate::model::grid::transfer::{self, Stencil};
    use burn::tensor::backend::Backend;
    use burn::tensor::{Distribution, Int, Tensor, TensorData};
    use std::time::Instant;

    type B = CudaInfer;

    /// The CPU backend, the check's reference (its stencil and transfers are tested against
    /// `transfer::stencil_host`).
    type Cpu = burn::backend::NdArray<f32>;

    /// Host values of a tensor on either backend.
    fn host<K: Backend, const D: usize>(t: Tensor<K, D>) -> Vec<f32> {
        t.into_data().convert::<f32>().into_vec().expect("f32 data")
    }

    /// A stencil's node indices on the host, as i32 (the CPU backend's are i64).
    fn nodes<K: Backend>(index: Tensor<K, 1, Int>) -> Vec<i32> {
        index
            .into_data()
            .convert::<i32>()
            .into_vec()
            .expect("i32 data")
    }

    /// Largest `|a - b|` over the largest `|b|`.
    fn rel_diff(a: &[f32], b: &[f32]) -> f64 {
        let scale = b.iter().fold(1e-30f32, |m, v| m.max(v.abs()));
        let d = a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs()));
        f64::from(d / scale)
    }

    /// The check: one line per quantity, its relative difference from the CPU backend's; false
    /// when one is above 1e-4 (2e-3 for the dense products, which round in TF32).
    fn check(device: &CudaDevice) -> bool {
        let (b, n_p, n, c) = (3usize, 400usize, 16usize, 5usize);
        let pos = Tensor::<B, 3>::random([b, n_p, 2], Distribution::Uniform(0.0, 1.0), device);
        let values = Tensor::<B, 3>::random([b, n_p, c], Distribution::Uniform(-1.0, 1.0), device);
        let grid = Tensor::<B, 3>::random([b, n * n, c], Distribution::Uniform(-1.0, 1.0), device);
        // The reference: the same inputs through the CPU backend's own stencil and transfers.
        let on_cpu =
            |t: &Tensor<B, 3>| Tensor::<Cpu, 3>::from_data(t.to_data(), &Default::default());
        let cpu = transfer::stencil(on_cpu(&pos), n, false);
        let index_h = nodes(cpu.index.clone());
        let weight_h = host(cpu.weight.clone());
        let p2g_h = host(transfer::p2g(&cpu, on_cpu(&values)));
        let g2p_h = host(transfer::g2p(&cpu, on_cpu(&grid)));
        let uploaded = Stencil::<B> {
            index: Tensor::<B, 1, Int>::from_data(
                TensorData::new(index_h.clone(), [b * n_p * 9]),
                device,
            ),
            weight: Tensor::from_data(TensorData::new(weight_h.clone(), [b, n_p, 9]), device),
            dense: None,
            n,
            batch: b,
            particles: n_p,
        };
        let kernel = transfer::stencil(pos.clone(), n, false);
        let composed = transfer::composed_stencil(pos.clone(), n, false);
        let dense = transfer::stencil(pos, n, true);
        println!(
            "check ({b} scenes x {n_p} particles, {n}^2 grid, {c} channels), largest difference \
             / largest entry against the CPU backend:"
        );
        let mut ok = true;
        for (what, s) in [("kernel", &kernel), ("composed", &composed)] {
            let nodes = nodes(s.index.clone());
            let wrong = nodes.iter().zip(&index_h).filter(|(a, b)| a != b).count();
            ok &= wrong == 0 && nodes.len() == index_h.len();
            println!(
                "  {what} stencil: {wrong} of {} nodes differ",
                index_h.len()
            );
        }
        // The dense products go through the GPU's matmul, which rounds its inputs to TF32
        // (10-bit mantissa: ~5e-4); the sparse forms add in f32 or fixed point (~1e-7).
        let mut line = |what: &str, got: Vec<f32>, want: &[f32]| {
            let d = rel_diff(&got, want);
            ok &= d <= if what.contains("dense") { 2e-3 } else { 1e-4 };
            println!("  {what:<36} {d:.2e}");
        };
        line(
            "kernel stencil weights",
            host(kernel.weight.clone()),
            &weight_h,
        );
        line(
            "composed stencil weights",
            host(composed.weight.clone()),
            &weight_h,
        );
        for (form, s) in [
            ("sparse, CPU stencil", &uploaded),
            ("sparse, kernel stencil", &kernel),
            ("sparse, composed stencil", &composed),
            ("dense", &dense),
        ] {
            line(
                &format!("P2G {form}"),
                host(transfer::p2g(s, values.clone())),
                &p2g_h,
            );
            line(
                &format!("G2P {form}"),
                host(transfer::g2p(s, grid.clone())),
                &g2p_h,
            );
        }
        ok
    }

    /// Milliseconds of `f`, mean over `reps` after one untimed call.
    fn timed(device: &CudaDevice, reps: u32, f: impl Fn() -> Tensor<B, 3>) -> anyhow::Result<f64> {
        drop(f());
        B::sync(device)?;
        let start = Instant::now();
        for _ in 0..reps {
            drop(f());
        }
        B::sync(device)?;
        Ok(start.elapsed().as_secs_f64() * 1e3 / f64::from(reps))
    }

    /// Whether the sparse P2G is the same to the bit when run again and when each scene's
    /// particles come in reverse order (the atomic adds then land in another order); prints
    /// how many of its entries differ.
    fn deterministic(pos: &Tensor<B, 3>, values: &Tensor<B, 3>, n: usize) -> bool {
        let [b, n_p, _] = pos.dims();
        let s = transfer::stencil(pos.clone(), n, false);
        let reversed = Stencil::<B> {
            index: s
                .index
                .clone()
                .reshape([b, n_p, 9])
                .flip([1])
                .reshape([b * n_p * 9]),
            weight: s.weight.clone().flip([1]),
            ..s.clone()
        };
        let bits = |t: Tensor<B, 3>| -> Vec<u32> { host(t).iter().map(|v| v.to_bits()).collect() };
        let first = bits(transfer::p2g(&s, values.clone()));
        let again = bits(transfer::p2g(&s, values.clone()));
        let flipped = bits(transfer::p2g(&reversed, values.clone().flip([1])));
        let differ = |o: &[u32]| first.iter().zip(o).filter(|(a, b)| a != b).count();
        let (a, r) = (differ(&again), differ(&flipped));
        println!(
            "sparse P2G bits: {a} of {} entries differ when run again, {r} with the particles \
             reversed",
            first.len()
        );
        a == 0 && r == 0
    }

    /// The check, then the table.
    pub(super) fn run(args: &TransferBenchArgs, device: CudaDevice) -> anyhow::Result<Outcome> {
        let ok = check(&device);
        let (b, n_p, n, c, l) = (
            args.scenes as usize,
            args.particles as usize,
            args.grid as usize,
            args.channels as usize,
            args.latent as usize,
        );
        let pos = Tensor::<B, 3>::random([b, n_p, 2], Distribution::Uniform(0.0, 1.0), &device);
        let values = Tensor::<B, 3>::random([b, n_p, c], Distribution::Uniform(-1.0, 1.0), &device);
        let grid = Tensor::<B, 3>::random([b, n * n, l], Distribution::Uniform(-1.0, 1.0), &device);
        println!(
            "\n{b} scenes x {n_p} particles, {n}^2 grid, P2G of {c} and G2P of {l} channels, {} \
             reps, {}",
            args.reps,
            B::name(&device)
        );
        println!("| form | stencil ms | P2G ms | G2P ms |\n| --- | ---: | ---: | ---: |");
        let mut results = Vec::new();
        for (form, dense) in [("dense products", true), ("sparse kernels", false)] {
            let st = timed(&device, args.reps, || {
                let s = transfer::stencil(pos.clone(), n, dense);
                s.weight
            })?;
            let s = transfer::stencil(pos.clone(), n, dense);
            let p2g = timed(&device, args.reps, || transfer::p2g(&s, values.clone()))?;
            let g2p = timed(&device, args.reps, || transfer::g2p(&s, grid.clone()))?;
            println!("| {form} | {st:.3} | {p2g:.3} | {g2p:.3} |");
            results.push((
                host(transfer::p2g(&s, values.clone())),
                host(transfer::g2p(&s, grid.clone())),
            ));
        }
        // At this size too (where the kernels run past 65,535 blocks): sparse against dense.
        // The dense products may round in TF32 (~1e-3); a wrong node or layout is O(1).
        let (p2g, g2p) = (
            rel_diff(&results[1].0, &results[0].0),
            rel_diff(&results[1].1, &results[0].1),
        );
        println!("sparse against dense at this size: P2G {p2g:.2e}, G2P {g2p:.2e}");
        let same = deterministic(&pos, &values, n);
        let ok = ok && p2g <= 1e-2 && g2p <= 1e-2 && same;
        anyhow::ensure!(ok, "the GPU's transfers differ from the CPU's (above)");
        Ok(Outcome::Done)
    }
}
