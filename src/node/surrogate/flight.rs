//! A batch's network call on its way through the surrogate node: one scene's part of it
//! ([`Job`]), the call recorded with its predictions still on the device ([`InFlight`],
//! pipelined calls, `--pipeline`), the call landed, its predictions on the host and
//! projected ([`Landed`], what the lander published of it: [`Published`]), and the
//! publisher the loop and the lander share ([`SharedPublisher`]). The batcher (`batcher.rs`)
//! makes the jobs and hands the calls in flight to the lander thread (`lander.rs`), which
//! hands them back landed; both read these types from here.

use std::sync::{Arc, Mutex, MutexGuard};

use crate::model::store::{Finished, Predict, State, Submitted};
use crate::transport::FramePublisher;

use super::schedule::Pending;

/// One scene's part of a batch.
pub(super) struct Job<B: burn::tensor::backend::Backend> {
    /// The scene's id.
    pub(super) scene: String,
    /// `[N, 4]` the frame the call reads.
    pub(super) rows: Vec<f32>,
    /// `[N]` material ids.
    pub(super) material: Vec<u8>,
    /// Frame spacing, s.
    pub(super) dt: f32,
    /// The scene's state before the call.
    pub(super) state: State<B>,
    /// A whole network call (K frames: a rollout's) or the next frame alone.
    pub(super) predict: Predict,
    /// The input frame of a live job; None for a rollout's call.
    pub(super) input: Option<Pending>,
}

/// A batch of live frames whose call is recorded and whose predictions are on their way
/// (`batcher.rs`'s module doc): the call, and per scene of it the job (None: its call
/// failed at once).
pub(super) struct InFlight<B: burn::tensor::backend::Backend> {
    /// The recorded call.
    pub(super) submitted: Submitted<B>,
    /// Per scene of the call, its job.
    pub(super) jobs: Vec<Option<Job<B>>>,
}

impl<B: burn::tensor::backend::Backend> InFlight<B> {
    /// The call and its jobs.
    pub(super) fn into_parts(self) -> (Submitted<B>, Vec<Option<Job<B>>>) {
        (self.submitted, self.jobs)
    }
}

/// A call whose predictions are on the host, projected: the call's per-scene frames and its
/// jobs (None: the job's call failed when it was recorded).
pub(super) struct Landed<B: burn::tensor::backend::Backend> {
    pub(super) finished: Finished,
    pub(super) jobs: Vec<Option<Job<B>>>,
    /// What the lander thread published of the call's live frames (None: it publishes
    /// nothing, the loop does: `Lander::start`).
    pub(super) published: Option<Published>,
}

/// The counts of a call's predictions the lander thread published, for the loop's report.
#[derive(Debug, Default)]
pub(super) struct Published {
    /// Frames sent.
    pub(super) sent: u64,
    /// Frames the transport refused, and its last error.
    pub(super) failed: u64,
    pub(super) last_error: Option<String>,
    /// Per frame sent, arrival -> publication, us.
    pub(super) latencies_us: Vec<f64>,
}

/// The node's frame publisher, shared by the loop and the lander thread (`lander.rs`).
pub(super) type SharedPublisher = Arc<Mutex<Box<dyn FramePublisher>>>;

/// `publisher` locked; a thread that panicked while holding it left nothing half-sent
/// that matters (a frame is one call), so its poison is passed over.
pub(super) fn lock(publisher: &SharedPublisher) -> MutexGuard<'_, Box<dyn FramePublisher>> {
    publisher.lock().unwrap_or_else(|e| e.into_inner())
}
