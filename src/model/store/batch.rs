//! Dynamic batching at the model: [`Surrogate::step_scenes`] steps several scenes, each with
//! its own opaque [`State`], through as few network calls as their shapes allow. Scenes whose
//! frames have the same particle count N and whose states have the same shape (the same fields
//! present, the same sizes: `State::shape_key`) are stacked into one batch state
//! (`State::stack`), stepped as one `[B, N, 4]` batch and split back (`State::split`); other
//! scenes go through calls of their own. Scenes of different N are not padded into one call: a
//! grid model's cost grows with the particles a call carries, and padding particles would
//! change P2G's splat, so grouping by N is exact. A call may be padded with copies of its last
//! scene to a power-of-two batch ([`Surrogate::with_padded_batches`]: on a GPU each new batch
//! shape compiles kernels). Used by the surrogate node (`minflow node --max-batch`), whose
//! scheduler follows NVIDIA Triton Inference Server's dynamic batcher.

use std::collections::BTreeMap;
use std::ops::AddAssign;
use std::time::{Duration, Instant};

use super::constrained::ConstraintState;
use super::outs::{Outs, Read};
use super::{Predict, State, StoreError, Surrogate};
use crate::ops::NetOps;

/// One scene's input to [`Surrogate::step_scenes`].
pub struct SceneStep<'a, B: burn::tensor::backend::Backend> {
    /// The scene's frame, `[N, 4]` physical x, y, vx, vy rows.
    pub rows: Vec<f32>,
    /// Material ids, `[N]`.
    pub material: &'a [u8],
    /// Time between frames (simulation time units).
    pub dt: f32,
    /// The scene's state before this frame.
    pub state: State<B>,
}

/// What [`Surrogate::step_scenes`] returns.
pub struct SceneSteps<B: burn::tensor::backend::Backend> {
    /// Per scene, in the input's order: the predicted frames (`[N, 4]` each; K of them for
    /// [`Predict::Bundle`], else the next one) and the scene's state after them, or why not.
    pub results: Vec<Result<(Vec<Vec<f32>>, State<B>), StoreError>>,
    /// Scenes per network call, one entry per call.
    pub calls: Vec<usize>,
    /// Where the calls' wall time went.
    pub times: StepTimes,
}

/// Wall time of [`Surrogate::step_scenes`] by stage, summed over its calls: `stack` gathers
/// the scenes' frames and stacks their states (`State::stack`), `call` runs the network,
/// reads its predictions back to the host (on a GPU this waits for the kernels, so it holds
/// the device's work too), projects them and cuts them per scene, `split` splits the state
/// back per scene (`State::split`). On a GPU kernels are queued, not waited for: the stack's
/// concatenations and uploads land in `call`, which waits for them, and the split's in the
/// next call. A call that fails adds nothing.
#[derive(Debug, Default, Clone, Copy, PartialEq)]
pub struct StepTimes {
    /// Frames gathered and states stacked.
    pub stack: Duration,
    /// The network call, predictions read back, projected and cut per scene.
    pub call: Duration,
    /// States split per scene.
    pub split: Duration,
}

impl AddAssign for StepTimes {
    fn add_assign(&mut self, other: Self) {
        self.stack += other.stack;
        self.call += other.call;
        self.split += other.split;
    }
}

impl<B: NetOps> Surrogate<B> {
    /// Steps every scene of `scenes` once: [`Surrogate::step`] ([`Predict::Next`]) or
    /// [`Surrogate::step_bundle`] ([`Predict::Bundle`]) on each, with scenes of equal particle count and
    /// state shape stacked into one network call (module doc). The predictions equal those
    /// of stepping each scene alone (to float rounding: about 1e-6).
    ///
    /// # Shapes
    /// Each scene's `rows` `[N, 4]`, `material` `[N]`; returns `[N, 4]` frames per scene.
    ///
    /// # Errors
    /// Per scene, in `results`: a step's [`StoreError`] (every scene of a failed call gets
    /// its message).
    pub fn step_scenes(&self, scenes: Vec<SceneStep<'_, B>>, predict: Predict) -> SceneSteps<B> {
        let mut submitted = self.submit_with(scenes, predict, Read::Now);
        let states = std::mem::take(&mut submitted.states);
        let calls = submitted.calls.clone();
        let Finished { frames, times } = submitted.finish(self);
        let results = (frames.into_iter().zip(states))
            .map(|(frames, state)| -> Result<_, StoreError> { Ok((frames?, state?)) })
            .collect();
        SceneSteps {
            results,
            calls,
            times,
        }
    }

