//! `minflow bench rollout`: what a surrogate costs against the solver it stands in for, in
//! one run (docs/design.md, "Metrics": cost). On scenes of one family generated with
//! `--seed` (other than the training seed: unseen scenes), the MLS-MPM solver simulates
//! W + H frames of each scene, one scene per thread of the pool; then each model, on the same
//! pool (or a GPU), rolls every scene out closed-loop for H frames from the solver's first W
//! frames, `--batch` scenes per network call. Printed per row: frames per call (K), calls per
//! rollout (ceil(H / K)), milliseconds per predicted frame (wall time over scenes x frames),
//! its ratio to the solver's milliseconds per simulated frame, and the rollout's mean scaled
//! MSE against the simulated frames (`avgH`, the model's scaler). The ratio comes from one run,
//! so it holds on a noisy machine; quote it rather than the milliseconds. With several
//! `--constraints` settings each model gets a row per setting (`DIR[setting]`): the
//! projection's own cost is the difference of its `on` and `off` rows; the last two columns
//! are the projection's wall time a frame (all parts, measured inside the rollout; on a GPU
//! that projects on the device, its host side only, laying out the plan: the kernel is part
//! of the call) and its share of the frame, and the thread time a scene spent once building
//! its constraint data (inside that wall time; over a whole scene it is spread over every
//! frame). With
//! `MINFLOW_CALL_STAGES=1` a line under each row splits a grid call's wall time by stage
//! (input, record, device, output; `model::store::stages`).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use rayon::prelude::*;

use crate::cli::device::{Device, DeviceArgs};
use crate::cli::Outcome;
use crate::eval::frame_metrics;
use crate::model::constraints::Parts;
use crate::model::roofline::{self, Tally};
use crate::model::store::{stages, Surrogate};
use crate::ops::NetOps;
use crate::sim::families::Family;
use crate::sim::{Scene, SceneRun};

/// The flags of `minflow bench rollout`.
#[derive(Debug, Args)]
pub struct RolloutBenchArgs {
    /// Run folders of trained models (repeatable), e.g. models/all-grid-mingru.
    #[arg(long = "model", value_name = "DIR", required = true)]
    models: Vec<PathBuf>,
    /// Scene family: multi (64^2 grid, 20 substeps) | fluid (128^2, 80 substeps).
    #[arg(long, default_value = "multi", value_parser = ["multi", "fluid"])]
    family: String,
    /// Scenes, ids 0..N of `simulate --seed`.
    #[arg(long, default_value_t = 4, value_parser = crate::cli::flags::at_least_one)]
    scenes: usize,
    /// Seed of the scenes (the shipped models trained on seed 1: 7 gives unseen scenes).
    #[arg(long, default_value_t = 7)]
    seed: u64,
    /// Frames predicted per rollout, H.
    #[arg(long, default_value_t = 100, value_parser = crate::cli::flags::at_least_one)]
    frames: usize,
    /// Scenes per network call (a batch of rollouts at once; 1: one scene after another).
    #[arg(long, default_value_t = 1, value_parser = crate::cli::flags::at_least_one)]
    batch: usize,
    /// Threads of the pool the solver and the CPU models run on (default: all cores).
    #[arg(long, value_parser = crate::cli::flags::at_least_one)]
    threads: Option<usize>,
    /// Which parts of each model's material constraints the rollouts project onto: on | off | a
    /// list of rope, jelly, snow, liquid, walls, contact, momentum, rebound, pressure. Repeat for a
    /// row per setting.
    #[arg(long = "constraints", value_name = "PARTS", default_value = "on")]
    constraints: Vec<Parts>,
    /// Refine the scenes onto an N x N grid with proportionally more particles (`simulate
    /// --grid`: `multi` at 128 has 10,000 particles, at 256 40,000), to measure the cost at
    /// scale.
    #[arg(long, value_parser = clap::value_parser!(u32).range(8..=4096))]
    grid: Option<u32>,
    /// Print a roofline under each grid model's row: each part of a call waited for on its
    /// own, its time, FLOPs and bytes against the GPU's limits (docs/speed.md, "Roofline by part").
    /// The waits make the rollout slower: time the rows without it.
    #[arg(long)]
    stages: bool,
    /// The GPU's memory bandwidth for the roofline, GB/s (H200: 4800; H100 SXM: 3350).
    #[arg(long, default_value_t = 4800.0, value_parser = crate::cli::flags::positive)]
    peak_gbs: f64,
    /// The GPU's dense arithmetic rate for the roofline, TFLOP/s (TF32 tensor cores: 495).
    #[arg(long, default_value_t = 495.0, value_parser = crate::cli::flags::positive)]
    peak_tflops: f64,
    #[command(flatten)]
    device: DeviceArgs,
}

