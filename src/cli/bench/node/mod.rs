//! `minflow bench node`: the surrogate node's latency and throughput per core type and
//! transport, between processes on loopback. For each core, an untrained model at the
//! paper's sizes (2,500 particles, encoder 5 -> 256 -> 1250, two layers of 1250, global
//! decoder; weights do not change the cost) is saved; then, per transport, a `minflow node`
//! process is started, warmed up (frames until it has returned a few predictions), and this
//! process publishes the frames of a bundled bag at 62.5 Hz
//! (one scene, consecutive frame indices, so the hidden state carries on) and receives the
//! predictions. Printed per row: the model's own step time in this process (p50, p99), the
//! publish-to-prediction latency through the node (p50, p99; two transport hops plus the
//! model), what the transport adds over the model (p50 difference over the model's p50),
//! and the sustained frames per second of a burst (predictions received per second while
//! frames are published as fast as the transport accepts them; the node drops the oldest
//! pending frames it cannot keep up with). `--device cuda[:N]` runs the model, in this
//! process and in the node, on a GPU (a build with the `cuda` feature). `--batch 1,16,64`
//! adds a table of the model's step on that many scenes at once (frames per second a batching
//! node could sustain); `--skip-node` measures in this process only. The node process and
//! its paced and burst runs live in `through.rs`. `--streams N --rate HZ` measures instead
//! one node serving N live streams, one row per `--max-batch` (`streams.rs`).

mod streams;
mod through;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context};
use burn::backend::NdArray;
use clap::Args;

use super::common::{percentile as pct, BenchTransportOptions};
use crate::bag::{read_frames, FRAMES_TOPIC};
use crate::cli::Outcome;
use crate::data::{self, Scaler};
use crate::model::store::{save, ModelMeta, Surrogate};
use crate::model::CoreKind;
use crate::model::{LastActivation, ModelConfig};
use crate::msgs::ParticleFrame;
use crate::node::surrogate::state_rows as rows;
use crate::ops::NetOps;
use crate::transport::TransportKind;
use through::through_node;

