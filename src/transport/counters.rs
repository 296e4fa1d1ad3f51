//! Node counters (received, published, dropped, malformed): shared between a node's threads,
//! printed on exit and, with `--stats-interval`, periodically as one log line.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// Message counters of one node. Cheap to clone (an `Arc` inside); all updates are relaxed
/// atomic adds.
#[derive(Debug, Clone, Default)]
pub struct Counters(Arc<Inner>);

#[derive(Debug, Default)]
struct Inner {
    received: AtomicU64,
    published: AtomicU64,
    dropped: AtomicU64,
    malformed: AtomicU64,
}

/// A snapshot of [`Counters`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct CounterValues {
    /// Messages that arrived (well-formed or not).
    pub received: u64,
    /// Messages sent.
    pub published: u64,
    /// Messages discarded without being processed (queue overflow, publish failure).
    pub dropped: u64,
    /// Messages that arrived but were not valid frames.
    pub malformed: u64,
}

impl Counters {
    /// Counts one received message.
    pub fn received(&self) {
        self.0.received.fetch_add(1, Ordering::Relaxed);
    }
    /// Counts one published message.
    pub fn published(&self) {
        self.0.published.fetch_add(1, Ordering::Relaxed);
    }
    /// Counts one dropped message.
    pub fn dropped(&self) {
        self.0.dropped.fetch_add(1, Ordering::Relaxed);
    }
    /// Counts one malformed message.
    pub fn malformed(&self) {
        self.0.malformed.fetch_add(1, Ordering::Relaxed);
    }
    /// Current values.
    pub fn get(&self) -> CounterValues {
        CounterValues {
            received: self.0.received.load(Ordering::Relaxed),
            published: self.0.published.load(Ordering::Relaxed),
            dropped: self.0.dropped.load(Ordering::Relaxed),
            malformed: self.0.malformed.load(Ordering::Relaxed),
        }
    }

    /// Logs the counters as one line every `interval` (on a background thread) until the
    /// returned guard is dropped.
    pub fn log_every(&self, node: &str, interval: Duration) -> StatsGuard {
        let (stop, rx) = std::sync::mpsc::channel::<()>();
        let counters = self.clone();
        let node = node.to_owned();
        let thread = std::thread::Builder::new()
            .name("stats".into())
            .spawn(move || {
                while let Err(std::sync::mpsc::RecvTimeoutError::Timeout) =
                    rx.recv_timeout(interval)
                {
                    tracing::info!("{node}: {}", counters.get());
                }
            })
            .expect("spawn stats thread");
        StatsGuard {
            stop: Some(stop),
            thread: Some(thread),
        }
    }
}

impl std::fmt::Display for CounterValues {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "received={} published={} dropped={} malformed={}",
            self.received, self.published, self.dropped, self.malformed
        )
    }
}

/// Stops the periodic stats line when dropped.
#[derive(Debug)]
pub struct StatsGuard {
    stop: Option<std::sync::mpsc::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Drop for StatsGuard {
    fn drop(&mut self) {
        drop(self.stop.take());
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
