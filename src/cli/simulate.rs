//! `minflow simulate`: generates scenes of a family (`--family multi --scenes 0..60`) or
//! from TOML scene files (`--scene-file FILE`), one MCAP bag per scene in `--out`, in
//! parallel over scenes with a progress bar. Each bag is written to `NAME.mcap.part` and
//! renamed when complete, so a folder never holds a half-written bag under a final name.

use super::transport::{PointCloud2Args, TransportArgs};
use super::{Outcome, UsageError};
use crate::bag::{BagWriter, FRAMES_TOPIC};
use crate::msgs::ParticleFrame;
use crate::sim::families::{self, Family};
use crate::sim::run::SceneRun;
use crate::sim::Scene;
use crate::transport::{wait_for_subscribers, Counters, FramePublisher};
use crate::viz::VizPublisher;
use anyhow::{bail, Context};
use clap::Args;
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Duration;

#[derive(Debug, Args)]
pub struct SimulateArgs {
    /// Scene family: `multi` (64^2 grid, 60 scenes), `fluid` (128^2 grid, 40 scenes) or
    /// `mixed` (1-4 bodies of any material and shape, either grid, 400 frames; 100 scenes by
    /// default, any number with `--scenes`).
    #[arg(long, default_value = "multi")]
    family: String,
    /// Scene ids: `A..B` (B excluded), `A..=B`, a list `0,3,7`, or one id. Default: the
    /// family's 60 (multi), 40 (fluid) or 100 (mixed); ids beyond them keep cycling through its scene kinds
    /// with new random placements (more training scenes: `--scenes 60..180`).
    #[arg(long)]
    scenes: Option<String>,
    /// Seed of the scene generator; the same (family, id, seed) gives the same bag.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// TOML scene file(s) to run instead of a family (format: docs/mpm.md, "Scene files").
    #[arg(long, conflicts_with_all = ["scenes"])]
    scene_file: Vec<PathBuf>,
    /// Put every scene on an N x N grid (a multiple of its own) with proportionally more
    /// particles (x (N / grid)^2: the `multi` family's 2,500 become 10,000 on 128 and 40,000 on
    /// 256) and the substeps the finer grid needs; names become `FAMILY@N/...`.
    #[arg(long, value_parser = clap::value_parser!(u32).range(8..=4096))]
    grid: Option<u32>,
    /// Shorten every scene to at most N frames (frame 0 included).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    frames: Option<u32>,
    /// Output folder (created if missing).
    #[arg(short, long, default_value = "data")]
    out: PathBuf,
    /// Scenes simulated at once (default: all cores).
    #[arg(short, long)]
    jobs: Option<usize>,
    /// Where the solver runs: `cpu` (one scene per thread) or `cuda` / `cuda:N` (the solver
    /// batched over `--batch` scenes on a GPU; needs a build with `--features cuda`).
    #[arg(long, default_value = "cpu")]
    device: String,
    /// With `--device cuda`: scenes a GPU call advances together.
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u32).range(1..=4096))]
    batch: u32,
    /// Topic the frames are written (and published) on.
    #[arg(long, default_value = FRAMES_TOPIC)]
    topic: String,
    /// Also publish every frame live on `--topic` while simulating.
    #[arg(long)]
    publish: bool,
    #[command(flatten)]
    transport: TransportArgs,
    /// With --publish: pace each scene at its simulation clock times this factor (1 = real
    /// time, 62.5 frames per second); 0 publishes frames as fast as they are simulated.
    #[arg(long, default_value_t = 1.0, value_parser = super::flags::rate)]
    rate: f64,
    /// With --publish: wait for this many subscribers before simulating (a Foxglove client
    /// watching the points counts as one).
    #[arg(long, default_value_t = 1)]
    wait_for_subscribers: usize,
    /// With --publish.
    #[command(flatten)]
    foxglove: super::foxglove::FoxgloveArgs,
    /// With --publish.
    #[command(flatten)]
    pointcloud2: PointCloud2Args,
}

/// Parses `A..B`, `A..=B`, `a,b,c` or `a` into ids.
pub fn parse_ids(spec: &str) -> anyhow::Result<Vec<u32>> {
    let num = |s: &str| -> anyhow::Result<u32> {
        s.trim()
            .parse()
            .map_err(|_| UsageError(format!("--scenes: scene id {s:?} is not a number")).into())
    };
    let ids: Vec<u32> = if let Some((a, b)) = spec.split_once("..=") {
        (num(a)?..=num(b)?).collect()
    } else if let Some((a, b)) = spec.split_once("..") {
        (num(a)?..num(b)?).collect()
    } else {
        spec.split(',').map(num).collect::<anyhow::Result<_>>()?
    };
    if ids.is_empty() {
        return Err(
            UsageError(format!("--scenes {spec:?} names no scene (an empty range)")).into(),
        );
    }
    Ok(ids)
}

