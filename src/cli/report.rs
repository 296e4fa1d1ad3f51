//! `minflow report --data DIR --out DIR`: the paper's experiment end to end on one dataset.
//! Trains the five cores (mlp, lstm, gru, minlstm, mingru) in each architecture (`--archs`:
//! the paper's pooled encoder-decoder and the grid architecture, where `mlp` is the grid
//! model without memory, `none`) with one configuration (`minflow train`, into
//! `OUT/runs/<arch>-<core>`), evaluates them side by side with the baselines on the test
//! scenes (`minflow eval`, into `OUT/eval`), measures training speed from the runs
//! themselves (seconds per epoch and microseconds per sample, the paper's Table 4), and
//! writes `OUT/REPORT.md`: the machine (CPU model, cores), the configuration and seed,
//! Tables 2 (fluid scenes), 3 (multi-material scenes) and 4, the detailed metrics and the
//! figures. Flags shorten it (`--epochs`, `--width`, `--encoder-hidden`, `--cores`,
//! `--grid`, `--samples-per-epoch`) for a quick run on the bundled bags; `--reuse` keeps runs
//! that already have a model.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context};
use burn::module::Module;
use clap::Args;

use super::eval::{direct, EvalArgs};
use super::train::TrainArgs;
use super::Outcome;
use crate::eval::{output, table, CpuInfer, Evaluation};
use crate::model::store::RunFolder;

#[derive(Debug, Args)]
pub struct ReportArgs {
    /// Ground-truth bags or folders of bags.
    #[arg(long, required = true, num_args = 1..)]
    pub data: Vec<PathBuf>,
    /// Output folder: REPORT.md, runs/<arch>-<core>, eval/.
    #[arg(short, long, default_value = "report")]
    pub out: PathBuf,
    /// Architectures to train each core in: paper (the paper's Table 1) | grid (P2G -> U-Net
    /// -> G2P with per-particle memory; `mlp` there is the model without memory).
    #[arg(long, value_delimiter = ',', default_value = "paper,grid", value_parser = ["paper", "grid"])]
    pub archs: Vec<String>,
    /// Cores to train and compare.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "mlp,lstm,gru,minlstm,mingru"
    )]
    pub cores: Vec<String>,
    /// Epochs per core (at most; early stopping may end sooner).
    #[arg(long, default_value_t = 30, value_parser = super::flags::at_least_one)]
    pub epochs: usize,
    /// Latent and core width W (the paper: 1250).
    #[arg(long, default_value_t = 1250, value_parser = super::flags::at_least_one)]
    pub width: usize,
    /// Encoder hidden width (the paper: 256).
    #[arg(long, default_value_t = 256, value_parser = super::flags::at_least_one)]
    pub encoder_hidden: usize,
    /// Effective batch size.
    #[arg(long, default_value_t = 16, value_parser = super::flags::at_least_one)]
    pub batch_size: usize,
    /// Windows per forward pass.
    #[arg(long, default_value_t = 16, value_parser = super::flags::at_least_one)]
    pub micro_batch: usize,
    /// Input frames per sample T.
    #[arg(long, default_value_t = 2, value_parser = super::flags::at_least_one)]
    pub window: usize,
    /// Seed of the split, the weights, the data order and dropout.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Early-stopping patience (0: never stop early).
    #[arg(long, default_value_t = 5)]
    pub patience: usize,
    /// Activation after the encoder's last Linear: none | elu (the paper's text).
    #[arg(long, default_value = "none")]
    pub encoder_last_activation: String,
    /// Grid architecture: the network's sizes.
    #[command(flatten)]
    pub grid_net: super::train::args::GridNetArgs,
    /// Grid architecture: samples per epoch at most (0: every window).
    #[arg(long, default_value_t = 0)]
    pub samples_per_epoch: usize,
    /// Grid architecture: minutes of training per core at most (0: no limit).
    #[arg(long, default_value_t = 0.0, value_parser = super::flags::non_negative)]
    pub max_minutes: f64,
    /// Steps per rollout H.
    #[arg(long, default_value_t = 20, value_parser = super::flags::at_least_one)]
    pub horizon: usize,
    /// Rollouts per test trajectory (evenly spaced start frames).
    #[arg(long, default_value_t = 1, value_parser = super::flags::at_least_one)]
    pub starts: usize,
    /// Scenes to evaluate: test | val | train | all.
    #[arg(long, default_value = "test")]
    pub eval_split: String,
    /// Keep runs that already hold a model.json instead of training again.
    #[arg(long)]
    pub reuse: bool,
}

fn path(p: &Path) -> String {
    p.display().to_string()
}

/// One run's training record from its `metrics.csv` and `model.json`.
struct Speed {
    core: String,
    params: usize,
    epochs: usize,
    total_s: f64,
    us_per_sample: f64,
    best_epoch: usize,
    best_val: f64,
}

