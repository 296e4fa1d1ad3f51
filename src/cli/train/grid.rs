//! `minflow train --arch grid` (the default): the grid architecture's run (its flags,
//! `GridArgs`, live in `args.rs`): load the bags, split 80:10:10 by scene, fit the
//! min-max scaler and the velocity statistics on the training split, train with
//! [`crate::train::grid::GridTrainer`] (rollout loss, clipping, cosine decay, best
//! checkpoint by validation rollout error) and leave the run folder as `train --arch paper`
//! does (`model.json` + `model.mpk`, `checkpoint/`, `metrics.csv`, `loss.png`,
//! `split.json`, `train.json`).

use std::path::PathBuf;

use anyhow::{bail, Context};
use burn::tensor::backend::AutodiffBackend;

use super::args::TrainArgs;
use crate::cli::run_folder::{
    check_resume, differences, print_best, run_split, write_run_files, Progress,
};
use crate::cli::Outcome;
use crate::data::{
    Layout, Part, Scaler, ScalerFit, SceneInfo, Split, StreamingLoader, Trajectory, WindowIndex,
};
use crate::model::constraints::{Constraints, Parts};
use crate::model::grid::{GridConfig, Update};
use crate::model::store::{ModelMeta, NetConfig, RunFolder};
use crate::ops::NetOps;
use crate::train::grid::{fit_stats, GridTrainOptions, GridTrainer, StatsFit, VelocityStats};
use crate::train::{BatchSource, CallShare, DatasetInfo, EpochRecord, Observer, TrainError};

/// Runs `train --arch grid`.
///
/// # Errors
/// Bad flags (before any data is read), unreadable bags, no training scenes, training errors.
pub fn run(args: TrainArgs) -> anyhow::Result<Outcome> {
    args.refuse_paper_flags()?;
    let mut config = args.grid_config()?;
    let (opts, init) = start_point(&args, &config)?;
    let device = args.device.parse()?;
    let topic = Some(args.topic.as_str());
    let (infos, resident, report) = super::read_data(&args, topic)?;
    let scenes: Vec<String> = infos.iter().map(|s| s.scene.clone()).collect();
    let split = run_split(
        &scenes,
        args.seed,
        super::split_source(&args).as_deref(),
        args.grid_args.init_from.as_deref(),
    )?;
    let frames = config.window + opts.calls() * config.bundle - 1;
    let train_infos = split.select_infos(Part::Train, &infos);
    let (budget, streamed) = super::resident_budget(&args, &infos, &train_infos);
    let dataset = super::dataset_info(&args, &train_infos, streamed);
    // The batches written straight into one share a device (`Layout::Shares`).
    let devices = match &device {
        crate::cli::device::Device::Cuda(ids) => ids.len(),
        crate::cli::device::Device::Cpu => 1,
    };
    let layout = Layout::frames_for(devices);
    let mut data = match streamed {
        true => RunData::streamed(&args, budget, infos, &split, (frames, layout), init)?,
        false => {
            let trajs = match resident {
                Some(trajs) => trajs,
                // Bags without summary statistics fit after all: read them once more.
                None => super::load(&args.data, topic)?.0,
            };
            RunData::resident(trajs, &split, (frames, layout), init)?
        }
    };
    if data.train_scenes == 0 {
        bail!("no training scenes in {:?}", args.data);
    }
    let Normalisation { stats, scaler } = data.normalisation;
    stats.apply(&mut config);
    write_run_files(&args.out, &split, &opts)?;
    let mut index: &WindowIndex;
    let (train, streamed): (&mut dyn BatchSource, _) = match &mut data.train {
        TrainWindows::Resident(resident) => {
            index = resident;
            (&mut index, false)
        }
        TrainWindows::Streamed(loader) => (loader, true),
    };
    let counts = SceneCounts {
        all: scenes.len(),
        train: data.train_scenes,
        val: count_scenes(&data.val),
        test: data.test_scenes,
    };
    print_summary(&counts, (&*train, streamed), (&config, &opts))?;
    let mut progress = Progress::new(args.out.clone());
    let run = GridFit {
        config,
        opts,
        out: args.out.clone(),
        init_from: args.grid_args.init_from.clone(),
        train,
        val: &data.val,
        scaler: &scaler,
        resume: args.resume,
        observer: &mut progress,
        share: args.call_share(),
        dataset,
    };
    let history = super::fit_on(&device, args.device.kernels(), run)?;
    print_best(&history, "validation rollout MSE", &args.out);
    Ok(crate::cli::read_to_damage(&report.truncated))
}

