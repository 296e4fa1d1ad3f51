//! `minflow demo`: the main job on a fresh machine (README, first line). Lists the bundled bags
//! in `bags/`, takes the shipped small grid minGRU of the long run
//! (`models/all-grid-mingru-small-k4-long`, README "Results": trained on 2,000 scenes, 3.2 M
//! samples; the closest over 20 frames, and its liquid runs up walls and is thrown across the
//! box as the solver's; `--train`, or a
//! `--model` folder that holds no model, trains one on the bundled bags first, in this
//! process), then launches `launch_configs/replay_eval.yaml` over zenoh with an embedded peer
//! (replay -> surrogate node in closed loop -> recorder -> `eval --pred --truth`), which prints
//! the replay evaluation table beside the `persist` and `constvel` baselines. With `--grid 128`
//! or `256` the demo at scale: one `multi` scene of 10,000 or 40,000 particles simulated on the
//! spot (seed 7: no shipped model trained on it) and served by the scale model
//! (`models/scale-grid-mingru-small-k4`) the same way.

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
    /// Run folder of the model (by default `models/all-grid-mingru-small-k4-long`, a small
    /// grid minGRU that predicts 4 frames per network call, trained on 2,000 scenes: the
    /// closest to the truth over 20 frames and, with `-rest`, over whole scenes; with
    /// --grid the scale model, `models/scale-grid-mingru-small-k4`); trained here first if
    /// it holds no model.
    #[arg(long)]
    model: Option<PathBuf>,
    /// The demo at scale: instead of the bundled bags, simulate `--scene` of the `multi`
    /// family on an N x N grid (128: 10,000 particles, 256: 40,000; `simulate --grid`) into
    /// `OUT/truth@N-SCENE` and serve it.
    #[arg(long, value_parser = clap::builder::PossibleValuesParser::new(["128", "256"]))]
    grid: Option<String>,
    /// With --grid: the `multi` scene id simulated (2: a jelly disk falling into a liquid;
    /// `simulate --family multi` lists the kinds), with seed 7. Scene 4 stops in the solver
    /// on 256^2 (a liquid jet faster than check 6 allows, docs/mpm.md).
    #[arg(long, default_value_t = 2, requires = "grid")]
    scene: u32,
    /// Where `--train` (or a missing model) trains the demo's own model.
    #[arg(long, default_value = "runs/demo-grid-mingru")]
    train_out: PathBuf,
    /// Output folder of the replay evaluation (its `eval/` is replaced by each run's).
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
    /// --model (not with --grid: a model of the bundled 2,500-particle scenes).
    #[arg(long, alias = "retrain", conflicts_with = "grid")]
    train: bool,
}

pub fn run(args: DemoArgs) -> anyhow::Result<Outcome> {
    let start = Instant::now();
    let bags = demo_bags(&args)?;
    let model = demo_model(&args)?;
    clear_last_eval(&args.out)?;
    println!(
        "\n== launch replay_eval over {}: replay {} -> surrogate node (closed loop, {} frames) -> record -> eval ==",
        args.transport,
        bags.display(),
        args.horizon
    );
    let file = crate::launch::bundled("replay_eval");
    let overrides = [
        ("model", model.display().to_string()),
        ("bags", bags.display().to_string()),
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

/// Removes `out/eval`, the tables and renders of the demo's previous run, so the folder
/// holds only this run's (its predictions bag is overwritten by the recorder; the scenes
/// simulated for `--grid`, `out/truth@...`, are kept for the next run).
///
/// # Errors
///
/// When the folder exists and cannot be removed.
fn clear_last_eval(out: &std::path::Path) -> anyhow::Result<()> {
    let eval = out.join("eval");
    if eval.is_dir() {
        std::fs::remove_dir_all(&eval)
            .with_context(|| format!("removing the last demo's {}", eval.display()))?;
    }
    Ok(())
}

/// The ground truth the demo replays: the bundled bags, or with `--grid` one scene simulated
/// here into `OUT/truth@GRID-SCENE`; listed on stdout.
fn demo_bags(args: &DemoArgs) -> anyhow::Result<PathBuf> {
    let bags = match &args.grid {
        None => args.bags.clone(),
        Some(grid) => {
            // A folder per setting: the replay takes every bag it finds there.
            let out = args.out.join(format!("truth@{grid}-{}", args.scene));
            let frames = (args.horizon + 4).to_string();
            let scene = args.scene.to_string();
            let out_s = out.display().to_string();
            let argv = [
                "--family", "multi", "--seed", "7", "--scenes", &scene, "--grid", grid, "--frames",
                &frames, "--out", &out_s,
            ];
            println!(
                "== simulating multi scene {scene} on a {grid}^2 grid ({frames} frames, seed 7) =="
            );
            let sim = super::flags::parse(&argv).context("the demo's simulate flags")?;
            super::simulate::run(sim).context("simulating the demo's scene")?;
            out
        }
    };
    let found = bag::bag_paths(std::slice::from_ref(&bags))
        .with_context(|| format!("finding the bags in {}", bags.display()))?;
    let info = bag::info(&found).context("reading the bags")?;
    println!("== ground truth ({}) ==", bags.display());
    for f in &info.files {
        let scenes: Vec<&str> = f.scenes.keys().map(String::as_str).collect();
        println!(
            "{:<40} {:>5} frames  {}",
            f.path.display(),
            f.messages,
            scenes.join(", ")
        );
    }
    Ok(bags)
}

/// The demo's model: `--model` (by default the shipped small `-long` model, or with `--grid`
/// the scale model), or one trained here on the bundled bags (`--train`, or a `--model` folder
/// without a model; with `--grid`, an error instead).
fn demo_model(args: &DemoArgs) -> anyhow::Result<PathBuf> {
    let shipped = match args.grid {
        Some(_) => "models/scale-grid-mingru-small-k4",
        None => "models/all-grid-mingru-small-k4-long",
    };
    let model = args.model.clone().unwrap_or_else(|| PathBuf::from(shipped));
    let found = RunFolder::new(&model).model_json().is_file();
    if args.grid.is_some() && !found {
        bail!(
            "no model in {} to serve the scene at scale (a 2,500-particle model trained here \
             would not do): run from the repository root or give --model",
            model.display()
        );
    }
    if !args.train && found {
        println!(
            "\n== model: {} (shipped; --train to train one on the bundled bags) ==",
            model.display()
        );
        return Ok(model);
    }
    if !args.train {
        println!("\n(no model in {}: training one)", model.display());
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
    Ok(args.train_out.clone())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_demo_clears_the_last_runs_eval_and_keeps_its_simulated_truth() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path();
        std::fs::create_dir_all(out.join("eval")).unwrap();
        std::fs::write(out.join("eval/render_multi_liquid_004.png"), b"stale").unwrap();
        std::fs::create_dir_all(out.join("truth@256-2")).unwrap();
        std::fs::write(out.join("truth@256-2/multi_jelly+liquid_002.mcap"), b"bag").unwrap();
        clear_last_eval(out).unwrap();
        assert!(!out.join("eval").exists());
        assert!(out
            .join("truth@256-2/multi_jelly+liquid_002.mcap")
            .is_file());
        // Nothing to clear: no error.
        clear_last_eval(&out.join("missing")).unwrap();
    }
}
