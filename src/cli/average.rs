//! `minflow average`: one model whose weights are the mean of several models' weights, for
//! weights of one run taken some epochs apart (stochastic weight averaging, Izmailov et al.
//! 2018; [`crate::model::average`]). The models must share their network configuration and
//! normalisation. The output folder gets the first model's `model.json` (its constraints,
//! epoch and validation loss) and `split.json`, the averaged `model.mpk`, and `average.json`
//! naming the models and weights it came from.

use std::path::PathBuf;

use anyhow::{bail, Context};
use clap::Args;

use super::{Outcome, UsageError};
use crate::model::average::average;
use crate::model::store::{ModelMeta, Net, RunFolder};

/// The CPU backend the weights are averaged on.
type Cpu = burn::backend::NdArray<f32>;

#[derive(Debug, Args)]
pub struct AverageArgs {
    /// Run folders whose weights to average (at least two; `model.json` + `model.mpk`).
    #[arg(long = "model", value_name = "DIR", required = true, num_args = 1..)]
    models: Vec<PathBuf>,
    /// Each model's weight (one per `--model`, normalised to sum to 1); default: equal.
    #[arg(long = "weight", value_name = "W", value_parser = super::flags::non_negative)]
    weights: Vec<f64>,
    /// The run folder to write the averaged model into.
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
}

pub fn run(args: AverageArgs) -> anyhow::Result<Outcome> {
    let (models, weights) = (args.models.len(), args.weights.len());
    if models < 2 {
        let msg = "give at least two --model folders to average".to_string();
        return Err(UsageError(msg).into());
    }
    if weights != 0 && weights != models {
        let msg = format!("{weights} --weight values for {models} --model folders");
        return Err(UsageError(msg).into());
    }
    if weights != 0 && args.weights.iter().sum::<f64>() <= 0.0 {
        return Err(UsageError("the --weight values sum to 0".to_string()).into());
    }
    let device = Default::default();
    let mut nets = Vec::new();
    let mut metas: Vec<ModelMeta> = Vec::new();
    for dir in &args.models {
        let (net, meta) = (RunFolder::new(dir).load::<Cpu>(&device))
            .with_context(|| format!("loading {}", dir.display()))?;
        if let Some(first) = metas.first() {
            same_network(first, &meta).with_context(|| {
                format!(
                    "{} cannot be averaged with {}",
                    dir.display(),
                    args.models[0].display()
                )
            })?;
        }
        nets.push(net);
        metas.push(meta);
    }
    let weights = (!args.weights.is_empty()).then_some(args.weights.as_slice());
    // same_network checked that every network has the first's architecture.
    let net = match nets[0] {
        Net::Grid(_) => {
            let grid = |n| if let Net::Grid(m) = n { Some(m) } else { None };
            Net::Grid(average(of_one_kind(nets, grid), weights)?)
        }
        Net::Paper(_) => {
            let paper = |n| if let Net::Paper(m) = n { Some(m) } else { None };
            Net::Paper(average(of_one_kind(nets, paper), weights)?)
        }
    };
    save(&args, net, &metas)?;
    Ok(Outcome::Done)
}

/// Each network's module of one architecture (`module`: None for the other).
fn of_one_kind<M>(nets: Vec<Net<Cpu>>, module: fn(Net<Cpu>) -> Option<M>) -> Vec<M> {
    let one = |n| module(n).expect("same_network checked the architecture");
    nets.into_iter().map(one).collect()
}

/// Networks of one configuration and normalisation (their JSON descriptions equal).
fn same_network(first: &ModelMeta, other: &ModelMeta) -> anyhow::Result<()> {
    if serde_json::to_value(&first.net)? != serde_json::to_value(&other.net)? {
        bail!("their network configurations differ (model.json)");
    }
    if serde_json::to_value(&first.scaler)? != serde_json::to_value(&other.scaler)? {
        bail!("their normalisations differ (model.json's scaler: not one run's weights)");
    }
    Ok(())
}

/// Writes the averaged network with the first model's `model.json` and `split.json`, and
/// `average.json` with the sources.
fn save(args: &AverageArgs, net: Net<Cpu>, metas: &[ModelMeta]) -> anyhow::Result<()> {
    let out = RunFolder::new(&args.out);
    match &net {
        Net::Grid(m) => out.save(m, &metas[0]),
        Net::Paper(m) => out.save(m, &metas[0]),
    }
    .with_context(|| format!("writing {}", args.out.display()))?;
    let first = RunFolder::new(&args.models[0]);
    if first.split_json().exists() {
        std::fs::copy(first.split_json(), out.split_json())
            .with_context(|| format!("writing {}", out.split_json().display()))?;
    }
    let n = args.models.len() as f64;
    let total: f64 = args.weights.iter().sum();
    let sources: Vec<serde_json::Value> = (args.models.iter().zip(metas).enumerate())
        .map(|(i, (dir, meta))| {
            serde_json::json!({
                "model": dir.display().to_string(),
                "epoch": meta.epoch,
                "val_loss": meta.val_loss,
                "weight": args.weights.get(i).map_or(1.0 / n, |w| w / total),
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
