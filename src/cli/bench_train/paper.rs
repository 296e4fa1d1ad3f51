//! `minflow bench train --arch paper`: the paper's Table 4 on this machine, in one run: for each core,
//! trainable parameters, seconds per epoch (mean and max), microseconds per sample and peak
//! memory, on one fixed synthetic dataset, at each window length T; then the ratios
//! LSTM/minLSTM and GRU/minGRU (how much faster the minimal cores train).
//! `--device` picks the backend. Peak memory is the process's VmHWM on the CPU (reset before
//! each core, Linux `clear_refs`) and the largest pool cubecl holds on the GPU (sampled after
//! each epoch, freed before each core). `--warmup-epochs` run first and are left out of the
//! means (JIT compilation and autotuning on the GPU); their time is its own column. `wait %`
//! is the share of the epoch the host spent waiting for the device (near 100: device-bound;
//! low: bound by issuing the work); `data %` the share it waited for host batches (windows
//! assembled and scaled on a second thread). Used for `--arch paper`.

use crate::cli::device::{Device, DeviceArgs};
use crate::cli::train::CpuTrain;
use crate::cli::Outcome;
use crate::data::{Scaler, Trajectory, WindowIndex};
use crate::model::{CoreKind, LastActivation, ModelConfig};
use crate::ops::NetOps;
use crate::train::{TrainOptions, Trainer};
use burn::module::Module;
use burn::tensor::backend::AutodiffBackend;
use clap::Args;

#[derive(Debug, Args)]
pub struct TrainBenchArgs {
    /// Architecture: paper (the paper's Table 4) | grid (P2G -> U-Net -> G2P, docs/grid.md).
    #[arg(long, default_value = "paper", value_parser = ["paper", "grid"])]
    pub(super) arch: String,
    /// Window lengths T to measure (paper).
    #[arg(long, value_delimiter = ',', default_value = "2,32")]
    windows: Vec<usize>,
    /// Cores to measure [paper: mlp,lstm,gru,minlstm,mingru; grid: none,mingru,minlstm].
    #[arg(long, value_delimiter = ',')]
    pub(super) cores: Option<Vec<String>>,
    /// Samples (windows) per epoch.
    #[arg(long, default_value_t = 16, value_parser = crate::cli::flags::at_least_one)]
    pub(super) samples: usize,
    /// Epochs per core (the first includes warm-up).
    #[arg(long, default_value_t = 2, value_parser = crate::cli::flags::at_least_one)]
    pub(super) epochs: usize,
    /// Micro-batch (= batch) size.
    #[arg(long, default_value_t = 8, value_parser = crate::cli::flags::at_least_one)]
    pub(super) micro_batch: usize,
    /// Particles N.
    #[arg(long, default_value_t = 2500, value_parser = crate::cli::flags::at_least_one)]
    pub(super) particles: usize,
    /// Grid size n (grid).
    #[arg(long, default_value_t = 64, value_parser = crate::cli::flags::at_least_one)]
    pub(super) grid: usize,
    /// Rollout steps per sample P (grid).
    #[arg(long, default_value_t = 4, value_parser = crate::cli::flags::at_least_one)]
    pub(super) rollout_steps: usize,
    /// Convolution kernels to measure (grid): auto | burn | gather | shift.
    #[arg(long, value_delimiter = ',', default_value = "auto", value_parser = crate::cli::flags::conv_kernel)]
    pub(super) conv: Vec<crate::model::grid::ConvKernel>,
    /// Also time each stage of one step, forward + backward (grid).
    #[arg(long)]
    pub(super) stages: bool,
    /// Latent and core width W.
    #[arg(long, default_value_t = 1250)]
    width: usize,
    /// Encoder hidden width.
    #[arg(long, default_value_t = 256)]
    encoder_hidden: usize,
    /// Encoder's last activation: none (pool-then-project, cheap) | elu (the paper's).
    #[arg(long, default_value = "none")]
    encoder_last_activation: String,
    /// Epochs run before the measured ones and left out of the means (warm-up).
    #[arg(long, default_value_t = 0)]
    pub(super) warmup_epochs: usize,
    /// Split the long reductions of the per-particle layers' weight gradients into row
    /// chunks (on) or run each as one product (off: to measure what the split buys; the CPU
    /// backend has its own kernels and ignores it).
    #[arg(long, default_value = "on")]
    split_weight_grad: String,
    #[command(flatten)]
    pub(super) device: DeviceArgs,
}

