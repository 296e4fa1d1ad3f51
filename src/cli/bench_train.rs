//! `minflow bench train`: the paper's Table 4 on this machine, in one run: for each core,
//! trainable parameters, seconds per epoch (mean and max), microseconds per sample and peak
//! resident memory, on one fixed synthetic dataset, at each window length T; then the
//! ratios LSTM/minLSTM and GRU/minGRU (how much faster the minimal cores train).
//! Peak memory is the process's VmHWM, reset before each core (Linux `clear_refs`).

use super::train::CpuTrain;
use super::Outcome;
use crate::data::{Scaler, Trajectory, WindowIndex};
use crate::model::{CoreKind, LastActivation, ModelConfig};
use crate::train::{TrainOptions, Trainer};
use burn::module::Module;
use clap::Args;

#[derive(Debug, Args)]
pub struct TrainBenchArgs {
    /// Window lengths T to measure.
    #[arg(long, value_delimiter = ',', default_value = "2,32")]
    windows: Vec<usize>,
    /// Cores to measure.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "mlp,lstm,gru,minlstm,mingru"
    )]
    cores: Vec<String>,
    /// Samples (windows) per epoch.
    #[arg(long, default_value_t = 16)]
    samples: usize,
    /// Epochs per core (the first includes warm-up).
    #[arg(long, default_value_t = 2)]
    epochs: usize,
    /// Micro-batch (= batch) size.
    #[arg(long, default_value_t = 8)]
    micro_batch: usize,
    /// Particles N.
    #[arg(long, default_value_t = 2500)]
    particles: usize,
    /// Latent and core width W.
    #[arg(long, default_value_t = 1250)]
    width: usize,
    /// Encoder hidden width.
    #[arg(long, default_value_t = 256)]
    encoder_hidden: usize,
    /// Encoder's last activation: none (pool-then-project, cheap) | elu (the paper's).
    #[arg(long, default_value = "none")]
    encoder_last_activation: String,
}

/// A deterministic synthetic trajectory of `frames` frames.
fn synthetic(n: usize, frames: usize) -> Trajectory {
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

/// Peak resident memory in MiB since the last reset, and a reset.
fn peak_mib(reset: bool) -> Option<f64> {
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

pub fn run(args: TrainBenchArgs) -> anyhow::Result<Outcome> {
    let last = if args.encoder_last_activation == "elu" {
        LastActivation::Elu
    } else {
        LastActivation::None
    };
    println!(
        "N = {}, W = {}, encoder 5 -> {} -> {} ({:?}), micro-batch {}, {} samples/epoch, {} epochs, {} threads",
        args.particles, args.width, args.encoder_hidden, args.width, last, args.micro_batch, args.samples, args.epochs,
        rayon::current_num_threads()
    );
    println!(
        "{:<8} {:>3} {:>11} {:>10} {:>10} {:>10} {:>9}",
        "core", "T", "params", "s/epoch", "max s", "us/sample", "peak MiB"
    );
    for &t in &args.windows {
        let traj = synthetic(args.particles, args.samples + t);
        let scaler = Scaler::fit(&[&traj]);
        let index = WindowIndex::new(vec![traj], t, scaler)?;
        let mut times = std::collections::BTreeMap::new();
        for name in &args.cores {
            let core =
                CoreKind::parse(name).ok_or_else(|| anyhow::anyhow!("unknown core {name:?}"))?;
            let config = ModelConfig::new(core, args.particles)
                .with_window(t)
                .with_width(args.width)
                .with_encoder_hidden(args.encoder_hidden)
                .with_encoder_last_activation(last);
            let params = config.init::<CpuTrain>(&Default::default()).num_params();
            let opts = TrainOptions {
                epochs: args.epochs,
                batch_size: args.micro_batch,
                micro_batch: args.micro_batch,
                lr: 1e-3,
                seed: 0,
                patience: 0,
                density_grid: 32,
                density_weight: 0.1,
            };
            let dir = tempfile::tempdir()?;
            peak_mib(true);
            let history = Trainer::<CpuTrain>::new(
                config,
                opts,
                dir.path().into(),
                Default::default(),
            )
            .fit(&index, None, &scaler, false, |_, _| {})?;
            let peak = peak_mib(false).unwrap_or(f64::NAN);
            let mean = history.iter().map(|r| r.seconds).sum::<f64>() / history.len() as f64;
            let max = history.iter().map(|r| r.seconds).fold(0.0, f64::max);
            let us = mean * 1e6 / index.len() as f64;
            times.insert(core.name(), mean);
            println!(
                "{:<8} {:>3} {:>11} {:>10.2} {:>10.2} {:>10.0} {:>9.0}",
                core.name(),
                t,
                params,
                mean,
                max,
                us,
                peak
            );
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
    Ok(Outcome::Done)
}
