//! `minflow bench train [--arch grid|paper]`: training speed on this machine, one command for
//! both architectures. This file holds the flags ([`TrainBenchArgs`]) and the kernel choice
//! both take; [`paper`] measures the paper's Table 4 (per core, parameters, seconds per epoch,
//! microseconds per sample, peak memory), [`grid`] the grid architecture (and its stages).
//! The synthetic data, epoch means and peak memory they share are in `bench/common.rs`.

mod grid;
mod paper;

use clap::Args;

use crate::cli::device::DeviceArgs;
use crate::cli::Outcome;

/// The flags of `minflow bench train`, both architectures.
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
    /// The grid network's shape: full (the default flags of `train`: U-Net width 32, 4
    /// levels, K = 1) | small (the demo's `-small-k4-long`: width 16, 3 levels, latent and
    /// hidden 32, head 64, K = 4 frames a call, reference channels).
    #[arg(long, default_value = "full", value_parser = ["full", "small"])]
    pub(super) shape: String,
    /// Rollout steps per sample P (grid).
    #[arg(long, default_value_t = 4, value_parser = crate::cli::flags::at_least_one)]
    pub(super) rollout_steps: usize,
    /// Convolution kernels to measure (grid): auto | burn | gather | shift.
    #[arg(long, value_delimiter = ',', default_value = "auto", value_parser = crate::cli::flags::conv_kernel)]
    pub(super) conv: Vec<crate::model::grid::ConvKernel>,
    /// Also time each stage of one step, forward + backward (grid).
    #[arg(long)]
    pub(super) stages: bool,
    /// Time the batch feed alone instead of training (grid): the samples/s at which the host
    /// assembles and packs batches for 1, 2 and 4 shares (devices), which no training step on
    /// any number of GPUs can beat.
    #[arg(long)]
    pub(super) feed: bool,
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

/// Runs `minflow bench train`: the architecture `--arch` names.
///
/// # Errors
/// Bad flags, a failed training epoch.
pub fn run(args: TrainBenchArgs) -> anyhow::Result<Outcome> {
    match args.arch.as_str() {
        "grid" => grid::run(&args),
        _ => paper::run(args),
    }
}
