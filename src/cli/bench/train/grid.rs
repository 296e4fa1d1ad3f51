//! `minflow bench train --arch grid`: the grid architecture's training speed on this machine,
//! in one run: for each memory core and convolution kernel, trainable parameters, seconds per
//! epoch, samples per second, warm-up, `wait %` / `data %` (as for the paper's model), peak
//! memory and the first epoch's training loss (kernels that compute the same function, such as
//! the `--conv` choices, start from the same weights and data, so it agrees between them to
//! float rounding: a check of the kernels on the device), training with [`GridTrainer`]
//! (rollout loss over P steps, clipping, Adam) on one fixed synthetic dataset; with `--stages`,
//! the time of one forward + backward pass of each stage of a step (stencil, P2G, U-Net, G2P,
//! memory, the whole step) at the same batch size, each synchronised with the device, to show
//! where a step's time goes; with `--feed`, instead of training, the rate at which the
//! trainer's feed prepares the same batches for 1, 2 and 4 devices.

use std::time::Instant;

use burn::module::Module;
use burn::tensor::backend::{AutodiffBackend, Backend};
use burn::tensor::{Distribution, Tensor};

use super::{kernels, TrainBenchArgs};
use crate::cli::bench::common::{peak_mib, synthetic, EpochMeans};
use crate::cli::Outcome;
use crate::data::{Layout, Scaler, WindowIndex};
use crate::model::grid::{
    one_hot, transfer, GridConfig, Memory, MemoryKind, MemoryState, StepInput, UNetConfig,
};
use crate::ops::NetOps;
use crate::train::grid::{feed_rate, fit_stats, GridTrainOptions, GridTrainer};
use crate::train::Quiet;

/// The grid table on backend `B` over `devices` (data-parallel when more than one, the
/// first the main one); `peak(reset)` reads the memory column (and resets it).
pub fn bench<B: AutodiffBackend + NetOps>(
    args: &TrainBenchArgs,
    devices: Vec<B::Device>,
    memory: &str,
    peak: &dyn Fn(bool) -> Option<f64>,
) -> anyhow::Result<Outcome>
where
    B::InnerBackend: NetOps,
{
    let device = devices[0].clone();
    let cores = match &args.cores {
        Some(cores) => cores.clone(),
        None => vec!["none".into(), "mingru".into(), "minlstm".into()],
    };
    let (t, p) = (2, args.rollout_steps);
    // A sample of the small shape rolls out P calls of K = 4 frames.
    let span = t + p * shaped(GridConfig::new(MemoryKind::None), &args.shape).bundle - 1;
    let traj = synthetic(args.particles, args.samples + span);
    let stats = fit_stats(&[&traj]);
    // Batches as `train` writes them for this many devices.
    let mut index = WindowIndex::new(vec![traj], span, Scaler::default())?
        .with_layout(Layout::frames_for(devices.len()));
    println!(
        "grid architecture ({} shape): N = {}, n = {}, T = {t}, P = {p}, batch {}, {} samples/epoch, {} epochs (+{} warm-up), {} x {}",
        args.shape, args.particles, args.grid, args.micro_batch, index.len(), args.epochs, args.warmup_epochs,
        devices.len(), B::name(&device)
    );
    if args.feed {
        println!("{:<7} {:>10} {:>10}", "shares", "s/epoch", "samples/s");
        // One untimed epoch first: the allocator's first pages of a batch cost more.
        index = index.with_layout(Layout::Frames);
        feed_rate(&index, args.micro_batch, 1);
        for shares in [1, 2, 4] {
            index = index.with_layout(Layout::frames_for(shares));
            let rate = feed_rate(&index, args.micro_batch, shares);
            let seconds = index.len() as f64 / rate;
            println!("{shares:<7} {seconds:>10.3} {rate:>10.1}");
        }
        return Ok(Outcome::Done);
    }
    println!(
        "{:<8} {:<7} {:>9} {:>10} {:>10} {:>10} {:>7} {:>7} {:>9} {:>12}",
        "core",
        "conv",
        "params",
        "s/epoch",
        "samples/s",
        "warm-up s",
        "wait %",
        "data %",
        "peak MiB",
        "loss 1"
    );
    for name in &cores {
        let memory_kind = MemoryKind::parse(name).ok_or_else(|| {
            anyhow::anyhow!(
                "unknown core {name:?} for --arch grid (none | mingru | minlstm | gru | lstm)"
            )
        })?;
        for &kernel in &args.conv {
            let config = shaped(GridConfig::new(memory_kind), &args.shape)
                .with_grid(args.grid)
                .with_window(t)
                .with_vel_scale(stats.vel_scale)
                .with_dv_mean(stats.dv_mean)
                .with_dv_scale(stats.dv_scale)
                .with_conv(kernel);
            config.validate().map_err(anyhow::Error::msg)?;
            bench_config::<B>(args, &config, (&index, &devices), p, peak)?;
            if args.stages {
                stages::<B>(&config, args.micro_batch, args.particles, &device);
            }
        }
    }
    println!("peak MiB: {memory} memory");
    Ok(Outcome::Done)
}