/// The flags of `minflow bench node`.
#[derive(Debug, Args)]
pub struct NodeBenchArgs {
    /// Cores to measure (comma-separated): mlp, lstm, gru, minlstm, mingru.
    #[arg(long, default_value = "mingru,minlstm,gru,lstm,mlp")]
    cores: String,
    #[command(flatten)]
    transport: BenchTransportOptions,
    /// Frames published at 62.5 Hz per row.
    #[arg(long, default_value_t = 300)]
    frames: u32,
    /// Frames of the burst per row.
    #[arg(long, default_value_t = 200)]
    burst: u32,
    /// Encoder's last activation: none (mean pooling lets the second Linear run after
    /// pooling, ~200x cheaper, exactly) | elu (the paper's text, ~1.6 GFLOP per frame).
    #[arg(long, default_value = "none")]
    encoder_last_activation: String,
    /// Bag whose frames are published.
    #[arg(long, default_value = "bags/multi_rope+snow_001.mcap")]
    bag: PathBuf,
    /// Trained run folders to measure (repeatable; e.g. the shipped models/all-grid-mingru)
    /// instead of untrained paper-sized models of --cores.
    #[arg(long = "model", value_name = "DIR")]
    models: Vec<PathBuf>,
    /// Also run every row with the node serving Foxglove (`--foxglove 127.0.0.1:0`) and no
    /// client connected: what the idle live view costs.
    #[arg(long)]
    foxglove_idle: bool,
    /// Batch sizes (comma-separated, each 1-1024) for the batched table: the model's step on
    /// that many scenes at once in this process, and the frames per second it sustains
    /// (scenes / step time): what one node serving many streams could reach with batching.
    #[arg(long, value_delimiter = ',', value_parser = clap::value_parser!(u32).range(1..=1024))]
    batch: Vec<u32>,
    /// Measure in this process only (the model's step and `--batch`), without starting nodes.
    #[arg(long, conflicts_with_all = ["transports", "foxglove_idle", "frames", "burst"])]
    skip_node: bool,
    /// Run the `--model` grid models as mirror ensembles (`node --mirror`: twice the work).
    #[arg(long)]
    mirror: bool,
    /// Which parts of the `--model` models' material constraints the node (and the step in this
    /// process) projects every predicted frame onto (`node --constraints`): on | off | a list of
    /// rope, jelly, snow, liquid, walls, contact, momentum, rebound, pressure. The projection runs
    /// on the host.
    #[arg(long, value_name = "PARTS", default_value = "on")]
    constraints: crate::model::constraints::Parts,
    /// `--streams`: whether the node publishes a call's predictions only after recording the
    /// next call (`node --pipeline`). Default: the node's (true on a GPU).
    #[arg(long, value_name = "BOOL")]
    pipeline: Option<bool>,
    /// `--streams`: whether the node warms up every batch size first (`node
    /// --warm-up-batches`). Default: the node's (true on a GPU).
    #[arg(long, value_name = "BOOL")]
    warm_up_batches: Option<bool>,
    /// Many streams into one node (zenoh): this many scenes, interleaved, from one
    /// publisher process; one row per `--max-batch` value (1-4096).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=4096))]
    streams: Option<u32>,
    /// `--streams`: nodes serving the streams (1-16), sharded over zenoh (`node --shard`):
    /// each predicts the scenes it owns, as instances of one model on one device do in
    /// NVIDIA Triton's instance groups.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=16))]
    nodes: u32,
    /// `--streams`: frames per second of each stream (0.1-1000).
    #[arg(long, default_value_t = 12.5, value_parser = rate_hz)]
    rate: f64,
    /// `--streams`: seconds timed (1-3600), after `--warm-up`.
    #[arg(long, default_value_t = 10.0, value_parser = seconds_1h)]
    seconds: f64,
    /// `--streams`: seconds sent first and not counted (0-3600).
    #[arg(long, default_value_t = 3.0, value_parser = crate::cli::flags::seconds)]
    warm_up: f64,
    /// `--streams`: the node's `--max-batch` per row (comma-separated, each 1-4096).
    #[arg(long, value_delimiter = ',', default_value = "1,4",
          value_parser = clap::value_parser!(u32).range(1..=4096))]
    max_batch: Vec<u32>,
    /// `--streams`: the node's `--max-batch-delay`, ms (0-1000).
    #[arg(long, default_value_t = 2.0)]
    max_batch_delay: f64,
    /// `--streams`: the node's `--queue-depth`, pending frames per scene (1: each scene's
    /// newest frame only, the lowest latency when the node falls behind).
    #[arg(long, default_value_t = 8, value_parser = crate::cli::flags::at_least_one)]
    queue_depth: usize,
    /// Internal: be the publisher process of `--streams`, publishing to this topic.
    #[arg(long, hide = true)]
    publish_to: Option<String>,
    #[command(flatten)]
    device: crate::cli::device::DeviceArgs,
}

/// `--rate`: frames per second per stream, 0.1 to 1000.
fn rate_hz(s: &str) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|e| format!("{s:?}: {e}"))?;
    (0.1..=1000.0)
        .contains(&v)
        .then_some(v)
        .ok_or(format!("{v} Hz is outside 0.1..=1000"))
}

/// `--seconds`: 1 to 3600.
fn seconds_1h(s: &str) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|e| format!("{s:?}: {e}"))?;
    (1.0..=3600.0)
        .contains(&v)
        .then_some(v)
        .ok_or(format!("{v} s is outside 1..=3600"))
}

/// Saves an untrained paper-sized model for `core` into `dir`.
fn make_model(
    dir: &Path,
    core: CoreKind,
    last: LastActivation,
    scaler: &Scaler,
) -> anyhow::Result<()> {
    type B = NdArray<f32>;
    let config = ModelConfig::new(core, 2500)
        .with_encoder_last_activation(last)
        .with_decoder_zero_init(false);
    let model = config.init::<B>(&Default::default());
    let meta = ModelMeta {
        net: crate::model::store::NetConfig::Paper(config),
        scaler: *scaler,
        epoch: 0,
        val_loss: 0.0,
        constraints: None,
    };
    save(dir, &model, &meta)?;
    Ok(())
}

