//! The surrogate node's lander thread (`--pipeline`): it takes the pipelined calls in
//! order ([`InFlight`]), waits for each call's predictions to reach the host, projects them
//! onto the model's constraints (`Submitted::finish`) and, given an outlet, publishes the
//! live frames' predictions itself, then hands the call back to the loop for its counters
//! (and, without an outlet, to publish). The loop meanwhile gathers, stacks and records the
//! next batch's call, so neither the wait for the GPU, the projection (on the host's cores)
//! nor the encoding and sending of 256 frames a call holds it.
//! At most [`MAX_LANDING`] calls are handed over and not yet back: the loop waits for the
//! oldest before it hands over another, so the GPU has the next call queued but the queue
//! stays short. The thread ends when the loop drops its [`Lander`]. Used by
//! `batcher.rs`; started by `run.rs`.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{channel, Receiver, Sender};
use std::sync::Arc;
use std::thread::Scope;
use std::time::Instant;

use crate::model::store::{Finished, Surrogate};
use crate::ops::NetOps;

use super::flight::{lock, InFlight, Job, Landed, Published, SharedPublisher};
use super::frames::predicted_frame;

/// Calls handed to the lander and not yet back, at most.
pub(super) const MAX_LANDING: usize = 2;

/// The loop's end of the lander thread.
pub(super) struct Lander<B: burn::tensor::backend::Backend> {
    calls: Sender<InFlight<B>>,
    landed: Receiver<Landed<B>>,
    /// Calls handed over and not yet back.
    pub(super) landing: usize,
}

impl<B: NetOps> Lander<B> {
    /// Starts the lander thread in `scope`, landing calls of `surrogate`; with `outlet` it
    /// publishes each live job's next frame there (the node's publisher, shared with the
    /// loop). Its busy time (ns) is added to `busy`.
    ///
    /// # Panics
    /// When the thread cannot be spawned (as `std::thread::Builder::spawn_scoped`).
    pub(super) fn start<'scope, 'env>(
        scope: &'scope Scope<'scope, 'env>,
        surrogate: &'env Surrogate<B>,
        outlet: Option<SharedPublisher>,
        busy: Arc<AtomicU64>,
    ) -> Self {
        let (calls, to_land) = channel::<InFlight<B>>();
        let (done, landed) = channel();
        std::thread::Builder::new()
            .name("minflow-land".into())
            .spawn_scoped(scope, move || {
                for call in to_land {
                    let start = Instant::now();
                    let (submitted, jobs) = call.into_parts();
                    let finished = submitted.finish(surrogate);
                    let published = outlet.as_ref().map(|o| publish(o, &finished, &jobs));
                    busy.fetch_add(start.elapsed().as_nanos() as u64, Ordering::Relaxed);
                    let back = Landed {
                        finished,
                        jobs,
                        published,
                    };
                    if done.send(back).is_err() {
                        return;
                    }
                }
            })
            .expect("spawning the node's lander thread");
        Lander {
            calls,
            landed,
            landing: 0,
        }
    }

    /// Hands `call` over to be landed.
    pub(super) fn hand_over(&mut self, call: InFlight<B>) {
        // A lander that ended (it panicked) takes nothing; its calls are not published.
        if self.calls.send(call).is_ok() {
            self.landing += 1;
        }
    }

    /// The next landed call: waiting for it when `block`, else only if one is back.
    /// None when none is (or the thread ended).
    pub(super) fn next(&mut self, block: bool) -> Option<Landed<B>> {
        if self.landing == 0 {
            return None;
        }
        let landed = match block {
            true => self.landed.recv().ok(),
            false => self.landed.try_recv().ok(),
        };
        match landed {
            Some(l) => {
                self.landing -= 1;
                Some(l)
            }
            None if block => {
                // The thread ended: nothing more comes back.
                self.landing = 0;
                None
            }
            None => None,
        }
    }
}

/// Publishes on `outlet` the next frame of each live job of a landed call whose prediction
/// came back (as the loop's `publish_call` would), and counts what it sent.
fn publish<B: burn::tensor::backend::Backend>(
    outlet: &SharedPublisher,
    finished: &Finished,
    jobs: &[Option<Job<B>>],
) -> Published {
    let mut counts = Published::default();
    let mut publisher = lock(outlet);
    for (job, result) in jobs.iter().zip(&finished.frames) {
        let (
            Some(Job {
                input: Some(input), ..
            }),
            Ok(bundle),
        ) = (job, result)
        else {
            continue;
        };
        let Some(rows) = bundle.first() else { continue };
        let next = predicted_frame(&input.frame, rows, 1);
        match publisher.publish(&next) {
            Ok(()) => {
                counts.sent += 1;
                (counts.latencies_us).push(input.arrived.elapsed().as_secs_f64() * 1e6);
            }
            Err(e) => {
                counts.failed += 1;
                counts.last_error = Some(e.to_string());
            }
        }
    }
    counts
}