pub use crate::bag::bag_name;

pub fn run(args: SimulateArgs) -> anyhow::Result<Outcome> {
    simulate(args, Live::open)
}

/// `run` without `--publish`, for `minflow-cuda`: no transport is linked in.
pub(super) fn run_offline(args: SimulateArgs) -> anyhow::Result<Outcome> {
    simulate(args, |_| bail!("--publish needs the full minflow binary"))
}

/// The scenes `args` names: `--scene-file`s, or ids of a family; a usage error for a bad
/// file or two scenes with one bag name.
fn scenes_of(args: &SimulateArgs) -> anyhow::Result<Vec<Scene>> {
    let mut scenes: Vec<Scene> = Vec::new();
    if args.scene_file.is_empty() {
        let family: Family = args.family.parse()?;
        let ids = match &args.scenes {
            Some(spec) => parse_ids(spec)?,
            None => (0..family.scene_count()).collect(),
        };
        scenes.extend(
            ids.into_iter()
                .map(|id| families::scene(family, id, args.seed)),
        );
    } else {
        for path in &args.scene_file {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading scene file {}", path.display()))?;
            // A value out of range in the file is a usage error (exit 2) naming the field.
            let scene = Scene::from_toml(&text)
                .map_err(|e| UsageError(format!("--scene-file {}: {e}", path.display())))?;
            scenes.push(scene);
        }
    }
    if let Some(n) = args.grid {
        scenes = scenes
            .iter()
            .map(|s| s.refined(n as usize))
            .collect::<Result<_, _>>()
            .map_err(|e| UsageError(format!("--grid {n}: {e}")))?;
    }
    // Two scenes with one bag name would be written to the same file at once.
    let mut names = std::collections::BTreeSet::new();
    if let Some(twice) = scenes.iter().find(|s| !names.insert(bag_name(&s.name))) {
        let flag = match args.scene_file.is_empty() {
            true => "--scenes",
            false => "--scene-file",
        };
        return Err(UsageError(format!(
            "{flag}: scene {:?} is named twice (each scene writes {})",
            twice.name,
            bag_name(&twice.name)
        ))
        .into());
    }
    Ok(scenes)
}