/// A deterministic synthetic trajectory of `frames` frames (values uniform in [0, 1)).
pub(super) fn synthetic(n: usize, frames: usize) -> Trajectory {
    let mut s = 7u64;
    let mut next = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 40) as f32 / (1u64 << 24) as f32
    };
    let states = (0..frames * n * 4).map(|_| next()).collect();
    Trajectory {
        scene: "bench/synthetic/000".into(),
        dt: 0.016,
        material: (0..n).map(|p| (p % 4) as u8).collect(),
        start_index: 0,
        states,
        frames,
        n,
    }
}

/// Seconds per epoch of a benchmark run: the warm-up epochs' total, then the timed ones'
/// mean and maximum, and the mean seconds waiting for the device and for host batches.
pub(super) struct EpochMeans {
    pub warmup: f64,
    pub mean: f64,
    pub max: f64,
    pub wait: f64,
    pub data: f64,
}

impl EpochMeans {
    /// The means of `history` after its first `warmup_epochs`.
    pub fn of(history: &[crate::train::EpochRecord], warmup_epochs: usize) -> Self {
        let (warm, timed) = history.split_at(warmup_epochs.min(history.len()));
        let n = timed.len().max(1) as f64;
        let mean_of =
            |f: fn(&crate::train::EpochRecord) -> f64| timed.iter().map(f).sum::<f64>() / n;
        Self {
            warmup: warm.iter().map(|r| r.seconds).sum(),
            mean: mean_of(|r| r.seconds),
            max: timed.iter().map(|r| r.seconds).fold(0.0, f64::max),
            wait: mean_of(|r| r.wait_seconds),
            data: mean_of(|r| r.data_seconds),
        }
    }
}

/// Peak resident memory in MiB since the last reset, and a reset.
pub(super) fn peak_mib(reset: bool) -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let kb: f64 = status
        .lines()
        .find(|l| l.starts_with("VmHWM:"))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()?;
    if reset {
        let _ = std::fs::write("/proc/self/clear_refs", "5");
    }
    Some(kb / 1024.0)
}

/// The kernel choices the GPUs are opened with: `--gpu-gemm` and `--split-weight-grad`.
pub(super) fn kernels(args: &TrainBenchArgs) -> anyhow::Result<crate::ops::Kernels> {
    let split_weight_grad = match args.split_weight_grad.as_str() {
        "on" => true,
        "off" => false,
        other => anyhow::bail!("--split-weight-grad {other:?}: expected on | off"),
    };
    Ok(crate::ops::Kernels {
        split_weight_grad,
        ..args.device.kernels()
    })
}

#[cfg_attr(not(feature = "cuda"), allow(unused_variables))]
pub fn run(args: TrainBenchArgs) -> anyhow::Result<Outcome> {
    let kernels = kernels(&args)?;
    match args.device.parse()? {
        Device::Cpu => bench::<CpuTrain>(&args, vec![Default::default()], "host", &|reset| {
            peak_mib(reset)
        }),
        #[cfg(feature = "cuda")]
        Device::Cuda(ids) => {
            use crate::cli::device::cuda::{devices, reserved_bytes, CudaTrain};
            let devices = devices(&ids, kernels)?;
            // The largest pool on any one device.
            let peak = |reset: bool| {
                let mut most = None::<f64>;
                for device in &devices {
                    if reset {
                        <CudaTrain as burn::tensor::backend::Backend>::memory_cleanup(device);
                    }
                    if let Some(bytes) = reserved_bytes(device) {
                        let mib = bytes as f64 / (1 << 20) as f64;
                        most = Some(most.map_or(mib, |m| m.max(mib)));
                    }
                }
                most
            };
            println!("GPU products: --gpu-gemm {}", args.device.gpu_gemm);
            let memory = if ids.len() > 1 {
                "GPU pool (largest of the devices)"
            } else {
                "GPU pool"
            };
            bench::<CudaTrain>(&args, devices.clone(), memory, &peak)
        }
        #[cfg(not(feature = "cuda"))]
        Device::Cuda(_) => unreachable!("--device cuda is refused without the cuda feature"),
    }
}

