//! `minflow bench transport`: publish-to-receive latency of a 2,500-particle frame between
//! two processes on loopback, per transport (p50, p99, max over `--frames` frames at
//! `--hz`), and the sustained frames per second of a burst published as fast as the
//! transport accepts it (with the frames lost, if any).
//!
//! The benchmark process subscribes and starts a second `minflow` process that publishes
//! (`bench transport --role publisher`). Each frame carries its send time (wall clock, ns)
//! in `header.stamp`; the receiver subtracts it from its arrival time on the transport's
//! I/O thread. Both processes read the same clock, so no synchronisation is needed.

use std::collections::BTreeMap;
use std::process::{Command, Stdio};
use std::sync::mpsc::channel;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use clap::{Args, ValueEnum};

use super::common::{percentile, wall_ns, BenchTransportOptions};
use crate::cli::Outcome;
use crate::msgs::{Header, ParticleFrame, Time};
use crate::transport::{self, wait_for_subscribers, TransportKind};

/// Which side of `bench transport` a process is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Role {
    /// Subscribe, start the publisher process, print the table.
    Bench,
    /// Publish the frames (started by the bench itself).
    Publisher,
}

/// The flags of `minflow bench transport`.
#[derive(Debug, Args)]
pub struct TransportBenchArgs {
    #[command(flatten)]
    transport: BenchTransportOptions,
    /// Frames for the latency run.
    #[arg(long, default_value_t = 1000)]
    frames: u32,
    /// Publishing rate of the latency run, frames per second.
    #[arg(long, default_value_t = 60.0)]
    hz: f64,
    /// Frames of the burst (throughput run).
    #[arg(long, default_value_t = 2000)]
    burst: u32,
    /// Particles per frame.
    #[arg(long, default_value_t = 2500)]
    particles: usize,
    #[arg(long, value_enum, default_value_t = Role::Bench, hide = true)]
    role: Role,
    #[arg(long, hide = true)]
    topic: Option<String>,
}

const LATENCY_SCENE: &str = "bench/latency";
const BURST_SCENE: &str = "bench/burst";

/// A frame of `n` particles with deterministic contents.
fn frame(n: usize, scene: &str, index: u32) -> ParticleFrame {
    ParticleFrame {
        header: Header {
            stamp: Time::default(),
            frame_id: "world".into(),
        },
        scene: scene.into(),
        frame_index: index,
        dt: 0.016,
        position: (0..2 * n).map(|i| (i % 997) as f32 / 997.0).collect(),
        velocity: (0..2 * n).map(|i| (i % 101) as f32 / 101.0 - 0.5).collect(),
        material: (0..n).map(|i| (i % 4) as u8).collect(),
    }
}

/// Runs `minflow bench transport` as its `--role` says.
///
/// # Errors
/// A transport that cannot be opened, a publisher process that fails.
pub fn run(args: TransportBenchArgs) -> anyhow::Result<Outcome> {
    match args.role {
        Role::Publisher => publish(&args),
        Role::Bench => bench(&args),
    }
}

fn publish(args: &TransportBenchArgs) -> anyhow::Result<Outcome> {
    let kind = *args
        .transport
        .transports
        .first()
        .context("--transport is required")?;
    let topic = args.topic.clone().context("--topic is required")?;
    let session = transport::open(&args.transport.options(kind))?;
    let mut publisher = session.publisher(&topic)?;
    if !wait_for_subscribers(publisher.as_ref(), 1, Duration::from_secs(30)) {
        bail!("no subscriber within 30 s");
    }
    // Discovery settles on both sides (DDS matches the reader before the writer knows).
    std::thread::sleep(Duration::from_millis(500));
    let mut f = frame(args.particles, LATENCY_SCENE, 0);
    let period = Duration::from_secs_f64(1.0 / args.hz);
    let start = Instant::now();
    for i in 0..args.frames {
        let due = start + period * i;
        if let Some(wait) = due.checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
        f.frame_index = i;
        f.header.stamp = Time::from_nanos(wall_ns());
        publisher.publish(&f)?;
    }
    f.scene = BURST_SCENE.into();
    for i in 0..args.burst {
        f.frame_index = i;
        f.header.stamp = Time::from_nanos(wall_ns());
        publisher.publish(&f)?;
    }
    publisher.flush(Duration::from_secs(10));
    std::thread::sleep(Duration::from_millis(500));
    Ok(Outcome::Done)
}

struct Row {
    kind: TransportKind,
    received: u32,
    p50: f64,
    p99: f64,
    max: f64,
    burst_received: u32,
    burst_fps: f64,
}

