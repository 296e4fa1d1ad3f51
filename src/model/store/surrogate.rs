//! [`Surrogate`]: a trained model of either architecture ready for step-by-step prediction in
//! physical units (scaling inside), with one [`State`] per batch of trajectories (`state.rs`):
//! the paper core's layer states, or the grid model's per-particle memory, velocity history,
//! reference positions, rest neighbourhoods and advected `F`. `step` predicts the next frame,
//! `step_bundle` the K frames of one network call (temporal bundling; [`Predict`] says which of
//! the two), `rollout` feeds predictions back; a mirror ensemble steps each frame beside its
//! mirror image. Every predicted frame is then projected onto the model's material constraints
//! ([`crate::model::constraints`]) where the model has them and they are on
//! ([`Surrogate::with_constraints`]); a scene's constraint data lives in its [`State`] beside
//! the network's (`constrained.rs`). Used by `eval`, `node`, `report`, `bench` and the grid
//! trainer's validation.
//!
//! This file holds the type, its settings and its fresh states; the step is in `step.rs`
//! (a grid model's call in `grid_step.rs`), the closed-loop rollouts in `rollout.rs`.

use super::constrained::{DeviceMoves, PlanCache};
use super::grid_state::GridState;
use super::state::{NetState, State};
use super::{ModelMeta, Net, RunFolder, StoreError};
use crate::model::constraints::{Constraints, Correction, Parts};
use crate::model::{Model, Scaling};
use crate::ops::NetOps;
use burn::tensor::backend::Backend;
use std::path::Path;

/// Which frames of a network call a step returns.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Predict {
    /// The next frame alone ([`Surrogate::step`]): a bundled model makes its whole call and
    /// returns the first frame; its state goes on from the input (the next observed frame
    /// follows).
    Next,
    /// All K frames of the call ([`Surrogate::step_bundle`]): the state goes on from the
    /// bundle's last frame.
    Bundle,
}

/// A trained model ready for step-by-step prediction in physical units.
pub struct Surrogate<B: Backend> {
    /// The network, of either architecture.
    pub(super) net: Net<B>,
    /// The model's description (`model.json`).
    pub(super) meta: ModelMeta,
    /// The scaling constants as the network uses them ([`ModelMeta::scaling`]).
    pub(super) scaling: Scaling,
    /// Where the network runs.
    pub(super) device: B::Device,
    /// A mirror ensemble ([`Surrogate::with_mirror`]).
    pub(super) mirror: bool,
    pub(super) pad_batches: bool,
    /// Bytes of predicted frames a device-side rollout holds before reading them back
    /// ([`Surrogate::with_feedback_bytes`]).
    pub(super) feedback_bytes: usize,
    /// The constraint parts applied after each predicted frame (None: no projection).
    pub(super) constraints: Option<Constraints>,
    /// The solver grid of the scenes its fresh states serve, when known
    /// ([`Surrogate::with_solver_grid`]).
    pub(super) solver_grid: Option<u32>,
    /// The solver grid of named scenes ([`Surrogate::with_solver_grids`]).
    solver_grids: std::sync::Arc<std::collections::HashMap<String, u32>>,
    /// How far the projection has moved each material since [`Surrogate::take_corrections`].
    pub(super) corrections: std::sync::Mutex<Correction>,
    /// The same for the calls projected on the device, summed there until taken.
    pub(super) device_moves: std::sync::Mutex<DeviceMoves<B>>,
    /// The last grid call's material one-hot on the device, by the materials it encodes
    /// (`grid_step.rs`): a rollout's or a node's calls read the same materials call after
    /// call, so it is uploaded once, not every call (at 256 scenes of 2,500 particles, 12.8 MB).
    pub(super) one_hot: std::sync::Mutex<Option<(Vec<u8>, burn::tensor::Tensor<B, 3>)>>,
    /// The last device plan laid out, which the next call of the same scenes reuses with its
    /// copy on the device (`ConstraintState::device_plan`).
    pub(super) plans: std::sync::Mutex<PlanCache>,
}

impl<B: NetOps> Surrogate<B> {
    /// Loads a run folder (either architecture).
    pub fn load(dir: &Path, device: &B::Device) -> Result<Self, StoreError> {
        RunFolder::new(dir).surrogate(device)
    }

    /// Wraps an in-memory paper model.
    pub fn new(model: Model<B>, meta: ModelMeta, device: &B::Device) -> Self {
        Self::from_net(Net::Paper(model), meta, device)
    }