/// The frames a scene's solver produced, `[N, 4]` physical each, and its materials.
struct Simulated {
    frames: Vec<Vec<f32>>,
    material: Vec<u8>,
    dt: f32,
}

/// Simulates `frames` frames (frame 0 included) of `scene`.
fn simulate(scene: Scene, frames: usize) -> anyhow::Result<Simulated> {
    let mut run = SceneRun::new(scene)?;
    let mut out = Vec::with_capacity(frames);
    let (mut material, mut dt) = (Vec::new(), 0.0);
    while out.len() < frames {
        let frame = run.next_frame().context("the scene ended early")??;
        let state: Vec<f32> = frame
            .position
            .chunks_exact(2)
            .zip(frame.velocity.chunks_exact(2))
            .flat_map(|(x, v)| [x[0], x[1], v[0], v[1]])
            .collect();
        material = frame.material;
        dt = frame.dt;
        out.push(state);
    }
    Ok(Simulated {
        frames: out,
        material,
        dt,
    })
}

/// One model's row: frames per call, seconds of all rollouts, mean scaled MSE, and with
/// `MINFLOW_CALL_STAGES=1` a grid call's mean milliseconds by stage and the calls timed
/// (`model::store::stages`).
struct Row {
    bundle: usize,
    seconds: f64,
    mse: f64,
    stages: Option<([f64; 4], usize)>,
    /// With `--stages`: each part's tally and the calls.
    roofline: Option<([Tally; 9], usize)>,
    /// Seconds of those spent in the constraint projection.
    projection: f64,
    /// Thread seconds of building the scenes' constraint data, and the scenes built.
    setup: (f64, usize),
}

/// The shape of a benchmark rollout.
#[derive(Debug, Clone, Copy)]
struct Sizes {
    /// Seed frames before the first prediction (the model's window T).
    window: usize,
    /// Frames predicted per rollout.
    horizon: usize,
    /// Scenes per call.
    batch: usize,
}

/// Rolls every scene out with `surrogate`, `sizes.batch` scenes per call, and scores it.
fn roll<B: NetOps>(
    surrogate: &Surrogate<B>,
    scenes: &[Simulated],
    sizes: Sizes,
) -> anyhow::Result<Row> {
    let Sizes {
        window: w,
        horizon: h,
        batch,
    } = sizes;
    let scaler = surrogate.meta().scaler;
    let (mut sum, mut count) = (0.0f64, 0usize);
    let mut seconds = 0.0;
    let _ = stages::take(); // Earlier calls (a warm-up) are not this row's.
    let _ = (
        stages::take_projection(),
        stages::take_setup(),
        roofline::take(),
    );
    for chunk in scenes.chunks(batch) {
        let cat =
            |k: usize| -> Vec<f32> { chunk.iter().flat_map(|s| s.frames[k].clone()).collect() };
        let material: Vec<u8> = chunk.iter().flat_map(|s| s.material.clone()).collect();
        let dt: Vec<f32> = chunk.iter().map(|s| s.dt).collect();
        let started = Instant::now();
        let seed: Vec<Vec<f32>> = (0..w).map(cat).collect();
        let mut preds: Vec<Vec<f32>> = Vec::with_capacity(h);
        let keep = |_, f| preds.push(f);
        surrogate.rollout_batch(Some(&cat(0)), &seed, &material, &dt, h, keep)?;
        seconds += started.elapsed().as_secs_f64();
        // Each predicted frame of the batch scored as one frame of all its particles: the mean
        // over particles and scaled features that `eval` reports as MSE.
        for (k, pred) in preds.iter().take(h).enumerate() {
            sum += frame_metrics(pred, &cat(w + k), &material, &scaler, 0).mse;
            count += 1;
        }
    }
    Ok(Row {
        bundle: surrogate.bundle(),
        seconds,
        mse: sum / count.max(1) as f64,
        stages: stages::take(),
        roofline: roofline::take(),
        projection: stages::take_projection(),
        setup: stages::take_setup(),
    })
}

