//! `minflow train --data DIR --model mingru --out runs/NAME`: loads trajectories from bags,
//! splits them 80:10:10 by scene (seeded), fits the scaler on the training scenes, trains
//! with a progress bar per epoch, and leaves in the run folder: `model.json` + `model.mpk`
//! (best epoch), `checkpoint/` (last epoch, for `--resume`), `metrics.csv`, `loss.png`,
//! `split.json` and `train.json` (the options). `--device` picks the backend: the CPU (burn
//! ndarray, default) or a GPU (burn CUDA, feature `cuda`). A dataset of more than
//! `--max-resident-frames` frames is streamed from the bags each epoch.

use super::device::{Device, DeviceArgs};
use super::Outcome;
use crate::data::{
    self, LoadReport, Part, Scaler, SceneInfo, Split, StreamingLoader, Trajectory, WindowIndex,
};
use crate::model::store::NetConfig;
use crate::model::{CoreKind, DecoderKind, LastActivation, ModelConfig, Pooling};
use crate::ops::NetOps;
use crate::train::{BatchSource, EpochRecord, Observer, TrainError, TrainOptions, Trainer};
use anyhow::{bail, Context};
use burn::backend::{Autodiff, NdArray};
use burn::tensor::backend::AutodiffBackend;
use clap::Args;
use std::io::Write;
use std::path::{Path, PathBuf};

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
    #[arg(long, default_value_t = 30, value_parser = super::flags::at_least_one)]
    pub epochs: usize,
    /// Effective batch size (windows per optimizer step).
    #[arg(long, default_value_t = 16, value_parser = super::flags::at_least_one)]
    pub batch_size: usize,
    /// Windows per forward pass; gradients accumulate up to --batch-size.
    #[arg(long, default_value_t = 16, value_parser = super::flags::at_least_one)]
    pub micro_batch: usize,
    /// Input frames per sample T.
    #[arg(long, default_value_t = 2, value_parser = super::flags::at_least_one)]
    pub window: usize,
    /// Seed of the split, the weights, the data order and dropout.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Adam learning rate.
    #[arg(long, default_value_t = 1e-3, value_parser = super::flags::positive)]
    pub lr: f64,
    /// Stop after this many epochs without a better validation loss (0: never).
    #[arg(long, default_value_t = 5)]
    pub patience: usize,
    /// Latent and core width W (the paper: 1250).
    #[arg(long, default_value_t = 1250, value_parser = super::flags::at_least_one)]
    pub width: usize,
    /// Encoder hidden width (the paper: 256).
    #[arg(long, default_value_t = 256, value_parser = super::flags::at_least_one)]
    pub encoder_hidden: usize,
    /// Activation after the encoder's last Linear: elu (the paper's text) | none (with mean
    /// pooling the encoder is then ~200x cheaper, exactly).
    #[arg(long, default_value = "none")]
    pub encoder_last_activation: String,
    /// Pooling over particles: mean | max | mean-max.
    #[arg(long, default_value = "mean")]
    pub pooling: String,
    /// Recurrent layers.
    #[arg(long, default_value_t = 2, value_parser = super::flags::at_least_one)]
    pub layers: usize,
    /// Dropout after each recurrent layer.
    #[arg(long, default_value_t = 0.1, value_parser = super::flags::dropout)]
    pub dropout: f64,
    /// Decoder: global (the paper's, fixed N) | pointwise (any N).
    #[arg(long, default_value = "global")]
    pub decoder: String,
    /// Initial decoder output layer: zero (an untrained model is the constant-velocity
    /// baseline) | random (burn's default Kaiming-uniform, as in the paper's PyTorch code).
    #[arg(long, default_value = "zero")]
    pub decoder_init: String,
    /// Density-map grid G for the loss.
    #[arg(long, default_value_t = 32, value_parser = super::flags::at_least_one)]
    pub density_grid: usize,
    /// Weight of the density-map loss.
    #[arg(long, default_value_t = 0.1, value_parser = super::flags::non_negative_f32)]
    pub density_weight: f32,
    /// Topic to read frames from.
    #[arg(long, default_value = crate::bag::FRAMES_TOPIC)]
    pub topic: String,
    #[command(flatten)]
    pub device: DeviceArgs,
    /// Continue a killed run from OUT/checkpoint.
    #[arg(long)]
    pub resume: bool,
    /// Frames held in memory at most; a larger dataset is streamed from the bags in chunks
    /// each epoch (a frame of 2,500 particles is 40 kB).
    #[arg(long, default_value_t = 50_000)]
    pub max_resident_frames: usize,
    #[command(flatten)]
    pub grid_args: super::train_grid::GridArgs,
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

