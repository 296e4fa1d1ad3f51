//! `minflow train --arch grid` (the default): the grid architecture's flags ([`GridArgs`],
//! flattened into `train`'s) and its run: load the bags, split 80:10:10 by scene, fit the
//! min-max scaler and the velocity statistics on the training split, train with
//! [`crate::train::grid::GridTrainer`] (rollout loss, clipping, cosine decay, best
//! checkpoint by validation rollout error) and leave the run folder as `train --arch paper`
//! does (`model.json` + `model.mpk`, `checkpoint/`, `metrics.csv`, `loss.png`,
//! `split.json`, `train.json`).

use std::path::PathBuf;

use anyhow::{bail, Context};
use burn::tensor::backend::AutodiffBackend;
use clap::Args;

use super::device::Device;
use super::train::{check_resume, CpuTrain, Progress, TrainArgs};
use super::Outcome;
use crate::data::{self, Scaler, Split, Trajectory, WindowIndex};
use crate::model::grid::{ConvKernel, GridConfig, MemoryKind};
use crate::model::store::NetConfig;
use crate::ops::NetOps;
use crate::train::grid::{fit_stats, GridTrainOptions, GridTrainer};
use crate::train::{EpochRecord, Observer, TrainError};

/// The grid network's sizes (`train` and `report`).
#[derive(Debug, Clone, Args)]
pub struct GridNetArgs {
    /// Grid size n of P2G / U-Net / G2P (a multiple of 2^(levels - 1)).
    #[arg(long, default_value_t = 64, value_parser = super::flags::at_least_one)]
    pub grid: usize,
    /// U-Net first-level width (channels).
    #[arg(long, default_value_t = 32, value_parser = super::flags::at_least_one)]
    pub unet_width: usize,
    /// U-Net resolutions.
    #[arg(long, default_value_t = 4, value_parser = super::flags::at_least_one)]
    pub levels: usize,
    /// Channels the U-Net hands back to the particles.
    #[arg(long, default_value_t = 32, value_parser = super::flags::at_least_one)]
    pub latent: usize,
    /// Hidden state values per particle (memory cores).
    #[arg(long, default_value_t = 32, value_parser = super::flags::at_least_one)]
    pub hidden: usize,
    /// Per-particle head width.
    #[arg(long, default_value_t = 64, value_parser = super::flags::at_least_one)]
    pub head_hidden: usize,
}

impl GridNetArgs {
    /// These flags as `train` takes them (what `report` prints to reproduce a run).
    pub fn argv(&self) -> Vec<String> {
        [
            ("--grid", self.grid),
            ("--unet-width", self.unet_width),
            ("--levels", self.levels),
            ("--latent", self.latent),
            ("--hidden", self.hidden),
            ("--head-hidden", self.head_hidden),
        ]
        .into_iter()
        .flat_map(|(flag, value)| [flag.to_owned(), value.to_string()])
        .collect()
    }
}

/// Flags of the grid architecture (ignored by `--arch paper`).
#[derive(Debug, Clone, Args)]
pub struct GridArgs {
    #[command(flatten)]
    pub net: GridNetArgs,
    /// How the U-Net's convolutions run: auto (gather on the CPU, shift on a GPU) | burn |
    /// gather | shift (the same weights and results; `bench train --arch grid` compares them).
    #[arg(long, default_value = "auto", value_parser = super::flags::conv_kernel)]
    pub conv: ConvKernel,
    /// Steps per training sample P (a short rollout; the loss averages them).
    #[arg(long, default_value_t = 4, value_parser = super::flags::at_least_one)]
    pub rollout_steps: usize,
    /// Of those, steps that read the true frame (the rest read the model's own predictions).
    #[arg(long, default_value_t = 1, value_parser = super::flags::at_least_one)]
    pub teacher_steps: usize,
    /// Gaussian noise on the true input velocities, in units of the velocity change's
    /// standard deviation.
    #[arg(long, default_value_t = 0.0, value_parser = super::flags::non_negative_f32)]
    pub noise: f32,
    /// Gradient-norm clipping threshold (0: off).
    #[arg(long, default_value_t = 1.0, value_parser = super::flags::non_negative_f32)]
    pub clip: f32,
    /// Learning rate at the end of the cosine decay.
    #[arg(long, default_value_t = 1e-5, value_parser = super::flags::non_negative)]
    pub lr_final: f64,
    /// Samples per epoch at most (0: every window).
    #[arg(long, default_value_t = 0)]
    pub samples_per_epoch: usize,
    /// Validation rollouts per validation scene.
    #[arg(long, default_value_t = 3, value_parser = super::flags::at_least_one)]
    pub val_starts: usize,
    /// Validation rollout length (frames).
    #[arg(long, default_value_t = 20, value_parser = super::flags::at_least_one)]
    pub val_horizon: usize,
    /// Stop after this many minutes of training (the epoch in progress is cut short,
    /// validated and kept; 0: no limit).
    #[arg(long, default_value_t = 0.0, value_parser = super::flags::non_negative)]
    pub max_minutes: f64,
    /// Start from the weights of this run folder (fine-tuning, or continuing a finished run
    /// with a new learning-rate schedule) instead of fresh ones. Its architecture must be the
    /// one these flags describe; its normalisation constants are kept.
    #[arg(long, value_name = "DIR", conflicts_with = "resume")]
    pub init_from: Option<PathBuf>,
}

