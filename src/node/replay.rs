//! The ground-truth player (`minflow replay`, like `ros2 bag play`): merges the frames of
//! one or more bags by log time and publishes them on a topic at the bags' own pace
//! (scaled by a rate, or as fast as the transport accepts them), optionally looping,
//! starting at an offset and keeping only scenes that match glob patterns.
//!
//! Bags are streamed, not loaded: one open reader per bag and a heap of their next messages
//! (a k-way merge by log time), so a dataset larger than memory plays as well. A truncated
//! bag plays up to its last complete message and is reported.

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use crate::bag::{bag_paths, read::decode_checked, BagError, BagReader};
use crate::msgs::ParticleFrame;
use crate::transport::{wait_for_subscribers, Counters, FramePublisher};

/// What to play and how.
#[derive(Debug, Clone)]
pub struct ReplayOptions {
    /// Bag files or folders of bags.
    pub inputs: Vec<PathBuf>,
    /// Topic read from the bags.
    pub input_topic: String,
    /// Playback speed: 1 = the bags' own pace (log times), 2 = twice as fast, 0 = as fast
    /// as the transport accepts frames.
    pub rate: f64,
    /// Play again from the start when done, until stopped.
    pub looped: bool,
    /// Skip the first seconds of log time.
    pub start_offset: f64,
    /// Keep only scenes matching one of these glob patterns (all when empty).
    pub scenes: Vec<glob::Pattern>,
    /// Wait for this many subscribers before the first frame (0: do not wait).
    pub wait_for_subscribers: usize,
    /// Give up waiting after this long.
    pub wait_timeout: Duration,
}

/// What a replay did.
#[derive(Debug, Clone, Default)]
pub struct ReplayReport {
    /// Frames published.
    pub published: u64,
    /// Frames skipped by `--scene` or `--start-offset`.
    pub filtered: u64,
    /// Bags that ended early (truncated or damaged), with the reason.
    pub truncated: Vec<String>,
    /// Whether the replay was stopped by a signal before the end.
    pub interrupted: bool,
    /// Wall time from the first to the last frame.
    pub elapsed: Duration,
}

