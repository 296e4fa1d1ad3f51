//! The surrogate node's per-scene state: one hidden state per `scene` id, with the index
//! of its last frame and the time of its last activity (a frame arrived, or a prediction of
//! its rollout was published). Applies [`super::admission`]'s rules to each frame, evicts
//! the least recently active scene before a new one would pass `max_scenes`, and drops
//! scenes idle past `idle_timeout`, so memory stays bounded. In closed loop it remembers
//! which scenes were rolled out beyond their states (the last [`ROLLED_OUT_KEPT`]), so a
//! scene gets one rollout however long it waited. Held by the loop's state
//! (`node_loop.rs`; `minflow node`).

use std::collections::{BTreeMap, HashSet, VecDeque};
use std::time::{Duration, Instant};

use crate::model::store::{State, Surrogate};
use crate::ops::NetOps;

use super::admission::{admission, Admission, SceneView};
use super::options::NodeOptions;

/// One scene's hidden state and bookkeeping.
struct SceneState<B: burn::tensor::backend::Backend> {
    /// None before the first step and after a restart.
    state: Option<State<B>>,
    last_index: Option<u32>,
    /// Last activity: a frame of the scene arrived, was admitted, or a prediction of its
    /// rollout was published.
    last_seen: Instant,
}

/// Names of rolled-out scenes remembered (closed loop): memory stays bounded, and a scene
/// that comes back after this many others were rolled out is rolled out again.
pub(super) const ROLLED_OUT_KEPT: usize = 65_536;

/// What [`Scenes::admit`] decided for a frame.
pub(super) enum Admitted<B: burn::tensor::backend::Backend> {
    /// Step from this hidden state.
    Step(State<B>),
    /// An older frame under `--on-gap skip`: not predicted on, to be counted as dropped.
    Dropped,
    /// Not predicted on and not counted (closed loop, scene already rolled out).
    Ignored,
}

/// The hidden states of the scenes a node serves, by scene id.
pub(super) struct Scenes<B: burn::tensor::backend::Backend> {
    map: BTreeMap<String, SceneState<B>>,
    /// Closed loop: scenes whose rollout started, oldest first (at most [`ROLLED_OUT_KEPT`]).
    rolled: HashSet<String>,
    rolled_order: VecDeque<String>,
}

impl<B: NetOps> Scenes<B> {
    /// No scenes yet.
    pub(super) fn new() -> Self {
        Scenes {
            map: BTreeMap::new(),
            rolled: HashSet::new(),
            rolled_order: VecDeque::new(),
        }
    }

    /// Scenes held now.
    pub(super) fn len(&self) -> usize {
        self.map.len()
    }

    /// Scenes held now that have not been rolled out: those that may still send frames
    /// to step (the dynamic batcher waits for them).
    pub(super) fn live(&self) -> usize {
        self.map
            .keys()
            .filter(|k| !self.rolled.contains(*k))
            .count()
    }

    /// True when `scene`'s closed-loop rollout started (it waits for its frame 0).
    pub(super) fn rolled_out(&self, scene: &str) -> bool {
        self.rolled.contains(scene)
    }

    /// Marks `scene`'s rollout as started; forgets the oldest past [`ROLLED_OUT_KEPT`].
    pub(super) fn mark_rolled_out(&mut self, scene: &str) {
        if self.rolled.insert(scene.to_owned()) {
            self.rolled_order.push_back(scene.to_owned());
        }
        while self.rolled_order.len() > ROLLED_OUT_KEPT {
            if let Some(old) = self.rolled_order.pop_front() {
                self.rolled.remove(&old);
            }
        }
    }

    /// Forgets that `scene` was rolled out (it starts again at frame 0).
    fn unmark_rolled_out(&mut self, scene: &str) {
        if self.rolled.remove(scene) {
            self.rolled_order.retain(|s| s != scene);
        }
    }

    /// Notes activity of `scene` (a frame arrived, a prediction was published). A scene
    /// idle past `idle` is dropped first (true: counted as idle), as the periodic sweep
    /// would have done.
    pub(super) fn touch(&mut self, scene: &str, idle: Duration) -> bool {
        let Some(entry) = self.map.get_mut(scene) else {
            return false;
        };
        if entry.last_seen.elapsed() > idle {
            self.map.remove(scene);
            return true;
        }
        entry.last_seen = Instant::now();
        false
    }

    /// True when `scene` has a state entry.
    pub(super) fn contains(&self, scene: &str) -> bool {
        self.map.contains_key(scene)
    }

    /// Keeps `state` (None: start again at the next frame) as `scene`'s hidden state.
    pub(super) fn keep(&mut self, scene: &str, state: Option<State<B>>) {
        if let Some(entry) = self.map.get_mut(scene) {
            entry.state = state;
        }
    }

    /// Before a new scene is admitted at `max_scenes`, evicts the least recently seen one;
    /// returns its name.
    pub(super) fn make_room_for(&mut self, scene: &str, max_scenes: usize) -> Option<String> {
        if self.map.len() < max_scenes.max(1) || self.map.contains_key(scene) {
            return None;
        }
        let oldest = self
            .map
            .iter()
            .min_by_key(|(_, s)| s.last_seen)
            .map(|(k, _)| k.clone())?;
        self.map.remove(&oldest);
        Some(oldest)
    }

    /// Cuts the kept states that are rows of a batch most of whose scenes have moved on out
    /// of that batch ([`State::compact`]), so that stale batches are freed.
    pub(super) fn compact(&mut self) {
        for entry in self.map.values_mut() {
            entry.state = entry.state.take().map(State::compact);
        }
    }

    /// Drops the scenes without a frame for longer than `idle`; returns how many.
    pub(super) fn evict_idle(&mut self, idle: Duration) -> usize {
        let before = self.map.len();
        self.map.retain(|_, s| s.last_seen.elapsed() <= idle);
        before - self.map.len()
    }

    /// Applies the state rules to frame `index` of `scene` (seen now): the hidden state to
    /// step from, or why the frame is not predicted on. A new scene is added.
    pub(super) fn admit(
        &mut self,
        scene: &str,
        index: u32,
        options: &NodeOptions,
        surrogate: &Surrogate<B>,
    ) -> Admitted<B> {
        let entry = self
            .map
            .entry(scene.to_owned())
            .or_insert_with(|| SceneState {
                state: None,
                last_index: None,
                last_seen: Instant::now(),
            });
        let view = SceneView {
            last_index: entry.last_index,
            idle_too_long: entry.last_seen.elapsed() > options.idle_timeout,
            rolled_out: self.rolled.contains(scene),
        };
        entry.last_seen = Instant::now();
        match admission(view, index, options.rollout.is_some(), options.on_gap) {
            Admission::Ignore => return Admitted::Ignored,
            Admission::DropOlder => return Admitted::Dropped,
            Admission::Continue => {}
            Admission::Restart => {
                entry.state = None;
                entry.last_index = Some(index);
                self.unmark_rolled_out(scene);
                return Admitted::Step(surrogate.init_state_for(scene));
            }
            Admission::GapReset => {
                tracing::debug!(
                    "{scene}: gap {:?} -> {index}: state reset",
                    entry.last_index
                );
                // The stream goes on: its reference positions are kept.
                entry.state = entry.state.take().map(|s| surrogate.restart(s));
            }
        }
        entry.last_index = Some(index);
        Admitted::Step(
            entry
                .state
                .take()
                .unwrap_or_else(|| surrogate.init_state_for(scene)),
        )
    }
}
