//! `minflow node`: the surrogate node (live next-frame prediction over zenoh, iceoryx2 or
//! ROS 2). Logic in [`crate::node::surrogate`]. The model runs on `--device` (CPU or one GPU).

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::Args;

use super::transport::{PointCloud2Args, TransportArgs};
use super::Outcome;
use crate::bag::{FRAMES_TOPIC, PREDICTED_TOPIC};
use crate::model::store::Surrogate;
use crate::msgs::status::STATUS_TOPIC;
use crate::node::shutdown_flag;
use crate::node::surrogate::{self, NodeOptions, OnGap};
use crate::ops::NetOps;

#[derive(Debug, Args)]
pub struct NodeArgs {
    /// Run folder of a trained model (`minflow train --out`).
    #[arg(long)]
    model: PathBuf,
    #[command(flatten)]
    transport: TransportArgs,
    /// Input topic: ground-truth frames.
    #[arg(long = "in", default_value = FRAMES_TOPIC)]
    input: String,
    /// Output topic: predicted next frames.
    #[arg(long = "out", default_value = PREDICTED_TOPIC)]
    output: String,
    /// Status topic (counters and last error, once per second); "none" to disable.
    #[arg(long, default_value = STATUS_TOPIC)]
    status: String,
    /// Node name in logs and status reports.
    #[arg(long, default_value = "surrogate")]
    name: String,
    /// On a gap or out-of-order frame: reset the scene's hidden state, or skip old frames.
    #[arg(long, value_enum, default_value_t = OnGap::Reset)]
    on_gap: OnGap,
    /// Seconds without frames after which a scene's state is reset and dropped.
    #[arg(long, default_value_t = 10.0, value_parser = super::flags::seconds)]
    idle_timeout: f64,
    /// Most scene states kept (least recently seen dropped first).
    #[arg(long, default_value_t = 1024, value_parser = super::flags::at_least_one)]
    max_scenes: usize,
    /// Pending frames per scene before the oldest is dropped.
    #[arg(long, default_value_t = 8, value_parser = super::flags::at_least_one)]
    queue_depth: usize,
    /// Frames whose payload is larger than this many bytes are rejected before they are
    /// decoded (counted as `rejected`, logged), so one publisher cannot make the node
    /// allocate without bound. The default, 64 MiB, holds 4 million particles.
    #[arg(long, default_value_t = 64 << 20, value_parser = super::flags::at_least_one)]
    max_frame_bytes: usize,
    /// Closed loop: after the first T frames of a scene, publish R predicted frames (a model
    /// trained with --bundle K makes ceil(R / K) network calls). Without it, each input
    /// frame gets its next frame (for a bundled model, the first of its bundle).
    #[arg(long, value_name = "R", value_parser = super::flags::at_least_one)]
    rollout: Option<usize>,
    /// Closed-loop pacing factor (1 = the scene's own frame rate); 0 = as fast as possible.
    #[arg(long, default_value_t = 0.0, value_parser = super::flags::rate)]
    rate: f64,
    /// Dynamic batching (as NVIDIA Triton's dynamic batcher): most scenes stepped by one
    /// network call, each with its own state (1: one scene a call, no batching). Default:
    /// 4 on the CPU (a call of more scenes costs more per scene there: docs/scale.md), 256
    /// on a GPU (calls padded to powers of two, `--pad-batches`; in `bench node` on an H100,
    /// 256 gave 1.1-1.8x the predictions/s of 64 when overloaded, at a higher p50:
    /// docs/scale.md, "Where the node's time goes").
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=4096))]
    max_batch: Option<u32>,
    /// Dynamic batching: milliseconds the oldest waiting frame may wait for frames of other
    /// scenes to join its call (0-1000; a small fraction of the frame period). A call goes
    /// at once when every scene that could join has.
    #[arg(long, default_value_t = 2.0, value_name = "MS", value_parser = batch_delay_ms)]
    max_batch_delay: f64,
    /// Dynamic batching: pad each call to a power-of-two number of scenes (copies of its
    /// last scene, their results dropped), so calls come in log2(--max-batch) shapes, not
    /// --max-batch of them. Default: true on a GPU (each new batch shape compiles and
    /// autotunes kernels there), false on the CPU (padding is only extra work there).
    #[arg(long, value_name = "BOOL")]
    pad_batches: Option<bool>,
    /// Dynamic batching: record the next call before waiting for the last one's predictions,
    /// which a thread of their own reads back and projects while the loop gathers and
    /// records (at most two calls handed over), so the GPU runs while the host works; costs
    /// latency at a light load (docs/scale.md). Default: true on a GPU, false on the CPU
    /// (which computes as it records: nothing to overlap).
    #[arg(long, value_name = "BOOL")]
    pipeline: Option<bool>,
    /// Dynamic batching: before a batch size first carries frames of a particle count, make
    /// one call of it (copies of one scene, their results dropped), as Triton's model warmup
    /// does: on a GPU a call of a new shape compiles kernels and times cuDNN's algorithms, a
    /// stall of a second or more when a burst first makes that batch. The sizes follow the
    /// scenes seen of that count, up to --max-batch. Default: true on a GPU, false on the CPU.
    #[arg(long, value_name = "BOOL")]
    warm_up_batches: Option<bool>,
    /// Shard the scenes over the live nodes of GROUP (zenoh only): each node declares a
    /// zenoh liveliness token, a scene is predicted by the live node of highest rendezvous
    /// hash, and a dead node's scenes move to the others (restarting from the next frame).
    #[arg(long, value_name = "GROUP", value_parser = shard_group)]
    shard: Option<String>,
    /// Exit after publishing this many predicted frames.
    #[arg(long)]
    max_published: Option<u64>,
    /// Subscribe to the input only once the output topic has this many subscribers.
    #[arg(long, default_value_t = 0)]
    wait_for_subscribers: usize,
    /// Log the counters every this many seconds.
    #[arg(long, value_parser = super::flags::interval)]
    stats_interval: Option<f64>,
    /// Step a grid model as a mirror ensemble: each frame and its mirror image about the
    /// box's vertical midline, predictions averaged (`eval --mirror`; twice the work per
    /// step, two memory states per scene).
    #[arg(long)]
    mirror: bool,
    /// Which parts of the model's material constraints every predicted frame is projected
    /// onto: on (all the model has) | off | a list of rope, jelly, snow, liquid, walls,
    /// contact, momentum, rebound, pressure.
    #[arg(long, value_name = "PARTS", default_value = "on")]
    constraints: crate::model::constraints::Parts,
    /// The solver grid (cells per side) of the scenes served, when known: the liquid's
    /// pressure part takes that grid's threshold (the model's default threshold without it).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..))]
    solver_grid: Option<u32>,
    /// Bags or folders whose scenes' solver grids (the `minflow/solver_grid` metadata
    /// `simulate` writes) the node takes for those scenes (the replay's bags, say).
    #[arg(long, value_name = "BAGS", num_args = 1..)]
    solver_grid_from: Vec<std::path::PathBuf>,
    #[command(flatten)]
    device: super::device::DeviceArgs,
    #[command(flatten)]
    foxglove: super::foxglove::FoxgloveArgs,
    #[command(flatten)]
    pointcloud2: PointCloud2Args,
}