impl TrainArgs {
    /// The grid network these flags describe (normalisation constants still at their
    /// defaults: [`fit_stats`] fills them from the training split).
    ///
    /// # Errors
    /// An unknown core or a size out of range, naming the flag (a [`super::UsageError`]).
    pub fn grid_config(&self) -> anyhow::Result<GridConfig> {
        self.checked_grid_config()
            .map_err(|e| super::UsageError(format!("{e:#}")).into())
    }

    fn checked_grid_config(&self) -> anyhow::Result<GridConfig> {
        let memory = match self.model.as_str() {
            "mlp" => MemoryKind::None,
            name => MemoryKind::parse(name).with_context(|| {
                format!("unknown --model {name:?} for --arch grid (none | mingru | minlstm | gru | lstm)")
            })?,
        };
        let g = &self.grid_args;
        let config = GridConfig::new(memory)
            .with_grid(g.net.grid)
            .with_window(self.window)
            .with_unet_width(g.net.unet_width)
            .with_levels(g.net.levels)
            .with_latent(g.net.latent)
            .with_hidden(g.net.hidden)
            .with_head_hidden(g.net.head_hidden)
            .with_conv(g.conv);
        config
            .validate()
            .map_err(|e| anyhow::anyhow!("--arch grid: {e}"))?;
        if g.rollout_steps == 0 || g.teacher_steps == 0 || g.teacher_steps > g.rollout_steps {
            bail!("--rollout-steps must be at least 1 and --teacher-steps in 1..=--rollout-steps");
        }
        if !(g.noise >= 0.0 && g.clip >= 0.0 && self.lr > 0.0 && g.lr_final >= 0.0) {
            bail!("--noise, --clip and --lr-final must be >= 0 and --lr > 0");
        }
        if self.batch_size == 0 || self.epochs == 0 || g.val_horizon == 0 {
            bail!("--batch-size, --epochs and --val-horizon must be at least 1");
        }
        Ok(config)
    }

    /// The grid run's optimisation settings.
    pub fn grid_options(&self) -> GridTrainOptions {
        let g = &self.grid_args;
        GridTrainOptions {
            epochs: self.epochs,
            batch_size: self.batch_size,
            samples_per_epoch: g.samples_per_epoch,
            lr: self.lr,
            lr_final: g.lr_final,
            clip: g.clip,
            steps: g.rollout_steps,
            teacher: g.teacher_steps,
            noise: g.noise,
            seed: self.seed,
            patience: self.patience,
            val_starts: g.val_starts,
            val_horizon: g.val_horizon,
            max_minutes: g.max_minutes,
        }
    }
}

