//! `minflow bench node --streams N --rate HZ`: one node (or `--nodes` sharded ones) serving
//! many live streams, per `--max-batch` value (one row each, same model, one run). Processes
//! on loopback over zenoh: a publisher process (this binary, `--publish-to`) sends N scenes
//! interleaved, each at HZ frames per second (the bag's frames looped, consecutive frame
//! indices, frames spread evenly over each period, each stamped with its wall-clock
//! publication time), `minflow node` predicts, and this process subscribes and counts.
//! The first `--warm-up` seconds are not counted (the node's first calls of each batch
//! shape are slow). Printed per row: frames sent and predictions delivered, frames dropped
//! (sent, never predicted: the node's per-scene queues overflowed), the publish ->
//! prediction latency p50/p99 (both hops and the node; the stamp carries the publication
//! time), predictions per second, and the node's mean and largest scenes per call (its
//! closing counters); then a second table of where the node's wall time went, by stage (its
//! closing `time:` line). Used by [`super::run`].

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::channel;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};

use super::NodeBenchArgs;
use crate::cli::bench::common::{percentile as pct, wall_ns};
use crate::msgs::{ParticleFrame, Time};
use crate::node::surrogate::LOOP_STAGES;
use crate::transport::{self, wait_for_subscribers, TransportKind};

/// One row: a node with one `--max-batch`.
struct Row {
    max_batch: u32,
    sent: u64,
    delivered: u64,
    latency_ms: Vec<f64>,
    per_s: f64,
    batch_mean: f64,
    batch_max: u64,
    /// The node's seconds per stage, in [`stages`]' order (NaN: not in its log).
    stages: Vec<f64>,
}

/// The fields of the node's closing `time:` line: its wall time, the loop's stages
/// ([`LOOP_STAGES`]), the decoder and lander threads' busy times.
fn stages() -> Vec<&'static str> {
    let mut names = vec!["wall"];
    names.extend(LOOP_STAGES);
    names.extend(["decode", "land"]);
    names
}

/// Runs the streams benchmark: one row per `--max-batch` value, the table on stdout.
///
/// # Errors
/// A process that cannot start, a node that never subscribes, a transport error.
pub(super) fn run(args: &NodeBenchArgs, exe: &Path, model: &Path) -> anyhow::Result<()> {
    let mut rows = Vec::new();
    for &max_batch in &args.max_batch {
        eprintln!(
            "bench node: {} streams at {} Hz, --max-batch {max_batch} ...",
            args.streams.unwrap_or(0),
            args.rate
        );
        rows.push(one_row(args, exe, model, max_batch)?);
    }
    print_rows(args, model, &rows);
    Ok(())
}

/// Frame `index` of stream `k`: the bag's frames looped from offset `k`.
fn stream_frame(frames: &[ParticleFrame], k: usize, index: u32) -> ParticleFrame {
    let mut f = frames[(k + index as usize) % frames.len()].clone();
    f.scene = format!("stream/{k:04}");
    f.frame_index = index;
    f
}

/// The publisher process (`--publish-to TOPIC`): waits for the node, then sends `--streams`
/// scenes at `--rate` each for `--warm-up` + `--seconds`, stamped with wall-clock time.
///
/// # Errors
/// The transport, or no subscriber within 60 s.
pub(super) fn publish(args: &NodeBenchArgs, topic: &str) -> anyhow::Result<()> {
    let frames = super::bag_frames(&args.bag)?;
    let kind = TransportKind::Zenoh;
    let session = transport::open(&args.transport.options(kind))?;
    let mut publisher = session.publisher(topic)?;
    let nodes = args.nodes as usize;
    if !wait_for_subscribers(publisher.as_ref(), nodes, Duration::from_secs(60)) {
        bail!("fewer than {nodes} nodes subscribed to {topic} within 60 s");
    }
    let streams = args.streams.unwrap_or(1) as usize;
    let ticks = ((args.warm_up + args.seconds) * args.rate).ceil() as u32;
    let gap = Duration::from_secs_f64(1.0 / (args.rate * streams as f64));
    let start = Instant::now();
    let mut sent = 0u32;
    for i in 0..ticks {
        for k in 0..streams {
            let due = start + gap * sent;
            std::thread::sleep(due.saturating_duration_since(Instant::now()));
            let mut f = stream_frame(&frames, k, i);
            f.header.stamp = Time::from_nanos(wall_ns());
            publisher.publish(&f)?;
            sent += 1;
        }
    }
    publisher.flush(Duration::from_secs(5));
    Ok(())
}

