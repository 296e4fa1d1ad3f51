//! Issue 35, the soak: `replay --loop` at the bag's own pace (62.5 Hz) into `node` and
//! `record` over zenoh, for `MINFLOW_SOAK_SECS` seconds (20 in CI; `tests/soak.sh` runs
//! 600). Every second the resident memory (VmRSS in /proc/PID/status) of each process is
//! sampled; this test process subscribes to the input and the predictions and measures
//! end-to-end latency (a frame's arrival here -> the arrival of its prediction). Printed:
//! memory at the end of the warm-up (the first third of the run, at most 60 s) and its
//! largest value after, the latency p50/p99 of the first and the last third, and the counts.
//! Asserted: 0 frames dropped (the node's counter, and the recording holds every frame the
//! node received), every frame predicted, memory growth after the warm-up <= 10 % (the
//! issue's target is 5 %; the margin is for a loaded CI machine); and, in `tests/soak.sh`
//! only (`MINFLOW_SOAK_SECS` set, the test alone on the machine), the last third's p99
//! within 1.5x the first's plus 5 ms: latency is printed, not held, inside `cargo test`.

use std::collections::HashMap;
use std::path::Path;
use std::sync::mpsc::{channel, Receiver};
use std::time::{Duration, Instant};

use minflow::transport::{self, Sample, Transport};

use crate::transport_support::*;

/// Resident memory of `pid` in KiB (VmRSS), if it still runs.
fn rss_kib(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next()?.parse().ok())
}

/// The p-th quantile of `v` (sorted here).
fn quantile(v: &mut [f64], p: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

/// Memory of one process: (samples KiB by second); returns (the warm-up's peak, the peak
/// after it, growth). Peak against peak: a node's VmRSS swings by ~20 % from second to second
/// as it frees and reuses memory (86-106 MB in one full-suite run), so a single sample at
/// the warm-up's end measured that swing, not a leak (it read +15.8 % where the peaks were
/// 104.7 and 106.5 MB); a leak still raises the later peak. The first second is left out
/// (the process is still loading).
fn growth(samples: &[u64], warm: usize) -> (u64, u64, f64) {
    let end = warm.min(samples.len() - 1);
    let base = samples[1.min(end)..=end].iter().copied().max().unwrap_or(1);
    let max = samples[warm.min(samples.len() - 1)..]
        .iter()
        .copied()
        .max()
        .unwrap_or(base);
    (base, max, (max as f64 - base as f64) / base as f64)
}

/// The soak's three processes: replay (looping), node, recorder (of the input topic).
fn spawn(input: &str, output: &str, out: &Path) -> [Node; 3] {
    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/all-grid-mingru-small");
    let recorder = Node::spawn(
        "record",
        &["record", "--topic", input, "-o", out.to_str().unwrap()],
    );
    let node = Node::spawn(
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
            "--queue-depth",
            "64",
        ],
    );
    let source = source_bag();
    let player = Node::spawn(
        "replay",
        &[
            "replay",
            source.to_str().unwrap(),
            "--topic",
            input,
            "--loop",
            // The node, the recorder and this test.
            "--wait-for-subscribers",
            "3",
        ],
    );
    [player, node, recorder]
}

/// What this test saw during the soak.
#[derive(Default)]
struct Watch {
    /// VmRSS (KiB) of replay, node and recorder, one sample a second.
    memory: [Vec<u64>; 3],
    /// (seconds since the first input frame, input arrival -> prediction arrival in ms).
    latencies: Vec<(f64, f64)>,
    /// Input frames and predictions received here.
    inputs: usize,
    predictions: usize,
}

/// Samples memory every second and times every prediction for `secs` seconds from the
/// first input frame (`rx` delivers both topics).
fn watch(rx: &Receiver<Sample>, input: &str, pids: [u32; 3], secs: u64) -> Watch {
    let mut w = Watch::default();
    let mut arrivals: HashMap<(String, u32), Instant> = HashMap::new();
    let mut first_input: Option<Instant> = None;
    let mut next_sample = Instant::now();
    let deadline = Instant::now() + Duration::from_secs(secs + 60);
    loop {
        let done = first_input.is_some_and(|t| t.elapsed() >= Duration::from_secs(secs));
        if done || Instant::now() > deadline {
            break;
        }
        if Instant::now() >= next_sample && first_input.is_some() {
            next_sample += Duration::from_secs(1);
            for (k, pid) in pids.iter().enumerate() {
                w.memory[k].push(rss_kib(*pid).expect("a process of the soak died"));
            }
        }
        let Ok(sample) = rx.recv_timeout(Duration::from_millis(100)) else {
            continue;
        };
        let frame = sample.decode().unwrap();
        w.count(&sample, input);
        if sample.topic == input {
            if first_input.is_none() {
                first_input = Some(sample.received);
                next_sample = Instant::now();
            }
            arrivals.insert((frame.scene, frame.frame_index), sample.received);
        } else if let Some(sent) = arrivals.get(&(frame.scene, frame.frame_index.wrapping_sub(1))) {
            let at = sent.duration_since(first_input.unwrap()).as_secs_f64();
            let ms = sample.received.duration_since(*sent).as_secs_f64() * 1e3;
            w.latencies.push((at, ms));
        }
    }
    assert!(first_input.is_some(), "no frame arrived");
    w
}