/// The normalisation of a run: the velocity statistics and the min-max scaler.
#[derive(Debug, Clone, Copy)]
struct Normalisation {
    stats: VelocityStats,
    scaler: Scaler,
}

/// A grid run's training windows: in memory, or streamed from the bags a chunk at a time
/// when the dataset has more than `--max-resident-frames` frames.
enum TrainWindows {
    Resident(WindowIndex),
    Streamed(StreamingLoader),
}

/// What a grid run trains and validates on.
struct RunData {
    train: TrainWindows,
    /// Scenes in the training split.
    train_scenes: usize,
    /// The validation scenes, whole (the validation rollouts read them from frame 0), in
    /// memory even when the training scenes are streamed.
    val: Vec<Trajectory>,
    /// Scenes in the test split.
    test_scenes: usize,
    /// `--init-from`'s, or fitted on the training split.
    normalisation: Normalisation,
}

impl RunData {
    /// Every scene in memory (`trajs`), parted by `split`, windows of `frames` frames
    /// batched in `layout`.
    fn resident(
        trajs: Vec<Trajectory>,
        split: &Split,
        (frames, layout): (usize, Layout),
        init: Option<Normalisation>,
    ) -> anyhow::Result<Self> {
        let (train, val, test) = split.partition(trajs);
        let refs: Vec<&Trajectory> = train.iter().collect();
        // Weights from --init-from were trained against their run's normalisation: keep it,
        // and its scaler, so validation and `eval` score in the parent's units whatever
        // scenes were added.
        let normalisation = init.unwrap_or_else(|| Normalisation {
            stats: fit_stats(&refs),
            scaler: Scaler::fit(&refs),
        });
        Ok(Self {
            train_scenes: count_scenes(&train),
            test_scenes: count_scenes(&test),
            train: TrainWindows::Resident(
                WindowIndex::new(train, frames, Scaler::default())?.with_layout(layout),
            ),
            val,
            normalisation,
        })
    }

    /// The training scenes of `infos` streamed from their bags under `--max-resident-frames`
    /// ([`StreamingLoader`]); the normalisation, unless `init` gives it, from one chunked
    /// pass; the validation scenes read whole.
    fn streamed(
        args: &TrainArgs,
        budget: usize,
        infos: Vec<SceneInfo>,
        split: &Split,
        (frames, layout): (usize, Layout),
        init: Option<Normalisation>,
    ) -> anyhow::Result<Self> {
        let topic = Some(args.topic.as_str());
        let train = split.select_infos(Part::Train, &infos);
        let normalisation = match init {
            Some(n) => n,
            None => {
                let (mut stats, mut scaler) = (StatsFit::default(), ScalerFit::new());
                StreamingLoader::for_each_chunk(train.clone(), topic, budget, |trajs| {
                    trajs.iter().for_each(|t| {
                        stats.add(t);
                        scaler.add(t);
                    });
                })
                .context("fitting the normalisation on the training scenes")?;
                Normalisation {
                    stats: stats.finish(),
                    scaler: scaler.finish(),
                }
            }
        };
        let val = StreamingLoader::load_whole(split.select_infos(Part::Val, &infos), topic)
            .context("loading the validation scenes")?;
        Ok(Self {
            train_scenes: train.len(),
            test_scenes: split.select_infos(Part::Test, &infos).len(),
            train: TrainWindows::Streamed(
                StreamingLoader::new(train, topic, frames, Scaler::default(), budget)?
                    .with_layout(layout),
            ),
            val,
            normalisation,
        })
    }
}

/// Scenes in the data and in each part of the split, for the run's summary line.
struct SceneCounts {
    all: usize,
    train: usize,
    val: usize,
    test: usize,
}

/// Distinct scenes of `trajs` (a scene with missing frames holds several trajectories).
fn count_scenes(trajs: &[Trajectory]) -> usize {
    let mut scenes: Vec<&str> = trajs.iter().map(|t| t.scene.as_str()).collect();
    scenes.sort_unstable();
    scenes.dedup();
    scenes.len()
}

