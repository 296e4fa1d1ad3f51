//! `minflow bench sim --device cuda`: the MLS-MPM solver batched on the GPU
//! ([`crate::sim::gpu::GpuSolver`]) against the CPU solver, in one run: milliseconds per
//! scene-frame at `--batch` scenes a call for the `multi` and `fluid` settings, and its
//! physics against the CPU's over `--frames` frames of the first `--scenes` scenes.
//!
//! Two f32 solvers of a chaotic system agree only to rounding per substep and then drift
//! apart, so the GPU's distance from the CPU is shown beside the distance between two CPU runs
//! that differ only in the order P2G sums the particles (the scene's particles reversed):
//! the GPU passes when it is no farther from the CPU than that (docs/mpm.md, "The solver on
//! a GPU").

use crate::sim::diagnostics::Diagnostics;
use crate::sim::gpu::{CudaDevice, GpuSolver};
use crate::sim::{Particles, Scene, Solver};
use std::time::Instant;

/// What one family's GPU run measured.
pub(super) struct GpuRow {
    /// Milliseconds per scene-frame at `batch` scenes a call.
    pub ms: f64,
    /// Substep splits over the batch.
    pub splits: u64,
    /// Parts launched per substep (the batch runs its most split scene's parts).
    pub passes: f64,
    /// Frames taken again substep by substep (`GpuSolver::advance`).
    pub redone: u64,
}

/// Simulates `scenes` (one setting) together on the GPU, speculating each frame's parts from
/// the last `window` frames: `warm` untimed frames (at least one: the kernels compile on
/// first use; more let the window fill), then `frames` timed ones. The upload is not timed.
/// With `read_back` each timed frame is read back to the host and kept
/// ([`GpuSolver::read_frame`]), as a rollout keeps a model's predicted frames.
///
/// # Errors
/// A scene the solver refuses, or the device's error.
pub(super) fn time_batch(
    device: &CudaDevice,
    scenes: &[Scene],
    (warm, frames): (u32, u32),
    window: u32,
    read_back: bool,
) -> anyhow::Result<GpuRow> {
    let batch = scenes.len();
    let config = scenes[0].solver_config();
    let particles = scenes.iter().map(|s| s.particles().0).collect();
    let mut gpu = GpuSolver::new(device, config, particles)?.with_window(window as usize);
    for _ in 0..warm.max(1) {
        gpu.advance(scenes[0].substeps)?;
    }
    gpu.tallies()?;
    let (passes, redone) = (gpu.passes, gpu.redone);
    let mut kept = Vec::with_capacity(if read_back { frames as usize } else { 0 });
    let start = Instant::now();
    for _ in 0..frames {
        gpu.advance(scenes[0].substeps)?;
        if read_back {
            kept.push(gpu.read_frame()?);
        }
    }
    let tallies = gpu.tallies()?;
    let secs = start.elapsed().as_secs_f64();
    let substeps = frames as f64 * scenes[0].substeps as f64;
    Ok(GpuRow {
        ms: secs * 1e3 / (batch as f64 * frames as f64),
        splits: tallies.iter().map(|t| t.1).sum(),
        passes: (gpu.passes - passes) as f64 / substeps,
        redone: gpu.redone - redone,
    })
}

/// Times `scenes` on the GPU ([`time_batch`], one untimed frame, `(frames, window)`) and prints their row of
/// `bench sim`'s table, against `cpu_ms` a frame of the CPU row above.
///
/// # Errors
/// As [`time_batch`].
pub(super) fn print_row(
    device: &CudaDevice,
    family: crate::sim::Family,
    scenes: Vec<Scene>,
    (frames, window): (u32, u32),
    cpu_ms: f64,
) -> anyhow::Result<()> {
    let (grid, substeps, particles) = (
        scenes[0].grid,
        scenes[0].substeps,
        scenes[0].particle_count(),
    );
    let batch = scenes.len();
    let row = time_batch(device, &scenes, (1, frames), window, false)?;
    println!(
        "{:<8} {:>5} {:>9} {:>9} {:>8} {:>10.4} {:>10.1} {:>8}   GPU, {batch} scenes a call, {:.1}x the row above; {:.2} parts a substep, {} of {frames} frames redone",
        family.name(),
        grid,
        substeps,
        particles,
        "gpu",
        row.ms,
        1e3 / row.ms,
        row.splits,
        cpu_ms / row.ms,
        row.passes,
        row.redone,
    );
    Ok(())
}