/// One row of the table: a model over one transport.
struct Row {
    name: String,
    /// None for a row measured in this process only (`--skip-node`).
    kind: Option<TransportKind>,
    /// The node served Foxglove (nothing connected).
    foxglove: bool,
    /// The model's own step time in this process, p50 and p99, us.
    model_p50: f64,
    model_p99: f64,
    /// Predictions received of the paced run.
    received: usize,
    /// Publish-to-prediction latency, p50 and p99, us.
    e2e_p50: f64,
    e2e_p99: f64,
    /// Predictions received per second during the burst.
    burst_fps: f64,
}

/// Runs `minflow bench node`: the publisher of a streams run (`--publish-to`), the streams
/// table (`--streams`), or the per-core tables.
///
/// # Errors
/// Bad flags, a bag that cannot be read, a model or node process that fails.
pub fn run(args: NodeBenchArgs) -> anyhow::Result<Outcome> {
    if let Some(topic) = &args.publish_to {
        streams::publish(&args, topic)?;
        return Ok(Outcome::Done);
    }
    if args.streams.is_some() {
        anyhow::ensure!(
            (0.0..=1000.0).contains(&args.max_batch_delay),
            "--max-batch-delay {} ms is outside 0..=1000",
            args.max_batch_delay
        );
        let exe = std::env::current_exe().context("locating the minflow binary")?;
        let model = args
            .models
            .first()
            .cloned()
            .unwrap_or_else(|| PathBuf::from("models/all-grid-mingru-small"));
        streams::run(&args, &exe, &model)?;
        return Ok(Outcome::Done);
    }
    per_core(&args)
}

/// The per-core tables: each model's step in this process (alone and in `--batch` sizes),
/// then through a node process per transport unless `--skip-node`.
fn per_core(args: &NodeBenchArgs) -> anyhow::Result<Outcome> {
    let last = match args.encoder_last_activation.as_str() {
        "none" => LastActivation::None,
        "elu" => LastActivation::Elu,
        other => bail!("unknown --encoder-last-activation {other:?} (none | elu)"),
    };
    let gpu = args.device.parse()?.single("bench node")?;
    let frames = bag_frames(&args.bag)?;
    let (trajs, _) = data::load(std::slice::from_ref(&args.bag), Some(FRAMES_TOPIC))?;
    let scaler = Scaler::fit(&trajs.iter().collect::<Vec<_>>());
    let exe = std::env::current_exe().context("locating the minflow binary")?;
    let tmp = tempfile::tempdir()?;
    let runs = model_runs(args, tmp.path(), last, &scaler)?;
    let mut table = Vec::new();
    let mut batched = Vec::new();
    for (name, dir) in &runs {
        let step_us = |b: usize| model_step_on(args, gpu, dir, &frames, b);
        let model_us = step_us(1)?;
        for &b in &args.batch {
            eprintln!("bench node: {name}, {b} scenes per step ...");
            let us = step_us(b as usize)?;
            batched.push((name.clone(), b, pct(&us, 0.5), pct(&us, 0.99)));
        }
        if args.skip_node {
            table.push(Row::in_process(name, &model_us));
            continue;
        }
        table.extend(node_rows(args, &exe, (name, dir), &model_us, &frames)?);
    }
    print_table(args, &table);
    print_batched(args, &batched);
    Ok(Outcome::Done)
}

/// [`model_step_us`] of the model in `dir` on `b` scenes, on the CPU or the GPU `gpu`.
#[cfg_attr(not(feature = "cuda"), allow(unused_variables))]
fn model_step_on(
    args: &NodeBenchArgs,
    gpu: Option<usize>,
    dir: &Path,
    frames: &[ParticleFrame],
    b: usize,
) -> anyhow::Result<Vec<f64>> {
    match gpu {
        None => model_step_us::<NdArray<f32>>(dir, frames, b, args, &Default::default()),
        #[cfg(feature = "cuda")]
        Some(id) => {
            use crate::cli::device::cuda::{device, CudaInfer};
            let device = device(id, args.device.kernels())?;
            model_step_us::<CudaInfer>(dir, frames, b, args, &device)
        }
        #[cfg(not(feature = "cuda"))]
        Some(_) => bail!("built without CUDA"),
    }
}