pub fn run(args: NodeArgs) -> anyhow::Result<Outcome> {
    match args.device.parse()?.single("node")? {
        None => serve::<burn::backend::NdArray<f32>>(args, Default::default()),
        #[cfg(feature = "cuda")]
        Some(id) => {
            use super::device::cuda::{device, CudaInfer};
            let device = device(id, args.device.kernels())?;
            serve::<CudaInfer>(args, device)
        }
        #[cfg(not(feature = "cuda"))]
        Some(_) => anyhow::bail!("built without CUDA"),
    }
}

/// The solver grid of each scene in `bags` that records one (`--solver-grid-from`).
fn solver_grids(
    bags: &[std::path::PathBuf],
) -> anyhow::Result<std::collections::HashMap<String, u32>> {
    if bags.is_empty() {
        return Ok(Default::default());
    }
    let infos = crate::data::scan(bags, None).context("reading --solver-grid-from")?;
    Ok(infos
        .into_iter()
        .filter_map(|i| Some((i.scene, i.solver_grid?)))
        .collect())
}

/// Loads the model onto `device` of backend `B` and serves until stopped.
fn serve<B: NetOps>(args: NodeArgs, device: B::Device) -> anyhow::Result<Outcome> {
    let on_cpu = args.device.parse()?.single("node")?.is_none();
    let max_batch = args.max_batch.unwrap_or(if on_cpu { 4 } else { 256 });
    let model = Surrogate::<B>::load(&args.model, &device)
        .with_context(|| format!("loading the model in {}", args.model.display()))?
        .with_mirror(args.mirror)
        .with_constraints(args.constraints)
        .with_solver_grid(args.solver_grid)
        .with_solver_grids(solver_grids(&args.solver_grid_from)?)
        .with_padded_batches(args.pad_batches.unwrap_or(!on_cpu));
    let foxglove = args
        .foxglove
        .start(&format!("minflow node {}", args.name))?;
    let options = NodeOptions {
        name: args.name,
        input: args.input,
        output: args.output,
        status: (args.status != "none").then_some(args.status),
        on_gap: args.on_gap,
        idle_timeout: Duration::from_secs_f64(args.idle_timeout.max(0.0)),
        max_scenes: args.max_scenes,
        queue_depth: args.queue_depth,
        max_frame_bytes: args.max_frame_bytes,
        rollout: args.rollout,
        rate: args.rate,
        max_batch: max_batch as usize,
        max_batch_delay: Duration::from_secs_f64(args.max_batch_delay / 1e3),
        pipeline: args.pipeline.unwrap_or(!on_cpu),
        warm_up: args.warm_up_batches.unwrap_or(!on_cpu),
        shard: args.shard,
        max_published: args.max_published,
        wait_for_subscribers: args.wait_for_subscribers,
        stats_interval: args
            .stats_interval
            .map(|s| Duration::from_secs_f64(s.max(0.1))),
        foxglove,
    };
    let stop = shutdown_flag();
    let session = args.pointcloud2.open(&args.transport)?;
    let report = surrogate::run(&options, &model, session.as_ref(), &stop)?;
    eprintln!("{}", surrogate::summary(&report));
    Ok(Outcome::Done)
}

