//! What `eval` rolls out: the [`Predictor`] trait and its implementations, the two trivial
//! baselines docs/design.md ("Metrics") requires beside every model, [`Persist`] (copy the last
//! frame) and [`ConstVel`] (`x' = x + v dt`, `v' = v`), and [`ModelPredictor`], a trained
//! run folder on burn's CPU backend ([`Surrogate`], scaling inside).
//!
//! Every predictor sees a ground-truth [`Trajectory`] and the offset `first` of the first
//! frame to predict; it may read only the frames before `first` (its seed: the last
//! [`Predictor::window`] frames) and returns `steps` predicted physical `[N, 4]` frames,
//! frame `first + k - 1` of the trajectory for step `k`. (Tests build an oracle that reads the
//! truth through the same trait.) Used by [`super::rollout`] and [`super::replay`].
//! [`ModelPredictor`] runs on the CPU by default; `load_on` puts it on any backend (the
//! `--device` of `minflow eval`).

use std::path::Path;

use burn::backend::NdArray;

use super::EvalError;
use crate::data::Trajectory;
use crate::model::constraints::{Correction, Parts};
use crate::model::store::Surrogate;
use crate::ops::NetOps;

/// The CPU inference backend.
pub type CpuInfer = NdArray<f32>;

/// Something that predicts frames autoregressively from ground-truth seed frames.
pub trait Predictor {
    /// Column name in tables and legends.
    fn name(&self) -> &str;

    /// Seed frames it reads before `first` (the model's T; 1 for the baselines).
    fn window(&self) -> usize;

    /// `steps` predicted `[N, 4]` physical frames for trajectory offsets `first..first+steps`,
    /// seeded with the truth frames `first - window..first`. `first >= window` is the
    /// caller's duty.
    fn rollout(
        &self,
        traj: &Trajectory,
        first: usize,
        steps: usize,
    ) -> Result<Vec<Vec<f32>>, EvalError>;

    /// How far a constraint projection moved each material in the rollouts since the last
    /// call (resets the sums); None for a predictor that projects nothing.
    fn corrections(&self) -> Option<Correction> {
        None
    }
}

/// Baseline: every predicted frame is the last seed frame.
#[derive(Debug, Clone, Copy, Default)]
pub struct Persist;

impl Predictor for Persist {
    fn name(&self) -> &str {
        "persist"
    }

    fn window(&self) -> usize {
        1
    }

    fn rollout(
        &self,
        traj: &Trajectory,
        first: usize,
        steps: usize,
    ) -> Result<Vec<Vec<f32>>, EvalError> {
        let last = traj.state(first - 1);
        Ok(vec![last.to_vec(); steps])
    }
}

/// Baseline: constant velocity from the last seed frame, `x_k = x + k v dt`, `v_k = v`
/// (iterated in f32 exactly as `x' = x + v dt` step by step).
#[derive(Debug, Clone, Copy, Default)]
pub struct ConstVel;

impl Predictor for ConstVel {
    fn name(&self) -> &str {
        "constvel"
    }

    fn window(&self) -> usize {
        1
    }

    fn rollout(
        &self,
        traj: &Trajectory,
        first: usize,
        steps: usize,
    ) -> Result<Vec<Vec<f32>>, EvalError> {
        let mut state = traj.state(first - 1).to_vec();
        let dt = traj.dt;
        let mut out = Vec::with_capacity(steps);
        for _ in 0..steps {
            for r in state.chunks_exact_mut(4) {
                r[0] += r[2] * dt;
                r[1] += r[3] * dt;
            }
            out.push(state.clone());
        }
        Ok(out)
    }
}

/// Where a model with reference positions (`train --reference first-frame`) takes them
/// from in a rollout (`eval --reference-from`, `cli::eval`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ReferenceFrom {
    /// The trajectory's frame 0: a node that has seen the stream from its start.
    #[default]
    SceneStart,
    /// The first frame of the rollout's seed window: a node that joined the stream there.
    RolloutStart,
}

/// A trained model (a `minflow train` run folder), on the CPU backend unless loaded with
/// [`ModelPredictor::load_on`].
pub struct ModelPredictor<B: NetOps = CpuInfer> {
    name: String,
    surrogate: Surrogate<B>,
    reference: ReferenceFrom,
}

impl ModelPredictor<CpuInfer> {
    /// Loads the run folder `dir` (`model.json` + `model.mpk`) onto the CPU; the column is
    /// called `name`.
    pub fn load(dir: &Path, name: impl Into<String>) -> Result<Self, EvalError> {
        Self::load_on(dir, name, &Default::default())
    }
}

impl<B: NetOps> ModelPredictor<B> {
    /// [`ModelPredictor::load`] onto `device` of backend `B`.
    pub fn load_on(
        dir: &Path,
        name: impl Into<String>,
        device: &B::Device,
    ) -> Result<Self, EvalError> {
        let surrogate = Surrogate::load(dir, device).map_err(|e| EvalError::Model {
            dir: dir.to_path_buf(),
            what: e.to_string(),
        })?;
        Ok(Self::new(surrogate, name))
    }

    /// Wraps an already loaded model.
    pub fn new(surrogate: Surrogate<B>, name: impl Into<String>) -> Self {
        Self {
            name: name.into(),
            surrogate,
            reference: ReferenceFrom::default(),
        }
    }

    /// This predictor with its reference positions taken from `reference`.
    pub fn with_reference_from(self, reference: ReferenceFrom) -> Self {
        Self { reference, ..self }
    }

    /// This predictor as a mirror ensemble ([`Surrogate::with_mirror`], `eval --mirror`).
    pub fn with_mirror(self, mirror: bool) -> Self {
        let surrogate = self.surrogate.with_mirror(mirror);
        Self { surrogate, ..self }
    }

    /// This predictor projecting onto the `parts` of its model's constraints
    /// ([`Surrogate::with_constraints`], `eval --constraints`).
    pub fn with_constraints(self, parts: Parts) -> Self {
        let surrogate = self.surrogate.with_constraints(parts);
        Self { surrogate, ..self }
    }

    /// The model (its [`crate::model::store::ModelMeta`] holds the scaler and the config).
    pub fn surrogate(&self) -> &Surrogate<B> {
        &self.surrogate
    }
}

impl<B: NetOps> Predictor for ModelPredictor<B> {
    fn name(&self) -> &str {
        &self.name
    }

    fn window(&self) -> usize {
        self.surrogate.meta().window()
    }

    fn rollout(
        &self,
        traj: &Trajectory,
        first: usize,
        steps: usize,
    ) -> Result<Vec<Vec<f32>>, EvalError> {
        let t = self.window();
        let seed: Vec<Vec<f32>> = (first - t..first).map(|k| traj.state(k).to_vec()).collect();
        let first = match self.reference {
            ReferenceFrom::SceneStart => Some(traj.state(0)),
            ReferenceFrom::RolloutStart => None,
        };
        let mut frames = Vec::with_capacity(steps);
        let on = (traj.material.as_slice(), std::slice::from_ref(&traj.dt));
        self.surrogate
            .rollout_on(traj.solver_grid, first, &seed, on, steps, |_, f| {
                frames.push(f)
            })
            .map(|()| frames)
            .map_err(|e| EvalError::Rollout {
                predictor: self.name.clone(),
                scene: traj.scene.clone(),
                what: e.to_string(),
            })
    }

    fn corrections(&self) -> Option<Correction> {
        self.surrogate
            .constraints()
            .map(|_| self.surrogate.take_corrections())
    }
}
