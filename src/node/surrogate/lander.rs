//! The surrogate node's lander thread (`--pipeline`): it takes the pipelined calls in
//! order ([`InFlight`]), waits for each call's predictions to reach the host and projects
//! them onto the model's constraints (`Submitted::finish`), and hands them back to the loop,
//! which publishes them. The loop meanwhile gathers, stacks and records the next batch's
//! call, so neither the wait for the GPU nor the projection (on the host's cores) holds it.
//! At most [`MAX_LANDING`] calls are handed over and not yet back: the loop waits for the
//! oldest before it hands over another, so the GPU has the next call queued but the queue
//! stays short. The thread ends when the loop drops its [`Lander`]. Used by
//! `batcher.rs`; started by `run.rs`.

use std::sync::mpsc::{channel, Receiver, Sender};
use std::thread::Scope;

use crate::model::store::Surrogate;
use crate::ops::NetOps;

use super::flight::{InFlight, Landed};

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
    /// Starts the lander thread in `scope`, landing calls of `surrogate`.
    ///
    /// # Panics
    /// When the thread cannot be spawned (as `std::thread::Builder::spawn_scoped`).
    pub(super) fn start<'scope, 'env>(
        scope: &'scope Scope<'scope, 'env>,
        surrogate: &'env Surrogate<B>,
    ) -> Self {
        let (calls, to_land) = channel::<InFlight<B>>();
        let (done, landed) = channel();
        std::thread::Builder::new()
            .name("minflow-land".into())
            .spawn_scoped(scope, move || {
                for call in to_land {
                    let (submitted, jobs) = call.into_parts();
                    let finished = submitted.finish(surrogate);
                    if done.send(Landed { finished, jobs }).is_err() {
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