/// `--max-batch-delay`: milliseconds from 0 to 1000.
fn batch_delay_ms(s: &str) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|e| format!("{s:?}: {e}"))?;
    if (0.0..=1000.0).contains(&v) {
        Ok(v)
    } else {
        Err(format!("{v} ms is outside 0..=1000"))
    }
}

/// `--shard`: a group name usable as one zenoh key chunk (letters, digits, `-`, `_`, `.`).
fn shard_group(s: &str) -> Result<String, String> {
    let ok = |c: char| c.is_ascii_alphanumeric() || "-_.".contains(c);
    if !s.is_empty() && s.chars().all(ok) {
        Ok(s.to_owned())
    } else {
        Err(format!("{s:?}: use letters, digits, '-', '_' and '.'"))
    }
}

/// `--on-gap`'s values, each with its help line.
impl clap::ValueEnum for OnGap {
    fn value_variants<'a>() -> &'a [Self] {
        &[OnGap::Reset, OnGap::Skip]
    }

    fn to_possible_value(&self) -> Option<clap::builder::PossibleValue> {
        let (name, help) = match self {
            OnGap::Reset => (
                "reset",
                "Reset the scene's hidden state and start again from this frame",
            ),
            OnGap::Skip => (
                "skip",
                "Drop frames older than the last one; carry the state over forward gaps",
            ),
        };
        Some(clap::builder::PossibleValue::new(name).help(help))
    }
}
