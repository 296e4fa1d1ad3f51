//! [`Surrogate`]: a trained model of either architecture ready for step-by-step prediction in
//! physical units (scaling inside), with one [`State`] per batch of trajectories: the paper
//! core's layer states, or the grid model's per-particle memory, velocity history and
//! reference positions. `step` predicts the next frame, `step_bundle` the K frames of one
//! network call (temporal bundling), `rollout` feeds predictions back; a mirror ensemble
//! steps each frame beside its mirror image. Every predicted frame is then projected onto
//! the model's material constraints ([`crate::model::constraints`]) where the model has
//! them and they are on ([`Surrogate::with_constraints`]); a scene's constraint data lives
//! in its [`State`] beside the network's. Used by `eval`, `node`, `report`, `bench` and the
//! grid trainer's validation.

use super::stack::{mean_of_mirror_rows, with_mirror_rows};
use super::{ModelMeta, Net, RunFolder, StoreError};
use crate::model::constraints::{Constraints, Correction, Parts, SceneShape};
use crate::model::grid::{
    one_hot, GridModel, MemoryState, NeighbourTensors, Neighbourhood, StepInput,
};
use crate::model::{LayerState, Model, Scaling};
use crate::ops::NetOps;
use burn::tensor::backend::Backend;
use burn::tensor::Tensor;
use std::path::Path;

/// A trained model ready for step-by-step prediction in physical units.
pub struct Surrogate<B: Backend> {
    net: Net<B>,
    meta: ModelMeta,
    scaling: Scaling,
    device: B::Device,
    mirror: bool,
    pad_batches: bool,
    /// The constraint parts applied after each predicted frame (None: no projection).
    constraints: Option<Constraints>,
    /// How far the projection has moved each material since [`Surrogate::take_corrections`].
    corrections: std::sync::Mutex<Correction>,
}

/// What a grid model carries between steps: memory, velocity history, reference positions,
/// the rest neighbourhoods built from them and the advected deformation gradient.
type GridCarry<B> = (
    MemoryState<B>,
    Option<Tensor<B, 3>>,
    Option<Tensor<B, 3>>,
    Option<NeighbourTensors<B>>,
    Option<Tensor<B, 3>>,
);

/// Per-trajectory state (one batch row per trajectory).
#[derive(Clone)]
pub struct State<B: Backend> {
    pub(super) inner: NetState<B>,
    /// Per trajectory (batch row): its constraint data, built from its rest frame on the
    /// first projected step (empty before; see [`Surrogate::with_constraints`]).
    pub(super) shapes: Vec<Option<SceneShape>>,
    /// The rest frames (`[B, N, 4]`) set by [`Surrogate::init_state_at`] that the first
    /// projected step builds `shapes` from; without them it takes its input frame.
    pub(super) rest_frames: Option<Vec<f32>>,
    /// Frames consumed since the state was reset.
    pub frames: usize,
}

/// What each architecture carries between frames (stacked and split in `stack.rs`).
#[derive(Clone)]
pub(super) enum NetState<B: Backend> {
    /// The paper core's layer states.
    Paper(Vec<LayerState<B>>),
    /// The grid model's per-particle memory, the velocities of the last T - 1 frames
    /// (`[B, N, 2 (T - 1)]`, oldest first; `None` before the first frame or when T = 1) and
    /// the reference positions (`[B, N, 2]`: the first frame's, unless set by
    /// [`Surrogate::init_state_at`]; read only by a model with `reference`), and the rest
    /// neighbourhoods of the reference positions (built on the first step of a model with
    /// `rest_shape`: the scene's physical state beside its memory, kept across a restart),
    /// and the advected deformation gradient (`[B, N, 4]`, a model with `Deformation::Advect`:
    /// the F of the frame the next step reads; `None` before the first step and after a
    /// restart, when the step starts it from the fit to the rest neighbourhoods).
    Grid {
        memory: MemoryState<B>,
        history: Option<Tensor<B, 3>>,
        reference: Option<Tensor<B, 3>>,
        rest: Option<NeighbourTensors<B>>,
        deformation: Option<Tensor<B, 3>>,
    },
}

impl<B: NetOps> Surrogate<B> {
    /// Loads a run folder (either architecture).
    pub fn load(dir: &Path, device: &B::Device) -> Result<Self, StoreError> {
        RunFolder::open(dir)?.surrogate(device)
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
            constraints,
            corrections: Default::default(),
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
        let inner = match &self.net {
            Net::Paper(model) => NetState::Paper(model.core.init_state()),
            Net::Grid(_) => NetState::Grid {
                memory: MemoryState::Empty,
                history: None,
                reference: None,
                rest: None,
                deformation: None,
            },
        };
        State {
            inner,
            shapes: Vec::new(),
            rest_frames: None,
            frames: 0,
        }
    }

