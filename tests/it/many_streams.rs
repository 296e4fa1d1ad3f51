//! Issue 35, many streams: 256 scenes interleaved into one node over zenoh, with particle
//! counts from 500 to 2,499, in four waves of 64 that join and leave (`--max-scenes 64`, so
//! each wave evicts the one before; `--idle-timeout 3`). Evictions are counted and logged; a
//! scene that returns after eviction mid-stream starts again (no error, every frame
//! predicted); nothing is dropped, rejected or lost. Printed against one scene: the
//! publish -> prediction latency p50/p99 at 125 Hz and the predictions per second of a burst.

use std::collections::HashMap;
use std::path::Path;
use std::sync::mpsc::{channel, Receiver};
use std::time::{Duration, Instant};

use minflow::msgs::{ParticleFrame, Time};
use minflow::transport::{self, FramePublisher, Sample, Transport};

use crate::transport_support::*;

/// The first `n` particles of `base` as frame `index` of `scene` (stamp = index * dt).
fn frame_of(base: &ParticleFrame, scene: &str, n: usize, index: u32) -> ParticleFrame {
    let mut f = base.clone();
    f.scene = scene.to_owned();
    f.frame_index = index;
    f.header.stamp = Time::from_nanos((f64::from(index) * f64::from(f.dt) * 1e9) as u64);
    f.position.truncate(2 * n);
    f.velocity.truncate(2 * n);
    f.material.truncate(n);
    f
}

/// Publishes frames, keeps their publication times and collects the predictions' arrivals.
struct Stream {
    publisher: Box<dyn FramePublisher>,
    rx: Receiver<Sample>,
    sent: HashMap<(String, u32), Instant>,
    /// Latency ms of each prediction, in arrival order.
    latencies: Vec<f64>,
    predicted: HashMap<String, Vec<u32>>,
}

impl Stream {
    fn send(&mut self, frame: &ParticleFrame) {
        self.publisher.publish(frame).unwrap();
        self.sent
            .insert((frame.scene.clone(), frame.frame_index), Instant::now());
        self.drain(Duration::ZERO);
    }

    /// Takes the predictions that arrive within `wait` (or until none is missing).
    fn drain(&mut self, wait: Duration) {
        let deadline = Instant::now() + wait;
        loop {
            let missing = self.latencies.len() < self.sent.len();
            let left = deadline.saturating_duration_since(Instant::now());
            let sample = match (missing, left.is_zero()) {
                (_, true) => self.rx.try_recv().ok(),
                (true, false) => self.rx.recv_timeout(left).ok(),
                (false, false) => None,
            };
            let Some(sample) = sample else { return };
            let f = sample.decode().unwrap();
            let key = (f.scene.clone(), f.frame_index.wrapping_sub(1));
            if let Some(t) = self.sent.get(&key) {
                let ms = sample.received.duration_since(*t).as_secs_f64() * 1e3;
                self.latencies.push(ms);
            }
            self.predicted
                .entry(f.scene)
                .or_default()
                .push(f.frame_index);
        }
    }

    /// Sends `frames` at `hz` (0: as fast as the transport accepts); returns (p50 ms, p99 ms,
    /// predictions per second) of these frames.
    fn run(&mut self, frames: &[ParticleFrame], hz: f64) -> (f64, f64, f64) {
        let (first, start) = (self.latencies.len(), Instant::now());
        for (i, f) in frames.iter().enumerate() {
            if hz > 0.0 {
                let due = start + Duration::from_secs_f64(i as f64 / hz);
                std::thread::sleep(due.saturating_duration_since(Instant::now()));
            }
            self.send(f);
        }
        self.drain(Duration::from_secs(20));
        let per_s = (self.latencies.len() - first) as f64 / start.elapsed().as_secs_f64();
        let mut v = self.latencies[first..].to_vec();
        v.sort_by(f64::total_cmp);
        let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
        (q(0.5), q(0.99), per_s)
    }
}

fn rss_kib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next()?.parse().ok())
        .unwrap()
}

/// The node under test: `--max-scenes 64 --idle-timeout 3`, room for every pending frame.
fn spawn_node(input: &str, output: &str) -> Node {
    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/all-grid-mingru-small");
    Node::spawn(
        "node",
        &[
            "node",
            "--model",
            model.to_str().unwrap(),
            "--in",
            input,
            "--out",
            output,
            "--status",
            "none",
            "--max-scenes",
            "64",
            "--idle-timeout",
            "3",
            "--queue-depth",
            "1024",
        ],
    )
}

/// Scene `k` of the 256: its name and particle count (500 to 2,499, at most `n_max`).
fn many(k: usize, n_max: usize) -> (String, usize) {
    (format!("many/{k:03}"), (500 + (k * 379) % 2000).min(n_max))
}

/// Frames `rounds` of wave `w` (scenes 64w to 64w + 63), interleaved scene by scene.
fn wave(base: &[ParticleFrame], w: usize, rounds: std::ops::Range<u32>) -> Vec<ParticleFrame> {
    let n_max = base[0].material.len();
    let mut v = Vec::new();
    for i in rounds {
        for k in 64 * w..64 * (w + 1) {
            let (scene, n) = many(k, n_max);
            v.push(frame_of(&base[(i as usize + k) % base.len()], &scene, n, i));
        }
    }
    v
}

