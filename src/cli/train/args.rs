//! `minflow train`'s flags ([`TrainArgs`], with the grid architecture's [`GridArgs`] and
//! [`GridNetArgs`], which `report` shares) and the configurations they describe for each
//! architecture. `mod.rs` dispatches on `--arch`, `paper.rs` and `grid.rs` run each
//! architecture, `cli/run_folder.rs` holds what both leave in the run folder.

use anyhow::{bail, Context};
use burn::backend::{Autodiff, NdArray};
use clap::Args;
use std::path::PathBuf;

pub use super::net_args::{GridNetArgs, Reference, RestShape};
use crate::cli::device::DeviceArgs;
use crate::data::ResidentBudget;
use crate::model::grid::{ConvKernel, Deformation, GridConfig, MemoryKind};
use crate::model::{CoreKind, DecoderKind, LastActivation, ModelConfig, Pooling};
use crate::train::grid::GridTrainOptions;
use crate::train::TrainOptions;

/// The CPU training backend.
pub type CpuTrain = Autodiff<NdArray<f32>>;

#[derive(Debug, Args)]
pub struct TrainArgs {
    /// Bags or folders of bags.
    #[arg(long, required = true, num_args = 1..)]
    pub data: Vec<PathBuf>,
    /// Architecture: grid (local: P2G -> U-Net -> G2P with per-particle memory; any N) |
    /// paper (the paper's Table 1: pooled encoder, core, decoder).
    #[arg(long, default_value = "grid", value_parser = ["grid", "paper"])]
    pub arch: String,
    /// Core. grid: none | mingru | minlstm | gru | lstm (per-particle memory); paper: mlp |
    /// lstm | gru | minlstm | mingru.
    #[arg(long, alias = "core", default_value = "mingru")]
    pub model: String,
    /// Run folder.
    #[arg(short, long)]
    pub out: PathBuf,
    /// Epochs (at most; early stopping may end sooner).
    #[arg(long, default_value_t = 30, value_parser = crate::cli::flags::at_least_one)]
    pub epochs: usize,
    /// Effective batch size (windows per optimizer step).
    #[arg(long, default_value_t = 16, value_parser = crate::cli::flags::at_least_one)]
    pub batch_size: usize,
    /// Windows per forward pass; gradients accumulate up to --batch-size.
    #[arg(long, default_value_t = 16, value_parser = crate::cli::flags::at_least_one)]
    pub micro_batch: usize,
    /// Input frames per sample T.
    #[arg(long, default_value_t = 2, value_parser = crate::cli::flags::at_least_one)]
    pub window: usize,
    /// Seed of the split, the weights, the data order and dropout.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Adam learning rate.
    #[arg(long, default_value_t = 1e-3, value_parser = crate::cli::flags::positive)]
    pub lr: f64,
    /// Stop after this many epochs without a better validation loss (0: never).
    #[arg(long, default_value_t = 5)]
    pub patience: usize,
    /// Latent and core width W (the paper: 1250).
    #[arg(long, default_value_t = 1250, value_parser = crate::cli::flags::at_least_one)]
    pub width: usize,
    /// Encoder hidden width (the paper: 256).
    #[arg(long, default_value_t = 256, value_parser = crate::cli::flags::at_least_one)]
    pub encoder_hidden: usize,
    /// Activation after the encoder's last Linear: elu (the paper's text) | none (with mean
    /// pooling the encoder is then ~200x cheaper, exactly).
    #[arg(long, default_value = "none", value_parser = ["none", "elu"])]
    pub encoder_last_activation: String,
    /// Pooling over particles: mean | max | mean-max.
    #[arg(long, default_value = "mean", value_parser = ["mean", "max", "mean-max"])]
    pub pooling: String,
    /// Recurrent layers.
    #[arg(long, default_value_t = 2, value_parser = crate::cli::flags::at_least_one)]
    pub layers: usize,
    /// Dropout after each recurrent layer.
    #[arg(long, default_value_t = 0.1, value_parser = crate::cli::flags::dropout)]
    pub dropout: f64,
    /// Decoder: global (the paper's, fixed N) | pointwise (any N).
    #[arg(long, default_value = "global", value_parser = ["global", "pointwise"])]
    pub decoder: String,
    /// Initial decoder output layer: zero (an untrained model is the constant-velocity
    /// baseline) | random (burn's default Kaiming-uniform, as in the paper's PyTorch code).
    #[arg(long, default_value = "zero", value_parser = ["zero", "random"])]
    pub decoder_init: String,
    /// Density-map grid G for the loss.
    #[arg(long, default_value_t = 32, value_parser = crate::cli::flags::at_least_one)]
    pub density_grid: usize,
    /// Weight of the density-map loss.
    #[arg(long, default_value_t = 0.1, value_parser = crate::cli::flags::non_negative_f32)]
    pub density_weight: f32,
    /// Topic to read frames from.
    #[arg(long, default_value = crate::bag::FRAMES_TOPIC)]
    pub topic: String,
    #[command(flatten)]
    pub device: DeviceArgs,
    /// Continue a killed run from OUT/checkpoint.
    #[arg(long)]
    pub resume: bool,
    /// Keep the validation and test scenes of this run folder's `split.json` (or of that
    /// file itself) held out and train on every other scene of --data, instead of a new
    /// seeded split: more training scenes (e.g. `simulate --scenes 60..300`) for a model
    /// whose held-out scenes must stay unseen. Default with --init-from: its run's split
    /// (a fresh one when no scene of --data is in it: a parent of another family or size).
    #[arg(long, value_name = "DIR")]
    pub split_from: Option<PathBuf>,
    /// Frames held in memory at most, or `auto`: 40 % of the machine's available memory
    /// over a frame's size (a frame of 2,500 particles is 40 kB). A larger dataset's
    /// training scenes are streamed from the bags in chunks of half of it, the next chunk
    /// read while one is trained on (`--arch grid` keeps its validation scenes in memory).
    #[arg(long, default_value = "auto", value_name = "FRAMES|auto")]
    pub max_resident_frames: ResidentBudget,
    #[command(flatten)]
    pub grid_args: GridArgs,
}

