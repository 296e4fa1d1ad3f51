//! The surrogate node's loop (`minflow node`): declare the output and status publishers,
//! wait for the output's subscribers, join the shard group (`--shard`), subscribe to the
//! input (its samples decoded on a thread of their own), then repeat { periodic status and
//! counters, gather the decoded samples into per-scene queues ([`super::intake`]), publish
//! the rollout frames that are due ([`super::closed`]), and when a batch is due step it
//! ([`super::batcher`]) }. The totals come back as a [`NodeReport`].

use std::collections::{BTreeMap, HashSet, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::channel;
use std::time::{Duration, Instant};

use crate::model::store::Surrogate;
use crate::msgs::ParticleFrame;
use crate::ops::NetOps;
use crate::transport::{FramePublisher, StatusPublisher, Transport, TransportError};
use crate::viz::PredictionView;

use super::closed::Rollouts;
use super::intake::spawn_decoder;
use super::report::{log_latencies, log_start, wall_time, BatchStats, StageTimes, Tally};
use super::scenes::Scenes;
use super::shard::Shard;
use super::{summary, NodeOptions, NodeReport};

/// Runs the node until `stop` turns true (or `max_published` is reached). Returns totals.
///
/// Reads as its steps: declare the output (and status) publishers, wait for the output's
/// subscribers, join the shard group, subscribe to the input, then loop { status, gather,
/// publish due rollout frames, step a batch when one is due }.
///
/// # Errors
/// Declaring the subscription, publishers or shard token fails ([`TransportError`]);
/// `--shard` over a transport without a zenoh session.
pub fn run<B: NetOps>(
    options: &NodeOptions,
    surrogate: &Surrogate<B>,
    transport: &dyn Transport,
    stop: &AtomicBool,
) -> Result<NodeReport, TransportError> {
    let publisher = transport.publisher(&options.output)?;
    let status_pub = open_status_publisher(options, transport);
    if !wait_for_output_subscribers(options, publisher.as_ref(), stop) {
        return Ok(NodeReport {
            node: options.name.clone(),
            ..NodeReport::default()
        });
    }
    let shard = join_shard(options, transport)?;
    let (tx, rx) = channel();
    let _subscription = transport.subscribe(&options.input, tx)?;
    log_start(options, surrogate, transport);
    let mut node = NodeLoop::new(options, surrogate, publisher, status_pub);
    node.shard = shard;
    let (rx, decoder) = spawn_decoder(
        rx,
        options.max_frame_bytes,
        node.model_n,
        node.times.decode.clone(),
    );
    while !stop.load(Ordering::Relaxed) && !node.done() {
        node.periodic();
        if !node.gather(&rx) {
            // The decoder ended: the transport closed the subscription, or it panicked
            // (then so does the node, not a clean stop).
            if let Err(panic) = decoder.join() {
                std::panic::resume_unwind(panic);
            }
            break;
        }
        node.publish_due_rollouts();
        if node.batch_due(Instant::now()).is_now() {
            node.step_batch();
        }
    }
    Ok(node.finish())
}

/// Joins `options.shard`'s group on the transport's zenoh session (None without `--shard`).
fn join_shard(
    options: &NodeOptions,
    transport: &dyn Transport,
) -> Result<Option<Shard>, TransportError> {
    let Some(group) = &options.shard else {
        return Ok(None);
    };
    let Some(session) = transport.zenoh_session() else {
        return Err(TransportError::Declare {
            transport: transport.kind(),
            what: "shard group",
            topic: group.clone(),
            reason: "--shard needs --transport zenoh (zenoh liveliness tokens)".into(),
        });
    };
    let shard = Shard::join(&session, group, &options.name)?;
    tracing::info!(
        "{}: shard group {group:?}: {} node(s) alive",
        options.name,
        shard.members()
    );
    Ok(Some(shard))
}

/// The status publisher if `options.status` names a topic; a failure to declare it is
/// logged and the node runs without status reports.
fn open_status_publisher(
    options: &NodeOptions,
    transport: &dyn Transport,
) -> Option<Box<dyn StatusPublisher>> {
    let topic = options.status.as_ref()?;
    match transport.status_publisher(topic) {
        Ok(p) => Some(p),
        Err(e) => {
            tracing::warn!("no status reports: {e}");
            None
        }
    }
}

/// Waits until the output has `options.wait_for_subscribers` subscribers. False when `stop`
/// turned true first.
fn wait_for_output_subscribers(
    options: &NodeOptions,
    publisher: &dyn FramePublisher,
    stop: &AtomicBool,
) -> bool {
    if options.wait_for_subscribers == 0 {
        return true;
    }
    tracing::info!(
        "{}: waiting for {} subscriber(s) on {}",
        options.name,
        options.wait_for_subscribers,
        options.output
    );
    while publisher.subscriber_count() < options.wait_for_subscribers {
        if stop.load(Ordering::Relaxed) {
            return false;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    true
}

/// A frame waiting to be predicted on, with its arrival time.
pub(super) struct Pending {
    pub(super) frame: ParticleFrame,
    pub(super) arrived: Instant,
}

/// The node's state between loop iterations: per-scene hidden states, pending frames,
/// rollouts under way, counters and the timers of the periodic reports.
pub(super) struct NodeLoop<'a, B: NetOps> {
    pub(super) options: &'a NodeOptions,
    pub(super) surrogate: &'a Surrogate<B>,
    publisher: Box<dyn FramePublisher>,
    status_pub: Option<Box<dyn StatusPublisher>>,
    /// The model's particle count, where it has a fixed one.
    pub(super) model_n: Option<usize>,
    /// Frames a scene needs before closed loop starts (T, at least 1).
    pub(super) window: usize,
    pub(super) tally: Tally,
    pub(super) scenes: Scenes<B>,
    pub(super) pending: BTreeMap<String, VecDeque<Pending>>,
    pub(super) rollouts: Rollouts<B>,
    pub(super) batches: BatchStats,
    /// Where the loop's wall time went.
    pub(super) times: StageTimes,
    /// The shard group (`--shard`), and the counts of frames of other nodes' scenes and of
    /// scenes this node took over.
    pub(super) shard: Option<Shard>,
    pub(super) others: u64,
    pub(super) adopted: u64,
    pub(super) next_status: Instant,
    next_stats: Option<Instant>,
    /// Arrival -> publication latencies, us: the last [`LATENCY_WINDOW`] to 2x that many.
    latencies_us: Vec<f64>,
    pub(super) view: Option<PredictionView>,
    /// Scene states dropped: (at `max_scenes`, least recently active; idle past
    /// `idle_timeout`).
    pub(super) evicted: (u64, u64),
}

/// Latencies kept for the percentiles logged at exit (bounded memory over hours).
const LATENCY_WINDOW: usize = 100_000;

impl<'a, B: NetOps> NodeLoop<'a, B> {
    /// An empty loop state for the node.
    fn new(
        options: &'a NodeOptions,
        surrogate: &'a Surrogate<B>,
        publisher: Box<dyn FramePublisher>,
        status_pub: Option<Box<dyn StatusPublisher>>,
    ) -> Self {
        let meta = surrogate.meta();
        NodeLoop {
            options,
            surrogate,
            publisher,
            status_pub,
            model_n: meta.fixed_particles(),
            window: meta.window().max(1),
            tally: Tally {
                report: NodeReport {
                    node: options.name.clone(),
                    ..NodeReport::default()
                },
                logged: HashSet::new(),
            },
            scenes: Scenes::new(),
            pending: BTreeMap::new(),
            rollouts: Rollouts::new(),
            batches: BatchStats::default(),
            times: StageTimes::new(),
            shard: None,
            others: 0,
            adopted: 0,
            next_status: Instant::now(),
            next_stats: options.stats_interval.map(|d| Instant::now() + d),
            latencies_us: Vec::new(),
            evicted: (0, 0),
            view: options
                .foxglove
                .as_ref()
                .map(|v| PredictionView::new(v, &options.input, &options.output)),
        }
    }

    /// True once `max_published` frames were published.
    fn done(&self) -> bool {
        self.options
            .max_published
            .is_some_and(|m| self.tally.report.published >= m)
    }

    /// Once per second: publishes the status and drops idle scenes. Every
    /// `stats_interval`: logs the counters.
    fn periodic(&mut self) {
        if Instant::now() >= self.next_status {
            self.next_status += Duration::from_secs(1);
            self.stamp_report();
            if let Some(p) = self.status_pub.as_mut() {
                if let Err(e) = p.publish(&self.tally.report) {
                    tracing::warn!("status: {e}");
                }
            }
            let idle = self.scenes.evict_idle(self.options.idle_timeout);
            self.note_idle(idle as u64);
        }
        if let (Some(due), Some(every)) = (self.next_stats, self.options.stats_interval) {
            if Instant::now() >= due {
                self.next_stats = Some(due + every);
                tracing::info!("{}", summary(&self.tally.report));
            }
        }
    }

    /// Counts and logs `idle` scene states dropped as idle past `--idle-timeout`.
    pub(super) fn note_idle(&mut self, idle: u64) {
        if idle > 0 {
            self.evicted.1 += idle;
            tracing::info!(
                "{}: {idle} scene state(s) idle over --idle-timeout dropped ({} so far)",
                self.options.name,
                self.evicted.1
            );
        }
    }

    /// Sets the report's scene count, batch sizes and stamp to now.
    fn stamp_report(&mut self) {
        self.tally.report.active_scenes = self.scenes.len() as u32;
        self.batches.fill(&mut self.tally.report);
        self.tally.report.stamp = wall_time();
    }

    /// Publishes the rollout frames due now (each counts as activity of its scene).
    pub(super) fn publish_due_rollouts(&mut self) {
        for frame in self.rollouts.due(Instant::now()) {
            let idle = self.scenes.touch(&frame.scene, self.options.idle_timeout);
            self.note_idle(u64::from(idle));
            self.emit(&frame);
        }
    }

    /// Publishes a predicted frame (counted) and hands it to the live view; `arrived`, the
    /// input frame's arrival, is timed.
    pub(super) fn emit_timed(&mut self, frame: &ParticleFrame, arrived: Instant) {
        self.emit(frame);
        if self.latencies_us.len() >= 2 * LATENCY_WINDOW {
            self.latencies_us.drain(..LATENCY_WINDOW);
        }
        self.latencies_us
            .push(arrived.elapsed().as_secs_f64() * 1e6);
    }

    /// Publishes a predicted frame (counted) and hands it to the live view.
    pub(super) fn emit(&mut self, frame: &ParticleFrame) {
        let start = Instant::now();
        let sent = self.publisher.publish(frame);
        self.times.publish += start.elapsed();
        match sent {
            Ok(()) => self.tally.report.published += 1,
            Err(e) => {
                self.tally.report.dropped += 1;
                self.tally.report.last_error = e.to_string();
                tracing::warn!("{e}");
            }
        }
        if let Some(view) = self.view.as_mut() {
            view.prediction(frame);
        }
    }

    /// Flushes the output, publishes the final status, logs the latency percentiles and
    /// returns the totals.
    fn finish(mut self) -> NodeReport {
        // The loop's wall time ends here: the closing flush and reports are not the loop's.
        let loop_end = Instant::now();
        self.publisher.flush(Duration::from_secs(5));
        if let Some(view) = self.view.as_mut() {
            view.finish();
        }
        self.stamp_report();
        if let Some(p) = self.status_pub.as_mut() {
            let _ = p.publish(&self.tally.report);
        }
        log_latencies(&self.options.name, &mut self.latencies_us);
        let (full, idle) = self.evicted;
        tracing::info!(
            "{}: evicted={} scene states ({full} at --max-scenes, {idle} idle)",
            self.options.name,
            full + idle
        );
        tracing::info!("{}: {}", self.options.name, self.batches.line());
        tracing::info!("{}: {}", self.options.name, self.times.line(loop_end));
        if self.shard.is_some() {
            tracing::info!(
                "{}: shard: taken_over={} scene(s) (state started again from the next \
                 frame); {} frame(s) of other nodes' scenes passed over",
                self.options.name,
                self.adopted,
                self.others
            );
        }
        self.tally.report
    }
}
