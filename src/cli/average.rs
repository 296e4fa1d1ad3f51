//! `minflow average`: one model whose weights are the mean of several models' weights, for
//! weights of one run taken some epochs apart (stochastic weight averaging, Izmailov et al.
//! 2018; [`crate::model::average`]). The models must share their network configuration and
//! normalisation. The output folder gets the first model's `model.json` (its constraints,
//! epoch and validation loss) and `split.json`, the averaged `model.mpk`, and `average.json`
//! naming the models and weights it came from.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use clap::Args;

use super::run_folder::fields_differing;
use super::{Outcome, UsageError};
use crate::model::average::{average, normalised};
use crate::model::store::{ModelMeta, Net, RunFolder};

/// The CPU backend the weights are averaged on.
type Cpu = burn::backend::NdArray<f32>;

/// `minflow average`'s flags.
#[derive(Debug, Args)]
pub struct AverageArgs {
    /// Run folders whose weights to average (at least two; `model.json` + `model.mpk`).
    #[arg(long = "model", value_name = "DIR", required = true, num_args = 1..)]
    models: Vec<PathBuf>,
    /// Each model's weight (one per `--model`, normalised to sum to 1); default: equal.
    #[arg(long = "weight", value_name = "W", value_parser = super::flags::non_negative)]
    weights: Vec<f64>,
    /// The run folder to write the averaged model into (not one of the `--model` folders).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
}

/// Averages the `--model` folders' weights into `--out`.
///
/// # Errors
/// [`UsageError`] for fewer than two models, weights that do not fit them, or an `--out`
/// that is one of them; a model that does not load or differs from the first in its network
/// or normalisation; a file that cannot be written.
pub fn run(args: AverageArgs) -> anyhow::Result<Outcome> {
    if args.models.len() < 2 {
        let msg = "give at least two --model folders to average".to_string();
        return Err(UsageError(msg).into());
    }
    let given = (!args.weights.is_empty()).then_some(args.weights.as_slice());
    let weights = normalised(args.models.len(), given).map_err(|e| UsageError(e.to_string()))?;
    if let Some(dir) = args.models.iter().find(|dir| same_folder(dir, &args.out)) {
        let msg = format!("--out {} is a --model folder: give another", dir.display());
        return Err(UsageError(msg).into());
    }
    let device = Default::default();
    let mut nets: Vec<Net<Cpu>> = Vec::new();
    let mut metas: Vec<ModelMeta> = Vec::new();
    for dir in &args.models {
        let (net, meta) = (RunFolder::new(dir).load::<Cpu>(&device))
            .with_context(|| format!("loading {}", dir.display()))?;
        if let Some(first) = metas.first() {
            let (this, first_dir) = (dir.display(), args.models[0].display());
            same_network(first, &meta)
                .with_context(|| format!("{this} cannot be averaged with {first_dir}"))?;
        }
        nets.push(net);
        metas.push(meta);
    }
    // `Net` is a module of either architecture; same_network checked they are one.
    let net = average(nets, Some(&weights))?;
    save(&args, &net, &metas, &weights)?;
    Ok(Outcome::Done)
}

/// Whether `a` and `b` name one folder (`b` need not exist yet).
fn same_folder(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => a == b,
    }
}

/// Networks of one configuration and normalisation: every field of their `model.json`
/// descriptions equal but the convolution form (`conv`), which does not change the weights.
fn same_network(first: &ModelMeta, other: &ModelMeta) -> anyhow::Result<()> {
    let (a, b) = (
        serde_json::to_value(&first.net)?,
        serde_json::to_value(&other.net)?,
    );
    let describe = |key: &str, theirs: &str, value: &serde_json::Value| {
        format!("{key}: {value} in the first, {theirs} here")
    };
    let fields = fields_differing(&b, &a, &["conv"], describe);
    if !fields.is_empty() {
        bail!("their networks differ (model.json): {}", fields.join("; "));
    }
    if serde_json::to_value(&first.scaler)? != serde_json::to_value(&other.scaler)? {
        bail!("their normalisations differ (model.json's scaler: not one run's weights)");
    }
    Ok(())
}

/// Writes the averaged network with the first model's `model.json` and `split.json` (an
/// older `split.json` in `--out` removed where the first has none), and `average.json` with
/// the sources and their normalised `weights`.
fn save(
    args: &AverageArgs,
    net: &Net<Cpu>,
    metas: &[ModelMeta],
    weights: &[f64],
) -> anyhow::Result<()> {
    let out = RunFolder::new(&args.out);
    match net {
        Net::Grid(m) => out.save(m, &metas[0]),
        Net::Paper(m) => out.save(m, &metas[0]),
    }
    .with_context(|| format!("writing {}", args.out.display()))?;
    let (split, out_split) = (
        RunFolder::new(&args.models[0]).split_json(),
        out.split_json(),
    );
    let copied = match split.exists() {
        true => std::fs::copy(&split, &out_split).map(drop),
        false => std::fs::remove_file(&out_split).or_else(|e| match e.kind() {
            std::io::ErrorKind::NotFound => Ok(()),
            _ => Err(e),
        }),
    };
    copied.with_context(|| format!("writing {}", out_split.display()))?;
    let sources: Vec<serde_json::Value> = (args.models.iter().zip(metas).zip(weights))
        .map(|((dir, meta), weight)| {
            serde_json::json!({
                "model": dir.display().to_string(),
                "epoch": meta.epoch,
                "val_loss": meta.val_loss,
                "weight": weight,
            })
        })
        .collect();
    let path = args.out.join("average.json");
    let text = serde_json::to_string_pretty(&serde_json::json!({ "averaged": sources }))?;
    std::fs::write(&path, text + "\n").with_context(|| format!("writing {}", path.display()))?;
    println!(
        "wrote {} (the mean of {} models' weights)",
        args.out.display(),
        metas.len()
    );
    Ok(())
}