fn speed(core: &str, dir: &Path) -> anyhow::Result<Speed> {
    let folder = RunFolder::new(dir);
    let csv = folder.metrics_csv();
    let text =
        std::fs::read_to_string(&csv).with_context(|| format!("reading {}", csv.display()))?;
    let (mut epochs, mut total, mut rate) = (0usize, 0.0f64, 0.0f64);
    for line in text.lines().skip(1) {
        let f: Vec<f64> = line.split(',').filter_map(|v| v.parse().ok()).collect();
        if f.len() >= 5 {
            epochs += 1;
            total += f[3];
            rate += f[4];
        }
    }
    let meta = folder.meta()?;
    let params = meta.net.init::<CpuInfer>(&Default::default()).num_params();
    let rate = rate / epochs.max(1) as f64;
    Ok(Speed {
        core: core.to_owned(),
        params,
        epochs,
        total_s: total,
        us_per_sample: if rate > 0.0 { 1e6 / rate } else { f64::NAN },
        best_epoch: meta.epoch,
        best_val: meta.val_loss,
    })
}

/// CPU model name and logical core count.
fn machine() -> (String, usize) {
    let model = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|t| {
            t.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_owned())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    (model, cores)
}

pub fn run(args: ReportArgs) -> anyhow::Result<Outcome> {
    if args.cores.is_empty() {
        bail!("--cores is empty");
    }
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", path(&args.out)))?;
    let runs = args.out.join("runs");
    let mut train_argv = Vec::new();
    let mut dirs = Vec::new();
    let mut names = Vec::new();
    for (arch, core) in args
        .archs
        .iter()
        .flat_map(|a| args.cores.iter().map(move |c| (a.as_str(), c.as_str())))
    {
        let name = run_name(arch, core);
        let dir = runs.join(&name);
        let train = train_args(&args, arch, core, &dir)?;
        let argv = train_flags(&train);
        if args.reuse && RunFolder::new(&dir).model_json().exists() {
            eprintln!("{name}: reusing {}", path(&dir));
        } else {
            eprintln!("== training {name} -> {}", path(&dir));
            let start = Instant::now();
            super::train::run(train).with_context(|| format!("training {name}"))?;
            eprintln!("{name}: trained in {:.1} s", start.elapsed().as_secs_f64());
        }
        train_argv.push(argv);
        dirs.push(dir);
        names.push(name);
    }
    let eval_dir = args.out.join("eval");
    let mut eval_args: EvalArgs = super::flags::defaults(&["--model", "--data"])?;
    eval_args.models = dirs.clone();
    eval_args.data = args.data.clone();
    eval_args.split = args.eval_split.clone();
    eval_args.seed = args.seed;
    eval_args.horizon = super::flags::Horizon::Steps(args.horizon);
    eval_args.starts = args.starts;
    eval_args.out = eval_dir.clone();
    let argv = eval_flags(&eval_args);
    eprintln!("== evaluating {} models", dirs.len());
    let (eval, models, outcome) = direct(&eval_args)?;
    let bar = super::progress(0, "renders");
    output::write_all(&eval_dir, &eval, models, "minflow report: evaluation", &bar)?;
    bar.finish_and_clear();
    let speeds: Vec<Speed> = names
        .iter()
        .zip(&dirs)
        .map(|(c, d)| speed(c, d))
        .collect::<anyhow::Result<_>>()?;
    let text = report_text(&args, &names, &train_argv, &argv, &eval, &speeds);
    let out = args.out.join("REPORT.md");
    std::fs::write(&out, &text).with_context(|| format!("writing {}", path(&out)))?;
    print!("{}", table::markdown(&eval));
    println!("report: {}", path(&out));
    Ok(outcome)
}

/// The run (and column) name of `core` in `arch`: `paper-mingru`, `grid-none` (the grid
/// model's `mlp` is the one without memory).
fn run_name(arch: &str, core: &str) -> String {
    match (arch, core) {
        ("grid", "mlp") => "grid-none".to_owned(),
        _ => format!("{arch}-{core}"),
    }
}

/// The `train` flags of one run: train's defaults, with what the report's flags set.
fn train_args(args: &ReportArgs, arch: &str, core: &str, dir: &Path) -> anyhow::Result<TrainArgs> {
    let mut t: TrainArgs = super::flags::defaults(&["--data", "--out"])?;
    t.data = args.data.clone();
    t.out = dir.to_path_buf();
    t.arch = arch.to_owned();
    t.model = core.to_owned();
    t.epochs = args.epochs;
    t.batch_size = args.batch_size;
    t.window = args.window;
    t.seed = args.seed;
    t.patience = args.patience;
    if arch == "paper" {
        t.width = args.width;
        t.encoder_hidden = args.encoder_hidden;
        t.micro_batch = args.micro_batch;
        t.encoder_last_activation = args.encoder_last_activation.clone();
    } else {
        t.grid_args.samples_per_epoch = args.samples_per_epoch;
        t.grid_args.max_minutes = args.max_minutes;
        t.grid_args.net = args.grid_net.clone();
    }
    Ok(t)
}

