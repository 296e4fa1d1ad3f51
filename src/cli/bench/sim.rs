//! `minflow bench sim`: milliseconds per saved frame of the MLS-MPM ground truth for the
//! `multi` setting (2,500 particles, 64^2 grid, 20 substeps) and the `fluid` setting
//! (128^2 grid, 80 substeps), on one thread and on all threads (one scene per thread), in
//! one run so the ratios are comparable on a noisy machine. Taichi 1.7.4's CPU backend needs
//! 16-20 ms and 62-75 ms per frame for the same work on this kind of machine (docs/mpm.md,
//! "Speed anchor").

use crate::cli::Outcome;
use crate::sim::families::{self, Family};
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
