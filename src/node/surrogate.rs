//! The surrogate node (`minflow node`): subscribes to particle frames, keeps one hidden
//! state per `scene`, and for every input frame publishes the predicted next frame
//! (docs/design.md, "Messages": same scene and material, `frame_index` + 1, stamp + `dt`).
//! In closed loop (`rollout`), after the first T frames of a scene it publishes K predicted
//! frames by feeding its own predictions back.
//!
//! Threads: the transport's I/O thread only hands samples over (a channel); this node's
//! own thread decodes, checks, queues per scene and predicts, so a slow model never blocks
//! a publisher. When frames of a scene arrive faster than they are predicted, the oldest
//! pending frame of that scene is dropped and counted (`queue_depth`).
//!
//! State rules: a scene's hidden state is reset when the scene starts (frame_index 0 or an
//! unseen scene id), on a gap or out-of-order frame ([`OnGap::Reset`]; [`OnGap::Skip`]
//! drops out-of-order frames and carries on over gaps), and after `idle_timeout` without
//! frames; states idle that long are dropped, and at most `max_scenes` are kept (least
//! recently seen evicted), so memory stays bounded. A grid model with `--reference
//! first-frame` takes the first frame of a scene as its reference positions and keeps them
//! over a gap reset (the stream goes on), not over a restart.
//!
//! Bad input is never predicted on: a payload larger than `max_frame_bytes` is `rejected`
//! before it is decoded; a payload that does not decode is `malformed`; a frame with a
//! particle count other than the model's N, non-finite values or a material id above 3 is
//! `rejected`. Each is counted, logged once per scene and reason, and reported in
//! [`SurrogateStatus`] (published once per second); other scenes are served as usual.

use std::collections::{BTreeMap, HashSet, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{channel, Receiver, RecvTimeoutError};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use crate::model::store::{State, Surrogate};
use crate::msgs::status::SurrogateStatus;
use crate::msgs::{ParticleFrame, Time};
use crate::ops::NetOps;
use crate::transport::{FramePublisher, Sample, StatusPublisher, Transport, TransportError};
use crate::viz::PredictionView;

/// What to do with a frame that does not follow the previous one of its scene.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum OnGap {
    /// Reset the scene's hidden state and start again from this frame.
    Reset,
    /// Drop frames older than the last one; carry the state over forward gaps.
    Skip,
}

/// How the node runs.
#[derive(Debug, Clone)]
pub struct NodeOptions {
    /// Node name (in logs and status reports).
    pub name: String,
    /// Input topic (ground-truth frames).
    pub input: String,
    /// Output topic (predicted frames).
    pub output: String,
    /// Status topic; None for no status reports.
    pub status: Option<String>,
    /// Gap policy.
    pub on_gap: OnGap,
    /// Reset and drop a scene's state after this long without frames.
    pub idle_timeout: Duration,
    /// Most scene states kept at once.
    pub max_scenes: usize,
    /// Pending frames per scene before the oldest is dropped.
    pub queue_depth: usize,
    /// Payloads larger than this (bytes) are rejected before decoding (`--max-frame-bytes`).
    pub max_frame_bytes: usize,
    /// Closed loop: after the first T frames of a scene, publish K predicted frames.
    pub rollout: Option<usize>,
    /// Closed-loop pacing: predicted frames per simulated second times this factor
    /// (1 = the scene's own pace); 0 = as fast as possible.
    pub rate: f64,
    /// Stop after this many predicted frames were published (tests, benchmarks).
    pub max_published: Option<u64>,
    /// Log the counters as one line this often.
    pub stats_interval: Option<Duration>,
    /// Subscribe to the input only once the output has this many subscribers (so a
    /// recorder started alongside misses nothing).
    pub wait_for_subscribers: usize,
    /// Live view (`--foxglove`): the input on `<input>/points`, predictions on
    /// `<output>/points` coloured by their error against the ground truth.
    pub foxglove: Option<crate::viz::LiveView>,
}

/// Totals of a node run, as in the status message.
pub type NodeReport = SurrogateStatus;

/// Per-scene hidden state and bookkeeping.
struct SceneState<B: burn::tensor::backend::Backend> {
    state: Option<State<B>>,
    last_index: Option<u32>,
    last_seen: Instant,
    /// Closed loop: the rollout of this scene was published.
    rolled_out: bool,
}

