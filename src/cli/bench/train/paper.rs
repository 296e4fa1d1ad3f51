//! `minflow bench train --arch paper`: the paper's Table 4 on this machine, in one run: for
//! each core, trainable parameters, seconds per epoch (mean and max), microseconds per sample
//! and peak memory, on one fixed synthetic dataset, at each window length T; then the ratios
//! LSTM/minLSTM and GRU/minGRU (how much faster the minimal cores train). `--device` picks the
//! backend. Peak memory is the process's VmHWM on the CPU (reset before each core, Linux
//! `clear_refs`) and the largest pool cubecl holds on the GPU (sampled after each epoch, freed
//! before each core). `--warmup-epochs` run first and are left out of the means (JIT
//! compilation and autotuning on the GPU); their time is its own column. `wait %` is the share
//! of the epoch the host spent waiting for the device (near 100: device-bound; low: bound by
//! issuing the work); `data %` the share it waited for host batches (windows assembled and
//! scaled on a second thread). Used for `--arch paper`.

use super::{kernels, TrainBenchArgs};
use crate::cli::bench::common::{peak_mib, synthetic, EpochMeans};
use crate::cli::device::Device;
use crate::cli::train::CpuTrain;
use crate::cli::Outcome;
use crate::data::{Scaler, WindowIndex};
use crate::model::{CoreKind, LastActivation, ModelConfig};
use crate::ops::NetOps;
use crate::train::{TrainOptions, Trainer};
use burn::module::Module;
use burn::tensor::backend::AutodiffBackend;

/// Runs `minflow bench train --arch paper`: the table on `--device`.
///
/// # Errors
/// Bad flags, a failed training epoch.
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
