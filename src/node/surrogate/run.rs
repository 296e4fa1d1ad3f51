//! The surrogate node's loop (`minflow node`): declare the output and status publishers,
//! wait for the output's subscribers, subscribe to the input, then repeat { periodic status
//! and counters, gather the waiting samples into per-scene queues, predict one frame (scenes
//! round robin) and publish it, or in closed loop its rollout }. Frames are checked by
//! [`super::admission`] and stepped from the hidden states of [`super::scenes`]; the totals
//! come back as a [`NodeReport`].

use std::collections::{BTreeMap, HashSet, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{channel, Receiver, RecvTimeoutError};
use std::time::{Duration, Instant};

use crate::model::store::{State, Surrogate};
use crate::msgs::ParticleFrame;
use crate::ops::NetOps;
use crate::transport::{FramePublisher, Sample, StatusPublisher, Transport, TransportError};
use crate::viz::PredictionView;

use super::admission::check_frame;
use super::report::{log_latencies, log_start, wall_time, Tally};
use super::scenes::{Admitted, Scenes};
use super::{payload_bytes, predicted_frame, state_rows, summary, NodeOptions, NodeReport};

/// Runs the node until `stop` turns true (or `max_published` is reached). Returns totals.
///
/// Reads as its steps: declare the output (and status) publishers, wait for the output's
/// subscribers, subscribe to the input, then loop { status, gather, predict one frame }.
///
/// # Errors
/// Declaring the subscription or publishers fails ([`TransportError`]).
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
    let (tx, rx) = channel();
    let _subscription = transport.subscribe(&options.input, tx)?;
    log_start(options, surrogate, transport);
    let mut node = NodeLoop::new(options, surrogate, publisher, status_pub);
    while !stop.load(Ordering::Relaxed)
        && options
            .max_published
            .is_none_or(|m| node.tally.report.published < m)
    {
        node.periodic();
        if !node.gather(&rx) {
            break;
        }
        node.predict_next();
    }
    Ok(node.finish())
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

/// The node's state between loop iterations: per-scene hidden states, pending frames,
/// arrival times, counters and the timers of the periodic reports.
struct NodeLoop<'a, B: NetOps> {
    options: &'a NodeOptions,
    surrogate: &'a Surrogate<B>,
    publisher: Box<dyn FramePublisher>,
    status_pub: Option<Box<dyn StatusPublisher>>,
    /// The model's particle count, where it has a fixed one.
    model_n: Option<usize>,
    /// Frames a scene needs before closed loop starts (T, at least 1).
    window: usize,
    tally: Tally,
    scenes: Scenes<B>,
    pending: BTreeMap<String, VecDeque<ParticleFrame>>,
    /// Arrival time of each pending frame, by (scene, frame index).
    arrivals: BTreeMap<(String, u32), Instant>,
    /// The scene predicted last (round robin starts after it).
    cursor: String,
    next_status: Instant,
    next_stats: Option<Instant>,
    /// Arrival -> publication latencies, us: the last [`LATENCY_WINDOW`] to 2x that many.
    latencies_us: Vec<f64>,
    view: Option<PredictionView>,
    /// Scene states dropped: (at `max_scenes`, least recently seen; idle past `idle_timeout`).
    evicted: (u64, u64),
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
            arrivals: BTreeMap::new(),
            cursor: String::new(),
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
            if idle > 0 {
                self.evicted.1 += idle as u64;
                tracing::info!(
                    "{}: {idle} scene state(s) idle over --idle-timeout dropped ({} so far)",
                    self.options.name,
                    self.evicted.1
                );
            }
        }
        if let (Some(due), Some(every)) = (self.next_stats, self.options.stats_interval) {
            if Instant::now() >= due {
                self.next_stats = Some(due + every);
                tracing::info!("{}", summary(&self.tally.report));
            }
        }
    }

    /// Sets the report's scene count and stamp to now.
    fn stamp_report(&mut self) {
        self.tally.report.active_scenes = self.scenes.len() as u32;
        self.tally.report.stamp = wall_time();
    }

    /// Takes every sample waiting in `rx` into the per-scene queues; blocks (until the next
    /// status, at most 100 ms) only when nothing is pending. False when the transport is gone.
    fn gather(&mut self, rx: &Receiver<Sample>) -> bool {
        let idle = self.pending.values().all(VecDeque::is_empty);
        let first = if idle {
            match rx.recv_timeout(
                self.next_status
                    .saturating_duration_since(Instant::now())
                    .min(Duration::from_millis(100)),
            ) {
                Ok(s) => Some(s),
                Err(RecvTimeoutError::Timeout) => None,
                Err(RecvTimeoutError::Disconnected) => return false,
            }
        } else {
            None
        };
        for sample in first.into_iter().chain(rx.try_iter()) {
            self.accept(sample);
        }
        true
    }

    /// Decodes and checks one sample and queues its frame (dropping the scene's oldest
    /// pending frame past `queue_depth`); bad input is counted and noted.
    fn accept(&mut self, sample: Sample) {
        self.tally.report.received += 1;
        let bytes = payload_bytes(&sample.payload);
        if bytes > self.options.max_frame_bytes {
            self.tally.report.rejected += 1;
            let limit = self.options.max_frame_bytes;
            let reason = format!("payload of {bytes} bytes over --max-frame-bytes {limit}");
            self.tally.note("?", reason);
            return;
        }
        let frame = match sample.decode() {
            Ok(f) => f,
            Err(reason) => {
                self.tally.report.malformed += 1;
                self.tally.note("?", format!("malformed payload: {reason}"));
                return;
            }
        };
        if let Err(reason) = check_frame(&frame, self.model_n) {
            self.tally.report.rejected += 1;
            self.tally.note(&frame.scene.clone(), reason.to_string());
            return;
        }
        if let Some(view) = self.view.as_mut() {
            view.truth(&frame);
        }
        // Closed loop: a scene already rolled out waits for its next start (frame 0).
        if self.options.rollout.is_some()
            && frame.frame_index != 0
            && self.scenes.rolled_out(&frame.scene)
        {
            return;
        }
        self.arrivals
            .insert((frame.scene.clone(), frame.frame_index), sample.received);
        let queue = self.pending.entry(frame.scene.clone()).or_default();
        queue.push_back(frame);
        if queue.len() > self.options.queue_depth.max(1) {
            if let Some(old) = queue.pop_front() {
                self.arrivals.remove(&(old.scene.clone(), old.frame_index));
            }
            self.tally.report.dropped += 1;
        }
    }

    /// Predicts one pending frame, scenes round robin, and publishes the prediction (or,
    /// in closed loop once the scene has T frames, its rollout).
    fn predict_next(&mut self) {
        let Some(scene) = next_scene(&self.pending, &self.cursor) else {
            return;
        };
        self.cursor.clone_from(&scene);
        let frame = self
            .pending
            .get_mut(&scene)
            .and_then(VecDeque::pop_front)
            .expect("scene has a pending frame");
        if self.pending.get(&scene).is_some_and(VecDeque::is_empty) {
            self.pending.remove(&scene);
        }
        let arrived = self
            .arrivals
            .remove(&(frame.scene.clone(), frame.frame_index));
        if let Some(evicted) = self.scenes.make_room_for(&scene, self.options.max_scenes) {
            self.evicted.0 += 1;
            // The first, then every 100th: a stream of new scenes must not flood the log.
            if self.evicted.0 == 1 || self.evicted.0 % 100 == 0 {
                tracing::info!(
                    "{}: scene {evicted:?} evicted at --max-scenes {} ({} so far; a scene that \
                     comes back starts again)",
                    self.options.name,
                    self.options.max_scenes,
                    self.evicted.0
                );
            }
        }
        let state = match self
            .scenes
            .admit(&scene, frame.frame_index, self.options, self.surrogate)
        {
            Admitted::Step(state) => state,
            Admitted::Dropped => {
                self.tally.report.dropped += 1;
                return;
            }
            Admitted::Ignored => return,
        };
        // In closed loop the scene's T-th frame starts the rollout: a whole network call
        // (K frames for a bundled model); before it, and fed live frames, one step.
        let closing = self.options.rollout.is_some() && state.frames + 1 >= self.window;
        let (mut bundle, state) = match self.step_frame(&frame, state, closing) {
            Ok(v) => v,
            Err(e) => {
                self.tally.report.rejected += 1;
                self.tally.note(&scene, e.to_string());
                return;
            }
        };
        self.tally.report.predicted += 1;
        let keep = match self.options.rollout {
            None => {
                self.emit(&predicted_frame(&frame, &bundle.swap_remove(0), 1));
                if let Some(t) = arrived {
                    if self.latencies_us.len() >= 2 * LATENCY_WINDOW {
                        self.latencies_us.drain(..LATENCY_WINDOW);
                    }
                    self.latencies_us.push(t.elapsed().as_secs_f64() * 1e6);
                }
                Some(state)
            }
            Some(k) if closing => {
                // Closed loop from here: K frames, fed back.
                self.scenes.mark_rolled_out(&scene);
                self.roll_out(&scene, &frame, bundle, state, k);
                None
            }
            Some(_) => Some(state),
        };
        self.scenes.keep(&scene, keep);
    }

    /// One network call on `frame`: its whole bundle (`whole`, where a closed loop starts)
    /// or the next frame alone.
    fn step_frame(
        &self,
        frame: &ParticleFrame,
        state: State<B>,
        whole: bool,
    ) -> Result<(Vec<Vec<f32>>, State<B>), crate::model::store::StoreError> {
        let rows = state_rows(frame);
        let (material, dt) = (&frame.material, &[frame.dt]);
        if whole {
            return self.surrogate.step_bundle(&rows, material, dt, state);
        }
        let (next, state) = self.surrogate.step(&rows, material, dt, state)?;
        Ok((vec![next], state))
    }

    /// Closed loop: publishes `k` frames after `frame`, those of `bundle` first, then those
    /// of further network calls, each from the last frame the call before predicted
    /// (ceil(k / K) calls for a model that predicts K frames per call); paced at the scene's
    /// `dt` over `rate` when `rate` > 0.
    fn roll_out(
        &mut self,
        scene: &str,
        frame: &ParticleFrame,
        bundle: Vec<Vec<f32>>,
        state: State<B>,
        k: usize,
    ) {
        let mut state = state;
        let mut queue: VecDeque<Vec<f32>> = bundle.into();
        // A frame's dt is any positive f32: pacing that overflows the clock is skipped
        // rather than a panic.
        let period = match self.options.rate > 0.0 {
            true => Duration::try_from_secs_f64(f64::from(frame.dt) / self.options.rate).ok(),
            false => None,
        };
        let start = Instant::now();
        for i in 0..k {
            let Some(rows) = queue.pop_front() else { break };
            let due = period
                .and_then(|p| p.checked_mul(u32::try_from(i).ok()?))
                .and_then(|d| start.checked_add(d));
            if let Some(due) = due {
                if let Some(wait) = due.checked_duration_since(Instant::now()) {
                    std::thread::sleep(wait);
                }
            }
            self.emit(&predicted_frame(frame, &rows, i as u32 + 1));
            if queue.is_empty() && i + 1 < k {
                match self
                    .surrogate
                    .step_bundle(&rows, &frame.material, &[frame.dt], state)
                {
                    Ok((next, s)) => {
                        queue.extend(next);
                        state = s;
                        self.tally.report.predicted += 1;
                    }
                    Err(e) => {
                        self.tally.note(scene, e.to_string());
                        break;
                    }
                }
            }
        }
    }

    /// Publishes a predicted frame (counted) and hands it to the live view.
    fn emit(&mut self, frame: &ParticleFrame) {
        publish(self.publisher.as_mut(), frame, &mut self.tally.report);
        if let Some(view) = self.view.as_mut() {
            view.prediction(frame);
        }
    }

    /// Flushes the output, publishes the final status, logs the latency percentiles and
    /// returns the totals.
    fn finish(mut self) -> NodeReport {
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
        self.tally.report
    }
}

