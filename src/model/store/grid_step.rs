//! A grid model's step inside [`Surrogate`]: its carried [`GridState`] fitted to the call
//! and turned into the network's [`StepInput`] (the velocity history completed, the
//! reference positions and rest neighbourhoods taken or built), the network's call, and the
//! state it leaves for the next call. Called by `Surrogate::step_here` (`step.rs`).

use burn::tensor::{Tensor, TensorPrimitive};

use super::grid_state::GridState;
use super::outs::{split_frames, Outs, Read};
use super::stages::{self, Stage};
use super::{Predict, StoreError, Surrogate};
use crate::model::grid::rest::advect::identity;
use crate::model::grid::{
    one_hot, GridModel, MemoryState, NeighbourTensors, Neighbourhood, StepInput,
};
use crate::model::roofline::{self, Part};
use crate::ops::{NetOps, ProjectionPlan, MATERIALS};

impl<B: NetOps> Surrogate<B> {
    /// [`Surrogate::step`] ([`Predict::Next`]) or [`Surrogate::step_bundle`]
    /// ([`Predict::Bundle`]) of a grid model: the velocity history is completed from the
    /// state (the current velocity repeated before T frames were seen, or when B or N
    /// changed), and the reference positions are this frame's when the state has none of
    /// this shape. Returns the K predicted frames (the first alone for [`Predict::Next`]),
    /// read back as `read` says ([`Read::Ahead`]: behind the call, where the backend can).
    /// With a `plan` the frames are first projected on the device where the backend can
    /// ([`NetOps::project_constraints`]; the velocity history then follows the projected frames,
    /// as `finish_here` makes it on the host); the returned flag says whether they were.
    pub(super) fn grid_step(
        &self,
        model: &GridModel<B>,
        frames: &[f32],
        material: &[u8],
        dt: &[f32],
        carry: GridState<B>,
        (predict, read, mut plan): (Predict, Read, Option<ProjectionPlan>),
    ) -> Result<(Outs, GridState<B>, bool), StoreError> {
        let b = dt.len();
        let n = material.len() / b;
        let mut clock = stages::Clock::start();
        roofline::begin::<B>(&self.device);
        let frame = crate::model::upload::<B, 3>(frames.to_vec(), [b, n, 4], &self.device);
        let input = frame.clone();
        let call = self.grid_call(model, frame, material, dt, carry, predict, &mut clock)?;
        let ((next, state), on_device) = self.projected_call(call, &input, plan.as_mut());
        let ahead = match read {
            Read::Ahead => B::read_ahead(next.clone().into_primitive().tensor()),
            Read::Now => None,
        };
        let out = match ahead {
            Some(read) => Outs::Ahead {
                read,
                k: next.dims()[0] / b.max(1),
                shape: next.dims(),
            },
            None => Outs::Host(self.download_frames(next, b, &mut clock)?),
        };
        Ok((out, state, on_device))
    }

