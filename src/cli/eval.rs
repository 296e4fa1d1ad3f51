//! `minflow eval`: rollout metrics of trained models and the two baselines on ground-truth
//! bags (`--model DIR... --data DIR`), or of a recorded bag of predicted frames
//! (`--pred BAG --truth BAG|DIR`), written as tables, curves and renders into `--out` (see
//! [`crate::eval`]); the main table is printed on stdout.
//!
//! Scaling rule (one for every mode and for the baselines): the first `--model`'s stored
//! scaler when a model is given, otherwise a scaler fitted on the training split of the
//! ground-truth data (the seeded 80:10:10 split of `minflow train`, `--seed`). Direct
//! evaluation rolls out the scenes of `--split` (test by default) of that same split.
//! Exit code 3 when predicted frames were missing or a bag was truncated.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use clap::Args;

use super::flags::Horizon;
use super::Outcome;
use crate::bag::{FRAMES_TOPIC, PREDICTED_TOPIC};
use crate::data::{self, Part, Scaler, Split, StreamingLoader};
use crate::eval::{
    self, output, ConstVel, Evaluation, ModelPredictor, Persist, Predictor, ReferenceFrom,
    ReplayOptions, RolloutOptions,
};
use crate::model::constraints::Parts;
use crate::model::store::RunFolder;

#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Run folder of a trained model (`minflow train --out`); repeat for several models.
    #[arg(long = "model", value_name = "DIR")]
    pub models: Vec<PathBuf>,
    /// Ground-truth bags or folders of bags: roll every model out on them.
    #[arg(long, num_args = 1.., conflicts_with = "pred")]
    pub data: Vec<PathBuf>,
    /// Which scenes of the seeded 80:10:10 split to roll out: test | val | train | all.
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Seed of the split (use the one the models were trained with).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Steps predicted per rollout H (the paper's avg20 / f20: 20), or `full`: one rollout
    /// per trajectory from its seed frames to its last frame (avg_full / f_full; --data only).
    #[arg(long, default_value = "20", value_parser = super::flags::horizon)]
    pub horizon: super::flags::Horizon,
    /// Skip the plausibility metrics (Sinkhorn divergence per material, strain error of the
    /// solids; structure: volume ratio, intact fraction, rope connectivity) at steps 20, 50,
    /// 100, 200, ... and the rollout's end.
    #[arg(long)]
    pub no_plausibility: bool,
    /// Rollouts per trajectory from evenly spaced start frames (1: from the first frame).
    #[arg(long, default_value_t = 1, value_parser = super::flags::at_least_one)]
    pub starts: usize,
    /// Seed frames before the first prediction when no model is given (else the largest
    /// model window T).
    #[arg(long, default_value_t = 2)]
    pub window: usize,
    /// Topic of the ground-truth frames.
    #[arg(long, default_value = FRAMES_TOPIC)]
    pub topic: String,
    /// Bags of predicted frames (recorded from a surrogate node) to score.
    #[arg(long, num_args = 1.., requires = "truth")]
    pub pred: Vec<PathBuf>,
    /// Ground-truth bags or folders for --pred.
    #[arg(long, num_args = 1..)]
    pub truth: Vec<PathBuf>,
    /// Topic of the predicted frames in --pred.
    #[arg(long, default_value = PREDICTED_TOPIC)]
    pub pred_topic: String,
    /// Column name of --pred in the tables.
    #[arg(long, default_value = "pred")]
    pub name: String,
    /// --pred holds one-step predictions of every replayed frame: baselines predict one step
    /// from the truth too (default: a closed-loop rollout, baselines roll out as well).
    #[arg(long)]
    pub one_step: bool,
    /// Write each rollout's predicted frames as an MCAP bag on /surrogate/frames under DIR
    /// (`DIR/<predictor>/<scene>_from<frame>.mcap`): view them in Foxglove, score them with
    /// `eval --pred` (--data only).
    #[arg(long, value_name = "DIR", conflicts_with = "pred")]
    pub save_pred: Option<PathBuf>,
    /// Output folder (tables, curves, renders).
    #[arg(short, long, default_value = "eval")]
    pub out: PathBuf,
    /// Density-map grid G of the density-error diagnostic.
    #[arg(long, default_value_t = 32)]
    pub density_grid: usize,
    /// Skip the particle renders (PNG grid and GIF per scene).
    #[arg(long)]
    pub no_render: bool,
    /// Where models with reference positions (`train --reference first-frame`) take them:
    /// scene-start (the scene's frame 0, as a node that saw the stream from its start) |
    /// rollout-start (the first seed frame of each rollout, as a node that joined there).
    #[arg(long, value_enum, default_value_t = ReferenceFrom::SceneStart)]
    pub reference_from: ReferenceFrom,
    /// Step grid models as a mirror ensemble: each frame and its mirror image about the
    /// box's vertical midline, predictions averaged (test-time augmentation by a symmetry of
    /// MPM's box; twice the work of a step).
    #[arg(long)]
    pub mirror: bool,
    /// Which parts of each model's material constraints every predicted frame is projected onto: on
    /// (all the model has; `minflow constraints fit` writes them) | off | a list of rope, jelly,
    /// snow, liquid, walls, contact, momentum, rebound, pressure. Repeat to evaluate each model
    /// once per setting (columns `NAME[setting]`): an ablation in one run.
    #[arg(long = "constraints", value_name = "PARTS", default_value = "on")]
    pub constraints: Vec<Parts>,
    #[command(flatten)]
    pub device: super::device::DeviceArgs,
}