/// Simulates the scenes `args` names; `open` starts live publishing for `--publish`.
fn simulate(
    args: SimulateArgs,
    open: impl Fn(&SimulateArgs) -> anyhow::Result<Live>,
) -> anyhow::Result<Outcome> {
    if args.foxglove.foxglove.is_some() && !args.publish {
        return Err(UsageError("--foxglove needs --publish".into()).into());
    }
    if args.pointcloud2.pointcloud2.is_some() && !args.publish {
        return Err(UsageError("--pointcloud2 needs --publish".into()).into());
    }
    if args.publish && args.device != "cpu" {
        return Err(UsageError("--publish runs with the CPU solver (--device cpu)".into()).into());
    }
    let gpu = gpu_of(&args)?;
    let mut scenes = scenes_of(&args)?;
    if let Some(n) = args.frames {
        scenes.iter_mut().for_each(|s| s.frames = s.frames.min(n));
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating output folder {}", args.out.display()))?;
    let total: u64 = scenes.iter().map(|s| s.frames as u64).sum();
    let bar = super::progress(total, "frames");
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(args.jobs.unwrap_or(0))
        .build()
        .context("starting worker threads")?;
    let live = if args.publish {
        Some(open(&args)?)
    } else {
        None
    };
    let results: Vec<(String, anyhow::Result<PathBuf>)> = if let Some(gpu) = gpu {
        gpu(scenes, &args, &bar)?
    } else {
        pool.install(|| {
            scenes
                .into_par_iter()
                .map(|scene| {
                    let name = scene.name.clone();
                    let started = std::time::Instant::now();
                    let publish = |frame: &ParticleFrame| match &live {
                        Some(live) => live.publish(frame, started),
                        None => Ok(()),
                    };
                    let res = write_scene(scene, &args.out, &args.topic, &bar, &publish);
                    (name, res)
                })
                .collect()
        })
    };
    bar.finish_and_clear();
    if let Some(live) = live {
        live.finish();
    }
    let mut failed = 0;
    for (name, res) in &results {
        match res {
            Ok(path) => println!("{name}\t{}", path.display()),
            Err(err) => {
                failed += 1;
                eprintln!("error: scene {name}: {err:#}");
            }
        }
    }
    if failed > 0 {
        let summary = format!("{failed} of {} scene(s) failed", results.len());
        // A write that ran out of room keeps its cause in the chain: exit 3, data lost.
        let mut errors = results.into_iter().filter_map(|(_, r)| r.err());
        if let Some(full) = errors.find(super::out_of_room) {
            return Err(full.context(summary));
        }
        bail!(summary);
    }
    Ok(Outcome::Done)
}

/// A batch of scenes simulated on a GPU: their results, as the CPU path gives them.
type GpuRun = Box<
    dyn FnOnce(
        Vec<Scene>,
        &SimulateArgs,
        &indicatif::ProgressBar,
    ) -> anyhow::Result<Vec<(String, anyhow::Result<PathBuf>)>>,
>;

/// The GPU path `--device` names (`None` for `cpu`), checked before any work starts.
fn gpu_of(args: &SimulateArgs) -> anyhow::Result<Option<GpuRun>> {
    super::device::solver_gpu(&args.device)?
        .map(gpu_run)
        .transpose()
}

#[cfg(feature = "cuda")]
fn gpu_run(index: usize) -> anyhow::Result<GpuRun> {
    let device = super::device::cuda::device(index, crate::ops::Kernels::default())?;
    Ok(Box::new(move |scenes, args, bar| {
        let batch = args.batch as usize;
        super::simulate_gpu::simulate(scenes, &device, batch, &args.out, &args.topic, bar)
    }))
}

/// Unreachable: without the feature `device::parse` refuses `cuda`.
#[cfg(not(feature = "cuda"))]
fn gpu_run(_index: usize) -> anyhow::Result<GpuRun> {
    anyhow::bail!("this minflow was built without CUDA")
}

/// Live publishing for `simulate --publish`: one publisher shared by the scene threads.
struct Live {
    publisher: Mutex<Box<dyn FramePublisher>>,
    _session: Box<dyn crate::transport::Transport>,
    rate: f64,
    counters: Counters,
}

impl Live {
    fn open(args: &SimulateArgs) -> anyhow::Result<Self> {
        anyhow::ensure!(
            args.rate >= 0.0 && args.rate.is_finite(),
            "--rate must be >= 0"
        );
        let session = args.pointcloud2.open(&args.transport)?;
        let mut publisher = session.publisher(&args.topic)?;
        if let Some(view) = args.foxglove.start("minflow simulate")? {
            publisher = Box::new(VizPublisher::new(publisher, view.points(&args.topic)));
        }
        if args.wait_for_subscribers > 0 {
            tracing::info!(
                "waiting for {} subscriber(s) on {}",
                args.wait_for_subscribers,
                args.topic
            );
            let timeout = Duration::from_secs(60);
            if !wait_for_subscribers(publisher.as_ref(), args.wait_for_subscribers, timeout) {
                bail!(
                    "no subscriber on {} within {timeout:?} (use --wait-for-subscribers 0)",
                    args.topic
                );
            }
        }
        Ok(Live {
            publisher: Mutex::new(publisher),
            _session: session,
            rate: args.rate,
            counters: Counters::default(),
        })
    }

    /// Publishes `frame` of a scene whose simulation started at `started`, paced by its
    /// stamp (frame 0 goes out at once).
    fn publish(&self, frame: &ParticleFrame, started: std::time::Instant) -> anyhow::Result<()> {
        if self.rate > 0.0 {
            // Stamps of a scene file's frames can be far off (any positive dt): a wait past
            // the clock's range is skipped rather than a panic.
            let due = Duration::try_from_secs_f64(frame.header.stamp.as_secs_f64() / self.rate)
                .ok()
                .and_then(|d| started.checked_add(d));
            if let Some(wait) =
                due.and_then(|d| d.checked_duration_since(std::time::Instant::now()))
            {
                std::thread::sleep(wait);
            }
        }
        let mut publisher = self.publisher.lock().expect("publisher lock poisoned");
        publisher.publish(frame)?;
        self.counters.published();
        Ok(())
    }

    fn finish(self) {
        let mut publisher = self
            .publisher
            .into_inner()
            .expect("publisher lock poisoned");
        publisher.flush(Duration::from_secs(5));
        eprintln!("simulate: published {}", self.counters.get());
    }
}

/// Simulates one scene into `out/NAME.mcap` (via `.part`, renamed when complete), calling
/// `on_frame` with every frame after it is written (live publishing).
pub(super) fn write_scene(
    scene: Scene,
    out: &Path,
    topic: &str,
    bar: &indicatif::ProgressBar,
    on_frame: &(dyn Fn(&ParticleFrame) -> anyhow::Result<()> + Sync),
) -> anyhow::Result<PathBuf> {
    let path = out.join(bag_name(&scene.name));
    let part = path.with_extension("mcap.part");
    let mut writer = BagWriter::create(&part)?;
    writer.channel_metadata(crate::bag::SOLVER_GRID_KEY, &scene.grid.to_string());
    let run = SceneRun::new(scene)?;
    for frame in run {
        let frame = frame?;
        writer.write(topic, &frame)?;
        on_frame(&frame)?;
        bar.inc(1);
    }
    writer.finish()?;
    std::fs::rename(&part, &path).with_context(|| format!("renaming {}", part.display()))?;
    Ok(path)
}
