//! A device tensor's values on their way to the host ([`ReadAhead`]): the read queued behind
//! the work recorded before it, so that the host can record more work (the next network
//! call) before it waits, and the GPU runs that work while the host publishes what came back.
//! burn's own read (`into_data`) is a future that queues nothing until it is polled, and then
//! waits for everything queued before the poll, the next call included. Made by
//! [`super::NetOps::read_ahead`] (CUDA: `cuda/read.rs`); used by the surrogate node's
//! pipelined calls (`model::store::Surrogate::submit_scenes`).

/// What waits for the values: returns them in `parts` equal consecutive pieces of the
/// tensor's row-major f32 order (none for 0: the wait alone), or the backend's error.
type Wait = Box<dyn FnOnce(usize) -> Result<Vec<Vec<f32>>, String> + Send>;

/// The values of a device tensor, read back in stream order after the work recorded before
/// [`super::NetOps::read_ahead`] made it; [`ReadAhead::wait`] blocks until they are on the
/// host. Dropped unread, it still waits for the copy (the host buffer it lands in is only
/// reused or freed once the copy is done).
pub struct ReadAhead {
    wait: Option<Wait>,
}

impl ReadAhead {
    /// A read whose values `wait(parts)` returns once they have landed, in `parts` equal
    /// consecutive pieces (`wait(0)`: only waits).
    pub fn new(wait: impl FnOnce(usize) -> Result<Vec<Vec<f32>>, String> + Send + 'static) -> Self {
        Self {
            wait: Some(Box::new(wait)),
        }
    }

    /// Blocks until the values are on the host; returns them (row-major f32).
    ///
    /// # Errors
    /// The backend's copy or synchronisation failed (its message).
    pub fn wait(self) -> Result<Vec<f32>, String> {
        Ok(self.wait_parts(1)?.pop().unwrap_or_default())
    }

    /// Blocks until the values are on the host; returns them as `parts` (at least 1) equal
    /// consecutive pieces of their row-major order, each copied once from where they landed:
    /// a call's `[K B, N, 4]` predictions as its K frames.
    ///
    /// # Errors
    /// The backend's copy or synchronisation failed (its message).
    pub fn wait_parts(mut self, parts: usize) -> Result<Vec<Vec<f32>>, String> {
        match self.wait.take() {
            Some(wait) => wait(parts.max(1)),
            None => Err("read waited for twice".into()),
        }
    }
}

impl Drop for ReadAhead {
    fn drop(&mut self) {
        if let Some(wait) = self.wait.take() {
            let _ = wait(0);
        }
    }
}

impl std::fmt::Debug for ReadAhead {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ReadAhead")
            .field("waited", &self.wait.is_none())
            .finish()
    }
}