fn publish(publisher: &mut dyn FramePublisher, frame: &ParticleFrame, report: &mut NodeReport) {
    match publisher.publish(frame) {
        Ok(()) => report.published += 1,
        Err(e) => {
            report.dropped += 1;
            report.last_error = e.to_string();
            tracing::warn!("{e}");
        }
    }
}

/// The first scene after `cursor` (wrapping) with pending frames.
fn next_scene(pending: &BTreeMap<String, VecDeque<ParticleFrame>>, cursor: &str) -> Option<String> {
    use std::ops::Bound::{Excluded, Unbounded};
    pending
        .range::<str, _>((Excluded(cursor), Unbounded))
        .chain(pending.range::<str, _>((Unbounded, Excluded(cursor))))
        .chain(pending.get_key_value(cursor))
        .find(|(_, q)| !q.is_empty())
        .map(|(k, _)| k.clone())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_robin_over_scenes() {
        let mut p: BTreeMap<String, VecDeque<ParticleFrame>> = BTreeMap::new();
        for s in ["a", "b", "c"] {
            p.entry(s.into())
                .or_default()
                .push_back(ParticleFrame::default());
        }
        assert_eq!(next_scene(&p, "").as_deref(), Some("a"));
        assert_eq!(next_scene(&p, "a").as_deref(), Some("b"));
        assert_eq!(next_scene(&p, "c").as_deref(), Some("a"));
        p.remove("a");
        p.remove("c");
        assert_eq!(next_scene(&p, "b").as_deref(), Some("b"));
    }
}