    /// [`Surrogate::step_scenes`] for [`Predict::Next`], its predictions left on their way
    /// to the host ([`NetOps::read_ahead`](crate::ops::NetOps::read_ahead)) where the
    /// backend can: the scenes' states after the calls are ready now (the next calls may
    /// stack them), the predictions and their projection onto the constraints come with
    /// [`Submitted::finish`]. On a GPU the host can so record the next calls before it
    /// waits for these, and the GPU runs them while the host publishes these (the surrogate
    /// node's pipelined calls). A [`Predict::Bundle`] call is finished before it returns (its
    /// next state follows its projected frames).
    pub fn submit_scenes(&self, scenes: Vec<SceneStep<'_, B>>, predict: Predict) -> Submitted<B> {
        self.submit_with(scenes, predict, Read::Ahead)
    }

    /// [`Surrogate::submit_scenes`] with the predictions read as `read` says.
    pub(super) fn submit_with(
        &self,
        scenes: Vec<SceneStep<'_, B>>,
        predict: Predict,
        read: Read,
    ) -> Submitted<B> {
        let mut groups: BTreeMap<(usize, Vec<usize>), Vec<usize>> = BTreeMap::new();
        for (i, s) in scenes.iter().enumerate() {
            let key = (s.material.len(), s.state.shape_key());
            groups.entry(key).or_default().push(i);
        }
        let mut slots: Vec<Option<SceneStep<'_, B>>> = scenes.into_iter().map(Some).collect();
        let mut states: Vec<Option<Result<State<B>, StoreError>>> =
            slots.iter().map(|_| None).collect();
        let mut submitted = Submitted {
            states: Vec::new(),
            flights: Vec::with_capacity(groups.len()),
            calls: Vec::with_capacity(groups.len()),
            times: StepTimes::default(),
        };
        for members in groups.into_values() {
            let group: Vec<SceneStep<'_, B>> =
                members.iter().filter_map(|&i| slots[i].take()).collect();
            submitted.calls.push(group.len());
            let called = self.submit_group(group, predict, read, &mut submitted.times);
            let (after, flight): (Vec<Result<State<B>, StoreError>>, _) = match called {
                Ok((after, flight)) => (after.into_iter().map(Ok).collect(), Ok(flight)),
                Err(e) => {
                    let failed = || StoreError::Shape(e.to_string());
                    (
                        members.iter().map(|_| Err(failed())).collect(),
                        Err(failed()),
                    )
                }
            };
            for (&i, state) in members.iter().zip(after) {
                states[i] = Some(state);
            }
            submitted.flights.push((members, flight));
        }
        submitted.states = (states.into_iter())
            .map(|s| s.unwrap_or_else(|| Err(StoreError::Shape("scene not stepped".into()))))
            .collect();
        submitted
    }

    /// One network call on `group` (scenes of one N and one state shape): frames, materials
    /// and time steps concatenated, states stacked, the call recorded and the state split
    /// back per scene; the predictions are left in the returned [`Flight`] (for
    /// [`Predict::Bundle`] read and projected first, since the state follows them). With
    /// padded batches the call carries copies of the last scene up to the next power of
    /// two, whose outputs and states are dropped. Its stages' wall time is added to `times`.
    fn submit_group(
        &self,
        group: Vec<SceneStep<'_, B>>,
        predict: Predict,
        read: Read,
        times: &mut StepTimes,
    ) -> Result<(Vec<State<B>>, Flight), StoreError> {
        let start = Instant::now();
        let b = group.len();
        let per_scene = group.first().map_or(0, |s| s.rows.len());
        let copies = if self.mirrored() { 2 } else { 1 };
        let mut frames = Vec::with_capacity(b * per_scene);
        let mut material = Vec::with_capacity(b * per_scene / 4);
        let (mut dt, mut counts, mut states) = (vec![], vec![], vec![]);
        for s in group {
            frames.extend_from_slice(&s.rows);
            material.extend_from_slice(s.material);
            dt.push(s.dt);
            counts.push(s.state.frames);
            states.push(s.state);
        }
        let padded = self.padded(b);
        if padded > b {
            let rows = frames[(b - 1) * per_scene..].to_vec();
            let ids = material[(b - 1) * per_scene / 4..].to_vec();
            let last_dt = dt[b - 1];
            for _ in b..padded {
                frames.extend_from_slice(&rows);
                material.extend_from_slice(&ids);
                dt.push(last_dt);
                states.push(states[b - 1].detached());
            }
        }
        let stacked = State::stack(states, copies)?;
        let called = Instant::now();
        times.stack += called - start;
        let (outs, mut after) =
            B::run_step(|| self.submit_here(&frames, &material, &dt, stacked, predict, read))?;
        let input = (frames, material, dt);
        let mut flight = Flight {
            outs,
            projection: None,
            per_scene,
            scenes: b,
        };
        match predict {
            Predict::Bundle => {
                let (f, m, d) = (&input.0[..], &input.1[..], &input.2[..]);
                let history = Some(&mut after.net);
                let out =
                    self.finish_here(flight.outs, (f, m, d), &mut after.constraints, history)?;
                flight.outs = Outs::Host(out);
            }
            // The split states share the call's constraint slots (`constrained.rs`).
            Predict::Next => flight.projection = Some((input, after.constraints.clone())),
        }
        let returned = Instant::now();
        times.call += returned - called;
        let per: Vec<State<B>> = (after.split(&vec![1; padded], copies).into_iter())
            .zip(counts)
            .map(|(mut state, frames)| {
                state.frames = frames + 1;
                state
            })
            .collect();
        times.split += returned.elapsed();
        Ok((per, flight))
    }
}