/// The largest gaps over frames between two runs' diagnostics: relative kinetic energy
/// (against the run's largest) and centre of mass (domain units).
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct Gap {
    pub kinetic: f64,
    pub centre: f64,
}

impl Gap {
    fn widen(&mut self, a: &[Diagnostics], b: &[Diagnostics]) {
        let peak = a
            .iter()
            .map(|d| d.kinetic)
            .fold(f64::MIN_POSITIVE, f64::max);
        for (a, b) in a.iter().zip(b) {
            self.kinetic = self.kinetic.max((a.kinetic - b.kinetic).abs() / peak);
            let (ca, cb) = (a.center_of_mass, b.center_of_mass);
            self.centre = self.centre.max((ca[0] - cb[0]).hypot(ca[1] - cb[1]));
        }
    }
}

/// The parity of one family: the GPU's gap from the CPU, the CPU's own gap under reversed
/// particle order, and whether two GPU runs gave the same bits.
pub(super) struct Parity {
    pub gpu: Gap,
    pub cpu: Gap,
    pub same_bits: bool,
}

/// Runs `scenes` (one setting) for `frames` frames on the CPU (twice: as generated and with
/// the particles reversed) and on the GPU (twice, one batch), comparing the per-frame
/// diagnostics.
///
/// # Errors
/// A scene the solver refuses, or the device's error.
pub(super) fn parity(device: &CudaDevice, scenes: &[Scene], frames: u32) -> anyhow::Result<Parity> {
    let config = scenes[0].solver_config();
    let substeps = scenes[0].substeps;
    let gpu_run = || -> anyhow::Result<(Vec<Vec<Diagnostics>>, Vec<Particles>)> {
        let particles = scenes.iter().map(|s| s.particles().0).collect();
        let mut gpu = GpuSolver::new(device, config, particles)?;
        let mut diags = vec![Vec::new(); scenes.len()];
        let mut last = Vec::new();
        for frame in 0..frames {
            if frame > 0 {
                gpu.advance(substeps)?;
            }
            last = gpu.read()?;
            for (d, ps) in diags.iter_mut().zip(&last) {
                d.push(Diagnostics::of_particles(&config, ps));
            }
        }
        Ok((diags, last))
    };
    let (gpu, first) = gpu_run()?;
    let (_, second) = gpu_run()?;
    let mut out = Parity {
        gpu: Gap::default(),
        cpu: Gap::default(),
        same_bits: first == second,
    };
    for (scene, gpu) in scenes.iter().zip(&gpu) {
        let cpu = cpu_run(scene, frames, false)?;
        let reversed = cpu_run(scene, frames, true)?;
        out.gpu.widen(&cpu, gpu);
        out.cpu.widen(&cpu, &reversed);
    }
    Ok(out)
}

/// The CPU solver's diagnostics of `scene` per frame, its particles reversed when `reverse`.
fn cpu_run(scene: &Scene, frames: u32, reverse: bool) -> anyhow::Result<Vec<Diagnostics>> {
    let (mut ps, _) = scene.particles();
    if reverse {
        ps.x.reverse();
        ps.v.reverse();
        ps.c.reverse();
        ps.f.reverse();
        ps.jp.reverse();
        ps.material.reverse();
    }
    let mut solver = Solver::new(scene.solver_config(), ps)?;
    let mut out = Vec::with_capacity(frames as usize);
    for frame in 0..frames {
        if frame > 0 {
            solver.advance(scene.substeps);
        }
        out.push(Diagnostics::of(&solver));
    }
    Ok(out)
}
