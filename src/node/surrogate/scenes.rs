//! The surrogate node's per-scene state: one hidden state per `scene` id, with the index
//! and time of its last frame and whether its closed-loop rollout was published. Applies
//! [`super::admission`]'s rules to each frame, evicts the least recently seen scene before
//! a new one would pass `max_scenes`, and drops scenes idle past `idle_timeout`, so memory
//! stays bounded. Used by [`super::run`] (`minflow node`).

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use crate::model::store::{State, Surrogate};
use crate::ops::NetOps;

use super::admission::{admission, Admission, SceneView};
use super::NodeOptions;

/// One scene's hidden state and bookkeeping.
struct SceneState<B: burn::tensor::backend::Backend> {
    /// None before the first step and after a restart.
    state: Option<State<B>>,
    last_index: Option<u32>,
    last_seen: Instant,
    /// Closed loop: the rollout of this scene was published.
    rolled_out: bool,
}

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
}

impl<B: NetOps> Scenes<B> {
    /// No scenes yet.
    pub(super) fn new() -> Self {
        Scenes {
            map: BTreeMap::new(),
        }
    }

    /// Scenes held now.
    pub(super) fn len(&self) -> usize {
        self.map.len()
    }

    /// True when `scene`'s closed-loop rollout was published (it waits for a restart).
    pub(super) fn rolled_out(&self, scene: &str) -> bool {
        self.map.get(scene).is_some_and(|s| s.rolled_out)
    }

    /// Marks `scene`'s rollout as published.
    pub(super) fn mark_rolled_out(&mut self, scene: &str) {
        if let Some(entry) = self.map.get_mut(scene) {
            entry.rolled_out = true;
        }
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
                rolled_out: false,
            });
        let view = SceneView {
            last_index: entry.last_index,
            idle_too_long: entry.last_seen.elapsed() > options.idle_timeout,
            rolled_out: entry.rolled_out,
        };
        entry.last_seen = Instant::now();
        match admission(view, index, options.rollout.is_some(), options.on_gap) {
            Admission::Ignore => return Admitted::Ignored,
            Admission::DropOlder => return Admitted::Dropped,
            Admission::Continue => {}
            Admission::Restart => {
                entry.state = None;
                entry.rolled_out = false;
            }
            Admission::GapReset => {
                tracing::debug!(
                    "{scene}: gap {:?} -> {index}: state reset",
                    entry.last_index
                );
                // The stream goes on: its reference positions are kept.
                entry.state = entry.state.take().map(|s| surrogate.restart(s));
                entry.rolled_out = false;
            }
        }
        entry.last_index = Some(index);
        Admitted::Step(entry.state.take().unwrap_or_else(|| surrogate.init_state()))
    }
}
