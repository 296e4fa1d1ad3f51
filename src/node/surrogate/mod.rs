//! The surrogate node (`minflow node`): subscribes to particle frames, keeps one hidden
//! state per `scene`, and for every input frame publishes the predicted next frame
//! (docs/design.md, "Messages": same scene and material, `frame_index` + 1, stamp + `dt`).
//! In closed loop (`rollout` R), after the first T frames of a scene it publishes R predicted
//! frames by feeding its own predictions back, one network call at a time between the
//! other scenes' work. A bundled grid model (`train --bundle K`)
//! predicts K frames per network call there, so R frames cost ceil(R / K) calls, each from
//! the last frame of the call before. Fed live frames, a bundled model makes one call per
//! input frame and publishes the first frame of its bundle (the next frame, as a
//! single-frame model does); the rest of the bundle is not published, since the next input
//! frame supersedes it.
//!
//! Threads: the transport's I/O thread only hands samples over (a channel); this node's
//! own thread decodes, checks, queues per scene and predicts, so a slow model never blocks
//! a publisher. When frames of a scene arrive faster than they are predicted, the oldest
//! pending frame of that scene is dropped and counted (`queue_depth`).
//!
//! State rules: a scene's hidden state is reset when the scene starts (frame_index 0 or an
//! unseen scene id), on a gap or out-of-order frame ([`OnGap::Reset`]; [`OnGap::Skip`]
//! drops out-of-order frames and carries on over gaps), and after `idle_timeout` without
//! activity (a frame arriving, or a prediction of its rollout published); states idle that
//! long are dropped; in closed loop a scene is rolled out once (until its frame 0 comes
//! again), even if its state was dropped meanwhile, and at most `max_scenes` are kept (least
//! recently seen evicted), so memory stays bounded. A grid model with `--reference
//! first-frame` takes the first frame of a scene as its reference positions and keeps them
//! over a gap reset (the stream goes on), not over a restart.
//!
//! Bad input is never predicted on: a payload larger than `max_frame_bytes` is `rejected`
//! before it is decoded; a payload that does not decode is `malformed`; a frame with a
//! particle count other than the model's N, non-finite values or an unknown material id is
//! `rejected`. Each is counted, logged once per scene and reason, and reported in
//! [`SurrogateStatus`] (published once per second); other scenes are served as usual.
//!
//! Dynamic batching (`max_batch`, `max_batch_delay`; [`batcher`]): frames of different
//! scenes that wait together go through one network call, each scene's state stacked into
//! the call's batch and split back, as NVIDIA Triton Inference Server's dynamic batcher
//! does for requests. Closed-loop rollouts ([`closed`]) are calls like any other, so a long
//! rollout never holds the other scenes up. Sharding (`shard`; [`shard`]): nodes of one
//! group divide the scenes among the live ones over zenoh liveliness.
//!
//! Files: [`options`] holds the options and the report, [`admission`] the rules (which
//! frames are taken, what a frame does to its scene's state), [`scenes`] the per-scene
//! states under those rules, [`schedule`] the queues (pending frames, rollouts under way)
//! and when a batch is due, [`node_loop`] the loop's state, [`intake`] the arrival of
//! frames, [`batcher`] the calls (their sizes warmed up first on a GPU: [`warm`]), [`flight`]
//! a call's jobs on their way, [`lander`] the thread that lands pipelined calls, [`closed`]
//! the rollouts, [`shard`] the group, [`run`] the loop itself, [`report`] the counters and
//! logs, [`frames`] the frame helpers.

mod admission;
mod batcher;
mod closed;
mod flight;
mod frames;
mod intake;
mod lander;
mod node_loop;
mod options;
mod report;
mod run;
mod scenes;
mod schedule;
pub mod shard;
mod warm;

pub use frames::state_rows;
pub use options::{summary, NodeOptions, NodeReport, OnGap};
pub use report::LOOP_STAGES;
pub use run::run;