impl TrainArgs {
    /// The network configuration these flags describe, for `particles` particles.
    pub fn model_config(&self, particles: usize) -> anyhow::Result<ModelConfig> {
        let core = CoreKind::parse(&self.model).with_context(|| {
            format!(
                "unknown --model {:?} (mlp | lstm | gru | minlstm | mingru)",
                self.model
            )
        })?;
        let last = match self.encoder_last_activation.as_str() {
            "elu" => LastActivation::Elu,
            "none" => LastActivation::None,
            other => bail!("unknown --encoder-last-activation {other:?} (elu | none)"),
        };
        let pooling = match self.pooling.as_str() {
            "mean" => Pooling::Mean,
            "max" => Pooling::Max,
            "mean-max" => Pooling::MeanMax,
            other => bail!("unknown --pooling {other:?} (mean | max | mean-max)"),
        };
        let decoder = match self.decoder.as_str() {
            "global" => DecoderKind::Global,
            "pointwise" => DecoderKind::Pointwise,
            other => bail!("unknown --decoder {other:?} (global | pointwise)"),
        };
        let zero_init = match self.decoder_init.as_str() {
            "zero" => true,
            "random" => false,
            other => bail!("unknown --decoder-init {other:?} (zero | random)"),
        };
        if self.window == 0 || self.batch_size == 0 || self.micro_batch == 0 {
            bail!("--window, --batch-size and --micro-batch must be at least 1");
        }
        Ok(ModelConfig::new(core, particles)
            .with_window(self.window)
            .with_width(self.width)
            .with_encoder_hidden(self.encoder_hidden)
            .with_encoder_last_activation(last)
            .with_pooling(pooling)
            .with_layers(self.layers)
            .with_dropout(self.dropout)
            .with_decoder(decoder)
            .with_decoder_zero_init(zero_init))
    }