/// Why the node rejects a decoded frame (counted and logged; the node keeps serving).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
enum Rejection {
    /// The model takes a fixed particle count (the paper's architecture) and this is another.
    #[error("{got} particles, the model was trained for N = {model}")]
    ParticleCount { got: usize, model: usize },
    /// A material id beyond the four the models know.
    #[error("unknown material id {0} (0 liquid, 1 jelly, 2 snow, 3 rope)")]
    Material(u8),
    /// A NaN or infinity in the state.
    #[error("non-finite position, velocity or dt")]
    NonFinite,
    /// The message's own checks ([`ParticleFrame::validate`]).
    #[error("{0}")]
    Invalid(String),
}

/// Reasons a frame is rejected, checked in order.
fn check_frame(frame: &ParticleFrame, model_n: Option<usize>) -> Result<(), Rejection> {
    if let Some(model) = model_n.filter(|&n| n != frame.len()) {
        return Err(Rejection::ParticleCount {
            got: frame.len(),
            model,
        });
    }
    if let Some(&m) = frame.material.iter().find(|&&m| m > 3) {
        return Err(Rejection::Material(m));
    }
    let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
    if !finite(&frame.position) || !finite(&frame.velocity) || !frame.dt.is_finite() {
        return Err(Rejection::NonFinite);
    }
    frame
        .validate()
        .map_err(|e| Rejection::Invalid(e.to_string()))
}

/// Interleaved position/velocity -> `[N, 4]` rows (x, y, vx, vy), as `Surrogate::step` takes them.
pub fn state_rows(frame: &ParticleFrame) -> Vec<f32> {
    let mut rows = Vec::with_capacity(frame.len() * 4);
    for i in 0..frame.len() {
        rows.extend_from_slice(&[
            frame.position[2 * i],
            frame.position[2 * i + 1],
            frame.velocity[2 * i],
            frame.velocity[2 * i + 1],
        ]);
    }
    rows
}

/// The frame `steps` frames after `input`, carrying `rows` (`[N, 4]`).
fn predicted_frame(input: &ParticleFrame, rows: &[f32], steps: u32) -> ParticleFrame {
    let n = rows.len() / 4;
    let mut position = Vec::with_capacity(2 * n);
    let mut velocity = Vec::with_capacity(2 * n);
    for r in rows.chunks_exact(4) {
        position.extend_from_slice(&r[..2]);
        velocity.extend_from_slice(&r[2..]);
    }
    let stamp_ns = input.header.stamp.as_nanos()
        + (f64::from(input.dt) * 1e9).round() as i64 * i64::from(steps);
    let mut header = input.header.clone();
    header.stamp = Time::from_nanos(stamp_ns.max(0) as u64);
    ParticleFrame {
        header,
        scene: input.scene.clone(),
        frame_index: input.frame_index + steps,
        dt: input.dt,
        position,
        velocity,
        material: input.material.clone(),
    }
}

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

/// Logs the model and topics the node serves, once at start.
fn log_start<B: NetOps>(
    options: &NodeOptions,
    surrogate: &Surrogate<B>,
    transport: &dyn Transport,
) {
    let meta = surrogate.meta();
    tracing::info!(
        "{}: {} architecture, {} core, T = {}, {} -> {} over {}{}",
        options.name,
        meta.arch_name(),
        meta.core_name(),
        meta.window().max(1),
        options.input,
        options.output,
        transport.kind(),
        options
            .rollout
            .map_or(String::new(), |k| format!(", closed loop {k} frames"))
    );
}

/// The run's counters, and which (scene, reason kind) pairs were already logged.
struct Tally {
    report: NodeReport,
    logged: HashSet<(String, String)>,
}