/// Progress bar per epoch, one log line per epoch, metrics.csv and loss.png kept current.
pub(crate) struct Progress {
    out: PathBuf,
    bar: Option<indicatif::ProgressBar>,
}

impl Progress {
    /// Progress of a run writing to `out`.
    pub(crate) fn new(out: PathBuf) -> Self {
        Self { out, bar: None }
    }
}

impl Observer for Progress {
    fn batch(&mut self, epoch: usize, done: usize, total: usize, loss: f64, rate: f64) {
        let bar = self
            .bar
            .get_or_insert_with(|| super::progress(total as u64, &format!("epoch {epoch}")));
        bar.set_position(done as u64);
        bar.set_message(format!("epoch {epoch} loss {loss:.3e} {rate:.1}/s"));
    }

    fn epoch(&mut self, r: &EpochRecord, history: &[EpochRecord]) {
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
        }
        eprintln!(
            "epoch {:>3}  train {:.4e}  val {:.4e}  {:.1} s  {:.1} samples/s",
            r.epoch, r.train_loss, r.val_loss, r.seconds, r.samples_per_sec
        );
        if let Err(err) = write_metrics(&self.out, history) {
            tracing::warn!("writing metrics: {err:#}");
        }
    }
}

/// Rewrites `metrics.csv` (and `loss.png`) from the whole history.
fn write_metrics(out: &Path, history: &[EpochRecord]) -> anyhow::Result<()> {
    let path = out.join("metrics.csv");
    let mut f =
        std::fs::File::create(&path).with_context(|| format!("writing {}", path.display()))?;
    writeln!(f, "epoch,train_loss,val_loss,seconds,samples_per_sec")?;
    for r in history {
        writeln!(
            f,
            "{},{},{},{:.3},{:.3}",
            r.epoch, r.train_loss, r.val_loss, r.seconds, r.samples_per_sec
        )?;
    }
    super::loss_plot(&out.join("loss.png"), history)
}

pub fn run(args: TrainArgs) -> anyhow::Result<Outcome> {
    if args.arch == "grid" {
        return super::train_grid::run(args);
    }
    // The flags' names and ranges, before any bag is read (the particle count comes later).
    args.model_config(1)
        .map_err(|e| super::UsageError(format!("{e:#}")))?;
    let device = args.device.parse()?;
    let topic = Some(args.topic.as_str());
    let (infos, resident, scanned) = read_data(&args, topic)?;
    let scenes: Vec<String> = infos.iter().map(|s| s.scene.clone()).collect();
    let split = Split::new(&scenes, args.seed);
    let in_part = |part: Part| -> Vec<SceneInfo> {
        infos
            .iter()
            .filter(|s| split.part_of(&s.scene) == Some(part))
            .cloned()
            .collect()
    };
    let (train_infos, val_infos) = (in_part(Part::Train), in_part(Part::Val));
    let Some(first) = train_infos.first() else {
        bail!("no training scenes in {:?}", args.data);
    };
    let particles = first.n;
    // A sample is T input frames and the next: a window no training scene can hold trains on
    // nothing (it once saved a model with validation loss 0).
    let longest = train_infos.iter().map(|s| s.frames).max().unwrap_or(0);
    if longest <= args.window {
        return Err(super::UsageError(format!(
            "--window {}: no training samples: the longest training scene has {longest} frames, \
             a sample needs T + 1 = {}",
            args.window,
            args.window + 1
        ))
        .into());
    }
    let config = args
        .model_config(particles)
        .map_err(|e| super::UsageError(format!("{e:#}")))?;
    if args.resume {
        check_resume(&args.out, &NetConfig::Paper(config.clone()))?;
    }
    write_run_files(&args.out, &split, &args.options())?;
    let total: usize = infos.iter().map(|s| s.frames).sum();
    let streamed = total > args.max_resident_frames;
    eprintln!(
        "{} scenes, {total} frames: {} train, {} val, {} test ({}){}; core {}, N = {particles}, T = {}",
        scenes.len(),
        split.scenes(Part::Train).len(),
        split.scenes(Part::Val).len(),
        split.scenes(Part::Test).len(),
        args.out.join("split.json").display(),
        if streamed { ", streamed from the bags" } else { "" },
        config.core.name(),
        config.window
    );
    let fit = |train: &mut dyn BatchSource,
               val: Option<&mut dyn BatchSource>,
               scaler: &Scaler,
               progress: &mut Progress| {
        let (opts, out) = (args.options(), args.out.clone());
        fit_on(
            (&device, args.device.kernels()),
            config.clone(),
            opts,
            out,
            train,
            val,
            scaler,
            args.resume,
            progress,
        )
    };
    let mut progress = Progress {
        out: args.out.clone(),
        bar: None,
    };
    let history = if streamed {
        let budget = args.max_resident_frames;
        let scaler = StreamingLoader::fit_scaler(train_infos.clone(), topic, budget)?;
        let mut train = StreamingLoader::new(train_infos, topic, args.window, scaler, budget)?;
        let mut val = StreamingLoader::new(val_infos, topic, args.window, scaler, budget)?;
        let val = (!val.is_empty()).then_some(&mut val as &mut dyn BatchSource);
        fit(&mut train, val, &scaler, &mut progress)?
    } else {
        let trajs = match resident {
            Some(trajs) => trajs,
            // Bags without summary statistics fit after all: read them once more.
            None => load(&args.data, topic)?.0,
        };
        let (train, val, _test) = split.partition(trajs);
        let scaler = Scaler::fit(&train.iter().collect::<Vec<_>>());
        let train_index = WindowIndex::new(train, args.window, scaler)?;
        let val_index = WindowIndex::new(val, args.window, scaler)?;
        let mut train_ref = &train_index;
        let mut val_ref = &val_index;
        let val = (!val_index.is_empty()).then_some(&mut val_ref as &mut dyn BatchSource);
        fit(&mut train_ref, val, &scaler, &mut progress)?
    };
    print_best(&history, "val loss", &args.out);
    Ok(super::read_to_damage(&scanned.truncated))
}

