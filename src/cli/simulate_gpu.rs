//! `minflow simulate --device cuda`: the scenes advanced together on the GPU solver
//! ([`crate::sim::gpu::GpuSolver`]), `--batch` scenes of one solver setting a call. Each frame
//! of the batch is read back once and written into every scene's bag in parallel, after the
//! same per-frame sanity checks as the CPU path ([`crate::sim::sanity`]); a scene that fails
//! one stops there and its bag is left as `.part` (as on the CPU), the others go on. Bags
//! hold the same messages and metadata as the CPU path's.

use crate::bag::{bag_name, BagWriter};
use crate::sim::gpu::{CudaDevice, GpuSolver};
use crate::sim::run::particle_frame;
use crate::sim::{sanity, BodySpan, Particles, Scene, SolverConfig};
use anyhow::Context;
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// One scene of a batch being written.
struct Slot {
    scene: Scene,
    bodies: Vec<BodySpan>,
    period_ns: u64,
    path: PathBuf,
    part: PathBuf,
    writer: Option<BagWriter>,
    error: Option<anyhow::Error>,
}

impl Slot {
    fn open(scene: Scene, bodies: Vec<BodySpan>, out: &Path) -> Self {
        let period_ns = scene.period_ns();
        let path = out.join(bag_name(&scene.name));
        let part = path.with_extension("mcap.part");
        let mut slot = Self {
            scene,
            bodies,
            period_ns,
            path,
            part,
            writer: None,
            error: None,
        };
        match BagWriter::create(&slot.part) {
            Ok(mut w) => {
                w.channel_metadata(crate::bag::SOLVER_GRID_KEY, &slot.scene.grid.to_string());
                slot.writer = Some(w);
            }
            Err(e) => slot.error = Some(e.into()),
        }
        slot
    }

    /// Checks and writes frame `index` (`ps`, the scene's particles); after the scene's last
    /// frame, or a failure, does nothing.
    fn frame(&mut self, index: u32, ps: &Particles, topic: &str) {
        if index >= self.scene.frames || self.error.is_some() {
            return;
        }
        let Some(writer) = self.writer.as_mut() else {
            return;
        };
        let dx = 1.0 / self.scene.grid as f32;
        if let Err(violation) = sanity::check_particles(ps, dx, &self.bodies) {
            let scene = self.scene.name.clone();
            self.error = Some(
                crate::sim::SimError::Unstable {
                    scene,
                    frame: index,
                    violation,
                }
                .into(),
            );
            return;
        }
        let frame = particle_frame(&self.scene.name, index, self.period_ns, ps);
        if let Err(e) = writer.write(topic, &frame) {
            self.error = Some(e.into());
        }
    }

    /// Finishes the bag and gives it its final name, or reports why the scene failed.
    fn finish(mut self) -> (String, anyhow::Result<PathBuf>) {
        let name = self.scene.name.clone();
        if let Some(e) = self.error.take() {
            return (name, Err(e));
        }
        let result = (|| {
            let writer = self.writer.take().context("bag writer")?;
            writer.finish()?;
            std::fs::rename(&self.part, &self.path)
                .with_context(|| format!("renaming {}", self.part.display()))?;
            Ok(self.path.clone())
        })();
        (name, result)
    }
}

/// The key scenes share a GPU batch by: the solver setting and the substeps a frame.
fn batch_key(scene: &Scene) -> (SolverConfig, u32) {
    (scene.solver_config(), scene.substeps)
}

/// Simulates `scenes` on `device`, `batch` at a time (grouped by solver setting, in order of
/// first appearance), into `out`; one result per scene, as the CPU path returns them.
///
/// # Errors
/// The device failed (a launch or a read); a scene's own failure is its result instead.
pub(super) fn simulate(
    scenes: Vec<Scene>,
    device: &CudaDevice,
    batch: usize,
    out: &Path,
    topic: &str,
    bar: &indicatif::ProgressBar,
) -> anyhow::Result<Vec<(String, anyhow::Result<PathBuf>)>> {
    let mut groups: Vec<((SolverConfig, u32), Vec<Scene>)> = Vec::new();
    for scene in scenes {
        let key = batch_key(&scene);
        match groups.iter_mut().find(|(k, _)| *k == key) {
            Some((_, g)) => g.push(scene),
            None => groups.push((key, vec![scene])),
        }
    }
    let mut results = Vec::new();
    for ((config, substeps), group) in groups {
        let mut group = group.into_iter().peekable();
        while group.peek().is_some() {
            let chunk: Vec<Scene> = group.by_ref().take(batch.max(1)).collect();
            results.extend(run_batch(chunk, config, substeps, device, out, topic, bar)?);
        }
    }
    Ok(results)
}

/// One GPU batch of scenes of one setting, frame by frame, for as many frames as its longest
/// scene.
fn run_batch(
    scenes: Vec<Scene>,
    config: SolverConfig,
    substeps: u32,
    device: &CudaDevice,
    out: &Path,
    topic: &str,
    bar: &indicatif::ProgressBar,
) -> anyhow::Result<Vec<(String, anyhow::Result<PathBuf>)>> {
    let frames = scenes.iter().map(|s| s.frames).max().unwrap_or(0);
    for s in &scenes {
        s.validate()?;
    }
    let (particles, bodies): (Vec<_>, Vec<_>) = scenes.iter().map(Scene::particles).unzip();
    let mut gpu = GpuSolver::new(device, config, particles)?;
    let mut slots: Vec<Slot> = scenes
        .into_iter()
        .zip(bodies)
        .map(|(s, b)| Slot::open(s, b, out))
        .collect();
    for index in 0..frames {
        if index > 0 {
            gpu.advance(substeps)?;
        }
        let states = gpu.read()?;
        slots
            .par_iter_mut()
            .zip(states.par_iter())
            .for_each(|(slot, ps)| slot.frame(index, ps, topic));
        let live = slots.iter().filter(|s| index < s.scene.frames).count();
        bar.inc(live as u64);
    }
    Ok(slots.into_iter().map(Slot::finish).collect())
}
