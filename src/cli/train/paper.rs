//! `minflow train --arch paper`: the paper's architecture. Loads trajectories from bags
//! (streamed from the bags each epoch when the dataset has more than
//! `--max-resident-frames` frames), fits the scaler on the training scenes and trains with
//! [`crate::train::paper::Trainer`] on the CPU or one or more GPUs (data-parallel).

use super::args::TrainArgs;

use crate::cli::run_folder::{check_resume, print_best, run_split, write_run_files, Progress};
use crate::cli::Outcome;
use crate::data::{Part, Scaler, SceneInfo, StreamingLoader, WindowIndex};
use crate::model::store::NetConfig;
use crate::model::ModelConfig;
use crate::ops::NetOps;
use crate::train::{BatchSource, EpochRecord, Observer, TrainError, TrainOptions, Trainer};
use anyhow::bail;
use burn::tensor::backend::AutodiffBackend;
use std::path::PathBuf;

/// Runs `train --arch paper`.
///
/// # Errors
/// Bad flags (before any data is read), unreadable bags, no training scenes, training errors.
pub fn run(args: TrainArgs) -> anyhow::Result<Outcome> {
    // The flags' names and ranges, before any bag is read (the particle count comes later).
    args.model_config(1)
        .map_err(|e| crate::cli::UsageError(format!("{e:#}")))?;
    let device = args.device.parse()?;
    let topic = Some(args.topic.as_str());
    let (infos, resident, scanned) = super::read_data(&args, topic)?;
    let scenes: Vec<String> = infos.iter().map(|s| s.scene.clone()).collect();
    let split = run_split(
        &scenes,
        args.seed,
        super::split_source(&args).as_deref(),
        None,
    )?;
    let train_infos = split.select_infos(Part::Train, &infos);
    let val_infos = split.select_infos(Part::Val, &infos);
    let Some(first) = train_infos.first() else {
        bail!("no training scenes in {:?}", args.data);
    };
    let particles = first.n;
    check_samples(&train_infos, args.window)?;
    let config = args
        .model_config(particles)
        .map_err(|e| crate::cli::UsageError(format!("{e:#}")))?;
    if args.resume {
        check_resume(&args.out, &NetConfig::Paper(config.clone()))?;
    }
    write_run_files(&args.out, &split, &args.options())?;
    let total: usize = infos.iter().map(|s| s.frames).sum();
    let (budget, streamed) = super::resident_budget(&args, &infos, &train_infos);
    let dataset = super::dataset_info(&args, &train_infos, streamed);
    print_summary((scenes.len(), &split), &args.out, total, streamed, &config);
    let fit = |train: &mut dyn BatchSource,
               val: Option<&mut dyn BatchSource>,
               scaler: &Scaler,
               progress: &mut Progress| {
        let run = PaperFit {
            config: config.clone(),
            opts: args.options(),
            out: args.out.clone(),
            train,
            val,
            scaler,
            resume: args.resume,
            observer: progress,
            dataset: dataset.clone(),
        };
        super::fit_on(&device, args.device.kernels(), run)
    };
    let mut progress = Progress::new(args.out.clone());
    let history = if streamed {
        let scaler = StreamingLoader::fit_scaler(train_infos.clone(), topic, budget)?;
        let mut train = StreamingLoader::new(train_infos, topic, args.window, scaler, budget)?;
        let mut val = StreamingLoader::new(val_infos, topic, args.window, scaler, budget)?;
        let val = (!val.is_empty()).then_some(&mut val as &mut dyn BatchSource);
        fit(&mut train, val, &scaler, &mut progress)?
    } else {
        let trajs = match resident {
            Some(trajs) => trajs,
            // Bags without summary statistics fit after all: read them once more.
            None => super::load(&args.data, topic)?.0,
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
    Ok(crate::cli::read_to_damage(&scanned.truncated))
}

/// A sample is T input frames and the next: a window no training scene can hold trains on
/// nothing (it once saved a model with validation loss 0), a usage error.
fn check_samples(train: &[SceneInfo], window: usize) -> anyhow::Result<()> {
    let longest = train.iter().map(|s| s.frames).max().unwrap_or(0);
    if longest > window {
        return Ok(());
    }
    Err(crate::cli::UsageError(format!(
        "--window {window}: no training samples: the longest training scene has {longest} \
         frames, a sample needs T + 1 = {}",
        window + 1
    ))
    .into())
}

/// The run's one-line summary on stderr: scenes and frames per part, the core, N and T.
fn print_summary(
    (scenes, split): (usize, &crate::data::Split),
    out: &std::path::Path,
    total: usize,
    streamed: bool,
    config: &crate::model::ModelConfig,
) {
    eprintln!(
        "{} scenes, {total} frames: {} train, {} val, {} test ({}){}; core {}, N = {}, T = {}",
        scenes,
        split.scenes(Part::Train).len(),
        split.scenes(Part::Val).len(),
        split.scenes(Part::Test).len(),
        crate::model::store::RunFolder::new(out)
            .split_json()
            .display(),
        if streamed {
            ", streamed from the bags"
        } else {
            ""
        },
        config.core.name(),
        config.particles,
        config.window
    );
}

/// A paper run as [`super::fit_on`] starts it.
struct PaperFit<'a, 't, 'v> {
    /// The architecture.
    config: ModelConfig,
    /// The training options.
    opts: TrainOptions,
    /// The run folder.
    out: PathBuf,
    train: &'t mut dyn BatchSource,
    val: Option<&'v mut dyn BatchSource>,
    scaler: &'a Scaler,
    resume: bool,
    observer: &'a mut dyn Observer,
    /// What the run trains on, for its ledger.
    dataset: crate::train::DatasetInfo,
}

impl super::FitOn for PaperFit<'_, '_, '_> {
    fn fit<B: AutodiffBackend + NetOps>(
        self,
        devices: Vec<B::Device>,
    ) -> Result<Vec<EpochRecord>, TrainError>
    where
        B::InnerBackend: NetOps,
    {
        let mut trainer = Trainer::<B>::data_parallel(self.config, self.opts, self.out, devices);
        trainer.dataset = self.dataset;
        trainer.fit_observed(
            self.train,
            self.val,
            self.scaler,
            self.resume,
            self.observer,
        )
    }
}