/// Starts the nodes and the publisher, counts the predictions of the timed frames, stops
/// the nodes and reads their closing counters.
fn one_row(args: &NodeBenchArgs, exe: &Path, model: &Path, max_batch: u32) -> anyhow::Result<Row> {
    let tag = format!("{}_{max_batch}", std::process::id());
    let (input, output) = (
        format!("/minflow_streams_{tag}/in"),
        format!("/minflow_streams_{tag}/out"),
    );
    let kind = TransportKind::Zenoh;
    let session = transport::open(&args.transport.options(kind))?;
    let (tx, rx) = channel();
    let _sub = session.subscribe(&output, tx)?;
    let (mut nodes, logs) = spawn_nodes(args, exe, model, (&input, &output), (max_batch, &tag))?;
    let mut publisher = Command::new(exe)
        .args(["bench", "node", "--publish-to", &input])
        .args(args.transport.child_args(kind))
        .args(["--streams", &args.streams.unwrap_or(1).to_string()])
        .args(["--nodes", &args.nodes.to_string()])
        .args([
            "--rate",
            &args.rate.to_string(),
            "--seconds",
            &args.seconds.to_string(),
        ])
        .args(["--warm-up", &args.warm_up.to_string(), "--bag"])
        .arg(&args.bag)
        .stdout(Stdio::null())
        .spawn()
        .context("starting the publisher process")?;
    let warm_ticks = (args.warm_up * args.rate).ceil() as u32;
    let (mut latency_ms, mut first, mut last) = (Vec::new(), None, Instant::now());
    let mut published = false;
    // Until the publisher is done and 2 s pass without a prediction.
    loop {
        match rx.recv_timeout(Duration::from_secs(2)) {
            Ok(s) => {
                let Ok(f) = s.decode() else { continue };
                if f.frame_index <= warm_ticks {
                    continue;
                }
                let arrived = wall_ns().saturating_sub(s.received.elapsed().as_nanos() as u64);
                let sent_ns = f.header.stamp.as_nanos() - (f64::from(f.dt) * 1e9).round() as i64;
                latency_ms.push(arrived.saturating_sub(sent_ns.max(0) as u64) as f64 / 1e6);
                first.get_or_insert(s.received);
                last = s.received;
            }
            Err(_) if published => break,
            Err(_) => {}
        }
        if !published {
            if let Some(status) = publisher.try_wait()? {
                anyhow::ensure!(status.success(), "the publisher process failed ({status})");
                published = true;
            }
        }
    }
    for node in &mut nodes {
        stop_node(node)?;
    }
    let logs: Vec<String> = logs
        .into_iter()
        .map(|l| l.join().unwrap_or_default())
        .collect();
    echo_warm_up(&logs);
    let timed_ticks = ((args.warm_up + args.seconds) * args.rate).ceil() as u32 - warm_ticks;
    latency_ms.sort_by(f64::total_cmp);
    let span = first.map_or(0.0, |f| (last - f).as_secs_f64());
    Ok(Row {
        max_batch,
        sent: u64::from(timed_ticks) * u64::from(args.streams.unwrap_or(1)),
        delivered: latency_ms.len() as u64,
        per_s: latency_ms.len() as f64 / span.max(1e-9),
        latency_ms,
        batch_mean: mean_over(&logs, "batch_mean"),
        batch_max: (logs.iter())
            .filter_map(|l| log_value(l, "batch_max"))
            .fold(0.0, f64::max) as u64,
        stages: (stages().iter())
            .map(|n| mean_over(&logs, &format!("{n}_s")))
            .collect(),
    })
}

/// The `--nodes` nodes of one row and the threads reading their logs (sharded when more
/// than one, the group named after `tag`).
#[allow(clippy::type_complexity)]
fn spawn_nodes(
    args: &NodeBenchArgs,
    exe: &Path,
    model: &Path,
    topics: (&str, &str),
    (max_batch, tag): (u32, &str),
) -> anyhow::Result<(Vec<Child>, Vec<std::thread::JoinHandle<String>>)> {
    let (mut nodes, mut logs) = (Vec::new(), Vec::new());
    for i in 0..args.nodes {
        let shard = (args.nodes > 1).then(|| (format!("bench_{tag}"), i));
        let mut node = spawn_node(args, exe, model, topics, max_batch, shard)?;
        // The node's log, read as it comes (a full pipe would stall the node).
        let err = node.stderr.take().context("the node's stderr")?;
        logs.push(std::thread::spawn(move || {
            let mut log = String::new();
            let _ = std::io::Read::read_to_string(&mut std::io::BufReader::new(err), &mut log);
            log
        }));
        nodes.push(node);
    }
    Ok((nodes, logs))
}

/// Echoes the nodes' log lines of their batch warm-up (`node --warm-up-batches`: what they
/// did before serving, and for how long) on stderr.
fn echo_warm_up(logs: &[String]) {
    for line in logs.iter().flat_map(|l| l.lines()) {
        if line.contains("warmed up") || line.contains("warming up") {
            eprintln!("bench node: the node: {line}");
        }
    }
}

/// The mean over the nodes' `logs` of `name=` (NaN where none has it).
fn mean_over(logs: &[String], name: &str) -> f64 {
    let v: Vec<f64> = logs.iter().filter_map(|l| log_value(l, name)).collect();
    v.iter().sum::<f64>() / v.len() as f64
}

