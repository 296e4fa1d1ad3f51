//! The node half of `minflow bench node`: a `minflow node` process started over a transport,
//! warmed up, fed frames at 62.5 Hz and then a burst, its predictions timed from publish to
//! arrival. Used by [`super::run`].

use std::collections::HashMap;
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::mpsc::{channel, Receiver};
use std::time::{Duration, Instant};

use anyhow::bail;

use super::NodeBenchArgs;
use crate::cli::bench::common::wall_ns;
use crate::msgs::{ParticleFrame, Time};
use crate::transport::{self, wait_for_subscribers, FramePublisher, Sample, TransportKind};

/// Starts a `minflow node` process serving the model in `dir` over `kind` (with
/// `--foxglove 127.0.0.1:0` when `foxglove`), publishes
/// `--frames` frames at 62.5 Hz and then a burst of `--burst`. Returns the predictions
/// received of the paced run, their publish-to-prediction latencies (us, sorted) and the
/// burst's predictions per second.
pub(super) fn through_node(
    args: &NodeBenchArgs,
    exe: &Path,
    dir: &Path,
    (kind, foxglove): (TransportKind, bool),
    frames: &[ParticleFrame],
) -> anyhow::Result<(usize, Vec<f64>, f64)> {
    let input = format!("/minflow_bench_{}/in", std::process::id());
    let output = format!("/minflow_bench_{}/out", std::process::id());
    let session = transport::open(&args.transport.options(kind))?;
    let (tx, rx) = channel();
    let _sub = session.subscribe(&output, tx)?;
    let mut publisher = session.publisher(&input)?;
    let mut node = Command::new(exe)
        .args(["node", "--model"])
        .arg(dir)
        .args(args.transport.child_args(kind))
        .args(["--in", &input, "--out", &output, "--status", "none"])
        .args(["--queue-depth", "4", "--on-gap", "skip"])
        .args([
            "--device",
            &args.device.device,
            "--gpu-gemm",
            &args.device.gpu_gemm,
        ])
        .args(if foxglove {
            &["--foxglove", "127.0.0.1:0"][..]
        } else {
            &[]
        })
        .args(if args.mirror { &["--mirror"][..] } else { &[] })
        .args(["--constraints", &args.constraints.to_string()])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()?;
    if !wait_for_subscribers(publisher.as_ref(), 1, Duration::from_secs(60)) {
        let _ = node.kill();
        bail!("{kind}: the node did not subscribe within 60 s");
    }
    std::thread::sleep(Duration::from_millis(500));
    let Some(first) = warm_up(publisher.as_mut(), &rx, frames, &mut node)? else {
        let _ = node.kill();
        bail!("{kind}: the node predicted nothing within {WARM_UP_S} s of frames");
    };
    let (mut latency, index) = paced(args.frames, first, publisher.as_mut(), &rx, frames)?;
    let received = latency.len();
    let burst_fps = burst(args.burst, index, publisher.as_mut(), &rx, frames)?;
    let _ = node.kill();
    let _ = node.wait();
    latency.sort_by(f64::total_cmp);
    Ok((received, latency, burst_fps))
}

/// Frame `index` of the stream the benchmark publishes: the bag's frames in a loop, with
/// consecutive indices (so the node's hidden state carries on) and stamps 16 ms apart.
fn frame_at(frames: &[ParticleFrame], index: u32) -> ParticleFrame {
    let mut f = frames[(index as usize) % frames.len()].clone();
    f.frame_index = index;
    f.header.stamp = Time::from_nanos(u64::from(index) * 16_000_000);
    f
}

/// How long [`warm_up`] waits for the node's first predictions.
const WARM_UP_S: u64 = 120;

/// Predictions the node must return before the timed runs start.
const WARM_UP_PREDICTIONS: usize = 5;

/// Publishes frames (indices from 0) at 62.5 Hz until the node has returned
/// [`WARM_UP_PREDICTIONS`] predictions: a node on a GPU compiles its kernels on its first
/// steps (seconds), and frames sent meanwhile are dropped. Returns the next frame index, or
/// None after [`WARM_UP_S`] seconds without them; an error as soon as the node exits.
fn warm_up(
    publisher: &mut dyn FramePublisher,
    rx: &Receiver<Sample>,
    frames: &[ParticleFrame],
    node: &mut std::process::Child,
) -> anyhow::Result<Option<u32>> {
    let deadline = Instant::now() + Duration::from_secs(WARM_UP_S);
    let mut received = 0;
    let mut index = 0u32;
    while Instant::now() < deadline {
        if let Some(status) = node.try_wait()? {
            bail!(
                "the node exited ({status}) before predicting anything; run the same \
                 `minflow node --model ... --device ...` alone to see why"
            );
        }
        publisher.publish(&frame_at(frames, index))?;
        index += 1;
        std::thread::sleep(Duration::from_millis(16));
        received += rx.try_iter().filter(|s| s.decode().is_ok()).count();
        if received >= WARM_UP_PREDICTIONS {
            // Let the node's queue drain, and drop what it still sends.
            std::thread::sleep(Duration::from_millis(200));
            rx.try_iter().for_each(drop);
            return Ok(Some(index));
        }
    }
    Ok(None)
}

/// Publishes `count` frames (consecutive indices from `first`) at 62.5 Hz and collects the
/// predictions for 2 s more. Returns the latency of each prediction received (us, from
/// publication to arrival on the transport's I/O thread) and the next frame index.
fn paced(
    count: u32,
    first: u32,
    publisher: &mut dyn FramePublisher,
    rx: &Receiver<Sample>,
    frames: &[ParticleFrame],
) -> anyhow::Result<(Vec<f64>, u32)> {
    let period = Duration::from_secs_f64(0.016);
    let mut sent = HashMap::new();
    let mut latency = Vec::new();
    let start = Instant::now();
    let mut index = first;
    let drain = |latency: &mut Vec<f64>, sent: &HashMap<u32, u64>| {
        for s in rx.try_iter() {
            if let Ok(f) = s.decode() {
                if let Some(t0) = sent.get(&(f.frame_index - 1)) {
                    let arrived = wall_ns().saturating_sub(s.received.elapsed().as_nanos() as u64);
                    latency.push(arrived.saturating_sub(*t0) as f64 / 1e3);
                }
            }
        }
    };
    for i in 0..count {
        let due = start + period * i;
        while Instant::now() < due {
            drain(&mut latency, &sent);
            std::thread::sleep(Duration::from_micros(200));
        }
        let f = frame_at(frames, index);
        sent.insert(index, wall_ns());
        publisher.publish(&f)?;
        index += 1;
    }
    let settle = Instant::now() + Duration::from_secs(2);
    while Instant::now() < settle && latency.len() < count as usize {
        drain(&mut latency, &sent);
        std::thread::sleep(Duration::from_millis(1));
    }
    Ok((latency, index))
}

/// Publishes `count` frames from index `index` as fast as the transport accepts them;
/// returns the predictions received per second until 1.5 s pass without one.
fn burst(
    count: u32,
    mut index: u32,
    publisher: &mut dyn FramePublisher,
    rx: &Receiver<Sample>,
    frames: &[ParticleFrame],
) -> anyhow::Result<f64> {
    let burst_start = Instant::now();
    for _ in 0..count {
        publisher.publish(&frame_at(frames, index))?;
        index += 1;
    }
    let mut got = 0usize;
    let mut last = burst_start;
    let quiet = Duration::from_millis(1500);
    while rx.recv_timeout(quiet).is_ok() {
        got += 1;
        last = Instant::now();
    }
    Ok(got as f64 / (last - burst_start).as_secs_f64().max(1e-9))
}