impl Tally {
    /// Records `reason` as the last error; logs it once per scene and reason kind (the
    /// reason's text up to its first digit).
    fn note(&mut self, scene: &str, reason: String) {
        let kind: String = reason
            .split(|c: char| c.is_ascii_digit())
            .next()
            .unwrap_or("")
            .to_owned();
        if self.logged.insert((scene.to_owned(), kind)) {
            tracing::warn!(
                "{}: scene {scene:?}: {reason} (logged once per scene and reason)",
                self.report.node
            );
        }
        self.report.last_error = format!("{scene}: {reason}");
    }
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
    scenes: BTreeMap<String, SceneState<B>>,
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
            scenes: BTreeMap::new(),
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
            let idle = evict_idle(&mut self.scenes, self.options.idle_timeout);
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
            && self.scenes.get(&frame.scene).is_some_and(|s| s.rolled_out)
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
        self.make_room_for(&scene);
        let Some(state) = self.admit(&scene, &frame) else {
            return;
        };
        let rows = state_rows(&frame);
        let (next, state) = match self
            .surrogate
            .step(&rows, &frame.material, &[frame.dt], state)
        {
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
                self.emit(&predicted_frame(&frame, &next, 1));
                if let Some(t) = arrived {
                    if self.latencies_us.len() >= 2 * LATENCY_WINDOW {
                        self.latencies_us.drain(..LATENCY_WINDOW);
                    }
                    self.latencies_us.push(t.elapsed().as_secs_f64() * 1e6);
                }
                Some(state)
            }
            Some(k) if state.frames >= self.window => {
                // Closed loop from here: K frames, fed back.
                if let Some(entry) = self.scenes.get_mut(&scene) {
                    entry.rolled_out = true;
                }
                self.roll_out(&scene, &frame, next, state, k);
                None
            }
            Some(_) => Some(state),
        };
        if let Some(entry) = self.scenes.get_mut(&scene) {
            entry.state = keep;
        }
    }

    /// Before a new scene is admitted at `max_scenes`, evicts the least recently seen one.
    fn make_room_for(&mut self, scene: &str) {
        if self.scenes.len() >= self.options.max_scenes.max(1) && !self.scenes.contains_key(scene) {
            if let Some(oldest) = self
                .scenes
                .iter()
                .min_by_key(|(_, s)| s.last_seen)
                .map(|(k, _)| k.clone())
            {
                self.scenes.remove(&oldest);
                self.evicted.0 += 1;
                // The first, then every 100th: a stream of new scenes must not flood the log.
                if self.evicted.0 == 1 || self.evicted.0 % 100 == 0 {
                    tracing::info!(
                        "{}: scene {oldest:?} evicted at --max-scenes {} ({} so far; a scene \
                         that comes back starts again)",
                        self.options.name,
                        self.options.max_scenes,
                        self.evicted.0
                    );
                }
            }
        }
    }

    /// Applies the state rules (module doc) to `frame` of `scene`: the hidden state to
    /// step from, or None when the frame is not predicted on (an older frame under
    /// [`OnGap::Skip`], counted as dropped; a scene already rolled out).
    fn admit(&mut self, scene: &str, frame: &ParticleFrame) -> Option<State<B>> {
        let options = self.options;
        let surrogate = self.surrogate;
        let entry = self
            .scenes
            .entry(scene.to_owned())
            .or_insert_with(|| SceneState {
                state: None,
                last_index: None,
                last_seen: Instant::now(),
                rolled_out: false,
            });
        let follows = entry
            .last_index
            .is_some_and(|last| frame.frame_index == last + 1);
        let older = entry
            .last_index
            .is_some_and(|last| frame.frame_index <= last);
        let idle_too_long = entry.last_seen.elapsed() > options.idle_timeout;
        entry.last_seen = Instant::now();
        let restart = frame.frame_index == 0 || entry.last_index.is_none() || idle_too_long;
        if options.rollout.is_some() && entry.rolled_out && !restart {
            return None;
        }
        if !restart && !follows {
            match options.on_gap {
                OnGap::Reset => {
                    tracing::debug!(
                        "{scene}: gap {:?} -> {}: state reset",
                        entry.last_index,
                        frame.frame_index
                    );
                    // The stream goes on: its reference positions are kept.
                    entry.state = entry.state.take().map(|s| surrogate.restart(s));
                    entry.rolled_out = false;
                }
                OnGap::Skip if older => {
                    self.tally.report.dropped += 1;
                    return None;
                }
                OnGap::Skip => {}
            }
        }
        if restart {
            entry.state = None;
            entry.rolled_out = false;
        }
        entry.last_index = Some(frame.frame_index);
        if options.rollout.is_some() && entry.rolled_out {
            return None;
        }
        Some(entry.state.take().unwrap_or_else(|| surrogate.init_state()))
    }

    /// Closed loop: publishes `k` frames after `frame`, the first `next`, each further one
    /// predicted from the previous; paced at the scene's `dt` over `rate` when `rate` > 0.
    fn roll_out(
        &mut self,
        scene: &str,
        frame: &ParticleFrame,
        next: Vec<f32>,
        state: State<B>,
        k: usize,
    ) {
        let mut state = state;
        let mut rows = next;
        // A frame's dt is any positive f32: pacing that overflows the clock is skipped
        // rather than a panic.
        let period = match self.options.rate > 0.0 {
            true => Duration::try_from_secs_f64(f64::from(frame.dt) / self.options.rate).ok(),
            false => None,
        };
        let start = Instant::now();
        for i in 0..k {
            let due = period
                .and_then(|p| p.checked_mul(u32::try_from(i).ok()?))
                .and_then(|d| start.checked_add(d));
            if let Some(due) = due {
                if let Some(wait) = due.checked_duration_since(Instant::now()) {
                    std::thread::sleep(wait);
                }
            }
            self.emit(&predicted_frame(frame, &rows, i as u32 + 1));
            if i + 1 < k {
                match self
                    .surrogate
                    .step(&rows, &frame.material, &[frame.dt], state)
                {
                    Ok((r, s)) => {
                        rows = r;
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

/// Logs the arrival -> publication latency percentiles (nothing when no frame was timed).
fn log_latencies(name: &str, latencies_us: &mut [f64]) {
    if latencies_us.is_empty() {
        return;
    }
    latencies_us.sort_by(f64::total_cmp);
    let pct = |p: f64| latencies_us[((latencies_us.len() - 1) as f64 * p).round() as usize];
    tracing::info!(
        "{}: arrival -> publication latency over {} frames: p50 {:.0} us, p99 {:.0} us, max {:.0} us",
        name,
        latencies_us.len(),
        pct(0.5),
        pct(0.99),
        pct(1.0)
    );
}

/// The counters as one line.
pub fn summary(r: &NodeReport) -> String {
    format!(
        "{}: received={} predicted={} published={} dropped={} malformed={} rejected={} scenes={}{}",
        r.node,
        r.received,
        r.predicted,
        r.published,
        r.dropped,
        r.malformed,
        r.rejected,
        r.active_scenes,
        if r.last_error.is_empty() {
            String::new()
        } else {
            format!("; last error: {}", r.last_error)
        }
    )
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

/// Drops the scene states not seen for longer than `idle`; returns how many.
fn evict_idle<B: burn::tensor::backend::Backend>(
    scenes: &mut BTreeMap<String, SceneState<B>>,
    idle: Duration,
) -> usize {
    let before = scenes.len();
    scenes.retain(|_, s| s.last_seen.elapsed() <= idle);
    before - scenes.len()
}

/// The size of a payload in bytes, as it travelled (CDR) or as its arrays take in memory.
fn payload_bytes(payload: &crate::transport::Payload) -> usize {
    use crate::transport::Payload;
    match payload {
        Payload::Cdr(bytes) => bytes.len(),
        Payload::Frame(f) => {
            4 * (f.position.len() + f.velocity.len()) + f.material.len() + f.scene.len()
        }
        Payload::Malformed(_) => 0,
    }
}

fn wall_time() -> Time {
    Time::from_nanos(
        SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64),
    )
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

    #[test]
    fn bad_frames_are_named() {
        let mut f = ParticleFrame {
            position: vec![0.5; 4],
            velocity: vec![0.0; 4],
            material: vec![0, 1],
            dt: 0.016,
            ..ParticleFrame::default()
        };
        assert_eq!(check_frame(&f, Some(2)), Ok(()));
        let wrong_n = check_frame(&f, Some(3)).unwrap_err();
        assert_eq!(wrong_n, Rejection::ParticleCount { got: 2, model: 3 });
        assert!(wrong_n.to_string().contains("N = 3"));
        f.material[1] = 9;
        assert_eq!(check_frame(&f, None), Err(Rejection::Material(9)));
        f.material[1] = 0;
        f.velocity[3] = f32::NAN;
        assert_eq!(check_frame(&f, None), Err(Rejection::NonFinite));
    }
}
