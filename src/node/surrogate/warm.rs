//! The node's batch warm-up (`--warm-up-batches`, on by default on a GPU): before a batch
//! size of a particle count first carries real frames, one call of that size of copies of one
//! steady scene ([`Surrogate::warm_up_batches`](crate::model::store::Surrogate::warm_up_batches)),
//! so that its kernels and cuDNN's algorithms are ready: otherwise the first call of each size
//! stalls every stream for a few hundred milliseconds, in mid-stream, when a burst first makes
//! it (NVIDIA Triton Inference Server's "model warmup" does the same before serving). The sizes
//! follow the scenes seen of that count (up to `--max-batch`): a count that starts with one
//! stream warms one size, and the larger ones as more streams come, so that a new count in
//! mid-service holds the other streams up no longer than its own first calls would.

use std::time::Instant;

use crate::model::store::Predict;
use crate::ops::NetOps;

use super::flight::Job;
use super::node_loop::NodeLoop;

impl<B: NetOps> NodeLoop<'_, B> {
    /// Warms up the batch sizes `jobs`' kinds of call (particle count; a live frame's call or
    /// a closed-loop rollout's) may now take and have not taken warmed (module doc), each with
    /// a steady job of that kind (its state T frames in: the calls the node makes from then
    /// on). The calls handed over land first, so no other projection runs meanwhile.
    pub(super) fn warm_up(&mut self, jobs: &[Job<B>]) {
        if !self.options.warm_up {
            return;
        }
        let max = self.options.max_batch.max(1);
        let mut todo = Vec::new();
        for (i, job) in jobs.iter().enumerate() {
            let bundle = job.predict == Predict::Bundle;
            let kind = self.warmed.entry((job.material.len(), bundle)).or_default();
            // Every call passes here: the scene's name is copied only the first time.
            if kind.scenes.len() < max && !kind.scenes.contains(&job.scene) {
                kind.scenes.insert(job.scene.clone());
            }
            // A rollout's first call is its T-th frame's; a live frame's, the one after.
            let steady = job.state.frames + usize::from(bundle) >= self.window;
            // The sizes warmed (powers of two, or the count itself unpadded) cover `seen`
            // exactly when `up_to >= seen`: nothing to ask `batch_sizes` then.
            let seen = kind.scenes.len();
            if !steady || kind.up_to >= seen {
                continue;
            }
            if !todo.iter().any(|&(j, _)| same_kind(&jobs[j], job)) {
                todo.push((i, self.surrogate.batch_sizes(kind.up_to, seen)));
            }
        }
        if todo.is_empty() {
            return;
        }
        self.publish_landed(0);
        for (i, sizes) in todo {
            self.warm_up_kind(&jobs[i], &sizes);
        }
    }

    /// One call of each of `sizes` of copies of `job`'s scene, logged.
    fn warm_up_kind(&mut self, job: &Job<B>, sizes: &[usize]) {
        let (n, bundle) = (job.material.len(), job.predict == Predict::Bundle);
        let start = Instant::now();
        let scene = (&job.rows[..], &job.material[..], job.dt);
        let ahead = self.lander.is_some() && !bundle;
        let warmed = self
            .surrogate
            .warm_up_batches(scene, &job.state, sizes, job.predict, ahead);
        let what = if bundle { " (closed loop)" } else { "" };
        let list = sizes.iter().map(usize::to_string).collect::<Vec<_>>();
        match warmed {
            Ok(()) => tracing::info!(
                "warmed up batch sizes {} of scenes of {n} particles{what} in {:.1} s",
                list.join(", "),
                start.elapsed().as_secs_f64()
            ),
            Err(e) => tracing::warn!(
                "warming up batches of scenes of {n} particles{what} failed, the node goes on: {e}"
            ),
        }
        // Tried once: a failure is not tried again every batch.
        let kind = self.warmed.entry((n, bundle)).or_default();
        kind.up_to = kind.up_to.max(sizes.iter().copied().max().unwrap_or(0));
    }
}

/// Whether two jobs make calls of one kind (particle count, closed loop or not).
fn same_kind<B: burn::tensor::backend::Backend>(a: &Job<B>, b: &Job<B>) -> bool {
    a.material.len() == b.material.len() && a.predict == b.predict
}