    /// For `--arch grid`: an error naming every flag of the paper's architecture that was
    /// set away from its default (the grid run would ignore it), checked before any work.
    /// Values the paper's architecture would refuse (`--decoder banana`) are refused too.
    ///
    /// # Errors
    /// A [`crate::cli::UsageError`] naming the flags.
    pub fn refuse_paper_flags(&self) -> anyhow::Result<()> {
        let d: Self = crate::cli::flags::defaults(&["--data", "--out"])?;
        let set: Vec<&str> = [
            ("--width", self.width != d.width),
            ("--encoder-hidden", self.encoder_hidden != d.encoder_hidden),
            (
                "--encoder-last-activation",
                self.encoder_last_activation != d.encoder_last_activation,
            ),
            ("--pooling", self.pooling != d.pooling),
            ("--layers", self.layers != d.layers),
            ("--dropout", self.dropout != d.dropout),
            ("--decoder", self.decoder != d.decoder),
            ("--decoder-init", self.decoder_init != d.decoder_init),
            ("--micro-batch", self.micro_batch != d.micro_batch),
            ("--density-grid", self.density_grid != d.density_grid),
            ("--density-weight", self.density_weight != d.density_weight),
        ]
        .into_iter()
        .filter_map(|(flag, differs)| differs.then_some(flag))
        .collect();
        if set.is_empty() {
            return Ok(());
        }
        Err(crate::cli::UsageError(format!(
            "{} {} of --arch paper; --arch {} does not use {}",
            set.join(", "),
            if set.len() == 1 {
                "is a flag"
            } else {
                "are flags"
            },
            self.arch,
            if set.len() == 1 { "it" } else { "them" }
        ))
        .into())
    }

    /// The optimisation settings these flags describe.
    pub fn options(&self) -> TrainOptions {
        TrainOptions {
            epochs: self.epochs,
            batch_size: self.batch_size,
            micro_batch: self.micro_batch.min(self.batch_size),
            lr: self.lr,
            seed: self.seed,
            patience: self.patience,
            density_grid: self.density_grid,
            density_weight: self.density_weight,
        }
    }
}