/// Loads `dir` on the device the flags name and rolls the scenes out.
fn model_row(
    args: &RolloutBenchArgs,
    (dir, parts): (&std::path::Path, Parts),
    scenes: &[Simulated],
    sizes: Sizes,
) -> anyhow::Result<Row> {
    match args.device.parse()? {
        Device::Cpu => {
            let s = Surrogate::<crate::eval::CpuInfer>::load(dir, &Default::default())?
                .with_constraints(parts);
            roll(&s, scenes, sizes)
        }
        #[cfg(feature = "cuda")]
        Device::Cuda(ids) => {
            use crate::cli::device::cuda::{device, CudaInfer};
            let device = device(ids[0], args.device.kernels())?;
            let s = Surrogate::<CudaInfer>::load(dir, &device)?.with_constraints(parts);
            // One untimed rollout of a full call's scenes first: the kernels are compiled
            // (and autotuned) per tensor shape, so a warm-up with one scene left the timed
            // batches' compilation to the first model timed (a single-frame model listed
            // first read 2.3 ms a frame, the same model listed after another 0.5 ms). A
            // smaller last call (scenes not a multiple of --batch) still compiles its own.
            let warm = Sizes {
                horizon: sizes.horizon.min(8),
                ..sizes
            };
            roll(&s, &scenes[..sizes.batch.min(scenes.len())], warm)?;
            roll(&s, scenes, sizes)
        }
        #[cfg(not(feature = "cuda"))]
        Device::Cuda(_) => anyhow::bail!("built without CUDA"),
    }
}

/// Runs `minflow bench rollout`.
///
/// # Errors
/// A model that cannot be loaded or refuses the scenes, a scene the solver cannot run.
pub fn run(args: RolloutBenchArgs) -> anyhow::Result<Outcome> {
    roofline::enable(args.stages);
    let family = match args.family.as_str() {
        "fluid" => Family::Fluid,
        _ => Family::Multi,
    };
    let mut w = 1;
    for dir in &args.models {
        let meta = crate::model::store::RunFolder::new(dir).meta()?;
        w = w.max(meta.window());
    }
    let (h, frames) = (args.frames, w + args.frames);
    let threads = args.threads.unwrap_or_else(rayon::current_num_threads);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    // The solver: one scene per thread, frame 0 is the initial state (not simulated).
    let started = Instant::now();
    let specs = super::common::family_scenes(family, 0..args.scenes as u32, args.seed, args.grid)?;
    let scenes: anyhow::Result<Vec<Simulated>> = pool.install(|| {
        specs
            .par_iter()
            .map(|scene| simulate(scene.clone(), frames))
            .collect()
    });
    let scenes = scenes?;
    let solver_ms = started.elapsed().as_secs_f64() * 1e3 / (scenes.len() * (frames - 1)) as f64;
    let gpus = gpu_solver_ms(&args, &specs, frames)?;
    print_header(&args, (w, h, threads), solver_ms, gpus);
    let gpu_ms = gpus.map(|(read_back, _)| read_back);
    let versus_gpu = |ms: f64| gpu_ms.map_or(String::new(), |g| format!("{:.2}", ms / g));
    let mut settings = args.constraints.clone();
    settings.dedup();
    let rows = args
        .models
        .iter()
        .flat_map(|dir| settings.iter().map(move |&parts| (dir, parts)));
    let sizes = Sizes {
        window: w,
        horizon: h,
        batch: args.batch,
    };
    for (dir, parts) in rows {
        let row = pool
            .install(|| model_row(&args, (dir, parts), &scenes, sizes))
            .with_context(|| format!("rolling out {}", dir.display()))?;
        let ms = row.seconds * 1e3 / (scenes.len() * h) as f64;
        let name = match settings.len() {
            1 => dir.display().to_string(),
            _ => format!("{}[{parts}]", dir.display()),
        };
        let projection = row.projection * 1e3 / (scenes.len() * h) as f64;
        let setup = row.setup.0 * 1e3 / row.setup.1.max(1) as f64;
        println!(
            "| {name} | {} | {} | {ms:.3} | {:.2} | {} | {:.3e} | {projection:.3} ({:.0} %) | {setup:.2} |",
            row.bundle,
            h.div_ceil(row.bundle),
            ms / solver_ms,
            versus_gpu(ms),
            row.mse,
            100.0 * projection / ms.max(f64::MIN_POSITIVE)
        );
        if let Some(([input, record, device, output], calls)) = row.stages {
            println!(
                "|   stages, ms a call ({calls} calls): input {input:.2}, record {record:.2}, \
                 device {device:.2}, output {output:.2} | | | | | | | | |"
            );
        }
        if let Some((parts, calls)) = row.roofline {
            let peaks = super::roofline::Peaks {
                gbs: args.peak_gbs,
                tflops: args.peak_tflops,
            };
            super::roofline::print(&parts, calls, peaks);
        }
    }
    Ok(Outcome::Done)
}

