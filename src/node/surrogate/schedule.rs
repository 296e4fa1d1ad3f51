//! The surrogate node's queues, under one owner: [`Schedule`] holds the frames waiting per
//! scene ([`Pending`]) and the closed-loop rollouts under way ([`Rollouts`], whose next
//! network calls wait beside them), and says when the next batch is due ([`Due`], the
//! dynamic batcher's rule: `batcher.rs`) and which items wait, oldest first ([`Waiting`]).
//! The loop (`node_loop.rs`) queues arrivals here (`intake.rs`) and takes batches
//! from here (`batcher.rs`).

use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

use crate::msgs::ParticleFrame;

use super::closed::Rollouts;

/// A frame waiting to be predicted on, with its arrival time.
pub(super) struct Pending {
    /// The frame (its position and velocity arrays emptied unless a live view draws them:
    /// `rows` holds them).
    pub(super) frame: ParticleFrame,
    /// `[N, 4]` the frame's particles as the model takes them (`msgs::state_rows`).
    pub(super) rows: Vec<f32>,
    /// When the transport received it.
    pub(super) arrived: Instant,
}

/// When the next batch is due.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Due {
    /// Now: full, or its oldest item waited `--max-batch-delay`.
    Now,
    /// At this time, unless it fills up before.
    At(Instant),
    /// Nothing waits.
    Nothing,
}

impl Due {
    /// True for [`Due::Now`].
    pub(super) fn is_now(self) -> bool {
        self == Due::Now
    }
}

/// An item waiting for a network call: a scene's next pending frame, or the next call of
/// its rollout.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub(super) enum Waiting {
    /// The scene's oldest pending frame.
    Live(String),
    /// The scene's rollout waits for its next call.
    Rollout(String),
}

/// The node's queues: pending frames per scene and the rollouts under way.
pub(super) struct Schedule<B: burn::tensor::backend::Backend> {
    /// Frames waiting per scene, oldest first.
    pending: BTreeMap<String, VecDeque<Pending>>,
    /// The rollouts under way (closed loop).
    pub(super) rollouts: Rollouts<B>,
}

impl<B: burn::tensor::backend::Backend> Schedule<B> {
    /// Nothing queued.
    pub(super) fn new() -> Self {
        Schedule {
            pending: BTreeMap::new(),
            rollouts: Rollouts::new(),
        }
    }

    /// Triton's rule (`batcher.rs`) on what waits at `now`: due when `max_batch` items wait,
    /// or every item that could take part (the `live` scenes held and the rollouts under
    /// way) when there are fewer, or when the oldest item has waited `delay`.
    pub(super) fn due(&self, now: Instant, live: usize, max_batch: usize, delay: Duration) -> Due {
        let heads = self.pending.values().filter_map(|q| q.front());
        let oldest = heads
            .map(|p| p.arrived)
            .chain(self.rollouts.waiting().map(|(t, _)| t))
            .min();
        let Some(oldest) = oldest else {
            return Due::Nothing;
        };
        let ready = self.pending.len() + self.rollouts.waiting().count();
        let could_join = (live + self.rollouts.len()).max(ready);
        if ready >= max_batch.min(could_join).max(1) {
            return Due::Now;
        }
        match oldest.checked_add(delay) {
            Some(t) if t > now => Due::At(t),
            _ => Due::Now,
        }
    }

    /// Every waiting item, oldest first (by its frame's arrival or the time its rollout
    /// began to wait).
    pub(super) fn oldest_first(&self) -> Vec<Waiting> {
        let mut waiting: Vec<(Instant, Waiting)> = self
            .pending
            .iter()
            .filter_map(|(k, q)| Some((q.front()?.arrived, Waiting::Live(k.clone()))))
            .chain(
                self.rollouts
                    .waiting()
                    .map(|(t, k)| (t, Waiting::Rollout(k.to_owned()))),
            )
            .collect();
        waiting.sort();
        waiting.into_iter().map(|(_, w)| w).collect()
    }

    /// Queues `pending` for its scene; past `depth` frames the scene's oldest is dropped.
    /// True when one was dropped.
    pub(super) fn queue(&mut self, pending: Pending, depth: usize) -> bool {
        let queue = self.pending.entry(pending.frame.scene.clone()).or_default();
        queue.push_back(pending);
        if queue.len() > depth.max(1) {
            queue.pop_front();
            return true;
        }
        false
    }

    /// Takes `scene`'s oldest pending frame.
    pub(super) fn take_pending(&mut self, scene: &str) -> Option<Pending> {
        let queue = self.pending.get_mut(scene)?;
        let pending = queue.pop_front()?;
        if queue.is_empty() {
            self.pending.remove(scene);
        }
        Some(pending)
    }

    /// Whether frames of `scene` wait.
    pub(super) fn has_pending(&self, scene: &str) -> bool {
        self.pending.contains_key(scene)
    }
}