/// Creates the run folder `out` with its `split.json` and `train.json` (`options`).
///
/// # Errors
/// The folder or a file could not be written.
pub(crate) fn write_run_files(
    out: &Path,
    split: &Split,
    options: &impl serde::Serialize,
) -> anyhow::Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    for (name, text) in [
        ("split.json", serde_json::to_string_pretty(split)?),
        ("train.json", serde_json::to_string_pretty(options)?),
    ] {
        let path = out.join(name);
        std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

/// Prints the best epoch of `history` (by validation loss, called `what`) and where its
/// model was saved.
pub(crate) fn print_best(history: &[EpochRecord], what: &str, out: &Path) {
    if let Some(best) = history
        .iter()
        .min_by(|a, b| a.val_loss.total_cmp(&b.val_loss))
    {
        println!(
            "best epoch {} {what} {:.4e} -> {}",
            best.epoch,
            best.val_loss,
            out.join("model.json").display()
        );
    }
}

/// The paper path's scene index, with the trajectories themselves when the bags fit in
/// memory (`--max-resident-frames`, by their summaries' frame counts): then the bags are
/// read once. Otherwise (a large dataset, or bags without summary statistics) the index
/// comes from a decoding pass and the trajectories are streamed or loaded afterwards.
fn read_data(
    args: &TrainArgs,
    topic: Option<&str>,
) -> anyhow::Result<(Vec<SceneInfo>, Option<Vec<Trajectory>>, LoadReport)> {
    let fits = data::summary_frames(&args.data, topic)
        .is_some_and(|frames| frames <= args.max_resident_frames as u64);
    if fits {
        let (trajs, report) = load(&args.data, topic)?;
        Ok((SceneInfo::of(&trajs), Some(trajs), report))
    } else {
        let (infos, report) =
            data::scan_with_report(&args.data, topic).context("reading the bags")?;
        Ok((infos, None, report))
    }
}

/// [`data::load`], with its gaps logged.
fn load(inputs: &[PathBuf], topic: Option<&str>) -> anyhow::Result<(Vec<Trajectory>, LoadReport)> {
    let (trajs, report) = data::load(inputs, topic).context("loading trajectories")?;
    for gap in &report.gaps {
        tracing::warn!("{gap}");
    }
    Ok((trajs, report))
}

/// Trains on `device`: the CPU backend, or burn's CUDA backend (one GPU; several train
/// data-parallel).
#[allow(clippy::too_many_arguments)]
#[cfg_attr(not(feature = "cuda"), allow(unused_variables))]
fn fit_on(
    (device, kernels): (&Device, crate::ops::Kernels),
    config: ModelConfig,
    opts: TrainOptions,
    out: PathBuf,
    train: &mut dyn BatchSource,
    val: Option<&mut dyn BatchSource>,
    scaler: &Scaler,
    resume: bool,
    observer: &mut dyn Observer,
) -> anyhow::Result<Vec<EpochRecord>> {
    fn on<B: AutodiffBackend + NetOps>(
        devices: Vec<B::Device>,
        args: (ModelConfig, TrainOptions, PathBuf),
        train: &mut dyn BatchSource,
        val: Option<&mut dyn BatchSource>,
        scaler: &Scaler,
        resume: bool,
        observer: &mut dyn Observer,
    ) -> Result<Vec<EpochRecord>, TrainError>
    where
        B::InnerBackend: NetOps,
    {
        let (config, opts, out) = args;
        Trainer::<B>::data_parallel(config, opts, out, devices)
            .fit_observed(train, val, scaler, resume, observer)
    }
    let args = (config, opts, out);
    let history = match device {
        Device::Cpu => on::<CpuTrain>(
            vec![Default::default()],
            args,
            train,
            val,
            scaler,
            resume,
            observer,
        )?,
        #[cfg(feature = "cuda")]
        Device::Cuda(ids) => {
            use super::device::cuda::{devices, CudaTrain};
            on::<CudaTrain>(
                devices(ids, kernels)?,
                args,
                train,
                val,
                scaler,
                resume,
                observer,
            )?
        }
        #[cfg(not(feature = "cuda"))]
        Device::Cuda(_) => unreachable!("--device cuda is refused without the cuda feature"),
    };
    Ok(history)
}

/// With `--resume`, the run folder's `model.json` (written with the first checkpoint) must
/// describe the network this invocation builds: weights of another shape cannot load, and
/// other settings would silently change the run. Compares every hyper-parameter of `net`
/// with the saved one, except the values fitted on the data (`vel_scale`, `dv_mean`,
/// `dv_scale`) and the convolution kernel (`conv`: the same weights and results). A folder
/// without `model.json` passes (nothing to resume yet).
///
/// # Errors
/// An unreadable `model.json`, or one whose settings differ: the error names each field with
/// both values.
pub(crate) fn check_resume(out: &Path, net: &NetConfig) -> anyhow::Result<()> {
    let Some(differ) = config_differences(out, net)? else {
        return Ok(());
    };
    if !differ.is_empty() {
        bail!(
            "--resume: {} was trained with other settings ({}); resume with the flags it was \
             started with, or train into a new --out",
            out.display(),
            differ.join("; ")
        );
    }
    Ok(())
}

/// Each hyper-parameter of `net` that differs from the one saved in `dir/model.json`, as
/// `"field: checkpoint OLD, this run NEW"`, skipping the values fitted on the data
/// (`vel_scale`, `dv_mean`, `dv_scale`) and the convolution kernel (`conv`). `None` when
/// `dir` has no `model.json`.
///
/// # Errors
/// An unreadable or unparsable `model.json`.
pub(crate) fn config_differences(
    dir: &Path,
    net: &NetConfig,
) -> anyhow::Result<Option<Vec<String>>> {
    let path = dir.join("model.json");
    let text = match std::fs::read_to_string(&path) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
    };
    let saved: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
    differences(&saved, net).map(Some)
}

/// Each hyper-parameter of `net` that differs from its value in `saved` (a `model.json`, or
/// a saved [`NetConfig`], as JSON), as [`config_differences`] lists them.
///
/// # Errors
/// `net` does not serialise (not expected).
pub(crate) fn differences(
    saved: &serde_json::Value,
    net: &NetConfig,
) -> anyhow::Result<Vec<String>> {
    const NOT_COMPARED: [&str; 4] = ["vel_scale", "dv_mean", "dv_scale", "conv"];
    let new = serde_json::to_value(net)?;
    Ok(new
        .as_object()
        .into_iter()
        .flatten()
        .filter(|(key, _)| !NOT_COMPARED.contains(&key.as_str()))
        .filter_map(|(key, value)| {
            let old = saved.get(key);
            (old != Some(value)).then(|| {
                let old = old.map_or_else(|| "absent".to_owned(), ToString::to_string);
                format!("{key}: checkpoint {old}, this run {value}")
            })
        })
        .collect())
}