/// Prints the run's settings, the table's header and the solver rows (the CPU solver's
/// `solver_ms` a frame on `threads` threads; the GPU solver's with its frames read back, the
/// "x GPU solver" baseline, and left on the device, when there is one).
fn print_header(
    args: &RolloutBenchArgs,
    (w, h, threads): (usize, usize, usize),
    solver_ms: f64,
    gpus: Option<(f64, f64)>,
) {
    println!(
        "{} {} scenes (seed {}), H = {h} frames after W = {w} seed frames, {threads} threads, \
         {} per call",
        args.scenes,
        args.family,
        args.seed,
        if args.batch == 1 {
            "1 scene".to_owned()
        } else {
            format!("{} scenes", args.batch)
        }
    );
    println!(
        "\n| predictor | K | calls/rollout | ms/frame | x solver | x GPU solver | avg{h} MSE | projection ms/frame (share) | its setup ms/scene |\n| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"
    );
    let versus_gpu = gpus.map_or(String::new(), |(g, _)| format!("{:.2}", solver_ms / g));
    println!(
        "| MPM solver (`simulate`, {threads} threads) | | | {solver_ms:.3} | 1.00 | {versus_gpu} | | | |"
    );
    if let Some((g, on_device)) = gpus {
        let batch = args.batch;
        println!(
            "| MPM solver on the GPU (`simulate --device cuda`, {batch} scenes a call; frames read \
             back, as the models') | | | {g:.4} | {:.3} | 1.00 | | | |",
            g / solver_ms
        );
        println!(
            "| MPM solver on the GPU, frames left on the device | | | {on_device:.4} | {:.3} | {:.2} \
             | | | |",
            on_device / solver_ms,
            on_device / g
        );
    }
}

/// With `--device cuda`: milliseconds per scene-frame of the same scenes on the GPU solver,
/// `--batch` scenes a call (`sim::gpu`), in steady state (after a first frame that compiles
/// its kernels and the frames that fill its substep-split window, not counting each batch's
/// upload): each frame read back to the host and kept, as the models' predicted frames are
/// (the baseline), and left on the device; `None` on the CPU.
#[cfg(feature = "cuda")]
fn gpu_solver_ms(
    args: &RolloutBenchArgs,
    scenes: &[Scene],
    frames: usize,
) -> anyhow::Result<Option<(f64, f64)>> {
    let ids = match args.device.parse()? {
        Device::Cuda(ids) => ids,
        Device::Cpu => return Ok(None),
    };
    let device = crate::cli::device::cuda::device(ids[0], args.device.kernels())?;
    // Steady state: `WARM` untimed frames (the substep split's speculation window fills),
    // then at least `TIMED` frames whatever the rollout's length.
    const WARM: u32 = 10;
    const TIMED: usize = 50;
    let timed = (frames - 1).max(TIMED);
    let window = crate::sim::gpu::RECENT as u32;
    let ms = |read_back: bool| -> anyhow::Result<f64> {
        let mut secs = 0.0;
        for chunk in scenes.chunks(args.batch) {
            let timing = (WARM, timed as u32);
            let row = super::sim_gpu::time_batch(&device, chunk, timing, window, read_back)?;
            secs += row.ms * 1e-3 * (chunk.len() * timed) as f64;
        }
        Ok(secs * 1e3 / (scenes.len() * timed) as f64)
    };
    Ok(Some((ms(true)?, ms(false)?)))
}

/// Without the `cuda` feature there is no GPU solver row.
#[cfg(not(feature = "cuda"))]
fn gpu_solver_ms(
    _: &RolloutBenchArgs,
    _: &[Scene],
    _: usize,
) -> anyhow::Result<Option<(f64, f64)>> {
    Ok(None)
}