/// A node of one row (stderr kept for its closing counters); with `shard` (group, index)
/// a member of that shard group, named `bench<index>`.
fn spawn_node(
    args: &NodeBenchArgs,
    exe: &Path,
    model: &Path,
    (input, output): (&str, &str),
    max_batch: u32,
    shard: Option<(String, u32)>,
) -> anyhow::Result<Child> {
    let shard_args = match shard {
        Some((group, i)) => vec![
            "--shard".to_string(),
            group,
            "--name".into(),
            format!("bench{i}"),
        ],
        None => Vec::new(),
    };
    Command::new(exe)
        .args(["node", "--model"])
        .arg(model)
        .args(args.transport.child_args(TransportKind::Zenoh))
        .args(["--in", input, "--out", output, "--status", "none"])
        .args(["--max-batch", &max_batch.to_string()])
        .args(["--max-batch-delay", &args.max_batch_delay.to_string()])
        .args(["--queue-depth", &args.queue_depth.to_string()])
        .args([
            "--device",
            &args.device.device,
            "--gpu-gemm",
            &args.device.gpu_gemm,
        ])
        .args(if args.mirror { &["--mirror"][..] } else { &[] })
        .args(["--constraints", &args.constraints.to_string()])
        .args(args.pipeline.map(|p| format!("--pipeline={p}")))
        .args(
            args.warm_up_batches
                .map(|w| format!("--warm-up-batches={w}")),
        )
        .args(shard_args)
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .context("starting the node")
}

/// Stops the node with SIGINT (killed after 30 s).
fn stop_node(node: &mut Child) -> anyhow::Result<()> {
    // SAFETY: kill(2) with the pid of our own child and a valid signal number.
    unsafe {
        libc::kill(node.id() as libc::pid_t, libc::SIGINT);
    }
    let deadline = Instant::now() + Duration::from_secs(30);
    while node.try_wait()?.is_none() {
        if Instant::now() > deadline {
            let _ = node.kill();
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let _ = node.wait();
    Ok(())
}

/// The decimal value of `name=` in the last line of `log` that has it.
fn log_value(log: &str, name: &str) -> Option<f64> {
    let key = format!("{name}=");
    log.lines().rev().find_map(|line| {
        let at = line.find(&key)?;
        line[at + key.len()..]
            .split(|c: char| !(c.is_ascii_digit() || c == '.'))
            .next()?
            .parse()
            .ok()
    })
}

/// A node flag's value as the table's header gives it: the value passed, or the node's own.
fn or_default(flag: Option<bool>) -> String {
    flag.map_or("the node's default".to_string(), |v| v.to_string())
}

/// Prints the table (Markdown) on stdout.
fn print_rows(args: &NodeBenchArgs, model: &Path, rows: &[Row]) {
    let streams = args.streams.unwrap_or(1);
    println!(
        "\n{}, {streams} streams at {} Hz each ({:.0} frames/s offered), {} s timed after \
         {} s warm-up, model {}, on {}, --constraints {}, --max-batch-delay {} ms, --pipeline {}, --warm-up-batches {}:",
        match args.nodes {
            1 => "One node".to_string(),
            n => format!("{n} sharded nodes on one device"),
        },
        args.rate,
        args.rate * f64::from(streams),
        args.seconds,
        args.warm_up,
        model.display(),
        args.device.device,
        args.constraints,
        args.max_batch_delay,
        or_default(args.pipeline),
        or_default(args.warm_up_batches)
    );
    println!("| --max-batch | sent | delivered | dropped | p50 ms | p99 ms | predictions/s | mean batch | max batch |");
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in rows {
        println!(
            "| {} | {} | {} | {} | {:.1} | {:.1} | {:.0} | {:.2} | {} |",
            r.max_batch,
            r.sent,
            r.delivered,
            r.sent.saturating_sub(r.delivered),
            pct(&r.latency_ms, 0.5),
            pct(&r.latency_ms, 0.99),
            r.per_s,
            r.batch_mean,
            r.batch_max
        );
    }
    println!(
        "\nWhere the node's wall time went, seconds (wait: blocked with nothing due; intake: \
         count, queue; stack / call / split: the model's calls; publish: encode, send; landing: \
         blocked on the lander thread; \
         decode: the decoder thread's busy time beside the loop, decode and check; land: the \
         lander thread's, landing, projecting and publishing pipelined calls; the mean over \
         the nodes):"
    );
    let names = stages();
    println!("| --max-batch | {} |", names.join(" | "));
    println!("|---:|{}", "---:|".repeat(names.len()));
    for r in rows {
        let cells: Vec<String> = r.stages.iter().map(|v| format!("{v:.2}")).collect();
        println!("| {} | {} |", r.max_batch, cells.join(" | "));
    }
}