/// Runs `train --arch grid`.
///
/// # Errors
/// Bad flags (before any data is read), unreadable bags, no training scenes, training errors.
pub fn run(args: TrainArgs) -> anyhow::Result<Outcome> {
    let mut config = args.grid_config()?;
    let opts = args.grid_options();
    let device = args.device.parse()?;
    let init = match &args.grid_args.init_from {
        Some(dir) => Some(init_normalisation(dir, &config)?),
        None => None,
    };
    let topic = Some(args.topic.as_str());
    let (trajs, report) = data::load(&args.data, topic).context("loading trajectories")?;
    for gap in &report.gaps {
        tracing::warn!("{gap}");
    }
    let mut scenes: Vec<String> = trajs.iter().map(|t| t.scene.clone()).collect();
    scenes.dedup();
    let split = Split::new(&scenes, args.seed);
    let (train, val, test) = split.partition(trajs);
    if train.is_empty() {
        bail!("no training scenes in {:?}", args.data);
    }
    let refs: Vec<&Trajectory> = train.iter().collect();
    let scaler = Scaler::fit(&refs);
    // Weights from --init-from were trained against their run's normalisation: keep it.
    let (vel_scale, dv_mean, dv_scale) = init.unwrap_or_else(|| fit_stats(&refs));
    config.vel_scale = vel_scale;
    config.dv_mean = dv_mean;
    config.dv_scale = dv_scale;
    if args.resume {
        check_resume(&args.out, &NetConfig::Grid(config.clone()))?;
    }
    super::train::write_run_files(&args.out, &split, &opts)?;
    let index = WindowIndex::new(train, config.window + opts.steps - 1, Scaler::default())?;
    let counts: Vec<usize> = index.particle_counts();
    eprintln!(
        "{} scenes: {} train ({} samples), {} val, {} test; grid architecture, {} memory, n = {}, T = {}, P = {} (teacher {}), N = {counts:?}",
        scenes.len(),
        index.trajectories().len(),
        index.len(),
        val.len(),
        test.len(),
        config.memory.name(),
        config.grid,
        config.window,
        opts.steps,
        opts.teacher,
    );
    if index.is_empty() {
        return Err(super::UsageError(format!(
            "--window {}: no training samples: every training scene has fewer than the T + P - \
             1 = {} frames a sample needs (lower --window or --rollout-steps)",
            config.window,
            index.t()
        ))
        .into());
    }
    let mut progress = Progress::new(args.out.clone());
    let history = fit_on(
        (&device, args.device.kernels()),
        (
            config,
            opts,
            args.out.clone(),
            args.grid_args.init_from.clone(),
        ),
        &index,
        &val,
        &scaler,
        args.resume,
        &mut progress,
    )?;
    super::train::print_best(&history, "validation rollout MSE", &args.out);
    Ok(super::read_to_damage(&report.truncated))
}

/// The normalisation constants `(vel_scale, dv_mean, dv_scale)` of the grid model in `dir`
/// (`--init-from`), after checking that it is the architecture `config` describes.
///
/// # Errors
/// `dir` has no readable `model.json`, holds another architecture, or one whose
/// hyper-parameters differ (each named, a usage error).
fn init_normalisation(
    dir: &std::path::Path,
    config: &GridConfig,
) -> anyhow::Result<([f32; 2], [f32; 2], [f32; 2])> {
    let (path, meta) = crate::model::store::read_meta(dir)
        .with_context(|| format!("--init-from {}", dir.display()))?;
    let differ = super::train::differences(
        &serde_json::to_value(&meta.net)?,
        &NetConfig::Grid(config.clone()),
    )?;
    if !differ.is_empty() {
        return Err(super::UsageError(format!(
            "--init-from {}: its network differs from the one these flags describe ({}); \
             give the flags it was trained with",
            dir.display(),
            differ.join("; ")
        ))
        .into());
    }
    match meta.net {
        NetConfig::Grid(saved) => Ok((saved.vel_scale, saved.dv_mean, saved.dv_scale)),
        NetConfig::Paper(_) => unreachable!("{}: compared equal to a grid config", path.display()),
    }
}

/// Trains on `device` (the CPU, or one GPU opened with the kernel choices).
#[cfg_attr(not(feature = "cuda"), allow(unused_variables))]
fn fit_on(
    (device, kernels): (&Device, crate::ops::Kernels),
    run: (GridConfig, GridTrainOptions, PathBuf, Option<PathBuf>),
    train: &WindowIndex,
    val: &[Trajectory],
    scaler: &Scaler,
    resume: bool,
    observer: &mut dyn Observer,
) -> anyhow::Result<Vec<EpochRecord>> {
    fn on<B: AutodiffBackend + NetOps>(
        device: B::Device,
        run: (GridConfig, GridTrainOptions, PathBuf, Option<PathBuf>),
        train: &WindowIndex,
        val: &[Trajectory],
        scaler: &Scaler,
        resume: bool,
        observer: &mut dyn Observer,
    ) -> Result<Vec<EpochRecord>, TrainError>
    where
        B::InnerBackend: NetOps,
    {
        let (config, opts, out, init_from) = run;
        GridTrainer::<B> {
            config,
            opts,
            out,
            device,
            init_from,
        }
        .fit(train, val, scaler, resume, observer)
    }
    let ordinal = device.single("train --arch grid")?;
    let history = match ordinal {
        None => on::<CpuTrain>(
            Default::default(),
            run,
            train,
            val,
            scaler,
            resume,
            observer,
        )?,
        #[cfg(feature = "cuda")]
        Some(id) => {
            use super::device::cuda::{device as cuda_device, CudaTrain};
            on::<CudaTrain>(
                cuda_device(id, kernels)?,
                run,
                train,
                val,
                scaler,
                resume,
                observer,
            )?
        }
        #[cfg(not(feature = "cuda"))]
        Some(_) => unreachable!("--device cuda is refused without the cuda feature"),
    };
    Ok(history)
}