/// A call's input frames (`[B, N, 4]`), materials (`[B N]`) and time steps (`[B]`).
type CallInput = (Vec<f32>, Vec<u8>, Vec<f32>);

/// One network call's predictions, on the host or on their way, and what their projection
/// onto the constraints needs.
struct Flight {
    outs: Outs,
    /// The call's input and its constraint data, where the projection is still to come
    /// ([`Predict::Next`]).
    projection: Option<(CallInput, ConstraintState)>,
    /// Values of one scene's frame (`N 4`).
    per_scene: usize,
    /// Scenes of the call (its padded copies not counted).
    scenes: usize,
}

/// Scenes stepped by [`Surrogate::submit_scenes`]: their states after the calls, and the
/// calls' predictions on their way ([`Submitted::finish`]).
pub struct Submitted<B: burn::tensor::backend::Backend> {
    /// Per scene, in the input's order: its state after the call, or why the call failed.
    pub states: Vec<Result<State<B>, StoreError>>,
    /// Per call: its scenes (indices into the input) and its predictions (or its error).
    flights: Vec<(Vec<usize>, Result<Flight, StoreError>)>,
    /// Scenes per network call, one entry per call.
    pub calls: Vec<usize>,
    /// Where the calls' wall time went so far.
    pub times: StepTimes,
}

/// What [`Submitted::finish`] returns.
pub struct Finished {
    /// Per scene, in the input's order: its predicted frames (`[N, 4]` each; K of them for
    /// [`Predict::Bundle`], else the next one), or why not.
    pub frames: Vec<Result<Vec<Vec<f32>>, StoreError>>,
    /// Where the calls' wall time went, the wait for the predictions included (`call`).
    pub times: StepTimes,
}

impl<B: NetOps> Submitted<B> {
    /// Waits for the calls' predictions, projects them onto `surrogate`'s constraints where
    /// that is still to do, and cuts them per scene.
    ///
    /// # Errors
    /// Per scene, in `frames`: its call's [`StoreError`], or the read's.
    pub fn finish(self, surrogate: &Surrogate<B>) -> Finished {
        let scenes: usize = self.flights.iter().map(|(m, _)| m.len()).sum();
        let mut frames: Vec<Option<Result<Vec<Vec<f32>>, StoreError>>> =
            (0..scenes).map(|_| None).collect();
        let mut times = self.times;
        for (members, flight) in self.flights {
            let start = Instant::now();
            let out = flight.and_then(|f| f.land(surrogate));
            times.call += start.elapsed();
            match out {
                Ok(per) => {
                    for (&i, f) in members.iter().zip(per) {
                        frames[i] = Some(Ok(f));
                    }
                }
                Err(e) => {
                    for &i in &members {
                        frames[i] = Some(Err(StoreError::Shape(e.to_string())));
                    }
                }
            }
        }
        Finished {
            frames: (frames.into_iter())
                .map(|f| f.unwrap_or_else(|| Err(StoreError::Shape("scene not stepped".into()))))
                .collect(),
            times,
        }
    }
}

impl Flight {
    /// The call's predictions on the host, projected where still to do, cut per scene
    /// (padded copies dropped): per scene its K frames.
    fn land<B: NetOps>(self, surrogate: &Surrogate<B>) -> Result<Vec<Vec<Vec<f32>>>, StoreError> {
        let outs = match self.projection {
            Some(((frames, material, dt), mut constraints)) => {
                let input = (&frames[..], &material[..], &dt[..]);
                surrogate.finish_here(self.outs, input, &mut constraints, None)?
            }
            None => self.outs.wait()?,
        };
        let mut per: Vec<Vec<Vec<f32>>> = (0..self.scenes)
            .map(|_| Vec::with_capacity(outs.len()))
            .collect();
        for out in outs {
            for (scene, chunk) in per.iter_mut().zip(out.chunks_exact(self.per_scene.max(1))) {
                scene.push(chunk.to_vec());
            }
        }
        Ok(per)
    }
}