/// Parses `--split`.
pub(crate) fn parse_split(s: &str) -> anyhow::Result<Option<Part>> {
    Ok(match s {
        "test" => Some(Part::Test),
        "val" => Some(Part::Val),
        "train" => Some(Part::Train),
        "all" => None,
        other => bail!("unknown --split {other:?} (test | val | train | all)"),
    })
}

/// Column names for run folders: the folder name, made unique.
pub(crate) fn model_names(dirs: &[PathBuf]) -> Vec<String> {
    let mut names: Vec<String> = Vec::new();
    for dir in dirs {
        let base = dir.file_name().map_or_else(
            || dir.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        );
        let mut name = base.clone();
        let mut i = 2;
        while names.contains(&name) || name == "persist" || name == "constvel" {
            name = format!("{base}#{i}");
            i += 1;
        }
        names.push(name);
    }
    names
}

/// The scaler by the rule of the module doc, and where it comes from.
pub(crate) fn scaler_for(
    models: &[PathBuf],
    data: &[PathBuf],
    topic: &str,
    seed: u64,
) -> anyhow::Result<(Scaler, String)> {
    if let Some(dir) = models.first() {
        let meta = RunFolder::new(dir).meta().context("reading the model")?;
        return Ok((
            meta.scaler,
            format!("scaled with the scaler stored in {}", dir.display()),
        ));
    }
    let infos = data::scan(data, Some(topic)).context("reading the ground-truth bags")?;
    let split = Split::new(infos.iter().map(|s| &s.scene), seed);
    let train: Vec<_> = infos
        .into_iter()
        .filter(|s| split.part_of(&s.scene) == Some(Part::Train))
        .collect();
    // Streamed chunk by chunk, so a paper-sized training split need not fit in memory.
    let budget = train
        .iter()
        .map(|s| s.frames)
        .max()
        .unwrap_or(1)
        .max(50_000);
    let scaler = StreamingLoader::fit_scaler(train, Some(topic), budget)
        .context("fitting the scaler on the training scenes")?;
    Ok((
        scaler,
        format!(
            "scaled with a scaler fitted on the {} training scenes of the data (split seed {seed})",
            split.train.len()
        ),
    ))
}

