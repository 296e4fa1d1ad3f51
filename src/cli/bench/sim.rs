//! `minflow bench sim`: milliseconds per saved frame of the MLS-MPM ground truth for the
//! `multi` setting (2,500 particles, 64^2 grid, 20 substeps) and the `fluid` setting
//! (128^2 grid, 80 substeps), on one thread and on all threads (one scene per thread), in
//! one run so the ratios are comparable on a noisy machine. Taichi 1.7.4's CPU backend needs
//! 16-20 ms and 62-75 ms per frame for the same work on this kind of machine (docs/mpm.md,
//! "Speed anchor").

use super::common::family_scenes;
use crate::cli::{Outcome, UsageError};
use crate::sim::families::Family;
use crate::sim::Scene;
use clap::Args;
use rayon::prelude::*;
use std::time::Instant;

/// The flags of `minflow bench sim`.
#[derive(Debug, Args)]
pub struct SimBenchArgs {
    /// Frames simulated per scene (after frame 0).
    #[arg(long, default_value_t = 100)]
    frames: u32,
    /// Scenes per family (ids 0..N, so several material pairings are averaged).
    #[arg(long, default_value_t = 4)]
    scenes: u32,
    /// Threads for the parallel row (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Also run the solver batched on a GPU: `cuda` or `cuda:N` (needs a build with
    /// `--features cuda`). Adds a row per setting at `--batch` scenes a call, and the GPU's
    /// physics against the CPU's over `--frames` frames of the `--scenes` scenes.
    #[arg(long, default_value = "cpu")]
    device: String,
    /// Scenes a GPU call advances together (ids 0..N of each family).
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u32).range(1..=4096))]
    batch: u32,
    /// GPU: each frame runs as many parts a substep as the most split substep of the last N
    /// frames needed (a frame that needs more is taken again substep by substep); 0 reads
    /// each substep's parts back before running them.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(0..=1000))]
    window: u32,
    /// Settings to run, comma-separated families (`multi`, `fluid`, `mixed`).
    #[arg(long, default_value = "multi,fluid", value_delimiter = ',')]
    family: Vec<String>,
    /// Refine each family's scenes onto an N x N grid (where finer than its own) with
    /// proportionally more particles (`simulate --grid`): 128 puts `multi` at 10,000
    /// particles, 256 at 40,000 and `fluid` at 10,000.
    #[arg(long, value_parser = clap::value_parser!(u32).range(8..=4096))]
    grid: Option<u32>,
}

/// Simulates `frames` frames of each scene; returns the substep splits taken.
fn simulate(scene: &Scene, frames: u32) -> anyhow::Result<u64> {
    let (mut solver, _) = scene.solver()?;
    for _ in 0..frames {
        solver.advance(scene.substeps);
    }
    Ok(solver.splits)
}

/// Runs `minflow bench sim`: prints the table.
///
/// # Errors
/// A scene that cannot be built, or no thread pool.
pub fn run(args: SimBenchArgs) -> anyhow::Result<Outcome> {
    let threads = args
        .threads
        .unwrap_or_else(rayon::current_num_threads)
        .max(1);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    let gpu = gpu_of(&args.device)?;
    println!(
        "{:<8} {:>5} {:>9} {:>9} {:>8} {:>10} {:>10} {:>8}",
        "setting", "grid", "substeps", "particles", "threads", "ms/frame", "frames/s", "splits"
    );
    let families: Vec<Family> = args
        .family
        .iter()
        .map(|f| {
            f.parse()
                .map_err(|e: crate::sim::SimError| UsageError(format!("--family: {e}")))
        })
        .collect::<Result<_, _>>()?;
    for &family in &families {
        let scenes = family_scenes(family, 0..args.scenes.max(1), 0, args.grid)?;
        let frames = (scenes.len() as u64) * args.frames as u64;
        // One thread: scenes one after another.
        let start = Instant::now();
        let mut splits = 0;
        for scene in &scenes {
            splits += simulate(scene, args.frames)?;
        }
        let single = start.elapsed().as_secs_f64();
        // All threads: one scene per thread.
        let start = Instant::now();
        let parallel: anyhow::Result<Vec<u64>> = pool.install(|| {
            scenes
                .par_iter()
                .map(|s| simulate(s, args.frames))
                .collect()
        });
        parallel?;
        let multi = start.elapsed().as_secs_f64();
        let s = &scenes[0];
        #[cfg(feature = "cuda")]
        if let Some(device) = &gpu {
            let batch = family_scenes(family, 0..args.batch, 0, args.grid)?;
            let cpu_ms = multi * 1e3 / frames as f64;
            super::sim_gpu::print_row(device, family, batch, (args.frames, args.window), cpu_ms)?;
        }
        for (t, secs) in [(1, single), (threads, multi)] {
            let ms = secs * 1e3 / frames as f64;
            println!(
                "{:<8} {:>5} {:>9} {:>9} {:>8} {:>10.3} {:>10.1} {:>8}",
                family.name(),
                s.grid,
                s.substeps,
                s.particle_count(),
                t,
                ms,
                1e3 / ms,
                splits
            );
        }
    }
    println!("(Taichi 1.7.4 CPU, same machine kind: 16-20 ms multi, 62-75 ms fluid; docs/mpm.md)");
    #[cfg(feature = "cuda")]
    if let Some(device) = &gpu {
        parity_table(device, &args, &families)?;
    }
    #[cfg(not(feature = "cuda"))]
    let _ = gpu;
    Ok(Outcome::Done)
}

/// The GPU `--device` names ([`crate::cli::device::solver_gpu`]), opened; `None` for `cpu`.
#[cfg(feature = "cuda")]
fn gpu_of(text: &str) -> anyhow::Result<Option<crate::sim::gpu::CudaDevice>> {
    let kernels = crate::ops::Kernels::default();
    crate::cli::device::solver_gpu(text)?
        .map(|i| crate::cli::device::cuda::device(i, kernels))
        .transpose()
}

/// Without the `cuda` feature only `cpu` is accepted ([`crate::cli::device::parse`] says why).
#[cfg(not(feature = "cuda"))]
fn gpu_of(text: &str) -> anyhow::Result<Option<()>> {
    crate::cli::device::solver_gpu(text).map(|_| None)
}

/// Prints the GPU solver's physics against the CPU's, per setting (`sim_gpu::parity`).
#[cfg(feature = "cuda")]
fn parity_table(
    device: &crate::sim::gpu::CudaDevice,
    args: &SimBenchArgs,
    families: &[Family],
) -> anyhow::Result<()> {
    println!(
        "\nGPU against CPU over {} frames of scenes 0..{} (largest gap over frames and scenes):",
        args.frames, args.scenes
    );
    println!(
        "| setting | kinetic energy, GPU vs CPU | same, CPU reversed vs CPU | centre of mass, GPU vs CPU | same, CPU reversed vs CPU | two GPU runs |\n| --- | ---: | ---: | ---: | ---: | --- |"
    );
    for &family in families {
        let scenes = family_scenes(family, 0..args.scenes.max(1), 0, args.grid)?;
        let p = super::sim_gpu::parity(device, &scenes, args.frames)?;
        println!(
            "| {} | {:.2e} | {:.2e} | {:.2e} | {:.2e} | {} |",
            family.name(),
            p.gpu.kinetic,
            p.cpu.kinetic,
            p.gpu.centre,
            p.cpu.centre,
            if p.same_bits { "same bits" } else { "DIFFER" }
        );
    }
    Ok(())
}
