//! How frames enter the surrogate node: [`NodeLoop::gather`] takes the samples waiting on
//! the transport's channel (blocking only until the next thing is due: a batch, a rollout
//! frame, the status), and [`NodeLoop::accept`] decodes and checks each, passes over the
//! scenes another shard member owns, notes the scene's activity and queues the frame (the
//! scene's oldest pending frame dropped past `queue_depth`). Used by [`super::run`].

use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::time::{Duration, Instant};

use crate::ops::NetOps;
use crate::transport::Sample;

use super::admission::check_frame;
use super::batcher::Due;
use super::payload_bytes;
use super::run::{NodeLoop, Pending};

/// The longest the loop blocks on the transport with nothing due.
const MAX_WAIT: Duration = Duration::from_millis(100);

impl<B: NetOps> NodeLoop<'_, B> {
    /// Takes every sample waiting in `rx` into the per-scene queues; blocks until the next
    /// batch, rollout frame or status is due (at most 100 ms) for the first one. False when
    /// the transport is gone.
    pub(super) fn gather(&mut self, rx: &Receiver<Sample>) -> bool {
        let now = Instant::now();
        let mut wait = match self.batch_due(now) {
            Due::Now => Duration::ZERO,
            Due::At(t) => t.saturating_duration_since(now),
            Due::Nothing => MAX_WAIT,
        };
        wait = wait.min(self.next_status.saturating_duration_since(now));
        if let Some(t) = self.rollouts.next_due() {
            wait = wait.min(t.saturating_duration_since(now));
        }
        let first = if wait.is_zero() {
            None
        } else {
            match rx.recv_timeout(wait.min(MAX_WAIT)) {
                Ok(s) => Some(s),
                Err(RecvTimeoutError::Timeout) => None,
                Err(RecvTimeoutError::Disconnected) => return false,
            }
        };
        for sample in first.into_iter().chain(rx.try_iter()) {
            self.accept(sample);
        }
        true
    }

    /// Decodes and checks one sample and queues its frame (dropping the scene's oldest
    /// pending frame past `queue_depth`); bad input is counted and noted; frames of scenes
    /// another shard member owns are passed over (counted apart).
    fn accept(&mut self, sample: Sample) {
        let bytes = payload_bytes(&sample.payload);
        if bytes > self.options.max_frame_bytes {
            self.tally.report.received += 1;
            self.tally.report.rejected += 1;
            let limit = self.options.max_frame_bytes;
            let reason = format!("payload of {bytes} bytes over --max-frame-bytes {limit}");
            self.tally.note("?", reason);
            return;
        }
        let frame = match sample.decode() {
            Ok(f) => f,
            Err(reason) => {
                self.tally.report.received += 1;
                self.tally.report.malformed += 1;
                self.tally.note("?", format!("malformed payload: {reason}"));
                return;
            }
        };
        if self.shard.as_ref().is_some_and(|s| !s.owns(&frame.scene)) {
            self.others += 1;
            return;
        }
        self.tally.report.received += 1;
        if let Err(reason) = check_frame(&frame, self.model_n) {
            self.tally.report.rejected += 1;
            self.tally.note(&frame.scene.clone(), reason.to_string());
            return;
        }
        if let Some(view) = self.view.as_mut() {
            view.truth(&frame);
        }
        // Closed loop: a scene already rolled out waits for its next start (frame 0).
        if self.options.rollout.is_some()
            && frame.frame_index != 0
            && self.scenes.rolled_out(&frame.scene)
        {
            return;
        }
        let idle = self.scenes.touch(&frame.scene, self.options.idle_timeout);
        self.note_idle(u64::from(idle));
        self.note_takeover(&frame.scene, frame.frame_index);
        let queue = self.pending.entry(frame.scene.clone()).or_default();
        queue.push_back(Pending {
            frame,
            arrived: sample.received,
        });
        if queue.len() > self.options.queue_depth.max(1) {
            queue.pop_front();
            self.tally.report.dropped += 1;
        }
    }

    /// Sharded: counts and logs a scene this node meets mid-stream (it owns it now: a
    /// member left, or this node joined), whose state starts again from this frame.
    fn note_takeover(&mut self, scene: &str, index: u32) {
        let fresh = index != 0 && !self.scenes.contains(scene) && !self.pending.contains_key(scene);
        if self.shard.is_none() || !fresh {
            return;
        }
        self.adopted += 1;
        // The first ten, then every 100th: a node joining many streams must not flood the log.
        if self.adopted <= 10 || self.adopted % 100 == 0 {
            tracing::info!(
                "{}: took scene {scene:?} over at frame {index}; its state starts again here \
                 ({} so far)",
                self.options.name,
                self.adopted
            );
        }
    }
}