/// The rows of the model `name` in `dir` through a node process, per transport (and with
/// the idle live view, `--foxglove-idle`); `model_us` its step times in this process.
fn node_rows(
    args: &NodeBenchArgs,
    exe: &Path,
    (name, dir): (&str, &Path),
    model_us: &[f64],
    frames: &[ParticleFrame],
) -> anyhow::Result<Vec<Row>> {
    let variants: &[bool] = if args.foxglove_idle {
        &[false, true]
    } else {
        &[false]
    };
    let transports = args.transport.kinds();
    let mut rows = Vec::new();
    for (&kind, &foxglove) in transports
        .iter()
        .flat_map(|k| variants.iter().map(move |f| (k, f)))
    {
        eprintln!("bench node: {name} over {kind}{} ...", suffix(foxglove));
        let (received, latency, burst_fps) =
            through_node(args, exe, dir, (kind, foxglove), frames)?;
        rows.push(Row {
            name: name.to_owned(),
            kind: Some(kind),
            foxglove,
            model_p50: pct(model_us, 0.5),
            model_p99: pct(model_us, 0.99),
            received,
            e2e_p50: pct(&latency, 0.5),
            e2e_p99: pct(&latency, 0.99),
            burst_fps,
        });
    }
    Ok(rows)
}

/// How a row's transport column names the idle live view.
fn suffix(foxglove: bool) -> &'static str {
    if foxglove {
        " + foxglove (idle)"
    } else {
        ""
    }
}

/// The frames of `bag`'s frames topic; an error unless there are at least two of 2,500
/// particles.
fn bag_frames(bag: &Path) -> anyhow::Result<Vec<ParticleFrame>> {
    let frames: Vec<ParticleFrame> = read_frames(bag, Some(FRAMES_TOPIC))
        .with_context(|| format!("reading {}", bag.display()))?
        .frames
        .into_iter()
        .map(|m| m.2)
        .collect();
    anyhow::ensure!(
        frames.len() >= 2 && frames[0].len() == 2500,
        "{} must hold 2,500-particle frames",
        bag.display()
    );
    Ok(frames)
}

/// The models to measure, as (row name, run folder): the `--model` folders, or an untrained
/// paper-sized model per `--cores` entry saved under `tmp`.
fn model_runs(
    args: &NodeBenchArgs,
    tmp: &Path,
    last: LastActivation,
    scaler: &Scaler,
) -> anyhow::Result<Vec<(String, PathBuf)>> {
    let mut runs = Vec::new();
    if args.models.is_empty() {
        for name in args
            .cores
            .split(',')
            .map(str::trim)
            .filter(|s| !s.is_empty())
        {
            let core = CoreKind::parse(name).with_context(|| format!("unknown core {name:?}"))?;
            let dir = tmp.join(name);
            make_model(&dir, core, last, scaler)?;
            runs.push((name.to_owned(), dir));
        }
    } else {
        for dir in &args.models {
            let name = dir.file_name().map_or_else(
                || dir.display().to_string(),
                |n| n.to_string_lossy().into_owned(),
            );
            runs.push((name, dir.clone()));
        }
    }
    Ok(runs)
}

