//! `sim`: the MLS-MPM ground truth. Scenes (generated families or TOML scene files) are turned
//! into particles and advanced substep by substep; every `substeps` substeps a frame is saved
//! (0.016 time units for both families).
//!
//! Layout: [`linalg`] (2x2 polar decomposition and signed SVD), [`material`] (constitutive
//! models), [`mpm`] (the solver), [`scene`] (bodies and sampling), [`families`] (`multi`,
//! `fluid` and `mixed`, the last in [`mixed`]), [`refine`] (a scene on a finer grid), [`diagnostics`] (conservation sums), [`sanity`]
//! (per-frame checks), [`run`] (a scene to `ParticleFrame`s); with the `cuda` feature, `gpu`
//! (the solver batched over scenes on a GPU). Used by `minflow simulate`,
//! `minflow bench sim` and `minflow bench rollout`.

pub mod diagnostics;
pub mod families;
#[cfg(feature = "cuda")]
pub mod gpu;
pub mod linalg;
pub mod material;
pub mod mixed;
pub mod mpm;
pub mod refine;
pub mod run;
pub mod sanity;
pub mod scene;

pub use diagnostics::Diagnostics;
pub use families::Family;
pub use material::Material;
pub use mpm::{Particles, Solver, SolverConfig};
pub use run::SceneRun;
pub use scene::{Body, BodySpan, Scene, Shape};

/// Errors of the simulator.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// A scene or solver setting is out of range.
    #[error("invalid scene: {0}")]
    Invalid(String),
    /// A scene file could not be parsed.
    #[error("scene file: {0}")]
    SceneFile(String),
    /// A frame failed the sanity checks.
    #[error("scene {scene}, frame {frame}: {violation}")]
    Unstable {
        /// Scene id.
        scene: String,
        /// Frame index.
        frame: u32,
        /// What failed.
        violation: sanity::Violation,
    },
}