/// The node's closing counters: every frame predicted, nothing lost, at most 64 scenes
/// kept, at least `min_evicted` evictions logged.
fn check_counters(log: &str, sent: u64, min_evicted: u64) {
    assert_eq!(counter(log, "received"), Some(sent), "{log}");
    assert_eq!(counter(log, "predicted"), Some(sent), "{log}");
    for c in ["dropped", "rejected", "malformed"] {
        assert_eq!(counter(log, c), Some(0), "{c}\n{log}");
    }
    assert!(counter(log, "scenes").unwrap() <= 64, "{log}");
    let evicted = counter(log, "evicted").unwrap();
    assert!(evicted >= min_evicted, "evicted {evicted}\n{log}");
    assert!(log.contains("evicted at --max-scenes 64"), "{log}");
}

#[test]
fn many_scenes_into_one_node_are_bounded_and_evicted_cleanly() {
    let (input, output) = (unique_topic("many_in"), unique_topic("many_out"));
    let node = spawn_node(&input, &output);
    let session = transport::zenoh::ZenohTransport::open(None).unwrap();
    let (tx, rx) = channel();
    let _sub = session.subscribe(&output, tx).unwrap();
    let publisher = session.publisher(&input).unwrap();
    let subscribed =
        transport::wait_for_subscribers(publisher.as_ref(), 1, Duration::from_secs(30));
    assert!(subscribed, "the node never subscribed");
    let mut s = Stream {
        publisher,
        rx,
        sent: HashMap::new(),
        latencies: Vec::new(),
        predicted: HashMap::new(),
    };
    let base: Vec<ParticleFrame> = raw_messages(&source_bag(), Some(minflow::bag::FRAMES_TOPIC))
        .iter()
        .map(|b| minflow::msgs::decode(b).unwrap())
        .collect();
    let n_max = base[0].material.len();
    // Warm-up, then one scene: 200 frames at 125 Hz, then a burst of 200.
    let one: Vec<_> = (0..450u32)
        .map(|i| frame_of(&base[i as usize % base.len()], "one/000", n_max, i))
        .collect();
    s.run(&one[..50], 125.0);
    let (p50_one, p99_one, _) = s.run(&one[50..250], 125.0);
    let (_, _, burst_one) = s.run(&one[250..], 0.0);
    // 64 other scenes (256..320) as fast as the transport accepts: the pending queues and the
    // allocator reach their high water before the first measurement, so the waves below
    // compare the state the node keeps, not how far a loaded machine let frames pile up.
    // Without it the baseline rose with load (155 MB alone, 199 MB beside two busy loops) and
    // a CI run under the full suite read 148 -> 196 MB over the waves.
    s.run(&wave(&base, 4, 0..4), 0.0);
    // 320 scenes in five waves of 64, four frames each: the first at 125 Hz (its latency
    // printed), the others as fast as the transport accepts, as the warm-up above (each
    // run waits for all its predictions, so every wave still joins and evicts the one
    // before it, and memory is read with nothing pending).
    let pid = node.child.as_ref().unwrap().id();
    let (p50_many, p99_many, _) = s.run(&wave(&base, 0, 0..4), 125.0);
    // The baseline after a wave sent as the later ones are (a full suite's CI read 156 -> 199
    // MB from the paced wave to the fourth): three more waves of new scenes must not grow it.
    s.run(&wave(&base, 1, 0..4), 0.0);
    let rss_first_wave = rss_kib(pid);
    for w in [2, 3, 5] {
        s.run(&wave(&base, w, 0..4), 0.0);
    }
    let rss_last_wave = rss_kib(pid);
    // Scene 0 comes back mid-stream (frames 4..8) after it was evicted.
    let (scene0, n0) = many(0, n_max);
    let back: Vec<_> = (4..8u32)
        .map(|i| frame_of(&base[i as usize], &scene0, n0, i))
        .collect();
    s.run(&back, 125.0);
    // Throughput over 256 scenes: one frame each, as fast as the transport accepts.
    let burst: Vec<_> = (0..256)
        .map(|k| {
            let (scene, n) = many(k, n_max);
            frame_of(&base[k % base.len()], &scene, n, 8)
        })
        .collect();
    let (_, _, burst_many) = s.run(&burst, 0.0);
    node.signal("INT");
    let log = ok(&node.wait(Duration::from_secs(30)), "node");
    println!(
        "one scene: p50 {p50_one:.2} ms, p99 {p99_one:.2} ms at 125 Hz, burst {burst_one:.0} \
         predictions/s"
    );
    println!(
        "256 scenes: p50 {p50_many:.2} ms, p99 {p99_many:.2} ms at 125 Hz (first wave), burst \
         {burst_many:.0} predictions/s; node VmRSS {rss_first_wave} KiB after the second wave, \
         {rss_last_wave} KiB after the fifth"
    );
    let sent = s.sent.len() as u64;
    check_counters(&log, sent, 192);
    assert_eq!(s.latencies.len() as u64, sent, "every prediction arrived");
    assert_eq!(s.predicted[&scene0], [1, 2, 3, 4, 5, 6, 7, 8, 9]);
    assert!(
        rss_last_wave <= rss_first_wave + rss_first_wave / 4,
        "memory grew from {rss_first_wave} to {rss_last_wave} KiB over three more waves"
    );
}
