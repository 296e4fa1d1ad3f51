//! One step of a [`Surrogate`]: its input checked ([`Surrogate::step`],
//! [`Surrogate::step_bundle`]), the network's call (the paper's model here, a grid model's
//! in `grid_step.rs`, a mirror ensemble's two rows averaged), and the predicted frames
//! projected onto the model's constraints where they are on. `submit_here` and
//! `finish_here` are the two halves dynamic batching (`batch.rs`) calls apart.

use super::constrained::ConstraintState;
use super::grid_state::{mean_of_mirror_rows, with_mirror_rows};
use super::outs::{Outs, Read};
use super::state::{NetState, State};
use super::surrogate::{Predict, Surrogate};
use super::{Net, StoreError};
use crate::model::{LayerState, Model};
use crate::ops::{NetOps, ProjectionPlan};

impl<B: NetOps> Surrogate<B> {
    /// Predicts the next frame of each trajectory in the batch and advances the state. A
    /// bundled model (K > 1) makes a whole call and returns its first frame; its state then
    /// goes on from `frames` (the next input is the next observed frame): what a node fed
    /// live frames does on the frames where it calls the network.
    ///
    /// # Shapes
    /// - `frames`: `[B, N, 4]` physical x, y, vx, vy; `material`: `[B, N]`; `dt`: `[B]`
    /// - returns `[B, N, 4]` physical, the frame `dt` later
    ///
    /// # Errors
    /// [`StoreError::Shape`] when the lengths disagree or the model is tied to another N.
    pub fn step(
        &self,
        frames: &[f32],
        material: &[u8],
        dt: &[f32],
        state: State<B>,
    ) -> Result<(Vec<f32>, State<B>), StoreError> {
        // On the CPU: on the rayon pool with a worker awake (`NetOps::run_step`).
        let (mut out, state) =
            B::run_step(|| self.step_here(frames, material, dt, state, Predict::Next))?;
        Ok((out.swap_remove(0), state))
    }

    /// One network call: the next K = [`Surrogate::bundle`] frames of each trajectory in the
    /// batch, oldest first, and the state after the last of them (its velocity history ends
    /// with the bundle's frames: the next call reads the bundle's last frame). A rollout of
    /// H frames takes ceil(H / K) calls.
    ///
    /// # Shapes
    /// As [`Surrogate::step`]; returns K frames of `[B, N, 4]`.
    ///
    /// # Errors
    /// As [`Surrogate::step`].
    pub fn step_bundle(
        &self,
        frames: &[f32],
        material: &[u8],
        dt: &[f32],
        state: State<B>,
    ) -> Result<(Vec<Vec<f32>>, State<B>), StoreError> {
        B::run_step(|| self.step_here(frames, material, dt, state, Predict::Bundle))
    }

    /// [`Surrogate::step`] ([`Predict::Next`]) or [`Surrogate::step_bundle`]
    /// ([`Predict::Bundle`]) on the calling thread: the network's step, then the projection
    /// onto the constraints where they are on.
    pub(super) fn step_here(
        &self,
        frames: &[f32],
        material: &[u8],
        dt: &[f32],
        state: State<B>,
        predict: Predict,
    ) -> Result<(Vec<Vec<f32>>, State<B>), StoreError> {
        let (outs, mut state) =
            self.submit_here(frames, material, dt, state, predict, Read::Now)?;
        let history = match predict {
            Predict::Bundle => Some(&mut state.net),
            Predict::Next => None,
        };
        let input = (frames, material, dt);
        let out = self.finish_here(outs, input, &mut state.constraints, history)?;
        Ok((out, state))
    }

    /// The network's part of [`Surrogate::step_here`]: the call recorded, its predictions
    /// read as `read` says, the state after it (its frame count advanced; its constraint
    /// data used only by [`Surrogate::finish_here`]).
    pub(super) fn submit_here(
        &self,
        frames: &[f32],
        material: &[u8],
        dt: &[f32],
        state: State<B>,
        predict: Predict,
        read: Read,
    ) -> Result<(Outs, State<B>), StoreError> {
        self.check_step(frames, material, dt)?;
        let State {
            net,
            mut constraints,
            frames: count,
        } = state;
        // A pipelined caller (the node: `Read::Ahead`) projects on the host, where the
        // projection of one call overlaps the GPU's next: on one H100 at 256 streams x 62.5 Hz
        // the node delivered 8,905 / 9,953 predictions/s so (`-small-k4`, `all-grid-mingru`)
        // against 6,634 / 7,995 with the device's (docs/cuda.md).
        let plan = match (&self.constraints, &self.net) {
            (Some(c), Net::Grid(_))
                if B::projects_constraints() && !self.mirror && read == Read::Now =>
            {
                constraints.device_plan(c, (frames, material, dt), &self.plans)
            }
            _ => None,
        };
        let (outs, net, on_device) =
            self.net_step(frames, material, dt, net.owned(), (predict, read), plan)?;
        constraints.on_device = on_device;
        let state = State {
            net,
            constraints,
            frames: count + 1,
        };
        Ok((outs, state))
    }

