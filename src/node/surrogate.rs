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
//! recently seen evicted), so memory stays bounded.
//!
//! Bad input is never predicted on: a payload that does not decode is `malformed`; a frame
//! with a particle count other than the model's N, non-finite values or a material id
//! above 3 is `rejected`. Each is counted, logged once per scene and reason, and reported in
//! [`SurrogateStatus`] (published once per second); other scenes are served as usual.

use std::collections::{BTreeMap, HashSet, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{channel, RecvTimeoutError};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use crate::model::store::{State, Surrogate};
use crate::msgs::status::SurrogateStatus;
use crate::msgs::{ParticleFrame, Time};
use crate::ops::NetOps;
use crate::transport::{FramePublisher, StatusPublisher, Transport, TransportError};

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

/// Reasons a frame is rejected, checked in order.
fn check_frame(frame: &ParticleFrame, model_n: Option<usize>) -> Result<(), String> {
    if let Some(n) = model_n {
        if frame.len() != n {
            return Err(format!(
                "{} particles, the model was trained for N = {n}",
                frame.len()
            ));
        }
    }
    if let Some(m) = frame.material.iter().find(|&&m| m > 3) {
        return Err(format!(
            "unknown material id {m} (0 liquid, 1 jelly, 2 snow, 3 rope)"
        ));
    }
    let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
    if !finite(&frame.position) || !finite(&frame.velocity) || !frame.dt.is_finite() {
        return Err("non-finite position, velocity or dt".into());
    }
    Ok(())
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
/// # Errors
/// Declaring the subscription or publishers fails ([`TransportError`]).
pub fn run<B: NetOps>(
    options: &NodeOptions,
    surrogate: &Surrogate<B>,
    transport: &dyn Transport,
    stop: &AtomicBool,
) -> Result<NodeReport, TransportError> {
    let mut publisher = transport.publisher(&options.output)?;
    let mut status_pub: Option<Box<dyn StatusPublisher>> = match &options.status {
        Some(topic) => match transport.status_publisher(topic) {
            Ok(p) => Some(p),
            Err(e) => {
                tracing::warn!("no status reports: {e}");
                None
            }
        },
        None => None,
    };
    if options.wait_for_subscribers > 0 {
        tracing::info!(
            "{}: waiting for {} subscriber(s) on {}",
            options.name,
            options.wait_for_subscribers,
            options.output
        );
        while publisher.subscriber_count() < options.wait_for_subscribers {
            if stop.load(Ordering::Relaxed) {
                return Ok(NodeReport {
                    node: options.name.clone(),
                    ..NodeReport::default()
                });
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }
    let (tx, rx) = channel();
    let _subscription = transport.subscribe(&options.input, tx)?;
    let meta = surrogate.meta();
    let model_n = meta.fixed_particles();
    let window = meta.window().max(1);
    tracing::info!(
        "{}: {} architecture, {} core, T = {window}, {} -> {} over {}{}",
        options.name,
        meta.arch_name(),
        meta.core_name(),
        options.input,
        options.output,
        transport.kind(),
        options
            .rollout
            .map_or(String::new(), |k| format!(", closed loop {k} frames"))
    );

    let mut report = NodeReport {
        node: options.name.clone(),
        ..NodeReport::default()
    };
    let mut scenes: BTreeMap<String, SceneState<B>> = BTreeMap::new();
    let mut pending: BTreeMap<String, VecDeque<ParticleFrame>> = BTreeMap::new();
    let mut logged: HashSet<(String, String)> = HashSet::new();
    let mut next_status = Instant::now();
    let mut next_stats = options.stats_interval.map(|d| Instant::now() + d);
    let mut cursor = String::new();
    let mut latencies_us: Vec<f64> = Vec::new();
    let mut arrivals: BTreeMap<(String, u32), Instant> = BTreeMap::new();

    let mut note = |report: &mut NodeReport, scene: &str, reason: String| {
        let kind: String = reason
            .split(|c: char| c.is_ascii_digit())
            .next()
            .unwrap_or("")
            .to_owned();
        if logged.insert((scene.to_owned(), kind)) {
            tracing::warn!(
                "{}: scene {scene:?}: {reason} (logged once per scene and reason)",
                options.name
            );
        }
        report.last_error = format!("{scene}: {reason}");
    };

    while !stop.load(Ordering::Relaxed)
        && options.max_published.is_none_or(|m| report.published < m)
    {
        // Status once per second.
        if Instant::now() >= next_status {
            next_status += Duration::from_secs(1);
            report.active_scenes = scenes.len() as u32;
            report.stamp = wall_time();
            if let Some(p) = status_pub.as_mut() {
                if let Err(e) = p.publish(&report) {
                    tracing::warn!("status: {e}");
                }
            }
            evict_idle(&mut scenes, options.idle_timeout);
        }
        if let (Some(due), Some(every)) = (next_stats, options.stats_interval) {
            if Instant::now() >= due {
                next_stats = Some(due + every);
                tracing::info!("{}", summary(&report));
            }
        }
        // Gather: block only when nothing is pending.
        let idle = pending.values().all(VecDeque::is_empty);
        let first = if idle {
            match rx.recv_timeout(
                next_status
                    .saturating_duration_since(Instant::now())
                    .min(Duration::from_millis(100)),
            ) {
                Ok(s) => Some(s),
                Err(RecvTimeoutError::Timeout) => None,
                Err(RecvTimeoutError::Disconnected) => break,
            }
        } else {
            None
        };
        for sample in first.into_iter().chain(rx.try_iter()) {
            report.received += 1;
            let frame = match sample.decode() {
                Ok(f) => f,
                Err(reason) => {
                    report.malformed += 1;
                    note(&mut report, "?", format!("malformed payload: {reason}"));
                    continue;
                }
            };
            if let Err(reason) = check_frame(&frame, model_n)
                .and_then(|()| frame.validate().map_err(|e| e.to_string()))
            {
                report.rejected += 1;
                note(&mut report, &frame.scene.clone(), reason);
                continue;
            }
            // Closed loop: a scene already rolled out waits for its next start (frame 0).
            if options.rollout.is_some()
                && frame.frame_index != 0
                && scenes.get(&frame.scene).is_some_and(|s| s.rolled_out)
            {
                continue;
            }
            arrivals.insert((frame.scene.clone(), frame.frame_index), sample.received);
            let queue = pending.entry(frame.scene.clone()).or_default();
            queue.push_back(frame);
            if queue.len() > options.queue_depth.max(1) {
                if let Some(old) = queue.pop_front() {
                    arrivals.remove(&(old.scene.clone(), old.frame_index));
                }
                report.dropped += 1;
            }
        }
        // Predict one frame, scenes round robin.
        let Some(scene) = next_scene(&pending, &cursor) else {
            continue;
        };
        cursor.clone_from(&scene);
        let frame = pending
            .get_mut(&scene)
            .and_then(VecDeque::pop_front)
            .expect("scene has a pending frame");
        if pending.get(&scene).is_some_and(VecDeque::is_empty) {
            pending.remove(&scene);
        }
        let arrived = arrivals.remove(&(frame.scene.clone(), frame.frame_index));
        if scenes.len() >= options.max_scenes.max(1) && !scenes.contains_key(&scene) {
            if let Some(oldest) = scenes
                .iter()
                .min_by_key(|(_, s)| s.last_seen)
                .map(|(k, _)| k.clone())
            {
                scenes.remove(&oldest);
            }
        }
        let entry = scenes.entry(scene.clone()).or_insert_with(|| SceneState {
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
            continue;
        }
        if !restart && !follows {
            match options.on_gap {
                OnGap::Reset => {
                    tracing::debug!(
                        "{scene}: gap {:?} -> {}: state reset",
                        entry.last_index,
                        frame.frame_index
                    );
                    entry.state = None;
                    entry.rolled_out = false;
                }
                OnGap::Skip if older => {
                    report.dropped += 1;
                    continue;
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
            continue;
        }
        let state = entry.state.take().unwrap_or_else(|| surrogate.init_state());
        let rows = state_rows(&frame);
        let (next, state) = match surrogate.step(&rows, &frame.material, &[frame.dt], state) {
            Ok(v) => v,
            Err(e) => {
                report.rejected += 1;
                note(&mut report, &scene, e.to_string());
                continue;
            }
        };
        report.predicted += 1;
        match options.rollout {
            None => {
                publish(
                    publisher.as_mut(),
                    &predicted_frame(&frame, &next, 1),
                    &mut report,
                );
                if let Some(t) = arrived {
                    latencies_us.push(t.elapsed().as_secs_f64() * 1e6);
                }
                entry.state = Some(state);
            }
            Some(k) if state.frames >= window => {
                // Closed loop from here: K frames, fed back.
                entry.rolled_out = true;
                let mut state = state;
                let mut rows = next;
                // A frame's dt is any positive f32: pacing that overflows the clock is skipped
                // rather than a panic.
                let period = match options.rate > 0.0 {
                    true => Duration::try_from_secs_f64(f64::from(frame.dt) / options.rate).ok(),
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
                    publish(
                        publisher.as_mut(),
                        &predicted_frame(&frame, &rows, i as u32 + 1),
                        &mut report,
                    );
                    if i + 1 < k {
                        match surrogate.step(&rows, &frame.material, &[frame.dt], state) {
                            Ok((r, s)) => {
                                rows = r;
                                state = s;
                                report.predicted += 1;
                            }
                            Err(e) => {
                                note(&mut report, &scene, e.to_string());
                                break;
                            }
                        }
                    }
                }
                entry.state = None;
            }
            Some(_) => entry.state = Some(state),
        }
    }
    publisher.flush(Duration::from_secs(5));
    report.active_scenes = scenes.len() as u32;
    report.stamp = wall_time();
    if let Some(p) = status_pub.as_mut() {
        let _ = p.publish(&report);
    }
    if !latencies_us.is_empty() {
        latencies_us.sort_by(f64::total_cmp);
        let pct = |p: f64| latencies_us[((latencies_us.len() - 1) as f64 * p).round() as usize];
        tracing::info!(
            "{}: arrival -> publication latency over {} frames: p50 {:.0} us, p99 {:.0} us, max {:.0} us",
            options.name,
            latencies_us.len(),
            pct(0.5),
            pct(0.99),
            pct(1.0)
        );
    }
    Ok(report)
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

fn evict_idle<B: burn::tensor::backend::Backend>(
    scenes: &mut BTreeMap<String, SceneState<B>>,
    idle: Duration,
) {
    scenes.retain(|_, s| s.last_seen.elapsed() <= idle);
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
        assert!(check_frame(&f, Some(2)).is_ok());
        assert!(check_frame(&f, Some(3)).unwrap_err().contains("N = 3"));
        f.material[1] = 9;
        assert!(check_frame(&f, None).unwrap_err().contains("material id 9"));
        f.material[1] = 0;
        f.velocity[3] = f32::NAN;
        assert!(check_frame(&f, None).unwrap_err().contains("non-finite"));
    }
}
