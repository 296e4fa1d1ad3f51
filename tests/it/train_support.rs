//! Shared helpers of the training tests: tiny trajectories and tiny model settings.

use burn::backend::{Autodiff, NdArray};
use minflow::data::Trajectory;
use minflow::model::{CoreKind, ModelConfig};
use minflow::sim::{Body, Material, Scene, SceneRun, Shape};
use minflow::train::TrainOptions;

/// The autodiff CPU backend the tests train on.
pub type B = Autodiff<NdArray<f32>>;

/// A jelly disk and a liquid block, `n` particles, `frames` frames, as one trajectory.
pub fn trajectory(n: usize, frames: u32) -> Trajectory {
    let body = |material, position: [f32; 2], count| Body {
        shape: Shape::Disk,
        material,
        position,
        size: [0.2, 0.2],
        velocity: [0.5, -0.3],
        spin: 1.0,
        count,
    };
    let scene = Scene {
        name: "test/tiny/000".into(),
        grid: 64,
        dt: 8e-4,
        substeps: 20,
        frames,
        gravity: [0.0, -9.8],
        elasticity: Default::default(),
        seed: 3,
        bodies: vec![
            body(Material::Jelly, [0.35, 0.5], n / 2),
            body(Material::Liquid, [0.65, 0.5], n - n / 2),
        ],
    };
    let frames: Vec<_> = SceneRun::new(scene).unwrap().map(|f| f.unwrap()).collect();
    let mut states = Vec::new();
    for f in &frames {
        for p in 0..f.material.len() {
            states.extend_from_slice(&[
                f.position[2 * p],
                f.position[2 * p + 1],
                f.velocity[2 * p],
                f.velocity[2 * p + 1],
            ]);
        }
    }
    Trajectory {
        scene: frames[0].scene.clone(),
        dt: frames[0].dt,
        material: frames[0].material.clone(),
        start_index: 0,
        states,
        frames: frames.len(),
        n: frames[0].material.len(),
        solver_grid: None,
    }
}

pub fn tiny(core: CoreKind, n: usize) -> ModelConfig {
    ModelConfig::new(core, n)
        .with_encoder_hidden(16)
        .with_width(24)
        .with_dropout(0.0)
}

pub fn options(epochs: usize) -> TrainOptions {
    TrainOptions {
        epochs,
        batch_size: 2,
        micro_batch: 1,
        lr: 3e-3,
        seed: 5,
        patience: 0,
        density_grid: 8,
        density_weight: 0.1,
    }
}

/// `n` particles over `frames` frames integrated exactly as the model integrates, with
/// random accelerations (deterministic).
pub fn integrator_trajectory(n: usize, frames: usize) -> Trajectory {
    let dt = 0.016f32;
    let mut seed = 12345u64;
    let mut rnd = || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((seed >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    };
    let mut state: Vec<f32> = (0..n).flat_map(|_| [0.5, 0.5, 0.0, 0.0]).collect();
    for p in 0..n {
        state[4 * p] = 0.5 + 0.3 * rnd();
        state[4 * p + 1] = 0.5 + 0.3 * rnd();
        state[4 * p + 2] = rnd();
        state[4 * p + 3] = rnd();
    }
    let mut states = state.clone();
    for _ in 1..frames {
        for p in 0..n {
            for d in 0..2 {
                state[4 * p + 2 + d] += 10.0 * rnd() * dt;
                state[4 * p + d] += state[4 * p + 2 + d] * dt;
            }
        }
        states.extend_from_slice(&state);
    }
    Trajectory {
        scene: "test/integrator/000".into(),
        dt,
        material: (0..n).map(|p| (p % 4) as u8).collect(),
        start_index: 0,
        states,
        frames,
        n,
        solver_grid: None,
    }
}