/// `config` in the `--shape` named: `full` as it is (`train`'s default flags), `small` the
/// demo's network (`models/all-grid-mingru-small-k4-long`).
fn shaped(config: GridConfig, shape: &str) -> GridConfig {
    match shape {
        "small" => config
            .with_unet_width(16)
            .with_levels(3)
            .with_latent(32)
            .with_hidden(32)
            .with_head_hidden(64)
            .with_bundle(4)
            .with_reference(true),
        _ => config,
    }
}

/// One row of the grid table: trains `config` for the benchmark's epochs on `index` (P =
/// `p` rollout steps) and prints its speed, memory and first loss.
fn bench_config<B: AutodiffBackend + NetOps>(
    args: &TrainBenchArgs,
    config: &GridConfig,
    (index, devices): (&WindowIndex, &[B::Device]),
    p: usize,
    peak: &dyn Fn(bool) -> Option<f64>,
) -> anyhow::Result<()>
where
    B::InnerBackend: NetOps,
{
    let device = &devices[0];
    let params = config.init::<B>(device).num_params();
    let opts = GridTrainOptions {
        epochs: args.warmup_epochs + args.epochs,
        batch_size: args.micro_batch,
        lr_final: 1e-5,
        clip: 1.0,
        steps: p,
        ..GridTrainOptions::default()
    };
    let dir = tempfile::tempdir()?;
    let mut high = peak(true).unwrap_or(0.0);
    let trainer = GridTrainer::<B> {
        config: config.clone(),
        opts,
        out: dir.path().into(),
        device: device.clone(),
        replicas: devices[1..].to_vec(),
        init_from: None,
        share: Default::default(),
        dataset: Default::default(),
    };
    let history = trainer.fit(&mut { index }, &[], &Scaler::default(), false, &mut Quiet)?;
    high = high.max(peak(false).unwrap_or(f64::NAN));
    let EpochMeans {
        warmup,
        mean,
        wait,
        data,
        ..
    } = EpochMeans::of(&history, args.warmup_epochs);
    println!(
        "{:<8} {:<7} {:>9} {:>10.3} {:>10.1} {:>10.2} {:>7.0} {:>7.0} {:>9.0} {:>12.6e}",
        config.memory.name(),
        config.conv.resolve::<B>().name(),
        params,
        mean,
        index.len() as f64 / mean,
        warmup,
        100.0 * wait / mean.max(1e-12),
        100.0 * data / mean.max(1e-12),
        high,
        history.first().map_or(f64::NAN, |e| e.train_loss)
    );
    Ok(())
}

/// Milliseconds per call of `f`, after one untimed call, synchronised with the device.
fn timed<B: Backend>(device: &B::Device, repeats: usize, mut f: impl FnMut()) -> f64 {
    f();
    let _ = B::sync(device);
    let started = Instant::now();
    for _ in 0..repeats {
        f();
    }
    let _ = B::sync(device);
    started.elapsed().as_secs_f64() * 1e3 / repeats.max(1) as f64
}