/// What a run starts from besides its data: the training options with their constraints,
/// and the normalisation that `--init-from` (or, resuming, the run's own folder) fixes; None
/// for one to fit. A resume whose flags differ from its run's is refused first.
fn start_point(
    args: &TrainArgs,
    config: &GridConfig,
) -> anyhow::Result<(GridTrainOptions, Option<Normalisation>)> {
    // A resumed run keeps what its start fixed (`--init-from` conflicts with `--resume`),
    // and its flags are checked against its checkpoint's, written from the first step on.
    let resumed = resumed_from(args);
    if args.resume {
        let saved = resumed.as_ref().map_or(args.out.as_path(), |(dir, _)| dir);
        check_resume(saved, &NetConfig::Grid(config.clone()))?;
    }
    // Its model.json, read once for the constraints and the normalisation.
    let start = match &args.grid_args.init_from {
        Some(dir) => Some((
            dir.clone(),
            (RunFolder::new(dir).meta())
                .with_context(|| format!("the model to start from, {}", dir.display()))?,
        )),
        None => resumed,
    };
    let mut opts = args.grid_options();
    let fitted = start
        .as_ref()
        .and_then(|(_, meta)| meta.constraints.clone());
    opts.constraints = training_constraints(args, fitted);
    let init = start
        .map(|(dir, meta)| init_normalisation(&dir, meta, config))
        .transpose()?;
    Ok((opts, init))
}

/// The folder whose `model.json` a resumed run (`--resume`) keeps its normalisation and
/// training constraints from, as its start fixed them (fitted, or `--init-from`'s), with
/// that `model.json`: the first that reads of its checkpoint's, the previous checkpoint's
/// (a damaged checkpoint's fallback) and its kept model's (runs checkpointed before
/// checkpoints held one). None for a fresh run, and for a resumed one with none: that fits
/// them again.
fn resumed_from(args: &TrainArgs) -> Option<(PathBuf, ModelMeta)> {
    if !args.resume {
        return None;
    }
    let folder = RunFolder::new(&args.out);
    let candidates = [
        folder.checkpoint(),
        folder.checkpoint_old(),
        args.out.clone(),
    ];
    (candidates.into_iter()).find_map(|dir| Some((dir.clone(), RunFolder::new(&dir).meta().ok()?)))
}

/// The constraints `--constraints` asks the training rollouts to project onto: the parts
/// of `fitted` (those of `--init-from`'s `model.json`, or of the resumed run's own), else
/// of the defaults; None for `off`.
fn training_constraints(args: &TrainArgs, fitted: Option<Constraints>) -> Option<Constraints> {
    let parts = args.grid_args.constraints;
    if parts == Parts::NONE {
        return None;
    }
    let c = fitted.unwrap_or_else(Constraints::defaults).select(parts);
    (!c.is_empty()).then_some(c)
}

/// The run's one-line summary on stderr (scenes: all, train, val, test; samples, the
/// network, P, K, N); a usage error when no training scene holds a sample.
fn print_summary(
    counts: &SceneCounts,
    (source, streamed): (&dyn BatchSource, bool),
    (config, opts): (&GridConfig, &crate::train::grid::GridTrainOptions),
) -> anyhow::Result<()> {
    eprintln!(
        "{} scenes: {} train ({} samples{}), {} val, {} test; grid architecture, {} memory, \
         n = {}, T = {}, P = {} (teacher {}, push-forward {}, chunks {}), K = {}{}, N = {:?}",
        counts.all,
        counts.train,
        source.windows(),
        if streamed {
            ", streamed from the bags"
        } else {
            ""
        },
        counts.val,
        counts.test,
        config.memory.name(),
        config.grid,
        config.window,
        opts.steps,
        opts.teacher,
        opts.pushforward,
        opts.chunks(),
        config.bundle,
        match (config.substeps, config.interaction) {
            (1, 0) => String::new(),
            (s, 0) => format!(", S = {s} substeps"),
            (1, r) => format!(", {r} rounds of message passing"),
            (s, r) => format!(", S = {s} substeps, {r} rounds of message passing"),
        },
        source.particle_counts(),
    );
    if source.windows() > 0 {
        return Ok(());
    }
    Err(crate::cli::UsageError(format!(
        "--window {}: no training samples: every training scene has fewer than the T + (M + C P) \
         K = {} frames a sample needs (lower --window, --rollout-steps, --pushforward, --chunks \
         or --bundle)",
        config.window,
        source.t() + 1
    ))
    .into())
}