/// The `minflow train` command line of a run from [`train_args`] (what REPORT.md prints to
/// reproduce it): the flags the report sets.
fn train_flags(t: &TrainArgs) -> Vec<String> {
    let mut argv = vec!["train".to_owned(), "--data".to_owned()];
    argv.extend(t.data.iter().map(|p| path(p)));
    let mut flags = vec![
        ("--arch", t.arch.clone()),
        ("--model", t.model.clone()),
        ("--out", path(&t.out)),
        ("--epochs", t.epochs.to_string()),
        ("--batch-size", t.batch_size.to_string()),
        ("--window", t.window.to_string()),
        ("--seed", t.seed.to_string()),
        ("--patience", t.patience.to_string()),
    ];
    if t.arch == "paper" {
        flags.extend([
            ("--width", t.width.to_string()),
            ("--encoder-hidden", t.encoder_hidden.to_string()),
            ("--micro-batch", t.micro_batch.to_string()),
            (
                "--encoder-last-activation",
                t.encoder_last_activation.clone(),
            ),
        ]);
    } else {
        let g = &t.grid_args;
        flags.extend([
            ("--samples-per-epoch", g.samples_per_epoch.to_string()),
            ("--max-minutes", g.max_minutes.to_string()),
        ]);
    }
    for (flag, value) in flags {
        argv.extend([flag.to_owned(), value]);
    }
    if t.arch == "grid" {
        argv.extend(t.grid_args.net.argv());
    }
    argv
}

/// The `minflow eval` command line of the report's evaluation (printed in REPORT.md).
fn eval_flags(e: &EvalArgs) -> Vec<String> {
    let mut argv = vec!["eval".to_owned()];
    for dir in &e.models {
        argv.extend(["--model".to_owned(), path(dir)]);
    }
    argv.push("--data".into());
    argv.extend(e.data.iter().map(|p| path(p)));
    for (flag, value) in [
        ("--split", e.split.clone()),
        ("--seed", e.seed.to_string()),
        ("--horizon", e.horizon.to_string()),
        ("--starts", e.starts.to_string()),
        ("--out", path(&e.out)),
    ] {
        argv.extend([flag.to_owned(), value]);
    }
    argv
}

/// Table 4: training speed per run, then the classic/minimal ratios of each architecture.
fn speed_table(speeds: &[Speed]) -> String {
    let mut s = String::from(
        "| core | parameters | epochs | total training s | s / epoch | us / sample | best epoch | best val loss |\n\
         | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |\n",
    );
    for r in speeds {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {:.1} | {:.2} | {:.0} | {} | {:.4e} |",
            r.core,
            r.params,
            r.epochs,
            r.total_s,
            r.total_s / r.epochs.max(1) as f64,
            r.us_per_sample,
            r.best_epoch,
            r.best_val
        );
    }
    let per_epoch = |name: &str| {
        speeds
            .iter()
            .find(|r| r.core == name)
            .map(|r| r.total_s / r.epochs.max(1) as f64)
    };
    for arch in ["paper", "grid"] {
        for (classic, minimal) in [("lstm", "minlstm"), ("gru", "mingru")] {
            let (classic, minimal) = (run_name(arch, classic), run_name(arch, minimal));
            if let (Some(a), Some(b)) = (per_epoch(&classic), per_epoch(&minimal)) {
                let _ = writeln!(s, "\n{classic} / {minimal} time per epoch: {:.2}x", a / b);
            }
        }
    }
    s
}

/// The Markdown of REPORT.md.
fn report_text(
    args: &ReportArgs,
    names: &[String],
    train_argv: &[Vec<String>],
    eval_argv: &[String],
    eval: &Evaluation,
    speeds: &[Speed],
) -> String {
    let mut s = report_header(args, eval);
    s.push_str(&family_tables(eval));
    let _ = writeln!(
        s,
        "## Table 4: training speed\n\nMeasured during the runs above (`metrics.csv`): total \
         training time is the sum of the epochs' training time (validation and checkpoints \
         excluded), s / epoch its mean, us / sample the inverse of the mean training \
         throughput.\n\n{}",
        speed_table(speeds)
    );
    let _ = writeln!(s, "## All scenes, details\n\n{}", table::markdown(eval));
    let _ = writeln!(s, "{}", table::details(eval));
    s.push_str(&figures_and_commands(eval, names, train_argv, eval_argv));
    s
}