/// Flags of the grid architecture (ignored by `--arch paper`).
#[derive(Debug, Clone, Args)]
pub struct GridArgs {
    #[command(flatten)]
    pub net: GridNetArgs,
    /// How the U-Net's convolutions run: auto (gather: single-kernel im2col on the CPU and CUDA) | burn |
    /// gather | shift (the same weights and results; `bench train --arch grid` compares them).
    #[arg(long, default_value = "auto", value_parser = crate::cli::flags::conv_kernel)]
    pub conv: ConvKernel,
    /// Steps per training sample P (a short rollout; the loss averages them).
    #[arg(long, default_value_t = 4, value_parser = crate::cli::flags::at_least_one)]
    pub rollout_steps: usize,
    /// Of those, steps that read the true frame (the rest read the model's own predictions).
    #[arg(long, default_value_t = 1, value_parser = crate::cli::flags::at_least_one)]
    pub teacher_steps: usize,
    /// Push-forward: network calls made before the --rollout-steps ones, on the model's own
    /// predictions, without gradient or loss (memory and state carried into the others), so
    /// training sees the inputs of a longer rollout at the cost of forward passes only
    /// (Brandstetter et al. 2022). Samples grow by this many calls' frames. The push-forward
    /// calls always feed their own predictions on; --teacher-steps counts from the first of
    /// them.
    #[arg(long, default_value_t = 0, value_name = "CALLS")]
    pub pushforward: usize,
    /// Truncated backpropagation through time: the --rollout-steps calls are made this many
    /// times in a row per sample, an optimizer step after each, the rollout (frames, memory
    /// state, F) carried on from one chunk to the next with its gradient cut between them.
    /// Training sees CHUNKS x --rollout-steps calls of the model's own rollout at the GPU
    /// memory of --rollout-steps; samples grow to match.
    #[arg(long, default_value_t = 1, value_parser = crate::cli::flags::at_least_one)]
    pub chunks: usize,
    /// Gaussian noise on the true input velocities, in units of the velocity change's
    /// standard deviation.
    #[arg(long, default_value_t = 0.0, value_parser = crate::cli::flags::non_negative_f32)]
    pub noise: f32,
    /// Train on each sample or, with probability 1/2, its mirror image about the box's
    /// vertical midline (x -> 1 - x, vx -> -vx): a symmetry of MPM's box, walls and gravity,
    /// so twice the scenes.
    #[arg(long)]
    pub mirror: bool,
    /// Weight of the strain loss: the squared error of each solid rest-neighbour pair's
    /// length |x_i - x_j| in units of the particle's rest neighbour distance (8 nearest of the
    /// same material in the scene's first frame), prediction against truth, beside the
    /// position and velocity MSE (0: off).
    #[arg(long, default_value_t = 0.0, value_parser = crate::cli::flags::non_negative_f32)]
    pub strain_loss: f32,
    /// Weight of the volume loss: the squared error of each liquid particle's J (the area
    /// change of its 8 nearest liquid neighbours since the sample's first frame, fitted by
    /// least squares), prediction against truth (0: off). At weight 20 it made fine-tunes of
    /// the shipped small model worse over whole scenes, not better (docs/liquid.md).
    #[arg(long, default_value_t = 0.0, value_parser = crate::cli::flags::non_negative_f32)]
    pub volume_loss: f32,
    /// Weight of the energy loss: per sample, the squared relative error of the predicted
    /// frame's RMS particle speed against the truth's (after the constraint projection when
    /// training through it), so the network makes up the motion the projection takes (0: off).
    #[arg(long, default_value_t = 0.0, value_parser = crate::cli::flags::non_negative_f32)]
    pub energy_loss: f32,
    /// Weight of the liquid density-map loss: the liquid's particles per cell on a 32 x 32
    /// grid (quadratic B-spline, differentiable in the positions), in units of the scene's
    /// mean, squared error of the prediction's against the truth's, as the paper's density
    /// loss (section 3). With --chunks above 1, the chunks after the first are scored by it
    /// (and the structure and energy terms) instead of by each particle's place, so a long
    /// rollout is asked for the truth's liquid shape, not a particle-by-particle match (0: off).
    #[arg(long, default_value_t = 0.0, value_parser = crate::cli::flags::non_negative_f32)]
    pub density_loss: f32,
    /// Weight of the fast particles in the velocity and position MSE: each particle's squared
    /// error weighs 1 + W |v| / (mean |v| + 0.1), |v| its true speed and the mean over its
    /// sample, normalised to mean 1 over the batch (a moving sample also weighs more than one
    /// at rest), so a splash's few thrown particles count for more than the liquid at rest
    /// around them (0: every particle alike).
    #[arg(long, default_value_t = 0.0, value_parser = crate::cli::flags::non_negative_f32)]
    pub fast_loss: f32,
    /// Discount of the loss along each sample's rollout, in (0, 1]: the rollout's frame j
    /// (from 0) weighs discount^j, the weights normalised to sum to 1, so a long
    /// --rollout-steps keeps the first frames' error in view (1: every frame alike).
    #[arg(long, default_value_t = 1.0, value_parser = crate::cli::flags::discount)]
    pub rollout_discount: f32,
    /// Gradient-norm clipping threshold (0: off).
    #[arg(long, default_value_t = 1.0, value_parser = crate::cli::flags::non_negative_f32)]
    pub clip: f32,
    /// Learning rate at the end of the cosine decay.
    #[arg(long, default_value_t = 1e-5, value_parser = crate::cli::flags::non_negative)]
    pub lr_final: f64,
    /// Samples per epoch at most (0: every window).
    #[arg(long, default_value_t = 0)]
    pub samples_per_epoch: usize,
    /// Validation rollouts per validation scene.
    #[arg(long, default_value_t = 3, value_parser = crate::cli::flags::at_least_one)]
    pub val_starts: usize,
    /// Validation rollout length (frames).
    #[arg(long, default_value_t = 20, value_parser = crate::cli::flags::at_least_one)]
    pub val_horizon: usize,
    /// Stop after this many minutes of training (the epoch in progress is cut short,
    /// validated and kept; the learning rate decays by the clock; 0: no limit).
    #[arg(long, default_value_t = 0.0, value_parser = crate::cli::flags::non_negative)]
    pub max_minutes: f64,
    /// Keep the weights of the last N epochs (an epoch --max-minutes cut short included) as
    /// run folders `epochs/NNNN` beside the best (for `minflow average`, or an epoch picked
    /// by whole-scene eval; 0: none).
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub keep_epochs: usize,
    /// End this call after this many minutes with a mid-epoch checkpoint that `--resume`
    /// continues exactly (a run of hours over calls of a few minutes; the schedule is
    /// unchanged; 0: no limit).
    #[arg(long, default_value_t = 0.0, value_parser = crate::cli::flags::non_negative)]
    pub call_minutes: f64,
    /// End this call after this many optimizer steps, as --call-minutes does (0: no limit).
    #[arg(long, default_value_t = 0)]
    pub call_steps: usize,
    /// Write a mid-epoch checkpoint after this many minutes without one (0: only after each
    /// epoch and when the call ends).
    #[arg(long, default_value_t = 5.0, value_parser = crate::cli::flags::non_negative)]
    pub checkpoint_minutes: f64,
    /// Start from the weights of this run folder (fine-tuning, or continuing a finished run
    /// with a new learning-rate schedule) instead of fresh ones. Its architecture must be the
    /// one these flags describe, but for --grid (the U-Net is convolutional: the same weights
    /// on another network grid); its normalisation constants are kept.
    #[arg(long, value_name = "DIR", conflicts_with = "resume")]
    pub init_from: Option<PathBuf>,
    /// Project every frame the training rollouts feed on (after the teacher-forced calls) onto the
    /// material constraints, with a straight-through gradient: on | off | a list of rope, jelly,
    /// snow, liquid, walls, contact, momentum, rebound, pressure. Parameters: --init-from's
    /// `model.json` constraints (`minflow constraints fit`), else the defaults; the trained model
    /// keeps them.
    #[arg(long = "constraints", value_name = "PARTS", default_value = "off")]
    pub constraints: crate::model::constraints::Parts,
}