    /// Wraps an in-memory network of either architecture.
    pub fn from_net(net: Net<B>, meta: ModelMeta, device: &B::Device) -> Self {
        let scaling = meta.scaling();
        let constraints = meta.constraints.clone().filter(|c| !c.is_empty());
        Self {
            net,
            meta,
            scaling,
            device: device.clone(),
            mirror: false,
            pad_batches: false,
            // On the host nothing runs ahead of the caller: the call-by-call loop.
            feedback_bytes: if B::ON_HOST { 0 } else { feedback_bytes() },
            constraints,
            solver_grid: None,
            solver_grids: Default::default(),
            corrections: Default::default(),
            device_moves: std::sync::Mutex::new(DeviceMoves::default()),
            one_hot: Default::default(),
            plans: Default::default(),
        }
    }

    /// This surrogate serving scenes the solver made on a `grid` x `grid` grid (`node
    /// --solver-grid`): the liquid's pressure part picks its threshold by it
    /// ([`crate::model::constraints::PressureParams::rest_for`]); None: unknown.
    pub fn with_solver_grid(self, grid: Option<u32>) -> Self {
        Self {
            solver_grid: grid,
            ..self
        }
    }

    /// This surrogate projecting its predictions onto the `parts` of the model's constraints
    /// (`--constraints`; all of them by default, when `model.json` has any). Applies from
    /// the next step; states made before keep their scenes' constraint data.
    pub fn with_constraints(self, parts: Parts) -> Self {
        let constraints = self.meta.constraints.as_ref().map(|c| c.select(parts));
        Self {
            constraints: constraints.filter(|c| !c.is_empty()),
            ..self
        }
    }

    /// The constraints applied after each predicted frame, if any.
    pub fn constraints(&self) -> Option<&Constraints> {
        self.constraints.as_ref()
    }

    /// How far the projection moved each material since the last call (particle spacings,
    /// summed over particles and frames, with their count); resets the sums.
    pub fn take_corrections(&self) -> Correction {
        let mut sums = self.corrections.lock().unwrap_or_else(|e| e.into_inner());
        let mut taken = std::mem::take(&mut *sums);
        let mut held = self.device_moves.lock().unwrap_or_else(|e| e.into_inner());
        taken.add(&std::mem::take(&mut *held).read());
        taken
    }

    /// This surrogate as a mirror ensemble (`--mirror`): a grid model steps each frame and
    /// its mirror image about the box's vertical midline (`x -> 1 - x`, `vx -> -vx`) as two
    /// batch rows, each with its own state, and predicts the mean of the first row's
    /// prediction and the second's mirrored back. MPM's box, walls (nodes `< 3` or `> n - 3`:
    /// free from 2.5 to n - 2.5 cells) and gravity are symmetric under that mirror, so the
    /// mirrored scene is one the model could have been trained on: test-time augmentation
    /// by a symmetry of the physics. Twice the work of a step; no effect on a paper model
    /// (its output is tied to particle index, not position). States made before this was
    /// switched do not fit: switch it before [`Surrogate::init_state`].
    pub fn with_mirror(self, mirror: bool) -> Self {
        Self { mirror, ..self }
    }

    /// This surrogate padding each call of [`Surrogate::step_scenes`] to a power-of-two
    /// number of scenes (copies of its last scene, their results dropped): on a GPU every new
    /// batch shape costs kernel compilation and autotuning, and a dynamic batcher's calls
    /// come in every size from 1 to `--max-batch`; padded, they come in log2 of that many
    /// (Triton's "preferred batch sizes" do the same). The predictions are unchanged.
    pub fn with_padded_batches(self, pad_batches: bool) -> Self {
        Self {
            pad_batches,
            ..self
        }
    }

    /// This surrogate holding at most `bytes` of predicted frames on the device in a
    /// closed-loop rollout before reading them back ([`Surrogate::rollout_batch`]; default
    /// [`FEEDBACK_BYTES`] or `MINFLOW_FEEDBACK_BYTES` on a GPU, 0 on the CPU, where the device
    /// is the host; at least one call's frames are always held). Less device memory, more
    /// waits; the frames are the same. 0 turns the device-side loop off: each call's frames
    /// go through the host.
    pub fn with_feedback_bytes(self, bytes: usize) -> Self {
        Self {
            feedback_bytes: bytes,
            ..self
        }
    }

