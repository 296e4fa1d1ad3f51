//! `minflow demo`: the main job on a fresh machine (README, first line). Lists the bundled bags
//! in `bags/`, takes the shipped small bundled grid minGRU (`models/all-grid-mingru-small-k4`;
//! `--train`, or a `--model` folder that holds no model, trains one on the bundled bags first,
//! in this process), then launches `launch_configs/replay_eval.yaml` over zenoh with an
//! embedded peer (replay -> surrogate node in closed loop -> recorder -> `eval --pred
//! --truth`), which prints the replay evaluation table beside the `persist` and `constvel`
//! baselines.

use super::train::TrainArgs;
use super::Outcome;
use crate::bag;
use crate::model::store::RunFolder;
use crate::node::shutdown_flag;
use anyhow::{bail, Context};
use clap::Args;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Bundled ground-truth bags.
    #[arg(long, default_value = "bags")]
    bags: PathBuf,
    /// Run folder of the model (by default the shipped small grid minGRU that predicts 4
    /// frames per network call, the cheapest shipped model; `models/all-grid-mingru-rest` has
    /// the lowest errors); trained here first if it holds no model.
    #[arg(long, default_value = "models/all-grid-mingru-small-k4")]
    model: PathBuf,
    /// Where `--train` (or a missing model) trains the demo's own model.
    #[arg(long, default_value = "runs/demo-grid-mingru")]
    train_out: PathBuf,
    /// Output folder of the replay evaluation.
    #[arg(short, long, default_value = "runs/demo")]
    out: PathBuf,
    /// Transport of the replay evaluation.
    #[arg(long, default_value = "zenoh")]
    transport: String,
    /// Frames the node predicts per scene in closed loop.
    #[arg(long, default_value_t = 20)]
    horizon: u32,
    /// Which parts of the model's material constraints the node projects every predicted
    /// frame onto: on (all the model has) | off | a list of rope, jelly, snow, liquid,
    /// walls, contact, momentum, rebound, pressure.
    #[arg(long, value_name = "PARTS", default_value = "on")]
    constraints: crate::model::constraints::Parts,
    /// Training epochs when a model is trained.
    #[arg(long, default_value_t = 6)]
    epochs: u32,
    /// Train a grid minGRU on the bundled bags (into --train-out) and use it instead of
    /// --model.
    #[arg(long, alias = "retrain")]
    train: bool,
}

pub fn run(args: DemoArgs) -> anyhow::Result<Outcome> {
    let start = Instant::now();
    let bundled = bag::bag_paths(std::slice::from_ref(&args.bags))
        .with_context(|| format!("finding the bundled bags in {}", args.bags.display()))?;
    let info = bag::info(&bundled).context("reading the bundled bags")?;
    println!("== bundled bags ({}) ==", args.bags.display());
    for f in &info.files {
        let scenes: Vec<&str> = f.scenes.keys().map(String::as_str).collect();
        println!(
            "{:<40} {:>5} frames  {}",
            f.path.display(),
            f.messages,
            scenes.join(", ")
        );
    }
    let model = if args.train || !RunFolder::new(&args.model).model_json().is_file() {
        if !args.train {
            println!("\n(no model in {}: training one)", args.model.display());
        }
        println!(
            "\n== training a small grid minGRU on {} ({} epochs) ==",
            args.bags.display(),
            args.epochs
        );
        let mut train: TrainArgs = super::flags::defaults(&["--data", "--out"])?;
        train.data = vec![args.bags.clone()];
        train.out = args.train_out.clone();
        train.epochs = args.epochs as usize;
        train.batch_size = 4;
        train.patience = 0;
        train.grid_args.net.unet_width = 16;
        train.grid_args.samples_per_epoch = 96;
        crate::cli::train::run(train).context("training the demo model")?;
        args.train_out.clone()
    } else {
        println!(
            "\n== model: {} (shipped; --train to train one on the bundled bags) ==",
            args.model.display()
        );
        args.model.clone()
    };
    println!(
        "\n== launch replay_eval over {}: replay {} -> surrogate node (closed loop, {} frames) -> record -> eval ==",
        args.transport,
        args.bags.display(),
        args.horizon
    );
    let file = crate::launch::bundled("replay_eval");
    let overrides = [
        ("model", model.display().to_string()),
        ("bags", args.bags.display().to_string()),
        ("transport", args.transport.clone()),
        ("horizon", args.horizon.to_string()),
        ("constraints", args.constraints.to_string()),
        ("out", args.out.display().to_string()),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_owned(), v))
    .collect();
    let nodes = crate::launch::load(&file, &overrides)?;
    let stop = shutdown_flag();
    let exe = std::env::current_exe().context("locating the minflow binary")?;
    let results = crate::launch::run(&nodes, &exe, &stop)?;
    if let Some(failed) = results
        .iter()
        .find(|r| !r.status.is_some_and(|s| s.success()))
    {
        bail!("the replay evaluation failed at node {}", failed.name);
    }
    println!(
        "\nDone in {:.0} s. Predictions: {}/pred, tables and plots: {}/eval (table.md, mse_curves.png, render_*.png/gif).",
        start.elapsed().as_secs_f64(),
        args.out.display(),
        args.out.display()
    );
    Ok(Outcome::Done)
}
