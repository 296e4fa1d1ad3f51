//! Closed-loop rollouts of a [`Surrogate`]: [`Surrogate::rollout`] and
//! [`Surrogate::rollout_batch`] seed a state with observed frames and feed each call's
//! predictions back as the next call's input, on the host call by call or, for a grid model
//! on a GPU, on the device ([`Surrogate::with_feedback_bytes`]; with the liquid's
//! projection there too where the device makes it), the frames read back in batches. Used
//! by `eval`, `report`, `bench` and the grid trainer's validation.

use super::grid_state::GridState;
use super::state::NetState;
use super::surrogate::{Predict, Surrogate};
use super::{Net, StoreError};
use crate::model::roofline;
use crate::ops::{NetOps, ProjectionPlan};

impl<B: NetOps> Surrogate<B> {
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
        each: impl FnMut(usize, Vec<f32>),
    ) -> Result<(), StoreError> {
        self.rollout_on(None, first, seed, (material, dt), k, each)
    }

    /// [`Surrogate::rollout_batch`] of scenes the solver made on the grid `grid` (when
    /// known; else this surrogate's [`Surrogate::with_solver_grid`]).
    ///
    /// # Errors
    /// As [`Surrogate::rollout_batch`].
    pub fn rollout_on(
        &self,
        grid: Option<u32>,
        first: Option<&[f32]>,
        seed: &[Vec<f32>],
        (material, dt): (&[u8], &[f32]),
        k: usize,
        mut each: impl FnMut(usize, Vec<f32>),
    ) -> Result<(), StoreError> {
        let mut state = match first {
            Some(frame) => self.init_state_at(frame, dt.len())?,
            None => self.init_state(),
        };
        state.constraints.solver_grids = vec![grid.or(self.solver_grid)];
        if seed.is_empty() {
            return Err(StoreError::Shape("rollout: no seed frame".into()));
        }
        let loop_on_device = self.feedback_bytes > 0 && !self.mirror;
        // The projection stays on the device too where every scene's parts are ones it
        // projects (its data built from the rest frames, else the first seed frame, as the
        // host loop's first projection builds it).
        let plan = match &self.constraints {
            Some(c) if loop_on_device && B::projects_constraints() => {
                (state.constraints).device_plan(c, (&seed[0], material, dt), &self.plans)
            }
            _ => None,
        };
        let on_device = loop_on_device && (self.constraints.is_none() || plan.is_some());
        if let (Net::Grid(model), true) = (&self.net, on_device) {
            for frame in seed {
                self.check_step(frame, material, dt)?;
            }
            let NetState::Grid(carry) = state.net.owned() else {
                return Err(StoreError::Shape("state of another architecture".into()));
            };
            return self.grid_rollout(model, seed, (material, dt, plan), k, carry, each);
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

    /// The closed loop of [`Surrogate::rollout_batch`] for a grid model without mirror, and
    /// without projection or with one the device makes (`plan`, [`NetOps::project_constraints`]:
    /// each call's frames projected there and the velocity history taken from them): each
    /// call's last predicted frame is fed back on the device (no download and upload
    /// between calls), and the predictions are read back together once
    /// [`Surrogate::with_feedback_bytes`] of them are held or the rollout ends. On a GPU the
    /// host then records call c + 1's network while the device runs call c (with the rebound
    /// part, call c + 1's projection then waits for the contacts call c left, `events.rs`);
    /// the frames are the ones the call-by-call loop gives (the same values go back
    /// in).
    fn grid_rollout(
        &self,
        model: &crate::model::grid::GridModel<B>,
        seed: &[Vec<f32>],
        (material, dt, mut plan): (&[u8], &[f32], Option<ProjectionPlan>),
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
        // dropped unread, so the host does not wait for them either. They are projected as
        // the host loop's steps project them, so that the moves counted
        // ([`Surrogate::take_corrections`]) are the same frames' either way.
        for f in before {
            let mut none = None;
            roofline::begin::<B>(&self.device);
            let input = upload(f);
            let call = B::run_step(|| {
                self.grid_call(
                    model,
                    input.clone(),
                    material,
                    dt,
                    carry,
                    Predict::Next,
                    &mut none,
                )
            })?;
            carry = self.projected_call(call, &input, plan.as_mut()).0 .1;
        }
        let mut frame = upload(last);
        let (mut pending, mut held, mut recorded, mut done) = (Vec::new(), 0, 0, 0);
        while recorded < k {
            let mut clock = super::stages::Clock::start();
            roofline::begin::<B>(&self.device);
            let input = frame.clone();
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
                Ok(call) => self.projected_call(call, &input, plan.as_mut()).0,
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
            // Read back call by call, each into pinned memory and copied once per frame
            // (`download_frames`); 20 calls' frames of 256 scenes read as one tensor through
            // burn (200 MB, pageable) took 0.6 s on an H100, call by call 1.6 ms each.
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