/// Errors that stop a replay.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    /// A bag could not be opened or a message could not be decoded.
    #[error(transparent)]
    Bag(#[from] BagError),
    /// No subscriber came within the timeout.
    #[error("{wanted} subscriber(s) wanted, {have} after waiting {timeout:?} (use --wait-for-subscribers 0 to play anyway)")]
    NoSubscribers {
        wanted: usize,
        have: usize,
        timeout: Duration,
    },
    /// Publishing failed.
    #[error(transparent)]
    Transport(#[from] crate::transport::TransportError),
    /// Nothing to play.
    #[error("no frames on {topic} in {inputs} (after --scene and --start-offset filters)")]
    Empty { topic: String, inputs: String },
}

/// One message of the merge: its log time, the bag it came from, bytes and frame.
struct Next {
    log_time: u64,
    bag: usize,
    data: Vec<u8>,
    frame: ParticleFrame,
}

impl PartialEq for Next {
    fn eq(&self, other: &Self) -> bool {
        (self.log_time, self.bag) == (other.log_time, other.bag)
    }
}
impl Eq for Next {}
impl PartialOrd for Next {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Next {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        (self.log_time, self.bag).cmp(&(other.log_time, other.bag))
    }
}

/// The frames of several bags merged by log time (ties: earlier bag, then file order).
struct Merge {
    readers: Vec<BagReader>,
    heap: BinaryHeap<Reverse<Next>>,
    topic: String,
    truncated: Vec<String>,
}

impl Merge {
    fn open(paths: &[PathBuf], topic: &str) -> Result<Self, BagError> {
        let mut merge = Merge {
            readers: Vec::new(),
            heap: BinaryHeap::new(),
            topic: topic.to_owned(),
            truncated: Vec::new(),
        };
        for path in paths {
            merge.readers.push(BagReader::open(path)?);
        }
        for bag in 0..merge.readers.len() {
            merge.advance(bag)?;
        }
        Ok(merge)
    }

    /// Pushes bag `bag`'s next frame on the topic, if any.
    fn advance(&mut self, bag: usize) -> Result<(), BagError> {
        let reader = &mut self.readers[bag];
        for message in reader.by_ref() {
            let message = match message {
                Ok(m) => m,
                Err(err) => {
                    tracing::warn!("{err}; playing what came before");
                    self.truncated.push(err.to_string());
                    return Ok(());
                }
            };
            if message.topic() != self.topic || !message.is_particle_frame() {
                continue;
            }
            let frame = decode_checked(reader.path(), &self.topic, message.index, &message.data)?;
            self.heap.push(Reverse(Next {
                log_time: message.log_time,
                bag,
                data: message.data,
                frame,
            }));
            return Ok(());
        }
        Ok(())
    }

    /// The earliest log time of any frame on `topic` in `paths` (a pass over the bags: log
    /// times need not be sorted in file order, and a recording may start mid-scene).
    fn earliest(paths: &[PathBuf], topic: &str) -> Result<Option<u64>, BagError> {
        let mut merge = Merge::open(paths, topic)?;
        let mut least: Option<u64> = None;
        while let Some(next) = merge.next()? {
            least = Some(least.map_or(next.log_time, |l| l.min(next.log_time)));
        }
        Ok(least)
    }

    fn next(&mut self) -> Result<Option<Next>, BagError> {
        let Some(Reverse(next)) = self.heap.pop() else {
            return Ok(None);
        };
        self.advance(next.bag)?;
        Ok(Some(next))
    }
}

/// Plays the bags on `publisher`. `progress` is called after every published frame with the
/// count so far. Stops early when `stop` turns true.
///
/// # Errors
/// [`ReplayError`]: unreadable bags, no subscribers in time, publish failures, nothing to play.
pub fn play(
    options: &ReplayOptions,
    publisher: &mut dyn FramePublisher,
    counters: &Counters,
    stop: &AtomicBool,
    mut progress: impl FnMut(u64),
) -> Result<ReplayReport, ReplayError> {
    let paths = bag_paths(&options.inputs)?;
    let mut report = ReplayReport::default();
    wait_for_readers(options, publisher)?;
    // `--start-offset` counts from the earliest log time in the bags; without it nothing is
    // filtered by time (a frame logged before the first one in file order still plays).
    let offset_ns = (options.start_offset.max(0.0) * 1e9) as u64;
    let earliest = if offset_ns > 0 {
        Merge::earliest(&paths, &options.input_topic)?
    } else {
        None
    };
    let mut first_start: Option<Instant> = None;
    loop {
        let mut merge = Merge::open(&paths, &options.input_topic)?;
        let mut anchor: Option<(Instant, u64)> = None;
        let mut played_this_pass = 0u64;
        while let Some(next) = merge.next()? {
            if stop.load(Ordering::Relaxed) {
                report.interrupted = true;
                break;
            }
            // The pass's clock: its first message's log time maps onto now.
            let (t0, log0) =
                *anchor.get_or_insert_with(|| (Instant::now(), earliest.unwrap_or(next.log_time)));
            if (offset_ns > 0 && next.log_time < log0 + offset_ns)
                || (!options.scenes.is_empty()
                    && !options.scenes.iter().any(|p| p.matches(&next.frame.scene)))
            {
                report.filtered += 1;
                continue;
            }
            if options.rate > 0.0 {
                // Log times are any u64: a wait past the clock's range waits until stopped.
                let wait = Duration::try_from_secs_f64(
                    next.log_time.saturating_sub(log0).saturating_sub(offset_ns) as f64
                        / 1e9
                        / options.rate,
                )
                .unwrap_or(Duration::MAX);
                let far = Duration::from_secs(u64::from(u32::MAX));
                sleep_until(t0.checked_add(wait).unwrap_or(t0 + far), stop);
            }
            publisher.publish_cdr(&next.data, &next.frame)?;
            first_start.get_or_insert_with(Instant::now);
            counters.published();
            report.published += 1;
            played_this_pass += 1;
            progress(report.published);
        }
        report.truncated.append(&mut merge.truncated);
        if played_this_pass == 0 && !report.interrupted {
            return Err(ReplayError::Empty {
                topic: options.input_topic.clone(),
                inputs: options
                    .inputs
                    .iter()
                    .map(|p| p.display().to_string())
                    .collect::<Vec<_>>()
                    .join(" "),
            });
        }
        if !options.looped || report.interrupted || stop.load(Ordering::Relaxed) {
            report.interrupted |= stop.load(Ordering::Relaxed);
            break;
        }
    }
    report.elapsed = first_start.map_or(Duration::ZERO, |t| t.elapsed());
    publisher.flush(Duration::from_secs(5));
    Ok(report)
}

/// Waits for `--wait-for-subscribers` subscribers (none: at once), then a moment more so
/// the subscribers' side has matched too.
///
/// # Errors
/// [`ReplayError::NoSubscribers`] when they do not come in time.
fn wait_for_readers(
    options: &ReplayOptions,
    publisher: &mut dyn FramePublisher,
) -> Result<(), ReplayError> {
    if options.wait_for_subscribers > 0 {
        tracing::info!("waiting for {} subscriber(s)", options.wait_for_subscribers);
        if !wait_for_subscribers(
            publisher,
            options.wait_for_subscribers,
            options.wait_timeout,
        ) {
            return Err(ReplayError::NoSubscribers {
                wanted: options.wait_for_subscribers,
                have: publisher.subscriber_count(),
                timeout: options.wait_timeout,
            });
        }
        // Matching is seen from the publisher's side first; give the subscriber's side (DDS
        // readers accept data only from writers they matched) a moment too.
        std::thread::sleep(Duration::from_millis(300));
    }
    Ok(())
}

/// Sleeps until `due`, waking early if `stop` turns true. Sleeps in slices and spins for
/// the last 200 microseconds for accurate pacing.
fn sleep_until(due: Instant, stop: &AtomicBool) {
    loop {
        let now = Instant::now();
        if now >= due || stop.load(Ordering::Relaxed) {
            return;
        }
        let left = due - now;
        if left > Duration::from_micros(200) {
            std::thread::sleep((left - Duration::from_micros(200)).min(Duration::from_millis(50)));
        } else {
            std::hint::spin_loop();
        }
    }
}