    /// The rest of [`Surrogate::step_here`] once the predictions are wanted: `outs` on the
    /// host, projected onto the constraints where they are on (`constraints`, the call's
    /// constraint data, `input` its input frames, materials and time steps); a bundle's
    /// velocity history (`history`, the network state after a [`Predict::Bundle`] call)
    /// then follows the projected frames.
    ///
    /// # Errors
    /// The predictions could not be read back.
    pub(super) fn finish_here(
        &self,
        outs: Outs,
        (frames, material, dt): (&[f32], &[u8], &[f32]),
        constraints: &mut ConstraintState,
        history: Option<&mut NetState<B>>,
    ) -> Result<Vec<Vec<f32>>, StoreError> {
        let mut out = outs.wait()?;
        let on_device = std::mem::take(&mut constraints.on_device);
        if let Some(c) = self.constraints.as_ref().filter(|_| !on_device) {
            let moved = constraints.project(c, (frames, material, dt), &mut out);
            let mut sums = self.corrections.lock().unwrap_or_else(|e| e.into_inner());
            for m in &moved {
                sums.add(m);
            }
            if let Some(NetState::Grid(grid)) = history {
                let b = dt.len();
                grid.history_from(&out, [b, material.len() / b.max(1)], &self.device);
            }
        }
        constraints.rest_frames = None;
        Ok(out)
    }

    /// `[B, N]` of a step's input (`frames` `[B, N, 4]`, `material` `[B N]`, `dt` `[B]`).
    ///
    /// # Errors
    /// [`StoreError::Shape`] when the lengths disagree, the model is tied to another N or a
    /// material id is one the model does not know.
    pub(super) fn check_step(
        &self,
        frames: &[f32],
        material: &[u8],
        dt: &[f32],
    ) -> Result<[usize; 2], StoreError> {
        let b = dt.len();
        let n = material.len().checked_div(b).unwrap_or(0);
        if b == 0 || frames.len() != b * n * 4 || material.len() != b * n {
            return Err(StoreError::Shape(format!(
                "step: {} state values, {} materials for {b} frames",
                frames.len(),
                material.len()
            )));
        }
        if let Some(expected) = self.meta.fixed_particles().filter(|&e| e != n) {
            return Err(StoreError::Shape(format!(
                "model was trained for N = {expected} particles, frame has {n}"
            )));
        }
        let known = self.meta.materials();
        if let Some(&m) = material.iter().find(|&&m| usize::from(m) >= known) {
            return Err(StoreError::Shape(format!(
                "material id {m}: the model knows {known} materials (ids 0..{known})"
            )));
        }
        Ok([b, n])
    }

    /// The network's part of a step: the predicted frames, the network's next state and
    /// whether the frames were projected on the device (a grid model's call with a `plan`,
    /// [`Surrogate::grid_step`]); a mirror ensemble's grid model steps each frame beside its
    /// mirror image and returns their mean.
    fn net_step(
        &self,
        frames: &[f32],
        material: &[u8],
        dt: &[f32],
        net: NetState<B>,
        (predict, read): (Predict, Read),
        plan: Option<ProjectionPlan>,
    ) -> Result<(Outs, NetState<B>, bool), StoreError> {
        match (&self.net, net) {
            (Net::Paper(model), NetState::Paper(layers)) => {
                let (out, layers) = self.paper_step(model, frames, material, dt, layers)?;
                Ok((Outs::Host(vec![out]), NetState::Paper(layers), false))
            }
            (Net::Grid(model), NetState::Grid(grid)) if self.mirror => {
                let (material, dt) = ([material, material].concat(), [dt, dt].concat());
                let frames = with_mirror_rows(frames);
                let call = (predict, Read::Now, None);
                let (out, grid, _) = self.grid_step(model, &frames, &material, &dt, grid, call)?;
                let out = out.wait()?.iter().map(|o| mean_of_mirror_rows(o)).collect();
                Ok((Outs::Host(out), NetState::Grid(grid), false))
            }
            (Net::Grid(model), NetState::Grid(grid)) => {
                let call = (predict, read, plan);
                let (out, grid, on_device) =
                    self.grid_step(model, frames, material, dt, grid, call)?;
                Ok((out, NetState::Grid(grid), on_device))
            }
            _ => Err(StoreError::Shape("state of another architecture".into())),
        }
    }

    /// One step of the paper's model: the next frame (`[B, N, 4]` physical) and the core's
    /// next layer states.
    fn paper_step(
        &self,
        model: &Model<B>,
        frames: &[f32],
        material: &[u8],
        dt: &[f32],
        layers: Vec<LayerState<B>>,
    ) -> Result<(Vec<f32>, Vec<LayerState<B>>), StoreError> {
        let b = dt.len();
        let n = material.len() / b;
        // The training batches' own scaling (data::Scaler), so inputs match training.
        let mut feats = Vec::with_capacity(b * n * 5);
        self.meta.scaler.scale_into(frames, material, &mut feats);
        let x = crate::model::upload::<B, 3>(feats, [b, n, 5], &self.device);
        let dt_t = crate::model::upload::<B, 1>(dt.to_vec(), [b], &self.device);
        let (out, layers) = model.step(x, dt_t, layers, &self.scaling);
        let mut out = crate::model::download(out)?;
        self.meta.scaler.unscale_rows(&mut out, 4);
        Ok((out, layers))
    }
}
