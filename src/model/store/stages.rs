//! Where a grid model's network call spends its wall time, by stage, while
//! `MINFLOW_CALL_STAGES=1` (off otherwise: no clock is read). `bench rollout` prints the
//! stages after each row (docs/speed.md, "Where a GPU call's time goes"); the figures are what a GPU call costs
//! beyond its kernels.
//!
//! The stages of one call ([`Stage`]): the input (the frame uploaded, the velocity history
//! and features built), the recording (the network's operations queued: on a GPU the host
//! returns before the device has run them), the device (a wait for the GPU to finish what
//! was queued; on the CPU nothing is left to wait for), and the output (the predictions
//! downloaded and split by frame). The device stage's wait is one the download makes anyway.
//!
//! The constraint projection's wall time is counted always (one clock read a call):
//! [`take_projection`], and the thread time of building each scene's constraint data on its
//! first projection (a once-a-scene cost inside that wall time): [`take_setup`].

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

/// The stages of a call, in order.
#[derive(Clone, Copy, Debug)]
pub(super) enum Stage {
    Input,
    Record,
    Device,
    Output,
}

/// Seconds per stage, summed over the calls since the last [`take`].
static SECONDS: Mutex<[f64; 4]> = Mutex::new([0.0; 4]);
/// Calls since the last [`take`].
static CALLS: AtomicUsize = AtomicUsize::new(0);

/// Whether `MINFLOW_CALL_STAGES=1` (read once).
pub(super) fn on() -> bool {
    crate::switches::call_stages()
}

/// A call's clock: [`Clock::lap`] ends a stage; dropping the clock counts the call.
pub(super) struct Clock {
    last: Instant,
}

impl Clock {
    /// A clock for a call starting now, or None when stages are off.
    pub(super) fn start() -> Option<Self> {
        on().then(|| Self {
            last: Instant::now(),
        })
    }

    /// Adds the time since the last lap to `stage`.
    pub(super) fn lap(&mut self, stage: Stage) {
        let now = Instant::now();
        let mut seconds = SECONDS.lock().unwrap_or_else(|e| e.into_inner());
        seconds[stage as usize] += (now - self.last).as_secs_f64();
        self.last = now;
    }
}

impl Drop for Clock {
    fn drop(&mut self) {
        CALLS.fetch_add(1, Ordering::Relaxed);
    }
}

/// The stages' mean milliseconds a call since the last take (input, record, device, output)
/// and the number of calls, then zeroed; None when stages are off or no call was timed.
pub fn take() -> Option<([f64; 4], usize)> {
    if !on() {
        return None;
    }
    let calls = CALLS.swap(0, Ordering::Relaxed);
    let seconds = std::mem::take(&mut *SECONDS.lock().unwrap_or_else(|e| e.into_inner()));
    (calls > 0).then(|| (seconds.map(|s| s * 1e3 / calls as f64), calls))
}

/// Nanoseconds of constraint projection (every scene of a call), summed since the last
/// [`take_projection`].
static PROJECTION_NS: AtomicU64 = AtomicU64::new(0);

/// Adds one projection's wall time.
pub(super) fn count_projection(took: std::time::Duration) {
    let ns = u64::try_from(took.as_nanos()).unwrap_or(u64::MAX);
    PROJECTION_NS.fetch_add(ns, Ordering::Relaxed);
}

/// Seconds of constraint projection since the last take (all threads' calls), then zeroed.
pub fn take_projection() -> f64 {
    PROJECTION_NS.swap(0, Ordering::Relaxed) as f64 * 1e-9
}

/// Nanoseconds of building scenes' constraint data (thread time, every thread), and the
/// scenes built, since the last [`take_setup`].
static SETUP_NS: AtomicU64 = AtomicU64::new(0);
static SETUPS: AtomicUsize = AtomicUsize::new(0);

/// Adds one scene's constraint-data build.
pub(super) fn count_setup(took: std::time::Duration) {
    let ns = u64::try_from(took.as_nanos()).unwrap_or(u64::MAX);
    SETUP_NS.fetch_add(ns, Ordering::Relaxed);
    SETUPS.fetch_add(1, Ordering::Relaxed);
}

/// Seconds of constraint-data builds and the scenes built since the last take, then zeroed.
pub fn take_setup() -> (f64, usize) {
    let ns = SETUP_NS.swap(0, Ordering::Relaxed);
    (ns as f64 * 1e-9, SETUPS.swap(0, Ordering::Relaxed))
}