    /// `next` (`[K B, N, 4]`), predicted from `input` (`[B, N, 4]`), projected on the device
    /// as `plan` lays it out (its K set from `next`), the moves added to the corrections
    /// ([`Surrogate::take_corrections`]); None where the backend does not project
    /// ([`NetOps::project_constraints`]).
    fn project_on_device(
        &self,
        next: &Tensor<B, 3>,
        input: &Tensor<B, 3>,
        plan: &mut ProjectionPlan,
    ) -> Option<Tensor<B, 3>> {
        plan.k = next.dims()[0] / input.dims()[0].max(1);
        let frames = next.clone().into_primitive().tensor();
        let input = Some(input.clone().into_primitive().tensor());
        let (p, moves) = B::project_constraints(frames, input, plan)?;
        let moves = Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(moves));
        let mut held = self.device_moves.lock().unwrap_or_else(|e| e.into_inner());
        held.add(moves.sum_dim(0).reshape([MATERIALS]), plan);
        Some(Tensor::from_primitive(TensorPrimitive::Float(p)))
    }

    /// A call's frames (`[K B, N, 4]`) and state, predicted from `input` (`[B, N, 4]`),
    /// projected on the device by `plan` where there is one and the backend projects
    /// ([`Surrogate::project_on_device`]; the state's velocity history then follows the
    /// projected frames, as `finish_here` makes it follow the host's), and whether they were.
    pub(super) fn projected_call(
        &self,
        (next, mut state): (Tensor<B, 3>, GridState<B>),
        input: &Tensor<B, 3>,
        plan: Option<&mut ProjectionPlan>,
    ) -> ((Tensor<B, 3>, GridState<B>), bool) {
        let b = input.dims()[0];
        let called = match plan.and_then(|p| self.project_on_device(&next, input, p)) {
            Some(projected) => {
                state.history = history_of(state.history, &projected, b);
                ((projected, state), true)
            }
            None => ((next, state), false),
        };
        roofline::mark::<B>(&self.device, Part::Projection);
        called
    }

    /// The network call of [`Surrogate::grid_step`] on a frame already on the device
    /// (`frame` `[B, N, 4]` physical), recorded but not waited for: the predicted frames
    /// stay on the device as one `[K B, N, 4]` tensor (frame k's rows `k B..(k + 1) B`), so
    /// a closed-loop rollout can feed the last of them back without a round trip through
    /// the host ([`Surrogate::rollout_batch`]). Laps `clock`'s input and record stages.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn grid_call(
        &self,
        model: &GridModel<B>,
        frame: Tensor<B, 3>,
        material: &[u8],
        dt: &[f32],
        carry: GridState<B>,
        predict: Predict,
        clock: &mut Option<stages::Clock>,
    ) -> Result<(Tensor<B, 3>, GridState<B>), StoreError> {
        let t = model.window();
        let (input, memory) = self.grid_input(model, frame, material, dt, carry)?;
        lap(clock, Stage::Input);
        let (vel_hist, reference, rest) = (
            input.vel.clone(),
            input.reference.clone(),
            input.rest.clone(),
        );
        let (mut outs, memory) = model.step_bundle(input, memory);
        if predict == Predict::Next {
            outs.truncate(1);
        }
        // The F of the frame the next call reads: the last one returned.
        let deformation = outs.last().and_then(|o| o.deformation.clone());
        // The T - 1 velocities before the next call's input frame: the input frame's own
        // window (the next observed frame follows it), or that window continued by the
        // bundle's frames but its last (the next call's input is that last frame).
        let mut window = vec![vel_hist];
        if predict == Predict::Bundle {
            window.extend(outs[..outs.len() - 1].iter().map(|o| o.vel.clone()));
        }
        let window = Tensor::cat(window, 2);
        let width = window.dims()[2];
        let history = (t > 1).then(|| window.narrow(2, width - 2 * (t - 1), 2 * (t - 1)));
        let next = Tensor::cat(
            outs.into_iter()
                .map(|o| Tensor::cat(vec![o.pos, o.vel], 2))
                .collect(),
            0,
        ); // [K B, N, 4]
        lap(clock, Stage::Record);
        let state = GridState {
            memory,
            history,
            reference,
            rest,
            deformation,
            fresh: None,
        };
        Ok((next, state))
    }

    /// Frames of `b` trajectories recorded on the device (`next`, `[K B, N, 4]`) read back
    /// as K host frames of `[B, N, 4]`, oldest first. Laps `clock`'s device stage (when
    /// stages are on: a wait the download makes anyway) and output stage, and ends the
    /// roofline's read-back part.
    ///
    /// # Errors
    /// [`StoreError`] carrying the backend's read error.
    pub(super) fn download_frames(
        &self,
        next: Tensor<B, 3>,
        b: usize,
        clock: &mut Option<stages::Clock>,
    ) -> Result<Vec<Vec<f32>>, StoreError> {
        let [kb, n, _] = next.dims();
        // Over PCIe, not the GPU's memory: the frames, f32.
        roofline::count(0.0, (kb * n * 16) as f64);
        if clock.is_some() {
            B::sync(&self.device).map_err(|e| crate::model::DownloadError {
                shape: vec![kb, n, 4],
                source: Box::new(e),
            })?;
            lap(clock, Stage::Device);
        }
        let k = kb / b.max(1);
        // Where the backend reads into its own pinned buffers (CUDA), each frame is copied
        // once from there; burn's read of a call over 100 MB (256 scenes of 10,000
        // particles) goes through pageable memory, and splitting copies it again.
        let read = B::read_ahead(next.clone().into_primitive().tensor());
        let out = match read {
            Some(read) => read
                .wait_parts(k)
                .map_err(|e| crate::model::DownloadError {
                    shape: vec![kb, n, 4],
                    source: e.into(),
                })?,
            None => split_frames(crate::model::download(next)?, k),
        };
        lap(clock, Stage::Output);
        roofline::mark::<B>(&self.device, Part::ReadBack);
        Ok(out)
    }

    /// A grid model's input for `frame` (`[B, N, 4]` physical, on the device) from the
    /// state `carry` ([`GridState::fit`] to this call's shape), and the memory the call goes
    /// on from. Rows marked restarted ([`GridState::fresh`]) start as a state restarted
    /// whole does: memory zero (what the cells' update reads for no state: `h = z h~`),
    /// velocity history the input's velocity repeated, F the fit to the rest neighbourhoods
    /// (or the identity); the marks pick per row, so the other rows are unchanged.
    fn grid_input(
        &self,
        model: &GridModel<B>,
        frame: Tensor<B, 3>,
        material: &[u8],
        dt: &[f32],
        carry: GridState<B>,
    ) -> Result<(StepInput<B>, MemoryState<B>), StoreError> {
        let (b, t) = (dt.len(), model.window());
        let n = material.len() / b;
        let pos = frame.clone().narrow(2, 0, 2);
        let vel = frame.narrow(2, 2, 2);
        let carry = carry.fit([b, n], t);
        // `[B, 1, 1]`: 1 for a restarted row. `pick(carried, start)` takes each row's own by
        // selection (a restarted row's carried values, even non-finite ones, are dropped);
        // `start` is recorded only when some row restarts.
        let fresh = carry.fresh.map(|f| f.reshape([b, 1, 1]));
        let pick = |carried: Tensor<B, 3>, start: &dyn Fn() -> Tensor<B, 3>| match &fresh {
            Some(f) => {
                let mask = f.clone().greater_elem(0.5).expand(carried.dims());
                carried.mask_where(mask, start())
            }
            None => carried,
        };
        let reference = carry.reference.unwrap_or_else(|| pos.clone());
        let repeated = || vel.clone().repeat_dim(2, t);
        let vel = match carry.history {
            Some(h) => pick(Tensor::cat(vec![h, vel.clone()], 2), &repeated),
            None => repeated(),
        };
        let rest = match carry.rest {
            Some(rest) => Some(rest),
            None if model.uses_rest_shape() => Some(self.rest_of(&reference, material, [b, n])?),
            None => None,
        };
        let fitted = || match rest.as_ref().filter(|r| r.dims() == [b, n]) {
            Some(r) => r.fitted(pos.clone()),
            None => identity::<B>([b, n], &self.device),
        };
        let deformation = carry.deformation.map(|f| pick(f, &fitted));
        let memory = match &fresh {
            Some(f) => zero_rows(carry.memory, f),
            None => carry.memory,
        };
        let input = StepInput {
            pos,
            vel,
            material: self.material_one_hot(material, [b, n]),
            dt: crate::model::upload::<B, 1>(dt.to_vec(), [b], &self.device),
            reference: Some(reference),
            rest,
            deformation,
        };
        Ok((input, memory))
    }

    /// The `[B, N, M]` one-hot of `material` (`[B N]`), M = the model's materials: the last
    /// call's tensor when it encodes the same materials ([`Surrogate::one_hot`]), otherwise
    /// built on the host, uploaded and kept.
    fn material_one_hot(&self, material: &[u8], [b, n]: [usize; 2]) -> Tensor<B, 3> {
        let mut kept = self.one_hot.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((of, tensor)) = kept.as_ref() {
            if of.as_slice() == material && tensor.dims()[..2] == [b, n] {
                return tensor.clone();
            }
        }
        let tensor = one_hot(material, self.meta.materials(), b, n, &self.device);
        *kept = Some((material.to_vec(), tensor.clone()));
        tensor
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
}

