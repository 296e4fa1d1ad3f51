//! `minflow bench`: the subcommands (train, transport, node, rollout and gemm live in their own
//! files). `bench sim`: milliseconds per saved frame of the MLS-MPM ground truth for the
//! `multi` setting (2,500 particles, 64^2 grid, 20 substeps) and the `fluid` setting
//! (128^2 grid, 80 substeps), on one thread and on all threads (one scene per thread), in
//! one run so the ratios are comparable on a noisy machine. Taichi 1.7.4's CPU backend needs
//! 16-20 ms and 62-75 ms per frame for the same work on this kind of machine (docs/mpm.md, "Speed anchor").

use super::Outcome;
use crate::sim::families::{self, Family};
use crate::sim::Scene;
use clap::{Args, Subcommand};
use rayon::prelude::*;
use std::time::Instant;

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Simulator speed: ms per saved frame, one thread and all threads.
    Sim(SimBenchArgs),
    /// Training speed per core (the paper's Table 4): parameters, s/epoch, us/sample, memory.
    Train(super::bench_train::TrainBenchArgs),
    /// Transport latency between two processes (p50/p99/max) and burst throughput.
    Transport(super::bench_transport::TransportBenchArgs),
    /// Surrogate node latency and throughput per core and transport (two processes).
    Node(super::bench_node::NodeBenchArgs),
    /// GPU dense-layer products: cubecl vs cuBLAS TF32 / FP32, ms, TFLOP/s, difference.
    Gemm(super::bench_gemm::GemmBenchArgs),
    /// Closed-loop rollout cost per frame of models against the MPM solver, as a ratio.
    Rollout(super::bench_rollout::RolloutBenchArgs),
    /// GPU particle-grid transfers (P2G, G2P): sparse kernels vs dense products, checked
    /// against the host, ms.
    Transfer(super::bench_transfer::TransferBenchArgs),
}

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
}

pub fn run(cmd: BenchCommand) -> anyhow::Result<Outcome> {
    match cmd {
        BenchCommand::Sim(args) => sim(args),
        BenchCommand::Train(args) => super::bench_train::run(args),
        BenchCommand::Transport(args) => super::bench_transport::run(args),
        BenchCommand::Node(args) => super::bench_node::run(args),
        BenchCommand::Gemm(args) => super::bench_gemm::run(args),
        BenchCommand::Rollout(args) => super::bench_rollout::run(args),
        BenchCommand::Transfer(args) => super::bench_transfer::run(args),
    }
}

/// Simulates `frames` frames of each scene; returns the substep splits taken.
fn simulate(scene: &Scene, frames: u32) -> anyhow::Result<u64> {
    let (mut solver, _) = scene.solver()?;
    for _ in 0..frames {
        solver.advance(scene.substeps);
    }
    Ok(solver.splits)
}

fn sim(args: SimBenchArgs) -> anyhow::Result<Outcome> {
    let threads = args
        .threads
        .unwrap_or_else(rayon::current_num_threads)
        .max(1);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    println!(
        "{:<8} {:>5} {:>9} {:>9} {:>8} {:>10} {:>10} {:>8}",
        "setting", "grid", "substeps", "particles", "threads", "ms/frame", "frames/s", "splits"
    );
    for family in [Family::Multi, Family::Fluid] {
        let scenes: Vec<Scene> = (0..args.scenes.max(1))
            .map(|id| families::scene(family, id, 0))
            .collect();
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
    Ok(Outcome::Done)
}