/// The normalisation (velocity statistics and min-max scaler) of the grid model `meta`
/// (the `model.json` of `dir`: `--init-from`, or the resumed run's own), after checking that
/// it is the architecture `config` describes.
///
/// # Errors
/// `meta` holds another architecture, or one whose hyper-parameters differ (each named, a
/// usage error).
fn init_normalisation(
    dir: &std::path::Path,
    meta: ModelMeta,
    config: &GridConfig,
) -> anyhow::Result<Normalisation> {
    let path = RunFolder::new(dir).model_json();
    // A model without reference channels may grow them (`GridModel::with_reference`), a
    // single-frame model its bundle (`GridModel::with_bundle`), a model without rest shape
    // or with the free update those (`model::grid::grow`), any model another grid.
    let compared = match &meta.net {
        NetConfig::Grid(saved) => {
            let passing = if saved.interaction == 0 {
                saved
            } else {
                config
            };
            config
                .clone()
                .with_reference(config.reference && saved.reference)
                .with_bundle(if saved.bundle == 1 { 1 } else { config.bundle })
                // Substeps may change (the same weights: `GridModel::with_substeps`).
                .with_substeps(saved.substeps)
                // So may the box the positions are clamped into (`GridModel::with_box_grid`).
                .with_box_grid(saved.box_grid)
                // A model without message passing may grow it (`GridModel::with_interaction`):
                // then its own (unread) message-passing fields are compared.
                .with_interaction(passing.interaction)
                .with_interaction_radius(passing.interaction_radius)
                .with_interaction_neighbours(passing.interaction_neighbours)
                // The network grid may change (`GridModel::with_grid`).
                .with_grid(saved.grid)
                .with_rest_shape(config.rest_shape && saved.rest_shape)
                // A fitted-F model may be fine-tuned into an advected-F one and back.
                .with_deformation(saved.deformation)
                .with_update(if saved.update == Update::Free {
                    Update::Free
                } else {
                    config.update
                })
        }
        NetConfig::Paper(_) => config.clone(),
    };
    let differ = differences(
        &serde_json::to_value(&meta.net)?,
        &NetConfig::Grid(compared),
    )?;
    if !differ.is_empty() {
        return Err(crate::cli::UsageError(format!(
            "--init-from {}: its network differs from the one these flags describe ({}); \
             give the flags it was trained with",
            dir.display(),
            differ.join("; ")
        ))
        .into());
    }
    match meta.net {
        NetConfig::Grid(saved) => Ok(Normalisation {
            stats: VelocityStats {
                vel_scale: saved.vel_scale,
                dv_mean: saved.dv_mean,
                dv_scale: saved.dv_scale,
            },
            scaler: meta.scaler,
        }),
        NetConfig::Paper(_) => unreachable!("{}: compared equal to a grid config", path.display()),
    }
}

/// A grid run as [`super::fit_on`] starts it.
struct GridFit<'a> {
    /// The architecture, as fitted to the training scenes.
    config: GridConfig,
    /// The training options.
    opts: GridTrainOptions,
    /// The run folder.
    out: PathBuf,
    /// The run folder of the model to start from (`--init-from`).
    init_from: Option<PathBuf>,
    train: &'a mut dyn BatchSource,
    val: &'a [Trajectory],
    scaler: &'a Scaler,
    resume: bool,
    observer: &'a mut dyn Observer,
    /// This call's share of the run.
    share: CallShare,
    /// What the run trains on, for its ledger.
    dataset: DatasetInfo,
}

impl super::FitOn for GridFit<'_> {
    fn fit<B: AutodiffBackend + NetOps>(
        self,
        mut devices: Vec<B::Device>,
    ) -> Result<Vec<EpochRecord>, TrainError>
    where
        B::InnerBackend: NetOps,
    {
        GridTrainer::<B> {
            config: self.config,
            opts: self.opts,
            out: self.out,
            device: devices.remove(0),
            replicas: devices,
            init_from: self.init_from,
            share: self.share,
            dataset: self.dataset,
        }
        .fit(
            self.train,
            self.val,
            self.scaler,
            self.resume,
            self.observer,
        )
    }
}