/// Direct evaluation: loads the models and the scenes of `part`, rolls everything out.
/// Returns the evaluation, the number of model columns and the outcome (data lost when a
/// bag was truncated: its frames before the damage were used).
pub(crate) fn direct(args: &EvalArgs) -> anyhow::Result<(Evaluation, usize, Outcome)> {
    let part = parse_split(&args.split)?;
    let names = model_names(&args.models);
    let device = args.device.parse()?.single("eval")?;
    let device = device.map(|id| (id, args.device.kernels()));
    let mut models: Vec<Box<dyn Predictor>> = Vec::new();
    let mut settings = args.constraints.clone();
    settings.dedup();
    for (dir, name) in args.models.iter().zip(&names) {
        let has = RunFolder::new(dir)
            .meta()
            .with_context(|| format!("loading model {}", dir.display()))?
            .constraints
            .is_some_and(|c| !c.is_empty());
        let settings = if has { &settings[..] } else { &settings[..1] };
        for &parts in settings {
            let name = match settings.len() {
                1 => name.clone(),
                _ => format!("{name}[{parts}]"),
            };
            let opened = (args.reference_from, args.mirror, parts);
            models.push(load_model(dir, &name, device, opened)?);
        }
    }
    let topic = args.topic.as_str();
    let infos = data::scan(&args.data, Some(topic)).context("reading the ground-truth bags")?;
    let split = Split::new(infos.iter().map(|s| &s.scene), args.seed);
    // `--split all` rolls out every scene: which of them a model held out does not matter.
    if part.is_some() {
        for dir in &args.models {
            warn_if_split_differs(dir, &split);
        }
    }
    let scenes: Vec<String> = match part {
        Some(p) => split.scenes(p).to_vec(),
        None => infos.iter().map(|s| s.scene.clone()).collect(),
    };
    if scenes.is_empty() {
        bail!(
            "no {} scenes among the {} scenes of {:?} (split seed {}; with fewer than 3 scenes all are training scenes); try --split all",
            args.split,
            infos.len(),
            args.data,
            args.seed
        );
    }
    let (scaler, source) = scaler_for(&args.models, &args.data, topic, args.seed)?;
    let (trajs, report) =
        data::load_scenes(&args.data, Some(topic), &scenes).context("loading the scenes")?;
    for gap in &report.gaps {
        tracing::warn!("{gap}");
    }
    let mut predictors: Vec<&dyn Predictor> = models.iter().map(|m| m.as_ref()).collect();
    predictors.extend([&Persist as &dyn Predictor, &ConstVel]);
    let opts = RolloutOptions {
        horizon: match args.horizon {
            Horizon::Steps(k) => k,
            Horizon::Full => 0,
        },
        starts: args.starts,
        window: args.window,
        density_grid: args.density_grid,
        snapshots: !args.no_render,
        full: args.horizon == Horizon::Full,
        plausibility: !args.no_plausibility,
        save_pred: args.save_pred.clone(),
    };
    let bar = super::progress(0, "rollouts");
    let eval = eval::evaluate(&trajs, &predictors, &scaler, &source, &opts, &bar)?;
    bar.finish_and_clear();
    Ok((eval, models.len(), super::read_to_damage(&report.truncated)))
}

/// A run folder's model on the CPU (`None`) or on CUDA GPU `cuda` (its ordinal and the
/// kernel choices it is opened with).
fn load_model(
    dir: &Path,
    name: &str,
    cuda: Option<(usize, crate::ops::Kernels)>,
    (reference, mirror, parts): (ReferenceFrom, bool, Parts),
) -> anyhow::Result<Box<dyn Predictor>> {
    Ok(match cuda {
        None => Box::new(
            ModelPredictor::load(dir, name)?
                .with_reference_from(reference)
                .with_mirror(mirror)
                .with_constraints(parts),
        ),
        #[cfg(feature = "cuda")]
        Some((id, kernels)) => {
            use super::device::cuda::{device, CudaInfer};
            Box::new(
                ModelPredictor::<CudaInfer>::load_on(dir, name, &device(id, kernels)?)?
                    .with_reference_from(reference)
                    .with_mirror(mirror)
                    .with_constraints(parts),
            )
        }
        #[cfg(not(feature = "cuda"))]
        Some(_) => bail!("built without CUDA"),
    })
}

/// Warns when a run folder's `split.json` puts other scenes in the test part (counts and the
/// first few names of each: a long run's split holds hundreds).
fn warn_if_split_differs(dir: &Path, split: &Split) {
    if let Some(theirs) = RunFolder::new(dir).split() {
        if theirs.test != split.test {
            tracing::warn!(
                "{}: the model's {} test scenes ({}) differ from this split's {} ({}); check --seed and --data",
                dir.display(),
                theirs.test.len(),
                first_names(&theirs.test),
                split.test.len(),
                first_names(&split.test)
            );
        }
    }
}

/// Up to three scene names, then how many more.
fn first_names(scenes: &[String]) -> String {
    let mut shown = scenes
        .iter()
        .take(3)
        .cloned()
        .collect::<Vec<_>>()
        .join(", ");
    if scenes.len() > 3 {
        shown.push_str(&format!(", ... {} more", scenes.len() - 3));
    }
    shown
}

