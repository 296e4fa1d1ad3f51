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

use super::constrained::ConstraintState;
use super::outs::{Outs, Read};
use super::state::{mean_of_mirror_rows, with_mirror_rows, GridState, NetState, State};
use super::{ModelMeta, Net, RunFolder, StoreError};
use crate::model::constraints::{Constraints, Correction, Parts};
use crate::model::{LayerState, Model, Scaling};
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
    net: Net<B>,
    /// The model's description (`model.json`).
    pub(super) meta: ModelMeta,
    scaling: Scaling,
    /// Where the network runs.
    pub(super) device: B::Device,
    mirror: bool,
    pad_batches: bool,
    /// Bytes of predicted frames a device-side rollout holds before reading them back
    /// ([`Surrogate::with_feedback_bytes`]).
    feedback_bytes: usize,
    /// The constraint parts applied after each predicted frame (None: no projection).
    constraints: Option<Constraints>,
    /// How far the projection has moved each material since [`Surrogate::take_corrections`].
    corrections: std::sync::Mutex<Correction>,
    /// The last grid call's material one-hot on the device, by the materials it encodes
    /// (`grid_step.rs`): a rollout's or a node's calls read the same materials call after
    /// call, so it is uploaded once, not every call (at 256 scenes of 2,500 particles, 12.8 MB).
    pub(super) one_hot: std::sync::Mutex<Option<(Vec<u8>, burn::tensor::Tensor<B, 3>)>>,
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
            corrections: Default::default(),
            one_hot: Default::default(),
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
        std::mem::take(&mut *sums)
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
        State::new(self.fresh_net_state())
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
            constraints,
            frames: count,
        } = state;
        let (outs, net) = self.net_step(frames, material, dt, net.owned(), predict, read)?;
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
        if let Some(c) = &self.constraints {
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
    fn check_step(
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

    /// The network's part of a step: the predicted frames and the network's next state; a
    /// mirror ensemble's grid model steps each frame beside its mirror image and returns
    /// their mean.
    fn net_step(
        &self,
        frames: &[f32],
        material: &[u8],
        dt: &[f32],
        net: NetState<B>,
        predict: Predict,
        read: Read,
    ) -> Result<(Outs, NetState<B>), StoreError> {
        match (&self.net, net) {
            (Net::Paper(model), NetState::Paper(layers)) => {
                let (out, layers) = self.paper_step(model, frames, material, dt, layers)?;
                Ok((Outs::Host(vec![out]), NetState::Paper(layers)))
            }
            (Net::Grid(model), NetState::Grid(grid)) if self.mirror => {
                let (material, dt) = ([material, material].concat(), [dt, dt].concat());
                let frames = with_mirror_rows(frames);
                let (out, grid) =
                    self.grid_step(model, &frames, &material, &dt, grid, predict, Read::Now)?;
                let out = out.wait()?.iter().map(|o| mean_of_mirror_rows(o)).collect();
                Ok((Outs::Host(out), NetState::Grid(grid)))
            }
            (Net::Grid(model), NetState::Grid(grid)) => {
                let (out, grid) =
                    self.grid_step(model, frames, material, dt, grid, predict, read)?;
                Ok((out, NetState::Grid(grid)))
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

    /// Seeds with `seed` frames (each `[N, 4]` physical, one trajectory) and predicts `k`
    /// frames autoregressively, feeding predictions back. Returns the `k` predicted frames.
    /// `first`, the trajectory's first frame (`[N, 4]`), sets the reference positions (see
    /// [`Surrogate::init_state_at`]); without it the first seed frame is the reference.
    ///
    /// # Errors
    /// A step's [`StoreError`].
    pub fn rollout(
        &self,
        first: Option<&[f32]>,
        seed: &[Vec<f32>],
        material: &[u8],
        dt: f32,
        k: usize,
    ) -> Result<Vec<Vec<f32>>, StoreError> {
        let mut frames = Vec::with_capacity(k);
        self.rollout_batch(first, seed, material, &[dt], k, |_, f| frames.push(f))?;
        Ok(frames)
    }

    /// [`Surrogate::rollout`] of a batch of B trajectories at once (`seed` frames, `first`,
    /// `material` and the results `[B, N, 4]`, `dt` `[B]`): the seed frames but the last are
    /// stepped on, then ceil(k / K) network calls each start from the last frame the call
    /// before predicted; `each(i, frame)` is handed predicted frame i (0-based) of the `k`,
    /// in order, to keep (no copy is made for it, but a bundle's frames are cut apart). On a
    /// GPU a grid model without projection or mirror keeps the loop on the device
    /// ([`Surrogate::with_feedback_bytes`]), so `each` then gets the frames in batches.
    ///
    /// # Errors
    /// A step's [`StoreError`]; no seed frame. The frames predicted before a failed call
    /// have reached `each`.
    pub fn rollout_batch(
        &self,
        first: Option<&[f32]>,
        seed: &[Vec<f32>],
        material: &[u8],
        dt: &[f32],
        k: usize,
        mut each: impl FnMut(usize, Vec<f32>),
    ) -> Result<(), StoreError> {
        let mut state = match first {
            Some(frame) => self.init_state_at(frame, dt.len())?,
            None => self.init_state(),
        };
        if seed.is_empty() {
            return Err(StoreError::Shape("rollout: no seed frame".into()));
        }
        let on_device = self.feedback_bytes > 0 && self.constraints.is_none() && !self.mirror;
        if let (Net::Grid(model), true) = (&self.net, on_device) {
            for frame in seed {
                self.check_step(frame, material, dt)?;
            }
            let NetState::Grid(carry) = state.net.owned() else {
                return Err(StoreError::Shape("state of another architecture".into()));
            };
            return self.grid_rollout(model, seed, (material, dt), k, carry, each);
        }
        let (last, before) = seed.split_last().expect("a seed frame");
        for frame in before {
            state = self.step(frame, material, dt, state)?.1;
        }
        // The last frame of each call is the next call's input: it is handed to `each` once
        // that call has run (`held`, its index), so no frame is copied.
        let (mut done, mut input, mut held) = (0, last.clone(), None);
        while done < k {
            let called = self.step_bundle(&input, material, dt, state);
            if let Some(i) = held.take() {
                each(i, std::mem::take(&mut input));
            }
            let (bundle, s) = called?;
            state = s;
            let take = bundle.len().min(k - done);
            for frame in bundle.into_iter().take(take) {
                if let Some(i) = held.replace(done) {
                    each(i, std::mem::replace(&mut input, frame));
                } else {
                    input = frame;
                }
                done += 1;
            }
        }
        if let Some(i) = held {
            each(i, input);
        }
        Ok(())
    }

    /// The closed loop of [`Surrogate::rollout_batch`] for a grid model without projection
    /// or mirror: each call's last predicted frame is fed back on the device (no download
    /// and upload between calls), and the predictions are read back together once
    /// [`Surrogate::with_feedback_bytes`] of them are held or the rollout ends. On a GPU the
    /// host then never waits between calls, so it records call c + 1 while the device runs
    /// call c; the frames are the ones the call-by-call loop gives (the same values go back
    /// in).
    fn grid_rollout(
        &self,
        model: &crate::model::grid::GridModel<B>,
        seed: &[Vec<f32>],
        (material, dt): (&[u8], &[f32]),
        k: usize,
        mut carry: GridState<B>,
        mut each: impl FnMut(usize, Vec<f32>),
    ) -> Result<(), StoreError> {
        let b = dt.len();
        let n = material.len() / b;
        let bundle = model.bundle();
        let per_flush = (self.feedback_bytes / (b * n * 4 * 4).max(1)).max(1);
        let upload = |f: &[f32]| crate::model::upload::<B, 3>(f.to_vec(), [b, n, 4], &self.device);
        let (last, before) = seed.split_last().expect("a seed frame");
        // The seed frames but the last only carry the state on: their predictions are
        // dropped unread, so the host does not wait for them either.
        for f in before {
            let mut none = None;
            carry = B::run_step(|| {
                self.grid_call(
                    model,
                    upload(f),
                    material,
                    dt,
                    carry,
                    Predict::Next,
                    &mut none,
                )
            })?
            .1;
        }
        let mut frame = upload(last);
        let (mut pending, mut held, mut recorded, mut done) = (Vec::new(), 0, 0, 0);
        while recorded < k {
            let mut clock = super::stages::Clock::start();
            let called = B::run_step(|| {
                self.grid_call(
                    model,
                    frame,
                    material,
                    dt,
                    carry,
                    Predict::Bundle,
                    &mut clock,
                )
            });
            let (next, c) = match called {
                Ok(call) => call,
                Err(e) => {
                    // The frames predicted before still reach `each`, as in the host loop.
                    self.deliver(&mut pending, b, &mut clock, (&mut each, &mut done))?;
                    return Err(e);
                }
            };
            carry = c;
            let take = bundle.min(k - recorded);
            frame = next.clone().narrow(0, (bundle - 1) * b, b);
            pending.push(match take == bundle {
                true => next,
                false => next.narrow(0, 0, take * b),
            });
            (held, recorded) = (held + take, recorded + take);
            // Read back call by call: one call's frames stay under the 100 MB up to which
            // cubecl-cuda reads through its pinned buffers (`command.rs`); 20 calls' frames
            // of 256 scenes read as one tensor (200 MB, pageable) took 0.6 s on an H100,
            // call by call 1.6 ms each.
            if recorded == k || held >= per_flush {
                self.deliver(&mut pending, b, &mut clock, (&mut each, &mut done))?;
                held = 0;
            }
        }
        Ok(())
    }

    /// Reads the held calls' frames back (`pending`: `[K B, N, 4]` each, oldest first), call
    /// by call, and hands them to `each` as frames `done`, `done + 1`, ...
    fn deliver(
        &self,
        pending: &mut Vec<burn::tensor::Tensor<B, 3>>,
        b: usize,
        clock: &mut Option<super::stages::Clock>,
        (each, done): (&mut impl FnMut(usize, Vec<f32>), &mut usize),
    ) -> Result<(), StoreError> {
        for next in std::mem::take(pending) {
            for f in self.download_frames(next, b, clock)? {
                each(*done, f);
                *done += 1;
            }
        }
        Ok(())
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
