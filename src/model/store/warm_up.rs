//! Warming up a batch's shapes before they are needed: [`Surrogate::warm_up_batches`] makes one
//! call of each batch size asked for, so that a GPU compiles its kernels and times cuDNN's
//! algorithms for each shape once, up front, and not in the middle of a stream the first time
//! a burst of frames makes a larger batch (NVIDIA Triton Inference Server's "model warmup",
//! `model_warmup` in a model's configuration, does the same before serving).

use super::outs::Read;
use super::{Predict, SceneStep, State, StoreError, Surrogate};
use crate::ops::NetOps;

impl<B: NetOps> Surrogate<B> {
    /// The batch sizes calls of up to `max_batch` scenes take that are above `above`, in
    /// increasing order: with [`Surrogate::with_padded_batches`] every power of two up to the
    /// one at or above `max_batch`, else `max_batch` itself (what a loaded node makes).
    pub fn batch_sizes(&self, above: usize, max_batch: usize) -> Vec<usize> {
        let top = self.padded(max_batch.max(1));
        let sizes: Vec<usize> = match self.pad_batches {
            true => std::iter::successors(Some(1usize), |b| Some(b * 2))
                .take_while(|&b| b <= top)
                .collect(),
            false => vec![top],
        };
        sizes.into_iter().filter(|&b| b > above).collect()
    }

    /// One call of each of `sizes` scenes (as [`Surrogate::step_scenes`] makes them, with
    /// `predict`), each scene a copy of one: its frame `rows` (`[N, 4]` physical), `material`
    /// (`[N]`), time step `dt` and a detached copy of `state` each (as a padded call's copies:
    /// the scene's own state and constraint data are left as they were). `ahead`: the calls
    /// read their predictions as the node's pipelined calls do ([`Surrogate::submit_scenes`]),
    /// so the same operations are recorded. The predictions are dropped and the projection's
    /// sums ([`Surrogate::take_corrections`]) kept as they were.
    ///
    /// # Errors
    /// The first call's [`StoreError`] that failed (the calls after it are not made).
    pub fn warm_up_batches(
        &self,
        (rows, material, dt): (&[f32], &[u8], f32),
        state: &State<B>,
        sizes: &[usize],
        predict: Predict,
        ahead: bool,
    ) -> Result<(), StoreError> {
        let kept = self.take_corrections();
        let read = if ahead { Read::Ahead } else { Read::Now };
        let mut result = Ok(());
        for &b in sizes {
            let steps = (0..b)
                .map(|_| SceneStep {
                    rows: rows.to_vec(),
                    material,
                    dt,
                    state: state.detached(),
                })
                .collect();
            let finished = self.submit_with(steps, predict, read).finish(self);
            if let Some(Err(e)) = finished.frames.into_iter().find(Result::is_err) {
                result = Err(e);
                break;
            }
        }
        // The copies' projections counted too: their sums go, the caller's come back.
        let _ = self.take_corrections();
        let mut sums = self.corrections.lock().unwrap_or_else(|e| e.into_inner());
        sums.add(&kept);
        result
    }
}