/// REPORT.md's title, introduction and machine and configuration section.
fn report_header(args: &ReportArgs, eval: &Evaluation) -> String {
    let (cpu, cores) = machine();
    let mut s = String::from("# minflow report\n\n");
    let _ = writeln!(
        s,
        "The experiment of Dharma et al. (ICCS 2025), \"MinRNNs for Lagrangian-Based \
         Simulations of Transient Flow Problems\", reproduced on `{}`: the cores {} trained \
         in the architecture(s) {} with one configuration, rolled out on the scenes of the \
         `{}` split beside the `persist` and `constvel` baselines, and their training speed \
         measured.\n",
        args.data
            .iter()
            .map(|p| path(p))
            .collect::<Vec<_>>()
            .join(" "),
        args.cores.join(", "),
        args.archs.join(", "),
        args.eval_split
    );
    let _ = writeln!(
        s,
        "## Machine and configuration\n\n- CPU: {cpu}, {cores} logical cores ({} rayon \
         threads); burn ndarray backend (f32), minflow {}\n- seed: {} (split 80:10:10 by \
         scene, weights, data order, dropout)\n- training: epochs {}, batch {}, T {}, patience \
         {}; paper: W {}, encoder hidden {}, final encoder activation {}, micro-batch {}; \
         grid: n {}, U-Net width {}, {} levels, samples per epoch {} (0: all), max minutes {} \
         (0: no limit)\n- evaluation: horizon {}, {} start(s) per trajectory; {}\n",
        rayon::current_num_threads(),
        env!("CARGO_PKG_VERSION"),
        args.seed,
        args.epochs,
        args.batch_size,
        args.window,
        args.patience,
        args.width,
        args.encoder_hidden,
        args.encoder_last_activation,
        args.micro_batch,
        args.grid_net.grid,
        args.grid_net.unet_width,
        args.grid_net.levels,
        args.samples_per_epoch,
        args.max_minutes,
        args.horizon,
        args.starts,
        eval.scaler_source
    );
    if args.eval_split != "test" {
        let _ = writeln!(
            s,
            "**Note:** the evaluated scenes (`--eval-split {}`) are not only held-out test \
             scenes, so the tables below are not a generalisation result.\n",
            args.eval_split
        );
    }
    s
}

/// REPORT.md's Tables 2 and 3 (fluid and multi scenes) and any other scenes.
fn family_tables(eval: &Evaluation) -> String {
    let mut s = String::new();
    let h = eval.horizon;
    let families = [
        ("Table 2: fluid scenes", "fluid/"),
        ("Table 3: multi-material scenes", "multi/"),
    ];
    for (title, prefix) in families {
        let sub = eval.subset(|sc| sc.starts_with(prefix));
        let _ = writeln!(
            s,
            "## {title}\n\nMSE over scaled (x, y, vx, vy): mean over steps 1..{h} (avg{h}) and \
             at step {h} (f{h}); lowest of each row and block in bold.\n"
        );
        if sub.scenes.is_empty() {
            let _ = writeln!(s, "No {prefix} scenes among the evaluated scenes.\n");
        } else {
            let _ = writeln!(s, "{}", table::markdown(&sub));
        }
    }
    let others = eval.subset(|sc| !families.iter().any(|(_, p)| sc.starts_with(p)));
    if !others.scenes.is_empty() {
        let _ = writeln!(s, "## Other scenes\n\n{}", table::markdown(&others));
    }
    s
}

/// REPORT.md's figures, loss-curve links and the commands that reproduce it.
fn figures_and_commands(
    eval: &Evaluation,
    names: &[String],
    train_argv: &[Vec<String>],
    eval_argv: &[String],
) -> String {
    let mut s = String::new();
    s.push_str("## Figures\n\nPer-scene MSE curves (Figures 4, 8, 9):\n\n![MSE curves](eval/mse_curves.png)\n\n");
    s.push_str("Ground truth beside each model (Figures 1, 7; GIF: every step):\n\n");
    for scene in eval.scenes.iter().filter(|sc| sc.snapshots.is_some()) {
        let stem = crate::eval::render::file_stem(&scene.scene);
        let _ = writeln!(
            s,
            "- `{}`: ![{0}](eval/render_{stem}.png) [animation](eval/render_{stem}.gif)",
            scene.scene
        );
    }
    s.push_str("\nTraining loss curves: ");
    let links: Vec<String> = names
        .iter()
        .map(|c| format!("[{c}](runs/{c}/loss.png)"))
        .collect();
    s.push_str(&links.join(", "));
    s.push_str("\n\n## Reproduce\n\n```sh\n");
    for argv in train_argv {
        let _ = writeln!(s, "minflow {}", argv.join(" "));
    }
    let _ = writeln!(s, "minflow {}", eval_argv.join(" "));
    s.push_str("```\n");
    s
}