fn bench(args: &TransportBenchArgs) -> anyhow::Result<Outcome> {
    let kinds = args.transport.kinds();
    let exe = std::env::current_exe().context("locating the minflow binary")?;
    let mut rows = Vec::new();
    for kind in kinds {
        eprintln!("bench transport: {kind} ...");
        let topic = format!("/minflow_bench_{}/frames", std::process::id());
        let session = transport::open(&args.transport.options(kind))?;
        let (tx, rx) = channel();
        let subscription = session.subscribe(&topic, tx)?;
        let mut child = spawn_publisher(&exe, args, kind, &topic)?;
        let mut latencies = Vec::with_capacity(args.frames as usize);
        let mut seen: BTreeMap<&str, u32> = BTreeMap::new();
        let (mut burst_first, mut burst_last) = (None, None);
        let expected_time =
            Duration::from_secs_f64(args.frames as f64 / args.hz) + Duration::from_secs(60);
        let deadline = Instant::now() + expected_time;
        while Instant::now() < deadline {
            let Ok(sample) = rx.recv_timeout(Duration::from_millis(200)) else {
                if child.try_wait()?.is_some() {
                    break;
                }
                continue;
            };
            let arrived_wall =
                wall_ns().saturating_sub(sample.received.elapsed().as_nanos() as u64);
            let f = match sample.frame() {
                Ok(f) => f,
                Err(reason) => bail!("{kind}: malformed frame in the benchmark: {reason}"),
            };
            if f.scene == LATENCY_SCENE {
                let sent = f.header.stamp.as_unsigned_nanos().unwrap_or(0);
                latencies.push(arrived_wall.saturating_sub(sent) as f64 / 1e3);
                *seen.entry(LATENCY_SCENE).or_default() += 1;
            } else {
                burst_first.get_or_insert(sample.received);
                burst_last = Some(sample.received);
                let n = seen.entry(BURST_SCENE).or_default();
                *n += 1;
                if *n == args.burst {
                    break;
                }
            }
        }
        let _ = child.wait();
        drop(subscription);
        latencies.sort_by(f64::total_cmp);
        let burst_received = seen.get(BURST_SCENE).copied().unwrap_or(0);
        let burst_fps = match (burst_first, burst_last) {
            (Some(a), Some(b)) if burst_received > 1 => {
                (burst_received - 1) as f64 / (b - a).as_secs_f64()
            }
            _ => f64::NAN,
        };
        rows.push(Row {
            kind,
            received: latencies.len() as u32,
            p50: percentile(&latencies, 0.5),
            p99: percentile(&latencies, 0.99),
            max: latencies.last().copied().unwrap_or(f64::NAN),
            burst_received,
            burst_fps,
        });
    }
    print_rows(args, &rows);
    Ok(Outcome::Done)
}

/// Starts this binary as the publisher process of the benchmark of `kind` on `topic`.
fn spawn_publisher(
    exe: &std::path::Path,
    args: &TransportBenchArgs,
    kind: TransportKind,
    topic: &str,
) -> anyhow::Result<std::process::Child> {
    let mut child = Command::new(&exe);
    child.args([
        "bench",
        "transport",
        "--role",
        "publisher",
        "--topic",
        topic,
    ]);
    child.args(args.transport.child_args(kind));
    child.args([
        "--frames",
        &args.frames.to_string(),
        "--hz",
        &args.hz.to_string(),
    ]);
    child.args([
        "--burst",
        &args.burst.to_string(),
        "--particles",
        &args.particles.to_string(),
    ]);
    child
        .stdout(Stdio::null())
        .spawn()
        .context("starting the publisher process")
}

/// Prints the latency and burst table (Markdown) of `rows` on stdout.
fn print_rows(args: &TransportBenchArgs, rows: &[Row]) {
    println!(
        "\nTransport latency, {} particles ({} KB CDR), two processes on loopback, {} frames at {} Hz; burst of {}:",
        args.particles,
        crate::msgs::cdr::encode(&frame(args.particles, LATENCY_SCENE, 0)).len() / 1024,
        args.frames,
        args.hz,
        args.burst
    );
    println!("| transport | received | lost | p50 us | p99 us | max us | burst received | burst frames/s |");
    println!("|---|---|---|---|---|---|---|---|");
    for r in rows {
        println!(
            "| {} | {} | {} | {:.0} | {:.0} | {:.0} | {} | {:.0} |",
            r.kind,
            r.received,
            args.frames - r.received.min(args.frames),
            r.p50,
            r.p99,
            r.max,
            r.burst_received,
            r.burst_fps
        );
    }
}