/// Replay evaluation of `--pred` against `--truth`.
fn replay(args: &EvalArgs) -> anyhow::Result<(Evaluation, bool)> {
    let preds = eval::read_predictions(&args.pred, Some(&args.pred_topic))
        .context("reading the predicted frames")?;
    let scenes: Vec<String> = preds.scenes.keys().cloned().collect();
    let (truth, report) = data::load_scenes(&args.truth, Some(&args.topic), &scenes)
        .context("reading the ground truth")?;
    let (scaler, source) = scaler_for(&args.models, &args.truth, &args.topic, args.seed)?;
    let Horizon::Steps(horizon) = args.horizon else {
        return Err(super::UsageError(
            "--horizon full rolls models out on --data; for --pred give a number of steps".into(),
        )
        .into());
    };
    let opts = ReplayOptions {
        horizon,
        one_step: args.one_step,
        density_grid: args.density_grid,
        snapshots: !args.no_render,
    };
    let baselines: [&dyn Predictor; 2] = [&Persist, &ConstVel];
    let eval = eval::score_predictions(
        &preds, &args.name, &truth, &baselines, &scaler, &source, &opts,
    )?;
    let lost = !preds.truncated.is_empty() || !report.truncated.is_empty();
    Ok((eval, lost))
}

pub fn run(args: EvalArgs) -> anyhow::Result<Outcome> {
    let (eval, models, lost) = match (args.pred.is_empty(), args.data.is_empty()) {
        (true, false) => {
            let (eval, models, outcome) = direct(&args)?;
            (eval, models, outcome == Outcome::DataLost)
        }
        (false, true) => {
            let (eval, lost) = replay(&args)?;
            (eval, 1, lost)
        }
        _ => bail!("give either --data (with --model DIR...) or --pred BAG --truth BAG|DIR"),
    };
    let bar = super::progress(0, "renders");
    let title = if args.pred.is_empty() {
        "minflow eval: rollouts"
    } else {
        "minflow eval: recorded predictions"
    };
    let files = output::write_all(&args.out, &eval, models, title, &bar)?;
    bar.finish_and_clear();
    print!("{}", eval::table::markdown(&eval));
    for note in &eval.notes {
        eprintln!("note: {note}");
    }
    let scenes = if args.pred.is_empty() {
        format!("{} scenes of the {} split", eval.scenes.len(), args.split)
    } else {
        format!("{} predicted scenes", eval.scenes.len())
    };
    eprintln!(
        "{scenes}, {}; {} files in {}",
        eval.scaler_source,
        files.len(),
        args.out.display()
    );
    if eval.missing() > 0 {
        eprintln!(
            "{} predicted frames missing (excluded from the scores)",
            eval.missing()
        );
    }
    if eval.missing() > 0 || lost {
        return Ok(Outcome::DataLost);
    }
    Ok(Outcome::Done)
}

/// `--reference-from`'s values, each with its help line.
impl clap::ValueEnum for ReferenceFrom {
    fn value_variants<'a>() -> &'a [Self] {
        &[ReferenceFrom::SceneStart, ReferenceFrom::RolloutStart]
    }

    fn to_possible_value(&self) -> Option<clap::builder::PossibleValue> {
        let (name, help) = match self {
            ReferenceFrom::SceneStart => (
                "scene-start",
                "The trajectory's frame 0: a node that has seen the stream from its start",
            ),
            ReferenceFrom::RolloutStart => (
                "rollout-start",
                "The first frame of the rollout's seed window: a node that joined the stream \
                 there",
            ),
        };
        Some(clap::builder::PossibleValue::new(name).help(help))
    }
}

#[cfg(test)]
mod tests {
    use super::first_names;

    #[test]
    fn a_long_list_of_scenes_is_named_by_its_first_three_and_a_count() {
        let scenes: Vec<String> = (0..200).map(|i| format!("fluid/circle/{i:03}")).collect();
        assert_eq!(
            first_names(&scenes),
            "fluid/circle/000, fluid/circle/001, fluid/circle/002, ... 197 more"
        );
        assert_eq!(
            first_names(&scenes[..2]),
            "fluid/circle/000, fluid/circle/001"
        );
    }
}