/// `memory` (`[B N, H]` rows) with the rows of the trajectories `fresh` marks (`[B, 1, 1]`,
/// 1 for a restarted one) set to zero, what the cells read for no state (a fill, so even a
/// non-finite carried value is dropped).
fn zero_rows<B: NetOps>(memory: MemoryState<B>, fresh: &Tensor<B, 3>) -> MemoryState<B> {
    let b = fresh.dims()[0];
    let zero = |h: Tensor<B, 2>| {
        let [rows, width] = h.dims();
        let per_row = fresh.clone().repeat_dim(1, rows / b).reshape([rows, 1]);
        h.mask_fill(per_row.greater_elem(0.5).expand([rows, width]), 0.0)
    };
    match memory {
        MemoryState::Hidden(h) => MemoryState::Hidden(zero(h)),
        MemoryState::Lstm(s) => MemoryState::Lstm(crate::model::rnn::LstmState {
            h: zero(s.h),
            c: zero(s.c),
        }),
        MemoryState::Empty => MemoryState::Empty,
    }
}

/// Ends `stage` on the call's clock, when stages are on ([`stages`]).
fn lap(clock: &mut Option<stages::Clock>, stage: Stage) {
    if let Some(clock) = clock {
        clock.lap(stage);
    }
}

/// The velocity history `history` (`[B, N, 2 (T - 1)]`) taken from the projected bundle `next`
/// (`[K B, N, 4]`): the velocities of the T - 1 frames before its last, as
/// `GridState::history_from` takes them from the host's frames; as is when K <= T - 1 (a
/// [`Predict::Next`] call's one frame).
fn history_of<B: NetOps>(
    history: Option<Tensor<B, 3>>,
    next: &Tensor<B, 3>,
    b: usize,
) -> Option<Tensor<B, 3>> {
    let h = history?;
    let [rows, _, width] = h.dims();
    let (t1, k) = (width / 2, next.dims()[0] / b.max(1));
    if k <= t1 || rows != b {
        return Some(h);
    }
    let window = (k - 1 - t1..k - 1)
        .map(|f| next.clone().narrow(0, f * b, b).narrow(2, 2, 2))
        .collect();
    Some(Tensor::cat(window, 2))
}