/// The model's own step times in this process on `device`, us, sorted: 50 steps after 10
/// warm-up ones over consecutive `frames`, `b` scenes per step (scene j starts j frames into
/// the bag; each step returns its predictions to the host, as the node's does).
fn model_step_us<B: NetOps>(
    dir: &Path,
    frames: &[ParticleFrame],
    b: usize,
    args: &NodeBenchArgs,
    device: &B::Device,
) -> anyhow::Result<Vec<f64>> {
    let surrogate = Surrogate::<B>::load(dir, device)?
        .with_mirror(args.mirror)
        .with_constraints(args.constraints);
    let mut state = surrogate.init_state();
    let mut model_us = Vec::new();
    for i in 0..60 {
        let batch: Vec<&ParticleFrame> = (0..b).map(|j| &frames[(i + j) % frames.len()]).collect();
        let states: Vec<f32> = batch.iter().flat_map(|f| rows(f)).collect();
        let material: Vec<u8> = batch
            .iter()
            .flat_map(|f| f.material.iter().copied())
            .collect();
        let dt: Vec<f32> = batch.iter().map(|f| f.dt).collect();
        let t = Instant::now();
        let (_, s) = surrogate.step(&states, &material, &dt, state)?;
        state = s;
        if i >= 10 {
            model_us.push(t.elapsed().as_secs_f64() * 1e6);
        }
    }
    model_us.sort_by(f64::total_cmp);
    Ok(model_us)
}

impl Row {
    /// A row measured in this process only (`--skip-node`): no transport columns.
    fn in_process(name: &str, model_us: &[f64]) -> Self {
        Self {
            name: name.to_owned(),
            kind: None,
            foxglove: false,
            model_p50: pct(model_us, 0.5),
            model_p99: pct(model_us, 0.99),
            received: 0,
            e2e_p50: f64::NAN,
            e2e_p99: f64::NAN,
            burst_fps: f64::NAN,
        }
    }
}

/// Prints the batched table (Markdown) on stdout: per model and batch size, the step's p50 and
/// p99 and the frames per second at p50. Nothing when `--batch` was not given.
fn print_batched(args: &NodeBenchArgs, rows: &[(String, u32, f64, f64)]) {
    if rows.is_empty() {
        return;
    }
    println!(
        "\nBatched step in this process on {} (B scenes per step, 2,500 particles each):",
        args.device.device
    );
    println!("| model | B | step p50 ms | step p99 ms | frames/s (B / p50) |");
    println!("|---|---:|---:|---:|---:|");
    for (name, b, p50, p99) in rows {
        let fps = f64::from(*b) / (p50 / 1e6);
        println!(
            "| {name} | {b} | {:.3} | {:.3} | {fps:.0} |",
            p50 / 1e3,
            p99 / 1e3
        );
    }
}

/// Prints the table (Markdown) on stdout.
fn print_table(args: &NodeBenchArgs, table: &[Row]) {
    let what = if args.models.is_empty() {
        format!(
            "untrained paper-sized models (N = 2,500, W = 1,250, encoder last activation {})",
            args.encoder_last_activation
        )
    } else {
        "the given run folders".to_owned()
    };
    if args.skip_node {
        println!(
            "\nModel step in this process, {what}, on {}:",
            args.device.device
        );
        println!("| model | model p50 ms | model p99 ms |");
        println!("|---|---|---|");
        for r in table {
            let (p50, p99) = (r.model_p50 / 1e3, r.model_p99 / 1e3);
            println!("| {} | {p50:.2} | {p99:.2} |", r.name);
        }
        return;
    }
    println!(
        "\nSurrogate node, {what}, on {}, {} frames at 62.5 Hz, burst of {}:",
        args.device.device, args.frames, args.burst
    );
    println!("| core | transport | model p50 ms | model p99 ms | predictions | e2e p50 ms | e2e p99 ms | transport adds (p50) | burst predictions/s |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for r in table {
        println!(
            "| {} | {}{} | {:.2} | {:.2} | {}/{} | {:.2} | {:.2} | {:+.0} % | {:.0} |",
            r.name,
            r.kind.map_or_else(String::new, |k| k.to_string()),
            suffix(r.foxglove),
            r.model_p50 / 1e3,
            r.model_p99 / 1e3,
            r.received,
            args.frames,
            r.e2e_p50 / 1e3,
            r.e2e_p99 / 1e3,
            (r.e2e_p50 - r.model_p50) / r.model_p50 * 100.0,
            r.burst_fps,
        );
    }
}
