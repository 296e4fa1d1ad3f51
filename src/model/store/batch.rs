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
/// the scenes' frames and stacks their states (`State::stack`), `call` runs the network and
/// reads its predictions back to the host (on a GPU this waits for the kernels, so it holds
/// the device's work too), `split` splits the state back per scene (`State::split`) and
/// cuts the predictions per scene. On a GPU kernels are queued, not waited for: the stack's
/// concatenations and uploads land in `call`, which waits for them, and the split's in the
/// next call. A call that fails adds nothing.
#[derive(Debug, Default, Clone, Copy, PartialEq)]
pub struct StepTimes {
    /// Frames gathered and states stacked.
    pub stack: Duration,
    /// The network call, predictions read back.
    pub call: Duration,
    /// States split and predictions cut per scene.
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
        let mut groups: BTreeMap<(usize, Vec<usize>), Vec<usize>> = BTreeMap::new();
        for (i, s) in scenes.iter().enumerate() {
            let key = (s.material.len(), s.state.shape_key());
            groups.entry(key).or_default().push(i);
        }
        let mut slots: Vec<Option<SceneStep<'_, B>>> = scenes.into_iter().map(Some).collect();
        let mut results: Vec<Option<Result<_, StoreError>>> = slots.iter().map(|_| None).collect();
        let mut calls = Vec::with_capacity(groups.len());
        let mut times = StepTimes::default();
        for members in groups.into_values() {
            let group: Vec<SceneStep<'_, B>> =
                members.iter().filter_map(|&i| slots[i].take()).collect();
            calls.push(group.len());
            match self.step_group(group, predict, &mut times) {
                Ok(outs) => {
                    for (&i, out) in members.iter().zip(outs) {
                        results[i] = Some(Ok(out));
                    }
                }
                Err(e) => {
                    for &i in &members {
                        results[i] = Some(Err(StoreError::Shape(e.to_string())));
                    }
                }
            }
        }
        let results = results
            .into_iter()
            .map(|r| r.unwrap_or_else(|| Err(StoreError::Shape("scene not stepped".into()))))
            .collect();
        SceneSteps {
            results,
            calls,
            times,
        }
    }

    /// One network call on `group` (scenes of one N and one state shape): frames, materials
    /// and time steps concatenated, states stacked, outputs and states split back. With
    /// padded batches the call carries copies of the last scene up to the next power of
    /// two, whose outputs and states are dropped. Its stages' wall time is added to `times`.
    #[allow(clippy::type_complexity)]
    fn step_group(
        &self,
        group: Vec<SceneStep<'_, B>>,
        predict: Predict,
        times: &mut StepTimes,
    ) -> Result<Vec<(Vec<Vec<f32>>, State<B>)>, StoreError> {
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
            let (last_dt, last) = (dt[b - 1], states[b - 1].clone());
            for _ in b..padded {
                frames.extend_from_slice(&rows);
                material.extend_from_slice(&ids);
                dt.push(last_dt);
                states.push(last.clone());
            }
        }
        let stacked = State::stack(states, copies)?;
        let called = Instant::now();
        times.stack += called - start;
        let (outs, after) =
            B::run_step(|| self.step_here(&frames, &material, &dt, stacked, predict))?;
        let returned = Instant::now();
        times.call += returned - called;
        let mut per: Vec<(Vec<Vec<f32>>, State<B>)> = after
            .split(&vec![1; padded], copies)
            .into_iter()
            .zip(counts)
            .map(|(mut state, frames)| {
                state.frames = frames + 1;
                (Vec::with_capacity(outs.len()), state)
            })
            .collect();
        for out in outs {
            for (scene, chunk) in per.iter_mut().zip(out.chunks_exact(per_scene.max(1))) {
                scene.0.push(chunk.to_vec());
            }
        }
        times.split += returned.elapsed();
        Ok(per)
    }
}