impl Watch {
    /// Counts `sample` as an input frame or a prediction.
    fn count(&mut self, sample: &Sample, input: &str) {
        if sample.topic == input {
            self.inputs += 1;
        } else {
            self.predictions += 1;
        }
    }

    /// After the player stopped: takes what is still on its way until every input frame
    /// received here has its prediction, at most `limit` (the node's queue drains).
    fn settle(&mut self, rx: &Receiver<Sample>, input: &str, limit: Duration) {
        let deadline = Instant::now() + limit;
        while self.predictions < self.inputs && Instant::now() < deadline {
            if let Ok(sample) = rx.recv_timeout(Duration::from_millis(20)) {
                self.count(&sample, input);
            }
        }
    }
}

/// Prints p50/p99 of the first and last third; returns their p99s (ms).
/// `(p95, p99)` of the first third and `(p95, p99)` of the last (ms), printed with the
/// medians.
fn latency_thirds(w: &Watch, secs: u64) -> ([f64; 2], [f64; 2]) {
    let third = secs as f64 / 3.0;
    let part = |lo: f64, hi: f64| -> Vec<f64> {
        w.latencies
            .iter()
            .filter(|(t, _)| *t >= lo && *t < hi)
            .map(|(_, ms)| *ms)
            .collect()
    };
    let (mut first, mut last) = (part(1.0, third), part(secs as f64 - third, f64::MAX));
    let (p50_first, p99_first) = (quantile(&mut first, 0.5), quantile(&mut first, 0.99));
    let (p50_last, p99_last) = (quantile(&mut last, 0.5), quantile(&mut last, 0.99));
    let (p95_first, p95_last) = (quantile(&mut first, 0.95), quantile(&mut last, 0.95));
    println!(
        "latency ms: first third p50 {p50_first:.2} p99 {p99_first:.2} ({} frames); last third \
         p50 {p50_last:.2} p99 {p99_last:.2} ({} frames); p99 ratio {:.3}; p95 {p95_first:.2} -> \
         {p95_last:.2}",
        first.len(),
        last.len(),
        p99_last / p99_first
    );
    ([p95_first, p99_first], [p95_last, p99_last])
}

#[test]
fn soak_replay_loop_into_node_and_record() {
    let secs: u64 = std::env::var("MINFLOW_SOAK_SECS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(20);
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().join("soak");
    let (input, output) = (unique_topic("soak_in"), unique_topic("soak_out"));
    let session = transport::zenoh::ZenohTransport::open(None).unwrap();
    let (tx, rx) = channel();
    let _subs = [
        session.subscribe(&input, tx.clone()).unwrap(),
        session.subscribe(&output, tx).unwrap(),
    ];
    let [player, node, recorder] = spawn(&input, &output, &out);
    let pids = [&player, &node, &recorder].map(|n| n.child.as_ref().unwrap().id());
    let mut w = watch(&rx, &input, pids, secs);
    player.signal("INT");
    let _ = player.wait(Duration::from_secs(30));
    w.settle(&rx, &input, Duration::from_secs(2));
    node.signal("INT");
    let node_log = ok(&node.wait(Duration::from_secs(30)), "node");
    recorder.signal("INT");
    ok(&recorder.wait(Duration::from_secs(30)), "record");

    let received = counter(&node_log, "received").unwrap();
    let recorded = raw_messages(&out, Some(&input)).len() as u64;
    println!(
        "soak {secs} s: {received} frames received by the node ({:.1} Hz), {recorded} recorded, \
         {} predictions timed here",
        received as f64 / secs as f64,
        w.latencies.len()
    );
    let (first, last) = latency_thirds(&w, secs);
    let warm = ((secs / 3).min(60)) as usize;
    let mut growths = Vec::new();
    for (name, samples) in ["replay", "node", "record"].iter().zip(&w.memory) {
        let (base, max, g) = growth(samples, warm);
        println!(
            "{name}: VmRSS peak {base} KiB in the first {warm} s, {max} KiB after ({:+.2} %), {} samples",
            g * 100.0,
            samples.len()
        );
        growths.push((name, g));
        println!("{name}: VmRSS KiB by second {samples:?}");
    }
    assert_eq!(counter(&node_log, "dropped"), Some(0), "{node_log}");
    assert_eq!(
        counter(&node_log, "predicted"),
        Some(received),
        "{node_log}"
    );
    assert_eq!(recorded, received, "the recording holds every frame");
    for (name, g) in growths {
        assert!(g <= 0.10, "{name}: memory grew {:.1} %", g * 100.0);
    }
    // Latency growth is a benchmark's check, not the suite's: within `cargo test` a build or
    // the other tests share the two cores, and one of them moved this test's p95 from 25 to
    // 87 ms once (issue 83). `tests/soak.sh` (MINFLOW_SOAK_SECS set, the test alone) holds
    // the p99; `bench node` reports the node's latency under load (docs/reliability.md).
    if std::env::var("MINFLOW_SOAK_SECS").is_ok() {
        assert!(
            last[1] <= 1.5 * first[1] + 5.0,
            "p99 {:.2} ms at the end vs {:.2} ms at the start",
            last[1],
            first[1]
        );
    }
}
