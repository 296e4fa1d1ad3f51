//! The surrogate node's closed-loop rollouts (`minflow node --rollout R`) as scheduled work:
//! each scene that has had its first T frames rolls out R predicted frames, one network
//! call (K frames for a bundled model) at a time, and the node's loop interleaves those
//! calls with every other scene's work (batched with them, `batcher.rs`) instead of
//! rolling one scene out from start to end while the others wait. Frames are published
//! when due: at once, or paced at the scene's `dt` over `--rate`. Held by the node's queues
//! (`schedule.rs`).

use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

use crate::model::store::State;
use crate::msgs::ParticleFrame;

use super::frames::predicted_frame;

/// One scene's rollout under way.
struct Rollout<B: burn::tensor::backend::Backend> {
    /// The frame the rollout follows (its arrays emptied but `material`).
    base: ParticleFrame,
    /// Predicted frames not yet published (`[N, 4]` rows), oldest first.
    queue: VecDeque<Vec<f32>>,
    /// The last frame predicted: the next call's input.
    last: Vec<f32>,
    /// Frames published, and frames to publish in all.
    published: usize,
    total: usize,
    /// The state for the next call; None while that call is under way.
    state: Option<State<B>>,
    start: Instant,
    /// Time between published frames; None: as fast as predicted.
    period: Option<Duration>,
    /// Since when the rollout waits for a network call.
    waiting_since: Instant,
}

/// The rollouts under way, by scene.
pub(super) struct Rollouts<B: burn::tensor::backend::Backend> {
    map: BTreeMap<String, Rollout<B>>,
}

/// One network call a rollout asks for: the input frame, its materials and `dt`, the state.
pub(super) struct RolloutCall<B: burn::tensor::backend::Backend> {
    pub(super) rows: Vec<f32>,
    pub(super) material: Vec<u8>,
    pub(super) dt: f32,
    pub(super) state: State<B>,
}

impl<B: burn::tensor::backend::Backend> Rollouts<B> {
    /// None under way.
    pub(super) fn new() -> Self {
        Rollouts {
            map: BTreeMap::new(),
        }
    }

    /// Rollouts under way.
    pub(super) fn len(&self) -> usize {
        self.map.len()
    }

    /// Starts `scene`'s rollout of `total` frames after `base`, from the first call's
    /// `bundle` and the state after it; paced at `base.dt / rate` when `rate` > 0. Replaces
    /// a rollout of the scene still under way (the scene started again).
    pub(super) fn start(
        &mut self,
        base: &ParticleFrame,
        bundle: Vec<Vec<f32>>,
        state: State<B>,
        total: usize,
        rate: f64,
    ) {
        // A frame's dt is any positive f32: pacing that overflows the clock is skipped.
        let period = (rate > 0.0)
            .then(|| Duration::try_from_secs_f64(f64::from(base.dt) / rate).ok())
            .flatten();
        let mut base = ParticleFrame {
            position: Vec::new(),
            velocity: Vec::new(),
            ..base.clone()
        };
        base.material.shrink_to_fit();
        let rollout = Rollout {
            base,
            last: bundle.last().cloned().unwrap_or_default(),
            queue: bundle.into(),
            published: 0,
            total,
            state: Some(state),
            start: Instant::now(),
            period,
            waiting_since: Instant::now(),
        };
        self.map.insert(rollout.base.scene.clone(), rollout);
    }

    /// The frames due now, in order per scene; rollouts that published their last frame
    /// end.
    pub(super) fn due(&mut self, now: Instant) -> Vec<ParticleFrame> {
        let mut out = Vec::new();
        for r in self.map.values_mut() {
            while r.published < r.total && r.due_at().is_none_or(|t| t <= now) {
                let Some(rows) = r.queue.pop_front() else {
                    break;
                };
                r.published += 1;
                out.push(predicted_frame(&r.base, &rows, r.published as u32));
                if r.queue.is_empty() {
                    r.waiting_since = now;
                }
            }
        }
        self.map.retain(|_, r| r.published < r.total);
        out
    }

    /// When the next frame of any rollout is due (None: none waits for its time).
    pub(super) fn next_due(&self) -> Option<Instant> {
        self.map
            .values()
            .filter(|r| !r.queue.is_empty())
            .map(|r| r.due_at().unwrap_or(r.start))
            .min()
    }

    /// The rollouts that wait for a network call, as (since when, scene).
    pub(super) fn waiting(&self) -> impl Iterator<Item = (Instant, &str)> + '_ {
        self.map
            .iter()
            .filter(|(_, r)| r.needs_call())
            .map(|(k, r)| (r.waiting_since, k.as_str()))
    }

    /// Takes the call `scene`'s rollout waits for (its state goes with it).
    pub(super) fn take_call(&mut self, scene: &str) -> Option<RolloutCall<B>> {
        let r = self.map.get_mut(scene).filter(|r| r.needs_call())?;
        Some(RolloutCall {
            rows: r.last.clone(),
            material: r.base.material.clone(),
            dt: r.base.dt,
            state: r.state.take()?,
        })
    }

    /// Hands `scene`'s rollout the frames and state of its call.
    pub(super) fn feed(&mut self, scene: &str, bundle: Vec<Vec<f32>>, state: State<B>) {
        if let Some(r) = self.map.get_mut(scene) {
            if let Some(last) = bundle.last() {
                r.last.clone_from(last);
            }
            r.queue.extend(bundle);
            r.state = Some(state);
        }
    }

    /// Ends `scene`'s rollout (its call failed).
    pub(super) fn cancel(&mut self, scene: &str) {
        self.map.remove(scene);
    }
}

impl<B: burn::tensor::backend::Backend> Rollout<B> {
    /// When the next frame is due; None when unpaced.
    fn due_at(&self) -> Option<Instant> {
        let p = self.period?;
        self.start
            .checked_add(p.checked_mul(u32::try_from(self.published).ok()?)?)
    }

    /// Published all it has, more to come, and its state is here.
    fn needs_call(&self) -> bool {
        self.queue.is_empty() && self.published < self.total && self.state.is_some()
    }
}