    /// `state` reset as at the start of a stream (memory, velocity history, frame count,
    /// advected F: fitted again to the rest neighbourhoods from the next frame), except that a
    /// grid model's reference positions and rest neighbourhoods, and the constraint data, are
    /// kept: what the node does over a gap in a stream that goes on.
    pub fn restart(&self, state: State<B>) -> State<B> {
        let mut fresh = self.init_state();
        (fresh.shapes, fresh.rest_frames) = (state.shapes, state.rest_frames);
        if let (
            NetState::Grid {
                reference, rest, ..
            },
            NetState::Grid {
                reference: kept,
                rest: kept_rest,
                ..
            },
        ) = (&mut fresh.inner, state.inner)
        {
            *reference = kept;
            *rest = kept_rest;
        }
        fresh
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
        state.rest_frames = Some(first.to_vec());
        if let NetState::Grid { reference, .. } = &mut state.inner {
            let (first, b) = if self.mirror {
                (with_mirror_rows(first), 2 * b)
            } else {
                (first.to_vec(), b)
            };
            let n = first.len() / (4 * b);
            let frame = crate::model::upload::<B, 3>(first, [b, n, 4], &self.device);
            *reference = Some(frame.narrow(2, 0, 2));
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
        let (mut out, state) = B::run_step(|| self.step_here(frames, material, dt, state, false))?;
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
        B::run_step(|| self.step_here(frames, material, dt, state, true))
    }

    /// [`Surrogate::step`] (`whole`: false) or [`Surrogate::step_bundle`] (true) on the
    /// calling thread.
    pub(super) fn step_here(
        &self,
        frames: &[f32],
        material: &[u8],
        dt: &[f32],
        state: State<B>,
        whole: bool,
    ) -> Result<(Vec<Vec<f32>>, State<B>), StoreError> {
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
        let (mut out, mut inner) = match (&self.net, state.inner) {
            (Net::Paper(model), NetState::Paper(layers)) => {
                // The training batches' own scaling (data::Scaler), so inputs match training.
                let mut feats = Vec::with_capacity(b * n * 5);
                self.meta.scaler.scale_into(frames, material, &mut feats);
                let x = crate::model::upload::<B, 3>(feats, [b, n, 5], &self.device);
                let dt_t = crate::model::upload::<B, 1>(dt.to_vec(), [b], &self.device);
                let (out, layers) = model.step(x, dt_t, layers, &self.scaling);
                let mut out = crate::model::download(out)?;
                self.meta.scaler.unscale_rows(&mut out, 4);
                (vec![out], NetState::Paper(layers))
            }
            (
                Net::Grid(model),
                NetState::Grid {
                    memory,
                    history,
                    reference,
                    rest,
                    deformation,
                },
            ) => {
                let carry = (memory, history, reference, rest, deformation);
                if self.mirror {
                    let (material, dt) = ([material, material].concat(), [dt, dt].concat());
                    let frames = with_mirror_rows(frames);
                    let (out, inner) =
                        self.grid_step(model, &frames, &material, &dt, carry, whole)?;
                    (out.iter().map(|o| mean_of_mirror_rows(o)).collect(), inner)
                } else {
                    self.grid_step(model, frames, material, dt, carry, whole)?
                }
            }
            _ => return Err(StoreError::Shape("state of another architecture".into())),
        };
        let shapes = match &self.constraints {
            Some(c) => {
                let rest = state.rest_frames.as_deref();
                let shapes = self.project(c, (frames, material, dt), &mut out, state.shapes, rest);
                if whole {
                    self.history_of_projected(&mut inner, &out, [b, n]);
                }
                shapes
            }
            None => state.shapes,
        };
        Ok((
            out,
            State {
                inner,
                shapes,
                rest_frames: None,
                frames: state.frames + 1,
            },
        ))
    }

    /// Projects the predicted frames `out` (K frames of `[B, N, 4]`) of the input `frames`
    /// (`[B, N, 4]`, materials `[B N]`, time steps `[B]`) onto `c`, scene by scene in
    /// parallel; returns the scenes' constraint data, each built on its first projection from
    /// its row of `rest` (`[B, N, 4]`) or else of `frames`. Within a bundle, frame k + 1 is
    /// first moved by frame k's correction (the network integrated it from its own frame k),
    /// then projected. The moves are added to the surrogate's correction sums.
    fn project(
        &self,
        c: &Constraints,
        (frames, material, dt): (&[f32], &[u8], &[f32]),
        out: &mut [Vec<f32>],
        mut shapes: Vec<Option<SceneShape>>,
        rest: Option<&[f32]>,
    ) -> Vec<Option<SceneShape>> {
        use rayon::prelude::*;
        let b = dt.len();
        let n = material.len() / b;
        let per = n * 4;
        if shapes.len() != b {
            shapes = (0..b).map(|_| None).collect();
        }
        let rest = rest.filter(|r| r.len() == b * per).unwrap_or(frames);
        let mut rows: Vec<Vec<&mut [f32]>> =
            (0..b).map(|_| Vec::with_capacity(out.len())).collect();
        for frame in out.iter_mut() {
            for (row, chunk) in rows.iter_mut().zip(frame.chunks_exact_mut(per)) {
                row.push(chunk);
            }
        }
        let moved: Vec<Correction> = shapes
            .par_iter_mut()
            .zip(rows.par_iter_mut())
            .enumerate()
            .map(|(i, (shape, row))| {
                let ids = &material[i * n..(i + 1) * n];
                let shape = shape.get_or_insert_with(|| {
                    SceneShape::new(&rest[i * per..(i + 1) * per], 4, ids, c)
                });
                let mut total = Correction::default();
                let mut carried: Option<Vec<f32>> = None;
                let last = row.len().saturating_sub(1);
                for (k, frame) in row.iter_mut().enumerate() {
                    // The network's own frame, kept where its correction carries into the
                    // next frame (not after the bundle's last).
                    let own = (k < last).then(|| frame.to_vec());
                    if let Some(offset) = &carried {
                        for (v, o) in frame.iter_mut().zip(offset) {
                            *v += o;
                        }
                    }
                    total.add(&shape.project(c, frame, ids, dt[i]));
                    // The position correction relative to the network's own frame.
                    carried = own.map(|own| {
                        let mut offset: Vec<f32> =
                            frame.iter().zip(&own).map(|(a, b)| a - b).collect();
                        for o in offset.chunks_exact_mut(4) {
                            (o[2], o[3]) = (0.0, 0.0);
                        }
                        offset
                    });
                }
                total
            })
            .collect();
        let mut sums = self.corrections.lock().unwrap_or_else(|e| e.into_inner());
        for m in &moved {
            sums.add(m);
        }
        shapes
    }

    /// After a projected bundle (K frames `out`, `[B, N, 4]` each) of a grid model: its
    /// velocity history (`[copies B, N, 2 (T - 1)]`: the T - 1 frames before the next call's
    /// input, the bundle's last) taken from the projected frames, so the next call reads the
    /// velocities a caller feeding back the projected frames sees. Left as is when K <= T - 1.
    fn history_of_projected(&self, inner: &mut NetState<B>, out: &[Vec<f32>], [b, n]: [usize; 2]) {
        let NetState::Grid {
            history: Some(history),
            ..
        } = inner
        else {
            return;
        };
        let [rows, _, width] = history.dims();
        let (t1, k) = (width / 2, out.len());
        let copies = rows / b.max(1);
        if k <= t1 || rows != copies * b || !(1..=2).contains(&copies) {
            return;
        }
        let window = &out[k - 1 - t1..k - 1];
        let mut host = vec![0.0f32; rows * n * width];
        for copy in 0..copies {
            let sign = if copy == 1 { -1.0 } else { 1.0 };
            for p in 0..b * n {
                for (w, frame) in window.iter().enumerate() {
                    let at = ((copy * b * n + p) * t1 + w) * 2;
                    host[at] = sign * frame[4 * p + 2];
                    host[at + 1] = frame[4 * p + 3];
                }
            }
        }
        *history = crate::model::upload::<B, 3>(host, [rows, n, width], &self.device);
    }

    /// [`Surrogate::step`] (`whole`: false) or [`Surrogate::step_bundle`] (true) of a grid
    /// model: the velocity history is completed from the state (the current velocity
    /// repeated before T frames were seen, or when B or N changed), and the reference
    /// positions are this frame's when the state has none of this shape. Returns the K
    /// predicted frames (the first alone unless `whole`).
    fn grid_step(
        &self,
        model: &GridModel<B>,
        frames: &[f32],
        material: &[u8],
        dt: &[f32],
        (memory, history, reference, rest, deformation): GridCarry<B>,
        whole: bool,
    ) -> Result<(Vec<Vec<f32>>, NetState<B>), StoreError> {
        let (b, t) = (dt.len(), model.window());
        let n = material.len() / b;
        let frame = crate::model::upload::<B, 3>(frames.to_vec(), [b, n, 4], &self.device);
        let pos = frame.clone().narrow(2, 0, 2);
        let vel = frame.narrow(2, 2, 2);
        let history = history.filter(|h| h.dims() == [b, n, 2 * (t - 1)]);
        let reference = reference
            .filter(|r| r.dims() == [b, n, 2])
            .unwrap_or_else(|| pos.clone());
        let memory = match memory.rows() {
            Some(rows) if rows != b * n => MemoryState::Empty,
            _ => memory,
        };
        let vel_hist = match history {
            Some(h) => Tensor::cat(vec![h, vel.clone()], 2),
            None => vel.repeat_dim(2, t),
        };
        let rest = match rest.filter(|r| r.dims() == [b, n]) {
            Some(rest) => Some(rest),
            None if model.uses_rest_shape() => Some(self.rest_of(&reference, material, [b, n])?),
            None => None,
        };
        let input = StepInput {
            pos,
            vel: vel_hist.clone(),
            material: one_hot(material, self.meta.materials(), b, n, &self.device),
            dt: crate::model::upload::<B, 1>(dt.to_vec(), [b], &self.device),
            reference: Some(reference.clone()),
            rest: rest.clone(),
            deformation: deformation.filter(|f| f.dims() == [b, n, 4]),
        };
        let (mut outs, memory) = model.step_bundle(input, memory);
        if !whole {
            outs.truncate(1);
        }
        // The F of the frame the next call reads: the last one returned.
        let deformation = outs.last().and_then(|o| o.deformation.clone());
        // The T - 1 velocities before the next call's input frame: the input frame's own
        // window (the next observed frame follows it), or that window continued by the
        // bundle's frames but its last (the next call's input is that last frame).
        let mut window = vec![vel_hist];
        if whole {
            window.extend(outs[..outs.len() - 1].iter().map(|o| o.vel.clone()));
        }
        let window = Tensor::cat(window, 2);
        let width = window.dims()[2];
        let history = (t > 1).then(|| window.narrow(2, width - 2 * (t - 1), 2 * (t - 1)));
        let k = outs.len();
        let next = Tensor::cat(
            outs.into_iter()
                .map(|o| Tensor::cat(vec![o.pos, o.vel], 2))
                .collect(),
            0,
        ); // [K B, N, 4]
        let out = crate::model::download(next)?;
        let per_frame = b * n * 4;
        let out = (0..k)
            .map(|i| out[i * per_frame..(i + 1) * per_frame].to_vec())
            .collect();
        let reference = Some(reference);
        Ok((
            out,
            NetState::Grid {
                memory,
                history,
                reference,
                rest,
                deformation,
            },
        ))
    }

    /// The rest neighbourhoods of the solids' particles in `reference` (`[B, N, 2]`),
    /// materials `material` (`[B N]`): built once per scene on the host
    /// ([`Neighbourhood::build`]) and uploaded.
    fn rest_of(
        &self,
        reference: &Tensor<B, 3>,
        material: &[u8],
        [b, n]: [usize; 2],
    ) -> Result<NeighbourTensors<B>, StoreError> {
        let host = crate::model::download(reference.clone())?;
        Ok(Neighbourhood::build(&host, material, [b, n], |m| m != 0).upload(&self.device))
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
        self.rollout_batch(first, seed, material, &[dt], k, |_, f| {
            frames.push(f.to_vec())
        })?;
        Ok(frames)
    }

    /// [`Surrogate::rollout`] of a batch of B trajectories at once (`seed` frames, `first`,
    /// `material` and the results `[B, N, 4]`, `dt` `[B]`): the seed frames but the last are
    /// stepped on, then ceil(k / K) network calls each start from the last frame the call
    /// before predicted; `each(i, frame)` sees predicted frame i (0-based) of the `k`.
    ///
    /// # Errors
    /// A step's [`StoreError`]; no seed frame.
    pub fn rollout_batch(
        &self,
        first: Option<&[f32]>,
        seed: &[Vec<f32>],
        material: &[u8],
        dt: &[f32],
        k: usize,
        mut each: impl FnMut(usize, &[f32]),
    ) -> Result<(), StoreError> {
        let mut state = match first {
            Some(frame) => self.init_state_at(frame, dt.len())?,
            None => self.init_state(),
        };
        let Some((last, before)) = seed.split_last() else {
            return Err(StoreError::Shape("rollout: no seed frame".into()));
        };
        for frame in before {
            state = self.step(frame, material, dt, state)?.1;
        }
        let (mut done, mut input) = (0, last.clone());
        while done < k {
            let (bundle, s) = self.step_bundle(&input, material, dt, state)?;
            state = s;
            for frame in bundle.into_iter().take(k - done) {
                each(done, &frame);
                done += 1;
                input = frame;
            }
        }
        Ok(())
    }
}