/// The table on backend `B`; `peak(reset)` reads the memory column (and resets it).
fn bench<B: AutodiffBackend + NetOps>(
    args: &TrainBenchArgs,
    devices: Vec<B::Device>,
    memory: &str,
    peak: &dyn Fn(bool) -> Option<f64>,
) -> anyhow::Result<Outcome>
where
    B::InnerBackend: NetOps,
{
    let last = if args.encoder_last_activation == "elu" {
        LastActivation::Elu
    } else {
        LastActivation::None
    };
    println!(
        "N = {}, W = {}, encoder 5 -> {} -> {} ({:?}), micro-batch {}, {} samples/epoch, {} epochs (+{} warm-up), {}, {} threads",
        args.particles, args.width, args.encoder_hidden, args.width, last, args.micro_batch,
        args.samples, args.epochs, args.warmup_epochs, B::name(&devices[0]),
        rayon::current_num_threads()
    );
    if devices.len() > 1 {
        println!(
            "data parallel on {} devices (micro-batch {} each), weight-gradient split {}",
            devices.len(),
            args.micro_batch.div_ceil(devices.len()),
            args.split_weight_grad
        );
    }
    println!(
        "{:<8} {:>3} {:>11} {:>10} {:>10} {:>10} {:>10} {:>10} {:>7} {:>7} {:>9}",
        "core",
        "T",
        "params",
        "s/epoch",
        "max s",
        "us/sample",
        "samples/s",
        "warm-up s",
        "wait %",
        "data %",
        "peak MiB"
    );
    for &t in &args.windows {
        let traj = synthetic(args.particles, args.samples + t);
        let scaler = Scaler::fit(&[&traj]);
        let index = WindowIndex::new(vec![traj], t, scaler)?;
        let mut times = std::collections::BTreeMap::new();
        let default_cores = ["mlp", "lstm", "gru", "minlstm", "mingru"].map(String::from);
        for name in args.cores.as_deref().unwrap_or(&default_cores) {
            let core =
                CoreKind::parse(name).ok_or_else(|| anyhow::anyhow!("unknown core {name:?}"))?;
            let mean = bench_core::<B>(args, core, (&index, &scaler, t), &devices, (last, peak))?;
            times.insert(core.name(), mean);
        }
        for (classic, minimal) in [("lstm", "minlstm"), ("gru", "mingru")] {
            if let (Some(a), Some(b)) = (times.get(classic), times.get(minimal)) {
                println!(
                    "  T = {t}: {classic}/{minimal} time per epoch = {:.2}x",
                    a / b
                );
            }
        }
    }
    println!("peak MiB: {memory} memory");
    Ok(Outcome::Done)
}

/// One row of the paper table: trains `core` at window `t` for the benchmark's epochs on
/// `index` and prints its speed and memory; returns the mean seconds per epoch.
fn bench_core<B: AutodiffBackend + NetOps>(
    args: &TrainBenchArgs,
    core: CoreKind,
    (index, scaler, t): (&WindowIndex, &Scaler, usize),
    devices: &[B::Device],
    (last, peak): (LastActivation, &dyn Fn(bool) -> Option<f64>),
) -> anyhow::Result<f64>
where
    B::InnerBackend: NetOps,
{
    let config = ModelConfig::new(core, args.particles)
        .with_window(t)
        .with_width(args.width)
        .with_encoder_hidden(args.encoder_hidden)
        .with_encoder_last_activation(last);
    let params = config.init::<CpuTrain>(&Default::default()).num_params();
    let opts = TrainOptions {
        epochs: args.warmup_epochs + args.epochs,
        batch_size: args.micro_batch,
        micro_batch: args.micro_batch,
        lr: 1e-3,
        seed: 0,
        patience: 0,
        density_grid: 32,
        density_weight: 0.1,
    };
    let dir = tempfile::tempdir()?;
    let mut high = peak(true).unwrap_or(0.0);
    let history = Trainer::<B>::data_parallel(config, opts, dir.path().into(), devices.to_vec())
        .fit(&index, None, &scaler, false, |_, _| {
            high = high.max(peak(false).unwrap_or(f64::NAN));
        })?;
    let EpochMeans {
        warmup,
        mean,
        max,
        wait,
        data,
    } = EpochMeans::of(&history, args.warmup_epochs);
    let us = mean * 1e6 / index.len() as f64;
    println!(
        "{:<8} {:>3} {:>11} {:>10.3} {:>10.3} {:>10.0} {:>10.0} {:>10.2} {:>7.0} {:>7.0} {:>9.0}",
        core.name(),
        t,
        params,
        mean,
        max,
        us,
        index.len() as f64 / mean,
        warmup,
        100.0 * wait / mean.max(1e-12),
        100.0 * data / mean.max(1e-12),
        high
    );
    Ok(mean)
}