/// One line: forward + backward milliseconds of each stage of a step of `config` at batch
/// `b`, and the whole step.
fn stages<B: AutodiffBackend + NetOps>(
    config: &GridConfig,
    b: usize,
    n_p: usize,
    device: &B::Device,
) {
    let normal = Distribution::Normal(0.0, 1.0);
    let n = config.grid;
    let dense = B::dense_stencil();
    let pos = Tensor::<B, 3>::random([b, n_p, 2], Distribution::Uniform(0.05, 0.95), device);
    let s = transfer::stencil(pos.clone(), n, dense);
    let repeats = 5;
    let stencil = timed::<B>(device, repeats, || {
        let _ = transfer::stencil(pos.clone(), n, dense);
    });
    let c_in = config.grid_channels();
    let values = Tensor::<B, 3>::random([b, n_p, c_in], normal, device).require_grad();
    let p2g = timed::<B>(device, repeats, || {
        let _ = transfer::p2g(&s, values.clone()).sum().backward();
    });
    // A bundled network's U-Net hands back K latent fields, one a frame.
    let fields = config.latent * config.bundle;
    let unet = UNetConfig::new(c_in, fields)
        .with_width(config.unet_width)
        .with_levels(config.levels)
        .with_conv(config.conv)
        .init::<B>(device);
    let grid = Tensor::<B, 4>::random([b, n, n, c_in], normal, device).require_grad();
    let unet_ms = timed::<B>(device, repeats, || {
        let _ = unet.forward(grid.clone()).sum().backward();
    });
    let latent = Tensor::<B, 3>::random([b, n * n, fields], normal, device).require_grad();
    let g2p = timed::<B>(device, repeats, || {
        let _ = transfer::g2p(&s, latent.clone()).sum().backward();
    });
    let d_u = config.latent + config.own_features();
    let memory = Memory::<B>::new(config.memory, d_u, config.hidden, device);
    let u = Tensor::<B, 2>::random([b * n_p, d_u], normal, device).require_grad();
    let memory_ms = timed::<B>(device, repeats, || {
        if let (Some(out), _) = memory.step(u.clone(), MemoryState::Empty) {
            let _ = out.sum().backward();
        }
    });
    let model = config.init::<B>(device);
    let material: Vec<u8> = (0..b * n_p).map(|i| (i % 4) as u8).collect();
    let input = StepInput {
        pos: pos.clone(),
        vel: Tensor::random([b, n_p, 2 * config.window], normal, device).require_grad(),
        material: one_hot(&material, config.materials, b, n_p, device),
        dt: Tensor::ones([b], device).mul_scalar(0.016),
        reference: None,
        rest: None,
        deformation: None,
    };
    let step = timed::<B>(device, repeats, || {
        let (out, _) = model.step(input.clone(), MemoryState::Empty);
        let _ = (out.pos.sum() + out.vel.sum()).backward();
    });
    println!(
        "  ms per forward + backward at batch {b}: stencil {stencil:.2} (forward), P2G {p2g:.2}, U-Net {unet_ms:.2}, G2P {g2p:.2}, memory {memory_ms:.2}, whole step {step:.2}"
    );
}

/// `--arch grid` on the chosen devices (a list: data-parallel; the memory column is the
/// main device's).
#[cfg_attr(not(feature = "cuda"), allow(unused_variables))]
pub fn run(args: &TrainBenchArgs) -> anyhow::Result<Outcome> {
    use crate::cli::device::Device;
    use crate::cli::train::CpuTrain;
    let kernels = kernels(args)?;
    match args.device.parse()? {
        Device::Cpu => bench::<CpuTrain>(args, vec![Default::default()], "host", &|reset| {
            peak_mib(reset)
        }),
        #[cfg(feature = "cuda")]
        Device::Cuda(ids) => {
            use crate::cli::device::cuda::{devices, reserved_bytes, CudaTrain};
            let devices = devices(&ids, kernels)?;
            let main = devices[0].clone();
            let peak = |reset: bool| {
                if reset {
                    <CudaTrain as burn::tensor::backend::Backend>::memory_cleanup(&main);
                }
                reserved_bytes(&main).map(|b| b as f64 / (1 << 20) as f64)
            };
            bench::<CudaTrain>(args, devices, "GPU pool", &peak)
        }
        #[cfg(not(feature = "cuda"))]
        Device::Cuda(_) => unreachable!("--device cuda is refused without the cuda feature"),
    }
}