impl TrainArgs {
    /// The grid network these flags describe (normalisation constants still at their
    /// defaults: [`fit_stats`] fills them from the training split).
    ///
    /// # Errors
    /// An unknown core or a size out of range, naming the flag (a [`crate::cli::UsageError`]).
    pub fn grid_config(&self) -> anyhow::Result<GridConfig> {
        self.checked_grid_config()
            .map_err(|e| crate::cli::UsageError(format!("{e:#}")).into())
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
            .with_bundle(g.net.bundle)
            .with_substeps(g.net.substeps)
            .with_box_grid(g.net.box_grid)
            .with_interaction(g.net.interaction)
            .with_interaction_radius(g.net.interaction_radius)
            .with_interaction_neighbours(g.net.interaction_neighbours)
            .with_conv(g.conv)
            .with_reference(g.net.reference == Reference::FirstFrame)
            .with_rest_shape(g.net.rest_shape != RestShape::None)
            .with_deformation(match g.net.rest_shape {
                RestShape::Advect => Deformation::Advect,
                _ => Deformation::Fit,
            })
            .with_update(g.net.update);
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

    /// This call's share of a grid run (`--call-minutes`, `--call-steps`,
    /// `--checkpoint-minutes`).
    pub fn call_share(&self) -> crate::train::CallShare {
        let g = &self.grid_args;
        crate::train::CallShare::new(g.call_minutes, g.call_steps, g.checkpoint_minutes)
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
            pushforward: g.pushforward,
            chunks: g.chunks,
            noise: g.noise,
            mirror: g.mirror,
            strain_weight: g.strain_loss,
            volume_weight: g.volume_loss,
            energy_weight: g.energy_loss,
            density_weight: g.density_loss,
            fast_weight: g.fast_loss,
            discount: g.rollout_discount,
            seed: self.seed,
            patience: self.patience,
            val_starts: g.val_starts,
            val_horizon: g.val_horizon,
            max_minutes: g.max_minutes,
            keep_epochs: g.keep_epochs,
            // Set by the grid run from --constraints and --init-from.
            constraints: None,
        }
    }
}
