//! Running a scene: [`SceneRun`] yields the scene's saved frames as [`ParticleFrame`]s,
//! frame 0 being the initial state and each later frame `substeps` substeps after the last,
//! and runs the per-frame sanity checks on each one.
//!
//! Stamps are `frame_index * period` in integer nanoseconds, with the period
//! `round(dt * substeps * 1e9)` (16,000,000 ns for both families), so stamps never drift;
//! the message's `dt` is that period in time units. `frame_id` is `"world"`.
//! Used by `minflow simulate` and `minflow bench sim`.

use super::mpm::{Particles, Solver};
use super::sanity;
use super::scene::{BodySpan, Scene};
use super::SimError;
use crate::msgs::ParticleFrame;

/// A scene being simulated, frame by frame.
pub struct SceneRun {
    scene: Scene,
    solver: Solver,
    bodies: Vec<BodySpan>,
    next: u32,
    period_ns: u64,
}

impl SceneRun {
    /// Validates the scene and samples its particles.
    pub fn new(scene: Scene) -> Result<Self, SimError> {
        let (solver, bodies) = scene.solver()?;
        let period_ns = scene.period_ns();
        Ok(Self {
            scene,
            solver,
            bodies,
            next: 0,
            period_ns,
        })
    }

    /// The scene description.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// The solver in its current state.
    pub fn solver(&self) -> &Solver {
        &self.solver
    }

    /// Time between frames in nanoseconds.
    pub fn period_ns(&self) -> u64 {
        self.period_ns
    }

    /// Advances to the next frame (frame 0 is the initial state and needs no step), checks
    /// it, and returns it as a message. `None` after `scene.frames` frames.
    pub fn next_frame(&mut self) -> Option<Result<ParticleFrame, SimError>> {
        if self.next >= self.scene.frames {
            return None;
        }
        if self.next > 0 {
            self.solver.advance(self.scene.substeps);
        }
        let index = self.next;
        self.next += 1;
        if let Err(violation) = sanity::check(&self.solver, &self.bodies) {
            self.next = self.scene.frames;
            return Some(Err(SimError::Unstable {
                scene: self.scene.name.clone(),
                frame: index,
                violation,
            }));
        }
        Some(Ok(self.frame(index)))
    }

    /// The current particle state as frame `index` of this scene.
    pub fn frame(&self, index: u32) -> ParticleFrame {
        particle_frame(
            &self.scene.name,
            index,
            self.period_ns,
            &self.solver.particles,
        )
    }
}

/// Particles `ps` as frame `index` of scene `name`, stamped `index * period_ns` (also the
/// GPU solver's frames, `cli::simulate_gpu`).
pub fn particle_frame(name: &str, index: u32, period_ns: u64, ps: &Particles) -> ParticleFrame {
    ParticleFrame::on_clock(
        name.to_owned(),
        index,
        period_ns,
        ps.x.as_flattened().to_vec(),
        ps.v.as_flattened().to_vec(),
        ps.material.clone(),
    )
}

impl Iterator for SceneRun {
    type Item = Result<ParticleFrame, SimError>;
    fn next(&mut self) -> Option<Self::Item> {
        self.next_frame()
    }
}