    /// The scenes a call of `b` scenes carries: `b`, or the next power of two when
    /// [`Surrogate::with_padded_batches`] is on.
    pub(super) fn padded(&self, b: usize) -> usize {
        match self.pad_batches {
            true => b.next_power_of_two(),
            false => b,
        }
    }

    /// Whether [`Surrogate::with_mirror`] is on (and the model is a grid model).
    pub fn mirrored(&self) -> bool {
        self.mirror && matches!(self.net, Net::Grid(_))
    }

    /// The model's description.
    pub fn meta(&self) -> &ModelMeta {
        &self.meta
    }

    /// A fresh (empty) state. The batch size is set by the first `step`.
    pub fn init_state(&self) -> State<B> {
        let mut state = State::new(self.fresh_net_state());
        state.constraints.solver_grids = vec![self.solver_grid];
        state
    }

    /// [`Surrogate::init_state`] for the scene `scene`: its solver grid from
    /// [`Surrogate::with_solver_grids`] when named there.
    pub fn init_state_for(&self, scene: &str) -> State<B> {
        let mut state = self.init_state();
        if let Some(&grid) = self.solver_grids.get(scene) {
            state.constraints.solver_grids = vec![Some(grid)];
        }
        state
    }

    /// This surrogate knowing the solver grid of each scene in `grids` (scene id -> cells
    /// per side; `node --solver-grid-from BAGS`, read from the bags' metadata), for the
    /// states [`Surrogate::init_state_for`] makes.
    pub fn with_solver_grids(self, grids: std::collections::HashMap<String, u32>) -> Self {
        Self {
            solver_grids: std::sync::Arc::new(grids),
            ..self
        }
    }

    /// The network's part of a fresh state.
    fn fresh_net_state(&self) -> NetState<B> {
        match &self.net {
            Net::Paper(model) => NetState::Paper(model.core.init_state()),
            Net::Grid(_) => NetState::Grid(GridState::new()),
        }
    }

    /// `state` reset as at the start of a stream (memory, velocity history, frame count,
    /// advected F: fitted again to the rest neighbourhoods from the next frame), except that a
    /// grid model's reference positions and rest neighbourhoods, and the constraint data, are
    /// kept: what the node does over a gap in a stream that goes on.
    pub fn restart(&self, state: State<B>) -> State<B> {
        state.restart(self.fresh_net_state())
    }

    /// A fresh state whose reference positions are those of `first` (`[B, N, 4]` physical
    /// frames: the first frame of each trajectory, when the prediction starts later in it).
    /// Without this the first frame a state steps on is taken as the reference. Only a grid
    /// model trained with `--reference first-frame` reads it; for others this is
    /// [`Surrogate::init_state`].
    ///
    /// # Errors
    /// [`StoreError::Shape`] when `first` is not `b` frames of 4 values per particle.
    pub fn init_state_at(&self, first: &[f32], b: usize) -> Result<State<B>, StoreError> {
        let mut state = self.init_state();
        if b == 0 || first.len() % (4 * b) != 0 {
            return Err(StoreError::Shape(format!(
                "reference: {} state values for {b} frames",
                first.len()
            )));
        }
        state.constraints.rest_frames = Some(first.to_vec());
        if let NetState::Grid(grid) = &mut state.net {
            grid.set_reference(first, b, self.mirror, &self.device);
        }
        Ok(state)
    }

    /// Frames one network call predicts (K, `train --bundle`): 1 for the paper's model and
    /// a single-frame grid model.
    pub fn bundle(&self) -> usize {
        match &self.net {
            Net::Grid(model) => model.bundle(),
            Net::Paper(_) => 1,
        }
    }
}

/// How many bytes of predicted frames a device-side closed-loop rollout
/// ([`Surrogate::rollout_batch`] of a grid model) holds on the device before reading them
/// back, by default ([`Surrogate::with_feedback_bytes`]): 512 MiB, about 50 frames of 256
/// scenes of 2,500 particles. Each read back makes the host wait for the device, which then
/// idles while the host records the next call.
pub const FEEDBACK_BYTES: usize = 512 << 20;

/// [`FEEDBACK_BYTES`], or the bytes `MINFLOW_FEEDBACK_BYTES` names (0: every call's frames
/// through the host, as before the device-side loop; read once).
fn feedback_bytes() -> usize {
    crate::switches::feedback_bytes().unwrap_or(FEEDBACK_BYTES)
}
